"""``sygrid convert``: labels made elsewhere -> a dataset folder in the layout ``sygrid generate`` writes
(``OUT/bop``, ``OUT/coco``, ``OUT/yolo``), through the project's readers and writers.

Sources:

- the SyGRID label pickle (``sygrid.readers.sygrid_pickle``) with its images (and depth maps, optional);
- a YOLO-seg folder (``sygrid.readers.yolo_seg``): real photos with polygon labels; no camera and no poses, so
  only the COCO and YOLO formats can be written from it.

Classes become BOP obj_ids through ``sygrid.id_map.class_obj_ids`` (the id map, the labels' own ids, built-in part
names). A box the source stores is compared with its mask's box; where any edge differs by more than
``box_tolerance_px`` the box is replaced by the mask's, and the check is reported (boxes checked, recomputed, the
worst difference and where). Depth is kept only when it is metric: a 16-bit PNG with a depth scale (millimetres per
unit); 8-bit depth (a picture of depth, not a measurement) is dropped with a warning.

The output is written into a fresh temporary folder beside ``out`` and renamed into place at the end, so ``out``
holds either a whole conversion or none; an existing non-empty ``out`` is replaced only with ``force``. The report
(``OUT/convert.json``) lists what was done, and which source image became which output item.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import trimesh

from sygrid.annotations import ImageAnnotation, mask_bbox
from sygrid.errors import ConfigError
from sygrid.fileio import write_json_atomic
from sygrid.id_map import class_obj_ids
from sygrid.objects.model import ObjectModel
from sygrid.readers.sygrid_pickle import image_from_entry, pickle_entries
from sygrid.readers.yolo_seg import SPLITS, open_yolo_seg, read_yolo_item
from sygrid.train.detector.data import IMAGE_SUFFIXES, read_rgb
from sygrid.writers import DatasetWriter, create_writer

if TYPE_CHECKING:
    from sygrid.catalogue import Catalogue

log = logging.getLogger(__name__)

FORMATS = ("bop", "coco", "yolo")
REPORT_NAME = "convert.json"
MM_PER_M = 1000.0


@dataclass(frozen=True)
class ConvertOptions:
    """``formats``: a subset of ``FORMATS``. ``split``: the output split of a source without splits (the pickle, a
    flat YOLO folder): train, val or test. ``id_map``: class name or index -> obj_id (``sygrid.id_map``).
    ``box_tolerance_px``: largest accepted difference between a stored box's edge and its mask's. ``depth_scale_mm``:
    millimetres per unit of 16-bit depth PNGs (None: 16-bit depth is refused). ``bop_models``: a BOP ``models/``
    folder with the meshes of the output obj_ids (needed for the bop format). ``depth``: False reads no depth.
    ``force``: replace a non-empty ``out``. ``catalogue``: the parts catalogue (``sygrid.catalogue``): class names
    map to its ids (``class_obj_ids``'s ``known``), the output parts take its names, and its meshes serve the bop
    format.
    """

    formats: tuple[str, ...] = FORMATS
    split: str = "test"
    id_map: dict[str, int] | None = None
    box_tolerance_px: float = 2.0
    depth_scale_mm: float | None = None
    bop_models: Path | None = None
    depth: bool = True
    force: bool = False
    catalogue: Catalogue | None = None

    @property
    def known(self) -> dict[str, int]:
        """Class name -> obj_id of the catalogue's parts ({} without a catalogue)."""
        return {p.name: p.id for p in self.catalogue.parts} if self.catalogue is not None else {}

    def __post_init__(self) -> None:
        unknown = [f for f in self.formats if f not in FORMATS]
        if not self.formats or unknown or len(set(self.formats)) != len(self.formats):
            raise ConfigError(f"formats: expected distinct names among {list(FORMATS)}, got {list(self.formats)}")
        if self.split not in SPLITS:
            raise ConfigError(f"split: expected one of {list(SPLITS)}, got {self.split!r}")
        if not self.box_tolerance_px >= 0:
            raise ConfigError(f"box_tolerance_px: expected >= 0 pixels, got {self.box_tolerance_px}")
        if self.depth_scale_mm is not None and not self.depth_scale_mm > 0:
            raise ConfigError(f"depth_scale_mm: expected > 0 millimetres per unit, got {self.depth_scale_mm}")


@dataclass
class ConvertReport:
    """What a conversion did; ``as_dict`` is ``convert.json``."""

    source: str
    formats: tuple[str, ...]
    classes: list[dict] = field(default_factory=list)  # {"obj_id", "name", "source"} per output class
    images: dict[str, int] = field(default_factory=dict)  # split -> images written
    instances: int = 0
    boxes_checked: int = 0
    boxes_recomputed: int = 0
    box_worst_px: float = 0.0
    box_worst_where: str = ""
    depth: dict[str, int] = field(default_factory=lambda: {"kept": 0, "dropped_non_metric": 0, "missing": 0})
    items: list[dict] = field(default_factory=list)  # {"source", "split", "name"} per image

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)

    def summary(self) -> str:
        lines = [
            f"{sum(self.images.values())} images ({', '.join(f'{s} {n}' for s, n in self.images.items())}), "
            f"{self.instances} instances, classes "
            + ", ".join(f"{c['source']} -> {c['obj_id']} {c['name']}" for c in self.classes),
        ]
        if self.boxes_checked:
            lines.append(
                f"boxes: {self.boxes_recomputed} of {self.boxes_checked} recomputed from their masks; worst "
                f"disagreement {self.box_worst_px:.0f} px ({self.box_worst_where})"
            )
        d = self.depth
        if any(d.values()):
            lines.append(f"depth: {d['kept']} kept, {d['dropped_non_metric']} dropped (not metric), "
                         f"{d['missing']} missing")  # fmt: skip
        return "\n".join(lines)


