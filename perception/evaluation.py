"""Evaluation of the perception pipeline on a generated BOP split: detection mAP and pose accuracy per part.

Every ground-truth instance seen at least ``min_visib_fract`` is matched to an estimated pose of the same part by
the BOP toolkit's rule (``match_poses``: estimates by decreasing score, each to the instance it localises best
within the ADD(-S) tolerance, whatever its detection mask); unmatched instances count as misses (ADD(-S)
failures). Detection mAP goes through pycocotools
(``sygrid.metrics.detection_metrics``) with less-visible instances ignored rather than required.

Sensing: each image's RGB and exact depth (``depth_true/`` when the dataset was generated through a sensor, else
``depth/``) go through ``EvalSettings.sensor`` (a ``sygrid.sensor`` preset), seeded from ``sensor_seed`` and the
image's ids, before the pipeline sees them; "ideal" keeps the stored frame. The sensed depth's AbsRel, delta1 and
fill rate against the exact depth are reported per image and overall. The pipeline's verification allows the depth
noise of the sensor the frames went through (``frames_sensor``: ``EvalSettings.sensor``, else the dataset's own).

As a cell knows its bin from calibration, the pipeline is given each image's bin floor (``bin_floor_camera``: the
plane and the bin's inner corners, from the dataset's ``DatasetBin``), for the depth tare on the floor
(``perception.depth_tare``) and the floor's pixels left out of the fit; the tare's offsets are reported, and the
depth metrics again after the tare.

A dataset without depth (photos converted by ``sygrid convert``) is evaluated for detection only, and a dataset
whose parts the models do not know, by obj_id and name, is refused up front (``check_model_classes``), naming both
lists.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from perception.camera import Frame
from perception.depth_tare import Tare, apply_tare
from perception.detector import YoloSegDetector
from perception.detector_eval import bin_region_camera, detector_report, run_detector
from perception.pipeline import PerceptionPipeline, region_of_interest
from perception.results import ObjectPose
from sygrid.annotations import ImageAnnotation, InstanceAnnotation
from sygrid.dataset import LEDGER_NAME, DatasetBin
from sygrid.detection_breakdown import match_instances
from sygrid.errors import ConfigError
from sygrid.fileio import read_json
from sygrid.metrics import (
    PoseErrors,
    depth_metrics,
    detection_metrics,
    mean_depth_metrics,
    pose_errors,
    pose_metrics_table,
)
from sygrid.objects.model import ObjectModel
from sygrid.scene import METALS
from sygrid.sensor import IDEAL, SensorModel, metal_mask, sensor_preset, sensor_rng
from sygrid.train.detector.data import parse_data_yaml
from sygrid.writers import load_bop_item, load_bop_true_depth

NO_DEPTH = "the dataset has no depth maps: detection metrics only, no pose estimation"


@dataclass(frozen=True)
class EvalSettings:
    split: str | None = None  # None: "test" if present, else "val_pbr"
    max_images: int | None = None
    min_visib_fract: float = 0.1
    match_iou: float = 0.5
    sensor: str = "ideal"  # a sygrid.sensor preset the frames go through
    sensor_seed: int = 0
    region: str = "full"  # where the detector looks: "full" frame or the "bin"'s box (perception.detector_eval)
    floor: bool = True  # the pipeline gets each image's bin floor (bin_floor_camera) where the dataset has a ledger
    rescue: bool = False  # every frame also asks PerceptionPipeline.rescue for the parts the detections missed


def bop_items(root: Path, split: str) -> list[tuple[int, int]]:
    """(scene_id, image_id) of every image of a BOP split, in order."""
    split_dir = root / split
    if not split_dir.is_dir():
        raise ConfigError(f"{root}: no split folder {split!r} (have {sorted(p.name for p in root.iterdir())})")
    items = []
    for scene_dir in sorted(p for p in split_dir.iterdir() if p.is_dir()):
        gt_path = scene_dir / "scene_gt.json"
        if gt_path.is_file():
            items += [(int(scene_dir.name), int(k)) for k in sorted(json.loads(gt_path.read_text()), key=int)]
    return items


def default_split(root: Path) -> str:
    """``test``, else ``val_pbr``, else ``train_pbr``, else the BOP root's only split folder (a converted set's)."""
    for split in ("test", "val_pbr", "train_pbr"):
        if (root / split).is_dir():
            return split
    have = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name != "models")
    if len(have) == 1:
        return have[0]
    raise ConfigError(f"{root}: no test, val_pbr or train_pbr split folder; splits here: {have}; choose with --split")


def eval_items(data_dir: str | Path, settings: EvalSettings) -> tuple[Path, str, list[tuple[int, int]]]:
    """The BOP root, split and (scene_id, image_id) items of a generated dataset that an evaluation runs on."""
    root = Path(data_dir) / "bop"
    if not root.is_dir():
        raise ConfigError(f"{data_dir}: not a generated dataset (no bop/ folder)")
    split = settings.split or default_split(root)
    return root, split, bop_items(root, split)[: settings.max_images]


def dataset_sensor(data_dir: str | Path) -> str:
    """The sensor model a generated dataset's RGB and depth went through (its ledger's recipe): "ideal" for a
    ledger from before sensor models, "unknown" for a folder without a ledger."""
    path = Path(data_dir) / LEDGER_NAME
    if not path.is_file():
        return "unknown"
    ledger = read_json(path, "dataset ledger")
    recipe = ledger.get("recipe") if isinstance(ledger, dict) else None
    return str(recipe.get("sensor", "ideal")) if isinstance(recipe, dict) else "unknown"


def frames_sensor(data_dir: str | Path, settings: EvalSettings) -> SensorModel:
    """The sensor model the frames an evaluation feeds the pipeline went through: ``settings.sensor`` where it is
    not "ideal" (it senses the exact depth again), else the dataset's own (``dataset_sensor``; ideal if unknown)."""
    if settings.sensor != "ideal":
        return sensor_preset(settings.sensor, "EvalSettings.sensor")
    name = dataset_sensor(data_dir)
    return IDEAL if name == "unknown" else sensor_preset(name, f"{Path(data_dir) / LEDGER_NAME}: recipe.sensor")


