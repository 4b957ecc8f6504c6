"""perception.refine on render-free synthetic depth: the visible surface of a built-in part is ray-cast (open3d) at a
known pose, the pose is perturbed by a few millimetres and degrees, and ICP must bring it back."""

from __future__ import annotations

import cv2
import numpy as np
import open3d as o3d
import pytest

from perception.refine import DepthRefiner, RefineConfig, masked_depth_points, refine_pose, visible_model_points
from perception.results import Detection, ObjectPose
from sygrid.camera import CameraIntrinsics
from sygrid.metrics import symmetric_pose_errors
from sygrid.objects.model import ObjectModel
from sygrid.objects.parts import builtin_part
from sygrid.transforms import make_T, rotation_about

CAMERA = CameraIntrinsics.from_fov(320, 240, 40.0)


def raycast_depth(model: ObjectModel, T_camera_object: np.ndarray, camera: CameraIntrinsics) -> np.ndarray:
    """(h, w) float32 z-depth [m] of the model at the pose, 0 where the ray misses (open3d ray casting)."""
    scene = o3d.t.geometry.RaycastingScene()
    R, t = T_camera_object[:3, :3], T_camera_object[:3, 3]
    vertices = (np.asarray(model.mesh.vertices) @ R.T + t).astype(np.float32)
    scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(np.asarray(model.mesh.faces, dtype=np.uint32)))
    K = camera.K.copy()
    K[:2, 2] += 0.5  # open3d casts through u + 0.5; our pixel centres are the integers
    rays = scene.create_rays_pinhole(o3d.core.Tensor(K), o3d.core.Tensor(np.eye(4)), camera.width, camera.height)
    depth = scene.cast_rays(rays)["t_hit"].numpy()  # the ray directions have z = 1: t is the z-depth
    depth[~np.isfinite(depth)] = 0.0
    return depth.astype(np.float32)


def _pose(model: ObjectModel, mask: np.ndarray, T: np.ndarray) -> ObjectPose:
    ys, xs = np.nonzero(mask) if mask.any() else (np.array([0]), np.array([0]))
    box = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], float)
    return ObjectPose(Detection(0, model.obj_id, 0.9, box, mask), T, 0.8, "direct", {"inliers": 12})


def _perturbed(T_true: np.ndarray, axis: list[float], deg: float, shift_mm: list[float]) -> np.ndarray:
    T = T_true @ make_T(rotation_about(np.array(axis), np.radians(deg)))
    T[:3, 3] += np.array(shift_mm) * 1e-3
    return T


T_NUT = make_T(rotation_about(np.array([1.0, 0.4, 0.0]), np.radians(35)), [0.01, -0.005, 0.3])
T_BRACKET = make_T(rotation_about(np.array([0.3, 1.0, 0.5]), np.radians(120)), [-0.01, 0.01, 0.35])


@pytest.mark.parametrize(
    ("name", "T_true", "axis", "deg", "shift_mm"),
    [
        ("hex_nut", T_NUT, [0.2, 1.0, 0.3], 4.0, [2.0, -1.5, 2.5]),
        ("l_bracket", T_BRACKET, [1.0, -0.5, 0.2], 3.0, [-3.0, 2.0, 1.0]),
    ],
)
def test_icp_brings_a_perturbed_pose_back(name: str, T_true: np.ndarray, axis, deg, shift_mm):
    model = builtin_part(name)
    depth = raycast_depth(model, T_true, CAMERA)
    mask = depth > 0
    assert mask.sum() > 300
    T_init = _perturbed(T_true, axis, deg, shift_mm)
    symmetries = model.symmetry_transforms()
    re0, te0 = symmetric_pose_errors(T_init, T_true, symmetries)
    assert re0 > 2.5 and te0 > 0.003

    refined = DepthRefiner(seed=0).refine(_pose(model, mask, T_init), depth, CAMERA, model)
    re, te = symmetric_pose_errors(refined.T_camera_object, T_true, symmetries)
    assert re < 1.0, f"rotation error {re:.3f} deg (was {re0:.2f})"
    assert te < 0.001, f"translation error {te * 1e3:.3f} mm (was {te0 * 1e3:.2f})"
    assert refined.method == "direct+icp" and refined.score == 0.8
    icp = refined.details["icp"]
    assert icp["status"] == "refined" and icp["fitness"] > 0.9 and icp["inlier_rmse_m"] < 0.001
    assert 1 <= icp["iterations"] <= 2 * RefineConfig().max_iterations and icp["time_ms"] > 0
    assert icp["scene_points"] >= RefineConfig().min_scene_points
    assert refined.details["inliers"] == 12  # the estimator's own details are kept
    # The same input gives the same answer.
    again = refine_pose(_pose(model, mask, T_init), depth, CAMERA, model)
    np.testing.assert_allclose(again.T_camera_object, refined.T_camera_object, atol=1e-12)


