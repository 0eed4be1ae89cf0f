"""Camera in the loop on a synthetic world: the loop against scipy's optimum of the world as it is."""

import numpy as np
import pytest
import torch
from scipy.optimize import lsq_linear

from torchproj.calib import ResponseCurve
from torchproj.core import InputError
from torchproj.solve import captured_loss, refine_patterns, solve_fista
from torchproj.core.sparse import csr_tensor
from torchproj.transport import TransportOperator, build_transport

from ..helpers import synthetic_calibration, targets

RESPONSES = [ResponseCurve(torch.tensor([1.0]), torch.tensor([b]), torch.tensor([0.0])) for b in (2.2, 2.0)]


@pytest.fixture(scope="module")
def op():
    return build_transport(synthetic_calibration(), targets(), merge=False, footprint="bilinear")


def shown_light(op, images):
    """The linear light the projectors emit for 8-bit images, at the operator's columns (true responses)."""
    light = torch.empty(op.shape[1], 1)
    for j, (img, resp) in enumerate(zip(images, RESPONSES)):
        sel = op.column_projector == j
        light[sel, 0] = resp(img.float() / 255)[0].flatten()[op.column_cell[sel]]
    return light


def world(op, matrix):
    """A camera on a world whose transport is ``matrix`` (dense, rows x columns): captured rows."""
    def measure(images):
        return torch.from_numpy(matrix @ shown_light(op, images).double().numpy()).float()
    return measure


def optimum(matrix, rhs):
    """scipy's bounded least squares on the world itself: the best any patterns can do there."""
    x = lsq_linear(matrix, rhs[:, 0], bounds=(0, 1), tol=1e-12, max_iter=10000).x
    return float(((matrix @ x - rhs[:, 0]) ** 2).sum())


def loop_in_a_brighter_world(op, gain):
    """Four updates from the model's optimum in a world ``gain`` times brighter than calibrated:
    the loop's result, scipy's optimum of that world, and each capture's loss."""
    truth = gain * op.dense().double().numpy()
    start = solve_fista(op, max_iter=3000, tol=1e-12).patterns
    result = refine_patterns(op, start, world(op, truth), responses=RESPONSES, iterations=4, solver_iterations=500)
    return result, optimum(truth, op.rhs.double().numpy()), [h["loss"] for h in result.history]


def test_a_brighter_world_is_brought_to_its_own_optimum(op):
    # Every projector 30% brighter than calibrated: the stale patterns overshoot; four captures and
    # updates reach the optimum of the world as it is (scipy), where the stale ones are far from it.
    result, best, losses = loop_in_a_brighter_world(op, 1.3)
    assert losses[0] > 1.3 * best
    assert min(losses) <= best * 1.01  # 8-bit patterns: a hair above the continuous optimum
    assert result.best == int(np.argmin(losses)) and result.best > 0
    assert all(0 <= float(v) <= 1 for v in (result.patterns.min(), result.patterns.max()))


def test_a_world_that_answers_twice_as_strongly_is_not_left_in_a_two_cycle(op):
    # Every projector 1.9 times brighter than calibrated: a full step along the surrogate overshoots
    # the optimum by 0.9 of the miss, each capture a little better than the last (a slow 2-cycle
    # about the optimum). The surrogate promised far more than each such capture gained, so the
    # loop shortens its step, and half a step lands within 5% of the miss.
    result, best, losses = loop_in_a_brighter_world(op, 1.9)
    assert losses[1] < losses[0] and losses[1] > 2 * best  # the full step: better, far from the optimum
    assert result.history[1]["predicted"] < 1.01 * best  # what the model promised it
    assert [h["step"] for h in result.history[:3]] == [1.0, 1.0, 0.5]
    assert min(losses) <= best * 1.02


def test_the_loop_never_returns_worse_than_it_began(op):
    # A world the model cannot describe (its columns shuffled): whatever the loop tries, it keeps the
    # best capture, the start included, and reports it.
    A = op.dense().double().numpy()
    shuffled = A[:, np.random.default_rng(0).permutation(A.shape[1])]
    start = solve_fista(op, max_iter=500).patterns
    result = refine_patterns(op, start, world(op, shuffled), responses=RESPONSES, iterations=5)
    losses = [h["loss"] for h in result.history]
    assert result.history[result.best]["loss"] == min(losses)
    again = captured_loss(op, world(op, shuffled)(result.images))[0]
    assert again == pytest.approx(min(losses), rel=1e-6)
    assert again <= losses[0]


