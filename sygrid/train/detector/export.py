"""ONNX export of the segmentation network in the ultralytics YOLOv8-seg layout, checked against torch.

The file has one input ``images`` ``[1, 3, H, W]`` float32 (RGB in [0, 1]) and two outputs: ``output0``
``[1, 4 + nc + 32, A]`` (box ``cx, cy, w, h`` in input pixels, per-class sigmoid scores, 32 mask coefficients; no
objectness) and ``output1`` ``[1, 32, H/4, W/4]`` (prototypes). ``H`` and ``W`` are dynamic by default (any multiple
of 32), so the runtime can letterbox a 640x480 frame to a 4:3 input instead of a padded square; ``fixed_hw`` exports
one fixed size instead. Metadata as ultralytics writes it (``names`` as a python dict string, ``imgsz``, ``stride``,
``task``, ``batch``) plus the BOP obj_id of each class (``obj_ids``, which ``perception.detector`` reads, and
``sygrid_class_obj_ids``, the same list).

Uses torch's TorchScript-based exporter (``dynamo=False``): the torch.export-based one needs onnxscript, which is
not installed; it folds each BatchNorm into its convolution.
"""

from __future__ import annotations

import copy
import io
import json
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from onnx import helper, numpy_helper

from sygrid.errors import ExportError
from sygrid.fileio import write_bytes_atomic
from sygrid.train.detector.model import YoloSeg

OPSET = 17
CHECK_ATOL = 1e-4  # scores, coefficients, prototypes
# Boxes are in pixels (hundreds): torch's oneDNN and onnxruntime's MLAS kernels sum in different orders, and through
# the network's depth their float32 results part by about 1e-5 relative: a few 1e-3 px on a 640 px input (seen: 3.7e-3
# on an AVX2-only CPU); a hundredth of a pixel is still far below anything a detection is judged by.
CHECK_BOX_ATOL_PX = 1e-2
HALF_CHECK_ATOL = 1e-2  # float16 weights (relative rounding 5e-4 per weight)
HALF_CHECK_BOX_ATOL_PX = 0.5


@dataclass(frozen=True)
class ExportReport:
    """What was exported and how it compared with torch: ``max_abs_diff`` per output over the checked input
    shapes (boxes separately, in pixels)."""

    path: Path
    size_bytes: int
    input_shapes_checked: list[tuple[int, int]]
    max_abs_diff: dict[str, float]
    metadata: dict[str, str]

    def as_dict(self) -> dict:
        return {
            "path": str(self.path),
            "size_bytes": self.size_bytes,
            "input_shapes_checked": [list(s) for s in self.input_shapes_checked],
            "max_abs_diff": self.max_abs_diff,
            "metadata": self.metadata,
        }


def model_metadata(names: Sequence[str], obj_ids: Sequence[int], imgsz: int, size: str) -> dict[str, str]:
    """The ``metadata_props`` of an exported detector."""
    ids = json.dumps([int(i) for i in obj_ids])
    return {
        "description": f"SyGRID YOLOv8-style instance segmentation, size {size!r}",
        "author": "sygrid",
        "task": "segment",
        "stride": "32",
        "batch": "1",
        "imgsz": json.dumps([int(imgsz), int(imgsz)]),
        "names": str({i: str(n) for i, n in enumerate(names)}),
        "obj_ids": ids,
        "sygrid_class_obj_ids": ids,
    }


