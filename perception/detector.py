"""YOLO instance segmentation at run time: numpy + onnxruntime, for our models and ultralytics' alike.

The model contract is the ultralytics YOLOv8-seg ONNX layout:

- input: one image tensor ``[1, 3, H, W]`` float (RGB, 0..1), fixed or dynamic ``H, W``;
- ``output0``: ``[1, 4 + nc + nm, A]``, per anchor the box ``cx, cy, w, h`` in input pixels, ``nc`` per-class scores
  (already sigmoided, no objectness) and ``nm`` (32) mask coefficients;
- ``output1``: the mask prototypes ``[1, nm, H/s, W/s]`` covering the input (``s`` = 4 in ultralytics' models, 2 or 4
  in ours). A detection-only model has no ``output1`` and an ``output0`` of ``[1, 4 + nc, A]``.

Class names come from the ONNX ``metadata_props`` (ultralytics writes ``names`` as a python dict string
``"{0: 'hex_nut', 1: 'washer'}"``, ``imgsz`` as ``"[640, 640]"`` and ``stride``); our exporter adds ``obj_ids``
(``"[1, 3]"``). Each class maps to a BOP obj_id: an explicit ``class_obj_ids`` argument wins, then the ``obj_ids``
metadata, then the built-in part of the same name, then ``class index + 1`` (with a warning).

Pre-processing is ultralytics' letterbox (``sygrid.letterbox``: keep aspect ratio, pad with grey 114 around the
centred image; a model with a fixed input is padded to that size, a dynamic one to the next multiple of the stride);
post-processing (confidence filtering, class-aware NMS, masks in image pixels) is ``sygrid.detection_decode``, the
same code that validates a model in training.
"""

from __future__ import annotations

import ast
import logging
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import onnxruntime as ort
from onnxruntime.capi import onnxruntime_pybind11_state as ort_state

from perception.providers import session_providers
from perception.results import Detection
from perception.tiling import ViewSettings, merge_tiles, tile_layout
from sygrid.detection_decode import postprocess
from sygrid.errors import ModelError
from sygrid.letterbox import Letterbox, letterbox, letterbox_at_scale, letterbox_geometry

log = logging.getLogger(__name__)

DEFAULT_INPUT_SIZE = 640  # for a model with a dynamic input and no ``imgsz`` metadata
DEFAULT_STRIDE = 32

# Everything onnxruntime raises on a bad model or a failing run (its exceptions share no base class but Exception).
_ORT_ERRORS = (
    ort_state.Fail,
    ort_state.InvalidArgument,
    ort_state.InvalidGraph,
    ort_state.InvalidProtobuf,
    ort_state.NoSuchFile,
    ort_state.NotImplemented,
    ort_state.RuntimeException,
    ort_state.EPFail,
    RuntimeError,
)


def to_blob(image: np.ndarray, dtype: type = np.float32) -> np.ndarray:
    """(h, w, 3) uint8 -> (1, 3, h, w) C-contiguous in [0, 1] (cheaper than cv2.dnn.blobFromImage)."""
    blob = np.empty((1, 3, *image.shape[:2]), dtype=dtype)
    np.multiply(image.transpose(2, 0, 1), dtype(1.0 / 255.0), out=blob[0], casting="unsafe")
    return blob


def _to_frame(detection: Detection, offset_xy: tuple[int, int], frame_hw: tuple[int, int]) -> Detection:
    """A detection made in a region of the frame, in the frame's pixels."""
    x0, y0 = offset_xy
    mask = None
    if detection.mask is not None:
        mask = np.zeros(frame_hw, dtype=bool)
        h, w = detection.mask.shape
        mask[y0 : y0 + h, x0 : x0 + w] = detection.mask
    box = detection.bbox_xyxy + np.array([x0, y0, x0, y0], dtype=np.float64)
    return Detection(detection.class_index, detection.obj_id, detection.score, box, mask)


