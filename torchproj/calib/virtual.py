"""Calibration captures on the virtual rig, and their check against the simulator's ground truth."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..sim.rig import VirtualRig
from .capture import GraycodeCapture
from .graycode import graycode_patterns
from .response import ramp_pattern

__all__ = ["simulate_calibration", "DecodingError", "decoding_error"]


def simulate_calibration(rig: VirtualRig, state: str, projector: int | str, ramp_steps: int = 32,
                         noise: bool = True, bits: int | tuple[int, int] | None = None) -> GraycodeCapture:
    """Capture the calibration sequence of one projector in one state on the virtual rig.

    The projector shows its Gray code (the first ``bits`` pairs per axis of it, if given), white,
    black and the ramp and mirrored ramp; the other projectors stay on showing black, as on a real
    bench.
    """
    index = projector if isinstance(projector, int) else [p.name for p in rig.scene.projectors].index(projector)
    proj = rig.scene.projectors[index]
    gray = graycode_patterns(proj.width, proj.height, bits)
    ramps = torch.cat([ramp_pattern(proj.width, proj.height, ramp_steps),
                       ramp_pattern(proj.width, proj.height, ramp_steps, mirrored=True)])
    images = rig.capture(state, {index: torch.cat([gray, ramps])}, noise=noise)
    return GraycodeCapture(patterns=images[:-4], white=images[-4], black=images[-3], ramp=images[-2:])


@dataclass
class DecodingError:
    """How decoded coordinates compare with the simulator's truth for one projector and state.

    Fractions are over the camera pixels the projector truly lights (``lit``).
    """

    lit: int  # pixels truly lit
    decoded: float  # fraction of lit pixels decoded
    exact: float  # fraction of decoded pixels whose cell equals the true cell
    within_one: float  # ... within one cell in x and y
    false_valid: float  # fraction of unlit pixels (shadow, background) reported valid
    rms_px: float  # RMS distance to the continuous true coordinate, over decoded lit pixels

    def as_dict(self) -> dict:
        return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


def decoding_error(decoded: torch.Tensor, truth: torch.Tensor) -> DecodingError:
    """Compare decoded :math:`(H, W, 2)` projector coordinates with the true ones (NaN = unlit)."""
    lit = torch.isfinite(truth).all(-1)
    valid = torch.isfinite(decoded).all(-1)
    both = lit & valid
    cell_true = torch.floor(truth[both] + 0.5)
    cell_dec = torch.floor(decoded[both] + 0.5)
    diff = (cell_dec - cell_true).abs().max(-1).values
    n_lit, n_both = int(lit.sum()), int(both.sum())
    err = (decoded[both] - truth[both]).norm(dim=-1)
    return DecodingError(
        lit=n_lit,
        decoded=n_both / max(n_lit, 1),
        exact=float((diff == 0).float().mean()) if n_both else 0.0,
        within_one=float((diff <= 1).float().mean()) if n_both else 0.0,
        false_valid=float((valid & ~lit).sum()) / max(int((~lit).sum()), 1),
        rms_px=float(err.pow(2).mean().sqrt()) if n_both else float("nan"),
    )
