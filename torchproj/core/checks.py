"""The one place for input checks.

Every check raises :class:`torchproj.core.errors.InputError` (a ``ValueError``) whose message names
the argument and says how to fix it.
"""

from __future__ import annotations

import functools
import math
import numbers
import os
import warnings
from typing import Sequence

import numpy as np
import torch

from .errors import InputError

# Above this many camera rays per state (pixels x supersampling^2), or cells per projector, a rig is
# refused before any work: the default scene casts 1.7e7 rays per state (3.8 s, docs/measured.md), so
# the limit is ~6x that in time and memory; a mistyped size (60000 x 40000, supersampling 200) would
# otherwise run for hours or fail in the allocator. Raise it with load_scene(size_limit=) or --size-limit.
from .choices import SIZE_LIMIT  # noqa: E402  (10^8; there, for the command's parser)

__all__ = ["SIZE_LIMIT", "check_array", "check_indices", "check_mask", "check_pair", "check_window", "check_shape", "check_finite", "check_image", "check", "check_count", "check_device",
           "check_number", "check_seed", "env_number", "env_switch"]


def check(condition: bool, message: str) -> None:
    """Raise :class:`InputError` with ``message`` unless ``condition`` holds."""
    if not condition:
        raise InputError(message)


def is_whole(value) -> bool:
    """Whether ``value`` is a whole number of any integer type (numpy's too): not a bool, though Python
    counts True as 1, and not a float such as 2.0."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def check_count(value, name: str, minimum: int = 1) -> int:
    """``value`` as an int: a whole number (not a bool, not a float such as 2.5) of at least ``minimum``."""
    check(is_whole(value) and value >= minimum,
          f"{name} must be a whole number >= {minimum}, got {value!r}")
    return int(value)


def check_indices(tensor: torch.Tensor, name: str, dims: Sequence[str | int]) -> dict[str, int]:
    """:func:`check_shape`, and integer values: indices into something (a float or bool tensor would
    be read as values or as a mask instead)."""
    sizes = check_shape(tensor, name, dims)
    check(not tensor.is_floating_point() and tensor.dtype != torch.bool and not tensor.is_complex(),
          f"{name} must be integer indices, got {tensor.dtype}")
    return sizes


def check_mask(mask: torch.Tensor, name: str, dims: Sequence[str | int]) -> dict[str, int]:
    """:func:`check_shape`, and bool: a mask of pixels (an integer one would index pixels 0 and 1
    instead of choosing pixels)."""
    sizes = check_shape(mask, name, dims)
    check(mask.dtype == torch.bool, f"{name} must be a bool tensor, got {mask.dtype}")
    return sizes


def check_window(window, name: str = "window") -> int:
    """A window of pixels centred on each pixel: an odd whole number >= 3."""
    check(is_whole(window) and window % 2 == 1 and window >= 3, f"{name} must be an odd whole number >= 3, got {window!r}")
    return int(window)


def check_pair(value, name: str, what: str, minimum: int = 0) -> tuple[int, int]:
    """``value`` as two whole numbers of at least ``minimum`` (a list or tuple): ``what`` says which two,
    for the message (``"(width, height)"``)."""
    check(isinstance(value, (tuple, list)) and len(value) == 2 and all(is_whole(v) and v >= minimum for v in value),
          f"{name} must be {what}, whole numbers >= {minimum}, got {value!r}")
    return int(value[0]), int(value[1])


def check_seed(value, name: str = "seed", limit: int = 2 ** 63, hint: str = "") -> int:
    """``value`` as an int: a whole number from 0 to ``limit - 1`` (torch's and numpy's generators take
    no negative seed, torch none of 2**63 or more). ``hint`` follows the range in the message."""
    check(is_whole(value) and 0 <= value < limit,
          f"{name} must be a whole number from 0 to {_power(limit)} - 1{hint}, got {value!r}")
    return int(value)


def env_switch(name: str) -> bool:
    """An environment switch: on for ``1`` (or ``true``, ``yes``, ``on``), off when unset, empty or ``0``
    (``false``, ``no``, ``off``), any case. Anything else is off, and warned of once: ``TORCHPROJ_COMPILE=
    true`` had been off without a word, as only ``1`` turned it on."""
    raw = os.environ.get(name, "")
    value = raw.strip().lower()
    if value in ("1", "true", "yes", "on"):
        return True
    if value not in ("", "0", "false", "no", "off"):
        _warn_setting(name, raw, "off (set it to 1 to turn it on, or unset it)")
    return False


def env_number(name: str, default: float, minimum: float = 0.0) -> float:
    """A number from the environment, ``default`` where it is unset or empty (``inf`` is a number: no
    limit). One that is not a number of at least ``minimum`` gives ``default``, and is warned of once
    (``TORCHPROJ_CACHE_MAX_GB=500MB`` had kept 2 GB without a word, and ``nan`` removed every entry)."""
    raw = os.environ.get(name, "")
    if not raw.strip():
        return default
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not value >= minimum:  # NaN too
        _warn_setting(name, raw, f"{default:g} (give a number of at least {minimum:g})")
        return default
    return value


@functools.lru_cache(maxsize=None)
def _warn_setting(name: str, raw: str, taken: str) -> None:
    """Once per variable and value, however often it is read."""
    warnings.warn(f"{name}={raw!r} is not a value torchproj reads; taking {taken}", stacklevel=4)


def _power(limit: int) -> str:
    """``2**k`` where ``limit`` is a power of two, else the number."""
    return f"2**{limit.bit_length() - 1}" if limit & (limit - 1) == 0 else str(limit)


def check_array(values, name: str, shape: Sequence[int | None], dtype=np.float64, finite: bool = False) -> np.ndarray:
    """``values`` (an array, a tensor on the CPU, nested lists) as a numpy array of ``dtype`` and ``shape``
    (None: any size along that axis), its values finite where ``finite``: what the functions that
    compute in numpy (poses, point clouds) take."""
    try:
        array = np.asarray(values, dtype=dtype)
    except (TypeError, ValueError, OverflowError, RuntimeError):
        array = None
    fits = array is not None and array.ndim == len(shape) and all(n in (None, s) for n, s in zip(shape, array.shape))
    wanted = "(" + ", ".join("N" if n is None else str(n) for n in shape) + (",)" if len(shape) == 1 else ")")
    check(fits, f"{name} must be {wanted} numbers, got {type(values).__name__}"
                + ("" if array is None else f" of shape {tuple(array.shape)}"))
    check(not finite or bool(np.isfinite(array).all()), f"{name} must be finite, got {values!r}")
    return array


def check_path(value, name: str, what: str) -> None:
    """``value`` a path (a str or an ``os.PathLike``): ``what`` says whose, for the message."""
    check(isinstance(value, (str, os.PathLike)), f"{name} must be {what}'s path, got {type(value).__name__}")


def is_number(value) -> bool:
    """Whether ``value`` is a real number (a bool is not, though Python counts True as 1); NaN and inf are."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def check_number(value, name: str, minimum: float = 0.0, *, strict: bool = False) -> float:
    """``value`` as a float: a finite real number at least ``minimum`` (above it where ``strict``)."""
    ok = is_number(value) and math.isfinite(value) and (
        value > minimum if strict else value >= minimum)
    check(ok, f"{name} must be a finite number {'>' if strict else '>='} {minimum:g}, got {value!r}")
    return float(value)


