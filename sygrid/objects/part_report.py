"""What ``sygrid parts`` says about a part: its size, mesh health (watertight, components, repairs), volume, mass
and where the mass comes from, diameter, wall thickness (``thickness``), and its symmetries, declared and
proposed (``symmetry_proposal``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sygrid.objects.model import ObjectModel
from sygrid.objects.symmetry_proposal import SymmetryProposal, propose_symmetries, same_symmetries
from sygrid.objects.thickness import wall_thickness_m

# Under this wall, a part falling at 1 m/s (a 5 cm drop) crosses it in one 2 ms physics step (sygrid.physics).
_THIN_WALL_M = 0.002


@dataclass(frozen=True)
class PartReport:
    """A part's figures (SI units) and the warnings a user should act on."""

    obj_id: int
    name: str
    source: str
    material: str
    extents_m: tuple[float, float, float]
    watertight: bool
    components: int
    repairs: dict[str, int]
    volume_m3: float
    mass_kg: float
    mass_source: str
    density_kg_m3: float
    diameter_m: float
    wall_thickness_m: float
    declared: str
    proposal: SymmetryProposal | None
    proposal_matches: bool | None  # None: nothing proposed or nothing declared to compare with
    warnings: list[str] = field(default_factory=list)


def part_report(model: ObjectModel, propose: bool = True) -> PartReport:
    """The report of ``model``; ``propose`` also searches its symmetries (a second or so per part)."""
    proposal = propose_symmetries(model) if propose else None
    matches = None
    if proposal is not None and model.is_symmetric:
        matches = same_symmetries(
            proposal.symmetries_discrete,
            proposal.symmetries_continuous,
            model.symmetries_discrete,
            model.symmetries_continuous,
            proposal.tol_m,
        )
    warnings = []
    if model.mass_source == "density x repaired solid volume" and not model.mesh.is_watertight:
        warnings.append("open mesh: its volume and mass come from a repaired solid (a zero-thickness sheet thickened "
                        "to the minimum thickness); declare mass_kg if the part is heavier")  # fmt: skip
    warnings += [f"declared symmetry does not hold: {p}" for p in model.metadata.get("symmetry_problems", [])]
    wall_m = wall_thickness_m(model.solid)
    if wall_m < _THIN_WALL_M:
        warnings.append(f'thin walls ({wall_m * 1e3:.1f} mm): scenes with this part need "physics": '
                        '{"speculative_contacts": "auto"}, else walls can interlock in the drop')  # fmt: skip
    if matches is False:
        warnings.append("the declared symmetries differ from the proposed ones: check both")
    return PartReport(
        obj_id=model.obj_id,
        name=model.name,
        source=model.source,
        material=model.material,
        extents_m=tuple(float(v) for v in model.extents_m),  # type: ignore[arg-type]
        watertight=bool(model.mesh.is_watertight),
        components=int(model.mesh.body_count),
        repairs={k: int(v) for k, v in model.metadata.get("repairs", {}).items() if v},
        volume_m3=model.volume_m3,
        mass_kg=model.mass_kg,
        mass_source=model.mass_source,
        density_kg_m3=model.density_kg_m3,
        diameter_m=model.diameter_m,
        wall_thickness_m=wall_m,
        declared=_declared(model),
        proposal=proposal,
        proposal_matches=matches,
        warnings=warnings,
    )


def format_report(r: PartReport) -> list[str]:
    """The report as indented text lines (millimetres and grams, as a user reads them)."""
    size = " x ".join(f"{v * 1e3:.1f}" for v in r.extents_m)
    repairs = ", ".join(f"{k} {v}" for k, v in r.repairs.items()) or "none"
    lines = [
        f"{r.obj_id:>3} {r.name}  ({r.source})",
        f"    size {size} mm, diameter {r.diameter_m * 1e3:.1f} mm, wall {r.wall_thickness_m * 1e3:.1f} mm, "
        f"material {r.material}",
        f"    mesh: {'watertight' if r.watertight else 'OPEN (not watertight)'}, {r.components} component(s), "
        f"repairs: {repairs}",
        f"    volume {r.volume_m3 * 1e6:.3f} cm3, mass {r.mass_kg * 1e3:.1f} g ({r.mass_source}; "
        f"density {r.density_kg_m3:.0f} kg/m3)",
        f"    symmetries declared: {r.declared}",
    ]
    if r.proposal is not None:
        verdict = {True: " (matches the declared)", False: " (DIFFERS from the declared)", None: ""}
        lines.append(f"    symmetries proposed: {r.proposal.summary()}{verdict[r.proposal_matches]}")
    lines += [f"    warning: {w}" for w in r.warnings]
    return lines


def _declared(model: ObjectModel) -> str:
    if not model.is_symmetric:
        return "none"
    axes = ", ".join(
        f"continuous about ({', '.join(f'{v:.3g}' for v in np.asarray(s.axis) + 0.0)})"
        for s in model.symmetries_continuous
    )
    return f"{len(model.symmetries_discrete)} discrete + {len(model.symmetries_continuous)} continuous" + (
        f": {axes}" if axes else ""
    )
