"""A thin lens's circle of confusion, sampled: one definition for the simulator that blurs light
with it and the transport model that spreads a pixel's footprint over it.

A disc is sampled at points of a Vogel spiral, which covers it evenly (its mean squared radius is
exactly the disc's). How many points a disc gets grows with its diameter in cells (below each bound
of ``DISC_POINTS``, that many): under a twentieth of a cell it is taken as its centre, under a cell
a few points share its light between the cells it straddles, and 16 points (times the samples of a
camera pixel) cover a disc several cells wide.
"""

from __future__ import annotations

import math

import torch

__all__ = ["DISC_POINTS", "GOLDEN_ANGLE", "disc_points", "points_for_diameter"]

DISC_POINTS = ((0.05, 1), (1.0, 4), (math.inf, 16))
GOLDEN_ANGLE = math.pi * (3 - math.sqrt(5))


def points_for_diameter(diameter: float) -> int:
    """How many points sample a disc ``diameter`` cells wide (``DISC_POINTS``)."""
    return next(count for bound, count in DISC_POINTS if diameter < bound)


def disc_points(count: int, device=None) -> torch.Tensor:
    """:math:`(K, 2)` float32 points of the unit-diameter disc, a Vogel spiral (the centre for K = 1)."""
    k = torch.arange(count, dtype=torch.float64, device=device)
    radius = ((k + 0.5) / count).sqrt() / 2 if count > 1 else torch.zeros(1, dtype=torch.float64, device=device)
    angle = k * GOLDEN_ANGLE
    return torch.stack([radius * angle.cos(), radius * angle.sin()], -1).float()
