"""Loading a user's CAD mesh (PLY, OBJ, STL) into an ``ObjectModel``: units to metres, repair, checks.

Real CAD exports are messy, so the loader repairs what it safely can (duplicate vertices, degenerate and duplicate
faces, unreferenced vertices, inconsistent winding, small holes, tiny stray components) and refuses, with a
``MeshError`` naming the file and the problem, what it cannot (no file, unknown format, unparsable or empty mesh,
NaN/inf vertices, a size implausible for the declared unit). A mesh that stays open after repair is still accepted
(it renders fine) with a warning and ``metadata["watertight"] = False``; its volume, mass, inertia and collision
come from a repaired closed solid (``ObjectModel.solid``, made on first use).

The CAD frame is kept by default, because user-declared symmetries are given in it (in metres, after the unit
conversion); ``recenter=True`` moves the origin to the bounding-box centre and moves the symmetries with it.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np
import trimesh

from sygrid.errors import MeshError
from sygrid.objects.model import ContinuousSymmetry, ObjectModel
from sygrid.objects.symmetry import check_symmetries
from sygrid.transforms import invert, is_rigid, make_T

log = logging.getLogger(__name__)

SUPPORTED_EXTENSIONS: tuple[str, ...] = (".ply", ".obj", ".stl")
UNIT_SCALE_M: dict[str, float] = {"mm": 1e-3, "m": 1.0}

# A part a parallel gripper picks from a bin: its largest extent lies between these (metres).
PLAUSIBLE_EXTENT_M: tuple[float, float] = (1e-3, 2.0)

# Density per material when none is given. "zinc" and "painted" are finishes on steel.
MATERIAL_DENSITY_KG_M3: dict[str, float] = {
    "steel": 7850.0,
    "zinc": 7850.0,
    "brass": 8500.0,
    "aluminium": 2700.0,
    "painted": 7850.0,
    "plastic": 1200.0,
}

_MERGE_DIGITS_M = 8  # vertices closer than ~10 nm are one vertex
_DEGENERATE_HEIGHT_M = 1e-10  # faces thinner than this are dropped (zero-area, collapsed by the merge)
_STRAY_AREA_FRACTION = 0.01  # disconnected components with less than this share of the total area are dropped
SYMMETRY_TOL_REL = 0.01  # declared symmetries are checked to this fraction of the model diameter


def load_cad(
    path: str | Path,
    unit: Literal["mm", "m"],
    obj_id: int,
    name: str | None = None,
    material: str = "steel",
    symmetries_discrete: Sequence[np.ndarray] = (),
    symmetries_continuous: Sequence[ContinuousSymmetry] = (),
    recenter: bool = False,
    density_kg_m3: float | None = None,
    verify_symmetries: bool = True,
) -> ObjectModel:
    """Loads a PLY, OBJ or STL mesh as an ``ObjectModel`` in metres.

    Args:
        path: the mesh file.
        unit: the unit of the file's coordinates, ``"mm"`` or ``"m"``.
        obj_id: the BOP object id (>= 1).
        name: the model's name (optional; default: the file's stem).
        material: one of ``MATERIAL_DENSITY_KG_M3``'s keys (the renderer maps it to an appearance).
        symmetries_discrete: 4x4 ``T_obj_obj`` in the CAD frame, translations in metres (BOP convention).
        symmetries_continuous: axes in the CAD frame, offsets in metres.
        recenter: move the origin to the bounding-box centre (symmetries are moved with it); the pose of the new
            frame in the CAD frame is recorded in ``metadata["T_cad_obj"]``.
        density_kg_m3: overrides the material's density (optional).
        verify_symmetries: check each declared symmetry on the mesh and log a warning (recorded in
            ``metadata["symmetry_problems"]``) for one that moves the surface more than ``SYMMETRY_TOL_REL`` of the
            model diameter.

    Raises:
        MeshError: the file is missing, has an unsupported extension, cannot be parsed, holds no faces or
            non-finite vertices, has a size implausible for ``unit``, or an argument is invalid.
    """
    path = Path(path)
    _check_arguments(path, unit, obj_id, material)
    raw = _read_mesh(path)
    scale_m = UNIT_SCALE_M[unit]
    _check_extent(path, raw, unit, scale_m)
    mesh = trimesh.Trimesh(vertices=raw.vertices * scale_m, faces=raw.faces, process=False)
    repairs = _repair(path, mesh)
    watertight = bool(mesh.is_watertight)
    if not watertight:
        log.warning(
            "%s: the mesh is not watertight after repair (%d open edges): accepted for rendering; its volume, mass "
            "and collision come from a repaired solid, made on first use",
            path,
            _open_edge_count(mesh),
        )
    discrete = tuple(_as_symmetry_transform(path, i, T) for i, T in enumerate(symmetries_discrete))
    continuous = tuple(_as_continuous_symmetry(path, i, s) for i, s in enumerate(symmetries_continuous))
    metadata: dict = {"watertight": watertight, "file": str(path), "unit": unit, "repairs": repairs}
    if recenter:
        T_cad_obj = make_T(t=mesh.bounds.mean(axis=0))
        T_obj_cad = invert(T_cad_obj)
        mesh.apply_transform(T_obj_cad)
        discrete = tuple(T_obj_cad @ T @ T_cad_obj for T in discrete)
        continuous = tuple(
            ContinuousSymmetry(s.axis, tuple(float(v) for v in np.asarray(s.offset_m) + T_obj_cad[:3, 3]))
            for s in continuous
        )
        metadata["T_cad_obj"] = T_cad_obj.tolist()
    model = ObjectModel(
        obj_id=obj_id,
        name=name if name is not None else path.stem,
        mesh=mesh,
        symmetries_discrete=discrete,
        symmetries_continuous=continuous,
        material=material,
        source=f"file:{path}",
        density_kg_m3=float(density_kg_m3) if density_kg_m3 is not None else MATERIAL_DENSITY_KG_M3[material],
        metadata=metadata,
    )
    if verify_symmetries and model.is_symmetric:
        problems = check_symmetries(model, tol_m=SYMMETRY_TOL_REL * model.diameter_m)
        metadata["symmetry_problems"] = problems
        for problem in problems:
            log.warning("%s: declared symmetry does not hold: %s", path, problem)
    log.info(
        "loaded %s as obj_id %d %r: %d faces, extents %s mm, watertight=%s",
        path,
        obj_id,
        model.name,
        len(mesh.faces),
        np.round(model.extents_m * 1e3, 2).tolist(),
        watertight,
    )
    return model


def _check_arguments(path: Path, unit: str, obj_id: int, material: str) -> None:
    if unit not in UNIT_SCALE_M:
        raise MeshError(f"{path}: unit must be one of {sorted(UNIT_SCALE_M)}, got {unit!r}")
    if isinstance(obj_id, bool) or not isinstance(obj_id, (int, np.integer)) or obj_id < 1:
        raise MeshError(f"{path}: obj_id must be an integer >= 1, got {obj_id!r}")
    if material not in MATERIAL_DENSITY_KG_M3:
        raise MeshError(f"{path}: material must be one of {list(MATERIAL_DENSITY_KG_M3)}, got {material!r}")
    if path.suffix.lower() not in SUPPORTED_EXTENSIONS:
        raise MeshError(
            f"{path}: unsupported mesh format {path.suffix or '(no extension)'!r}; "
            f"supported: {', '.join(SUPPORTED_EXTENSIONS)}"
        )
    if not path.is_file():
        raise MeshError(f"{path}: mesh file not found")


def _read_mesh(path: Path) -> trimesh.Trimesh:
    """The file's vertices and faces, unprocessed (no merging, no repair)."""
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh's parsers raise many types (ValueError, KeyError, struct.error, ...)
        raise MeshError(f"{path}: could not parse the file as {path.suffix.lower()[1:].upper()}: {exc}") from exc
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshError(f"{path}: holds no triangle mesh (got {type(loaded).__name__})")
    vertices = np.asarray(loaded.vertices, dtype=float)
    faces = np.asarray(loaded.faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        raise MeshError(
            f"{path}: the mesh has no faces (an empty file, a point cloud, or not a valid "
            f"{path.suffix.lower()[1:].upper()} file)"
        )
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(f"{path}: faces index vertices outside 0..{len(vertices) - 1}")
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise MeshError(f"{path}: {int(bad.sum())} of {len(vertices)} vertices are NaN or infinite")
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)


