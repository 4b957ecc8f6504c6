"""What every benchmark shares: where results go, medians, and the JSON/PNG writing."""

from __future__ import annotations

import platform
from pathlib import Path

import numpy as np

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


def replot(name: str, chart, out_dir: Path = DEFAULT_RESULTS_DIR) -> Path:
    """Redraws ``<name>.png`` from the saved ``<name>.json`` alone (``chart``: results dict -> figure), with no
    measurement run; prints and returns the chart's path."""
    saved = read_json(out_dir / f"{name}.json", f"{name} benchmark results")
    path = save_chart(name, chart(saved), out_dir)
    print(f"redrew {path} from {out_dir / f'{name}.json'}")
    return path
