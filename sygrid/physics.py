"""The MuJoCo drop: instances spawned without overlap above the bin fall and settle; one ``T_world_obj`` each.

The SyGRID paper drops its parts with pybullet; we use MuJoCo, which the simulated cell uses too, so a pile that the
generator renders and a pile that the robot picks from are made by the same physics. The scene frame ("world")
has its origin at the centre of the bin's inner floor, z up.

Contact parameters are chosen for small steel parts: with MuJoCo's default ``solref`` (0.02 s time constant) a
20 g nut sinks 10-17 mm into the floor on impact and can tunnel through a wall. A time constant of two timesteps,
critically damped, set on every geom, keeps penetration at rest well under 0.5 mm (platform notes).

Thin walls are the exception: a part whose wall is thinner than the distance it falls in one step can pass into
another's wall between two steps and settle interlocked. ``physics.speculative_contacts`` turns on MuJoCo's
speculative contacts (contacts predicted over the coming step) for such scenes: always, never, or ("auto") when
the thinnest wall of the scene's parts (``sygrid.objects.thickness``) is under the step's travel at the impact
speed of the highest spawned part. They cost solver time, so scenes of thick parts go without.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from sygrid.errors import DropError
from sygrid.mjspec import add_open_box, add_part_body
from sygrid.objects.collision.geometry import CollisionModel
from sygrid.objects.model import ObjectModel
from sygrid.objects.thickness import wall_thickness_m
from sygrid.scene import ContainerSpec, PhysicsSpec

log = logging.getLogger(__name__)

# Spawning: each instance gets a bounding sphere; spheres never overlap, so meshes cannot touch at t=0.
_SPAWN_CANDIDATES = 24
_SPAWN_FLOOR_GAP_M = 0.005
_MAX_SPAWN_HEIGHT_M = 3.0
# Settling: speeds are checked every few steps and must stay below the thresholds for this long.
_SETTLE_CHECK_EVERY_STEPS = 10
_SETTLE_HOLD_S = 0.1
_MIN_SIM_TIME_S = 0.2
_FLOOR_THICKNESS_M = 0.02
_INSIDE_TOLERANCE_M = 0.002
_GRAVITY_M_S2 = 9.81  # MuJoCo's default gravity, which the drop keeps


@dataclass(frozen=True)
class Instance:
    """One part in the pile: which model (index into the drop's model list) and its instance number."""

    model_index: int
    inst_id: int


@dataclass
class StabilityReport:
    """What the drop checked about the final pile, and the bounds it was checked against.

    The bounds are the scene's ``physics``: the pile settled (speeds below ``settle_*`` for a hold time) within
    ``max_time_s`` of simulated time (``sim_time_s`` is then the settle time), and its deepest contact at rest is at
    most ``penetration_bound_m`` (``physics.max_penetration_m``). ``ok``: the poses are usable at all (every part
    in the bin, every pose finite); ``within_bounds``: ``ok`` and both bounds met, what the generator's quality gate
    and ``sygrid drop``'s exit code require; ``failures`` says, one phrase each, which bounds failed.
    """

    settled: bool
    sim_time_s: float
    wall_time_s: float
    max_penetration_m: float
    escaped: list[int] = field(default_factory=list)
    non_finite: list[int] = field(default_factory=list)
    max_linear_speed_m_s: float = 0.0
    rest_drift_m: float | None = None  # largest move of any part when the pile, awake, runs on (if measured)
    penetration_bound_m: float = math.inf
    max_time_s: float = math.inf
    speculative_contacts: bool = False  # whether the drop ran with MuJoCo's speculative contacts

    @property
    def ok(self) -> bool:
        return not self.escaped and not self.non_finite

    @property
    def failures(self) -> list[str]:
        out = []
        if self.non_finite:
            out.append(f"non-finite poses of instances {self.non_finite}")
        if self.escaped:
            out.append(f"instances {self.escaped} left the bin")
        if not self.settled:
            out.append(f"the pile did not settle within {self.max_time_s:.2f} s of simulated time")
        if not self.max_penetration_m <= self.penetration_bound_m:
            out.append(
                f"penetration at rest {self.max_penetration_m * 1e3:.2f} mm is above the bound "
                f"{self.penetration_bound_m * 1e3:.2f} mm"
            )
        return out

    @property
    def within_bounds(self) -> bool:
        return not self.failures

    def to_json(self) -> dict:
        return {
            "settled": self.settled,
            "sim_time_s": self.sim_time_s,
            "wall_time_s": self.wall_time_s,
            "max_penetration_m": self.max_penetration_m,
            "escaped": list(self.escaped),
            "non_finite": list(self.non_finite),
            "max_linear_speed_m_s": self.max_linear_speed_m_s,
            "rest_drift_m": self.rest_drift_m,
            "penetration_bound_m": self.penetration_bound_m,
            "speculative_contacts": self.speculative_contacts,
            "max_time_s": self.max_time_s,
            "within_bounds": self.within_bounds,
        }


@dataclass
class DropResult:
    """Final poses ``T_world_obj`` (n, 4, 4) of every instance, in the scene frame, and the stability report.
    ``collision[k]`` is the collision model that ``models[k]`` was dropped with."""

    models: list[ObjectModel]
    collision: list[CollisionModel]
    instances: list[Instance]
    T_world_obj: np.ndarray
    report: StabilityReport


def sample_spawn_poses(
    radii_m: np.ndarray, container: ContainerSpec, clearance_m: float, rng: np.random.Generator
) -> np.ndarray:
    """(n, 4, 4) non-overlapping spawn poses above the bin floor, packed low: each instance takes the lowest of
    several random footprint positions at which its bounding sphere clears every sphere placed before it."""
    half_x, half_y = container.inner_size_m[0] / 2, container.inner_size_m[1] / 2
    centres = np.zeros((len(radii_m), 3))
    padded = np.asarray(radii_m) + clearance_m
    for i, r in enumerate(padded):
        xy = rng.uniform(
            [-max(half_x - r, 0.0), -max(half_y - r, 0.0)],
            [max(half_x - r, 0.0), max(half_y - r, 0.0)],
            size=(_SPAWN_CANDIDATES, 2),
        )
        z = np.full(_SPAWN_CANDIDATES, r + _SPAWN_FLOOR_GAP_M)
        if i:
            reach = r + padded[:i]  # (i,)
            d2 = ((xy[:, None, :] - centres[None, :i, :2]) ** 2).sum(-1)  # (candidates, i)
            lift = np.sqrt(np.clip(reach[None, :] ** 2 - d2, 0.0, None))
            z = np.maximum(z, np.where(d2 < reach[None, :] ** 2, centres[None, :i, 2] + lift, 0.0).max(1))
        best = int(np.argmin(z))
        centres[i] = [*xy[best], z[best] + 1e-6]
        if centres[i, 2] > _MAX_SPAWN_HEIGHT_M:
            raise DropError(
                f"cannot spawn instance {i}: the column of parts above the bin is over {_MAX_SPAWN_HEIGHT_M} m "
                f"high. Try 1. fewer instances, 2. a larger container.inner_size_m (now "
                f"{list(container.inner_size_m)}), or 3. smaller parts."
            )
    poses = np.tile(np.eye(4), (len(radii_m), 1, 1))
    poses[:, :3, :3] = Rotation.random(len(radii_m), random_state=rng).as_matrix()
    poses[:, :3, 3] = centres
    return poses


def build_drop_spec(
    models: list[ObjectModel],
    collision: list[CollisionModel],
    instances: list[Instance],
    T_world_obj: np.ndarray,
    container: ContainerSpec,
    physics: PhysicsSpec,
    speculative: bool = False,
) -> mujoco.MjSpec:
    """An MjSpec with the bin (static boxes) and one free body per instance, its geoms from the collision model
    and its mass and inertia from the repaired solid (``ObjectModel.solid``; a collision hull would fill the holes
    and overstate both). ``speculative``: MuJoCo's speculative contacts on (see the module's docstring)."""
    spec = mujoco.MjSpec()
    spec.option.timestep = physics.timestep_s
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    if speculative:
        spec.option.enableflags |= mujoco.mjtEnableBit.mjENBL_SPECULATIVE
    # Island sleeping: parts at rest stop costing collision and solver time while the rest of the pile settles.
    if physics.sleep_tolerance > 0:
        spec.option.enableflags |= mujoco.mjtEnableBit.mjENBL_SLEEP
        spec.option.sleep_tolerance = physics.sleep_tolerance
    solref = [2 * physics.timestep_s, 1.0]
    friction = [physics.friction, 0.005, 0.0001]
    add_open_box(
        spec.worldbody, "bin", np.eye(4), container.inner_size_m, container.wall_thickness_m, _FLOOR_THICKNESS_M,
        solref, friction,
    )  # fmt: skip
    for n, inst in enumerate(instances):
        model, coll = models[inst.model_index], collision[inst.model_index]
        add_part_body(spec, f"inst{n}", model, coll, T_world_obj[n], solref, friction)
    return spec


def simulate_drop(
    models: list[ObjectModel],
    collision: list[CollisionModel],
    instances: list[Instance],
    container: ContainerSpec,
    physics: PhysicsSpec,
    rng: np.random.Generator,
    rest_check_s: float = 0.0,
) -> DropResult:
    """Spawns, simulates until settled or ``physics.max_time_s``, and checks the pile.

    With ``rest_check_s`` > 0 the final poses are simulated again from rest (zero velocity, no sleeping) for that
    long, as the sim cell does when it receives them, and the largest displacement of any part is reported as
    ``rest_drift_m``: how far from a resting pile "settled" was.
    """
    start = time.perf_counter()
    bounding = [bounding_radius_m(m, c) for m, c in zip(models, collision, strict=True)]
    radii = np.array([bounding[i.model_index] for i in instances])
    T_spawn = sample_spawn_poses(radii, container, physics.spawn_clearance_m, rng)
    speculative = use_speculative_contacts(physics, [models[i.model_index] for i in instances], T_spawn)
    spec = build_drop_spec(models, collision, instances, T_spawn, container, physics, speculative)
    mj_model = spec.compile()
    data = mujoco.MjData(mj_model)
    mujoco.mj_forward(mj_model, data)
    _check_no_initial_contact(mj_model, data)

    settled, hold_steps = False, 0
    need_hold = max(1, round(_SETTLE_HOLD_S / physics.timestep_s / _SETTLE_CHECK_EVERY_STEPS))
    max_steps = round(physics.max_time_s / physics.timestep_s)
    min_steps = round(_MIN_SIM_TIME_S / physics.timestep_s)
    lin_speed = 0.0
    for step in range(0, max_steps, _SETTLE_CHECK_EVERY_STEPS):
        mujoco.mj_step(mj_model, data, nstep=_SETTLE_CHECK_EVERY_STEPS)
        qvel = data.qvel.reshape(-1, 6)  # free joints only: linear (world) then angular (body) velocity
        lin_speed = float(np.linalg.norm(qvel[:, :3], axis=1).max(initial=0.0))
        ang_speed = float(np.linalg.norm(qvel[:, 3:], axis=1).max(initial=0.0))
        calm = lin_speed < physics.settle_linear_speed_m_s and ang_speed < physics.settle_angular_speed_rad_s
        hold_steps = hold_steps + 1 if calm else 0
        if hold_steps >= need_hold and step >= min_steps:
            settled = True
            break
        if not np.all(np.isfinite(data.qpos)):
            break

    T_world_obj = _body_poses(data, len(instances))
    # Sleeping bodies skip collision detection: wake everything to measure the penetration of the final pile.
    mj_model.opt.enableflags &= ~int(mujoco.mjtEnableBit.mjENBL_SLEEP)
    mujoco.mj_forward(mj_model, data)
    max_penetration_m = _max_penetration(data)
    wall_time_s, sim_time_s = time.perf_counter() - start, float(data.time)
    rest_drift_m = None
    if rest_check_s > 0:  # the poses are what leaves the drop: restart from them at rest, as the cell does
        rest = mujoco.MjData(mj_model)
        rest.qpos[:] = data.qpos
        mujoco.mj_step(mj_model, rest, nstep=max(1, round(rest_check_s / physics.timestep_s)))
        moved = _body_poses(rest, len(instances))[:, :3, 3] - T_world_obj[:, :3, 3]
        rest_drift_m = float(np.nanmax(np.linalg.norm(moved, axis=1), initial=0.0))
    report = StabilityReport(
        settled=settled,
        sim_time_s=sim_time_s,
        wall_time_s=wall_time_s,
        max_penetration_m=max_penetration_m,
        escaped=_escaped(T_world_obj, container),
        non_finite=[n for n in range(len(instances)) if not np.all(np.isfinite(T_world_obj[n]))],
        max_linear_speed_m_s=lin_speed,
        rest_drift_m=rest_drift_m,
        penetration_bound_m=physics.max_penetration_m,
        max_time_s=physics.max_time_s,
        speculative_contacts=speculative,
    )
    for failure in report.failures:
        log.warning("%s", failure)
    return DropResult(list(models), list(collision), list(instances), T_world_obj, report)


# ---------------------------------------------------------------------------------------------- helpers


def use_speculative_contacts(physics: PhysicsSpec, models: list[ObjectModel], T_spawn: np.ndarray) -> bool:
    """``physics.speculative_contacts`` resolved for one drop: "on" / "off" as given; "auto": on when the thinnest
    wall among ``models`` is under the distance the highest instance of ``T_spawn`` ((n, 4, 4), world) travels in
    one step when it reaches the floor."""
    if physics.speculative_contacts != "auto":
        return physics.speculative_contacts == "on"
    if not models:
        return False
    impact_speed = math.sqrt(2 * _GRAVITY_M_S2 * max(float(T_spawn[:, 2, 3].max()), 0.0))
    thinnest = min(wall_thickness_m(m.solid) for m in models)
    return thinnest < impact_speed * physics.timestep_s


def bounding_radius_m(model: ObjectModel, collision: CollisionModel) -> float:
    """Radius of a sphere about the object origin that holds the mesh and every collision geom. Not the model's
    half diameter: the origin need not be the centre of the smallest enclosing sphere (an L-bracket's is not), and
    decomposition pieces may stand slightly proud of the mesh."""
    points = [model.mesh.convex_hull.vertices] + [p.vertices for p in collision.pieces]
    radius = max(float(np.linalg.norm(p, axis=1).max()) for p in points)
    for prim in collision.primitives:
        if prim.kind == "box":
            corner_reach = float(np.linalg.norm(prim.size_m))
        else:
            corner_reach = float(np.hypot(prim.size_m[0], prim.size_m[1]))
        radius = max(radius, float(np.linalg.norm(prim.T_obj_geom[:3, 3])) + corner_reach)
    return radius


def _check_no_initial_contact(mj_model: mujoco.MjModel, data: mujoco.MjData) -> None:
    overlapping = [
        (int(data.contact.geom1[i]), int(data.contact.geom2[i])) for i in range(data.ncon) if data.contact.dist[i] < 0
    ]
    if overlapping:
        g1, g2 = overlapping[0]
        raise DropError(
            f"{len(overlapping)} contacts at t=0 (first: geom {mj_model.geom(g1).name or g1} with "
            f"{mj_model.geom(g2).name or g2}); spawning overlapping parts throws them out of the bin. "
            "This is a bug in the spawner: please report it with the scene and seed."
        )


def _body_poses(data: mujoco.MjData, n: int) -> np.ndarray:
    qpos = data.qpos.reshape(n, 7)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = qpos[:, :3]
    quat_xyzw = qpos[:, [4, 5, 6, 3]]
    finite = np.all(np.isfinite(quat_xyzw), axis=1) & (np.linalg.norm(quat_xyzw, axis=1) > 0)
    T[finite, :3, :3] = Rotation.from_quat(quat_xyzw[finite]).as_matrix()
    T[~finite] = np.nan
    return T


def _max_penetration(data: mujoco.MjData) -> float:
    if data.ncon == 0:
        return 0.0
    return float(max(0.0, -data.contact.dist[: data.ncon].min()))


def _escaped(T_world_obj: np.ndarray, c: ContainerSpec) -> list[int]:
    half = np.array(c.inner_size_m[:2]) / 2 + _INSIDE_TOLERANCE_M
    p = T_world_obj[:, :3, 3]
    outside = (np.abs(p[:, :2]) > half).any(axis=1) | (p[:, 2] < -_INSIDE_TOLERANCE_M)
    return [int(i) for i in np.flatnonzero(outside | ~np.isfinite(p).all(axis=1))]
