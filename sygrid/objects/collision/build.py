"""A part's collision model: one tier built through the disk cache with its fidelity measured
(``build_collision_model``), and the rule that picks the cheapest tier faithful enough (``select_collision_model``).

"Model no more than a scene needs": a part collides through the cheapest geometry that meets the tolerances.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from sygrid.errors import MeshError
from sygrid.objects.collision.cache import cache_entry, load_cached, resolve_cache_dir, save_cached
from sygrid.objects.collision.fidelity import measure_fidelity
from sygrid.objects.collision.geometry import CollisionModel, Fidelity
from sygrid.objects.collision.params import DEFAULT_TIER_ORDER, CollisionParams, CollisionTier
from sygrid.objects.collision.tiers import build_tier
from sygrid.objects.model import ObjectModel

log = logging.getLogger(__name__)

COACD_REFINE_FACTOR = 0.4  # the finer CoACD try of select_collision_model: a finer concavity threshold
_WARNED: set[tuple] = set()  # (content hash, tier, missed tolerances) already warned about in this process


def build_collision_model(
    model: ObjectModel,
    tier: CollisionTier | str,
    params: CollisionParams | None = None,
    cache_dir: Path | str | None = None,
) -> CollisionModel:
    """``model``'s collision model in ``tier``, from the disk cache when it holds one, else built and cached.

    Args:
        model: the part; its ``content_hash`` keys the cache.
        tier: a ``CollisionTier`` or its name ("hull", "coacd", "vhacd").
        params: tier and measurement knobs (optional; ``CollisionParams()`` when not given).
        cache_dir: folder of the cache (optional). When not given: ``$SYGRID_CACHE_DIR/collision`` if that
            variable is set (read at each call), else ``~/.cache/sygrid/collision``.

    Raises:
        ValueError: ``tier`` is not a tier name (the message lists the valid ones).
        MeshError: the mesh has no inside, or the decomposer returned no usable piece.
    """
    tier = CollisionTier(tier)
    params = CollisionParams() if params is None else params
    if not isinstance(params, CollisionParams):
        raise ValueError(f"params must be a CollisionParams, got {type(params).__name__}")
    stem, key = cache_entry(resolve_cache_dir(cache_dir), model.content_hash, tier, params)
    cached = load_cached(stem, key, tier, model.content_hash, params)
    if cached is not None:
        log.debug("collision cache hit for %s (%s): %s", model.name, tier.value, stem)
        return cached

    if not model.mesh.is_watertight:
        log.warning(
            "%s: the mesh is not watertight; its inside is ill-defined, so the fidelity numbers are approximate",
            model.name,
        )
    start = time.perf_counter()
    pieces, primitives = build_tier(model.mesh, tier, params)
    compute_s = time.perf_counter() - start
    if not pieces and not primitives:
        raise MeshError(
            f"{model.name}: the {tier.value} decomposition gave no usable convex piece (all flat or slivers); "
            "expected a watertight mesh with volume. Try another tier or finer parameters."
        )
    start = time.perf_counter()
    fidelity = measure_fidelity(
        model.mesh, pieces, primitives, params.fidelity_samples, params.fidelity_seed, name=model.name
    )
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
) -> CollisionModel:
    """The cheapest collision model of ``model`` that meets the tolerances.

    Tiers are tried in the order given, by default cheapest first: hull (1 geom), coacd, vhacd; cost is the number
    of pieces, then the compute time. A tier is only built when the cheaper ones failed; coacd is tried twice, the
    second time with its concavity threshold times ``COACD_REFINE_FACTOR`` (finer, more pieces). If none meets the
    tolerances, the one that misses them by the least (summed relative shortfall; ties to the cheaper) is returned
    and a warning names each missed tolerance and by how much.

    Defaults:
        max_excess_volume_ratio=0.05: at most 5 % extra material. A box-like or cylindrical part stays a
            primitive; a part with a hole (a washer, a nut) goes to a decomposition, since its hull fills the hole.
        min_concavity_kept=0.5: at least half of the holes and inside corners stay free.
        max_missed_volume_ratio=0.05: at most 5 % of the part uncovered (a decomposition can shave surfaces).
        ignore_concavity_below_ratio=0.02: ``min_concavity_kept`` is not checked when the concave space is under
            2 % of the part's volume (a fillet, a shallow engraving): there is nothing worth keeping.

    Raises:
        ValueError: a tolerance is out of range, or a tier name is unknown.
    """
    for name, value in {
        "max_excess_volume_ratio": max_excess_volume_ratio,
        "min_concavity_kept": min_concavity_kept,
        "max_missed_volume_ratio": max_missed_volume_ratio,
        "ignore_concavity_below_ratio": ignore_concavity_below_ratio,
    }.items():
        if not 0.0 <= value <= (1.0 if name == "min_concavity_kept" else float("inf")):
            raise ValueError(f"{name} must be >= 0 (and <= 1 for a fraction), got {value!r}")
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
        return missed

    base = params or CollisionParams()
    tried: list[tuple[CollisionModel, dict[str, tuple[float, float]]]] = []
    for tier in order:
        # CoACD gets a second, finer try before the next tier: a lower concavity threshold keeps more detail
        # for a few more pieces.
        attempts = [base]
        if tier is CollisionTier.COACD:
            finer = base.coacd_concavity_threshold * COACD_REFINE_FACTOR
            attempts.append(replace(base, coacd_concavity_threshold=finer))
        for attempt in attempts:
            candidate = build_collision_model(model, tier, attempt, cache_dir)
            missed = shortfalls(candidate.fidelity)
            if not missed:
                log.debug("%s: %s meets the collision tolerances", model.name, candidate.description)
                return candidate
            tried.append((candidate, missed))

    def badness(item: tuple[CollisionModel, dict[str, tuple[float, float]]]) -> tuple[float, int, float]:
        cand, missed = item
        relative = sum(abs(value - limit) / max(limit, 1e-9) for value, limit in missed.values())
        return (relative, cand.n_pieces, cand.compute_s)

    best, missed = min(tried, key=badness)
    warning_key = (model.content_hash, best.tier, tuple(missed))
    if warning_key in _WARNED:  # once per part and outcome per process, not at every drop
        return best
    _WARNED.add(warning_key)
    log.warning(
        "%s: no collision tier of %s meets the tolerances; using %s, which misses %s",
        model.name,
        [t.value for t in order],
        best.description,
        "; ".join(f"{name}={limit:g} (measured {value:.3f}, off by {abs(value - limit):.3f})"
                  for name, (value, limit) in missed.items()),
    )  # fmt: skip
    return best
