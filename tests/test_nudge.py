"""robot.nudge on hand-made scenes in the default cell's bin: which parts get a nudge, where the fingers press and
which way they drag, and that the whole motion keeps the gripper off the walls."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from perception.results import Detection, ObjectPose
from robot.grasp_config import PlannerConfig
from robot.grasp_geometry import box_corners
from robot.grasp_plan import PartEstimate
from robot.grasp_planner import GraspPlanner
from robot.grasp_set import GraspSetParams
from robot.nudge import NudgeConfig, NudgePlanner, gap_to_points_m, straight_lines
from sygrid.errors import ConfigError
from sygrid.objects import builtin_part
from sygrid.robots.kinematics import forward_kinematics, ik_nearest
from sygrid.transforms import make_T, transform_points

PARAMS = GraspSetParams(n_surface_samples=150, n_dense_samples=1500)  # as tests/test_grasp.py: faster to build
FLOOR_Z = 0.02  # the default cell's bin: inner floor centre (-0.5, 0, 0.02), 300 x 200 mm inside
WALL_XP, WALL_YN = -0.5 + 0.15, -0.10
GEAR = builtin_part("spur_gear")
GEAR_RADIUS = GEAR.extents_m[0] / 2


@pytest.fixture(scope="module")
def nudger(tmp_path_factory: pytest.TempPathFactory) -> NudgePlanner:
    cache = tmp_path_factory.mktemp("grasp_cache")
    models = [GEAR, builtin_part("hex_nut"), builtin_part("pipe")]
    planner = GraspPlanner(models, PlannerConfig(grasp_params=PARAMS), cache_dir=cache)
    return NudgePlanner(planner)


def _flat_gear(x: float, y: float) -> np.ndarray:
    return make_T(t=(x, y, FLOOR_Z + GEAR.extents_m[2] / 2))


def _poses(*T_base_obj: np.ndarray, obj_id: int = GEAR.obj_id) -> list[ObjectPose]:
    """The poses as the camera would give them, with the camera at the base origin (T_base_camera = I)."""
    det = Detection(0, obj_id, 1.0, np.zeros(4))
    return [ObjectPose(det, T, 1.0, "test") for T in T_base_obj]


def test_a_gear_in_a_corner_is_pressed_on_its_top_and_dragged_away_from_both_walls(nudger):
    planner = nudger.planner
    # 5 mm from the -y wall and 24 mm from the +x wall: no grasp fits (the case a pick run in the cell left)
    T = _flat_gear(WALL_XP - 0.024 - GEAR_RADIUS, WALL_YN + 0.005 + GEAR_RADIUS)
    poses = _poses(T)
    plan = planner.plan(poses, np.eye(4))
    assert plan.nothing_safe and plan.parts[0].status == "collision_bin"
    q_home = planner.q_reference
    nudge = nudger.plan(poses, np.eye(4), plan, q_home, q_home)
    assert nudge is not None and nudge.part_index == 0 and nudge.cause == "collision_bin"
    # away from both walls (the corner's diagonal), far enough that the nearest wall is then target_gap_m away
    np.testing.assert_allclose(nudge.direction, np.array([-1.0, 1.0, 0.0]) / np.sqrt(2), atol=1e-9)
    assert nudge.distance_m == pytest.approx(NudgeConfig().target_gap_m - 0.005, abs=1e-3)
    np.testing.assert_allclose(nudge.T_base_end[:3, 3] - nudge.T_base_press[:3, 3], nudge.distance_m * nudge.direction)
    # the tool leans away from the walls (the housing clears them) and the lowest pad edge presses on the gear's top
    assert nudge.tilt_deg > 0 and nudge.T_base_press[:3, 2] @ nudge.direction < 0
    g = planner.config.gripper
    lowest = _lowest_pad_point(nudger, nudge)
    assert lowest[2] == pytest.approx(FLOOR_Z + GEAR.extents_m[2] - NudgeConfig().press_depth_m, abs=2e-4)
    assert np.linalg.norm(lowest[:2] - T[:2, 3]) < GEAR_RADIUS - NudgeConfig().edge_margin_m + 1e-6
    # every pose of the motion keeps the closed gripper off the walls, and the joint solutions reach the poses
    Ts = np.stack([nudge.T_base_above, nudge.T_base_press, nudge.T_base_end, nudge.T_base_retreat])
    closed = np.broadcast_to(g.boxes(0.0), (4, 6, 2, 3))
    assert planner.collision.wall_gap_m(Ts, closed).min() >= planner.config.bin_clearance_m
    qs = np.stack([nudge.q_above, nudge.q_press, nudge.q_end, nudge.q_retreat])
    np.testing.assert_allclose(forward_kinematics(qs, g.T_flange_tcp), Ts, atol=1e-6)
    # where the drag leaves the gear, the planner finds a grasp
    moved = T.copy()
    moved[:3, 3] += nudge.distance_m * nudge.direction
    assert not planner.plan(_poses(moved), np.eye(4)).nothing_safe


def test_only_parts_left_for_a_wall_or_the_cone_are_nudged_and_skip_is_honoured(nudger):
    planner = nudger.planner
    q = planner.q_reference
    middle = _poses(_flat_gear(-0.5, 0.0))
    plan = planner.plan(middle, np.eye(4))
    assert not plan.nothing_safe and nudger.plan(middle, np.eye(4), plan, q, q) is None
    corner = _poses(_flat_gear(WALL_XP - 0.024 - GEAR_RADIUS, WALL_YN + 0.005 + GEAR_RADIUS))
    plan = planner.plan(corner, np.eye(4))
    assert nudger.plan(corner, np.eye(4), plan, q, q, skip=lambda i: i == 0) is None


def test_a_nut_near_a_long_wall_is_not_dragged_where_the_drag_would_tip_it(nudger):
    planner = nudger.planner
    q = planner.q_reference
    nut = builtin_part("hex_nut")
    T = make_T(t=(-0.5, WALL_YN + 0.008 + nut.extents_m[1] / 2, FLOOR_Z + nut.extents_m[2] / 2))
    near = _poses(T, obj_id=nut.obj_id)
    plan = planner.plan(near, np.eye(4))
    assert plan.parts[0].status == "collision_bin"
    # the only presses that keep the gripper off both long walls are near the nut's edge away from the wall ...
    unchecked = NudgePlanner(planner, NudgeConfig(floor_friction=0.0)).plan(near, np.eye(4), plan, q, q)
    np.testing.assert_allclose(unchecked.direction, [0.0, 1.0, 0.0], atol=1e-9)
    lever = T[1, 3] + nut.extents_m[1] / 2 - _lowest_pad_point(nudger, unchecked)[1]
    # ... less than the simulated floor's friction (0.5) x the nut's height behind its leading flat: it would tip
    assert lever < 0.5 * nut.extents_m[2]
    assert nudger.plan(near, np.eye(4), plan, q, q) is None


def test_a_nut_is_pressed_in_the_middle_of_its_hole_and_the_drag_keeps_it_standing(nudger):
    q = nudger.planner.q_reference
    nut = builtin_part("hex_nut")
    cfg = NudgeConfig()
    T = make_T(t=(WALL_XP - 0.006 - nut.extents_m[0] / 2, 0.0, FLOOR_Z + nut.extents_m[2] / 2))
    nudge = nudger.plan_part(PartEstimate(nut.obj_id, T), 0, "collision_bin", q, q)
    assert nudge is not None
    np.testing.assert_allclose(nudge.direction, [-1.0, 0.0, 0.0], atol=1e-9)
    press = _lowest_pad_point(nudger, nudge)
    assert np.linalg.norm(press[:2] - T[:2, 3]) < 1e-3  # the middle of the hole (the nut's axis)
    assert press[2] == pytest.approx(FLOOR_Z + nut.extents_m[2] - cfg.press_depth_m, abs=2e-4)
    # where the floor's reaction acts when the nut starts to slide: inside its bearing face (0.95 x 18 mm across)
    pressure = press[:2] + cfg.floor_friction * nut.extents_m[2] * nudge.direction[:2]
    assert np.linalg.norm(pressure - T[:2, 3]) < 0.95 * 0.018 / 2


def test_a_pipe_lying_along_a_wall_is_rolled_away_from_it_where_a_flat_part_would_be_refused(nudger):
    q = nudger.planner.q_reference
    pipe = builtin_part("pipe")
    radius = pipe.extents_m[0] / 2
    # lying along the +x wall (its axis along y), 6 mm from it: a drag away from the wall rolls it (its centre is
    # over its line of contact), which moves it away from the wall as a slide would
    lying = make_T(np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]]),
                   (WALL_XP - 0.006 - radius, 0.0, FLOOR_Z + radius))  # fmt: skip
    part = PartEstimate(pipe.obj_id, lying)
    nudge = nudger.plan_part(part, 0, "collision_bin", q, q)
    assert nudge is not None and nudge.direction @ np.array([-1.0, 0.0, 0.0]) > 0.5
    # held to the tipping check like a flat part, it would get none: no press keeps a lying pipe from rolling
    assert NudgePlanner(nudger.planner, NudgeConfig(roll_deg=0.0)).plan_part(part, 0, "collision_bin", q, q) is None


def _lowest_pad_point(nudger: NudgePlanner, nudge) -> np.ndarray:
    """Where the closed pads are lowest at the press (base frame): the middle of their lowest edge or corner."""
    pads = transform_points(nudge.T_base_press, box_corners(nudger.planner.config.gripper.boxes(0.0)[:2]))
    return pads[pads[:, 2] < pads[:, 2].min() + 1e-4].mean(axis=0)


def test_a_nudge_keeps_the_tilted_gripper_off_a_part_standing_where_it_leans(nudger):
    planner = nudger.planner
    q = planner.q_reference
    pipe = builtin_part("pipe")
    corner = PartEstimate(GEAR.obj_id, _flat_gear(WALL_XP - 0.024 - GEAR_RADIUS, WALL_YN + 0.005 + GEAR_RADIUS))
    # a pipe standing on its end 72 mm from the gear, toward the bin's middle: under the tool, which leans that way
    standing = planner.surface_base(
        PartEstimate(pipe.obj_id, make_T(t=(-0.445, -0.03, FLOOR_Z + pipe.extents_m[2] / 2)))
    )
    closed = planner.config.gripper.boxes(0.0)

    def gap_to_pipe(nudge) -> float:
        path = np.stack([nudge.T_base_above, nudge.T_base_press, nudge.T_base_end, nudge.T_base_retreat])
        return gap_to_points_m(straight_lines(list(path), 0.002), closed, standing, planner.config.clearance_m)

    blind = nudger.plan_part(corner, 0, "collision_bin", q, q)  # planned without the pipe: its gripper hits it
    assert blind is not None and gap_to_pipe(blind) <= 0.0
    seeing = nudger.plan_part(corner, 0, "collision_bin", q, q, standing)
    # another candidate (a slanted drag, less tilt) passes beside it
    assert seeing is not None and gap_to_pipe(seeing) >= planner.config.clearance_m - 1e-6


def _nut_beside_a_gear() -> tuple[np.ndarray, np.ndarray]:
    """``(T_nut, T_gear)``: a nut in the bin's middle, a gear 3 mm beyond its +x side (20.8 mm across its corners)."""
    nut = builtin_part("hex_nut")
    T_nut = make_T(t=(-0.5, 0.0, FLOOR_Z + nut.extents_m[2] / 2))
    return T_nut, _flat_gear(-0.5 + nut.extents_m[0] / 2 + 0.003 + GEAR_RADIUS, 0.0)


