"""Point-in-solid tests on plain arrays: inside a closed convex mesh, inside a closed triangle mesh.

Written here because ``trimesh.contains`` took 3-55 s per 20 000 points on the built-in parts (ray tests without
embree); this ray-parity test with spatial binning takes 0.05-0.4 s and agrees with it to a few points in 20 000.
"""

from __future__ import annotations

import itertools

import numpy as np

_MAX_PAIRS_PER_BATCH = 2_000_000  # memory bound of the point-in-mesh test (about 100 MB of temporaries)


def points_in_convex(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, tol_m: float = 1e-9) -> np.ndarray:
    """(n,) bool: which ``points`` (n, 3) lie inside the closed convex mesh ``vertices`` (v, 3), ``faces`` (f, 3)
    with outward normals: behind every face plane, within ``tol_m``."""
    tri = vertices[faces]  # (f, 3, 3)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normals, axis=1)
    ok = length > 1e-8 * length.max()  # a near-zero-area triangle's normal is rounding noise: not a plane
    normals = normals[ok] / length[ok, None]
    offsets = np.einsum("ij,ij->i", normals, tri[ok, 0])
    # coplanar triangles share a plane: test each plane once (a 192-gon prism: 194 planes instead of 764 faces)
    scale = max(float(np.abs(vertices).max()), 1e-12)
    _, first = np.unique(np.round(np.column_stack([normals, offsets / scale]), 9), axis=0, return_index=True)
    normals, offsets = normals[first], offsets[first]
    lo, hi = vertices.min(0) - tol_m, vertices.max(0) + tol_m
    inside = np.all((points >= lo) & (points <= hi), axis=1)
    candidates = np.flatnonzero(inside)
    if len(candidates):
        signed = points[candidates] @ normals.T - offsets  # (k, f) signed distance to each face plane
        inside[candidates] = np.all(signed <= tol_m, axis=1)
    return inside


def points_in_mesh(triangles: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(n,) bool: which ``points`` (n, 3) lie inside the closed triangle mesh ``triangles`` (f, 3, 3).

    Ray parity: a point is inside when an axis-parallel ray from it crosses the surface an odd number of times.
    Points are binned on a grid across the ray axis, so each triangle is tested only against the points in its
    projected box: the cost is about linear in points + faces. Adjacent triangles evaluate a shared edge with the
    same floating-point products (opposite sign), and a ray exactly on an edge goes to one side by a fixed tie
    rule, so a ray through an edge or a vertex counts once (grid-aligned points work, not only random ones).
    """
    n = len(points)
    if n == 0 or len(triangles) == 0:
        return np.zeros(n, dtype=bool)
    # cast along the axis whose projection is cheapest: fewest (triangle box, point) pairs, e.g. along a washer's
    # diameter rather than its axis, where every sliver of its faces covers much of the ring
    spans = np.maximum(points.max(0) - points.min(0), 1e-12)
    widths = triangles.max(1) - triangles.min(1)  # (f, 3)
    axis = int(
        np.argmin([np.sum(np.prod(np.delete(widths, k, 1), 1)) / np.prod(np.delete(spans, k)) for k in range(3)])
    )
    perm = [i for i in range(3) if i != axis] + [axis]
    triangles, points = triangles[:, :, perm], points[:, perm]
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    area2 = _cross2(b - a, c - a)  # twice the signed xy area
    keep = area2 != 0.0  # vertical triangles never cross a vertical ray
    a, b, c, area2 = a[keep], b[keep], c[keep], area2[keep]

    # xy grid over the points; point indices sorted by cell so that a row of cells is one contiguous slice
    lo = points[:, :2].min(0)
    span = np.maximum(points[:, :2].max(0) - lo, 1e-12)
    grid = int(np.clip(np.sqrt(n / 8.0), 1, 512))
    cell = span / grid

    def cell_of(xy: np.ndarray) -> np.ndarray:
        return np.clip(np.floor((xy - lo) / cell), 0, grid - 1).astype(np.int64)

    pc = cell_of(points[:, :2])
    cell_id = pc[:, 1] * grid + pc[:, 0]
    order = np.argsort(cell_id, kind="stable")
    cell_start = np.searchsorted(cell_id[order], np.arange(grid * grid + 1))

    tri_xy = np.stack([a[:, :2], b[:, :2], c[:, :2]], axis=1)
    t0, t1 = cell_of(tri_xy.min(1)), cell_of(tri_xy.max(1))  # (t, 2) first and last cell of each triangle
    rows_per_tri = t1[:, 1] - t0[:, 1] + 1
    row_tri = np.repeat(np.arange(len(a)), rows_per_tri)
    row = t0[row_tri, 1] + _ranks(rows_per_tri)
    first = cell_start[row * grid + t0[row_tri, 0]]
    count = cell_start[row * grid + t1[row_tri, 0] + 1] - first

    crossings = np.zeros(n, dtype=np.int64)
    ends = np.cumsum(count)
    cuts = np.searchsorted(ends, np.arange(1, ends[-1] // _MAX_PAIRS_PER_BATCH + 1) * _MAX_PAIRS_PER_BATCH)
    batches = np.unique(np.concatenate([[0], cuts, [len(count)]]))
    for lo_row, hi_row in itertools.pairwise(batches):
        sel = slice(lo_row, hi_row)
        pair_tri = np.repeat(row_tri[sel], count[sel])
        pair_pt = order[np.repeat(first[sel], count[sel]) + _ranks(count[sel])]
        p = points[pair_pt]
        ta, tb, tc, s = a[pair_tri], b[pair_tri], c[pair_tri], np.sign(area2[pair_tri])
        e0, e1, e2 = _cross2(tb - p, tc - p), _cross2(tc - p, ta - p), _cross2(ta - p, tb - p)
        under = _edge_in(e0, s, tc - tb) & _edge_in(e1, s, ta - tc) & _edge_in(e2, s, tb - ta)
        e0, e1, e2, ta, tb, tc = e0[under], e1[under], e2[under], ta[under], tb[under], tc[under]
        z = (e0 * ta[:, 2] + e1 * tb[:, 2] + e2 * tc[:, 2]) / area2[pair_tri[under]]
        z = np.clip(z, np.minimum(np.minimum(ta[:, 2], tb[:, 2]), tc[:, 2]),
                    np.maximum(np.maximum(ta[:, 2], tb[:, 2]), tc[:, 2]))  # fmt: skip
        crossings += np.bincount(pair_pt[under][z > p[under, 2]], minlength=n)
    return crossings % 2 == 1


def _cross2(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """z of the cross product of the xy parts of ``u`` and ``v`` (..., >=2)."""
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _edge_in(e: np.ndarray, s: np.ndarray, edge: np.ndarray) -> np.ndarray:
    """Whether points are on the inner side of a triangle edge: edge function ``e`` times the triangle's xy
    orientation ``s`` positive, or zero on an edge whose direction (``edge``, made counter-clockwise by ``s``)
    points up or, horizontal, left. Two triangles that share the edge see it in opposite directions, so exactly
    one of them takes a point on it."""
    dx, dy = edge[:, 0] * s, edge[:, 1] * s
    return (e * s > 0) | ((e == 0) & ((dy > 0) | ((dy == 0) & (dx < 0))))


def _ranks(counts: np.ndarray) -> np.ndarray:
    """0, 1, ..., counts[0]-1, 0, 1, ..., counts[1]-1, ...: the index of each repeated element in its group."""
    total = int(counts.sum())
    return np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
