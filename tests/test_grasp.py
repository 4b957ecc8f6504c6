"""The grasp candidates and the grasp planner on hand-made scenes (no rendering): antipodal candidates checked
against the mesh, the symmetry expansion, and the planner's picks, rejections and waypoints in the default cell."""

from __future__ import annotations

import math
from dataclasses import replace

import mujoco
import numpy as np
import pytest
import trimesh

from perception.results import Detection, ObjectPose
from robot.grasp_cache import resolve_cache_dir
from robot.grasp_candidates import antipodal_grasps, deduplicate, expand_by_symmetry, grasp_candidates
from robot.grasp_config import PlannerConfig
from robot.grasp_geometry import (
    ELBOW_LINKS,
    FINGER_BOXES,
    WRIST_LINKS,
    GripperGeometry,
    box_corners,
    lowest_elbow_point_m,
    obb_gap_m,
    part_box_tcp,
    points_box_distance_m,
    required_backoff_m,
    wrist_link_frames,
)
from robot.grasp_plan import REJECTION_CAUSES, PartEstimate
from robot.grasp_planner import GraspPlanner
from robot.grasp_scene import BinGeometry, depth_points
from robot.grasp_set import GraspSetParams
from sygrid.camera import CameraIntrinsics, unproject_depth
from sygrid.errors import ConfigError
from sygrid.objects import GraspAnnotation, ObjectModel, builtin_part
from sygrid.robots import ur5e
from sygrid.robots.kinematics import forward_kinematics, ik_nearest
from sygrid.transforms import invert, make_T, rotation_about, transform_points

# Fewer samples than the defaults: the same grasps, a few times faster to build.
PARAMS = GraspSetParams(n_surface_samples=150, n_dense_samples=1500)
FLOOR_Z = 0.02  # the default cell's bin floor (base frame)
BIN_CENTRE = np.array([-0.5, 0.0, FLOOR_Z])
MM = 1e-3


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory):
    return tmp_path_factory.mktemp("grasp_cache")


@pytest.fixture(scope="module")
def planner(cache_dir) -> GraspPlanner:
    models = [builtin_part(n) for n in ("hex_nut", "pipe", "spur_gear", "washer")]
    return GraspPlanner(models, PlannerConfig(grasp_params=PARAMS), cache_dir=cache_dir)


def _flat(name: str, x: float, y: float, yaw_rad: float = 0.0, on_z: float = FLOOR_Z) -> np.ndarray:
    """``T_base_obj`` of a built-in part lying on its z face (resting at ``on_z``), at (x, y), turned by yaw."""
    half_height = builtin_part(name).extents_m[2] / 2
    return make_T(rotation_about(np.array([0.0, 0.0, 1.0]), yaw_rad), (x, y, on_z + half_height))


def _lying_pipe(x: float, y: float, axis_xy: tuple[float, float], on_z: float = FLOOR_Z) -> np.ndarray:
    """The pipe lying on its side, its axis along ``axis_xy`` (base frame)."""
    z = np.array([*axis_xy, 0.0]) / np.linalg.norm(axis_xy)
    x_axis = np.cross(np.array([0.0, 0.0, 1.0]), z)
    R = np.column_stack([x_axis, np.cross(z, x_axis), z])
    return make_T(R, (x, y, on_z + 21.3 * MM / 2))


# ---------------------------------------------------------------------------------------------- box maths


def test_box_maths_on_known_configurations():
    unit = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])[None]  # one box, half size 1, at the origin
    # in the box's column: ahead of it (z = 5) it may go 4 - clearance deeper, behind it (z = -3) it must stay
    # back 4 + clearance; beside it (x = 5) nothing; behind the sweep's start nothing
    points = np.array([[[0.0, 0.0, 5.0]], [[0.0, 0.0, -3.0]], [[5.0, 0.0, 0.0]], [[0.0, 0.0, -3.0]]])
    backoff = required_backoff_m(points[:3], unit, 0.1)
    np.testing.assert_allclose(backoff, [-3.9, 4.1, -np.inf])
    assert required_backoff_m(points[3:], unit, 0.1, sweep_length_m=1.5)[0] == -np.inf
    assert required_backoff_m(points[3:], unit, 0.1, sweep_length_m=2.0)[0] == pytest.approx(4.1)
    np.testing.assert_allclose(points_box_distance_m(points[:3], unit), [4.0, 2.0, 4.0])
    # separating axes: face to face, overlap, and a cube turned 45 degrees (its edge towards the other's face)
    eye, half = np.eye(3), np.ones(3)
    assert obb_gap_m(np.zeros(3), eye, half, np.array([2.5, 0.0, 0.0]), eye, half) == pytest.approx(0.5)
    assert obb_gap_m(np.zeros(3), eye, half, np.array([1.5, 0.5, 0.0]), eye, half) == pytest.approx(-0.5)
    turned = rotation_about(np.array([0.0, 0.0, 1.0]), np.pi / 4)
    gap = obb_gap_m(np.zeros(3), eye, half, np.array([3.0, 0.0, 0.0]), turned, half)
    assert gap == pytest.approx(3.0 - 1.0 - np.sqrt(2.0))
    # broadcasting: (2, 1) against (3,) boxes
    many = obb_gap_m(np.zeros((2, 1, 3)), eye, half, np.array([[2.5, 0, 0], [0, 3.0, 0], [0, 0, 4.0]]), eye, half)
    np.testing.assert_allclose(many, [[0.5, 1.0, 2.0]] * 2)


def test_depth_points_agree_with_the_camera_model():
    """The planner's strided float32 cloud against ``sygrid.camera.unproject_depth`` then ``transform_points``."""
    K = CameraIntrinsics.from_fov(64, 48, 40.0)
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.4, 0.9, (48, 64)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.2] = 0.0  # no data
    T = make_T(rotation_about(np.array([1.0, 2.0, 3.0]), 0.7), (0.1, -0.2, 0.5))
    for stride in (1, 3):
        reference = unproject_depth(K.K, depth)[::stride, ::stride].reshape(-1, 3)
        reference = transform_points(T, reference[np.isfinite(reference[:, 2])])
        np.testing.assert_allclose(depth_points(depth, K, T, stride), reference, atol=1e-6)
        np.testing.assert_allclose(depth_points(depth, K.K, T, stride), reference, atol=1e-6)


# ---------------------------------------------------------------------------------------------- candidates


