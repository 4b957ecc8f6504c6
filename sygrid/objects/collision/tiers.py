"""The three collision tiers, cheapest first, each turning a part's mesh into collision geometry:

- ``hull``: one geom. A fitted primitive (box or cylinder, exact for MuJoCo's collision code) when its volume is
  within ``CollisionParams.primitive_max_excess_ratio`` of the mesh's convex hull, else the convex hull itself.
  Fills every hole and inside corner.
- ``coacd``: approximate convex decomposition with CoACD (Wei et al. 2022, the default decomposer): convex pieces
  that keep holes and inside corners.
- ``vhacd``: V-HACD (through ``vhacdx``), the SyGRID paper's method: voxel based, at most
  ``CollisionParams.vhacd_max_hulls`` pieces; it can shave thin walls.

Every decomposer piece is re-hulled into a closed convex mesh with outward normals, and slivers are dropped.
"""

from __future__ import annotations

import logging

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError

from sygrid.errors import MeshError
from sygrid.objects.collision.geometry import ConvexPiece, PrimitiveGeom
from sygrid.objects.collision.params import CollisionParams, CollisionTier
from sygrid.objects.collision.worker import run_decomposer, run_in_child

log = logging.getLogger(__name__)


class DecompositionTimeoutError(MeshError):
    """A decomposer did not finish within its time limit (``limit_s``, seconds)."""

    def __init__(self, message: str, limit_s: float) -> None:
        super().__init__(message)
        self.limit_s = limit_s


_MIN_PIECE_VOLUME_RATIO = 1e-6  # pieces smaller than this fraction of the hull's volume are slivers: dropped


def _build_hull(mesh: trimesh.Trimesh, params: CollisionParams, limit_s: float | None) -> tuple[tuple, tuple]:
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


def _build_coacd(mesh: trimesh.Trimesh, params: CollisionParams, limit_s: float | None) -> tuple[tuple, tuple]:
    remesh = params.coacd_remesh == "always" or (params.coacd_remesh == "if_not_watertight" and not mesh.is_volume)
    options = {
        "threshold": params.coacd_concavity_threshold,
        "max_convex_hull": params.coacd_max_hulls,
        "preprocess_mode": "on" if remesh else "off",
        "preprocess_resolution": params.coacd_preprocess_resolution,
        "pca": params.coacd_pca,
        "mcts_iterations": params.coacd_mcts_iterations,
        "mcts_nodes": params.coacd_mcts_nodes,
        "mcts_max_depth": params.coacd_mcts_max_depth,
        "seed": params.coacd_seed,
    }
    return _clean_pieces(_decompose("coacd", mesh, options, limit_s), mesh), ()


def _build_vhacd(mesh: trimesh.Trimesh, params: CollisionParams, limit_s: float | None) -> tuple[tuple, tuple]:
    options = {
        "maxConvexHulls": params.vhacd_max_hulls,
        "resolution": params.vhacd_voxel_resolution,
        "minimumVolumePercentErrorAllowed": params.vhacd_min_volume_error_percent,
        "maxRecursionDepth": params.vhacd_max_recursion_depth,
        "maxNumVerticesPerCH": params.vhacd_max_vertices_per_hull,
        "asyncACD": False,  # the threaded search is not guaranteed to give the same pieces twice
    }
    return _clean_pieces(_decompose("vhacd", mesh, options, limit_s), mesh), ()


def _decompose(decomposer: str, mesh: trimesh.Trimesh, options: dict, limit_s: float | None) -> list[np.ndarray]:
    """The decomposer's pieces: in this process without a time limit, else in a child process killed at it."""
    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    if limit_s is None:
        return run_decomposer(decomposer, vertices, faces, options)
    try:
        pieces = run_in_child(decomposer, vertices, faces, options, limit_s)
    except RuntimeError as exc:
        raise MeshError(str(exc)) from exc
    if pieces is None:
        raise DecompositionTimeoutError(f"{decomposer} did not finish within {limit_s:.1f} s", limit_s)
    return pieces


_BUILDERS = {CollisionTier.HULL: _build_hull, CollisionTier.COACD: _build_coacd, CollisionTier.VHACD: _build_vhacd}


def build_tier(
    mesh: trimesh.Trimesh, tier: CollisionTier, params: CollisionParams, time_limit_s: float | None = None
) -> tuple[tuple[ConvexPiece, ...], tuple[PrimitiveGeom, ...]]:
    """``mesh``'s collision geometry in ``tier`` (object frame): ``(pieces, primitives)``, one of them empty; both
    empty when the decomposer gave no usable piece.

    With ``time_limit_s`` a decomposer (coacd, vhacd) runs in a child process that is killed at the limit; the hull
    is always built in this process (it takes milliseconds).

    Raises:
        DecompositionTimeoutError: the decomposer ran out of ``time_limit_s``.
        MeshError: the decomposer's child process failed.
    """
    return _BUILDERS[tier](mesh, params, time_limit_s)


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
