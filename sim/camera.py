"""The simulated cell's cameras, rendered by MuJoCo: RGB and metric depth from one rasterised pass.

Fast path: no multisampling (the cell sets ``offsamples=0``), no shadows, reflections or skybox (frame times:
``sygrid bench sim``). Depth is read from the same pass and
converted from MuJoCo's reversed-z depth buffer to metres along the camera z axis with the model's clip planes
(``vis.map.znear/zfar * stat.extent``); pixels that see nothing get 0 ("no data").

Threads: ``capture`` holds ``world.lock`` only while it brings the kinematics up to date and copies the scene
(``mjv_updateScene``, well under a millisecond); rasterising runs outside it, so the world's tick thread keeps
stepping. MuJoCo's render calls hold Python's GIL, so the camera waits for the rasteriser with ``glFinish``
through ctypes (which releases it), so a frame blocks other Python threads only while drawing is queued. On two
cores the rasteriser still competes with the tick thread for CPU. The OpenGL context is created on the first
``capture`` (which also uploads the meshes, tens of milliseconds: take one frame before a tick thread starts) and
belongs to the thread that made it: capture from one thread. The backend is ``gl_backend``, else the
``MUJOCO_GL`` environment variable read when the camera is made, else EGL (``osmesa`` works where EGL does not).

Frames are stamped with the world's simulated time and carry the true ``T_base_camera`` (a real camera learns
it from hand-eye calibration; pass ``report_T_base_camera=False`` to withhold it). A ``sensor``
(``sygrid.sensor.SensorModel``, e.g. the "oak-d" preset) turns the rendered RGB and exact depth into what that
sensor reports, drawing from the camera's ``rng``; without one (or with "ideal") frames are exact.
"""

from __future__ import annotations

import importlib
import logging
import os
import threading
from collections.abc import Callable

import mujoco
import numpy as np

from perception.camera import Camera, Frame
from sim.cell_model import OVERHEAD_CAMERA, WRIST_CAMERA
from sim.world import CellWorld
from sygrid.camera import CameraIntrinsics
from sygrid.mjspec import model_camera_intrinsics
from sygrid.sensor import IDEAL, SensorModel
from sygrid.transforms import invert, make_T

log = logging.getLogger(__name__)

_GL_BACKENDS = {"egl": "mujoco.egl", "osmesa": "mujoco.osmesa", "glfw": "mujoco.glfw"}
_CV_FROM_MUJOCO_CAMERA = np.diag([1.0, -1.0, -1.0])  # MuJoCo camera axes (y up, looking along -z) -> OpenCV


def depth_buffer_to_metres(buffer: np.ndarray, znear_m: float, zfar_m: float) -> np.ndarray:
    """MuJoCo's reversed-z depth buffer ((H, W) in [0, 1], 1 at the near plane, 0 at the far plane) -> float32
    metres along the camera z axis, 0 where the ray hit nothing (the far plane)."""
    b = np.asarray(buffer, dtype=np.float64)
    z = znear_m * zfar_m / (b * (zfar_m - znear_m) + znear_m)
    z[b <= 0.0] = 0.0
    return z.astype(np.float32)


