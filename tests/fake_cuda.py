"""A stand-in for a CUDA device on a machine without one, to find what breaks the GPU path in CI.

CI has no GPU, and the GPU path broke unseen more than once: a tensor still on the device handed to
numpy, or a tensor made on the host (``torch.arange(n)``) mixed with one on the device. Inside
:func:`fake_cuda`, ``"cuda"`` is accepted as a device and every tensor made on it or moved to it is
an ordinary CPU tensor carrying a mark; the mark follows through every torch operation (a
``TorchFunctionMode``), ``x.device`` of a marked tensor reads ``cuda`` (so ``device=x.device``
keeps tensors together, as on a GPU), and what a GPU refuses is refused here too:

- ``.numpy()`` (and numpy's ``__array__``) of a marked tensor, as torch does for a CUDA tensor;
- an operation mixing marked tensors with unmarked ones that are not 0-dim (torch's "Expected all
  tensors to be on the same device"), except copies between devices and a device tensor indexed
  by host indices, which torch allows.

It checks where tensors live, not the numbers or the speed: kernels that differ or fail on a GPU
(cuSOLVER's batched eigen-decomposition did) are only checked on a real one
(``tests/solve/test_cuda.py``, ``benchmarks/cuda_checks.sh``). ``torch.Generator(device="cuda")``,
``torch.load(map_location="cuda")`` and ``nn.Parameter`` of a device tensor give host objects that
read as on the device; ``torch.cuda.synchronize`` and the like do nothing.
"""

from __future__ import annotations

import contextlib
from unittest import mock

import torch
from torch.overrides import TorchFunctionMode

_MARK = "_fake_cuda"
CUDA = torch.device("cuda")


class FakeCudaError(RuntimeError):
    """What a GPU would refuse."""


def on_fake_cuda(t) -> bool:
    return isinstance(t, torch.Tensor) and getattr(t, _MARK, False)


def _tensors(tree):
    """The tensors in nested tuples (torch's named return types among them), lists and dicts: what
    torch functions take and return. torch's own pytree walk did the same at a third of the tests'
    time in this mode."""
    if isinstance(tree, torch.Tensor):
        yield tree
    elif isinstance(tree, (tuple, list)):
        for item in tree:
            yield from _tensors(item)
    elif isinstance(tree, dict):
        for item in tree.values():
            yield from _tensors(item)


def _mark(out):
    for t in _tensors(out):
        setattr(t, _MARK, True)
    return out


def _is_cuda(device) -> bool:
    if device is None:
        return False
    if isinstance(device, torch.Tensor):
        return on_fake_cuda(device)
    try:
        return torch.device(device).type == "cuda"
    except (RuntimeError, TypeError):
        return False


def _host(device):
    return torch.device("cpu") if _is_cuda(device) else device


# Operations a GPU allows across devices: copies, and indexing within the rules of _check_indexing.
_INDEXING = {torch.Tensor.__getitem__, torch.Tensor.__setitem__, torch.Tensor.index_put_}
_CROSSING = {torch.Tensor.copy_, *_INDEXING}
_FREE = {torch._has_compatible_shallow_copy_type}
_SETTERS = {torch.Tensor.data.__set__}
_TO_HOST = {torch.Tensor.numpy, torch.Tensor.__array__}


class _FakeCudaMode(TorchFunctionMode):
    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        name = getattr(func, "__name__", "")
        if func in _FREE:
            return func(*args, **kwargs)
        if func in _SETTERS:  # x.data = y: x lives where y does
            func(*args, **kwargs)
            if on_fake_cuda(args[1]):
                _mark(args[0])
            elif on_fake_cuda(args[0]):
                delattr(args[0], _MARK)
            return None
        if func == torch.Tensor.device.__get__:  # method-wrappers are made afresh: compare, not identity
            return CUDA if on_fake_cuda(args[0]) else func(*args, **kwargs)
        if func in _TO_HOST and on_fake_cuda(args[0]):
            raise FakeCudaError(f"can't convert cuda:0 device type tensor to numpy ({name}); use .cpu() first")
        if func is torch.Tensor.cpu:
            return _unmarked(args[0])
        if func is torch.Tensor.cuda:
            return _mark(_unmarked(args[0]))
        if func is torch.Tensor.to:
            return self._to(func, args, kwargs)
        to_device = _is_cuda(kwargs.get("device"))
        if "device" in kwargs:
            kwargs["device"] = _host(kwargs["device"])
        tensors = list(_tensors((args, kwargs)))
        marked = any(on_fake_cuda(t) for t in tensors)
        if marked and func not in _CROSSING:
            host = [tuple(t.shape) for t in tensors if not on_fake_cuda(t) and t.dim() > 0]
            if host:
                raise FakeCudaError(f"{name}: tensors on cuda:0 and on the host (shapes {host}) in one operation")
        if func in _INDEXING:
            _check_indexing(name, args)
        out = func(*args, **kwargs)
        # In place (copy_, __setitem__) the result is the target, which keeps its own place.
        lands_on_device = (marked and func not in _CROSSING) or to_device or (
            func is torch.Tensor.__getitem__ and on_fake_cuda(args[0]))
        return _mark(out) if lands_on_device else out

    def _to(self, func, args, kwargs):
        self_, rest = args[0], args[1:]
        copy = kwargs.pop("copy", False)
        if rest and isinstance(rest[0], torch.Tensor):  # .to(other): other's device and dtype
            target, dtype, non_blocking, memory_format = rest[0], rest[0].dtype, False, None
        else:
            device = kwargs.pop("device", None)
            rest = tuple(_host(a) if isinstance(a, (str, torch.device)) else a for a in rest)
            target, dtype, non_blocking, memory_format = torch._C._nn._parse_to(*rest, **kwargs)
            target = device if device is not None else (CUDA if any(_is_cuda(a) for a in args[1:]) else target)
        out = func(self_, dtype=dtype or self_.dtype, non_blocking=non_blocking, copy=copy,
                   **({"memory_format": memory_format} if memory_format is not None else {}))
        out = out if out is not self_ else _unmarked(self_)
        if _is_cuda(target) or (target is None and on_fake_cuda(self_)):
            return _mark(out)
        return out


