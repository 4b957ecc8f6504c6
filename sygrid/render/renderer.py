"""One data item: path-traced RGB (+ OIDN), metric depth, visible instance ids and full (amodal) masks.

Passes (Mitsuba, variant from ``choose_variant``):

1. colour: ``path`` integrator at ``scene.render.spp`` / ``max_depth`` with the scene's reconstruction filter,
   wrapped in an ``aov`` integrator that also writes albedo and shading normals as OIDN guides at the same spp;
2. ids + depth: ``aov`` integrator (``position``, ``shape_index``) at 1 spp with a box filter, so ids never blend;
   depth is the camera-frame z of ``position``;
3. full masks: the same 1-spp ``shape_index`` pass per instance with that instance alone in the scene.

``scene.render.mode == "raster"`` renders with MuJoCo's offscreen rasteriser instead (``_render_raster``): flat
colours per material, no global illumination, far cheaper than path tracing; ids come from MuJoCo's segmentation
pass and full masks from one segmentation pass per instance with the other parts moved away. Both modes render any
pinhole intrinsics (``fx != fy``, an off-centre principal point): MuJoCo's camera takes them natively
(``sygrid.mjspec.add_camera``), Mitsuba's through the anamorphic warp of ``sygrid.render.mitsuba_scene``. The
OpenGL backend is ``MUJOCO_GL`` (``egl`` when unset; ``osmesa`` works where EGL does not).

Randomisation (``render_item``'s ``draws`` and ``clutter``): textured floor and bin, a finish per part instance,
drawn skies and lamps, and distractors that occlude the parts without an id of their own; in raster mode the
textures, the finishes' flat colours and the lamps.

Determinism: Mitsuba's sampler seed and every material/light draw come from ``rng`` (the randomisation's draws
carry their own seeds); the same rng state and draws give the same bytes on the same machine and variant.
"""

from __future__ import annotations

import importlib
import logging
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sygrid.camera import CameraIntrinsics
from sygrid.objects.model import ObjectModel
from sygrid.physics import Instance
from sygrid.randomise.clutter import ClutterPiece
from sygrid.randomise.draws import ItemDraws
from sygrid.render.mitsuba_scene import (
    MitsubaShapes,
    anamorphic_warp,
    build_shapes,
    environment_emitters,
    sensor_dict,
    shape_index_values,
)
from sygrid.render.randomised import RASTER_METAL_RGB, finish_rgba, lighting_emitters, surface_texture_u8
from sygrid.render.variant import choose_variant
from sygrid.scene import SceneSpec

log = logging.getLogger(__name__)


@dataclass
class RenderResult:
    """One rendered item.

    rgb: (H, W, 3) uint8 sRGB. depth_m: (H, W) float32 camera-frame z in metres, 0 = no hit.
    ids_visib: (H, W) int32, 0 = background (floor, bin, nothing), k + 1 = instance k.
    masks_full: (n, H, W) bool, instance k's silhouette as if alone in the scene.
    timings: seconds per stage (``build``, ``rgb``, ``denoise``, ``ids_depth``, ``masks_full``, ``total``).
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    ids_visib: np.ndarray
    masks_full: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)
    variant: str = ""

    @property
    def masks_visib(self) -> np.ndarray:
        """(n, H, W) bool visible masks, from ``ids_visib``."""
        n = len(self.masks_full)
        return self.ids_visib[None, :, :] == np.arange(1, n + 1)[:, None, None]


def linear_to_srgb_u8(img: np.ndarray) -> np.ndarray:
    """(H, W, 3) linear RGB -> uint8 sRGB (values clipped to [0, 1])."""
    x = np.clip(np.nan_to_num(np.asarray(img, dtype=np.float32)), 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
    return np.round(s * 255.0).astype(np.uint8)


def camera_z_from_position(position_world: np.ndarray, hit: np.ndarray, T_world_camera: np.ndarray) -> np.ndarray:
    """(H, W, 3) world points + (H, W) hit mask -> (H, W) float32 camera-frame z in metres (0 where no hit)."""
    T = np.asarray(T_world_camera, dtype=float)
    z = (position_world.astype(np.float64) - T[:3, 3]) @ T[:3, 2]
    return np.where(hit, z, 0.0).astype(np.float32)


def _seed(rng: np.random.Generator) -> int:
    return int(rng.integers(0, 2**31 - 1))


def _load_scene(shapes: dict[str, object], sensor: dict, integrator: dict, emitters: dict | None = None) -> object:
    import mitsuba as mi

    d: dict = {"type": "scene", "integrator": integrator, "sensor": sensor}
    d.update(shapes)
    d.update(emitters or {})
    return mi.load_dict(d, optimize=False)


def _ids_pass(
    shapes: dict[str, object], part_names: list[str], sensor: dict, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> (H, W) int32 instance ids (k + 1 for ``part_names[k]``), (H, W, 3) world positions, (H, W) hit mask."""
    import mitsuba as mi

    scene = _load_scene(shapes, sensor, {"type": "aov", "aovs": "pp:position,si:shape_index"})
    img = np.asarray(mi.render(scene, spp=1, seed=seed))
    values = shape_index_values(scene)
    lut_size = max(values.values()) + 1
    lut = np.zeros(lut_size, dtype=np.int32)
    for k, name in enumerate(part_names):
        lut[values[name]] = k + 1
    raw = np.rint(img[..., 3]).astype(np.int64)
    if raw.min() < 0 or raw.max() >= lut_size:
        raise RuntimeError(f"shape_index AOV wrote {raw.min()}..{raw.max()}, outside the scene's ids 0..{lut_size - 1}")
    return lut[raw], img[..., :3], raw > 0


