"""Collision tiers: primitives for simple shapes, decompositions that keep holes, the disk cache, the selection rule."""

from __future__ import annotations

import logging
from pathlib import Path

import mujoco
import numpy as np
import pytest
import trimesh

from sygrid.errors import MeshError
from sygrid.objects.collision.build import build_collision_model, select_collision_model
from sygrid.objects.collision.geometry import CollisionModel
from sygrid.objects.collision.params import CollisionParams, CollisionTier
from sygrid.objects.inside import points_in_convex, points_in_mesh
from sygrid.objects.model import ObjectModel
from sygrid.objects.parts import builtin_part
from sygrid.transforms import make_T, rotation_about

# ---------------------------------------------------------------------------------------------- fixtures


def _model(mesh: trimesh.Trimesh, name: str) -> ObjectModel:
    return ObjectModel(obj_id=99, name=name, mesh=mesh)


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One cache for the module, so each decomposition is computed once per test run."""
    return tmp_path_factory.mktemp("collision_cache")


@pytest.fixture(scope="module")
def box() -> ObjectModel:
    return _model(trimesh.creation.box([0.04, 0.03, 0.02]), "box")


@pytest.fixture(scope="module")
def tilted_box() -> ObjectModel:
    mesh = trimesh.creation.box([0.05, 0.02, 0.01])
    mesh.apply_transform(make_T(rotation_about(np.array([1.0, 2.0, 3.0]), 0.7), np.array([0.01, -0.02, 0.005])))
    return _model(mesh, "tilted_box")


@pytest.fixture(scope="module")
def cylinder() -> ObjectModel:
    return _model(trimesh.creation.cylinder(radius=0.01, height=0.03, sections=64), "cylinder")


@pytest.fixture(scope="module")
def nut() -> ObjectModel:
    """M12 hex nut (ISO 4032): 18 mm across flats, 10.8 mm high, 12 mm hole; its hole is 41 % of its volume."""
    return builtin_part("hex_nut")


def assert_valid_pieces(model: ObjectModel, coll: CollisionModel, margin_m: float = 5e-4) -> None:
    """Every piece a closed convex mesh with positive volume, vertices within the part's bounds + margin, and the
    pieces together cover the part (little missed volume)."""
    assert coll.pieces, "no pieces"
    lo, hi = model.bounds_m
    for k, (vertices, faces) in enumerate(coll.convex_pieces()):
        assert vertices.dtype == np.float64 and vertices.shape[1] == 3, k
        assert faces.shape[1] == 3 and faces.min() >= 0 and faces.max() < len(vertices), k
        piece = trimesh.Trimesh(vertices, faces, process=False)
        assert piece.is_watertight and piece.is_winding_consistent, f"piece {k} is not closed"
        assert piece.is_convex, f"piece {k} is not convex"
        assert piece.volume > 0, f"piece {k} has volume {piece.volume} (inward normals or flat)"
        assert np.all(vertices >= lo - margin_m) and np.all(vertices <= hi + margin_m), f"piece {k} out of bounds"
    assert coll.fidelity.missed_volume_ratio < 0.1, coll.fidelity


# ---------------------------------------------------------------------------------------------- tiers


def test_box_gets_a_box_primitive(box: ObjectModel, tmp_path: Path) -> None:
    coll = build_collision_model(box, "hull", cache_dir=tmp_path)
    assert coll.tier is CollisionTier.HULL and not coll.pieces
    (prim,) = coll.primitive_geoms()
    assert prim.kind == "box"
    np.testing.assert_allclose(sorted(prim.size_m), [0.01, 0.015, 0.02], atol=1e-9)
    fid = coll.fidelity
    assert fid.excess_volume_ratio < 1e-3 and fid.missed_volume_ratio < 1e-3
    assert fid.concavity_kept == 1.0 and fid.concave_volume_ratio == 0.0
    assert (fid.n_pieces, fid.n_vertices_total) == (1, 0)


def test_tilted_box_primitive_pose_matches_the_mesh(tilted_box: ObjectModel, tmp_path: Path) -> None:
    coll = build_collision_model(tilted_box, "hull", cache_dir=tmp_path)
    (prim,) = coll.primitive_geoms()
    assert prim.kind == "box"
    assert coll.fidelity.excess_volume_ratio < 1e-3 and coll.fidelity.missed_volume_ratio < 1e-3
    np.testing.assert_allclose(prim.T_obj_geom[:3, 3], tilted_box.mesh.center_mass, atol=1e-9)


def test_cylinder_gets_a_cylinder_primitive(cylinder: ObjectModel, tmp_path: Path) -> None:
    coll = build_collision_model(cylinder, CollisionTier.HULL, cache_dir=tmp_path)
    (prim,) = coll.primitive_geoms()
    assert prim.kind == "cylinder"
    np.testing.assert_allclose(prim.size_m, [0.01, 0.015], rtol=1e-3)  # MuJoCo: radius, half-length
    np.testing.assert_allclose(np.abs(prim.T_obj_geom[:3, 2]), [0, 0, 1], atol=1e-3)  # geom z along the axis
    # a 64-gon prism is 0.16 % smaller than its circumscribed cylinder
    assert coll.fidelity.excess_volume_ratio < 0.01 and coll.fidelity.missed_volume_ratio < 1e-3


def test_nut_hull_fills_the_hole(nut: ObjectModel, cache_dir: Path) -> None:
    coll = build_collision_model(nut, "hull", cache_dir=cache_dir)
    assert not coll.primitives and len(coll.pieces) == 1  # a hexagon is neither a box nor a cylinder
    fid = coll.fidelity
    # the hull adds exactly the hole: (hull volume - mesh volume) / mesh volume, within Monte-Carlo error
    exact = nut.mesh.convex_hull.volume / nut.mesh.volume - 1.0
    assert fid.excess_volume_ratio == pytest.approx(exact, abs=0.03)
    assert fid.excess_volume_ratio > 0.3
    assert fid.concavity_kept < 0.02 and fid.missed_volume_ratio < 1e-3
    assert fid.concave_volume_ratio == pytest.approx(exact, abs=0.03)
    assert_valid_pieces(nut, coll)


def test_nut_coacd_keeps_the_hole(nut: ObjectModel, cache_dir: Path) -> None:
    coll = build_collision_model(nut, "coacd", cache_dir=cache_dir)
    fid = coll.fidelity
    assert fid.concavity_kept > 0.7, fid
    assert fid.excess_volume_ratio < 0.08 and fid.missed_volume_ratio < 0.01, fid
    assert 2 <= fid.n_pieces == len(coll.pieces) <= 30
    assert fid.n_vertices_total == sum(len(v) for v, _f in coll.convex_pieces())
    assert_valid_pieces(nut, coll)
    # a pin through the hole's axis is free of every piece
    pin = np.column_stack([np.zeros(50), np.zeros(50), np.linspace(-0.005, 0.005, 50)])
    assert not coll.contains(pin).any()


def test_nut_vhacd_pieces_are_sane(nut: ObjectModel, cache_dir: Path) -> None:
    """vhacdx given (F, 3) faces instead of the flat [3, i, j, k, ...] array returns convex pieces inside the part's
    bounds that miss about 35 % of the nut: the coverage check is what catches that pitfall."""
    coll = build_collision_model(nut, "vhacd", cache_dir=cache_dir)
    assert_valid_pieces(nut, coll)
    fid = coll.fidelity
    assert fid.missed_volume_ratio < 0.08 and fid.excess_volume_ratio < 0.08, fid
    assert fid.concavity_kept > 0.7, fid
    assert fid.n_pieces <= CollisionParams().vhacd_max_hulls


def test_to_mujoco_geoms_compile_in_an_mjspec(box: ObjectModel, nut: ObjectModel, cache_dir: Path) -> None:
    for coll in (build_collision_model(box, "hull", cache_dir=cache_dir),
                 build_collision_model(nut, "coacd", cache_dir=cache_dir)):  # fmt: skip
        geoms = coll.to_mujoco_geoms()
        assert len(geoms) == coll.n_pieces
        spec = mujoco.MjSpec()
        body = spec.worldbody.add_body(name="part")
        body.add_freejoint()
        for k, g in enumerate(geoms):
            np.testing.assert_allclose(np.linalg.norm(g["quat"]), 1.0)
            if g["type"] == "mesh":
                spec.add_mesh(name=f"piece{k}", uservert=g["vertices"].reshape(-1).tolist())
                body.add_geom(type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"piece{k}")
            else:
                geom_type = {"box": mujoco.mjtGeom.mjGEOM_BOX, "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER}[g["type"]]
                body.add_geom(type=geom_type, size=g["size"].tolist(), pos=g["pos"].tolist(), quat=g["quat"].tolist())
        model = spec.compile()
        assert model.ngeom == len(geoms)


# ---------------------------------------------------------------------------------------------- cache


def _same(a: CollisionModel, b: CollisionModel) -> bool:
    pieces_equal = len(a.pieces) == len(b.pieces) and all(
        np.array_equal(pa.vertices, pb.vertices) and np.array_equal(pa.faces, pb.faces)
        for pa, pb in zip(a.pieces, b.pieces, strict=True)
    )
    prims_equal = len(a.primitives) == len(b.primitives) and all(
        pa.kind == pb.kind and pa.size_m == pb.size_m and np.array_equal(pa.T_obj_geom, pb.T_obj_geom)
        for pa, pb in zip(a.primitives, b.primitives, strict=True)
    )
    return pieces_equal and prims_equal and a.fidelity == b.fidelity and a.compute_s == b.compute_s


def _same_geometry(a: CollisionModel, b: CollisionModel) -> bool:
    return len(a.pieces) == len(b.pieces) and all(
        np.array_equal(x.vertices, y.vertices) for x, y in zip(a.pieces, b.pieces, strict=True)
    )


@pytest.mark.parametrize("part", ["nut", "cylinder"])
def test_second_call_is_a_cache_hit_with_identical_arrays(part: str, request: pytest.FixtureRequest,
                                                          tmp_path: Path) -> None:  # fmt: skip
    model = request.getfixturevalue(part)
    first = build_collision_model(model, "hull", cache_dir=tmp_path)
    second = build_collision_model(model, "hull", cache_dir=tmp_path)
    assert not first.from_cache and second.from_cache
    assert _same(first, second)
    assert {p.suffix for p in tmp_path.iterdir()} == {".npz", ".json"}


def test_decomposition_cache_hit(nut: ObjectModel, cache_dir: Path) -> None:
    first = build_collision_model(nut, "coacd", cache_dir=cache_dir)
    again = build_collision_model(nut, "coacd", cache_dir=cache_dir)
    assert again.from_cache and _same(first, again)


def test_params_are_part_of_the_key(nut: ObjectModel, tmp_path: Path) -> None:
    build_collision_model(nut, "hull", cache_dir=tmp_path)
    other = build_collision_model(nut, "hull", CollisionParams(fidelity_seed=1), cache_dir=tmp_path)
    assert not other.from_cache
    # a knob of another tier does not invalidate this tier's entry
    unrelated = build_collision_model(nut, "hull", CollisionParams(coacd_concavity_threshold=0.2), cache_dir=tmp_path)
    assert unrelated.from_cache


@pytest.mark.parametrize("damage", ["truncate_npz", "garbage_json", "swap_npz"])
def test_corrupt_cache_entry_is_rebuilt_with_a_warning(
    damage: str, nut: ObjectModel, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    good = build_collision_model(nut, "hull", cache_dir=tmp_path)
    (npz,) = tmp_path.glob("*.npz")
    (meta,) = tmp_path.glob("*.json")
    if damage == "truncate_npz":
        npz.write_bytes(npz.read_bytes()[:100])
    elif damage == "garbage_json":
        meta.write_text("{not json")
    else:  # a valid npz of other content: the recorded hash does not match
        np.savez(npz, vertices=np.zeros((4, 3)), faces=np.zeros((4, 3), dtype=np.int64))
    with caplog.at_level(logging.WARNING, logger="sygrid.objects.collision"):
        rebuilt = build_collision_model(nut, "hull", cache_dir=tmp_path)
    assert not rebuilt.from_cache
    assert any("unreadable collision cache entry" in r.getMessage() for r in caplog.records)
    assert _same_geometry(good, rebuilt)
    assert build_collision_model(nut, "hull", cache_dir=tmp_path).from_cache  # the rebuilt entry is good again


def test_cache_dir_from_the_environment_at_call_time(
    box: ObjectModel, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("SYGRID_CACHE_DIR", str(tmp_path / "root"))
    build_collision_model(box, "hull")
    assert list((tmp_path / "root" / "collision").glob("*.npz"))


# ---------------------------------------------------------------------------------------------- selection


def test_selection_keeps_a_box_a_primitive(box: ObjectModel, tmp_path: Path) -> None:
    coll = select_collision_model(box, cache_dir=tmp_path)
    assert coll.tier is CollisionTier.HULL and coll.primitives[0].kind == "box"
    assert not list(tmp_path.glob("*coacd*"))  # the decompositions were never built


def test_selection_decomposes_a_nut(nut: ObjectModel, cache_dir: Path) -> None:
    coll = select_collision_model(nut, cache_dir=cache_dir)
    assert coll.tier is not CollisionTier.HULL
    assert coll.fidelity.excess_volume_ratio <= 0.05 and coll.fidelity.concavity_kept >= 0.5


def test_selection_warns_when_no_tier_meets_the_tolerance(
    nut: ObjectModel, cache_dir: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING, logger="sygrid.objects.collision"):
        coll = select_collision_model(nut, max_excess_volume_ratio=0.01, tiers=["hull"], cache_dir=cache_dir)
    assert coll.tier is CollisionTier.HULL
    (record,) = [r for r in caplog.records if "no collision tier" in r.getMessage()]
    assert "max_excess_volume_ratio=0.01" in record.getMessage() and "min_concavity_kept" in record.getMessage()


# ---------------------------------------------------------------------------------------------- errors


def test_bad_tier_name_lists_the_valid_tiers(box: ObjectModel, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unknown collision tier 'convex'; valid tiers: hull, coacd, vhacd"):
        build_collision_model(box, "convex", cache_dir=tmp_path)
    with pytest.raises(ValueError, match="valid tiers"):
        select_collision_model(box, tiers=["hull", "bullet"], cache_dir=tmp_path)
    assert CollisionTier(" CoACD ") is CollisionTier.COACD


def test_a_decomposition_without_pieces_is_an_error(
    nut: ObjectModel, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import coacd

    monkeypatch.setattr(coacd, "run_coacd", lambda *args, **kwargs: [])
    with pytest.raises(MeshError, match="hex_nut: the coacd decomposition gave no usable convex piece"):
        build_collision_model(nut, "coacd", cache_dir=tmp_path)
    assert not list(tmp_path.iterdir())  # nothing cached


def test_bad_params_name_the_field() -> None:
    with pytest.raises(ValueError, match=r"coacd_concavity_threshold must be in \(0, 1\], got 0"):
        CollisionParams(coacd_concavity_threshold=0)
    with pytest.raises(ValueError, match="fidelity_samples must be >= 1000"):
        CollisionParams(fidelity_samples=10)


# ---------------------------------------------------------------------------------------------- geometry


def test_points_in_mesh_agrees_with_trimesh(nut: ObjectModel) -> None:
    points = np.random.default_rng(0).uniform(*nut.bounds_m, size=(3000, 3))
    ours = points_in_mesh(np.asarray(nut.mesh.triangles), points)
    theirs = nut.mesh.contains(points)
    assert (ours != theirs).sum() <= 3  # ray tests through nearly-tangent faces may differ on a point or two


def test_points_in_mesh_on_a_grid_through_edges_and_vertices() -> None:
    """Grid points line up with the diagonals that split the box's faces into triangles: the tie rule must count
    each crossing once (without it, 275 of the 8000 inside points come out outside)."""
    mesh = trimesh.creation.box([0.02, 0.02, 0.02])
    axis = np.linspace(-0.0145, 0.0145, 30)  # never on a face; x == +-y == +-z on many rays
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    inside = np.all(np.abs(grid) < 0.01, axis=1)
    np.testing.assert_array_equal(points_in_mesh(np.asarray(mesh.triangles), grid), inside)
    np.testing.assert_array_equal(points_in_convex(mesh.vertices, mesh.faces, grid), inside)


def test_vhacd_flat_faces_pitfall_is_caught(nut: ObjectModel, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Feeding vhacdx (F, 3) faces, as a natural reading of its signature suggests, gives no error but garbage
    pieces: ``assert_valid_pieces`` (used on every decomposition above) must reject them."""
    import vhacdx

    real = vhacdx.compute_vhacd

    def with_unflattened_faces(points: np.ndarray, faces: np.ndarray, **kwargs: object) -> list:
        return real(points, faces.reshape(-1, 4)[:, 1:].copy(), **kwargs)

    monkeypatch.setattr(vhacdx, "compute_vhacd", with_unflattened_faces)
    garbage = build_collision_model(nut, "vhacd", cache_dir=tmp_path)
    with pytest.raises(AssertionError, match="missed_volume_ratio"):
        assert_valid_pieces(nut, garbage)


def test_selection_tries_a_finer_coacd_before_vhacd(tmp_path):
    """The pipe misses the excess tolerance with CoACD's default threshold (12 %); the finer try meets it."""
    from sygrid.objects import builtin_part

    # no time budget: the choice, not the machine's load, is under test
    chosen = select_collision_model(builtin_part("pipe"), cache_dir=tmp_path, time_budget_s=None)
    assert chosen.tier is CollisionTier.COACD
    assert chosen.params.coacd_concavity_threshold == pytest.approx(CollisionParams().coacd_concavity_threshold * 0.4)
    assert chosen.fidelity.excess_volume_ratio <= 0.05 and chosen.fidelity.missed_volume_ratio <= 0.05
