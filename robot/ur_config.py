"""What ``robot.ur`` may do: the robot's configuration, the workspace box, and the checks every motion passes
before anything is sent (pure functions of the configuration and the kinematics).

Workspace rule: the TCP origin must be inside the box at the target, and along the path from the first point that
is inside (a motion may bring the TCP into the box, never take it out). ``move_l``: the box is convex, so a straight
line between two points inside stays inside and only the target is checked. ``move_j``: ``movej`` follows a straight
line in joint space; it is sampled every ``path_check_step_rad`` and each sample's TCP is checked. Only the TCP
origin is checked, not the links or the tool's extent.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from robot.ur_errors import MotionRefusedError, OutsideWorkspaceError
from sygrid.errors import ConfigError
from sygrid.robots import ur5e
from sygrid.robots.kinematics import forward_kinematics
from sygrid.transforms import is_rigid

__all__ = [
    "URConfig",
    "WorkspaceBox",
    "check_joint_path",
    "check_joint_target",
    "check_rate",
    "check_rigid",
    "check_target_in_workspace",
    "trapezoid_duration_s",
]


@dataclass(frozen=True, eq=False)
class WorkspaceBox:
    """An axis-aligned box in the robot base frame (m) that a frame's origin must stay inside: the TCP for motion
    (``URConfig.workspace``), the flange for calibration pose sets (``robot.calibration``)."""

    lo_m: tuple[float, float, float]
    hi_m: tuple[float, float, float]

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.lo_m, dtype=float), np.asarray(self.hi_m, dtype=float)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo)) or not np.all(lo < hi):
            raise ConfigError(f"WorkspaceBox needs finite lo_m < hi_m on x, y and z, got {self.lo_m}, {self.hi_m}")
        object.__setattr__(self, "lo_m", tuple(float(v) for v in lo))
        object.__setattr__(self, "hi_m", tuple(float(v) for v in hi))

    def contains(self, p_m: np.ndarray) -> np.ndarray | bool:
        """Whether points (3,) or (n, 3) lie inside (boundary included)."""
        p = np.asarray(p_m, dtype=float)
        inside = np.all((p >= self.lo_m) & (p <= self.hi_m), axis=-1)
        return bool(inside) if inside.ndim == 0 else inside

    def joint_path_exit(
        self, T_flange_tcp: np.ndarray, q_from: np.ndarray, q_to: np.ndarray, step_rad: float
    ) -> tuple[float, np.ndarray] | None:
        """Where the TCP (``T_flange_tcp``) leaves the box along the joint-space line from ``q_from`` to ``q_to``
        (movej's path, sampled every ``step_rad`` on the joint that turns most), or ends outside it: ``(fraction of
        the path, TCP position [m])`` of the first such sample; None when the path stays inside. A path may enter
        the box (from a pose outside it), never leave it."""
        q_from, q_to = np.asarray(q_from, dtype=float), np.asarray(q_to, dtype=float)
        n = max(2, math.ceil(float(np.max(np.abs(q_to - q_from))) / step_rad) + 1)
        s = np.linspace(0.0, 1.0, n)[:, None]
        p = forward_kinematics(q_from + s * (q_to - q_from), T_flange_tcp)[:, :3, 3]
        inside = self.contains(p)
        bad = np.flatnonzero(np.maximum.accumulate(inside) & ~inside)
        if inside[-1] and not len(bad):
            return None
        k = int(bad[0]) if len(bad) else n - 1
        return k / (n - 1), p[k]

    def describe(self) -> str:
        return "x {:.3f}..{:.3f}, y {:.3f}..{:.3f}, z {:.3f}..{:.3f} m".format(
            *(v for pair in zip(self.lo_m, self.hi_m, strict=True) for v in pair)
        )


@dataclass(frozen=True, eq=False)
class URConfig:
    """How to reach the robot and what motion is allowed.

    Motion defaults (``joint_speed_rad_s`` ...) are used when a call passes none; the maxima are hard limits that a
    call may not exceed. ``T_flange_tcp`` is set as the controller's TCP on connect and after every program
    restart; poses and the workspace check refer to that TCP.
    """

    host: str
    workspace: WorkspaceBox
    T_flange_tcp: np.ndarray = field(default_factory=lambda: np.eye(4))
    #: RTDE rate (Hz); None: the controller's default (500 Hz on e-Series, 125 Hz on CB3).
    rtde_frequency_hz: float | None = None
    #: Bound on each connection step that would otherwise block (RTDE handshake, dashboard connect).
    connect_timeout_s: float = 2.0
    #: How long to wait for the control script to run after an upload.
    program_start_timeout_s: float = 5.0
    #: Bound on ``recover()``; includes the controller's unlock delay (5 s after a protective stop on e-Series).
    recovery_timeout_s: float = 12.0
    joint_speed_rad_s: float = 1.05
    joint_accel_rad_s2: float = 1.4
    linear_speed_m_s: float = 0.25
    linear_accel_m_s2: float = 1.2
    max_joint_speed_rad_s: float = float(ur5e.MAX_JOINT_SPEED_RAD_S[0])
    max_joint_accel_rad_s2: float = 10.0
    max_linear_speed_m_s: float = 1.0
    max_linear_accel_m_s2: float = 5.0
    #: (6, 2) rad; None: ``ur5e.JOINT_LIMITS_RAD``. Targets must keep ``joint_limit_margin_rad`` from them.
    joint_limits_rad: np.ndarray | None = None
    joint_limit_margin_rad: float = 0.0
    #: Joint-space sampling step of the move_j workspace check.
    path_check_step_rad: float = 0.02
    #: A motion fails when it takes longer than factor * (trapezoid duration / speed scaling) + margin.
    motion_timeout_factor: float = 2.0
    motion_timeout_margin_s: float = 2.0
    #: The link counts as lost when the controller timestamp has not advanced for this long.
    stale_state_timeout_s: float = 0.5
    #: Force-limited motion (``robot.ur_force``): the fastest move until contact or press, and the largest press.
    max_contact_speed_m_s: float = 0.05
    max_press_force_n: float = 40.0
    #: Decelerations of ``stop()``.
    stop_decel_rad_s2: float = 4.0
    stop_decel_m_s2: float = 2.0
    #: Deceleration of a guarded linear move stopped on a contact (``move_l(max_force_n=...)``): short, as the
    #: force grows with every millimetre travelled into what was met (the controller's own stopL default).
    contact_stop_decel_m_s2: float = 10.0
    #: Reconnect by itself before a motion when the link is down (nothing is in flight then).
    auto_reconnect: bool = True
    #: Re-upload the control script before a motion when it stopped without a safety stop (a script error, a
    #: watchdog, a dashboard stop). Protective stops always need an explicit ``recover()``.
    restart_stopped_program: bool = True
    #: Use RTDE input/output registers 24-47 (when another RTDE client uses 0-23).
    upper_range_registers: bool = False
    #: Stop the control script on ``close()`` (ur_rtde leaves it running otherwise).
    stop_script_on_close: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.host, str) or not self.host:
            raise ConfigError(f"URConfig.host must be a non-empty address, got {self.host!r}")
        if not isinstance(self.workspace, WorkspaceBox):
            raise ConfigError(f"URConfig.workspace must be a WorkspaceBox, got {type(self.workspace).__name__}")
        T = np.array(self.T_flange_tcp, dtype=float)
        if T.shape != (4, 4) or not is_rigid(T):
            raise ConfigError(f"URConfig.T_flange_tcp must be a 4x4 rigid transform, got {T.tolist()}")
        T.flags.writeable = False
        object.__setattr__(self, "T_flange_tcp", T)
        limits = np.array(ur5e.JOINT_LIMITS_RAD if self.joint_limits_rad is None else self.joint_limits_rad, float)
        if limits.shape != (6, 2) or np.any(limits[:, 0] >= limits[:, 1]):
            raise ConfigError(f"URConfig.joint_limits_rad must be (6, 2) [lower, upper] rad, got {limits.tolist()}")
        limits.flags.writeable = False
        object.__setattr__(self, "joint_limits_rad", limits)
        positive = (
            "connect_timeout_s", "program_start_timeout_s", "recovery_timeout_s", "joint_speed_rad_s",
            "joint_accel_rad_s2", "linear_speed_m_s", "linear_accel_m_s2", "max_joint_speed_rad_s",
            "max_joint_accel_rad_s2", "max_linear_speed_m_s", "max_linear_accel_m_s2", "path_check_step_rad",
            "motion_timeout_factor", "stale_state_timeout_s", "stop_decel_rad_s2", "stop_decel_m_s2",
            "max_contact_speed_m_s", "max_press_force_n", "contact_stop_decel_m_s2",
        )  # fmt: skip
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ConfigError(f"URConfig.{name} must be a positive number, got {value!r}")
        for name in ("joint_limit_margin_rad", "motion_timeout_margin_s"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ConfigError(f"URConfig.{name} must be a number >= 0, got {value!r}")
        if self.rtde_frequency_hz is not None and not self.rtde_frequency_hz > 0:
            raise ConfigError(f"URConfig.rtde_frequency_hz must be > 0 or None, got {self.rtde_frequency_hz!r}")
        for default, maximum in (
            ("joint_speed_rad_s", "max_joint_speed_rad_s"),
            ("joint_accel_rad_s2", "max_joint_accel_rad_s2"),
            ("linear_speed_m_s", "max_linear_speed_m_s"),
            ("linear_accel_m_s2", "max_linear_accel_m_s2"),
        ):
            if getattr(self, default) > getattr(self, maximum):
                raise ConfigError(
                    f"URConfig.{default} = {getattr(self, default)} exceeds {maximum} = {getattr(self, maximum)}"
                )

    @property
    def joint_limits_with_margin_rad(self) -> np.ndarray:
        limits = np.array(self.joint_limits_rad, dtype=float)
        return limits + np.array([self.joint_limit_margin_rad, -self.joint_limit_margin_rad])

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = "robot config") -> URConfig:
        """From a TOML/JSON table: the field names above; ``workspace`` is ``{lo_m = [x, y, z], hi_m = [...]}``,
        ``T_flange_tcp`` a 4x4 nested list. ``where`` names the file/section in error messages."""
        if not isinstance(data, Mapping):
            raise ConfigError(f"{where}: expected a table of robot settings, got {type(data).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ConfigError(f"{where}: unknown keys {unknown}; valid keys: {sorted(known)}")
        for key in ("host", "workspace"):
            if key not in data:
                raise ConfigError(f"{where}: missing {key!r}")
        kwargs = dict(data)
        box = data["workspace"]
        if not isinstance(box, Mapping) or set(box) != {"lo_m", "hi_m"}:
            raise ConfigError(f"{where}: workspace must be a table with lo_m and hi_m (3 numbers each), got {box!r}")
        try:
            kwargs["workspace"] = WorkspaceBox(tuple(box["lo_m"]), tuple(box["hi_m"]))
            if "T_flange_tcp" in data:
                kwargs["T_flange_tcp"] = np.array(data["T_flange_tcp"], dtype=float)
            if data.get("joint_limits_rad") is not None:
                kwargs["joint_limits_rad"] = np.array(data["joint_limits_rad"], dtype=float)
            return cls(**kwargs)
        except (ConfigError, TypeError, ValueError) as exc:
            raise ConfigError(f"{where}: {exc}") from None


# ---------------------------------------------------------------------------------------------- checks


def check_rigid(T: np.ndarray) -> np.ndarray:
    """``T`` as a float (4, 4) array; ``MotionRefusedError`` unless it is a finite rigid transform."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not is_rigid(T):
        raise MotionRefusedError(f"a target pose must be a finite 4x4 rigid transform, got {T.tolist()}")
    return T


