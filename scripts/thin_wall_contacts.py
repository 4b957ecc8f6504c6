"""Which contact setting keeps a pile of thin-walled parts within the drop's bounds: 20 copies of one CAD part
dropped over several seeds with the drop's own settings and with one change each (docs/decisions.md, "Speculative
contacts for thin walls").

    python scripts/thin_wall_contacts.py [--part tests/fixtures/foreign_parts/duct_cover.stl] [--seeds 5]

Variants: ``default`` (the drop as it is, speculative contacts off), ``margin_0.5mm`` (every geom's contact margin
0.5 mm: contacts start before the walls touch, and parts rest on the margin), ``timestep_1ms`` (half the step, the
contact time constant halved with it), ``ccd_200`` (200 convex-collision iterations at 1e-8 tolerance),
``stiff_solimp`` (impedance 0.95-0.99 over 1 mm), ``speculative`` (MuJoCo's speculative contacts). Prints, per
variant, the piles within the bounds and the deepest penetration at rest of each seed.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np

import sygrid.physics as physics
from sygrid.objects import load_cad, select_collision_model
from sygrid.scene import parse_scene


def _margin(spec: mujoco.MjSpec) -> None:
    for g in spec.geoms:
        g.margin = 0.0005


def _timestep_1ms(spec: mujoco.MjSpec) -> None:
    spec.option.timestep = 0.001
    for g in spec.geoms:
        g.solref = [0.002, 1.0]


def _ccd(spec: mujoco.MjSpec) -> None:
    spec.option.ccd_iterations = 200
    spec.option.ccd_tolerance = 1e-8


def _solimp(spec: mujoco.MjSpec) -> None:
    for g in spec.geoms:
        g.solimp = [0.95, 0.99, 0.001, 0.5, 2]


def _speculative(spec: mujoco.MjSpec) -> None:
    spec.option.enableflags |= mujoco.mjtEnableBit.mjENBL_SPECULATIVE


VARIANTS: dict[str, Callable[[mujoco.MjSpec], None] | None] = {
    "default": None, "margin_0.5mm": _margin, "timestep_1ms": _timestep_1ms, "ccd_200": _ccd,
    "stiff_solimp": _solimp, "speculative": _speculative,
}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--part", type=Path, default=Path("tests/fixtures/foreign_parts/duct_cover.stl"))
    parser.add_argument("--unit", default="mm")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--count", type=int, default=20)
    args = parser.parse_args()
    logging.getLogger("sygrid.physics").setLevel(logging.ERROR)  # each failed bound is in the table
    model = load_cad(args.part, args.unit, 1)
    collision = select_collision_model(model)
    scene = parse_scene({"name": "thin_walls", "objects": [{"builtin": "hex_nut"}]})  # the default bin and physics
    instances = [physics.Instance(model_index=0, inst_id=i) for i in range(args.count)]
    build = physics.build_drop_spec
    for name, change in VARIANTS.items():

        def changed(*a, change=change, **k) -> mujoco.MjSpec:
            spec = build(*a, **k)
            if change is not None:
                change(spec)
            return spec

        physics.build_drop_spec = changed  # the drop builds its MjSpec here; the change is applied on top
        try:
            reports = [
                physics.simulate_drop(
                    [model], [collision], instances, scene.container, scene.physics, np.random.default_rng(seed)
                ).report
                for seed in range(args.seeds)
            ]
        finally:
            physics.build_drop_spec = build
        within = sum(r.within_bounds for r in reports)
        deepest = " ".join(f"{r.max_penetration_m * 1e3:.2f}" for r in reports)
        print(f"{name:<14} within bounds {within}/{len(reports)}   deepest penetration per seed [mm]: {deepest}")


if __name__ == "__main__":
    main()
