"""The CUDA path against the CPU one. Skipped where torch sees no GPU (CI has none)."""

import pytest
import torch

from torchproj.solve import solve_fista, solve_pgd
from torchproj.transport import build_transport

from ..transport.test_build import synthetic_calibration, targets
from ..transport.test_operator import LARGE

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(),
                                reason="no CUDA device: the GPU path is checked on machines that have one")


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
    for (ne_gpu, block_gpu), (ne_cpu, block_cpu) in zip(gpu.coarse_levels(3), cpu.coarse_levels(3)):
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
