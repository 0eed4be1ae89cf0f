"""From one capture folder's images to everything calibration knows about one projector."""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from ..core.checks import check
from .capture import GraycodeCapture
from .graycode import GrayDecoding, decode_gray, refine_subpixel
from .maps import fill_holes, inverse_map
from .response import ResponseCurve, fit_response, measure_ramp

__all__ = ["ProjectorCalibration", "calibrate_projector"]


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
        response: fitted response curve, if the capture held a ramp.
        ramp: ``(levels (L,), measured (L, C))``, the points the curve was fitted to, or None.
        timings_s: seconds spent in each step.
    """

    decoding: GrayDecoding
    prj_xy: torch.Tensor
    cam_xy: torch.Tensor
    count: torch.Tensor
    response: ResponseCurve | None
    ramp: tuple[torch.Tensor, torch.Tensor] | None
    timings_s: dict


def calibrate_projector(capture: GraycodeCapture, projector_size: tuple[int, int], *, white_threshold: float = 5,
                        black_threshold: float = 40, subpixel: bool = True, max_hole: int = 16,
                        ramp_steps: int = 32) -> ProjectorCalibration:
    """Decode, refine, fill, invert and fit the response of one capture.

    Args:
        capture: the images (:func:`~torchproj.calib.read_graycode_folder` or the virtual rig).
        projector_size: ``(width, height)``.
        white_threshold, black_threshold: decoder thresholds, 8-bit units (OpenCV's defaults).
        subpixel: refine coordinates by the local affine fit (:func:`refine_subpixel`).
        max_hole: largest hole (pixels) filled in the forward and inverse maps; 0 disables.
        ramp_steps: bars in the ramp pattern, when the capture holds one.
    """
    check(max_hole >= 0, f"max_hole must be >= 0, got {max_hole}")
    timings = {}
    t0 = time.perf_counter()
    dec = decode_gray(capture.patterns, capture.white, capture.black, projector_size,
                      white_threshold=white_threshold, black_threshold=black_threshold)
    timings["decode"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    prj_xy = refine_subpixel(dec.prj_xy, dec.valid) if subpixel else dec.prj_xy.clone()
    if max_hole:
        prj_xy = fill_holes(prj_xy, max_hole)
    cam_xy, count = inverse_map(prj_xy, projector_size)
    if max_hole:
        cam_xy = fill_holes(cam_xy, max_hole)
    timings["maps"] = time.perf_counter() - t0
    response = ramp = None
    if capture.ramp is not None:
        t0 = time.perf_counter()
        levels, measured = measure_ramp(capture.ramp[0], capture.white, capture.black, dec.prj_xy[..., 0],
                                        projector_size[0], ramp_steps)
        response = fit_response(levels, measured)
        ramp = (levels, measured)
        timings["response"] = time.perf_counter() - t0
    return ProjectorCalibration(decoding=dec, prj_xy=prj_xy, cam_xy=cam_xy, count=count, response=response,
                                ramp=ramp, timings_s=timings)
