"""One dataset item: the drop, the view, the render, the annotations, and the quality gate that decides whether the
item may be written.

Item ``i`` is a pure function of ``(recipe, seed, i)``. Attempt ``a`` of it draws from ``SeedSequence([seed, i])``
for ``a == 0`` and from ``SeedSequence([seed, i, a])`` for ``a > 0``, four streams each: the drop's seed; the render
mode, the camera pose and every render draw; (unused after attempt 0); the recipe's randomisation (one child stream
per knob, ``sygrid.randomise.draws``). A redraw is therefore a new drop, a new view and a new render, the same on
every run, executor and worker count. The split (train / val) comes from attempt 0's third stream whichever attempt
is written, so a redraw never moves an item between splits. With every randomisation knob off nothing is drawn
from the fourth stream, and the items are the ones the generator made before the randomisation existed.

The quality gate, cheapest check first (a bad view or a bad drop costs no render):

1. the camera pose is finite;
2. the drop is within its stability bounds (``StabilityReport.within_bounds``: every pose finite, every part in the
   bin, settled within the scene's ``physics.max_time_s``, penetration at rest at most ``physics.max_penetration_m``);
3. every annotated pose is finite and at least ``recipe.min_visible_instances`` instances have a visible pixel.

An attempt that fails is logged with the item index and its reason and drawn again, at most ``recipe.max_redraws``
times; then ``GateError`` names every attempt's reason, and the generator records the item as failed.

``Item.record`` is what the dataset keeps of each written item (``DIR/records/``, ``sygrid.dataset``): the attempt
written, the reason of each attempt before it, the drop's seed and stability figures (``RECORD_STABILITY_KEYS``: not
the wall time, which differs from run to run), how many instances are visible and, when any randomisation knob is
on, the draws of the enabled knobs (``randomisation``: ``ItemDraws.to_json``).

Randomisation in an attempt: ``geometry`` moves the camera (before the drop), ``distractors`` are dropped with the
parts (only the parts are annotated; the pieces hide them in the visible masks and depth), ``parts`` gives each
part instance a finish, ``surfaces`` and ``lighting`` go to the renderer, and ``camera`` applies its optics to the
rendered RGB before the recipe's sensor and its JPEG compression after it.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from sygrid.annotations import ImageAnnotation, annotate
from sygrid.drop import drop_scene
from sygrid.errors import SygridError
from sygrid.randomise.camera_effects import compress, optics
from sygrid.randomise.clutter import bin_clutter, placed_clutter
from sygrid.randomise.draws import GeometryDraw, draw_geometry, draw_item, draw_parts, knob_rng
from sygrid.recipe import Recipe
from sygrid.render import render_item
from sygrid.render.camera_pose import camera_T_world_camera
from sygrid.render.mitsuba_scene import BIN_FLOOR_THICKNESS_M
from sygrid.scene import METALS, SceneSpec, intrinsics_from_spec
from sygrid.sensor import metal_mask, sensor_preset
from sygrid.transforms import invert

log = logging.getLogger(__name__)

IMAGES_PER_SCENE = 1000
#: The drop's stability figures an item's record keeps (``StabilityReport.to_json`` keys; ``sim_time_s`` is the
#: settle time when ``settled``).
RECORD_STABILITY_KEYS = (
    "settled", "sim_time_s", "max_time_s", "max_penetration_m", "penetration_bound_m", "max_linear_speed_m_s",
)  # fmt: skip


class GateError(SygridError, RuntimeError):
    """No attempt of an item passed the quality gate; the message names the item and each attempt's reason."""


@dataclass
class Item:
    """One generated item, ready to write; ``record``: see the module doc."""

    index: int
    annotation: ImageAnnotation
    rgb: np.ndarray
    depth_m: np.ndarray  # as the recipe's sensor reports it
    is_val: bool
    mode: str
    timings: dict[str, float] = field(default_factory=dict)
    depth_true_m: np.ndarray | None = None  # the exact depth, when the sensor is not the ideal one
    record: dict = field(default_factory=dict)


