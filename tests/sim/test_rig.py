"""The virtual rig against independent float64 physics, and its capture mechanics."""

import math
import subprocess
import sys

import numpy as np
import pytest
import torch

from torchproj.core import InputError
from torchproj.scene import parse_scene
from torchproj.sim import VirtualRig

from ..helpers import small_config, small_scene


def _expected_radiance(scene, geo, patterns_value: dict[int, float]):
    """Radiance at pixel centres from the physics contract, in float64 numpy, from the cast points."""
    pts = geo.points.double().numpy().reshape(-1, 3)
    nrm = geo.normals.double().numpy().reshape(-1, 3)
    albedo = np.array([scene.surfaces[scene.states[0].surfaces[0]].albedo[0]])
    total = np.full(len(pts), scene.ambient) * albedo / math.pi
    for j, p in enumerate(scene.projectors):
        x = patterns_value.get(j, 0.0)
        rel = (pts - p.centre) @ p.world_from_prj[:3, :3]
        u = p.fx * rel[:, 0] / rel[:, 2] + p.cx
        v = p.fy * rel[:, 1] / rel[:, 2] + p.cy
        cu, cv = np.floor(u + 0.5), np.floor(v + 0.5)
        r2 = (cu - p.cx) ** 2 + (cv - p.cy) ** 2
        corners = np.array([[0, 0], [p.width - 1, 0], [0, p.height - 1], [p.width - 1, p.height - 1]])
        r2max = (((corners - [p.cx, p.cy]) ** 2).sum(1)).max()
        light = p.power * (p.response_a * x ** p.response_b[0] + p.black_level) * (1 - p.vignetting * r2 / r2max)
        to = p.centre - pts
        dist = np.linalg.norm(to, axis=1)
        cos = np.clip((nrm * to).sum(1) / dist, 0, None)
        inside = (cu >= 0) & (cu < p.width) & (cv >= 0) & (cv < p.height)
        total += np.where(inside, albedo / math.pi * light * cos / dist**2, 0)
    return total.reshape(geo.points.shape[:2])


def test_radiance_matches_the_physics_contract():
    scene = small_scene(supersampling=1)
    rig = VirtualRig(scene)
    state = scene.states[0].name
    geo = rig.geometry(state)
    prj = scene.projectors[0]
    white = torch.ones(1, 1, prj.height, prj.width)
    got = rig.radiance(state, {0: white * 0.7})[0, 0].double().numpy()
    want = _expected_radiance(scene, geo, {0: 0.7})
    on_surface = np.isfinite(geo.points.numpy()).all(-1)
    assert on_surface.mean() > 0.3
    np.testing.assert_allclose(got[on_surface], want[on_surface], rtol=2e-4)
    assert np.all(got[~on_surface] == 0)  # the background reflects nothing


def test_geometry_is_cast_once_per_state(monkeypatch):
    rig = VirtualRig(small_scene(supersampling=1))
    casts = []
    cast = rig._cast
    monkeypatch.setattr(rig, "_cast", lambda state: casts.append(state) or cast(state))
    first, again = rig.geometry("near"), rig.geometry("near")
    assert again is first
    rig.geometry("far")
    assert casts == ["near", "far"]  # one cast per state, the cache serves the rest
    fresh = VirtualRig(small_scene(supersampling=1)).geometry("near")  # the cache holds the cast's values
    for cached, recast in zip(again.prj_xy, fresh.prj_xy):
        torch.testing.assert_close(cached, recast, equal_nan=True)
    torch.testing.assert_close(again.points, fresh.points, equal_nan=True)
    rig.release("near")
    rig.geometry("near")
    assert casts == ["near", "far", "near"]  # released states are cast again


