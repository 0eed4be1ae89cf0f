"""EO: the paper's epipolar optimisation, chains of projector cells solved within the box.

Light from two projectors mixes only between pixels on corresponding epipolar lines (section
"Problem reduction using epipolar constraints and constraint-aware optimization" of the paper), so
the problem splits into small problems ("chains"), each solved with the box ``lo <= p <= hi``.
Two ways to form them:

- ``"epipolar"``: the fundamental matrix between the two projectors is estimated (kornia's
  normalised 8-point algorithm) from the calibrated correspondences (camera pixels decoded by both
  projectors see the same surface point); every projector cell gets the parameter of its epipolar
  line, and cells whose lines fall in one pixel-wide strip form a band (:func:`epipolar_bands`).
  The paper's chains are walked through the correspondences inside a band (:func:`epipolar_chains`:
  the connected components of the rows that stay in it: a cell, the camera pixels it lights, the
  other projector's cells that light them, and so on). They share no row, so a band is solved as
  one block of its chains: the same minimiser, without finding them on every solve.
- ``"components"``: the connected components of the whole operator's column graph. No row joins two
  of them; on a rig whose camera is finer than the projectors one component can span most of the
  image. Works for any number of projectors.

On a real (or virtual) camera the bands are not closed: a camera pixel whose footprint straddles
two bands couples them (17% of ``A^T A``'s weight on the paper's full-size rig). The paper's split
drops that light; here it is kept, with block sweeps: blocks are coloured so that no row touches two
blocks of one colour, and each sweep solves every block of a colour at once, in one batched
accelerated projected gradient (a step size, momentum and restarts per block), the other colours'
light held fixed, colour after colour. The objective never rises, and the sweeps converge to the
optimum of the whole bounded problem, the one FISTA reaches. Our choices, not the paper's, measured
in ``benchmarks/model_space.py`` against their alternatives: the sweeps start from the rig solved
with cells tied in blocks (as FISTA does), are extrapolated with restart, and give each block a few
gradient steps per sweep rather than solving it exactly.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from kornia.geometry.epipolar import find_fundamental

from ..core.checks import check, check_count, check_number, check_shape, is_whole
from ..core.progress import progress_bar
from ..core.sparse import csr_tensor, spmm
from ..transport.build import StateCalibration, check_calibrations
from ..transport.operator import TransportOperator, _blockwise_sum, entry_rows
from .solvers import SolveResult, _beside, _clamp_, _stop, check_bounds, check_operator, coarse_start

__all__ = ["CHAINS", "fundamental_between_projectors", "epipolar_bands", "epipolar_chains", "component_chains",
           "solve_eo"]

from ..core.choices import CHAINS  # noqa: E402  solve_eo's independent problems, by name (it also takes an index)


def fundamental_between_projectors(calibrations: dict[str, StateCalibration], first: int = 0, second: int = 1,
                                   max_points: int = 20000) -> torch.Tensor:
    """Fundamental matrix F with ``x2^T F x1 = 0`` between two projectors' pixel coordinates.

    Correspondences: camera pixels decoded by both projectors (in any state) see one surface point.

    Returns:
        :math:`(3, 3)` float64.
    """
    check_calibrations(calibrations)
    count = len(next(iter(calibrations.values())).prj_xy) if calibrations else 0
    for name, j in (("first", first), ("second", second)):
        check(is_whole(j) and 0 <= j < count, f"{name} must be a projector's index from 0 to {count - 1}, got {j!r}")
    check(first != second, f"first and second must be two projectors, got {first} twice")
    check_count(max_points, "max_points", 8)
    p1, p2 = [], []
    pixels = sum(cal.prj_xy[first][..., 0].numel() for cal in calibrations.values())
    stride = max(1, pixels // (8 * max_points))  # a grid of pixels, well over max_points of them, is plenty
    for cal in calibrations.values():
        a, b = cal.prj_xy[first].reshape(-1, 2)[::stride], cal.prj_xy[second].reshape(-1, 2)[::stride]
        both = torch.isfinite(a).all(-1) & torch.isfinite(b).all(-1)
        p1.append(a[both])
        p2.append(b[both])
    p1, p2 = torch.cat(p1).double(), torch.cat(p2).double()
    check(p1.shape[0] >= 8, f"only {p1.shape[0]} camera pixels are decoded by both projectors {first} and {second}; "
                            "the epipolar geometry needs at least 8 (use chains='components')")
    if p1.shape[0] > max_points:
        pick = torch.linspace(0, p1.shape[0] - 1, max_points).long()  # evenly over the states' pixels
        p1, p2 = p1[pick], p2[pick]
    return find_fundamental(p1[None], p2[None])[0]


def _line_parameter(lines: torch.Tensor, centre: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """Where lines (N, 3) cross the line through ``centre`` along ``normal``: signed distance (px)."""
    num = lines[:, 0] * centre[0] + lines[:, 1] * centre[1] + lines[:, 2]
    den = lines[:, 0] * normal[0] + lines[:, 1] * normal[1]
    return -num / torch.where(den.abs() < 1e-12, torch.full_like(den, 1e-12), den)


def epipolar_chains(op: TransportOperator, F: torch.Tensor, band: float = 1.0) -> torch.Tensor:
    """Chain index of every column: the paper's chains, walked through the rows inside each epipolar band.

    Args:
        op: the operator (columns of projectors 0 and 1).
        F: fundamental matrix, ``x2^T F x1 = 0``.
        band: band width in projector-1 pixels, measured at its image centre.

    Returns:
        :math:`(N_{cols},)` int64 chain index (chains of one band are numbered together).
    """
    return _within(op, epipolar_bands(op, F, band))


def epipolar_bands(op: TransportOperator, F: torch.Tensor, band: float = 1.0) -> torch.Tensor:
    """Band index of every column: cells whose epipolar lines fall in one ``band``-wide strip (two
    projectors), numbered in order across the image.

    Returns:
        :math:`(N_{cols},)` int64 band index.
    """
    check_operator(op)
    check_shape(F, "F", [3, 3])
    check(len(op.projector_sizes) == 2, "epipolar chains need exactly two projectors; use chains='components'")
    # NaN, 0 or inf would round every line to one integer past int64's reach: one band of everything.
    band = check_number(band, "band", strict=True)
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
    check_operator(op)
    return _within(op, torch.zeros(op.shape[1], dtype=torch.int64, device=op.col.device))


def _q_entries(Q: torch.Tensor):
    """Row, column and value of every entry of a CSR matrix (for ``Q = A^T A``: every pair of cells
    that light one camera pixel); the indices in Q's own type (int32 as scipy's product gives them),
    which every gather here takes: on the default scene's 15.7 M entries an int64 copy of each was
    0.13 GB written and then read by every pass over the entries."""
    return entry_rows(Q, Q.col_indices().dtype), Q.col_indices(), Q.values()


def _within(op: TransportOperator, group: torch.Tensor, entries=None) -> torch.Tensor:
    """Connected components of the columns through the rows whose cells all lie in one group,
    numbered group by group: :math:`(N_{cols},)` int64."""
    from scipy.sparse import csr_matrix  # here: a run that solves with another method need not import scipy
    from scipy.sparse.csgraph import connected_components

    Q = op.normal_equations().Q
    rows, col, _ = _q_entries(Q) if entries is None else entries
    same = (group.index_select(0, rows) == group.index_select(0, col)).to(torch.int8).cpu().numpy()
    # copy=True: eliminate_zeros works in place, and Q's own index arrays must stay as they are.
    graph = csr_matrix((same, Q.col_indices().cpu().numpy(), Q.crow_indices().cpu().numpy()), shape=Q.shape, copy=True)
    graph.eliminate_zeros()
    _, labels = connected_components(graph, directed=False)
    labels = torch.from_numpy(labels).to(group.device)
    return torch.unique(group * Q.shape[0] + labels, return_inverse=True)[1]


# Up to this many colours, groups are coloured by their index modulo the colours (exact for bands
# numbered across the image, where a row couples neighbouring bands only); beyond, greedily.
_MODULO_COLOURS = 4


def _narrowest(values: torch.Tensor, count: int) -> torch.Tensor:
    """``values`` (integers from 0 to ``count - 1``) in the narrowest integer type that holds them: a
    pass over ``Q``'s millions of entries then reads 1, 2 or 4 bytes an entry instead of 8."""
    return next((values.to(t) for t in (torch.int8, torch.int16, torch.int32) if count <= torch.iinfo(t).max), values)


