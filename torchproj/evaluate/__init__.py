"""Evaluation: metrics, the main job on the virtual rig (``run_virtual``) and depth sweeps."""

from .depth import DepthSweep, depth_sweep
from .metrics import crosstalk, masked_ssim, model_space_psnr, psnr
from .run import (RunResult, VirtualCalibration, calibrate_virtual, default_images, run_virtual, scene_images,
                  target_image)

__all__ = ["DepthSweep", "RunResult", "VirtualCalibration", "calibrate_virtual", "crosstalk", "default_images",
           "depth_sweep", "masked_ssim", "model_space_psnr", "psnr", "run_virtual", "scene_images", "target_image"]
