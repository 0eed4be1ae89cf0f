"""The public API surface: a change here is a change users feel, so it is made on purpose."""

import torchproj

SURFACE = {
    "": [
        "BUILTIN_SCENES", "CalibrationBundle", "ClampedAdam", "ImageLoss", "InputError", "OBJECTIVES", "PSNRBudget",
        "ProjectionModel",
        "ResponseCurve", "SOLVERS", "SSIMLoss", "Scene", "SolveResult", "StateCalibration", "Target",
        "TorchprojError", "TransportOperator", "VirtualCalibration", "VirtualRig", "__version__",
        "build_transport", "calib", "calibrate_folders", "calibrate_virtual", "core", "crosstalk", "decode_gray",
        "evaluate_patterns", "experiments", "graycode_patterns", "load_bundle", "load_scene", "make_patterns",
        "metrics", "pipeline", "psnr", "refine_patterns", "rig_measure", "run_virtual", "scene", "scene_targets",
        "shown_world", "sim", "solve", "solve_adam",
        "solve_eo", "solve_fista", "solve_lf", "solve_patterns", "solve_pgd", "solve_ssim", "ssim", "target_image",
        "transport"],
    "core": [
        "CaptureError", "ConfigError", "InputError", "TorchprojError", "atomic_output", "check", "check_count",
        "check_finite", "check_image", "check_number", "check_seed", "check_shape", "pixel_grid", "read_image", "round_to_pixel", "to_numpy", "to_uint", "write_image",
        "write_json"],
    "scene": [
        "BUILTIN_SCENES", "Camera", "Projector", "SIZE_LIMIT", "Scene", "ShowChanges", "State", "Surface", "TargetSpec",
        "builtin_config", "config_dir", "load_scene", "look_at", "parse_scene", "procedural_config",
        "procedural_scene", "rotation_from_euler_deg", "rotation_from_rotvec", "scale_config", "shown_scene",
        "suite_names"],
    "sim": [
        "Caster", "StateGeometry", "VirtualRig", "apply_camera", "make_caster"],
    "calib": [
        "BUNDLE_VERSION", "CREASE_RATIO", "CURVE_RATIO", "STRIPE_MARGIN", "STRIPE_TOLERANCE", "CalibrationBundle", "CellShares", "DEFAULT_NAMES", "DIM_THRESHOLD", "DecodedFolder", "EdgePixels",
        "FEW_DECODED", "GrayDecoding", "NOISY_CAPTURES", "GraycodeCapture", "HomographyFit", "ProCamCalibration", "ProjectorCalibration",
        "ResponseCurve", "SATURATED", "SATURATED_SHARE", "band_pixels", "calibrate_folders", "calibrate_projector", "capture_noise", "cell_means", "cell_shares", "check_plane", "checker_patterns", "checker_shares",
        "decode_folder", "decode_gray", "fill_holes", "find_edge_pixels", "fit_colour_mixing", "fit_homography", "fit_plane", "fit_response",
        "graycode_bits", "graycode_patterns", "homography_map",
        "inverse_map", "largest_plane", "load_bundle", "measure_blur", "measure_ramp", "primary_patterns", "ramp_pattern", "read_graycode_folder",
        "read_opencv_calibration", "refine_subpixel", "scan_map", "sequence_bits", "stripe_contrast", "stripe_shares", "triangulate", "triangulate_map",
        "warn_if_few_decoded", "warn_if_noisy", "warn_if_saturated", "write_bundle", "write_graycode_folder", "write_ply", "write_sequence"],
    "transport": [
        "COLOUR_WEIGHTS", "DEFAULT_FOOTPRINT", "FOOTPRINTS", "HomographyFit", "MAPS", "StateCalibration", "Target",
        "TransportOperator", "build_channel_transports", "build_transport", "cell_blocks", "csr_from_coo",
        "fit_homography", "geometric_weights", "group_rows", "has_colour_weights", "homography_map", "map_slope", "normal_form", "normal_map", "planar_calibration", "point_map", "retarget_rhs", "select_maps",
        "target_on_camera", "triangulate_rays"],
    "metrics": [
        "SSIMLoss", "crosstalk", "explained_share", "model_space_psnr", "psnr", "ssim", "ssim_map"],
    "solve": [
        "CHAINS", "ClampedAdam", "ImageLoss", "ImageObjective", "LF_NORMALISE", "OBJECTIVES", "OUTSIDE",
        "PSNRBudget", "PSNR_DROP_DB", "ProjectionModel", "REFINE_SOLVER_ITERATIONS", "RefineResult", "SOLVERS", "SolveResult",
        "calibration_parts", "captured_loss", "check_bounds",
        "check_solve_options", "compensate", "component_chains", "epipolar_bands", "epipolar_chains",
        "fundamental_between_projectors", "image_objective", "make_patterns", "projectable_patterns", "psnr_hinge",
        "refine_patterns", "solve_adam",
        "solve_eo", "solve_fista", "solve_gain_offset", "solve_lf", "solve_patterns", "solve_pgd", "solve_ssim",
        "solve_target_sets", "to_projectable"],
    "pipeline": [
        "AUTO_TOLERANCE_DB", "BundleSolution", "CEILING_ITERATIONS", "DEFAULT_IMAGES", "DecodingAccuracy",
        "EVALUATION", "FootprintChoice", "ORACLES",
        "OpenCVCamera", "OpenCVDisplay", "PatternEvaluation", "RunResult", "TargetScore", "VirtualCalibration",
        "affine_psnr", "calibrate_rig", "calibrate_virtual", "capture_sequence", "check_calibration", "choose_footprint",
        "decoding_accuracy", "default_images", "describe_light", "evaluate_patterns", "ghost_images", "image_with_channels",
        "light_transport",
        "refine_bundle", "rig_measure", "run_markdown", "run_virtual", "scene_images", "scene_targets", "score_image",
        "shown_world",
        "simulate_calibration", "simulate_markdown", "simulate_scene", "solve_bundle", "solve_on_light_transport",
        "target_image", "true_responses", "white_levels"],
    "experiments": [
        "DepthSweep", "PAPER_RMSE_PERCENT", "PlacementTrial", "PositioningResult", "box_surface_distance",
        "depth_sweep", "evaluate_positioning", "feedback_profile", "place_by_feedback", "placement_error",
        "pose_error", "position_markdown", "random_pose_near", "rig_procam", "scan_distance", "scan_surface"],
}


