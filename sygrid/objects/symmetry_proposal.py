"""Symmetry proposals: the rigid symmetries of a part's mesh, found from its geometry, verified with the existing
check (``sygrid.objects.symmetry.check_symmetries``), and returned in the model's object frame (BOP convention).

Every rigid symmetry of a surface maps its area centroid onto itself and commutes with its area second-moment
tensor, so each rotation axis passes through the centroid, and:

1. Candidate axes: the three principal axes of the surface's second moment. Where two principal moments are equal
   (within ``DEGENERATE_REL`` of the largest), the third axis may carry an n-fold or a continuous symmetry and the
   2-fold axes ("flips") may lie anywhere in the plane of the other two: their angles are searched (angles that
   pair up the outermost vertices first, then a grid). Where all three are equal (a cube-like part), axes are
   searched among the convex hull's face normals and vertex and edge-midpoint directions.
2. On each axis: a continuous symmetry (tested at the check's seven angles), else the largest order
   ``n <= max_order`` whose rotation by 360/n degrees holds. A principal axis whose perpendicular moments differ
   can only be 2-fold.
3. The rotations found generate a group (closed under composition); its elements other than the identity are the
   proposed ``symmetries_discrete``. With a continuous axis, only one flip perpendicular to it is listed (the
   others are that flip composed with rotations about the axis), as the built-in parts declare theirs.
4. The proposal is checked with ``check_symmetries`` at the same tolerance; a transform that fails is dropped.

"Holds" means: surface samples moved by the transform stay within ``tol_rel`` x the model diameter of the surface
(the loader's ``SYMMETRY_TOL_REL`` by default), so a proposal passes the check the CAD loader runs on declared
symmetries.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, replace

import numpy as np
import trimesh

from sygrid.objects.cad import SYMMETRY_TOL_REL
from sygrid.objects.model import ContinuousSymmetry, ObjectModel
from sygrid.objects.symmetry import CONTINUOUS_CHECK_ANGLES_RAD, SurfaceDistance, check_symmetries, sample_surface
from sygrid.transforms import make_T, rotation_about, transform_points

log = logging.getLogger(__name__)

DEGENERATE_REL = 0.02  # principal moments closer than this fraction of the largest are treated as equal
DEFAULT_MAX_ORDER = 64  # the largest n-fold order searched on an axis
CONTINUOUS = 0  # the order recorded for a continuous axis

_PROBE_POINTS = 512  # surface samples a candidate transform is tested on (the first few reject most candidates)
_FIRST_CHUNK = 48
_FLIP_GRID = 32  # grid angles tried per flip period when no vertex-derived angle holds
_ISOTROPIC_MAX_AXES = 120
_ISOTROPIC_ORDER = 6  # orders tried on the hull-derived axes of an isotropic part (polyhedral groups: <= 5)
_ISOTROPIC_FULL_ORDER_AXES = 6  # the largest hull facets' normals also get the full order range
_MAX_GROUP = 512
_SNAP = 1e-9  # rotation entries this close to -1, 0, 1 and translations below this [m] are snapped


@dataclass(frozen=True)
class SymmetryProposal:
    """Symmetries found on a mesh, in the model's object frame (translations in metres, BOP convention).

    ``axes``: each symmetry axis found, as (unit direction, order), order ``CONTINUOUS`` (0) for a continuous axis
    and 2 for a flip; ``tol_m``: the tolerance they hold to."""

    symmetries_discrete: tuple[np.ndarray, ...]
    symmetries_continuous: tuple[ContinuousSymmetry, ...]
    axes: tuple[tuple[tuple[float, float, float], int], ...]
    tol_m: float

    @property
    def is_symmetric(self) -> bool:
        return bool(self.symmetries_discrete or self.symmetries_continuous)

    def summary(self) -> str:
        """One line, e.g. ``11 discrete + 0 continuous: 6-fold about (0, 0, 1), 2-fold about (1, 0, 0)``."""
        if not self.is_symmetric:
            return "none"
        axes = ", ".join(
            f"{'continuous' if n == CONTINUOUS else f'{n}-fold'} about ({', '.join(f'{v:.3g}' for v in a)})"
            for a, n in self.axes
        )
        return f"{len(self.symmetries_discrete)} discrete + {len(self.symmetries_continuous)} continuous: {axes}"


def surface_moments(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The area centroid (3,), the principal moments (3,) ascending and the principal axes (3, 3) (columns) of the
    surface's second moment about its centroid (per unit area). Defined for open meshes too."""
    tri = np.asarray(mesh.triangles, dtype=float)
    area = np.asarray(mesh.area_faces, dtype=float)
    total = float(area.sum())
    if not total > 0.0:
        raise ValueError("the mesh has no surface area")
    s = tri.sum(axis=1)
    centroid = (area[:, None] * s).sum(axis=0) / (3.0 * total)
    # Exact per triangle: integral of x x^T over the triangle = area / 12 * (sum of v v^T + s s^T).
    second = np.einsum("f,fki,fkj->ij", area, tri, tri) + np.einsum("f,fi,fj->ij", area, s, s)
    cov = second / (12.0 * total) - np.outer(centroid, centroid)
    moments, axes = np.linalg.eigh(0.5 * (cov + cov.T))
    return centroid, moments, axes


