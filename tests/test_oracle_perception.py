"""OraclePerception: the simulated cell's ground truth as a perception result, for built-in and catalogue parts."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from perception.camera import Frame
from sim.oracle_perception import OraclePerception
from sygrid.camera import CameraIntrinsics
from sygrid.objects import ObjectModel, builtin_part
from sygrid.transforms import make_T


class FakeProcess:
    """The two hooks the oracle reads from the emulator: body names and ``T_world_obj``."""

    def __init__(self, names: list[str], poses: np.ndarray) -> None:
        self._names, self._poses = names, poses

    def part_names(self) -> list[str]:
        return self._names

    def part_poses(self) -> np.ndarray:
        return self._poses


def _frame(depth_m: float = 1.0) -> Frame:
    K = CameraIntrinsics(fx=600.0, fy=600.0, cx=320.0, cy=240.0, width=640, height=480)
    rgb, depth = np.zeros((480, 640, 3), np.uint8), np.full((480, 640), depth_m, np.float32)
    return Frame(rgb=rgb, depth_m=depth, intrinsics=K, timestamp_s=0.0)


def test_oracle_sees_catalogue_parts_by_name_and_refuses_unknown_ones():
    cover = ObjectModel(obj_id=12, name="duct cover", mesh=trimesh.creation.box([0.05, 0.02, 0.012]))
    poses = np.stack([make_T(t=(0.0, 0.0, 0.5)), make_T(t=(0.05, 0.0, 0.5))])
    process = FakeProcess(["part0_duct_cover", "part1_hex_nut"], poses)  # names as sim.world makes them
    oracle = OraclePerception(process, np.eye(4), np.eye(4), [cover, builtin_part("hex_nut")])
    result = oracle.run(_frame())
    assert [p.detection.obj_id for p in result.poses] == [12, builtin_part("hex_nut").obj_id]
    np.testing.assert_allclose(result.poses[0].T_camera_object, poses[0])
    with pytest.raises(ValueError, match=r"\['duct_cover'\] are not among"):
        OraclePerception(process, np.eye(4), np.eye(4))  # the built-in parts only
