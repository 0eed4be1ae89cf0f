"""The exact-light reference against the simulator's own captures, and the ceiling in a run's report."""

import json

import pytest
import torch
import yaml

from torchproj.cli import main
from torchproj.core import InputError
from torchproj.pipeline import (CEILING_ITERATIONS, light_transport, run_markdown, run_virtual,
                                scene_targets, solve_on_light_transport)
from torchproj.pipeline.ceiling import bounce_terms
from torchproj.scene import parse_scene
from torchproj.solve import solve_patterns
from torchproj.transport import build_transport

from ..helpers import calibrate_once, small_config, small_scene


def _exact(name):
    if name == "grey_and_colour":  # one state's surface coloured, the other's grey
        config = small_config("colour_two_planes", camera=(200, 150), projector=(128, 96))
        config["surfaces"]["far_plane"]["albedo"] = 0.8
        scene = parse_scene(config, name=name)
    else:
        scene = small_scene(name, camera=(200, 150), projector=(128, 96))
    cal = calibrate_once(scene, oracle=True)
    targets = scene_targets(scene, None, cal.rig)
    rows = build_transport(cal.states, targets, merge=False)
    return scene, cal, targets, rows, light_transport(cal.rig, targets, rows)


@pytest.mark.parametrize("name", ["paper_two_planes", "colour_two_planes", "grey_and_colour", "two_screens"])
def test_prediction_is_the_noise_free_capture(name):
    """``A l`` equals what the simulator captures (noise-free, unquantised) minus its black capture, for
    any light, every row, every channel: grey surfaces share one operator, coloured ones get one per
    channel; a semi-transparent screen's light passes through to the surface behind."""
    scene, cal, targets, rows, ops = _exact(name)
    assert len(ops) == (3 if "colour" in name else 1)
    light = torch.rand(ops[0].shape[1], 1, generator=torch.Generator().manual_seed(0)) * 0.6
    images = ops[0].to_images(light)
    for k, target in enumerate(targets):
        shown = {j: images[j][None] ** (1 / torch.tensor(p.response_b).view(-1, 1, 1))
                 for j, p in enumerate(scene.projectors)}
        seen = cal.rig.capture(target.state, shown, noise=False, quantise=False)[0]
        dark = cal.rig.capture(target.state, {}, noise=False, quantise=False)[0]
        above_black = (seen - dark).flatten(1)
        for c, op in enumerate(ops):
            mine = op.row_target == k
            predicted = op.A(light)[mine, 0]
            captured = above_black[c, op.row_pixel[mine]]
            assert mine.sum() > 1000 and float(captured.max()) > 0.2
            torch.testing.assert_close(predicted, captured, rtol=1e-5, atol=1e-6)
    # Same rows and right-hand side as the operator it was built on (its targets and scale).
    assert all(torch.equal(op.row_pixel, rows.row_pixel) and op.scale == rows.scale for op in ops)
    torch.testing.assert_close(torch.cat([op.rhs for op in ops], 1), rows.rhs)


def test_the_bounce_term_adds_what_the_simulator_bounces():
    """With interreflection, ``A l + B l`` (the direct transport and the :class:`BounceTerm`) is the
    noise-free capture less black, every row and channel; without B the corner misses by the bounce."""
    scene, cal, targets, rows, ops = _exact("corner_screens")
    terms = bounce_terms(cal.rig, targets, ops)
    assert len(ops) == len(terms) == 3
    light = torch.rand(ops[0].shape[1], 1, generator=torch.Generator().manual_seed(0)) * 0.6
    images = ops[0].to_images(light)
    shown = {j: images[j][None] ** (1 / torch.tensor(p.response_b).view(-1, 1, 1)) for j, p in enumerate(scene.projectors)}
    seen = cal.rig.capture("corner", shown, noise=False, quantise=False)[0]
    dark = cal.rig.capture("corner", {}, noise=False, quantise=False)[0]
    above_black = (seen - dark).flatten(1)
    for c, (op, term) in enumerate(zip(ops, terms)):
        captured = above_black[c, op.row_pixel]
        torch.testing.assert_close(op.A(light)[:, 0] + term.forward(light)[:, 0], captured, rtol=1e-4, atol=1e-5)
        bounced = term.forward(light)[:, 0]
        assert float(bounced.mean()) > 0.05 * float(captured.mean())  # a corner bounces a good share
        # The adjoint is the forward map's transpose.
        r = torch.rand(op.shape[0], 1, generator=torch.Generator().manual_seed(c), dtype=torch.float64)
        v = torch.rand(op.shape[1], 1, generator=torch.Generator().manual_seed(9 + c), dtype=torch.float64)
        assert float((term.forward(v.float()).double() * r).sum()) == pytest.approx(
            float((term.adjoint(r.float()).double() * v).sum()), rel=1e-4)


