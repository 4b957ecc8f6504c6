"""The project's exception hierarchy: one base class, so callers can catch everything SyGRID raises.

Input-checking errors subclass ``ValueError`` as well, because they are bad arguments.
"""

from __future__ import annotations


class SygridError(Exception):
    """Base of every error this project raises on purpose."""


class ConfigError(SygridError, ValueError):
    """A configuration or scene file is invalid. The message names the file, the field path and the expectation."""


class MeshError(SygridError, ValueError):
    """A CAD mesh cannot be used. The message names the file and the problem."""


class UnknownObjectError(SygridError, KeyError):
    """A built-in part name that does not exist. The message lists the valid names."""

    def __str__(self) -> str:  # KeyError would print the message with quotes around it
        return str(self.args[0]) if self.args else ""


class ModelError(SygridError, ValueError):
    """A model file (ONNX) cannot be used: missing, unreadable, or not following its network's contract."""


class DropError(SygridError, RuntimeError):
    """The physics drop could not produce a valid pile (placement failed, or the simulation became unstable)."""


class ExportError(SygridError, RuntimeError):
    """An exported ONNX model does not reproduce its torch model (a bug, not bad input); nothing is written."""
