"""Least squares through a colour camera's mixing of the projectors' primaries.

A colour camera's channel c sees ``q_c = sum_p N[c, p] x_p`` of a projector cell's primaries x
(:func:`~torchproj.calib.fit_colour_mixing`; conventions module, "Colour"). The transport model is
written in what the camera sees, one channel at a time, so a solver's box on q is the cube
``[lo, hi]^3``, while what the primaries can give is its image under N, a smaller slanted box: a
saturated colour solved in q lies outside it, and undoing the mixing then clips. Solved in the
primaries instead, the channels couple through N:

    ``min_x sum_c ||A_c (x N^T)_c - t_c||^2``  subject to  ``lo <= x <= hi``,

whose gradient is ``(grad_q) N`` with ``grad_q`` the channels' own gradients. This module runs FISTA
on it from the channel solve's answer, brought into the primaries' box (our method; the paper's
camera and projectors are grey).
"""

from __future__ import annotations

import dataclasses
import time

import torch

from ..calib.response import check_mixing
from ..core.checks import check, check_count
from ..transport.operator import check_operators
from .solvers import SolveResult, check_bounds

__all__ = ["MIXING_ITERATIONS", "solve_through_mixing"]

MIXING_ITERATIONS = 200


def _mixing_per_column(op, mixings: list[torch.Tensor | None], channels: int) -> torch.Tensor:
    """:math:`(N_{cols}, C, C)` each column's projector's mixing (identity where it has none, and for
    one channel)."""
    eye = torch.eye(channels, dtype=op.val.dtype, device=op.val.device)
    stack = torch.stack([eye if m is None or channels == 1 else m.to(eye) for m in mixings])
    return stack[op.column_projector.long()]


