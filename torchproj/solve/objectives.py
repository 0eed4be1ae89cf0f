"""Objectives beyond least squares: SSIM on the predicted camera images, within a PSNR budget.

The paper scores SSIM, and every bounded least-squares solver minimises squared error; the two
disagree. :func:`solve_ssim` minimises, over patterns in the box, the image-space loss

    (1/K) sum_k [ (1 - SSIM_k) + w r_k + mu max(0, 10 log10 r_k - d)^2 ],   r_k = MSE_k / MSE_k(start)

where SSIM_k is the score the evaluation reports (:func:`torchproj.metrics.ssim`) of target k's
predicted image (:class:`~torchproj.solve.ProjectionModel`) against its target image, MSE_k its
mean squared error, relative to the start's (the least-squares optimum), so that nothing depends
on the scene's brightness. ``w`` anchors the squared error (``w`` SSIM buys a target's doubled
error); the hinge keeps each target's PSNR within ``d`` dB of the start (``mu`` = 1 per dB^2 holds
it to ~0.05 dB in the model). Without the hinge the loss trades one target's PSNR for another's
SSIM: on the paper's rig at half size the near image gained up to 2.7 dB while the far one lost up
to 1.6 dB; pure SSIM (``w = 0``) gave the near image away (-1.6 to -3.9 dB). The weights, the start
and the optimiser (clamped Adam at lr 1e-2) are torchproj's choices, measured against the
alternatives in ``benchmarks/objectives.py --study``; the paper optimises least squares only.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch
from torch import nn

from ..core.checks import check, check_count, check_number, check_shape, is_number
from ..core.progress import progress_bar
from ..metrics import SSIMLoss
from ..transport.operator import TransportOperator
from .model import ProjectionModel, _least_squares, _one_operator, check_patterns_shape, image_operator
from .solvers import ClampedAdam, SolveResult, check_bounds

__all__ = ["ImageLoss", "ImageObjective", "OBJECTIVES", "PSNRBudget", "PSNR_DROP_DB", "image_objective", "psnr_hinge",
           "solve_ssim"]

# Objective name -> weight w of the relative squared error (None: least squares itself), and the PSNR
# per target that an image objective may give up against the least-squares start (model, dB); both in
# core.choices, which the command's parser reads.
from ..core.choices import OBJECTIVES, PSNR_DROP_DB  # noqa: E402
_HINGE = 1.0  # mu, per dB^2


@dataclass(frozen=True)
class ImageObjective:
    """An image-space objective's settings (:func:`solve_ssim`; module docs for the loss).

    Attributes:
        name: ``ssim`` or ``mixed`` (for reports).
        l2_weight: ``w``, the weight of each target's relative squared error.
        psnr_drop: ``d``, the dB of PSNR each target may lose against the least-squares start
            (in the model); None: no limit.
        iterations: Adam iterations.
    """

    name: str = "ssim"
    l2_weight: float = OBJECTIVES["ssim"]
    psnr_drop: float | None = PSNR_DROP_DB
    iterations: int = 30


def check_psnr_drop(psnr_drop, optional: bool = True) -> float | None:
    """The dB of PSNR each target may lose against its start: a finite number >= 0 (None: no limit,
    where ``optional``)."""
    if psnr_drop is None and optional:
        return None
    check(is_number(psnr_drop) and math.isfinite(psnr_drop)
          and psnr_drop >= 0, f"psnr_drop must be a finite number of dB >= 0{' (or None: no limit)' if optional else ''}, "
                              f"got {psnr_drop!r}")
    return float(psnr_drop)


def image_objective(name="l2", l2_weight: float | None = None, psnr_drop: float | None = PSNR_DROP_DB,
                    iterations: int = 30) -> ImageObjective | None:
    """An objective by name (``l2``, ``ssim``, ``mixed``) with its defaults, or as given.

    ``name`` may already be an :class:`ImageObjective` (returned as is) or None (least squares).
    Returns None for ``l2``: least squares, no image-space loss.
    """
    if name is None or isinstance(name, ImageObjective):
        return name
    check(isinstance(name, str) and name in OBJECTIVES, f"objective must be one of {list(OBJECTIVES)}, got {name!r}")
    if name == "l2":
        check(l2_weight is None, "l2_weight weighs the squared error against SSIM: give it with objective 'ssim' or "
                                 "'mixed'")
        return None
    weight = OBJECTIVES[name] if l2_weight is None else check_number(l2_weight, "l2_weight")
    psnr_drop = check_psnr_drop(psnr_drop)
    return ImageObjective(name, weight, psnr_drop, check_count(iterations, "iterations (of the SSIM objective)"))


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


def psnr_hinge(ratio: torch.Tensor, psnr_drop: float, weight: float = _HINGE) -> torch.Tensor:
    """``weight * relu(10 log10(ratio) - psnr_drop)^2``: zero while a target's squared error is at most
    ``10^(psnr_drop / 10)`` times its reference's (it has lost at most ``psnr_drop`` dB of PSNR),
    the square of the excess in dB beyond (element-wise, any shape)."""
    check(isinstance(ratio, torch.Tensor), f"ratio must be a torch.Tensor, got {type(ratio).__name__}")
    return _psnr_hinge(ratio, check_psnr_drop(psnr_drop, optional=False), check_number(weight, "weight"))


def _psnr_hinge(ratio: torch.Tensor, psnr_drop: float, weight: float = _HINGE) -> torch.Tensor:
    """:func:`psnr_hinge` for the losses that checked their budget once, when made: they take it on
    every iteration."""
    # Clamped inside the logarithm: at an error of exactly 0 its slope is infinite, and times the
    # hinge's zero that would be NaN.
    return weight * torch.relu(10 * torch.log10(ratio.clamp_min(1e-12)) - psnr_drop) ** 2


class PSNRBudget(nn.Module):
    """A PSNR budget per target, as a loss part: each target may lose at most ``psnr_drop`` dB
    against a reference prediction, and pays the square of the excess beyond it.

    The failure it prevents: a loss summed (or averaged) over targets lets the optimiser buy one
    target's improvement with another's loss. Trained on an L1 + edge loss from the least-squares
    start, the paper's pair went from 19.4 to 31.1 dB on the near target and from 17.8 to 13.5 dB on
    the far one: a better sum, and a far image nobody asked to lose. With the budget added each
    target keeps its PSNR within ``psnr_drop`` of the start while the loss improves what it may
    (:func:`solve_ssim` and ``examples/train_patterns.py`` use it). Our choice, not the paper's.

    Args:
        targets: :math:`(K, C, H, W)` the target images (:attr:`ProjectionModel.targets`).
        mask: :math:`(K, H, W)` bool, each target's pixels (:attr:`ProjectionModel.mask`).
        reference: :math:`(K, C, H, W)` the prediction whose PSNR is the budget's base (the start's:
            ``model()`` before training).
        psnr_drop: the dB each target may lose, >= 0.
        weight: of the squared excess (per dB^2).

    Shape:
        ``forward(prediction)``: :math:`(K, C, H, W)` -> :math:`(K,)`, or :math:`(B, K, C, H, W)` ->
        :math:`(B, K)`; sum or average it with the rest of the loss.
    """

    def __init__(self, targets: torch.Tensor, mask: torch.Tensor, reference: torch.Tensor,
                 psnr_drop: float = PSNR_DROP_DB, weight: float = _HINGE):
        super().__init__()
        check_shape(targets, "targets", ["K", "C", "H", "W"])
        check_shape(mask, "mask", [targets.shape[0], targets.shape[2], targets.shape[3]])
        check_shape(reference, "reference", list(targets.shape))
        self.psnr_drop, self.weight = check_psnr_drop(psnr_drop, optional=False), check_number(weight, "weight")
        self.register_buffer("targets", targets.detach())
        self.register_buffer("weights", mask[:, None].to(targets.dtype))
        self.register_buffer("reference_error", self.squared_error(reference.detach()).clamp_min(1e-12))

    def squared_error(self, prediction: torch.Tensor) -> torch.Tensor:
        """Each target's mean squared error over its pixels: :math:`(..., K)`."""
        pixels = self.weights.sum((-3, -2, -1)) * self.targets.shape[1]
        return ((prediction - self.targets) ** 2 * self.weights).sum((-3, -2, -1)) / pixels

    def ratio(self, prediction: torch.Tensor) -> torch.Tensor:
        """Each target's squared error over the reference's: :math:`(..., K)` (a loss term of its own)."""
        return self.squared_error(prediction) / self.reference_error

    def hinge(self, ratio: torch.Tensor) -> torch.Tensor:
        """The budget's penalty for ratios :meth:`ratio` already gave (a loop that uses both)."""
        return _psnr_hinge(ratio, self.psnr_drop, self.weight)

    def psnr_change(self, prediction: torch.Tensor) -> torch.Tensor:
        """Each target's PSNR change against the reference, dB: :math:`(..., K)`."""
        return -10 * torch.log10(self.ratio(prediction).clamp_min(1e-12))

    def forward(self, prediction: torch.Tensor) -> torch.Tensor:
        return self.hinge(self.ratio(prediction))


