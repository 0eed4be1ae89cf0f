"""PSNR, crosstalk and the share of an error that ghosts explain: scores that say what they compare (SSIM: :mod:`torchproj.metrics.ssim`)."""

from __future__ import annotations

import math

import torch

from ..core.checks import check, check_mask, check_number, check_shape

__all__ = ["psnr", "model_space_psnr", "crosstalk", "explained_share"]


def _check_float(image, name: str) -> None:
    """A float tensor: integers would be scored against a data range of 1 (8-bit images over 255
    first), where scikit-image would take the dtype's range."""
    check(isinstance(image, torch.Tensor) and image.is_floating_point(),
          f"{name} must be a float tensor (8-bit images over 255), got "
          f"{image.dtype if isinstance(image, torch.Tensor) else type(image).__name__}")


def _check_float_pair(estimate, reference) -> None:
    _check_float(estimate, "estimate")
    _check_float(reference, "reference")


def _check_range(data_range) -> float:
    return check_number(data_range, "data_range", 0.0, strict=True)


def _check_masked(first: tuple[str, torch.Tensor], rest: tuple[str, list], mask) -> None:
    """An image :math:`(C, H, W)`, a list of images shaped like it and a mask of its pixels."""
    name, image = first
    _check_float(image, name)
    sizes = check_shape(image, name, ["C", "H", "W"])
    listed, images = rest
    check(isinstance(images, (list, tuple)), f"{listed} must be a list of images, got {type(images).__name__}")
    for k, other in enumerate(images):
        _check_float(other, f"{listed}[{k}]")
        check(other.shape == image.shape, f"{listed}[{k}] {tuple(other.shape)} must have {name}'s shape {tuple(image.shape)}")
    check_mask(mask, "mask", [sizes["H"], sizes["W"]])


def psnr(estimate: torch.Tensor, reference: torch.Tensor, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB over all given values: ``10 log10(range^2 / MSE)``."""
    _check_float_pair(estimate, reference)
    check(estimate.shape == reference.shape, f"shapes differ: {tuple(estimate.shape)} vs {tuple(reference.shape)}")
    check(estimate.numel() > 0, "estimate and reference hold no values to score")
    _check_range(data_range)
    mse = float((estimate.double() - reference.double()).pow(2).mean())
    return math.inf if mse == 0 else 10 * math.log10(data_range**2 / mse)


def model_space_psnr(op, p: torch.Tensor) -> list[float]:
    """PSNR per target of what a :class:`~torchproj.transport.TransportOperator` predicts, ``A p / scale``, against the target values.

    Compares, over each target's rows (its camera pixels), the predicted image in target units
    (1 = white) with the target image warped onto those pixels; data range 1. Needs an operator
    built without row merging (merged rows mix pixels).
    """
    from ..transport.operator import check_operator

    check_operator(op)
    check_shape(p, "p", [op.shape[1], op.rhs.shape[1]])
    check(not bool(op.constant.abs().sum() > 0), "model_space_psnr needs an operator built with merge=False")
    pred = op.A(p) / op.scale
    want = op.rhs / op.scale
    return [psnr(pred[op.row_target == k].clamp(0, 1), want[op.row_target == k])
            for k in range(int(op.row_target.max()) + 1)]


def crosstalk(captured: torch.Tensor, others: list[torch.Tensor], mask: torch.Tensor) -> float:
    """How much of other targets' images shows in a capture: the largest absolute Pearson
    correlation, over the mask's pixels (each channel centred on its own mean, then pooled), between
    the capture and each other target's image placed on the same pixels (0: no trace of it; 1: it is
    fully there).

    Args:
        captured: :math:`(C, H, W)` float.
        others: each :math:`(C, H, W)`, as ``captured``.
        mask: :math:`(H, W)` bool, the pixels compared.
    """
    _check_masked(("captured", captured), ("others", others), mask)
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


def explained_share(residual: torch.Tensor, regressors: list[torch.Tensor], mask: torch.Tensor) -> float:
    """Share of a residual's variance that a least-squares mix of regressor images explains.

    Over the mask's pixels, each image is centred per channel (NaN in a regressor, a pixel it says
    nothing about, counts as its mean); one coefficient per regressor, shared by the channels.

    Args:
        residual: :math:`(C, H, W)`, e.g. capture minus target.
        regressors: each :math:`(C, H, W)`, e.g. other targets' images as ghosts would place them.
        mask: :math:`(H, W)` bool.

    Returns:
        :math:`1 - \\|r - G\\beta\\|^2 / \\|r\\|^2` in [0, 1] (0 with no regressors or no residual).
    """
    _check_masked(("residual", residual), ("regressors", regressors), mask)
    r = residual[:, mask].double()
    r = (r - r.mean(1, keepdim=True)).reshape(-1)
    energy = float(r.pow(2).sum())
    if not regressors or energy == 0:
        return 0.0
    columns = []
    for g in regressors:
        g = g[:, mask].double()
        known = torch.isfinite(g)
        mean = torch.where(known, g, 0).sum(1, keepdim=True) / known.sum(1, keepdim=True).clamp_min(1)
        columns.append(torch.where(known, g - mean, 0).reshape(-1))
    G = torch.stack(columns, 1)
    beta = torch.linalg.lstsq(G, r[:, None]).solution
    return float(min(max(1 - float((r[:, None] - G @ beta).pow(2).sum()) / energy, 0.0), 1.0))
