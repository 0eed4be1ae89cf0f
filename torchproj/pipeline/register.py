"""Where the light lands now: the calibrated transport's rows moved to match a capture of the patterns.

A bumped projector or camera moves every camera pixel's projector coordinates: the calibrated
transport's entries then sit a fraction of a cell, or a few cells, from where the light lands, and
correcting the patterns through it (:func:`~torchproj.solve.refine_patterns`) pushes light to the
wrong cells. A capture of any patterns measures the move. Each target's pixels see each projector's
light image ``L_j`` (the patterns as linear light) through the map ``x_j(r)``; the capture is modelled
as

    m(r) ~ (A p)(r) + sum_j w_j(r) [g_kj L_j(x_j(r) + d_kj(r)) - L_j(x_j(r))] + c_k,

with ``d_kj`` an affine function of the camera pixel per target ``k`` and projector ``j`` (a plane's
map moves by a homography, close to affine for a drift; each target is its own piece), ``g_kj`` a
gain and ``c_k`` an offset that take what is photometric out of the fit. Gauss-Newton on the 6 + 1
numbers per target and projector and one per target, on light images blurred by 2 cells, then 1,
then sharp (a move of a few cells is found before the fine gradients take over), with Huber
weights (a pixel on an outline sees two surfaces; the point-sampled light misses what a wide
footprint averages), gives ``d``. The moved model is then the one that predicts the capture best
(:class:`Reregister`): each row's entries moved by its ``d``, or the transport rebuilt from the
moved maps, with the calibration's cell shares dropped or carried through the move.

The cell shares (how each pixel's light splits across the edges of its cell, which the area rows are
fitted to) belong to the maps as calibrated: a move of a fraction of a cell changes them. Dropped,
the rows lose what they measured (rebuilt without them, ``box_cylinders`` at quarter size loses 2.4 /
1.3 dB in the world it was calibrated in, suite-1-7 up to 7.0 dB). :func:`carry_shares` carries them
instead: per axis, the shares every pixel of the projector measured, tabled against where the map
puts the pixel in its cell and how wide its light is, read at the pixel's moved place (an even
interval of light where the table has too few pixels). Given the simulator's moves (``python
benchmarks/drift.py --moved-models``), the model rebuilt with carried shares scores a 2 mm projector
move on ``box_cylinders`` at quarter size 29.91 / 30.55 dB, against 27.82 / 29.13 with the shares
dropped and 29.76 / 25.80 with the rows moved (the ceiling 30.25 / 31.11), and a 0.2 degree turn
29.59 / 29.84 against 28.08 / 28.83 and 22.31 / 21.25 (30.99 / 31.02); where the rows moved score
better (suite-1-7's near plane), the loop takes them, so all three stay candidates. The outline pixels that see
two surfaces (:class:`~torchproj.calib.EdgePixels`) move with them: dropped, the sphere's ball loses
1.6 dB where nothing moved.

A moved camera is another move: every target's image slides across the camera pixels, and through
each projector's map (curved on a sphere, steep on a cylinder) that is no affine move of the cells.
:func:`register_camera` fits it in the camera's own terms, a shift per target (and a gain and an
offset), ``m(r) ~ g_k (A p)(r + s_k) + c_k``, with the same blurs and weights, and carries each row's
shifted pixel through the calibrated maps into a move per projector, ``u_j(r + s_k) - u_j(r)``. The
transport rebuilt from those moves is a third candidate model.

Measured in ``benchmarks/drift.py``. This is torchproj's construction; the paper calibrates once.
"""

from __future__ import annotations

import dataclasses

import torch
import torch.nn.functional as F
from kornia.filters import gaussian_blur2d

from ..calib import CellShares
from ..core.checks import check
from ..core.conventions import round_to_pixel
from ..transport import Target
from ..transport.build import build_operators

__all__ = ["REGISTER_MIN_CELLS", "REREGISTER_MIN_CELLS", "Reregister", "carry_shares", "register_camera", "register_maps"]

