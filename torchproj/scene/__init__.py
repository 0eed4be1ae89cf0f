"""Rig and scene descriptions: YAML configs loaded into validated dataclasses."""

from .config import (
    BUILTIN_SCENES,
    SIZE_LIMIT,
    Camera,
    Projector,
    Scene,
    State,
    Surface,
    TargetSpec,
    builtin_config,
    config_dir,
    load_scene,
    parse_scene,
    scale_config,
)
from .pose import look_at, rotation_from_euler_deg, rotation_from_rotvec
from .procedural import procedural_config, procedural_scene, suite_names
from .show import ShowChanges, shown_scene

__all__ = [
    "BUILTIN_SCENES",
    "SIZE_LIMIT",
    "ShowChanges",
    "Camera",
    "Projector",
    "Scene",
    "State",
    "Surface",
    "TargetSpec",
    "builtin_config",
    "config_dir",
    "load_scene",
    "look_at",
    "parse_scene",
    "procedural_config",
    "procedural_scene",
    "rotation_from_euler_deg",
    "rotation_from_rotvec",
    "scale_config",
    "shown_scene",
    "suite_names",
]
