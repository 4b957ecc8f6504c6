"""A model folder's ``manifest.json``: the schema (pydantic, strict: unknown keys and bad values are errors naming the
file and field), loading it, and what it names (the parts, their pose strategies, the depth tare's settings).

``format`` ``sygrid-models/1``; ``objects`` the parts (built-in names, CAD files or a ``catalogue``'s parts, relative
to the folder); ``detector`` and ``pose`` the ONNX files with their settings; ``refine``, ``verify``, ``depth_tare``
the pipeline's stages (``perception.pipeline``).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from perception.depth_tare import TareConfig
from perception.pose_strategies import STRATEGIES, StrategyConfig
from perception.tiling import DEFAULT_TILE_OVERLAP
from perception.verify import VerifyConfig
from sygrid.drop import resolve_parts
from sygrid.errors import ConfigError
from sygrid.fileio import read_json
from sygrid.objects.model import ObjectModel
from sygrid.scene import ObjectSpec, validation_message

if TYPE_CHECKING:
    from perception.detector import YoloSegDetector

MANIFEST_NAME = "manifest.json"
MANIFEST_FORMAT = "sygrid-models/1"


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class DetectorEntry(_Strict):
    onnx: str
    conf_threshold: float = Field(default=0.4, gt=0, lt=1)
    iou_threshold: float = Field(default=0.6, gt=0, le=1)
    input_size: int | None = Field(default=None, ge=32, le=4096)
    # Where and at what scale the detector looks (perception.tiling.ViewSettings) and the smallest part size in
    # network pixels it resolves reliably (sygrid.part_pixels); None: the plain full-frame behaviour / no check.
    scale: float | None = Field(default=None, ge=0.05, le=8)
    tile_px: int | None = Field(default=None, ge=32, le=4096)
    tile_overlap: float = Field(default=DEFAULT_TILE_OVERLAP, ge=0, le=0.9)
    min_part_px: float | None = Field(default=None, gt=0)


class PoseEntry(_Strict):
    onnx: str
    method: Literal["direct", "pnp"] = "direct"
    # part name -> pose strategy (perception.pose_strategies.STRATEGIES); None: the network + the refiner
    strategies: dict[str, str] | None = None
    # the strategies' search ends once a fit's depth agreement reaches this (StrategyConfig.good_confidence): lower
    # is faster under depth noise and accepts fewer right poses (sygrid bench perception --search-bars)
    search_bar: float = Field(default=StrategyConfig().good_confidence, gt=0, le=1)

    def search_config(self) -> StrategyConfig:
        """The strategies' search settings this entry sets (the rest at their defaults)."""
        return StrategyConfig(good_confidence=self.search_bar)

    @field_validator("strategies")
    @classmethod
    def _known_strategies(cls, value: dict[str, str] | None) -> dict[str, str] | None:
        for name, strategy in (value or {}).items():
            if strategy not in STRATEGIES:
                raise ValueError(f"{name}: unknown pose strategy {strategy!r} (known: {', '.join(STRATEGIES)})")
        return value


class VerifyEntry(_Strict):
    """The verification of the strategies' poses (perception.verify.VerifyConfig)."""

    min_confidence: float = Field(default=VerifyConfig().min_confidence, ge=0, le=1)
    # part name -> that part's own threshold (VerifyConfig.part_min_confidence); the others use min_confidence
    part_min_confidence: dict[str, Annotated[float, Field(ge=0, le=1)]] = {}
    depth_noise_m: float = Field(default=0.0, ge=0, lt=0.1)

    def config(self) -> VerifyConfig:
        """The verifier's settings these entries set (the rest at VerifyConfig's defaults)."""
        return VerifyConfig(
            min_confidence=self.min_confidence,
            part_min_confidence=dict(self.part_min_confidence),
            depth_noise_m=self.depth_noise_m,
        )

    def thresholds(self, models: dict[int, ObjectModel], path: Path) -> dict[int, float]:
        """obj_id -> the verification threshold of each of ``models``; ConfigError naming ``path`` when
        ``part_min_confidence`` names a part that is not one of them."""
        names = {m.name for m in models.values()}
        unknown = sorted(set(self.part_min_confidence) - names)
        if unknown:
            raise ConfigError(f"{path}: verify.part_min_confidence: no object named {', '.join(unknown)} in objects "
                              f"(the objects: {', '.join(sorted(names))})")  # fmt: skip
        config = self.config()
        return {obj_id: config.threshold(m.name) for obj_id, m in models.items()}


