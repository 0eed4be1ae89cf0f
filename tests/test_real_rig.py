"""The real-rig path through files: sequence, capture folders, calibrate, solve. The proof is that
captures the virtual rig writes as folders give the same patterns as ``torchproj run``."""

import json
import re

import cv2
import numpy as np
import pytest
import torch

from torchproj.calib import (calibrate_folders, calibrate_projector, checker_patterns, graycode_patterns, primary_patterns, load_bundle, read_graycode_folder,
                             write_graycode_folder)
from torchproj.calib.capture import CHECKER_NAMES, PRIMARY_NAMES, RAMP_NAMES
from torchproj.pipeline import simulate_calibration
from torchproj.cli import main
from torchproj.core import CaptureError, InputError, read_image, write_image
from torchproj.pipeline import capture_sequence, run_virtual
from torchproj.scene import parse_scene
from torchproj.sim import VirtualRig

from .helpers import CHESSBOARD, RigDisplay, small_config


@pytest.fixture(scope="module")
def scene():
    data = small_config()
    # States and projectors in name order, as a bundle lists a capture root's folders: the run then
    # takes each projector's response from the same state, and its operator has the same columns and
    # rows in the same order, so that the two solves are the same sums to the last bit (in another
    # order they differ by round-off, enough to stop FISTA an iteration apart).
    data["states"] = sorted(data["states"], key=lambda s: s["name"])
    data["projectors"] = sorted(data["projectors"], key=lambda p: p["name"])
    return parse_scene(data, name="small")


@pytest.fixture(scope="module")
def capture_root(scene, tmp_path_factory):
    """The virtual rig's calibration captures written as a real bench would store them."""
    root = tmp_path_factory.mktemp("captures")
    rig = VirtualRig(scene)  # same seed and capture order as run_virtual's calibration: same noise
    for st in scene.states:
        for j, p in enumerate(scene.projectors):
            write_graycode_folder(root / st.name / p.name, simulate_calibration(rig, st.name, j), bits=8)
    return root


@pytest.fixture(scope="module")
def bench(capture_root, tmp_path_factory):
    """The captures calibrated from their folders, as ``torchproj calibrate`` writes a bundle."""
    calib = tmp_path_factory.mktemp("bench") / "calib"
    assert main(["calibrate", str(capture_root), "--projector", "256x192", "--out", str(calib)]) == 0
    return calib


def test_sequence_is_what_the_virtual_rig_shows(scene, tmp_path):
    assert main(["sequence", "--projector", "256x192", "--out", str(tmp_path / "seq")]) == 0
    manifest = json.loads((tmp_path / "seq" / "sequence.json").read_text())
    files = [e["file"] for e in manifest["images"]]
    gray = graycode_patterns(256, 192)
    assert len(files) == len(gray) + 7 and files[len(gray):] == [*RAMP_NAMES, *CHECKER_NAMES, *PRIMARY_NAMES]
    assert [e["kind"] for e in manifest["images"]][len(gray) - 2:len(gray)] == ["white", "black"]
    assert [(e["kind"], e["inverse"]) for e in manifest["images"][-5:-3]] == [("checker", False), ("checker", True)]
    # The primaries last: full-field red, green, blue, what a colour camera's mixing is measured from.
    for k, name in enumerate(PRIMARY_NAMES):
        assert torch.equal(read_image(tmp_path / "seq" / name), primary_patterns(256, 192)[k])
    shown = torch.cat([gray, checker_patterns(256, 192)])
    for i, k in ((0, 0), (5, 5), (len(gray) - 1, len(gray) - 1), (-5, len(gray)), (-4, len(gray) + 1)):
        assert torch.equal(read_image(tmp_path / "seq" / files[i]), shown[k])
    # What the virtual rig shows: the same images, the checkerboard pair after the ramps.
    p = scene.projectors[0]
    cap = simulate_calibration(VirtualRig(scene), scene.states[0].name, 0, noise=False)
    assert cap.patterns.shape[0] == len(graycode_patterns(p.width, p.height)) - 2
    assert cap.checker.shape == (2, *cap.white.shape)


def test_a_shortened_sequence_shows_no_checkerboard(scene, tmp_path):
    # Its map is one homography and its rows no measured shares: the pair would be two wasted captures.
    assert main(["sequence", "--projector", "256x192", "--bits", "3", "--out", str(tmp_path / "seq")]) == 0
    kinds = [e["kind"] for e in json.loads((tmp_path / "seq" / "sequence.json").read_text())["images"]]
    assert "checker" not in kinds and not (tmp_path / "seq" / CHECKER_NAMES[0]).exists()
    assert simulate_calibration(VirtualRig(scene), scene.states[0].name, 0, bits=3, noise=False).checker is None


