"""Sparse CSR construction and products shared by the simulator and the transport operator."""

from __future__ import annotations

import warnings

import torch

from .checks import check, check_indices, check_pair, check_shape

__all__ = ["csr_from_coo", "csr_tensor", "index_dtype", "spmm"]

_INT32_LIMIT = 2**31 - 1
_WIDENED = (torch.float16, torch.bfloat16)  # stored in 16 bits, multiplied in float32


def index_dtype(*sizes: int) -> torch.dtype:
    """The index type torchproj keeps for arrays that count or point up to ``sizes``: int32 where
    every one fits (:func:`csr_tensor`'s reason), else int64."""
    return torch.int32 if max(sizes) <= _INT32_LIMIT else torch.int64


def csr_tensor(crow: torch.Tensor, col: torch.Tensor, val: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """A CSR tensor from its arrays, without invariant checks (callers build them sorted).

    Indices are stored as int32 wherever they fit. The CPU's sparse kernels (MKL) take 32-bit
    indices and torch converts 64-bit ones on every product; on the paper's full-size rig that
    conversion cost as much as the product itself (``benchmarks/solvers.py`` measures the product).

    torch flags CSR support as beta on every construction, and (2.11 with CUDA) that invariant checks
    are off, which is what ``check_invariants=False`` asks; the products torchproj uses are stable and
    the callers build sorted arrays, so both warnings are silenced here rather than everywhere.
    """
    if index_dtype(*shape, col.numel()) == torch.int32:
        crow, col = crow.to(torch.int32), col.to(torch.int32)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
        warnings.filterwarnings("ignore", message="Sparse invariant checks are implicitly disabled")
        return torch.sparse_csr_tensor(crow, col, val, shape, check_invariants=False)


#: Whether one column goes to the sparse matrix-vector kernel on the CPU (:func:`spmm`); off, the
#: matrix-matrix one, as before (``benchmarks/spmv.py`` compares them in one process).
VECTOR_KERNEL = True


def spmm(matrix: torch.Tensor, x: torch.Tensor, out: torch.Tensor | None = None, add: bool = False) -> torch.Tensor:
    """``matrix @ x`` for a CSR matrix and a dense :math:`(N, K)` block, written into ``out``.

    ``addmm`` with ``beta=0`` into a given output is torch's direct path to the sparse kernel:
    ``matrix @ x`` first fills a zero result and copies it, which doubles the time of a product.
    ``out`` (:math:`(M, K)`, same dtype and device) lets iterative solvers reuse one buffer; its
    contents are ignored, or with ``add`` (and ``out`` given) the product is added to them.
    """
    beta = 1 if add and out is not None else 0
    if x.device.type == "meta":  # shapes only (a model moved to the meta device): no values to multiply
        return torch.empty(matrix.shape[0], x.shape[1], dtype=x.dtype, device=x.device)
    if x.dtype in _WIDENED:
        # The sparse kernels take no 16-bit floats (MKL: "not implemented for 'Half'"): the values are
        # stored in 16 bits and the product accumulates in float32, rounded once at the end.
        wide = spmm(matrix.to(torch.float32), x.to(torch.float32))
        return wide.to(x.dtype) if out is None else out.add_(wide) if beta else out.copy_(wide)
    if out is None:
        out = torch.empty(matrix.shape[0], x.shape[1], dtype=x.dtype, device=x.device)
    if x.shape[1] == 1 and x.device.type == "cpu" and VECTOR_KERNEL:
        # One column (a grey image, one colour channel's operator): the CPU's sparse matrix-vector
        # kernel, 1.2-2.4x faster than its matrix-matrix one on the same column (the default rig's
        # A 11.6 against 15.4 ms, A^T 5.8 against 10.4, Q 8.8 against 15.7; benchmarks/spmv.py),
        # while 3 columns cost the matrix-matrix kernel about what one does.
        torch.addmv(out[:, 0], matrix, x[:, 0], beta=beta, out=out[:, 0])
        return out
    return torch.addmm(out, matrix, x, beta=beta, out=out)


def csr_from_coo(rows: torch.Tensor, cols: torch.Tensor, vals: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """A CSR matrix from COO triplets (duplicates summed, columns sorted within each row)."""
    shape = check_pair(shape, "shape", "(rows, columns)")
    sizes = check_shape(vals, "vals", ["N"])
    for name, index in (("rows", rows), ("cols", cols)):
        check_indices(index, name, [sizes["N"]])
    n_rows, n_cols = shape
    # A column past the last lands in the next row's key without a word: one pass each (a few ms on a
    # full-size build's entries, against the sort below).
    for name, index, size in (("rows", rows, n_rows), ("cols", cols, n_cols)):
        if index.numel():
            low, high = torch.aminmax(index)
            check(int(low) >= 0 and int(high) < size, f"{name} must index 0 to {size - 1} (shape {tuple(shape)}), "
                                                       f"got {int(low)} to {int(high)}")
    key = rows * n_cols + cols
    key, inverse = torch.unique(key, return_inverse=True)
    merged = torch.zeros(key.shape[0], dtype=vals.dtype, device=vals.device).index_add_(0, inverse, vals)
    r, c = key // n_cols, key % n_cols
    crow = torch.zeros(n_rows + 1, dtype=torch.int64, device=vals.device)
    crow[1:] = torch.cumsum(torch.bincount(r, minlength=n_rows), 0)
    return csr_tensor(crow, c, merged, shape)
