"""A simulated arm chosen by name (``sygrid sim --backend``, ``ControllerProcess(backend=...)``).

- ``kinematic``: ``sim.controller.backend.KinematicBackend``, perfect tracking, no physics.
- ``mujoco``: ``sim.controller.world_backend``, a fresh MuJoCo cell (``sim.world.CellWorld``).
"""

from __future__ import annotations

from sim.controller.backend import ArmBackend, KinematicBackend
from sim.controller.world_backend import make_world_backend

__all__ = ["BACKENDS", "make_backend"]

BACKENDS = ("kinematic", "mujoco")


def make_backend(name: str, **kwargs: object) -> ArmBackend:
    """``kinematic`` (``KinematicBackend(**kwargs)``) or ``mujoco`` (``make_world_backend(**kwargs)``, which raises
    ``BackendUnavailableError`` when ``sim.world`` cannot be imported). ``ValueError`` names the valid choices."""
    if name == "kinematic":
        return KinematicBackend(**kwargs)  # type: ignore[arg-type]
    if name == "mujoco":
        return make_world_backend(**kwargs)  # type: ignore[arg-type]
    raise ValueError(f"unknown backend {name!r}; choose one of: {', '.join(BACKENDS)}")