def render_item(
    scene: SceneSpec,
    models: list[ObjectModel],
    instances: list[Instance],
    T_world_obj: np.ndarray,
    T_world_camera: np.ndarray,
    intrinsics: CameraIntrinsics,
    rng: np.random.Generator,
    variant: str | None = None,
    base_dir: Path | str = ".",
    full_masks: bool = True,
    draws: ItemDraws | None = None,
    clutter: Sequence[ClutterPiece] = (),
) -> RenderResult:
    """Renders one item of ``scene`` with the parts at ``T_world_obj`` ((n, 4, 4), one per instance).

    Args:
        scene: the scene (render settings, container, environment).
        models, instances, T_world_obj: the settled pile (``DropResult`` fields).
        T_world_camera: (4, 4) OpenCV camera pose in the world frame.
        intrinsics: pinhole intrinsics; the image size is ``intrinsics.width`` x ``intrinsics.height``.
        rng: every random draw (materials, lights, sampler seeds) comes from it.
        variant: a Mitsuba variant to force; None chooses automatically.
        base_dir: folder that relative paths in the scene (environment map) are relative to.
        full_masks: render each instance alone for ``masks_full``; False leaves them equal to the visible masks.
        draws: the randomisation's draws of the item (``sygrid.randomise.draws``): textured surfaces, finishes per
            instance, lighting; None (or knobs off) keeps the scene's own look. They replace the renderer's own
            draws from ``rng`` but never change them (nor the sampler seeds).
        clutter: distractors to render: they occlude the parts (ids and depth see them) but have no id of their
            own (0, as the background) and never enter a full mask.
    """
    if scene.render.mode == "raster":
        return _render_raster(
            scene, models, instances, T_world_obj, T_world_camera, intrinsics, rng, full_masks, draws, clutter
        )
    import mitsuba as mi

    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    used = choose_variant(variant)
    T_world_obj = np.asarray(T_world_obj, dtype=float).reshape(-1, 4, 4)
    warp = anamorphic_warp(T_world_camera, intrinsics)  # None unless fx != fy
    built: MitsubaShapes = build_shapes(models, instances, T_world_obj, scene.container, rng, warp, draws, clutter)
    emitters = environment_emitters(scene.environment, rng, base_dir, warp)
    if draws is not None and draws.lighting is not None:
        emitters = lighting_emitters(draws.lighting, scene.environment, base_dir, warp)
    seed_rgb, seed_ids = _seed(rng), _seed(rng)
    rs = scene.render
    colour_sensor = sensor_dict(T_world_camera, intrinsics, rs.spp, rs.reconstruction_filter)
    colour_integrator = {
        "type": "aov",
        "aovs": "alb:albedo,nn:sh_normal",
        "integrator": {"type": "path", "max_depth": int(rs.max_depth)},
    }
    colour_scene = _load_scene(built.shapes, colour_sensor, colour_integrator, emitters)
    timings["build"] = time.perf_counter() - t0

    t = time.perf_counter()
    img = np.asarray(mi.render(colour_scene, spp=rs.spp, seed=seed_rgb), dtype=np.float32)
    timings["rgb"] = time.perf_counter() - t
    colour, albedo, normal = img[..., 0:3], img[..., 3:6], img[..., 6:9]
    t = time.perf_counter()
    if rs.denoiser == "oidn":
        colour = _oidn(colour, albedo, normal)
    timings["denoise"] = time.perf_counter() - t
    rgb = linear_to_srgb_u8(colour)

    t = time.perf_counter()
    id_sensor = sensor_dict(T_world_camera, intrinsics, 1, "box", pixel_format="rgba")
    ids, position, hit = _ids_pass(built.shapes, built.part_names, id_sensor, seed_ids)
    depth_m = camera_z_from_position(position, hit, T_world_camera)
    timings["ids_depth"] = time.perf_counter() - t

    t = time.perf_counter()
    n = len(built.part_names)
    masks = ids[None, :, :] == np.arange(1, n + 1)[:, None, None]
    if full_masks:
        for k, name in enumerate(built.part_names):
            solo, _, _ = _ids_pass({name: built.shapes[name]}, [name], id_sensor, seed_ids)
            masks[k] = solo == 1
    timings["masks_full"] = time.perf_counter() - t
    _release_jit_caches()
    timings["total"] = time.perf_counter() - t0
    log.debug("rendered %dx%d, %d parts, %s: %s", intrinsics.width, intrinsics.height, n, used, timings)
    return RenderResult(rgb, depth_m, ids, masks, timings, used)


