"""Photometric calibration: projector response ``f(x) = a x^b + c`` from a captured intensity ramp.

The paper (section 4.1) projects a grey ramp, plots captured against nominal intensity, fits
``a x^b + c`` and inverts it to linearise the projector. A ramp spreads its levels over the image,
and every camera pixel sees the projector through its own fall-off, angle, albedo and vignetting;
dividing each pixel's ramp value by that pixel's white-minus-black removes all of them, so the
curve fitted here is the projector's own, normalised so that black is 0 and white is 1:
``y(x) = (L(x) - L(0)) / (L(1) - L(0))``, with ``a ~ 1``, ``c ~ 0`` and b the projector's exponent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.optimize import curve_fit

from ..core.checks import check, check_shape

__all__ = ["ResponseCurve", "ramp_pattern", "measure_ramp", "fit_response"]


def ramp_pattern(width: int, height: int, steps: int = 32, mirrored: bool = False) -> torch.Tensor:
    """A ramp of ``steps`` vertical bars from 0 (left) to 1 (right), or its mirror.

    Returns:
        :math:`(1, 1, H, W)` pattern. The ramp and its mirror add up to exactly 1 everywhere.
    """
    check(2 <= steps <= width, f"steps must be between 2 and the width {width}, got {steps}")
    level = torch.div(torch.arange(width) * steps, width, rounding_mode="floor").float() / (steps - 1)
    if mirrored:
        level = 1 - level
    return level.expand(height, width)[None, None].clone()


@dataclass
class ResponseCurve:
    """``y = a x^b + c`` per colour channel (tensors of shape (C,)), x and y in [0, 1].

    Methods take images :math:`(..., C, H, W)`; C may be 1 with a 3-channel curve or vice versa.
    """

    a: torch.Tensor
    b: torch.Tensor
    c: torch.Tensor

    def _params(self):
        return (t.view(-1, 1, 1) for t in (self.a, self.b, self.c))

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """Relative light for pattern values x."""
        a, b, c = self._params()
        return a * x.clamp(0, 1) ** b + c

    def to_pattern(self, y: torch.Tensor) -> torch.Tensor:
        """Pattern values that make the projector emit relative light y (0 = its black, 1 = its white).

        This is the inverse response used for compensation, ``f^-1(f(0) + y (f(1) - f(0)))``,
        which for ``a x^b + c`` is ``y^(1/b)``.
        """
        _, b, _ = self._params()
        return y.clamp(0, 1) ** (1 / b)

    def as_dict(self) -> dict:
        return {"a": self.a.tolist(), "b": self.b.tolist(), "c": self.c.tolist()}


def measure_ramp(ramp: torch.Tensor, white: torch.Tensor, black: torch.Tensor, prj_x: torch.Tensor,
                 projector_width: int, steps: int = 32, margin: float = 1.5,
                 min_contrast: float = 0.05) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-level normalised response from one capture of :func:`ramp_pattern`.

    Args:
        ramp, white, black: :math:`(C, H, W)` captures of the ramp, all-white and all-black.
        prj_x: :math:`(H, W)` decoded projector column per camera pixel (NaN where invalid).
        projector_width: projector width in pixels.
        steps: number of bars in the ramp.
        margin: camera pixels whose projector column is within this many projector pixels of a bar
            edge are left out (their footprint straddles two levels).
        min_contrast: pixels with white - black below this are left out (too dark to measure).

    Returns:
        ``levels`` :math:`(L,)` nominal values and ``response`` :math:`(L, C)` median of
        ``(ramp - black) / (white - black)`` over the pixels of each level seen.
    """
    sizes = check_shape(ramp, "ramp", ["C", "H", "W"])
    check_shape(white, "white", [sizes["C"], sizes["H"], sizes["W"]])
    check_shape(black, "black", [sizes["C"], sizes["H"], sizes["W"]])
    check_shape(prj_x, "prj_x", [sizes["H"], sizes["W"]])
    bar = projector_width / steps
    pos = prj_x / bar
    level = torch.floor(pos)
    frac = pos - level
    contrast = (white - black).min(0).values
    ok = torch.isfinite(prj_x) & (frac * bar >= margin) & ((1 - frac) * bar >= margin) & (contrast >= min_contrast)
    norm = ((ramp - black) / (white - black).clamp_min(1e-6))[:, ok]  # (C, M)
    lv = level[ok].long()
    levels, response = [], []
    for k in range(steps):
        sel = lv == k
        if int(sel.sum()) >= 5:
            levels.append(k / (steps - 1))
            response.append(norm[:, sel].median(1).values)
    check(len(levels) >= 4, f"the ramp capture shows only {len(levels)} usable levels; "
                            "check that the projector lights the scene and decoding succeeded")
    return torch.tensor(levels), torch.stack(response)


def fit_response(levels: torch.Tensor, response: torch.Tensor) -> ResponseCurve:
    """Least-squares fit of ``a x^b + c`` per channel (scipy's ``curve_fit``).

    Args:
        levels: :math:`(L,)` nominal values in [0, 1].
        response: :math:`(L,)` or :math:`(L, C)` measured relative light.

    Returns:
        the fitted :class:`ResponseCurve`.
    """
    if response.dim() == 1:
        response = response[:, None]
    check_shape(response, "response", [levels.shape[0], "C"])
    x = levels.double().numpy()
    params = []
    for ch in range(response.shape[1]):
        y = response[:, ch].double().numpy()
        p, _ = curve_fit(lambda x, a, b, c: a * np.power(x, b) + c, x, y, p0=(1.0, 2.0, 0.0),
                         bounds=([1e-6, 0.2, -1.0], [10.0, 6.0, 1.0]), maxfev=10000)
        params.append(p)
    p = torch.tensor(np.array(params), dtype=torch.float32)
    return ResponseCurve(a=p[:, 0], b=p[:, 1], c=p[:, 2])
