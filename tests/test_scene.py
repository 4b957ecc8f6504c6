import json
from pathlib import Path

import pytest

from sygrid.errors import ConfigError
from sygrid.scene import RENDER_PRESETS, CountRange, default_scene, load_scene, parse_scene

NUT = {"builtin": "hex_nut"}


@pytest.mark.parametrize(
    ("scene", "message"),
    [
        ({"objects": [NUT, NUT, {"builtin": "pipe", "count": -1}]}, r"objects\[2\]\.count: must be >= 0, got -1$"),
        ({"objects": [{"builtin": "hex_nut", "colour": "red"}]}, r"objects\[0\]\.colour: unknown key"),
        ({"objects": []}, r"objects: must list at least one part"),
        ({"objects": [{**NUT, "count": {"min": 3, "max": 1}}]}, r"objects\[0\]\.count: max must be >= min"),
        ({"objects": [{**NUT, "count": {"min": 1}}]}, r"objects\[0\]\.count\.max: is required"),
        ({"objects": [{**NUT, "count": 2.5}]}, r"objects\[0\]\.count: must be an integer, got 2\.5"),
        ({"objects": [{"file": "part.ply", "obj_id": 3}]}, r"objects\[0\]: 'unit' is required with 'file'"),
        ({"objects": [{"file": "part.ply", "unit": "cm", "obj_id": 3}]},
         r"objects\[0\]\.unit: must be one of 'mm' or 'm', got \"cm\""),
        ({"objects": [{**NUT, "file": "part.ply"}]}, r"objects\[0\]: give exactly one of 'builtin'"),
        ({"objects": [NUT], "render": {"spp": 0}}, r"render\.spp: must be >= 1, got 0"),
        ({"objects": [NUT], "render": {"preset": "ultra"}}, r"render\.preset: must be one of 'fast' or 'paper'"),
        ({"objects": [NUT], "physics": {"collision_tier": "mesh"}}, r"physics\.collision_tier: must be one of"),
        ({"objects": [NUT], "container": {"inner_size_m": [0.3, 0, 0.1]}},
         r"container\.inner_size_m: every side must be > 0"),
        ({"objects": [NUT], "camera": {"T_world_camera": [1, 0, 0]}},
         r"camera\.T_world_camera: must be a 4x4 transform as 16 numbers"),
        ({"objects": [NUT], "camera": {"fov_y_deg": 45, "intrinsics": {"fx": 1, "fy": 1, "cx": 0, "cy": 0}}},
         r"camera: give 'fov_y_deg' or 'intrinsics', not both"),
        ({"objects": [{"file": "a.ply", "unit": "mm", "obj_id": 7}, {"file": "b.ply", "unit": "mm", "obj_id": 7}]},
         r"obj_id values must be unique, repeated: \[7\]"),
        ({"objects": [NUT], "physics": {"timestep_s": 0.05}}, r"physics\.timestep_s: must be <= 0\.01, got 0\.05"),
        ([], r"\(top level\): must be an object"),
    ],
)  # fmt: skip
def test_bad_scene_names_file_field_and_expectation(scene, message):
    with pytest.raises(ConfigError, match=r"^bad\.json: .*" + message.lstrip("^")):
        parse_scene(scene, "bad.json")


def test_unknown_keys_are_reported_at_every_level():
    with pytest.raises(ConfigError, match=r"physics\.gravity: unknown key"):
        parse_scene({"objects": [NUT], "physics": {"gravity": -9.81}}, "s.json")


def test_presets_fill_unset_fields_and_explicit_values_win():
    paper = parse_scene({"objects": [NUT], "render": {"preset": "paper"}}).render
    assert (paper.spp, paper.max_depth, paper.denoiser) == (5000, 32, "oidn")
    tuned = parse_scene({"objects": [NUT], "render": {"preset": "paper", "spp": 128}}).render
    assert (tuned.spp, tuned.max_depth) == (128, 32)
    fast = default_scene().render
    assert fast.spp == RENDER_PRESETS["fast"]["spp"] and fast.reconstruction_filter == "box"
    cam = default_scene().camera
    assert (cam.width_px, cam.height_px) == (640, 480)


def test_count_forms():
    scene = parse_scene({"objects": [{**NUT, "count": {"min": 1, "max": 4}}, {"builtin": "washer", "count": 0}]})
    assert scene.objects[0].count == CountRange(min=1, max=4)
    assert scene.objects[1].count == 0


def test_load_scene_reports_file_problems(tmp_path):
    with pytest.raises(ConfigError, match=r"missing\.json: cannot read the scene file"):
        load_scene(tmp_path / "missing.json")
    broken = tmp_path / "broken.json"
    broken.write_text('{"objects": [\n  {"builtin": "hex_nut",}\n]}')
    with pytest.raises(ConfigError, match=r"broken\.json: not valid JSON at line 2"):
        load_scene(broken)
    good = tmp_path / "good.json"
    good.write_text(json.dumps({"name": "x", "objects": [NUT]}))
    assert load_scene(good).name == "x"