# A median move below these (cells) is left to the loop's defect: rebuilding costs a transport build.
# Our choices, measured in benchmarks/drift.py. From the calibrated model, REGISTER_MIN_CELLS: at 0.1
# the first capture of suite-3131-1 with a projector moved 0.5 mm measured 0.10 cells (the
# simulator's move is 0.17) and the loop never rebuilt; a brighter lamp fits under 0.025. From a model
# the loop already moved, REREGISTER_MIN_CELLS: a rebuilt model's own errors (its decoded maps' and
# carried shares') fit as moves too, and at 0.05 suite-1-7's moved camera measured 0.07-0.08 cells on
# later captures, each rebuild predicting the capture better and scoring worse (3.69 dB below the
# ceiling after 10 captures, against 1.83).
REGISTER_MIN_CELLS = 0.05
REREGISTER_MIN_CELLS = 0.1
_BLURS = (2.0, 1.0, 0.0)  # cells; Gauss-Newton steps per blur below
_STEPS = 3
_RIDGE = 1e-6
_FIT_ROWS = 100_000  # rows per target the fit samples (evenly)
_HUBER = 1.5  # robust scales (median absolute deviations) past which a pixel's residual counts linearly
_MIN_SHIFT_ROWS = 32  # a target with fewer pixels inside its blurred image keeps the shift it has
# carry_shares: a share under this is no light across the edge; over this, clamped (the decoded cell holds the most)
_CARRY_MIN_SHARE, _CARRY_MAX_SHARE = 0.005, 0.49
_CARRY_MIN_REACH = 0.01  # cells: the least distance from u to an edge, and from a one-edge share to a half
_CARRY_MIN_INSIDE = 0.1  # the least share left in the cell of light measured across both its edges
# carry_shares' table of the measured shares against the map's phase in its cell and the pixel's
# extent (cells; our choices, measured in benchmarks/drift.py --moved-models): bins of phase over
# [-1, 1] and of extent up to 3 cells; a bin averages at least _TABLE_MIN pixels or is not read.
_TABLE_PHASE_BIN, _TABLE_EXTENT_BIN, _TABLE_EXTENT_MAX, _TABLE_MIN = 0.02, 0.05, 3.0, 3
# Where a pixel's measured shares differ from the table's at its phase by over _PHASE_MISFIT, its
# phase is corrected by one of _PHASE_STEPS offsets within +-_PHASE_SPAN cells (about three times a
# decoded map's rms error), each penalised by _PHASE_PENALTY per square cell against the squared
# misfit of its two shares.
_PHASE_MISFIT, _PHASE_SPAN, _PHASE_STEPS, _PHASE_PENALTY = 0.05, 0.1, 21, 10.0
# How much better than the best other model the carried shares must predict a capture (a share of its
# miss). Near-ties gain nothing: paper_bumped at full size predicted its first capture at 436.03 with
# them against 436.12 without and ended with SSIM 0.02 lower, PSNR the same; the paper's rig at
# quarter size turned 0.05 / 0.2 degrees, 2.1 / 1.8% better, PSNR within 0.05 dB and SSIM 0.01 lower.
_CARRY_MARGIN = 0.05


