"""Virtual-rig calibration says how much of each projector's light decoded, and warns when little did."""

import warnings

import pytest
import torch

from torchproj.calib import FEW_DECODED
from torchproj.core import InputError
from torchproj.pipeline import calibrate_virtual, decoding_accuracy
from torchproj.scene import parse_scene

from ..helpers import small_config, small_scene


def test_decoded_share_is_reported_and_warned_where_stripes_are_finer_than_the_camera():
    # A camera as fine as the projectors decodes nearly everything it sees lit.
    fine = parse_scene(small_config(camera=(400, 300), projector=(256, 192)), name="fine")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning at all
        cal = calibrate_virtual(fine, progress=False)
    shares = [v for per in cal.decoded.values() for v in per.values()]
    assert len(shares) == 4 and min(shares) > 0.95
    # One camera pixel over ~2.4 projector cells, averaged over 4x4 samples: the finest stripes blur to grey and fail the
    # reliability test, so few lit pixels decode fully; their sharp bits still name two or four cells, so nearly all are
    # partly decoded, placed from their neighbours, and nothing needs a warning.
    coarse = parse_scene(small_config(camera=(100, 75), projector=(256, 192), supersampling=4), name="coarse")
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*decoded")
        cal = calibrate_virtual(coarse, progress=False)
    for state, per in cal.decode.items():
        for name, v in per.items():
            assert v["full"] < FEW_DECODED and v["partial"] > 0.5 and v["none"] < 0.05
            assert v["full"] + v["partial"] + v["none"] == pytest.approx(1, abs=1e-3)
            # The decoded share a run reports, and the warning compares, counts both: what calibration places.
            assert cal.decoded[state][name] == pytest.approx(v["full"] + v["partial"], abs=2e-4)
    # The share agrees with the simulator's truth within what the shadow mask leaves out.
    geo = cal.rig.geometry("near")
    truth = decoding_accuracy(cal.states["near"].prj_xy[0], geo.prj_xy[0].cpu())
    placed = cal.decode["near"]["upper"]
    assert abs(truth.decoded - (placed["full"] + placed["partial"])) < 0.15


def test_a_state_too_dim_to_decode_is_refused_before_calibrating(tmp_path, capsys):
    """The far plane at 39/255 failed after minutes of calibration at the ramp; now it is refused at
    once, saying how much exposure would do."""
    import yaml

    from torchproj.cli import main
    from torchproj.pipeline.virtual import check_light

    data = small_config(camera=(200, 150), projector=(128, 96))
    data["camera"]["exposure"] = 0.5  # the near plane passes, the far one (1 m, not 0.8) does not
    with pytest.raises(InputError, match=r"state 'far': projector '\w+' lights it at most \d+/255 above black .* "
                                         r"raise camera.exposure \(to about 0.\d+\)") as refused:
        check_light(parse_scene(data))
    path = tmp_path / "dim.yaml"
    path.write_text(yaml.safe_dump(dict(data, name="dim")))
    assert main(["run", str(path), "--out", str(tmp_path / "out")]) == 2
    assert "checked before calibrating" in capsys.readouterr().err and not (tmp_path / "out").exists()
    # The exposure it names is enough.
    import re

    data["camera"]["exposure"] = float(re.search(r"to about ([\d.]+)", str(refused.value)).group(1))
    check_light(parse_scene(data))


