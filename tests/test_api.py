"""The public API surface: a change here is a change users feel, so it is made on purpose."""

import torchproj.calib
import torchproj.evaluate
import torchproj.core
import torchproj.scene
import torchproj.sim
import torchproj.solve
import torchproj.transport

SURFACE = {
    "core": ["CaptureError", "ConfigError", "InputError", "TorchprojError", "atomic_output", "check", "check_finite",
             "check_image", "check_shape", "pixel_grid", "read_image", "round_to_pixel", "to_uint", "write_image",
             "write_json"],
    "scene": ["BUILTIN_SCENES", "Camera", "Projector", "Scene", "State", "Surface", "TargetSpec", "builtin_config", "load_scene",
              "look_at", "parse_scene", "rotation_from_euler_deg", "rotation_from_rotvec"],
    "sim": ["Caster", "StateGeometry", "VirtualRig", "apply_camera", "make_caster"],
    "calib": ["BUNDLE_VERSION", "CalibrationBundle", "DEFAULT_NAMES", "DecodingError", "GrayDecoding", "GraycodeCapture",
              "HomographyFit", "OpenCVCamera", "OpenCVDisplay", "ProCamCalibration",
              "ProjectorCalibration", "ResponseCurve", "calibrate_folders", "calibrate_projector", "capture_sequence",
              "check_plane", "decode_gray", "decoding_error", "fill_holes", "fit_homography", "fit_plane", "fit_response",
              "graycode_bits", "graycode_patterns", "homography_map", "inverse_map", "load_bundle", "measure_ramp",
              "ramp_pattern", "read_graycode_folder", "read_opencv_calibration", "refine_subpixel", "sequence_bits",
              "simulate_calibration", "triangulate", "write_bundle", "write_graycode_folder", "write_ply", "write_sequence"],
    "transport": ["HomographyFit", "StateCalibration", "Target", "TransportOperator", "build_transport", "cell_blocks",
                  "csr_from_coo",
                  "fit_homography", "geometric_weights", "group_rows", "homography_map", "normal_map",
                  "planar_calibration", "point_map", "target_on_camera", "triangulate_rays"],
    "solve": ["ClampedAdam", "SOLVERS", "SolveResult", "check_bounds", "compensate", "component_chains",
              "epipolar_chains", "fundamental_between_projectors", "make_patterns", "solve_adam", "solve_eo", "solve_fista",
              "solve_gain_offset", "solve_lf", "solve_patterns", "solve_pgd", "to_projectable"],
    "evaluate": ["DepthSweep", "PAPER_RMSE_PERCENT", "PlacementTrial", "PositioningResult", "RunResult",
                 "VirtualCalibration", "box_surface_distance", "calibrate_virtual", "crosstalk", "default_images",
                 "depth_sweep", "evaluate_positioning", "feedback_profile", "masked_ssim", "model_space_psnr",
                 "place_by_feedback", "pose_error", "psnr", "random_pose_near", "rig_procam", "run_virtual",
                 "scan_distance", "scan_surface", "scene_images", "target_image"],
}


def test_public_api_surface():
    for room, names in SURFACE.items():
        module = getattr(torchproj, room)
        assert sorted(module.__all__) == sorted(names), room
        for name in names:
            assert hasattr(module, name), f"{room}.{name}"
