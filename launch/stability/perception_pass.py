"""One measurement pass of the perception stack over a generated set, per ground-truth instance, and its tally.

A pass (``measure_set``) gives every instance seen at least ``EvalSettings.min_visib_fract`` a row: its part, visible
fraction, nominal size in image pixels (``fx * diameter / z``) and, per method, whether the method got it:

- detection methods (``DETECTION_METHODS``): the model folder's detector at its operating threshold, on the bin's
  box or the whole frame (``perception.detector_eval.run_detector``); found = matched by a detection of its part
  with mask IoU >= ``match_iou`` (``sygrid.detection_breakdown.match_instances``);
- pose strategies with ground-truth masks (``perception.strategy_eval.evaluate_strategies``): success = ADD(-S) <
  0.1 d and accepted by the verification at the manifest's thresholds (refused counts as a failure);
  ``any_correct`` keeps ADD(-S) < 0.1 d before the verification.

Frames may go through a sensor model first (``sensing``: the exact depth sensed again, seeded per image). A pass is
cached as JSON (``cache_path``) under a key of everything it depends on, so axes that bin the same pass (part size,
occlusion) measure it once. ``tally`` counts the rows a point selects, per method, part family and part.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

from launch.stability.sweep import Measurement
from sygrid.bench.common import dataset_digest, folder_digest
from sygrid.fileio import read_json, write_json_atomic

if TYPE_CHECKING:
    from sygrid.sensor import SensorModel

DETECTION_METHODS = {"detector (bin box)": "bin", "detector (whole frame)": "full"}
THIN_M = 0.0022  # a part whose mean wall thickness (2 x volume / surface) is below this is "thin"
MANY_FOLD = 3  # discrete symmetries (besides the identity) from which a part counts as "n-fold symmetric"
FAMILIES = ("thin", "rotational", "n-fold symmetric", "low symmetry")
Row = dict[str, Any]


def part_family(model) -> str:
    """A part's family (``FAMILIES``): "thin" (sheets, washers: mean wall thickness ``2 V / S`` below ``THIN_M``),
    else "rotational" (a continuous symmetry), "n-fold symmetric" (at least ``MANY_FOLD`` discrete symmetries besides
    the identity), "low symmetry"."""
    if 2.0 * model.volume_m3 / float(model.mesh.area) < THIN_M:
        return "thin"
    if model.symmetries_continuous:
        return "rotational"
    return "n-fold symmetric" if len(model.symmetries_discrete) >= MANY_FOLD else "low symmetry"


@dataclass
class PerceptionStack:
    """The model folder's pipeline, loaded once: the detector, the pose network, the strategies' runner and the
    verification threshold; ``strategies`` the pose strategies measured."""

    models_dir: Path
    strategies: tuple[str, ...]
    threads: int = 2

    @cached_property
    def pipeline(self):
        from perception.pipeline import PerceptionPipeline, PipelineOverrides

        return PerceptionPipeline.from_folder(self.models_dir, PipelineOverrides(num_threads=self.threads))

    @cached_property
    def min_confidence(self) -> dict[int, float]:
        """obj_id -> the manifest's verification threshold for that part."""
        from perception.manifest import MANIFEST_NAME, load_manifest

        return load_manifest(self.models_dir).verify.thresholds(self.pipeline.models, self.models_dir / MANIFEST_NAME)

    @cached_property
    def runner(self):
        from perception.manifest import load_manifest
        from perception.pose_strategies import StrategyRunner
        from perception.verify import PoseVerifier

        if self.pipeline.runner is not None:
            return self.pipeline.runner
        return StrategyRunner(verifier=PoseVerifier(load_manifest(self.models_dir).verify.config()))

    @cached_property
    def families(self) -> dict[int, str]:
        return {obj_id: part_family(m) for obj_id, m in self.pipeline.models.items()}

    @property
    def methods(self) -> tuple[str, ...]:
        return (*DETECTION_METHODS, *self.strategies)

    def groups(self, obj_id: int) -> list[str]:
        """The groups an instance of ``obj_id`` counts in: its family and its part."""
        m = self.pipeline.models.get(obj_id)
        return [f"family {self.families.get(obj_id, '?')}", f"part {obj_id} {m.name if m else '?'}"]