def _blurred(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """An (H, W) image blurred by a Gaussian of ``sigma`` cells (3 sigma each side, edges replicated)."""
    if sigma <= 0:
        return image
    size = 2 * int(3 * sigma + 0.5) + 1
    return gaussian_blur2d(image[None, None], (size, size), (sigma, sigma), border_type="replicate")[0, 0]


def _sample(image: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of an (H, W) image at cell coordinates (N, 2) (cell centres at integers)."""
    h, w = image.shape
    grid = torch.stack([2 * xy[:, 0] / max(w - 1, 1) - 1, 2 * xy[:, 1] / max(h - 1, 1) - 1], -1)
    return F.grid_sample(image[None, None], grid.view(1, 1, -1, 2), mode="bilinear", padding_mode="border",
                         align_corners=True).view(-1)


def _affine_basis(pixels: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """(N, 3): 1 and the camera pixel's coordinates scaled to about [-1, 1] (a well-conditioned fit)."""
    x, y = _pixel_xy(pixels, width).unbind(1)
    u, v = x / max(width - 1, 1) * 2 - 1, y / max(height - 1, 1) * 2 - 1
    return torch.stack([torch.ones_like(u), u, v], 1)


def register_maps(states: dict, targets: list[Target], op, p: torch.Tensor, measured: torch.Tensor,
                  moved: torch.Tensor | None = None):
    """Where a capture of ``p`` says each row's light now lands (module docs).

    Args:
        states: per state the :class:`~torchproj.transport.StateCalibration` the operator was built from.
        targets: the operator's targets.
        op: the operator the patterns were solved on (rows on camera pixels), or one per colour channel.
        p: :math:`(N_{cols}, C)` the patterns captured.
        measured: :math:`(N_{rows}, C)` their capture above black at the rows.
        moved: :math:`(N_{rows}, J, 2)` moves ``op`` already holds (cells; None: none), the start of the fit.

    Returns:
        ``(moves, median, explained)``: :math:`(N_{rows}, J, 2)` each row's total move per projector
        (cells, for :meth:`~torchproj.transport.TransportOperator.with_rows_moved` on the calibrated
        operator), the largest over projectors of this fit's median change on the rows it reaches, and the share of the
        residual energy (robustly weighted) the moves explain beyond a gain per projector and an offset.
    """
    ops = list(op) if isinstance(op, (list, tuple)) else [op]
    first = ops[0]
    check(first.row_pixel is not None, "re-registering needs rows on camera pixels: build with merge=False")
    w_cam, h_cam = first.camera_size
    n_proj = len(first.projector_sizes)
    moved = torch.zeros(first.shape[0], n_proj, 2, dtype=torch.float64) if moved is None else moved.double().cpu()
    grey_light = [img.double().mean(0).cpu() for img in first.to_images(p.detach())]
    predicted = torch.cat([o.A(p[:, c:c + 1]) for c, o in enumerate(ops)], 1) if len(ops) > 1 else first.A(p)
    residual_base = (measured.double() - predicted.double()).mean(1).cpu()
    total = moved.clone()
    energy = {"still": 0.0, "moved": 0.0}
    for k, target in enumerate(targets):
        every = torch.nonzero(first.row_target == k)[:, 0].cpu()
        # 15 numbers per target and projector need no million rows: an even sample of them, every row moved.
        rows = every[::max(1, len(every) // _FIT_ROWS)]
        pixels = first.row_pixel[rows].cpu()
        cal = states[target.state]
        basis = _affine_basis(pixels, w_cam, h_cam)
        # The fit is a few thousand rows: on the host, where the patterns' images already are.
        maps = [m.reshape(-1, 2)[pixels.to(m.device)].double().cpu() for m in cal.prj_xy]
        base = [torch.nan_to_num(m) + moved[rows, j] for j, m in enumerate(maps)]
        weight = [wt.reshape(-1)[pixels.to(wt.device)].double().cpu() for wt in cal.weight]
        usable = [torch.isfinite(m).all(-1) & (wt > 0) for m, wt in zip(maps, weight)]
        theta = torch.zeros(n_proj, 7, dtype=torch.float64)  # affine x (3), affine y (3), gain - 1
        offset = torch.zeros((), dtype=torch.float64)
        residual0 = residual_base[rows]
        for sigma in _BLURS:
            light = [_blurred(img, sigma) for img in grey_light]
            grads = [torch.gradient(img) for img in light]  # (d/dy, d/dx)
            # What each projector adds where the model has it now: fixed within a blur level.
            still = [torch.where(ok, wt * _sample(img, at), 0.0) for img, at, wt, ok in zip(light, base, weight, usable)]
            for _ in range(_STEPS):
                model = torch.zeros_like(residual0)
                columns = []
                for j in range(n_proj):
                    ok = usable[j]
                    at = base[j] + torch.stack([basis @ theta[j, :3], basis @ theta[j, 3:6]], 1)
                    seen = torch.where(ok, _sample(light[j], at), 0.0)
                    gain = 1 + theta[j, 6]
                    model += torch.where(ok, weight[j] * gain * seen, 0.0) - still[j]
                    gx = torch.where(ok, gain * weight[j] * _sample(grads[j][1], at), 0.0)
                    gy = torch.where(ok, gain * weight[j] * _sample(grads[j][0], at), 0.0)
                    columns += [gx[:, None] * basis, gy[:, None] * basis, torch.where(ok, weight[j] * seen, 0.0)[:, None]]
                jac = torch.cat(columns + [torch.ones(len(rows), 1, dtype=torch.float64)], 1)
                res = residual0 - model - offset
                # Huber weights: outline pixels that see two surfaces, and what the point-sampled light
                # misses of a wide footprint, must not pull every pixel's move.
                step, robust = _huber_step(jac, res)
                theta += step[:-1].view(n_proj, 7)
                offset = offset + step[-1]
        left = res - jac @ step
        energy["moved"] += float((robust * left.pow(2)).sum())
        energy["still"] += _photometric_residual(still, residual0, robust)
        basis = _affine_basis(first.row_pixel[every].cpu(), w_cam, h_cam)
        for j in range(n_proj):
            total[every, j, 0] += basis @ theta[j, :3]
            total[every, j, 1] += basis @ theta[j, 3:6]
    explained = 1 - energy["moved"] / energy["still"] if energy["still"] > 0 else 0.0
    return total, _median_change(first, total - moved), explained


def _median_change(op, change: torch.Tensor) -> float:
    """The largest over projectors of the median length of ``change`` :math:`(N_{rows}, J, 2)` (cells) on
    the rows that have an entry in one of the projector's columns."""
    length = change.norm(dim=-1)  # (rows, J)
    reached = torch.zeros_like(length, dtype=torch.bool)
    reached[torch.repeat_interleave(torch.arange(op.shape[0]), op.crow.diff().cpu()),
            op.column_projector[op.col].cpu()] = True
    return max((float(length[reached[:, j], j].median()) for j in range(length.shape[1]) if bool(reached[:, j].any())),
               default=0.0)


def _huber_step(jac: torch.Tensor, res: torch.Tensor, inside: torch.Tensor | None = None):
    """One Gauss-Newton step of a robust fit, and its Huber weights: residuals past :data:`_HUBER`
    robust scales (median absolute deviations, over the ``inside`` rows where given; the others weigh
    nothing) count linearly, and the normal equations are damped by :data:`_RIDGE` of their mean
    diagonal. Returns ``(step, robust)``."""
    spread = _HUBER * 1.4826 * float((res if inside is None else res[inside]).abs().median()) + 1e-12
    robust = (spread / res.abs().clamp_min(1e-12)).clamp(max=1.0)
    robust = robust if inside is None else robust * inside
    normal = jac.T @ (robust[:, None] * jac)
    normal += _RIDGE * normal.diagonal().mean() * torch.eye(normal.shape[0], dtype=torch.float64)
    return torch.linalg.solve(normal, jac.T @ (robust * res)), robust


def _pixel_xy(pixels: torch.Tensor, width: int) -> torch.Tensor:
    """(N, 2) float64 ``(x, y)`` of flat camera pixel indices (row-major, ``width`` pixels a row)."""
    return torch.stack([(pixels % width).double(), torch.div(pixels, width, rounding_mode="floor").double()], 1)


def _photometric_residual(still: list[torch.Tensor], residual: torch.Tensor, robust: torch.Tensor) -> float:
    """The (robustly weighted) residual energy left by a gain per projector (on ``still``, each
    projector's light where the model has it) and one offset, nothing moved."""
    jac = torch.stack(still + [torch.ones_like(residual)], 1)
    root = robust.sqrt()[:, None]
    fit = torch.linalg.lstsq(jac * root, residual[:, None] * root).solution
    return float((robust * (residual - (jac @ fit)[:, 0]).pow(2)).sum())


def register_camera(states: dict, targets: list[Target], op, p: torch.Tensor, measured: torch.Tensor):
    """Where a capture of ``p`` says the camera moved (module docs): a shift of each target's image.

    Args:
        states, targets: as :func:`register_maps`.
        op: the operator as calibrated (rows on camera pixels), or one per colour channel.
        p: :math:`(N_{cols}, C)` the patterns captured, on ``op``'s columns.
        measured: :math:`(N_{rows}, C)` their capture above black at the rows.

    Returns:
        ``(moves, shifts)``: :math:`(N_{rows}, J, 2)` each row's move per projector (cells, from the
        calibrated maps: the cells its shifted pixel's light comes from, less its own; a pixel whose
        shifted place the maps do not cover takes its target's median move), and per target the
        fitted shift ``(dx, dy)`` in camera pixels.
    """
    ops = list(op) if isinstance(op, (list, tuple)) else [op]
    first = ops[0]
    check(first.row_pixel is not None, "re-registering needs rows on camera pixels: build with merge=False")
    w_cam, h_cam = first.camera_size
    predicted = torch.cat([o.A(p[:, c:c + 1]) for c, o in enumerate(ops)], 1) if len(ops) > 1 else first.A(p)
    predicted, measured = predicted.detach().double().mean(1).cpu(), measured.detach().double().mean(1).cpu()
    moves = torch.zeros(first.shape[0], len(first.projector_sizes), 2, dtype=torch.float64)
    shifts = []
    row_target, row_pixel = first.row_target.cpu(), first.row_pixel.cpu()
    for k, target in enumerate(targets):
        every = torch.nonzero(row_target == k)[:, 0]
        shift = _fit_shift(predicted, measured, every, row_pixel, w_cam, h_cam)
        shifts.append(tuple(round(float(v), 4) for v in shift))
        pixels = row_pixel[every]
        at = _pixel_xy(pixels, w_cam) + shift
        for j, xy in enumerate(states[target.state].prj_xy):
            here = xy.reshape(-1, 2)[pixels.to(xy.device)].double().cpu()
            there = _bilinear_map(xy.double().cpu(), at)
            known = torch.isfinite(here).all(-1) & torch.isfinite(there).all(-1)
            move = there - here
            fallback = move[known].median(0).values if bool(known.any()) else torch.zeros(2, dtype=torch.float64)
            moves[every, j] = torch.where(known[:, None], move, fallback)
    return moves, shifts


def _fit_shift(predicted: torch.Tensor, measured: torch.Tensor, rows: torch.Tensor, row_pixel: torch.Tensor,
               width: int, height: int) -> torch.Tensor:
    """``(dx, dy)`` camera pixels with ``measured(r) ~ g predicted(r + s) + c`` on one target's ``rows``:
    Gauss-Newton on the predicted image, blurred among the target's own pixels (a normalised
    convolution: no edge to the black around it) by 2, 1, then 0 pixels, with Huber weights. A shift
    alone: an affine warp per target fitted shears and scales that no camera move makes on a target
    of a few hundred pixels (suite-1-7), and a bumped camera moves a target's image nearly rigidly."""
    image = torch.zeros(height * width, dtype=torch.float64)
    mask = torch.zeros(height * width, dtype=torch.float64)
    image[row_pixel[rows]] = predicted[rows]
    mask[row_pixel[rows]] = 1.0
    image, mask = image.view(height, width), mask.view(height, width)
    sample = rows[::max(1, len(rows) // _FIT_ROWS)]
    pixels = row_pixel[sample]
    xy = _pixel_xy(pixels, width)
    value = measured[sample]
    theta = torch.zeros(4, dtype=torch.float64)  # dx, dy, gain - 1, offset
    for sigma in _BLURS:
        weight = _blurred(mask, sigma)
        light = torch.where(weight > 0.1, _blurred(image, sigma) / weight.clamp_min(1e-12), 0.0)
        grad_y, grad_x = torch.gradient(light)
        for _ in range(_STEPS):
            at = xy + theta[:2]
            inside = _sample(weight, at) > 0.5
            if int(inside.sum()) < _MIN_SHIFT_ROWS:
                return theta[:2]
            seen = _sample(light, at)
            gain = 1 + theta[2]
            res = torch.where(inside, value - gain * seen - theta[3], 0.0)
            jac = torch.stack([gain * _sample(grad_x, at), gain * _sample(grad_y, at), seen, torch.ones_like(seen)], 1)
            theta += _huber_step(jac * inside[:, None], res, inside)[0]
    return theta[:2]


def _bilinear_map(xy: torch.Tensor, at: torch.Tensor) -> torch.Tensor:
    """An :math:`(H, W, 2)` map read between its pixels at :math:`(N, 2)` camera coordinates ``at``: the
    mean of the four around, weighted bilinearly, over those mapped; NaN where they weigh under half."""
    height, width = xy.shape[:2]
    x0, y0 = at[:, 0].floor(), at[:, 1].floor()
    fx, fy = (at[:, 0] - x0)[:, None], (at[:, 1] - y0)[:, None]
    total = torch.zeros(len(at), 2, dtype=xy.dtype)
    weight = torch.zeros(len(at), 1, dtype=xy.dtype)
    for dx, dy, share in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        x, y = (x0 + dx).long(), (y0 + dy).long()
        inside = ((x >= 0) & (x < width) & (y >= 0) & (y < height))[:, None]
        value = xy[y.clamp(0, height - 1), x.clamp(0, width - 1)]
        ok = inside & torch.isfinite(value).all(-1, keepdim=True)
        total += torch.where(ok, value * share, 0.0)
        weight += torch.where(ok, share, 0.0)
    return torch.where(weight > 0.5, total / weight.clamp_min(1e-12), float("nan"))


def carry_shares(shares: CellShares, xy: torch.Tensor, moved: torch.Tensor, slope: torch.Tensor,
                 projector_size: tuple[int, int]) -> CellShares:
    """One projector's measured cell shares carried to maps moved from ``xy`` to ``moved`` (module docs).

    The shares say how a pixel's light splits across the edges of its cell, which a move of a
    fraction of a cell changes; the maps say where the light's centre is. Two models, the first
    read wherever it has data:

    **What the other pixels measured** (:func:`_table_shares`). Per axis and edge, a pixel's share
    is a function of where its map puts it in its cell (the phase, ``u - n``) and how wide its light
    is (the extent, ``|du/dx| + |du/dy|``), whatever the light's shape within the pixel: the
    camera's own aperture, or the virtual rig's few samples per pixel, whose shares step from 0 to
    a half as a sample crosses an edge. So the measured shares of every pixel of the projector and
    state, averaged in bins of phase and extent, say what a pixel's shares are at its moved phase.
    A pixel whose measured shares the table does not give at its phase is first placed, within a
    decoded map's error, where the table gives them best; its share after the move is the table's
    at the moved phase plus what the pixel measured beyond the table's value at its own (so that
    with no move the shares come back as measured). Against a recalibration of the moved world, on
    two unseen suite scenes whose camera pixels are about 0.4 cells wide seen through 2 x 2 samples
    (suite-3131-1 and suite-606-0, a projector moved 2 mm or turned 0.2 degrees), the
    shares carried this way are 0.035-0.062 rms from those measured, against 0.066-0.124 through the
    interval alone, and the rebuilt model scores 0.42-4.47 dB higher on every target
    (``docs/camera-in-the-loop.md``).

    **An even interval**, where a bin holds too few pixels (and in the tests' hand-worked cases).
    Per axis, the light is taken as spread evenly over an interval (a camera pixel's square seen through the map, a
    parallelogram, projects onto one projector axis as a trapezoid: the interval is its simplest
    stand-in), which the measured shares and the map's coordinate ``u`` in cell ``n`` fix:

    - light across both edges: the interval covers the cell and reaches past each edge by its share,
      ``w = 1 / (1 - f_lower - f_upper)``;
    - across one edge: it reaches past that edge by its share and is centred on ``u``;
    - across neither: it lies in the cell, centred on ``u``, as wide as the pixel's extent along the axis
      (``|du/dx| + |du/dy|``, ``slope``) or the cell allows.

    The interval moves with the map; the new cell is the decoded one moved by the cell edges the
    map's coordinate crosses, and the shares across its edges are the interval's parts past them.
    The checkerboard's share (the light on the other parity) moves by what the same intervals, taken
    as independent along the two axes, predict before and after; light from beyond cells ``n +- 1``
    (``outside``) is kept as measured.
    With no move the shares come back as measured (to the clamps below). Our construction: the paper
    calibrates once. Against a recalibration of the moved world (a projector moved 2 mm, half a cell),
    carried shares are 0.09 from the measured ones rms, those moved by whole cells 0.15
    (``tests/pipeline/test_shown.py``). Where a one-edge share is near a half and ``u`` near that edge
    the width is barely fixed; the interval then keeps the narrow width the centre gives: in throwaway
    variants measured as ``--moved-models`` measures (with the cell holding the moved coordinate as the
    new cell), the pixel's extent or the widest interval the share allows there scored
    ``box_cylinders``' 2 mm move 0.45 / 0.12 dB lower.

    Args:
        shares: the projector's :class:`~torchproj.calib.CellShares`, :math:`(H, W, ...)`.
        xy: :math:`(H, W, 2)` the calibrated map (cells; NaN where undecoded).
        moved: :math:`(H, W, 2)` the moved map.
        slope: :math:`(H, W, 2, 2)` the calibrated map's :func:`~torchproj.calib.maps.map_slope`.
        projector_size: ``(width, height)`` cells.
    """
    known = (shares.cell >= 0).all(-1) & torch.isfinite(xy).all(-1) & torch.isfinite(moved).all(-1)
    u, v, across = xy.double(), moved.double(), shares.across.double()
    extent = torch.nan_to_num(slope.double().abs().sum(-1), nan=1.0).clamp(0.05, 4.0)  # (H, W, 2) per axis
    # The decoded cell moved by the cell edges the map's coordinate crosses: with no move the shares are
    # re-read about the cell they were measured about (where the map's coordinate lies outside it, as on
    # a limb, too), and come back as measured.
    crossed = round_to_pixel(torch.nan_to_num(v, nan=0.0)) - round_to_pixel(torch.nan_to_num(u, nan=0.0))
    cell = shares.cell.long() + crossed
    for axis in (0, 1):
        cell[..., axis].clamp_(0, projector_size[axis] - 1)
    carried = torch.full_like(across, float("nan"))
    parity = []  # per axis, the share across either edge before and after
    for axis in (0, 1):
        n, x = shares.cell[..., axis].double(), u[..., axis]
        lower, upper = n - 0.5, n + 0.5
        f_low = torch.nan_to_num(across[..., axis, 0]).clamp(0, _CARRY_MAX_SHARE)
        f_up = torch.nan_to_num(across[..., axis, 1]).clamp(0, _CARRY_MAX_SHARE)
        low, up = f_low > _CARRY_MIN_SHARE, f_up > _CARRY_MIN_SHARE
        width = torch.where(
            low & up, 1 / (1 - f_low - f_up).clamp_min(_CARRY_MIN_INSIDE),
            torch.where(low, _one_edge_width(f_low, x - lower),
                        torch.where(up, _one_edge_width(f_up, upper - x),
                                    torch.minimum(extent[..., axis], 2 * torch.minimum(x - lower, upper - x).clamp_min(0)))))
        start = torch.where(low, lower - f_low * width, torch.where(up, upper + f_up * width - width, x - width / 2))
        start = start + (v[..., axis] - x)
        m = cell[..., axis].double()
        span = width.clamp_min(1e-9)
        below = torch.where(width > 1e-9, ((m - 0.5 - start) / span).clamp(0, 1), 0.0)
        above = torch.where(width > 1e-9, ((start + width - m - 0.5) / span).clamp(0, 1), 0.0)
        below, above = _table_shares(across[..., axis, :], x - n, v[..., axis] - m, extent[..., axis], known,
                                     (below, above))
        # No light from beyond the projector's border: NaN there, as measured.
        carried[..., axis, 0] = torch.where(cell[..., axis] >= 1, below, float("nan"))
        carried[..., axis, 1] = torch.where(cell[..., axis] < projector_size[axis] - 1, above, float("nan"))
        parity.append((f_low + f_up, below + above))
    carried = torch.where(known[..., None, None], carried, float("nan"))
    checker = shares.checker
    if checker is not None:
        (x0, x1), (y0, y1) = parity
        change = (x1 * (1 - y1) + (1 - x1) * y1) - (x0 * (1 - y0) + (1 - x0) * y0)
        checker = torch.where(known, (checker.double() + change).clamp(0, 1), float("nan")).to(shares.checker.dtype)
    cell = torch.where(known[..., None], cell, -1).to(shares.cell.dtype)
    return CellShares(cell, carried.to(shares.across.dtype), shares.outside, checker)


def _table_shares(measured: torch.Tensor, phase: torch.Tensor, moved_phase: torch.Tensor, extent: torch.Tensor,
                  known: torch.Tensor, interval: tuple[torch.Tensor, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """One axis of :func:`carry_shares`: the shares across the lower and upper edge of each pixel's new
    cell as the table of all pixels' measured shares gives them (its docstring), the ``interval``
    model's where the table has too few pixels.

    Args:
        measured: :math:`(H, W, 2)` the measured shares across the lower and upper edge (NaN: none).
        phase, moved_phase: :math:`(H, W)` the map's coordinate less the decoded cell's, before and after
            the move (less the new cell's).
        extent: :math:`(H, W)` the pixel's extent along the axis (cells).
        known: :math:`(H, W)` the pixels carried.
        interval: the interval model's shares, :math:`(H, W)` each.
    """
    flat = torch.nonzero(known.reshape(-1))[:, 0]
    f = torch.nan_to_num(measured.reshape(-1, 2)[flat].float(), nan=0.0)
    at, to = phase.reshape(-1)[flat].float(), moved_phase.reshape(-1)[flat].float()
    n_phase = round(2 / _TABLE_PHASE_BIN)
    n_extent = round(_TABLE_EXTENT_MAX / _TABLE_EXTENT_BIN)
    # Each extent's row of bins has a NaN bin at either end, so that a phase past the table reads NaN.
    row = (extent.reshape(-1)[flat] / _TABLE_EXTENT_BIN).floor().long().clamp(0, n_extent - 1) * (n_phase + 2)
    column = ((at + 1) / _TABLE_PHASE_BIN).floor().long()
    inside = (column >= 0) & (column < n_phase)
    slot = (row + column + 1)[inside]
    size = n_extent * (n_phase + 2)
    count = f.new_zeros(size).index_add_(0, slot, f.new_ones(len(slot)))
    table = f.new_zeros(size, 2).index_add_(0, slot, f[inside])
    table = torch.where((count >= _TABLE_MIN)[:, None], table / count.clamp_min(1)[:, None], float("nan"))

    def read(where: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """The table at phases ``where`` of the pixels' extent rows ``rows`` (:math:`(P,)` or
        :math:`(P, K)` phases, :math:`(P,)` rows), linear between bin centres; where one of the two
        bins is too sparse, the nearer one (NaN where that is)."""
        position = (where + 1) / _TABLE_PHASE_BIN + 0.5  # 1 at the first bin's centre
        left = position.floor().clamp(0, n_phase)
        share = (position - left).clamp(0, 1)[..., None]
        index = rows.view(-1, *([1] * (where.dim() - 1))) + left.long()
        a, b = table[index], table[index + 1]
        both = a + (b - a) * share
        return torch.where(torch.isfinite(both), both, torch.where(share < 0.5, a, b))

    # Where a pixel measured other shares than the table gives at its phase, it may lie elsewhere in
    # its cell than its map says (a decoded map errs by a few hundredths of a cell, and near an edge
    # the sampled light's shares step): its phase is corrected within that error, to where the table
    # gives its measured shares best.
    offset = torch.zeros_like(at)
    own = read(at, row)
    misfit = (own - f).abs().amax(-1)
    near = torch.nonzero(torch.nan_to_num(misfit, nan=0.0) > _PHASE_MISFIT)[:, 0]
    if len(near):
        steps = torch.linspace(-_PHASE_SPAN, _PHASE_SPAN, _PHASE_STEPS, device=f.device)
        miss = (read(at[near, None] + steps, row[near]) - f[near, None, :]).pow(2).sum(-1)
        cost = torch.nan_to_num(miss, nan=float("inf")) + _PHASE_PENALTY * steps.pow(2)
        offset[near] = steps[cost.argmin(1)]
        own[near] = read(at[near] + offset[near], row[near])
    # The share of each edge at the moved phase, plus what the pixel measured beyond the table's value.
    shares = (f + (read(to + offset, row) - own)).clamp(0, 1)
    out = []
    for side in (0, 1):
        value = interval[side].reshape(-1).clone()
        got = shares[:, side]
        value[flat] = torch.where(torch.isfinite(got), got.to(value.dtype), value[flat])
        out.append(value.view_as(interval[side]))
    return out[0], out[1]


def _one_edge_width(share: torch.Tensor, reach: torch.Tensor) -> torch.Tensor:
    """:func:`carry_shares`' interval across one edge of the cell by ``share``, centred on a coordinate
    ``reach`` cells inside that edge: its width (a coordinate at or past the edge counts as a hundredth
    of a cell inside, so the interval keeps a width), never past the cell's other edge."""
    centred = reach.clamp(_CARRY_MIN_REACH, 1) / (0.5 - share).clamp_min(_CARRY_MIN_REACH)
    return centred.clamp(max=1 / (1 - share))


def _capture_miss(candidate: list, old, p: torch.Tensor, measured: torch.Tensor) -> float:
    """How far a model's prediction of a capture of ``p`` (on ``old``'s columns) is from the capture."""
    from ..solve.refine import carry_patterns

    carried = carry_patterns(p, old, candidate[0])
    predicted = (torch.cat([o.A(carried[:, c:c + 1]) for c, o in enumerate(candidate)], 1)
                 if len(candidate) > 1 else candidate[0].A(carried))
    return float((measured - predicted).double().pow(2).sum())


class Reregister:
    """The camera loop's ``remodel`` on the virtual rig (:func:`~torchproj.solve.refine_patterns`).

    After each capture, while the light keeps moving (a median move of at least
    :data:`REGISTER_MIN_CELLS` from the calibrated model, :data:`REREGISTER_MIN_CELLS` from one the
    loop moved, by the projectors' fit or the camera's): :func:`register_maps` and
    :func:`register_camera`, then the model that predicts that capture best among five: the operator
    as it is, the calibrated operator with its rows moved by the projectors' fit
    (:meth:`~torchproj.transport.TransportOperator.with_rows_moved`: each row's measured footprint,
    shares and defocus kept, translated, at the price of a bilinear split of each entry), the
    transport rebuilt from the maps moved by the projectors' fit, its measured shares dropped (they
    belong to the old maps: sharp footprints from the maps' geometry) or carried through the move
    (:func:`carry_shares`; taken only where it predicts the capture more than :data:`_CARRY_MARGIN`
    better than the best of the others), and the transport rebuilt from the maps the camera's fit
    moved, its shares dropped (carried, they scored below it on both moved-camera cases of
    ``benchmarks/drift.py --moved-models``). Neither moved model wins everywhere: given the
    simulator's exact moves (``python benchmarks/drift.py --moved-models``), box_cylinders at quarter
    size with its upper projector turned 0.2 degrees scored 22.3 / 21.2 dB with rows moved and
    28.0 / 28.8 rebuilt, suite-1-7 23.5 / 28.1 / 18.7 / 22.8 moved and 21.1 / 23.6 / 17.7 / 23.1
    rebuilt; which predicted the capture better was the better one in both. Once a capture shows
    less move, or the operator as it is predicts best, the loop is left to its defect. ``fits``
    records each fit: its median move (cells), the share of the residual it explained, the camera
    shift per target (pixels) and the median move it makes (cells), and the model chosen.
    """

    def __init__(self, states: dict, targets: list[Target], *, footprint: str, colour_weights: str, device="cpu"):
        self.states, self.targets = states, targets
        self.footprint, self.colour_weights, self.device = footprint, colour_weights, device
        self.calibrated = None  # the operator(s) as calibrated, which every move is applied to
        self.moves = None
        self.fits: list[dict] = []
        self.done = False
        self.camera_won = False  # whether the model the loop runs on is the camera's

    def __call__(self, ops, p, measured):
        if self.done:
            return None
        if self.calibrated is None:
            self.calibrated = list(ops)
        from ..solve.refine import carry_patterns

        moves, median, explained = register_maps(self.states, self.targets, ops, p, measured, self.moves)
        # The camera's move is fitted against the calibrated model, whatever model the loop runs on now.
        camera, shifts = register_camera(self.states, self.targets, self.calibrated,
                                         carry_patterns(p, ops[0], self.calibrated[0]), measured)
        held = torch.zeros_like(camera) if self.moves is None else self.moves
        camera_median = _median_change(self.calibrated[0], camera - held)
        fit = {"median_move_cells": round(median, 4), "explained": round(explained, 4),
               "camera_shift_px": [list(s) for s in shifts], "camera_move_cells": round(camera_median, 4),
               "model": "as it was"}
        self.fits.append(fit)
        # The camera's fit stays in play after the first capture only where its model won: a projector's
        # move it explains badly, and the shift it finds would otherwise keep every later capture
        # building models.
        least = REGISTER_MIN_CELLS if self.moves is None else REREGISTER_MIN_CELLS
        camera_moving = camera_median >= least and (len(self.fits) == 1 or self.camera_won)
        if median < least and not camera_moving:
            self.done = True
            return None
        # One candidate at a time, the better kept: each is an operator of the full rig (the paper's at full
        # size holds 9-12 M nonzeros and their transpose), and three at once doubled a run's peak memory.
        # Each with the share of the best miss so far by which it must beat it: the carried shares rest on
        # a model of the light inside a pixel that the others do not need (the table of what the other
        # pixels measured, or the even interval), and are taken only where clearly better.
        makers = {"rows moved": (moves, lambda: [o.with_rows_moved(moves) for o in self.calibrated], 0.0),
                  "rebuilt": (moves, lambda: self._rebuilt(ops[0], moves), 0.0),
                  "rebuilt, shares carried": (moves, lambda: self._rebuilt(ops[0], moves, carry=True), _CARRY_MARGIN)}
        if camera_moving:
            makers["camera shifted, rebuilt"] = (camera, lambda: self._rebuilt(ops[0], camera), 0.0)
        misses = {"as it was": _capture_miss(list(ops), ops[0], p, measured)}
        best, best_ops, best_moves = "as it was", None, None
        for name, (candidate_moves, make, margin) in makers.items():
            candidate = make()
            if candidate is None:
                continue
            misses[name] = _capture_miss(candidate, ops[0], p, measured)
            if misses[name] < (1 - margin) * misses[best]:
                best, best_ops, best_moves = name, candidate, candidate_moves
            del candidate
        fit["model"] = best
        fit["capture_miss"] = {name: round(v, 4) for name, v in misses.items()}
        if best_ops is None:
            self.done = True
            return None
        self.moves, self.camera_won = best_moves, best == "camera shifted, rebuilt"
        return best_ops

    def _rebuilt(self, op, moves, carry: bool = False):
        """The transport built as calibrated from maps moved by ``moves``, its cell shares and edge pixels
        dropped or, with ``carry``, carried through the move (:func:`carry_shares`; an edge pixel's two
        places move with the pixel); a pixel of a state that is no row moves by the median of its
        state's rows."""
        moved = {}
        row_target = op.row_target.cpu()
        for state, cal in self.states.items():
            # Each row's state through its target's (a Python loop over 2 M rows took 2.3 s a state).
            mine = torch.tensor([t.state == state for t in self.targets], dtype=torch.bool)[row_target]
            if not bool(mine.any()):
                moved[state] = cal
                continue
            pixels = op.row_pixel.cpu()[mine]
            maps, carried, edges = [], [], []
            for j, xy in enumerate(cal.prj_xy):
                flat = xy.reshape(-1, 2).double() + moves[mine, j].median(0).values
                flat[pixels] = xy.reshape(-1, 2)[pixels].double() + moves[mine, j]
                w, h = cal.projector_sizes[j]
                flat[:, 0].clamp_(0, w - 1)
                flat[:, 1].clamp_(0, h - 1)
                maps.append(flat.to(xy.dtype).view(xy.shape))
                if carry and cal.shares is not None:
                    carried.append(carry_shares(cal.shares[j], xy, maps[-1], cal._slope(j), (w, h)))
                if carry and cal.edges is not None:
                    # A pixel on an outline sees two surfaces: both its places move with the pixel's move.
                    edge = cal.edges[j]
                    # (an edge pixel whose map is undecoded moves by nothing)
                    at = edge.pixel.to(flat.device)
                    move = torch.nan_to_num(flat[at] - xy.reshape(-1, 2)[at].double())
                    edges.append(dataclasses.replace(edge, xy=(edge.xy.double() + move[:, None]).to(edge.xy.dtype)))
            moved[state] = dataclasses.replace(cal, prj_xy=maps, shares=carried or None, edges=edges or None)
        new = build_operators(moved, self.targets, footprint=self.footprint, merge=False,
                              colour_weights=self.colour_weights if len(self.calibrated) > 1 else "grey",
                              device=self.device)
        same = len(new) == len(self.calibrated) and new[0].shape[0] == op.shape[0]
        return new if same and torch.equal(new[0].row_pixel, op.row_pixel) else None
