"""``sygrid bench perception``: speed against accuracy of the perception pipeline on a generated test set.

One run, one pass over the test images; for each image every variant is run on the same input:

- detector: the model folder's detector at several input sizes (and further detector ONNX files given with
  ``--detector NAME=PATH``, e.g. a wider model): median latency per frame against box mAP50 and mask mAP50-95;
- pose: on the detections of the manifest's detector, the direct (GDR-Net-style) and the PnP-RANSAC estimate, each
  with and without depth refinement (ICP), two more refinement settings on the direct estimate, and further pose
  ONNX files (``--pose NAME=PATH``): median milliseconds per object against ADD(-S) recall, median re and te.

Writes ``bench/results/perception.{json,png}``; the chart puts latency on the x axis and accuracy on the y axis,
one panel per stage, so a user can pick the point they need. Medians throughout; the targets (detector <= 40 ms,
pose <= 10 ms per object, refinement <= 20 ms per object on a 2-core CPU) are printed beside the figures.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from tqdm import tqdm

from perception.detector import YoloSegDetector
from perception.evaluation import EvalSettings, eval_items, match_poses
from perception.pipeline import PerceptionPipeline, PipelineOverrides, load_manifest
from perception.pose import PoseEstimator
from perception.refine import DepthRefiner, RefineConfig
from sygrid.bench.common import DEFAULT_RESULTS_DIR, median, percentile, save_chart, save_results
from sygrid.errors import ConfigError
from sygrid.fileio import read_json
from sygrid.metrics import detection_metrics, pose_errors, pose_metrics_table
from sygrid.writers import load_bop_item

TARGETS_MS = {"detector": 40.0, "pose_per_object": 10.0, "refine_per_object": 20.0}
DEFAULT_SIZES = (320, 416, 480, 640)
QUICK_SIZES = (320, 480)
# Refinement settings compared on the direct estimate, besides the default (5 starts, ICP from the best one)
REFINE_VARIANTS = {
    "ICP, 2 best starts": RefineConfig(icp_starts=2, max_iterations=30),
    "ICP from the estimate only": RefineConfig(pca_hypotheses=False),
    "ICP, 1 iteration per open3d call": RefineConfig(iterations_per_call=1),
}


@dataclass
class _Variant:
    """Accumulates one variant's outputs and timings over the images."""

    name: str
    outputs: list = field(default_factory=list)  # per image: detections or records
    ms: list[float] = field(default_factory=list)  # per frame (detector) or per object (pose)
    refine_ms: list[float] = field(default_factory=list)


def _named_paths(values: list[str], flag: str) -> dict[str, Path]:
    out = {}
    for value in values:
        name, sep, path = value.partition("=")
        if not sep or not name or not Path(path).is_file():
            raise ConfigError(f"{flag} {value!r}: expected NAME=PATH to an existing ONNX file")
        out[name] = Path(path)
    return out


