"""``sygrid bench generation``: seconds per generated item, recipe against recipe, in one run.

``sygrid bench generation --recipe A.json --recipe B.json ... [--items N] [--seed S] [--name NAME]`` makes items
0 .. N-1 of every recipe (``make_item`` and the generator's own BOP/YOLO/COCO writers, into a temporary folder per
recipe), the recipes taking turns item by item, so that the load of a shared machine falls on all of them alike.
One item at a time in one process (``sygrid generate --workers 2`` makes two at once). With the same seed the
recipes draw the same drops, camera poses and render modes where their settings agree, so the difference is what
their settings cost: the randomised training recipe against the plain one, or each knob of the ablation recipes.

Reports per recipe: items made and failed, median and p90 seconds per item, the medians per render mode (a recipe's
``raster_fraction`` mixes path-traced and rasterised items), median seconds per stage, and the ratio of its median
to the first recipe's. The first ``warmup_items`` items of each recipe (imports, JIT kernels, caches) are left
out. Writes ``bench/results/NAME.{json,png}``: the median stages of each recipe stacked (left), the seconds of
every item per recipe and mode (right).
"""

from __future__ import annotations

import argparse
import logging
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from tqdm import tqdm

from sygrid.bench.common import DEFAULT_RESULTS_DIR, add_result_arguments, median, percentile, replot, save_results
from sygrid.bench.render import complete_item, warmup_items
from sygrid.dataset import DatasetOutput
from sygrid.drop import resolve_objects
from sygrid.errors import ConfigError, SygridError
from sygrid.recipe import Recipe, load_recipe

#: Row fields that are not stages of the item.
_NOT_STAGES = ("index", "mode", "item_s", "cpu_s", "instances", "rss_mb", "render_s")


def run_items(recipes: dict[str, Recipe], count: int, seed: int, progress: bool = True) -> dict[str, dict]:
    """Items 0 .. count-1 of every recipe, taking turns; per recipe name ``rows`` (``complete_item``'s) and
    ``failed`` (index -> error)."""
    runs: dict[str, dict] = {name: {"rows": [], "failed": {}} for name in recipes}
    with tempfile.TemporaryDirectory(prefix="sygrid_bench_generation_") as tmp:
        outputs = {
            name: DatasetOutput(Path(tmp) / name, recipe, resolve_objects(recipe.scene, recipe.base_dir))
            for name, recipe in recipes.items()
        }
        for i in tqdm(range(count), desc="items (every recipe)", unit="item", disable=not progress):
            for name, recipe in recipes.items():
                try:
                    runs[name]["rows"].append(complete_item(recipe, outputs[name], seed, i))
                except SygridError as exc:  # a drop that never settles: recorded, the run goes on
                    runs[name]["failed"][str(i)] = f"{type(exc).__name__}: {exc}"
    return runs


def stage_names(rows: list[dict]) -> list[str]:
    """The stage fields of the rows, in the order they first appear."""
    names: list[str] = []
    for row in rows:
        names += [k for k in row if k not in _NOT_STAGES and k not in names]
    return names


def summarise(run: dict, warmup: int) -> dict:
    """Medians of one recipe's rows after the first ``warmup`` (by index, so every recipe leaves out the same
    items)."""
    timed = [r for r in run["rows"] if r["index"] >= warmup]
    modes = sorted({r["mode"] for r in timed})
    return {
        "items": len(timed), "failed": len(run["failed"]),
        "median_item_s": median([r["item_s"] for r in timed]),
        "p90_item_s": percentile([r["item_s"] for r in timed], 90),
        "median_item_cpu_s": median([r["cpu_s"] for r in timed]),
        "median_item_s_by_mode": {m: median([r["item_s"] for r in timed if r["mode"] == m]) for m in modes},
        "items_by_mode": {m: sum(r["mode"] == m for r in timed) for m in modes},
        "median_stage_s": {s: median([r.get(s, 0.0) for r in timed]) for s in stage_names(timed)},
    }  # fmt: skip


def run_benchmark(recipe_paths: list[Path], count: int, seed: int, progress: bool = True) -> dict:
    names = [p.stem for p in recipe_paths]
    if len(set(names)) != len(names):
        raise ConfigError(f"--recipe: two recipes share a file name ({', '.join(names)}); the results key on it")
    recipes = {name: load_recipe(path) for name, path in zip(names, recipe_paths, strict=True)}
    warmup = warmup_items(count)
    if count - warmup < 1:
        raise ConfigError(f"--items {count}: at least {warmup + 1} needed ({warmup} warm-up)")
    runs = run_items(recipes, count, seed, progress)
    summary = {name: summarise(run, warmup) for name, run in runs.items()}
    first = summary[names[0]]["median_item_s"]
    for s in summary.values():
        s["ratio_to_first"] = s["median_item_s"] / first if first > 0 else float("nan")
    return {
        "config": {
            "recipes": {n: str(p) for n, p in zip(names, recipe_paths, strict=True)},
            "items": count,
            "warmup_items": warmup,
            "seed": seed,
        },
        "summary": summary,
        "runs": runs,
    }


