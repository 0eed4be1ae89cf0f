"""Photometric calibration: projector response ``f(x) = a x^b + c`` from a captured intensity ramp.

The paper (section 4.1) projects a grey ramp, plots captured against nominal intensity, fits
``a x^b + c`` and inverts it to linearise the projector. A ramp spreads its levels over the image,
and every camera pixel sees the projector through its own fall-off, angle, albedo and vignetting;
dividing each pixel's ramp value by that pixel's white-minus-black removes all of them, so the
curve fitted here is the projector's own, normalised so that black is 0 and white is 1:
``y(x) = (L(x) - L(0)) / (L(1) - L(0))``, with ``a ~ 1``, ``c ~ 0`` and b the projector's exponent.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch

from ..core.checks import check, check_count, check_finite, check_mask, check_number, check_shape
from ..core.errors import InputError
from ..core.conventions import MAX_MIXING_CONDITION, to_numpy
from .maps import _check_projector_size

__all__ = ["ResponseCurve", "check_mixing", "fit_colour_mixing", "fit_response", "measure_ramp", "primary_patterns", "ramp_pattern"]


# Bars of the photometric ramp ``torchproj sequence`` and the virtual rig show, the levels ``a x^b + c`` is
# fitted to. The paper's "System calibration" shows a grey ramp and its mirror without saying how many
# bars; 32 is our choice. A projector needs at least this many cells across, one a bar.
from ..core.choices import RAMP_STEPS  # noqa: E402  (32; there, for the command's parser)


def ramp_pattern(width: int, height: int, steps: int = RAMP_STEPS, mirrored: bool = False) -> torch.Tensor:
    """A ramp of ``steps`` vertical bars from 0 (left) to 1 (right), or its mirror.

    Returns:
        :math:`(1, 1, H, W)` pattern. The ramp and its mirror add up to exactly 1 everywhere.
    """
    _check_projector_size(width, height)
    check_count(steps, "steps (the ramp's bars)", 2)
    check(steps <= width, f"steps must be between 2 and the width {width}, got {steps}")
    level = torch.div(torch.arange(width) * steps, width, rounding_mode="floor").float() / (steps - 1)
    if mirrored:
        level = 1 - level
    return level.expand(height, width)[None, None].clone()


@dataclass
class ResponseCurve:
    """``y = a x^b + c`` per colour channel (tensors of shape (C,)), x and y in [0, 1].

    Methods take images :math:`(..., C, H, W)`; C may be 1 with a 3-channel curve or vice versa.

    ``mixing``, for a colour camera, is the :math:`(3, 3)` share of each projector primary (column)
    that each camera channel (row) sees, rows summing to 1 (:func:`fit_colour_mixing`): the camera's
    channel c then sees ``sum_p mixing[c, p] y_p``. Solvers work in what the camera sees, one
    channel at a time; :meth:`to_pattern` takes that back to the primaries. None: each channel sees
    its own primary alone.
    """

    a: torch.Tensor
    b: torch.Tensor
    c: torch.Tensor
    mixing: torch.Tensor | None = None

    def __post_init__(self):
        # Numbers and lists become tensors; a curve that does not rise has no inverse, so compensation
        # through it would give nonsense (b = -2 asked the projector for 22 times its white).
        for name in ("a", "b", "c"):
            value = getattr(self, name)
            if not isinstance(value, torch.Tensor):
                try:
                    value = torch.as_tensor(value, dtype=torch.float32)
                except (TypeError, ValueError, RuntimeError):
                    raise InputError(f"response {name} must be a number or one per channel, got {value!r}") from None
                setattr(self, name, value)
            check(value.numel() >= 1 and bool(torch.isfinite(value).all()),
                  f"response {name} must be finite numbers, got {value.tolist()}")
        check(bool((self.a > 0).all()) and bool((self.b > 0).all()),
              f"y = a x^b + c needs a > 0 and b > 0 (a projector's light rises with its input), got "
              f"a={self.a.tolist()}, b={self.b.tolist()}")
        if self.mixing is not None:
            check_mixing(self.mixing, "response mixing")

    def _params(self, x: torch.Tensor):
        """a, b, c shaped to broadcast over ``x``'s channels, on its device (a curve fitted where the
        captures were serves patterns made anywhere)."""
        return (t.to(x.device).view(-1, 1, 1) for t in (self.a, self.b, self.c))

    def _mixes(self, x: torch.Tensor) -> bool:
        return self.mixing is not None and x.dim() >= 3 and x.shape[-3] == 3

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """Relative light for pattern values x, as the camera's channels see it."""
        a, b, c = self._params(x)
        y = a * x.clamp(0, 1) ** b + c
        if self._mixes(y):
            y = torch.einsum("cp,...phw->...chw", self.mixing.to(y), y)
        return y

    def to_pattern(self, y: torch.Tensor) -> torch.Tensor:
        """Pattern values that make the projector emit relative light y (0 = its black, 1 = its white).

        This is the inverse response used for compensation, ``f^-1(f(0) + y (f(1) - f(0)))``,
        which for ``a x^b + c`` is ``y^(1/b)``. With ``mixing``, y is what the camera's channels
        see: the primaries' light is ``mixing^-1 y`` first, and light no primary can give (a
        colour outside the projector's gamut as this camera sees it) is clipped to [0, 1].
        """
        _, b, _ = self._params(y)
        if self._mixes(y):
            y = torch.einsum("pc,...chw->...phw", torch.linalg.inv(self.mixing.double()).to(y), y)
        return y.clamp(0, 1) ** (1 / b)

    def from_pattern(self, x: torch.Tensor) -> torch.Tensor:
        """The relative light (0 = black, 1 = white) pattern values x make the projector emit, as the
        camera's channels see it: :meth:`to_pattern`'s inverse, ``x^b``, through the mixing."""
        _, b, _ = self._params(x)
        y = x.clamp(0, 1) ** b
        if self._mixes(y):
            y = torch.einsum("cp,...phw->...chw", self.mixing.to(y), y)
        return y

    def as_dict(self) -> dict:
        out = {"a": self.a.tolist(), "b": self.b.tolist(), "c": self.c.tolist()}
        if self.mixing is not None:
            out["mixing"] = [[round(v, 6) for v in row] for row in self.mixing.tolist()]
        return out


