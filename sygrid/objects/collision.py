"""Collision models in three tiers, each with a measured fidelity, and the rule that picks the cheapest good one.

"Model no more than a scene needs": a part collides through the cheapest geometry that is faithful enough.

Tiers, cheapest first:

- ``hull``: one geom. A fitted primitive (box or cylinder, exact for MuJoCo's collision code) when its volume is
  within ``CollisionParams.primitive_max_excess_ratio`` of the mesh's convex hull, else the convex hull itself.
  Fills every hole and inside corner.
- ``coacd``: approximate convex decomposition with CoACD (the default decomposer): convex pieces that keep holes
  and inside corners; 2-35 pieces in 0.3-7 s for the built-in parts on a 2-core machine.
- ``vhacd``: V-HACD (through ``vhacdx``), the SyGRID paper's method: voxel based, up to 32 pieces in 0.6-2.5 s;
  it shaves thin walls (up to 9 % of the part missed).

Each ``CollisionModel`` carries a ``Fidelity`` measured against the true mesh by seeded Monte-Carlo points (see
``Fidelity``), and is cached on disk by (mesh content hash, tier, parameters), so each decomposition is computed
once per machine. ``select_collision_model`` walks the tiers cheapest first and returns the first one that meets
the tolerances.

This module is MuJoCo-free: ``CollisionModel.to_mujoco_geoms()`` gives plain arrays (mesh vertices per piece, or
primitive type, size and pose) that the physics module adds to an ``MjSpec``.
"""

from __future__ import annotations

import enum
import hashlib
import importlib.metadata
import io
import json
import logging
import os
import time
import zipfile
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields, replace
from functools import cache
from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError
from scipy.spatial.transform import Rotation

from sygrid.errors import MeshError
from sygrid.fileio import write_bytes_atomic, write_json_atomic
from sygrid.objects.inside import points_in_convex, points_in_mesh
from sygrid.objects.model import ObjectModel

log = logging.getLogger(__name__)

_CACHE_FORMAT = "sygrid-collision/1"
_CACHE_ENV = "SYGRID_CACHE_DIR"  # a root shared by SyGRID caches; collision models go to its "collision" folder
_MIN_PIECE_VOLUME_RATIO = 1e-6  # pieces smaller than this fraction of the hull's volume are slivers: dropped
_WARNED: set[tuple] = set()  # (content hash, tier, missed tolerances) already warned about in this process
_COACD_REFINE_FACTOR = 0.4  # the finer CoACD try of select_collision_model: threshold 0.05 -> 0.02
_MIN_CONCAVE_SAMPLES = 20  # fewer Monte-Carlo samples than this in the concave space: nothing to keep


class CollisionTier(str, enum.Enum):
    """How a part collides, cheapest first. The value is the name used in scene files and cache keys."""

    HULL = "hull"
    COACD = "coacd"
    VHACD = "vhacd"

    @classmethod
    def _missing_(cls, value: object) -> CollisionTier:
        if isinstance(value, str):
            for tier in cls:
                if tier.value == value.strip().lower():
                    return tier
        raise ValueError(f"unknown collision tier {value!r}; valid tiers: {', '.join(t.value for t in cls)}")

    def __str__(self) -> str:
        return self.value


DEFAULT_TIER_ORDER: tuple[CollisionTier, ...] = (CollisionTier.HULL, CollisionTier.COACD, CollisionTier.VHACD)