def test_a_part_pressed_against_a_neighbour_is_dragged_away_from_it(nudger):
    planner = nudger.planner
    q = planner.q_reference
    nut = builtin_part("hex_nut")
    T_nut, T_gear = _nut_beside_a_gear()
    neighbours = planner.surface_base(PartEstimate(GEAR.obj_id, T_gear))
    nudge = nudger.plan_part(PartEstimate(nut.obj_id, T_nut), 0, "collision_parts", q, q, neighbours)
    assert nudge is not None
    assert nudge.direction @ np.array([-1.0, 0.0, 0.0]) > 0.95  # straight away from the gear
    assert nudge.distance_m == pytest.approx(NudgeConfig().target_gap_m - 0.003, abs=1.5e-3)


def test_a_neighbour_only_the_depth_shows_is_an_obstacle_of_the_nudge(nudger):
    planner = nudger.planner
    q = planner.q_reference
    nut = builtin_part("hex_nut")
    T_nut, T_gear = _nut_beside_a_gear()  # the gear seen by the depth camera but not posed: its surface as points
    gear_points = planner.surface_base(PartEstimate(GEAR.obj_id, T_gear))
    nut_points = planner.surface_base(PartEstimate(nut.obj_id, T_nut))
    poses = _poses(T_nut, obj_id=nut.obj_id)
    plan = planner.plan_parts([PartEstimate(nut.obj_id, T_nut)], np.concatenate([gear_points, nut_points]))
    # the pile as the plan was checked against: the points above the bin's floor
    assert 0 < len(plan.cloud_base) <= len(gear_points) + len(nut_points)
    # the nut as a plan leaves it where its grasps reach the gear (here one side is still free: made so by hand)
    plan = replace(plan, grasps=(), parts=(replace(plan.parts[0], status="collision_parts"),))
    nudge = nudger.plan(poses, np.eye(4), plan, q, q)
    assert nudge is not None
    assert nudge.direction @ np.array([-1.0, 0.0, 0.0]) > 0.95  # away from the unposed gear, as from a posed one
    path = straight_lines([nudge.T_base_above, nudge.T_base_press, nudge.T_base_end, nudge.T_base_retreat], 0.005)
    closed = planner.config.gripper.boxes(0.0)
    # the gear as the depth shows it, less what lies within own_points_tolerance_m of the nut (taken for the nut's)
    cfg = planner.config
    near_nut = cKDTree(nut_points).query(plan.cloud_base)[0] <= cfg.own_points_tolerance_m
    on_gear = np.linalg.norm(plan.cloud_base[:, :2] - T_gear[:2, 3], axis=1) <= GEAR_RADIUS + 1e-6
    seen_gear = plan.cloud_base[on_gear & ~near_nut]
    assert len(seen_gear) and gap_to_points_m(path, closed, seen_gear, 0.05) >= cfg.clearance_m
    # without the depth points the nut has no neighbour: the drag would go elsewhere, blind to the gear
    blind = replace(plan, cloud_base=np.zeros((0, 3)))
    other = nudger.plan(poses, np.eye(4), blind, q, q)
    assert other is None or other.direction @ np.array([-1.0, 0.0, 0.0]) < 0.95