@pytest.mark.parametrize(
    ("name", "widths_mm"),
    [("washer", {2.5, 24.0}), ("pipe", {21.3, 50.0}), ("l_bracket", {2.0, 20.0})],
)
def test_candidates_are_antipodal_within_the_stroke(name, widths_mm, cache_dir):
    model = builtin_part(name)
    grasps = grasp_candidates(model, PARAMS, cache_dir=cache_dir)
    assert len(grasps) > 20
    g = PARAMS.gripper
    # the part's widths between the pads are its true dimensions: across the outer faces, or across a wall/sheet
    assert set(np.round(grasps.width_m / MM, 1)) == widths_mm
    assert np.all(grasps.width_m + 2 * PARAMS.min_open_clearance_m <= g.stroke_m + 1e-12)
    assert np.all((grasps.opening_m > grasps.width_m) & (grasps.opening_m <= g.stroke_m + 1e-12))
    # An independent look at the mesh (another sample): with the pads closed to the width, each pad touches the
    # part on a surface facing it within the friction cone, and nothing of the part lies beyond a pad's plane.
    points, faces = trimesh.sample.sample_surface(model.mesh, 6000, seed=np.random.default_rng(99))
    normals = model.mesh.face_normals[faces]
    cos_cone = math.cos(math.atan(PARAMS.friction_coefficient))
    for T, width in zip(grasps.T_obj_grasp, grasps.width_m, strict=True):
        R, t = T[:3, :3], T[:3, 3]
        p, n_x = (points - t) @ R, normals @ R[:, 0]
        on_pads = (np.abs(p[:, 1]) <= g.pad_width_m / 2) & (np.abs(p[:, 2]) <= g.pad_length_m / 2)
        for sign in (1.0, -1.0):
            contact = on_pads & (np.abs(p[:, 0] - sign * width / 2) <= 1.0 * MM) & (sign * n_x >= cos_cone)
            assert contact.sum() >= 3, f"{name}: a pad touches nothing at {T.tolist()}"
        beyond = on_pads & (np.abs(p[:, 0]) > width / 2 + 1.0 * MM)
        assert not beyond.any(), f"{name}: the part sticks out past a pad at {T.tolist()}"


def test_symmetry_expansion_multiplies_the_hex_nut_candidates(cache_dir):
    nut = builtin_part("hex_nut")
    symmetries = nut.symmetry_transforms()
    assert len(symmetries) == 12  # D6: 6 rotations about the axis, each with and without the flip
    base = antipodal_grasps(nut, PARAMS)
    expanded = expand_by_symmetry(base, nut)
    assert len(expanded) == 12 * len(base)
    np.testing.assert_allclose(
        expanded.T_obj_grasp[5 * len(base) : 6 * len(base)], symmetries[5] @ base.T_obj_grasp, atol=1e-12
    )
    np.testing.assert_array_equal(expanded.width_m, np.tile(base.width_m, 12))
    # the finished set: more than the sample alone gave, and closed under every symmetry (each mapped grasp is
    # within the de-duplication tolerance of a kept one)
    final = grasp_candidates(nut, PARAMS, cache_dir=cache_dir)
    assert len(deduplicate(base, PARAMS)) < len(final) <= len(expanded)
    positions = final.T_obj_grasp[:, :3, 3]
    for S in symmetries[1:]:
        mapped = S @ final.T_obj_grasp
        dist = np.linalg.norm(mapped[:, None, :3, 3] - positions[None], axis=2)
        same_approach = np.einsum("ai,bi->ab", mapped[:, :3, 2], final.T_obj_grasp[:, :3, 2]) > math.cos(0.3)
        near = (dist < 2 * PARAMS.dedup_position_m) & same_approach
        assert near.any(axis=1).all()
    # a continuous axis: 36 steps about it, times the flip
    washer = builtin_part("washer")
    small = antipodal_grasps(washer, GraspSetParams(n_surface_samples=20, n_dense_samples=500))
    assert len(expand_by_symmetry(small, washer)) == 72 * len(small)


def test_candidates_are_cached_by_mesh_and_parameters(cache_dir, tmp_path, caplog):
    nut = builtin_part("hex_nut")
    first = grasp_candidates(nut, PARAMS, cache_dir=tmp_path)
    files = sorted(tmp_path.glob("*.npz"))
    assert len(files) == 1 and files[0].name.startswith(nut.content_hash[:16])
    again = grasp_candidates(nut, PARAMS, cache_dir=tmp_path)
    np.testing.assert_array_equal(again.T_obj_grasp, first.T_obj_grasp)
    np.testing.assert_array_equal(again.contact_z_m, first.contact_z_m)
    other = GraspSetParams(n_surface_samples=150, n_dense_samples=1500, friction_coefficient=0.3)
    grasp_candidates(nut, other, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("*.npz"))) == 2  # another parameter, another entry
    files[0].write_bytes(b"not an npz")  # a damaged entry is rebuilt, with a warning
    rebuilt = grasp_candidates(nut, PARAMS, cache_dir=tmp_path)
    np.testing.assert_array_equal(rebuilt.T_obj_grasp, first.T_obj_grasp)
    assert "unreadable grasp cache entry" in caplog.text
    assert resolve_cache_dir(tmp_path) == tmp_path


def test_declared_grasps_are_used_expanded_and_measured(tmp_path):
    """A part with declared grasps uses them (not the mesh's antipodal pairs), with its symmetries."""
    block = trimesh.creation.box((0.03, 0.02, 0.01))
    # from above, across the 20 mm, 8 mm off the centre along the 30 mm
    top_down_across_y = np.array([[0, 1, 0, 0.008], [1, 0, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]], dtype=float)
    model = ObjectModel(
        obj_id=9,
        name="block",
        mesh=block,
        symmetries_discrete=(np.diag([-1.0, -1.0, 1.0, 1.0]),),  # 180 degrees about z
        grasps=(GraspAnnotation(top_down_across_y, 0.02, 0.8),),
    )
    grasps = grasp_candidates(model, PARAMS, cache_dir=tmp_path)
    assert grasps.source == "declared" and len(grasps) == 2  # the declared grasp and its turned copy (at -8 mm)
    np.testing.assert_allclose(sorted(grasps.T_obj_grasp[:, 0, 3]), [-0.008, 0.008])
    np.testing.assert_allclose(grasps.width_m, 0.02)
    np.testing.assert_allclose(grasps.contact_z_m, [[-0.005, 0.005]] * 2, atol=0.5 * MM)  # the block's 10 mm
    planner = GraspPlanner([model], PlannerConfig(grasp_params=PARAMS), cache_dir=tmp_path)
    T_base_block = make_T(t=(-0.5, 0.0, FLOOR_Z + 0.005))
    g = planner.plan_parts([PartEstimate(9, T_base_block)]).best
    np.testing.assert_allclose(np.abs(g.T_base_grasp[:3, 0]), [0.0, 1.0, 0.0], atol=1e-9)  # across the 20 mm
    assert g.grasp_width_m == pytest.approx(0.02)
    wide = ObjectModel(obj_id=10, name="wide", mesh=block, grasps=(GraspAnnotation(top_down_across_y, 0.09),))
    with pytest.raises(ConfigError, match=r"wide: declared grasp\(s\) \[0\] are wider"):
        grasp_candidates(wide, PARAMS, cache_dir=tmp_path)


