import torch

from torchproj.calib import calibrate_projector, fit_response, measure_ramp, ramp_pattern
from torchproj.pipeline import simulate_calibration
from torchproj.sim import VirtualRig

from ..helpers import small_scene


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


def test_measure_ramp_needs_a_lit_scene():
    import pytest

    from torchproj.core import InputError

    dark = torch.zeros(1, 10, 10)
    with pytest.raises(InputError, match="usable levels"):
        measure_ramp(dark, dark + 0.5, dark, torch.full((10, 10), float("nan")), 64)


def test_response_is_fitted_per_colour_channel():
    from ..helpers import small_config
    from torchproj.scene import parse_scene

    data = small_config(camera=(320, 240), channels=3)
    data["projectors"][0]["response"] = {"a": 1.0, "b": [1.8, 2.2, 2.6]}
    rig = VirtualRig(parse_scene(data))
    cal = calibrate_projector(simulate_calibration(rig, "far", 0), (256, 192))
    assert cal.response.b.shape == (3,)
    assert torch.allclose(cal.response.b, torch.tensor([1.8, 2.2, 2.6]), atol=0.05)
