"""Image quality scores, each saying what it compares: PSNR, SSIM (differentiable, in torch), crosstalk.

Imports only :mod:`torchproj.core`, so that solvers can optimise the same SSIM that evaluation reports.
"""

from .scores import crosstalk, explained_share, model_space_psnr, psnr
from .ssim import SSIMLoss, ssim, ssim_map

__all__ = ["SSIMLoss", "crosstalk", "explained_share", "model_space_psnr", "psnr", "ssim", "ssim_map"]