@dataclass(frozen=True)
class CollisionParams:
    """Knobs of the three tiers and of the fidelity measurement. Defaults suit small parts (1-10 cm).

    Hull tier:
        primitive_max_excess_ratio: a fitted box or cylinder replaces the convex hull when its volume exceeds the
            hull's by at most this fraction (a 32-segment cylinder mesh is 0.6 % smaller than its true cylinder).
    CoACD (Wei et al. 2022; parameter names of ``coacd.run_coacd``):
        coacd_concavity_threshold: the concavity (a distance relative to the part's size) below which a piece is
            not cut further; 0.01 is very fine, 1.0 coarse. 0.05 keeps the excess volume of the built-in parts
            under 5 % except the long thin-walled pipe (12 %); 0.1 halves the pieces but doubles the excess.
        coacd_max_hulls: at most this many pieces after merging (-1: no limit). Merging does not shorten the search.
        coacd_remesh: when CoACD voxel-remeshes the input first: "if_not_watertight" (meshes that trimesh finds
            not to be a watertight volume; CoACD's own check also rejects sound meshes with sliver triangles,
            e.g. the chamfered nut, and its remesh inflates small parts by about 2 %), "always" or "never".
        coacd_preprocess_resolution: voxel resolution of that remesh.
        coacd_mcts_iterations, coacd_mcts_nodes, coacd_mcts_max_depth: the Monte-Carlo tree search budget for the
            cutting planes. The defaults here are well under CoACD's own (150, 20, 3): about 2.5x faster with the
            same holes kept.
        coacd_pca: cut in the part's principal-axis frame. CoACD only tries axis-aligned cutting planes; without
            this the flange (holes at 45 degrees) takes 4-5 minutes and 190 pieces instead of 15 s and 24 pieces.
        coacd_seed: CoACD's random seed.
    V-HACD (parameter names of ``vhacdx.compute_vhacd``):
        vhacd_voxel_resolution: number of voxels of the part's bounding box.
        vhacd_max_hulls: at most this many pieces.
        vhacd_max_vertices_per_hull: vertices per piece.
        vhacd_min_volume_error_percent: stop splitting a piece when its hull is within this percent of its volume.
        vhacd_max_recursion_depth: splitting depth.
    Fidelity measurement:
        fidelity_samples: Monte-Carlo points (20 000 give about 0.5 % standard error on the volume ratios of a nut).
        fidelity_seed: seed of those points; the same seed gives the same numbers.
    """

    primitive_max_excess_ratio: float = 0.03
    coacd_concavity_threshold: float = 0.05
    coacd_max_hulls: int = -1
    coacd_remesh: Literal["if_not_watertight", "always", "never"] = "if_not_watertight"
    coacd_preprocess_resolution: int = 50
    coacd_mcts_iterations: int = 60
    coacd_mcts_nodes: int = 10
    coacd_mcts_max_depth: int = 2
    coacd_pca: bool = True
    coacd_seed: int = 0
    vhacd_voxel_resolution: int = 100_000
    vhacd_max_hulls: int = 32
    vhacd_max_vertices_per_hull: int = 64
    vhacd_min_volume_error_percent: float = 1.0
    vhacd_max_recursion_depth: int = 10
    fidelity_samples: int = 20_000
    fidelity_seed: int = 0

    def __post_init__(self) -> None:
        checks = {
            "primitive_max_excess_ratio": (0.0 <= self.primitive_max_excess_ratio <= 1.0, "in [0, 1]"),
            "coacd_concavity_threshold": (0.0 < self.coacd_concavity_threshold <= 1.0, "in (0, 1]"),
            "coacd_max_hulls": (self.coacd_max_hulls == -1 or self.coacd_max_hulls >= 1, "-1 or >= 1"),
            "coacd_remesh": (
                self.coacd_remesh in ("if_not_watertight", "always", "never"),
                "one of 'if_not_watertight', 'always', 'never'",
            ),
            "coacd_preprocess_resolution": (self.coacd_preprocess_resolution >= 10, ">= 10"),
            "coacd_mcts_iterations": (self.coacd_mcts_iterations >= 1, ">= 1"),
            "coacd_mcts_nodes": (self.coacd_mcts_nodes >= 1, ">= 1"),
            "coacd_mcts_max_depth": (self.coacd_mcts_max_depth >= 1, ">= 1"),
            "vhacd_voxel_resolution": (self.vhacd_voxel_resolution >= 10_000, ">= 10000"),
            "vhacd_max_hulls": (self.vhacd_max_hulls >= 1, ">= 1"),
            "vhacd_max_vertices_per_hull": (self.vhacd_max_vertices_per_hull >= 4, ">= 4"),
            "vhacd_min_volume_error_percent": (0.0 < self.vhacd_min_volume_error_percent <= 100.0, "in (0, 100]"),
            "vhacd_max_recursion_depth": (self.vhacd_max_recursion_depth >= 1, ">= 1"),
            "fidelity_samples": (self.fidelity_samples >= 1000, ">= 1000"),
        }
        for name, (ok, expected) in checks.items():
            if not ok:
                raise ValueError(f"CollisionParams.{name} must be {expected}, got {getattr(self, name)!r}")

    def key_fields(self, tier: CollisionTier) -> dict:
        """The fields that change ``tier``'s result: the cache key does not change with another tier's knobs."""
        prefix = {CollisionTier.HULL: "primitive_", CollisionTier.COACD: "coacd_", CollisionTier.VHACD: "vhacd_"}
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name.startswith((prefix[tier], "fidelity_"))}


