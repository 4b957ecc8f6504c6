"""``sygrid parts``: the built-in parts with their size, mass, symmetries and collision tiers; ``--export`` writes
one as a mesh file (PLY, OBJ or STL, in millimetres or metres)."""

from __future__ import annotations

import argparse
from pathlib import Path

from sygrid.errors import ConfigError
from sygrid.objects import BUILTIN_PARTS, builtin_part
from sygrid.objects.collision.build import build_collision_model, select_collision_model
from sygrid.objects.collision.params import CollisionTier


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--collision", action="store_true", help="also build and measure the three collision tiers")
    parser.add_argument("--export", metavar="NAME", choices=BUILTIN_PARTS, help="write this part as a mesh file")
    parser.add_argument("--out", type=Path, help="mesh file for --export (.ply, .obj or .stl)")
    parser.add_argument("--unit", choices=("mm", "m"), default="mm", help="unit of the exported file")


def run(args: argparse.Namespace) -> int:
    if args.export:
        return _export(args.export, args.out, args.unit)
    print(f"{'id':>3} {'name':<10} {'size x*y*z [mm]':<22} {'diameter':>9} {'mass':>8} {'material':<10} symmetries")
    for name in BUILTIN_PARTS:
        m = builtin_part(name)
        size = "x".join(f"{v * 1e3:.1f}" for v in m.extents_m)
        syms = f"{len(m.symmetries_discrete)} discrete" + (
            f" + {len(m.symmetries_continuous)} continuous axis" if m.symmetries_continuous else ""
        )
        print(f"{m.obj_id:>3} {name:<10} {size:<22} {m.diameter_m * 1e3:>6.1f} mm {m.mass_kg * 1e3:>6.1f} g "
              f"{m.material:<10} {syms}")  # fmt: skip
    if args.collision:
        print(f"\n{'name':<10} {'tier':<6} {'geoms':>6} {'excess vol':>11} {'missed vol':>11} "
              f"{'holes kept':>11} {'build s':>8}  chosen by default rule")  # fmt: skip
        for name in BUILTIN_PARTS:
            m = builtin_part(name)
            chosen = select_collision_model(m)
            rows = [build_collision_model(m, tier) for tier in CollisionTier]
            if all(c.params != chosen.params or c.tier is not chosen.tier for c in rows):
                rows.append(chosen)  # the rule's finer CoACD try
            for c in rows:
                f = c.fidelity
                tier = c.tier.value if c.params == rows[0].params else f"{c.tier.value}*"
                mark = "<--" if c.tier is chosen.tier and c.params == chosen.params else ""
                print(
                    f"{name:<10} {tier:<6} {c.n_pieces:>6} {f.excess_volume_ratio:>10.1%} "
                    f"{f.missed_volume_ratio:>10.1%} {f.concavity_kept:>10.1%} {c.compute_s:>8.2f}  {mark}"
                )
        print("* coacd with the finer concavity threshold that the default rule tries before vhacd")
    return 0


def _export(name: str, out: Path | None, unit: str) -> int:
    if out is None or out.suffix.lower() not in (".ply", ".obj", ".stl"):
        raise ConfigError(f"--out: expected a .ply, .obj or .stl path for --export, got {out}")
    mesh = builtin_part(name).mesh.copy()
    if unit == "mm":
        mesh.apply_scale(1000.0)
    out.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(out)
    print(f"wrote {name} ({unit}) to {out}")
    return 0
