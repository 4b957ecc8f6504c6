"""The object catalogue: the one file that declares a set of parts (id, name, mesh and unit or built-in, material,
mass or density, symmetries, grasp overrides). Scenes name its parts (``{"catalogue_part": "clamp"}`` with the
scene's top-level ``"catalogue"``), so ids and names have one source; BOP ``models/`` folders are imported from and
exported to it (``sygrid.catalogue_bop``).

A catalogue is a TOML file, or JSON by suffix (``{"part": [...]}``), with one ``[[part]]`` table per part::

    [[part]]
    id = 11                    # BOP obj_id >= 1, unique
    name = "clamp"             # unique; the class name in labels and models
    file = "cad/clamp.stl"     # relative to the catalogue file; or builtin = "hex_nut" (exactly one of the two)
    unit = "mm"                # required with file: "mm" or "m"
    material = "steel"         # sygrid.scene.Material; default: the built-in's own, or steel
    mass_kg = 0.042            # optional; or density_kg_m3; neither: the material's density x the volume
    symmetries_discrete = [[1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1]]   # 4x4 row-major, metres
    symmetries_continuous = [{axis = [0, 0, 1], offset_m = [0, 0, 0]}]
    [part.grasp]               # optional overrides of the grasp planner's defaults for this part
    max_opening_m = 0.06

Symmetries are in the CAD file's frame (metres, after the unit conversion); built-in parts declare their own.
Unknown keys are errors; every error names the file, the part (index and name) and the field, e.g.
``parts.toml: part[2] (clamp).unit: must be one of 'mm', 'm', got "cm"``. ``ConfigError`` only, never a traceback.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictFloat,
    StrictInt,
    ValidationError,
    field_validator,
    model_validator,
)

from sygrid.errors import ConfigError
from sygrid.fileio import read_json, write_bytes_atomic, write_json_atomic
from sygrid.objects.cad import MATERIAL_DENSITY_KG_M3, SUPPORTED_EXTENSIONS, load_cad
from sygrid.objects.model import ContinuousSymmetry, ObjectModel
from sygrid.objects.parts import BUILTIN_PARTS, builtin_part
from sygrid.objects.symmetry_proposal import SymmetryProposal
from sygrid.scene import ContinuousSymmetrySpec, Material, Vec3, check_sixteen_numbers, validation_message

CATALOGUE_SUFFIXES: tuple[str, ...] = (".toml", ".json")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class GraspOverrides(_Strict):
    """A part's own settings for the grasp planner (object frame, metres), where the defaults do not suit it.

    friction_coefficient: pad-part friction of this part's surface (``GraspSetParams.friction_coefficient``).
    min_width_m: do not grasp across spans narrower than this. max_opening_m: open the gripper at most this wide
    for this part (less than the stroke, e.g. to keep off its neighbours). approach_axis: the preferred approach
    direction (into the part) in the object frame, with approach_cone_deg the largest angle from it.
    """

    friction_coefficient: Annotated[StrictFloat, Field(gt=0, le=2)] | None = None
    min_width_m: Annotated[StrictFloat, Field(ge=0, le=0.5)] | None = None
    max_opening_m: Annotated[StrictFloat, Field(gt=0, le=0.5)] | None = None
    approach_axis: Vec3 | None = None
    approach_cone_deg: Annotated[StrictFloat, Field(gt=0, le=90)] | None = None

    @field_validator("approach_axis")
    @classmethod
    def _unit_axis(cls, axis: Vec3 | None) -> Vec3 | None:
        return None if axis is None else ContinuousSymmetrySpec(axis=axis).axis

    @model_validator(mode="after")
    def _consistent(self) -> GraspOverrides:
        if self.min_width_m is not None and self.max_opening_m is not None and self.max_opening_m <= self.min_width_m:
            raise ValueError(f"max_opening_m ({self.max_opening_m}) must be > min_width_m ({self.min_width_m})")
        if self.approach_cone_deg is not None and self.approach_axis is None:
            raise ValueError("'approach_cone_deg' needs 'approach_axis'")
        return self


class CataloguePart(_Strict):
    """One part of a catalogue (see the module docstring for the fields)."""

    id: Annotated[StrictInt, Field(ge=1)]
    name: Annotated[str, Field(min_length=1, pattern=r"^\S(.*\S)?$")]
    file: str | None = None
    builtin: str | None = None
    unit: Literal["mm", "m"] | None = None
    material: Material | None = None
    mass_kg: Annotated[StrictFloat, Field(gt=0)] | None = None
    density_kg_m3: Annotated[StrictFloat, Field(gt=0)] | None = None
    symmetries_discrete: tuple[tuple[StrictFloat, ...], ...] = ()
    symmetries_continuous: tuple[ContinuousSymmetrySpec, ...] = ()
    grasp: GraspOverrides | None = None

    @field_validator("symmetries_discrete")
    @classmethod
    def _sixteen_numbers(cls, syms: tuple[tuple[float, ...], ...]) -> tuple[tuple[float, ...], ...]:
        return check_sixteen_numbers(syms)

    @model_validator(mode="after")
    def _one_source(self) -> CataloguePart:
        if (self.builtin is None) == (self.file is None):
            raise ValueError("give exactly one of 'file' (a CAD path) or 'builtin' (a built-in part name)")
        if self.mass_kg is not None and self.density_kg_m3 is not None:
            raise ValueError("give 'mass_kg' or 'density_kg_m3', not both")
        if self.file is not None:
            if self.unit is None:
                raise ValueError("'unit' is required with 'file': 'mm' or 'm'")
            if Path(self.file).suffix.lower() not in SUPPORTED_EXTENSIONS:
                raise ValueError(f"file: must be a {', '.join(SUPPORTED_EXTENSIONS)} mesh, got {self.file!r}")
        elif self.builtin not in BUILTIN_PARTS:
            raise ValueError(f"builtin: unknown part {self.builtin!r}; valid: {', '.join(BUILTIN_PARTS)}")
        elif self.unit is not None or self.symmetries_discrete or self.symmetries_continuous:
            raise ValueError("'unit' and symmetries apply to 'file' parts only; built-in parts declare their own")
        return self


class CatalogueSpec(_Strict):
    part: Annotated[tuple[CataloguePart, ...], Field(min_length=1)]

    @field_validator("part")
    @classmethod
    def _unique(cls, parts: tuple[CataloguePart, ...]) -> tuple[CataloguePart, ...]:
        for key in ("id", "name"):
            values = [getattr(p, key) for p in parts]
            repeated = sorted({v for v in values if values.count(v) > 1}, key=str)
            if repeated:
                where = "; ".join(
                    f"{v!r} in " + ", ".join(f"part[{i}]" for i, w in enumerate(values) if w == v) for v in repeated
                )
                raise ValueError(f"{key} values must be unique, repeated: {where}")
        return parts


@dataclass(frozen=True, eq=False)
class Catalogue:
    """A validated catalogue: its parts, and the folder their files are relative to. ``source`` names it in
    errors. Models are built on first use and kept."""

    parts: tuple[CataloguePart, ...]
    base_dir: Path
    source: str = "<catalogue>"
    _models: dict[str, ObjectModel] = field(default_factory=dict, repr=False)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parts)

    def part(self, name: str) -> CataloguePart:
        for p in self.parts:
            if p.name == name:
                return p
        raise ConfigError(f"{self.source}: no part named {name!r}; its parts: {', '.join(self.names)}")

    def model(self, name: str) -> ObjectModel:
        """The ``ObjectModel`` of the part ``name``: its id, name, material, mass and symmetries as declared."""
        if name not in self._models:
            self._models[name] = _build_model(self, self.part(name))
        return self._models[name]

    def models(self) -> list[ObjectModel]:
        """Every part's model, in catalogue order."""
        return [self.model(p.name) for p in self.parts]

    def to_json(self) -> dict:
        """The catalogue as plain data (``{"part": [...]}``), defaults left out; file paths as given."""
        return {"part": [p.model_dump(mode="json", exclude_defaults=True) for p in self.parts]}