@pytest.mark.slow
def test_calibrate_and_solve_from_folders_match_the_virtual_run(scene, capture_root, tmp_path, capsys):
    calib, solved = tmp_path / "calib", tmp_path / "solved"
    assert main(["calibrate", str(capture_root), "--projector", "256x192", "--out", str(calib)]) == 0
    assert (calib / "calibration.png").is_file()
    # The captures' camera noise, said per state and projector: this camera's, about 1% of white - black.
    said = re.findall(r"(far|near)/(upper|lower) (\d+\.\d+)%", capsys.readouterr().out.split("camera noise")[1])
    assert len(said) == 4 and all(0.3 < float(share) < 3 for _, _, share in said)
    bundle = load_bundle(calib)
    assert list(bundle.states) == ["far", "near"] and bundle.camera_size == (400, 300)
    assert main(["solve", str(calib), "--targets", "far=astronaut", "near=chelsea", "--out", str(solved)]) == 0
    run = run_virtual(scene)
    # The bench's calibration says the same decoded share of each projector's lit pixels as the run.
    assert bundle.decoded_lit == run.report["decoded_fraction"]
    report = json.loads((solved / "report.json").read_text())
    assert report["objective"] == pytest.approx(run.report["objective"], rel=1e-5)
    shown = {}
    for j, p in enumerate(scene.projectors):
        from_files = (read_image(solved / "patterns" / f"{p.name}.png") * 255).round()
        diff = (from_files - run.patterns[j].float()).abs()
        assert float(diff.max()) <= 1 and float((diff > 0).float().mean()) < 0.01, p.name
        shown[j] = from_files[None] / 255
    # Fed those patterns, the virtual rig shows the targets at the same quality as the run.
    rig = VirtualRig(scene)
    for t, row in zip(run.targets, run.report["targets"]):
        shot = rig.capture(row["state"], shown)[0]
        black = rig.capture(row["state"], {})[0]
        est = ((shot - black) / run.report["scale"]).clamp(0, 1)
        cov = t.covered
        got = 10 * np.log10(1 / float(((est[:, cov] - t.values[:, cov]) ** 2).mean()))
        assert got == pytest.approx(row["psnr_db"], abs=0.3)
    assert (solved / "predicted" / "near.png").is_file()
    for row in report["targets"]:
        assert row["predicted_psnr_db"] > 15
    # The same bundle with one homography per plane gives what the virtual run gives with them.
    planar = tmp_path / "planar"
    assert main(["solve", str(calib), "--targets", "far=astronaut", "near=chelsea", "--out", str(planar),
                 "--maps", "homography"]) == 0
    report = json.loads((planar / "report.json").read_text())
    run = run_virtual(scene, maps="homography")
    assert report["maps"] == "homography" and sorted(report["homographies"]) == ["far", "near"]
    assert report["objective"] == pytest.approx(run.report["objective"], rel=1e-4)
    in_run_order = [[name for name, _, _ in bundle.projectors].index(p.name) for p in scene.projectors]
    for state, fits in report["homographies"].items():
        for j, theirs in zip(in_run_order, run.report["homographies"][state]):
            ours = fits[j]
            assert ours["p95_px"] < 1 and np.allclose(ours["matrix"], theirs["matrix"], rtol=1e-4, atol=1e-4)


@pytest.mark.slow
def test_a_shortened_sequence_from_folders_matches_the_virtual_run(scene, tmp_path):
    assert main(["sequence", "--projector", "256x192", "--bits", "3", "--out", str(tmp_path / "seq")]) == 0
    manifest = json.loads((tmp_path / "seq" / "sequence.json").read_text())
    # 12 Gray-code images, white, black, the two ramps and the three primaries (read with a colour camera).
    assert manifest["bits"] == [3, 3] and len(manifest["images"]) == 19
    assert [e["bit"] for e in manifest["images"][:12:2]] == [0, 1, 2, 0, 1, 2]
    assert torch.equal(read_image(tmp_path / "seq" / "graycode_07.png"), graycode_patterns(256, 192, 3)[7])
    # The rig's captures of that sequence, stored as a bench would store them (sequence.json beside).
    root = tmp_path / "captures"
    rig = VirtualRig(scene)
    for st in scene.states:
        for j, p in enumerate(scene.projectors):
            folder = root / st.name / p.name
            write_graycode_folder(folder, simulate_calibration(rig, st.name, j, bits=3), bits=8)
            (folder / "sequence.json").write_text((tmp_path / "seq" / "sequence.json").read_text())
    calib, solved = tmp_path / "calib", tmp_path / "solved"
    assert main(["calibrate", str(root), "--out", str(calib)]) == 0
    bundle = load_bundle(calib)
    assert bundle.bits == [(3, 3), (3, 3)] and sorted(bundle.homographies) == ["far", "near"]
    assert main(["solve", str(calib), "--targets", "far=astronaut", "near=chelsea", "--out", str(solved)]) == 0
    report = json.loads((solved / "report.json").read_text())
    assert report["maps"] == "homography" and report["graycode_bits"] == {"lower": [3, 3], "upper": [3, 3]}
    assert all(f["block_cells"] == [32, 32] for per in report["homographies"].values() for f in per)
    run = run_virtual(scene, bits=3)
    assert report["objective"] == pytest.approx(run.report["objective"], rel=1e-4)
    # Read with the full sequence's count, the folder is refused with the fix named.
    with pytest.raises(CaptureError, match=r"missing 20: .*\(check --projector, --bits"):
        read_graycode_folder(root / "far" / "upper", (256, 192))


