"""Built-in procedural industrial parts with their true (standard) dimensions, symmetries and materials.

Every part is built from code (shapely profiles extruded by trimesh, manifold3d booleans), in metres, watertight,
in a meaningful object frame: origin on the main symmetry axis at the bounding-box centre, z along that axis.

Tessellation respects each part's symmetry group: every circle is a polygon whose vertex angles are a multiple of
the discrete symmetry order and symmetric about the x axis, so each declared ``symmetries_discrete`` transform maps
the mesh exactly onto itself; parts with a continuous symmetry use fine circles (error below a micrometre).

Symmetries follow the BOP convention (``sygrid.objects.model``): the identity is not listed; a part with a
continuous axis lists only the discrete transforms that are not rotations about that axis.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache

import numpy as np
import shapely.affinity
import trimesh
from shapely.geometry import Polygon

from sygrid.errors import MeshError, UnknownObjectError
from sygrid.objects.model import ContinuousSymmetry, ObjectModel
from sygrid.transforms import make_T, rotation_about

log = logging.getLogger(__name__)

MM = 1e-3  # metres per millimetre: standards tabulate millimetres, the project works in metres

DENSITY_STEEL_KG_M3 = 7850.0
DENSITY_BRASS_KG_M3 = 8500.0  # CuZn39Pb3 (free-cutting brass), 8.47 g/cm3

# Circle segment counts. Each is a multiple of the discrete symmetry order of the part that uses it.
_SEGMENTS_FINE = 192  # parts with a continuous axis: r * (1 - cos(pi / 192)) < 2 um for r < 15 mm
_SEGMENTS_HOLE = 48  # small holes (multiple of 2, 4, 6, 12)

_Z_AXIS = (0.0, 0.0, 1.0)


# ----------------------------------------------------------------------------------------------- symmetry helpers
def _rot_z(angle_rad: float) -> np.ndarray:
    return make_T(rotation_about(np.array(_Z_AXIS), angle_rad))


def _flip_x() -> np.ndarray:
    """180 degrees about x: turns a part upside down, (x, y, z) -> (x, -y, -z)."""
    return np.diag([1.0, -1.0, -1.0, 1.0])


def _cyclic_z(order: int, with_flip: bool) -> tuple[np.ndarray, ...]:
    """The non-identity elements of C_n (n-fold about z), or of D_n (C_n composed with the flip about x)."""
    rotations = [_rot_z(2.0 * np.pi * k / order) for k in range(order)]
    group = rotations + ([_flip_x() @ R for R in rotations] if with_flip else [])
    return tuple(group[1:])


# --------------------------------------------------------------------------------------------- geometry helpers
def _circle_xy(radius: float, segments: int, centre: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """(segments, 2) polygon vertices at angles 2*pi*k/segments: symmetric about the x axis through ``centre``."""
    theta = 2.0 * np.pi * np.arange(segments) / segments
    return np.column_stack((centre[0] + radius * np.cos(theta), centre[1] + radius * np.sin(theta)))


def _regular_polygon_xy(circumradius: float, sides: int) -> np.ndarray:
    """(sides, 2) vertices of a regular polygon with a corner on +x."""
    return _circle_xy(circumradius, sides)


def _extrude(polygon: Polygon, height: float) -> trimesh.Trimesh:
    """Extrudes an xy profile along z, centred on z = 0."""
    return trimesh.creation.extrude_polygon(polygon, height, mid_plane=True)


def _revolve(profile_rz: np.ndarray, sections: int) -> trimesh.Trimesh:
    """Revolves a closed (r, z) profile about z; section vertices at angles 2*pi*k/sections, starting on +x."""
    mesh = trimesh.creation.revolve(np.asarray(profile_rz, dtype=float), sections=sections)
    mesh.merge_vertices()
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def _chamfer_solid(
    r_face: float,
    z_bottom: float,
    z_top: float,
    r_max: float,
    angle_rad: float,
    sections: int,
    bottom: bool = True,
    top: bool = True,
) -> trimesh.Trimesh:
    """Body of revolution that, intersected with a prism, chamfers its outer edges: a cone leaving each chamfered
    face at ``r_face`` and rising at ``angle_rad`` from the face plane, clipped to the cylinder ``r_max``."""
    dz = (r_max - r_face) * np.tan(angle_rad)
    lo = (
        [(0.0, z_bottom), (r_face, z_bottom), (r_max, z_bottom + dz)]
        if bottom
        else [(0.0, z_bottom), (r_max, z_bottom)]
    )
    hi = [(r_max, z_top - dz), (r_face, z_top), (0.0, z_top)] if top else [(r_max, z_top), (0.0, z_top)]
    return _revolve(np.array(lo + hi), sections)


def _boolean(op: Callable, meshes: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    return op(meshes, engine="manifold")


def _centre_z(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Moves the mesh along z so that its bounding box is centred on z = 0 (x, y stay on the symmetry axis)."""
    z_mid = 0.5 * (mesh.bounds[0, 2] + mesh.bounds[1, 2])
    mesh.apply_translation((0.0, 0.0, -z_mid))
    return mesh


