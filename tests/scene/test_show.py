"""The show: section: a world changed after calibration, parsed, validated and rendered as described."""

import copy

import numpy as np
import pytest
import torch

from torchproj.core.errors import ConfigError
from torchproj.scene import parse_scene, shown_scene
from torchproj.sim import VirtualRig

from ..helpers import small_config


def scene_with(show, **kwargs):
    data = small_config(camera=(80, 60), projector=(64, 48), **kwargs)
    data["show"] = show
    return parse_scene(data, name="small")


def test_a_scene_without_show_is_shown_as_calibrated():
    data = small_config(camera=(80, 60), projector=(64, 48))
    scene = parse_scene(data, name="small")
    assert scene.show is None and shown_scene(scene) is scene


def test_the_changes_land_where_the_section_says():
    scene = scene_with({"projectors": {"upper": {"translation_mm": [2, -1, 0.5], "gain": 1.25, "exponent": 1.1},
                                       "lower": {"rotation_deg": [0, 0.3, 0]}},
                        "camera": {"translation_mm": [0, 0, 3]}, "ambient": 0.07})
    shown = shown_scene(scene)
    upper, lower = scene.projectors
    s_upper, s_lower = shown.projectors
    assert np.allclose(s_upper.centre - upper.centre, [0.002, -0.001, 0.0005])
    assert np.allclose(s_upper.world_from_prj[:3, :3], upper.world_from_prj[:3, :3])
    assert s_upper.power == pytest.approx(upper.power * 1.25)
    assert s_upper.response_b == pytest.approx(tuple(b * 1.1 for b in upper.response_b))
    # Turned about its own centre, in its own frame: the centre stays, the axis turns by 0.3 degrees.
    assert np.allclose(s_lower.centre, lower.centre)
    cos = float(s_lower.world_from_prj[:3, 2] @ lower.world_from_prj[:3, 2])
    assert np.degrees(np.arccos(min(cos, 1.0))) == pytest.approx(0.3, abs=1e-6)
    assert np.allclose(shown.camera.world_from_cam[:3, 3], scene.camera.world_from_cam[:3, 3] + [0, 0, 0.003])
    assert shown.ambient == 0.07 and shown.show is None
    assert scene.projectors[0].power == upper.power  # the calibrated scene is untouched


def test_gain_and_exponent_change_the_emitted_light_by_hand():
    # a x^b + black, times power and vignetting: at x = 0.5 the shown projector emits
    # power g (a 0.5^(b e) + black) where the calibrated one emits power (a 0.5^b + black).
    scene = scene_with({"projectors": {"upper": {"gain": 2.0, "exponent": 1.2}}})
    p = scene.projectors[0]
    before, after = VirtualRig(scene), VirtualRig(shown_scene(scene))
    half = torch.full((1, 1, p.height, p.width), 0.5)
    centre = (p.height // 2) * p.width + p.width // 2
    vignette = float(before.emitted(0, half)[0, 0, centre]) / (p.power * (p.response_a * 0.5 ** p.response_b[0]
                                                                          + p.black_level))
    expected = 2.0 * p.power * (p.response_a * 0.5 ** (p.response_b[0] * 1.2) + p.black_level) * vignette
    assert float(after.emitted(0, half)[0, 0, centre]) == pytest.approx(expected, rel=1e-5)


def test_a_camera_moved_sideways_sees_the_plane_shifted_by_f_t_over_z():
    # A plane facing the camera at depth z: moving the camera by t along x moves the plane's image by
    # -f t / z pixels, so each shown pixel sees what the calibrated pixel s = f t / z to its right saw.
    data = small_config(camera=(120, 90), projector=(64, 48))
    data["camera"]["pose"] = {"position": [0.0, 0.0, 0.0]}
    data["camera"]["supersampling"] = 4
    data["surfaces"]["near_plane"]["size"] = [1.0, 1.0]
    focal = data["camera"]["focal"]
    z = data["surfaces"]["near_plane"]["pose"]["position"][2]
    shift = 3
    t_mm = shift * z / focal * 1000
    data["show"] = {"camera": {"translation_mm": [t_mm, 0, 0]}}
    scene = parse_scene(data, name="small")
    before = VirtualRig(scene).geometry("near").prj_xy[0].view(90, 120, 2)
    after = VirtualRig(shown_scene(scene)).geometry("near").prj_xy[0].view(90, 120, 2)
    a, b = after[:, :-shift], before[:, shift:]
    both = torch.isfinite(a).all(-1) & torch.isfinite(b).all(-1)
    assert int(both.sum()) > 1000
    assert float((a - b)[both].norm(dim=-1).median()) < 0.02
    unshifted = (after[:, :-shift] - before[:, :-shift])[both].norm(dim=-1).median()
    assert float(unshifted) > 0.5  # the test can tell a shift from none


@pytest.mark.parametrize("show, where, message", [
    ({"projectors": {"nope": {"gain": 2}}}, "show.projectors.nope", "known: ['upper', 'lower']"),
    ({"projectors": {"upper": {"translation_mm": [500, 0, 0]}}}, "show.projectors.upper.translation_mm",
     "more than a drift"),
    ({"projectors": {"upper": {"rotation_deg": [0, 45, 0]}}}, "show.projectors.upper.rotation_deg", "more than a drift"),
    ({"projectors": {"upper": {"exponent": 3}}}, "show.projectors.upper.exponent", "outside [0.2, 5.0]"),
    ({"projectors": {"upper": {"gain": 0}}}, "show.projectors.upper.gain", ""),
    ({"projectors": {"upper": {"gian": 2}}}, "show.projectors.upper.gian", "did you mean 'gain'?"),
    ({"camra": {"translation_mm": [1, 0, 0]}}, "show.camra", "did you mean 'camera'?"),
    ({"camera": {"translation_mm": [1, 0]}}, "show.camera.translation_mm", ""),
    ({"ambient": -1}, "show.ambient", ""),
    ({}, "show", "changes nothing"),
    ({"projectors": []}, "show.projectors", ""),
])
def test_bad_show_sections_name_the_field(show, where, message):
    with pytest.raises(ConfigError) as err:
        scene_with(copy.deepcopy(show))
    assert where in str(err.value) and message in str(err.value)


def test_the_changes_are_said_in_words_naming_only_what_changed():
    """``torchproj scene`` and the reports printed the section as a dict, every default zero in it."""
    from torchproj.scene.show import describe_show

    data = small_config()
    data["show"] = {"projectors": {"upper": {"translation_mm": [1.5, 0, 0], "gain": 1.12}, "lower": {"exponent": 1.05}},
                    "camera": {"rotation_deg": [0, 0.2, 0]}, "ambient": 0.05}
    scene = parse_scene(data)
    said = describe_show(scene.show.as_dict())
    assert said == ("projector upper: moved [1.5, 0.0, 0.0] mm, light x1.12; projector lower: response exponent x1.05; "
                    "camera: turned [0.0, 0.2, 0.0] degrees; room light 0.05 W/m^2")
    assert f"  shown after calibration with changes: {said}" in scene.describe().splitlines()
    assert describe_show({"projectors": {"upper": {"translation_mm": [0, 0, 0], "gain": 1.0}}}) == "projector upper: unchanged"