def primary_patterns(width: int, height: int) -> torch.Tensor:
    """Full-field red, green and blue, :math:`(3, 3, H, W)`: what a colour camera's channels see of
    each primary alone gives the projector's colour mixing (:func:`fit_colour_mixing`)."""
    _check_projector_size(width, height)
    return torch.eye(3)[:, :, None, None].expand(3, 3, height, width).clone()


def tells_primaries_apart(mixing) -> bool:
    """Whether ``mixing`` is a :math:`(3, 3)` tensor of finite shares >= 0 whose inverse a solve can
    take: its condition number at most :data:`~torchproj.core.conventions.MAX_MIXING_CONDITION`."""
    return (isinstance(mixing, torch.Tensor) and mixing.shape == (3, 3) and not mixing.is_complex()
            and bool(torch.isfinite(mixing).all()) and not bool((mixing < 0).any())
            and float(torch.linalg.cond(mixing.double())) <= MAX_MIXING_CONDITION)


def check_mixing(mixing, name: str = "mixing") -> torch.Tensor:
    """``mixing`` a projector's colour mixing (:class:`ResponseCurve`): rows camera channels, columns
    primaries, shares that the camera can tell apart (:func:`tells_primaries_apart`)."""
    check(tells_primaries_apart(mixing),
          f"{name} must be a (3, 3) tensor of shares >= 0 (rows camera channels, columns primaries) that tell "
          f"the primaries apart (condition number <= {MAX_MIXING_CONDITION:g}), got "
          f"{mixing.tolist() if isinstance(mixing, torch.Tensor) and mixing.numel() <= 9 else type(mixing).__name__}")
    return mixing


# Below this white minus black (in [0, 1]) a pixel's primaries are too dark to divide by.
_MIXING_CONTRAST = 0.05