# ------------------------------------------------------------------------------------------------------ the parts
@dataclass(frozen=True)
class _Part:
    """What a builder returns: the mesh in metres and the part's annotations."""

    mesh: trimesh.Trimesh
    symmetries_discrete: tuple[np.ndarray, ...]
    symmetries_continuous: tuple[ContinuousSymmetry, ...]
    material: str
    density_kg_m3: float
    dimensions_mm: dict[str, float]
    standard: str


def _hex_nut() -> _Part:
    # ISO 4032 hexagon nut, style 1, M12: s = 18 mm across flats, m = 10.8 mm height (max), e = s / cos(30 deg)
    # across corners (20.78 mm; ISO allows down to e_min = 20.03 mm for rounded corners). Both faces chamfered at
    # 30 degrees down to a circle of 0.95 s (inside ISO's bearing-face diameter range d_w = 16.6 mm .. s).
    # The thread is not modelled: the hole is the thread's minor diameter D1 = 12 - 1.0825 * 1.75 = 10.106 mm.
    s, m, d1 = 18.0 * MM, 10.8 * MM, 10.106 * MM
    e = s / np.cos(np.pi / 6)
    profile = Polygon(_regular_polygon_xy(e / 2, 6), holes=[_circle_xy(d1 / 2, _SEGMENTS_HOLE)[::-1]])
    prism = _extrude(profile, m)
    chamfer = _chamfer_solid(0.95 * s / 2, -m / 2, m / 2, e / 2 + 0.5 * MM, np.radians(30.0), _SEGMENTS_HOLE)
    mesh = _boolean(trimesh.boolean.intersection, [prism, chamfer])
    return _Part(
        mesh=_centre_z(mesh),
        symmetries_discrete=_cyclic_z(6, with_flip=True),  # D6: 12 transforms with the identity
        symmetries_continuous=(),
        material="zinc",  # zinc-plated steel
        density_kg_m3=DENSITY_STEEL_KG_M3,
        dimensions_mm={"s": 18.0, "m": 10.8, "e": float(e / MM), "D1": 10.106},
        standard="ISO 4032 M12",
    )


def _hex_bolt() -> _Part:
    # ISO 4017 hexagon head screw (fully threaded), M8 x 30: s = 13 mm, k = 5.3 mm head height, d = 8 mm,
    # l = 30 mm under the head. Thread not modelled (shank at the nominal diameter), end chamfered 45 degrees to the
    # minor diameter (d - 1.0825 P, P = 1.25 mm), head top chamfered at 30 degrees down to 0.95 s.
    s, k, d, length = 13.0 * MM, 5.3 * MM, 8.0 * MM, 30.0 * MM
    e = s / np.cos(np.pi / 6)
    end_chamfer = 0.5 * (d - (d - 1.0825 * 1.25 * MM))
    head = _extrude(Polygon(_regular_polygon_xy(e / 2, 6)), k)
    head.apply_translation((0.0, 0.0, k / 2))  # head from z = 0 (bearing face) to z = k
    chamfer = _chamfer_solid(0.95 * s / 2, 0.0, k, e / 2 + 0.5 * MM, np.radians(30.0), _SEGMENTS_HOLE, bottom=False)
    head = _boolean(trimesh.boolean.intersection, [head, chamfer])
    overlap = 0.5 * MM  # the shank reaches into the head, so the union has no coplanar faces
    shank = _revolve(
        np.array(
            [
                (0.0, -length),
                (d / 2 - end_chamfer, -length),
                (d / 2, -length + end_chamfer),
                (d / 2, overlap),
                (0.0, overlap),
            ]
        ),
        _SEGMENTS_HOLE,
    )
    mesh = _boolean(trimesh.boolean.union, [head, shank])
    return _Part(
        mesh=_centre_z(mesh),
        symmetries_discrete=_cyclic_z(6, with_flip=False),  # C6: the head breaks the flip
        symmetries_continuous=(),
        material="steel",
        density_kg_m3=DENSITY_STEEL_KG_M3,
        dimensions_mm={"s": 13.0, "k": 5.3, "d": 8.0, "l": 30.0, "e": float(e / MM)},
        standard="ISO 4017 M8x30",
    )


