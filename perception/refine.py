"""Optional pose refinement with depth: point-to-plane ICP of the object model against the masked depth cloud.

The depth pixels inside the detection mask are unprojected with the intrinsics (the scene cloud). The model is
represented by points sampled from its surface with their face normals; only the side the camera can see is kept
(points whose normal faces away from the camera are culled), because matching the hidden back of a part against the
visible front pulls it towards the camera. ICP starts from the initial rotation and, optionally, from the four
rotations that put the model's principal axes on the cloud's; each start is moved so that the visible model surface
shares the cloud's centroid (the depth says where the part is far better than an RGB estimate of its distance).
open3d's point-to-plane ICP aligns the scene cloud to the model points (the model side carries exact normals), in
stages of shrinking correspondence distance tied to the object diameter, and the best fit wins. The result is kept
only when it is plausible: enough scene points, enough of them explained by the model (fitness), and a correction
from its start no larger than a fraction of the diameter and a few tens of degrees; otherwise the initial pose comes
back, with the reason in ``details["icp"]``.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
import open3d as o3d
import trimesh

from perception.results import ObjectPose
from sygrid.camera import CameraIntrinsics, unproject_depth
from sygrid.metrics import symmetric_pose_errors
from sygrid.objects.model import ObjectModel
from sygrid.transforms import invert, make_T, rotation_angle_deg

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RefineConfig:
    """Settings of the depth refinement; lengths are fractions of the object diameter unless named ``_m``.

    Attributes:
        model_points: surface samples (with normals) per model, before visibility culling.
        pca_hypotheses: besides the initial rotation, start ICP from the four rotations that put the model's
            principal axes on the depth cloud's, and keep the best fit (a pose network's rotation can be tens of
            degrees off, beyond ICP's basin; for the axisymmetric parts the cloud's principal axes give the axis).
        icp_starts: of those starts, how many (the best fits before any ICP) ICP is run from.
        fallback_starts: when the result from those is refused (the checks below), ICP from up to this many of the
            next starts in rank order, until one passes: a start that fits best before ICP is not always the one
            ICP converges from (in the simulated cell, a nut estimated within millimetres was refused after ICP
            from a principal-axes start tens of degrees away), and the extra runs cost only where refinement would
            have failed. The default tries every start: on a nut lying flat (a planar patch of a few dozen points
            whose turn about the axis the depth hardly fixes) point-to-plane ICP diverges from some starts and
            converges from others (docs/decisions.md).
        correspondence_fractions: ICP stages: the max correspondence distance of each, x diameter (coarse to fine).
        max_iterations: ICP iterations per stage at most.
        iterations_per_call: ICP iterations per open3d call; the stage ends after a call whose last update was
            negligible (the two ``converged_`` thresholds). 1 stops at the exact iteration but costs a k-d tree
            build per iteration.
        voxel_fraction: voxel size for thinning the scene cloud, x diameter (0: no thinning).
        max_scene_points: scene points kept at most (a seeded random subset beyond that).
        mask_erosion_px: mask pixels peeled off the border first (edge depth mixes object and background).
        min_scene_points: fewer valid depth points than this: keep the initial pose.
        min_fitness: final fraction of scene points within the last correspondence distance of the model below
            this: keep the initial pose.
        max_correction_fraction: a refined centre that moved more than this x diameter: keep the initial pose.
        max_correction_deg: a refined rotation that turned more than this [deg]: keep the initial pose.
        converged_translation_fraction: an ICP update smaller than this x diameter ...
        converged_rotation_deg: ... and than this [deg] ends a stage.
    """

    model_points: int = 3000
    pca_hypotheses: bool = True
    icp_starts: int = 1
    fallback_starts: int = 4
    correspondence_fractions: tuple[float, ...] = (0.2, 0.05)
    max_iterations: int = 15
    iterations_per_call: int = 5
    voxel_fraction: float = 1.0 / 60.0
    max_scene_points: int = 1000
    mask_erosion_px: int = 1
    min_scene_points: int = 30
    min_fitness: float = 0.3
    max_correction_fraction: float = 0.5
    max_correction_deg: float = 30.0
    converged_translation_fraction: float = 1e-5
    converged_rotation_deg: float = 0.001

    def __post_init__(self) -> None:
        if self.model_points < 10:
            raise ValueError(f"RefineConfig.model_points must be >= 10, got {self.model_points}")
        if not self.correspondence_fractions or min(self.correspondence_fractions) <= 0:
            raise ValueError(
                f"RefineConfig.correspondence_fractions must be positive fractions, got {self.correspondence_fractions}"
            )
        if self.icp_starts < 1 or self.fallback_starts < 0:
            raise ValueError(
                f"RefineConfig: need icp_starts >= 1 and fallback_starts >= 0, got {self.icp_starts}, "
                f"{self.fallback_starts}"
            )
        counts_ok = self.max_iterations >= 1 and self.iterations_per_call >= 1
        if not counts_ok or self.min_scene_points < 3 or self.max_scene_points < self.min_scene_points:
            raise ValueError(
                "RefineConfig: need max_iterations >= 1, iterations_per_call >= 1 and 3 <= min_scene_points <= "
                f"max_scene_points, got {self.max_iterations}, {self.iterations_per_call}, {self.min_scene_points}, "
                f"{self.max_scene_points}"
            )
        if not 0.0 <= self.min_fitness <= 1.0 or self.voxel_fraction < 0 or self.mask_erosion_px < 0:
            raise ValueError(
                "RefineConfig: need min_fitness in [0, 1], voxel_fraction >= 0, mask_erosion_px >= 0, got "
                f"{self.min_fitness}, {self.voxel_fraction}, {self.mask_erosion_px}"
            )


@lru_cache(maxsize=64)
def model_surface(model: ObjectModel, n_points: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) surface points [m] and (n, 3) unit outward normals of ``model`` (area-uniform samples, seeded).

    Cached per (model, n_points, seed); the arrays are read-only.
    """
    points, face_index = trimesh.sample.sample_surface(model.mesh, int(n_points), seed=seed)
    normals = np.asarray(model.mesh.face_normals)[face_index]
    points, normals = np.asarray(points, dtype=np.float64), np.asarray(normals, dtype=np.float64)
    points.setflags(write=False)
    normals.setflags(write=False)
    return points, normals