# ---------------------------------------------------------------------------------------------- reading and writing


def parse_catalogue(data: Any, source: str, base_dir: Path) -> Catalogue:
    """Validates catalogue data; ``source`` names it in errors, ``base_dir`` is where its file paths start."""
    try:
        spec = CatalogueSpec.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_with_part_names(validation_message(exc, source), data)) from None
    for i, p in enumerate(spec.part):
        if p.file is not None and not (base_dir / p.file).is_file():
            raise ConfigError(f"{source}: part[{i}] ({p.name}).file: no such file {p.file!r} ({base_dir / p.file})")
    return Catalogue(spec.part, base_dir, source)


def load_catalogue(path: str | Path) -> Catalogue:
    """Reads and validates a catalogue file (``.toml`` or ``.json``); file paths are relative to its folder."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in CATALOGUE_SUFFIXES:
        raise ConfigError(f"{path}: a catalogue must be a .toml or .json file")
    data = read_json(path, "catalogue") if suffix == ".json" else _read_toml(path)
    return parse_catalogue(data, str(path), path.parent)


def _read_toml(path: Path) -> Any:
    try:
        return tomllib.loads(path.read_text())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the catalogue ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None


def write_catalogue(catalogue: Catalogue, path: str | Path, header: str = "") -> Path:
    """Writes ``catalogue`` atomically as TOML or JSON (by ``path``'s suffix), file paths made relative to
    ``path``'s folder; ``header`` (TOML only) is written first as comment lines."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in CATALOGUE_SUFFIXES:
        raise ConfigError(f"{path}: a catalogue must be written as .toml or .json")
    moved = relocated(catalogue, path.parent)
    if suffix == ".json":
        return write_json_atomic(path, moved.to_json())
    comments = "".join(f"# {line}\n" if line else "#\n" for line in header.splitlines())
    return write_bytes_atomic(path, (comments + to_toml(moved.to_json())).encode())


def copy_catalogue(
    catalogue: Catalogue, names: list[str], folder: str | Path, file_name: str = "parts.toml", header: str = ""
) -> Path:
    """Writes the parts ``names`` of ``catalogue`` into ``folder`` as a catalogue of their own (``file_name``, with
    ``header`` as its comment) with their CAD files copied beside it (``<part name><suffix>``): a copy that moves
    with the folder it is in (a model folder). Returns the catalogue file's path. Raises ConfigError for a name that
    is no part of the catalogue."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    parts = []
    for name in names:
        part = catalogue.part(name)
        if part.file is not None:
            copied = f"{part.name}{Path(part.file).suffix.lower()}"
            shutil.copyfile(catalogue.base_dir / part.file, folder / copied)
            part = part.model_copy(update={"file": copied})
        parts.append(part)
    return write_catalogue(Catalogue(tuple(parts), folder, catalogue.source), folder / file_name, header)


def relocated(catalogue: Catalogue, base_dir: Path) -> Catalogue:
    """The same catalogue with its file paths relative to ``base_dir`` (where it is about to be written)."""
    parts = tuple(
        p
        if p.file is None
        else p.model_copy(update={"file": Path(os.path.relpath(catalogue.base_dir / p.file, base_dir)).as_posix()})
        for p in catalogue.parts
    )
    return Catalogue(parts, Path(base_dir), catalogue.source)


def to_toml(data: dict) -> str:
    """A catalogue's plain data as TOML: an array of ``[[part]]`` tables, each with scalars, arrays, inline tables
    (continuous symmetries) and sub-tables (``[part.grasp]``)."""
    out = []
    for table in data["part"]:
        lines = ["[[part]]"]
        subtables = []
        for key, value in table.items():
            if isinstance(value, dict):
                subtables.append((key, value))
            elif key == "symmetries_discrete":
                lines.append(f"{key} = [\n" + "".join(f"  {_toml_value(T)},\n" for T in value) + "]")
            else:
                lines.append(f"{key} = {_toml_value(value)}")
        for key, sub in subtables:
            lines += ["", f"[part.{key}]", *(f"{k} = {_toml_value(v)}" for k, v in sub.items())]
        out.append("\n".join(lines) + "\n")
    return "\n".join(out)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a JSON string is a valid TOML basic string
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"no TOML form for {type(value).__name__}")


def _with_part_names(message: str, data: Any) -> str:
    """``part[2]`` in a validation message becomes ``part[2] (clamp)`` where the raw part has a name."""
    raw = data.get("part") if isinstance(data, dict) else None

    def label(match: re.Match) -> str:
        i = int(match.group(1))
        entry = raw[i] if isinstance(raw, list) and i < len(raw) else None
        name = entry.get("name") if isinstance(entry, dict) else None
        return f"part[{i}] ({name})" if isinstance(name, str) and name else match.group(0)

    return re.sub(r"(?<![\w.])part\[(\d+)\]", label, message)


# ---------------------------------------------------------------------------------------------- models


def _build_model(catalogue: Catalogue, part: CataloguePart) -> ObjectModel:
    if part.builtin is not None:
        base = builtin_part(part.builtin)
        density = part.density_kg_m3 or (
            MATERIAL_DENSITY_KG_M3[part.material] if part.material is not None else base.density_kg_m3
        )
        model = replace(
            base,
            obj_id=part.id,
            name=part.name,
            material=part.material or base.material,
            density_kg_m3=density,
            metadata=dict(base.metadata),
        )
    else:
        model = load_cad(
            catalogue.base_dir / (part.file or ""),
            unit=part.unit or "m",
            obj_id=part.id,
            name=part.name,
            material=part.material or "steel",
            symmetries_discrete=tuple(np.asarray(T, dtype=float).reshape(4, 4) for T in part.symmetries_discrete),
            symmetries_continuous=tuple(ContinuousSymmetry(s.axis, s.offset_m) for s in part.symmetries_continuous),
            density_kg_m3=part.density_kg_m3,
        )
    if part.mass_kg is not None:
        model = model.with_mass(part.mass_kg)
    model.metadata["catalogue"] = catalogue.source
    if part.grasp is not None:
        model.metadata["grasp"] = part.grasp.model_dump(mode="json", exclude_none=True)
    return model


# ---------------------------------------------------------------------------------------------- building catalogues


def catalogue_from_files(
    files: list[Path], unit: Literal["mm", "m"], base_dir: Path, first_id: int = 1, source: str = "<files>"
) -> Catalogue:
    """A catalogue of CAD files: ids from ``first_id`` in the given order, names their stems, steel, no mass or
    symmetries declared. Raises ConfigError when two files have the same stem."""
    stems = [f.stem for f in files]
    clash = sorted({s for s in stems if stems.count(s) > 1})
    if clash:
        raise ConfigError(f"{source}: files share a name (their stem): {clash}; rename one of each")
    data = {
        "part": [
            {
                "id": first_id + k,
                "name": f.stem,
                "file": Path(os.path.relpath(f, base_dir)).as_posix(),
                "unit": unit,
                "material": "steel",
            }
            for k, f in enumerate(files)
        ]
    }
    return parse_catalogue(data, source, base_dir)


def open_parts(path: str | Path, unit: Literal["mm", "m"] | None = None, first_id: int = 1) -> Catalogue:
    """The parts at ``path``: a catalogue file, a CAD file, or a folder of CAD files (sorted by file name; ids
    from ``first_id``). CAD files need ``unit``."""
    path = Path(path)
    if path.is_dir():
        files = sorted(f for f in path.iterdir() if f.is_file() and f.suffix.lower() in SUPPORTED_EXTENSIONS)
        if not files:
            raise ConfigError(f"{path}: no CAD files ({', '.join(SUPPORTED_EXTENSIONS)}) in this folder")
    elif path.suffix.lower() in CATALOGUE_SUFFIXES:
        return load_catalogue(path)
    elif path.suffix.lower() in SUPPORTED_EXTENSIONS:
        if not path.is_file():
            raise ConfigError(f"{path}: no such file")
        files = [path]
    else:
        raise ConfigError(
            f"{path}: expected a catalogue ({', '.join(CATALOGUE_SUFFIXES)}), a CAD file "
            f"({', '.join(SUPPORTED_EXTENSIONS)}) or a folder of CAD files"
        )
    if unit is None:
        raise ConfigError(f"{path}: --unit is required with CAD files: the unit of their coordinates, 'mm' or 'm'")
    base_dir = path if path.is_dir() else path.parent
    return catalogue_from_files(files, unit, base_dir, first_id, str(path))


def with_proposals(catalogue: Catalogue, proposals: dict[str, SymmetryProposal]) -> Catalogue:
    """The catalogue with each CAD part that declares no symmetries given its proposed ones (by part name)."""
    parts = []
    for p in catalogue.parts:
        proposal = proposals.get(p.name)
        if p.file is None or proposal is None or p.symmetries_discrete or p.symmetries_continuous:
            parts.append(p)
            continue
        update = {
            "symmetries_discrete": tuple(tuple(float(v) for v in T.reshape(-1)) for T in proposal.symmetries_discrete),
            "symmetries_continuous": tuple(
                ContinuousSymmetrySpec(axis=s.axis, offset_m=s.offset_m) for s in proposal.symmetries_continuous
            ),
        }
        parts.append(CataloguePart.model_validate({**p.model_dump(), **update}))
    return Catalogue(tuple(parts), catalogue.base_dir, catalogue.source)
