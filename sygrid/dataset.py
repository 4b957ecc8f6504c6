"""Dataset generation: ``count`` items of a recipe, in BOP / YOLO / COCO, resumable and the same on any executor.

Item ``i`` depends only on ``(seed, i)``: its random streams come from ``SeedSequence([seed, i])``, so the worker
count, the executor and the order items finish in change nothing in the files (and the COCO ids are stable, see
``sygrid.writers.coco``). Each item is its own drop and one camera view; ``scene_id = i // 1000``,
``image_id = i % 1000``.

Crash safety: workers only compute; the driver writes. Every file is written atomically, an item's files first and
its ledger entry (``DIR/dataset.json``) last, so a run killed at any moment leaves complete items and, at worst, the
files of one unrecorded item, which the next run rewrites byte for byte. A failing item is recorded with its index
and error and the run goes on; a write error (disk full) stops the run, naming the item, with everything before it
intact. Rerunning the same command finishes the set; a different recipe or seed for the same folder is refused.

Layout under ``DIR``: ``dataset.json`` (recipe, seed, ledger), ``bop/`` (models, ``train_pbr``/``val_pbr`` or
``test``), ``yolo/`` (``data.yaml``, images, labels), ``coco/`` (``annotations/instances_<split>.json``, images).
"""

from __future__ import annotations

import errno
import logging
import os
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from sygrid.annotations import ImageAnnotation, annotate
from sygrid.drop import drop_scene, resolve_objects
from sygrid.errors import ConfigError, SygridError
from sygrid.fileio import read_json, remove_stale_temporaries, write_json_atomic
from sygrid.objects.model import ObjectModel
from sygrid.recipe import Recipe, parse_recipe
from sygrid.render import intrinsics_from_spec, render_item
from sygrid.render.camera_pose import camera_T_world_camera
from sygrid.scene import METALS, SceneSpec
from sygrid.sensor import metal_mask, sensor_preset
from sygrid.transforms import invert
from sygrid.writers import BopWriter, CocoWriter, YoloWriter

log = logging.getLogger(__name__)

LEDGER_NAME = "dataset.json"
LEDGER_FORMAT = "sygrid-dataset/1"
IMAGES_PER_SCENE = 1000
# Ledger keys of older versions: the recipe's and the scene's render depth_noise (stereo noise after rendering, now
# the recipe's sensor).
LEGACY_LEDGER_KEYS = {"recipe": ("depth_noise",), "render": ("depth_noise",)}


class DatasetError(SygridError, RuntimeError):
    """Generation cannot go on (output folder unusable, disk full)."""


@dataclass
class Item:
    """One generated item, ready to write."""

    index: int
    annotation: ImageAnnotation
    rgb: np.ndarray
    depth_m: np.ndarray  # as the recipe's sensor reports it
    is_val: bool
    mode: str
    timings: dict[str, float] = field(default_factory=dict)
    depth_true_m: np.ndarray | None = None  # the exact depth, when the sensor is not the ideal one


@dataclass
class Summary:
    out_dir: Path
    written: int
    skipped: int
    failed: dict[int, str]
    seconds: float

    @property
    def seconds_per_item(self) -> float:
        return self.seconds / self.written if self.written else float("nan")


