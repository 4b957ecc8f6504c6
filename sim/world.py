"""The simulated picking cell: a UR5e with a parallel gripper on a table, a bin, a place tray, parts and cameras.

Built with MuJoCo's MjSpec from the project's own UR5e description (``sygrid.robots.ur5e``: UR's DH and dynamic
parameters, cylinder geometry), so no model files are downloaded. The arm's joint bodies are placed from the DH
parameters, so the MuJoCo flange pose equals ``forward_kinematics(q)`` exactly.

Frames: the world origin is on the table top, z up. ``T_world_base`` places the robot's DH base frame (the frame
the controller reports poses in). ``T_world_bin`` is the bin frame: the centre of its inner floor, the same frame
that ``sygrid.physics`` drops parts in, so a drop's poses map into the cell as ``T_world_bin @ T_bin_obj``.

Arm control is computed torque: every 2 ms step, ``tau = M(q) (qdd_ref + Kp e + Kd de) + bias(q, qd)`` with the
mass matrix and the gravity/Coriolis forces of the model itself, limited to the UR5e joint torques. It tracks a
trajectory to well under a milliradian and reports real joint torques (gravity included) in ``arm_torque``.

Parts: MjSpec must be recompiled when bodies are added. ``add_parts`` does that in place, keeping the state of
everything already there (arm pose and targets, gripper, earlier parts), and replaces ``world.model`` and
``world.data``. Add parts before anything holds on to ``model``/``data`` (the camera re-binds itself).

Threads: ``world.lock`` (re-entrant) guards ``model`` and ``data``. Every method of this class takes it, so a 500 Hz
tick thread can call ``step`` while a camera thread renders: the camera holds the lock only while it copies the
scene (well under a millisecond), not while it rasterises.
"""

from __future__ import annotations

import logging
import threading

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from sim import gripper_model
from sim.cell_config import CellConfig
from sim.cell_model import ARM_BODY_NAMES, FLANGE_SITE, build_cell_spec
from sim.throw_watch import Throw, ThrowWatch
from sygrid.mjspec import add_part_body, quat_wxyz
from sygrid.objects.collision.geometry import CollisionModel
from sygrid.objects.model import ObjectModel
from sygrid.robots import gripper_2f85, ur5e
from sygrid.transforms import invert, is_rigid, make_T

log = logging.getLogger(__name__)

_PART_FRICTION = (0.5, 0.005, 0.0001)  # steel on steel / plastic: sliding 0.5
_PART_RGBA = (0.62, 0.63, 0.66, 1.0)
# qd targets further apart than this in time are not differentiated into an acceleration feed-forward.
_MAX_FEEDFORWARD_GAP_S = 0.05