def sensing(sensor, seed: int, data_dir: Path, split: str, models: dict) -> Callable:
    """A ``strategy_eval`` sense function: each image's exact depth (``depth_true/``, else ``depth/``) and RGB through
    ``sensor`` (a ``sygrid.sensor.SensorModel``), seeded from ``seed`` and the image's ids, specular metal dropping
    out on the parts of a metal material (as ``perception.evaluation`` senses its frames)."""
    from perception.evaluation import image_metal_mask
    from sygrid.sensor import sensor_rng
    from sygrid.writers import load_bop_true_depth

    root = Path(data_dir) / "bop"

    def sense(ann, rgb, depth):
        if depth is None:
            return rgb, depth
        true = load_bop_true_depth(root, ann, split)
        metals = image_metal_mask(ann, models)
        rng = sensor_rng(seed, ann.scene_id, ann.image_id)
        return sensor.sense(rgb, depth if true is None else true, ann.intrinsics, rng, metal_mask=metals)

    return sense


def cache_path(cache_dir: Path, key: dict[str, Any]) -> Path:
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]
    return Path(cache_dir) / "passes" / f"{digest}.json"


# Bumped when what a pass measures changes (2: the depth tare and the sensor's noise allowance; 3: parts at rest on
# their support; 4: the verification's verdict over pixel footprints), so that cached passes of the old measurement
# are not reused.
PASS_VERSION = 4


def measure_set(
    stack: PerceptionStack,
    data_dir: Path,
    max_images: int | None,
    cache_dir: Path,
    detection: bool = True,
    sensor=None,
    sensor_seed: int = 0,
    progress: bool = False,
) -> list[Row]:
    """The pass's rows (see the module docstring), read from the cache when it was measured before. ``sensor``: a
    ``SensorModel`` the frames go through (None: as stored); ``detection`` False leaves the detectors out."""
    frames = frames_sensor_of(data_dir, sensor)
    key = {"data": str(Path(data_dir).resolve()), "max_images": max_images, "models": str(stack.models_dir.resolve()),
           "models_digest": folder_digest(stack.models_dir), "data_digest": dataset_digest(data_dir),
           "strategies": list(stack.strategies), "detection": detection,
           "sensor": None if sensor is None else repr(sensor), "sensor_seed": sensor_seed,
           "frames_sensor": repr(frames),
           "pipeline": PASS_VERSION, **_tare_key(frames)}  # fmt: skip
    path = cache_path(cache_dir, key)
    if path.is_file():
        return read_json(path, "stability pass")["rows"]
    start = time.perf_counter()
    rows = _measure(stack, Path(data_dir), max_images, detection, sensor, frames, sensor_seed, progress)
    write_json_atomic(path, {"key": key, "seconds": time.perf_counter() - start, "rows": rows}, indent=None)
    return rows


def _tare_key(frames: SensorModel) -> dict:
    """The depth tare's quantisation for frames from ``frames`` where it has one (a stereo sensor's disparity step):
    passes tared before the tare knew it are not reused; exact-depth passes keep their keys."""
    from perception.depth_tare import TareConfig

    quantum = TareConfig().for_sensor(frames).quantum_inv_m
    return {"tare_quantum_inv_m": quantum} if quantum > 0 else {}


def frames_sensor_of(data_dir: Path, sensor: SensorModel | None = None) -> SensorModel:
    """The sensor model the pass's frames went through: ``sensor`` where the pass senses the exact depth itself,
    else the one the dataset was generated with (its ledger's ``recipe.sensor``), so that a set generated through
    the OAK-D model is verified with the OAK-D's noise allowance, not an ideal sensor's."""
    from perception.evaluation import EvalSettings, frames_sensor

    return sensor if sensor is not None else frames_sensor(data_dir, EvalSettings())


