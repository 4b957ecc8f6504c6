"""Decoded training images kept in memory, so that only the first epoch reads and decodes them.

An example is built from one image (or four, for a mosaic) and its instance-id map: the PNG decode and the masks'
RLE decode (``data.load_instances``) are most of the data thread's work: on a 2-core CPU it takes its time from the
network's, and on a GPU, whose step is short, it would set the pace. Kept decoded, an image costs ``h x w x 3``
bytes and its id map ``h x w`` bytes (2 with more than 255 instances), about 1.2 MB for a 640 x 480 frame. The cache
fills as the first epoch reads each image (nothing is read ahead) and returns copies of exactly what
``load_instances`` returns, so a run is the same with or without it, resumed or not.

``mode``: ``"ram"`` keeps every image; ``"none"`` keeps none; ``"auto"`` keeps them when all of them fit in
``AUTO_FRACTION`` of the memory available when the run starts (``psutil``; ultralytics' ``cache="ram"`` checks the
available memory likewise, with its own margin). The train log's ``data_build_seconds`` and ``data_wait_seconds``
per epoch say what building the batches took and how much of it the network waited for.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import psutil

from sygrid.train.detector.config import CACHE_MODES
from sygrid.train.detector.data import DetectionDataset, load_instances

AUTO_FRACTION = 0.5  # "auto" caches when the whole dataset takes at most this share of the available memory


@dataclass(frozen=True)
class CachePlan:
    """Whether the run keeps decoded images, what that takes (bytes, estimated from the labels) and what the
    machine had available when it was decided."""

    enabled: bool
    mode: str
    bytes_needed: int
    bytes_available: int

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def cache_bytes(dataset: DetectionDataset, splits: tuple[str, ...] = ("train", "val")) -> int:
    """The memory ``splits`` take decoded: image and id map per image, from the COCO ground truth's image sizes."""
    total = 0
    for split in splits:
        images = dataset.coco_gt[split]["images"]  # in the order of the split's labels
        for image, labels in zip(images, dataset.labels[split], strict=True):
            total += image["height"] * image["width"] * (3 + _ids_dtype(len(labels.classes)).itemsize)
    return total


def plan_cache(dataset: DetectionDataset, mode: str) -> CachePlan:
    """``mode`` (``CACHE_MODES``) decided for ``dataset`` on this machine."""
    if mode not in CACHE_MODES:
        raise ValueError(f"cache: expected one of {CACHE_MODES}, got {mode!r}")
    needed, available = cache_bytes(dataset), int(psutil.virtual_memory().available)
    enabled = mode == "ram" or (mode == "auto" and needed <= AUTO_FRACTION * available)
    return CachePlan(enabled, mode, needed, available)


class InstanceCache:
    """``load(split, index)``: ``data.load_instances``' image, instance-id map (int32) and classes, from memory
    after the first read when ``enabled``. Used from one data thread at a time."""

    def __init__(self, dataset: DetectionDataset, enabled: bool) -> None:
        self.dataset, self.enabled = dataset, enabled
        self._kept: dict[tuple[str, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self._kept)

    def load(self, split: str, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        key = (split, index)
        kept = self._kept.get(key)
        if kept is None:
            image, ids, classes = load_instances(self.dataset, split, index)
            if not self.enabled:
                return image, ids, classes
            kept = (image, ids.astype(_ids_dtype(len(classes))), classes)
            for array in kept:
                array.flags.writeable = False
            self._kept[key] = kept
        image, ids, classes = kept
        return image.copy(), ids.astype(np.int32), classes.copy()


def _ids_dtype(instances: int) -> np.dtype:
    """The smallest unsigned type that holds instance ids 0..instances."""
    return np.dtype(np.uint8 if instances < 256 else np.uint16 if instances < 65536 else np.int32)
