"""The JSON scene description of the SyGRID method, validated with pydantic.

A scene says which parts go into the bin and how many, what the bin is, where the camera may be, how the scene is
lit and rendered, and how the drop is simulated. Every field carries its unit in its name. Unknown keys are errors,
and every error names the file, the field path and what was expected, e.g.
``scene.json: objects[2].count: must be >= 0, got -1``.

Numbers are strict and finite: NaN and infinities are refused (``must be a finite number``), and so are ``true`` and
``false`` where a number is expected (``must be a number`` / ``must be an integer``). Transforms must be rigid
(orthonormal rotation with det +1, last row 0 0 0 1, to ``RIGID_TOLERANCE``), and a fixed camera must see the bin.

Frames: the scene ("world") frame has its origin at the centre of the bin's inner floor, z up.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Strict,
    Tag,
    ValidationError,
    field_validator,
    model_validator,
)

from sygrid.camera import CameraIntrinsics, project_points
from sygrid.errors import ConfigError
from sygrid.fileio import read_json
from sygrid.transforms import invert, is_rigid, transform_points

# The number types of the scene and recipe schemas: a bool is not a number (strict), and the models'
# ``allow_inf_nan=False`` (``STRICT_NUMBERS``) refuses NaN and infinities.
Float = Annotated[float, Strict()]
Int = Annotated[int, Strict()]
Bool = Annotated[bool, Strict()]
Vec3 = tuple[Float, Float, Float]
Positive = Annotated[float, Strict(), Field(gt=0)]
NonNegative = Annotated[float, Strict(), Field(ge=0)]
#: The model config of the scene and recipe schemas: unknown keys refused, values frozen, numbers finite.
STRICT_NUMBERS = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
#: How far a transform typed into a JSON file may be from rigid (rotation entries, last row).
RIGID_TOLERANCE = 1e-5
DEFAULT_FOV_Y_DEG = 45.0


class _Strict(BaseModel):
    model_config = STRICT_NUMBERS


class CountRange(_Strict):
    """An instance count drawn uniformly from [min, max] (both inclusive) for each scene."""

    min: Int = Field(ge=0)
    max: Int = Field(ge=0)

    @model_validator(mode="after")
    def _ordered(self) -> CountRange:
        if self.max < self.min:
            raise ValueError(f"max must be >= min, got min={self.min}, max={self.max}")
        return self


# A count is a number or a {min, max} range; the discriminator reports only the branch the user meant.
Count = Annotated[
    Annotated[Int, Tag("number")] | Annotated[CountRange, Tag("range")],
    Discriminator(lambda v: "range" if isinstance(v, (dict, CountRange)) else "number"),
]


class ContinuousSymmetrySpec(_Strict):
    axis: Vec3
    offset_m: Vec3 = (0.0, 0.0, 0.0)

    @field_validator("axis")
    @classmethod
    def _unit_axis(cls, axis: Vec3) -> Vec3:
        norm = sum(a * a for a in axis) ** 0.5
        if norm < 1e-9:
            raise ValueError("must be a non-zero 3-vector")
        return (axis[0] / norm, axis[1] / norm, axis[2] / norm)


# The keys of sygrid.objects.cad.MATERIAL_DENSITY_KG_M3 (a test keeps the two in step).
Material = Literal["steel", "zinc", "brass", "aluminium", "painted", "plastic"]
#: The materials rendered as conductors (``sygrid.render.materials``): specular metal, where stereo matching fails.
METALS: frozenset[str] = frozenset({"steel", "zinc", "brass", "aluminium"})


def check_sixteen_numbers(syms: tuple[tuple[float, ...], ...]) -> tuple[tuple[float, ...], ...]:
    """``symmetries_discrete``' check, shared by the scene and the catalogue: each entry 16 numbers of a rigid
    transform."""
    for i, T in enumerate(syms):
        if len(T) != 16:
            raise ValueError(f"[{i}] must be a 4x4 transform as 16 numbers (row-major), got {len(T)}")
        _check_rigid(T, f"[{i}] ")
    return syms


class ObjectSpec(_Strict):
    """One kind of part: a built-in part by name, a CAD file (path relative to the scene file) with its unit, or a
    part of the scene's catalogue by name (``catalogue_part``: its id, name, file, material and symmetries all
    come from the catalogue; only ``count`` is given here)."""

    builtin: str | None = None
    file: str | None = None
    catalogue_part: str | None = None
    unit: Literal["mm", "m"] | None = None
    obj_id: Int | None = Field(default=None, ge=1)
    name: str | None = None
    material: Material | None = None
    count: Count = 1
    symmetries_discrete: tuple[tuple[Float, ...], ...] = ()
    symmetries_continuous: tuple[ContinuousSymmetrySpec, ...] = ()

    @field_validator("count")
    @classmethod
    def _non_negative(cls, count: Count) -> Count:
        if isinstance(count, int) and count < 0:
            raise ValueError(f"must be >= 0, got {count}")
        return count

    @field_validator("symmetries_discrete")
    @classmethod
    def _sixteen_numbers(cls, syms: tuple[tuple[float, ...], ...]) -> tuple[tuple[float, ...], ...]:
        return check_sixteen_numbers(syms)

    @model_validator(mode="after")
    def _one_source(self) -> ObjectSpec:
        if sum(v is not None for v in (self.builtin, self.file, self.catalogue_part)) != 1:
            raise ValueError(
                "give exactly one of 'builtin' (a built-in part name), 'file' (a CAD path) or 'catalogue_part' "
                "(a part of the scene's catalogue)"
            )
        if self.catalogue_part is not None:
            given = [k for k in ("unit", "obj_id", "name", "material") if getattr(self, k) is not None]
            if given or self.symmetries_discrete or self.symmetries_continuous:
                raise ValueError(
                    f"a 'catalogue_part' takes only 'count': its {', '.join(given) or 'symmetries'} come(s) from "
                    "the catalogue"
                )
            return self
        if self.file is not None:
            if self.unit is None:
                raise ValueError("'unit' is required with 'file': 'mm' or 'm'")
            if self.obj_id is None:
                raise ValueError("'obj_id' (>= 1) is required with 'file'")
        elif self.unit is not None or self.symmetries_discrete or self.symmetries_continuous:
            raise ValueError("'unit' and symmetries apply to 'file' objects only; built-in parts declare their own")
        return self

    @property
    def label(self) -> str:
        return self.name or self.builtin or self.catalogue_part or Path(self.file or "").stem


class ContainerSpec(_Strict):
    """An open box (the bin): inner size, wall thickness, material."""

    inner_size_m: Vec3 = (0.30, 0.20, 0.12)
    wall_thickness_m: Positive = 0.01
    material: Material = "plastic"

    @field_validator("inner_size_m")
    @classmethod
    def _positive(cls, size: Vec3) -> Vec3:
        if min(size) <= 0:
            raise ValueError(f"every side must be > 0, got {list(size)}")
        return size


def bin_volume_points(inner_size_m: Sequence[float], per_side: int = 9) -> np.ndarray:
    """(per_side**2 * 3, 3) a grid over the bin's inner volume (floor, half height, rim) in the bin frame."""
    hx, hy, hz = (float(v) / 2.0 for v in inner_size_m)
    x, y, z = np.meshgrid(
        np.linspace(-hx, hx, per_side), np.linspace(-hy, hy, per_side), (0.0, hz, 2.0 * hz), indexing="ij"
    )
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)


