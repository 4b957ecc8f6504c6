"""``sygrid bench physics``: the drop's speed and stability against parts count and collision tier.

For each variant (collision tier x sleep tolerance), parts count and seed, a bin of mixed built-in parts is
dropped; we record the wall time to settle (spawn + compile + simulate; decompositions are cached and built before
timing), the simulated time, penetration at rest, escaped instances, and the rest drift: the largest move of any
part when the settled pile is woken and simulated 0.5 s longer (how far from rest "settled" was). Targets on a
2-core machine: 20 parts < 0.5 s, 60 parts < 1.5 s, no escapes, penetration < 0.5 mm, over at least 5 seeds.
"""

from __future__ import annotations

import argparse
import logging
from itertools import product
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from tqdm import tqdm

from sygrid.bench.common import DEFAULT_RESULTS_DIR, median, save_results
from sygrid.drop import collision_models, resolve_objects
from sygrid.physics import Instance, simulate_drop
from sygrid.scene import SceneSpec, parse_scene

BENCH_PARTS = ("hex_nut", "hex_bolt", "washer", "l_bracket", "pipe", "spur_gear", "flange")
# (label, collision tier, sleep tolerance): every tier at the default sleep tolerance, then the default tier
# with less sleeping (slower, closer to rest).
VARIANTS = (
    ("hull", "hull", 0.03),
    ("coacd", "coacd", 0.03),
    ("vhacd", "vhacd", 0.03),
    ("auto", "auto", 0.03),
    ("auto, sleep 0.01", "auto", 0.01),
    ("auto, no sleep", "auto", 0.0),
)
COUNTS = (10, 20, 40, 60, 80)
REST_CHECK_S = 0.5
TARGETS = {"wall_s_at_20": 0.5, "wall_s_at_60": 1.5, "max_penetration_mm": 0.5, "escapes": 0}


def bench_scene(tier: str, sleep_tolerance: float) -> SceneSpec:
    return parse_scene(
        {
            "name": "bench_physics",
            "objects": [{"builtin": p, "count": 1} for p in BENCH_PARTS],
            "container": {"inner_size_m": [0.36, 0.26, 0.15]},
            "physics": {"collision_tier": tier, "sleep_tolerance": sleep_tolerance},
        }
    )


def run_sweep(counts=COUNTS, variants=VARIANTS, seeds: int = 5) -> list[dict]:
    rows = []
    jobs = list(product(variants, counts, range(seeds)))
    cache: dict[str, tuple] = {}
    for (label, tier, sleep), count, seed in tqdm(jobs, desc="bench physics", unit="drop"):
        scene = bench_scene(tier, sleep)
        if tier not in cache:
            models = resolve_objects(scene, Path("."))
            cache[tier] = (models, collision_models(models, tier))  # built (or loaded) before timing
        models, coll = cache[tier]
        instances = [Instance(model_index=i % len(models), inst_id=i) for i in range(count)]
        rng = np.random.default_rng(seed)
        r = simulate_drop(models, coll, instances, scene.container, scene.physics, rng, REST_CHECK_S).report
        rows.append(
            {
                "variant": label, "tier": tier, "sleep_tolerance": sleep, "parts": count, "seed": seed,
                "wall_s": r.wall_time_s, "sim_s": r.sim_time_s, "settled": r.settled,
                "max_penetration_mm": r.max_penetration_m * 1e3, "escaped": len(r.escaped),
                "rest_drift_mm": (r.rest_drift_m or 0.0) * 1e3,
                "geoms_per_instance": float(np.mean([c.n_pieces for c in coll])),
            }
        )  # fmt: skip
    return rows


