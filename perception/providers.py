"""Which onnxruntime execution providers a session runs on: ``auto`` (CUDA when this onnxruntime offers it, else
the CPU), ``cpu`` or ``cuda``. The CPU path is onnxruntime's ``CPUExecutionProvider`` alone, as before; CUDA keeps
the CPU provider as the fallback for operators CUDA lacks.
"""

from __future__ import annotations

import onnxruntime as ort

from sygrid.errors import ModelError

PROVIDER_CHOICES = ("auto", "cpu", "cuda")
CPU = "CPUExecutionProvider"
CUDA = "CUDAExecutionProvider"


def session_providers(choice: str = "auto", available: list[str] | None = None) -> list[str]:
    """The provider list for ``ort.InferenceSession``. ``available``: onnxruntime's (default
    ``ort.get_available_providers()``).

    Raises:
        ValueError: an unknown choice.
        ModelError: ``"cuda"`` where this onnxruntime has no CUDA provider (the CPU-only package is installed).
    """
    if choice not in PROVIDER_CHOICES:
        raise ValueError(f"providers: expected one of {PROVIDER_CHOICES}, got {choice!r}")
    offered = ort.get_available_providers() if available is None else available
    if choice == "cpu":
        return [CPU]
    if CUDA in offered:
        return [CUDA, CPU]
    if choice == "cuda":
        raise ModelError(
            f"providers 'cuda': this onnxruntime {ort.__version__} offers {offered}, no {CUDA} (install "
            "onnxruntime-gpu, or use providers 'auto' or 'cpu')"
        )
    return [CPU]
