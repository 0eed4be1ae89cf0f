"""Planes through triangulated points: the least-squares plane, and the largest plane of a scan."""

import numpy as np
import pytest
import torch

from torchproj.calib import fit_plane, largest_plane
from torchproj.core import InputError


def board_wall_and_clutter(seed=0):
    """A tilted board (0.3 mm noise), a wall 120 mm behind it and a clump near the floor (mm)."""
    rng = np.random.default_rng(seed)
    normal = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0])
    u = np.cross(normal, [0, 1, 0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    ab = rng.uniform(-100, 100, size=(6000, 2))
    board = 800 * np.array([0, 0, 1.0]) + ab[:, :1] * u + ab[:, 1:] * v + rng.normal(0, 0.3, (6000, 1)) * normal
    wall = np.c_[rng.uniform(-300, 300, (4000, 2)), np.full(4000, 920.0)]
    clump = rng.normal([0, 250, 850], 30, (1500, 3))
    return np.vstack([board, wall, clump]), normal, len(board)


def test_the_largest_plane_is_the_board_and_measures_its_noise():
    points, normal, n_board = board_wall_and_clutter()
    pts = torch.as_tensor(points)
    everything = fit_plane(pts)[2]
    assert float(everything.pow(2).mean().sqrt()) > 20  # one plane through all of it measures nothing
    # 5 times the board's noise: the clump's points that cross the board's plane within it are few.
    centroid, found, residuals, on_plane = largest_plane(pts, threshold=1.5)
    assert abs(float(torch.as_tensor(normal) @ found)) > 0.9999
    assert bool(on_plane[:n_board].float().mean() > 0.99) and not bool(on_plane[n_board:n_board + 4000].any())
    rms = float(residuals[on_plane].pow(2).mean().sqrt())
    assert rms == pytest.approx(0.3, rel=0.1)  # the board's own noise
    torch.testing.assert_close(residuals, (pts - centroid) @ found)


def test_the_largest_plane_refuses_what_has_none():
    with pytest.raises(InputError, match="3 points or more"):
        largest_plane(torch.zeros(2, 3), 1.0)
    with pytest.raises(InputError, match="collinear"):
        largest_plane(torch.linspace(0, 1, 30)[:, None] * torch.tensor([1.0, 2.0, 3.0]), 1.0)
