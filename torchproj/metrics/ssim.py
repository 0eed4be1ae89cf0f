"""SSIM in torch: the evaluation's score, and a loss with a closed-form gradient.

The definition is scikit-image's ``structural_similarity`` with its defaults, which the
evaluation has always reported: a uniform 7x7 window, the sample covariance (49 / 48),
``K1 = 0.01``, ``K2 = 0.03``, and the image extended at its border by half-sample symmetric
reflection (scipy's ``mode="reflect"``, ``d c b a | a b c d``). Per pixel::

    S = (2 ux uy + C1) (2 vxy + C2) / ((ux^2 + uy^2 + C1) (vx + vy + C2)),   C1 = (K1 R)^2, C2 = (K2 R)^2

with local means ``u``, variances ``v`` and covariance ``vxy`` over the window, and ``R`` the data
range. A masked score crops both images to the bounding box of the mask, computes the map there
(so the reflection happens at the crop's border, as the evaluation always did) and averages it
over the mask's pixels and the channels.

Kornia's ``ssim`` uses an 11x11 Gaussian window and zero padding: a different number. Optimising
it would optimise something other than the score reported, so torchproj's objective is this one.

Window sums are separable and built by doubling (four additions per axis, exact to the rounding
of seven terms, where running sums would round with the length of a row), which with the
closed-form gradient of :class:`SSIMLoss` makes the score cheap enough for an optimisation loop
(``benchmarks/ssim_speed.py``). The evaluation computes in float64 (agreement with
scikit-image: ~1e-12), a loss in float32 (a masked mean within ~1e-6 of it).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ..core.checks import check, check_mask, check_shape
from .scores import _check_float, _check_float_pair, _check_range

__all__ = ["ssim_map", "ssim", "SSIMLoss"]

WINDOW = 7
_HALF = WINDOW // 2
_AREA = WINDOW * WINDOW
_COV = _AREA / (_AREA - 1)  # sample covariance, scikit-image's default
K1, K2 = 0.01, 0.03


def _reflect_pad(x: torch.Tensor) -> torch.Tensor:
    """Extend the last two dimensions by ``_HALF`` pixels, half-sample symmetric (scipy's ``reflect``)."""
    h = _HALF
    x = torch.cat([x[..., :h].flip(-1), x, x[..., -h:].flip(-1)], -1)
    return torch.cat([x[..., :h, :].flip(-2), x, x[..., -h:, :].flip(-2)], -2)


def _sums_of_seven(x: torch.Tensor, dim: int) -> torch.Tensor:
    """Sums of every 7 consecutive entries along ``dim`` (n -> n - 6), by doubling: pairs, fours,
    then four + pair + one. Four additions, and no running sum whose rounding grows with n."""
    n = x.shape[dim]
    pairs = x.narrow(dim, 0, n - 1) + x.narrow(dim, 1, n - 1)
    fours = pairs.narrow(dim, 0, n - 3) + pairs.narrow(dim, 2, n - 3)
    return (fours.narrow(dim, 0, n - 6) + pairs.narrow(dim, 4, n - 6)).add_(x.narrow(dim, 6, n - 6))


def _window_mean(x: torch.Tensor) -> torch.Tensor:
    """Mean over every full ``WINDOW x WINDOW`` window: :math:`(*, H + 6, W + 6) -> (*, H, W)`."""
    return _sums_of_seven(_sums_of_seven(x, -1), -2).div_(_AREA)


def _local_mean(x: torch.Tensor) -> torch.Tensor:
    """The window mean at every pixel, the border reflected: :math:`(*, H, W) -> (*, H, W)`."""
    return _window_mean(_reflect_pad(x))


def _local_mean_adjoint(g: torch.Tensor) -> torch.Tensor:
    """The adjoint of :func:`_local_mean`: spread each pixel's weight over its window, then fold the
    reflected border back onto the pixels it copied."""
    h = _HALF
    full = _window_mean(F.pad(g, (2 * h,) * 4)).clone()  # (*, H + 6, W + 6): weight on the padded image
    full[..., h:2 * h, :] += full[..., :h, :].flip(-2)
    full[..., -2 * h:-h, :] += full[..., -h:, :].flip(-2)
    full = full[..., h:-h, :]
    full[..., h:2 * h] += full[..., :h].flip(-1)
    full[..., -2 * h:-h] += full[..., -h:].flip(-1)
    return full[..., h:-h]


def _constants(data_range: float) -> tuple[float, float]:
    _check_range(data_range)
    return (K1 * data_range) ** 2, (K2 * data_range) ** 2


def ssim_map(estimate: torch.Tensor, reference: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """Per-pixel SSIM of two images (scikit-image's ``structural_similarity(..., full=True)`` map).

    Differentiable in both images, to any order (plain autograd).

    Args:
        estimate, reference: :math:`(*, H, W)` with H, W >= 7; each channel on its own.
        data_range: the value range (1 for images in [0, 1]).

    Returns:
        :math:`(*, H, W)`.
    """
    _check_float_pair(estimate, reference)
    check(estimate.shape == reference.shape, f"estimate and reference differ in shape: {tuple(estimate.shape)} vs "
                                             f"{tuple(reference.shape)}")
    check(estimate.dim() >= 2 and min(estimate.shape[-2:]) >= WINDOW,
          f"SSIM needs images of at least {WINDOW}x{WINDOW} pixels, got {tuple(estimate.shape)}")
    c1, c2 = _constants(data_range)
    ux, uy, uxx, uyy, uxy = _local_mean(torch.stack([estimate, reference, estimate * estimate,
                                                     reference * reference, estimate * reference]))
    vx, vy, vxy = _COV * (uxx - ux * ux), _COV * (uyy - uy * uy), _COV * (uxy - ux * uy)
    return (2 * ux * uy + c1) * (2 * vxy + c2) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))


