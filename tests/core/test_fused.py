"""Fused element-wise chains: compiled where torch can, the eager chain's results, and eager with one
warning where compiling is switched off or impossible."""

import warnings
from types import SimpleNamespace

import pytest
import torch

from torchproj.core import fused as fused_module
from torchproj.sim.camera import _sensor, apply_camera


def _camera(**kw):
    return SimpleNamespace(**{"exposure": 1.6, "full_well": 20000, "read_noise": 0.002, "gamma": 1.0,
                              "bit_depth": 8, "frames": 1, **kw})


# Compiling takes 15-19 s on a first use in a process (every CI run's): with the slow tests, as the
# solvers' compiled pass (tests/solve/test_solvers.py) and the model's (tests/solve/test_model.py).
@pytest.mark.slow
@pytest.mark.parametrize("gamma, full_well, read_noise, bits", [(1.0, 20000, 0.002, 8), (2.2, 5000, 0.0, 8),
                                                                 (1.8, 0, 0.01, 16)])
def test_the_fused_camera_model_is_the_eager_chain(gamma, full_well, read_noise, bits, monkeypatch):
    """Compiled (``TORCHPROJ_COMPILE=1``) against the same chain run eagerly, image by image with the
    same noise: equal but where the last bit of a float rounds otherwise (at most one quantisation
    level, on a few pixels in 10^4)."""
    monkeypatch.setenv(fused_module.COMPILE_ENV, "1")
    radiance = torch.rand(2, 3, 120, 160, generator=torch.Generator().manual_seed(0)) * 0.8
    camera = _camera(gamma=gamma, full_well=full_well, read_noise=read_noise, bit_depth=bits)
    got = apply_camera(radiance.clone(), camera, torch.Generator().manual_seed(5))
    g = torch.Generator().manual_seed(5)
    peak = float((1 << bits) - 1)
    expected = torch.stack([_sensor.eager(r, torch.randn(r.shape, generator=g), camera.exposure,
                                          1 / full_well if full_well else 0.0, read_noise ** 2, 1 / gamma, peak)
                            for r in radiance])
    differ = got != expected
    assert float(differ.float().mean()) < 1e-4
    assert float((got - expected).abs().max()) <= 1 / peak + 1e-7
    # The physics, independently: no noise, no response: exposure, saturation and quantisation only.
    plain = apply_camera(radiance.clone(), _camera(gamma=1.0, bit_depth=bits), None)
    torch.testing.assert_close(plain, (radiance * 1.6).clamp(0, 1).mul(peak).round().div(peak), rtol=0, atol=1e-6)


def test_off_by_default_and_without_a_compiler_the_chain_runs_eagerly(monkeypatch):
    calls = []

    def chain(x):
        calls.append(x)
        return x * 2

    monkeypatch.delenv(fused_module.COMPILE_ENV, raising=False)
    plain = fused_module.fused(chain)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # off by default: no warning, no compile
        assert torch.equal(plain(torch.ones(3)), torch.full((3,), 2.0))
    monkeypatch.setenv(fused_module.COMPILE_ENV, "1")
    monkeypatch.setattr(fused_module.shutil, "which", lambda name: None)
    missing = fused_module.fused(chain)
    with pytest.warns(UserWarning, match="no C.. compiler found for torch.compile: chain runs unfused"):
        missing(torch.ones(3))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # one warning, not one per call
        missing(torch.ones(3))
    assert len(calls) == 3


def test_a_chain_that_fails_to_compile_warns_once_and_runs_eagerly(monkeypatch):
    def broken_compile(fn, **kwargs):
        def compiled(*args):
            raise RuntimeError("inductor: no C++ compiler could build this")
        return compiled

    monkeypatch.setattr(fused_module.torch, "compile", broken_compile)
    monkeypatch.setenv(fused_module.COMPILE_ENV, "1")
    monkeypatch.setattr(fused_module, "_compiler", lambda: True)
    chain = fused_module.fused(lambda x: x + 1)
    with pytest.warns(UserWarning, match=r"torch.compile failed \(RuntimeError: .*\): <lambda> runs unfused"):
        assert torch.equal(chain(torch.zeros(2)), torch.ones(2))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert torch.equal(chain(torch.zeros(2)), torch.ones(2))
