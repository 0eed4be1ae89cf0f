"""EO chains: the epipolar geometry against the simulator, and the per-chain solves against scipy."""

import numpy as np
import pytest
import torch
from scipy.optimize import lsq_linear, minimize
from scipy.sparse import csr_matrix

from torchproj.calib import calibrate_projector
from torchproj.pipeline import simulate_calibration
from torchproj.core import InputError
from torchproj.sim import VirtualRig
from torchproj.solve import (component_chains, epipolar_bands, epipolar_chains, fundamental_between_projectors, solve_eo,
                             solve_fista)
from torchproj.solve.eo import _chain_index
from torchproj.transport import StateCalibration, Target, TransportOperator, build_transport, csr_from_coo

from ..helpers import small_scene
from ..helpers import synthetic_calibration, targets


@pytest.fixture(scope="module")
def paper_rig():
    scene = small_scene(camera=(320, 240), projector=(128, 96))
    rig = VirtualRig(scene)
    cals = {}
    for st in scene.states:
        pcs = [calibrate_projector(simulate_calibration(rig, st.name, j), (128, 96)) for j in range(2)]
        cals[st.name] = StateCalibration([c.prj_xy for c in pcs], [c.decoding.contrast for c in pcs], [(128, 96)] * 2)
    return scene, rig, cals


def test_fundamental_matrix_fits_the_true_correspondences(paper_rig):
    scene, rig, cals = paper_rig
    F = fundamental_between_projectors(cals)
    # The simulator's exact projector coordinates of the same surface points satisfy x2^T F x1 = 0:
    # measure the distance of x2 from the epipolar line F x1, in pixels.
    truth = rig.geometry("far").prj_xy
    both = torch.isfinite(truth).all(-1).all(0)
    x1 = torch.cat([truth[0][both], torch.ones(int(both.sum()), 1)], 1).double()
    x2 = torch.cat([truth[1][both], torch.ones(int(both.sum()), 1)], 1).double()
    lines = x1 @ F.T
    dist = (lines * x2).sum(1).abs() / lines[:, :2].norm(dim=1)
    assert float(dist.median()) < 0.1 and float(dist.quantile(0.99)) < 0.5
    # Vertically stacked projectors: epipolar lines run (nearly) vertically.
    assert float((lines[:, 1].abs() / lines[:, :2].norm(dim=1)).max()) < 0.1


def test_epipolar_chains_follow_projector_columns(paper_rig):
    _, _, cals = paper_rig
    img = torch.rand(1, 16, 16, generator=torch.Generator().manual_seed(0))
    op = build_transport(cals, [Target("near", img, name="a"), Target("far", img, name="b")])
    chain = epipolar_chains(op, fundamental_between_projectors(cals))
    # In projector 0, cells of one chain share (almost) one column: the epipolar lines are vertical.
    j0 = op.column_projector == 0
    x = (op.column_cell[j0] % 128).float()
    spread = [float(x[chain[j0] == c].max() - x[chain[j0] == c].min()) for c in torch.unique(chain[j0])[:50]]
    assert np.median(spread) <= 2
    assert int(chain.max()) + 1 > 50  # many small chains, not one


def test_eo_with_components_is_exact():
    op = build_transport(synthetic_calibration(shape=(30, 40)), targets(channels=3), scale=0.9).double()
    res = solve_eo(op, (0, 1), chains="components", max_iter=20000, tol=1e-14)
    A, b = op.dense().numpy(), op.rhs.numpy()
    ref = np.stack([lsq_linear(A, b[:, c], bounds=(0, 1), tol=1e-12).x for c in range(3)], 1)
    f_ref = float(((A @ ref - b) ** 2).sum() + op.constant.sum())
    assert res.info["coupled_weight"] == 0.0 and res.info["colours"] == 1  # no row joins two components
    assert res.objective == pytest.approx(f_ref, rel=1e-6)


def test_each_chain_is_solved_to_its_own_optimum():
    """Two decoupled blocks with different scales: EO must solve both exactly, in one batched run."""
    rows = torch.tensor([0, 0, 1, 1, 2, 3, 3, 4])
    cols = torch.tensor([0, 1, 1, 2, 0, 3, 4, 4])
    vals = torch.tensor([1.0, 0.5, 0.3, 1.2, 0.7, 100.0, 50.0, 80.0], dtype=torch.float64)
    m = csr_from_coo(rows, cols, vals, (5, 5))
    rhs = torch.tensor([[0.9], [2.0], [-0.3], [120.0], [10.0]], dtype=torch.float64)
    op = TransportOperator(m, rhs, torch.zeros(5, dtype=torch.long), torch.arange(5), [(5, 1)])
    chain = component_chains(op)
    assert chain.tolist()[:3] == [chain[0]] * 3 and chain[3] == chain[4] != chain[0]
    res = solve_eo(op, (0, 1), chains=chain, max_iter=50000, tol=1e-15)
    ref = lsq_linear(op.dense().numpy(), rhs[:, 0].numpy(), bounds=(0, 1), tol=1e-14).x
    np.testing.assert_allclose(res.patterns[:, 0].numpy(), ref, atol=1e-6)