def check_rate(value: float | None, default: float, maximum: float, name: str) -> float:
    """A speed or acceleration: ``default`` when None; ``MotionRefusedError`` unless in (0, maximum]."""
    value = default if value is None else value
    if not (isinstance(value, int | float) and math.isfinite(value) and 0 < value <= maximum):
        raise MotionRefusedError(f"{name} must be in (0, {maximum:g}] (URConfig maximum), got {value!r}")
    return float(value)


def check_target_in_workspace(config: URConfig, T_base_tcp: np.ndarray) -> None:
    """``OutsideWorkspaceError`` when the TCP position of ``T_base_tcp`` is outside the box."""
    T = check_rigid(T_base_tcp)
    if not config.workspace.contains(T[:3, 3]):
        raise OutsideWorkspaceError(
            f"target TCP position {np.round(T[:3, 3], 4).tolist()} m is outside the workspace box "
            f"({config.workspace.describe()}); nothing was sent"
        )


def check_joint_target(config: URConfig, q: np.ndarray) -> np.ndarray:
    """``q`` as a float (6,) array; ``MotionRefusedError`` unless finite and within the limits less the margin."""
    q_arr = np.asarray(q, dtype=float)
    if q_arr.shape != (6,) or not np.all(np.isfinite(q_arr)):
        raise MotionRefusedError(f"joint target must be 6 finite angles (rad), got {np.asarray(q).tolist()}")
    limits = config.joint_limits_with_margin_rad
    bad = [i for i in range(6) if not limits[i, 0] <= q_arr[i] <= limits[i, 1]]
    if bad:
        detail = ", ".join(
            f"{ur5e.JOINT_NAMES[i]} {q_arr[i]:.4f} not in [{limits[i, 0]:.4f}, {limits[i, 1]:.4f}]" for i in bad
        )
        raise MotionRefusedError(f"joint target outside the limits (less the margin): {detail}; nothing was sent")
    return q_arr


def check_joint_path(config: URConfig, T_flange_tcp: np.ndarray, q_from: np.ndarray, q_to: np.ndarray) -> None:
    """``OutsideWorkspaceError`` when the TCP leaves the box along the joint-space line from ``q_from`` to ``q_to``
    (movej's path), or ends outside it; the joint-target checks of ``check_joint_target`` too."""
    q_to = check_joint_target(config, q_to)
    leaves = config.workspace.joint_path_exit(T_flange_tcp, q_from, q_to, config.path_check_step_rad)
    if leaves is not None:
        fraction, p = leaves
        raise OutsideWorkspaceError(
            f"joint move to {np.round(q_to, 4).tolist()} rad takes the TCP to {np.round(p, 4).tolist()} m "
            f"({100 * fraction:.0f}% along the path), outside the workspace box "
            f"({config.workspace.describe()}); nothing was sent"
        )


def trapezoid_duration_s(distance: float, speed: float, accel: float) -> float:
    """Time of a rest-to-rest trapezoidal (or triangular) profile over ``distance`` (m or rad)."""
    if distance <= 0:
        return 0.0
    if distance > speed * speed / accel:
        return distance / speed + speed / accel
    return 2.0 * math.sqrt(distance / accel)
