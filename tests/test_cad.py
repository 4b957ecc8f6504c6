"""CAD loading: round trips in mm and m for PLY/OBJ/STL, repair of messy meshes, and clear errors."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import trimesh

from sygrid.errors import MeshError
from sygrid.objects import ContinuousSymmetry, check_symmetries, load_cad
from sygrid.transforms import make_T, rotation_about

BOX_M = (0.04, 0.02, 0.01)


def _box(unit: str) -> trimesh.Trimesh:
    return trimesh.creation.box(np.array(BOX_M) * (1000.0 if unit == "mm" else 1.0))


def _write(mesh: trimesh.Trimesh, path: Path) -> Path:
    mesh.export(path)
    return path


def _soup(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The same surface with every face owning its own three vertices (as STL stores it)."""
    return trimesh.Trimesh(mesh.triangles.reshape(-1, 3), np.arange(3 * len(mesh.faces)).reshape(-1, 3), process=False)


@pytest.mark.parametrize("unit", ["mm", "m"])
@pytest.mark.parametrize("ext", ["ply", "obj", "stl"])
def test_round_trip(tmp_path: Path, ext: str, unit: str) -> None:
    path = _write(_box(unit), tmp_path / f"block.{ext}")
    model = load_cad(path, unit=unit, obj_id=9)
    np.testing.assert_allclose(sorted(model.extents_m), sorted(BOX_M), rtol=1e-6)
    np.testing.assert_allclose(model.mesh.bounds.mean(axis=0), 0.0, atol=1e-9)  # CAD frame kept
    assert model.mesh.is_watertight and model.metadata["watertight"] is True
    assert model.volume_m3 == pytest.approx(np.prod(BOX_M), rel=1e-5)
    assert (model.obj_id, model.name, model.material) == (9, "block", "steel")
    assert model.source == f"file:{path}" and len(model.mesh.faces) == 12
    assert model.models_info_entry()["size_x"] == pytest.approx(40.0, rel=1e-5)


def test_name_material_and_density(tmp_path: Path) -> None:
    path = _write(_box("mm"), tmp_path / "b.ply")
    model = load_cad(path, "mm", 2, name="spacer", material="aluminium")
    assert (model.name, model.material, model.density_kg_m3) == ("spacer", "aluminium", 2700.0)
    assert load_cad(path, "mm", 2, density_kg_m3=1000.0).density_kg_m3 == 1000.0


def test_duplicate_vertices_and_faces_are_merged(tmp_path: Path) -> None:
    soup = _soup(_box("mm"))
    messy = trimesh.Trimesh(soup.vertices, np.vstack((soup.faces, soup.faces[:1])), process=False)
    path = _write(messy, tmp_path / "soup.ply")
    model = load_cad(path, "mm", 1)
    assert len(model.mesh.vertices) == 8 and len(model.mesh.faces) == 12
    assert model.metadata["repairs"]["merged_vertices"] == 28
    assert model.metadata["repairs"]["duplicate_faces"] == 1
    assert model.mesh.is_volume


def test_inverted_winding_is_fixed(tmp_path: Path) -> None:
    box = _box("mm")
    path = _write(trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False), tmp_path / "inside_out.ply")
    model = load_cad(path, "mm", 1)
    assert model.mesh.volume > 0.0 and model.mesh.is_volume


