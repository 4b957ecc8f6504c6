"""``sygrid bench stability``: where each method fails, one difficulty axis at a time (resumable, saved per point).

Each axis (``AXES``, in the order run) sweeps one difficulty over its points and seeds and measures every method
the stack offers at that stage (``launch.stability.perception_axes``, ``cell_axes``, ``soak``); each (point, seed)
is saved as it is measured under ``OUT/stability/points/`` (``launch.stability.sweep``), so a stopped run goes on
where it stopped and ``--axis`` runs a part. Per axis it writes ``OUT/stability_<axis>.{json,png}`` (the curves and
each method's failure point, ``launch.stability.failure``), and over every axis saved so far
``OUT/stability_summary.md`` and ``OUT/stability_overview.png`` (``launch.stability.report``). ``--quick``: a tiny
version of every axis (two or three points, one seed, a few images or cycles) under ``stability_quick`` names.
Generated sets and measurement passes are cached under ``--cache-dir``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from launch.stability import cell_axes, perception_axes, soak
from launch.stability.options import Options
from launch.stability.perception_pass import PerceptionStack
from launch.stability.sweep import Axis, run_axis
from sygrid.bench.common import DEFAULT_RESULTS_DIR, save_results
from sygrid.errors import ConfigError

Factory = Callable[[Options, PerceptionStack], Axis]
AXES: dict[str, Factory] = {  # in the order they run
    "depth_noise": perception_axes.depth_noise_axis,
    "occlusion": perception_axes.occlusion_axis,
    "part_size": perception_axes.size_axis,
    "distance": perception_axes.distance_axis,
    "timing": lambda o, s: cell_axes.timing_axis(o),
    "calibration_mm": lambda o, s: cell_axes.calibration_axis(o, "mm"),
    "calibration_deg": lambda o, s: cell_axes.calibration_axis(o, "deg"),
    "clutter": perception_axes.clutter_axis,
    "clutter_cell": lambda o, s: cell_axes.clutter_cell_axis(o),
    "lighting": perception_axes.lighting_axis,
    "material": perception_axes.material_axis,
    "soak": lambda o, s: soak.soak_axis(o),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = Options()
    parser.add_argument("--axis", default=None, help=f"comma-separated axes (default: all): {', '.join(AXES)}")
    parser.add_argument("--quick", action="store_true", help="a tiny version of each axis (stability_quick_* files)")
    parser.add_argument("--report-only", action="store_true", help="measure nothing: JSON, charts and summary from "
                        "the saved points")  # fmt: skip
    parser.add_argument("--list", action="store_true", help="list the axes and their points, run nothing")
    parser.add_argument("--models", type=Path, default=d.models, help="model folder (manifest.json)")
    parser.add_argument("--data", type=Path, default=d.data, help="noise-free test set (depth noise, occlusion, size)")
    parser.add_argument("--recipe", type=Path, default=d.recipe, help="the recipe the generated points vary")
    parser.add_argument("--max-images", type=int, default=d.max_images, help="test-set images per pass "
                        "(0: all; default: all for occlusion and size, 50 for depth noise)")  # fmt: skip
    parser.add_argument("--images-per-point", type=int, default=d.images_per_point, help="generated items per "
                        "(point, seed)")  # fmt: skip
    parser.add_argument("--strategies", default=None, help="comma-separated pose strategies (default: all)")
    parser.add_argument("--threads", type=int, default=d.threads, help="onnxruntime threads")
    parser.add_argument("--seeds", type=int, default=None, help="seeds per point (default: each axis's own)")
    parser.add_argument("--cache-dir", type=Path, default=d.cache_dir, help="generated sets, passes, soak logs")
    parser.add_argument("--cell-config", type=Path, default=d.cell_config, help="the simulated cell's file")
    parser.add_argument("--max-cycles", type=int, default=None, help=f"pick cycles per bin (default {d.max_cycles}; "
                        "2 with --quick)")  # fmt: skip
    parser.add_argument("--cell-perception", choices=("oracle", "models"), default=d.cell_perception)
    parser.add_argument("--soak-items", type=int, default=d.soak_items, help="the soak's generated items")
    parser.add_argument("--soak-minutes", type=float, default=d.soak_minutes, help="the soak's cell minutes")
    parser.add_argument("--progress", action="store_true", help="progress bars of the passes")


def options(args: argparse.Namespace) -> Options:
    from perception.bench import parse_strategies

    return Options(
        models=args.models, data=args.data, recipe=args.recipe,
        max_images=args.max_images, images_per_point=args.images_per_point,
        strategies=parse_strategies(args.strategies), threads=args.threads, seeds=args.seeds,
        cache_dir=args.cache_dir.expanduser(), cell_config=args.cell_config,
        max_cycles=args.max_cycles or (2 if args.quick else Options().max_cycles),
        cell_perception=args.cell_perception, soak_items=args.soak_items, soak_minutes=args.soak_minutes,
        quick=args.quick, progress=args.progress,
    )  # fmt: skip


def chosen_axes(value: str | None) -> list[str]:
    """``--axis``: the named axes in ``AXES``' order (all without a value); an unknown name: ConfigError."""
    if value is None:
        return list(AXES)
    names = [n.strip() for n in value.split(",") if n.strip()]
    unknown = [n for n in names if n not in AXES]
    if unknown or not names:
        raise ConfigError(f"--axis {value!r}: unknown {unknown}; known: {', '.join(AXES)}")
    return [n for n in AXES if n in names]


