"""EO: the paper's epipolar optimisation, split into independent chains solved within the box.

Light from two projectors mixes only between pixels on corresponding epipolar lines (section 4.3
of the paper), so the problem splits into small independent problems ("chains"), each solved on
its own with the box constraint ``lo <= p <= hi``. Two ways to form chains:

- ``"epipolar"``: the fundamental matrix between the two projectors is estimated (kornia's
  normalised 8-point algorithm) from the calibrated correspondences (camera pixels decoded by both
  projectors see the same surface point); every projector cell gets the parameter of its epipolar
  line, and cells whose lines fall in the same one-pixel-wide band form a chain. Rows that straddle
  two bands are given to the band holding most of their weight, the other entries dropped: that is
  the paper's approximation, and its cost shows in the full objective reported.
- ``"components"``: the connected components of the operator's column graph. Exact (nothing is
  dropped), but on a rig whose camera is finer than the projectors neighbouring cells are coupled
  and a component can span most of the image.

All chains are solved at once: the problem restricted to the chains is block diagonal (so is its
normal matrix ``Q``), and each block runs its own accelerated projected gradient with its own step
size (its own Lipschitz bound from a per-chain power iteration), momentum and restarts, until every
chain has converged. No Python loop runs over chains.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from kornia.geometry.epipolar import find_fundamental
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from ..core.checks import check
from ..transport.build import StateCalibration
from ..transport.operator import TransportOperator, csr_from_coo
from ..core.progress import progress_bar
from .solvers import SolveResult, check_bounds

__all__ = ["CHAINS", "fundamental_between_projectors", "epipolar_chains", "component_chains", "solve_eo"]

CHAINS = ("epipolar", "components")  # solve_eo's independent problems, by name (it also takes an index)


def fundamental_between_projectors(calibrations: dict[str, StateCalibration], first: int = 0, second: int = 1,
                                   max_points: int = 20000, seed: int = 0) -> torch.Tensor:
    """Fundamental matrix F with ``x2^T F x1 = 0`` between two projectors' pixel coordinates.

    Correspondences: camera pixels decoded by both projectors (in any state) see one surface point.

    Returns:
        :math:`(3, 3)` float64.
    """
    p1, p2 = [], []
    for cal in calibrations.values():
        a, b = cal.prj_xy[first].reshape(-1, 2), cal.prj_xy[second].reshape(-1, 2)
        both = torch.isfinite(a).all(-1) & torch.isfinite(b).all(-1)
        p1.append(a[both])
        p2.append(b[both])
    p1, p2 = torch.cat(p1).double(), torch.cat(p2).double()
    check(p1.shape[0] >= 8, f"only {p1.shape[0]} camera pixels are decoded by both projectors {first} and {second}; "
                            "the epipolar geometry needs at least 8 (use chains='components')")
    if p1.shape[0] > max_points:
        pick = torch.randperm(p1.shape[0], generator=torch.Generator().manual_seed(seed))[:max_points]
        p1, p2 = p1[pick], p2[pick]
    return find_fundamental(p1[None], p2[None])[0]


def _line_parameter(lines: torch.Tensor, centre: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """Where lines (N, 3) cross the line through ``centre`` along ``normal``: signed distance (px)."""
    num = lines[:, 0] * centre[0] + lines[:, 1] * centre[1] + lines[:, 2]
    den = lines[:, 0] * normal[0] + lines[:, 1] * normal[1]
    return -num / torch.where(den.abs() < 1e-12, torch.full_like(den, 1e-12), den)


def epipolar_chains(op: TransportOperator, F: torch.Tensor, band: float = 1.0) -> torch.Tensor:
    """Chain index of every column: the band of its epipolar line (two projectors).

    Args:
        op: the operator (columns of projectors 0 and 1).
        F: fundamental matrix, ``x2^T F x1 = 0``.
        band: band width in projector-1 pixels, measured at its image centre.

    Returns:
        :math:`(N_{cols},)` int64 chain index.
    """
    check(len(op.projector_sizes) == 2, "epipolar chains need exactly two projectors; use chains='components'")
    F = F.double().cpu()
    e1 = torch.linalg.svd(F)[2][-1]  # right null vector: the epipole in projector 1
    w1, h1 = op.projector_sizes[0]
    centre = torch.tensor([(w1 - 1) / 2, (h1 - 1) / 2, 1.0], dtype=torch.float64)
    through_centre = torch.linalg.cross(e1, centre)
    normal = through_centre[:2] / through_centre[:2].norm()  # crossing all epipolar lines near the centre
    cell = op.column_cell.cpu()
    proj = op.column_projector.cpu()
    params = torch.empty(cell.shape[0], dtype=torch.float64)
    for j in (0, 1):
        sel = proj == j
        w = op.projector_sizes[j][0]
        pts = torch.stack([(cell[sel] % w).double(), (cell[sel] // w).double(), torch.ones(int(sel.sum()),
                                                                                          dtype=torch.float64)], 1)
        # Projector 1 cells: the line through the epipole; projector 2 cells: their epipolar line F^T x2.
        lines = torch.linalg.cross(e1.expand_as(pts), pts) if j == 0 else pts @ F
        params[sel] = _line_parameter(lines, centre, normal)
    chain = torch.round(params / band).long()
    return torch.unique(chain, return_inverse=True)[1].to(op.col.device)


def component_chains(op: TransportOperator) -> torch.Tensor:
    """Chain index of every column: connected components of the column graph of ``A^T A`` (scipy)."""
    m = csr_matrix((np.ones(op.nnz), op.col.cpu().numpy(), op.crow.cpu().numpy()), shape=op.shape)
    _, labels = connected_components(m.T @ m, directed=False)
    return torch.from_numpy(labels).long().to(op.col.device)


def _split(op: TransportOperator, chain: torch.Tensor):
    """The block-diagonal operator: each row keeps only its entries in its heaviest chain."""
    rows = torch.repeat_interleave(torch.arange(op.shape[0], device=op.col.device), op.crow.diff())
    entry_chain = chain[op.col]
    n_chains = int(chain.max()) + 1
    key = rows * n_chains + entry_chain
    uniq, inverse = torch.unique(key, return_inverse=True)
    weight = torch.zeros(uniq.shape[0], dtype=op.val.dtype, device=op.val.device).index_add_(0, inverse, op.val.abs())
    best = torch.full((op.shape[0],), -1.0, dtype=op.val.dtype, device=op.val.device)
    best.scatter_reduce_(0, uniq // n_chains, weight, reduce="amax")
    # Row r's chain: the (first) chain holding its largest weight.
    is_best = weight >= best[uniq // n_chains]
    row_chain = torch.full((op.shape[0],), n_chains, dtype=torch.int64, device=op.col.device)
    row_chain.scatter_reduce_(0, (uniq // n_chains)[is_best], (uniq % n_chains)[is_best], reduce="amin")
    keep = entry_chain == row_chain[rows]
    matrix = csr_from_coo(rows[keep], op.col[keep], op.val[keep], op.shape)
    kept = float(op.val[keep].pow(2).sum() / op.val.pow(2).sum())
    return TransportOperator(matrix, op.rhs, op.column_projector, op.column_cell, op.projector_sizes,
                             op.constant, op.row_target, op.scale), row_chain, kept


def _per_chain(values: torch.Tensor, index: torch.Tensor, n: int) -> torch.Tensor:
    """Sum of (N, C) values per chain over rows/columns -> (n,)."""
    return torch.zeros(n, dtype=values.dtype, device=values.device).index_add_(0, index, values.sum(1))


def _chain_index(op, chains, calibrations, band) -> torch.Tensor:
    """:math:`(N_{cols},)` chain of each column, by name (``epipolar``, ``components``) or as given."""
    if isinstance(chains, torch.Tensor):
        chain = chains.to(op.col.device)
    elif chains == "epipolar":
        check(calibrations is not None, "chains='epipolar' needs the calibrations (for the fundamental matrix)")
        check(len(op.projector_sizes) == 2, f"epipolar chains need exactly two projectors, the operator has "
                                            f"{len(op.projector_sizes)}; use chains='components' or another solver")
        chain = epipolar_chains(op, fundamental_between_projectors(calibrations), band)
    else:
        check(chains == "components", f"chains must be one of {list(CHAINS)} or a tensor, got {chains!r}")
        chain = component_chains(op)
    check(chain.shape == (op.shape[1],), f"chain index must have shape ({op.shape[1]},)")
    return chain


def _chain_steps(ne, chain: torch.Tensor, n: int) -> torch.Tensor:
    """Per-chain step sizes, :math:`(N_{cols}, 1)`: power iteration on the block-diagonal Q, normalised
    chain by chain; max over a chain of (Q x)_i / x_i bounds its largest eigenvalue from above (Q >= 0)."""
    x = torch.ones(ne.q.shape[0], 1, dtype=ne.q.dtype, device=ne.q.device)
    for _ in range(30):
        y = ne.product(x)
        x = y / _per_chain(y * y, chain, n).sqrt().clamp_min(1e-30)[chain][:, None]
    ratio = (ne.product(x) / x.clamp_min(1e-30))[:, 0]
    lam = torch.zeros(n, dtype=ne.q.dtype, device=ne.q.device).scatter_reduce_(0, chain, ratio, reduce="amax")
    return (1.0 / lam.clamp_min(1e-30))[chain][:, None]


def solve_eo(op: TransportOperator, bounds=(0.0, 1.0), *, chains: str | torch.Tensor = "epipolar",
             calibrations: dict[str, StateCalibration] | None = None, band: float = 1.0, max_iter: int = 2000,
             tol: float = 1e-8, progress: bool | None = None) -> SolveResult:
    """The paper's EO: independent chains, each solved within ``bounds``.

    Args:
        op: the transport operator.
        bounds: ``(lo, hi)`` in linear relative light (``EO_0^255``: (0, 1); ``EO_-100^255``:
            (-100/255, 1), then :func:`~torchproj.solve.to_projectable`).
        chains: ``"epipolar"`` (needs ``calibrations``), ``"components"``, or a precomputed
            :math:`(N_{cols},)` chain index.
        calibrations: the state calibrations the operator was built from (for the epipolar geometry).
        band: epipolar band width in projector pixels.
        max_iter: iteration limit of the per-chain solves.
        tol: a chain has converged when its objective changes by less than ``tol`` relatively.
        progress: progress bar (None: on a terminal, for solves longer than a second).

    Returns:
        a :class:`SolveResult` whose ``objective`` is on the full operator (cross-chain light included).
    """
    lo, hi = check_bounds(bounds)
    t0 = time.perf_counter()
    chain = _chain_index(op, chains, calibrations, band)
    n = int(chain.max()) + 1
    block, row_chain, kept = _split(op, chain)
    ne = block.normal_equations()  # block diagonal: Q couples columns of one chain only
    q = ne.q
    step = _chain_steps(ne, chain, n)
    rows_const = _per_chain(block.rhs.double().pow(2), row_chain, n)

    def chain_objective(p, qp):
        return _per_chain((p.double() * (qp.double() - 2 * q.double())), chain, n) + rows_const

    x = torch.full((op.shape[1], op.channels), 0.5 * (lo + hi), dtype=op.val.dtype, device=op.val.device)
    qx = ne.product(x)
    y, qy = x, qx
    t_k = torch.ones(n, dtype=op.val.dtype, device=op.val.device)
    f = chain_objective(x, qx)
    active = torch.ones(n, dtype=torch.bool, device=op.val.device)
    history = [(time.perf_counter() - t0, float(op.objective(x)))]
    bar = progress_bar(desc="eo", enabled=progress, total=max_iter)
    it = 0
    for it in range(1, max_iter + 1):
        bar.update(1)
        x_new = (y - step * (qy - q)).clamp_(lo, hi)
        qx_new = ne.product(x_new)
        f_new = chain_objective(x_new, qx_new)
        restart = (f_new > f) & (t_k > 1)
        if bool(restart.any()):
            # Chains whose objective would rise drop their momentum and step from x instead.
            cols = restart[chain][:, None]
            x_new = torch.where(cols, (x - step * (qx - q)).clamp_(lo, hi), x_new)
            qx_new = ne.product(x_new)
            f_new = chain_objective(x_new, qx_new)
            t_k = torch.where(restart, torch.ones_like(t_k), t_k)
        t_next = 0.5 * (1 + torch.sqrt(1 + 4 * t_k * t_k))
        beta = ((t_k - 1) / t_next)[chain][:, None]
        y, qy = x_new + beta * (x_new - x), qx_new + beta * (qx_new - qx)
        t_k = t_next
        active &= (f - f_new).abs() > tol * f_new.abs().clamp_min(1e-30)
        x, qx, f = x_new, qx_new, f_new
        if it % 10 == 0:
            history.append((time.perf_counter() - t0, float(op.objective(x))))
        if not bool(active.any()):
            break
    bar.close()
    objective = float(op.objective(x))
    history.append((time.perf_counter() - t0, objective))
    sizes = torch.bincount(chain)
    return SolveResult(patterns=x, iterations=it, objective=objective, history=history,
                       time_s=time.perf_counter() - t0, converged=not bool(active.any()), method="eo",
                       info={"chains": n, "largest_chain": int(sizes.max()), "median_chain": float(sizes.float().median()),
                             "weight_kept": kept})
