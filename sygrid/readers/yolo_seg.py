"""Reader for YOLO segmentation label folders (real photos labelled in an annotation tool, or a YOLO export),
converted to ``ImageAnnotation``s.

Layouts read::

    DIR/data.yaml + the folders it names     train / val / test: image folders, names: the classes by index
    DIR/images/{train,val,test}/ + DIR/labels/{train,val,test}/    without data.yaml: class names given
    DIR/images/ + DIR/labels/                                      one split, its name given

An image ``.../images/<split>/x.png`` has its labels in ``.../labels/<split>/x.txt``: one line per instance,
``class x1 y1 x2 y2 ...`` with coordinates normalised by the image size; no label file means no instances. A
split whose folder is an earlier split's (the ``val: images/train`` a dataset without a val split carries) is read
once, under the earlier name.

YOLO labels hold no camera and no pose: the annotations' intrinsics ``fx, fy, cx, cy`` and every ``T_camera_obj``
are NaN (only the image size is known), there is no amodal mask (``mask_full`` None, ``bbox_obj`` the visible box)
and the visible fraction is taken as 1.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sygrid.annotations import ImageAnnotation, InstanceAnnotation, mask_bbox, polygon_to_mask
from sygrid.camera import CameraIntrinsics
from sygrid.errors import ConfigError
from sygrid.train.detector.data import IMAGE_SUFFIXES, label_path, parse_data_yaml, read_rgb
from sygrid.writers.yolo import parse_label_line

log = logging.getLogger(__name__)

SPLITS = ("train", "val", "test")
_COORD_SLACK = 0.01  # normalised coordinates a little outside [0, 1] (rounding in annotation tools) are clipped


@dataclass(frozen=True)
class YoloSegSource:
    """A YOLO-seg folder: ``names`` (class names by index), ``splits`` (split -> sorted image paths), ``where``
    (the data.yaml or folder, for messages)."""

    names: list[str]
    splits: dict[str, list[Path]]
    where: Path


def open_yolo_seg(path: str | Path, names: Sequence[str] | None = None, split: str = "test") -> YoloSegSource:
    """Finds the splits and class names of the YOLO-seg folder (or ``data.yaml``) at ``path``.

    ``names``: the class names by index where there is no data.yaml (overrides its names where there is one).
    ``split``: the split name of a flat ``images/`` folder.

    Raises:
        ConfigError: no such folder, no images, a split folder missing, or no class names; names the path.
        DetectorDataError: a malformed data.yaml (names the file and line).
    """
    path = Path(path)
    yaml_path = path if path.is_file() else path / "data.yaml"
    if yaml_path.is_file():
        spec = parse_data_yaml(yaml_path.read_text(), yaml_path)
        root = yaml_path.parent / spec["path"] if spec.get("path") else yaml_path.parent
        folders = {s: root / spec[s] for s in SPLITS if s in spec}
        if not folders:
            raise ConfigError(f"{yaml_path}: no train, val or test entry (the image folders)")
        for s, folder in folders.items():
            if not folder.is_dir():
                raise ConfigError(f"{yaml_path}: {s}: {folder} is not a folder (image lists are not supported)")
        class_names = list(names) if names else spec.get("names")
        where = yaml_path
    elif (path / "images").is_dir():
        nested = {s: path / "images" / s for s in SPLITS if (path / "images" / s).is_dir()}
        folders = nested or {split: path / "images"}
        class_names, where = list(names) if names else None, path
    else:
        raise ConfigError(f"{path}: not a YOLO-seg folder (expected data.yaml or an images/ folder)")
    if not class_names:
        raise ConfigError(f"{where}: no class names (no data.yaml with 'names'); pass them (--names a,b,c)")
    splits: dict[str, list[Path]] = {}
    seen: dict[Path, str] = {}
    for s, folder in folders.items():
        resolved = folder.resolve()
        if resolved in seen:
            log.info("%s: split %s is split %s's folder %s: read once", where, s, seen[resolved], folder)
            continue
        seen[resolved] = s
        images = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not images:
            raise ConfigError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)})")
        splits[s] = images
    return YoloSegSource([str(n) for n in class_names], splits, where)


def read_yolo_item(
    image_path: Path, class_obj_ids: Sequence[int], image_id: int, scene_id: int = 0
) -> tuple[ImageAnnotation, np.ndarray]:
    """One image and its labels: ``(annotation, rgb)``; class ``k`` of a label line becomes ``class_obj_ids[k]``.

    Raises:
        DetectorDataError: an unreadable image (names the file).
        ConfigError: a label line that is not a polygon of a known class inside the image;
            names the label file and line.
    """
    rgb = read_rgb(image_path)
    h, w = rgb.shape[:2]
    instances = []
    labels = label_path(image_path)
    lines = labels.read_text().splitlines() if labels.is_file() else []
    for lineno, line in enumerate(lines, 1):
        if not line.strip():
            continue
        where = f"{labels}:{lineno}"
        try:
            cls, xy = parse_label_line(line, w, h)
        except ValueError as err:
            raise ConfigError(f"{where}: {err} (segmentation polygons expected, not boxes)") from err
        if not 0 <= cls < len(class_obj_ids):
            raise ConfigError(f"{where}: class {cls} outside 0..{len(class_obj_ids) - 1} (the names' indices)")
        norm = xy / np.array([w, h])
        if not np.all(np.isfinite(norm)) or norm.min() < -_COORD_SLACK or norm.max() > 1 + _COORD_SLACK:
            raise ConfigError(f"{where}: polygon coordinates must be normalised to [0, 1]")
        mask = polygon_to_mask(np.clip(xy, 0, [w - 1, h - 1]), h, w)
        px = int(np.count_nonzero(mask))
        box = mask_bbox(mask)
        instances.append(
            InstanceAnnotation(
                obj_id=int(class_obj_ids[cls]),
                inst_id=len(instances),
                T_camera_obj=np.full((4, 4), np.nan),
                mask_visib=mask,
                mask_full=None,
                bbox_visib=box,
                bbox_obj=box,
                px_count_all=px,
                px_count_visib=px,
                visib_fract=1.0,
                px_count_valid=px,
            )
        )
    intrinsics = CameraIntrinsics(math.nan, math.nan, math.nan, math.nan, w, h)
    return ImageAnnotation(image_id, intrinsics, tuple(instances), scene_id=scene_id), rgb
