"""Letterboxing: an image resized with its aspect ratio kept and padded into a network input, and back.

One rule for training (``sygrid.train.detector``) and inference (``perception.detector``), as ultralytics uses it:
scale to fit, centre, pad with grey 114; a model with a dynamic input is padded only up to the next multiple of its
stride.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

PAD_VALUE = 114  # letterbox grey, as ultralytics trains and exports with it


@dataclass(frozen=True)
class Letterbox:
    """How an image of ``image_hw`` was placed in a network input of ``input_hw``.

    The image was resized to ``resized_hw`` and its top-left corner put at ``(pad_left, pad_top)`` input pixels;
    an image pixel coordinate ``x`` (continuous, 0 at the left edge) sits at input ``x * scale_x + pad_left``.
    """

    image_hw: tuple[int, int]
    input_hw: tuple[int, int]
    resized_hw: tuple[int, int]
    pad_left: int
    pad_top: int

    @property
    def scale_x(self) -> float:
        return self.resized_hw[1] / self.image_hw[1]

    @property
    def scale_y(self) -> float:
        return self.resized_hw[0] / self.image_hw[0]

    def boxes_to_image(self, boxes_xyxy: np.ndarray) -> np.ndarray:
        """(n, 4) ``[x0, y0, x1, y1]`` input pixels -> image pixels, clipped to the image."""
        out = np.asarray(boxes_xyxy, dtype=np.float64).copy()
        out[:, 0::2] = (out[:, 0::2] - self.pad_left) / self.scale_x
        out[:, 1::2] = (out[:, 1::2] - self.pad_top) / self.scale_y
        h, w = self.image_hw
        out[:, 0::2] = out[:, 0::2].clip(0.0, w)
        out[:, 1::2] = out[:, 1::2].clip(0.0, h)
        return out


def letterbox_geometry(image_hw: tuple[int, int], input_hw: tuple[int, int], stride: int | None) -> Letterbox:
    """Where an ``image_hw`` image goes in a network input of (at most) ``input_hw``.

    ``stride`` None: the input is exactly ``input_hw``. With a stride (a model with a dynamic input), the padding is
    reduced to what makes each side a multiple of the stride.
    """
    h, w = image_hw
    in_h, in_w = input_hw
    r = min(in_h / h, in_w / w)
    new_h, new_w = max(1, round(h * r)), max(1, round(w * r))
    pad_h, pad_w = in_h - new_h, in_w - new_w
    if stride is not None:
        pad_h, pad_w = pad_h % stride, pad_w % stride
    return _centred((h, w), (new_h, new_w), (pad_h, pad_w))


def letterbox_at_scale(image_hw: tuple[int, int], scale: float, stride: int) -> Letterbox:
    """An ``image_hw`` image resized by ``scale`` and padded (centred) up to the next multiple of ``stride``: how a
    model with a dynamic input sees a region of a frame at the scale it sees the whole frame at."""
    h, w = image_hw
    new_h, new_w = max(1, round(h * scale)), max(1, round(w * scale))
    return _centred((h, w), (new_h, new_w), (-new_h % stride, -new_w % stride))


def _centred(image_hw: tuple[int, int], resized_hw: tuple[int, int], pad_hw: tuple[int, int]) -> Letterbox:
    """The resized image centred in its padding; the 0.1 breaks ties so that an odd padding puts the extra pixel at
    the bottom/right."""
    (new_h, new_w), (pad_h, pad_w) = resized_hw, pad_hw
    top, left = round(pad_h / 2 - 0.1), round(pad_w / 2 - 0.1)
    return Letterbox(image_hw, (new_h + pad_h, new_w + pad_w), resized_hw, int(left), int(top))


def letterbox(image: np.ndarray, geometry: Letterbox, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """Resize + pad an (h, w[, c]) image to ``geometry.input_hw`` (grey 114 for colour images, 0 for id maps)."""
    new_h, new_w = geometry.resized_hw
    resized = (
        image if image.shape[:2] == (new_h, new_w) else cv2.resize(image, (new_w, new_h), interpolation=interpolation)
    )
    in_h, in_w = geometry.input_hw
    top, left = geometry.pad_top, geometry.pad_left
    value = (PAD_VALUE,) * 3 if image.ndim == 3 else 0
    return cv2.copyMakeBorder(
        resized, top, in_h - new_h - top, left, in_w - new_w - left, cv2.BORDER_CONSTANT, value=value
    )
