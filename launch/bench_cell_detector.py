"""``sygrid bench cell-detector``: the detector on the simulated cell's own camera, per input size.

The training images and the cell's overhead camera (0.9 m above the bin) see parts at different sizes, so the
input size that the test set prefers is not the cell's. For each seed the cell's bin is filled (the cell file's
scene, dropped with the seed) and the first overhead frame is taken; the detector runs at each input size on the
same frames. Ground truth is the simulator's: the parts whose centre the camera sees (``sim.oracle_perception``'s
visibility test) with the box of their projected 3D bounds. A detection is right when it has a part's class and
its box centre lies in that part's box (the projected 3D box is loose, so no IoU threshold). Each size runs on the
whole frame and on the bin's box only (``perception.pipeline.region_of_interest`` of the planner's bin, as the
picking runtime does with ``detect_in_bin``; same scale, so ``size`` is the whole frame's input size either way).
Reports per size and region: recall (parts found) and precision at the model folder's confidence threshold, the
recall over thresholds, and the median detector time per frame (this machine, onnxruntime CPU). Writes
``bench/results/cell_detector.{json,png}``.
"""

from __future__ import annotations

import argparse
import itertools
import time
from pathlib import Path
from typing import Any

import numpy as np

from launch.bench_cell import CELL_FILE
from robot.cell_setup import load_cell_setup
from robot.grasp_scene import BinGeometry
from sygrid.bench.common import DEFAULT_RESULTS_DIR, median, save_results
from sygrid.errors import ConfigError

SIZES = (480, 640, 800, 960)
REGIONS = ("frame", "bin")
THRESHOLDS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6)
_FLOOR_CONF = 0.05  # detections kept for the threshold sweep


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", type=int, default=12, help="bins (seeds 0..N-1), one frame each")
    parser.add_argument("--sizes", type=int, nargs="+", default=list(SIZES), help="detector input sizes")
    parser.add_argument("--config", type=Path, default=CELL_FILE, help="the simulated cell's file")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per frame and size")
    parser.add_argument(
        "--models", type=Path, action="append", default=[], help="another model folder to compare (repeatable)"
    )


def run(args: argparse.Namespace, out_dir: Path = DEFAULT_RESULTS_DIR) -> int:
    from perception.detector import YoloSegDetector
    from perception.manifest import load_manifest

    setup = load_cell_setup(args.config)
    if not setup.is_sim:
        raise ConfigError(f"{args.config}: sygrid bench cell-detector needs a simulated cell ([cell] kind = 'sim')")
    if args.seeds < 1 or args.repeats < 1 or any(s < 32 for s in args.sizes):
        raise ConfigError("--seeds >= 1, --repeats >= 1 and every --size >= 32 expected")
    folders = [setup.resolve(setup.data.perception.models_dir), *args.models]
    conf = setup.data.perception.conf_threshold or load_manifest(folders[0]).detector.conf_threshold
    bin_ = setup.planner_config().bin
    frames = [first_frame(setup.resolve(setup.data.sim.scene), seed, bin_) for seed in range(args.seeds)]
    truth_ids = np.array([obj_id for _, _, truth in frames for obj_id, _ in truth])
    rows = []
    for models_dir in folders:
        manifest = load_manifest(models_dir)
        for size, region in itertools.product(args.sizes, REGIONS):
            detector = YoloSegDetector(models_dir / manifest.detector.onnx, conf_threshold=_FLOOR_CONF,
                                       iou_threshold=manifest.detector.iou_threshold, input_size=size)  # fmt: skip
            detector.detect(frames[0][0], frames[0][1] if region == "bin" else None)  # warm-up
            names = dict(zip(detector.class_obj_ids, detector.class_names, strict=True))
            times, found, kept = [], [], []
            for rgb, roi, truth in frames:
                for _ in range(args.repeats):
                    start = time.perf_counter()
                    detections = detector.detect(rgb, roi if region == "bin" else None)
                    times.append(time.perf_counter() - start)
                found += best_scores(truth, detections)
                kept += [(d.score, is_right(d, truth)) for d in detections]
            found = np.array(found)
            row = {"models": models_dir.name, "region": region, **size_row(size, times, found, kept, conf)}
            row["recall_by_part"] = {
                names.get(int(k), str(k)): float((found[truth_ids == k] >= conf).mean()) for k in np.unique(truth_ids)
            }
            rows.append(row)
            print(f"{models_dir.name} @ {size:4d} px, {region:>5}: {row['ms_median']:6.1f} ms, recall "
                  f"{row['recall']:.2f}, precision {row['precision']:.2f} at confidence {conf}; "
                  f"by part {row['recall_by_part']}")  # fmt: skip
    results = {"config": {"cell": str(args.config), "seeds": args.seeds, "conf_threshold": conf,
                          "models": [str(f) for f in folders], "parts_seen": len(truth_ids)},
               "sizes": rows}  # fmt: skip
    json_path, png_path = save_results("cell_detector", results, chart(results), out_dir)
    print(f"wrote {json_path} and {png_path}")
    return 0


