"""torchproj's SSIM against scikit-image (the evaluation's reference), and its gradients."""

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from torchproj.core import InputError
from torchproj.metrics import SSIMLoss, crosstalk, ssim, ssim_map


def images(channels=1, shape=(40, 52), seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(channels, *shape, generator=g, dtype=dtype)
    b = (0.6 * a + 0.4 * torch.rand(channels, *shape, generator=g, dtype=dtype)).clamp(0, 1)
    b[:, :10, :12] = 0.7  # a flat patch: variances near zero, where C2 carries the score
    return a, b


def blob(shape=(40, 52)):
    """An irregular mask whose bounding box does not reach the image border."""
    y, x = torch.meshgrid(torch.arange(shape[0]), torch.arange(shape[1]), indexing="ij")
    return ((x - 27) ** 2 / 18**2 + (y - 19) ** 2 / 13**2 < 1) | ((x > 5) & (x < 14) & (y > 24) & (y < 37))


def skimage_masked(estimate, reference, mask):
    """The evaluation as it was: scikit-image's map on the mask's bounding box, averaged over the mask."""
    ys, xs = torch.nonzero(mask, as_tuple=True)
    y0, y1, x0, x1 = int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1
    m = mask[y0:y1, x0:x1].numpy()
    maps = [structural_similarity(e, r, data_range=1.0, full=True)[1]
            for e, r in zip(estimate[:, y0:y1, x0:x1].double().numpy(), reference[:, y0:y1, x0:x1].double().numpy())]
    return float(np.mean([mp[m].mean() for mp in maps]))


@pytest.mark.parametrize("channels", [1, 3])
def test_map_is_scikit_images(channels):
    a, b = images(channels)
    for e, r, mine in zip(a, b, ssim_map(a, b)):
        _, ref = structural_similarity(e.numpy(), r.numpy(), data_range=1.0, full=True)
        np.testing.assert_allclose(mine.numpy(), ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("channels", [1, 3])
def test_masked_score_is_the_evaluations(channels):
    a, b = images(channels)
    mask = blob()
    assert float(ssim(a, b, mask)) == pytest.approx(skimage_masked(a, b, mask), abs=1e-12)
    # float32, as a loss computes it: the running sums round, the mean barely moves
    assert float(ssim(a.float(), b.float(), mask)) == pytest.approx(skimage_masked(a, b, mask), abs=1e-5)
    assert float(ssim(a, a, mask)) == pytest.approx(1.0, abs=1e-12)


def test_a_batch_is_its_images_scored_one_by_one():
    a, b = images(3)
    c, d = images(3, seed=4)
    masks = torch.stack([blob(), torch.ones(40, 52, dtype=torch.bool)])
    batch = ssim(torch.stack([a, c]), torch.stack([b, d]), masks)
    assert batch.shape == (2,)
    assert float(batch[0]) == pytest.approx(float(ssim(a, b, masks[0])), abs=1e-14)
    assert float(batch[1]) == pytest.approx(float(ssim(c, d, masks[1])), abs=1e-14)
    loss = SSIMLoss(torch.stack([b, d]), masks)
    torch.testing.assert_close(loss(torch.stack([a, c])), 1 - batch, rtol=0, atol=1e-14)


def test_closed_form_gradient_is_autograds():
    a, b = images(3)
    mask = blob()
    x = a.clone().requires_grad_(True)
    ssim(x, b, mask).backward()  # closed form: the reference needs no gradient
    y = a.clone().requires_grad_(True)
    ssim(y, b.clone().requires_grad_(True), mask).backward()  # autograd through ssim_map
    assert float(x.grad.abs().max()) > 1e-4
    torch.testing.assert_close(x.grad, y.grad, rtol=1e-9, atol=1e-14)
    small_a, small_b = a[:, 5:17, 8:22].clone(), b[:, 5:17, 8:22]
    small_mask = blob()[5:17, 8:22] | (torch.arange(14) > 9)[None, :]
    assert torch.autograd.gradcheck(lambda t: ssim(t, small_b, small_mask), (small_a.requires_grad_(True),))


def test_the_map_has_second_derivatives():
    a, b = images(1, shape=(9, 10))
    assert torch.autograd.gradgradcheck(lambda t: ssim_map(t, b).sum(), (a.requires_grad_(True),))


def test_ssim_and_crosstalk_measure_what_they_say():
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(1, 40, 40, generator=g), torch.rand(1, 40, 40, generator=g)
    mask = torch.zeros(40, 40, dtype=torch.bool)
    mask[5:35, 5:35] = True
    assert float(ssim(a, a, mask)) == pytest.approx(1.0, abs=1e-6)
    assert float(ssim(b, a, mask)) < 0.2
    mix = 0.7 * a + 0.3 * b
    assert crosstalk(mix, [b], mask) > crosstalk(a, [b], mask) + 0.2
    assert crosstalk(a, [], mask) == 0.0


class TestBadInput:
    def test_shapes_differ(self):
        a, b = images()
        with pytest.raises(InputError, match="differ in shape"):
            ssim(a, b[:, :-1], blob())

    def test_mask_of_another_size(self):
        a, b = images()
        with pytest.raises(InputError, match="mask must have shape"):
            ssim(a, b, blob()[:-1])

    def test_mask_not_bool(self):
        a, b = images()
        with pytest.raises(InputError, match="bool"):
            ssim(a, b, blob().float())

    def test_empty_mask(self):
        a, b = images()
        with pytest.raises(InputError, match="empty"):
            SSIMLoss(b, torch.zeros(40, 52, dtype=torch.bool))

    def test_mask_smaller_than_the_window(self):
        a, b = images()
        mask = torch.zeros(40, 52, dtype=torch.bool)
        mask[3:8, 3:20] = True
        with pytest.raises(InputError, match="at least 7x7"):
            ssim(a, b, mask)

    def test_estimate_of_another_shape_than_the_loss_reference(self):
        a, b = images()
        with pytest.raises(InputError, match="estimate must have shape"):
            SSIMLoss(b, blob())(a[:, :, :-1])

    def test_estimate_of_another_dtype_than_the_loss_reference(self):
        """A float64 estimate against a float32 loss ended in torch.dot's dtype error."""
        a, b = images()
        with pytest.raises(InputError, match=r"estimate is torch.float32 and the loss's reference torch.float64"):
            SSIMLoss(b, blob())(a.float())

    @pytest.mark.parametrize("data_range", ["1", float("nan"), float("inf"), 0, True])
    def test_a_data_range_that_is_no_positive_number(self, data_range):
        a, b = images()
        with pytest.raises(InputError, match="data_range must be a finite number > 0"):
            ssim(a, b, blob(), data_range=data_range)

    def test_a_meta_mask(self):
        """SSIM crops to the mask's pixels, which a meta tensor does not hold (torch's .item() error before)."""
        a, b = images()
        with pytest.raises(InputError, match="mask is a meta tensor"):
            ssim(a.to("meta"), b.to("meta"), blob().to("meta"))


def test_images_of_two_precisions_are_scored_in_the_finer():
    """As psnr scores whatever it is given in float64 (torch.dot refused the pair before)."""
    a, b = images()
    assert float(ssim(a.float(), b, blob())) == pytest.approx(float(ssim(a.float().double(), b, blob())), abs=1e-12)
    assert ssim(b, a.float(), blob()).dtype == torch.float64


def test_a_batch_of_no_images_has_no_scores():
    a, b = images()
    empty = torch.zeros(0, *a.shape, dtype=a.dtype), torch.zeros(0, *a.shape[1:], dtype=torch.bool)
    assert ssim(empty[0], empty[0], empty[1]).shape == (0,)
    assert SSIMLoss(empty[0], empty[1])(empty[0]).shape == (0,)


def test_the_loss_has_second_derivatives_and_they_are_autograds():
    """SSIMLoss's closed-form gradient gave no graph under create_graph=True (a Hessian-vector
    product failed); its second derivatives now match autograd through ssim_map."""
    a, b = images(1, shape=(11, 12))
    mask = torch.ones(11, 12, dtype=torch.bool)
    mask[:2, :3] = False
    loss = SSIMLoss(b, mask)
    x = a.clone().requires_grad_(True)
    assert torch.autograd.gradgradcheck(loss, (x,))
    v = torch.rand_like(a)
    (g,) = torch.autograd.grad(loss(x), x, create_graph=True)
    (hv,) = torch.autograd.grad((g * v).sum(), x)
    (g_ref,) = torch.autograd.grad(1 - ssim(x, b.clone().requires_grad_(True), mask), x, create_graph=True)
    (hv_ref,) = torch.autograd.grad((g_ref * v).sum(), x)
    torch.testing.assert_close(hv, hv_ref, rtol=1e-9, atol=1e-12)
