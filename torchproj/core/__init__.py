"""Shared errors, input checks, conventions and image I/O (imports no other sub-package).

Imported on first use (:mod:`torchproj._lazy`): the command reads its errors and output contract
from here before anything has imported torch.
"""

from .._lazy import lazy_names

_WHERE = {**dict.fromkeys(("check", "check_count", "check_finite", "check_image", "check_number", "check_seed",
                           "check_shape"), "checks"),
          **dict.fromkeys(("pixel_grid", "round_to_pixel", "to_numpy"), "conventions"),
          **dict.fromkeys(("CaptureError", "ConfigError", "InputError", "TorchprojError"), "errors"),
          **dict.fromkeys(("read_image", "to_uint", "write_image"), "imageio"),
          **dict.fromkeys(("atomic_output", "write_json"), "output")}
__getattr__, __dir__ = lazy_names(__name__, _WHERE)

__all__ = sorted(_WHERE)
