"""The perception pipeline: a frame (RGB, depth, intrinsics) -> detections -> 6D poses (+ depth refinement).

Loaded from a model folder whose ``manifest.json`` names the files and settings::

    {"format": "sygrid-models/1",
     "objects": [{"builtin": "hex_nut"}, {"file": "cad/bracket.ply", "unit": "mm", "obj_id": 12}],
     "detector": {"onnx": "detector.onnx", "conf_threshold": 0.4},
     "pose": {"onnx": "pose.onnx", "method": "direct",
              "strategies": {"hex_nut": "depth+icp", "bracket": "hybrid+search"}},
     "verify": {"min_confidence": 0.9},
     "depth_tare": {"enabled": true},
     "refine": {"enabled": true}}

``objects`` uses the scene description's object entries (paths relative to the folder); with a top-level
``"catalogue"`` (a ``sygrid.catalogue`` file, relative to the folder, as a scene's is to the scene file) they may
name its parts (``{"catalogue_part": "strap_clamp"}``), so the folder's ids and names come from the catalogue the
models were trained with (``sygrid models pack --catalogue``). Its parts are resolved where a scene's are
(``sygrid.drop.resolve_parts``), and the detector's classes must agree with them by obj_id and name. The detector gives
classes, boxes and masks. With ``pose.strategies`` (a strategy per object name, ``perception.pose_strategies``,
written by ``sygrid models choose-pose``), each detection's pose comes from its part's strategy: the pose network
runs only for the detections whose strategy uses it, every pose is verified against the depth and mask
(``perception.verify``, accepted from ``verify.min_confidence`` or the part's own ``verify.part_min_confidence``),
and the refused ones are kept apart (``PerceptionResult.refused``). Without it, the pose model gives a pose per
detection of a part it knows and the refiner (point-to-plane ICP against the depth inside the mask) a refined pose
where it can be trusted. Any stage can be overridden by the caller (``PipelineOverrides``; a pose method or
refinement override runs the network and refiner path), which is how the benchmark sweeps input sizes and methods.

A cell knows where parts can be (the bin), so the pipeline can be given that region as 3D points in the camera
frame; the detector then looks only at their image box (``region_of_interest``), at the scale it would see the
whole frame at: same parts found, at the region's share of the cost. It can also be given the plane of the bin's
floor: the refinement then ignores depth pixels on the floor (the strategies' mask clean-up takes it as the
support, else finds the surface around each part, ``perception.mask_cleanup``). A detection mask at this scale is
a filled blob, so a nut's mask takes in the floor seen through its hole, which pulled ICP towards a nut standing on
edge; no part surface lies on the floor plane itself.

With the floor plane, a stereo camera's per-frame depth offset is measured on the floor and taken out of the depth
before anything uses it (``perception.depth_tare``, manifest ``depth_tare``, on by default), inside the floor's
polygon: the region's points (the bin's corners) projected onto the floor, or ``floor_bounds_camera_m``. The
estimate is in ``PerceptionResult.depth_tare``. When the frames come through a sensor model (``from_folder``'s
``sensor``, ``use_sensor``), the verification allows at least that sensor's depth noise (``VerifyConfig.for_sensor``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from perception.blob_rescue import (
    RescueConfig,
    best_verified,
    explained_mask,
    outline_from_image,
    pile_blobs,
)
from perception.camera import Frame
from perception.depth_tare import Tare, TareConfig, tared_depth
from perception.detector import YoloSegDetector
from perception.manifest import (
    MANIFEST_NAME,
    DetectorEntry,
    check_detector_parts,
    load_manifest,
    manifest_models,
    strategy_ids,
    tare_config,
)
from perception.pose import PoseEstimator
from perception.pose_strategies import NETWORK_STRATEGIES, StrategyRunner
from perception.refine import DepthRefiner, RefineConfig
from perception.results import Detection, ObjectPose
from perception.tiling import ViewSettings
from perception.verify import PoseVerifier
from sygrid.camera import CameraIntrinsics, project_points
from sygrid.errors import ConfigError
from sygrid.objects.model import ObjectModel
from sygrid.sensor import SensorModel

# Pixels added around a region's box: a part on the rim or leaning out over it still has its whole box inside,
# and the detector sees some of the context it was trained with around the parts.
REGION_MARGIN_PX = 8
# Depth this close to the floor plane is the floor: the sim camera's depth is exact and a calibration within 2 mm
# and 0.3 deg (robot.calibration's target) tilts the plane by ~1 mm over the bin; the thinnest part lying flat (a
# 3 mm washer) stays above it. A noisy stereo camera needs a wider margin (``[perception] floor_margin_m``).
FLOOR_MARGIN_M = 0.0015


@dataclass(frozen=True)
class PipelineOverrides:
    """Settings a caller may change without editing the manifest (None keeps the manifest's)."""

    detector_input_size: int | None = None
    conf_threshold: float | None = None
    pose_method: str | None = None
    refine: bool | None = None
    max_refined: int | None = None
    min_fitness: float | None = None  # the refinement's acceptance (perception.refine.RefineConfig.min_fitness)
    mask_erosion_px: int | None = None  # perception.refine.RefineConfig.mask_erosion_px
    num_threads: int = 2
    detector_scale: float | None = None  # perception.tiling.ViewSettings.scale
    detector_tile_px: int | None = None  # perception.tiling.ViewSettings.tile_px (0: no tiles)
    depth_tare: bool | None = None  # the depth tare on the floor (perception.depth_tare) on or off


@dataclass
class PerceptionResult:
    """Poses of the parts found in one frame, best score first, with the detections and stage timings (ms).

    ``refused``: the poses the verification refused (the model at the fitted pose disagrees with the depth and
    mask: a wrong pose or a wrong class), kept out of ``poses`` so that nothing picks them; empty without pose
    strategies (no verification). ``depth_tare``: the stereo offset measured on the floor and taken out of the depth
    (``perception.depth_tare``; its ``applied`` False with the reason where it could not be measured); None without
    a floor plane or with the tare off."""

    poses: list[ObjectPose]
    detections: list[Detection]
    timings_ms: dict[str, float] = field(default_factory=dict)
    refused: list[ObjectPose] = field(default_factory=list)
    depth_tare: Tare | None = None


class PerceptionPipeline:
    """Detector + pose estimator + optional depth refiner over a set of object models."""

    def __init__(
        self,
        detector: YoloSegDetector,
        pose: PoseEstimator,
        models: dict[int, ObjectModel],
        refiner: DepthRefiner | None = None,
        pose_method: str = "direct",
        min_mask_px: int = 30,
        max_refined: int | None = None,
        region_camera_m: np.ndarray | None = None,
        floor_plane_camera: np.ndarray | None = None,
        floor_margin_m: float = FLOOR_MARGIN_M,
        strategies: dict[int, str] | None = None,
        runner: StrategyRunner | None = None,
        depth_tare: TareConfig | None = None,
        floor_bounds_camera_m: np.ndarray | None = None,
    ) -> None:
        """``strategies``: obj_id -> pose strategy (``perception.pose_strategies``), run by ``runner``; the network
        runs only for the detections whose strategy uses it, and every pose is verified. None: the network's pose
        refined by ``refiner`` (no verification).
        ``max_refined``: stop refining once this many poses are refined, nearest parts (top of the pile) first;
        the rest keep their RGB estimate with ``details["icp"]["status"] == "skipped"``. None refines every pose.
        ``region_camera_m``: (n, 3) points in the camera frame (metres) that bound where parts can be, e.g. a bin's
        inner corners at its floor and rim; the detector looks only inside their image box. None: the whole frame.
        ``floor_plane_camera``: ``(a, b, c, d)`` the floor the parts lie on, in the camera frame (see
        ``without_floor``); depth less than ``floor_margin_m`` above it is not used for refinement. None: all depth.
        ``depth_tare``: with a floor plane, each frame's depth is corrected by the stereo offset measured on the floor
        (``perception.depth_tare``) inside the polygon of ``floor_bounds_camera_m`` ((n, 3) camera-frame points
        bounding the floor, e.g. the bin's inner corners; None: ``region_camera_m``; neither: no tare, since the plane
        reaches beyond the bin where a table or the ground lies lower). None: no tare.
        """
        if max_refined is not None and max_refined < 1:
            raise ConfigError(f"PerceptionPipeline: max_refined must be >= 1 or None, got {max_refined}")
        self.detector, self.pose, self.models, self.refiner = detector, pose, models, refiner
        self.pose_method = pose_method
        self.min_mask_px = min_mask_px
        self.max_refined = max_refined
        self.region_camera_m = _camera_points(region_camera_m, "region_camera_m")
        self.floor_bounds_camera_m = _camera_points(floor_bounds_camera_m, "floor_bounds_camera_m")
        self.depth_tare = depth_tare
        self.floor_plane_camera = None
        if floor_plane_camera is not None:
            plane = np.asarray(floor_plane_camera, dtype=float)
            if plane.shape != (4,) or not np.isfinite(plane).all() or abs(np.linalg.norm(plane[:3]) - 1.0) > 1e-6:
                raise ConfigError(
                    "PerceptionPipeline: floor_plane_camera must be (a, b, c, d) with (a, b, c) a unit normal, got "
                    f"{np.asarray(floor_plane_camera).tolist()}"
                )
            self.floor_plane_camera = plane
        if not 0.0 <= floor_margin_m < 0.05:
            raise ConfigError(f"PerceptionPipeline: floor_margin_m must be in [0, 0.05) m, got {floor_margin_m}")
        self.floor_margin_m = float(floor_margin_m)
        if strategies is not None and set(strategies) != set(models):
            raise ConfigError(
                f"PerceptionPipeline: strategies must name every model's obj_id {sorted(models)}, got "
                f"{sorted(strategies)}"
            )
        self.strategies = strategies
        self.runner = runner if runner is not None or strategies is None else StrategyRunner()
        # the verification's and the tare's settings without a sensor's (use_sensor starts from these)
        self._verify_config = self.runner.verifier.config if self.runner is not None else None
        self._tare_config = depth_tare

    @classmethod
    def from_folder(
        cls,
        folder: str | Path,
        overrides: PipelineOverrides | None = None,
        region_camera_m: np.ndarray | None = None,
        floor_plane_camera: np.ndarray | None = None,
        floor_margin_m: float | None = None,
        sensor: SensorModel | None = None,
        floor_bounds_camera_m: np.ndarray | None = None,
    ) -> PerceptionPipeline:
        """Loads the manifest's models; errors name the folder's files and fields. ``floor_margin_m`` None: the
        default (``FLOOR_MARGIN_M``). ``sensor``: the sensor model the frames come through (a simulated camera's),
        for the verification's noise allowance (``use_sensor``); None: the manifest's allowance as it is."""
        folder = Path(folder)
        o = overrides or PipelineOverrides()
        manifest = load_manifest(folder)
        models = manifest_models(folder, manifest)
        d = manifest.detector
        detector = YoloSegDetector(
            folder / d.onnx,
            conf_threshold=o.conf_threshold or d.conf_threshold,
            iou_threshold=d.iou_threshold,
            input_size=o.detector_input_size or d.input_size,
            num_threads=o.num_threads,
            view=detector_view(d, o),
        )
        check_detector_parts(detector, models, folder / d.onnx)
        pose = PoseEstimator(folder / manifest.pose.onnx, models=models, num_threads=o.num_threads)
        refine = manifest.refine.enabled if o.refine is None else o.refine
        strategies, runner = None, None
        if manifest.pose.strategies is not None and o.pose_method is None and o.refine is None:
            strategies = strategy_ids(manifest.pose.strategies, models, folder / MANIFEST_NAME)
            manifest.verify.thresholds(models, folder / MANIFEST_NAME)  # every part it names is one of the objects
            verifier = PoseVerifier(manifest.verify.config())
            runner = StrategyRunner(verifier=verifier, config=manifest.pose.search_config())
        pipeline = cls(
            detector,
            pose,
            models,
            DepthRefiner(_refine_config(o)) if refine else None,
            pose_method=o.pose_method or manifest.pose.method,
            min_mask_px=manifest.min_mask_px,
            max_refined=o.max_refined or manifest.refine.max_refined,
            region_camera_m=region_camera_m,
            floor_plane_camera=floor_plane_camera,
            floor_margin_m=FLOOR_MARGIN_M if floor_margin_m is None else floor_margin_m,
            strategies=strategies,
            runner=runner,
            depth_tare=tare_config(manifest.depth_tare, o.depth_tare),
            floor_bounds_camera_m=floor_bounds_camera_m,
        )
        if sensor is not None:
            pipeline.use_sensor(sensor)
        return pipeline

    def use_sensor(self, sensor: SensorModel) -> None:
        """The frames come through ``sensor`` from now on: the verification allows at least its depth noise
        (``VerifyConfig.for_sensor`` of the pipeline's own settings, not of an earlier sensor's; without pose
        strategies there is no verification) and the depth tare knows its disparity step (``TareConfig.for_sensor``)."""
        if self.runner is not None and self._verify_config is not None:
            self.runner.verifier = PoseVerifier(self._verify_config.for_sensor(sensor))
        if self._tare_config is not None:
            self.depth_tare = self._tare_config.for_sensor(sensor)

    def tare(self, frame: Frame) -> tuple[Frame, Tare | None]:
        """``frame`` with its depth corrected by the stereo offset measured on the floor (``depth_tare``), and the
        estimate; ``(frame, None)`` without a floor plane, floor bounds or tare config."""
        depth, tare = tared_depth(
            frame.depth_m, frame.intrinsics, self.floor_plane_camera, self._floor_bounds, self.depth_tare
        )
        if tare is None or not tare.applied:
            return frame, tare
        return replace(frame, depth_m=depth), tare

    def poseable(self, detections: list[Detection]) -> list[Detection]:
        """The detections a pose is estimated for: of a part the pipeline has a model of, and not a sliver (too few
        mask pixels for the RoI or the depth fit)."""
        return [
            d for d in detections if d.obj_id in self.models and (d.mask is None or d.mask.sum() >= self.min_mask_px)
        ]

    def run(self, frame: Frame) -> PerceptionResult:
        """Detects, estimates and (optionally) refines every part in ``frame``; an empty frame gives no poses. With a
        floor plane and the depth tare, the depth is corrected first (``tare``; ``timings_ms["tare"]``)."""
        timings: dict[str, float] = {}
        t = time.perf_counter()
        frame, tare = self.tare(frame)
        if tare is not None:
            timings["tare"] = 1e3 * (time.perf_counter() - t)
            t = time.perf_counter()
        roi = None
        if self.region_camera_m is not None:
            roi = region_of_interest(self.region_camera_m, frame.intrinsics)
            if roi is None:  # a wrong calibration or bin pose, not an empty bin
                raise ConfigError(
                    f"PerceptionPipeline: the region of interest (the bin) lies outside the {frame.intrinsics.width}x"
                    f"{frame.intrinsics.height} image; check the camera calibration and the bin's pose"
                )
        detections = self.detector.detect(frame.rgb, roi)
        timings["detect"] = 1e3 * (time.perf_counter() - t)
        usable = self.poseable(detections)
        if self.strategies is not None:
            result = self._run_strategies(frame, detections, usable, timings)
            result.depth_tare = tare
            return result
        t = time.perf_counter()
        poses = self.pose.estimate(frame.rgb, usable, frame.intrinsics, method=self.pose_method)
        timings["pose"] = 1e3 * (time.perf_counter() - t)
        t = time.perf_counter()
        if self.refiner is not None:
            poses = self._refine(poses, frame)
        timings["refine"] = 1e3 * (time.perf_counter() - t)
        timings["total"] = sum(timings.values())
        poses.sort(key=lambda p: -p.score)
        return PerceptionResult(poses, detections, timings, depth_tare=tare)

    def refine_more(self, poses: list[ObjectPose], frame: Frame) -> list[ObjectPose] | None:
        """``poses`` with the next ``max_refined`` of those ``run`` skipped refined (nearest first), for a caller
        that found nothing to do with the refined ones; None when none was skipped. With pose strategies, the
        skipped parts are fitted, and those the verification refuses are left out. ``frame``: the one given to
        ``run`` (its depth is corrected again, as there)."""
        if not any(_icp_status(p) == "skipped" for p in poses):
            return None
        frame, _ = self.tare(frame)
        if self.strategies is not None:
            skipped = [p for p in poses if _icp_status(p) == "skipped"]
            kept = [p for p in poses if _icp_status(p) != "skipped"]
            detections = [p.detection for p in skipped]
            fitted = self._fit(frame, detections, self._network_poses(frame, detections))
            return sorted(kept + [p for p in fitted if p.verified is not False], key=lambda p: -p.score)
        if self.refiner is None:
            return None
        refined = self._refine(poses, frame, todo=lambda p: _icp_status(p) == "skipped")
        return sorted(refined, key=lambda p: -p.score)

    def rescue(self, poses: list[ObjectPose], frame: Frame) -> list[ObjectPose] | None:
        """``poses`` with the parts the detector's classes missed (``perception.blob_rescue``): the pile's regions of
        depth that no pose in ``poses`` explains, each fitted with every model's strategy and kept where the
        verification accepts one (the most confident), best score first; None when nothing new was found, or
        without pose strategies (no verification), a floor plane or floor bounds. ``frame``: the one given to
        ``run`` (its depth is corrected again, as there)."""
        bounds = self._floor_bounds
        if self.strategies is None or self.floor_plane_camera is None or bounds is None:
            return None
        frame, _ = self.tare(frame)
        explained = explained_mask(poses, frame.depth_m.shape)
        found = []
        config = RescueConfig(min_height_m=max(self.floor_margin_m, 1e-4))
        # the sensor's depth noise (``TareConfig.for_sensor``: 1/z's sigma), 0 for exact depth or an unknown sensor
        sigma_inv = self.depth_tare.noise_inv_m if self.depth_tare is not None else None
        regions = pile_blobs(
            frame.depth_m, frame.intrinsics, self.floor_plane_camera, bounds, explained, config, sigma_inv or 0.0
        )
        for region in regions:
            mask = outline_from_image(frame.rgb, region, config.outline_ring_px)
            # no detector saw it: score 0
            detections = [Detection.from_mask(mask, i, 0.0, self._class_index(i)) for i in self.models]
            network = self._network_poses(frame, detections)
            fits = [self._fit_one(frame, d, network) for d in detections]
            best = best_verified(fits)
            if best is not None:
                runner_up = max((f.score for f in fits if f is not None and f is not best), default=0.0)
                best.details["rescued"] = {
                    "region_px": int(region.sum()), "outline_px": int(mask.sum()), "models_tried": len(detections),
                    "runner_up": float(runner_up),
                }  # fmt: skip
                found.append(best)
        if not found:
            return None
        return sorted([*poses, *found], key=lambda p: -p.score)

    def _run_strategies(
        self, frame: Frame, detections: list[Detection], usable: list[Detection], timings: dict[str, float]
    ) -> PerceptionResult:
        """``run`` with pose strategies: the network for the detections whose strategy uses it, then every
        detection's strategy (nearest first, ``max_refined``), the refused poses apart."""
        assert self.strategies is not None
        t = time.perf_counter()
        network = self._network_poses(frame, usable)
        timings["pose"] = 1e3 * (time.perf_counter() - t)
        t = time.perf_counter()
        poses = self._fit(frame, usable, network)
        timings["refine"] = 1e3 * (time.perf_counter() - t)
        timings["total"] = sum(timings.values())
        accepted = sorted((p for p in poses if p.verified is not False), key=lambda p: -p.score)
        refused = sorted((p for p in poses if p.verified is False), key=lambda p: -p.score)
        return PerceptionResult(accepted, detections, timings, refused)

    def _network_poses(self, frame: Frame, detections: list[Detection]) -> dict[int, ObjectPose]:
        """The pose network's estimates, by ``id`` of their detection, of the detections whose strategy starts
        from it (``NETWORK_STRATEGIES``); the others are not run through the network."""
        assert self.strategies is not None
        need = [d for d in detections if self.strategies[d.obj_id] in NETWORK_STRATEGIES]
        return {id(p.detection): p for p in self.pose.estimate(frame.rgb, need, frame.intrinsics)} if need else {}

    def _fit(self, frame: Frame, detections: list[Detection], network: dict[int, ObjectPose]) -> list[ObjectPose]:
        """Each detection's strategy, nearest first; past ``max_refined`` accepted fits, the rest are ``skipped``
        (a placeholder at the mask's depth, for ``refine_more``). A detection whose strategy finds nothing to fit
        (no mask, too few depth points) gives no pose."""
        assert self.strategies is not None and self.runner is not None
        out: list[ObjectPose] = []
        n_fitted = 0
        for det in sorted(detections, key=lambda d: _mask_depth(d, frame.depth_m, math.inf)):
            if self.max_refined is not None and n_fitted >= self.max_refined:
                out.append(_skipped(det, frame, self.strategies[det.obj_id], self.max_refined))
                continue
            pose = self._fit_one(frame, det, network)
            if pose is not None:
                out.append(pose)
                n_fitted += bool(pose.verified)
        return out

    @property
    def _floor_bounds(self) -> np.ndarray | None:
        """The points bounding the floor (the tare's and the rescue's polygon): ``floor_bounds_camera_m``, else
        ``region_camera_m``."""
        return self.floor_bounds_camera_m if self.floor_bounds_camera_m is not None else self.region_camera_m

    def _fit_one(self, frame: Frame, det: Detection, network: dict[int, ObjectPose]) -> ObjectPose | None:
        """One detection's pose by its part's strategy (verified), None when there is nothing to fit."""
        assert self.strategies is not None and self.runner is not None
        return self.runner.estimate(
            self.strategies[det.obj_id], det, frame.depth_m, frame.intrinsics, self.models[det.obj_id],
            network.get(id(det)), self.floor_plane_camera,
        )  # fmt: skip

    def _class_index(self, obj_id: int) -> int:
        """The detector's class index of ``obj_id`` (-1 for a part the detector has no class for)."""
        ids = list(self.detector.class_obj_ids)
        return ids.index(obj_id) if obj_id in ids else -1

    def _refine(
        self, poses: list[ObjectPose], frame: Frame, todo: Callable[[ObjectPose], bool] = lambda p: True
    ) -> list[ObjectPose]:
        """Refines the poses ``todo`` selects, nearest first: a picking cell takes parts from the top of the pile,
        so with ``max_refined`` the ICP time (the costliest stage per part) goes to the parts a grasp planner
        chooses from. The others keep their RGB estimate, marked ``skipped``."""
        assert self.refiner is not None
        depth_m = frame.depth_m
        if self.floor_plane_camera is not None:
            depth_m = without_floor(depth_m, frame.intrinsics, self.floor_plane_camera, self.floor_margin_m)
        out: list[ObjectPose] = []
        n_refined = 0
        for pose in sorted(poses, key=lambda p: _median_depth(p, frame.depth_m)):
            if not todo(pose):
                out.append(pose)
            elif self.max_refined is not None and n_refined >= self.max_refined:
                icp = {"status": "skipped", "reason": f"{self.max_refined} nearer parts were refined (max_refined)"}
                out.append(ObjectPose(pose.detection, pose.T_camera_object, pose.score, pose.method,
                                      {**pose.details, "icp": icp}))  # fmt: skip
            else:
                out.append(self.refiner.refine(pose, depth_m, frame.intrinsics, self.models[pose.obj_id]))
                n_refined += _icp_status(out[-1]) == "refined"
        return out


def detector_view(entry: DetectorEntry, overrides: PipelineOverrides) -> ViewSettings:
    """The detector's view: the overrides' scale and tiles where given, else the manifest's."""
    tile_px = entry.tile_px if overrides.detector_tile_px is None else (overrides.detector_tile_px or None)
    return ViewSettings(overrides.detector_scale or entry.scale, tile_px, entry.tile_overlap)


def region_of_interest(
    points_camera_m: np.ndarray, intrinsics: CameraIntrinsics, margin_px: int = REGION_MARGIN_PX
) -> tuple[int, int, int, int] | None:
    """The integer pixel box ``[x0, y0, x1, y1]`` around the points' projections, ``margin_px`` wider on each side
    and clipped to the image; None when none of it is in the image."""
    uv = project_points(intrinsics.K, np.asarray(points_camera_m, dtype=float))
    x0, y0 = np.floor(uv.min(axis=0)).astype(int) - margin_px
    x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + margin_px
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, intrinsics.width), min(y1, intrinsics.height)
    return (int(x0), int(y0), int(x1), int(y1)) if x1 > x0 and y1 > y0 else None


