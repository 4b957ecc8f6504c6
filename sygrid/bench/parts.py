"""``sygrid bench parts``: a folder of foreign CAD parts from first use to settled piles.

Per part (default: the foreign test set, ``tests/fixtures/foreign_parts``, millimetres): the repaired solid (how it
was made, its volume, the mass from it against the old rule's: an open mesh's convex hull), the first-use collision
selection in an empty cache (wall time, tier, pieces, fidelity against the solid) and a second, cached call; then a
pile of that part over several seeds (settled, largest penetration at rest, escapes); then a mixed pile of all the
parts over the same seeds, and the generation time per item of a small rasterised dataset of that mixed pile.
Each pile runs once per speculative-contacts setting (``--contacts``, default "off" and "auto": what thin walls
gain from them and what they cost in wall time, seed for seed); the part table gives each part's wall thickness.

Targets: every part within ``TARGETS["first_use_s"]`` on first use and ``TARGETS["pieces"]`` pieces; piles settle
with penetration under the scene's bound in at least ``TARGETS["settled_fraction"]`` of the seeds, checked on the
last ``--contacts`` setting (the one a recipe for these parts uses).
"""

from __future__ import annotations

import argparse
import logging
import os
import tempfile
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from tqdm import tqdm

from sygrid.bench.common import DEFAULT_RESULTS_DIR, save_results
from sygrid.errors import ConfigError
from sygrid.fileio import CACHE_ENV
from sygrid.objects import load_cad, select_collision_model
from sygrid.objects.collision.solid import repaired_solid, solid_method
from sygrid.objects.thickness import wall_thickness_m
from sygrid.physics import Instance, simulate_drop
from sygrid.scene import parse_scene

DEFAULT_FOLDER = Path("tests/fixtures/foreign_parts")
TARGETS = {"first_use_s": 30.0, "pieces": 64, "settled_fraction": 0.95}


def _part_rows(paths: list[Path], unit: str) -> tuple[list, list, list[dict]]:
    """Loads each part, times its first-use solid and collision selection; returns models, collision, rows."""
    models, collisions, rows = [], [], []
    for k, path in enumerate(tqdm(paths, desc="bench parts: first use", unit="part")):
        model = load_cad(path, unit, k + 1, name=path.stem)
        start = time.perf_counter()
        solid = repaired_solid(model.mesh, model.content_hash, name=model.name)
        chosen = select_collision_model(model)
        first_use_s = time.perf_counter() - start
        start = time.perf_counter()
        again = select_collision_model(model)
        cached_s = time.perf_counter() - start
        mesh = model.mesh
        old_volume = abs(mesh.volume) if mesh.is_volume else mesh.convex_hull.volume  # the rule before repairs
        fid = chosen.fidelity
        rows.append(
            {
                "part": model.name, "faces": len(mesh.faces), "watertight": bool(mesh.is_watertight),
                "bodies": int(mesh.body_count), "solid_method": solid_method(mesh), "solid_s": solid.compute_s,
                "solid_volume_mm3": model.volume_m3 * 1e9, "hull_volume_mm3": mesh.convex_hull.volume * 1e9,
                "mass_g": model.mass_kg * 1e3, "mass_g_old_rule": old_volume * model.density_kg_m3 * 1e3,
                "first_use_s": first_use_s, "cached_s": cached_s, "cache_hit": bool(again.from_cache),
                "collision": chosen.description, "tier": chosen.tier.value, "pieces": chosen.n_pieces,
                "excess_volume_ratio": fid.excess_volume_ratio, "missed_volume_ratio": fid.missed_volume_ratio,
                "concavity_kept": fid.concavity_kept, "wall_thickness_mm": wall_thickness_m(solid.mesh) * 1e3,
            }
        )  # fmt: skip
        models.append(model)
        collisions.append(chosen)
    return models, collisions, rows


def _drop_rows(label: str, models: list, collisions: list, count: int, seeds: int, scene) -> list[dict]:
    rows = []
    contacts = scene.physics.speculative_contacts
    for seed in range(seeds):
        instances = [Instance(model_index=i % len(models), inst_id=i) for i in range(count)]
        report = simulate_drop(
            models, collisions, instances, scene.container, scene.physics, np.random.default_rng(seed)
        ).report
        rows.append(
            {
                "pile": label, "contacts": contacts, "speculative": report.speculative_contacts, "seed": seed,
                "parts": count, "settled": report.settled, "ok": report.within_bounds,
                "max_penetration_mm": report.max_penetration_m * 1e3, "escaped": len(report.escaped),
                "non_finite": len(report.non_finite), "wall_s": report.wall_time_s, "sim_s": report.sim_time_s,
            }
        )  # fmt: skip
    return rows