def test_a_remodelled_world_is_refined_on_the_new_model_without_building_its_q(op):
    """A remodel after the first capture hands the loop a model of the world as it is (30% brighter):
    the updates solve on it through ``A`` and ``A^T`` (its ``Q`` is never built: inside an update it
    is most of the first one's time) and reach that world's optimum, as on the model itself."""
    truth = 1.3 * op.dense().double().numpy()
    brighter = TransportOperator(csr_tensor(op.crow, op.col, 1.3 * op.val, op.shape), op.rhs, op.column_projector,
                                 op.column_cell, op.projector_sizes, row_target=op.row_target, scale=op.scale,
                                 row_pixel=op.row_pixel, camera_size=op.camera_size, target_count=op.target_count)
    np.testing.assert_allclose(brighter.dense().double().numpy(), truth, rtol=1e-6)
    handed = []

    def remodel(ops, p, measured):
        if handed:
            return None
        handed.append(brighter)
        return brighter

    start = solve_fista(op, max_iter=3000, tol=1e-12).patterns
    result = refine_patterns(op, start, world(op, truth), responses=RESPONSES, iterations=3, solver_iterations=500,
                             remodel=remodel)
    losses = [h["loss"] for h in result.history]
    assert result.history[0].get("remodelled") and brighter.normal_matrix() is None
    assert min(losses) <= optimum(truth, op.rhs.double().numpy()) * 1.01 < losses[0]


def test_an_unchanged_world_loses_nothing(op):
    A = op.dense().double().numpy()
    start = solve_fista(op, max_iter=3000, tol=1e-12).patterns
    result = refine_patterns(op, start, world(op, A), responses=RESPONSES, iterations=3)
    losses = [h["loss"] for h in result.history]
    assert min(losses) <= losses[0]
    assert min(losses) <= optimum(A, op.rhs.double().numpy()) * 1.03 + 1e-4


def test_an_image_objective_refines_on_the_capture(op):
    truth = 1.2 * op.dense().double().numpy()
    start = solve_fista(op, max_iter=500).patterns
    result = refine_patterns(op, start, world(op, truth), responses=RESPONSES, iterations=2, objective="ssim")
    losses = [h["loss"] for h in result.history]
    assert result.best > 0 and losses[result.best] < losses[0]


@pytest.mark.parametrize("kwargs, message", [
    ({"iterations": -1}, "iterations"), ({"relax": 0}, "relax"), ({"relax": 1.5}, "relax"),
    ({"responses": None}, "response curves"), ({"solver_iterations": 0}, "solver_iterations"),
    ({"solver_iterations": 2.5}, "solver_iterations must be a whole number"),
    # A string ended in a TypeError on '<', one curve for two projectors or a number as remodel only
    # after the first capture.
    ({"relax": "x"}, r"relax must be in \(0, 1\], got 'x'"), ({"responses": RESPONSES[:1]}, "1 response curves"),
    ({"remodel": 3}, "remodel must be None or a function that gives the operator again, got int"),
])
def test_bad_loop_options_are_refused_before_any_capture(op, kwargs, message):
    def measure(images):
        raise AssertionError("captured before the options were checked")
    options = {"responses": RESPONSES, **kwargs}
    with pytest.raises(InputError, match=message):
        refine_patterns(op, torch.zeros(op.shape[1], 1), measure, **options)


def test_a_measure_that_is_no_function_is_named(op):
    """A capture's rows given in its place ended in "'Tensor' object is not callable"."""
    with pytest.raises(InputError, match="measure must be a function of the patterns .*, got Tensor"):
        refine_patterns(op, torch.zeros(op.shape[1], 1), torch.zeros(op.shape[0], 1), responses=RESPONSES)


def test_a_capture_that_is_not_light_is_named_by_the_loop(op):
    """A NaN from a failed read ended the loop in its scores' math (ValueError: math domain error)."""
    truth = 1.2 * op.dense().double().numpy()
    measure = world(op, truth)
    with pytest.raises(InputError, match="measure\\(...\\)'s rows of capture 0 holds .* non-finite"):
        refine_patterns(op, torch.zeros(op.shape[1], 1), lambda images: measure(images) + float("inf"),
                        responses=RESPONSES, iterations=1)


def test_a_merged_operator_is_refused(op):
    merged = build_transport(synthetic_calibration(), targets(), merge=True)
    with pytest.raises(InputError, match="merge=False"):
        refine_patterns(merged, torch.zeros(merged.shape[1], 1), lambda images: None, responses=RESPONSES)


def test_the_models_straight_through_step_has_the_captures_value_and_the_models_gradient():
    from torchproj.solve import ProjectionModel

    op = build_transport(synthetic_calibration(), targets(), merge=False, footprint="bilinear").double()
    model = ProjectionModel(op, start=torch.full((op.shape[1], 1), 0.4, dtype=torch.float64))
    g = torch.Generator().manual_seed(5)
    captured_rows = torch.rand(op.shape[0], 1, generator=g, dtype=torch.float64)
    captured = model.operator.to_camera(captured_rows)
    images = model.straight_through(captured)
    assert torch.allclose(images.detach(), captured, atol=1e-12)
    want = model.operator.to_camera(model.operator.rhs / model.scale)
    ((images - want) ** 2).sum().backward()
    # d/dp of sum((A p / s - t)^2) with A p / s replaced by the capture's rows: 2 A^T (c - t) / s.
    expected = 2 * model.operator.A_adjoint(captured_rows - model.operator.rhs / model.scale) / model.scale
    assert torch.allclose(model.patterns.grad, expected, atol=1e-10)
    with pytest.raises(InputError, match="captured must be"):
        model.straight_through(captured[:1])
    with pytest.raises(InputError, match="captured must be a torch.Tensor, got ndarray"):
        model.straight_through(captured.detach().numpy())
