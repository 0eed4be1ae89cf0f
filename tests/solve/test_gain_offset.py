"""Patterns with a per-target gain and offset, against scipy's bounded least squares on the joint problem."""

import numpy as np
import pytest
import torch
from scipy.optimize import lsq_linear

from torchproj.core import InputError
from torchproj.solve import solve_fista, solve_gain_offset
from torchproj.transport import Target, build_transport

from ..helpers import synthetic_calibration, targets

GAIN, OFFSET = (0.5, 1.5), (-0.2, 0.2)


@pytest.fixture(scope="module")
def problem():
    cals = synthetic_calibration(shape=(30, 40))
    tgts = targets(channels=3)
    op = build_transport(cals, tgts, merge=False, scale=0.9).double()
    flat = build_transport(cals, [Target(t.state, torch.ones_like(t.image), name=t.name) for t in tgts],
                           merge=False, scale=0.9).double()
    return op, flat.rhs


def joint_reference(op, flat, bounds):
    """min ||A p_c - g_k s t_c - o_k s||^2 over p (per channel), g and o (shared by channels), all boxed."""
    A = op.dense().numpy()
    N, n = A.shape
    C = op.channels
    K = int(op.row_target.max()) + 1
    t, one, k = op.rhs.numpy(), flat.numpy(), op.row_target.numpy()
    M = np.zeros((N * C, n * C + 2 * K))
    for c in range(C):
        M[c * N:(c + 1) * N, c * n:(c + 1) * n] = A
        for kk in range(K):
            rows = np.nonzero(k == kk)[0]
            M[c * N + rows, n * C + kk] = -t[rows, c]
            M[c * N + rows, n * C + K + kk] = -one[rows, c]
    lo = np.r_[np.full(n * C, bounds[0]), np.full(K, GAIN[0]), np.full(K, OFFSET[0])]
    hi = np.r_[np.full(n * C, bounds[1]), np.full(K, GAIN[1]), np.full(K, OFFSET[1])]
    res = lsq_linear(M, np.zeros(N * C), bounds=(lo, hi), tol=1e-12, max_iter=10000)
    return float((res.fun ** 2).sum()), res.x[n * C:n * C + K], res.x[n * C + K:]


def test_reaches_the_joint_optimum(problem):
    op, flat = problem
    best, g_ref, o_ref = joint_reference(op, flat, (0.0, 1.0))
    res = solve_gain_offset(op, flat, (0.0, 1.0), gain=GAIN, offset=OFFSET, outer=30, max_iter=6000, tol=1e-12)
    assert res.objective == pytest.approx(best, rel=2e-3)
    # The plain problem (g = 1, o = 0) is one point of the feasible set: the option can only help.
    plain = solve_fista(op, (0.0, 1.0), max_iter=3000, tol=1e-12).objective
    assert res.objective < plain
    g, o = np.array(res.info["gain"]), np.array(res.info["offset"])
    assert ((g >= GAIN[0]) & (g <= GAIN[1]) & (o >= OFFSET[0]) & (o <= OFFSET[1])).all()
    assert np.allclose(g, g_ref, atol=0.02) and np.allclose(o, o_ref, atol=0.02)
    # The operator returned holds the chosen targets: its objective is the reported one.
    assert float(res.info["operator"].objective(res.patterns)) == pytest.approx(res.objective, rel=1e-9)


def test_block_steps_never_raise_the_objective(problem):
    op, flat = problem
    res = solve_gain_offset(op, flat, (0.0, 1.0), gain=GAIN, offset=OFFSET, outer=10, max_iter=500)
    values = [f for _, f in res.history]
    assert all(b <= a * (1 + 1e-9) for a, b in zip(values, values[1:]))


def test_fixed_gain_and_offset_is_the_plain_problem(problem):
    op, flat = problem
    res = solve_gain_offset(op, flat, (0.0, 1.0), gain=(1, 1), offset=(0, 0), outer=1, max_iter=2000, tol=1e-12)
    plain = solve_fista(op, (0.0, 1.0), max_iter=2000, tol=1e-12)
    assert res.objective == pytest.approx(plain.objective, rel=1e-6)
    assert res.info["gain"] == [1.0, 1.0] and res.info["offset"] == [0.0, 0.0]


def test_needs_unmerged_rows_and_sane_limits(problem):
    op, flat = problem
    merged = build_transport(synthetic_calibration(shape=(30, 40)), targets(channels=3), scale=0.9).double()
    with pytest.raises(InputError, match="merge=False|flat"):
        solve_gain_offset(merged, flat, (0.0, 1.0))
    with pytest.raises(InputError, match="lo <= hi"):
        solve_gain_offset(op, flat, (0.0, 1.0), gain=(1.5, 0.5))
    with pytest.raises(InputError, match="positive"):
        solve_gain_offset(op, flat, (0.0, 1.0), gain=(0.0, 0.0))
    with pytest.raises(InputError, match="gain must be two numbers"):
        solve_gain_offset(op, flat, (0.0, 1.0), gain=1.0)
    with pytest.raises(InputError, match="offset limits must be finite"):
        solve_gain_offset(op, flat, (0.0, 1.0), offset=(0.0, float("inf")))


def test_a_run_checks_its_gain_and_offset_before_calibrating(monkeypatch):
    """A run given gain_offset=(1, 2) calibrated first and then raised Python's 'not iterable'."""
    from torchproj.pipeline import run as run_module
    from torchproj.scene import parse_scene

    from ..helpers import small_config

    def no_work(*args, **kwargs):
        raise AssertionError("calibrated before the options were checked")
    monkeypatch.setattr(run_module, "calibrate_virtual", no_work)
    monkeypatch.setattr(run_module, "cached_calibration", no_work)
    scene = parse_scene(small_config())
    for given, says in [((1.0, 2.0), "gain must be two numbers"), (((1.0, 2.0),), "gain_offset must be \\(\\(gain_lo")]:
        with pytest.raises(InputError, match=says):
            run_module.run_virtual(scene, gain_offset=given)
