"""The detector alone on a generated dataset: where it looks (the whole frame or the bin's box), its COCO mAP, and
where it fails (``sygrid.detection_breakdown``: AP and recall per part, size and visibility, at the operating
threshold and at 0.001), with the pixels-per-part threshold read off the measured recall curve.

Regions: ``"full"`` (the whole frame) or ``"bin"`` (the image box of the bin's inner volume, from the dataset's bin
pose, ``sygrid.dataset.DatasetBin``); how the detector sees the region (scale, tiles) is its own ``view``
(``perception.tiling.ViewSettings``). The same ``bin_region_camera`` points feed the pipeline's region in
``sygrid eval``, as the cell's calibrated bin does in ``sygrid pick``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from tqdm import tqdm

from perception.detector import YoloSegDetector
from perception.pipeline import region_of_interest
from perception.results import Detection
from sygrid.annotations import ImageAnnotation
from sygrid.dataset import LEDGER_NAME, DatasetBin
from sygrid.detection_breakdown import SIZE_BINS, VISIB_BINS, breakdown
from sygrid.metrics import detection_metrics
from sygrid.scene import bin_inner_corners
from sygrid.transforms import transform_points
from sygrid.writers import load_bop_item

Region = Literal["full", "bin"]
REGIONS = ("full", "bin")
COCO_CONF = 0.001  # the detection benchmarks' convention for mAP


@dataclass(frozen=True, eq=False)
class StoredDetection:
    """A detection kept for evaluation with its mask cropped to its box: ``mask`` expands it to the frame on each
    access (the full-frame masks of every detection of a few hundred images at confidence 0.001 are gigabytes).
    ``crop`` (h, w) bool at ``crop_xy`` (x0, y0) of a frame of ``frame_hw``; None for a detection-only model."""

    class_index: int
    obj_id: int
    score: float
    bbox_xyxy: np.ndarray
    frame_hw: tuple[int, int]
    crop_xy: tuple[int, int] = (0, 0)
    crop: np.ndarray | None = None

    @classmethod
    def of(cls, det: Detection) -> StoredDetection:
        if det.mask is None:
            return cls(det.class_index, det.obj_id, det.score, det.bbox_xyxy, (0, 0))
        h, w = det.mask.shape
        x0, y0, x1, y1 = det.bbox_xyxy
        x0, y0 = min(max(int(x0), 0), w), min(max(int(y0), 0), h)
        x1, y1 = max(min(math.ceil(x1), w), x0), max(min(math.ceil(y1), h), y0)
        crop = det.mask[y0:y1, x0:x1].copy()
        if np.count_nonzero(crop) != np.count_nonzero(det.mask):  # a mask reaching out of its box: keep it whole
            return cls(det.class_index, det.obj_id, det.score, det.bbox_xyxy, (h, w), (0, 0), det.mask)
        return cls(det.class_index, det.obj_id, det.score, det.bbox_xyxy, (h, w), (x0, y0), crop)

    @property
    def mask(self) -> np.ndarray | None:
        if self.crop is None:
            return None
        full = np.zeros(self.frame_hw, dtype=bool)
        x0, y0 = self.crop_xy
        full[y0 : y0 + self.crop.shape[0], x0 : x0 + self.crop.shape[1]] = self.crop
        return full


def bin_region_camera(dataset_bin: DatasetBin, ann: ImageAnnotation) -> np.ndarray:
    """(8, 3) the corners of the bin's inner volume in the camera frame of ``ann``'s image, metres."""
    return transform_points(dataset_bin.T_camera_bin(ann), bin_inner_corners(dataset_bin.inner_size_m))


def dataset_region(data_dir: Path, region: Region | None = None) -> Region:
    """``region`` where given (a ``--region`` option), else where a cell's detector looks in this dataset's images:
    ``"bin"`` where the dataset knows its bin (a ledger of ``sygrid generate``), as the cell's pipeline is given the
    bin's box, else ``"full"`` (a converted dataset)."""
    if region is not None:
        return region
    return "bin" if (Path(data_dir) / LEDGER_NAME).is_file() else "full"


def region_box(region: Region, dataset_bin: DatasetBin | None, ann: ImageAnnotation) -> tuple[int, ...] | None:
    """The ``roi_xyxy`` to give the detector for ``ann``'s image: None for the whole frame."""
    if region == "full":
        return None
    if dataset_bin is None:
        raise ValueError("region 'bin' needs the dataset's bin (sygrid.dataset.DatasetBin)")
    return region_of_interest(bin_region_camera(dataset_bin, ann), ann.intrinsics)


