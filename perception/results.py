"""What the perception runtime returns: 2D detections and 6D object poses.

Every stage (detector, pose estimator, depth refinement, the pipeline) exchanges these; the grasp planner and the
picker read them. Pixels are in the original image (not the network input), poses are 4x4 ``T_camera_object`` in
metres (OpenCV camera frame: x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, eq=False)
class Detection:
    """One detected part instance.

    class_index: index into the detector's class list. obj_id: the BOP object id of that class.
    bbox_xyxy: (4,) float64 ``[x0, y0, x1, y1]`` pixels. mask: (H, W) bool instance mask, None for a
    detection-only model.
    """

    class_index: int
    obj_id: int
    score: float
    bbox_xyxy: np.ndarray
    mask: np.ndarray | None = None

    def __post_init__(self) -> None:
        if np.shape(self.bbox_xyxy) != (4,):
            raise ValueError(
                f"Detection.bbox_xyxy must be 4 numbers [x0, y0, x1, y1], got shape {np.shape(self.bbox_xyxy)}"
            )

    @classmethod
    def from_mask(cls, mask: np.ndarray, obj_id: int, score: float, class_index: int = 0) -> Detection:
        """A detection of ``mask`` ((H, W) bool, not empty) as ``obj_id``, its box the mask's tight bounds (pixel
        edges, as the detector's boxes)."""
        ys, xs = np.nonzero(mask)
        box = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], dtype=np.float64)
        return cls(class_index, int(obj_id), float(score), box, mask)


@dataclass(frozen=True, eq=False)
class ObjectPose:
    """A detection with its estimated 6D pose.

    T_camera_object: (4, 4) pose in metres. score: pose confidence in [0, 1], what consumers (the grasp planner)
    rank and filter by: the verification's confidence where the pose was verified against depth
    (``perception.verify``), else the estimator's own measure (e.g. the predicted mask agreement). method: how the
    pose was obtained, e.g. ``"direct"``, ``"pnp"``, ``"direct+icp"``, a strategy name (``"depth+icp"``). details:
    per-method diagnostics (inlier counts, ICP rmse, the verification's figures, timings) for logs and reports.
    verified: the verification's verdict: True accepted, False refused (the model at this pose disagrees with the
    depth and mask: a wrong pose or a wrong class), None not verified.
    """

    detection: Detection
    T_camera_object: np.ndarray
    score: float
    method: str
    details: dict = field(default_factory=dict)
    verified: bool | None = None

    def __post_init__(self) -> None:
        if np.shape(self.T_camera_object) != (4, 4):
            raise ValueError(f"ObjectPose.T_camera_object must be 4x4, got shape {np.shape(self.T_camera_object)}")

    @property
    def obj_id(self) -> int:
        return self.detection.obj_id
