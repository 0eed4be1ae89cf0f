"""Gray-code structured light: patterns from OpenCV, a vectorised decoder in torch.

The decoder follows the semantics of OpenCV's ``cv2.structured_light.GrayCodePattern``
(``decode`` / ``getProjPixel``), evaluated for every camera pixel at once:

- shadow mask: a pixel is usable only where ``|white - black| > black_threshold``;
- for each pattern/inverse pair, the bit is ``pattern > inverse``; a pair whose difference
  ``|pattern - inverse| < white_threshold`` makes the pixel unreliable (invalid);
- column bits come first, most significant bit first, then row bits; the Gray code is turned into
  a binary number; decoded coordinates outside the projector image are invalid.

A pixel whose bits do not all pass the threshold is invalid in OpenCV's sense, but some of its bits
still say where it is. Where only the finest ``m`` bits of an axis are unreliable (stripes finer than
the camera or a defocused lens resolves), the reliable ones name a block of ``2^m`` cells; where one
coarser bit is unreliable and flipping it names the neighbouring cell, the pixel sits on that
bit's stripe edge, between two cells. Such a pixel is *partly* decoded: :attr:`GrayDecoding.coarse_xy`
holds the centre of the cells its bits leave open and :attr:`GrayDecoding.spread` how many there are
per axis, so that calibration can place it from its neighbours instead of dropping it.

A shortened sequence keeps only the first (most significant) ``k`` of the ``n`` pattern pairs per
axis, ``bits=(kx, ky)``: they are exactly the Gray code of the block of ``2^(n-k)`` cells a pixel
falls in (the top bits of a Gray code are the Gray code of the top bits), so it decodes to the
block's centre. Such a map is only usable through a model that the coarse blocks pin down, one
homography per plane (:mod:`torchproj.calib.homography`).

Thresholds are in 8-bit units whatever the file depth (OpenCV's defaults: white 5, black 40).
Coordinates follow :mod:`torchproj.core.conventions` (a decoded value is the integer centre of the
LCD cell that lit the pixel).
"""

from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from ..core.checks import check, check_count, check_indices, check_number, check_pair, check_shape, check_window, is_number, is_whole
from ..core.choices import BLACK_THRESHOLD
from .maps import _check_projector_size, _recompute_near, check_projector_size, depth_edges

__all__ = ["CREASE_RATIO", "CURVE_RATIO", "STRIPE_MARGIN", "STRIPE_TOLERANCE", "WIDE_SHARE", "CellShares", "GrayDecoding", "band_pixels", "capture_noise", "cell_means", "cell_shares", "checker_patterns",
           "checker_shares", "graycode_patterns", "graycode_bits", "sequence_bits", "decode_gray", "refine_subpixel",
           "stripe_contrast", "stripe_shares"]

_EPS = 1e-3  # half a quantisation step is 0.5: this only guards float round-off of integer data


def graycode_bits(width: int, height: int) -> tuple[int, int]:
    """Number of column and row bits OpenCV uses for a projector of this size."""
    _check_projector_size(width, height)
    return math.ceil(math.log2(width)), math.ceil(math.log2(height))


def sequence_bits(width: int, height: int, bits: int | tuple[int, int] | None = None) -> tuple[int, int]:
    """The pattern pairs per axis a sequence shows: all of them (None), or the first ``bits``.

    Args:
        bits: None for the full sequence, one number for both axes (at most the axis's own count
            is used), or ``(kx, ky)``. At least 2 per axis: the blocks of a shortened sequence are
            read through a homography, and one bit shows a single block edge per axis, too few
            lines to pin one down (:func:`~torchproj.calib.fit_homography`).

    Returns:
        ``(kx, ky)``, each between 2 (or the axis's count, if smaller) and the axis's
        :func:`graycode_bits`.
    """
    nx, ny = graycode_bits(width, height)
    if bits is None:
        return nx, ny
    one = is_whole(bits)
    pair = (bits, bits) if one else tuple(bits) if isinstance(bits, (tuple, list)) else ()
    check(len(pair) == 2 and all(is_whole(b) for b in pair),
          f"bits must be a whole number, or a pair (kx, ky) of them, one per axis, got {bits!r}")
    kx, ky = (int(b) for b in pair)
    check(kx >= min(2, nx) and ky >= min(2, ny),
          f"bits must be at least 2 Gray-code bits per axis (a homography needs two block edges per axis), got {bits}")
    if one:
        # One number is what a user asks (--bits K): one that covers the whole sequence would silently
        # calibrate as if shortened, through a homography, for nothing.
        check(kx < max(nx, ny), f"bits {bits} shows the whole Gray-code sequence of a {width}x{height} projector "
                                f"({nx} x {ny} pattern pairs): leave bits out for it, or give fewer than {max(nx, ny)}")
        return min(kx, nx), min(ky, ny)
    check(kx <= nx and ky <= ny, f"bits must be at most ({nx}, {ny}) for a {width}x{height} projector, got {tuple(bits)}")
    return kx, ky


def graycode_patterns(width: int, height: int, bits: int | tuple[int, int] | None = None) -> torch.Tensor:
    """The Gray-code sequence of a projector, then white and black.

    Args:
        bits: keep only the first pattern pairs per axis (:func:`sequence_bits`); None: all.

    Returns:
        :math:`(2 (k_x + k_y) + 2, 1, H, W)` float patterns in {0, 1}: pattern/inverse pairs
        (columns first, most significant bit first), then all-white, then all-black. This is the
        order of a capture folder (``graycode_00.png`` ...).
    """
    nx, _ = graycode_bits(width, height)
    kx, ky = sequence_bits(width, height, bits)
    patterns = _opencv_graycode(width, height)
    patterns = list(patterns[:2 * kx]) + list(patterns[2 * nx:2 * (nx + ky)])
    stack = np.stack(patterns + [np.full((height, width), 255, np.uint8), np.zeros((height, width), np.uint8)])
    return torch.from_numpy(stack).float().div_(255.0)[:, None]


@functools.lru_cache(maxsize=4)
def _opencv_graycode(width: int, height: int) -> tuple[np.ndarray, ...]:
    """OpenCV's full pattern/inverse sequence, read-only: generated once per size, because a virtual
    calibration shows the same sequence in every state."""
    ok, patterns = cv2.structured_light.GrayCodePattern.create(width, height).generate()
    check(bool(ok), f"OpenCV could not generate Gray code for {width}x{height}")
    for p in patterns:
        p.flags.writeable = False
    return tuple(patterns)


@dataclass
class GrayDecoding:
    """Result of :func:`decode_gray`.

    Attributes:
        prj_xy: :math:`(H, W, 2)` float32 projector ``(x, y)`` per camera pixel, NaN where invalid.
        valid: :math:`(H, W)` bool, decoded and reliable.
        lit: :math:`(H, W)` bool, the shadow mask (``|white - black| > black_threshold``).
        contrast: :math:`(H, W)` white minus black, in [0, 1] units (a decoding confidence and the
            radiometric weight of this projector at each pixel); from a full sequence,
            :func:`~torchproj.calib.calibrate_projector` gives the mean over every capture that shows
            the pixel white and black (:func:`stripe_contrast`).
        block: ``(bx, by)`` projector cells per decoded value: ``(1, 1)`` for a full sequence; for
            a shortened one ``prj_xy`` is the centre of a block of that many cells.
        coarse_xy: :math:`(H, W, 2)` what the reliable bits say: ``prj_xy`` where valid, the centre of
            the cells the reliable bits leave open where the pixel is partly decoded (module
            docstring), NaN elsewhere. None for a shortened sequence.
        spread: :math:`(H, W, 2)` int, the cells per axis that ``coarse_xy`` leaves open (1 where
            valid, 0 where nothing is known). None for a shortened sequence.
    """

    prj_xy: torch.Tensor
    valid: torch.Tensor
    lit: torch.Tensor
    contrast: torch.Tensor
    block: tuple[int, int] = (1, 1)
    coarse_xy: torch.Tensor | None = None
    spread: torch.Tensor | None = None

    def above(self, black_threshold: float) -> "GrayDecoding":
        """This decoding with a higher shadow threshold (8-bit units, as :func:`decode_gray`'s): what
        :func:`decode_gray` gives with that ``black_threshold``, without decoding again (a pixel's
        bits read the same at any threshold; only which pixels count as lit changes)."""
        black_threshold = _check_threshold(black_threshold, "black_threshold")
        lit = self.lit & (self.contrast.abs() > (black_threshold + _EPS) / 255)
        valid = self.valid & lit
        prj_xy = torch.where(valid[..., None], self.prj_xy, float("nan"))
        coarse_xy = spread = None
        if self.coarse_xy is not None:
            coarse_xy = torch.where(lit[..., None], self.coarse_xy, float("nan"))
            spread = torch.where(lit[..., None], self.spread, 0)
        return GrayDecoding(prj_xy=prj_xy, valid=valid, lit=lit, contrast=self.contrast, block=self.block,
                            coarse_xy=coarse_xy, spread=spread)

    @property
    def partial(self) -> torch.Tensor:
        """:math:`(H, W)` bool, lit pixels partly decoded (some bits unreliable, yet a few cells named)."""
        if self.coarse_xy is None:
            return torch.zeros_like(self.valid)
        return torch.isfinite(self.coarse_xy).all(-1) & ~self.valid

    def counts(self) -> dict[str, int]:
        """How many of the pixels the projector visibly lights decoded fully, partly or not at all."""
        lit, full, partial = self.lit, self.valid & self.lit, self.partial & self.lit
        return {"lit": int(lit.sum()), "full": int(full.sum()), "partial": int(partial.sum()),
                "none": int(lit.sum() - full.sum() - partial.sum())}

    @property
    def lit_located_fraction(self) -> float:
        """Share of the lit pixels decoded fully or partly: those calibration can place."""
        counts = self.counts()
        return (counts["full"] + counts["partial"]) / max(counts["lit"], 1)

    @property
    def valid_fraction(self) -> float:
        """Share of the camera's pixels decoded."""
        return float(self.valid.float().mean())

    @property
    def lit_decoded_fraction(self) -> float:
        """Share of the pixels the projector visibly lights (``lit``) that decoded: what calibration
        could have had and got (a shadowed or unlit pixel is no loss)."""
        return float((self.valid & self.lit).sum()) / max(int(self.lit.sum()), 1)


