"""Reader for the published SyGRID labels (``gt.pickle``), converted to ``ImageAnnotation``s in metres.

The file holds, per image (a dict keyed by image name or id, or a list in image order), a dict::

    cam_K    9 numbers, row-major 3x3 intrinsics
    objects  list of {obj_id, inst_id, R (9, row-major), t (3, mm), bbox [x, y, w, h] px,
                      3d-bbox (8 corners, camera frame, mm), segmentation [polygon, ...] of [x, y] points,
                      mask_visib (visible fraction in percent)}

Visible masks are rasterised from the polygons; there is no amodal mask (``mask_full`` is None), so
``px_count_all`` is the visible pixel count divided by the visible fraction, and ``bbox_obj`` is the box of the
projected 3-D box corners, clipped to the image.

Pickle runs code while loading. ``safe_load_pickle`` uses an unpickler whose ``find_class`` allows only the few
globals plain data needs (builtin containers and numbers, and the numpy array/dtype/scalar reconstructors) and
refuses everything else with a ``ConfigError`` before anything is called.
"""

from __future__ import annotations

import io
import logging
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from sygrid.annotations import ImageAnnotation, InstanceAnnotation, mask_bbox, polygon_to_mask
from sygrid.camera import CameraIntrinsics, project_points
from sygrid.errors import ConfigError

log = logging.getLogger(__name__)

MM_PER_M = 1000.0

_SAFE_BUILTINS = frozenset(
    {"dict", "list", "tuple", "set", "frozenset", "int", "float", "complex", "str", "bytes", "bytearray", "bool"}
)
# numpy arrays and scalars: _reconstruct only builds an ndarray of the (allowed) ndarray type; the element data
# of object arrays is itself unpickled through this same restricted unpickler.
_SAFE_GLOBALS = frozenset(
    {
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "scalar"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "scalar"),
    }
)


def _latin1_encode(text: str, encoding: str = "utf-8") -> bytes:
    """``_codecs.encode`` limited to the latin-1 round trip pickle uses (no other codec is looked up)."""
    if encoding.replace("_", "-").lower() not in ("latin1", "latin-1"):
        raise pickle.UnpicklingError(f"refused codec {encoding!r} in _codecs.encode; only latin1 is allowed")
    return text.encode("latin-1")


class _RestrictedUnpickler(pickle.Unpickler):
    def __init__(self, file: io.BufferedIOBase, source: str) -> None:
        super().__init__(file)
        self._source = source

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) == ("_codecs", "encode"):
            return _latin1_encode  # protocol-2 pickles store bytes as _codecs.encode(str, "latin1")
        if (module == "builtins" and name in _SAFE_BUILTINS) or (module, name) in _SAFE_GLOBALS:
            return super().find_class(module, name)
        raise ConfigError(
            f"{self._source}: refused to load the global '{module}.{name}'; a label pickle may only hold plain "
            "containers, numbers, strings and numpy arrays"
        )


