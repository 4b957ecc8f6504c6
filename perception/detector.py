"""YOLO instance segmentation at run time: numpy + onnxruntime (CPU), for our models and ultralytics' alike.

The model contract is the ultralytics YOLOv8-seg ONNX layout:

- input: one image tensor ``[1, 3, H, W]`` float (RGB, 0..1), fixed or dynamic ``H, W``;
- ``output0``: ``[1, 4 + nc + nm, A]``, per anchor the box ``cx, cy, w, h`` in input pixels, ``nc`` per-class scores
  (already sigmoided, no objectness) and ``nm`` (32) mask coefficients;
- ``output1``: the mask prototypes ``[1, nm, H/4, W/4]``. A detection-only model has no ``output1`` and an
  ``output0`` of ``[1, 4 + nc, A]``.

Class names come from the ONNX ``metadata_props`` (ultralytics writes ``names`` as a python dict string
``"{0: 'hex_nut', 1: 'washer'}"``, ``imgsz`` as ``"[640, 640]"`` and ``stride``); our exporter adds ``obj_ids``
(``"[1, 3]"``). Each class maps to a BOP obj_id: an explicit ``class_obj_ids`` argument wins, then the ``obj_ids``
metadata, then the built-in part of the same name, then ``class index + 1`` (with a warning).

Pre-processing is ultralytics' letterbox (keep aspect ratio, pad with grey 114 around the centred image; a model
with a fixed input is padded to that size, a dynamic one to the next multiple of the stride); post-processing is
confidence filtering, class-aware NMS (OpenCV), then mask assembly per kept box: coefficients @ prototypes, sigmoid,
bilinear resampling straight into the original image's pixels (upsampling and un-letterboxing in one affine warp),
crop to the box, threshold 0.5. Masks are built only inside each box, so their cost scales with the box area.
"""

from __future__ import annotations

import ast
import logging
import math
import time
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort
from onnxruntime.capi import onnxruntime_pybind11_state as ort_state

from perception.results import Detection
from sygrid.errors import ModelError
from sygrid.letterbox import Letterbox, letterbox_at_scale, letterbox_geometry
from sygrid.letterbox import letterbox as letterbox

log = logging.getLogger(__name__)

DEFAULT_INPUT_SIZE = 640  # for a model with a dynamic input and no ``imgsz`` metadata
DEFAULT_STRIDE = 32
MAX_NMS_CANDIDATES = 30000  # boxes entering NMS at most (highest scores first): bounds the cost of a noisy frame
MASK_THRESHOLD = 0.5

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
    """(h, w, 3) uint8 -> (1, 3, h, w) C-contiguous in [0, 1] (a few times faster than cv2.dnn.blobFromImage)."""
    blob = np.empty((1, 3, *image.shape[:2]), dtype=dtype)
    np.multiply(image.transpose(2, 0, 1), dtype(1.0 / 255.0), out=blob[0], casting="unsafe")
    return blob


