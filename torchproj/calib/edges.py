"""Camera pixels at the edges of what a map covers: objects' outlines and the fringe of the light.

Two kinds of pixel get no faithful light model from the decoded map alone:

- Beside a depth edge (:func:`~torchproj.calib.maps.depth_edges`), where an object stands in front
  of another, a pixel may see part of the object and part of the surface behind, lit by cells far
  apart: its light is the sum of two footprints, each by its share of the pixel's white minus
  black. Gray code decodes it to one of the two places, or to a wrong one (its bits mix two codes).
- Where light grazes a surface or a shadow begins, a pixel the projector visibly lights (white
  minus black over 0.1) may stay unmapped: under the decoder's shadow threshold (40/255, OpenCV's)
  where its code does not read down to the dim threshold (:data:`~torchproj.calib.DIM_THRESHOLD`). If another projector's light keeps it in the solve, the model then says this projector
  sends it nothing; on ``box_cylinders`` such pixels fringe the cylinders' outlines.

Both are read from the captures: the mapped pixels within two pixels carry their surfaces'
coordinates to the pixel through their own slopes (:func:`~torchproj.calib.maps.map_slope`; a
surface seen as a strip one pixel wide, between an outline and a shadow, borrows the slope across
the strip from along it, :func:`~torchproj.calib.maps.fill_slope`). Each
candidate predicts every Gray-code bit's normalised difference ``d = (pattern - inverse) / (white -
black)`` as the mean of the stripes over the pixel's square carried through its slope, ``s``; a pair
of candidates on two surfaces predicts ``a s_A + (1 - a) s_B``, with the share ``a`` in closed form
(least squares over the bits of both axes). The best candidate, or the best pair where it matches
the captured differences clearly better, is the pixel's model.

The paper models one coordinate per decoded pixel; this model, its candidates and its thresholds are
our choices, measured against the exact light in docs/accuracy.md ("The ceiling").
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..core.checks import check, check_shape
from .graycode import check_full_sequence, stripe_signs
from .maps import EDGE_JUMP, depth_edges, fill_slope, map_slope, pixel_square

__all__ = ["EdgePixels", "find_edge_pixels"]

_REACH = 2  # pixels either side whose surfaces are candidates: a 5 x 5 window
_SAMPLES = 4  # points per axis across the pixel's square, as the area footprint
# The best pair must leave at most this share of the best single candidate's squared miss: two
# surfaces fit any pixel a little better than one (one more unknown), a pixel that sees two far better.
_BETTER = 0.5
_MIN_SHARE = 0.05  # a surface with less of the pixel than this is left out (the pixel is one surface)
# White minus black ([0, 1] units) over which a pixel counts as lit: lower than the decoder's shadow
# threshold (40/255), since a pixel here needs no reliable bit of its own. On the shipped scenes 0.05
# gave the same scores; under it a pixel's bits are mostly the camera's noise.
_MIN_CONTRAST = 0.1
_CHUNK = 2048  # pixels per pass: their candidates' stripes are (pixels, 25, 16, bits) floats


@dataclass
class EdgePixels:
    """Camera pixels at the edges of one projector's map, each modelled on one or two surfaces
    (:func:`find_edge_pixels`).

    Attributes:
        pixel: :math:`(M,)` int64 flat camera pixel (row-major).
        xy: :math:`(M, 2, 2)` each surface's projector coordinate at the pixel's centre.
        slope: :math:`(M, 2, 2, 2)` each surface's map slope there (:func:`~torchproj.calib.maps.map_slope`'s
            layout, per surface).
        share: :math:`(M, 2)` each surface's share of the pixel's white minus black (they sum to 1; a
            pixel that sees one surface has ``(1, 0)`` and both surfaces the same).
    """

    pixel: torch.Tensor
    xy: torch.Tensor
    slope: torch.Tensor
    share: torch.Tensor

    @classmethod
    def none(cls, device=None) -> "EdgePixels":
        """No pixel sees two surfaces."""
        return cls(torch.zeros(0, dtype=torch.int64, device=device), torch.zeros(0, 2, 2, device=device),
                   torch.zeros(0, 2, 2, 2, device=device), torch.zeros(0, 2, device=device))

    def __len__(self) -> int:
        return int(self.pixel.numel())

    def check(self, camera: tuple[int, int], where: str) -> None:
        """Shapes and values against an ``(H, W)`` camera; ``where`` names them in the message."""
        m = len(self)
        check_shape(self.xy, f"{where} edge xy", [m, 2, 2])
        check_shape(self.slope, f"{where} edge slope", [m, 2, 2, 2])
        check_shape(self.share, f"{where} edge share", [m, 2])
        check(bool(((self.pixel >= 0) & (self.pixel < camera[0] * camera[1])).all()),
              f"{where}: an edge pixel lies outside the {camera[1]}x{camera[0]} camera")
        check(bool(torch.isfinite(self.xy).all() & torch.isfinite(self.slope).all() & torch.isfinite(self.share).all()
                   & (self.share >= 0).all()),
              f"{where}: edge pixels need finite coordinates and slopes, and shares of at least 0")


def _difference(patterns: torch.Tensor, k: int, y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Pattern pair ``k``'s pattern minus inverse at pixels ``(y, x)``, colour averaged."""
    pair = patterns[2 * k:2 * k + 2][..., y, x].float()  # (2, n) or (2, C, n)
    return (pair if pair.dim() == 2 else pair.mean(1)).diff(dim=0).neg()[0]


