"""Collision models of real-CAD-like meshes (tests/fixtures/foreign_parts): the repaired solid of open, multi-body
and thin meshes, decomposition within the piece cap and the time budget, mass from the solid, and the cache keys
of repaired parts."""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

from sygrid.mjspec import part_inertial
from sygrid.objects import load_cad
from sygrid.objects.collision import build as build_module
from sygrid.objects.collision import solid as solid_module
from sygrid.objects.collision.build import build_collision_model, select_collision_model
from sygrid.objects.collision.params import CollisionParams, CollisionTier
from sygrid.objects.collision.solid import make_solid, repaired_solid, solid_method
from sygrid.objects.collision.tiers import DecompositionTimeoutError
from sygrid.objects.model import ObjectModel
from sygrid.objects.parts import builtin_part

FIXTURES = Path(__file__).parent / "fixtures" / "foreign_parts"
# coarse settings that keep these tests to seconds: a 0.75 mm grid, fewer fidelity samples
FAST = CollisionParams(solid_min_thickness_m=0.0015, fidelity_samples=5000)
BUDGET_S = 20.0  # time budget per part in these tests


@pytest.fixture(autouse=True)
def _own_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every cache (the repaired solids of ``ObjectModel.solid`` too) in the test's own folder."""
    monkeypatch.setenv("SYGRID_CACHE_DIR", str(tmp_path / "cache"))


def _load(name: str) -> ObjectModel:
    return load_cad(FIXTURES / f"{name}.stl", "mm", 1, name=name)


def _open_tube(r_in: float, r_out: float, height: float, sections: int = 48) -> trimesh.Trimesh:
    """A tube's inner and outer walls (metres) without its end rings: open, each wall a separate surface."""
    outer = trimesh.creation.cylinder(radius=r_out, height=height, sections=sections)
    inner = trimesh.creation.cylinder(radius=r_in, height=height, sections=sections)
    inner.invert()
    return trimesh.util.concatenate(
        [trimesh.Trimesh(m.vertices, m.faces[np.abs(m.face_normals[:, 2]) < 0.5]) for m in (outer, inner)]
    )


# ---------------------------------------------------------------------------------------------- the solid


def test_fixtures_have_the_problems_they_are_for() -> None:
    methods = {p.stem: solid_method(trimesh.load(p, force="mesh")) for p in sorted(FIXTURES.glob("*.stl"))}
    assert methods == {
        "bolt_nut_pair": "union", "duct_cover": "as-is", "nozzle": "voxel", "plate_bracket": "union",
        "spacer_block": "as-is", "strap_clamp": "voxel",
    }  # fmt: skip
    assert sum(p.stat().st_size for p in FIXTURES.iterdir()) < 300_000


def test_builtin_parts_are_their_own_solid() -> None:
    nut = builtin_part("hex_nut")
    assert nut.solid is nut.mesh and nut.volume_m3 == pytest.approx(nut.mesh.volume)


def test_open_walls_are_closed_not_thickened() -> None:
    """Inner and outer walls 2 mm apart with open ends: the matter between them, not two thickened sheets."""
    r_in, r_out, height = 0.005, 0.007, 0.012
    solid = make_solid(_open_tube(r_in, r_out, height), FAST, "tube")
    assert solid.method == "voxel" and solid.mesh.is_volume and solid.mesh.body_count == 1
    assert solid.mesh.volume == pytest.approx(np.pi * (r_out**2 - r_in**2) * height, rel=0.1)


def test_a_wall_thinner_than_the_minimum_is_thickened_about_its_middle() -> None:
    r_mid, t, height = 0.006, FAST.solid_min_thickness_m, 0.012
    solid = make_solid(_open_tube(r_mid - 0.00025, r_mid + 0.00025, height), FAST, "thin tube").mesh
    assert solid.volume == pytest.approx(np.pi * ((r_mid + t / 2) ** 2 - (r_mid - t / 2) ** 2) * height, rel=0.15)