class _MeanSSIM(torch.autograd.Function):
    """``sum(S * weight)`` over a crop, for a fixed reference whose local statistics are given.

    The gradient in closed form: with ``S = A1 A2 / (B1 B2)`` and ``u``, ``uxx = mean(x^2)``,
    ``uxy = mean(x y)`` the local means of the estimate, ``dS = dS/dux dux + dS/duxx duxx +
    dS/duxy duxy``, and each local mean is linear in x, so the gradient is three adjoint window
    means: ``M^T a + 2 x M^T b + y M^T c``. Three window means forward and three back, against
    five and five (plus the saved intermediates) through autograd: a third of the time on the
    full-size rig (``benchmarks/ssim_speed.py``).

    ``reference`` holds the reference's ``(y, uy, uy^2 + C1, vy + C2)``, computed once.
    """

    @staticmethod
    def forward(ctx, x, reference, weight, c1, c2):
        y, uy, b1_reference, b2_reference = reference
        ux, uxx, uxy = _local_mean(torch.stack([x, x * x, x * y]))
        ux2 = ux * ux
        a1 = (ux * uy).mul_(2).add_(c1)
        a2 = (uxy - ux * uy).mul_(2 * _COV).add_(c2)  # 2 vxy + C2
        b1 = ux2 + b1_reference
        b2 = (uxx - ux2).mul_(_COV).add_(b2_reference)  # vx + vy + C2
        inverse = (b1 * b2).reciprocal_()
        s = a1 * a2 * inverse
        ctx.save_for_backward(x, y, uy, weight, ux, a1, a2, b1, b2, inverse, s)
        ctx.reference, ctx.c1, ctx.c2 = reference, c1, c2  # constants, for a differentiable backward
        return torch.dot(s.reshape(-1), weight.reshape(-1))

    @staticmethod
    def backward(ctx, grad):
        x, y, uy, weight, ux, a1, a2, b1, b2, inverse, s = ctx.saved_tensors
        if torch.is_grad_enabled():
            # create_graph=True (a Hessian-vector product, a gradient penalty): the gradient must itself be
            # differentiable, so it is taken through autograd from x, whose graph the saved input keeps.
            # The reference's parts are constants: B1 and B2 hold them beside the estimate's.
            value = torch.dot(_ssim_of(x, *ctx.reference, ctx.c1, ctx.c2).reshape(-1), weight.reshape(-1))
            return torch.autograd.grad(value, x, grad, create_graph=True)[0], None, None, None, None
        w = weight * grad
        q = w * inverse
        d_a1, d_a2 = q * a2, q.mul_(a1)
        ws = w.mul_(s)
        d_b1, d_b2 = -ws / b1, ws.div_(b2).neg_()
        # a1(ux), b1(ux), a2(vxy(ux, uxy)), b2(vx(ux, uxx)) with vx = cov (uxx - ux^2), vxy = cov (uxy - ux uy)
        d_ux = (d_a1 * uy).add_(d_b1 * ux).sub_((ux * d_b2).add_(uy * d_a2), alpha=_COV).mul_(2)
        m_ux, m_uxx, m_uxy = _local_mean_adjoint(torch.stack([d_ux, d_b2.mul_(_COV), d_a2.mul_(2 * _COV)]))
        return m_ux.add_(m_uxx.mul_(x), alpha=2).add_(m_uxy.mul_(y)), None, None, None, None


