"""sygrid.train.detector: box maths, assigner and loss on hand-made cases, the data pipeline on synthetic and tiny
generated data, validation plumbing, and a smoke training run that exports an ONNX model the runtime loads and
that resumes from its checkpoint."""

from __future__ import annotations

import ast
import itertools
import json
import math
import shutil

import numpy as np
import onnx
import onnxruntime as ort
import pytest

torch = pytest.importorskip("torch")

from pycocotools import mask as mask_utils  # noqa: E402

from sygrid.bench.training import earlier_curves, run_curve  # noqa: E402
from sygrid.errors import ConfigError  # noqa: E402
from sygrid.letterbox import Letterbox  # noqa: E402
from sygrid.train.detector import cache as cache_module  # noqa: E402
from sygrid.train.detector.assigner import TaskAlignedAssigner  # noqa: E402
from sygrid.train.detector.augment import (  # noqa: E402
    example_rng,
    letterbox_geometry,
    targets_from_ids,
    train_example,
    val_example,
)
from sygrid.train.detector.boxes import (  # noqa: E402
    box_ciou,
    box_to_dist,
    dfl_expectation,
    dist_to_box,
    make_anchors,
)
from sygrid.train.detector.cache import InstanceCache, cache_bytes, plan_cache  # noqa: E402
from sygrid.train.detector.config import MODEL_SIZES, AugmentConfig, TrainConfig  # noqa: E402
from sygrid.train.detector.data import (  # noqa: E402
    DetectorDataError,
    combine_datasets,
    load_instances,
    open_dataset,
    open_datasets,
    parse_data_yaml,
)
from sygrid.train.detector.evaluate import ImageDetections, coco_evaluate, val_detections  # noqa: E402
from sygrid.train.detector.export import _store_weights_as_half  # noqa: E402
from sygrid.train.detector.loss import SegmentationLoss, Targets  # noqa: E402
from sygrid.train.detector.model import SIZES, ModelConfig, build_model  # noqa: E402
from sygrid.train.detector.trainer import TrainError, _Trainer, learning_rate, train  # noqa: E402

REG_MAX = 16


