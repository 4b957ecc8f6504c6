"""What a collision model is: convex mesh pieces or primitive geoms in the object frame, its measured fidelity,
and the plain arrays the physics module turns into MuJoCo geoms (this module is MuJoCo-free)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from sygrid.objects.collision.params import CollisionParams, CollisionTier
from sygrid.objects.inside import points_in_convex

MIN_CONCAVE_SAMPLES = 20  # fewer Monte-Carlo samples than this in the concave space: nothing to keep


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
    points inside it times the box volume, so each ratio below is a ratio of point counts
    (``sygrid.objects.collision.fidelity.measure_fidelity``).

    excess_volume_ratio: volume inside C but outside M, over M's volume. What the model adds: filled holes, filled
        inside corners, the corners of a box around a round part. Parts collide early by this much material.
    missed_volume_ratio: volume inside M but outside C, over M's volume. What the model lacks: parts can
        interpenetrate there. A hull or a fitted primitive encloses M, so it misses nothing.
    concavity_kept: of the concave space (inside M's convex hull but outside M: holes, slots, gaps between gear
        teeth, inside corners), the fraction that C leaves free. 1.0: every hole and inside corner survives (a
        pin can go through the nut); 0.0: all filled, as by a convex hull. 1.0 too when M has no measurable
        concave space (fewer than ``MIN_CONCAVE_SAMPLES`` samples in it).
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
        return pieces_contain(self.pieces, self.primitives, points)

    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned bounds of the collision geometry in the object frame."""
        return pieces_bounds(self.pieces, self.primitives)


def pieces_contain(
    pieces: Sequence[ConvexPiece], primitives: Sequence[PrimitiveGeom], points: np.ndarray
) -> np.ndarray:
    """(n,) bool: which ``points`` (n, 3, object frame, metres) lie inside any of the pieces or primitives."""
    inside = np.zeros(len(points), dtype=bool)
    for prim in primitives:
        inside |= prim.contains(points)
    for piece in pieces:
        inside |= points_in_convex(piece.vertices, piece.faces, points)
    return inside


def pieces_bounds(pieces: Sequence[ConvexPiece], primitives: Sequence[PrimitiveGeom]) -> np.ndarray:
    """(2, 3) axis-aligned bounds (object frame, metres) of pieces and primitives together (at least one)."""
    boxes = [p.bounds() for p in primitives] + [np.stack([p.vertices.min(0), p.vertices.max(0)]) for p in pieces]
    stacked = np.stack(boxes)
    return np.stack([stacked[:, 0].min(0), stacked[:, 1].max(0)])