def bin_inner_corners(inner_size_m: Sequence[float]) -> np.ndarray:
    """(8, 3) the corners of a bin's inner volume (floor and rim), where parts can be, in the bin frame (metres;
    origin at the centre of the inner floor, z up)."""
    hx, hy, hz = (float(v) / 2.0 for v in inner_size_m)
    return np.array([(x, y, z) for x in (-hx, hx) for y in (-hy, hy) for z in (0.0, 2.0 * hz)])


class IntrinsicsSpec(_Strict):
    """Pinhole intrinsics in pixels (OpenCV: pixel centres at integers); ``fx`` and ``fy`` may differ."""

    fx: Positive
    fy: Positive
    cx: Float
    cy: Float


class CameraPoseSampling(_Strict):
    """The camera looks at a point near the bin centre from a random viewpoint on a spherical cap above it."""

    distance_m: tuple[Positive, Positive] = (0.55, 0.75)
    max_tilt_deg: Annotated[float, Strict(), Field(ge=0, le=80)] = 15.0
    look_at_jitter_m: NonNegative = 0.02

    @field_validator("distance_m")
    @classmethod
    def _ordered(cls, d: tuple[float, float]) -> tuple[float, float]:
        if d[1] < d[0]:
            raise ValueError(f"must be [min, max] with min <= max, got {list(d)}")
        return d


