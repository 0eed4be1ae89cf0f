"""``torchproj refine``: the camera loop on a bench, in turns over a folder, with the virtual rig as the
person who shows the patterns and takes the photos."""

import json

import pytest
import torch

from torchproj.cli import main
from torchproj.core import CaptureError, InputError, read_image, write_image
from torchproj.pipeline.bench_loop import refine_bundle
from torchproj.scene import parse_scene, shown_scene
from torchproj.sim import VirtualRig

from ..helpers import RigDisplay, calibrate_bench, small_config

TARGETS = ["near=camera", "far=coffee"]


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    """A small two-plane bench calibrated from files, and the world the patterns are then shown in:
    the upper projector's lamp 25% brighter than at calibration."""
    data = small_config(camera=(200, 150), projector=(128, 96))
    calib = calibrate_bench(tmp_path_factory.mktemp("bench"), parse_scene(data, name="bench"))
    data["show"] = {"projectors": {"upper": {"gain": 1.25}}}
    world = VirtualRig(shown_scene(parse_scene(data, name="bench")))
    return calib, world


def photograph(world, step):
    """What a person does between turns: show the step's patterns, photograph each state."""
    shown = {p.name: read_image(step / "patterns" / f"{p.name}.png")[None] for p in world.scene.projectors}
    (step / "captures").mkdir(exist_ok=True)
    for state in ("near", "far"):
        write_image(step / "captures" / f"{state}.png", world.capture(state, shown)[0])


def test_the_loop_runs_in_turns_and_wins_back_a_brighter_lamp(bench, tmp_path, capsys):
    calib, world = bench
    out = tmp_path / "loop"
    args = ["refine", str(calib), "--targets", *TARGETS, "--iterations", "3", "--no-register", "--out", str(out)]
    assert main(args) == 0
    assert "show " in capsys.readouterr().out and (out / "step_00" / "patterns" / "upper.png").is_file()
    for k in range(4):
        report = json.loads((out / "report.json").read_text())
        assert report["waiting"]["step"] == k and len(report["steps"]) == k
        photograph(world, out / f"step_{k:02d}")
        mine = out / f"step_{k:02d}" / "captures" / "near.png"
        before = mine.read_bytes()
        assert main(args) == 0
        assert mine.read_bytes() == before  # the person's photos are never touched
    report = json.loads((out / "report.json").read_text())
    assert "done" in report and len(report["steps"]) == 4
    first, best = report["steps"][0]["psnr_db"], report["steps"][report["done"]["best_step"]]["psnr_db"]
    assert sum(best) > sum(first) + 1.0  # the brighter lamp's miss is won back (measured ~+3 dB)
    assert (out / "best" / "patterns" / "lower.png").is_file()
    assert "Done: the best photos were step" in (out / "report.md").read_text()


def test_bad_photos_and_a_changed_loop_are_refused_naming_the_file(bench, tmp_path):
    calib, world = bench
    out = tmp_path / "loop"
    refine_bundle(calib, TARGETS, out, iterations=2, register=False)
    step = out / "step_00"
    (step / "captures").mkdir()
    write_image(step / "captures" / "middle.png", torch.zeros(1, 150, 200))
    with pytest.raises(CaptureError, match=r"middle.png: names no state of this loop's targets \(near, far\)"):
        refine_bundle(calib, TARGETS, out, iterations=2, register=False)
    (step / "captures" / "middle.png").unlink()
    write_image(step / "captures" / "near.png", torch.zeros(1, 100, 200))
    write_image(step / "captures" / "far.png", torch.zeros(1, 150, 200))
    with pytest.raises(CaptureError, match=r"near.png: size \(1, 100, 200\) .* gives \(1, 150, 200\)"):
        refine_bundle(calib, TARGETS, out, iterations=2, register=False)
    # Other options than the loop was started with: its photos are of other patterns.
    with pytest.raises(InputError, match="started with other iterations"):
        refine_bundle(calib, TARGETS, out, iterations=5, register=False)
    # A folder of someone else's files is not taken over.
    (tmp_path / "theirs").mkdir()
    (tmp_path / "theirs" / "NOTES.txt").write_text("mine")
    with pytest.raises(InputError, match="holds files but no loop.json"):
        refine_bundle(calib, TARGETS, tmp_path / "theirs", iterations=2)
    # A target image that changed after the first turn gives other patterns: refused.
    write_image(tmp_path / "t.png", torch.rand(1, 60, 80, generator=torch.Generator().manual_seed(1)))
    other = tmp_path / "other"
    refine_bundle(calib, [f"near={tmp_path / 't.png'}", "far=coffee"], other, iterations=1, register=False)
    write_image(tmp_path / "t.png", torch.rand(1, 60, 80, generator=torch.Generator().manual_seed(2)))
    with pytest.raises(InputError, match="other patterns for this step"):
        refine_bundle(calib, [f"near={tmp_path / 't.png'}", "far=coffee"], other, iterations=1, register=False)