def test_a_sheet_is_thickened_to_the_minimum_thickness() -> None:
    sheet = trimesh.Trimesh([[0, 0, 0], [0.02, 0, 0], [0.02, 0.02, 0], [0, 0.02, 0]], [[0, 1, 2], [0, 2, 3]])
    solid = make_solid(sheet, FAST, "sheet").mesh
    assert solid.is_volume
    assert solid.extents[2] == pytest.approx(FAST.solid_min_thickness_m, rel=0.15)
    assert solid.volume == pytest.approx(0.02 * 0.02 * FAST.solid_min_thickness_m, rel=0.15)


def test_multi_body_meshes_are_unioned() -> None:
    pair = trimesh.load(FIXTURES / "bolt_nut_pair.stl", force="mesh")
    bracket = trimesh.load(FIXTURES / "plate_bracket.stl", force="mesh")
    pair_solid, bracket_solid = make_solid(pair, FAST).mesh, make_solid(bracket, FAST).mesh
    assert pair_solid.body_count == 2 and pair_solid.volume == pytest.approx(pair.volume, rel=1e-6)  # apart
    # the overlapping plates count once: less than the sum of the bodies, as much as a boolean union
    union = trimesh.boolean.union(bracket.split(only_watertight=False), engine="manifold")
    assert bracket_solid.body_count == 1 and bracket_solid.volume < 0.98 * bracket.volume
    assert bracket_solid.volume == pytest.approx(union.volume, rel=1e-6)


def test_mass_of_an_open_mesh_comes_from_its_solid_not_its_hull() -> None:
    clamp = _load("strap_clamp")
    assert not clamp.metadata["watertight"]
    assert clamp.solid.is_volume
    assert clamp.mass_kg == pytest.approx(clamp.solid.volume * clamp.density_kg_m3)
    # a 1 mm sheet: about its (one-sided) area times the thickness; its convex hull is five times heavier
    assert clamp.volume_m3 == pytest.approx(clamp.mesh.area * 1e-3, rel=0.3)
    assert clamp.mesh.convex_hull.volume > 5 * clamp.volume_m3
    assert clamp.mass_source == "density x repaired solid volume"
    # a declared mass: the inertia is the solid's at the density that gives it
    declared = clamp.with_mass(0.01)
    mass, _com, inertia = part_inertial(declared)
    assert mass == pytest.approx(0.01)
    np.testing.assert_allclose(inertia[0], clamp.solid.moment_inertia[0, 0] * 0.01 / clamp.volume_m3, rtol=1e-9)


def test_the_solid_is_cached_on_disk(tmp_path: Path) -> None:
    mesh = trimesh.load(FIXTURES / "strap_clamp.stl", force="mesh")
    mesh.apply_scale(1e-3)
    solid_module._MEMO.clear()
    first = repaired_solid(mesh, "f" * 64, FAST, tmp_path)
    solid_module._MEMO.clear()
    start = time.perf_counter()
    again = repaired_solid(mesh, "f" * 64, FAST, tmp_path)
    assert time.perf_counter() - start < first.compute_s + 0.5
    assert np.array_equal(first.mesh.vertices, again.mesh.vertices) and again.compute_s == first.compute_s
    assert len(list(tmp_path.glob("*-solid-*.npz"))) == 1


# ---------------------------------------------------------------------------------------------- decomposition


