"""The detector transfer matrix (``sygrid bench transfer``): detectors evaluated, never trained, on image sources.

Inputs: detectors ``NAME=PATH`` (a model folder, whose manifest gives the detector's ONNX file, its view and its
operating threshold; or a training run folder holding ``detector.onnx``, seen whole at the manifest's default
threshold), and sources ``NAME=DATASET`` (a ``sygrid generate`` or ``sygrid convert`` folder; its default split,
``perception.evaluation.default_split``; depth is never read). Each detector looks at the whole frame.

Per (detector, source) cell, from one run at confidence ``COCO_CONF`` (``perception.detector_eval.run_detector``):

- class-aware: box mAP50 and mAP50-95, mask mAP50 (None for a detection-only model), box AP50 per part and per
  visible-box size bin, recall per size bin at the operating threshold (``detector_report``). Only the parts the
  detector and the source share count (``shared_parts``; the note says which were left out); with none shared,
  these are NaN (mAP) or None and the cell is measured class-agnostic only;
- class-agnostic (``sygrid.detection_breakdown.class_agnostic``: every part one category, a right box under the
  wrong name counts): box mAP50, recall per size bin, and the recall at the operating threshold of the instances
  whose visible box's longer side is at least ``MIN_SIDE_PX`` (every ground-truth part, known to the detector or
  not), and the instances per size bin (``n_by_size``, every part);
- speed: the median detector milliseconds per image at the operating threshold, over the first ``timing_images``.

Instances seen less than ``EvalSettings.min_visib_fract`` are neither needed nor penalised; a match needs mask IoU
(box IoU for a detection-only model) of at least ``EvalSettings.match_iou``.

The matrix: per detector, each cell's class-aware box mAP50 over its home cell's (the detector's same-source
cell): 1.0 on the home cell, NaN without a home or where the home figure is 0 or NaN. The targets (``TARGETS``)
are checked per detector on the held-apart source.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from perception.detector import YoloSegDetector
from perception.detector_eval import COCO_CONF, detector_report, run_detector
from perception.evaluation import EvalSettings, check_model_classes, dataset_classes, eval_items, same_part
from perception.manifest import MANIFEST_NAME, DetectorEntry, load_manifest
from perception.pipeline import PipelineOverrides, detector_view
from sygrid.detection_breakdown import SIZE_BINS, class_agnostic, instance_records, only_parts, recall_table
from sygrid.errors import ConfigError
from sygrid.metrics import detection_metrics

RUN_ONNX = "detector.onnx"  # a training run folder's detector
MIN_SIDE_PX = 32.0  # the agnostic recall target's parts: visible box's longer side at least this, image pixels
# issue 23's targets on the held-apart source: box mAP50 at least this fraction of the home figure, and the
# class-agnostic recall of the parts of MIN_SIDE_PX or more at the operating threshold
TARGETS = {"map50_ratio": 0.85, "agnostic_recall": 0.90}


@dataclass(frozen=True)
class DetectorSpec:
    """A detector of the matrix: ``folder`` with ``entry.onnx``; ``kind`` "model folder" or "training run"."""

    name: str
    folder: Path
    kind: str
    entry: DetectorEntry

    def detector(self, conf_threshold: float, threads: int) -> YoloSegDetector:
        """The detector at ``conf_threshold``, with the manifest's input size, NMS IoU and view."""
        e = self.entry
        return YoloSegDetector(self.folder / e.onnx, conf_threshold=conf_threshold, iou_threshold=e.iou_threshold,
                               input_size=e.input_size, num_threads=threads,
                               view=detector_view(e, PipelineOverrides()))  # fmt: skip

    def as_dict(self) -> dict:
        e = self.entry
        return {"path": str(self.folder), "kind": self.kind, "onnx": str(self.folder / e.onnx),
                "operating_threshold": e.conf_threshold, "view": {"scale": e.scale, "tile_px": e.tile_px}}  # fmt: skip


def name_and_path(text: str, option: str, what: str) -> tuple[str, Path]:
    """``NAME=PATH`` of ``option`` split; ConfigError naming the option where it is not that."""
    name, sep, path = text.partition("=")
    if not sep or not name.strip() or not path.strip():
        raise ConfigError(f"{option} {text!r}: expected NAME={what}")
    return name.strip(), Path(path.strip())