def _measure(stack, data_dir, max_images, detection, sensor, frames, sensor_seed, progress) -> list[Row]:
    from perception.detector_eval import run_detector
    from perception.evaluation import EvalSettings, eval_items
    from perception.strategy_eval import evaluate_strategies
    from sygrid.dataset import DatasetBin
    from sygrid.detection_breakdown import match_instances

    settings = EvalSettings(max_images=max_images)
    root, split, items = eval_items(data_dir, settings)
    p = stack.pipeline
    rows: dict[str, Row] = {}
    if detection:
        dataset_bin = DatasetBin(data_dir)
        for name, region in DETECTION_METHODS.items():
            images, detections, _ = run_detector(p.detector, root, split, items, region, dataset_bin, progress)
            for ann, dets in zip(images, detections, strict=True):
                for inst, det in match_instances(ann, dets, settings.min_visib_fract, settings.match_iou):
                    row = rows.setdefault(f"{ann.name}/{inst.inst_id}", _row(ann, inst, p.models))
                    row["found"][name] = det is not None
    sense = None if sensor is None else sensing(sensor, sensor_seed, data_dir, split, p.models)
    # As the pipeline runs on such frames: the verification allows for this sensor's noise, and the depth is tared
    # on the bin's floor.
    p.use_sensor(frames)
    records = evaluate_strategies(stack.runner, p.pose, p.models, data_dir, stack.strategies, settings,
                                  wrong_class=False, sense=sense, progress=progress, tare=p.depth_tare)  # fmt: skip
    for (obj_id, strategy), recs in records.items():
        for r in recs:
            row = rows.setdefault(r.image, {"obj_id": obj_id, "visib": r.visib_fract, "nominal_px": None,
                                            "found": {}, "pose": {}, "any_correct": {}})  # fmt: skip
            row["pose"][strategy] = bool(r.correct and r.confidence >= stack.min_confidence[obj_id])
            row["any_correct"][strategy] = bool(r.correct)
    return [{"instance": k, **v} for k, v in rows.items()]


def _row(ann, inst, models: dict) -> Row:
    model = models.get(inst.obj_id)
    z = float(inst.T_camera_obj[2, 3])
    nominal = ann.intrinsics.fx * model.diameter_m / z if model is not None and z > 0 else None
    return {"obj_id": int(inst.obj_id), "visib": float(inst.visib_fract), "nominal_px": nominal, "found": {},
            "pose": {}, "any_correct": {}}  # fmt: skip


def tally(stack: PerceptionStack, rows: Sequence[Row], select: Callable[[Row], bool] = lambda r: True) -> dict:
    """Per method of ``stack``, a ``Measurement`` of the rows ``select`` keeps: detection methods count ``found``,
    strategies ``pose`` (accepted and correct; ``extra["any_correct"]`` before the verification); groups per part
    family and part. A method the pass did not run is left out."""
    out: dict[str, Measurement] = {}
    kept = [r for r in rows if select(r)]
    for method in stack.methods:
        field_ = "found" if method in DETECTION_METHODS else "pose"
        mine = [r for r in kept if method in r[field_]]
        if not mine and not any(method in r[field_] for r in rows):
            continue
        groups: dict[str, list[int]] = {}
        for r in mine:
            for g in stack.groups(r["obj_id"]):
                kn = groups.setdefault(g, [0, 0])
                kn[0] += int(r[field_][method])
                kn[1] += 1
        extra = {}
        if field_ == "pose":
            extra["any_correct"] = sum(int(r["any_correct"][method]) for r in mine)
        out[method] = Measurement(sum(int(r[field_][method]) for r in mine), len(mine), groups, extra)
    return out
