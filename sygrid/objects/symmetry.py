"""Checks that declared symmetries really map a part onto itself.

A symmetry that does not hold corrupts ADD-S and grasp planning silently, so every declared transform can be
measured: sample the surface, move the samples by ``T_obj_obj``, and take the largest distance from a moved sample
to the original surface. For a true symmetry of the mesh that distance is zero up to floating point (or up to the
tessellation error, for a continuous axis on a tessellated circle).

The distances are computed here rather than by ``trimesh.proximity.closest_point``: trimesh's point-triangle routine
uses absolute tolerances that misplace the closest point (by up to ~0.2 mm) for millimetre triangles in metres.
"""

from __future__ import annotations

import logging

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from sygrid.objects.model import ObjectModel
from sygrid.transforms import is_rigid, transform_points

log = logging.getLogger(__name__)

# Angles at which a continuous symmetry is checked: irrational fractions of a turn, so that no tessellation with a
# "round" segment count happens to be symmetric at them by accident.
CONTINUOUS_CHECK_ANGLES_RAD: tuple[float, ...] = tuple(
    float(2.0 * np.pi * ((k * (np.sqrt(5.0) - 1.0) / 2.0) % 1.0)) for k in range(1, 8)
)

_MAX_PAIRS = 500_000  # (point, candidate face) pairs evaluated at once: a few hundred MB of temporaries at most


def sample_surface(mesh: trimesh.Trimesh, n_samples: int, rng: np.random.Generator) -> np.ndarray:
    """(n_samples, 3) points uniformly distributed (by area) on the mesh surface, drawn from ``rng``."""
    areas = np.asarray(mesh.area_faces, dtype=float)
    if len(areas) == 0 or areas.sum() <= 0.0:
        raise ValueError(f"cannot sample the surface of a mesh with {len(areas)} faces and zero area")
    face = rng.choice(len(areas), size=n_samples, p=areas / areas.sum())
    u, v = rng.random(n_samples), rng.random(n_samples)
    flip = u + v > 1.0  # fold the unit square onto the triangle
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    tri = mesh.triangles[face]  # (n, 3, 3)
    return tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])


def symmetry_error_m(mesh: trimesh.Trimesh, T_obj_obj: np.ndarray, n_samples: int = 2000, seed: int = 0) -> float:
    """Largest distance [m] from the surface samples moved by ``T_obj_obj`` (4x4) to the original surface.

    Zero (to floating point) when ``T_obj_obj`` maps the mesh onto itself. The same seed gives the same samples.
    """
    T = np.asarray(T_obj_obj, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"T_obj_obj must be a 4x4 transform, got shape {T.shape}")
    points = sample_surface(mesh, n_samples, np.random.default_rng(seed))
    return float(np.max(SurfaceDistance(mesh)(transform_points(T, points))))


