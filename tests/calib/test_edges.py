"""Edge pixels against captures rendered from a known pair of surfaces, and their rows in the operator."""

import pytest
import torch

from torchproj.calib import EdgePixels, GraycodeCapture, calibrate_projector, find_edge_pixels, graycode_patterns
from torchproj.calib.maps import map_slope, pixel_square
from torchproj.core.errors import InputError
from torchproj.transport import StateCalibration, Target, build_transport

PROJECTOR = (64, 32)
CAMERA = (24, 40)  # (H, W)
EDGE_X = 20.3  # where the front surface ends, in camera x: pixel 20's square [19.5, 20.5] is 80% front
DIM_FROM = 35  # columns from here get light under the decoder's shadow threshold (40/255)


def _surface(x, y):
    """Projector coordinates of camera points: a front surface left of EDGE_X, a farther one right of
    it (13 cells further along x there: a depth edge)."""
    front = torch.stack([0.9 * x + 3, 0.8 * y + 2], -1)
    back = torch.stack([0.7 * x + 20, 0.75 * y + 5], -1)
    return torch.where((x < EDGE_X)[..., None], front, back)


def _captures(samples: int = 8, shadow=None) -> tuple[GraycodeCapture, torch.Tensor]:
    """Each camera pixel the mean of ``samples`` x ``samples`` points of its square, each lit by the
    cell it falls in; black 0.05, white minus black 0.8 (0.12 from DIM_FROM on). ``shadow(x, y)``:
    where True, a camera point gets no light. Returns the capture and the true coordinates at the
    pixel centres."""
    h, w = CAMERA
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    offset = pixel_square(samples)
    px, py = xs[..., None] + offset[:, 0], ys[..., None] + offset[:, 1]
    points = _surface(px, py)  # (H, W, S, 2)
    cell = torch.floor(points + 0.5).long()
    shown = graycode_patterns(*PROJECTOR)[:, 0]  # (N + 2, h_p, w_p): pairs, then white, black
    seen = shown[:, cell[..., 1].clamp(0, PROJECTOR[1] - 1), cell[..., 0].clamp(0, PROJECTOR[0] - 1)]
    seen = (seen if shadow is None else seen * ~shadow(px, py)).mean(-1)
    contrast = torch.where(xs >= DIM_FROM, 0.12, 0.8)
    images = (0.05 + contrast * seen)[:, None]  # (N + 2, 1, H, W)
    return GraycodeCapture(patterns=images[:-2], white=images[-2], black=images[-1], ramp=None), _surface(xs, ys)


def test_edge_pixels_recover_two_surfaces_and_the_dim_fringe():
    capture, truth = _captures()
    cal = calibrate_projector(capture, PROJECTOR, dim_threshold=40)  # no dim map: its fringe is edge pixels
    edges = cal.edges
    assert isinstance(edges, EdgePixels) and len(edges) > 0
    found = {int(p): k for k, p in enumerate(edges.pixel)}
    w = CAMERA[1]
    # The outline's pixels, away from the image's top and bottom: the front surface's 80% and the
    # back one's 20%, each surface's own coordinates at the pixel's centre.
    for y in range(3, CAMERA[0] - 3):
        k = found[y * w + 20]
        share = edges.share[k]
        first_is_front = bool(share[0] > share[1])
        front, back = (0, 1) if first_is_front else (1, 0)
        assert float(share[front]) == pytest.approx(0.8, abs=0.1)
        want_front = torch.tensor([0.9 * 20 + 3, 0.8 * y + 2])
        want_back = torch.tensor([0.7 * 20 + 20, 0.75 * y + 5])
        torch.testing.assert_close(edges.xy[k, front], want_front, atol=0.5, rtol=0)
        torch.testing.assert_close(edges.xy[k, back], want_back, atol=0.5, rtol=0)
    # Smooth pixels are no edge pixels; the dim fringe the decoder leaves unmapped is, within two pixels
    # of the mapped ones, on its own surface.
    assert all(y * w + x not in found for y in range(CAMERA[0]) for x in range(3, 17))
    assert not torch.isfinite(cal.prj_xy[:, DIM_FROM:]).any()
    for y in range(3, CAMERA[0] - 3):
        for x in (DIM_FROM, DIM_FROM + 1):
            k = found[y * w + x]
            assert float(edges.share[k].max()) == 1.0
            torch.testing.assert_close(edges.xy[k, int(edges.share[k].argmax())], truth[y, x], atol=0.5, rtol=0)
        assert y * w + DIM_FROM + 3 not in found  # no mapped surface within two pixels


