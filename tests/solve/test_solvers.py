"""Solvers against scipy's bounded least squares and float64 dense algebra."""

import contextlib
import copy
import dataclasses

import numpy as np
import pytest
import torch
from scipy.optimize import lsq_linear
from scipy.sparse import csr_matrix, diags

from torchproj.calib import ResponseCurve
from torchproj.core import InputError
from torchproj.core import fused as fused_module
from torchproj.core.fused import COMPILE_ENV
from torchproj.solve import (ClampedAdam, compensate, solve_adam, solve_fista, solve_lf, solve_patterns, solve_pgd,
                             to_projectable)
from torchproj.solve import solvers
from torchproj.transport import TransportOperator, build_transport, csr_from_coo
from torchproj.transport.operator import SUM_RUN

from ..helpers import LARGE, synthetic_calibration, targets


@pytest.fixture(scope="module")
def problem():
    op = build_transport(synthetic_calibration(shape=(30, 40)), targets(channels=3), scale=0.9).double()
    A = op.dense().numpy()
    return op, A, op.rhs.numpy()


def objective(op, A, b, x):
    """The objective in dense float64, including what row merging took out of A and b."""
    return float(((A @ x - b) ** 2).sum()) + float(op.constant.sum())


def reference(A, b, bounds):
    return np.stack([lsq_linear(A, b[:, c], bounds=bounds, tol=1e-12, max_iter=5000).x for c in range(b.shape[1])], 1)


@pytest.mark.parametrize("precondition", [True, False])
@pytest.mark.parametrize("bounds", [(0.0, 1.0), (-100 / 255, 1.0)])
@pytest.mark.parametrize("solver", [solve_pgd, solve_fista])
def test_proximal_solvers_reach_the_bounded_optimum(problem, solver, bounds, precondition):
    op, A, b = problem
    ref = reference(A, b, bounds)
    f_ref = objective(op, A, b, ref)
    res = solver(op, bounds, max_iter=20000, tol=1e-14, precondition=precondition)
    assert res.objective == pytest.approx(f_ref, rel=1e-6, abs=1e-9)
    np.testing.assert_allclose(res.patterns.numpy(), ref, atol=2e-3)
    assert float(res.patterns.min()) >= bounds[0] and float(res.patterns.max()) <= bounds[1]


@pytest.mark.parametrize("solver", [solve_pgd, solve_fista])
def test_the_product_form_reaches_the_same_optimum_without_building_q(solver):
    """``form="products"`` iterates on ``A^T (A p)``: scipy's optimum as on ``Q``, and no ``Q`` built
    (what the camera loop asks of a moved model's first updates)."""
    op = build_transport(synthetic_calibration(shape=(30, 40)), targets(channels=3), scale=0.9).double()
    A, b = op.dense().numpy(), op.rhs.numpy()
    ref = reference(A, b, (0.0, 1.0))
    res = solver(op, (0.0, 1.0), max_iter=20000, tol=1e-14, form="products", levels=2)
    assert op.normal_matrix() is None and op.normal_equations("products").Q is None
    assert res.objective == pytest.approx(objective(op, A, b, ref), rel=1e-6, abs=1e-9)
    np.testing.assert_allclose(res.patterns.numpy(), ref, atol=2e-3)
    with pytest.raises(InputError, match="form must be 'matrix', 'products' or 'auto'"):
        solver(op, (0.0, 1.0), form="dense")


@pytest.fixture(scope="module")
def tied_problem():
    """Large enough for two coarse levels (see ``tests/transport/test_operator.py``)."""
    op = build_transport(synthetic_calibration(shape=(40, 50), sizes=LARGE), targets(channels=3), scale=0.8).double()
    return op, op.dense().numpy(), op.rhs.numpy()