class SimCamera(Camera):
    """A camera of a ``CellWorld`` ("overhead", or "wrist" when the cell has one)."""

    def __init__(
        self,
        world: CellWorld,
        camera_name: str = OVERHEAD_CAMERA,
        width: int | None = None,
        height: int | None = None,
        sensor: SensorModel = IDEAL,
        rng: np.random.Generator | None = None,
        gl_backend: str | None = None,
        report_T_base_camera: bool = True,
    ) -> None:
        names = [world.model.camera(i).name for i in range(world.model.ncam)]
        if camera_name not in names:
            raise ValueError(f"the cell has no camera {camera_name!r}; available: {names}")
        if not sensor.is_ideal and rng is None:
            raise ValueError(
                f"sensor {sensor.name!r} needs an rng (np.random.Generator) so that frames are reproducible"
            )
        default = {OVERHEAD_CAMERA: world.config.camera_intrinsics, WRIST_CAMERA: world.config.wrist_camera_intrinsics}
        base = default.get(camera_name, CameraIntrinsics.from_fov(640, 480, 45.0))
        width, height = width or base.width, height or base.height
        off_w, off_h = world.model.vis.global_.offwidth, world.model.vis.global_.offheight
        if not (0 < width <= off_w and 0 < height <= off_h):
            raise ValueError(
                f"image size {width}x{height} must be positive and fit the offscreen buffer "
                f"{off_w}x{off_h} (model.vis.global_.offwidth/offheight)"
            )
        backend = (gl_backend or os.environ.get("MUJOCO_GL") or "egl").lower()
        if backend not in _GL_BACKENDS:
            raise ValueError(f"unknown OpenGL backend {backend!r}; valid: {sorted(_GL_BACKENDS)}")
        self._world = world
        self._camera_name = camera_name
        self._width, self._height = int(width), int(height)
        self._sensor, self._rng = sensor, rng
        self._backend = backend
        self._report_pose = report_T_base_camera
        self._camera_id = names.index(camera_name)
        self._intrinsics = model_camera_intrinsics(world.model, self._camera_id, self._width, self._height)
        self._rect = mujoco.MjrRect(0, 0, self._width, self._height)
        self._rgb = np.empty((self._height, self._width, 3), dtype=np.uint8)
        self._depth = np.empty((self._height, self._width), dtype=np.float32)
        self._gl = None
        self._gl_finish: Callable[[], None] | None = None
        self._gl_thread: int | None = None
        self._context: mujoco.MjrContext | None = None
        self._scene: mujoco.MjvScene | None = None
        self._model: mujoco.MjModel | None = None
        self._option = mujoco.MjvOption()
        self._option.geomgroup[:] = [1, 1, 1, 0, 0, 0]  # group 3 holds the parts' collision hulls
        self._option.sitegroup[:] = 0
        self._mjv_camera = mujoco.MjvCamera()
        self._mjv_camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._mjv_camera.fixedcamid = self._camera_id
        self._closed = False

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return self._intrinsics

    @property
    def name(self) -> str:
        return self._camera_name

    def capture(self) -> Frame:
        if self._closed:
            raise RuntimeError(f"SimCamera {self._camera_name!r} is closed")
        self._ensure_gl()
        world = self._world
        if world.model is not self._model:
            self._bind(world.model)  # first capture, or add_parts recompiled the world (model objects are immutable)
        with world.lock:
            model, data = world.model, world.data
            if model is not self._model:  # recompiled again meanwhile: rare, bind under the lock
                self._bind(model)
            world.sync_kinematics()
            mujoco.mjv_updateScene(
                model, data, self._option, None, self._mjv_camera, mujoco.mjtCatBit.mjCAT_ALL, self._scene
            )
            timestamp_s = float(data.time)
            T_world_camera = make_T(
                data.cam_xmat[self._camera_id].reshape(3, 3) @ _CV_FROM_MUJOCO_CAMERA, data.cam_xpos[self._camera_id]
            )
        mujoco.mjr_render(self._rect, self._scene, self._context)  # queues the drawing (holds the GIL ~1 ms)
        if self._gl_finish is not None:
            self._gl_finish()  # waits for the rasteriser through ctypes, which releases the GIL meanwhile
        mujoco.mjr_readPixels(self._rgb, self._depth, self._rect, self._context)
        rgb = np.flipud(self._rgb).copy()  # OpenGL rows run bottom-up
        extent = float(model.stat.extent)
        depth = depth_buffer_to_metres(
            np.flipud(self._depth), model.vis.map.znear * extent, model.vis.map.zfar * extent
        )
        if not self._sensor.is_ideal:
            rgb, depth = self._sensor.sense(rgb, depth, self._intrinsics, self._rng)
        T_base_camera = invert(world.config.T_world_base) @ T_world_camera if self._report_pose else None
        return Frame(rgb, depth, self._intrinsics, timestamp_s, T_base_camera)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._gl is not None:
            if self._context is not None:
                self._gl.make_current()
                self._context.free()
            self._gl.free()
        self._context, self._scene, self._gl = None, None, None

    # ------------------------------------------------------------------------------------------ internals

    def _ensure_gl(self) -> None:
        if self._gl is not None:
            if threading.get_ident() != self._gl_thread:
                raise RuntimeError(
                    f"SimCamera {self._camera_name!r} was first used in another thread; its OpenGL context belongs "
                    "to that thread. Capture from one thread, or make one SimCamera per thread."
                )
            self._gl.make_current()  # another camera may have made its own context current
            return
        try:
            module = importlib.import_module(_GL_BACKENDS[self._backend])
        except ImportError as err:
            raise RuntimeError(
                f"OpenGL backend {self._backend!r} is not available ({err}); try gl_backend='osmesa' or 'egl' "
                "(Debian packages libegl1 / libosmesa6)"
            ) from err
        self._gl = module.GLContext(self._width, self._height)
        self._gl.make_current()
        self._gl_thread = threading.get_ident()
        try:  # PyOpenGL comes with MuJoCo's EGL/OSMesa backends; without it frames are the same, the GIL held longer
            self._gl_finish = importlib.import_module("OpenGL.GL").glFinish
        except ImportError:
            self._gl_finish = None

    def _bind(self, model: mujoco.MjModel) -> None:
        """(Re)creates the render context and scene for ``model``; the GL context must be current."""
        if self._context is not None:
            self._context.free()
        self._context = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._context)
        self._context.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self._scene = mujoco.MjvScene(model, maxgeom=max(1000, 4 * model.ngeom))
        for flag in (
            mujoco.mjtRndFlag.mjRND_SHADOW,
            mujoco.mjtRndFlag.mjRND_REFLECTION,
            mujoco.mjtRndFlag.mjRND_SKYBOX,
        ):
            self._scene.flags[flag] = False
        self._model = model
        log.debug("SimCamera %r bound to a model with %d geoms", self._camera_name, model.ngeom)