def run_benchmark(
    models_dir: Path,
    data_dir: Path,
    sizes: tuple[int, ...] = DEFAULT_SIZES,
    max_images: int | None = None,
    extra_detectors: dict[str, Path] | None = None,
    extra_poses: dict[str, Path] | None = None,
    threads: int = 2,
    progress: bool = True,
) -> dict:
    """Runs every variant on every image of the dataset's test split; returns the results as a JSON-able dict."""
    pipeline = PerceptionPipeline.from_folder(models_dir, PipelineOverrides(refine=True, num_threads=threads))
    manifest = load_manifest(models_dir)
    base_size = manifest.detector.input_size or pipeline.detector.input_hw[0]
    detectors = {f"{manifest.detector.onnx} @ {s}": _detector(models_dir / manifest.detector.onnx, s, manifest, threads)
                 for s in sizes}  # fmt: skip
    for name, path in (extra_detectors or {}).items():
        detectors[f"{name} @ {base_size}"] = _detector(path, base_size, manifest, threads)
    poses = {manifest.pose.onnx: pipeline.pose}
    for name, path in (extra_poses or {}).items():
        poses[name] = PoseEstimator(path, models=pipeline.models, num_threads=threads)
    # refinement variants: the pipeline's (the default RefineConfig) for every estimate; two more for the direct one
    refiners = {"ICP": pipeline.refiner, **{k: DepthRefiner(c) for k, c in REFINE_VARIANTS.items()}}
    pose_variants = [(p, m, r) for p in poses for m in ("direct", "pnp") for r in ("", "ICP")]
    pose_variants[2:2] = [(manifest.pose.onnx, "direct", r) for r in REFINE_VARIANTS]

    settings = EvalSettings(max_images=max_images)
    root, split, items = eval_items(data_dir, settings)
    det_acc = {name: _Variant(name) for name in detectors}
    pose_acc = {v: _Variant(_pose_label(*v)) for v in pose_variants}
    base_name = f"{manifest.detector.onnx} @ {base_size}"
    images, n_detections, image_hw = [], [], None
    for scene_id, image_id in tqdm(items, unit="image", disable=not progress):
        ann, rgb, depth = load_bop_item(root, scene_id, image_id, split=split)
        images.append(ann)
        image_hw = list(rgb.shape[:2])
        for name, detector in detectors.items():
            t = time.perf_counter()
            found = detector.detect(rgb)
            det_acc[name].ms.append(1e3 * (time.perf_counter() - t))
            det_acc[name].outputs.append(found)
        base = det_acc.get(base_name)
        found = base.outputs[-1] if base else pipeline.detector.detect(rgb)
        usable = pipeline.poseable(found)
        n_detections.append(len(usable))
        for pose_name, estimator in poses.items():
            for method in ("direct", "pnp"):
                t = time.perf_counter()
                estimates = estimator.estimate(rgb, usable, ann.intrinsics, method=method)
                pose_ms = 1e3 * (time.perf_counter() - t)
                for refine in [r for p, m, r in pose_variants if p == pose_name and m == method]:
                    t = time.perf_counter()
                    result = [refiners[refine].refine(p, depth, ann.intrinsics, pipeline.models[p.obj_id])
                              for p in estimates] if refine else estimates  # fmt: skip
                    refine_ms = 1e3 * (time.perf_counter() - t) if refine else 0.0
                    acc = pose_acc[(pose_name, method, refine)]
                    if usable:  # per-object times of frames with objects
                        acc.ms.append((pose_ms + refine_ms) / len(usable))
                        if refine:
                            acc.refine_ms.append(refine_ms / len(usable))
                    for inst, pose in match_poses(ann, result, settings.min_visib_fract, settings.match_iou):
                        T = None if pose is None else pose.T_camera_object
                        acc.outputs.append(pose_errors(T, inst.T_camera_obj, pipeline.models[inst.obj_id]))

    names = {obj_id: m.name for obj_id, m in pipeline.models.items()}
    detector_rows = []
    for name, acc in det_acc.items():
        metrics = detection_metrics(images, acc.outputs, min_visib_fract=settings.min_visib_fract)
        detector_rows.append({"name": name, "ms_median": median(acc.ms), "ms_p90": percentile(acc.ms, 90),
                              "box_map50": metrics.box_map50, "box_map50_95": metrics.box_map50_95,
                              "mask_map50": metrics.mask_map50, "mask_map50_95": metrics.mask_map50_95})  # fmt: skip
    pose_rows = []
    for (pose_name, method, refine), acc in pose_acc.items():
        table = pose_metrics_table(acc.outputs)
        pose_rows.append({
            "name": acc.name, "pose_model": pose_name, "method": method, "refine": refine,
            "ms_per_object_median": median(acc.ms), "refine_ms_per_object_median": median(acc.refine_ms),
            "add_recall": table["all"]["add_recall"], "median_re_deg": table["all"]["median_re_deg"],
            "median_te_mm": table["all"]["median_te_mm"],
            "per_object": {f"{k} {names.get(k, '?')}": v for k, v in table["per_object"].items()},
        })  # fmt: skip
    return {
        "models": str(models_dir),
        "data": str(data_dir),
        "split": split,
        "n_images": len(items),
        "image_hw": image_hw,
        "detections_per_image_median": median(n_detections),
        "threads": threads,
        "targets_ms": TARGETS_MS,
        "detector": detector_rows,
        "pose": pose_rows,
    }


def _detector(path: Path, size: int, manifest, threads: int) -> YoloSegDetector:
    d = manifest.detector
    return YoloSegDetector(path, conf_threshold=d.conf_threshold, iou_threshold=d.iou_threshold, input_size=size,
                           num_threads=threads)  # fmt: skip


def _pose_label(pose_name: str, method: str, refine: str) -> str:
    return f"{Path(pose_name).stem} {method}{' + ' + refine if refine else ''}"