@pytest.mark.parametrize("bounds", [(0.0, 1.0), (-100 / 255, 1.0)])
def test_coarse_to_fine_fista_reaches_the_bounded_optimum(tied_problem, bounds):
    op, A, b = tied_problem
    # scipy's sparse path (LSMR inside): its dense one factorises A at every step, slow at this size.
    ref = np.stack([lsq_linear(csr_matrix(A), b[:, c], bounds=bounds, tol=1e-12, lsmr_tol=1e-12, max_iter=5000).x
                    for c in range(b.shape[1])], 1)
    f_ref = objective(op, A, b, ref)
    res = solve_fista(op, bounds, max_iter=20000, tol=1e-14, levels=3)
    assert len(res.info["coarse_iterations"]) == 2 and all(k > 0 for k in res.info["coarse_iterations"])
    assert res.objective == pytest.approx(f_ref, rel=1e-6, abs=1e-9)
    assert float(res.patterns.min()) >= bounds[0] and float(res.patterns.max()) <= bounds[1]


def textbook_iteration(A, b, constant, L, bounds, iterations, accelerate):
    """Projected gradient (or FISTA restarted when the objective rises) on the Jacobi-scaled
    system, written out in float64 with scipy's sparse matrices (dense products made this test 7x
    slower and check nothing more). Returns the objective after each iteration, and the number of
    restarts."""
    A = csr_matrix(A)
    Q = (A.T @ A).tocsr()
    s = 1 / np.sqrt(Q.diagonal())[:, None]
    Qs, qs = diags(s[:, 0]) @ Q @ diags(s[:, 0]), s * (A.T @ b)
    lo, hi = (np.broadcast_to(v / s, qs.shape) for v in bounds)

    def f(z):
        return float(((A @ (s * z) - b) ** 2).sum()) + constant

    def step(v):
        return np.clip(v - (Qs @ v - qs) / L, lo, hi)

    z = np.full_like(qs, 0.5 * sum(bounds)) / s
    y, t, history, restarts = z, 1.0, [f(z)], 0
    for _ in range(iterations):
        z_new = step(y)
        if accelerate and f(z_new) > history[-1] and t > 1:
            z_new, t, restarts = step(z), 1.0, restarts + 1
        t_next = (1 + np.sqrt(1 + 4 * t * t)) / 2 if accelerate else 1.0
        y = z_new + (t - 1) / t_next * (z_new - z)
        z, t = z_new, t_next
        history.append(f(z))
    return history, restarts


# The compiled pass (TORCHPROJ_COMPILE=1) compiles for seconds on first use: with the slow tests.
ONE_LOOP = pytest.param("one loop", marks=pytest.mark.slow)


@pytest.mark.parametrize("chunk", [None, SUM_RUN, ONE_LOOP])
@pytest.mark.parametrize("bounds", [(0.0, 1.0), (-100 / 255, 1.0)])
@pytest.mark.parametrize("solver", [solve_pgd, solve_fista])
def test_iterates_are_the_textbook_ones(tied_problem, monkeypatch, solver, bounds, chunk):
    """The fused, chunked iteration (speculative step, restarts) is the plain algorithm. With
    ``chunk`` the tied problem's 6471 entries per block run through seven chunks, the last one
    with a partial summation run; with ``"one loop"`` the pass is compiled into one loop over whole
    blocks (``TORCHPROJ_COMPILE=1``), a number or a block for the lower bound."""
    op, A, b = tied_problem
    if chunk == "one loop":
        monkeypatch.setenv(COMPILE_ENV, "1")
        if not solvers._pass_in_one_loop.active():
            pytest.skip("torch.compile gave up earlier in this process (no C++ compiler?)")
    elif chunk is not None:
        monkeypatch.setattr(solvers, "_CHUNK", chunk)
    res = solver(op, bounds, max_iter=150, tol=0, levels=0)
    ref, restarts = textbook_iteration(A, b, float(op.constant.sum()), op.normal_equations().jacobi().lipschitz(),
                                       bounds, 150, accelerate=solver is solve_fista)
    assert restarts > 0 or solver is solve_pgd  # FISTA's comparison covers restarts
    np.testing.assert_allclose([f for _, f in res.history], ref, rtol=1e-10)