def fit_colour_mixing(primaries: torch.Tensor, white: torch.Tensor, black: torch.Tensor,
                      lit: torch.Tensor | None = None) -> torch.Tensor:
    """The share of each projector primary that each camera channel sees.

    A colour camera's channels do not see one primary each: a DLP's or LCD's red, green and blue
    overlap the Bayer filters' pass bands, so red light lifts the green channel too. Whatever the
    surface's albedo and the projector's fall-off, the ratio ``(primary_p - black) / (white - black)``
    in channel c is the share of channel c's white that primary p gives (the other primaries' black
    level cancels against the black capture); its median over the well-lit pixels is ``mixing[c, p]``.
    The method is ours (the paper's camera and projector are grey); rows are normalised to sum to 1,
    as white is the sum of the primaries.

    Args:
        primaries: :math:`(3, 3, H, W)` captures of :func:`primary_patterns` (primary, channel).
        white, black: :math:`(3, H, W)` captures.
        lit: optional :math:`(H, W)` pixels to use (e.g. decoded ones); those with white - black
            under 0.05 in any channel are left out as well.

    Returns:
        :math:`(3, 3)` mixing, rows camera channels, columns primaries.
    """
    check_shape(primaries, "primaries", [3, 3, "H", "W"])
    check_shape(white, "white", [3, primaries.shape[2], primaries.shape[3]])
    check_shape(black, "black", list(white.shape))
    if lit is not None:
        check_mask(lit, "lit", list(white.shape[1:]))
    span = (white - black).float()
    ok = (span >= _MIXING_CONTRAST).all(0)
    if lit is not None:
        ok &= lit
    check(int(ok.sum()) >= 100, f"only {int(ok.sum())} pixels are lit well enough (white - black >= "
                                f"{_MIXING_CONTRAST:g} in every channel) to measure the projector's colour mixing; "
                                "check exposure and that the projector lights the scene")
    share = ((primaries - black).float() / span.clamp_min(1e-6))[:, :, ok]  # (primary, channel, M)
    mixing = share.median(-1).values.T.clamp_min(0)  # (channel, primary)
    mixing = mixing / mixing.sum(1, keepdim=True).clamp_min(1e-12)
    # A grey camera writing colour files sees each primary alike in all three channels: the rows are
    # equal and the primaries' curves cannot be taken apart from the grey ramp (the inverse below).
    check(tells_primaries_apart(mixing),
          f"the camera's channels do not tell the projector's primaries apart (colour mixing "
          f"{[[round(v, 3) for v in row] for row in mixing.tolist()]}, condition number "
          f"{float(torch.linalg.cond(mixing.double())):.3g}, over {MAX_MIXING_CONDITION:g}): a grey camera that "
          "writes colour files sees each primary alike in every channel; save its captures in grey, or check that "
          "the primaries' captures show the projector's red, green and blue")
    return mixing


