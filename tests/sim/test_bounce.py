"""One bounce between surfaces, against the same light integrated cell by cell by hand."""

import math

import numpy as np
import pytest
import torch

from torchproj.core import ConfigError, InputError
from torchproj.scene import parse_scene
from torchproj.sim import VirtualRig

WALL, FLOOR = 0.8, 0.6  # albedos

# The corner's camera is coarse for its projector (a warning says so); the bounce is smooth, so it does not matter here.
pytestmark = pytest.mark.filterwarnings("ignore:scene 'corner'")


def corner(interreflection=True, occluder=False) -> dict:
    """A wall at z = 1 m and a floor 0.25 m below the projector's axis (y down): a concave corner. The
    projector, level with its axis, lights the wall only; the camera, above, looks down at both."""
    surfaces = {
        "wall": {"type": "rectangle", "size": [1.2, 1.0], "pose": {"position": [0.0, 0.0, 1.0]}, "albedo": WALL},
        "floor": {"type": "rectangle", "size": [1.2, 0.8], "pose": {"position": [0.0, 0.25, 0.6], "euler_deg": [90, 0, 0]},
                  "albedo": FLOOR},
    }
    if occluder:
        surfaces["post"] = {"type": "box", "size": [0.06, 0.15, 0.06], "pose": {"position": [0.0, 0.175, 0.8]},
                            "albedo": 0.5}
    return {
        "name": "corner", "interreflection": interreflection,
        "projectors": [{"name": "p", "resolution": [256, 192], "focal": 384, "pose": {"position": [0.0, -0.1, 0.0],
                        "look_at": [0.0, -0.1, 1.0]}, "response": {"a": 1.0, "b": 1.0}, "black_level": 0.01}],
        "camera": {"resolution": [160, 120], "focal": 120, "pose": {"position": [0.1, -0.2, 0.05],
                   "look_at": [0.0, 0.2, 0.8]}, "supersampling": 2},
        "surfaces": surfaces,
        "states": [{"name": "s", "surfaces": list(surfaces)}],
    }


BLOCK = (slice(176, 184), slice(128, 136))  # one 8 x 8 block of cells (a source block: 256 / 32 = 8 wide)


def by_hand(scene, points: np.ndarray) -> np.ndarray:
    """Floor radiance at ``points`` (M, 3) from the lit block, each of its 64 cells by itself: cell c sends
    intensity L = power a into solid angle cos^3 / (f_x f_y) towards the wall point its centre ray meets;
    that point reflects rho_wall of it as a Lambertian patch; the floor point receives
    I cos_out cos_in / r^2 and shows rho_floor / pi of that."""
    proj = scene.projectors[0]
    centre = proj.centre
    rotation = proj.world_from_prj[:3, :3]
    total = np.zeros(len(points))
    for v in range(BLOCK[0].start, BLOCK[0].stop):
        for u in range(BLOCK[1].start, BLOCK[1].stop):
            local = np.array([(u - proj.cx) / proj.fx, (v - proj.cy) / proj.fy, 1.0])
            cos = 1 / np.linalg.norm(local)
            d = rotation @ (local * cos)
            y = centre + d * (1.0 - centre[2]) / d[2]  # on the wall z = 1
            flux = proj.power * proj.response_a * cos**3 / (proj.fx * proj.fy)
            span = points - y
            r2 = (span**2).sum(1)
            w = span / np.sqrt(r2)[:, None]
            cos_out = np.clip(w @ np.array([0, 0, -1.0]), 0, None)  # the wall faces the projector: -z
            cos_in = np.clip(-(w @ np.array([0, -1.0, 0])), 0, None)  # the floor faces up: -y
            total += WALL * flux * cos_out * cos_in / (math.pi * r2)
    return FLOOR / math.pi * total


def lit_block():
    on = torch.zeros(2, 1, 192, 256)
    on[0, :, BLOCK[0], BLOCK[1]] = 1.0
    return on


def test_one_bounce_matches_the_light_integrated_cell_by_cell():
    scene = parse_scene(corner())
    rig = VirtualRig(scene)
    shots = rig.radiance("s", {0: lit_block()})
    bounced = (shots[0] - shots[1])[0]  # the block's light alone: black level and ambient cancel
    geo = rig.geometry("s")
    floor = geo.surface_id == scene.state("s").surfaces.index("floor")
    points = geo.points[floor].double().numpy()
    want = by_hand(scene, points)
    got = bounced[floor].double().numpy()
    # Where the floor receives a useful amount (it falls off as 1 / r^2 from the wall's spot).
    strong = want > 0.05 * want.max()
    assert strong.sum() > 500
    assert np.median(np.abs(got[strong] / want[strong] - 1)) < 0.01
    assert np.percentile(np.abs(got[strong] / want[strong] - 1), 95) < 0.04
    # The projector lights the wall, not the floor: without the bounce the floor sees nothing of the block.
    plain = VirtualRig(parse_scene(corner(interreflection=False))).radiance("s", {0: lit_block()})
    assert float((plain[0] - plain[1])[0][floor].abs().max()) < 1e-9
    # The wall does not light itself (a plane is convex): its own pixels gain nothing but the direct light.
    wall = geo.surface_id == 0
    assert torch.allclose((shots[0] - shots[1])[0][wall], (plain[0] - plain[1])[0][wall], atol=1e-7)


def test_a_post_in_the_way_shadows_the_bounce():
    rig = VirtualRig(parse_scene(corner(occluder=True)))
    shots = rig.radiance("s", {0: lit_block()})
    bounced = (shots[0] - shots[1])[0]
    geo = rig.geometry("s")
    floor = geo.surface_id == 1
    points = geo.points[floor].double().numpy()
    # Floor points the post hides from the block's spot on the wall get none of its light.
    spot = np.array([0.0, -0.1 + (179.5 - 95.5) / 384, 1.0])
    hidden = np.zeros(len(points), dtype=bool)
    for i, x in enumerate(points):  # the segment to the spot passes inside the post's box
        s = np.linspace(0.02, 0.98, 200)[:, None]
        p = x + s * (spot - x) - np.array([0.0, 0.175, 0.8])
        hidden[i] = bool((np.abs(p) <= np.array([0.03, 0.075, 0.03])).all(1).any())
    assert hidden.sum() > 20
    seen = bounced[floor].numpy()
    assert np.median(seen[hidden]) < 0.1 * np.median(seen[~hidden & (seen > 0)])


def test_interreflection_options_are_checked():
    data = corner()
    data["interreflection"] = "yes"
    with pytest.raises(ConfigError, match="interreflection: must be true or false"):
        parse_scene(data)
    data = corner()
    data["surfaces"]["wall"].update(transmittance=0.3)
    with pytest.raises(ConfigError, match="interreflection: is simulated between opaque surfaces"):
        parse_scene(data)
    assert "interreflection: one bounce" in parse_scene(corner()).describe()
    rig = VirtualRig(parse_scene(corner()))
    with pytest.raises(InputError, match="direct light only"):
        rig.capture_surfaces(list(rig.scene.surfaces.values()), {0: torch.ones(1, 1, 192, 256)})