# scipy's reference takes 3-10 s a case on one core: the default suite checks EO_0^255, the slow one both.
@pytest.mark.parametrize("bounds", [pytest.param((0.0, 1.0), id="EO_0^255"),
                                    pytest.param((-100 / 255, 1.0), id="EO_-100^255", marks=pytest.mark.slow)])
def test_epipolar_eo_reaches_the_bounded_optimum(paper_rig, bounds):
    """The paper's chains leak light into their neighbours on a camera finer than the projectors; the
    sweeps keep that coupling, so EO reaches the optimum of the whole problem (FISTA's and scipy's)."""
    _, _, cals = paper_rig
    g = torch.Generator().manual_seed(1)
    op = build_transport(cals, [Target("near", torch.rand(1, 20, 20, generator=g), name="a"),
                                Target("far", torch.rand(1, 20, 20, generator=g), name="b")]).double()
    res = solve_eo(op, bounds, calibrations=cals)
    assert bounds[0] <= float(res.patterns.min()) and float(res.patterns.max()) <= bounds[1]
    assert res.info["colours"] >= 2 and res.converged
    # The weight between blocks, as Q's entries and the bands say (the solve takes it from the colours).
    bands = epipolar_bands(op, fundamental_between_projectors(cals), 1.0)
    Q = op.normal_equations().Q.to_sparse_coo().coalesce()
    (i, j), q = Q.indices(), Q.values()
    between = float(q[bands[i] != bands[j]].sum() / q.sum())
    assert 0.0 < between < 1.0 and res.info["coupled_weight"] == pytest.approx(between, rel=1e-9)
    # The reference: scipy's L-BFGS-B on ||A p - i||^2 with A's own gradient, a bounded quasi-Newton method
    # apart from every solver here. It reaches lsq_linear's optimum (lower by 1e-13 of it) in a third of
    # lsq_linear's time (2.7 against 7.4 s on one core).
    A = csr_matrix((op.val.numpy(), op.col.numpy(), op.crow.numpy()), shape=op.shape)
    rhs, At = op.rhs[:, 0].numpy(), A.T.tocsr()

    def value_and_gradient(p):
        r = A @ p - rhs
        return float(r @ r), 2.0 * (At @ r)

    ref = minimize(value_and_gradient, np.full(A.shape[1], 0.5), jac=True, method="L-BFGS-B", bounds=[bounds] * A.shape[1],
                   options={"maxiter": 20000, "ftol": 1e-15, "gtol": 1e-12})
    f_ref = ref.fun + float(op.constant.sum())
    fista = solve_fista(op, bounds, max_iter=5000, tol=1e-12).objective
    assert fista == pytest.approx(f_ref, rel=1e-4)
    assert f_ref <= res.objective <= f_ref * (1 + 1e-2)  # the bar: within 1e-2 of the optimum
    tight = solve_eo(op, bounds, calibrations=cals, tol=1e-10, max_iter=3000)
    assert tight.objective == pytest.approx(f_ref, rel=1e-5)  # and to the optimum itself when asked


def test_no_row_touches_two_chains_of_one_colour(paper_rig):
    """What makes a colour's chains independent, so that solving them at once is exact."""
    _, _, cals = paper_rig
    img = torch.rand(1, 16, 16, generator=torch.Generator().manual_seed(2))
    op = build_transport(cals, [Target("near", img, name="a"), Target("far", img, name="b")])
    Q = op.normal_equations().Q
    rows = torch.repeat_interleave(torch.arange(Q.shape[0]), Q.crow_indices().long().diff())
    col = Q.col_indices().long()
    chain, colour = _chain_index(op, "epipolar", cals, 1.0, (rows, col, Q.values()))
    same_colour = colour[rows] == colour[col]
    assert bool((chain[rows] == chain[col])[same_colour].all())
    assert bool((chain[rows] != chain[col]).any())  # rows do straddle chains: the colours are needed
    assert int(colour.max()) + 1 == 2  # epipolar bands couple their neighbours only


def test_epipolar_chains_need_two_projectors_and_calibrations():
    op = build_transport(synthetic_calibration(), targets(), scale=1.0)
    with pytest.raises(InputError, match="needs the calibrations"):
        solve_eo(op, (0, 1), chains="epipolar")
    with pytest.raises(InputError, match="chains must be"):
        solve_eo(op, (0, 1), chains="rows")
    cals = synthetic_calibration()
    for band in (0.0, -1.0, float("nan"), float("inf")):  # each made every cell one band, or reversed them
        with pytest.raises(InputError, match="band must be a finite number > 0"):
            solve_eo(op, (0, 1), calibrations=cals, band=band)