def floor_bin(data_dir: str | Path, settings: EvalSettings) -> DatasetBin | None:
    """The dataset's bin when ``settings.floor`` is on and the dataset has a ledger (a converted set has none)."""
    return DatasetBin(data_dir) if settings.floor and (Path(data_dir) / LEDGER_NAME).is_file() else None


def bin_floor_camera(dataset_bin: DatasetBin, ann: ImageAnnotation) -> tuple[np.ndarray, np.ndarray]:
    """``(plane, bounds)`` of the bin's inner floor in ``ann``'s camera frame: the plane ``(a, b, c, d)`` (a point p
    lies ``(a, b, c) . p + d`` above it; the bin frame's z = 0, z up) and the bin's (8, 3) inner corners, which
    bound where the floor is seen (``perception.depth_tare``)."""
    T = dataset_bin.T_camera_bin(ann)
    normal = T[:3, 2] / np.linalg.norm(T[:3, 2])
    return np.append(normal, -normal @ T[:3, 3]), bin_region_camera(dataset_bin, ann)


@dataclass(frozen=True)
class _RankedByPose:
    """A pose seen by the matching rule as a detection ranked by the pose's score (``sygrid.metrics.DetectionLike``)."""

    pose: ObjectPose

    obj_id = property(lambda self: self.pose.obj_id)
    score = property(lambda self: self.pose.score)
    bbox_xyxy = property(lambda self: self.pose.detection.bbox_xyxy)
    mask = property(lambda self: self.pose.detection.mask)