def test_every_name_readme_calls_from_the_top_level_exists():
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    readme = "\n".join(p.read_text() for p in [root / "README.md", *sorted((root / "docs").glob("*.md"))])
    names = set(re.findall(r"`torchproj\.([A-Za-z_]\w*)", readme))
    assert names, "README names no torchproj.X"
    missing = sorted(n for n in names if not hasattr(torchproj, n))
    assert not missing, f"README names torchproj.{missing}, which do not exist"


def test_public_api_surface():
    for room, names in SURFACE.items():
        module = getattr(torchproj, room) if room else torchproj
        assert sorted(module.__all__) == sorted(names), room or "torchproj"
        for name in names:
            assert hasattr(module, name), f"{room or 'torchproj'}.{name}"


def test_help_lists_the_face_one_line_each():
    """``help(torchproj)`` opens with every top-level name, each on a line of its own group."""
    import re

    listed = set(re.findall(r"``(\w+)``", torchproj.__doc__))
    face = set(torchproj.__all__) - {"__version__"}
    assert face <= listed, f"help(torchproj) does not list {sorted(face - listed)}"
    assert all(len(line) <= 120 for line in torchproj.__doc__.splitlines())


def test_importing_torchproj_or_its_command_imports_no_torch():
    """The face is imported on first use: the command parses its arguments, and Ctrl-C is caught,
    before torch has been imported (a second or more)."""
    import subprocess
    import sys

    code = "import sys, torchproj, torchproj.cli; print('torch' in sys.modules); torchproj.ProjectionModel; " \
           "print('torch' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.split() == ["False", "True"]


def test_the_commands_parser_imports_no_torch_and_offers_the_librarys_choices():
    """``torchproj --help`` took seconds and 320 MB importing the library for its option lists; the
    lists live in core.choices, and each is the one the library uses."""
    import subprocess
    import sys

    code = "import sys; from torchproj.cli import build_parser; build_parser(); print('torch' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.split() == ["False"]
    from torchproj import calib, pipeline, solve, transport
    from torchproj.core import choices

    assert tuple(solve.SOLVERS) == choices.SOLVER_NAMES
    assert solve.OBJECTIVES is choices.OBJECTIVES and transport.FOOTPRINTS is choices.FOOTPRINTS
    assert pipeline.ORACLES is choices.ORACLES and calib.DIM_THRESHOLD == choices.DIM_THRESHOLD


def test_every_module_compiles_without_a_warning():
    """A string escape Python does not know (a docstring's ``\\ s``) compiles with a SyntaxWarning
    (a DeprecationWarning before 3.12), shown to a user of every process that compiles the module
    afresh (one that writes no bytecode) and an error in a later Python."""
    import warnings
    from pathlib import Path

    failures = []
    for path in sorted(Path(torchproj.__file__).parent.rglob("*.py")):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            try:
                compile(path.read_text(encoding="utf-8"), str(path), "exec")
            except (SyntaxError, SyntaxWarning, DeprecationWarning) as exc:
                failures.append(f"{path.name}: {exc}")
    assert not failures, "\n".join(failures)
