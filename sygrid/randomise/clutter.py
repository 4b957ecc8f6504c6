"""Distractor pieces as objects: the models and collision models the drop takes for the pieces dropped into the bin,
and every piece posed in the world with its finish, for the renderer.

Primitives are meshed so that they come to rest: a box collides as its exact box, a cylinder as the convex hull of
its 12-sided prism and a sphere as a once-subdivided icosahedron (a smooth round shape rolls on, and a pile with a
rolling piece never settles); the same mesh is rendered. A built-in part collides through its disk-cached hull.
Distractors have ``obj_id`` 0: they are never labelled.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import trimesh

from sygrid.drop import collision_models
from sygrid.objects.collision.geometry import CollisionModel, ConvexPiece, Fidelity, PrimitiveGeom
from sygrid.objects.collision.params import CollisionParams, CollisionTier
from sygrid.objects.model import ObjectModel
from sygrid.objects.parts import builtin_part
from sygrid.randomise.draws import DistractorsDraw, FinishDraw, PieceDraw

DISTRACTOR_OBJ_ID = 0
_CYLINDER_SECTIONS = 12


@dataclass(frozen=True, eq=False)
class ClutterPiece:
    """A distractor in the world: its model (object frame), ``T_world_obj`` (4, 4) and finish."""

    model: ObjectModel
    T_world_obj: np.ndarray
    finish: FinishDraw


def piece_model(piece: PieceDraw, index: int) -> ObjectModel:
    """The object model of a distractor (``obj_id`` 0, named ``distractor_<index>``)."""
    material = "steel" if piece.finish.is_metal else "plastic"
    name = f"distractor_{index}"
    if piece.shape.startswith("builtin:"):
        part = builtin_part(piece.shape.removeprefix("builtin:"))
        return replace(part, obj_id=DISTRACTOR_OBJ_ID, name=name, material=material, grasps=())
    a, b, c = piece.size_m
    if piece.shape == "box":
        mesh = trimesh.creation.box(extents=(a, b, c))
    elif piece.shape == "cylinder":
        mesh = trimesh.creation.cylinder(radius=a / 2, height=c, sections=_CYLINDER_SECTIONS)
    elif piece.shape == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=1, radius=a / 2)
    else:
        raise ValueError(f"unknown distractor shape {piece.shape!r}")
    return ObjectModel(
        obj_id=DISTRACTOR_OBJ_ID, name=name, mesh=mesh, material=material, source=f"distractor:{piece.shape}",
        density_kg_m3=piece.density_kg_m3,
    )  # fmt: skip


def piece_collision(model: ObjectModel, piece: PieceDraw) -> CollisionModel:
    """The collision model a distractor drops with (see the module doc)."""
    if piece.shape.startswith("builtin:"):
        return collision_models([model], "hull")[0]
    mesh = model.mesh
    if piece.shape == "box":
        primitives: tuple[PrimitiveGeom, ...] = (PrimitiveGeom("box", tuple(np.asarray(piece.size_m) / 2), np.eye(4)),)
        pieces: tuple[ConvexPiece, ...] = ()
    else:
        hull = mesh.convex_hull
        primitives, pieces = (), (ConvexPiece(np.asarray(hull.vertices, float), np.asarray(hull.faces, np.int64)),)
    fidelity = Fidelity(0.0, 0.0, 1.0, 0.0, 1, sum(len(p.vertices) for p in pieces), 0)
    return CollisionModel(
        CollisionTier.HULL, pieces, primitives, fidelity, 0.0, 0.0, model.content_hash, CollisionParams()
    )


def bin_clutter(draw: DistractorsDraw | None) -> list[tuple[ObjectModel, CollisionModel]]:
    """The models and collision models of the pieces to drop into the bin, in draw order (none when off)."""
    if draw is None:
        return []
    models = [piece_model(p, k) for k, p in enumerate(draw.in_bin)]
    return [(m, piece_collision(m, p)) for m, p in zip(models, draw.in_bin, strict=True)]


def placed_clutter(draw: DistractorsDraw | None, T_world_in_bin: np.ndarray) -> list[ClutterPiece]:
    """Every piece in the world: those in the bin at the drop's poses ``T_world_in_bin`` ((n, 4, 4), draw order),
    then those around it at their drawn poses."""
    if draw is None:
        return []
    n = len(draw.in_bin)
    if len(T_world_in_bin) != n:
        raise ValueError(f"{len(T_world_in_bin)} poses for {n} pieces dropped into the bin")
    out = [
        ClutterPiece(piece_model(p, k), np.asarray(T, dtype=float), p.finish)
        for k, (p, T) in enumerate(zip(draw.in_bin, T_world_in_bin, strict=True))
    ]
    for k, p in enumerate(draw.around_bin):
        T = np.asarray(p.T_world_obj, dtype=float).reshape(4, 4)
        out.append(ClutterPiece(piece_model(p, n + k), T, p.finish))
    return out