@pytest.fixture(autouse=True)
def one_torch_thread():
    """One intra-op thread: these tensors are tiny, and on a busy small machine threads wait on each other at every
    operation."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# ------------------------------------------------------------------------------------------------ box maths
def _one_hot_dfl_logits(dist: torch.Tensor) -> torch.Tensor:
    """(n, 4) distances -> (n, 4 * REG_MAX) logits whose softmax puts the interpolation weights on the two bins."""
    left = dist.floor().long()
    w = dist - left
    probs = torch.zeros((*dist.shape, REG_MAX))
    probs.scatter_(-1, left[..., None], (1 - w)[..., None])
    probs.scatter_add_(-1, (left + 1).clamp(max=REG_MAX - 1)[..., None], w[..., None])
    return torch.log(probs + 1e-12).reshape(dist.shape[0], -1)


def test_dfl_decode_inverts_encode():
    gen = torch.Generator().manual_seed(0)
    anchors = torch.rand((50, 2), generator=gen) * 20 + 10
    half = torch.rand((50, 4), generator=gen) * 6 + 0.5
    boxes = torch.cat((anchors - half[:, :2], anchors + half[:, 2:]), 1)
    dist = box_to_dist(anchors, boxes, REG_MAX - 1 - 0.01)
    decoded = dist_to_box(dfl_expectation(_one_hot_dfl_logits(dist), REG_MAX), anchors)
    assert torch.allclose(decoded, boxes, atol=1e-4)
    # Beyond the support the distance saturates at reg_max - 1 - 0.01 cells.
    far = box_to_dist(anchors[:1], torch.tensor([[0.0, 0.0, 100.0, 100.0]]), REG_MAX - 1 - 0.01)
    assert torch.allclose(far[0, 2:], torch.full((2,), REG_MAX - 1.01))


def test_anchors_are_cell_centres_level_by_level():
    points, strides = make_anchors([(2, 3), (1, 2)], (8, 16))
    assert points.shape == (8, 2) and strides.shape == (8, 1)
    assert points[:3].tolist() == [[0.5, 0.5], [1.5, 0.5], [2.5, 0.5]]
    assert points[5].tolist() == [2.5, 1.5] and points[6].tolist() == [0.5, 0.5]
    assert strides[:, 0].tolist() == [8.0] * 6 + [16.0] * 2


def test_ciou_is_one_for_identical_boxes_and_drops_with_shift():
    box = torch.tensor([[10.0, 10.0, 30.0, 20.0]])
    assert box_ciou(box, box).item() == pytest.approx(1.0, abs=1e-6)
    shifted = [box_ciou(box, box + torch.tensor([[d, 0.0, d, 0.0]])).item() for d in (1.0, 5.0, 15.0, 40.0)]
    assert all(a > b for a, b in itertools.pairwise(shifted))
    assert shifted[-1] < 0  # disjoint boxes: the centre-distance term makes CIoU negative


# ------------------------------------------------------------------------------------------------- assigner
def test_assigner_picks_aligned_anchors_inside_the_box():
    anchors = torch.stack(torch.meshgrid(torch.arange(8.0), torch.arange(8.0), indexing="xy"), -1).reshape(-1, 2)
    anchors = anchors * 8 + 4  # an 8x8 grid of stride 8 (64 x 64 input)
    a = len(anchors)
    gt = torch.tensor([[[8.0, 8.0, 40.0, 32.0], [0.0, 0.0, 0.0, 0.0]]])  # second row is padding
    # Each anchor predicts the ground truth shifted by its offset from (20, 20): alignment falls with distance.
    best = int(((anchors - torch.tensor([20.0, 20.0])) ** 2).sum(1).argmin())
    pred_boxes = (gt[0, 0] + (anchors - anchors[best]).repeat(1, 2))[None]
    pred_scores = torch.full((1, a, 3), 0.1)
    assigner = TaskAlignedAssigner(num_classes=3, topk=10)
    out = assigner(pred_scores, pred_boxes, anchors, torch.tensor([[2, 0]]), gt, torch.tensor([[True, False]]))
    inside = (anchors[:, 0] > 8) & (anchors[:, 0] < 40) & (anchors[:, 1] > 8) & (anchors[:, 1] < 32)
    fg = out.fg[0]
    assert int(inside.sum()) == 12 and int(fg.sum()) == 10  # the top 10 of the 12 anchors inside the box
    assert bool(fg[best]) and not bool((fg & ~inside).any())
    assert out.labels[0, best] == 2 and torch.equal(out.boxes[0, best], gt[0, 0])
    # The best-aligned anchor gets the class target equal to its IoU (1.0); the others get less; classes other
    # than the ground truth's get 0.
    assert out.scores[0, best, 2].item() == pytest.approx(1.0, abs=1e-5)
    assert float(out.scores[0, :, :2].abs().sum()) == 0.0
    assert float(out.scores[0, fg & (torch.arange(a) != best), 2].max()) < 1.0


def test_assigner_with_no_ground_truth_assigns_nothing():
    assigner = TaskAlignedAssigner(num_classes=2)
    out = assigner(
        torch.rand(2, 5, 2), torch.rand(2, 5, 4), torch.rand(5, 2), torch.zeros(2, 0).long(), torch.zeros(2, 0, 4),
        torch.zeros(2, 0, dtype=torch.bool),
    )  # fmt: skip
    assert not bool(out.fg.any()) and float(out.scores.sum()) == 0.0


# ----------------------------------------------------------------------------------------------------- loss
def _head_outputs(box_xyxy: torch.Tensor, cls_index: int, nc: int, mask_logit_sign: float):
    """Raw head outputs of a 64 x 64 input (levels 8x8, 4x4, 2x2) that predict ``box_xyxy`` at every anchor with a
    confident score for ``cls_index`` inside the box, and prototypes whose first channel is +/-5 inside the box."""
    raw = []
    for s in (8, 16, 32):
        n = 64 // s
        points, _ = make_anchors([(n, n)], (s,))
        dist = box_to_dist(points, box_xyxy / s, REG_MAX - 1 - 0.01)
        box_logits = _one_hot_dfl_logits(dist).T.reshape(4 * REG_MAX, n, n)
        centre = points * s
        inside = (
            (centre[:, 0] > box_xyxy[0]) & (centre[:, 0] < box_xyxy[2])
            & (centre[:, 1] > box_xyxy[1]) & (centre[:, 1] < box_xyxy[3])
        )  # fmt: skip
        cls_logits = torch.full((nc, n * n), -8.0)
        cls_logits[cls_index, inside] = 6.0
        raw.append(torch.cat((box_logits, cls_logits.reshape(nc, n, n)), 0)[None])
    a = 64 + 16 + 4
    coef = torch.zeros((1, 32, a))
    coef[0, 0] = 1.0
    proto = torch.full((1, 32, 16, 16), -5.0 * mask_logit_sign)
    x0, y0, x1, y1 = (int(v) // 4 for v in box_xyxy)
    proto[0, 0, y0:y1, x0:x1] = 5.0 * mask_logit_sign
    return raw, coef, proto


def test_loss_prefers_the_true_box_class_and_mask():
    box = torch.tensor([16.0, 16.0, 48.0, 40.0])
    mask = torch.zeros((1, 1, 16, 16))
    mask[0, 0, 4:10, 4:12] = 1.0
    targets = Targets(torch.tensor([[1]]), box[None, None], torch.tensor([[True]]), mask)
    loss = SegmentationLoss(num_classes=3)
    _, perfect = loss(_head_outputs(box, 1, 3, +1.0), targets)
    _, shifted = loss(_head_outputs(box + torch.tensor([6.0, 4.0, 6.0, 4.0]), 1, 3, +1.0), targets)
    _, wrong_class = loss(_head_outputs(box, 0, 3, +1.0), targets)
    _, wrong_mask = loss(_head_outputs(box, 1, 3, -1.0), targets)
    assert perfect["box"] < 0.01 and perfect["box"] < shifted["box"]
    assert perfect["dfl"] < shifted["dfl"]
    assert perfect["cls"] < wrong_class["cls"]
    assert perfect["mask"] < 0.1 < wrong_mask["mask"]


def test_loss_backpropagates_through_the_network():
    model = build_model(ModelConfig(num_classes=2, size="p")).train()
    images = torch.rand((2, 3, 64, 64))
    targets = Targets(
        torch.tensor([[0, 1], [1, 0]]),
        torch.tensor([[[8.0, 8.0, 30.0, 24.0], [32.0, 30.0, 60.0, 60.0]], [[4.0, 4.0, 20.0, 20.0], [0, 0, 0, 0]]]),
        torch.tensor([[True, True], [True, False]]),
        torch.rand((2, 2, 16, 16)),
    )
    total, terms = SegmentationLoss(num_classes=2)(model(images), targets)
    total.backward()
    assert math.isfinite(float(total.detach())) and set(terms) == {"box", "mask", "cls", "dfl"}
    grads = [p.grad for p in model.parameters() if p.requires_grad]
    assert all(g is not None for g in grads) and sum(float(g.abs().sum()) for g in grads) > 0


def test_config_sizes_match_the_model():
    assert tuple(SIZES) == MODEL_SIZES


def test_eval_output_layout():
    model = build_model(ModelConfig(num_classes=3, size="p")).eval()
    with torch.no_grad():
        output0, protos = model(torch.rand((1, 3, 96, 128)))
    anchors = 12 * 16 + 6 * 8 + 3 * 4
    assert output0.shape == (1, 4 + 3 + 32, anchors) and protos.shape == (1, 32, 24, 32)
    scores = output0[0, 4:7]
    assert float(scores.min()) >= 0.0 and float(scores.max()) <= 1.0  # sigmoided, no objectness
    assert float(output0[0, 2:4].min()) > 0  # widths and heights in pixels


# ------------------------------------------------------------------------------------------------------ data
def test_parse_data_yaml_forms(tmp_path):
    written = 'train: images/train\nval: images/val\nnames:\n  0: "hex_nut"\n  1: "washer"\n'
    assert parse_data_yaml(written, tmp_path / "a.yaml") == {
        "train": "images/train",
        "val": "images/val",
        "names": ["hex_nut", "washer"],
    }
    assert parse_data_yaml("names: ['a', 'b']\ntrain: x # comment\n", tmp_path)["names"] == ["a", "b"]
    assert parse_data_yaml("names: {0: 'a', 1: 'b'}\n", tmp_path)["names"] == ["a", "b"]
    with pytest.raises(DetectorDataError, match=r"class indices 0\.\.n-1"):
        parse_data_yaml("names:\n  0: a\n  2: b\n", tmp_path / "bad.yaml")


def test_targets_from_ids_boxes_and_coverage():
    ids = np.zeros((16, 16), np.int32)
    ids[2:6, 4:12] = 1  # 4 x 8 block aligned to cell rows 0-1 half covered, cells x 1-2 full
    ids[9, 9] = 2  # a single pixel: dropped (below the minimum area)
    classes, boxes, masks = targets_from_ids(ids, np.array([3, 1]))
    assert classes.tolist() == [3]
    assert boxes.tolist() == [[4.0, 2.0, 12.0, 6.0]]
    assert masks.shape == (1, 4, 4)
    assert masks[0, 0].tolist() == [0.0, 0.5, 0.5, 0.0] and masks[0, 1].tolist() == [0.0, 0.5, 0.5, 0.0]
    assert float(masks[0].sum()) * 16 == 32  # coverage integrates to the pixel count


def test_letterbox_geometry_by_hand():
    """(image_hw, side, stride) -> (input_hw, resized_hw, pad_left, pad_top), worked out from the rule: scale to fit,
    centre, pad (with a stride, only up to the next multiple of it); an odd padding puts the extra pixel at the
    bottom/right."""
    cases = {
        ((480, 640), 416, None): ((416, 416), (312, 416), 0, 52),  # scale 0.65, 104 rows of padding, 52 on top
        ((480, 640), 416, 32): ((320, 416), (312, 416), 0, 4),  # 104 % 32 = 8 rows: 4 on top
        ((120, 160), 128, None): ((128, 128), (96, 128), 0, 16),
        ((120, 160), 128, 32): ((96, 128), (96, 128), 0, 0),  # 32 % 32 = 0: no padding
        ((300, 200), 320, None): ((320, 320), (320, 213), 53, 0),  # 213.3 -> 213 columns, 107 of padding: 53 + 54
        ((300, 200), 320, 32): ((320, 224), (320, 213), 5, 0),  # 107 % 32 = 11 columns: 5 + 6
    }
    for (image_hw, size, stride), expected in cases.items():
        g = letterbox_geometry(image_hw, size, stride)
        assert (g.input_hw, g.resized_hw, g.pad_left, g.pad_top) == expected, (image_hw, size, stride)


def test_open_dataset_errors(tmp_path):
    with pytest.raises(DetectorDataError, match="no YOLO dataset"):
        open_dataset(tmp_path)
    root = tmp_path / "yolo"
    (root / "images" / "train").mkdir(parents=True)
    (root / "images" / "val").mkdir(parents=True)
    (root / "data.yaml").write_text('train: images/train\nval: images/val\nnames:\n  0: "hex_nut"\n')
    with pytest.raises(DetectorDataError, match="no images"):
        open_dataset(tmp_path, obj_ids=[1])
    for split in ("train", "val"):
        (root / "images" / split / "a.png").write_bytes(b"")
    (root / "labels" / "train").mkdir(parents=True)
    (root / "labels" / "train" / "a.txt").write_text("0 0.1 0.1 0.2\n")
    with pytest.raises(DetectorDataError, match=r"a\.txt:1: expected 'class x1 y1"):
        open_dataset(tmp_path, labels="yolo", obj_ids=[1])


# ---------------------------------------------------------------------------------- tiny generated dataset
def test_examples_are_deterministic_and_consistent(tiny_dataset):
    ds = open_dataset(tiny_dataset)
    assert ds.label_source == "coco" and ds.names == ["hex_nut", "washer", "l_bracket"] and ds.obj_ids == [1, 3, 4]
    cfg = AugmentConfig()
    a = train_example(ds, 0, 96, cfg, example_rng(5, 2, 0), imgsz=128)
    b = train_example(ds, 0, 96, cfg, example_rng(5, 2, 0), imgsz=128)
    c = train_example(ds, 0, 96, cfg, example_rng(5, 3, 0), imgsz=128)
    assert (
        np.array_equal(a.image, b.image) and np.array_equal(a.masks, b.masks) and not np.array_equal(a.image, c.image)
    )
    # No augmentation at the native letterbox: the targets are the COCO ground truth scaled by 128 / 160.
    plain = train_example(ds, 0, 128, AugmentConfig.none(), example_rng(0, 0, 0), imgsz=128)
    gt = ds.coco_gt["train"]
    boxes = np.array([a["bbox"] for a in gt["annotations"] if a["image_id"] == 1]) * 0.8
    boxes[:, 2:] += boxes[:, :2]
    boxes[:, 1::2] += 16  # 120 x 160 -> 96 x 128, centred in 128 rows
    found = np.abs(plain.boxes_xyxy[:, None, :] - boxes[None]).max(-1).min(-1)
    assert len(plain.classes) >= 1 and float(found.max()) <= 1.5  # resampling moves an edge by about a pixel
    example, geometry = val_example(ds, 0, 128, 32)
    assert example.image.shape == (96, 128, 3) and geometry.pad_top == 0 and example.masks.shape[1:] == (24, 32)


def test_the_image_cache_gives_what_the_files_hold_and_the_same_examples(tiny_dataset, monkeypatch):
    ds = open_dataset(tiny_dataset)
    kept, passing = InstanceCache(ds, enabled=True), InstanceCache(ds, enabled=False)
    n = len(ds.images["train"])
    for _ in range(2):  # the first read fills the cache, the second comes from it
        for i in range(n):
            image, ids, classes = kept.load("train", i)
            truth = load_instances(ds, "train", i)
            assert ids.dtype == truth[1].dtype == np.int32
            assert all(np.array_equal(a, b) for a, b in zip((image, ids, classes), truth, strict=True))
    assert len(kept) == n and len(passing) == 0
    image, ids, _ = kept.load("train", 0)
    image[:] = 0  # a caller's change to what it got ...
    ids[:] = 0
    assert np.array_equal(kept.load("train", 0)[0], load_instances(ds, "train", 0)[0])  # ... is not the cache's
    assert int(kept.load("train", 0)[1].max()) > 0
    # The same examples, mosaics included, whichever way the images come.
    cfg = AugmentConfig(mosaic=1.0)
    for i in range(n):
        a = train_example(ds, i, 96, cfg, example_rng(5, 2, i), imgsz=128)
        b = train_example(ds, i, 96, cfg, example_rng(5, 2, i), imgsz=128, load=kept.load)
        assert np.array_equal(a.image, b.image) and np.array_equal(a.masks, b.masks)
    (a, _), (b, _) = val_example(ds, 0, 128, 32), val_example(ds, 0, 128, 32, load=kept.load)
    assert np.array_equal(a.image, b.image) and np.array_equal(a.masks, b.masks)

    # What it would take: image (3 bytes) and id map (1 byte, under 256 instances) per pixel of every image.
    pixels = sum(im["height"] * im["width"] for s in ("train", "val") for im in ds.coco_gt[s]["images"])
    assert cache_bytes(ds) == 4 * pixels
    assert plan_cache(ds, "ram").enabled and not plan_cache(ds, "none").enabled

    class Memory:
        def __init__(self, available: int) -> None:
            self.available = available

    monkeypatch.setattr(cache_module.psutil, "virtual_memory", lambda: Memory(8 * pixels))
    assert plan_cache(ds, "auto").enabled  # 4 x pixels fits in half of 8 x pixels
    monkeypatch.setattr(cache_module.psutil, "virtual_memory", lambda: Memory(8 * pixels - 1))
    plan = plan_cache(ds, "auto")
    assert not plan.enabled and plan.bytes_needed == 4 * pixels and plan.bytes_available == 8 * pixels - 1
    with pytest.raises(ValueError, match="cache: expected one of"):
        TrainConfig(data=str(tiny_dataset), out="x", cache="disk")


def test_coco_evaluate_of_the_ground_truth_is_perfect(tiny_dataset):
    ds = open_dataset(tiny_dataset)
    gt = ds.coco_gt["val"]
    detections = []
    for labels in ds.labels["val"]:  # the COCO masks the dataset read, as perfect detections
        rles = list(labels.rles)
        boxes = mask_utils.toBbox(rles).reshape(-1, 4) if rles else np.zeros((0, 4))
        boxes[:, 2:] += boxes[:, :2]
        detections.append(ImageDetections(boxes, np.ones(len(rles)), labels.classes, rles))
    metrics = coco_evaluate(gt, detections, ds.obj_ids)
    assert metrics.box_map50 == pytest.approx(1.0) and metrics.mask_map50_95 == pytest.approx(1.0)


def test_datasets_trained_together_are_one_dataset(tiny_dataset, tmp_path):
    """--data twice: the union of the images and labels, the validation ground truth renumbered so that perfect
    detections of every image still score 1; a YOLO-polygon copy joins a COCO-labelled set; other classes are
    refused with both folders named."""
    one = open_dataset(tiny_dataset)
    shutil.copytree(tiny_dataset / "yolo", tmp_path / "yolo")
    both = open_datasets([tiny_dataset, tmp_path / "yolo" / "data.yaml"], obj_ids=[1, 3, 4])
    assert both.label_source == "coco+yolo" and both.roots == (tiny_dataset / "yolo", tmp_path / "yolo")
    for split in ("train", "val"):
        n = len(one.images[split])
        assert both.images[split][n:] == [tmp_path / "yolo" / p.relative_to(tiny_dataset / "yolo")
                                          for p in one.images[split]]  # fmt: skip
        gt = both.coco_gt[split]
        assert [im["id"] for im in gt["images"]] == list(range(1, 2 * n + 1))
        assert sorted(a["id"] for a in gt["annotations"]) == list(range(1, len(gt["annotations"]) + 1))
        assert len(gt["annotations"]) == 2 * len(one.coco_gt[split]["annotations"])
    detections = []
    for k in range(len(both.images["val"])):  # the ground truth's masks, as perfect detections, image by image
        anns = [a for a in both.coco_gt["val"]["annotations"] if a["image_id"] == k + 1]
        rles = [a["segmentation"] for a in anns]
        boxes = np.array([a["bbox"] for a in anns], dtype=float).reshape(-1, 4)
        boxes[:, 2:] += boxes[:, :2]
        classes = np.array([both.obj_ids.index(a["category_id"]) for a in anns], dtype=np.int64)
        detections.append(ImageDetections(boxes, np.ones(len(anns)), classes, rles))
    assert coco_evaluate(both.coco_gt["val"], detections, both.obj_ids).box_map50 == pytest.approx(1.0)
    assert TrainConfig(data=(str(tiny_dataset), "b"), out="o").as_dict()["data"] == [str(tiny_dataset), "b"]
    with pytest.raises(DetectorDataError, match=r"classes .* differ from .*tiny_dataset.*same classes"):
        combine_datasets([one, open_dataset(tmp_path / "yolo" / "data.yaml", obj_ids=[1, 3, 5])])


def test_coco_evaluate_with_nothing_detected_is_zero(tiny_dataset):
    ds = open_dataset(tiny_dataset)
    gt = ds.coco_gt["val"]
    nothing = ImageDetections(np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64), [])
    metrics = coco_evaluate(gt, [nothing] * len(gt["images"]), ds.obj_ids)
    assert (metrics.box_map50_95, metrics.box_map50, metrics.mask_map50_95, metrics.mask_map50) == (0, 0, 0, 0)
    assert metrics.n_detections == 0 and metrics.n_gt > 0


def test_postprocess_decodes_nms_and_masks():
    nc, nm = 2, 32
    geometry = Letterbox((48, 64), (48, 64), (48, 64), 0, 0)  # identity letterbox
    output0 = np.zeros((4 + nc + nm, 4), np.float32)
    output0[:4, 0] = [20, 20, 16, 16]  # box 12..28
    output0[:4, 1] = [21, 20, 16, 16]  # a near duplicate of the same class, lower score: suppressed
    output0[:4, 2] = [50, 30, 8, 8]  # another class
    output0[:4, 3] = [10, 40, 8, 8]  # below the confidence threshold
    output0[4:6, :] = [[0.9, 0.8, 0.0, 0.0001], [0.0, 0.0, 0.7, 0.0]]
    output0[6, :] = 1.0  # every mask = prototype 0
    protos = np.full((nm, 12, 16), -10.0, np.float32)
    protos[0, 4:6, 4:6] = 10.0  # input pixels 16..24 in both axes
    det = val_detections(output0, protos, geometry, nc, conf_threshold=0.01)
    assert det.classes.tolist() == [0, 1] and det.scores.tolist() == pytest.approx([0.9, 0.7])
    assert det.boxes_xyxy[0].tolist() == pytest.approx([12, 12, 28, 28])
    mask = mask_utils.decode(det.rles[0]).astype(bool)
    ys, xs = np.nonzero(mask)
    assert (xs.min(), xs.max(), ys.min(), ys.max()) == (16, 23, 16, 23)


# ---------------------------------------------------------------------------------------------- smoke run
def test_learning_rate_warms_up_then_decays():
    cfg = TrainConfig(data="x", out="y", epochs=4, lr=1e-3, lr_final=0.1, warmup_epochs=1.0, warmup_min_iters=1)
    lrs = [learning_rate(cfg, i, 10) for i in range(40)]
    assert lrs[0] == pytest.approx(1e-4) and lrs[9] == pytest.approx(1e-3)
    assert all(a >= b for a, b in itertools.pairwise(lrs[9:])) and lrs[-1] == pytest.approx(1e-4, rel=0.05)


@pytest.mark.slow  # two short training runs with validation and an ONNX export
def test_smoke_training_exports_onnx_and_resumes(tiny_dataset, tmp_path):
    out = tmp_path / "run"
    common = {
        "data": str(tiny_dataset),
        "out": str(out),
        "imgsz": 128,
        "batch": 2,
        "size": "p",
        "seed": 3,
        "threads": 1,
    }
    result = train(TrainConfig(**common, epochs=1, max_iters=2, progress=False))
    assert [p.name for p in sorted(out.iterdir())] == ["best.pt", "detector.onnx", "last.pt", "train_log.json"]
    log = json.loads((out / "train_log.json").read_text())
    assert [e["epoch"] for e in log["epochs"]] == [1] and log["epochs"][0]["iterations"] == 2
    assert set(log["epochs"][0]["loss"]) == {"box", "mask", "cls", "dfl", "total"}
    assert 0.0 <= log["epochs"][0]["val"]["box_map50"] <= 1.0
    assert log["cache"]["mode"] == "auto" and log["cache"]["bytes_needed"] > 0
    data = log["epochs"][0]
    assert data["data_build_seconds"] > 0 and 0 <= data["data_wait_seconds"] <= data["train_seconds"]

    # The ONNX file: ultralytics layout and metadata, onnxruntime agrees with torch (checked by the exporter).
    session = ort.InferenceSession(str(result.export.path), providers=["CPUExecutionProvider"])
    meta = session.get_modelmeta().custom_metadata_map
    assert ast.literal_eval(meta["names"]) == {0: "hex_nut", 1: "washer", 2: "l_bracket"}
    assert json.loads(meta["imgsz"]) == [128, 128] and meta["stride"] == "32" and meta["task"] == "segment"
    assert json.loads(meta["sygrid_class_obj_ids"]) == [1, 3, 4] == json.loads(meta["obj_ids"])
    output0, output1 = session.run(["output0", "output1"], {"images": np.zeros((1, 3, 96, 128), np.float32)})
    assert output0.shape == (1, 4 + 3 + 32, 12 * 16 + 6 * 8 + 3 * 4) and output1.shape == (1, 32, 48, 64)  # stride 2
    assert max(result.export.max_abs_diff[k] for k in ("scores", "coefficients", "protos")) <= 1e-4
    assert result.export.size_bytes < 6_000_000

    # Float16 weight storage (--half-weights) halves the file and moves the outputs only a little.
    proto = onnx.load(result.export.path)
    _store_weights_as_half(proto)
    onnx.checker.check_model(proto)
    half = proto.SerializeToString()
    assert 0.45 < len(half) / result.export.size_bytes < 0.55
    image = np.random.default_rng(0).random((1, 3, 96, 128), dtype=np.float32)
    full_out, half_out = (
        ort.InferenceSession(m, providers=["CPUExecutionProvider"]).run(None, {"images": image})
        for m in (str(result.export.path), half)
    )
    assert np.abs(full_out[0][0, :4] - half_out[0][0, :4]).max() < 0.5  # boxes, pixels
    assert np.abs(full_out[0][0, 4:] - half_out[0][0, 4:]).max() < 1e-2  # scores and coefficients
    assert np.abs(full_out[1] - half_out[1]).max() < 1e-2  # prototypes

    # The runtime loads it and runs a frame (an untrained model: any number of detections, valid ones).
    detector_module = pytest.importorskip("perception.detector")
    detector = detector_module.YoloSegDetector(result.export.path, conf_threshold=0.001)
    assert detector.class_obj_ids == [1, 3, 4] and detector.has_masks
    frame = np.full((120, 160, 3), 90, np.uint8)
    for det in detector.detect(frame):
        assert det.obj_id in (1, 3, 4) and det.mask.shape == (120, 160)

    # Resume: the epoch count goes on from the checkpoint.
    first_iteration = torch.load(out / "last.pt", weights_only=True)["iteration"]
    resumed = train(TrainConfig(**common, epochs=2, max_iters=2, progress=False, resume=True, export=False))
    assert resumed.export is None
    ckpt = torch.load(out / "last.pt", weights_only=True)
    assert ckpt["epoch"] == 2 and ckpt["iteration"] == first_iteration + 2
    log = json.loads((out / "train_log.json").read_text())
    assert [e["epoch"] for e in log["epochs"]] == [1, 2]

    # Its learning curve (sygrid bench training): one point per validated epoch, images seen = iterations x batch.
    curve = run_curve(out)
    assert [p["epoch"] for p in curve["points"]] == [1, 2]
    assert [p["images_seen"] for p in curve["points"]] == [4, 8]
    assert 0.0 < curve["points"][0]["hours"] < curve["points"][1]["hours"]
    assert curve["width"] == "p" and curve["train_images"] == log["dataset"]["train_images"]
    assert curve["cache"] is log["cache"]["enabled"] and curve["seconds_per_iter_median"] > 0
    assert [p["epoch"] for p in curve["speed"]] == [1, 2] and all(p["data_build"] > 0 for p in curve["speed"])

    # A different network cannot resume from this checkpoint.
    with pytest.raises(TrainError, match="differs from this run"):
        train(TrainConfig(**{**common, "size": "n"}, epochs=3, max_iters=1, progress=False, resume=True, export=False))

    # Fine-tuning (--init): a new run in another folder starts from the checkpoint's EMA weights, at another input
    # size; its first epoch is 1 again. Another network size is refused.
    ema = torch.load(out / "last.pt", weights_only=True)["ema"]
    tuned_cfg = {**common, "out": str(tmp_path / "tuned"), "imgsz": 160, "init": str(out / "last.pt")}
    tuned = _Trainer(TrainConfig(**tuned_cfg, epochs=1, max_iters=1, progress=False, export=False))
    assert all(torch.equal(v, tuned.model.state_dict()[k]) for k, v in ema.items())
    assert tuned.epoch == 0
    with pytest.raises(TrainError, match=r"--init\): the checkpoint's network"):
        _Trainer(TrainConfig(**{**tuned_cfg, "size": "f"}, epochs=1, progress=False))


@pytest.mark.slow  # three short training runs
def test_a_run_interrupted_inside_an_epoch_resumes_to_the_weights_of_an_uninterrupted_one(
    tiny_dataset, tmp_path, monkeypatch
):
    common = {"data": str(tiny_dataset), "imgsz": 64, "batch": 2, "size": "f", "seed": 5, "threads": 1,
              "epochs": 2, "val_every": 2, "progress": False, "export": False}  # fmt: skip
    whole = train(TrainConfig(**common, out=str(tmp_path / "whole"), checkpoint_minutes=None))
    assert [e["iterations"] for e in whole.history] == [3, 3]

    # Killed right after the mid-epoch checkpoint written after the 2nd iteration of epoch 2 (one every iteration).
    class KilledError(Exception):
        pass

    save_last = _Trainer._save_last

    def save_then_die(self, partial_epoch=None):
        path = save_last(self, partial_epoch)
        if partial_epoch is not None and self.epoch == 1 and partial_epoch["iterations"] == 2:
            raise KilledError
        return path

    out = tmp_path / "cut"
    monkeypatch.setattr(_Trainer, "_save_last", save_then_die)
    with pytest.raises(KilledError):
        train(TrainConfig(**common, out=str(out), checkpoint_minutes=1e-9))
    monkeypatch.undo()
    ckpt = torch.load(out / "last.pt", weights_only=True)
    assert ckpt["epoch"] == 1 and ckpt["iteration"] == 5 and ckpt["partial_epoch"]["iterations"] == 2

    # Another batch size cannot finish that epoch; the same run can, and ends where the uninterrupted one did.
    with pytest.raises(TrainError, match=r"stopped inside epoch 2 of batches of 2.*keep the same --batch"):
        _Trainer(TrainConfig(**{**common, "batch": 3}, out=str(out), resume=True))
    resumed = train(TrainConfig(**common, out=str(out), resume=True))
    final, reference = (torch.load(r.last, weights_only=True) for r in (resumed, whole))
    assert final["iteration"] == reference["iteration"] == 6 and final["partial_epoch"] is None
    for key in ("model", "ema"):
        assert all(torch.equal(v, reference[key][k]) for k, v in final[key].items()), key
    for mine, theirs in zip(resumed.history, whole.history, strict=True):
        assert mine["iterations"] == theirs["iterations"]
        assert mine["loss"] == pytest.approx(theirs["loss"], rel=1e-6)
    for key in ("box_map50", "mask_map50_95"):
        assert resumed.history[1]["val"][key] == pytest.approx(whole.history[1]["val"][key])


def test_learning_curve_of_a_folder_without_a_log_is_a_clear_error(tmp_path):
    with pytest.raises(ConfigError, match="no training log"):
        run_curve(tmp_path)
    (tmp_path / "train_log.json").write_text('{"epochs": []}')
    with pytest.raises(ConfigError, match="not a detector training log"):
        run_curve(tmp_path)


def test_an_earlier_result_charts_its_runs_marked_and_a_wrong_file_is_a_clear_error(tmp_path):
    run = {"run": "runs/gone", "width": "p", "points": [{"epoch": 1, "images_seen": 8, "hours": 0.1, "box_map50": 0.2}]}
    result = tmp_path / "training.json"
    result.write_text(json.dumps({"machine": {}, "runs": [run]}))
    assert earlier_curves(result) == [{**run, "earlier": str(result)}]
    for bad in ('{"runs": []}', '{"runs": [{"run": "x"}]}', "[1, 2]"):
        result.write_text(bad)
        with pytest.raises(ConfigError, match=r"training\.json: not a `sygrid bench training` result"):
            earlier_curves(result)


def test_resume_without_checkpoint_is_a_clear_error(tiny_dataset, tmp_path):
    with pytest.raises(TrainError, match=r"last\.pt: checkpoint not found"):
        train(TrainConfig(data=str(tiny_dataset), out=str(tmp_path / "none"), imgsz=64, resume=True, threads=1))


def test_training_on_yolo_polygons_only(tiny_dataset, tmp_path):
    """A YOLO folder on its own (no COCO beside it): masks from the polygons, ground truth rasterised from them."""
    shutil.copytree(tiny_dataset / "yolo", tmp_path / "yolo")
    ds = open_dataset(tmp_path / "yolo" / "data.yaml", obj_ids=[1, 3, 4])
    assert ds.label_source == "yolo" and len(ds.coco_gt["val"]["annotations"]) > 0
    example = train_example(ds, 0, 64, AugmentConfig(), example_rng(0, 0, 0), imgsz=128)
    assert example.masks.shape[1:] == (16, 16) and len(example.classes) == len(example.boxes_xyxy)