def test_bad_capture_folders_are_named(capture_root, tmp_path, monkeypatch):
    import shutil

    import torchproj.calib.bundle as bundle

    broken = tmp_path / "root"
    shutil.copytree(capture_root, broken)
    (broken / "far" / "upper" / "graycode_03.png").write_bytes(b"not a png")  # a truncated transfer
    with pytest.raises(CaptureError, match="graycode_03.png.*cannot be read"):
        calibrate_folders(broken, {"*": (256, 192)})
    shutil.copy(capture_root / "far" / "upper" / "graycode_03.png", broken / "far" / "upper" / "graycode_03.png")
    (broken / "near" / "lower" / "graycode_07.png").unlink()
    # The last folder's missing file is named before any folder is decoded.
    with monkeypatch.context() as patched:
        patched.setattr(bundle, "calibrate_projector", lambda *a, **k: pytest.fail("decoded before the names were checked"))
        with pytest.raises(CaptureError, match="graycode_07.png"):
            calibrate_folders(broken, {"*": (256, 192)})
    shutil.rmtree(broken / "near" / "lower")
    with pytest.raises(CaptureError, match="one folder per projector"):
        calibrate_folders(broken, {"*": (256, 192)})
    with pytest.raises(CaptureError, match="--projector"):
        calibrate_folders(capture_root)  # no sequence.json and no size given
    dark = tmp_path / "dark"
    shutil.copytree(capture_root / "near" / "upper", dark / "s" / "p")
    white = len(graycode_patterns(256, 192)) - 2
    write_image(dark / "s" / "p" / f"graycode_{white:02d}.png", torch.zeros(1, 300, 400))
    with pytest.raises(CaptureError, match="dark everywhere"):
        calibrate_folders(dark, {"*": (256, 192)})
    # Every pattern equal to its inverse (the projector froze on one image): nothing decodes.
    frozen = tmp_path / "frozen"
    shutil.copytree(capture_root / "near" / "upper", frozen / "s" / "p")
    for i in range(white):
        shutil.copy(capture_root / "near" / "upper" / "graycode_00.png", frozen / "s" / "p" / f"graycode_{i:02d}.png")
    with pytest.raises(CaptureError, match=r"frozen.*(decoded; is the projector aimed|usable levels)"):
        calibrate_folders(frozen, {"*": (256, 192)})
    (frozen / "s" / "p" / "ramp.png").unlink()  # without the ramp, the decoding check speaks
    with pytest.raises(CaptureError, match="0.000% of the camera decoded; is the projector aimed"):
        calibrate_folders(frozen, {"*": (256, 192)})


@pytest.mark.parametrize("options, says", [
    ({"black_threshold": float("nan")}, "black_threshold must be a finite number >= 0, got nan"),
    ({"ramp_steps": 0}, r"ramp_steps \(--ramp-steps, the ramp's bars\) must be a whole number >= 2, got 0"),
    ({"ramp_steps": 1.5}, "ramp_steps .* must be a whole number >= 2, got 1.5"),
    ({"plane_tolerance": "x"}, r"plane_tolerance \(projector pixels\) must be a finite number > 0, got 'x'"),
    ({"plane_tolerance": -1}, "plane_tolerance .* must be a finite number > 0, got -1"),
    ({"crease_ratio": "x"}, r"crease_ratio must be >= 1 \(1: the best-fitting window\), got 'x'"),
    ({"curve_ratio": float("nan")}, "curve_ratio must be >= 1 .*, got nan"),
    ({"dim_threshold": None}, r"dim_threshold must be >= 0 \(8-bit units\), got None"),
    ({"sizes": 256}, "sizes must be a dict of projector name -> \\(width, height\\), got int"),
    ({"sizes": {"*": (256.5, 192)}}, "projector width must be a whole number of cells, at least 1, got 256.5"),
    ({"sizes": {"*": (256,)}}, r"sizes\['\*'\] must be \(width, height\), got \(256,\)"),
    ({"states": "near"}, "states must be a list of state folder names, got 'near'"),
])
def test_calibration_options_of_the_wrong_kind_are_named_before_any_folder_is_read(capture_root, options, says,
                                                                                 monkeypatch):
    """The Python face of `torchproj calibrate`: a ramp of 0 bars ended in a ZeroDivisionError, strings in
    TypeErrors, a NaN shadow threshold was not read at all (min() passed the dim one), and the plane
    tolerance of a full sequence was never read, so any value passed; (256.5, 192) was taken as 256."""
    import torchproj.calib.bundle as bundle

    monkeypatch.setattr(bundle, "read_graycode_folder", lambda *a, **k: pytest.fail("read before the options were checked"))
    with pytest.raises(InputError, match=says):
        calibrate_folders(capture_root, **{"sizes": {"*": (256, 192)}, **options})


