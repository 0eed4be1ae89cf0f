"""The operator's coarse levels (cells tied in blocks) against dense float64 algebra."""

import io
import math

import numpy as np
import pytest
import torch

from torchproj.core.errors import InputError
from torchproj.transport import StateCalibration, TransportOperator, build_transport, cell_blocks
from torchproj.core.sparse import csr_tensor
from torchproj.transport.operator import _blockwise_sum, _transpose

from ..helpers import LARGE, synthetic_calibration, targets


@pytest.fixture(scope="module")
def op():
    return build_transport(synthetic_calibration(shape=(40, 50), sizes=LARGE), targets(channels=3), scale=0.8).double()


@pytest.fixture(scope="module")
def op_gram(op):
    """``op``'s ``A^T A`` by float64 dense algebra, made once: it is the reference eight tests compare with."""
    dense = op._csr().to_dense()
    return dense.T @ dense


def two_projectors(channels: int) -> TransportOperator:
    """A fresh small operator of two projectors, for the smoothness tests (each smoothed operator is kept
    by the one it was made from, so a test that counts what is built starts from a new one)."""
    return build_transport(synthetic_calibration(shape=(20, 24), sizes=[(14, 12), (12, 10)]),
                           targets(channels=channels), scale=0.8)


def tie_matrix(block: torch.Tensor) -> torch.Tensor:
    """The dense 0/1 matrix P with p = P p_c."""
    return torch.nn.functional.one_hot(block, int(block.max()) + 1).double()