def test_where_the_pass_cannot_compile_it_warns_once_and_solves_as_eagerly(tied_problem, monkeypatch):
    """``TORCHPROJ_COMPILE=1`` without a compiler: one warning, then the chunked eager pass, the
    same iterates as with compiling off."""
    op, _, _ = tied_problem
    plain = solve_fista(op, max_iter=60, tol=0)
    monkeypatch.setenv(COMPILE_ENV, "1")
    monkeypatch.setattr(fused_module.shutil, "which", lambda name: None)
    monkeypatch.setattr(solvers, "_pass_in_one_loop", fused_module.fused(solvers._pass_in_one_loop.eager))
    with pytest.warns(UserWarning, match="no C.. compiler found for torch.compile: _pass_in_one_loop runs unfused") as seen:
        res = solve_fista(op, max_iter=60, tol=0)
    assert len([w for w in seen if "compiler" in str(w.message)]) == 1
    np.testing.assert_allclose([f for _, f in res.history], [f for _, f in plain.history], rtol=1e-12)
    torch.testing.assert_close(res.patterns, plain.patterns, rtol=0, atol=1e-12)


def test_history_runs_through_the_levels_and_never_rises(tied_problem):
    op, A, b = tied_problem
    res = solve_fista(op, (0, 1), max_iter=40, tol=0, levels=3)
    values = [f for _, f in res.history]
    assert len(values) == 1 + sum(res.info["coarse_iterations"]) + res.iterations
    assert all(b <= a * (1 + 1e-12) + 1e-12 for a, b in zip(values, values[1:]))
    # Its last value is the objective of what it returns, in dense float64.
    assert values[-1] == pytest.approx(objective(op, A, b, res.patterns.numpy()), rel=1e-9)
    # A given start is kept: no coarse levels.
    warm = solve_fista(op, (0, 1), max_iter=5, tol=0, x0=res.patterns)
    assert warm.info["coarse_iterations"] == [] and warm.objective <= res.objective * (1 + 1e-12)


def test_adam_gets_close(problem):
    op, A, b = problem
    f_ref = objective(op, A, b, reference(A, b, (0, 1)))
    res = solve_adam(op, (0, 1), lr=0.01, max_iter=3000, tol=1e-12)
    assert res.objective <= f_ref * 1.01 + 1e-6
    assert 0 <= float(res.patterns.min()) and float(res.patterns.max()) <= 1


def test_lf_is_the_normalised_least_squares_solution(problem):
    op, A, b = problem
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    res = solve_lf(op, (0, 1), tol=1e-12)
    assert res.converged and res.info["residual"] < 1e-9  # a converged least squares, not an iteration count
    expected = (x - x.min()) / (x.max() - x.min())  # the paper's normalisation: everything together
    np.testing.assert_allclose(res.patterns.numpy(), expected, atol=1e-6)
    clipped = solve_lf(op, (0, 1), tol=1e-12, normalise="clip")
    np.testing.assert_allclose(clipped.patterns.numpy(), x.clip(0, 1), atol=1e-6)
    own = solve_lf(op, (0, 1), tol=1e-12, normalise="projector").patterns.numpy()
    for j in range(len(op.projector_sizes)):
        cols = (op.column_projector == j).numpy()
        xj = x[cols]
        np.testing.assert_allclose(own[cols], (xj - xj.min(0)) / (xj.max(0) - xj.min(0)), atol=1e-6)


def test_lf_converges_in_float32_and_stops_on_a_singular_system(problem):
    op, A, b = problem
    single_precision = build_transport(synthetic_calibration(shape=(30, 40)), targets(channels=3), scale=0.9)
    res = solve_lf(single_precision, (-1e3, 1e3), normalise="clip")
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    assert res.converged and res.info["residual"] < 1e-4
    assert res.objective == pytest.approx(objective(op, A, b, x), rel=1e-4)
    # Two columns that always light the same rows: Q is singular, CG must neither blow up nor spin.
    twin = torch.cat([op.dense(), op.dense()[:, :1]], 1).float()
    rows, cols = torch.nonzero(twin, as_tuple=True)
    single = TransportOperator(csr_from_coo(rows, cols, twin[rows, cols], tuple(twin.shape)), op.rhs.float(),
                               torch.cat([op.column_projector, op.column_projector[:1]]),
                               torch.cat([op.column_cell, op.column_cell[:1] + 1]), op.projector_sizes)
    res = solve_lf(single, (0, 1))
    assert torch.isfinite(res.patterns).all() and res.iterations < 20000