class ConvexPiece(NamedTuple):
    """One convex piece: ``vertices`` (n, 3) float64 metres in the object frame, ``faces`` (m, 3) int64, a closed
    triangle mesh with outward normals (counter-clockwise seen from outside)."""

    vertices: np.ndarray
    faces: np.ndarray


@dataclass(frozen=True, eq=False)
class PrimitiveGeom:
    """A box or cylinder at ``T_obj_geom`` (4x4, the geom frame in the object frame).

    ``size_m`` follows MuJoCo's geom ``size``: a box's half-extents along the geom's x, y, z; a cylinder's
    (radius, half-length), its axis along the geom's z.
    """

    kind: Literal["box", "cylinder"]
    size_m: tuple[float, ...]
    T_obj_geom: np.ndarray

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(n,) bool: which ``points`` (n, 3, object frame) lie inside."""
        T_geom_obj = np.linalg.inv(self.T_obj_geom)
        p = points @ T_geom_obj[:3, :3].T + T_geom_obj[:3, 3]
        if self.kind == "box":
            return np.all(np.abs(p) <= np.asarray(self.size_m), axis=1)
        radius, half = self.size_m
        return (p[:, 0] ** 2 + p[:, 1] ** 2 <= radius**2) & (np.abs(p[:, 2]) <= half)

    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned bounds in the object frame (for a cylinder, of its bounding box)."""
        half = np.asarray(self.size_m) if self.kind == "box" else np.array([self.size_m[0]] * 2 + [self.size_m[1]])
        corners = np.array(np.meshgrid(*[[-h, h] for h in half], indexing="ij")).reshape(3, -1).T
        world = corners @ self.T_obj_geom[:3, :3].T + self.T_obj_geom[:3, 3]
        return np.stack([world.min(0), world.max(0)])

    @property
    def volume_m3(self) -> float:
        if self.kind == "box":
            return float(8.0 * np.prod(self.size_m))
        return float(np.pi * self.size_m[0] ** 2 * 2.0 * self.size_m[1])


@dataclass(frozen=True)
class Fidelity:
    """How well a collision model C matches the true mesh M, from seeded Monte-Carlo points.

    Points are drawn uniformly in the axis-aligned box around M and C together; each volume is the fraction of
    points inside it times the box volume, so each ratio below is a ratio of point counts. With the default 20 000
    points the standard error of each ratio is about 0.5 % for a nut-sized part.

    excess_volume_ratio: volume inside C but outside M, over M's volume. What the model adds: filled holes, filled
        inside corners, the corners of a box around a round part. Parts collide early by this much material.
    missed_volume_ratio: volume inside M but outside C, over M's volume. What the model lacks: parts can
        interpenetrate there. A hull or a fitted primitive encloses M, so it misses nothing.
    concavity_kept: of the concave space (inside M's convex hull but outside M: holes, slots, gaps between gear
        teeth, inside corners), the fraction that C leaves free. 1.0: every hole and inside corner survives (a
        pin can go through the nut); 0.0: all filled, as by a convex hull. 1.0 too when M has no measurable
        concave space (fewer than 20 samples in it).
    concave_volume_ratio: the concave space's volume over M's volume (0 for a convex part); it says how much
        ``concavity_kept`` matters.
    n_pieces: geoms the model adds per instance (1 for a primitive or a single hull).
    n_vertices_total: mesh vertices over all pieces (0 for a primitive: MuJoCo collides it analytically).
    n_samples: Monte-Carlo points used.
    """

    excess_volume_ratio: float
    missed_volume_ratio: float
    concavity_kept: float
    concave_volume_ratio: float
    n_pieces: int
    n_vertices_total: int
    n_samples: int


