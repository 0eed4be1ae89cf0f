"""Errors raised by torchproj. All are ``ValueError``s so callers can catch them as such."""

from __future__ import annotations

__all__ = ["TorchprojError", "InputError", "ConfigError", "CaptureError"]


class TorchprojError(ValueError):
    """Base class of torchproj's errors."""


class InputError(TorchprojError):
    """A function argument has the wrong shape, dtype, device or values."""


class ConfigError(TorchprojError):
    """A scene or rig description is invalid. The message names the field (``camera.focal``)."""

    def __init__(self, field: str, problem: str, fix: str = ""):
        self.field = field
        message = f"{field}: {problem}"
        if fix:
            message += f" ({fix})"
        super().__init__(message)


class CaptureError(TorchprojError):
    """A folder of captured images is incomplete, inconsistent or unreadable."""
