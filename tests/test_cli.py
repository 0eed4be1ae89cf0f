import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

import torchproj
from torchproj.cli import main
from torchproj.scene import BUILTIN_SCENES

from .helpers import small_config


@pytest.mark.parametrize("name", BUILTIN_SCENES)
def test_scene_describes_builtin_configs(name, capsys):
    assert main(["scene", name]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"scene {name}") and "projector" in out and "state" in out


def test_bad_config_exits_with_a_named_field(tmp_path, capsys):
    data = small_config()
    data["camera"]["focal"] = -1
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    assert main(["scene", str(path)]) == 2
    assert "camera.focal: must be greater than 0" in capsys.readouterr().err


def test_simulate_then_decode_the_written_folders(tmp_path, capsys):
    path = tmp_path / "small.yaml"
    path.write_text(yaml.safe_dump(dict(small_config(camera=(240, 180), projector=(128, 96)), name="small")))
    out = tmp_path / "sim"
    assert main(["simulate", str(path), "--out", str(out), "--write-captures"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["scene"] == "small" and len(report["calibrations"]) == 4
    for row in report["calibrations"]:
        assert row["decoding_integer"]["decoded"] > 0.99 and row["decoding_integer"]["exact"] > 0.999
        assert row["decoding_subpixel"]["rms_px"] < row["decoding_integer"]["rms_px"]
        assert abs(row["response_fit"]["b"][0] - row["response_true_b"][0]) < 0.1
        assert 0.003 < row["capture_noise"] < 0.03  # this camera's, about 1% of white - black
    assert "| noise |" in (out / "report.md").read_text()
    for name in ("report.md", "calibration.png", "calibration/near/upper/correspondence.npz"):
        assert (out / name).is_file()
    # The written capture folder is a real capture to the decoder.
    dec = tmp_path / "dec"
    assert main(["decode", str(out / "captures" / "far" / "lower"), "--projector", "128x96", "--out", str(dec)]) == 0
    got = np.load(dec / "correspondence.npz")["prj_xy"]
    want = np.load(out / "calibration" / "far" / "lower" / "correspondence.npz")["prj_xy_integer"]
    assert np.array_equal(np.isnan(got), np.isnan(want)) and np.array_equal(got[~np.isnan(got)], want[~np.isnan(want)])
    # Each folder holds sequence.json, as torchproj capture leaves it, naming the images there (a grey
    # camera's rig took no primaries): calibrate reads the projectors' sizes from it, where it had
    # asked for --projector.
    manifest = json.loads((out / "captures" / "far" / "lower" / "sequence.json").read_text())
    assert manifest["projector"] == [128, 96] and "bits" not in manifest
    assert sorted(e["file"] for e in manifest["images"]) == sorted(
        f.name for f in (out / "captures" / "far" / "lower").glob("*.png"))
    assert not any(e["kind"] == "primary" for e in manifest["images"])
    assert main(["calibrate", str(out / "captures"), "--out", str(tmp_path / "bundle")]) == 0
    bundle = json.loads((tmp_path / "bundle" / "bundle.json").read_text())
    assert bundle["projectors"] == [{"name": "lower", "size": [128, 96]}, {"name": "upper", "size": [128, 96]}]
    # decode reads the size from it too (it had required --projector), and a size that is not its
    # projector's is refused naming both, nothing written.
    assert main(["decode", str(out / "captures" / "far" / "lower"), "--out", str(tmp_path / "dec_said")]) == 0
    assert np.array_equal(np.load(tmp_path / "dec_said" / "correspondence.npz")["prj_xy"], got, equal_nan=True)
    assert main(["decode", str(out / "captures" / "far" / "lower"), "--projector", "256x192", "--out",
                 str(tmp_path / "d")]) == 2
    capsys.readouterr()
    assert main(["decode", str(out / "captures" / "far" / "lower"), "--bits", "3", "--out", str(tmp_path / "d")]) == 2
    assert "its sequence.json says [7, 7] Gray-code pattern pairs per axis, and bits 3" in capsys.readouterr().err
    assert main(["decode", str(tmp_path / "nowhere"), "--out", str(tmp_path / "d")]) == 2
    assert "nowhere: capture folder not found" in capsys.readouterr().err  # not a size it could not read there
    assert not (tmp_path / "d").exists()


def test_simulate_writes_a_mean_of_frames_at_16_bits(tmp_path):
    """camera.frames: 4 makes each capture the mean of four 8-bit frames, which an 8-bit file would
    round back to one frame's levels: the folders hold 16-bit PNGs with levels between, and they
    decode as the calibration simulate ran on them."""
    import cv2

    path = tmp_path / "averaged.yaml"
    data = dict(small_config(camera=(160, 120), projector=(128, 96), frames=4), name="averaged")
    path.write_text(yaml.safe_dump(data))
    out = tmp_path / "sim"
    assert main(["simulate", str(path), "--out", str(out), "--write-captures"]) == 0
    first = cv2.imread(str(out / "captures" / "near" / "upper" / "graycode_00.png"), cv2.IMREAD_UNCHANGED)
    assert first.dtype == np.uint16
    levels = np.unique(first)
    assert not np.allclose(levels / 65535 * 255, np.round(levels / 65535 * 255), atol=1e-3)  # between 8-bit levels
    dec = tmp_path / "dec"
    assert main(["decode", str(out / "captures" / "near" / "upper"), "--projector", "128x96", "--out", str(dec)]) == 0
    got = np.load(dec / "correspondence.npz")["prj_xy"]
    want = np.load(out / "calibration" / "near" / "upper" / "correspondence.npz")["prj_xy_integer"]
    assert np.array_equal(np.isnan(got), np.isnan(want)) and np.array_equal(got[~np.isnan(got)], want[~np.isnan(want)])
    # Four frames a capture halve the noise its white - black carries.
    noise = [r["capture_noise"] for r in json.loads((out / "report.json").read_text())["calibrations"]]
    assert all(0.002 < n < 0.008 for n in noise)


@pytest.mark.slow
def test_simulate_a_shortened_sequence_checks_the_fitted_maps(tmp_path):
    path = tmp_path / "small.yaml"
    path.write_text(yaml.safe_dump(dict(small_config(camera=(240, 180), projector=(128, 96)), name="small")))
    out = tmp_path / "sim"
    assert main(["simulate", str(path), "--out", str(out), "--bits", "3", "--write-captures"]) == 0
    report = json.loads((out / "report.json").read_text())
    for row in report["calibrations"]:
        # 16-cell blocks decoded, a map within a tenth of a cell of the simulator's truth fitted to them.
        assert row["block_cells"] == [16, 16] and row["decoding_integer"]["rms_px"] > 4
        assert row["decoding_subpixel"]["rms_px"] < 0.1
        assert abs(row["response_fit"]["b"][0] - row["response_true_b"][0]) < 0.1
    assert "| 16x16 |" in (out / "report.md").read_text()
    assert json.loads((out / "captures" / "far" / "lower" / "sequence.json").read_text())["bits"] == [3, 3]
    # The written 14-image folder decodes to the same fitted map; read as a full sequence it is refused.
    folder = out / "captures" / "far" / "lower"
    dec = tmp_path / "dec"
    assert main(["decode", str(folder), "--projector", "128x96", "--bits", "3", "--out", str(dec)]) == 0
    got = np.load(dec / "correspondence.npz")["prj_xy_refined"]
    want = np.load(out / "calibration" / "far" / "lower" / "correspondence.npz")["prj_xy"]
    assert np.array_equal(np.isnan(got), np.isnan(want)) and np.allclose(got[~np.isnan(got)], want[~np.isnan(want)])
    assert json.loads((dec / "report.json").read_text())["homography"]["block_cells"] == [16, 16]
    # Its sequence.json says the size and bits: decode needs neither option. Without it, the folder read as
    # a full sequence is refused.
    assert main(["decode", str(folder), "--out", str(tmp_path / "said")]) == 0
    assert np.array_equal(np.load(tmp_path / "said" / "correspondence.npz")["prj_xy_refined"], got, equal_nan=True)
    bare = tmp_path / "bare"
    shutil.copytree(folder, bare)
    (bare / "sequence.json").unlink()
    assert main(["decode", str(bare), "--projector", "128x96", "--out", str(tmp_path / "full")]) == 2


def test_failed_decode_writes_nothing(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    out = tmp_path / "dec"
    assert main(["decode", str(empty), "--projector", "64x48", "--out", str(out)]) == 2
    assert "expected 26 images" in capsys.readouterr().err
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["empty"]


def test_projector_size_is_checked(capsys):
    with pytest.raises(SystemExit):
        main(["decode", "x", "--projector", "1024by768", "--out", "y"])
    assert "expected WIDTHxHEIGHT" in capsys.readouterr().err


@pytest.mark.slow
def test_console_script_is_installed(tmp_path):
    """The ``torchproj`` command beside this interpreter (what ``pip install`` puts on the PATH), run
    from a folder outside the checkout."""
    script = Path(sys.executable).parent / "torchproj"
    assert script.is_file(), f"no torchproj command beside {sys.executable}: pip install -e . first"
    out = subprocess.run([str(script), "--version"], capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0 and out.stdout.strip() == f"torchproj {torchproj.__version__}"
    out = subprocess.run([str(script), "scene", "three_planes"], capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0 and "state c: plane_c" in out.stdout, out.stderr


def test_ssim_objective_from_the_command_line(tmp_path, capsys):
    path = tmp_path / "small.yaml"
    path.write_text(yaml.safe_dump(dict(small_config(camera=(240, 180), projector=(128, 96)), name="small")))
    out = tmp_path / "run"
    assert main(["run", str(path), "--out", str(out), "--objective", "mixed", "--ssim-iter", "8",
                 "--psnr-drop", "0.5"]) == 0
    report = json.loads((out / "report.json").read_text())
    image = report["image_objective"]
    assert image["name"] == "mixed" and image["l2_weight"] == 1.0 and image["psnr_drop_db"] == 0.5
    assert image["iterations"] <= 8 and min(image["model_psnr_change_db"]) > -0.6
    assert "Image objective: mixed" in (out / "report.md").read_text()
    capsys.readouterr()
    assert main(["run", str(path), "--out", str(tmp_path / "bad"), "--l2-weight", "0.3"]) == 2
    assert "give it with objective 'ssim' or 'mixed'" in capsys.readouterr().err and not (tmp_path / "bad").exists()


@pytest.mark.slow
def test_main_job_on_the_full_resolution_paper_rig(tmp_path):
    """`torchproj simulate` with no arguments: the README's first command, at full resolution."""
    out = tmp_path / "sim"
    assert main(["simulate", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["scene"] == "paper_two_planes"
    for row in report["calibrations"]:
        assert row["decoding_integer"]["decoded"] > 0.999 and row["decoding_integer"]["exact"] > 0.9999
        assert row["decoding_subpixel"]["rms_px"] < 0.12
        assert abs(row["response_fit"]["b"][0] - row["response_true_b"][0]) < 0.03
        assert abs(row["compensated_ramp_sum"]["mean"] - 1) < 0.01 and row["compensated_ramp_sum"]["std"] < 0.03


@pytest.mark.slow
def test_run_with_no_arguments_on_the_full_resolution_paper_rig(tmp_path, monkeypatch):
    """`torchproj run`: the README's first command, as a newcomer runs it."""
    monkeypatch.chdir(tmp_path)
    assert main(["run"]) == 0
    report = json.loads((tmp_path / "out" / "run" / "report.json").read_text())
    assert report["scene"] == "paper_two_planes" and report["solver"] == "fista"
    near, far = report["targets"]
    assert near["psnr_db"] > 17 and far["psnr_db"] > 16.5
    assert near["ssim"] > 0.5 and far["ssim"] > 0.5
    # Its time is a benchmark's to measure (docs/measured.md), never a test's: a busy machine is slow.
    assert set(report["timings_s"]) >= {"calibrate", "transport", "solve", "evaluate", "total"}


def test_out_never_takes_a_persons_files_and_an_interrupt_exits_130(tmp_path, capsys, monkeypatch):
    out = tmp_path / "seq"
    (out / "captures").mkdir(parents=True)
    (out / "captures" / "graycode_00.png").write_bytes(b"theirs")
    assert main(["sequence", "--projector", "64x48", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "holds captures, which torchproj did not write" in err and "nothing was touched" in err
    assert (out / "captures" / "graycode_00.png").read_bytes() == b"theirs"
    # Its own output it replaces; Ctrl-C (or SIGTERM) while writing leaves that whole and exits 130.
    mine = tmp_path / "mine"
    assert main(["sequence", "--projector", "64x48", "--out", str(mine)]) == 0
    before = sorted(p.name for p in mine.iterdir())
    import torchproj.calib as calib

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(calib, "write_sequence", interrupted)
    assert main(["sequence", "--projector", "64x48", "--out", str(mine)]) == 130
    assert "interrupted; " in capsys.readouterr().err
    assert sorted(p.name for p in mine.iterdir()) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine", "seq"]


@pytest.mark.parametrize("screen", ["abc", "1", "1,2,3", "1.5,2", ""])
def test_capture_refuses_a_screen_corner_it_cannot_read_naming_the_option(screen, tmp_path, capsys):
    """``torchproj capture --screen abc`` ended in a ValueError traceback, and ``1,2,3`` in OpenCV's TypeError."""
    with pytest.raises(SystemExit) as stopped:
        main(["capture", str(tmp_path), "--out", str(tmp_path / "cap"), f"--screen={screen}"])
    assert stopped.value.code == 2
    assert "argument --screen: expected X,Y in whole pixels" in capsys.readouterr().err
    assert not (tmp_path / "cap").exists()


def test_a_screen_left_of_the_main_one_is_read_as_written():
    from torchproj.cli import build_parser
    from torchproj.cli_options import join_negative_pairs

    args = build_parser().parse_args(join_negative_pairs(["capture", "seq", "--out", "cap", "--screen", "-1920,0"]))
    assert args.screen == (-1920, 0)
    assert build_parser().parse_args(["capture", "seq", "--out", "cap"]).screen == (0, 0)


def test_out_is_refused_where_it_is_or_holds_what_the_command_reads(tmp_path, capsys):
    """``--out`` replaces a folder torchproj wrote, and an input is often one: ``torchproj solve calib
    --out calib`` replaced the bundle it had just read with its patterns. Refused before any work,
    naming the input; nothing is touched."""
    seq = tmp_path / "seq"
    assert main(["sequence", "--projector", "64x48", "--out", str(seq)]) == 0
    before = sorted(p.name for p in seq.iterdir())
    image = seq / "graycode_00.png"
    for argv, what in ((["solve", str(seq), "--out", str(seq), "--targets", "a=astronaut"], "is this command's calibration bundle"),
                       (["capture", str(seq), "--out", str(seq)], "is this command's sequence folder"),
                       (["solve", str(tmp_path / "calib"), "--out", str(seq), "--targets", f"a={image}"],
                        f"holds {image}, this command's --targets image"),
                       (["decode", str(seq), "--projector", "64x48", "--out", str(seq)], "is this command's capture folder")):
        capsys.readouterr()
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert f"output folder {seq}: {what}" in err and "nothing was touched" in err, err
        assert sorted(p.name for p in seq.iterdir()) == before
    # An --out apart from its inputs is the command's to write: it goes on to read them (here, no bundle).
    assert main(["solve", str(tmp_path / "calib"), "--out", str(tmp_path / "patterns"), "--targets", f"a={image}"]) == 2
    assert "not a calibration bundle" in capsys.readouterr().err


@pytest.mark.parametrize("size, message", [("1x1", "projector 1x1: a Gray code needs at least 2 x 2 cells"),
                                           ("16x8", "projector 16x8: narrower than the ramp's 32 bars"),
                                           ("64x64 --ramp-steps 1", "ramp_steps (--ramp-steps, the ramp's bars) must be "
                                                                    "a whole number >= 2, got 1")])
def test_a_projector_too_small_for_the_sequence_is_named(tmp_path, capsys, size, message):
    assert main(["sequence", "--projector", *size.split(), "--out", str(tmp_path / "seq")]) == 2
    assert message in capsys.readouterr().err and not (tmp_path / "seq").exists()


@pytest.mark.parametrize("args, message", [
    (["--solver", "eo", "--smoothness", "0.01"], "smoothness is for the least-squares solvers"),
    (["--smoothness", "-1"], "smoothness must be a number >= 0"),
    (["--smoothness", "nan"], "smoothness must be a number >= 0"),
    (["--oracle", "transport", "--smoothness", "0.01"], "solved without a smoothness penalty"),
])
def test_a_smoothness_the_run_cannot_use_is_refused_before_any_work(tmp_path, capsys, args, message):
    out = tmp_path / "out"
    assert main(["run", *args, "--out", str(out)]) == 2
    assert message in capsys.readouterr().err and not out.exists()


def test_sequence_asks_for_the_projector_it_writes_for(tmp_path, capsys):
    """decode's --projector became optional (a folder's sequence.json says it); sequence's, which writes
    the sequence for that size, went optional with it by mistake and ended in a TypeError. It is asked for."""
    with pytest.raises(SystemExit) as stopped:
        main(["sequence", "--out", str(tmp_path / "seq")])
    assert stopped.value.code == 2 and "the following arguments are required: --projector" in capsys.readouterr().err
    assert not (tmp_path / "seq").exists()


def test_decode_names_the_folder_whose_sequence_json_holds_bad_bits(tmp_path, capsys):
    folder = tmp_path / "capture"
    folder.mkdir()
    (folder / "sequence.json").write_text(json.dumps({"projector": [64, 48], "bits": "x"}))
    assert main(["decode", str(folder), "--out", str(tmp_path / "dec")]) == 2
    assert f"{folder}: Gray-code bits 'x': bits must be a whole number" in capsys.readouterr().err
    assert not (tmp_path / "dec").exists()
