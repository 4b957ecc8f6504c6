"""UR5e kinematics: the controller's FK reference vector, IK/FK round trips, singularities, UR pose conversions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sygrid.robots import T_to_pose, forward_kinematics, ik_nearest, inverse_kinematics, pose_to_T, ur5e
from sygrid.robots.kinematics import ik_solutions_near, link_transforms
from sygrid.transforms import make_T, rotation_about


def _wrapped_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(np.mod(np.asarray(a) - np.asarray(b) + math.pi, 2 * math.pi) - math.pi)


def _random_q(rng: np.random.Generator, n: int) -> np.ndarray:
    limits = ur5e.JOINT_LIMITS_RAD
    return rng.uniform(limits[:, 0], limits[:, 1], size=(n, 6))


def test_fk_matches_the_controller_reference_vector() -> None:
    # ur-rtde-protocol notes, pitfall 12: DH base frame (not ROS base_link), home pose.
    T = forward_kinematics(ur5e.HOME_Q)
    np.testing.assert_allclose(T[:3, 3], [-0.4919, -0.1333, 0.4879], atol=1e-4)
    np.testing.assert_allclose(T[:3, :3], [[0, 1, 0], [1, 0, 0], [0, 0, -1]], atol=1e-12)
    pose = T_to_pose(T)
    np.testing.assert_allclose(pose[3:], [math.pi / math.sqrt(2), math.pi / math.sqrt(2), 0.0], atol=1e-9)


def test_batched_fk_and_link_frames_agree_with_single_fk() -> None:
    q = _random_q(np.random.default_rng(3), 20)
    batched = forward_kinematics(q)
    assert batched.shape == (20, 4, 4)
    for k in range(20):
        np.testing.assert_allclose(batched[k], forward_kinematics(q[k]), atol=1e-15)
        np.testing.assert_allclose(link_transforms(q[k])[6], batched[k], atol=1e-15)


def test_ik_fk_round_trip_over_500_random_configurations() -> None:
    rng = np.random.default_rng(0)
    d4 = ur5e.DH_D_M[3]
    checked = 0
    for q in _random_q(rng, 500):
        T = forward_kinematics(q)
        solutions = inverse_kinematics(T)
        assert 1 <= len(solutions) <= 8
        assert np.all(np.isfinite(solutions))
        np.testing.assert_allclose(forward_kinematics(solutions), np.broadcast_to(T, (len(solutions), 4, 4)), atol=1e-9)
        limits = ur5e.JOINT_LIMITS_RAD
        assert np.all((solutions >= limits[:, 0]) & (solutions <= limits[:, 1]))
        wrist_centre = T[:3, 3] - ur5e.DH_D_M[5] * T[:3, 2]
        singular = (
            abs(math.sin(q[4])) < 1e-3 or abs(math.sin(q[2])) < 1e-3 or abs(math.hypot(*wrist_centre[:2]) - d4) < 1e-3
        )
        if not singular:
            checked += 1
            assert _wrapped_distance(solutions, q).max(axis=1).min() < 1e-7, f"q={q.tolist()} not among solutions"
    assert checked > 480


@pytest.mark.parametrize(
    "q",
    [
        [0.3, -1.2, 1.4, -0.5, 0.0, 0.7],  # wrist singularity: joints 4 and 6 aligned
        [0.3, -1.2, 1.4, -0.5, math.pi, 0.7],
        [0.3, -1.2, 0.0, -0.5, 1.0, 0.7],  # elbow fully stretched
        [0.0, -math.pi / 2, 0.0, -math.pi / 2, 0.0, 0.0],  # upright, wrist singular
    ],
)
def test_ik_at_singularities_gives_exact_solutions_and_no_nan(q: list[float]) -> None:
    q = np.array(q)
    T = forward_kinematics(q)
    solutions = inverse_kinematics(T)
    assert len(solutions) >= 1 and np.all(np.isfinite(solutions))
    np.testing.assert_allclose(forward_kinematics(solutions), np.broadcast_to(T, (len(solutions), 4, 4)), atol=1e-9)
    nearest = ik_nearest(T, q)
    assert nearest is not None
    np.testing.assert_allclose(forward_kinematics(nearest), T, atol=1e-9)
    assert np.abs(nearest - q).max() < 1e-6  # at the wrist singularity q6 stays at q_near's


def test_unreachable_poses_give_no_solution() -> None:
    far = make_T(t=(1.5, 0.0, 0.3))
    assert inverse_kinematics(far).shape == (0, 6)
    assert ik_nearest(far, ur5e.HOME_Q) is None
    # The wrist centre cannot come within d4 of the base axis.
    on_axis = make_T(np.diag([1.0, -1.0, -1.0]), (0.0, 0.0, 0.5 + ur5e.DH_D_M[5]))
    assert inverse_kinematics(on_axis).shape == (0, 6)


def test_ik_with_a_tool_offset() -> None:
    T_flange_tcp = make_T(rotation_about(np.array([0, 0, 1.0]), 0.4), (0.01, -0.02, 0.15))
    q = np.array([0.4, -1.0, 1.2, -1.7, -1.3, 0.5])
    T_base_tcp = forward_kinematics(q, T_flange_tcp)
    np.testing.assert_allclose(T_base_tcp, forward_kinematics(q) @ T_flange_tcp, atol=1e-15)
    nearest = ik_nearest(T_base_tcp, q + 0.05, T_flange_tcp=T_flange_tcp)
    np.testing.assert_allclose(nearest, q, atol=1e-9)


def test_ik_nearest_keeps_the_turn_of_multi_turn_joints() -> None:
    q = np.array([4.0, -1.0, 1.2, -1.7, -1.3, -5.0])  # beyond +-pi on joints 1 and 6
    nearest = ik_nearest(forward_kinematics(q), q + 0.01)
    np.testing.assert_allclose(nearest, q, atol=1e-9)
    # Tighter limits exclude the equivalents outside them.
    limits = np.array(ur5e.JOINT_LIMITS_RAD)
    limits[0] = [-math.pi, math.pi]
    restricted = ik_nearest(forward_kinematics(q), q, limits=limits)
    assert restricted is not None and -math.pi <= restricted[0] <= math.pi
    np.testing.assert_allclose(forward_kinematics(restricted), forward_kinematics(q), atol=1e-9)


def test_ik_solutions_near_are_every_branch_nearest_first_and_the_first_is_ik_nearest() -> None:
    q = np.array([0.4, -1.0, 1.2, -1.7, -1.3, 0.5])
    T = forward_kinematics(q)
    near = q + np.array([0.02, -0.03, 0.01, 0.02, -0.01, 0.03])
    solutions = ik_solutions_near(T, near)
    n = len(inverse_kinematics(T))
    assert n >= 2 and solutions.shape == (n, 6)  # every branch that the joint limits allow
    np.testing.assert_allclose(forward_kinematics(solutions), np.broadcast_to(T, (n, 4, 4)), atol=1e-9)
    distances = np.linalg.norm(solutions - near, axis=1)
    assert np.all(np.diff(distances) >= 0)
    np.testing.assert_allclose(solutions[0], q, atol=1e-9)
    np.testing.assert_allclose(solutions[0], ik_nearest(T, near), atol=0)
    # the same branches as inverse_kinematics, each joint wrapped towards q_near
    assert np.all(_wrapped_distance(solutions[:, None], inverse_kinematics(T)[None]).max(axis=2).min(axis=1) < 1e-9)
    assert ik_solutions_near(make_T(t=(1.5, 0.0, 0.3)), near).shape == (0, 6)


def test_pose_round_trip_and_rotation_vector_at_pi() -> None:
    rng = np.random.default_rng(7)
    for _ in range(200):
        axis = rng.normal(size=3)
        rotvec = axis / np.linalg.norm(axis) * rng.uniform(0.0, math.pi - 1e-3)
        pose = np.concatenate([rng.uniform(-1, 1, 3), rotvec])
        np.testing.assert_allclose(T_to_pose(pose_to_T(pose)), pose, atol=1e-9)
    # A half turn: r and -r are the same rotation; one canonical answer (first non-zero component positive).
    a = np.array([math.pi / math.sqrt(2), math.pi / math.sqrt(2), 0.0])
    for rv in (a, -a):
        np.testing.assert_allclose(T_to_pose(pose_to_T(np.concatenate([[0, 0, 0], rv])))[3:], a, atol=1e-9)
    # Continuity along a path: the equivalent nearest the previous rotation vector.
    near = T_to_pose(pose_to_T(np.concatenate([[0, 0, 0], a])), rotvec_near=-a)
    np.testing.assert_allclose(near[3:], -a, atol=1e-9)


def test_bad_inputs_name_the_problem() -> None:
    with pytest.raises(ValueError, match=r"shape \(6,\)"):
        forward_kinematics(np.zeros(5))
    with pytest.raises(ValueError, match="finite"):
        forward_kinematics(np.array([0, 0, np.nan, 0, 0, 0]))
    with pytest.raises(ValueError, match=r"\[x, y, z, rx, ry, rz\]"):
        pose_to_T(np.array([1.0, 2.0, 3.0]))
    with pytest.raises(ValueError, match="4x4"):
        inverse_kinematics(np.eye(3))
    with pytest.raises(ValueError, match="shoulder_pan"):
        ur5e.joint_index("elbow_joint")
    assert ur5e.joint_index("elbow") == 2
