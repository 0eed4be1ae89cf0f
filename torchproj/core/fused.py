"""Chains of element-wise operations fused into one loop by ``torch.compile`` (inductor), on request.

Eager torch reads and writes every pixel once per operation; the camera model's chain (exposure,
shot and read noise, saturation, response, quantisation) is eight such passes over each image.
Compiled it is one loop: on a capture of the default rig 0.034 s against 0.231 s eager, at the floor
its bytes set at this machine's memory bandwidth (0.033 s), with the same values but for the last
bit of a float on 4 pixels in 84 million (``benchmarks/fused_kernels.py``, ``tests/core/test_fused.py``).
It is off by default, measured: drawing the noise (0.300 s) and the capture's copies stay, so the
camera model goes from 0.68 to 0.59 s, and importing and compiling costs each process more than that
saves in a ``torchproj run`` (49-51 s against 42-46 s wall, inductor's cache warm; 55 s cold).
``TORCHPROJ_COMPILE=1`` turns it on (long simulations of many captures in one process); where no C++
compiler exists, or compiling fails, the chain runs eagerly after one warning.

The same switch compiles FISTA's element-wise pass (:mod:`torchproj.solve.solvers`) into one loop over
whole blocks, for batches of target sets whose blocks do not fit in the cache
(``python benchmarks/batch_solves.py`` measures it against the eager pass, in turn).
"""

from __future__ import annotations

import functools
import os
import shutil
import warnings

import torch

from .checks import env_switch

__all__ = ["COMPILE_ENV", "compile_enabled", "fused"]

COMPILE_ENV = "TORCHPROJ_COMPILE"  # "1": compile the fused chains (default off, see the module's docs)


def compile_enabled() -> bool:
    """Whether fused chains are to be compiled: asked for with ``TORCHPROJ_COMPILE=1``
    (:func:`~torchproj.core.checks.env_switch`)."""
    return env_switch(COMPILE_ENV)


def _compiler() -> bool:
    """A C++ compiler for inductor's CPU code."""
    return any(shutil.which(name) for name in (os.environ.get("CXX", ""), "g++", "c++", "clang++") if name)


def fused(fn):
    """``fn`` (tensors and numbers in, one tensor out, element-wise; it may also write into tensors it
    is given), compiled on its first call when :func:`compile_enabled`, else ``fn`` itself.

    Where compiling is asked for but impossible (no compiler, a platform inductor does not support),
    it warns once and runs ``fn`` eagerly from then on; results are the same either way. The
    wrapper's ``active()`` says whether its calls run compiled (asked for, and not given up), for a
    caller whose own eager path is faster than ``fn`` run eagerly.
    """
    state = {"compiled": None, "failed": False}

    def give_up(message: str) -> None:
        state["failed"] = True
        warnings.warn(f"{message}: {fn.__name__} runs unfused (slower, the same results); unset {COMPILE_ENV} to "
                      "silence this", stacklevel=3)

    @functools.wraps(fn)
    def call(*args):
        if state["failed"] or not compile_enabled():
            return fn(*args)
        if state["compiled"] is None:
            if not _compiler():
                give_up("no C++ compiler found for torch.compile")
                return fn(*args)
            state["compiled"] = torch.compile(fn, dynamic=True, fullgraph=True)
        try:
            return state["compiled"](*args)
        except Exception as exc:  # noqa: BLE001 - any failure to compile falls back to the same function, eagerly
            give_up(f"torch.compile failed ({type(exc).__name__}: {str(exc)[:200]})")
            return fn(*args)

    call.eager = fn
    call.active = lambda: compile_enabled() and not state["failed"]
    return call
