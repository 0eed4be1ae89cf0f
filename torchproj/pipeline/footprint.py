"""``footprint="auto"``: the least costly model of a pixel's light whose expected loss is within a tolerance.

The models, cheapest first: ``nearest`` (one cell per pixel and projector, the paper's; rows merge),
then ``area`` (the cells the pixel's area covers, fitted to the shares its captures measured: the
richest, and several times the cost to build and solve). ``bilinear`` is not on the ladder: on the
procedural suite it costs about twice nearest and stays 2.3 dB (median) short of area
(``benchmarks/suite.py``).

What nearest loses is measured by the calibration itself, not by the simulator: every full-sequence
calibration keeps, per pixel, the share of its light that came from across each edge of its cell
(:class:`~torchproj.calib.CellShares`). Nearest's row puts all of it on one cell. So the patterns
nearest solves are carried through both rows, nearest's and the measured shares' (the decoded cell
and its four neighbours by their shares), and their difference on the targets' pixels is the error
nearest's model makes on its own patterns. Against what nearest leaves unexplained anyway (its
residual to the targets), it gives each target's expected loss in PSNR,
``10 log10(1 + mean(difference^2) / mean(residual^2))``. Where every target's is within
``tolerance_db``, nearest is chosen; else area. Our rule (the paper models one cell per pixel):
where the shares say that a pixel's light stays on one cell, a richer model has nothing to add.

The estimate is taken first before anything is built or solved, on the targets' back-projection
through nearest's rows (each cell the weighted mean of what its pixels ask, ``A^T b / A^T A 1``),
then, where that does not decide, on nearest's patterns after :data:`SCREEN_ITERATIONS` iterations
from its coarse start. Both are smoother than the solution and leave more of the targets
unexplained, and both make the estimate smaller than at the end: on the procedural suite's seed 1
(20 scenes, 60 targets) each target's estimate on the back-projection was at or below its value
after 5 iterations, and those after 5, 10 and 20 at or below the next but for 7 of 180 (target,
iterations) pairs, by at most 0.02 dB where nearest had all but converged
(``benchmarks/auto_cost.py``); on the unseen seed 97 the back-projection's was above the
5-iteration one on 2 of 62 targets, each with every estimate 8 dB or more, far past any tolerance. So where even the earlier one is over the tolerance, area is chosen
without solving nearest further (our rule, which saves building and solving nearest: the
back-projection costs one pass over nearest's rows and the shares'), and solved from its own
coarse start, so that it shows exactly what ``footprint="area"`` shows; otherwise nearest is
solved to the end and decided on as before (the benchmark measures each rule).

Where no shares were measured (a shortened Gray-code sequence, maps from homographies, a bundle
written without them) nothing tells the models apart from the captures, and area is chosen.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import torch

from ..core.checks import check, check_number
from ..core.conventions import round_to_pixel
from ..core.sparse import spmm
from ..solve import solve_fista
from ..solve.compensate import iteration_limit
from ..transport import FOOTPRINTS, StateCalibration, Target, TransportOperator, build_transport, csr_from_coo
# build_transport's own rows and scale, before assembly: the screen needs nearest's rows, not its operator
from ..transport.build import _scale, _target_rows, check_calibrations, check_targets

__all__ = ["AUTO", "AUTO_TOLERANCE_DB", "SCREEN_BACK_PROJECTION", "SCREEN_ITERATIONS", "FootprintChoice", "check_footprint", "choose_footprint"]

AUTO = "auto"
# The loss against the richest model that auto accepts for a cheaper one: the "within 0.2 dB".
AUTO_TOLERANCE_DB = 0.2
#: Nearest's iterations before its expected loss is first looked at on its patterns (module docstring).
SCREEN_ITERATIONS = 10
#: Whether the expected loss is looked at on the targets' back-projection first (module docstring).
SCREEN_BACK_PROJECTION = True


def check_footprint(footprint: str) -> None:
    """``footprint`` names a model of :data:`~torchproj.transport.FOOTPRINTS` or ``"auto"`` (checked
    before any work)."""
    check(footprint in (*FOOTPRINTS, AUTO), f"footprint must be one of {[*FOOTPRINTS, AUTO]}, got {footprint!r}")


@dataclass
class FootprintChoice:
    """What :func:`choose_footprint` chose and why.

    Attributes:
        footprint: ``"nearest"`` or ``"area"``.
        expected_loss_db: per target name, nearest's expected PSNR loss against a model that holds
            the measured shares (None where no shares were measured).
        tolerance_db: the loss accepted.
        seconds: time the choice took (the back-projection's estimate where that decides; else nearest
            built and solved: for :data:`SCREEN_ITERATIONS` iterations where that decides, else to the end).
        reason: one sentence for the report.
        iterations: nearest's iterations the estimate was taken after: 0 where the back-projection's
            estimate already exceeded the tolerance (or no shares were measured),
            :data:`SCREEN_ITERATIONS` where the early estimate did.
    """

    footprint: str
    expected_loss_db: dict[str, float] | None
    tolerance_db: float
    seconds: float
    reason: str = ""
    iterations: int = 0
    # nearest's columns' cell indices (_cell_index), its patterns and mid-grey; not its operator, which
    # may be gone before the chosen model is built
    _start: tuple | None = field(default=None, repr=False)

    def start_for(self, op: TransportOperator) -> torch.Tensor | None:
        """Nearest's solved patterns on ``op``'s columns (mid-grey where nearest had no such cell),
        :math:`(N_{cols}, C)`: a start for the chosen model's solve, which then skips its coarse
        levels (on suite scenes about the time nearest's own solve took). None where nothing was solved,
        nearest was only screened (:data:`SCREEN_ITERATIONS`) or the channels differ."""
        if self._start is None:
            return None
        (cells, count), patterns, middle = self._start
        if patterns.shape[1] != op.channels:
            return None
        table = torch.full((count, patterns.shape[1]), middle, dtype=patterns.dtype, device=patterns.device)
        table[cells.to(patterns.device)] = patterns
        return table[_cell_index(op)[0].to(patterns.device)].to(op.val)

    def solver_options(self, ops: list[TransportOperator], solver: str, options: dict | None = None) -> dict | None:
        """``options`` for :func:`~torchproj.solve.make_patterns` with nearest's patterns as FISTA's
        start (``x0``) where one operator is solved by FISTA; ``options`` as they are otherwise."""
        x0 = self.start_for(ops[0]) if solver == "fista" and len(ops) == 1 else None
        return options if x0 is None else {**(options or {}), "x0": x0}

    def as_dict(self) -> dict:
        return {"footprint": self.footprint, "tolerance_db": self.tolerance_db, "seconds": round(self.seconds, 3),
                "nearest_iterations": self.iterations,
                "expected_loss_db": None if self.expected_loss_db is None else
                {k: round(v, 3) for k, v in self.expected_loss_db.items()}, "reason": self.reason}


def choose_footprint(states: dict[str, StateCalibration], targets: list[Target], bounds: tuple[float, float] = (0.0, 1.0),
                     *, tolerance_db: float = AUTO_TOLERANCE_DB, device="cpu") -> FootprintChoice:
    """The least costly footprint whose expected loss is within ``tolerance_db`` of the richest
    (module docstring): ``nearest`` or ``area``.

    Args:
        states: state name -> :class:`~torchproj.transport.StateCalibration`, as for
            :func:`~torchproj.transport.build_transport`.
        targets: the targets to be solved.
        bounds: the solver's box, linear light.
        tolerance_db: the expected PSNR loss (dB, >= 0) a cheaper model may have on any target.
    """
    check_number(tolerance_db, "tolerance_db (dB)")
    check_calibrations(states, "states")
    check_targets(targets)
    t0 = time.perf_counter()
    used = {t.state for t in targets}
    if any(states[s].shares is None for s in used if s in states):
        return FootprintChoice("area", None, tolerance_db, time.perf_counter() - t0,
                               "area: no cell shares were measured (a shortened Gray-code sequence, homography maps "
                               "or a bundle without them), so nothing tells the models apart; the richest is kept")
    if SCREEN_BACK_PROJECTION:
        loss = _back_projected_loss(states, targets, bounds)
        worst = max(loss, key=loss.get)
        if loss[worst] > tolerance_db:
            return FootprintChoice("area", loss, tolerance_db, time.perf_counter() - t0,
                                   f"area: the measured cell shares put nearest's expected loss at {loss[worst]:.2f} dB "
                                   f"on {worst}, over {tolerance_db:g} dB already on the targets' back-projection (an "
                                   "estimate that rises as nearest's patterns sharpen), before nearest was built")
    op = build_transport(states, targets, footprint="nearest", merge=False, device=device)
    shares = _share_rows(states, targets, op)
    result = solve_fista(op, bounds, progress=False, max_iter=SCREEN_ITERATIONS)
    iterations = result.iterations
    loss = _expected_loss(op, shares, result.patterns, targets)
    worst = max(loss, key=loss.get)
    screened = loss[worst] > tolerance_db
    if not screened:  # not decided yet: nearest to the end, from where it stopped
        limit = iteration_limit(None)["max_iter"]
        if not result.converged and iterations < limit:
            result = solve_fista(op, bounds, progress=False, x0=result.patterns, max_iter=limit - iterations)
            iterations += result.iterations
            loss = _expected_loss(op, shares, result.patterns, targets)
            worst = max(loss, key=loss.get)
    if loss[worst] <= tolerance_db:
        footprint = "nearest"
        reason = (f"nearest: the measured cell shares put nearest's expected loss at {loss[worst]:.2f} dB at most "
                  f"({worst}), within {tolerance_db:g} dB")
    else:
        footprint = "area"
        reason = (f"area: the measured cell shares put nearest's expected loss at {loss[worst]:.2f} dB on {worst}, over "
                  f"{tolerance_db:g} dB" + (f" already after {iterations} of nearest's iterations (an estimate that rises "
                                            "as nearest converges)" if screened else ""))
    # A screen's patterns (a few of nearest's iterations) are a poor start for area, and without one
    # area shows exactly what footprint="area" shows.
    start = None if screened else (_cell_index(op), result.patterns, 0.5 * (bounds[0] + bounds[1]))
    return FootprintChoice(footprint, loss, tolerance_db, time.perf_counter() - t0, reason, iterations, start)


def _expected_loss(op: TransportOperator, shares: torch.Tensor, patterns: torch.Tensor,
                   targets: list[Target]) -> dict[str, float]:
    """Per target name, nearest's expected PSNR loss on ``patterns`` (module docstring): what the rows of
    the measured ``shares`` differ from nearest's rows by, against nearest's residual to the targets."""
    with torch.no_grad():
        return _loss_from_rows(op.A(patterns), spmm(shares, patterns), op.rhs, op.row_target, targets)


def _loss_from_rows(nearest: torch.Tensor, measured: torch.Tensor, rhs: torch.Tensor, row_target: torch.Tensor,
                    targets: list[Target]) -> dict[str, float]:
    """Per target name, ``10 log10(1 + mean(difference^2) / mean(residual^2))`` over its rows, from
    nearest's rows' values, the measured shares' and the right-hand side, :math:`(N, C)` each."""
    loss = {}
    for k, target in enumerate(targets):
        rows = row_target == k
        residual = float((nearest[rows] - rhs[rows]).double().pow(2).mean())
        difference = float((measured[rows] - nearest[rows]).double().pow(2).mean())
        loss[target.name or f"target{k}"] = 10 * math.log10(1 + difference / max(residual, 1e-30))
    return loss


def _back_projected_loss(states: dict[str, StateCalibration], targets: list[Target],
                         bounds: tuple[float, float]) -> dict[str, float]:
    """Per target name, nearest's expected loss (:func:`_loss_from_rows`) on the targets' back-projection
    through nearest's rows, before anything is built or solved (module docstring).

    Nearest's rows come straight from the maps (each pixel's cell and weight per projector,
    as :func:`~torchproj.transport.build_transport` takes them); each cell's pattern is the weighted mean of
    what its rows ask over what all projectors give there, ``p = A^T b / A^T A 1``, clamped to the box.
    A cell no row lights is black, as a cell that is no column of nearest's operator."""
    rows = _target_rows(states, targets, "nearest", colour=False)
    rhs = rows.values * _scale(rows.vals, None)
    sizes = rows.sizes
    count = sum(w * h for w, h in sizes)
    used = rows.cols >= 0
    row = torch.nonzero(used)[:, 0]
    cell, weight = rows.cols[used], rows.vals[used]
    asked = rhs.new_zeros(count, rhs.shape[1]).index_add_(0, cell, weight[:, None] * rhs[row])
    given = rhs.new_zeros(count).index_add_(0, cell, weight * rows.vals.sum(1)[row])
    patterns = torch.where(given[:, None] > 0, asked / given.clamp_min(1e-30)[:, None], 0.0).clamp(*bounds)
    nearest = torch.zeros_like(rhs).index_add_(0, row, weight[:, None] * patterns[cell])
    at_row, at_cell, share = (t.to(rhs.device) for t in _share_parts(states, targets, rows.target, rows.pixel, sizes))
    measured = torch.zeros_like(rhs).index_add_(0, at_row, share[:, None] * patterns[at_cell])
    return _loss_from_rows(nearest, measured, rhs, rows.target, targets)


def _cell_index(op: TransportOperator) -> tuple[torch.Tensor, int]:
    """Each of ``op``'s columns as one index over every projector's cells (projectors one after
    another), and how many cells there are."""
    starts = torch.tensor([0] + [w * h for w, h in op.projector_sizes], device=op.column_cell.device).cumsum(0)
    return starts[op.column_projector] + op.column_cell, int(starts[-1])


def _share_parts(states: dict[str, StateCalibration], targets: list[Target], row_target: torch.Tensor,
                 row_pixel: torch.Tensor, sizes: list[tuple[int, int]]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rows (camera pixels: each ``row_target``'s pixel ``row_pixel``) as the measured shares place each
    pixel's light, in coordinates: ``(row, cell, value)`` :math:`(E,)`, ``cell`` one index over every
    projector's cells (:func:`_cell_index`'s). A row's pixel gives its share cell ``n`` the share not
    measured across an edge, each neighbour ``n +- 1`` along x and y the share measured across that
    edge, each times the projector's weight."""
    starts = torch.tensor([0] + [w * h for w, h in sizes]).cumsum(0)
    steps = torch.tensor([[0, 0], [-1, 0], [1, 0], [0, -1], [0, 1]])
    rows, cells, vals = [], [], []
    row_target, row_pixel = row_target.cpu(), row_pixel.cpu()
    for name in dict.fromkeys(t.state for t in targets):  # each state's rows together: fewer, longer passes
        which = torch.nonzero(torch.tensor([t.state == name for t in targets])[row_target])[:, 0]
        pixels = row_pixel[which]
        state = states[name]
        for j, (w, h) in enumerate(sizes):
            shares, weight = state.shares[j], state.weight[j].reshape(-1)[pixels].float()
            cell = shares.cell.reshape(-1, 2)[pixels].long()
            nearest = round_to_pixel(torch.nan_to_num(state.prj_xy[j].reshape(-1, 2)[pixels], nan=-10.0))
            known = (cell >= 0).all(-1)
            # A pixel without a share cell (filled holes, dim light) keeps its nearest cell whole.
            cell = torch.where(known[:, None], cell, nearest)
            across = torch.nan_to_num(shares.across.reshape(-1, 2, 2)[pixels].float(), nan=0.0)
            across = torch.where(known[:, None, None], across, 0.0).reshape(-1, 4)
            # The five places, cell first, then x - 1, x + 1, y - 1, y + 1 (across's order), all at once.
            at = cell[None] + steps.to(cell.device)[:, None]
            share = torch.cat([1 - across.sum(1, keepdim=True), across], 1).T
            keep = ((at >= 0).all(-1) & (at[..., 0] < w) & (at[..., 1] < h) & (share > 0)
                    & (torch.isfinite(weight) & (weight > 0))[None])
            part, pixel = torch.nonzero(keep, as_tuple=True)
            rows.append(which[pixel.cpu()])
            cells.append((starts[j] + at[part, pixel, 1].cpu() * w + at[part, pixel, 0].cpu()))
            vals.append((weight[pixel] * share[part, pixel]).cpu())
    return torch.cat(rows), torch.cat(cells), torch.cat(vals)


def _share_rows(states: dict[str, StateCalibration], targets: list[Target], op: TransportOperator) -> torch.Tensor:
    """CSR, ``op``'s rows (camera pixels) as the measured shares place each pixel's light
    (:func:`_share_parts`), over ``op``'s columns (a cell that is no column is black in every pattern
    of ``op``)."""
    cells, count = _cell_index(op)
    column = torch.full((count,), -1, dtype=torch.int64)
    column[cells.cpu()] = torch.arange(op.shape[1])
    rows, at, vals = _share_parts(states, targets, op.row_target, op.row_pixel, op.projector_sizes)
    col = column[at]
    keep = col >= 0
    return csr_from_coo(rows[keep], col[keep], vals[keep], op.shape).to(op.val.device)
