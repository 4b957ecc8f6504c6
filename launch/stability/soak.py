"""The soak (issue 25, axis 9): the generator over many items and the simulated cell over a long pick loop, in this
process, with the figures of each tenth of the run, to see whether anything grows or degrades with time.

- generator: ``Options.soak_items`` items of the test recipe (``sygrid.dataset.generate``, one worker, in this
  process), a tenth at a time: per tenth the items written of those asked, seconds per item, each item's making
  (drop, render, sensor) and writing seconds, and this process's RSS after it;
- cell: bins of the simulated cell (``launch.bench_cell.run_bin``, seeds 0, 1, ...) back to back for
  ``Options.soak_minutes``; the bins split into tenths in order: per tenth the picks of the attempts, the median of
  the bins' median cycle times and this process's RSS (the runtime's side: the emulator is a new process per bin).

A soak is measured whole, once (kept under the cache folder, written as it goes); one stopped part way is measured
again from its start, as resuming it would hide growth. The notes compare the last tenth with the first: RSS growth,
a two-proportion z score of the success rates (|z| > 2: worse or better beyond noise) and, for the generator, the
median making and writing seconds per item with a one-sided Mann-Whitney p value that the last tenth's items are
slower (items differ in cost, rasterised or path-traced, redrawn or not, so their times are compared as samples;
p < 0.01: slower beyond noise).
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import time
from dataclasses import dataclass, field
from statistics import median
from typing import Any

from launch.stability.cell_axes import CELL_CRITERION, bin_measurements
from launch.stability.options import Options
from launch.stability.sweep import Axis, Measurement, Method, Point
from sygrid.fileio import read_json, write_json_atomic

GENERATOR, CELL = "generator: items written", "cell: pick success"


def rss_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 2**20


def soak_axis(opts: Options) -> Axis:
    parts = 2 if opts.quick else 10
    items = min(opts.soak_items, 4) if opts.quick else opts.soak_items
    minutes = 0.0 if opts.quick else opts.soak_minutes
    cycles = min(opts.max_cycles, 2) if opts.quick else opts.max_cycles
    settings = {"recipe": str(opts.recipe), "items": items, "minutes": minutes, "cell_config": str(opts.cell_config),
                "perception": opts.cell_perception, "max_cycles": cycles, "parts": parts}  # fmt: skip
    key = hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:12]
    folder = opts.cache_dir / "soak" / key

    def measure(point: Point, seed: int) -> dict[str, Measurement]:
        i = point.params["part"]
        gen = _generator_soak(opts, folder, items, parts)
        cell = _cell_soak(opts, folder, minutes, parts, cycles)
        g = gen["parts"][i]
        bins = [b for k, b in enumerate(cell["bins"]) if k * parts // len(cell["bins"]) == i] if cell["bins"] else []
        picked, tried = sum(b["n_picked"] for b in bins), sum(b["n_tried"] for b in bins)
        cycle = [b["cycle_median_s"] for b in bins if b["cycle_median_s"] is not None]
        return {
            GENERATOR: Measurement(g["written"], g["asked"], extra={"s_per_item": g["s_per_item"],
                                                                     "rss_mb": g["rss_mb"],
                                                                     "make_s": g.get("make_s", []),
                                                                     "write_s": g.get("write_s", [])}),
            CELL: Measurement(picked, tried, extra={"bins": len(bins), "rss_mb": bins[-1]["rss_mb"] if bins else None,
                                                    "cycle_median_s": median(cycle) if cycle else None}),
        }  # fmt: skip

    return Axis(
        name="soak", title="Soak", x_label=f"part of the run (1/{parts} each)",
        points=tuple(Point(f"{i + 1}/{parts}", float(i + 1), {"part": i}) for i in range(parts)),
        methods=(Method(GENERATOR, "items written"), Method(CELL, "pick success")), measure=measure, seeds=(0,),
        criterion=CELL_CRITERION, summary="holds through part {x} of the run", unit="", settings=settings,
        notes=soak_notes,
        description=f"The generator over {items} items and the simulated cell for {minutes:g} minutes, in one "
        "process; figures per part of the run.",
    )  # fmt: skip


def _generator_soak(opts: Options, folder, items: int, parts: int) -> dict[str, Any]:
    from sygrid.dataset import generate
    from sygrid.recipe import load_recipe

    log_path = folder / "generator.json"
    if log_path.is_file():
        log = read_json(log_path, "soak log")
        if log.get("complete"):
            return log
    data_dir = folder / "dataset"
    if data_dir.exists():
        shutil.rmtree(data_dir)  # a stopped soak starts again: its RSS figures need the whole run in one process
    recipe = load_recipe(opts.recipe)
    log = {"complete": False, "parts": []}
    for i in range(parts):
        lo, hi = i * items // parts, (i + 1) * items // parts
        times = ItemSeconds()
        start = time.perf_counter()
        summary = generate(recipe, data_dir, max(hi, 1), seed=9000, workers=1, progress=False, on_written=times)
        seconds = time.perf_counter() - start
        failed = sum(1 for j in summary.failed if lo <= j < hi)
        log["parts"].append({"asked": hi - lo, "written": hi - lo - failed, "seconds": seconds,
                             "s_per_item": seconds / max(hi - lo, 1), "rss_mb": rss_mb(),
                             "make_s": times.make_s, "write_s": times.write_s})  # fmt: skip
        write_json_atomic(log_path, log)
    log["complete"] = True
    write_json_atomic(log_path, log)
    return log


@dataclass
class ItemSeconds:
    """Each written item's making (``item.timings["item"]``) and writing seconds, as ``generate``'s ``on_written``."""

    make_s: list[float] = field(default_factory=list)
    write_s: list[float] = field(default_factory=list)

    def __call__(self, item: Any, write_s: float) -> None:
        self.make_s.append(round(float(item.timings["item"]), 4))
        self.write_s.append(round(write_s, 5))


def _cell_soak(opts: Options, folder, minutes: float, parts: int, cycles: int) -> dict[str, Any]:
    from launch.bench_cell import run_bin
    from launch.cell_variants import Variant
    from robot.cell_setup import load_cell_setup

    log_path = folder / "cell.json"
    if log_path.is_file():
        log = read_json(log_path, "soak log")
        if log.get("complete"):
            return log
    base = load_cell_setup(opts.cell_config)
    variant = Variant(opts.cell_perception, "soak", calibration="sim")
    log = {"complete": False, "bins": []}
    start = time.perf_counter()
    seed = 0
    while time.perf_counter() - start < 60.0 * minutes or len(log["bins"]) < parts:
        try:
            picks = bin_measurements(run_bin(base, variant, seed, None, cycles), cycles)["pick success"]
            row = {"n_picked": picks.k, "n_tried": picks.n, "cycle_median_s": picks.extra["cycle_median_s"],
                   "error": None}  # fmt: skip
        except Exception as exc:  # a bin that raised is a bin without picks
            row = {"n_picked": 0, "n_tried": 0, "cycle_median_s": None, "error": f"{type(exc).__name__}: {exc}"}
        row.update(seed=seed, at_s=time.perf_counter() - start, rss_mb=rss_mb())
        log["bins"].append(row)
        write_json_atomic(log_path, log)
        seed += 1
    log["complete"] = True
    write_json_atomic(log_path, log)
    return log


def soak_notes(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Per method: RSS growth from the first to the last part (%), the success rate of both and the z score of
    their difference."""
    out = {}
    for method in sorted({r["method"] for r in records}):
        rows = sorted((r for r in records if r["method"] == method), key=lambda r: r["x"])
        if len(rows) < 2:
            continue
        first, last = rows[0], rows[-1]
        a, b = first["extra"].get("rss_mb"), last["extra"].get("rss_mb")
        out[method] = {
            "rss_first_mb": a, "rss_last_mb": b,
            "rss_growth_pct": 100.0 * (b - a) / a if a and b else None,
            "first": _rate(first), "last": _rate(last), "z_last_vs_first": _z(first, last),
        }  # fmt: skip
        for stage in ("make_s", "write_s"):
            a, b = first["extra"].get(stage), last["extra"].get(stage)
            if a and b:
                out[method].update({f"{stage}_first_median": median(a), f"{stage}_last_median": median(b),
                                    f"{stage}_p_last_slower": slower_p(a, b)})  # fmt: skip
    return out


def slower_p(first: list[float], last: list[float]) -> float:
    """One-sided Mann-Whitney U p value of ``last``'s values being larger than ``first``'s (scipy)."""
    from scipy.stats import mannwhitneyu

    return float(mannwhitneyu(last, first, alternative="greater").pvalue)


def _rate(r: dict[str, Any]) -> float | None:
    return r["k"] / r["n"] if r["n"] else None


def _z(a: dict[str, Any], b: dict[str, Any]) -> float | None:
    """Two-proportion z score of ``b``'s rate against ``a``'s (pooled standard error); None where undefined."""
    if not a["n"] or not b["n"]:
        return None
    p = (a["k"] + b["k"]) / (a["n"] + b["n"])
    se = math.sqrt(p * (1 - p) * (1 / a["n"] + 1 / b["n"]))
    return (b["k"] / b["n"] - a["k"] / a["n"]) / se if se > 0 else 0.0
