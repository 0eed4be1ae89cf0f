"""The camera's sensor: exposure, shot and read noise, response curve and quantisation."""

from __future__ import annotations

import torch

from ..core.checks import check, check_shape
from ..core.fused import fused
from ..scene.config import Camera

__all__ = ["apply_camera"]

_SENSOR_FIELDS = ("exposure", "full_well", "read_noise", "gamma", "bit_depth", "frames")


def apply_camera(radiance: torch.Tensor, camera: Camera, generator: torch.Generator | None,
                 quantise: bool = True, out: torch.Tensor | None = None) -> torch.Tensor:
    """Turn linear radiance into stored pixel values.

    The sensor collects ``exposure * radiance`` (1.0 = full well). Shot noise is Poisson in the
    collected electrons, drawn as its Gaussian limit with variance ``v / full_well``; read noise adds
    a Gaussian of standard deviation ``read_noise``. The value is clipped (saturation), bent by the
    response ``v**(1/gamma)`` and quantised to ``bit_depth`` bits. A camera of several ``frames``
    gives each capture as the mean of that many such frames, each with its own noise, each quantised
    (as a bench averages the grabs its camera stores).

    Args:
        radiance: :math:`(N, C, H, W)` linear radiance.
        camera: the camera description.
        generator: random generator for the noise; None captures without noise.
        quantise: False keeps the exact values (the expected image, for oracle comparisons).
        out: where to write the result (may be ``radiance`` itself, overwriting it image by image).

    Returns:
        :math:`(N, C, H, W)` values in [0, 1] on the quantisation grid ``k / (2^bits - 1)`` (a
        mean of ``frames`` values of it for a camera of several).
    """
    check_shape(radiance, "radiance", ["N", "C", "H", "W"])
    # What the sensor reads of a camera: a scene's Camera has them, and so may a stand-in of the caller's.
    check(all(hasattr(camera, a) for a in _SENSOR_FIELDS), f"camera must be a scene's Camera (scene.camera), or hold "
                                                           f"its {', '.join(_SENSOR_FIELDS)}; got {type(camera).__name__}")
    check(generator is None or isinstance(generator, torch.Generator),
          f"generator must be a torch.Generator, or None for no noise, got {type(generator).__name__}")
    if out is not None:
        check_shape(out, "out", list(radiance.shape))
    peak = (1 << camera.bit_depth) - 1
    out = torch.empty_like(radiance) if out is None else out
    noisy = generator is not None and (camera.full_well > 0 or camera.read_noise > 0)
    # One image at a time: whole-stack temporaries of tens of millions of values cost more in memory
    # traffic than the arithmetic. The noise is drawn here, from the rig's generator, so that a fused
    # and an eager run capture the same images.
    # Without noise every frame is the same, and their mean is one of them.
    frames = camera.frames if noisy else 1
    for i in range(radiance.shape[0]):
        total = None
        for _ in range(frames):
            noise = torch.randn(radiance[i].shape, generator=generator, device=radiance.device,
                                dtype=radiance.dtype) if noisy else None
            frame = _sensor(radiance[i], noise, camera.exposure, 1.0 / camera.full_well if camera.full_well > 0 else 0.0,
                            camera.read_noise ** 2, 1.0 / camera.gamma, float(peak) if quantise else 0.0)
            total = frame if total is None else total.add_(frame)
        out[i] = total if frames == 1 else total.div_(frames)
    return out


@fused
def _sensor(radiance: torch.Tensor, noise: torch.Tensor | None, exposure: float, per_electron: float,
            read_variance: float, inverse_gamma: float, peak: float) -> torch.Tensor:
    """The sensor's chain for one image (:func:`apply_camera`), fused into one loop where torch can.

    ``per_electron``: 1 / full well (0: no shot noise); ``peak``: 2^bits - 1, or 0 for no quantisation.
    """
    v = radiance * exposure
    if noise is not None:
        v = torch.addcmul(v, noise, (v.clamp_min(0) * per_electron + read_variance).sqrt())
    v = v.clamp(0, 1)
    if inverse_gamma != 1.0:
        v = v.pow(inverse_gamma)
    if peak:
        v = (v * peak).round() / peak
    return v