class CameraSpec(_Strict):
    """The image size, the intrinsics (``fov_y_deg``, square pixels, or explicit ``intrinsics``; default a 45 deg
    vertical field of view) and the pose: a fixed, rigid ``T_world_camera`` (16 numbers, row-major; OpenCV
    camera frame) or ``pose_sampling``."""

    width_px: Int = Field(default=640, gt=0, le=8192)
    height_px: Int = Field(default=480, gt=0, le=8192)
    fov_y_deg: Annotated[float, Strict(), Field(gt=1, lt=170)] | None = None
    intrinsics: IntrinsicsSpec | None = None
    T_world_camera: tuple[Float, ...] | None = None
    pose_sampling: CameraPoseSampling = CameraPoseSampling()

    @field_validator("T_world_camera")
    @classmethod
    def _rigid(cls, T: tuple[float, ...] | None) -> tuple[float, ...] | None:
        if T is not None:
            if len(T) != 16:
                raise ValueError(f"must be a 4x4 transform as 16 numbers (row-major), got {len(T)}")
            _check_rigid(T, "")
        return T

    @model_validator(mode="after")
    def _one_intrinsics(self) -> CameraSpec:
        if self.fov_y_deg is not None and self.intrinsics is not None:
            raise ValueError("give 'fov_y_deg' or 'intrinsics', not both")
        return self


def intrinsics_from_spec(camera: CameraSpec) -> CameraIntrinsics:
    """Pinhole intrinsics from the scene's camera: explicit ``intrinsics``, else ``fov_y_deg`` (default
    ``DEFAULT_FOV_Y_DEG``) with square pixels and the principal point at the image centre."""
    if camera.intrinsics is not None:
        k = camera.intrinsics
        return CameraIntrinsics(k.fx, k.fy, k.cx, k.cy, camera.width_px, camera.height_px)
    return CameraIntrinsics.from_fov(camera.width_px, camera.height_px, camera.fov_y_deg or DEFAULT_FOV_Y_DEG)


def _check_rigid(T: Sequence[float], prefix: str) -> None:
    """Raises ValueError (``prefix`` + what is wrong) unless the 16 numbers are a rigid 4x4 transform."""
    M = np.asarray(T, dtype=float).reshape(4, 4)
    if is_rigid(M, atol=RIGID_TOLERANCE):
        return
    scales = np.linalg.svd(M[:3, :3], compute_uv=False)
    raise ValueError(
        f"{prefix}must be a rigid transform (orthonormal rotation with det +1, last row 0 0 0 1, to "
        f"{RIGID_TOLERANCE:g}); got rotation scales {np.round(scales, 6).tolist()}, det "
        f"{np.linalg.det(M[:3, :3]):.6g}, last row {M[3].tolist()}"
    )


class EnvironmentSpec(_Strict):
    """Lighting: an HDR environment map file (path relative to the scene file) or a procedural sky + lamps."""

    map_file: str | None = None
    procedural: Bool = True
    strength: NonNegative = 1.0
    random_lights: tuple[Annotated[int, Strict(), Field(ge=0)], Annotated[int, Strict(), Field(ge=0)]] = (1, 3)


RENDER_PRESETS: dict[str, dict[str, Any]] = {
    # The SyGRID paper's fixed values: 640x480, 5000 spp, path depth 32, denoised.
    "paper": {"spp": 5000, "max_depth": 32, "denoiser": "oidn", "reconstruction_filter": "gaussian"},
    # Fast CPU default: 4 spp + OIDN with a box filter reaches ~40 dB against 1024 spp (``sygrid bench render``);
    # 16 spp buys 2 dB for about three times the render time.
    "fast": {"spp": 4, "max_depth": 8, "denoiser": "oidn", "reconstruction_filter": "box"},
}


