"""A two-finger parallel gripper like the Robotiq 2F-85, built into an MjSpec, and its finger controller.

Mechanics: two fingers on slide joints along the flange x axis, mirrored; an equality constraint keeps them
symmetric (the real gripper's single motor and linkage do the same), and a fixed tendon measures the opening
``width = q_a + q_b`` (the distance between the pads). A stiff position servo on that tendon follows a set point
that moves towards the commanded width at the commanded speed; its force is limited to the commanded grip force
(force on each pad, N). When a part stops the fingers the set point runs on to the commanded width, the servo
saturates and squeezes with the grip force (unless the part is within ``force_n / kp`` of the commanded width,
about 2 mm at full force). Grasps hold only by contact and friction (rubber-like pads, friction 1.0, torsional
friction on). The drive's reflected inertia is an armature on the finger joints (non-backdrivable in reality).

Geometry: ``sygrid.robots.gripper_2f85`` (the planner's collision boxes are built from the same numbers), placed in
the flange frame (z out of the flange, x along the line between the pads): a coupling, the housing, and per finger
a pad and a finger link. The TCP is the pad centre, ``gripper_2f85.T_FLANGE_TCP``.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from sygrid.robots import gripper_2f85

MIN_FORCE_N, MAX_FORCE_N = gripper_2f85.FORCE_RANGE_N
MIN_SPEED_M_S, MAX_SPEED_M_S = gripper_2f85.SPEED_RANGE_M_S
MASS_KG = 0.925
PAD_FRICTION = 1.0

# Servo: position gain (N/m) and damping (N s/m) on the width; with the armature below it is critically damped
# and stable at a 2 ms step.
_SERVO_KP_N_M = 1.0e5
_SERVO_KV_N_S_M = 700.0
_FINGER_MASS_KG = 0.05
_FINGER_ARMATURE_KG = 0.5
# Status thresholds.
_MOVING_SPEED_M_S = 0.002
_CREEP_SPEED_M_S = 0.005  # a quarter of the slowest commanded speed (20 mm/s)
_POSITION_TOL_M = 0.0015

_HOUSING_RGBA = (0.15, 0.15, 0.17, 1.0)
_PAD_RGBA = (0.25, 0.25, 0.28, 1.0)


@dataclass(frozen=True)
class GripperNames:
    """Names of the MjSpec elements the gripper adds (prefixed), for binding after compile."""

    body: str
    finger_bodies: tuple[str, str]
    finger_joints: tuple[str, str]
    tendon: str
    actuator: str


def add_gripper(
    spec: mujoco.MjSpec, flange_body: mujoco.MjsBody, pad_solref: list[float], prefix: str = "gripper"
) -> GripperNames:
    """Adds the gripper to ``flange_body`` (a body whose frame is the flange frame) and returns its names.

    ``pad_solref``: contact time constant and damping ratio of the pads; stiff ([2 dt, 1]) so that a squeezed
    part is not pressed into them."""
    names = GripperNames(
        body=prefix,
        finger_bodies=(f"{prefix}_finger_a", f"{prefix}_finger_b"),
        finger_joints=(f"{prefix}_finger_a_joint", f"{prefix}_finger_b_joint"),
        tendon=f"{prefix}_width",
        actuator=f"{prefix}_servo",
    )
    body = flange_body.add_body(name=names.body)
    body.explicitinertial = True
    body.mass = MASS_KG - 2 * _FINGER_MASS_KG
    body.ipos = [0.0, 0.0, 0.06]
    body.inertia = [1.2e-3, 1.2e-3, 8e-4]
    box, cyl = mujoco.mjtGeom.mjGEOM_BOX, mujoco.mjtGeom.mjGEOM_CYLINDER
    g = gripper_2f85
    coupling = [0, 0, 0, 0, 0, g.COUPLING_LENGTH_M]
    body.add_geom(
        name=f"{prefix}_coupling", type=cyl, fromto=coupling, size=[g.COUPLING_RADIUS_M, 0, 0], rgba=_HOUSING_RGBA
    )
    housing_z, housing_half_z = _flange_z_span(g.HOUSING_Z_RANGE_M)
    housing_size = [*g.HOUSING_HALF_XY_M, housing_half_z]
    body.add_geom(name=f"{prefix}_housing", type=box, pos=[0, 0, housing_z], size=housing_size, rgba=_HOUSING_RGBA)
    link_z, link_half_z = _flange_z_span(g.LINK_Z_RANGE_M)

    for k, sign in enumerate((1.0, -1.0)):
        finger = body.add_body(name=names.finger_bodies[k])
        finger.explicitinertial = True
        finger.mass = _FINGER_MASS_KG
        finger.ipos = [sign * 0.012, 0.0, 0.14]
        finger.inertia = [1e-5, 1e-5, 4e-6]
        finger.add_joint(
            name=names.finger_joints[k],
            type=mujoco.mjtJoint.mjJNT_SLIDE,
            axis=[sign, 0.0, 0.0],
            range=[0.0, gripper_2f85.STROKE_M / 2],
            limited=mujoco.mjtLimited.mjLIMITED_TRUE,
            armature=_FINGER_ARMATURE_KG,
            damping=1.0,
        )
        # Pad: inner face at x = sign * q (the finger's joint position), so width = q_a + q_b.
        finger.add_geom(
            name=f"{names.finger_bodies[k]}_pad",
            type=box,
            pos=[sign * g.PAD_THICKNESS_M / 2, 0, g.TCP_OFFSET_M],
            size=[g.PAD_THICKNESS_M / 2, g.PAD_WIDTH_M / 2, g.PAD_LENGTH_M / 2],
            friction=[PAD_FRICTION, 0.005, 0.0001],
            condim=4,
            solref=pad_solref,
            rgba=_PAD_RGBA,
        )
        finger.add_geom(
            name=f"{names.finger_bodies[k]}_link",
            type=box,
            pos=[sign * (g.PAD_THICKNESS_M + g.LINK_THICKNESS_M / 2), 0, link_z],
            size=[g.LINK_THICKNESS_M / 2, g.LINK_WIDTH_M / 2, link_half_z],
            rgba=_HOUSING_RGBA,
        )

    tendon = spec.add_tendon(name=names.tendon)
    tendon.wrap_joint(names.finger_joints[0], 1.0)
    tendon.wrap_joint(names.finger_joints[1], 1.0)
    spec.add_equality(
        type=mujoco.mjtEq.mjEQ_JOINT,
        name1=names.finger_joints[0],
        name2=names.finger_joints[1],
        data=[0.0, 1.0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0],
        solref=[0.005, 1.0],
    )
    servo = spec.add_actuator(name=names.actuator, trntype=mujoco.mjtTrn.mjTRN_TENDON, target=names.tendon)
    servo.set_to_position(kp=_SERVO_KP_N_M, kv=_SERVO_KV_N_S_M)
    servo.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
    servo.forcerange = [-MAX_FORCE_N, MAX_FORCE_N]
    servo.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
    servo.ctrlrange = [0.0, gripper_2f85.STROKE_M]
    spec.add_exclude(bodyname1=names.finger_bodies[0], bodyname2=names.finger_bodies[1])
    return names


class GripperController:
    """Runtime side of the gripper: the command (width, speed, force), the servo law and the status bits.

    ``bind`` must be called after every compile; ``apply`` once per physics step, before integration.
    """

    def __init__(self, names: GripperNames, dt_s: float) -> None:
        self.names = names
        self._dt_s = dt_s
        self._target_width_m = gripper_2f85.STROKE_M
        self._setpoint_m = 0.0  # the servo's moving set point; starts closed, like the compiled model
        self._restart_from_width = False
        self._speed_m_s = MAX_SPEED_M_S
        self._force_n = MAX_FORCE_N
        self._qadr = np.zeros(2, dtype=int)
        self._dofadr = np.zeros(2, dtype=int)
        self._actuator_id = -1
        self._pad_geoms: frozenset[int] = frozenset()
        self._is_finger_geom = np.zeros(0, dtype=bool)

    def bind(self, model: mujoco.MjModel) -> None:
        joints = [model.joint(n) for n in self.names.finger_joints]
        self._qadr = np.array([int(j.qposadr[0]) for j in joints])
        self._dofadr = np.array([int(j.dofadr[0]) for j in joints])
        self._actuator_id = model.actuator(self.names.actuator).id
        finger_ids = [model.body(n).id for n in self.names.finger_bodies]
        self._is_finger_geom = np.isin(model.geom_bodyid, finger_ids)
        self._pad_geoms = frozenset(int(g) for g in np.flatnonzero(self._is_finger_geom))
        model.actuator_forcerange[self._actuator_id] = [-self._force_n, self._force_n]

    def command(self, model: mujoco.MjModel, width_m: float, speed_m_s: float, force_n: float) -> None:
        """Moves the fingers to ``width_m`` at ``speed_m_s``, squeezing with at most ``force_n`` per pad."""
        _check_range("width_m", width_m, 0.0, gripper_2f85.STROKE_M)
        _check_range("speed_m_s", speed_m_s, MIN_SPEED_M_S, MAX_SPEED_M_S)
        _check_range("force_n", force_n, MIN_FORCE_N, MAX_FORCE_N)
        self._target_width_m, self._speed_m_s, self._force_n = float(width_m), float(speed_m_s), float(force_n)
        model.actuator_forcerange[self._actuator_id] = [-self._force_n, self._force_n]
        self._restart_from_width = True

    def apply(self, data: mujoco.MjData) -> None:
        if self._restart_from_width:
            # A new request starts from where the fingers are: after squeezing a part the set point lies at the
            # closed end, and opening from there kept the servo stalled (reported as "stopped on an object while
            # opening") until the set point had travelled back up to the part's width.
            self._setpoint_m = float(np.clip(self.width_m(data), 0.0, gripper_2f85.STROKE_M))
            self._restart_from_width = False
        step = self._speed_m_s * self._dt_s
        self._setpoint_m += float(np.clip(self._target_width_m - self._setpoint_m, -step, step))
        data.ctrl[self._actuator_id] = self._setpoint_m

    def reset(self, data: mujoco.MjData, width_m: float) -> None:
        """Puts the fingers at ``width_m`` at rest, commanded to stay there."""
        _check_range("width_m", width_m, 0.0, gripper_2f85.STROKE_M)
        data.qpos[self._qadr] = width_m / 2
        data.qvel[self._dofadr] = 0.0
        self._target_width_m = self._setpoint_m = float(width_m)

    def width_m(self, data: mujoco.MjData) -> float:
        return float(data.qpos[self._qadr].sum())

    def speed_m_s(self, data: mujoco.MjData) -> float:
        return float(data.qvel[self._dofadr].sum())

    @property
    def target_width_m(self) -> float:
        return self._target_width_m

    @property
    def force_n(self) -> float:
        return self._force_n

    def moving(self, data: mujoco.MjData) -> bool:
        """The fingers are moving, or about to: the set point still travels and the servo is not stalled. A servo
        at its force limit whose fingers touch something and only creep (below ``_CREEP_SPEED_M_S``) is stalled:
        MuJoCo's soft friction lets pads pressed on a surface slide slowly where a real gripper's stick, and its
        firmware reports them stopped. (Without a contact, a servo at its limit is accelerating.)"""
        speed = abs(self.speed_m_s(data))
        # at its force limit pushing towards the target (a squeeze that a new opening request has not yet relieved
        # pushes the other way: that is no stall)
        force = float(data.actuator_force[self._actuator_id])
        stalled = abs(force) >= 0.99 * self._force_n and force * (self._target_width_m - self.width_m(data)) > 0
        if stalled and speed < _CREEP_SPEED_M_S and self._touching(data):
            return False
        if speed > _MOVING_SPEED_M_S:
            return True
        return self._setpoint_m != self._target_width_m and not stalled

    def object_detected(self, data: mujoco.MjData) -> bool:
        """The fingers stopped short of the target (by more than 1.5 mm) while a pad touches something."""
        if self.moving(data):
            return False
        if abs(self._target_width_m - self.width_m(data)) <= _POSITION_TOL_M:
            return False
        return self._touching(data)

    def _touching(self, data: mujoco.MjData) -> bool:
        """A finger (pad or link) is in contact with something."""
        n = data.ncon
        touching = self._is_finger_geom[data.contact.geom1[:n]] | self._is_finger_geom[data.contact.geom2[:n]]
        return bool(touching.any())

    @property
    def pad_geoms(self) -> frozenset[int]:
        """Geom ids of both fingers (pads and links)."""
        return self._pad_geoms


def _flange_z_span(z_range_tcp_m: tuple[float, float]) -> tuple[float, float]:
    """A z span given in the TCP frame as the centre (flange frame) and half length of a geom. The dimensions are
    whole micrometres: rounding to the nanometre drops the float error of the frame change."""
    lo, hi = z_range_tcp_m
    return round(gripper_2f85.TCP_OFFSET_M + (lo + hi) / 2, 9), round((hi - lo) / 2, 9)


def _check_range(name: str, value: float, lo: float, hi: float) -> None:
    if not (lo - 1e-9 <= float(value) <= hi + 1e-9):
        raise ValueError(f"gripper {name} must be in [{lo}, {hi}], got {value}")