def _release_jit_caches() -> None:
    """Every item is a new scene, so Dr.Jit compiles new kernels and keeps them (and their allocations) cached:
    memory that a long-running generator never gets back (``sygrid bench render`` measures RSS over 300 items)."""
    import drjit as dr

    dr.flush_kernel_cache()
    dr.flush_malloc_cache()


def _oidn(colour: np.ndarray, albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Denoises linear HDR colour with albedo and normal guides (Intel Open Image Denoise)."""
    import pyoidn

    alb = np.clip(np.nan_to_num(albedo), 0.0, 1.0).astype(np.float32)
    nrm = np.clip(np.nan_to_num(normal), -1.0, 1.0).astype(np.float32)
    col = np.maximum(np.nan_to_num(colour), 0.0).astype(np.float32)
    return pyoidn.denoise(col, alb, nrm, hdr=True)


# ---------------------------------------------------------------------------------------------- raster mode

_GL_BACKENDS = {"egl": "mujoco.egl", "osmesa": "mujoco.osmesa", "glfw": "mujoco.glfw"}
_RASTER_RGB = {**RASTER_METAL_RGB, "painted": None, "plastic": None}  # base colours of the materials in raster mode
_FAR_AWAY_M = 1000.0


def _raster_rgba(material: str, rng: np.random.Generator) -> list[float]:
    base = _RASTER_RGB.get(material)
    rgb = rng.uniform(0.1, 0.9, 3) if base is None else np.clip(np.array(base) * rng.uniform(0.9, 1.1), 0, 1)
    return [*np.asarray(rgb, dtype=float).tolist(), 1.0]


def _raster_texture(spec: object, name: str, texture: np.ndarray, repeat_per_m: float) -> str:
    """Adds a 2D texture (``(n, n, 3)`` uint8 display values) and a material showing it uniformly in space,
    ``repeat_per_m`` tiles per metre; returns the material's name."""
    import mujoco

    h, w = texture.shape[:2]
    tex = spec.add_texture(name=f"{name}_tex", type=mujoco.mjtTexture.mjTEXTURE_2D, width=w, height=h, nchannel=3)
    tex.data = np.ascontiguousarray(texture, dtype=np.uint8).tobytes()
    mat = spec.add_material(name=f"{name}_mat", texuniform=True, texrepeat=[repeat_per_m, repeat_per_m])
    mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = f"{name}_tex"
    return f"{name}_mat"


def _render_raster(
    scene: SceneSpec,
    models: list[ObjectModel],
    instances: list[Instance],
    T_world_obj: np.ndarray,
    T_world_camera: np.ndarray,
    intrinsics: CameraIntrinsics,
    rng: np.random.Generator,
    full_masks: bool,
    draws: ItemDraws | None = None,
    clutter: Sequence[ClutterPiece] = (),
) -> RenderResult:
    """The rasterised item; the randomisation's draws (``render_item``) as textures of the floor and bin, flat
    colours of the finishes, and lamps (the sky's strength scales the headlight)."""
    import mujoco

    from sygrid.mjspec import add_camera, add_mesh_asset, add_open_box, open_box_parts, quat_wxyz
    from sygrid.render.mitsuba_scene import BIN_FLOOR_THICKNESS_M

    t0 = time.perf_counter()
    K = intrinsics
    T_world_obj = np.asarray(T_world_obj, dtype=float).reshape(-1, 4, 4)
    if len(T_world_obj) != len(instances):
        raise ValueError(f"T_world_obj has {len(T_world_obj)} poses for {len(instances)} instances")
    draws = draws or ItemDraws()
    spec = mujoco.MjSpec()
    spec.visual.global_.offwidth, spec.visual.global_.offheight = K.width, K.height
    spec.visual.quality.offsamples = 0
    spec.visual.map.znear, spec.visual.map.zfar = 0.005, 50.0
    spec.stat.extent = 1.0
    c = scene.container
    grey = float(rng.uniform(0.15, 0.6))
    floor = spec.worldbody.add_geom(
        name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3, 3, 0.1], pos=[0, 0, -BIN_FLOOR_THICKNESS_M],
        rgba=[grey, grey, grey, 1.0],
    )  # fmt: skip
    add_open_box(
        spec.worldbody, "bin", np.eye(4), c.inner_size_m, c.wall_thickness_m, BIN_FLOOR_THICKNESS_M,
        [0.02, 1.0], [0.5, 0.005, 0.0001], tuple(_raster_rgba(c.material, rng)),
    )  # fmt: skip
    if draws.surfaces is not None:
        f, b = draws.surfaces["floor"], draws.surfaces["bin"]
        floor.material = _raster_texture(spec, "floor", surface_texture_u8(f), 1.0 / f.tile_m)
        floor.rgba = [1.0, 1.0, 1.0, 1.0]
        bin_material = _raster_texture(spec, "bin", surface_texture_u8(b), 1.0 / b.tile_m)
        for part in open_box_parts(c.inner_size_m, c.wall_thickness_m, BIN_FLOOR_THICKNESS_M):
            geom = spec.geom(f"bin_{part}")
            geom.material, geom.rgba = bin_material, [1.0, 1.0, 1.0, 1.0]
    rgba = [_raster_rgba(m.material, rng) for m in models]
    part_geoms: list[str] = []
    for k, (inst, T) in enumerate(zip(instances, T_world_obj, strict=True)):
        model = models[inst.model_index]
        mesh = add_mesh_asset(spec, f"mesh_{inst.model_index}", model.mesh.vertices, model.mesh.faces)
        body = spec.worldbody.add_body(name=f"part_{k}", pos=T[:3, 3].tolist(), quat=quat_wxyz(T[:3, :3]).tolist())
        colour = rgba[inst.model_index] if draws.parts is None else finish_rgba(draws.parts[k])
        body.add_geom(name=f"part_{k}", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=mesh, rgba=colour)
        part_geoms.append(f"part_{k}")
    for k, piece in enumerate(clutter):
        mesh = add_mesh_asset(spec, f"clutter_mesh_{k}", piece.model.mesh.vertices, piece.model.mesh.faces)
        T = np.asarray(piece.T_world_obj, dtype=float)
        body = spec.worldbody.add_body(name=f"clutter_{k}", pos=T[:3, 3].tolist(), quat=quat_wxyz(T[:3, :3]).tolist())
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_MESH, meshname=mesh, rgba=finish_rgba(piece.finish))
    lo, hi = scene.environment.random_lights
    lamps = []  # (position, diffuse) of each lamp
    for _ in range(int(rng.integers(lo, hi + 1))):
        lamps.append(([*rng.uniform(-0.6, 0.6, 2).tolist(), float(rng.uniform(0.7, 1.5))], [0.5] * 3))
    if draws.lighting is not None:
        level = draws.lighting.strength
        spec.visual.headlight.ambient = [0.1 * level] * 3
        spec.visual.headlight.diffuse = [0.4 * level] * 3
        lamps = [(list(d.position_m), (0.5 * d.irradiance * np.asarray(d.tint)).tolist()) for d in draws.lighting.lamps]
    for i, (pos, diffuse) in enumerate(lamps):
        spec.worldbody.add_light(
            name=f"lamp_{i}", pos=pos, dir=(-np.asarray(pos) / np.linalg.norm(pos)).tolist(),
            diffuse=(np.asarray(diffuse) * scene.environment.strength).tolist(), castshadow=False,
        )  # fmt: skip
    add_camera(spec.worldbody, "cam", np.asarray(T_world_camera, dtype=float), K)
    mj_model = spec.compile()
    data = mujoco.MjData(mj_model)
    mujoco.mj_forward(mj_model, data)
    timings = {"build": time.perf_counter() - t0}

    backend = os.environ.get("MUJOCO_GL", "egl").lower()
    if backend not in _GL_BACKENDS:
        raise ValueError(f"MUJOCO_GL={backend!r} is not a usable offscreen backend; valid: {sorted(_GL_BACKENDS)}")
    gl = importlib.import_module(_GL_BACKENDS[backend]).GLContext(K.width, K.height)
    gl.make_current()
    try:
        ctx = mujoco.MjrContext(mj_model, mujoco.mjtFontScale.mjFONTSCALE_100)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, ctx)
        ctx.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        mjscene = mujoco.MjvScene(mj_model, maxgeom=max(1000, 4 * mj_model.ngeom))
        cam = mujoco.MjvCamera()
        cam.type, cam.fixedcamid = mujoco.mjtCamera.mjCAMERA_FIXED, 0
        opt = mujoco.MjvOption()
        rect = mujoco.MjrRect(0, 0, K.width, K.height)
        rgb = np.zeros((K.height, K.width, 3), np.uint8)
        buf = np.zeros((K.height, K.width), np.float32)
        geom_to_id = np.zeros(mj_model.ngeom + 1, np.int32)
        for k, name in enumerate(part_geoms):
            geom_to_id[mj_model.geom(name).id] = k + 1

        def draw(segment: bool) -> None:
            mujoco.mjv_updateScene(mj_model, data, opt, None, cam, mujoco.mjtCatBit.mjCAT_ALL, mjscene)
            mjscene.flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = segment
            mjscene.flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = segment
            for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION):
                mjscene.flags[flag] = False
            mujoco.mjr_render(rect, mjscene, ctx)
            mujoco.mjr_readPixels(rgb, buf, rect, ctx)

        def ids() -> np.ndarray:
            draw(True)
            seg = rgb[::-1].astype(np.int64)
            segid = seg[..., 0] + seg[..., 1] * 256 + seg[..., 2] * 65536 - 1
            lut = np.zeros(mjscene.ngeom + 1, np.int32)
            for g in range(mjscene.ngeom):
                vg = mjscene.geoms[g]
                if vg.objtype == mujoco.mjtObj.mjOBJ_GEOM:
                    lut[g + 1] = geom_to_id[vg.objid]
            return lut[np.clip(segid + 1, 0, mjscene.ngeom)]

        t = time.perf_counter()
        draw(False)
        colour = rgb[::-1].copy()
        znear = mj_model.vis.map.znear * mj_model.stat.extent
        zfar = mj_model.vis.map.zfar * mj_model.stat.extent
        b = buf[::-1].astype(np.float64)
        depth_m = np.where(b > 0, znear * zfar / (b * (zfar - znear) + znear), 0.0).astype(np.float32)
        timings["rgb"] = time.perf_counter() - t  # colour and depth come from the same pass
        t = time.perf_counter()
        ids_visib = ids()
        timings["ids_depth"] = time.perf_counter() - t
        t = time.perf_counter()
        n = len(part_geoms)
        masks = ids_visib[None, :, :] == np.arange(1, n + 1)[:, None, None]
        if full_masks and n:
            # Every part, distractor and the bin are moved away but the part whose full mask is drawn: a full mask
            # is the part alone (BOP's), so that a part behind the bin's wall is not counted as fully visible.
            body_ids = [mj_model.body(f"part_{k}").id for k in range(n)]
            body_ids += [mj_model.body(f"clutter_{k}").id for k in range(len(clutter))]
            body_ids += [mj_model.body("bin").id]
            pos0 = mj_model.body_pos[body_ids].copy()
            for k in range(n):
                mj_model.body_pos[body_ids] = pos0 + np.array([0.0, 0.0, _FAR_AWAY_M])
                mj_model.body_pos[body_ids[k]] = pos0[k]
                mujoco.mj_kinematics(mj_model, data)
                masks[k] = ids() == k + 1
            mj_model.body_pos[body_ids] = pos0
        timings["masks_full"] = time.perf_counter() - t
        ctx.free()
    finally:
        gl.free()
    timings["denoise"] = 0.0
    timings["total"] = time.perf_counter() - t0
    return RenderResult(colour, depth_m, ids_visib, masks, timings, f"mujoco-{backend}")
