"""The camera's sensor: exposure, shot and read noise, response curve and quantisation."""

from __future__ import annotations

import torch

from ..scene.config import Camera

__all__ = ["apply_camera"]


def apply_camera(radiance: torch.Tensor, camera: Camera, generator: torch.Generator | None,
                 quantise: bool = True, out: torch.Tensor | None = None) -> torch.Tensor:
    """Turn linear radiance into stored pixel values.

    The sensor collects ``exposure * radiance`` (1.0 = full well). Shot noise is Poisson in the
    collected electrons, drawn as its Gaussian limit with variance ``v / full_well``; read noise adds
    a Gaussian of standard deviation ``read_noise``. The value is clipped (saturation), bent by the
    response ``v**(1/gamma)`` and quantised to ``bit_depth`` bits.

    Args:
        radiance: :math:`(N, C, H, W)` linear radiance.
        camera: the camera description.
        generator: random generator for the noise; None captures without noise.
        quantise: False keeps the exact values (the expected image, for oracle comparisons).
        out: where to write the result (may be ``radiance`` itself, overwriting it image by image).

    Returns:
        :math:`(N, C, H, W)` values in [0, 1] on the quantisation grid ``k / (2^bits - 1)``.
    """
    peak = (1 << camera.bit_depth) - 1
    out = torch.empty_like(radiance) if out is None else out
    # One image at a time, in place: whole-stack temporaries of tens of millions of values cost
    # more in memory traffic than the arithmetic itself.
    for i in range(radiance.shape[0]):
        v = radiance[i].mul_(camera.exposure) if out is radiance else radiance[i] * camera.exposure
        if generator is not None and (camera.full_well > 0 or camera.read_noise > 0):
            var = v.clamp_min(0).mul_(1.0 / camera.full_well) if camera.full_well > 0 else torch.zeros_like(v)
            var.add_(camera.read_noise**2).sqrt_()
            noise = torch.randn(v.shape, generator=generator, device=v.device, dtype=v.dtype)
            v.addcmul_(noise, var)
        v.clamp_(0, 1)
        if camera.gamma != 1.0:
            v.pow_(1.0 / camera.gamma)
        if quantise:
            v.mul_(peak).round_().div_(peak)
        if out is not radiance:
            out[i] = v
    return out
