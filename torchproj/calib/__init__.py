"""Calibration: Gray code and its decoding, correspondence maps, response fit, triangulation."""

from .acquire import OpenCVCamera, OpenCVDisplay, capture_sequence
from .bundle import BUNDLE_VERSION, CalibrationBundle, calibrate_folders, load_bundle, write_bundle, write_sequence
from .capture import DEFAULT_NAMES, GraycodeCapture, read_graycode_folder, write_graycode_folder
from .graycode import GrayDecoding, decode_gray, graycode_bits, graycode_patterns, refine_subpixel, sequence_bits
from .homography import HomographyFit, check_plane, fit_homography, homography_map
from .maps import fill_holes, inverse_map
from .pipeline import DecodedFolder, ProjectorCalibration, calibrate_projector, decode_folder
from .response import ResponseCurve, fit_response, measure_ramp, ramp_pattern
from .triangulate import ProCamCalibration, fit_plane, read_opencv_calibration, triangulate, triangulate_map, write_ply

__all__ = [
    "BUNDLE_VERSION",
    "CalibrationBundle",
    "DEFAULT_NAMES",
    "DecodedFolder",
    "GrayDecoding",
    "GraycodeCapture",
    "HomographyFit",
    "OpenCVCamera",
    "OpenCVDisplay",
    "ProCamCalibration",
    "ProjectorCalibration",
    "ResponseCurve",
    "calibrate_folders",
    "capture_sequence",
    "calibrate_projector",
    "check_plane",
    "decode_folder",
    "decode_gray",
    "fill_holes",
    "fit_homography",
    "fit_plane",
    "fit_response",
    "graycode_bits",
    "graycode_patterns",
    "homography_map",
    "inverse_map",
    "load_bundle",
    "measure_ramp",
    "ramp_pattern",
    "read_graycode_folder",
    "read_opencv_calibration",
    "refine_subpixel",
    "sequence_bits",
    "triangulate",
    "triangulate_map",
    "write_bundle",
    "write_graycode_folder",
    "write_ply",
    "write_sequence",
]