class RenderSpec(_Strict):
    preset: Literal["fast", "paper"] = "fast"
    mode: Literal["pathtrace", "raster"] = "pathtrace"
    spp: Int = Field(default=16, ge=1, le=1 << 16)
    max_depth: Int = Field(default=8, ge=1, le=128)
    denoiser: Literal["none", "oidn"] = "oidn"
    reconstruction_filter: Literal["box", "gaussian"] = "box"

    @model_validator(mode="before")
    @classmethod
    def _apply_preset(cls, data: Any) -> Any:
        """Fields not given explicitly take the preset's value."""
        if not isinstance(data, dict):
            return data
        preset = data.get("preset", "fast")
        if preset not in RENDER_PRESETS:
            return data  # the Literal check reports the bad preset name
        return {**RENDER_PRESETS[preset], **data}


class PhysicsSpec(_Strict):
    timestep_s: Annotated[float, Strict(), Field(gt=0, le=0.01)] = 0.002
    max_time_s: Annotated[float, Strict(), Field(gt=0, le=60)] = 3.0
    settle_linear_speed_m_s: Positive = 0.005
    settle_angular_speed_rad_s: Positive = 0.1
    friction: Annotated[float, Strict(), Field(gt=0, le=2)] = 0.5
    collision_tier: Literal["auto", "hull", "coacd", "vhacd"] = "auto"
    max_penetration_m: Positive = 0.0005
    spawn_clearance_m: NonNegative = 0.002
    # MuJoCo island sleeping: an island whose velocities stay below this (MuJoCo's size-scaled threshold) stops
    # being simulated; 0 turns sleeping off. `sygrid bench physics` charts its speed gain against rest drift.
    sleep_tolerance: Annotated[float, Strict(), Field(ge=0, le=1)] = 0.03
    # MuJoCo's speculative contacts, against thin walls passing into each other in one step (sygrid.physics):
    # "auto" turns them on when a part's wall is thinner than a step's travel at impact. "off" by default: the
    # built-in parts do not need them, and scenes that leave it off keep their content hash.
    speculative_contacts: Literal["off", "on", "auto"] = "off"


class SceneSpec(_Strict):
    name: str = "scene"
    catalogue: str | None = None  # an object catalogue file (sygrid.catalogue), relative to the scene file
    objects: tuple[ObjectSpec, ...]
    container: ContainerSpec = ContainerSpec()
    camera: CameraSpec = CameraSpec()
    environment: EnvironmentSpec = EnvironmentSpec()
    render: RenderSpec = RenderSpec()
    physics: PhysicsSpec = PhysicsSpec()

    @field_validator("objects")
    @classmethod
    def _not_empty(cls, objects: tuple[ObjectSpec, ...]) -> tuple[ObjectSpec, ...]:
        if not objects:
            raise ValueError("must list at least one part")
        return objects

    @model_validator(mode="after")
    def _unique_ids(self) -> SceneSpec:
        ids = [o.obj_id for o in self.objects if o.obj_id is not None]
        dupes = sorted({i for i in ids if ids.count(i) > 1})
        if dupes:
            raise ValueError(f"obj_id values must be unique, repeated: {dupes}")
        named = [f"objects[{k}]" for k, o in enumerate(self.objects) if o.catalogue_part is not None]
        if named and self.catalogue is None:
            raise ValueError(f"{', '.join(named)} name(s) a 'catalogue_part': give the scene's 'catalogue' file")
        return self

    @model_validator(mode="after")
    def _fixed_camera_sees_the_bin(self) -> SceneSpec:
        """A fixed camera that sees none of the bin's inner volume would only make empty items."""
        if self.camera.T_world_camera is None:
            return self
        K = intrinsics_from_spec(self.camera)
        T_camera_world = invert(np.asarray(self.camera.T_world_camera, dtype=float).reshape(4, 4))
        p = transform_points(T_camera_world, bin_volume_points(self.container.inner_size_m))
        front = p[:, 2] > 1e-6
        uv = project_points(K.K, p[front]) if front.any() else np.zeros((0, 2))
        inside = (uv[:, 0] >= -0.5) & (uv[:, 0] < K.width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < K.height - 0.5)
        if not inside.any():
            raise ValueError(
                "camera.T_world_camera: the camera sees none of the bin (its inner volume projects outside the "
                f"{K.width}x{K.height} image or lies behind the camera); point the camera's +z axis at the bin"
            )
        return self


