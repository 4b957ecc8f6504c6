"""``sygrid bench detection``: where and at what scale the detector looks, accuracy against latency.

Variants of one model folder's detector on a generated test set: the whole frame at several input sizes, the bin's
image box (``perception.detector_eval``) at several scales, and overlapping tiles (``perception.tiling``). Per
variant: box and mask mAP (confidence 0.001), recall at the manifest's threshold per visible-box size bin, and the
median detector milliseconds per frame at that threshold (onnxruntime CPU, ``--threads``; timed on the first
``--timing-images`` images in a separate pass, since a 0.001 threshold makes the masks of many more boxes).

Writes ``bench/results/NAME.{json,png}`` (``--name``, default ``detection``); the chart puts latency on the x axis
and accuracy on the y axis.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from perception.detector import YoloSegDetector
from perception.detector_eval import COCO_CONF, detector_report, region_box, run_detector
from perception.evaluation import EvalSettings, eval_items
from perception.manifest import load_manifest
from perception.tiling import ViewSettings
from sygrid.bench.common import DEFAULT_RESULTS_DIR, add_result_arguments, median, replot, save_results
from sygrid.dataset import DatasetBin
from sygrid.detection_breakdown import SIZE_BINS
from sygrid.errors import ConfigError
from sygrid.writers import load_bop_item


@dataclass(frozen=True)
class Variant:
    """``region`` "full" or "bin"; ``input_size`` the model's input side (whole-frame scale) or None; ``view`` how the
    region is seen."""

    name: str
    region: str
    input_size: int | None = None
    view: ViewSettings = field(default_factory=ViewSettings)


DEFAULT_VARIANTS = (
    Variant("full @ 480", "full", 480),
    Variant("full @ 640", "full", 640),
    Variant("full @ 800", "full", 800),
    Variant("bin @ 0.75", "bin", view=ViewSettings(scale=0.75)),
    Variant("bin @ 1.0", "bin", view=ViewSettings(scale=1.0)),
    Variant("bin @ 1.25", "bin", view=ViewSettings(scale=1.25)),
    Variant("bin @ 1.5", "bin", view=ViewSettings(scale=1.5)),
    Variant("tiles 640 px @ 1.67 (frame)", "full", view=ViewSettings(scale=640 / 384, tile_px=640)),
    Variant("tiles 320 px @ 1.0 (bin)", "bin", view=ViewSettings(scale=1.0, tile_px=320)),
    Variant("tiles 256 px @ 1.0 (bin)", "bin", view=ViewSettings(scale=1.0, tile_px=256)),
    Variant("tiles 320 px @ 1.0 (frame)", "full", view=ViewSettings(scale=1.0, tile_px=320)),
)
QUICK_VARIANTS = (DEFAULT_VARIANTS[0], DEFAULT_VARIANTS[4], DEFAULT_VARIANTS[8])


def select_variants(names: list[str]) -> tuple[Variant, ...]:
    """The named default variants, in the default table's order."""
    known = {v.name for v in DEFAULT_VARIANTS}
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ConfigError(f"--variant: unknown {', '.join(map(repr, unknown))}; expected one of "
                          f"{', '.join(repr(v.name) for v in DEFAULT_VARIANTS)}")  # fmt: skip
    return tuple(v for v in DEFAULT_VARIANTS if v.name in names)


def run_benchmark(
    models_dir: Path,
    data_dir: Path,
    variants: tuple[Variant, ...] = DEFAULT_VARIANTS,
    max_images: int | None = None,
    timing_images: int = 30,
    threads: int = 2,
    progress: bool = True,
) -> dict:
    manifest = load_manifest(models_dir)
    d = manifest.detector
    settings = EvalSettings(max_images=max_images)
    root, split, items = eval_items(data_dir, settings)
    if not items:
        raise ConfigError(f"{root / split}: no images")
    dataset_bin = DatasetBin(data_dir) if any(v.region == "bin" for v in variants) else None
    rows = []
    for v in variants:

        def make(conf: float, v: Variant = v) -> YoloSegDetector:
            size = v.input_size or d.input_size
            return YoloSegDetector(models_dir / d.onnx, conf_threshold=conf, iou_threshold=d.iou_threshold,
                                   input_size=size, num_threads=threads, view=v.view)  # fmt: skip

        if progress:
            print(f"-- {v.name}")
        detector = make(COCO_CONF)
        images, detections, _ = run_detector(detector, root, split, items, v.region, dataset_bin, progress)
        report = detector_report(detector, images, detections, d.conf_threshold, settings.min_visib_fract,
                                 settings.match_iou)  # fmt: skip
        ms = _time(make(d.conf_threshold), root, split, items[:timing_images], v.region, dataset_bin)
        recall = report["breakdown"]["recall"]["all"]
        t_op = f"recall@{d.conf_threshold:g}"
        del images, detections  # a variant's detections go before the next one's come
        rows.append({
            "name": v.name, "region": v.region, "input_size": v.input_size, "scale": report["scale"],
            "tile_px": v.view.tile_px, "tile_overlap": v.view.tile_overlap if v.view.tile_px else None,
            "ms_median": median(ms), "box_map50": report["box_map50"], "box_map50_95": report["box_map50_95"],
            "mask_map50": report["mask_map50"], "mask_map50_95": report["mask_map50_95"],
            "recall": recall["all"][t_op],
            "recall_by_size": {label: recall[label][t_op] for label, _, _ in SIZE_BINS},
            "n_by_size": {label: recall[label]["n"] for label, _, _ in SIZE_BINS},
            "recall_by_part": {p: r["all"][t_op] for p, r in report["breakdown"]["recall"].items() if p != "all"},
            "nominal_curve": report["breakdown"]["nominal_curve"][f"{d.conf_threshold:g}"],
            "box_curve": report["breakdown"]["box_curve"][f"{d.conf_threshold:g}"],
            "recall_by_part_size": {p: {k: r[k][t_op] for k, _, _ in SIZE_BINS}
                                    for p, r in report["breakdown"]["recall"].items()},
            "min_reliable_px": report["breakdown"]["min_reliable_px"][f"{d.conf_threshold:g}"],
        })  # fmt: skip
    return {
        "models": str(models_dir),
        "data": str(data_dir),
        "split": split,
        "n_images": len(items),
        "timing_images": min(timing_images, len(items)),
        "threads": threads,
        "operating_threshold": d.conf_threshold,
        "variants": rows,
    }


