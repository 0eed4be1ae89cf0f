"""Box-constrained least squares ``min ||A p - i||^2  s.t.  lo <= p <= hi`` on a transport operator.

The solvers know only the operator: ``A`` and ``A_adjoint`` (Adam, through autograd) or its
normal equations ``Q = A^T A``, ``q = A^T i`` (PGD, FISTA, LF: one sparse product per iteration). A
box constraint is a projection, a clamp. Bounds are in linear relative light, the paper's 8-bit bounds
divided by 255 (``EO_0^255`` is ``(0, 1)``, ``EO_-100^255`` is ``(-100/255, 1)``); bounds outside
[0, 1] are brought back into the projectable range by :func:`to_projectable`.
"""

from __future__ import annotations

import contextlib
import math
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import torch

from ..core.checks import check, check_count, check_finite, check_number, check_shape
from ..core.errors import InputError
from ..core.fused import fused
from ..core.progress import progress_bar
from ..transport.operator import SUM_RUN, TransportOperator, check_operator

__all__ = ["OUTSIDE", "LF_NORMALISE", "SolveResult", "ClampedAdam", "solve_pgd", "solve_fista", "solve_adam", "solve_lf", "solve_target_sets", "to_projectable",
           "check_bounds"]


@dataclass
class SolveResult:
    """What every solver returns.

    Attributes:
        patterns: :math:`(N_{cols}, C)` solved values (in the bounds the solver was given).
        iterations: iterations (or operator applications for LF) performed.
        objective: final ``||A p - i||^2``.
        history: ``(seconds since start, objective)`` after each iteration.
        time_s: wall time.
        converged: whether the stopping rule fired before the iteration limit.
        method: the solver's name.
        info: solver-specific facts (EO: number and sizes of chains, share of A it kept).
    """

    patterns: torch.Tensor
    iterations: int
    objective: float
    history: list[tuple[float, float]] = field(default_factory=list)
    time_s: float = 0.0
    converged: bool = False
    method: str = ""
    info: dict = field(default_factory=dict)


def check_bounds(bounds: tuple[float, float]) -> tuple[float, float]:
    """``bounds`` as two floats ``(lo, hi)``, finite and ordered; an :class:`InputError` otherwise."""
    try:
        lo, hi = (float(b) for b in bounds)
    except (TypeError, ValueError):
        raise InputError(f"bounds must be two numbers (lo, hi) in linear light, 0 black and 1 white; got {bounds!r}") \
            from None
    check(math.isfinite(lo) and math.isfinite(hi), f"bounds must be finite numbers, got {bounds}")
    check(lo < hi, f"bounds must satisfy lo < hi, got lo={lo:g}, hi={hi:g}")
    return lo, hi


from ..core.choices import OUTSIDE  # noqa: E402  how a solution whose bounds leave [0, 1] is shown: to_projectable


def check_outside(outside: str) -> None:
    """``outside`` names one of :data:`OUTSIDE` (one message for every entry point)."""
    check(outside in OUTSIDE, f"outside must be one of {list(OUTSIDE)} (how values solved below black are shown), "
                              f"got {outside!r}")


def to_projectable(p: torch.Tensor, bounds: tuple[float, float], outside: str = "clip") -> torch.Tensor:
    """Bring values solved within ``bounds`` into [0, 1], what a projector can show.

    Our choice, not the paper's: the paper solves ``EO_-100^255`` with a lower bound below black but
    does not say how such values are shown. ``clip`` (default) shows them black; ``map`` maps the
    bounds linearly onto [0, 1], which keeps the solution's contrast but lifts a zero to
    ``-lo / (hi - lo)`` of white. ``benchmarks/image_quality.py`` measures both for ``EO_-100^255``.
    """
    lo, hi = check_bounds(bounds)
    check_outside(outside)
    check(isinstance(p, torch.Tensor) and p.is_floating_point(),
          f"p must be a float tensor of solved values, got {p.dtype if isinstance(p, torch.Tensor) else type(p).__name__}")
    if lo >= 0 and hi <= 1:
        return p
    return p.clamp(0, 1) if outside == "clip" else (p - lo) / (hi - lo)


