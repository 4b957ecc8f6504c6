"""Detection masks cleaned with depth before a pose is fitted to them.

A detector's mask is a filled blob at a coarse scale: it takes in the floor seen through a nut's or washer's hole,
a rim of floor or bin wall around the part, and sometimes a sliver of a neighbour. Fitting a model to those points
pulls the pose off, and the principal axes of the cloud with them. The clean-up keeps the pixels that can be the
part's surface:

1. pixels without depth go;
2. the floor: with a known floor plane (the cell knows its bin), pixels less than ``floor_margin_m`` above it go;
   without one, the plane the part lies on is found in the depth just around the mask (``support_plane``) and
   pixels within ``floor_margin_m`` of it go (a plane above most of the mask is a taller neighbour, not a support,
   and is not used). No part surface lies on its support itself. The plane used is the observation's ``support``,
   which the verification holds the model above;
3. the mask is cut along depth discontinuities (4-neighbours whose depths differ by more than ``jump_m``, more
   than a part's own surface steps between neighbouring pixels) into connected pieces;
4. a piece that lies behind the pieces it touches is what is seen past the part's edge or through its hole when it
   is enclosed by the mask (a hole), a rim (an erosion by ``rim_px`` removes it) or tiny: those go. A larger piece
   behind its neighbours that reaches the mask's edge stays (a bracket's far leg seen past its near one).

Returns the cleaned observation and what was removed, per reason (``details``), for the pose's diagnostics.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from perception.observation import Observation
from sygrid.camera import CameraIntrinsics


@dataclass(frozen=True)
class MaskCleanupConfig:
    """Attributes:
    jump_m: a depth difference between 4-neighbours larger than this [m] cuts the mask there.
    min_piece_px: pieces behind their neighbours smaller than this (pixels) are dropped.
    rim_px: pieces behind their neighbours that an erosion by this many pixels removes are a rim: dropped.
    floor_margin_m: with a floor plane, pixels less than this [m] above it are floor.
    local_floor: without a floor plane, take the plane the part lies on from the depth around its mask
        (``support_plane``): the ring ``support_ring_px`` wide around the mask, ``support_trials`` RANSAC triples,
        inliers within ``support_tolerance_m``, at least ``support_fraction`` of at least ``support_min_points``.
    """

    jump_m: float = 0.008
    min_piece_px: int = 4
    rim_px: int = 1
    local_floor: bool = True
    support_ring_px: int = 4
    support_min_points: int = 20
    support_trials: int = 64
    support_tolerance_m: float = 0.001
    support_fraction: float = 0.5
    floor_margin_m: float = 0.0015

    def __post_init__(self) -> None:
        if self.jump_m <= 0 or self.min_piece_px < 1 or self.floor_margin_m < 0:
            raise ValueError(
                "MaskCleanupConfig: need jump_m > 0, min_piece_px >= 1 and floor_margin_m >= 0, got "
                f"{self.jump_m}, {self.min_piece_px}, {self.floor_margin_m}"
            )


def floor_height_m(
    depth_m: np.ndarray, intrinsics: CameraIntrinsics, floor_plane_camera: np.ndarray, x0: int = 0, y0: int = 0
) -> np.ndarray:
    """Height [m] above the plane ``(a, b, c, d)`` (camera frame, unit normal pointing up) of each pixel of the
    depth crop whose top-left pixel is ``(x0, y0)``; NaN where there is no depth."""
    depth = np.asarray(depth_m, dtype=np.float64)
    h, w = depth.shape
    K = intrinsics.K
    n, d = np.asarray(floor_plane_camera[:3], dtype=float), float(floor_plane_camera[3])
    # height = z * (n . ray(u, v)) + d with the ray of unit depth through the pixel (separable in u and v)
    along_u = n[0] * (np.arange(x0, x0 + w) - K[0, 2]) / K[0, 0]
    along_v = n[1] * (np.arange(y0, y0 + h) - K[1, 2]) / K[1, 1]
    height = depth * (along_v[:, None] + along_u[None, :] + n[2]) + d
    return np.where(depth > 0, height, np.nan)


def support_plane(obs: Observation, config: MaskCleanupConfig | None = None) -> np.ndarray | None:
    """The plane the part lies on, from the depth just around its mask: ``(a, b, c, d)`` with the unit normal
    towards the camera, or None when no plane holds ``support_fraction`` of the ring's points (a cluttered or
    empty surround). RANSAC over seeded triples of the ring's points (inliers within ``support_tolerance_m``),
    refined by least squares on the inliers."""
    cfg = config or MaskCleanupConfig()
    kernel = np.ones((3, 3), np.uint8)
    ring = cv2.dilate(obs.mask.astype(np.uint8), kernel, iterations=cfg.support_ring_px).astype(bool) & ~obs.mask
    ring &= obs.depth_m > 0
    ys, xs = np.nonzero(ring)
    if len(xs) < cfg.support_min_points:
        return None
    z = obs.depth_m[ys, xs]
    K = obs.intrinsics.K
    p = np.column_stack([(xs + obs.x0 - K[0, 2]) * z / K[0, 0], (ys + obs.y0 - K[1, 2]) * z / K[1, 1], z])
    rng = np.random.default_rng(0)
    triples = p[rng.integers(0, len(p), size=(cfg.support_trials, 3))]
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    length = np.linalg.norm(normals, axis=1)
    good = length > 1e-9
    if not good.any():
        return None
    normals = normals[good] / length[good, None]
    offsets = -(normals * triples[good, 0]).sum(axis=1)
    inliers = np.abs(p @ normals.T + offsets) < cfg.support_tolerance_m  # (n, trials)
    best = int(np.argmax(inliers.sum(axis=0)))
    chosen = inliers[:, best]
    if chosen.sum() < cfg.support_fraction * len(p):
        return None
    q = p[chosen]
    centre = q.mean(axis=0)
    normal = np.linalg.svd(q - centre, full_matrices=False)[2][2]
    if normal @ centre > 0:  # point towards the camera (the origin)
        normal = -normal
    return np.append(normal, -normal @ centre)


def clean_mask(
    obs: Observation, config: MaskCleanupConfig | None = None, floor_plane_camera: np.ndarray | None = None
) -> tuple[Observation, dict]:
    """The observation with its mask reduced to the pixels that can be the part's surface (module docstring).

    Args:
        obs: the detection's crop (depth and mask).
        config: the settings (defaults if None).
        floor_plane_camera: ``(a, b, c, d)`` the floor in the camera frame, or None.

    Returns:
        ``(cleaned observation, details)``, details: ``pixels`` (in the mask), ``no_depth``, ``floor``, ``behind``
        (pieces behind the part), ``small`` (tiny pieces), ``kept``.
    """
    cfg = config or MaskCleanupConfig()
    depth = obs.depth_m
    valid = obs.mask & (depth > 0)
    details = {"pixels": int(obs.mask.sum()), "no_depth": 0, "floor": 0, "hole": 0, "rim": 0, "kept": 0}
    details["no_depth"] = details["pixels"] - int(valid.sum())
    support = None
    if floor_plane_camera is not None:
        support = np.asarray(floor_plane_camera, dtype=float)
        height = floor_height_m(depth, obs.intrinsics, support, obs.x0, obs.y0)
        on_floor = valid & (height < cfg.floor_margin_m)
        details["floor"] = int(on_floor.sum())
        valid &= ~on_floor
    elif cfg.local_floor and (plane := support_plane(obs, cfg)) is not None:
        height = floor_height_m(depth, obs.intrinsics, plane, obs.x0, obs.y0)
        # a part lies on its support, so the mask's pixels are on or above it; a plane above most of them is
        # something else in the surround (a taller neighbour), and the part's pixels below it are kept
        if valid.any() and np.median(height[valid]) > -cfg.floor_margin_m:
            support = plane
            on_floor = valid & (np.abs(height) < cfg.floor_margin_m)
            details["floor"] = int(on_floor.sum())
            valid &= ~on_floor
    pieces = _pieces(depth, valid, cfg.jump_m)
    n = int(pieces.max())
    if n == 0:
        return obs.with_mask(valid, support), details
    sizes = np.bincount(pieces.ravel(), minlength=n + 1)[1:]
    main = int(np.argmax(sizes))
    keep = np.ones(n + 1, dtype=bool)
    keep[0] = False
    if n > 1:
        behind = _behind_pieces(depth, pieces, n, cfg.jump_m)
        inside = _enclosed_pieces(pieces, obs.mask, n)
        thin = _thin_pieces(pieces, n, cfg.rim_px)
        for k in range(n):
            if k == main or not behind[k]:
                continue
            if inside[k] or thin[k] or sizes[k] < cfg.min_piece_px:
                keep[k + 1] = False
                details["hole" if inside[k] else "rim"] += int(sizes[k])
    kept = keep[pieces]
    details["kept"] = int(kept.sum())
    return obs.with_mask(kept, support), details


def _behind_pieces(depth: np.ndarray, pieces: np.ndarray, n: int, jump_m: float) -> np.ndarray:
    """(n,) bool: pieces that lie behind the pieces they touch (the median depth step across their shared border,
    this piece minus the neighbour, exceeds ``jump_m``); a piece touching no other is not behind."""
    ks, steps = [], []
    for a, b, da, db in (
        (pieces[:, :-1], pieces[:, 1:], depth[:, :-1], depth[:, 1:]),
        (pieces[:-1, :], pieces[1:, :], depth[:-1, :], depth[1:, :]),
    ):
        border = (a > 0) & (b > 0) & (a != b)
        ks += [a[border] - 1, b[border] - 1]
        steps += [da[border] - db[border], db[border] - da[border]]
    k_all, step_all = np.concatenate(ks), np.concatenate(steps)
    out = np.zeros(n, dtype=bool)
    for k in np.unique(k_all):
        out[k] = float(np.median(step_all[k_all == k])) > jump_m
    return out


def _enclosed_pieces(pieces: np.ndarray, mask: np.ndarray, n: int) -> np.ndarray:
    """(n,) bool: pieces that touch neither the mask's outside (a pixel not in the mask, or the crop's edge) nor
    a mask pixel without depth: what is seen through a hole of the part."""
    outside = np.pad(~mask, 1, constant_values=True)
    near_outside = outside[:-2, 1:-1] | outside[2:, 1:-1] | outside[1:-1, :-2] | outside[1:-1, 2:]
    touching = np.unique(pieces[near_outside & (pieces > 0)]) - 1
    out = np.ones(n, dtype=bool)
    out[touching] = False
    return out


def _thin_pieces(pieces: np.ndarray, n: int, rim_px: int) -> np.ndarray:
    """(n,) bool: pieces no part of which survives an erosion by ``rim_px`` pixels (a rim along an edge)."""
    out = np.ones(n, dtype=bool)
    for k in range(n):
        piece = (pieces == k + 1).astype(np.uint8)
        if cv2.erode(piece, np.ones((3, 3), np.uint8), iterations=rim_px).any():
            out[k] = False
    return out


def _pieces(depth: np.ndarray, valid: np.ndarray, jump_m: float) -> np.ndarray:
    """Connected pieces (4-neighbourhood) of ``valid`` pixels that no depth jump above ``jump_m`` separates:
    (h, w) int32 labels, 0 = not in any piece (the links across a jump are dropped before labelling)."""
    h, w = depth.shape
    index = np.arange(h * w).reshape(h, w)
    right = valid[:, :-1] & valid[:, 1:] & (np.abs(depth[:, :-1] - depth[:, 1:]) <= jump_m)
    down = valid[:-1, :] & valid[1:, :] & (np.abs(depth[:-1, :] - depth[1:, :]) <= jump_m)
    rows = np.concatenate([index[:, :-1][right], index[:-1, :][down]])
    cols = np.concatenate([index[:, 1:][right], index[1:, :][down]])
    graph = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(h * w, h * w))
    _, component = connected_components(graph, directed=False)
    labels = np.zeros(h * w, dtype=np.int32)
    flat = valid.ravel()
    _, compact = np.unique(component[flat], return_inverse=True)
    labels[flat] = compact.astype(np.int32) + 1
    return labels.reshape(h, w)
