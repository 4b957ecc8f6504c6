"""The knobs of the collision tiers and of their fidelity measurement, and the tier names."""

from __future__ import annotations

import enum
from dataclasses import dataclass, fields
from typing import Literal


class CollisionTier(enum.StrEnum):
    """How a part collides, cheapest first. The value is the name used in scene files and cache keys."""

    HULL = "hull"
    COACD = "coacd"
    VHACD = "vhacd"

    @classmethod
    def _missing_(cls, value: object) -> CollisionTier:
        if isinstance(value, str):
            for tier in cls:
                if tier.value == value.strip().lower():
                    return tier
        raise ValueError(f"unknown collision tier {value!r}; valid tiers: {', '.join(t.value for t in cls)}")

    def __str__(self) -> str:
        return self.value


DEFAULT_TIER_ORDER: tuple[CollisionTier, ...] = (CollisionTier.HULL, CollisionTier.COACD, CollisionTier.VHACD)


@dataclass(frozen=True)
class CollisionParams:
    """Knobs of the three tiers and of the fidelity measurement. Defaults suit small parts (centimetres).

    Hull tier:
        primitive_max_excess_ratio: a fitted box or cylinder replaces the convex hull when its volume exceeds the
            hull's by at most this fraction.
    CoACD (Wei et al. 2022; parameter names of ``coacd.run_coacd``):
        coacd_concavity_threshold: the concavity (a distance relative to the part's size) below which a piece is
            not cut further; 0.01 is very fine, 1.0 coarse. Lower keeps more detail with more pieces.
        coacd_max_hulls: at most this many pieces after merging (-1: no limit). Merging does not shorten the search.
            The default is the cap on pieces per part (each piece is a geom per instance in every drop).
        coacd_remesh: when CoACD voxel-remeshes the input first: "if_not_watertight" (meshes that trimesh finds
            not to be a watertight volume; CoACD's own check also rejects sound meshes with sliver triangles, and
            its remesh inflates small parts), "always" or "never".
        coacd_preprocess_resolution: voxel resolution of that remesh.
        coacd_mcts_iterations, coacd_mcts_nodes, coacd_mcts_max_depth: the Monte-Carlo tree search budget for the
            cutting planes (CoACD's own defaults are 150, 20, 3).
        coacd_pca: cut in the part's principal-axis frame. CoACD only tries axis-aligned cutting planes, so a part
            with features off its axes is cut far finer (slower, more pieces) without this.
        coacd_seed: CoACD's random seed.
    V-HACD (parameter names of ``vhacdx.compute_vhacd``):
        vhacd_voxel_resolution: number of voxels of the part's bounding box.
        vhacd_max_hulls: at most this many pieces.
        vhacd_max_vertices_per_hull: vertices per piece.
        vhacd_min_volume_error_percent: stop splitting a piece when its hull is within this percent of its volume.
        vhacd_max_recursion_depth: splitting depth.
    Repaired solid (``sygrid.objects.collision.solid``; only for meshes that are not one closed volume):
        solid_min_thickness_m: surfaces that bound no volume (a sheet exported as its mid-surface) are thickened to
            this. Twice the drop's penetration bound (``PhysicsSpec.max_penetration_m``, 0.5 mm by default), so a
            neighbour resting on a thickened sheet cannot reach its middle.
        solid_seal_m: openings narrower than twice this (a wall's open end, a crack between faces) are closed before
            the inside is filled.
        solid_max_cells: the voxel grid spans at most this many cells along the part's longest side; its pitch is
            half ``solid_min_thickness_m`` unless that would exceed it (then sheets are thickened to 2 pitches).
    Fidelity measurement:
        fidelity_samples: Monte-Carlo points; the standard error of the volume ratios falls as 1 / sqrt(samples).
        fidelity_seed: seed of those points; the same seed gives the same numbers.
    """

    primitive_max_excess_ratio: float = 0.03
    coacd_concavity_threshold: float = 0.05
    coacd_max_hulls: int = 64
    coacd_remesh: Literal["if_not_watertight", "always", "never"] = "if_not_watertight"
    coacd_preprocess_resolution: int = 50
    coacd_mcts_iterations: int = 60
    coacd_mcts_nodes: int = 10
    coacd_mcts_max_depth: int = 2
    coacd_pca: bool = True
    coacd_seed: int = 0
    vhacd_voxel_resolution: int = 100_000
    vhacd_max_hulls: int = 32
    vhacd_max_vertices_per_hull: int = 64
    vhacd_min_volume_error_percent: float = 1.0
    vhacd_max_recursion_depth: int = 10
    solid_min_thickness_m: float = 0.001
    solid_seal_m: float = 0.001
    solid_max_cells: int = 96
    fidelity_samples: int = 20_000
    fidelity_seed: int = 0

    def __post_init__(self) -> None:
        checks = {
            "primitive_max_excess_ratio": (0.0 <= self.primitive_max_excess_ratio <= 1.0, "in [0, 1]"),
            "coacd_concavity_threshold": (0.0 < self.coacd_concavity_threshold <= 1.0, "in (0, 1]"),
            "coacd_max_hulls": (self.coacd_max_hulls == -1 or self.coacd_max_hulls >= 1, "-1 or >= 1"),
            "coacd_remesh": (
                self.coacd_remesh in ("if_not_watertight", "always", "never"),
                "one of 'if_not_watertight', 'always', 'never'",
            ),
            "coacd_preprocess_resolution": (self.coacd_preprocess_resolution >= 10, ">= 10"),
            "coacd_mcts_iterations": (self.coacd_mcts_iterations >= 1, ">= 1"),
            "coacd_mcts_nodes": (self.coacd_mcts_nodes >= 1, ">= 1"),
            "coacd_mcts_max_depth": (self.coacd_mcts_max_depth >= 1, ">= 1"),
            "vhacd_voxel_resolution": (self.vhacd_voxel_resolution >= 10_000, ">= 10000"),
            "vhacd_max_hulls": (self.vhacd_max_hulls >= 1, ">= 1"),
            "vhacd_max_vertices_per_hull": (self.vhacd_max_vertices_per_hull >= 4, ">= 4"),
            "vhacd_min_volume_error_percent": (0.0 < self.vhacd_min_volume_error_percent <= 100.0, "in (0, 100]"),
            "vhacd_max_recursion_depth": (self.vhacd_max_recursion_depth >= 1, ">= 1"),
            "solid_min_thickness_m": (0.0 < self.solid_min_thickness_m <= 0.05, "in (0, 0.05] m"),
            "solid_seal_m": (0.0 <= self.solid_seal_m <= 0.05, "in [0, 0.05] m"),
            "solid_max_cells": (16 <= self.solid_max_cells <= 512, "in [16, 512]"),
            "fidelity_samples": (self.fidelity_samples >= 1000, ">= 1000"),
        }
        for name, (ok, expected) in checks.items():
            if not ok:
                raise ValueError(f"CollisionParams.{name} must be {expected}, got {getattr(self, name)!r}")

    def key_fields(self, tier: CollisionTier) -> dict:
        """The fields that change ``tier``'s result: the cache key does not change with another tier's knobs."""
        prefix = {CollisionTier.HULL: "primitive_", CollisionTier.COACD: "coacd_", CollisionTier.VHACD: "vhacd_"}
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name.startswith((prefix[tier], "fidelity_"))}

    def solid_key_fields(self) -> dict:
        """The fields that change a repaired solid (``sygrid.objects.collision.solid``)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name.startswith("solid_")}
