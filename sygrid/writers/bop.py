"""BOP dataset writer and reader (the layout the BOP toolkit reads), millimetres in the files, metres inside.

Layout under ``root``::

    models/models_info.json, models/obj_OOOOOO.ply            (mm)
    <split>/SSSSSS/rgb/IIIIII.png, depth/IIIIII.png            (uint16, depth_mm = value * depth_scale)
    <split>/SSSSSS/depth_true/IIIIII.png                       (the exact depth, when depth/ is a sensor's; not BOP)
    <split>/SSSSSS/mask/IIIIII_GGGGGG.png, mask_visib/...      (GGGGGG = index in the scene_gt list;
                                                                an instance without a full mask gets its visible one)
    <split>/SSSSSS/scene_gt.json, scene_camera.json, scene_gt_info.json
                                                               (scene_camera.json: cam_K, depth_scale and, where
                                                                the scene's world frame is known, cam_R_w2c and
                                                                cam_t_w2c; older datasets lack these two)

Every file goes through ``write_bytes_atomic``. ``write`` stores an image's files and then its three scene-JSON
entries as one record, ``<split>/SSSSSS/gt_items/IIIIII.json`` (not BOP), last: so an item is complete or absent,
and its cost does not grow with the scene (rewriting a thousand-image scene's JSONs per item would). ``flush`` (and
``finish``; ``flush_split`` for a folder left by a killed run) merges the records into the scene JSONs,
``scene_gt.json`` last, then deletes them; a crash in between leaves records that the next flush merges again.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from sygrid.annotations import ImageAnnotation, InstanceAnnotation, check_item
from sygrid.camera import CameraIntrinsics
from sygrid.errors import ConfigError
from sygrid.fileio import read_json, write_bytes_atomic, write_json_atomic
from sygrid.objects.model import ObjectModel

log = logging.getLogger(__name__)

MM_PER_M = 1000.0
_UINT16_MAX = 65535
ITEMS_DIR = "gt_items"  # per-image records of the scene JSON entries, until flushed
# Scene JSON -> its key in an item record; scene_gt.json last: its entry is the one that commits an image.
SCENE_FILES = (
    ("scene_gt_info.json", "scene_gt_info"), ("scene_camera.json", "scene_camera"), ("scene_gt.json", "scene_gt"),
)  # fmt: skip


# ------------------------------------------------------------------------------------------ JSON <-> numpy helpers
def gt_as_json(inst: InstanceAnnotation) -> dict:
    """A ``scene_gt.json`` entry (new dict): rotation row-major, translation in millimetres."""
    T = np.asarray(inst.T_camera_obj, dtype=np.float64)
    return {
        "cam_R_m2c": [float(v) for v in T[:3, :3].reshape(-1)],
        "cam_t_m2c": [float(v) * MM_PER_M for v in T[:3, 3]],
        "obj_id": int(inst.obj_id),
    }


def T_from_gt_json(entry: dict, where: str) -> np.ndarray:
    """(4, 4) metres from a ``scene_gt.json`` entry; ``where`` names the file and key for errors."""
    return _T_from_R_t_mm(entry, "cam_R_m2c", "cam_t_m2c", where)


def _T_from_R_t_mm(entry: dict, r_key: str, t_key: str, where: str) -> np.ndarray:
    """(4, 4) metres from a BOP entry's rotation ``r_key`` (9 numbers, row-major) and translation ``t_key`` (mm)."""
    try:
        R = np.asarray(entry[r_key], dtype=np.float64).reshape(3, 3)
        t = np.asarray(entry[t_key], dtype=np.float64).reshape(3) / MM_PER_M
    except (KeyError, ValueError, TypeError) as err:
        raise ConfigError(f"{where}: expected {r_key} (9 numbers) and {t_key} (3 numbers, mm): {err}") from err
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def gt_info_as_json(inst: InstanceAnnotation) -> dict:
    """A ``scene_gt_info.json`` entry (new dict)."""
    return {
        "bbox_obj": [int(v) for v in inst.bbox_obj],
        "bbox_visib": [int(v) for v in inst.bbox_visib],
        "px_count_all": int(inst.px_count_all),
        "px_count_valid": int(inst.px_count_valid),
        "px_count_visib": int(inst.px_count_visib),
        "visib_fract": float(inst.visib_fract),
    }