def visible_model_points(
    T_camera_object: np.ndarray, points: np.ndarray, normals: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Model points and normals moved into the camera frame, keeping those that face the camera.

    A point faces the camera when its normal points against the viewing ray (camera centre at the origin):
    ``n . p < 0``. This back-face test does not remove the front faces that other parts of the same object hide.
    """
    R, t = T_camera_object[:3, :3], T_camera_object[:3, 3]
    p_cam = points @ R.T + t
    n_cam = normals @ R.T
    facing = np.einsum("ij,ij->i", p_cam, n_cam) < 0.0
    return p_cam[facing], n_cam[facing]


def masked_depth_points(
    depth_m: np.ndarray, mask: np.ndarray, intrinsics: CameraIntrinsics, erosion_px: int = 0
) -> np.ndarray:
    """(n, 3) camera-frame points [m] of the valid depth pixels inside ``mask`` (eroded by ``erosion_px``)."""
    mask = np.asarray(mask, dtype=bool)
    if erosion_px > 0:
        mask = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=erosion_px).astype(bool)
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return np.zeros((0, 3))
    # Unproject only the mask's bounding box: the crop is a camera with the principal point shifted.
    x0, x1, y0, y1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
    K = intrinsics.K.copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    crop = np.asarray(depth_m[y0:y1, x0:x1], dtype=np.float64)
    crop = np.where(np.isfinite(crop), crop, 0.0)
    points = unproject_depth(K, crop)[mask[y0:y1, x0:x1]]
    return points[np.isfinite(points[:, 2])]


@lru_cache(maxsize=64)
def _symmetries(model: ObjectModel) -> np.ndarray:
    return model.symmetry_transforms(360)


def _rotation_step_deg(R_a: np.ndarray, R_b: np.ndarray, R_frame_object: np.ndarray, axes: np.ndarray) -> float:
    """Angle [deg] between two ICP rotations (scene -> model), ignoring turns about the model's symmetry ``axes``.

    The model's pose implied by an ICP rotation ``R`` is ``R^T R_frame_object``; without continuous axes this is the
    plain angle of ``R_a^T R_b``, with them the largest angle by which an axis direction moved.
    """
    if len(axes) == 0:
        return rotation_angle_deg(R_a, R_b)
    dirs_a = (R_a.T @ R_frame_object @ axes.T).T
    dirs_b = (R_b.T @ R_frame_object @ axes.T).T
    cos = np.clip(np.einsum("ij,ij->i", dirs_a, dirs_b) / np.linalg.norm(axes, axis=1) ** 2, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)).max())


def principal_axes(points: np.ndarray) -> np.ndarray:
    """(3, 3) right-handed frame whose columns are the point set's principal directions, least variance first."""
    _, vectors = np.linalg.eigh(np.cov(np.asarray(points, dtype=np.float64).T))
    if np.linalg.det(vectors) < 0:
        vectors[:, 2] *= -1.0
    return vectors


def pca_rotations(model_points: np.ndarray, scene_points: np.ndarray) -> list[np.ndarray]:
    """The four rotations (object -> camera) that map the model's principal axes onto the depth cloud's, one per
    choice of signs. The cloud is one visible side, so its axes are only a start for ICP, not a pose."""
    E_model, E_scene = principal_axes(model_points), principal_axes(scene_points)
    signs = ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1))
    return [E_scene @ np.diag(s) @ E_model.T for s in signs]