@dataclass(frozen=True, eq=False)
class CollisionModel:
    """A part's collision geometry in one tier: either convex mesh pieces or primitives, never both.

    ``compute_s`` is the wall time of building the geometry when it was first computed (kept in the cache, so a
    cache hit reports the original cost); ``fidelity_s`` the time of the Monte-Carlo measurement. ``from_cache``
    says whether this object was loaded from the disk cache.
    """

    tier: CollisionTier
    pieces: tuple[ConvexPiece, ...]
    primitives: tuple[PrimitiveGeom, ...]
    fidelity: Fidelity
    compute_s: float
    fidelity_s: float
    content_hash: str
    params: CollisionParams
    from_cache: bool = False

    @property
    def n_pieces(self) -> int:
        return len(self.pieces) + len(self.primitives)

    @property
    def description(self) -> str:
        """Short words for logs and tables, e.g. ``hull/cylinder`` or ``coacd/7 pieces``."""
        if self.primitives:
            return f"{self.tier.value}/{'+'.join(p.kind for p in self.primitives)}"
        if self.tier is CollisionTier.HULL:
            return "hull/convex hull"
        return f"{self.tier.value}/{len(self.pieces)} pieces"

    def convex_pieces(self) -> tuple[ConvexPiece, ...]:
        """The convex mesh pieces, each ``(vertices (n, 3) float64 m, faces (m, 3) int64)``; empty for primitives."""
        return self.pieces

    def primitive_geoms(self) -> tuple[PrimitiveGeom, ...]:
        """The primitive geoms (box or cylinder); empty for mesh pieces."""
        return self.primitives

    def to_mujoco_geoms(self) -> list[dict]:
        """One dict per geom, in plain arrays that an ``MjSpec`` builder consumes.

        Keys: ``type`` ("box", "cylinder" or "mesh"); ``size`` (MuJoCo's size convention, empty for a mesh);
        ``pos`` (3,) metres and ``quat`` (4,) (w, x, y, z) of the geom in the body (object) frame; for a mesh also
        ``vertices`` (n, 3) float64 metres and ``faces`` (m, 3) int64, the vertices in the object frame.
        """
        geoms: list[dict] = []
        for prim in self.primitives:
            x, y, z, w = Rotation.from_matrix(prim.T_obj_geom[:3, :3]).as_quat()
            geoms.append(
                {
                    "type": prim.kind,
                    "size": np.asarray(prim.size_m, dtype=np.float64),
                    "pos": np.array(prim.T_obj_geom[:3, 3], dtype=np.float64),
                    "quat": np.array([w, x, y, z]),
                }
            )
        for piece in self.pieces:
            geoms.append(
                {
                    "type": "mesh",
                    "size": np.zeros(0),
                    "pos": np.zeros(3),
                    "quat": np.array([1.0, 0.0, 0.0, 0.0]),
                    "vertices": piece.vertices,
                    "faces": piece.faces,
                }
            )
        return geoms

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(n,) bool: which ``points`` (n, 3, object frame, metres) lie inside any piece or primitive."""
        return _contains(self.pieces, self.primitives, points)

    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned bounds of the collision geometry in the object frame."""
        return _bounds(self.pieces, self.primitives)


def _contains(pieces: Sequence[ConvexPiece], primitives: Sequence[PrimitiveGeom], points: np.ndarray) -> np.ndarray:
    inside = np.zeros(len(points), dtype=bool)
    for prim in primitives:
        inside |= prim.contains(points)
    for piece in pieces:
        inside |= points_in_convex(piece.vertices, piece.faces, points)
    return inside


def _bounds(pieces: Sequence[ConvexPiece], primitives: Sequence[PrimitiveGeom]) -> np.ndarray:
    boxes = [p.bounds() for p in primitives] + [np.stack([p.vertices.min(0), p.vertices.max(0)]) for p in pieces]
    stacked = np.stack(boxes)
    return np.stack([stacked[:, 0].min(0), stacked[:, 1].max(0)])


