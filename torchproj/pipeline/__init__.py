"""The whole workflow on the virtual rig, one implementation behind every entry point.

Calibrate (:func:`calibrate_virtual`), place the targets (:func:`scene_targets`), solve and score
the patterns on the rig's captures (:func:`evaluate_patterns`), or all of it in one call
(:func:`run_virtual`, which is ``torchproj run``). For a real bench: capture a sequence with a
camera and a projector (:func:`capture_sequence`), solve from its calibration bundle
(:func:`solve_bundle`), and refine with the bench's camera in the loop over files (:func:`refine_bundle`).
"""

from .acquire import OpenCVCamera, OpenCVDisplay, capture_sequence
from .bench_loop import refine_bundle
from .real_rig import BundleSolution, solve_bundle
from .ceiling import light_transport, solve_on_light_transport
from .footprint import AUTO_TOLERANCE_DB, FootprintChoice, choose_footprint
from .run import CEILING_ITERATIONS, ORACLES, RunResult, run_markdown, run_virtual
from .shown import rig_measure, shown_world
from .scoring import (EVALUATION, PatternEvaluation, TargetScore, affine_psnr, evaluate_patterns, ghost_images,
                      score_image)
from .targets import DEFAULT_IMAGES, default_images, image_with_channels, scene_images, scene_targets, target_image
from .virtual import (DecodingAccuracy, VirtualCalibration, calibrate_rig, calibrate_virtual, check_calibration,
                      decoding_accuracy, describe_light, simulate_calibration, simulate_markdown, simulate_scene,
                      true_responses, white_levels)

__all__ = [
    "AUTO_TOLERANCE_DB", "BundleSolution", "CEILING_ITERATIONS", "DEFAULT_IMAGES", "DecodingAccuracy", "EVALUATION", "FootprintChoice", "ORACLES",
    "OpenCVCamera", "OpenCVDisplay", "PatternEvaluation", "RunResult", "TargetScore", "VirtualCalibration",
    "calibrate_rig", "calibrate_virtual", "capture_sequence", "check_calibration", "choose_footprint", "decoding_accuracy",
    "affine_psnr", "default_images", "evaluate_patterns", "ghost_images", "image_with_channels", "light_transport", "run_markdown", "run_virtual", "scene_images",
    "scene_targets", "score_image", "simulate_calibration", "simulate_markdown", "simulate_scene", "solve_bundle",
    "refine_bundle", "rig_measure", "shown_world", "solve_on_light_transport", "target_image", "true_responses",
    "describe_light", "white_levels",
]
