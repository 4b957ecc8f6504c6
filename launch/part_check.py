"""The pixels-per-part check (``sygrid.part_pixels``) where a camera meets a detector: a recipe's camera (``sygrid
generate``, ``sygrid eval``) and a cell's calibrated camera and bin (``sygrid pick``). Each returns the warnings to
print (empty when every part is resolved, or when the model folder states no ``detector.min_part_px``).

And where a simulated cell's scene meets its model folder: ``check_scene_parts`` refuses a scene whose parts the
models do not know by obj_id and name (both lists named).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from perception.detector import YoloSegDetector
from sygrid.camera import CameraIntrinsics
from sygrid.errors import ConfigError
from sygrid.objects.model import ObjectModel
from sygrid.part_pixels import part_warnings
from sygrid.scene import SceneSpec

log = logging.getLogger(__name__)


def detector_warnings(
    detector: YoloSegDetector,
    min_part_px: float | None,
    models: Iterable[ObjectModel],
    intrinsics: CameraIntrinsics,
    far_distance_m: float,
) -> list[str]:
    """Warnings for ``models`` seen by ``detector`` (at the scale it sees a frame of ``intrinsics``' size) at
    ``far_distance_m``; none when ``min_part_px`` (the model folder's ``detector.min_part_px``) is None."""
    scale = detector.frame_scale((intrinsics.height, intrinsics.width))
    diameters = {m.name: m.diameter_m for m in models}
    return part_warnings(diameters, intrinsics.fx, far_distance_m, scale, min_part_px)


def folder_detector(models_dir: Path) -> tuple[YoloSegDetector, float | None]:
    """A model folder's detector as its manifest configures it, and its ``min_part_px``."""
    from perception.manifest import load_manifest
    from perception.pipeline import PipelineOverrides, detector_view

    d = load_manifest(models_dir).detector
    view = detector_view(d, PipelineOverrides())
    return YoloSegDetector(models_dir / d.onnx, input_size=d.input_size, num_threads=1, view=view), d.min_part_px


def scene_warnings(scene: SceneSpec, base_dir: Path, models_dir: Path) -> list[str]:
    """Warnings for a scene's parts and camera: the far end of its sampled distance (or its fixed camera's distance
    from the bin's floor centre)."""
    from sygrid.drop import resolve_objects
    from sygrid.scene import intrinsics_from_spec

    if not (models_dir / "manifest.json").is_file():
        return []
    detector, min_px = folder_detector(models_dir)
    if min_px is None:
        return []
    camera = scene.camera
    if camera.T_world_camera is not None:
        far = float(np.linalg.norm(np.asarray(camera.T_world_camera, dtype=float).reshape(4, 4)[:3, 3]))
    else:
        far = float(camera.pose_sampling.distance_m[1])
    return detector_warnings(detector, min_px, resolve_objects(scene, base_dir), intrinsics_from_spec(camera), far)


def cell_warnings(
    detector: YoloSegDetector,
    models_dir: Path,
    models: Iterable[ObjectModel],
    intrinsics: CameraIntrinsics,
    floor_corners_camera: np.ndarray,
) -> list[str]:
    """Warnings for a cell's running ``detector`` (``models_dir``: its model folder, for ``min_part_px``): parts on
    the bin's floor, as far as its farthest floor corner (camera frame, metres)."""
    from perception.manifest import load_manifest

    far = float(np.max(np.asarray(floor_corners_camera, dtype=float)[:, 2]))
    return detector_warnings(detector, load_manifest(models_dir).detector.min_part_px, models, intrinsics, far)


def check_scene_parts(scene_models: Iterable[ObjectModel], models: dict[int, ObjectModel], where: str) -> None:
    """Raises ConfigError, naming both lists, when a part of the scene (``scene_models``) is not a part of the model
    folder (``models``: obj_id -> model) by obj_id and name: the models would never find it, or call it another
    part."""
    scene = {m.obj_id: m.name for m in scene_models}
    wrong = sorted(i for i, name in scene.items() if i not in models or models[i].name != name)
    if wrong:
        listing = "; models: ".join(
            ", ".join(f"{i} {n}" for i, n in sorted(parts.items()))
            for parts in (scene, {i: m.name for i, m in models.items()})
        )
        raise ConfigError(
            f"{where}: the scene's parts {wrong} are not the model folder's (by obj_id and name). Scene: {listing}. "
            "The scene and the models must come from one catalogue"
        )


def log_warnings(warnings: list[str], where: str) -> None:
    for message in warnings:
        log.warning("%s: %s", where, message)
        print(f"warning ({where}): {message}")
