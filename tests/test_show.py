"""``sygrid show`` and the drawing functions of ``sygrid.visualize``.

The dataset is the session's ``tiny_dataset`` (8 raster-mode items of a 6-part bin at 160x120, written by the real
generator and writers); the projection checks draw known poses on blank images, with the expected pixels computed
by hand from the pinhole model.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from launch.cli import main
from sygrid.camera import CameraIntrinsics
from sygrid.errors import ConfigError
from sygrid.transforms import make_T, rotation_about
from sygrid.visualize import (
    AXIS_COLOURS,
    BOX_EDGES,
    box_corners_m,
    compose_grid,
    depth_colormap,
    draw_3d_box,
    draw_annotation,
    draw_axes,
    draw_bbox,
    draw_mask_outlines,
    instance_colours,
)
from sygrid.writers import load_bop_item

K = CameraIntrinsics(200.0, 200.0, 99.5, 79.5, 200, 160).K


def _blank(h: int = 160, w: int = 200) -> np.ndarray:
    return np.zeros((h, w, 3), dtype=np.uint8)


# ------------------------------------------------------------------------------------------------------ drawing
def test_3d_box_of_a_known_pose_lands_on_the_hand_projected_corners():
    # A 10 x 6 x 4 cm box 0.5 m in front of the camera, turned 30 degrees about the viewing axis.
    bounds = np.array([[-0.05, -0.03, -0.02], [0.05, 0.03, 0.02]])
    T = make_T(rotation_about([0, 0, 1], np.radians(30.0)), [0.01, -0.02, 0.5])
    img = draw_3d_box(_blank(), K, T, bounds, colour=(255, 255, 255))
    drawn = np.argwhere(img[..., 0] > 0)[:, ::-1]  # (n, 2) x, y
    assert len(drawn) > 100
    # Corners by hand: p = R @ c + t, u = fx x / z + cx, v = fy y / z + cy.
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    uv = []
    for x in (-0.05, 0.05):
        for y in (-0.03, 0.03):
            for z in (-0.02, 0.02):
                px, py, pz = c * x - s * y + 0.01, s * x + c * y - 0.02, z + 0.5
                uv.append((200.0 * px / pz + 99.5, 200.0 * py / pz + 79.5))
    uv = np.array(uv)
    hull = cv2.convexHull(uv.astype(np.float32))
    # Every drawn pixel lies within the corners' hull, widened by one pixel of line rasterisation.
    dist = np.array([cv2.pointPolygonTest(hull, (float(x), float(y)), True) for x, y in drawn])
    assert dist.min() >= -1.0
    # Every corner is drawn (within a pixel), and the box spans the hull's extent.
    for u, v in np.rint(uv).astype(int):
        assert img[v - 1 : v + 2, u - 1 : u + 2].any(), (u, v)
    assert np.allclose(drawn.min(0), np.floor(uv.min(0)), atol=1) and np.allclose(
        drawn.max(0), np.ceil(uv.max(0)), atol=1
    )


def test_box_corners_and_edges_form_a_box():
    corners = box_corners_m(np.array([[0, 0, 0], [1, 2, 3]]))
    assert corners.shape == (8, 3) and {tuple(c) for c in corners} == {
        (x, y, z) for x in (0, 1) for y in (0, 2) for z in (0, 3)
    }
    assert len(BOX_EDGES) == 12
    for a, b in BOX_EDGES:  # every edge is parallel to one axis
        assert np.count_nonzero(corners[a] != corners[b]) == 1


def test_axes_point_where_the_pose_says_in_their_colours():
    T = make_T(t=[0.0, 0.0, 0.4])  # object frame aligned with the camera's: x right, y down
    img = draw_axes(_blank(), K, T, length_m=0.05, thickness=1)
    # x axis ends at u = 200 * 0.05 / 0.4 + 99.5 = 124.5, y axis at v = 79.5 + 25 = 104.5
    assert tuple(img[80, 120]) == AXIS_COLOURS[0]
    assert tuple(img[100, 100]) == AXIS_COLOURS[1] or tuple(img[100, 99]) == AXIS_COLOURS[1]
    assert not img[60:75, :].any()  # nothing above the origin: y points down, z along the view


def test_pose_behind_the_camera_draws_nothing():
    T = make_T(t=[0.0, 0.0, -0.5])
    assert not draw_3d_box(_blank(), K, T, np.array([[-0.05] * 3, [0.05] * 3])).any()
    assert not draw_axes(_blank(), K, T, 0.05).any()


def test_outlines_boxes_depth_and_grid():
    mask = np.zeros((1, 160, 200), dtype=bool)
    mask[0, 40:80, 50:120] = True
    out = draw_mask_outlines(_blank(), mask, np.array([[0, 255, 0]]))
    edge = mask[0] & ~cv2.erode(mask[0].astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert np.all(out[edge] == [0, 255, 0]) and not out[~edge].any()  # exactly the boundary pixels
    box = draw_bbox(_blank(), (50, 40, 70, 40), (255, 0, 0))
    assert tuple(box[40, 50]) == (255, 0, 0) and tuple(box[79, 119]) == (255, 0, 0) and not box[80, 120].any()
    assert not draw_bbox(_blank(), (-1, -1, -1, -1)).any()
    depth = np.tile(np.linspace(0.5, 1.0, 200, dtype=np.float32), (160, 1))
    depth[:, :10] = 0.0
    cm = depth_colormap(depth)
    assert not cm[:, :10].any() and cm[:, 20:].any(axis=-1).all()
    assert cm[80, 20, 0] > cm[80, 20, 2] and cm[80, 190, 2] > cm[80, 190, 0]  # near red, far blue
    grid = compose_grid([_blank(10, 20)] * 3, cols=2, pad_px=4)
    assert grid.shape == (2 * 10 + 3 * 4, 2 * 20 + 3 * 4, 3)
    with pytest.raises(ValueError, match=r"images\[1\]: expected 20x10"):
        compose_grid([_blank(10, 20), _blank(12, 20)], cols=2)
    colours = instance_colours(20)
    assert len({tuple(c) for c in colours}) == 20


# ------------------------------------------------------------------------------------------------------ the command
def test_annotation_overlay_outlines_each_visible_instance(tiny_dataset: Path):
    ann, rgb, _ = load_bop_item(tiny_dataset / "bop", 0, 0)
    out = draw_annotation(ann, rgb, {})
    colours = instance_colours(len(ann.instances))
    visible = [i for i in ann.instances if i.px_count_visib > 20]
    assert visible
    for inst in visible:
        m = inst.mask_visib
        edge = m & ~cv2.erode(m.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        on_edge = np.all(out[edge] == colours[inst.inst_id], axis=-1)
        assert on_edge.mean() > 0.5, inst.inst_id  # later instances' outlines may cross an earlier one's


def test_show_writes_a_grid_of_the_expected_size(tiny_dataset: Path, tmp_path: Path, capsys):
    out = tmp_path / "show.png"
    assert main(["show", str(tiny_dataset), "--items", "3", "--out", str(out)]) == 0
    assert str(out) in capsys.readouterr().out
    img = cv2.imread(str(out))
    # 160x120 items, RGB + depth side by side (320x120), scaled x2 to reach 240 px high; 2 per row, 4 px apart.
    assert img.shape == (2 * 240 + 3 * 4, 2 * 640 + 3 * 4, 3)
    assert not np.all(img[4:244, 4:644] == 255)  # the first tile is drawn
    assert np.all(img[248:, 648:] == 255)  # the fourth slot is empty
    seeded = tmp_path / "seeded.png"
    assert main(["show", str(tiny_dataset), "--items", "2", "--seed", "3", "--out", str(seeded)]) == 0
    assert cv2.imread(str(seeded)).shape == (240 + 2 * 4, 2 * 640 + 3 * 4, 3)


def test_show_names_what_is_missing(tiny_dataset: Path, tmp_path: Path, capsys):
    from argparse import Namespace

    from launch.show import run

    def args(d: Path, split: str = "train_pbr") -> Namespace:
        return Namespace(dir=d, items=2, split=split, out=tmp_path / "x.png", seed=None)

    with pytest.raises(ConfigError, match=r"bop/models/models_info\.json: missing"):
        run(args(tmp_path))
    with pytest.raises(ConfigError, match="not a folder"):
        run(args(tmp_path / "nope"))
    with pytest.raises(ConfigError, match=r"no_split: missing; splits in .*\['train_pbr', 'val_pbr'\]"):
        run(args(tiny_dataset, "no_split"))
    copy = tmp_path / "copy"
    shutil.copytree(tiny_dataset / "bop" / "models", copy / "bop" / "models")
    (copy / "bop" / "train_pbr").mkdir()
    with pytest.raises(ConfigError, match=r"train_pbr: no items"):
        run(args(copy))
    assert main(["show", str(tmp_path)]) == 2
    assert "models_info.json: missing" in capsys.readouterr().err