def make_item(recipe: Recipe, seed: int, index: int) -> Item:
    """Item ``index`` of ``recipe``: the first attempt that passes the quality gate. Raises ``GateError`` when
    none of the ``1 + recipe.spec.max_redraws`` attempts does."""
    t0 = time.perf_counter()
    redraws: list[dict] = []
    for attempt in range(recipe.spec.max_redraws + 1):
        item, reason = make_attempt(recipe, seed, index, attempt)
        if item is not None:
            item.record["redraws"] = redraws
            item.timings["item"] = time.perf_counter() - t0
            return item
        log.info("item %d: attempt %d failed the quality gate (%s); drawing the item again", index, attempt, reason)
        redraws.append({"attempt": attempt, "reason": reason})
    reasons = "; ".join(f"attempt {r['attempt']}: {r['reason']}" for r in redraws)
    raise GateError(f"item {index}: none of {len(redraws)} attempts passed the quality gate ({reasons})")


def make_attempt(recipe: Recipe, seed: int, index: int, attempt: int) -> tuple[Item | None, str]:
    """Attempt ``attempt`` of item ``index``: ``(item, "")`` when it passes the quality gate, else ``(None, the
    reason)``. A pure function of ``(recipe, seed, index, attempt)``."""
    t0 = time.perf_counter()
    drop_ss, render_ss, _, random_ss = _attempt_streams(seed, index, attempt)
    rng = np.random.default_rng(render_ss)
    randomisation = recipe.spec.randomisation
    has_map = recipe.scene.environment.map_file is not None
    draws = draw_item(randomisation, random_ss, recipe.scene.container, -BIN_FLOOR_THICKNESS_M, has_map)
    scene, T_world_camera = _draw_view(recipe, rng, draws.geometry)
    if not np.all(np.isfinite(T_world_camera)):
        return None, "the camera pose is not finite"
    drop_seed = int(np.random.default_rng(drop_ss).integers(0, 2**31 - 1))
    dropped_clutter = bin_clutter(draws.distractors)
    result = drop_scene(recipe.scene, drop_seed, recipe.base_dir, dropped_clutter)
    if not result.report.within_bounds:
        return None, "; ".join(result.report.failures)
    t_drop = time.perf_counter() - t0
    n_parts = len(result.instances) - len(dropped_clutter)  # the parts come first, the dropped pieces after
    instances, T_world_obj = result.instances[:n_parts], result.T_world_obj[:n_parts]
    clutter = placed_clutter(draws.distractors, result.T_world_obj[n_parts:])
    materials = [result.models[inst.model_index].material for inst in instances]
    draws.parts = draw_parts(randomisation, random_ss, materials)

    intrinsics = intrinsics_from_spec(scene.camera)
    rendered = render_item(
        scene,
        result.models,
        instances,
        T_world_obj,
        T_world_camera,
        intrinsics,
        rng,
        base_dir=recipe.base_dir,
        full_masks=recipe.spec.full_masks,
        draws=draws,
        clutter=clutter,
    )
    sensor = sensor_preset(recipe.spec.sensor, "recipe sensor")
    rgb, depth_m, depth_true_m = rendered.rgb, rendered.depth_m, None
    t_sensor = time.perf_counter()
    if draws.camera is not None:
        rgb = optics(rgb, draws.camera)
    if not sensor.is_ideal:
        if draws.parts is not None:  # a finish, not the scene's material, says what is bare metal
            materials = ["steel" if finish.is_metal else "plastic" for finish in draws.parts]
        metals = metal_mask([rendered.ids_visib == k + 1 for k in range(len(materials))], materials, METALS)
        rgb, depth_m = sensor.sense(rgb, rendered.depth_m, intrinsics, rng, metal_mask=metals)
        depth_true_m = rendered.depth_m
    if draws.camera is not None:
        rgb = compress(rgb, draws.camera)
    t_sensor = time.perf_counter() - t_sensor
    T_camera_obj = invert(T_world_camera)[None] @ T_world_obj
    if not np.all(np.isfinite(T_camera_obj)):
        return None, "an instance's pose in the camera frame is not finite"
    obj_ids = [result.models[inst.model_index].obj_id for inst in instances]
    masks_full = rendered.masks_full if recipe.spec.full_masks else None
    instances = annotate(rendered.ids_visib, masks_full, T_camera_obj, obj_ids, intrinsics, depth_m)
    visible = sum(1 for inst in instances if inst.px_count_visib > 0)
    if visible < recipe.spec.min_visible_instances:
        return None, (
            f"{visible} of {len(instances)} instances visible, fewer than min_visible_instances "
            f"{recipe.spec.min_visible_instances}"
        )
    annotation = ImageAnnotation(
        image_id=index % IMAGES_PER_SCENE,
        intrinsics=intrinsics,
        instances=tuple(instances),
        scene_id=index // IMAGES_PER_SCENE,
        T_camera_world=invert(T_world_camera),
    )
    report = result.report.to_json()
    record = {
        "index": index,
        "attempt": attempt,
        "drop_seed": drop_seed,
        "mode": scene.render.mode,
        "instances": len(instances),
        "visible_instances": visible,
        "stability": {k: report[k] for k in RECORD_STABILITY_KEYS},
    }
    if randomisation.enabled:
        record["randomisation"] = draws.to_json()
    timings = {"drop": t_drop, **{f"render_{k}": v for k, v in rendered.timings.items()}, "sensor": t_sensor}
    timings["item"] = time.perf_counter() - t0
    is_val = item_is_val(recipe, seed, index)
    return Item(index, annotation, rgb, depth_m, is_val, scene.render.mode, timings, depth_true_m, record), ""


