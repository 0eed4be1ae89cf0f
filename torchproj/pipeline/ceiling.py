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
``exposure * T_j[r, c] * power_j * a_j * vignette_j(c)``, where ``T_j`` holds the radiance each
unit of emitted light sends to the pixel (albedo, fall-off, angle, shadows and the camera samples
that fall in the cell). Calibration's weight ``w_j(r)`` is this row's sum over the cells.
"""

from __future__ import annotations

import torch

from ..core.checks import check
from ..transport import Target, TransportOperator, csr_from_coo

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
    check(n_albedo == 1 or rows.rhs.shape[1] == n_albedo,
          f"the surfaces' albedo differs per colour channel, so the exact light needs {n_albedo}-channel targets; "
          f"got {rows.rhs.shape[1]}")
    entries = [[] for _ in range(n_albedo)]  # per albedo channel: (row, global column, value) pieces
    for k, target in enumerate(targets):
        which = torch.nonzero(rows.row_target == k)[:, 0]
        pixels = rows.row_pixel[which].to(rig.device)
        geo = rig.geometry(target.state)
        for j, proj in enumerate(scene.projectors):
            # What one unit of linear light adds to each cell's emission (power * a * vignette: a white
            # cell's light less a black one's), in camera values (times the exposure).
            on, off = (rig.emitted(j, torch.full((1, 1, proj.height, proj.width), v, device=rig.device))[0, 0]
                       for v in (1.0, 0.0))
            unit = scene.camera.exposure * (on - off)
            for channel in range(n_albedo):
                r, c, v = _gather_rows(geo.transport[j][min(channel, len(geo.transport[j]) - 1)], pixels)
                entries[channel].append((which[r.to(device)], (c + offsets[j]).to(device), (v * unit[c]).to(device)))
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


def solve_on_light_transport(ops: list[TransportOperator], bounds: tuple[float, float], responses, *,
                             solver: str = "fista", max_iter: int = 2000, progress=None, objective="l2",
                             outside: str = "clip"):
    """Solve on :func:`light_transport`'s operators as :func:`~torchproj.solve.make_patterns` does.

    With one operator per colour channel each channel is solved alone (least squares with a box
    separates over channels), and their solutions are joined; an image objective couples the
    channels, so it needs one operator (surfaces whose albedo is the same in every channel).

    Returns:
        ``(result, light, patterns)`` as :func:`~torchproj.solve.make_patterns`; ``result`` joins
        the channels' results (objective summed, iterations the most any channel took).
    """
    from ..solve import make_patterns

    check(solver != "eo", "the exact light transport has no epipolar chains for eo to walk: choose another solver")
    return make_patterns(ops, solver, bounds, responses, max_iter=max_iter, progress=progress, objective=objective,
                         outside=outside)
