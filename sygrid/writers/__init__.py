"""Dataset writers, one module per format, chosen by name from ``WRITERS``.

Every writer is built as ``WRITERS[name](root, models, split=...)``, takes items with
``write(annotation, rgb, depth_m=None)`` (returns the item's paths) and ends with ``finish()`` (writes what is
assembled from the items, returns those paths); writers count files, they keep no list of them. All files go through
``sygrid.fileio``'s atomic writes.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Protocol

import numpy as np

from sygrid.annotations import ImageAnnotation
from sygrid.objects.model import ObjectModel
from sygrid.writers.bop import BopWriter as BopWriter
from sygrid.writers.bop import load_bop_item as load_bop_item
from sygrid.writers.bop import load_bop_true_depth as load_bop_true_depth
from sygrid.writers.coco import CocoWriter as CocoWriter
from sygrid.writers.yolo import YoloWriter as YoloWriter


class DatasetWriter(Protocol):
    """What the generator needs of a writer."""

    def __init__(self, root: str | Path, models: Sequence[ObjectModel], split: str = ...) -> None: ...

    def write(self, ann: ImageAnnotation, rgb: np.ndarray, depth_m: np.ndarray | None = None) -> list[Path]: ...

    def finish(self) -> list[Path]: ...


WRITERS: dict[str, type[DatasetWriter]] = {"bop": BopWriter, "yolo": YoloWriter, "coco": CocoWriter}


def create_writer(name: str, root: str | Path, models: Sequence[ObjectModel], **kwargs: object) -> DatasetWriter:
    """The writer registered as ``name``; an unknown name raises ValueError listing the valid ones."""
    if name not in WRITERS:
        raise ValueError(f"writer {name!r}: unknown format, expected one of {sorted(WRITERS)}")
    return WRITERS[name](root, models, **kwargs)
