"""6D pose from detections with a GDR-Net-style ONNX model (numpy + onnxruntime; no torch at run time).

Each detection's box gives a square RoI (``pad_scale`` x its longer side, as in training); the RoIs are resampled
to the network's input size and run as one batch. Two decodings of the network's outputs:

- ``"direct"``: the regressed allocentric 6D rotation and SITE, turned into ``T_camera_object`` with the camera
  intrinsics and the RoI (``sygrid.pose_geometry.decode_direct``). Score: the mean predicted mask probability over
  the cells predicted visible.
- ``"pnp"``: PnP-RANSAC (OpenCV AP3P minimal sets, then Levenberg-Marquardt on the inliers) on the predicted object
  coordinates inside the predicted mask, de-normalised to metres with the part's bounds from the model's metadata.
  Score: the mask score times the inlier fraction. Where PnP finds no pose (too few mask cells, no consensus) the
  direct pose is returned instead, with ``method="direct"`` and ``details["fallback_from"] = "pnp"`` and the reason.

The model's contract (input/output names and shapes, obj_ids, bounds, pad scale) is read from its metadata
(``sygrid.pose_geometry.POSE_METADATA_KEY``) and checked when the estimator is built, so a wrong or damaged file
fails there with a message naming it, not inside onnxruntime on the first frame.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort

from perception.providers import session_providers
from perception.results import Detection, ObjectPose
from sygrid.camera import CameraIntrinsics
from sygrid.errors import ModelError
from sygrid.objects.model import ObjectModel
from sygrid.pose_geometry import (
    POSE_INPUTS,
    POSE_METADATA_KEY,
    POSE_ONNX_FORMAT,
    POSE_OUTPUTS,
    decode_direct,
    decode_pnp,
    roi_affine,
    roi_ray_map,
    square_roi,
)

log = logging.getLogger(__name__)

METHODS = ("direct", "pnp")
BOUNDS_TOLERANCE_M = 1e-4  # a given ObjectModel must match the bounds the network was trained with


def _dims(shape: Sequence) -> list:
    """onnxruntime shape -> list with None for symbolic dimensions."""
    return [d if isinstance(d, int) else None for d in shape]


class PoseEstimator:
    """Estimates ``T_camera_object`` for detections with a pose ONNX model.

    Args:
        onnx_path: the model written by ``sygrid train pose`` (``pose.onnx``).
        models: optional ``{obj_id: ObjectModel}``; each one the model knows is checked against the bounds and
            diameter it was trained with (a different mesh would make its coordinates wrong).
        num_threads: onnxruntime intra-op threads.
        mask_threshold: probability above which an output cell counts as visible.

    Raises:
        ModelError: the file is missing or not a valid ONNX model, lacks the pose metadata, its inputs or
            outputs differ from the contract, or a given ObjectModel does not match.
    """

    def __init__(
        self,
        onnx_path: str | Path,
        models: dict[int, ObjectModel] | None = None,
        num_threads: int = 2,
        mask_threshold: float = 0.5,
    ) -> None:
        path = Path(onnx_path)
        self.path = path
        if not path.is_file():
            raise ModelError(f"{path}: pose model not found")
        options = ort.SessionOptions()
        options.intra_op_num_threads = int(num_threads)
        options.inter_op_num_threads = 1
        options.log_severity_level = 3
        # Worker threads sleep as soon as a run ends instead of spinning: the PnP decoding (OpenCV threads) runs right
        # after, and on a 2-core CPU spinning threads starve it (solvePnPRansac became tens of times slower).
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        try:
            self._session = ort.InferenceSession(str(path), options, providers=session_providers())
        except Exception as exc:  # onnxruntime raises its own pybind error types for unreadable graphs
            raise ModelError(f"{path}: not a loadable ONNX model ({type(exc).__name__}: {exc})") from exc
        self._read_metadata()
        self._check_io()
        self.mask_threshold = float(mask_threshold)
        if models:
            self._check_models(models)

    # ------------------------------------------------------------------------------------------ contract
    def _read_metadata(self) -> None:
        meta = self._session.get_modelmeta().custom_metadata_map
        if POSE_METADATA_KEY not in meta:
            raise ModelError(
                f"{self.path}: no '{POSE_METADATA_KEY}' metadata; expected a model exported by 'sygrid train pose'"
            )
        try:
            info = json.loads(meta[POSE_METADATA_KEY])
            if info.get("format") != POSE_ONNX_FORMAT:
                raise ValueError(f"format {info.get('format')!r}, expected {POSE_ONNX_FORMAT!r}")
            self.input_size = int(info["input_size"])
            self.output_size = int(info["output_size"])
            self.pad_scale = float(info["pad_scale"])
            self.num_regions = int(info["num_regions"])
            self.obj_ids: tuple[int, ...] = tuple(int(i) for i in info["obj_ids"])
            self.names: tuple[str, ...] = tuple(str(n) for n in info.get("names", [str(i) for i in self.obj_ids]))
            self.bounds_m = {i: np.asarray(info["objects"][str(i)]["bounds_m"], dtype=np.float64) for i in self.obj_ids}
            self.diameter_m = {i: float(info["objects"][str(i)]["diameter_m"]) for i in self.obj_ids}
        except (ValueError, KeyError, TypeError) as exc:
            raise ModelError(f"{self.path}: invalid '{POSE_METADATA_KEY}' metadata: {exc}") from exc
        for obj_id, b in self.bounds_m.items():
            if b.shape != (2, 3) or not np.all(b[1] > b[0]):
                raise ModelError(f"{self.path}: metadata bounds_m of obj_id {obj_id} must be (2, 3) with max > min")

    def _check_io(self) -> None:
        S, s, C, R = self.input_size, self.output_size, len(self.obj_ids), self.num_regions
        expected_in = {"image": [None, 3, S, S], "coord2d": [None, 2, s, s], "class_onehot": [None, C]}
        expected_out = {
            "xyz": [None, 3, s, s], "mask": [None, 1, s, s], "region": [None, R, s, s], "rot6d": [None, 6],
            "site": [None, 3],
        }  # fmt: skip
        for kind, got, expected in (
            ("inputs", self._session.get_inputs(), expected_in),
            ("outputs", self._session.get_outputs(), expected_out),
        ):
            shapes = {a.name: _dims(a.shape) for a in got}
            for name, shape in expected.items():
                have = shapes.get(name)
                if (
                    have is None
                    or len(have) != len(shape)
                    or any(e is not None and h is not None and e != h for e, h in zip(shape, have, strict=True))
                ):
                    raise ModelError(
                        f"{self.path}: {kind} {shapes} do not match the pose contract "
                        f"{ {k: ['B', *v[1:]] for k, v in expected.items()} } (missing or different: {name!r})"
                    )

    def _check_models(self, models: dict[int, ObjectModel]) -> None:
        for obj_id in self.obj_ids:
            model = models.get(obj_id)
            if model is None:
                continue
            if not np.allclose(model.bounds_m, self.bounds_m[obj_id], atol=BOUNDS_TOLERANCE_M):
                raise ModelError(
                    f"{self.path}: obj_id {obj_id} was trained with bounds {self.bounds_m[obj_id].tolist()} m, the "
                    f"given model {model.name!r} has {model.bounds_m.tolist()} m: a different mesh"
                )

    # ------------------------------------------------------------------------------------------ inference
    def infer(
        self, rgb: np.ndarray, boxes_xyxy: np.ndarray, obj_ids: Sequence[int], intrinsics: CameraIntrinsics
    ) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """Runs the network on the RoIs of ``boxes_xyxy`` (n, 4); returns the outputs by name and the RoIs (n, 3)
        as centre x, y and size in pixels."""
        S, s = self.input_size, self.output_size
        n = len(boxes_xyxy)
        images = np.empty((n, S, S, 3), dtype=np.uint8)
        coord2d = np.empty((n, 2, s, s), dtype=np.float32)
        onehot = np.zeros((n, len(self.obj_ids)), dtype=np.float32)
        rois = np.empty((n, 3))
        K = intrinsics.K
        for i, (box, obj_id) in enumerate(zip(boxes_xyxy, obj_ids, strict=True)):
            centre, size = square_roi(box, self.pad_scale)
            rois[i] = (centre[0], centre[1], size)
            images[i] = cv2.warpAffine(
                rgb, roi_affine(centre, size, S), (S, S), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
            )
            coord2d[i] = roi_ray_map(centre, size, s, K)
            onehot[i, self.obj_ids.index(int(obj_id))] = 1.0
        feeds = {
            "image": np.ascontiguousarray(images.transpose(0, 3, 1, 2), dtype=np.float32) / np.float32(255.0),
            "coord2d": coord2d,
            "class_onehot": onehot,
        }
        outputs = self._session.run(list(POSE_OUTPUTS), {name: feeds[name] for name in POSE_INPUTS})
        return dict(zip(POSE_OUTPUTS, outputs, strict=True)), rois

    def estimate(
        self,
        rgb: np.ndarray,
        detections: Sequence[Detection],
        intrinsics: CameraIntrinsics,
        method: str = "direct",
    ) -> list[ObjectPose]:
        """One ``ObjectPose`` per detection of a part the model knows, in the order given.

        Detections of other parts are skipped with a warning; an empty list gives an empty list.

        Raises:
            ValueError: unknown ``method``, or ``rgb`` is not a uint8 (height, width, 3) image of the camera's size.
        """
        if method not in METHODS:
            raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
        shape = (intrinsics.height, intrinsics.width, 3)
        rgb = np.asarray(rgb)
        if rgb.shape != shape or rgb.dtype != np.uint8:
            raise ValueError(
                f"rgb: expected a uint8 array of shape {shape} (the intrinsics' size), got {rgb.dtype} {rgb.shape}"
            )
        known = [d for d in detections if d.obj_id in self.obj_ids]
        for d in detections:
            if d.obj_id not in self.obj_ids:
                log.warning("%s: no pose for obj_id %d (the model knows %s)", self.path.name, d.obj_id, self.obj_ids)
        if not known:
            return []
        t0 = time.perf_counter()
        out, rois = self.infer(rgb, np.stack([d.bbox_xyxy for d in known]), [d.obj_id for d in known], intrinsics)
        infer_s = time.perf_counter() - t0
        K = intrinsics.K
        poses = []
        for i, det in enumerate(known):
            centre, size = rois[i, :2], float(rois[i, 2])
            mask = out["mask"][i, 0]
            visible = mask > self.mask_threshold
            mask_score = float(mask[visible].mean()) if visible.any() else 0.0
            details: dict = {"roi": rois[i].tolist(), "mask_cells": int(visible.sum()), "batch_infer_s": infer_s}
            try:
                T_direct = decode_direct(out["rot6d"][i], out["site"][i], centre, size, K, self.diameter_m[det.obj_id])
            except ValueError as exc:
                log.warning("%s: no pose for a detection of obj_id %d: %s", self.path.name, det.obj_id, exc)
                continue
            if method == "direct":
                poses.append(ObjectPose(det, T_direct, mask_score, "direct", details))
                continue
            sol = decode_pnp(
                out["xyz"][i], mask, centre, size, K, self.bounds_m[det.obj_id], mask_threshold=self.mask_threshold
            )
            if sol is None:
                details.update(fallback_from="pnp", reason=f"PnP found no pose from {int(visible.sum())} mask cells")
                poses.append(ObjectPose(det, T_direct, mask_score, "direct", details))
                continue
            details.update(n_points=sol.n_points, n_inliers=sol.n_inliers)
            score = mask_score * sol.n_inliers / max(sol.n_points, 1)
            poses.append(ObjectPose(det, sol.T_camera_object, score, "pnp", details))
        return poses
