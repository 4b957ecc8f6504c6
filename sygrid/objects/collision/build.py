"""A part's collision model: one tier built through the disk cache with its fidelity measured
(``build_collision_model``), and the rule that picks the cheapest tier faithful enough within a piece cap and a
time budget (``select_collision_model``).

"Model no more than a scene needs": a part collides through the cheapest geometry that meets the tolerances. Every
tier is built from, and measured against, the part's repaired solid (``sygrid.objects.collision.solid``): the mesh
itself for a closed part, a closed manifold made from an open, multi-body or non-manifold one.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from sygrid.errors import MeshError
from sygrid.objects.collision.cache import (
    cache_entry,
    load_cached,
    load_timeout,
    resolve_cache_dir,
    save_cached,
    save_timeout,
)
from sygrid.objects.collision.fidelity import measure_fidelity
from sygrid.objects.collision.geometry import CollisionModel, Fidelity
from sygrid.objects.collision.params import DEFAULT_TIER_ORDER, CollisionParams, CollisionTier
from sygrid.objects.collision.solid import repaired_solid, solid_key
from sygrid.objects.collision.tiers import DecompositionTimeoutError, build_tier
from sygrid.objects.model import ObjectModel

log = logging.getLogger(__name__)

COACD_REFINE_FACTOR = 0.4  # the finer CoACD try of select_collision_model: a finer concavity threshold
DEFAULT_MAX_PIECES = 64  # select_collision_model's cap on geoms per part
DEFAULT_TIME_BUDGET_S = 30.0  # select_collision_model's budget per part on first use (repair + tiers + fidelity)
RETRY_AFTER_TIMEOUT_FACTOR = 1.25  # a decomposition that ran out of time is retried only with this much more
_MIN_ATTEMPT_S = 1.0  # a decomposition is not started with less time left than this
# Kept back from a decomposition's time limit: the worker process's start and stop and the fidelity measurement run
# outside the decomposer's own clock but inside the part's budget.
_RESERVE_S = 1.5
_WARNED: set[tuple] = set()  # (content hash, tier, missed tolerances) already warned about in this process


def build_collision_model(
    model: ObjectModel,
    tier: CollisionTier | str,
    params: CollisionParams | None = None,
    cache_dir: Path | str | None = None,
    time_limit_s: float | None = None,
) -> CollisionModel:
    """``model``'s collision model in ``tier``, from the disk cache when it holds one, else built and cached.

    The geometry is built from, and its fidelity measured against, the part's repaired solid (made and cached
    first when the mesh is not one closed volume).

    Args:
        model: the part; its ``content_hash`` keys the cache.
        tier: a ``CollisionTier`` or its name ("hull", "coacd", "vhacd").
        params: tier, repair and measurement knobs (optional; ``CollisionParams()`` when not given).
        cache_dir: folder of the cache (optional). When not given: ``$SYGRID_CACHE_DIR/collision`` if that
            variable is set (read at each call), else ``~/.cache/sygrid/collision``.
        time_limit_s: the most a decomposer (coacd, vhacd) may take (optional; None: no limit, run in this
            process). With a limit it runs in a child process killed at the limit; a run that ran out of time is
            recorded in the cache, and not started again with at most ``RETRY_AFTER_TIMEOUT_FACTOR`` times that
            limit.

    Raises:
        ValueError: ``tier`` is not a tier name (the message lists the valid ones).
        DecompositionTimeoutError: the decomposer ran out of ``time_limit_s`` (now, or before with as much time).
        MeshError: the repair gave no solid, or the decomposer returned no usable piece.
    """
    tier = CollisionTier(tier)
    params = CollisionParams() if params is None else params
    if not isinstance(params, CollisionParams):
        raise ValueError(f"params must be a CollisionParams, got {type(params).__name__}")
    folder = resolve_cache_dir(cache_dir)
    stem, key = cache_entry(folder, model.content_hash, tier, params, solid_key(model.mesh, params))
    cached = load_cached(stem, key, tier, model.content_hash, params)
    if cached is not None:
        log.debug("collision cache hit for %s (%s): %s", model.name, tier.value, stem)
        return cached
    limit = None if tier is CollisionTier.HULL else time_limit_s
    if limit is not None:
        ran_out = load_timeout(stem, key)
        if ran_out is not None and limit <= ran_out * RETRY_AFTER_TIMEOUT_FACTOR:
            raise DecompositionTimeoutError(
                f"{model.name}: {tier.value} ran out of {ran_out:.1f} s before (cached); not retried with "
                f"{limit:.1f} s", ran_out,
            )  # fmt: skip

    solid = repaired_solid(model.mesh, model.content_hash, params, folder, model.name).mesh
    log.info("%s: building its %s collision model%s", model.name, tier.value,
             f" (at most {limit:.0f} s)" if limit is not None else "")  # fmt: skip
    start = time.perf_counter()
    try:
        pieces, primitives = build_tier(solid, tier, params, limit)
    except DecompositionTimeoutError as exc:
        save_timeout(stem, key, exc.limit_s)
        raise DecompositionTimeoutError(f"{model.name}: {exc}", exc.limit_s) from exc
    compute_s = time.perf_counter() - start
    if not pieces and not primitives:
        raise MeshError(
            f"{model.name}: the {tier.value} decomposition gave no usable convex piece (all flat or slivers); "
            "expected a watertight mesh with volume. Try another tier or finer parameters."
        )
    start = time.perf_counter()
    fidelity = measure_fidelity(solid, pieces, primitives, params.fidelity_samples, params.fidelity_seed, model.name)
    fidelity_s = time.perf_counter() - start
    result = CollisionModel(
        tier=tier,
        pieces=pieces,
        primitives=primitives,
        fidelity=fidelity,
        compute_s=compute_s,
        fidelity_s=fidelity_s,
        content_hash=model.content_hash,
        params=params,
    )
    log.info(
        "%s: %s collision model in %.2f s (fidelity %.2f s): excess %.3f, missed %.3f, concavity kept %.2f",
        model.name, result.description, compute_s, fidelity_s, fidelity.excess_volume_ratio,
        fidelity.missed_volume_ratio, fidelity.concavity_kept,
    )  # fmt: skip
    save_cached(stem, key, result)
    return result


def select_collision_model(
    model: ObjectModel,
    max_excess_volume_ratio: float = 0.05,
    min_concavity_kept: float = 0.5,
    max_missed_volume_ratio: float = 0.05,
    ignore_concavity_below_ratio: float = 0.02,
    tiers: Sequence[CollisionTier | str] = DEFAULT_TIER_ORDER,
    params: CollisionParams | None = None,
    cache_dir: Path | str | None = None,
    max_pieces: int = DEFAULT_MAX_PIECES,
    time_budget_s: float | None = DEFAULT_TIME_BUDGET_S,
) -> CollisionModel:
    """The cheapest collision model of ``model`` that meets the tolerances, within ``max_pieces`` and
    ``time_budget_s``.

    Tiers are tried in the order given, by default cheapest first: hull (1 geom), coacd, vhacd; cost is the number
    of pieces, then the compute time. A tier is only built when the cheaper ones failed; coacd is tried twice, the
    second time with its concavity threshold times ``COACD_REFINE_FACTOR`` (finer, more pieces). If none meets the
    tolerances, the one that misses them by the least (summed relative shortfall; ties to the cheaper) is returned
    and a warning names each missed tolerance and by how much.

    The time budget counts the repair of the solid and each try at its first-use cost (a cached try counts the
    time it took when it was built, so the same tries are made, and the same model chosen, in every later
    process on this machine). A decomposition gets the time left and is stopped at it; no try starts with less
    than a second left. When the budget runs out the best model built so far is taken, at worst the hull (one
    convex geom or primitive: the cheapest tier, and it keeps piles stable). Each stage is logged (INFO).

    Defaults:
        max_excess_volume_ratio=0.05: at most 5 % extra material. A box-like or cylindrical part stays a
            primitive; a part with a hole (a washer, a nut) goes to a decomposition, since its hull fills the hole.
        min_concavity_kept=0.5: at least half of the holes and inside corners stay free.
        max_missed_volume_ratio=0.05: at most 5 % of the part uncovered (a decomposition can shave surfaces).
        ignore_concavity_below_ratio=0.02: ``min_concavity_kept`` is not checked when the concave space is under
            2 % of the part's volume (a fillet, a shallow engraving): there is nothing worth keeping.
        max_pieces=64: a model with more pieces (geoms per instance) misses the tolerances.
        time_budget_s=30: per part, on first use; None: no budget (decomposers run in this process).

    Raises:
        ValueError: a tolerance, ``max_pieces`` or ``time_budget_s`` is out of range, or a tier name is unknown.
    """
    for name, value in {
        "max_excess_volume_ratio": max_excess_volume_ratio,
        "min_concavity_kept": min_concavity_kept,
        "max_missed_volume_ratio": max_missed_volume_ratio,
        "ignore_concavity_below_ratio": ignore_concavity_below_ratio,
    }.items():
        if not 0.0 <= value <= (1.0 if name == "min_concavity_kept" else float("inf")):
            raise ValueError(f"{name} must be >= 0 (and <= 1 for a fraction), got {value!r}")
    if isinstance(max_pieces, bool) or not isinstance(max_pieces, int) or max_pieces < 1:
        raise ValueError(f"max_pieces must be an integer >= 1, got {max_pieces!r}")
    if time_budget_s is not None and not time_budget_s > 0:
        raise ValueError(f"time_budget_s must be > 0 seconds or None, got {time_budget_s!r}")
    order = [CollisionTier(t) for t in tiers]
    if not order:
        raise ValueError(f"tiers must name at least one tier; valid tiers: {', '.join(t.value for t in CollisionTier)}")

    def shortfalls(fid: Fidelity) -> dict[str, tuple[float, float]]:
        """Missed tolerance name -> (measured, limit)."""
        missed: dict[str, tuple[float, float]] = {}
        if fid.excess_volume_ratio > max_excess_volume_ratio:
            missed["max_excess_volume_ratio"] = (fid.excess_volume_ratio, max_excess_volume_ratio)
        if fid.missed_volume_ratio > max_missed_volume_ratio:
            missed["max_missed_volume_ratio"] = (fid.missed_volume_ratio, max_missed_volume_ratio)
        concavity_matters = fid.concave_volume_ratio >= ignore_concavity_below_ratio
        if concavity_matters and fid.concavity_kept < min_concavity_kept:
            missed["min_concavity_kept"] = (fid.concavity_kept, min_concavity_kept)
        if fid.n_pieces > max_pieces:
            missed["max_pieces"] = (float(fid.n_pieces), float(max_pieces))
        return missed

    base = params or CollisionParams()
    # the budget's clock: first-use seconds, the repair's first
    spent = repaired_solid(model.mesh, model.content_hash, base, cache_dir, model.name).compute_s
    tried: list[tuple[CollisionModel, dict[str, tuple[float, float]]]] = []
    for tier in order:
        # CoACD gets a second, finer try before the next tier: a lower concavity threshold keeps more detail
        # for a few more pieces.
        attempts = [base]
        if tier is CollisionTier.COACD:
            finer = base.coacd_concavity_threshold * COACD_REFINE_FACTOR
            attempts.append(replace(base, coacd_concavity_threshold=finer))
        for attempt in attempts:
            left = None if time_budget_s is None else time_budget_s - spent - _RESERVE_S
            if left is not None and left < _MIN_ATTEMPT_S and tier is not CollisionTier.HULL:
                log.info("%s: the %.0f s collision time budget is spent; %s not tried", model.name, time_budget_s,
                         tier.value)  # fmt: skip
                continue
            try:
                candidate = build_collision_model(model, tier, attempt, cache_dir, left)
            except DecompositionTimeoutError as exc:
                log.info("%s: %s", model.name, exc)
                spent += exc.limit_s
                continue
            spent += candidate.compute_s + candidate.fidelity_s
            missed = shortfalls(candidate.fidelity)
            if not missed:
                log.debug("%s: %s meets the collision tolerances", model.name, candidate.description)
                return candidate
            tried.append((candidate, missed))
    if not tried:  # every try ran out of time: the hull, the cheapest tier, keeps piles stable
        candidate = build_collision_model(model, CollisionTier.HULL, base, cache_dir)
        tried.append((candidate, shortfalls(candidate.fidelity)))

    def badness(item: tuple[CollisionModel, dict[str, tuple[float, float]]]) -> tuple[bool, float, int, float]:
        cand, missed = item
        relative = sum(abs(value - limit) / max(limit, 1e-9) for value, limit in missed.values())
        return ("max_pieces" in missed, relative, cand.n_pieces, cand.compute_s)

    best, missed = min(tried, key=badness)
    warning_key = (model.content_hash, best.tier, tuple(missed))
    if warning_key in _WARNED:  # once per part and outcome per process, not at every drop
        return best
    _WARNED.add(warning_key)
    log.warning(
        "%s: no collision tier of %s meets the tolerances%s; using %s, which misses %s",
        model.name,
        [t.value for t in order],
        f" within {time_budget_s:g} s" if time_budget_s is not None else "",
        best.description,
        "; ".join(f"{name}={limit:g} (measured {value:.3f}, off by {abs(value - limit):.3f})"
                  for name, (value, limit) in missed.items()),
    )  # fmt: skip
    return best