def camera_as_json(
    intrinsics: CameraIntrinsics, depth_scale_mm: float, T_camera_world: np.ndarray | None = None
) -> dict:
    """A ``scene_camera.json`` entry (new dict); with ``T_camera_world`` (4x4, metres) also BOP's world-to-camera
    pose ``cam_R_w2c`` (row-major) and ``cam_t_w2c`` (mm)."""
    entry = {"cam_K": [float(v) for v in intrinsics.K.reshape(-1)], "depth_scale": float(depth_scale_mm)}
    if T_camera_world is not None:
        T = np.asarray(T_camera_world, dtype=np.float64)
        entry["cam_R_w2c"] = [float(v) for v in T[:3, :3].reshape(-1)]
        entry["cam_t_w2c"] = [float(v) * MM_PER_M for v in T[:3, 3]]
    return entry


def T_camera_world_from_json(entry: dict, where: str) -> np.ndarray | None:
    """(4, 4) metres from a ``scene_camera.json`` entry's ``cam_R_w2c`` / ``cam_t_w2c``; None when it has none
    (datasets written before the pose was recorded). ``where`` names the file and key for errors."""
    if "cam_R_w2c" not in entry and "cam_t_w2c" not in entry:
        return None
    return _T_from_R_t_mm(entry, "cam_R_w2c", "cam_t_w2c", where)


def depth_to_png_units(depth_m: np.ndarray, depth_scale_mm: float) -> np.ndarray:
    """(h, w) float metres (0 = no data) -> (h, w) uint16 in units of ``depth_scale_mm``; too far raises."""
    units = np.round(np.asarray(depth_m, dtype=np.float64) * MM_PER_M / depth_scale_mm)
    if np.any(units > _UINT16_MAX) or np.any(units < 0) or not np.all(np.isfinite(units)):
        raise ValueError(
            f"depth_m: values must be finite and in [0, {_UINT16_MAX * depth_scale_mm / MM_PER_M:.3f}] m for "
            f"depth_scale {depth_scale_mm} mm, got [{np.nanmin(depth_m):.3f}, {np.nanmax(depth_m):.3f}] m"
        )
    return units.astype(np.uint16)


def encode_png(image: np.ndarray, what: str) -> bytes:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise ValueError(f"{what}: cv2 could not encode an image of shape {image.shape} dtype {image.dtype} as PNG")
    return buf.tobytes()