def propose_symmetries(
    model: ObjectModel, tol_rel: float = SYMMETRY_TOL_REL, max_order: int = DEFAULT_MAX_ORDER, seed: int = 0
) -> SymmetryProposal:
    """The rigid symmetries of ``model.mesh`` (see the module docstring), each verified to ``tol_rel`` x the
    model's diameter. The same inputs give the same proposal. ``max_order >= 2``."""
    if not tol_rel > 0.0 or max_order < 2:
        raise ValueError(f"tol_rel must be > 0 and max_order >= 2, got {tol_rel}, {max_order}")
    tol_m = tol_rel * model.diameter_m
    centre, moments, principal = surface_moments(model.mesh)
    probe = _Probe(model.mesh, centre, tol_m, seed)
    near = np.abs(moments[:, None] - moments[None, :]) <= DEGENERATE_REL * float(moments.max())
    n_equal = int(near.sum()) - 3  # 0: all distinct, 2: one equal pair, 6: all equal

    axes: list[tuple[np.ndarray, int]] = []  # (unit axis, order >= 2 or CONTINUOUS)
    if n_equal == 0:
        axes = [(principal[:, k], 2) for k in range(3) if probe.holds(_rotation(principal[:, k], np.pi))]
    elif n_equal == 2:
        unique = int(np.argmin(near.sum(axis=1)))
        u = principal[:, unique]
        order = _axis_order(probe, u, max_order)
        if order != 1:
            axes.append((u, order))
        flip = _perpendicular_flip(probe, model.mesh, centre, u, order)
        if flip is not None:
            axes.append((flip, 2))
    else:
        axes = _isotropic_axes(probe, model.mesh, centre, principal, max_order)

    continuous = [(a, n) for a, n in axes if n == CONTINUOUS][:1]
    if continuous:  # the flips perpendicular to it; any other rotation is about the same axis
        u = continuous[0][0]
        axes = continuous + [(a, n) for a, n in axes if n == 2 and abs(float(a @ u)) < 1e-6][:1]
        rotations = [_rotation(a, np.pi) for a, _ in axes[1:]]
    else:
        rotations = _closure([_rotation(a, 2.0 * np.pi / n) for a, n in axes])
    discrete = tuple(_snap(make_T(R, centre - R @ centre)) for R in rotations)
    continuous_syms = tuple(
        ContinuousSymmetry(
            tuple(float(v) for v in _snap(_canonical(a))),  # type: ignore[arg-type]
            tuple(float(v) for v in _snap(centre - (centre @ a) * a)),  # type: ignore[arg-type]
        )
        for a, _ in continuous
    )
    discrete, continuous_syms = _verified(model, discrete, continuous_syms, tol_m)
    found = tuple((tuple(float(v) for v in _snap(_canonical(a))), n) for a, n in axes)
    return SymmetryProposal(discrete, continuous_syms, found, tol_m)  # type: ignore[arg-type]


def same_symmetries(
    a_discrete: tuple[np.ndarray, ...] | list[np.ndarray],
    a_continuous: tuple[ContinuousSymmetry, ...] | list[ContinuousSymmetry],
    b_discrete: tuple[np.ndarray, ...] | list[np.ndarray],
    b_continuous: tuple[ContinuousSymmetry, ...] | list[ContinuousSymmetry],
    tol_m: float,
    tol_rad: float = 1e-3,
) -> bool:
    """True when two symmetry declarations describe the same group (e.g. declared and proposed), whatever the
    order or the axes' signs: the same continuous axes (as lines; ``tol_m``, ``tol_rad``) and, with the identity
    added, every discrete transform of each equal to one of the other's, up to a rotation about the continuous
    axis where there is one."""
    if len(a_continuous) != len(b_continuous):
        return False
    for sa in a_continuous:
        if not any(_same_line(sa, sb, tol_m, tol_rad) for sb in b_continuous):
            return False
    axis = a_continuous[0] if a_continuous else None
    a_all = [np.eye(4), *[np.asarray(T, dtype=float) for T in a_discrete]]
    b_all = [np.eye(4), *[np.asarray(T, dtype=float) for T in b_discrete]]
    return all(any(_equivalent(A, B, axis, tol_m, tol_rad) for B in b_all) for A in a_all) and all(
        any(_equivalent(A, B, axis, tol_m, tol_rad) for A in a_all) for B in b_all
    )


