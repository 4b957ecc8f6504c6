"""Training samples for the pose network from a BOP dataset: RoI crops with dynamic zoom-in and colour jitter, and
the dense targets (object coordinates, visible mask) ray-cast from the ground-truth pose.

Indexing reads each image once and keeps, per instance, only a crop large enough for every zoom-in the
augmentation can draw, at native resolution and PNG-compressed in memory (several times smaller than raw, and
cheap to decode), so an epoch needs no disk access.

Targets are exact rather than warped from full-resolution maps: the object coordinates of each output cell are the
first hit of the ray through the cell centre with the model at its ground-truth pose (open3d's ``RaycastingScene``,
built once per model in the object frame; the rays are moved into it instead). A cell counts as visible where the
ray hits the model and the rendered visible mask, sampled bilinearly there, is at least one half (which removes what
other parts and the bin occlude). Parts are small in the images (18-90 px), so warping a full-resolution map with
nearest-neighbour sampling, as GDR-Net does, would give blocky targets.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
from tqdm import tqdm

from sygrid.errors import ConfigError
from sygrid.fileio import read_json
from sygrid.objects.model import ObjectModel
from sygrid.pose_geometry import (
    bop_bbox_to_xyxy,
    dynamic_zoom_roi,
    egocentric_to_allocentric,
    normalise_xyz,
    roi_affine,
    roi_grid,
    roi_ray_map,
    site_encode,
    square_roi,
)
from sygrid.train.pose.objects import ObjectTables
from sygrid.writers.bop import T_from_gt_json, encode_png

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SampleConfig:
    """RoI sampling. ``input_size``: network input side (px); ``output_size``: side of the dense outputs;
    ``pad_scale``: RoI side / box side; ``shift_ratio``, ``scale_ratio``: dynamic zoom-in ranges (fractions of the
    box); ``colour_jitter``: strength of the colour augmentation (0 disables it)."""

    input_size: int = 64
    output_size: int = 32
    pad_scale: float = 1.5
    shift_ratio: float = 0.25
    scale_ratio: float = 0.25
    colour_jitter: float = 1.0

    def __post_init__(self) -> None:
        if self.input_size < 16 or self.input_size % self.output_size:
            raise ValueError(
                f"input_size {self.input_size} must be >= 16 and a multiple of output_size {self.output_size}"
            )

    @property
    def crop_margin(self) -> float:
        """Half side of the stored crop in units of the box's longer side: covers every zoom-in drawn."""
        return self.pad_scale * (1.0 + self.scale_ratio) / 2.0 + self.shift_ratio + 0.05


