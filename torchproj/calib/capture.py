"""Capture folders: the images a camera took while one projector showed the calibration sequence.

Layout (that of ``shared/data/procam_chessboard/capture_0``): the Gray-code captures in pattern
order, then the all-white capture, then the all-black one, named by a template that defaults to
``graycode_{:02d}.png`` (``graycode_00.png`` ... ``graycode_41.png`` for a 1024x768 projector).
Optional photometric captures sit beside them as ``ramp.png`` and ``ramp_mirrored.png``, and the
optional checkerboard pair (:func:`~torchproj.calib.checker_patterns`) as ``checker.png`` and
``checker_inverse.png``, and, for a colour camera, the full-field primaries
(:func:`~torchproj.calib.primary_patterns`) as ``red.png``, ``green.png`` and ``blue.png``.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import torch

from ..core.checks import check, check_path
from ..core.errors import CaptureError
from ..core.imageio import read_image, write_image
from .graycode import check_projector_size, sequence_bits

__all__ = ["GraycodeCapture", "read_graycode_folder", "sequence_paths", "write_graycode_folder", "DEFAULT_NAMES",
           "RAMP_NAMES", "CHECKER_NAMES", "PRIMARY_NAMES"]

DEFAULT_NAMES = "graycode_{:02d}.png"
RAMP_NAMES = ("ramp.png", "ramp_mirrored.png")
CHECKER_NAMES = ("checker.png", "checker_inverse.png")
PRIMARY_NAMES = ("red.png", "green.png", "blue.png")
_DARK = 8 / 255  # a white capture whose brightest pixel is below this saw no projector light


@dataclass
class GraycodeCapture:
    """Images of one capture folder, float :math:`(C, H, W)` each (conventions module).

    Attributes:
        patterns: :math:`(N, C, H, W)` Gray-code captures in pattern order.
        white, black: :math:`(C, H, W)`.
        ramp: :math:`(2, C, H, W)` ramp and mirrored ramp captures, or None if absent.
        checker: :math:`(2, C, H, W)` captures of the checkerboard and its inverse
            (:func:`~torchproj.calib.checker_patterns`), or None if absent.
        primaries: :math:`(3, C, H, W)` captures of full-field red, green and blue
            (:func:`~torchproj.calib.primary_patterns`), or None if absent.
    """

    patterns: torch.Tensor
    white: torch.Tensor
    black: torch.Tensor
    ramp: torch.Tensor | None = None
    checker: torch.Tensor | None = None
    primaries: torch.Tensor | None = None


def sequence_paths(folder: str | os.PathLike, projector_size: tuple[int, int], names: str = DEFAULT_NAMES,
                   bits: int | tuple[int, int] | None = None) -> list[Path]:
    """The Gray-code sequence's files of a capture folder, in pattern order, checked by name only
    (every one there, none beyond the sequence): what :func:`read_graycode_folder` reads, and what
    a capture root's every folder is checked for before any is decoded (arguments as there).

    Raises:
        CaptureError: naming the folder or file and what to do.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise CaptureError(f"{folder}: capture folder not found")
    nx, ny = sequence_bits(*check_projector_size(projector_size), bits)
    count = 2 * (nx + ny) + 2
    paths = [folder / name for name in _file_names(names, count)]
    missing = [p.name for p in paths if not p.is_file()]
    if missing:
        raise CaptureError(
            f"{folder}: expected {count} images for a {projector_size[0]}x{projector_size[1]} projector "
            f"({2 * nx} column + {2 * ny} row Gray-code images, then white, then black) named like "
            f"{paths[0].name}; missing {len(missing)}: {', '.join(missing[:4])}"
            f"{' ...' if len(missing) > 4 else ''} (check --projector, --bits and the name template)")
    extra = _numbered_files(folder, names) - {p.name for p in paths}
    if extra:
        raise CaptureError(f"{folder / min(extra)}: {len(extra)} image(s) named like the sequence beyond a "
                           f"{projector_size[0]}x{projector_size[1]} projector's {count} ({nx} column + {ny} row "
                           "bits, then white and black); check --projector and --bits, or move extra files out of "
                           "the folder")
    return paths