def _same_line(a: ContinuousSymmetry, b: ContinuousSymmetry, tol_m: float, tol_rad: float) -> bool:
    ua, ub = np.asarray(a.axis, dtype=float), np.asarray(b.axis, dtype=float)
    if np.linalg.norm(np.cross(ua, ub)) > tol_rad:
        return False
    d = np.asarray(b.offset_m, dtype=float) - np.asarray(a.offset_m, dtype=float)
    return float(np.linalg.norm(d - (d @ ua) * ua)) <= tol_m


def _equivalent(A: np.ndarray, B: np.ndarray, axis: ContinuousSymmetry | None, tol_m: float, tol_rad: float) -> bool:
    """A equals B, or (with a continuous ``axis``) A equals B followed by a rotation about that axis."""
    D = A @ np.linalg.inv(B)
    R = D[:3, :3]
    if axis is None:
        return float(np.abs(R - np.eye(3)).max()) <= tol_rad and float(np.linalg.norm(D[:3, 3])) <= tol_m
    u, p = np.asarray(axis.axis, dtype=float), np.asarray(axis.offset_m, dtype=float)
    return float(np.linalg.norm(R @ u - u)) <= tol_rad and float(np.linalg.norm(R @ p + D[:3, 3] - p)) <= tol_m


class _Probe:
    """Tests whether a rotation about an axis through ``centre`` maps the surface onto itself within ``tol_m``."""

    def __init__(self, mesh: trimesh.Trimesh, centre: np.ndarray, tol_m: float, seed: int) -> None:
        self._distance = SurfaceDistance(mesh)
        self._points = sample_surface(mesh, _PROBE_POINTS, np.random.default_rng(seed))
        self._centre = centre
        self._tol_m = tol_m

    def holds(self, R: np.ndarray) -> bool:
        T = make_T(R, self._centre - R @ self._centre)
        for chunk in (self._points[:_FIRST_CHUNK], self._points[_FIRST_CHUNK:]):
            if float(np.max(self._distance(transform_points(T, chunk)))) > self._tol_m:
                return False
        return True


def _rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    return rotation_about(np.asarray(axis, dtype=float), angle_rad)


def _axis_order(probe: _Probe, u: np.ndarray, max_order: int) -> int:
    """``CONTINUOUS``, the largest n-fold order about ``u`` (up to ``max_order``), or 1 when none holds."""
    if all(probe.holds(_rotation(u, a)) for a in CONTINUOUS_CHECK_ANGLES_RAD):
        return CONTINUOUS
    for n in range(max_order, 1, -1):
        # A small step can hold within the tolerance without being a symmetry (it moves no point far): its
        # multiples nearest a quarter, a third and half a turn must hold too, as they do for a true n-fold axis.
        steps = dict.fromkeys((1, *(round(n * f) % n for f in (0.25, 1.0 / 3.0, 0.5))))
        if all(probe.holds(_rotation(u, 2.0 * np.pi * k / n)) for k in steps if k):
            return n
    return 1


def _perpendicular_flip(
    probe: _Probe, mesh: trimesh.Trimesh, centre: np.ndarray, u: np.ndarray, order: int
) -> np.ndarray | None:
    """A 2-fold axis through ``centre`` perpendicular to ``u`` (about which the part has ``order``), or None."""
    ref = np.eye(3)[int(np.argmin(np.abs(u)))]  # the object axis most perpendicular to u: tidy output
    e1 = ref - (ref @ u) * u
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    if order == CONTINUOUS:
        return e1 if probe.holds(_rotation(e1, np.pi)) else None
    period = np.pi / max(order, 1)  # flip axes repeat every 180/n degrees
    rel = np.asarray(mesh.vertices, dtype=float) - centre
    radial = rel - np.outer(rel @ u, u)
    radius = np.linalg.norm(radial, axis=1)
    outer = radial[radius >= radius.max() * (1.0 - 1e-3)][:256]
    phi = np.arctan2(outer @ e2, outer @ e1)
    paired = np.unique(np.round(np.mod((phi[0] + phi) / 2.0, period), 9)) if len(phi) else np.zeros(0)
    grid = np.arange(_FLIP_GRID) * period / _FLIP_GRID
    for theta in (*paired, *grid):
        axis = np.cos(theta) * e1 + np.sin(theta) * e2
        if probe.holds(_rotation(axis, np.pi)):
            return axis
    return None