def export_onnx(
    model: YoloSeg,
    path: str | Path,
    names: Sequence[str],
    obj_ids: Sequence[int],
    imgsz: int,
    fixed_hw: tuple[int, int] | None = None,
    check_shapes: Sequence[tuple[int, int]] | None = None,
    half_weights: bool = False,
) -> ExportReport:
    """Exports ``model`` (a copy, in eval mode) to ``path`` and checks it with ``onnx.checker`` and onnxruntime.

    Args:
        names, obj_ids: class names and BOP obj_ids by class index (into the metadata).
        imgsz: the training input side (metadata ``imgsz``; the runtime letterboxes into it).
        fixed_hw: export one fixed ``(H, W)`` instead of dynamic height and width.
        check_shapes: input ``(H, W)`` to compare onnxruntime with torch on (random images); default the
            training square and a 4:3 input of the same width (or ``fixed_hw``).
        half_weights: store the weights as float16 (half the file), cast back to float32 when onnxruntime loads the
            model (it folds the casts: the computation stays float32). The rounding moves the outputs by more than
            the float32 tolerances; ``HALF_CHECK_ATOL`` / ``HALF_CHECK_BOX_ATOL_PX`` apply instead.

    Raises:
        ExportError: the ONNX outputs differ from torch beyond ``CHECK_ATOL`` (``CHECK_BOX_ATOL_PX`` for boxes);
            nothing is written then.
    """
    if len(names) != model.cfg.num_classes or len(obj_ids) != model.cfg.num_classes:
        raise ValueError(
            f"names ({len(names)}) and obj_ids ({len(obj_ids)}) must both list the {model.cfg.num_classes} classes"
        )
    net = copy.deepcopy(model).float().eval().to(memory_format=torch.contiguous_format)
    export_hw = fixed_hw or (imgsz, imgsz)
    dummy = torch.zeros((1, 3, *export_hw), dtype=torch.float32)
    dynamic_axes = None
    if fixed_hw is None:
        dynamic_axes = {
            "images": {2: "height", 3: "width"},
            "output0": {2: "anchors"},
            "output1": {2: "mask_height", 3: "mask_width"},
        }
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation and tracer warnings
        torch.onnx.export(
            net,
            (dummy,),
            buffer,
            dynamo=False,
            input_names=["images"],
            output_names=["output0", "output1"],
            dynamic_axes=dynamic_axes,
            opset_version=OPSET,
            do_constant_folding=True,
        )
    proto = onnx.load_from_string(buffer.getvalue())
    # The tracer leaves the batch and channel axes of output0 symbolic; state them, as ultralytics' files do, so
    # that a reader can tell the class count from the shape.
    channels = 4 + model.cfg.num_classes + model.cfg.num_masks
    dims = proto.graph.output[0].type.tensor_type.shape.dim
    dims[0].Clear()
    dims[0].dim_value = 1
    dims[1].Clear()
    dims[1].dim_value = channels
    metadata = model_metadata(names, obj_ids, imgsz, model.cfg.size)
    del proto.metadata_props[:]
    for key, value in metadata.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    proto.producer_name = "sygrid"
    if half_weights:
        _store_weights_as_half(proto)
    onnx.checker.check_model(proto)
    payload = proto.SerializeToString()

    if check_shapes is None:
        check_shapes = [export_hw] if fixed_hw else [(imgsz, imgsz), (max(32, (imgsz * 3 // 4) // 32 * 32), imgsz)]
    diffs = _compare(net, payload, check_shapes)
    atol, box_atol = (HALF_CHECK_ATOL, HALF_CHECK_BOX_ATOL_PX) if half_weights else (CHECK_ATOL, CHECK_BOX_ATOL_PX)
    if diffs["boxes_px"] > box_atol or max(v for k, v in diffs.items() if k != "boxes_px") > atol:
        raise ExportError(f"{path}: onnxruntime differs from torch: {diffs}; not written")
    path = write_bytes_atomic(path, payload)
    return ExportReport(path, len(payload), [tuple(s) for s in check_shapes], diffs, metadata)


def _store_weights_as_half(proto: onnx.ModelProto) -> None:
    """Every float32 initializer of more than 64 values becomes a float16 initializer and a ``Cast`` to float32
    (placed first in the graph, under the original name, so that the consumers do not change)."""
    graph = proto.graph
    casts = []
    for init in graph.initializer:
        if init.data_type != onnx.TensorProto.FLOAT or int(np.prod(init.dims)) <= 64:
            continue
        value = numpy_helper.to_array(init)
        name = init.name
        init.CopyFrom(numpy_helper.from_array(value.astype(np.float16), f"{name}__fp16"))
        casts.append(helper.make_node("Cast", [f"{name}__fp16"], [name], to=onnx.TensorProto.FLOAT))
    nodes = casts + list(graph.node)
    del graph.node[:]
    graph.node.extend(nodes)


def _compare(net: YoloSeg, payload: bytes, shapes: Sequence[tuple[int, int]]) -> dict[str, float]:
    options = ort.SessionOptions()
    options.log_severity_level = 3
    options.intra_op_num_threads = 1  # a check on a few images: threads only add start-up and contention
    session = ort.InferenceSession(payload, sess_options=options, providers=["CPUExecutionProvider"])
    nc = net.cfg.num_classes
    diffs = {"boxes_px": 0.0, "scores": 0.0, "coefficients": 0.0, "protos": 0.0}
    rng = np.random.default_rng(0)
    for h, w in shapes:
        image = rng.random((1, 3, h, w), dtype=np.float32)
        with torch.no_grad():
            ref0, ref1 = (t.numpy() for t in net(torch.from_numpy(image)))
        out0, out1 = session.run(["output0", "output1"], {"images": image})
        if out0.shape != ref0.shape or out1.shape != ref1.shape:
            raise ExportError(f"ONNX output shapes {out0.shape}, {out1.shape} != torch {ref0.shape}, {ref1.shape}")
        d0 = np.abs(out0 - ref0)[0]
        diffs["boxes_px"] = max(diffs["boxes_px"], float(d0[:4].max()))
        diffs["scores"] = max(diffs["scores"], float(d0[4 : 4 + nc].max()))
        diffs["coefficients"] = max(diffs["coefficients"], float(d0[4 + nc :].max()))
        diffs["protos"] = max(diffs["protos"], float(np.abs(out1 - ref1).max()))
    return diffs
