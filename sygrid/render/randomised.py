"""The randomisation's draws (``sygrid.randomise.draws``) as Mitsuba objects and rasteriser colours: textured
surfaces, part finishes, skies and lamps, and the texture coordinates they need.

Texture coordinates come from a box projection: every triangle takes the two coordinates across its dominant normal
axis, divided by the tile size, so a texture keeps its scale on every face. Such a mesh has its own vertices per
triangle (the same triangles, in the same places: geometry, depth and ids do not change).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sygrid.randomise.draws import FinishDraw, LampDraw, LightingDraw, SurfaceDraw
from sygrid.randomise.skies import sky_map
from sygrid.randomise.textures import surface_texture, wear_mask
from sygrid.render.materials import material_bsdf
from sygrid.scene import EnvironmentSpec

#: Mean sky radiance at ``environment_strength`` 1 (the scene's constant sky averages about this).
SKY_RADIANCE = 0.35
#: The rasteriser's base colours of the metals (display values).
RASTER_METAL_RGB = {
    "steel": (0.62, 0.63, 0.65), "zinc": (0.70, 0.72, 0.76), "brass": (0.78, 0.62, 0.30),
    "aluminium": (0.80, 0.81, 0.83),
}  # fmt: skip


def box_projected_uv(vertices: np.ndarray, faces: np.ndarray, tile: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(3 m, 3) vertices, (m, 3) faces, (3 m, 2) texture coordinates of the triangles ``faces`` of ``vertices``,
    box-projected at ``tile`` units per texture tile (see the module doc)."""
    V = np.asarray(vertices, dtype=float)
    F = np.asarray(faces, dtype=np.int64)
    tri = V[F]  # (m, 3, 3)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    axis = np.argmax(np.abs(normal), axis=1)
    uv_axes = np.array([[1, 2], [0, 2], [0, 1]])[axis]  # (m, 2)
    uv = np.take_along_axis(tri, np.repeat(uv_axes[:, None, :], 3, axis=1), axis=2) / float(tile)
    return tri.reshape(-1, 3), np.arange(3 * len(F)).reshape(-1, 3), uv.reshape(-1, 2)


def _bitmap(array: np.ndarray, raw: bool = False) -> dict:
    import mitsuba as mi

    return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(array, dtype=np.float32)), "raw": raw}


def surface_bsdf(draw: SurfaceDraw) -> dict:
    """A floor or bin surface: its texture as a diffuse (concrete, cardboard), glossy (the rest) or brushed
    conductor (``brushed_metal``) reflectance."""
    tex = _bitmap(surface_texture(draw.family, np.array(draw.base_rgb), draw.texture_px, draw.seed))
    if draw.family == "brushed_metal":
        return {
            "type": "roughconductor", "distribution": "ggx", "material": "Al", "alpha_u": draw.roughness,
            "alpha_v": 0.2 * draw.roughness, "specular_reflectance": tex,
        }  # fmt: skip
    if draw.family in ("concrete", "cardboard"):
        return {"type": "diffuse", "reflectance": tex}
    return {"type": "roughplastic", "distribution": "ggx", "alpha": draw.roughness, "diffuse_reflectance": tex}


def _conductor(draw: FinishDraw) -> dict:
    bsdf = dict(material_bsdf(draw.metal or "steel", np.random.default_rng(draw.seed)))
    if draw.anisotropy > 0:
        del bsdf["alpha"]
        bsdf["alpha_u"], bsdf["alpha_v"] = draw.alpha, draw.alpha * (1.0 - draw.anisotropy)
    else:
        bsdf["alpha"] = draw.alpha
    return bsdf


def finish_bsdf(draw: FinishDraw) -> dict:
    """A part's (or a distractor's) finish: a conductor, a rough plastic, or paint over a conductor blended by the
    wear mask."""
    if draw.family in ("bare_metal", "anisotropic_metal"):
        return _conductor(draw)
    paint = {
        "type": "roughplastic", "distribution": "ggx", "alpha": draw.paint_alpha or draw.alpha,
        "diffuse_reflectance": {"type": "rgb", "value": list(draw.colour or (0.5, 0.5, 0.5))},
    }  # fmt: skip
    if draw.family == "plastic":
        paint["alpha"] = draw.alpha
        return paint
    if draw.family == "worn_paint":
        mask = wear_mask(draw.wear, draw.mask_px, draw.seed)
        return {"type": "blendbsdf", "weight": _bitmap(mask, raw=True), "bsdf_0": paint, "bsdf_1": _conductor(draw)}
    raise ValueError(f"unknown finish family {draw.family!r}")