def test_defaults_match_the_simulated_cell():
    """The planner's gripper boxes lie where the simulated gripper's geoms are (both are built from
    ``sygrid.robots.gripper_2f85``, each in its own frame), its stroke is the simulated fingers' travel, and its bin
    and place pose are the simulated cell's (robot may not import sim: those numbers are repeated)."""
    from sim.cell_config import CellConfig
    from sim.gripper_model import add_gripper

    g = GripperGeometry()
    spec = mujoco.MjSpec()
    add_gripper(spec, spec.worldbody, pad_solref=[0.004, 1.0])
    model = spec.compile()
    travel = [model.joint(f"gripper_finger_{k}_joint").range[1] - model.joint(f"gripper_finger_{k}_joint").range[0]
              for k in "ab"]  # fmt: skip
    assert sum(travel) == pytest.approx(g.stroke_m, abs=1e-12)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)  # fingers closed: the pads' inner faces at x = 0
    boxes = dict(zip(("pad_pos", "pad_neg", "link_pos", "link_neg", "housing"), g.boxes(0.0)[:5], strict=True))
    names = {"pad_pos": "finger_a_pad", "pad_neg": "finger_b_pad", "link_pos": "finger_a_link"}
    names |= {"link_neg": "finger_b_link", "housing": "housing"}
    for box, geom in names.items():
        centre = data.geom(f"gripper_{geom}").xpos - g.T_flange_tcp[:3, 3]
        half = model.geom(f"gripper_{geom}").size
        np.testing.assert_allclose(boxes[box][0], centre - half, atol=1e-9, err_msg=box)
        np.testing.assert_allclose(boxes[box][1], centre + half, atol=1e-9, err_msg=box)
    cell, b = CellConfig(), BinGeometry()
    np.testing.assert_allclose(b.T_base_bin, invert(cell.T_world_base) @ cell.T_world_bin)
    assert b.inner_size_m == cell.bin_inner_size_m and b.wall_thickness_m == cell.bin_wall_thickness_m
    np.testing.assert_allclose(PlannerConfig().T_base_place[:2, 3], cell.T_world_tray[:2, 3])


# ---------------------------------------------------------------------------------------------- the planner


def test_a_flat_nut_in_the_middle_gets_a_top_down_grasp_across_its_flats(planner):
    T_base_nut = _flat("hex_nut", -0.5, 0.0, yaw_rad=0.3)
    plan = planner.plan_parts([PartEstimate(1, T_base_nut, 0.9)])
    assert not plan.nothing_safe, plan.summary()
    g = plan.best
    assert g.part_index == 0 and g.obj_id == 1
    assert g.approach_angle_deg < 1.0
    np.testing.assert_allclose(g.T_base_grasp[:3, 2], [0.0, 0.0, -1.0], atol=1e-6)
    assert g.grasp_width_m == pytest.approx(18.0 * MM, abs=0.05 * MM)  # ISO 4032 M12: 18 mm across flats
    assert g.opening_width_m == pytest.approx(18.0 * MM + 2 * PARAMS.open_clearance_m, abs=0.05 * MM)
    # the pads close across a pair of flats: the pad axis is a flat normal (at 30 + 60 k degrees from the nut's x)
    angle = math.degrees(math.atan2(g.T_base_grasp[1, 0], g.T_base_grasp[0, 0])) - math.degrees(0.3)
    assert min((angle - 30.0) % 60.0, 60.0 - (angle - 30.0) % 60.0) < 1.0
    # centred between the flats; anywhere along them that the pads still cover (a flat is 10.4 mm long)
    offset = g.T_base_grasp[:3, 3] - T_base_nut[:3, 3]
    assert abs(offset @ g.T_base_grasp[:3, 0]) < 0.1 * MM
    assert abs(offset @ g.T_base_grasp[:3, 1]) < PARAMS.dedup_position_m
    # the pads stay clear of the floor and hold the nut over most of its 10.8 mm height
    pad_tips_z = g.T_base_grasp[2, 3] - GripperGeometry().pad_length_m / 2
    assert pad_tips_z >= FLOOR_Z + planner.config.floor_clearance_m - 1e-9
    assert 5.0 * MM < g.engagement_m <= 10.8 * MM
    assert plan.parts[0].status == "planned" and plan.parts[0].rejections["approach_angle"] > 0


def test_waypoints_are_ordered_and_reached_by_their_joint_solutions(planner):
    plan = planner.plan_parts([PartEstimate(1, _flat("hex_nut", -0.45, 0.03, yaw_rad=1.0), 0.9)])
    g = plan.best
    cfg = planner.config
    assert [name for name, _ in g.waypoints] == ["pre_grasp", "grasp", "lift", "place"]
    approach = g.T_base_grasp[:3, 2]
    # pre-grasp: back along the approach, above the grasp; lift: back out the same way, above the grasp
    np.testing.assert_allclose(g.T_base_pregrasp[:3, 3], g.T_base_grasp[:3, 3] - cfg.pre_grasp_distance_m * approach)
    np.testing.assert_allclose(g.T_base_lift[:3, 3], g.T_base_grasp[:3, 3] - cfg.lift_height_m * approach)
    assert g.T_base_pregrasp[2, 3] > g.T_base_grasp[2, 3] + 0.05
    assert g.T_base_lift[2, 3] >= g.T_base_grasp[2, 3] + math.cos(math.radians(cfg.approach_cone_deg)) * 0.15
    for T in (g.T_base_pregrasp, g.T_base_lift):
        np.testing.assert_allclose(T[:3, :3], g.T_base_grasp[:3, :3])
    np.testing.assert_allclose(_held_box_centre(g)[:2], cfg.place_pose_at(0)[:2, 3], atol=1e-12)
    np.testing.assert_allclose(g.T_base_place[2, 3], cfg.place_pose_at(0)[2, 3])
    np.testing.assert_allclose(g.T_base_place[:3, 2], [0.0, 0.0, -1.0], atol=1e-9)
    for (name, T), (_, q) in zip(g.waypoints, g.joint_waypoints, strict=True):
        np.testing.assert_allclose(forward_kinematics(q, cfg.gripper.T_flange_tcp), T, atol=1e-9, err_msg=name)
    # straight-line moves without a branch switch, and joints off their limits by the margin
    assert np.abs(g.q_pregrasp - g.q_grasp).max() < cfg.max_joint_step_rad
    assert np.abs(g.q_lift - g.q_grasp).max() < cfg.max_joint_step_rad
    assert np.all(np.abs(g.q_grasp[[0, 1, 3, 4, 5]]) <= 2 * np.pi - cfg.joint_limit_margin_rad)
    assert abs(g.q_grasp[2]) <= np.pi - cfg.joint_limit_margin_rad


def test_a_pipe_against_a_wall_keeps_only_the_grasps_without_a_finger_at_the_wall(planner):
    config = PlannerConfig(grasp_params=PARAMS, max_grasps_per_part=200)
    wide = GraspPlanner([builtin_part("pipe")], config, cache_dir=planner.cache_dir)
    wall_x = -0.5 + 0.15  # the +x wall's inner face
    # the pipe's axis along x, one end touching the wall; and the same pipe in the middle of the bin
    against = wide.plan_parts([PartEstimate(5, _lying_pipe(wall_x - 0.025, 0.0, (1.0, 0.0)), 0.9)])
    middle = wide.plan_parts([PartEstimate(5, _lying_pipe(-0.5, 0.0, (1.0, 0.0)), 0.9)])
    assert not against.nothing_safe and not middle.nothing_safe

    def end_to_end(plan):  # the 50 mm grasps: one pad on each end of the pipe
        return [g for g in plan.grasps if g.grasp_width_m > 40 * MM]

    # in the middle, the pads can close along the pipe, across its ends; at the wall that puts a finger between
    # the pipe's end and the wall: all such grasps are rejected, and so are the ones whose housing would hit it
    assert end_to_end(middle)
    assert not end_to_end(against)
    assert against.rejections["collision_bin"] > middle.rejections["collision_bin"]
    assert len(against.grasps) < len(middle.grasps)
    for g in against.grasps:
        assert abs(g.T_base_grasp[0, 0]) < 0.2  # pads close across the pipe, not towards the wall
        # the housing (62 mm wide) stays off the wall: the grasp is far enough from it, or leans away from it
        lo, hi = GripperGeometry().boxes(g.opening_width_m)[4]
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        housing = transform_points(g.T_base_grasp, corners)
        assert np.max(housing[:, 0]) <= wall_x - wide.config.bin_clearance_m + 1e-9
        assert wall_x - g.T_base_grasp[0, 3] > 0.03 or g.T_base_grasp[0, 2] > 0.3
        assert g.clearance_m >= wide.config.bin_clearance_m


