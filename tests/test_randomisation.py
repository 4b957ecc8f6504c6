"""The recipe's randomisation: off by default (hashes and items unchanged), each knob seeded and recorded, each knob
changing what it should and only that, distractors that occlude but are never labelled, held-apart families that a
training recipe never draws. Tiny renders (64x48 path-traced at 4 spp, or the rasteriser)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import trimesh

from sygrid.camera import CameraIntrinsics
from sygrid.dataset import generate
from sygrid.dataset_item import item_T_world_camera, make_attempt
from sygrid.errors import ConfigError
from sygrid.objects.model import ObjectModel
from sygrid.physics import Instance
from sygrid.randomise.camera_effects import compress, optics
from sygrid.randomise.clutter import ClutterPiece
from sygrid.randomise.draws import CameraDraw, FinishDraw, draw_item, draw_parts, knob_rng
from sygrid.randomise.families import ALL_FAMILIES, FAMILIES
from sygrid.randomise.skies import sky_map
from sygrid.randomise.spec import APPEARANCE_KNOBS, KNOBS, RandomisationSpec
from sygrid.randomise.textures import SURFACE_TEXTURES, surface_texture, wear_mask
from sygrid.recipe import load_recipe, parse_recipe
from sygrid.render import look_at_T_world_camera, render_item
from sygrid.render.mitsuba_scene import BIN_FLOOR_THICKNESS_M
from sygrid.scene import parse_scene
from sygrid.transforms import invert, make_T
from tests.conftest import TINY_SCENE, tiny_recipe_json

pytestmark = pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")  # pycocotools

ROOT = Path(__file__).resolve().parents[1]
W, H = 64, 48
SEED = 11
#: The families the shipped training recipe holds apart for the held-out test recipe.
HELD_APART = {"cardboard", "rubber_mat", "anisotropic_metal", "window_sky"}


def _scene(width: int = W, height: int = H) -> dict:
    scene = json.loads(json.dumps(TINY_SCENE))
    scene["camera"].update(width_px=width, height_px=height)
    scene["render"] = {"spp": 4, "max_depth": 4}
    return scene


def _recipe(tmp_path: Path, knobs: dict | None = None, raster: bool = False, **overrides: object):
    block = {k: {"enabled": True, **v} for k, v in (knobs or {}).items()}
    data = tiny_recipe_json(scene=_scene(), raster_fraction=1.0 if raster else 0.0, val_fraction=0.0, **overrides)
    if block:
        data["randomisation"] = block
    return parse_recipe(data, "tiny recipe", tmp_path)


def _attempt(recipe):
    item, reason = make_attempt(recipe, SEED, 0, 0)
    assert item is not None, reason
    return item


def _labels(item) -> list:
    return [
        (i.obj_id, i.mask_visib.tobytes(), i.mask_full.tobytes(), i.bbox_visib, i.bbox_obj, i.T_camera_obj.tobytes())
        for i in item.annotation.instances
    ]


def _mean_diff(a: np.ndarray, b: np.ndarray, where: np.ndarray) -> float:
    return float(np.abs(a.astype(float) - b.astype(float))[where].mean()) if where.any() else 0.0


# ---------------------------------------------------------------------------------------------- off by default
def test_off_by_default_keeps_recipes_and_their_hashes(tmp_path):
    assert RandomisationSpec().enabled == ()
    for path in sorted((ROOT / "launch" / "recipes").glob("*.json")):
        data = json.loads(path.read_text())
        recipe = load_recipe(path)
        if "randomisation" not in data:
            assert "randomisation" not in recipe.to_json(), path
    plain = parse_recipe(tiny_recipe_json(), "r.json", tmp_path)
    all_off = parse_recipe(tiny_recipe_json(randomisation={k: {"enabled": False} for k in KNOBS}), "r.json", tmp_path)
    assert plain.sha256() == all_off.sha256()
    on = parse_recipe(tiny_recipe_json(randomisation={"camera": {"enabled": True}}), "r.json", tmp_path)
    assert on.sha256() != plain.sha256() and on.to_json()["randomisation"]["camera"]["enabled"]


def test_bad_blocks_name_the_file_and_field(tmp_path):
    cases = {
        "randomisation.surfaces.roughness: must be [min, max] with min <= max": {"surfaces": {"roughness": [0.5, 0.1]}},
        "randomisation.lighting.lamps[0]: must be an integer, got true": {"lighting": {"lamps": [True, 2]}},
        "randomisation.families: exclude: unknown famil": {"families": {"exclude": ["marble"]}},
        "randomisation.camera.blur: unknown key": {"camera": {"blur": 1.0}},
        "every sky family": {"lighting": {"enabled": True}, "families": {"exclude": list(FAMILIES["sky"])}},
    }
    for message, block in cases.items():
        with pytest.raises(ConfigError, match="r.json: .*" + re.escape(message)):
            parse_recipe(tiny_recipe_json(randomisation=block), "r.json", tmp_path)
    with pytest.raises(ConfigError, match=r"builtin_parts: \['washer'\] are labelled parts of the scene"):
        parse_recipe(tiny_recipe_json(randomisation={"distractors": {"builtin_parts": ["washer"]}}), "r.json", tmp_path)


def test_family_names_are_unique_across_categories():
    assert len(ALL_FAMILIES) == len(set(ALL_FAMILIES))
    assert set(SURFACE_TEXTURES) == set(FAMILIES["surface"])


# ---------------------------------------------------------------------------------------------- seeded draws
def _all_on(**extra: dict) -> RandomisationSpec:
    return RandomisationSpec.model_validate({k: {"enabled": True, **extra.get(k, {})} for k in KNOBS})


def test_same_stream_same_draws_and_each_knob_has_its_own_stream():
    container = parse_scene(TINY_SCENE).container
    spec = _all_on()

    def draws(s: RandomisationSpec, key: list[int]) -> dict:
        stream = np.random.SeedSequence(key)
        d = draw_item(s, stream, container, -BIN_FLOOR_THICKNESS_M)
        d.parts = draw_parts(s, stream, ["steel", "painted", "plastic", "zinc"])
        return d.to_json()

    a, b, c = draws(spec, [1, 2]), draws(spec, [1, 2]), draws(spec, [1, 3])
    assert a == b and a != c and set(a) == set(KNOBS)
    for knob in KNOBS:  # one knob alone draws what it draws among all the others
        alone = RandomisationSpec.model_validate({knob: {"enabled": True}})
        assert draws(alone, [1, 2]) == {knob: a[knob]}
    stream = np.random.SeedSequence(5)
    assert knob_rng(stream, "parts").random() != knob_rng(stream, "camera").random()


def test_textures_skies_and_masks_are_seeded_and_in_range():
    for family in FAMILIES["surface"]:
        tex = surface_texture(family, np.array([0.4, 0.3, 0.2]), 32, seed=3)
        assert tex.shape == (32, 32, 3) and tex.dtype == np.float32 and tex.min() >= 0 and tex.max() <= 1
        assert np.array_equal(tex, surface_texture(family, np.array([0.4, 0.3, 0.2]), 32, seed=3))
        if family != "plain":
            assert not np.array_equal(tex, surface_texture(family, np.array([0.4, 0.3, 0.2]), 32, seed=4))
    for family in FAMILIES["sky"]:
        sky = sky_map(family, 16, seed=1)
        if sky is not None:
            weights = np.cos(np.pi / 2 - (np.arange(16) + 0.5) / 16 * np.pi)[:, None, None]
            assert sky.shape == (16, 32, 3) and sky.min() >= 0
            assert (sky * weights).sum() / (weights.sum() * 32 * 3) == pytest.approx(1.0, rel=1e-4)
    mask = wear_mask(0.3, 64, seed=2)
    assert mask.shape == (64, 64, 1) and 0.2 < float((mask > 0.5).mean()) < 0.4


def test_camera_effects_each_change_the_image_and_not_when_zero():
    rng = np.random.default_rng(0)
    rgb = (rng.random((48, 64, 3)) * 255).astype(np.uint8)
    assert np.abs(optics(rgb, CameraDraw()).astype(int) - rgb).max() <= 1  # nothing drawn: the same image
    assert np.array_equal(compress(rgb, CameraDraw()), rgb)
    for effect in (
        {"exposure_ev": 0.7}, {"white_balance": (1.2, 0.9)}, {"defocus_sigma_px": 1.0},
        {"motion_blur_px": 3.0, "motion_angle_deg": 30.0}, {"vignetting": 0.4},
    ):  # fmt: skip
        assert np.abs(optics(rgb, CameraDraw(**effect)).astype(int) - rgb).mean() > 2, effect
    assert np.abs(compress(rgb, CameraDraw(jpeg_quality=50)).astype(int) - rgb).mean() > 2


# ---------------------------------------------------------------------------------------------- renders
@pytest.fixture(scope="module")
def off_items(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("off")
    return {raster: _attempt(_recipe(tmp, raster=raster)) for raster in (False, True)}


@pytest.mark.parametrize("raster", [False, True], ids=["pathtrace", "raster"])
@pytest.mark.parametrize("knob", APPEARANCE_KNOBS)
def test_appearance_knobs_change_pixels_but_never_labels(tmp_path, off_items, knob, raster):
    off = off_items[raster]
    extra = {"surfaces": {"texture_px": 32}, "lighting": {"sky_px": 16}, "parts": {"mask_px": 32}}.get(knob, {})
    on = _attempt(_recipe(tmp_path, {knob: extra}, raster=raster))
    assert _labels(on) == _labels(off)
    assert np.array_equal(on.depth_m, off.depth_m)
    assert set(on.record["randomisation"]) == {knob}
    parts = np.any([i.mask_visib for i in off.annotation.instances], axis=0)
    background = ~parts
    on_parts, on_background = _mean_diff(on.rgb, off.rgb, parts), _mean_diff(on.rgb, off.rgb, background)
    if knob == "surfaces":  # the floor and bin change; the parts only by the light they bounce
        assert on_background > 5 and on_background > 2 * on_parts
    elif knob == "parts":  # the parts change; the rest only by the light they bounce
        assert on_parts > 5 and on_parts > 3 * on_background
    else:  # lighting and the camera: everywhere
        assert on_parts > 1 and on_background > 1


@pytest.mark.parametrize("mode", ["pathtrace", "raster"])
def test_a_distractor_occludes_a_part_but_is_never_labelled(mode):
    """A box part on the floor and a distractor plate hovering over half of it: the plate hides that half in the
    visible mask and the depth, leaves the part's full mask as it was, and has no id of its own."""
    scene = parse_scene({"objects": [{"builtin": "hex_nut"}], "render": {"spp": 1, "max_depth": 2, "mode": mode}})
    part = ObjectModel(obj_id=1, name="box", mesh=trimesh.creation.box(extents=(0.06, 0.06, 0.02)), material="plastic")
    T_part = make_T(t=[0.0, 0.0, 0.01])[None]
    plate = ObjectModel(obj_id=0, name="plate", mesh=trimesh.creation.box(extents=(0.04, 0.1, 0.004)))
    piece = ClutterPiece(plate, make_T(t=[0.03, 0.0, 0.05]), FinishDraw("plastic", None, 0.3, colour=(0.9, 0.1, 0.1)))
    K = CameraIntrinsics.from_fov(W, H, 45.0)
    T_world_camera = look_at_T_world_camera(np.array([0.0, 0.0, 0.4]), np.zeros(3))

    def render(clutter):
        return render_item(scene, [part], [Instance(0, 0)], T_part, T_world_camera, K, np.random.default_rng(1),
                           clutter=clutter)  # fmt: skip

    clear, hidden = render(()), render([piece])
    assert set(np.unique(hidden.ids_visib)) <= {0, 1}
    assert np.array_equal(hidden.masks_full, clear.masks_full)
    lost = clear.masks_visib[0] & ~hidden.masks_visib[0]
    assert lost.sum() > 0.2 * clear.masks_visib[0].sum() and not np.any(hidden.masks_visib[0] & ~clear.masks_visib[0])
    z_plate = 0.4 - 0.052
    assert np.allclose(hidden.depth_m[lost], z_plate, atol=2e-3)


