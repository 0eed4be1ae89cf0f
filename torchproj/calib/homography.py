"""A plane's camera-to-projector map as one homography instead of a decoded map.

For a pinhole camera and projector, the points of one plane map between the two images by a
homography, ``x_prj ~ H x_cam`` (coordinates: :mod:`torchproj.core.conventions`). Fitting ``H`` to
the Gray-code correspondences gives every pixel of the plane an exact sub-cell projector coordinate.
The decoded map has quantisation, bit errors and holes; the fitted one has none. The fit uses
kornia's iteratively reweighted DLT, which down-weights the bit errors. It needs far fewer
correspondences than a map: the coarse Gray-code patterns alone pin an 8-parameter model, which
is what a shortened sequence (``torchproj sequence --bits``) relies on.

**When it is enough.** A homography fits only when everything a projector lights in a state is one
plane and the optics are close to pinhole. :func:`fit_homography` reports the 95th percentile of
the distance between decoded and predicted coordinates; :func:`check_plane` refuses a map whose
percentile exceeds the tolerance (a box, two planes seen by one projector, a curved screen, or
strong lens distortion).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from kornia.geometry.homography import find_homography_dlt_iterated
from kornia.geometry.linalg import transform_points

from ..core.checks import check, check_count, check_number, check_pair, check_shape
from ..core.conventions import pixel_grid
from .maps import check_projector_size

__all__ = ["HomographyFit", "check_plane", "fit_homography", "homography_map"]


@dataclass
class HomographyFit:
    """A homography fitted to one decoded map.

    Attributes:
        matrix: :math:`(3, 3)` float64, camera pixel ``(x, y, 1)`` to projector coordinates.
        p95: 95th percentile of the residual (projector pixels, :func:`fit_homography`) over every
            decoded pixel.
        median: median of the same residuals.
        points: decoded pixels the percentiles are taken over.
        fitted_on: pixels the homography was fitted on (an even subsample of them).
        block: ``(bx, by)`` projector cells per decoded value along x and y: ``(1, 1)`` for a full
            Gray-code sequence, ``2^(n - k)`` for the first k of n bits.
    """

    matrix: torch.Tensor
    p95: float
    median: float
    points: int
    fitted_on: int
    block: tuple[int, int] = (1, 1)

    def as_dict(self) -> dict:
        return {"p95_px": round(self.p95, 4), "median_px": round(self.median, 4), "points": self.points,
                "fitted_on": self.fitted_on, "block_cells": list(self.block),
                "matrix": [[round(v, 10) for v in row] for row in self.matrix.tolist()]}


def fit_homography(prj_xy: torch.Tensor, *, block: tuple[int, int] = (1, 1), max_points: int = 20000,
                   soft_threshold: float = 2.0, iterations: int = 5) -> HomographyFit:
    """Fit the homography from camera pixels to the projector coordinates they decoded to.

    **Full maps** (``block`` of one cell): kornia's iteratively reweighted DLT on the decoded
    coordinates; the residual of a pixel is the distance from its fitted coordinate to the decoded
    one, taken over every decoded pixel.

    **Block maps** (a shortened sequence, ``prj_xy`` holding block centres): the centres are only
    a start. All a block says is that the true coordinate lies inside it, and the sharp
    information is where blocks change: the camera pixels at a block edge pin the projector
    coordinate of that edge. So the start is refined by scipy's robust least squares on the
    pixels at block edges, each pixel's residual being how far its fitted coordinate falls
    outside its block (zero inside). The fit's residual percentiles are taken over those edge
    pixels: deep inside a block a surface off the plane would go unseen.

    Args:
        prj_xy: :math:`(H, W, 2)` projector coordinates per camera pixel, NaN where unknown.
        block: projector cells per decoded value along x and y.
        max_points: at most this many decoded pixels, evenly spread, enter the fit (8 parameters do
            not need a million equations); the residuals are then taken over all of them.
        soft_threshold: standard deviation (pixels) of the reweighting that down-weights bit errors;
            for block maps it grows to the block size, so that the quantisation itself is not
            mistaken for bit errors.
        iterations: reweighted solves.

    Returns:
        a :class:`HomographyFit`.
    """
    check_shape(prj_xy, "prj_xy", ["H", "W", 2])
    check_count(max_points, "max_points", 4)
    check_count(iterations, "iterations", 1)
    check_number(soft_threshold, "soft_threshold (pixels)", 0, strict=True)
    bx, by = check_pair(block, "block", "(cells along x, cells along y)", 1)
    ok = torch.isfinite(prj_xy).all(-1)
    n = int(ok.sum())
    check(n >= 4, f"a homography needs at least 4 decoded pixels, this map has {n}")
    if (bx, by) != (1, 1):
        edge, (ex, ey) = _block_edges(_drop_isolated(prj_xy))
        # Each block edge is a line of known projector x (or y); a homography needs two of each
        # (four lines, no three through one point) to be pinned down. Counted before the start's fit,
        # which a map of a few blocks leaves degenerate: the count says what to do about it.
        check(ex >= 2 and ey >= 2, f"the decoded blocks show {ex} column and {ey} row edges, a homography needs at "
                                   "least 2 of each: show more bits of the Gray-code sequence (--bits)")
    cam = pixel_grid(*prj_xy.shape[:2], device=prj_xy.device, dtype=torch.float64)[ok]
    prj = prj_xy[ok].double()
    pick = _spread(n, max_points, prj_xy.device)
    matrix = find_homography_dlt_iterated(cam[pick][None], prj[pick][None], prj.new_ones(1, len(pick)),
                                          soft_inl_th=max(soft_threshold, bx, by), n_iter=iterations)[0]
    check(bool(torch.isfinite(matrix).all()), "the homography fit failed (degenerate correspondences: are the decoded "
                                              "pixels on a line?)" + ("" if (bx, by) == (1, 1) else
                                                                      "; show more bits of the Gray-code sequence (--bits)"))
    if (bx, by) == (1, 1):
        error = (transform_points(matrix[None], cam[None])[0] - prj).norm(dim=-1)
        fitted_on = len(pick)
    else:
        cam, prj = cam[edge[ok]], prj[edge[ok]]
        half = torch.tensor([bx / 2, by / 2], dtype=torch.float64, device=prj.device)
        pick = _spread(len(cam), max_points, prj.device)
        matrix = _fit_to_blocks(matrix, cam[pick], prj[pick] - half, prj[pick] + half)
        fitted = transform_points(matrix[None], cam[None])[0]
        error = (fitted - torch.minimum(torch.maximum(fitted, prj - half), prj + half)).norm(dim=-1)
        n, fitted_on = len(cam), len(pick)
    p95, median = torch.quantile(error[_spread(n, 1_000_000, error.device)],
                                 torch.tensor([0.95, 0.5], dtype=torch.float64, device=error.device)).tolist()
    return HomographyFit(matrix=matrix, p95=p95, median=median, points=n, fitted_on=fitted_on, block=(bx, by))


def _spread(n: int, most: int, device) -> torch.Tensor:
    """Indices of at most ``most`` of ``n`` items, evenly spread."""
    return torch.linspace(0, n - 1, min(n, most), device=device).round().long()


def _drop_isolated(prj_xy: torch.Tensor) -> torch.Tensor:
    """The map without pixels that differ from at least 3 of their 4 decoded neighbours.

    A flipped bit makes a pixel decode to another block than everything around it; left in, it
    would count as a block edge and its four neighbours too. A pixel on a true edge differs from
    the neighbours across the edge only (two at a corner).
    """
    ok = torch.isfinite(prj_xy).all(-1)
    padded = torch.nn.functional.pad(prj_xy.permute(2, 0, 1), (1, 1, 1, 1), value=float("nan")).permute(1, 2, 0)
    h, w = prj_xy.shape[:2]
    differ = torch.zeros(prj_xy.shape[:2], dtype=torch.int64, device=prj_xy.device)
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        other = padded[dy:dy + h, dx:dx + w]
        differ += (torch.isfinite(other).all(-1) & (other != prj_xy).any(-1)).long()
    out = prj_xy.clone()
    out[ok & (differ >= 3)] = float("nan")
    return out


def _block_edges(prj_xy: torch.Tensor, min_pixels: int = 8) -> tuple[torch.Tensor, tuple[int, int]]:
    """Decoded pixels at a block edge, and how many distinct edges each axis shows.

    Returns:
        :math:`(H, W)` bool, decoded pixels with a 4-neighbour that decoded to another block; and
        the number of distinct column and row edges (block boundaries crossed between neighbours
        at least ``min_pixels`` times, so that a flipped bit does not count as an edge).
    """
    ok = torch.isfinite(prj_xy).all(-1)
    edge = torch.zeros_like(ok)
    crossings: list[list[torch.Tensor]] = [[], []]
    for dim in (0, 1):
        size = prj_xy.shape[dim] - 1
        a, b = prj_xy.narrow(dim, 0, size), prj_xy.narrow(dim, 1, size)
        both = ok.narrow(dim, 0, size) & ok.narrow(dim, 1, size)
        step = both & (a != b).any(-1)
        edge.narrow(dim, 0, size).logical_or_(step)
        edge.narrow(dim, 1, size).logical_or_(step)
        for axis in (0, 1):
            moved = both & (a[..., axis] != b[..., axis])
            crossings[axis].append(0.5 * (a[..., axis][moved] + b[..., axis][moved]))
    counts = []
    for axis in (0, 1):
        _, seen = torch.unique(torch.cat(crossings[axis]), return_counts=True)
        counts.append(int((seen >= min_pixels).sum()))
    return edge, (counts[0], counts[1])


def _fit_to_blocks(start: torch.Tensor, cam: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """The homography that puts every camera point inside its block ``[lo, hi]``, from ``start``.

    Minimises ``sum |h(c) - clamp(h(c), lo, hi)|^2`` over the 8 free entries with scipy's
    trust-region least squares and a Huber loss of one projector pixel (a flipped bit puts a pixel
    a whole block off: it must not pull the fit). Coordinates are normalised first, so that the
    entries are of one scale.
    """
    import numpy as np
    from scipy.optimize import least_squares

    c, a, b = (t.cpu().numpy() for t in (cam, lo, hi))
    mc, sc = c.mean(0), c.std() + 1e-12
    mp, sp = 0.5 * (a + b).mean(0), 0.5 * (a + b).std() + 1e-12
    to_c = np.array([[1 / sc, 0, -mc[0] / sc], [0, 1 / sc, -mc[1] / sc], [0, 0, 1]])
    to_p = np.array([[1 / sp, 0, -mp[0] / sp], [0, 1 / sp, -mp[1] / sp], [0, 0, 1]])
    h0 = to_p @ start.cpu().numpy() @ np.linalg.inv(to_c)
    u, v = ((c - mc) / sc).T
    a, b = (a - mp) / sp, (b - mp) / sp

    def project(h):
        w = h[6] * u + h[7] * v + 1
        return (h[0] * u + h[1] * v + h[2]) / w, (h[3] * u + h[4] * v + h[5]) / w, w

    def residual(h):
        x, y, _ = project(h)
        xy = np.stack([x, y], 1)
        return ((xy - np.clip(xy, a, b)) * sp).ravel()  # projector pixels

    def jacobian(h):
        x, y, w = project(h)
        xy = np.stack([x, y], 1)
        outside = ((xy < a) | (xy > b)) * (sp / w)[:, None]  # zero where inside the block
        jac = np.zeros((len(u), 2, 8))
        jac[:, 0, 0:3] = np.stack([u, v, np.ones_like(u)], 1)
        jac[:, 1, 3:6] = jac[:, 0, 0:3]
        jac[:, 0, 6:8] = -x[:, None] * np.stack([u, v], 1)
        jac[:, 1, 6:8] = -y[:, None] * np.stack([u, v], 1)
        return (jac * outside[:, :, None]).reshape(-1, 8)

    h0 = h0 / h0[2, 2]
    fit = least_squares(residual, h0.ravel()[:8], jac=jacobian, method="trf", loss="huber", f_scale=1.0,
                        x_scale="jac")
    matrix = np.linalg.inv(to_p) @ np.append(fit.x, 1.0).reshape(3, 3) @ to_c
    return torch.from_numpy(matrix / matrix[2, 2]).to(start.device, torch.float64)


def check_plane(fit: HomographyFit, tolerance: float, where: str, fix: str) -> None:
    """Refuse a fit whose 95th-percentile residual exceeds ``tolerance`` (projector pixels).

    Args:
        where: what the map belongs to, for the message (``"state 'near', projector 0"``).
        fix: what the user can do instead, for the message.
    """
    check(tolerance > 0 and math.isfinite(tolerance), f"the plane tolerance must be > 0 projector pixels, got {tolerance}")
    check(fit.p95 <= tolerance,
          f"{where}: the decoded map is not one plane (95% of pixels within {fit.p95:.2f} projector pixels of the "
          f"best homography, tolerance {tolerance:g}); {fix}, or raise the tolerance (--plane-tolerance; "
          "plane_tolerance= in Python) if the optics are known to distort")


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
    width, height = check_projector_size(projector_size)
    out = torch.full((*mask.shape, 2), float("nan"), dtype=torch.float32, device=mask.device)
    cam = pixel_grid(*mask.shape, device=mask.device, dtype=torch.float64)[mask]
    xy = transform_points(matrix.to(mask.device, torch.float64)[None], cam[None])[0]
    edge = 0.5 - 1e-3  # cells are centred on integers (conventions): keep to the outermost cells' far sides
    xy[:, 0].clamp_(-0.5, width - 1 + edge)
    xy[:, 1].clamp_(-0.5, height - 1 + edge)
    out[mask] = xy.float()
    return out
