"""The native decomposers (CoACD, V-HACD) on plain arrays, run in this process or in a child process that is
killed at a time limit (a native call cannot be interrupted from Python).

This module imports nothing of the project, only numpy and the decomposer, so the child starts quickly: it runs
this file by path, ``python worker.py IN.npz OUT.npz``. IN holds ``vertices`` (n, 3) float64, ``faces`` (m, 3)
int64, ``decomposer`` ("coacd" or "vhacd") and ``options`` (JSON of the decomposer's keyword arguments); OUT holds
the pieces' vertices concatenated (``vertices``) with their counts (``counts``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

DECOMPOSERS = ("coacd", "vhacd")


def run_decomposer(decomposer: str, vertices: np.ndarray, faces: np.ndarray, options: dict) -> list[np.ndarray]:
    """The pieces' vertex arrays (each (k, 3) float64) of ``decomposer`` on the mesh ``vertices``, ``faces``, with
    ``options`` its keyword arguments (``coacd.run_coacd`` or ``vhacdx.compute_vhacd``)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if decomposer == "coacd":
        import coacd  # heavy native library: imported on use

        coacd.set_log_level("error")
        parts = coacd.run_coacd(coacd.Mesh(vertices, faces), **options)
    elif decomposer == "vhacd":
        from vhacdx import compute_vhacd  # heavy native library: imported on use

        # vhacdx wants the faces flat, each prefixed by its vertex count: [3, i, j, k, 3, ...] (as
        # trimesh.decomposition builds them). An (f, 3) array is accepted without an error and gives garbage hulls.
        flat = np.column_stack([np.full(len(faces), 3), faces]).ravel().astype(np.uint32)
        parts = compute_vhacd(vertices, flat, **options)
    else:
        raise ValueError(f"decomposer must be one of {DECOMPOSERS}, got {decomposer!r}")
    return [np.asarray(v, dtype=np.float64).reshape(-1, 3) for v, _f in parts]


def run_in_child(
    decomposer: str, vertices: np.ndarray, faces: np.ndarray, options: dict, limit_s: float
) -> list[np.ndarray] | None:
    """``run_decomposer`` in a child process; None when it has not finished after ``limit_s`` seconds (it is then
    killed).

    Raises:
        RuntimeError: the child failed (its last lines of error output are in the message).
    """
    with tempfile.TemporaryDirectory(prefix="sygrid-decompose-") as tmp:
        inp, out = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(inp, vertices=vertices, faces=faces, decomposer=decomposer, options=json.dumps(options))
        # -P: the child's import path does not start with this folder (Python >= 3.11)
        flags = ["-P"] if sys.version_info >= (3, 11) else []
        with open(Path(tmp) / "stderr.txt", "w+b") as err:
            child = subprocess.Popen(
                [sys.executable, *flags, str(Path(__file__).resolve()), str(inp), str(out)],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err, env=os.environ.copy(),
            )  # fmt: skip
            try:
                code = child.wait(timeout=max(limit_s, 0.0))
            except subprocess.TimeoutExpired:
                return None
            finally:  # out of time, or interrupted: the child does not outlive the call
                if child.poll() is None:
                    child.kill()
                    child.wait()
            if code != 0:
                err.seek(0)
                tail = err.read().decode(errors="replace").strip().splitlines()[-5:]
                raise RuntimeError(f"the {decomposer} child process exited with {code}: {' | '.join(tail)}")
        with np.load(out, allow_pickle=False) as data:
            flat, counts = data["vertices"], data["counts"]
    return list(np.split(flat, np.cumsum(counts)[:-1])) if len(counts) else []


def main(argv: list[str]) -> int:
    inp, out = argv
    with np.load(inp, allow_pickle=False) as data:
        pieces = run_decomposer(
            str(data["decomposer"]), data["vertices"], data["faces"], json.loads(str(data["options"]))
        )
    counts = np.array([len(p) for p in pieces], dtype=np.int64)
    flat = np.concatenate(pieces) if pieces else np.zeros((0, 3))
    np.savez(out, vertices=flat, counts=counts)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