def _time(detector: YoloSegDetector, root: Path, split: str, items: list, region: str, dataset_bin) -> list[float]:
    frames = []
    for scene_id, image_id in items:
        ann, rgb, _ = load_bop_item(root, scene_id, image_id, split=split)
        frames.append((rgb, region_box(region, dataset_bin, ann)))  # type: ignore[arg-type]
    detector.detect(*frames[0])  # warm-up
    ms = []
    for rgb, roi in frames:
        t = time.perf_counter()
        detector.detect(rgb, roi)
        ms.append(1e3 * (time.perf_counter() - t))
    return ms


def chart(results: dict):
    fig, (ax_map, ax_rec) = plt.subplots(1, 2, figsize=(13, 5))
    for k, row in enumerate(results["variants"]):
        colour = plt.cm.tab20(k % 20)
        ax_map.scatter(row["ms_median"], row["box_map50"], marker="o", color=colour, label=row["name"])
        ax_map.scatter(row["ms_median"], row["mask_map50_95"], marker="s", color=colour)
        ax_rec.scatter(row["ms_median"], row["recall"], marker="o", color=colour, label=row["name"])
        ax_rec.scatter(row["ms_median"], row["recall_by_size"][SIZE_BINS[0][0]], marker="v", color=colour)
    ax_map.set(xlabel="detector ms per frame, median", ylabel="box mAP50 (o), mask mAP50-95 (s)", ylim=(0, 1),
               title=f"mAP at confidence {COCO_CONF} ({results['n_images']} images)")  # fmt: skip
    ax_rec.set(xlabel="detector ms per frame, median", ylim=(0, 1),
               ylabel=f"recall (o), recall of parts < {SIZE_BINS[0][2]:g} px (v)",
               title=f"recall at confidence {results['operating_threshold']}")  # fmt: skip
    ax_map.legend(fontsize=7, loc="center right")
    fig.tight_layout()
    return fig


def format_results(results: dict) -> str:
    labels = [label for label, _, _ in SIZE_BINS]
    lines = [f"{results['n_images']} images ({results['split']}); ms: median over {results['timing_images']} images,"
             f" {results['threads']} threads; recall at {results['operating_threshold']}",
             f"{'variant':<30}{'scale':>6}{'ms':>8}{'box50':>7}{'mask50-95':>10}{'recall':>8}"
             + "".join(f"{'r ' + label:>9}" for label in labels) + f"{'min px':>8}"]  # fmt: skip
    for r in results["variants"]:
        lines.append(f"{r['name']:<30}{r['scale']:>6.2f}{r['ms_median']:>8.1f}{r['box_map50']:>7.3f}"
                     f"{r['mask_map50_95']:>10.3f}{100 * r['recall']:>7.1f}%"
                     + "".join(f"{100 * r['recall_by_size'][label]:>8.1f}%" for label in labels)
                     + f"{r['min_reliable_px']:>8.0f}")  # fmt: skip
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--models", type=Path, default=Path("models/builtin"), help="model folder (manifest.json)")
    parser.add_argument("--data", type=Path, default=Path("datasets/builtin_test"), help="generated test set")
    parser.add_argument("--max-images", type=int, default=None)
    parser.add_argument("--timing-images", type=int, default=30, help="images of the timing pass")
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime threads")
    parser.add_argument("--quick", action="store_true", help="three variants, 20 images")
    parser.add_argument(
        "--variant",
        action="append",
        default=None,
        metavar="NAME",
        help="run only this variant (repeatable; names as in the default table, e.g. 'bin @ 1.0')",
    )
    add_result_arguments(parser, "detection")


def run(args: argparse.Namespace, out_dir: Path = DEFAULT_RESULTS_DIR) -> int:
    if args.replot:
        replot(args.name, chart, out_dir)
        return 0
    results = run_benchmark(
        args.models,
        args.data,
        select_variants(args.variant) if args.variant else QUICK_VARIANTS if args.quick else DEFAULT_VARIANTS,
        max_images=20 if args.quick and args.max_images is None else args.max_images,
        timing_images=args.timing_images,
        threads=args.threads,
    )
    print(format_results(results))
    json_path, png_path = save_results(args.name, results, chart(results), out_dir)
    print(f"wrote {json_path} and {png_path}")
    return 0