def format_results(results: dict) -> str:
    cfg = results["config"]
    lines = [
        f"{cfg['items']} items per recipe ({cfg['warmup_items']} warm-up left out), seed {cfg['seed']}, "
        "recipes taking turns item by item; seconds per item",
        f"{'recipe':<44}{'items':>6}{'failed':>7}{'median':>8}{'p90':>7}{'x first':>8}  per mode (median s)",
    ]
    for name, s in results["summary"].items():
        modes = ", ".join(f"{m} {v:.2f} ({s['items_by_mode'][m]})" for m, v in s["median_item_s_by_mode"].items())
        lines.append(f"{name:<44}{s['items']:>6}{s['failed']:>7}{s['median_item_s']:>8.2f}{s['p90_item_s']:>7.2f}"
                     f"{s['ratio_to_first']:>8.2f}  {modes}")  # fmt: skip
    for name, s in results["summary"].items():
        stages = ", ".join(f"{k.removesuffix('_s')} {v:.2f}" for k, v in s["median_stage_s"].items())
        lines.append(f"  {name}: median stages [s]: {stages}")
    return "\n".join(lines)


def chart(results: dict):
    summary, runs = results["summary"], results["runs"]
    names = list(summary)
    stages = stage_names([{k: 0 for k in s["median_stage_s"]} for s in summary.values()])
    fig, (ax_stage, ax_items) = plt.subplots(1, 2, figsize=(14, 0.45 * len(names) + 3.5))
    left = [0.0] * len(names)
    for k, stage in enumerate(stages):
        widths = [summary[n]["median_stage_s"].get(stage, 0.0) for n in names]
        ax_stage.barh(range(len(names)), widths, left=left, color=plt.cm.tab10(k % 10), label=stage.removesuffix("_s"))
        left = [a + b for a, b in zip(left, widths, strict=True)]
    for i, n in enumerate(names):
        ax_stage.text(left[i], i, f" {summary[n]['median_item_s']:.2f} s  x{summary[n]['ratio_to_first']:.2f}",
                      va="center", fontsize=8)  # fmt: skip
    ax_stage.set_yticks(range(len(names)), names, fontsize=8)
    ax_stage.invert_yaxis()
    ax_stage.set(xlabel="median seconds per stage (stacked); label: median item and ratio to the first recipe",
                 title="where an item's time goes")  # fmt: skip
    ax_stage.legend(fontsize=7, loc="lower right")
    warmup = results["config"]["warmup_items"]
    for i, n in enumerate(names):
        for mode, marker in (("pathtrace", "o"), ("raster", "s")):
            y = [r["item_s"] for r in runs[n]["rows"] if r["index"] >= warmup and r["mode"] == mode]
            ax_items.scatter(y, [i + (0.15 if mode == "raster" else -0.15)] * len(y), marker=marker, s=12,
                             alpha=0.6, color="tab:orange" if mode == "raster" else "tab:blue",
                             label=mode if i == 0 else None)  # fmt: skip
    ax_items.set_yticks(range(len(names)), names, fontsize=8)
    ax_items.invert_yaxis()
    ax_items.set(xlabel="seconds per complete item", title="every timed item, by render mode")
    ax_items.legend(fontsize=7, loc="lower right")
    ax_items.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--recipe", type=Path, action="append", default=[], help="recipe JSON; repeatable, the "
                        "first is the others' reference")  # fmt: skip
    parser.add_argument("--items", type=int, default=30, help="items per recipe (the first few are warm-up)")
    parser.add_argument("--seed", type=int, default=0)
    add_result_arguments(parser, "generation")


def run(args: argparse.Namespace, out_dir: Path = DEFAULT_RESULTS_DIR) -> int:
    if args.replot:
        replot(args.name, chart, out_dir)
        return 0
    if not args.recipe:
        raise ConfigError("sygrid bench generation: give at least one --recipe RECIPE.json")
    logging.getLogger("sygrid.physics").setLevel(logging.ERROR)  # per-drop warnings are not this benchmark's topic
    results = run_benchmark(args.recipe, args.items, args.seed)
    print(format_results(results))
    fig = chart(results)
    json_path, png_path = save_results(args.name, results, fig, out_dir)
    plt.close(fig)
    print(f"wrote {json_path} and {png_path}")
    return 0
