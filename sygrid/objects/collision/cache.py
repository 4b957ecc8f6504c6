"""The disk cache of collision models: one entry per (mesh content hash, tier, the tier's parameters, decomposer
version, and for a repaired part the repair's method, parameters and version), an ``.npz`` of the pieces and a
``.json`` of the rest with the npz's SHA-256, each replaced atomically; a damaged or foreign entry is ignored with a
warning (and rebuilt by the caller).

Beside them: the repaired solids (``<hash>-solid-<key>.{npz,json}``, the same way) and time-out markers
(``<entry>.timeout.json``: a decomposition that ran out of its time limit, so that it is not started again with no
more time than that)."""

from __future__ import annotations

import hashlib
import importlib.metadata
import io
import json
import logging
import zipfile
from dataclasses import asdict
from functools import cache
from pathlib import Path

import numpy as np

from sygrid.fileio import cache_dir_for, write_bytes_atomic, write_json_atomic
from sygrid.objects.collision.geometry import CollisionModel, ConvexPiece, Fidelity, PrimitiveGeom
from sygrid.objects.collision.params import CollisionParams, CollisionTier

log = logging.getLogger(__name__)

_CACHE_FORMAT = "sygrid-collision/1"
_SOLID_FORMAT = "sygrid-solid/1"
_TIMEOUT_FORMAT = "sygrid-timeout/1"


def resolve_cache_dir(cache_dir: Path | str | None = None) -> Path:
    """The collision cache folder (``sygrid.fileio.cache_dir_for("collision", cache_dir)``)."""
    return cache_dir_for("collision", cache_dir)


@cache
def _library_version(tier: CollisionTier) -> str:
    """The decomposer's version: a new release can give other pieces, so it is part of the cache key."""
    dist = {CollisionTier.HULL: "trimesh", CollisionTier.COACD: "coacd", CollisionTier.VHACD: "vhacdx"}[tier]
    try:
        return f"{dist}=={importlib.metadata.version(dist)}"
    except importlib.metadata.PackageNotFoundError:
        return f"{dist}==unknown"


def cache_entry(
    folder: Path, content_hash: str, tier: CollisionTier, params: CollisionParams, solid: dict | None = None
) -> tuple[Path, str]:
    """``(stem, key)`` of the cache entry of a mesh (by content hash) in ``tier`` with ``params``: the entry's files
    are ``stem.npz`` and ``stem.json``; ``key`` (SHA-256 of the format, hash, tier, the tier's parameters, the
    decomposer's version and ``solid``: what the repair that made the decomposed solid depends on, None for a mesh
    decomposed as it is) is recorded in the JSON and checked on loading."""
    payload = {
        "format": _CACHE_FORMAT,
        "content_hash": content_hash,
        "tier": tier.value,
        "params": params.key_fields(tier),
        "library": _library_version(tier),
    }
    if solid is not None:
        payload["solid"] = solid
    key = hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()
    return folder / f"{content_hash[:16]}-{tier.value}-{key[:16]}", key


def solid_entry(folder: Path, content_hash: str, solid: dict) -> tuple[Path, str]:
    """``(stem, key)`` of the cache entry of a mesh's repaired solid; ``solid``: what the repair depends on."""
    payload = {"format": _SOLID_FORMAT, "content_hash": content_hash, "solid": solid}
    key = hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()
    return folder / f"{content_hash[:16]}-solid-{key[:16]}", key


