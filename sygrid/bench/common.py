"""What every benchmark shares: where results go, medians, and the JSON/PNG writing."""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from sygrid.errors import ConfigError
from sygrid.fileio import read_json, write_json_atomic

DEFAULT_RESULTS_DIR = Path("bench/results")


def machine_info() -> dict:
    import os

    return {"machine": platform.machine(), "python": platform.python_version(), "cpus": os.cpu_count()}


def median(values: list[float]) -> float:
    return float(np.median(values)) if values else float("nan")


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def save_results(name: str, data: dict, figure, out_dir: Path = DEFAULT_RESULTS_DIR) -> tuple[Path, Path]:
    """Writes ``<name>.json`` and ``<name>.png`` into ``out_dir``; returns both paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    json_path = write_json_atomic(out_dir / f"{name}.json", {"machine": machine_info(), **data})
    return json_path, save_chart(name, figure, out_dir)


def save_chart(name: str, figure, out_dir: Path = DEFAULT_RESULTS_DIR) -> Path:
    """Writes ``<name>.png`` into ``out_dir`` (``save_results``'s chart alone: a redraw from saved results)."""
    png_path = out_dir / f"{name}.png"
    figure.savefig(png_path, dpi=110, bbox_inches="tight")
    return png_path


def add_result_arguments(parser: argparse.ArgumentParser, default_name: str) -> None:
    """``--name`` (the results' file name, ``default_name`` unless given) and ``--replot`` (redraw the chart from the
    saved results only): what every benchmark that keeps its results under a chosen name offers."""
    parser.add_argument("--name", default=default_name, help="result name: bench/results/NAME.{json,png}")
    parser.add_argument("--replot", action="store_true", help="only redraw the chart from the saved NAME.json")


def replot(name: str, chart, out_dir: Path = DEFAULT_RESULTS_DIR) -> Path:
    """Redraws ``<name>.png`` from the saved ``<name>.json`` alone (``chart``: results dict -> figure), with no
    measurement run; prints and returns the chart's path."""
    saved = read_json(out_dir / f"{name}.json", f"{name} benchmark results")
    path = save_chart(name, chart(saved), out_dir)
    print(f"redrew {path} from {out_dir / f'{name}.json'}")
    return path


class StageCheckpoint:
    """The finished stages of a long benchmark, kept in a JSON file so that a stopped run goes on where it stopped.

    ``settings`` (JSON-able) names what the stages measure; a checkpoint written for other settings is refused when
    resuming (ConfigError naming the file and the settings that differ), and overwritten when not. Each stage's
    result (JSON-able) is written as soon as it is done (atomically: a run killed while writing keeps the previous
    file); ``finish`` removes the file once the whole result is saved. Hand-written: the stages are a benchmark's
    own steps (seconds to hours each), which no job library would know how to split.
    """

    def __init__(self, path: Path | None, settings: dict, resume: bool) -> None:
        self.path, self.settings = (None if path is None else Path(path)), json_roundtrip(settings)
        self.done: dict = {}
        if resume and self.path is not None and self.path.exists():
            saved = read_json(self.path, "benchmark checkpoint")
            if not isinstance(saved, dict) or saved.get("settings") != self.settings:
                theirs = saved.get("settings", {}) if isinstance(saved, dict) else {}
                differ = sorted(k for k in {*self.settings, *theirs} if self.settings.get(k) != theirs.get(k))
                raise ConfigError(
                    f"{self.path}: a checkpoint of a run with other settings ({', '.join(differ) or 'unreadable'}); "
                    "run without --resume to start over"
                )
            self.done = saved.get("stages", {})

    @classmethod
    def in_memory(cls) -> StageCheckpoint:
        """A checkpoint that keeps nothing on disk (a run that cannot be resumed)."""
        return cls(None, {}, resume=False)

    def run(self, stage: str, measure: Callable[[], Any]) -> Any:
        """The stage's saved result, or ``measure()``'s, saved before it is returned."""
        if stage not in self.done:
            self.done[stage] = json_roundtrip(measure())
            if self.path is not None:
                write_json_atomic(self.path, {"settings": self.settings, "stages": self.done})
        return self.done[stage]

    def finish(self) -> None:
        if self.path is not None:
            self.path.unlink(missing_ok=True)


def folder_digest(folder: Path) -> str:
    """A digest of a folder's files (not its subfolders; by name and content): a model folder repacked, or a
    package's modules edited, is a new key."""
    h = hashlib.sha256()
    for path in sorted(p for p in Path(folder).iterdir() if p.is_file()):
        h.update(path.name.encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def dataset_digest(data_dir: Path) -> str:
    """A digest of a dataset's record and annotations (``dataset.json`` and every ``scene_gt*.json``): a set
    generated again with other annotations is a new key, though its path is the same."""
    h = hashlib.sha256()
    root = Path(data_dir)
    for path in [root / "dataset.json", *sorted(root.glob("bop/*/*/scene_gt*.json"))]:
        if path.is_file():
            h.update(str(path.relative_to(root)).encode())
            h.update(path.read_bytes())
    return h.hexdigest()[:16]


def json_roundtrip(data: Any) -> Any:
    """``data`` as it reads back from JSON (tuples as lists, numpy scalars as floats), so that a resumed run and a
    fresh one hand the same values on."""
    return json.loads(json.dumps(data, default=_json_default))


def _json_default(x: Any) -> Any:
    if isinstance(x, np.generic):
        return x.item()
    raise TypeError(f"not JSON-able: {type(x).__name__}")
