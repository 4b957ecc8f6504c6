"""A part's repaired solid: the closed, manifold, single-volume mesh that collision decomposition, fidelity and
mass work on. Real CAD exports are often open (a sheet-metal part as its zero-thickness mid-surface, a revolved
wall without end caps), made of several bodies (touching, overlapping or apart) or thin-walled; the visual mesh is
kept for rendering, the solid stands in for the part's matter.

Three ways, the cheapest that applies (``solid_method``):

- ``as-is``: the mesh is already one closed volume (watertight, consistent winding, positive volume, one body):
  the solid is the mesh itself, unchanged (every built-in part).
- ``union``: closed bodies, several of them: their boolean union (manifold3d), exact; an inner shell (a void)
  is subtracted. Falls back to ``voxel`` when manifold3d refuses a body.
- ``voxel``: anything else (open or non-manifold). On a grid of pitch ``h`` tied to the part's size
  (``solid_pitch_m``): the surface is sampled; the region the surface encloses once openings narrower than
  ``2 * CollisionParams.solid_seal_m`` are sealed (a morphological closing) is the inside, and so is the gap
  between two surfaces facing each other closer than that (a wall given by its two faces, with open ends); a
  surface with no matter on either side (a sheet exported as its mid-surface) and a wall thinner than
  ``CollisionParams.solid_min_thickness_m`` are thickened about their middle to that thickness; the signed
  distance field is meshed as a manifold level set and simplified to within half a pitch. Near the surface the
  field's magnitude is the distance to surface samples, so the solid follows the surface to a fraction of the
  pitch, not to whole voxels. Openings wider than ``2 * solid_seal_m`` stay open: such a part is taken as a
  shell of walls (a box missing a face is a cup).

Units: metres in, metres out. The result is deterministic for a given mesh and parameters.
"""

from __future__ import annotations

import importlib.metadata
import logging
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

from sygrid.errors import MeshError
from sygrid.objects.collision.cache import load_solid, resolve_cache_dir, save_solid, solid_entry
from sygrid.objects.collision.params import CollisionParams

log = logging.getLogger(__name__)

SolidMethod = Literal["as-is", "union", "voxel"]
SOLID_VERSION = 1  # bump when the repair changes its output: it is part of every cache key of a repaired part

_MEMO_SIZE = 32  # repaired solids kept in memory per process (by cache key)
_SAMPLE_SPACING = 0.5  # surface samples per pitch: every surface point is within a quarter pitch of one
_BAND_CELLS = 3.0  # the field is refined with surface distances within this many cells of the surface
_MIN_THICKNESS_CELLS = 2.0  # thickened sheets are at least this many cells thick, whatever the minimum thickness
_SIDE_CELLS = 2.0  # the core on either side of a surface is looked up this many cells away from it
_SIMPLIFY_CELLS = 0.5  # the level set is simplified to within this many cells


@dataclass(frozen=True, eq=False)
class RepairedSolid:
    """The solid of a part: ``mesh`` (metres, closed, outward normals), how it was made, the grid pitch of a
    ``voxel`` repair (None otherwise) and the wall time of the repair when first computed."""

    mesh: trimesh.Trimesh
    method: SolidMethod
    pitch_m: float | None
    compute_s: float


def solid_method(mesh: trimesh.Trimesh) -> SolidMethod:
    """How ``mesh``'s solid is made (cheap: a topology check, no geometry is built)."""
    if not (mesh.is_watertight and mesh.is_winding_consistent):
        return "voxel"
    if mesh.body_count == 1 and mesh.volume > 0:
        return "as-is"
    return "union"


def solid_pitch_m(mesh: trimesh.Trimesh, params: CollisionParams) -> float:
    """The voxel repair's grid pitch (m): half the minimum thickness, coarser for a large part so that its longest
    side spans at most ``params.solid_max_cells`` cells."""
    return max(params.solid_min_thickness_m / 2.0, float(mesh.extents.max()) / params.solid_max_cells)