def test_distractors_are_dropped_and_laid_and_only_parts_are_labelled(tmp_path, off_items):
    knobs = {"distractors": {"in_bin": [2, 2], "around_bin": [2, 2], "builtin_parts": ["hex_bolt"]}}
    item = _attempt(_recipe(tmp_path, knobs, raster=True))
    draws = item.record["randomisation"]["distractors"]
    assert len(draws["in_bin"]) == 2 and len(draws["around_bin"]) <= 2
    assert [i.obj_id for i in item.annotation.instances] == [i.obj_id for i in off_items[True].annotation.instances]
    for inst in item.annotation.instances:
        assert not np.any(inst.mask_visib & ~inst.mask_full)


def test_geometry_moves_the_camera_by_the_bin_pose(tmp_path, off_items):
    knobs = {"geometry": {"bin_offset_m": 0.05, "bin_yaw_deg": 20.0, "camera": {"distance_m": [0.3, 0.3]}}}
    recipe = _recipe(tmp_path, knobs, raster=True)
    item = _attempt(recipe)
    T_world_camera = invert(item.annotation.T_camera_world)
    assert np.allclose(T_world_camera, item_T_world_camera(recipe, SEED, 0))
    off_T = invert(off_items[True].annotation.T_camera_world)
    assert not np.allclose(T_world_camera, off_T)
    g = item.record["randomisation"]["geometry"]
    assert max(abs(v) for v in g["bin_offset_m"]) <= 0.05 and abs(g["bin_yaw_deg"]) <= 20.0
    # The bin moved by J in the room: the camera's distance to the room's look-at point is the knob's 0.3 m.
    c, s = np.cos(np.radians(g["bin_yaw_deg"])), np.sin(np.radians(g["bin_yaw_deg"]))
    J = make_T(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]), [*g["bin_offset_m"], 0.0])
    eye_room = (J @ T_world_camera)[:3, 3]
    assert 0.29 < np.linalg.norm(eye_room) < 0.31 + 0.03  # the look-at jitter is at most 2 cm per axis