def stripe_signs(position: torch.Tensor, bits: int, size: int) -> torch.Tensor:
    """What the last ``bits`` pattern pairs of an axis' Gray code show at projector coordinates
    ``position`` (cell centres at integers): +1 white, -1 black, 0 off the projector, most
    significant first, ``(..., bits)``. What a sharp point there sees as pattern minus inverse, in
    units of white minus black."""
    cell = torch.floor(position + 0.5).long()
    inside = (cell >= 0) & (cell < size)
    gray = cell.clamp(0, size - 1)
    gray = gray ^ (gray >> 1)
    shifts = torch.arange(bits - 1, -1, -1, device=position.device)
    sign = ((gray[..., None] >> shifts) & 1).to(position.dtype) * 2 - 1
    return sign * inside[..., None].to(position.dtype)


def _grey(images: torch.Tensor) -> torch.Tensor:
    """(N, C, H, W) or (N, H, W) -> (N, H, W); colour averaged (OpenCV decodes grey images)."""
    if images.dim() == 4:
        return images[:, 0] if images.shape[1] == 1 else images.mean(1)
    return images


def _grey_image(image: torch.Tensor) -> torch.Tensor:
    """One capture, (C, H, W) or (H, W) -> (H, W), as :func:`_grey`."""
    return _grey(image[None] if image.dim() <= 3 else image)[0]


def _grey_at(images: torch.Tensor, pixels: torch.Tensor) -> torch.Tensor:
    """(N, C, H, W) or (N, H, W) captures at the flat camera ``pixels`` (M,) -> (N, M) float, as :func:`_grey`."""
    return _grey(images.flatten(-2)[..., pixels, None]).float()[..., 0]


def _contrast(white: torch.Tensor, black: torch.Tensor) -> torch.Tensor:
    """White minus black of each pixel, grey :math:`(H, W)`: the span a pair's difference is read in."""
    return _grey_image(white).float() - _grey_image(black).float()


def _channels(image: torch.Tensor) -> torch.Tensor:
    """One capture, (H, W) or (C, H, W) -> (C, H, W) float."""
    return image.float()[None] if image.dim() == 2 else image.float()


def _pair_share(shown: torch.Tensor, span: torch.Tensor, mine: torch.Tensor) -> torch.Tensor:
    """The share ``f`` of a pixel's light on the cells a pattern pair lights otherwise than the
    pixel's cell, from the pair's captures :math:`(2, H, W)` (``mine``: +1 where the first pattern
    lights that cell, -1 where the second does): the difference is ``+-(1 - 2 f)`` of ``span``."""
    return ((1 - (shown[0] - shown[1]) / span * mine) / 2).clamp(0, 1)


def _check_cells(cells: torch.Tensor, camera) -> None:
    """Cells given per camera pixel: :math:`(H, W, 2)` integer indices."""
    check_indices(cells, "cells", [*camera, 2])


def _check_captures(patterns: torch.Tensor, white: torch.Tensor, black: torch.Tensor) -> None:
    """Captures as every reader of them takes them: float tensors (their sizes each reader checks
    against what it needs)."""
    for name, image in (("patterns", patterns), ("white", white), ("black", black)):
        check(isinstance(image, torch.Tensor) and image.is_floating_point(),
              f"{name} must be float captures in [0, 1] (8-bit images over 255), got "
              f"{image.dtype if isinstance(image, torch.Tensor) else type(image).__name__}")
    check(white.dim() in (2, 3) and white.shape == black.shape,
          f"white and black must be (H, W) or (C, H, W) captures of one size, got {tuple(white.shape)} and "
          f"{tuple(black.shape)}")


def check_full_sequence(patterns: torch.Tensor, white: torch.Tensor, black: torch.Tensor, prj_xy: torch.Tensor,
                        projector_size: tuple[int, int], who: str, why: str = "") -> tuple[int, int, torch.Tensor]:
    """What the estimators that read the captures beyond the decoder check first (:func:`~torchproj.calib.measure_blur`,
    :func:`~torchproj.calib.find_edge_pixels`): ``patterns`` hold the full Gray-code sequence of the
    projector, and ``prj_xy`` and ``white - black`` are the captures' size.

    Returns:
        the column and row bits ``(nx, ny)`` and the grey white minus black :math:`(H, W)` float.
    """
    _check_captures(patterns, white, black)
    width, height = check_projector_size(projector_size)
    nx, ny = graycode_bits(width, height)
    stack = patterns.dim() in (3, 4)
    check(stack and patterns.shape[0] == 2 * (nx + ny),
          f"{who} needs the full Gray-code sequence of a {width}x{height} projector: {2 * (nx + ny)} pattern/inverse "
          f"captures, got {patterns.shape[0] if stack else tuple(patterns.shape)}{why}")
    H, W = patterns.shape[-2:]
    check_shape(prj_xy, "prj_xy", [H, W, 2])
    contrast = _contrast(white, black)
    check_shape(contrast, "white - black", [H, W])
    return nx, ny, contrast


def _decode_axis(images: torch.Tensor, pairs: range, threshold: float):
    """Decode the Gray code that ``pairs`` of the pattern/inverse captures spell, MSB first.

    One pair at a time: a capture sequence is tens of full-size images, and whole-stack temporaries
    would cost more memory traffic (and memory) than the comparisons.

    Returns:
        :math:`(H, W)` int64 binary values (every bit read by its sign, reliable or not), and int16
        maps of the first unreliable pair's index (``len(pairs)`` where none) and of the number of
        unreliable pairs (difference below ``threshold``, [0, 1] units).
    """
    shape, device = images.shape[-2:], images.device
    binary = torch.zeros(shape, dtype=torch.bool, device=device)
    value = torch.zeros(shape, dtype=torch.int32, device=device)
    first_bad = torch.full(shape, len(pairs), dtype=torch.int16, device=device)
    bad = torch.zeros(shape, dtype=torch.int16, device=device)
    for i, k in enumerate(pairs):  # b_i = b_{i-1} xor g_i; value accumulates MSB first
        pair = _grey(images[2 * k:2 * k + 2])
        diff = pair[0] - pair[1]
        binary ^= diff > 0
        value.mul_(2).add_(binary)
        weak = ~(diff.abs_() >= threshold)  # so written, a NaN capture's bit is weak, not read as a sign
        bad += weak
        first_bad.masked_fill_(weak & (first_bad == len(pairs)), i)
    return value.to(torch.int64), first_bad, bad


# At most this many finest bits of an axis may be unreliable for a pixel to count as partly decoded:
# a block of 8 cells is still pinned by its neighbours' fit (refine_subpixel); wider ones are guesses.
_MAX_OPEN_BITS = 3


def _open_cells(value: torch.Tensor, first_bad: torch.Tensor, bad: torch.Tensor, bits: int):
    """What an axis' reliable bits say (module docstring): the centre of the cells they leave open
    :math:`(H, W)` float and how many :math:`(H, W)` int (0 where they name no contiguous cells)."""
    first, bad = first_bad.long(), bad.long()
    suffix = (bad == bits - first) & (bad <= _MAX_OPEN_BITS)  # all bits from the first unreliable one on
    width = torch.where(suffix, 1 << bad.clamp(max=_MAX_OPEN_BITS), 1)
    start = torch.div(value, width, rounding_mode="floor") * width
    # One unreliable coarser bit: flipping its Gray bit flips every binary bit from it down. The two
    # readings are neighbours exactly when the pixel sits on that bit's stripe edge.
    other = value ^ ((1 << (bits - first).clamp(min=0, max=bits)) - 1)
    edge = (bad == 1) & ~suffix & ((other - value).abs() == 1)
    start = torch.where(edge, torch.minimum(value, other), start)
    width = torch.where(edge, 2, width)
    known = suffix | edge | (bad == 0)
    centre = start.to(torch.float32) + (width - 1).to(torch.float32) / 2
    return centre, torch.where(known, width, 0)


def check_ratio(value, name: str, one: str) -> float:
    """How many times better one fit must be than another to be taken: at least 1 (``one`` says what 1
    means), ``math.inf`` for never."""
    check(is_number(value) and value >= 1,
          f"{name} must be >= 1 ({one}), got {value!r}")
    return float(value)


def _check_threshold(value, name: str) -> float:
    """A threshold on a difference of captures, in 8-bit units: at most 255 apart, so a threshold there
    keeps no pixel, which was then reported as a projector that lit nothing."""
    value = check_number(value, name)
    check(value < 255, f"{name} is in 8-bit units and must be under 255 (no difference of captures reaches it), "
                       f"got {value:g}")
    return value


