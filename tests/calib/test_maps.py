import numpy as np
import pytest
import torch

from torchproj.calib import fill_holes, inverse_map
from torchproj.calib.maps import _tiles_within, depth_edges, fill_slope, map_slope


def test_inverse_map_matches_a_plain_loop():
    g = torch.Generator().manual_seed(0)
    prj = torch.randint(0, 8, (20, 30, 2), generator=g).float()
    prj[torch.rand(20, 30, generator=g) < 0.2] = float("nan")
    cam_xy, count = inverse_map(prj, (8, 8))
    sums, n = np.zeros((8, 8, 2)), np.zeros((8, 8), int)
    arr = prj.numpy()
    for y in range(20):
        for x in range(30):
            if np.isfinite(arr[y, x]).all():
                px, py = int(arr[y, x, 0]), int(arr[y, x, 1])
                sums[py, px] += (x, y)
                n[py, px] += 1
    assert np.array_equal(count.numpy(), n)
    seen = n > 0
    np.testing.assert_allclose(cam_xy.numpy()[seen], sums[seen] / n[seen][:, None], rtol=1e-6)
    assert np.isnan(cam_xy.numpy()[~seen]).all()


def test_fill_holes_fills_small_interior_holes_only():
    ys, xs = torch.meshgrid(torch.arange(40.0), torch.arange(40.0), indexing="ij")
    true = torch.stack([2 * xs + 1, ys - 3], -1)
    values = true.clone()
    values[10, 10] = float("nan")  # a one-pixel hole
    values[20:22, 5:7] = float("nan")  # a 2x2 hole
    values[25:35, 20:30] = float("nan")  # a large gap: genuine, stays
    values[0, 15:18] = float("nan")  # touches the border: stays
    filled = fill_holes(values, max_area=16)
    assert torch.allclose(filled[10, 10], true[10, 10])
    assert torch.allclose(filled[20:22, 5:7], true[20:22, 5:7], atol=1e-3)  # affine data: harmonic fill is exact
    assert torch.isnan(filled[25:35, 20:30]).all()
    assert torch.isnan(filled[0, 15:18]).all()
    known = torch.isfinite(values).all(-1)
    assert torch.equal(filled[known], values[known])


def _line_map(xs: list[float]) -> torch.Tensor:
    """A map one row of pixels high whose x coordinate runs through ``xs`` (y constant)."""
    x = torch.tensor(xs, dtype=torch.float32)
    return torch.stack([x, torch.full_like(x, 10.0)], -1)[None].repeat(3, 1, 1)


def test_a_small_jump_between_surfaces_is_a_depth_edge_and_a_steep_surface_is_not():
    """Two planes a few centimetres apart in depth part by two or three cells, under the 4 cells that
    always count: against the steps beside it such a jump is an edge, in one step or spread over the
    two beside a pixel that sees both; a steep surface's steps of up to 3.5 cells growing smoothly
    are not, and its slope is taken across them."""
    one_step = _line_map([0, 1, 2, 3, 4, 7, 8, 9, 10, 11])  # a 3-cell jump between 4 and 7
    assert depth_edges(one_step)[1].nonzero()[:, 0].tolist() == [4, 5]
    spread = _line_map([0, 1, 2, 3, 5.8, 8.6, 9.6, 10.6, 11.6, 12.6])  # 2.8 and 2.8 beside pixel 4
    assert depth_edges(spread)[1].nonzero()[:, 0].tolist() == [3, 4, 5]
    steep = _line_map([0, 2.6, 5.3, 8.1, 11.0, 14.0, 17.1, 20.3, 23.6, 27.0])  # steps 2.6 -> 3.4
    assert not depth_edges(steep).any()
    slope = map_slope(steep)[1, 5, 0, 0]
    assert abs(float(slope) - 3.0) < 0.2  # the mean step over two pixels either side
    assert float(map_slope(one_step)[1, 4, 0, 0]) == 1.0  # the pixel beside the jump: its own side only


def test_a_pixel_that_decodes_between_two_surfaces_bridges_a_depth_edge():
    """suite-97-5: a plane 4 cells behind another along y, through pixels 1.05 cells wide along x.
    The pixel that sees both decodes between them, 63 -> 65.3 -> 67.1: two steps of 2.3 and 1.8,
    neither an edge by itself. Taken together against the surface's own steps along y (none) they
    are, and the pixel and its two neighbours on the line are beside a depth edge. A steep surface
    whose steps grow 1.0, 1.5, 2.2, 3.0 and 3.9 cells is no edge, nor is a step beside another
    mixed pixel whose small step would hide the surface's own."""
    across = torch.arange(9.0) * 1.05
    bridged = torch.stack([across, torch.tensor([63, 63, 63, 63, 65.3, 67.1, 67.1, 67.1, 67.1])], -1)[None].repeat(3, 1, 1)
    assert depth_edges(bridged)[1].nonzero()[:, 0].tolist() == [3, 4, 5]
    growing = _line_map([0, 1, 2.5, 4.7, 7.7, 11.6, 15.5, 19.4])
    assert not depth_edges(growing).any()
    # suite-2412-12's sphere: steps 1.6, 1.6, 1.55, then 0.54 to a pixel beside the outline.
    beside = _line_map([110.5, 112.1, 113.7, 115.3, 116.9, 118.4, 118.96, 119.5])
    assert not depth_edges(beside).any()


