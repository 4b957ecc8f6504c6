"""Detector training data: the dataset's images and instance labels (numpy + OpenCV + pycocotools).

Reads the YOLO-seg layout that ``sygrid generate`` writes (``DIR/yolo/data.yaml``, ``images/{train,val}``,
``labels/{train,val}`` with normalised polygons). Where the dataset also has its COCO annotations
(``DIR/coco/annotations/instances_<split>.json``, RLE of the visible masks, as ``sygrid generate`` writes them) the
masks come from there by default: they are the exact pixels, where a polygon is a traced outline (holes are kept
through zero-width bridges, ``sygrid.annotations.mask_to_polygon``, but a one-pixel part becomes a point).

Each image's instances become one instance-id map (0 background, ``k + 1`` instance ``k``) at the image's
resolution, which ``sygrid.train.detector.augment`` warps together with the image.
"""

from __future__ import annotations

import ast
import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
from pycocotools import mask as mask_utils

from sygrid.annotations import polygon_to_mask
from sygrid.errors import ConfigError, SygridError
from sygrid.id_map import class_obj_ids

if TYPE_CHECKING:
    from sygrid.catalogue import Catalogue

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")
LABEL_SOURCES = ("auto", "coco", "yolo")


class DetectorDataError(SygridError, ValueError):
    """The dataset cannot be read: missing folder or file, unreadable image, malformed label. Names the file."""


# ------------------------------------------------------------------------------------------------ the dataset
def parse_data_yaml(text: str, path: Path) -> dict:
    """The keys of a YOLO ``data.yaml`` that training needs: ``train``, ``val``, ``names`` (and ``path``, ``nc``).

    Reads the flat form that ``sygrid.writers.yolo`` writes (``key: value`` lines and an indented ``names:`` block
    of ``index: name``) and the inline forms ultralytics also accepts (``names: [a, b]`` or ``{0: a}``). Hand-written
    because PyYAML is not a dependency of the project and the format used here is this small.
    """
    out: dict = {}
    block_key = None
    names: dict[int, str] = {}
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.split(" #")[0].rstrip() if not raw.lstrip().startswith("#") else ""
        if not line.strip():
            continue
        indented = line[0] in " \t"
        key, sep, value = line.strip().partition(":")
        if not sep:
            raise DetectorDataError(f"{path}:{lineno}: expected 'key: value', got {raw!r}")
        key, value = key.strip().strip("'\""), value.strip()
        if indented and block_key == "names":
            try:
                names[int(key)] = _yaml_scalar(value)
            except ValueError as err:
                raise DetectorDataError(f"{path}:{lineno}: names: expected 'index: name', got {raw!r}") from err
            continue
        block_key = None
        if key == "names" and not value:
            block_key = "names"
        elif key == "names":
            try:
                parsed = ast.literal_eval(value)
            except (ValueError, SyntaxError) as err:
                raise DetectorDataError(f"{path}:{lineno}: names: expected a list or a mapping, got {value!r}") from err
            names = dict(enumerate(parsed)) if isinstance(parsed, list) else {int(k): v for k, v in parsed.items()}
        else:
            out[key] = _yaml_scalar(value)
    if names:
        if sorted(names) != list(range(len(names))):
            raise DetectorDataError(f"{path}: names: expected class indices 0..n-1, got {sorted(names)}")
        out["names"] = [str(names[i]) for i in range(len(names))]
    return out


def _yaml_scalar(value: str) -> str:
    if len(value) >= 2 and value[0] == value[-1] and value[0] in "'\"":
        return json.loads(value) if value[0] == '"' else value[1:-1].replace("''", "'")
    return value


@dataclass(frozen=True)
class InstanceLabels:
    """The labelled instances of one image: class indices and, per instance, either a COCO RLE or a polygon."""

    classes: np.ndarray  # (n,) int
    rles: tuple = ()  # COCO RLE dicts (label source "coco")
    polygons: tuple = ()  # (m, 2) normalised polygons (label source "yolo")