def test_white_levels_are_the_rigs_white_minus_black_and_the_scene_command_prints_them(capsys, tmp_path):
    """Against the full-resolution noiseless captures of the same rig: the grid's brightest pixel can
    only miss the brightest of all by the light's variation between grid points."""
    import yaml

    import torch

    from torchproj.cli import main
    from torchproj.pipeline import white_levels
    from torchproj.sim import VirtualRig

    data = small_config(camera=(200, 150), projector=(128, 96))
    data["camera"]["exposure"] = 0.5
    scene = parse_scene(data)
    levels = white_levels(scene)
    rig = VirtualRig(scene)
    for state in scene.states:
        black = rig.capture(state.name, {}, noise=False)[0]
        for j, proj in enumerate(scene.projectors):
            white = rig.capture(state.name, {j: torch.ones(1, 1, proj.height, proj.width)}, noise=False)[0]
            full = float((white - black).mean(0).max())
            assert full * 0.97 <= levels[state.name, proj.name] <= full + 1e-6, (state.name, proj.name)
    path = tmp_path / "dim.yaml"
    path.write_text(yaml.safe_dump(dict(data, name="dim")))
    assert main(["scene", str(path)]) == 0
    printed = capsys.readouterr().out
    for (_state, name), peak in levels.items():
        verdict = "too dim" if peak < 40 / 255 else "ok"
        assert f"{name} {peak * 255:.0f} ({verdict}" in printed, printed
    assert "too dim" in printed  # the far plane at this exposure


def test_a_state_saturated_by_room_light_is_refused_before_calibrating():
    from torchproj.pipeline.virtual import check_light

    data = small_config(camera=(200, 150), projector=(128, 96))
    data["ambient"] = 1e6
    with pytest.raises(InputError, match=r"state '\w+': the black capture saturates the camera \(room light alone"):
        check_light(parse_scene(data))


def test_a_state_no_projector_lights_is_refused_before_calibrating(monkeypatch):
    """A black surface (albedo 0), or one moved out of view, left a state dark: calibration ran to the
    end and the run was refused at its target (the fuzzer's config mutations). Refused before, naming
    the state; a small object the check's grid passes between is found pixel by pixel."""
    import torchproj.pipeline.virtual as virtual

    data = small_config(camera=(200, 150), projector=(128, 96))
    data["surfaces"]["far_plane"]["albedo"] = 0
    monkeypatch.setattr(virtual, "simulate_calibration", lambda *a, **k: pytest.fail("calibrated before checking"))
    with pytest.raises(InputError, match=r"state 'far': no projector's light reaches the camera there .* albedo"):
        virtual.calibrate_virtual(parse_scene(data))
    # Light too faint to move the camera's 8 bits reads as none: the message names that cause too.
    faint = small_config(camera=(200, 150), projector=(128, 96))
    for projector in faint["projectors"]:
        projector["power"] = 1e-4
    with pytest.raises(InputError, match=r"no projector's light reaches .* lit too faintly for the camera's 8 bits to "
                                         r"register; .* the projectors' power against camera.exposure"):
        virtual.calibrate_virtual(parse_scene(faint))
    # ... and a camera gamma that takes mid-tones under one level (v**5), with every pose and power right.
    bent = small_config(camera=(200, 150), projector=(128, 96), gamma=0.2, exposure=0.3)
    with pytest.raises(InputError, match=r"no projector's light reaches .* against camera.exposure and camera.gamma "
                                         r"\(0.2: values go as v\*\*5\)"):
        virtual.calibrate_virtual(parse_scene(bent))
    # One grid point, the corner pixel, which the planes leave dark: the state is lit elsewhere.
    scene = small_scene(camera=(200, 150), projector=(128, 96))
    assert all(level == 0 for level in virtual._light_levels(scene, "cpu", grid=1)[0].values())
    virtual.check_light(scene, grid=1)


def test_a_projector_that_lights_nothing_is_refused_before_calibrating(monkeypatch):
    """A projector turned away from every surface decoded nothing; calibration simulated every state
    and stopped at its ramp ("0 usable levels"). Refused before, naming it; the other still lights."""
    import torchproj.pipeline.virtual as virtual

    data = small_config(camera=(200, 150), projector=(128, 96))
    data["projectors"][1]["pose"]["look_at"] = [0.0, 0.1, -1.0]
    monkeypatch.setattr(virtual, "simulate_calibration", lambda *a, **k: pytest.fail("calibrated before checking"))
    with pytest.raises(InputError, match=r"projectors\[1\]: projector 'lower' lights nothing the camera sees in any "
                                         r"state .* check its pose"):
        virtual.calibrate_virtual(parse_scene(data))
    levels = virtual._light_levels(parse_scene(data), "cpu", grid=None)[0]
    assert all(levels[state, "lower"] == 0 < levels[state, "upper"] for state in ("near", "far"))



