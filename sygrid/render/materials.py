"""Scene material names -> Mitsuba BSDF dicts, randomised from an injected ``np.random.Generator``.

Metals are rough conductors (GGX) with measured complex IORs from Mitsuba's table where one exists. Mitsuba has no
table for iron or zinc, so steel draws from chromium / nickel (the platform notes), zinc plating from nickel /
aluminium with a faint blue-grey tint, and brass uses an explicit RGB eta/k fit of Cu-Zn alloy. ``painted`` is a
rough plastic with a random saturated colour, ``plastic`` (bins, crates) a rough plastic in the muted colours of
industrial bins. Roughness is GGX ``alpha`` (perceptual roughness squared is not used: these are alpha values).
"""

from __future__ import annotations

import colorsys
from collections.abc import Callable

import numpy as np

MATERIALS: tuple[str, ...] = ("steel", "zinc", "brass", "aluminium", "painted", "plastic")

# (alpha_min, alpha_max) GGX roughness per metal: turned/ground steel is glossy, zinc plating is satin.
_ALPHA_RANGE = {"steel": (0.06, 0.25), "zinc": (0.15, 0.35), "brass": (0.08, 0.25), "aluminium": (0.10, 0.30)}
# Brass (about 70/30 Cu-Zn) as RGB complex IOR at roughly 650/550/450 nm.
_BRASS_ETA = (0.444, 0.527, 1.094)
_BRASS_K = (3.695, 2.765, 1.829)


def _rgb(value: tuple[float, float, float] | np.ndarray) -> dict:
    return {"type": "rgb", "value": [float(v) for v in value]}


def _alpha(material: str, rng: np.random.Generator) -> float:
    lo, hi = _ALPHA_RANGE[material]
    return float(rng.uniform(lo, hi))


def _steel(rng: np.random.Generator) -> dict:
    name = ("Cr", "Ni_palik")[int(rng.integers(2))]
    return {"type": "roughconductor", "distribution": "ggx", "material": name, "alpha": _alpha("steel", rng)}


def _zinc(rng: np.random.Generator) -> dict:
    name = ("Ni_palik", "Al")[int(rng.integers(2))]
    tint = rng.uniform(0.85, 0.95, 3)
    tint[2] = min(1.0, tint[2] + 0.05)  # zinc plating leans slightly blue
    return {
        "type": "roughconductor", "distribution": "ggx", "material": name, "alpha": _alpha("zinc", rng),
        "specular_reflectance": _rgb(tint),
    }  # fmt: skip


def _brass(rng: np.random.Generator) -> dict:
    return {
        "type": "roughconductor", "distribution": "ggx", "alpha": _alpha("brass", rng),
        "eta": _rgb(_BRASS_ETA), "k": _rgb(_BRASS_K),
    }  # fmt: skip


def _aluminium(rng: np.random.Generator) -> dict:
    return {"type": "roughconductor", "distribution": "ggx", "material": "Al", "alpha": _alpha("aluminium", rng)}


def _painted(rng: np.random.Generator) -> dict:
    hue, sat, val = rng.uniform(0, 1), rng.uniform(0.5, 0.95), rng.uniform(0.35, 0.85)
    return {
        "type": "roughplastic", "distribution": "ggx", "alpha": float(rng.uniform(0.1, 0.4)),
        "diffuse_reflectance": _rgb(colorsys.hsv_to_rgb(hue, sat, val)),
    }  # fmt: skip


def _plastic(rng: np.random.Generator) -> dict:
    # Industrial bins: grey, blue, black, green, red-ish, at moderate saturation.
    hue = float(rng.choice([0.0, 0.33, 0.58, 0.62, 0.08]))
    sat = float(rng.uniform(0.0, 0.6))
    val = float(rng.uniform(0.08, 0.6))
    return {
        "type": "roughplastic", "distribution": "ggx", "alpha": float(rng.uniform(0.2, 0.5)),
        "diffuse_reflectance": _rgb(colorsys.hsv_to_rgb(hue, sat, val)),
    }  # fmt: skip


_BUILDERS: dict[str, Callable[[np.random.Generator], dict]] = {
    "steel": _steel,
    "zinc": _zinc,
    "brass": _brass,
    "aluminium": _aluminium,
    "painted": _painted,
    "plastic": _plastic,
}


def material_bsdf(material: str, rng: np.random.Generator) -> dict:
    """The Mitsuba BSDF dict (for ``mi.load_dict``) of a scene material, with randomised roughness and colour."""
    builder = _BUILDERS.get(material)
    if builder is None:
        raise ValueError(f"unknown material {material!r}; valid materials: {', '.join(MATERIALS)}")
    return builder(rng)


def floor_bsdf(rng: np.random.Generator) -> dict:
    """A matte grey-ish floor (workbench, concrete) under the bin."""
    grey = float(rng.uniform(0.15, 0.6))
    tint = rng.uniform(0.9, 1.1, 3)
    return {"type": "diffuse", "reflectance": _rgb(np.clip(grey * tint, 0.0, 1.0))}
