"""Shared errors, input checks, conventions and image I/O (imports no other room)."""

from .checks import check, check_finite, check_image, check_shape
from .conventions import pixel_grid, round_to_pixel
from .errors import CaptureError, ConfigError, InputError, TorchprojError
from .imageio import read_image, to_uint, write_image
from .output import atomic_output, write_json

__all__ = [
    "CaptureError",
    "ConfigError",
    "InputError",
    "TorchprojError",
    "atomic_output",
    "check",
    "check_finite",
    "check_image",
    "check_shape",
    "pixel_grid",
    "read_image",
    "round_to_pixel",
    "to_uint",
    "write_image",
    "write_json",
]
