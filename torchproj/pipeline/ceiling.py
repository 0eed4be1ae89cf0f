"""The exact-light reference: patterns solved on the simulator's own light transport.

Calibration gives the solver a model of each camera pixel's light: one projector cell per pixel,
weighted by the pixel's white minus black (:mod:`torchproj.transport.build`). The virtual rig knows
the exact answer: each pixel's camera samples fall in several cells, each with its own share
(:class:`~torchproj.sim.StateGeometry`'s ``transport``). Solving on that exact light, with the same
targets, rows, bounds and evaluation, gives the best any calibration could reach: the ceiling that
``torchproj run --oracle transport`` and ``--ceiling`` report. It exists only on the virtual rig.

The exact entry of row r (camera pixel r) and cell c of projector j, in camera value per unit of
the solver's linear relative light l (0 = the cell's black, 1 = its white), follows the physics
contract (:mod:`torchproj.sim.rig`) with a linear camera (``gamma`` 1): the cell emits
``power_j (a_j l + black) vignette_j(c)`` above nothing, so one unit of l adds
``exposure * T_j[r, c] * power_j * a_j * vignette_j(c)`` (times camera channel k's share of
white, ``sum_p M_j[k, p]``, where the projector's colour mixes; l is then what channel k sees),
where ``T_j`` holds the radiance each unit of emitted light sends to the pixel (albedo, fall-off, angle, shadows and the camera samples
that fall in the cell). Calibration's weight ``w_j(r)`` is this row's sum over the cells.
"""

from __future__ import annotations

import dataclasses

import torch

from ..core.checks import check
from ..sim.rig import check_rig
from ..transport import Target, TransportOperator, csr_from_coo
from ..transport.build import check_targets
from ..transport.operator import check_operator
from .shown import CapturedRows, rig_measure

__all__ = ["check_linear_camera", "light_transport", "solve_on_light_transport"]


def check_linear_camera(scene) -> None:
    """Refuse a scene whose camera bends its values (``gamma`` != 1): no linear operator is exact there."""
    check(scene.camera.gamma == 1.0, f"the exact light transport is linear in the camera's values only with gamma 1; "
                                     f"scene {scene.name!r} has camera.gamma {scene.camera.gamma:g}")


def _gather_rows(matrix: torch.Tensor, pixels: torch.Tensor):
    """Entries of CSR ``matrix`` rows ``pixels``: (position in ``pixels``, column, value)."""
    crow, col, val = matrix.crow_indices(), matrix.col_indices(), matrix.values()
    start, counts = crow[pixels], crow[pixels + 1] - crow[pixels]
    row = torch.repeat_interleave(torch.arange(len(pixels), device=pixels.device), counts)
    first = torch.repeat_interleave(torch.cumsum(counts, 0) - counts, counts)
    index = torch.repeat_interleave(start, counts) + torch.arange(int(counts.sum()), device=pixels.device) - first
    return row, col[index], val[index]


def _unit_light(rig, j: int) -> torch.Tensor:
    """:math:`(H_j W_j,)` what one unit of projector j's linear light adds to each cell's emission
    (power * a * vignette: a white cell's light less a black one's), in camera values (times the
    exposure)."""
    proj = rig.scene.projectors[j]
    on, off = (rig.emitted(j, torch.full((1, 1, proj.height, proj.width), v, device=rig.device))[0, 0]
               for v in (1.0, 0.0))
    return rig.scene.camera.exposure * (on - off)


