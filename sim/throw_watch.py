"""Parts the physics throws: a part moving faster than anything in the cell can move it has been thrown by the
solver (a deep penetration resolved in one step), not by the cell; its pose is not to be trusted afterwards.

``ThrowWatch`` keeps the last ``HISTORY_STEPS`` physics states (time, ``qpos``, ``qvel``: a few microseconds a step)
and, when a part's speed first exceeds ``MAX_PLAUSIBLE_PART_SPEED_M_S``, explains the throw from them: it recomputes
the contacts of each kept state (``mj_fwdPosition`` on a scratch ``MjData``) and reports the part's deepest
penetration before the throw, what it penetrated, and its speed just before.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass

import mujoco
import numpy as np

#: A part dropped from 1 m reaches 4.4 m/s and the arm's TCP moves at most 1 m/s here.
MAX_PLAUSIBLE_PART_SPEED_M_S = 10.0
HISTORY_STEPS = 100


@dataclass(frozen=True)
class Throw:
    """One thrown part: when it was first seen too fast and how fast [m/s]; before that (within the kept history)
    its deepest contact penetration [m] (0 without contact), the geom it penetrated, when [s], and its largest
    speed [m/s] before the throw."""

    part: str
    time_s: float
    speed_m_s: float
    max_penetration_m: float = 0.0
    against: str = ""
    penetration_time_s: float = float("nan")
    speed_before_m_s: float = 0.0

    def describe(self) -> str:
        text = f"{self.part} moves at {self.speed_m_s:.0f} m/s at t = {self.time_s:.3f} s"
        if self.max_penetration_m > 0:
            text += (
                f"; before, it penetrated {self.against} by {1e3 * self.max_penetration_m:.1f} mm "
                f"(t = {self.penetration_time_s:.3f} s) moving at most {self.speed_before_m_s:.2f} m/s"
            )
        return text


class ThrowWatch:
    """Watches the parts of one compiled model; ``bind`` again after a recompile."""

    def __init__(self, history_steps: int = HISTORY_STEPS) -> None:
        self._history: collections.deque[tuple[float, np.ndarray, np.ndarray]] = collections.deque(maxlen=history_steps)
        self._names: list[str] = []
        self._dofadr = np.zeros(0, dtype=int)
        self._body = np.zeros(0, dtype=int)
        self.thrown: dict[str, Throw] = {}

    def bind(self, model: mujoco.MjModel, part_names: list[str], part_dofadr: np.ndarray) -> None:
        self._names = list(part_names)
        self._dofadr = np.asarray(part_dofadr, dtype=int)
        self._body = np.array([model.body(n).id for n in part_names], dtype=int)
        self._history.clear()

    def record(self, data: mujoco.MjData) -> None:
        """Keeps the state of the step just taken (call once per physics step)."""
        if len(self._dofadr):
            self._history.append((float(data.time), data.qpos.copy(), data.qvel.copy()))

    def check(self, model: mujoco.MjModel, data: mujoco.MjData) -> list[Throw]:
        """The parts first seen too fast now, each explained from the kept history."""
        if not len(self._dofadr):
            return []
        speeds = np.linalg.norm(data.qvel[self._dofadr.reshape(-1, 1) + np.arange(3)], axis=1)
        new = []
        for k in np.flatnonzero(speeds > MAX_PLAUSIBLE_PART_SPEED_M_S):
            name = self._names[int(k)]
            if name not in self.thrown:
                self.thrown[name] = self._explain(model, int(k), float(data.time), float(speeds[k]))
                new.append(self.thrown[name])
        return new

    def _explain(self, model: mujoco.MjModel, k: int, time_s: float, speed: float) -> Throw:
        scratch = mujoco.MjData(model)
        dof, body = int(self._dofadr[k]), int(self._body[k])
        deepest, against, when, fastest = 0.0, "", float("nan"), 0.0
        for t, qpos, qvel in self._history:
            v = float(np.linalg.norm(qvel[dof : dof + 3]))
            if v > MAX_PLAUSIBLE_PART_SPEED_M_S:
                break  # the throw itself: what came before explains it
            fastest = max(fastest, v)
            scratch.qpos[:], scratch.qvel[:] = qpos, qvel
            mujoco.mj_fwdPosition(model, scratch)
            n = scratch.ncon
            g1, g2 = scratch.contact.geom1[:n], scratch.contact.geom2[:n]
            b1, b2 = model.geom_bodyid[g1], model.geom_bodyid[g2]
            mine = np.flatnonzero((b1 == body) | (b2 == body))
            if not len(mine):
                continue
            i = int(mine[np.argmin(scratch.contact.dist[mine])])
            if -float(scratch.contact.dist[i]) > deepest:
                deepest, when = -float(scratch.contact.dist[i]), t
                other = int(g2[i]) if b1[i] == body else int(g1[i])
                against = _geom_label(model, other)
        return Throw(self._names[k], time_s, speed, deepest, against, when, fastest)


def _geom_label(model: mujoco.MjModel, geom: int) -> str:
    """The geom's name, else its body's name with the geom index (mesh pieces are often unnamed)."""
    name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, geom)
    if name:
        return name
    body = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.geom_bodyid[geom]))
    return f"{body or 'body'}#{geom}"
