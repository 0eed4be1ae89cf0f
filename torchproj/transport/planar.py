"""Planar scenes: every state's decoded maps replaced by one fitted homography per projector.

The fit and its test of planarity live in :mod:`torchproj.calib.homography`; this module applies
them to whole states, keeping the measured weights, so that the operator has the same rows and
columns as with the decoded maps.
"""

from __future__ import annotations

import torch

from ..calib.homography import HomographyFit, check_plane, fit_homography, homography_map
from .build import StateCalibration

__all__ = ["HomographyFit", "fit_homography", "homography_map", "planar_calibration"]


def planar_calibration(states: dict, tolerance: float = 1.0, **fit_options) -> tuple[dict, dict]:
    """Every state's maps replaced by fitted homographies, where each state is one plane.

    The weights (white minus black) stay as measured: they carry fall-off and vignetting, which a
    homography does not model. The fitted map covers the pixels that decoded, so the operator
    keeps the same rows and columns as with the decoded map.

    Args:
        states: state name -> :class:`~torchproj.transport.StateCalibration`.
        tolerance: the largest 95th-percentile distance (projector pixels) between decoded and
            fitted coordinates that still counts as a plane.
        fit_options: passed to :func:`fit_homography`.

    Returns:
        state name -> planar :class:`~torchproj.transport.StateCalibration`, and state name -> one
        :class:`HomographyFit` per projector.
    """
    planar, fits = {}, {}
    for name, state in states.items():
        fits[name] = [fit_homography(xy, **fit_options) for xy in state.prj_xy]
        for j, fit in enumerate(fits[name]):
            check_plane(fit, tolerance, f"state {name!r}, projector {j}", "keep the decoded maps for this scene")
        maps = [homography_map(fit.matrix, torch.isfinite(xy).all(-1), size)
                for fit, xy, size in zip(fits[name], state.prj_xy, state.projector_sizes)]
        planar[name] = StateCalibration(maps, state.weight, state.projector_sizes)
    return planar, fits
