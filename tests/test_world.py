"""The simulated cell: MuJoCo flange == DH forward kinematics, trajectory tracking, grasping by friction,
collision forces for the protective stop, parts and configuration errors."""

from __future__ import annotations

import math
from dataclasses import replace

import mujoco
import numpy as np
import pytest
import trimesh

from sim.world import CellConfig, CellWorld
from sygrid.errors import ConfigError
from sygrid.objects.collision.build import build_collision_model
from sygrid.objects.collision.geometry import ConvexPiece
from sygrid.objects.model import ObjectModel
from sygrid.robots import forward_kinematics, ik_nearest, ur5e
from sygrid.transforms import invert, make_T, rotation_about

R_TOOL_DOWN = np.diag([1.0, -1.0, -1.0])  # tool z pointing at the floor, pads along world x


def _box_part(size_m: float = 0.03) -> ObjectModel:
    return ObjectModel(obj_id=1, name="box", mesh=trimesh.creation.box((size_m, size_m, size_m)))


def _q_for_tcp(
    world: CellWorld, p_world: np.ndarray, q_near: np.ndarray | None = None, yaw_rad: float = 0.0
) -> np.ndarray:
    """Joint angles with the tool pointing down at ``p_world``, its pads along world x turned by ``yaw_rad``."""
    R = rotation_about(np.array([0, 0, 1.0]), yaw_rad) @ R_TOOL_DOWN
    T_base_tcp = invert(world.T_world_base) @ make_T(R, p_world)
    q = ik_nearest(T_base_tcp, ur5e.HOME_Q if q_near is None else q_near, T_flange_tcp=world.T_flange_tcp)
    assert q is not None, f"no IK solution for a TCP at {p_world}"
    return q


def _move(world: CellWorld, q_goal: np.ndarray, duration_s: float) -> tuple[float, float]:
    """Quintic joint move, one target per 2 ms tick; returns (max tracking error rad, max collision force N)."""
    q_start = world.arm_target()[0]
    n = round(duration_s / world.dt_s)
    max_error, max_force = 0.0, 0.0
    for k in range(1, n + 1):
        s = k / n
        blend = 10 * s**3 - 15 * s**4 + 6 * s**5
        rate = (30 * s**2 - 60 * s**3 + 30 * s**4) / duration_s
        max_error = max(max_error, float(np.abs(world.arm_q() - world.arm_target()[0]).max()))
        world.set_arm_target(q_start + (q_goal - q_start) * blend, (q_goal - q_start) * rate)
        world.step()
        max_force = max(max_force, world.arm_collision_force_n())
    return max_error, max_force


def test_mujoco_flange_equals_dh_forward_kinematics() -> None:
    rng = np.random.default_rng(0)
    T_world_base = make_T(rotation_about(np.array([0, 0, 1.0]), 0.7), (0.1, -0.2, 0.05))
    for world in (CellWorld(), CellWorld(CellConfig(T_world_base=T_world_base))):
        for q in rng.uniform(ur5e.JOINT_LIMITS_RAD[:, 0], ur5e.JOINT_LIMITS_RAD[:, 1], size=(50, 6)):
            world.reset_arm(q)
            np.testing.assert_allclose(world.T_base_flange(), forward_kinematics(q), atol=1e-6)
    # ... and after dynamics, not only after a reset.
    world.step(10)
    np.testing.assert_allclose(world.T_base_flange(), forward_kinematics(world.arm_q()), atol=1e-9)


def test_arm_holds_against_gravity_and_tracks_a_trajectory() -> None:
    world = CellWorld()
    assert world.dt_s == pytest.approx(0.002)
    world.step(250)
    np.testing.assert_allclose(world.arm_q(), ur5e.HOME_Q, atol=1e-5)
    assert abs(world.arm_torque()[1]) > 5.0  # the shoulder carries the arm's weight
    goal = np.array([0.6, -1.2, 1.1, -1.4, -1.2, 0.8])  # about 1 rad on the base, peak speed 1.1 rad/s
    max_error, max_force = _move(world, goal, 1.5)
    assert max_error < 1e-3
    assert max_force < 1.0, "normal motion must not look like a collision"
    world.step(100)
    np.testing.assert_allclose(world.arm_q(), goal, atol=1e-4)
    assert np.all(np.abs(world.arm_torque()) <= ur5e.MAX_JOINT_TORQUE_NM + 1e-9)
    assert world.time_s == pytest.approx((250 + 750 + 100) * 0.002)