# ---------------------------------------------------------------------------------------------------- decoding
def decode_predictions(
    output0: np.ndarray, num_classes: int, conf_threshold: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Candidates of one ``[1, 4 + nc + nm, A]`` (or ``[4 + nc + nm, A]``) prediction above ``conf_threshold``.

    Returns ``boxes_xyxy`` (n, 4) input pixels, ``scores`` (n,), ``class_index`` (n,) int, ``coefficients`` (n, nm)
    (nm = 0 for a detection-only model), at most ``MAX_NMS_CANDIDATES``, highest score first. Each anchor votes
    for its best class only, as ultralytics' single-label prediction does.
    """
    pred = output0[0] if output0.ndim == 3 else output0
    class_scores = pred[4 : 4 + num_classes]
    best = class_scores.max(axis=0)  # the max over classes first: cheaper than an argmax over every anchor
    keep = np.flatnonzero(best > conf_threshold)
    keep = keep[np.argsort(-best[keep], kind="stable")][:MAX_NMS_CANDIDATES]
    class_index = np.argmax(class_scores[:, keep], axis=0)
    cx, cy, w, h = pred[0:4, keep].astype(np.float64)
    boxes = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1)
    coefficients = pred[4 + num_classes :, keep].T.astype(np.float32)
    return boxes, best[keep].astype(np.float64), class_index.astype(np.int64), coefficients


def class_aware_nms(
    boxes_xyxy: np.ndarray, scores: np.ndarray, class_index: np.ndarray, iou_threshold: float, max_detections: int
) -> np.ndarray:
    """Indices of the boxes kept by per-class NMS (IoU > ``iou_threshold`` with a better box of the same class
    suppresses), highest score first, at most ``max_detections``. OpenCV's batched NMS does the work."""
    if len(boxes_xyxy) == 0:
        return np.zeros(0, dtype=np.int64)
    xywh = np.concatenate([boxes_xyxy[:, :2], boxes_xyxy[:, 2:] - boxes_xyxy[:, :2]], axis=1)
    kept = np.asarray(
        cv2.dnn.NMSBoxesBatched(
            xywh.astype(np.float64), scores.astype(np.float32), class_index.astype(np.int32), -math.inf, iou_threshold
        ),
        dtype=np.int64,
    ).reshape(-1)
    kept = kept[np.argsort(-scores[kept], kind="stable")]
    return kept[:max_detections]


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))  # = 1 / (1 + exp(-x)), without overflow warnings


