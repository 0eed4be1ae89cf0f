"""The image-space model: its prediction against dense algebra, its derivatives, its state and its errors."""

import pytest
import torch

from torchproj.calib import ResponseCurve
from torchproj.core import InputError
from torchproj.solve import ClampedAdam, ProjectionModel, compensate, solve_fista, to_projectable
from torchproj.transport import build_transport, target_on_camera

from ..helpers import dense_reference, synthetic_calibration, targets

SCALE = 0.7


def operator(merge=False, seed=0, scale=SCALE, channels=1):
    return build_transport(synthetic_calibration(seed), targets(channels), merge=merge, scale=scale).double()


def row_pixels(cals, tgts):
    """(target, y, x) of every row, in the row order of the dense reference (loops, not the builder)."""
    out = []
    for k, t in enumerate(tgts):
        cal = cals[t.state]
        _, covered = target_on_camera(t, cal.lit())
        for y in range(covered.shape[0]):
            for x in range(covered.shape[1]):
                lit = any(bool(torch.isfinite(cal.prj_xy[j][y, x]).all()) for j in range(len(cal.prj_xy)))
                if covered[y, x] and lit:
                    out.append((k, y, x))
    return out


def test_forward_is_a_p_placed_on_the_camera():
    cals, tgts = synthetic_calibration(), targets()
    model = ProjectionModel(operator())
    A, rhs, _ = dense_reference(cals, tgts, SCALE)
    p = torch.rand(A.shape[1], 1, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    with torch.no_grad():
        model.patterns.copy_(p)
        image = model()
    expected = torch.zeros_like(image)
    targets_on_camera = torch.zeros_like(image)
    pixels = row_pixels(cals, tgts)
    assert len(pixels) == A.shape[0]
    for r, (k, y, x) in enumerate(pixels):
        expected[k, :, y, x] = float((torch.from_numpy(A[r]) @ p[:, 0]) / SCALE)
        targets_on_camera[k, :, y, x] = float(rhs[r, 0] / SCALE)
    torch.testing.assert_close(image, expected, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(model.targets, targets_on_camera, rtol=1e-6, atol=1e-6)
    mask = torch.zeros(image.shape[0], *image.shape[2:], dtype=torch.bool)
    for k, y, x in pixels:
        mask[k, y, x] = True
    assert torch.equal(model.mask, mask)


def test_gradients_of_first_and_second_order():
    model = ProjectionModel(operator())
    p = torch.rand_like(model.patterns, dtype=torch.float64).requires_grad_(True)

    def predict(x):
        with torch.no_grad():
            model.patterns.copy_(x)
        return model.operator.to_camera(model.operator.A(x) / model.scale)

    assert torch.autograd.gradcheck(predict, (p,))
    # An image-space L2 loss has the Hessian (2 / scale^2) A^T A: a double backward must give it.
    A = model.operator.dense().double()
    v = torch.rand_like(p)
    loss = predict(p).sub(model.targets).pow(2).sum()
    (g,) = torch.autograd.grad(loss, p, create_graph=True)
    (hv,) = torch.autograd.grad((g * v).sum(), p)
    torch.testing.assert_close(hv, 2 / model.scale**2 * A.T @ (A @ v), rtol=1e-10, atol=1e-10)


def test_state_dict_restores_patterns_scale_and_refuses_another_rig():
    model = ProjectionModel(operator(scale=SCALE))
    with torch.no_grad():
        model.patterns.uniform_(0, 1, generator=torch.Generator().manual_seed(2))
    state = model.state_dict()
    assert "operator._extra_state" in state
    other = ProjectionModel(operator(scale=2.5))  # same rig, another scale
    other.load_state_dict(state)
    assert other.scale == SCALE
    torch.testing.assert_close(other(), model())
    torch.testing.assert_close(other.targets, model.targets)
    elsewhere = ProjectionModel(operator(seed=3))  # another rig: other columns and rows
    with pytest.raises(InputError, match="build the operator from the same calibration"):
        elsewhere.load_state_dict(state)


def test_state_dict_with_patterns_outside_the_box_is_refused_before_loading():
    model = ProjectionModel(operator(), bounds=(0.0, 1.0))
    state = {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in model.state_dict().items()}
    state["patterns"][0, 0] = 5.0
    before = model.patterns.detach().clone()
    with pytest.raises(InputError, match=r"outside this model's bounds \[0, 1\]"):
        model.load_state_dict(state)
    assert torch.equal(model.patterns.detach(), before)  # nothing loaded
    wide = ProjectionModel(operator(), bounds=(-0.5, 5.0))  # the same patterns fit a wider box
    wide.load_state_dict(state)
    assert float(wide.patterns.max()) == 5.0


def test_patterns_are_the_ones_make_patterns_sends():
    op = operator()
    responses = [ResponseCurve(torch.ones(1), torch.tensor([2.2]), torch.zeros(1)),
                 ResponseCurve(torch.ones(1), torch.tensor([1.8]), torch.zeros(1))]
    bounds = (-100 / 255, 1.0)
    start = solve_fista(op, bounds).patterns
    model = ProjectionModel(op, bounds, responses, start)
    light = [img for img in op.to_images(to_projectable(start, bounds).clamp(0, 1))]
    expected = compensate(light, responses)
    for got, want in zip(model.to_patterns(), expected):
        assert got.dtype == torch.uint8 and torch.equal(got, want)


def test_a_training_loop_with_clamped_adam_stays_in_the_box_and_descends():
    model = ProjectionModel(operator(), (0.0, 1.0))
    opt = ClampedAdam(model.parameters(), lr=0.05, bounds=model.bounds)
    losses = []
    for _ in range(60):
        opt.zero_grad()
        loss = (model() - model.targets).pow(2).sum()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]
    assert float(model.patterns.detach().min()) >= 0 and float(model.patterns.detach().max()) <= 1


def test_clamped_adam_bounds_are_a_default_for_groups_added_later_and_may_be_tensors():
    p, q = torch.nn.Parameter(torch.full((4, 1), 0.5)), torch.nn.Parameter(torch.full((4, 1), 0.5))
    opt = ClampedAdam([p], lr=1.0, bounds=(0.0, 1.0))
    opt.add_param_group({"params": [q]})
    assert opt.param_groups[1]["bounds"] == (0.0, 1.0)
    (-p.sum() + q.sum()).backward()
    opt.step()
    assert float(p.detach().max()) <= 1.0 and float(q.detach().min()) >= 0.0
    r = torch.nn.Parameter(torch.full((2, 1), 0.5))
    lo, hi = torch.tensor([[0.0], [0.6]]), torch.tensor([[0.55], [1.0]])
    opt = ClampedAdam([r], lr=1.0, bounds=(lo, hi))
    (-r.sum()).backward()
    opt.step()
    assert r.detach().ravel().tolist() == pytest.approx([0.55, 1.0])
    opt.load_state_dict(opt.state_dict())
    with pytest.raises(InputError, match="lo < hi everywhere"):
        ClampedAdam([r], bounds=(hi, lo))


class TestBadInput:
    def test_merged_operator(self):
        cals = synthetic_calibration(shape=(40, 50))
        with pytest.raises(InputError, match="merge=False"):
            ProjectionModel(build_transport(cals, targets(), merge=True, scale=1.0))

    def test_start_outside_the_box(self):
        op = operator()
        with pytest.raises(InputError, match="start must lie in the bounds"):
            ProjectionModel(op, (0.0, 1.0), start=torch.full((op.shape[1], 1), 1.5, dtype=torch.float64))

    def test_start_of_the_wrong_shape(self):
        op = operator()
        with pytest.raises(InputError, match="start must have shape"):
            ProjectionModel(op, start=torch.zeros(op.shape[1] + 1, 1, dtype=torch.float64))

    def test_responses_for_another_number_of_projectors(self):
        with pytest.raises(InputError, match="one response curve per projector"):
            ProjectionModel(operator(), responses=[ResponseCurve(torch.ones(1), torch.ones(1), torch.zeros(1))])

    def test_patterns_without_responses(self):
        with pytest.raises(InputError, match="no response curves"):
            ProjectionModel(operator()).to_patterns()

    def test_calibration_of_another_kind(self):
        with pytest.raises(InputError, match="calibration must be"):
            ProjectionModel.from_calibration({"near": "not a calibration"}, targets())

    def test_target_mask_of_another_camera(self):
        bad = targets()
        bad[0].mask = torch.ones(3, 4, dtype=torch.bool)
        with pytest.raises(InputError, match="mask must have shape"):
            ProjectionModel.from_calibration(synthetic_calibration(), bad)

    def test_target_of_a_state_the_calibration_lacks(self):
        bad = targets()
        bad[0].state = "elsewhere"
        with pytest.raises(InputError, match="not calibrated"):
            ProjectionModel.from_calibration(synthetic_calibration(), bad)