# ---------------------------------------------------------------------------------------------- loading


def parse_scene(data: Any, source: str = "<scene>") -> SceneSpec:
    """Validates a scene given as plain JSON data. ``source`` names the file in error messages."""
    try:
        return SceneSpec.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(validation_message(exc, source)) from None


def validation_message(exc: ValidationError, source: str) -> str:
    """A pydantic error as ``source: field.path: expectation, got value; ...`` (shared by every JSON schema)."""
    return f"{source}: " + "; ".join(_describe(e) for e in exc.errors())


def load_scene(path: str | Path) -> SceneSpec:
    """Reads and validates a scene JSON file."""
    return parse_scene(read_json(path, "scene file"), str(path))


def scene_to_json(scene: SceneSpec) -> dict:
    """The scene as plain data. The catalogue keys and speculative contacts are left out where unused, so a scene
    that uses neither keeps the content hash (``sygrid.drop.scene_sha256``, the dataset ledger's recipe hash) it
    had before they existed."""
    data = scene.model_dump(mode="json")
    if data["catalogue"] is None:
        del data["catalogue"]
    if data["physics"]["speculative_contacts"] == "off":
        del data["physics"]["speculative_contacts"]
    for obj in data["objects"]:
        if obj["catalogue_part"] is None:
            del obj["catalogue_part"]
    return data


def default_scene(parts: tuple[str, ...] = ("hex_nut", "washer", "l_bracket", "pipe"), per_part: int = 5) -> SceneSpec:
    """A bin of built-in parts with the fast preset: what the demo and the benchmarks use."""
    return parse_scene({"name": "builtin_bin", "objects": [{"builtin": p, "count": per_part} for p in parts]})


def _field_path(loc: tuple[int | str, ...]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part in ("number", "range"):
            continue  # the count discriminator's branch names are noise to a user
        else:
            out += f".{part}" if out else str(part)
    return out or "(top level)"


def _describe(err: dict) -> str:
    """One pydantic error as ``path: expectation, got value``."""
    kind, ctx, value = err["type"], err.get("ctx", {}), err.get("input")
    loc = tuple(p for p in err["loc"] if not (isinstance(p, str) and p.startswith("function-")))
    path = _field_path(loc)
    expectations = {
        "greater_than_equal": lambda: f"must be >= {ctx.get('ge')}",
        "greater_than": lambda: f"must be > {ctx.get('gt')}",
        "less_than_equal": lambda: f"must be <= {ctx.get('le')}",
        "less_than": lambda: f"must be < {ctx.get('lt')}",
        "literal_error": lambda: f"must be one of {ctx.get('expected')}",
        "missing": lambda: "is required",
        "too_short": lambda: f"must have at least {ctx.get('min_length')} item(s)",
        "int_type": lambda: "must be an integer",
        "int_from_float": lambda: "must be an integer",
        "int_parsing": lambda: "must be an integer",
        "float_type": lambda: "must be a number",
        "float_parsing": lambda: "must be a number",
        "finite_number": lambda: "must be a finite number",
        "string_type": lambda: "must be a string",
        "bool_type": lambda: "must be true or false",
        "tuple_type": lambda: "must be a list",
        "model_type": lambda: "must be an object",
        "model_attributes_type": lambda: "must be an object",
    }
    if kind == "extra_forbidden":
        return f"{path}: unknown key (check the spelling; unknown keys are not ignored)"
    if kind in ("value_error", "assertion_error"):
        return f"{path}: {str(err['msg']).removeprefix('Value error, ')}"
    if kind == "missing" or value is None:
        return f"{path}: {expectations.get(kind, lambda: err['msg'])()}"
    return f"{path}: {expectations.get(kind, lambda: err['msg'])()}, got {json.dumps(value, default=str)}"