def light_transport(rig, targets: list[Target], rows: TransportOperator) -> list[TransportOperator]:
    """The simulator's own light transport on the camera pixels of an operator's rows (module docstring).

    Args:
        rig: the :class:`~torchproj.sim.VirtualRig` the targets' states belong to.
        targets: the targets the operator was built for (a row's state is its target's).
        rows: an operator with unmerged rows (``build_transport(..., merge=False)``): its rows' pixels,
            right-hand side, targets and scale are kept. A row that no projector reaches in the
            exact transport (none on the shipped scenes) is dropped.

    Returns:
        one operator, or one per colour channel where the surfaces' albedo differs per channel
        (each with that channel's right-hand side). All have the same columns: every cell that
        reaches a row, in the layout of :class:`~torchproj.transport.TransportOperator`.
    """
    check_rig(rig)
    check_targets(targets)
    check_operator(rows, "rows")
    scene = rig.scene
    check(rows.row_pixel is not None, "the exact light transport needs an operator whose rows are camera pixels: "
                                      "build it with merge=False")
    check_linear_camera(scene)
    check(len(targets) == rows.target_count, f"give the {rows.target_count} targets the operator was built for, "
                                             f"got {len(targets)}")
    device = rows.rhs.device
    sizes = [(p.width, p.height) for p in scene.projectors]
    offsets = torch.tensor([0] + [w * h for w, h in sizes], device=device).cumsum(0)
    # A state of grey surfaces holds one matrix per projector, one with a coloured surface three;
    # where any target's state has three, every state's rows are given per channel.
    n_albedo = max(len(rig.geometry(t.state).transport[0]) for t in targets)
    # Colour mixing whose rows do not sum alike gives each channel its own share of white.
    gains = [rig.channel_gain(j).to(device) for j in range(len(scene.projectors))]
    if rows.rhs.shape[1] == 3 and any(bool((g != g[0]).any()) for g in gains):
        n_albedo = 3
    check(n_albedo == 1 or rows.rhs.shape[1] == n_albedo,
          f"the surfaces' albedo differs per colour channel, so the exact light needs {n_albedo}-channel targets; "
          f"got {rows.rhs.shape[1]}")
    entries = [[] for _ in range(n_albedo)]  # per albedo channel: (row, global column, value) pieces
    units = [_unit_light(rig, j) for j in range(len(scene.projectors))]
    for k, target in enumerate(targets):
        which = torch.nonzero(rows.row_target == k)[:, 0]
        pixels = rows.row_pixel[which].to(rig.device)
        geo = rig.geometry(target.state)
        for j, unit in enumerate(units):
            for channel in range(n_albedo):
                r, c, v = _gather_rows(geo.transport[j][min(channel, len(geo.transport[j]) - 1)], pixels)
                gain = gains[j][min(channel, len(gains[j]) - 1)]
                entries[channel].append((which[r.to(device)], (c + offsets[j]).to(device),
                                         (v * unit[c]).to(device) * gain))
    parts = [[torch.cat(piece) for piece in zip(*channel)] for channel in entries]
    used = torch.unique(parts[0][1])
    lit = torch.zeros(rows.shape[0], dtype=torch.bool, device=device)
    lit[parts[0][0]] = True
    keep = torch.nonzero(lit)[:, 0]
    renumber = torch.cumsum(lit.long(), 0) - 1
    projector = torch.searchsorted(offsets, used, right=True) - 1
    ops = []
    for channel, (r, c, v) in enumerate(parts):
        matrix = csr_from_coo(renumber[r], torch.searchsorted(used, c), v.to(rows.val.dtype),
                              (len(keep), len(used)))
        rhs = rows.rhs[keep] if len(parts) == 1 else rows.rhs[keep][:, channel:channel + 1]
        ops.append(TransportOperator(matrix, rhs, projector, used - offsets[projector], sizes,
                                     row_target=rows.row_target[keep], scale=rows.scale,
                                     row_pixel=rows.row_pixel[keep], camera_size=rows.camera_size,
                                     target_count=rows.target_count))
    return ops


class BounceTerm:
    """The light bounced once between surfaces (:mod:`torchproj.sim.bounce`) on an operator's rows, as
    a linear map of its columns' values in one colour channel: the exact light is ``A q + B q``.

    ``B = D T S``: S sums each column's unit light into its source block (times the camera channel's
    share of white), T carries the sources' light to the receivers (albedos included), D interpolates
    receivers to the rows' pixels and shows them through the pixels' albedo and the exposure. B is
    dense (every cell that lights a source reaches every row that source sees), but of low rank: its
    products cost a few hundred thousand operations, not a matrix.
    """

    def __init__(self, rig, targets: list[Target], rows: TransportOperator, channel: int):
        scene = rig.scene
        device, dtype = rows.rhs.device, rows.rhs.dtype
        self.rows = rows.shape[0]
        bounces = {t.state: rig.geometry(t.state).bounce for t in targets}
        first = next(b for b in bounces.values() if b is not None)
        projector = rows.column_projector.long()
        cell = rows.column_cell.long()
        source, self.sources = first.source_of([(p.width, p.height) for p in scene.projectors], projector, cell)
        unit = torch.empty(len(cell), dtype=dtype, device=device)
        for j in range(len(scene.projectors)):
            mine = projector == j
            gain = rig.channel_gain(j)[min(channel, scene.camera.channels - 1)]
            unit[mine] = (_unit_light(rig, j) * gain).to(device, dtype)[cell[mine]]
        self.source, self.unit = source, unit
        self.states = []  # per state: (rows, interpolation CSR (rows, R) times albedo, transfer (R, S))
        for state, which in CapturedRows(rows, targets).rows_of.items():
            bounce = bounces[state]
            if bounce is None:
                continue
            albedo = bounce.receiver_albedo[min(channel, bounce.receiver_albedo.shape[0] - 1)].reshape(-1)
            pixels = rows.row_pixel[which].to(rig.device)
            r, c, v = _gather_rows(bounce.interpolation, pixels)
            v = v * albedo[pixels[r]]
            spread = csr_from_coo(r.to(device), c.long().to(device), v.to(device, dtype),
                                  (len(which), bounce.transfer.shape[0]))
            transfer = bounce.transfer * bounce.source_albedo[min(channel, bounce.source_albedo.shape[0] - 1)]
            self.states.append((which, spread, transfer.to(device, dtype)))

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        """:math:`(N_{cols}, 1)` values -> :math:`(N_{rows}, 1)` bounced camera values."""
        flux = torch.zeros(self.sources, q.shape[1], dtype=q.dtype, device=q.device).index_add_(
            0, self.source, q * self.unit[:, None])
        out = torch.zeros(self.rows, q.shape[1], dtype=q.dtype, device=q.device)
        for which, spread, transfer in self.states:
            out[which] = spread @ (transfer @ flux)
        return out

    def adjoint(self, r: torch.Tensor) -> torch.Tensor:
        flux = torch.zeros(self.sources, r.shape[1], dtype=r.dtype, device=r.device)
        for which, spread, transfer in self.states:
            flux += transfer.T @ (spread.transpose(0, 1) @ r[which])
        return flux[self.source] * self.unit[:, None]


