"""Scene description + seed -> a settled pile, and the poses file that hands it to the renderer.

This is the SyGRID two-file hand-off: the scene JSON says what is in the bin, the poses file says where each
instance came to rest. The poses file records the scene's content hash and the seed, so a poses file can always be
traced to (and regenerated from) the scene that made it.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from sygrid.catalogue import Catalogue, load_catalogue
from sygrid.errors import ConfigError
from sygrid.fileio import read_json, write_json_atomic
from sygrid.objects import ContinuousSymmetry, ObjectModel, builtin_part, load_cad
from sygrid.objects.collision.build import build_collision_model, select_collision_model
from sygrid.objects.collision.geometry import CollisionModel
from sygrid.objects.collision.params import CollisionTier
from sygrid.physics import DropResult, Instance, simulate_drop
from sygrid.scene import CountRange, ObjectSpec, SceneSpec, scene_to_json

log = logging.getLogger(__name__)

POSES_FORMAT = "sygrid-poses/1"
POSES_FRAME = "world: origin at the centre of the bin's inner floor, z up; metres"


def resolve_object(spec: ObjectSpec, base_dir: Path, catalogue: Catalogue | None = None) -> ObjectModel:
    """The ObjectModel a scene entry names: a built-in part, a CAD file relative to the scene file, or a part of
    ``catalogue`` (ConfigError without one)."""
    if spec.catalogue_part is not None:
        if catalogue is None:
            raise ConfigError(f"catalogue_part {spec.catalogue_part!r}: no catalogue to take it from")
        return catalogue.model(spec.catalogue_part)
    if spec.builtin is not None:
        model = builtin_part(spec.builtin)
        if spec.obj_id is None and spec.material is None and spec.name is None:
            return model
        return _with_overrides(model, spec)
    path = Path(spec.file or "")
    path = path if path.is_absolute() else base_dir / path
    return load_cad(
        path,
        unit=spec.unit or "m",
        obj_id=int(spec.obj_id or 0),
        name=spec.name,
        material=spec.material or "steel",
        symmetries_discrete=tuple(np.asarray(T, dtype=float).reshape(4, 4) for T in spec.symmetries_discrete),
        symmetries_continuous=tuple(
            ContinuousSymmetry(tuple(s.axis), tuple(s.offset_m)) for s in spec.symmetries_continuous
        ),
    )


def resolve_objects(scene: SceneSpec, base_dir: Path) -> list[ObjectModel]:
    """The scene's models, one per entry (``resolve_parts`` of its objects and catalogue; ``base_dir``: the scene
    file's folder)."""
    return resolve_parts(scene.objects, scene.catalogue, Path(base_dir), f"scene {scene.name!r}")


def resolve_parts(
    objects: Sequence[ObjectSpec], catalogue: str | None, base_dir: Path, where: str
) -> list[ObjectModel]:
    """The models of object entries (a scene's, a model folder manifest's), one per entry: the one place where parts
    and their catalogue (a path relative to ``base_dir``, the folder of the file that names it) are resolved.
    Raises ConfigError, prefixed with ``where``, for an unreadable catalogue, an unknown catalogue part or two
    different parts with one obj_id."""
    try:
        parts = load_catalogue(Path(base_dir) / catalogue) if catalogue is not None else None
    except ConfigError as exc:
        raise ConfigError(f"{where}: catalogue: {exc}") from None
    models = []
    for k, spec in enumerate(objects):
        try:
            models.append(resolve_object(spec, Path(base_dir), parts))
        except ConfigError as exc:
            raise ConfigError(f"{where}: objects[{k}]: {exc}") from None
    seen: dict[int, str] = {}
    for k, model in enumerate(models):
        if seen.setdefault(model.obj_id, model.name) != model.name:
            raise ConfigError(
                f"{where}: objects[{k}] ({model.name}) has obj_id {model.obj_id}, already taken by "
                f"{seen[model.obj_id]!r}: every part needs its own obj_id"
            )
    return models


def collision_models(models: list[ObjectModel], tier: str) -> list[CollisionModel]:
    """Per model: the cheapest collision tier that meets the default tolerances (``auto``), or the named tier."""
    if tier == "auto":
        return [select_collision_model(m) for m in models]
    return [build_collision_model(m, CollisionTier(tier)) for m in models]


