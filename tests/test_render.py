"""Rendering: variant choice, metric depth, instance ids and masks, determinism.

Tiny renders (64x48, 4 spp) of hand-placed boxes, so the expected depths and pixels are known exactly.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from sygrid.camera import CameraIntrinsics, project_points
from sygrid.objects.model import ObjectModel
from sygrid.physics import Instance
from sygrid.render import (
    VARIANTS,
    choose_variant,
    look_at_T_world_camera,
    material_bsdf,
    render_item,
    sample_T_world_camera,
)
from sygrid.render.variant import find_libllvm
from sygrid.scene import CameraPoseSampling, parse_scene
from sygrid.transforms import make_T

W, H = 64, 48
CAM_HEIGHT_M = 0.6
BOX_HEIGHT_M = 0.02


def _scene(spp: int = 4):
    return parse_scene({"objects": [{"builtin": "hex_nut"}], "render": {"spp": spp, "max_depth": 4}})


def _box(material: str, size=(0.04, 0.04, BOX_HEIGHT_M), obj_id: int = 1) -> ObjectModel:
    return ObjectModel(
        obj_id=obj_id, name=f"box_{material}", mesh=trimesh.creation.box(extents=size), material=material
    )


def _pile():
    """Instance 0: a box at the bin centre; instance 1: a box to its +x; instance 2: a thin plate lying on top
    of instance 0, overlapping it (so instance 0 is partly hidden)."""
    models = [_box("steel"), _box("painted", obj_id=2), _box("brass", size=(0.03, 0.015, 0.004), obj_id=3)]
    instances = [Instance(0, 0), Instance(1, 1), Instance(2, 2)]
    T = np.stack(
        [
            make_T(t=[0.0, 0.0, BOX_HEIGHT_M / 2]),
            make_T(t=[0.08, 0.0, BOX_HEIGHT_M / 2]),
            make_T(t=[0.01, 0.0, BOX_HEIGHT_M + 0.002]),
        ]
    )
    return models, instances, T


def _top_down() -> np.ndarray:
    return look_at_T_world_camera(np.array([0.0, 0.0, CAM_HEIGHT_M]), np.zeros(3))


@pytest.fixture(scope="module")
def item():
    models, instances, T = _pile()
    K = CameraIntrinsics.from_fov(W, H, 45.0)
    res = render_item(_scene(), models, instances, T, _top_down(), K, np.random.default_rng(7))
    return models, instances, T, K, res


def test_variant_choice_is_valid_and_cached():
    v = choose_variant()
    assert v in VARIANTS
    assert choose_variant() == v
    lib = find_libllvm()
    assert lib is None or "libLLVM" in lib.name


def test_unknown_variant_and_material_name_the_choices():
    with pytest.raises(ValueError, match="unknown Mitsuba variant 'no_such'"):
        choose_variant("no_such")
    with pytest.raises(ValueError, match="valid materials: steel"):
        material_bsdf("gold", np.random.default_rng(0))


def test_result_types_and_shapes(item):
    _, instances, _, _, res = item
    assert res.rgb.shape == (H, W, 3) and res.rgb.dtype == np.uint8
    assert res.depth_m.shape == (H, W) and res.depth_m.dtype == np.float32
    assert res.ids_visib.shape == (H, W) and res.ids_visib.dtype == np.int32
    assert res.masks_full.shape == (len(instances), H, W) and res.masks_full.dtype == bool
    assert 20 < res.rgb.mean() < 250  # lit, not blown out


def test_depth_is_camera_z_of_flat_surfaces(item):
    _, _, _, K, res = item
    # The box top (instance 0's visible part) at z = BOX_HEIGHT_M, the bin floor at z = 0.
    top = res.ids_visib == 1
    assert top.sum() > 5
    np.testing.assert_allclose(res.depth_m[top], CAM_HEIGHT_M - BOX_HEIGHT_M, atol=1e-3)
    # A point of the bin's inner floor away from the parts: depth is camera z (0.6 m), not ray length.
    p_camera = np.linalg.inv(_top_down()) @ np.array([-0.09, 0.06, 0.0, 1.0])
    u, v = np.rint(project_points(K.K, p_camera[None, :3])[0]).astype(int)
    assert res.ids_visib[v, u] == 0
    np.testing.assert_allclose(res.depth_m[v, u], CAM_HEIGHT_M, atol=1e-3)
    off_axis = np.hypot(u - K.cx, v - K.cy) / K.fx
    assert off_axis > 0.1  # far enough off the axis for ray length and camera z to differ by > 3 mm


def test_ids_have_depth_and_visible_masks_are_subsets(item):
    _, instances, _, _, res = item
    assert (res.depth_m[res.ids_visib > 0] > 0).all()
    visib = res.masks_visib
    for k in range(len(instances)):
        assert visib[k].sum() > 0, f"instance {k} not visible"
        assert not (visib[k] & ~res.masks_full[k]).any(), f"instance {k}: visible pixels outside its full mask"
    # instance 0 is partly under the plate: its full mask is larger than what is visible.
    assert res.masks_full[0].sum() > visib[0].sum()
    assert (visib[2] & res.masks_full[0]).any()


def test_projected_centres_fall_in_their_masks():
    """Off-centre principal point and a tilted camera: catches wrong sensor conventions and wrong id mapping."""
    models, instances, T = _pile()
    K = CameraIntrinsics(fx=60.0, fy=60.0, cx=38.0, cy=20.0, width=W, height=H)
    T_world_camera = sample_T_world_camera(CameraPoseSampling(max_tilt_deg=20.0), np.random.default_rng(3))
    res = render_item(_scene(1), models, instances, T, T_world_camera, K, np.random.default_rng(1))
    T_camera_world = np.linalg.inv(T_world_camera)
    for k in (1, 2):  # the free box and the plate on top: their centres are visible
        top_centre = T[k] @ np.array([0.0, 0.0, models[k].extents_m[2] / 2, 1.0])
        uv = project_points(K.K, (T_camera_world @ top_centre)[None, :3])[0]
        u, v = np.rint(uv).astype(int)
        assert 0 <= u < W and 0 <= v < H
        assert res.ids_visib[v, u] == k + 1, f"instance {k}: pixel ({u}, {v}) has id {res.ids_visib[v, u]}"


def test_same_seed_same_bytes(item):
    models, instances, T, K, res = item
    again = render_item(_scene(), models, instances, T, _top_down(), K, np.random.default_rng(7))
    assert again.rgb.tobytes() == res.rgb.tobytes()
    assert again.depth_m.tobytes() == res.depth_m.tobytes()
    assert again.ids_visib.tobytes() == res.ids_visib.tobytes()
    other = render_item(_scene(), models, instances, T, _top_down(), K, np.random.default_rng(8))
    assert other.rgb.tobytes() != res.rgb.tobytes()


def test_raster_mode_matches_the_path_tracer_geometry(item):
    models, instances, T, K, res = item
    scene = parse_scene({"objects": [{"builtin": "hex_nut"}], "render": {"mode": "raster"}})
    fast = render_item(scene, models, instances, T, _top_down(), K, np.random.default_rng(7))
    assert fast.rgb.shape == (H, W, 3) and fast.rgb.dtype == np.uint8
    top = fast.ids_visib == 1
    assert top.sum() > 5
    np.testing.assert_allclose(fast.depth_m[top], CAM_HEIGHT_M - BOX_HEIGHT_M, atol=2e-3)
    assert (fast.depth_m[fast.ids_visib > 0] > 0).all()
    for k in range(len(instances)):
        assert not (fast.masks_visib[k] & ~fast.masks_full[k]).any()
        # the rasteriser and the ray tracer agree on (almost) every pixel of every mask
        assert (fast.masks_visib[k] != res.masks_visib[k]).mean() < 0.01
    assert fast.masks_full[0].sum() > fast.masks_visib[0].sum()


@pytest.mark.parametrize("mode", ["pathtrace", "raster"])
def test_a_part_behind_the_bin_wall_is_not_fully_visible(mode):
    """A full mask is the part alone (BOP's ``mask``): a box just inside the bin's +x wall, seen over that wall
    from outside the bin, has a visible mask smaller than its full mask in both render modes."""
    scene = parse_scene({"objects": [{"builtin": "hex_nut"}], "render": {"mode": mode, "spp": 1, "max_depth": 4}})
    inner_x = scene.container.inner_size_m[0]
    models = [_box("painted")]
    T = make_T(t=[inner_x / 2 - 0.03, 0.0, BOX_HEIGHT_M / 2])[None]
    T_world_camera = look_at_T_world_camera(np.array([inner_x / 2 + 0.25, 0.0, 0.2]), T[0, :3, 3])
    K = CameraIntrinsics.from_fov(W, H, 30.0)
    res = render_item(scene, models, [Instance(0, 0)], T, T_world_camera, K, np.random.default_rng(1))
    full, visib = res.masks_full[0].sum(), res.masks_visib[0].sum()
    assert full > 20 and visib < 0.8 * full  # the wall hides a part of the box that the full mask keeps


def test_non_square_pixels_project_alike_in_the_rasteriser_and_the_path_tracer():
    """A real camera's K (fx 608.2, fy 631.4) with an off-centre principal point: the centre of each thin plate lands
    on the pixel K projects it to, in both render modes (square pixels would put the outer plates ~1.3 px off)."""
    K = CameraIntrinsics(fx=608.2, fy=631.4, cx=50.3, cy=33.7, width=96, height=72)
    plate = (0.012, 0.012, 0.002)
    models = [_box("painted", size=plate)]
    xy = [(0.0, 0.0), (0.035, 0.015), (-0.035, -0.015), (0.03, -0.018)]
    instances = [Instance(0, k) for k in range(len(xy))]
    T = np.stack([make_T(t=[x, y, plate[2] / 2]) for x, y in xy])
    T_camera_world = np.linalg.inv(_top_down())
    expected = project_points(K.K, (T_camera_world @ T[:, :, 3].T).T[:, :3])
    assert np.abs(expected[:, 0] - K.cx).max() > 30  # far enough off-axis for fx vs fy to move a plate > 1 px
    u, v = np.rint(expected).astype(int).T
    for mode in ("raster", "pathtrace"):
        scene = parse_scene({"objects": [{"builtin": "hex_nut"}], "render": {"mode": mode, "spp": 1, "max_depth": 2}})
        res = render_item(scene, models, instances, T, _top_down(), K, np.random.default_rng(0), full_masks=False)
        assert res.ids_visib[v, u].tolist() == [1, 2, 3, 4], mode  # each centre's pixel shows its plate
        for k in range(len(xy)):
            ys, xs = np.nonzero(res.ids_visib == k + 1)
            assert xs.size > 80, f"{mode}: plate {k} has {xs.size} pixels"
            # a mask's centroid is within half a pixel of the truth (each edge rounds by up to half a pixel)
            np.testing.assert_allclose([xs.mean(), ys.mean()], expected[k], atol=0.5, err_msg=f"{mode}, plate {k}")


def test_camera_pose_sampling_looks_at_bin():
    sampling = CameraPoseSampling(distance_m=(0.5, 0.7), max_tilt_deg=15.0, look_at_jitter_m=0.02)
    rng = np.random.default_rng(0)
    for _ in range(50):
        T = sample_T_world_camera(sampling, rng)
        np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-9)
        assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
        assert 0.5 - 1e-9 <= np.linalg.norm(T[:3, 3] - _ray_floor_hit(T)) <= 0.7 + 1e-9
        assert np.abs(_ray_floor_hit(T)[:2]).max() <= 0.02 + 1e-9
        assert np.degrees(np.arccos(-T[2, 2])) <= 15.0 + 1e-6  # optical axis within the tilt cap


def _ray_floor_hit(T: np.ndarray) -> np.ndarray:
    o, d = T[:3, 3], T[:3, 2]
    return o + d * (-o[2] / d[2])


def test_environment_map_from_file_lights_the_scene(tmp_path):
    """An equirectangular map written here (red sky above the horizon, black below) is the only light: the render
    is red, twice as bright at strength 2, and a missing file names the field and the path."""
    import mitsuba as mi

    choose_variant()
    sky = np.zeros((16, 32, 3), dtype=np.float32)
    sky[:8] = [0.5, 0.02, 0.02]  # the upper half (Mitsuba's envmap: +y up, turned to +z up by the renderer)
    path = tmp_path / "red_sky.exr"
    mi.Bitmap(sky).write(str(path))
    models, instances, T = _pile()
    K = CameraIntrinsics.from_fov(W, H, 45.0)
    means = []
    for strength in (1.0, 2.0):
        scene = parse_scene(
            {"objects": [{"builtin": "hex_nut"}], "render": {"spp": 4, "max_depth": 4},
             "environment": {"map_file": str(path), "strength": strength}}
        )  # fmt: skip
        res = render_item(scene, models, instances, T, _top_down(), K, np.random.default_rng(7), full_masks=False)
        means.append(res.rgb.reshape(-1, 3).mean(axis=0))
    red, green, blue = means[0]
    assert red > 3 * max(green, blue) and red > 20
    assert means[1][0] > 1.15 * red  # sRGB-encoded, so less than twice
    scene = parse_scene({"objects": [{"builtin": "hex_nut"}], "environment": {"map_file": "no/such.exr"}})
    with pytest.raises(FileNotFoundError, match=r"environment.map_file: no such file .*no/such.exr"):
        render_item(scene, models, instances, T, _top_down(), K, np.random.default_rng(7), base_dir=tmp_path)