def solid_key(mesh: trimesh.Trimesh, params: CollisionParams) -> dict | None:
    """What ``mesh``'s repaired solid depends on besides the mesh (method, parameters, repair and library
    versions): part of the cache key of everything computed from the solid. None for an ``as-is`` mesh."""
    method = solid_method(mesh)
    if method == "as-is":
        return None
    try:
        manifold_version = importlib.metadata.version("manifold3d")
    except importlib.metadata.PackageNotFoundError:
        manifold_version = "unknown"
    return {"method": method, "version": SOLID_VERSION, "manifold3d": manifold_version, **params.solid_key_fields()}


_MEMO: OrderedDict[str, RepairedSolid] = OrderedDict()
_MEMO_LOCK = threading.Lock()


def repaired_solid(
    mesh: trimesh.Trimesh,
    content_hash: str,
    params: CollisionParams | None = None,
    cache_dir: Path | str | None = None,
    name: str = "mesh",
) -> RepairedSolid:
    """``make_solid`` through the disk cache (``cache_dir`` as in ``build_collision_model``) and an in-process
    memo; ``content_hash`` is the mesh's (``ObjectModel.content_hash``). An ``as-is`` mesh is returned at once.

    Raises:
        MeshError: the repair gave no volume.
    """
    params = CollisionParams() if params is None else params
    key_fields = solid_key(mesh, params)
    if key_fields is None:
        return RepairedSolid(mesh, "as-is", None, 0.0)
    stem, key = solid_entry(resolve_cache_dir(cache_dir), content_hash, key_fields)
    with _MEMO_LOCK:
        if key in _MEMO:
            _MEMO.move_to_end(key)
            return _MEMO[key]
    cached = load_solid(stem, key)
    if cached is not None:
        vertices, faces, meta = cached
        solid = RepairedSolid(
            trimesh.Trimesh(vertices, faces, process=False), meta["method"], meta["pitch_m"], float(meta["compute_s"])
        )
    else:
        solid = make_solid(mesh, params, name)
        meta = {"content_hash": content_hash, "solid": key_fields, "method": solid.method, "pitch_m": solid.pitch_m,
                "compute_s": solid.compute_s, "volume_m3": float(solid.mesh.volume)}  # fmt: skip
        save_solid(stem, key, solid.mesh.vertices, solid.mesh.faces, meta)
    with _MEMO_LOCK:
        _MEMO[key] = solid
        while len(_MEMO) > _MEMO_SIZE:
            _MEMO.popitem(last=False)
    return solid


def make_solid(mesh: trimesh.Trimesh, params: CollisionParams, name: str = "mesh") -> RepairedSolid:
    """``mesh``'s repaired solid (module docstring); ``name`` is for logs and errors.

    Raises:
        MeshError: the repair gave no volume (a mesh with no area).
    """
    method = solid_method(mesh)
    start = time.perf_counter()
    if method == "as-is":
        return RepairedSolid(mesh, method, None, 0.0)
    solid, pitch = None, None
    if method == "union":
        solid = _union_of_bodies(mesh, name)
    if solid is None:
        method = "voxel"
        pitch = solid_pitch_m(mesh, params)
        log.info("%s: making a solid of an open or non-manifold mesh on a %.2f mm grid", name, pitch * 1e3)
        solid = _voxel_solid(mesh, params, pitch, name)
    if not (solid.is_volume and solid.volume > 0):
        raise MeshError(f"{name}: the {method} repair gave no closed volume (is the mesh empty or flat?)")
    compute_s = time.perf_counter() - start
    with np.errstate(invalid="ignore", divide="ignore"):  # the hull of a flat sheet has no volume
        hull_m3 = float(mesh.convex_hull.volume)
    log.info(
        "%s: repaired solid by %s in %.1f s: %d faces, %.0f mm3 (convex hull %.0f mm3)",
        name, method, compute_s, len(solid.faces), solid.volume * 1e9, hull_m3 * 1e9,
    )  # fmt: skip
    return RepairedSolid(solid, method, pitch, compute_s)