@dataclass(frozen=True)
class DetectionDataset:
    """A YOLO-seg dataset ready to sample from.

    ``yolo_root``: the folder of ``data.yaml``. ``names``: class names by index. ``obj_ids``: BOP obj_id per class.
    ``images``: split -> sorted image paths. ``label_source``: ``"coco"`` or ``"yolo"``. ``coco_gt``: split -> the
    COCO instances dict (images, annotations, categories = obj_ids) used as validation ground truth. ``sources``:
    the folders of a combined dataset (``combine_datasets``; empty for one folder, see ``roots``).
    """

    yolo_root: Path
    names: list[str]
    obj_ids: list[int]
    images: dict[str, list[Path]]
    label_source: str
    labels: dict[str, list[InstanceLabels]] = field(repr=False)
    coco_gt: dict[str, dict] = field(repr=False)
    sources: tuple[Path, ...] = ()

    @property
    def roots(self) -> tuple[Path, ...]:
        """The ``data.yaml`` folders the dataset was read from (several for ``combine_datasets``' union)."""
        return self.sources or (self.yolo_root,)

    @property
    def num_classes(self) -> int:
        return len(self.names)


def open_dataset(
    data_dir: str | Path,
    labels: str = "auto",
    obj_ids: Sequence[int] | None = None,
    splits: Sequence[str] = ("train", "val"),
    id_map: Mapping[str, int] | None = None,
    catalogue: Catalogue | None = None,
) -> DetectionDataset:
    """Opens the dataset at ``data_dir`` (a ``sygrid generate`` folder with ``yolo/data.yaml``, a YOLO folder with
    ``data.yaml``, or the ``data.yaml`` itself) and reads every label of ``splits``.

    Args:
        labels: ``"coco"`` (masks from ``DIR/coco``), ``"yolo"`` (polygons) or ``"auto"`` (coco where present).
        obj_ids: BOP obj_id of each class; None: ``catalogue`` where given, else ``id_map`` where given, else
            ``DIR/bop/models/models_info.json`` (class index = position in the sorted ids, as ``sygrid generate``
            numbers classes), else by class name from the COCO categories (``DIR/coco``), else from the built-in part
            names (``sygrid.id_map``).
        id_map: class name or index -> obj_id (``sygrid.id_map.load_id_map``), for classes no other source names.
        catalogue: the parts catalogue the dataset was made from: every class must be one of its parts (by name),
            and takes its id; where the dataset has ``bop/models`` too, their ids must be the same.

    Raises:
        DetectorDataError: a missing file or folder, a malformed ``data.yaml`` or label, or classes that cannot be
            mapped to obj_ids.
    """
    if labels not in LABEL_SOURCES:
        raise ValueError(f"labels: expected one of {LABEL_SOURCES}, got {labels!r}")
    yaml_path = _find_data_yaml(Path(data_dir))
    spec = parse_data_yaml(yaml_path.read_text(), yaml_path)
    if "names" not in spec:
        raise DetectorDataError(f"{yaml_path}: no 'names' (the class names by index)")
    names = spec["names"]
    root = yaml_path.parent / spec["path"] if spec.get("path") else yaml_path.parent
    dataset_dir = yaml_path.parent.parent if yaml_path.parent.name == "yolo" else None
    if catalogue is not None and obj_ids is None:
        obj_ids = catalogue_class_ids(names, catalogue, yaml_path, dataset_dir)
    ids = _class_obj_ids(names, obj_ids, id_map, dataset_dir, yaml_path, splits)
    images: dict[str, list[Path]] = {}
    for split in splits:
        if split not in spec:
            raise DetectorDataError(f"{yaml_path}: no {split!r} entry (the folder of the {split} images)")
        folder = root / spec[split]
        if not folder.is_dir():
            raise DetectorDataError(f"{yaml_path}: {split}: folder {folder} does not exist")
        images[split] = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not images[split]:
            raise DetectorDataError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)})")
    coco_files = (
        {s: dataset_dir / "coco" / "annotations" / f"instances_{s}.json" for s in splits} if dataset_dir else {}
    )
    has_coco = bool(coco_files) and all(f.is_file() for f in coco_files.values())
    if labels == "coco" and not has_coco:
        raise DetectorDataError(f"labels 'coco': expected {', '.join(map(str, coco_files.values())) or 'DIR/coco'}")
    source = "coco" if labels == "coco" or (labels == "auto" and has_coco) else "yolo"
    all_labels: dict[str, list[InstanceLabels]] = {}
    coco_gt: dict[str, dict] = {}
    for split in splits:
        if source == "coco":
            all_labels[split], coco_gt[split] = _coco_labels(coco_files[split], images[split], ids)
        else:
            all_labels[split] = [_yolo_labels(p, len(names)) for p in images[split]]
            coco_gt[split] = _gt_from_polygons(images[split], all_labels[split], ids)
    log.info(
        "dataset %s: %s, labels from %s",
        yaml_path,
        ", ".join(f"{s} {len(v)} images" for s, v in images.items()),
        source,
    )
    return DetectionDataset(yaml_path.parent, names, ids, images, source, all_labels, coco_gt)


