"""A plane's camera-to-projector map as one homography instead of a decoded map.

For a pinhole camera and projector, the points of one plane map between the two images by a
homography, ``x_prj ~ H x_cam`` (coordinates: :mod:`torchproj.core.conventions`). Fitting ``H`` to
the Gray-code correspondences gives every pixel of the plane an exact sub-cell projector coordinate.
The decoded map has quantisation, bit errors and holes; the fitted one has none. The fit uses
kornia's iteratively reweighted DLT, which down-weights the bit errors. It needs far fewer
correspondences than a map: the coarse Gray-code patterns alone pin an 8-parameter model
(``benchmarks/homography.py`` measures how many).

**When it is enough.** A homography fits only when everything a projector lights in a state is one
plane and the optics are close to pinhole. :func:`fit_homography` reports the 95th percentile of
the distance between decoded and predicted coordinates. :meth:`StateCalibration.planar` refuses a
map whose percentile exceeds the tolerance: a box, two planes seen by one projector, a curved
screen, or strong lens distortion.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from kornia.geometry.homography import find_homography_dlt_iterated
from kornia.geometry.linalg import transform_points

from ..core.checks import check, check_shape
from ..core.conventions import pixel_grid
from .build import StateCalibration

__all__ = ["HomographyFit", "fit_homography", "homography_map", "planar_calibration"]


@dataclass
class HomographyFit:
    """A homography fitted to one decoded map.

    Attributes:
        matrix: :math:`(3, 3)` float64, camera pixel ``(x, y, 1)`` to projector coordinates.
        p95: 95th percentile of the distance (projector pixels) between the decoded coordinates
            and the fitted ones, over every decoded pixel.
        median: median of the same distances.
        points: decoded pixels the percentiles are taken over.
        fitted_on: pixels the homography was fitted on (an even subsample of them).
    """

    matrix: torch.Tensor
    p95: float
    median: float
    points: int
    fitted_on: int

    def as_dict(self) -> dict:
        return {"p95_px": round(self.p95, 4), "median_px": round(self.median, 4), "points": self.points,
                "fitted_on": self.fitted_on, "matrix": [[round(v, 10) for v in row] for row in self.matrix.tolist()]}


def fit_homography(prj_xy: torch.Tensor, *, max_points: int = 20000, soft_threshold: float = 2.0,
                   iterations: int = 5) -> HomographyFit:
    """Fit the homography from camera pixels to the projector coordinates they decoded to.

    Args:
        prj_xy: :math:`(H, W, 2)` projector coordinates per camera pixel, NaN where unknown.
        max_points: at most this many decoded pixels, evenly spread, enter the fit (8 parameters do
            not need a million equations); the residuals are then taken over all of them.
        soft_threshold: standard deviation (pixels) of the reweighting that down-weights bit errors.
        iterations: reweighted solves.

    Returns:
        a :class:`HomographyFit`.
    """
    check_shape(prj_xy, "prj_xy", ["H", "W", 2])
    check(max_points >= 4, f"max_points must be >= 4, got {max_points}")
    ok = torch.isfinite(prj_xy).all(-1)
    n = int(ok.sum())
    check(n >= 4, f"a homography needs at least 4 decoded pixels, this map has {n}")
    cam = pixel_grid(*prj_xy.shape[:2], device=prj_xy.device, dtype=torch.float64)[ok]
    prj = prj_xy[ok].double()
    pick = torch.linspace(0, n - 1, min(n, max_points), device=prj_xy.device).round().long()
    matrix = find_homography_dlt_iterated(cam[pick][None], prj[pick][None], torch.ones(1, len(pick), dtype=torch.float64),
                                          soft_inl_th=soft_threshold, n_iter=iterations)[0]
    check(bool(torch.isfinite(matrix).all()), "the homography fit failed (degenerate correspondences: are the decoded "
                                              "pixels on a line?)")
    error = (transform_points(matrix[None], cam[None])[0] - prj).norm(dim=-1)
    p95, median = torch.quantile(error[torch.linspace(0, n - 1, min(n, 1_000_000)).long()],
                                 torch.tensor([0.95, 0.5], dtype=torch.float64)).tolist()
    return HomographyFit(matrix=matrix, p95=p95, median=median, points=n, fitted_on=len(pick))


def homography_map(matrix: torch.Tensor, mask: torch.Tensor, projector_size: tuple[int, int]) -> torch.Tensor:
    """Projector coordinates of the camera pixels in ``mask``, by the homography.

    Every pixel in ``mask`` gets a coordinate inside the projector image: the mask is where the
    projector was seen to shine, and a pixel at the image's edge that the fit puts a fraction of a
    cell outside is clamped to the edge cell. So a planar calibration lights exactly the pixels
    the decoded one does, and targets land on the same pixels.

    Args:
        matrix: :math:`(3, 3)` camera to projector homography.
        mask: :math:`(H, W)` bool pixels to map.
        projector_size: ``(width, height)``.

    Returns:
        :math:`(H, W, 2)` float32 map, NaN outside ``mask``.
    """
    check_shape(mask, "mask", ["H", "W"])
    check_shape(matrix, "matrix", [3, 3])
    width, height = projector_size
    out = torch.full((*mask.shape, 2), float("nan"), dtype=torch.float32, device=mask.device)
    cam = pixel_grid(*mask.shape, device=mask.device, dtype=torch.float64)[mask]
    xy = transform_points(matrix.to(mask.device, torch.float64)[None], cam[None])[0]
    edge = 0.5 - 1e-3  # cells are centred on integers (conventions): keep to the outermost cells' far sides
    xy[:, 0].clamp_(-0.5, width - 1 + edge)
    xy[:, 1].clamp_(-0.5, height - 1 + edge)
    out[mask] = xy.float()
    return out


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
    check(tolerance > 0, f"tolerance must be > 0 projector pixels, got {tolerance}")
    planar, fits = {}, {}
    for name, state in states.items():
        fits[name] = [fit_homography(xy, **fit_options) for xy in state.prj_xy]
        for j, fit in enumerate(fits[name]):
            check(fit.p95 <= tolerance,
                  f"state {name!r}, projector {j}: the decoded map is not one plane (95% of pixels within "
                  f"{fit.p95:.2f} projector pixels of the best homography, tolerance {tolerance:g}); keep the "
                  "decoded maps for this scene, or raise the tolerance if the optics are known to distort")
        maps = [homography_map(fit.matrix, torch.isfinite(xy).all(-1), size)
                for fit, xy, size in zip(fits[name], state.prj_xy, state.projector_sizes)]
        planar[name] = StateCalibration(maps, state.weight, state.projector_sizes)
    return planar, fits
