"""The sparse light-transport operator ``i = A p``: targets, building, row merging, planar maps."""

from .build import (COLOUR_WEIGHTS, DEFAULT_FOOTPRINT, FOOTPRINTS, StateCalibration, Target, build_channel_transports,
                    build_transport, group_rows, has_colour_weights, map_slope, retarget_rhs, target_on_camera)
from .geometric import geometric_weights, normal_map, point_map, triangulate_rays
from .operator import TransportOperator, cell_blocks, csr_from_coo, normal_form
from .planar import MAPS, HomographyFit, fit_homography, homography_map, planar_calibration, select_maps

__all__ = ["COLOUR_WEIGHTS", "DEFAULT_FOOTPRINT", "FOOTPRINTS", "MAPS", "HomographyFit", "StateCalibration", "Target", "TransportOperator", "build_channel_transports", "build_transport", "cell_blocks", "csr_from_coo",
           "fit_homography", "geometric_weights", "group_rows", "has_colour_weights", "homography_map", "map_slope", "normal_form", "normal_map", "planar_calibration", "select_maps",
           "point_map", "retarget_rhs", "target_on_camera", "triangulate_rays"]