def test_solve_refuses_unknown_states_and_writes_nothing(bench, tmp_path, capsys):
    calib = bench
    out = tmp_path / "solved"
    assert main(["solve", str(calib), "--targets", "middle=astronaut", "--out", str(out)]) == 2
    assert "no state 'middle'" in capsys.readouterr().err and not out.exists()
    # The footprint reaches the bench's solve, and its prediction follows the same model.
    reports = {}
    for footprint in ("nearest", "bilinear"):
        assert main(["solve", str(calib), "--targets", "near=astronaut", "far=camera", "--footprint", footprint,
                     "--out", str(tmp_path / footprint)]) == 0
        reports[footprint] = json.loads((tmp_path / footprint / "report.json").read_text())
        assert reports[footprint]["footprint"] == footprint
    assert reports["bilinear"]["model"]["nnz"] > 2 * reports["nearest"]["model"]["nnz"]
    # auto chooses from the bundle's own cell shares, and says which and why.
    assert main(["solve", str(calib), "--targets", "near=astronaut", "far=camera", "--footprint", "auto",
                 "--out", str(tmp_path / "auto")]) == 0
    auto = json.loads((tmp_path / "auto" / "report.json").read_text())
    assert auto["footprint"] == auto["footprint_choice"]["footprint"] in ("nearest", "area")
    assert set(auto["footprint_choice"]["expected_loss_db"]) == {"near", "far"}


@pytest.mark.skipif(not CHESSBOARD.is_dir(), reason=f"real captures not found at {CHESSBOARD} (they live in "
                                                     "../shared/data beside the checkout)")
@pytest.mark.slow
def test_calibrate_real_captures_matches_decode(tmp_path, capsys):
    assert main(["calibrate", str(CHESSBOARD), "--states", "capture_0", "capture_1", "--projector", "1024x768",
                 "--calibration", str(CHESSBOARD / "calibration_result.xml"), "--out", str(tmp_path / "calib")]) == 0
    # These captures hold no ramps: the library's warning reaches the user in the command's voice. Their
    # white is clipped at 0.03% of the lit pixels, which is no cause for one.
    err = capsys.readouterr().err
    assert "torchproj calibrate: warning: no ramp captures for ['projector']" in err and "clipped" not in err
    bundle = load_bundle(tmp_path / "calib")
    assert list(bundle.states) == ["capture_0", "capture_1"] and bundle.procam_calibration.is_file() and bundle.projectors == [("projector", 1024, 768)]
    assert main(["decode", str(CHESSBOARD / "capture_0"), "--projector", "1024x768", "--out", str(tmp_path / "dec")]) == 0
    with np.load(tmp_path / "dec" / "correspondence.npz") as dec:
        m = bundle.states["capture_0"][0]
        np.testing.assert_array_equal(m["valid"].numpy(), dec["valid"])
        np.testing.assert_array_equal(np.nan_to_num(m["prj_xy_integer"].numpy(), nan=-1),
                                      np.nan_to_num(dec["prj_xy"], nan=-1))
        np.testing.assert_allclose(m["prj_xy"].numpy(), dec["prj_xy_refined"], equal_nan=True)


class _RigCamera:
    """A camera that photographs the virtual rig while the display's projector shows its image."""

    def __init__(self, rig, state, projector, display):
        self.rig, self.state, self.j, self.display = rig, state, projector, display

    def grab(self):
        shot = self.rig.capture(self.state, {self.j: self.display.pattern()})[0]
        return (shot[0] * 255).round().to(torch.uint8).numpy()


def test_capture_helper_with_a_fake_display_and_camera(scene, tmp_path):
    from torchproj.pipeline import capture_sequence

    assert main(["sequence", "--projector", "256x192", "--out", str(tmp_path / "seq")]) == 0
    rig = VirtualRig(scene)
    for j, p in enumerate(scene.projectors):
        display = RigDisplay()
        capture_sequence(tmp_path / "seq", tmp_path / "captures" / "near" / p.name, display,
                         _RigCamera(rig, "near", j, display), settle_s=0)
    bundle = calibrate_folders(tmp_path / "captures")  # sizes from the copied sequence.json
    names = [p.name for p in scene.projectors]
    assert [n for n, _, _ in bundle.projectors] == sorted(names)  # a capture root lists projectors by name
    for (name, _, _), m, response in zip(bundle.projectors, bundle.states["near"], bundle.responses):
        j = names.index(name)
        truth = rig.geometry("near").prj_xy
        ok = m["valid"] & torch.isfinite(truth[j]).all(-1)
        assert float(ok.float().mean()) > 0.4
        assert float((torch.floor(m["prj_xy_integer"][ok] + 0.5) == torch.floor(truth[j][ok] + 0.5)).all(-1)
                     .float().mean()) > 0.99
        assert float(response.b[0]) == pytest.approx(scene.projectors[j].response_b[0], abs=0.05)
    with pytest.raises(CaptureError, match="sequence.json"):
        capture_sequence(tmp_path, tmp_path / "x", RigDisplay(), None)


class _CountingCamera:
    """A camera whose k-th grab is the uint8 image filled with 10 k (mod 250)."""

    def __init__(self):
        self.grabs = 0

    def grab(self):
        self.grabs += 1
        return np.full((6, 8), 10 * self.grabs % 250, dtype=np.uint8)


