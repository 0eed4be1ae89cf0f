"""The CUDA stand-in (``tests/fake_cuda.py``) refuses what a GPU refuses and allows what it allows;
the cases follow torch's own rules for CUDA tensors."""

import numpy as np
import pytest
import torch

from torchproj.core import to_numpy

from .fake_cuda import FakeCudaError, fake_cuda, on_fake_cuda


def test_tensors_made_or_moved_there_read_cuda_and_keep_it_through_operations():
    with fake_cuda():
        x = torch.arange(6.0, device="cuda").reshape(2, 3)
        y = torch.ones(3).to("cuda")
        assert x.device.type == "cuda" and on_fake_cuda(y)
        z = (x * y).sum(0)
        assert on_fake_cuda(z) and z.device.type == "cuda"
        assert on_fake_cuda(torch.zeros(2, device=z.device))  # the idiom that keeps tensors together
        assert on_fake_cuda(x.double()) and on_fake_cuda(torch.zeros(2).to(x))
        host = x.cpu()
        assert not on_fake_cuda(host) and host.device.type == "cpu" and on_fake_cuda(x)
        model = torch.nn.Linear(3, 2).to("cuda")
        assert all(on_fake_cuda(p) for p in model.parameters())
        assert on_fake_cuda(torch.nn.Parameter(x.clone()))
        g = torch.Generator(device="cuda").manual_seed(0)
        assert g.device.type == "cuda" and on_fake_cuda(torch.rand(3, generator=g, device="cuda"))


def test_numpy_of_a_device_tensor_is_refused_and_to_numpy_brings_it_home():
    with fake_cuda():
        x = torch.ones(3, device="cuda")
        with pytest.raises(FakeCudaError, match="numpy"):
            x.numpy()
        with pytest.raises(FakeCudaError, match="numpy"):
            np.asarray(x)
        np.testing.assert_array_equal(to_numpy(x), np.ones(3))
        np.testing.assert_array_equal(torch.ones(2).numpy(), np.ones(2))  # a host tensor is fine


def test_host_and_device_tensors_do_not_mix_except_as_torch_allows():
    with fake_cuda():
        x = torch.ones(4, device="cuda")
        with pytest.raises(FakeCudaError, match="same device|on the host"):
            x + torch.arange(4)
        with pytest.raises(FakeCudaError):
            torch.arange(4)[torch.tensor([0, 1], device="cuda")]  # a host tensor through device indices
        assert on_fake_cuda(x + torch.tensor(2.0))  # a 0-dim host scalar is allowed
        assert on_fake_cuda(x[torch.tensor([0, 2])])  # a device tensor through host indices is allowed
        host = torch.zeros(4)
        host[1:3] = x[:2]  # a slice written from the other device is a copy
        host.copy_(x)
        x[1:] = torch.ones(3)
        assert on_fake_cuda(x) and not on_fake_cuda(host)
        with pytest.raises(FakeCudaError, match="index tensors"):
            host[torch.tensor([0, 1])] = x[:2]


def test_outside_the_context_nothing_is_changed():
    with fake_cuda():
        pass
    assert torch.Generator is torch._C.Generator
    x = torch.ones(2)
    assert not on_fake_cuda(x) and x.numpy().sum() == 2