# ---------------------------------------------------------------------------------------------- public API


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
    folder = resolve_cache_dir(cache_dir)
    key = _cache_key(model.content_hash, tier, params)
    stem = folder / f"{model.content_hash[:16]}-{tier.value}-{key[:16]}"

    cached = _load_cached(stem, key, tier, model.content_hash, params)
    if cached is not None:
        log.debug("collision cache hit for %s (%s): %s", model.name, tier.value, stem)
        return cached

    if not model.mesh.is_watertight:
        log.warning(
            "%s: the mesh is not watertight; its inside is ill-defined, so the fidelity numbers are approximate",
            model.name,
        )
    start = time.perf_counter()
    pieces, primitives = _BUILDERS[tier](model.mesh, params)
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
    _save_cached(stem, key, result)
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

    Tiers are tried in the order given, by default cheapest first: hull (1 geom, milliseconds), coacd (2-35
    pieces, 0.3-7 s), vhacd (up to 32 pieces, 0.6-2.5 s); cost is the number of pieces, then the compute time.
    A tier is only built when the cheaper ones failed; coacd is tried twice, the second time with its concavity
    threshold times 0.4 (finer, more pieces). If none meets the tolerances, the one that misses them by
    the least (summed relative shortfall; ties to the cheaper) is returned and a warning names each missed
    tolerance and by how much.

    Defaults:
        max_excess_volume_ratio=0.05: at most 5 % extra material. A box-like or cylindrical part stays a
            primitive; a washer's or a nut's hull fills the hole (42 % and 41 % excess), so they go to a
            decomposition. No default tier meets it for the thin-walled pipe (coacd 12 %, vhacd 6 % with 9 %
            missed): a finer ``coacd_concavity_threshold`` does.
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
        # for a few more pieces, which beats V-HACD's fixed 32 pieces (the pipe: 24 pieces, 1.9 % excess).
        attempts = [base]
        if tier is CollisionTier.COACD:
            finer = base.coacd_concavity_threshold * _COACD_REFINE_FACTOR
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


def resolve_cache_dir(cache_dir: Path | str | None = None) -> Path:
    """The collision cache folder: ``cache_dir``, else ``$SYGRID_CACHE_DIR/collision``, else
    ``~/.cache/sygrid/collision``. The environment is read at each call, never at import."""
    if cache_dir is not None:
        return Path(cache_dir).expanduser()
    root = os.environ.get(_CACHE_ENV)
    if root:
        return Path(root).expanduser() / "collision"
    return Path.home() / ".cache" / "sygrid" / "collision"


# ---------------------------------------------------------------------------------------------- fidelity


def measure_fidelity(
    mesh: trimesh.Trimesh,
    pieces: Sequence[ConvexPiece],
    primitives: Sequence[PrimitiveGeom],
    n_samples: int,
    seed: int,
    name: str = "mesh",
) -> Fidelity:
    """The ``Fidelity`` of a collision model (pieces and primitives, object frame) against ``mesh``.

    Cost: one point-in-mesh test of ``n_samples`` points (about 0.1 s for 20 000 points and 2 000 faces), plus a
    half-space test per convex piece (negligible). ``name`` is the part's name for error messages.

    Raises:
        MeshError: no sample falls inside the mesh (it has no inside).
    """
    model_lo, model_hi = _bounds(pieces, primitives)
    lo, hi = np.minimum(model_lo, mesh.bounds[0]), np.maximum(model_hi, mesh.bounds[1])
    points = np.random.default_rng(seed).uniform(lo, hi, size=(n_samples, 3))

    in_mesh = np.zeros(n_samples, dtype=bool)
    mesh_lo, mesh_hi = np.asarray(mesh.bounds)
    near = np.all((points >= mesh_lo) & (points <= mesh_hi), axis=1)  # outside M's box nothing is inside M
    in_mesh[near] = points_in_mesh(np.asarray(mesh.triangles), points[near])
    hull = mesh.convex_hull
    in_hull = np.zeros(n_samples, dtype=bool)
    in_hull[near] = points_in_convex(np.asarray(hull.vertices), np.asarray(hull.faces), points[near])
    in_model = _contains(pieces, primitives, points)

    n_mesh = int(in_mesh.sum())
    if n_mesh == 0:
        raise MeshError(
            f"{name}: no Monte-Carlo point of {n_samples} in its bounding box fell inside the mesh, so it has no "
            "inside (open, or normals pointing inward); expected a watertight mesh with outward normals"
        )
    concave = in_hull & ~in_mesh
    n_concave = int(concave.sum())
    return Fidelity(
        excess_volume_ratio=float((in_model & ~in_mesh).sum() / n_mesh),
        missed_volume_ratio=float((in_mesh & ~in_model).sum() / n_mesh),
        concavity_kept=float((concave & ~in_model).sum() / n_concave) if n_concave >= _MIN_CONCAVE_SAMPLES else 1.0,
        concave_volume_ratio=float(n_concave / n_mesh),
        n_pieces=len(pieces) + len(primitives),
        n_vertices_total=int(sum(len(p.vertices) for p in pieces)),
        n_samples=n_samples,
    )