def _check_extent(path: Path, mesh: trimesh.Trimesh, unit: str, scale_m: float) -> None:
    """Raises when the largest extent, read in ``unit``, is not a pickable part's size; suggests the other unit."""
    used = mesh.vertices[np.unique(mesh.faces)]
    extent_m = float((used.max(axis=0) - used.min(axis=0)).max()) * scale_m
    lo, hi = PLAUSIBLE_EXTENT_M
    if lo <= extent_m <= hi:
        return
    hint = ""
    other = "mm" if unit == "m" else "m"
    if lo <= extent_m / scale_m * UNIT_SCALE_M[other] <= hi:
        hint = f"; did you mean unit={other!r}?"
    raise MeshError(
        f"{path}: the mesh is {extent_m:.6g} m across with unit={unit!r}, outside the plausible range "
        f"{lo * 1e3:g} mm to {hi:g} m for a part{hint}"
    )


def _repair(path: Path, mesh: trimesh.Trimesh) -> dict[str, int]:
    """Cleans ``mesh`` in place; returns what was changed, by kind."""
    n_vertices, n_faces = len(mesh.vertices), len(mesh.faces)
    mesh.merge_vertices(merge_tex=True, merge_norm=True, digits_vertex=_MERGE_DIGITS_M)
    merged = n_vertices - len(mesh.vertices)
    keep = mesh.nondegenerate_faces(height=_DEGENERATE_HEIGHT_M)
    degenerate = int((~keep).sum())
    mesh.update_faces(keep)
    keep = mesh.unique_faces()
    duplicate = int((~keep).sum())
    mesh.update_faces(keep)
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise MeshError(f"{path}: all {n_faces} faces are degenerate (zero area)")
    stray = _drop_stray_components(path, mesh)
    holes_filled = 0
    if not mesh.is_watertight:
        n_before = len(mesh.faces)
        trimesh.repair.fill_holes(mesh)
        holes_filled = len(mesh.faces) - n_before
    mesh.fix_normals(multibody=True)
    repairs = {
        "merged_vertices": merged,
        "degenerate_faces": degenerate,
        "duplicate_faces": duplicate,
        "stray_components": stray,
        "hole_faces_added": holes_filled,
    }
    changed = {k: v for k, v in repairs.items() if v}
    if changed:
        log.info("%s: repaired %s", path, ", ".join(f"{k}={v}" for k, v in changed.items()))
    return repairs


