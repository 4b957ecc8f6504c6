"""The sweep machinery: an axis is a declarative object (its points, methods, seeds, what to measure), and a run
measures every (point, seed) it has not measured yet, saving one small JSON per (point, seed, method).

Layout under the points folder: ``<axis>/<point>/s<seed>/<method>.json``, each ``{"axis", "point", "x", "params",
"seed", "method", "metric", "k", "n", "groups", "extra", "seconds", "settings"}``: ``k`` successes of ``n`` trials
(the metric is a proportion), ``groups`` the same per group of the trials (``"family <name>"``, ``"part <id>
<name>"``: ``[k, n]``), ``seconds`` the wall time of the whole (point, seed) measurement (shared by its methods).
Files are written atomically (``sygrid.fileio``) as soon as a (point, seed) is measured, so a run stopped at any
time goes on where it stopped. A saved point measured with other ``settings`` (data, images, models, strategies) is
refused rather than mixed in. Several runs of one axis can share the work: a run claims a (point, seed) with a
``.claim`` file (created exclusively, holding its process id) and skips one claimed by a live process; a claim left by
a process that died is taken over.
"""

from __future__ import annotations

import os
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from launch.stability.failure import Criterion
from sygrid.errors import ConfigError
from sygrid.fileio import read_json, write_json_atomic


@dataclass(frozen=True)
class Point:
    """One point of an axis: ``label`` names it (and its folder), ``x`` places it on the axis (None: a categorical
    axis), ``params`` says what it sets (JSON-able; the axis's measure reads them)."""

    label: str
    x: float | None
    params: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Method:
    """A method measured along an axis and what its proportion is (e.g. "detection recall"); ``grouped`` False: its
    per-group counts (saved with the points) are not reported, where a group's share does not measure the method."""

    name: str
    metric: str
    grouped: bool = True


@dataclass
class Measurement:
    """One method at one (point, seed): ``k`` successes of ``n`` trials, per group ``[k, n]``, and free extras."""

    k: int
    n: int
    groups: dict[str, list[int]] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)


MeasureFn = Callable[[Point, int], dict[str, Measurement]]


@dataclass(frozen=True)
class Axis:
    """A difficulty swept one point at a time.

    ``points`` in order of increasing difficulty; ``measure(point, seed)`` returns a ``Measurement`` per method
    name (a method it leaves out is saved as not measured: ``n`` 0); ``settings`` what the measurement depends on
    besides the point and seed; ``summary`` a phrase for the summary table with ``{x}`` where the failure point
    goes (e.g. "works down to {x} px"); ``unit`` the unit of ``x``; ``notes`` figures of the whole axis computed
    from its records (e.g. the soak's growth), for its JSON and the summary.
    """

    name: str
    title: str
    x_label: str
    points: tuple[Point, ...]
    methods: tuple[Method, ...]
    measure: MeasureFn
    seeds: tuple[int, ...] = (0,)
    criterion: Criterion = field(default_factory=Criterion)
    summary: str = "holds to {x}"
    unit: str = ""
    settings: dict[str, Any] = field(default_factory=dict)
    description: str = ""
    notes: Callable[[list[dict[str, Any]]], dict[str, Any]] | None = None

    def __post_init__(self) -> None:
        labels = [safe_name(p.label) for p in self.points]
        if len(set(labels)) != len(labels):
            raise ConfigError(f"axis {self.name}: point labels must differ (as folder names: {labels})")
        if not self.points or not self.methods or not self.seeds:
            raise ConfigError(f"axis {self.name}: needs at least one point, method and seed")
        if len({p.x is None for p in self.points}) > 1:
            raise ConfigError(f"axis {self.name}: either every point has an x or none does (categorical)")

    @property
    def categorical(self) -> bool:
        return self.points[0].x is None


def safe_name(label: str) -> str:
    """``label`` as a file or folder name: runs of characters other than letters, digits, ``.``, ``+`` and ``-``
    become ``_``."""
    return re.sub(r"[^A-Za-z0-9.+-]+", "_", label).strip("_") or "_"


def point_path(points_dir: Path, axis: str, point: str, seed: int, method: str) -> Path:
    return Path(points_dir) / safe_name(axis) / safe_name(point) / f"s{seed}" / f"{safe_name(method)}.json"