def without_floor(
    depth_m: np.ndarray, intrinsics: CameraIntrinsics, floor_plane_camera: np.ndarray, margin_m: float
) -> np.ndarray:
    """A copy of ``depth_m`` with the pixels that see the floor (less than ``margin_m`` above the plane, or below
    it) set to 0 (no data), same dtype. ``floor_plane_camera``: ``(a, b, c, d)``; a camera-frame point p lies
    ``(a, b, c) . p + d`` above the floor, ``(a, b, c)`` the unit normal pointing up, out of the floor."""
    depth = np.asarray(depth_m, dtype=np.float64)
    h, w = depth.shape
    K = intrinsics.K
    normal, offset = np.asarray(floor_plane_camera[:3], dtype=float), float(floor_plane_camera[3])
    # height = z * (n . ray(u, v)) + d, the ray with unit depth through the pixel. Not sygrid.camera.unproject_depth
    # and a dot product: the ray term is separable in u and v, and this runs on every frame (an order of magnitude
    # cheaper than unprojecting every pixel).
    along_u = normal[0] * (np.arange(w) - K[0, 2]) / K[0, 0]
    along_v = normal[1] * (np.arange(h) - K[1, 2]) / K[1, 1]
    height = depth * (along_v[:, None] + along_u[None, :] + normal[2]) + offset
    on_floor = np.isfinite(depth) & (depth > 0) & (height < margin_m)
    return np.where(on_floor, 0, depth_m).astype(np.asarray(depth_m).dtype)