def test_tiny_stray_component_is_dropped(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    speck = trimesh.creation.box((1.0, 1.0, 1.0))
    speck.apply_translation((60.0, 0.0, 0.0))
    path = _write(trimesh.util.concatenate([_box("mm"), speck]), tmp_path / "with_speck.stl")
    with caplog.at_level(logging.WARNING, logger="sygrid.objects.cad"):
        model = load_cad(path, "mm", 1)
    assert "dropped 1 of 2 disconnected components" in caplog.text
    assert len(model.mesh.faces) == 12 and model.metadata["repairs"]["stray_components"] == 1
    assert model.extents_m.max() == pytest.approx(0.04)


def test_large_components_are_kept(tmp_path: Path) -> None:
    other = _box("mm")
    other.apply_translation((60.0, 0.0, 0.0))
    path = _write(trimesh.util.concatenate([_box("mm"), other]), tmp_path / "pair.ply")
    model = load_cad(path, "mm", 1)
    assert len(model.mesh.faces) == 24 and model.metadata["repairs"]["stray_components"] == 0


def test_small_hole_is_filled(tmp_path: Path) -> None:
    box = _box("mm")
    path = _write(trimesh.Trimesh(box.vertices, box.faces[1:], process=False), tmp_path / "one_face_missing.obj")
    model = load_cad(path, "mm", 1)
    assert model.mesh.is_watertight and model.metadata["repairs"]["hole_faces_added"] == 1


def test_open_mesh_is_accepted_with_a_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("SYGRID_CACHE_DIR", str(tmp_path / "cache"))
    tube = trimesh.creation.cylinder(radius=10.0, height=30.0, sections=32)
    walls = np.abs(tube.face_normals[:, 2]) < 0.5  # drop both caps: two 32-edge holes, too big to fill
    path = _write(trimesh.Trimesh(tube.vertices, tube.faces[walls], process=False), tmp_path / "open_tube.ply")
    with caplog.at_level(logging.WARNING, logger="sygrid.objects.cad"):
        model = load_cad(path, "mm", 1)
    assert "not watertight" in caplog.text and "64 open edges" in caplog.text
    assert model.metadata["watertight"] is False
    # its matter is the zero-thickness wall thickened to the minimum thickness (1 mm), not its convex hull
    assert model.solid.is_volume
    assert model.volume_m3 == pytest.approx(2 * np.pi * 10e-3 * 30e-3 * 1e-3, rel=0.1)
    assert model.mass_kg == pytest.approx(model.volume_m3 * model.density_kg_m3)


def test_recenter_moves_the_symmetries_with_the_frame(tmp_path: Path) -> None:
    box = _box("m")
    box.apply_translation((0.1, 0.0, 0.0))
    path = _write(box, tmp_path / "offset_box.ply")
    T_cad_sym = make_T(rotation_about(np.array([0.0, 0.0, 1.0]), np.pi), (0.2, 0.0, 0.0))  # about x = 0.1
    axis_x = ContinuousSymmetry((2.0, 0.0, 0.0), (0.0, 0.0, 0.0))  # not a symmetry of a 40x20x10 box
    kept = load_cad(path, "m", 1, symmetries_discrete=(T_cad_sym,))
    assert kept.metadata["symmetry_problems"] == [] and "T_cad_obj" not in kept.metadata
    model = load_cad(path, "m", 1, symmetries_discrete=(T_cad_sym,), recenter=True)
    np.testing.assert_allclose(model.mesh.bounds.mean(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(model.symmetries_discrete[0][:3, 3], 0.0, atol=1e-8)  # PLY stores float32
    np.testing.assert_allclose(np.asarray(model.metadata["T_cad_obj"])[:3, 3], (0.1, 0.0, 0.0), atol=1e-8)
    assert check_symmetries(model, tol_m=1e-6, n_samples=300) == []
    normalised = load_cad(path, "m", 1, symmetries_continuous=(axis_x,), verify_symmetries=False)
    assert normalised.symmetries_continuous[0].axis == (1.0, 0.0, 0.0)


def test_a_false_declared_symmetry_is_warned_about(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = _write(_box("mm"), tmp_path / "b.ply")
    quarter_turn = make_T(rotation_about(np.array([0.0, 0.0, 1.0]), np.pi / 2))
    with caplog.at_level(logging.WARNING, logger="sygrid.objects.cad"):
        model = load_cad(path, "mm", 1, symmetries_discrete=(quarter_turn,))
    assert "declared symmetry does not hold" in caplog.text
    assert len(model.metadata["symmetry_problems"]) == 1


# ---------------------------------------------------------------------------------------------------- errors
def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(MeshError, match=r"nothere\.stl: mesh file not found"):
        load_cad(tmp_path / "nothere.stl", "mm", 1)


def test_unsupported_extension_lists_the_supported_ones(tmp_path: Path) -> None:
    path = tmp_path / "part.step"
    path.write_text("ISO-10303-21;")
    with pytest.raises(
        MeshError, match=r"part\.step: unsupported mesh format '\.step'; supported: \.ply, \.obj, \.stl"
    ):
        load_cad(path, "mm", 1)


def test_garbage_ply_fails_to_parse(tmp_path: Path) -> None:
    path = tmp_path / "junk.ply"
    path.write_bytes(b"\x00\x01garbage, not a mesh\xff")
    with pytest.raises(MeshError, match=r"junk\.ply: could not parse the file as PLY"):
        load_cad(path, "mm", 1)


@pytest.mark.parametrize("ext", ["stl", "obj"])
def test_garbage_text_has_no_faces(tmp_path: Path, ext: str) -> None:
    path = tmp_path / f"junk.{ext}"
    path.write_text("this is not a mesh\nat all\n")
    with pytest.raises(MeshError, match=rf"junk\.{ext}: the mesh has no faces .*not a valid {ext.upper()} file"):
        load_cad(path, "mm", 1)


def test_mesh_without_faces(tmp_path: Path) -> None:
    path = tmp_path / "points.obj"
    path.write_text("v 0 0 0\nv 10 0 0\nv 0 10 0\n")
    with pytest.raises(MeshError, match=r"points\.obj: the mesh has no faces"):
        load_cad(path, "mm", 1)


def test_all_faces_degenerate(tmp_path: Path) -> None:
    path = tmp_path / "flat.obj"
    path.write_text("v 0 0 0\nv 10 0 0\nv 20 0 0\nv 30 0 0\nf 1 2 3\nf 2 3 4\n")
    with pytest.raises(MeshError, match=r"flat\.obj: all 2 faces are degenerate"):
        load_cad(path, "mm", 1)


@pytest.mark.parametrize("bad", ["nan", "inf"])
def test_non_finite_vertices(tmp_path: Path, bad: str) -> None:
    path = tmp_path / "bad.obj"
    path.write_text(f"v {bad} 0 0\nv 10 0 0\nv 0 10 0\nv 0 0 10\nf 1 2 3\nf 1 2 4\n")
    with pytest.raises(MeshError, match=r"bad\.obj: 1 of 4 vertices are NaN or infinite"):
        load_cad(path, "mm", 1)


def test_millimetres_declared_as_metres_suggests_mm(tmp_path: Path) -> None:
    path = _write(trimesh.creation.box((45.0, 20.0, 10.0)), tmp_path / "big.stl")
    with pytest.raises(MeshError, match=r"big\.stl: the mesh is 45 m across with unit='m'.*did you mean unit='mm'\?"):
        load_cad(path, "m", 1)


def test_metres_declared_as_millimetres_suggests_m(tmp_path: Path) -> None:
    path = _write(_box("m"), tmp_path / "small.obj")
    with pytest.raises(
        MeshError, match=r"small\.obj: the mesh is 4e-05 m across with unit='mm'.*did you mean unit='m'\?"
    ):
        load_cad(path, "mm", 1)


def test_implausible_in_both_units_has_no_suggestion(tmp_path: Path) -> None:
    path = _write(trimesh.creation.box((1e5, 1.0, 1.0)), tmp_path / "huge.ply")
    with pytest.raises(MeshError, match=r"huge\.ply: the mesh is 100000 m across .*for a part$"):
        load_cad(path, "m", 1)


def test_invalid_arguments(tmp_path: Path) -> None:
    path = _write(_box("mm"), tmp_path / "b.ply")
    with pytest.raises(MeshError, match=r"b\.ply: unit must be one of \['m', 'mm'\], got 'cm'"):
        load_cad(path, "cm", 1)  # type: ignore[arg-type]
    with pytest.raises(MeshError, match=r"obj_id must be an integer >= 1, got 0"):
        load_cad(path, "mm", 0)
    with pytest.raises(MeshError, match=r"material must be one of \['steel', .*got 'gold'"):
        load_cad(path, "mm", 1, material="gold")
    with pytest.raises(MeshError, match=r"symmetries_discrete\[0\] must be a rigid 4x4 transform"):
        load_cad(path, "mm", 1, symmetries_discrete=(np.diag([2.0, 1.0, 1.0, 1.0]),))
    with pytest.raises(MeshError, match=r"symmetries_continuous\[0\] needs a non-zero finite 3-vector axis"):
        load_cad(path, "mm", 1, symmetries_continuous=(ContinuousSymmetry((0.0, 0.0, 0.0)),))
