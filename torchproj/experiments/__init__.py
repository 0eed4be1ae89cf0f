"""The paper's experiments on the virtual rig: depth selectivity sweeps and the positioning test."""

from .depth import DepthSweep, depth_sweep
from .positioning import (PAPER_RMSE_PERCENT, PlacementTrial, PositioningResult, box_surface_distance,
                          evaluate_positioning, feedback_profile, place_by_feedback, placement_error, pose_error,
                          position_markdown, random_pose_near,
                          rig_procam, scan_distance, scan_surface)

__all__ = ["DepthSweep", "PAPER_RMSE_PERCENT", "PlacementTrial", "PositioningResult", "box_surface_distance",
           "depth_sweep", "evaluate_positioning", "feedback_profile", "place_by_feedback", "placement_error",
           "pose_error", "position_markdown",
           "random_pose_near", "rig_procam", "scan_distance", "scan_surface"]