# ---------------------------------------------------------------------------------------------- the tiers


def _build_hull(mesh: trimesh.Trimesh, params: CollisionParams) -> tuple[tuple, tuple]:
    """A box or cylinder that encloses the convex hull with little excess volume, else the hull itself."""
    hull = mesh.convex_hull
    hull_volume = float(hull.volume)
    candidates: list[PrimitiveGeom] = []
    obb = hull.bounding_box_oriented
    candidates.append(
        PrimitiveGeom("box", tuple(float(e) / 2 for e in obb.primitive.extents), np.array(obb.primitive.transform))
    )
    cyl = trimesh.bounds.minimum_cylinder(hull)
    candidates.append(
        PrimitiveGeom(
            "cylinder", (float(cyl["radius"]), float(cyl["height"]) / 2), np.array(cyl["transform"], dtype=float)
        )
    )
    fitting = [p for p in candidates if p.volume_m3 <= hull_volume * (1.0 + params.primitive_max_excess_ratio)]
    if fitting:
        best = min(fitting, key=lambda p: p.volume_m3)
        log.debug("hull tier: %s, %.2f %% over the convex hull", best.kind, 100 * (best.volume_m3 / hull_volume - 1))
        return (), (best,)
    return (_convex_piece(np.asarray(hull.vertices)),), ()


def _build_coacd(mesh: trimesh.Trimesh, params: CollisionParams) -> tuple[tuple, tuple]:
    import coacd  # heavy native library: imported on use

    coacd.set_log_level("error")
    remesh = params.coacd_remesh == "always" or (params.coacd_remesh == "if_not_watertight" and not mesh.is_volume)
    parts = coacd.run_coacd(
        coacd.Mesh(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)),
        threshold=params.coacd_concavity_threshold,
        max_convex_hull=params.coacd_max_hulls,
        preprocess_mode="on" if remesh else "off",
        preprocess_resolution=params.coacd_preprocess_resolution,
        pca=params.coacd_pca,
        mcts_iterations=params.coacd_mcts_iterations,
        mcts_nodes=params.coacd_mcts_nodes,
        mcts_max_depth=params.coacd_mcts_max_depth,
        seed=params.coacd_seed,
    )
    return _clean_pieces([np.asarray(v, dtype=np.float64) for v, _f in parts], mesh), ()


def _build_vhacd(mesh: trimesh.Trimesh, params: CollisionParams) -> tuple[tuple, tuple]:
    from vhacdx import compute_vhacd  # heavy native library: imported on use

    # vhacdx wants the faces flat, each prefixed by its vertex count: [3, i, j, k, 3, ...] (as trimesh.decomposition
    # builds them). An (f, 3) array is accepted without an error and gives garbage hulls.
    faces = np.column_stack([np.full(len(mesh.faces), 3), mesh.faces]).ravel().astype(np.uint32)
    parts = compute_vhacd(
        np.asarray(mesh.vertices, dtype=np.float64),
        faces,
        maxConvexHulls=params.vhacd_max_hulls,
        resolution=params.vhacd_voxel_resolution,
        minimumVolumePercentErrorAllowed=params.vhacd_min_volume_error_percent,
        maxRecursionDepth=params.vhacd_max_recursion_depth,
        maxNumVerticesPerCH=params.vhacd_max_vertices_per_hull,
        asyncACD=False,  # the threaded search is not guaranteed to give the same pieces twice
    )
    return _clean_pieces([np.asarray(v, dtype=np.float64) for v, _f in parts], mesh), ()


_BUILDERS = {CollisionTier.HULL: _build_hull, CollisionTier.COACD: _build_coacd, CollisionTier.VHACD: _build_vhacd}


