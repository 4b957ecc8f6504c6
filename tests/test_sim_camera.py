"""The MuJoCo-rendered camera: frame format, metric depth against ray-plane geometry, re-binding after parts are
added, the sensor model, rendering beside a stepping thread, the frame time, and the render process's priority."""

from __future__ import annotations

import itertools
import logging
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import trimesh

from perception.camera import Camera, Frame
from sim.camera import SimCamera, depth_buffer_to_metres
from sim.world import CellConfig, CellWorld
from sygrid.camera import CameraIntrinsics
from sygrid.objects.model import ObjectModel
from sygrid.robots import ur5e
from sygrid.sensor import SENSOR_PRESETS
from sygrid.transforms import invert, make_T, rotation_about

log = logging.getLogger(__name__)

_DEPTH_TOL_M = 1e-3
_ARM_AWAY_Q = np.array([np.pi / 2, *ur5e.HOME_Q[1:]])  # swung over the tray, out of the overhead view of the bin


@pytest.fixture()
def world() -> CellWorld:
    w = CellWorld()
    w.reset_arm(_ARM_AWAY_Q)
    return w


def _capture_or_skip(camera: SimCamera) -> Frame:
    try:
        return camera.capture()
    except RuntimeError as err:
        if "not available" in str(err):
            pytest.skip(f"no OpenGL backend on this machine: {err}")
        raise


def test_frame_format_intrinsics_and_timestamps(world: CellWorld) -> None:
    with SimCamera(world) as camera:
        assert isinstance(camera, Camera)
        frame = _capture_or_skip(camera)
        assert frame.rgb.shape == (480, 640, 3) and frame.rgb.dtype == np.uint8
        assert frame.depth_m.shape == (480, 640) and frame.depth_m.dtype == np.float32
        fovy = float(world.model.cam_fovy[world.model.camera("overhead").id])
        assert frame.intrinsics == CameraIntrinsics.from_fov(640, 480, fovy) == camera.intrinsics
        assert fovy == pytest.approx(45.0)
        np.testing.assert_allclose(
            frame.T_base_camera, invert(world.T_world_base) @ world.config.T_world_camera, atol=1e-9
        )
        assert frame.rgb.std() > 10  # not a blank image
        world.step(25)
        assert camera.capture().timestamp_s == pytest.approx(frame.timestamp_s + 0.05)
    small = SimCamera(world, width=320, height=240)
    assert small.capture().rgb.shape == (240, 320, 3)
    small.close()
    small.close()  # twice is fine
    with pytest.raises(RuntimeError, match="closed"):
        small.capture()


@pytest.mark.parametrize(
    ("intrinsics", "pan_deg"),
    [(None, 0.0), (CameraIntrinsics(608.2, 631.4, 331.0, 229.5, 640, 480), -20.0)],
    ids=["from_fov", "non_square"],
)
def test_depth_is_camera_z_on_a_tilted_plane(intrinsics: CameraIntrinsics | None, pan_deg: float) -> None:
    # The camera looks at an empty stretch of table, tilted, so every pixel's depth follows from ray-plane geometry
    # and a wrong intrinsic, ray distance instead of camera z, or a wrong clip plane would show. A real camera's K
    # (fx != fy, principal point off the centre) renders as it is; tilted about its y axis too, the plane's depth
    # changes along the rows, where fy in place of fx would be 4 mm off.
    R = (
        np.diag([1.0, -1.0, -1.0])
        @ rotation_about(np.array([1.0, 0, 0]), np.radians(10.0))
        @ rotation_about(np.array([0, 1.0, 0]), np.radians(pan_deg))
    )
    T_world_camera = make_T(R, (-0.35, 0.27, 0.30))
    config = CellConfig(T_world_camera=T_world_camera)
    if intrinsics is not None:
        config = CellConfig(T_world_camera=T_world_camera, camera_intrinsics=intrinsics)
    world = CellWorld(config)
    K = world.config.camera_intrinsics.K
    h, w = 480, 640
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    rays_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, dtype=float)], -1)
    rays_world = rays_cam @ R.T
    expected = -T_world_camera[2, 3] / rays_world[..., 2]  # camera z where the ray meets the table top (z = 0)
    hit = T_world_camera[:3, 3] + rays_world * expected[..., None]
    assert hit[..., 0].min() > -0.85 and hit[..., 0].max() < 0.25, "the view must stay on the table"
    assert hit[..., 1].min() > 0.13 and hit[..., 1].max() < 0.49, "the view must miss the bin and the robot"
    with SimCamera(world) as camera:
        frame = _capture_or_skip(camera)
    np.testing.assert_allclose(frame.intrinsics.K, K, rtol=1e-6, atol=1e-4)
    error = np.abs(frame.depth_m - expected)
    assert error.max() < _DEPTH_TOL_M, f"worst depth error {error.max() * 1e3:.3f} mm"


