"""Symmetry proposals: found on the built-in parts as declared (as groups), rotating with a rotated copy, none on an
asymmetric part, every proposed transform accepted by the existing check."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import trimesh

from sygrid.objects import BUILTIN_PARTS, ContinuousSymmetry, ObjectModel, builtin_part, check_symmetries
from sygrid.objects.symmetry_proposal import CONTINUOUS, propose_symmetries, same_symmetries, surface_moments
from sygrid.transforms import invert, is_rigid, make_T, random_rotation

TOL_M = 1e-6  # proposals on exact meshes are exact up to floating point


def _model(mesh: trimesh.Trimesh, name: str = "part") -> ObjectModel:
    return ObjectModel(obj_id=1, name=name, mesh=mesh)


def _moved(model: ObjectModel, T: np.ndarray) -> ObjectModel:
    """A copy of ``model`` moved by ``T`` (its symmetries conjugated with it)."""
    mesh = model.mesh.copy()
    mesh.apply_transform(T)
    T_inv = invert(T)
    continuous = tuple(
        ContinuousSymmetry(tuple(T[:3, :3] @ s.axis), tuple(T[:3, :3] @ s.offset_m + T[:3, 3]))
        for s in model.symmetries_continuous
    )
    discrete = tuple(T @ S @ T_inv for S in model.symmetries_discrete)
    return replace(model, mesh=mesh, symmetries_discrete=discrete, symmetries_continuous=continuous)


@pytest.mark.parametrize("name", BUILTIN_PARTS)
def test_proposal_matches_the_declared_symmetries(name: str) -> None:
    model = builtin_part(name)
    proposal = propose_symmetries(model)
    assert same_symmetries(
        proposal.symmetries_discrete,
        proposal.symmetries_continuous,
        model.symmetries_discrete,
        model.symmetries_continuous,
        TOL_M,
    ), proposal.summary()
    assert len(proposal.symmetries_discrete) == len(model.symmetries_discrete)
    assert all(is_rigid(T) for T in proposal.symmetries_discrete)
    proposed = replace(
        model, symmetries_discrete=proposal.symmetries_discrete, symmetries_continuous=proposal.symmetries_continuous
    )
    assert check_symmetries(proposed, tol_m=1e-5, n_samples=500) == []


@pytest.mark.parametrize("name", ["hex_nut", "l_bracket", "pipe", "flange"])
def test_proposal_axes_rotate_with_the_part(name: str) -> None:
    rng = np.random.default_rng(sum(map(ord, name)))
    T = make_T(random_rotation(rng), rng.uniform(-0.02, 0.02, 3))
    moved = _moved(builtin_part(name), T)
    proposal = propose_symmetries(moved)
    assert same_symmetries(
        proposal.symmetries_discrete,
        proposal.symmetries_continuous,
        moved.symmetries_discrete,
        moved.symmetries_continuous,
        TOL_M,
    ), proposal.summary()
    main_axis = T[:3, 2]  # the part's z axis, where each of these has its main symmetry axis
    assert any(abs(float(np.dot(axis, main_axis))) > 1 - 1e-6 for axis, _ in proposal.axes)


def test_an_asymmetric_part_gets_none() -> None:
    a = trimesh.creation.box((0.03, 0.01, 0.01))
    b = trimesh.creation.box((0.01, 0.02, 0.01))
    b.apply_translation((0.01, 0.012, 0.0))
    c = trimesh.creation.box((0.005, 0.005, 0.015))
    c.apply_translation((-0.01, 0.0, 0.008))
    proposal = propose_symmetries(_model(trimesh.util.concatenate([a, b, c])))
    assert not proposal.is_symmetric and proposal.summary() == "none"


def test_a_cube_gets_the_octahedral_group() -> None:
    """All three principal moments equal: the axes come from the convex hull (4-, 3- and 2-fold)."""
    proposal = propose_symmetries(_model(trimesh.creation.box((0.02, 0.02, 0.02))))
    assert len(proposal.symmetries_discrete) == 23 and not proposal.symmetries_continuous
    assert sorted(n for _, n in proposal.axes) == [2] * 6 + [3] * 4 + [4] * 3


def test_an_open_tube_off_the_origin_gets_its_axis_through_its_centre() -> None:
    tube = trimesh.creation.annulus(0.004, 0.010, 0.030, sections=64)
    tube.update_faces(np.abs(tube.face_normals[:, 2]) < 0.5)  # no end faces: open
    tube.remove_unreferenced_vertices()
    tube.apply_translation((0.05, -0.02, 0.01))
    assert not tube.is_watertight
    proposal = propose_symmetries(_model(tube))
    assert [n for _, n in proposal.axes] == [CONTINUOUS, 2]
    (axis,) = proposal.symmetries_continuous
    np.testing.assert_allclose(axis.axis, (0.0, 0.0, 1.0), atol=1e-9)
    np.testing.assert_allclose(axis.offset_m, (0.05, -0.02, 0.0), atol=1e-9)
    (flip,) = proposal.symmetries_discrete
    np.testing.assert_allclose(flip @ np.array([0.05, -0.02, 0.01, 1.0]), [0.05, -0.02, 0.01, 1.0], atol=1e-9)


def test_surface_moments_are_those_of_a_box() -> None:
    centre, moments, axes = surface_moments(trimesh.creation.box((0.04, 0.02, 0.01)))
    np.testing.assert_allclose(centre, 0.0, atol=1e-12)
    assert moments[0] < moments[1] < moments[2]
    np.testing.assert_allclose(np.abs(axes[:, 2]), (1.0, 0.0, 0.0), atol=1e-9)  # the longest side: largest moment


def test_same_symmetries_tells_groups_apart() -> None:
    nut, pipe = builtin_part("hex_nut"), builtin_part("pipe")
    assert not same_symmetries(nut.symmetries_discrete[:5], (), nut.symmetries_discrete, (), TOL_M)
    shifted = ContinuousSymmetry((0.0, 0.0, 1.0), (0.001, 0.0, 0.0))
    assert not same_symmetries(
        pipe.symmetries_discrete, (shifted,), pipe.symmetries_discrete, pipe.symmetries_continuous, TOL_M
    )
    flipped_axis = ContinuousSymmetry((0.0, 0.0, -1.0), (0.0, 0.0, 0.007))  # same line
    flip_y = np.diag([-1.0, 1.0, -1.0, 1.0])  # the flip about x, composed with half a turn about z
    assert same_symmetries((flip_y,), (flipped_axis,), pipe.symmetries_discrete, pipe.symmetries_continuous, TOL_M)


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError, match="max_order"):
        propose_symmetries(builtin_part("washer"), max_order=1)