def test_a_part_beneath_another_comes_after_it_and_is_refused_when_covered(planner):
    # a washer lying across one end of a pipe: both can be picked, the washer (on top) first
    pipe = _lying_pipe(-0.5, 0.0, (1.0, 0.0))
    washer = _flat("washer", -0.5 + 0.026, 0.0, on_z=FLOOR_Z + 21.3 * MM)
    config = PlannerConfig(grasp_params=PARAMS, max_grasps_per_part=100)
    several = GraspPlanner([builtin_part("pipe"), builtin_part("washer")], config, cache_dir=planner.cache_dir)
    plan = several.plan_parts([PartEstimate(5, pipe, 0.95), PartEstimate(3, washer, 0.9)])
    order = [g.part_index for g in plan.grasps]
    assert set(order) == {0, 1} and order == sorted(order, reverse=True), plan.summary()
    assert 0.02 < plan.parts[0].covered_fraction < 0.3 and plan.parts[1].covered_fraction == 0.0
    # the washer keeps the fingers off the pipe's end it lies on: alone, the pipe is also taken there
    alone = several.plan_parts([PartEstimate(5, pipe, 0.95)])
    under_x = [g.T_base_grasp[0, 3] for g in plan.grasps if g.part_index == 0]
    alone_x = [g.T_base_grasp[0, 3] for g in alone.grasps]
    assert len(under_x) < len(alone_x)
    assert max(under_x) < washer[0, 3] - 0.02 < max(alone_x)

    nut = _flat("hex_nut", -0.5, 0.0)
    # the pipe right on top of the nut: the nut is covered, not picked; the pipe still is
    pipe_on_nut = _lying_pipe(-0.5, 0.0, (1.0, 0.0), on_z=FLOOR_Z + 10.8 * MM)
    parts = [PartEstimate(1, nut, 0.95), PartEstimate(5, pipe_on_nut, 0.9)]
    covered = planner.plan_parts(parts)
    assert covered.parts[0].status == "covered" and covered.parts[0].covered_fraction > 0.9
    assert covered.rejections["covered"] == covered.parts[0].n_candidates
    assert {g.part_index for g in covered.grasps} == {1}
    # the same from the camera: poses in the camera frame and a depth frame in which the pipe hides the nut
    T_base_camera = make_T(np.diag([1.0, -1.0, -1.0]), (-0.5, 0.0, 0.52))
    K = CameraIntrinsics.from_fov(96, 72, 30.0)
    depth = _render_depth([(builtin_part("hex_nut"), nut), (builtin_part("pipe"), pipe_on_nut)], K, T_base_camera)
    poses = [_pose(1, invert(T_base_camera) @ nut), _pose(5, invert(T_base_camera) @ pipe_on_nut)]
    from_camera = planner.plan(poses, T_base_camera, depth, K)
    assert from_camera.parts[0].status == "covered"
    assert {g.part_index for g in from_camera.grasps} == {1}
    assert from_camera.timings_s["depth_cloud"] >= 0.0


def test_a_part_seen_through_depth_noise_is_not_blocked_by_its_own_points(planner):
    """A stereo camera's points scatter about the surface: with 3 mm of noise some of a lone nut's own points lie
    beyond ``own_points_tolerance_m`` and read as a neighbour in the fingers' way, unless the tolerances allow for
    the noise (``for_depth_noise``)."""
    nut = _flat("hex_nut", -0.5, 0.0)
    T_base_camera = make_T(np.diag([1.0, -1.0, -1.0]), (-0.5, 0.0, 0.52))
    K = CameraIntrinsics.from_fov(320, 240, 30.0)
    depth = _render_depth([(builtin_part("hex_nut"), nut)], K, T_base_camera)
    noisy = np.where(depth > 0, depth + np.random.default_rng(0).normal(0.0, 0.003, depth.shape), 0.0)
    poses = [_pose(1, invert(T_base_camera) @ nut)]
    assert planner.plan(poses, T_base_camera, depth, K).parts[0].status == "planned"
    assert planner.plan(poses, T_base_camera, noisy, K).parts[0].status == "collision_parts"
    allowing = GraspPlanner([builtin_part("hex_nut")], planner.config.for_depth_noise(0.003),
                            cache_dir=planner.cache_dir)  # fmt: skip
    plan = allowing.plan(poses, T_base_camera, noisy, K)
    assert plan.parts[0].status == "planned" and plan.grasps, plan.summary()
    assert allowing.config.own_points_tolerance_m == pytest.approx(planner.config.own_points_tolerance_m + 0.009)
    with pytest.raises(ConfigError, match="sigma_m"):
        planner.config.for_depth_noise(-1.0)


def test_an_unseen_neighbour_in_the_depth_frame_blocks_the_fingers(planner):
    """A part the detector missed is only in the depth frame: the gripper must still keep off it."""
    nut = _flat("hex_nut", -0.5, 0.0)
    T_base_camera = make_T(np.diag([1.0, -1.0, -1.0]), (-0.5, 0.0, 0.52))
    K = CameraIntrinsics.from_fov(96, 72, 30.0)
    alone = planner.plan([_pose(1, invert(T_base_camera) @ nut)], T_base_camera, None, None)
    # four gears around the nut, 28 mm off (1 mm from its corners; every finger path crosses one), seen only by depth
    gears = [_flat("spur_gear", -0.5 + dx, dy) for dx, dy in ((0.028, 0), (-0.028, 0), (0, 0.028), (0, -0.028))]
    scene = [(builtin_part("hex_nut"), nut)] + [(builtin_part("spur_gear"), T) for T in gears]
    depth = _render_depth(scene, K, T_base_camera)
    crowded = planner.plan([_pose(1, invert(T_base_camera) @ nut)], T_base_camera, depth, K)
    assert not alone.nothing_safe
    assert crowded.nothing_safe and crowded.parts[0].status == "collision_parts", crowded.summary()


def _arm_contacts_with_bin(world, qs: np.ndarray, width_m: float) -> list[tuple[str, str]]:
    """MuJoCo's arm/gripper-vs-bin contacts (penetrating) at joint configurations ``qs`` with the fingers at
    ``width_m``: the simulated cell's own geometry, independent of the planner's boxes."""
    m, d = world.model, world.data
    arm_q = [m.joint(n).qposadr[0] for n in ur5e.JOINT_NAMES]
    fingers = [m.joint(f"gripper_finger_{k}_joint").qposadr[0] for k in "ab"]
    bin_id = m.body("bin").id
    hits = set()
    for q in qs:
        d.qpos[arm_q], d.qpos[fingers] = q, width_m / 2
        mujoco.mj_forward(m, d)
        for c in d.contact[: d.ncon]:
            bodies = {m.geom_bodyid[c.geom1], m.geom_bodyid[c.geom2]}
            if bin_id in bodies and c.dist < 0:
                hits.add((m.geom(c.geom1).name, m.geom(c.geom2).name))
    return sorted(hits)


