"""BOP ``models/`` folders and the object catalogue: a catalogue's parts exported as a BOP models folder (by the
BOP writer: ``obj_OOOOOO.ply`` in millimetres and ``models_info.json`` with ids, diameters and symmetries in BOP's
millimetre convention), and a BOP models folder imported as a catalogue (ids and symmetries from its
``models_info.json``, the meshes as the parts' files)."""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from pathlib import Path

from sygrid.catalogue import Catalogue, parse_catalogue
from sygrid.errors import ConfigError
from sygrid.fileio import read_json
from sygrid.objects.model import symmetries_from_models_info
from sygrid.writers.bop import BopWriter

log = logging.getLogger(__name__)

DIAMETER_MISMATCH_REL = 0.01  # an imported mesh's diameter further than this from models_info's is warned about


def export_bop_models(catalogue: Catalogue, root: str | Path) -> list[Path]:
    """Writes ``root/models/``: each part's mesh (``obj_OOOOOO.ply``, mm) and ``models_info.json``; returns the
    paths written."""
    return BopWriter(root, catalogue.models()).model_files


def catalogue_from_bop_models(
    models_dir: str | Path,
    base_dir: str | Path | None = None,
    names: Mapping[int, str] | None = None,
    material: str = "steel",
) -> Catalogue:
    """A catalogue of a BOP models folder (``models_info.json`` and ``obj_OOOOOO.ply`` in mm): one part per
    ``models_info.json`` entry, named by ``names`` (obj_id -> name; default ``obj_OOOOOO``), of ``material``.
    File paths are relative to ``base_dir`` (where the catalogue will be written; default ``models_dir``). A mesh
    whose diameter disagrees with its entry's by more than ``DIAMETER_MISMATCH_REL`` is logged as a warning.

    Raises:
        ConfigError: no or malformed ``models_info.json`` (the message names the file and the entry), a missing
        mesh, or parts that fail the catalogue's checks.
    """
    models_dir = Path(models_dir)
    base = Path(base_dir) if base_dir is not None else models_dir
    info_path = models_dir / "models_info.json"
    if not info_path.is_file():
        raise ConfigError(f"{info_path}: missing; expected a BOP models folder (models_info.json, obj_OOOOOO.ply)")
    info = read_json(info_path, "BOP models info")
    if not isinstance(info, dict) or not info:
        raise ConfigError(f"{info_path}: expected a JSON object keyed by obj_id, with at least one entry")
    names = dict(names or {})
    parts, diameters = [], {}
    for key in sorted(info, key=lambda k: (not k.isdigit(), int(k) if k.isdigit() else 0, k)):
        where = f"{info_path}[{key}]"
        entry = info[key]
        if not key.isdigit() or int(key) < 1 or not isinstance(entry, dict):
            raise ConfigError(f"{where}: expected an obj_id >= 1 as the key and an object as the entry")
        obj_id = int(key)
        try:
            discrete, continuous = symmetries_from_models_info(entry, where)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        mesh = models_dir / f"obj_{obj_id:06d}.ply"
        if not mesh.is_file():
            raise ConfigError(f"{where}: no mesh {mesh}")
        if isinstance(entry.get("diameter"), (int, float)):
            diameters[obj_id] = float(entry["diameter"]) / 1000.0
        parts.append(
            {
                "id": obj_id,
                "name": names.get(obj_id, f"obj_{obj_id:06d}"),
                "file": Path(os.path.relpath(mesh, base)).as_posix(),
                "unit": "mm",
                "material": material,
                "symmetries_discrete": [[float(v) for v in T.reshape(-1)] for T in discrete],
                "symmetries_continuous": [{"axis": list(s.axis), "offset_m": list(s.offset_m)} for s in continuous],
            }
        )
    catalogue = parse_catalogue({"part": parts}, str(info_path), base)
    for model in catalogue.models():
        declared = diameters.get(model.obj_id)
        if declared and abs(model.diameter_m - declared) > DIAMETER_MISMATCH_REL * declared:
            log.warning(
                "%s: obj_id %d: the mesh's diameter %.2f mm differs from models_info's %.2f mm",
                info_path, model.obj_id, model.diameter_m * 1e3, declared * 1e3,
            )  # fmt: skip
    return catalogue
