"""The PNG summaries: readable at a glance, one scale where panels are compared, no empty panel."""

import numpy as np
import torch

from torchproj.calib import ResponseCurve
from torchproj.core import read_image
from torchproj.figures import DPI, calibration_summary


def test_calibration_errors_of_a_twentieth_of_a_pixel_are_not_drawn_black(tmp_path):
    """The error maps were on a fixed 0-0.5 px scale: sub-pixel errors of 0.05 px came out nearly
    black. The scale is now the errors' own 99th percentile, one for every row."""
    g = torch.Generator().manual_seed(0)
    rows = []
    for k in range(2):
        rows.append({"label": f"state{k}", "prj_xy": torch.rand(40, 50, 2, generator=g) * 100,
                     "error": torch.rand(40, 50, generator=g) * 0.05, "levels": np.linspace(0, 1, 8),
                     "measured": np.linspace(0, 1, 8)[:, None] ** 2.2,
                     "response": ResponseCurve(torch.ones(1), torch.full((1,), 2.2), torch.zeros(1))})
    path = tmp_path / "calibration.png"
    calibration_summary(path, rows)
    rgb = read_image(path).numpy()
    assert rgb.shape[2] == round(17 * DPI)  # the figure's width at the stated resolution
    errors = rgb[:, :, rgb.shape[2] // 2:rgb.shape[2] * 3 // 4]  # the third of four columns: the error maps
    bright = (errors[0] > 0.8) & (errors[1] > 0.4)  # magma's upper half: orange to yellow
    assert bright.sum() > 2000