def test_projected_gradient_never_raises_the_objective(problem):
    op, _, _ = problem
    for solver in (solve_pgd, solve_fista):
        for precondition in (True, False):
            values = [f for _, f in solver(op, (0, 1), max_iter=300, tol=0, precondition=precondition).history]
            assert all(b <= a * (1 + 1e-12) + 1e-12 for a, b in zip(values, values[1:])), solver.__name__


def test_fista_beats_pgd_at_equal_iterations(problem):
    op, _, _ = problem
    f_pgd = solve_pgd(op, (0, 1), max_iter=50, tol=0).objective
    f_fista = solve_fista(op, (0, 1), max_iter=50, tol=0).objective
    assert f_fista < f_pgd
    # Jacobi scaling evens out the cells' weights: fewer iterations for the same objective.
    f_plain = solve_fista(op, (0, 1), max_iter=50, tol=0, precondition=False).objective
    assert f_fista <= f_plain


def test_stopping_rule_fires(problem):
    op, _, _ = problem
    res = solve_fista(op, (0, 1), max_iter=10000, tol=1e-6)
    assert res.converged and res.iterations < 10000
    assert len(res.history) == res.iterations + 1 and res.time_s > 0


def test_adam_warns_when_the_learning_rate_is_too_large(problem):
    op, _, _ = problem
    with pytest.warns(RuntimeWarning, match="lower the learning rate"):
        solve_adam(op, (-50.0, 50.0), lr=20.0, max_iter=60, tol=0)


def test_clamped_adam_in_a_training_loop_with_a_scheduler():
    target = torch.tensor([2.0, -1.0, 0.3])
    p = torch.zeros(3, requires_grad=True)
    opt = ClampedAdam([p], lr=0.1, bounds=(0.0, 1.0))
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=50, gamma=0.5)
    for _ in range(300):
        opt.zero_grad()
        ((p - target) ** 2).sum().backward()
        opt.step()
        sched.step()
    torch.testing.assert_close(p.detach(), torch.tensor([1.0, 0.0, 0.3]), atol=1e-3, rtol=0)
    state = opt.state_dict()
    again = ClampedAdam([torch.zeros(3, requires_grad=True)], lr=0.1, bounds=(0.0, 1.0))
    again.load_state_dict(state)
    assert again.param_groups[0]["bounds"] == (0.0, 1.0) and again.param_groups[0]["lr"] == opt.param_groups[0]["lr"]


@pytest.mark.parametrize("bounds", [(1.0, 1.0), (0.5, 0.2), (0.0, float("nan")), (0.0, 1.0, 2.0), 1.0, ("a", 1.0)])
def test_bad_bounds(problem, bounds):
    op, _, _ = problem
    with pytest.raises(InputError, match="bounds"):
        solve_patterns(op, "fista", bounds)


def test_unknown_solver(problem):
    with pytest.raises(InputError, match="unknown solver 'magic'"):
        solve_patterns(problem[0], "magic")


def test_an_option_the_solver_does_not_take_is_named_with_those_it_does(problem):
    with pytest.raises(InputError, match=r"solver 'fista' takes no option 'lr'; its options: \['max_iter'"):
        solve_patterns(problem[0], "fista", (0.0, 1.0), lr=0.1)
    assert solve_patterns(problem[0], "adam", (0.0, 1.0), lr=0.05, max_iter=3).iterations <= 3


@pytest.mark.parametrize("solver", ["fista", "pgd", "adam", "lf"])
@pytest.mark.parametrize("option, value, says", [
    ("max_iter", 2.5, "max_iter must be a whole number >= 1, got 2.5"),
    ("max_iter", True, "max_iter must be a whole number >= 1, got True"),
    ("tol", float("nan"), "tol must be a finite number >= 0, got nan"),
    ("tol", -1.0, "tol must be a finite number >= 0, got -1"),
])
def test_iteration_options_of_the_wrong_kind_are_named(problem, solver, option, value, says):
    """A float count broke inside range() as a TypeError; a NaN tolerance never stopped (or at once)."""
    with pytest.raises(InputError, match=says):
        solve_patterns(problem[0], solver, (0.0, 1.0), **{option: value})