def _convex_piece(points: np.ndarray) -> ConvexPiece:
    """The convex hull of ``points`` (n, 3) as a closed triangle mesh with outward normals, arrays read-only.

    Qhull's triangulation is kept whole, zero-area triangles included: dropping them (as ``trimesh.convex``
    does) opens holes in hulls of nearly coplanar points, which V-HACD produces. Falls back to joggled input.

    Raises:
        ValueError: the points span no volume (fewer than 4, or all coplanar).
    """
    for options in (None, "QJ"):
        try:
            hull = ConvexHull(points, qhull_options=options)
        except QhullError:
            continue
        used = np.unique(hull.simplices)
        remap = np.zeros(len(points), dtype=np.int64)
        remap[used] = np.arange(len(used))
        vertices, faces = np.array(points[used], dtype=np.float64), remap[hull.simplices]
        tri = vertices[faces]
        outward = np.einsum("ij,ij->i", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), hull.equations[:, :3])
        faces[outward < 0] = faces[outward < 0, ::-1]
        mesh = trimesh.Trimesh(vertices, faces, process=False)
        if not mesh.is_winding_consistent:  # a zero-area triangle oriented by rounding noise
            mesh.fix_normals(multibody=False)
            faces = np.array(mesh.faces, dtype=np.int64)
        if mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0:
            vertices.flags.writeable = False
            faces.flags.writeable = False
            return ConvexPiece(vertices, faces)
    raise ValueError(f"the convex hull of {len(points)} points has no volume (flat or degenerate point set)")


def _clean_pieces(point_sets: list[np.ndarray], mesh: trimesh.Trimesh) -> tuple[ConvexPiece, ...]:
    """Each decomposer piece re-hulled (a closed convex mesh with outward normals whatever the decomposer's face
    order) and slivers dropped: MuJoCo refuses meshes of (near) zero volume."""
    min_volume = _MIN_PIECE_VOLUME_RATIO * float(mesh.convex_hull.volume)
    pieces = []
    for points in point_sets:
        if len(points) < 4 or not np.all(np.isfinite(points)):
            continue
        try:
            piece = _convex_piece(points)
        except ValueError as exc:
            log.debug("dropped a degenerate piece of %d points: %s", len(points), exc)
            continue
        volume = float(trimesh.Trimesh(piece.vertices, piece.faces, process=False).volume)
        if volume > min_volume:
            pieces.append(piece)
    if len(pieces) < len(point_sets):
        log.debug("dropped %d of %d pieces as slivers", len(point_sets) - len(pieces), len(point_sets))
    return tuple(pieces)


# ---------------------------------------------------------------------------------------------- disk cache


@cache
def _library_version(tier: CollisionTier) -> str:
    """The decomposer's version: a new release can give other pieces, so it is part of the cache key."""
    dist = {CollisionTier.HULL: "trimesh", CollisionTier.COACD: "coacd", CollisionTier.VHACD: "vhacdx"}[tier]
    try:
        return f"{dist}=={importlib.metadata.version(dist)}"
    except importlib.metadata.PackageNotFoundError:
        return f"{dist}==unknown"


