"""Image-space objectives: SSIM of the predicted images, judged on the virtual rig's captures."""

import math

import pytest
import torch

from torchproj.core import InputError
from torchproj.metrics import SSIMLoss
from torchproj.pipeline import run_virtual, scene_targets
from torchproj.solve import OBJECTIVES, ImageLoss, ProjectionModel, image_objective, solve_fista, solve_ssim
from torchproj.transport import build_transport

from ..helpers import synthetic_calibration, targets


@pytest.fixture
def quarter(quarter_rig):
    return quarter_rig


def test_ssim_objective_raises_the_captured_ssim(quarter):
    scene, cal = quarter
    l2 = run_virtual(scene, calibration=cal, progress=False)
    ssim = run_virtual(scene, calibration=cal, progress=False, objective="ssim")
    for a, b in zip(l2.report["targets"], ssim.report["targets"]):
        assert b["ssim"] > a["ssim"] + 0.03, (a, b)
        assert b["psnr_db"] > a["psnr_db"] - 1.0, (a, b)
    image = ssim.report["image_objective"]
    assert image["name"] == "ssim" and image["l2_weight"] == OBJECTIVES["ssim"] and image["psnr_drop_db"] == 1.0
    assert image["start"]["solver"] == "fista" and image["iterations"] >= 6
    assert min(image["model_psnr_change_db"]) > -1.1  # the budget holds in the model
    # The least-squares objective reported is that of the patterns solved, which the SSIM moved off its optimum.
    assert ssim.report["objective"] > l2.report["objective"]


def test_more_weight_on_the_squared_error_keeps_closer_to_least_squares(quarter):
    scene, cal = quarter
    targets_ = scene_targets(scene, rig=cal.rig)
    op = build_transport(cal.states, targets_, merge=False)
    start = solve_fista(op, (0, 1)).patterns
    light, heavy = (solve_ssim(op, (0, 1), l2_weight=w, psnr_drop=None, x0=start, max_iter=20) for w in (0.1, 3.0))
    assert light.info["l2_objective"] > heavy.info["l2_objective"] > 0.999 * light.info["start_l2_objective"]
    assert min(light.info["model_ssim"]) > 0
    assert sum(light.info["model_ssim"]) > sum(heavy.info["model_ssim"])


def test_ssim_solve_descends_stays_in_its_box_and_reports_the_model_ssim():
    op = build_transport(synthetic_calibration(shape=(40, 50)), targets(channels=3), merge=False, scale=0.8)
    res = solve_ssim(op, (-0.2, 1.0), l2_weight=0.1, max_iter=40)
    assert res.history[-1][1] < res.history[0][1]
    assert float(res.patterns.min()) >= -0.2 and float(res.patterns.max()) <= 1.0
    model = ProjectionModel(op, (-0.2, 1.0), start=res.patterns)
    loss = SSIMLoss(model.targets, model.mask)
    with torch.no_grad():
        assert res.info["model_ssim"] == pytest.approx((1 - loss(model())).tolist(), abs=1e-6)


