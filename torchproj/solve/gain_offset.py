"""Patterns and a per-target gain and offset, optimised together.

The paper's constraint set only limits ``p``, yet a viewer judges an image up to its brightness and
contrast. Letting each target k ask for ``g_k t + o_k`` instead of ``t`` (with the gain and offset in
limits the user sets) gives the solver room where the box constraints bind: a dim, lower-contrast
image the projectors can really make often looks better than a full-contrast one they cannot.

The objective ``||A p - s (g_k t + o_k)||^2`` is minimised by block coordinate descent: FISTA on p
for fixed (g, o), then the exact box-constrained minimiser of the 2x2 quadratic in (g_k, o_k) of each
target for fixed p. Each block step cannot raise the objective, so the sequence is monotone.
"""

from __future__ import annotations

import math
import time

import torch

from ..core.checks import check, check_count, check_shape
from ..core.errors import InputError
from ..transport.operator import TransportOperator
from .solvers import SolveResult, check_bounds, check_operator, solve_fista

__all__ = ["solve_gain_offset"]


def _box_quadratic_2d(H: torch.Tensor, r: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """Minimise ``x^T H x - 2 r^T x`` over the box ``box[:, 0] <= x <= box[:, 1]`` (x of size 2).

    The minimiser is the unconstrained one when it lies inside; otherwise it lies on an edge, where
    the problem is one-dimensional: try all four edges and keep the best.
    """
    H, r = H.double(), r.double()

    def value(x):
        return float(x @ H @ x - 2 * r @ x)

    candidates = []
    if float(torch.linalg.det(H)) > 1e-12 * abs(float(H.diagonal().prod())):
        x = torch.linalg.solve(H, r)
        if bool(((x >= box[:, 0]) & (x <= box[:, 1])).all()):
            return x
    for fixed in (0, 1):
        free = 1 - fixed
        for bound in box[fixed]:
            x = torch.empty(2, dtype=torch.float64)
            x[fixed] = bound
            h = float(H[free, free])
            x[free] = (r[free] - H[free, fixed] * bound) / h if h > 0 else box[free, 0]
            x[free] = x[free].clamp(box[free, 0], box[free, 1])
            candidates.append(x)
    return min(candidates, key=value)


def check_gain_offset(gain, offset) -> tuple[tuple[float, float], tuple[float, float]]:
    """``gain`` and ``offset`` as ``(lo, hi)`` pairs of finite numbers, lo <= hi and a positive upper gain."""
    limits = []
    for name, pair in (("gain", gain), ("offset", offset)):
        try:
            lo, hi = (float(v) for v in pair)
        except (TypeError, ValueError):
            raise InputError(f"{name} must be two numbers (lo, hi), got {pair!r}") from None
        check(math.isfinite(lo) and math.isfinite(hi), f"{name} limits must be finite, got {pair!r}")
        limits.append((lo, hi))
    (g_lo, g_hi), (o_lo, o_hi) = limits
    check(g_lo <= g_hi and o_lo <= o_hi, f"gain and offset limits need lo <= hi, got gain={gain}, offset={offset}")
    check(g_hi > 0, f"the gain's upper limit must be positive (a gain of 0 shows no image), got {gain}")
    return (g_lo, g_hi), (o_lo, o_hi)


def solve_gain_offset(op: TransportOperator, flat: torch.Tensor, bounds=(0.0, 1.0), *, gain=(0.5, 1.5), offset=(-0.2, 0.2),
                      outer: int = 8, max_iter: int = 300, tol: float = 1e-6, progress: bool | None = None) -> SolveResult:
    """Box-constrained patterns plus one gain and offset per target.

    Args:
        op: the operator of the targets t, built with ``merge=False`` so that any ``s (g t + o)`` is
            an exact new right-hand side; its ``row_target`` says which target each row serves.
        flat: :math:`(N_{rows}, C)` the right-hand side of the same rows for targets of constant 1
            (``build_transport`` with all-ones images, ``merge=False`` and the same ``scale``).
        bounds: box for p, as for every solver.
        gain, offset: ``(lo, hi)`` limits for each target's gain g and offset o (target units: the
            image asked for is ``g t + o``; ``gain=(1, 1), offset=(0, 0)`` is the plain problem).
        outer: block-coordinate rounds (p, then gain and offset).
        max_iter: FISTA iterations in total, spread over the rounds.

    Returns:
        :class:`SolveResult` whose ``patterns`` are :math:`(N_{cols}, C)`, with ``info["gain"]`` and
        ``info["offset"]`` (one per target) and ``info["operator"]``, the operator of the final targets.
    """
    check_operator(op)
    lo, hi = check_bounds(bounds)
    (g_lo, g_hi), (o_lo, o_hi) = check_gain_offset(gain, offset)
    check_shape(flat, "flat", [op.shape[0], op.channels])
    check(bool((op.constant == 0).all()), "op must be built with merge=False: merged rows fix the targets")
    check_count(outer, "outer (rounds of gain and offset)")
    check_count(max_iter, "max_iter")
    t0 = time.perf_counter()
    image, ones = op.rhs, flat.to(op.rhs)
    target = op.row_target
    n_targets = int(target.max()) + 1
    g = torch.full((n_targets,), min(max(1.0, g_lo), g_hi), dtype=torch.float64)
    o = torch.full((n_targets,), min(max(0.0, o_lo), o_hi), dtype=torch.float64)
    box = torch.tensor([[g_lo, g_hi], [o_lo, o_hi]], dtype=torch.float64)
    # Per target, the 2x2 Gram of (s t, s) over its rows and channels: the quadratic part in (g, o).
    hess = torch.zeros(n_targets, 2, 2, dtype=torch.float64, device=op.rhs.device)
    for a, u in enumerate((image, ones)):
        for b, v in enumerate((image, ones)):
            hess[:, a, b] = torch.zeros(n_targets, dtype=torch.float64, device=u.device).index_add_(
                0, target, (u.double() * v.double()).sum(1))
    hess = hess.cpu()

    def targets_for(g, o):
        return (g.to(image)[target, None] * image + o.to(image)[target, None] * ones)

    p, history, iterations, moved = None, [], 0, float("inf")
    per_round = max(1, max_iter // outer)
    current = op.with_rhs(targets_for(g, o))
    for _ in range(outer):
        result = solve_fista(current, (lo, hi), max_iter=per_round, tol=tol, x0=p, progress=progress)
        p, iterations = result.patterns, iterations + result.iterations
        history.append((time.perf_counter() - t0, result.objective))
        shown = op.A(p).double()
        lin_t = torch.zeros(n_targets, dtype=torch.float64, device=shown.device).index_add_(
            0, target, (shown * image.double()).sum(1)).cpu()
        lin_1 = torch.zeros(n_targets, dtype=torch.float64, device=shown.device).index_add_(
            0, target, (shown * ones.double()).sum(1)).cpu()
        new = torch.stack([_box_quadratic_2d(hess[k], torch.stack([lin_t[k], lin_1[k]]), box)
                           for k in range(n_targets)])
        moved = float((new[:, 0] - g).abs().max() + (new[:, 1] - o).abs().max())
        g, o = new[:, 0], new[:, 1]
        current = op.with_rhs(targets_for(g, o))
        if moved < 1e-4:
            break
    objective = float(current.objective(p))
    history.append((time.perf_counter() - t0, objective))
    return SolveResult(patterns=p, iterations=iterations, objective=objective, history=history,
                       time_s=time.perf_counter() - t0, converged=moved < 1e-4, method="fista+gain/offset",
                       info={"gain": g.tolist(), "offset": o.tolist(), "operator": current})