@pytest.mark.parametrize("size", [(1200, 1600), (130, 70), (5, 9), (64, 128)])
def test_the_tiles_a_second_fit_visits_are_those_a_dilation_reaches(size):
    """The tiles _refine_again and map_slope's like= visit, from the changed pixels' coordinates: the same as dilating the mask by the
    reach (torch's max pooling) and asking which tiles hold any of it, at the image's edges too."""
    gen = torch.Generator().manual_seed(sum(size))
    reach, tile = 12, 64
    for density in (0.0, 2e-5, 1e-3, 0.2):
        mask = torch.rand(size, generator=gen) < density
        mask[0, -1] = mask[-1, 0] = density > 0.1  # corners set, at the densest
        # A square window's max is the max of its rows' maxes: two 1-D poolings, the 2-D one's result
        # at a twentieth of its time on the full-size frame.
        rows = torch.nn.functional.max_pool2d(mask.float()[None, None], (1, 2 * reach + 1), 1, (0, reach))
        near = torch.nn.functional.max_pool2d(rows, (2 * reach + 1, 1), 1, (reach, 0))
        expected = torch.nn.functional.max_pool2d(near, tile, tile, ceil_mode=True)[0, 0] > 0
        assert torch.equal(_tiles_within(mask, reach, tile), expected)


def test_a_slope_taken_like_another_maps_is_the_slope_computed_whole():
    """map_slope(b, like=(a, map_slope(a))) equals map_slope(b) to the bit: b is a with pixels added
    (calibration's dim pixels) and removed, beside depth edges and the image's borders, and maps that
    are the same or differ everywhere."""
    gen = torch.Generator().manual_seed(8)
    height, width = 200, 330
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32),
                            indexing="ij")
    a = torch.stack([0.6 * xs + 0.1 * ys, 0.05 * xs + 0.7 * ys], -1) + torch.rand(height, width, 2, generator=gen) * 0.2
    a[:, 150:] += torch.tensor([9.0, 3.0])  # a depth edge down the middle
    a[torch.rand(height, width, generator=gen) < 0.3] = float("nan")
    b = a.clone()
    extra = torch.rand(height, width, generator=gen) < 0.002
    extra[0, 0] = extra[-1, -1] = extra[100, 149] = extra[5, -2] = True  # corners, the edge, a border
    b[extra] = torch.rand(int(extra.sum()), 2, generator=gen) * 50
    b[60:64, 10:13] = float("nan")  # and some pixels gone
    slope_a = map_slope(a)
    for other, theirs in ((a, slope_a), (b, map_slope(b)), (torch.rand(height, width, 2, generator=gen), None)):
        theirs = map_slope(other) if theirs is None else theirs
        taken = map_slope(b, like=(other, theirs))
        whole = map_slope(b)
        assert torch.equal(torch.isnan(taken), torch.isnan(whole))
        assert torch.equal(torch.nan_to_num(taken), torch.nan_to_num(whole))
    # The farthest a pixel's slope reads: a pixel added three to the right of a tile's last column turns
    # the 3.25-cell step before it into a jump (the step after it is now 0.5 cells), which the slope at
    # that column must no longer take in (its steps grow, so that leaving one out moves the mean).
    row = torch.stack([3.0 * xs[0] + 0.001 * xs[0] ** 2, torch.zeros(width)], -1)
    a = row.expand(height, width, 2).clone()
    a[:, 130] = float("nan")
    b = a.clone()
    b[:, 130] = a[:, 129] + torch.tensor([0.5, 0.0])
    taken, whole = map_slope(b, like=(a, map_slope(a))), map_slope(b)
    assert not torch.equal(torch.nan_to_num(map_slope(a)[:, 127]), torch.nan_to_num(whole[:, 127]))
    assert torch.equal(torch.isnan(taken), torch.isnan(whole)) and torch.equal(torch.nan_to_num(taken), torch.nan_to_num(whole))


def test_a_strip_of_a_surface_borrows_its_unknown_slope_along_the_strip():
    """Surface A seen three rows tall over columns 0-5 and one row tall (row 2) from column 6 on,
    surface B far from it below: the strip's d/dy is unknown to map_slope and fill_slope lends A's,
    one pixel further each pass up to its reach, never B's across the depth edge; past the reach it
    completes the strip's d/dy from its d/dx as the map's pixels relate theirs."""
    h, w = 8, 20
    y, x = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    a = torch.stack([1.1 * x + 0.3 * y + 2, -0.2 * x + 0.9 * y + 1], -1)
    b = torch.stack([0.7 * x + 40, 0.75 * y + 30], -1)
    xy = torch.where((y >= 3)[..., None], b, a)
    xy[:2, 6:] = float("nan")
    slope = map_slope(xy)
    strip = slope[2, 6:]
    assert torch.isnan(strip[..., 1]).all() and torch.isfinite(strip[..., 0]).all()
    filled = fill_slope(xy, slope, reach=8)
    torch.testing.assert_close(filled[2, 6:14, :, 1], torch.tensor([0.3, 0.9], dtype=torch.float64).expand(8, 2))
    # Beyond the reach no neighbour lends: the slope along the strip, turned and scaled as the map's
    # median pixel's (B's: most of the map) turns its own, d/dy = z d/dx with z = 0.75i / 0.7.
    z = complex(0, 0.75 / 0.7)
    along = z * complex(1.1, -0.2)
    torch.testing.assert_close(filled[2, 14:, :, 1], torch.tensor([along.real, along.imag], dtype=torch.float64).expand(6, 2))
    known = ~torch.isnan(slope)
    assert torch.equal(filled[known], slope[known])  # what map_slope knew stays
    assert torch.isnan(filled[:2, 6:]).all()  # unmapped pixels stay unknown
    whole = map_slope(xy[3:])  # B alone: every slope known, nothing to lend
    assert torch.equal(fill_slope(xy[3:], whole), whole)