def test_same_seed_same_item_and_records_keep_the_draws(tmp_path):
    knobs = {k: {} for k in KNOBS}
    knobs["surfaces"], knobs["lighting"] = {"texture_px": 32}, {"sky_px": 16}
    a, b = (_attempt(_recipe(tmp_path, knobs, raster=True)) for _ in range(2))
    assert np.array_equal(a.rgb, b.rgb) and a.record == b.record and _labels(a) == _labels(b)
    out = tmp_path / "ds"
    generate(_recipe(tmp_path, knobs, raster=True), out, count=2, seed=SEED, progress=False)
    records = json.loads((out / "records" / "000000.json").read_text())
    assert len(records) == 2
    for record in records.values():
        assert set(record["randomisation"]) == set(KNOBS)
        assert len(record["randomisation"]["parts"]) == record["instances"]
    plain = tmp_path / "plain"
    generate(_recipe(tmp_path, raster=True), plain, count=1, seed=SEED, progress=False)
    assert all("randomisation" not in r for r in json.loads((plain / "records" / "000000.json").read_text()).values())


# ---------------------------------------------------------------------------------------------- held apart
def _families_drawn(recipe, items: int) -> set[str]:
    materials = [m for o in recipe.scene.objects for m in [o.material or _builtin_material(o.builtin)] * 2]
    seen: set[str] = set()
    for i in range(items):
        stream = np.random.SeedSequence([SEED, i, 0, 3])
        d = draw_item(recipe.spec.randomisation, stream, recipe.scene.container, -BIN_FLOOR_THICKNESS_M)
        d.parts = draw_parts(recipe.spec.randomisation, stream, materials)
        seen |= d.families_drawn()
    return seen


