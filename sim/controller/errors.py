"""Errors raised by the controller emulator, under the project's ``SygridError`` base."""

from __future__ import annotations

from sygrid.errors import SygridError


class EmulatorError(SygridError, RuntimeError):
    """Base of the controller emulator's errors."""


class MotionError(EmulatorError):
    """A motion the emulated robot cannot execute (target out of reach, outside the joint limits). On a real UR
    this is a URScript runtime error: the program halts."""


class BackendUnavailableError(EmulatorError):
    """The requested simulation backend cannot be built (its module is missing or failed to load)."""