def _washer() -> _Part:
    # ISO 7089 plain washer, normal series, size 12: d1 = 13 mm, d2 = 24 mm, h = 2.5 mm.
    d1, d2, h = 13.0 * MM, 24.0 * MM, 2.5 * MM
    profile = Polygon(_circle_xy(d2 / 2, _SEGMENTS_FINE), holes=[_circle_xy(d1 / 2, _SEGMENTS_FINE)[::-1]])
    return _Part(
        mesh=_extrude(profile, h),
        symmetries_discrete=(_flip_x(),),
        symmetries_continuous=(ContinuousSymmetry(_Z_AXIS),),
        material="zinc",
        density_kg_m3=DENSITY_STEEL_KG_M3,
        dimensions_mm={"d1": 13.0, "d2": 24.0, "h": 2.5},
        standard="ISO 7089 size 12",
    )


def _l_bracket() -> _Part:
    # Sheet-metal angle bracket (no dimensional standard): two equal legs 40 mm (outer), width 20 mm, sheet 2 mm,
    # inside bend radius = sheet thickness, one 6.6 mm hole per leg (ISO 273 medium clearance hole for M6) on the
    # leg's centre line, 24 mm from the outer face of the other leg.
    # Built with the legs along +x and +y ("L frame"), then turned so that z is its one symmetry axis: the
    # 180-degree rotation about the bend's bisector, which swaps the legs. In the object frame the bracket is a "V"
    # opening towards +z, the sheet width along y.
    leg, width, t, d_hole, hole_at = 40.0 * MM, 20.0 * MM, 2.0 * MM, 6.6 * MM, 24.0 * MM
    r_in, r_out = t, 2.0 * t
    bend = 12  # arc segments per bend, the vertex set is symmetric about the bisector
    outer = [(r_out + r_out * np.cos(a), r_out + r_out * np.sin(a)) for a in np.linspace(np.pi, 1.5 * np.pi, bend + 1)]
    inner = [(r_out + r_in * np.cos(a), r_out + r_in * np.sin(a)) for a in np.linspace(1.5 * np.pi, np.pi, bend + 1)]
    profile = Polygon([(leg, 0.0), (leg, t), *inner, (t, leg), (0.0, leg), *outer])
    plate = trimesh.creation.extrude_polygon(profile, width)  # z in [0, width]
    # Leg symmetry in the L frame: (x, y, z) -> (y, x, width - z), a proper 180-degree rotation.
    T_swap = np.array([[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, width], [0.0, 0.0, 0.0, 1.0]])
    hole_a = trimesh.creation.cylinder(
        d_hole / 2,
        3.0 * t,
        sections=_SEGMENTS_HOLE,
        transform=make_T(rotation_about(np.array([1.0, 0.0, 0.0]), np.pi / 2), (hole_at, t / 2, width / 2)),
    )
    hole_b = hole_a.copy().apply_transform(T_swap)  # the exact image, so the swap maps the mesh onto itself
    mesh = _boolean(trimesh.boolean.difference, [plate, hole_a, hole_b])
    # Object frame: z along the bisector (1, 1, 0)/sqrt(2), y along the sheet width, x = y cross z.
    c = 1.0 / np.sqrt(2.0)
    R_obj_L = np.array([[-c, c, 0.0], [0.0, 0.0, 1.0], [c, c, 0.0]])
    mesh.apply_transform(make_T(R_obj_L, -R_obj_L @ np.array([0.0, 0.0, width / 2])))
    return _Part(
        mesh=_centre_z(mesh),
        symmetries_discrete=(np.diag([-1.0, -1.0, 1.0, 1.0]),),  # 180 degrees about z: swaps the legs
        symmetries_continuous=(),
        material="painted",
        density_kg_m3=DENSITY_STEEL_KG_M3,
        dimensions_mm={"leg": 40.0, "width": 20.0, "t": 2.0, "hole_d": 6.6, "hole_at": 24.0, "r_in": 2.0},
        standard="ISO 273 (hole)",
    )


