"""The main job on a small virtual rig: what it writes and what it measures."""

import json

import pytest
import torch
import yaml

from torchproj.cli import main
from torchproj.evaluate import calibrate_virtual, crosstalk, masked_ssim, run_virtual
from torchproj.scene import parse_scene

from ..helpers import small_config


@pytest.fixture(scope="module")
def config(tmp_path_factory):
    path = tmp_path_factory.mktemp("cfg") / "small.yaml"
    path.write_text(yaml.safe_dump(dict(small_config(camera=(400, 300), projector=(256, 192)), name="small")))
    return path


def test_run_writes_a_complete_report(config, tmp_path):
    out = tmp_path / "run"
    assert main(["run", str(config), "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    for key in ("scene", "solver", "model", "timings_s", "objective", "targets", "evaluation"):
        assert key in report
    assert set(report["model"]) == {"variables", "rows", "nnz"}
    assert set(report["timings_s"]) == {"calibrate", "transport", "solve", "evaluate", "total"}
    assert [t["name"] for t in report["targets"]] == ["near", "far"]
    for t in report["targets"]:
        assert t["psnr_db"] > 15 and t["ssim"] > 0.4 and 0 <= t["crosstalk"] < 0.5
    for name in ("report.md", "overview.png", "patterns/upper.png", "patterns/lower.png", "captures/near.png",
                 "captures/far.png"):
        assert (out / name).is_file(), name


def test_bounded_solver_beats_the_baseline_on_the_captures(config):
    scene = parse_scene(yaml.safe_load(config.read_text()))
    cal = calibrate_virtual(scene)  # one calibration, three solvers
    fista = run_virtual(scene, solver="fista", calibration=cal).report["targets"]
    lf = run_virtual(scene, solver="lf", calibration=cal).report["targets"]
    eo_neg = run_virtual(scene, solver="eo", bounds_8bit=(-100, 255), calibration=cal).report["targets"]
    for a, b, c in zip(fista, lf, eo_neg):
        assert a["psnr_db"] > b["psnr_db"] + 5 and a["ssim"] > b["ssim"]
        assert a["psnr_db"] > c["psnr_db"]


def test_bad_bounds_are_refused_before_any_work(config, tmp_path, capsys):
    out = tmp_path / "run"
    with pytest.raises(SystemExit):
        main(["run", str(config), "--out", str(out), "--bounds", "255,0"])
    assert "LO < HI" in capsys.readouterr().err and not out.exists()


def test_ssim_and_crosstalk_measure_what_they_say():
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(1, 40, 40, generator=g), torch.rand(1, 40, 40, generator=g)
    mask = torch.zeros(40, 40, dtype=torch.bool)
    mask[5:35, 5:35] = True
    assert masked_ssim(a, a, mask) == pytest.approx(1.0)
    assert masked_ssim(b, a, mask) < 0.2
    mix = 0.7 * a + 0.3 * b
    assert crosstalk(mix, [b], mask) > crosstalk(a, [b], mask) + 0.2
    assert crosstalk(a, [], mask) == 0.0
