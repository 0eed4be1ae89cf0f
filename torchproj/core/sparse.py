"""Sparse CSR construction shared by the simulator and the transport operator."""

from __future__ import annotations

import warnings

import torch

__all__ = ["csr_tensor"]


def csr_tensor(crow: torch.Tensor, col: torch.Tensor, val: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """A CSR tensor from its arrays, without invariant checks (callers build them sorted).

    torch flags CSR support as beta on every construction; the products torchproj uses are stable,
    so that warning is silenced here rather than everywhere.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
        return torch.sparse_csr_tensor(crow, col, val, shape, check_invariants=False)
