"""The 3D inspection scripts render off-screen and show what they should."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from torchproj.core import read_image
from torchproj.scene import load_scene

ROOT = Path(__file__).resolve().parents[1]


def _load(name):
    spec = importlib.util.spec_from_file_location(f"viz_{name}", ROOT / "viz" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def rig_module():
    pytest.importorskip("pyvista")
    return _load("rig")


def test_rig_view_draws_devices_and_surfaces(rig_module, tmp_path):
    images = {}
    for name in ("paper_two_planes", "box_cylinders"):
        out = tmp_path / f"{name}.png"
        rig_module.draw_rig(load_scene(name), out, window_size=(400, 300)).close()
        img = read_image(out)
        assert img.shape[1:] == (300, 400)
        images[name] = img
        # Not blank: the frusta (red) and surfaces (blue-ish) are drawn on the white background.
        rgb = img.numpy()
        red = (rgb[0] > 0.6) & (rgb[1] < 0.4) & (rgb[2] < 0.4)
        blue = (rgb[2] > rgb[0] + 0.2)
        assert red.sum() > 100 and blue.sum() > 500
    assert not np.array_equal(images["paper_two_planes"].numpy(), images["box_cylinders"].numpy())


def test_frustum_passes_through_the_image_corners(rig_module):
    scene = load_scene()
    p = scene.projectors[0]
    lines = rig_module.frustum(p.K, p.width, p.height, p.world_from_prj, depth=1.0)
    corner = lines.points[1]  # top-left image corner at depth 1 m along the optical axis
    local = (corner - p.centre) @ p.world_from_prj[:3, :3]
    assert local[2] == pytest.approx(1.0)
    assert p.fx * local[0] / local[2] + p.cx == pytest.approx(-0.5)
    assert p.fy * local[1] / local[2] + p.cy == pytest.approx(-0.5)
