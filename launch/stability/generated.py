"""Small generated sets for the axes whose points change the scene: a base recipe with a point's changes, generated
(or completed: ``sygrid.dataset.generate`` resumes) into a cache folder named after the point, the seed and the
changed recipe's hash.

A point's changes (``Point.params``) are a dict: ``"parts_per_bin": N`` spreads N parts over the scene's objects in
proportion to their counts (largest remainders; a kind may get none), ``"material": NAME`` gives every part that
material, and any other key is a dotted path into the recipe JSON (scene inlined) set to the value, e.g.
``"scene.camera.pose_sampling.distance_m": [1.0, 1.0]`` or ``"sensor": "oak-d"``.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

from launch.stability.sweep import safe_name
from sygrid.errors import ConfigError

GENERATION_SEED = 7000  # + the sweep's seed: items apart from the training (0..) and test (1000) sets' draws


def point_recipe_json(base: dict[str, Any], params: dict[str, Any]) -> dict[str, Any]:
    """The recipe JSON ``base`` (scene inlined) with a point's changes (see the module docstring)."""
    out = copy.deepcopy(base)
    objects = out["scene"]["objects"]
    for key, value in params.items():
        if key == "parts_per_bin":
            for obj, count in zip(objects, spread_counts([_count(o) for o in objects], int(value)), strict=True):
                obj["count"] = count
        elif key == "material":
            for obj in objects:
                obj["material"] = value
        else:
            node = out
            *path, last = key.split(".")
            for part in path:
                if not isinstance(node.get(part), dict):
                    raise ConfigError(f"stability point: {key}: the recipe has no object at {part!r}")
                node = node[part]
            node[last] = value
    return out


def spread_counts(counts: list[int], total: int) -> list[int]:
    """``total`` spread over kinds in proportion to ``counts`` (largest remainders, ties to the first kinds)."""
    if total < 0 or sum(counts) <= 0:
        raise ConfigError(f"parts_per_bin: need a total >= 0 and some parts to spread it over, got {total}")
    shares = [total * c / sum(counts) for c in counts]
    out = [math.floor(s) for s in shares]
    order = sorted(range(len(counts)), key=lambda i: (-(shares[i] - out[i]), i))
    for i in order[: total - sum(out)]:
        out[i] += 1
    return out


def _count(obj: dict[str, Any]) -> int:
    count = obj.get("count", 1)
    return int(count["max"]) if isinstance(count, dict) else int(count)


def generated_set(
    base_recipe: Path, params: dict[str, Any], count: int, seed: int, cache_dir: Path, axis: str, point: str
) -> Path:
    """The folder of ``count`` items of ``base_recipe`` with ``params``, generated with ``GENERATION_SEED + seed``
    (items already there are kept); raises ConfigError when no item could be made."""
    from sygrid.dataset import generate
    from sygrid.recipe import load_recipe, parse_recipe

    base = load_recipe(base_recipe)
    data = point_recipe_json(base.to_json(), params)
    recipe = parse_recipe(data, f"{base_recipe} with {params}", base.base_dir)
    out = Path(cache_dir) / "datasets" / safe_name(axis) / f"{safe_name(point)}-s{seed}-{recipe.sha256()[:10]}"
    summary = generate(recipe, out, count, GENERATION_SEED + seed, workers=1, progress=False)
    if summary.written + summary.skipped == 0:
        raise ConfigError(f"{out}: no item of the point could be generated: {summary.failed}")
    return out