def open_datasets(data_dirs: Sequence[str | Path], **options) -> DetectionDataset:
    """Opens each of ``data_dirs`` (``open_dataset`` with ``options``) and returns them as one dataset
    (``combine_datasets``): one folder is returned as it is."""
    if not data_dirs:
        raise DetectorDataError("no dataset given (expected at least one --data folder)")
    parts = [open_dataset(d, **options) for d in data_dirs]
    return parts[0] if len(parts) == 1 else combine_datasets(parts)


def combine_datasets(parts: Sequence[DetectionDataset]) -> DetectionDataset:
    """Several datasets as one: each split's images and labels in the order given, the validation ground truth
    renumbered (image ids follow the combined image order). Training on the union is how one recipe's items are
    mixed with another's (plain renders with randomised ones, synthetic with labelled photos) without generating
    them again. ``yolo_root`` is the first dataset's; ``label_source`` joins the parts' distinct sources with
    ``+`` (each image's labels say which kind they are).

    Raises:
        DetectorDataError: the datasets' classes (names or obj_ids) or splits differ.
    """
    first = parts[0]
    for other in parts[1:]:
        if other.names != first.names or other.obj_ids != first.obj_ids:
            raise DetectorDataError(
                f"{other.yolo_root}: classes {other.names} (obj_ids {other.obj_ids}) differ from {first.yolo_root}'s "
                f"{first.names} (obj_ids {first.obj_ids}); datasets trained together must have the same classes"
            )
        if other.images.keys() != first.images.keys():
            raise DetectorDataError(f"{other.yolo_root}: splits {list(other.images)}, {first.yolo_root} has "
                                    f"{list(first.images)}")  # fmt: skip
    splits = list(first.images)
    return DetectionDataset(
        first.yolo_root,
        first.names,
        first.obj_ids,
        {s: [p for d in parts for p in d.images[s]] for s in splits},
        "+".join(dict.fromkeys(d.label_source for d in parts)),
        {s: [lab for d in parts for lab in d.labels[s]] for s in splits},
        {s: _merged_gt([d.coco_gt[s] for d in parts]) for s in splits},
        tuple(root for d in parts for root in d.roots),
    )


def _merged_gt(gts: Sequence[dict]) -> dict:
    """COCO ground truths of consecutive image lists as one: image ids offset by the images before, annotation ids
    renumbered from 1."""
    images, annotations, offset = [], [], 0
    for gt in gts:
        renumber = {im["id"]: offset + k + 1 for k, im in enumerate(gt["images"])}
        images += [{**im, "id": renumber[im["id"]]} for im in gt["images"]]
        annotations += [
            {**a, "id": len(annotations) + j + 1, "image_id": renumber[a["image_id"]]}
            for j, a in enumerate(gt["annotations"])
        ]
        offset += len(gt["images"])
    return {"images": images, "annotations": annotations, "categories": gts[0]["categories"]}


def _find_data_yaml(path: Path) -> Path:
    for candidate in (path, path / "yolo" / "data.yaml", path / "data.yaml"):
        if candidate.is_file():
            return candidate
    raise DetectorDataError(f"{path}: no YOLO dataset here (expected {path / 'yolo' / 'data.yaml'} or data.yaml)")


def _class_obj_ids(
    names: list[str],
    obj_ids: Sequence[int] | None,
    id_map: Mapping[str, int] | None,
    dataset_dir: Path | None,
    yaml_path: Path,
    splits: Sequence[str],
) -> list[int]:
    if obj_ids is not None:
        if len(obj_ids) != len(names):
            raise DetectorDataError(f"obj_ids: {len(obj_ids)} ids given for the {len(names)} classes of {yaml_path}")
        return [int(i) for i in obj_ids]
    info = dataset_dir / "bop" / "models" / "models_info.json" if dataset_dir else None
    if id_map is None and info is not None and info.is_file():
        ids = sorted(int(k) for k in json.loads(info.read_text()))
        if len(ids) != len(names):
            raise DetectorDataError(f"{info}: {len(ids)} models for the {len(names)} classes of {yaml_path}")
        return ids
    try:
        return class_obj_ids(names, str(yaml_path), id_map, known=_coco_category_ids(dataset_dir, splits))
    except ConfigError as err:
        raise DetectorDataError(str(err)) from err