def _ssim_of(x, y, uy, b1_reference, b2_reference, c1: float, c2: float) -> torch.Tensor:
    """The SSIM map of :class:`_MeanSSIM`'s forward in out-of-place operations, for autograd."""
    ux, uxx, uxy = _local_mean(torch.stack([x, x * x, x * y]))
    a1 = 2 * ux * uy + c1
    a2 = 2 * _COV * (uxy - ux * uy) + c2
    b1 = ux * ux + b1_reference
    b2 = _COV * (uxx - ux * ux) + b2_reference
    return a1 * a2 / (b1 * b2)


def _bounding_box(mask: torch.Tensor, name: str) -> tuple[int, int, int, int]:
    rows, cols = mask.any(1), mask.any(0)
    check(bool(rows.any()), f"{name} is empty: no pixel to score")
    ys, xs = torch.nonzero(rows)[:, 0], torch.nonzero(cols)[:, 0]
    y0, y1, x0, x1 = int(ys[0]), int(ys[-1]) + 1, int(xs[0]), int(xs[-1]) + 1
    check(y1 - y0 >= WINDOW and x1 - x0 >= WINDOW,
          f"the bounding box of {name} must be at least {WINDOW}x{WINDOW} pixels for SSIM, got {x1 - x0}x{y1 - y0}")
    return y0, y1, x0, x1


def _batched(estimate, reference, mask):
    """Shapes checked; (B, C, H, W), (B, C, H, W), (B, H, W) and whether a batch was given."""
    _check_float_pair(estimate, reference)
    batched = estimate.dim() == 4
    dims = ["B", "C", "H", "W"] if batched else ["C", "H", "W"]
    sizes = check_shape(estimate, "estimate", dims)
    check_shape(reference, "reference", dims)
    check(tuple(reference.shape) == tuple(estimate.shape), f"estimate {tuple(estimate.shape)} and reference "
                                                           f"{tuple(reference.shape)} differ in shape")
    check_mask(mask, "mask", (["B"] if batched else []) + [sizes["H"], sizes["W"]])
    # SSIM crops to the mask's bounding box: a meta tensor has no pixels to find it from.
    check(mask.device.type != "meta", "mask is a meta tensor: SSIM is scored over the pixels it marks, so it needs their values")
    if not batched:
        return estimate[None], reference[None], mask[None], False
    check(mask.shape[0] == estimate.shape[0], f"mask has {mask.shape[0]} images for a batch of {estimate.shape[0]}")
    return estimate, reference, mask, True


