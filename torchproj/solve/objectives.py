"""Objectives beyond least squares: SSIM on the predicted camera images, anchored by a little L2.

The paper scores SSIM, and every bounded least-squares solver minimises squared error; the two
disagree. :func:`solve_ssim` minimises, over patterns in the box, the image-space loss

    (1/K) sum_k [ (1 - SSIM_k) + w MSE_k / MSE_k(start) ]

where SSIM_k is the score the evaluation reports (:func:`torchproj.metrics.ssim`) of target k's
predicted image (:class:`~torchproj.solve.ProjectionModel`) against its target image, and MSE_k
its mean squared error, relative to the start's, so that ``w`` does not depend on the scene's
brightness: ``w`` is the SSIM the loss gives up to keep a target's squared error from doubling
(3 dB). Pure SSIM (``w = 0``) gives one target away: on the paper's rig it sacrifices the near
image (-7 dB) for the far one. The choice of ``w`` per named objective, of the start (the L2
optimum) and of the optimiser (clamped Adam) are torchproj's, measured in
``benchmarks/objectives.py``; the paper optimises least squares only.
"""

from __future__ import annotations

import time

import torch

from ..core.checks import check
from ..metrics import SSIMLoss
from ..transport.operator import TransportOperator
from .model import ProjectionModel
from ..core.progress import progress_bar
from .solvers import ClampedAdam, SolveResult, check_bounds, solve_fista

__all__ = ["OBJECTIVES", "image_objective", "solve_ssim"]

# Objective name -> weight w of the relative squared error (None: least squares itself).
OBJECTIVES = {"l2": None, "ssim": 0.1, "mixed": 1.0}


def image_objective(name: str, l2_weight: float | None = None) -> float | None:
    """The weight ``w`` of an objective by name (``l2``, ``ssim``, ``mixed``), or ``l2_weight`` if given.

    Returns None for ``l2`` (least squares, no image-space loss).
    """
    check(name in OBJECTIVES, f"objective must be one of {list(OBJECTIVES)}, got {name!r}")
    if name == "l2":
        check(l2_weight is None, "l2_weight weighs the squared error against SSIM: give it with objective 'ssim' or "
                                 "'mixed'")
        return None
    weight = OBJECTIVES[name] if l2_weight is None else float(l2_weight)
    check(weight >= 0 and weight == weight and weight != float("inf"),
          f"l2_weight must be a finite number >= 0, got {l2_weight}")
    return weight


def _squared_error(op: TransportOperator):
    """Per target, the mean squared error of predicted rows (target units): a function (N_rows, C) -> (K,).

    Rows of one target are contiguous in an operator from :func:`~torchproj.transport.build_transport`,
    so each target's sum is a slice's; otherwise they are gathered by ``row_target``.
    """
    want = op.rhs / op.scale
    counts = torch.bincount(op.row_target, minlength=op.target_count)
    pixels = counts.to(want.dtype) * op.channels
    contiguous = bool((op.row_target[1:] >= op.row_target[:-1]).all())
    sizes = counts.tolist()

    def error(rows: torch.Tensor) -> torch.Tensor:
        err = (rows - want).pow_(2).sum(1)
        if contiguous:
            total = torch.stack([part.sum() for part in err.split(sizes)])
        else:
            total = torch.zeros(op.target_count, dtype=err.dtype, device=err.device).index_add(0, op.row_target, err)
        return total / pixels

    return error


def solve_ssim(op: TransportOperator, bounds=(0.0, 1.0), *, l2_weight: float = OBJECTIVES["ssim"],
               x0: torch.Tensor | None = None, max_iter: int = 30, lr: float = 1e-2, tol: float = 1e-4,
               progress: bool | None = None) -> SolveResult:
    """Patterns that maximise the targets' SSIM, with a weight on their squared error (module docs).

    Clamped Adam from ``x0`` (default: the bounded least-squares optimum, FISTA), one prediction
    and its gradient per iteration. On the paper's full-size rig an iteration takes ~0.2 s on 2
    cores and 30 of them lift captured SSIM from 0.56 / 0.61 to ~0.69 / 0.77
    (``benchmarks/objectives.py``).

    Args:
        op: an operator whose rows are camera pixels (``build_transport(..., merge=False)``).
        bounds: the box, linear light.
        l2_weight: ``w``: 0.1 is :data:`OBJECTIVES` ``ssim``, 1.0 ``mixed``.
        x0: start inside the box; None: FISTA's solution.
        max_iter: Adam iterations.
        lr: Adam's learning rate (linear light per step).
        tol: stop when the loss fell by less than this (relative) over the last 5 iterations.

    Returns:
        a :class:`SolveResult` with ``objective`` the image-space loss and ``info`` holding
        ``l2_weight``, the model's SSIM per target (``model_ssim``), the least-squares objective
        of the patterns (``l2_objective``) and the start's (``start_l2_objective``).
    """
    lo, hi = check_bounds(bounds)
    check(max_iter >= 1, f"max_iter must be >= 1, got {max_iter}")
    check(lr > 0, f"lr must be positive, got {lr}")
    check(l2_weight >= 0, f"l2_weight must be >= 0, got {l2_weight}")
    t0 = time.perf_counter()
    if x0 is None:
        x0 = solve_fista(op, (lo, hi), progress=False).patterns
    model = ProjectionModel(op, (lo, hi), start=x0.clamp(lo, hi))
    ssim_loss = SSIMLoss(model.targets, model.mask)
    squared_error = _squared_error(op)
    with torch.no_grad():
        reference = squared_error(op.A(model.patterns) / op.scale).clamp_min(1e-12)

    def loss_of(p):
        rows = op.A(p) / op.scale
        per_target = ssim_loss(op.to_camera(rows)) + l2_weight * squared_error(rows) / reference
        return per_target.mean()

    opt = ClampedAdam(model.parameters(), lr=lr, bounds=(lo, hi))
    history, start_l2 = [], float(op.objective(model.patterns.detach()))
    bar = progress_bar(desc="ssim", enabled=progress, total=max_iter)
    converged, it = False, 0
    for it in range(1, max_iter + 1):
        opt.zero_grad(set_to_none=True)
        loss = loss_of(model.patterns)
        loss.backward()
        history.append((time.perf_counter() - t0, loss.item()))
        opt.step()
        bar.update(1)
        if it > 5 and history[-6][1] - history[-1][1] <= tol * abs(history[-1][1]):
            converged = True
            break
    bar.close()
    p = model.patterns.detach()
    with torch.no_grad():
        final = float(loss_of(p))
        model_ssim = (1 - ssim_loss(op.to_camera(op.A(p) / op.scale))).tolist()
    history.append((time.perf_counter() - t0, final))
    return SolveResult(patterns=p, iterations=it, objective=final, history=history, time_s=time.perf_counter() - t0,
                       converged=converged, method="ssim",
                       info={"l2_weight": l2_weight, "lr": lr, "model_ssim": model_ssim,
                             "l2_objective": float(op.objective(p)), "start_l2_objective": start_l2})