def save_cached(stem: Path, key: str, result: CollisionModel) -> None:
    """The model's arrays and metadata as the entry at ``stem`` (``_write_entry``)."""
    pieces = result.pieces
    buffer = io.BytesIO()
    np.savez(
        buffer,
        vertices=np.concatenate([p.vertices for p in pieces]) if pieces else np.zeros((0, 3)),
        faces=np.concatenate([p.faces for p in pieces]) if pieces else np.zeros((0, 3), dtype=np.int64),
        vertex_counts=np.array([len(p.vertices) for p in pieces], dtype=np.int64),
        face_counts=np.array([len(p.faces) for p in pieces], dtype=np.int64),
    )
    meta = {
        "format": _CACHE_FORMAT,
        "key": key,
        "content_hash": result.content_hash,
        "tier": result.tier.value,
        "params": asdict(result.params),
        "library": _library_version(result.tier),
        "compute_s": result.compute_s,
        "fidelity_s": result.fidelity_s,
        "fidelity": asdict(result.fidelity),
        "primitives": [
            {"kind": p.kind, "size_m": list(p.size_m), "T_obj_geom": np.asarray(p.T_obj_geom).tolist()}
            for p in result.primitives
        ],
    }
    _write_entry(stem, buffer.getvalue(), meta)


def _write_entry(stem: Path, payload: bytes, meta: dict) -> None:
    """``payload`` to ``stem.npz``, then ``meta`` with the npz's SHA-256 to ``stem.json``: the JSON is written last,
    so a reader never pairs a new JSON with an old or half-written npz. Each file is replaced atomically."""
    meta = {**meta, "npz_sha256": hashlib.sha256(payload).hexdigest()}
    try:
        write_bytes_atomic(stem.with_suffix(".npz"), payload)
        write_json_atomic(stem.with_suffix(".json"), meta)
    except OSError as exc:  # a read-only or full cache folder costs a rebuild next time, not the result
        log.warning("could not write the collision cache entry %s: %s", stem, exc)
        return
    log.debug("wrote collision cache entry %s.{npz,json}", stem)


def _read_entry(stem: Path, key: str, fmt: str) -> tuple[dict, bytes] | None:
    """``(meta, npz bytes)`` of the entry at ``stem``; None when there is none.

    Raises:
        ValueError: the entry is of another format or key, or its npz does not match its recorded SHA-256.
        OSError: a file cannot be read.
    """
    json_path, npz_path = stem.with_suffix(".json"), stem.with_suffix(".npz")
    if not json_path.exists():
        return None
    meta = json.loads(json_path.read_text())
    if meta.get("format") != fmt or meta.get("key") != key:
        raise ValueError(f"format/key mismatch (expected {fmt}, key {key[:16]}...)")
    payload = npz_path.read_bytes()
    if hashlib.sha256(payload).hexdigest() != meta["npz_sha256"]:
        raise ValueError(f"{npz_path.name} does not match the SHA-256 recorded in {json_path.name}")
    return meta, payload


_UNREADABLE = (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile)


def load_cached(
    stem: Path, key: str, tier: CollisionTier, content_hash: str, params: CollisionParams
) -> CollisionModel | None:
    """The cached model at ``stem``, or None when there is none or it is unreadable (with a warning)."""
    try:
        entry = _read_entry(stem, key, _CACHE_FORMAT)
        if entry is None:
            return None
        meta, payload = entry
        with np.load(io.BytesIO(payload), allow_pickle=False) as npz:
            pieces = _split_pieces(npz["vertices"], npz["faces"], npz["vertex_counts"], npz["face_counts"])
        primitives = tuple(_primitive_from_json(p) for p in meta["primitives"])
        fidelity = Fidelity(**meta["fidelity"])
        if not pieces and not primitives:
            raise ValueError("the entry holds no geometry")
        return CollisionModel(
            tier=tier,
            pieces=pieces,
            primitives=primitives,
            fidelity=fidelity,
            compute_s=float(meta["compute_s"]),
            fidelity_s=float(meta["fidelity_s"]),
            content_hash=content_hash,
            params=params,
            from_cache=True,
        )
    except _UNREADABLE as exc:
        log.warning("ignoring the unreadable collision cache entry %s.json (%s); rebuilding it", stem, exc)
        return None


def save_solid(stem: Path, key: str, vertices: np.ndarray, faces: np.ndarray, meta: dict) -> None:
    """A repaired solid's mesh (metres) and ``meta`` (how it was made) as the entry at ``stem``."""
    buffer = io.BytesIO()
    np.savez(buffer, vertices=np.asarray(vertices, dtype=np.float64), faces=np.asarray(faces, dtype=np.int64))
    _write_entry(stem, buffer.getvalue(), {"format": _SOLID_FORMAT, "key": key, **meta})


