"""Drawing labels and poses over images: mask outlines, 2D boxes, 3D boxes, pose axes, depth maps, picture grids.

Pure functions on numpy images (RGB uint8 (H, W, 3); depth float metres (H, W), 0 = no data); each returns a new
image and leaves its input untouched. ``sygrid show`` draws a dataset's ground truth with them; the picking demo
draws estimated poses with the same functions, so a picture of labels and a picture of estimates look alike.

Poses are ``T_camera_obj`` (4, 4) metres, camera frame OpenCV (x right, y down, z forward); ``K`` is the (3, 3)
pinhole matrix. Object boxes are ``bounds_m`` (2, 3): the model's [min, max] corners in its own frame.
"""

from __future__ import annotations

import colorsys
import math
from collections.abc import Sequence

import cv2
import numpy as np

from sygrid.annotations import ImageAnnotation
from sygrid.camera import project_points
from sygrid.transforms import transform_points

Colour = tuple[int, int, int]
AXIS_COLOURS: tuple[Colour, Colour, Colour] = ((230, 30, 30), (30, 200, 30), (40, 80, 255))  # x, y, z as RGB
# The 12 edges of a box whose corners are numbered by the bits (x, y, z) of the index: corner i has x = max when
# i & 1, y = max when i & 2, z = max when i & 4. Edges join corners that differ in one bit.
BOX_EDGES: tuple[tuple[int, int], ...] = tuple(
    (i, i | bit) for bit in (1, 2, 4) for i in range(8) if not i & bit
)  # fmt: skip
_MIN_Z_M = 1e-3  # points closer to the camera plane than this are not projected (a line to them is not drawn)


def instance_colours(n: int) -> np.ndarray:
    """(n, 3) uint8 RGB colours, well apart in hue (golden-ratio steps), the same for the same ``n``."""
    hues = (np.arange(n) * 0.618033988749895) % 1.0
    return np.array([[round(255 * c) for c in colorsys.hsv_to_rgb(h, 0.85, 1.0)] for h in hues], dtype=np.uint8)


def _as_rgb(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"img: expected an RGB uint8 array of shape (H, W, 3), got {img.dtype} {img.shape}")
    return np.ascontiguousarray(img).copy()


def _colour(c: Sequence[int] | np.ndarray) -> Colour:
    return tuple(int(v) for v in np.asarray(c).reshape(3))


def draw_mask_outlines(
    img: np.ndarray, masks: np.ndarray | Sequence[np.ndarray], colours: np.ndarray, thickness: int = 1
) -> np.ndarray:
    """Outlines of (n, H, W) bool masks (outer contours and holes), mask k in ``colours[k]`` (RGB)."""
    out = _as_rgb(img)
    masks = np.asarray(masks, dtype=bool).reshape(-1, *out.shape[:2])
    colours = np.asarray(colours).reshape(-1, 3)
    if len(colours) < len(masks):
        raise ValueError(f"colours: expected at least {len(masks)} colours for {len(masks)} masks, got {len(colours)}")
    for mask, colour in zip(masks, colours, strict=False):
        contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(out, contours, -1, _colour(colour), int(thickness))
    return out


def draw_bbox(
    img: np.ndarray,
    bbox_xywh: Sequence[int],
    colour: Sequence[int] = (255, 255, 0),
    thickness: int = 1,
    label: str | None = None,
) -> np.ndarray:
    """An axis-aligned box ``(x, y, w, h)`` in pixels (BOP convention: the box covers pixels x .. x + w - 1),
    with an optional text label above it; an empty box ``(-1, -1, -1, -1)`` draws nothing."""
    out = _as_rgb(img)
    x, y, w, h = (int(v) for v in bbox_xywh)
    if w <= 0 or h <= 0:
        return out
    cv2.rectangle(out, (x, y), (x + w - 1, y + h - 1), _colour(colour), int(thickness))
    if label:
        cv2.putText(out, label, (x, max(y - 3, 9)), cv2.FONT_HERSHEY_PLAIN, 0.8, _colour(colour), 1, cv2.LINE_AA)
    return out


