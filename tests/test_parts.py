"""Built-in parts: watertight, true dimensions, declared symmetries that hold (and a check that can fail)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from sygrid.errors import SygridError, UnknownObjectError
from sygrid.objects import (
    BUILTIN_PARTS,
    ContinuousSymmetry,
    ObjectModel,
    builtin_part,
    check_symmetries,
    symmetry_error_m,
)
from sygrid.transforms import is_rigid, make_T, rotation_about

MM = 1e-3
SYM_TOL_M = 1e-5  # declared symmetries must hold to 10 um
N_SAMPLES = 500  # surface samples per symmetry check: enough to catch a wrong transform, fast on 2 cores

EXPECTED_IDS = {"hex_nut": 1, "hex_bolt": 2, "washer": 3, "l_bracket": 4, "pipe": 5, "spur_gear": 6, "flange": 7}
# (non-identity discrete transforms, continuous axes)
EXPECTED_SYMMETRY_COUNTS = {
    "hex_nut": (11, 0),  # D6
    "hex_bolt": (5, 0),  # C6
    "washer": (1, 1),  # continuous z x flip
    "l_bracket": (1, 0),  # 180 degrees about the bisector
    "pipe": (1, 1),
    "spur_gear": (39, 0),  # D20
    "flange": (7, 0),  # D4
}
# A rigid transform that is NOT a symmetry of each part, and the least error it must produce.
NON_SYMMETRIES = {
    "hex_nut": (make_T(rotation_about(np.array([0.0, 0.0, 1.0]), np.radians(30.0))), 0.5 * MM),
    "hex_bolt": (np.diag([1.0, -1.0, -1.0, 1.0]), 2.0 * MM),  # flip: the head breaks it
    "washer": (make_T(rotation_about(np.array([1.0, 0.0, 0.0]), np.pi / 2)), 5.0 * MM),
    "l_bracket": (np.diag([1.0, -1.0, -1.0, 1.0]), 5.0 * MM),
    "pipe": (make_T(rotation_about(np.array([1.0, 0.0, 0.0]), np.pi / 2)), 5.0 * MM),
    "spur_gear": (make_T(rotation_about(np.array([0.0, 0.0, 1.0]), np.pi / 20)), 0.5 * MM),  # half a tooth
    "flange": (make_T(rotation_about(np.array([0.0, 0.0, 1.0]), np.pi / 4)), 5.0 * MM),
}


def _through(mesh, x_m: float, y_m: float) -> bool:
    """True when a ray along z at (x, y) misses the mesh: there is a through hole there."""
    return not bool(mesh.ray.intersects_any([[x_m, y_m, -1.0]], [[0.0, 0.0, 1.0]])[0])


def _max_radius(vertices: np.ndarray) -> float:
    return float(np.linalg.norm(vertices[:, :2], axis=1).max())


def test_names_ids_and_order() -> None:
    assert tuple(EXPECTED_IDS) == BUILTIN_PARTS
    assert [builtin_part(n).obj_id for n in BUILTIN_PARTS] == list(range(1, 8))


@pytest.mark.parametrize("name", BUILTIN_PARTS)
def test_part_is_a_watertight_volume_in_its_object_frame(name: str) -> None:
    model = builtin_part(name)
    assert model.mesh.is_watertight and model.mesh.is_volume
    assert model.metadata["watertight"] is True
    assert model.name == name and model.source == f"builtin:{name}"
    assert model.material in {"steel", "zinc", "brass", "aluminium", "painted", "plastic"}
    assert 1000.0 < model.density_kg_m3 < 10000.0
    # 1-10 cm, pickable by a parallel gripper
    assert 10 * MM <= model.extents_m.max() <= 100 * MM
    # origin at the bounding-box centre
    np.testing.assert_allclose(model.bounds_m[0], -model.bounds_m[1], atol=1e-9)
    assert model.volume_m3 > 0.0 and 0.001 < model.mass_kg < 1.0


@pytest.mark.parametrize("name", BUILTIN_PARTS)
def test_declared_symmetries_hold(name: str) -> None:
    model = builtin_part(name)
    n_discrete, n_continuous = EXPECTED_SYMMETRY_COUNTS[name]
    assert (len(model.symmetries_discrete), len(model.symmetries_continuous)) == (n_discrete, n_continuous)
    assert all(is_rigid(T) for T in model.symmetries_discrete)
    assert not any(np.allclose(T, np.eye(4)) for T in model.symmetries_discrete)  # identity not listed
    flat = np.round(np.stack([T.reshape(-1) for T in model.symmetries_discrete]), 9)
    assert len(np.unique(flat, axis=0)) == n_discrete  # no duplicates
    assert check_symmetries(model, tol_m=SYM_TOL_M, n_samples=N_SAMPLES) == []


@pytest.mark.parametrize("name", BUILTIN_PARTS)
def test_a_non_symmetry_is_rejected(name: str) -> None:
    model = builtin_part(name)
    T_wrong, least_error_m = NON_SYMMETRIES[name]
    assert symmetry_error_m(model.mesh, T_wrong, n_samples=N_SAMPLES) > least_error_m
    # declared, it is reported by the check, by index
    wrong = replace(model, symmetries_discrete=(*model.symmetries_discrete[:1], T_wrong))
    problems = check_symmetries(wrong, tol_m=SYM_TOL_M, n_samples=N_SAMPLES)
    assert len(problems) == 1 and "symmetries_discrete[1]" in problems[0] and name in problems[0]


def test_symmetry_error_is_seeded_and_exact_for_the_identity() -> None:
    mesh = builtin_part("hex_nut").mesh
    T = make_T(rotation_about(np.array([0.0, 0.0, 1.0]), 0.3))
    assert symmetry_error_m(mesh, T, n_samples=300, seed=4) == symmetry_error_m(mesh, T, n_samples=300, seed=4)
    assert symmetry_error_m(mesh, np.eye(4), n_samples=300) < 1e-12


def test_wrong_continuous_axis_and_non_rigid_transform_are_reported() -> None:
    pipe = builtin_part("pipe")
    tilted = replace(pipe, symmetries_discrete=(), symmetries_continuous=(ContinuousSymmetry((1.0, 0.0, 0.0)),))
    problems = check_symmetries(tilted, tol_m=SYM_TOL_M, n_samples=N_SAMPLES)
    assert len(problems) == 1 and "symmetries_continuous[0]" in problems[0]
    scaled = replace(pipe, symmetries_discrete=(np.diag([2.0, 1.0, 1.0, 1.0]),), symmetries_continuous=())
    assert "not a rigid 4x4 transform" in check_symmetries(scaled, tol_m=SYM_TOL_M)[0]
    with pytest.raises(ValueError, match="tol_m must be > 0"):
        check_symmetries(pipe, tol_m=0.0)


def test_hex_nut_iso_4032_m12() -> None:
    model = builtin_part("hex_nut")
    e = 18.0 * MM / np.cos(np.pi / 6)
    np.testing.assert_allclose(model.extents_m, [e, 18.0 * MM, 10.8 * MM], atol=0.1 * MM)  # corner on +x
    assert _through(model.mesh, 0.0, 0.0) and _through(model.mesh, 4.9 * MM, 0.0)  # D1 = 10.106 mm
    assert not _through(model.mesh, 5.2 * MM, 0.0)
    corners = model.mesh.vertices[np.linalg.norm(model.mesh.vertices[:, :2], axis=1) > e / 2 - 1e-6]
    assert np.abs(corners[:, 2]).max() < 10.8 * MM / 2 - 0.5 * MM  # both faces chamfered at the corners


def test_hex_bolt_iso_4017_m8x30() -> None:
    model = builtin_part("hex_bolt")
    assert model.extents_m[1] == pytest.approx(13.0 * MM, abs=0.1 * MM)  # across flats
    assert model.extents_m[2] == pytest.approx(35.3 * MM, abs=0.1 * MM)  # l + k
    v = model.mesh.vertices
    head = v[np.linalg.norm(v[:, :2], axis=1) > 4.0 * MM + 1e-6]
    assert np.ptp(head[:, 2]) == pytest.approx(5.3 * MM, abs=1e-6)  # k
    assert head[:, 2].max() == pytest.approx(model.bounds_m[1, 2])  # head on top (+z)
    shank = v[v[:, 2] < head[:, 2].min() - 1e-6]
    assert _max_radius(shank) == pytest.approx(4.0 * MM, abs=1e-6)  # d = 8 mm


def test_washer_iso_7089_size_12() -> None:
    model = builtin_part("washer")
    np.testing.assert_allclose(model.extents_m, [24.0 * MM, 24.0 * MM, 2.5 * MM], atol=0.05 * MM)
    assert _through(model.mesh, 6.4 * MM, 0.0) and not _through(model.mesh, 6.6 * MM, 0.0)  # d1 = 13


def test_pipe_en_10255_dn15() -> None:
    model = builtin_part("pipe")
    np.testing.assert_allclose(model.extents_m, [21.3 * MM, 21.3 * MM, 50.0 * MM], atol=0.05 * MM)
    assert _through(model.mesh, 8.0 * MM, 0.0) and not _through(model.mesh, 8.1 * MM, 0.0)  # 16.1 mm bore


def test_spur_gear_module_1_5_twenty_teeth() -> None:
    model = builtin_part("spur_gear")
    v = model.mesh.vertices
    assert _max_radius(v) == pytest.approx(16.5 * MM, abs=1e-6)  # tip diameter 33 mm
    outer = np.linalg.norm(v[:, :2], axis=1)
    assert outer[outer > 5 * MM].min() == pytest.approx(13.125 * MM, abs=1e-6)  # root diameter 26.25 mm
    assert model.extents_m[2] == pytest.approx(10.0 * MM)
    assert _through(model.mesh, 3.9 * MM, 0.0) and not _through(model.mesh, 4.1 * MM, 0.0)
    # 20 teeth: a ray at the tip radius hits only every 18 degrees
    hits = [not _through(model.mesh, 16.2 * MM * np.cos(a), 16.2 * MM * np.sin(a)) for a in np.radians([0, 9, 18])]
    assert hits == [True, False, True]


def test_flange_en_1092_1_dn15_pn16() -> None:
    model = builtin_part("flange")
    np.testing.assert_allclose(model.extents_m, [95.0 * MM, 95.0 * MM, 14.0 * MM], atol=0.05 * MM)
    assert _through(model.mesh, 10.9 * MM, 0.0) and not _through(model.mesh, 11.2 * MM, 0.0)  # bore 22 mm
    for angle in np.radians([45.0, 135.0, 225.0, 315.0]):  # 4 x 14 mm holes on the 65 mm bolt circle
        x, y = 32.5 * MM * np.cos(angle), 32.5 * MM * np.sin(angle)
        assert _through(model.mesh, x, y)
    assert not _through(model.mesh, 32.5 * MM, 0.0)


def test_l_bracket_dimensions() -> None:
    model = builtin_part("l_bracket")
    leg, t, width, r_in, hole = 40.0 * MM, 2.0 * MM, 20.0 * MM, 2.0 * MM, 6.6 * MM
    assert model.extents_m[0] == pytest.approx(2.0 * leg * np.cos(np.pi / 4), abs=1e-6)
    assert model.extents_m[1] == pytest.approx(width, abs=1e-9)
    r_out = r_in + t
    section = 2.0 * (leg - r_out) * t + np.pi / 4.0 * (r_out**2 - r_in**2)
    volume = section * width - 2.0 * np.pi * (hole / 2) ** 2 * t
    assert model.volume_m3 == pytest.approx(volume, rel=5e-3)


def test_builtin_part_is_cached() -> None:
    assert builtin_part("flange") is builtin_part("flange")


def test_unknown_name_lists_the_valid_ones() -> None:
    with pytest.raises(UnknownObjectError, match="unknown built-in part 'hex_nutt'; valid names: hex_nut, ") as info:
        builtin_part("hex_nutt")
    assert all(name in str(info.value) for name in BUILTIN_PARTS)
    assert isinstance(info.value, (SygridError, KeyError))


def test_models_info_entry_in_millimetres() -> None:
    nut = builtin_part("hex_nut").models_info_entry()
    assert nut["size_y"] == pytest.approx(18.0, abs=0.1) and nut["size_z"] == pytest.approx(10.8, abs=0.1)
    assert nut["min_z"] == pytest.approx(-5.4, abs=0.05)
    assert nut["diameter"] == pytest.approx(np.hypot(18.0 / np.cos(np.pi / 6), 10.8 - 2 * 1.06), abs=0.3)
    assert len(nut["symmetries_discrete"]) == 11 and all(len(T) == 16 for T in nut["symmetries_discrete"])
    washer = builtin_part("washer").models_info_entry()
    assert washer["symmetries_continuous"] == [{"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 0.0]}]
    json.dumps([builtin_part(n).models_info_entry() for n in BUILTIN_PARTS])  # plain JSON types


def test_models_are_object_models() -> None:
    assert all(isinstance(builtin_part(n), ObjectModel) for n in BUILTIN_PARTS)
