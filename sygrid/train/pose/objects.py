"""The parts a pose model is trained for: models read from a BOP ``models/`` folder (or taken from the parts catalogue
the dataset was made from, for their names), and the per-part tables the losses need (bounds, diameter, symmetry
transforms, surface regions, points), in class order.

Class index = position of the obj_id in the sorted list of trained obj_ids (the detector's convention).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d

from sygrid.catalogue import Catalogue
from sygrid.errors import ConfigError
from sygrid.fileio import read_json
from sygrid.objects.cad import load_cad
from sygrid.objects.model import ObjectModel, symmetries_from_models_info
from sygrid.objects.symmetry import sample_surface

log = logging.getLogger(__name__)

MM_PER_M = 1000.0
SURFACE_SAMPLES = 4000  # surface points the region centres are chosen from


def load_bop_models(models_dir: str | Path, obj_ids: Sequence[int] | None = None) -> dict[int, ObjectModel]:
    """``ObjectModel``s (metres) of a BOP ``models/`` folder: ``obj_OOOOOO.ply`` in mm plus the symmetries of
    ``models_info.json``; ``obj_ids`` None loads every model listed there."""
    models_dir = Path(models_dir)
    info_path = models_dir / "models_info.json"
    if not info_path.is_file():
        raise ConfigError(f"{info_path}: missing; expected the BOP models folder written by 'sygrid generate'")
    info = read_json(info_path, "BOP models info")
    available = sorted(int(k) for k in info)
    wanted = available if obj_ids is None else sorted({int(i) for i in obj_ids})
    missing = sorted(set(wanted) - set(available))
    if missing:
        raise ConfigError(f"{info_path}: no model for obj_id {missing}; the dataset has obj_ids {available}")
    models = {}
    for obj_id in wanted:
        try:
            discrete, continuous = symmetries_from_models_info(info[str(obj_id)], f"{info_path}[{obj_id}]")
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        models[obj_id] = load_cad(
            models_dir / f"obj_{obj_id:06d}.ply",
            unit="mm",
            obj_id=obj_id,
            symmetries_discrete=discrete,
            symmetries_continuous=continuous,
            verify_symmetries=False,  # written by our own BOP writer from checked models
        )
    return models


DIAMETER_TOLERANCE = 0.01  # a catalogue part and the dataset's model of its id differ by less: the same part


def catalogue_models(
    catalogue: Catalogue, models_dir: str | Path, obj_ids: Sequence[int] | None = None
) -> dict[int, ObjectModel]:
    """The catalogue's models of the dataset's parts (``models_info.json``'s ids; ``obj_ids`` None: all of them), so
    the pose model carries the catalogue's names and symmetries. Raises ConfigError for a dataset id that is no part
    of the catalogue, or a part whose diameter differs from the dataset's model of that id by more than
    ``DIAMETER_TOLERANCE`` (the dataset was made from another catalogue)."""
    info_path = Path(models_dir) / "models_info.json"
    if not info_path.is_file():
        raise ConfigError(f"{info_path}: missing; expected the BOP models folder written by 'sygrid generate'")
    info = read_json(info_path, "BOP models info")
    available = sorted(int(k) for k in info)
    wanted = available if obj_ids is None else sorted({int(i) for i in obj_ids})
    by_id = {p.id: p.name for p in catalogue.parts}
    missing = [i for i in wanted if i not in by_id or i not in available]
    if missing:
        raise ConfigError(
            f"{info_path}: obj_ids {missing} are not in both the dataset ({available}) and the catalogue "
            f"{catalogue.source} ({', '.join(f'{i} {n}' for i, n in sorted(by_id.items()))})"
        )
    models = {}
    for obj_id in wanted:
        model = catalogue.model(by_id[obj_id])
        diameter_mm = float(info[str(obj_id)].get("diameter", math.nan))
        if not abs(model.diameter_m * MM_PER_M - diameter_mm) <= DIAMETER_TOLERANCE * diameter_mm:
            raise ConfigError(
                f"{info_path}[{obj_id}]: diameter {diameter_mm:.2f} mm, the catalogue's part {model.name!r} "
                f"{model.diameter_m * MM_PER_M:.2f} mm: the dataset was made from another catalogue"
            )
        models[obj_id] = model
    return models


def region_centres(model: ObjectModel, num_regions: int, seed: int = 0) -> np.ndarray:
    """(num_regions, 3) surface points [m] spread by farthest-point sampling: the centres of the surface
    regions (GDR-Net's region attention); a point's region is its nearest centre."""
    points = sample_surface(model.mesh, SURFACE_SAMPLES, np.random.default_rng(seed))
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    return np.asarray(cloud.farthest_point_down_sample(int(num_regions)).points, dtype=np.float64)


@dataclass(frozen=True, eq=False)
class ObjectTables:
    """Per-class arrays, class index first; symmetric transforms padded to the largest count.

    obj_ids (C,); diameters_m (C,); bounds_m (C, 2, 3); sym_T (C, S, 4, 4) with identity in slot 0 and padding
    repeating the identity; sym_valid (C, S) bool; regions_m (C, R, 3); points_m (C, P, 3) surface samples.
    """

    obj_ids: tuple[int, ...]
    names: tuple[str, ...]
    diameters_m: np.ndarray
    bounds_m: np.ndarray
    sym_T: np.ndarray
    sym_valid: np.ndarray
    regions_m: np.ndarray
    points_m: np.ndarray
    symmetric: np.ndarray

    @property
    def num_classes(self) -> int:
        return len(self.obj_ids)

    def class_index(self, obj_id: int) -> int:
        return self.obj_ids.index(int(obj_id))


def build_tables(
    models: dict[int, ObjectModel], num_regions: int, num_points: int = 300, sym_steps: int = 36, seed: int = 0
) -> ObjectTables:
    """The tables for ``models`` (any order; sorted by obj_id). ``sym_steps``: samples per turn of a continuous
    symmetry for the symmetric losses."""
    if not models:
        raise ConfigError("no object models to train for")
    ids = sorted(models)
    syms = [models[i].symmetry_transforms(sym_steps) for i in ids]
    n_sym = max(len(s) for s in syms)
    sym_T = np.tile(np.eye(4), (len(ids), n_sym, 1, 1))
    sym_valid = np.zeros((len(ids), n_sym), dtype=bool)
    for c, s in enumerate(syms):
        sym_T[c, : len(s)] = s
        sym_valid[c, : len(s)] = True
    rng = np.random.default_rng(seed)
    return ObjectTables(
        obj_ids=tuple(ids),
        names=tuple(models[i].name for i in ids),
        diameters_m=np.array([models[i].diameter_m for i in ids]),
        bounds_m=np.stack([models[i].bounds_m for i in ids]),
        sym_T=sym_T,
        sym_valid=sym_valid,
        regions_m=np.stack([region_centres(models[i], num_regions, seed) for i in ids]),
        points_m=np.stack([sample_surface(models[i].mesh, num_points, rng) for i in ids]),
        symmetric=np.array([models[i].is_symmetric for i in ids]),
    )