def test_each_rows_light_sums_to_the_calibration_weight():
    """A row's entries over one projector's cells add up to that pixel's white minus black, which is
    the single weight calibration's nearest-cell model puts on one cell."""
    _, cal, _, rows, (op,) = _exact("paper_two_planes")
    ones = torch.zeros(op.shape[1], 1)
    for j in range(2):
        ones.zero_()[op.column_projector == j] = 1
        weight = cal.states["near"].weight[j].reshape(-1)[rows.row_pixel]
        mine = rows.row_target == 0
        torch.testing.assert_close(op.A(ones)[mine, 0], weight[mine], rtol=1e-4, atol=1e-6)
    # The exact light spreads over more cells than calibration's one per projector.
    assert op.nnz > 2 * rows.nnz


def test_light_transport_refuses_merged_rows():
    scene = small_scene(camera=(200, 150), projector=(128, 96))
    cal = calibrate_once(scene, oracle=True)
    targets = scene_targets(scene, None, cal.rig)
    with pytest.raises(InputError, match="merge=False"):
        light_transport(cal.rig, targets, build_transport(cal.states, targets))


def test_ceiling_is_the_optimum_of_the_exact_light(quarter_rig):
    """The ceiling's patterns are optimal for the exact light: the run's own patterns, put on the same
    exact operator, explain no more; and every target's row of the report carries its ceiling."""
    scene, cal = quarter_rig
    # The nearest-cell model: the default area footprint comes within 0.001 dB of the ceiling here,
    # where the captured PSNR may fall either side of the least-squares optimum's.
    result = run_virtual(scene, calibration=cal, ceiling=True, progress=False, footprint="nearest")
    rows = result.report["targets"]
    assert all(set(r["ceiling"]) == {"psnr_db", "ssim"} for r in rows)
    assert "ceiling PSNR (dB)" in run_markdown(result.report)
    # Near target: the exact light's optimum beats calibration's nearest-cell model (measured ~+1 dB).
    assert rows[0]["ceiling"]["psnr_db"] > rows[0]["psnr_db"]
    targets = scene_targets(scene, None, cal.rig)
    calibrated = build_transport(cal.states, targets, merge=False)
    (exact,) = light_transport(cal.rig, targets, calibrated)
    best, _, _ = solve_on_light_transport([exact], (0.0, 1.0), cal.responses, max_iter=CEILING_ITERATIONS)
    assert best.converged
    run_light = calibrated.to_images(solve_patterns(calibrated, "fista", (0.0, 1.0)).patterns)
    on_exact = torch.stack([run_light[j][0].reshape(-1)[c] for j, c in zip(exact.column_projector.tolist(),
                                                                           exact.column_cell.tolist())])[:, None]
    assert float(exact.objective(best.patterns)) <= float(exact.objective(on_exact)) * (1 + 1e-3)


def test_with_a_gain_and_offset_the_ceiling_is_asked_for_the_fitted_images(quarter_rig):
    """A run with a gain and offset is scored against the images it fitted (g t + o); its ceiling must
    be too, or a dimmed target's ceiling (scored against the image as given) falls below the run."""
    scene, cal = quarter_rig
    result = run_virtual(scene, calibration=cal, ceiling=True, progress=False, footprint="nearest",
                         gain_offset=((0.5, 0.7), (0.1, 0.2)))
    rows = result.report["targets"]
    assert all(r["gain"] <= 0.7 and r["psnr_db_original"] < r["psnr_db"] for r in rows)  # the images were refitted
    # The exact light for the same images beats the nearest-cell model, as without a gain (above).
    assert all(r["ceiling"]["psnr_db"] > r["psnr_db"] for r in rows), rows
    assert "for the images this run fitted" in run_markdown(result.report)


def test_a_run_that_maximises_ssim_is_measured_against_ssim_maximised_on_the_exact_light(quarter_rig):
    """With an image objective the ceiling is that objective solved on the exact light: what the
    transport oracle's run with the same objective captures (within what the two paths' captures differ
    by with least squares too, 0.0007 SSIM and 0.005 dB here), and above the least-squares ceiling's
    SSIM (which an SSIM run passes, so that a ceiling of least squares said nothing of it)."""
    scene, cal = quarter_rig
    ssim = run_virtual(scene, calibration=cal, ceiling=True, progress=False, objective="ssim").report
    plain = run_virtual(scene, calibration=cal, ceiling=True, progress=False).report
    oracle = run_virtual(scene, calibration=cal, oracle="transport", objective="ssim", progress=False,
                         max_iter=CEILING_ITERATIONS).report
    for row, least, exact in zip(ssim["targets"], plain["targets"], oracle["targets"]):
        assert row["ceiling"]["ssim"] == pytest.approx(exact["ssim"], abs=3e-3)
        assert row["ceiling"]["psnr_db"] == pytest.approx(exact["psnr_db"], abs=0.05)
        assert row["ceiling"]["ssim"] > least["ceiling"]["ssim"] + 0.01
    assert "then the ssim objective as this run" in run_markdown(ssim)
    assert "then the" not in run_markdown(plain)