def match_poses(
    ann: ImageAnnotation, poses: list[ObjectPose], models: dict[int, ObjectModel], min_visib: float, min_iou: float
) -> list[tuple[InstanceAnnotation, ObjectPose | None, PoseErrors]]:
    """Per evaluated GT instance (seen at least ``min_visib``, in ``ann``'s order): (instance, its estimate or None,
    the errors), by the BOP toolkit's rule for pose recall: the estimates by decreasing score, each matched to the
    not yet matched instance of its part that it localises best, if within the ADD(-S) tolerance
    (``ADD_THRESHOLD_FRACTION`` x diameter), whatever its detection mask (a right pose from a mask that caught one
    leg of a bracket is a right pose). An instance no estimate localises is given the estimate left whose detection
    mask overlaps its visible mask most (the detection metrics' rule, IoU >= ``min_iou``): a miss, with that
    estimate's error in the error medians."""
    instances = [i for i in ann.instances if i.visib_fract >= min_visib]
    matched: dict[int, tuple[int, PoseErrors]] = {}  # instance index -> (pose index, errors)
    for k in sorted(range(len(poses)), key=lambda k: -poses[k].score):
        pose, best = poses[k], None
        for j, inst in enumerate(instances):
            if inst.obj_id != pose.obj_id or j in matched or pose.obj_id not in models:
                continue
            e = _errors(pose, inst.T_camera_obj, models[pose.obj_id])
            if e.correct() and (best is None or e.add_m < best[1].add_m):
                best = (j, e)
        if best is not None:
            matched[best[0]] = (k, best[1])
    used = {k for k, _ in matched.values()}
    rest = [j for j in range(len(instances)) if j not in matched]
    by_mask = match_instances(
        replace(ann, instances=tuple(instances[j] for j in rest)),
        [_RankedByPose(p) for k, p in enumerate(poses) if k not in used], min_visib, min_iou,
    )  # fmt: skip
    fallback = {j: ranked.pose if ranked is not None else None for j, (_, ranked) in zip(rest, by_mask, strict=True)}
    out = []
    for j, inst in enumerate(instances):
        if j in matched:
            k, e = matched[j]
            out.append((inst, poses[k], e))
        else:
            pose = fallback[j]
            out.append((inst, pose, _errors(pose, inst.T_camera_obj, models[inst.obj_id])))
    return out


