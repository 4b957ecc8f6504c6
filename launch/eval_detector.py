"""``sygrid eval``'s detector options and reports: where the detector looks (``--region``, ``--scale``,
``--tile-px``), the pixels-per-part warning for the dataset's camera, and the breakdown of the detector alone at
0.001 and at the operating threshold (AP and recall per part, size and visibility: ``perception.detector_eval``).
"""

from __future__ import annotations

import argparse

from perception.detector import YoloSegDetector
from perception.detector_eval import COCO_CONF, REGIONS, format_breakdown
from perception.evaluation import EvalSettings, evaluate_detector
from perception.pipeline import PerceptionPipeline
from sygrid.errors import ConfigError


def add_detector_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--region",
        choices=REGIONS,
        default=None,
        help="where the detector looks: the bin's box (from the dataset's bin pose; what a cell does with "
        "detect_in_bin) or the whole frame (default: bin for a dataset made by 'sygrid generate', else full)",
    )
    parser.add_argument(
        "--scale",
        type=float,
        default=None,
        help="detector scale, network px per image px (default: the manifest's, else the whole frame "
        "fitted to the input size)",
    )
    parser.add_argument(
        "--tile-px",
        type=int,
        default=None,
        help="overlapping tiles of this many network px over the region (0: none; default: manifest)",
    )
    parser.add_argument(
        "--no-breakdown", action="store_true", help="skip the detector-alone pass at 0.001 (AP, recall per size)"
    )


def detector_overrides(args: argparse.Namespace) -> dict:
    """The ``PipelineOverrides`` fields the detector options set."""
    return {"detector_scale": args.scale, "detector_tile_px": args.tile_px}


def warn_part_pixels(args: argparse.Namespace) -> None:
    """Prints a warning per part that the dataset's camera shows below the detector's ``min_part_px``."""
    from launch.part_check import log_warnings, scene_warnings
    from sygrid.dataset import ledger_recipe

    try:
        recipe, _ = ledger_recipe(args.data)
    except ConfigError:
        return  # not a generated dataset: no camera description to check
    log_warnings(scene_warnings(recipe.scene, recipe.base_dir, args.models), "pixels per part")


def detector_breakdown(args: argparse.Namespace, pipeline: PerceptionPipeline, settings: EvalSettings) -> dict | None:
    """The pipeline's detector again at 0.001 (same model, view and region): mAP and the breakdown at 0.001 and at
    the pipeline's threshold; printed, and returned for the JSON report. None with ``--no-breakdown``."""
    if args.no_breakdown:
        return None
    d = pipeline.detector
    low = YoloSegDetector(d.path, class_obj_ids=d.class_obj_ids, conf_threshold=COCO_CONF,
                          iou_threshold=d.iou_threshold, input_size=d.input_hw if d.dynamic_input else None,
                          num_threads=args.threads, view=d.view)  # fmt: skip
    report = evaluate_detector(low, args.data, settings, operating_threshold=d.conf_threshold)
    print(f"detector alone ({report['region']}, scale {report['scale']:.2f}): box mAP50 {report['box_map50']:.3f}, "
          f"mask mAP50-95 {report['mask_map50_95']:.3f} at {COCO_CONF}")  # fmt: skip
    print(format_breakdown(report["breakdown"]))
    return report
