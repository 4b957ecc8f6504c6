"""COCO instance-segmentation writer: ``annotations/instances_<split>.json`` with RLE masks, images as PNG.

Layout under ``root``::

    images/<split>/SSSSSS_IIIIII.png
    annotations/instances_<split>.json     images, categories (id = obj_id), annotations (visible-mask RLE)
    annotations/items_<split>/SSSSSS_IIIIII.json   one record per image: what the JSON is assembled from

Each ``write`` stores its image and a per-image record atomically, so an item is either complete or absent and the
cost of an item does not grow with the dataset; ``finish()`` (and ``flush()``) assembles the COCO JSON from all
records. Ids are stable: the image id comes from ``(scene_id, image_id)``, annotation ids are numbered in image
order at assembly, so the file does not depend on the order items arrive in (parallel or resumed runs), and
writing an image again replaces it.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from pycocotools import mask as mask_utils

from sygrid.annotations import ImageAnnotation, check_item, image_name
from sygrid.errors import ConfigError
from sygrid.fileio import write_bytes_atomic, write_json_atomic
from sygrid.objects.model import ObjectModel
from sygrid.writers.bop import encode_png

log = logging.getLogger(__name__)


def mask_to_rle(mask: np.ndarray) -> dict:
    """(h, w) bool -> COCO RLE ``{"size": [h, w], "counts": str}`` (JSON-ready, new dict)."""
    rle = mask_utils.encode(np.asfortranarray(np.asarray(mask, dtype=np.uint8)))
    return {"size": [int(v) for v in rle["size"]], "counts": rle["counts"].decode("ascii")}


def rle_to_mask(rle: dict) -> np.ndarray:
    """Inverse of ``mask_to_rle``: (h, w) bool."""
    return mask_utils.decode({"size": rle["size"], "counts": rle["counts"].encode("ascii")}).astype(bool)


def coco_image_id(scene_id: int, image_id: int) -> int:
    """The COCO image id of BOP image ``scene_id/image_id`` (>= 1, unique for up to a million images a scene)."""
    return scene_id * 1_000_000 + image_id + 1


class CocoWriter:
    """Writes items into a COCO dataset at ``root`` for one ``split``."""

    def __init__(self, root: str | Path, models: Sequence[ObjectModel], split: str = "train") -> None:
        if not split or "/" in split:
            raise ValueError(f"split: expected a folder name such as 'train', got {split!r}")
        self.root = Path(root)
        self.split = split
        self.json_path = self.root / "annotations" / f"instances_{split}.json"
        self.items_dir = self.root / "annotations" / f"items_{split}"
        self.categories = [{"id": int(m.obj_id), "name": m.name} for m in sorted(models, key=lambda m: m.obj_id)]
        if not self.categories:
            raise ValueError("models: expected at least one ObjectModel to name the COCO categories")
        self.files_written = 0  # a count, not a list: a million-item run must not grow memory

    def write(self, ann: ImageAnnotation, rgb: np.ndarray, depth_m: np.ndarray | None = None) -> list[Path]:
        """Writes the image file and its annotation record (``depth_m`` is not part of the format)."""
        check_item(ann, rgb, depth_m)
        known = {c["id"] for c in self.categories}
        for inst in ann.instances:
            if inst.obj_id not in known:
                raise ValueError(f"obj_id {inst.obj_id} not among the writer's models {sorted(known)}")
        file_name = f"{ann.name}.png"
        image_id = coco_image_id(ann.scene_id, ann.image_id)
        annotations = []
        for inst in ann.instances:
            if inst.px_count_visib == 0:
                continue
            rle = mask_to_rle(inst.mask_visib)
            x, y, w, h = inst.bbox_visib
            annotations.append(
                {
                    "image_id": image_id,
                    "category_id": int(inst.obj_id),
                    "segmentation": rle,
                    "area": float(mask_utils.area({**rle, "counts": rle["counts"].encode("ascii")})),
                    "bbox": [float(x), float(y), float(w), float(h)],
                    "iscrowd": 0,
                }
            )
        image = {"id": image_id, "file_name": file_name, "width": ann.intrinsics.width, "height": ann.intrinsics.height}
        paths = [
            write_bytes_atomic(
                self.root / "images" / self.split / file_name, encode_png(np.asarray(rgb)[..., ::-1], "rgb")
            ),
            write_json_atomic(self.items_dir / f"{ann.name}.json", {"image": image, "annotations": annotations}, None),
        ]
        self.files_written += len(paths)
        return paths

    def item_files(self, scene_id: int, image_id: int) -> list[Path]:
        """The files ``write`` makes for image ``scene_id/image_id``: the image and its annotation record."""
        name = image_name(scene_id, image_id)
        return [self.root / "images" / self.split / f"{name}.png", self.items_dir / f"{name}.json"]

    def _records(self) -> list[dict]:
        records = []
        for path in sorted(self.items_dir.glob("*.json")):
            try:
                record = json.loads(path.read_text())
                _ = (record["image"]["id"], record["annotations"])  # shape check
            except (json.JSONDecodeError, KeyError, TypeError) as err:
                raise ConfigError(
                    f"{path}: expected a COCO image record with 'image' and 'annotations': {err}"
                ) from err
            records.append(record)
        return sorted(records, key=lambda r: r["image"]["id"])

    def flush(self) -> Path:
        """Assembles the annotation JSON from every image record so far and writes it atomically."""
        images, annotations = [], []
        for record in self._records():
            images.append(record["image"])
            for a in record["annotations"]:
                annotations.append({"id": len(annotations) + 1, **a})
        data = {"images": images, "annotations": annotations, "categories": self.categories}
        return write_json_atomic(self.json_path, data, indent=None)

    def finish(self) -> list[Path]:
        """Writes the annotation JSON; returns it."""
        path = self.flush()
        log.info("COCO dataset written to %s (%d image and record files this run)", path, self.files_written)
        return [path]