def evaluate(
    pipeline: PerceptionPipeline,
    data_dir: str | Path,
    settings: EvalSettings | None = None,
    progress: bool = True,
) -> dict:
    """Runs ``pipeline`` on the split's images; returns detection metrics, the pose table and median timings.

    A dataset without depth maps (its first image has none; a converted set of photos) gets the detector alone:
    detection metrics, ``"pose": None`` and the reason in ``"pose_skipped"``.

    Raises:
        ConfigError: no images, the models lack some of the dataset's parts (``check_model_classes``), an image
            without depth in a dataset with depth, or a simulated sensor on a dataset without depth.
    """
    s = settings or EvalSettings()
    sensor = sensor_preset(s.sensor, "EvalSettings.sensor")
    root, split, items = eval_items(data_dir, s)
    if not items:
        raise ConfigError(f"{root / split}: no images")
    names = {obj_id: m.name for obj_id, m in pipeline.models.items()}
    check_model_classes(data_dir, names, split)
    pipeline.use_sensor(frames_sensor(data_dir, s))
    images, detections, records, timings, depth_rows, sensor_ms = [], [], [], [], [], []
    verdicts, per_object, rescued, rescue_ms = [], [], [], []
    with_depth: bool | None = None  # decided by the first image
    dataset_bin = DatasetBin(data_dir) if s.region == "bin" else None
    floor = floor_bin(data_dir, s)
    for scene_id, image_id in tqdm(items, unit="image", disable=not progress):
        ann, rgb, depth = load_bop_item(root, scene_id, image_id, split=split)
        if dataset_bin is not None:  # the bin moves with each generated view
            pipeline.region_camera_m = bin_region_camera(dataset_bin, ann)
        if floor is not None:
            pipeline.floor_plane_camera, pipeline.floor_bounds_camera_m = bin_floor_camera(floor, ann)
        if with_depth is None:
            with_depth = depth is not None
            if not with_depth and not sensor.is_ideal:
                raise ConfigError(f"{root / split}: no depth maps, so the sensor {s.sensor!r} cannot be simulated")
        images.append(ann)
        if not with_depth:
            t0 = time.perf_counter()
            detections.append(pipeline.detector.detect(rgb, _region_box(pipeline, ann)))
            timings.append({"detect": 1000.0 * (time.perf_counter() - t0)})
            continue
        if depth is None:
            raise ConfigError(f"{root / split / f'{scene_id:06d}'}: image {image_id} has no depth map")
        depth_true = load_bop_true_depth(root, ann, split)
        depth_true = depth if depth_true is None else depth_true
        t0 = time.perf_counter()
        if not sensor.is_ideal:
            rng = sensor_rng(s.sensor_seed, scene_id, image_id)
            metals = image_metal_mask(ann, pipeline.models)
            rgb, depth = sensor.sense(rgb, depth_true, ann.intrinsics, rng, metal_mask=metals)
        sensor_ms.append(1000.0 * (time.perf_counter() - t0))
        frame = Frame(rgb, depth, ann.intrinsics, timestamp_s=0.0)
        result = pipeline.run(frame)
        if s.rescue:  # the rescued poses are scored as the pipeline's; their verdicts apart
            t0 = time.perf_counter()
            more = pipeline.rescue(result.poses, frame)
            rescue_ms.append(1000.0 * (time.perf_counter() - t0))
            result = replace(result, poses=more) if more is not None else result
            rescued += _verdicts(ann, [p for p in result.poses if "rescued" in p.details], pipeline.models)
        tare = result.depth_tare
        tared = depth_metrics(apply_tare(depth, tare), depth_true) if tare is not None else None
        depth_rows.append((scene_id, image_id, depth_metrics(depth, depth_true), tared, tare))
        detections.append(result.detections)
        timings.append(result.timings_ms)
        records += [e for _, _, e in match_poses(ann, result.poses, pipeline.models, s.min_visib_fract, s.match_iou)]
        verdicts += _verdicts(ann, result.poses + result.refused, pipeline.models)
        per_object += [(p.details["time_ms"], p.details["cpu_ms"]) for p in result.poses + result.refused
                       if "cpu_ms" in p.details]  # fmt: skip
    det = detection_metrics(images, detections, min_visib_fract=s.min_visib_fract)
    n_objects = [len(r) for r in detections]
    return {
        "split": split,
        "n_images": len(items),
        "detection": det.as_dict(),
        "pose": _named(pose_metrics_table(records), names) if with_depth else None,
        "pose_skipped": None if with_depth else NO_DEPTH,
        "pose_method": pipeline.pose_method,
        "refine": pipeline.refiner is not None,
        "conf_threshold": pipeline.detector.conf_threshold,
        "timings_ms_median": {k: float(np.median([t[k] for t in timings])) for k in timings[0]},
        "detections_per_image_median": float(np.median(n_objects)),
        "sensor": sensor.name,
        "sensor_seed": s.sensor_seed,
        "sensor_ms_median": _median_of(sensor_ms) if with_depth else None,
        "depth": asdict(mean_depth_metrics(m for _, _, m, _, _ in depth_rows)) if with_depth else None,
        "depth_tared": _tared_metrics(depth_rows) if with_depth else None,
        "depth_tare": _tare_summary([t for *_, t in depth_rows]) if with_depth else None,
        "depth_per_image": [
            {"scene_id": sc, "image_id": im, **asdict(m), "tare": None if t is None else t.as_dict()}
            for sc, im, m, _, t in depth_rows
        ],
        "strategies": None if pipeline.strategies is None else {names[k]: v for k, v in pipeline.strategies.items()},
        "verification": _verification_summary(verdicts) if pipeline.strategies is not None and with_depth else None,
        "rescue": {"accepted": len(rescued), "correct": sum(c for _, c in rescued), "ms_median": _median_of(rescue_ms)}
        if s.rescue
        else None,
        "pose_ms_per_object_median": _median_of([t for t, _ in per_object]),
        "pose_cpu_ms_per_object_median": _median_of([c for _, c in per_object]),
    }


def _tared_metrics(rows: list) -> dict | None:
    """The depth metrics after the tare (rows ``(scene, image, sensed, tared, tare)``), None where none ran."""
    tared = [r[3] for r in rows]
    return None if any(m is None for m in tared) else asdict(mean_depth_metrics(tared))