# --------------------------------------------------------------------------------------------------- one item
def make_item(recipe: Recipe, seed: int, index: int) -> Item:
    """Drops, renders and annotates item ``index``: a pure function of ``(recipe, seed, index)``."""
    t0 = time.perf_counter()
    drop_ss, render_ss, split_ss = np.random.SeedSequence([seed, index]).spawn(3)
    drop_seeds = np.random.default_rng(drop_ss).integers(0, 2**31 - 1, size=recipe.spec.max_drop_attempts)
    for attempt, drop_seed in enumerate(drop_seeds):
        result = drop_scene(recipe.scene, int(drop_seed), recipe.base_dir)
        if result.report.ok:
            break
        log.info("item %d: drop attempt %d did not come to rest (%s), dropping again", index, attempt, result.report)
    else:
        raise DatasetError(f"item {index}: no stable drop in {len(drop_seeds)} attempts (last: {result.report})")
    t_drop = time.perf_counter() - t0

    rng = np.random.default_rng(render_ss)
    scene, T_world_camera = _draw_view(recipe, rng)
    intrinsics = intrinsics_from_spec(scene.camera)
    rendered = render_item(
        scene,
        result.models,
        result.instances,
        result.T_world_obj,
        T_world_camera,
        intrinsics,
        rng,
        base_dir=recipe.base_dir,
        full_masks=recipe.spec.full_masks,
    )
    sensor = sensor_preset(recipe.spec.sensor, "recipe sensor")
    rgb, depth_m, depth_true_m = rendered.rgb, rendered.depth_m, None
    t_sensor = time.perf_counter()
    if not sensor.is_ideal:
        materials = [result.models[inst.model_index].material for inst in result.instances]
        metals = metal_mask([rendered.ids_visib == k + 1 for k in range(len(materials))], materials, METALS)
        rgb, depth_m = sensor.sense(rendered.rgb, rendered.depth_m, intrinsics, rng, metal_mask=metals)
        depth_true_m = rendered.depth_m
    t_sensor = time.perf_counter() - t_sensor
    T_camera_obj = invert(T_world_camera)[None] @ result.T_world_obj
    obj_ids = [result.models[inst.model_index].obj_id for inst in result.instances]
    masks_full = rendered.masks_full if recipe.spec.full_masks else None
    instances = annotate(rendered.ids_visib, masks_full, T_camera_obj, obj_ids, intrinsics, depth_m)
    annotation = ImageAnnotation(
        image_id=index % IMAGES_PER_SCENE,
        intrinsics=intrinsics,
        instances=tuple(instances),
        scene_id=index // IMAGES_PER_SCENE,
        T_camera_world=invert(T_world_camera),
    )
    is_val = recipe.spec.split == "train" and np.random.default_rng(split_ss).random() < recipe.spec.val_fraction
    timings = {"drop": t_drop, **{f"render_{k}": v for k, v in rendered.timings.items()}, "sensor": t_sensor}
    timings["item"] = time.perf_counter() - t0
    return Item(index, annotation, rgb, depth_m, bool(is_val), scene.render.mode, timings, depth_true_m)


def _draw_view(recipe: Recipe, rng: np.random.Generator) -> tuple[SceneSpec, np.ndarray]:
    """The first draws of an item's render stream: the render mode (the scene with it), then ``T_world_camera``."""
    scene = recipe.scene
    if rng.random() < recipe.spec.raster_fraction:
        scene = scene.model_copy(update={"render": scene.render.model_copy(update={"mode": "raster"})})
    return scene, camera_T_world_camera(scene.camera, rng)


def item_T_world_camera(recipe: Recipe, seed: int, index: int) -> np.ndarray:
    """(4, 4) the camera pose of item ``index`` (world frame = the bin's), drawn again without dropping or rendering:
    the same stream ``make_item`` draws it from."""
    render_ss = np.random.SeedSequence([seed, index]).spawn(3)[1]
    return _draw_view(recipe, np.random.default_rng(render_ss))[1]


