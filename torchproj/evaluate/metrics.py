"""Metrics that say what they compare."""

from __future__ import annotations

import math

import torch

from ..core.checks import check
from ..transport.operator import TransportOperator

__all__ = ["psnr", "model_space_psnr"]


def psnr(estimate: torch.Tensor, reference: torch.Tensor, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB over all given values: ``10 log10(range^2 / MSE)``."""
    check(estimate.shape == reference.shape, f"shapes differ: {tuple(estimate.shape)} vs {tuple(reference.shape)}")
    mse = float((estimate.double() - reference.double()).pow(2).mean())
    return math.inf if mse == 0 else 10 * math.log10(data_range**2 / mse)


def model_space_psnr(op: TransportOperator, p: torch.Tensor) -> list[float]:
    """PSNR per target of what the operator predicts, ``A p / scale``, against the target values.

    Compares, over each target's rows (its camera pixels), the predicted image in target units
    (1 = white) with the target image warped onto those pixels; data range 1. Needs an operator
    built without row merging (merged rows mix pixels).
    """
    check(not bool(op.constant.abs().sum() > 0), "model_space_psnr needs an operator built with merge=False")
    pred = op.A(p) / op.scale
    want = op.rhs / op.scale
    return [psnr(pred[op.row_target == k].clamp(0, 1), want[op.row_target == k])
            for k in range(int(op.row_target.max()) + 1)]