def _pipe() -> _Part:
    # EN 10255 (ISO 65) medium series steel tube, DN 15 (R 1/2"): outside diameter 21.3 mm, wall 2.6 mm;
    # a 50 mm cut length.
    d_out, wall, length = 21.3 * MM, 2.6 * MM, 50.0 * MM
    d_in = d_out - 2.0 * wall
    profile = Polygon(_circle_xy(d_out / 2, _SEGMENTS_FINE), holes=[_circle_xy(d_in / 2, _SEGMENTS_FINE)[::-1]])
    return _Part(
        mesh=_extrude(profile, length),
        symmetries_discrete=(_flip_x(),),
        symmetries_continuous=(ContinuousSymmetry(_Z_AXIS),),
        material="steel",
        density_kg_m3=DENSITY_STEEL_KG_M3,
        dimensions_mm={"d_out": 21.3, "wall": 2.6, "d_in": float(d_in / MM), "length": 50.0},
        standard="EN 10255 medium DN 15",
    )


def _involute(angle_rad: np.ndarray) -> np.ndarray:
    return np.tan(angle_rad) - angle_rad


def _gear_outline(module: float, teeth: int, pressure_angle_rad: float, flank_points: int = 8) -> np.ndarray:
    """(n, 2) outline of an involute spur gear (ISO 53 basic rack: addendum 1 m, dedendum 1.25 m), tooth 0 centred
    on +x and every tooth symmetric about its centre line. Flanks run radially below the base circle; no fillet."""
    r_pitch = module * teeth / 2.0
    r_base = r_pitch * np.cos(pressure_angle_rad)
    r_tip, r_root = r_pitch + module, r_pitch - 1.25 * module
    # Half the tooth's angular thickness at radius r: pi / (2 z) at the pitch circle, then along the involute.
    radii = np.linspace(max(r_base, r_root), r_tip, flank_points)
    half = np.pi / (2 * teeth) + _involute(pressure_angle_rad) - _involute(np.arccos(np.minimum(r_base / radii, 1.0)))
    if half[-1] <= 0.0:
        raise ValueError(f"gear with module {module} m and {teeth} teeth has pointed teeth")
    if r_root < r_base:  # radial flank from the root circle to the base circle
        radii, half = np.concatenate(([r_root], radii)), np.concatenate(([half[0]], half))
    pitch = 2.0 * np.pi / teeth
    root_gap = np.linspace(half[0], pitch - half[0], 6)[1:-1]  # root circle between tooth 0 and tooth 1
    tooth = np.concatenate(
        (
            np.column_stack((radii, -half)),  # leading flank, root to tip
            np.column_stack((radii[::-1], half[::-1])),  # trailing flank, tip to root
            np.column_stack((np.full(root_gap.shape, r_root), root_gap)),
        )
    )
    polar = np.concatenate([tooth + np.array([0.0, k * pitch]) for k in range(teeth)])
    return np.column_stack((polar[:, 0] * np.cos(polar[:, 1]), polar[:, 0] * np.sin(polar[:, 1])))


def _spur_gear() -> _Part:
    # Involute spur gear, ISO 53 basic rack (20 degree pressure angle), ISO 54 module 1.5, 20 teeth: pitch diameter
    # 30 mm, tip diameter m (z + 2) = 33 mm, root diameter m (z - 2.5) = 26.25 mm; face width 10 mm, 8 mm bore
    # (no keyway, which would break the 20-fold symmetry). Bore segments: 60, a multiple of the 20 teeth.
    module, teeth, face, bore = 1.5 * MM, 20, 10.0 * MM, 8.0 * MM
    outline = _gear_outline(module, teeth, np.radians(20.0))
    profile = Polygon(outline, holes=[_circle_xy(bore / 2, 3 * teeth)[::-1]])
    return _Part(
        mesh=_extrude(profile, face),
        symmetries_discrete=_cyclic_z(teeth, with_flip=True),  # D20: 40 transforms with the identity
        symmetries_continuous=(),
        material="brass",
        density_kg_m3=DENSITY_BRASS_KG_M3,
        dimensions_mm={
            "module": 1.5,
            "teeth": 20,
            "d_pitch": 30.0,
            "d_tip": 33.0,
            "d_root": 26.25,
            "face_width": 10.0,
            "bore": 8.0,
        },
        standard="ISO 53 / ISO 54 m1.5 z20",
    )