def _check_indexing(name: str, args) -> None:
    """What torch allows when indexing across devices: a device tensor indexed by host tensors, and
    slices (no index tensor) written from either device, which is a copy; not a host tensor indexed by
    device tensors, nor device values scattered through index tensors into a host tensor or host
    values (not 0-dim) into a device one."""
    self_, index = args[0], args[1]
    value = args[2] if len(args) > 2 else None
    index_tensors = list(_tensors(index))
    if not on_fake_cuda(self_) and any(map(on_fake_cuda, index_tensors)):
        raise FakeCudaError(f"{name}: a host tensor indexed through cuda:0 tensors")
    if isinstance(value, torch.Tensor) and value.dim() > 0 and index_tensors \
            and on_fake_cuda(value) != on_fake_cuda(self_):
        raise FakeCudaError(f"{name}: values on one device written through index tensors into the other")


def _unmarked(t: torch.Tensor) -> torch.Tensor:
    """A new tensor object over the same data, without the mark (``.cpu()`` of a host tensor is itself)."""
    with torch._C.DisableTorchFunction():
        out = t.view_as(t) if t.layout == torch.strided else t.clone()
    return out


class _HostGenerator(torch.Generator):
    """``torch.Generator(device="cuda")`` on the host (a real CUDA generator needs a GPU)."""

    def __new__(cls, device="cpu"):
        generator = super().__new__(cls, _host(device))
        generator.on_cuda = _is_cuda(device)
        return generator

    @property
    def device(self):
        return CUDA if self.on_cuda else torch.device("cpu")


_parameter_new = torch.nn.Parameter.__new__
_load = torch.load


def _parameter(cls, data=None, requires_grad=True):
    """``nn.Parameter(x)`` wraps ``x``'s data in a new object (not through torch's function overrides):
    on the device where ``x`` is."""
    out = _parameter_new(cls, data, requires_grad)
    return _mark(out) if on_fake_cuda(data) else out


def _fake_load(*args, map_location=None, **kwargs):
    """``torch.load(..., map_location="cuda")``: read on the host, every tensor marked."""
    if not _is_cuda(map_location):
        return _load(*args, map_location=map_location, **kwargs)
    out = _load(*args, map_location="cpu", **kwargs)
    _mark_all(out)
    return out


def _mark_all(obj, seen=None) -> None:
    """Mark every tensor reachable from ``obj`` through containers and dataclasses' fields."""
    seen = set() if seen is None else seen
    if id(obj) in seen:
        return
    seen.add(id(obj))
    if isinstance(obj, torch.Tensor):
        _mark(obj)
    elif isinstance(obj, dict):
        for v in obj.values():
            _mark_all(v, seen)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            _mark_all(v, seen)
    elif hasattr(obj, "__dict__"):
        for v in vars(obj).values():
            _mark_all(v, seen)


@contextlib.contextmanager
def fake_cuda():
    """Run the enclosed code as if a CUDA device were present (see the module's docstring)."""
    with mock.patch("torch.cuda.is_available", return_value=True), \
            mock.patch("torch.cuda.device_count", return_value=1), \
            mock.patch("torch.cuda.synchronize"), mock.patch("torch.cuda.set_sync_debug_mode"), \
            mock.patch("torch.cuda.get_device_name", return_value="fake CUDA"), \
            mock.patch("torch.Generator", _HostGenerator), \
            mock.patch.object(torch.nn.Parameter, "__new__", _parameter), mock.patch("torch.load", _fake_load), \
            _FakeCudaMode():
        yield
