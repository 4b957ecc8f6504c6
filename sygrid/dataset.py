"""Dataset generation: ``count`` items of a recipe, in BOP / YOLO / COCO, resumable and the same on any executor.

Item ``i`` depends only on ``(seed, i)`` (``sygrid.dataset_item``: its random streams, its redraws and the quality
gate it must pass), so the worker count, the executor and the order items finish in change nothing in the files (and
the COCO ids are stable, see ``sygrid.writers.coco``). Each item is its own drop and one camera view;
``scene_id = i // 1000``, ``image_id = i % 1000``.

Crash safety: workers only compute; the driver writes. Every file is written atomically, an item's files first and
its ledger entry (``DIR/dataset.json``) last, so a run killed at any moment leaves complete items and, at worst, the
files of one unrecorded item, which the next run rewrites byte for byte. A failing item is recorded with its index
and error (an item that fails the quality gate in every attempt too: never as done) and the run goes on; a write
error (disk full) stops the run, naming the item, with everything before it intact. Rerunning the same command
finishes the set; a different recipe or seed for the same folder is refused. A rerun does not trust the ledger
alone: an item recorded as done whose files (images, depth, masks, labels, record; in every format written) are not
all there is logged, with the first missing file, and made again.

Layout under ``DIR``: ``dataset.json`` (recipe, seed, ledger), ``bop/`` (models, ``train_pbr``/``val_pbr`` or
``test``), ``yolo/`` (``data.yaml``, images, labels), ``coco/`` (``annotations/instances_<split>.json``, images),
``records/SSSSSS.json`` (per scene, keyed by image id: each written item's record, ``Item.record``: the attempt
written, the reasons of the attempts redrawn, the drop's stability figures, the visible instance count).
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

from sygrid.annotations import ImageAnnotation
from sygrid.dataset_item import IMAGES_PER_SCENE, Item, item_is_val, item_T_world_camera, make_item
from sygrid.drop import resolve_objects
from sygrid.errors import ConfigError, SygridError
from sygrid.fileio import read_json, remove_stale_temporaries, write_json_atomic
from sygrid.objects.model import ObjectModel
from sygrid.recipe import Recipe, parse_recipe
from sygrid.sensor import sensor_preset
from sygrid.transforms import invert
from sygrid.writers import BopWriter, CocoWriter, YoloWriter
from sygrid.writers.bop import flush_split

log = logging.getLogger(__name__)

LEDGER_NAME = "dataset.json"
LEDGER_FORMAT = "sygrid-dataset/1"
RECORDS_DIR = "records"
# Ledger keys of older versions: the recipe's and the scene's render depth_noise (stereo noise after rendering, now
# the recipe's sensor), the recipe's max_drop_attempts (drops redone on an escape only; now max_redraws).
LEGACY_LEDGER_KEYS = {"recipe": ("depth_noise", "max_drop_attempts"), "render": ("depth_noise",)}


class DatasetError(SygridError, RuntimeError):
    """Generation cannot go on (output folder unusable, disk full)."""


@dataclass
class Summary:
    """A run's outcome; ``redrawn``: item index -> the reasons of its redrawn attempts, for the items written in this
    run that passed the quality gate only after one or more redraws; ``redone``: items recorded as done whose files
    were missing (made again)."""

    out_dir: Path
    written: int
    skipped: int
    failed: dict[int, str]
    seconds: float
    redrawn: dict[int, list[str]] = field(default_factory=dict)
    redone: list[int] = field(default_factory=list)

    @property
    def seconds_per_item(self) -> float:
        return self.seconds / self.written if self.written else float("nan")


def ledger_recipe(out_dir: str | Path) -> tuple[Recipe, int]:
    """The recipe (scene inlined) and seed a generated dataset folder was made with, from its ledger: for its camera
    and scene (the bin, the camera draws), not to regenerate it. The keys of older ledgers that no longer exist
    (``LEGACY_LEDGER_KEYS``, none of which changes the camera draws of an item's first attempt) are left out."""
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
                what = f"({data.get(key)!r}, now {self.header[key]!r})"
                if key == "recipe_sha256" and isinstance(data.get("recipe"), dict):
                    what = f"(fields that differ: {', '.join(_differences(data['recipe'], self.recipe_json))})"
                raise ConfigError(
                    f"{self.path}: this folder was generated with another {key.replace('_sha256', '')} "
                    f"{what}; use a new --out folder to keep both"
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


def _differences(old: dict, new: dict, prefix: str = "") -> list[str]:
    """The keys (``scene.render.spp``) whose values differ between two recipe JSONs, nested dicts followed."""
    out = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += _differences(a, b, f"{prefix}{key}.")
        elif a != b:
            out.append(f"{prefix}{key}" + (" (new)" if key not in old else " (gone)" if key not in new else ""))
    return out or ["none (the recipe's hash function changed)"]


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
    """The recipe's writers under ``DIR``; BOP and COCO writers per split, made when a split first appears; the
    per-item records (``DIR/records/``)."""

    def __init__(self, out_dir: Path, recipe: Recipe, models: list[ObjectModel]) -> None:
        self.out_dir, self.recipe, self.models = out_dir, recipe, models
        self.formats = recipe.spec.formats
        self.yolo = YoloWriter(out_dir / "yolo", models) if "yolo" in self.formats else None
        self.bop: dict[str, BopWriter] = {}
        self.coco: dict[str, CocoWriter] = {}
        self._true_depth = not sensor_preset(recipe.spec.sensor, "recipe sensor").is_ideal
        self._listings: dict[Path, set[str]] = {}  # resume checks: folder -> the names in it
        self._json_keys: dict[Path, set[str]] = {}  # resume checks: scene JSON -> its image keys
        self._instance_counts: dict[tuple[str, int], dict[int, int]] = {}

    def _bop(self, split: str) -> BopWriter:
        if split not in self.bop:
            self.bop[split] = BopWriter(self.out_dir / "bop", self.models, split=split)
        return self.bop[split]

    def _coco(self, split: str) -> CocoWriter:
        if split not in self.coco:
            self.coco[split] = CocoWriter(self.out_dir / "coco", self.models, split=split)
        return self.coco[split]

    def write(self, item: Item) -> None:
        """The item in every format, then its record (the ledger entry, written by the caller, comes last)."""
        ann, rgb, depth = item.annotation, item.rgb, item.depth_m
        if "bop" in self.formats:
            self._bop(self.recipe.bop_split(item.is_val)).write(ann, rgb, depth, depth_true_m=item.depth_true_m)
        label_split = self.recipe.label_split(item.is_val)
        if self.yolo is not None:
            self.yolo.write(ann, rgb, depth, split=label_split)
        if "coco" in self.formats:
            self._coco(label_split).write(ann, rgb, depth)
        path = record_path(self.out_dir, ann.scene_id)
        records = read_json(path, "item records") if path.exists() else {}
        records[str(ann.image_id)] = item.record
        write_json_atomic(path, dict(sorted(records.items(), key=lambda kv: int(kv[0]))), indent=1)

    def missing_file(self, index: int, is_val: bool) -> str | None:
        """The first file of item ``index`` (every format written, and its record) that is not on disk, or None
        when the item is complete. Folder listings and scene JSONs are read once per run."""
        scene_id, image_id = divmod(index, IMAGES_PER_SCENE)
        paths: list[Path] = []
        if "bop" in self.formats:
            writer = self._bop(self.recipe.bop_split(is_val))
            key = (writer.split, scene_id)
            if key not in self._instance_counts:
                self._instance_counts[key] = writer.instance_counts(scene_id)
            n_instances = self._instance_counts[key].get(image_id)
            if n_instances is None:
                return f"{writer.scene_dir(scene_id) / 'scene_gt.json'} (no entry for image {image_id})"
            paths += writer.item_files(scene_id, image_id, n_instances, self._true_depth)
        label_split = self.recipe.label_split(is_val)
        if self.yolo is not None:
            paths += self.yolo.item_files(scene_id, image_id, label_split)
        if "coco" in self.formats:
            paths += self._coco(label_split).item_files(scene_id, image_id)
        for path in paths:
            if path.name not in self._listing(path.parent):
                return str(path)
        records = record_path(self.out_dir, scene_id)
        if records not in self._json_keys:
            self._json_keys[records] = set(read_json(records, "item records")) if records.exists() else set()
        if str(image_id) not in self._json_keys[records]:
            return f"{records} (no record of image {image_id})"
        return None

    def _listing(self, folder: Path) -> set[str]:
        if folder not in self._listings:
            self._listings[folder] = set(os.listdir(folder)) if folder.is_dir() else set()
        return self._listings[folder]

    def finish(self) -> None:
        """Assembles the per-split files (BOP scene JSONs, COCO JSON, YOLO data.yaml) from everything on disk, old
        runs included."""
        if "bop" in self.formats:
            for split_dir in sorted(p for p in (self.out_dir / "bop").glob("*") if p.is_dir() and p.name != "models"):
                flush_split(self.out_dir / "bop", split_dir.name)
        if "coco" in self.formats:
            coco_root = self.out_dir / "coco" / "annotations"
            for split in sorted(p.name.removeprefix("items_") for p in coco_root.glob("items_*")):
                writer = self.coco.get(split) or CocoWriter(self.out_dir / "coco", self.models, split=split)
                writer.finish()
        if self.yolo is not None:
            self.yolo.finish()


def record_path(out_dir: Path, scene_id: int) -> Path:
    """The records file of scene ``scene_id``: image id -> ``Item.record``."""
    return Path(out_dir) / RECORDS_DIR / f"{scene_id:06d}.json"


def load_records(out_dir: str | Path) -> dict[int, dict]:
    """Item index -> record of every item a dataset folder records (empty for folders written before records)."""
    out: dict[int, dict] = {}
    for path in sorted((Path(out_dir) / RECORDS_DIR).glob("*.json")):
        data = read_json(path, "item records")
        if not isinstance(data, dict) or not path.stem.isdigit():
            raise ConfigError(f"{path}: expected a JSON object keyed by image id")
        out.update({int(path.stem) * IMAGES_PER_SCENE + int(k): v for k, v in data.items()})
    return out


# ---------------------------------------------------------------------------------------------------- generate
def generate(
    recipe: Recipe,
    out_dir: str | Path,
    count: int,
    seed: int,
    workers: int = 1,
    executor: str = "local",
    progress: bool = True,
    on_written: Callable[[Item, float], None] | None = None,
) -> Summary:
    """Generates (or completes) items ``0 .. count - 1`` of ``recipe`` under ``out_dir``; see the module doc.
    ``on_written(item, write_s)``, when given, is called after each item is written with the seconds its writing
    took (its making: ``item.timings``), for callers that watch the run's cost per item."""
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
    models = resolve_objects(recipe.scene, recipe.base_dir)
    output = DatasetOutput(out_dir, recipe, models)
    redone = []
    for index in sorted(i for i in ledger.done if i < count):
        missing = output.missing_file(index, item_is_val(recipe, seed, index))
        if missing is not None:
            log.warning("item %d: recorded as done, but %s is missing; making the item again", index, missing)
            redone.append(index)
    ledger.done.difference_update(redone)
    todo = [i for i in range(count) if i not in ledger.done]
    ledger.save()
    t0 = time.perf_counter()
    written, redrawn = 0, {}
    bar = _progress_bar(len(todo), progress)
    try:
        for index, item, error in EXECUTORS[executor](recipe, seed, todo, workers):
            if item is None:
                ledger.failed[index] = str(error)
                log.error("item %d failed: %s", index, error)
            else:
                t_write = time.perf_counter()
                _write_item(output, item, out_dir)
                if on_written is not None:
                    on_written(item, time.perf_counter() - t_write)
                ledger.done.add(index)
                ledger.failed.pop(index, None)
                written += 1
                if item.record.get("redraws"):
                    redrawn[index] = [r["reason"] for r in item.record["redraws"]]
            ledger.save()
            bar.update(1)
            bar.set_postfix(failed=len(ledger.failed), refresh=False)
    finally:
        bar.close()
        output.finish()
    seconds = time.perf_counter() - t0
    return Summary(out_dir, written, count - len(todo), dict(ledger.failed), seconds, redrawn, redone)


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
