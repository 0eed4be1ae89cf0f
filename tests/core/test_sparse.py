import pytest
import torch

import torchproj.core.sparse as sparse
from torchproj.core.sparse import csr_tensor, spmm


def _matrix(rows: int, cols: int, density: float, dtype, seed: int):
    gen = torch.Generator().manual_seed(seed)
    dense = torch.rand(rows, cols, generator=gen, dtype=torch.float64)
    dense *= torch.rand(rows, cols, generator=gen, dtype=torch.float64) < density
    dense[rows // 2] = 0  # an empty row
    csr = dense.to(dtype).to_sparse_csr()
    return csr_tensor(csr.crow_indices(), csr.col_indices(), csr.values(), (rows, cols)), dense.to(dtype).double()


@pytest.mark.parametrize("vector_kernel", [True, False])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16])
@pytest.mark.parametrize("columns", [1, 3])
def test_spmm_is_the_dense_product_by_either_kernel(vector_kernel, dtype, columns, monkeypatch):
    # one column goes to torch's matrix-vector kernel, more to its matrix-matrix one; the same
    # product by either, into a buffer given or not, from a column of a wider block or not
    monkeypatch.setattr(sparse, "VECTOR_KERNEL", vector_kernel)
    matrix, dense = _matrix(300, 170, 0.05, dtype, seed=columns)
    gen = torch.Generator().manual_seed(7)
    wide = torch.rand(170, columns + 2, generator=gen).to(dtype)
    tol = {torch.float64: 1e-12, torch.float32: 1e-5, torch.float16: 2e-3}[dtype]
    for x in (wide[:, :columns].contiguous(), wide[:, 1:1 + columns]):
        expected = dense @ x.double()
        scale = float(expected.abs().max())
        got = spmm(matrix, x)
        assert got.shape == (300, columns) and got.dtype == dtype
        assert float((got.double() - expected).abs().max()) <= tol * scale
        buffer = torch.full((300, columns + 1), float("nan"), dtype=dtype)
        out = buffer[:, 1:]  # a view whose rows are not contiguous: written in place
        assert spmm(matrix, x, out).data_ptr() == out.data_ptr()
        assert float((out.double() - expected).abs().max()) <= tol * scale
        assert torch.isnan(buffer[:, 0]).all()

