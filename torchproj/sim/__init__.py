"""The virtual rig: ray casting, shading, the camera model, capture of any image sequence."""

from .camera import apply_camera
from .primitives import Caster, make_caster
from .rig import StateGeometry, VirtualRig

__all__ = ["Caster", "StateGeometry", "VirtualRig", "apply_camera", "make_caster"]