def _colours(group: torch.Tensor, entries) -> torch.Tensor:
    """A colour for every group such that no row touches two groups of one colour: :math:`(G,)`."""
    rows, col, _ = entries
    n = int(group.max()) + 1
    # Each entry's two groups (int16 for the default scene's bands); their difference fits the same type.
    small = _narrowest(group, n)
    a, b = small.index_select(0, rows), small.index_select(0, col)
    span = int((a - b).abs_().max()) if a.numel() else 0
    if span < _MODULO_COLOURS:
        return torch.arange(n, device=group.device) % (span + 1)
    cross = a != b
    pairs = torch.unique(a[cross].long() * n + b[cross].long()).cpu().numpy()
    neighbours = [[] for _ in range(n)]
    for u, v in zip((pairs // n).tolist(), (pairs % n).tolist()):
        neighbours[u].append(v)
    colour = np.full(n, -1, dtype=np.int64)
    for g in range(n):
        taken = {colour[v] for v in neighbours[g]}
        colour[g] = next(c for c in range(len(taken) + 1) if c not in taken)
    return torch.from_numpy(colour).to(group.device)


def _chain_index(op, chains, calibrations, band, entries) -> tuple[torch.Tensor, torch.Tensor]:
    """:math:`(N_{cols},)` the block each column is solved in (a band of chains, a component, or the
    given chain), and its :math:`(N_{cols},)` colour."""
    if isinstance(chains, torch.Tensor):
        check(chains.shape == (op.shape[1],), f"chain index must have shape ({op.shape[1]},)")
        chain = torch.unique(chains.to(op.col.device).long(), return_inverse=True)[1]
        return chain, _colours(chain, entries)[chain]
    if chains == "epipolar":
        check(calibrations is not None, "chains='epipolar' needs the calibrations (for the fundamental matrix)")
        check(len(op.projector_sizes) == 2, f"epipolar chains need exactly two projectors, the operator has "
                                            f"{len(op.projector_sizes)}; use chains='components' (--chains "
                                            "components) or another solver")
        # The paper's chains inside one band share no row (that is how they are walked), so solving a band
        # as one block solves each of its chains: the same minimiser, for one step size per band and
        # without finding the chains (epipolar_chains does, 0.3 s at full size).
        bands = epipolar_bands(op, fundamental_between_projectors(calibrations), band)
        return bands, _colours(bands, entries)[bands]
    check(chains == "components", f"chains must be one of {list(CHAINS)} or a tensor, got {chains!r}")
    chain = _within(op, torch.zeros(op.shape[1], dtype=torch.int64, device=op.col.device), entries)
    return chain, torch.zeros_like(chain)


def _per_chain(values: torch.Tensor, index: torch.Tensor, n: int) -> torch.Tensor:
    """Sum of (N, C) values per chain -> (n,)."""
    return torch.zeros(n, dtype=values.dtype, device=values.device).index_add_(0, index, values.sum(1))


class _Colour:
    """The blocks of one colour: their part of the (Jacobi-scaled) ``Q``, its coupling to the other
    colours, and a step size per block (``chain`` numbers the blocks)."""

    def __init__(self, ne, rows, col, val, colour, entry_colours, position, chain, c: int, lo, hi):
        n = ne.Q.shape[0]
        self.idx = torch.nonzero(colour == c)[:, 0]
        mine = entry_colours[0] == c
        inside = mine & (entry_colours[1] == c)
        # Q's entries are sorted by row, then column, and positions keep that order: both blocks are CSR as cut.
        # Each mask becomes an index once, shared by the three arrays it selects from; index_select
        # gathers (on this CPU several times faster than indexing by a tensor, the same values).
        keep = torch.nonzero(inside)[:, 0]
        self.block = self._csr(position.index_select(0, rows.index_select(0, keep)),
                               position.index_select(0, col.index_select(0, keep)), val.index_select(0, keep),
                               (self.idx.shape[0],) * 2)
        keep = torch.nonzero(mine.logical_xor_(inside))[:, 0]
        self.coupling = self._csr(position.index_select(0, rows.index_select(0, keep)),
                                  col.index_select(0, keep).long(), val.index_select(0, keep), (self.idx.shape[0], n))
        self.chain = torch.unique(chain[self.idx], return_inverse=True)[1]
        self.n = int(self.chain.max()) + 1
        self.q = ne.q[self.idx]
        self.lo, self.hi = (b[self.idx] if torch.is_tensor(b) else b for b in (lo, hi))
        self.step = self._steps()

    @staticmethod
    def _csr(r, c, v, shape):
        crow = torch.zeros(shape[0] + 1, dtype=torch.int64, device=v.device)
        crow[1:] = torch.cumsum(torch.bincount(r, minlength=shape[0]), 0)
        return csr_tensor(crow, c, v, shape)

    def _steps(self, iterations: int = 5) -> torch.Tensor:
        """Per-block step sizes, :math:`(N, 1)`: power iteration on the block-diagonal block, normalised
        block by block; max over a block of (Q x)_i / x_i bounds its largest eigenvalue from above (Q >= 0).
        Five iterations measured as fast per sweep as ten and faster than Gershgorin's row sums."""
        x = torch.ones(self.idx.shape[0], 1, dtype=self.q.dtype, device=self.q.device)
        for _ in range(iterations):
            y = spmm(self.block, x)
            x = y / _per_chain(y * y, self.chain, self.n).sqrt().clamp_min(1e-30).index_select(0, self.chain)[:, None]
        ratio = (spmm(self.block, x) / x.clamp_min(1e-30))[:, 0]
        lam = torch.zeros(self.n, dtype=self.q.dtype, device=self.q.device).scatter_reduce_(0, self.chain, ratio,
                                                                                             reduce="amax")
        return (1.0 / lam.clamp_min(1e-30)).index_select(0, self.chain)[:, None]

    def solve(self, z: torch.Tensor, iterations: int) -> None:
        """Accelerated projected gradient on every block of this colour at once, the others held fixed;
        writes the blocks' new values into ``z``. Each block restarts its own momentum when its objective
        would rise, so none gets worse."""
        b = self.q - spmm(self.coupling, z)
        chain, n, step = self.chain, self.n, self.step

        def objective(x, qx):
            return _per_chain(x * (qx - 2 * b), chain, n)

        def gradient_step(x, qx):
            return _clamp_(x - step * (qx - b), self.lo, self.hi)

        x = z.index_select(0, self.idx)
        qx = spmm(self.block, x)
        y, qy, f = x, qx, objective(x, qx)
        t = torch.ones(n, dtype=x.dtype, device=x.device)
        for _ in range(iterations):
            x_new = gradient_step(y, qy)
            qx_new = spmm(self.block, x_new)
            f_new = objective(x_new, qx_new)
            restart = (f_new > f) & (t > 1)
            if bool(restart.any()):
                cols = restart.index_select(0, chain)[:, None]
                x_new = torch.where(cols, gradient_step(x, qx), x_new)
                qx_new = spmm(self.block, x_new)
                f_new = objective(x_new, qx_new)
                t = torch.where(restart, torch.ones_like(t), t)
            t_next = 0.5 * (1 + torch.sqrt(1 + 4 * t * t))
            beta = ((t - 1) / t_next).index_select(0, chain)[:, None]
            y, qy = x_new + beta * (x_new - x), qx_new + beta * (qx_new - qx)
            x, qx, f, t = x_new, qx_new, f_new, t_next
        z.index_copy_(0, self.idx, x)


def solve_eo(op: TransportOperator, bounds=(0.0, 1.0), *, chains: str | torch.Tensor = "epipolar",
             calibrations: dict[str, StateCalibration] | None = None, band: float = 1.0, max_iter: int = 300,
             tol: float = 1e-3, inner_iter: int = 3, levels: int = 3, progress: bool | None = None) -> SolveResult:
    """The paper's EO: chains of projector cells, solved within ``bounds`` in block sweeps that keep the
    light rows share between them (see the module's text).

    Args:
        op: the transport operator.
        bounds: ``(lo, hi)`` in linear relative light (``EO_0^255``: (0, 1); ``EO_-100^255``:
            (-100/255, 1), then :func:`~torchproj.solve.to_projectable`).
        chains: ``"epipolar"`` (two projectors; needs ``calibrations``), ``"components"`` (any number),
            or a precomputed :math:`(N_{cols},)` chain index.
        calibrations: the state calibrations the operator was built from (for the epipolar geometry).
        band: epipolar band width in projector pixels.
        max_iter: the most sweeps (each sweep visits every block once).
        tol: stop when a sweep lowers the objective by less than ``tol`` of it.
        inner_iter: accelerated gradient steps per block and sweep (3 measured fastest to the optimum on
            the paper's rig, before 5 and 10: more sweeps, each cheaper).
        levels: coarse levels of the start (see :func:`~torchproj.solve.solvers.coarse_start`);
            0 starts in the middle of the box.
        progress: progress bar (None: on a terminal, for solves longer than a second).

    Returns:
        a :class:`SolveResult`; ``iterations`` counts sweeps, ``info`` gives the number and sizes of the
        blocks solved together (epipolar bands of chains, components, or the given chains), the colours,
        the share of ``A^T A``'s weight that couples two blocks (what the paper's split drops and the
        sweeps keep) and the coarse levels' iterations.
    """
    check_operator(op)
    lo, hi = check_bounds(bounds)
    max_iter, inner_iter = check_count(max_iter, "max_iter"), check_count(inner_iter, "inner_iter")
    levels, tol = check_count(levels, "levels", 0), check_number(tol, "tol")
    t0 = time.perf_counter()
    plain = op.normal_equations()
    history = []
    # The coarse start (scipy's products P^T Q P on one core, then small solves) runs on a second thread
    # while this one cuts Q into the colours' blocks (solvers._beside): neither writes what the other
    # reads, and the patterns are the same to the bit; on the default scene it hides most of the
    # start's 0.5 s.
    with _beside(op.val.device, coarse_start, op, lo, hi, levels, 0.0, t0, history) as start:
        rows, col, unscaled = _q_entries(plain.Q)
        ne = plain.jacobi(rows)  # unit diagonal: the same scaling FISTA runs on; the same pattern
        val = ne.Q.values()
        chain, colour = _chain_index(op, chains, calibrations, band, (rows, col, val))
        n_colours = int(colour.max()) + 1
        # Each column's place among the columns of its colour.
        position = (torch.nn.functional.one_hot(colour, n_colours).cumsum(0) - 1).gather(1, colour[:, None])[:, 0]
        # Each entry's two colours, one byte each for a few colours: every colour's cut reads both.
        small = _narrowest(colour, n_colours)
        entry_colours = (small.index_select(0, rows), small.index_select(0, col))
        colours = [_Colour(ne, rows, col, val, colour, entry_colours, position, chain, c, ne.bound(lo), ne.bound(hi))
                   for c in range(n_colours)]
        p, coarse_iterations, _ = start()
    z = p / ne.scale

    def objective(x):
        return ne.objective(x, ne.product(x))

    f = objective(z)
    history.append((time.perf_counter() - t0, f))
    # Sweeps are extrapolated like FISTA's iterates (from the last kept sweep), and restarted, that
    # sweep taken again without momentum, when the objective would rise.
    kept, t = z.clone(), 1.0
    bar = progress_bar(desc="eo", enabled=progress, total=max_iter)
    converged, sweep = False, 0
    for sweep in range(1, max_iter + 1):
        bar.update(1)
        for block in colours:
            block.solve(z, inner_iter)
        f_new = objective(z)
        if f_new > f and t > 1:
            z, t = kept.clone(), 1.0
            continue
        history.append((time.perf_counter() - t0, f_new))
        done = _stop(f, f_new, tol)
        t_next = 0.5 * (1 + (1 + 4 * t * t) ** 0.5)
        beta = (t - 1) / t_next
        z, kept = _clamp_(z + beta * (z - kept), ne.bound(lo), ne.bound(hi)), z
        f, t = f_new, t_next
        if done:
            converged = True
            break
    bar.close()
    p = (kept * ne.scale).clamp_(lo, hi)
    objective_p = float(op.objective(p))
    history.append((time.perf_counter() - t0, objective_p))
    sizes = torch.bincount(chain)
    return SolveResult(patterns=p, iterations=sweep, objective=objective_p, history=history,
                       time_s=time.perf_counter() - t0, converged=converged, method="eo",
                       info={"blocks": int(sizes.shape[0]), "largest_block": int(sizes.max()),
                             "median_block": float(sizes.float().median()), "colours": len(colours),
                             "coupled_weight": _coupled_weight(unscaled, entry_colours),
                             "coarse_iterations": coarse_iterations})


def _coupled_weight(values: torch.Tensor, entry_colours) -> float:
    """Share of ``A^T A``'s weight (the sum of Q's entries ``values``: every product of two cells' light on
    one camera pixel) between cells of different blocks: what a split into independent blocks would drop.
    Blocks of one colour share no entry (:func:`_colours`), so that is the weight between colours.
    Summed as the objective is, run by run in float32 and the runs in float64: converting the default
    scene's 15.7 M entries to float64 first took most of the 0.08 s this took then.
    """
    between = torch.where(entry_colours[0] != entry_colours[1], values, 0)
    return float(_blockwise_sum(between) / _blockwise_sum(values).clamp_min(1e-300))
