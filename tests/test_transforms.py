"""sygrid.transforms: the relative rotation's angle stays exact from a nanoradian to a half turn."""

from __future__ import annotations

import numpy as np
import pytest

from sygrid.transforms import make_T, pose_difference, rotation_about, rotation_angle_deg, rotation_angle_rad

AXIS = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])


@pytest.mark.parametrize("angle", [1e-9, 1e-6, 0.3, np.pi / 2, 3.0, np.pi])
def test_the_angle_between_two_rotations_is_the_turn_between_them(angle):
    R_a = rotation_about(np.array([0.0, 0.0, 1.0]), 0.7)
    R_b = R_a @ rotation_about(AXIS, angle)
    assert rotation_angle_rad(R_a, R_b) == pytest.approx(angle, rel=1e-6)
    assert rotation_angle_rad(R_b, R_a) == pytest.approx(angle, rel=1e-6)
    assert rotation_angle_deg(R_a, R_b) == pytest.approx(np.degrees(angle), rel=1e-6)


def test_a_poses_difference_is_its_origins_distance_and_its_turn():
    T_a = make_T(rotation_about(AXIS, 0.2), [0.1, -0.2, 0.3])
    T_b = T_a @ make_T(rotation_about(AXIS, 1e-8), [0.0, 0.003, -0.004])
    metres, radians = pose_difference(T_a, T_b)
    assert metres == pytest.approx(0.005) and radians == pytest.approx(1e-8, rel=1e-5)
    assert pose_difference(T_a, T_a) == (0.0, 0.0)