def find_edge_pixels(patterns: torch.Tensor, white: torch.Tensor, black: torch.Tensor, prj_xy: torch.Tensor,
                     projector_size: tuple[int, int], slope: torch.Tensor | None = None,
                     depth: torch.Tensor | None = None) -> EdgePixels:
    """The pixels beside depth edges and the lit ones the map misses, each on one or two surfaces
    carried over from its neighbours (module docstring).

    Args:
        patterns: :math:`(N, H, W)` or :math:`(N, C, H, W)` the full Gray-code sequence's
            pattern/inverse captures (:func:`~torchproj.calib.graycode_patterns` order).
        white, black: :math:`(H, W)` or :math:`(C, H, W)`.
        prj_xy: :math:`(H, W, 2)` the refined map (NaN where unknown).
        projector_size: ``(width, height)``.
        slope: :math:`(H, W, 2, 2)` ``map_slope(prj_xy)`` where the caller has it; None: computed here.
        depth: :math:`(H, W)` ``depth_edges(prj_xy)`` where the caller has it; None: computed here.

    Returns:
        the :class:`EdgePixels`: every lit pixel beside a depth edge, and every lit unmapped one with
        a mapped pixel within two pixels.
    """
    nx, ny, contrast = check_full_sequence(patterns, white, black, prj_xy, projector_size, "find_edge_pixels")
    width, height = projector_size
    H, W = contrast.shape
    device = prj_xy.device

    lit = contrast > _MIN_CONTRAST
    slope = map_slope(prj_xy) if slope is None else slope
    check_shape(slope, "slope", [H, W, 2, 2])
    known = torch.isfinite(prj_xy).all(-1)
    had = known & torch.isfinite(slope).all(-1).all(-1)
    slope = fill_slope(prj_xy, slope)
    source = known & torch.isfinite(slope).all(-1).all(-1)  # pixels whose surface can be carried over
    step = torch.arange(-_REACH, _REACH + 1, device=device)
    window_y, window_x = (t.reshape(-1) for t in torch.meshgrid(step, step, indexing="ij"))  # the 5 x 5 window
    square = pixel_square(_SAMPLES, device=device)
    pairs = torch.triu_indices(window_y.numel(), window_y.numel(), 1, device=device)

    def fit(y, x):
        """Each pixel's best surface or pair: (the pixels modelled, whether on two surfaces, the two
        candidates, the first's share, every candidate's coordinate and slope)."""
        # Candidates: each window pixel's coordinate carried to this pixel through its slope.
        cy, cx = y[:, None] + window_y, x[:, None] + window_x
        inside = (cy >= 0) & (cy < H) & (cx >= 0) & (cx < W)
        cy, cx = cy.clamp(0, H - 1), cx.clamp(0, W - 1)
        ok = inside & source[cy, cx]  # the pixel itself among them, if mapped
        g = torch.nan_to_num(slope[cy, cx])  # (n, K, 2, 2)
        offset = torch.stack([x[:, None] - cx, y[:, None] - cy], -1).to(g.dtype)  # (n, K, 2)
        xy = torch.nan_to_num(prj_xy[cy, cx]) + torch.einsum("nkij,nkj->nki", g, offset)
        # Each candidate's stripes, averaged over the pixel's square through its slope: (n, K, bits).
        points = xy[:, :, None, :] + torch.einsum("nkij,sj->nksi", g, square)
        predicted = torch.cat([stripe_signs(points[..., 0], nx, width).mean(2),
                               stripe_signs(points[..., 1], ny, height).mean(2)], -1)
        observed = torch.stack([_difference(patterns, k, y, x) for k in range(nx + ny)], -1) / contrast[y, x, None].clamp_min(1e-3)
        single = (predicted - observed[:, None]).square().sum(-1).masked_fill(~ok, float("inf"))  # (n, K)
        a, b = predicted[:, pairs[0]], predicted[:, pairs[1]]  # (n, P, bits)
        apart = a - b
        span = apart.square().sum(-1)
        share = (((observed[:, None] - b) * apart).sum(-1) / span.clamp_min(1e-6)).clamp(0, 1)
        miss = (observed[:, None] - b - share[..., None] * apart).square().sum(-1)
        # Two surfaces: candidates more than the smallest depth edge's step apart, both mapped.
        distinct = (xy[:, pairs[0]] - xy[:, pairs[1]]).abs().amax(-1) > EDGE_JUMP
        usable = ok[:, pairs[0]] & ok[:, pairs[1]] & distinct & (span > 0)
        usable &= (share >= _MIN_SHARE) & (share <= 1 - _MIN_SHARE)
        miss = miss.masked_fill(~usable, float("inf"))
        best_pair, which = miss.min(1)
        one, pick = single.min(1)
        two = torch.isfinite(best_pair) & (best_pair <= _BETTER * one)
        use = two | torch.isfinite(one)
        n = torch.nonzero(use)[:, 0]
        two = two[n]
        ia = torch.where(two, pairs[0][which[n]], pick[n])
        ib = torch.where(two, pairs[1][which[n]], pick[n])
        return n, two, ia, ib, torch.where(two, share[n, which[n]], 1.0), xy, g

    # A pixel whose slope was lent along a strip is a candidate only where it sees one surface itself
    # (its own fit, as below, takes no pair): a row of mixed pixels along an outline decodes to a
    # strip too, at a wrong place (suite-8080-8's sphere lost 0.34 dB to it). A threshold on its own
    # bits' miss did not tell them apart: lent pixels that won 2.5 dB on suite-97-8's box missed by
    # 0.17-0.97, those that lost on suite-8080-8 by 0.56-1.95.
    ly, lx = torch.nonzero(source & ~had, as_tuple=True)
    for start in range(0, ly.numel(), _CHUNK):
        y, x = ly[start:start + _CHUNK], lx[start:start + _CHUNK]
        n, two = fit(y, x)[:2]
        source[y[n[two]], x[n[two]]] = False
    # A pixel with no mapped pixel within reach has no candidate: left out before the candidates'
    # work (a capture that decodes nothing would otherwise send every lit pixel through it).
    reach = F.max_pool2d(source.float()[None, None], 2 * _REACH + 1, stride=1, padding=_REACH)[0, 0] > 0
    depth = depth_edges(prj_xy) if depth is None else depth
    check_shape(depth, "depth", [H, W])
    examine = lit & (depth | ~known) & reach
    ys, xs = torch.nonzero(examine, as_tuple=True)
    found = []
    for start in range(0, ys.numel(), _CHUNK):
        y, x = ys[start:start + _CHUNK], xs[start:start + _CHUNK]
        n, two, ia, ib, alpha, xy, g = fit(y, x)
        found.append((y[n] * W + x[n], torch.stack([xy[n, ia], xy[n, ib]], 1), torch.stack([g[n, ia], g[n, ib]], 1),
                      torch.stack([alpha, 1 - alpha], -1)))
    if not found:
        return EdgePixels.none(device)
    return EdgePixels(*(torch.cat(parts) for parts in zip(*found)))