def decode_gray(patterns: torch.Tensor, white: torch.Tensor, black: torch.Tensor, projector_size: tuple[int, int],
                white_threshold: float = 5, black_threshold: float = BLACK_THRESHOLD,
                bits: int | tuple[int, int] | None = None) -> GrayDecoding:
    """Decode a Gray-code capture into per-pixel projector coordinates.

    Args:
        patterns: :math:`(N, H, W)` or :math:`(N, C, H, W)` captures of the pattern/inverse pairs,
            in [0, 1], in :func:`graycode_patterns` order (N = 2 (k_x + k_y)).
        white: :math:`(H, W)` or :math:`(C, H, W)` capture of the all-white image.
        black: same, all-black.
        projector_size: ``(width, height)`` of the projector.
        white_threshold: minimum ``|pattern - inverse|`` (8-bit units) for a reliable bit.
        black_threshold: minimum ``|white - black|`` (8-bit units) for a lit pixel.
        bits: the pattern pairs per axis the sequence showed (:func:`sequence_bits`); None: all.

    Returns:
        a :class:`GrayDecoding`; with a shortened sequence, ``prj_xy`` holds the centre of the cells
        of the decoded block that lie inside the projector image.
    """
    _check_captures(patterns, white, black)
    width, height = check_projector_size(projector_size)
    nx, ny = graycode_bits(width, height)
    kx, ky = sequence_bits(width, height, bits)
    white_threshold = _check_threshold(white_threshold, "white_threshold")
    black_threshold = _check_threshold(black_threshold, "black_threshold")
    white, black = _grey_image(white), _grey_image(black)
    # The thresholds are in 8-bit units over 255: captures in 0-255 would pass nearly every pixel as lit
    # and every bit as reliable. The white capture is the brightest, and one image is cheap to read.
    brightest = float(white.max()) if white.numel() else 0.0
    check(brightest <= 1.0 + 1e-6, f"white must lie in [0, 1] (8-bit captures over 255), got values up to "
                                   f"{brightest:.4g}")
    sizes = check_shape(patterns[:, 0] if patterns.dim() == 4 else patterns, "patterns", ["N", "H", "W"])
    check(sizes["N"] == 2 * (kx + ky),
          f"patterns must hold {2 * (kx + ky)} images for a {width}x{height} projector "
          f"({kx} column + {ky} row bits, each a pattern/inverse pair), got {sizes['N']}")
    check_shape(white, "white", [sizes["H"], sizes["W"]])
    check_shape(black, "black", [sizes["H"], sizes["W"]])

    threshold = (white_threshold - _EPS) / 255  # [0, 1] units, as the captures
    axes = [_decode_axis(patterns, range(kx), threshold), _decode_axis(patterns, range(kx, kx + ky), threshold)]
    codes = [value for value, _, _ in axes]
    reliable = (axes[0][2] == 0) & (axes[1][2] == 0)
    block = (2 ** (nx - kx), 2 ** (ny - ky))
    # A block index names cells [b * block, (b + 1) * block - 1], cut at the image edge; its
    # coordinate is the centre of the cells inside (the cell itself for a full sequence).
    first = [codes[0] * block[0], codes[1] * block[1]]
    centre = [(f + torch.clamp(f + b, max=size) - 1).to(torch.float32) / 2
              for f, b, size in zip(first, block, (width, height))]
    contrast = white - black
    lit = contrast.abs() > (black_threshold + _EPS) / 255
    inside = (first[0] < width) & (first[1] < height)
    valid = lit & reliable & inside
    _warn_if_codes_beyond(lit & reliable, inside, first, projector_size)
    prj_xy = torch.stack(centre, -1)
    prj_xy[~valid] = float("nan")
    coarse_xy = spread = None
    if block == (1, 1):
        (cx, sx), (cy, sy) = (_open_cells(*axis, bits) for axis, bits in zip(axes, (kx, ky)))
        spread = torch.stack([sx, sy], -1).to(torch.int16)
        known = lit & (sx > 0) & (sy > 0) & (cx < width) & (cy < height)
        spread[~known] = 0
        coarse_xy = torch.where(valid[..., None], prj_xy, torch.stack([cx, cy], -1))
        coarse_xy[~(known | valid)] = float("nan")
    return GrayDecoding(prj_xy=prj_xy, valid=valid, lit=lit, contrast=contrast, block=block, coarse_xy=coarse_xy,
                        spread=spread)


# Light measured past cells n +- 1 (CellShares.outside) over this share is a footprint wider than
# the two edges of n describe (defocus): noise alone stays below 0.035 on the virtual rig (99th
# percentile). Calibration keeps such a partly decoded pixel's open cells rather than its means, and
# the area footprint leaves its row's split alone (docs/accuracy.md "The ceiling").
WIDE_SHARE = 0.05
_BEYOND = 0.05  # a share of reliably decoded pixels beyond the projector that noise does not explain


def _warn_if_codes_beyond(decoded: torch.Tensor, inside: torch.Tensor, first: list, projector_size) -> None:
    """Codes past the projector's edge on many pixels mean the sequence came from another size: with
    the same bit count (1000x700 read as 1024x768) the image count matches and nothing else says so."""
    outside = decoded & ~inside
    share = float(outside.sum()) / max(int(decoded.sum()), 1)
    if share > _BEYOND:
        reach = [int(f[decoded].max()) + 1 for f in first]
        warnings.warn(f"{share:.0%} of the decoded pixels read codes beyond a {projector_size[0]}x{projector_size[1]} "
                      f"projector (up to {reach[0]}x{reach[1]}): is that the size that showed the sequence? Check "
                      "--projector (or sequence.json)", stacklevel=3)


@dataclass
class CellShares:
    """How each decoded camera pixel's light is shared across the edges of its cell, as its Gray-code
    differences measure it (:func:`cell_shares`).

    A camera pixel covers an area, so its light often comes from its decoded cell ``n`` and a
    neighbour. Each cell edge is the stripe edge of exactly one pattern pair (neighbouring Gray codes
    differ in one bit), and that pair's difference, in units of white minus black, is ``+-1`` where
    all the light came from one side and ``1 - 2 f`` where a share ``f`` came from the other side.
    Exactly, ``f`` is the share of the pixel's light from the cells on which that pair's stripe
    differs from cell ``n``'s; for a footprint within a cell of ``n``, the share from across the edge.

    Attributes:
        cell: :math:`(H, W, 2)` int32 cell ``n = (x, y)`` the shares are about: the decoded cell of
            a fully decoded pixel, or the cell :func:`cell_shares` was given (for a partly decoded
            pixel, the nearest cell of its refined map); -1 where none.
        across: :math:`(H, W, 2, 2)` float32, per axis ``(x, y)``: ``f`` of the edge towards cell
            ``n - 1`` and of the edge towards ``n + 1``; NaN where the pixel has no cell or the
            edge is the projector's border (nothing lights the pixel from beyond it).
        outside: :math:`(H, W, 2)` float32, per axis the largest ``f`` of the axis' other pairs: light
            from beyond cells ``n - 1`` and ``n + 1`` (0 up to the captures' noise for a footprint
            within a cell of ``n``; a tenth and more under defocus, over :data:`WIDE_SHARE`); NaN
            where the pixel has no cell.
        checker: optional :math:`(H, W)` float32, the share of the pixel's light on the cells whose
            parity ``(x + y) mod 2`` differs from cell ``n``'s, measured by a checkerboard pair
            (:func:`checker_shares`); NaN where the pixel has no cell. Gray code, constant along one
            projector axis at a time, measures how a pixel's light splits along each axis but not
            how the two splits combine; this one pair tells a footprint leaning along one diagonal
            of a block of cells from one leaning along the other. None: not measured.
        band: optional :math:`(M,)` int64 flat camera pixels (row-major) beside an outline, whose
            every pattern pair's share is kept in ``band_white`` (:func:`band_pixels`); None: none kept.
        band_white: :math:`(M, B)` float32 with ``band``, the share of each such pixel's light on the
            cells that pattern pair ``k`` (``x`` pairs, then ``y``, most significant first) shows
            white in its first image (:func:`stripe_shares`). Beside an outline a pixel's light falls
            on cells that no parallelogram about its cell holds; each pair says how it splits.
    """

    cell: torch.Tensor
    across: torch.Tensor
    outside: torch.Tensor
    checker: torch.Tensor | None = None
    band: torch.Tensor | None = None
    band_white: torch.Tensor | None = None

    def means(self) -> torch.Tensor:
        """:math:`(H, W, 2)` projector ``(x, y)``: the mean cell centre of each pixel's light,
        ``n - f_lower + f_upper`` per axis; NaN where the pixel has no cell.

        Fitted over neighbouring pixels (:func:`refine_subpixel`), these means place a pixel
        between cells two to four times as closely as the integer cells do (0.042 against 0.117
        cells rms on a noisy virtual plane, ``tests/calib/test_graycode.py``): the cell staircase is
        quantised to whole cells, the means only by the pixel's own shares. Footprints wider than a
        cell or two (steep faces, defocus) reach cells the two edges do not see, and their mean
        leans towards ``n``; the fit is unbiased on a symmetric footprint all the same. A decoder
        that picked the neighbour (the pixel straddles the edge about evenly) gives the same mean.
        """
        shares = torch.nan_to_num(self.across)
        mean = self.cell.to(torch.float32) - shares[..., 0] + shares[..., 1]
        return torch.where((self.cell >= 0).all(-1, keepdim=True), mean, float("nan"))

    def check(self, camera: tuple[int, int], projector_size: tuple[int, int], where: str) -> None:
        """Shapes for a ``(H, W)`` camera, cells on a ``(width, height)`` projector, shares in [0, 1]."""
        check_shape(self.cell, f"{where}: cell shares' cell", [*camera, 2])
        check_shape(self.across, f"{where}: cell shares' across", [*camera, 2, 2])
        check_shape(self.outside, f"{where}: cell shares' outside", [*camera, 2])
        # Reductions, not masks: these run on every build, on every state and projector.
        x, y = self.cell[..., 0], self.cell[..., 1]
        check(x.numel() == 0 or (int(self.cell.min()) >= -1 and int(x.max()) < projector_size[0]
                                 and int(y.max()) < projector_size[1]),
              f"{where}: cell shares name cells outside the {projector_size[0]}x{projector_size[1]} projector")
        if self.checker is not None:
            check_shape(self.checker, f"{where}: cell shares' checker", list(camera))
        check((self.band is None) == (self.band_white is None),
              f"{where}: cell shares need both band and band_white, or neither")
        if self.band is not None:
            check(self.band.dim() == 1 and not self.band.is_floating_point(),
                  f"{where}: cell shares' band must be a 1-D array of integer camera pixels")
            check_shape(self.band_white, f"{where}: cell shares' band_white", [self.band.numel(), "B"])
            check(self.band.numel() == 0 or (int(self.band.min()) >= 0 and int(self.band.max()) < camera[0] * camera[1]),
                  f"{where}: cell shares' band names a pixel outside the {camera[1]}x{camera[0]} camera")
            check(bool(torch.isfinite(self.band_white).all()), f"{where}: cell shares' band_white must be finite")
        for name, share in (("across", self.across), ("outside", self.outside), ("checker", self.checker),
                            ("band_white", self.band_white)):
            if share is None or share.numel() == 0:
                continue
            low, high = torch.nan_to_num(share, nan=0.0, posinf=0.0, neginf=0.0).aminmax()  # finite ones only
            check(float(low) >= 0 and float(high) <= 1, f"{where}: cell shares' {name} must lie in [0, 1]")


