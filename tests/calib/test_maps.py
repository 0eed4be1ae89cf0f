import numpy as np
import torch

from torchproj.calib import fill_holes, inverse_map
from torchproj.calib.maps import depth_edges, map_slope


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
