"""From one capture folder's images to everything calibration knows about one projector."""

from __future__ import annotations

import os
import time
import warnings
from dataclasses import dataclass, replace

import torch

from ..core.checks import check, check_count, check_number, is_number
from ..core.conventions import to_numpy
from ..core.errors import CaptureError, InputError
from .capture import GraycodeCapture
from .graycode import (CREASE_RATIO, CURVE_RATIO, WIDE_SHARE, CellShares, GrayDecoding, _check_threshold, _refine_again, band_pixels, capture_noise, cell_shares, checker_shares,
                       check_projector_size, check_ratio, decode_gray, graycode_bits, refine_subpixel, sequence_bits, stripe_contrast,
                       stripe_shares)
from .homography import HomographyFit, check_plane, fit_homography, homography_map
from .maps import depth_edges, fill_holes, inverse_map, map_slope
from .blur import measure_blur
from .edges import EdgePixels, find_edge_pixels
from .response import RAMP_STEPS, ResponseCurve, fit_colour_mixing, fit_response, measure_ramp

__all__ = ["DIM_THRESHOLD", "FEW_DECODED", "NOISY_CAPTURES", "SATURATED", "SATURATED_SHARE", "DecodedFolder",
           "ProjectorCalibration", "calibrate_projector", "decode_folder", "scan_map", "warn_if_few_decoded", "warn_if_noisy",
           "warn_if_saturated"]

# Below this share of its lit pixels decoded, a projector's calibration is warned about (measured on
# the shipped scenes: docs/commands.md, "Bad inputs and odd captures").
FEW_DECODED = 0.7

# White minus black (8-bit units) down to which a projector's code is still read where it lights a
# pixel too dimly for the shadow threshold (OpenCV's 40): grazing light, the limb of a curved object.
# Such a pixel is no target pixel of its own, but where another projector lights it, this one's light
# there belongs in its row (StateCalibration.dim). Our choice, not the paper's (docs/accuracy.md, "The ceiling",
# measures it against none; other values are not benchmarked).
from ..core.choices import BLACK_THRESHOLD, DIM_THRESHOLD  # noqa: E402  (40 and 10; there, for the command's parser)


# A camera value at or above this (of 1) is clipped: 255 of 255, and the mean of frames most of which
# were (camera.frames, capture --frames).
SATURATED = 254.5 / 255
# Past this share of its lit pixels whose white capture is clipped, a projector's calibration is warned
# about. The paper's rig at 200x150 / 128x96 (tests/pipeline/test_virtual.py's), `torchproj run` at
# camera.exposure 1, 2.8 and 3.6: the near state's white clipped at 0 and 0, 82 and 28, 98 and 98% of
# its two projectors' lit pixels, and the far target at 17.4, 17.0 and 14.1 dB, the near one unharmed.
# The real chessboard captures clip 0.03% (capture_0).
SATURATED_SHARE = 0.05


def _check_share(value, name: str) -> None:
    """A share a calibration measured (NaN where nothing was lit to measure it), or None."""
    check(value is None or is_number(value), f"{name} must be a share (a number) or None, got {value!r}")


def warn_if_saturated(saturated: float | None, where: str, fix: str = "lower the camera's exposure (or the "
                      "projector's brightness) and capture again") -> None:
    """Warn, naming ``where`` and the ``fix``, when more than :data:`SATURATED_SHARE` of the lit pixels'
    white capture is clipped (:attr:`ProjectorCalibration.saturated`)."""
    _check_share(saturated, "saturated")
    if saturated is not None and saturated > SATURATED_SHARE:
        warnings.warn(f"{where}: the white capture is clipped at {saturated:.0%} of the pixels the projector "
                      f"lights (over {SATURATED_SHARE:.0%}): there every row's weight (white minus black) and the "
                      f"ramp the response is fitted to read less light than the projector gives. {fix}",
                      stacklevel=3)


# Past this camera noise of white minus black (capture_noise: median share over the lit pixels) a
# projector's calibration is warned about. A single frame reads at most 2.6% on the shipped scenes and
# the suite scenes of seeds 1 and 2412 (suite-1-4, as `torchproj simulate` tabulates it) and 2.4-2.5%
# on the real chessboard captures; a pattern image in every other pair 15% darker (an exposure that
# changed while capturing) reads 6.6% and a camera with a full well of 20 electrons 40%
# (tests/calib/test_pipeline.py). Clipped whites read high too, and are said as such instead.
NOISY_CAPTURES = 0.05