def bounce_terms(rig, targets: list[Target], ops: list[TransportOperator]) -> list[BounceTerm] | None:
    """Per colour channel of ``ops`` (:func:`light_transport`'s), its :class:`BounceTerm`; None where no
    target's state bounces light."""
    if all(rig.geometry(t.state).bounce is None for t in targets):
        return None
    channels = len(ops) if len(ops) > 1 else ops[0].rhs.shape[1]
    return [BounceTerm(rig, targets, ops[0], c) for c in range(channels)]


def solve_on_light_transport(ops: list[TransportOperator], bounds: tuple[float, float], responses, *,
                             solver: str = "fista", max_iter: int = 2000, progress=None, objective="l2",
                             outside: str = "clip", world=None, targets: list[Target] | None = None):
    """Solve on :func:`light_transport`'s operators as :func:`~torchproj.solve.make_patterns` does.

    With one operator per colour channel each channel is solved alone (least squares with a box
    separates over channels), and their solutions are joined; an image objective couples the
    channels, so it needs one operator (surfaces whose albedo is the same in every channel).

    Light that bounces between surfaces (``interreflection``) is no sparse matrix: given the
    ``world`` (a :class:`~torchproj.pipeline.VirtualCalibration`) and the ``targets``, the direct
    transport's answer is corrected against the world's noise-free captures
    (:func:`~torchproj.solve.refine_patterns`) and then solved on the exact light, direct plus
    :class:`BounceTerm`, with the channels coupled through any colour mixing
    (:func:`~torchproj.solve.mixing.solve_through_mixing`); an image objective keeps the direct
    transport's answer.

    Returns:
        ``(result, light, patterns)`` as :func:`~torchproj.solve.make_patterns`; ``result`` joins
        the channels' results (objective summed, iterations the most any channel took).
    """
    from ..solve import make_patterns, refine_patterns
    from ..solve.compensate import projectable_patterns
    from ..solve.mixing import solve_through_mixing

    check(solver != "eo", "the exact light transport has no epipolar chains for eo to walk: choose another solver")
    # The exact light is the world itself: nothing in it is uncertain for a smoothness penalty to guard.
    result, light, patterns = make_patterns(ops, solver, bounds, responses, max_iter=max_iter, progress=progress,
                                            objective=objective, outside=outside, smoothness=0)
    bounce = None if world is None or objective not in (None, "l2") else bounce_terms(world.rig, targets, ops)
    if bounce is not None:
        check(0 <= bounds[0] and bounds[1] <= 1, "the exact light with interreflection is solved within [0, 1]: "
                                                 f"give bounds within 0,255, got {bounds}")
        # The bounce's few large singular values (a whole image's light lands everywhere) set FISTA's
        # step, which then crawls on the direct light's detail: the direct transport's answer is first
        # corrected against the exact (noise-free) captures, whose fixed point is near the optimum,
        # then FISTA on the exact light takes it the rest of the way.
        corrected = refine_patterns(ops, result.patterns, rig_measure(world, ops, targets, noise=False), bounds,
                                    responses, iterations=BOUNCE_UPDATES, outside=outside,
                                    solver_iterations=BOUNCE_SOLVER_ITERATIONS)
        result = dataclasses.replace(result, patterns=corrected.patterns)
        result = solve_through_mixing(ops, result, [r.mixing for r in responses], bounds, extra=bounce,
                                      max_iter=BOUNCE_ITERATIONS)
        result.info["bounce"] = {"corrections": BOUNCE_UPDATES, **result.info.pop("mixing")}
        light, patterns = projectable_patterns(ops[0], result.patterns, bounds, responses, outside)
    return result, light, patterns


# With interreflection: corrections of the direct answer against the exact captures (FISTA iterations
# each), then FISTA iterations on the exact light, direct plus bounce.
BOUNCE_UPDATES, BOUNCE_SOLVER_ITERATIONS, BOUNCE_ITERATIONS = 8, 100, 300