def first_frame(
    scene: Path, seed: int, bin_: BinGeometry
) -> tuple[np.ndarray, tuple[int, int, int, int] | None, list[tuple[int, np.ndarray]]]:
    """The overhead RGB frame of a fresh bin, the bin's image box, and its visible parts as (obj_id, box xyxy)."""
    from perception.pipeline import region_of_interest
    from sim.camera import SimCamera
    from sim.cell import build_cell_world
    from sim.oracle_perception import OraclePerception

    world = build_cell_world(scene, seed)
    camera = SimCamera(world)
    try:
        frame = camera.capture()
    finally:
        camera.close()
    oracle = OraclePerception(world, world.config.T_world_base, frame.T_base_camera)
    roi = region_of_interest(bin_.inner_corners_camera(frame.T_base_camera), frame.intrinsics)
    return frame.rgb, roi, [(d.obj_id, d.bbox_xyxy) for d in oracle.run(frame).detections]


def _centre_in(detection: Any, obj_id: int, box: np.ndarray) -> bool:
    cx, cy = (detection.bbox_xyxy[:2] + detection.bbox_xyxy[2:]) / 2.0
    return detection.obj_id == obj_id and box[0] <= cx <= box[2] and box[1] <= cy <= box[3]


def is_right(detection: Any, truth: list[tuple[int, np.ndarray]]) -> bool:
    return any(_centre_in(detection, obj_id, box) for obj_id, box in truth)


def best_scores(truth: list[tuple[int, np.ndarray]], detections: list[Any]) -> list[float]:
    """Per visible part, the highest score of a detection that finds it (0: none)."""
    return [max((d.score for d in detections if _centre_in(d, obj_id, box)), default=0.0) for obj_id, box in truth]


def size_row(size: int, times: list[float], found: np.ndarray, kept: list[tuple[float, bool]], conf: float) -> dict:
    scores = np.array([s for s, _ in kept])
    right = np.array([r for _, r in kept], dtype=bool)

    def recall(th: float) -> float:
        return float((found >= th).mean()) if len(found) else float("nan")

    def precision(th: float) -> float:
        above = scores >= th
        return float(right[above].mean()) if above.any() else float("nan")

    return {
        "size": size,
        "ms_median": 1e3 * median(times),
        "recall": recall(conf),
        "precision": precision(conf),
        "by_threshold": [{"conf": th, "recall": recall(th), "precision": precision(th)} for th in THRESHOLDS],
    }


def chart(results: dict):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_time, ax_pr) = plt.subplots(1, 2, figsize=(11, 4.2))
    rows, conf = results["sizes"], results["config"]["conf_threshold"]
    lines = list(dict.fromkeys((r.get("models", ""), r.get("region", "frame")) for r in rows))
    for folder, region in lines:
        mine = [r for r in rows if (r.get("models", ""), r.get("region", "frame")) == (folder, region)]
        ax_time.plot([r["ms_median"] for r in mine], [r["recall"] for r in mine], "o-" if region == "frame" else "s--",
                     label=f"{folder}, {region}".strip(", "))  # fmt: skip
    for r in rows:
        ax_time.annotate(f"{r['size']} px", (r["ms_median"], r["recall"]), textcoords="offset points", xytext=(5, -10))
    # precision against recall where the runtime detects: the bin's box (the whole frame for older results)
    shown = [r for r in rows if r.get("region", "bin") == "bin"]
    for r in shown:
        ax_pr.plot([b["recall"] for b in r["by_threshold"]], [b["precision"] for b in r["by_threshold"]], "o-",
                   label=" @ ".join(x for x in (r.get("models", ""), f"{r['size']} px") if x))  # fmt: skip
    ax_time.legend(fontsize=8)
    ax_time.set(xlabel="detector ms per frame (median)", ylabel=f"parts found at confidence {conf}",
                title="Cell camera: recall against time")  # fmt: skip
    where = ", bin box" if any("region" in r for r in shown) else ""
    ax_pr.set(xlabel="recall", ylabel="precision", title=f"Thresholds {THRESHOLDS[0]}-{THRESHOLDS[-1]}{where}")
    ax_pr.legend(fontsize=7)
    for ax in (ax_time, ax_pr):
        ax.grid(alpha=0.3)
    n = results["config"]["parts_seen"]
    fig.suptitle(f"sygrid bench cell-detector: {results['config']['seeds']} bins, {n} visible parts")
    fig.tight_layout()
    return fig