def catalogue_class_ids(
    names: Sequence[str], catalogue: Catalogue, yaml_path: Path, dataset_dir: Path | None = None
) -> list[int]:
    """The catalogue's id of each class (by name). Raises DetectorDataError for a class that is no part of the
    catalogue, or a dataset whose ``bop/models`` hold other ids (the dataset was made from another catalogue)."""
    unknown = [n for n in names if n not in catalogue.names]
    if unknown:
        raise DetectorDataError(
            f"{yaml_path}: classes {unknown} are not parts of the catalogue {catalogue.source} (its parts: "
            f"{', '.join(catalogue.names)})"
        )
    ids = [catalogue.part(n).id for n in names]
    info = dataset_dir / "bop" / "models" / "models_info.json" if dataset_dir else None
    if info is not None and info.is_file():
        have = sorted(int(k) for k in json.loads(info.read_text()))
        if have != sorted(ids) or ids != sorted(ids):
            raise DetectorDataError(
                f"{info}: the dataset's obj_ids {have} (classes {list(names)} in that order) are not the catalogue "
                f"{catalogue.source}'s ids of those classes {ids}: the dataset was made from another catalogue"
            )
    return ids


def _coco_category_ids(dataset_dir: Path | None, splits: Sequence[str]) -> dict[str, int]:
    """name -> id of the COCO categories beside the yolo folder (the first split's file that exists), or {}."""
    paths = [dataset_dir / "coco" / "annotations" / f"instances_{s}.json" for s in splits] if dataset_dir else []
    path = next((p for p in paths if p.is_file()), None)
    if path is None:
        return {}
    try:
        categories = json.loads(path.read_text()).get("categories", [])
        return {str(c["name"]): int(c["id"]) for c in categories}
    except (OSError, json.JSONDecodeError, AttributeError, KeyError, TypeError, ValueError) as err:
        raise DetectorDataError(f"{path}: categories: expected a list of {{id, name}} ({err!r})") from err


def label_path(image_path: Path) -> Path:
    """``.../images/<split>/x.png`` -> ``.../labels/<split>/x.txt`` (the YOLO rule: the last ``images`` folder)."""
    parts = list(image_path.parts)
    for k in range(len(parts) - 2, -1, -1):
        if parts[k] == "images":
            parts[k] = "labels"
            return Path(*parts).with_suffix(".txt")
    raise DetectorDataError(f"{image_path}: not inside an 'images' folder, cannot find its label file")


def _yolo_labels(image_path: Path, num_classes: int) -> InstanceLabels:
    path = label_path(image_path)
    if not path.is_file():  # YOLO convention: no label file = no instances
        return InstanceLabels(np.zeros(0, dtype=np.int64))
    classes, polygons = [], []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) < 7 or len(fields) % 2 == 0:
            raise DetectorDataError(f"{path}:{lineno}: expected 'class x1 y1 x2 y2 x3 y3 ...', got {line[:80]!r}")
        try:
            cls, xy = int(fields[0]), np.asarray(fields[1:], dtype=np.float64).reshape(-1, 2)
        except ValueError as err:
            raise DetectorDataError(f"{path}:{lineno}: not numbers: {line[:80]!r}") from err
        if not 0 <= cls < num_classes:
            raise DetectorDataError(f"{path}:{lineno}: class {cls} outside 0..{num_classes - 1}")
        if not np.all(np.isfinite(xy)) or xy.min() < -0.01 or xy.max() > 1.01:
            raise DetectorDataError(f"{path}:{lineno}: polygon coordinates must be normalised to [0, 1]")
        classes.append(cls)
        polygons.append(xy)
    return InstanceLabels(np.asarray(classes, dtype=np.int64), polygons=tuple(polygons))