def ledger_recipe(out_dir: str | Path) -> tuple[Recipe, int]:
    """The recipe (scene inlined) and seed a generated dataset folder was made with, from its ledger: for its camera
    and scene (the bin, the camera draws), not to regenerate it. The keys of older ledgers that no longer exist
    (``LEGACY_LEDGER_KEYS``, none of which changes the camera draws) are left out."""
    path = Path(out_dir) / LEDGER_NAME
    if not path.is_file():
        raise ConfigError(f"{out_dir}: no {LEDGER_NAME} (not a folder made by 'sygrid generate')")
    data = read_json(path, "dataset ledger")
    if not isinstance(data, dict) or data.get("format") != LEDGER_FORMAT or not isinstance(data.get("recipe"), dict):
        raise ConfigError(f"{path}: not a SyGRID dataset ledger (format {LEDGER_FORMAT!r} with a recipe expected)")
    recipe = {k: v for k, v in data["recipe"].items() if k not in LEGACY_LEDGER_KEYS["recipe"]}
    if isinstance(recipe.get("scene"), dict) and isinstance(recipe["scene"].get("render"), dict):
        render = {k: v for k, v in recipe["scene"]["render"].items() if k not in LEGACY_LEDGER_KEYS["render"]}
        recipe["scene"] = {**recipe["scene"], "render": render}
    return parse_recipe(recipe, f"{path}: recipe", Path(out_dir)), int(data["seed"])


class DatasetBin:
    """Where the bin is in the images of a generated dataset: its inner size (the recipe's container) and, per
    image, ``T_camera_bin`` (the bin frame is the scene's world frame: origin at the inner floor's centre, z up).

    The pose comes from the image's annotation (``ImageAnnotation.T_camera_world``, written since datasets record
    it) or, for an older dataset, from the ledger's recipe and seed (``item_T_world_camera``).
    """

    def __init__(self, out_dir: str | Path) -> None:
        self.out_dir = Path(out_dir)
        self.recipe, self.seed = ledger_recipe(out_dir)
        self.inner_size_m = tuple(float(v) for v in self.recipe.scene.container.inner_size_m)

    def T_camera_bin(self, ann: ImageAnnotation) -> np.ndarray:
        if ann.T_camera_world is not None:
            return np.asarray(ann.T_camera_world, dtype=np.float64)
        index = ann.scene_id * IMAGES_PER_SCENE + ann.image_id
        return invert(item_T_world_camera(self.recipe, self.seed, index))


def _make_item_safely(recipe: Recipe, seed: int, index: int) -> tuple[int, Item | None, str | None]:
    """``make_item`` for executors: an exception comes back as text, so one bad item cannot stop the others."""
    try:
        return index, make_item(recipe, seed, index), None
    except Exception as exc:  # any failure of one item is reported with its index, not raised
        log.debug("item %d failed:\n%s", index, traceback.format_exc())
        return index, None, f"{type(exc).__name__}: {exc}"


# -------------------------------------------------------------------------------------------------- executors
Result = tuple[int, "Item | None", "str | None"]


def run_local(recipe: Recipe, seed: int, indices: list[int], workers: int) -> Iterator[Result]:
    """Items in this process (``workers == 1``) or in a pool of spawned processes, as they finish."""
    if workers == 1:
        for i in indices:
            yield _make_item_safely(recipe, seed, i)
        return
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    # spawn, not fork: the parent may hold OpenGL / LLVM / OpenMP state that a forked child must not inherit.
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(workers, context, initializer=_exit_with_parent, initargs=(os.getpid(),)) as pool:
        yield from _windowed(
            indices,
            2 * workers,
            lambda i: pool.submit(_make_item_safely, recipe, seed, i),
            lambda pending: wait(pending, return_when=FIRST_COMPLETED)[0],
            lambda f: f.result(),
        )


