"""The real-rig path through files: the sequence to project, capture folders, the calibration bundle.

Sequence (``write_sequence``): per projector, the images to show in order, named as their captures
must be named: ``graycode_00.png`` ... (Gray-code pattern/inverse pairs, columns first, most
significant bit first), then white and black (the last two ``graycode_`` indices), then ``ramp.png``
and ``ramp_mirrored.png`` (the photometric ramp), then ``checker.png`` and ``checker_inverse.png``
(a checkerboard of single cells and its inverse, :func:`~torchproj.calib.checker_patterns`: how each
pixel's light splits between diagonal neighbours, which the ``area`` rows fit), with
``sequence.json`` saying what each image is. A shortened sequence (``bits``) shows only the first
pattern pairs per axis and no checkerboard (its map is one homography, its rows no measured shares);
``sequence.json`` records them (``"bits": [kx, ky]``), and calibration reads such a capture through one homography
per state and projector (:mod:`torchproj.calib.homography`), for planar scenes.

Capture root (what ``calibrate_folders`` reads), one folder per scene state and projector, each
holding the camera's image of every sequence image under the same file name::

    CAPTURE_ROOT/
      near/                    a scene state
        upper/                 a projector: graycode_00.png ... graycode_41.png, ramp.png, ramp_mirrored.png,
                               checker.png, checker_inverse.png
        lower/                 (sequence.json here gives the projector's size)
      far/
        upper/ ...

A state folder that holds ``graycode_00.png`` itself is one projector named ``projector`` (the layout
of ``shared/data/procam_chessboard``); one that holds ``bundle.json`` is a calibration bundle kept
there, not a state, and is left out with a warning.

Bundle (``write_bundle`` / ``load_bundle``), format version 1: ``bundle.json`` (camera size and
channels, projectors and sizes, states, response curves, decoded fractions, files) and per state
``STATE/PROJECTOR.npz`` (``prj_xy`` refined and filled, ``prj_xy_integer``, ``valid``, ``contrast``
(white minus black, [0, 1] units: the radiometric weight), ``cam_xy`` inverse map, ``count``; from a
colour camera also ``colour_contrast``, white minus black per channel ``(C, H, W)``, whose mean is
``contrast``; bundles without it give every channel the grey weight; from a full sequence also
``edge_pixel``, ``edge_xy``, ``edge_slope``, ``edge_share``, the :class:`~torchproj.calib.EdgePixels`,
and ``share_cell``, ``share_across``, ``share_outside`` (and, where a checkerboard pair was measured,
``share_checker``; ``share_band`` and ``share_band_white``, the pixels beside outlines and every pattern
pair's share there), the :class:`~torchproj.calib.CellShares`, ``dim_xy``,
the dimly lit pixels' coordinates (:attr:`~torchproj.calib.ProjectorCalibration.dim_xy`), and ``blur``, each
pixel's defocus disc in cells (:attr:`~torchproj.calib.ProjectorCalibration.blur`); bundles without them
model no edge pixel, fit no row to measured shares, add no dim light to rows and take every lens as sharp) and
``STATE/black.npz`` (``black``: the mean of the state's all-black captures, ``(C, H, W)``).
``bundle.json``'s ``files`` names each projector's file: a projector named ``black``, or one whose
name another's matches but for case, is written as ``PROJECTOR_1.npz``.
Bundles from shortened sequences also record ``graycode_bits`` (per projector) and ``homographies``
(per state and projector, :meth:`~torchproj.calib.HomographyFit.as_dict`).
"""

from __future__ import annotations

import json
import os
import shutil
import warnings
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..core.checks import SIZE_LIMIT, check, check_count, check_path, is_whole
from ..core.conventions import to_numpy
from ..core.errors import CaptureError, InputError
from ..core.progress import progress_bar
from ..core.imageio import write_image
from .edges import EdgePixels
from .capture import CHECKER_NAMES, DEFAULT_NAMES, PRIMARY_NAMES, RAMP_NAMES, read_graycode_folder, sequence_paths
from .graycode import CellShares, check_projector_size, checker_patterns, graycode_bits, graycode_patterns, sequence_bits
from .pipeline import (ProjectorCalibration, calibrate_projector, check_calibration_options, check_decoded, warn_if_few_decoded,
                       warn_if_noisy, warn_if_saturated)
from .response import RAMP_STEPS, ResponseCurve, primary_patterns, ramp_pattern, tells_primaries_apart