def _read_png(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ConfigError(f"{path}: missing or not a readable PNG")
    return image


def _load_json(path: Path) -> dict:
    if not path.exists():
        return {}
    data = read_json(path, "BOP scene file")
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a JSON object keyed by image id, got {type(data).__name__}")
    return data


# ------------------------------------------------------------------------------------------------------ the writer
class BopWriter:
    """Writes items into a BOP dataset at ``root`` (``split`` e.g. ``train_pbr``), models on construction."""

    def __init__(self, root: str | Path, models: Sequence[ObjectModel], split: str = "train_pbr") -> None:
        if not split or "/" in split:
            raise ValueError(f"split: expected a folder name such as 'train_pbr', got {split!r}")
        self.root = Path(root)
        self.split = split
        self.models = {m.obj_id: m for m in models}
        self.model_files = self._write_models()
        self.files_written = len(self.model_files)  # a count, not a list: a million-item run must not grow memory

    def _write_models(self) -> list[Path]:
        info, paths = {}, []
        for obj_id, model in sorted(self.models.items()):
            info[str(obj_id)] = model.models_info_entry()
            mesh_mm = model.mesh.copy()
            mesh_mm.apply_scale(MM_PER_M)
            payload = mesh_mm.export(file_type="ply")
            paths.append(write_bytes_atomic(self.root / "models" / f"obj_{obj_id:06d}.ply", payload))
        paths.append(write_json_atomic(self.root / "models" / "models_info.json", info))
        return paths

    def scene_dir(self, scene_id: int) -> Path:
        return self.root / self.split / f"{scene_id:06d}"

    def write(
        self,
        ann: ImageAnnotation,
        rgb: np.ndarray,
        depth_m: np.ndarray | None = None,
        depth_true_m: np.ndarray | None = None,
    ) -> list[Path]:
        """Writes one image and its ground truth; returns the paths written. ``depth_true_m``: the exact depth
        beside a sensor's ``depth_m`` (``depth_true/``), same units and scale."""
        check_item(ann, rgb, depth_m)
        check_item(ann, rgb, depth_true_m)
        unknown = sorted({i.obj_id for i in ann.instances} - set(self.models))
        if unknown:
            raise ValueError(f"obj_id {unknown} not among the writer's models {sorted(self.models)}")
        if not ann.depth_scale_mm > 0:
            raise ValueError(f"depth_scale_mm: expected > 0, got {ann.depth_scale_mm}")
        sdir, im = self.scene_dir(ann.scene_id), f"{ann.image_id:06d}"
        # Convert and check everything before the first write, so a bad item leaves the dataset untouched.
        depth_pngs = {
            folder: encode_png(depth_to_png_units(d, ann.depth_scale_mm), "depth")
            for folder, d in (("depth", depth_m), ("depth_true", depth_true_m))
            if d is not None
        }
        paths = [write_bytes_atomic(sdir / "rgb" / f"{im}.png", encode_png(np.asarray(rgb)[..., ::-1], "rgb"))]
        for folder, png in depth_pngs.items():
            paths.append(write_bytes_atomic(sdir / folder / f"{im}.png", png))
        for g, inst in enumerate(ann.instances):
            name = f"{im}_{g:06d}.png"
            visib = np.asarray(inst.mask_visib, dtype=bool)
            full = visib if inst.mask_full is None else np.asarray(inst.mask_full, dtype=bool)
            paths.append(write_bytes_atomic(sdir / "mask" / name, encode_png(full.astype(np.uint8) * 255, "mask")))
            paths.append(
                write_bytes_atomic(sdir / "mask_visib" / name, encode_png(visib.astype(np.uint8) * 255, "mask"))
            )
        record = {
            "scene_gt_info": [gt_info_as_json(i) for i in ann.instances],
            "scene_camera": camera_as_json(ann.intrinsics, ann.depth_scale_mm, ann.T_camera_world),
            "scene_gt": [gt_as_json(i) for i in ann.instances],
        }
        paths.append(write_json_atomic(sdir / ITEMS_DIR / f"{im}.json", record, None))  # last: commits the image
        self.files_written += len(paths)
        return paths

    def item_files(self, scene_id: int, image_id: int, n_instances: int, true_depth: bool = False) -> list[Path]:
        """The image files ``write`` makes for an image with ``n_instances`` instances (its entries in the scene
        JSONs aside): rgb, depth (and depth_true), and a full and a visible mask per instance."""
        sdir, im = self.scene_dir(scene_id), f"{image_id:06d}"
        paths = [sdir / "rgb" / f"{im}.png", sdir / "depth" / f"{im}.png"]
        if true_depth:
            paths.append(sdir / "depth_true" / f"{im}.png")
        for g in range(n_instances):
            paths += [sdir / "mask" / f"{im}_{g:06d}.png", sdir / "mask_visib" / f"{im}_{g:06d}.png"]
        return paths

    def instance_counts(self, scene_id: int) -> dict[int, int]:
        """image id -> number of instances, for every image of the scene written: with a ``scene_gt.json`` entry or
        a record not yet flushed."""
        sdir = self.scene_dir(scene_id)
        gt = _load_json(sdir / "scene_gt.json")
        gt.update({str(int(k)): r["scene_gt"] for k, r in _item_records(sdir).items()})
        return {int(k): len(v) if isinstance(v, list) else 0 for k, v in gt.items()}

    def flush(self) -> list[Path]:
        """Merges every item record of the split into its scene JSONs; returns the scene files written."""
        return flush_split(self.root, self.split)

    def finish(self) -> list[Path]:
        """Flushes; returns the scene files written."""
        paths = self.flush()
        log.info("BOP dataset: %d files written under %s", self.files_written + len(paths), self.root)
        return paths


def flush_split(root: str | Path, split: str) -> list[Path]:
    """Merges the item records (``gt_items/``) of every scene of ``root/split`` into the scene's JSONs, atomically,
    ``scene_gt.json`` last, then deletes them; returns the scene files written. A record replaces the scene files'
    entry of its image (an image written again)."""
    paths: list[Path] = []
    for items_dir in sorted(Path(root, split).glob(f"*/{ITEMS_DIR}")):
        sdir = items_dir.parent
        records = _item_records(sdir)
        for fname, field in SCENE_FILES:
            data = _load_json(sdir / fname)
            data.update({str(int(k)): r[field] for k, r in records.items()})
            paths.append(write_json_atomic(sdir / fname, dict(sorted(data.items(), key=lambda kv: int(kv[0])))))
        for name in records:
            (items_dir / f"{name}.json").unlink()
        if not any(items_dir.iterdir()):  # a killed write's temporary stays for the generator's clean-up
            items_dir.rmdir()
    return paths


def _item_records(sdir: Path) -> dict[str, dict]:
    """Image name (``IIIIII``) -> the item record of every image of scene folder ``sdir`` not yet flushed."""
    records = {}
    for path in sorted((sdir / ITEMS_DIR).glob("*.json")):
        record = read_json(path, "BOP item record")
        complete = isinstance(record, dict) and all(field in record for _, field in SCENE_FILES)
        if not complete or not path.stem.isdigit():
            fields = ", ".join(field for _, field in SCENE_FILES)
            raise ConfigError(f"{path}: expected a BOP item record (a JSON object with {fields}) named by image id")
        records[path.stem] = record
    return records


# ------------------------------------------------------------------------------------------------------ the reader
def load_bop_item(
    root: str | Path, scene_id: int, image_id: int, split: str = "train_pbr"
) -> tuple[ImageAnnotation, np.ndarray, np.ndarray | None]:
    """Reads one image back: ``(annotation, rgb (h, w, 3) uint8, depth_m (h, w) float32 metres or None)``."""
    sdir = Path(root) / split / f"{scene_id:06d}"
    im, key = f"{image_id:06d}", str(image_id)
    rgb = _read_png(sdir / "rgb" / f"{im}.png")[..., ::-1].copy()
    h, w = rgb.shape[:2]
    cams, gts, infos = (_load_json(sdir / f) for f in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json"))
    for fname, data in (("scene_camera.json", cams), ("scene_gt.json", gts)):
        if key not in data:
            raise ConfigError(f"{sdir / fname}: no entry for image {key} (have {sorted(data, key=int)[:10]}...)")
    cam = cams[key]
    try:
        intrinsics = CameraIntrinsics.from_K(np.asarray(cam["cam_K"], dtype=float), w, h)
        depth_scale_mm = float(cam.get("depth_scale", 1.0))
    except (KeyError, ValueError, TypeError) as err:
        raise ConfigError(f"{sdir / 'scene_camera.json'}[{key}]: expected cam_K (9 numbers): {err}") from err
    depth_m = _read_depth(sdir / "depth" / f"{im}.png", depth_scale_mm)
    info_list = infos.get(key, [])
    instances = []
    for g, entry in enumerate(gts[key]):
        where = f"{sdir / 'scene_gt.json'}[{key}][{g}]"
        name = f"{im}_{g:06d}.png"
        visib = _read_png(sdir / "mask_visib" / name) > 0
        full_path = sdir / "mask" / name
        full = _read_png(full_path) > 0 if full_path.exists() else None
        info = info_list[g] if g < len(info_list) else {}
        px_visib = int(info.get("px_count_visib", np.count_nonzero(visib)))
        px_all = int(info.get("px_count_all", np.count_nonzero(full) if full is not None else px_visib))
        instances.append(
            InstanceAnnotation(
                obj_id=int(entry["obj_id"]),
                inst_id=g,
                T_camera_obj=T_from_gt_json(entry, where),
                mask_visib=visib,
                mask_full=full,
                bbox_visib=tuple(int(v) for v in info.get("bbox_visib", (-1, -1, -1, -1))),
                bbox_obj=tuple(int(v) for v in info.get("bbox_obj", (-1, -1, -1, -1))),
                px_count_all=px_all,
                px_count_visib=px_visib,
                visib_fract=float(info.get("visib_fract", px_visib / px_all if px_all else 0.0)),
                px_count_valid=int(info.get("px_count_valid", px_all)),
            )
        )
    T_camera_world = T_camera_world_from_json(cam, f"{sdir / 'scene_camera.json'}[{key}]")
    ann = ImageAnnotation(
        image_id, intrinsics, tuple(instances), scene_id=scene_id, depth_scale_mm=depth_scale_mm,
        T_camera_world=T_camera_world,
    )  # fmt: skip
    return ann, rgb, depth_m


def load_bop_true_depth(root: str | Path, ann: ImageAnnotation, split: str = "train_pbr") -> np.ndarray | None:
    """The exact depth (h, w) float32 metres of an image whose ``depth/`` is a sensor's (``depth_true/``), None
    when the dataset has none (its ``depth/`` is then exact)."""
    sdir = Path(root) / split / f"{ann.scene_id:06d}"
    return _read_depth(sdir / "depth_true" / f"{ann.image_id:06d}.png", ann.depth_scale_mm)


def _read_depth(path: Path, depth_scale_mm: float) -> np.ndarray | None:
    if not path.exists():
        return None
    return (_read_png(path).astype(np.float64) * depth_scale_mm / MM_PER_M).astype(np.float32)