def check_device(device) -> torch.device:
    """``device`` as a :class:`torch.device` this machine has; an :class:`InputError` that lists the
    devices it does have otherwise (torch's own errors name its internal backends, not what to use)."""
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    have = ["cpu"] + (["cuda"] + [f"cuda:{i}" for i in range(count)] if count else [])
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise InputError(f"device {device!r} is not a torch device; this machine has {have}") from None
    if dev.type == "cuda" and (not count or (dev.index or 0) >= count):
        why = "no such CUDA device is visible" if torch.version.cuda else "this torch is a CPU-only build"
        raise InputError(f"device {device!r}: {why} (torch {torch.__version__}); use one of {have}")
    check(dev.type in ("cpu", "cuda"), f"device {device!r}: torchproj runs on {have}")
    return dev


def check_shape(tensor: torch.Tensor, name: str, dims: Sequence[str | int]) -> dict[str, int]:
    """Check a tensor's shape against a pattern and return the sizes bound to named dimensions.

    Args:
        tensor: the tensor to check.
        name: the argument's name, used in the error message.
        dims: one entry per dimension: an int (that exact size) or a letter (any size, but the same
            letter must have the same size everywhere it appears). ``"*"`` as the first entry allows
            any number of leading dimensions.

    Returns:
        a dict from dimension letters to sizes.

    Example:
        >>> check_shape(torch.zeros(5, 7, 2), "prj_xy", ["H", "W", 2])
        {'H': 5, 'W': 7}
    """
    if not isinstance(tensor, torch.Tensor):
        raise InputError(f"{name} must be a torch.Tensor, got {type(tensor).__name__}")
    dims = list(dims)
    shape = list(tensor.shape)
    if dims and dims[0] == "*":
        dims = dims[1:]
        shape = shape[len(shape) - len(dims):] if len(shape) >= len(dims) else None
    pattern = "(" + ", ".join(str(d) for d in dims) + ")"
    if shape is None or len(shape) != len(dims):
        raise InputError(f"{name} must have shape {pattern}, got {tuple(tensor.shape)}")
    bound: dict[str, int] = {}
    for d, s in zip(dims, shape):
        if isinstance(d, int):
            if s != d:
                raise InputError(f"{name} must have shape {pattern}, got {tuple(tensor.shape)}")
        else:
            if bound.setdefault(d, s) != s:
                raise InputError(
                    f"{name} must have shape {pattern} with equal sizes for '{d}', got {tuple(tensor.shape)}"
                )
    return bound


