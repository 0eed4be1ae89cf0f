"""The ``torchproj`` command's argument types and the options that several subcommands share.

Each option is declared here once; :mod:`torchproj.cli` declares what is a command's own.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

__all__ = ["BITS_HELP", "bounds", "command", "config_option", "decoding_options", "device_options", "existing_file",
           "join_negative_pairs", "limits", "map_options", "named_projector_size", "positive_float", "positive_int", "projector_size", "solve_options",
           "solver_options"]


# ------------------------------------------------------------------------------ argument types
def positive_int(text: str) -> int:
    """A whole number of at least 1 (an iteration limit)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def positive_float(text: str) -> float:
    """A finite number above 0 (a length, a tolerance)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (0 < value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a finite number above 0, got {text}")
    return value


def projector_size(text: str) -> tuple[int, int]:
    from .core.choices import SIZE_LIMIT

    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w <= 0 or h <= 0:
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT in pixels such as 1024x768, got {text!r}") from None
    if w * h > SIZE_LIMIT:
        raise argparse.ArgumentTypeError(f"{text}: {w * h:.3g} cells, more than any projector ({SIZE_LIMIT:.0e})")
    return w, h


def named_projector_size(text: str) -> tuple[str, tuple[int, int]]:
    """``[NAME=]WxH``: a projector's name (``*``: every projector) and its size."""
    name, _, size = text.rpartition("=")
    try:
        return name or "*", projector_size(size)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected [NAME=]WIDTHxHEIGHT such as lower=1024x768, got {text!r}") from None


def screen_corner(text: str) -> tuple[int, int]:
    """``X,Y``: a projector's screen's top-left corner in the desktop, in whole pixels (left of or above
    the main screen negative)."""
    try:
        x, y = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in whole pixels (the projector's screen's top-left corner in "
                                         f"the desktop, e.g. 1920,0), got {text!r}") from None
    return x, y


def named_screen_corner(text: str) -> tuple[str, tuple[int, int]]:
    """``NAME=X,Y``: a projector's screen corner in the desktop."""
    name, sep, corner = text.partition("=")
    try:
        if sep and name:
            return name, screen_corner(corner)
    except argparse.ArgumentTypeError:
        pass
    raise argparse.ArgumentTypeError(f"expected NAME=X,Y (a projector's screen corner, e.g. upper=1920,0), got {text!r}")


def _pair(text: str, example: str, strict: bool) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LO,HI such as {example}, got {text!r}") from None
    if not (lo < hi if strict else lo <= hi):
        raise argparse.ArgumentTypeError(f"need LO {'<' if strict else '<='} HI, got {text!r}")
    return lo, hi


def bounds(text: str) -> tuple[float, float]:
    return _pair(text, "0,255 or -100,255 (8-bit units)", strict=True)


def limits(text: str) -> tuple[float, float]:
    return _pair(text, "0.5,1.5", strict=False)


def existing_file(text: str) -> Path:
    if not Path(text).is_file():
        raise argparse.ArgumentTypeError(f"{text}: no such file")
    return Path(text)


# ------------------------------------------------------------------------ shared options
BITS_HELP = ("show only the first K Gray-code pattern pairs per axis (at least 2): 4K + 4 images per projector "
              "and state with white, black and the two ramps, instead of 46 for a 1024x768 projector (with the "
              "checkerboard pair)")


def command(sub, name: str, func, help: str, out: str | None = None, out_help: str = "output folder"):
    """A subcommand that runs ``func``, with its ``--out`` folder (required where ``out`` is None)."""
    p = sub.add_parser(name, help=help)
    p.set_defaults(func=func)
    if out != "":
        p.add_argument("--out", type=Path, default=out, required=out is None,
                       help=out_help + (f" (default: {out})" if out else ""))
    return p


def config_option(p, default: str = "paper_two_planes") -> None:
    from .core.choices import SIZE_LIMIT

    p.add_argument("config", nargs="?", default=default, help=f"YAML file or built-in name (default: {default})")
    p.add_argument("--size-limit", type=float, default=SIZE_LIMIT, metavar="N", help="refuse a scene with more camera "
                   f"rays per state (pixels x supersampling^2) or cells per projector than this (default {SIZE_LIMIT:.0e})")


def device(text: str) -> str:
    if text == "cpu":  # always there; checked without importing torch, so that --help answers at once
        return text
    from .core.checks import check_device
    from .core.errors import InputError

    try:
        check_device(text)
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def cache_option(p) -> None:
    p.add_argument("--no-cache", action="store_true", help="simulate the calibration (and build the transport) even "
                   "where the same scene ran before (kept in the user cache folder, or $TORCHPROJ_CACHE_DIR; at most "
                   "$TORCHPROJ_CACHE_MAX_GB, default 2, the least recently used removed first)")


def device_options(p, max_iter: bool = True) -> None:
    p.add_argument("--device", type=device, default="cpu", help="torch device, cpu or cuda (default: cpu)")
    if max_iter:
        p.add_argument("--max-iter", type=positive_int, default=None,
                       help="iteration limit of the pattern solver (default: 300 for fista, pgd and adam; lf and eo "
                            "stop on their own convergence rules)")


