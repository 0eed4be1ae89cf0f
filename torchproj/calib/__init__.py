"""Calibration: Gray code and its decoding, correspondence maps, response fit, triangulation, bundles.

The calibration types, and how they relate:

- :class:`ProjectorCalibration`: what one projector's capture folder in one state decodes to
  (:func:`calibrate_projector`): maps, inverse map, response curve.
- :class:`CalibrationBundle`: all of them for a real rig, as files (:func:`calibrate_folders`,
  :func:`write_bundle`, :func:`load_bundle`).
- :class:`~torchproj.pipeline.VirtualCalibration`: the same for the virtual rig, with the rig kept to
  evaluate on (:func:`~torchproj.pipeline.calibrate_virtual`).
- :class:`~torchproj.transport.StateCalibration`: what the transport operator needs of one state
  (a map and a weight per projector), made from either.
- :class:`ProCamCalibration`: OpenCV's camera-projector stereo calibration, for triangulation.
"""

from .blur import measure_blur
from .bundle import BUNDLE_VERSION, CalibrationBundle, calibrate_folders, load_bundle, write_bundle, write_sequence
from .capture import DEFAULT_NAMES, GraycodeCapture, read_graycode_folder, write_graycode_folder
from .graycode import (CREASE_RATIO, CURVE_RATIO, STRIPE_MARGIN, STRIPE_TOLERANCE, WIDE_SHARE, CellShares, GrayDecoding, band_pixels, capture_noise, cell_means, cell_shares, checker_patterns, checker_shares, decode_gray, graycode_bits, graycode_patterns, stripe_contrast,
                       refine_subpixel, stripe_shares, sequence_bits)
from .homography import HomographyFit, check_plane, fit_homography, homography_map
from .maps import fill_holes, inverse_map
from .edges import EdgePixels, find_edge_pixels
from .pipeline import (DIM_THRESHOLD, FEW_DECODED, NOISY_CAPTURES, SATURATED, SATURATED_SHARE, DecodedFolder,
                       ProjectorCalibration, calibrate_projector, decode_folder, scan_map, warn_if_few_decoded, warn_if_noisy,
                       warn_if_saturated)
from .response import ResponseCurve, fit_colour_mixing, fit_response, measure_ramp, primary_patterns, ramp_pattern
from .triangulate import (ProCamCalibration, fit_plane, largest_plane, read_opencv_calibration, triangulate,
                          triangulate_map, write_ply)

__all__ = [
    "BUNDLE_VERSION",
    "CalibrationBundle",
    "CREASE_RATIO",
    "CURVE_RATIO",
    "STRIPE_MARGIN",
    "STRIPE_TOLERANCE",
    "CellShares",
    "DEFAULT_NAMES",
    "DIM_THRESHOLD",
    "DecodedFolder",
    "FEW_DECODED",
    "NOISY_CAPTURES",
    "SATURATED",
    "SATURATED_SHARE",
    "GrayDecoding",
    "GraycodeCapture",
    "EdgePixels",
    "HomographyFit",
    "ProCamCalibration",
    "ProjectorCalibration",
    "ResponseCurve",
    "band_pixels",
    "calibrate_folders",
    "calibrate_projector",
    "scan_map",
    "cell_means",
    "cell_shares",
    "checker_patterns",
    "checker_shares",
    "check_plane",
    "decode_folder",
    "decode_gray",
    "fill_holes",
    "find_edge_pixels",
    "fit_colour_mixing",
    "fit_homography",
    "fit_plane",
    "fit_response",
    "graycode_bits",
    "graycode_patterns",
    "homography_map",
    "inverse_map",
    "largest_plane",
    "load_bundle",
    "measure_blur",
    "measure_ramp",
    "primary_patterns",
    "ramp_pattern",
    "read_graycode_folder",
    "read_opencv_calibration",
    "refine_subpixel",
    "sequence_bits",
    "stripe_contrast",
    "capture_noise",
    "stripe_shares",
    "triangulate",
    "triangulate_map",
    "write_bundle",
    "write_graycode_folder",
    "warn_if_few_decoded",
    "warn_if_noisy",
    "warn_if_saturated",
    "write_ply",
    "write_sequence",
]
