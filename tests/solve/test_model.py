"""The image-space model: its prediction against dense algebra, its derivatives, its state and its errors."""

import numpy as np
import pytest
import torch

from torchproj.calib import ResponseCurve
from torchproj.core import InputError
from torchproj.solve import ClampedAdam, ProjectionModel, compensate, projectable_patterns, solve_fista, to_projectable
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

    @pytest.mark.parametrize("given, says", [
        (lambda n: np.zeros((n, 1)), "patterns must be a torch.Tensor, got ndarray"),
        (lambda n: torch.zeros(n + 1, 1, dtype=torch.float64), r"patterns must be \(\d+, 1\) like the model's"),
    ])
    def test_patterns_given_to_forward_that_are_not_the_models_kind(self, given, says):
        model = ProjectionModel(operator())
        with pytest.raises(InputError, match=says):
            model(given(model.patterns.shape[0]))

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


def test_torch_func_transforms_compose_with_the_operator_and_the_model():
    """grad, jvp, vjp and vmap (each failed: sparse tensors have no strides, the Function had no
    setup_context) against eager autograd and dense algebra."""
    from torch.func import grad, jacrev, jvp, vjp, vmap

    model = ProjectionModel(operator())
    op = model.operator
    A = op.dense().double()
    g = torch.Generator().manual_seed(3)
    p, t = (torch.rand(A.shape[1], 1, generator=g, dtype=torch.float64) for _ in range(2))

    def loss(x):
        return (op.A(x) - op.rhs).pow(2).sum()

    torch.testing.assert_close(grad(loss)(p), 2 * A.T @ (A @ p - op.rhs), rtol=1e-10, atol=1e-10)
    value, tangent = jvp(op.A, (p,), (t,))
    torch.testing.assert_close(value, A @ p, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(tangent, A @ t, rtol=1e-12, atol=1e-12)
    r = torch.rand(A.shape[0], 1, generator=g, dtype=torch.float64)
    torch.testing.assert_close(vjp(op.A, p)[1](r)[0], A.T @ r, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(jacrev(lambda x: op.A(x)[:, 0])(p)[:, :, 0], A, rtol=1e-12, atol=1e-12)
    batch = torch.rand(4, *p.shape, generator=g, dtype=torch.float64)
    torch.testing.assert_close(vmap(op.A)(batch), torch.stack([A @ q for q in batch]), rtol=1e-12, atol=1e-12)
    # Per-member gradients of an image loss through the whole model, in one call.
    per_member = vmap(grad(lambda q: (model(q) - model.targets).pow(2).sum()))(batch)
    for q, got in zip(batch, per_member):
        x = q.clone().requires_grad_(True)
        (model(x) - model.targets).pow(2).sum().backward()
        torch.testing.assert_close(got, x.grad, rtol=1e-10, atol=1e-12)


def test_a_batch_of_patterns_is_each_member_predicted_alone():
    model = ProjectionModel(operator(channels=3))
    batch = torch.rand(5, *model.patterns.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    images = model(batch)
    assert images.shape == (5, *model().shape)
    for q, image in zip(batch, images):
        torch.testing.assert_close(image, model(q), rtol=0, atol=1e-12)
    torch.testing.assert_close(model(None), model(model.patterns))
    with pytest.raises(InputError, match=r"patterns must be \(\d+, 3\) like the model's, or a batch"):
        model(batch[:, :-1])


def test_torch_compile_traces_the_model_as_one_graph_and_matches_eager():
    """``fullgraph=True`` failed on the operator (a device comparison, a sparse tensor); traced here with
    aot_eager, which checks the graph and its backward without a C++ compiler (the inductor run is a
    slow test)."""
    model = ProjectionModel(operator())
    explained = torch._dynamo.explain(model)()
    assert explained.graph_count == 1 and explained.graph_break_count == 0, explained.break_reasons
    compiled = torch.compile(model, fullgraph=True, backend="aot_eager")
    torch.testing.assert_close(compiled(), model())
    compiled().sum().backward()
    got = model.patterns.grad.clone()
    model.patterns.grad = None
    model().sum().backward()
    torch.testing.assert_close(got, model.patterns.grad)


@pytest.mark.slow
def test_torch_compile_with_inductor_matches_eager():
    model = ProjectionModel(operator())
    compiled = torch.compile(model, fullgraph=True)
    torch.testing.assert_close(compiled(), model())


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_models_store_16_bits_and_accumulate_in_float32(dtype):
    """MKL's sparse product takes no 16-bit floats; the values are widened for the product only."""
    reference = ProjectionModel(operator())
    model = ProjectionModel(operator()).to(dtype)
    assert model.operator.val.dtype == dtype and model.patterns.dtype == dtype
    image = model()
    assert image.dtype == dtype
    # The product of 16-bit inputs, accumulated in float64 and rounded once, is what it returns.
    p16 = reference.patterns.to(dtype).double()
    op = reference.operator
    A16 = op.dense().to(dtype).double()
    expected = op.to_camera(A16 @ p16 / op.scale).to(dtype)
    torch.testing.assert_close(image, expected, rtol=0, atol=float(torch.finfo(dtype).eps) * 2)
    (image - model.targets).pow(2).sum().backward()
    assert model.patterns.grad.dtype == dtype and bool(torch.isfinite(model.patterns.grad).all())


def test_a_model_on_the_meta_device_gives_shapes():
    model = ProjectionModel(operator()).to("meta")
    image = model()
    assert image.device.type == "meta" and image.shape == ProjectionModel(operator())().shape


def test_a_psnr_budget_holds_every_target_where_a_summed_loss_trades_one_away():
    """A loss that rewards target 0 alone, minimised with and without the budget: without it target
    1's PSNR falls by many dB; with it no target falls by much more than the budget's 1 dB."""
    from torchproj.solve import PSNRBudget

    def train(held):
        model = ProjectionModel(operator())
        with torch.no_grad():
            budget = PSNRBudget(model.targets, model.mask, model(), psnr_drop=1.0, weight=10.0)
            start = budget.squared_error(model())
        optimizer = ClampedAdam(model.parameters(), lr=0.05, bounds=model.bounds)
        for _ in range(150):
            optimizer.zero_grad()
            prediction = model()
            # Target 0's mean absolute error, and a reward for light on target 1 whatever its image.
            greedy = ((prediction[0] - model.targets[0]).abs() * model.mask[0]).sum() / model.mask[0].sum() \
                - (prediction[1] * model.mask[1]).sum() / model.mask[1].sum()
            (greedy + (budget(prediction).sum() if held else 0)).backward()
            optimizer.step()
        with torch.no_grad():
            return -10 * torch.log10(budget.squared_error(model()) / start)

    free, held = train(False), train(True)
    model = ProjectionModel(operator())
    with torch.no_grad():
        budget = PSNRBudget(model.targets, model.mask, model() * 0.9, psnr_drop=1.0)
        torch.testing.assert_close(budget(model()), budget.hinge(budget.ratio(model())))
        torch.testing.assert_close(budget.psnr_change(model()), -10 * torch.log10(budget.ratio(model())))
    assert float(free[1]) < -3  # the failure: target 1 given away
    assert float(held.min()) > -1.3  # within the budget (a soft hinge: a little past it)
    # None (no limit elsewhere), a string or inf ended in TypeErrors or a budget nothing could break.
    for drop in (-1, None, "1", float("inf")):
        with pytest.raises(InputError, match=f"psnr_drop must be a finite number of dB >= 0, got {drop!r}"):
            PSNRBudget(torch.zeros(1, 1, 4, 4), torch.ones(1, 4, 4, dtype=torch.bool), torch.zeros(1, 1, 4, 4), drop)
    with pytest.raises(InputError, match="weight must be a finite number >= 0, got -1"):
        PSNRBudget(torch.zeros(1, 1, 4, 4), torch.ones(1, 4, 4, dtype=torch.bool), torch.zeros(1, 1, 4, 4), 1.0, -1)


def test_one_operator_per_colour_channel_predicts_each_channel_with_its_own():
    """A colour calibration's model: channel c of the images is channel c's dense matrix times channel c
    of the patterns, one at a time or in a batch; from_calibration builds it where each channel's
    white minus black was measured (run's default), the grey one where asked."""
    from torchproj.transport import build_channel_transports

    cals = synthetic_calibration(seed=3)
    g = torch.Generator().manual_seed(4)
    for cal in cals.values():
        cal.colour_weight = [w * torch.tensor([0.5, 1.0, 1.6])[:, None, None] for w in cal.weight]
    tgts = targets(channels=3)
    ops = [op.double() for op in build_channel_transports(cals, tgts, scale=SCALE)]
    model = ProjectionModel(ops)
    p = torch.rand(ops[0].shape[1], 3, generator=g, dtype=torch.float64)
    rows = torch.cat([op.dense() @ p[:, c:c + 1] for c, op in enumerate(ops)], 1) / SCALE
    torch.testing.assert_close(model(p), ops[0].to_camera(rows))
    batch = torch.rand(4, *p.shape, generator=g, dtype=torch.float64)
    torch.testing.assert_close(model(batch), torch.stack([model(member) for member in batch]))
    assert model.targets.shape[1] == 3 and model.mask.shape[0] == len(tgts)
    channel = ProjectionModel.from_calibration(cals, tgts, footprint="nearest", scale=SCALE, start=None)
    grey = ProjectionModel.from_calibration(cals, tgts, footprint="nearest", scale=SCALE, start=None, colour_weights="grey")
    centre = torch.full_like(p, 0.5)
    torch.testing.assert_close(channel(centre.float()).double(), model(centre), rtol=1e-5, atol=1e-6)
    assert not torch.allclose(grey(centre.float()).double(), model(centre), rtol=1e-2)
    with pytest.raises(InputError, match="colour_weights must be one of"):
        ProjectionModel.from_calibration(cals, tgts, colour_weights="rgb")
    with pytest.raises(InputError, match="one single-channel operator per colour channel"):
        ProjectionModel([ops[0], build_transport(cals, tgts, merge=False)])


def test_a_colour_models_patterns_are_the_ones_make_patterns_sends():
    """One operator per colour channel share their columns: the model of a colour calibration (what
    from_calibration builds for colour targets) gives each projector's 8-bit colour images, as the grey
    one does. It ended in "op must be a TransportOperator" once the helper checked its operator."""
    from torchproj.transport import build_channel_transports

    cals = synthetic_calibration(seed=3)
    for cal in cals.values():
        cal.colour_weight = [w * torch.tensor([0.5, 1.0, 1.6])[:, None, None] for w in cal.weight]
    ops = [op.double() for op in build_channel_transports(cals, targets(channels=3), scale=SCALE)]
    responses = [ResponseCurve(torch.ones(3), torch.tensor([2.2, 2.0, 2.4]), torch.zeros(3)),
                 ResponseCurve(torch.ones(3), torch.tensor([1.8, 1.9, 2.1]), torch.zeros(3))]
    start = torch.rand(ops[0].shape[1], 3, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    model = ProjectionModel(ops, (0.0, 1.0), responses, start)
    expected = compensate(ops[0].to_images(start.clamp(0, 1)), responses)
    got = model.to_patterns()
    assert [tuple(g.shape) for g in got] == [(3, h, w) for w, h in ops[0].projector_sizes]
    for got_one, want in zip(got, expected):
        assert got_one.dtype == torch.uint8 and torch.equal(got_one, want)


def test_a_colour_models_operator_is_taken_where_one_per_channel_is():
    """A script's camera loop passes ``model.operator`` as the model gives it (``rig_measure(world,
    model.operator, targets)``, then ``straight_through``): a colour model's holds one operator per
    channel, and what takes those takes it, with the same rows, losses and updates."""
    from torchproj.pipeline.shown import CapturedRows
    from torchproj.solve import captured_loss, refine_patterns
    from torchproj.transport import build_channel_transports

    cals = synthetic_calibration(seed=3)
    for cal in cals.values():
        cal.colour_weight = [w * torch.tensor([0.5, 1.0, 1.6])[:, None, None] for w in cal.weight]
    tgts = targets(channels=3)
    ops = [op.double() for op in build_channel_transports(cals, tgts, scale=SCALE)]
    model = ProjectionModel(ops)
    g = torch.Generator().manual_seed(7)
    above = {state: torch.rand(3, *cal.weight[0].shape, generator=g, dtype=torch.float64)
             for state, cal in cals.items()}
    rows = CapturedRows(model.operator, tgts)(above)
    assert torch.equal(rows, CapturedRows(ops, tgts)(above))
    assert captured_loss(model.operator, rows) == captured_loss(ops, rows)
    responses = [ResponseCurve(torch.ones(3), torch.full((3,), 2.0), torch.zeros(3))] * 2
    start = torch.full((ops[0].shape[1], 3), 0.5, dtype=torch.float64)
    kept = [refine_patterns(op, start, lambda images: rows, (0.0, 1.0), responses, iterations=1, progress=False)
            for op in (model.operator, ops)]
    assert torch.equal(kept[0].patterns, kept[1].patterns)
    for got, want in zip(projectable_patterns(model.operator, start, (0.0, 1.0), responses)[1],
                         projectable_patterns(ops[0], start, (0.0, 1.0), responses)[1]):
        assert torch.equal(got, want)
    for given in (ops, model.operator):  # what solves one operator says why, and which way through
        with pytest.raises(InputError, match="op is one operator per colour channel, and this takes one: give each "
                                             "channel's alone, or make_patterns"):
            solve_fista(given, (0.0, 1.0))