class CellWorld:
    """The MuJoCo cell. See the module docstring for frames, control, parts and threading."""

    def __init__(self, config: CellConfig | None = None) -> None:
        self.config = config if config is not None else CellConfig()
        self.lock = threading.RLock()
        self._spec = self._build_spec()
        self._gripper = gripper_model.GripperController(self._gripper_names, self.config.timestep_s)
        self._part_names: list[str] = []
        self._throws = ThrowWatch()
        self.model = self._spec.compile()
        self.data = mujoco.MjData(self.model)
        self._bind()
        self._q_ref = np.array(ur5e.HOME_Q)
        self._qd_ref = np.zeros(6)
        self._qdd_ref = np.zeros(6)
        self._t_ref = 0.0
        self._gripper.reset(self.data, gripper_2f85.STROKE_M)
        self.reset_arm(ur5e.HOME_Q)

    # ------------------------------------------------------------------------------------------ time

    @property
    def dt_s(self) -> float:
        return float(self.model.opt.timestep)

    @property
    def time_s(self) -> float:
        return float(self.data.time)

    @property
    def T_world_base(self) -> np.ndarray:
        return self.config.T_world_base.copy()

    @property
    def T_world_bin(self) -> np.ndarray:
        return self.config.T_world_bin.copy()

    @property
    def T_flange_tcp(self) -> np.ndarray:
        """The gripper's tool centre point (pad centre) in the flange frame."""
        return np.array(gripper_2f85.T_FLANGE_TCP)

    def step(self, n: int = 1) -> None:
        """Advances ``n`` physics steps of ``dt_s``, running the arm and gripper controllers every step."""
        with self.lock:
            m, d = self.model, self.data
            for _ in range(n):
                mujoco.mj_step1(m, d)
                self._arm_control(m, d)
                self._gripper.apply(d)
                mujoco.mj_step2(m, d)
                self._throws.record(d)
            for throw in self._throws.check(m, d):
                log.warning("%s: the physics threw it; its pose is not to be trusted", throw.describe())

    @property
    def thrown_parts(self) -> dict[str, tuple[float, float]]:
        """Parts the physics threw (faster than ``sim.throw_watch.MAX_PLAUSIBLE_PART_SPEED_M_S``): name -> (time
        [s], speed [m/s]) when first seen; their poses are not to be trusted after that (``throws``: why)."""
        return {name: (t.time_s, t.speed_m_s) for name, t in self._throws.thrown.items()}

    @property
    def throws(self) -> list[Throw]:
        """The thrown parts with what the kept history says of the cause (``sim.throw_watch.Throw``)."""
        return list(self._throws.thrown.values())

    # ------------------------------------------------------------------------------------------ arm

    def set_arm_target(self, q: np.ndarray, qd: np.ndarray | None = None, qdd: np.ndarray | None = None) -> None:
        """The joint reference at the current time: position (rad), velocity (rad/s, default 0) and acceleration
        (rad/s^2; default: the change of ``qd`` since the previous call, or 0). Between calls the reference moves
        on at ``qd``. Call it once per controller tick for trajectory tracking."""
        q = _check_vector("q", q)
        lo, hi = ur5e.JOINT_LIMITS_RAD[:, 0], ur5e.JOINT_LIMITS_RAD[:, 1]
        if np.any(q < lo - 1e-9) or np.any(q > hi + 1e-9):
            raise ValueError(f"target q {q.tolist()} is outside the joint limits {ur5e.JOINT_LIMITS_RAD.tolist()}")
        qd = np.zeros(6) if qd is None else _check_vector("qd", qd)
        with self.lock:
            t = self.time_s
            if qdd is not None:
                qdd = _check_vector("qdd", qdd)
            elif 0.0 < t - self._t_ref <= _MAX_FEEDFORWARD_GAP_S:
                qdd = (qd - self._qd_ref) / (t - self._t_ref)
            else:
                qdd = np.zeros(6)
            limit = 4.0 * np.asarray(ur5e.MAX_JOINT_ACCEL_RAD_S2)
            self._q_ref, self._qd_ref, self._qdd_ref = q.copy(), qd.copy(), np.clip(qdd, -limit, limit)
            self._t_ref = t

    def reset_arm(self, q: np.ndarray) -> None:
        """Puts the arm at ``q`` at rest, with that as its target (no dynamics; for set-up and tests)."""
        q = _check_vector("q", q)
        with self.lock:
            self.data.qpos[self._arm_qadr] = q
            self.data.qvel[self._arm_dofadr] = 0.0
            self._q_ref, self._qd_ref, self._qdd_ref, self._t_ref = q.copy(), np.zeros(6), np.zeros(6), self.time_s
            mujoco.mj_forward(self.model, self.data)

    def arm_q(self) -> np.ndarray:
        with self.lock:
            return self.data.qpos[self._arm_qadr].copy()

    def arm_qd(self) -> np.ndarray:
        with self.lock:
            return self.data.qvel[self._arm_dofadr].copy()

    def arm_torque(self) -> np.ndarray:
        """Joint motor torques of the last step (N m), gravity and friction compensation included."""
        with self.lock:
            return self.data.actuator_force[self._arm_actuators].copy()

    def arm_target(self) -> tuple[np.ndarray, np.ndarray]:
        """The current joint reference (q, qd)."""
        with self.lock:
            return self._reference(self.time_s)[:2]

    def T_base_flange(self) -> np.ndarray:
        """The flange pose in the robot base frame, from MuJoCo's kinematics of the current joint state."""
        with self.lock:
            mujoco.mj_kinematics(self.model, self.data)
            T_world_flange = make_T(
                self.data.site_xmat[self._flange_site].reshape(3, 3), self.data.site_xpos[self._flange_site]
            )
        return invert(self.config.T_world_base) @ T_world_flange

    def arm_collision_force_n(self) -> float:
        """Largest contact normal force (N) between an arm or gripper geom and the table, bin, tray or robot base,
        or between two arm links, in the last step. Contacts with parts are never collisions."""
        return self.arm_collision()[0]

    def arm_collision(self) -> tuple[float, str]:
        """``arm_collision_force_n`` and the two geoms of that contact (``"geom_a / geom_b"``; "" without one),
        so a protective stop can say what hit what."""
        with self.lock:
            m, d = self.model, self.data
            n = d.ncon
            if n == 0:
                return 0.0, ""
            g1, g2 = d.contact.geom1[:n], d.contact.geom2[:n]
            arm, env = self._geom_is_arm, self._geom_is_env
            hit = (arm[g1] & (env[g2] | arm[g2])) | (arm[g2] & env[g1])
            force = np.zeros(6)
            largest, pair = 0.0, ""
            for i in np.flatnonzero(hit):
                mujoco.mj_contactForce(m, d, int(i), force)
                if force[0] > largest:
                    largest = float(force[0])
                    pair = f"{_geom_name(m, int(g1[i]))} / {_geom_name(m, int(g2[i]))}"
            return largest, pair

    def tool_wrench(self) -> np.ndarray:
        """(6,) the contact wrench that everything else (parts, bin, table, other links) exerts on the gripper in
        the last step, in the robot base frame: force [N], then torque [N m] about the flange origin. What a
        force/torque sensor between the flange and the gripper reads with its payload compensated (zero in free
        space); contacts between the gripper's own bodies are internal and left out."""
        with self.lock:
            m, d = self.model, self.data
            wrench = np.zeros(6)
            n = d.ncon
            if n == 0:
                return wrench
            tool = self._geom_is_tool
            g1, g2 = d.contact.geom1[:n], d.contact.geom2[:n]
            p_flange = d.site_xpos[self._flange_site]
            f = np.zeros(6)
            for i in np.flatnonzero(tool[g1] != tool[g2]):
                mujoco.mj_contactForce(m, d, int(i), f)
                # contact frame rows: normal (from geom1 to geom2), tangents; the force acts on geom2, -f on geom1
                force = d.contact.frame[i].reshape(3, 3).T @ f[:3]
                if tool[g1[i]]:
                    force = -force
                wrench[:3] += force
                wrench[3:] += np.cross(d.contact.pos[i] - p_flange, force)
            R_base_world = self.config.T_world_base[:3, :3].T
            return np.concatenate([R_base_world @ wrench[:3], R_base_world @ wrench[3:]])

    # ------------------------------------------------------------------------------------------ gripper

    def set_gripper(self, width_m: float, speed_m_s: float, force_n: float) -> None:
        """Moves the fingers to ``width_m`` (0..0.085) at ``speed_m_s`` (0.02..0.15) squeezing with at most
        ``force_n`` per pad (20..235 N)."""
        with self.lock:
            self._gripper.command(self.model, width_m, speed_m_s, force_n)

    def gripper_width_m(self) -> float:
        with self.lock:
            return self._gripper.width_m(self.data)

    def gripper_moving(self) -> bool:
        with self.lock:
            return self._gripper.moving(self.data)

    def gripper_object_detected(self) -> bool:
        """The fingers were stopped by contact before reaching the commanded width."""
        with self.lock:
            return self._gripper.object_detected(self.data)

    # ------------------------------------------------------------------------------------------ parts

    def add_parts(
        self,
        models: list[ObjectModel],
        T_world_obj: np.ndarray,
        collision: list[CollisionModel] | None = None,
    ) -> list[str]:
        """Adds one free body per entry of ``models`` at ``T_world_obj`` ((n, 4, 4)) and recompiles in place.

        ``collision[i]`` is part i's collision model (``sygrid.objects.collision``: the same tiers the generator's
        drop uses); the part is then drawn with its true mesh. Without one the mesh itself is the collision geom
        (convexified by MuJoCo). Mass and inertia come from the repaired solid (``ObjectModel.solid``) and the
        model's density.
        Returns the new bodies' names.
        """
        T_world_obj = np.asarray(T_world_obj, dtype=float)
        if T_world_obj.shape != (len(models), 4, 4):
            raise ValueError(
                f"T_world_obj must be ({len(models)}, 4, 4) for {len(models)} models, got {T_world_obj.shape}"
            )
        bad = [i for i, T in enumerate(T_world_obj) if not is_rigid(T)]
        if bad:
            raise ValueError(f"T_world_obj[{bad[0]}] is not a rigid transform: {T_world_obj[bad[0]].tolist()}")
        if collision is not None and len(collision) != len(models):
            raise ValueError(f"collision must have one model per part ({len(models)}), got {len(collision)}")
        collision = list(collision) if collision is not None else [None] * len(models)
        for model in models:
            if not model.mass_kg > 0.0:
                raise ValueError(f"part {model.name!r} has no volume (mass {model.mass_kg} kg): it cannot be simulated")
        with self.lock:
            added: list[mujoco.MjsBody] = []
            meshes_before = {mesh.name for mesh in self._spec.meshes}
            solref, friction = [2.0 * self.config.timestep_s, 1.0], list(_PART_FRICTION)
            try:
                for model, T, coll in zip(models, T_world_obj, collision, strict=True):
                    name = f"part{len(self._part_names) + len(added)}_{safe_name(model.name)}"
                    added.append(add_part_body(self._spec, name, model, coll, T, solref, friction, _PART_RGBA))
                self.model, self.data = self._recompile()
            except Exception:  # leave the spec as it was, so the world stays usable
                for body in added:
                    self._spec.delete(body)
                for mesh in [m for m in self._spec.meshes if m.name not in meshes_before]:
                    self._spec.delete(mesh)
                raise
            names = [body.name for body in added]
            self._part_names += names
            self._bind()
            self._warn_on_initial_overlap(names)
        log.info("added %d parts (%d in the cell)", len(names), len(self._part_names))
        return names

    def part_names(self) -> list[str]:
        return list(self._part_names)

    def part_poses(self) -> np.ndarray:
        """(n, 4, 4) ``T_world_obj`` of every part, in the order added."""
        with self.lock:
            qpos = self.data.qpos[self._part_qadr.reshape(-1, 1) + np.arange(7)].reshape(-1, 7)
        T = np.tile(np.eye(4), (len(qpos), 1, 1))
        T[:, :3, 3] = qpos[:, :3]
        if len(qpos):
            T[:, :3, :3] = Rotation.from_quat(qpos[:, [4, 5, 6, 3]]).as_matrix()
        return T

    def set_part_poses(self, T_world_obj: np.ndarray) -> None:
        """Teleports every part to ``T_world_obj`` ((n, 4, 4)) at rest (for set-up and tests)."""
        T_world_obj = np.asarray(T_world_obj, dtype=float)
        if T_world_obj.shape != (len(self._part_names), 4, 4):
            raise ValueError(f"expected ({len(self._part_names)}, 4, 4) poses, got {T_world_obj.shape}")
        with self.lock:
            for k, T in enumerate(T_world_obj):
                adr = self._part_qadr[k]
                self.data.qpos[adr : adr + 3] = T[:3, 3]
                self.data.qpos[adr + 3 : adr + 7] = quat_wxyz(T[:3, :3])
                self.data.qvel[self._part_dofadr[k] : self._part_dofadr[k] + 6] = 0.0
            mujoco.mj_forward(self.model, self.data)

    def sync_kinematics(self) -> None:
        """Brings body, geom and camera poses up to the current joint state (a physics step leaves them one step
        behind). Renderers call it before copying the scene."""
        with self.lock:
            mujoco.mj_kinematics(self.model, self.data)
            mujoco.mj_camlight(self.model, self.data)

    # ------------------------------------------------------------------------------------------ internals

    def _reference(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        dt = t - self._t_ref
        q = self._q_ref + self._qd_ref * dt + 0.5 * self._qdd_ref * dt * dt if dt > 0 else self._q_ref
        qd = self._qd_ref + self._qdd_ref * dt if dt > 0 else self._qd_ref
        if dt > _MAX_FEEDFORWARD_GAP_S:  # a stale reference holds its velocity, it does not keep accelerating
            q = self._q_ref + self._qd_ref * dt
            qd = self._qd_ref
        limits = ur5e.JOINT_LIMITS_RAD
        return np.clip(q, limits[:, 0], limits[:, 1]), qd, self._qdd_ref

    def _arm_control(self, m: mujoco.MjModel, d: mujoco.MjData) -> None:
        q_ref, qd_ref, qdd_ref = self._reference(float(d.time))
        q, qd = d.qpos[self._arm_qadr], d.qvel[self._arm_dofadr]
        qdd = qdd_ref + self._kp * (q_ref - q) + self._kd * (qd_ref - qd)
        self._acc[:] = 0.0
        self._acc[self._arm_dofadr] = qdd
        mujoco.mj_mulM(m, d, self._mass_times_acc, self._acc)
        tau = self._mass_times_acc[self._arm_dofadr] + d.qfrc_bias[self._arm_dofadr] + self._damping * qd
        d.ctrl[self._arm_actuators] = tau

    def _build_spec(self) -> mujoco.MjSpec:
        spec, self._gripper_names = build_cell_spec(self.config)
        return spec

    def _recompile(self) -> tuple[mujoco.MjModel, mujoco.MjData]:
        forcerange = self.model.actuator_forcerange.copy()
        model, data = self._spec.recompile(self.model, self.data)
        model.actuator_forcerange[: len(forcerange)] = forcerange  # the gripper's force setting is runtime state
        mujoco.mj_forward(model, data)
        return model, data

    def _warn_on_initial_overlap(self, names: list[str]) -> None:
        new_bodies = {self.model.body(n).id for n in names}
        d = self.data
        overlapping = [
            i
            for i in range(d.ncon)
            if d.contact.dist[i] < -1e-4
            and (
                self.model.geom_bodyid[d.contact.geom1[i]] in new_bodies
                or self.model.geom_bodyid[d.contact.geom2[i]] in new_bodies
            )
        ]
        if overlapping:
            log.warning(
                "%d contacts of new parts penetrate by more than 0.1 mm at t=%.3f s; overlapping parts are "
                "thrown apart when the world steps",
                len(overlapping),
                self.time_s,
            )

    def _bind(self) -> None:
        m = self.model
        joints = [m.joint(n) for n in ur5e.JOINT_NAMES]
        self._arm_qadr = np.array([int(j.qposadr[0]) for j in joints])
        self._arm_dofadr = np.array([int(j.dofadr[0]) for j in joints])
        self._arm_actuators = np.array([m.actuator(n).id for n in ur5e.JOINT_NAMES])
        self._flange_site = m.site(FLANGE_SITE).id
        self._damping = m.dof_damping[self._arm_dofadr].copy()
        bandwidth = self.config.arm_bandwidth_rad_s
        self._kp, self._kd = bandwidth**2, 2.0 * bandwidth
        self._acc = np.zeros(m.nv)
        self._mass_times_acc = np.zeros(m.nv)
        arm_bodies = {m.body(n).id for n in ARM_BODY_NAMES} | {m.body(self._gripper_names.body).id}
        arm_bodies |= {m.body(n).id for n in self._gripper_names.finger_bodies}
        env_bodies = {m.body(n).id for n in ("table", "bin", "tray", "robot_base")}
        tool_bodies = {m.body(n).id for n in (self._gripper_names.body, *self._gripper_names.finger_bodies)}
        self._geom_is_tool = np.isin(m.geom_bodyid, list(tool_bodies))
        self._geom_is_arm = np.isin(m.geom_bodyid, list(arm_bodies))
        self._geom_is_env = np.isin(m.geom_bodyid, list(env_bodies))
        parts = [m.joint(f"{n}_free") for n in self._part_names]
        self._part_qadr = np.array([int(j.qposadr[0]) for j in parts], dtype=int)
        self._part_dofadr = np.array([int(j.dofadr[0]) for j in parts], dtype=int)
        self._throws.bind(m, self._part_names, self._part_dofadr)
        self._gripper.bind(m)


def _check_vector(name: str, v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    if v.shape != (6,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be 6 finite numbers (one per joint {list(ur5e.JOINT_NAMES)}), got {v!r}")
    return v


def safe_name(name: str) -> str:
    """``name`` with every character MuJoCo names should not hold replaced by ``_`` (part bodies are
    ``part{k}_{safe_name(model.name)}``)."""
    return "".join(c if c.isalnum() or c in "_-" else "_" for c in name)


def _geom_name(model: mujoco.MjModel, geom: int) -> str:
    """The geom's name, else its body's name with the geom index (mesh pieces are often unnamed)."""
    name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, geom)
    if name:
        return name
    body = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.geom_bodyid[geom]))
    return f"{body or 'body'}#{geom}"