def test_capture_averages_frames_into_16_bit_files(tmp_path, capsys):
    """--frames N: each image is the mean of N grabs, kept at 16 bits (an 8-bit file would round the
    mean back to one grab's levels); a bad count is refused before any window opens."""
    assert main(["sequence", "--projector", "64x32", "--out", str(tmp_path / "seq")]) == 0
    camera = _CountingCamera()
    out = capture_sequence(tmp_path / "seq", tmp_path / "cap", RigDisplay(), camera, settle_s=0, frames=4)
    files = sorted(out.glob("*.png"))
    assert camera.grabs == 4 * len(files)
    first = cv2.imread(str(out / "graycode_00.png"), cv2.IMREAD_UNCHANGED)
    assert first.dtype == np.uint16  # the mean of grabs 1-4: 25 / 255
    np.testing.assert_allclose(read_image(out / "graycode_00.png").numpy(), 25 / 255, atol=1 / 65535)
    assert cv2.imread(str(out / "graycode_01.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    for bad in (0, -2):
        with pytest.raises(InputError, match=f"frames must be a whole number of camera frames, at least 1, got {bad}"):
            capture_sequence(tmp_path / "seq", tmp_path / "bad", RigDisplay(), camera, settle_s=0, frames=bad)
    assert not (tmp_path / "bad").exists()
    assert main(["capture", str(tmp_path / "seq"), "--frames", "0", "--out", str(tmp_path / "cli")]) == 2
    assert "frames must be a whole number of camera frames, at least 1, got 0" in capsys.readouterr().err
    assert not (tmp_path / "cli").exists()
    # A wait time.sleep refuses with a traceback (negative, NaN) or never ends (inf), refused before any window.
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(InputError, match=r"settle must be seconds in \[0, 60\] \(--settle\)"):
            capture_sequence(tmp_path / "seq", tmp_path / "bad", RigDisplay(), camera, settle_s=bad)
    assert not (tmp_path / "bad").exists() and camera.grabs == 4 * len(files)



class _OddCamera:
    """A camera a script wrote: its frames as ``frame(k)`` makes the k-th."""

    def __init__(self, frame):
        self.frame, self.grabs = frame, 0

    def grab(self):
        self.grabs += 1
        return self.frame(self.grabs)


def test_a_cameras_odd_frames_and_a_display_without_show_are_refused_naming_them(tmp_path):
    """Frames the files could not hold (floats, four channels, none) were written as whatever
    ``write_image`` made of them or ended in numpy's errors, frames that change size between the
    grabs of one mean in a broadcast error; a display or camera without ``show`` / ``grab`` in an
    AttributeError after the folder was made; numpy's float for the wait in ``time.sleep``'s
    TypeError."""
    assert main(["sequence", "--projector", "64x32", "--out", str(tmp_path / "seq")]) == 0
    for frame, says in [(lambda k: np.zeros((6, 8), np.float32), "gave a float32 frame of shape"),
                        (lambda k: np.zeros((6, 8, 4), np.uint8), r"shape \(6, 8, 4\)"),
                        (lambda k: None, "gave a object frame"),
                        (lambda k: np.zeros((6, 8 + k), np.uint8), "frames changed shape between grabs")]:
        with pytest.raises(CaptureError, match=says):
            capture_sequence(tmp_path / "seq", tmp_path / "odd", RigDisplay(), _OddCamera(frame), settle_s=0, frames=2)
    for display, camera, says in [(object(), _CountingCamera(), "display must be a display with show"),
                                  (RigDisplay(), cv2, "camera must have grab")]:
        with pytest.raises(InputError, match=says):
            capture_sequence(tmp_path / "seq", tmp_path / "none", display, camera, settle_s=0)
    assert not (tmp_path / "none").exists()
    out = capture_sequence(tmp_path / "seq", tmp_path / "cap", RigDisplay(), _CountingCamera(), settle_s=np.float32(0))
    assert (out / "graycode_00.png").is_file()

def test_a_colour_bench_keeps_each_channels_weight(tmp_path, capsys):
    """A colour camera's bundle stores white minus black per channel; solve then models each channel
    with its own weight. A bundle without it (written before, or edited) falls back to the grey
    weight, and one whose per-channel array has the wrong shape is refused. The camera mixes the
    primaries (a colour camera's default): the bundle holds each projector's measured mixing, and an
    edited one that cannot be undone is refused."""
    data = small_config("colour_two_planes", camera=(200, 150), projector=(128, 96))
    for p in data["projectors"]:
        p.pop("colour_mixing")
    scene = parse_scene(data, name="colour")
    rig, root = VirtualRig(scene), tmp_path / "captures"
    for st in scene.states:
        for j, p in enumerate(scene.projectors):
            write_graycode_folder(root / st.name / p.name, simulate_calibration(rig, st.name, j), bits=8)
    calib = tmp_path / "calib"
    assert main(["calibrate", str(root), "--projector", "128x96", "--out", str(calib)]) == 0
    capture = read_graycode_folder(root / "near" / "upper", (128, 96))
    stored = np.load(calib / "near" / "upper.npz")
    # White minus black per channel, averaged over the captures that show each pixel white and black
    # (stripe_contrast): what calibrating the folder in Python gives, and within the noise of one frame.
    np.testing.assert_allclose(stored["colour_contrast"], calibrate_projector(capture, (128, 96)).colour_contrast.numpy(),
                               atol=1e-6)
    assert np.abs(stored["colour_contrast"] - (capture.white - capture.black).numpy()).mean() < 0.01
    np.testing.assert_allclose(stored["colour_contrast"].mean(0), stored["contrast"], atol=1e-6)
    from torchproj.core.conventions import DEFAULT_COLOUR_MIXING

    meta = json.loads((calib / "bundle.json").read_text())
    for response in meta["responses"]:
        np.testing.assert_allclose(response["mixing"], DEFAULT_COLOUR_MIXING, atol=0.01)
    args = ["solve", str(calib), "--targets", "far=astronaut", "near=chelsea"]
    assert main([*args, "--out", str(tmp_path / "channel")]) == 0
    edited = json.loads((calib / "bundle.json").read_text())
    edited["responses"][0]["mixing"] = [[0.5, 0.5, 0.0], [0.5, 0.5, 0.0], [0.0, 0.0, 1.0]]
    (calib / "bundle.json").write_text(json.dumps(edited))
    assert main([*args, "--out", str(tmp_path / "singular")]) == 2
    assert "mixing must be 3 rows of 3 shares >= 0 that tell the primaries apart" in capsys.readouterr().err
    (calib / "bundle.json").write_text(json.dumps(meta))
    assert json.loads((tmp_path / "channel" / "report.json").read_text())["colour_weights"] == "channel"
    assert main([*args, "--colour-weights", "grey", "--out", str(tmp_path / "grey")]) == 0
    assert json.loads((tmp_path / "grey" / "report.json").read_text())["colour_weights"] == "grey"
    arrays = {k: stored[k] for k in stored.files}
    np.savez_compressed(calib / "near" / "upper.npz", **{k: v for k, v in arrays.items() if k != "colour_contrast"})
    assert main([*args, "--out", str(tmp_path / "old")]) == 0
    assert json.loads((tmp_path / "old" / "report.json").read_text())["colour_weights"] == "grey"
    np.savez_compressed(calib / "near" / "upper.npz", **{**arrays, "colour_contrast": arrays["colour_contrast"][:2]})
    assert main([*args, "--out", str(tmp_path / "bad")]) == 2
    assert "'colour_contrast' has shape (2, 150, 200)" in capsys.readouterr().err and not (tmp_path / "bad").exists()


def test_a_bench_bundle_keeps_its_edge_pixels_and_cell_shares(tmp_path, capsys):
    """Calibrating a bench with an object in front of another stores each map's edge pixels, cell
    shares (with the pattern pairs' shares beside outlines) and dimly lit pixels; the bundle gives the
    transport model the same ones as calibrating the captures directly.
    A bundle without them (older) models none; one with a pixel outside the camera, a share outside
    [0, 1], only some of the share arrays, a checkerboard share that does not fit, or outline shares
    without their pixels or of another count is refused, naming the file; a checkerboard share that
    fits comes back."""
    from torchproj.calib import calibrate_projector
    from torchproj.transport import StateCalibration

    scene = parse_scene(small_config("box_cylinders", camera=(320, 240), projector=(256, 192)), name="edges")
    rig, root = VirtualRig(scene), tmp_path / "captures"
    for j, p in enumerate(scene.projectors):
        write_graycode_folder(root / "together" / p.name, simulate_calibration(rig, "together", j), bits=8)
    calib = tmp_path / "calib"
    assert main(["calibrate", str(root), "--projector", "256x192", "--out", str(calib)]) == 0
    state = StateCalibration.from_bundle(load_bundle(calib))["together"]
    names = [p.name for p in scene.projectors]
    for (name, _, _), edges, shares, xy, dim in zip(load_bundle(calib).projectors, state.edges, state.shares,
                                                   state.prj_xy, state.dim):
        direct = calibrate_projector(read_graycode_folder(root / "together" / name, (256, 192)), (256, 192))
        assert len(edges) > 20 and name in names
        for field in ("pixel", "xy", "slope", "share"):
            torch.testing.assert_close(getattr(edges, field), getattr(direct.edges, field))
        # Shares for every fully decoded pixel, the dimly lit ones' too, whose coordinates the bundle keeps.
        assert bool(((shares.cell >= 0).all(-1) >= direct.decoding.valid).all())
        assert int(direct.decoding.valid.sum()) > 10000
        assert torch.equal(dim, torch.isfinite(direct.dim_xy).all(-1)) and int(dim.sum()) > 100
        torch.testing.assert_close(xy, torch.where(dim[..., None], direct.dim_xy, direct.prj_xy), equal_nan=True)
        for field in ("cell", "across", "outside", "band", "band_white"):
            torch.testing.assert_close(getattr(shares, field), getattr(direct.shares, field), equal_nan=True)
        assert shares.band.numel() > 100  # the outlines of the cylinders and the box's
    # Each map's defocus disc comes back as calibration measured it.
    for blur, (name, _, _) in zip(state.blur, load_bundle(calib).projectors):
        direct = calibrate_projector(read_graycode_folder(root / "together" / name, (256, 192)), (256, 192))
        torch.testing.assert_close(blur, direct.blur, equal_nan=True)
    path = calib / "together" / f"{names[0]}.npz"
    arrays = dict(np.load(path))
    np.savez_compressed(path, **{k: v for k, v in arrays.items() if not k.startswith(("edge_", "share_"))})
    old = StateCalibration.from_bundle(load_bundle(calib))["together"]
    assert old.edges is None and old.shares is None
    for broken, message in (({"edge_pixel": arrays["edge_pixel"] + 320 * 240}, "an edge pixel lies outside the 320x240"),
                            ({"share_across": arrays["share_across"] + 1.5}, "cell shares' across must lie in"),
                            ({"share_outside": None}, "holds .* but not every share_\\* array"),
                            ({"share_checker": np.zeros((5, 5), np.float32)}, "'share_checker' has shape"),
                            ({"share_checker": np.full((240, 320), 2.0, np.float32)}, "checker must lie in"),
                            ({"share_band_white": None}, "need both band and band_white, or neither"),
                            ({"share_band": arrays["share_band"] + 320 * 240}, "band names a pixel outside the 320x240"),
                            ({"share_band_white": arrays["share_band_white"][:-1]}, "band_white.*shape"),
                            ({"share_band_white": arrays["share_band_white"] + 1.5}, "band_white must lie in"),
                            ({"blur": np.full((240, 320), -1.0, np.float32)}, "'blur' must hold defocus diameters"),
                            ({"blur": np.full((240, 320), np.inf, np.float32)}, "'blur' must hold defocus diameters")):
        np.savez_compressed(path, **{k: v for k, v in {**arrays, **broken}.items() if v is not None})
        with pytest.raises(CaptureError, match=f"{names[0]}.npz: .*{message}"):
            load_bundle(calib)
    # A checkerboard pair's share, where a bench measured one, comes back beside the others.
    checker = np.where((arrays["share_cell"] >= 0).all(-1), 0.25, np.nan).astype(np.float32)
    np.savez_compressed(path, **{**arrays, "share_checker": checker})
    bundle = load_bundle(calib)
    which = [name for name, _, _ in bundle.projectors].index(names[0])
    kept = StateCalibration.from_bundle(bundle)["together"].shares[which].checker
    torch.testing.assert_close(kept, torch.from_numpy(checker), equal_nan=True)


def test_a_state_whose_ramp_shows_few_bars_takes_the_response_from_another_folder(tmp_path):
    """Folders are read in name order, so the narrow far plane's ramp (a couple of its 32 bars seen)
    comes first: the projector's response is fitted from the near state's instead; with the far
    state alone it is refused, naming the projector and the folder."""
    data = small_config(camera=(200, 150), projector=(128, 96))
    data["surfaces"]["far_plane"]["size"] = [0.04, 0.3]
    scene = parse_scene(data, name="narrow_far")
    rig = VirtualRig(scene)
    for st in scene.states:
        for j, p in enumerate(scene.projectors):
            write_graycode_folder(tmp_path / "root" / st.name / p.name, simulate_calibration(rig, st.name, j), bits=8)
    bundle = calibrate_folders(tmp_path / "root", {"*": (128, 96)})
    for (name, _, _), response in zip(bundle.projectors, bundle.responses):
        true_b = next(p.response_b[0] for p in scene.projectors if p.name == name)
        assert abs(float(response.b[0]) - true_b) < 0.05
    (tmp_path / "root" / "near").rename(tmp_path / "near")
    with pytest.raises(CaptureError, match=r"projector 'lower': no state's ramp captures fit its response; "
                                           r".*far.lower: the ramp capture shows only"):
        calibrate_folders(tmp_path / "root", {"*": (128, 96)})


def test_calibrating_captures_whose_white_is_clipped_says_which_folder(tmp_path, capsys):
    """A bench camera set too bright clips the white capture; calibrate says so per folder, with the fix."""
    data = small_config(camera=(200, 150), projector=(128, 96))
    data["camera"]["exposure"] = 3.6  # the near plane's white clipped nearly everywhere
    data["states"] = [s for s in data["states"] if s["name"] == "near"]
    scene = parse_scene(data, name="exposed")
    rig, root = VirtualRig(scene), tmp_path / "captures"
    for j, p in enumerate(scene.projectors):
        write_graycode_folder(root / "near" / p.name, simulate_calibration(rig, "near", j), bits=8)
    assert main(["calibrate", str(root), "--projector", "128x96", "--out", str(tmp_path / "calib")]) == 0
    err = capsys.readouterr().err
    for p in scene.projectors:
        assert f"warning: {root / 'near' / p.name}: the white capture is clipped at" in err, err
    assert "lower the camera's exposure" in err


def test_projectors_named_like_the_black_file_or_each_other_but_for_case_keep_their_own_maps(tmp_path):
    """A state folder holds each projector's map beside ``black.npz``: a projector named ``black`` had its
    map overwritten by the black level (``torchproj solve`` then said the file lacks ``prj_xy``:
    "calibrate again", which gave the same), and on macOS's and Windows' file systems ``a.npz`` and
    ``A.npz`` are one file. Each map comes back as it was written, and so does the black level."""
    from torchproj.calib import CalibrationBundle, write_bundle

    g = torch.Generator().manual_seed(0)
    names = ["black", "Black", "a", "A", "black_1"]
    camera, states = (5, 4), {}
    for state in ("near", "far"):
        states[state] = [{"prj_xy": torch.rand(4, 5, 2, generator=g) * 5, "valid": torch.ones(4, 5, dtype=torch.bool),
                          "contrast": torch.rand(4, 5, generator=g)} for _ in names]
    black = {state: torch.rand(1, 4, 5, generator=g) for state in states}
    bundle = CalibrationBundle(camera_size=camera, channels=1, projectors=[(n, 8, 6) for n in names], states=states,
                               black=black, responses=[None] * len(names))
    write_bundle(tmp_path / "calib", bundle)
    back = load_bundle(tmp_path / "calib")
    assert [n for n, _, _ in back.projectors] == names
    for state in states:
        torch.testing.assert_close(back.black[state], black[state])
        for j, written in enumerate(states[state]):
            for key, value in written.items():
                assert torch.equal(back.states[state][j][key], value), (state, names[j], key)
    files = [p.name.casefold() for p in (tmp_path / "calib" / "near").iterdir()]
    assert len(files) == len(set(files)) == len(names) + 1


def test_a_bundle_kept_in_the_capture_root_is_left_out_of_its_states(tmp_path):
    """``torchproj calibrate ROOT --out ROOT/calib`` put the bundle where the next calibrate looks for
    states, which then stopped at "projectors ... differ from calib's". It is left out, and said so."""
    from torchproj.calib.bundle import _projector_folders

    for state in ("far", "near"):
        for projector in ("lower", "upper"):
            (tmp_path / state / projector).mkdir(parents=True)
    (tmp_path / "calib" / "near").mkdir(parents=True)
    (tmp_path / "calib" / "bundle.json").write_text("{}")
    with pytest.warns(UserWarning, match=r"calib: a calibration bundle, not a state's captures: left out"):
        layout = _projector_folders(tmp_path, {"*": (64, 48)})
    assert list(layout) == ["far", "near"]
    assert [name for name, *_ in layout["near"]] == ["lower", "upper"]


def test_a_script_solves_a_bundle_for_tensors_and_targets_as_for_names(bench, tmp_path):
    """solve_bundle's targets from a script: (state, tensor) pairs and Targets solve as the names of the
    same images do; what is none of these is refused naming it, and the file-based loop, which keeps
    its targets by name, says so."""
    from torchproj.pipeline import refine_bundle, solve_bundle
    from torchproj.pipeline.targets import target_image
    from torchproj.transport import Target

    bundle = load_bundle(bench)
    by_name = solve_bundle(bundle, ["far=astronaut", "near=camera"], max_iter=20)
    images = {state: target_image(name, bundle.channels) for state, name in (("far", "astronaut"), ("near", "camera"))}
    by_tensor = solve_bundle(bundle, [("far", images["far"]), ("near", images["near"])], max_iter=20)
    by_target = solve_bundle(bundle, [Target("far", images["far"]), Target("near", images["near"], name="near")], max_iter=20)
    for other in (by_tensor, by_target):
        for name, pattern in by_name.patterns.items():
            assert torch.equal(other.patterns[name], pattern), name
    # Colour tensors on this grey bench are read as colour files are, by their luminance (they had
    # ended in torch's "shape [1, 120, 160] is invalid"); a Target made by hand is named instead.
    colour = {state: images[state].expand(3, -1, -1) for state in images}
    by_colour = solve_bundle(bundle, [("far", colour["far"]), ("near", colour["near"])], max_iter=20)
    for name, pattern in by_name.patterns.items():
        assert (by_colour.patterns[name].int() - pattern.int()).abs().max() <= 1, name
    with pytest.raises(InputError, match=r"target 'far' has 3 channel\(s\) and the camera 1"):
        solve_bundle(bundle, [Target("far", colour["far"], name="far"), Target("near", images["near"], name="near")])
    for bad in ([("far",)], [3], "far=astronaut", [("far", None)]):
        with pytest.raises(InputError, match="target"):
            solve_bundle(bundle, bad, max_iter=2)
    with pytest.raises(InputError, match="by name"):
        refine_bundle(bench, [("far", images["far"])], tmp_path / "loop")
    with pytest.raises(InputError, match="bundle folder"):
        refine_bundle(bundle, ["far=astronaut"], tmp_path / "loop")
    assert not (tmp_path / "loop").exists()
    from torchproj.calib import write_bundle

    for folder, given in ((None, bundle), (tmp_path / "copy", "bundle")):
        with pytest.raises(InputError, match="folder|bundle"):
            write_bundle(folder, given)
    assert not (tmp_path / "copy").exists()
