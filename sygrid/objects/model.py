"""The object model shared by the whole stack: a mesh in metres with its id, name, symmetries and grasps.

Symmetries follow the BOP ``models_info.json`` convention: ``symmetries_discrete`` are 4x4 transforms
``T_obj_obj`` that map the model onto itself, ``symmetries_continuous`` are an axis and an offset (a point on the
axis) about which every rotation maps the model onto itself. Inside the project translations are in metres; the
BOP writer converts to millimetres at the file boundary (``models_info_entry``).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
import trimesh

from sygrid.transforms import make_T, rotation_about


@dataclass(frozen=True)
class ContinuousSymmetry:
    """Rotation symmetry about ``axis`` (unit 3-vector) through the point ``offset_m`` (object frame, metres)."""

    axis: tuple[float, float, float]
    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def transform(self, angle_rad: float) -> np.ndarray:
        """``T_obj_obj`` for a rotation of ``angle_rad`` about this axis."""
        R = rotation_about(np.asarray(self.axis), angle_rad)
        offset = np.asarray(self.offset_m)
        return make_T(R, offset - R @ offset)


@dataclass(frozen=True)
class GraspAnnotation:
    """A parallel-gripper grasp in the object frame.

    ``T_obj_grasp``: the grasp frame, z along the approach direction (pointing into the part), x along the line
    between the finger pads, origin midway between the pads. ``width_m``: the part's width between the pads.
    """

    T_obj_grasp: np.ndarray
    width_m: float
    score: float = 1.0


@dataclass(frozen=True, eq=False)
class ObjectModel:
    """A rigid part: triangle mesh in metres (object frame), BOP id, name and symmetry/grasp annotations.

    ``mesh`` is what is rendered; ``solid`` is the part's matter (the mesh itself when it is one closed volume,
    else a repaired closed solid: ``sygrid.objects.collision.solid``), which volume, mass, inertia and collision
    come from. A declared mass (``with_mass``) sets the density that gives it over that volume.
    """

    obj_id: int
    name: str
    mesh: trimesh.Trimesh
    symmetries_discrete: tuple[np.ndarray, ...] = ()
    symmetries_continuous: tuple[ContinuousSymmetry, ...] = ()
    grasps: tuple[GraspAnnotation, ...] = ()
    material: str = "steel"
    source: str = ""
    density_kg_m3: float = 7850.0
    metadata: dict = field(default_factory=dict)

    @cached_property
    def diameter_m(self) -> float:
        """Largest distance between two mesh points (BOP's model diameter), from the convex hull's vertices."""
        hull = self.mesh.convex_hull.vertices
        diffs = hull[:, None, :] - hull[None, :, :]
        return float(np.sqrt((diffs**2).sum(-1)).max())

    @cached_property
    def bounds_m(self) -> np.ndarray:
        """(2, 3) axis-aligned bounds in the object frame."""
        return np.asarray(self.mesh.bounds, dtype=float)

    @property
    def extents_m(self) -> np.ndarray:
        return self.bounds_m[1] - self.bounds_m[0]

    @cached_property
    def solid(self) -> trimesh.Trimesh:
        """The closed solid (metres, object frame) of the part's matter: ``mesh`` when it is one closed volume,
        else its repair with the default ``CollisionParams``, made on first use and kept in the collision cache."""
        from sygrid.objects.collision.solid import repaired_solid  # the repair is only loaded when needed

        return repaired_solid(self.mesh, self.content_hash, name=self.name).mesh

    @cached_property
    def volume_m3(self) -> float:
        """The volume of ``solid`` (m^3)."""
        return float(abs(self.solid.volume))

    @property
    def mass_kg(self) -> float:
        return self.volume_m3 * self.density_kg_m3

    @property
    def mass_source(self) -> str:
        """Where ``mass_kg`` comes from: ``"declared"`` (``with_mass``), ``"density x solid volume"`` (a closed
        mesh), or ``"density x repaired solid volume"`` (an open or multi-body mesh: ``solid``)."""
        from sygrid.objects.collision.solid import solid_method

        if "mass_declared_kg" in self.metadata:
            return "declared"
        return "density x solid volume" if solid_method(self.mesh) == "as-is" else "density x repaired solid volume"

    def with_mass(self, mass_kg: float) -> ObjectModel:
        """This model with a declared mass [kg] (> 0): its density becomes ``mass_kg / volume_m3``, so the mass,
        and the inertia computed from density and volume, match the declaration."""
        if not (np.isfinite(mass_kg) and mass_kg > 0.0):
            raise ValueError(f"mass_kg must be a finite number > 0, got {mass_kg}")
        return replace(
            self,
            density_kg_m3=float(mass_kg) / self.volume_m3,
            metadata={**self.metadata, "mass_declared_kg": float(mass_kg)},
        )

    @property
    def is_symmetric(self) -> bool:
        return bool(self.symmetries_discrete or self.symmetries_continuous)

    @cached_property
    def content_hash(self) -> str:
        """SHA-256 of the mesh geometry: the key for anything cached per mesh (e.g. convex decompositions)."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.mesh.vertices, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(self.mesh.faces, dtype=np.int64).tobytes())
        return h.hexdigest()

    def symmetry_transforms(self, continuous_steps: int = 36) -> np.ndarray:
        """(n, 4, 4) every symmetry transform, identity first; continuous ones sampled every 360/steps degrees.

        Discrete and continuous symmetries are combined the way the BOP toolkit does it
        (``misc.get_symmetry_transformations``): each discrete transform (and the identity) composed with each
        sampled rotation about each continuous axis.
        """
        discrete = [np.eye(4), *[np.asarray(T, dtype=float) for T in self.symmetries_discrete]]
        continuous = [np.eye(4)]
        for sym in self.symmetries_continuous:
            continuous += [sym.transform(2 * np.pi * k / continuous_steps) for k in range(1, continuous_steps)]
        return np.stack([Tc @ Td for Td in discrete for Tc in continuous])

    def models_info_entry(self) -> dict:
        """This model's entry of BOP ``models_info.json`` (millimetres, as the format demands)."""
        lo, size = self.bounds_m[0] * 1000.0, self.extents_m * 1000.0
        entry: dict = {
            "diameter": self.diameter_m * 1000.0,
            "min_x": lo[0], "min_y": lo[1], "min_z": lo[2],
            "size_x": size[0], "size_y": size[1], "size_z": size[2],
        }  # fmt: skip
        if self.symmetries_discrete:
            entry["symmetries_discrete"] = [_T_to_bop_mm(T) for T in self.symmetries_discrete]
        if self.symmetries_continuous:
            entry["symmetries_continuous"] = [
                {"axis": list(map(float, s.axis)), "offset": [float(v) * 1000.0 for v in s.offset_m]}
                for s in self.symmetries_continuous
            ]
        return {k: (float(v) if isinstance(v, (np.floating, float)) else v) for k, v in entry.items()}


def _T_to_bop_mm(T: np.ndarray) -> list[float]:
    T_mm = np.array(T, dtype=float)
    T_mm[:3, 3] *= 1000.0
    return [float(v) for v in T_mm.reshape(-1)]


def symmetries_from_models_info(
    entry: dict, where: str
) -> tuple[tuple[np.ndarray, ...], tuple[ContinuousSymmetry, ...]]:
    """The symmetries of a BOP ``models_info.json`` entry (millimetres) in metres: the inverse of
    ``ObjectModel.models_info_entry``. ``where`` names the file and entry in errors.

    Raises:
        ValueError: a discrete symmetry is not 16 numbers, or a continuous one lacks a 3-number axis/offset.
    """
    discrete = []
    for i, values in enumerate(entry.get("symmetries_discrete", [])):
        T = np.asarray(values, dtype=np.float64)
        if T.size != 16:
            raise ValueError(f"{where}.symmetries_discrete[{i}]: expected 16 numbers (a 4x4 row-major, mm)")
        T = T.reshape(4, 4).copy()
        T[:3, 3] /= 1000.0
        discrete.append(T)
    continuous = []
    for i, sym in enumerate(entry.get("symmetries_continuous", [])):
        try:
            axis = tuple(float(v) for v in sym["axis"])
            offset = tuple(float(v) / 1000.0 for v in sym.get("offset", (0.0, 0.0, 0.0)))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise ValueError(f"{where}.symmetries_continuous[{i}]: expected 'axis' and 'offset' (mm): {exc}") from None
        if len(axis) != 3 or len(offset) != 3:
            raise ValueError(f"{where}.symmetries_continuous[{i}]: 'axis' and 'offset' must be 3 numbers each")
        continuous.append(ContinuousSymmetry(axis, offset))  # type: ignore[arg-type]
    return tuple(discrete), tuple(continuous)
