"""Grasp candidates of a part for a parallel gripper: antipodal pairs from the mesh (cached) or the part's declared
grasps, expanded by the part's symmetries and de-duplicated.

A candidate is a TCP pose in the object frame (``GraspAnnotation``'s convention: z the approach, into the part;
x the line between the pads; origin between the pads), the part's width between the pads, the opening the gripper
needs before it comes in, a quality score, and the span along z where the part touches the pads (so the planner
can slide a grasp back to clear the floor and still know how much of the pads hold the part).

Antipodal generation (``antipodal_grasps``), in the object frame:

1. Sample surface points; from each, cast a ray into the part along the inward normal. Every point where the ray
   leaves the solid (the exit face's normal within the friction cone of the ray) closes a pair: a grasp across
   the part, possibly across a hole (the pads touch only the two contacts). Width within the gripper's stroke.
2. Around each pair's axis, ``n_approach`` approach directions.
3. Against a dense sample of the part's own surface, in each grasp frame: the contact patches (surface within
   ``contact_tolerance_m`` of each pad plane, facing it); how far back the gripper must stay so that neither the
   pads' closing stroke nor the links, housing or wrist run into the part; then the depth that centres the pads on
   the patches, if the part allows it. Kept when both pads touch at least ``min_contact_area_m2`` and engage at
   least ``min_engagement_m`` along z.
4. Score: the friction-cone margin, how close the centre of mass lies to the grasp axis (less torque), the contact
   area; all in [0, 1], averaged.

The finished set (generated or declared, expanded, de-duplicated) is cached on disk (``robot.grasp_cache``) keyed by
the mesh's content hash and every parameter; a cache that cannot be read or written costs a rebuild, not the
result.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import logging
import time
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from robot.grasp_cache import load_entry, resolve_cache_dir, save_entry
from robot.grasp_geometry import required_backoff_m
from robot.grasp_set import GraspSet, GraspSetParams
from sygrid.errors import ConfigError
from sygrid.objects.model import ObjectModel

log = logging.getLogger(__name__)

_CACHE_FORMAT = "sygrid-grasps/1"
_RAY_START_M = 1e-6  # rays start this far inside the surface, so they do not hit their own face
_BATCH = 48  # grasp frames analysed at once against the dense surface sample (memory: batch x samples x 3)
_SIGN_REF = np.array([0.8017837, 0.5345225, 0.2672612])  # any fixed direction; sets the sign of the pad axis


# ---------------------------------------------------------------------------------------------- public API


def grasp_candidates(
    model: ObjectModel,
    params: GraspSetParams | None = None,
    cache_dir: Path | str | None = None,
    use_cache: bool = True,
) -> GraspSet:
    """``model``'s grasp candidates: its declared grasps (``model.grasps``) when it has any, else antipodal grasps
    from its mesh; expanded by its symmetries and de-duplicated. Cached on disk (``robot.grasp_cache``), keyed by
    the mesh, its declared grasps and symmetries, and every parameter.

    Raises:
        ConfigError: ``params`` is not a ``GraspSetParams``, or a declared grasp is wider than the stroke allows.
    """
    params = GraspSetParams() if params is None else params
    if not isinstance(params, GraspSetParams):
        raise ConfigError(f"params must be a GraspSetParams, got {type(params).__name__}")
    key = _cache_key(model, params)
    path = resolve_cache_dir(cache_dir) / f"{model.content_hash[:16]}-{key[:16]}.npz"
    if use_cache:
        cached = load_entry(path, key, _from_arrays)
        if cached is not None:
            log.debug("grasp cache hit for %s: %s", model.name, path)
            return cached
    start = time.perf_counter()
    base = declared_grasps(model, params) if model.grasps else antipodal_grasps(model, params)
    result = _expand_unique(base, model, params)
    log.info(
        "%s: %d %s grasp candidates (%d before the symmetry expansion) in %.2f s",
        model.name, len(result), result.source, len(base), time.perf_counter() - start,
    )  # fmt: skip
    if use_cache:
        save_entry(path, key, _to_arrays(result))
    return result


def antipodal_grasps(model: ObjectModel, params: GraspSetParams | None = None) -> GraspSet:
    """Antipodal grasps computed from ``model``'s mesh (not expanded, not de-duplicated, not cached)."""
    params = GraspSetParams() if params is None else params
    rng = np.random.default_rng(params.seed)
    mesh = model.mesh
    cos_cone = np.cos(params.cone_half_angle_rad)

    # 1. pairs: inward rays from surface samples, every exit point within the friction cone
    points, faces = trimesh.sample.sample_surface(mesh, params.n_surface_samples, seed=rng)
    normals = mesh.face_normals[faces]
    hits, ray, tri = mesh.ray.intersects_location(points - _RAY_START_M * normals, -normals, multiple_hits=True)
    exit_cos = np.einsum("ij,ij->i", mesh.face_normals[tri], -normals[ray])
    width = np.einsum("ij,ij->i", hits - points[ray], -normals[ray])
    keep = (exit_cos >= cos_cone) & (width >= params.min_width_m) & (width <= params.max_width_m)
    p1, axis, width, exit_cos = points[ray[keep]], -normals[ray[keep]], width[keep], exit_cos[keep]
    friction_margin = 1.0 - np.arccos(np.clip(exit_cos, -1.0, 1.0)) / params.cone_half_angle_rad
    centre = p1 + axis * width[:, None] / 2.0
    if not len(width):
        log.warning("%s: no antipodal pair within the stroke (%.3f m)", model.name, params.max_width_m)
        return _empty_set()
    # pairs that would give the same grasps (close centres, close axes either way round): keep the best one
    unique = _suppress_near(_features(centre, axis, width, params, None), friction_margin)
    p1, axis, width, friction_margin, centre = (
        p1[unique],
        axis[unique],
        width[unique],
        friction_margin[unique],
        centre[unique],
    )

    # 2. approach directions around each axis
    frames = _frames_around_axes(centre, axis, params.n_approach)
    reps = params.n_approach
    width, friction_margin = np.repeat(width, reps), np.repeat(friction_margin, reps)

    # 3. contacts and clearance against the part's own surface
    dense, dense_faces = trimesh.sample.sample_surface(mesh, params.n_dense_samples, seed=rng)
    analysis = _analyse(frames, width, dense, mesh.face_normals[dense_faces], mesh.area / len(dense), params, True)
    ok = analysis["ok"]

    # 4. score
    com = np.asarray(mesh.center_mass if mesh.is_volume else mesh.centroid)
    to_com = com - frames[:, :3, 3]
    along = np.einsum("ij,ij->i", to_com, frames[:, :3, 0])
    off_axis = np.linalg.norm(to_com - along[:, None] * frames[:, :3, 0], axis=1)
    com_term = 1.0 - np.clip(off_axis / (model.diameter_m / 2.0), 0.0, 1.0)
    area_term = np.clip(analysis["area_m2"] / params.contact_area_saturation_m2, 0.0, 1.0)
    score = (np.clip(friction_margin, 0.0, 1.0) + com_term + area_term) / 3.0
    opening = np.minimum(width + 2.0 * params.open_clearance_m, params.gripper.stroke_m)
    return GraspSet(
        analysis["T"][ok], width[ok], opening[ok], score[ok], analysis["contact_z_m"][ok], source="antipodal"
    )