def check_patterns_shape(op, patterns: torch.Tensor, name: str = "start") -> None:
    """``patterns`` :math:`(N_{cols}, C)` for the (image) operator ``op``."""
    shape = (op.shape[1], op.channels)
    check(isinstance(patterns, torch.Tensor), f"{name} must be a torch.Tensor, got {type(patterns).__name__}")
    check(tuple(patterns.shape) == shape, f"{name} must have shape {shape} (columns, channels), got "
                                          f"{tuple(patterns.shape)}")


def _start(op: TransportOperator, x0: torch.Tensor | None, lo: float, hi: float) -> torch.Tensor:
    if x0 is None:
        return torch.full((op.shape[1], op.channels), 0.5 * (lo + hi), dtype=op.val.dtype, device=op.val.device)
    check_patterns_shape(op, x0, "x0")
    check_finite(x0, "x0")
    return x0.to(op.val.device, op.val.dtype).clamp(lo, hi)


def _stop(prev: float, cur: float, tol: float) -> bool:
    """Relative objective change below tol."""
    return abs(prev - cur) <= tol * max(abs(cur), 1e-30)


def solve_pgd(op: TransportOperator, bounds=(0.0, 1.0), *, max_iter: int = 500, tol: float = 1e-6,
              x0: torch.Tensor | None = None, precondition: bool = True, levels: int = 0,
              progress: bool | None = None, form: str = "auto") -> SolveResult:
    """Projected gradient with step 1/L: monotone (the objective never rises).

    ``precondition`` runs it on the Jacobi-scaled normal equations (still a box, still step 1/L of
    the scaled system; see :meth:`NormalEquations.jacobi`). ``levels`` as in :func:`solve_fista`;
    0 by default, so that PGD stays the textbook reference the benchmarks compare against. ``form`` as
    in :func:`solve_fista`.
    """
    return _proximal(op, bounds, max_iter, tol, x0, precondition, levels, progress, accelerate=False, form=form)


def solve_fista(op: TransportOperator, bounds=(0.0, 1.0), *, max_iter: int = 500, tol: float = 1e-6,
                x0: torch.Tensor | None = None, precondition: bool = True, levels: int = 3,
                progress: bool | None = None, form: str = "auto") -> SolveResult:
    """FISTA (accelerated projected gradient, step 1/L) with adaptive restart, started coarse to fine.

    Momentum is reset whenever the objective would rise (O'Donoghue & Candes), so the reported
    iterates never get worse and the method keeps FISTA's speed on well-conditioned parts.
    ``precondition`` as in :func:`solve_pgd`.

    Without ``x0``, the same method first solves the rig with projector cells tied in 8x8 blocks,
    then 4x4, then 2x2 (``levels`` of them; see :meth:`TransportOperator.coarse_levels`), each to a
    relative change of 1e-4 (or ``tol`` if looser) and at most 100 iterations, and starts from the
    last of those patterns. Smooth patterns are what gradient steps are slowest on (two
    projectors' smooth patterns look alike on every target) and what the tied problems, a quarter
    of the size and less, solve cheaply. On the paper's full-size rig this nearly halves the time
    to a 1e-3 gap; at quarter size (58 k variables) it costs a few milliseconds instead
    (``benchmarks/solvers.py``); ``levels=0`` turns it off. Every tied pattern is a pattern of the
    full rig, in the box, with the same objective, so ``history`` runs through all levels. ``iterations`` and
    ``max_iter`` count the full-resolution iterations; ``info["coarse_iterations"]`` gives the
    others, coarsest first. With ``x0`` the solve starts there instead.

    ``form``: the normal equations iterated on (:meth:`TransportOperator.normal_equations`):
    ``"auto"`` (:func:`~torchproj.transport.normal_form`) builds ``Q = A^T A`` where that pays over a
    solve; ``"products"`` never builds it, for a few iterations on an operator whose ``Q`` nothing
    has built yet (the camera loop's first updates on a moved model).
    """
    return _proximal(op, bounds, max_iter, tol, x0, precondition, levels, progress, accelerate=True, form=form)


