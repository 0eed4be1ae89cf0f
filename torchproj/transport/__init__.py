"""The sparse light-transport operator ``i = A p``: targets, building, row merging."""

from .build import StateCalibration, Target, build_transport, group_rows, target_on_camera
from .geometric import geometric_weights, normal_map, point_map, triangulate_rays
from .operator import TransportOperator, csr_from_coo

__all__ = ["StateCalibration", "Target", "TransportOperator", "build_transport", "csr_from_coo", "geometric_weights",
           "group_rows", "normal_map", "point_map", "target_on_camera", "triangulate_rays"]