def test_a_projector_that_lights_a_sliver_too_faintly_is_refused_before_calibrating(monkeypatch):
    """A projector behind the planes lights their backs and, past the near plane's edge, a ball's far
    limb at 1/255: the light check's grid read 0 there, the full image read more than 0, and neither
    the unlit nor the dim check refused it; calibration then simulated every state and stopped at its
    ramp ("0 usable levels")."""
    import torchproj.pipeline.virtual as virtual

    data = small_config(camera=(200, 150), projector=(128, 96))
    data["projectors"][1]["pose"] = {"position": [0.0, 0.0, 2.0], "look_at": [0.0, 0.0, 0.9]}
    data["surfaces"]["ball"] = {"type": "sphere", "radius": 0.04, "pose": {"position": [0.26, 0.0, 0.75]}, "albedo": 0.8}
    data["states"][0]["surfaces"].append("ball")
    scene = parse_scene(data)
    assert all(level == 0 for (state, name), level in virtual._light_levels(scene, "cpu", grid=8)[0].items()
               if name == "lower")
    monkeypatch.setattr(virtual, "simulate_calibration", lambda *a, **k: pytest.fail("calibrated before checking"))
    with pytest.raises(InputError, match=r"projectors\[1\]: projector 'lower' lights what the camera sees at most "
                                         r"1/255 above black, in any state, and Gray-code decoding needs 40/255, .* "
                                         r"light the surfaces from behind"):
        virtual.check_light(scene, grid=8)

@pytest.mark.parametrize("resolution", [[31, 96], [128, 1]])
def test_a_projector_too_small_for_the_calibration_sequence_is_refused_before_simulating(resolution, monkeypatch):
    """A projector narrower than the ramp's 32 bars stopped at "steps must be between 2 and the width
    31, got 32", one of a single row at "finest must be 1..0", each after casting every state."""
    import torchproj.pipeline.virtual as virtual

    data = small_config(camera=(200, 150), projector=(128, 96))
    data["projectors"][1]["resolution"] = resolution
    rig = virtual.VirtualRig(parse_scene(data))
    monkeypatch.setattr(rig, "geometry", lambda *a, **k: pytest.fail("cast before checking"))
    with pytest.raises(InputError, match=rf"projectors\[1\].resolution: projector 'lower' is {resolution[0]}x"
                                         rf"{resolution[1]} cells, .* give it at least 32x2"):
        next(virtual.calibrate_rig(rig, progress=False))


def test_a_procedural_scenes_simulate_report_names_what_loads_it_again(tmp_path):
    """viz/correspondences.py loads the scene from the report's ``config``: a procedural scene has no
    file, and its report said "None", which no loader takes."""
    import json

    from torchproj.pipeline.virtual import simulate_scene
    from torchproj.scene import load_scene

    scene = load_scene("suite-1-2")
    simulate_scene(scene, tmp_path / "sim")
    again = load_scene(json.loads((tmp_path / "sim" / "report.json").read_text())["config"])
    assert again.name == scene.name and again.describe() == scene.describe()