def _joint_line(q0: np.ndarray, q1: np.ndarray, n: int = 60) -> np.ndarray:
    return q0[None] + np.linspace(0.0, 1.0, n)[:, None] * (q1 - q0)[None]


def test_joint_moves_to_and_from_the_bin_keep_the_gripper_off_its_walls(planner):
    """A joint move is not a straight tool line: from the place pose over the tray (on the bin's -y side) to a lift
    above the bin it can swing the fingers through the -y wall. The planner samples the moves; MuJoCo's own
    geometry of the cell confirms that what it plans is clear, and that with the old, low place pose (pads below
    the rim) some moves it refuses (or raises the lift for) were not."""
    from sim.world import CellWorld

    world = CellWorld()
    nut = PartEstimate(1, _flat("hex_nut", -0.5, 0.0), 0.9)
    low_place = make_T(np.diag([1.0, -1.0, -1.0]), (-0.2, -0.42, 0.12))  # the old place pose: pads below the rim
    for T_place in (PlannerConfig().T_base_place, low_place):
        config = PlannerConfig(grasp_params=PARAMS, T_base_place=T_place, max_grasps_per_part=20)
        p = GraspPlanner([builtin_part("hex_nut")], config, cache_dir=planner.cache_dir)
        q_place = ik_nearest(T_place, p.q_reference, config.gripper.T_flange_tcp)
        plan = p.plan_parts([nut], q_seed=q_place)
        for g in plan.grasps:
            # the lift holds the gripper above the rim (0.14 m), and the moves to and from it stay clear
            boxes = GripperGeometry().boxes(g.grasp_width_m)
            corners = np.array(
                [[b[i, 0], b[j, 1], b[k, 2]] for b in boxes for i in (0, 1) for j in (0, 1) for k in (0, 1)]
            )
            lowest = transform_points(g.T_base_lift, corners)[:, 2]
            assert lowest.min() >= FLOOR_Z + 0.12 + config.rim_clearance_m - 1e-9
            assert _arm_contacts_with_bin(world, _joint_line(q_place, g.q_lift), g.opening_width_m) == []
            assert _arm_contacts_with_bin(world, _joint_line(g.q_lift, g.q_place), g.opening_width_m) == []
        if T_place is low_place:
            # some moves are cleared only by a lift further back than the rim needs (0.15 m, or 0.184 m at 45 deg)
            lifts = [np.linalg.norm(g.T_base_lift[:3, 3] - g.T_base_grasp[:3, 3]) for g in plan.grasps]
            assert plan.rejections["collision_transit"] > 0 or max(lifts) > 0.199, plan.summary()
            unchecked = PlannerConfig(
                grasp_params=PARAMS, T_base_place=low_place, transit_clearance_m=None, max_grasps_per_part=20
            )
            refused = GraspPlanner([builtin_part("hex_nut")], unchecked, cache_dir=planner.cache_dir)
            hits = [
                _arm_contacts_with_bin(world, _joint_line(q_place, g.q_lift), g.opening_width_m)
                + _arm_contacts_with_bin(world, _joint_line(g.q_lift, g.q_place), g.opening_width_m)
                for g in refused.plan_parts([nut], q_seed=q_place).grasps
            ]
            assert any(hits), "without the check, some planned move should hit the wall"
        else:
            assert not plan.nothing_safe, plan.summary()


def test_wrist_boxes_follow_the_simulated_arm_and_cover_its_wrist(planner):
    """The planner's wrist links (frames from the DH chain, boxes around the collision cylinders) are the simulated
    cell's: same frames as MuJoCo's bodies, and every wrist/bin contact MuJoCo finds is a negative gap."""
    from sim.world import CellWorld

    world = CellWorld()
    m, d = world.model, world.data
    arm_q = [m.joint(n).qposadr[0] for n in ur5e.JOINT_NAMES]
    wrist_bodies = [m.body(ur5e.LINK_NAMES[i]).id for i in WRIST_LINKS]
    bin_id = m.body("bin").id
    b = planner.config.bin
    rng = np.random.default_rng(3)
    qs = []
    for _ in range(300):  # the TCP near a wall, low in the bin, tilted up to 60 deg: the wrist meets the rim
        side = rng.choice([-1.0, 1.0])
        axis = rng.integers(2)
        xy = rng.uniform(-0.5, 0.5, 2) * np.array(b.inner_size_m[:2])
        xy[axis] = side * (b.inner_size_m[axis] / 2 - rng.uniform(0.02, 0.08))
        T_bin_tcp = make_T(
            rotation_about([1.0, 0.0, 0.0], math.pi) @ rotation_about(rng.normal(size=3), rng.uniform(0, 1.05)),
            (*xy, rng.uniform(0.01, 0.1)),
        )
        q = ik_nearest(b.T_base_bin @ T_bin_tcp, planner.q_reference, planner.config.gripper.T_flange_tcp)
        if q is not None:
            qs.append(q)
    qs = np.array(qs)
    frames = wrist_link_frames(qs)
    gaps = planner.collision.wrist_gap_m(qs)
    T_base_world = invert(world.config.T_world_base)
    touching = []
    for q, T_links, gap in zip(qs, frames, gaps, strict=True):
        d.qpos[arm_q] = q
        mujoco.mj_forward(m, d)
        for T, body in zip(T_links, wrist_bodies, strict=True):
            T_mj = T_base_world @ make_T(d.xmat[body].reshape(3, 3), d.xpos[body])
            assert np.allclose(T, T_mj, atol=1e-9)
        wrist_on_bin = any(
            {m.geom_bodyid[c.geom1], m.geom_bodyid[c.geom2]} & set(wrist_bodies)
            and bin_id in {m.geom_bodyid[c.geom1], m.geom_bodyid[c.geom2]}
            and c.dist < 0
            for c in d.contact[: d.ncon]
        )
        touching.append(wrist_on_bin)
        if wrist_on_bin:
            assert gap < 0.0
    assert len(qs) > 200 and 5 <= sum(touching) < len(qs)  # the sample has both cases
    assert np.all(gaps[~np.array(touching)] > -0.03)  # the boxes are only a little larger than the cylinders


def test_lowest_elbow_point_is_that_of_the_simulated_arms_cylinders():
    from sim.world import CellWorld

    world = CellWorld()
    m, d = world.model, world.data
    arm_q = [m.joint(n).qposadr[0] for n in ur5e.JOINT_NAMES]
    bodies = [m.body(ur5e.LINK_NAMES[i]).id for i in ELBOW_LINKS]
    geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] in bodies]
    assert geoms and all(m.geom_type[g] == mujoco.mjtGeom.mjGEOM_CYLINDER for g in geoms)
    qs = np.random.default_rng(4).uniform(-np.pi, np.pi, (40, 6))
    expected = []
    for q in qs:
        d.qpos[arm_q] = q
        mujoco.mj_forward(m, d)
        low = []
        for g in geoms:  # centre z less the half-length along the axis and the radius across it
            radius, half = m.geom_size[g, 0], m.geom_size[g, 1]
            axis_z = d.geom_xmat[g].reshape(3, 3)[2, 2]
            low.append(d.geom_xpos[g, 2] - abs(axis_z) * half - radius * np.sqrt(1.0 - axis_z**2))
        expected.append(min(low) - world.config.T_world_base[2, 3])
    assert np.allclose(lowest_elbow_point_m(qs), expected, atol=1e-9)