def _exit_with_parent(parent_pid: int) -> None:
    """Pool worker initializer: a driver killed outright (SIGKILL) cannot stop its pool, and a spawned worker would
    wait for work forever; this one exits once it has been orphaned."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="exit-with-parent").start()


def run_ray(recipe: Recipe, seed: int, indices: list[int], workers: int) -> Iterator[Result]:
    """Items as Ray tasks: on the cluster at ``RAY_ADDRESS`` when set, else on a local Ray with ``workers`` CPUs."""
    try:
        import ray
    except ImportError as exc:
        raise ConfigError("--executor ray needs the 'dist' extra: pip install 'sygrid[dist]'") from exc
    started_here = not ray.is_initialized()
    if started_here:
        address = os.environ.get("RAY_ADDRESS")
        kwargs = {"address": address} if address else {"num_cpus": workers, "include_dashboard": False}
        # Workers must render headless like the driver; a cluster's nodes get the same variables.
        ray.init(
            runtime_env={"env_vars": {k: os.environ[k] for k in ("MUJOCO_GL",) if k in os.environ}},
            logging_level=logging.WARNING,
            **kwargs,
        )
    try:
        task = ray.remote(num_cpus=1, max_retries=1)(_make_item_safely)
        recipe_ref = ray.put(recipe)
        yield from _windowed(
            indices,
            2 * workers,
            lambda i: task.remote(recipe_ref, seed, i),
            lambda pending: ray.wait(list(pending), num_returns=1)[0],
            ray.get,
        )
    finally:
        if started_here:
            ray.shutdown()


def _windowed(indices: list[int], window: int, submit: Callable, wait_any: Callable, result: Callable) -> Iterator:
    """Keeps at most ``window`` tasks in flight (bounded memory) and yields results as they complete."""
    todo = iter(indices)
    pending = set()
    for i in todo:
        pending.add(submit(i))
        if len(pending) >= window:
            break
    while pending:
        for done in wait_any(pending):
            pending.discard(done)
            yield result(done)
            nxt = next(todo, None)
            if nxt is not None:
                pending.add(submit(nxt))


EXECUTORS: dict[str, Callable[[Recipe, int, list[int], int], Iterator[Result]]] = {"local": run_local, "ray": run_ray}


# ---------------------------------------------------------------------------------------------- ledger + writers
class Ledger:
    """``DIR/dataset.json``: the recipe and seed a folder belongs to, and which items are complete or failed."""

    def __init__(self, out_dir: Path, recipe: Recipe, seed: int, count: int) -> None:
        self.path = out_dir / LEDGER_NAME
        self.done: set[int] = set()
        self.failed: dict[int, str] = {}
        self.header = {"format": LEDGER_FORMAT, "recipe_sha256": recipe.sha256(), "seed": seed}
        self.recipe_json = recipe.to_json()
        self.count = count
        if self.path.exists():
            self._load()

    def _load(self) -> None:
        data = read_json(self.path, "dataset ledger")
        if not isinstance(data, dict) or data.get("format") != LEDGER_FORMAT:
            raise ConfigError(f"{self.path}: not a SyGRID dataset ledger (format {LEDGER_FORMAT!r} expected)")
        for key in ("recipe_sha256", "seed"):
            if data.get(key) != self.header[key]:
                raise ConfigError(
                    f"{self.path}: this folder was generated with another {key.replace('_sha256', '')} "
                    f"({data.get(key)!r}, now {self.header[key]!r}); use a new --out folder to keep both"
                )
        self.done = {i for a, b in data.get("done", []) for i in range(a, b + 1)}
        self.count = max(self.count, int(data.get("count", 0)))

    def save(self) -> None:
        data = {
            **self.header,
            "count": self.count,
            "done": _ranges(sorted(self.done)),
            "failed": {str(i): msg for i, msg in sorted(self.failed.items())},
            "recipe": self.recipe_json,
        }
        write_json_atomic(self.path, data, indent=1)


def _ranges(sorted_ints: Iterable[int]) -> list[list[int]]:
    """[0, 1, 2, 5, 6] -> [[0, 2], [5, 6]]: a ledger of a million items stays small."""
    out: list[list[int]] = []
    for i in sorted_ints:
        if out and out[-1][1] == i - 1:
            out[-1][1] = i
        else:
            out.append([i, i])
    return out


class DatasetOutput:
    """The recipe's writers under ``DIR``; BOP and COCO writers per split, made when a split first appears."""

    def __init__(self, out_dir: Path, recipe: Recipe, models: list[ObjectModel]) -> None:
        self.out_dir, self.recipe, self.models = out_dir, recipe, models
        self.formats = recipe.spec.formats
        self.yolo = YoloWriter(out_dir / "yolo", models) if "yolo" in self.formats else None
        self.bop: dict[str, BopWriter] = {}
        self.coco: dict[str, CocoWriter] = {}

    def write(self, item: Item) -> None:
        ann, rgb, depth = item.annotation, item.rgb, item.depth_m
        if "bop" in self.formats:
            split = self.recipe.bop_split(item.is_val)
            if split not in self.bop:
                self.bop[split] = BopWriter(self.out_dir / "bop", self.models, split=split)
            self.bop[split].write(ann, rgb, depth, depth_true_m=item.depth_true_m)
        label_split = self.recipe.label_split(item.is_val)
        if self.yolo is not None:
            self.yolo.write(ann, rgb, depth, split=label_split)
        if "coco" in self.formats:
            if label_split not in self.coco:
                self.coco[label_split] = CocoWriter(self.out_dir / "coco", self.models, split=label_split)
            self.coco[label_split].write(ann, rgb, depth)

    def finish(self) -> None:
        """Assembles the per-split files (COCO JSON, YOLO data.yaml) from everything on disk, old runs included."""
        if "coco" in self.formats:
            coco_root = self.out_dir / "coco" / "annotations"
            for split in sorted(p.name.removeprefix("items_") for p in coco_root.glob("items_*")):
                writer = self.coco.get(split) or CocoWriter(self.out_dir / "coco", self.models, split=split)
                writer.finish()
        if self.yolo is not None:
            self.yolo.finish()