def detector_spec(text: str) -> DetectorSpec:
    """``--detector NAME=PATH``: a model folder (manifest.json) or a training run folder (detector.onnx)."""
    name, folder = name_and_path(text, "--detector", "PATH (a model folder or a training run folder)")
    if (folder / MANIFEST_NAME).is_file():
        return DetectorSpec(name, folder, "model folder", load_manifest(folder).detector)
    if (folder / RUN_ONNX).is_file():
        return DetectorSpec(name, folder, "training run", DetectorEntry(onnx=RUN_ONNX))
    raise ConfigError(f"--detector {text!r}: {folder} is neither a model folder (no {MANIFEST_NAME}) nor a training "
                      f"run folder (no {RUN_ONNX})" + ("" if folder.exists() else ": no such folder"))  # fmt: skip


def source_spec(text: str) -> tuple[str, Path]:
    """``--source NAME=DATASET``: a dataset folder with a ``bop/`` folder."""
    name, folder = name_and_path(text, "--source", "DATASET (a sygrid generate or sygrid convert folder)")
    if not (folder / "bop").is_dir():
        raise ConfigError(f"--source {text!r}: {folder} is not a dataset folder (no bop/ folder)")
    return name, folder


def unique(names: list[str], option: str) -> None:
    """ConfigError naming ``option`` where a name is given twice."""
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ConfigError(f"{option}: the name(s) {', '.join(repeated)} given twice; each needs its own name")


def homes(detectors: list[str], sources: list[str], pairs: list[str]) -> dict[str, str | None]:
    """Each detector's home source: ``--home DET=SRC`` where given, else the source of the detector's name, else
    None."""
    out: dict[str, str | None] = {d: d if d in sources else None for d in detectors}
    given = []
    for text in pairs:
        det, sep, src = (s.strip() for s in text.partition("="))
        if not sep or not det or not src:
            raise ConfigError(f"--home {text!r}: expected DETECTOR=SOURCE")
        if det not in detectors:
            raise ConfigError(f"--home {text!r}: no detector named {det!r} (the --detector names: "
                              f"{', '.join(detectors)})")  # fmt: skip
        if src not in sources:
            raise ConfigError(f"--home {text!r}: no source named {src!r} (the --source names: {', '.join(sources)})")
        given.append(det)
        out[det] = src
    unique(given, "--home")
    return out


def shared_parts(model: dict[int, str], data_dir: Path, split: str) -> tuple[list[int], str | None]:
    """The obj_ids a detector (``model``: obj_id -> name) and a source share, by ``check_model_classes``' rule (an
    unnamed source part is matched by obj_id alone), and a note where that is not every part of the source."""
    try:
        check_model_classes(data_dir, model, split)
        return sorted(dataset_classes(data_dir, split)), None
    except ConfigError as exc:
        source = dataset_classes(data_dir, split)
        shared = sorted(i for i, n in source.items() if same_part(i, n, model))
        left = sorted(set(source) - set(shared))
        how = f"on the shared obj_ids {shared} alone" if shared else "class-agnostic only (no obj_id shared)"
        return shared, f"class-aware metrics {how}; the source's parts {left} left out ({exc})"