def test_the_grasp_branch_does_not_drift_and_joint_moves_keep_the_elbow_up(planner):
    """Seeded from wherever the arm was, IK drifted pick by pick to a branch with the shoulder turned back; a joint
    move from there to the next grasp swung the elbow down onto the tray (the emulator stopped the arm on its wall).
    The grasp's branch is the reference's whatever the arm's configuration, and the joint moves from an arm left in
    such a configuration keep the upper arm and forearm above min_elbow_height_m."""
    config = PlannerConfig(grasp_params=PARAMS, max_grasps_per_part=20)
    p = GraspPlanner([builtin_part("spur_gear")], config, cache_dir=planner.cache_dir)
    gear = PartEstimate(6, _flat("spur_gear", -0.413, 0.015, yaw_rad=2.99), 0.9)
    q_canonical = ik_nearest(config.T_base_place, p.q_reference, config.gripper.T_flange_tcp)
    q_drifted = np.array([-1.7246, -3.3054, 1.4073, 0.3272, -1.5708, 3.7766])  # the place pose, shoulder turned back
    T_drifted = forward_kinematics(q_drifted, config.gripper.T_flange_tcp)  # over the tray, tool down, turned about z
    assert np.allclose(T_drifted[:3, 2:], config.T_base_place[:3, 2:], atol=1e-3)

    def on_reference_branch(q: np.ndarray) -> bool:  # shoulder, elbow and wrists near the reference's (q6 turns)
        return bool(np.abs(q[:5] - p.q_reference[:5]).max() < np.pi / 2)

    from_canonical = p.plan_parts([gear], q_seed=q_canonical).grasps
    assert from_canonical and all(on_reference_branch(g.q_grasp) for g in from_canonical)
    from_drifted = p.plan_parts([gear], q_seed=q_drifted)
    for g in from_drifted.grasps:
        assert on_reference_branch(g.q_grasp)
        assert lowest_elbow_point_m(_joint_line(q_drifted, g.q_lift)).min() >= config.min_elbow_height_m
    unchecked = GraspPlanner(
        [builtin_part("spur_gear")], replace(config, min_elbow_height_m=None), cache_dir=planner.cache_dir
    )
    unchecked_plan = unchecked.plan_parts([gear], q_seed=q_drifted).grasps
    assert unchecked_plan and all(on_reference_branch(g.q_grasp) for g in unchecked_plan)
    dips = [lowest_elbow_point_m(_joint_line(q_drifted, g.q_lift)).min() for g in unchecked_plan]
    assert min(dips) < config.min_elbow_height_m  # without the check, the elbow goes down
    assert from_drifted.rejections["collision_transit"] > 0


def test_the_early_wall_check_only_refuses_grasps_that_hit_a_wall_at_every_backoff(planner):
    """The cheap wall check before the points check must not refuse a grasp that some allowed backoff would clear:
    for the candidates it refuses, every backoff in the allowed range still hits a wall (swept to the lift)."""
    cfg = planner.config
    g = cfg.gripper
    sweep = max(cfg.pre_grasp_distance_m, cfg.lift_height_m)
    refused = 0
    for x, y, yaw in ((-0.5 + 0.13, 0.0, 0.3), (-0.5, 0.085, 1.0), (-0.5 - 0.125, -0.075, 0.0)):  # near walls
        part = PartEstimate(1, _flat("hex_nut", x, y, yaw), 0.9)
        grasps = planner.candidates(1)
        T = part.T_base_obj @ grasps.T_obj_grasp
        boxes = np.concatenate(
            [
                g.boxes(grasps.opening_m, inner_half_m=grasps.width_m / 2 + cfg.clearance_m),
                g.boxes(grasps.width_m)[:, 2:4],
            ],
            axis=1,
        )
        d_min = np.maximum(planner.collision.floor_backoff(T, boxes, np.clip(-T[:, 2, 2], 0.0, 1.0)), 0.0)
        hit = planner.collision.walls_at_every_backoff(T, boxes, d_min, grasps.contact_z_m, sweep)
        d_max = g.pad_length_m / 2 - grasps.contact_z_m[:, 0] - cfg.min_engagement_m
        for k in np.flatnonzero(hit & (d_max >= d_min)):
            for d in np.linspace(d_min[k], d_max[k], 5):
                back = make_T(t=(0.0, 0.0, -d))
                swept = boxes[k].copy()
                swept[:, 0, 2] -= sweep
                assert planner.collision.wall_gap_m((T[k] @ back)[None], swept[None])[0] < cfg.bin_clearance_m
            refused += 1
    assert refused > 10


def test_with_max_planned_parts_the_best_parts_are_planned_and_the_rest_skipped(planner):
    """Planning only the best parts gives the same best grasps as planning all, and leaves the others unchecked."""
    parts = [
        PartEstimate(1, _flat("hex_nut", -0.55 + 0.05 * k, 0.05 * (k % 2) - 0.025, yaw_rad=0.4 * k), 0.5 + 0.1 * k)
        for k in range(4)
    ]
    one = GraspPlanner(
        [builtin_part("hex_nut")], PlannerConfig(grasp_params=PARAMS, max_planned_parts=1), cache_dir=planner.cache_dir
    )
    full, lazy = planner.plan_parts(parts), one.plan_parts(parts)
    assert len({g.part_index for g in full.grasps}) == 4
    assert lazy.best.part_index == full.best.part_index and lazy.best.score == pytest.approx(full.best.score)
    statuses = [p.status for p in lazy.parts]
    assert statuses.count("planned") == 1 and statuses.count("not_planned") == 3
    skipped = [p for p in lazy.parts if p.status == "not_planned" and sum(p.rejections.values()) == 0]
    assert skipped, "a part that cannot beat the planned one is not checked at all"


def test_grasps_narrower_than_min_grasp_width_are_not_used(planner):
    """A sheet pinch (2 mm across the L-bracket's sheet) is a candidate by default (``min_grasp_width_m`` 0) and is
    dropped, with every other candidate narrower than the minimum, when the minimum is above it."""
    bracket = builtin_part("l_bracket")
    all_widths = grasp_candidates(bracket, PARAMS, cache_dir=planner.cache_dir).width_m
    assert (all_widths < 0.004).any() and (all_widths >= 0.004).any()  # across the sheet, and across the bracket
    pinching = GraspPlanner([bracket], PlannerConfig(grasp_params=PARAMS), cache_dir=planner.cache_dir)
    assert len(pinching.candidates(4)) == len(all_widths)
    no_pinch = PlannerConfig(grasp_params=PARAMS, min_grasp_width_m=0.004)
    p = GraspPlanner([bracket], no_pinch, cache_dir=planner.cache_dir)
    assert len(p.candidates(4)) == int((all_widths >= 0.004).sum())
    assert p.candidates(4).width_m.min() >= 0.004