@dataclass(frozen=True, eq=False)
class InstanceCrop:
    """One annotated instance, with the image region around it.

    ``origin_xy``: image pixel of the crop's top-left; ``rgb_png`` (RGB stored as a BGR PNG) and ``mask_png``
    (visible mask, 255 visible) are the encoded crop; ``rgb()`` and ``mask_visib()`` decode them.
    ``bbox_xyxy``: visible box, outer pixel edges (``sygrid.pose_geometry``).
    ``source``: ``split/scene/image/instance`` for messages.
    """

    obj_id: int
    class_index: int
    T_camera_obj: np.ndarray
    K: np.ndarray
    bbox_xyxy: np.ndarray
    visib_fract: float
    origin_xy: tuple[int, int]
    rgb_png: bytes
    mask_png: bytes
    source: str

    def rgb(self) -> np.ndarray:
        """(h, w, 3) uint8 RGB crop."""
        return np.ascontiguousarray(cv2.imdecode(np.frombuffer(self.rgb_png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1])

    def mask_visib(self) -> np.ndarray:
        """(h, w) uint8 visible mask crop (255 visible)."""
        return cv2.imdecode(np.frombuffer(self.mask_png, np.uint8), cv2.IMREAD_GRAYSCALE)


# ------------------------------------------------------------------------------------------------ indexing
def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise ConfigError(f"{path}: missing (a BOP scene needs scene_gt.json, scene_gt_info.json, scene_camera.json)")
    return read_json(path, "BOP scene file")


def _read_image(path: Path, flags: int) -> np.ndarray:
    image = cv2.imread(str(path), flags)
    if image is None:
        raise ConfigError(f"{path}: missing or not a readable image")
    return image


def index_split(
    bop_root: str | Path,
    split: str,
    obj_ids: Sequence[int],
    config: SampleConfig,
    min_visib_fract: float = 0.2,
    min_visib_px: int = 30,
    max_images: int | None = None,
    progress: bool = True,
) -> list[InstanceCrop]:
    """Every instance of ``split`` (e.g. ``train_pbr``) of the trained ``obj_ids`` that is visible enough.

    ``min_visib_fract``: drop instances with less of their silhouette visible; ``min_visib_px``: and fewer visible
    pixels. A missing split gives an empty list (a dataset may have no val_pbr).
    """
    split_dir = Path(bop_root) / split
    if not split_dir.is_dir():
        return []
    wanted = sorted(int(i) for i in obj_ids)
    images = []
    for scene_dir in sorted(p for p in split_dir.iterdir() if p.is_dir() and p.name.isdigit()):
        gt = _read_json(scene_dir / "scene_gt.json")
        info = _read_json(scene_dir / "scene_gt_info.json")
        cams = _read_json(scene_dir / "scene_camera.json")
        images += [(scene_dir, key, gt[key], info.get(key), cams.get(key)) for key in sorted(gt, key=int)]
    if max_images is not None:
        images = images[:max_images]
    crops: list[InstanceCrop] = []
    for scene_dir, key, gt_list, info_list, cam in tqdm(images, desc=f"index {split}", disable=not progress):
        where = f"{scene_dir}/scene_*.json[{key}]"
        if info_list is None or cam is None or len(info_list) != len(gt_list):
            raise ConfigError(f"{where}: scene_gt_info.json and scene_camera.json must have an entry per instance")
        keep = [
            g
            for g, (e, i) in enumerate(zip(gt_list, info_list, strict=True))
            if int(e["obj_id"]) in wanted
            and float(i.get("visib_fract", 0.0)) >= min_visib_fract
            and int(i.get("px_count_visib", 0)) >= min_visib_px
        ]
        if not keep:
            continue
        K = np.asarray(cam["cam_K"], dtype=np.float64).reshape(3, 3)
        im = f"{int(key):06d}"
        bgr = _read_image(scene_dir / "rgb" / f"{im}.png", cv2.IMREAD_COLOR)
        h, w = bgr.shape[:2]
        for g in keep:
            bbox = bop_bbox_to_xyxy(info_list[g]["bbox_visib"])
            side = max(bbox[2] - bbox[0], bbox[3] - bbox[1])
            centre = (bbox[:2] + bbox[2:]) / 2.0
            half = config.crop_margin * side + 2.0
            x0, y0 = (max(int(np.floor(c - half)), 0) for c in centre)
            x1, y1 = min(int(np.ceil(centre[0] + half)) + 1, w), min(int(np.ceil(centre[1] + half)) + 1, h)
            mask = _read_image(scene_dir / "mask_visib" / f"{im}_{g:06d}.png", cv2.IMREAD_GRAYSCALE)
            crops.append(
                InstanceCrop(
                    obj_id=int(gt_list[g]["obj_id"]),
                    class_index=wanted.index(int(gt_list[g]["obj_id"])),
                    T_camera_obj=T_from_gt_json(gt_list[g], f"{scene_dir / 'scene_gt.json'}[{key}][{g}]"),
                    K=K,
                    bbox_xyxy=bbox,
                    visib_fract=float(info_list[g]["visib_fract"]),
                    origin_xy=(x0, y0),
                    rgb_png=encode_png(np.ascontiguousarray(bgr[y0:y1, x0:x1]), "rgb crop"),
                    mask_png=encode_png(np.ascontiguousarray(mask[y0:y1, x0:x1]), "mask crop"),
                    source=f"{split}/{scene_dir.name}/{im}/{g}",
                )
            )
    return crops


# ------------------------------------------------------------------------------------------------ targets
class CoordinateRenderer:
    """Object coordinates seen through given pixels: ray casting against each model in its own frame."""

    def __init__(self, models: dict[int, ObjectModel]) -> None:
        self._scenes = {}
        for obj_id, model in models.items():
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(
                o3d.core.Tensor(np.asarray(model.mesh.vertices, dtype=np.float32)),
                o3d.core.Tensor(np.asarray(model.mesh.faces, dtype=np.uint32)),
            )
            self._scenes[obj_id] = scene

    def render(self, obj_id: int, T_camera_obj: np.ndarray, K: np.ndarray, pixels_xy: np.ndarray) -> np.ndarray:
        """(..., 2) image points -> (..., 3) object-frame points [m] of the first surface hit, NaN for a miss."""
        shape = pixels_xy.shape[:-1]
        uv = pixels_xy.reshape(-1, 2)
        d_cam = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))], axis=1)
        R, t = T_camera_obj[:3, :3], T_camera_obj[:3, 3]
        origin = -R.T @ t  # the camera centre in the object frame
        rays = np.empty((len(uv), 6), dtype=np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = d_cam @ R  # R^T d for each row
        t_hit = self._scenes[obj_id].cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
        points = origin[None] + t_hit[:, None] * (d_cam @ R)
        points[~np.isfinite(t_hit)] = np.nan
        return points.reshape(*shape, 3)


def colour_jitter(image: np.ndarray, rng: np.random.Generator, strength: float = 1.0) -> np.ndarray:
    """(h, w, 3) uint8 RGB -> float32 [0, 1] with random brightness, contrast, saturation, hue, per-channel gain,
    blur and noise (the path-traced and rasterised renders differ in all of these from a real camera)."""
    x = image.astype(np.float32) / 255.0
    if strength <= 0:
        return x
    s = float(strength)
    if rng.random() < 0.5:  # hue: rotate in HSV (OpenCV float HSV has H in degrees)
        hsv = cv2.cvtColor(x, cv2.COLOR_RGB2HSV)
        hsv[..., 0] = (hsv[..., 0] + rng.uniform(-10, 10) * s) % 360.0
        hsv[..., 1] = np.clip(hsv[..., 1] * rng.uniform(1 - 0.4 * s, 1 + 0.4 * s), 0, 1)
        x = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
    x = x * rng.uniform(1 - 0.3 * s, 1 + 0.3 * s) * rng.uniform(1 - 0.08 * s, 1 + 0.08 * s, size=3)
    mean = x.mean()
    x = (x - mean) * rng.uniform(1 - 0.3 * s, 1 + 0.3 * s) + mean
    if rng.random() < 0.3 * s:
        x = cv2.GaussianBlur(x, (0, 0), sigmaX=rng.uniform(0.3, 1.0))
    if rng.random() < 0.5 * s:
        x = x + rng.normal(0.0, rng.uniform(0.0, 0.03 * s), size=x.shape).astype(np.float32)
    return np.clip(x, 0.0, 1.0).astype(np.float32)


def make_sample(
    crop: InstanceCrop,
    tables: ObjectTables,
    renderer: CoordinateRenderer,
    config: SampleConfig,
    rng: np.random.Generator | None,
) -> dict[str, np.ndarray]:
    """One network input and its targets; ``rng`` None: no augmentation (the RoI of the box, as at run time).

    Returns float32 arrays: ``image`` (3, S, S) in [0, 1]; ``coord2d`` (2, s, s); ``xyz`` (3, s, s) normalised
    object coordinates (0 where not visible); ``xyz_m`` (3, s, s) metres (0 where not visible); ``visible``
    (s, s) 0/1; ``R_allo`` (3, 3); ``site`` (3,); ``class_index`` int64; ``roi`` (3,) centre x, y and size.
    """
    if rng is None:
        centre, size = square_roi(crop.bbox_xyxy, config.pad_scale)
    else:
        centre, size = dynamic_zoom_roi(crop.bbox_xyxy, rng, config.pad_scale, config.shift_ratio, config.scale_ratio)
    S, s = config.input_size, config.output_size
    origin = np.asarray(crop.origin_xy, dtype=np.float64)
    M = roi_affine(centre, size, S)
    M[:, 2] += M[:, :2] @ origin  # the crop's pixel (0, 0) is the image's origin_xy
    roi_rgb = cv2.warpAffine(crop.rgb(), M, (S, S), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    image = colour_jitter(roi_rgb, rng, config.colour_jitter) if rng is not None else roi_rgb / np.float32(255.0)

    grid = roi_grid(centre, size, s)  # (s, s, 2) image coordinates of the output cells
    points = renderer.render(crop.obj_id, crop.T_camera_obj, crop.K, grid)
    hit = np.isfinite(points[..., 0])
    local = (grid - origin).astype(np.float32)
    mask = cv2.remap(
        crop.mask_visib().astype(np.float32) / 255.0, local[..., 0], local[..., 1], cv2.INTER_LINEAR, borderValue=0.0
    )
    visible = hit & (mask >= 0.5)
    points = np.where(visible[..., None], points, 0.0)
    c = crop.class_index
    xyz = np.where(visible[..., None], normalise_xyz(points, tables.bounds_m[c]), 0.0)

    R, t = crop.T_camera_obj[:3, :3], crop.T_camera_obj[:3, 3]
    return {
        "image": np.ascontiguousarray(image.transpose(2, 0, 1), dtype=np.float32),
        "coord2d": roi_ray_map(centre, size, s, crop.K),
        "xyz": xyz.transpose(2, 0, 1).astype(np.float32),
        "xyz_m": points.transpose(2, 0, 1).astype(np.float32),
        "visible": visible.astype(np.float32),
        "R_allo": egocentric_to_allocentric(R, t).astype(np.float32),
        "site": site_encode(t, centre, size, crop.K, tables.diameters_m[c]).astype(np.float32),
        "class_index": np.int64(c),
        "roi": np.array([centre[0], centre[1], size], dtype=np.float64),
    }


def collate(samples: Sequence[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Stacks samples along a new batch axis."""
    return {k: np.stack([s[k] for s in samples]) for k in samples[0]}