def test_gripper_closes_and_opens_without_an_object() -> None:
    world = CellWorld()
    assert world.gripper_width_m() == pytest.approx(0.085, abs=1e-4)
    world.set_gripper(0.0, 0.15, 50.0)
    world.step(10)
    assert world.gripper_moving()
    world.step(400)
    assert world.gripper_width_m() < 1e-3
    assert not world.gripper_moving() and not world.gripper_object_detected()
    world.set_gripper(0.05, 0.15, 50.0)
    world.step(300)
    assert world.gripper_width_m() == pytest.approx(0.05, abs=1e-3)
    with pytest.raises(ValueError, match=r"force_n must be in \[20.0, 235.0\]"):
        world.set_gripper(0.05, 0.1, 500.0)


def test_part_is_grasped_and_lifted_by_friction() -> None:
    world = CellWorld()
    T_world_obj = world.T_world_bin @ make_T(t=(0.0, 0.0, 0.0155))
    world.add_parts([_box_part()], T_world_obj[None])
    world.step(50)
    part_xyz = world.part_poses()[0][:3, 3]
    _move(world, _q_for_tcp(world, part_xyz + np.array([0, 0, 0.12])), 1.2)
    q_grasp = _q_for_tcp(world, part_xyz + np.array([0, 0, 0.01]))
    _move(world, q_grasp, 0.8)
    world.set_gripper(0.0, 0.1, 100.0)
    world.step(500)
    assert world.gripper_object_detected() and not world.gripper_moving()
    assert world.gripper_width_m() == pytest.approx(0.03, abs=1.5e-3)

    T_flange_obj_before = invert(world.T_world_base @ world.T_base_flange()) @ world.part_poses()[0]
    z_part, z_flange = world.part_poses()[0][2, 3], world.T_base_flange()[2, 3]
    _move(world, _q_for_tcp(world, part_xyz + np.array([0, 0, 0.15]), q_near=q_grasp), 1.0)
    world.step(100)
    rise_part = world.part_poses()[0][2, 3] - z_part
    rise_flange = world.T_base_flange()[2, 3] - z_flange
    assert rise_flange == pytest.approx(0.14, abs=1e-3)
    assert rise_part == pytest.approx(rise_flange, abs=2e-3)
    T_flange_obj_after = invert(world.T_world_base @ world.T_base_flange()) @ world.part_poses()[0]
    assert np.abs(T_flange_obj_after[:3, 3] - T_flange_obj_before[:3, 3]).max() < 1e-3  # no slip
    # Held by contact alone: the only equality constraint is the fingers' coupling.
    assert world.model.neq == 1 and world.model.eq_type[0] == mujoco.mjtEq.mjEQ_JOINT
    # Opening releases it: it falls back. The fingers move from the first steps on (a set point left at the
    # closed end would hold them on the part, stalled, which reads as "stopped on an object while opening").
    world.set_gripper(0.085, 0.15, 100.0)
    # Until the request reaches the servo (the next step) it still squeezes at its force limit, away from the new
    # target: not a stall, so not "stopped on an object while opening".
    assert world.gripper_moving() and not world.gripper_object_detected()
    for _ in range(10):
        world.step()
        assert world.gripper_moving() and not world.gripper_object_detected()
    world.step(390)
    assert world.part_poses()[0][2, 3] < z_part + 0.02