def _camera_points(points: np.ndarray | None, name: str) -> np.ndarray | None:
    """``points`` as an (n, 3) float array of points in front of the camera; None stays None."""
    if points is None:
        return None
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 1 or not (p[:, 2] > 0).all():
        raise ConfigError(f"PerceptionPipeline: {name} must be (n, 3) points in front of the camera (z > 0), got "
                          f"{p.tolist()}")  # fmt: skip
    return p


def _refine_config(overrides: PipelineOverrides) -> RefineConfig:
    """``RefineConfig``'s defaults with the overrides' refinement settings that are given."""
    given = {"min_fitness": overrides.min_fitness, "mask_erosion_px": overrides.mask_erosion_px}
    return RefineConfig(**{name: value for name, value in given.items() if value is not None})


def _icp_status(pose: ObjectPose) -> str | None:
    return pose.details.get("icp", {}).get("status")


def _median_depth(pose: ObjectPose, depth_m: np.ndarray) -> float:
    """The median measured depth (m) inside the pose's mask; the estimate's own depth where the mask has none."""
    return _mask_depth(pose.detection, depth_m, float(pose.T_camera_object[2, 3]))


def _mask_depth(detection: Detection, depth_m: np.ndarray, default: float) -> float:
    """The median measured depth (m) inside the detection's mask; ``default`` where the mask has none."""
    mask = detection.mask
    if mask is not None and mask.shape == depth_m.shape:
        z = depth_m[mask]
        z = z[np.isfinite(z) & (z > 0)]
        if len(z):
            return float(np.median(z))
    return default


def _skipped(detection: Detection, frame: Frame, strategy: str, max_refined: int) -> ObjectPose:
    """A placeholder for a detection not fitted (``max_refined``): no rotation, at the mask's median depth along
    the ray through its box centre; ``details["icp"]["status"] == "skipped"``, so the grasp planner takes it
    for unrefined."""
    z = _mask_depth(detection, frame.depth_m, 0.0)
    x0, y0, x1, y1 = np.asarray(detection.bbox_xyxy, dtype=float)
    K = frame.intrinsics
    T = np.eye(4)
    T[:3, 3] = ((0.5 * (x0 + x1) - K.cx) * z / K.fx, (0.5 * (y0 + y1) - K.cy) * z / K.fy, z)
    icp = {"status": "skipped", "reason": f"{max_refined} nearer parts were fitted (max_refined)"}
    return ObjectPose(detection, T, 0.0, strategy, {"strategy": strategy, "icp": icp})