def measure_ramp(ramp: torch.Tensor, white: torch.Tensor, black: torch.Tensor, prj_x: torch.Tensor,
                 projector_width: int, steps: int = RAMP_STEPS, margin: float = 1.5,
                 min_contrast: float = 0.05, mirrored: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-level normalised response from one capture of :func:`ramp_pattern` (and of its mirror).

    The mirror shows bar ``k`` at level ``1 - k / (steps - 1)``: an object that sees a few bars
    low on the ramp sees them high on the mirror, so the two together span the curve from both ends
    (our choice; the paper shows one ramp).

    Args:
        ramp, white, black: :math:`(C, H, W)` captures of the ramp, all-white and all-black.
        mirrored: optional :math:`(C, H, W)` capture of the mirrored ramp.
        prj_x: :math:`(H, W)` decoded projector column per camera pixel (NaN where invalid).
        projector_width: projector width in pixels.
        steps: number of bars in the ramp.
        margin: camera pixels whose projector column is within this many projector pixels of a bar
            edge are left out (their footprint straddles two levels); at most a third of a bar, so
            that a narrow projector's bars (3 cells for 96 columns and 32 steps) keep their middle.
        min_contrast: pixels with white - black below this are left out (too dark to measure).

    Returns:
        ``levels`` :math:`(L,)` nominal values and ``response`` :math:`(L, C)` median of
        ``(ramp - black) / (white - black)`` over the pixels of each level seen.
    """
    sizes = check_shape(ramp, "ramp", ["C", "H", "W"])
    check_shape(white, "white", [sizes["C"], sizes["H"], sizes["W"]])
    check_shape(black, "black", [sizes["C"], sizes["H"], sizes["W"]])
    check_shape(prj_x, "prj_x", [sizes["H"], sizes["W"]])
    _check_projector_size(projector_width, 1)
    check_count(steps, "steps (the ramp's bars)", 2)
    check_number(margin, "margin (projector pixels)")
    check_number(min_contrast, "min_contrast (white - black, in [0, 1])")
    bar = projector_width / steps
    # A margin of 1.5 cells either side of a 3-cell bar left no pixel of any bar: a 96-column
    # projector failed calibration for want of a ramp, however well lit.
    margin = min(margin, bar / 3)
    pos = prj_x / bar
    level = torch.floor(pos)
    frac = pos - level
    contrast = (white - black).min(0).values
    ok = torch.isfinite(prj_x) & (frac * bar >= margin) & ((1 - frac) * bar >= margin) & (contrast >= min_contrast)
    span = (white - black).clamp_min(1e-6)
    norm = ((ramp - black) / span)[:, ok]  # (C, M)
    lv = level[ok].long()
    if mirrored is not None:
        check_shape(mirrored, "mirrored ramp", [sizes["C"], sizes["H"], sizes["W"]])
        norm = torch.cat([norm, ((mirrored - black) / span)[:, ok]], 1)
        lv = torch.cat([lv, steps - 1 - lv])  # the mirror's bar k shows level steps - 1 - k
    levels, response = [], []
    for k in range(steps):
        sel = lv == k
        if int(sel.sum()) >= 5:
            levels.append(k / (steps - 1))
            response.append(norm[:, sel].median(1).values)
    if len(levels) < 4:
        # Say which of the two causes it is: too few pixels decoded (dark, or stripes the camera does
        # not resolve), or decoded pixels that each see two bars (camera pixels as wide as a bar).
        seen = torch.isfinite(prj_x) & (contrast >= min_contrast)
        raise InputError(
            f"the ramp capture shows only {len(levels)} usable levels (bars of at least 5 decoded pixels with white - "
            f"black over {min_contrast * 255:.0f}/255, clear of the bar's edges by {margin:.2g} cells): "
            f"{int(seen.sum())} of the {prj_x.numel()} camera pixels are decoded and that bright, {int(ok.sum())} of "
            f"them clear of an edge of the {bar:.3g}-cell bars. Where few decode, check that the projector lights the "
            "scene and is bright enough against the camera's exposure, and that decoding succeeded (camera pixels "
            "wider than a cell decode only partly); where few are clear of an edge, the camera's pixels are as wide "
            "as a bar: bring the camera closer or give it more pixels")
    return torch.tensor(levels), torch.stack(response)


def fit_response(levels: torch.Tensor, response: torch.Tensor, normalised: bool = False) -> ResponseCurve:
    """Least-squares fit of ``a x^b + c`` per channel (scipy's ``curve_fit``), the paper's curve.

    Args:
        levels: :math:`(L,)` nominal values in [0, 1].
        response: :math:`(L,)` or :math:`(L, C)` measured relative light.
        normalised: the response is normalised by each pixel's black and white
            (:func:`measure_ramp`), so it is 0 at 0 and 1 at 1 by construction: fit ``x^b`` alone
            (``a = 1``, ``c = 0``). Compensation uses ``b`` alone (:meth:`ResponseCurve.to_pattern`),
            and where the levels seen span a small part of the curve (an object a few bars wide)
            three free parameters trade ``b`` against ``a`` and ``c``: suite-97-10's fitted
            exponents missed the true ones by up to 0.65 that way (our choice; the paper fits the
            unnormalised captures).

    Returns:
        the fitted :class:`ResponseCurve`.
    """
    # Imported here: a run from the cache fits no response and need not import scipy.
    from scipy.optimize import OptimizeWarning, curve_fit

    for name, values in (("levels", levels), ("response", response)):
        check(isinstance(values, torch.Tensor) and values.is_floating_point(),
              f"{name} must be a float tensor, got "
              f"{values.dtype if isinstance(values, torch.Tensor) else type(values).__name__}")
    check_shape(levels, "levels", ["L"])
    if response.dim() == 1:
        response = response[:, None]
    check_shape(response, "response", [levels.shape[0], "C"])
    check_finite(levels, "levels")
    check_finite(response, "response")
    check(bool(((levels >= 0) & (levels <= 1)).all()),
          f"levels must lie in [0, 1] (8-bit levels over 255), got [{float(levels.min()):g}, {float(levels.max()):g}]")
    unknowns = 1 if normalised else 3
    check(levels.shape[0] >= unknowns, f"{levels.shape[0]} levels cannot fit {unknowns} unknowns "
                                       f"({'x^b' if normalised else 'a x^b + c'}): measure more levels")
    x = to_numpy(levels.double())  # scipy fits on the host
    params = []
    with warnings.catch_warnings():
        # Only the parameters are used: a fit as determined as its unknowns (one level for x^b) has no
        # covariance, which scipy warns of.
        warnings.simplefilter("ignore", OptimizeWarning)
        for ch in range(response.shape[1]):
            y = to_numpy(response[:, ch].double())
            if normalised:
                (b,), _ = curve_fit(lambda x, b: np.power(x, b), x, y, p0=(2.0,), bounds=([0.2], [6.0]), maxfev=10000)
                params.append((1.0, b, 0.0))
                continue
            # A flat or falling response has no curve that compensation could invert (its fit sits at a's
            # bound, with any b).
            low, high = y[np.argmin(x)], y[np.argmax(x)]
            check(high > low, f"response channel {ch} does not rise with the level (from {low:.4g} at the lowest level "
                              f"to {high:.4g} at the highest): were the projector and camera on, and the levels in "
                              "the order shown?")
            p, _ = curve_fit(lambda x, a, b, c: a * np.power(x, b) + c, x, y, p0=(1.0, 2.0, 0.0),
                             bounds=([1e-6, 0.2, -1.0], [10.0, 6.0, 1.0]), maxfev=10000)
            params.append(p)
    p = torch.tensor(np.array(params), dtype=torch.float32, device=response.device)
    return ResponseCurve(a=p[:, 0], b=p[:, 1], c=p[:, 2])
