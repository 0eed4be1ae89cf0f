"""Evaluation: metrics, and the main job on the virtual rig (``run_virtual``)."""

from .metrics import crosstalk, masked_ssim, model_space_psnr, psnr
from .run import RunResult, VirtualCalibration, calibrate_virtual, default_images, run_virtual

__all__ = ["RunResult", "VirtualCalibration", "calibrate_virtual", "crosstalk", "default_images", "masked_ssim", "model_space_psnr", "psnr", "run_virtual"]
