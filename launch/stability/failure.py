"""Where a method fails along an axis: its curve (successes over trials per point, seeds pooled) and the failure
point, with an uncertainty from the per-point sample counts. Pure functions.

The criterion (``Criterion``): a method fails at a point whose value is below ``threshold = max(fraction * best,
floor)``, ``best`` its highest value over the axis's points. Points are in order of increasing difficulty; the
failure point is the first crossing: between the last point at or above the threshold and the first below it, by
linear interpolation of the value in the axis's coordinate ``x``. A categorical axis (no ``x``, no order of
difficulty) names the points below instead (``"fails"`` when any is).

Uncertainty (the delta method): each point's value is a binomial proportion with standard error
``sqrt(p (1 - p) / n)``, ``p`` kept within ``[0.5 / n, 1 - 0.5 / n]`` so that a perfect or null score of a finite
sample still has one; the two neighbouring points' errors are propagated to the interpolated crossing, the threshold
taken as exact. The crossing's standard error ``sigma_x`` is in the axis's unit; it can exceed the distance
between the two points where they barely differ.

Outcomes (``status``): ``"holds"`` (never below the threshold: the failure point lies beyond the hardest point),
``"fails"`` (a crossing), ``"below_from_start"`` (already below at the easiest point: the threshold is the floor
and the best is under it), ``"no_data"`` (no point with trials).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

HOLDS, FAILS, BELOW_FROM_START, NO_DATA = "holds", "fails", "below_from_start", "no_data"


@dataclass(frozen=True)
class Criterion:
    """A method fails below ``max(fraction * best, floor)`` (fractions of 1, as the metric)."""

    fraction: float = 0.8
    floor: float = 0.5

    def threshold(self, best: float) -> float:
        return max(self.fraction * best, self.floor)

    def to_json(self) -> dict:
        return {"fraction": self.fraction, "floor": self.floor}


@dataclass(frozen=True)
class CurvePoint:
    """One point of a method's curve: ``k`` successes of ``n`` trials (seeds pooled) at ``x`` (None: categorical)."""

    label: str
    x: float | None
    k: int
    n: int

    @property
    def value(self) -> float:
        return self.k / self.n if self.n else math.nan

    @property
    def se(self) -> float:
        return binomial_se(self.k, self.n)

    def to_json(self) -> dict:
        return {"label": self.label, "x": self.x, "k": self.k, "n": self.n, "value": _num(self.value),
                "se": _num(self.se)}  # fmt: skip


def binomial_se(k: int, n: int) -> float:
    """Standard error of the proportion ``k / n`` (NaN without trials), ``p`` clamped to ``[0.5/n, 1 - 0.5/n]``."""
    if n <= 0:
        return math.nan
    p = min(max(k / n, 0.5 / n), 1.0 - 0.5 / n)
    return math.sqrt(p * (1.0 - p) / n)


def failure_point(curve: Sequence[CurvePoint], criterion: Criterion) -> dict:
    """The failure point of one curve (points in order of increasing difficulty; those without trials skipped):
    ``{"status", "x", "sigma_x", "label", "between", "best", "threshold", "below", "last_measured"}``, see the module
    docstring. ``x`` is the crossing (``"fails"``), the easiest point's ``x`` (``"below_from_start"``), or None;
    ``label`` the first point below (None when it holds); ``between`` the labels of the two points around the
    crossing; ``below`` every point below the threshold (a curve may come back above it); ``last_measured`` the
    hardest point with trials."""
    points = [p for p in curve if p.n > 0]
    if not points:
        return {**_result(NO_DATA, None, None, None, None, math.nan, math.nan), "below": [], "last_measured": None}
    best = max(p.value for p in points)
    threshold = criterion.threshold(best)
    below = next((i for i, p in enumerate(points) if p.value < threshold), None)
    if below is None:
        out = _result(HOLDS, None, None, None, None, best, threshold)
    elif points[below].x is None:  # categorical: no order of difficulty to cross
        out = _result(FAILS, None, None, points[below].label, None, best, threshold)
    elif below == 0:
        p = points[0]
        out = _result(BELOW_FROM_START, p.x, None, p.label, None, best, threshold)
    else:
        a, b = points[below - 1], points[below]
        x, sigma = crossing(a.x, a.value, a.se, b.x, b.value, b.se, threshold)
        out = _result(FAILS, x, sigma, b.label, (a.label, b.label), best, threshold)
    below_all = [p.label for p in points if p.value < threshold]
    return {**out, "below": below_all, "last_measured": points[-1].label}


def crossing(x0: float, v0: float, se0: float, x1: float, v1: float, se1: float, threshold: float) -> tuple:
    """``(x, sigma_x)``: where the line through ``(x0, v0)`` and ``(x1, v1)`` (``v0 >= threshold > v1``) meets the
    threshold, and its standard error from ``se0`` and ``se1`` (delta method, independent points)."""
    drop = v0 - v1
    t = (v0 - threshold) / drop
    dt_dv0 = (threshold - v1) / drop**2
    dt_dv1 = (v0 - threshold) / drop**2
    sigma_t = math.hypot(dt_dv0 * se0, dt_dv1 * se1)
    return x0 + t * (x1 - x0), abs(x1 - x0) * sigma_t


def _result(status, x, sigma, label, between, best, threshold) -> dict:
    return {
        "status": status, "x": _num(x), "sigma_x": _num(sigma), "label": label,
        "between": list(between) if between else None, "best": _num(best), "threshold": _num(threshold),
    }  # fmt: skip


def _num(x: float | None) -> float | None:
    """JSON-safe: None for a missing or non-finite number."""
    return None if x is None or not math.isfinite(x) else float(x)