def run(args: argparse.Namespace, out_dir: Path = DEFAULT_RESULTS_DIR) -> int:
    import matplotlib.pyplot as plt

    from launch.stability.report import axis_chart, axis_result, describe_failure

    opts = options(args)
    stack = PerceptionStack(opts.models, opts.strategies, opts.threads)
    prefix = "stability_quick" if opts.quick else "stability"
    points_dir = out_dir / prefix / "points"
    for name in chosen_axes(args.axis):
        axis = AXES[name](opts, stack)
        if args.list:
            print(f"{name}: {axis.title}; points {', '.join(p.label for p in axis.points)}; seeds {list(axis.seeds)}; "
                  f"methods {', '.join(m.name for m in axis.methods)}")  # fmt: skip
            continue
        records = run_axis(axis, points_dir, measure=not args.report_only)
        if not records:
            print(f"{name}: no saved points")
            continue
        result = axis_result(axis, records)
        figure = axis_chart(result)
        json_path, png_path = save_results(f"{prefix}_{name}", result, figure, out_dir)
        plt.close(figure)
        for method, m in result["methods"].items():
            print(f"{name}: {method}: {describe_failure(m['failure'], result)}")
        print(f"wrote {json_path} and {png_path} ({result['seconds'] / 60:.1f} min measured)")
    if not args.list:
        print(f"wrote {' and '.join(str(p) for p in write_summary(out_dir, prefix))}")
    return 0


def write_summary(out_dir: Path, prefix: str) -> list[Path]:
    """The Markdown summary and the overview chart of every axis saved under ``out_dir`` with ``prefix``."""
    import matplotlib.pyplot as plt

    from launch.stability.report import overview_chart, summary_markdown
    from sygrid.bench.common import save_chart
    from sygrid.fileio import read_json, write_bytes_atomic

    results = [read_json(out_dir / f"{prefix}_{n}.json", "stability axis results") for n in AXES
               if (out_dir / f"{prefix}_{n}.json").is_file()]  # fmt: skip
    if not results:
        return []
    md = write_bytes_atomic(out_dir / f"{prefix}_summary.md", summary_markdown(results).encode())
    figure = overview_chart(results)
    png = save_chart(f"{prefix}_overview", figure, out_dir)
    plt.close(figure)
    return [md, png]