def assemble_mask(
    coefficients: np.ndarray, prototypes: np.ndarray, box_image_xyxy: np.ndarray, geometry: Letterbox
) -> np.ndarray:
    """The (h, w) bool instance mask, in original image pixels, of one detection.

    Args:
        coefficients: (nm,) mask coefficients of the detection.
        prototypes: (nm, mh, mw) mask prototypes covering the network input.
        box_image_xyxy: (4,) the detection's box in image pixels: the mask is cropped to it (pixel centres inside).
        geometry: the letterbox that made the network input.

    The mask probability ``sigmoid(coefficients @ prototypes)`` is resampled bilinearly (edge pixels replicated,
    like an ``align_corners=False`` upsampling) at each image pixel centre, mapped back through the letterbox to
    prototype coordinates; pixels above 0.5 are the mask. Only the prototype window under the box is computed.
    """
    h, w = geometry.image_hw
    mask = np.zeros((h, w), dtype=bool)
    x0, y0, x1, y1 = (float(v) for v in box_image_xyxy)
    # Pixels whose centre (j + 0.5) lies in [x0, x1).
    j0, j1 = max(0, math.ceil(x0 - 0.5)), min(w, math.ceil(x1 - 0.5))
    i0, i1 = max(0, math.ceil(y0 - 0.5)), min(h, math.ceil(y1 - 0.5))
    if j1 <= j0 or i1 <= i0:
        return mask
    nm, mh, mw = prototypes.shape
    in_h, in_w = geometry.input_hw
    # Image pixel (j, i) centre -> prototype index coordinates: x_p = ((j + 0.5) * s_x + pad_left) * mw / in_w - 0.5.
    ax, ay = geometry.scale_x * mw / in_w, geometry.scale_y * mh / in_h
    bx = (0.5 * geometry.scale_x + geometry.pad_left) * mw / in_w - 0.5
    by = (0.5 * geometry.scale_y + geometry.pad_top) * mh / in_h - 0.5
    # The prototype window the box needs (one cell of margin for the bilinear neighbours).
    px0 = min(max(math.floor(ax * j0 + bx), 0), mw - 1)
    px1 = min(max(math.floor(ax * (j1 - 1) + bx) + 2, px0 + 1), mw)
    py0 = min(max(math.floor(ay * i0 + by), 0), mh - 1)
    py1 = min(max(math.floor(ay * (i1 - 1) + by) + 2, py0 + 1), mh)
    window = prototypes[:, py0:py1, px0:px1].reshape(nm, -1)  # a small copy: the window under the box
    probability = _sigmoid(coefficients @ window).reshape(py1 - py0, px1 - px0).astype(np.float32)
    # Output pixel (u, v) = image pixel (j0 + u, i0 + v) samples the window at (ax*(j0+u) + bx - px0, ...).
    warp = np.array([[ax, 0.0, ax * j0 + bx - px0], [0.0, ay, ay * i0 + by - py0]], dtype=np.float64)
    patch = cv2.warpAffine(
        probability,
        warp,
        (j1 - j0, i1 - i0),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )
    mask[i0:i1, j0:j1] = patch > MASK_THRESHOLD
    return mask


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
    """A YOLO(v8)-seg or detection ONNX model on onnxruntime's CPU provider.

    Args:
        onnx_path: the ``.onnx`` file.
        class_obj_ids: BOP obj_id of each class index; None reads them from the model (see the module docstring).
        conf_threshold: minimum class score of a detection, in [0, 1).
        iou_threshold: NMS IoU above which the lower-scored box of the same class is dropped, in (0, 1].
        input_size: network input ``(height, width)`` or one int for a square; only for a model with a dynamic
            input (a fixed-input model must be given None or its own size). None: the ``imgsz`` metadata, else 640.
        num_threads: onnxruntime intra-op threads.
        max_detections: most detections returned per image.

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
        self.session = self._open_session(self.path, int(num_threads))
        self.metadata: dict[str, str] = dict(self.session.get_modelmeta().custom_metadata_map)
        self._check_input(input_size)
        self._check_outputs()
        self.class_names, self.class_obj_ids, self.obj_id_source = self._class_mapping(class_obj_ids)
        self.last_timings_ms: dict[str, float] = {}

    # ------------------------------------------------------------------------------------------- loading
    @staticmethod
    def _open_session(path: Path, num_threads: int) -> ort.InferenceSession:
        if not path.is_file():
            raise ModelError(f"{path}: ONNX model file not found" + (" (it is a directory)" if path.is_dir() else ""))
        options = ort.SessionOptions()
        options.intra_op_num_threads = num_threads
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        options.log_severity_level = 3  # errors only: a model's harmless warnings must not flood the demo's log
        # Worker threads sleep when a run ends instead of spinning: on 2 cores the spinning threads took the CPU from
        # the mask assembly, the next session and the simulator (`sygrid bench perception`, detector at 640 px:
        # 70.1 ms per frame with spinning, 30.5 ms without).
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        try:
            return ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])
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
            "[1, nm, H/4, W/4], or a detection-only 'output0' [1, 4+nc, A]"
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
            roi_xyxy: ``[x0, y0, x1, y1]`` integer pixels: look only there (a bin's region of the image). A model
                with a dynamic input sees the region at the scale it would see the whole frame at (so ``input_size``
                keeps its meaning and the parts their size in pixels), which costs the region's share of the
                frame's area; a fixed input is filled by the region. None: the whole frame.

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
        t0 = time.perf_counter()
        x0, y0, x1, y1 = self._region(rgb.shape[:2], roi_xyxy)
        image = rgb[y0:y1, x0:x1]
        if self.dynamic_input and image.shape[:2] != rgb.shape[:2]:
            full = letterbox_geometry(rgb.shape[:2], self.input_hw, self.stride)
            geometry = letterbox_at_scale(image.shape[:2], full.scale_x, self.stride)
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
        self.last_timings_ms = {
            "preprocess": (t1 - t0) * 1e3,
            "inference": (t2 - t1) * 1e3,
            "postprocess": (t3 - t2) * 1e3,
        }
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
        pred = outputs[0].astype(np.float32, copy=False)
        boxes, scores, classes, coefficients = decode_predictions(pred, self.num_classes, self.conf_threshold)
        kept = class_aware_nms(boxes, scores, classes, self.iou_threshold, self.max_detections)
        boxes_image = geometry.boxes_to_image(boxes[kept])
        protos = outputs[1][0].astype(np.float32, copy=False) if self.has_masks else None
        detections = []
        for k, idx in enumerate(kept):
            mask = None
            if protos is not None:
                mask = assemble_mask(coefficients[idx], protos, boxes_image[k], geometry)
            detections.append(
                Detection(
                    class_index=int(classes[idx]),
                    obj_id=int(self.class_obj_ids[classes[idx]]),
                    score=float(scores[idx]),
                    bbox_xyxy=boxes_image[k],
                    mask=mask,
                )
            )
        return detections
