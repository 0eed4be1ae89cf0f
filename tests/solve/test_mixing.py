"""Least squares through a colour camera's mixing, against scipy's bounded least squares."""

import numpy as np
import pytest
import torch
from scipy.optimize import lsq_linear

from torchproj.calib import ResponseCurve
from torchproj.core import InputError
from torchproj.solve import make_patterns, solve_patterns
from torchproj.solve.mixing import solve_through_mixing
from torchproj.transport import build_channel_transports, build_transport

from ..helpers import synthetic_calibration, targets

# Strong mixing, different per projector (rows sum to 1): saturated targets leave the primaries' gamut.
MIXINGS = [torch.tensor([[0.7, 0.25, 0.05], [0.1, 0.75, 0.15], [0.05, 0.25, 0.7]]),
           torch.tensor([[0.8, 0.2, 0.0], [0.15, 0.7, 0.15], [0.0, 0.2, 0.8]])]


def reference(ops, bounds):
    """The coupled problem as one dense matrix: channel c's rows see A_c (x N_j^T)_c per column."""
    dense = [op.dense().double().numpy() for op in ops]
    columns = ops[0].column_projector.numpy()
    n = dense[0].shape[1]
    blocks, rhs = [], []
    for c in range(3):
        A = dense[0] if len(dense) == 1 else dense[c]
        row = np.zeros((A.shape[0], 3 * n))
        for p in range(3):
            share = np.array([MIXINGS[j][c, p].item() for j in columns])
            row[:, p * n:(p + 1) * n] = A * share[None, :]
        blocks.append(row)
        op = ops[0] if len(ops) == 1 else ops[c]
        rhs.append((op.rhs[:, c] if op.rhs.shape[1] == 3 else op.rhs[:, 0]).double().numpy())
    fit = lsq_linear(np.vstack(blocks), np.concatenate(rhs), bounds=bounds, tol=1e-12)
    return fit.x.reshape(3, n).T, 2 * fit.cost


@pytest.mark.parametrize("per_channel", [False, True])
def test_the_coupled_solve_reaches_scipys_optimum(per_channel):
    cals, tgts = synthetic_calibration(), targets(channels=3)
    for t in tgts:  # saturated colours, which the primaries' mix cannot all give
        t.image[0] = (t.image[0] > 0.5).float()
        t.image[1] = 1 - t.image[0]
    if per_channel:  # each channel its own weight (a tint per pixel and projector), hence its own operator
        g = torch.Generator().manual_seed(5)
        for cal in cals.values():
            cal.colour_weight = [w * (0.6 + 0.8 * torch.rand(3, *w.shape, generator=g)) for w in cal.weight]
    ops = build_channel_transports(cals, tgts, scale=1.0) if per_channel else [build_transport(cals, tgts, scale=1.0)]
    bounds = (0.0, 1.0)
    channel = [solve_patterns(op, "fista", bounds, max_iter=2000) for op in ops]
    start = channel[0] if len(ops) == 1 else type(channel[0])(**{**channel[0].__dict__, "patterns": torch.cat(
        [r.patterns for r in channel], 1)})
    x_ref, best = reference(ops, bounds)
    refined = solve_through_mixing(ops, start, MIXINGS, bounds, max_iter=3000)
    # The refined values are what the camera sees: x N^T, with x the primaries.
    eye = torch.stack(MIXINGS)[ops[0].column_projector.long()]
    x = torch.einsum("npc,nc->np", torch.linalg.inv(eye.double()), refined.patterns.double())
    assert float(x.min()) >= -1e-6 and float(x.max()) <= 1 + 1e-6
    assert refined.info["mixing"]["residual"] == pytest.approx(best, rel=1e-3, abs=1e-6)
    assert refined.info["mixing"]["residual"] < refined.info["mixing"]["residual_clipped"] - 1e-3
    assert float((x - torch.from_numpy(x_ref)).abs().max()) < 0.02


def test_make_patterns_solves_through_the_responses_mixing():
    cals, tgts = synthetic_calibration(), targets(channels=3)
    op = build_transport(cals, tgts, scale=1.0)
    curves = [ResponseCurve(torch.ones(1), torch.ones(1), torch.zeros(1), m) for m in MIXINGS]
    result, light, _ = make_patterns(op, "fista", (0.0, 1.0), curves, max_iter=300)
    assert "mixing" in result.info
    plain, _, _ = make_patterns(op, "fista", (0.0, 1.0), [ResponseCurve(torch.ones(1), torch.ones(1), torch.zeros(1))] * 2,
                                max_iter=300)
    assert "mixing" not in plain.info
    with pytest.raises(InputError, match="bounds within"):
        solve_through_mixing(op, result, MIXINGS, (-0.4, 1.0))


def test_an_identity_mixing_leaves_the_channels_answer():
    """A colour camera on a rig without mixing measures the identity: it couples nothing, so the
    channels' answer stands as it is (the coupled iterations had been half a small scene's solve);
    the same curves with the least mixing are refined."""
    cals, tgts = synthetic_calibration(), targets(channels=3)
    op = build_transport(cals, tgts, scale=1.0)

    def solved(mixing):
        curves = [ResponseCurve(torch.ones(1), torch.ones(1), torch.zeros(1), mixing)] * 2
        return make_patterns(op, "fista", (0.0, 1.0), curves, max_iter=300)[0]

    plain = make_patterns(op, "fista", (0.0, 1.0), [ResponseCurve(torch.ones(1), torch.ones(1), torch.zeros(1))] * 2,
                          max_iter=300)[0]
    identity = solved(torch.eye(3))
    assert "mixing" not in identity.info and torch.equal(identity.patterns, plain.patterns)
    slight = torch.eye(3) * 0.98 + 0.02 / 3
    assert "mixing" in solved(slight).info
