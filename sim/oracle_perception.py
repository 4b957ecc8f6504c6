"""``OraclePerception``: the simulated cell's ground truth dressed as a perception result — for development and for
tests of the robot side where perception is not what is tested. Never the default (``perception = "oracle"`` in a
cell file selects it).

Poses come from the emulator's ``part_poses`` hook (``T_world_obj``), mapped into the camera frame with the
camera's true pose; a part counts as seen when its centre projects into the image in front of the camera and the
depth frame there is not far in front of it (i.e. it is not fully hidden under the pile). Boxes are the projected
corners of its bounding box; no masks; score 1.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from perception.camera import Frame
from perception.results import Detection, ObjectPose
from sim.world import safe_name
from sygrid.camera import project_points
from sygrid.objects import BUILTIN_PARTS, ObjectModel, builtin_part
from sygrid.transforms import invert, transform_points
from sygrid.visualize import bounds_from_extents, box_corners_m

_HIDDEN_DEPTH_M = 0.03  # something this much in front of a part's centre along its pixel ray hides it


@dataclass
class OracleResult:
    poses: list[ObjectPose]
    detections: list[Detection]
    timings_ms: dict[str, float] = field(default_factory=dict)


class OraclePerception:
    """Ground-truth poses of the emulated cell's parts (``process``: a ``ControllerProcess``, MuJoCo backend).

    ``T_world_base``: the robot base in the world (``CellConfig.T_world_base``); ``T_base_camera``: the camera's
    true pose (the sim camera's known pose). ``models``: the scene's parts (the cell's parts are matched to them by
    name); default: the built-in parts."""

    def __init__(
        self,
        process: Any,
        T_world_base: np.ndarray,
        T_base_camera: np.ndarray,
        models: Sequence[ObjectModel] | None = None,
    ) -> None:
        self.process = process
        self.T_camera_world = invert(np.asarray(T_world_base) @ np.asarray(T_base_camera))
        if models is None:
            models = [builtin_part(name) for name in BUILTIN_PARTS]
        by_name = {safe_name(m.name): m for m in models}
        names = [name.split("_", 1)[1] for name in process.part_names()]  # bodies are part{k}_{name}
        unknown = sorted(set(names) - set(by_name))
        if unknown:
            raise ValueError(f"oracle perception: the cell's parts {unknown} are not among {sorted(by_name)}")
        self._models = [by_name[n] for n in names]

    def run(self, frame: Frame) -> OracleResult:
        K, h, w = frame.intrinsics.K, frame.intrinsics.height, frame.intrinsics.width
        poses, detections = [], []
        for k, (model, T_world_obj) in enumerate(zip(self._models, self.process.part_poses(), strict=True)):
            T_camera_obj = self.T_camera_world @ T_world_obj
            centre = T_camera_obj[:3, 3]
            if centre[2] <= 0:
                continue
            u, v = project_points(K, centre[None])[0]
            if not (0 <= u < w and 0 <= v < h):
                continue
            seen = frame.depth_m[int(v), int(u)]
            if 0 < seen < centre[2] - _HIDDEN_DEPTH_M - model.diameter_m / 2:
                continue
            corners = project_points(
                K, transform_points(T_camera_obj, box_corners_m(bounds_from_extents(model.extents_m)))
            )
            bbox = np.array([*corners.min(0), *corners.max(0)], dtype=float)
            det = Detection(class_index=k, obj_id=model.obj_id, score=1.0, bbox_xyxy=bbox)
            detections.append(det)
            poses.append(ObjectPose(T_camera_object=T_camera_obj, detection=det, score=1.0, method="oracle"))
        return OracleResult(poses, detections, {"total": 0.0})

    def refine_more(self, poses: list[ObjectPose], frame: Frame) -> list[ObjectPose] | None:
        """None: ground-truth poses have nothing left to refine (``robot.pick_protocols.PerceptionLike``)."""
        return None

    def rescue(self, poses: list[ObjectPose], frame: Frame) -> list[ObjectPose] | None:
        """None: the ground truth misses no part (``robot.pick_protocols.PerceptionLike``)."""
        return None