# ---------------------------------------------------------------------------------------------------- generate
def generate(
    recipe: Recipe,
    out_dir: str | Path,
    count: int,
    seed: int,
    workers: int = 1,
    executor: str = "local",
    progress: bool = True,
) -> Summary:
    """Generates (or completes) items ``0 .. count - 1`` of ``recipe`` under ``out_dir``; see the module doc."""
    if count < 1:
        raise ConfigError(f"count: expected >= 1, got {count}")
    if workers < 1:
        raise ConfigError(f"workers: expected >= 1, got {workers}")
    if executor not in EXECUTORS:
        raise ConfigError(f"executor: expected one of {sorted(EXECUTORS)}, got {executor!r}")
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"{out_dir}: exists and is not a folder")
    ledger = Ledger(out_dir, recipe, seed, count)
    if out_dir.is_dir():  # a killed run can leave a half-written file's temporary behind; the item is redone
        for path in remove_stale_temporaries(out_dir):
            log.info("removed %s, left by an interrupted run", path)
    todo = [i for i in range(count) if i not in ledger.done]
    models = resolve_objects(recipe.scene, recipe.base_dir)
    output = DatasetOutput(out_dir, recipe, models)
    ledger.save()
    t0 = time.perf_counter()
    written = 0
    bar = _progress_bar(len(todo), progress)
    try:
        for index, item, error in EXECUTORS[executor](recipe, seed, todo, workers):
            if item is None:
                ledger.failed[index] = str(error)
                log.error("item %d failed: %s", index, error)
            else:
                _write_item(output, item, out_dir)
                ledger.done.add(index)
                ledger.failed.pop(index, None)
                written += 1
            ledger.save()
            bar.update(1)
            bar.set_postfix(failed=len(ledger.failed), refresh=False)
    finally:
        bar.close()
        output.finish()
    return Summary(out_dir, written, count - len(todo), dict(ledger.failed), time.perf_counter() - t0)


def _write_item(output: DatasetOutput, item: Item, out_dir: Path) -> None:
    try:
        output.write(item)
    except OSError as exc:
        cause = "disk full" if exc.errno == errno.ENOSPC else f"cannot write ({exc})"
        raise DatasetError(
            f"item {item.index}: {cause} under {out_dir}; the items before it are complete, "
            "rerun the same command to resume"
        ) from exc


def _progress_bar(total: int, enabled: bool) -> tqdm:
    return tqdm(total=total, unit="item", disable=not enabled, dynamic_ncols=True, smoothing=0.1)