def solver_options(p) -> None:
    """The pattern solver and its bounds (``run``, ``solve``, ``position``)."""
    from .core.choices import CHAINS, OUTSIDE, SOLVER_NAMES

    p.add_argument("--solver", default="fista", choices=list(SOLVER_NAMES), help="pattern solver (default: fista)")
    p.add_argument("--bounds", type=bounds, default=(0.0, 255.0), metavar="LO,HI",
                   help="solver bounds in 8-bit units as in the paper (default 0,255; eo with -100,255 is EO_-100^255)")
    p.add_argument("--outside", default="clip", choices=list(OUTSIDE),
                   help="how values solved below 0 (bounds LO < 0) are shown: clip them to black (default) or map "
                        "LO..HI linearly onto 0..255 (the paper does not say which it did)")
    p.add_argument("--chains", default="epipolar", choices=list(CHAINS),
                   help="eo's independent problems: epipolar chains between two projectors (the paper's; default) "
                        "or the connected components of the transport (any number of projectors)")


def solve_options(p) -> None:
    """The options of every command that solves patterns (``run``, ``solve``)."""
    from .core.choices import COLOUR_WEIGHTS, DEFAULT_FOOTPRINT, DEFAULT_SMOOTHNESS, FOOTPRINTS, OBJECTIVES, PSNR_DROP_DB

    solver_options(p)
    p.add_argument("--objective", default="l2", choices=list(OBJECTIVES),
                   help="l2: least squares (default); ssim or mixed: SSIM of the predicted camera images with a small "
                        "or larger weight on their squared error, started from the solver's patterns")
    p.add_argument("--l2-weight", type=float, metavar="W", help="ssim/mixed: the squared error's weight relative to "
                   f"the start's (defaults: ssim {OBJECTIVES['ssim']:g}, mixed {OBJECTIVES['mixed']:g})")
    p.add_argument("--psnr-drop", type=float, default=PSNR_DROP_DB, metavar="DB", help="ssim/mixed: the PSNR each "
                   f"target may give up against least squares, in the model (default {PSNR_DROP_DB:g}; -1: no limit)")
    p.add_argument("--ssim-iter", type=int, default=30, metavar="N", help="ssim/mixed: iterations (default 30)")
    p.add_argument("--footprint", default=DEFAULT_FOOTPRINT, choices=[*FOOTPRINTS, "auto"], help="the projector cells "
                   "a camera pixel's light is modelled on: nearest (one per projector, as the paper), bilinear (the four "
                   "around its sub-pixel coordinate), area (those its area covers) or auto (nearest where the measured "
                   "cell shares put its expected loss within 0.2 dB of a model that holds them, else area; the report "
                   f"says which and why); default {DEFAULT_FOOTPRINT}")
    p.add_argument("--smoothness", type=float, metavar="W", help="weight of a penalty on neighbouring projector "
                   "cells' differences in the least-squares solve, over the target scale squared: among patterns that "
                   "the model finds nearly equal it picks the smoother, whose light depends least on the model's "
                   "sub-cell detail; it holds where few camera pixels see a cell (default "
                   f"{DEFAULT_SMOOTHNESS:g} for fista, pgd and adam; 0: none; lf and eo take none)")
    p.add_argument("--colour-weights", default="channel", choices=list(COLOUR_WEIGHTS), help="colour camera and "
                   "targets: model each channel with its own white minus black and solve the channels apart (channel, "
                   "default; ssim/mixed then refine the channels together), or give every channel their mean (grey)")
    device_options(p)


def map_options(p, maps: bool = True, bits: str | None = None) -> None:
    from .core.choices import MAPS

    if maps:
        p.add_argument("--maps", default="decoded", choices=list(MAPS),
                       help="camera-to-projector maps: decoded per pixel (default), or one homography per state and "
                            "projector fitted to them (scenes where each state is one plane)")
    if bits is not None:
        p.add_argument("--bits", type=int, metavar="K", help=bits)
    p.add_argument("--plane-tolerance", type=float, default=1.0, metavar="PX",
                   help="with --maps homography or --bits: the largest 95th-percentile residual (projector pixels) "
                        "between decoded and fitted coordinates that counts as a plane (default 1)")


def decoding_options(p) -> None:
    """Thresholds and hole filling of ``calibrate`` and ``decode`` (OpenCV's defaults)."""
    p.add_argument("--white-threshold", type=float, default=5, help="8-bit units (OpenCV default 5)")
    from .core.choices import BLACK_THRESHOLD

    p.add_argument("--black-threshold", type=float, default=BLACK_THRESHOLD,
                   help=f"8-bit units (OpenCV default {BLACK_THRESHOLD})")
    p.add_argument("--fill-holes", type=int, default=16, metavar="N", help="fill holes up to N pixels (0: off)")


_PAIR_OPTIONS = ("--bounds", "--gain", "--offset", "--screen")  # --screen: a screen left of the main one


def join_negative_pairs(argv: list[str]) -> list[str]:
    """``--bounds -100,255`` -> ``--bounds=-100,255``: argparse takes a value starting with '-' (and
    not a plain number) for an option, so the paper's own notation would otherwise be refused."""
    out, i = [], 0
    while i < len(argv):
        if argv[i] in _PAIR_OPTIONS and i + 1 < len(argv) and re.fullmatch(r"-[\d.]+,-?[\d.]+", argv[i + 1]):
            out.append(f"{argv[i]}={argv[i + 1]}")
            i += 2
        else:
            out.append(argv[i])
            i += 1
    return out