def read_graycode_folder(folder: str | os.PathLike, projector_size: tuple[int, int],
                         names: str = DEFAULT_NAMES, bits: int | tuple[int, int] | None = None) -> GraycodeCapture:
    """Read and check a capture folder.

    Args:
        folder: the folder.
        projector_size: ``(width, height)`` of the projector that showed the sequence.
        names: file name template, formatted with the image index (``graycode_{:02d}.png``).
        bits: pattern pairs per axis of a shortened sequence
            (:func:`~torchproj.calib.graycode.sequence_bits`); None: the full sequence.

    Raises:
        CaptureError: naming the file and what to do, for a missing folder or image, an unreadable
            file, images of different sizes, or a white capture that shows no projector light.
    """
    check_path(folder, "folder", "a capture folder")
    folder = Path(folder)  # a path given as text, as the signature allows
    paths = sequence_paths(folder, projector_size, names, bits)
    # PNG decoding releases the GIL: read on a few threads.
    with ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as pool:
        images = list(pool.map(read_image, paths))
    for p, img in zip(paths, images):
        if img.shape != images[0].shape:
            raise CaptureError(f"{p}: size {tuple(img.shape)} (C, H, W) differs from {paths[0].name}'s "
                               f"{tuple(images[0].shape)}; all captures must come from one camera setting")
    stack = torch.stack(images)
    white, black = stack[-2], stack[-1]
    if float(white.max()) < _DARK:
        raise CaptureError(f"{paths[-2]}: the white capture is dark everywhere (max {float(white.max()) * 255:.0f}/255): "
                           "was the projector on and pointed at the scene? Capture again")
    ramp = None
    ramp_paths = [folder / n for n in RAMP_NAMES]
    if all(p.is_file() for p in ramp_paths):
        ramp = _read_extra(ramp_paths, white.shape, paths[0].name)
    checker = _read_set(folder, CHECKER_NAMES, white.shape, paths[0].name, "the checkerboard is read as a pair")
    primaries = _read_set(folder, PRIMARY_NAMES, white.shape, paths[0].name, "the primaries are read as a set of three")
    return GraycodeCapture(patterns=stack[:-2], white=white, black=black, ramp=ramp, checker=checker,
                          primaries=primaries)


def _read_set(folder: Path, names: tuple[str, ...], shape, first: str, why: str) -> torch.Tensor | None:
    """Captures that come as a set (the checkerboard pair, the three primaries): all, or None where
    none is there; a set with some missing is refused, naming one."""
    paths = [folder / n for n in names]
    present = [p.is_file() for p in paths]
    if not any(present):
        return None
    if not all(present):
        lack = paths[present.index(False)]
        have = paths[present.index(True)]
        raise CaptureError(f"{lack}: missing, while {have.name} is there: {why}; capture the rest, or move "
                           f"{', '.join(names)} out of the folder to calibrate without them")
    return _read_extra(paths, shape, first)


def _read_extra(paths: list[Path], shape, first: str) -> torch.Tensor:
    """Captures beside the Gray code (the ramps, the checkerboard pair), of the Gray code's size."""
    images = [read_image(p) for p in paths]
    for p, img in zip(paths, images):
        if img.shape != shape:
            raise CaptureError(f"{p}: size {tuple(img.shape)} (C, H, W) differs from {first}'s {tuple(shape)}; all "
                               "captures must come from one camera setting")
    return torch.stack(images)


def _file_names(names: str, count: int) -> list[str]:
    """The first ``count`` file names of a template, or a :class:`CaptureError` that says what a template is."""
    try:
        files = [names.format(i) for i in range(count)]
    except (ValueError, IndexError, KeyError, AttributeError):
        files = []
    if len(set(files)) != count or any(not f or "/" in f or "\\" in f for f in files):
        raise CaptureError(f"names {names!r} is not a file name template with one number field for the image index, "
                           f"such as {DEFAULT_NAMES!r}")
    return files


def _numbered_files(folder: Path, names: str) -> set[str]:
    """Files of ``folder`` that the template ``names`` could have made (any index)."""
    head, _, rest = names.partition("{")
    tail = rest.partition("}")[2]
    return {p.name for p in folder.iterdir() if p.is_file() and p.name.startswith(head) and p.name.endswith(tail)
            and len(p.name) > len(head) + len(tail) and p.name[len(head):len(p.name) - len(tail)].isdigit()}


def write_graycode_folder(folder: str | os.PathLike, capture: GraycodeCapture, bits: int = 8,
                          names: str = DEFAULT_NAMES) -> None:
    """Write a capture in the folder layout :func:`read_graycode_folder` reads."""
    check_path(folder, "folder", "a capture folder")
    check(isinstance(capture, GraycodeCapture), f"capture must be a GraycodeCapture, got {type(capture).__name__}")
    images = list(capture.patterns) + [capture.white, capture.black]
    files = _file_names(names, len(images))  # a template without the index wrote every image to one file
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for file, img in zip(files, images):
        write_image(folder / file, img, bits)
    for files, shots in ((RAMP_NAMES, capture.ramp), (CHECKER_NAMES, capture.checker),
                         (PRIMARY_NAMES, capture.primaries)):
        if shots is not None:
            for name, img in zip(files, shots):
                write_image(folder / name, img, bits)
