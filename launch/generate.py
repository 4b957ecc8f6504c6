"""``sygrid generate RECIPE.json --out DIR --count N --seed S [--workers W] [--executor local|ray]``.

The dataset regeneration command: item i depends only on (seed, i); rerunning the same command after a crash or a
kill completes the set. Recipes the project trains on: ``launch/recipes/``. Exit codes: ``EXIT_CODES``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from launch.part_check import log_warnings, scene_warnings
from sygrid.dataset import EXECUTORS, generate
from sygrid.recipe import load_recipe

#: ``sygrid generate``'s exit codes (its ``--help`` epilog says the same).
EXIT_CODES = (
    "exit codes: 0 every item is written; 1 some items failed (an error, or no attempt passed the quality gate within "
    "the recipe's max_redraws): they are listed and recorded in DIR/dataset.json, never as done, and rerunning the "
    "same command retries them; 2 bad input (the recipe, its scene, a folder made with another recipe or seed) or a "
    "write error (disk full)."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EXIT_CODES
    parser.add_argument("recipe", type=Path, help="recipe JSON (see launch/recipes/)")
    parser.add_argument("--out", type=Path, required=True, help="dataset folder (created, or resumed)")
    parser.add_argument("--count", type=int, required=True, help="number of items")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=1, help="parallel worker processes / Ray tasks")
    parser.add_argument("--executor", choices=sorted(EXECUTORS), default="local")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar (logs only)")
    parser.add_argument(
        "--check-models", type=Path, default=Path("models/builtin"), help="warn when this folder's detector sees a "
        "part too small (pixels per part)"
    )  # fmt: skip


def run(args: argparse.Namespace) -> int:
    recipe = load_recipe(args.recipe)
    log_warnings(scene_warnings(recipe.scene, recipe.base_dir, args.check_models), f"{args.recipe} camera")
    summary = generate(
        recipe, args.out, args.count, args.seed, args.workers, args.executor, progress=not args.no_progress
    )
    print(
        f"{summary.written} items written ({summary.skipped} already there) in {summary.seconds:.1f} s, "
        f"{summary.seconds_per_item:.2f} s per item, to {summary.out_dir}"
    )
    if summary.redone:
        print(f"{len(summary.redone)} item(s) recorded as done had files missing and were made again")
    if summary.redrawn:
        redraws = sum(len(r) for r in summary.redrawn.values())
        print(
            f"{len(summary.redrawn)} item(s) passed the quality gate only after redraws ({redraws} redraws in all; "
            f"the reasons are in {summary.out_dir / 'records'})"
        )
    for index, error in sorted(summary.failed.items()):
        print(f"item {index} failed: {error}")
    if summary.failed:
        print(f"{len(summary.failed)} item(s) failed; rerun the same command to retry them")
    return 1 if summary.failed else 0
