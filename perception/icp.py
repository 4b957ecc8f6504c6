"""Point-to-plane ICP of a part's model against its depth points, in numpy with a closest-point map per model.

The depth points are moved into the object frame at the current pose and matched to the model surface sample
nearest to their cell of a grid around the model (``ClosestPointMap``, built once per model with a k-d tree: the
model never moves in its own frame, so nothing is built per iteration or per hypothesis). Only samples the camera
sees at the current pose are matched: facing it and, with ``occlusion``, not hidden behind the part's own surface
(ray cast, at the start and before the last stage), so that a point on a pipe's near wall does not match its far
wall's inside. A match farther than the stage's distance is dropped. Each iteration solves the linearised
point-to-plane problem for a small twist about the object origin (6x6 normal equations, with a small ridge term so
that a turn about a symmetry axis, which the data cannot fix, stays put) and composes it onto the pose. Stages of
shrinking match distance (fractions of the diameter) run until the update is negligible.

The result's ``fitness`` is the fraction of depth points matched within the last stage's distance, ``rmse_m`` their
point-to-plane RMS residual.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.spatial import cKDTree

from perception.refine import model_surface
from perception.verify import raycaster
from sygrid.objects.model import ObjectModel

_RIDGE = 1e-6  # relative ridge weight on the normal equations (of their trace)


@dataclass(frozen=True)
class IcpConfig:
    """Attributes:
    model_points: surface samples (with normals) of the model.
    grid_cells: cells of the closest-point map along the diameter.
    distance_fractions: the stages' match distances, x the diameter (coarse to fine).
    max_iterations: iterations per stage at most.
    max_scene_points: depth points used at most (an even subsample beyond that).
    converged_fraction: an update moving the object's points less than this x diameter ends a stage.
    occlusion: drop matches to model points that the part's own surface hides from the camera (ray cast); without
        it only the back faces are dropped, and a scene point can match the inside of a pipe's far wall.
    """

    model_points: int = 2000
    grid_cells: int = 64
    distance_fractions: tuple[float, ...] = (0.2, 0.08, 0.04)
    max_iterations: int = 6
    max_scene_points: int = 300
    converged_fraction: float = 5e-3
    occlusion: bool = True

    def __post_init__(self) -> None:
        if self.model_points < 10 or not self.distance_fractions or min(self.distance_fractions) <= 0:
            raise ValueError(
                "IcpConfig: need model_points >= 10 and positive distance_fractions, got "
                f"{self.model_points}, {self.distance_fractions}"
            )
        if self.max_iterations < 1 or self.max_scene_points < 3 or self.converged_fraction <= 0:
            raise ValueError(
                "IcpConfig: need max_iterations >= 1, max_scene_points >= 3 and converged_fraction > 0, got "
                f"{self.max_iterations}, {self.max_scene_points}, {self.converged_fraction}"
            )


@dataclass(frozen=True)
class IcpResult:
    """``T_camera_object`` after ICP; ``fitness`` in [0, 1]; ``rmse_m`` (NaN without matches); ``iterations``."""

    T_camera_object: np.ndarray
    fitness: float
    rmse_m: float
    iterations: int

    def as_dict(self) -> dict:
        return {"fitness": self.fitness, "rmse_m": self.rmse_m, "iterations": self.iterations}


@dataclass(frozen=True, eq=False)
class ClosestPointMap:
    """For every cell of a grid around the model (object frame), the index of the nearest surface sample: a
    depth point's match is one lookup instead of a k-d tree search.

    ``origin``: (3,) the grid's corner [m]; ``cell_m``: the cell size; ``index``: (nx, ny, nz) int32 sample index,
    -1 for cells farther than ``reach_m`` from the surface; ``points``, ``normals``: the samples.
    """

    origin: np.ndarray
    cell_m: float
    index: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    reach_m: float

    def lookup(self, x: np.ndarray) -> np.ndarray:
        """(n,) sample index of each object-frame point's cell, -1 outside the grid or beyond the reach."""
        f = (x - self.origin) * (1.0 / self.cell_m)
        nx, ny, nz = self.index.shape
        inside = (f[:, 0] >= 0) & (f[:, 1] >= 0) & (f[:, 2] >= 0) & (f[:, 0] < nx) & (f[:, 1] < ny) & (f[:, 2] < nz)
        ijk = f[inside].astype(np.int64)  # non-negative: truncation is the floor
        out = np.full(len(x), -1, dtype=np.int64)
        out[inside] = self.index.ravel()[(ijk[:, 0] * ny + ijk[:, 1]) * nz + ijk[:, 2]]
        return out