def solve_target_sets(op: TransportOperator, rhs_sets: list[torch.Tensor], bounds=(0.0, 1.0), *, max_iter: int = 300,
                      tol: float = 1e-6, progress: bool | None = None) -> tuple[list[torch.Tensor], "SolveResult"]:
    """Many sets of targets on one transport at once: FISTA on their right-hand sides side by side.

    Least squares in a box separates over columns, so B target sets (frames of a video, points of a
    sweep; :func:`~torchproj.transport.retarget_rhs` gives each) are one problem with B times the
    columns: every iteration is one sparse product with more columns, which costs far less than B
    products (``python benchmarks/batch_solves.py``). The iterations run until the set that
    converges last does.

    Args:
        op: the transport; its own ``rhs`` is not used.
        rhs_sets: per set, :math:`(N_{rows}, C)` targets in camera units.

    Returns:
        per set its :math:`(N_{cols}, C)` values, and the joint :class:`SolveResult`.
    """
    check_operator(op)
    check(isinstance(rhs_sets, (list, tuple)) and all(isinstance(r, torch.Tensor) for r in rhs_sets),
          f"rhs_sets must be a list of (N_rows, C) tensors, one per set, got {type(rhs_sets).__name__}"
          + (" (a stacked batch: give list(rhs_sets))" if isinstance(rhs_sets, torch.Tensor) else ""))
    check(len(rhs_sets) >= 1, "give at least one set of targets")
    for k, r in enumerate(rhs_sets):
        check_shape(r, f"rhs_sets[{k}]", [op.shape[0], "C"])
    widths = [r.shape[1] for r in rhs_sets]
    joint = solve_fista(op.with_rhs(torch.cat(rhs_sets, 1)), bounds, max_iter=max_iter, tol=tol, progress=progress)
    return list(torch.split(joint.patterns, widths, 1)), joint


# Coarse levels only give a start: a loose stop and a cap keep them a small share of the work.
_COARSE_TOL = 1e-4
_COARSE_MAX_ITER = 100


def _proximal(op, bounds, max_iter, tol, x0, precondition, levels, progress, accelerate, form="auto"):
    check_operator(op)
    lo, hi = check_bounds(bounds)
    max_iter, levels = check_count(max_iter, "max_iter"), check_count(levels, "levels", 0)
    tol = check_number(tol, "tol")
    t0 = time.perf_counter()
    ne = op.normal_equations(form)
    history = []
    if x0 is None:
        # The coarse start and the full level's own setup (its scaling and step bound, 17 products) read
        # the same Q and write nothing the other reads: the start runs on a second thread meanwhile.
        with _beside(op.val.device, coarse_start, op, lo, hi, levels, tol, t0, history, precondition, accelerate,
                     form) as start:
            ne = ne.jacobi() if precondition else ne
            ne.lipschitz()
            p, coarse_iterations, coarse_columns = start()
    else:
        p, coarse_iterations, coarse_columns = _start(op, x0, lo, hi), [], []
        ne = ne.jacobi() if precondition else ne
    bar = progress_bar(desc="fista" if accelerate else "pgd", enabled=progress, total=max_iter)
    p, f, it, converged = _iterate(ne, p, lo, hi, max_iter, tol, accelerate, t0, history, bar)
    bar.close()
    return SolveResult(patterns=p, iterations=it, objective=f, history=history, time_s=time.perf_counter() - t0,
                       converged=converged, method="fista" if accelerate else "pgd",
                       info={"lipschitz": ne.lipschitz(), "preconditioned": bool(precondition),
                             "coarse_iterations": coarse_iterations, "coarse_columns": coarse_columns})


@contextlib.contextmanager
def _beside(device: torch.device, fn, *args):
    """``fn(*args)`` run on a second thread while the block runs, for a solve on the CPU; the block
    gets a function that waits for its result (and raises what ``fn`` raised). On another device it
    runs first, in this thread.

    The solvers run their coarse start so (scipy's products ``P^T Q P`` hold one core, then small
    solves) while the calling thread prepares the full level: the two read the same ``Q`` and write
    apart, so the result is the one a single thread gives, to the bit. On a GPU the calling thread
    only queues kernels, and nothing is gained. Grad mode is per thread: the caller's holds in the
    second one too (a solve under ``torch.no_grad()`` records no graph there either).
    """
    if torch.device(device).type != "cpu":
        value = fn(*args)
        yield lambda: value
        return
    grad = torch.is_grad_enabled()

    def run():
        with torch.set_grad_enabled(grad):
            return fn(*args)

    with ThreadPoolExecutor(1) as pool:
        yield pool.submit(run).result


