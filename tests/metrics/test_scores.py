import math

import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio

from torchproj.core import InputError
from torchproj.metrics import model_space_psnr, psnr
from torchproj.transport import build_transport

from ..helpers import synthetic_calibration, targets


def test_psnr_matches_scikit_image():
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(3, 20, 20, generator=g), torch.rand(3, 20, 20, generator=g)
    assert psnr(a, b) == pytest.approx(peak_signal_noise_ratio(b.numpy(), a.numpy(), data_range=1.0), rel=1e-9)
    assert psnr(a, a) == math.inf


@pytest.mark.parametrize("metric", ["psnr", "ssim"])
def test_8_bit_images_are_refused_where_scikit_image_would_read_their_range(metric):
    """psnr of uint8 images scored them against a range of 1: -21.6 dB for what is 26.5 dB."""
    from torchproj.metrics import ssim

    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(1, 20, 20, generator=g), torch.rand(1, 20, 20, generator=g)
    score = (lambda x, y: psnr(x, y)) if metric == "psnr" else (lambda x, y: ssim(x, y, torch.ones(20, 20, dtype=bool)))
    with pytest.raises(InputError, match="estimate must be a float tensor .*got torch.uint8"):
        score((a * 255).to(torch.uint8), (b * 255).to(torch.uint8))
    with pytest.raises(InputError, match="reference must be a float tensor .*got ndarray"):
        score(a, b.numpy())


def test_psnr_of_nothing_or_no_range_is_refused():
    with pytest.raises(InputError, match="hold no values"):
        psnr(torch.zeros(1, 0, 4), torch.zeros(1, 0, 4))
    for data_range in (0, "255", float("nan")):
        with pytest.raises(InputError, match="data_range must be a finite number > 0"):
            psnr(torch.zeros(1, 2, 2), torch.ones(1, 2, 2), data_range=data_range)


def test_model_space_psnr_per_target():
    op = build_transport(synthetic_calibration(), targets(), merge=False, scale=1.0)
    exact = torch.linalg.lstsq(op.dense().double(), op.rhs.double()).solution.float()
    scores = model_space_psnr(op, exact)
    assert len(scores) == 2 and all(s > 10 for s in scores)
    assert model_space_psnr(op, torch.zeros_like(exact))[0] < scores[0]
    # Merged rows mix pixels (and leave a constant behind): refuse them.
    cals = synthetic_calibration(shape=(40, 50))
    for cal in cals.values():
        cal.prj_xy = [torch.floor(m) for m in cal.prj_xy]
    merged = build_transport(cals, targets(), merge=True, scale=1.0)
    with pytest.raises(InputError, match="merge=False"):
        model_space_psnr(merged, torch.zeros(merged.shape[1], 1))


def test_crosstalk_ignores_colour_balance():
    """Two unrelated colour images with the same channel means (a warm tint): no trace of one in the other."""
    from torchproj.metrics import crosstalk

    g = torch.Generator().manual_seed(3)
    tint = torch.tensor([0.7, 0.4, 0.1])[:, None, None]
    a = 0.3 * torch.rand(3, 50, 50, generator=g) + tint
    b = 0.3 * torch.rand(3, 50, 50, generator=g) + tint
    mask = torch.ones(50, 50, dtype=torch.bool)
    assert crosstalk(a, [b], mask) < 0.05
    assert crosstalk(0.5 * a + 0.5 * b, [b], mask) > 0.6


@pytest.mark.parametrize("score", ["crosstalk", "explained_share"])
def test_masked_scores_refuse_masks_and_images_that_do_not_fit(score):
    """An integer mask indexed pixels 0 and 1 instead of choosing pixels (crosstalk 0.0 without a word);
    images of other shapes ended in torch's indexing errors."""
    from torchproj import metrics

    fn = getattr(metrics, score)
    names = ("captured", "others") if score == "crosstalk" else ("residual", "regressors")
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(3, 9, 11, generator=g), torch.rand(3, 9, 11, generator=g)
    mask = torch.ones(9, 11, dtype=torch.bool)
    assert fn(a, [0.5 * a + 0.5 * b], mask) > 0.3
    with pytest.raises(InputError, match="mask must be a bool tensor, got torch.int64"):
        fn(a, [b], mask.long())
    with pytest.raises(InputError, match=r"mask must have shape \(9, 11\)"):
        fn(a, [b], mask[:, :5])
    with pytest.raises(InputError, match=rf"{names[1]}\[1\] \(1, 9, 11\) must have {names[0]}'s shape \(3, 9, 11\)"):
        fn(a, [b, b[:1]], mask)
    with pytest.raises(InputError, match=rf"{names[1]} must be a list of images, got Tensor"):
        fn(a, b, mask)
    with pytest.raises(InputError, match=rf"{names[0]} must have shape \(C, H, W\)"):
        fn(a[0], [b[0]], mask)


def test_explained_share_is_the_r_squared_of_numpy_least_squares():
    import numpy as np

    from torchproj.metrics import explained_share

    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(2, 9, 11, generator=g), torch.rand(2, 9, 11, generator=g)
    residual = 0.7 * a - 0.2 * b + 0.3 * torch.rand(2, 9, 11, generator=g)
    mask = torch.rand(9, 11, generator=g) > 0.2
    # Independent reference: centred per channel, one coefficient per regressor, numpy's lstsq.
    centre = lambda x: (x[:, mask].double() - x[:, mask].double().mean(1, keepdim=True)).reshape(-1).numpy()  # noqa: E731
    r, G = centre(residual), np.stack([centre(a), centre(b)], 1)
    beta = np.linalg.lstsq(G, r, rcond=None)[0]
    want = 1 - ((r - G @ beta) ** 2).sum() / (r ** 2).sum()
    assert explained_share(residual, [a, b], mask) == pytest.approx(want, abs=1e-12)
    assert explained_share(a, [a], mask) == pytest.approx(1.0) and explained_share(a, [], mask) == 0.0
    # A pixel a regressor knows nothing about (NaN) counts as its mean, and changes nothing else.
    holed = a.clone()
    holed[:, ~mask] = float("nan")
    assert explained_share(residual, [holed, b], mask) == pytest.approx(want, abs=1e-12)
