"""perception.detector on ONNX models built here with the ultralytics YOLOv8-seg layout and known outputs.

Each model ignores its input's values (its outputs are constants plus 0 x the input's mean, so the graph still
consumes the input) and so fixes exactly what the runtime must decode: boxes, scores, mask coefficients and
prototypes. The expected detections are worked out by hand below.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from perception.detector import YoloSegDetector
from sygrid.detection_decode import assemble_mask
from sygrid.errors import ModelError
from sygrid.letterbox import letterbox_geometry

IN = 64  # network input 64 x 64, prototypes 16 x 16 (stride 4)
NM = 32
NAMES = "{0: 'hex_nut', 1: 'washer'}"  # built-in parts: obj_ids 1 and 3
IMAGE_H, IMAGE_W = 64, 128  # letterbox: scale 0.5, resized to 64 x 32, 16 rows of padding on top and bottom


def save_model(
    path: Path,
    outputs: dict[str, np.ndarray],
    metadata: dict[str, str] | None = None,
    input_shape: list | None = None,
) -> Path:
    """An ONNX model with input ``images`` whose outputs are the given constants (+ 0 x mean(images))."""
    image = helper.make_tensor_value_info("images", TensorProto.FLOAT, input_shape or [1, 3, IN, IN])
    nodes = [
        helper.make_node("ReduceMean", ["images"], ["mean"], keepdims=0),
        helper.make_node("Mul", ["mean", "zero"], ["nothing"]),
    ]
    inits = [numpy_helper.from_array(np.array(0.0, np.float32), "zero")]
    outs = []
    for name, value in outputs.items():
        inits.append(numpy_helper.from_array(value.astype(np.float32), f"{name}_const"))
        nodes.append(helper.make_node("Add", [f"{name}_const", "nothing"], [name]))
        outs.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, list(value.shape)))
    graph = helper.make_graph(nodes, "fixed_yolo", [image], outs, initializer=inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], producer_name="test")
    model.ir_version = 8
    helper.set_model_props(model, metadata if metadata is not None else {"names": NAMES, "stride": "32"})
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return path


def anchors(transpose: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """output0 [1, 4 + 2 + 32, 6] and output1 [1, 32, 16, 16] of the hand-computed case.

    Anchors (input pixels, xyxy):
      0: hex_nut 0.90, box [8, 20, 40, 44], coefficients e0 (prototype 0: +10 on prototype columns 3..7)
      1: hex_nut 0.80, box [10, 20, 40, 44]: IoU 0.9375 with anchor 0 -> suppressed
      2: washer  0.70, same box as anchor 0: another class -> kept; e1 (prototype 1: +10 on rows 6..9)
      3: hex_nut 0.20: below the 0.25 threshold
      4: washer  0.60, box [44, 24, 60, 40], e2 (prototype 2: +10 everywhere)
      5: hex_nut 0.50, box [0, 40, 16, 56] (reaches into the bottom padding), e3 (+10 everywhere)
    ``transpose``: the same scene with x and y swapped (for a tall image, padded left and right).
    """
    boxes = np.array(
        [[8, 20, 40, 44], [10, 20, 40, 44], [8, 20, 40, 44], [20, 20, 30, 30], [44, 24, 60, 40], [0, 40, 16, 56]],
        float,
    )
    scores = np.array([[0.9, 0.05], [0.8, 0.05], [0.05, 0.7], [0.2, 0.1], [0.05, 0.6], [0.5, 0.05]])
    coefficients = np.zeros((6, NM))
    coefficients[[0, 1, 2, 3, 4, 5], [0, 0, 1, 0, 2, 3]] = 1.0
    protos = np.full((NM, 16, 16), -10.0)
    protos[0][:, 3:8] = 10.0
    protos[1][6:10, :] = 10.0
    protos[2:4] = 10.0
    if transpose:
        boxes = boxes[:, [1, 0, 3, 2]]
        protos = protos.transpose(0, 2, 1)
    cxcywh = np.stack(
        [
            (boxes[:, 0] + boxes[:, 2]) / 2,
            (boxes[:, 1] + boxes[:, 3]) / 2,
            boxes[:, 2] - boxes[:, 0],
            boxes[:, 3] - boxes[:, 1],
        ],
        axis=1,
    )
    output0 = np.concatenate([cxcywh, scores, coefficients], axis=1).T[None]
    return output0, protos[None]


def expected_masks() -> list[np.ndarray]:
    """Masks of the kept detections (0, 2, 4, 5) in the 64 x 128 image: image x = 2 * input x, image y =
    2 * (input y - 16); a prototype cell edge at p maps to image x = 8 p, image y = 8 p - 32. A +10/-10 step is
    crossed at the cell edge (sigmoid 0.5 halfway between cell centres), and each mask is cut to its box."""
    masks = [np.zeros((IMAGE_H, IMAGE_W), bool) for _ in range(4)]
    masks[0][8:56, 24:64] = True  # columns 3..7 -> x 24..63, cut to the box rows y 8..55
    masks[1][16:48, 16:80] = True  # rows 6..9 -> y 16..47, cut to the box columns x 16..79
    masks[2][16:48, 88:120] = True  # everywhere -> the box [88, 16, 120, 48]
    masks[3][48:64, 0:32] = True  # everywhere -> the box [0, 48, 32, 80] clipped to the image
    return masks


EXPECTED_BOXES = np.array([[16, 8, 80, 56], [16, 8, 80, 56], [88, 16, 120, 48], [0, 48, 32, 64]], float)
EXPECTED_SCORES = [0.9, 0.7, 0.6, 0.5]
EXPECTED_CLASSES = [0, 1, 1, 0]


@pytest.fixture(scope="module")
def seg_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    output0, output1 = anchors()
    return save_model(tmp_path_factory.mktemp("onnx") / "seg.onnx", {"output0": output0, "output1": output1})


def test_decodes_boxes_classes_scores_and_nms(seg_model: Path):
    detector = YoloSegDetector(seg_model)
    assert detector.input_hw == (IN, IN) and detector.has_masks and detector.num_classes == 2
    assert detector.class_names == ["hex_nut", "washer"] and detector.class_obj_ids == [1, 3]
    dets = detector.detect(np.zeros((IMAGE_H, IMAGE_W, 3), np.uint8))
    assert [d.class_index for d in dets] == EXPECTED_CLASSES  # anchor 1 suppressed, anchor 3 below threshold
    assert [d.obj_id for d in dets] == [1, 3, 3, 1]
    np.testing.assert_allclose([d.score for d in dets], EXPECTED_SCORES, rtol=1e-6)
    np.testing.assert_allclose(np.stack([d.bbox_xyxy for d in dets]), EXPECTED_BOXES, atol=1e-4)
    for det, mask in zip(dets, expected_masks(), strict=True):
        assert det.mask.shape == (IMAGE_H, IMAGE_W) and det.mask.dtype == bool
        np.testing.assert_array_equal(det.mask, mask)
    assert set(detector.last_timings_ms) == {"preprocess", "inference", "postprocess"}


def test_padding_on_the_left_and_right(tmp_path: Path):
    # The transposed scene in a tall 128 x 64 image: 16 columns of padding left and right.
    output0, output1 = anchors(transpose=True)
    detector = YoloSegDetector(save_model(tmp_path / "tall.onnx", {"output0": output0, "output1": output1}))
    dets = detector.detect(np.zeros((IMAGE_W, IMAGE_H, 3), np.uint8))
    np.testing.assert_allclose(np.stack([d.bbox_xyxy for d in dets]), EXPECTED_BOXES[:, [1, 0, 3, 2]], atol=1e-4)
    for det, mask in zip(dets, expected_masks(), strict=True):
        np.testing.assert_array_equal(det.mask, mask.T)


def test_nms_iou_threshold_is_respected(seg_model: Path):
    # IoU(anchor 0, anchor 1) = 0.9375: a threshold above it keeps both boxes of class 0.
    dets = YoloSegDetector(seg_model, iou_threshold=0.95).detect(np.zeros((IMAGE_H, IMAGE_W, 3), np.uint8))
    assert [round(d.score, 2) for d in dets] == [0.9, 0.8, 0.7, 0.6, 0.5]
    dets = YoloSegDetector(seg_model, conf_threshold=0.65, max_detections=1).detect(
        np.zeros((IMAGE_H, IMAGE_W, 3), np.uint8)
    )
    assert [round(d.score, 2) for d in dets] == [0.9]


def _reference_mask(coefficients, protos, box, image_hw, scale_xy, pad_left, pad_top, input_hw) -> np.ndarray:
    """A slow, independent mask: per image pixel centre, bilinear (edge-clamped) sigmoid of the prototypes."""
    h, w = image_hw
    _, mh, mw = protos.shape
    prob = 1.0 / (1.0 + np.exp(-np.tensordot(coefficients, protos, axes=1)))
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    px = (xs * scale_xy[0] + pad_left) * mw / input_hw[1] - 0.5
    py = (ys * scale_xy[1] + pad_top) * mh / input_hw[0] - 0.5
    px, py = px.clip(0, mw - 1), py.clip(0, mh - 1)
    x0, y0 = np.floor(px).astype(int), np.floor(py).astype(int)
    x1, y1 = np.minimum(x0 + 1, mw - 1), np.minimum(y0 + 1, mh - 1)
    fx, fy = px - x0, py - y0
    value = (
        prob[y0, x0] * (1 - fx) * (1 - fy)
        + prob[y0, x1] * fx * (1 - fy)
        + prob[y1, x0] * (1 - fx) * fy
        + prob[y1, x1] * fx * fy
    )
    inside = (xs >= box[0]) & (xs < box[2]) & (ys >= box[1]) & (ys < box[3])
    return (value > 0.5) & inside


def test_mask_assembly_agrees_with_a_dense_reference():
    rng = np.random.default_rng(5)
    protos = rng.normal(size=(NM, 20, 16)).astype(np.float32)  # a non-square 80 x 64 input
    geometry = letterbox_geometry((90, 50), (80, 64), None)  # scale 80/90 -> 44 x 80, 10 columns of padding
    assert (geometry.pad_left, geometry.pad_top, geometry.resized_hw) == (10, 0, (80, 44))
    scale_xy = (44 / 50, 80 / 90)  # the resize's exact scale per axis
    for _ in range(5):
        coefficients = rng.normal(size=NM).astype(np.float32)
        box = np.array([rng.uniform(-5, 20), rng.uniform(-5, 40), rng.uniform(25, 55), rng.uniform(45, 95)])
        box_clipped = np.clip(box, 0, [50, 90, 50, 90])
        ours = assemble_mask(coefficients, protos, box_clipped, geometry)
        ref = _reference_mask(coefficients, protos, box_clipped, (90, 50), scale_xy, 10, 0, (80, 64))
        assert ref.sum() > 50
        # OpenCV resamples at 1/32-pixel positions: at most a pixel or two on the 0.5 contour may differ.
        assert np.count_nonzero(ours != ref) <= max(2, 0.01 * ref.sum())


def test_detection_only_model(tmp_path: Path):
    output0, _ = anchors()
    det_only = output0[:, : 4 + 2]  # [1, 6, A]: boxes and class scores, no coefficients
    detector = YoloSegDetector(save_model(tmp_path / "det.onnx", {"output0": det_only}))
    assert not detector.has_masks
    dets = detector.detect(np.zeros((IMAGE_H, IMAGE_W, 3), np.uint8))
    np.testing.assert_allclose(np.stack([d.bbox_xyxy for d in dets]), EXPECTED_BOXES, atol=1e-4)
    assert [d.class_index for d in dets] == EXPECTED_CLASSES and all(d.mask is None for d in dets)


def test_obj_id_mapping_sources(tmp_path: Path, caplog: pytest.LogCaptureFixture):
    output0, output1 = anchors()
    outputs = {"output0": output0, "output1": output1}
    with_ids = save_model(tmp_path / "ids.onnx", outputs, {"names": NAMES, "obj_ids": "[11, 12]"})
    assert YoloSegDetector(with_ids).class_obj_ids == [11, 12]
    assert YoloSegDetector(with_ids, class_obj_ids=[7, 9]).class_obj_ids == [7, 9]  # the argument overrides
    custom = save_model(tmp_path / "custom.onnx", outputs, {"names": "{0: 'bracket_a', 1: 'bracket_b'}"})
    with caplog.at_level(logging.WARNING, logger="perception.detector"):
        detector = YoloSegDetector(custom)
    assert detector.class_obj_ids == [1, 2] and detector.obj_id_source == "class index + 1"
    assert "pass class_obj_ids" in caplog.text
    with pytest.raises(ModelError, match="number of classes disagrees"):
        YoloSegDetector(custom, class_obj_ids=[1, 2, 3])


def test_empty_frame_gives_no_detections(tmp_path: Path):
    output0, output1 = anchors()
    output0[:, 4:6] = 0.01  # no class score above the threshold
    detector = YoloSegDetector(save_model(tmp_path / "empty.onnx", {"output0": output0, "output1": output1}))
    assert detector.detect(np.zeros((IMAGE_H, IMAGE_W, 3), np.uint8)) == []


def test_dynamic_input_is_padded_to_the_stride(tmp_path: Path):
    # 480 x 640 needs no padding at 640; 500 x 640 is padded to 512 (6 rows on top).
    assert letterbox_geometry((480, 640), (640, 640), 32).input_hw == (480, 640)
    g = letterbox_geometry((500, 640), (640, 640), 32)
    assert (g.input_hw, g.pad_top, g.pad_left) == ((512, 640), 6, 0)
    output0, output1 = anchors()
    path = save_model(tmp_path / "dyn.onnx", {"output0": output0, "output1": output1}, None, [1, 3, "h", "w"])
    detector = YoloSegDetector(path, input_size=IN)
    assert detector.dynamic_input and detector.input_hw == (IN, IN)
    dets = detector.detect(np.zeros((IMAGE_H, IMAGE_W, 3), np.uint8))
    # The 64 x 128 image becomes a 32 x 64 input with no padding: image = 2 x input coordinates.
    np.testing.assert_allclose(dets[0].bbox_xyxy, [16, 40, 80, 64], atol=1e-4)
    # Without input_size, ultralytics' 'imgsz' metadata sets the size.
    meta = {"names": NAMES, "imgsz": "[96, 128]", "stride": "32"}
    path = save_model(tmp_path / "dyn_meta.onnx", {"output0": output0, "output1": output1}, meta, [1, 3, "h", "w"])
    assert YoloSegDetector(path).input_hw == (96, 128)


def test_bad_model_files(tmp_path: Path):
    missing = tmp_path / "nope.onnx"
    with pytest.raises(ModelError, match=r"nope\.onnx: ONNX model file not found"):
        YoloSegDetector(missing)
    corrupt = tmp_path / "corrupt.onnx"
    corrupt.write_bytes(b"this is not a protobuf \x00\xff" * 10)
    with pytest.raises(ModelError, match=r"corrupt\.onnx: not a loadable ONNX model"):
        YoloSegDetector(corrupt)
    output0, output1 = anchors()
    wrong_rank = save_model(tmp_path / "rank.onnx", {"output0": output0[0]})
    with pytest.raises(ModelError, match=r"found output0 \[38, 6\]; expected 'output0' \[1, 4\+nc\+nm, A\]"):
        YoloSegDetector(wrong_rank)
    too_few = save_model(tmp_path / "few.onnx", {"output0": output0[:, :30], "output1": output1})
    with pytest.raises(ModelError, match="outputs match no supported layout"):
        YoloSegDetector(too_few)
    with pytest.raises(ModelError, match="number of classes disagrees"):
        YoloSegDetector(
            save_model(tmp_path / "names.onnx", {"output0": output0, "output1": output1}, {"names": "['a']"})
        )
    fixed = save_model(tmp_path / "fixed.onnx", {"output0": output0, "output1": output1})
    with pytest.raises(ValueError, match="differs from the fixed input 64x64"):
        YoloSegDetector(fixed, input_size=320)


def test_bad_images(seg_model: Path):
    detector = YoloSegDetector(seg_model)
    for bad in (
        np.zeros((IMAGE_H, IMAGE_W), np.uint8),
        np.zeros((IMAGE_H, IMAGE_W, 4), np.uint8),
        np.zeros((IMAGE_H, IMAGE_W, 3), np.float32),
        [[0, 0, 0]],
    ):
        with pytest.raises(ValueError, match=r"rgb: expected a uint8 \(H, W, 3\) RGB image"):
            detector.detect(bad)
    with pytest.raises(ValueError, match="non-empty"):
        detector.detect(np.zeros((0, 10, 3), np.uint8))


def test_a_region_is_seen_at_the_whole_frames_scale(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    output0, output1 = anchors()
    path = save_model(tmp_path / "dyn.onnx", {"output0": output0, "output1": output1}, None, [1, 3, "h", "w"])
    detector = YoloSegDetector(path, input_size=IN)  # the 64 x 128 frame is seen at scale 0.5
    inputs = []
    run = detector._run
    monkeypatch.setattr(detector, "_run", lambda blob: inputs.append(blob.shape) or run(blob))
    image = np.zeros((IMAGE_H, IMAGE_W, 3), np.uint8)
    full = detector.detect(image)
    dets = detector.detect(image, roi_xyxy=(32, 16, 96, 48))
    # the 64 x 32 region at scale 0.5 is 32 x 16, padded to the stride (32): 8 rows on top, none on the sides
    assert inputs == [(1, 3, 32, 64), (1, 3, 32, 32)]
    # the same network box [8, 20, 40, 32] (input pixels): x 16..80, y (20 - 8) / 0.5 = 24..48 in the region,
    # clipped to the region (64 x 32) and moved by its corner
    np.testing.assert_allclose(dets[0].bbox_xyxy, [48, 40, 96, 48], atol=1e-4)
    assert len(dets) == len(full)
    for d in dets:
        assert d.mask.shape == (IMAGE_H, IMAGE_W)  # frame pixels, nothing outside the region
        assert not d.mask[:16].any() and not d.mask[48:].any() and not d.mask[:, :32].any() and not d.mask[:, 96:].any()
    # a region reaching out of the image is clipped to it; one that leaves nothing is an error
    detector.detect(image, roi_xyxy=(-10, -10, 40, 30))
    assert inputs[-1] == (1, 3, 32, 32)  # 40 x 30 at scale 0.5 = 20 x 15, padded to 32 x 32
    with pytest.raises(ValueError, match=r"roi_xyxy: \[130, 0, 140, 10\] leaves nothing of a 128x64 image"):
        detector.detect(image, roi_xyxy=(130, 0, 140, 10))
    with pytest.raises(ValueError, match=r"roi_xyxy: expected \[x0, y0, x1, y1\]"):
        detector.detect(image, roi_xyxy=(0, 0, 10))