def test_an_unreachable_part_gives_nothing_safe_with_the_reason(planner):
    # a bin beyond the UR5e's 0.85 m reach, and a nut in it
    far_bin = BinGeometry(T_base_bin=make_T(t=(1.4, 0.2, FLOOR_Z)))
    config = PlannerConfig(grasp_params=PARAMS, bin=far_bin, q_reference_rad=tuple(ur5e.HOME_Q))
    far = GraspPlanner([builtin_part("hex_nut")], config, cache_dir=planner.cache_dir)
    plan = far.plan_parts([PartEstimate(1, _flat("hex_nut", 1.4, 0.2), 0.9)])
    assert plan.nothing_safe and plan.best is None
    assert plan.parts[0].status == "unreachable"
    assert plan.rejections["unreachable"] > 0
    assert set(plan.rejections) == set(REJECTION_CAUSES)
    summary = plan.summary()
    assert summary.startswith("nothing safe to pick") and "unreachable" in summary
    # in reach of the arm, but the cell's workspace box (the robot refuses motion outside it) ends below the lift
    from robot.ur_config import WorkspaceBox

    low_box = WorkspaceBox((-0.85, -0.65, 0.0), (0.1, 0.45, 0.15))
    boxed = GraspPlanner(
        [builtin_part("hex_nut")], PlannerConfig(grasp_params=PARAMS, workspace=low_box), cache_dir=planner.cache_dir
    )
    nut = PartEstimate(1, _flat("hex_nut", -0.5, 0.0), 0.9)
    assert not planner.plan_parts([nut]).nothing_safe
    assert boxed.plan_parts([nut]).parts[0].status == "unreachable"


def test_parts_outside_the_bin_are_not_planned_and_do_not_count_as_in_it(planner):
    """The camera also sees the place tray: a part lying there is outside the bin, never planned (the planner does
    not know the tray's walls), and a plan with only such parts says the bin is empty."""
    in_tray = PartEstimate(1, _flat("hex_nut", -0.2, -0.40, on_z=0.01), 0.9)
    in_bin = PartEstimate(1, _flat("hex_nut", -0.5, 0.0), 0.9)
    plan = planner.plan_parts([in_tray, in_bin])
    assert [p.status for p in plan.parts] == ["outside_bin", "planned"] and plan.n_in_bin == 1
    assert {g.part_index for g in plan.grasps} == {1}
    only_tray = planner.plan_parts([in_tray])
    assert only_tray.nothing_safe and only_tray.n_in_bin == 0 and "outside_bin" in only_tray.summary()
    above = PartEstimate(1, make_T(t=(-0.5, 0.0, 0.6)), 0.9)  # held or falling above the bin: still the bin's
    assert planner.plan_parts([above]).parts[0].status != "outside_bin"


def test_part_level_refusals_are_results_not_errors(planner):
    nut = _flat("hex_nut", -0.5, 0.0)
    strict = GraspPlanner([builtin_part("hex_nut")], PlannerConfig(grasp_params=PARAMS, min_pose_score=0.5),
                          cache_dir=planner.cache_dir)  # fmt: skip
    plan = strict.plan_parts([PartEstimate(1, nut, 0.2), PartEstimate(42, nut, 0.9)])
    assert plan.nothing_safe
    assert [p.status for p in plan.parts] == ["low_confidence", "no_model"]
    assert plan.rejections["low_confidence"] == plan.parts[0].n_candidates and plan.rejections["no_model"] == 1
    assert strict.plan_parts([]).nothing_safe


def test_successive_picks_are_let_go_side_by_side_over_the_simulated_tray(planner):
    from sim.cell_config import CellConfig

    cfg, cell = planner.config, CellConfig()
    nx, ny = cfg.place_grid
    slots = np.array([cfg.place_pose_at(k)[:3, 3] for k in range(nx * ny)])
    # every slot apart from the others by at least the smaller pitch, all at the place pose's height and centred on it
    gaps = np.linalg.norm(slots[:, None, :2] - slots[None, :, :2], axis=-1) + np.eye(nx * ny)
    assert gaps.min() >= min(cfg.place_pitch_m) - 1e-9
    np.testing.assert_allclose(slots[:, 2], cfg.T_base_place[2, 3])
    np.testing.assert_allclose(slots.mean(axis=0), cfg.T_base_place[:3, 3], atol=1e-12)
    # the held part's box is centred on its slot: the longest built-in part (an L-bracket, 57 mm) at any slot, either
    # way round, lies inside the tray's floor with 10 mm to spare for its bounce; a 10-part bin needs no slot twice
    T_base_tray = invert(cell.T_world_base) @ cell.T_world_tray
    half = np.array(cell.tray_inner_size_m[:2]) / 2
    reach = builtin_part("l_bracket").mesh.extents.max() / 2 + 0.010
    assert np.all(np.abs(slots[:, :2] - T_base_tray[:2, 3]) + reach <= half)
    assert nx * ny >= 10
    # the grid repeats, and the planned pick lets go at the slot asked for, pointing down
    np.testing.assert_allclose(cfg.place_pose_at(nx * ny + 4), cfg.place_pose_at(4))
    plan = planner.plan_parts([PartEstimate(1, _flat("hex_nut", -0.45, 0.03, yaw_rad=1.0), 0.9)], place_slot=4)
    np.testing.assert_allclose(_held_box_centre(plan.best)[:2], slots[4, :2], atol=1e-12)
    np.testing.assert_allclose(plan.best.T_base_place[:3, 2], [0.0, 0.0, -1.0], atol=1e-9)


def test_a_long_part_held_near_one_end_is_let_go_centred_on_its_slot(planner):
    """An L-bracket (57 mm long) held near one end: the place pose moves the tool so that the held part's box, not
    the pads, is centred on the slot, and the part at every slot lies inside the simulated tray's floor."""
    from sim.cell_config import CellConfig

    cell = CellConfig()
    bracket = builtin_part("l_bracket")
    config = PlannerConfig(grasp_params=PARAMS, max_grasps_per_part=20)
    p = GraspPlanner([bracket], config, cache_dir=planner.cache_dir)
    T_base_tray = invert(cell.T_world_base) @ cell.T_world_tray
    half = np.array(cell.tray_inner_size_m[:2]) / 2
    off_centre = 0.0
    for slot in range(config.place_grid[0] * config.place_grid[1]):
        plan = p.plan_parts([PartEstimate(4, _flat("l_bracket", -0.45, 0.03, yaw_rad=0.5), 0.9)], place_slot=slot)
        assert plan.grasps, plan.summary()
        for g in plan.grasps:
            box = _held_box_base(g, "l_bracket")
            np.testing.assert_allclose(box.mean(axis=0)[:2], config.place_pose_at(slot)[:2, 3], atol=1e-9)
            assert np.all(np.abs(box[:, :2] - T_base_tray[:2, 3]) <= half)
            off_centre = max(off_centre, float(np.linalg.norm(g.T_base_place[:2, 3] - box.mean(axis=0)[:2])))
    assert off_centre > 0.015  # some grasps hold the bracket well off its centre: the move is not a no-op


def _held_box_base(g, name: str) -> np.ndarray:
    """``(8, 3)`` the corners (base frame) of the planner's box around the built-in part ``name`` held by the planned
    grasp ``g`` (axis-aligned in the TCP frame), at its place pose."""
    T_base_obj = g.T_base_place @ invert(g.T_base_grasp) @ g.T_base_obj
    box = part_box_tcp(g.T_base_place[None], T_base_obj, builtin_part(name).bounds_m)
    return transform_points(g.T_base_place, box_corners(box))


def _held_box_centre(g, name: str = "hex_nut") -> np.ndarray:
    return _held_box_base(g, name).mean(axis=0)