def _tare_summary(tares: list[Tare | None]) -> dict | None:
    """How often the tare was applied, the median and largest size of its offsets (mm of depth at 1 m) and the median
    floor pixels; None where it did not run (no floor plane, or off)."""
    ran = [t for t in tares if t is not None]
    if not ran:
        return None
    applied = [t for t in ran if t.applied]
    sizes = [abs(t.offset_mm_at_1m) for t in applied]
    return {
        "images": len(ran),
        "applied": len(applied),
        "offset_mm_at_1m_abs_median": _median_of(sizes),
        "offset_mm_at_1m_abs_max": max(sizes) if sizes else math.nan,
        "floor_px_median": _median_of([float(t.floor_px) for t in ran]),
        "not_applied": sorted({t.reason for t in ran if not t.applied}),
    }


def _region_box(pipeline: PerceptionPipeline, ann: ImageAnnotation) -> tuple[int, ...] | None:
    """The detector's region of interest in ``ann``'s image, as ``PerceptionPipeline.run`` sets it."""
    if pipeline.region_camera_m is None:
        return None
    roi = region_of_interest(pipeline.region_camera_m, ann.intrinsics)
    if roi is None:
        raise ConfigError(f"image {ann.name}: the region of interest (the bin) lies outside the image")
    return roi


def dataset_classes(data_dir: str | Path, split: str) -> dict[int, str]:
    """obj_id -> name of a dataset's parts: the ids of ``bop/models/models_info.json`` (else those in the split's
    ground truth), the names of ``yolo/data.yaml`` where it names as many classes (class index = position in the
    sorted ids, as the writers number them), else ``"?"``."""
    root = Path(data_dir) / "bop"
    info = root / "models" / "models_info.json"
    if info.is_file():
        ids = sorted(int(k) for k in read_json(info, "BOP models info"))
    else:
        ids = sorted({int(g["obj_id"]) for scene in sorted((root / split).glob("*/scene_gt.json"))
                      for entries in read_json(scene, "BOP scene_gt").values() for g in entries})  # fmt: skip
    names = ["?"] * len(ids)
    yaml_path = Path(data_dir) / "yolo" / "data.yaml"
    if yaml_path.is_file():
        yolo_names = parse_data_yaml(yaml_path.read_text(), yaml_path).get("names", [])
        names = yolo_names if len(yolo_names) == len(ids) else names
    return dict(zip(ids, names, strict=True))


def check_model_classes(data_dir: str | Path, model_classes: dict[int, str], split: str | None = None) -> None:
    """Raises ConfigError, naming both lists, when the dataset has parts (obj_ids) the models do not know, or a part
    the models know by another name (one obj_id, two names: the dataset and the models came from different
    catalogues); models that know more parts than the dataset has are fine. ``model_classes``: obj_id -> name of the
    models' parts. A dataset part without a name (``"?"``, or the placeholder ``obj_OOOOOO`` of a BOP model file or a
    converted label set) is checked by obj_id only."""
    root = Path(data_dir) / "bop"
    if not root.is_dir():
        raise ConfigError(f"{data_dir}: not a generated dataset (no bop/ folder)")
    dataset = dataset_classes(data_dir, split or default_split(root))
    missing = sorted(set(dataset) - set(model_classes))
    if missing:
        raise ConfigError(
            f"{data_dir}: the models do not know the dataset's parts {missing}. Dataset: {_listing(dataset)}; "
            f"models: {_listing(model_classes)}. Evaluate models trained for this dataset's parts, or convert the "
            "dataset with an --id-map onto the models' obj_ids"
        )
    renamed = sorted(i for i in dataset if not same_part(i, dataset[i], model_classes))
    if renamed:
        raise ConfigError(
            f"{data_dir}: the models name the dataset's parts {renamed} differently. Dataset: {_listing(dataset)}; "
            f"models: {_listing(model_classes)}. The dataset and the models must come from one catalogue (its ids "
            "and names)"
        )


def same_part(obj_id: int, dataset_name: str, model_classes: dict[int, str]) -> bool:
    """Whether the models know the dataset's part ``obj_id`` as the same part: by obj_id, and by name unless the
    dataset leaves it unnamed (``"?"`` or the placeholder ``obj_OOOOOO``)."""
    if obj_id not in model_classes:
        return False
    return dataset_name in ("?", f"obj_{obj_id:06d}") or model_classes[obj_id] == dataset_name