def test_fingers_dragged_along_the_floor_at_their_force_limit_read_as_stopped() -> None:
    """Pads pressed onto the bin floor (the TCP 4 mm above it) close against the floor's friction: MuJoCo's soft
    friction lets them creep at about 2 mm/s with the servo at its force limit, where a real gripper's fingers stick
    and it reports them stopped on an object. Read as moving, a close never ended (the runtime's move deadline)."""
    world = CellWorld()
    spot = world.T_world_bin[:3, 3] + np.array([0.0, 0.0, 0.004])
    q_above = _q_for_tcp(world, spot + np.array([0, 0, 0.1]), yaw_rad=np.pi / 6)
    _move(world, q_above, 1.2)
    _move(world, _q_for_tcp(world, spot, q_above, yaw_rad=np.pi / 6), 0.8)
    world.set_gripper(0.0, 0.1, 100.0)
    world.step(round(1.0 / world.dt_s))  # the set point has travelled the stroke (0.85 s)
    width_before = world.gripper_width_m()
    readings = []
    for _ in range(round(1.0 / world.dt_s)):
        world.step()
        readings.append((world.gripper_moving(), world.gripper_object_detected()))
    assert world.gripper_width_m() > 0.03  # held open by the floor, not closed
    assert 0.002 < width_before - world.gripper_width_m() < 0.005  # still creeping, above 2 mm/s, over that second
    assert not any(moving for moving, _ in readings) and all(detected for _, detected in readings)


def test_pushing_into_the_table_is_a_large_collision_force() -> None:
    world = CellWorld()
    spot = np.array([-0.3, 0.3, 0.0])  # free table top between the bin and the robot
    _, free_force = _move(world, _q_for_tcp(world, spot + np.array([0, 0, 0.08])), 1.2)
    assert free_force < 1.0
    _, push_force = _move(world, _q_for_tcp(world, spot + np.array([0, 0, -0.03])), 0.6)
    assert push_force > 100.0
    force, geoms = world.arm_collision()
    assert force == world.arm_collision_force_n() > 100.0
    assert "table" in geoms  # the protective-stop message says what hit what


def test_parts_keep_the_world_state_and_rest_in_the_bin(tmp_path) -> None:
    world = CellWorld()
    q = np.array([0.2, -1.4, 1.3, -1.5, -1.6, 0.1])
    world.reset_arm(q)
    world.set_gripper(0.04, 0.15, 60.0)
    world.step(200)
    width, t = world.gripper_width_m(), world.time_s
    part = _box_part(0.02)
    hull = build_collision_model(part, "hull", cache_dir=tmp_path)  # a box primitive
    poses = np.stack([world.T_world_bin @ make_T(t=(x, 0.0, 0.0105)) for x in (-0.05, 0.0, 0.05)])
    names = world.add_parts([part] * 3, poses, collision=[hull] * 3)
    assert names == world.part_names() and len(names) == 3
    np.testing.assert_allclose(world.arm_q(), q, atol=1e-5)
    assert world.gripper_width_m() == pytest.approx(width, abs=1e-9) and world.time_s == t
    np.testing.assert_allclose(world.part_poses(), poses, atol=1e-12)
    world.step(300)
    resting = world.part_poses()
    np.testing.assert_allclose(resting[:, 2, 3], world.T_world_bin[2, 3] + 0.01, atol=5e-4)  # no sinking
    assert world.arm_collision_force_n() == 0.0 and world.thrown_parts == {}
    mass = world.model.body(names[0]).mass[0]
    assert mass == pytest.approx(part.mass_kg, rel=1e-9)
    world.set_part_poses(poses)
    np.testing.assert_allclose(world.part_poses(), poses, atol=1e-12)