def solve_through_mixing(ops, result, mixings: list[torch.Tensor | None], bounds: tuple[float, float], *,
                         max_iter: int = MIXING_ITERATIONS, extra=None):
    """Refine a channel-by-channel solution in the projectors' primaries (module docstring).

    Args:
        ops: one operator with the channels as right-hand sides, or one single-channel operator per
            colour channel with the same columns (:func:`~torchproj.transport.build_channel_transports`).
        result: the channels' :class:`~torchproj.solve.SolveResult`, values ``q`` :math:`(N_{cols}, C)`
            as the camera sees them.
        mixings: per projector, its :math:`(3, 3)` mixing (rows summing to 1), or None for none.
        bounds: the box on what the primaries emit (within [0, 1]).
        extra: None, or per channel a further linear term of the light with ``forward(q_c)`` and
            ``adjoint(r_c)`` (the bounce between surfaces of the exact light,
            :class:`~torchproj.pipeline.ceiling.BounceTerm`): channel c then sees ``A_c q_c + B_c q_c``.

    Returns:
        the result with ``patterns`` the camera's view ``x N^T`` of the refined primaries (what
        :meth:`~torchproj.calib.ResponseCurve.to_pattern` turns back into x) and ``info["mixing"]``
        saying what the refinement gained.
    """
    lo, hi = check_bounds(bounds)
    check(0 <= lo < hi <= 1, f"a solve through colour mixing needs bounds within [0, 1], got {bounds}")
    ops = check_operators(ops, "ops")
    max_iter = check_count(max_iter, "max_iter", 0)
    check(isinstance(result, SolveResult) and isinstance(result.patterns, torch.Tensor)
          and result.patterns.dim() == 2 and result.patterns.shape[0] == ops[0].shape[1],
          f"result must be the channels' SolveResult, patterns ({ops[0].shape[1]}, C) for the operator's columns, "
          f"got {type(result).__name__}")
    t0 = time.perf_counter()
    q = result.patterns
    n_ch = q.shape[1]
    check(n_ch in (1, 3), f"the solution must have 1 or 3 channels, got {n_ch}")
    check(len(ops) in (1, n_ch) and all(op.shape[1] == ops[0].shape[1] for op in ops),
          f"ops must be one operator, or one per channel ({n_ch}) with the same columns, got {len(ops)}")
    projectors = len(ops[0].projector_sizes)
    check(isinstance(mixings, (list, tuple)) and len(mixings) == projectors,
          f"mixings must be a list of one (3, 3) mixing or None per projector ({projectors}), got "
          f"{type(mixings).__name__}{f' of {len(mixings)}' if isinstance(mixings, (list, tuple)) else ''}")
    for j, m in enumerate(mixings):
        if m is not None:
            check_mixing(m, f"mixings[{j}]")
    check(extra is None or (isinstance(extra, (list, tuple)) and len(extra) == n_ch
                            and all(callable(getattr(e, "forward", None)) and callable(getattr(e, "adjoint", None))
                                    for e in extra)),
          f"extra must be None or one term per channel ({n_ch}) with forward and adjoint, got {type(extra).__name__}")
    mix = _mixing_per_column(ops[0], mixings, n_ch)
    channels = [(ops[0] if len(ops) == 1 else ops[c], c) for c in range(n_ch)]  # each channel's operator

    def light(op, c, v):  # channel c's camera values for its column of values v
        seen = op.A(v)
        return seen if extra is None else seen + extra[c].forward(v)

    def objective_and_gradient(x: torch.Tensor):
        seen = torch.einsum("ncp,np->nc", mix, x)
        grad_q = torch.empty_like(seen)
        value = 0.0
        for op, c in channels:
            rhs = op.rhs[:, c:c + 1] if op.rhs.shape[1] == n_ch else op.rhs
            residual = light(op, c, seen[:, c:c + 1]) - rhs
            value += float(residual.pow(2).sum())
            grad_q[:, c:c + 1] = op.A_adjoint(residual) + (0 if extra is None else extra[c].adjoint(residual))
        return value, torch.einsum("ncp,nc->np", mix, grad_q)

    with torch.no_grad():
        inverse = torch.linalg.inv(mix.double()).to(q)
        x = torch.einsum("npc,nc->np", inverse, q).clamp(lo, hi)
        step = 1 / _curvature(channels, mix, extra, light, q)
        start, _ = objective_and_gradient(x)
        first, y, momentum = x.clone(), x.clone(), 1.0
        for _ in range(max_iter):
            _, grad = objective_and_gradient(y)
            nxt = (y - step * grad).clamp(lo, hi)
            if float(((y - nxt) * (nxt - x)).sum()) > 0:  # O'Donoghue and Candes' restart
                momentum, y = 1.0, x.clone()
                continue
            following = (1 + (1 + 4 * momentum**2) ** 0.5) / 2
            y = nxt + (momentum - 1) / following * (nxt - x)
            x, momentum = nxt, following
        end, _ = objective_and_gradient(x)
        if end > start:  # FISTA is not monotone: never return worse than where it started
            x, end = first, start
        seen = torch.einsum("ncp,np->nc", mix, x)
    info = {**result.info, "mixing": {"residual_clipped": start, "residual": end, "iterations": max_iter,
                                      "seconds": round(time.perf_counter() - t0, 3)}}
    return dataclasses.replace(result, patterns=seen, objective=end, info=info,
                               time_s=result.time_s + time.perf_counter() - t0)


def _curvature(channels, mix, extra, light, q, iterations: int = 30) -> float:
    """An upper bound of the coupled objective's curvature: the largest channel's, by power iteration
    on its (direct plus extra) operator, times the mixing's largest squared singular value, plus 1%.
    Seeded, unlike :meth:`~torchproj.transport.TransportOperator.lipschitz`: the same patterns come
    back each time, which ``torchproj refine``'s replay relies on."""
    worst = 0.0
    if extra is None:  # channels on one operator share its curvature: one power iteration per operator
        channels = list({id(op): (op, c) for op, c in channels}.values())
    for op, c in channels:
        v = torch.rand(q.shape[0], 1, generator=torch.Generator().manual_seed(0), dtype=q.dtype).to(q.device)
        value = 0.0
        for _ in range(iterations):
            w = light(op, c, v / v.norm())
            v = op.A_adjoint(w) + (0 if extra is None else extra[c].adjoint(w))
            value = float(v.norm())
            if value == 0:
                break
        worst = max(worst, value)
    return 1.01 * worst * float(torch.linalg.matrix_norm(mix, 2).max()) ** 2
