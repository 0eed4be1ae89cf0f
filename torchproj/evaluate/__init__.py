"""Evaluation: metrics, the main job on the virtual rig (``run_virtual``), depth sweeps and positioning."""

from .depth import DepthSweep, depth_sweep
from .positioning import (PAPER_RMSE_PERCENT, PlacementTrial, PositioningResult, box_surface_distance,
                          evaluate_positioning, feedback_profile, place_by_feedback, pose_error, random_pose_near,
                          rig_procam, scan_distance, scan_surface)
from .metrics import crosstalk, masked_ssim, model_space_psnr, psnr
from .run import (RunResult, VirtualCalibration, calibrate_virtual, default_images, run_virtual, scene_images,
                  target_image)

__all__ = ["PAPER_RMSE_PERCENT", "PlacementTrial", "PositioningResult", "box_surface_distance",
           "evaluate_positioning", "feedback_profile", "place_by_feedback", "pose_error", "random_pose_near",
           "rig_procam", "scan_distance", "scan_surface", "DepthSweep", "RunResult", "VirtualCalibration", "calibrate_virtual", "crosstalk", "default_images",
           "depth_sweep", "masked_ssim", "model_space_psnr", "psnr", "run_virtual", "scene_images", "target_image"]