def _cache_key(content_hash: str, tier: CollisionTier, params: CollisionParams) -> str:
    payload = {
        "format": _CACHE_FORMAT,
        "content_hash": content_hash,
        "tier": tier.value,
        "params": params.key_fields(tier),
        "library": _library_version(tier),
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def _save_cached(stem: Path, key: str, result: CollisionModel) -> None:
    """Arrays to ``stem.npz``, then metadata (with the npz's SHA-256) to ``stem.json``: the JSON is written last,
    so a reader never pairs a new JSON with an old or half-written npz. Each file is replaced atomically."""
    pieces = result.pieces
    buffer = io.BytesIO()
    np.savez(
        buffer,
        vertices=np.concatenate([p.vertices for p in pieces]) if pieces else np.zeros((0, 3)),
        faces=np.concatenate([p.faces for p in pieces]) if pieces else np.zeros((0, 3), dtype=np.int64),
        vertex_counts=np.array([len(p.vertices) for p in pieces], dtype=np.int64),
        face_counts=np.array([len(p.faces) for p in pieces], dtype=np.int64),
    )
    payload = buffer.getvalue()
    meta = {
        "format": _CACHE_FORMAT,
        "key": key,
        "content_hash": result.content_hash,
        "tier": result.tier.value,
        "params": asdict(result.params),
        "library": _library_version(result.tier),
        "compute_s": result.compute_s,
        "fidelity_s": result.fidelity_s,
        "fidelity": asdict(result.fidelity),
        "primitives": [
            {"kind": p.kind, "size_m": list(p.size_m), "T_obj_geom": np.asarray(p.T_obj_geom).tolist()}
            for p in result.primitives
        ],
        "npz_sha256": hashlib.sha256(payload).hexdigest(),
    }
    try:
        write_bytes_atomic(stem.with_suffix(".npz"), payload)
        write_json_atomic(stem.with_suffix(".json"), meta)
    except OSError as exc:  # a read-only or full cache folder costs a rebuild next time, not the result
        log.warning("could not write the collision cache entry %s: %s", stem, exc)
        return
    log.debug("wrote collision cache entry %s.{npz,json}", stem)


def _load_cached(
    stem: Path, key: str, tier: CollisionTier, content_hash: str, params: CollisionParams
) -> CollisionModel | None:
    """The cached model at ``stem``, or None when there is none or it is unreadable (with a warning)."""
    json_path, npz_path = stem.with_suffix(".json"), stem.with_suffix(".npz")
    if not json_path.exists():
        return None
    try:
        meta = json.loads(json_path.read_text())
        if meta.get("format") != _CACHE_FORMAT or meta.get("key") != key:
            raise ValueError(f"format/key mismatch (expected {_CACHE_FORMAT}, key {key[:16]}...)")
        payload = npz_path.read_bytes()
        if hashlib.sha256(payload).hexdigest() != meta["npz_sha256"]:
            raise ValueError(f"{npz_path.name} does not match the SHA-256 recorded in {json_path.name}")
        with np.load(io.BytesIO(payload), allow_pickle=False) as npz:
            pieces = _split_pieces(npz["vertices"], npz["faces"], npz["vertex_counts"], npz["face_counts"])
        primitives = tuple(_primitive_from_json(p) for p in meta["primitives"])
        fidelity = Fidelity(**meta["fidelity"])
        if not pieces and not primitives:
            raise ValueError("the entry holds no geometry")
        return CollisionModel(
            tier=tier,
            pieces=pieces,
            primitives=primitives,
            fidelity=fidelity,
            compute_s=float(meta["compute_s"]),
            fidelity_s=float(meta["fidelity_s"]),
            content_hash=content_hash,
            params=params,
            from_cache=True,
        )
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile) as exc:
        log.warning("ignoring the unreadable collision cache entry %s (%s); rebuilding it", json_path, exc)
        return None


def _split_pieces(
    vertices: np.ndarray, faces: np.ndarray, vertex_counts: np.ndarray, face_counts: np.ndarray
) -> tuple[ConvexPiece, ...]:
    """Concatenated arrays back into pieces, checking shapes and indices so a damaged entry is never returned."""
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"vertices/faces must be (n, 3), got {vertices.shape} and {faces.shape}")
    if (
        len(vertex_counts) != len(face_counts)
        or vertex_counts.sum() != len(vertices)
        or face_counts.sum() != len(faces)
    ):
        raise ValueError("piece counts do not add up to the stored vertices and faces")
    if not np.all(np.isfinite(vertices)):
        raise ValueError("non-finite vertices")
    if len(vertex_counts) == 0:
        return ()
    pieces = []
    v_split = np.split(vertices.astype(np.float64), np.cumsum(vertex_counts)[:-1])
    f_split = np.split(faces.astype(np.int64), np.cumsum(face_counts)[:-1])
    for v, f in zip(v_split, f_split, strict=True):
        if len(f) < 4 or f.min() < 0 or f.max() >= len(v):
            raise ValueError("a piece has fewer than 4 faces or face indices out of range")
        v.flags.writeable = False
        f.flags.writeable = False
        pieces.append(ConvexPiece(v, f))
    return tuple(pieces)


def _primitive_from_json(entry: dict) -> PrimitiveGeom:
    kind = entry["kind"]
    size = tuple(float(s) for s in entry["size_m"])
    T = np.asarray(entry["T_obj_geom"], dtype=np.float64)
    expected = {"box": 3, "cylinder": 2}
    if kind not in expected or len(size) != expected[kind] or T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"bad primitive entry {entry!r}")
    T.flags.writeable = False
    return PrimitiveGeom(kind, size, T)