def test_a_start_below_black_is_refined_in_its_own_box():
    """EO_-100^255's box reaches below black; ``--objective ssim`` on its patterns stopped at "start
    must lie in the bounds [0, 1]": the loss built a model in the default box only to read its
    targets. The loss and the solve take such a start, and the solve stays in the box given."""
    op = build_transport(synthetic_calibration(shape=(40, 50)), targets(), merge=False, scale=0.8).double()
    lo = -100 / 255
    start = (torch.rand(op.shape[1], 1, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 1.5
             + lo).clamp(lo, 1.0)
    assert float(start.min()) < -0.3
    loss = ImageLoss(op, start, l2_weight=0.3, psnr_drop=None)
    model = ProjectionModel(op, (lo, 1.0), start=start)
    with torch.no_grad():
        dissimilarity = SSIMLoss(model.targets, model.mask)(model())  # 1 - SSIM per target
    assert float(loss(start)) == pytest.approx(float(dissimilarity.mean()) + 0.3, rel=1e-12)
    res = solve_ssim(op, (lo, 1.0), x0=start, max_iter=10)
    assert float(res.patterns.min()) >= lo and float(res.patterns.max()) <= 1.0
    assert res.objective <= res.history[0][1]
    with pytest.raises(InputError, match=r"start must have shape \(\d+, 1\) \(columns, channels\), got \(3, 1\)"):
        ImageLoss(op, start[:3])


def test_the_psnr_budget_holds_where_the_weight_alone_would_give_a_target_away(quarter):
    scene, cal = quarter
    op = build_transport(cal.states, scene_targets(scene, rig=cal.rig), merge=False)
    start = solve_fista(op, (0, 1)).patterns
    free, held = (solve_ssim(op, (0, 1), l2_weight=0.0, psnr_drop=d, x0=start, max_iter=40) for d in (None, 0.5))
    assert min(free.info["model_psnr_change_db"]) < -1.0  # pure SSIM gives PSNR away
    assert min(held.info["model_psnr_change_db"]) > -0.6  # the hinge keeps each target within ~0.5 dB
    model = ProjectionModel(op, (0, 1), start=start)
    with torch.no_grad():
        start_ssim = (1 - SSIMLoss(model.targets, model.mask)(model())).tolist()
    assert all(h > s + 0.02 for h, s in zip(held.info["model_ssim"], start_ssim))


class TestBadInput:
    def test_unknown_objective(self):
        with pytest.raises(InputError, match="objective must be one of"):
            image_objective("perceptual")

    def test_weight_with_least_squares(self):
        with pytest.raises(InputError, match="give it with objective 'ssim' or 'mixed'"):
            image_objective("l2", 0.5)

    def test_negative_weight(self):
        with pytest.raises(InputError, match="l2_weight must be a finite number >= 0"):
            image_objective("ssim", -1.0)

    def test_negative_budget(self):
        with pytest.raises(InputError, match="psnr_drop must be a finite number of dB >= 0"):
            image_objective("ssim", psnr_drop=-2.0)

    @pytest.mark.parametrize("option, value, says", [
        ("l2_weight", "0.1", "l2_weight must be a finite number >= 0, got '0.1'"),  # float() read it
        ("psnr_drop", "1", r"psnr_drop must be a finite number of dB >= 0 \(or None: no limit\), got '1'"),
        ("psnr_drop", float("inf"), "psnr_drop must be a finite number of dB >= 0 .*, got inf"),  # the loss took it
    ])
    def test_objective_and_loss_options_that_are_no_numbers(self, option, value, says):
        """A string as psnr_drop ended in a TypeError on '>=' (the objective and the loss each had a check of
        their own, and the loss took inf)."""
        op = build_transport(synthetic_calibration(shape=(40, 50)), targets(), merge=False, scale=1.0)
        with pytest.raises(InputError, match=says):
            image_objective("ssim", **{option: value})
        with pytest.raises(InputError, match=says):
            ImageLoss(op, torch.zeros(op.shape[1], 1), **{option: value})

    @pytest.mark.parametrize("option, value, says", [
        ("l2_weight", float("inf"), "l2_weight must be a finite number >= 0, got inf"),  # crashed in the loss
        ("lr", float("inf"), "lr must be a finite number > 0, got inf"),  # ran, and returned the start
        ("max_iter", 2.5, "max_iter must be a whole number >= 1, got 2.5"),
        ("tol", float("nan"), "tol must be a finite number >= 0, got nan"),
    ])
    def test_solve_ssim_options_out_of_kind(self, option, value, says):
        op = build_transport(synthetic_calibration(shape=(40, 50)), targets(), merge=False, scale=1.0)
        with pytest.raises(InputError, match=says):
            solve_ssim(op, **{option: value})

    def test_merged_operator(self):
        op = build_transport(synthetic_calibration(shape=(40, 50)), targets(), merge=True, scale=1.0)
        with pytest.raises(InputError, match="merge=False"):
            solve_ssim(op)

    def test_gain_offset_with_an_image_objective(self, quarter):
        scene, cal = quarter
        with pytest.raises(InputError, match="l2 objective"):
            run_virtual(scene, calibration=cal, objective="ssim", gain_offset=((0.5, 1.5), (0.0, 0.0)))


def test_a_start_nothing_beats_is_returned_unchanged():
    """A start the model fits exactly: Adam's first steps can only add noise, and the solver must
    hand the start back rather than its last, worse iterate."""
    op = build_transport(synthetic_calibration(shape=(40, 50)), targets(), merge=False, scale=0.8).double()
    exact = torch.rand(op.shape[1], 1, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    op = op.with_rhs(op.A(exact))  # targets these patterns show exactly: SSIM 1, squared error 0
    res = solve_ssim(op, (0.0, 1.0), x0=exact, max_iter=10, lr=0.5)
    assert all(math.isfinite(f) for _, f in res.history)
    assert res.history[1][1] > res.history[0][1]  # the first step made it worse
    torch.testing.assert_close(res.patterns, exact)
    assert res.objective == pytest.approx(res.history[0][1])


def test_the_image_loss_at_its_start_and_its_gradient():
    op = build_transport(synthetic_calibration(shape=(40, 50)), targets(), merge=False, scale=0.8).double()
    start = torch.rand(op.shape[1], 1, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    loss = ImageLoss(op, start, l2_weight=0.3, psnr_drop=1.0)
    model = ProjectionModel(op, start=start)
    with torch.no_grad():
        ssim_at_start = 1 - SSIMLoss(model.targets, model.mask)(model())
    # At the start the relative squared error is 1 and the hinge 0: the loss is mean(1 - SSIM) + w.
    assert float(loss(start)) == pytest.approx(float((1 - ssim_at_start).mean()) + 0.3, rel=1e-12)
    assert loss.report(start)["model_psnr_change_db"] == pytest.approx([0.0, 0.0], abs=1e-9)
    small = start.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: loss(p), (small,), atol=1e-6)


def test_one_operator_per_colour_channel_predicts_each_channel_with_its_own_weights():
    """ImageLoss and solve_ssim on build_channel_transports' operators: channel c's prediction is
    channel c's dense matrix times channel c's patterns, each target's SSIM and squared error taken
    over all channels; checked against dense float64 products and torchproj.metrics.ssim."""
    from torchproj.metrics import ssim
    from torchproj.transport import build_channel_transports

    cals = synthetic_calibration(shape=(40, 50))
    g = torch.Generator().manual_seed(7)
    for cal in cals.values():  # a strong tint: the grey weight would mispredict every channel
        cal.colour_weight = [w * torch.tensor([0.5, 1.0, 1.6])[:, None, None] * (0.8 + 0.4 * torch.rand(3, *w.shape, generator=g))
                             for w in cal.weight]
    ops = [op.double() for op in build_channel_transports(cals, targets(channels=3), scale=0.8)]
    start = torch.rand(ops[0].shape[1], 3, generator=g, dtype=torch.float64)
    p = (start + 0.2 * torch.rand(start.shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    loss = ImageLoss(ops, start, l2_weight=0.3, psnr_drop=None)
    dense = [op.dense() for op in ops]
    rows = torch.cat([A @ p[:, c:c + 1] for c, A in enumerate(dense)], 1) / ops[0].scale
    rows0 = torch.cat([A @ start[:, c:c + 1] for c, A in enumerate(dense)], 1) / ops[0].scale
    want = torch.cat([op.rhs for op in ops], 1) / ops[0].scale
    first = ops[0]
    images, wanted = first.to_camera(rows), first.to_camera(want)
    dissimilarity, ratio = loss.terms(p)
    for k, mask in enumerate(first.camera_masks()):
        assert float(dissimilarity[k]) == pytest.approx(1 - float(ssim(images[k], wanted[k], mask)), rel=1e-9)
        mine = first.row_target == k
        expected = ((rows[mine] - want[mine]) ** 2).sum() / ((rows0[mine] - want[mine]) ** 2).sum()
        assert float(ratio[k]) == pytest.approx(float(expected), rel=1e-9)
    # The solve runs on them and never returns worse than its start, in the channels' own model.
    res = solve_ssim(ops, (0.0, 1.0), max_iter=15, psnr_drop=1.0)
    assert res.patterns.shape == start.shape and 0 <= float(res.patterns.min()) and float(res.patterns.max()) <= 1
    assert res.objective <= res.history[0][1] and min(res.info["model_psnr_change_db"]) >= -1.1