def chart(results: dict):
    fig, (ax_det, ax_pose) = plt.subplots(1, 2, figsize=(12, 4.8))
    for row in results["detector"]:
        for key, marker in (("box_map50", "o"), ("mask_map50_95", "s")):
            ax_det.scatter(row["ms_median"], row[key], marker=marker, color="C0" if key == "box_map50" else "C1")
        model, _, size = row["name"].rpartition(" @ ")
        ax_det.annotate(
            size if model.endswith(".onnx") else row["name"],  # the folder's detector: its size; others: named
            (row["ms_median"], row["box_map50"]),
            textcoords="offset points",
            xytext=(4, 4),
            fontsize=8,
        )
    ax_det.axvline(TARGETS_MS["detector"], color="grey", ls="--", lw=0.8)
    ax_det.scatter([], [], marker="o", color="C0", label="box mAP50")
    ax_det.scatter([], [], marker="s", color="C1", label="mask mAP50-95")
    ax_det.set(xlabel="detector latency per frame, median [ms]", ylabel="accuracy", ylim=(0, 1.02),
               title=f"detector input sizes ({results['n_images']} test images)")  # fmt: skip
    ax_det.legend(loc="lower right", fontsize=8)
    # colour: method and refinement; marker: the pose model (its width)
    methods = list(dict.fromkeys((r["method"], r["refine"]) for r in results["pose"]))
    markers = dict(zip(dict.fromkeys(r["pose_model"] for r in results["pose"]), "o^sDv", strict=False))
    for row in results["pose"]:
        colour = f"C{methods.index((row['method'], row['refine'])) % 10}"
        ax_pose.scatter(row["ms_per_object_median"], row["add_recall"], color=colour,
                        marker=markers.get(row["pose_model"], "o"), label=row["name"])  # fmt: skip
    ax_pose.axvline(TARGETS_MS["pose_per_object"], color="grey", ls="--", lw=0.8)
    ax_pose.axvline(TARGETS_MS["pose_per_object"] + TARGETS_MS["refine_per_object"], color="grey", ls=":", lw=0.8)
    ax_pose.set(xlabel="pose (+ refinement) per object, median [ms]", ylabel="ADD(-S) < 0.1 d recall", ylim=(0, 1.02),
                title="pose methods")  # fmt: skip
    ax_pose.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    return fig


def format_results(results: dict) -> str:
    lines = [f"{results['n_images']} images ({results['split']}), median {results['detections_per_image_median']:.0f}"
             f" detections per image, onnxruntime threads {results['threads']}",
             f"{'detector':<28}{'ms med':>8}{'ms p90':>8}{'box50':>7}{'box50-95':>9}{'mask50-95':>10}"]  # fmt: skip
    for r in results["detector"]:
        lines.append(f"{r['name']:<28}{r['ms_median']:>8.1f}{r['ms_p90']:>8.1f}{r['box_map50']:>7.3f}"
                     f"{r['box_map50_95']:>9.3f}{r['mask_map50_95']:>10.3f}")  # fmt: skip
    lines.append(f"{'pose':<28}{'ms/obj':>8}{'ICP ms':>8}{'ADD(-S)':>9}{'re deg':>8}{'te mm':>8}")
    for r in results["pose"]:
        lines.append(f"{r['name']:<28}{r['ms_per_object_median']:>8.2f}{r['refine_ms_per_object_median']:>8.2f}"
                     f"{100 * r['add_recall']:>8.1f}%{r['median_re_deg']:>8.2f}{r['median_te_mm']:>8.2f}")  # fmt: skip
    lines.append("targets: " + ", ".join(f"{k} <= {v:.0f} ms" for k, v in TARGETS_MS.items()))
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--models", type=Path, default=Path("models/builtin"), help="model folder (manifest.json)")
    parser.add_argument("--data", type=Path, default=Path("datasets/builtin_test"),
                        help="generated test set (sygrid generate launch/recipes/builtin_test.json)")  # fmt: skip
    parser.add_argument("--sizes", type=int, nargs="+", default=None, help=f"detector input sizes {DEFAULT_SIZES}")
    parser.add_argument("--max-images", type=int, default=None)
    parser.add_argument("--detector", action="append", default=[], metavar="NAME=PATH", help="another detector")
    parser.add_argument("--pose", action="append", default=[], metavar="NAME=PATH", help="another pose model")
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime threads")
    parser.add_argument("--quick", action="store_true", help=f"sizes {QUICK_SIZES}, 20 images")
    parser.add_argument("--replot", action="store_true", help="only redraw the chart from the saved perception.json")


def run(args: argparse.Namespace, out_dir: Path = DEFAULT_RESULTS_DIR) -> int:
    if args.replot:
        saved = read_json(out_dir / "perception.json", "perception benchmark results")
        print(f"redrew {save_chart('perception', chart(saved), out_dir)} from {out_dir / 'perception.json'}")
        return 0
    sizes = tuple(args.sizes or (QUICK_SIZES if args.quick else DEFAULT_SIZES))
    results = run_benchmark(
        args.models,
        args.data,
        sizes=sizes,
        max_images=20 if args.quick and args.max_images is None else args.max_images,
        extra_detectors=_named_paths(args.detector, "--detector"),
        extra_poses=_named_paths(args.pose, "--pose"),
        threads=args.threads,
    )
    print(format_results(results))
    fig = chart(results)
    json_path, png_path = save_results("perception", results, fig, out_dir)
    print(f"wrote {json_path} and {png_path}")
    return 0
