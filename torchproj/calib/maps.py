"""Correspondence maps: the inverse map (projector -> camera), hole filling and the local slope.

Conventions: :mod:`torchproj.core.conventions`. The forward map ``prj_xy`` is :math:`(H, W, 2)`
projector coordinates per camera pixel; the inverse map ``cam_xy`` is :math:`(H_p, W_p, 2)` camera
coordinates per projector cell; NaN marks "no correspondence" in both.
"""

from __future__ import annotations

import operator

import numpy as np
import torch

from ..core.checks import check, check_count, check_shape
from ..core.conventions import pixel_grid, round_to_pixel

__all__ = ["EDGE_EXCESS", "EDGE_JUMP", "EDGE_STEP", "inverse_map", "fill_holes", "map_slope", "depth_edges", "pixel_square"]


def _check_projector_size(width, height) -> None:
    """A projector's ``width`` and ``height``: whole numbers of cells, at least one each."""
    for name, value in (("width", width), ("height", height)):
        try:
            whole = operator.index(value)
        except TypeError:
            whole = None
        check(whole is not None and whole >= 1 and not isinstance(value, bool),
              f"projector {name} must be a whole number of cells, at least 1, got {value!r}")


def check_projector_size(size, name: str = "projector_size") -> tuple[int, int]:
    """A projector's ``(width, height)`` in whole cells."""
    check(isinstance(size, (tuple, list)) and len(size) == 2, f"{name} must be (width, height), got {size!r}")
    _check_projector_size(*size)
    return operator.index(size[0]), operator.index(size[1])