def box_corners_m(bounds_m: np.ndarray) -> np.ndarray:
    """(2, 3) [min, max] corners -> (8, 3) box corners, corner i taking max along axis b when bit b of i is set."""
    lo, hi = np.asarray(bounds_m, dtype=float).reshape(2, 3)
    return np.array([[(hi if i & (1 << a) else lo)[a] for a in range(3)] for i in range(8)])


def bounds_from_extents(extents_m: Sequence[float]) -> np.ndarray:
    """(2, 3) bounds of a box of ``extents_m`` centred on the object origin."""
    half = np.asarray(extents_m, dtype=float).reshape(3) / 2.0
    return np.stack([-half, half])


def _draw_segments(
    out: np.ndarray, K: np.ndarray, p_cam: np.ndarray, segments: Sequence[tuple[int, int]], colours, thickness: int
) -> None:
    """Draws 3D segments between camera-frame points; a segment with an end behind the camera is skipped (a
    pinhole projection of it would be wrong, and the pose is then not drawable anyway)."""
    front = p_cam[:, 2] > _MIN_Z_M
    uv = np.zeros((len(p_cam), 2))
    if front.any():
        uv[front] = project_points(np.asarray(K, dtype=float), p_cam[front])
    for (a, b), colour in zip(segments, colours, strict=True):
        if not (front[a] and front[b]):
            continue
        # cv2.clipLine keeps far off-image points from overflowing the int drawing coordinates.
        pa, pb = (tuple(int(v) for v in np.rint(np.clip(uv[i], -1e6, 1e6))) for i in (a, b))
        ok, pa, pb = cv2.clipLine((0, 0, out.shape[1], out.shape[0]), pa, pb)
        if ok:
            cv2.line(out, pa, pb, _colour(colour), int(thickness), cv2.LINE_8)


def draw_3d_box(
    img: np.ndarray,
    K: np.ndarray,
    T_camera_obj: np.ndarray,
    bounds_m: np.ndarray,
    colour: Sequence[int] = (255, 255, 0),
    thickness: int = 1,
) -> np.ndarray:
    """The object's bounding box (``bounds_m`` (2, 3) in its frame) at pose ``T_camera_obj``, projected with ``K``.

    Edges are straight lines between the projected corners (pinhole, no distortion), so every drawn pixel lies in
    the convex hull of the projected corners, widened by the line thickness.
    """
    out = _as_rgb(img)
    p_cam = transform_points(np.asarray(T_camera_obj, dtype=float), box_corners_m(bounds_m))
    _draw_segments(out, K, p_cam, BOX_EDGES, [colour] * len(BOX_EDGES), thickness)
    return out


def draw_axes(
    img: np.ndarray, K: np.ndarray, T_camera_obj: np.ndarray, length_m: float, thickness: int = 2
) -> np.ndarray:
    """The object frame's axes at pose ``T_camera_obj``: x red, y green, z blue, each ``length_m`` long."""
    if not length_m > 0:
        raise ValueError(f"length_m: expected > 0, got {length_m}")
    out = _as_rgb(img)
    p_obj = np.vstack([np.zeros(3), np.eye(3) * float(length_m)])
    p_cam = transform_points(np.asarray(T_camera_obj, dtype=float), p_obj)
    _draw_segments(out, K, p_cam, ((0, 1), (0, 2), (0, 3)), AXIS_COLOURS, thickness)
    return out