__all__ = ["BUNDLE_VERSION", "CalibrationBundle", "calibrate_folders", "load_bundle", "sequence_manifest",
           "write_bundle", "write_sequence"]

BUNDLE_VERSION = 1
SEQUENCE_FILE = "sequence.json"


def sequence_manifest(width: int, height: int, ramp_steps: int = RAMP_STEPS,
                      bits: int | tuple[int, int] | None = None) -> dict:
    """``sequence.json`` for a projector of ``width`` x ``height`` cells: the images it shows, in order
    (Gray code, white, black, the ramps, the checkerboard pair of a full sequence, the primaries),
    each by file name and kind. A capture folder keeps it beside the captures it names, and
    :func:`calibrate_folders` reads the projector's size and bits from it."""
    nx, ny = sequence_bits(width, height, bits)  # the sizes' and bits' kinds, before anything is written
    if not (2 <= width and 2 <= height):
        raise InputError(f"projector {width}x{height}: a Gray code needs at least 2 x 2 cells; check the projector's "
                         "resolution (WIDTHxHEIGHT, e.g. 1024x768)")
    ramp_steps = check_count(ramp_steps, "ramp_steps (--ramp-steps, the ramp's bars)", 2)
    if ramp_steps > width:
        raise InputError(f"projector {width}x{height}: narrower than the ramp's {ramp_steps} bars; check the projector's "
                         f"resolution, or give at most {width} ramp steps")
    entries = []
    for i in range(2 * (nx + ny) + 2):
        if i < 2 * (nx + ny):
            axis, bit = ("x", i // 2) if i < 2 * nx else ("y", (i - 2 * nx) // 2)
            entry = {"kind": "graycode", "axis": axis, "bit": bit, "inverse": bool(i % 2)}
        else:
            entry = {"kind": "white" if i == 2 * (nx + ny) else "black"}
        entries.append({"file": DEFAULT_NAMES.format(i), **entry})
    entries += [{"file": name, "kind": "ramp_mirrored" if mirrored else "ramp", "steps": ramp_steps}
                for name, mirrored in zip(RAMP_NAMES, (False, True))]
    if (nx, ny) == graycode_bits(width, height):
        entries += [{"file": name, "kind": "checker", "inverse": name != CHECKER_NAMES[0]} for name in CHECKER_NAMES]
    # A colour camera's channels each see some of every primary: the three full-field primaries
    # measure how much (fit_colour_mixing). A grey camera's calibration leaves them unread.
    entries += [{"file": name, "kind": "primary", "channel": name.removesuffix(".png")} for name in PRIMARY_NAMES]
    manifest = {"version": BUNDLE_VERSION, "projector": [width, height], "order": "show and capture in this order; "
                "save each capture under the same file name", "images": entries}
    if (nx, ny) != graycode_bits(width, height):
        manifest["bits"] = [nx, ny]
    return manifest


def write_sequence(folder: str | os.PathLike, width: int, height: int, ramp_steps: int = RAMP_STEPS,
                   bits: int | tuple[int, int] | None = None) -> dict:
    """Write the images one projector shows, in order, and ``sequence.json``; returns the manifest.

    Args:
        bits: show only the first pattern pairs per axis (:func:`~torchproj.calib.sequence_bits`),
            for planar scenes; None: the full sequence.
    """
    check_path(folder, "folder", "the sequence folder")
    manifest = sequence_manifest(width, height, ramp_steps, bits)  # every check before anything is written
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    images = [*graycode_patterns(width, height, bits),
              *(ramp_pattern(width, height, int(ramp_steps), mirrored=mirrored)[0] for mirrored in (False, True)),
              *(checker_patterns(width, height) if "bits" not in manifest else []),
              *primary_patterns(width, height)]
    for entry, image in zip(manifest["images"], images, strict=True):
        write_image(folder / entry["file"], image)
    (folder / SEQUENCE_FILE).write_text(json.dumps(manifest, indent=2) + "\n")
    return manifest


@dataclass
class CalibrationBundle:
    """What calibration of a real (or virtual) rig recovered, as the solver needs it.

    Attributes:
        camera_size: ``(width, height)``.
        channels: camera channels.
        projectors: ``[(name, width, height)]`` in column order.
        states: state name -> per projector :class:`ProjectorCalibration`-like arrays (see module).
        black: state name -> :math:`(C, H, W)` all-black capture.
        responses: per projector, its :class:`ResponseCurve` (None where no ramp was captured).
        ramps: per projector, the measured ramp points its curve was fitted to (or None).
        decoded: state -> projector -> fraction of camera pixels decoded.
        decoded_lit: state -> projector -> share of the pixels it visibly lights that decoded
            (:attr:`~torchproj.calib.GrayDecoding.lit_located_fraction`).
        capture_noise: state -> projector -> the camera noise of a lit pixel's white minus black,
            as a share of it (:func:`~torchproj.calib.capture_noise`); said when calibrating, not
            kept in ``bundle.json``.
        bits: per projector, the Gray-code pattern pairs per axis its sequence showed.
        homographies: state -> projector -> :class:`~torchproj.calib.HomographyFit` as a dict,
            for projectors calibrated from a shortened sequence.
    """

    camera_size: tuple[int, int]
    channels: int
    projectors: list[tuple[str, int, int]]
    states: dict[str, list[dict]]
    black: dict[str, torch.Tensor]
    responses: list[ResponseCurve | None]
    decoded: dict[str, dict[str, float]] = field(default_factory=dict)
    decoded_lit: dict[str, dict[str, float]] = field(default_factory=dict)
    procam_calibration: Path | None = None
    ramps: list = field(default_factory=list)  # per projector, (levels (L,), measured (L, C)) the fit used, or None
    bits: list = field(default_factory=list)
    homographies: dict = field(default_factory=dict)
    capture_noise: dict[str, dict[str, float]] = field(default_factory=dict)

    def summary(self) -> str:
        """One line: states, projectors, the fraction of the camera decoded in each and (in brackets)
        the share of the pixels each projector lights."""
        lit = self.decoded_lit
        line = (f"{len(self.states)} state(s) x {len(self.projectors)} projector(s); decoded: "
                + ", ".join(f"{s}/{p} {f:.1%}" + (f" ({lit[s][p]:.1%} of its lit pixels)" if p in lit.get(s, {}) else "")
                            for s, d in self.decoded.items() for p, f in d.items()))
        noise = [f"{s}/{p} {f:.2%}" for s, d in self.capture_noise.items() for p, f in d.items() if f is not None]
        if noise:
            line += ("; camera noise of white - black (median share): " + ", ".join(noise)
                     + " (torchproj capture --frames N divides it by the square root of N)")
        return line

    def figure_rows(self) -> list[dict]:
        """Per state and projector, a row of :func:`torchproj.figures.calibration_summary`."""
        rows = []
        for state, maps in self.states.items():
            for (name, _, _), m, response, ramp in zip(self.projectors, maps, self.responses, self.ramps):
                row = {"label": f"{state}/{name}", "prj_xy": m["prj_xy"], "error": None, "valid": m["valid"]}
                if ramp is not None:
                    row.update(levels=to_numpy(ramp[0]), measured=to_numpy(ramp[1]), response=response)
                rows.append(row)
        return rows

    def response_curves(self) -> list[ResponseCurve]:
        """Per projector, its response curve; a linear one, with a warning, where no ramp was captured."""
        curves = []
        for (name, _, _), r in zip(self.projectors, self.responses):
            if r is None:
                warnings.warn(f"projector {name}: the bundle holds no response curve (no ramp captured); assuming "
                              "a linear response", stacklevel=2)
                r = ResponseCurve(torch.ones(1), torch.ones(1), torch.zeros(1))
            curves.append(r)
        return curves


def folder_sequence(folder: Path) -> tuple[tuple[int, int], object] | None:
    """A capture folder's projector size and Gray-code bits (None: the full sequence) as its
    ``sequence.json`` says them; None where it holds none."""
    manifest = folder / SEQUENCE_FILE
    if not manifest.is_file():
        return None
    meta = read_json(manifest, "copy it again from the torchproj sequence output")
    size = _size(meta.get("projector"), f"{manifest}: 'projector'")
    size = (int(size[0]), int(size[1]))
    return size, _shown_bits(folder, size, meta.get("bits"))


def _shown_bits(folder: Path, size: tuple[int, int], bits) -> tuple[int, int]:
    """The pattern pairs per axis a folder's sequence shows (:func:`sequence_bits`), refused naming it."""
    try:
        return sequence_bits(*size, bits)
    except (InputError, TypeError, ValueError) as exc:
        raise CaptureError(f"{folder}: Gray-code bits {bits!r}: {exc}") from None


def _projector_folders(root: Path, sizes: dict[str, tuple[int, int]] | None, only: list[str] | None = None,
                       bits: int | None = None):
    """``{state: [(projector name, folder, (w, h), (kx, ky))]}`` in sorted order, checked for a common set.

    A folder's ``sequence.json`` gives its projector's size and bits; ``sizes`` and ``bits`` stand
    in where a folder has none.
    """
    if not root.is_dir():
        raise CaptureError(f"{root}: capture root not found")
    if only is not None:
        for name in only:
            if not (root / name).is_dir():
                raise CaptureError(f"{root / name}: state folder not found")
    layout = {}
    for state_dir in sorted(p for p in root.iterdir() if p.is_dir() and (only is None or p.name in only)):
        if (state_dir / "bundle.json").is_file() and only is None:
            # ``calibrate ROOT --out ROOT/calib`` puts its bundle where the next calibrate looks for states.
            warnings.warn(f"{state_dir}: a calibration bundle, not a state's captures: left out (keep bundles "
                          "outside the capture root, or name the states with --states)", stacklevel=3)
            continue
        if (state_dir / DEFAULT_NAMES.format(0)).is_file():
            folders = [("projector", state_dir)]
        else:
            folders = [(p.name, p) for p in sorted(state_dir.iterdir()) if p.is_dir()]
        if not folders:
            continue
        entries = []
        for name, folder in folders:
            said = folder_sequence(folder)
            if said is not None:
                size, shown = said
            elif sizes and (name in sizes or "*" in sizes):
                size = check_projector_size(sizes.get(name, sizes.get("*")), f"sizes[{name if name in sizes else '*'!r}]")
                size = (int(size[0]), int(size[1]))
                shown = _shown_bits(folder, size, bits)
            else:
                raise CaptureError(f"{folder}: no {SEQUENCE_FILE} says the projector's size; give it with "
                                   f"--projector WxH (all projectors) or --projector {name}=WxH")
            entries.append((name, folder, size, shown))
        layout[state_dir.name] = entries
    if not layout:
        raise CaptureError(f"{root}: no capture folders (expected {root}/STATE/PROJECTOR/{DEFAULT_NAMES.format(0)} "
                           "...; see docs/commands.md for the capture layout)")
    first_state, first = next(iter(layout.items()))
    names = [(n, s, b) for n, _, s, b in first]
    for state, entries in layout.items():
        if [(n, s, b) for n, _, s, b in entries] != names:
            raise CaptureError(f"{root / state}: projectors (name, size, Gray-code bits) "
                               f"{[(n, s, b) for n, _, s, b in entries]} differ from {first_state}'s {names}; every "
                               "state needs one folder per projector, captured with the same sequence")
    return layout


def calibrate_folders(root: str | os.PathLike, sizes: dict[str, tuple[int, int]] | None = None, *,
                      states: list[str] | None = None, progress: bool | None = None, bits: int | None = None,
                      **options) -> CalibrationBundle:
    """Decode every state and projector under a capture root and fit the projectors' responses.

    Args:
        root: the capture root (module docstring).
        sizes: projector sizes where folders hold no ``sequence.json``: name -> ``(w, h)``, or
            ``{"*": (w, h)}`` for all.
        states: the state folders to calibrate (default: every folder of the root).
        bits: Gray-code bits per axis of a shortened sequence, where folders hold no
            ``sequence.json`` (one that does says its own).
        options: passed to :func:`~torchproj.calib.calibrate_projector` (thresholds, hole size,
            plane tolerance).

    The response of each projector comes from the first state whose folder holds ramps that show
    enough of their bars (a small object in one state may see only a few).
    """
    check(sizes is None or isinstance(sizes, Mapping),
          f"sizes must be a dict of projector name -> (width, height), got {type(sizes).__name__}")
    check(states is None or (isinstance(states, (list, tuple)) and all(isinstance(s, str) for s in states)),
          f"states must be a list of state folder names, got {states!r}")
    check_calibration_options(options)  # before minutes of decoding, and whatever sequence a folder holds
    check_path(root, "root", "the capture root")
    root = Path(root)
    layout = _projector_folders(root, sizes, states, bits)
    first = next(iter(layout.values()))
    projectors = [(n, s[0], s[1]) for n, _, s, _ in first]
    shown = [b for _, _, _, b in first]
    maps, black, decoded, decoded_lit, homographies, noise = {}, {}, {}, {}, {}, {}
    responses: list[ResponseCurve | None] = [None] * len(projectors)
    ramps: list = [None] * len(projectors)
    unfit: dict[int, str] = {}  # projector -> why its first ramp that showed too few bars fit nothing
    shape = None
    jobs = [(state, j, entry) for state, entries in layout.items() for j, entry in enumerate(entries)]
    for _, _, (_, folder, size, k) in jobs:  # a file missing from the last folder is named before minutes of decoding
        sequence_paths(folder, size, bits=k)
    for state, j, (name, folder, size, k) in progress_bar(jobs, "calibrating states x projectors", progress):
        capture = read_graycode_folder(folder, size, bits=k)
        if shape is None:
            shape = tuple(capture.white.shape)
        elif tuple(capture.white.shape) != shape:
            raise CaptureError(f"{folder}: images of size {tuple(capture.white.shape)} (C, H, W), but earlier "
                               f"folders hold {shape}; all captures must come from one camera setting")
        try:
            cal = calibrate_projector(capture, size, bits=k, require_response=False, **options)
        except InputError as exc:  # e.g. a ramp with no usable levels or a block map off the plane: name the folder
            raise CaptureError(f"{folder}: {exc}") from None
        if cal.homography is not None:
            homographies.setdefault(state, {})[name] = cal.homography.as_dict()
        fraction = check_decoded(cal.decoding, folder)
        decoded_lit.setdefault(state, {})[name] = round(warn_if_few_decoded(cal.decoding, str(folder)), 4)
        warn_if_saturated(cal.saturated, str(folder))
        warn_if_noisy(cal.capture_noise, cal.saturated, str(folder), "torchproj capture --frames N")
        noise.setdefault(state, {})[name] = cal.capture_noise
        decoded.setdefault(state, {})[name] = fraction
        maps.setdefault(state, []).append(_maps(cal))
        black.setdefault(state, []).append(capture.black)
        if responses[j] is None and cal.response is not None:
            responses[j], ramps[j] = cal.response, cal.ramp
        if cal.response_note is not None:
            unfit.setdefault(j, f"{folder}: {cal.response_note}")
    for j, note in unfit.items():
        if responses[j] is None:
            raise CaptureError(f"projector {projectors[j][0]!r}: no state's ramp captures fit its response; {note}")
    missing = [n for (n, _, _), r in zip(projectors, responses) if r is None]
    if missing:
        warnings.warn(f"no ramp captures for {missing}: solving will assume a linear response there", stacklevel=2)
    return CalibrationBundle(camera_size=(shape[2], shape[1]), channels=shape[0], projectors=projectors,
                             states=maps, black={s: torch.stack(b).mean(0) for s, b in black.items()},
                             responses=responses, decoded=decoded, decoded_lit=decoded_lit, ramps=ramps, bits=shown,
                             homographies=homographies, capture_noise=noise)


def _maps(cal: ProjectorCalibration) -> dict:
    maps = {"prj_xy": cal.prj_xy, "prj_xy_integer": cal.decoding.prj_xy, "valid": cal.decoding.valid,
            "contrast": cal.decoding.contrast.float(), "cam_xy": cal.cam_xy, "count": cal.count}
    if cal.colour_contrast is not None:
        maps["colour_contrast"] = cal.colour_contrast.float()
    if cal.edges is not None:
        maps.update({f"edge_{k}": getattr(cal.edges, k) for k in EDGE_FIELDS})
    if cal.shares is not None:
        maps.update({f"share_{k}": getattr(cal.shares, k) for k in SHARE_FIELDS})
        if cal.shares.checker is not None:
            maps["share_checker"] = cal.shares.checker
        if cal.shares.band is not None:
            maps.update(share_band=cal.shares.band, share_band_white=cal.shares.band_white)
    if cal.dim_xy is not None:
        maps["dim_xy"] = cal.dim_xy
    if cal.blur is not None:
        maps["blur"] = cal.blur.float()
    return maps


EDGE_FIELDS = ("pixel", "xy", "slope", "share")  # EdgePixels' arrays, stored as edge_pixel, edge_xy, ...


def edge_pixels(maps: dict) -> EdgePixels | None:
    """A bundle map's :class:`EdgePixels`, or None where it has none (a shortened sequence, an
    older bundle)."""
    if "edge_pixel" not in maps:
        return None
    return EdgePixels(*(maps[f"edge_{k}"] for k in EDGE_FIELDS))


SHARE_FIELDS = ("cell", "across", "outside")  # CellShares' arrays, stored as share_cell, ...


def cell_shares_of(maps: dict) -> CellShares | None:
    """A bundle map's :class:`CellShares`, or None where it has none (a shortened sequence, an
    older bundle)."""
    if "share_cell" not in maps:
        return None
    return CellShares(*(maps[f"share_{k}"] for k in SHARE_FIELDS), checker=maps.get("share_checker"),
                      band=maps.get("share_band"), band_white=maps.get("share_band_white"))


def _map_stems(names: list[str]) -> list[str]:
    """Each projector's file name (without ``.npz``) in a state folder: its own name, unless the state's
    ``black.npz`` or another projector's file has it, ignoring case as macOS's and Windows' file
    systems do (projectors named ``black``, or ``a`` and ``A``); then the name with ``_1``, ``_2``, ...
    ``bundle.json``'s ``files`` says which file is whose, so that a reader needs no rule."""
    taken, stems = {"black"}, []
    for name in names:
        stem, k = name, 0
        while stem.casefold() in taken:
            k += 1
            stem = f"{name}_{k}"
        taken.add(stem.casefold())
        stems.append(stem)
    return stems


def write_bundle(folder: str | os.PathLike, bundle: CalibrationBundle, procam_calibration=None) -> None:
    """Write a bundle into ``folder`` (module docstring: the format)."""
    check_path(folder, "folder", "the bundle folder")
    check(isinstance(bundle, CalibrationBundle), f"bundle must be a CalibrationBundle (calibrate_folders' or load_bundle's), "
                                                 f"got {type(bundle).__name__}")
    folder = Path(folder)
    files = {}
    stems = _map_stems([name for name, _, _ in bundle.projectors])
    for state, maps in bundle.states.items():
        (folder / state).mkdir(parents=True, exist_ok=True)
        for (name, _, _), stem, m in zip(bundle.projectors, stems, maps):
            np.savez_compressed(folder / state / f"{stem}.npz", **{k: to_numpy(v) for k, v in m.items()})
            files.setdefault(state, {})[name] = f"{state}/{stem}.npz"
        np.savez_compressed(folder / state / "black.npz", black=to_numpy(bundle.black[state]))
    meta = {
        "format": "torchproj calibration bundle", "version": BUNDLE_VERSION,
        "camera": {"size": list(bundle.camera_size), "channels": bundle.channels},
        "projectors": [{"name": n, "size": [w, h]} for n, w, h in bundle.projectors],
        "states": list(bundle.states),
        "responses": [None if r is None else r.as_dict() for r in bundle.responses],
        "ramps": [None if r is None else {"levels": r[0].tolist(), "measured": r[1].tolist()}
                  for r in (bundle.ramps or [None] * len(bundle.projectors))],
        "decoded_fraction": bundle.decoded, "decoded_lit_fraction": bundle.decoded_lit, "files": files,
    }
    full = [graycode_bits(w, h) for _, w, h in bundle.projectors]
    if bundle.bits and [tuple(b) for b in bundle.bits] != full:
        meta["graycode_bits"] = {n: list(b) for (n, _, _), b in zip(bundle.projectors, bundle.bits)}
    if bundle.homographies:
        meta["homographies"] = bundle.homographies
    if procam_calibration is not None:
        shutil.copyfile(procam_calibration, folder / "procam_calibration.xml")
        meta["procam_calibration"] = "procam_calibration.xml"
    (folder / "bundle.json").write_text(json.dumps(meta, indent=2) + "\n")


def load_bundle(folder: str | os.PathLike) -> CalibrationBundle:
    """Read a bundle written by :func:`write_bundle` (or ``torchproj calibrate``).

    Every file is checked as it is read: a :class:`CaptureError` names the file (and the field of
    ``bundle.json``) that is missing, truncated, edited out of shape or physically impossible.
    """
    check_path(folder, "folder", "a bundle folder")
    folder = Path(folder)
    if folder.name == "bundle.json" and folder.is_file():  # the bundle's own file given for its folder
        folder = folder.parent
    path = folder / "bundle.json"
    if not path.is_file():
        raise CaptureError(f"{folder}: not a calibration bundle (no bundle.json); make one with torchproj calibrate")
    meta = read_json(path, "calibrate again")
    if meta.get("version") != BUNDLE_VERSION:
        raise CaptureError(f"{path}: bundle format version {meta.get('version')!r}, this torchproj reads "
                           f"version {BUNDLE_VERSION}; calibrate again")
    try:
        return _bundle_from_meta(folder, meta)
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        if isinstance(exc, CaptureError):
            raise
        what = f"lacks the field {exc}" if isinstance(exc, KeyError) else f"holds a malformed value ({exc})"
        raise CaptureError(f"{path}: {what}; was it edited or cut short? Calibrate again") from None


def read_json(path: Path, fix: str) -> dict:
    """A JSON object from ``path``, or a :class:`CaptureError` that names the file and ``fix``."""
    try:
        meta = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CaptureError(f"{path}: not valid JSON ({exc}); {fix}") from None
    if not isinstance(meta, dict):
        raise CaptureError(f"{path}: expected a JSON object, got {type(meta).__name__}; {fix}")
    return meta


def _bundle_from_meta(folder: Path, meta: dict) -> CalibrationBundle:
    path = folder / "bundle.json"
    width, height = _size(meta["camera"]["size"], f"{path}: camera.size")
    channels = meta["camera"]["channels"]
    if channels not in (1, 3) or isinstance(channels, bool):
        raise CaptureError(f"{path}: camera.channels must be 1 or 3, got {channels!r}; calibrate again")
    projectors = [(str(p["name"]), *_size(p["size"], f"{path}: projectors[{j}].size"))
                  for j, p in enumerate(meta["projectors"])]
    if not projectors or len(projectors) != len(meta["responses"]):
        raise CaptureError(f"{path}: {len(projectors)} projector(s) but {len(meta['responses'])} response(s); "
                           "calibrate again")
    camera = (height, width)
    states, black = {}, {}
    for state in meta["states"]:
        maps = []
        for name, w, h in projectors:
            arrays = _read_npz(folder / meta["files"][state][name], {"prj_xy": (*camera, 2), "valid": camera,
                                                                     "contrast": camera},
                               optional={"colour_contrast": (channels, *camera), "dim_xy": (*camera, 2),
                                         "share_checker": tuple(camera), "blur": tuple(camera)})
            _check_parts(arrays, camera, (w, h), folder / meta["files"][state][name])
            for key in (k for k in ("prj_xy", "dim_xy") if k in arrays):
                xy = arrays[key]
                inside = (xy[..., 0] >= -1) & (xy[..., 0] <= w) & (xy[..., 1] >= -1) & (xy[..., 1] <= h)
                if not (inside | ~torch.isfinite(xy).all(-1)).all():
                    raise CaptureError(f"{folder / meta['files'][state][name]}: {key} holds projector coordinates "
                                       f"outside the {w}x{h} projector that bundle.json names; calibrate again")
            maps.append(arrays)
        states[state] = maps
        black[state] = _read_npz(folder / state / "black.npz", {"black": (channels, *camera)})["black"]
    if not states:
        raise CaptureError(f"{path}: no states; calibrate again")
    responses = [None if r is None else _response(r, f"{path}: responses[{j}]") for j, r in enumerate(meta["responses"])]
    ramps = [None if r is None else _ramp(r, f"{path}: ramps[{j}]", channels)
             for j, r in enumerate(meta.get("ramps", [None] * len(projectors)))]
    xml = meta.get("procam_calibration")
    shown = meta.get("graycode_bits", {})
    return CalibrationBundle(camera_size=(width, height), channels=channels, projectors=projectors, states=states,
                             black=black, responses=responses, decoded=meta.get("decoded_fraction", {}),
                             decoded_lit=meta.get("decoded_lit_fraction", {}), ramps=ramps,
                             procam_calibration=None if xml is None else folder / xml,
                             bits=[tuple(shown.get(n, graycode_bits(w, h))) for n, w, h in projectors],
                             homographies=meta.get("homographies", {}))


def _check_parts(arrays: dict, camera: tuple[int, int], size: tuple[int, int], path: Path) -> None:
    """A projector map's edge pixels and cell shares (all of each one's arrays or none), in the
    bundle's terms."""
    for prefix, fields, read, check_part in (
            ("edge", EDGE_FIELDS, edge_pixels, lambda part: part.check(camera, str(path))),
            ("share", SHARE_FIELDS, cell_shares_of, lambda part: part.check(camera, size, str(path)))):
        names = [f"{prefix}_{k}" for k in fields]
        present = [n for n in names if n in arrays]
        if not present:
            continue
        if len(present) < len(names):
            raise CaptureError(f"{path}: holds {present} but not every {prefix}_* array ({names}); calibrate again")
        try:
            check_part(read(arrays))
        except InputError as exc:
            raise CaptureError(f"{exc}; calibrate again") from None
    blur = arrays.get("blur")
    if blur is not None and bool((torch.isinf(blur) | (blur < 0)).any()):
        raise CaptureError(f"{path}: 'blur' must hold defocus diameters in cells, 0 or more (NaN where unknown); "
                           "calibrate again")


def _size(value, where: str) -> tuple[int, int]:
    """``[width, height]`` of a device, in whole pixels and within :data:`~torchproj.core.checks.SIZE_LIMIT`."""
    if (not isinstance(value, list) or len(value) != 2
            or not all(is_whole(v) and v > 0 for v in value)
            or value[0] * value[1] > SIZE_LIMIT):
        raise CaptureError(f"{where} must be [width, height] in whole pixels (at most {SIZE_LIMIT:.0e} of them), got "
                           f"{value!r}; write or calibrate it again")
    return value[0], value[1]


_MAY_BE_NAN = ("prj_xy", "dim_xy", "share_across", "share_outside", "share_checker", "blur")  # maps that mark unknown pixels with NaN


def _read_npz(path: Path, shapes: dict[str, tuple[int, ...]],
              optional: dict[str, tuple[int, ...]] | None = None) -> dict[str, torch.Tensor]:
    """The arrays of a bundle's ``.npz`` file, each array named in ``shapes`` (and each of ``optional``
    that the file holds) checked: shape, finite where it is not a map that marks undecoded pixels
    with NaN."""
    if not path.is_file():
        raise CaptureError(f"{path}: missing from the bundle; calibrate again")
    try:
        with np.load(path) as data:
            arrays = {k: torch.from_numpy(data[k]) for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise CaptureError(f"{path}: unreadable ({type(exc).__name__}: truncated or not a .npz file); "
                           "calibrate again") from None
    shapes = {**shapes, **{k: v for k, v in (optional or {}).items() if k in arrays}}
    for key, shape in shapes.items():
        if key not in arrays:
            raise CaptureError(f"{path}: lacks the array {key!r}; calibrate again")
        if tuple(arrays[key].shape) != shape:
            raise CaptureError(f"{path}: {key!r} has shape {tuple(arrays[key].shape)}, but bundle.json's camera "
                               f"needs {shape}; calibrate again")
        if key not in _MAY_BE_NAN and arrays[key].is_floating_point() and not torch.isfinite(arrays[key]).all():
            raise CaptureError(f"{path}: {key!r} holds NaN or infinite values; calibrate again")
    return arrays


def _ramp(values: dict, where: str, channels: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A bundle's measured ramp: levels :math:`(L,)` and the light measured at each :math:`(L, C)`."""
    try:
        levels, measured = torch.tensor(values["levels"]), torch.tensor(values["measured"])
    except (RuntimeError, TypeError, ValueError):
        levels = measured = None
    if (levels is None or levels.ndim != 1 or tuple(measured.shape) != (len(levels), channels)
            or not (torch.isfinite(levels).all() and torch.isfinite(measured).all())):
        raise CaptureError(f"{where}: levels must be L finite numbers and measured L rows of {channels}; "
                           "calibrate again")
    return levels, measured


def _response(values: dict, where: str) -> ResponseCurve:
    """A bundle's response curve, refused where no projector could have it (``a x^b + c`` must rise,
    a colour mixing must be a 3 x 3 of shares that a camera can tell apart)."""
    try:
        a, b, c = (torch.tensor(values[k], dtype=torch.float32).reshape(-1) for k in ("a", "b", "c"))
    except (RuntimeError, TypeError, ValueError):
        a = b = c = torch.zeros(0)
    if not all(len(t) in (1, 3) and torch.isfinite(t).all() for t in (a, b, c)):
        raise CaptureError(f"{where}: a, b and c must be 1 or 3 finite numbers each, got {values}; calibrate again")
    if not ((a > 0).all() and (b > 0).all()):
        raise CaptureError(f"{where}: y = a x^b + c needs a > 0 and b > 0 (a projector's light rises with its "
                           f"input), got a={a.tolist()}, b={b.tolist()}; was it edited? Calibrate again")
    mixing = values.get("mixing")
    if mixing is not None:
        try:
            mixing = torch.tensor(mixing, dtype=torch.float32)
        except (RuntimeError, TypeError, ValueError):
            mixing = torch.zeros(0)
        if not tells_primaries_apart(mixing):
            raise CaptureError(f"{where}: mixing must be 3 rows of 3 shares >= 0 that tell the primaries apart, got "
                               f"{values.get('mixing')}; was it edited? Calibrate again")
    return ResponseCurve(a, b, c, mixing)