def inverse_map(prj_xy: torch.Tensor, projector_size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """For each projector cell, the mean camera position of the camera pixels it lights.

    Args:
        prj_xy: :math:`(H, W, 2)` projector coordinates per camera pixel (NaN where invalid).
        projector_size: ``(width, height)``.

    Returns:
        ``cam_xy`` :math:`(H_p, W_p, 2)` camera coordinates (NaN where no camera pixel decoded to the
        cell) and ``count`` :math:`(H_p, W_p)` how many camera pixels did.
    """
    check_shape(prj_xy, "prj_xy", ["H", "W", 2])
    width, height = check_projector_size(projector_size)
    h, w = prj_xy.shape[:2]
    ok = torch.isfinite(prj_xy).all(-1)
    cell = round_to_pixel(prj_xy[ok])
    inside = (cell[:, 0] >= 0) & (cell[:, 0] < width) & (cell[:, 1] >= 0) & (cell[:, 1] < height)
    flat = cell[inside, 1] * width + cell[inside, 0]
    cam = pixel_grid(h, w, device=prj_xy.device, dtype=torch.float64)[ok][inside]
    sums = torch.zeros(height * width, 2, dtype=torch.float64, device=prj_xy.device).index_add_(0, flat, cam)
    count = torch.zeros(height * width, dtype=torch.int64, device=prj_xy.device).index_add_(
        0, flat, torch.ones_like(flat))
    cam_xy = (sums / count[:, None].clamp_min(1)).to(torch.float32)
    cam_xy[count == 0] = float("nan")
    return cam_xy.reshape(height, width, 2), count.reshape(height, width)


def fill_holes(values: torch.Tensor, max_area: int = 16) -> torch.Tensor:
    """Fill small holes in a map by harmonic interpolation from the surrounding valid entries.

    The paper's hole filling: decoding drops isolated correspondences where the camera samples the
    surface more coarsely than the projector (or a bit flips), leaving holes of a few pixels inside
    valid regions. A hole is a connected set (8-connectivity) of NaN entries that does not touch the
    image border and has at most ``max_area`` entries; larger gaps (shadows, object edges, the
    background) are genuine and stay NaN.

    Args:
        values: :math:`(H, W, D)` map with NaN where missing.
        max_area: largest hole, in entries, that is filled.

    Returns:
        :math:`(H, W, D)` map with the small holes filled.
    """
    check_shape(values, "values", ["H", "W", "D"])
    check_count(max_area, "max_area (the largest hole filled, entries)", 0)
    from scipy import ndimage  # imported here: a run from the cache fills no holes and need not import it

    missing = ~torch.isfinite(values).all(-1)
    labels, n = ndimage.label(missing.cpu().numpy(), structure=np.ones((3, 3)))
    if n == 0:
        return values.clone()
    sizes = np.bincount(labels.ravel())
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    fillable = sizes <= max_area
    fillable[0] = False
    fillable[border] = False
    holes = torch.from_numpy(np.flatnonzero(fillable[labels])).to(values.device)
    out = values.clone().reshape(-1, values.shape[-1])
    if holes.numel() == 0:
        return out.reshape(values.shape)
    # Harmonic interpolation of the rim: Jacobi sweeps of the 4-neighbour Laplacian over the hole
    # pixels only. Smooth, and exact wherever the map is locally affine, as on a plane. A hole's
    # 4-neighbours are hole pixels or valid ones (it touches no border and no other gap).
    w = values.shape[1]
    neighbours = torch.stack([holes - 1, holes + 1, holes - w, holes + w], 1)  # (M, 4)
    around = out[neighbours]  # (M, 4, D); NaN at neighbours inside the hole
    known = torch.isfinite(around).all(-1, keepdim=True)
    out[holes] = torch.nan_to_num(around).sum(1) / known.sum(1).clamp_min(1)  # start from the known rim
    for _ in range(50 + 10 * max_area):
        out[holes] = out[neighbours].mean(1)
    return out.reshape(values.shape)


# Camera pixels either side over which the map's slope is taken: a wider difference averages the
# refined coordinates' own error (about a tenth of a cell) over more pixels.
_SLOPE_REACH = 2
# A step between neighbouring pixels over this many cells (on either projector axis) is a depth edge,
# not a surface: the two pixels see different surfaces, and no slope is taken across it.
EDGE_STEP = 4.0
# A smaller step is a depth edge too where it is over EDGE_JUMP cells and over the smaller of the
# steps either side of it along the same line by EDGE_EXCESS cells: two surfaces a few centimetres
# apart in depth (planes overlapping in the camera's view) part by two or three cells, in one step
# or over the two beside a pixel that sees both, while a steep surface's steps grow smoothly. Our
# choice, measured on the suite's unseen seed 97 (docs/accuracy.md): with 4 cells alone such a
# pixel's footprint was carried across the jump on one surface's slope; with 2.5 cells alone a
# steep face through 1.7-cell pixels (suite-97-8's box) broke into edges and lost 6 dB, and with an
# excess of 1 cell the cylinders' limbs on box_cylinders, where the steps grow fast, lost 0.36 dB.
# A pixel that decodes between the two surfaces splits the jump into two steps each under EDGE_JUMP:
# depth_edges takes the two together (_bridges).
EDGE_JUMP, EDGE_EXCESS = 2.5, 1.5


def _steps(prj_xy: torch.Tensor, dim: int, k: int, known: dict) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The step ``u[p + k + 1] - u[p + k]`` along ``dim`` at every pixel ``p``, whether both ends are
    mapped (inside the image) and the step's larger coordinate. Each is the step to the next pixel
    rolled by ``k``: that step, its finiteness and size are taken once per map and axis and kept in
    ``known`` (one subtraction and one roll per ``k`` instead of two rolls and a subtraction)."""
    if "next" not in known:
        step = torch.roll(prj_xy, -1, dim) - prj_xy  # wraps round at the end: masked below
        # Per axis, then combined: reductions over a last dimension of two run slower than one step each.
        x, y = step.unbind(-1)
        known["next"] = step, torch.isfinite(x) & torch.isfinite(y), torch.maximum(x.abs(), y.abs())
    step, finite, size = (torch.roll(t, -k, dim) if k else t for t in known["next"])
    inner = torch.zeros(prj_xy.shape[:2], dtype=torch.bool, device=prj_xy.device)
    lo, hi = max(0, -k), prj_xy.shape[dim] - max(0, k + 1)  # roll wraps round
    inner.narrow(dim, lo, max(hi - lo, 0)).fill_(True)
    return step, inner & finite, size


def _edge_steps(prj_xy: torch.Tensor, dim: int, k: int, known: dict | None = None):
    """:func:`_steps`, and whether each step is a depth edge (:data:`EDGE_STEP`, or :data:`EDGE_JUMP`
    and :data:`EDGE_EXCESS` over the smaller of the known steps before and after it). ``known``
    keeps each ``k``'s steps along ``dim`` for the next call."""
    known = {} if known is None else known
    for i in (k - 1, k, k + 1):
        if i not in known:
            known[i] = _steps(prj_xy, dim, i, known)
    step, ok, size = known[k]
    (_, before, size_before), (_, after, size_after) = known[k - 1], known[k + 1]
    around = torch.minimum(torch.where(before, size_before, float("inf")), torch.where(after, size_after, float("inf")))
    around.masked_fill_(torch.isinf(around), 0.0)  # no step known either side: the jump alone
    edge = (size > EDGE_STEP) | ((size > EDGE_JUMP) & (size - around > EDGE_EXCESS))
    return step, ok, ok & edge


def map_slope(prj_xy: torch.Tensor, like: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """:math:`(H, W, 2, 2)` the map's local slope, projector cells per camera pixel:
    ``[..., i, 0] = d u_i / d x``, ``[..., i, 1] = d u_i / d y``.

    Per axis, the mean of the steps between neighbouring mapped pixels within ``_SLOPE_REACH``
    pixels either side, taken outwards from the pixel and stopped at a depth edge (a step over
    :data:`EDGE_STEP` cells, or a jump over the steps beside it, :func:`depth_edges`): on a
    surface, the central difference over ``2 _SLOPE_REACH`` pixels;
    beside an object's outline, the steps on the pixel's own side only. NaN where no step is known.

    ``like``: another map of the same camera and its slope, ``(prj_xy, map_slope(prj_xy))``, where the
    caller has them (calibration's map with and without its dim pixels): the slope is then taken from
    it wherever the two maps agree within the steps a pixel's slope reads, and computed only near the
    pixels where they differ. The same slope to the bit, as each pixel's is computed from the same
    values in the same order.
    """
    check_shape(prj_xy, "prj_xy", ["H", "W", 2])
    check_shape(prj_xy, "prj_xy", ["H", "W", 2])
    if like is not None:
        check(isinstance(like, (tuple, list)) and len(like) == 2, "like must be (another map, its map_slope), got "
                                                                 f"{type(like).__name__}")
        return _slope_like(prj_xy, *like)
    slope = torch.full((*prj_xy.shape[:2], 2, 2), float("nan"), dtype=prj_xy.dtype, device=prj_xy.device)
    for axis, dim in ((0, 1), (1, 0)):  # x runs along dim 1 (columns), y along dim 0 (rows)
        total = torch.zeros_like(prj_xy)
        count = torch.zeros(prj_xy.shape[:2], dtype=prj_xy.dtype, device=prj_xy.device)
        known = {}
        for side in (1, -1):  # ahead: steps 0, 1, ...; behind: steps -1, -2, ...
            open_ = torch.ones(prj_xy.shape[:2], dtype=torch.bool, device=prj_xy.device)
            for i in range(_SLOPE_REACH):
                step, ok, edge = _edge_steps(prj_xy, dim, i if side == 1 else -1 - i, known)
                open_ &= ok & ~edge
                total += step.masked_fill(~open_[..., None], 0.0)
                count += open_
        slope[..., axis] = torch.where(count[..., None] > 0, total / count.clamp_min(1)[..., None], float("nan"))
    return slope


def fill_slope(prj_xy: torch.Tensor, slope: torch.Tensor, reach: int = 8) -> torch.Tensor:
    """``slope`` :math:`(H, W, 2, 2)` of the map ``prj_xy`` with each mapped pixel's unknown camera
    axis taken from its 4-neighbours on the same surface, up to ``reach`` pixels away.

    :func:`map_slope` reads a pixel's slope along an axis from its mapped neighbours along that axis.
    A strip of a surface one pixel wide across that axis (the surface behind an object's outline
    seen between the outline and a shadow) has none there: its slope along the strip is known, the
    one across it not. On a surface the slope varies slowly, so the neighbours along the strip lend
    theirs, from where the surface is seen wider, one pixel further each pass (their mean). Two
    neighbours are on the same surface where their coordinates are within :data:`EDGE_JUMP` cells.
    A pixel no neighbour lends to within ``reach`` (a strip seen one pixel wide all along) takes the
    slope along it, turned and scaled as the map's median pixel turns its own (:func:`_complete`).
    Our choice (the paper has no slope): measured in docs/accuracy.md on suite scenes' outlines.
    """
    check_shape(slope, "slope", [*prj_xy.shape[:2], 2, 2])
    height, width = prj_xy.shape[:2]
    # Only the pixels that want an axis are visited: a handful along outlines, none on most maps.
    # (A sum of the four entries is NaN where any is: on a 1600 x 1200 map a fifth of the time of
    # reducing the (H, W, 2, 2) mask.)
    some = torch.isnan(slope[..., 0, 0] + slope[..., 1, 0] + slope[..., 0, 1] + slope[..., 1, 1])
    some &= ~torch.isnan(prj_xy[..., 0] + prj_xy[..., 1])
    ys, xs = torch.nonzero(some, as_tuple=True)
    if not ys.numel():
        return slope
    wanted = torch.isnan(slope[ys, xs]).any(-2)  # (M, 2): per camera axis
    pick, axis = torch.nonzero(wanted, as_tuple=True)
    ys, xs = ys[pick], xs[pick]
    out = slope.clone()
    flat_xy, flat = prj_xy.reshape(-1, 2), out.reshape(-1, 2, 2)
    moves = torch.tensor([[0, 1], [0, -1], [1, 0], [-1, 0]], device=prj_xy.device)
    ny, nx = ys[:, None] + moves[:, 0], xs[:, None] + moves[:, 1]  # (M, 4) the 4-neighbours
    inside = (ny >= 0) & (ny < height) & (nx >= 0) & (nx < width)
    here, there = ys * width + xs, (ny.clamp(0, height - 1) * width + nx.clamp(0, width - 1))
    same = inside & ((flat_xy[there] - flat_xy[here][:, None]).abs().amax(-1) <= EDGE_JUMP)  # NaN: False
    column = axis[:, None].expand_as(there)
    for _ in range(reach):
        lent = flat[there, :, column]  # (M, 4, 2): each neighbour's slope along the wanted axis
        lend = same & ~torch.isnan(lent).any(-1)
        fill = lend.any(-1) & torch.isnan(flat[here, :, axis]).any(-1)
        if not bool(fill.any()):
            break
        mean = torch.where(lend[..., None], lent, 0.0).sum(1) / lend.sum(1, keepdim=True).clamp_min(1)
        flat[here[fill], :, axis[fill]] = mean[fill].to(flat.dtype)
    left = torch.isnan(flat[here, :, axis]).any(-1) & ~torch.isnan(flat[here, :, 1 - axis]).any(-1)
    if bool(left.any()):
        _complete(flat, here[left], axis[left])
    return out


def _complete(flat: torch.Tensor, here: torch.Tensor, axis: torch.Tensor) -> None:
    """Each pixel ``here`` of ``flat`` :math:`(H W, 2, 2)` given the slope along camera ``axis`` from
    the one along the other, in place: what no neighbour lends (a strip seen one pixel high all along
    it, suite-56-5's far plane between its outline and the sky).

    Locally the map is near a similarity (the projector sees the camera's two axes turned by about a
    right angle and scaled alike), so the unknown axis is the known one turned and scaled as the
    map's median over its pixels with both: as complex numbers, ``d/dy = z d/dx`` with ``z`` the
    median of that ratio. Our choice: a surface's own tilt is not known from one row of it.
    """
    both = ~torch.isnan(flat.reshape(-1, 4)).any(-1)
    full = flat[both].double()
    across, along = torch.complex(full[:, 0, 0], full[:, 1, 0]), torch.complex(full[:, 0, 1], full[:, 1, 1])
    keep = across.abs() > 0
    if not bool(keep.any()):
        return
    ratio = along[keep] / across[keep]
    z = torch.complex(ratio.real.median(), ratio.imag.median())
    if not bool(z.abs() > 0):
        return
    known = flat[here, :, 1 - axis].double()
    known = torch.complex(known[:, 0], known[:, 1])
    given = torch.where(axis == 1, known * z, known / z)
    flat[here, :, axis] = torch.stack([given.real, given.imag], -1).to(flat.dtype)


# Camera pixels a side of the tiles in which a slope is computed again near a changed pixel.
_SLOPE_TILE = 64


def _slope_like(prj_xy: torch.Tensor, other: torch.Tensor, slope: torch.Tensor) -> torch.Tensor:
    """:func:`map_slope` of ``prj_xy`` from ``other``'s ``slope``: computed again near the pixels where
    the maps differ (NaN matching NaN)."""
    check_shape(other, "like's map", list(prj_xy.shape))
    check_shape(slope, "like's slope", [*prj_xy.shape[:2], 2, 2])
    same = (prj_xy == other) | (torch.isnan(prj_xy) & torch.isnan(other))
    # A pixel's slope reads the steps up to _SLOPE_REACH pixels away along its row and column, and
    # the edge test the steps either side of those: the map _SLOPE_REACH + 1 pixels away.
    return _recompute_near(~(same[..., 0] & same[..., 1]), _SLOPE_REACH + 1, _SLOPE_TILE, slope.clone(),
                           lambda crop: map_slope(prj_xy[crop]))


def _recompute_near(changed: torch.Tensor, reach: int, tile: int, out: torch.Tensor, compute) -> torch.Tensor:
    """``out`` :math:`(H, W, ...)`, each ``tile x tile`` tile within ``reach`` pixels of a ``changed``
    :math:`(H, W)` pixel replaced by ``compute(crop)``: a per-pixel map computed on the crop (a pair of
    slices), the tile with a border of ``reach``. For a map whose every pixel reads its input no
    farther than ``reach`` away, each tile gets what computing it on the whole input gives."""
    height, width = changed.shape
    for ty, tx in torch.nonzero(_tiles_within(changed, reach, tile)).tolist():
        y0, x0 = ty * tile, tx * tile
        y1, x1 = min(y0 + tile, height), min(x0 + tile, width)
        ya, xa = max(y0 - reach, 0), max(x0 - reach, 0)
        part = compute((slice(ya, min(y1 + reach, height)), slice(xa, min(x1 + reach, width))))
        out[y0:y1, x0:x1] = part[y0 - ya:y1 - ya, x0 - xa:x1 - xa]
    return out


def _tiles_within(mask: torch.Tensor, reach: int, tile: int) -> torch.Tensor:
    """:math:`(\\lceil H / t \\rceil, \\lceil W / t \\rceil)` bool: the ``tile x tile`` tiles of ``mask``
    :math:`(H, W)` that hold a pixel within ``reach`` pixels (a square) of a set one. From the set
    pixels' coordinates: each reaches the tiles of its square's corners, at most two a side where the
    reach is under a tile (a dilation of the whole mask by a 25 x 25 square cost 0.15 s a map)."""
    check(0 <= reach < tile, f"reach must be under the tile, got {reach} and {tile}")
    height, width = mask.shape
    ys, xs = torch.nonzero(mask, as_tuple=True)
    rows = torch.stack([(ys - reach).clamp_min(0), (ys + reach).clamp_max(height - 1)]) // tile
    cols = torch.stack([(xs - reach).clamp_min(0), (xs + reach).clamp_max(width - 1)]) // tile
    tiles = torch.zeros(-(-height // tile), -(-width // tile), dtype=torch.bool, device=mask.device)
    tiles[rows[:, None].expand(2, 2, -1), cols[None].expand(2, 2, -1)] = True
    return tiles


def depth_edges(prj_xy: torch.Tensor) -> torch.Tensor:
    """:math:`(H, W)` bool: mapped pixels beside a depth edge, a step to a mapped 4-neighbour over
    :data:`EDGE_STEP` cells, or over :data:`EDGE_JUMP` and by :data:`EDGE_EXCESS` over the steps
    either side of it (the pixel, or the one beyond the step, may see both surfaces at once)."""
    check_shape(prj_xy, "prj_xy", ["H", "W", 2])
    edge = torch.zeros(prj_xy.shape[:2], dtype=torch.bool, device=prj_xy.device)
    for dim in (0, 1):
        known = {}
        for k in (0, -1):
            edge |= _edge_steps(prj_xy, dim, k, known)[2]
        edge |= _bridges(dim, known)
    return edge


def _bridges(dim: int, known: dict) -> torch.Tensor:
    """Pixels that bridge a depth edge along ``dim``, and their two neighbours on that line, from
    the steps ``known`` holds (:func:`_edge_steps` for ``k`` 0 and -1 took steps -2 to 1).

    Such a pixel sees both surfaces, its code mixes theirs, and it decodes between them, so the jump
    comes in two steps each under EDGE_JUMP (suite-97-5: a plane 4 cells behind another, in steps
    of 2.2 and 1.7). Per projector axis, the two steps from the pixel before to the pixel after,
    less the surface's own step (the larger of the steps beyond them: the smaller may be another
    mixed pixel's), make a depth edge by the rule of :func:`_edge_steps`, and each of the two is
    over the surface's own step by half EDGE_EXCESS, as a steep surface's growing steps are not."""
    (before, ok_before, size_before), (after, ok_after, size_after) = known[-1], known[0]
    (out_step, ok_out, _), (in_step, ok_in, _) = known[-2], known[1]
    # Only pixels both of whose steps are over half EDGE_EXCESS along some axis can pass (a step's
    # size is its larger axis): on most maps none, and the rest is done on those alone.
    bridge = ok_before & ok_after & (size_before > EDGE_EXCESS / 2) & (size_after > EDGE_EXCESS / 2)
    at = torch.nonzero(bridge, as_tuple=True)
    if at[0].numel():
        b, a = before[at], after[at]  # (n, 2)
        # Per projector axis: a jump along one axis measured against the surface's steps along it;
        # no step known beyond: none.
        around = torch.maximum(torch.where(ok_out[at][:, None], out_step[at].abs(), 0.0),
                               torch.where(ok_in[at][:, None], in_step[at].abs(), 0.0))
        span = (b + a).abs() - around
        halves = torch.minimum(b.abs(), a.abs()) - around
        bridge[at] = ((span > EDGE_JUMP) & (span - around > EDGE_EXCESS) & (halves > EDGE_EXCESS / 2)).any(-1)
    out = bridge.clone()
    for shift in (1, -1):  # the pixels either side may see both surfaces too
        out |= torch.roll(bridge, shift, dim)
    return out


def pixel_square(samples: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """:math:`(S^2, 2)` ``(dx, dy)`` offsets from a camera pixel's centre, a ``samples x samples`` grid
    of the centres of equal parts of its square: what a pixel's area carries through :func:`map_slope`."""
    steps = (torch.arange(samples, dtype=dtype, device=device) + 0.5) / samples - 0.5
    dy, dx = (t.reshape(-1) for t in torch.meshgrid(steps, steps, indexing="ij"))
    return torch.stack([dx, dy], -1)