def _flange() -> _Part:
    # EN 1092-1 type 01 (plate flange for welding), DN 15, PN 16: outside diameter D = 95 mm, bolt circle K = 65 mm,
    # 4 bolt holes L = 14 mm (M12), thickness C1 = 14 mm, bore B1 = 22 mm. Holes straddle the centre lines (45 deg).
    d_out, k_circle, n_holes, d_hole, thickness, bore = 95.0 * MM, 65.0 * MM, 4, 14.0 * MM, 14.0 * MM, 22.0 * MM
    hole = Polygon(_circle_xy(d_hole / 2, _SEGMENTS_HOLE, centre=(k_circle / 2, 0.0)))  # symmetric about +x
    holes = [
        np.asarray(shapely.affinity.rotate(hole, 45.0 + 360.0 * i / n_holes, origin=(0, 0)).exterior.coords)[:-1]
        for i in range(n_holes)
    ]
    profile = Polygon(
        _circle_xy(d_out / 2, _SEGMENTS_FINE),
        holes=[_circle_xy(bore / 2, _SEGMENTS_FINE)[::-1], *[h[::-1] for h in holes]],
    )
    return _Part(
        mesh=_extrude(profile, thickness),
        symmetries_discrete=_cyclic_z(n_holes, with_flip=True),  # D4: 8 transforms with the identity
        symmetries_continuous=(),
        material="painted",
        density_kg_m3=DENSITY_STEEL_KG_M3,
        dimensions_mm={"D": 95.0, "K": 65.0, "L": 14.0, "holes": 4, "C1": 14.0, "B1": 22.0},
        standard="EN 1092-1 type 01 DN 15 PN 16",
    )


# name -> (BOP obj_id, builder); ids are fixed: datasets written with them must stay readable.
_BUILDERS: dict[str, tuple[int, Callable[[], _Part]]] = {
    "hex_nut": (1, _hex_nut),
    "hex_bolt": (2, _hex_bolt),
    "washer": (3, _washer),
    "l_bracket": (4, _l_bracket),
    "pipe": (5, _pipe),
    "spur_gear": (6, _spur_gear),
    "flange": (7, _flange),
}

BUILTIN_PARTS: tuple[str, ...] = tuple(_BUILDERS)


def builtin_part(name: str) -> ObjectModel:
    """The built-in part ``name`` (one of ``BUILTIN_PARTS``), built once and cached.

    The same name returns the same object: treat its mesh as read-only (``model.mesh.copy()`` before editing).

    Raises:
        UnknownObjectError: ``name`` is not a built-in part; the message lists the valid names.
    """
    if name not in _BUILDERS:
        raise UnknownObjectError(f"unknown built-in part {name!r}; valid names: {', '.join(BUILTIN_PARTS)}")
    return _build(name)


@cache
def _build(name: str) -> ObjectModel:
    obj_id, builder = _BUILDERS[name]
    part = builder()
    mesh = part.mesh
    mesh.fix_normals()
    if not (mesh.is_watertight and mesh.is_volume):
        raise MeshError(f"builtin:{name}: the generated mesh is not a watertight volume (a bug in {__name__})")
    log.debug("built %s: %d faces, extents %s m", name, len(mesh.faces), np.round(mesh.extents, 5))
    return ObjectModel(
        obj_id=obj_id,
        name=name,
        mesh=mesh,
        symmetries_discrete=part.symmetries_discrete,
        symmetries_continuous=part.symmetries_continuous,
        material=part.material,
        source=f"builtin:{name}",
        density_kg_m3=part.density_kg_m3,
        metadata={"watertight": True, "standard": part.standard, "dimensions_mm": dict(part.dimensions_mm)},
    )