def test_shipped_scenes_are_valid():
    scene = load_scene(Path(__file__).parents[1] / "launch" / "scenes" / "builtin_bin.json")
    assert len(scene.objects) >= 6


def test_scene_materials_are_the_object_materials():
    from typing import get_args

    from sygrid.objects.cad import MATERIAL_DENSITY_KG_M3
    from sygrid.scene import Material

    assert set(get_args(Material)) == set(MATERIAL_DENSITY_KG_M3)


# ------------------------------------------------------------------------------- numbers, transforms, the view
DOWN = [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0.6, 0, 0, 0, 1]  # 0.6 m above the bin, looking straight down
UP = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0.6, 0, 0, 0, 1]  # the same place, looking up: away from the bin


@pytest.mark.parametrize(
    ("scene", "message"),
    [
        ({"objects": [NUT], "container": {"inner_size_m": [float("nan"), 0.2, 0.1]}},
         r"container\.inner_size_m\[0\]: must be a finite number, got NaN$"),
        ({"objects": [NUT], "camera": {"T_world_camera": [*DOWN[:3], float("inf"), *DOWN[4:]]}},
         r"camera\.T_world_camera\[3\]: must be a finite number, got Infinity$"),
        ({"objects": [NUT], "physics": {"friction": float("nan")}}, r"physics\.friction: must be a finite number"),
        ({"objects": [NUT], "camera": {"intrinsics": {"fx": 600, "fy": 600, "cx": float("nan"), "cy": 240}}},
         r"camera\.intrinsics\.cx: must be a finite number"),
        ({"objects": [{**NUT, "count": True}]}, r"objects\[0\]\.count: must be an integer, got true$"),
        ({"objects": [{**NUT, "count": {"min": 0, "max": True}}]}, r"objects\[0\]\.count\.max: must be an integer"),
        ({"objects": [NUT], "render": {"spp": True}}, r"render\.spp: must be an integer, got true$"),
        ({"objects": [NUT], "container": {"inner_size_m": [True, 0.2, 0.1]}},
         r"container\.inner_size_m\[0\]: must be a number, got true$"),
        ({"objects": [NUT], "camera": {"width_px": False}}, r"camera\.width_px: must be an integer, got false$"),
        ({"objects": [NUT], "environment": {"procedural": 1}}, r"environment\.procedural: must be true or false"),
        ({"objects": [NUT], "camera": {"T_world_camera": [2 * v if i < 11 and i % 4 < 3 else v
                                                          for i, v in enumerate(DOWN)]}},
         r"camera\.T_world_camera: must be a rigid transform .* rotation scales \[2\.0, 2\.0, 2\.0\]"),
        ({"objects": [NUT], "camera": {"T_world_camera": [*DOWN[:12], 0, 0, 0, 2]}},
         r"camera\.T_world_camera: must be a rigid transform .* last row \[0\.0, 0\.0, 0\.0, 2\.0\]"),
        ({"objects": [NUT], "camera": {"T_world_camera": [*DOWN[:5], 1, *DOWN[6:]]}},
         r"camera\.T_world_camera: must be a rigid transform .* det -1"),
        ({"objects": [NUT], "camera": {"T_world_camera": UP}},
         r"camera\.T_world_camera: the camera sees none of the bin"),
        ({"objects": [{"file": "a.ply", "unit": "mm", "obj_id": 3,
                       "symmetries_discrete": [[1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1.5, 0, 0, 0, 0, 1]]}]},
         r"objects\[0\]\.symmetries_discrete: \[0\] must be a rigid transform"),
    ],
)  # fmt: skip
def test_nan_booleans_and_non_rigid_transforms_are_refused_naming_the_field(scene, message):
    with pytest.raises(ConfigError, match=r"^bad\.json: .*" + message):
        parse_scene(scene, "bad.json")


def test_a_fixed_camera_that_sees_the_bin_and_a_real_cameras_k_are_accepted():
    camera = {"T_world_camera": DOWN, "intrinsics": {"fx": 608.2, "fy": 631.4, "cx": 322.1, "cy": 241.7}}
    scene = parse_scene({"objects": [NUT], "camera": camera})
    assert scene.camera.T_world_camera == tuple(float(v) for v in DOWN)
    assert parse_scene({"objects": [{**NUT, "count": 3}], "container": {"inner_size_m": [1, 0.2, 0.1]}})


def test_nan_in_the_bin_size_is_refused_in_python_too():
    """Not only from a file: a ContainerSpec made in code refuses NaN (it used to reach the spawner as an
    OverflowError)."""
    from pydantic import ValidationError

    from sygrid.scene import ContainerSpec

    with pytest.raises(ValidationError, match="finite number"):
        ContainerSpec(inner_size_m=(float("nan"), 0.2, 0.1))
