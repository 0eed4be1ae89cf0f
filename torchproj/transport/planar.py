"""Planar scenes: every state's decoded maps replaced by one fitted homography per projector.

The fit and its test of planarity live in :mod:`torchproj.calib.homography`; this module applies
them to whole states, keeping the measured weights, so that the operator has the same rows and
columns as with the decoded maps.
"""

from __future__ import annotations

import dataclasses

import torch

from ..calib.homography import HomographyFit, check_plane, fit_homography, homography_map
from ..core.checks import check, check_number
from .build import check_calibrations

__all__ = ["HomographyFit", "MAPS", "fit_homography", "homography_map", "planar_calibration", "select_maps"]

from ..core.choices import MAPS  # noqa: E402


def planar_calibration(states: dict, tolerance: float = 1.0, names: list[str] | None = None,
                       **fit_options) -> tuple[dict, dict]:
    """Every state's maps replaced by fitted homographies, where each state is one plane.

    The weights (white minus black) stay as measured: they carry fall-off and vignetting, which a
    homography does not model. The fitted map covers the pixels that decoded, so the operator
    keeps the same rows and columns as with the decoded map.

    Args:
        states: state name -> :class:`~torchproj.transport.StateCalibration`.
        tolerance: the largest 95th-percentile distance (projector pixels) between decoded and
            fitted coordinates that still counts as a plane.
        names: each projector's name, for the message that refuses a state that is not one plane
            (None: its index).
        fit_options: passed to :func:`fit_homography`.

    Returns:
        state name -> planar :class:`~torchproj.transport.StateCalibration`, and state name -> one
        :class:`HomographyFit` per projector.
    """
    check_calibrations(states, "states")
    check_number(tolerance, "tolerance (projector pixels)", 0, strict=True)
    check(names is None or (isinstance(names, (list, tuple)) and all(isinstance(n, str) for n in names)),
          f"names must be the projectors' names (a list of str), or None, got {names!r}")
    planar, fits = {}, {}
    for name, state in states.items():
        check(names is None or len(names) == len(state.prj_xy), f"names must name the {len(state.prj_xy)} projectors, "
                                                                 f"got {len(names or [])}")
        fits[name] = [fit_homography(xy, **fit_options) for xy in state.prj_xy]
        for j, fit in enumerate(fits[name]):
            check_plane(fit, tolerance, f"state {name!r}, projector {j if names is None else repr(names[j])}",
                        "keep the decoded maps for this scene")
        maps = [homography_map(fit.matrix, torch.isfinite(xy).all(-1), size)
                for fit, xy, size in zip(fits[name], state.prj_xy, state.projector_sizes)]
        # The same weights (grey and per channel), blur and measured cell shares (they measure the light,
        # whatever map places it); on one plane there is no depth edge, and the decoded map's edge
        # pixels would not match the fitted map.
        planar[name] = dataclasses.replace(state, prj_xy=maps, edges=None)
    return planar, fits


def select_maps(states: dict, maps: str = "decoded", tolerance: float = 1.0, fitted: dict | None = None,
                names: list[str] | None = None):
    """The maps an operator is built on: decoded per pixel, or one homography per state and projector.

    Args:
        states: state name -> :class:`~torchproj.transport.StateCalibration` as calibrated.
        maps: ``"decoded"`` or ``"homography"`` (:func:`planar_calibration`; planar scenes only).
        tolerance, names: see :func:`planar_calibration`.
        fitted: state name -> per projector, the fits (:class:`HomographyFit` or its ``as_dict``) a
            calibration from shortened Gray-code sequences was read through: its maps are
            homographies already, whatever ``maps`` asks.

    Returns:
        ``(states, maps, fits)``: the states to build on, the maps they are, and state name -> per
        projector the fit as a dict (None for decoded maps).
    """
    from ..core.checks import check

    check(maps in MAPS, f"maps must be one of {list(MAPS)}, got {maps!r}")
    check(fitted is None or (isinstance(fitted, dict) and all(
              isinstance(per, (list, tuple)) and all(isinstance(f, (dict, HomographyFit)) for f in per)
              for per in fitted.values())),
          f"fitted must be None or a dict of state name -> per projector its HomographyFit (or its as_dict), got "
          f"{type(fitted).__name__}")
    if fitted:
        return states, "homography", {name: [f if isinstance(f, dict) else f.as_dict() for f in per]
                                      for name, per in fitted.items()}
    if maps == "decoded":
        return states, maps, None
    planar, fits = planar_calibration(states, tolerance, names)
    return planar, maps, {name: [f.as_dict() for f in per] for name, per in fits.items()}