def run_detector(
    detector: YoloSegDetector,
    root: Path,
    split: str,
    items: Sequence[tuple[int, int]],
    region: Region = "full",
    dataset_bin: DatasetBin | None = None,
    progress: bool = True,
) -> tuple[list[ImageAnnotation], list[list], list[float]]:
    """``detector`` on each (scene_id, image_id) of a BOP split: annotations (without the amodal masks),
    detections (``StoredDetection``), milliseconds per frame."""
    images, detections, ms = [], [], []
    for scene_id, image_id in tqdm(items, unit="image", disable=not progress):
        ann, rgb, _ = load_bop_item(root, scene_id, image_id, split=split)
        roi = region_box(region, dataset_bin, ann)
        t = time.perf_counter()
        found = detector.detect(rgb, roi)
        ms.append(1e3 * (time.perf_counter() - t))
        detections.append([StoredDetection.of(d) for d in found])
        instances = tuple(dataclasses.replace(i, mask_full=None) for i in ann.instances)
        images.append(dataclasses.replace(ann, instances=instances))
    return images, detections, ms


def detector_report(
    detector: YoloSegDetector,
    images: Sequence[ImageAnnotation],
    detections: Sequence[Sequence],
    operating_threshold: float,
    min_visib_fract: float,
    match_iou: float,
) -> dict:
    """COCO mAP of ``detections`` (made at ``detector.conf_threshold``) and, where the detector kept low scores,
    also at ``operating_threshold``; the breakdown at both; names and diameters from the built-in parts."""
    low = detector.conf_threshold
    thresholds = sorted({low, max(low, operating_threshold)})
    names = dict(zip(detector.class_obj_ids, detector.class_names, strict=True))
    diameters = _diameters(detector.class_names, detector.class_obj_ids)
    hw = (images[0].intrinsics.height, images[0].intrinsics.width) if images else (0, 0)
    report = {
        **detection_metrics(images, detections, min_visib_fract=min_visib_fract).as_dict(),
        "scale": detector.frame_scale(hw) if images else math.nan,
        "view": {
            "scale": detector.view.scale,
            "tile_px": detector.view.tile_px,
            "tile_overlap": detector.view.tile_overlap,
        },
    }
    if thresholds[-1] > low:
        kept = [[d for d in dets if d.score >= thresholds[-1]] for dets in detections]
        at = detection_metrics(images, kept, min_visib_fract=min_visib_fract).as_dict()
        report["at_operating_threshold"] = {"conf_threshold": thresholds[-1], **at}
    report["breakdown"] = breakdown(
        images, detections, thresholds, min_visib_fract, match_iou, names, diameters, report["scale"]
    )
    return report


def _diameters(names: Sequence[str], obj_ids: Sequence[int]) -> dict[int, float] | None:
    """obj_id -> diameter of the built-in part of each class name; None when a class is not a built-in part."""
    from sygrid.objects.parts import BUILTIN_PARTS, builtin_part  # builds meshes: only when asked

    if not all(n in BUILTIN_PARTS for n in names):
        return None
    return {int(i): float(builtin_part(n).diameter_m) for n, i in zip(names, obj_ids, strict=True)}


def format_breakdown(b: dict) -> str:
    """The breakdown as plain-text tables: recall per part and bin at each threshold, then AP per bin."""
    thresholds = [f"{t:g}" for t in b["thresholds"]]
    labels = ["all"] + [label for label, _, _ in SIZE_BINS] + [label for label, _, _ in VISIB_BINS]
    lines = ["recall (mask IoU >= 0.5) per part, visible-box size [px] and visibility; n instances in brackets"]
    for t in thresholds:
        lines.append(f"  at confidence {t}")
        lines.append(f"  {'part':<14}" + "".join(f"{label:>14}" for label in labels))
        for part, row in b["recall"].items():
            cells = "".join(f"{_pct(row[label][f'recall@{t}']):>8} ({row[label]['n']:>4})" for label in labels)
            lines.append(f"  {part:<14}{cells}")
    for t in thresholds:
        lines.append(f"box AP50 / mask AP50-95 per bin at confidence {t}")
        lines.append(f"  {'obj_id':<14}" + "".join(f"{label:>14}" for label in labels))
        for part, row in b["ap"][t].items():
            cells = "".join(
                f"{_num(row[label]['box_ap50']):>7}/{_num(row[label]['mask_ap50_95']):<6}" for label in labels
            )
            lines.append(f"  {part:<14}{cells}")
        px = b["min_reliable_px"][t]
        lines.append(
            f"  smallest nominal part size resolved reliably at {t}: "
            + (f"{px:g} network px" if math.isfinite(px) else "none")
        )
    return "\n".join(lines)


def _pct(x: float) -> str:
    return "n/a" if not math.isfinite(x) else f"{100 * x:.1f}%"


def _num(x: float) -> str:
    return "n/a" if not math.isfinite(x) else f"{x:.3f}"