def all_finite(tensor: torch.Tensor) -> bool:
    """Whether every value of a float tensor is finite, from its least and greatest value alone (one
    pass: ``aminmax`` propagates NaN, and an infinity is one of the two). ``isfinite(t).all()``
    writes a mask of every value and reads it again: 4.8 ms against 0.37 ms on a 3 x 872 x 1000
    target image on 2 cores, paid by every transport build for each target."""
    if tensor.numel() == 0:
        return True
    lo, hi = torch.aminmax(tensor)
    return bool(torch.isfinite(lo) & torch.isfinite(hi))


def check_finite(tensor: torch.Tensor, name: str) -> None:
    """Reject NaN or infinite values (a silent NaN would poison every later step)."""
    if tensor.is_floating_point() and not all_finite(tensor):
        bad = int((~torch.isfinite(tensor)).sum())
        raise InputError(f"{name} holds {bad} non-finite values (NaN or inf); replace or mask them first")


def check_image(image: torch.Tensor, name: str) -> dict[str, int]:
    """Check a library image: float ``(C, H, W)`` with C in {1, 3}, finite, values in [0, 1]."""
    sizes = check_shape(image, name, ["C", "H", "W"])
    check(sizes["C"] in (1, 3), f"{name} must have 1 or 3 channels, got {sizes['C']}")
    check(image.is_floating_point(), f"{name} must be a float tensor in [0, 1], got {image.dtype}")
    check(image.numel() > 0, f"{name} is empty (shape {tuple(image.shape)}): give an image of at least one pixel")
    lo, hi = (float(v) for v in torch.aminmax(image.detach()))  # NaN where any value is NaN: one pass for both checks
    if not (lo >= 0.0 and hi <= 1.0):
        check_finite(image, name)
        check(False, f"{name} must lie in [0, 1], got values in [{lo:.3g}, {hi:.3g}]")
    return sizes