def finish_needs_uv(draw: FinishDraw) -> bool:
    """Whether the finish varies over the surface (a mask, or a direction): its mesh needs texture coordinates."""
    return draw.family == "worn_paint" or draw.anisotropy > 0


def lighting_emitters(
    draw: LightingDraw, env: EnvironmentSpec, base_dir: Path | str = ".", warp: np.ndarray | None = None
) -> dict:
    """The drawn environment and lamps as Mitsuba emitter dicts (the scene's ``strength`` scales all of them);
    ``warp``: ``anamorphic_warp``'s stretch of the lamps, or None."""
    import mitsuba as mi

    level = env.strength * draw.strength
    # Mitsuba's envmap has y up; the scene has z up.
    to_world = mi.ScalarTransform4f().rotate([0, 0, 1], draw.rotation_deg).rotate([1, 0, 0], 90.0)
    emitters: dict[str, dict] = {}
    if draw.sky == "map_file":
        path = Path(env.map_file or "")
        path = path if path.is_absolute() else Path(base_dir) / path
        if not path.is_file():
            raise FileNotFoundError(f"environment.map_file: no such file {path}")
        emitters["env"] = {"type": "envmap", "filename": str(path), "scale": level, "to_world": to_world}
    else:
        sky = sky_map(draw.sky, draw.sky_px, draw.seed, draw.sun_elevation_deg)
        if sky is None:
            emitters["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": [SKY_RADIANCE * level] * 3}}
        else:
            emitters["env"] = {
                "type": "envmap", "bitmap": mi.Bitmap(sky), "scale": SKY_RADIANCE * level, "to_world": to_world,
            }  # fmt: skip
    for i, lamp in enumerate(draw.lamps):
        emitters[f"lamp_{i}"] = _lamp(lamp, env.strength, warp)
    return emitters


def _lamp(lamp: LampDraw, strength: float, warp: np.ndarray | None) -> dict:
    """A point light of intensity ``E d^2``, or a square area light facing the bin centre of radiance
    ``E d^2 / side^2``: irradiance ``E`` at the bin centre either way."""
    import mitsuba as mi

    pos = np.asarray(lamp.position_m, dtype=float)
    d2 = float(pos @ pos)
    tint = np.asarray(lamp.tint) * lamp.irradiance * strength * d2
    if lamp.family == "point_light":
        if warp is not None:
            pos = warp[:3, :3] @ pos + warp[:3, 3]
        return {"type": "point", "position": pos.tolist(), "intensity": {"type": "rgb", "value": tint.tolist()}}
    side = lamp.size_m
    to_world = mi.ScalarTransform4f.look_at(origin=pos.tolist(), target=[0, 0, 0], up=[0, 1, 0]).scale(
        [side / 2, side / 2, 1.0]
    )
    if warp is not None:
        to_world = mi.ScalarTransform4f(warp.tolist()) @ to_world
    return {
        "type": "rectangle",
        "to_world": to_world,
        "emitter": {"type": "area", "radiance": {"type": "rgb", "value": (tint / side**2).tolist()}},
        "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
    }


# ---------------------------------------------------------------------------------------------- the rasteriser
def linear_to_display(rgb: np.ndarray) -> np.ndarray:
    """Linear reflectance -> the display values the rasteriser's colours and textures take (sRGB curve)."""
    x = np.clip(np.asarray(rgb, dtype=float), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def finish_rgba(draw: FinishDraw) -> list[float]:
    """The rasteriser's flat colour of a finish: the metal's base colour, the plastic's, or paint and metal mixed
    by the wear."""
    metal = np.array(RASTER_METAL_RGB.get(draw.metal or "steel", RASTER_METAL_RGB["steel"]))
    if draw.family in ("bare_metal", "anisotropic_metal"):
        rgb = metal
    else:
        rgb = linear_to_display(np.array(draw.colour or (0.5, 0.5, 0.5)))
        if draw.family == "worn_paint":
            rgb = (1.0 - draw.wear) * rgb + draw.wear * metal
    return [*np.clip(rgb, 0.0, 1.0).tolist(), 1.0]


def surface_texture_u8(draw: SurfaceDraw) -> np.ndarray:
    """(n, n, 3) uint8 display-value texture of a surface, for the rasteriser."""
    tex = surface_texture(draw.family, np.array(draw.base_rgb), draw.texture_px, draw.seed)
    return np.round(linear_to_display(tex) * 255.0).astype(np.uint8)
