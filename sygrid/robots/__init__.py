"""Robot models shared by the simulated cell and the real-robot runtime."""

from sygrid.robots import ur5e
from sygrid.robots.kinematics import (
    T_to_pose,
    forward_kinematics,
    ik_nearest,
    inverse_kinematics,
    link_transforms,
    pose_to_T,
)

__all__ = [
    "T_to_pose",
    "forward_kinematics",
    "ik_nearest",
    "inverse_kinematics",
    "link_transforms",
    "pose_to_T",
    "ur5e",
]
