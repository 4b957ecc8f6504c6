"""``sygrid bench physics``: the drop's speed and stability against parts count and collision tier.

For each (parts count, tier, seed) a bin of mixed built-in parts is dropped; we record the wall time to settle
(spawn + compile + simulate; decompositions are cached and built before timing), the simulated time, penetration
at rest and escaped instances. Targets on a 2-core machine: 20 parts < 0.5 s, 60 parts < 1.5 s, no escapes,
penetration < 0.5 mm, over at least 5 seeds.
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
TIERS = ("hull", "coacd", "vhacd", "auto")
COUNTS = (10, 20, 40, 60, 80)
TARGETS = {"wall_s_at_20": 0.5, "wall_s_at_60": 1.5, "max_penetration_mm": 0.5, "escapes": 0}


def bench_scene(tier: str) -> SceneSpec:
    return parse_scene(
        {
            "name": "bench_physics",
            "objects": [{"builtin": p, "count": 1} for p in BENCH_PARTS],
            "container": {"inner_size_m": [0.36, 0.26, 0.15]},
            "physics": {"collision_tier": tier},
        }
    )


def run_sweep(counts=COUNTS, tiers=TIERS, seeds: int = 5) -> list[dict]:
    rows = []
    jobs = list(product(tiers, counts, range(seeds)))
    cache: dict[str, tuple] = {}
    for tier, count, seed in tqdm(jobs, desc="bench physics", unit="drop"):
        scene = bench_scene(tier)
        if tier not in cache:
            models = resolve_objects(scene, Path("."))
            cache[tier] = (models, collision_models(models, tier))  # built (or loaded) before timing
        models, coll = cache[tier]
        instances = [Instance(model_index=i % len(models), inst_id=i) for i in range(count)]
        result = simulate_drop(models, coll, instances, scene.container, scene.physics, np.random.default_rng(seed))
        r = result.report
        rows.append(
            {
                "tier": tier, "parts": count, "seed": seed, "wall_s": r.wall_time_s, "sim_s": r.sim_time_s,
                "settled": r.settled, "max_penetration_mm": r.max_penetration_m * 1e3, "escaped": len(r.escaped),
                "geoms_per_instance": float(np.mean([c.fidelity.n_pieces for c in coll])),
            }
        )  # fmt: skip
    return rows


def summarise(rows: list[dict]) -> list[dict]:
    out = []
    for tier in dict.fromkeys(r["tier"] for r in rows):
        for count in dict.fromkeys(r["parts"] for r in rows):
            sel = [r for r in rows if r["tier"] == tier and r["parts"] == count]
            if not sel:
                continue
            out.append(
                {
                    "tier": tier, "parts": count, "runs": len(sel),
                    "median_wall_s": median([r["wall_s"] for r in sel]),
                    "max_wall_s": max(r["wall_s"] for r in sel),
                    "median_sim_s": median([r["sim_s"] for r in sel]),
                    "all_settled": all(r["settled"] for r in sel),
                    "max_penetration_mm": max(r["max_penetration_mm"] for r in sel),
                    "escaped_total": sum(r["escaped"] for r in sel),
                    "geoms_per_instance": sel[0]["geoms_per_instance"],
                }
            )  # fmt: skip
    return out


def chart(summary: list[dict]):
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for tier in dict.fromkeys(s["tier"] for s in summary):
        sel = [s for s in summary if s["tier"] == tier]
        x = [s["parts"] for s in sel]
        label = f"{tier} ({sel[0]['geoms_per_instance']:.1f} geoms/part)"
        axes[0].plot(x, [s["median_wall_s"] for s in sel], "o-", label=label)
        axes[1].plot(x, [s["max_penetration_mm"] for s in sel], "o-", label=tier)
        axes[2].plot(x, [s["escaped_total"] for s in sel], "o-", label=tier)
    axes[0].axhline(0.5, color="grey", ls=":", lw=1)
    axes[0].axhline(1.5, color="grey", ls=":", lw=1)
    axes[0].set(xlabel="parts in the bin", ylabel="wall time to settle, median [s]", title="Drop speed")
    axes[1].axhline(0.5, color="grey", ls=":", lw=1)
    axes[1].set(xlabel="parts in the bin", ylabel="penetration at rest, max [mm]", title="Contact accuracy")
    axes[2].set(xlabel="parts in the bin", ylabel="escaped instances (all seeds)", title="Stability")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("sygrid bench physics: MuJoCo drop of mixed built-in parts, 2 ms step")
    return fig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--counts", type=int, nargs="+", default=list(COUNTS))
    parser.add_argument("--tiers", nargs="+", default=list(TIERS), choices=TIERS)


def run(args: argparse.Namespace, out_dir: Path = DEFAULT_RESULTS_DIR) -> int:
    logging.getLogger("sygrid.physics").setLevel(logging.ERROR)  # per-drop warnings are in the table
    rows = run_sweep(tuple(args.counts), tuple(args.tiers), args.seeds)
    summary = summarise(rows)
    print(f"{'tier':<7}{'parts':>6}{'wall s (median)':>17}{'wall s (max)':>14}{'sim s':>8}"
          f"{'pen. mm (max)':>15}{'escaped':>9}{'settled':>9}")  # fmt: skip
    for s in summary:
        print(f"{s['tier']:<7}{s['parts']:>6}{s['median_wall_s']:>17.3f}{s['max_wall_s']:>14.3f}"
              f"{s['median_sim_s']:>8.2f}{s['max_penetration_mm']:>15.3f}{s['escaped_total']:>9}"
              f"{'yes' if s['all_settled'] else 'no':>9}")  # fmt: skip
    json_path, png_path = save_results(
        "physics", {"targets": TARGETS, "summary": summary, "runs": rows}, chart(summary), out_dir
    )
    print(f"wrote {json_path} and {png_path}")
    return 0
