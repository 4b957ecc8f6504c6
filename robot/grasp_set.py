"""The grasp candidates' types: ``GraspSetParams`` (how candidates are generated, and the gripper they are for) and
``GraspSet`` (the candidates of one part, in its object frame). ``robot.grasp_candidates`` makes them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from robot.grasp_geometry import GripperGeometry
from sygrid.errors import ConfigError
from sygrid.objects.model import GraspAnnotation


@dataclass(frozen=True)
class GraspSetParams:
    """How candidates are generated, expanded and de-duplicated. Every field is part of the cache key.

    friction_coefficient: pad-part friction; the friction cone's half angle is ``atan`` of it.
    n_surface_samples: surface points whose inward rays seed the pairs. n_dense_samples: surface points for the
    contact and self-collision analysis (each stands for ``area / n`` of surface). n_approach: approach directions
    around each pair's axis (16: every 22.5 degrees, so 0, 22.5 and 45 degrees of tilt within the planner's cone).
    contact_tolerance_m: how far from a pad's plane the surface still counts as touching (rubber pads).
    min_contact_area_m2 / contact_area_saturation_m2: the least area each pad must touch, and the area at which the
    score stops growing. min_engagement_m: the least length (along the approach) over which both
    pads touch. open_clearance_m: per side, how much wider than the part the gripper opens to come in (5 mm: more
    than a pose error of a few millimetres, and each millimetre more keeps the fingers off more neighbours);
    min_open_clearance_m: the least per-side margin a part must leave in the stroke. self_clearance_m: distance kept
    between the gripper and the part outside the contacts. dedup_position_m / dedup_angle_deg: candidates closer
    than this (position and axes) are one. continuous_steps: samples of a continuous symmetry (every 360/steps
    degrees). seed: the sampler's seed.
    """

    friction_coefficient: float = 0.4
    n_surface_samples: int = 400
    n_dense_samples: int = 3000
    n_approach: int = 16
    contact_tolerance_m: float = 0.001
    min_contact_area_m2: float = 6e-6
    contact_area_saturation_m2: float = 60e-6
    min_engagement_m: float = 0.002
    min_width_m: float = 0.002
    open_clearance_m: float = 0.005
    min_open_clearance_m: float = 0.003
    self_clearance_m: float = 0.001
    dedup_position_m: float = 0.004
    dedup_angle_deg: float = 15.0
    continuous_steps: int = 36
    seed: int = 0
    gripper: GripperGeometry = field(default_factory=GripperGeometry)

    def __post_init__(self) -> None:
        if not self.friction_coefficient > 0:
            raise ConfigError(f"GraspSetParams.friction_coefficient must be > 0, got {self.friction_coefficient}")
        for name in ("n_surface_samples", "n_dense_samples", "n_approach", "continuous_steps"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"GraspSetParams.{name} must be >= 1, got {getattr(self, name)}")
        for name in (
            "contact_tolerance_m", "min_contact_area_m2", "contact_area_saturation_m2", "min_engagement_m",
            "min_width_m", "open_clearance_m", "min_open_clearance_m", "self_clearance_m", "dedup_position_m",
            "dedup_angle_deg",
        ):  # fmt: skip
            if getattr(self, name) < 0:
                raise ConfigError(f"GraspSetParams.{name} must be >= 0, got {getattr(self, name)}")

    @property
    def cone_half_angle_rad(self) -> float:
        return float(np.arctan(self.friction_coefficient))

    @property
    def max_width_m(self) -> float:
        """The widest part that still leaves ``min_open_clearance_m`` per side in the stroke."""
        return self.gripper.stroke_m - 2.0 * self.min_open_clearance_m


@dataclass(frozen=True, eq=False)
class GraspSet:
    """Grasp candidates of one part, in its object frame. All arrays have ``n`` rows.

    T_obj_grasp: ``(n, 4, 4)`` TCP poses. width_m: ``(n,)`` the part's width between the pads. opening_m: ``(n,)``
    how far to open before coming in. score: ``(n,)`` quality in [0, 1]. contact_z_m: ``(n, 2)`` the span
    ``[lo, hi]`` along the grasp's z over which both pads touch the part (in the grasp frame; the pads span
    ``+-pad_length / 2``). source: ``"antipodal"`` or ``"declared"``.
    """

    T_obj_grasp: np.ndarray
    width_m: np.ndarray
    opening_m: np.ndarray
    score: np.ndarray
    contact_z_m: np.ndarray
    source: str = "antipodal"

    def __post_init__(self) -> None:
        n = len(self.T_obj_grasp)
        shapes = {
            "T_obj_grasp": (np.shape(self.T_obj_grasp), (n, 4, 4)),
            "width_m": (np.shape(self.width_m), (n,)),
            "opening_m": (np.shape(self.opening_m), (n,)),
            "score": (np.shape(self.score), (n,)),
            "contact_z_m": (np.shape(self.contact_z_m), (n, 2)),
        }
        for name, (got, want) in shapes.items():
            if got != want:
                raise ValueError(f"GraspSet.{name} must have shape {want}, got {got}")
        for name in shapes:
            value = np.array(getattr(self, name), dtype=float)  # private, read-only copies
            value.flags.writeable = False
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return len(self.T_obj_grasp)

    def subset(self, index: np.ndarray) -> GraspSet:
        """The candidates at ``index`` (an index array or a boolean mask)."""
        return GraspSet(
            self.T_obj_grasp[index], self.width_m[index], self.opening_m[index], self.score[index],
            self.contact_z_m[index], self.source,
        )  # fmt: skip

    def to_annotations(self) -> tuple[GraspAnnotation, ...]:
        """The candidates as ``GraspAnnotation`` (pose, width, score), e.g. to declare them on a model."""
        return tuple(
            GraspAnnotation(T.copy(), float(w), float(s))
            for T, w, s in zip(self.T_obj_grasp, self.width_m, self.score, strict=True)
        )