def sample_instances(scene: SceneSpec, rng: np.random.Generator) -> list[Instance]:
    """Instance list, grouped by scene entry; ranged counts drawn from ``rng``."""
    instances: list[Instance] = []
    for k, spec in enumerate(scene.objects):
        count = spec.count
        n = int(rng.integers(count.min, count.max + 1)) if isinstance(count, CountRange) else int(count)
        instances += [Instance(model_index=k, inst_id=len(instances) + j) for j in range(n)]
    return instances


def drop_scene(
    scene: SceneSpec,
    seed: int,
    base_dir: Path | str = ".",
    clutter: Sequence[tuple[ObjectModel, CollisionModel]] = (),
) -> DropResult:
    """Resolves the scene's parts, draws the instance counts and drops them: the same seed gives the same poses.

    ``clutter``: unlabelled pieces (model, collision model) dropped with the parts, one instance each; their
    models follow the scene's in ``DropResult.models`` and their instances follow the parts' (so the first
    ``len(instances) - len(clutter)`` instances are the scene's parts). Without clutter the drop is the same as
    before it existed.
    """
    rng = np.random.default_rng(seed)
    models = resolve_objects(scene, Path(base_dir))
    instances = sample_instances(scene, rng)
    if not instances:
        raise ConfigError(f"scene '{scene.name}': every object count is 0, nothing to drop")
    coll = collision_models(models, scene.physics.collision_tier)
    for model, collision in clutter:
        instances.append(Instance(model_index=len(models), inst_id=len(instances)))
        models.append(model)
        coll.append(collision)
    return simulate_drop(models, coll, instances, scene.container, scene.physics, rng)


# ---------------------------------------------------------------------------------------------- poses file


@dataclass
class PosesFile:
    """A poses file's content: which scene and seed, which objects, and ``T_world_obj`` per instance."""

    scene_sha256: str
    seed: int
    objects: list[dict]
    instances: list[Instance]
    T_world_obj: np.ndarray
    report: dict

    def obj_id(self, instance: Instance) -> int:
        return int(self.objects[instance.model_index]["obj_id"])


def scene_sha256(scene: SceneSpec) -> str:
    return hashlib.sha256(json.dumps(scene_to_json(scene), sort_keys=True).encode()).hexdigest()


def poses_to_json(result: DropResult, scene: SceneSpec, seed: int) -> dict:
    return {
        "format": POSES_FORMAT,
        "frame": POSES_FRAME,
        "scene_name": scene.name,
        "scene_sha256": scene_sha256(scene),
        "seed": int(seed),
        "objects": [{"obj_id": m.obj_id, "name": m.name, "source": m.source} for m in result.models],
        "instances": [
            {
                "inst_id": inst.inst_id,
                "object_index": inst.model_index,
                "obj_id": result.models[inst.model_index].obj_id,
                "T_world_obj": np.round(T, 12).tolist(),
            }
            for inst, T in zip(result.instances, result.T_world_obj, strict=True)
        ],
        "report": result.report.to_json(),
    }


def save_poses(path: str | Path, result: DropResult, scene: SceneSpec, seed: int) -> Path:
    """Writes the poses file atomically (a crash leaves the old file or the new one, never half of one)."""
    return write_json_atomic(Path(path), poses_to_json(result, scene, seed))


def load_poses(path: str | Path) -> PosesFile:
    path = Path(path)
    data = read_json(path, "poses file")
    if not isinstance(data, dict) or data.get("format") != POSES_FORMAT:
        found = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise ConfigError(f"{path}: format: expected '{POSES_FORMAT}', got {found!r}")
    try:
        instances = [Instance(int(i["object_index"]), int(i["inst_id"])) for i in data["instances"]]
        T = np.array([i["T_world_obj"] for i in data["instances"]], dtype=float).reshape(-1, 4, 4)
        return PosesFile(
            scene_sha256=str(data["scene_sha256"]),
            seed=int(data["seed"]),
            objects=list(data["objects"]),
            instances=instances,
            T_world_obj=T,
            report=dict(data.get("report", {})),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: malformed poses file: {exc!r}") from None


def _with_overrides(model: ObjectModel, spec: ObjectSpec) -> ObjectModel:
    return replace(
        model,
        obj_id=spec.obj_id if spec.obj_id is not None else model.obj_id,
        name=spec.name or model.name,
        material=spec.material or model.material,
    )