def _better(a: dict, b: dict) -> bool:
    """Is ICP result ``a`` a better fit than ``b``: more of the depth explained, then the smaller residual."""
    if abs(a["fitness"] - b["fitness"]) > 0.02:
        return a["fitness"] > b["fitness"]
    return a["inlier_rmse_m"] < b["inlier_rmse_m"]


@dataclass(frozen=True)
class _Start:
    """One ICP start: the object pose it starts from, the centred scene and model clouds, the cloud sizes, and its
    fit before ICP (``fitness``, ``inlier_rmse_m``)."""

    T_camera_object: np.ndarray
    cloud: o3d.geometry.PointCloud
    target: o3d.geometry.PointCloud
    figures: dict
    fit: dict


def _keep(pose: ObjectPose, reason: str, info: dict) -> ObjectPose:
    log.debug("ICP kept the initial pose of obj_id %d: %s", pose.obj_id, reason)
    icp = {**info, "status": "kept_initial", "reason": reason}
    return ObjectPose(
        pose.detection, pose.T_camera_object.copy(), pose.score, pose.method, {**pose.details, "icp": icp}
    )


class DepthRefiner:
    """Refines object poses with a depth image by point-to-plane ICP (open3d). Thread-compatible, no state per call.

    Args:
        config: the settings (``RefineConfig()`` if None).
        seed: seeds the model surface samples and the scene subsampling, so a refinement is repeatable.
    """

    def __init__(self, config: RefineConfig | None = None, seed: int = 0) -> None:
        self.config = config if config is not None else RefineConfig()
        self.seed = int(seed)
        self._estimation = o3d.pipelines.registration.TransformationEstimationPointToPlane()

    def refine(
        self, pose: ObjectPose, depth_m: np.ndarray, intrinsics: CameraIntrinsics, model: ObjectModel
    ) -> ObjectPose:
        """The refined pose (``method + "+icp"``), or ``pose`` again with the reason when ICP cannot be trusted.

        Args:
            pose: the initial estimate; its detection's mask selects the depth pixels.
            depth_m: (H, W) depth in metres, 0 or non-finite = no data, in the frame of the mask.
            intrinsics: the depth camera (registered to the image the mask comes from).
            model: the object model of ``pose.obj_id``.

        Returns:
            An ``ObjectPose`` whose ``details["icp"]`` holds ``status`` ("refined" or "kept_initial"), ``reason``
            (when kept), ``fitness``, ``inlier_rmse_m``, ``iterations``, ``time_ms``, ``scene_points``,
            ``model_points`` and the correction (``correction_m``, ``correction_deg``).

        Raises:
            ValueError: the depth image, mask and intrinsics disagree in size, or ``model`` is not the pose's object.
        """
        t_start = time.perf_counter()
        cfg = self.config
        depth = np.asarray(depth_m)
        shape = (intrinsics.height, intrinsics.width)
        if depth.shape != shape:
            raise ValueError(f"depth_m: expected shape {shape} (the intrinsics' height, width), got {depth.shape}")
        if model.obj_id != pose.obj_id:
            raise ValueError(f"model: obj_id {model.obj_id} is not the pose's obj_id {pose.obj_id}")
        mask = pose.detection.mask
        info: dict = {"fitness": math.nan, "inlier_rmse_m": math.nan, "iterations": 0, "scene_points": 0}
        if mask is None:
            info["time_ms"] = (time.perf_counter() - t_start) * 1e3
            return _keep(pose, "the detection has no mask to select depth pixels", info)
        if np.shape(mask) != shape:
            raise ValueError(f"detection mask: expected shape {shape}, got {np.shape(mask)}")

        diameter = float(model.diameter_m)
        T_init = np.asarray(pose.T_camera_object, dtype=np.float64)
        scene = masked_depth_points(depth, mask, intrinsics, cfg.mask_erosion_px)
        n_masked = len(scene)
        if n_masked < cfg.min_scene_points:
            info.update(scene_points=n_masked, time_ms=(time.perf_counter() - t_start) * 1e3)
            return _keep(pose, f"{n_masked} depth points in the mask, fewer than {cfg.min_scene_points}", info)
        # Depth of other things seen through or around the mask (edge pixels, the bin floor behind a thin part)
        # cannot be the object: drop what lies farther than the diameter from the cloud's median point.
        scene = scene[np.linalg.norm(scene - np.median(scene, axis=0), axis=1) < diameter]
        if len(scene) < cfg.min_scene_points:
            info.update(scene_points=len(scene), time_ms=(time.perf_counter() - t_start) * 1e3)
            reason = (f"{len(scene)} of the {n_masked} depth points in the mask lie within one diameter of their "
                      f"median, fewer than {cfg.min_scene_points}")  # fmt: skip
            return _keep(pose, reason, info)
        points, normals = model_surface(model, cfg.model_points, self.seed)
        if len(scene) > cfg.max_scene_points * 4:  # bound the cost of a close-up part before thinning
            scene = scene[np.random.default_rng(self.seed).choice(len(scene), cfg.max_scene_points * 4, replace=False)]
        starts = [T_init[:3, :3]]
        if cfg.pca_hypotheses:
            starts += pca_rotations(points, scene)
        n_starts = len(starts)
        prepared = [p for p in (self._start(R, T_init, scene, model, points, normals) for R in starts) if p is not None]
        # rank the starts by how well they fit before any ICP; refine the best, then the next ones if refused
        prepared.sort(key=lambda p: (-round(p.fit["fitness"], 2), p.fit["inlier_rmse_m"]))
        best = None
        for start in prepared[: cfg.icp_starts]:
            candidate = self._fit(start, model)
            if best is None or _better(candidate[2], best[2]):
                best = candidate
        if best is None:
            info["time_ms"] = (time.perf_counter() - t_start) * 1e3
            return _keep(pose, "no model surface faces the camera from any start", info)
        fallbacks = prepared[cfg.icp_starts : cfg.icp_starts + cfg.fallback_starts]
        n_fallbacks = 0
        while self._refusal(best, diameter) is not None and n_fallbacks < len(fallbacks):
            candidate = self._fit(fallbacks[n_fallbacks], model)
            n_fallbacks += 1
            if self._refusal(candidate, diameter) is None:
                best = candidate
        T_start, T_refined, result_info = best
        info.update(result_info, hypotheses=n_starts, fallback_runs=n_fallbacks)
        info["start_shift_m"] = float(np.linalg.norm(T_start[:3, 3] - T_init[:3, 3]))
        info["start_turn_deg"] = symmetric_pose_errors(T_start, T_init, _symmetries(model))[0]
        info["time_ms"] = (time.perf_counter() - t_start) * 1e3
        reason = self._refusal(best, diameter)
        if reason is not None:
            return _keep(pose, reason, info)
        return ObjectPose(
            pose.detection,
            T_refined,
            pose.score,
            f"{pose.method}+icp",
            {**pose.details, "icp": {**info, "status": "refined"}},
        )

    def _refusal(self, fit: tuple[np.ndarray, np.ndarray, dict], diameter: float) -> str | None:
        """Why an ICP result (``_fit``'s) cannot be trusted, or None."""
        cfg, (_, T_refined, info) = self.config, fit
        if info["scene_points"] < cfg.min_scene_points:
            return f"{info['scene_points']} depth points after thinning, fewer than {cfg.min_scene_points}"
        if not np.all(np.isfinite(T_refined)):
            return "ICP diverged (non-finite transform)"
        if info["fitness"] < cfg.min_fitness:
            return f"ICP fitness {info['fitness']:.2f} below {cfg.min_fitness}"
        if info["correction_m"] > cfg.max_correction_fraction * diameter:
            return (f"ICP moved the object {info['correction_m'] * 1e3:.1f} mm, more than "
                    f"{cfg.max_correction_fraction} x its diameter: diverged")  # fmt: skip
        if info["correction_deg"] > cfg.max_correction_deg:
            return f"ICP turned the object {info['correction_deg']:.1f} deg, more than {cfg.max_correction_deg}"
        return None

    def _start(
        self,
        R_start: np.ndarray,
        T_init: np.ndarray,
        scene: np.ndarray,
        model: ObjectModel,
        points: np.ndarray,
        normals: np.ndarray,
    ) -> _Start | None:
        """The ICP problem from one start rotation, with the start's own fit at the widest correspondence distance
        (what the starts are ranked by), or None when no model surface faces the camera. The start is where the
        depth says the part is: the visible model surface at ``R_start`` moved to share the depth cloud's centroid
        (the estimator's translation is its weakest output, a relative depth error of a few per cent is
        centimetres at the bin, and ICP's basin is a fraction of the diameter)."""
        cfg = self.config
        diameter = float(model.diameter_m)
        T_start = make_T(R_start, T_init[:3, 3])
        p_cam, _ = visible_model_points(T_start, points, normals)
        if len(p_cam) < 3:
            return None
        T_start[:3, 3] += scene.mean(axis=0) - p_cam.mean(axis=0)
        centre = T_start[:3, 3].copy()
        # ICP runs in a frame centred on the start's object centre: open3d linearises rotations about the origin, and
        # about the camera origin a rotation about a part's symmetry axis (a direction the data cannot fix) becomes
        # a coupled rotation + translation whose ill-conditioned solve threw small symmetric parts off by centimetres.
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scene - centre))
        if cfg.voxel_fraction > 0:
            cloud = cloud.voxel_down_sample(diameter * cfg.voxel_fraction)
        if len(cloud.points) > cfg.max_scene_points:
            keep = np.random.default_rng(self.seed).choice(len(cloud.points), cfg.max_scene_points, replace=False)
            cloud = cloud.select_by_index(np.sort(keep).tolist())
        p_cam, n_cam = visible_model_points(T_start, points, normals)
        target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p_cam - centre))
        target.normals = o3d.utility.Vector3dVector(n_cam)
        figures: dict = {"scene_points": len(cloud.points), "model_points": len(p_cam)}
        if len(cloud.points) < cfg.min_scene_points:
            fit = {"fitness": 0.0, "inlier_rmse_m": math.nan}
        else:
            result = o3d.pipelines.registration.evaluate_registration(
                cloud, target, max(cfg.correspondence_fractions) * diameter
            )
            fit = {"fitness": result.fitness, "inlier_rmse_m": result.inlier_rmse}
        return _Start(T_start, cloud, target, figures, fit)

    def _fit(self, start: _Start, model: ObjectModel) -> tuple[np.ndarray, np.ndarray, dict]:
        """ICP from a prepared start: (T_start, T_refined, figures)."""
        T_start, figures = start.T_camera_object, start.figures
        if len(start.cloud.points) < self.config.min_scene_points:
            return T_start, T_start.copy(), {**figures, "fitness": 0.0, "inlier_rmse_m": math.nan, "iterations": 0,
                                             "correction_m": 0.0, "correction_deg": 0.0}  # fmt: skip
        axes = np.array([s.axis for s in model.symmetries_continuous], dtype=np.float64).reshape(-1, 3)
        diameter = float(model.diameter_m)
        T_scene_to_model, iterations, result = self._icp(start.cloud, start.target, diameter, T_start[:3, :3], axes)
        # ICP moved the (centred) scene onto the model; move the model onto the scene instead.
        T_centre = make_T(t=T_start[:3, 3])
        T_refined = T_centre @ invert(T_scene_to_model) @ invert(T_centre) @ T_start
        return (
            T_start,
            T_refined,
            {
                **figures,
                "fitness": float(result.fitness),
                "inlier_rmse_m": float(result.inlier_rmse),
                "iterations": iterations,
                # ICP's own correction from its start (what tells a diverged run)
                "correction_m": float(np.linalg.norm(T_refined[:3, 3] - T_start[:3, 3])),
                "correction_deg": symmetric_pose_errors(T_refined, T_start, _symmetries(model))[0],
            },
        )

    def _icp(
        self,
        source: o3d.geometry.PointCloud,
        target: o3d.geometry.PointCloud,
        diameter: float,
        R_frame_object: np.ndarray,
        symmetry_axes: np.ndarray,
    ) -> tuple[np.ndarray, int, o3d.pipelines.registration.RegistrationResult]:
        """Staged point-to-plane ICP of ``source`` onto ``target``; (transform, iterations, last result).

        Each open3d call runs ``iterations_per_call`` iterations, and a stage ends after the call whose update was
        negligible: open3d's legacy result does not report its iteration count and its own stopping rule does not
        know symmetry axes, and its tensor API, which does report the count, is slower on these small clouds. Not
        one iteration per call: every call builds the target's k-d tree again, which costs more than an iteration.
        For a part with continuous symmetry axes (``symmetry_axes``
        (k, 3), object frame; ``R_frame_object`` the model's rotation in the ICP frame) the rotation update is
        measured on the axes' directions only: about such an axis the data cannot pin the
        pose, open3d's unregularised solve wanders there (back and forth for ever on a washer), and that harmless
        wandering must not keep the loop running.
        """
        cfg = self.config
        T = np.eye(4)
        iterations = 0
        result = None
        for fraction in cfg.correspondence_fractions:
            distance = fraction * diameter
            done = 0
            while done < cfg.max_iterations:
                n = min(cfg.iterations_per_call, cfg.max_iterations - done)
                # relative thresholds 0: open3d runs all n iterations; the stopping rule is the one below
                criteria = o3d.pipelines.registration.ICPConvergenceCriteria(0.0, 0.0, n)
                result = o3d.pipelines.registration.registration_icp(
                    source, target, distance, T, self._estimation, criteria
                )
                T_next = np.asarray(result.transformation)
                iterations += n
                done += n
                # How far the implied object centre moved (a turn about an axis through it moves it not at all).
                step_m = float(np.linalg.norm(invert(T_next)[:3, 3] - invert(T)[:3, 3]))
                step_deg = _rotation_step_deg(T[:3, :3], T_next[:3, :3], R_frame_object, symmetry_axes)
                T = T_next
                if len(result.correspondence_set) < 3:
                    break
                if step_m < cfg.converged_translation_fraction * diameter and step_deg < cfg.converged_rotation_deg:
                    break
        # The fitness and rmse of the final transform at the finest distance.
        final = o3d.pipelines.registration.evaluate_registration(
            source, target, cfg.correspondence_fractions[-1] * diameter, T
        )
        return T, iterations, final


def refine_pose(
    pose: ObjectPose,
    depth_m: np.ndarray,
    intrinsics: CameraIntrinsics,
    model: ObjectModel,
    config: RefineConfig | None = None,
) -> ObjectPose:
    """One-call form of ``DepthRefiner(config).refine(pose, depth_m, intrinsics, model)``."""
    return DepthRefiner(config).refine(pose, depth_m, intrinsics, model)
