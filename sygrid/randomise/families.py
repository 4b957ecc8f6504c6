"""The named families of the randomisation (textures of floors and bins, finishes of parts, skies, lamps) and the
recipe's choice among them (``FamiliesSpec``: ``include`` / ``exclude`` by name).

Every family name is unique across the categories, so a name alone says what it is. A test recipe can use a family
that its training recipe excludes: a held-apart family, never drawn in training (``allowed`` is the only way the
draws see the families).
"""

from __future__ import annotations

from pydantic import BaseModel, model_validator

from sygrid.scene import STRICT_NUMBERS

#: Family names by category. ``surface``: procedural textures of the floor and the bin; ``finish``: a part
#: instance's material; ``sky``: the environment light; ``lamp``: the extra lights.
FAMILIES: dict[str, tuple[str, ...]] = {
    "surface": ("plain", "wood", "concrete", "cardboard", "brushed_metal", "painted_metal", "rubber_mat"),
    "finish": ("bare_metal", "anisotropic_metal", "plastic", "worn_paint"),
    "sky": ("uniform_sky", "gradient_sky", "sun_sky", "window_sky"),
    "lamp": ("area_light", "point_light"),
}
ALL_FAMILIES: tuple[str, ...] = tuple(name for names in FAMILIES.values() for name in names)
#: The finishes a part of each scene material class may take (``sygrid.scene.Material``; metals share one class).
FINISHES_BY_MATERIAL: dict[str, tuple[str, ...]] = {
    "metal": ("bare_metal", "anisotropic_metal"),
    "painted": ("worn_paint",),
    "plastic": ("plastic",),
}


class FamiliesSpec(BaseModel):
    """Which families the draws may use. ``include``: when it names any family of a category, only the named
    families of that category are allowed (categories it does not name are not restricted); ``exclude``: never
    allowed. Unknown names are errors, and so is a name in both lists."""

    model_config = STRICT_NUMBERS

    include: tuple[str, ...] = ()
    exclude: tuple[str, ...] = ()

    @model_validator(mode="after")
    def _known(self) -> FamiliesSpec:
        for key in ("include", "exclude"):
            unknown = [n for n in getattr(self, key) if n not in ALL_FAMILIES]
            if unknown:
                raise ValueError(f"{key}: unknown famil(ies) {unknown}; valid: {list(ALL_FAMILIES)}")
        both = sorted(set(self.include) & set(self.exclude))
        if both:
            raise ValueError(f"{both} both included and excluded")
        return self

    def allowed(self, category: str) -> tuple[str, ...]:
        """The families of ``category`` (a key of ``FAMILIES``) the draws may use, in ``FAMILIES`` order."""
        names = FAMILIES[category]
        named = [n for n in names if n in self.include]
        return tuple(n for n in (named or names) if n not in self.exclude)