def cell_shares(patterns: torch.Tensor, white: torch.Tensor, black: torch.Tensor, decoding: GrayDecoding,
                projector_size: tuple[int, int], cells: torch.Tensor | None = None) -> CellShares:
    """The share of each fully decoded pixel's light from across each edge of its cell
    (:class:`CellShares`), from the pattern pairs whose stripe edges they are; or of each pixel's
    light across the edges of a cell it is given.

    Calibration fits its maps to their means (:meth:`CellShares.means`) and the ``area`` transport
    footprint fits its rows to them (:func:`~torchproj.transport.build_transport`). A partly decoded
    pixel has no decoded cell, but its captures measure its light across any cell's edges all the
    same: a pair whose stripe its footprint straddles evenly shows a share near one half, which is
    why the decoder could not read that bit. :func:`~torchproj.calib.calibrate_projector` asks for
    those pixels' shares about the nearest cell of their refined map.

    Args:
        patterns, white, black: the full-sequence captures :func:`decode_gray` read.
        decoding: its result.
        projector_size: ``(width, height)``.
        cells: optional :math:`(H, W, 2)` integer cells ``(x, y)`` to measure each pixel's shares
            about, -1 where none; None: each fully decoded pixel's decoded cell.
    """
    check(isinstance(decoding, GrayDecoding), f"decoding must be decode_gray's GrayDecoding of these captures, got "
                                              f"{type(decoding).__name__}")
    check(decoding.block == (1, 1), "cell shares need the full Gray-code sequence (decoding.block is "
                                    f"{decoding.block}): a shortened one shows no stripe at the cells' edges")
    nx, ny, contrast = check_full_sequence(patterns, white, black, decoding.prj_xy, projector_size, "cell_shares")
    span = contrast.clamp_min(_EPS)
    if cells is None:
        valid = decoding.valid
        cells = torch.where(valid[..., None], torch.nan_to_num(decoding.prj_xy).round(), -1).to(torch.int32)
    else:
        _check_cells(cells, decoding.valid.shape)
        valid = (cells >= 0).all(-1)
        size = torch.tensor(projector_size, device=cells.device)
        check(bool((cells[valid] < size).all()),
              f"cells name cells outside the {projector_size[0]}x{projector_size[1]} projector; -1 marks a pixel "
              "without one")
        cells = torch.where(valid[..., None], cells, -1).to(torch.int32)
    # Only the pixels with a cell are measured, gathered from each pair (the same values, element by
    # element, as a pass over the whole frame): on the default scene about half the frame, and a
    # handful of pixels where calibration measures its partly decoded ones again.
    pixels = torch.nonzero(valid.reshape(-1))[:, 0]
    across = torch.full((*valid.shape, 2, 2), float("nan"), device=valid.device)
    outside = torch.full((*valid.shape, 2), float("nan"), device=valid.device)
    measured, far_shares = _shares_at(patterns, span.reshape(-1)[pixels], cells.reshape(-1, 2)[pixels], pixels,
                                      (nx, ny), projector_size)
    across.view(-1, 2, 2)[pixels] = measured
    outside.view(-1, 2)[pixels] = far_shares
    return CellShares(cells, across, outside)


def band_pixels(prj_xy: torch.Tensor, reach: int = 2, depth: torch.Tensor | None = None) -> torch.Tensor:
    """:math:`(M,)` flat camera pixels of a map :math:`(H, W, 2)` (NaN where unknown) within ``reach``
    pixels of a depth edge (:func:`~torchproj.calib.maps.depth_edges`) or of a pixel the map does not
    know: where a pixel may see two surfaces, or one surface and nothing, and its light falls where
    no parallelogram about its own coordinate puts it. ``depth``: :math:`(H, W)`
    ``depth_edges(prj_xy)`` where the caller has it; None: computed here."""
    check_shape(prj_xy, "prj_xy", ["H", "W", 2])
    check_count(reach, "reach (pixels)", 0)
    known = torch.isfinite(prj_xy).all(-1)
    depth = depth_edges(prj_xy) if depth is None else depth
    check_shape(depth, "depth", list(known.shape))
    beside = (depth | ~known).float()[None, None]
    near = F.max_pool2d(beside, 2 * reach + 1, stride=1, padding=reach)[0, 0] > 0
    return torch.nonzero((known & near).reshape(-1))[:, 0]


def stripe_shares(patterns: torch.Tensor, span: torch.Tensor, pixels: torch.Tensor, bits: tuple[int, int]) -> torch.Tensor:
    """:math:`(M, B)` the share of each flat camera pixel's light (``pixels`` :math:`(M,)`, white
    minus black ``span`` :math:`(H, W)`) on the cells each of the full sequence's ``bits = (x, y)``
    pattern pairs shows white in its first image, ``x`` pairs first: ``(1 + d) / 2`` of the pair's
    difference ``d`` in units of ``span``, clipped to [0, 1] (:attr:`CellShares.band_white`)."""
    sizes = check_shape(span, "span", ["H", "W"])
    check_indices(pixels, "pixels (flat camera pixels)", ["M"])
    bits = check_pair(bits, "bits", "(column bits, row bits)")
    check(isinstance(patterns, torch.Tensor) and patterns.dim() in (3, 4) and patterns.shape[0] >= 2 * sum(bits)
          and tuple(patterns.shape[-2:]) == (sizes["H"], sizes["W"]),
          f"patterns must hold the {2 * sum(bits)} pattern/inverse captures of {bits} bits at the span's size, got "
          f"{tuple(patterns.shape) if isinstance(patterns, torch.Tensor) else type(patterns).__name__}")
    out = torch.empty(pixels.numel(), bits[0] + bits[1], device=pixels.device)
    first = -torch.ones(pixels.numel(), device=pixels.device)  # the first image lights the cells in question
    width = span.reshape(-1)[pixels].clamp_min(_EPS)
    for k in range(bits[0] + bits[1]):  # one pair at a time, as the decoder
        out[:, k] = _pair_share(_grey_at(patterns[2 * k:2 * k + 2], pixels), width, first)
    return out


