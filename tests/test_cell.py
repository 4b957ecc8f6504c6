"""The cell with a pile: the generator's drop fills the sim cell's bin, and the pile stays at rest there."""

import numpy as np
import pytest

from sim.cell import build_cell_world, cell_scene
from sim.cell_config import CellConfig
from sygrid.errors import ConfigError
from sygrid.scene import parse_scene
from sygrid.transforms import invert

SCENE = parse_scene(
    {"name": "small", "objects": [{"builtin": "hex_nut", "count": 3}, {"builtin": "washer", "count": 3}]}
)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SYGRID_CACHE_DIR", str(tmp_path_factory.mktemp("cache")))
        yield


def test_cell_scene_takes_the_cells_bin():
    config = CellConfig(bin_inner_size_m=(0.25, 0.18, 0.1))
    assert cell_scene(SCENE, config).container.inner_size_m == (0.25, 0.18, 0.1)
    assert cell_scene(SCENE, config).objects == SCENE.objects


def test_pile_lands_in_the_cell_bin_and_stays_at_rest(cache):
    world = build_cell_world(SCENE, seed=4)
    assert len(world.part_names()) == 6
    T_bin_obj = invert(world.T_world_bin) @ world.part_poses()
    half = np.array(world.config.bin_inner_size_m[:2]) / 2
    assert np.all(np.abs(T_bin_obj[:, :2, 3]) < half) and np.all(T_bin_obj[:, 2, 3] > 0)
    before = world.part_poses()[:, :3, 3]
    world.step(250)  # 0.5 s: the cell does not sleep, so a pile that was not at rest would move
    assert np.abs(world.part_poses()[:, :3, 3] - before).max() < 0.002
    assert world.arm_collision_force_n() == 0.0


def test_same_seed_same_cell(cache):
    a = build_cell_world(SCENE, seed=2).part_poses()
    b = build_cell_world(SCENE, seed=2).part_poses()
    np.testing.assert_allclose(a, b, atol=1e-9)


def test_a_bad_scene_file_is_reported(tmp_path):
    bad = tmp_path / "scene.json"
    bad.write_text('{"objects": [{"builtin": "hex_nut", "count": -2}]}')
    with pytest.raises(ConfigError, match=r"scene\.json: objects\[0\]\.count: must be >= 0"):
        build_cell_world(bad)