def declared_grasps(model: ObjectModel, params: GraspSetParams | None = None) -> GraspSet:
    """``model.grasps`` as a ``GraspSet`` (poses kept as declared), with their contact spans measured on the mesh
    (the pads' full length where the mesh shows no contact, with a warning)."""
    params = GraspSetParams() if params is None else params
    if not model.grasps:
        return _empty_set("declared")
    frames = np.stack([np.asarray(g.T_obj_grasp, dtype=float) for g in model.grasps])
    width = np.array([float(g.width_m) for g in model.grasps])
    too_wide = width > params.max_width_m
    if too_wide.any():
        raise ConfigError(
            f"{model.name}: declared grasp(s) {np.flatnonzero(too_wide).tolist()} are wider ({width.max():.4f} m) "
            f"than the gripper's stroke allows ({params.max_width_m:.4f} m with the open clearance)"
        )
    rng = np.random.default_rng(params.seed)
    dense, faces = trimesh.sample.sample_surface(model.mesh, params.n_dense_samples, seed=rng)
    analysis = _analyse(
        frames, width, dense, model.mesh.face_normals[faces], model.mesh.area / len(dense), params, False
    )
    contact = analysis["contact_z_m"].copy()
    missing = ~analysis["has_patch"]
    if missing.any():
        log.warning(
            "%s: declared grasp(s) %s show no contact on the mesh; taking the pads' full length as the contact span",
            model.name, np.flatnonzero(missing).tolist(),
        )  # fmt: skip
        contact[missing] = (-params.gripper.pad_length_m / 2, params.gripper.pad_length_m / 2)
    opening = np.minimum(width + 2.0 * params.open_clearance_m, params.gripper.stroke_m)
    scores = np.array([float(g.score) for g in model.grasps])
    return GraspSet(frames, width, opening, scores, contact, source="declared")