def safe_load_pickle(path: str | Path) -> Any:
    """Loads a data-only pickle; any other global (functions, classes, os.system ...) raises ConfigError."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            return _RestrictedUnpickler(f, str(path)).load()
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError) as err:
        if isinstance(err, ConfigError):
            raise
        raise ConfigError(f"{path}: not a readable pickle ({type(err).__name__}: {err})") from err


def _numbers(value: Any, count: int | None, where: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (ValueError, TypeError) as err:
        raise ConfigError(f"{where}: expected numbers, got {type(value).__name__}") from err
    if count is not None and arr.size != count:
        raise ConfigError(f"{where}: expected {count} numbers, got {arr.size}")
    return arr


def _field(entry: dict, key: str, where: str) -> Any:
    if not isinstance(entry, dict) or key not in entry:
        raise ConfigError(f"{where}: missing field '{key}'")
    return entry[key]


def _image_id(key: Any, index: int) -> int:
    if isinstance(key, (int, np.integer)):
        return int(key)
    stem = Path(str(key)).stem
    return int(stem) if stem.isdigit() else index


def image_from_entry(entry: dict, image_id: int, width: int, height: int, where: str) -> ImageAnnotation:
    """One image's dict of the published format -> ``ImageAnnotation`` (metres, rasterised visible masks)."""
    K = _numbers(_field(entry, "cam_K", where), 9, f"{where}.cam_K").reshape(3, 3)
    intrinsics = CameraIntrinsics.from_K(K, width, height)
    objects = _field(entry, "objects", where)
    if not isinstance(objects, (list, tuple)):
        raise ConfigError(f"{where}.objects: expected a list, got {type(objects).__name__}")
    instances = []
    for k, obj in enumerate(objects):
        w = f"{where}.objects[{k}]"
        T = np.eye(4)
        T[:3, :3] = _numbers(_field(obj, "R", w), 9, f"{w}.R").reshape(3, 3)
        T[:3, 3] = _numbers(_field(obj, "t", w), 3, f"{w}.t") / MM_PER_M
        polygons = [
            _numbers(p, None, f"{w}.segmentation[{j}]").reshape(-1, 2)
            for j, p in enumerate(_field(obj, "segmentation", w))
        ]
        visib = polygon_to_mask(polygons, height, width)
        visib_fract = float(_field(obj, "mask_visib", w)) / 100.0
        if not 0.0 <= visib_fract <= 1.0:
            raise ConfigError(f"{w}.mask_visib: expected a percentage in [0, 100], got {visib_fract * 100.0}")
        px_visib = int(np.count_nonzero(visib))
        corners_m = _numbers(_field(obj, "3d-bbox", w), 24, f"{w}.3d-bbox").reshape(8, 3) / MM_PER_M
        bbox_obj = _projected_bbox(K, corners_m, width, height)
        bbox = tuple(round(v) for v in _numbers(_field(obj, "bbox", w), 4, f"{w}.bbox"))
        instances.append(
            InstanceAnnotation(
                obj_id=int(_field(obj, "obj_id", w)),
                inst_id=int(obj.get("inst_id", k)),
                T_camera_obj=T,
                mask_visib=visib,
                mask_full=None,
                bbox_visib=bbox if px_visib else mask_bbox(visib),
                bbox_obj=bbox_obj,
                px_count_all=round(px_visib / visib_fract) if visib_fract > 0 else px_visib,
                px_count_visib=px_visib,
                visib_fract=visib_fract,
                px_count_valid=round(px_visib / visib_fract) if visib_fract > 0 else px_visib,
            )
        )
    return ImageAnnotation(image_id=image_id, intrinsics=intrinsics, instances=tuple(instances))


def _projected_bbox(K: np.ndarray, corners_m: np.ndarray, width: int, height: int) -> tuple[int, int, int, int]:
    """``(x, y, w, h)`` of projected camera-frame points clipped to the image; -1s if none is in front."""
    front = corners_m[corners_m[:, 2] > 0]
    if len(front) == 0:
        return (-1, -1, -1, -1)
    uv = project_points(K, front)
    x0, y0 = np.clip(np.floor(uv.min(0)), 0, [width - 1, height - 1]).astype(int)
    x1, y1 = np.clip(np.ceil(uv.max(0)), 0, [width - 1, height - 1]).astype(int)
    return (int(x0), int(y0), int(x1 - x0 + 1), int(y1 - y0 + 1))


def pickle_entries(path: str | Path) -> list[tuple[Any, int, dict, str]]:
    """The images of ``gt.pickle`` in file order: ``(key, image_id, entry, where)`` with the key as in the file
    (list index for a list), the image id (the key when it is an integer or a numeric file name such as
    ``"000042.png"``, else the position in the file), the image's dict and ``where`` (the file and key, for errors).
    """
    path = Path(path)
    data = safe_load_pickle(path)
    if isinstance(data, dict):
        items = list(data.items())
    elif isinstance(data, (list, tuple)):
        items = list(enumerate(data))
    else:
        raise ConfigError(f"{path}: expected a dict or list of per-image dicts, got {type(data).__name__}")
    return [(key, _image_id(key, index), entry, f"{path}[{key!r}]") for index, (key, entry) in enumerate(items)]


def load_sygrid_pickle(path: str | Path, width: int, height: int) -> dict[Any, ImageAnnotation]:
    """Reads ``gt.pickle``: ``{image key: ImageAnnotation}`` (key as in the file, list index for a list).

    ``width`` / ``height``: the image size in pixels (the labels do not store it). Image ids as ``pickle_entries``.
    """
    if width <= 0 or height <= 0:
        raise ValueError(f"width, height: expected positive pixel counts, got {width} x {height}")
    out = {key: image_from_entry(entry, image_id, width, height, where)
           for key, image_id, entry, where in pickle_entries(path)}  # fmt: skip
    log.info("read %d images from %s", len(out), path)
    return out