def _generation(paths: list[Path], unit: str, count: int, items: int, contacts: str, out_dir: Path) -> dict:
    """Seconds per item of a rasterised dataset of the mixed pile (``items`` items, 640 x 480)."""
    from sygrid.dataset import generate  # the renderers load only for this part of the benchmark
    from sygrid.recipe import parse_recipe

    per_part = [count // len(paths) + (k < count % len(paths)) for k in range(len(paths))]
    objects = [
        {"file": str(p.resolve()), "unit": unit, "obj_id": k + 1, "name": p.stem, "count": n}
        for k, (p, n) in enumerate(zip(paths, per_part, strict=True))
    ]
    recipe = parse_recipe(
        {
            "name": "bench_parts", "raster_fraction": 1.0,
            "scene": {"name": "bench_parts", "objects": objects, "physics": {"speculative_contacts": contacts}},
        },
        "bench parts recipe", out_dir,
    )  # fmt: skip
    summary = generate(recipe, out_dir / "dataset", count=items, seed=0, progress=False)
    return {
        "items": items, "written": summary.written, "failed": len(summary.failed), "seconds": summary.seconds,
        "seconds_per_item": summary.seconds / max(summary.written, 1), "mode": "raster 640x480",
    }  # fmt: skip


def chart(parts: list[dict], drops: list[dict]):
    names = [p["part"] for p in parts]
    x = np.arange(len(names))
    fig, axes = plt.subplots(1, 4, figsize=(22, 4.8))
    ax = axes[0]
    ax.bar(x, [p["first_use_s"] for p in parts], color="tab:blue", label="first use [s]")
    ax.axhline(TARGETS["first_use_s"], color="tab:blue", ls=":", lw=1)
    twin = ax.twinx()
    twin.plot(x, [p["pieces"] for p in parts], "o", color="tab:red", label="pieces")
    twin.axhline(TARGETS["pieces"], color="tab:red", ls=":", lw=1)
    twin.set_ylim(0, TARGETS["pieces"] * 1.15)
    twin.set_ylabel("collision pieces", color="tab:red")
    ax.set(ylabel="first-use repair + selection [s]", title="First use (dotted: the targets)")
    ax = axes[1]
    ax.bar(x - 0.2, [100 * p["excess_volume_ratio"] for p in parts], 0.4, label="excess")
    ax.bar(x + 0.2, [100 * p["missed_volume_ratio"] for p in parts], 0.4, label="missed")
    ax.set(ylabel="% of the repaired solid's volume", title="Fidelity of the chosen collision model")
    ax.legend(fontsize=8)
    ax = axes[2]
    ax.bar(x - 0.2, [p["mass_g_old_rule"] for p in parts], 0.4, label="old rule (open: convex hull)")
    ax.bar(x + 0.2, [p["mass_g"] for p in parts], 0.4, label="repaired solid")
    ax.set(ylabel="mass, steel [g]", title="Mass", yscale="log")
    ax.legend(fontsize=8)
    ax = axes[3]
    piles = list(dict.fromkeys(d["pile"] for d in drops))
    contacts = list(dict.fromkeys(d["contacts"] for d in drops))
    for i, pile in enumerate(piles):
        for j, setting in enumerate(contacts):
            sel = [d for d in drops if d["pile"] == pile and d["contacts"] == setting]
            offset = (j - (len(contacts) - 1) / 2) * 0.3
            ax.scatter([i + offset] * len(sel), [d["max_penetration_mm"] for d in sel], marker="ox^"[j % 3],
                       c=["tab:green" if d["ok"] else "tab:red" for d in sel], s=25,
                       label=f"speculative contacts {setting}" if i == 0 else None)  # fmt: skip
    ax.axhline(0.5, color="grey", ls=":", lw=1)
    ax.set_xticks(range(len(piles)), piles, rotation=30, ha="right", fontsize=8)
    ax.set(ylabel="penetration at rest, max [mm]", title="Piles (green: settled within the bounds)")
    ax.legend(fontsize=8)
    for ax in axes[:3]:
        ax.set_xticks(x, names, rotation=30, ha="right", fontsize=8)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.suptitle("sygrid bench parts: foreign CAD parts, first use (empty cache) to settled piles")
    fig.tight_layout()
    return fig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--folder", type=Path, default=DEFAULT_FOLDER, help="CAD meshes (*.stl, *.ply, *.obj)")
    parser.add_argument("--unit", choices=["mm", "m"], default="mm")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--count", type=int, default=20, help="parts per pile")
    parser.add_argument("--items", type=int, default=5, help="dataset items for the generation time (0: skip)")
    parser.add_argument(
        "--contacts", nargs="+", choices=["off", "on", "auto"], default=["off", "auto"],
        help="physics.speculative_contacts settings to run every pile with; the last is checked against the target",
    )  # fmt: skip


def run(args: argparse.Namespace, out_dir: Path = DEFAULT_RESULTS_DIR) -> int:
    paths = sorted(p for p in args.folder.iterdir() if p.suffix.lower() in (".stl", ".ply", ".obj"))
    if not paths:
        raise ConfigError(f"--folder: no .stl, .ply or .obj file in {args.folder}")
    logging.getLogger("sygrid.physics").setLevel(logging.ERROR)  # per-drop warnings are in the table
    logging.getLogger("sygrid.objects.cad").setLevel(logging.ERROR)  # the repairs are in the table
    scenes = [  # the default bin and physics, but for the contacts
        parse_scene({"name": "bench", "objects": [{"builtin": "hex_nut"}], "physics": {"speculative_contacts": c}})
        for c in args.contacts
    ]
    saved_env = os.environ.get(CACHE_ENV)
    with tempfile.TemporaryDirectory(prefix="sygrid-bench-parts-") as tmp:
        os.environ[CACHE_ENV] = tmp  # first use: an empty cache, shared by every step below
        try:
            models, collisions, parts = _part_rows(paths, args.unit)
            drops = []
            pile_sets = [(m.name, [m], [c]) for m, c in zip(models, collisions, strict=True)]
            pile_sets.append(("mixed", models, collisions))
            for label, pile_models, pile_colls in tqdm(pile_sets, desc="bench parts: piles", unit="pile"):
                for scene in scenes:
                    drops += _drop_rows(label, pile_models, pile_colls, args.count, args.seeds, scene)
            generation = None
            if args.items:
                generation = _generation(paths, args.unit, args.count, args.items, args.contacts[-1], Path(tmp))
        finally:
            if saved_env is None:
                os.environ.pop(CACHE_ENV, None)
            else:
                os.environ[CACHE_ENV] = saved_env
    piles = []
    for pile, contacts in dict.fromkeys((d["pile"], d["contacts"]) for d in drops):
        sel = [d for d in drops if d["pile"] == pile and d["contacts"] == contacts]
        piles.append({
            "pile": pile, "contacts": contacts, "speculative_fraction": float(np.mean([d["speculative"] for d in sel])),
            "seeds": len(sel), "ok_fraction": float(np.mean([d["ok"] for d in sel])),
            "settled_fraction": float(np.mean([d["settled"] for d in sel])),
            "max_penetration_mm": max(d["max_penetration_mm"] for d in sel),
            "escaped_total": sum(d["escaped"] for d in sel),
            "median_wall_s": float(np.median([d["wall_s"] for d in sel])),
        })  # fmt: skip
    print(f"{'part':<15}{'faces':>6}{'solid':>7}{'first s':>9}{'cached s':>9}  {'collision':<17}{'excess':>8}"
          f"{'missed':>8}{'mass g':>8}{'old g':>8}{'wall mm':>9}")  # fmt: skip
    for p in parts:
        print(f"{p['part']:<15}{p['faces']:>6}{p['solid_method']:>7}{p['first_use_s']:>9.1f}{p['cached_s']:>9.2f}  "
              f"{p['collision']:<17}{p['excess_volume_ratio']:>8.3f}{p['missed_volume_ratio']:>8.3f}"
              f"{p['mass_g']:>8.1f}{p['mass_g_old_rule']:>8.1f}{p['wall_thickness_mm']:>9.2f}")  # fmt: skip
    print(f"\n{'pile':<15}{'contacts':>9}{'on':>5}{'seeds':>6}{'ok':>6}{'settled':>9}{'pen. mm max':>13}"
          f"{'escaped':>9}{'wall s':>8}")  # fmt: skip
    for s in piles:
        print(f"{s['pile']:<15}{s['contacts']:>9}{s['speculative_fraction']:>5.0%}{s['seeds']:>6}"
              f"{s['ok_fraction']:>6.0%}{s['settled_fraction']:>9.0%}{s['max_penetration_mm']:>13.3f}"
              f"{s['escaped_total']:>9}{s['median_wall_s']:>8.2f}")  # fmt: skip
    checked = [d for d in drops if d["contacts"] == args.contacts[-1]]
    summary = {
        "contacts": args.contacts[-1],
        "within_bounds_fraction": float(np.mean([d["ok"] for d in checked])),
        "first_use_s_max": max(p["first_use_s"] for p in parts),
        "pieces_max": max(p["pieces"] for p in parts),
    }
    print(f"\ntargets: first use {summary['first_use_s_max']:.1f} s max (<= {TARGETS['first_use_s']}), pieces "
          f"{summary['pieces_max']} max (<= {TARGETS['pieces']}), piles within the bounds "
          f"{summary['within_bounds_fraction']:.1%} with contacts {summary['contacts']} "
          f"(>= {TARGETS['settled_fraction']:.0%})")  # fmt: skip
    if generation:
        print(f"\ngeneration: {generation['seconds_per_item']:.2f} s per item ({generation['mode']}, "
              f"{generation['written']} written, {generation['failed']} failed)")  # fmt: skip
    data = {
        "folder": str(args.folder), "unit": args.unit, "targets": TARGETS, "summary": summary, "parts": parts,
        "piles": piles,
        "drops": drops, "generation": generation,
    }  # fmt: skip
    json_path, png_path = save_results("parts", data, chart(parts, drops), out_dir)
    print(f"wrote {json_path} and {png_path}")
    return 0