@lru_cache(maxsize=64)
def closest_point_map(model: ObjectModel, n_points: int, cells: int, reach_fraction: float) -> ClosestPointMap:
    """The model's ``ClosestPointMap`` with ``cells`` cells along the diameter, reaching ``reach_fraction`` x the
    diameter beyond the model's bounds (cached per model and settings)."""
    points, normals = model_surface(model, n_points, 0)
    diameter = float(model.diameter_m)
    cell = diameter / cells
    reach = reach_fraction * diameter
    lo = np.asarray(model.bounds_m[0]) - reach
    shape = np.ceil((np.asarray(model.bounds_m[1]) + reach - lo) / cell).astype(int)
    axes = [lo[k] + cell * (np.arange(shape[k]) + 0.5) for k in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    distance, index = cKDTree(points).query(centres, k=1, distance_upper_bound=reach)
    index = np.where(np.isfinite(distance), index, -1).astype(np.int32).reshape(tuple(shape))
    return ClosestPointMap(lo, cell, index, points, normals, reach)


def subsample(points: np.ndarray, n: int) -> np.ndarray:
    """At most ``n`` of the points, evenly spread over their order (deterministic)."""
    if len(points) <= n:
        return points
    return points[np.linspace(0, len(points) - 1, n).round().astype(int)]


def icp(
    T_camera_object: np.ndarray, scene: np.ndarray, model: ObjectModel, config: IcpConfig | None = None
) -> IcpResult:
    """Point-to-plane ICP from ``T_camera_object`` of the (n, 3) camera-frame depth points ``scene`` [m]."""
    cfg = config or IcpConfig()
    cpm = closest_point_map(model, cfg.model_points, cfg.grid_cells, max(cfg.distance_fractions))
    diameter = float(model.diameter_m)
    scene = subsample(np.asarray(scene, dtype=np.float64), cfg.max_scene_points)
    T = np.array(T_camera_object, dtype=np.float64)
    iterations = 0
    converged = cfg.converged_fraction * diameter
    seen = _seen(T, cpm, model, cfg.occlusion)
    for stage, fraction in enumerate(cfg.distance_fractions):
        distance = fraction * diameter
        if 0 < stage == len(cfg.distance_fractions) - 1:  # the fine stage sees from where the coarse ones ended
            seen = _seen(T, cpm, model, cfg.occlusion)
        for _ in range(cfg.max_iterations):
            iterations += 1
            R, t = T[:3, :3], T[:3, 3]
            x = (scene - t) @ R  # object frame: R^T (s - t)
            keep, q, n = _matches(x, cpm, seen, distance)
            if len(q) < 6:
                break
            x = x[keep]
            # minimise sum(((x + w x x + v) - q) . n)^2 over the twist (w, v) in the object frame
            A = np.empty((len(x), 6))
            A[:, 0] = x[:, 1] * n[:, 2] - x[:, 2] * n[:, 1]
            A[:, 1] = x[:, 2] * n[:, 0] - x[:, 0] * n[:, 2]
            A[:, 2] = x[:, 0] * n[:, 1] - x[:, 1] * n[:, 0]
            A[:, 3:] = n
            H = A.T @ A
            H[np.diag_indices(6)] += _RIDGE * np.trace(H)
            w_v = np.linalg.solve(H, A.T @ ((q - x) * n).sum(axis=1))
            # the scene moves by (dR, v) in the object frame, x' = dR x + v; the object pose becomes T (dR, v)^-1
            T[:3, :3] = R @ _rotation(w_v[:3]).T
            T[:3, 3] = t - T[:3, :3] @ w_v[3:]
            if np.linalg.norm(w_v[3:]) + np.linalg.norm(w_v[:3]) * diameter / 2 < converged:
                break
    x = (scene - T[:3, 3]) @ T[:3, :3]
    keep, q, n = _matches(x, cpm, seen, cfg.distance_fractions[-1] * diameter)
    fitness = float(keep.mean()) if len(scene) else 0.0
    rmse = float(np.sqrt(np.mean(((q - x[keep]) * n).sum(axis=1) ** 2))) if len(q) else math.nan
    return IcpResult(T, fitness, rmse, iterations)


def _seen(T: np.ndarray, cpm: ClosestPointMap, model: ObjectModel, occlusion: bool) -> np.ndarray:
    """(n,) bool: the model samples the camera sees at pose ``T``: facing it and, with ``occlusion``, not hidden by
    the part's own surface (ray cast)."""
    eye = -(T[:3, :3].T @ T[:3, 3])  # the camera centre in the object frame
    facing = ((cpm.points - eye) * cpm.normals).sum(axis=1) < 0
    if occlusion and facing.any():
        facing[facing] = raycaster(model).visible(T, cpm.points[facing])
    return facing


def _matches(
    x: np.ndarray, cpm: ClosestPointMap, seen: np.ndarray, distance: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For object-frame points ``x``: the (n,) mask of kept matches (the nearest sample, within ``distance``,
    among those ``seen``) and the kept matches' model points and normals."""
    idx = cpm.lookup(x)
    found = idx >= 0
    found[found] = seen[idx[found]]
    q = cpm.points[idx[found]]
    ok = ((q - x[found]) ** 2).sum(axis=1) < distance * distance
    keep = np.zeros(len(x), dtype=bool)
    keep[np.flatnonzero(found)[ok]] = True
    return keep, q[ok], cpm.normals[idx[found][ok]]


def _rotation(w: np.ndarray) -> np.ndarray:
    """The rotation matrix of the rotation vector ``w`` (Rodrigues)."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return np.eye(3)
    k = w / angle
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * Kx + (1 - math.cos(angle)) * Kx @ Kx
