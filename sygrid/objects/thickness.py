"""A part's typical wall thickness: how far inside the solid a ray from its surface, pointing inwards, travels.

Why it is measured: a free-falling part whose wall is thinner than the distance it moves in one physics step can
pass into another part's wall between two steps, and the contact solver then settles them interlocked, deeper
than the drop's penetration bound (the 1 mm walls of a cable-duct cover do this; the built-in parts do not). The
drop turns on MuJoCo's speculative contacts for such scenes (``PhysicsSpec.speculative_contacts``).

The measure is the median, over surface points sampled by area, of the distance from the point along the inward
normal to the next surface of the solid (trimesh's ray casting): on a sheet of thickness t it is t; on a block it
is a typical cross-section. The median, not the minimum, because rays that start at an edge or a chamfer hit the
neighbouring face within microns, which says nothing of the wall.
"""

from __future__ import annotations

import numpy as np
import trimesh

# Rays start this far inside the surface so they do not hit their own face (10 microns: well below any wall;
# trimesh's ray test still reports the own face from 1 micron in on some meshes). Hits closer than this are that.
_RAY_START_OFFSET_M = 1e-5
_SAMPLES = 256
_SAMPLE_SEED = 0  # fixed: the thickness is a property of the mesh, the same on every call


_cache: dict[tuple[str, int], float] = {}


def wall_thickness_m(solid: trimesh.Trimesh, samples: int = _SAMPLES) -> float:
    """Median inward wall thickness (m) of the closed ``solid`` (object frame, metres); cached by mesh content.

    Raises ValueError on a mesh that is not a closed volume (an open sheet has no inside to measure)."""
    if not solid.is_volume:
        raise ValueError("wall thickness needs a closed solid (use ObjectModel.solid, the repaired one)")
    key = (solid.identifier_hash, samples)
    if key not in _cache:
        _cache[key] = _measure(solid, samples)
    return _cache[key]


def _measure(solid: trimesh.Trimesh, samples: int) -> float:
    points, faces = trimesh.sample.sample_surface(solid, samples, seed=_SAMPLE_SEED)
    inward = -solid.face_normals[faces]
    origins = points + inward * _RAY_START_OFFSET_M
    hits, rays, _ = solid.ray.intersects_location(origins, inward, multiple_hits=False)
    depth = np.linalg.norm(hits - origins[rays], axis=1)
    depth = depth[depth > _RAY_START_OFFSET_M] + _RAY_START_OFFSET_M
    return float(np.median(depth)) if len(depth) else float(np.min(solid.extents))