class ImageLoss(nn.Module):
    """The loss :func:`solve_ssim` minimises, as a function of the patterns (module docs).

    For an optimiser of your own: ``loss = ImageLoss(op, start); loss(p).backward()``.

    Args:
        op: an operator whose rows are camera pixels (``build_transport(..., merge=False)``), or
            one per colour channel (:func:`~torchproj.transport.build_channel_transports`), each
            channel then predicted with its own weights.
        start: :math:`(N_{cols}, C)` the patterns whose squared error the terms are relative to
            (the least-squares optimum).
        l2_weight, psnr_drop: ``w`` and ``d`` of the module docs (``d`` None: no limit).
        offset: :math:`(N_{rows}, C)` camera values added to every prediction, ``A p + offset``
            (what a capture showed the model misses: :func:`~torchproj.solve.refine_patterns`);
            None: the model as it is.

    Shape:
        ``forward(p)``: :math:`(N_{cols}, C)` -> a 0-dim tensor, the mean over targets.
    """

    def __init__(self, op: TransportOperator | list[TransportOperator], start: torch.Tensor,
                 l2_weight: float = OBJECTIVES["ssim"], psnr_drop: float | None = PSNR_DROP_DB,
                 offset: torch.Tensor | None = None):
        super().__init__()
        l2_weight = check_number(l2_weight, "l2_weight")
        psnr_drop = check_psnr_drop(psnr_drop)
        # The start may lie anywhere a solve's box allows (EO_-100^255's below 0): a model of it, whose
        # box is [0, 1] unless told, refused such a start; only the targets and masks are needed.
        op = image_operator(op)
        check_patterns_shape(op, start)
        self.op, self.l2_weight, self.psnr_drop = op, float(l2_weight), psnr_drop
        if offset is not None:
            check_shape(offset, "offset", list(op.rhs.shape))
        self.offset = offset
        self.ssim_loss = SSIMLoss(op.to_camera(op.rhs / op.scale), op.camera_masks())
        self.squared_error = _squared_error(op)
        with torch.no_grad():
            start_rows = self._predict(start.detach())
            self.register_buffer("reference", self.squared_error(start_rows / op.scale).clamp_min(1e-12))

    def _predict(self, p: torch.Tensor) -> torch.Tensor:
        rows = self.op.A(p)
        return rows if self.offset is None else rows + self.offset

    def terms(self, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per target, ``1 - SSIM`` and the squared error relative to the start's: two :math:`(K,)`."""
        return self.row_terms(self._predict(p))

    def row_terms(self, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`terms` of camera values at the rows (predicted, or captured), :math:`(N_{rows}, C)`."""
        rows = rows / self.op.scale
        return self.ssim_loss(self.op.to_camera(rows)), self.squared_error(rows) / self.reference

    def forward(self, p: torch.Tensor) -> torch.Tensor:
        return self._combine(*self.terms(p))

    def of_rows(self, rows: torch.Tensor) -> torch.Tensor:
        """The loss of camera values at the rows (a capture's, :func:`~torchproj.solve.refine_patterns`)."""
        return self._combine(*self.row_terms(rows))

    def _combine(self, dissimilarity: torch.Tensor, ratio: torch.Tensor) -> torch.Tensor:
        per_target = dissimilarity + self.l2_weight * ratio
        if self.psnr_drop is not None:
            # Clamped inside the logarithm: at an error of exactly 0 its slope is infinite, and times
            # the hinge's zero that would be NaN.
            per_target = per_target + _psnr_hinge(ratio, self.psnr_drop)
        return per_target.mean()

    @torch.no_grad()
    def report(self, p: torch.Tensor) -> dict:
        """The model's SSIM per target, and its PSNR change against the start (dB)."""
        dissimilarity, ratio = self.terms(p)
        return {"model_ssim": (1 - dissimilarity).tolist(),
                "model_psnr_change_db": (-10 * torch.log10(ratio.clamp_min(1e-12))).tolist()}


def solve_ssim(op: TransportOperator | list[TransportOperator], bounds=(0.0, 1.0), *, l2_weight: float = OBJECTIVES["ssim"],
               psnr_drop: float | None = PSNR_DROP_DB, x0: torch.Tensor | None = None, max_iter: int = 30,
               lr: float = 1e-2, tol: float = 1e-4, progress: bool | None = None,
               offset: torch.Tensor | None = None) -> SolveResult:
    """Patterns that maximise the targets' SSIM within a PSNR budget (module docs; :class:`ImageLoss`).

    Clamped Adam from ``x0`` (default: the bounded least-squares optimum, FISTA), one prediction
    and its gradient per iteration; the best iterate seen is returned (the start where nothing
    beats it). On the paper's full-size rig an iteration takes ~0.16 s on 2 cores (grey; ~0.6 s in
    RGB), and 30 of them lift captured SSIM by 0.13-0.26 on the paper's image pairs
    (``benchmarks/objectives.py``, which also compares other optimisers and weights).

    Args:
        op: an operator whose rows are camera pixels (``build_transport(..., merge=False)``), or
            one per colour channel (:func:`~torchproj.transport.build_channel_transports`): the
            loss is over the whole image, each channel predicted with its own weights.
        bounds: the box, linear light.
        l2_weight: ``w``: 0.1 is :data:`OBJECTIVES` ``ssim``, 1.0 ``mixed``.
        psnr_drop: ``d``, the dB of PSNR each target may lose against ``x0`` in the model; None: no limit.
        x0: start inside the box; None: FISTA's solution, with ``torchproj run``'s smoothness penalty.
        max_iter: Adam iterations.
        lr: Adam's learning rate (linear light per step).
        tol: stop when the loss fell by less than this (relative) over the last 5 iterations.
        offset: camera values added to the model's prediction (:class:`ImageLoss`).

    Returns:
        a :class:`SolveResult` with ``objective`` the image-space loss and ``info`` holding
        ``l2_weight``, ``psnr_drop``, the model's SSIM per target (``model_ssim``) and its PSNR
        change against the start (``model_psnr_change_db``), the least-squares objective of the
        patterns (``l2_objective``) and the start's (``start_l2_objective``).
    """
    lo, hi = check_bounds(bounds)
    max_iter, tol = check_count(max_iter, "max_iter"), check_number(tol, "tol")
    lr = check_number(lr, "lr", strict=True)
    t0 = time.perf_counter()
    op = _one_operator(op)
    if x0 is None:
        x0 = _least_squares(op, (lo, hi))
    check_patterns_shape(op, x0, "x0")  # before the clamp, which a number or a list would fail in
    x0 = x0.clamp(lo, hi)
    loss_of = ImageLoss(op, x0, l2_weight, psnr_drop, offset=offset)
    model = ProjectionModel(op, (lo, hi), start=x0)
    opt = ClampedAdam(model.parameters(), lr=lr, bounds=(lo, hi))
    history, start_l2 = [], float(op.objective(x0))
    bar = progress_bar(desc="ssim", enabled=progress, total=max_iter)
    # Adam's first steps move every cell by about lr whatever its gradient: where the start already
    # fits the model well (box_cylinders: model SSIM 0.98), that is noise the loss may never win back
    # in a few iterations. The best iterate seen is returned, the start included.
    best, best_p = math.inf, None
    converged, it = False, 0
    for it in range(1, max_iter + 1):
        opt.zero_grad(set_to_none=True)
        loss = loss_of(model.patterns)
        loss.backward()
        history.append((time.perf_counter() - t0, loss.item()))
        if history[-1][1] < best:
            best, best_p = history[-1][1], model.patterns.detach().clone()
        opt.step()
        bar.update(1)
        if it > 5 and history[-6][1] - history[-1][1] <= tol * abs(history[-1][1]):
            converged = True
            break
    bar.close()
    with torch.no_grad():
        last = float(loss_of(model.patterns))
    p = model.patterns.detach() if last < best else best_p
    final = min(last, best)
    history.append((time.perf_counter() - t0, final))
    return SolveResult(patterns=p, iterations=it, objective=final, history=history, time_s=time.perf_counter() - t0,
                       converged=converged, method="ssim",
                       info={"l2_weight": l2_weight, "psnr_drop": psnr_drop, "lr": lr, **loss_of.report(p),
                             "l2_objective": float(op.objective(p)), "start_l2_objective": start_l2})