def test_depth_of_the_bin_floor_and_of_a_part_added_later(world: CellWorld) -> None:
    camera = SimCamera(world)
    frame = _capture_or_skip(camera)
    distance = world.config.T_world_camera[2, 3] - world.T_world_bin[2, 3]  # 0.9 m, straight down
    # Pixels over the bin's inner floor (a margin inside the walls): parallel to the image plane, constant z.
    T_camera_bin = invert(world.config.T_world_camera) @ world.T_world_bin
    corners = np.array([[sx * 0.12, sy * 0.08, 0.0, 1.0] for sx in (-1, 1) for sy in (-1, 1)]) @ T_camera_bin.T
    uv = corners[:, :2] / corners[:, 2:3] * [frame.intrinsics.fx, frame.intrinsics.fy] + [
        frame.intrinsics.cx,
        frame.intrinsics.cy,
    ]
    u0, v0 = np.ceil(uv.min(axis=0)).astype(int)
    u1, v1 = np.floor(uv.max(axis=0)).astype(int)
    floor = frame.depth_m[v0:v1, u0:u1]
    assert floor.size > 10_000
    assert np.abs(floor - distance).max() < _DEPTH_TOL_M
    # A 30 mm cube added at the bin centre: the camera re-binds to the recompiled model and sees its top.
    cube = ObjectModel(obj_id=1, name="cube", mesh=trimesh.creation.box((0.03, 0.03, 0.03)))
    world.add_parts([cube], (world.T_world_bin @ make_T(t=(0, 0, 0.015)))[None])
    world.step(20)
    frame = camera.capture()
    centre = frame.depth_m[238:242, 318:322]
    assert np.abs(centre - (distance - 0.03)).max() < _DEPTH_TOL_M
    camera.close()


def test_depth_buffer_conversion_round_trip() -> None:
    near, far = 0.02, 100.0
    z = np.array([[0.02, 0.5, 0.9, 3.0, 99.0]])
    buffer = near * (far - z) / (z * (far - near))  # reversed z: 1 at near, 0 at far
    np.testing.assert_allclose(depth_buffer_to_metres(buffer, near, far), z, rtol=1e-6)
    assert depth_buffer_to_metres(np.zeros((2, 2)), near, far).max() == 0.0  # nothing hit: no data


def test_a_sensor_model_gets_the_seeded_generator(world: CellWorld) -> None:
    oak = SENSOR_PRESETS["oak-d"]
    with pytest.raises(ValueError, match="needs an rng"):
        SimCamera(world, sensor=oak)
    frames = []
    for _ in range(2):
        with SimCamera(world, width=160, height=120, sensor=oak, rng=np.random.default_rng(5)) as camera:
            frames.append(_capture_or_skip(camera))
    assert np.array_equal(frames[0].depth_m, frames[1].depth_m)  # same seed, same bytes
    assert np.array_equal(frames[0].rgb, frames[1].rgb)
    floor = frames[0].depth_m[50:70, 70:90]  # the bin floor, 0.9 m away
    floor = floor[floor > 0]
    assert floor.size > 0.8 * 400
    assert float(np.std(floor)) == pytest.approx(oak.depth_noise_sigma_m(0.9), rel=0.5)
    assert abs(float(np.mean(floor)) - 0.9) < 4 * oak.depth_bias_sigma_m(0.9)


def test_unknown_camera_and_oversized_image_are_refused(world: CellWorld) -> None:
    with pytest.raises(ValueError, match=r"no camera 'wrist'; available: \['overhead'\]"):
        SimCamera(world, camera_name="wrist")
    with pytest.raises(ValueError, match="offscreen buffer"):
        SimCamera(world, width=4000, height=3000)
    wrist_world = CellWorld(CellConfig(wrist_camera=True))
    with SimCamera(wrist_world, camera_name="wrist", width=160, height=120) as wrist:
        frame = _capture_or_skip(wrist)
        assert frame.intrinsics.fov_y_deg == pytest.approx(60.0)


def test_captures_while_another_thread_steps_the_world(world: CellWorld) -> None:
    stop = threading.Event()
    errors: list[BaseException] = []

    def tick() -> None:
        try:
            while not stop.is_set():
                world.step()
        except BaseException as err:  # reported to the main thread below
            errors.append(err)

    with SimCamera(world) as camera:
        _capture_or_skip(camera)  # warm up: GL context and render context
        thread = threading.Thread(target=tick, daemon=True)
        thread.start()
        times, stamps = [], []
        for _ in range(8):
            start = time.perf_counter()
            stamps.append(camera.capture().timestamp_s)
            times.append(time.perf_counter() - start)
        stop.set()
        thread.join(timeout=5)
    assert not errors
    assert all(b >= a for a, b in itertools.pairwise(stamps)) and stamps[-1] > stamps[0]
    log.info("640x480 RGB + depth while stepping: median %.1f ms", float(np.median(times)) * 1e3)  # bench sim times it


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="Linux scheduling classes")
def test_the_render_process_runs_only_on_cores_the_tick_leaves_idle() -> None:
    """The emulator's render process lowers itself to the idle scheduling class: a waking tick takes its core at
    once (a niceness would only shrink its share)."""
    code = "import os, sim.render_process as r; r._lower_priority(); print(os.sched_getscheduler(0))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert int(out.stdout) == os.SCHED_IDLE