def depth_colormap(
    depth_m: np.ndarray, near_m: float | None = None, far_m: float | None = None, colormap: int = cv2.COLORMAP_TURBO
) -> np.ndarray:
    """(H, W) depth in metres -> (H, W, 3) RGB uint8 picture; near is warm (red), far is cold (blue), 0 is black.

    ``near_m`` / ``far_m`` default to the 1st / 99th percentile of the valid depths, so a few far floor pixels do
    not wash out the parts.
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth_m: expected an (H, W) array, got shape {depth.shape}")
    valid = np.isfinite(depth) & (depth > 0)
    if not valid.any():
        return np.zeros((*depth.shape, 3), dtype=np.uint8)
    lo, hi = np.percentile(depth[valid], [1, 99])
    lo = float(lo if near_m is None else near_m)
    hi = float(hi if far_m is None else far_m)
    scaled = np.clip((np.where(valid, depth, hi) - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    bgr = cv2.applyColorMap(np.round(255 * (1.0 - scaled)).astype(np.uint8), colormap)
    rgb = bgr[..., ::-1].copy()
    rgb[~valid] = 0
    return rgb


def put_caption(img: np.ndarray, text: str, colour: Sequence[int] = (255, 255, 255)) -> np.ndarray:
    """``text`` in the top-left corner on a dark strip, readable on any background."""
    out = _as_rgb(img)
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_PLAIN, 1.0, 1)
    cv2.rectangle(out, (0, 0), (min(w + 6, out.shape[1] - 1), h + base + 4), (0, 0, 0), -1)
    cv2.putText(out, text, (3, h + 3), cv2.FONT_HERSHEY_PLAIN, 1.0, _colour(colour), 1, cv2.LINE_AA)
    return out


def compose_grid(images: Sequence[np.ndarray], cols: int, pad_px: int = 4, background: int = 255) -> np.ndarray:
    """Tiles RGB images of one size into ``ceil(n / cols)`` rows of ``min(cols, n)``, ``pad_px`` apart and around.

    The result is ``rows * H + (rows + 1) * pad_px`` high and ``c * W + (c + 1) * pad_px`` wide, ``c = min(cols, n)``.
    """
    if not images:
        raise ValueError("images: expected at least one image")
    if cols < 1:
        raise ValueError(f"cols: expected >= 1, got {cols}")
    tiles = [_as_rgb(im) for im in images]
    h, w = tiles[0].shape[:2]
    for i, t in enumerate(tiles):
        if t.shape[:2] != (h, w):
            raise ValueError(f"images[{i}]: expected {w}x{h} like images[0], got {t.shape[1]}x{t.shape[0]}")
    c = min(cols, len(tiles))
    rows = math.ceil(len(tiles) / c)
    grid = np.full((rows * h + (rows + 1) * pad_px, c * w + (c + 1) * pad_px, 3), background, dtype=np.uint8)
    for i, t in enumerate(tiles):
        r, k = divmod(i, c)
        y, x = pad_px + r * (h + pad_px), pad_px + k * (w + pad_px)
        grid[y : y + h, x : x + w] = t
    return grid


def draw_annotation(
    ann: ImageAnnotation,
    rgb: np.ndarray,
    bounds_m: dict[int, np.ndarray],
    min_visib_fract: float = 0.0,
    axis_fraction: float = 0.5,
) -> np.ndarray:
    """One item's ground truth over its RGB image: visible-mask outlines, visible 2D boxes labelled with the
    ``obj_id``, 3D boxes and pose axes (axis length ``axis_fraction`` of the box's largest side), in one colour per
    instance. ``bounds_m``: obj_id -> (2, 3) model bounds; instances whose obj_id is missing get no 3D box/axes.
    Instances seen less than ``min_visib_fract`` are left out (their pose is drawn through other parts otherwise).
    """
    out = _as_rgb(rgb)
    K = ann.intrinsics.K
    shown = [i for i in ann.instances if i.px_count_visib > 0 and i.visib_fract >= min_visib_fract]
    colours = instance_colours(len(ann.instances))
    for inst in shown:
        colour = colours[inst.inst_id % len(colours)]
        out = draw_mask_outlines(out, inst.mask_visib[None], colour[None])
        out = draw_bbox(out, inst.bbox_visib, colour, label=str(inst.obj_id))
        if inst.obj_id in bounds_m:
            b = np.asarray(bounds_m[inst.obj_id], dtype=float).reshape(2, 3)
            out = draw_3d_box(out, K, inst.T_camera_obj, b, colour)
            out = draw_axes(out, K, inst.T_camera_obj, axis_fraction * float(np.max(b[1] - b[0])), thickness=1)
    return out