def item_is_val(recipe: Recipe, seed: int, index: int) -> bool:
    """Whether item ``index`` goes to the validation split (training recipes only), whichever attempt is written."""
    split_ss = _attempt_streams(seed, index, 0)[2]
    return recipe.spec.split == "train" and bool(np.random.default_rng(split_ss).random() < recipe.spec.val_fraction)


def item_T_world_camera(recipe: Recipe, seed: int, index: int, attempt: int = 0) -> np.ndarray:
    """(4, 4) the camera pose of attempt ``attempt`` of item ``index`` (world frame = the bin's), drawn again without
    dropping or rendering: the same stream ``make_attempt`` draws it from."""
    _, render_ss, _, random_ss = _attempt_streams(seed, index, attempt)
    knob = recipe.spec.randomisation.geometry
    geometry = draw_geometry(knob, knob_rng(random_ss, "geometry")) if knob.enabled else None
    return _draw_view(recipe, np.random.default_rng(render_ss), geometry)[1]


def _attempt_streams(seed: int, index: int, attempt: int) -> list[np.random.SeedSequence]:
    """The four seed streams of an attempt (see the module doc)."""
    key = [seed, index] if attempt == 0 else [seed, index, attempt]
    return np.random.SeedSequence(key).spawn(4)


def _draw_view(
    recipe: Recipe, rng: np.random.Generator, geometry: GeometryDraw | None = None
) -> tuple[SceneSpec, np.ndarray]:
    """The first draws of an attempt's render stream: the render mode (the scene with it), then ``T_world_camera``
    (from the geometry knob's pose sampling when it gives one, then moved by the inverse of the bin's drawn pose in
    the room)."""
    scene = recipe.scene
    if rng.random() < recipe.spec.raster_fraction:
        scene = scene.model_copy(update={"render": scene.render.model_copy(update={"mode": "raster"})})
    camera = scene.camera
    sampling = recipe.spec.randomisation.geometry.camera
    if geometry is not None and sampling is not None:
        camera = camera.model_copy(update={"pose_sampling": sampling})
    T_world_camera = camera_T_world_camera(camera, rng)
    if geometry is not None:
        T_world_camera = invert(geometry.T_room_bin()) @ T_world_camera
    return scene, T_world_camera