def test_a_surface_seen_as_a_one_pixel_strip_is_a_candidate():
    """The back surface seen through one column of pixels (20.5 to 21.5) between the outline and a
    shadow, from row 12 down (above it, wide): the strip's slope across it is unknown (map_slope), and
    lent along the strip from where the surface is seen wide (fill_slope), so the outline pixels
    beside it find both surfaces, as they do beside the wide part."""
    strip_from = 12
    capture, _ = _captures(shadow=lambda x, y: (x > 21.5) & (y > strip_from - 0.5) & (x < DIM_FROM - 0.5))
    cal = calibrate_projector(capture, PROJECTOR, dim_threshold=40)
    assert torch.isnan(map_slope(cal.prj_xy)[strip_from + 1:CAMERA[0] - 3, 21, :, 0]).all()  # the strip's d/dx
    found = {int(p): k for k, p in enumerate(cal.edges.pixel)}
    w = CAMERA[1]
    for y in range(strip_from, strip_from + 8):  # fill_slope's reach: 8 pixels along the strip
        k = found[y * w + 20]
        back = int(cal.edges.share[k].argmin())
        assert float(cal.edges.share[k, back]) == pytest.approx(0.2, abs=0.1), y
        torch.testing.assert_close(cal.edges.xy[k, back], torch.tensor([0.7 * 20 + 20, 0.75 * y + 5]), atol=0.5, rtol=0)


def test_a_surface_seen_only_as_a_one_pixel_strip_completes_its_slope():
    """The back surface seen through one column of pixels all the way down: no part of it is seen
    wide to lend the strip its slope across, so fill_slope turns the slope along it as the map's
    other pixels turn theirs, and the outline pixels beside it find both surfaces all down the
    column, the strip's pixels their own coordinates."""
    capture, truth = _captures(shadow=lambda x, y: (x > 21.5) & (x < DIM_FROM - 0.5))
    cal = calibrate_projector(capture, PROJECTOR, dim_threshold=40)
    assert torch.isnan(map_slope(cal.prj_xy)[:, 21, :, 0]).all()
    found = {int(p): k for k, p in enumerate(cal.edges.pixel)}
    w = CAMERA[1]
    for y in range(3, CAMERA[0] - 3):
        k = found[y * w + 20]
        back = int(cal.edges.share[k].argmin())
        assert float(cal.edges.share[k, back]) == pytest.approx(0.2, abs=0.1), y
        torch.testing.assert_close(cal.edges.xy[k, back], torch.tensor([0.7 * 20 + 20, 0.75 * y + 5]), atol=0.5, rtol=0)
        if y * w + 21 in found:  # a strip pixel modelled again keeps its own surface
            k = found[y * w + 21]
            own = int(cal.edges.share[k].argmax())
            torch.testing.assert_close(cal.edges.xy[k, own], truth[y, 21], atol=0.5, rtol=0)


def test_dim_light_is_read_into_its_own_map_and_is_then_no_edge():
    """Light under the shadow threshold (0.12 of white, 31/255) whose code reads: its coordinates go to
    ``dim_xy``, against the surface they were rendered from, and the lit map stays as it was."""
    capture, truth = _captures()
    cal = calibrate_projector(capture, PROJECTOR)
    lit, dim = torch.isfinite(cal.prj_xy).all(-1), torch.isfinite(cal.dim_xy).all(-1)
    assert bool(dim[:, DIM_FROM:].all()) and not dim[:, :DIM_FROM].any() and not lit[:, DIM_FROM:].any()
    inner = dim.clone()
    inner[:3], inner[-3:], inner[:, -3:] = False, False, False  # the refining window's full neighbourhoods
    torch.testing.assert_close(cal.dim_xy[inner], truth[inner], atol=0.05, rtol=0)
    # The lit map keeps its pixels; beside the dim light its refining fit has the dim neighbours too
    # (without them, the window beside the pixel, on the lit side, does as well there).
    alone = calibrate_projector(capture, PROJECTOR, dim_threshold=40).prj_xy
    assert torch.equal(lit, torch.isfinite(alone).all(-1))
    miss, miss_alone = ((xy - truth).abs().amax(-1)[3:-3, :DIM_FROM] for xy in (cal.prj_xy, alone))
    assert float(miss.max()) <= float(miss_alone.max()) + 1e-3
    assert float(miss[:, -1].max()) < 0.05
    w = CAMERA[1]
    assert not any(y * w + x in set(cal.edges.pixel.tolist()) for y in range(CAMERA[0]) for x in range(DIM_FROM - 1, w))


def test_an_edge_pixel_row_is_each_surface_square_by_its_share():
    """The area footprint's row of an edge pixel against a dense sum over each surface's 4 x 4 samples."""
    capture, _ = _captures()
    cal = calibrate_projector(capture, PROJECTOR)
    state = StateCalibration([cal.prj_xy], [cal.decoding.contrast.clamp_min(0)], [PROJECTOR], edges=[cal.edges])
    target = Target("s", torch.full((1, 8, 8), 0.5), name="t")
    op = build_transport({"s": state}, [target], footprint="area", merge=False)
    dense = torch.zeros(op.shape[0], PROJECTOR[0] * PROJECTOR[1], dtype=torch.float64)
    dense[:, op.column_cell] = op.dense().double()
    offset = pixel_square(4).double()
    checked = 0
    for row, pixel in enumerate(op.row_pixel.tolist()):
        k = torch.nonzero(cal.edges.pixel == pixel)
        if not k.numel():
            continue
        k = int(k[0])
        points = cal.edges.xy[k].double()[:, None] + offset @ cal.edges.slope[k].double().transpose(1, 2)
        if ((points + 0.5 - torch.round(points + 0.5)).abs() < 1e-4).any():
            continue  # a sample on a cell's border: float round-off picks either cell
        want = torch.zeros(PROJECTOR[0] * PROJECTOR[1], dtype=torch.float64)
        for s in range(2):
            cell = torch.floor(points[s] + 0.5).long()
            flat = cell[:, 1] * PROJECTOR[0] + cell[:, 0]
            share = float(cal.edges.share[k, s]) * float(cal.decoding.contrast.reshape(-1)[pixel]) / len(offset)
            want.index_add_(0, flat, torch.full((len(offset),), share, dtype=torch.float64))
        torch.testing.assert_close(dense[row].float(), want.float(), atol=1e-5, rtol=1e-4)
        checked += 1
    assert checked >= 20