def _union_of_bodies(mesh: trimesh.Trimesh, name: str) -> trimesh.Trimesh | None:
    """The union of ``mesh``'s closed bodies (inner shells subtracted), or None when manifold3d refuses one."""
    import manifold3d  # imported on use: only repairs need it

    outer, inner = [], []
    for body in mesh.split(only_watertight=False):
        try:
            solid = manifold3d.Manifold(_manifold_mesh(body.vertices, body.faces))
        except Exception as exc:  # manifold3d raises its own types for non-manifold input
            log.info("%s: a body is not manifold (%s): voxel repair instead of a union", name, exc)
            return None
        if solid.status() != manifold3d.Error.NoError:
            log.info("%s: a body is not manifold (%s): voxel repair instead of a union", name, solid.status())
            return None
        if body.volume >= 0:
            outer.append(solid)
        else:  # an inner shell: the void it bounds, as a positive solid, is subtracted
            inner.append(manifold3d.Manifold(_manifold_mesh(body.vertices, body.faces[:, ::-1])))
    if not outer:
        return None
    result = manifold3d.Manifold.batch_boolean(outer, manifold3d.OpType.Add)
    if inner:
        result = result - manifold3d.Manifold.batch_boolean(inner, manifold3d.OpType.Add)
    return _trimesh_of(result, scale=1.0, offset=np.zeros(3))


def _manifold_mesh(vertices: np.ndarray, faces: np.ndarray):
    import manifold3d

    return manifold3d.Mesh(
        vert_properties=np.ascontiguousarray(vertices, dtype=np.float32),
        tri_verts=np.ascontiguousarray(faces, dtype=np.uint32),
    )


def _trimesh_of(solid, scale: float, offset: np.ndarray) -> trimesh.Trimesh:
    out = solid.to_mesh64() if hasattr(solid, "to_mesh64") else solid.to_mesh()
    vertices = np.asarray(out.vert_properties, dtype=np.float64)[:, :3] * scale + offset
    return trimesh.Trimesh(vertices, np.asarray(out.tri_verts, dtype=np.int64), process=False)


# ---------------------------------------------------------------------------------------------- voxel repair


def surface_samples(mesh: trimesh.Trimesh, spacing_m: float) -> tuple[np.ndarray, np.ndarray]:
    """``(points, normals)``: points on every triangle on a grid of about ``spacing_m`` along its two edges from the
    first corner (corners and edges included), each with its triangle's unit normal. Deterministic."""
    tri = np.asarray(mesh.triangles, dtype=np.float64)
    normals = np.asarray(mesh.face_normals, dtype=np.float64)
    n1 = np.maximum(np.ceil(np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1) / spacing_m), 1).astype(int)
    n2 = np.maximum(np.ceil(np.linalg.norm(tri[:, 2] - tri[:, 0], axis=1) / spacing_m), 1).astype(int)
    points, point_normals = [tri.reshape(-1, 3)], [np.repeat(normals, 3, axis=0)]
    for a, b in np.unique(np.column_stack([n1, n2]), axis=0):
        sel = np.flatnonzero((n1 == a) & (n2 == b))
        i, j = np.meshgrid(np.arange(a + 1) / a, np.arange(b + 1) / b, indexing="ij")
        keep = i + j <= 1.0 + 1e-9
        u, v = i[keep], j[keep]  # barycentric weights of corners 1 and 2
        t = tri[sel]
        p = (
            t[:, None, 0]
            + u[None, :, None] * (t[:, None, 1] - t[:, None, 0])
            + v[None, :, None] * (t[:, None, 2] - t[:, None, 0])
        )
        points.append(p.reshape(-1, 3))
        point_normals.append(np.repeat(normals[sel], len(u), axis=0))
    return np.concatenate(points), np.concatenate(point_normals)


