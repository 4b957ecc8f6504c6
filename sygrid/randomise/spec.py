"""A recipe's ``randomisation`` block: one knob per aspect of an item's look, each off unless ``enabled``.

A knob holds ranges (``[min, max]``, drawn uniformly per item unless said otherwise; ``min == max`` fixes a value)
and an ``enabled`` switch. Every knob is off by default, and a recipe without the block (or with every knob off)
makes exactly the items it made before the block existed. ``families`` selects the named families of textures,
finishes and lights (``sygrid.randomise.families``) the knobs draw from.

The knobs (units in the field names; colours are linear reflectances or gains):

- ``surfaces``: procedural textures of the floor and the bin (``surface`` families), colour and roughness;
- ``parts``: a finish per part instance (``finish`` families; a part keeps its material class: metal, painted,
  plastic, see ``FINISHES_BY_MATERIAL``), metal roughness and anisotropy, plastic and paint colours, paint wear;
- ``lighting``: a procedural sky (``sky`` families) or the scene's map, its strength and rotation, and extra lamps
  (``lamp`` families: area lights give soft shadows, point lights hard ones) with irradiance and size ranges;
- ``distractors``: unlabelled clutter (primitives, optionally built-in parts) dropped into the bin with the parts
  and laid on the floor around it: it occludes parts and never appears in their labels;
- ``camera``: image effects after rendering: exposure, white balance, defocus and motion blur, vignetting, then
  (after the recipe's sensor) JPEG compression;
- ``geometry``: the camera's distance and tilt ranges (a ``CameraPoseSampling`` that replaces the scene's) and the
  bin's pose in the room (an offset and a yaw: the camera moves by the inverse, so a fixed camera sees the bin move).
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import AfterValidator, BaseModel, Field, Strict, field_validator, model_validator

from sygrid.objects.parts import BUILTIN_PARTS
from sygrid.randomise.families import FAMILIES, FamiliesSpec
from sygrid.scene import STRICT_NUMBERS, Bool, CameraPoseSampling, Float, NonNegative


def _ordered(value: tuple) -> tuple:
    if value[1] < value[0]:
        raise ValueError(f"must be [min, max] with min <= max, got {list(value)}")
    return value


def _num(**bounds: float) -> object:
    return Annotated[float, Strict(), Field(**bounds)]


def _range(item: object) -> object:
    """``[min, max]`` of ``item`` numbers, ``min <= max``."""
    return Annotated[tuple[item, item], AfterValidator(_ordered)]


Range = _range(Float)
PositiveRange = _range(_num(gt=0))
NonNegativeRange = _range(_num(ge=0))
UnitRange = _range(_num(ge=0, le=1))
CountRange = _range(Annotated[int, Strict(), Field(ge=0, le=32)])
TexturePx = Annotated[int, Strict(), Field(ge=8, le=2048)]
Fraction = _num(ge=0, le=1)
AnisotropyRange = _range(_num(ge=0, lt=1))
ElevationRange = _range(_num(ge=0, le=90))
QualityRange = _range(Annotated[int, Strict(), Field(ge=1, le=100)])
HueShift = _num(ge=0, le=0.5)
YawDeg = _num(ge=0, le=180)
SkyPx = Annotated[int, Strict(), Field(ge=8, le=1024)]


class Knob(BaseModel):
    model_config = STRICT_NUMBERS

    enabled: Bool = False


class SurfacesKnob(Knob):
    """Floor and bin textures. Each family has its own base colour; ``brightness`` and ``saturation`` scale it,
    ``hue_shift`` (fraction of the hue circle) turns it either way. ``roughness``: GGX alpha of the surface's
    gloss (of the metal itself for ``brushed_metal``). ``tile_m``: side of one texture tile on the surface."""

    brightness: PositiveRange = (0.6, 1.4)
    saturation: NonNegativeRange = (0.6, 1.4)
    hue_shift: HueShift = 0.04
    roughness: PositiveRange = (0.15, 0.8)
    tile_m: PositiveRange = (0.15, 0.6)
    texture_px: TexturePx = 256


class PartsKnob(Knob):
    """A finish per part instance. Metals: GGX alpha ``metal_roughness``; ``anisotropic_metal`` stretches it by
    ``1 / (1 - anisotropy)`` along one surface direction. ``plastic_*``: a random hue at these saturation, value
    and alpha ranges. ``worn_paint``: paint (``paint_*`` colour, plastic alpha) over bare metal, ``paint_wear`` the
    fraction of the surface where the metal shows (a noise mask of ``mask_px`` pixels per side)."""

    metal_roughness: PositiveRange = (0.02, 0.4)
    anisotropy: AnisotropyRange = (0.5, 0.9)
    plastic_saturation: UnitRange = (0.0, 0.9)
    plastic_value: UnitRange = (0.05, 0.9)
    plastic_roughness: PositiveRange = (0.05, 0.5)
    paint_saturation: UnitRange = (0.4, 0.95)
    paint_value: UnitRange = (0.2, 0.85)
    paint_wear: UnitRange = (0.0, 0.4)
    mask_px: TexturePx = 128


class LightingKnob(Knob):
    """The environment and extra lamps; replaces the scene's sky and ``random_lights`` (its ``strength`` still
    scales everything). A scene ``map_file`` stays the environment (rotated and scaled by these ranges); else a
    procedural sky of ``sky_px`` rows. Lamps: ``lamp_irradiance`` at the bin centre (the renderer's radiance units
    times m^2), ``lamp_size_m`` the side of an area light, placed ``lamp_height_m`` above the bin and up to
    ``lamp_offset_m`` to the side, tinted by per-channel gains ``lamp_tint``."""

    environment_strength: NonNegativeRange = (0.3, 1.5)
    environment_rotation_deg: Range = (0.0, 360.0)
    sun_elevation_deg: ElevationRange = (20.0, 80.0)
    sky_px: SkyPx = 64
    lamps: CountRange = (0, 3)
    lamp_irradiance: NonNegativeRange = (0.3, 3.0)
    lamp_size_m: PositiveRange = (0.05, 0.5)
    lamp_height_m: PositiveRange = (0.5, 1.5)
    lamp_offset_m: NonNegative = 0.8
    lamp_tint: PositiveRange = (0.85, 1.15)


Shape = Literal["box", "cylinder", "sphere"]


class DistractorsKnob(Knob):
    """Unlabelled clutter: ``in_bin`` pieces dropped with the parts (they settle in the pile), ``around_bin``
    pieces laid on the floor within ``around_margin_m`` of the bin's outer walls. A piece is a primitive of
    ``shapes`` sized ``size_m`` (box side, cylinder diameter and length, sphere diameter; each drawn) or, when
    ``builtin_parts`` names any, one of those parts (chosen with probability ``builtin_fraction``): parts the
    scene does not label. A piece is bare metal with probability ``metal_fraction``, else a plastic of random
    colour; ``density_kg_m3`` sets its mass in the drop."""

    in_bin: CountRange = (1, 3)
    around_bin: CountRange = (0, 4)
    shapes: tuple[Shape, ...] = ("box", "cylinder", "sphere")
    size_m: PositiveRange = (0.01, 0.05)
    builtin_parts: tuple[str, ...] = ()
    builtin_fraction: Fraction = 0.3
    around_margin_m: NonNegativeRange = (0.01, 0.2)
    metal_fraction: Fraction = 0.3
    density_kg_m3: PositiveRange = (300.0, 1500.0)

    @field_validator("shapes")
    @classmethod
    def _some_shape(cls, shapes: tuple[str, ...]) -> tuple[str, ...]:
        if not shapes:
            raise ValueError("must name at least one of 'box', 'cylinder', 'sphere'")
        return shapes

    @field_validator("builtin_parts")
    @classmethod
    def _known_parts(cls, names: tuple[str, ...]) -> tuple[str, ...]:
        unknown = [n for n in names if n not in BUILTIN_PARTS]
        if unknown:
            raise ValueError(f"unknown built-in part(s) {unknown}; valid: {list(BUILTIN_PARTS)}")
        return names


class CameraKnob(Knob):
    """Image effects, applied to the rendered RGB in linear light: defocus (Gaussian, ``defocus_sigma_px``),
    motion blur (a line ``motion_blur_px`` long at a random angle), vignetting (``vignetting``: the fraction of
    light lost at the image corners, falling off with the squared radius), exposure (``exposure_ev`` stops) and
    white balance (red and blue gains ``white_balance`` against green); after the recipe's sensor, JPEG at a
    quality drawn from ``jpeg_quality`` (null: no compression). Pixel amounts are in the image's own pixels. The
    depth image is not touched."""

    exposure_ev: Range = (-1.0, 1.0)
    white_balance: PositiveRange = (0.85, 1.15)
    defocus_sigma_px: NonNegativeRange = (0.0, 1.5)
    motion_blur_px: NonNegativeRange = (0.0, 3.0)
    vignetting: UnitRange = (0.0, 0.4)
    jpeg_quality: QualityRange | None = (60, 95)


class GeometryKnob(Knob):
    """``camera``: replaces the scene's ``camera.pose_sampling`` (distance, tilt, look-at jitter; a scene with a
    fixed ``T_world_camera`` keeps it). The bin's pose in the room: an offset of up to ``bin_offset_m`` along x
    and y and a yaw of up to ``bin_yaw_deg`` either way."""

    camera: CameraPoseSampling | None = None
    bin_offset_m: NonNegative = 0.03
    bin_yaw_deg: YawDeg = 10.0


#: The knobs in the order their seed streams are numbered (``sygrid.randomise.draws``): a fixed order, so adding
#: a knob at the end never changes another knob's draws.
KNOBS: tuple[str, ...] = ("surfaces", "parts", "lighting", "distractors", "camera", "geometry")
#: The knobs that change only how an item looks, never its labels.
APPEARANCE_KNOBS: tuple[str, ...] = ("surfaces", "parts", "lighting", "camera")


class RandomisationSpec(BaseModel):
    """The recipe's ``randomisation`` block (see the module doc)."""

    model_config = STRICT_NUMBERS

    surfaces: SurfacesKnob = SurfacesKnob()
    parts: PartsKnob = PartsKnob()
    lighting: LightingKnob = LightingKnob()
    distractors: DistractorsKnob = DistractorsKnob()
    camera: CameraKnob = CameraKnob()
    geometry: GeometryKnob = GeometryKnob()
    families: FamiliesSpec = FamiliesSpec()

    @model_validator(mode="after")
    def _families_left(self) -> RandomisationSpec:
        """An enabled knob must have a family left to draw from."""
        needs = {"surfaces": ("surface",), "parts": ("finish",), "lighting": ("sky",), "distractors": ("finish",)}
        if self.lighting.lamps[1] > 0:
            needs["lighting"] = ("sky", "lamp")
        for knob, categories in needs.items():
            if not getattr(self, knob).enabled:
                continue
            for category in categories:
                if not self.families.allowed(category):
                    raise ValueError(
                        f"families: every {category} family ({list(FAMILIES[category])}) is excluded, but {knob} "
                        "is enabled; allow one or disable the knob"
                    )
        return self

    @property
    def enabled(self) -> tuple[str, ...]:
        """The names of the enabled knobs, in ``KNOBS`` order."""
        return tuple(k for k in KNOBS if getattr(self, k).enabled)