@pytest.mark.parametrize("solver", ["fista", "pgd", "adam", "ssim"])
@pytest.mark.parametrize("x0, says", [(0.5, "x0 must be a torch.Tensor, got float"),
                                      ([0.5, 0.5], "x0 must be a torch.Tensor, got list")])
def test_a_start_that_is_no_tensor_is_named(problem, solver, x0, says):
    """A number or a list as x0 ended in an AttributeError on .shape or .clamp."""
    from torchproj.solve import solve_ssim

    op = problem[0]
    solve = (lambda **k: solve_ssim(op, (0.0, 1.0), **k)) if solver == "ssim" else (
        lambda **k: solve_patterns(op, solver, (0.0, 1.0), **k))
    with pytest.raises(InputError, match=says):
        solve(x0=x0)
    with pytest.raises(InputError, match=r"x0 must have shape \(\d+, \d\) \(columns, channels\), got \(3,\)"):
        solve(x0=torch.zeros(3))


def test_make_patterns_names_a_solver_or_responses_of_the_wrong_kind_before_solving(problem, monkeypatch):
    """A list as the solver's name ended in an unhashable-type error; responses that are no list of
    curves in a TypeError or an AttributeError on .mixing, after the solve."""
    import sys

    from torchproj.solve import make_patterns

    compensate_module = sys.modules["torchproj.solve.compensate"]  # the package's `compensate` is the function

    op = problem[0]
    curves = [ResponseCurve(torch.ones(1), torch.ones(1), torch.zeros(1))] * len(op.projector_sizes)
    monkeypatch.setattr(compensate_module, "resolve_smoothness", lambda *a: pytest.fail("solved before the check"))
    with pytest.raises(InputError, match=r"unknown solver \['fista'\]; choose from"):
        make_patterns(op, ["fista"], (0.0, 1.0), curves)
    for responses, says in [(None, "got NoneType"), (curves[0], "got ResponseCurve"), ([0.5] * len(curves), r"got list of \['float'\]"),
                            (curves[:-1], f"got {len(curves)} projectors' images but {len(curves) - 1} response curves")]:
        with pytest.raises(InputError, match=says):
            make_patterns(op, "fista", (0.0, 1.0), responses)


def test_a_whole_number_of_any_integer_type_is_a_count(problem):
    res = solve_patterns(problem[0], "fista", (0.0, 1.0), max_iter=np.int64(7), levels=np.int32(0))
    assert res.iterations <= 7


def test_clamped_adam_rejects_bad_lr():
    with pytest.raises(ValueError, match="Invalid learning rate"):
        ClampedAdam([torch.zeros(1, requires_grad=True)], lr=-1.0)


def test_to_projectable_and_compensation():
    p = torch.tensor([[-100 / 255], [0.0], [0.2], [1.0]])
    # Below black: clipped (the default), or the bounds mapped linearly onto [0, 1].
    assert torch.equal(to_projectable(p, (-100 / 255, 1.0)), torch.tensor([[0.0], [0.0], [0.2], [1.0]]))
    mapped = to_projectable(p, (-100 / 255, 1.0), "map")
    assert torch.allclose(mapped, (p + 100 / 255) / (1 + 100 / 255)) and float(mapped[1]) == pytest.approx(100 / 355)
    with pytest.raises(InputError, match="outside must be one of"):
        to_projectable(p, (-100 / 255, 1.0), "wrap")
    assert torch.equal(to_projectable(p.clamp(0, 1), (0, 1)), p.clamp(0, 1))
    curve = ResponseCurve(a=torch.tensor([0.95]), b=torch.tensor([2.2]), c=torch.tensor([0.03]))
    light = torch.linspace(0, 1, 256).reshape(1, 16, 16)
    pattern = compensate([light], [curve])[0]
    assert pattern.dtype == torch.uint8 and pattern.shape == (1, 16, 16)
    # The projector's relative light for the sent values reproduces the asked light.
    sent = pattern.float() / 255
    relative = (curve(sent) - curve(torch.zeros(1, 1, 1))) / (curve(torch.ones(1, 1, 1)) - curve(torch.zeros(1, 1, 1)))
    assert float((relative - light).abs().max()) < 0.02
    with pytest.raises(InputError, match="to_projectable"):
        compensate([light - 0.5], [curve])