def test_oracles_and_footprint_from_the_command_line(tmp_path, capsys):
    config = tmp_path / "small.yaml"
    config.write_text(yaml.safe_dump(dict(small_config(camera=(200, 150), projector=(128, 96)), name="small")))
    out = tmp_path / "run"
    assert main(["run", str(config), "--oracle", "transport", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["calibration"] == "oracle (the simulator's own light transport)" and report["graycode"] is None
    assert main(["run", str(config), "--oracle", "transport", "--solver", "eo", "--out", str(tmp_path / "eo")]) == 2
    assert "use a solver other than eo" in capsys.readouterr().err and not (tmp_path / "eo").exists()
    with pytest.raises(SystemExit):
        main(["run", str(config), "--oracle", "exact"])
    assert "invalid choice: 'exact'" in capsys.readouterr().err
    # The footprint of calibration's model is the user's choice, and the report says which was used.
    assert main(["run", str(config), "--oracle", "--footprint", "bilinear", "--out", str(tmp_path / "bilinear")]) == 0
    report = json.loads((tmp_path / "bilinear" / "report.json").read_text())
    assert report["footprint"] == "bilinear" and report["calibration"].startswith("oracle (the simulator's exact geo")
    assert "footprint: bilinear" in (tmp_path / "bilinear" / "report.md").read_text()


def test_a_bending_camera_is_refused_before_calibrating(tmp_path, capsys):
    config = small_config(camera=(200, 150), projector=(128, 96))
    config["camera"]["gamma"] = 2.2
    path = tmp_path / "gamma.yaml"
    path.write_text(yaml.safe_dump(dict(config, name="gamma")))
    for option in (["--ceiling"], ["--oracle", "transport"]):
        assert main(["run", str(path), *option, "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        assert "linear in the camera's values only with gamma 1" in err and "calibrat" not in err
        assert not (tmp_path / "out").exists()


def _border_sums(op, j):
    """Per row of ``op``, the light of projector ``j`` and whether it reaches ``j``'s border cells."""
    w, h = op.projector_sizes[j]
    mine = op.column_projector[op.col] == j
    cell = op.column_cell[op.col]
    edge = mine & ((cell % w == 0) | (cell % w == w - 1) | (cell // w == 0) | (cell // w == h - 1))
    row = torch.repeat_interleave(torch.arange(op.shape[0]), op.crow.diff())
    total = torch.zeros(op.shape[0]).index_add_(0, row[mine], op.val[mine])
    return total, torch.zeros(op.shape[0], dtype=torch.bool).index_put_((row[edge],), torch.tensor(True))


def test_rows_past_the_projectors_edge_carry_the_light_the_pixel_measured():
    """A wall wider than the projectors' field: a camera pixel whose square runs past a projector's
    edge is lit only by its samples on the projector, and its measured white minus black is their
    light alone. The ``area`` rows give those samples the whole weight, as the exact light does
    (with each sample a fixed share of the square, such rows fell short by up to half of it)."""
    # Camera pixels about two cells wide, so that a pixel on the edge has many samples past it.
    config = small_config(camera=(64, 48), projector=(128, 96), supersampling=4)
    config["surfaces"]["near_plane"]["size"] = [1.2, 0.9]  # the projectors light about 0.53 x 0.40 m of it
    config["states"] = [{"name": "near", "surfaces": ["near_plane"]}]
    scene = parse_scene(config, name="wide_wall")
    cal = calibrate_once(scene, oracle=True)  # the exact maps and weights: only the footprint differs
    targets = scene_targets(scene, None, cal.rig)
    rows = build_transport(cal.states, targets, footprint="area", merge=False)
    (exact,) = light_transport(cal.rig, targets, rows)
    for j in range(len(rows.projector_sizes)):
        model, _ = _border_sums(rows, j)
        light, border = _border_sums(exact, j)
        border &= model > 0  # the pixels whose centre the projector lights (the others have no map for it)
        assert int(border.sum()) > 50
        error = (model[border] / light[border] - 1).abs()
        # The oracle's weight is the exact row's total; what is left is rows that also reach cells the
        # exact light does not (their samples' cells against the camera's), not light lost off the edge.
        assert float(error.median()) < 0.01 and float(error.quantile(0.9)) < 0.05, (j, error.median(), error.max())
