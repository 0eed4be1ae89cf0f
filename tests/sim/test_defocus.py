"""Projector defocus against the thin-lens circle of confusion, written the way optics books give it."""

import math

import pytest
import torch

from torchproj.scene import parse_scene
from torchproj.sim import VirtualRig

CELL = (32, 24)  # the one lit cell, near the projector's principal point (31.5, 23.5)


def _scene(depth: float, focus: dict | None, supersampling: int = 2):
    """One 64x48 projector looking down +z at a wide plane ``depth`` metres away, and a camera beside
    it about ten pixels per projector cell, so the spot of one lit cell covers hundreds of pixels."""
    projector = {"name": "p", "resolution": [64, 48], "focal": 96, "black_level": 0.0,
                 "pose": {"position": [0, 0, 0], "look_at": [0, 0, 1]}}
    if focus is not None:
        projector["focus"] = focus
    return parse_scene({
        "name": "defocus", "ambient": 0.0, "projectors": [projector],
        "camera": {"resolution": [320, 240], "focal": 960, "supersampling": supersampling,
                   "pose": {"position": [0.02, 0, 0], "look_at": [0, 0, depth]}},
        "surfaces": {"wall": {"type": "rectangle", "size": [3, 3], "pose": {"position": [0, 0, depth]}}},
        "states": [{"name": "s", "surfaces": ["wall"]}]})


def _spot(depth: float, focus: dict | None):
    """The light of the one lit cell on the camera, and the projector coordinate each pixel sees."""
    rig = VirtualRig(_scene(depth, focus))
    pattern = torch.zeros(1, 1, 48, 64)
    pattern[..., CELL[1], CELL[0]] = 1
    light = (rig.radiance("s", {"p": pattern}) - rig.radiance("s", {}))[0, 0].double()
    return light, rig.geometry("s").prj_xy[0].double()


def _thin_lens_diameter(depth: float, focus: float, aperture: float, fx: float, lens_focal: float = 0.02) -> float:
    """Circle of confusion in LCD cells: a lens of focal length F focused at z_f puts the LCD at
    v = F z_f / (z_f - F), where a cell spans v / fx metres; a point at depth z is blurred over
    ``A F |z - z_f| / (z (z_f - F))`` metres of the LCD. The result does not depend on F."""
    v = lens_focal * focus / (focus - lens_focal)
    blur = aperture * lens_focal * abs(depth - focus) / (depth * (focus - lens_focal))
    return blur / (v / fx)


@pytest.mark.parametrize("depth, focus, aperture_mm", [(1.0, 0.5, 20), (1.0, 0.5, 10), (0.6, 1.2, 25)])
def test_a_defocused_cell_spreads_over_the_thin_lens_circle_of_confusion(depth, focus, aperture_mm):
    light, prj_xy = _spot(depth, {"distance": focus, "aperture": aperture_mm})
    want = _thin_lens_diameter(depth, focus, aperture_mm / 1000, fx=96)
    ok = light > 0
    weight = light[ok] / light[ok].sum()
    offset = prj_xy[ok] - torch.tensor(CELL, dtype=torch.float64)
    variance = (weight[:, None] * offset**2).sum(0)  # per axis
    # A uniform disc of diameter D has variance D^2 / 16 per axis; the cell itself adds 1/12 and the
    # camera pixel (a tenth of a cell) 1/1200.
    got = (16 * (variance - 1 / 12 - 1 / 1200)).clamp_min(0).sqrt()
    assert got.tolist() == pytest.approx([want, want], rel=0.05)
    # All of the cell's light still arrives: blur moves it, it does not lose it.
    sharp, _ = _spot(depth, None)
    assert float(light.sum()) == pytest.approx(float(sharp.sum()), rel=0.01)


def test_a_lens_focused_on_the_surface_is_sharp():
    light, prj_xy = _spot(0.8, {"distance": 0.8, "aperture": 30})
    sharp, _ = _spot(0.8, None)
    torch.testing.assert_close(light, sharp)
    lit = prj_xy[light > 0]
    assert (lit - torch.tensor(CELL, dtype=torch.float64)).abs().max() <= 0.5 + 0.1  # the cell and a pixel


def test_capture_of_placed_surfaces_blurs_as_the_cast_transport():
    """``capture_surfaces`` (objects that move) samples the same circles of confusion as ``capture``."""
    scene = _scene(1.0, {"distance": 0.5, "aperture": 20})
    rig = VirtualRig(scene)
    pattern = (torch.rand(1, 1, 48, 64, generator=torch.Generator().manual_seed(0)) > 0.5).float()
    cast = rig.capture("s", {"p": pattern}, noise=False, quantise=False)[0].reshape(1, -1)
    placed = rig.capture_surfaces(list(scene.surfaces.values()), {"p": pattern}, noise=False)
    assert float((placed - cast).abs().max()) <= 1.5 / 255  # the placed capture is quantised
    assert not math.isclose(float(cast.std()), 0.0)