def _voxel_solid(mesh: trimesh.Trimesh, params: CollisionParams, h: float, name: str) -> trimesh.Trimesh:
    # a sheet thinner than 2 pitches could fall between the level set's grid points
    t_min, seal = max(params.solid_min_thickness_m, _MIN_THICKNESS_CELLS * h), params.solid_seal_m
    points, normals = surface_samples(mesh, _SAMPLE_SPACING * h)
    pad = int(np.ceil((seal + t_min) / h)) + 3
    origin = np.asarray(mesh.bounds[0]) - pad * h
    shape = tuple(int(v) for v in np.ceil(np.asarray(mesh.extents) / h).astype(int) + 2 * pad + 1)
    cell = np.floor((points - origin) / h).astype(np.int64)
    surface = np.zeros(shape, dtype=bool)
    surface[tuple(cell.T)] = True

    # inside: what the surface encloses once openings narrower than 2 * seal are closed (dilate, fill, erode)
    dist_surface = ndimage.distance_transform_edt(~surface) * h
    filled = ndimage.binary_fill_holes(dist_surface <= seal)
    closed = (ndimage.distance_transform_edt(filled) * h >= seal + h / 2) | surface
    core = closed & ~surface

    # each sample: is there matter in front of it, behind it, on both sides (an inner surface) or on neither (a
    # sheet)? Matter is the closed core a few cells away, or another surface within the sealed gap width.
    def core_at(p: np.ndarray) -> np.ndarray:
        return core[_cells(p, origin, h, shape)]

    # the gaps are probed from one sample per surface cell and normal octant (the two sides of a wall thinner than
    # a cell face different octants) and shared with the others of its group
    tree = cKDTree(points)
    octant = (normals > 0).astype(np.int64) @ np.array([1, 2, 4])
    group = np.ravel_multi_index(tuple(cell.T), shape) * 8 + octant
    _, first, cell_of = np.unique(group, return_index=True, return_inverse=True)
    front_rep = _gap_to_other_surface(points[first], normals[first], tree, h, 2.0 * seal)[cell_of]
    back_rep = _gap_to_other_surface(points[first], -normals[first], tree, h, 2.0 * seal)[cell_of]
    same_way = np.einsum("ij,ij->i", normals, normals[first][cell_of]) >= 0
    gap_front = np.where(same_way, front_rep, back_rep)
    gap_back = np.where(same_way, back_rep, front_rep)
    reach = _SIDE_CELLS * h
    matter_front = core_at(points + reach * normals) | np.isfinite(gap_front)
    matter_back = core_at(points - reach * normals) | np.isfinite(gap_back)
    # thin matter: a sheet (matter on neither side), or a wall thinner than the minimum thickness; its middle
    # is thickened to the minimum thickness
    sheet = ~matter_front & ~matter_back
    thin_front = gap_front < t_min  # NaN compares False
    thin_back = gap_back < t_min
    middles = np.concatenate([
        points[sheet],
        points[thin_front] + 0.5 * gap_front[thin_front, None] * normals[thin_front],
        points[thin_back] - 0.5 * gap_back[thin_back, None] * normals[thin_back],
    ])  # fmt: skip
    if len(middles):
        log.info("%s: %.0f %% of the surface bounds no volume or a wall under %.2f mm: thickened to it", name,
                 100.0 * (sheet | thin_front | thin_back).mean(), t_min * 1e3)  # fmt: skip

    # the signed distance field: positive inside. Far from the surface: the grid's distance transform; within a
    # band: the distance to the surface samples, signed by the core and, in surface cells, by the sample's side
    inside = core.copy()
    sdf = np.where(core, ndimage.distance_transform_edt(core), -ndimage.distance_transform_edt(~core)) * h
    band = np.argwhere(dist_surface <= _BAND_CELLS * h)
    centres = origin + (band + 0.5) * h
    dist, nearest = tree.query(centres, workers=-1)
    on_surface = surface[tuple(band.T)]
    side = np.einsum("ij,ij->i", centres - points[nearest], normals[nearest])
    k = nearest[on_surface]
    front, back = side[on_surface] > 0, side[on_surface] < 0
    inside_cell = (matter_front[k] & matter_back[k]) | (matter_front[k] & front) | (matter_back[k] & back)
    inside[tuple(band[on_surface].T)] = inside_cell
    sdf[tuple(band.T)] = np.where(inside[tuple(band.T)], dist, -dist)
    if len(middles):  # thin matter: everything within half the minimum thickness of its middle is inside
        near = np.argwhere(dist_surface <= t_min / 2 + _BAND_CELLS * h)
        d_middle, _ = cKDTree(middles).query(origin + (near + 0.5) * h, workers=-1)
        idx = tuple(near.T)
        sdf[idx] = np.maximum(sdf[idx], t_min / 2 - d_middle)
    return _level_set(sdf, origin, h)