# ---------------------------------------------------------------------------------------------------- metadata
def _literal(value: str, key: str, path: Path) -> object:
    try:
        return ast.literal_eval(value)
    except (ValueError, SyntaxError) as err:
        raise ModelError(f"{path}: metadata '{key}' is not a python/JSON literal: {value[:200]!r}") from err


def parse_names(value: str, path: Path) -> list[str]:
    """Ultralytics' ``names`` metadata (``"{0: 'a', 1: 'b'}"``, or a list) -> class names in index order."""
    names = _literal(value, "names", path)
    if isinstance(names, dict) and sorted(names) == list(range(len(names))):
        return [str(names[i]) for i in range(len(names))]
    if isinstance(names, (list, tuple)):
        return [str(n) for n in names]
    raise ModelError(f"{path}: metadata 'names' must map class indices 0..n-1 to names, got {value[:200]!r}")


def parse_obj_ids(value: str, path: Path) -> list[int]:
    """``obj_ids`` metadata (``"[1, 3]"`` or ``"{0: 1, 1: 3}"``) -> the BOP obj_id of each class index."""
    ids = _literal(value, "obj_ids", path)
    if isinstance(ids, dict) and sorted(ids) == list(range(len(ids))):
        ids = [ids[i] for i in range(len(ids))]
    if isinstance(ids, (list, tuple)) and all(isinstance(i, int) for i in ids):
        return [int(i) for i in ids]
    raise ModelError(f"{path}: metadata 'obj_ids' must list one integer obj_id per class, got {value[:200]!r}")


def _builtin_obj_ids(names: Sequence[str]) -> list[int] | None:
    from sygrid.objects.parts import BUILTIN_PARTS, builtin_part  # only when a model needs it: builds meshes

    if names and all(n in BUILTIN_PARTS for n in names):
        return [builtin_part(n).obj_id for n in names]
    return None


def _dim(shape: Sequence, k: int) -> int | None:
    """A static dimension, or None where the model leaves it symbolic."""
    return shape[k] if k < len(shape) and isinstance(shape[k], int) and shape[k] > 0 else None