def test_pipeline_iteration_limits():
    """The pipeline caps the gradient solvers where none is given (their last iterations fit calibration
    errors on scenes they do not converge on) and leaves LF and EO to their convergence rules."""
    from torchproj.solve.compensate import PIPELINE_ITERATIONS, iteration_limit

    assert iteration_limit(None, "fista") == {"max_iter": PIPELINE_ITERATIONS["fista"]}
    assert iteration_limit(None, "lf") == {} and iteration_limit(None, "eo") == {}
    assert iteration_limit(7, "eo") == {"max_iter": 7}
    with pytest.raises(InputError, match="max_iter"):
        iteration_limit(0, "fista")


@pytest.mark.filterwarnings("ignore:the patterns leave")  # random weights: no scene, nothing to show apart
def _channel_rig():
    """A synthetic colour rig whose channels see their own random weights: calibrations, one float64
    operator per channel and linear responses."""
    from torchproj.transport import build_channel_transports

    cals = synthetic_calibration(shape=(30, 40))
    g = torch.Generator().manual_seed(5)
    for cal in cals.values():
        cal.colour_weight = [w * (0.5 + torch.rand(3, *w.shape, generator=g)) for w in cal.weight]
    ops = [op.double() for op in build_channel_transports(cals, targets(channels=3), scale=0.9)]
    return cals, ops, [ResponseCurve(torch.ones(3), torch.ones(3), torch.zeros(3))] * 2


def test_channel_operators_reach_each_channels_bounded_optimum():
    """make_patterns on one operator per colour channel: channel c of the joined solution is scipy's
    bounded least squares on channel c's own matrix; the joined objective is their sum. Operators of
    different columns are refused."""
    from torchproj.solve import make_patterns

    cals, ops, linear = _channel_rig()
    result, light, patterns = make_patterns(ops, "fista", (0.0, 1.0), linear, max_iter=20000,
                                            solver_options={"tol": 1e-14}, smoothness=0)
    total = 0.0
    for c, op in enumerate(ops):
        A, b = op.dense().numpy(), op.rhs.numpy()
        ref = reference(A, b, (0.0, 1.0))
        total += objective(op, A, b, ref)
        np.testing.assert_allclose(result.patterns[:, c:c + 1].numpy(), ref, atol=2e-3)
    assert result.objective == pytest.approx(total, rel=1e-6) and result.info["channels_solved_apart"] == 3
    assert [p.shape[0] for p in patterns] == [3, 3] and result.converged
    # An image objective refines the joined solution with the channels together (tests/solve/test_objectives.py).
    refined = make_patterns(ops, "fista", (0.0, 1.0), linear, objective="ssim")[0]
    assert refined.method == "ssim" and refined.patterns.shape == result.patterns.shape
    with pytest.raises(InputError, match="one single-channel operator per colour channel"):
        make_patterns([ops[0], build_transport(cals, targets(channels=3), merge=False)], "fista", (0.0, 1.0), linear)


@pytest.mark.filterwarnings("ignore:the patterns leave")  # random weights: an ill-posed rig, on purpose of no test here
def test_make_patterns_smooths_the_least_squares_solve_and_reports_the_lights_own_error():
    """The default weight (DEFAULT_SMOOTHNESS) solves the operator with its smoothness rows, per colour
    channel as without; the result's objective is ||A p - i||^2 alone, the penalised one in its info.
    The paper's LF and EO take no penalty, and a bad weight is refused by name."""
    from torchproj.core.choices import DEFAULT_SMOOTHNESS
    from torchproj.solve import make_patterns
    from torchproj.solve.compensate import resolve_smoothness

    _, ops, linear = _channel_rig()
    result = make_patterns(ops, "fista", (0.0, 1.0), linear, max_iter=400)[0]
    for c, op in enumerate(ops):
        alone = solve_patterns(op.with_smoothness(DEFAULT_SMOOTHNESS), "fista", (0.0, 1.0), max_iter=400)
        torch.testing.assert_close(result.patterns[:, c:c + 1], alone.patterns)
    plain = sum(float(op.objective(result.patterns[:, c:c + 1])) for c, op in enumerate(ops))
    assert result.objective == pytest.approx(plain, rel=1e-9)
    assert result.info["smoothness"] == DEFAULT_SMOOTHNESS and result.info["penalised_objective"] > plain
    assert resolve_smoothness("eo", None) == 0 and resolve_smoothness("lf", 0) == 0
    with pytest.raises(InputError, match="smoothness is for the least-squares solvers"):
        make_patterns(ops[0], "lf", (0.0, 1.0), linear, smoothness=0.01)
    for bad in (-0.1, float("inf"), "1e-3"):
        with pytest.raises(InputError, match="smoothness must be a number >= 0"):
            make_patterns(ops[0], "fista", (0.0, 1.0), linear, smoothness=bad)