def run_axis(
    axis: Axis, points_dir: Path, log: Callable[[str], None] = print, measure: bool = True
) -> list[dict[str, Any]]:
    """Every (point, seed, method) record of ``axis``: read where saved, measured and saved otherwise (only the
    saved ones with ``measure`` False). A (point, seed) is measured again when any of its methods' files is
    missing.

    Raises:
        ConfigError: a saved record was measured with other settings than ``axis.settings``.
    """
    records = []
    for point in axis.points:
        for seed in axis.seeds:
            paths = {m.name: point_path(points_dir, axis.name, point.label, seed, m.name) for m in axis.methods}
            saved = {name: _read(path, axis) for name, path in paths.items() if path.is_file()}
            if len(saved) == len(paths) or not measure:
                records += saved.values()
                continue
            claim = next(iter(paths.values())).parent / CLAIM_FILE
            owner = _claim(claim)
            if owner is not None:
                log(f"{axis.name}: point {point.label}, seed {seed}: being measured by process {owner}; skipped here")
                continue
            try:
                records += _measure_point(axis, point, seed, paths, log)
            finally:
                claim.unlink(missing_ok=True)
    return records


def _measure_point(
    axis: Axis, point: Point, seed: int, paths: dict[str, Path], log: Callable[[str], None]
) -> list[dict[str, Any]]:
    log(f"{axis.name}: point {point.label}, seed {seed}")
    start = time.perf_counter()
    measured = axis.measure(point, seed)
    seconds = time.perf_counter() - start
    unknown = sorted(set(measured) - set(paths))
    if unknown:
        raise ValueError(f"axis {axis.name}: measure returned unknown methods {unknown}")
    records = []
    for m in axis.methods:
        result = measured.get(m.name, Measurement(0, 0, extra={"not_measured": True}))
        record = _record(axis, point, seed, m, result, seconds)
        write_json_atomic(paths[m.name], record)
        records.append(record)
    log(f"{axis.name}: point {point.label}, seed {seed}: {_brief(measured)} ({seconds:.0f} s)")
    return records


CLAIM_FILE = ".claim"


def _claim(path: Path) -> int | None:
    """Claim the (point, seed) folder of ``path`` for this process: None where claimed (a stale claim, whose
    process is gone, is taken over), else the live process id that holds it. Same machine only (process ids)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    for _ in range(2):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            try:
                owner = int(path.read_text().strip() or 0)
            except (OSError, ValueError):
                owner = 0
            if owner and owner != os.getpid() and _alive(owner):
                return owner
            path.unlink(missing_ok=True)
            continue
        with os.fdopen(fd, "w") as f:
            f.write(str(os.getpid()))
        return None
    raise ConfigError(f"{path}: could not claim the point (another run keeps taking it over)")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # alive, another user's
    return True


def _record(axis: Axis, point: Point, seed: int, method: Method, m: Measurement, seconds: float) -> dict[str, Any]:
    if not 0 <= m.k <= m.n:
        raise ValueError(f"axis {axis.name}, point {point.label}, method {method.name}: k={m.k} of n={m.n}")
    return {
        "axis": axis.name, "point": point.label, "x": point.x, "params": point.params, "seed": seed,
        "method": method.name, "metric": method.metric, "k": int(m.k), "n": int(m.n),
        "value": m.k / m.n if m.n else None, "groups": {g: [int(k), int(n)] for g, (k, n) in m.groups.items()},
        "extra": m.extra, "seconds": seconds, "settings": axis.settings,
    }  # fmt: skip


def _read(path: Path, axis: Axis) -> dict[str, Any]:
    record = read_json(path, "stability point")
    if not isinstance(record, dict) or not {"k", "n", "method", "settings"} <= set(record):
        raise ConfigError(f"{path}: not a stability point record (k, n, method and settings expected)")
    if record["settings"] != _jsonable(axis.settings):
        differ = sorted(k for k in set(record["settings"]) | set(axis.settings)
                        if record["settings"].get(k) != _jsonable(axis.settings).get(k))  # fmt: skip
        raise ConfigError(
            f"{path}: measured with other settings ({', '.join(differ)} differ); remove the axis's points folder "
            f"{path.parents[2]} to measure it again, or give another --out-dir"
        )
    return record


def _jsonable(value: Any) -> Any:
    """``value`` as it reads back from JSON (tuples become lists)."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    return value


def _brief(measured: dict[str, Measurement]) -> str:
    return ", ".join(f"{name} {m.k}/{m.n}" for name, m in measured.items())
