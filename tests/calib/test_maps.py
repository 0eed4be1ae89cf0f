import numpy as np
import torch

from torchproj.calib import fill_holes, inverse_map


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
