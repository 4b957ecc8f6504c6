"""An item's randomisation draws: what each enabled knob chose for it, as plain values an item's record keeps.

Each knob draws from its own stream, ``knob_rng(stream, knob)``, a child of the attempt's randomisation stream
numbered by the knob's place in ``KNOBS``: turning one knob on or off never changes what another draws, and a
disabled knob draws nothing. A draw holds everything its pixels depend on (texture seeds included), so the
record of an item is enough to rebuild its look. The draws never see a family that ``families`` does not allow.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import asdict, dataclass

import numpy as np

from sygrid.objects.parts import builtin_part
from sygrid.randomise.families import FINISHES_BY_MATERIAL, FamiliesSpec
from sygrid.randomise.spec import (
    KNOBS,
    CameraKnob,
    DistractorsKnob,
    GeometryKnob,
    LightingKnob,
    PartsKnob,
    RandomisationSpec,
    SurfacesKnob,
)
from sygrid.randomise.textures import SURFACE_HSV
from sygrid.scene import METALS, ContainerSpec
from sygrid.transforms import make_T, rotation_about

Rgb = tuple[float, float, float]
_DISTRACTOR_FINISH = PartsKnob()  # the ranges of a distractor's finish


def knob_rng(stream: np.random.SeedSequence, knob: str) -> np.random.Generator:
    """The generator of ``knob`` (one of ``KNOBS``) under an attempt's randomisation ``stream``."""
    child = np.random.SeedSequence(stream.entropy, spawn_key=(*stream.spawn_key, KNOBS.index(knob)))
    return np.random.default_rng(child)


