"""Pose hypothesis verification: the model rendered at a pose must agree with the observed depth and mask.

The model's depth is ray-cast (open3d ``RaycastingScene``, one scene per model, cached) through the pixels of a
window around the detection's mask and the model's projected box (``perception.observation``'s crop). Every rendered
pixel with a depth measurement is one of:

- an inlier: the observed depth lies within the tolerance of the rendered depth;
- a violation of free space: the observed surface lies behind the model (the model would hide it, so it cannot be
  there), or, inside the mask, the observed part surface lies in front of the model (the model sits too deep), or
  the model reaches below the surface the part lies on (the observation's ``support``);
- occluded: outside the mask, something lies in front of the model (another part): no evidence either way.

``fit`` is the inlier fraction of the rendered pixels that are not occluded (does the model's visible surface lie
where depth says a surface is), ``coverage`` the fraction of the mask's depth pixels that rendered inliers explain
(does the model account for what was segmented: a smaller part's model fitted into a larger part's mask covers only
some of it; 1 where the mask holds no depth pixel to explain); mask pixels the model leaves open whose depth lies
behind the model's surface next to them are background seen past the part (through its hole, around its edge) and do
not count. ``iou`` is the silhouette IoU of the unoccluded rendering and the segmenter's mask as it was before the
depth clean-up (the observation's ``silhouette``, less its background seen past the part as above; the model's own
holes count neither way, as a segmenter may fill them, and so do the model's pixels outside the mask where the depth
shows its surface clear of the support, which an under-segmenting detector missed): where depth cannot speak (no
data on specular metal, a thin part whose top quantises to the floor's depth, a fragment of a buried part), the
outline still does. With footprints (the verdict), a pixel the model's outline crosses counts neither way either.
The pose's confidence is ``sqrt(fit * coverage * iou)`` in [0, 1] (the depth's agreement ``sqrt(fit * coverage)``
times the outline's ``sqrt(iou)``); it is accepted when the confidence reaches ``min_confidence`` (or the part's own
threshold, ``part_min_confidence``).

The verdict (``verify(..., footprint=True)``) compares each pixel's observed depth with the range of the model's
depth over the pixel's footprint (its centre and four corners, ray-cast where the model has a silhouette or a depth
step nearby), not with the depth at its centre alone: an edge's position is known to a pixel at best, and a depth
pixel at a discontinuity (one leg of a bracket over the other) holds either side or a mix of both (a renderer's
filter, a stereo matcher's flying pixels). An observed depth within that range is an inlier; a mask pixel whose
footprint only touches the rendered silhouette counts neither way. Ranking poses against each other keeps the
centre's depth (the default): a score that forgives half a pixel cannot tell two poses half a pixel apart.

The tolerance is ``max(tolerance_min_m, tolerance_fraction x diameter)``, plus three standard deviations of the
camera's depth noise at the pixel's depth (``depth_noise_m`` at 1 m, growing with the square of the depth, the
stereo error model; ``VerifyConfig.for_sensor`` raises it to a sensor model's), plus a pixel's worth of the
surface's slope (``z / f x tan`` of the angle between the ray and the surface normal): where a face recedes steeply,
a sub-pixel shift of an edge changes the depth by millimetres.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import TYPE_CHECKING

import cv2
import numpy as np
import open3d as o3d

from perception.observation import Observation
from sygrid.camera import CameraIntrinsics, project_points
from sygrid.objects.model import ObjectModel

if TYPE_CHECKING:
    from sygrid.sensor import SensorModel


@dataclass(frozen=True)
class VerifyConfig:
    """Settings of the verification; lengths in metres unless named ``_fraction`` (x the object diameter).

    Attributes:
        tolerance_fraction: depth agreement tolerance, x the object diameter ...
        tolerance_min_m: ... and at least this.
        depth_noise_m: the camera's depth noise (one standard deviation) at 1 m; 0 for exact depth.
        min_confidence: a pose whose confidence is below this is refused ...
        part_min_confidence: ... unless its part has a threshold of its own here (model name -> threshold in
            [0, 1]; ``sygrid models choose-pose --per-part-thresholds`` chooses them, so that each part is held to
            what tells its right poses from its wrong ones).
        max_rays: rays cast at most per verification (a large window is sampled with a pixel stride).
        coarse_rays: rays cast at most for a coarse score (``align``, ranking unrefined hypotheses).
        window_margin_px: pixels added around the window (mask box united with the model's projected box).
        background_reach_fraction: a mask pixel the model leaves open counts as background seen past the part when
            its depth lies behind the model's farthest surface within this x diameter around it.
        threads: ray-casting threads (0: open3d's choice).
    """

    tolerance_fraction: float = 0.015
    tolerance_min_m: float = 0.001
    depth_noise_m: float = 0.0
    min_confidence: float = 0.7
    part_min_confidence: Mapping[str, float] = field(default_factory=dict)
    max_rays: int = 1500
    coarse_rays: int = 500
    window_margin_px: int = 4
    background_reach_fraction: float = 0.3
    threads: int = 2

    def __post_init__(self) -> None:
        if self.tolerance_fraction < 0 or self.tolerance_min_m <= 0 or self.depth_noise_m < 0:
            raise ValueError(
                "VerifyConfig: need tolerance_fraction >= 0, tolerance_min_m > 0 and depth_noise_m >= 0, got "
                f"{self.tolerance_fraction}, {self.tolerance_min_m}, {self.depth_noise_m}"
            )
        if (
            not 0.0 <= self.min_confidence <= 1.0
            or min(self.max_rays, self.coarse_rays) < 16
            or self.window_margin_px < 0
        ):
            raise ValueError(
                "VerifyConfig: need min_confidence in [0, 1], max_rays and coarse_rays >= 16 and window_margin_px >= 0,"
                f" got {self.min_confidence}, {self.max_rays}, {self.coarse_rays}, {self.window_margin_px}"
            )
        bad = {name: t for name, t in self.part_min_confidence.items() if not 0.0 <= t <= 1.0}
        if bad:
            raise ValueError(f"VerifyConfig: part_min_confidence must be in [0, 1], got {bad}")

    def threshold(self, part: str) -> float:
        """The confidence a pose of the part named ``part`` needs to be accepted."""
        return float(self.part_min_confidence.get(part, self.min_confidence))

    def for_sensor(self, sensor: SensorModel) -> VerifyConfig:
        """These settings for frames from ``sensor``: ``depth_noise_m`` at least the sensor's per-pixel depth noise at
        1 m (``SensorModel.depth_noise_sigma_m(1.0)``; 0 for the ideal sensor), this config's where higher. The one
        place the noise allowance follows the sensor: the pipeline, ``sygrid models choose-pose`` and the benchmark."""
        noise = float(sensor.depth_noise_sigma_m(1.0))
        return replace(self, depth_noise_m=noise) if noise > self.depth_noise_m else self


@dataclass(frozen=True)
class Verification:
    """How well a pose agrees with the observation. Fractions in [0, 1]; counts in (strided) pixels.

    ``confidence``: ``sqrt(fit * coverage * iou)``; ``accepted``: ``confidence >=`` the part's threshold
    (``VerifyConfig.threshold``). ``rmse_m``: the RMS depth residual of the inliers (the visible-surface
    discrepancy), NaN without inliers.
    """

    confidence: float
    accepted: bool
    fit: float
    coverage: float
    iou: float
    inliers: int
    violations: int
    occluded: int
    rendered: int
    mask_pixels: int
    rmse_m: float

    @property
    def depth_confidence(self) -> float:
        """``sqrt(fit * coverage)``: the depth's agreement alone, without the silhouette (the pose search's stopping
        rules: the depth already confirms the fit)."""
        return math.sqrt(self.fit * self.coverage)

    def as_dict(self) -> dict:
        return {k: (float(v) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


MAX_SLOPE = 5.0  # the slope term of the tolerance stops growing beyond this tangent (about 79 degrees)
VISIBLE_EPS_M = 3e-4  # a surface point is seen when the ray from the camera first hits within this of it


class ModelRaycaster:
    """Ray casting of one model in its own frame (rays are moved into the object frame, the scene never changes)."""

    def __init__(self, model: ObjectModel) -> None:
        self.model = model
        self._scene = o3d.t.geometry.RaycastingScene()
        vertices = o3d.core.Tensor(np.asarray(model.mesh.vertices, dtype=np.float32))
        faces = o3d.core.Tensor(np.asarray(model.mesh.faces, dtype=np.uint32))
        self._scene.add_triangles(vertices, faces)
        self.hull_vertices = np.asarray(model.mesh.convex_hull.vertices, dtype=np.float64)
        self.face_normals = np.asarray(model.mesh.face_normals, dtype=np.float64)

    def depth(
        self, T_camera_object: np.ndarray, rays_camera: np.ndarray, threads: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """z-depth [m] where each camera-frame ray (n, 3), direction with z = 1 from the camera centre, first hits
        the model at the pose (0 where it misses), and the tangent of the angle between the ray and the surface
        normal there (how steeply the surface recedes: depth changes by z / f x tan per pixel), at most
        ``MAX_SLOPE``."""
        R, t = T_camera_object[:3, :3], T_camera_object[:3, 3]
        rays = np.empty((len(rays_camera), 6), dtype=np.float32)
        rays[:, :3] = -(R.T @ t)
        rays[:, 3:] = rays_camera @ R  # R^T d for every row
        hit = self._scene.cast_rays(o3d.core.Tensor(rays), nthreads=threads)
        t_hit = hit["t_hit"].numpy()
        found = np.isfinite(t_hit)
        slope = np.zeros(len(t_hit))
        if found.any():
            d = rays[found, 3:].astype(np.float64)
            n = self.face_normals[hit["primitive_ids"].numpy()[found]]
            cos = np.abs((d * n).sum(axis=1)) / np.linalg.norm(d, axis=1)
            slope[found] = np.minimum(np.sqrt(np.maximum(1.0 - cos**2, 0.0)) / np.maximum(cos, 1e-6), MAX_SLOPE)
        return np.where(found, t_hit, 0.0), slope  # |d| has z = 1 in the camera frame: t is the z-depth

    def visible(self, T_camera_object: np.ndarray, points: np.ndarray, threads: int = 0) -> np.ndarray:
        """(n,) bool: which object-frame surface ``points`` the camera sees at the pose (the first hit along the ray
        from the camera centre to the point is the point itself, within ``VISIBLE_EPS_M``)."""
        R, t = T_camera_object[:3, :3], T_camera_object[:3, 3]
        eye = -(R.T @ t)
        to_point = np.asarray(points, dtype=np.float64) - eye
        distance = np.linalg.norm(to_point, axis=1)
        rays = np.empty((len(points), 6), dtype=np.float32)
        rays[:, :3] = eye
        rays[:, 3:] = to_point / distance[:, None]
        t_hit = self._scene.cast_rays(o3d.core.Tensor(rays), nthreads=threads)["t_hit"].numpy()
        return t_hit >= distance - VISIBLE_EPS_M


@lru_cache(maxsize=64)
def raycaster(model: ObjectModel) -> ModelRaycaster:
    """The cached ray-casting scene of ``model``."""
    return ModelRaycaster(model)


def _window(obs: Observation, T: np.ndarray, caster: ModelRaycaster, margin: int) -> tuple[int, int, int, int] | None:
    """The pixel window ``[x0, y0, x1, y1)`` in crop pixels: the mask's box united with the model's projected box,
    widened by ``margin`` and clipped to the crop; None when empty."""
    h, w = obs.mask.shape
    x0, y0, x1, y1 = obs.mask_box or (w, h, 0, 0)
    p = caster.hull_vertices @ T[:3, :3].T + T[:3, 3]
    if (p[:, 2] > 1e-3).all():
        uv = project_points(obs.intrinsics.K, p) - (obs.x0, obs.y0)
        x0, y0 = min(x0, int(np.floor(uv[:, 0].min()))), min(y0, int(np.floor(uv[:, 1].min())))
        x1, y1 = max(x1, int(np.ceil(uv[:, 0].max())) + 1), max(y1, int(np.ceil(uv[:, 1].max())) + 1)
    x0, y0, x1, y1 = max(x0 - margin, 0), max(y0 - margin, 0), min(x1 + margin, w), min(y1 + margin, h)
    return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None


class PoseVerifier:
    """Scores poses against a depth image and a mask (``verify``); stateless per call, models' scenes cached."""

    def __init__(self, config: VerifyConfig | None = None) -> None:
        self.config = config if config is not None else VerifyConfig()

    def tolerance_m(
        self, model: ObjectModel, depth_m: np.ndarray | float, fraction: float | None = None
    ) -> np.ndarray | float:
        """The depth agreement tolerance [m] for ``model`` at the given depth(s); ``fraction`` overrides
        ``tolerance_fraction``."""
        cfg = self.config
        fraction = cfg.tolerance_fraction if fraction is None else fraction
        base = max(cfg.tolerance_min_m, fraction * float(model.diameter_m))
        return base + 3.0 * cfg.depth_noise_m * np.square(depth_m)

    def _render(
        self,
        T: np.ndarray,
        caster: ModelRaycaster,
        obs: Observation,
        window: tuple[int, int, int, int],
        rays: int,
        footprint: bool = False,
    ) -> _Rendering:
        """The model's depth ray-cast through ``window`` (crop pixels, strided to at most ``rays``) with the
        observation at the same pixels; ``footprint``: with the depth range over each pixel's footprint."""
        cfg = self.config
        x0, y0, x1, y1 = window
        stride = max(1, math.ceil(math.sqrt((x1 - x0) * (y1 - y0) / rays)))
        u = np.arange(x0, x1, stride) + obs.x0
        v = np.arange(y0, y1, stride) + obs.y0
        K = obs.intrinsics.K
        dirs = np.empty((len(v), len(u), 3))
        dirs[..., 0] = ((u - K[0, 2]) / K[0, 0])[None, :]
        dirs[..., 1] = ((v - K[1, 2]) / K[1, 1])[:, None]
        dirs[..., 2] = 1.0
        shape = (len(v), len(u))
        rendered, slope = caster.depth(T, dirs.reshape(-1, 3), cfg.threads)
        rendered, slope = rendered.reshape(shape), slope.reshape(shape)
        partial = None
        if footprint:
            lo, hi, partial = _pixel_range(rendered, caster, T, dirs, obs.intrinsics, cfg)
        else:
            lo, hi = _centre_range(rendered)
        height = None
        if obs.support is not None:  # the height of the model's surface above the support
            height = rendered * (dirs @ obs.support[:3]) + float(obs.support[3])
        return _Rendering(
            rendered,
            slope,
            obs.depth_m[y0:y1:stride, x0:x1:stride],
            obs.mask[y0:y1:stride, x0:x1:stride],
            obs.seen_mask[y0:y1:stride, x0:x1:stride],
            height,
            stride,
            lo,
            hi,
            partial,
        )

    def verify(
        self,
        T_camera_object: np.ndarray,
        model: ObjectModel,
        obs: Observation,
        tolerance_fraction: float | None = None,
        footprint: bool = False,
    ) -> Verification:
        """The agreement of ``model`` at ``T_camera_object`` with the observation; a pose that renders nothing in
        the crop gets confidence 0. ``tolerance_fraction`` overrides the configured one (a coarse score for
        ranking unrefined hypotheses). ``footprint``: each pixel compared over its footprint (the verdict);
        False: at its centre (ranking poses)."""
        return self.align(T_camera_object, model, obs, tolerance_fraction, move=False, footprint=footprint)[1]

    def align(
        self,
        T_camera_object: np.ndarray,
        model: ObjectModel,
        obs: Observation,
        tolerance_fraction: float | None = None,
        move: bool = True,
        footprint: bool = False,
    ) -> tuple[np.ndarray, Verification]:
        """The pose moved along its viewing ray so that the rendered model meets the observed surface (the median
        of observed minus rendered depth over the mask's pixels where both exist), and its verification, from one
        rendering (the moved pose's depths are the rendered ones scaled by the move, its silhouette taken as
        unchanged), at most ``coarse_rays``. ``move`` False: the pose as given and its exact verification;
        ``footprint`` as in ``verify``."""
        cfg = self.config
        T = np.array(T_camera_object, dtype=np.float64)
        caster = raycaster(model)
        window = _window(obs, T, caster, cfg.window_margin_px) if np.isfinite(T).all() and T[2, 3] > 0 else None
        if window is None:
            return T, _empty(int(obs.mask.sum()))
        r = self._render(T, caster, obs, window, cfg.coarse_rays if move else cfg.max_rays, footprint)
        if move:
            both = r.in_mask & (r.rendered > 0) & (r.observed > 0)
            if both.any():
                scale = 1.0 + float(np.median(r.observed[both] - r.rendered[both])) / T[2, 3]
                T[:3, 3] *= scale
                r = replace(r, rendered=r.rendered * scale, lo=r.lo * scale, hi=r.hi * scale, height=None)
        return T, self._score(T, model, obs, r, tolerance_fraction)

    def _score(
        self, T: np.ndarray, model: ObjectModel, obs: Observation, r: _Rendering, tolerance_fraction: float | None
    ) -> Verification:
        """The verification figures from a rendering and the observation at the same (strided) pixels."""
        cfg = self.config
        rendered, slope, observed, in_mask, stride = r.rendered, r.slope, r.observed, r.in_mask, r.stride
        hit = rendered > 0
        valid = observed > 0
        near_hit = np.isfinite(r.lo)  # the model reaches into the pixel (its centre; with footprints, a corner)
        z = np.where(hit, rendered, np.where(near_hit, r.lo, 0.0))
        tol = self.tolerance_m(model, z, tolerance_fraction) + slope * z / obs.intrinsics.fx
        both = hit & valid
        with np.errstate(invalid="ignore"):  # inf - inf where the model does not reach the pixel
            within = valid & near_hit & (observed >= r.lo - tol) & (observed <= r.hi + tol)
            behind = both & (observed > r.hi + tol)  # the observed surface is behind the model: free space violated
            in_front = both & (observed < r.lo - tol)
        inlier = hit & within
        residual = observed - rendered
        violation = behind | (in_front & in_mask)
        support_tol = None if r.height is None else self.tolerance_m(model, rendered)
        if r.height is not None:  # the part cannot reach through what it lies on
            violation |= hit & (r.height < -support_tol)
        occluded = in_front & ~in_mask & ~violation
        n_inlier, n_violation = int(inlier.sum()), int(violation.sum())
        # Mask pixels the model leaves open whose depth lies behind the model's surface next to them are background
        # seen past the part (through its hole, around its edge in a loose mask): no part surface left unexplained,
        # and no part of the outline either.
        reach = cfg.background_reach_fraction * model.diameter_m * obs.intrinsics.fx / T[2, 3] / stride
        reach = max(2, math.ceil(reach))
        nearby = cv2.dilate(rendered.astype(np.float32), _disc(reach))
        past = valid & ~hit & (nearby > 0) & (observed > nearby + self.tolerance_m(model, nearby))
        background = in_mask & past
        n_mask = int((in_mask & valid & ~background & ~(within & ~hit)).sum())
        fit = n_inlier / (n_inlier + n_violation) if n_inlier + n_violation else 0.0
        # no depth in the mask to explain (a dropout over the whole part): coverage cannot speak either way, and
        # the fit and the outline decide
        coverage = int((inlier & in_mask).sum()) / n_mask if n_mask else 1.0
        seen, silhouette = hit & ~occluded, r.in_silhouette & ~past
        counted = ~mask_holes(hit)  # the model's own holes: a segmenter may fill them
        if r.height is not None:  # the model's surface where depth shows it, clear of the support: the mask missed it
            counted &= ~(inlier & ~silhouette & (r.height > support_tol))
        if r.partial is not None:  # an outline pixel the model half covers counts neither way
            counted &= ~r.partial
        union = int(((seen | silhouette) & counted).sum())
        iou = int((seen & silhouette & counted).sum()) / union if union else 0.0
        confidence = math.sqrt(fit * coverage * iou)
        rmse = float(np.sqrt(np.mean(np.square(residual[inlier])))) if n_inlier else math.nan
        return Verification(
            confidence=confidence,
            accepted=confidence >= cfg.threshold(model.name),
            fit=fit,
            coverage=coverage,
            iou=iou,
            inliers=n_inlier,
            violations=n_violation,
            occluded=int(occluded.sum()),
            rendered=int(hit.sum()),
            mask_pixels=n_mask,
            rmse_m=rmse,
        )


@dataclass(frozen=True)
class _Rendering:
    """The model's z-depth and slope at (strided) crop pixels, the observed depth, mask and silhouette there, the
    rendered surface's height above the observation's support (None without one), the pixel stride, and the model's
    depth range within one pixel (``_pixel_range``) and, with footprints, which pixels the model's outline crosses
    (``partial``; None without)."""

    rendered: np.ndarray
    slope: np.ndarray
    observed: np.ndarray
    in_mask: np.ndarray
    in_silhouette: np.ndarray
    height: np.ndarray | None
    stride: int
    lo: np.ndarray
    hi: np.ndarray
    partial: np.ndarray | None = None


_CORNERS = np.array([(-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5), (0.5, 0.5)])  # a pixel's footprint, in pixels
_KERNEL_3X3 = np.ones((3, 3), np.uint8)


def mask_holes(mask: np.ndarray) -> np.ndarray:
    """(h, w) bool: the pixels outside ``mask`` that no 4-connected path of outside pixels joins to the border
    (``scipy.ndimage.binary_fill_holes(mask) & ~mask``). A flood fill from the border in OpenCV: one pass, where
    scipy's dilates to convergence, and this runs in every verification."""
    # a free border joins every outside pixel that reaches the edge
    padded = cv2.copyMakeBorder(mask.astype(np.uint8), 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
    cv2.floodFill(padded, None, (0, 0), 1, flags=4)
    return padded[1:-1, 1:-1] == 0


@lru_cache(maxsize=32)
def _disc(radius: int) -> np.ndarray:
    """The elliptical structuring element of ``radius`` pixels (cached: every verification dilates with one)."""
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _centre_range(rendered: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The model's z-depth range at each pixel's centre alone: the rendered depth twice (inf and -inf where the
    centre's ray misses; ``rendered`` 0 = miss)."""
    hit = rendered > 0
    return np.where(hit, rendered, np.inf), np.where(hit, rendered, -np.inf)


def _pixel_range(
    rendered: np.ndarray,
    caster: ModelRaycaster,
    T: np.ndarray,
    dirs: np.ndarray,
    intrinsics: CameraIntrinsics,
    cfg: VerifyConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The nearest and farthest model z-depth over each (strided) pixel's footprint (its centre and corners; inf
    and -inf where no ray there hits), and which pixels the model's outline crosses (some of those rays hit it,
    some miss). ``rendered``: (h, w) z-depth at the centres, 0 = miss; ``dirs``: (h, w, 3)
    their rays. The corners are ray-cast only where the grid's 3 x 3 neighbourhood holds a silhouette or a depth
    step of more than ``tolerance_min_m`` (a smooth surface's slope is the tolerance's slope term); elsewhere the
    range is the centre's (``_centre_range``)."""
    hit = rendered > 0
    near = cv2.erode(np.where(hit, rendered, np.inf).astype(np.float32), _KERNEL_3X3)
    far = cv2.dilate(np.where(hit, rendered, -np.inf).astype(np.float32), _KERNEL_3X3)
    any_miss = cv2.dilate((~hit).astype(np.uint8), _KERNEL_3X3).astype(bool)
    with np.errstate(invalid="ignore", over="ignore"):  # inf - inf where nothing is hit
        edge = (any_miss & np.isfinite(near)) | (far - near > cfg.tolerance_min_m)
    lo, hi = _centre_range(rendered)
    partial = np.zeros(hit.shape, dtype=bool)
    if edge.any():
        d = dirs[edge]  # (m, 3)
        corners = (d[None, :, :2] + (_CORNERS / (intrinsics.fx, intrinsics.fy))[:, None, :]).reshape(-1, 2)
        z, _ = caster.depth(T, np.column_stack([corners, np.ones(len(corners))]), cfg.threads)
        z = z.reshape(len(_CORNERS), -1)
        z_hit = z > 0
        lo[edge] = np.minimum(lo[edge], np.where(z_hit, z, np.inf).min(axis=0))
        hi[edge] = np.maximum(hi[edge], np.where(z_hit, z, -np.inf).max(axis=0))
        partial[edge] = (z_hit.any(axis=0) | hit[edge]) & ~(z_hit.all(axis=0) & hit[edge])
    return lo, hi, partial


def _empty(mask_pixels: int) -> Verification:
    return Verification(0.0, False, 0.0, 0.0, 0.0, 0, 0, 0, 0, mask_pixels, math.nan)
