"""Image files at the edges of the library: integers on disk, float ``(C, H, W)`` in [0, 1] inside.

See :mod:`torchproj.core.conventions` for the image convention.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import torch

from .checks import check, check_path, is_whole
from .errors import CaptureError, InputError

__all__ = ["read_image", "write_image", "to_uint"]


def read_image(path: str | os.PathLike, remedy: str = "capture it again") -> torch.Tensor:
    """Read an 8- or 16-bit PNG/TIFF/JPEG as a float image.

    Args:
        path: the file.
        remedy: what the message of an unreadable file tells a person to do (a capture: take it
            again; a target image: save it again).

    Returns:
        :math:`(C, H, W)` float32 tensor in [0, 1], C = 1 (grey) or 3 (RGB order).

    Raises:
        CaptureError: naming the file when it is missing, unreadable or of an unsupported depth.
    """
    check_path(path, "path", "the image file")
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: file not found")
    # Upright as a viewer shows it: a phone's photo keeps its pixels as the sensor read them and says
    # the turn in its EXIF orientation. These flags turn JPEG and PNG by it (IMREAD_UNCHANGED does not)
    # and keep 16 bits; they drop alpha, which no image here uses. A TIFF is turned by libtiff either
    # way, but OpenCV 5.1 reads none whose turn swaps its sides (orientations 5-8).
    data = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    if data is None:
        turned = ("; OpenCV reads no TIFF turned a quarter by its EXIF orientation (5-8): save such a one "
                  "upright or as PNG") if path.suffix.lower() in (".tif", ".tiff") else ""
        raise CaptureError(f"{path}: cannot be read as an image (corrupt or truncated?); {remedy}{turned}")
    if data.dtype == np.uint8:
        scale = 255.0
    elif data.dtype == np.uint16:
        scale = 65535.0
    else:
        raise CaptureError(f"{path}: unsupported pixel type {data.dtype}; save 8- or 16-bit images")
    if data.ndim == 3:
        data = data[:, :, ::-1]  # OpenCV stores BGR
        tensor = torch.from_numpy(np.ascontiguousarray(data)).permute(2, 0, 1)
    else:
        tensor = torch.from_numpy(data)[None]
    return tensor.float() / scale


def to_uint(image: torch.Tensor, bits: int = 8) -> np.ndarray:
    """Quantise a float image in [0, 1] to an ``(H, W)`` or ``(H, W, 3)`` integer array (RGB)."""
    if not (is_whole(bits) and bits in (8, 16)):
        raise InputError(f"bits must be 8 or 16, got {bits!r}")
    check(isinstance(image, torch.Tensor) and image.dim() == 3 and image.shape[0] in (1, 3) and image.numel() > 0,
          f"image must be a (C, H, W) tensor of 1 or 3 channels, got "
          f"{tuple(image.shape) if isinstance(image, torch.Tensor) else type(image).__name__}")
    peak = (1 << bits) - 1
    dtype = np.uint8 if bits == 8 else np.uint16
    arr = torch.round(image.detach().clamp(0, 1) * peak).to(torch.int32).cpu().numpy().astype(dtype)
    return arr[0] if arr.shape[0] == 1 else np.ascontiguousarray(arr.transpose(1, 2, 0))


def write_image(path: str | os.PathLike, image: torch.Tensor, bits: int = 8) -> None:
    """Write a float ``(C, H, W)`` image in [0, 1] as an 8- or 16-bit file (format from the suffix)."""
    check_path(path, "path", "the image file")
    check(cv2.haveImageWriter(str(path)), f"{path}: no image format is written for the suffix "
                                          f"{Path(path).suffix or '(none)'!r}; give .png, .tif or .jpg")
    arr = to_uint(image, bits)
    if arr.ndim == 3:
        arr = arr[:, :, ::-1]
    # Encoded here and written by Python, so that a write the disk refuses raises the OSError that says
    # why (cv2.imwrite returns False and prints libpng's "Write Error" to the terminal).
    try:
        ok, encoded = cv2.imencode(Path(path).suffix, arr)
    except cv2.error:
        ok = False
    if not ok:
        raise OSError(f"{path}: cannot be written as an image of format {Path(path).suffix or '(no suffix)'!r}")
    Path(path).write_bytes(encoded.tobytes())