def _shares_at(patterns: torch.Tensor, span: torch.Tensor, cells: torch.Tensor, pixels: torch.Tensor,
               bits: tuple[int, int], projector_size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`cell_shares` at the flat camera ``pixels`` :math:`(N,)`, each with its white minus black
    ``span`` :math:`(N,)` and its cell ``cells`` :math:`(N, 2)`: ``across`` :math:`(N, 2, 2)` and
    ``outside`` :math:`(N, 2)`."""
    n = pixels.numel()
    across = torch.empty((n, 2, 2), device=pixels.device)
    outside = torch.empty((n, 2), device=pixels.device)
    for axis, (axis_bits, first, size) in enumerate(((bits[0], 0, projector_size[0]), (bits[1], bits[0], projector_size[1]))):
        cell = cells[:, axis].to(torch.int32).clamp(0, size - 1)  # int32: half the bytes of each pass below
        gray = cell ^ (cell >> 1)
        edges = []  # per side: the pair whose stripe edge it is, or -1 at the projector's border
        for step in (-1, 1):
            other = cell + step
            border = (other < 0) | (other >= size)  # the projector lights nothing past its edge
            flip = (gray ^ (other ^ (other >> 1))).clamp_min(1)  # the one Gray bit the two cells differ in
            bit = torch.log2(flip.to(torch.float32)).round().to(torch.int32)
            edges.append(torch.where(border, -1, axis_bits - 1 - bit))
        found = [torch.zeros(n, device=pixels.device) for _ in edges]
        far = torch.zeros(n, device=pixels.device)
        for i in range(axis_bits):  # one pair at a time, as the decoder: the stack is tens of images
            shown = _grey_at(patterns[2 * (first + i):2 * (first + i) + 2], pixels)
            mine = ((gray >> (axis_bits - 1 - i)) & 1).to(torch.float32) * 2 - 1  # what pair i shows on cell n
            share = _pair_share(shown, span, mine)
            for pair, seen in zip(edges, found):
                torch.where(pair == i, share, seen, out=seen)
            far = torch.where((edges[0] == i) | (edges[1] == i), far, torch.maximum(far, share))
        for side, (pair, seen) in enumerate(zip(edges, found)):
            across[:, axis, side] = torch.where(pair >= 0, seen, float("nan"))
        outside[:, axis] = far
    return across, outside


# A pattern pair counts as one more capture of white and of black for a pixel whose cell lies at least
# this many cells inside one of the pair's stripes, so that its whole footprint does (a camera pixel of
# up to about four cells, a steep face, a defocused lens of up to ~4 cells).
STRIPE_MARGIN = 2
# A pair whose lit side reads, over the pixels well inside its stripes, more than this share of white
# minus black away from the white capture (or its dark side from the black one) is no such capture.
# On the virtual rig every pair reads within noise (within 0.002). On the real chessboard captures
# (../shared/data/procam_chessboard) none does: lit stripes read 0.86-0.99 of white and dark ones
# 0.02-0.12 of it, less the finer the stripe (the lenses blur them, the projector scatters light),
# and averaging them would bias the weight by up to 14%; there the weight stays white minus black.
STRIPE_TOLERANCE = 0.01


def capture_noise(patterns: torch.Tensor, white: torch.Tensor, black: torch.Tensor, pixels: int = 30_000) -> float:
    """The camera noise of a pixel's white minus black, as a share of it: the median over the lit
    pixels (white minus black over the shadow threshold), about ``pixels`` of the camera's read
    evenly (every pixel of a smaller camera): 12 ms for a sequence of 40 captures of 1280 x 1024.

    A pattern and its inverse light every cell once between them, so the sum of their captures is
    the same for every pair, white plus black, whatever the stripes' blur or the projector's
    scatter: light adds. How the sums of a sequence's pairs spread about their mean is their
    captures' noise alone, and for read noise, and for shot noise (whose variance follows the light,
    and ``P + P'`` holds as much as ``W + B``), its variance is that of ``W - B``, the weight of
    every transport row. (Against ``W + B`` itself the misfit would carry the one draw of noise
    that white and black share across all the pairs, and its median over pixels read a tenth low.)
    Averaging frames (``torchproj capture --frames N``) divides it by the square root of N. A
    camera that is not linear (a gamma curve, saturated white) adds its own spread, and the figure
    reads high.

    Args:
        patterns: :math:`(2K, C, H, W)` or :math:`(2K, H, W)` pattern/inverse captures, pair by pair.
        white, black: :math:`(C, H, W)` or :math:`(H, W)` captures.

    Returns:
        the median share, or NaN where no pixel is lit. A colour camera's channels are read as their
        mean, as the decoder reads them: each channel alone carries more noise than their mean.
    """
    _check_captures(patterns, white, black)
    check_count(pixels, "pixels (read evenly over the camera)")
    check(patterns.dim() in (3, 4) and patterns.shape[0] % 2 == 0 and patterns.shape[0] >= 4,
          f"patterns must be two or more pattern/inverse pairs (2K, [C,] H, W), got {tuple(patterns.shape)}")
    contrast = _contrast(white, black).reshape(-1)
    probed = torch.arange(0, contrast.numel(), max(1, contrast.numel() // pixels), device=contrast.device)
    probed = probed[contrast[probed] > (BLACK_THRESHOLD + _EPS) / 255]
    if not probed.numel():
        return float("nan")
    shown = _grey_at(patterns, probed)  # (2K, M)
    spread = (shown[0::2] + shown[1::2]).std(0)  # over the pairs, (M,)
    return float((spread / contrast[probed]).median())


def stripe_contrast(patterns: torch.Tensor, white: torch.Tensor, black: torch.Tensor, cells: torch.Tensor,
                    projector_size: tuple[int, int], margin: int = STRIPE_MARGIN) -> torch.Tensor:
    """White minus black of each pixel, :math:`(C, H, W)`, measured over every capture that shows it.

    The white and the black capture each hold one frame of camera noise, and their difference is the
    weight of every transport row (:mod:`torchproj.transport.build`): on a camera with 20,000
    electrons of full well and 8 bits, about 1.5% rms of it. But each Gray-code pair shows the
    pixel's footprint all white in one capture and all black in the other wherever the footprint
    lies inside one of the pair's stripes, which it does for all but the few finest pairs: those
    captures are further frames of white and black. Averaging them (a pixel lies ``margin`` cells
    inside about 14 of a 1024x768 projector's 20 pairs: none of the two finest per axis, half of the
    third) cuts the weight's noise two- to fourfold, from captures calibration already took. Our choice, not the paper's (it weights by geometry).

    A pixel counts a pair only where the pair shows it no light from across (its share, as
    :class:`CellShares` reads it, under :data:`WIDE_SHARE`): a pixel on an object's outline also
    sees the surface behind, whose cells may lie in another stripe. A pair is used only where its lit
    and dark sides read, over the pixels inside its stripes, as
    white and black do (medians within :data:`STRIPE_TOLERANCE` of white minus black): on a real
    bench the lenses blur stripes and the projector scatters light, and then averaging would bias
    the weight instead of denoising it (on the real chessboard captures no pair qualifies, and this
    returns white minus black).

    Args:
        patterns, white, black: the full-sequence captures :func:`decode_gray` read; colour or grey.
        cells: :math:`(H, W, 2)` integer cell ``(x, y)`` of each pixel's light (its decoded cell,
            or :attr:`CellShares.cell`), -1 where none: such pixels keep white minus black.
        projector_size: ``(width, height)``.
        margin: cells between a pixel's cell and a stripe's edge for that pair to count.

    Returns:
        :math:`(C, H, W)` float32 (C = 1 for grey captures): mean lit minus mean dark reading.
    """
    _check_cells(cells, ("H", "W"))  # the captures' size, which check_full_sequence holds them to
    nx, ny, contrast = check_full_sequence(patterns, white, black, cells.float(), projector_size, "stripe_contrast")
    check_count(margin, "margin (cells between a pixel's cell and a stripe's edge)", 0)
    raw = _channels(white) - _channels(black)  # (C, H, W)
    total = raw.clone()  # white minus black summed over the frames that show it
    grey_black = _grey_image(black).float()
    count = torch.ones(contrast.shape, device=contrast.device)
    span = contrast.clamp_min(_EPS)
    # The pairs' medians are read on every 16th pixel: a hundred thousand on a full-size camera.
    sample = torch.zeros(contrast.numel(), dtype=torch.bool, device=contrast.device)
    sample[::16] = True
    sample = sample.view(contrast.shape) & (contrast > 0)
    for axis, (bits, first) in enumerate(((nx, 0), (ny, nx))):
        cell = cells[..., axis].to(torch.int32)
        has = (cell >= 0) & (contrast > 0)
        gray = cell.clamp_min(0) ^ (cell.clamp_min(0) >> 1)
        for i in range(bits):
            bit = bits - 1 - i
            period = 2 << bit  # a Gray bit's stripes are 2^(bit+1) cells wide, from cell 2^bit on
            # The cell's place in its stripe pair: the remainder by a power of two, as a bit mask (two's
            # complement keeps it right below cell 2^bit); ``margin`` cells or more from either edge.
            offset = (cell - (1 << bit)) & (period - 1)
            inside = has & (offset >= margin) & (offset < period - margin)
            # The medians on the probed pixels alone: each pair's test reads a sixteenth of the image. One
            # index for the four gathers (index_select; boolean indexing found the same pixels four times).
            at = torch.nonzero((inside & sample).reshape(-1))[:, 0]
            if not at.numel():
                continue
            shown = patterns[2 * (first + i):2 * (first + i) + 2]
            shown = shown[:, None] if shown.dim() == 3 else shown  # (2, C, H, W)
            lit_first = ((gray.reshape(-1).index_select(0, at) >> bit) & 1) > 0  # the first pattern lights the cell
            # Image by image: index_select along a tensor's last dimension gathers several times slower.
            on_grey, off_grey = torch.stack([image.reshape(-1).index_select(0, at) for image in shown.flatten(0, 1)]
                                            ).view(2, -1, at.numel()).float().mean(1)  # (n,) each, per pattern
            dark, width = grey_black.reshape(-1).index_select(0, at), span.reshape(-1).index_select(0, at)
            gain = ((torch.where(lit_first, on_grey, off_grey) - dark) / width).median()
            leak = ((torch.where(lit_first, off_grey, on_grey) - dark) / width).median()
            if max(abs(float(gain) - 1), abs(float(leak)), abs(float(gain - leak) - 1)) > STRIPE_TOLERANCE:
                continue
            sign = ((gray >> bit) & 1).float() * 2 - 1  # +1 where the first pattern lights the pixel's cell
            difference = (shown[0].float() - shown[1].float()).mul_(sign)  # lit minus dark, (C, H, W)
            # A pixel on an outline sees two surfaces, far apart on the projector: the stripe about its
            # cell may hold one and not the other. Its pair then reads a share across (_pair_share),
            # and it counts only where that share is within the noise (under WIDE_SHARE).
            inside &= difference.mean(0) > (1 - 2 * WIDE_SHARE) * span
            total += difference.mul_(inside)
            count += inside
    return total / count


def checker_patterns(width: int, height: int) -> torch.Tensor:
    """A checkerboard of single cells and its inverse, :math:`(2, 1, H, W)` in [0, 1]: cell ``(x, y)``
    lit in the first where ``x + y`` is even. Shown after the Gray code, its pair measures the share
    of each pixel's light that :attr:`CellShares.checker` holds (:func:`checker_shares`)."""
    _check_projector_size(width, height)
    ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    even = ((xs + ys) % 2 == 0).to(torch.float32)
    return torch.stack([even, 1 - even])[:, None]