# ---------------------------------------------------------------------------------------------------- detector
class YoloSegDetector:
    """A YOLO(v8)-seg or detection ONNX model on onnxruntime (CPU, or CUDA where installed).

    Args:
        onnx_path: the ``.onnx`` file.
        class_obj_ids: BOP obj_id of each class index; None reads them from the model (see the module docstring).
        conf_threshold: minimum class score of a detection, in [0, 1).
        iou_threshold: NMS IoU above which the lower-scored box of the same class is dropped, in (0, 1].
        input_size: network input ``(height, width)`` or one int for a square; only for a model with a dynamic
            input (a fixed-input model must be given None or its own size). None: the ``imgsz`` metadata, else 640.
        num_threads: onnxruntime intra-op threads.
        max_detections: most detections returned per image.
        providers: onnxruntime execution providers, ``"auto"`` (CUDA when offered), ``"cpu"`` or ``"cuda"``
            (``perception.providers``).
        view: where and at what scale the detector looks (``perception.tiling.ViewSettings``); None: the plain
            behaviour, one piece at the frame's scale. A scale or tiles need a model with a dynamic input.

    Raises:
        ModelError: the file is missing or not a loadable ONNX model, its input is not one ``[1, 3, H, W]`` image,
            its outputs match neither supported layout, or its metadata/class mapping is inconsistent.
        ValueError: a threshold or size out of range.
    """

    def __init__(
        self,
        onnx_path: str | Path,
        class_obj_ids: Sequence[int] | None = None,
        conf_threshold: float = 0.25,
        iou_threshold: float = 0.6,
        input_size: int | tuple[int, int] | None = None,
        num_threads: int = 2,
        max_detections: int = 300,
        view: ViewSettings | None = None,
        providers: str = "auto",
    ) -> None:
        if not 0.0 <= conf_threshold < 1.0:
            raise ValueError(f"conf_threshold must be in [0, 1), got {conf_threshold}")
        if not 0.0 < iou_threshold <= 1.0:
            raise ValueError(f"iou_threshold must be in (0, 1], got {iou_threshold}")
        if int(num_threads) < 1:
            raise ValueError(f"num_threads must be >= 1, got {num_threads}")
        if int(max_detections) < 1:
            raise ValueError(f"max_detections must be >= 1, got {max_detections}")
        self.path = Path(onnx_path)
        self.conf_threshold = float(conf_threshold)
        self.iou_threshold = float(iou_threshold)
        self.max_detections = int(max_detections)
        self.session = self._open_session(self.path, int(num_threads), session_providers(providers))
        self.metadata: dict[str, str] = dict(self.session.get_modelmeta().custom_metadata_map)
        self._check_input(input_size)
        self.view = view or ViewSettings()
        if not self.view.default and not self.dynamic_input:
            raise ValueError(
                f"view {self.view}: a scale or tiles need a model with a dynamic input; {self.path} has a fixed "
                f"{self.input_hw[0]}x{self.input_hw[1]} input"
            )
        self._check_outputs()
        self.class_names, self.class_obj_ids, self.obj_id_source = self._class_mapping(class_obj_ids)
        self.last_timings_ms: dict[str, float] = {}

    # ------------------------------------------------------------------------------------------- loading
    @staticmethod
    def _open_session(path: Path, num_threads: int, providers: list[str]) -> ort.InferenceSession:
        if not path.is_file():
            raise ModelError(f"{path}: ONNX model file not found" + (" (it is a directory)" if path.is_dir() else ""))
        options = ort.SessionOptions()
        options.intra_op_num_threads = num_threads
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        options.log_severity_level = 3  # errors only: a model's harmless warnings must not flood the demo's log
        # Worker threads sleep when a run ends instead of spinning: spinning threads take the CPU from the mask
        # assembly, the next session and the simulator on a small machine.
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        try:
            return ort.InferenceSession(str(path), sess_options=options, providers=providers)
        except _ORT_ERRORS as err:
            raise ModelError(f"{path}: not a loadable ONNX model ({type(err).__name__}: {err})") from err

    def _check_input(self, input_size: int | tuple[int, int] | None) -> None:
        inputs = self.session.get_inputs()
        described = ", ".join(f"{i.name} {i.shape} {i.type}" for i in inputs)
        if len(inputs) != 1 or len(inputs[0].shape) != 4 or _dim(inputs[0].shape, 1) not in (3, None):
            raise ModelError(f"{self.path}: expected one image input [1, 3, H, W], found {described}")
        if inputs[0].type not in ("tensor(float)", "tensor(float16)"):
            raise ModelError(f"{self.path}: expected a float or float16 image input, found {described}")
        if _dim(inputs[0].shape, 0) not in (1, None):
            raise ModelError(f"{self.path}: expected batch size 1 in the image input, found {described}")
        self.input_name = inputs[0].name
        self.input_dtype = np.float16 if inputs[0].type == "tensor(float16)" else np.float32
        self.stride = DEFAULT_STRIDE
        if "stride" in self.metadata:
            stride = _literal(self.metadata["stride"], "stride", self.path)
            if not isinstance(stride, (int, float)) or int(stride) < 1:
                raise ModelError(f"{self.path}: metadata 'stride' must be a positive integer, got {stride!r}")
            self.stride = int(stride)
        requested = None
        if input_size is not None:
            requested = (int(input_size), int(input_size)) if np.isscalar(input_size) else tuple(map(int, input_size))
            if len(requested) != 2 or min(requested) < 1:
                raise ValueError(f"input_size must be an int or (height, width), got {input_size!r}")
        fixed_h, fixed_w = _dim(inputs[0].shape, 2), _dim(inputs[0].shape, 3)
        if fixed_h is not None and fixed_w is not None:
            if requested is not None and requested != (fixed_h, fixed_w):
                raise ValueError(
                    f"input_size {requested} differs from the fixed input {fixed_h}x{fixed_w} of {self.path}; "
                    "pass None, or export the model with a dynamic input"
                )
            self.input_hw, self.dynamic_input = (fixed_h, fixed_w), False
            return
        if requested is None and "imgsz" in self.metadata:
            size = _literal(self.metadata["imgsz"], "imgsz", self.path)
            if isinstance(size, int):
                size = [size, size]
            if not isinstance(size, (list, tuple)) or len(size) != 2 or not all(isinstance(v, int) for v in size):
                raise ModelError(f"{self.path}: metadata 'imgsz' must be [height, width] or one int, got {size!r}")
            requested = (size[0], size[1])
        self.input_hw, self.dynamic_input = requested or (DEFAULT_INPUT_SIZE, DEFAULT_INPUT_SIZE), True

    def _layout_error(self, found: str) -> ModelError:
        return ModelError(
            f"{self.path}: outputs match no supported layout; found {found}; expected 'output0' [1, 4+nc+nm, A] "
            "(box cx, cy, w, h, nc class scores, nm mask coefficients) with 'output1' mask prototypes "
            "[1, nm, H/s, W/s], or a detection-only 'output0' [1, 4+nc, A]"
        )

    def _check_outputs(self) -> None:
        outputs = self.session.get_outputs()
        found = ", ".join(f"{o.name} {o.shape}" for o in outputs) or "no outputs"
        by_name = {o.name: o for o in outputs}
        if "output0" in by_name:
            pred = by_name["output0"]
            protos = by_name.get("output1")
        else:
            rank3 = [o for o in outputs if len(o.shape) == 3]
            rank4 = [o for o in outputs if len(o.shape) == 4]
            if len(rank3) != 1 or len(rank4) > 1:
                raise self._layout_error(found)
            pred, protos = rank3[0], (rank4[0] if rank4 else None)
        if len(pred.shape) != 3 or (protos is not None and len(protos.shape) != 4):
            raise self._layout_error(found)
        if _dim(pred.shape, 0) not in (1, None) or (protos is not None and _dim(protos.shape, 0) not in (1, None)):
            raise self._layout_error(found)
        self.output_names = [pred.name] + ([protos.name] if protos is not None else [])
        self.has_masks = protos is not None
        self.num_mask_coefficients = _dim(protos.shape, 1) if protos is not None else 0
        channels = _dim(pred.shape, 1)
        self.num_classes = None
        if channels is not None and (protos is None or self.num_mask_coefficients is not None):
            self.num_classes = channels - 4 - (self.num_mask_coefficients or 0)
            if self.num_classes < 1:
                raise self._layout_error(found)
        self._found_outputs = found

    def _class_mapping(self, class_obj_ids: Sequence[int] | None) -> tuple[list[str], list[int], str]:
        names = parse_names(self.metadata["names"], self.path) if "names" in self.metadata else None
        sizes = {
            "output0": self.num_classes,
            "metadata 'names'": len(names) if names is not None else None,
            "class_obj_ids": len(class_obj_ids) if class_obj_ids is not None else None,
        }
        known = {k: v for k, v in sizes.items() if v is not None}
        if len(set(known.values())) > 1:
            raise ModelError(f"{self.path}: the number of classes disagrees: {known} ({self._found_outputs})")
        if not known:
            raise ModelError(
                f"{self.path}: cannot tell the number of classes (symbolic output0 channels, no 'names' metadata); "
                "pass class_obj_ids"
            )
        nc = next(iter(known.values()))
        if self.num_classes is None:
            self.num_classes = nc
        names = names or [f"class_{i}" for i in range(nc)]
        if class_obj_ids is not None:
            return names, [int(i) for i in class_obj_ids], "class_obj_ids argument"
        if "obj_ids" in self.metadata:
            ids = parse_obj_ids(self.metadata["obj_ids"], self.path)
            if len(ids) != nc:
                raise ModelError(f"{self.path}: metadata 'obj_ids' lists {len(ids)} ids for {nc} classes")
            return names, ids, "metadata 'obj_ids'"
        builtin = _builtin_obj_ids(names)
        if builtin is not None:
            return names, builtin, "built-in part names"
        log.warning(
            "%s: no obj_ids in the model and class names %s are not built-in parts: using obj_id = class index + 1; "
            "pass class_obj_ids to set them",
            self.path,
            names,
        )
        return names, list(range(1, nc + 1)), "class index + 1"

    # ------------------------------------------------------------------------------------------- running
    def _run(self, blob: np.ndarray) -> list[np.ndarray]:
        try:
            return self.session.run(self.output_names, {self.input_name: blob})
        except _ORT_ERRORS as err:
            raise ModelError(
                f"{self.path}: inference failed on an input of shape {blob.shape} ({type(err).__name__}: {err})"
            ) from err

    def _check_run_outputs(self, outputs: list[np.ndarray]) -> None:
        pred = outputs[0]
        nm = outputs[1].shape[1] if self.has_masks and outputs[1].ndim == 4 else 0
        expected_c = 4 + self.num_classes + nm
        ok = pred.ndim == 3 and pred.shape[0] == 1 and pred.shape[1] == expected_c
        if self.has_masks:
            protos = outputs[1]
            ok = ok and protos.ndim == 4 and protos.shape[0] == 1 and nm > 0
        if not ok:
            shapes = ", ".join(f"{n} {list(o.shape)}" for n, o in zip(self.output_names, outputs, strict=True))
            raise self._layout_error(
                f"{shapes} at run time (expected {expected_c} channels for {self.num_classes} classes)"
            )

    def detect(self, rgb: np.ndarray, roi_xyxy: Sequence[int] | None = None) -> list[Detection]:
        """Detections in an RGB frame, highest score first; an empty list when there is nothing to detect.

        Args:
            rgb: (H, W, 3) uint8 RGB image.
            roi_xyxy: ``[x0, y0, x1, y1]`` integer pixels: look only there (a bin's region of the image). None: the
                whole frame. The region is seen as ``view`` says (``perception.tiling.ViewSettings``): by default
                at the scale the whole frame would be seen at (so ``input_size`` keeps its meaning and the parts
                their size in pixels, at the region's share of the cost; a fixed input is filled by the region),
                else at ``view.scale``, in one piece or in tiles.

        Returns:
            ``perception.results.Detection`` per kept box, with ``bbox_xyxy`` in image pixels (clipped to the image,
            or to the region) and, for a segmentation model, the (H, W) bool mask in image pixels.

        Raises:
            ValueError: ``rgb`` is not an (H, W, 3) uint8 array, or the region is not a non-empty box in the image.
            ModelError: inference fails or the outputs do not have the layout the model declared.
        """
        if not isinstance(rgb, np.ndarray) or rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            what = f"{rgb.dtype} array of shape {rgb.shape}" if isinstance(rgb, np.ndarray) else type(rgb).__name__
            raise ValueError(f"rgb: expected a uint8 (H, W, 3) RGB image, got a {what}")
        if rgb.shape[0] < 1 or rgb.shape[1] < 1:
            raise ValueError(f"rgb: expected a non-empty image, got shape {rgb.shape}")
        region = self._region(rgb.shape[:2], roi_xyxy)
        timings = dict.fromkeys(("preprocess", "inference", "postprocess"), 0.0)
        if self.view.tile_px is None:
            detections = self._detect_piece(rgb, region, timings)
        else:
            scale = self.frame_scale(rgb.shape[:2])
            tiles = tile_layout(region, max(1, round(self.view.tile_px / scale)), self.view.tile_overlap)
            found, tile_index = [], []
            for k, tile in enumerate(tiles):
                pieces = self._detect_piece(rgb, tile.xyxy, timings)
                found += pieces
                tile_index += [k] * len(pieces)
            t = time.perf_counter()
            detections = merge_tiles(found, tile_index, self.view.merge_overlap)[: self.max_detections]
            timings["postprocess"] += (time.perf_counter() - t) * 1e3
            timings["tiles"] = float(len(tiles))
        self.last_timings_ms = timings
        return detections

    def frame_scale(self, image_hw: tuple[int, int]) -> float:
        """Network input pixels per image pixel at which this detector sees a frame of ``image_hw``: ``view.scale``,
        else the scale that letterboxes the whole frame into ``input_hw``."""
        if self.view.scale is not None:
            return float(self.view.scale)
        return letterbox_geometry(image_hw, self.input_hw, self.stride if self.dynamic_input else None).scale_x

    def _detect_piece(
        self, rgb: np.ndarray, box: tuple[int, int, int, int], timings: dict[str, float]
    ) -> list[Detection]:
        """Detections in the integer box ``[x0, y0, x1, y1)`` of ``rgb``, in frame pixels; adds to ``timings``."""
        t0 = time.perf_counter()
        x0, y0, x1, y1 = box
        image = rgb[y0:y1, x0:x1]
        if self.view.scale is not None:
            geometry = letterbox_at_scale(image.shape[:2], self.view.scale, self.stride)
        elif self.dynamic_input and image.shape[:2] != rgb.shape[:2]:
            geometry = letterbox_at_scale(image.shape[:2], self.frame_scale(rgb.shape[:2]), self.stride)
        else:
            geometry = letterbox_geometry(image.shape[:2], self.input_hw, self.stride if self.dynamic_input else None)
        blob = to_blob(letterbox(np.ascontiguousarray(image), geometry), self.input_dtype)
        t1 = time.perf_counter()
        outputs = self._run(blob)
        t2 = time.perf_counter()
        self._check_run_outputs(outputs)
        detections = self._postprocess(outputs, geometry)
        if image.shape[:2] != rgb.shape[:2]:
            detections = [_to_frame(d, (x0, y0), rgb.shape[:2]) for d in detections]
        t3 = time.perf_counter()
        timings["preprocess"] += (t1 - t0) * 1e3
        timings["inference"] += (t2 - t1) * 1e3
        timings["postprocess"] += (t3 - t2) * 1e3
        return detections

    @staticmethod
    def _region(image_hw: tuple[int, int], roi_xyxy: Sequence[int] | None) -> tuple[int, int, int, int]:
        h, w = image_hw
        if roi_xyxy is None:
            return 0, 0, w, h
        if len(roi_xyxy) != 4:
            raise ValueError(f"roi_xyxy: expected [x0, y0, x1, y1] pixels, got {list(roi_xyxy)!r}")
        x0, y0, x1, y1 = (int(v) for v in roi_xyxy)
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
        if x1 <= x0 or y1 <= y0:
            raise ValueError(f"roi_xyxy: {list(roi_xyxy)} leaves nothing of a {w}x{h} image")
        return x0, y0, x1, y1

    def _postprocess(self, outputs: list[np.ndarray], geometry: Letterbox) -> list[Detection]:
        decoded = postprocess(
            outputs[0].astype(np.float32, copy=False),
            outputs[1] if self.has_masks else None,
            geometry,
            self.num_classes,
            self.conf_threshold,
            self.iou_threshold,
            self.max_detections,
        )
        return [
            Detection(
                class_index=int(c),
                obj_id=int(self.class_obj_ids[c]),
                score=float(decoded.scores[k]),
                bbox_xyxy=decoded.boxes_xyxy[k],
                mask=decoded.masks[k] if decoded.masks is not None else None,
            )
            for k, c in enumerate(decoded.class_index)
        ]