def warn_if_noisy(noise: float | None, saturated: float | None, where: str, frames: str) -> None:
    """Warn, naming ``where`` and how to average ``frames``, when the captures' noise
    (:attr:`ProjectorCalibration.capture_noise`) passes :data:`NOISY_CAPTURES`, unless clipped whites
    (:func:`warn_if_saturated`) explain it."""
    _check_share(noise, "noise")
    _check_share(saturated, "saturated")
    if noise is None or not noise > NOISY_CAPTURES or (saturated is not None and saturated > SATURATED_SHARE):
        return
    warnings.warn(f"{where}: the captures' noise is {noise:.1%} of white minus black (over {NOISY_CAPTURES:.0%}; how "
                  "far each pattern plus its inverse strays from the others' sum), and every row's weight, map and "
                  f"share carry it. Average frames ({frames}: the noise falls as the square root of their number), "
                  "and keep the camera's exposure and the room's light fixed while capturing", stacklevel=3)


def warn_if_few_decoded(decoding: GrayDecoding, where: str) -> float:
    """Warn, naming ``where`` and the likely causes, when few of the lit pixels decoded; returns the share."""
    check(isinstance(decoding, GrayDecoding), f"decoding must be decode_gray's GrayDecoding, got {type(decoding).__name__}")
    share = decoding.lit_located_fraction
    if share < FEW_DECODED:
        warnings.warn(f"{where}: only {share:.0%} of the pixels the projector lights decoded, fully or partly (under "
                      f"{FEW_DECODED:.0%}); the others take no part in the solve. Likely causes: Gray-code stripes "
                      "finer than the camera resolves (steep or distant surfaces), shadows and grazing light, or a "
                      "projector size that does not match the captures. Try fewer bits (--bits with --maps "
                      "homography on planes), a closer camera or more camera supersampling", stacklevel=3)
    return share


@dataclass
class ProjectorCalibration:
    """Calibration of one projector in one scene state.

    Attributes:
        decoding: the raw Gray-code decoding (integer cells, OpenCV semantics).
        prj_xy: :math:`(H, W, 2)` projector coordinates per camera pixel: sub-pixel refined
            (if asked) and with small holes filled; NaN where unknown.
        cam_xy: :math:`(H_p, W_p, 2)` inverse map, camera coordinates per projector cell,
            small holes filled; NaN where unknown.
        count: :math:`(H_p, W_p)` camera pixels that decoded to each cell (before filling).
        response: fitted response curve, if the capture held a ramp (and, with
            ``require_response=False``, it showed enough levels).
        ramp: ``(levels (L,), measured (L, C))``, the points the curve was fitted to, or None.
        response_note: why a ramp the capture held gave no response (too few of its bars seen),
            with ``require_response=False``; else None.
        timings_s: seconds spent in each step.
        homography: for a shortened sequence, the homography ``prj_xy`` comes from; else None.
        colour_contrast: for a colour camera, :math:`(C, H, W)` white minus black per camera
            channel (the decoding's ``contrast`` is their mean); None for a grey one. A tinted
            surface or projectors of different white balance make the channels differ.
        edges: the pixels beside depth edges and the lit ones the map misses, each on one or two
            surfaces (:func:`find_edge_pixels`), from a full sequence; None for a shortened one (its
            map is one plane).
        shares: how each decoded pixel's light is shared across the edges of its cell
            (:func:`~torchproj.calib.cell_shares`): the decoded cell of a fully decoded pixel, the
            nearest cell of its fitted map for a partly decoded one, with the checkerboard pair's
            share (:attr:`~torchproj.calib.CellShares.checker`) where the capture holds one; from a
            full sequence; None for a shortened one.
        dim_xy: :math:`(H, W, 2)` projector coordinates of the pixels the projector lights too
            dimly to count as lit (white minus black between the dim and the shadow threshold,
            :data:`DIM_THRESHOLD`) whose code still reads, refined and filled as ``prj_xy``; NaN
            elsewhere (and wherever ``prj_xy`` is known). From a full sequence; None for a shortened one.
        capture_noise: the camera noise of a pixel's white minus black, as a share of it (median
            over the lit pixels, :func:`~torchproj.calib.capture_noise`): what every row's weight,
            and the map and the shares, carry from one frame a capture; None for fewer than two
            pattern pairs.
        saturated: the share of the lit pixels whose white capture is clipped in any channel
            (:data:`SATURATED`): light the camera cannot count, so that white minus black, and the
            ramp, read low there (:func:`warn_if_saturated`).
        blur: :math:`(H, W)` the projector's defocus disc at each pixel, diameter in cells
            (:func:`~torchproj.calib.measure_blur` on the finest stripes; NaN where it could not
            tell), which the ``area`` footprint spreads rows over where it is a cell or wider. From
            a full sequence; None for a shortened one.
    """

    decoding: GrayDecoding
    prj_xy: torch.Tensor
    cam_xy: torch.Tensor
    count: torch.Tensor
    response: ResponseCurve | None
    ramp: tuple[torch.Tensor, torch.Tensor] | None
    timings_s: dict
    homography: HomographyFit | None = None
    colour_contrast: torch.Tensor | None = None
    edges: EdgePixels | None = None
    shares: CellShares | None = None
    dim_xy: torch.Tensor | None = None
    blur: torch.Tensor | None = None
    response_note: str | None = None
    capture_noise: float | None = None
    saturated: float | None = None