@pytest.mark.parametrize("exposure", [1.0, 3.6])
def test_a_white_capture_the_camera_clips_is_measured_warned_and_said_before_calibrating(exposure, tmp_path, capsys):
    """An over-exposed camera clips the white capture, and with it every row's weight and the ramp: at
    exposure 3.6 the far target lost 3.4 dB and nothing said why. The share calibration measures is
    the noise-free captures' (the simulator's truth) within the noise; the scene command says it first."""
    import yaml

    from torchproj.calib import SATURATED, SATURATED_SHARE
    from torchproj.cli import main
    from torchproj.pipeline import run_markdown, run_virtual
    from torchproj.sim import VirtualRig

    data = small_config(camera=(200, 150), projector=(128, 96))
    data["camera"]["exposure"] = exposure
    scene = parse_scene(data, name="exposed")
    truth = VirtualRig(scene)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cal = calibrate_virtual(scene, progress=False)
    measured = {(state, name): share for state, per in cal.white_clipped.items() for name, share in per.items()}
    said = [str(w.message) for w in caught if "the white capture is clipped" in str(w.message)]
    for state in scene.states:
        black = truth.capture(state.name, {}, noise=False)[0]
        for j, proj in enumerate(scene.projectors):
            white = truth.capture(state.name, {j: torch.ones(1, 1, proj.height, proj.width)}, noise=False)[0]
            lit = (white - black).mean(0) >= 40 / 255
            share = float((lit & (white.amax(0) >= SATURATED)).sum() / lit.sum())
            assert measured[state.name, proj.name] == pytest.approx(share, abs=0.05), (state.name, proj.name)
            warned = [m for m in said if m.startswith(f"state {state.name!r}, projector {proj.name!r}: ")]
            assert len(warned) == (share > SATURATED_SHARE), (state.name, proj.name, said)
    assert bool(said) == (exposure > 1) and all("Lower camera.exposure" in m for m in said)
    # The run's report keeps the shares, and report.md says them where any pixel was clipped.
    report = run_virtual(scene, calibration=cal, max_iter=20, progress=False).report
    assert report["white_clipped"] == cal.white_clipped
    assert ("White capture clipped by the camera" in run_markdown(report)) == (exposure > 1)
    path = tmp_path / "exposed.yaml"
    path.write_text(yaml.safe_dump(dict(data, name="exposed")))
    assert main(["scene", str(path)]) == 0
    levels = capsys.readouterr().out.split("white level per state and projector")[1].splitlines()
    near = next(line for line in levels if line.startswith("  state near:"))
    far = next(line for line in levels if line.startswith("  state far:"))
    assert ("white clipped at" in near) == (exposure > 1) and "white clipped" not in far


def test_a_camera_drowned_in_noise_is_said_naming_each_state_and_projector():
    """The stability tests' noisy camera (a full well of 20 electrons): its captures' pairs stray by 30-45%
    of white minus black, which calibration measures and now says, with the frames to average."""
    from torchproj.pipeline.virtual import calibrate_rig
    from torchproj.sim import VirtualRig

    data = small_config(camera=(200, 150), projector=(128, 96))
    data["camera"]["noise"] = {"full_well": 20, "read": 0.06}
    data["states"] = [s for s in data["states"] if s["name"] == "near"]
    data.pop("targets", None)
    scene = parse_scene(data, name="noisy")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        noise = {(state, j): cal.capture_noise for state, j, _, cal in calibrate_rig(VirtualRig(scene), progress=False)}
    said = [str(w.message) for w in caught if "the captures' noise is" in str(w.message)]
    assert len(said) == len(noise) == 2 and all(n > 0.25 for n in noise.values())
    assert all("camera.frames" in m for m in said) and said[0].startswith("state 'near', projector 'upper': ")


def test_a_coarse_camera_is_warned_of_once_per_run():
    """The warning that the camera's samples fall too far apart came once per rig made: from the light
    check's rig, the calibrating one and the world as shown, three times in one run."""
    import torchproj.pipeline.virtual as virtual
    from torchproj.pipeline import shown_world

    scene = small_scene("paper_bumped", camera=(200, 150), projector=(128, 96), supersampling=1)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        shown_world(virtual.calibrate_virtual(scene, progress=False), scene)
    said = [str(w.message) for w in seen if "camera samples are" in str(w.message)]
    assert len(said) == 1 and "set camera.supersampling to" in said[0]
    # The levels asked for alone (``torchproj scene``) still say it.
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        virtual.describe_light(scene)
    assert sum("camera samples are" in str(w.message) for w in seen) == 1