def test_bad_nudge_settings_name_the_field(nudger):
    with pytest.raises(ConfigError, match="min_drag_m"):
        NudgeConfig(min_drag_m=0.1, max_drag_m=0.05)
    with pytest.raises(ConfigError, match="speed_m_s"):
        NudgeConfig(speed_m_s=0.0)
    with pytest.raises(ConfigError, match="tilts_deg"):
        NudgeConfig(tilts_deg=(95.0,))
    with pytest.raises(ConfigError, match="slants_deg"):
        NudgeConfig(slants_deg=(0.0, 90.0))
    with pytest.raises(ConfigError, match="floor_friction"):
        NudgeConfig(floor_friction=-0.1)
    with pytest.raises(ConfigError, match="roll_deg"):
        NudgeConfig(roll_deg=120.0)
    with pytest.raises(ConfigError, match="no bin"):
        NudgePlanner(GraspPlanner([GEAR], PlannerConfig(grasp_params=PARAMS, bin=None),
                                  cache_dir=nudger.planner.cache_dir))  # fmt: skip


def test_part_estimate_is_what_the_nudger_plans_from(nudger):
    """``plan_part`` takes a base-frame estimate directly (what ``plan`` builds from each pose)."""
    planner = nudger.planner
    q = planner.q_reference
    part = PartEstimate(GEAR.obj_id, _flat_gear(WALL_XP - 0.024 - GEAR_RADIUS, WALL_YN + 0.005 + GEAR_RADIUS))
    nudge = nudger.plan_part(part, 3, "collision_bin", q, q)
    assert nudge is not None and nudge.part_index == 3 and nudge.obj_id == GEAR.obj_id