def summarise(rows: list[dict]) -> list[dict]:
    out = []
    for variant in dict.fromkeys(r["variant"] for r in rows):
        for count in dict.fromkeys(r["parts"] for r in rows):
            sel = [r for r in rows if r["variant"] == variant and r["parts"] == count]
            if not sel:
                continue
            out.append(
                {
                    "variant": variant, "tier": sel[0]["tier"], "sleep_tolerance": sel[0]["sleep_tolerance"],
                    "parts": count, "runs": len(sel),
                    "median_wall_s": median([r["wall_s"] for r in sel]),
                    "max_wall_s": max(r["wall_s"] for r in sel),
                    "median_sim_s": median([r["sim_s"] for r in sel]),
                    "all_settled": all(r["settled"] for r in sel),
                    "max_penetration_mm": max(r["max_penetration_mm"] for r in sel),
                    "escaped_total": sum(r["escaped"] for r in sel),
                    "median_rest_drift_mm": median([r["rest_drift_mm"] for r in sel]),
                    "max_rest_drift_mm": max(r["rest_drift_mm"] for r in sel),
                    "geoms_per_instance": sel[0]["geoms_per_instance"],
                }
            )  # fmt: skip
    return out


def chart(summary: list[dict]):
    fig, axes = plt.subplots(1, 4, figsize=(20, 4.4))
    for variant in dict.fromkeys(s["variant"] for s in summary):
        sel = [s for s in summary if s["variant"] == variant]
        x = [s["parts"] for s in sel]
        label = f"{variant} ({sel[0]['geoms_per_instance']:.1f} geoms/part)"
        axes[0].plot(x, [s["median_wall_s"] for s in sel], "o-", label=label)
        axes[1].plot(x, [s["max_penetration_mm"] for s in sel], "o-", label=variant)
        axes[2].plot(x, [s["median_rest_drift_mm"] for s in sel], "o-", label=variant)
        at60 = [s for s in sel if s["parts"] == 60] or sel[-1:]
        axes[3].scatter(at60[0]["median_wall_s"], at60[0]["median_rest_drift_mm"], s=60, label=variant)
        axes[3].annotate(variant, (at60[0]["median_wall_s"], at60[0]["median_rest_drift_mm"]), fontsize=7)
    for y in (0.5, 1.5):
        axes[0].axhline(y, color="grey", ls=":", lw=1)
    axes[0].set(xlabel="parts in the bin", ylabel="wall time to settle, median [s]", title="Drop speed", yscale="log")
    axes[1].axhline(0.5, color="grey", ls=":", lw=1)
    axes[1].set(xlabel="parts in the bin", ylabel="penetration at rest, max [mm]", title="Contact accuracy")
    axes[2].set(xlabel="parts in the bin", ylabel="rest drift in 0.5 s, median [mm]", title="How settled 'settled' is")
    axes[3].set(xlabel="wall time, 60 parts [s]", ylabel="rest drift, 60 parts [mm]", title="Speed against accuracy")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle("sygrid bench physics: MuJoCo drop of mixed built-in parts, 2 ms step, median over seeds")
    return fig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--counts", type=int, nargs="+", default=list(COUNTS))
    parser.add_argument(
        "--variants", nargs="+", default=[v[0] for v in VARIANTS], choices=[v[0] for v in VARIANTS], metavar="VARIANT"
    )


def run(args: argparse.Namespace, out_dir: Path = DEFAULT_RESULTS_DIR) -> int:
    logging.getLogger("sygrid.physics").setLevel(logging.ERROR)  # per-drop warnings are in the table
    variants = tuple(v for v in VARIANTS if v[0] in args.variants)
    rows = run_sweep(tuple(args.counts), variants, args.seeds)
    summary = summarise(rows)
    print(f"{'variant':<18}{'parts':>6}{'wall s (median)':>17}{'wall s (max)':>14}{'sim s':>8}"
          f"{'pen. mm (max)':>15}{'drift mm':>10}{'escaped':>9}{'settled':>9}")  # fmt: skip
    for s in summary:
        print(f"{s['variant']:<18}{s['parts']:>6}{s['median_wall_s']:>17.3f}{s['max_wall_s']:>14.3f}"
              f"{s['median_sim_s']:>8.2f}{s['max_penetration_mm']:>15.3f}{s['median_rest_drift_mm']:>10.2f}"
              f"{s['escaped_total']:>9}{'all' if s['all_settled'] else 'not all':>9}")  # fmt: skip
    json_path, png_path = save_results(
        "physics", {"targets": TARGETS, "summary": summary, "runs": rows}, chart(summary), out_dir
    )
    print(f"wrote {json_path} and {png_path}")
    return 0