def expand_by_symmetry(grasps: GraspSet, model: ObjectModel, continuous_steps: int = 36) -> GraspSet:
    """Every candidate mapped by every symmetry of ``model`` (``ObjectModel.symmetry_transforms``, identity first):
    ``len(symmetries) * len(grasps)`` candidates, not de-duplicated. A grasp on a part that looks the same after
    the symmetry transform is a grasp of the part."""
    sym = model.symmetry_transforms(continuous_steps)
    if len(sym) == 1 or not len(grasps):
        return grasps
    k = len(sym)
    T = np.einsum("sij,njk->snik", sym, grasps.T_obj_grasp).reshape(-1, 4, 4)
    return GraspSet(
        T, np.tile(grasps.width_m, k), np.tile(grasps.opening_m, k), np.tile(grasps.score, k),
        np.tile(grasps.contact_z_m, (k, 1)), grasps.source,
    )  # fmt: skip


def deduplicate(grasps: GraspSet, params: GraspSetParams | None = None) -> GraspSet:
    """Greedy suppression, best score first: a candidate within ``dedup_position_m`` (TCP position) and
    ``dedup_angle_deg`` (approach and pad axes, the two pad-swapped versions of a grasp being one) of a kept one is
    dropped. The result is sorted by score, best first."""
    params = GraspSetParams() if params is None else params
    if len(grasps) == 0:
        return grasps
    return grasps.subset(_suppress_near(_grasp_features(grasps, params), grasps.score))


# ---------------------------------------------------------------------------------------------- geometry


def _features(
    position: np.ndarray, axis: np.ndarray, width: np.ndarray, params: GraspSetParams, approach: np.ndarray | None
) -> np.ndarray:
    """Points in a space where "the same grasp" is a distance below 1: position and width in units of
    ``dedup_position_m``, unit vectors in units of ``dedup_angle_deg`` (the chord of a small angle is the angle).
    The pad axis is sign-free: x and -x (the pads swapped) are one grasp."""
    axis = axis * np.where(axis @ _SIGN_REF < 0, -1.0, 1.0)[:, None]
    angle_scale = 1.0 / max(np.radians(params.dedup_angle_deg), 1e-9)
    position_scale = 1.0 / max(params.dedup_position_m, 1e-12)
    columns = [position * position_scale, width[:, None] * position_scale, axis * angle_scale]
    if approach is not None:
        columns.append(approach * angle_scale)
    return np.hstack(columns)


def _grasp_features(grasps: GraspSet, params: GraspSetParams) -> np.ndarray:
    T = grasps.T_obj_grasp
    return _features(T[:, :3, 3], T[:, :3, 0], grasps.width_m, params, T[:, :3, 2])