class DepthTareEntry(_Strict):
    """The depth tare on the bin's floor (perception.depth_tare.TareConfig), used where a floor plane is given."""

    enabled: bool = True
    fit_gain: bool = False
    min_floor_px: int = Field(default=TareConfig().min_floor_px, ge=1)


class RefineEntry(_Strict):
    enabled: bool = True
    max_refined: int | None = Field(default=None, ge=1)


class Manifest(_Strict):
    format: Literal["sygrid-models/1"]
    catalogue: str | None = None  # a parts catalogue (sygrid.catalogue), relative to the model folder
    objects: tuple[ObjectSpec, ...]
    detector: DetectorEntry
    pose: PoseEntry
    refine: RefineEntry = RefineEntry()
    verify: VerifyEntry = VerifyEntry()
    depth_tare: DepthTareEntry = DepthTareEntry()
    min_mask_px: int = Field(default=30, ge=0)

    @model_validator(mode="after")
    def _catalogue_for_its_parts(self) -> Manifest:
        named = [f"objects[{k}]" for k, o in enumerate(self.objects) if o.catalogue_part is not None]
        if named and self.catalogue is None:
            raise ValueError(f"{', '.join(named)} name(s) a 'catalogue_part': give the manifest's 'catalogue' file")
        return self


def manifest_models(folder: str | Path, manifest: Manifest) -> dict[int, ObjectModel]:
    """obj_id -> model of each of the manifest's objects (its catalogue's parts resolved relative to ``folder``)."""
    models = resolve_parts(manifest.objects, manifest.catalogue, Path(folder), str(Path(folder) / MANIFEST_NAME))
    return {m.obj_id: m for m in models}


def check_detector_parts(detector: YoloSegDetector, models: dict[int, ObjectModel], where: str | Path) -> None:
    """Raises ConfigError when a detector class's obj_id is a part of ``models`` under another name: the detector
    and the manifest's objects (its catalogue) disagree about which part an id is."""
    clashes = [
        f"class {c} {name!r} is obj_id {obj_id}, which the manifest's objects call {models[obj_id].name!r}"
        for c, (obj_id, name) in enumerate(zip(detector.class_obj_ids, detector.class_names, strict=True))
        if obj_id in models and models[obj_id].name != name
    ]
    if clashes:
        raise ConfigError(
            f"{where}: the detector's parts disagree with the manifest's objects: {'; '.join(clashes)}. Pack the "
            "models with the catalogue they were trained with (sygrid models pack --catalogue)"
        )


def load_manifest(folder: Path) -> Manifest:
    path = folder / MANIFEST_NAME
    if not path.is_file():
        raise ConfigError(f"{folder}: not a model folder (no {MANIFEST_NAME})")
    try:
        manifest = Manifest.model_validate(read_json(path, "model manifest"))
    except ValidationError as exc:
        raise ConfigError(validation_message(exc, str(path))) from None
    for key, entry in (("detector.onnx", manifest.detector.onnx), ("pose.onnx", manifest.pose.onnx)):
        if not (folder / entry).is_file():
            raise ConfigError(f"{path}: {key}: no file {folder / entry}")
    return manifest


def tare_config(entry: DepthTareEntry, enabled: bool | None = None) -> TareConfig | None:
    """The depth tare's settings from the manifest's ``depth_tare`` (``enabled`` overrides its own); None: off."""
    if not (entry.enabled if enabled is None else enabled):
        return None
    return TareConfig(min_floor_px=entry.min_floor_px, fit_gain=entry.fit_gain)


def strategy_ids(by_name: dict[str, str], models: dict[int, ObjectModel], path: Path) -> dict[int, str]:
    """The manifest's ``pose.strategies`` (part name -> strategy) by obj_id; every object needs one."""
    ids = {m.name: obj_id for obj_id, m in models.items()}
    unknown = sorted(set(by_name) - set(ids))
    missing = sorted(set(ids) - set(by_name))
    if unknown or missing:
        raise ConfigError(
            f"{path}: pose.strategies: "
            + (
                f"no object named {', '.join(unknown)} in objects"
                if unknown
                else f"no strategy for {', '.join(missing)}"
            )
            + f" (the objects: {', '.join(sorted(ids))})"
        )
    return {ids[name]: strategy for name, strategy in by_name.items()}