# ------------------------------------------------------------------------------------------------- the two sources
def convert_sygrid_pickle(
    pickle_path: str | Path,
    out: str | Path,
    options: ConvertOptions,
    images_dir: str | Path | None = None,
    depth_dir: str | Path | None = None,
) -> ConvertReport:
    """Converts a SyGRID label pickle and its images into ``out`` (one split, ``options.split``).

    ``images_dir``: where the images are (default: ``rgb/`` or ``images/`` beside the pickle, else its folder); an
    image is found by the label key (``"000042.png"``) or, for a numeric key, as ``000042`` with an image suffix.
    ``depth_dir``: depth PNGs of the same stems (default: ``depth/`` beside the pickle, when it exists).
    """
    pickle_path = Path(pickle_path)
    images_dir = Path(images_dir) if images_dir is not None else _first_dir(pickle_path.parent, ("rgb", "images"))
    if depth_dir is None and (pickle_path.parent / "depth").is_dir():
        depth_dir = pickle_path.parent / "depth"
    if not options.depth:
        depth_dir = None
    entries = pickle_entries(pickle_path)
    source_ids = _pickle_obj_ids(entries)
    target = dict(zip(source_ids, class_obj_ids([None] * len(source_ids), str(pickle_path), options.id_map,
                                                own_ids=source_ids, known=options.known), strict=True))  # fmt: skip
    models = _output_models(target, {}, options)
    report = ConvertReport(str(pickle_path), options.formats, _classes(target, models))
    with _fresh_folder(Path(out), options.force) as tmp:
        writers = _writers(tmp, models, options.formats, options.split)
        for key, image_id, entry, where in entries:
            image_path = _find_image(images_dir, key, image_id, where)
            rgb = read_rgb(image_path)
            h, w = rgb.shape[:2]
            ann = image_from_entry(entry, image_id, w, h, where)
            instances = tuple(dataclasses.replace(i, obj_id=target[i.obj_id]) for i in ann.instances)
            ann = _fix_boxes(dataclasses.replace(ann, instances=instances), options.box_tolerance_px, report, where)
            depth_m = None
            if depth_dir is not None:
                depth_m = _read_depth(Path(depth_dir) / f"{image_path.stem}.png", (h, w), options, report)
            if depth_m is not None and options.depth_scale_mm is not None:  # kept depth always has its scale
                ann = dataclasses.replace(ann, depth_scale_mm=options.depth_scale_mm)
            _write(writers, ann, rgb, depth_m, report, str(image_path), options.split)
        _finish(writers, tmp, report)
    if report.depth["dropped_non_metric"]:
        log.warning(
            "%s: %d depth maps are 8-bit (not metric): dropped; the dataset has no depth",
            depth_dir, report.depth["dropped_non_metric"],
        )  # fmt: skip
    return report