def _suppress_near(features: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Indices kept by greedy suppression, best score first (ties by index), in that order: an item within
    distance 1 (see ``_features``) of a kept one is dropped."""
    n = len(features)
    pairs = cKDTree(features).query_pairs(1.0, output_type="ndarray")
    order = np.lexsort((np.arange(n), -score))
    rank = np.empty(n, dtype=int)
    rank[order] = np.arange(n)
    # each pair can only suppress its lower-ranked member: walk in rank order
    neighbours: list[list[int]] = [[] for _ in range(n)]
    for i, j in pairs:
        if rank[i] < rank[j]:
            neighbours[i].append(j)
        else:
            neighbours[j].append(i)
    suppressed = np.zeros(n, dtype=bool)
    kept = []
    for i in order:
        if suppressed[i]:
            continue
        kept.append(i)
        suppressed[neighbours[i]] = True
    return np.array(kept, dtype=int)


def _expand_unique(grasps: GraspSet, model: ObjectModel, params: GraspSetParams) -> GraspSet:
    """``deduplicate(expand_by_symmetry(grasps))``, computed one symmetry at a time: each transformed copy of the
    de-duplicated set adds only the grasps not already near a kept one. Much faster than suppressing the full
    expansion (a part with a continuous axis has 36-72 copies of every grasp, nearly all duplicates)."""
    base = deduplicate(grasps, params)
    sym = model.symmetry_transforms(params.continuous_steps)
    if len(sym) == 1 or not len(base):
        return base
    parts, kept_features = [base], _grasp_features(base, params)
    for S in sym[1:]:
        copy = GraspSet(S @ base.T_obj_grasp, base.width_m, base.opening_m, base.score, base.contact_z_m, base.source)
        features = _grasp_features(copy, params)
        distance, _ = cKDTree(kept_features).query(features, k=1, distance_upper_bound=1.0)
        new = ~(distance <= 1.0)
        if new.any():
            parts.append(copy.subset(new))
            kept_features = np.vstack([kept_features, features[new]])
    T = np.concatenate([p.T_obj_grasp for p in parts])
    merged = GraspSet(
        T,
        np.concatenate([p.width_m for p in parts]),
        np.concatenate([p.opening_m for p in parts]),
        np.concatenate([p.score for p in parts]),
        np.concatenate([p.contact_z_m for p in parts]),
        base.source,
    )
    return merged.subset(np.lexsort((np.arange(len(merged)), -merged.score)))


def _frames_around_axes(centre: np.ndarray, axis: np.ndarray, n_approach: int) -> np.ndarray:
    """``(n * n_approach, 4, 4)`` grasp frames: x = axis, z at ``n_approach`` even angles around it."""
    # a helper direction least aligned with each axis gives a stable first perpendicular
    helper = np.eye(3)[np.argmin(np.abs(axis), axis=1)]
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(axis, u)
    theta = 2.0 * np.pi * np.arange(n_approach) / n_approach
    z = np.cos(theta)[None, :, None] * u[:, None, :] + np.sin(theta)[None, :, None] * v[:, None, :]
    x = np.broadcast_to(axis[:, None, :], z.shape)
    y = np.cross(z, x)
    T = np.zeros((*z.shape[:2], 4, 4))
    T[..., :3, 0], T[..., :3, 1], T[..., :3, 2] = x, y, z
    T[..., :3, 3] = centre[:, None, :]
    T[..., 3, 3] = 1.0
    return T.reshape(-1, 4, 4)


def _analyse(
    frames: np.ndarray,
    width: np.ndarray,
    dense: np.ndarray,
    dense_normals: np.ndarray,
    area_per_sample_m2: float,
    params: GraspSetParams,
    choose_depth: bool,
) -> dict[str, np.ndarray]:
    """Contact patches, self-clearance and (with ``choose_depth``) the depth of each grasp frame, in batches.

    Returns ``T`` (frames moved to the chosen depth), ``contact_z_m`` (span of both patches in that frame),
    ``area_m2`` (the smaller pad's contact area at that depth), ``has_patch`` and ``ok`` (enough area, engagement
    and no part of the gripper inside the part)."""
    g = params.gripper
    cos_cone = np.cos(params.cone_half_angle_rad)
    tol = params.contact_tolerance_m
    half_pad_l = g.pad_length_m / 2
    n = len(frames)
    out = {
        "T": frames.copy(),
        "contact_z_m": np.zeros((n, 2)),
        "area_m2": np.zeros(n),
        "has_patch": np.zeros(n, dtype=bool),
        "ok": np.zeros(n, dtype=bool),
    }
    opening = np.minimum(width + 2.0 * params.open_clearance_m, g.stroke_m)
    for start in range(0, n, _BATCH):
        sl = slice(start, min(start + _BATCH, n))
        R, t = frames[sl, :3, :3], frames[sl, :3, 3]
        P = np.einsum("mi,nij->nmj", dense, R) - np.einsum("ni,nij->nj", t, R)[:, None, :]  # (b, m, 3) grasp frame
        nx = np.einsum("mi,ni->nm", dense_normals, R[:, :, 0])
        half = width[sl, None] / 2.0
        in_pad_y = np.abs(P[..., 1]) <= g.pad_width_m / 2
        patch_pos = in_pad_y & (np.abs(P[..., 0] - half) <= tol) & (nx >= cos_cone)
        patch_neg = in_pad_y & (np.abs(P[..., 0] + half) <= tol) & (nx <= -cos_cone)
        z = P[..., 2]
        lo = np.maximum(_masked_min(z, patch_pos), _masked_min(z, patch_neg))
        hi = np.minimum(_masked_max(z, patch_pos), _masked_max(z, patch_neg))
        has_patch = patch_pos.any(1) & patch_neg.any(1) & (hi >= lo)
        # the pads' closing strokes start just past the contacts (the clearance inflates the boxes back to them)
        boxes = g.boxes(opening[sl], inner_half_m=width[sl] / 2.0 + tol + params.self_clearance_m)
        d_self = required_backoff_m(P, boxes, params.self_clearance_m)
        if choose_depth:
            with np.errstate(invalid="ignore"):  # no patch: inf - inf, masked just below
                d = np.maximum(d_self, -(lo + hi) / 2.0)  # centre the pads on the patches unless the part is in the way
        else:
            d = np.zeros(len(P))
        d = np.where(has_patch, d, 0.0)
        lo, hi = np.where(has_patch, lo, 0.0), np.where(has_patch, hi, 0.0)
        pad_lo, pad_hi = -half_pad_l - d, half_pad_l - d  # the pads' span in the original frame
        engaged = np.minimum(pad_hi, hi) - np.maximum(pad_lo, lo)
        on_pad = (z >= pad_lo[:, None]) & (z <= pad_hi[:, None])
        area = np.minimum((patch_pos & on_pad).sum(1), (patch_neg & on_pad).sum(1)) * area_per_sample_m2
        shift = np.zeros((len(P), 4, 4))
        shift[:] = np.eye(4)
        shift[:, 2, 3] = -d
        out["T"][sl] = frames[sl] @ shift
        out["contact_z_m"][sl] = np.column_stack([lo + d, hi + d])
        out["area_m2"][sl] = area
        out["has_patch"][sl] = has_patch
        out["ok"][sl] = (
            has_patch
            & (engaged >= params.min_engagement_m)
            & (area >= params.min_contact_area_m2)
            & (d >= d_self - 1e-12)  # the gripper stays clear of the part itself
        )
    return out


def _masked_min(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    return np.where(mask, values, np.inf).min(axis=1)


def _masked_max(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    return np.where(mask, values, -np.inf).max(axis=1)


def _empty_set(source: str = "antipodal") -> GraspSet:
    return GraspSet(np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros((0, 2)), source)


# ---------------------------------------------------------------------------------------------- disk cache


def _cache_key(model: ObjectModel, params: GraspSetParams) -> str:
    declared = [
        {"T": np.asarray(g.T_obj_grasp, float).round(9).tolist(), "w": float(g.width_m), "s": float(g.score)}
        for g in model.grasps
    ]
    sym = np.asarray(model.symmetry_transforms(params.continuous_steps)).round(9)
    payload = {
        "format": _CACHE_FORMAT,
        "content_hash": model.content_hash,
        "params": asdict(params),
        "declared": declared,
        "symmetries": hashlib.sha256(sym.tobytes()).hexdigest(),
        "trimesh": _trimesh_version(),
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def _trimesh_version() -> str:
    try:
        return importlib.metadata.version("trimesh")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def _to_arrays(grasps: GraspSet) -> dict[str, np.ndarray]:
    """A grasp set as the cache stores it."""
    return {
        "source": np.array(grasps.source),
        "T_obj_grasp": grasps.T_obj_grasp,
        "width_m": grasps.width_m,
        "opening_m": grasps.opening_m,
        "score": grasps.score,
        "contact_z_m": grasps.contact_z_m,
    }


def _from_arrays(arrays: Mapping[str, np.ndarray]) -> GraspSet:
    """``_to_arrays``' inverse (``ValueError``/``KeyError`` on a malformed entry)."""
    return GraspSet(
        arrays["T_obj_grasp"], arrays["width_m"], arrays["opening_m"], arrays["score"], arrays["contact_z_m"],
        str(arrays["source"]),
    )  # fmt: skip