def checker_shares(pair: torch.Tensor, white: torch.Tensor, black: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """The share of each pixel's light on the cells whose parity differs from its cell's, from the
    captures of :func:`checker_patterns` (:attr:`CellShares.checker`).

    As for a Gray-code pair (:class:`CellShares`), the pair's difference in units of white minus
    black is ``+-1`` where all the light came from cells of one parity and ``1 - 2 f`` where a
    share ``f`` came from the other.

    Args:
        pair: :math:`(2, C, H, W)` captures of the checkerboard and its inverse.
        white, black: :math:`(C, H, W)` the all-white and all-black captures.
        cells: :math:`(H, W, 2)` integer cells ``(x, y)`` the shares are about, -1 where none
            (:attr:`CellShares.cell`).

    Returns:
        :math:`(H, W)` float32 in [0, 1], NaN where the pixel has no cell.
    """
    _check_captures(pair, white, black)
    check_shape(pair, "checker pair", [2, *white.shape])
    _check_cells(cells, white.shape[-2:])
    span = _contrast(white, black).clamp_min(_EPS)
    shown = _grey(pair).float()
    valid = (cells >= 0).all(-1)
    mine = 1 - 2 * ((cells[..., 0].long() + cells[..., 1].long()) % 2).to(torch.float32)  # +1: lit in the first
    return torch.where(valid, _pair_share(shown, span, mine), float("nan"))


def cell_means(patterns: torch.Tensor, white: torch.Tensor, black: torch.Tensor, decoding: GrayDecoding,
               projector_size: tuple[int, int]) -> torch.Tensor:
    """The mean cell centre of the light each fully decoded pixel saw, from its Gray-code differences
    (:meth:`CellShares.means` of :func:`cell_shares`, which says how).

    Args:
        patterns, white, black: the full-sequence captures :func:`decode_gray` read.
        decoding: its result.
        projector_size: ``(width, height)``.

    Returns:
        :math:`(H, W, 2)` projector ``(x, y)``: the mean where the pixel decoded fully, NaN elsewhere.
    """
    return cell_shares(patterns, white, black, decoding, projector_size).means()


# Camera pixels per strip of rows in refine_subpixel's float64 window sums: bounds their memory
# (tens of float64 maps) and the size of the running sums.
_REFINE_STRIP = 256

# How many times better a window beside the pixel must fit its values than the window centred on it
# before refine_subpixel takes it. A fit evaluated at its window's side is noisier than one at its
# centre (about three times the variance for a 7 x 7 plane), so on a smooth face the centred window
# should win unless the data say otherwise. Our choice, measured against the simulator's truth
# (python benchmarks/refine.py; map error in cells rms, beside box_positions' creases / on its faces
# away from creases and edges / the same on box_cylinders): the centred window only 0.321 / 0.024 /
# 0.037; ratio 1 (the best fit wins) 0.050 / 0.039 / 0.062; 1.5 0.047 / 0.022 / 0.045; 2 0.051 /
# 0.021 / 0.038; 3 0.069 / 0.021 / 0.038.
CREASE_RATIO = 2.0

# How many times better the quadratic through the centred window must fit its values than the centred
# plane before refine_subpixel takes it. Where camera pixels span a cell or more and an object spans a
# few dozen pixels (a small sphere before a coarse camera), the map curves within one window and the
# plane's value at the centre misses by a fifth of a cell; a quadratic has twice a plane's variance at
# the centre, so it must earn its place. Our choice, measured like CREASE_RATIO against the simulator's
# truth (python benchmarks/refine.py --vary curve; map error in cells rms inside suite-1206-6's
# ellipsoid / inside suite-1-14's spheres / near box_cylinders' edges / near suite-1206-5's planes'
# edges): planes only 0.208 / 0.161 / 0.125 / 0.098; ratio 1 0.018 / 0.031 / 0.115 / 0.101; 1.5
# 0.020 / 0.036 / 0.115 / 0.100; 2 0.055 / 0.050 / 0.117 / 0.099; 3 0.100 / 0.072 / 0.122 / 0.098.
CURVE_RATIO = 1.5

# refine_subpixel fits the quadratic only where the bend that the windows beside a pixel show moves
# its centred plane's value by more than this many standard errors (the conventional two): a
# significance test that spares the fine cameras' maps, where a quadratic would be taken by chance.
CURVE_ERRORS = 2.0


def _sliding_sums(images: torch.Tensor, window: int, dim: int) -> torch.Tensor:
    """Sums of ``window`` consecutive entries along ``dim`` centred at each one (zeros beyond the
    ends), as differences of a running sum: cost independent of the window."""
    r, n = window // 2, images.shape[dim]
    run = images.cumsum(dim)
    if n <= r:  # every window covers the whole line
        return run.narrow(dim, n - 1, 1).expand_as(run).clone()
    out = torch.empty_like(run)
    out.narrow(dim, 0, n - r).copy_(run.narrow(dim, r, n - r))
    out.narrow(dim, n - r, r).copy_(run.narrow(dim, n - 1, 1).expand_as(out.narrow(dim, n - r, r)))
    out.narrow(dim, r + 1, n - r - 1).sub_(run.narrow(dim, 0, n - r - 1))
    return out


def _window_planes(values: torch.Tensor, mask: torch.Tensor, window: int) -> tuple[torch.Tensor, ...]:
    """The least-squares plane through the masked values of each ``window x window`` neighbourhood.

    Args:
        values: :math:`(H, W, 2)` the map (any finite value where not masked).
        mask: :math:`(H, W)` bool, the pixels that count.

    Returns:
        ``planes`` :math:`(H, W, 2, 3)` per axis the plane's value at the window's centre and its
        slopes along ``x`` and ``y``; ``misfit`` :math:`(H, W)` the residual sum of squares of both
        axes per degree of freedom; ``count`` :math:`(H, W)` masked pixels in the window. Planes
        and misfit are NaN where the window holds too few pixels to fix a plane.
    """
    height, width = mask.shape
    dev = values.device
    planes = torch.full((height, width, 2, 3), float("nan"), dtype=torch.float32, device=dev)
    misfit = torch.full((height, width), float("nan"), dtype=torch.float32, device=dev)
    count = torch.zeros((height, width), dtype=torch.float32, device=dev)
    r = window // 2
    # The mask's moments about each window's centre are small integers: exact in float32.
    d = torch.arange(-r, r + 1, dtype=torch.float32, device=dev)
    dy, dx = torch.meshgrid(d, d, indexing="ij")
    kernels = torch.stack([torch.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy])[:, None]
    # conv2d correlates: kernel entry d weighs the neighbour at offset d (neighbour - centre).
    moments = F.conv2d(mask.float()[None, None], kernels, padding=r)[0]  # (6, H, W)
    # The values' sums in float64: the residual is a small difference of sums of squared
    # coordinates (up to 1e6 each). Coordinates are taken from each strip's first row and the
    # image's middle column, and the values from their mean, to keep the running sums small.
    centre = torch.nan_to_num(values[mask].double().mean(0)) if bool(mask.any()) else torch.zeros(2, dtype=torch.float64, device=dev)
    xs = torch.arange(width, dtype=torch.float64, device=dev) - width // 2
    for top in range(0, height, _REFINE_STRIP):
        lo, hi = max(top - r, 0), min(top + _REFINE_STRIP + r, height)
        # Only the columns within a window of a masked pixel of the strip (its margin rows included)
        # get a plane: outside them every sum is of zeros. Cut to them, the running sums add the same
        # values in the same order, so the planes are the same to the bit.
        seen = torch.nonzero(mask[lo:hi].any(0))[:, 0]
        if not seen.numel():
            continue  # no plane in the strip: NaN, count 0, as allocated
        left, right = max(int(seen[0]) - r, 0), min(int(seen[-1]) + r + 1, width)
        part = slice(left, right)
        u = (values[lo:hi, part].double() - centre).permute(2, 0, 1) * mask[lo:hi, part]  # (2, h, w)
        ys = torch.arange(hi - lo, dtype=torch.float64, device=dev)[:, None]
        xp = xs[part]
        sums = _sliding_sums(_sliding_sums(torch.cat([u, u * xp, u * ys, u * u]), window, -1), window, -2)
        sums, y = sums[:, top - lo:top - lo + _REFINE_STRIP], ys[top - lo:top - lo + _REFINE_STRIP]
        su, sux, suy, suu = sums[0:2], sums[2:4], sums[4:6], sums[6:8]
        # Moments about the window's centre (x, y): a plane c0 + c1 dx + c2 dy.
        n, sx, sy, sxx, sxy, syy = moments[:, top:top + sums.shape[1], part].double()
        sux, suy = sux - xp * su, suy - y * su
        # The symmetric 3 x 3 normal equations [[n, sx, sy], [sx, sxx, sxy], [sy, sxy, syy]] solved
        # by their cofactors.
        a00, a01, a02 = sxx * syy - sxy * sxy, sy * sxy - sx * syy, sx * sxy - sy * sxx
        a11, a12, a22 = n * syy - sy * sy, sx * sy - n * sxy, n * sxx - sx * sx
        det = n * a00 + sx * a01 + sy * a02
        fixed = det > 1e-6 * n.clamp_min(1) ** 3
        det = torch.where(fixed, det, 1.0)
        c0 = (a00 * su + a01 * sux + a02 * suy) / det
        c1 = (a01 * su + a11 * sux + a12 * suy) / det
        c2 = (a02 * su + a12 * sux + a22 * suy) / det
        rss = (suu - c0 * su - c1 * sux - c2 * suy).sum(0).clamp_min(0)
        rows = slice(top, top + n.shape[0])
        plane = torch.stack([c0 + centre[:, None, None], c1, c2], -1).permute(1, 2, 0, 3)
        planes[rows, part] = torch.where(fixed[..., None, None], plane, float("nan")).float()
        misfit[rows, part] = torch.where(fixed, rss / (2 * (n - 3)).clamp_min(1), float("nan")).float()
        count[rows, part] = n.float()
    return planes, misfit, count


# Pixels per chunk of _window_quadratics' gathered windows: bounds their float64 copies (a chunk of
# 49-pixel windows is 50 MB).
_QUADRATIC_CHUNK = 1 << 16


def _quadratic_terms(window: int, device) -> torch.Tensor:
    """:math:`(window^2, 6)` the terms ``1, dx, dy, dx^2, dx dy, dy^2`` at each offset of a window, row-major."""
    r = window // 2
    d = torch.arange(-r, r + 1, dtype=torch.float64, device=device)
    dy, dx = torch.meshgrid(d, d, indexing="ij")
    return torch.stack([torch.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy], -1).reshape(-1, 6)


def _window_quadratics(values: torch.Tensor, mask: torch.Tensor, window: int, pixels: torch.Tensor,
                       planes: torch.Tensor, misfit: torch.Tensor, count: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The least-squares quadratic (six terms in ``dx``, ``dy``) through the masked values of the
    ``window x window`` neighbourhood of each of ``pixels``, beside the planes of :func:`_window_planes`.

    In a window with every pixel masked in (most of them, away from a map's edges) the three
    second-order terms, taken about their window means, are orthogonal to the plane's: the quadratic
    is the plane plus their fit, whose sums are correlations of the map with three kernels that sum
    to zero (so float32 keeps them exact to the cells' 1e-4 where the map's values reach 1e3). The
    other windows are gathered and solved one by one in float64.

    Args:
        values: :math:`(H, W, 2)` the map (any finite value where not masked).
        mask: :math:`(H, W)` bool, the pixels that count.
        pixels: :math:`(N,)` flat indices ``y * W + x`` of the windows' centres.
        planes, misfit, count: :func:`_window_planes`' of the same values, mask and window.

    Returns:
        ``value`` :math:`(N, 2)` each axis' quadratic at the centre and ``misfit`` :math:`(N,)` the
        residual sum of squares of both axes per degree of freedom; NaN where the window's pixels
        do not fix six terms.
    """
    height, width = mask.shape
    dev = values.device
    r, area = window // 2, window * window
    terms = _quadratic_terms(window, dev)
    value = torch.full((pixels.numel(), 2), float("nan"), dtype=values.dtype, device=dev)
    quad_misfit = torch.full((pixels.numel(),), float("nan"), dtype=torch.float32, device=dev)
    # The correlations cover the whole map at a twentieth of a gathered window's cost per pixel: for
    # fewer windows than that, every one is gathered.
    whole = count.reshape(-1)[pixels] == area
    if pixels.numel() * 20 < height * width:
        whole = torch.zeros_like(whole)
    if bool(whole.any()):
        spread = float(terms[:, 1].square().mean())  # the mean of dx^2 (and of dy^2) over the window
        curved = torch.stack([terms[:, 3] - spread, terms[:, 5] - spread, terms[:, 4]])  # (3, window^2)
        # dx^2 and dy^2 about their means share a block of the normal matrix; dx dy is apart.
        inverse = torch.linalg.inv(curved @ curved.T).float()
        offset = values[mask].mean(0) if bool(mask.any()) else values.new_zeros(2)
        masked = ((values - offset) * mask[..., None]).permute(2, 0, 1)[:, None].float()
        h = F.conv2d(masked, curved.reshape(3, 1, window, window).float(), padding=r)  # (2, 3, H, W)
        h = h.reshape(2, 3, -1)[:, :, pixels[whole]]
        coef = torch.einsum("ij,ajn->ain", inverse, h)
        explained = (coef * h).sum((0, 1))  # what the three terms take off the plane's residual, both axes
        at = pixels[whole]
        plane = planes.reshape(-1, 2, 3)[at, :, 0]  # (n, 2) the plane's value at the centre: the window's mean
        value[whole] = (plane - spread * (coef[:, 0] + coef[:, 1]).T).to(values.dtype)
        rss = (misfit.reshape(-1)[at] * (2 * (area - 3)) - explained).clamp_min(0)
        quad_misfit[whole] = rss / (2 * (area - 6))
    outer = (terms[:, :, None] * terms[:, None, :]).reshape(-1, 36)
    step_x, step_y = terms[:, 1].long(), terms[:, 2].long()
    flat_mask, flat = mask.reshape(-1), values.reshape(-1, 2)
    partial = torch.nonzero(~whole)[:, 0]
    for start in range(0, partial.numel(), _QUADRATIC_CHUNK):
        chunk = pixels[partial[start:start + _QUADRATIC_CHUNK]]
        ys, xs = (chunk // width)[:, None] + step_y, (chunk % width)[:, None] + step_x  # (n, window^2)
        inside = (ys >= 0) & (ys < height) & (xs >= 0) & (xs < width)
        at = ys.clamp(0, height - 1) * width + xs.clamp(0, width - 1)
        weight = (flat_mask[at] & inside).double()
        # Values about each window's centre value keep the sums of squares small.
        centre = flat[chunk].double()  # (n, 2)
        u = (flat[at].double() - centre[:, None]).permute(2, 0, 1) * weight  # (2, n, window^2)
        normal = (weight @ outer).reshape(-1, 6, 6)
        rhs = u @ terms  # (2, n, 6)
        coef, info = torch.linalg.solve_ex(normal, rhs.permute(1, 2, 0))  # (n, 6, 2)
        n = weight.sum(1)
        # A window whose pixels leave the six terms nearly undetermined (a line of pixels) gets none.
        fixed = (info == 0) & (n > 6) & (torch.linalg.det(normal) > 1e-6 * n.clamp_min(1) ** 6)
        rss = (u.square().sum(-1) - (coef.permute(2, 0, 1) * rhs).sum(-1)).sum(0).clamp_min(0)
        here = partial[start:start + _QUADRATIC_CHUNK]
        value[here] = torch.where(fixed[:, None], coef[:, 0, :] + centre, float("nan")).to(values.dtype)
        quad_misfit[here] = torch.where(fixed, rss / (2 * (n - 6)).clamp_min(1), float("nan")).float()
    return value, quad_misfit


# Tiles (camera pixels a side) in which _refine_again fits again: each costs a fit over the tile and
# a border of a window either side, so smaller tiles waste less where few pixels changed.
_AGAIN_TILE = 64


def _refine_again(prj_xy: torch.Tensor, valid: torch.Tensor, before: torch.Tensor, changed: torch.Tensor,
                  spread: torch.Tensor, crease_ratio: float, curve_ratio: float = CURVE_RATIO,
                  window: int = 7) -> torch.Tensor:
    """:func:`refine_subpixel` of ``prj_xy`` where ``changed`` :math:`(H, W)` pixels' values (or spread)
    differ from those ``before`` :math:`(H, W, 2)` was fitted to, and ``before`` elsewhere.

    A pixel's fit reads the windows centred on it and half a window to each side, so only pixels
    within a window's width of a changed one can move: the fit runs on the tiles that hold such
    pixels, each with a border of that width (the same sums to float64 round-off: each fit centres
    its own values). Calibration's second fit changes a few hundred partly decoded pixels of the
    default scene's two million."""
    return _recompute_near(changed, 2 * (window // 2), _AGAIN_TILE, before.clone(),
                           lambda crop: refine_subpixel(prj_xy[crop], valid[crop], window=window, spread=spread[crop],
                                                        crease_ratio=crease_ratio, curve_ratio=curve_ratio))


def _shifted(dx: int, dy: int, height: int, width: int) -> tuple[tuple[slice, slice], tuple[slice, slice]]:
    """``(here, there)``: the slices of an :math:`(H, W)` image such that ``image[there]`` read at
    ``here`` is each pixel's neighbour at ``(x + dx, y + dy)`` (pixels whose neighbour lies outside
    are left out; stops clamped at 0, since a negative stop would count from the end of an image
    narrower than the shift)."""
    here = slice(max(-dy, 0), max(height - max(dy, 0), 0)), slice(max(-dx, 0), max(width - max(dx, 0), 0))
    there = slice(max(dy, 0), max(height - max(-dy, 0), 0)), slice(max(dx, 0), max(width - max(-dx, 0), 0))
    return here, there


def refine_subpixel(prj_xy: torch.Tensor, valid: torch.Tensor, window: int = 7,
                    min_fill: float = 0.7, max_shift: float = 0.75, spread: torch.Tensor | None = None,
                    crease_ratio: float = CREASE_RATIO, curve_ratio: float = CURVE_RATIO) -> torch.Tensor:
    """Sub-pixel projector coordinates by a local affine fit over neighbouring camera pixels.

    Gray code quantises each coordinate to whole LCD cells, a staircase across the camera image.
    On a smooth surface, the projector coordinate is locally an affine function of the camera
    coordinate; a least-squares plane through the decoded values in a ``window x window``
    neighbourhood, evaluated at the centre, recovers the position between the steps. The values may
    be the integer cells or, closer, the mean cell of each pixel's light (:func:`cell_means`, what
    :func:`~torchproj.calib.calibrate_projector` fits). Where the fit is not trustworthy (too few
    valid neighbours, or it lands more than ``max_shift`` from the pixel's own value, as at depth
    edges) that value is kept.

    Beside a crease (two faces of a box meeting: the map is continuous, its slope is not) a window
    centred on the pixel straddles both faces and its plane misses both, by a third of a cell on
    ``box_positions``. There the pixel takes the plane of a window beside it, shifted by half a
    window along ``x`` or ``y`` so that the pixel lies on its side, evaluated at the pixel: of the
    centred window and the four shifted ones, the one whose plane fits its values best, the centred
    one unless a shifted one fits ``crease_ratio`` times better (the choice of stencil of ENO
    interpolation; the paper does not refine at all, and this choice is ours, measured in
    ``benchmarks/refine.py``). Pixels beside a depth edge (:func:`~torchproj.calib.maps.depth_edges`)
    keep the centred window: they may see both surfaces, and a plane of either alone misplaces
    their light.

    Where the surface curves within a window (a small sphere seen by camera pixels a cell or more
    wide: the map's slope changes by cells across seven pixels) every plane misses the centre, by a
    fifth of a cell inside the procedural ``suite-1206-6``'s ellipsoid. There the pixel takes the
    quadratic through the centred window, where it fits ``curve_ratio`` times better than the
    centred plane, unless a window beside the pixel was taken (a crease's kink, which no quadratic
    follows). The quadratic has about twice the plane's variance at the centre, so it must earn its
    place, and it is fitted only where the planes of the windows beside the pixel bend enough to
    move the centred plane's value by :data:`CURVE_ERRORS` of its standard errors; our choice, as
    the stencils are (``python benchmarks/refine.py --vary curve``).

    Args:
        prj_xy: :math:`(H, W, 2)` decoded coordinates (NaN where invalid): cells, or their means.
        valid: :math:`(H, W)` bool.
        window: odd neighbourhood size in camera pixels.
        min_fill: minimum fraction of valid pixels in the window.
        max_shift: largest accepted move away from the decoded value, in projector pixels.
        spread: optional :math:`(H, W, 2)` cells per axis a partly decoded value leaves open
            (:attr:`GrayDecoding.spread`); such a value may move by half its block more.
        crease_ratio: how many times better a window beside the pixel must fit than the centred one
            to be taken (:data:`CREASE_RATIO`); ``math.inf``: the centred window only.
        curve_ratio: how many times better the centred window's quadratic must fit than its plane to
            be taken (:data:`CURVE_RATIO`); ``math.inf``: planes only.

    Returns:
        :math:`(H, W, 2)` refined coordinates, NaN where invalid.
    """
    check_window(window)
    check(is_number(min_fill) and 0 <= min_fill <= 1, f"min_fill must be a share of the window from 0 to 1, got {min_fill!r}")
    # inf: any fit is taken, however far it lands from the pixel's own value.
    check(is_number(max_shift) and max_shift > 0, f"max_shift must be a number of projector pixels > 0, got {max_shift!r}")
    check_ratio(crease_ratio, "crease_ratio", "1: the best-fitting window")
    check_ratio(curve_ratio, "curve_ratio", "1: the better-fitting of plane and quadratic")
    check_shape(prj_xy, "prj_xy", ["H", "W", 2])
    check_shape(valid, "valid", list(prj_xy.shape[:2]))
    if spread is not None:
        check_shape(spread, "spread", [*prj_xy.shape[:2], 2])
    height, width = valid.shape
    planes, misfit, count = _window_planes(torch.nan_to_num(prj_xy), valid, window)
    enough = count >= min_fill * window * window
    misfit = torch.where(enough, misfit, float("inf"))
    best, score = planes[..., 0], misfit  # (H, W, 2): the centred window's value at the pixel
    # Other windows and fits are for pixels away from depth edges, which keep the centred plane.
    beside = valid & ~depth_edges(prj_xy.masked_fill(~valid[..., None], float("nan"))) \
        if math.isfinite(crease_ratio) or math.isfinite(curve_ratio) else None
    r = window // 2
    shifts = ((r, 0), (-r, 0), (0, r), (0, -r))
    source = torch.full_like(count, -1, dtype=torch.int8)  # which window beside the pixel was taken, -1: none
    if math.isfinite(crease_ratio):
        score = misfit / crease_ratio
        for k, (dx, dy) in enumerate(shifts):
            # The window centred at (x + dx, y + dy), read at each pixel (x, y): its plane's value
            # there and its misfit, infinite where that centre lies outside the image.
            here, there = _shifted(dx, dy, height, width)
            misfit_there = torch.full_like(misfit, float("inf"))
            misfit_there[here] = misfit[there]
            value = torch.zeros_like(best)
            plane = planes[there]
            # Its plane read half a window along x or y: the other slope's term is zero (a plane is
            # finite, or NaN in all three parts).
            value[here] = plane[..., 0] - dx * plane[..., 1] if dx else plane[..., 0] - dy * plane[..., 2]
            take = beside & (misfit_there < score)
            score = torch.where(take, misfit_there, score)
            best = torch.where(take[..., None], value, best)
            source.masked_fill_(take, k)
    if math.isfinite(curve_ratio):
        # The centred quadratic, where it fits curve_ratio times better than the centred plane: a
        # surface curved within the window. Not beside a crease (a window beside the pixel taken),
        # whose kink no quadratic follows.
        candidates = beside & enough & (source < 0)
        # Only where the planes of the windows beside the pixel show a bend that moves the centred
        # plane's value by more than two of its standard errors can a quadratic gain: elsewhere (a
        # fine camera's map, planar faces) it would be taken by chance alone, and is not fitted.
        # The bias of the centred plane is spread * (f_xx + f_yy) / 2, the second derivatives from
        # the slopes of the windows half a window either side.
        bend = torch.full_like(planes[..., 0], float("nan"))  # (H, W, 2), NaN: unknown, so fitted
        if width > 2 * r and height > 2 * r:
            across = planes[:, 2 * r:, :, 1] - planes[:, :-2 * r, :, 1]  # at x: slope_x(x + r) - slope_x(x - r)
            down = planes[2 * r:, :, :, 2] - planes[:-2 * r, :, :, 2]
            bend[r:-r, r:-r] = (across[r:-r] + down[:, r:-r]) * (r * (r + 1) / 3 / (4 * r))
        error = (misfit / count.clamp_min(1)).sqrt()
        candidates &= ~(bend.abs().amax(-1) <= CURVE_ERRORS * error)
        pixels = torch.nonzero(candidates.reshape(-1))[:, 0]
        if pixels.numel():
            value, curved = _window_quadratics(torch.nan_to_num(prj_xy), valid, window, pixels, planes, misfit, count)
            take = curved * curve_ratio < misfit.reshape(-1)[pixels]
            flat_best = best.reshape(-1, 2).clone()
            flat_best[pixels[take]] = value[take].to(best.dtype)
            best = flat_best.view_as(best)
            flat_score = score.reshape(-1).clone()
            flat_score[pixels[take]] = curved[take]
            score = flat_score.view_as(score)
            # A pixel on an outline, whose own window the mask cuts, took a window beside it: where
            # that window's surface curves (its quadratic was taken), its plane read half a window
            # away misses by far more than the pixel's own value does (0.35-0.47 against 0.16-0.28
            # cells rms on suite-1206-6's outline; on planar faces the plane is the better, 0.05-0.15
            # against 0.12-0.22), so the pixel keeps its own value.
            bent = torch.zeros(height * width, dtype=torch.bool, device=valid.device)
            bent[pixels[take]] = True
            bent = bent.view(height, width)
            for k, (dx, dy) in enumerate(shifts):
                here, there = _shifted(dx, dy, height, width)
                from_bent = torch.zeros_like(bent)
                from_bent[here] = bent[there]
                score = score.masked_fill(~enough & (source == k) & from_bent, float("inf"))
    fitted = best.to(prj_xy.dtype)
    allowed = max_shift if spread is None else max_shift + (spread.to(prj_xy.dtype) - 1).clamp_min(0) / 2
    keep = valid & torch.isfinite(score) & torch.isfinite(fitted).all(-1) & ((fitted - prj_xy).abs() <= allowed).all(-1)
    return torch.where(keep[..., None], fitted, prj_xy)
