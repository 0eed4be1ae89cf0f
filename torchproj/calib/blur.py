"""Projector defocus measured from the Gray-code captures themselves.

A lens focused at one depth spreads each LCD cell's light over a disc (the circle of confusion) at
any other depth. The finest Gray-code stripes, a few cells wide, are where that shows: a sharp
pixel inside a stripe sees ``pattern - inverse = +-(white - black)``, a blurred one sees the stripes
averaged, and how much they average depends on the disc's diameter and on where the pixel sits
among the stripes. Calibration already knows where (the refined map) and what the pixel's own area
covers (the map's slope), so the disc's diameter is the one unknown: per sampled pixel, the
diameter whose predicted normalised differences of the finest bits of both axes best match the
captured ones (least squares over a grid of diameters), then a median over neighbouring samples,
because the blur follows depth, which varies smoothly on a surface.

The paper has no defocus model (its projectors are taken as sharp at every depth); this estimator,
its grid, sampling and median are our choices, measured in docs/accuracy.md ("The ceiling").
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..core.checks import check, check_count, check_number, check_shape, is_whole
from ..core.lens import disc_points
from .graycode import _grey, check_full_sequence, stripe_signs
from .maps import map_slope, pixel_square

__all__ = ["measure_blur"]

# Bits per axis compared, and the diameters (cells) tried per sample: half-cell steps from sharp to
# wider than the finest bits can tell (the fourth-finest stripes are 16 cells wide).
_FINEST = 4
_DIAMETERS = torch.arange(0, 12.25, 0.5)
_AREA = 4  # points per axis across a camera pixel's square, as the area footprint
_DISC = 16  # points of the disc (Vogel spiral), as the virtual rig samples a circle of confusion
# Neighbouring samples whose diameters differ by less than this (cells) are taken as one surface's.
_AGREE = 1.0


def measure_blur(patterns: torch.Tensor, white: torch.Tensor, black: torch.Tensor, prj_xy: torch.Tensor,
                 projector_size: tuple[int, int], *, finest: int | None = None, step: int = 16,
                 min_contrast: float = 0.1, slope: torch.Tensor | None = None) -> torch.Tensor:
    """Diameter in cells of each camera pixel's defocus disc, from the finest Gray-code captures.

    Args:
        patterns: :math:`(N, H, W)` or :math:`(N, C, H, W)` the full Gray-code sequence's
            pattern/inverse captures (:func:`~torchproj.calib.graycode_patterns` order).
        white, black: :math:`(H, W)` or :math:`(C, H, W)`.
        prj_xy: :math:`(H, W, 2)` the refined map (NaN where unknown).
        projector_size: ``(width, height)``.
        finest: how many of each axis' finest bits to compare; None: 4, or every bit of a projector
            with fewer (a narrower one tells a smaller range of diameters).
        step: camera pixels between samples along each axis; each pixel takes its sample's value.
        min_contrast: white minus black, [0, 1] units, below which a pixel is too dark to judge.
        slope: :math:`(H, W, 2, 2)` ``map_slope(prj_xy)`` where the caller has it; None: computed here.

    Returns:
        :math:`(H, W)` float32 diameters (0 = sharp), NaN where the map is unknown or no sample
        near it could be judged.
    """
    nx, ny, contrast = check_full_sequence(patterns, white, black, prj_xy, projector_size, "measure_blur",
                                           " (a shortened sequence, --bits, lacks the finest stripes that show the blur)")
    width, height = projector_size
    grey = _grey(patterns)
    H, W = contrast.shape
    finest = min(_FINEST, nx, ny) if finest is None else finest
    check(is_whole(finest) and 1 <= finest <= min(nx, ny), f"finest must be 1..{min(nx, ny)}, got {finest!r}")
    check_count(step, "step (camera pixels between samples)")
    check_number(min_contrast, "min_contrast (white - black, in [0, 1])")
    slope = map_slope(prj_xy) if slope is None else slope
    check_shape(slope, "slope", [H, W, 2, 2])
    # Samples on a grid, at pixel centres, where everything the prediction needs is known.
    device = prj_xy.device
    ys = torch.arange(step // 2, H, step, device=device)
    xs = torch.arange(step // 2, W, step, device=device)
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    u, g, c = prj_xy[gy, gx], slope[gy, gx], contrast[gy, gx]
    ok = torch.isfinite(u).all(-1) & torch.isfinite(g).all(-1).all(-1) & (c > min_contrast)
    u, g, c = u[ok], g[ok], c[ok]
    observed = []
    for first, bits in ((0, nx), (nx, ny)):
        pairs = range(first + bits - finest, first + bits)
        observed.append(torch.stack([(grey[2 * k] - grey[2 * k + 1])[gy, gx][ok] for k in pairs], -1) / c[:, None])
    area = u[:, None, :] + torch.einsum("nij,sj->nsi", g, pixel_square(_AREA, device=device))  # (n, S, 2)
    disc = disc_points(_DISC, device)  # (K, 2)
    diameters = _DIAMETERS.to(device)
    error = torch.zeros(u.shape[0], diameters.numel(), device=device)
    # What the finest bits show in each cell, a row per cell between two rows of zeros (off the
    # projector): a point's prediction is one row read, and a sample's mean over its points one
    # embedding_bag, instead of the Gray code worked out at each of the S x K points (5x faster).
    signs = [F.pad(stripe_signs(torch.arange(size, device=device, dtype=torch.float32), finest, size), (0, 0, 1, 1))
             for size in (width, height)]
    for i, diameter in enumerate(_DIAMETERS.tolist()):
        points = area[:, :, None, :] + diameter * disc  # (n, S, K, 2)
        for axis, size in enumerate((width, height)):
            row = torch.floor(points[..., axis].flatten(1) + 1.5).clamp_(0, size + 1).long()
            predicted = F.embedding_bag(row, signs[axis], mode="mean")
            error[:, i] += (predicted - observed[axis]).square().sum(-1)
    best = diameters[error.argmin(1)]
    grid = torch.full(gy.shape, float("nan"), device=device)
    grid[ok] = best
    at = torch.full((*gy.shape, 2), float("nan"), device=device)  # each sample's projector coordinate
    at[ok] = u
    return _on_the_surface(grid, at, ys, xs, prj_xy, slope, step)


def _on_the_surface(grid: torch.Tensor, at: torch.Tensor, ys: torch.Tensor, xs: torch.Tensor, prj_xy: torch.Tensor,
                    slope: torch.Tensor, step: int) -> torch.Tensor:
    """Each pixel's diameter: the median over the 3 x 3 samples about it that lie on its own surface.

    The blur follows depth, smooth on a surface, and one noisy sample should not set its block's
    model; but beside an object's outline the samples of the surface behind are as near as its own,
    and on a focused object before a defocused wall a median over both gave a fifth to a half of the
    object's pixels a disc a cell wide and more (``suite-3-0``). A sample is on the pixel's surface
    where the map carries the pixel there: its projector coordinate is within a cell (and a quarter of
    the way, for curvature) of the pixel's own carried through its slope. Where the 3 x 3 samples
    agree within ``_AGREE`` cells (all of a sharp scene, the inside of a blurred surface) they are one
    surface's, and the pixel takes their median without the test."""
    H, W = prj_xy.shape[:2]
    device = prj_xy.device
    rows = torch.clamp(torch.arange(H, device=device) // step, max=grid.shape[0] - 1)
    cols = torch.clamp(torch.arange(W, device=device) // step, max=grid.shape[1] - 1)
    padded = F.pad(grid[None, None], (1, 1, 1, 1), value=float("nan"))
    around = F.unfold(padded, 3).reshape(9, *grid.shape)  # each sample's 3 x 3 neighbours
    spread = torch.nan_to_num(around.nan_to_num(float("-inf")).amax(0) - around.nan_to_num(float("inf")).amin(0),
                              nan=0.0, posinf=0.0, neginf=0.0)
    blur = torch.nanmedian(around, 0).values[rows[:, None], cols[None, :]]
    disputed = torch.nonzero((spread >= _AGREE)[rows[:, None], cols[None, :]] & torch.isfinite(prj_xy).all(-1))
    if disputed.numel():
        py, px = disputed.unbind(-1)
        xy, g = prj_xy[py, px], slope[py, px]
        known = torch.isfinite(g).all(-1).all(-1)
        g = torch.nan_to_num(g)
        candidates = []
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                r = (rows[py] + dy).clamp(0, grid.shape[0] - 1)
                c = (cols[px] + dx).clamp(0, grid.shape[1] - 1)
                offset = torch.stack([xs[c] - px, ys[r] - py], -1).to(xy.dtype)  # camera pixels, (x, y)
                carried = torch.einsum("nij,nj->ni", g, offset)
                miss = (at[r, c] - xy - carried).norm(dim=-1)
                same = torch.where(known, miss <= torch.clamp(0.25 * carried.norm(dim=-1), min=1.0), (dy == 0) & (dx == 0))
                candidates.append(torch.where(same, grid[r, c], float("nan")))
        blur[py, px] = torch.nanmedian(torch.stack(candidates), 0).values
    return torch.where(torch.isfinite(prj_xy).all(-1), blur, float("nan")).to(torch.float32)
