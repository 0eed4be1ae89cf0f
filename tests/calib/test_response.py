import pytest
import torch

from torchproj.calib import calibrate_projector, fit_response, measure_ramp, ramp_pattern
from torchproj.core import InputError
from torchproj.pipeline import calibrate_virtual, simulate_calibration, simulate_scene
from torchproj.scene import parse_scene
from torchproj.sim import VirtualRig

from ..helpers import small_config, small_scene


def test_ramp_and_mirror_add_up_to_one():
    r, m = ramp_pattern(100, 4, 16), ramp_pattern(100, 4, 16, mirrored=True)
    assert torch.equal(r + m, torch.ones_like(r))
    assert r.min() == 0 and r.max() == 1 and len(torch.unique(r)) == 16


def test_fit_recovers_exact_parameters():
    x = torch.linspace(0, 1, 20)
    y = torch.stack([0.9 * x**2.3 + 0.02, 1.1 * x**1.8 + 0.0], -1)
    fit = fit_response(x, y)
    assert torch.allclose(fit.a, torch.tensor([0.9, 1.1]), atol=1e-4)
    assert torch.allclose(fit.b, torch.tensor([2.3, 1.8]), atol=1e-4)
    assert torch.allclose(fit.c, torch.tensor([0.02, 0.0]), atol=1e-4)


@pytest.mark.parametrize("levels, response, says", [
    (torch.linspace(0, 255, 9), torch.linspace(0, 1, 9) ** 2, r"levels must lie in \[0, 1\].*got \[0, 255\]"),
    ((torch.linspace(0, 1, 9) * 255).long(), torch.linspace(0, 1, 9) ** 2,
     "levels must be a float tensor, got torch.int64"),
    (torch.linspace(0, 1, 9), torch.zeros(9), "channel 0 does not rise with the level"),
    (torch.linspace(0, 1, 9), 1 - torch.linspace(0, 1, 9) ** 2, "channel 0 does not rise with the level"),
    (torch.linspace(0, 1, 9), torch.linspace(0, 1, 9).pow(2).index_fill(0, torch.tensor([4]), float("nan")),
     "response holds 1 non-finite"),
    (torch.tensor([0.0, 1.0]), torch.tensor([0.0, 1.0]), "2 levels cannot fit 3 unknowns"),
])
def test_a_response_no_curve_can_fit_is_refused_naming_why(levels, response, says):
    """Each of these gave a curve without a word (0-255 levels: a = 5e-6; a flat response: b = 6) or
    scipy's 'array must not contain infs or NaNs'."""
    with pytest.raises(InputError, match=says):
        fit_response(levels, response)


def test_a_curve_is_made_from_numbers_and_refused_where_it_does_not_rise():
    from torchproj.calib import ResponseCurve

    curve = ResponseCurve(1.0, [2.2], 0.0)  # numbers and lists become tensors
    y = torch.tensor([[[0.25]]])
    assert float(curve.to_pattern(y)) == pytest.approx(0.25 ** (1 / 2.2), rel=1e-6)
    for a, b, says in [(1.0, -2.0, "needs a > 0 and b > 0"), (0.0, 2.0, "needs a > 0 and b > 0"),
                       (1.0, float("nan"), "response b must be finite"), ("x", 2.0, "response a must be a number")]:
        with pytest.raises(InputError, match=says):
            ResponseCurve(a, b, 0.0)


def test_virtual_rig_response_fit_and_compensation():
    scene = small_scene(camera=(320, 240), projector=(256, 192))
    rig = VirtualRig(scene)
    for j, proj in enumerate(scene.projectors):
        cap = simulate_calibration(rig, "near", j)
        cal = calibrate_projector(cap, (256, 192))
        true_b = proj.response_b[0]
        assert abs(float(cal.response.b[0]) - true_b) < 0.05
        x = torch.linspace(0, 1, 101)
        fitted = cal.response.a[0] * x ** cal.response.b[0] + cal.response.c[0]
        assert float((fitted - x**true_b).abs().max()) < 0.015  # the normalised true curve
        # Compensated ramp + mirror is flat; the raw pair is not (x^b + (1-x)^b dips to 2^(1-b)).
        ramps = torch.cat([ramp_pattern(256, 192), ramp_pattern(256, 192, mirrored=True)])
        lit = cal.decoding.valid & ((cap.white - cap.black)[0] > 0.1)

        def summed(patterns):
            shot = rig.capture("near", {j: patterns})
            norm = (shot - cap.black) / (cap.white - cap.black).clamp_min(1e-3)
            return (norm[0] + norm[1])[0][lit]

        flat, raw = summed(cal.response.to_pattern(ramps)), summed(ramps)
        assert abs(float(flat.mean()) - 1) < 0.01 and float(flat.std()) < 0.03
        assert float(raw.std()) > 3 * float(flat.std()) and float(raw.min()) < 0.6


