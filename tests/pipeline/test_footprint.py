"""footprint="auto": the choice from the calibration's own shares, checked against the captures it predicts."""

import json

import pytest
import torch
import yaml

from torchproj.cli import main
from torchproj.core import InputError
from torchproj.pipeline import choose_footprint, run_virtual, scene_targets
from torchproj.pipeline.footprint import SCREEN_ITERATIONS, _back_projected_loss, _expected_loss, _share_rows
from torchproj.scene import builtin_config, load_scene, parse_scene, scale_config
from torchproj.solve import solve_fista
from torchproj.transport import build_transport

from ..helpers import calibrate_once


def _fine_camera():
    """The paper's rig seen by a camera whose pixels are a seventh of a cell across: each pixel's light
    stays on one cell, and nearest has nothing to lose."""
    data = scale_config(yaml.safe_load(builtin_config("paper_two_planes").read_text()), camera=(600, 450),
                        projector=(96, 72))
    data["camera"]["supersampling"] = 1
    return parse_scene(data, name="fine_camera")


def test_auto_keeps_nearest_where_the_shares_say_a_pixel_sees_one_cell():
    scene = _fine_camera()
    cal = calibrate_once(scene)
    choice = choose_footprint(cal.states, scene_targets(scene, None, cal.rig))
    assert choice.footprint == "nearest"
    assert max(choice.expected_loss_db.values()) < 0.2 and "within 0.2 dB" in choice.reason
    assert choice.iterations > SCREEN_ITERATIONS  # under the tolerance early: nearest solved on before deciding
    # The captures agree: area gains no more than the tolerance over nearest.
    runs = {fp: run_virtual(scene, footprint=fp, calibration=cal, progress=False) for fp in ("auto", "nearest", "area")}
    assert runs["auto"].report["footprint"] == "nearest"
    assert runs["auto"].report["footprint_choice"]["footprint"] == "nearest"
    for near, area in zip(runs["nearest"].report["targets"], runs["area"].report["targets"]):
        assert area["psnr_db"] - near["psnr_db"] < 0.2


def test_auto_takes_area_where_pixels_span_cells_and_says_why():
    """A suite scene whose camera pixels cover about a projector cell: nearest's expected loss is
    over the tolerance, and the captures show it losing more than that."""
    scene = load_scene("suite-7-1")
    cal = calibrate_once(scene)
    choice = choose_footprint(cal.states, scene_targets(scene, None, cal.rig))
    assert choice.footprint == "area"
    worst = max(choice.expected_loss_db, key=choice.expected_loss_db.get)
    assert choice.expected_loss_db[worst] > 0.2 and worst in choice.reason
    # Decided on the targets' back-projection, before nearest was built: its estimate is under the one
    # after nearest's first iterations, and that under the one nearest solved to the end gives.
    assert choice.iterations == 0 and "back-projection" in choice.reason
    targets = scene_targets(scene, None, cal.rig)
    op = build_transport(cal.states, targets, footprint="nearest", merge=False)
    shares = _share_rows(cal.states, targets, op)
    early = _expected_loss(op, shares, solve_fista(op, (0.0, 1.0), progress=False, max_iter=SCREEN_ITERATIONS).patterns,
                           targets)
    solved = solve_fista(op, (0.0, 1.0), progress=False, max_iter=300)
    assert solved.iterations > SCREEN_ITERATIONS
    final = _expected_loss(op, shares, solved.patterns, targets)
    assert all(choice.expected_loss_db[name] <= early[name] + 1e-9 <= final[name] + 2e-9 for name in final)
    # Screened: no start from nearest's early patterns, so auto shows exactly what area shows.
    assert choice.start_for(op) is None
    auto = run_virtual(scene, footprint="auto", calibration=cal, progress=False)
    area = run_virtual(scene, footprint="area", calibration=cal, progress=False)
    assert all(torch.equal(a, b) for a, b in zip(auto.patterns, area.patterns))
    near = run_virtual(scene, footprint="nearest", calibration=cal, progress=False)
    assert auto.report["footprint"] == "area" and "footprint" in auto.report["timings_s"]
    target = [t["name"] for t in auto.report["targets"]].index(worst)
    assert auto.report["targets"][target]["psnr_db"] - near.report["targets"][target]["psnr_db"] > 0.2


@pytest.mark.parametrize("name", ["quarter", "suite-1-0"])
def test_the_back_projections_estimate_is_the_one_nearests_operator_gives(quarter_rig, name):
    """The screen's estimate, taken from nearest's rows without building its operator, against the same
    estimate through the operator: its patterns ``A^T b / A^T A 1`` clamped to the box, its products
    and the shares' CSR rows (two states and two projectors; a colour scene, three channels)."""
    if name == "quarter":
        scene, cal = quarter_rig
    else:
        scene = load_scene(name)
        cal = calibrate_once(scene)
    targets = scene_targets(scene, None, cal.rig)
    op = build_transport(cal.states, targets, footprint="nearest", merge=False)
    with torch.no_grad():
        given = op.A_adjoint(op.A(torch.ones(op.shape[1], op.channels)))
        patterns = (op.A_adjoint(op.rhs) / given).clamp(0.0, 1.0)
    expected = _expected_loss(op, _share_rows(cal.states, targets, op), patterns, targets)
    loss = _back_projected_loss(cal.states, targets, (0.0, 1.0))
    assert loss.keys() == expected.keys() and len(loss) == len(targets)
    for key in loss:
        assert loss[key] == pytest.approx(expected[key], rel=1e-4, abs=1e-6)
    assert max(loss.values()) > 0.01  # the case tells the two apart: light across the cells' edges


def test_auto_keeps_the_richest_where_no_shares_were_measured():
    scene = load_scene("paper_two_planes", scale=0.25)
    cal = calibrate_once(scene, bits=3)
    choice = choose_footprint(cal.states, scene_targets(scene, None, cal.rig))
    assert choice.footprint == "area" and choice.expected_loss_db is None and "no cell shares" in choice.reason


@pytest.mark.parametrize("bad", [-0.1, float("nan"), "0.2"])
def test_a_bad_tolerance_is_refused(quarter_rig, bad):
    scene, cal = quarter_rig
    with pytest.raises(InputError, match="tolerance_db"):
        choose_footprint(cal.states, scene_targets(scene, None, cal.rig), tolerance_db=bad)


def test_one_target_without_a_list_is_named(quarter_rig):
    scene, cal = quarter_rig
    with pytest.raises(InputError, match="targets must be a list of Target, got Target"):
        choose_footprint(cal.states, scene_targets(scene, None, cal.rig)[0])


def test_an_unknown_footprint_is_refused_before_any_work(quarter_rig):
    scene, _ = quarter_rig
    with pytest.raises(InputError, match="footprint must be one of"):
        run_virtual(scene, footprint="widest")


def test_the_command_reports_the_choice(tmp_path):
    out = tmp_path / "run"
    assert main(["run", "suite-7-2", "--footprint", "auto", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["footprint"] in ("nearest", "area")
    assert report["footprint_choice"]["footprint"] == report["footprint"]
    assert "chosen by auto" in (out / "report.md").read_text()