def _listing(classes: dict[int, str]) -> str:
    return "[" + ", ".join(f"{i} {n}" for i, n in sorted(classes.items())) + "]"


def evaluate_detector(
    detector: YoloSegDetector,
    data_dir: str | Path,
    settings: EvalSettings | None = None,
    progress: bool = True,
    operating_threshold: float | None = None,
) -> dict:
    """Box and mask mAP of ``detector`` alone on the split's images (for the COCO convention of a low confidence
    threshold, e.g. 0.001, where the pipeline runs at its operating threshold), with the per-part, size and
    visibility breakdown at the detector's threshold and at ``operating_threshold`` (``perception.detector_eval``)."""
    s = settings or EvalSettings()
    root, split, items = eval_items(data_dir, s)
    check_model_classes(data_dir, dict(zip(detector.class_obj_ids, detector.class_names, strict=True)), split)
    region = "bin" if s.region == "bin" else "full"
    dataset_bin = DatasetBin(data_dir) if region == "bin" else None
    images, detections, ms = run_detector(detector, root, split, items, region, dataset_bin, progress)
    operating = detector.conf_threshold if operating_threshold is None else operating_threshold
    report = detector_report(detector, images, detections, operating, s.min_visib_fract, s.match_iou)
    return {"split": split, "n_images": len(items), "conf_threshold": detector.conf_threshold, "region": region,
            "ms_median": float(np.median(ms)) if ms else math.nan, **report}  # fmt: skip


def image_metal_mask(ann: ImageAnnotation, models: dict[int, ObjectModel]) -> np.ndarray | None:
    """The image's pixels of specular metal, from the visible masks and the parts' materials."""
    materials = [models[i.obj_id].material if i.obj_id in models else "" for i in ann.instances]
    return metal_mask([i.mask_visib for i in ann.instances], materials, METALS)


def _verdicts(ann: ImageAnnotation, poses: list[ObjectPose], models: dict[int, ObjectModel]) -> list[tuple[bool, bool]]:
    """(accepted, correct) per verified pose: correct when it is within ADD(-S) < 0.1 d of a ground-truth instance of
    its part that its mask overlaps (any visibility, any overlap: a partial mask with a right pose is right)."""
    out = []
    for pose in poses:
        if pose.verified is None or pose.detection.mask is None:
            continue
        model = models[pose.obj_id]
        correct = any(
            _errors(pose, inst.T_camera_obj, model).correct()
            for inst in ann.instances
            if inst.obj_id == pose.obj_id and np.any(pose.detection.mask & inst.mask_visib)
        )
        out.append((bool(pose.verified), correct))
    return out


def _verification_summary(verdicts: list[tuple[bool, bool]]) -> dict:
    """Accepted and refused counts; false accepts (wrong among the accepted) and false refusals (refused among the
    correct) as fractions."""
    n_acc = sum(a for a, _ in verdicts)
    n_correct = sum(c for _, c in verdicts)
    return {
        "accepted": n_acc,
        "refused": len(verdicts) - n_acc,
        "false_accept": sum(a and not c for a, c in verdicts) / n_acc if n_acc else math.nan,
        "false_refuse": sum(c and not a for a, c in verdicts) / n_correct if n_correct else math.nan,
    }


def _median_of(values: list[float]) -> float:
    return float(np.median(values)) if values else math.nan


def _errors(pose: ObjectPose | None, T_gt: np.ndarray, model: ObjectModel) -> PoseErrors:
    return pose_errors(None if pose is None else pose.T_camera_object, T_gt, model)


def _named(table: dict, names: dict[int, str]) -> dict:
    return {
        "all": table["all"],
        "per_object": {f"{obj_id} {names.get(obj_id, '?')}": row for obj_id, row in table["per_object"].items()},
    }