def test_target_sets_solved_side_by_side_equal_each_solved_alone(quarter_rig):
    """Frames on one transport: the same rows for new images (retarget_rhs equals building
    the transport again), and each frame's values as its own solve gives them."""
    from torchproj.pipeline import scene_targets
    from torchproj.solve import solve_target_sets
    from torchproj.transport import build_transport, retarget_rhs

    scene, cal = quarter_rig
    targets = scene_targets(scene, None, cal.rig)
    op = build_transport(cal.states, targets, merge=False, footprint="area")
    g = torch.Generator().manual_seed(0)
    frames = [[dataclasses.replace(t, image=torch.rand(1, 48, 64, generator=g)) for t in targets] for _ in range(4)]
    rhs = [retarget_rhs(op, cal.states, f) for f in frames]
    rebuilt = build_transport(cal.states, frames[1], merge=False, footprint="area", scale=op.scale)
    torch.testing.assert_close(rhs[1], rebuilt.rhs)
    values, joint = solve_target_sets(op, rhs, max_iter=2000, tol=1e-9)
    for r, v in zip(rhs, values):
        alone = solve_fista(op.with_rhs(r), max_iter=2000, tol=1e-9).patterns
        assert float(op.with_rhs(r).objective(v)) <= float(op.with_rhs(r).objective(alone)) * (1 + 1e-3) + 1e-9
    with pytest.raises(InputError, match="one image per target"):
        retarget_rhs(op, cal.states, frames[0][:1])
    with pytest.raises(InputError, match="a stacked batch: give list"):
        solve_target_sets(op, torch.stack(rhs))
    with pytest.raises(InputError, match=r"rhs_sets\[1\] must have shape"):
        solve_target_sets(op, [rhs[0], rhs[1][:5]])


@contextlib.contextmanager
def _in_turn(device, fn, *args):
    """The solvers' coarse start run first, in this thread: what the overlapped one must equal."""
    value = fn(*args)
    yield lambda: value


@pytest.mark.parametrize("solver", [solve_fista, solve_pgd])
def test_the_coarse_start_beside_the_full_level_gives_the_serial_result(tied_problem, solver, monkeypatch):
    """The coarse start runs on a second thread while this one scales the full level and bounds its
    step; both read the same Q, so the patterns are those of running one after the other, to the bit."""
    op = tied_problem[0]
    beside = [solver(_fresh(op), (0.0, 1.0), levels=3, max_iter=50).patterns for _ in range(2)]
    monkeypatch.setattr(solvers, "_beside", _in_turn)
    serial = solver(_fresh(op), (0.0, 1.0), levels=3, max_iter=50)
    assert len(serial.info["coarse_iterations"]) == 2
    assert torch.equal(beside[0], serial.patterns) and torch.equal(beside[1], serial.patterns)


def _fresh(op):
    """The same operator with nothing built on it yet (no Q, no coarse levels)."""
    return copy.deepcopy(op)


def test_an_error_in_the_coarse_start_beside_surfaces():
    def fails():
        raise InputError("the coarse start failed")

    for device in ("cpu", "meta"):  # a second thread on the CPU; in turn elsewhere
        with pytest.raises(InputError, match="coarse start failed"):
            with solvers._beside(torch.device(device), fails) as start:
                start()


def test_the_thread_beside_keeps_the_callers_grad_mode():
    for enabled in (False, True):
        with torch.set_grad_enabled(enabled), solvers._beside(torch.device("cpu"), torch.is_grad_enabled) as mode:
            assert mode() is enabled  # a new thread starts with grad enabled whatever the caller set
