"""The CUDA path against the CPU one: on a GPU where torch sees one, and everywhere on the stand-in
of ``tests/fake_cuda.py``, which checks where tensors live (CI has no GPU)."""

import pytest
import torch

from torchproj.solve import solve_fista, solve_pgd
from torchproj.transport import build_transport

from ..fake_cuda import fake_cuda
from ..helpers import LARGE, synthetic_calibration, targets


@pytest.fixture(autouse=True, params=["gpu", "stand-in"])
def cuda_device(request):
    """``"cuda"`` is a GPU, or the stand-in on a machine without one."""
    if request.param == "gpu":
        if not torch.cuda.is_available():
            pytest.skip("no CUDA device: the GPU itself is checked on machines that have one")
        yield
    else:
        with fake_cuda():
            yield


def rig():
    """Large enough for two coarse levels (see ``tests/transport/test_operator.py``)."""
    return build_transport(synthetic_calibration(shape=(40, 50), sizes=LARGE), targets(channels=3), scale=0.8)


def test_operator_products_on_cuda_match_the_cpu():
    cpu, gpu = rig(), rig().to("cuda")
    p = torch.rand(cpu.shape[1], 3, generator=torch.Generator().manual_seed(0))
    r = torch.rand(cpu.shape[0], 3, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(gpu.A(p.cuda()).cpu(), cpu.A(p), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(gpu.A_adjoint(r.cuda()).cpu(), cpu.A_adjoint(r), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(gpu.normal_equations().product(p.cuda()).cpu(), cpu.normal_equations().product(p),
                               rtol=1e-5, atol=1e-5)
    for (ne_gpu, block_gpu), (_, block_cpu) in zip(gpu.coarse_levels(3), cpu.coarse_levels(3)):
        assert ne_gpu.Q.device.type == "cuda" and block_gpu.device.type == "cuda"
        assert torch.equal(block_gpu.cpu(), block_cpu)


@pytest.mark.parametrize("bounds", [(0.0, 1.0), (-100 / 255, 1.0)])
@pytest.mark.parametrize("solver,levels", [(solve_fista, 3), (solve_fista, 0), (solve_pgd, 0)])
def test_solvers_on_cuda_reach_the_cpu_optimum(solver, levels, bounds):
    cpu = solver(rig(), bounds, max_iter=5000, tol=1e-10, levels=levels)
    gpu = solver(rig().to("cuda"), bounds, max_iter=5000, tol=1e-10, levels=levels)
    assert gpu.patterns.device.type == "cuda"
    assert len(gpu.info["coarse_iterations"]) == len(cpu.info["coarse_iterations"])
    assert gpu.objective == pytest.approx(cpu.objective, rel=1e-5)
    # The optimum's value, not its point: where targets leave directions free, the two devices'
    # round-off may settle on different patterns of the same objective. Bounds as float32 holds
    # them (-100/255 rounds down there).
    assert bool((gpu.patterns >= bounds[0]).all()) and bool((gpu.patterns <= bounds[1]).all())


def test_model_forward_and_backward_run_on_the_gpu_without_host_copies():
    from torchproj.metrics import SSIMLoss
    from torchproj.solve import ProjectionModel

    cpu = ProjectionModel(build_transport(synthetic_calibration(shape=(40, 50), sizes=LARGE), targets(channels=3),
                                          merge=False, scale=0.8))
    gpu = ProjectionModel(build_transport(synthetic_calibration(shape=(40, 50), sizes=LARGE), targets(channels=3),
                                          merge=False, scale=0.8)).to("cuda")
    with torch.no_grad():
        p = torch.rand(cpu.patterns.shape, generator=torch.Generator().manual_seed(4))
        cpu.patterns.copy_(p)
        gpu.patterns.copy_(p.cuda())
    losses = [SSIMLoss(m.targets, m.mask) for m in (cpu, gpu)]
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")  # any host synchronisation (a hidden copy, .item()) raises
    try:
        gpu_loss = (losses[1](gpu()) + (gpu() - gpu.targets).pow(2).mean()).sum()
        gpu_loss.backward()
    finally:
        torch.cuda.set_sync_debug_mode("default")
    cpu_loss = (losses[0](cpu()) + (cpu() - cpu.targets).pow(2).mean()).sum()
    cpu_loss.backward()
    assert gpu.patterns.grad.device.type == "cuda"
    assert gpu_loss.item() == pytest.approx(cpu_loss.item(), rel=1e-5)
    torch.testing.assert_close(gpu.patterns.grad.cpu(), cpu.patterns.grad, rtol=1e-4, atol=1e-6)


def test_ssim_solve_on_the_gpu_matches_the_cpu():
    from torchproj.solve import solve_ssim

    ops = [build_transport(synthetic_calibration(shape=(40, 50), sizes=LARGE), targets(channels=3), merge=False,
                           scale=0.8) for _ in range(2)]
    cpu = solve_ssim(ops[0], (0.0, 1.0), max_iter=20)
    gpu = solve_ssim(ops[1].to("cuda"), (0.0, 1.0), max_iter=20)
    assert gpu.patterns.device.type == "cuda" and gpu.iterations == cpu.iterations
    assert gpu.objective == pytest.approx(cpu.objective, rel=1e-3)
    assert gpu.info["model_ssim"] == pytest.approx(cpu.info["model_ssim"], abs=1e-3)


def channel_rig():
    """A colour rig with each channel's own white minus black (``build_channel_transports``)."""
    from torchproj.transport import build_channel_transports

    cals = synthetic_calibration(shape=(40, 50), sizes=LARGE)
    for cal in cals.values():
        cal.colour_weight = [w * torch.tensor([0.5, 1.0, 1.6])[:, None, None] for w in cal.weight]
    return build_channel_transports(cals, targets(channels=3), scale=0.8)


def test_one_operator_per_channel_moves_to_the_gpu_and_matches_the_cpu():
    """The per-channel stack reads its rows and targets from its operators, so a model moved to the
    GPU takes them along; its forward, gradient and SSIM solve are the CPU's."""
    from torchproj.solve import ProjectionModel, solve_ssim

    cpu, gpu = ProjectionModel(channel_rig()), ProjectionModel(channel_rig()).to("cuda")
    p = torch.rand(cpu.patterns.shape, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        cpu.patterns.copy_(p)
        gpu.patterns.copy_(p.cuda())
    losses = [(m() - m.targets).pow(2).mean() for m in (cpu, gpu)]
    for loss in losses:
        loss.backward()
    assert gpu.targets.device.type == "cuda" and gpu.patterns.grad.device.type == "cuda"
    assert losses[1].item() == pytest.approx(losses[0].item(), rel=1e-5)
    torch.testing.assert_close(gpu.patterns.grad.cpu(), cpu.patterns.grad, rtol=1e-4, atol=1e-6)
    solved_cpu = solve_ssim(channel_rig(), (0.0, 1.0), max_iter=10)
    solved_gpu = solve_ssim([op.to("cuda") for op in channel_rig()], (0.0, 1.0), max_iter=10)
    assert solved_gpu.patterns.device.type == "cuda" and solved_gpu.iterations == solved_cpu.iterations
    assert solved_gpu.objective == pytest.approx(solved_cpu.objective, rel=1e-3)
    assert solved_gpu.info["model_ssim"] == pytest.approx(solved_cpu.info["model_ssim"], abs=1e-3)


def test_shares_carried_on_the_gpu_are_the_cpus():
    """The camera loop's carried cell shares (its table of what the other pixels measured, and the even
    interval where that is sparse) computed on the GPU, against the CPU."""
    from torchproj.calib import CellShares
    from torchproj.pipeline.register import carry_shares

    g = torch.Generator().manual_seed(6)
    h, w = 40, 60
    xy = torch.stack(torch.meshgrid(torch.arange(w) * 0.4 + 2, torch.arange(h) * 0.45 + 2, indexing="xy"), -1)
    xy = xy + 0.02 * torch.randn(h, w, 2, generator=g)
    cell = torch.round(xy).to(torch.int32)
    across = (torch.rand(h, w, 2, 2, generator=g) * 0.6 - 0.2).clamp_min(0)
    shares = CellShares(cell, across, torch.zeros(h, w, 2), torch.rand(h, w, generator=g) * 0.3)
    slope = torch.tensor([[0.4, 0.0], [0.0, 0.45]]).expand(h, w, 2, 2)
    moved = xy + torch.tensor([0.3, -0.2])
    cpu = carry_shares(shares, xy, moved, slope, (40, 30))
    on = CellShares(*(t.cuda() for t in (shares.cell, shares.across, shares.outside, shares.checker)))
    gpu = carry_shares(on, xy.cuda(), moved.cuda(), slope.cuda(), (40, 30))
    assert gpu.across.device.type == "cuda"
    assert torch.equal(gpu.cell.cpu(), cpu.cell)
    torch.testing.assert_close(gpu.across.cpu(), cpu.across, rtol=1e-4, atol=1e-5, equal_nan=True)
    torch.testing.assert_close(gpu.checker.cpu(), cpu.checker, rtol=1e-4, atol=1e-5, equal_nan=True)
