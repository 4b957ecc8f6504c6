"""Where a part's masks go wrong between its labels and the detector's output: the IoU of each stage's mask against
the ground-truth visible mask (BOP ``mask_visib``) of every instance of a generated dataset, and the COCO mask AP of
a perfect prediction (a network that reproduces its training targets exactly, decoded by the runtime).

    python scripts/trace_masks.py DATA [--split test] [--imgsz 640] [--proto-stride 4] [--per-instance]

Stages: ``coco_rle`` (the COCO labels' RLE), ``yolo_polygon`` (the YOLO label's polygon, filled), ``train_ids`` (the
instance-id map training reads, from the COCO labels), ``decoded`` (the training targets at the prototypes' stride
as prototypes, one per instance, decoded by ``sygrid.detection_decode.postprocess``: upsampled, cropped to the box,
threshold 0.5). DATA: a ``sygrid generate`` folder with the bop, coco and yolo formats.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
from pycocotools import mask as mask_utils

from perception.evaluation import bop_items
from sygrid.annotations import polygon_to_mask
from sygrid.detection_decode import postprocess
from sygrid.letterbox import letterbox, letterbox_geometry
from sygrid.metrics import detection_metrics
from sygrid.train.detector.augment import targets_from_ids
from sygrid.train.detector.data import load_instances, open_dataset
from sygrid.writers import load_bop_item
from sygrid.writers.yolo import parse_label_line

STAGES = ("coco_rle", "yolo_polygon", "train_ids", "decoded")


class _Detection:  # sygrid.metrics.DetectionLike
    def __init__(self, obj_id: int, score: float, box: np.ndarray, mask: np.ndarray) -> None:
        self.obj_id, self.score, self.bbox_xyxy, self.mask = obj_id, score, box, mask


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.count_nonzero(a | b)
    return np.count_nonzero(a & b) / union if union else float("nan")


def _best(masks: list[np.ndarray], truth: np.ndarray) -> float:
    return max((_iou(m, truth) for m in masks), default=0.0)


def perfect_prediction(ids: np.ndarray, classes: np.ndarray, num_classes: int, imgsz: int, stride: int) -> tuple:
    """The runtime's decode of a network whose output is exactly the training targets of the id map ``ids``."""
    geometry = letterbox_geometry(ids.shape, (imgsz, imgsz), 32)
    cls, boxes, masks = targets_from_ids(letterbox(ids, geometry, cv2.INTER_NEAREST), classes, mask_stride=stride)
    m = len(cls)
    p = np.clip(masks, 1e-4, 1 - 1e-4)
    prototypes = np.log(p / (1 - p)).astype(np.float32) if m else np.zeros((0, 1, 1), np.float32)
    out = np.zeros((4 + num_classes + m, max(m, 1)), np.float32)
    for j, (x0, y0, x1, y1) in enumerate(boxes):
        out[0:4, j] = [(x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0]
        out[4 + int(cls[j]), j] = 0.99 - 1e-4 * j
        out[4 + num_classes + j, j] = 1.0
    return postprocess(out[None], prototypes, geometry, num_classes, 0.5, 0.99, 1000)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("--split", default="test", help="the BOP split (and its YOLO/COCO split name)")
    parser.add_argument("--imgsz", type=int, default=640, help="the detector's input side")
    parser.add_argument("--proto-stride", type=int, default=4, help="the prototypes' stride")
    parser.add_argument("--per-instance", action="store_true", help="one line per instance, by visible pixels")
    args = parser.parse_args()
    bop_split = {"train": "train_pbr", "val": "val_pbr"}.get(args.split, args.split)
    root = args.data / "bop"
    anns = [load_bop_item(root, s, i, bop_split)[0] for s, i in bop_items(root, bop_split)]
    coco = json.loads((args.data / "coco" / "annotations" / f"instances_{args.split}.json").read_text())
    dataset = open_dataset(args.data, labels="coco", splits=(args.split,))
    iou: dict[str, list[float]] = {s: [] for s in STAGES}
    pixels, predictions = [], []
    for n, ann in enumerate(anns):
        h, w = ann.intrinsics.height, ann.intrinsics.width
        image_id = coco["images"][n]["id"]
        rles = [mask_utils.decode({**a["segmentation"], "counts": a["segmentation"]["counts"].encode()}).astype(bool)
                for a in coco["annotations"] if a["image_id"] == image_id]  # fmt: skip
        lines = (args.data / "yolo" / "labels" / args.split / f"{ann.name}.txt").read_text().splitlines()
        polygons = [polygon_to_mask(parse_label_line(line, w, h)[1], h, w) for line in lines]
        _, ids, classes = load_instances(dataset, args.split, n)
        decoded = perfect_prediction(ids, classes, dataset.num_classes, args.imgsz, args.proto_stride)
        masks = decoded.masks or []
        predictions.append([_Detection(dataset.obj_ids[int(c)], float(s), b, m) for c, s, b, m in zip(
            decoded.class_index, decoded.scores, decoded.boxes_xyxy, masks, strict=True)])  # fmt: skip
        for inst in ann.instances:
            if inst.px_count_visib == 0:
                continue
            truth = inst.mask_visib
            pixels.append(inst.px_count_visib)
            iou["coco_rle"].append(_best(rles, truth))
            iou["yolo_polygon"].append(_best(polygons, truth))
            iou["train_ids"].append(_best([ids == k + 1 for k in range(len(classes))], truth))
            iou["decoded"].append(_best(masks, truth))
    print(f"{args.data}: {len(anns)} images, {len(pixels)} visible instances (median {np.median(pixels):.0f} px), "
          f"proto stride {args.proto_stride}")  # fmt: skip
    for stage, values in iou.items():
        v = np.asarray(values)
        print(
            f"  {stage:<13} IoU mean {np.nanmean(v):.3f} median {np.nanmedian(v):.3f}, >= 0.5: {np.mean(v >= 0.5):.2f}"
        )
    metrics = detection_metrics(anns, predictions, min_visib_fract=0.1).as_dict()
    print(f"  perfect prediction: box AP50 {metrics['box_map50']:.3f}, mask AP50 {metrics['mask_map50']:.3f}, "
          f"mask AP50-95 {metrics['mask_map50_95']:.3f}")  # fmt: skip
    if args.per_instance:
        for row in sorted(zip(pixels, *iou.values(), strict=True)):
            print(f"  {row[0]:>6} px  " + "  ".join(f"{s} {v:.2f}" for s, v in zip(STAGES, row[1:], strict=True)))


if __name__ == "__main__":
    main()
