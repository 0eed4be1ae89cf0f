"""Camera in the loop: patterns corrected by what the camera sees of them.

A calibrated transport ``A`` describes the world it was measured in. Once the world drifts (a
projector bumped, a lamp brighter, light bounced between surfaces) the patterns solved on ``A``
miss, and only a capture shows by how much. :func:`refine_patterns` closes the loop: show the
patterns, capture every state, and correct.

Each iteration is one step of the straight-through estimator taken to its end. The capture ``m_k``
of patterns ``p_k`` gives the loss's value; the model gives its gradient, through the surrogate

    m(p) ~ A p + d_k,    d_k = m_k - A p_k,

which equals the capture at ``p_k`` and moves with ``A`` around it. Rather than one gradient step
per capture (captures are what a bench pays for), the surrogate is solved to its optimum in the
box, from ``p_k``, for the next patterns: for least squares that is the bounded solve with the
targets moved by the defect, ``min ||A p - (i - d_k)||^2``, and for an image objective the same
start followed by :func:`~torchproj.solve.solve_ssim` on ``A p + d_k``. Where the world is the
model times a gain ``g`` the predicted light after k captures misses by ``(1 - g)^k`` of the first
miss: a 20% brighter lamp is within 0.2% after four. Camera noise enters through ``d_k``: each
capture's noise moves the next target by that much, so the loop holds its best iterate rather than
its last, and ``relax`` < 1 averages the defect over captures (``d_k = d_{k-1} + relax (m_k - A p_k
- d_{k-1})``) at the price of following a change more slowly (``benchmarks/drift.py`` measures
both). The best captured iterate is returned, the start among them: the loop never returns worse
than it began, as the camera measured it.

The step along the surrogate shrinks as a trust region does (the ratio test of trust-region
methods): by half where a capture is worse than the best, and by half where it is better by less
than a quarter (:data:`OVERPROMISED`) of what the surrogate promised. A world that answers a step
more strongly than the model does (a projector 1.9 times brighter, or moved, with the model's
footprints short of the light's) sends full steps past the optimum: each capture a little better
than the last, a slow 2-cycle about it. A pure gain ``g`` leaves a miss of ``(1 - s g)`` per step
of length ``s``, so half a step brings ``g = 1.9`` within 5%, where full steps keep 90% of it.

This is torchproj's construction (defect correction, also called iterative learning control); the
paper solves once on its calibrated ``A``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import torch

from ..core.checks import check, check_count, check_finite, check_shape, is_number
from ..core.progress import progress_bar
from ..transport.operator import check_operators
from .compensate import check_responses, projectable_patterns
from .model import _one_operator
from .objectives import ImageLoss, image_objective, solve_ssim
from .solvers import check_bounds, solve_fista

__all__ = ["OVERPROMISED", "REFINE_SOLVER_ITERATIONS", "RefineResult", "captured_loss", "carry_patterns", "refine_patterns"]

# FISTA iterations per loop step: the start is the last iterate, one capture away from the optimum,
# so a tenth of a cold solve's work reaches it. On paper_bumped at full size an update takes 0.26-0.31 s
# on the calibrated model's Q, 0.45-0.54 s on a re-registered model's A and A^T (0.68-0.82 s the first:
# its scaling and step bound; docs/camera-in-the-loop.md); when 30 was chosen, 60 kept the same
# captured PSNR there.
REFINE_SOLVER_ITERATIONS = 30
# A capture better than the best by less than this share of the surrogate's promised decrease halves
# the step (the ratio test of trust-region methods, whose textbook shrink threshold this is).
OVERPROMISED = 0.25


@dataclass
class RefineResult:
    """What :func:`refine_patterns` returns.

    Attributes:
        patterns: :math:`(N_{cols}, C)` the best captured iterate's values (in the bounds).
        images: per projector the uint8 images of ``patterns`` (what to show).
        best: which capture it was (0: the start).
        history: per capture, ``{capture, loss, psnr_db and ssim (per target, from the captured
            rows), step, solve_s, predicted}``; ``loss`` is :func:`captured_loss` (or the image
            objective's), ``predicted`` the loss the surrogate promised for that capture's patterns
            (none for the start).
        time_s: the loop's time, captures included.
    """

    patterns: torch.Tensor
    images: list[torch.Tensor]
    best: int
    history: list[dict] = field(default_factory=list)
    time_s: float = 0.0

    def as_dict(self) -> dict:
        return {"captures": len(self.history), "best_capture": self.best, "history": self.history,
                "seconds": round(self.time_s, 3)}


def _operators(op) -> list:
    ops = check_operators(op)
    check(all(o.row_pixel is not None for o in ops), "the loop compares captured camera pixels with the model's rows: "
                                                     "build the operator with merge=False")
    check(len({(o.shape, o.target_count) for o in ops}) == 1,
          "give one operator, or one per colour channel with the same rows and columns (build_channel_transports)")
    return ops


def _rows(ops, values: torch.Tensor) -> torch.Tensor:
    """``A p`` as :math:`(N_{rows}, C)`, one operator or one per channel (column c on operator c)."""
    return _one_operator(ops).A(values)


def _targets(ops) -> torch.Tensor:
    return _one_operator(ops).rhs


def _captured_ssim(op, measured: torch.Tensor, targets: torch.Tensor) -> list[float]:
    """Each target's SSIM (:func:`torchproj.metrics.ssim`) of captured rows placed on the camera."""
    from ..metrics import ssim

    images = op.to_camera((measured / op.scale).clamp(0, 1)).double()
    wanted = op.to_camera(targets / op.scale).double()
    return [float(ssim(images[k], wanted[k], mask)) for k, mask in enumerate(op.camera_masks())]


def captured_loss(op, measured: torch.Tensor) -> tuple[float, list[float]]:
    """The least-squares loss of captured rows, and each target's PSNR from them.

    Args:
        op: the operator (or one per colour channel) whose rows were captured.
        measured: :math:`(N_{rows}, C)` camera values above black at the rows' pixels.

    Returns:
        ``(loss, psnr_db)``: ``||m - i||^2`` (the solver's objective, measured instead of
        predicted) and per target the PSNR of ``m / scale`` against its target values.
    """
    ops = _operators(op)
    check_shape(measured, "measured", [ops[0].shape[0], len(ops) if len(ops) > 1 else "C"])
    err = (measured.double() - _targets(ops).double()).pow(2)
    first = ops[0]
    per_target = torch.zeros(first.target_count, dtype=torch.float64, device=err.device)
    per_target.index_add_(0, first.row_target, err.sum(1))
    counts = torch.bincount(first.row_target, minlength=first.target_count).double() * err.shape[1]
    mse = per_target / counts.clamp_min(1) / first.scale ** 2
    return float(err.sum()), [10 * math.log10(1 / v) if v > 0 else math.inf for v in mse.tolist()]


def carry_patterns(p: torch.Tensor, old, new) -> torch.Tensor:
    """Values on ``old``'s columns carried to ``new``'s by projector cell (a cell new to ``new`` gets 0)."""
    images = old.to_images(p)
    out = p.new_zeros(new.shape[1], p.shape[1])
    for j, img in enumerate(images):
        sel = new.column_projector == j
        out[sel] = img.flatten(1)[:, new.column_cell[sel]].T
    return out


def check_relax(relax, name: str = "relax") -> float:
    """The share of each new defect the loop takes: in (0, 1]."""
    check(is_number(relax) and 0 < relax <= 1,
          f"{name} must be in (0, 1], got {relax!r}")
    return float(relax)


def refine_patterns(op, start: torch.Tensor, measure: Callable[[list[torch.Tensor]], torch.Tensor],
                    bounds=(0.0, 1.0), responses=None, *, iterations: int = 4, objective="l2", relax: float = 1.0,
                    solver_iterations: int = REFINE_SOLVER_ITERATIONS, outside: str = "clip",
                    progress: bool | None = None, remodel=None) -> RefineResult:
    """Correct patterns from captures of them (module docs): ``iterations`` updates, one capture each
    and one of the start, the best captured iterate returned.

    Args:
        op: the calibrated :class:`~torchproj.transport.TransportOperator` with rows on camera
            pixels (``merge=False``), or one per colour channel with the same rows and columns.
        start: :math:`(N_{cols}, C)` patterns in ``bounds`` (any solver's).
        measure: shows per projector uint8 images :math:`(C, H_j, W_j)` and returns the captured
            rows, :math:`(N_{rows}, C)` camera values above the black capture at each row's pixel in
            its target's state (:func:`torchproj.pipeline.rig_measure` on the virtual rig; a bench's
            camera otherwise).
        bounds: the box, linear light.
        responses: per projector its :class:`~torchproj.calib.ResponseCurve` (compensation).
        iterations: updates (captures of patterns: ``iterations + 1``).
        objective: ``l2``, ``ssim``, ``mixed`` or an :class:`~torchproj.solve.ImageObjective`.
        relax: the share of each new defect taken (1: all; smaller averages camera noise).
        solver_iterations: FISTA iterations per update.
        outside: how values outside [0, 1] are shown (:func:`~torchproj.solve.to_projectable`).
        remodel: None, or ``remodel(op, p, measured)`` called after each capture but the last: a new
            operator (or list) with the same rows where the capture shows the model has moved (the
            virtual rig's run re-registers the maps, :func:`torchproj.pipeline.register_maps`), else
            None. Patterns are carried to its columns by projector cell.

    Returns:
        a :class:`RefineResult`; ``patterns`` in the last operator's columns.
    """
    ops = _operators(op)
    lo, hi = check_bounds(bounds)
    iterations = check_count(iterations, "iterations", 0)
    relax = check_relax(relax)
    solver_iterations = check_count(solver_iterations, "solver_iterations")
    check(responses is not None, "give the projectors' response curves: the loop shows 8-bit patterns")
    check_responses(responses, len(ops[0].projector_sizes))
    check(callable(measure), f"measure must be a function of the patterns that returns the captured rows, got "
                             f"{type(measure).__name__}")
    check(remodel is None or callable(remodel), f"remodel must be None or a function that gives the operator "
                                                f"again, got {type(remodel).__name__}")
    check_shape(start, "start", [ops[0].shape[1], len(ops) if len(ops) > 1 else "C"])
    check_finite(start, "start")
    image = image_objective(objective)
    t0 = time.perf_counter()
    targets = _targets(ops)
    p = start.detach().clamp(lo, hi)
    best = None  # {loss, capture, p, images, measured, defect}
    step = 1.0
    form = "auto"  # the normal equations' form the updates solve on (_update)
    promised = None  # the surrogate's loss at the best iterate and at the patterns shown next
    history = []
    bar = progress_bar(desc="refine", enabled=progress, total=iterations + 1)
    for k in range(iterations + 1):
        images = projectable_patterns(ops[0], p, (lo, hi), responses, outside)[1]
        measured = measure(images)
        check_shape(measured, "measure(...)'s rows", list(targets.shape))
        # A capture that is not light (NaN from a failed read, an inf) would end the loop deep in its
        # scores; what the camera gave back is named instead.
        check_finite(measured, f"measure(...)'s rows of capture {k}")
        measured = measured.to(targets)
        loss, psnr_db = captured_loss(ops, measured)
        if image is not None:
            if k == 0:  # the image loss of every capture, its squared error relative to the start's capture
                image_loss = ImageLoss(ops, p, image.l2_weight, image.psnr_drop, offset=measured - _rows(ops, p))
            with torch.no_grad():
                loss = float(image_loss.of_rows(measured))
        history.append({"capture": k, "loss": loss, "psnr_db": psnr_db, "ssim": _captured_ssim(ops[0], measured, targets),
                        "step": step})
        if promised is not None:
            history[-1]["predicted"] = promised[1]
        new_ops = remodel(ops, p, measured) if remodel is not None and k < iterations else None
        if new_ops is not None:
            new_ops = _operators(new_ops)
            check(new_ops[0].shape[0] == ops[0].shape[0] and len(new_ops) == len(ops),
                  "remodel must keep the operator's rows (the same camera pixels) and channels")
            p = carry_patterns(p, ops[0], new_ops[0])
            if best is not None:
                best["p"] = carry_patterns(best["p"], ops[0], new_ops[0])
                best["defect"] = best["measured"] - _rows(new_ops, best["p"])
            ops = new_ops
            form = "products"
            history[-1]["remodelled"] = True
        with torch.no_grad():
            fresh = measured - _rows(ops, p)
        if best is None or loss < best["loss"]:
            if promised is not None and best["loss"] - loss < OVERPROMISED * (promised[0] - promised[1]):
                # Better, but by far less than the surrogate promised: the world answers the step
                # differently from the model at that length (a 2-cycle about the optimum where it
                # answers more strongly). Shorter steps from here on, as a trust region shrinks.
                step /= 2
            defect = fresh if best is None or new_ops is not None else best["defect"] + relax * (fresh - best["defect"])
            best = {"loss": loss, "capture": k, "p": p, "images": images, "measured": measured, "defect": defect}
        else:
            # The capture got worse than the best: the model's direction is wrong at that length (a world
            # the model does not describe, noise). Back to the best iterate, half the step along the surrogate's.
            step /= 2
        bar.update(1)
        if k == iterations:
            break
        t_solve = time.perf_counter()
        base = best["p"]
        target = _update(ops, base, best["defect"], (lo, hi), image, solver_iterations, form)
        p = base + step * (target - base)
        promised = _surrogate_loss(ops, (base, p), best["defect"], image_loss if image is not None else None)
        history[-1]["solve_s"] = round(time.perf_counter() - t_solve, 4)
    bar.close()
    return RefineResult(patterns=best["p"], images=best["images"], best=best["capture"], history=history,
                        time_s=time.perf_counter() - t0)


def _surrogate_loss(ops, patterns, defect: torch.Tensor, image_loss) -> tuple[float, ...]:
    """The loop's loss as the surrogate ``A p + defect`` predicts it, for each of ``patterns``: the
    captures' loss (:func:`captured_loss`, or the image objective's) on the predicted rows."""
    out = []
    with torch.no_grad():
        for p in patterns:
            rows = _rows(ops, p) + defect
            out.append(float(image_loss.of_rows(rows)) if image_loss is not None else captured_loss(ops, rows)[0])
    return tuple(out)


def _update(ops, p: torch.Tensor, defect: torch.Tensor, bounds, image, solver_iterations: int,
            form: str = "auto") -> torch.Tensor:
    """The surrogate's optimum from ``p``: the bounded least squares on the targets less the defect,
    then the image objective on ``A p + defect`` where one is asked.

    ``form``: the normal equations' (:func:`~torchproj.solve.solve_fista`). The loop passes
    ``"products"`` once a remodel has given it new operators: their ``Q`` would be built inside the
    next update, which on the default rig (``torchproj run paper_bumped --refine 4``) took that
    update to 0.87-1.25 s (``Q`` 0.45 s, its scaling and bound 0.4 s, before 30 iterations), over
    the loop's 1 s an update. On ``A`` and ``A^T`` it takes 0.68-0.82 s, and each later update
    0.45-0.54 s against 0.26-0.31 s: the loop's total is 0.3-0.4 s longer (11.5-12.3 against
    11.1-12.0 s, five runs alternating), the same captured scores (docs/camera-in-the-loop.md)."""
    for o in ops:  # built (or found) on the operator itself, so that every update's targets share it
        o.normal_equations(form)
    moved = [o.with_rhs(o.rhs - (defect if len(ops) == 1 else defect[:, c:c + 1])) for c, o in enumerate(ops)]
    solved = [solve_fista(o, bounds, x0=p if len(ops) == 1 else p[:, c:c + 1], max_iter=solver_iterations,
                          progress=False, form=form).patterns for c, o in enumerate(moved)]
    p = solved[0] if len(ops) == 1 else torch.cat(solved, 1)
    if image is None:
        return p
    return solve_ssim(ops, bounds, l2_weight=image.l2_weight, psnr_drop=image.psnr_drop, x0=p,
                      max_iter=image.iterations, offset=defect, progress=False).patterns

