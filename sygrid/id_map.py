"""Class -> BOP obj_id: the explicit id map of ``sygrid convert`` and ``sygrid train detector`` (``--id-map FILE``),
and the one function that decides each class's obj_id (a parts catalogue, ``--catalogue FILE``, ties its part names
to ids through the ``known`` hook).

An id map file is a JSON object ``{key: obj_id}``: a key is a class name (``"clamp"``) or a class index / a label
file's own id written as a string (``"0"``, ``"12"``); an obj_id is an integer >= 1. Example::

    {"clamp": 11, "air_diverter": 12, "2": 13}
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from sygrid.errors import ConfigError
from sygrid.fileio import read_json


def load_id_map(path: str | Path) -> dict[str, int]:
    """Reads an id map file; a non-object, a non-integer or an obj_id < 1 raises ConfigError naming the key."""
    path = Path(path)
    data = read_json(path, "id map")
    if not isinstance(data, dict) or not data:
        raise ConfigError(f"{path}: expected a non-empty JSON object {{class name or index: obj_id}}")
    out = {}
    for key, value in data.items():
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigError(f"{path}[{key!r}]: expected an integer obj_id >= 1, got {value!r}")
        out[str(key)] = value
    return out


def class_obj_ids(
    names: Sequence[str | None],
    where: str,
    id_map: Mapping[str, int] | None = None,
    own_ids: Sequence[int] | None = None,
    known: Mapping[str, int] | None = None,
) -> list[int]:
    """The BOP obj_id of each class, by index. For class ``i`` (name ``names[i]``, None when the labels have none),
    the first that applies:

    1. ``id_map`` by the class's name, else by its own id (``own_ids[i]``) or, without own ids, its index;
    2. ``own_ids[i]``: labels that carry BOP obj_ids themselves (the SyGRID pickle);
    3. ``known[name]``: names another source ties to ids (a parts catalogue, a COCO file's categories);
    4. the built-in part of that name (``sygrid.objects.parts``).

    Raises:
        ConfigError: a class no rule maps (all such classes are listed), or two classes mapped to one obj_id;
            ``where`` names the labels in the message.
    """
    if own_ids is not None and len(own_ids) != len(names):
        raise ValueError(f"own_ids: {len(own_ids)} ids for {len(names)} classes")
    id_map, known = id_map or {}, known or {}
    ids: list[int | None] = []
    for i, name in enumerate(names):
        key = str(own_ids[i]) if own_ids is not None else str(i)
        if name is not None and name in id_map:
            ids.append(int(id_map[name]))
        elif key in id_map:
            ids.append(int(id_map[key]))
        elif own_ids is not None:
            ids.append(int(own_ids[i]))
        elif name is not None and name in known:
            ids.append(int(known[name]))
        else:
            ids.append(_builtin_obj_id(name))
    missing = [
        f"{i} {name!r}" if name is not None else str(i)
        for i, (name, obj_id) in enumerate(zip(names, ids, strict=True))
        if obj_id is None
    ]
    if missing:
        raise ConfigError(
            f"{where}: no obj_id for classes {', '.join(missing)} (index and name); they are not built-in parts: "
            "pass --catalogue FILE (the parts catalogue naming them) or --id-map FILE, a JSON object {class name or "
            "index: obj_id}"
        )
    found = [int(i) for i in ids if i is not None]
    seen: dict[int, int] = {}
    for i, obj_id in enumerate(found):
        if obj_id in seen:
            raise ConfigError(f"{where}: classes {seen[obj_id]} and {i} both map to obj_id {obj_id}")
        seen[obj_id] = i
    return found


def _builtin_obj_id(name: str | None) -> int | None:
    from sygrid.objects.parts import BUILTIN_PARTS, builtin_part  # builds a mesh: only when needed

    return builtin_part(name).obj_id if name in BUILTIN_PARTS else None