def evaluate_cell(spec: DetectorSpec, data_dir: Path, settings: EvalSettings, threads: int, timing_images: int,
                  progress: bool = True) -> dict:  # fmt: skip
    """One cell of the matrix: the figures of the module docstring as a JSON-able dict."""
    root, split, items = eval_items(data_dir, settings)
    if not items:
        raise ConfigError(f"{root / split}: no images")
    low = spec.detector(COCO_CONF, threads)
    model = dict(zip(low.class_obj_ids, low.class_names, strict=True))
    shared, note = shared_parts(model, data_dir, split)
    op = max(spec.entry.conf_threshold, COCO_CONF)
    images, detections, _ = run_detector(low, root, split, items, "full", None, progress)
    labels = [label for label, _, _ in SIZE_BINS]
    cell: dict = {"split": split, "n_images": len(items), "operating_threshold": op, "shared_obj_ids": shared,
                  "classes_note": note, "box_map50": math.nan, "box_map50_95": math.nan, "mask_map50": None,
                  "ap50_by_part": None, "ap50_by_size": None, "recall_by_size": None}  # fmt: skip
    if shared:
        kept_images, kept = only_parts(images, detections, shared)
        report = detector_report(low, kept_images, kept, op, settings.min_visib_fract, settings.match_iou)
        ap, recall = report["breakdown"]["ap"][f"{COCO_CONF:g}"], report["breakdown"]["recall"]["all"]
        t = f"recall@{op:g}"
        cell |= {"box_map50": report["box_map50"], "box_map50_95": report["box_map50_95"],
                 "mask_map50": report["mask_map50"] if low.has_masks else None,
                 "ap50_by_part": {f"{i} {model[i]}": ap.get(str(i), {}).get("all", {}).get("box_ap50", math.nan)
                                  for i in shared},
                 "ap50_by_size": {label: ap["all"][label]["box_ap50"] for label in labels},
                 "recall_by_size": {label: recall[label][t] for label in labels}}  # fmt: skip
    agnostic_images, agnostic = class_agnostic(images, detections)
    metrics = detection_metrics(agnostic_images, agnostic, min_visib_fract=settings.min_visib_fract)
    records = instance_records(agnostic_images, agnostic, [op], settings.min_visib_fract, settings.match_iou)
    rows = recall_table(records, [op])["all"]
    large = [r.found[op] for r in records if r.box_px >= MIN_SIDE_PX]
    cell |= {"agnostic_box_map50": metrics.box_map50,
             "agnostic_recall_by_size": {label: rows[label][f"recall@{op:g}"] for label in labels},
             "n_by_size": {label: rows[label]["n"] for label in labels},
             "agnostic_recall_large": float(np.mean(large)) if large else math.nan, "n_large": len(large)}  # fmt: skip
    del images, detections, agnostic  # a cell's detections go before the next one's come
    _, _, ms = run_detector(spec.detector(op, threads), root, split, items[:timing_images], progress=False)
    cell["ms_median"] = float(np.median(ms))
    cell["timing_images"] = len(ms)
    return cell


def ratio(value: float, home: float) -> float:
    """``value / home``; NaN where the home figure is not a positive number."""
    return value / home if math.isfinite(home) and home > 0 else math.nan


def transfer_matrix(cells: dict[str, dict[str, dict]], home: dict[str, str | None]) -> dict:
    """Rows detectors, columns sources: class-aware and agnostic box mAP50, the ratio to the home cell, ms."""
    detectors, sources = list(cells), list(next(iter(cells.values())))

    def grid(key: str) -> list[list[float]]:
        return [[cells[d][s][key] for s in sources] for d in detectors]

    ratios = [[ratio(cells[d][s]["box_map50"], cells[d][home[d]]["box_map50"]) if home[d] else math.nan
               for s in sources] for d in detectors]  # fmt: skip
    return {"detectors": detectors, "sources": sources, "home": home, "box_map50": grid("box_map50"),
            "ratio": ratios, "agnostic_box_map50": grid("agnostic_box_map50"),
            "ms_median": grid("ms_median")}  # fmt: skip


def target_checks(cells: dict[str, dict[str, dict]], home: dict[str, str | None], held_apart: str) -> list[dict]:
    """Per detector, issue 23's two targets on ``held_apart``: the box mAP50 ratio to the home cell and the
    class-agnostic recall of large parts, measured beside target; ``met`` None where the figure is not measured (no
    home or a home figure of 0, no shared parts, no large instance)."""
    rows = []
    for det, by_source in cells.items():
        cell = by_source[held_apart]
        home_map = cells[det][home[det]]["box_map50"] if home[det] else math.nan
        what = f"box mAP50 on {held_apart} / on its home ({home[det] or 'none'})"
        rows.append({**_check(det, what, ratio(cell["box_map50"], home_map), TARGETS["map50_ratio"]),
                     "box_map50": cell["box_map50"], "home_box_map50": home_map})  # fmt: skip
        op = cell["operating_threshold"]
        what = f"class-agnostic recall at {op:g} of parts >= {MIN_SIDE_PX:g} px on {held_apart}"
        rows.append({**_check(det, what, cell["agnostic_recall_large"], TARGETS["agnostic_recall"]),
                     "n": cell["n_large"]})  # fmt: skip
    return rows


def _check(detector: str, what: str, measured: float, target: float) -> dict:
    return {"detector": detector, "target": what, "measured": measured, "threshold": target,
            "met": bool(measured >= target) if math.isfinite(measured) else None}  # fmt: skip