class SSIMLoss(nn.Module):
    """``1 - ssim(estimate, reference, mask)`` against a fixed reference, per image.

    The reference's local statistics and each mask's crop are computed once, and the gradient is
    in closed form; under ``create_graph=True`` (a Hessian-vector product, a gradient penalty) it is
    taken through autograd instead, so derivatives of any order flow.

    Args:
        reference: :math:`(C, H, W)` or :math:`(B, C, H, W)`.
        mask: :math:`(H, W)` or :math:`(B, H, W)` bool, the pixels that count.
        data_range: value range of the images.

    Shape:
        ``forward(estimate)``: estimate shaped like ``reference``; returns a 0-dim tensor, or
        :math:`(B,)` for a batch.

    Example:
        >>> loss = SSIMLoss(target, mask)
        >>> loss(prediction).backward()
    """

    def __init__(self, reference: torch.Tensor, mask: torch.Tensor, data_range: float = 1.0):
        super().__init__()
        _check_float(reference, "reference")
        reference, _, mask, self.batched = _batched(reference, reference, mask)
        self.c1, self.c2 = _constants(data_range)
        self.crops = [_bounding_box(m, f"mask[{b}]" if self.batched else "mask") for b, m in enumerate(mask)]
        for b, (y0, y1, x0, x1) in enumerate(self.crops):
            y = reference[b, :, y0:y1, x0:x1].detach()
            m = mask[b, y0:y1, x0:x1]
            uy, uyy = _local_mean(torch.stack([y, y * y]))
            self.register_buffer(f"reference_{b}", y.contiguous())
            self.register_buffer(f"mean_{b}", uy)
            self.register_buffer(f"b1_{b}", uy * uy + self.c1)  # the reference's parts of B1 and B2
            self.register_buffer(f"b2_{b}", _COV * (uyy - uy * uy) + self.c2)
            self.register_buffer(f"weight_{b}", (m.to(y.dtype) / (int(m.sum()) * y.shape[0])).expand_as(y).contiguous())
        self.shape = tuple(reference.shape)

    def forward(self, estimate: torch.Tensor) -> torch.Tensor:
        batch = estimate if self.batched else estimate[None]
        check(tuple(batch.shape) == self.shape, f"estimate must have shape {self.shape if self.batched else self.shape[1:]}"
                                                f", got {tuple(estimate.shape)}")
        kept = self.reference_0.dtype if self.crops else batch.dtype
        check(batch.dtype == kept, f"estimate is {batch.dtype} and the loss's reference {kept}: give the estimate in "
                                   f"{kept}, or move the loss to {batch.dtype} (.to({batch.dtype}))")
        scores = []
        for b, (y0, y1, x0, x1) in enumerate(self.crops):
            reference = [getattr(self, f"{name}_{b}") for name in ("reference", "mean", "b1", "b2")]
            weight = getattr(self, f"weight_{b}")
            # One channel at a time: an RGB crop's maps (tens of MB each) overflow the cache, and the
            # window sums then run at memory speed.
            scores.append(sum(_MeanSSIM.apply(batch[b, c:c + 1, y0:y1, x0:x1], [r[c:c + 1] for r in reference],
                                              weight[c:c + 1], self.c1, self.c2) for c in range(weight.shape[0])))
        loss = 1 - torch.stack(scores) if scores else batch.new_zeros(0)  # a batch of no images: no scores
        return loss if self.batched else loss[0]


def ssim(estimate: torch.Tensor, reference: torch.Tensor, mask: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """Mean SSIM over the pixels of a mask: the score ``torchproj run`` reports.

    Each image is cropped to the bounding box of its mask, the SSIM map (:func:`ssim_map`) is
    computed per channel on the crop and averaged over the mask's pixels and the channels.
    Differentiable in ``estimate`` (closed form, :class:`SSIMLoss`) or, where ``reference``
    requires a gradient too, in both (autograd, any order).

    Args:
        estimate, reference: :math:`(C, H, W)`, or a batch :math:`(B, C, H, W)`.
        mask: :math:`(H, W)` bool, or :math:`(B, H, W)` for a batch; bounding box at least 7x7.
        data_range: value range of the images (1 for [0, 1]).

    Returns:
        0-dim tensor, or :math:`(B,)` for a batch.
    """
    est, ref, masks, batched = _batched(estimate, reference, mask)
    dtype = torch.promote_types(est.dtype, ref.dtype)  # as psnr, which scores in float64 whatever it is given
    est, ref = est.to(dtype), ref.to(dtype)
    if not ref.requires_grad:
        score = 1 - SSIMLoss(ref, masks, data_range)(est)
        return score if batched else score[0]
    scores = []
    for b, m in enumerate(masks):
        y0, y1, x0, x1 = _bounding_box(m, "mask")
        crop = m[y0:y1, x0:x1]
        s = ssim_map(est[b, :, y0:y1, x0:x1], ref[b, :, y0:y1, x0:x1], data_range)
        scores.append((s * crop).sum() / (crop.sum() * s.shape[0]))
    score = torch.stack(scores) if scores else est.new_zeros(0)
    return score if batched else score[0]
