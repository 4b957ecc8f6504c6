"""YOLO segmentation dataset writer (the layout ultralytics trains on).

Layout under ``root``::

    images/<split>/SSSSSS_IIIIII.png
    labels/<split>/SSSSSS_IIIIII.txt     one line per visible instance: ``class x1 y1 x2 y2 ...``
    data.yaml                             train, val (test), names {index: name}

``class`` is the index of the instance's ``obj_id`` in the sorted list of the writer's model ids. Coordinates are
normalised by the image size (``x / width``, ``y / height``). A visible mask split by an occluder becomes one
polygon through zero-width bridges (``sygrid.annotations.merge_polygons``), as the SyGRID labels did, and so do its
holes (a washer's, a strap's loop), bridged in as outlines running the other way round
(``sygrid.annotations.mask_to_polygon``): the filled polygon leaves them out.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from sygrid.annotations import ImageAnnotation, check_item, image_name, mask_to_polygon
from sygrid.fileio import write_bytes_atomic
from sygrid.objects.model import ObjectModel
from sygrid.writers.bop import encode_png

log = logging.getLogger(__name__)

_MIN_POLYGON_POINTS = 3  # ultralytics drops segments with fewer points


def polygon_label_line(class_index: int, polygon: np.ndarray, width: int, height: int) -> str:
    """``class x1 y1 ...`` with (n, 2) pixel coordinates normalised to [0, 1]."""
    norm = np.clip(np.asarray(polygon, dtype=np.float64) / np.array([width, height]), 0.0, 1.0)
    return " ".join([str(int(class_index)), *(f"{v:.6f}" for v in norm.reshape(-1))])


def parse_label_line(line: str, width: int, height: int) -> tuple[int, np.ndarray]:
    """Inverse of ``polygon_label_line``: ``(class index, (n, 2) pixel polygon)``."""
    fields = line.split()
    if len(fields) < 1 + 2 * _MIN_POLYGON_POINTS or len(fields) % 2 == 0:
        raise ValueError(f"YOLO label line: expected 'class x1 y1 x2 y2 x3 y3 ...', got {line[:80]!r}")
    xy = np.asarray(fields[1:], dtype=np.float64).reshape(-1, 2) * np.array([width, height])
    return int(fields[0]), xy


def data_yaml(names: dict[int, str], splits: dict[str, str]) -> str:
    """The ``data.yaml`` text, written by hand (flat keys and one mapping; no YAML library needed). No ``path``
    key: ultralytics then takes the folder of the YAML file, so the dataset can be moved or copied."""
    lines = [f"{split}: {folder}" for split, folder in splits.items()] + ["names:"]
    lines += [f"  {i}: {_yaml_str(n)}" for i, n in sorted(names.items())]
    return "\n".join(lines) + "\n"


def _yaml_str(text: str) -> str:
    """A double-quoted YAML scalar (JSON string escaping is valid YAML)."""
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


class YoloWriter:
    """Writes items into a YOLO segmentation dataset at ``root``; ``split`` per item (``train`` or ``val``)."""

    def __init__(self, root: str | Path, models: Sequence[ObjectModel], split: str = "train") -> None:
        _check_split(split)
        self.root = Path(root)
        self.split = split
        self.obj_ids = sorted({m.obj_id for m in models})
        if not self.obj_ids:
            raise ValueError("models: expected at least one ObjectModel to name the YOLO classes")
        self.class_index = {obj_id: i for i, obj_id in enumerate(self.obj_ids)}
        self.names = {self.class_index[m.obj_id]: m.name for m in models}
        self._write_yaml()
        self.files_written = 0  # images and labels; a count, not a list: a million-item run must not grow memory

    def _write_yaml(self) -> Path:
        present = [s for s in ("val", "train", "test") if (self.root / "images" / s).is_dir()]
        # ultralytics needs both keys; val names the first split there is (a test set alone: its test split, so
        # that `yolo val` evaluates it), and train is never pointed at another split's images
        splits = {"train": "images/train", "val": f"images/{present[0] if present else 'train'}"}
        if "test" in present:
            splits["test"] = "images/test"
        text = data_yaml(self.names, splits)
        return write_bytes_atomic(self.root / "data.yaml", text.encode())

    def label_lines(self, ann: ImageAnnotation) -> list[str]:
        """One label line per instance with a visible polygon of at least three points."""
        w, h = ann.intrinsics.width, ann.intrinsics.height
        lines = []
        for inst in ann.instances:
            if inst.obj_id not in self.class_index:
                raise ValueError(f"obj_id {inst.obj_id} not among the writer's models {self.obj_ids}")
            polygon = mask_to_polygon(inst.mask_visib)
            if len(polygon) < _MIN_POLYGON_POINTS:
                log.debug("image %s instance %d: visible polygon too small, no label", ann.name, inst.inst_id)
                continue
            lines.append(polygon_label_line(self.class_index[inst.obj_id], polygon, w, h))
        return lines

    def write(
        self, ann: ImageAnnotation, rgb: np.ndarray, depth_m: np.ndarray | None = None, split: str | None = None
    ) -> list[Path]:
        """Writes one image and its label file (``depth_m`` is not part of the format); returns the paths."""
        check_item(ann, rgb, depth_m)
        split = self.split if split is None else split
        _check_split(split)
        lines = self.label_lines(ann)
        new_split = not (self.root / "images" / split).is_dir()
        image = write_bytes_atomic(
            self.root / "images" / split / f"{ann.name}.png", encode_png(np.asarray(rgb)[..., ::-1], "rgb")
        )
        label = write_bytes_atomic(
            self.root / "labels" / split / f"{ann.name}.txt", "".join(f"{ln}\n" for ln in lines).encode()
        )
        self.files_written += 2
        if new_split:  # data.yaml names the splits: keep it true even if the run never reaches finish()
            self._write_yaml()
        return [image, label]

    def item_files(self, scene_id: int, image_id: int, split: str | None = None) -> list[Path]:
        """The files ``write`` makes for image ``scene_id/image_id`` in ``split``: the image and its label file."""
        split, name = self.split if split is None else split, image_name(scene_id, image_id)
        return [self.root / "images" / split / f"{name}.png", self.root / "labels" / split / f"{name}.txt"]

    def finish(self) -> list[Path]:
        """Rewrites ``data.yaml`` (``val`` points at ``images/val`` once it exists, else at the train or the test
        split); returns it."""
        path = self._write_yaml()
        log.info("YOLO dataset: %d image and label files written under %s", self.files_written, self.root)
        return [path]


def _check_split(split: str) -> None:
    if split not in ("train", "val", "test"):
        raise ValueError(f"split: expected 'train', 'val' or 'test', got {split!r}")