@pytest.mark.parametrize("name", ["strap_clamp", "plate_bracket"])
def test_open_and_multi_body_parts_decompose_within_the_caps(
    name: str, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    part = _load(name)
    start = time.perf_counter()
    with caplog.at_level(logging.INFO, logger="sygrid.objects.collision"):
        chosen = select_collision_model(part, params=FAST, cache_dir=tmp_path, time_budget_s=BUDGET_S)
    elapsed = time.perf_counter() - start
    assert chosen.n_pieces <= 64
    assert elapsed < BUDGET_S + 10.0  # the budget, plus the fidelity of the last try
    # fidelity against the repaired solid: the pieces cover it, and add a fraction of it, not multiples
    assert chosen.fidelity.missed_volume_ratio < 0.1 and chosen.fidelity.excess_volume_ratio < 0.5
    assert "building its hull collision model" in caplog.text  # progress: a line per stage
    again = select_collision_model(part, params=FAST, cache_dir=tmp_path, time_budget_s=BUDGET_S)
    assert again.from_cache and again.description == chosen.description


def test_a_decomposition_out_of_time_is_stopped_and_not_retried(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(build_module, "_WARNED", set())  # this test's warnings do not silence other tests'
    nut = builtin_part("hex_nut")
    with pytest.raises(DecompositionTimeoutError, match="did not finish within"):
        build_collision_model(nut, "coacd", FAST, tmp_path, time_limit_s=0.01)
    assert list(tmp_path.glob("*.timeout.json"))
    start = time.perf_counter()
    with pytest.raises(DecompositionTimeoutError, match="not retried"):
        build_collision_model(nut, "coacd", FAST, tmp_path, time_limit_s=0.0125)
    assert time.perf_counter() - start < 1.0
    # no time for any decomposition: the hull, the cheapest tier, is the fallback
    fallback = select_collision_model(nut, tiers=["coacd", "vhacd"], params=FAST, cache_dir=tmp_path, time_budget_s=0.5)
    assert fallback.tier is CollisionTier.HULL


def test_a_child_process_gives_the_same_pieces(tmp_path: Path) -> None:
    nut = builtin_part("hex_nut")
    here = build_collision_model(nut, "coacd", FAST, tmp_path / "a")
    child = build_collision_model(nut, "coacd", FAST, tmp_path / "b", time_limit_s=120.0)
    assert len(here.pieces) == len(child.pieces) <= 64
    assert all(np.array_equal(a.vertices, b.vertices) for a, b in zip(here.pieces, child.pieces, strict=True))


# ---------------------------------------------------------------------------------------------- cache keys


def test_a_changed_repair_invalidates_the_entries_of_repaired_parts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    clamp, nut = _load("strap_clamp"), builtin_part("hex_nut")
    for part in (clamp, nut):
        build_collision_model(part, "hull", FAST, tmp_path)
        assert build_collision_model(part, "hull", FAST, tmp_path).from_cache
    thicker = replace(FAST, solid_min_thickness_m=0.002)
    assert not build_collision_model(clamp, "hull", thicker, tmp_path).from_cache
    assert build_collision_model(nut, "hull", thicker, tmp_path).from_cache  # a closed part is not repaired
    monkeypatch.setattr(solid_module, "SOLID_VERSION", solid_module.SOLID_VERSION + 1)
    assert not build_collision_model(clamp, "hull", FAST, tmp_path).from_cache
    assert build_collision_model(nut, "hull", FAST, tmp_path).from_cache


# ---------------------------------------------------------------------------------------------- benchmark


def test_bench_parts_runs_on_a_small_folder(tmp_path: Path) -> None:
    import argparse
    import json
    import shutil

    from sygrid.bench import parts as bench_parts

    folder = tmp_path / "parts"
    folder.mkdir()
    shutil.copy(FIXTURES / "duct_cover.stl", folder)
    args = argparse.Namespace(folder=folder, unit="mm", seeds=1, count=3, items=0, contacts=["off", "on"])
    assert bench_parts.run(args, out_dir=tmp_path / "results") == 0
    data = json.loads((tmp_path / "results" / "parts.json").read_text())
    (row,) = data["parts"]
    assert row["part"] == "duct_cover" and row["pieces"] <= 64 and row["cache_hit"]
    assert row["wall_thickness_mm"] == pytest.approx(1.0, abs=0.05)
    piles = [(p["pile"], p["contacts"], p["speculative_fraction"]) for p in data["piles"]]
    assert piles == [("duct_cover", "off", 0.0), ("duct_cover", "on", 1.0), ("mixed", "off", 0.0), ("mixed", "on", 1.0)]
    assert data["summary"]["contacts"] == "on"
    assert (tmp_path / "results" / "parts.png").stat().st_size > 0
