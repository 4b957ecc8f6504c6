"""The disk cache of collision models: one entry per (mesh content hash, tier, the tier's parameters, decomposer
version), an ``.npz`` of the pieces and a ``.json`` of the rest with the npz's SHA-256, each replaced atomically; a
damaged or foreign entry is ignored with a warning (and rebuilt by the caller)."""

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


def cache_entry(folder: Path, content_hash: str, tier: CollisionTier, params: CollisionParams) -> tuple[Path, str]:
    """``(stem, key)`` of the cache entry of a mesh (by content hash) in ``tier`` with ``params``: the entry's files
    are ``stem.npz`` and ``stem.json``; ``key`` (SHA-256 of the format, hash, tier, the tier's parameters and the
    decomposer's version) is recorded in the JSON and checked on loading."""
    key = _cache_key(content_hash, tier, params)
    return folder / f"{content_hash[:16]}-{tier.value}-{key[:16]}", key


def _cache_key(content_hash: str, tier: CollisionTier, params: CollisionParams) -> str:
    payload = {
        "format": _CACHE_FORMAT,
        "content_hash": content_hash,
        "tier": tier.value,
        "params": params.key_fields(tier),
        "library": _library_version(tier),
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def save_cached(stem: Path, key: str, result: CollisionModel) -> None:
    """Arrays to ``stem.npz``, then metadata (with the npz's SHA-256) to ``stem.json``: the JSON is written last,
    so a reader never pairs a new JSON with an old or half-written npz. Each file is replaced atomically."""
    pieces = result.pieces
    buffer = io.BytesIO()
    np.savez(
        buffer,
        vertices=np.concatenate([p.vertices for p in pieces]) if pieces else np.zeros((0, 3)),
        faces=np.concatenate([p.faces for p in pieces]) if pieces else np.zeros((0, 3), dtype=np.int64),
        vertex_counts=np.array([len(p.vertices) for p in pieces], dtype=np.int64),
        face_counts=np.array([len(p.faces) for p in pieces], dtype=np.int64),
    )
    payload = buffer.getvalue()
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
        "npz_sha256": hashlib.sha256(payload).hexdigest(),
    }
    try:
        write_bytes_atomic(stem.with_suffix(".npz"), payload)
        write_json_atomic(stem.with_suffix(".json"), meta)
    except OSError as exc:  # a read-only or full cache folder costs a rebuild next time, not the result
        log.warning("could not write the collision cache entry %s: %s", stem, exc)
        return
    log.debug("wrote collision cache entry %s.{npz,json}", stem)


def load_cached(
    stem: Path, key: str, tier: CollisionTier, content_hash: str, params: CollisionParams
) -> CollisionModel | None:
    """The cached model at ``stem``, or None when there is none or it is unreadable (with a warning)."""
    json_path, npz_path = stem.with_suffix(".json"), stem.with_suffix(".npz")
    if not json_path.exists():
        return None
    try:
        meta = json.loads(json_path.read_text())
        if meta.get("format") != _CACHE_FORMAT or meta.get("key") != key:
            raise ValueError(f"format/key mismatch (expected {_CACHE_FORMAT}, key {key[:16]}...)")
        payload = npz_path.read_bytes()
        if hashlib.sha256(payload).hexdigest() != meta["npz_sha256"]:
            raise ValueError(f"{npz_path.name} does not match the SHA-256 recorded in {json_path.name}")
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
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile) as exc:
        log.warning("ignoring the unreadable collision cache entry %s (%s); rebuilding it", json_path, exc)
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