def test_a_photo_of_another_state_is_refused_and_one_of_no_state_is_warned_about(bench, tmp_path):
    """Issue 43: a capture of the wrong state is refused naming the file. Each photo is held against the
    light the model predicts for its state from the step's patterns: on this bench a photo misses its
    own state's by 3% (the brighter lamp) and the other's by 31-106% (benchmarks/photo_states.py)."""
    import warnings

    calib, world = bench
    out = tmp_path / "loop"
    refine_bundle(calib, TARGETS, out, iterations=2, register=False)
    step = out / "step_00"
    photograph(world, step)
    near, far = step / "captures" / "near.png", step / "captures" / "far.png"
    swapped = far.read_bytes(), near.read_bytes()
    near.write_bytes(swapped[0])
    far.write_bytes(swapped[1])
    with pytest.raises(CaptureError, match=r"near.png: shows the light of state 'far', not 'near' .* rename the files"):
        refine_bundle(calib, TARGETS, out, iterations=2, register=False)
    assert near.read_bytes() == swapped[0]  # the person's photos are left as they are
    near.write_bytes(swapped[1])
    far.write_bytes(swapped[0])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        report = refine_bundle(calib, TARGETS, out, iterations=2, register=False)
    assert report["waiting"]["step"] == 1 and not [w for w in caught if "predicts" in str(w.message)]
    # The projectors off (or other patterns shown): the photo matches no state, and the loop says so.
    photograph(world, out / "step_01")
    write_image(out / "step_01" / "captures" / "far.png", torch.zeros(1, 150, 200))
    with pytest.warns(UserWarning, match=r"far.png: differs from the light the model predicts for state 'far' by \d+%"):
        refine_bundle(calib, TARGETS, out, iterations=2, register=False)


class _Camera:
    """A camera on the virtual rig: photographs the state the prompt last set up, lit by the displays."""

    def __init__(self, world, displays):
        self.world, self.displays, self.state = world, displays, None

    def grab(self):
        shown = {name: d.pattern() for name, d in self.displays.items()}
        return (self.world.capture(self.state, shown)[0, 0] * 255).round().to(torch.uint8).numpy()


def test_a_live_bench_runs_the_whole_loop_in_one_turn(bench, tmp_path):
    from torchproj.pipeline.acquire import LiveBench

    calib, world = bench
    displays = {"upper": RigDisplay(), "lower": RigDisplay()}
    camera = _Camera(world, displays)
    asked = []

    def prompt(state):
        asked.append(state)
        camera.state = state

    report = refine_bundle(calib, TARGETS, tmp_path / "live", iterations=2, register=False,
                           live=LiveBench(displays, camera, settle_s=0, prompt=prompt))
    assert "done" in report and len(report["steps"]) == 3 and asked == ["near", "far"] * 3
    assert (tmp_path / "live" / "step_02" / "captures" / "far.png").is_file()
    assert sum(report["steps"][report["done"]["best_step"]]["psnr_db"]) > sum(report["steps"][0]["psnr_db"]) + 1.0
    # A projector without a display is refused before anything is photographed.
    with pytest.raises(CaptureError, match=r"no display for projector\(s\) \['lower'\]"):
        refine_bundle(calib, TARGETS, tmp_path / "half", iterations=1, register=False,
                      live=LiveBench({"upper": RigDisplay()}, camera, settle_s=0, prompt=prompt))


def test_live_options_are_checked(bench, tmp_path, capsys):
    calib, _ = bench
    base = ["refine", str(calib), "--targets", *TARGETS, "--out", str(tmp_path / "x"), "--camera", "0"]
    assert main([*base, "--screen", "upper=1920,0"]) == 2
    assert "give each its screen, --screen NAME=X,Y for ['lower']" in capsys.readouterr().err
    assert main([*base, "--screen", "left=0,0", "--screen", "upper=1,0"]) == 2
    assert "--screen names projector(s) ['left']" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([*base, "--screen", "upper"])
    assert "expected NAME=X,Y" in capsys.readouterr().err
    both = ["--screen", "upper=0,0", "--screen", "lower=1,0"]
    for option, message in ((["--frames", "0"], "frames must be a whole number of camera frames, at least 1"),
                            (["--settle", "nan"], "settle must be seconds in [0, 60]"),
                            (["--settle", "-1"], "settle must be seconds in [0, 60]")):
        assert main([*base, *both, *option]) == 2
        assert message in capsys.readouterr().err and not (tmp_path / "x").exists()
