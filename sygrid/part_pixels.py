"""Pixels per part: how many network input pixels a part spans at a camera distance, and whether the detector resolves
it; with a message that says what to change when it does not.

A part's nominal size is ``fx * diameter / z`` image pixels (its largest extent facing a pinhole camera of focal
length ``fx`` pixels at distance ``z``) times the detector's scale (network input pixels per image pixel: the whole
frame letterboxed into the model's input, or the ``scale`` the detector is given). The detector resolves a part when
the nominal size at the far end of the working distance is at least its ``min_part_px``: the smallest nominal size
from which its measured recall stays reliable (``sygrid.detection_breakdown.min_reliable_px``, written into a model
folder's manifest as ``detector.min_part_px`` by ``sygrid models pack``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass


@dataclass(frozen=True)
class PartPixels:
    """One part's check: nominal size in image and network pixels at ``distance_m``, against ``min_px``."""

    name: str
    diameter_m: float
    distance_m: float
    image_px: float
    input_px: float
    min_px: float

    @property
    def ok(self) -> bool:
        return self.input_px >= self.min_px


def nominal_px(diameter_m: float, fx_px: float, distance_m: float, scale: float = 1.0) -> float:
    """``fx * diameter / distance * scale``: a part's nominal size (image pixels with ``scale`` 1, network pixels with
    the detector's scale).

    Raises:
        ValueError: a non-positive diameter, focal length, distance or scale.
    """
    for name, value in (("diameter_m", diameter_m), ("fx_px", fx_px), ("distance_m", distance_m), ("scale", scale)):
        if not value > 0:
            raise ValueError(f"{name}: expected > 0, got {value}")
    return fx_px * diameter_m / distance_m * scale


def check_parts(
    diameters_m: Mapping[str, float], fx_px: float, far_distance_m: float, scale: float, min_px: float
) -> list[PartPixels]:
    """Each part (name -> diameter) at the far end of the working distance, smallest first."""
    checks = [
        PartPixels(name, d, far_distance_m, nominal_px(d, fx_px, far_distance_m),
                   nominal_px(d, fx_px, far_distance_m, scale), float(min_px))
        for name, d in diameters_m.items()
    ]  # fmt: skip
    return sorted(checks, key=lambda c: c.input_px)


def advice(check: PartPixels, fx_px: float, scale: float) -> str:
    """What to change so that ``check``'s part reaches ``min_px``: a closer camera, a larger detector scale (a crop of
    the bin seen larger), or a higher resolution (a longer focal length in pixels)."""
    closer_m = fx_px * check.diameter_m * scale / check.min_px
    need_scale = math.ceil(100 * check.min_px * check.distance_m / (fx_px * check.diameter_m)) / 100
    need_fx = check.min_px * check.distance_m / (check.diameter_m * scale)
    return (
        f"{check.name} spans {check.input_px:.1f} network px ({check.image_px:.1f} image px) at "
        f"{check.distance_m:.2f} m, below the {check.min_px:g} px the detector resolves reliably: bring the camera "
        f"within {closer_m:.2f} m of the bin's floor, or run the detector on the bin's crop at scale >= "
        f"{need_scale:.2f} (now {scale:.2f}; manifest detector.scale, for a detector trained to see parts at that "
        f"scale), or use a higher camera resolution (fx >= {need_fx:.0f} px, now {fx_px:.0f} px)"
    )


def part_warnings(
    diameters_m: Mapping[str, float], fx_px: float, far_distance_m: float, scale: float, min_px: float | None
) -> list[str]:
    """One message (``advice``) per part below ``min_px``; none when ``min_px`` is None (the model states none)."""
    if min_px is None:
        return []
    return [advice(c, fx_px, scale) for c in check_parts(diameters_m, fx_px, far_distance_m, scale, min_px) if not c.ok]
