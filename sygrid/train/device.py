"""Where a trainer runs: ``--device auto|cpu|cuda`` for ``sygrid train detector`` and ``sygrid train pose``.

``auto`` is CUDA when torch sees a CUDA device, else the CPU. On CUDA the network's forward pass runs under float16
autocast (mixed precision) with a gradient scaler; the losses are computed in float32 from the outputs cast back.
The CPU path is unchanged: no autocast, no scaling (``GradScaler`` disabled is a pass-through).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

from sygrid.train.device_choice import DEVICE_CHOICES


def resolve_device(choice: str) -> torch.device:
    """``"auto"``, ``"cpu"`` or ``"cuda"`` -> the torch device to train on.

    Raises:
        ValueError: an unknown choice, or ``"cuda"`` where torch sees no CUDA device.
    """
    if choice not in DEVICE_CHOICES:
        raise ValueError(f"device: expected one of {DEVICE_CHOICES}, got {choice!r}")
    if choice == "cpu":
        return torch.device("cpu")
    if torch.cuda.is_available():
        return torch.device("cuda")
    if choice == "cuda":
        raise ValueError(
            f"device 'cuda': torch {torch.__version__} sees no CUDA device (CUDA build {torch.version.cuda}); "
            "use --device cpu or auto"
        )
    return torch.device("cpu")


@contextlib.contextmanager
def autocast(device: torch.device) -> Iterator[None]:
    """float16 autocast on CUDA; nothing on the CPU."""
    if device.type == "cuda":
        with torch.autocast("cuda", dtype=torch.float16):
            yield
    else:
        yield


def grad_scaler(device: torch.device) -> torch.amp.GradScaler:
    """A gradient scaler, enabled on CUDA only (disabled, ``scale`` and ``step`` pass through)."""
    return torch.amp.GradScaler(device.type, enabled=device.type == "cuda")


def to_float32(value: object) -> object:
    """Floating tensors in (nested lists, tuples, dicts of) ``value`` as float32; the rest unchanged."""
    if isinstance(value, torch.Tensor):
        return value.float() if value.is_floating_point() else value
    if isinstance(value, (list, tuple)):
        return type(value)(to_float32(v) for v in value)
    if isinstance(value, dict):
        return {k: to_float32(v) for k, v in value.items()}
    return value