def test_a_nut_in_the_far_corner_is_nudged_on_another_arm_branch_where_the_nearest_puts_the_wrist_on_a_wall(nudger):
    planner = nudger.planner
    q = planner.q_reference
    nut = builtin_part("hex_nut")
    radius = nut.extents_m[0] / 2
    # 17 mm from the -x wall and 20 mm from the +y wall (a nut a pick run in the simulated cell left there)
    T = make_T(t=(-0.5 - 0.15 + 0.017 + radius, 0.10 - 0.020 - radius, FLOOR_Z + nut.extents_m[2] / 2))
    nudge = nudger.plan_part(PartEstimate(nut.obj_id, T), 0, "collision_bin", q, q)
    assert nudge is not None
    qs = np.stack([nudge.q_above, nudge.q_press, nudge.q_end, nudge.q_retreat])
    g = planner.config.gripper
    Ts = np.stack([nudge.T_base_above, nudge.T_base_press, nudge.T_base_end, nudge.T_base_retreat])
    np.testing.assert_allclose(forward_kinematics(qs, g.T_flange_tcp), Ts, atol=1e-6)
    assert planner.collision.wrist_gap_m(qs).min() >= planner.config.bin_clearance_m
    # the configuration nearest the reference reaches the same poses with a wrist link over the wall
    nearest = [ik_nearest(nudge.T_base_above, q, g.T_flange_tcp, planner.joint_limits_rad)]
    for X in Ts[1:]:
        nearest.append(ik_nearest(X, nearest[-1], g.T_flange_tcp, planner.joint_limits_rad))
    assert np.abs(nearest[0] - nudge.q_above).max() > 0.5
    assert planner.collision.wrist_gap_m(np.stack(nearest)).min() < planner.config.bin_clearance_m