def load_solid(stem: Path, key: str) -> tuple[np.ndarray, np.ndarray, dict] | None:
    """``(vertices, faces, meta)`` of the solid cached at ``stem``; None when there is none or it is unreadable
    (with a warning)."""
    try:
        entry = _read_entry(stem, key, _SOLID_FORMAT)
        if entry is None:
            return None
        meta, payload = entry
        with np.load(io.BytesIO(payload), allow_pickle=False) as npz:
            vertices, faces = np.array(npz["vertices"], dtype=np.float64), np.array(npz["faces"], dtype=np.int64)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"vertices/faces must be (n, 3), got {vertices.shape} and {faces.shape}")
        if len(faces) < 4 or faces.min() < 0 or faces.max() >= len(vertices) or not np.all(np.isfinite(vertices)):
            raise ValueError("too few faces, face indices out of range or non-finite vertices")
        return vertices, faces, meta
    except _UNREADABLE as exc:
        log.warning("ignoring the unreadable solid cache entry %s.json (%s); rebuilding it", stem, exc)
        return None


def save_timeout(stem: Path, key: str, limit_s: float) -> None:
    """Records that the decomposition of entry ``stem`` ran out of ``limit_s`` seconds."""
    try:
        write_json_atomic(
            stem.with_suffix(".timeout.json"), {"format": _TIMEOUT_FORMAT, "key": key, "limit_s": float(limit_s)}
        )
    except OSError as exc:
        log.warning("could not write the time-out marker of %s: %s", stem, exc)


def load_timeout(stem: Path, key: str) -> float | None:
    """The time limit (s) that the decomposition of entry ``stem`` ran out of, or None (none recorded)."""
    path = stem.with_suffix(".timeout.json")
    try:
        meta = json.loads(path.read_text())
        if meta.get("format") != _TIMEOUT_FORMAT or meta.get("key") != key:
            return None
        return float(meta["limit_s"])
    except FileNotFoundError:
        return None
    except _UNREADABLE as exc:
        log.warning("ignoring the unreadable time-out marker %s (%s)", path, exc)
        return None


def _split_pieces(
    vertices: np.ndarray, faces: np.ndarray, vertex_counts: np.ndarray, face_counts: np.ndarray
) -> tuple[ConvexPiece, ...]:
    """Concatenated arrays back into pieces, checking shapes and indices so a damaged entry is never returned."""
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"vertices/faces must be (n, 3), got {vertices.shape} and {faces.shape}")
    if (
        len(vertex_counts) != len(face_counts)
        or vertex_counts.sum() != len(vertices)
        or face_counts.sum() != len(faces)
    ):
        raise ValueError("piece counts do not add up to the stored vertices and faces")
    if not np.all(np.isfinite(vertices)):
        raise ValueError("non-finite vertices")
    if len(vertex_counts) == 0:
        return ()
    pieces = []
    v_split = np.split(vertices.astype(np.float64), np.cumsum(vertex_counts)[:-1])
    f_split = np.split(faces.astype(np.int64), np.cumsum(face_counts)[:-1])
    for v, f in zip(v_split, f_split, strict=True):
        if len(f) < 4 or f.min() < 0 or f.max() >= len(v):
            raise ValueError("a piece has fewer than 4 faces or face indices out of range")
        v.flags.writeable = False
        f.flags.writeable = False
        pieces.append(ConvexPiece(v, f))
    return tuple(pieces)


def _primitive_from_json(entry: dict) -> PrimitiveGeom:
    kind = entry["kind"]
    size = tuple(float(s) for s in entry["size_m"])
    T = np.asarray(entry["T_obj_geom"], dtype=np.float64)
    expected = {"box": 3, "cylinder": 2}
    if kind not in expected or len(size) != expected[kind] or T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"bad primitive entry {entry!r}")
    T.flags.writeable = False
    return PrimitiveGeom(kind, size, T)