@pytest.mark.slow
def test_primitive_scenes_use_no_mesh_machinery():
    code = ("import torch, sys; from tests.helpers import small_scene; from torchproj.sim import VirtualRig; "
            "r = VirtualRig(small_scene('box_cylinders')); r.geometry('together'); "
            "print(any(m.startswith(('embreex', 'trimesh')) for m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def _segment_hits_cylinder(a, b, surf, steps=400):
    t = np.linspace(0.001, 0.999, steps)[:, None]
    p = a + t * (b - a) - surf.world_from_local[:3, 3]
    local = p @ surf.world_from_local[:3, :3]
    return bool(np.any((local[:, 0] ** 2 + local[:, 2] ** 2 <= surf.radius**2) & (np.abs(local[:, 1]) <= surf.height / 2)))


def test_shadows_match_an_independent_segment_test():
    scene = small_scene("box_cylinders", supersampling=1)
    rig = VirtualRig(scene)
    geo = rig.geometry("together")
    box = scene.states[0].surfaces.index("box")
    cylinders = [scene.surfaces[n] for n in ("cylinder_left", "cylinder_right")]
    on_box = (geo.surface_id == box).numpy()
    rng = np.random.default_rng(0)
    for j, p in enumerate(scene.projectors):
        lit = np.isfinite(geo.prj_xy[j].numpy()).all(-1)
        pts = geo.points.double().numpy()
        # Box points facing the projector and inside its image: unlit exactly where shadowed.
        rel = (pts - p.centre) @ p.world_from_prj[:3, :3]
        u = p.fx * rel[..., 0] / rel[..., 2] + p.cx
        v = p.fy * rel[..., 1] / rel[..., 2] + p.cy
        facing = (geo.normals.double().numpy() * (p.centre - pts)).sum(-1) > 0
        candidates = on_box & facing & (u > 0) & (u < p.width - 1) & (v > 0) & (v < p.height - 1)
        shadowed_idx = np.argwhere(candidates & ~lit)
        lit_idx = np.argwhere(candidates & lit)
        assert len(shadowed_idx) > 50, "the cylinders should shadow part of the box"
        for idx, expect in [(shadowed_idx, True), (lit_idx, False)]:
            pick = idx[rng.choice(len(idx), size=min(150, len(idx)), replace=False)]
            verdicts = [any(_segment_hits_cylinder(pts[r, c], p.centre, s) for s in cylinders) for r, c in pick]
            assert np.mean(np.array(verdicts) == expect) > 0.97
        # And the projector's light really does not reach the shadow.
        white = torch.ones(1, 1, p.height, p.width)
        diff = rig.radiance("together", {j: white})[0, 0] - rig.radiance("together", {})[0, 0]
        assert float(diff[torch.from_numpy(candidates & ~lit)].abs().max()) == 0.0


def test_semi_transparent_screen_passes_light_twice():
    """Behind a screen of transmittance t, light is dimmed once on the way in and once on the way out."""
    data = small_config("two_screens", supersampling=1)
    # One screen straight behind the other, so that the camera looks through the front one.
    data["surfaces"]["front_screen"].update(size=[0.40, 0.30], pose={"position": [0.0, 0.0, 0.8]})
    data["surfaces"]["back_screen"].update(size=[0.50, 0.375], pose={"position": [0.0, 0.0, 1.0]})
    data.pop("targets")
    t = data["surfaces"]["front_screen"]["transmittance"]
    both = VirtualRig(parse_scene(data))
    back_only = dict(data, states=[{"name": "s", "surfaces": ["back_screen"]}])
    front_only = dict(data, states=[{"name": "s", "surfaces": ["front_screen"]}])
    white = {0: torch.ones(1, 1, 192, 256)}

    def projected(rig, state):
        # White minus black: the projector's own light, without ambient light (which reaches the
        # back screen without crossing the front one).
        return rig.radiance(state, white)[0, 0] - rig.radiance(state, {})[0, 0]

    r_both = projected(both, "both")
    r_back = projected(VirtualRig(parse_scene(back_only)), "s")
    r_front = projected(VirtualRig(parse_scene(front_only)), "s")
    front_rig = VirtualRig(parse_scene(front_only))
    back_rig = VirtualRig(parse_scene(back_only))
    seen_through = torch.isfinite(front_rig.geometry("s").points).all(-1) & (r_back > 0)
    # Does the projector's light reach the back point through the front screen too? Intersect the
    # segment point -> projector with the front rectangle analytically.
    front = data["surfaces"]["front_screen"]
    z0, (w, h) = front["pose"]["position"][2], front["size"]
    pts = back_rig.geometry("s").points.double()
    centre = torch.tensor(parse_scene(data).projectors[0].centre)
    s_ = (z0 - pts[..., 2]) / (centre[2] - pts[..., 2])
    q = pts + s_[..., None] * (centre - pts)
    lit_through = (q[..., 0].abs() <= w / 2) & (q[..., 1].abs() <= h / 2)
    # Away from the screen's edges, where a pixel's footprint straddles them.
    interior = torch.nn.functional.max_pool2d((~seen_through).float()[None, None], 5, 1, 2)[0, 0] == 0
    factor = torch.where(lit_through, t * t, t)
    assert int((interior & lit_through).sum()) > 1000 and int((interior & ~lit_through).sum()) > 100
    edge = torch.nn.functional.max_pool2d(lit_through.float()[None, None], 3, 1, 1)[0, 0] != \
        -torch.nn.functional.max_pool2d(-lit_through.float()[None, None], 3, 1, 1)[0, 0]
    check = interior & ~edge
    torch.testing.assert_close(r_both[check], (r_front + factor * r_back)[check].float(), rtol=1e-4, atol=1e-7)


def test_capture_noise_follows_the_sensor_model():
    scene = small_scene(bit_depth=16, supersampling=1)
    rig = VirtualRig(scene)
    white = {0: torch.ones(1, 1, 192, 256)}
    clean = rig.capture("near", white, noise=False)[0, 0]
    a = rig.capture("near", white, seed=1)[0, 0]
    b = rig.capture("near", white, seed=2)[0, 0]
    assert torch.equal(a, rig.capture("near", white, seed=1)[0, 0])  # seeded: repeatable
    mask = (clean > 0.2) & (clean < 0.9)
    cam = scene.camera
    predicted = torch.sqrt(clean[mask] / cam.full_well + cam.read_noise**2)
    measured = (a - b)[mask] / math.sqrt(2)
    assert float(measured.std() / predicted.mean()) == pytest.approx(1.0, abs=0.05)


@pytest.mark.parametrize("bits", [16, 8])
def test_a_capture_of_several_frames_is_their_mean(bits):
    """camera.frames: 16 averages 16 frames, each with its own noise: the noise falls to a quarter,
    the expected image stays, and each frame is quantised before the mean (at 8 bits with this
    noise, the mean holds levels between one frame's)."""
    scene = small_scene(bit_depth=bits, supersampling=1)
    averaged = parse_scene(small_config(bit_depth=bits, supersampling=1, frames=16), name="averaged")
    white = {0: torch.ones(1, 1, 192, 256)}
    clean = VirtualRig(scene).capture("near", white, noise=False, quantise=False)[0, 0]
    mask = (clean > 0.2) & (clean < 0.9)
    spread = {}
    for world in (scene, averaged):
        rig = VirtualRig(world)
        a, b = rig.capture("near", white, seed=1)[0, 0], rig.capture("near", white, seed=2)[0, 0]
        spread[world.camera.frames] = float(((a - b)[mask] / math.sqrt(2)).std())
        assert abs(float((a - clean)[mask].mean())) < 2e-4  # no bias from averaging
    assert spread[16] / spread[1] == pytest.approx(0.25, abs=0.03)
    a = VirtualRig(averaged).capture("near", white, seed=1)[0, 0]
    peak = (1 << bits) - 1
    assert torch.allclose(torch.round(a * peak * 16) / (peak * 16), a, atol=1e-6)  # a mean of 16 quantised frames
    assert bits == 16 or not torch.equal(torch.round(a * peak) / peak, a)
    assert averaged.camera.stored_bits == 16 and scene.camera.stored_bits == bits
    assert "each capture the mean of 16 frames" in averaged.describe() and "frames" not in scene.describe()
    # Without noise every frame is the same image.
    assert torch.equal(VirtualRig(averaged).capture("near", white, noise=False), VirtualRig(scene).capture("near", white, noise=False))


def test_captures_are_quantised_to_the_bit_depth():
    rig = VirtualRig(small_scene())
    img = rig.capture("far", {1: torch.rand(2, 1, 192, 256)})
    assert img.shape == (2, 1, 300, 400)
    assert torch.equal(torch.round(img * 255) / 255, img)


def test_colour_camera_and_colour_patterns():
    scene = small_scene(channels=3, supersampling=1)
    scene.surfaces["near_plane"].albedo = (0.9, 0.5, 0.1)
    rig = VirtualRig(scene)
    red = torch.zeros(1, 3, 192, 256)
    red[:, 0] = 1
    img = rig.radiance("near", {0: red})[0]
    lit = img[0] > img[0].max() * 0.5
    # Green and blue only see black level and ambient light; red sees the projector.
    assert float(img[0][lit].mean()) > 5 * float(img[1][lit].mean())
    grey = rig.radiance("near", {0: torch.ones(1, 1, 192, 256)})[0]
    ratio = grey[:, lit].mean(1)
    assert float(ratio[0] / ratio[2]) == pytest.approx(9.0, rel=0.01)  # albedo 0.9 vs 0.1


def test_bad_patterns_get_clear_errors():
    rig = VirtualRig(small_scene())
    with pytest.raises(InputError, match="no projector 'left'"):
        rig.capture("near", {"left": torch.ones(1, 1, 192, 256)})
    with pytest.raises(InputError, match=r"patterns\['upper'\] must have shape \(N, C, 192, 256\)"):
        rig.capture("near", {"upper": torch.ones(1, 1, 100, 256)})
    with pytest.raises(InputError, match=r"patterns\['upper'\] must be float light in \[0, 1\], got torch.uint8"):
        rig.capture("near", {"upper": torch.full((1, 1, 192, 256), 255, dtype=torch.uint8)})
    with pytest.raises(InputError, match="patterns hold no image"):
        rig.capture("near", {"upper": torch.ones(0, 1, 192, 256)})
    for seed in (1.5, -1, 2 ** 70, True):
        with pytest.raises(InputError, match="seed must be a whole number"):
            rig.capture("near", {}, seed=seed)
    # A list ended in an AttributeError; light past white or black, or NaN, was shown all the same; a
    # projector given by name and by index took the last of the two without a word.
    with pytest.raises(InputError, match="patterns must be a dict of projector name .*, got list"):
        rig.capture("near", [torch.ones(1, 1, 192, 256)])
    for bad, says in [(1.5, r"\[0, 1.5\]"), (-0.5, r"\[-0.5, 0\]"), (float("nan"), r"\[nan, nan\]")]:
        light = torch.zeros(1, 1, 192, 256)
        light[0, 0, 5, 5] = bad
        with pytest.raises(InputError, match=rf"patterns\['upper'\] must be light in \[0, 1\] .*got values in {says}"):
            rig.capture("near", {"upper": light})
    with pytest.raises(InputError, match="patterns give projector 'upper' twice"):
        rig.capture("near", {"upper": torch.ones(1, 1, 192, 256), 0: torch.zeros(1, 1, 192, 256)})


def test_distorted_camera_rays_land_where_opencv_projects_them():
    import cv2

    scene = small_scene(supersampling=1, distortion=[-0.15, 0.04, 0.001, -0.0005, 0.0])
    geo = VirtualRig(scene).geometry("near")
    cam = scene.camera
    seen = torch.isfinite(geo.points).all(-1)
    pts = geo.points[seen].double().numpy()
    cam_from_world = np.linalg.inv(cam.world_from_cam)
    local = pts @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    uv, _ = cv2.projectPoints(local, np.zeros(3), np.zeros(3), cam.K, np.array(cam.distortion))
    ys, xs = torch.nonzero(seen, as_tuple=True)
    expected = np.stack([xs.numpy(), ys.numpy()], -1)
    assert seen.float().mean() > 0.3
    assert np.abs(uv[:, 0] - expected).max() < 0.02


def test_surface_mask_is_the_projected_outline_of_the_surface():
    from matplotlib.path import Path as Polygon

    scene = small_scene("two_screens", supersampling=1)
    rig = VirtualRig(scene)
    cam = scene.camera
    cam_from_world = np.linalg.inv(cam.world_from_cam)
    ys, xs = np.mgrid[0:cam.height, 0:cam.width]
    pixels = np.stack([xs.ravel(), ys.ravel()], 1)
    for name in ("front_screen", "back_screen"):
        surf = scene.surfaces[name]
        w, h = surf.size
        corners = np.array([[-w / 2, -h / 2, 0, 1], [w / 2, -h / 2, 0, 1], [w / 2, h / 2, 0, 1], [-w / 2, h / 2, 0, 1]])
        local = (cam_from_world @ surf.world_from_local @ corners.T)[:3]
        uv = (cam.K @ local)[:2] / local[2]
        inside = Polygon(uv.T).contains_points(pixels).reshape(cam.height, cam.width)
        mask = rig.surface_mask("both", [name]).numpy()
        # The side-by-side screens do not overlap in the camera: the mask is the whole outline,
        # up to the pixels its edge passes through.
        assert (mask != inside).mean() < 0.01 * inside.mean()
    assert not (rig.surface_mask("both", ["front_screen"]) & rig.surface_mask("both", ["back_screen"])).any()
    everything = rig.surface_mask("both")
    assert bool((everything == (rig.geometry("both").surface_id >= 0)).all())
    with pytest.raises(InputError, match="not present in state"):
        rig.surface_mask("both", ["near_plane"])
    rig.release("both")
    assert "both" not in rig._geometry


def test_rig_warns_when_camera_samples_cannot_resolve_projector_cells():
    import warnings

    from ..helpers import small_scene

    # Camera pixels larger than projector cells, as in box_positions: 2 x 2 samples are 0.59 cells apart.
    with pytest.warns(UserWarning, match="0.59 projector cells apart.*camera.supersampling to 3"):
        VirtualRig(small_scene("box_positions", camera=(200, 150), projector=(256, 192), supersampling=2))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        VirtualRig(small_scene("box_positions", camera=(200, 150), projector=(256, 192)))
        VirtualRig(small_scene("paper_two_planes"))


def _oblique_camera_scene(angle_deg: float) -> dict:
    """A projector facing a plane 1 m away (focal 200 px, cells 0.5 camera pixels wide at the same
    distance), and a narrow camera (focal 400 px, 2 x 2 samples) 1 m from the plane's centre, turned
    ``angle_deg`` about the vertical from the projector's axis."""
    angle = math.radians(angle_deg)
    return {"name": f"oblique_{angle_deg:g}", "seed": 0,
            "projectors": [{"name": "front", "resolution": [64, 48], "focal": 200,
                            "pose": {"position": [0.0, 0.0, 0.0], "look_at": [0.0, 0.0, 1.0]}}],
            "camera": {"resolution": [40, 30], "focal": 400, "supersampling": 2,
                       "pose": {"position": [math.sin(angle), 0.0, 1.0 - math.cos(angle)], "look_at": [0.0, 0.0, 1.0]}},
            "surfaces": {"wall": {"type": "rectangle", "size": [1.0, 1.0], "pose": {"position": [0.0, 0.0, 1.0]}}},
            "states": [{"name": "only", "surfaces": ["wall"]}]}


@pytest.mark.parametrize("angle_deg", [0.0, 40.0, 60.0])
def test_sample_spacing_follows_the_obliquity_the_focal_lengths_miss(angle_deg):
    """By hand: the projector faces the plane, so a step of s metres on it is 200 s cells; a camera
    pixel at distance 1 m seen at angle a spans 1 / (400 cos a) m of the plane across its width
    (1 / 400 up it). With 2 x 2 samples that is 0.25 / cos a cells between samples, where the focal
    lengths alone say 0.25 at every angle. Over the narrow camera's pixels the median is within 4%."""
    import warnings

    from torchproj.sim.rig import sample_spacing

    scene = parse_scene(_oblique_camera_scene(angle_deg))
    expected = 0.25 / math.cos(math.radians(angle_deg))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rig = VirtualRig(scene)
        geo = rig.geometry("only")
        rig.geometry("only")  # checked once per state
    spacing = sample_spacing(geo.prj_xy, geo.surface_id, 2)
    assert float(spacing[0]) == pytest.approx(expected, rel=0.04)
    said = [str(w.message) for w in caught if "apart" in str(w.message)]
    if expected <= 0.4:
        assert not said
    else:  # 0.5 cells: three samples a side bring them to 0.33
        assert len(said) == 1
        assert "state 'only'" in said[0] and "projector 'front'" in said[0] and "camera.supersampling to 3" in said[0]
        assert f"{float(spacing[0]):.2f} cells" in said[0]


def test_sample_spacing_leaves_out_steps_between_surfaces_and_unlit_pixels():
    """Two pixels on different surfaces, or one unlit, are no neighbours to measure: a map stepping
    1 cell a pixel down each column, whose columns alternate between two surfaces 50 cells apart,
    with NaN holes, gives 1 / samples (counted across the surfaces, every pixel would give 50)."""
    from torchproj.sim.rig import sample_spacing

    col = torch.arange(8)[None, :].expand(6, 8)
    row = torch.arange(6)[:, None].expand(6, 8)
    xy = torch.stack([col + 50.0 * (col % 2), row.float()], -1)
    xy[2, 2] = xy[4, 5] = float("nan")
    sid = (col % 2).clone()
    assert float(sample_spacing(xy[None], sid, 4)[0]) == 0.25
    assert torch.isnan(sample_spacing(torch.full((1, 6, 8, 2), float("nan")), sid, 4)[0])
    with pytest.raises(InputError, match="surface_id"):
        sample_spacing(xy[None], sid[:5], 4)


def test_sample_spacing_of_a_large_camera_reads_every_kth_pixel_with_its_own_neighbours():
    """A 1600 x 1200 camera is read at every third pixel of each axis, each still against its
    neighbours one pixel away: a map stepping 0.6 cells right and 0.55 down gives 0.6 / 3 samples,
    and a map whose step grows across the image gives the median of all its pixels within 0.001."""
    from torchproj.sim import rig as rig_module

    yy, xx = torch.meshgrid(torch.arange(1200.0), torch.arange(1600.0), indexing="ij")
    sid = torch.zeros(1200, 1600, dtype=torch.int64)
    affine = torch.stack([0.6 * xx, 0.55 * yy], -1)[None]
    assert float(rig_module.sample_spacing(affine, sid, 3)[0]) == pytest.approx(0.2, abs=1e-6)
    growing = torch.stack([0.6 * xx + 0.0003 * xx * yy, 0.55 * yy], -1)[None]
    read = float(rig_module.sample_spacing(growing, sid, 3)[0])
    right = (growing[0, :, 1:] - growing[0, :, :-1]).norm(dim=-1)[:-1]
    down = (growing[0, 1:] - growing[0, :-1]).norm(dim=-1)[:, :-1]
    exact = float(torch.maximum(right, down).median()) / 3
    assert read == pytest.approx(exact, abs=1e-3) and read != pytest.approx(0.2, abs=0.01)


def test_centre_geometry_is_the_cast_states_own_at_a_fraction_of_the_rays():
    """The pixel centres' truth cast alone (one ray a pixel, no transport) equals what a full cast
    of the state holds, field by field and bit for bit, and a state already cast gives its own."""
    scene = small_scene("box_positions", camera=(160, 120), projector=(128, 96), supersampling=3)
    first = VirtualRig(scene)
    alone = first.centre_geometry("near")
    assert not first._geometry  # nothing kept
    rig = VirtualRig(scene)
    cast = rig.geometry("near")
    for name in ("prj_xy", "points", "normals", "surface_id"):
        torch.testing.assert_close(alone[name], getattr(cast, name), rtol=0, atol=0, equal_nan=True)
    assert rig.centre_geometry("near")["prj_xy"] is cast.prj_xy


def test_colour_mixing_shows_each_primary_in_every_channel_by_its_share():
    # By hand: a camera channel c sees sum_p M[c, p] L_p of the primaries. Pure primary p less black
    # is M[c, p] K_c (a unit of light through channel c's geometry and albedo K_c), white less black
    # sum_p M[c, p] K_c, so their ratio is M[c, p] / sum_p M[c, p] at every lit pixel, whatever the
    # albedo, fall-off and vignetting.
    mixing = ((0.7, 0.2, 0.0), (0.1, 0.9, 0.2), (0.05, 0.1, 0.6))  # rows need not sum to 1
    data = small_config("colour_two_planes", supersampling=1)
    data["projectors"][0]["colour_mixing"] = [list(r) for r in mixing]
    rig = VirtualRig(parse_scene(data))
    h, w = rig.scene.projectors[0].height, rig.scene.projectors[0].width
    shots = rig.radiance("near", {0: torch.cat([torch.eye(3)[:, :, None, None].expand(3, 3, h, w),
                                                torch.ones(1, 3, h, w), torch.zeros(1, 3, h, w)])})
    black, white = shots[4], shots[3]
    lit = (white - black).min(0).values > 0.2 * (white - black).max()
    M = torch.tensor(mixing)
    for p in range(3):
        ratio = ((shots[p] - black) / (white - black))[:, lit]  # (3 channels, pixels)
        assert torch.allclose(ratio, (M[:, p] / M.sum(1))[:, None].expand_as(ratio), atol=1e-4)
    # Without mixing, red light reaches the red channel only.
    data["projectors"][0]["colour_mixing"] = "none"
    plain = VirtualRig(parse_scene(data)).radiance("near", {0: torch.cat([torch.eye(3)[:1, :, None, None].expand(1, 3, h, w),
                                                                          torch.zeros(1, 3, h, w)])})
    assert float((plain[0, 1:] - plain[1, 1:]).abs().max()) < 1e-6
    # The white channel's light is the row sum times the unmixed light: the ceiling's channel gain.
    gain = ((white - black) / (plain[0] - plain[1]).clamp_min(1e-9))[0, lit]
    assert float(gain.median()) == pytest.approx(float(M.sum(1)[0]), rel=1e-3)
    assert torch.allclose(rig.channel_gain(0), M.sum(1))
