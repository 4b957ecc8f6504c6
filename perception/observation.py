"""A detection's view of the frame: a crop of the depth image around it with the part's mask.

The pose strategies, the mask clean-up and the verification work inside this crop, so that nothing per hypothesis
touches the whole image.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from perception.results import Detection
from sygrid.camera import CameraIntrinsics

# A detection's crop: its box widened by this fraction of its longer side on each side (and at least MARGIN_MIN_PX),
# room for the verification to see a wrong hypothesis stick out of the mask.
MARGIN_FRACTION = 0.5
MARGIN_MIN_PX = 8


@dataclass(frozen=True, eq=False)
class Observation:
    """What a detection's poses are verified against: a crop of the depth image and the part's (cleaned) mask.

    ``depth_m``: (h, w) float64 metres, 0 = no data; ``mask``: (h, w) bool; ``x0, y0``: the crop's top-left pixel
    in the image; ``intrinsics``: the full image's camera; ``support``: ``(a, b, c, d)`` the surface the part lies
    on (camera frame, unit normal towards the camera), None where unknown: no part of it can lie below;
    ``silhouette``: (h, w) bool, the segmenter's mask before any clean-up (None: ``mask`` is that mask): where the
    part is seen, whatever its depth pixels hold. The arrays are not modified once the observation is built (the
    mask's box is computed once).
    """

    depth_m: np.ndarray
    mask: np.ndarray
    x0: int
    y0: int
    intrinsics: CameraIntrinsics
    support: np.ndarray | None = None
    silhouette: np.ndarray | None = None

    @classmethod
    def crop(
        cls, depth_m: np.ndarray, mask: np.ndarray, intrinsics: CameraIntrinsics, box: tuple[int, int, int, int]
    ) -> Observation:
        """The observation inside ``box`` ``[x0, y0, x1, y1)`` (clipped to the image) of full-size arrays."""
        x0, y0 = max(int(box[0]), 0), max(int(box[1]), 0)
        x1, y1 = min(int(box[2]), intrinsics.width), min(int(box[3]), intrinsics.height)
        depth = np.asarray(depth_m[y0:y1, x0:x1], dtype=np.float64)
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
        return cls(depth, np.asarray(mask[y0:y1, x0:x1], dtype=bool), x0, y0, intrinsics)

    @property
    def points(self) -> np.ndarray:
        """(n, 3) camera-frame points [m] of the mask's pixels with depth."""
        ys, xs = np.nonzero(self.mask & (self.depth_m > 0))
        z = self.depth_m[ys, xs]
        K = self.intrinsics.K
        return np.column_stack([(xs + self.x0 - K[0, 2]) * z / K[0, 0], (ys + self.y0 - K[1, 2]) * z / K[1, 1], z])

    @classmethod
    def of_detection(cls, depth_m: np.ndarray, detection: Detection, intrinsics: CameraIntrinsics) -> Observation:
        """The crop around ``detection``'s box (widened by ``MARGIN_FRACTION`` of its longer side) with its mask;
        the detection must have a mask."""
        if detection.mask is None:
            raise ValueError("Observation.of_detection: the detection has no mask")
        x0, y0, x1, y1 = np.asarray(detection.bbox_xyxy, dtype=float)
        margin = max(MARGIN_MIN_PX, MARGIN_FRACTION * max(x1 - x0, y1 - y0))
        box = (
            int(np.floor(x0 - margin)),
            int(np.floor(y0 - margin)),
            int(np.ceil(x1 + margin)),
            int(np.ceil(y1 + margin)),
        )
        return cls.crop(depth_m, detection.mask, intrinsics, box)

    def with_mask(self, mask: np.ndarray, support: np.ndarray | None = None) -> Observation:
        """The same crop with another (h, w) mask (and support, where given); the silhouette stays the first mask's."""
        support = self.support if support is None else np.asarray(support, dtype=float)
        mask = np.asarray(mask, dtype=bool)
        return Observation(self.depth_m, mask, self.x0, self.y0, self.intrinsics, support, self.seen_mask)

    @cached_property
    def mask_box(self) -> tuple[int, int, int, int] | None:
        """The mask's bounding box ``[x0, y0, x1, y1)`` in crop pixels; None for an empty mask."""
        rows, cols = np.flatnonzero(self.mask.any(axis=1)), np.flatnonzero(self.mask.any(axis=0))
        return (int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1) if len(rows) else None

    @property
    def seen_mask(self) -> np.ndarray:
        """(h, w) bool: the segmenter's silhouette of the part (``silhouette``, else ``mask``)."""
        return self.mask if self.silhouette is None else self.silhouette
