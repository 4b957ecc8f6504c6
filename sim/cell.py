"""A cell with a bin of parts: the MuJoCo world plus a pile made by the generator's own drop.

The parts enter the cell with the same object models, collision models and poses as in the generator
(``sygrid.drop``): the drop runs in the bin frame and its poses map into the cell as ``T_world_bin @ T_bin_obj``.
The scene's container is replaced by the cell's bin, so the pile fits the bin it is placed in.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from sim.cell_config import CellConfig
from sim.world import CellWorld
from sygrid.drop import drop_scene
from sygrid.errors import DropError
from sygrid.physics import DropResult
from sygrid.scene import ContainerSpec, SceneSpec, default_scene, load_scene

log = logging.getLogger(__name__)

# Joint angles that turn the arm away from the bin, out of the overhead camera's view (default layout).
Q_CLEAR_OF_CAMERA = (np.pi, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0)


def cell_scene(scene: SceneSpec, config: CellConfig) -> SceneSpec:
    """``scene`` with its container replaced by the cell's bin."""
    container = ContainerSpec(
        inner_size_m=config.bin_inner_size_m, wall_thickness_m=config.bin_wall_thickness_m, material="plastic"
    )
    return scene.model_copy(update={"container": container})


def build_cell_world(
    scene: SceneSpec | str | Path | None = None, seed: int = 0, config: CellConfig | None = None
) -> CellWorld:
    """A ``CellWorld`` whose bin holds the parts of ``scene`` (default: 20 built-in parts), dropped with ``seed``. A
    scene file's paths (CAD files, its catalogue) are relative to it; a ``SceneSpec``'s to the working folder."""
    config = config or CellConfig()
    base_dir = Path(".")
    if scene is None:
        scene = default_scene()
    elif not isinstance(scene, SceneSpec):
        base_dir = Path(scene).parent
        scene = load_scene(scene)
    result = drop_scene(cell_scene(scene, config), seed, base_dir)
    if not result.report.ok:
        raise DropError(f"the drop of scene '{scene.name}' (seed {seed}) is unusable: {result.report.to_json()}")
    world = CellWorld(config)
    add_pile(world, result)
    log.info("cell with %d parts of scene '%s' (seed %d)", len(result.instances), scene.name, seed)
    return world


def add_pile(world: CellWorld, result: DropResult) -> list[str]:
    """Puts a drop's pile (poses in the bin frame) into the world's bin, with the drop's collision models."""
    models = [result.models[i.model_index] for i in result.instances]
    collision = [result.collision[i.model_index] for i in result.instances]
    return world.add_parts(models, world.T_world_bin @ result.T_world_obj, collision)
