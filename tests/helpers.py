"""Test helpers: small versions of the built-in scenes, and the real captures' location."""

from __future__ import annotations

import copy
from pathlib import Path

import yaml

from torchproj.scene import builtin_config, parse_scene

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
CHESSBOARD = SHARED_DATA / "procam_chessboard"


def small_config(name: str = "paper_two_planes", camera=(400, 300), projector=(256, 192), **camera_overrides) -> dict:
    """A built-in scene's YAML data with every device scaled to a smaller resolution.

    Focal lengths scale with the width, so fields of view and the geometry stay those of the
    shipped scene.
    """
    data = yaml.safe_load(builtin_config(name).read_text())
    data = copy.deepcopy(data)
    for dev, (w, h) in [(data["camera"], camera)] + [(p, projector) for p in data["projectors"]]:
        scale = w / dev["resolution"][0]
        dev["focal"] = dev["focal"] * scale
        dev["resolution"] = [w, h]
    data["camera"].update(camera_overrides)
    return data


def small_scene(name: str = "paper_two_planes", camera=(400, 300), projector=(256, 192), **camera_overrides):
    return parse_scene(small_config(name, camera, projector, **camera_overrides), name=name)
