"""``sygrid parts``: the built-in parts with their size, mass and symmetries. ``sygrid parts PATH``: your own parts,
from a CAD file, a folder of CAD files (ids in file-name order, names the file stems) or a catalogue: size, mesh
health, volume, mass and where it comes from, diameter, declared and proposed symmetries. ``--collision`` measures
the collision tiers, ``--export NAME`` writes a part as a mesh file (PLY, OBJ or STL, mm or m), and
``--write-catalogue OUT`` writes a catalogue of PATH's parts with the proposed symmetries filled in."""

from __future__ import annotations

import argparse
from pathlib import Path

from sygrid.catalogue import open_parts, with_proposals, write_catalogue
from sygrid.errors import ConfigError
from sygrid.objects import BUILTIN_PARTS, ObjectModel, builtin_part
from sygrid.objects.collision.build import build_collision_model, select_collision_model
from sygrid.objects.collision.params import CollisionTier
from sygrid.objects.part_report import format_report, part_report

_CATALOGUE_HEADER = """Written by 'sygrid parts --write-catalogue': ids in file-name order, names the file stems,
material steel, symmetries as proposed from the meshes (in each file's frame, metres).
Check each part (material, mass_kg or density_kg_m3, symmetries) before you use it."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "path", nargs="?", type=Path, help="a CAD file (.ply, .obj, .stl), a folder of them, or a catalogue (.toml)"
    )
    parser.add_argument(
        "--unit", choices=("mm", "m"), help="unit of the CAD files read (required with them) and of --export (mm)"
    )
    parser.add_argument("--first-id", type=int, default=1, help="obj_id of a folder's first file (default 1)")
    parser.add_argument("--collision", action="store_true", help="also build and measure the three collision tiers")
    parser.add_argument("--export", metavar="NAME", help="write this part as a mesh file")
    parser.add_argument("--out", type=Path, help="mesh file for --export (.ply, .obj or .stl)")
    parser.add_argument(
        "--write-catalogue", metavar="OUT", type=Path, help="write a catalogue (.toml or .json) of PATH's parts"
    )


def run(args: argparse.Namespace) -> int:
    if args.path is None:
        if args.write_catalogue:
            raise ConfigError("--write-catalogue: give PATH, the CAD file, folder or catalogue to write it from")
        models = [builtin_part(name) for name in BUILTIN_PARTS]
        if args.export:
            return _export(models, args.export, args.out, args.unit or "mm")
        _print_builtins(models)
    else:
        catalogue = open_parts(args.path, args.unit, args.first_id)
        models = catalogue.models()
        if args.export:
            return _export(models, args.export, args.out, args.unit or "mm")
        reports = [part_report(m) for m in models]
        for report in reports:
            print("\n".join(format_report(report)))
        if args.write_catalogue:
            proposals = {r.name: r.proposal for r in reports if r.proposal is not None}
            path = write_catalogue(with_proposals(catalogue, proposals), args.write_catalogue, _CATALOGUE_HEADER)
            print(f"wrote {path}: check each part's material, mass and symmetries")
    if args.collision:
        _print_collision(models)
    return 0


def _print_builtins(models: list[ObjectModel]) -> None:
    print(f"{'id':>3} {'name':<10} {'size x*y*z [mm]':<22} {'diameter':>9} {'mass':>8} {'material':<10} symmetries")
    for m in models:
        size = "x".join(f"{v * 1e3:.1f}" for v in m.extents_m)
        syms = f"{len(m.symmetries_discrete)} discrete" + (
            f" + {len(m.symmetries_continuous)} continuous axis" if m.symmetries_continuous else ""
        )
        print(f"{m.obj_id:>3} {m.name:<10} {size:<22} {m.diameter_m * 1e3:>6.1f} mm {m.mass_kg * 1e3:>6.1f} g "
              f"{m.material:<10} {syms}")  # fmt: skip


def _print_collision(models: list[ObjectModel]) -> None:
    width = max(10, *(len(m.name) for m in models))
    print(f"\n{'name':<{width}} {'tier':<6} {'geoms':>6} {'excess vol':>11} {'missed vol':>11} "
          f"{'holes kept':>11} {'build s':>8}  chosen by default rule")  # fmt: skip
    for m in models:
        chosen = select_collision_model(m)
        rows = [build_collision_model(m, tier) for tier in CollisionTier]
        if all(c.params != chosen.params or c.tier is not chosen.tier for c in rows):
            rows.append(chosen)  # the rule's finer CoACD try
        for c in rows:
            f = c.fidelity
            tier = c.tier.value if c.params == rows[0].params else f"{c.tier.value}*"
            mark = "<--" if c.tier is chosen.tier and c.params == chosen.params else ""
            print(
                f"{m.name:<{width}} {tier:<6} {c.n_pieces:>6} {f.excess_volume_ratio:>10.1%} "
                f"{f.missed_volume_ratio:>10.1%} {f.concavity_kept:>10.1%} {c.compute_s:>8.2f}  {mark}"
            )
    print("* coacd with the finer concavity threshold that the default rule tries before vhacd")


def _export(models: list[ObjectModel], name: str, out: Path | None, unit: str) -> int:
    by_name = {m.name: m for m in models}
    if name not in by_name:
        raise ConfigError(f"--export: no part named {name!r}; the parts: {', '.join(by_name)}")
    if out is None or out.suffix.lower() not in (".ply", ".obj", ".stl"):
        raise ConfigError(f"--out: expected a .ply, .obj or .stl path for --export, got {out}")
    mesh = by_name[name].mesh.copy()
    if unit == "mm":
        mesh.apply_scale(1000.0)
    out.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(out)
    print(f"wrote {name} ({unit}) to {out}")
    return 0