def test_too_few_depth_points_keep_the_initial_pose():
    model = builtin_part("hex_nut")
    depth = raycast_depth(model, T_NUT, CAMERA)
    solid = cv2.erode((depth > 0).astype(np.uint8), np.ones((5, 5), np.uint8))  # 5 x 5 blocks all on the nut
    v, u = np.argwhere(solid)[len(np.argwhere(solid)) // 2]
    mask = np.zeros(depth.shape, bool)
    mask[v - 2 : v + 3, u - 2 : u + 3] = True  # 25 pixels, 9 after the 1-pixel erosion
    T_init = _perturbed(T_NUT, [0, 1, 0], 3.0, [2, 0, 0])
    kept = DepthRefiner().refine(_pose(model, mask, T_init), depth, CAMERA, model)
    assert kept.details["icp"]["status"] == "kept_initial"
    assert kept.details["icp"]["reason"] == "9 depth points in the mask, fewer than 30"
    assert kept.method == "direct"
    np.testing.assert_array_equal(kept.T_camera_object, T_init)


def test_no_mask_keeps_the_pose_and_a_far_initial_translation_is_recovered_from_depth():
    model = builtin_part("hex_nut")
    depth = raycast_depth(model, T_NUT, CAMERA)
    no_mask = ObjectPose(Detection(0, model.obj_id, 0.9, np.array([0.0, 0, 10, 10])), T_NUT, 0.8, "pnp")
    kept = DepthRefiner().refine(no_mask, depth, CAMERA, model)
    assert kept.details["icp"]["reason"] == "the detection has no mask to select depth pixels"
    # An initial pose 30 mm off (1.3 diameters) and 40 mm too far (an RGB estimate's typical depth error): the
    # start is moved to the depth inside the mask, and ICP takes it from there.
    far = _perturbed(T_NUT, [0, 1, 0], 2.0, [30, 0, 40])
    refined = DepthRefiner().refine(_pose(model, depth > 0, far), depth, CAMERA, model)
    assert refined.details["icp"]["status"] == "refined" and refined.details["icp"]["start_shift_m"] > 0.03
    re, te = symmetric_pose_errors(refined.T_camera_object, T_NUT, model.symmetry_transforms())
    assert re < 1.0 and te < 0.001, (re, te)


def test_diverging_icp_is_rejected():
    # Depth of a flat plate where the mask says "nut": ICP slides the nut onto the plate, far from where it
    # started, and the correction check must refuse the result.
    model = builtin_part("hex_nut")
    mask = raycast_depth(model, T_NUT, CAMERA) > 0
    plate = np.where(mask, np.float32(T_NUT[2, 3] + 0.009), np.float32(0))
    config = RefineConfig(max_correction_fraction=0.05, min_fitness=0.0)
    kept = DepthRefiner(config).refine(_pose(model, mask, T_NUT), plate, CAMERA, model)
    assert kept.details["icp"]["status"] == "kept_initial"
    assert "diverged" in kept.details["icp"]["reason"] or "turned" in kept.details["icp"]["reason"]
    assert kept.details["icp"]["iterations"] >= 1
    np.testing.assert_array_equal(kept.T_camera_object, T_NUT)


def test_backface_culling_keeps_the_side_facing_the_camera():
    points = np.array([[0, 0, 0.01], [0, 0, -0.01]])
    normals = np.array([[0, 0, 1.0], [0, 0, -1.0]])  # top and bottom of a plate
    T = make_T(t=[0, 0, 0.5])  # the camera looks along +z at the bottom face (z = -0.01, normal -z)
    p, n = visible_model_points(T, points, normals)
    np.testing.assert_allclose(p, [[0, 0, 0.49]])
    np.testing.assert_allclose(n, [[0, 0, -1.0]])


def test_masked_depth_points_unproject_the_mask():
    depth = np.zeros((CAMERA.height, CAMERA.width), np.float32)
    depth[100:110, 150:160] = 0.5
    depth[105, 155] = np.nan
    mask = np.zeros(depth.shape, bool)
    mask[100:105, 150:153] = True
    points = masked_depth_points(depth, mask, CAMERA)
    assert points.shape == (15, 3)
    np.testing.assert_allclose(points[:, 2], 0.5)
    np.testing.assert_allclose(
        points[0, :2], [(150 - CAMERA.cx) * 0.5 / CAMERA.fx, (100 - CAMERA.cy) * 0.5 / CAMERA.fy]
    )
    assert masked_depth_points(depth, mask, CAMERA, erosion_px=1).shape == (3, 3)


def test_bad_inputs():
    model = builtin_part("hex_nut")
    depth = raycast_depth(model, T_NUT, CAMERA)
    pose = _pose(model, depth > 0, T_NUT)
    with pytest.raises(ValueError, match=r"depth_m: expected shape \(240, 320\)"):
        DepthRefiner().refine(pose, depth[:100], CAMERA, model)
    with pytest.raises(ValueError, match="obj_id 3 is not the pose's obj_id 1"):
        DepthRefiner().refine(pose, depth, CAMERA, builtin_part("washer"))
    with pytest.raises(ValueError, match="correspondence_fractions"):
        RefineConfig(correspondence_fractions=())
    with pytest.raises(ValueError, match="min_fitness"):
        RefineConfig(min_fitness=1.5)


@pytest.mark.parametrize("name", ["hex_nut", "hex_bolt"])
def test_a_rotation_far_outside_icps_basin_is_recovered_from_the_clouds_principal_axes(name: str):
    model = builtin_part(name)
    T_true = make_T(rotation_about(np.array([1.0, 0.3, 0.0]), np.radians(25)), [0.0, 0.01, 0.3])
    depth = raycast_depth(model, T_true, CAMERA)
    T_init = _perturbed(T_true, [1.0, 0.0, 0.0], 70.0, [4.0, -3.0, 25.0])  # axis 70 deg off, 25 mm too far
    symmetries = model.symmetry_transforms()
    assert symmetric_pose_errors(T_init, T_true, symmetries)[0] > 60
    pose = _pose(model, depth > 0, T_init)
    refined = DepthRefiner(RefineConfig(max_correction_deg=180.0)).refine(pose, depth, CAMERA, model)
    re, te = symmetric_pose_errors(refined.T_camera_object, T_true, symmetries)
    assert refined.details["icp"]["hypotheses"] == 5  # ICP ran from the one that fitted best at the start
    assert re < 5.0 and te < 0.0015, (re, te)
    # ICP alone, with the default 30 deg guard: it either does not get there (open3d's end point varies from run to
    # run: 3.5-30 deg seen) or gets there only by turning more than the guard trusts, and keeps the estimate
    alone = DepthRefiner(RefineConfig(pca_hypotheses=False)).refine(pose, depth, CAMERA, model)
    assert symmetric_pose_errors(alone.T_camera_object, T_true, symmetries)[0] > 5.0


class _RefusesFirst(DepthRefiner):
    """Refuses the first ICP result it is asked about, as if that start had diverged."""

    def __init__(self, config: RefineConfig) -> None:
        super().__init__(config)
        self.refused: list[int] = []

    def _refusal(self, fit, diameter):
        key = id(fit)
        if not self.refused or self.refused[0] == key:
            self.refused[:1] = [key]
            return "refused for the test"
        return super()._refusal(fit, diameter)


def test_a_refused_icp_run_falls_back_to_the_next_start():
    model = builtin_part("hex_nut")
    depth = raycast_depth(model, T_NUT, CAMERA)
    pose = _pose(model, depth > 0, _perturbed(T_NUT, [0.2, 1.0, 0.3], 4.0, [2.0, -1.5, 2.5]))
    refined = _RefusesFirst(RefineConfig()).refine(pose, depth, CAMERA, model)
    assert refined.details["icp"]["status"] == "refined" and refined.details["icp"]["fallback_runs"] == 1
    re, te = symmetric_pose_errors(refined.T_camera_object, T_NUT, model.symmetry_transforms())
    assert re < 2.0 and te < 0.001
    kept = _RefusesFirst(RefineConfig(fallback_starts=0)).refine(pose, depth, CAMERA, model)
    assert kept.details["icp"]["status"] == "kept_initial" and kept.details["icp"]["reason"] == "refused for the test"
    with pytest.raises(ValueError, match="fallback_starts >= 0"):
        RefineConfig(fallback_starts=-1)


def test_the_floor_seen_through_a_nuts_hole_stands_it_on_edge_unless_the_floor_is_removed():
    from perception.pipeline import without_floor

    # A nut lying flat on a floor, seen from above; the mask is its filled outline (a detector's mask at bin
    # scale), so a third of the masked depth is the floor through the hole, one nut thickness below the top face.
    model = builtin_part("hex_nut")
    T_true = make_T(rotation_about(np.array([0.0, 0.0, 1.0]), 0.3), [0.005, -0.004, 0.3])
    nut = raycast_depth(model, T_true, CAMERA)
    floor_z = 0.3 + float(np.asarray(model.mesh.vertices)[:, 2].max())
    depth = np.where(nut > 0, nut, floor_z).astype(np.float32)
    mask = np.zeros(depth.shape, np.uint8)
    cv2.fillConvexPoly(mask, cv2.convexHull(np.argwhere(nut > 0)[:, ::-1].astype(np.int32)), 1)
    mask = mask.astype(bool)
    assert (mask & (nut == 0)).sum() > 0.25 * mask.sum()
    pose = _pose(model, mask, _perturbed(T_true, [1.0, 1.0, 0.0], 15.0, [1.5, -1.0, 2.0]))

    def axis_error_deg(refined: ObjectPose) -> float:
        return float(np.degrees(np.arccos(min(1.0, abs(refined.T_camera_object[:3, 2] @ T_true[:3, 2])))))

    # the floor layer and the top face fit a nut on edge about as well as the flat one: ICP stands it up
    assert axis_error_deg(DepthRefiner().refine(pose, depth, CAMERA, model)) > 45.0
    floor_plane = np.array([0.0, 0.0, -1.0, floor_z])  # height above the floor = floor_z - z
    bare = without_floor(depth, CAMERA, floor_plane, 0.0015)
    assert bare.dtype == np.float32 and np.all(bare[nut > 0] == depth[nut > 0]) and np.all(bare[nut == 0] == 0)
    refined = DepthRefiner().refine(pose, bare, CAMERA, model)
    assert refined.details["icp"]["status"] == "refined"
    assert axis_error_deg(refined) < 2.0
    assert np.linalg.norm(refined.T_camera_object[:3, 3] - T_true[:3, 3]) < 0.0005


def test_a_wrong_class_fit_passes_a_loose_acceptance_and_fails_the_cells():
    # An L-bracket lying on a leg, seen from above (the other leg points at the camera), and a detector that called
    # it a gear (what the built-in detector does with most of them at the cell camera's scale). ICP puts the
    # gear's face on the bracket's leg: at the default acceptance (30 % of the depth on the model) that passes,
    # at the simulated cell's (80 %) it does not, while the L-bracket itself fits all its depth either way.
    bracket, gear = builtin_part("l_bracket"), builtin_part("spur_gear")
    R_camera_world = np.diag([1.0, -1.0, -1.0])  # looking straight down
    lying = rotation_about(np.array([0.0, 0.0, 1.0]), 1.9) @ rotation_about(np.array([0.0, 1.0, 0.0]), np.pi / 4)
    T_true = make_T(R_camera_world @ lying, [0.01, -0.005, 0.35])
    depth = raycast_depth(bracket, T_true, CAMERA)
    mask = depth > 0
    as_gear = _pose(gear, mask, make_T(R_camera_world, T_true[:3, 3]))  # a gear lying flat where the part is
    near = _pose(bracket, mask, _perturbed(T_true, [1.0, 0.0, 0.0], 3.0, [2.0, 0.0, 0.0]))
    loose, strict = DepthRefiner(RefineConfig(min_fitness=0.3)), DepthRefiner(RefineConfig(min_fitness=0.8))
    gear_fit = loose.refine(as_gear, depth, CAMERA, gear).details["icp"]
    assert gear_fit["status"] == "refined" and gear_fit["fitness"] < 0.6
    refused = strict.refine(as_gear, depth, CAMERA, gear).details["icp"]
    assert refused["status"] == "kept_initial" and "below 0.8" in refused["reason"]
    right = strict.refine(near, depth, CAMERA, bracket)
    assert right.details["icp"]["status"] == "refined" and right.details["icp"]["fitness"] > 0.95
    rotation_deg, shift_m = symmetric_pose_errors(right.T_camera_object, T_true, bracket.symmetry_transforms(360))[:2]
    assert rotation_deg < 5.0 and shift_m < 0.004  # the cell diagnostic's "right pose"
