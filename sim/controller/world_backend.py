"""``ArmBackend`` over the MuJoCo cell (``sim.world.CellWorld``).

Every call into the world holds ``world.lock``, which the world-state server of the render process
(``sim.render_process``) also takes; that is why this backend declares ``step_may_block`` and the controller steps
it in its own thread (see ``stepper.py``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np

from sim.controller.backend import GRIPPER_STROKE_M, ArmSample
from sim.controller.errors import BackendUnavailableError

log = logging.getLogger(__name__)


class WorldBackend:
    """Drives a ``CellWorld``: joint targets go to its position actuators, state comes from MuJoCo."""

    step_may_block = True

    def __init__(self, world: Any) -> None:
        self.world = world
        self.dt_s = float(world.dt_s)
        self._gripper_target_m = GRIPPER_STROKE_M
        with world.lock:
            self._gripper_target_m = float(world.gripper_width_m())

    def reset_arm(self, q: np.ndarray) -> None:
        with self.world.lock:
            self.world.reset_arm(np.asarray(q, dtype=float))

    def advance(self, targets: Sequence[tuple[np.ndarray, np.ndarray]], steps_per_target: int) -> ArmSample:
        with self.world.lock:
            for q, qd in targets:
                self.world.set_arm_target(q, qd)
                self.world.step(steps_per_target)
            return self._sample_locked()

    def sample(self) -> ArmSample:
        with self.world.lock:
            return self._sample_locked()

    def set_gripper(self, width_m: float, speed_m_s: float, force_n: float) -> None:
        with self.world.lock:
            self.world.set_gripper(width_m, speed_m_s, force_n)
            self._gripper_target_m = float(width_m)

    def _sample_locked(self) -> ArmSample:
        w = self.world
        collision_force_n, collision_geoms = w.arm_collision()
        return ArmSample(
            time_s=float(w.time_s),
            q=np.array(w.arm_q(), dtype=float),
            qd=np.array(w.arm_qd(), dtype=float),
            torque=np.array(w.arm_torque(), dtype=float),
            collision_force_n=collision_force_n,
            collision_geoms=collision_geoms,
            gripper_width_m=float(w.gripper_width_m()),
            gripper_target_m=self._gripper_target_m,
            gripper_moving=bool(w.gripper_moving()),
            gripper_object_detected=bool(w.gripper_object_detected()),
            tool_wrench=np.array(w.tool_wrench(), dtype=float),
        )


def make_world_backend(
    parts_scene: str | None = None, parts_seed: int | None = None, **world_kwargs: Any
) -> WorldBackend:
    """Builds a fresh ``CellWorld`` and wraps it. With ``parts_seed`` (or ``parts_scene``) the bin holds the parts
    of that scene (default: 20 built-in parts) dropped by the generator's drop. Raises ``BackendUnavailableError``
    when ``sim.world`` is missing."""
    try:
        from sim.cell import build_cell_world
        from sim.world import CellWorld
    except ImportError as exc:
        raise BackendUnavailableError(
            f"the 'mujoco' backend needs sim.world.CellWorld, which cannot be imported ({exc}); "
            "use the 'kinematic' backend instead"
        ) from exc
    if parts_scene is not None or parts_seed is not None:
        world = build_cell_world(parts_scene, parts_seed or 0, world_kwargs.get("config"))
    else:
        world = CellWorld(**world_kwargs)
    return WorldBackend(world)
