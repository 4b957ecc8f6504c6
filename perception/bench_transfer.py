"""``sygrid bench transfer``: does a detector trained on one image source work on another? The transfer matrix.

``sygrid bench transfer --detector NAME=PATH ... --source NAME=DATASET ... [--home DETECTOR=SOURCE ...]
[--held-apart SOURCE] [--max-images N] [--threads T]`` evaluates every detector on every source, training nothing.
``--detector``: a model folder (manifest.json) or a training run folder (detector.onnx); ``--source``: a
``sygrid generate`` or ``sygrid convert`` folder, its default split. ``--home``: a detector's same-source (default:
the source of the detector's name); ``--held-apart``: the source the targets are checked on. The measurements and
their definitions: ``perception.transfer``.

Prints the matrix (rows detectors, columns sources: class-aware box mAP50, its ratio to the detector's home cell,
class-agnostic box mAP50, median ms per image), then per detector and source the box AP50 per part and per size
bin and the recall per size bin, then with ``--held-apart`` each target with its measured value. Writes
``bench/results/NAME.{json,png}`` (``--name``, default ``transfer``): every cell's figures, the matrix and the
target checks; the chart is a heatmap of box mAP50 with the ratio in each cell (left) and the recall per size bin
of each cell (right). With ``--cards`` each model folder's row goes into its ``detector.card.md`` as the section
``CARD_HEADING`` (replacing that section of an earlier run; packing the folder again drops it with the rest of
the card, since a new detector has not been measured).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from perception.detector_eval import COCO_CONF
from perception.evaluation import EvalSettings
from perception.model_card import invoked_command, replace_card_section
from perception.transfer import (
    MIN_SIDE_PX,
    TARGETS,
    DetectorSpec,
    detector_spec,
    evaluate_cell,
    homes,
    source_spec,
    target_checks,
    transfer_matrix,
    unique,
)
from sygrid.bench.common import DEFAULT_RESULTS_DIR, add_result_arguments, replot, save_results
from sygrid.detection_breakdown import SIZE_BINS
from sygrid.errors import ConfigError


def run_benchmark(
    detectors: list[DetectorSpec],
    sources: dict[str, Path],
    home: dict[str, str | None],
    held_apart: str | None = None,
    max_images: int | None = None,
    threads: int = 2,
    timing_images: int = 20,
    progress: bool = True,
) -> dict:
    """Every detector on every source; the results as a JSON-able dict (``cells[detector][source]``)."""
    settings = EvalSettings(max_images=max_images)
    cells: dict[str, dict[str, dict]] = {}
    for spec in detectors:
        cells[spec.name] = {}
        for source, folder in sources.items():
            if progress:
                print(f"-- {spec.name} on {source}")
            cells[spec.name][source] = evaluate_cell(spec, folder, settings, threads, timing_images, progress)
    return {
        "detectors": {d.name: {**d.as_dict(), "home": home[d.name]} for d in detectors},
        "sources": {name: str(folder) for name, folder in sources.items()},
        "held_apart": held_apart,
        "max_images": max_images,
        "threads": threads,
        "coco_conf": COCO_CONF,
        "min_visib_fract": settings.min_visib_fract,
        "match_iou": settings.match_iou,
        "min_side_px": MIN_SIDE_PX,
        "size_bins_px": [[label, lo, hi if math.isfinite(hi) else None] for label, lo, hi in SIZE_BINS],
        "cells": cells,
        "matrix": transfer_matrix(cells, home),
        "targets": TARGETS,
        "target_checks": target_checks(cells, home, held_apart) if held_apart else [],
    }


CARD_HEADING = "## Transfer to other image sources"


def card_section(results: dict, detector: str, command: str) -> list[str]:
    """The model card section of ``detector``'s row of the matrix: per source box mAP50, its ratio to the home
    source, class-agnostic box mAP50 and recall of large parts, recall of small parts; the held-apart targets."""
    m, small = results["matrix"], SIZE_BINS[0][0]
    k, held_apart = m["detectors"].index(detector), results["held_apart"]
    lines = [CARD_HEADING, "",
             f"`{command}` ({results['max_images'] or 'all'} images per source; `bench/results/*.json` holds every "
             f"figure): box mAP50 at confidence {results['coco_conf']}, its ratio to the home source, class-agnostic "
             f"box mAP50 and recall of parts of {results['min_side_px']:g} px or more, and recall of parts under "
             f"{SIZE_BINS[0][2]:g} px at the operating threshold.", "",
             f"| source | box mAP50 | ratio to home | class-agnostic box mAP50 | class-agnostic recall >= "
             f"{results['min_side_px']:g} px | recall < {SIZE_BINS[0][2]:g} px |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for j, source in enumerate(m["sources"]):
        c = results["cells"][detector][source]
        tag = " (home)" if source == m["home"][detector] else " (held apart)" if source == held_apart else ""
        recall_small = c["recall_by_size"][small] if c["recall_by_size"] else None
        figures = (_num(c["box_map50"]), _num(m["ratio"][k][j], 2), _num(c["agnostic_box_map50"]),
                   _pct(c["agnostic_recall_large"]), _pct(recall_small))  # fmt: skip
        lines.append(f"| {source}{tag} | " + " | ".join(figures) + " |")
    checks = [t for t in results["target_checks"] if t["detector"] == detector]
    if checks:
        met = {True: "met", False: "not met", None: "not measured"}
        lines += ["", f"Targets on the held-apart source ({held_apart}): " + "; ".join(
            f"{t['target']} {_num(t['measured'])} against >= {_num(t['threshold'], 2)} ({met[t['met']]})"
            for t in checks) + "."]  # fmt: skip
    return lines


def _num(x: float | None, digits: int = 3) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _pct(x: float | None) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{100 * x:.1f}%"


def format_results(results: dict) -> str:
    m, labels = results["matrix"], [label for label, _, _ in SIZE_BINS]
    width = max(10, *(len(s) + 2 for s in m["sources"]))
    lines = [f"box mAP50 (at confidence {results['coco_conf']}), its ratio to the detector's home cell, "
             "class-agnostic box mAP50 and median detector ms per image at the operating threshold",
             f"{'detector':<24}{'':<10}" + "".join(f"{s:>{width}}" for s in m["sources"])]  # fmt: skip
    figures = (("box mAP50", "box_map50", _num), ("ratio", "ratio", _num), ("agnostic", "agnostic_box_map50", _num),
               ("ms", "ms_median", lambda x: _num(x, 1)))  # fmt: skip
    for k, det in enumerate(m["detectors"]):
        heads = [det, f"(home: {m['home'][det] or 'none'})"]
        for row, (label, key, fmt) in enumerate(figures):
            head = heads[row] if row < len(heads) else ""
            lines.append(f"{head:<24}{label:<10}" + "".join(f"{fmt(v):>{width}}" for v in m[key][k]))
    for det, by_source in results["cells"].items():
        for source, c in by_source.items():
            lines.append(f"\n{det} on {source}: {c['n_images']} images ({c['split']}), box mAP50-95 "
                         f"{_num(c['box_map50_95'])}, mask mAP50 {_num(c['mask_map50'])}")  # fmt: skip
            if c["classes_note"]:
                lines.append(f"  note: {c['classes_note']}")
            for part, ap in (c["ap50_by_part"] or {}).items():
                lines.append(f"  {part:<24} box AP50 {_num(ap)}")
            lines.append(f"  {'size [px]':<24}" + "".join(f"{label:>10}" for label in labels))
            rows = (("n (every part)", c["n_by_size"], str), ("box AP50", c["ap50_by_size"], _num),
                    (f"recall@{c['operating_threshold']:g}", c["recall_by_size"], _pct),
                    ("agnostic recall", c["agnostic_recall_by_size"], _pct))  # fmt: skip
            for name, values, fmt in rows:
                lines.append(f"  {name:<24}" + "".join(f"{fmt(values[lb]) if values else 'n/a':>10}" for lb in labels))
            lines.append(f"  class-agnostic recall of parts >= {results['min_side_px']:g} px: "
                         f"{_pct(c['agnostic_recall_large'])} of {c['n_large']}")  # fmt: skip
    if results["target_checks"]:
        lines.append(f"\ntargets on the held-apart source {results['held_apart']}:")
        for t in results["target_checks"]:
            met = {True: "met", False: "NOT met", None: "not measured"}[t["met"]]
            lines.append(f"  {t['detector']}: {t['target']}: measured {_num(t['measured'])}, target >= "
                         f"{_num(t['threshold'], 2)}: {met}")  # fmt: skip
    return "\n".join(lines)


def chart(results: dict):
    m = results["matrix"]
    detectors, sources = m["detectors"], m["sources"]
    fig, (ax_map, ax_rec) = plt.subplots(1, 2, figsize=(13, 0.6 * len(detectors) + 4))
    values = np.array([[math.nan if v is None else v for v in row] for row in m["box_map50"]], dtype=float)
    image = ax_map.imshow(values, vmin=0.0, vmax=1.0, cmap="viridis", aspect="auto")
    for i in range(len(detectors)):
        for j in range(len(sources)):
            r = m["ratio"][i][j]
            text = f"{_num(values[i, j])}\n" + (f"x{r:.2f}" if r is not None and math.isfinite(r) else "no ratio")
            ax_map.text(j, i, text, ha="center", va="center", fontsize=8,
                        color="white" if not values[i, j] > 0.6 else "black")  # fmt: skip
    ax_map.set_xticks(range(len(sources)), sources, rotation=30, ha="right")
    ax_map.set_yticks(range(len(detectors)), detectors)
    ax_map.set(xlabel="source", ylabel="detector", title=f"box mAP50 at {results['coco_conf']} (x ratio to home)")
    fig.colorbar(image, ax=ax_map, fraction=0.046)
    labels = [label for label, _, _ in SIZE_BINS]
    markers = "osv^Dp*h"
    for i, det in enumerate(detectors):
        for j, source in enumerate(sources):
            c = results["cells"][det][source]
            recall = c["recall_by_size"] or c["agnostic_recall_by_size"]
            y = [math.nan if recall[label] is None else recall[label] for label in labels]
            style = "-" if c["recall_by_size"] else ":"
            ax_rec.plot(range(len(labels)), y, style, marker=markers[j % len(markers)], color=plt.cm.tab10(i % 10),
                        label=f"{det} on {source}")  # fmt: skip
    ax_rec.set_xticks(range(len(labels)), labels)
    ax_rec.set(xlabel="visible box, longer side [px]", ylabel="recall at the operating threshold", ylim=(0, 1.02),
               title="recall per size (dotted: class-agnostic, no shared parts)")  # fmt: skip
    ax_rec.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    return fig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--detector",
        action="append",
        default=[],
        metavar="NAME=PATH",
        help="a model folder (manifest.json) or a training run folder (detector.onnx); repeatable",
    )
    parser.add_argument(
        "--source",
        action="append",
        default=[],
        metavar="NAME=DATASET",
        help="a sygrid generate or sygrid convert folder (its default split); repeatable",
    )
    parser.add_argument(
        "--home",
        action="append",
        default=[],
        metavar="DETECTOR=SOURCE",
        help="a detector's same-source (default: the source named as the detector); repeatable",
    )
    parser.add_argument("--held-apart", default=None, metavar="SOURCE", help="the source the targets are checked on")
    parser.add_argument("--max-images", type=int, default=None, help="at most this many images per source")
    parser.add_argument("--timing-images", type=int, default=20, help="images of each cell's timing pass")
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime threads")
    parser.add_argument("--cards", action="store_true",
                        help="write each model folder's row into its detector.card.md")  # fmt: skip
    add_result_arguments(parser, "transfer")


def _positive(value: int | None, option: str) -> None:
    if value is not None and value < 1:
        raise ConfigError(f"{option}: expected a positive whole number, got {value}")


def run(args: argparse.Namespace, out_dir: Path = DEFAULT_RESULTS_DIR) -> int:
    if args.replot:
        replot(args.name, chart, out_dir)
        return 0
    if not args.detector or not args.source:
        raise ConfigError("sygrid bench transfer: give at least one --detector NAME=PATH and one --source "
                          "NAME=DATASET")  # fmt: skip
    for value, option in ((args.max_images, "--max-images"), (args.timing_images, "--timing-images"),
                          (args.threads, "--threads")):  # fmt: skip
        _positive(value, option)
    detectors = [detector_spec(text) for text in args.detector]
    unique([d.name for d in detectors], "--detector")
    parsed = [source_spec(text) for text in args.source]
    unique([name for name, _ in parsed], "--source")
    sources = dict(parsed)
    home = homes([d.name for d in detectors], list(sources), args.home)
    if args.held_apart is not None and args.held_apart not in sources:
        raise ConfigError(f"--held-apart {args.held_apart!r}: no source of that name (the --source names: "
                          f"{', '.join(sources)})")  # fmt: skip
    results = run_benchmark(detectors, sources, home, args.held_apart, args.max_images, args.threads,
                            args.timing_images)  # fmt: skip
    print(format_results(results))
    json_path, png_path = save_results(args.name, results, chart(results), out_dir)
    print(f"wrote {json_path} and {png_path}")
    if args.cards:
        command = invoked_command("sygrid bench transfer")
        for spec in detectors:
            if spec.kind == "model folder":
                card = spec.folder / "detector.card.md"
                replace_card_section(card, CARD_HEADING, card_section(results, spec.name, command))
                print(f"wrote the transfer section of {card}")
    return 0