def _coco_labels(path: Path, images: list[Path], obj_ids: list[int]) -> tuple[list[InstanceLabels], dict]:
    try:
        coco = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise DetectorDataError(f"{path}: not a readable COCO JSON ({err})") from err
    by_name = {im["file_name"]: im for im in coco.get("images", [])}
    class_of = {obj_id: k for k, obj_id in enumerate(obj_ids)}
    per_image: dict[int, list[dict]] = {}
    for ann in coco.get("annotations", []):
        if ann["category_id"] not in class_of:
            raise DetectorDataError(f"{path}: annotation {ann['id']}: category {ann['category_id']} not in {obj_ids}")
        per_image.setdefault(ann["image_id"], []).append(ann)
    labels, gt_images, gt_anns = [], [], []
    for k, image in enumerate(images):
        record = by_name.get(image.name)
        if record is None:
            raise DetectorDataError(f"{path}: no record for image {image.name} (the COCO and YOLO folders differ)")
        anns = [a for a in per_image.get(record["id"], []) if not a.get("iscrowd", 0)]
        rles = tuple(_rle(a["segmentation"], record["height"], record["width"]) for a in anns)
        labels.append(InstanceLabels(np.asarray([class_of[a["category_id"]] for a in anns], np.int64), rles=rles))
        gt_images.append({"id": k + 1, "width": record["width"], "height": record["height"]})
        for a in per_image.get(record["id"], []):
            gt_anns.append({**a, "id": len(gt_anns) + 1, "image_id": k + 1})
    categories = [{"id": i, "name": str(i)} for i in obj_ids]
    return labels, {"images": gt_images, "annotations": gt_anns, "categories": categories}


def _rle(segmentation: dict | list, height: int, width: int) -> dict:
    if isinstance(segmentation, list):  # polygons
        return mask_utils.merge(mask_utils.frPyObjects(segmentation, height, width))
    if isinstance(segmentation.get("counts"), list):  # uncompressed RLE
        return mask_utils.frPyObjects(segmentation, height, width)
    return {"size": segmentation["size"], "counts": segmentation["counts"].encode("ascii")}


def _gt_from_polygons(images: list[Path], labels: list[InstanceLabels], obj_ids: list[int]) -> dict:
    """COCO ground truth from YOLO polygons (rasterised at each image's size, which is read from its header)."""
    gt_images, gt_anns = [], []
    for k, (path, lab) in enumerate(zip(images, labels, strict=True)):
        h, w = _image_size(path)
        gt_images.append({"id": k + 1, "width": w, "height": h})
        for cls, poly in zip(lab.classes, lab.polygons, strict=True):
            mask = polygon_to_mask(poly * np.array([w, h]), h, w)
            rle = mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))
            x, y, bw, bh = cv2.boundingRect(mask.astype(np.uint8))
            gt_anns.append(
                {
                    "id": len(gt_anns) + 1,
                    "image_id": k + 1,
                    "category_id": obj_ids[int(cls)],
                    "segmentation": rle,
                    "area": float(mask_utils.area(rle)),
                    "bbox": [float(x), float(y), float(bw), float(bh)],
                    "iscrowd": 0,
                }
            )
    return {"images": gt_images, "annotations": gt_anns, "categories": [{"id": i, "name": str(i)} for i in obj_ids]}


def _image_size(path: Path) -> tuple[int, int]:
    image = read_rgb(path)
    return image.shape[0], image.shape[1]


def read_rgb(path: Path) -> np.ndarray:
    """(h, w, 3) uint8 RGB of an image file."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise DetectorDataError(f"{path}: not a readable image")
    return np.ascontiguousarray(image[..., ::-1])


def load_instances(dataset: DetectionDataset, split: str, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Image ``index`` of ``split``: RGB (h, w, 3) uint8, instance-id map (h, w) int32 (0 background, k + 1 for
    instance k), classes (n,) int. Overlapping labels (polygon outlines of neighbours) go to the later instance."""
    image = read_rgb(dataset.images[split][index])
    h, w = image.shape[:2]
    lab = dataset.labels[split][index]
    ids = np.zeros((h, w), dtype=np.int32)
    if lab.rles:
        for k, rle in enumerate(lab.rles):
            if tuple(rle["size"]) != (h, w):
                raise DetectorDataError(
                    f"{dataset.images[split][index]}: COCO mask size {rle['size']} differs from the image {h}x{w}"
                )
            ids[mask_utils.decode(rle).astype(bool)] = k + 1
    else:
        for k, poly in enumerate(lab.polygons):
            ids[polygon_to_mask(poly * np.array([w, h]), h, w)] = k + 1
    return image, ids, lab.classes