def format_table(report: dict) -> str:
    """The report as a plain-text table (one row per part)."""
    det = report["detection"]
    how = f"pose method {report['pose_method']}{' + ICP' if report['refine'] else ''}"
    if report.get("strategies"):
        how = "pose strategies " + ", ".join(f"{k} {v}" for k, v in report["strategies"].items())
    if report["pose"] is None:
        how = f"pose skipped: {report['pose_skipped']}"
    lines = [
        f"{report['n_images']} images ({report['split']}), {how}",
        f"box mAP50 {det['box_map50']:.3f}  box mAP50-95 {det['box_map50_95']:.3f}  "
        f"mask mAP50 {det['mask_map50']:.3f}  mask mAP50-95 {det['mask_map50_95']:.3f}",
    ]
    if report["pose"] is not None:
        lines.append(f"{'part':<16}{'metric':>8}{'n':>6}{'ADD(-S)<0.1d':>14}{'re med deg':>12}{'te med mm':>11}")
        rows = {**report["pose"]["per_object"], "all": report["pose"]["all"]}
        for name, row in rows.items():
            lines.append(
                f"{name:<16}{row['metric']:>8}{row['n']:>6}{_pct(row['add_recall']):>14}"
                f"{row['median_re_deg']:>12.2f}{row['median_te_mm']:>11.2f}"
            )
        d = report["depth"]
        lines.append(
            f"sensor {report['sensor']} (seed {report['sensor_seed']}): depth AbsRel {d['abs_rel']:.4f}  "
            f"delta1 {_pct(d['delta1'])}  fill {_pct(d['fill_rate'])} against the exact depth"
        )
        if report.get("depth_tare"):
            tare, dt = report["depth_tare"], report.get("depth_tared") or {}
            lines.append(
                f"depth tare on the bin floor: applied in {tare['applied']} of {tare['images']} images, offset "
                f"|median| {tare['offset_mm_at_1m_abs_median']:.2f} mm at 1 m (max "
                f"{tare['offset_mm_at_1m_abs_max']:.2f}), floor pixels median {tare['floor_px_median']:.0f}; after it "
                f"AbsRel {dt.get('abs_rel', math.nan):.4f}"
            )
    t = dict(report["timings_ms_median"])
    if report["sensor_ms_median"] is not None:
        t["sensor"] = report["sensor_ms_median"]
    lines.append("median ms per frame: " + ", ".join(f"{k} {v:.1f}" for k, v in t.items()))
    if report.get("verification"):
        v = report["verification"]
        lines.append(
            f"verification: {v['accepted']} accepted, {v['refused']} refused; false accepts {_pct(v['false_accept'])}"
            f" of the accepted, false refusals {_pct(v['false_refuse'])} of the correct; pose + verification + "
            f"refinement per object median {report['pose_ms_per_object_median']:.1f} ms "
            f"({report['pose_cpu_ms_per_object_median']:.1f} ms CPU)"
        )
    if report.get("rescue"):
        r = report["rescue"]
        lines.append(
            f"rescue: {r['accepted']} parts posed on depth no detection explained, {r['correct']} of them right; "
            f"median {r['ms_median']:.0f} ms per frame"
        )
    return "\n".join(lines)


def format_comparison(reports: list[dict]) -> str:
    """One row per report (the same images through different sensors, with depth): detection, pose and depth side
    by side."""
    lines = [
        f"{'sensor':<11}{'box mAP50':>11}{'mask mAP50-95':>15}{'ADD(-S)<0.1d':>14}{'re med deg':>12}{'te med mm':>11}"
        f"{'AbsRel':>9}{'delta1':>8}{'fill':>8}{'sensor ms':>11}"
    ]
    for r in reports:
        det, pose, d = r["detection"], r["pose"]["all"], r["depth"]
        lines.append(
            f"{r['sensor']:<11}{det['box_map50']:>11.3f}{det['mask_map50_95']:>15.3f}{_pct(pose['add_recall']):>14}"
            f"{pose['median_re_deg']:>12.2f}{pose['median_te_mm']:>11.2f}{d['abs_rel']:>9.4f}{_pct(d['delta1']):>8}"
            f"{_pct(d['fill_rate']):>8}{r['sensor_ms_median']:>11.1f}"
        )
    return "\n".join(lines)


def _pct(x: float) -> str:
    return "n/a" if math.isnan(x) else f"{100 * x:.1f}%"