def coarse_start(op: TransportOperator, lo: float, hi: float, levels: int, tol: float, t0: float, history: list,
                 precondition: bool = True, accelerate: bool = True,
                 form: str = "auto") -> tuple[torch.Tensor, list[int], list[int]]:
    """A start for a full-resolution solve: the rig solved with cells tied in blocks, coarsest first.

    Each of ``levels`` tied problems (8x8, 4x4, 2x2 blocks for 3; see
    :meth:`TransportOperator.coarse_levels`) runs to a relative change of 1e-4 (or ``tol`` if looser),
    at most 100 iterations, from the previous level's patterns; ``levels=0`` starts in the middle of
    the box. Appends to ``history`` (times from ``t0``).

    Returns:
        :math:`(N_{cols}, C)` patterns within ``[lo, hi]``, and per level, coarsest first, its iterations
        and its number of columns.
    """
    coarse = op.coarse_levels(levels, form)
    p, iterations, columns = None, [], []
    for level in reversed(range(len(coarse))):
        level_ne, block = coarse[level]
        if p is None:
            p = torch.full_like(level_ne.q, 0.5 * (lo + hi))
        p, _, its, _ = _iterate(level_ne.jacobi() if precondition else level_ne, p, lo, hi, _COARSE_MAX_ITER,
                                max(tol, _COARSE_TOL), accelerate, t0, history, None)
        iterations.append(its)
        columns.append(level_ne.q.shape[0])
        p = p[block]  # each cell takes its block's value
    return (_start(op, None, lo, hi) if p is None else p), iterations, columns


# The element-wise part of an iteration (objective, extrapolation, gradient step, clamp) reads and
# writes blocks of N x C floats, 11 MB each on the paper's full-size rig. Op by op, each block
# went through main memory several times, and that cost more than the sparse product. Done chunk
# by chunk, the operations on one chunk find it in cache, and the extrapolated point is never
# stored. A chunk is a whole number of the objective's summation runs, so the objective is summed
# exactly as :meth:`NormalEquations.objective` sums it. On a GPU the whole block is one chunk:
# there each operation is a kernel launch, and 1 MB chunks make a full-size iteration about a
# hundred launches, more than its sparse product costs (0.29 ms on an H100, where FISTA's
# iterations averaged ~0.6 ms). With the whole block FISTA reached a 1e-3 gap at full size in 0.022 s
# on an H100; 0.046 s was measured at 4e7ee7b, with 1 MB chunks
# (benchmarks/results/cuda_checks/h100_9ea8b94, benchmarks/results/solvers/cuda_h100_4e7ee7b.json).
_CHUNK = 256 * SUM_RUN


@fused
def _pass_in_one_loop(z, qz, z_prev, qz_prev, two_q, lo, hi, weight, step, out, runs):
    """:class:`_Sweep`'s pass over whole flat blocks as one expression, which ``torch.compile``
    makes one loop (``TORCHPROJ_COMPILE=1``, :mod:`torchproj.core.fused`): each block is read
    once and ``out`` written once, where the eager pass goes over each chunk nine times. On
    sixteen target sets of the default rig it took 25.3 ms against 46.4 ms eager, at the floor
    of its seven blocks (26.5 ms at the bandwidth a copy reached beside it;
    ``python benchmarks/batch_solves.py``). Flat, so that one compiled loop serves one column and many:
    over :math:`(N, C)` blocks inductor's loop was no faster than the eager pass, and a width of
    1 is another compile. ``weight`` and ``step`` are 0-d tensors, so that a new value is not a
    new compile; ``lo`` and ``hi`` are numbers or flat blocks. Writes ``runs`` (the objective's
    terms summed per run, as :meth:`NormalEquations.objective` sums them) and ``out``; returns
    the partial run's sum in float64.
    """
    w = (qz - two_q) * z
    n = runs.numel() * SUM_RUN
    runs.copy_(w[:n].view(-1, SUM_RUN).sum(1))
    y = torch.lerp(z_prev, z, weight)
    q_y = torch.lerp(qz_prev, qz, weight)
    stepped = y - step * q_y + 0.5 * step * two_q
    stepped = torch.maximum(stepped, lo) if torch.is_tensor(lo) else stepped.clamp_min(lo)
    out.copy_(torch.minimum(stepped, hi) if torch.is_tensor(hi) else stepped.clamp_max(hi))
    return w[n:].double().sum()


