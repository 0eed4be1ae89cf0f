"""Defocus measured from Gray-code captures against the virtual rig's known thin lens."""

import pytest
import torch

from torchproj.calib import calibrate_projector, measure_blur
from torchproj.core.errors import InputError
from torchproj.pipeline import simulate_calibration
from torchproj.scene import parse_scene
from torchproj.sim import VirtualRig
from torchproj.transport import StateCalibration, Target, build_transport

PROJECTOR = (128, 96)


def _rig(focus: dict | None, size: tuple[int, int] = PROJECTOR) -> VirtualRig:
    """A 128x96 projector (or ``size``, the same cells) facing a wall 1 m away, a camera beside it at
    about 2.5 pixels per cell."""
    projector = {"name": "p", "resolution": list(size), "focal": 192, "black_level": 0.01,
                 "pose": {"position": [0, 0, 0], "look_at": [0, 0, 1]}}
    if focus is not None:
        projector["focus"] = focus
    return VirtualRig(parse_scene({
        "name": "blur", "seed": 1, "ambient": 0.01, "projectors": [projector],
        "camera": {"resolution": [320, 240], "focal": 480, "supersampling": 2,
                   "noise": {"full_well": 20000, "read": 0.002}, "bit_depth": 8,
                   "pose": {"position": [0.05, 0, 0], "look_at": [0, 0, 1]}},
        "surfaces": {"wall": {"type": "rectangle", "size": [1.2, 0.9], "pose": {"position": [0, 0, 1]}}},
        "states": [{"name": "s", "surfaces": ["wall"]}]}))


def _measured(rig: VirtualRig, size: tuple[int, int] = PROJECTOR):
    capture = simulate_calibration(rig, "s", 0)
    cal = calibrate_projector(capture, size)
    return cal, measure_blur(capture.patterns, capture.white, capture.black, cal.prj_xy, size)


# Focused at 0.5 m through a 20 mm aperture, the wall at 1 m gets f A |1/0.5 - 1/1| = 3.84 cells.
@pytest.mark.parametrize("focus, want", [(None, 0.0), ({"distance": 1.0, "aperture": 20}, 0.0),
                                         ({"distance": 0.5, "aperture": 20}, 3.84),
                                         ({"distance": 0.5, "aperture": 10}, 1.92)])
def test_measured_blur_recovers_the_thin_lens_circle_of_confusion(focus, want):
    rig = _rig(focus)
    assert rig.scene.projectors[0].blur_diameter(1.0)[0] == pytest.approx(want, abs=0.01)
    cal, blur = _measured(rig)
    known = torch.isfinite(blur)
    # Every mapped pixel gets a diameter, and they agree with the lens to half a cell.
    assert bool(known[torch.isfinite(cal.prj_xy).all(-1)].float().mean() > 0.95)
    assert float(blur[known].median()) == pytest.approx(want, abs=0.5)
    assert float((blur[known] - want).abs().quantile(0.9)) <= 1.0


def test_a_projector_of_few_rows_is_measured_on_the_bits_it_has():
    """An 8-row projector has 3 row bits, under the 4 finest compared by default: it is measured on 3
    (the calibration of such a projector stopped at "finest must be 1..3, got 4")."""
    size = (64, 8)
    rig = _rig({"distance": 0.5, "aperture": 10}, size)
    cal, blur = _measured(rig, size)
    known = torch.isfinite(blur)
    assert bool(known[torch.isfinite(cal.prj_xy).all(-1)].float().mean() > 0.9)
    assert float(blur[known].median()) == pytest.approx(1.92, abs=0.5)
    capture = simulate_calibration(rig, "s", 0)
    with pytest.raises(InputError, match="finest must be 1..3, got 4"):
        measure_blur(capture.patterns, capture.white, capture.black, cal.prj_xy, size, finest=4)


def test_a_model_with_the_measured_blur_predicts_a_defocused_capture():
    rig = _rig({"distance": 0.5, "aperture": 20})
    cal, blur = _measured(rig)
    state = StateCalibration([cal.prj_xy], [cal.decoding.contrast.clamp_min(0)], [PROJECTOR])
    pattern = torch.rand(1, 1, PROJECTOR[1], PROJECTOR[0], generator=torch.Generator().manual_seed(0))
    shot = rig.capture("s", {0: pattern}, noise=False, quantise=False)[0]
    black, white = (rig.emitted(0, torch.full_like(pattern, v))[0] for v in (0.0, 1.0))
    light = ((rig.emitted(0, pattern)[0] - black) / (white - black)).reshape(1, PROJECTOR[1], PROJECTOR[0])
    dark = rig.capture("s", {}, noise=False, quantise=False)[0]
    mapped = torch.isfinite(cal.prj_xy).all(-1) & (cal.decoding.contrast > 0.1)
    miss = {}
    for name, model in (("sharp", state), ("blurred", StateCalibration(state.prj_xy, state.weight, [PROJECTOR], [blur]))):
        predicted = model.predict([light], dark, footprint="area")
        miss[name] = float((predicted - shot)[:, mapped].pow(2).mean().sqrt())
    # Random cells blurred over ~4 cells average out, where a sharp model predicts each pixel's own
    # cells: the measured disc cuts the miss several times (0.008 against 0.058 when written).
    assert miss["blurred"] < 0.25 * miss["sharp"]
    assert miss["blurred"] < 0.5 * float((shot - dark)[:, mapped].std())


def test_bad_inputs_name_what_is_wrong():
    patterns = torch.rand(2 * (7 + 7), 30, 40)
    white, black, nowhere = torch.ones(30, 40), torch.zeros(30, 40), torch.full((30, 40, 2), float("nan"))
    with pytest.raises(InputError, match="full Gray-code sequence of a 128x96 projector: 28 .* got 24"):
        measure_blur(patterns[:24], white, black, nowhere, PROJECTOR)
    with pytest.raises(InputError, match="prj_xy"):
        measure_blur(patterns, white, black, nowhere[:10], PROJECTOR)
    # Nothing mapped: nothing to judge, and no pixel gets a diameter.
    assert not torch.isfinite(measure_blur(patterns, white, black, nowhere, PROJECTOR)).any()
    ys, xs = torch.meshgrid(torch.arange(30.0), torch.arange(40.0), indexing="ij")
    state = StateCalibration([torch.stack([xs, ys], -1)], [torch.ones(30, 40)], [PROJECTOR], [torch.zeros(10, 40)])
    with pytest.raises(InputError, match=r"blur\[0\] of state 's'"):
        build_transport({"s": state}, [Target("s", torch.rand(1, 8, 8))], footprint="area")
