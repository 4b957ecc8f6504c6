"""The fidelity of a collision model against the true mesh, measured with seeded Monte-Carlo points (the
quantities are defined on ``sygrid.objects.collision.geometry.Fidelity``)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import trimesh

from sygrid.errors import MeshError
from sygrid.objects.collision.geometry import (
    MIN_CONCAVE_SAMPLES,
    ConvexPiece,
    Fidelity,
    PrimitiveGeom,
    pieces_bounds,
    pieces_contain,
)
from sygrid.objects.inside import points_in_convex, points_in_mesh


def measure_fidelity(
    mesh: trimesh.Trimesh,
    pieces: Sequence[ConvexPiece],
    primitives: Sequence[PrimitiveGeom],
    n_samples: int,
    seed: int,
    name: str = "mesh",
) -> Fidelity:
    """The ``Fidelity`` of a collision model (pieces and primitives, object frame) against ``mesh``.

    Cost: one point-in-mesh test of ``n_samples`` points, plus a half-space test per convex piece. ``name`` is the
    part's name for error messages.

    Raises:
        MeshError: no sample falls inside the mesh (it has no inside).
    """
    model_lo, model_hi = pieces_bounds(pieces, primitives)
    lo, hi = np.minimum(model_lo, mesh.bounds[0]), np.maximum(model_hi, mesh.bounds[1])
    points = np.random.default_rng(seed).uniform(lo, hi, size=(n_samples, 3))

    in_mesh = np.zeros(n_samples, dtype=bool)
    mesh_lo, mesh_hi = np.asarray(mesh.bounds)
    near = np.all((points >= mesh_lo) & (points <= mesh_hi), axis=1)  # outside M's box nothing is inside M
    in_mesh[near] = points_in_mesh(np.asarray(mesh.triangles), points[near])
    hull = mesh.convex_hull
    in_hull = np.zeros(n_samples, dtype=bool)
    in_hull[near] = points_in_convex(np.asarray(hull.vertices), np.asarray(hull.faces), points[near])
    in_model = pieces_contain(pieces, primitives, points)

    n_mesh = int(in_mesh.sum())
    if n_mesh == 0:
        raise MeshError(
            f"{name}: no Monte-Carlo point of {n_samples} in its bounding box fell inside the mesh, so it has no "
            "inside (open, or normals pointing inward); expected a watertight mesh with outward normals"
        )
    concave = in_hull & ~in_mesh
    n_concave = int(concave.sum())
    return Fidelity(
        excess_volume_ratio=float((in_model & ~in_mesh).sum() / n_mesh),
        missed_volume_ratio=float((in_mesh & ~in_model).sum() / n_mesh),
        concavity_kept=float((concave & ~in_model).sum() / n_concave) if n_concave >= MIN_CONCAVE_SAMPLES else 1.0,
        concave_volume_ratio=float(n_concave / n_mesh),
        n_pieces=len(pieces) + len(primitives),
        n_vertices_total=int(sum(len(p.vertices) for p in pieces)),
        n_samples=n_samples,
    )