def test_where_the_gripper_met_something_the_next_plan_keeps_its_fingers_clear_of(planner):
    """A touch (the TCP pose an approach stopped at on contact, the pads' opening) is an obstacle owned by no part:
    the replanned grasps keep the fingers, along their line down, ``clearance_m`` from the leading faces of the
    fingers where they stopped, even though those lie beside the part's own surface; the part does not count as
    covered by it."""
    cfg = planner.config
    part = PartEstimate(5, _lying_pipe(-0.45, 0.03, (1.0, 0.3)), 0.9)  # 50 mm long: grasps all along it
    before = planner.plan_parts([part])
    g = before.best
    T_stop = g.T_base_grasp @ make_T(t=(0.0, 0.0, -0.006))  # 6 mm short of the grasp
    after = planner.plan_parts([part], touches=[(T_stop, g.opening_width_m)])
    assert after.grasps, after.summary()
    assert after.parts[0].covered_fraction == before.parts[0].covered_fraction
    fingers = cfg.gripper.boxes(g.opening_width_m)[FINGER_BOXES]
    lo, hi = fingers[:, 0], fingers[:, 1]
    faces = np.array(
        [[x, y, h[2]] for lo_, h in zip(lo, hi, strict=True) for x in (lo_[0], h[0]) for y in (lo_[1], h[1])]
    )
    touched = transform_points(T_stop, faces)
    for k in after.grasps:
        for T in (k.T_base_pregrasp, k.T_base_grasp):
            local = transform_points(invert(T), touched)[None]
            boxes = cfg.gripper.boxes(k.opening_width_m)[FINGER_BOXES][None]
            assert points_box_distance_m(local, boxes)[0] >= cfg.clearance_m - 1e-9
    # the grasp before is no longer planned as it was
    assert not any(np.allclose(k.T_base_grasp, g.T_base_grasp) for k in after.grasps)


def test_bad_settings_and_inputs_are_refused_with_the_field_name(planner):
    with pytest.raises(ValueError, match="place_grid"):
        PlannerConfig(place_grid=(0, 2))
    with pytest.raises(ValueError, match="place_pitch_m"):
        PlannerConfig(place_pitch_m=(0.07, -0.01))
    with pytest.raises(ValueError, match="approach_cone_deg"):
        PlannerConfig(approach_cone_deg=0.0)
    with pytest.raises(ValueError, match="T_base_place"):
        PlannerConfig(T_base_place=np.eye(3))
    with pytest.raises(ValueError, match="friction_coefficient"):
        GraspSetParams(friction_coefficient=0.0)
    with pytest.raises(ValueError, match="without its intrinsics"):
        planner.plan([], np.eye(4), np.zeros((4, 4), dtype=np.float32), None)
    with pytest.raises(ValueError, match="intrinsics are for"):
        planner.plan([], np.eye(4), np.zeros((4, 4), dtype=np.float32), CameraIntrinsics.from_fov(8, 6, 40.0))


# ---------------------------------------------------------------------------------------------- helpers


def _pose(obj_id: int, T_camera_object: np.ndarray, score: float = 0.9) -> ObjectPose:
    return ObjectPose(Detection(0, obj_id, 0.99, np.zeros(4)), T_camera_object, score, "test")


def _render_depth(parts, K: CameraIntrinsics, T_base_camera: np.ndarray) -> np.ndarray:
    """A depth frame (metres along the camera z) of parts on the bin floor, by ray casting the meshes."""
    meshes = [model.mesh.copy().apply_transform(T) for model, T in parts]
    floor = trimesh.creation.box((0.3, 0.2, 0.02), make_T(t=(-0.5, 0.0, FLOOR_Z - 0.01)))
    scene = trimesh.util.concatenate([*meshes, floor])
    u, v = np.meshgrid(np.arange(K.width), np.arange(K.height))
    rays_cam = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, dtype=float)], axis=-1).reshape(-1, 3)
    origins = np.repeat(T_base_camera[None, :3, 3], len(rays_cam), axis=0)
    directions = rays_cam @ T_base_camera[:3, :3].T
    hits, index, _ = scene.ray.intersects_location(origins, directions, multiple_hits=False)
    depth = np.zeros(len(rays_cam), dtype=np.float32)
    depth[index] = (hits - origins[index]) @ T_base_camera[:3, 2]  # distance along the camera z axis
    return depth.reshape(K.height, K.width)


def test_a_pose_whose_depth_refinement_was_refused_is_not_picked(planner):
    """The RGB estimate alone is centimetres off on the shipped models: a part whose ICP kept it is left alone,
    while a refined pose, and a pose that was never refined (ground truth), are planned."""
    T_base_nut = _flat("hex_nut", -0.5, 0.0, yaw_rad=0.3)
    plans = {r: planner.plan_parts([PartEstimate(1, T_base_nut, 0.9, refined=r)]) for r in (True, False, None)}
    assert not plans[True].nothing_safe and not plans[None].nothing_safe
    assert plans[False].nothing_safe and plans[False].parts[0].status == "unrefined"
    detection = Detection(0, 1, 0.9, np.array([0.0, 0.0, 10.0, 10.0]))
    kept = ObjectPose(detection, np.eye(4), 0.9, "direct", {"icp": {"status": "kept_initial"}})
    assert not planner.plan([kept], T_base_nut).grasps  # the status travels from the pose into the plan


def test_the_covered_area_of_the_bin_tells_an_empty_bin_from_unseen_parts(planner):
    """``pile_area_m2`` (the picker's check when nothing is detected): the top of a gear lying flat, seen from
    above, against the empty bin's floor."""
    T_base_camera = make_T(np.diag([1.0, -1.0, -1.0]), (-0.5, 0.0, 0.52))
    K = CameraIntrinsics.from_fov(160, 120, 40.0)
    empty = _render_depth([], K, T_base_camera)
    assert planner.pile_area_m2(empty, K, T_base_camera) == 0.0
    gear = builtin_part("spur_gear")
    with_gear = _render_depth([(gear, _flat("spur_gear", -0.52, 0.01))], K, T_base_camera)
    disc_m2 = np.pi * (max(gear.mesh.extents) / 2) ** 2  # lying flat, its outline is about its tip circle
    assert planner.pile_area_m2(with_gear, K, T_base_camera) == pytest.approx(disc_m2, rel=0.15)  # 7.8 / 8.5 cm2


def test_a_part_whose_origin_is_not_its_centre_is_judged_in_the_bin_by_its_centre(cache_dir):
    """A CAD file may put the origin anywhere: here at the bottom of a nut (as a duct cover's file puts it at one
    end), resting on the floor with its origin a hair below it. The bin test uses the middle of its bounding box."""
    nut = builtin_part("hex_nut")
    mesh = nut.mesh.copy()
    mesh.apply_translation([0.0, 0.0, -mesh.bounds[0, 2]])  # origin at the bottom face
    based = ObjectModel(obj_id=1, name="nut_origin_at_base", mesh=mesh)
    planner = GraspPlanner([based], PlannerConfig(grasp_params=PARAMS), cache_dir=cache_dir)
    resting = make_T(t=(-0.5, 0.0, FLOOR_Z - 0.2 * MM))
    assert planner.plan_parts([PartEstimate(1, resting, 0.9)]).parts[0].status != "outside_bin"
    in_tray = make_T(t=(-0.2, -0.40, 0.01))
    assert planner.plan_parts([PartEstimate(1, in_tray, 0.9)]).parts[0].status == "outside_bin"
