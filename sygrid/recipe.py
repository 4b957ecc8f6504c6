"""A dataset recipe: which scene to drop and render, in which formats and splits, with which render-mode mix.

A recipe is a JSON file (the ones the project trains on live in ``launch/recipes/``)::

    {"name": "builtin_train", "scene": "../scenes/builtin_bin.json", "split": "train", "val_fraction": 0.1,
     "formats": ["bop", "yolo", "coco"], "raster_fraction": 0.5}

``scene`` is a scene file path (relative to the recipe) or an inline scene object. ``raster_fraction`` of the items
are rendered with the rasterised mode instead of the scene's path-traced one: cheap items that also cover the look
of the simulated cell's camera. ``sensor`` names the RGB-D sensor model the items are seen through
(``sygrid.sensor.SENSOR_PRESETS``: "ideal", the default, keeps the rendered RGB and exact depth; any other writes
the sensed RGB and depth, and the exact depth beside it, ``depth_true/`` in BOP). Errors name the file and the
field, as the scene's do.

``randomisation`` (``sygrid.randomise.spec``) is the recipe's domain randomisation: knobs for surfaces, part
finishes, lighting, distractors, camera effects and geometry, and the families they may draw from, all off by
default. It lives in the recipe, not the scene: a scene describes a cell (its parts, bin and camera), and one scene
serves a training recipe and a test recipe that differ in what they randomise and in which families they hold
apart. A recipe whose knobs are all off has the hash (``Recipe.sha256``) it had before the block existed.

The quality gate (``sygrid.dataset_item``): an item is written only when its pile is within the drop's stability
bounds (the scene's ``physics``) and at least ``min_visible_instances`` instances are visible; otherwise it is drawn
again, at most ``max_redraws`` times, and then recorded as failed.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, Field, Strict, ValidationError, field_validator

from sygrid.errors import ConfigError
from sygrid.fileio import read_json
from sygrid.randomise.spec import RandomisationSpec
from sygrid.scene import (
    STRICT_NUMBERS,
    Bool,
    Int,
    SceneSpec,
    load_scene,
    parse_scene,
    scene_to_json,
    validation_message,
)
from sygrid.sensor import SENSOR_PRESETS

Format = Literal["bop", "yolo", "coco"]
Fraction = Annotated[float, Strict(), Field(ge=0, le=1)]


class RecipeSpec(BaseModel):
    model_config = STRICT_NUMBERS

    name: str
    scene: str | dict[str, Any]
    split: Literal["train", "test"] = "train"
    val_fraction: Annotated[float, Strict(), Field(ge=0, le=0.5)] = 0.1
    formats: tuple[Format, ...] = ("bop", "yolo", "coco")
    raster_fraction: Fraction = 0.0
    sensor: str = "ideal"
    full_masks: Bool = True
    # The quality gate: an item that fails it is drawn again (a new drop, view and render) at most this many times.
    max_redraws: Int = Field(default=5, ge=0, le=50)
    # Fewer visible instances (at least one visible pixel each) than this fail the gate; 0 accepts empty items.
    min_visible_instances: Int = Field(default=1, ge=0)
    randomisation: RandomisationSpec = RandomisationSpec()

    @field_validator("formats")
    @classmethod
    def _formats(cls, formats: tuple[str, ...]) -> tuple[str, ...]:
        if not formats:
            raise ValueError("must name at least one of 'bop', 'yolo', 'coco'")
        if len(set(formats)) != len(formats):
            raise ValueError(f"must not repeat a format, got {list(formats)}")
        return formats

    @field_validator("sensor")
    @classmethod
    def _sensor(cls, sensor: str) -> str:
        if sensor not in SENSOR_PRESETS:
            raise ValueError(f"unknown sensor {sensor!r}; valid: {sorted(SENSOR_PRESETS)}")
        return sensor


class Recipe:
    """A validated recipe with its scene resolved; ``base_dir`` is what the scene's relative paths are relative to."""

    def __init__(self, spec: RecipeSpec, scene: SceneSpec, base_dir: Path) -> None:
        self.spec = spec
        self.scene = scene
        self.base_dir = base_dir

    def to_json(self) -> dict:
        """The recipe with the scene inlined: what a dataset records, so it can be regenerated without the files.
        ``randomisation`` is left out when every knob is off and no family is named (the items are then the
        same as without the block, and so is the hash)."""
        data = {**self.spec.model_dump(mode="json"), "scene": scene_to_json(self.scene)}
        if self.spec.randomisation == RandomisationSpec():
            del data["randomisation"]
        return data

    def sha256(self) -> str:
        return hashlib.sha256(json.dumps(self.to_json(), sort_keys=True).encode()).hexdigest()

    def bop_split(self, is_val: bool) -> str:
        """BOP folder of an item: ``train_pbr`` / ``val_pbr`` for training recipes, ``test`` for test recipes."""
        if self.spec.split == "test":
            return "test"
        return "val_pbr" if is_val else "train_pbr"

    def label_split(self, is_val: bool) -> str:
        """YOLO / COCO split of an item: ``train`` / ``val``, or ``test``."""
        if self.spec.split == "test":
            return "test"
        return "val" if is_val else "train"


def parse_recipe(data: Any, source: str, base_dir: Path) -> Recipe:
    """Validates recipe data; ``source`` names it in errors, ``base_dir`` resolves a scene path."""
    try:
        spec = RecipeSpec.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(validation_message(exc, source)) from None
    if isinstance(spec.scene, str):
        scene_path = base_dir / spec.scene
        if not scene_path.is_file():
            raise ConfigError(f"{source}: scene: no scene file at {scene_path}")
        recipe = Recipe(spec, load_scene(scene_path), scene_path.parent)
    else:
        recipe = Recipe(spec, parse_scene(spec.scene, f"{source}: scene"), base_dir)
    labelled = {o.builtin for o in recipe.scene.objects if o.builtin is not None}
    clash = sorted(labelled & set(spec.randomisation.distractors.builtin_parts))
    if clash:
        raise ConfigError(
            f"{source}: randomisation.distractors.builtin_parts: {clash} are labelled parts of the scene; an "
            "unlabelled copy of a labelled part would teach a detector to miss it"
        )
    return recipe


def load_recipe(path: str | Path) -> Recipe:
    """Reads and validates a recipe file."""
    path = Path(path)
    return parse_recipe(read_json(path, "recipe file"), str(path), path.parent)