def _cells(points: np.ndarray, origin: np.ndarray, h: float, shape: tuple[int, ...]) -> tuple[np.ndarray, ...]:
    """Grid index tuple of the cells holding ``points`` (clipped to the grid)."""
    cells = np.clip(np.floor((points - origin) / h).astype(np.int64), 0, np.array(shape) - 1)
    return tuple(cells.T)


def _gap_to_other_surface(
    points: np.ndarray, directions: np.ndarray, tree: cKDTree, h: float, max_m: float
) -> np.ndarray:
    """(n,) distance (m) from each point along its unit direction to another surface within ``max_m``; NaN where
    there is none. Probed every half pitch: a probe at distance d is nearer than d / 2 to a surface sample only
    when a surface other than the point's own (which is d away) passes within d / 2 of it; this finds walls
    thicker than a quarter pitch. The gap is the found sample's distance along the direction."""
    gap = np.full(len(points), np.nan)
    for d in np.arange(1, int(np.ceil(max_m / (h / 2))) + 1) * (h / 2):
        todo = np.flatnonzero(np.isnan(gap))
        if not len(todo):
            break
        near, index = tree.query(points[todo] + d * directions[todo], distance_upper_bound=d / 2, workers=-1)
        found = np.isfinite(near)
        hit, q = todo[found], tree.data[index[found]]
        gap[hit] = np.abs(np.einsum("ij,ij->i", q - points[hit], directions[hit]))
    return gap


def _level_set(sdf: np.ndarray, origin: np.ndarray, h: float) -> trimesh.Trimesh:
    """The zero level set of ``sdf`` (grid values at cell centres, positive inside) as a simplified manifold mesh
    in metres."""
    import manifold3d

    nx, ny, nz = sdf.shape
    values = sdf.ravel().tolist()  # plain floats: the callback runs once per grid point, in Python
    sx, sy = ny * nz, nz

    def field(x: float, y: float, z: float) -> float:  # trilinear, in cell units
        i, j, k = int(x), int(y), int(z)
        if i < 0 or j < 0 or k < 0 or i >= nx - 1 or j >= ny - 1 or k >= nz - 1:
            return -1.0
        fx, fy, fz = x - i, y - j, z - k
        b = i * sx + j * sy + k
        c00 = values[b] + (values[b + sx] - values[b]) * fx
        c10 = values[b + sy] + (values[b + sx + sy] - values[b + sy]) * fx
        c01 = values[b + 1] + (values[b + sx + 1] - values[b + 1]) * fx
        c11 = values[b + sy + 1] + (values[b + sx + sy + 1] - values[b + sy + 1]) * fx
        c0, c1 = c00 + (c10 - c00) * fy, c01 + (c11 - c01) * fy
        return c0 + (c1 - c0) * fz

    solid = manifold3d.Manifold.level_set(field, [0.0, 0.0, 0.0, nx - 1.0, ny - 1.0, nz - 1.0], 1.0)
    solid = solid.simplify(_SIMPLIFY_CELLS)
    # grid index i is the centre of cell i: x = origin + (i + 0.5) * h
    return _trimesh_of(solid, scale=h, offset=np.asarray(origin) + 0.5 * h)