def test_a_part_the_physics_throws_is_reported_once(tmp_path, caplog) -> None:
    """A gear once ended 470 m from the cell in a pick run: a part moving faster than the cell can move anything is
    named (with the time), so a run's results can be read knowing it."""
    world = CellWorld()
    part = _box_part(0.02)
    hull = build_collision_model(part, "hull", cache_dir=tmp_path)
    world.add_parts([part] * 2, np.stack([world.T_world_bin @ make_T(t=(x, 0.0, 0.0105)) for x in (-0.05, 0.05)]),
                    collision=[hull] * 2)  # fmt: skip
    world.step(50)
    assert world.thrown_parts == {}
    dof = world.model.joint("part1_box_free").dofadr[0]
    world.data.qvel[dof : dof + 3] = (0.0, 0.0, 30.0)
    with caplog.at_level("WARNING", logger="sim.world"):
        world.step(1)
        world.step(1)
    ((name, (t, speed)),) = world.thrown_parts.items()
    assert name == "part1_box" and speed == pytest.approx(30.0, rel=0.01)
    assert t == pytest.approx(world.time_s - world.dt_s)  # the first step it was seen at
    assert [r.getMessage().split(" moves at")[0] for r in caplog.records] == ["part1_box"]  # once


def test_a_throw_is_explained_by_the_deepest_penetration_before_it(tmp_path, caplog) -> None:
    world = CellWorld()
    part = _box_part(0.02)
    hull = build_collision_model(part, "hull", cache_dir=tmp_path)
    world.add_parts([part], (world.T_world_bin @ make_T(t=(0.0, 0.0, 0.01 - 0.004)))[None], collision=[hull])
    world.step(20)  # 4 mm into the bin's floor at first: pushed out over a few steps
    dof = world.model.joint("part0_box_free").dofadr[0]
    world.data.qvel[dof : dof + 3] = (0.0, 0.0, 30.0)
    with caplog.at_level("WARNING", logger="sim.world"):
        world.step(1)
    (throw,) = world.throws
    assert throw.part == "part0_box" and throw.speed_m_s == pytest.approx(30.0, rel=0.01)
    assert 0.002 < throw.max_penetration_m <= 0.0045 and throw.penetration_time_s < 0.01  # after one step
    assert "bin" in throw.against and throw.speed_before_m_s < 10.0
    assert "penetrated" in caplog.records[-1].getMessage() and throw.against in caplog.records[-1].getMessage()


def test_bad_arguments_and_configs_are_refused_with_the_reason(tmp_path) -> None:
    world = CellWorld()
    with pytest.raises(ValueError, match="6 finite numbers"):
        world.set_arm_target(np.zeros(5))
    with pytest.raises(ValueError, match="outside the joint limits"):
        world.set_arm_target(np.array([0, 0, 4.0, 0, 0, 0]))
    with pytest.raises(ValueError, match=r"T_world_obj must be \(1, 4, 4\)"):
        world.add_parts([_box_part()], np.eye(4))
    flat_piece = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [0.01, 0.01, 0]], dtype=float)
    hull = build_collision_model(_box_part(), "hull", cache_dir=tmp_path)
    flat = replace(hull, primitives=(), pieces=(ConvexPiece(flat_piece, np.array([[0, 1, 2], [1, 3, 2]])),))
    with pytest.raises(ValueError, match="coplanar"):  # MuJoCo refuses it; the world is left as it was
        world.add_parts([_box_part()], np.eye(4)[None], collision=[flat])
    assert world.part_names() == []
    assert world.add_parts([_box_part()], make_T(t=(-0.5, 0.0, 0.04))[None]) == ["part0_box"]
    with pytest.raises(ConfigError, match="T_world_bin must be a 4x4 rigid transform"):
        CellConfig(T_world_bin=np.diag([1.0, 1.0, 2.0, 1.0]))
    from sygrid.camera import CameraIntrinsics

    off_centre = CameraIntrinsics(500.0, 520.0, 300.0, 240.0, 640, 480)  # any pinhole renders (sygrid.mjspec)
    assert CellConfig(camera_intrinsics=off_centre).camera_intrinsics == off_centre
    with pytest.raises(ConfigError, match="fx, fy > 0"):
        CellConfig(camera_intrinsics=CameraIntrinsics(-500.0, 500.0, 300.0, 240.0, 640, 480))
    with pytest.raises(ConfigError, match="timestep_s"):
        CellConfig(timestep_s=0.05)
    assert math.isclose(CellConfig().camera_intrinsics.fov_y_deg, 45.0)
