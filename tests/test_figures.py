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


def test_images_are_averaged_down_to_their_panel_with_nan_left_out():
    """A 1500 x 1100 image in a 480-pixel panel is drawn from block means (scikit-image's block_reduce with
    a NaN-ignoring mean is the reference), no fewer pixels than the panel shows; a small one as it is."""
    import warnings

    from matplotlib.figure import Figure
    from skimage.measure import block_reduce

    from torchproj.figures import _shown

    fig = Figure(figsize=(13.2, 10.8))
    ax = fig.subplots(3, 3)[1, 1]
    rng = np.random.default_rng(0)
    image = rng.random((1100, 1500, 3))
    image[rng.random((1100, 1500)) < 0.3] = np.nan
    image[:40, :40] = np.nan  # whole blocks unknown
    shown = _shown(image, ax)
    box = ax.get_position()
    panel = (box.height * 10.8 * DPI, box.width * 13.2 * DPI)
    k = -(-image.shape[0] // shown.shape[0])  # the block size: shown is the ceiling of the image over it
    assert k >= 2 and shown.shape[0] >= panel[0] and shown.shape[1] >= panel[1]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # nanmean of an all-NaN block
        want = block_reduce(image, (k, k, 1), func=np.nanmean, cval=np.nan)
    np.testing.assert_allclose(shown, want, rtol=1e-12, equal_nan=True)
    assert np.isnan(shown[0, 0]).all()
    small = rng.random((300, 400))
    assert _shown(small, ax) is small


def test_a_pattern_that_lights_a_few_cells_is_drawn_cropped_to_them(tmp_path):
    """A projector that reaches only a small object lights a few dozen cells of its image; drawn whole
    they were a speck in a black panel (suite-77-19: 77 x 27 cells of 240 x 150). The panel shows the
    lit box with a margin and says which cells; a pattern lit over most of its image is drawn whole."""
    from torchproj.figures import _lit_box, run_overview
    from torchproj.pipeline import TargetScore

    small = torch.zeros(1, 150, 240, dtype=torch.uint8)
    small[0, 66:93, 79:156] = 200
    wide = torch.full((1, 150, 240), 120, dtype=torch.uint8)
    wide[0, :10] = 0
    assert _lit_box(small) == (64, 95, 72, 163)  # a tenth of each side's extent around it
    assert _lit_box(wide) == (0, 150, 0, 240)
    assert _lit_box(torch.zeros(3, 20, 30, dtype=torch.uint8)) == (0, 20, 0, 30)
    covered = torch.zeros(60, 80, dtype=torch.bool)
    covered[10:50, 10:70] = True
    values = torch.rand(1, 60, 80, generator=torch.Generator().manual_seed(0))
    score = TargetScore(name="t", state="s", psnr_db=20.0, ssim=0.5, crosstalk=0.1, pixels=int(covered.sum()),
                        estimate=values * 0.9, values=values, covered=covered)
    path = tmp_path / "overview.png"
    run_overview(path, [small, wide], ["p0", "p1"], [score])
    rgb = read_image(path).numpy()
    top = rgb[:, : rgb.shape[1] // 2]  # the patterns' row
    first, second = top[:, :, : rgb.shape[2] // 3], top[:, :, rgb.shape[2] // 3: 2 * rgb.shape[2] // 3]
    grey = 200 / 255  # the small pattern's value, drawn now over most of its panel
    assert (np.abs(first - grey) < 0.02).all(0).sum() > 0.3 * (np.abs(second - 120 / 255) < 0.02).all(0).sum()
