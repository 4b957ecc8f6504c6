"""Choosing the Mitsuba variant: ``cuda_ad_rgb`` on a working CUDA GPU, ``llvm_ad_rgb`` with a usable LLVM, else
``scalar_rgb``.

Dr.Jit's LLVM backend needs LLVM >= 16 on these machines (Debian 12's default 14/15 abort with "Cannot select ...
fminimum"); Debian's ``libllvm19`` works when ``DRJIT_LIBLLVM_PATH`` points at it. ``choose_variant`` sets that
variable (at call time, never at import) to the newest ``libLLVM`` >= 16 found in the standard library folders,
unless it is already set, and then proves each candidate variant by rendering a tiny scene in it. The choice is
made once per process and logged.
"""

from __future__ import annotations

import glob
import logging
import os
import re
from pathlib import Path

from sygrid.errors import SygridError

log = logging.getLogger(__name__)

VARIANTS: tuple[str, ...] = ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb")
MIN_LLVM_MAJOR = 16
_LIB_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib64",
    "/usr/lib",
    "/usr/local/lib",
    "/opt/homebrew/opt/llvm/lib",
    "/usr/local/opt/llvm/lib",
)
# libLLVM.so.19.1, libLLVM-19.so, libLLVM-19.so.1, libLLVM.so.19, libLLVM-17.0.6.so
_LLVM_NAME = re.compile(r"^libLLVM(?:-(\d+)(?:\.\d+)*\.so(?:\.\d+)*|\.so\.(\d+)(?:\.\d+)*)$")

_chosen: str | None = None


class RenderBackendError(SygridError, RuntimeError):
    """No Mitsuba variant can render on this machine, or a requested one does not work."""


def find_libllvm(min_major: int = MIN_LLVM_MAJOR, lib_dirs: tuple[str, ...] = _LIB_DIRS) -> Path | None:
    """The newest ``libLLVM`` shared library with major version >= ``min_major`` in ``lib_dirs`` (also
    ``/usr/lib/llvm-*/lib``), or None."""
    dirs = list(lib_dirs) + sorted(glob.glob("/usr/lib/llvm-*/lib"))
    best: tuple[int, Path] | None = None
    for d in dirs:
        for path in sorted(Path(d).glob("libLLVM*.so*")) if Path(d).is_dir() else ():
            m = _LLVM_NAME.match(path.name)
            if m is None:
                continue
            major = int(m.group(1) or m.group(2))
            if major >= min_major and (best is None or major > best[0]):
                best = (major, path)
    return best[1] if best else None


def _try_variant(variant: str) -> str | None:
    """Renders a 4x4 sphere in ``variant``; None on success, else the reason it failed."""
    import mitsuba as mi

    try:
        mi.set_variant(variant)
        scene = mi.load_dict(
            {
                "type": "scene",
                "integrator": {"type": "path", "max_depth": 2},
                "sensor": {
                    "type": "perspective",
                    "film": {"type": "hdrfilm", "width": 4, "height": 4, "rfilter": {"type": "box"}},
                    "sampler": {"type": "independent", "sample_count": 1},
                    "to_world": mi.ScalarTransform4f.look_at(origin=[0, 0, 3], target=[0, 0, 0], up=[0, 1, 0]),
                },
                "sphere": {"type": "sphere"},
                "light": {"type": "constant"},
            }
        )
        import numpy as np

        img = np.asarray(mi.render(scene, spp=1))
        if img.shape[:2] != (4, 4) or not np.isfinite(img).all():
            return f"bad test image {img.shape}"
    except Exception as exc:  # any backend failure means "not this variant"
        return f"{type(exc).__name__}: {exc}"
    return None


def choose_variant(override: str | None = None) -> str:
    """Selects (``mi.set_variant``) and returns the Mitsuba variant to render with.

    Args:
        override: a variant name to use instead of the automatic choice (e.g. ``"scalar_rgb"``); it is still
            tested, and a failure raises ``RenderBackendError``.

    The automatic choice is cached for the process; an override is not cached and does not change the cache.
    """
    global _chosen
    import mitsuba as mi

    if override is None and _chosen is not None:
        if mi.variant() != _chosen:
            mi.set_variant(_chosen)
        return _chosen
    _ensure_llvm_path()
    if override is not None:
        if override not in mi.variants():
            raise ValueError(f"unknown Mitsuba variant {override!r}; this build has {sorted(mi.variants())}")
        if override == mi.variant():
            return override
        reason = _try_variant(override)
        if reason is not None:
            raise RenderBackendError(f"Mitsuba variant {override!r} does not render here: {reason}")
        log.info("Mitsuba variant %s (requested)", override)
        return override
    reasons = []
    for variant in VARIANTS:
        if variant not in mi.variants():
            reasons.append(f"{variant}: not in this build")
            continue
        if variant == "cuda_ad_rgb" and not _cuda_present():
            reasons.append(f"{variant}: no CUDA driver")
            continue
        if variant == "llvm_ad_rgb" and not os.environ.get("DRJIT_LIBLLVM_PATH"):
            reasons.append(f"{variant}: no libLLVM >= {MIN_LLVM_MAJOR} found")
            continue
        reason = _try_variant(variant)
        if reason is None:
            _chosen = variant
            log.info("Mitsuba variant %s (not used: %s)", variant, "; ".join(reasons) or "none")
            return variant
        reasons.append(f"{variant}: {reason}")
    raise RenderBackendError("no Mitsuba variant renders here: " + "; ".join(reasons))


def _ensure_llvm_path() -> None:
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return
    lib = find_libllvm()
    if lib is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = str(lib)
        log.debug("DRJIT_LIBLLVM_PATH=%s", lib)


def _cuda_present() -> bool:
    """A cheap check before trying CUDA (loading the variant without a driver prints noise)."""
    return any(Path(d).glob("libcuda.so*") for d in _LIB_DIRS if Path(d).is_dir()) or Path("/dev/nvidiactl").exists()