def _chunk_for(t: torch.Tensor) -> int:
    if t.device.type == "cpu":
        return _CHUNK
    return -(-t.numel() // SUM_RUN) * SUM_RUN


class _Sweep:
    """One chunked pass: the objective of the current iterate and the next gradient step.

    Blocks are ``(tensor, its chunks)`` pairs (:meth:`block`), so that a solve splits each of its
    blocks once.
    """

    def __init__(self, ne, step: float, lo: float, hi: float):
        self.ne, self.step, self.half_step = ne, step, 0.5 * step
        self.chunk = _chunk_for(ne.q)
        self.two_q = self.split(ne.two_q)
        self.lo, self.hi = (self.split(b) if torch.is_tensor(b) else [b] * len(self.two_q)
                            for b in (ne.bound(lo), ne.bound(hi)))
        scratch = torch.empty(3, min(self.chunk, ne.q.numel()), dtype=ne.q.dtype, device=ne.q.device)
        self.work, self.y, self.qy = scratch.unbind(0)
        self.runs = torch.empty(ne.q.numel() // SUM_RUN, dtype=ne.q.dtype, device=ne.q.device)
        self.run_chunks = self.runs.split(self.chunk // SUM_RUN)
        # The compiled pass, asked for on a CPU (a GPU's eager pass is one kernel per operation already).
        self.one_loop = ne.q.device.type == "cpu" and _pass_in_one_loop.active()
        if self.one_loop:
            self.flat_lo, self.flat_hi = ((b.view(-1) if torch.is_tensor(b) else b) for b in (ne.bound(lo), ne.bound(hi)))
            self.step_tensor = torch.tensor(step, dtype=ne.q.dtype)

    def split(self, t: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return t.view(-1).split(self.chunk)

    def block(self, t: torch.Tensor | None = None):
        t = torch.empty_like(self.ne.q) if t is None else t
        return t, self.split(t)

    def __call__(self, z, qz, z_prev, qz_prev, weight: float, out) -> float:
        """``f(z)``, and into ``out`` the step ``clamp(y - step (Q y - q))`` from
        ``y = z_prev + weight (z - z_prev)`` (``y = z`` for weight 1; Q y from the products likewise).
        """
        if self.one_loop and _pass_in_one_loop.active():
            z_prev, qz_prev = (z, qz) if weight == 1.0 else (z_prev, qz_prev)
            tail = _pass_in_one_loop(z[0].view(-1), qz[0].view(-1), z_prev[0].view(-1), qz_prev[0].view(-1),
                                     self.ne.two_q.view(-1), self.flat_lo, self.flat_hi,
                                     torch.tensor(weight, dtype=self.runs.dtype), self.step_tensor, out[0].view(-1),
                                     self.runs)
            return float(self.runs.double().sum() + tail + self.ne.c.sum())
        tail = 0.0
        for i, (zc, qc, oc) in enumerate(zip(z[1], qz[1], out[1])):
            m = zc.numel()
            w = torch.sub(qc, self.two_q[i], out=self.work[:m]).mul_(zc)
            full = m // SUM_RUN * SUM_RUN
            if full:
                torch.sum(w[:full].view(-1, SUM_RUN), 1, out=self.run_chunks[i])
            if full < m:
                tail = w[full:].double().sum()
            if weight == 1.0:
                y, qy = zc, qc
            else:
                y = torch.lerp(z_prev[1][i], zc, weight, out=self.y[:m])
                qy = torch.lerp(qz_prev[1][i], qc, weight, out=self.qy[:m])
            # clamp(y - step (Q y - q)) = clamp(y - step Q y + (step / 2) 2q)
            torch.add(y, qy, alpha=-self.step, out=oc).add_(self.two_q[i], alpha=self.half_step)
            _clamp_(oc, self.lo[i], self.hi[i])
        return float(self.runs.double().sum() + tail + self.ne.c.sum())


def _clamp_(x: torch.Tensor, lo, hi) -> torch.Tensor:
    """``x`` clamped in place to ``[lo, hi]``, each a number or a block shaped like ``x``."""
    if torch.is_tensor(lo) == torch.is_tensor(hi):
        return x.clamp_(lo, hi)
    if torch.is_tensor(hi):
        return x.clamp_min_(lo).clamp_(None, hi)
    return x.clamp_max_(hi).clamp_(lo, None)


def _iterate(ne, p, lo, hi, max_iter, tol, accelerate, t0, history, bar):
    """Projected gradient steps (accelerated or not) on ``ne`` from ``p``; appends to ``history``.

    ``p`` is overwritten: the callers' starts are theirs to give.

    Returns the patterns (in ``p``'s units, inside the box), the objective, the iterations and
    whether the stopping rule fired.
    """
    # On the normal equations the gradient is Q z - q: one sparse product per iteration. Q is
    # linear, so Q y follows from Q z by the same extrapolation as y.
    L = ne.lipschitz()
    check(L > 0, "the operator is zero: nothing to solve")
    sweep = _Sweep(ne, 1.0 / L, lo, hi)
    unscale = 1.0 if ne.scale is None else ne.scale
    p = p if ne.scale is None else p.div_(unscale)
    # Three iterate blocks rotate: the current one, the candidate (the step from the extrapolated
    # point, whose product is taken next) and the one the next step is written into. The first
    # is p itself, which the callers hand over.
    z, candidate, spare = sweep.block(p), sweep.block(), sweep.block()
    qz, q_candidate = sweep.block(ne.product(z[0])), sweep.block()
    f = sweep(z, qz, None, None, 1.0, candidate)
    if not history:
        history.append((time.perf_counter() - t0, f))
    t_k = 1.0
    converged = False
    it = 0
    for it in range(1, max_iter + 1):
        ne.product(candidate[0], q_candidate[0])
        t_next = 0.5 * (1 + math.sqrt(1 + 4 * t_k * t_k)) if accelerate else 1.0
        # The step after this candidate is taken on the guess that the candidate is kept.
        weight = 1 + (t_k - 1) / t_next
        f_new = sweep(candidate, q_candidate, z, qz, weight, spare)
        if accelerate and f_new > f and t_k > 1.0:
            # Restart: drop the momentum and take a plain projected step from z (monotone).
            sweep(z, qz, None, None, 1.0, candidate)
            ne.product(candidate[0], q_candidate[0])
            t_k = 1.0
            t_next = 0.5 * (1 + math.sqrt(1 + 4 * t_k * t_k))
            f_new = sweep(candidate, q_candidate, None, None, 1.0, spare)  # weight 1: no momentum yet
        t_k = t_next
        done = _stop(f, f_new, tol)
        z, candidate, spare = candidate, spare, z
        qz, q_candidate = q_candidate, qz
        f = f_new
        history.append((time.perf_counter() - t0, f))
        if bar is not None:  # coarse levels run without one
            bar.update(1)
        if done:
            converged = True
            break
    return (z[0] * unscale).clamp_(lo, hi), f, it, converged  # the clamp only removes the scaling's round-off


class ClampedAdam(torch.optim.Adam):
    """``torch.optim.Adam`` that clamps every parameter into ``bounds`` after each step.

    A subclass rather than a wrapper, so learning-rate schedulers and ``state_dict`` work as with
    Adam itself. The bounds are a hyper-parameter like ``lr``: each parameter group has its own
    (``group["bounds"]``), and a group added later (``add_param_group``) without one takes the
    default given here.

    Args:
        bounds: ``(lo, hi)``: numbers, or tensors broadcastable to the parameters (for example
            :math:`(N_{cols}, 1)` bounds that differ per projector cell).

    Example:
        >>> p = torch.full((10, 1), 0.5, requires_grad=True)
        >>> opt = ClampedAdam([p], lr=0.05, bounds=(0.0, 1.0))
    """

    def __init__(self, params, lr: float = 1e-2, bounds=(0.0, 1.0), **kwargs):
        if not lr > 0:
            raise ValueError(f"Invalid learning rate: {lr}")
        bounds = _adam_bounds(bounds)
        super().__init__(params, lr=lr, **kwargs)
        self.defaults["bounds"] = bounds
        for group in self.param_groups:
            group.setdefault("bounds", bounds)

    def add_param_group(self, param_group: dict) -> None:
        if "bounds" in param_group:
            param_group["bounds"] = _adam_bounds(param_group["bounds"])
        super().add_param_group(param_group)

    @torch.no_grad()
    def step(self, closure=None):
        loss = super().step(closure)
        for group in self.param_groups:
            lo, hi = group["bounds"]
            for p in group["params"]:
                p.clamp_(lo, hi)
        return loss


def _adam_bounds(bounds):
    """``(lo, hi)`` numbers (checked as :func:`check_bounds`) or tensors with ``lo < hi`` everywhere."""
    check(isinstance(bounds, (tuple, list)) and len(bounds) == 2, f"bounds must be a pair (lo, hi), got {bounds!r}")
    lo, hi = bounds
    if not (torch.is_tensor(lo) or torch.is_tensor(hi)):
        return check_bounds(bounds)
    lo, hi = (torch.as_tensor(b, dtype=torch.float32) if not torch.is_tensor(b) else b for b in (lo, hi))
    check(bool(torch.isfinite(lo).all()) and bool(torch.isfinite(hi).all()), "bounds must be finite")
    check(bool((lo < hi).all()), "bounds must satisfy lo < hi everywhere")
    return lo, hi


def solve_adam(op: TransportOperator, bounds=(0.0, 1.0), *, lr: float = 0.02, max_iter: int = 500,
               tol: float = 1e-6, x0: torch.Tensor | None = None, progress: bool | None = None,
               rise_window: int = 20) -> SolveResult:
    """Clamped Adam on the objective through autograd (as a user's training loop would run it).

    Warns when the objective ends a window of ``rise_window`` iterations higher than it started:
    the learning rate is too large for this problem.
    """
    check_operator(op)
    lo, hi = check_bounds(bounds)
    max_iter, tol = check_count(max_iter, "max_iter"), check_number(tol, "tol")
    lr, rise_window = check_number(lr, "lr", strict=True), check_count(rise_window, "rise_window")
    t0 = time.perf_counter()
    p = _start(op, x0, lo, hi).requires_grad_(True)
    opt = ClampedAdam([p], lr=lr, bounds=(lo, hi))
    # Adam is scale-invariant in the gradient; normalising the objective keeps tol meaningful.
    norm = float(op.rhs.pow(2).sum()) or 1.0
    with torch.no_grad():
        f = float(op.objective(p))
    history = [(time.perf_counter() - t0, f)]
    bar = progress_bar(desc="adam", enabled=progress, total=max_iter)
    converged, warned, it = False, False, 0
    for it in range(1, max_iter + 1):
        opt.zero_grad(set_to_none=True)
        loss = op.objective(p) / norm
        loss.backward()
        opt.step()
        with torch.no_grad():
            f_new = float(op.objective(p))
        history.append((time.perf_counter() - t0, f_new))
        bar.update(1)
        if not warned and it >= rise_window and f_new > history[it - rise_window][1] * (1 + 1e-6):
            warnings.warn(f"Adam's objective rose over the last {rise_window} iterations (lr={lr:g}); "
                          "lower the learning rate", RuntimeWarning, stacklevel=2)
            warned = True
        done = _stop(f, f_new, tol) and it > 10
        f = f_new
        if done:
            converged = True
            break
    bar.close()
    return SolveResult(patterns=p.detach(), iterations=it, objective=f, history=history,
                       time_s=time.perf_counter() - t0, converged=converged, method="adam")


LF_NORMALISE = ("joint", "projector", "clip")  # how solve_lf brings its least-squares solution into the bounds
_LF_STALL = 300  # CG iterations without a new smallest residual before LF stops short of tol


def solve_lf(op: TransportOperator, bounds=(0.0, 1.0), *, max_iter: int = 20000, tol: float = 1e-5,
             normalise: str = "joint", progress: bool | None = None) -> SolveResult:
    """The predecessor method (LF): unconstrained least squares, then brought into the bounds.

    The least squares is solved by conjugate gradients on the Jacobi-scaled normal equations
    (``S Q S z = S q``, ``p = S z``; see :meth:`NormalEquations.jacobi`) until the residual
    ``||q - Q p||`` falls below ``tol`` of ``||q||``, per channel: a converged solve, not a count
    (``max_iter`` is a safety limit). Then ``normalise``:

    - ``"joint"``: the paper's words, "normalising p so that the elements are in the range of
      [0,255]": the whole pattern vector, every projector and channel together, is mapped linearly so
      its minimum and maximum meet the bounds. What compresses the dynamic range and lowers contrast.
    - ``"projector"``: the same map per projector and channel (our variant; the paper does not say).
    - ``"clip"``: values outside the bounds clipped, the rest left as solved (our variant).

    ``info`` gives the residual reached and the unnormalised solution's range.
    """
    check_operator(op)
    lo, hi = check_bounds(bounds)
    check(normalise in LF_NORMALISE, f"normalise must be one of {list(LF_NORMALISE)}, got {normalise!r}")
    max_iter, tol = check_count(max_iter, "max_iter"), check_number(tol, "tol")
    t0 = time.perf_counter()
    base = op.normal_equations("auto")
    ne = base.jacobi()
    z = torch.zeros(op.shape[1], op.channels, dtype=op.val.dtype, device=op.val.device)
    r = ne.q.clone()  # residual of the normal equations at z = 0
    d = r.clone()
    rr = (r * r).sum(0, dtype=torch.float64)
    r0 = rr.clamp_min(1e-300)
    history = [(time.perf_counter() - t0, float(op.objective(z)))]
    bar = progress_bar(desc="lf (cg)", enabled=progress, total=max_iter)
    it, converged, best, since_best = 0, False, float("inf"), 0
    for it in range(1, max_iter + 1):
        qd = ne.product(d)
        curvature = (d * qd).sum(0, dtype=torch.float64)
        # Round-off on a singular system (projectors that see the scene alike) can leave a direction
        # without curvature; the solve stops there with what it has rather than step to infinity.
        if not bool((torch.isfinite(curvature) & ((curvature > 0) | (rr == 0))).all()):
            break
        alpha = (rr / curvature.clamp_min(1e-300)).to(z.dtype)
        z += alpha * d
        r -= alpha * qd
        rr_new = (r * r).sum(0, dtype=torch.float64)
        d = r + (rr_new / rr.clamp_min(1e-300)).to(z.dtype) * d
        rr = rr_new
        if it % 10 == 0:
            history.append((time.perf_counter() - t0, ne.objective(z, ne.q - r)))  # CG keeps r = q - Q z
        bar.update(1)
        if bool((rr <= tol * tol * r0).all()):
            converged = True
            break
        total = float(rr.sum())
        best, since_best = (total, 0) if total < best else (best, since_best + 1)
        if since_best >= _LF_STALL or not math.isfinite(total):
            break  # float32 round-off floor above tol: more iterations change nothing
    bar.close()
    x = z * ne.scale
    # The true residual of the unscaled system (CG's recursive one drifts in float32).
    residual = float(((base.q - base.product(x)).double().norm() / base.q.double().norm().clamp_min(1e-300)))
    p = _lf_normalise(op, x, lo, hi, normalise)
    f = float(op.objective(p))
    history.append((time.perf_counter() - t0, f))
    return SolveResult(patterns=p, iterations=it, objective=f, history=history, time_s=time.perf_counter() - t0,
                       converged=converged, method="lf",
                       info={"normalise": normalise, "residual": residual,
                             "least_squares_range": (float(x.min()), float(x.max()))})


def _lf_normalise(op: TransportOperator, x: torch.Tensor, lo: float, hi: float, normalise: str) -> torch.Tensor:
    """:math:`(N_{cols}, C)` least-squares values brought into ``[lo, hi]`` (see :func:`solve_lf`)."""
    if normalise == "clip":
        return x.clamp(lo, hi)
    if normalise == "joint":
        groups = torch.zeros(x.shape[0], dtype=torch.int64, device=x.device)
    else:
        groups = op.column_projector.to(x.device).long()
    n = int(groups.max()) + 1 if groups.numel() else 1
    index = groups[:, None].expand_as(x)
    low = torch.full((n, x.shape[1]), float("inf"), dtype=x.dtype, device=x.device).scatter_reduce(0, index, x, "amin")
    high = torch.full((n, x.shape[1]), -float("inf"), dtype=x.dtype, device=x.device).scatter_reduce(0, index, x,
                                                                                                     "amax")
    if normalise == "joint":
        low, high = low.min().expand_as(low), high.max().expand_as(high)
    span = (high - low).clamp_min(1e-12)
    return lo + (x - low[groups]) / span[groups] * (hi - lo)

