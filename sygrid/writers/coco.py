"""COCO instance-segmentation writer: ``annotations/instances_<split>.json`` with RLE masks, images as PNG.

Layout under ``root``::

    images/<split>/SSSSSS_IIIIII.png
    annotations/instances_<split>.json     images, categories (id = obj_id), annotations (visible-mask RLE)

Images are written as they come; the JSON is kept in memory and written atomically by ``finish()`` (and
``flush()``). An existing JSON is loaded on construction and extended, so an interrupted run resumes without
duplicate ids.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from pycocotools import mask as mask_utils

from sygrid.annotations import ImageAnnotation, check_item
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


class CocoWriter:
    """Writes items into a COCO dataset at ``root`` for one ``split``."""

    def __init__(self, root: str | Path, models: Sequence[ObjectModel], split: str = "train") -> None:
        if not split or "/" in split:
            raise ValueError(f"split: expected a folder name such as 'train', got {split!r}")
        self.root = Path(root)
        self.split = split
        self.json_path = self.root / "annotations" / f"instances_{split}.json"
        self.categories = [{"id": int(m.obj_id), "name": m.name} for m in sorted(models, key=lambda m: m.obj_id)]
        if not self.categories:
            raise ValueError("models: expected at least one ObjectModel to name the COCO categories")
        self.images: list[dict] = []
        self.annotations: list[dict] = []
        if self.json_path.exists():
            self._resume()
        self.written: list[Path] = []

    def _resume(self) -> None:
        try:
            data = json.loads(self.json_path.read_text())
            self.images, self.annotations = list(data["images"]), list(data["annotations"])
        except (json.JSONDecodeError, KeyError, TypeError) as err:
            raise ConfigError(f"{self.json_path}: expected a COCO JSON with 'images' and 'annotations': {err}") from err
        log.info("COCO: resuming %s with %d images", self.json_path, len(self.images))

    def write(self, ann: ImageAnnotation, rgb: np.ndarray, depth_m: np.ndarray | None = None) -> list[Path]:
        """Writes the image file and records its annotations (``depth_m`` is not part of the format)."""
        check_item(ann, rgb, depth_m)
        known = {c["id"] for c in self.categories}
        for inst in ann.instances:
            if inst.obj_id not in known:
                raise ValueError(f"obj_id {inst.obj_id} not among the writer's models {sorted(known)}")
        file_name = f"{ann.name}.png"
        if any(im["file_name"] == file_name for im in self.images):
            raise ValueError(f"image {file_name}: already in {self.json_path}; scene_id/image_id must be unique")
        path = write_bytes_atomic(
            self.root / "images" / self.split / file_name, encode_png(np.asarray(rgb)[..., ::-1], "rgb")
        )
        image_id = 1 + max((im["id"] for im in self.images), default=0)
        self.images.append(
            {"id": image_id, "file_name": file_name, "width": ann.intrinsics.width, "height": ann.intrinsics.height}
        )
        next_id = 1 + max((a["id"] for a in self.annotations), default=0)
        for inst in ann.instances:
            if inst.px_count_visib == 0:
                continue
            rle = mask_to_rle(inst.mask_visib)
            x, y, w, h = inst.bbox_visib
            self.annotations.append(
                {
                    "id": next_id,
                    "image_id": image_id,
                    "category_id": int(inst.obj_id),
                    "segmentation": rle,
                    "area": float(mask_utils.area({**rle, "counts": rle["counts"].encode("ascii")})),
                    "bbox": [float(x), float(y), float(w), float(h)],
                    "iscrowd": 0,
                }
            )
            next_id += 1
        self.written.append(path)
        return [path]

    def flush(self) -> Path:
        """Writes the annotation JSON atomically with everything recorded so far."""
        data = {"images": self.images, "annotations": self.annotations, "categories": self.categories}
        return write_json_atomic(self.json_path, data, indent=None)

    def finish(self) -> list[Path]:
        """Writes the annotation JSON; returns everything written."""
        self.written.append(self.flush())
        log.info("COCO dataset: %d images, %d annotations in %s", len(self.images), len(self.annotations), self.root)
        return list(self.written)