def test_cell_blocks_tie_two_by_two_cells_of_one_projector():
    sizes = [(7, 5), (6, 4)]
    g = torch.Generator().manual_seed(0)
    cells = [(j, c) for j, (w, h) in enumerate(sizes) for c in range(w * h)]
    keep = torch.randperm(len(cells), generator=g)[:40]
    projector = torch.tensor([cells[i][0] for i in keep])
    cell = torch.tensor([cells[i][1] for i in keep])
    block, block_projector, block_cell, block_sizes = cell_blocks(projector, cell, sizes)
    assert block_sizes == [(4, 3), (3, 2)]  # odd sizes round up
    for a in range(len(keep)):
        w = sizes[projector[a]][0]
        x, y = int(cell[a]) % w, int(cell[a]) // w
        b = int(block[a])
        assert int(block_projector[b]) == int(projector[a])
        assert int(block_cell[b]) == (y // 2) * block_sizes[projector[a]][0] + x // 2
        for other in range(len(keep)):
            wo = sizes[projector[other]][0]
            same = (int(projector[other]) == int(projector[a]) and int(cell[other]) % wo // 2 == x // 2
                    and int(cell[other]) // wo // 2 == y // 2)
            assert (int(block[other]) == b) == same
    assert sorted(set(block.tolist())) == list(range(len(block_cell)))  # every block has a column


def test_coarse_levels_are_the_tied_problem(op):
    levels = op.coarse_levels(3)
    assert len(levels) == 2  # a third level would fall under 64 columns
    assert levels[1][0].Q.shape[0] < levels[0][0].Q.shape[0] / 3 < op.shape[1] / 9
    A = op.dense()
    Q_full, q_full = A.T @ A, A.T @ op.rhs
    tie = torch.eye(op.shape[1], dtype=torch.float64)
    g = torch.Generator().manual_seed(3)
    for ne, block in levels:
        tie = tie @ tie_matrix(block)
        torch.testing.assert_close(ne.Q.to_dense(), tie.T @ Q_full @ tie, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(ne.q, tie.T @ q_full, rtol=1e-12, atol=1e-12)
        # The tied problem's objective is the full objective of the pattern it stands for.
        pc = torch.rand(ne.Q.shape[0], 3, generator=g, dtype=torch.float64)
        assert ne.objective(pc, ne.product(pc)) == pytest.approx(float(op.objective(tie @ pc)), rel=1e-12)
    assert op.coarse_levels(3)[0][0] is levels[0][0]  # cached


def test_with_rhs_carries_the_coarse_levels(op):
    levels = op.coarse_levels(2)
    for ne, _ in levels:
        ne.jacobi().lipschitz()
    cals = synthetic_calibration(shape=(40, 50), sizes=LARGE)
    fresh = build_transport(cals, targets(channels=3, seed=7), scale=0.8).double()
    swapped = op.with_rhs(fresh.rhs, fresh.constant)
    for (ne, block), (ref, ref_block), (old, _) in zip(swapped.coarse_levels(2), fresh.coarse_levels(2), levels):
        assert torch.equal(block, ref_block)
        assert ne.Q is old.Q and ne.jacobi().Q is old.jacobi().Q  # shared, not rebuilt
        torch.testing.assert_close(ne.q, ref.q, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(ne.jacobi().q, ref.jacobi().q, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("form", ["matrix", "products"])
def test_what_one_set_of_targets_computes_on_q_every_other_set_reuses(form):
    """Copies made before anything was solved (a video's frames, a loop's steps): the scaling, bounds
    and coarse levels one copy's solve computes are its parent's and every other copy's, not computed
    again per copy; each copy's targets are its own (against a fresh build with them)."""
    from torchproj.solve import solve_fista

    cals = synthetic_calibration(shape=(40, 50), sizes=LARGE)
    op = build_transport(cals, targets(channels=3), scale=0.8).double()
    root = op.normal_equations(form)
    fresh = [build_transport(cals, targets(channels=3, seed=s), scale=0.8).double() for s in (7, 8)]
    first, second = (op.with_rhs(f.rhs, f.constant) for f in fresh)
    assert root._jacobi is None and root._coarse is None
    first.normal_equations(form).jacobi().lipschitz()  # what a solve on the first copy computes
    for level, _ in first.coarse_levels(2, form):
        level.jacobi().lipschitz()
    assert root._jacobi is not None and root._jacobi._lipschitz is not None and root._coarse is not None
    ne = second.normal_equations(form)
    assert ne.jacobi().scale is root.jacobi().scale and ne.lipschitz() == root.lipschitz()
    assert ne.jacobi().lipschitz() == root.jacobi().lipschitz()
    for (level, block), (mine, _), (ref, ref_block) in zip(op.coarse_levels(2, form), second.coarse_levels(2, form),
                                                         fresh[1].coarse_levels(2, form)):
        assert torch.equal(block, ref_block)
        shared = (mine.Q is level.Q) if form == "matrix" else (mine.A is level.A)
        assert shared and mine.jacobi().scale is level.jacobi().scale
        torch.testing.assert_close(mine.q, ref.q, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(mine.jacobi().q, ref.jacobi().q, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(ne.jacobi().q, fresh[1].normal_equations(form).jacobi().q, rtol=1e-12, atol=1e-12)
    solved = solve_fista(second, (0, 1), max_iter=200, tol=1e-9).objective
    assert solved == pytest.approx(solve_fista(fresh[1], (0, 1), max_iter=200, tol=1e-9).objective, rel=1e-6)


def test_bounds_of_the_scaled_system_are_shared_by_every_set_of_targets(op):
    ne = op.normal_equations()
    assert ne.bound(0.7) == 0.7  # no scaling: a number
    scaled = ne.jacobi()
    assert scaled.bound(0.0) == 0.0  # zero scales to zero
    hi = scaled.bound(1.0)
    torch.testing.assert_close(hi * scaled.scale.expand_as(hi), torch.ones_like(hi), rtol=1e-12, atol=0)
    assert hi.shape == scaled.q.shape and hi.is_contiguous()
    assert scaled.bound(1.0) is hi
    fresh = build_transport(synthetic_calibration(shape=(40, 50), sizes=LARGE), targets(channels=3, seed=7), scale=0.8)
    swapped = op.with_rhs(fresh.rhs.double(), fresh.constant.double())
    assert swapped.normal_equations().jacobi().bound(1.0) is hi


def test_coarsening_stops_where_blocks_hold_one_lit_cell():
    # Every correspondence on a cell with even x and y: each 2x2 block holds one column, so tying
    # saves nothing.
    g = torch.Generator().manual_seed(1)
    sizes = [(40, 30), (40, 30)]
    prj = [2 * torch.randint(0, 15, (30, 40, 2), generator=g).double() for _ in sizes]
    wts = [torch.ones(30, 40) for _ in sizes]
    cal = {"near": StateCalibration(prj, wts, sizes), "far": StateCalibration(prj, wts, sizes)}
    scattered = build_transport(cal, targets(), scale=1.0)
    assert scattered.coarse_levels(3) == []


def test_coarse_levels_follow_dtype_changes():
    single = build_transport(synthetic_calibration(shape=(40, 50), sizes=LARGE), targets(), scale=0.8)
    assert single.coarse_levels(1)[0][0].Q.dtype == torch.float32
    single.double()  # in place, as nn.Module does
    ne, block = single.coarse_levels(1)[0]
    assert ne.Q.dtype == torch.float64 and ne.q.dtype == torch.float64 and block.device == single.column_cell.device


@pytest.mark.parametrize("n", [700, 5000, 2_782_953])  # under one run, a few runs, the full-size rig's p
def test_blockwise_sum_is_as_good_as_float64_accumulation(n):
    # Terms that nearly cancel, as the objective's do: a float32 running total would drift.
    x = torch.rand(n, generator=torch.Generator().manual_seed(n)) * 2 - 1.0003
    exact = math.fsum(x.double().tolist())
    total = _blockwise_sum(x)
    assert total.dtype == torch.float64
    assert abs(float(total) - exact) <= 1e-8 * float(x.abs().sum())
    assert float(_blockwise_sum(x.double())) == pytest.approx(exact, rel=1e-12, abs=1e-9)


def test_the_product_form_applies_the_same_normal_equations(op):
    """``A^T (A p)`` without Q: the same product, scaling, coarse levels (with their targets carried
    by ``with_rhs``) and Lipschitz bound as the formed ``Q``, against dense float64 algebra."""
    A = op.dense()
    g = torch.Generator().manual_seed(5)
    p = torch.rand(op.shape[1], 3, generator=g, dtype=torch.float64)
    matrix, products = op.normal_equations("matrix"), op.normal_equations("products")
    assert products.Q is None and op.normal_equations("products") is products  # never built; cached
    torch.testing.assert_close(products.product(p), A.T @ (A @ p), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(products.q, matrix.q, rtol=1e-12, atol=1e-12)
    assert products.objective(p, products.product(p)) == pytest.approx(float(op.objective(p)), rel=1e-12)
    scaled = products.jacobi()
    torch.testing.assert_close(scaled.scale, matrix.jacobi().scale, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(scaled.product(p), matrix.jacobi().product(p), rtol=1e-12, atol=1e-12)
    assert products.lipschitz() >= torch.linalg.eigvalsh(A.T @ A)[-1] * (1 - 1e-9)
    tie = torch.eye(op.shape[1], dtype=torch.float64)
    for (ne, block), (ref, ref_block) in zip(op.coarse_levels(2, "products"), op.coarse_levels(2, "matrix")):
        assert torch.equal(block, ref_block)
        tie = tie @ tie_matrix(block)
        pc = torch.rand(ne.q.shape[0], 3, generator=g, dtype=torch.float64)
        torch.testing.assert_close(ne.product(pc), tie.T @ A.T @ A @ tie @ pc, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(ne.q, ref.q, rtol=1e-12, atol=1e-12)
    fresh = build_transport(synthetic_calibration(shape=(40, 50), sizes=LARGE), targets(channels=3, seed=7),
                            scale=0.8).double()
    swapped = op.with_rhs(fresh.rhs, fresh.constant)
    for (ne, _), (ref, _) in zip(swapped.coarse_levels(2, "products"), fresh.coarse_levels(2, "products")):
        torch.testing.assert_close(ne.q, ref.q, rtol=1e-12, atol=1e-12)
    with pytest.raises(Exception, match="form must be"):
        op.normal_equations("dense")


def test_fista_reaches_the_same_patterns_on_either_form():
    from torchproj.solve import solve_fista
    from torchproj.transport import operator

    one = build_transport(synthetic_calibration(shape=(40, 50), sizes=LARGE), targets(channels=1), scale=0.8,
                          footprint="area")
    results = {}
    for form in ("matrix", "products"):
        one.forget_normal_equations()
        previous, operator.normal_form = operator.normal_form, (lambda op, f=form: f)
        try:
            results[form] = solve_fista(one, (0, 1), max_iter=2000, tol=1e-10)
        finally:
            operator.normal_form = previous
    assert results["products"].objective == pytest.approx(results["matrix"].objective, rel=1e-4)
    assert float((results["products"].patterns - results["matrix"].patterns).abs().max()) < 0.02


def test_the_solvers_iterate_on_products_where_rows_are_few_and_wide():
    """normal_form: Q where rows hold one or two cells (merged nearest rows) or repeat them (more rows
    than cells), products where camera pixels are fewer than the cells and rows are wide (a coarse
    camera's area rows)."""
    from torchproj.transport import TransportOperator, csr_from_coo, normal_form

    cals = synthetic_calibration(shape=(40, 50), sizes=LARGE)
    assert normal_form(build_transport(cals, targets(channels=1), footprint="nearest")) == "matrix"

    def banded(rows: int, cells: int, width: int) -> TransportOperator:
        """Row r lights ``width`` consecutive cells from ``r * cells // rows``: a pixel seeing a patch."""
        r = torch.arange(rows).repeat_interleave(width)
        c = (r * cells // rows + torch.arange(width).repeat(rows)).clamp(max=cells - 1)
        matrix = csr_from_coo(r, c, torch.ones(len(r)), (rows, cells))
        return TransportOperator(matrix, torch.ones(rows, 1), torch.zeros(cells, dtype=torch.int64),
                                 torch.arange(cells), [(cells, 1)])

    assert normal_form(banded(100, 400, 8)) == "products"  # few, wide rows
    assert normal_form(banded(100, 400, 2)) == "matrix"  # narrow rows keep Q sparse
    assert normal_form(banded(800, 400, 8)) == "matrix"  # every cell in several rows


def _moved_reference(op, moves, images):
    """``A' L`` by sampling: each entry's weight times the light at its cell plus the row's move, read
    bilinearly from the projector image with the edge value beyond the edge (torch's grid_sample)."""
    import torch.nn.functional as F

    dense = op.dense().double()
    out = torch.zeros(op.shape[0], dtype=torch.float64)
    for c in range(op.shape[1]):
        j = int(op.column_projector[c])
        w, h = op.projector_sizes[j]
        cell = int(op.column_cell[c])
        at = torch.tensor([cell % w, cell // w], dtype=torch.float64) + moves[:, j]
        grid = torch.stack([2 * at[:, 0] / (w - 1) - 1, 2 * at[:, 1] / (h - 1) - 1], -1).view(1, 1, -1, 2)
        seen = F.grid_sample(images[j][None].double(), grid, mode="bilinear", padding_mode="border",
                             align_corners=True).view(-1)
        out += dense[:, c] * seen
    return out


@pytest.mark.parametrize("kind", ["none", "whole", "fraction", "edge"])
def test_rows_moved_carry_their_light_where_the_move_says(op, kind):
    g = torch.Generator().manual_seed(3)
    n_proj = len(op.projector_sizes)
    moves = {"none": torch.zeros(op.shape[0], n_proj, 2),
             "whole": torch.tensor([1.0, -2.0]).expand(op.shape[0], n_proj, 2).clone(),
             "fraction": torch.rand(op.shape[0], n_proj, 2, generator=g) * 1.6 - 0.8,
             "edge": torch.tensor([-30.0, 25.0]).expand(op.shape[0], n_proj, 2).clone()}[kind]
    moved = op.with_rows_moved(moves)
    images = [torch.rand(1, h, w, generator=g, dtype=torch.float64) for w, h in op.projector_sizes]
    cells = torch.stack([images[int(j)][0].flatten()[int(c)] for j, c in zip(moved.column_projector, moved.column_cell)])
    assert torch.allclose(moved.A(cells[:, None])[:, 0], _moved_reference(op, moves.double(), images), atol=1e-9)
    assert moved.shape[0] == op.shape[0] and torch.equal(moved.row_target, op.row_target)
    # No light is lost or made: each row's weights sum to what they were.
    ones = torch.ones(moved.shape[1], 1, dtype=torch.float64)
    assert torch.allclose(moved.A(ones), op.A(ones.new_ones(op.shape[1], 1)), atol=1e-9)
    if kind == "none":
        assert torch.allclose(moved.dense(), op.dense())


def test_an_operator_with_its_normal_equations_cached_can_be_deep_copied(op):
    import copy

    op.normal_equations("matrix")
    twin = copy.deepcopy(op)
    assert twin.val.data_ptr() != op.val.data_ptr()
    p = torch.rand(op.shape[1], op.channels, dtype=op.val.dtype)
    torch.testing.assert_close(twin.A(p), op.A(p))
    torch.testing.assert_close(twin.normal_equations("matrix").q, op.normal_equations("matrix").q)


def test_a_transpose_given_is_the_one_computed_and_a_wrong_one_is_refused(op):
    """A cache keeps ``A^T``'s CSR arrays beside ``A``'s: an operator given them has what one that sorts
    its own nonzeros computes (its adjoint the dense ``A^T x``); arrays of another shape are refused."""
    given = TransportOperator(op._csr(), op.rhs, op.column_projector, op.column_cell, op.projector_sizes,
                              transpose=(op.t_crow.clone(), op.t_col.clone(), op.t_val.clone()))
    computed = TransportOperator(op._csr(), op.rhs, op.column_projector, op.column_cell, op.projector_sizes)
    for name in ("t_crow", "t_col", "t_val"):
        assert torch.equal(getattr(given, name), getattr(computed, name)), name
    y = torch.rand(op.shape[0], 2, dtype=torch.float64)
    dense = op._csr().to_dense().double()
    assert torch.allclose(given.A_adjoint(y), dense.T @ y)
    with pytest.raises(InputError, match="transpose"):
        TransportOperator(op._csr(), op.rhs, op.column_projector, op.column_cell, op.projector_sizes,
                          transpose=(op.t_crow[:-1], op.t_col, op.t_val))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.bfloat16])
def test_the_transpose_is_torchs_conversion_to_the_bit(op, dtype):
    """scipy's transpose on the CPU gives the arrays torch's CSC conversion gives (each column's rows
    in order), on the operator's matrix and on one with empty rows and columns; a dtype numpy lacks
    goes through torch."""
    from torchproj.transport.operator import _transpose

    sparse = torch.zeros(7, 9, dtype=dtype)
    sparse[0, 3], sparse[0, 8], sparse[4, 3], sparse[6, 0], sparse[6, 8] = 1.5, -2.0, 0.25, 3.0, 4.0
    for matrix in (op._csr().to(dtype), sparse.to_sparse_csr()):
        mine, theirs = _transpose(matrix), matrix.to_sparse_csc()
        assert torch.equal(mine.crow_indices().long(), theirs.ccol_indices().long())
        assert torch.equal(mine.col_indices().long(), theirs.row_indices().long())
        assert torch.equal(mine.values(), theirs.values())
        assert torch.equal(mine.to_dense(), matrix.to_dense().T)


@pytest.mark.parametrize("index_dtype", [torch.int32, torch.int64])
@pytest.mark.parametrize("given_rows", [False, True])
def test_the_jacobi_scaling_is_dense_algebra_with_either_index_type(op, index_dtype, given_rows):
    """``S Q S`` with ``S = diag(Q)^-1/2`` against float64 dense algebra, on Q's indices as scipy's product
    gives them (int32) and as torch's own (int64), with each entry's row given (EO's call) or not."""
    from torchproj.core.sparse import csr_tensor
    from torchproj.transport.operator import NormalEquations, entry_rows

    Q = op.normal_equations("matrix").Q
    Q = csr_tensor(Q.crow_indices().to(index_dtype), Q.col_indices().to(index_dtype), Q.values(), Q.shape)
    ne = NormalEquations(Q, torch.ones(Q.shape[0], 1, dtype=torch.float64), torch.zeros(1, dtype=torch.float64))
    scaled = ne.jacobi(entry_rows(Q) if given_rows else None)
    dense = Q.to_dense()
    s = dense.diagonal().rsqrt()
    torch.testing.assert_close(scaled.Q.to_dense(), s[:, None] * dense * s[None, :], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(scaled.scale[:, 0], s, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(scaled.Q.to_dense().diagonal(), torch.ones_like(s), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("parts", [1, 2, 3, 500])
@pytest.mark.parametrize("transpose_given", [False, True])
def test_the_gram_matrix_is_dense_algebra_whatever_the_number_of_blocks(op, op_gram, parts, transpose_given):
    """``A^T A`` built in row blocks against float64 dense algebra: sorted columns in every row, and the
    same to the bit as scipy's one whole product (each entry summed over the same rows in the same
    order), with the operator's transpose or one made here; more blocks than rows leave some empty."""
    from scipy.sparse import csr_matrix

    from torchproj.transport.operator import gram_matrix

    Q = gram_matrix(op._csr(), op._csr(transpose=True) if transpose_given else None, parts=parts)
    torch.testing.assert_close(Q.to_dense(), op_gram, rtol=1e-12, atol=1e-12)
    crow, col = Q.crow_indices().long(), Q.col_indices().long()
    rows = torch.repeat_interleave(torch.arange(Q.shape[0]), crow.diff())
    assert bool((col[1:] > col[:-1])[rows[1:] == rows[:-1]].all())
    a = csr_matrix((op.val.numpy(), op.col.numpy(), op.crow.numpy()), shape=op.shape)
    whole = (a.T @ a).tocsr()
    whole.sort_indices()
    assert torch.equal(crow, torch.from_numpy(whole.indptr).long()) and torch.equal(col, torch.from_numpy(whole.indices).long())
    assert torch.equal(Q.values(), torch.from_numpy(whole.data))


def test_the_gram_matrix_of_a_float32_operator_is_summed_in_float64(op):
    """A float32 ``A`` gets the float64 sums rounded once, not float32 sums."""
    from torchproj.transport.operator import gram_matrix

    single = op.float()
    Q = gram_matrix(single._csr(), parts=2)
    wide = gram_matrix(csr_tensor(single.crow, single.col, single.val.double(), single.shape), parts=2)
    assert Q.dtype == torch.float32
    assert torch.equal(Q.values(), wide.values().float())


def test_each_coarse_level_is_scipys_triple_product_to_the_bit(op):
    """``(P^T (Q P))^T`` in CSR is what ``(P^T @ Q @ P).tocsr()`` gives, entry for entry, on every level
    of a symmetric ``Q`` (the CSC copy of ``Q`` that product makes is left out)."""
    from scipy.sparse import csr_matrix

    ne = op.normal_equations("matrix")
    for level_ne, block in op.coarse_levels(3):
        q = csr_matrix((ne.Q.values().numpy(), ne.Q.col_indices().numpy(), ne.Q.crow_indices().numpy()), shape=ne.Q.shape)
        tie = csr_matrix((np.ones(len(block)), (np.arange(len(block)), block.numpy())), shape=(len(block), int(block.max()) + 1))
        expected = (tie.T @ q @ tie).tocsr()
        expected.sort_indices()
        assert torch.equal(level_ne.Q.crow_indices().long(), torch.from_numpy(expected.indptr).long())
        assert torch.equal(level_ne.Q.col_indices().long(), torch.from_numpy(expected.indices).long())
        assert torch.equal(level_ne.Q.values(), torch.from_numpy(expected.data).to(level_ne.Q.dtype))
        ne = level_ne


def _gram_system(A: torch.Tensor):
    """The normal equations of a dense float64 ``A`` (no targets), with the dense ``Q`` to check them."""
    from torchproj.transport.operator import NormalEquations

    Q = A.T @ A
    n = Q.shape[0]
    return NormalEquations(Q.to_sparse_csr(), torch.zeros(n, 1, dtype=torch.float64),
                           torch.zeros(1, dtype=torch.float64)), Q


def test_the_step_bound_is_a_bound_where_a_column_is_unseen():
    """A projector cell no row sees is a zero column of ``A`` and a zero row of ``Q``. The top
    eigenvector here sits on one column, which 30 power products from a flat start barely find:
    the estimate with a 5% margin stays below it (no bound: FISTA's step too long), while the
    Collatz-Wielandt ratio over the seen columns bounds it from the first product on, and a zero
    operator is bounded by 0."""
    n = 1500
    d = torch.ones(n, dtype=torch.float64)
    d[7] = 1.1 ** 0.5  # the largest eigenvalue, 1.1, on column 7 alone
    d[[3, 50]] = 0.0  # two cells no row sees
    A = torch.diag(d)
    A[10, 11] = 0.05  # a little coupling: Q is not diagonal
    Q = A.T @ A
    top = float(torch.linalg.eigvalsh(Q)[-1])
    for iterations in (0, 5, 30):
        ne, _ = _gram_system(A)
        x = torch.ones(n, 1, dtype=torch.float64)
        for _ in range(iterations):
            x = Q @ x
            x /= x.norm()
        assert 1.05 * float((Q @ x).norm() / x.norm()) < top  # the margin rule's estimate
        bound = ne.lipschitz(iterations)
        assert top * (1 - 1e-12) <= bound <= top * 1.01
    zero, _ = _gram_system(torch.zeros(5, 6, dtype=torch.float64))
    assert zero.lipschitz() == 0.0


def test_the_step_bound_tightens_with_products_on_a_rig():
    """On a rig's Jacobi-scaled Q (every weight non-negative) the bound is above the top eigenvalue
    (dense float64) after any number of products, and within 1% of it after 30."""
    torch.manual_seed(0)
    built = build_transport(synthetic_calibration(shape=(40, 50), sizes=LARGE), targets(channels=1), scale=0.8).double()
    dense = built.dense()
    dense[:, :3] = 0  # cells no row sees
    Q = dense.T @ dense
    s = Q.diagonal().clamp_min(1e-30).rsqrt()
    top = float(torch.linalg.eigvalsh(s[:, None] * Q * s[None, :])[-1])
    for iterations in (1, 5, 30):
        ne, _ = _gram_system(dense)
        bound = ne.jacobi().lipschitz(iterations)
        assert bound >= top * (1 - 1e-12)
    assert bound <= top * 1.01


def test_smoothness_rows_add_the_neighbour_differences_of_every_projector_image():
    """||A' p||^2 - ||A p||^2 is lam times the squared differences of neighbouring lit cells, read off
    each projector's image (cells that are no variable do not count); lam is the weight times the
    target scale squared, whatever A's columns hold."""
    op = build_transport(synthetic_calibration(shape=(40, 50), sizes=LARGE), targets(channels=3), scale=0.8).double()
    weight = 0.01
    smooth = op.with_smoothness(weight)
    g = torch.Generator().manual_seed(11)
    p = torch.rand(op.shape[1], 2, generator=g, dtype=torch.float64)
    lam = weight * 0.8 ** 2
    penalty = torch.zeros(2, dtype=torch.float64)
    for img in op.to_images(p, fill=float("nan")):
        for d in (img[:, :, 1:] - img[:, :, :-1], img[:, 1:, :] - img[:, :-1, :]):
            penalty += torch.nan_to_num(d, nan=0.0).pow(2).sum((1, 2))
    gained = smooth.A(p).pow(2).sum(0) - op.A(p).pow(2).sum(0)
    torch.testing.assert_close(gained, lam * penalty, rtol=1e-10, atol=1e-10)
    assert torch.equal(smooth.dense()[: op.shape[0]], op.dense())
    # A^T of the stack, placed by counting, is the one a transpose of the whole stack gives, to the bit.
    whole = _transpose(smooth._csr())
    for mine, theirs in zip((smooth.t_crow, smooth.t_col, smooth.t_val),
                            (whole.crow_indices(), whole.col_indices(), whole.values())):
        assert torch.equal(mine.long() if mine.dtype != torch.float64 else mine,
                           theirs.long() if theirs.dtype != torch.float64 else theirs)
    assert torch.equal(smooth.rhs[op.shape[0]:], torch.zeros(smooth.shape[0] - op.shape[0], op.rhs.shape[1],
                                                             dtype=op.rhs.dtype))
    assert op.with_smoothness(0) is op and smooth.row_pixel is None
    for bad in (-1.0, float("nan"), "0.1", True):
        with pytest.raises(InputError, match="smoothness weight"):
            op.with_smoothness(bad)
    # A weight whose lam overflows the operator's dtype is refused, naming the weight, not the matrix.
    with pytest.raises(InputError, match=r"smoothness weight 1e\+308 is too large for this torch.float32"):
        op.float().with_smoothness(1e308)


def test_a_smoothed_solve_is_scipys_penalised_box_least_squares():
    """FISTA on the smoothed operator reaches the minimiser of ||A p - i||^2 + lam ||D p||^2 in the
    box, as scipy's lsq_linear finds it on the dense stacked system in float64."""
    from scipy.optimize import lsq_linear

    from torchproj.solve import solve_patterns

    small = build_transport(synthetic_calibration(shape=(16, 20), sizes=[(12, 10), (10, 8)]), targets(channels=1),
                            scale=0.8).double()
    smooth = small.with_smoothness(0.05)
    found = solve_patterns(smooth, "fista", (0.0, 1.0), max_iter=5000, tol=1e-13).patterns[:, 0]
    stacked = smooth.dense().numpy()
    want = lsq_linear(stacked, smooth.rhs[:, 0].numpy(), bounds=(0.0, 1.0), tol=1e-13, method="bvls").x
    np.testing.assert_allclose(found.numpy(), want, atol=2e-4)
    plain = lsq_linear(small.dense().numpy(), small.rhs[:, 0].numpy(), bounds=(0.0, 1.0), method="bvls").x
    assert np.abs(plain - want).max() > 1e-2  # the penalty moved the answer


def test_a_smoothed_operator_takes_its_q_from_the_one_it_was_made_from_and_iterates_in_its_form():
    """Where A^T A and its coarse levels are built already (or read from a cache), the smoothed
    operator's are they plus lam D^T D, tied alike: the stacked matrix's own; its normal form is its
    origin's."""
    from torchproj.transport.operator import normal_form

    op = two_projectors(1).double()
    op.coarse_levels(3, "matrix")
    smooth = op.with_smoothness(0.02)
    stacked = smooth.dense()
    assert smooth.normal_matrix() is not None
    torch.testing.assert_close(smooth.normal_matrix().to_dense(), stacked.T @ stacked, rtol=1e-12, atol=1e-12)
    # Each coarse level is the stacked matrix's own P^T Q P: its tied columns' Gram matrix.
    assert len(smooth.coarse_matrices()) == len(op.coarse_matrices()) > 0
    tied = stacked
    for block, Qc in zip(smooth._level_blocks(3), smooth.coarse_matrices()):
        tied = tied @ torch.nn.functional.one_hot(block, int(block.max()) + 1).double()
        torch.testing.assert_close(Qc.to_dense(), tied.T @ tied, rtol=1e-12, atol=1e-12)
    assert op.with_smoothness(0.02) is smooth  # kept, with what was computed on it
    op.form = "products"
    assert normal_form(op.with_smoothness(0.03)) == "products"
    assert op.with_smoothness(0.03).normal_matrix() is not None  # the Q at hand is still taken
    assert op.with_rhs(op.rhs * 2).with_smoothness(0.03) is not op.with_smoothness(0.03)  # other targets
    kept = op.with_smoothness(0.03)
    op.float()  # converted in place: the kept operator holds float64 and is made again
    assert op.with_smoothness(0.03) is not kept and op.with_smoothness(0.03).val.dtype == torch.float32


def test_a_smoothed_operators_own_q_is_the_stacks_gram_matrix_made_without_the_stacks_transpose():
    """With no Q at hand (a cold run), the smoothed operator builds A^T A + lam D^T D from A's rows and
    A^T: the dense stack's own S^T S (float64), and in float32 within its rounding; the stack's
    transpose is never made. After a conversion it is built in the new dtype."""
    op = two_projectors(1)
    wide = op.double().with_smoothness(0.02)
    Q = wide.normal_equations("matrix").Q
    assert wide._buffers["t_val"] is None
    stacked = wide.dense()
    torch.testing.assert_close(Q.to_dense(), stacked.T @ stacked, rtol=1e-12, atol=1e-12)
    narrow = two_projectors(1).with_smoothness(0.02)
    Q32 = narrow.normal_equations("matrix").Q
    assert Q32.dtype == torch.float32 and narrow._buffers["t_val"] is None
    torch.testing.assert_close(Q32.to_dense().double(), stacked.T @ stacked, rtol=1e-6, atol=1e-6 * float(Q.values().abs().max()))
    converted = two_projectors(1).with_smoothness(0.02).double()
    assert converted.normal_equations("matrix").Q.dtype == torch.float64
    torch.testing.assert_close(converted.normal_equations("matrix").Q.to_dense(), stacked.T @ stacked,
                               rtol=1e-6, atol=1e-6 * float(Q.values().abs().max()))


def test_the_products_form_applies_the_penalty_beside_a_and_ties_and_scales_it_as_q():
    """On products, Q p is A^T (A p) + lam D^T D p: the dense stack's S^T S p (float64), on every
    coarse level P^T S^T S P and Jacobi-scaled alike, with the stack's transpose never made; FISTA on
    it reaches the matrix form's patterns."""
    from torchproj.solve import solve_fista

    op = two_projectors(3).double()
    smooth = op.with_smoothness(0.02)
    ne = smooth.normal_equations("products")
    assert ne.penalty is not None and smooth._buffers["t_val"] is None
    stacked = smooth.dense()
    tied, level = stacked, ne
    for block in [None, *smooth._level_blocks(3)]:
        if block is not None:
            tied = tied @ torch.nn.functional.one_hot(block, int(block.max()) + 1).double()
            level = level.coarsened(block)
        Q = tied.T @ tied
        eye = torch.eye(Q.shape[0], dtype=torch.float64)
        torch.testing.assert_close(level.product(eye), Q, rtol=1e-12, atol=1e-12)
        s = Q.diagonal().clamp_min(1e-30).rsqrt()
        torch.testing.assert_close(level.jacobi().product(eye), s[:, None] * Q * s[None, :], rtol=1e-12, atol=1e-12)
        assert not level._nonnegative()
        assert level.jacobi().lipschitz() >= float(torch.linalg.eigvalsh(s[:, None] * Q * s[None, :])[-1]) * (1 - 1e-12)
    assert len(smooth._level_blocks(3)) > 0
    on_products = solve_fista(smooth, (0.0, 1.0), max_iter=3000, tol=1e-12, form="products")
    on_matrix = solve_fista(op.with_smoothness(0.02), (0.0, 1.0), max_iter=3000, tol=1e-12, form="matrix")
    torch.testing.assert_close(on_products.patterns, on_matrix.patterns, rtol=1e-5, atol=1e-5)


def test_a_smoothed_operator_solved_from_a_kept_q_never_makes_its_transpose():
    """With Q and its coarse levels at hand (a cache's), a FISTA solve on the smoothed operator reads no
    A^T of the stack: its q is the plain operator's A^T i, as the penalty's targets are 0. Made later
    (read, moved to another dtype, saved), the transpose is the whole stack's, in the operator's dtype."""
    from torchproj.solve import solve_fista

    op = two_projectors(3)
    op.coarse_levels(3, "matrix")
    smooth = op.with_smoothness(0.02)
    reference = two_projectors(3).with_smoothness(0.02)  # Q built anew
    result = solve_fista(smooth, (0.0, 1.0), max_iter=60, tol=0.0)
    assert smooth._buffers["t_val"] is None  # never made
    torch.testing.assert_close(smooth.normal_equations().q, reference.A_adjoint(reference.rhs), rtol=1e-6, atol=1e-6)
    expected = solve_fista(reference, (0.0, 1.0), max_iter=60, tol=0.0)
    torch.testing.assert_close(result.patterns, expected.patterns, rtol=1e-4, atol=1e-4)
    # Made on demand after a conversion, in the new dtype, as a transpose of the whole stack gives it.
    wide = op.with_smoothness(0.03).double()
    assert wide._buffers["t_val"] is None
    whole = _transpose(wide._csr())
    assert wide.t_val.dtype == torch.float64 and torch.equal(wide.t_val, whole.values())
    assert torch.equal(wide.t_col.long(), whole.col_indices().long())
    # Another rhs: A^T i is the product again, not the kept one.
    other = smooth.with_rhs(smooth.rhs * 2)
    torch.testing.assert_close(other.targets_adjoint(), 2 * smooth.targets_adjoint(), rtol=1e-6, atol=1e-6)
    assert {"t_crow", "t_col", "t_val"} <= set(op.with_smoothness(0.04).state_dict())
    # An operator keeping a stack whose transpose is not made yet pickles (torch.save of a model), and
    # the loaded stack makes the same transpose.
    pending = op.with_smoothness(0.05)
    saved = io.BytesIO()
    torch.save(op, saved)
    loaded = torch.load(io.BytesIO(saved.getvalue()), weights_only=False)._smoothed[1]  # the kept stack
    assert loaded._buffers["t_val"] is None and torch.equal(loaded.t_val, pending.t_val)


@pytest.mark.parametrize("form", ["matrix", "products"])
def test_the_step_bound_holds_where_a_smoothness_penalty_puts_negative_entries_in_q(form):
    """The penalty's -lam between neighbours makes Q's entries mixed in sign; the Collatz-Wielandt
    bound, taken on |Q|, still bounds Q's largest eigenvalue (float64 dense eigvalsh), and closely."""
    op = two_projectors(1).double().with_smoothness(2.5)
    for ne in (op.normal_equations(form), op.normal_equations(form).jacobi()):
        dense = ne.product(torch.eye(op.shape[1], dtype=torch.float64))
        top = float(torch.linalg.eigvalsh((dense + dense.T) / 2)[-1])
        assert not ne._nonnegative()
        assert top <= ne.lipschitz() <= 1.1 * top


@pytest.mark.parametrize("product, name", [("A", "p"), ("A_adjoint", "r"), ("objective", "p"), ("gradient", "p")])
def test_a_product_of_something_that_is_no_tensor_is_named(op, product, name):
    """A number, a list or None ended in an AttributeError on .dim()."""
    for bad, kind in [(0.5, "float"), ([0.5], "list"), (None, "NoneType")]:
        with pytest.raises(InputError, match=f"{name} must be a torch.Tensor, got {kind}"):
            getattr(op, product)(bad)