def calibrate_projector(capture: GraycodeCapture, projector_size: tuple[int, int], *, white_threshold: float = 5,
                        black_threshold: float = BLACK_THRESHOLD, dim_threshold: float = DIM_THRESHOLD, subpixel: bool = True,
                        max_hole: int = 16, ramp_steps: int = RAMP_STEPS, bits: int | tuple[int, int] | None = None,
                        plane_tolerance: float = 1.0, crease_ratio: float = CREASE_RATIO,
                        curve_ratio: float = CURVE_RATIO, require_response: bool = True) -> ProjectorCalibration:
    """Decode, refine, fill, invert and fit the response of one capture.

    A shortened sequence (``bits``) decodes to blocks of cells only. Its map is then one
    homography fitted to the blocks (:mod:`torchproj.calib.homography`), which needs the scene
    this projector lights to be one plane: a map that is not is refused.

    Args:
        capture: the images (:func:`~torchproj.calib.read_graycode_folder` or the virtual rig).
        projector_size: ``(width, height)``.
        white_threshold, black_threshold: decoder thresholds, 8-bit units (OpenCV's defaults).
        dim_threshold: with a full sequence, read the code down to this white minus black (8-bit
            units) too, into ``dim_xy`` (:data:`DIM_THRESHOLD`); at or above ``black_threshold``: none.
        subpixel: refine coordinates by the local affine fit (:func:`refine_subpixel`) over the mean
            cell of each pixel's light (:func:`~torchproj.calib.cell_means`), then once more with the
            partly decoded pixels' means about the first fit's nearest cell; False: the decoded cells.
        max_hole: largest hole (pixels) filled in the forward and inverse maps; 0 disables.
        ramp_steps: bars in the ramp pattern, when the capture holds one.
        bits: pattern pairs per axis the capture holds (:func:`~torchproj.calib.sequence_bits`);
            None: the full sequence.
        plane_tolerance: with a shortened sequence, the largest 95th-percentile residual
            (projector pixels, :func:`~torchproj.calib.fit_homography`) that counts as a plane.
        crease_ratio: how much better a refining window beside a pixel must fit than the centred one
            (:func:`refine_subpixel`); ``math.inf``: the centred window only.
        curve_ratio: how much better the centred window's quadratic must fit than its plane
            (:func:`refine_subpixel`); ``math.inf``: planes only.
        require_response: refuse a ramp whose bars the camera sees too few of to fit a response
            (an object that covers a few of the 32 bars). False: give no response and say why
            (``response_note``), for a rig whose other states' ramps fit this projector's response.
    """
    check_calibration_options(dict(ramp_steps=ramp_steps))  # the others where the map is made
    m = _forward_map(capture, projector_size, white_threshold=white_threshold, black_threshold=black_threshold,
                     dim_threshold=dim_threshold, subpixel=subpixel, max_hole=max_hole, bits=bits,
                     plane_tolerance=plane_tolerance, crease_ratio=crease_ratio, curve_ratio=curve_ratio)
    dec, fit, shares, prj_xy, dim_xy, timings = m.decoding, m.homography, m.shares, m.prj_xy, m.dim_xy, m.timings_s
    t0 = time.perf_counter()
    cam_xy, count = inverse_map(prj_xy, projector_size)
    if max_hole:
        cam_xy = fill_holes(cam_xy, max_hole)
    timings["maps"] += time.perf_counter() - t0
    edges = blur = None
    if fit is None:
        t0 = time.perf_counter()
        # The edges read the map with its dim pixels, the blur without: one slope serves both, computed
        # again only near the dim pixels (map_slope's like=).
        merged = torch.where(torch.isfinite(prj_xy), prj_xy, dim_xy)
        merged_slope, merged_depth = map_slope(merged), depth_edges(merged)  # the band reads the same edges
        edges = find_edge_pixels(capture.patterns, capture.white, capture.black, merged, projector_size,
                                 slope=merged_slope, depth=merged_depth)
        timings["edges"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        # A lens focused elsewhere spreads each cell over a disc; the finest stripes show how wide.
        # Blur follows depth, smooth on a surface: about 1,500 samples per map are read, every 8th
        # pixel each way at most (0.2 s a full-size map, most of it choosing each pixel's neighbours
        # on its own surface).
        height, width = prj_xy.shape[:2]
        blur = measure_blur(capture.patterns, capture.white, capture.black, prj_xy, projector_size,
                            step=max(8, round((height * width / 1500) ** 0.5)),
                            slope=map_slope(prj_xy, like=(merged, merged_slope)))
        timings["blur"] = time.perf_counter() - t0
    response = ramp = note = None
    if capture.ramp is not None:
        t0 = time.perf_counter()
        # Ramp bars are told apart by projector column: the decoded cell, or the fitted coordinate
        # where blocks are wider than a bar.
        columns = dec.prj_xy[..., 0] if fit is None else prj_xy[..., 0]
        try:
            levels, measured = measure_ramp(capture.ramp[0], capture.white, capture.black, columns,
                                            projector_size[0], ramp_steps,
                                            mirrored=capture.ramp[1] if len(capture.ramp) > 1 else None)
        except InputError as exc:
            if require_response:
                raise
            note = str(exc)
        else:
            mixing = None
            if capture.primaries is not None and capture.white.shape[0] == 3:
                mixing = fit_colour_mixing(capture.primaries, capture.white, capture.black, dec.valid)
                # Channel c saw sum_p mixing[c, p] r_p(x) of the grey ramp: the primaries' own curves
                # are the measured levels through the mixing's inverse.
                measured = measured @ torch.linalg.inv(mixing.double()).T.to(measured)
            response = fit_response(levels, measured, normalised=True)
            response.mixing = mixing
            ramp = (levels, measured)
            timings["response"] = time.perf_counter() - t0
    colour = (capture.white - capture.black).float() if capture.white.dim() == 3 and capture.white.shape[0] > 1 else None
    if shares is not None:
        # Every transport row is weighted by white minus black; the pairs whose stripes hold a pixel's
        # footprint are further frames of both (stripe_contrast): their mean has a half to a quarter
        # of the noise, from captures already taken.
        t0 = time.perf_counter()
        span = stripe_contrast(capture.patterns, capture.white, capture.black, shares.cell, projector_size)
        dec = replace(dec, contrast=span.mean(0))
        colour = span if colour is not None else None
        # Beside outlines (and on the edge pixels, mapped or not) a pixel's light falls where no
        # parallelogram about its coordinate puts it; every pair's share there is kept for the rows
        # to be fitted to (CellShares.band_white).
        band = torch.unique(torch.cat([band_pixels(merged, depth=merged_depth), edges.pixel.to(torch.int64)]))  # sorted
        shares = replace(shares, band=band, band_white=stripe_shares(capture.patterns, dec.contrast, band,
                                                                     graycode_bits(*projector_size)))
        timings["stripes"] = time.perf_counter() - t0
    noise = capture_noise(capture.patterns, capture.white, capture.black) if capture.patterns.shape[0] >= 4 else None
    # The white capture is the brightest the projector makes a pixel: where it is clipped, so is every
    # pattern and ramp level near full light.
    clipped = (capture.white.amax(0) >= SATURATED) & dec.valid
    saturated = float(clipped.sum()) / max(int(dec.valid.sum()), 1)
    return ProjectorCalibration(decoding=dec, prj_xy=prj_xy, cam_xy=cam_xy, count=count, response=response,
                                ramp=ramp, timings_s=timings, homography=fit, colour_contrast=colour,
                                edges=edges, shares=shares, dim_xy=dim_xy, blur=blur, response_note=note,
                                capture_noise=noise, saturated=saturated)


@dataclass
class _ForwardMap:
    """The first half of :func:`calibrate_projector`: the decoding and the refined, filled forward map."""

    decoding: GrayDecoding
    homography: HomographyFit | None
    shares: CellShares | None
    prj_xy: torch.Tensor
    dim_xy: torch.Tensor | None
    timings_s: dict


def check_calibration_options(options: dict) -> None:
    """The numbers among :func:`calibrate_projector`'s ``options`` (by name), checked before any capture
    is read or decoded. Each is read late, some only in some sequences (the plane tolerance only in a
    shortened one), and a NaN shadow threshold was not read at all."""
    checks = {
        "white_threshold": lambda v: _check_threshold(v, "white_threshold"),
        "black_threshold": lambda v: _check_threshold(v, "black_threshold"),
        # At or above the shadow threshold (inf too), no dim pixel is read.
        "dim_threshold": lambda v: check(is_number(v) and v >= 0,
                                         f"dim_threshold must be >= 0 (8-bit units), got {v!r}"),
        "max_hole": lambda v: check_count(v, "max_hole (--fill-holes, the largest hole filled, pixels)", 0),
        "ramp_steps": lambda v: check_count(v, "ramp_steps (--ramp-steps, the ramp's bars)", 2),
        "plane_tolerance": lambda v: check_number(v, "plane_tolerance (projector pixels)", 0, strict=True),
        "crease_ratio": lambda v: check_ratio(v, "crease_ratio", "1: the best-fitting window"),
        "curve_ratio": lambda v: check_ratio(v, "curve_ratio", "1: the better-fitting of plane and quadratic"),
    }
    for name, value in options.items():
        if name in checks:
            checks[name](value)


def _forward_map(capture: GraycodeCapture, projector_size: tuple[int, int], *, white_threshold: float,
                 black_threshold: float, dim_threshold: float, subpixel: bool, max_hole: int,
                 bits: int | tuple[int, int] | None, plane_tolerance: float, crease_ratio: float,
                 curve_ratio: float = CURVE_RATIO) -> _ForwardMap:
    check(isinstance(capture, GraycodeCapture), f"capture must be a GraycodeCapture (read_graycode_folder's), got "
                                                f"{type(capture).__name__}")
    projector_size = check_projector_size(projector_size)
    check_calibration_options(dict(white_threshold=white_threshold, black_threshold=black_threshold,
                                   dim_threshold=dim_threshold, max_hole=max_hole, plane_tolerance=plane_tolerance,
                                   crease_ratio=crease_ratio, curve_ratio=curve_ratio))
    timings = {}
    t0 = time.perf_counter()
    full = sequence_bits(*projector_size, bits) == graycode_bits(*projector_size)
    # One decoding down to the dim threshold; the lit pixels' is the same with the shadow threshold.
    seen = decode_gray(capture.patterns, capture.white, capture.black, projector_size, white_threshold=white_threshold,
                       black_threshold=min(dim_threshold, black_threshold) if full else black_threshold, bits=bits)
    dec = seen.above(black_threshold) if full and dim_threshold < black_threshold else seen
    timings["decode"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    fit = shares = dim_xy = None
    if dec.block != (1, 1):
        fit = fit_homography(dec.prj_xy, block=dec.block)
        check_plane(fit, plane_tolerance, f"a {dec.block[0]}x{dec.block[1]}-cell Gray-code block map",
                    "use the full Gray-code sequence (no --bits) for a scene that is not one plane")
        # The fitted map covers the decoded pixels and the small holes between them.
        covered = dec.prj_xy.clone()
        if max_hole:
            covered = fill_holes(covered, max_hole)
        prj_xy = homography_map(fit.matrix, torch.isfinite(covered).all(-1), projector_size)
    else:
        # Partly decoded pixels join the fit: their open cells' centre is within half a block of the
        # truth, and the fit over their neighbours places them between the cells. Dim pixels join it
        # too (more neighbours on the same surface); the lit ones' map is then filled on its own, as
        # without them.
        shares = cell_shares(capture.patterns, capture.white, capture.black, seen, projector_size)
        if subpixel:
            coarse = torch.where(seen.valid[..., None], shares.means(), seen.coarse_xy)
            mapped = refine_subpixel(coarse, seen.valid | seen.partial, spread=seen.spread, crease_ratio=crease_ratio,
                                     curve_ratio=curve_ratio)
        else:
            mapped = seen.coarse_xy.clone()
        shares, sharp = _partial_shares(capture, seen, shares, mapped, projector_size)
        if capture.checker is not None:
            shares = replace(shares, checker=checker_shares(capture.checker, capture.white, capture.black, shares.cell))
        if subpixel and bool(sharp.any()):
            # Their means place them between cells where the open cells' centre leaves them half a
            # block off; a second fit over them takes box_positions' faces from 0.020 to 0.016 cells
            # rms, the fully decoded pixels' too (their windows hold partly decoded ones). A third
            # fit leaves the faces' error where it is (within 0.0001 cells rms): docs/accuracy.md "The ceiling".
            coarse = torch.where(sharp[..., None], shares.means(), coarse)
            mapped = _refine_again(coarse, seen.valid | seen.partial, mapped, sharp,
                                   torch.where(sharp[..., None], 1, seen.spread), crease_ratio, curve_ratio)
        prj_xy = torch.where((dec.valid | dec.partial)[..., None], mapped, float("nan"))
        if max_hole:
            prj_xy, mapped = fill_holes(prj_xy, max_hole), fill_holes(mapped, max_hole)
        dim_xy = torch.where(torch.isfinite(prj_xy).all(-1, keepdim=True), float("nan"), mapped)
    timings["maps"] = time.perf_counter() - t0
    return _ForwardMap(dec, fit, shares, prj_xy, dim_xy, timings)


def scan_map(capture: GraycodeCapture, projector_size: tuple[int, int], *, white_threshold: float = 5,
             black_threshold: float = BLACK_THRESHOLD, dim_threshold: float = DIM_THRESHOLD, subpixel: bool = True,
             max_hole: int = 16, crease_ratio: float = CREASE_RATIO) -> torch.Tensor:
    """:math:`(H, W, 2)` projector coordinates per camera pixel from a full Gray-code capture, NaN where
    unknown: :func:`calibrate_projector`'s ``prj_xy`` (the same decoding, refinement and filling, the
    same arguments), without what only a transport needs (inverse map, edge pixels, defocus, response,
    stripe contrast), which costs a scan about a third of its decoding time. What a 3D scan
    triangulates (:func:`~torchproj.calib.triangulate`)."""
    return _forward_map(capture, projector_size, white_threshold=white_threshold, black_threshold=black_threshold,
                        dim_threshold=dim_threshold, subpixel=subpixel, max_hole=max_hole, bits=None,
                        plane_tolerance=1.0, crease_ratio=crease_ratio).prj_xy


def _partial_shares(capture: GraycodeCapture, seen: GrayDecoding, shares: CellShares, mapped: torch.Tensor,
                    projector_size: tuple[int, int]) -> tuple[CellShares, torch.Tensor]:
    """``shares`` measured again with the partly decoded pixels' added, about the nearest cell of
    ``mapped`` (their fitted coordinate), and which of those pixels' light stays within a cell of it
    on both axes.

    The decoder could not read such a pixel's finest bits because its footprint straddles their
    stripes; the same captures measure how it straddles them (:func:`cell_shares`), so the ``area``
    footprint can fit its row as it does a fully decoded pixel's. Where light reaches past the
    cell's neighbours (over :data:`~torchproj.calib.graycode.WIDE_SHARE`: defocus), the two edges'
    shares lean towards the cell, and on ``paper_defocus``' blurred plane their means placed the map
    further from the truth than the open cells' centre: only the other pixels' means are fitted.
    """
    size = torch.tensor(projector_size, device=mapped.device)
    near = torch.nan_to_num(mapped, nan=-1.0).round()
    open_cells = seen.partial & ~seen.valid & ((near >= 0) & (near < size)).all(-1)
    # Only those pixels are measured (a few hundred on the default scene); the fully decoded ones
    # keep the shares they have.
    added = cell_shares(capture.patterns, capture.white, capture.black, seen, projector_size,
                        cells=torch.where(open_cells[..., None], near.to(torch.int32), -1))
    merged = CellShares(torch.where(open_cells[..., None], added.cell, shares.cell),
                        torch.where(open_cells[..., None, None], added.across, shares.across),
                        torch.where(open_cells[..., None], added.outside, shares.outside))
    return merged, open_cells & (merged.outside <= WIDE_SHARE).all(-1)


@dataclass
class DecodedFolder:
    """A folder of Gray-code captures decoded (``torchproj decode``): what it found and how fast.

    Attributes:
        calibration: the :class:`ProjectorCalibration` of the folder.
        report: what ``report.json`` holds (decoded fraction, timings, thresholds, ...).
        points: :math:`(H, W, 3)` triangulated points in the camera frame (NaN where not decoded),
            with a camera-projector calibration; else None.
        white: :math:`(C, H, W)` the all-white capture (colours the point cloud).
    """

    calibration: ProjectorCalibration
    report: dict
    points: torch.Tensor | None
    white: torch.Tensor

    def summary(self) -> str:
        """One line: the fraction of the camera decoded, how fast, and the points triangulated."""
        r = self.report
        return (f"decoded {r['valid_fraction']:.1%} of {r['camera'][0]}x{r['camera'][1]} camera pixels in "
                f"{r['decode_s']:.3f} s (reading {r['read_s']:.2f} s)" + (f"; {r['points']} points" if "points" in r
                                                                          else ""))

    def write(self, folder) -> None:
        """``correspondence.npz``, ``report.json``, ``decoded.png`` and (with points) ``points.ply``.

        ``correspondence.npz``: ``prj_xy`` (integer cells, OpenCV's semantics, NaN where invalid),
        ``prj_xy_refined`` (sub-pixel, holes filled), ``valid``, ``contrast``, ``cam_xy``, ``count``
        and, with points, ``points``.
        """
        from pathlib import Path

        import numpy as np

        from ..core.output import write_json
        from ..figures import decode_summary
        from .triangulate import write_ply

        folder, cal = Path(folder), self.calibration
        dec = cal.decoding
        arrays = {"prj_xy": to_numpy(dec.prj_xy).astype(np.float32), "prj_xy_refined": to_numpy(cal.prj_xy),
                  "valid": to_numpy(dec.valid), "contrast": to_numpy(dec.contrast).astype(np.float32),
                  "cam_xy": to_numpy(cal.cam_xy), "count": to_numpy(cal.count).astype(np.int32)}
        if self.points is not None:
            ok = torch.isfinite(self.points).all(-1)
            arrays["points"] = to_numpy(self.points)
            grey = to_numpy((self.white.mean(0)[ok] * 255).clamp(0, 255).to(torch.uint8))
            write_ply(folder / "points.ply", to_numpy(self.points[ok]), np.repeat(grey[:, None], 3, 1))
        np.savez_compressed(folder / "correspondence.npz", **arrays)
        write_json(folder / "report.json", self.report)
        decode_summary(folder / "decoded.png", dec.prj_xy, dec.contrast, self.points,
                       title=f"Fig. 1: {self.report['capture_dir']}: {dec.valid_fraction:.1%} of the camera decoded")


MIN_DECODED = 0.001  # below this fraction of the camera decoded, a capture folder is an error
FEW_DECODED_CAMERA = 0.02  # below this, a warning


def check_decoded(decoding, folder) -> float:
    """The fraction of the camera a folder's captures decoded; an error naming the folder below
    :data:`MIN_DECODED` (identical, saturated or unlit captures decode nothing), a warning below
    :data:`FEW_DECODED_CAMERA`."""
    fraction = decoding.valid_fraction
    if fraction < MIN_DECODED:
        raise CaptureError(f"{folder}: only {fraction:.3%} of the camera decoded; is the projector aimed at the scene, "
                           "in focus, and bright enough against room light (identical or saturated captures decode "
                           "nothing)? Capture again")
    if fraction < FEW_DECODED_CAMERA:
        warnings.warn(f"{folder}: only {fraction:.1%} of the camera decoded; targets there will be small", stacklevel=3)
    return fraction


def decode_folder(capture_dir, projector: tuple[int, int] | None = None, *, calibration=None, names: str | None = None,
                  white_threshold: float = 5, black_threshold: float = BLACK_THRESHOLD, subpixel: bool = True,
                  fill_holes: int = 16, bits: int | None = None, plane_tolerance: float = 1.0) -> DecodedFolder:
    """Decode a folder of Gray-code captures and, with a camera-projector calibration, triangulate it.

    Args:
        capture_dir: the folder (:func:`~torchproj.calib.read_graycode_folder`'s layout).
        projector: ``(width, height)`` of the projector that showed the sequence; None: the folder's
            ``sequence.json`` (``torchproj sequence`` and ``capture`` write it) says it, and its bits.
        calibration: an OpenCV camera-projector calibration file (XML/YAML) to triangulate with.
        names: file name template (default ``graycode_{:02d}.png``).
        white_threshold, black_threshold, subpixel, fill_holes, bits, plane_tolerance: as
            :func:`calibrate_projector` (``fill_holes`` is its ``max_hole``).
    """
    from pathlib import Path

    from .bundle import folder_sequence
    from .capture import DEFAULT_NAMES, read_graycode_folder
    from .triangulate import read_opencv_calibration, triangulate_map

    # A folder that is missing, or no path at all, is named by the reader below.
    said = folder_sequence(Path(capture_dir)) if isinstance(capture_dir, (str, os.PathLike)) else None
    if said is not None:  # what the folder was shown; an option that says otherwise contradicts it
        (width, height), shown = said
        check(projector is None or (isinstance(projector, (tuple, list)) and tuple(projector) == said[0]),
              f"{capture_dir}: its sequence.json says the projector is {width}x{height}, and it was given as "
              f"{projector!r}: leave the size out (--projector) to take the folder's")
        check(bits is None or sequence_bits(width, height, bits) == shown,
              f"{capture_dir}: its sequence.json says {list(shown)} Gray-code pattern pairs per axis, and bits "
              f"{bits!r} were given: leave --bits out to take the folder's")
        projector, bits = said
    if projector is None:
        found = isinstance(capture_dir, (str, os.PathLike)) and Path(capture_dir).is_dir()
        raise CaptureError(f"{capture_dir}: no sequence.json says the projector's size; give it (--projector WxH)"
                           if found else f"{capture_dir}: capture folder not found")
    procam = read_opencv_calibration(calibration) if calibration is not None else None
    t0 = time.perf_counter()
    capture = read_graycode_folder(capture_dir, projector, names=DEFAULT_NAMES if names is None else names, bits=bits)
    t_read = time.perf_counter() - t0
    cal = calibrate_projector(capture, projector, white_threshold=white_threshold, black_threshold=black_threshold,
                              subpixel=subpixel, max_hole=fill_holes, bits=bits, plane_tolerance=plane_tolerance)
    dec = cal.decoding
    check_decoded(dec, capture_dir)
    report = {"capture_dir": str(capture_dir), "projector": list(projector),
              "camera": [int(dec.valid.shape[1]), int(dec.valid.shape[0])],
              "valid_fraction": dec.valid_fraction, "read_s": round(t_read, 4),
              "decode_s": round(cal.timings_s["decode"], 4), "maps_s": round(cal.timings_s["maps"], 4),
              "white_threshold": white_threshold, "black_threshold": black_threshold,
              "subpixel": subpixel, "block_cells": list(dec.block)}
    if cal.homography is not None:
        report["homography"] = cal.homography.as_dict()
    points = None
    if procam is not None:
        t0 = time.perf_counter()
        points = triangulate_map(cal.prj_xy, procam)
        report["triangulate_s"] = round(time.perf_counter() - t0, 4)
        report["points"] = int(torch.isfinite(points).all(-1).sum())
    return DecodedFolder(calibration=cal, report=report, points=points, white=capture.white)
