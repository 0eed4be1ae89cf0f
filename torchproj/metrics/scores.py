"""PSNR and crosstalk: scores that say what they compare (SSIM: :mod:`torchproj.metrics.ssim`)."""

from __future__ import annotations

import math

import torch

from ..core.checks import check

__all__ = ["psnr", "model_space_psnr", "crosstalk"]


def psnr(estimate: torch.Tensor, reference: torch.Tensor, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB over all given values: ``10 log10(range^2 / MSE)``."""
    check(estimate.shape == reference.shape, f"shapes differ: {tuple(estimate.shape)} vs {tuple(reference.shape)}")
    mse = float((estimate.double() - reference.double()).pow(2).mean())
    return math.inf if mse == 0 else 10 * math.log10(data_range**2 / mse)


def model_space_psnr(op, p: torch.Tensor) -> list[float]:
    """PSNR per target of what a :class:`~torchproj.transport.TransportOperator` predicts, ``A p / scale``, against the target values.

    Compares, over each target's rows (its camera pixels), the predicted image in target units
    (1 = white) with the target image warped onto those pixels; data range 1. Needs an operator
    built without row merging (merged rows mix pixels).
    """
    check(not bool(op.constant.abs().sum() > 0), "model_space_psnr needs an operator built with merge=False")
    pred = op.A(p) / op.scale
    want = op.rhs / op.scale
    return [psnr(pred[op.row_target == k].clamp(0, 1), want[op.row_target == k])
            for k in range(int(op.row_target.max()) + 1)]


def crosstalk(captured: torch.Tensor, others: list[torch.Tensor], mask: torch.Tensor) -> float:
    """How much of other targets' images shows in a capture: the largest absolute Pearson
    correlation, over the mask's pixels (each channel centred on its own mean, then pooled), between
    the capture and each other target's image placed on the same pixels (0: no trace of it; 1: it is
    fully there)."""
    if not others:
        return 0.0
    # Centred per channel: colour images differ in their channel means, and a single mean over all
    # channels would count that difference as a trace of the other image.
    c = captured[:, mask].double()
    c = (c - c.mean(1, keepdim=True)).reshape(-1)
    best = 0.0
    for other in others:
        o = other[:, mask].double()
        o = (o - o.mean(1, keepdim=True)).reshape(-1)
        denom = float(c.norm() * o.norm())
        if denom > 0:
            best = max(best, abs(float((c * o).sum()) / denom))
    return best