def convert_yolo_seg(
    source: str | Path, out: str | Path, options: ConvertOptions, names: Sequence[str] | None = None
) -> ConvertReport:
    """Converts a YOLO-seg folder (or its data.yaml) into ``out``, split by split; COCO and YOLO formats only.

    ``names``: the class names by index where the folder has no data.yaml."""
    if "bop" in options.formats:
        raise ConfigError(
            f"{source}: YOLO-seg labels hold no camera and no poses, so no BOP dataset can be written from them; "
            "choose --formats coco,yolo"
        )
    src = open_yolo_seg(source, names, options.split)
    ids = class_obj_ids(src.names, str(src.where), options.id_map, known=options.known)
    target = dict(zip(ids, ids, strict=True))
    models = _output_models(target, dict(zip(ids, src.names, strict=True)), options)
    report = ConvertReport(str(src.where), options.formats, _classes(target, models, src.names))
    with _fresh_folder(Path(out), options.force) as tmp:
        writers: dict[str, list[DatasetWriter]] = {}
        for split, images in src.splits.items():
            writers[split] = _writers(tmp, models, options.formats, split)
            for image_id, image_path in enumerate(images):
                ann, rgb = read_yolo_item(image_path, ids, image_id)
                _write(writers[split], ann, rgb, None, report, str(image_path), split)
        _finish([w for ws in writers.values() for w in ws], tmp, report)
    return report


# --------------------------------------------------------------------------------------------------- the pieces
def box_disagreement_px(box: Sequence[int], reference: Sequence[int]) -> float:
    """The largest difference between the edges (x0, y0, x1, y1) of two ``(x, y, w, h)`` boxes, pixels."""
    a, b = np.asarray(box, dtype=float), np.asarray(reference, dtype=float)
    edges_a = np.concatenate([a[:2], a[:2] + a[2:]])
    edges_b = np.concatenate([b[:2], b[:2] + b[2:]])
    return float(np.abs(edges_a - edges_b).max())


def _fix_boxes(ann: ImageAnnotation, tolerance_px: float, report: ConvertReport, where: str) -> ImageAnnotation:
    """``ann`` with each visible box that disagrees with its mask by more than ``tolerance_px`` replaced by the
    mask's box; counted in ``report``."""
    instances = []
    for k, inst in enumerate(ann.instances):
        if inst.px_count_visib > 0:
            box = mask_bbox(inst.mask_visib)
            diff = box_disagreement_px(inst.bbox_visib, box)
            report.boxes_checked += 1
            if diff > report.box_worst_px:
                report.box_worst_px = diff
                report.box_worst_where = f"{where}.objects[{k}].bbox {list(inst.bbox_visib)}, mask box {list(box)}"
            if diff > tolerance_px:
                report.boxes_recomputed += 1
                inst = dataclasses.replace(inst, bbox_visib=box)
        instances.append(inst)
    return dataclasses.replace(ann, instances=tuple(instances))


def _read_depth(
    path: Path, shape: tuple[int, int], options: ConvertOptions, report: ConvertReport
) -> np.ndarray | None:
    """Metric depth (h, w) float32 metres from a 16-bit PNG, or None (missing or 8-bit: counted in ``report``)."""
    if not path.is_file():
        report.depth["missing"] += 1
        return None
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ConfigError(f"{path}: not a readable depth image")
    if image.dtype == np.uint8:
        log.debug("%s: 8-bit depth (not metric): dropped", path)
        report.depth["dropped_non_metric"] += 1
        return None
    if image.dtype != np.uint16 or image.ndim != 2:
        raise ConfigError(f"{path}: depth: expected a one-channel 16-bit PNG, got {image.dtype} {image.shape}")
    if image.shape != shape:
        raise ConfigError(f"{path}: depth: size {image.shape[1]}x{image.shape[0]} differs from its image's "
                          f"{shape[1]}x{shape[0]}")  # fmt: skip
    if options.depth_scale_mm is None:
        raise ConfigError(
            f"{path}: 16-bit depth needs its scale: pass --depth-scale-mm (millimetres per unit), or --no-depth"
        )
    report.depth["kept"] += 1
    return (image.astype(np.float64) * options.depth_scale_mm / MM_PER_M).astype(np.float32)


def _pickle_obj_ids(entries: list[tuple[Any, int, dict, str]]) -> list[int]:
    """The sorted distinct ``obj_id``s of the pickle's objects; the image ids must be distinct."""
    ids: set[int] = set()
    image_ids: dict[int, Any] = {}
    for key, image_id, entry, where in entries:
        if image_id in image_ids:
            raise ConfigError(f"{where}: image id {image_id} is also image {image_ids[image_id]!r}'s")
        image_ids[image_id] = key
        objects = entry.get("objects", []) if isinstance(entry, dict) else []
        for k, obj in enumerate(objects if isinstance(objects, (list, tuple)) else []):
            try:
                ids.add(int(obj["obj_id"]))
            except (KeyError, TypeError, ValueError) as err:
                raise ConfigError(f"{where}.objects[{k}].obj_id: expected an integer ({err!r})") from err
    if not ids:
        raise ConfigError(f"{entries[0][3] if entries else 'the pickle'}: no objects in any image")
    return sorted(ids)