def _rows_with_blur(cal, blur):
    """The area operator of ``cal`` with the blur map ``blur``, its dense rows and each column's cell (x, y)."""
    state = StateCalibration([cal.prj_xy], [cal.decoding.contrast.clamp_min(0)], [PROJECTOR], edges=[cal.edges],
                             blur=[blur])
    op = build_transport({"s": state}, [Target("s", torch.full((1, 8, 8), 0.5), name="t")], footprint="area",
                         merge=False)
    cell_xy = torch.stack([op.column_cell % PROJECTOR[0], op.column_cell // PROJECTOR[0]], -1).double()
    return op, op.dense().double(), cell_xy


def test_each_surface_of_an_edge_pixel_is_spread_by_its_own_blur():
    """A lens focused on the front surface, the back one blurred over a 6-cell disc: the outline
    pixels' measured blur says the back's (as their sample might), yet the front part of each of
    their rows stays in the cells its square covers, and only the back part spreads. On a projector
    measured sharp (most discs under a cell) each row keeps its pixel's own blur."""
    capture, _ = _captures()
    cal = calibrate_projector(capture, PROJECTOR)
    blur = torch.where(torch.arange(CAMERA[1]) >= 20, 6.0, 0.0).expand(*CAMERA).contiguous()
    blur[:, :8] = float("nan")  # not judged there: most of what was judged is blurred, the projector defocused
    op, rows, cell_xy = _rows_with_blur(cal, blur)
    checked = 0
    for y in range(3, CAMERA[0] - 3):
        pixel = y * CAMERA[1] + 20
        k = int(torch.nonzero(cal.edges.pixel == pixel)[0])
        row = rows[int(torch.nonzero(op.row_pixel == pixel)[0])]
        front = int(cal.edges.share[k].argmax())
        light = float(cal.edges.share[k].double()[front]) * float(cal.decoding.contrast.reshape(-1)[pixel])
        near_front = (cell_xy - cal.edges.xy[k, front].double()).abs().amax(-1) <= 1.0
        assert float(row[near_front].sum()) == pytest.approx(light, rel=0.02), y  # the front part, sharp
        near_back = (cell_xy - cal.edges.xy[k, 1 - front].double()).abs().amax(-1) <= 1.0
        assert float(row[near_back].sum()) < 0.6 * (float(row.sum()) - light), y  # the back part, spread
        checked += 1
    assert checked >= 15
    sharp = torch.where(torch.arange(CAMERA[1]) >= 36, 6.0, 0.0).expand(*CAMERA).contiguous()
    sharp[:, 20] = 6.0  # the outline pixels' own measured blur, on a projector measured sharp
    op, rows, cell_xy = _rows_with_blur(cal, sharp)
    pixel = 8 * CAMERA[1] + 20
    k = int(torch.nonzero(cal.edges.pixel == pixel)[0])
    row = rows[int(torch.nonzero(op.row_pixel == pixel)[0])]
    front = int(cal.edges.share[k].argmax())
    near_front = (cell_xy - cal.edges.xy[k, front].double()).abs().amax(-1) <= 1.0
    light = float(cal.edges.share[k].double()[front]) * float(cal.decoding.contrast.reshape(-1)[pixel])
    assert float(row[near_front].sum()) < 0.6 * light  # both parts spread by the pixel's own disc


def test_bad_inputs_name_what_is_wrong():
    capture, _ = _captures(samples=2)
    xy = torch.zeros(*CAMERA, 2)
    with pytest.raises(InputError, match="full Gray-code sequence"):
        find_edge_pixels(capture.patterns[:-2], capture.white, capture.black, xy, PROJECTOR)
    with pytest.raises(InputError, match="prj_xy"):
        find_edge_pixels(capture.patterns, capture.white, capture.black, xy[:-1], PROJECTOR)
    broken = EdgePixels(torch.tensor([CAMERA[0] * CAMERA[1]]), torch.zeros(1, 2, 2), torch.zeros(1, 2, 2, 2),
                        torch.tensor([[1.0, 0.0]]))
    with pytest.raises(InputError, match="outside the 40x24 camera"):
        broken.check(CAMERA, "edges[0]")