def _u(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(rng.uniform(bounds[0], bounds[1]))


def _seed(rng: np.random.Generator) -> int:
    return int(rng.integers(0, 2**31 - 1))


def _rgb(hue: float, sat: float, val: float) -> Rgb:
    r, g, b = colorsys.hsv_to_rgb(hue % 1.0, min(max(sat, 0.0), 1.0), min(max(val, 0.0), 1.0))
    return (r, g, b)


# ---------------------------------------------------------------------------------------------- the draws
@dataclass(frozen=True)
class SurfaceDraw:
    """A floor or bin surface: texture ``family`` around ``base_rgb``, GGX ``roughness``, a tile ``tile_m`` on a
    side, the bitmap ``texture_px`` wide made from ``seed`` (``sygrid.randomise.textures.surface_texture``)."""

    family: str
    base_rgb: Rgb
    roughness: float
    tile_m: float
    texture_px: int
    seed: int


@dataclass(frozen=True)
class FinishDraw:
    """A part instance's (or a distractor's) finish. ``metal``: the conductor (a scene metal) of the metal finishes
    and of the metal under worn paint, its look (measured IOR choice, tint) from ``seed``; ``alpha``: GGX alpha of
    the metal (or of the plastic); ``anisotropy``: ``alpha_v = alpha * (1 - anisotropy)`` along the surface's
    second direction; ``colour``: plastic or paint reflectance; ``paint_alpha``, ``wear``: the worn paint's
    roughness and the fraction of it worn through (mask from ``seed``, ``mask_px`` wide)."""

    family: str
    metal: str | None = None
    alpha: float = 0.1
    anisotropy: float = 0.0
    colour: Rgb | None = None
    paint_alpha: float = 0.0
    wear: float = 0.0
    mask_px: int = 0
    seed: int = 0

    @property
    def is_metal(self) -> bool:
        """Whether the finish is bare conductor (what a stereo sensor loses in specular patches)."""
        return self.family in ("bare_metal", "anisotropic_metal")


@dataclass(frozen=True)
class LampDraw:
    """An extra lamp at ``position_m`` (world) aimed at the bin centre; ``size_m``: an area light's side (0 for a
    point light); ``irradiance``: at the bin centre; ``tint``: per-channel gains."""

    family: str
    position_m: tuple[float, float, float]
    size_m: float
    irradiance: float
    tint: Rgb


@dataclass(frozen=True)
class LightingDraw:
    """The environment (``sky`` family, or ``map_file`` for the scene's own map) with its ``strength`` and
    ``rotation_deg`` about the world's up axis, the sky map made from ``seed`` (``sky_px`` rows), and the lamps."""

    sky: str
    strength: float
    rotation_deg: float
    sun_elevation_deg: float
    sky_px: int
    seed: int
    lamps: tuple[LampDraw, ...] = ()


@dataclass(frozen=True)
class PieceDraw:
    """A distractor: ``shape`` (``box``, ``cylinder``, ``sphere`` or ``builtin:<part>``), ``size_m`` (a box's
    extents; a cylinder's diameter, diameter, length; a sphere's diameter three times; a built-in part's own size,
    unused), its density and finish. ``T_world_obj``: 16 numbers for a piece laid around the bin; None for one
    dropped into it (its pose comes from the drop)."""

    shape: str
    size_m: tuple[float, float, float]
    density_kg_m3: float
    finish: FinishDraw
    T_world_obj: tuple[float, ...] | None = None


@dataclass(frozen=True)
class DistractorsDraw:
    in_bin: tuple[PieceDraw, ...] = ()
    around_bin: tuple[PieceDraw, ...] = ()


@dataclass(frozen=True)
class CameraDraw:
    exposure_ev: float = 0.0
    white_balance: tuple[float, float] = (1.0, 1.0)  # red and blue gains against green
    defocus_sigma_px: float = 0.0
    motion_blur_px: float = 0.0
    motion_angle_deg: float = 0.0
    vignetting: float = 0.0
    jpeg_quality: int | None = None


@dataclass(frozen=True)
class GeometryDraw:
    """The bin's pose in the room: an offset along x and y and a yaw (degrees)."""

    bin_offset_m: tuple[float, float] = (0.0, 0.0)
    bin_yaw_deg: float = 0.0

    def T_room_bin(self) -> np.ndarray:
        """(4, 4) the bin's pose in the room frame (the scene's world frame before the jitter)."""
        R = rotation_about(np.array([0.0, 0.0, 1.0]), math.radians(self.bin_yaw_deg))
        return make_T(R, [self.bin_offset_m[0], self.bin_offset_m[1], 0.0])


@dataclass
class ItemDraws:
    """Every enabled knob's draw for one item attempt (None: the knob is off). ``surfaces``: ``floor`` and ``bin``;
    ``parts``: one finish per part instance, in instance order (set once the drop has made the instances)."""

    surfaces: dict[str, SurfaceDraw] | None = None
    parts: tuple[FinishDraw, ...] | None = None
    lighting: LightingDraw | None = None
    distractors: DistractorsDraw | None = None
    camera: CameraDraw | None = None
    geometry: GeometryDraw | None = None

    def to_json(self) -> dict:
        """The draws of the enabled knobs as plain data (the item record's ``randomisation``)."""
        out = {}
        for knob in KNOBS:
            value = getattr(self, knob)
            if value is None:
                continue
            if isinstance(value, dict):
                out[knob] = {k: asdict(v) for k, v in value.items()}
            elif isinstance(value, tuple):
                out[knob] = [asdict(v) for v in value]
            else:
                out[knob] = asdict(value)
        return out

    def families_drawn(self) -> set[str]:
        """Every family name the draws use (a held-apart family must never be among a training recipe's)."""
        names: set[str] = set()
        if self.surfaces:
            names |= {s.family for s in self.surfaces.values()}
        if self.parts:
            names |= {f.family for f in self.parts}
        if self.lighting:
            names |= {self.lighting.sky} | {lamp.family for lamp in self.lighting.lamps}
        if self.distractors:
            names |= {p.finish.family for p in (*self.distractors.in_bin, *self.distractors.around_bin)}
        return names - {"map_file"}


def draw_item(
    spec: RandomisationSpec,
    stream: np.random.SeedSequence,
    container: ContainerSpec,
    floor_z_m: float,
    has_map_file: bool = False,
) -> ItemDraws:
    """The draws of every enabled knob but ``parts`` (which needs the drop's instances: ``draw_parts``).
    ``floor_z_m``: height of the room's floor (world frame), where pieces around the bin lie."""
    fam = spec.families
    out = ItemDraws()
    if spec.surfaces.enabled:
        rng = knob_rng(stream, "surfaces")
        out.surfaces = {where: draw_surface(spec.surfaces, fam, rng) for where in ("floor", "bin")}
    if spec.lighting.enabled:
        out.lighting = draw_lighting(spec.lighting, fam, knob_rng(stream, "lighting"), has_map_file)
    if spec.distractors.enabled:
        rng = knob_rng(stream, "distractors")
        out.distractors = draw_distractors(spec.distractors, fam, rng, container, floor_z_m)
    if spec.camera.enabled:
        out.camera = draw_camera(spec.camera, knob_rng(stream, "camera"))
    if spec.geometry.enabled:
        out.geometry = draw_geometry(spec.geometry, knob_rng(stream, "geometry"))
    return out


def draw_surface(knob: SurfacesKnob, families: FamiliesSpec, rng: np.random.Generator) -> SurfaceDraw:
    allowed = families.allowed("surface")
    family = allowed[int(rng.integers(len(allowed)))]
    hue, sat, val = SURFACE_HSV[family]
    hue = float(rng.uniform(0, 1)) if hue is None else hue + _u(rng, (-knob.hue_shift, knob.hue_shift))
    base = _rgb(hue, sat * _u(rng, knob.saturation), val * _u(rng, knob.brightness))
    return SurfaceDraw(family, base, _u(rng, knob.roughness), _u(rng, knob.tile_m), knob.texture_px, _seed(rng))


def draw_parts(
    spec: RandomisationSpec, stream: np.random.SeedSequence, materials: list[str]
) -> tuple[FinishDraw, ...] | None:
    """One finish per part instance (``materials``: each instance's scene material), or None when ``parts`` is
    off. An instance draws among the allowed finishes of its material class, or among all allowed finishes when
    its class has none left."""
    if not spec.parts.enabled:
        return None
    rng = knob_rng(stream, "parts")
    allowed = spec.families.allowed("finish")
    out = []
    for material in materials:
        kind = "metal" if material in METALS else material
        candidates = [f for f in FINISHES_BY_MATERIAL.get(kind, ()) if f in allowed] or list(allowed)
        family = candidates[int(rng.integers(len(candidates)))]
        metal = material if material in METALS else "steel"
        out.append(draw_finish(spec.parts, family, metal, rng))
    return tuple(out)


def draw_finish(knob: PartsKnob, family: str, metal: str, rng: np.random.Generator) -> FinishDraw:
    """A finish of ``family`` with ``metal`` as its conductor (bare, or under worn paint)."""
    alpha = _u(rng, knob.metal_roughness)
    if family == "bare_metal":
        return FinishDraw(family, metal, alpha, seed=_seed(rng))
    if family == "anisotropic_metal":
        return FinishDraw(family, metal, alpha, anisotropy=_u(rng, knob.anisotropy), seed=_seed(rng))
    if family == "plastic":
        colour = _rgb(float(rng.uniform(0, 1)), _u(rng, knob.plastic_saturation), _u(rng, knob.plastic_value))
        return FinishDraw(family, None, _u(rng, knob.plastic_roughness), colour=colour, seed=_seed(rng))
    if family == "worn_paint":
        colour = _rgb(float(rng.uniform(0, 1)), _u(rng, knob.paint_saturation), _u(rng, knob.paint_value))
        return FinishDraw(
            family, metal, alpha, colour=colour, paint_alpha=_u(rng, knob.plastic_roughness),
            wear=_u(rng, knob.paint_wear), mask_px=knob.mask_px, seed=_seed(rng),
        )  # fmt: skip
    raise ValueError(f"unknown finish family {family!r}")


def draw_lighting(
    knob: LightingKnob, families: FamiliesSpec, rng: np.random.Generator, has_map_file: bool
) -> LightingDraw:
    skies = families.allowed("sky")
    sky = "map_file" if has_map_file else skies[int(rng.integers(len(skies)))]
    strength, rotation = _u(rng, knob.environment_strength), _u(rng, knob.environment_rotation_deg)
    sun, seed = _u(rng, knob.sun_elevation_deg), _seed(rng)
    lamp_families = families.allowed("lamp")
    lamps = []
    for _ in range(int(rng.integers(knob.lamps[0], knob.lamps[1] + 1))):
        family = lamp_families[int(rng.integers(len(lamp_families)))]
        xy = rng.uniform(-knob.lamp_offset_m, knob.lamp_offset_m, 2)
        position = (float(xy[0]), float(xy[1]), _u(rng, knob.lamp_height_m))
        size = _u(rng, knob.lamp_size_m) if family == "area_light" else 0.0
        tint = tuple(float(v) for v in rng.uniform(knob.lamp_tint[0], knob.lamp_tint[1], 3))
        lamps.append(LampDraw(family, position, size, _u(rng, knob.lamp_irradiance), tint))
    return LightingDraw(sky, strength, rotation, sun, knob.sky_px, seed, tuple(lamps))


def draw_camera(knob: CameraKnob, rng: np.random.Generator) -> CameraDraw:
    wb = (_u(rng, knob.white_balance), _u(rng, knob.white_balance))
    quality = None if knob.jpeg_quality is None else int(rng.integers(knob.jpeg_quality[0], knob.jpeg_quality[1] + 1))
    return CameraDraw(
        exposure_ev=_u(rng, knob.exposure_ev), white_balance=wb, defocus_sigma_px=_u(rng, knob.defocus_sigma_px),
        motion_blur_px=_u(rng, knob.motion_blur_px), motion_angle_deg=float(rng.uniform(0, 180)),
        vignetting=_u(rng, knob.vignetting), jpeg_quality=quality,
    )  # fmt: skip


def draw_geometry(knob: GeometryKnob, rng: np.random.Generator) -> GeometryDraw:
    offset = rng.uniform(-knob.bin_offset_m, knob.bin_offset_m, 2)
    return GeometryDraw((float(offset[0]), float(offset[1])), _u(rng, (-knob.bin_yaw_deg, knob.bin_yaw_deg)))


def draw_distractors(
    knob: DistractorsKnob,
    families: FamiliesSpec,
    rng: np.random.Generator,
    container: ContainerSpec,
    floor_z_m: float,
) -> DistractorsDraw:
    """Pieces for the bin (posed by the drop) and pieces laid on the floor around it, each resting on a face (a
    cylinder upright or on its side) at a random yaw, clear of the bin's outer walls and of each other. A piece's
    finish is an allowed metal finish with probability ``metal_fraction``, else an allowed plastic or paint (either
    kind falls back to the other when none of it is allowed), drawn at ``PartsKnob``'s default ranges."""
    allowed = families.allowed("finish")
    in_bin = tuple(_piece(knob, allowed, rng) for _ in range(int(rng.integers(knob.in_bin[0], knob.in_bin[1] + 1))))
    around: list[PieceDraw] = []
    placed: list[tuple[np.ndarray, float]] = []
    half = np.array(container.inner_size_m[:2]) / 2 + container.wall_thickness_m
    for _ in range(int(rng.integers(knob.around_bin[0], knob.around_bin[1] + 1))):
        piece = _piece(knob, allowed, rng)
        radius = 0.5 * float(np.linalg.norm(piece.size_m[:2]))
        for _try in range(20):
            angle = float(rng.uniform(0, 2 * np.pi))
            d = np.array([math.cos(angle), math.sin(angle)])
            to_wall = float(min(half[0] / max(abs(d[0]), 1e-9), half[1] / max(abs(d[1]), 1e-9)))
            xy = d * (to_wall + _u(rng, knob.around_margin_m) + radius)
            if all(np.linalg.norm(xy - c) > radius + r for c, r in placed):
                break
        else:
            continue
        placed.append((xy, radius))
        around.append(_laid(piece, xy, floor_z_m, rng))
    return DistractorsDraw(in_bin, tuple(around))


def _piece(knob: DistractorsKnob, finishes: tuple[str, ...], rng: np.random.Generator) -> PieceDraw:
    if knob.builtin_parts and rng.random() < knob.builtin_fraction:
        shape = f"builtin:{knob.builtin_parts[int(rng.integers(len(knob.builtin_parts)))]}"
        size = (0.0, 0.0, 0.0)
    else:
        shape = knob.shapes[int(rng.integers(len(knob.shapes)))]
        a, b, c = (_u(rng, knob.size_m) for _ in range(3))
        size = {"box": (a, b, c), "cylinder": (a, a, b), "sphere": (a, a, a)}[shape]
    density = _u(rng, knob.density_kg_m3)
    metal = [f for f in finishes if f in FINISHES_BY_MATERIAL["metal"]]
    other = [f for f in finishes if f not in FINISHES_BY_MATERIAL["metal"]]
    candidates = (metal or other) if rng.random() < knob.metal_fraction else (other or metal)
    family = candidates[int(rng.integers(len(candidates)))]
    return PieceDraw(shape, size, density, draw_finish(_DISTRACTOR_FINISH, family, "steel", rng))


def _laid(piece: PieceDraw, xy: np.ndarray, floor_z_m: float, rng: np.random.Generator) -> PieceDraw:
    """``piece`` resting on the floor at ``xy`` (a built-in part upright in its own frame)."""
    yaw = rotation_about(np.array([0.0, 0.0, 1.0]), float(rng.uniform(0, 2 * np.pi)))
    R = yaw
    height = piece.size_m[2] / 2
    if piece.shape == "cylinder" and rng.random() < 0.5:  # on its side
        R = yaw @ rotation_about(np.array([1.0, 0.0, 0.0]), math.pi / 2)
        height = piece.size_m[0] / 2
    elif piece.shape.startswith("builtin:"):
        height = -float(builtin_part(piece.shape.removeprefix("builtin:")).bounds_m[0, 2])
    T = make_T(R, [float(xy[0]), float(xy[1]), floor_z_m + height])
    return PieceDraw(piece.shape, piece.size_m, piece.density_kg_m3, piece.finish, tuple(T.ravel().tolist()))