def _drop_stray_components(path: Path, mesh: trimesh.Trimesh) -> int:
    """Removes disconnected components holding less than ``_STRAY_AREA_FRACTION`` of the area (never the
    largest one); returns how many were removed."""
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    n_components = int(labels.max()) + 1 if len(labels) else 0
    if n_components < 2:
        return 0
    area = np.bincount(labels, weights=mesh.area_faces, minlength=n_components)
    stray = area < _STRAY_AREA_FRACTION * area.sum()
    stray[np.argmax(area)] = False
    if not stray.any():
        return 0
    mesh.update_faces(~stray[labels])
    mesh.remove_unreferenced_vertices()
    log.warning(
        "%s: dropped %d of %d disconnected components, each under %g%% of the surface area (%.3g%% in all)",
        path,
        int(stray.sum()),
        n_components,
        100.0 * _STRAY_AREA_FRACTION,
        100.0 * area[stray].sum() / area.sum(),
    )
    return int(stray.sum())


def _open_edge_count(mesh: trimesh.Trimesh) -> int:
    return len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))


def _as_symmetry_transform(path: Path, i: int, T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if T.shape == (16,):
        T = T.reshape(4, 4)
    if not is_rigid(T):
        raise MeshError(
            f"{path}: symmetries_discrete[{i}] must be a rigid 4x4 transform (orthonormal rotation, det +1, "
            f"last row 0 0 0 1), got {T.tolist()}"
        )
    return T


def _as_continuous_symmetry(path: Path, i: int, sym: ContinuousSymmetry) -> ContinuousSymmetry:
    axis = np.asarray(sym.axis, dtype=float)
    offset = np.asarray(sym.offset_m, dtype=float)
    norm = float(np.linalg.norm(axis)) if axis.shape == (3,) else 0.0
    if not (np.isfinite(norm) and norm > 1e-9) or offset.shape != (3,) or not np.isfinite(offset).all():
        raise MeshError(
            f"{path}: symmetries_continuous[{i}] needs a non-zero finite 3-vector axis and a finite 3-vector "
            f"offset_m, got axis={sym.axis}, offset_m={sym.offset_m}"
        )
    return ContinuousSymmetry(
        tuple(float(v) for v in axis / norm),  # type: ignore[arg-type]
        tuple(float(v) for v in offset),  # type: ignore[arg-type]
    )