def test_a_narrow_projectors_ramp_keeps_the_middle_of_its_bars():
    """32 bars on 96 columns are 3 cells wide: a margin of 1.5 cells either side of a bar edge left
    no pixel of any bar, and calibration failed for want of a ramp."""
    scene = small_scene(camera=(200, 150), projector=(96, 72))
    cal = calibrate_virtual(scene, progress=False)
    for proj, response in zip(scene.projectors, cal.responses):
        assert abs(float(response.b[0]) - proj.response_b[0]) < 0.1


def test_measure_ramp_needs_a_lit_scene():
    import pytest

    from torchproj.core import InputError

    dark = torch.zeros(1, 10, 10)
    with pytest.raises(InputError, match="usable levels .*: 0 of the 100 camera pixels are decoded and that bright"):
        measure_ramp(dark, dark + 0.5, dark, torch.full((10, 10), float("nan")), 64)
    # Every pixel decoded, each on a bar's edge (a camera pixel as wide as a bar sees two): the
    # message tells this apart from a dark or undecoded capture.
    wide = torch.zeros(1, 10, 64)
    edges = (torch.arange(64) // 2 * 2).float().expand(10, 64)  # 64 columns, 32 bars of 2 cells
    with pytest.raises(InputError, match=r"640 of the 640 camera pixels are decoded and that bright, 0 of them clear "
                                         r"of an edge of the 2-cell bars.*as wide as a bar"):
        measure_ramp(wide + 0.25, wide + 0.5, wide, edges, 64)
    levels, _ = measure_ramp(wide + 0.25, wide + 0.5, wide, edges + 1, 64)  # the bars' middles
    assert len(levels) == 32


def test_response_is_fitted_per_colour_channel():
    from ..helpers import small_config
    from torchproj.scene import parse_scene

    data = small_config(camera=(320, 240), channels=3)
    data["projectors"][0]["response"] = {"a": 1.0, "b": [1.8, 2.2, 2.6]}
    rig = VirtualRig(parse_scene(data))
    cal = calibrate_projector(simulate_calibration(rig, "far", 0), (256, 192))
    assert cal.response.b.shape == (3,)
    assert torch.allclose(cal.response.b, torch.tensor([1.8, 2.2, 2.6]), atol=0.05)
    # The camera saw the primaries mixed (the default for a colour camera): the fit measured it, as
    # shares of each channel's white, and took it out of the ramp before fitting each primary's curve.
    from torchproj.core.conventions import DEFAULT_COLOUR_MIXING

    assert torch.allclose(cal.response.mixing, torch.tensor(DEFAULT_COLOUR_MIXING), atol=0.01)


def test_colour_mixing_is_measured_as_shares_of_white_and_undone_by_compensation():
    from torchproj.calib import fit_colour_mixing, primary_patterns
    from torchproj.calib.response import ResponseCurve
    from torchproj.scene import parse_scene

    from ..helpers import small_config

    mixing = [[0.6, 0.3, 0.0], [0.1, 0.7, 0.2], [0.0, 0.25, 0.9]]
    data = small_config("colour_two_planes", camera=(320, 240), projector=(128, 96))
    data["projectors"][1]["colour_mixing"] = mixing
    rig = VirtualRig(parse_scene(data))
    cap = simulate_calibration(rig, "near", 1)
    assert cap.primaries.shape == (3, 3, 240, 320)
    shares = torch.tensor(mixing) / torch.tensor(mixing).sum(1, keepdim=True)
    fitted = fit_colour_mixing(cap.primaries, cap.white, cap.black)
    assert torch.allclose(fitted, shares, atol=0.01) and torch.allclose(fitted.sum(1), torch.ones(3))
    # Compensation shows what the camera's channels should see: a pure green request is met in the
    # camera (the primaries' light is the mixing's inverse of it), not by green light alone.
    curve = ResponseCurve(torch.ones(3), torch.tensor([2.0, 2.2, 2.4]), torch.zeros(3), shares)
    want = (shares @ torch.tensor([0.2, 0.7, 0.4])).view(3, 1, 1).expand(3, 4, 5)  # a colour the primaries give
    x = curve.to_pattern(want)
    assert torch.allclose(curve(x), want, atol=1e-5)
    assert torch.allclose(curve.from_pattern(x), want, atol=1e-5)  # compensation undone, as the bench loop reads it
    offset = ResponseCurve(torch.full((3,), 0.8), curve.b, torch.full((3,), 0.05), shares)  # relative light: a, c aside
    assert torch.allclose(offset.from_pattern(offset.to_pattern(want)), want, atol=1e-5)
    assert not torch.allclose(x, want ** (1 / curve.b.view(3, 1, 1)), atol=0.01)
    # A colour no primaries give (a pure red the mixing always lifts green for) is clipped, not wrapped.
    assert float(curve.to_pattern(torch.tensor([1.0, 0.0, 0.0]).view(3, 1, 1)).min()) == 0.0
    # Too dark to measure: an error that says so.
    import pytest

    from torchproj.core import InputError

    with pytest.raises(InputError, match="lit well enough"):
        fit_colour_mixing(cap.primaries, cap.black + 0.01, cap.black)
    assert primary_patterns(4, 2)[1, :, 0, 0].tolist() == [0.0, 1.0, 0.0]



def test_a_grey_camera_writing_colour_files_is_told_so_not_a_singular_matrix(tmp_path):
    """A grey camera that saves its frames as colour files sees each primary alike in all three channels:
    the mixing's rows are equal, and its inverse (the primaries' curves from the grey ramp) ended in
    torch's "linalg.inv: ... the input matrix is singular" from inside the calibration. It is refused
    naming the cause and the fix, and through a capture folder naming the folder; a mixing given to a
    response curve in Python is checked as a bundle's is."""
    from torchproj.calib import ResponseCurve, calibrate_folders, fit_colour_mixing, write_graycode_folder
    from torchproj.core import CaptureError

    data = small_config("colour_two_planes", camera=(160, 120), projector=(64, 48))
    cap = simulate_calibration(VirtualRig(parse_scene(data)), "near", 0)
    grey = {name: (image.mean(-3, keepdim=True).expand_as(image).clone() if isinstance(image, torch.Tensor) else
                   [i.mean(-3, keepdim=True).expand_as(i).clone() for i in image] if isinstance(image, list) else image)
            for name, image in vars(cap).items()}
    grey = type(cap)(**grey)
    assert grey.primaries.shape == (3, 3, 120, 160) and torch.equal(grey.white[0], grey.white[2])
    says = "the camera's channels do not tell the projector's primaries apart"
    with pytest.raises(InputError, match=says):
        fit_colour_mixing(grey.primaries, grey.white, grey.black)
    with pytest.raises(InputError, match="save its captures in grey"):
        calibrate_projector(grey, (64, 48))
    write_graycode_folder(tmp_path / "near" / "upper", grey, bits=8)
    with pytest.raises(CaptureError, match=f"upper: {says}"):
        calibrate_folders(tmp_path, {"*": (64, 48)})
    for mixing in (torch.ones(3, 3) / 3, torch.rand(2), -torch.eye(3), [[1, 0, 0]] * 3):
        with pytest.raises(InputError, match=r"response mixing must be a \(3, 3\) tensor of shares >= 0"):
            ResponseCurve(1.0, 2.2, 0.0, mixing)
    assert torch.equal(ResponseCurve(1.0, 2.2, 0.0, torch.eye(3)).mixing, torch.eye(3))

def _narrow_far_plane(states):
    """The paper's rig, small, with a far plane a few of the ramp's 32 bars wide."""
    config = small_config(camera=(200, 150), projector=(128, 96))
    config["surfaces"]["far_plane"]["size"] = [0.04, 0.3]  # about two 2.1 cm bars at 1 m
    config["states"] = [{"name": s, "surfaces": [f"{s}_plane"]} for s in states]
    return parse_scene(config, name="narrow_far")


def test_a_state_whose_ramp_shows_few_bars_leaves_the_response_to_another():
    """A projector's response is the same in every state: a small object that sees only a couple of
    the ramp's bars leaves it to a state that sees more, in either order, and the report of
    ``torchproj simulate`` says so for that state; a projector no state fits is refused by name."""
    for order in (["near", "far"], ["far", "near"]):
        scene = _narrow_far_plane(order)
        fitted = calibrate_virtual(scene, progress=False).responses
        for response, proj in zip(fitted, scene.projectors):  # the near plane's ramp, whatever the order
            assert abs(float(response.b[0]) - proj.response_b[0]) < 0.05
    only = calibrate_projector(simulate_calibration(VirtualRig(_narrow_far_plane(["far"])), "far", 0), (128, 96),
                               require_response=False)
    assert only.response is None and "usable levels" in only.response_note
    with pytest.raises(InputError, match="projector 'upper': no state's ramp fits its response; in state 'far': "
                                         "the ramp capture shows only"):
        calibrate_virtual(_narrow_far_plane(["far"]), progress=False)


def test_simulate_reports_a_state_without_its_own_response(tmp_path):
    text = simulate_scene(_narrow_far_plane(["near", "far"]), tmp_path, progress=False)
    far = [line for line in text.splitlines() if line.startswith("| far |")]
    assert len(far) == 2 and all("none, too few ramp bars seen" in line for line in far)
    assert (tmp_path / "calibration.png").exists()


def test_a_normalised_ramp_fits_its_exponent_from_a_few_bars():
    """A normalised response is 0 at 0 and 1 at 1 by construction, and compensation uses the exponent
    alone: fitted as ``x^b``, four noisy levels from a narrow object (two bars of the ramp, two of its
    mirror) give b within 0.02; the paper's three free parameters trade it against a and c there."""
    g = torch.Generator().manual_seed(3)
    levels = torch.tensor([6, 7, 24, 25]) / 31.0
    measured = levels ** 2.3 + 0.004 * torch.randn(4, generator=g)
    anchored = fit_response(levels, measured, normalised=True)
    assert float(anchored.a[0]) == 1.0 and float(anchored.c[0]) == 0.0
    assert abs(float(anchored.b[0]) - 2.3) < 0.02
    free = fit_response(levels, measured)
    assert abs(float(free.b[0]) - 2.3) > 2 * abs(float(anchored.b[0]) - 2.3)


def test_the_mirrored_ramp_adds_the_levels_from_the_other_end():
    """A narrow plane off to the left sees the ramp's low bars only; with its mirror the same columns
    add the levels ``1 - k / 31``, and the exponent fitted from that state alone is the true one
    within 0.02."""
    config = small_config(camera=(200, 150), projector=(128, 96))
    config["surfaces"]["far_plane"].update(size=[0.1, 0.3], pose={"position": [-0.2, 0.0, 1.0]})
    scene = parse_scene(config, name="left_far")
    rig = VirtualRig(scene)
    for j, proj in enumerate(scene.projectors):
        cap = simulate_calibration(rig, "far", j)
        cal = calibrate_projector(cap, (128, 96))
        columns = cal.decoding.prj_xy[..., 0]
        alone, _ = measure_ramp(cap.ramp[0], cap.white, cap.black, columns, 128)
        both, _ = measure_ramp(cap.ramp[0], cap.white, cap.black, columns, 128, mirrored=cap.ramp[1])
        assert 4 <= len(alone) and float(alone.max()) < 0.4  # the low end only
        torch.testing.assert_close(both, torch.cat([alone, torch.flip(1 - alone, [0])]))
        assert abs(float(cal.response.b[0]) - proj.response_b[0]) < 0.02