class SurfaceDistance:
    """Exact point-to-surface distances for one mesh, built once and queried for many point sets.

    Candidate faces per point come from an r-tree of face bounding boxes, queried with a box whose half-size is an
    upper bound of the distance (the nearest of the vertices and of dense surface samples); the distance to each
    candidate is computed by ``point_triangle_distance``, which has no absolute tolerances. Points are processed in
    batches of at most ``_MAX_PAIRS`` (point, candidate) pairs, so far-away points cannot exhaust memory.
    """

    def __init__(self, mesh: trimesh.Trimesh, n_reference: int = 20000) -> None:
        self._triangles = np.asarray(mesh.triangles, dtype=float)
        samples = sample_surface(mesh, n_reference, np.random.default_rng(0))  # only bounds the search
        self._kdtree = cKDTree(np.concatenate((np.asarray(mesh.vertices), samples)))
        self._rtree = mesh.triangles_tree
        self._pad_m = 1e-12 * float(mesh.scale)  # keeps the query box non-empty for a point on a vertex

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(n,) distance [mesh units] from each of the (n, 3) ``points`` to the surface."""
        points = np.asarray(points, dtype=float)
        upper = self._kdtree.query(points)[0]
        best = upper.copy()
        half = (upper * (1.0 + 1e-9) + self._pad_m)[:, None]
        start, batch = 0, len(points)
        while start < len(points):
            stop = min(len(points), start + batch)
            lo, hi = points[start:stop] - half[start:stop], points[start:stop] + half[start:stop]
            ids, counts = self._rtree.intersection_v(lo, hi)
            counts = np.asarray(counts, dtype=np.int64)
            if counts.sum() > _MAX_PAIRS and batch > 1:
                batch = max(1, batch // 2)
                continue
            which = np.repeat(np.arange(start, stop), counts)
            distance = point_triangle_distance(points[which], self._triangles[np.asarray(ids, dtype=np.int64)])
            np.minimum.at(best, which, distance)
            start = stop
        return best


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    length_sq = np.einsum("ij,ij->i", ab, ab)
    t = np.einsum("ij,ij->i", p - a, ab)
    t = np.clip(np.divide(t, length_sq, out=np.zeros_like(t), where=length_sq > 0.0), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


def point_triangle_distance(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(n,) distance from each of the (n, 3) ``points`` to the matching (n, 3, 3) triangle.

    Scale-free (no absolute tolerances, unlike ``trimesh.triangles.closest_point``, whose tolerances misplace the
    closest point of millimetre triangles given in metres); degenerate triangles reduce to their edges.
    """
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    normal = np.cross(b - a, c - a)
    normal_sq = np.einsum("ij,ij->i", normal, normal)
    inside = normal_sq > 0.0
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(v - u, points - u), normal) >= 0.0
    distance = np.minimum.reduce(
        [_segment_distance(points, a, b), _segment_distance(points, b, c), _segment_distance(points, c, a)]
    )
    plane = np.abs(np.einsum("ij,ij->i", points[inside] - a[inside], normal[inside])) / np.sqrt(normal_sq[inside])
    distance[inside] = np.minimum(distance[inside], plane)
    return distance


def check_symmetries(model: ObjectModel, tol_m: float, n_samples: int = 2000, seed: int = 0) -> list[str]:
    """One readable problem per declared symmetry transform that does not hold within ``tol_m`` [m].

    Discrete transforms are checked as declared (rigidity, then the surface error); each continuous axis is checked
    at the seven ``CONTINUOUS_CHECK_ANGLES_RAD``. An empty list means every declared symmetry holds.
    """
    if tol_m <= 0.0:
        raise ValueError(f"tol_m must be > 0, got {tol_m}")
    problems: list[str] = []
    distance_to_surface = SurfaceDistance(model.mesh)
    points = sample_surface(model.mesh, n_samples, np.random.default_rng(seed))
    where = f"{model.name} (obj_id {model.obj_id})"
    for i, T in enumerate(model.symmetries_discrete):
        T = np.asarray(T, dtype=float)
        if not is_rigid(T):
            problems.append(f"{where}: symmetries_discrete[{i}] is not a rigid 4x4 transform")
            continue
        err = float(np.max(distance_to_surface(transform_points(T, points))))
        if err > tol_m:
            problems.append(
                f"{where}: symmetries_discrete[{i}] moves the surface up to {err * 1e3:.4g} mm off itself "
                f"(tolerance {tol_m * 1e3:.4g} mm)"
            )
    for i, sym in enumerate(model.symmetries_continuous):
        if not np.isclose(np.linalg.norm(sym.axis), 1.0, atol=1e-6):
            problems.append(f"{where}: symmetries_continuous[{i}].axis {sym.axis} is not a unit vector")
            continue
        errors = [
            float(np.max(distance_to_surface(transform_points(sym.transform(a), points))))
            for a in CONTINUOUS_CHECK_ANGLES_RAD
        ]
        worst = int(np.argmax(errors))
        if errors[worst] > tol_m:
            problems.append(
                f"{where}: symmetries_continuous[{i}] (axis {sym.axis}, offset {sym.offset_m} m) moves the surface "
                f"up to {errors[worst] * 1e3:.4g} mm off itself at "
                f"{np.degrees(CONTINUOUS_CHECK_ANGLES_RAD[worst]):.1f} deg (tolerance {tol_m * 1e3:.4g} mm)"
            )
    for problem in problems:
        log.debug(problem)
    return problems
