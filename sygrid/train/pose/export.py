"""ONNX export of a trained pose network, with its contract in the model's metadata and a numerical check against
torch (onnxruntime must reproduce torch's outputs within ``EXPORT_TOLERANCE``)."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch

from sygrid.errors import ExportError
from sygrid.fileio import write_bytes_atomic
from sygrid.pose_geometry import POSE_INPUTS, POSE_METADATA_KEY, POSE_ONNX_FORMAT, POSE_OUTPUTS
from sygrid.train.pose.model import PoseNet, PoseNetForExport
from sygrid.train.pose.objects import ObjectTables

OPSET = 17
EXPORT_TOLERANCE = 1e-4  # max |onnxruntime - torch| over every output


def pose_metadata(net: PoseNet, tables: ObjectTables, pad_scale: float) -> dict:
    """The JSON contract stored under ``metadata_props[POSE_METADATA_KEY]``."""
    cfg = net.config
    return {
        "format": POSE_ONNX_FORMAT,
        "input_size": cfg.input_size,
        "output_size": cfg.output_size,
        "output_stride": cfg.input_size // cfg.output_size,
        "pad_scale": float(pad_scale),
        "num_regions": cfg.num_regions,
        "obj_ids": [int(i) for i in tables.obj_ids],
        "names": list(tables.names),
        "objects": {
            str(obj_id): {
                "bounds_m": tables.bounds_m[c].tolist(),
                "diameter_m": float(tables.diameters_m[c]),
                "symmetric": bool(tables.symmetric[c]),
            }
            for c, obj_id in enumerate(tables.obj_ids)
        },
        "architecture": cfg.as_dict(),
        "tensors": {
            "image": "(B, 3, S, S) float32 RGB in [0, 1], the square RoI (side pad_scale x the box's longer side) "
            "resampled bilinearly, pixel centres at integer coordinates",
            "coord2d": "(B, 2, s, s) float32 ((x - cx) / fx, (y - cy) / fy) of the output cells' image points",
            "class_onehot": "(B, C) float32 one-hot in the order of obj_ids",
            "xyz": "(B, 3, s, s) object coordinates normalised to [0, 1] over objects[obj_id].bounds_m",
            "mask": "(B, 1, s, s) visible-mask probability",
            "region": "(B, R, s, s) surface-region probabilities",
            "rot6d": "(B, 6) allocentric rotation, first two matrix columns (Zhou et al.)",
            "site": "(B, 3) dx, dy = (projected origin - RoI centre) / RoI size, dz = t_z * size / (f * diameter)",
        },
    }


def export_onnx(
    net: PoseNet, tables: ObjectTables, pad_scale: float, path: str | Path, check_inputs: dict[str, np.ndarray]
) -> float:
    """Writes ``path`` (atomically) and returns the largest |onnxruntime - torch| on ``check_inputs`` (a batch of
    the three inputs by name); raises ``ExportError`` above ``EXPORT_TOLERANCE``."""
    path = Path(path)
    net = net.eval()
    wrapper = PoseNetForExport(net).eval()
    feeds = {k: np.ascontiguousarray(check_inputs[k], dtype=np.float32) for k in POSE_INPUTS}
    args = tuple(torch.from_numpy(feeds[k]) for k in POSE_INPUTS)
    tmp = path.with_name(f".{path.name}.export.tmp")
    path.parent.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notice; its output is what we want
        torch.onnx.export(
            wrapper,
            args,
            str(tmp),
            dynamo=False,
            opset_version=OPSET,
            input_names=list(POSE_INPUTS),
            output_names=list(POSE_OUTPUTS),
            dynamic_axes={name: {0: "batch"} for name in (*POSE_INPUTS, *POSE_OUTPUTS)},
        )
    try:
        model = onnx.load(str(tmp))
    finally:
        tmp.unlink(missing_ok=True)
    meta = model.metadata_props.add()
    meta.key, meta.value = POSE_METADATA_KEY, json.dumps(pose_metadata(net, tables, pad_scale))
    model.producer_name = "sygrid.train.pose"
    onnx.checker.check_model(model)
    payload = model.SerializeToString()
    with torch.no_grad():
        expected = [t.numpy() for t in wrapper(*args)]
    session = ort.InferenceSession(payload, providers=["CPUExecutionProvider"])
    got = session.run(list(POSE_OUTPUTS), feeds)
    diff = max(float(np.abs(a - b).max()) for a, b in zip(got, expected, strict=True))
    if not diff <= EXPORT_TOLERANCE:
        raise ExportError(f"{path}: onnxruntime differs from torch by {diff:.3g} (> {EXPORT_TOLERANCE}); not written")
    write_bytes_atomic(path, payload)
    return diff