def _isotropic_axes(
    probe: _Probe, mesh: trimesh.Trimesh, centre: np.ndarray, principal: np.ndarray, max_order: int
) -> list[tuple[np.ndarray, int]]:
    """Axes of a part whose three principal moments are equal, from its convex hull's directions."""
    hull = mesh.convex_hull
    facet_normals = np.asarray(hull.facets_normal).reshape(-1, 3)
    by_area = np.argsort(-np.asarray(hull.facets_area)) if len(facet_normals) else np.zeros(0, dtype=int)
    directions = [
        facet_normals[by_area],
        np.asarray(hull.face_normals),
        np.asarray(hull.vertices) - centre,
        np.asarray(hull.vertices)[hull.edges_unique].mean(axis=1) - centre,
        principal.T,
    ]
    candidates = _unique_directions(np.concatenate(directions))[:_ISOTROPIC_MAX_AXES]
    full = _unique_directions(facet_normals[by_area])[:_ISOTROPIC_FULL_ORDER_AXES]
    axes = []
    for u in candidates:
        wide = any(abs(float(u @ f)) > 1.0 - 1e-9 for f in full)
        order = _axis_order(probe, u, max_order if wide else min(max_order, _ISOTROPIC_ORDER))
        if order == CONTINUOUS:  # a continuous axis and its flips are the whole proposal (BOP lists no more)
            flip = _perpendicular_flip(probe, mesh, centre, u, CONTINUOUS)
            return [(u, CONTINUOUS)] + ([] if flip is None else [(flip, 2)])
        if order != 1:
            axes.append((u, order))
    return axes


def _unique_directions(vectors: np.ndarray, cos_tol: float = np.cos(np.radians(0.5))) -> list[np.ndarray]:
    """Unit directions, one per line through the origin (v and -v are the same axis), in input order."""
    out: list[np.ndarray] = []
    for v in vectors:
        norm = float(np.linalg.norm(v))
        if norm < 1e-12:
            continue
        v = v / norm
        if all(abs(float(v @ w)) < cos_tol for w in out):
            out.append(v)
    return out


def _closure(generators: list[np.ndarray]) -> list[np.ndarray]:
    """The non-identity elements of the rotation group the 3x3 ``generators`` generate (generators only, with a
    warning, when it would exceed ``_MAX_GROUP`` elements: the tolerance admits transforms that do not compose)."""
    group = [np.eye(3)]
    frontier = [np.eye(3)]
    while frontier:
        new = []
        for A in frontier:
            for G in generators:
                C = G @ A
                if not any(np.abs(C - B).max() < 1e-6 for B in group):
                    group.append(C)
                    new.append(C)
        if len(group) > _MAX_GROUP:
            log.warning(
                "symmetry proposal: the rotations found generate over %d transforms; kept the generators", _MAX_GROUP
            )
            return generators
        frontier = new
    return group[1:]


def _canonical(axis: np.ndarray) -> np.ndarray:
    """The axis with its largest component positive (an axis and its negation are the same line)."""
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    return axis if axis[int(np.argmax(np.abs(axis)))] > 0 else -axis


def _snap(values: np.ndarray) -> np.ndarray:
    """Entries within ``_SNAP`` of -1, 0 or 1 set to it (rotation entries, axes; translations in metres)."""
    values = np.array(values, dtype=float)
    rounded = np.round(values)
    close = (np.abs(values - rounded) < _SNAP) & (np.abs(rounded) <= 1.0)
    values[close] = rounded[close]
    return values + 0.0  # no negative zeros


def _verified(
    model: ObjectModel,
    discrete: tuple[np.ndarray, ...],
    continuous: tuple[ContinuousSymmetry, ...],
    tol_m: float,
) -> tuple[tuple[np.ndarray, ...], tuple[ContinuousSymmetry, ...]]:
    """The proposal as ``check_symmetries`` accepts it: the transforms it reports are dropped, with a warning."""
    problems = check_symmetries(replace(model, symmetries_discrete=discrete, symmetries_continuous=continuous), tol_m)
    if not problems:
        return discrete, continuous
    log.warning("%s: %d proposed symmetries failed the check and are dropped", model.name, len(problems))
    failed = {(m.group(1), int(m.group(2))) for p in problems for m in re.finditer(r"symmetries_(\w+)\[(\d+)\]", p)}
    return (
        tuple(T for i, T in enumerate(discrete) if ("discrete", i) not in failed),
        tuple(s for i, s in enumerate(continuous) if ("continuous", i) not in failed),
    )
