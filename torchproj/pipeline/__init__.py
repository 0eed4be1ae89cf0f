"""The whole workflow on the virtual rig, one implementation behind every entry point.

Calibrate (:func:`calibrate_virtual`), place the targets (:func:`scene_targets`), solve and score
the patterns on the rig's captures (:func:`evaluate_patterns`), or all of it in one call
(:func:`run_virtual`, which is ``torchproj run``).
"""

from .real_rig import BundleSolution, solve_bundle
from .run import RunResult, run_markdown, run_virtual
from .scoring import EVALUATION, PatternEvaluation, TargetScore, evaluate_patterns, score_image
from .targets import DEFAULT_IMAGES, default_images, scene_images, scene_targets, target_image
from .virtual import (DecodingAccuracy, VirtualCalibration, calibrate_rig, calibrate_virtual, check_calibration,
                      decoding_accuracy, simulate_calibration, simulate_markdown, simulate_scene)

__all__ = ["BundleSolution", "DEFAULT_IMAGES", "DecodingAccuracy", "EVALUATION", "PatternEvaluation", "RunResult", "TargetScore",
           "VirtualCalibration", "calibrate_rig", "calibrate_virtual", "check_calibration", "decoding_accuracy", "default_images", "evaluate_patterns",
           "run_markdown", "run_virtual", "scene_images", "scene_targets", "score_image", "simulate_calibration", "simulate_markdown", "simulate_scene",
           "solve_bundle", "target_image"]