def _builtin_material(name: str | None) -> str:
    from sygrid.objects.parts import builtin_part

    return builtin_part(name or "").material


@pytest.mark.parametrize("recipe", ["builtin_train_random", "builtin_train_transfer"])
def test_a_held_apart_family_is_never_drawn_in_training_and_is_in_testing(recipe):
    train = load_recipe(ROOT / "launch" / "recipes" / f"{recipe}.json")
    test = load_recipe(ROOT / "launch" / "recipes" / "builtin_test_heldout.json")
    assert set(train.spec.randomisation.families.exclude) == HELD_APART
    train_seen, test_seen = _families_drawn(train, 300), _families_drawn(test, 100)
    assert not train_seen & HELD_APART
    assert test_seen >= HELD_APART
    shared = {"area_light", "point_light", "plastic", "worn_paint"}  # the families both recipes allow
    assert train_seen - shared and not test_seen & (train_seen - shared)


def test_the_transfer_training_recipe_keeps_the_knobs_the_ablation_found_to_pay():
    """``builtin_train_transfer.json`` is the randomised training recipe with the knobs the transfer ablation found to
    cost within the training budget (camera effects, lighting, camera geometry) off: docs/bench/transfer.md."""
    base = load_recipe(ROOT / "launch" / "recipes" / "builtin_train_random.json").to_json()
    chosen = load_recipe(ROOT / "launch" / "recipes" / "builtin_train_transfer.json").to_json()
    off = ("lighting", "camera", "geometry")
    assert [k for k in KNOBS if chosen["randomisation"][k]["enabled"]] == ["surfaces", "parts", "distractors"]
    for data in (base, chosen):
        del data["name"]
        for knob in off:
            del data["randomisation"][knob]
    assert chosen == base


@pytest.mark.parametrize("knob", KNOBS)
def test_an_ablation_recipe_is_the_randomised_training_recipe_with_one_knob_off(knob):
    """The transfer ablation (Makefile ``transfer-ablation``) compares the randomised training recipe with each
    knob switched off in turn: the variants must stay the same recipe in everything else."""
    base = load_recipe(ROOT / "launch" / "recipes" / "builtin_train_random.json").to_json()
    variant = load_recipe(ROOT / "launch" / "recipes" / "ablation" / f"without_{knob}.json").to_json()
    assert base["randomisation"][knob]["enabled"] and not variant["randomisation"][knob]["enabled"]
    assert variant["name"] == f"{base['name']}_without_{knob}"
    for data in (base, variant):
        del data["name"], data["randomisation"][knob]
    assert variant == base