def _find_image(images_dir: Path, key: Any, image_id: int, where: str) -> Path:
    name = Path(str(key)).name
    candidates = [images_dir / name] if Path(name).suffix.lower() in IMAGE_SUFFIXES else []
    stems = [Path(name).stem] if not isinstance(key, (int, np.integer)) else []
    stems += [f"{image_id:06d}", str(image_id)]
    candidates += [images_dir / f"{stem}{suffix}" for stem in stems for suffix in IMAGE_SUFFIXES]
    for path in candidates:
        if path.is_file():
            return path
    raise ConfigError(f"{where}: no image for this entry in {images_dir} (looked for {candidates[0].name}, ...)")


def _first_dir(folder: Path, names: Sequence[str]) -> Path:
    return next((folder / n for n in names if (folder / n).is_dir()), folder)


def _output_models(target: dict[int, int], names: dict[int, str], options: ConvertOptions) -> list[ObjectModel]:
    """The writers' models of the output obj_ids: the catalogue's parts where ``options.catalogue`` has every one;
    else from ``options.bop_models`` when the bop format is written (meshes needed), else name-only placeholders (an
    empty mesh: the COCO and YOLO writers use ids and names). The catalogue's names win over the labels'."""
    obj_ids = sorted(set(target.values()))
    in_catalogue = {v: k for k, v in options.known.items()}
    if options.catalogue is not None and all(i in in_catalogue for i in obj_ids):
        return [options.catalogue.model(in_catalogue[i]) for i in obj_ids]
    names = {**names, **{i: n for i, n in in_catalogue.items() if i in obj_ids}}
    if "bop" in options.formats:
        if options.bop_models is None:
            raise ConfigError(
                "bop format: the parts' meshes are needed (BOP models/); pass --bop-models DIR (a BOP models folder "
                f"with models_info.json and obj_OOOOOO.ply of obj_ids {obj_ids}), or choose --formats coco,yolo"
            )
        from sygrid.train.pose.objects import load_bop_models  # open3d: only for the bop format

        loaded = load_bop_models(options.bop_models, obj_ids)
        return [dataclasses.replace(loaded[i], name=names.get(i, loaded[i].name)) for i in obj_ids]
    return [ObjectModel(obj_id=i, name=names.get(i, f"obj_{i:06d}"), mesh=trimesh.Trimesh()) for i in obj_ids]


def _classes(target: dict[int, int], models: list[ObjectModel], source_names: Sequence[str] | None = None) -> list:
    name = {m.obj_id: m.name for m in models}
    sources = source_names or [str(s) for s in target]
    return [{"source": s, "obj_id": t, "name": name[t]} for s, t in zip(sources, target.values(), strict=True)]


def _writers(root: Path, models: list[ObjectModel], formats: Sequence[str], split: str) -> list[DatasetWriter]:
    return [create_writer(f, root / f, models, split=split) for f in formats]


def _write(
    writers: list[DatasetWriter],
    ann: ImageAnnotation,
    rgb: np.ndarray,
    depth_m: np.ndarray | None,
    report: ConvertReport,
    source: str,
    split: str,
) -> None:
    for writer in writers:
        writer.write(ann, rgb, depth_m)
    report.images[split] = report.images.get(split, 0) + 1
    report.instances += len(ann.instances)
    report.items.append({"source": source, "split": split, "name": ann.name})


def _finish(writers: list[DatasetWriter], root: Path, report: ConvertReport) -> None:
    for writer in writers:
        writer.finish()
    write_json_atomic(root / REPORT_NAME, report.as_dict())


@contextmanager
def _fresh_folder(out: Path, force: bool) -> Iterator[Path]:
    """A temporary folder beside ``out`` that replaces ``out`` when the block ends without an error (and is removed
    when it raises). An existing non-empty ``out`` is refused unless ``force``."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise ConfigError(f"{out}: exists and is not empty; pass --force to replace it")
    tmp = out.parent / f".{out.name}.convert-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = out.parent / f".{out.name}.replaced-{os.getpid()}"
    if out.exists():
        os.replace(out, old)
    os.replace(tmp, out)
    shutil.rmtree(old, ignore_errors=True)
