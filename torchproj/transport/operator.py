"""The light-transport operator ``i = A p`` as a ``torch.nn.Module``.

Rows are (merged) target pixels, columns the projector cells that light at least one row; the
variables ``p`` are the projectors' linear relative light in each of those cells (0 = the
projector's black, 1 = its white; see :mod:`torchproj.calib.response`). RGB targets are C
right-hand sides of the same A, so ``p`` is :math:`(N_{cols}, C)` and ``A p`` is :math:`(N_{rows}, C)`.

The matrix and its transpose are held as CSR buffers, so ``.to(device)`` moves them and the
adjoint is a product as fast as the forward one. Autograd flows through :meth:`A` (its backward is
:meth:`A_adjoint`) so the operator can sit inside a user's training-style loop.
"""

from __future__ import annotations

import copy
import functools
import math

import numpy as np
import torch
from torch import nn

from ..calib.maps import check_projector_size
from ..core.checks import check, check_finite, check_indices, check_shape, is_number
from ..core.sparse import csr_from_coo, csr_tensor, index_dtype, spmm

__all__ = ["TransportOperator", "normal_form", "gram_matrix", "NormalEquations", "ProductNormalEquations", "csr_from_coo", "cell_blocks"]

# Below this many columns a coarser level saves nothing worth its setup.
_MIN_COARSE_COLUMNS = 64
_TRANSPOSE = ("t_crow", "t_col", "t_val")  # the buffers of A^T's CSR arrays


def cell_blocks(column_projector: torch.Tensor, column_cell: torch.Tensor, projector_sizes: list[tuple[int, int]]):
    """Group columns by 2x2 blocks of projector cells: the same projectors at half the resolution.

    Args:
        column_projector: :math:`(N_{cols},)` projector index of each column.
        column_cell: :math:`(N_{cols},)` flat cell index ``y * W_j + x`` (see :class:`TransportOperator`).
        projector_sizes: ``(width, height)`` of each projector.

    Returns:
        ``(block, block_projector, block_cell, block_sizes)``: :math:`(N_{cols},)` the block of
        each column (blocks numbered by projector, then cell), and for each block its projector,
        its flat cell index on the half-resolution grid and those grids' ``(width, height)``
        (odd sizes round up).
    """
    sizes = check_indices(column_projector, "column_projector", ["N"])
    check_indices(column_cell, "column_cell", [sizes["N"]])
    check(isinstance(projector_sizes, (list, tuple)), f"projector_sizes must be a list of (width, height), got "
                                                      f"{type(projector_sizes).__name__}")
    projector_sizes = [check_projector_size(size, f"projector_sizes[{j}]") for j, size in enumerate(projector_sizes)]
    if sizes["N"]:
        low, high = (int(v) for v in torch.aminmax(column_projector))
        check(low >= 0 and high < len(projector_sizes), f"column_projector must index the {len(projector_sizes)} "
                                                        f"projector_sizes, got {low} to {high}")
    widths = torch.tensor([w for w, _ in projector_sizes], device=column_cell.device)[column_projector]
    block_sizes = [((w + 1) // 2, (h + 1) // 2) for w, h in projector_sizes]
    block_widths = torch.tensor([w for w, _ in block_sizes], device=column_cell.device)[column_projector]
    cell = (column_cell // widths // 2) * block_widths + (column_cell % widths) // 2
    cells_per_projector = max(w * h for w, h in block_sizes)
    blocks, block = torch.unique(column_projector.long() * cells_per_projector + cell, return_inverse=True)
    return block, blocks // cells_per_projector, blocks % cells_per_projector, block_sizes


class _Matrices:
    """``M`` and ``M^T`` as one argument that is not a tensor: torch.func's transforms wrap every tensor
    argument of a function they pass through, and a sparse CSR tensor cannot be wrapped (it has no
    strides). The matrices are constants of the operator; only ``x`` is differentiated or batched."""

    __slots__ = ("forward", "adjoint")

    def __init__(self, forward: torch.Tensor, adjoint: torch.Tensor):
        self.forward, self.adjoint = forward, adjoint

    def transposed(self) -> "_Matrices":
        return _Matrices(self.adjoint, self.forward)


class _Apply(torch.autograd.Function):
    """``M x`` with backward ``M^T g``, itself a product of this function, so that derivatives of
    any order flow (a Hessian-vector product of an image-space loss is a double backward), and with
    the forward-mode and batching rules torch.func asks for (``jvp``: ``M x_t``, linear; ``vmap``: a
    batch of ``x`` is one product with the batch folded into the columns)."""

    @staticmethod
    def forward(x, matrices):
        return spmm(matrices.forward, x)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.matrices = inputs[1]

    @staticmethod
    def backward(ctx, grad):
        return _Apply.apply(grad, ctx.matrices.transposed()), None

    @staticmethod
    def jvp(ctx, x_tangent, _):
        return _Apply.apply(x_tangent, ctx.matrices)

    @staticmethod
    def vmap(info, in_dims, x, matrices):
        if in_dims[0] is None:
            return _Apply.apply(x, matrices), None
        x = x.movedim(in_dims[0], -1)  # (N, C, B): the batch beside the channels, one product for all
        n, c, b = x.shape
        return _Apply.apply(x.reshape(n, c * b), matrices).reshape(-1, c, b), 2


@torch.library.custom_op("torchproj::transport_product", mutates_args=())
def _compiled_product(crow: torch.Tensor, col: torch.Tensor, val: torch.Tensor, t_crow: torch.Tensor,
                      t_col: torch.Tensor, t_val: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``M x`` for ``torch.compile``: the matrix (and its transpose, for the backward) as the dense
    arrays of its CSR form, which a compiled graph can carry (a sparse tensor it cannot). Opaque to
    the compiler, which calls torch's sparse kernel here as eager does."""
    return spmm(csr_tensor(crow, col, val, (crow.numel() - 1, x.shape[0])), x)


@_compiled_product.register_fake
def _(crow, col, val, t_crow, t_col, t_val, x):
    return x.new_empty(crow.numel() - 1, x.shape[1])


def _compiled_setup(ctx, inputs, output):
    ctx.arrays = inputs[:6]


def _compiled_backward(ctx, grad):
    crow, col, val, t_crow, t_col, t_val = ctx.arrays
    return None, None, None, None, None, None, _compiled_product(t_crow, t_col, t_val, crow, col, val, grad)


_compiled_product.register_autograd(_compiled_backward, setup_context=_compiled_setup)


class TransportOperator(nn.Module):
    """Sparse ``A`` (rows x columns) with the bookkeeping that maps columns back to projector cells.

    Args:
        matrix: CSR :math:`(N_{rows}, N_{cols})`.
        rhs: :math:`(N_{rows}, C)` target values ``i`` (already in camera units).
        column_projector: :math:`(N_{cols},)` projector index of each column.
        column_cell: :math:`(N_{cols},)` flat cell index ``y * W_j + x`` of each column.
        projector_sizes: ``(width, height)`` of each projector.
        constant: :math:`(C,)` part of the objective that merging rows took out of ``A`` and ``rhs``
            (0 without merging), so that :meth:`objective` equals the unmerged ``||A p - i||^2``.
        row_target: :math:`(N_{rows},)` index of the target each row belongs to (for reports).
        scale: camera value that a target value of 1 asks for (``rhs = scale * target``).
        row_pixel: :math:`(N_{rows},)` flat camera pixel ``y * W + x`` of each row, for operators
            whose rows are camera pixels (built with ``merge=False``); None for merged rows, which
            mix pixels. It is what :meth:`to_camera` places rows by.
        camera_size: ``(width, height)`` of the camera, with ``row_pixel``.
        target_count: number of targets (default: the largest ``row_target`` plus one).
        transpose: ``(crow, col, val)`` of ``A^T`` in CSR, as an operator's ``t_crow``, ``t_col``,
            ``t_val`` hold them (a cache keeps them: computing them is a sort of every nonzero);
            default: computed from ``matrix``. Only their shapes are checked.

    Convention: pixel and cell indices follow :mod:`torchproj.core.conventions` (``(x, y)`` order,
    flat index ``y * W + x``).

    ``state_dict`` holds the buffers and, as extra state, the shape, scale, projector sizes, camera
    size and target count; loading it into an operator of another rig is refused.
    """

    def __init__(self, matrix: torch.Tensor, rhs: torch.Tensor, column_projector: torch.Tensor,
                 column_cell: torch.Tensor, projector_sizes: list[tuple[int, int]], constant: torch.Tensor | None = None,
                 row_target: torch.Tensor | None = None, scale: float = 1.0, row_pixel: torch.Tensor | None = None,
                 camera_size: tuple[int, int] | None = None, target_count: int | None = None,
                 transpose: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None):
        super().__init__()
        check(matrix.layout == torch.sparse_csr, "matrix must be a CSR tensor (torch.sparse_csr)")
        matrix = csr_tensor(matrix.crow_indices(), matrix.col_indices(), matrix.values(), matrix.shape)
        n_rows, n_cols = matrix.shape
        check_shape(rhs, "rhs", [n_rows, "C"])
        check_finite(rhs, "rhs")
        check_finite(matrix.values(), "matrix values")
        check_shape(column_projector, "column_projector", [n_cols])
        check_shape(column_cell, "column_cell", [n_cols])
        counts = matrix.crow_indices().diff()
        check(bool((counts > 0).all()), f"{int((counts == 0).sum())} rows of A are empty: every target pixel must be "
                                        "lit by at least one projector (drop unlit pixels from the target)")
        # The CSR arrays as dense tensors of their own, not views into a sparse tensor: a compiled graph
        # (torch.compile) can carry the one and not the other.
        for name, array in zip(("crow", "col", "val"), (matrix.crow_indices(), matrix.col_indices(), matrix.values())):
            self.register_buffer(name, array.clone())
        self.shape = (n_rows, n_cols)
        # A function that makes the transpose is called when the transpose is first read (_make_transpose):
        # an operator solved from a Q read from a cache never reads it.
        pending = transpose if callable(transpose) else None
        if transpose is None:
            transposed = _transpose(matrix)  # A^T in CSR, for an adjoint as fast as the forward product
            transpose = (transposed.crow_indices().clone(), transposed.col_indices().clone(), transposed.values().clone())
        elif callable(transpose):
            transpose = (None, None, None)
        else:
            self._check_transpose(transpose)
        for name, array in zip(_TRANSPOSE, transpose):
            self.register_buffer(name, array)
        self._pending_transpose = pending
        self.register_buffer("rhs", rhs)
        self.register_buffer("column_projector", column_projector)
        self.register_buffer("column_cell", column_cell)
        self.register_buffer("constant", torch.zeros(rhs.shape[1], dtype=rhs.dtype, device=rhs.device)
                             if constant is None else constant)
        self.register_buffer("row_target", torch.zeros(n_rows, dtype=torch.int64, device=rhs.device)
                             if row_target is None else row_target)
        check((row_pixel is None) == (camera_size is None), "row_pixel and camera_size come together")
        if row_pixel is not None:
            check_shape(row_pixel, "row_pixel", [n_rows])
            check(bool((row_pixel >= 0).all()) and bool((row_pixel < camera_size[0] * camera_size[1]).all()),
                  f"row_pixel must index pixels of the {camera_size[0]}x{camera_size[1]} camera")
        self.register_buffer("row_pixel", row_pixel)
        self.camera_size = None if camera_size is None else tuple(int(v) for v in camera_size)
        self.target_count = int(self.row_target.max()) + 1 if target_count is None and n_rows else int(target_count or 0)
        self.projector_sizes = [tuple(s) for s in projector_sizes]
        self.form = None  # the normal equations' form its solvers use (normal_form); None: by its shape
        self.scale = float(scale)

    def _check_transpose(self, transpose) -> None:
        t_crow, t_col, t_val = transpose
        n_rows, n_cols = self.shape
        check(t_crow.shape == (n_cols + 1,) and t_col.shape == t_val.shape == self.val.shape
              and t_val.dtype == self.val.dtype and int(t_crow[-1]) == self.val.numel(),
              f"transpose must be the CSR arrays of a {n_cols} x {n_rows} matrix with {self.val.numel()} "
              "nonzeros (the transpose this operator's own matrix gives)")

    def __getattr__(self, name: str):
        if name in _TRANSPOSE and self.__dict__.get("_pending_transpose") is not None:
            self._make_transpose()
        return super().__getattr__(name)

    def _make_transpose(self) -> None:
        """The transpose from the function given for it, on this operator's device and in its dtype."""
        make, self._pending_transpose = self._pending_transpose, None
        device, dtype = self._buffers["val"].device, self._buffers["val"].dtype
        t_crow, t_col, t_val = make()
        transpose = (t_crow.to(device), t_col.to(device), t_val.to(device, dtype))
        self._check_transpose(transpose)
        self._buffers.update(zip(_TRANSPOSE, transpose))

    def _save_to_state_dict(self, destination, prefix, keep_vars):
        if self.__dict__.get("_pending_transpose") is not None:
            self._make_transpose()  # the state holds every array
        super()._save_to_state_dict(destination, prefix, keep_vars)

    # ----------------------------------------------------------------------------- state dict
    def get_extra_state(self) -> dict:
        """What the buffers do not say: shape, scale, projector and camera sizes, target count."""
        return {"shape": list(self.shape), "scale": self.scale, "projector_sizes": [list(s) for s in self.projector_sizes],
                "camera_size": None if self.camera_size is None else list(self.camera_size),
                "target_count": self.target_count}

    def set_extra_state(self, state: dict) -> None:
        self.scale = float(state["scale"])
        self._normal = self._products = None  # caches of the old values
        self._blocks_device = None

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        extra = state_dict.get(prefix + "_extra_state")
        if extra is not None:
            mine = self.get_extra_state()
            for key in ("shape", "projector_sizes", "camera_size", "target_count"):
                check(extra.get(key) == mine[key],
                      f"this state_dict belongs to an operator with {key} {extra.get(key)}, not {mine[key]}: build "
                      "the operator from the same calibration and targets before loading it")
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    # ------------------------------------------------------------------------------- matrices
    def _csr(self, transpose: bool = False) -> torch.Tensor:
        # Built outside torch.func's transforms (grad, jvp, vmap), which cannot construct a sparse tensor
        # ("Sparse CSR tensors do not have strides"): the arrays are the operator's buffers, constants
        # that no transform differentiates or batches.
        with torch._C._DisableFuncTorch():
            if transpose:
                return csr_tensor(self.t_crow, self.t_col, self.t_val, self.shape[::-1])
            return csr_tensor(self.crow, self.col, self.val, self.shape)

    @property
    def channels(self) -> int:
        return self.rhs.shape[1]

    @property
    def nnz(self) -> int:
        return int(self.val.numel())

    def size_report(self) -> dict:
        """Model size: variables (columns), rows and nonzeros."""
        return {"variables": self.shape[1], "rows": self.shape[0], "nnz": self.nnz}

    # -------------------------------------------------------------------------------- products
    def _check_vector(self, x: torch.Tensor, name: str, n: int) -> torch.Tensor:
        if isinstance(x, torch.Tensor) and x.dim() == 1:  # anything else is named by check_shape
            x = x[:, None]
        check_shape(x, name, [n, "C"])
        if torch.compiler.is_compiling():
            return x  # device and dtype are the compiled graph's guards; its tracer cannot compare devices
        check(x.device == self.val.device, f"{name} is on {x.device} but the operator is on {self.val.device}; "
                                            "move one with .to(device)")
        check(x.dtype == self.val.dtype, f"{name} has dtype {x.dtype} but the operator holds {self.val.dtype}")
        return x

    def A(self, p: torch.Tensor) -> torch.Tensor:
        """``A p``: :math:`(N_{cols}, C)` (or :math:`(N_{cols},)`) -> :math:`(N_{rows}, C)`."""
        return self._product(self._check_vector(p, "p", self.shape[1]), adjoint=False)

    def A_adjoint(self, r: torch.Tensor) -> torch.Tensor:
        """``A^T r``: :math:`(N_{rows}, C)` -> :math:`(N_{cols}, C)`."""
        return self._product(self._check_vector(r, "r", self.shape[0]), adjoint=True)

    def _product(self, x: torch.Tensor, adjoint: bool) -> torch.Tensor:
        """``A x`` or ``A^T x``: under ``torch.compile`` the custom op on the CSR arrays, else the
        autograd Function on the sparse matrices (torch.func's path)."""
        arrays = (self.crow, self.col, self.val, self.t_crow, self.t_col, self.t_val)
        if torch.compiler.is_compiling():
            return _compiled_product(*(arrays[3:] + arrays[:3] if adjoint else arrays), x)
        return _Apply.apply(x, _Matrices(self._csr(transpose=adjoint), self._csr(transpose=not adjoint)))

    def forward(self, p: torch.Tensor) -> torch.Tensor:
        return self.A(p)

    def residual(self, p: torch.Tensor) -> torch.Tensor:
        return self.A(p) - self.rhs

    def objective(self, p: torch.Tensor) -> torch.Tensor:
        """``||A p - i||^2`` summed over channels (including the constant merged rows left out)."""
        return self.residual(p).pow(2).sum() + self.constant.sum()

    def unexplained(self, p: torch.Tensor) -> float:
        """Share of the targets' energy the patterns leave unexplained: ``||A p - i||^2 / ||i||^2``.

        0 means every target is reproduced exactly, 1 is no better than projecting nothing. It stays
        high whatever the solver when the targets cannot be told apart (too little baseline or depth
        between them) or ask for opposite light along the same rays.
        """
        energy = float(self.rhs.pow(2).sum() + self.constant.sum())
        return float(self.objective(p)) / energy if energy > 0 else 0.0

    def gradient(self, p: torch.Tensor) -> torch.Tensor:
        """Gradient of :meth:`objective` / 2: ``A^T (A p - i)``."""
        return self.A_adjoint(self.residual(p))

    # ------------------------------------------------------------------------------- analysis
    def adjointness_test(self, generator: torch.Generator | None = None) -> float:
        """Relative gap ``|<A x, y> - <x, A^T y>| / (|A x| |y|)`` for random x, y (~1e-7 in float32)."""
        x = torch.randn(self.shape[1], 1, generator=generator, dtype=self.val.dtype).to(self.val.device)
        y = torch.randn(self.shape[0], 1, generator=generator, dtype=self.val.dtype).to(self.val.device)
        ax = self.A(x)
        lhs = (ax * y).sum()
        rhs = (x * self.A_adjoint(y)).sum()
        return float((lhs - rhs).abs() / (ax.norm() * y.norm()).clamp_min(1e-30))

    def lipschitz(self, iterations: int = 50, generator: torch.Generator | None = None) -> float:
        """Largest eigenvalue of ``A^T A`` (the squared largest singular value) by power iteration.

        Power iteration approaches it from below; the result is multiplied by 1.01 so that a step
        of ``1 / L`` stays safe.
        """
        x = torch.rand(self.shape[1], 1, generator=generator, dtype=self.val.dtype).to(self.val.device)
        x /= x.norm()
        value = 0.0
        for _ in range(iterations):
            y = self.A_adjoint(self.A(x))
            value = float(y.norm())
            if value == 0:
                return 0.0
            x = y / value
        return value * 1.01

    def normal_equations(self, form: str = "matrix") -> "NormalEquations":
        """``Q = A^T A``, ``q = A^T i`` and the constant: the objective as a quadratic in p.

        Args:
            form: ``"matrix"``: ``Q`` built once (scipy's sparse product), one sparse product per
                iteration after that; what EO's chains read. ``"products"``: ``Q p`` taken as
                ``A^T (A p)``, two products per iteration and ``Q`` never built
                (:class:`ProductNormalEquations`). ``"auto"``: :func:`normal_form`, what the
                gradient solvers (FISTA, PGD, LF) use.

        Cached per form.
        """
        check(form in ("matrix", "products", "auto"), f"form must be 'matrix', 'products' or 'auto', got {form!r}")
        form = normal_form(self) if form == "auto" else form
        key = "_normal" if form == "matrix" else "_products"
        cached = getattr(self, key, None)
        if cached is None or cached.q.device != self.val.device or cached.q.dtype != self.val.dtype:
            maker = NormalEquations if form == "matrix" else ProductNormalEquations
            setattr(self, key, maker.from_operator(self))
        return getattr(self, key)

    def __deepcopy__(self, memo):
        # The cached normal equations hold sparse tensors, which deepcopy cannot copy (a model built by
        # ProjectionModel.from_calibration, whose least-squares start cached them, could not be copied);
        # a copy builds its own when asked.
        new = type(self).__new__(type(self))
        memo[id(self)] = new
        for key, value in self.__dict__.items():
            new.__dict__[key] = None if key in ("_normal", "_products", "_smoothed") else copy.deepcopy(value, memo)
        return new

    def normal_matrix(self) -> torch.Tensor | None:
        """``Q = A^T A`` where :meth:`normal_equations` has built it in the matrix form, else None: what a
        cache can keep beside the operator (building it is a sparse product as long as 40 iterations)."""
        return None if getattr(self, "_normal", None) is None else self._normal.Q

    def adopt_normal_matrix(self, Q: torch.Tensor) -> None:
        """Take ``Q = A^T A`` built earlier for this same matrix (from :meth:`normal_matrix`, kept by a
        cache keyed by the matrix) instead of building it; its shape and layout are checked."""
        n = self.shape[1]
        check(Q.layout == torch.sparse_csr and tuple(Q.shape) == (n, n) and Q.dtype == self.val.dtype,
              f"Q must be a CSR matrix of {n} x {n} {self.val.dtype}, got {Q.layout} {tuple(Q.shape)} {Q.dtype}")
        self._normal = NormalEquations.from_operator(self, Q)

    def forget_normal_equations(self) -> None:
        """Drop the cached ``Q`` (:meth:`normal_equations` builds it again when asked): a solve over one
        operator per colour channel then holds one ``Q`` at a time (0.2 GB each on the full-size RGB rig
        with the area footprint). The operator :meth:`with_smoothness` kept goes too (a copy of A's arrays)."""
        self._normal = self._products = self._smoothed = None

    def coarse_levels(self, levels: int, form: str = "matrix") -> list[tuple["NormalEquations", torch.Tensor]]:
        """The normal equations of the same rig with projector cells tied in 2x2, 4x4, ... blocks.

        Tying the cells of a block to one value ``p_c`` is ``p = P p_c`` with ``P`` the 0/1 matrix of
        :func:`cell_blocks`; the tied problem's normal equations are ``P^T Q P`` and ``P^T q`` with the
        same constant, so its objective *is* the full objective of the pattern ``P p_c``, and a
        ``p_c`` inside the box gives a ``p`` inside it. Such a problem is four times smaller
        and solves the smooth part of the patterns, the part gradient methods are slowest on (two
        projectors' smooth patterns look alike on every target): a start for the full one.

        Coarsening stops early where a level would keep more than half the columns (scattered lit
        cells) or fewer than 64. Built once per operator and cached (``Q`` does not
        depend on the targets; :meth:`with_rhs` shares it).

        ``form``: of the normal equations, as :meth:`normal_equations`.

        Returns:
            Up to ``levels`` pairs ``(normal_equations, block)``, finest first: ``block`` maps the
            columns of the level above (the operator's own columns for the first) to this level's.
        """
        check(levels >= 0, f"levels must be >= 0, got {levels}")
        ne, out = self.normal_equations(form), []
        for block in self._level_blocks(levels):
            ne = ne.coarsened(block)
            out.append((ne, block))
        return out

    def _level_blocks(self, levels: int) -> list[torch.Tensor]:
        """The ``block`` of each of the first ``levels`` coarse levels (fewer where coarsening stops), cached."""
        device = self.column_cell.device
        if getattr(self, "_blocks_device", None) != device:
            self._blocks, self._blocks_complete, self._blocks_device = [], False, device
        while len(self._blocks) < levels and not self._blocks_complete:
            cp, cc, sizes = (self._blocks[-1][1:] if self._blocks
                             else (self.column_projector, self.column_cell, self.projector_sizes))
            block, *coarse = cell_blocks(cp, cc, sizes)
            if len(coarse[0]) > len(cp) // 2 or len(coarse[0]) < _MIN_COARSE_COLUMNS:
                self._blocks_complete = True
            else:
                self._blocks.append((block, *coarse))
        return [block for block, *_ in self._blocks[:levels]]

    def coarse_matrices(self) -> list[torch.Tensor]:
        """The coarse levels' ``P^T Q P`` that :meth:`coarse_levels` has built in the matrix form, finest
        first (empty where none): what a cache can keep beside ``Q`` (on the default scene the levels take
        about 0.3 s to build, and ``Q`` 0.33-0.43 s in a warm process)."""
        return [ne.Q for ne in self._normal_levels()[1:]]

    def _normal_levels(self) -> list["NormalEquations"]:
        """The matrix form's normal equations and its coarse levels built so far, finest first."""
        ne, out = getattr(self, "_normal", None), []
        if ne is None:
            return out
        out.append(ne)
        for block, *_ in getattr(self, "_blocks", []):
            if ne._coarse is None or ne._coarse[0] is not block:
                break
            ne = ne._coarse[1]
            out.append(ne)
        return out

    def solver_setup(self) -> list[dict]:
        """Per level of :meth:`_normal_levels` (``Q``, then each coarse level's ``P^T Q P``), what the
        solvers computed on it (:meth:`NormalEquations.setup`): what a cache keeps beside them."""
        return [ne.setup() for ne in self._normal_levels()]

    def adopt_solver_setup(self, setups: list[dict]) -> None:
        """Take :meth:`solver_setup` kept for this same matrix, once its ``Q`` and coarse levels are
        adopted (one entry per level; levels not adopted are refused)."""
        levels = self._normal_levels()
        check(len(setups) <= len(levels), f"a solver setup for {len(setups)} levels, {len(levels)} adopted")
        for ne, setup in zip(levels, setups):
            ne.adopt_setup(setup)

    def adopt_coarse_matrices(self, matrices: list[torch.Tensor]) -> None:
        """Take the coarse levels' ``P^T Q P`` built earlier for this same matrix (from
        :meth:`coarse_matrices`, kept by a cache keyed by the matrix) instead of building them; ``Q``
        must be adopted or built first. Each level's shape and layout are checked against its blocks."""
        check(getattr(self, "_normal", None) is not None, "adopt Q (adopt_normal_matrix) before its coarse levels")
        blocks = self._level_blocks(len(matrices))
        check(len(blocks) == len(matrices), f"{len(matrices)} coarse levels for an operator that has {len(blocks)}")
        ne = self._normal
        for block, Q in zip(blocks, matrices):
            ne = ne.adopt_coarsened(block, Q)

    def with_rhs(self, rhs: torch.Tensor, constant: torch.Tensor | None = None) -> "TransportOperator":
        """The same ``A`` with other targets (rows in the same order): shares the matrices and ``Q``.

        Args:
            rhs: :math:`(N_{rows}, C')` new target values, camera units.
            constant: :math:`(C',)` merged-away constant belonging to ``rhs`` (None: 0, exact for an
                operator built with ``merge=False``).
        """
        check_shape(rhs, "rhs", [self.shape[0], "C"])
        check_finite(rhs, "rhs")
        rhs = rhs.to(self.val.device, self.val.dtype)
        self._level_blocks(0)  # the coarse levels' blocks: one list, whichever operator builds them
        new = copy.copy(self)
        new._buffers = dict(self._buffers)
        new._buffers["rhs"] = rhs
        new._smoothed = None  # made with the old targets
        new._buffers["constant"] = (torch.zeros(rhs.shape[1], dtype=rhs.dtype, device=rhs.device)
                                    if constant is None else constant.to(rhs))
        for key in ("_normal", "_products"):
            cached = getattr(self, key, None)
            if cached is not None and cached.q.dtype == rhs.dtype and cached.q.device == rhs.device:
                setattr(new, key, cached.with_targets(new.A_adjoint(rhs), rhs.double().pow(2).sum(0)
                                                      + new.constant.double()))
            else:
                setattr(new, key, None)
        return new

    def with_smoothness(self, weight: float) -> "TransportOperator":
        """The same rows, and below them a penalty on the difference of each pair of neighbouring cells.

        For every two variables that are side by side in one projector (left-right or up-down), one
        row ``sqrt(lam) (p_c - p_d)`` with target 0, so that a least-squares solve on this operator
        minimises ``||A p - i||^2 + lam ||D p||^2``. ``lam`` is ``weight`` times ``scale`` squared: a
        difference of the whole box between two neighbouring cells costs what an error of
        ``sqrt(weight)`` of a target's full scale costs on one camera pixel. So the penalty holds
        where few pixels see a cell, and the light holds where many do: a cell that ``n`` pixels see
        whole has a squared column norm of about ``n scale^2``, and a cell finer than the pixels far
        less. (Over A's mean squared column norm instead, the same relative penalty on every scene, the
        targets of five suite seeds not used to choose either weight came out further from the
        ceiling: 0.010 dB in the median, 0.013 in the mean, 0.66 at the worst; ``benchmarks/smoothness.py``,
        ``docs/accuracy.md``.)

        Why: where cells are finer than the camera's pixels, or projectors overlap, many patterns
        give nearly the same light under the model, and the solve picks among them by the model's
        least reliable part (a pixel's exact share of each cell, an outline's position). What the
        world then shows departs from what the model promised, most on small targets. Among nearly
        equal patterns the penalty picks the smoother, whose light depends least on those details.
        The paper solves with box constraints alone (Sec. 3.3); this is our choice, measured on the
        procedural suite in ``docs/accuracy.md``.

        The new rows are no camera pixels: the operator has no ``row_pixel``, and is for solving
        (scores and images come from the operator it was made from).

        The operator made is kept, so that a second call with the same weight returns it with what was
        computed on it (its ``Q``, read from a cache or built by a solve).

        Args:
            weight: ``lam`` over ``scale`` squared, >= 0; 0 returns this operator.
        """
        check_smoothness(weight)
        if weight == 0:
            return self
        # What the kept operator was made from: moved, converted or given other targets since, it is stale.
        made_from = (weight, self.val.device, self.val.dtype, self.rhs.data_ptr(), self.rhs._version,
                     self.val.data_ptr(), self.val._version)
        kept = getattr(self, "_smoothed", None)
        if kept is not None and kept[0] == made_from:
            return kept[1]
        device = self.val.device
        root = math.sqrt(weight) * self.scale
        # lam is added to Q's entries in A's dtype: past its largest value the stack would hold inf.
        largest = torch.finfo(self.val.dtype).max
        check(root * root < largest, f"smoothness weight {weight:g} is too large for this {self.val.dtype} operator: "
                                     f"lam = weight x scale^2 = {root * root:.3g} passes its largest value; use a "
                                     f"weight below {largest / self.scale ** 2:.3g}")
        first, second = self._neighbour_pairs()
        pairs = first.numel()
        if pairs == 0:  # no two variables side by side: nothing to smooth
            return self
        # Two entries per new row, columns in order: the rows go below A's as they are, unsorted.
        cols = torch.stack([torch.minimum(first, second), torch.maximum(first, second)], 1).reshape(-1)
        ends = self.crow[-1] + 2 * torch.arange(1, pairs + 1, device=device, dtype=self.crow.dtype)
        matrix = csr_tensor(torch.cat([self.crow, ends]), torch.cat([self.col, cols.to(self.col.dtype)]),
                            torch.cat([self.val, torch.tensor([root, -root], dtype=self.val.dtype,
                                                              device=device).repeat(pairs)]),
                            (self.shape[0] + pairs, self.shape[1]))
        rhs = torch.cat([self.rhs, self.rhs.new_zeros(pairs, self.rhs.shape[1])])
        # The penalty's rows serve no target; they are counted with target 0 so that every row has one.
        row_target = torch.cat([self.row_target, self.row_target.new_zeros(pairs)])
        # The stack's transpose is made when first read: a solve from a Q read from a cache reads none of
        # it (0.3 s, and scipy's import, on the default scene). What makes it holds A^T's arrays, not this
        # operator, so that nothing refers back to an operator that keeps the stack; and it is a partial
        # of a module function, not a closure, so that such an operator still pickles. The same arrays
        # build its Q and its products (_penalty_parts).
        penalty = (self.t_crow, self.t_col, self.t_val, self.shape[0], cols, root)
        transposed = functools.partial(_stacked_transpose, *penalty)
        smoothed = TransportOperator(matrix, rhs, self.column_projector, self.column_cell, self.projector_sizes,
                                     constant=self.constant, row_target=row_target, scale=self.scale,
                                     target_count=self.target_count, transpose=transposed)
        # The penalty's targets are 0: the stack's A^T i is this operator's (the normal equations' q).
        smoothed._keep_targets_adjoint(self.A_adjoint(self.rhs))
        # Its Q is A^T A + lam D^T D, built from A's rows and A^T (:meth:`_gram_matrix`), not from the
        # stack and the stack's transpose, which a solve on Q then never makes.
        smoothed._penalty = penalty
        # Solved in this operator's form: the penalty's rows, two cells each, would otherwise tip a coarse
        # camera's wide rows (iterated on products) over to building Q.
        smoothed.form = normal_form(self)
        Q = self.normal_matrix()
        if Q is not None and Q.dtype == self.val.dtype and Q.device == self.val.device:
            # A^T A and its coarse levels P^T Q P built (or read from a cache) already: the penalty adds
            # lam D^T D to each, tied as they are, which costs a fraction of building them again.
            lam, differences = root * root, _penalty_gram(cols, self.shape[1])
            smoothed.adopt_normal_matrix(_plus(Q, differences, lam))
            coarse = self.coarse_matrices()
            if coarse:
                levels = []
                for block, Qc in zip(smoothed._level_blocks(len(coarse)), coarse):
                    differences = _tied(differences, block)
                    levels.append(_plus(Qc, differences, lam))
                smoothed.adopt_coarse_matrices(levels)
        self._smoothed = (made_from, smoothed)
        return smoothed

    def _gram_matrix(self) -> torch.Tensor:
        """``Q = A^T A`` built from the matrix (:func:`gram_matrix`). For an operator made by
        :meth:`with_smoothness`, ``Q`` of the stack ``[A; sqrt(lam) D]`` is ``A^T A + lam D^T D``:
        built from A's rows (the stack's first) and A^T, with ``D^T D`` added, and not from the stack
        and its transpose, which are then never made: on the default scene the cold run's solve took
        2.1-2.2 s against 2.9-3.0 s from the stack, its peak 2.73-2.86 against 2.91-2.97 GB (``torchproj
        run --no-cache``, two pairs alternating). The sum of ``lam D^T D`` is rounded to A's dtype, as
        where a Q read from a cache is given the penalty (:func:`_plus`)."""
        if self.__dict__.get("_penalty") is None:
            return gram_matrix(self._csr(), self._csr(transpose=True))
        A, At, differences, lam = self._penalty_parts()
        return _plus(gram_matrix(A, At), differences, lam)

    def _product_factors(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """``A``, ``A^T`` and the penalty ``lam D^T D`` (CSR, or None) that the products form applies
        (:class:`ProductNormalEquations`). For an operator made by :meth:`with_smoothness`, A's rows
        and A^T with ``lam D^T D`` beside them, not the stack and its transpose: a product reads
        ``D^T D``'s entries (a cell and its up to four neighbours) once, where the stack read D's
        twice, and the stack's transpose is never made."""
        if self.__dict__.get("_penalty") is None:
            return self._csr(), self._csr(transpose=True), None
        A, At, differences, lam = self._penalty_parts()
        return A, At, _from_scipy(differences * lam, self.val.dtype).to(self.val.device)

    def _penalty_parts(self):
        """For an operator made by :meth:`with_smoothness`: A (the stack's first rows, no copy), A^T
        (kept from the operator it was made from), ``D^T D`` (scipy, float64) and ``lam``."""
        t_crow, t_col, t_val, rows, cols, root = self._penalty
        device, dtype = self.val.device, self.val.dtype
        end = int(self.crow[rows])
        A = csr_tensor(self.crow[:rows + 1], self.col[:end], self.val[:end], (rows, self.shape[1]))
        At = csr_tensor(t_crow.to(device), t_col.to(device), t_val.to(device, dtype), (self.shape[1], rows))
        return A, At, _penalty_gram(cols, self.shape[1]), root * root

    def _keep_targets_adjoint(self, q: torch.Tensor) -> None:
        """Keep ``A^T i`` (known without a product) for :meth:`targets_adjoint`, while ``rhs`` is unchanged."""
        self._targets_adjoint = (self.rhs.data_ptr(), self.rhs._version, q)

    def targets_adjoint(self) -> torch.Tensor:
        """``A^T i``: :math:`(N_{cols}, C)`, the normal equations' ``q``."""
        kept = self.__dict__.get("_targets_adjoint")
        if (kept is not None and kept[:2] == (self.rhs.data_ptr(), self.rhs._version)
                and kept[2].device == self.rhs.device and kept[2].dtype == self.rhs.dtype):
            return kept[2]
        return self.A_adjoint(self.rhs)

    def _neighbour_pairs(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The columns of every two variables side by side in one projector, left-right then up-down."""
        device = self.val.device
        firsts, seconds = [], []
        for j, (w, h) in enumerate(self.projector_sizes):
            mine = torch.nonzero(self.column_projector == j)[:, 0]
            grid = torch.full((h * w,), -1, dtype=torch.int64, device=device)  # a cell's column, or -1
            grid[self.column_cell[mine].long()] = mine
            grid = grid.view(h, w)
            for a, b in ((grid[:, :-1], grid[:, 1:]), (grid[:-1, :], grid[1:, :])):
                both = (a >= 0) & (b >= 0)
                firsts.append(a[both])
                seconds.append(b[both])
        return torch.cat(firsts), torch.cat(seconds)

    def with_rows_moved(self, moves: torch.Tensor) -> "TransportOperator":
        """The same rows with each row's light moved across the projectors' cells (its footprint's shape kept).

        Where a projector or camera drifted, a camera pixel's light comes from cells a fraction of a
        cell or a few cells from where calibration saw it (:func:`torchproj.pipeline.register_maps`).
        Each entry of row r, at cell c, moves to ``c + moves[r, j]`` for its projector j and is split
        over the four cells around it (bilinear); a share past the projector's edge stays on its edge
        cell, so that no row is left empty.

        Args:
            moves: :math:`(N_{rows}, J, 2)` per row and projector, the move ``(dx, dy)`` in cells.

        Returns:
            an operator with the same rows, targets, scale and camera map, over the cells now reached.
        """
        n_proj = len(self.projector_sizes)
        check_shape(moves, "moves", [self.shape[0], n_proj, 2])
        check_finite(moves, "moves")
        device = self.val.device
        row = torch.repeat_interleave(torch.arange(self.shape[0], device=device), self.crow.diff())
        projector = self.column_projector[self.col]
        widths = torch.tensor([w for w, _ in self.projector_sizes], device=device)
        heights = torch.tensor([h for _, h in self.projector_sizes], device=device)
        cell = self.column_cell[self.col]
        w, h = widths[projector], heights[projector]
        move = moves.to(device=device, dtype=torch.float64)[row, projector]
        x = (cell % w).double() + move[:, 0]
        y = torch.div(cell, w, rounding_mode="floor").double() + move[:, 1]
        x0, y0 = torch.floor(x), torch.floor(y)
        fx, fy = x - x0, y - y0
        offsets = torch.cumsum(torch.cat([torch.zeros(1, dtype=torch.int64, device=device), widths * heights]), 0)
        # The two columns and two rows of cells around each moved entry, each computed once for the
        # four cells it borders. A share past the projector's edge stays on the edge cell: every row
        # keeps its light.
        ix, iy = x0.long(), y0.long()
        across = [torch.minimum((ix + d).clamp_min(0), w - 1) for d in (0, 1)]
        down = [torch.minimum((iy + d).clamp_min(0), h - 1) for d in (0, 1)]
        weight_x, weight_y = (1 - fx, fx), (1 - fy, fy)
        base, value = offsets[projector], self.val.double()
        del x, y, x0, y0, ix, iy, move, cell  # a full rig's are tens of millions of entries each
        rows, cells, vals = [], [], []
        for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
            share = weight_x[dx] * weight_y[dy]
            keep = torch.nonzero(share > 0)[:, 0]  # found once, not once per array a mask would index
            rows.append(row[keep])
            cells.append((base + down[dy] * w + across[dx])[keep])
            vals.append((value[keep] * share[keep]).to(self.val.dtype))
            del share, keep
        del fx, fy, weight_x, weight_y, across, down, base, value, w, h
        rows, cells, vals = torch.cat(rows), torch.cat(cells), torch.cat(vals)
        # The cells reached, in order, and each entry's column among them: what torch.unique(cells,
        # return_inverse=True) gives, by marking the rig's cells instead of sorting every entry (the
        # default scene's 35 M entries: a second of sorting).
        reached = torch.zeros(int(offsets[-1]), dtype=torch.bool, device=device)
        reached[cells] = True
        used = torch.nonzero(reached)[:, 0]
        column = (torch.cumsum(reached, 0) - 1)[cells]
        del cells, reached
        owner = torch.searchsorted(offsets, used, right=True) - 1
        matrix = csr_from_coo(rows, column, vals, (self.shape[0], len(used)))
        return TransportOperator(matrix, self.rhs, owner, used - offsets[owner], self.projector_sizes,
                                 constant=self.constant, row_target=self.row_target, scale=self.scale,
                                 row_pixel=self.row_pixel, camera_size=self.camera_size,
                                 target_count=self.target_count)

    def dense(self) -> torch.Tensor:
        """The matrix as a dense tensor (small problems and tests only)."""
        return self._csr().to_dense()

    # ------------------------------------------------------------------------------ camera view
    def _check_pixel_map(self) -> None:
        check(self.row_pixel is not None, "this operator's rows are merged and mix camera pixels: build it with "
                                          "merge=False to place rows on the camera")

    def to_camera(self, values: torch.Tensor, fill: float = 0.0) -> torch.Tensor:
        """Place row values on the camera, one image per target (differentiable in ``values``).

        Args:
            values: :math:`(N_{rows}, C)` (or :math:`(N_{rows},)`) per-row values, e.g. ``A p`` or ``rhs``.
            fill: value of the pixels that are not rows of a target.

        Returns:
            :math:`(K, C, H, W)`: image k holds the values of target k's rows at their pixels.
        """
        self._check_pixel_map()
        values = self._check_vector(values, "values", self.shape[0])
        w, h = self.camera_size
        index = self.row_target * (h * w) + self.row_pixel
        out = values.new_full((values.shape[1], self.target_count * h * w), fill)
        return out.index_copy(1, index, values.T).view(-1, self.target_count, h, w).transpose(0, 1)

    def camera_masks(self) -> torch.Tensor:
        """:math:`(K, H, W)` bool: the camera pixels that are rows of each target."""
        self._check_pixel_map()
        w, h = self.camera_size
        mask = torch.zeros(self.target_count * h * w, dtype=torch.bool, device=self.row_pixel.device)
        mask[self.row_target * (h * w) + self.row_pixel] = True
        return mask.view(self.target_count, h, w)

    # ------------------------------------------------------------------------------- patterns
    def to_images(self, p: torch.Tensor, fill: float = 0.0) -> list[torch.Tensor]:
        """Scatter column values into one :math:`(C, H_j, W_j)` image per projector.

        Cells that light no target are not variables; they get ``fill`` (default 0: black).
        """
        p = self._check_vector(p, "p", self.shape[1])
        images = []
        for j, (w, h) in enumerate(self.projector_sizes):
            img = torch.full((h * w, p.shape[1]), fill, dtype=p.dtype, device=p.device)
            sel = self.column_projector == j
            img[self.column_cell[sel]] = p[sel]
            images.append(img.T.reshape(p.shape[1], h, w))
        return images


# Entries per run of :func:`_blockwise_sum`, summed in float32 before the runs are added in float64.
SUM_RUN = 1024


def _blockwise_sum(values: torch.Tensor, block: int = SUM_RUN) -> torch.Tensor:
    """The sum of all entries, as float64, at the speed of a float32 sum.

    Runs of ``block`` entries are summed in their own dtype (torch sums a contiguous row pairwise,
    so the error stays near float32's resolution of each run's sum) and the runs' sums are added in
    float64. On the paper's full-size rig this matches a float64 sum of the same float32 terms to
    1e-9 of the objective, in a third of its time.
    """
    flat = values.reshape(-1)
    full = flat.numel() // block * block
    return flat[:full].view(-1, block).sum(1).double().sum() + flat[full:].double().sum()


def _sum_blocks(values: torch.Tensor, block: torch.Tensor, n: int) -> torch.Tensor:
    """``P^T values``: the rows of :math:`(N, C)` values summed per block."""
    return torch.zeros(n, values.shape[1], dtype=values.dtype, device=values.device).index_add_(0, block, values)


# Power-iteration products for the solvers' step bound (NormalEquations.lipschitz). Where Q has no
# negative entry the Collatz-Wielandt ratio is a bound after any number; after 15 it was 0.00-2.9%
# above the top eigenvalue on every scene, model and level of ``python benchmarks/step_bounds.py``
# (0.0-1.2% after 30, at twice the products). The 5% margin of the power estimate needs the estimate
# within 5% of the eigenvalue, which 30 products did not always reach (1.9% below it once).
STEP_BOUND_PRODUCTS = 15
MARGIN_PRODUCTS = 30


class NormalEquations:
    """The objective ``||A p - i||^2 + const`` written as ``p^T Q p - 2 q^T p + c`` (per channel).

    Attributes:
        Q: CSR :math:`(N_{cols}, N_{cols})`, symmetric positive semi-definite.
        q: :math:`(N_{cols}, C)`.
        c: :math:`(C,)` float64: ``||i||^2`` plus the operator's merged-away constant.
        scale: :math:`(N_{cols}, 1)` or None: for the Jacobi-scaled system (:meth:`jacobi`), the
            variables are ``p = scale * z``.
        two_q: ``2 q``, kept for the objective ``p^T (Q p - 2 q) + c``.
    """

    def __init__(self, Q: torch.Tensor, q: torch.Tensor, c: torch.Tensor, scale: torch.Tensor | None = None):
        self.Q, self.q, self.c, self.scale = Q, q, c, scale
        self.two_q = 2 * q
        self._lipschitz = None
        self._jacobi = None
        self._coarse = None
        self._bounds = {}
        # The relative (with_targets) that holds what depends on Q alone: its scaling, bound and coarse
        # levels are computed once there, whichever relative asks first. None: this one holds its own.
        self._origin = None

    @classmethod
    def from_operator(cls, op: TransportOperator, Q: torch.Tensor | None = None) -> "NormalEquations":
        """The normal equations of ``op``; ``Q``: its ``A^T A`` built earlier (a cache's), else built here."""
        if Q is None:
            Q = op._gram_matrix()
        return cls(Q.to(op.val.device), op.targets_adjoint(), op.rhs.double().pow(2).sum(0) + op.constant.double())

    def with_targets(self, q: torch.Tensor, c: torch.Tensor) -> "NormalEquations":
        """The same ``Q`` with new ``q`` and ``c``. What depends on ``Q`` alone (the Jacobi scaling, the
        Lipschitz bounds, the coarse levels' ``P^T Q P``) is shared with this system and every other
        it was made from or makes: computed once, by whichever solves first (a video's frames, a
        loop's steps and a batch of target sets each solved on :meth:`TransportOperator.with_rhs`
        paid them again on every solve)."""
        new = self._with(q, c)
        new._origin = self._origin if self._origin is not None else self
        return new

    def _sharing(self, origin: "NormalEquations", q: torch.Tensor) -> "NormalEquations":
        """``origin`` (the scaled or a coarse system of this one's origin) with ``q`` and this system's
        constant, sharing what is computed on it."""
        new = origin._with(q, self.c, origin.scale)
        new._origin, new._bounds = origin, origin._bounds
        return new

    def _with(self, q: torch.Tensor, c: torch.Tensor, scale: torch.Tensor | None = None) -> "NormalEquations":
        """The same ``Q`` with other ``q``, ``c`` and scale, nothing cached."""
        return NormalEquations(self.Q, q, c, scale)

    def coarsened(self, block: torch.Tensor) -> "NormalEquations":
        """``P^T Q P``, ``P^T q`` and ``c`` for the 0/1 matrix ``P`` that ties columns by ``block``.

        ``block`` is :math:`(N_{cols},)` (see :func:`cell_blocks`); the result is cached for that
        tensor, and :meth:`with_targets` carries it over with the new targets.
        """
        if (self._coarse is None or self._coarse[0] is not block) and self._origin is not None:
            coarse = self._origin.coarsened(block)
            self._coarse = (block, self._sharing(coarse, _sum_blocks(self.q, block, coarse.q.shape[0])))
        if self._coarse is None or self._coarse[0] is not block:
            from scipy.sparse import csr_matrix

            n = int(block.max()) + 1
            q_mat = _to_scipy(self.Q, torch.float64)
            tie = csr_matrix((torch.ones(len(block), dtype=torch.float64).numpy(),
                              (torch.arange(len(block)).numpy(), block.cpu().numpy())), shape=(len(block), n))
            # (P^T (Q P))^T, built in CSR and transposed: what (tie.T @ q_mat @ tie).tocsr() gives, without
            # the CSC copy of Q scipy makes to multiply a CSC matrix by it (that product is P^T (Q^T P)
            # in CSR read as its transpose). The same to the bit where Q is symmetric to the bit, as
            # A^T A is (an entry's products are summed over the same rows in the same order from
            # either side); on the default scene every level is. There the first level takes 0.21
            # against 0.30 s, and the levels' building peaks 0.30 GB above what it starts from, not 0.44.
            coarse = (tie.T.tocsr() @ (q_mat @ tie)).T.tocsr()
            coarse.sort_indices()
            return self.adopt_coarsened(block, _from_scipy(coarse, self.Q.dtype))
        return self._coarse[1]

    def adopt_coarsened(self, block: torch.Tensor, Q: torch.Tensor) -> "NormalEquations":
        """What :meth:`coarsened` gives for ``block``, with its ``P^T Q P`` given (built earlier, a cache's)."""
        n = int(block.max()) + 1
        check(Q.layout == torch.sparse_csr and tuple(Q.shape) == (n, n) and Q.dtype == self.Q.dtype,
              f"a coarse level's matrix must be a CSR matrix of {n} x {n} {self.Q.dtype}, got {Q.layout} "
              f"{tuple(Q.shape)} {Q.dtype}")
        self._coarse = (block, NormalEquations(Q.to(self.q.device), _sum_blocks(self.q, block, n), self.c))
        return self._coarse[1]

    def jacobi(self, rows: torch.Tensor | None = None) -> "NormalEquations":
        """The system in the variables ``z = p / scale`` with ``scale = diag(Q)^-1/2`` (cached).

        ``S Q S`` has a unit diagonal, which evens out how strongly each projector cell is seen (fall-off,
        vignetting, cells at the edge of a target) and lets gradient methods take longer steps.
        The box ``lo <= p <= hi`` stays a box: ``lo / scale <= z <= hi / scale``.

        ``rows``: the row of each of ``Q``'s entries (:func:`entry_rows`), where the caller has them.
        """
        if self._jacobi is None and self._origin is not None:
            j = self._origin.jacobi(rows)
            self._jacobi = self._sharing(j, self.q * j.scale)
        if self._jacobi is None:
            # Each entry's row in the indices' own type (int32 as scipy's product gives them).
            rows = entry_rows(self.Q, self.Q.col_indices().dtype) if rows is None else rows
            s = _diagonal(self.Q, rows).clamp_min(1e-30).rsqrt()
            self._jacobi = NormalEquations(_scaled_both(self.Q, s, rows), self.q * s[:, None], self.c, s[:, None])
        return self._jacobi

    def setup(self) -> dict:
        """What the solvers computed on this ``Q`` so far and a cache can keep beside it: the Lipschitz
        bound (:meth:`lipschitz`, 30 products) and, where built, the Jacobi scaling (:meth:`jacobi`:
        three passes over ``Q``'s entries) with its own bound; None where not computed."""
        j = self._jacobi
        return {"lipschitz": self._lipschitz,
                "jacobi": None if j is None else {"scale": j.scale, "values": j.Q.values(), "lipschitz": j._lipschitz}}

    def adopt_setup(self, setup: dict) -> None:
        """Take what :meth:`setup` gave for this same ``Q`` (a cache keyed by the matrix): bounds positive
        numbers or None, the scaling's shapes those of this ``Q`` (checked before anything is taken)."""
        j = setup.get("jacobi")
        bounds = {"lipschitz": setup.get("lipschitz"), "jacobi's lipschitz": None if j is None else j.get("lipschitz")}
        for key, value in bounds.items():
            check(value is None or (isinstance(value, float) and math.isfinite(value) and value > 0),
                  f"a kept {key} must be a positive number or None, got {value!r}")
        if j is not None:
            n, nnz = self.Q.shape[0], self.Q.values().numel()
            check(torch.is_tensor(j.get("scale")) and tuple(j["scale"].shape) == (n, 1)
                  and torch.is_tensor(j.get("values")) and tuple(j["values"].shape) == (nnz,)
                  and j["values"].dtype == self.Q.dtype,
                  f"a kept Jacobi scaling must be a ({n}, 1) scale and {nnz} {self.Q.dtype} values")
        self._lipschitz = setup.get("lipschitz") or self._lipschitz
        if j is not None:
            scale = j["scale"].to(self.q.device)
            Q = csr_tensor(self.Q.crow_indices(), self.Q.col_indices(), j["values"].to(self.q.device), self.Q.shape)
            self._jacobi = NormalEquations(Q, self.q * scale, self.c, scale)
            self._jacobi._lipschitz = j.get("lipschitz")

    def bound(self, value: float) -> torch.Tensor | float:
        """A bound on ``p`` as a bound on this system's variables, ``value / scale`` (cached).

        A number where it is the same for every variable (no scaling, or 0); otherwise an
        :math:`(N_{cols}, C)` block, stored whole because torch's clamp is five times slower when it
        broadcasts an (N, 1) bound across the channels. Every set of targets shares it.
        """
        if self.scale is None or value == 0:
            return value
        key = (value, self.q.shape[1])
        if key not in self._bounds:
            self._bounds[key] = torch.div(value, self.scale).expand_as(self.q).contiguous()
        return self._bounds[key]

    def product(self, p: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
        """``Q p`` for :math:`(N_{cols}, C)` p, into ``out`` when given (its contents are ignored)."""
        return spmm(self.Q, p, out)

    def objective(self, p: torch.Tensor, qp: torch.Tensor, work: torch.Tensor | None = None) -> float:
        """Objective from p and its product ``Q p``, summed in float64 (run by run: :func:`_blockwise_sum`).

        The objective is a small difference of large terms (the targets' energy ``c`` and
        ``p^T (Q p - 2 q)``): a float32 total is off by ~1e-6 of it, as much as a solver's stopping
        tolerance, and then rounding decides when FISTA restarts and stops. ``work`` (shaped like p)
        is scratch space, so an iterative solver allocates nothing per call.
        """
        work = torch.sub(qp, self.two_q, out=work).mul_(p)
        return float(_blockwise_sum(work) + self.c.sum())

    def lipschitz(self, iterations: int | None = None) -> float:
        """An upper bound of the largest eigenvalue of Q (cached), from power iteration: ``iterations``
        products and one more (default :data:`STEP_BOUND_PRODUCTS`, or :data:`MARGIN_PRODUCTS` where
        the margin below is what bounds it).

        Q has no negative entries when every weight is non-negative (the radiometric and geometric
        weightings); then, for the power-iteration vector x, ``max_i (Q x)_i / x_i`` over the columns
        with an entry bounds the largest eigenvalue from above (Collatz-Wielandt) after any number of
        products, and tightens as x converges. A column without one (a projector cell no row sees)
        is a zero row of the Gram matrix ``Q``, eigenvalue 0, and stays 0 in x: the bound holds on
        the rest, which the first product (Q's row sums, positive exactly on its nonzero rows) marks.
        Where Q has negative entries (a smoothness penalty's ``-lam`` between neighbouring cells,
        :meth:`TransportOperator.with_smoothness`), the iteration runs on ``|Q|``, entry by entry,
        whose largest eigenvalue is no smaller than Q's (Perron-Frobenius: ``rho(Q) <= rho(|Q|)``),
        so that bound holds for Q too. Otherwise (a seen column's entry of x rounded to 0) the power
        iteration's estimate gets a 5% margin, which is no bound where the products fall short of
        the top eigenvalue by more: with 30 it was 1.9% below it on the default scene's coarsest level
        (``python benchmarks/step_bounds.py``).
        """
        if self._lipschitz is None and self._origin is not None:
            self._lipschitz = self._origin.lipschitz(iterations)
        if self._lipschitz is None:
            product = self.product if self._nonnegative() else self._absolute_product()
            wanted = iterations if iterations is not None else STEP_BOUND_PRODUCTS
            x = torch.ones(self.q.shape[0], 1, dtype=self.q.dtype, device=self.q.device)
            rows, done = None, 0
            while True:
                y = product(x)
                rows = y[:, 0] > 0 if rows is None else rows
                if done >= wanted:
                    if bool((x[rows] > 0).all()):
                        self._lipschitz = float((y[rows] / x[rows]).max()) if bool(rows.any()) else 0.0
                        break
                    if iterations is not None or done >= MARGIN_PRODUCTS:
                        self._lipschitz = 1.05 * float(y.norm() / x.norm())
                        break
                    wanted = MARGIN_PRODUCTS
                x = y / y.norm().clamp_min(1e-30)
                done += 1
        return self._lipschitz

    def _nonnegative(self) -> bool:
        """Whether ``Q`` has no negative entry (then the Collatz-Wielandt bound holds)."""
        values = self.Q.values()
        return values.numel() == 0 or float(values.min()) >= 0

    def _absolute_product(self):
        """``x -> |Q| x``, Q's entries taken by their size (:meth:`lipschitz`)."""
        absolute = _absolute(self.Q)
        return lambda x: spmm(absolute, x)


def _difference_rows(cols: torch.Tensor, n: int):
    """``D`` (scipy CSR, float64, one row per pair, :math:`(pairs, n)`) of rows ``p_a - p_b`` for ``cols``
    holding ``a, b`` per row in order (:meth:`TransportOperator.with_smoothness`). ``D^T D`` from it is
    scipy's product of two entries per row, with no duplicates to sum: 0.12 s for the default scene's
    1.8 M pairs, against 0.9 s from coordinates."""
    from scipy.sparse import csr_matrix

    pairs = cols.numel() // 2
    return csr_matrix((np.tile([1.0, -1.0], pairs), cols.cpu().numpy(), np.arange(0, 2 * pairs + 1, 2)),
                      shape=(pairs, n))


def _penalty_gram(cols: torch.Tensor, n: int):
    """``D^T D`` (scipy CSR, float64, :math:`(n, n)`) of the difference rows ``cols`` (:func:`_difference_rows`)."""
    differences = _difference_rows(cols, n)
    gram = (differences.T @ differences).tocsr()
    gram.sort_indices()
    return gram


def _stacked_transpose(t_crow: torch.Tensor, t_col: torch.Tensor, t_val: torch.Tensor, rows: int, cols: torch.Tensor,
                       root: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The CSR arrays of ``[A; root D]^T``, for ``A^T`` in ``t_crow, t_col, t_val`` (``A`` with ``rows``
    rows) and ``D``'s rows ``p_a - p_b`` with ``a, b`` in ``cols`` (:func:`_difference_rows`) below A's:
    each of A^T's rows followed by D^T's, placed by counting, so no entry is sorted (a transpose of the
    whole stack took 0.7 s on the default scene)."""
    device = t_val.device
    # D^T's CSR arrays; +-root rounded to A's dtype below, as the stack holds them.
    D = (_difference_rows(cols, t_crow.numel() - 1) * root).tocsc()
    d_crow, d_col, d_val = (torch.from_numpy(a).to(device) for a in (D.indptr.astype(np.int64), D.indices, D.data))
    a_crow = t_crow.long()
    crow = a_crow + d_crow
    # An entry of A^T's row c moves down by D^T's entries in the rows before c; one of D^T's comes
    # after all of A^T's row c.
    a_at = torch.arange(t_val.numel(), device=device) + torch.repeat_interleave(d_crow[:-1], a_crow.diff())
    d_at = torch.arange(d_val.numel(), device=device) + torch.repeat_interleave(a_crow[1:], d_crow.diff())
    index = index_dtype(rows + D.shape[0], int(crow[-1]))
    col = torch.empty(int(crow[-1]), dtype=index, device=device)
    val = torch.empty(int(crow[-1]), dtype=t_val.dtype, device=device)
    col[a_at], val[a_at] = t_col.to(index), t_val
    col[d_at], val[d_at] = (d_col.long() + rows).to(index), d_val.to(t_val.dtype)
    return crow.to(index), col, val


def _tied(matrix, block: torch.Tensor):
    """``P^T M P`` of a scipy matrix, ``P`` tying columns in ``block`` (:meth:`TransportOperator.coarse_levels`)."""
    from scipy.sparse import csr_matrix

    index = block.cpu().numpy()
    tie = csr_matrix((np.ones(len(index)), (np.arange(len(index)), index)), shape=(len(index), int(index.max()) + 1))
    return (tie.T @ matrix @ tie).tocsr()


def _plus(Q: torch.Tensor, matrix, lam: float) -> torch.Tensor:
    """``Q + lam M`` for a scipy ``M``, added on the CPU in Q's dtype (float32: a rounding of 1e-7 of
    each entry, as Q is kept; float64 took twice as long on the default scene's Q), as a CSR tensor on
    Q's device, each row's columns in order."""
    q = _to_scipy(Q)
    total = q + (lam * matrix).astype(q.dtype)
    total.sort_indices()
    return _from_scipy(total.tocsr()).to(Q.device)


def gram_matrix(A: torch.Tensor, At: torch.Tensor | None = None, parts: int | None = None) -> torch.Tensor:
    """``Q = A^T A`` of a CSR matrix ``A`` :math:`(N_{rows}, N_{cols})`, as a CSR tensor
    :math:`(N_{cols}, N_{cols})` of ``A``'s dtype, summed in float64 on the CPU.

    scipy's sparse product builds it, one block of ``Q``'s rows per CPU thread (``parts``; default
    torch's thread count): block ``k`` is ``A^T[rows_k] A``, and scipy lets go of Python's lock inside
    the product, so the blocks run at once. Each entry is summed over the same rows in the same order
    as one whole product sums it, so ``Q`` is the same to the bit whatever ``parts`` is. The blocks are
    cut where ``A^T`` has equal shares of its nonzeros, and written straight into the result's arrays
    (float64 -> ``A``'s dtype), so no float64 copy of the whole ``Q`` is made beside the blocks.

    Args:
        At: ``A^T`` in CSR with each row's columns in order, where it is at hand (an operator holds
            it); else transposed here.
    """
    from concurrent.futures import ThreadPoolExecutor

    a = _to_scipy(A, torch.float64)
    at = a.T.tocsr() if At is None else _to_scipy(At, torch.float64)
    n = at.shape[0]
    parts = max(1, min(torch.get_num_threads() if parts is None else parts, n))
    nnz = torch.from_numpy(at.indptr).to(torch.int64)
    cuts = [0, *torch.searchsorted(nnz, nnz[-1] * torch.arange(1, parts) // parts).tolist(), n]

    def block(k: int):
        q = at[cuts[k]:cuts[k + 1]] @ a
        q.sort_indices()
        return q

    if parts == 1:
        blocks = [block(0)]
    else:
        with ThreadPoolExecutor(parts) as pool:
            blocks = list(pool.map(block, range(parts)))
    starts = [0]
    for q in blocks:
        starts.append(starts[-1] + q.nnz)
    index = index_dtype(n, starts[-1])  # as csr_tensor keeps them
    crow_q = torch.empty(n + 1, dtype=index)
    col_q = torch.empty(starts[-1], dtype=index)
    val_q = torch.empty(starts[-1], dtype=A.dtype)
    crow_q[0] = 0
    for k, q in enumerate(blocks):
        crow_q[cuts[k] + 1:cuts[k + 1] + 1] = torch.from_numpy(q.indptr[1:]) + starts[k]
        col_q[starts[k]:starts[k + 1]] = torch.from_numpy(q.indices)
        val_q[starts[k]:starts[k + 1]] = torch.from_numpy(q.data)
    return csr_tensor(crow_q, col_q, val_q, (n, n))


def check_smoothness(weight, name: str = "smoothness weight") -> float:
    """A smoothness weight (:meth:`TransportOperator.with_smoothness`): a finite number >= 0, 0 for none."""
    check(is_number(weight) and math.isfinite(weight) and weight >= 0,
          f"{name} must be a number >= 0 (0: none), got {weight!r}")
    return float(weight)


def check_operator(op, name: str = "op") -> None:
    """``op`` a :class:`TransportOperator` (:func:`~torchproj.transport.build_transport`'s)."""
    ops = _channel_list(op)
    # One operator per colour channel (build_channel_transports', a colour ProjectionModel's) is the
    # likeliest wrong kind here, and has its own way through.
    check(not (isinstance(ops, (list, tuple)) and len(ops) > 1 and all(isinstance(o, TransportOperator) for o in ops)),
          f"{name} is one operator per colour channel, and this takes one: give each channel's alone, or "
          f"make_patterns, which solves each channel's")
    check(isinstance(op, TransportOperator), f"{name} must be a TransportOperator (build_transport's), got "
                                             f"{type(op).__name__}")


def _channel_list(op):
    """A colour :class:`~torchproj.solve.ProjectionModel`'s ``operator`` (a module holding one operator
    per channel) as that list; anything else as it is. A script's camera loop passes it as the model
    gives it (``rig_measure(world, model.operator, targets)``)."""
    if isinstance(op, nn.Module) and isinstance(getattr(op, "ops", None), nn.ModuleList):
        return list(op.ops)
    return op


def check_operators(op, name: str = "op") -> list:
    """``op`` one :class:`TransportOperator`, or a list of one per colour channel
    (:func:`~torchproj.transport.build_channel_transports`) or a colour
    :class:`~torchproj.solve.ProjectionModel`'s ``operator``, which holds that list, as a list."""
    op = _channel_list(op)
    ops = list(op) if isinstance(op, (list, tuple)) else [op]
    check(len(ops) > 0 and all(isinstance(o, TransportOperator) for o in ops),
          f"{name} must be a TransportOperator (build_transport's), or a list of one per colour channel, got "
          f"{type(op).__name__}{' (empty)' if isinstance(op, (list, tuple)) and not op else ''}")
    return ops


def normal_form(op: "TransportOperator") -> str:
    """The form of the normal equations the gradient solvers iterate on for ``op``
    (:meth:`TransportOperator.normal_equations`' ``"auto"``): ``"products"`` where its rows are
    fewer than its columns and more than three cells wide on average (by the sum of squares), else
    ``"matrix"``.

    ``Q = A^T A`` has a nonzero for every pair of cells that share a row: up to ``s^2`` for a row of
    ``s`` cells, against the ``2 s`` that ``A`` and ``A^T`` apply. Where every cell is seen by
    several rows (a camera finer than the projectors: the paper's rig, 2.1 M rows on 0.93 M cells)
    those pairs repeat, ``Q`` is the compact form and building it once pays: on the default scene's
    area model FISTA takes 2.9 s on ``Q`` against 5.5 s on ``A`` and ``A^T``. Where camera pixels
    are fewer than the cells they see and rows are wide (a coarse camera, the area footprint's rows
    of 4-12 cells) nothing repeats, ``Q`` holds 2-5 times A's nonzeros, and building it and its
    coarse levels costs more than the iterations save: on ``box_positions``' area model (0.16 M rows,
    0.35 M cells, Q 5.5 times A's nonzeros) 2.5 s against 1.5 s. Rows of one or two cells (the nearest
    footprint) keep ``Q`` sparse: there it wins everywhere (``python benchmarks/normal_forms.py``).
    """
    check_operator(op)
    if getattr(op, "form", None) is not None:  # an operator made from another iterates as that one
        return op.form
    width = op.crow.diff().double()
    wide = float((width * width).sum()) > 3 * float(width.sum())
    return "products" if op.shape[0] < op.shape[1] and wide else "matrix"


class ProductNormalEquations(NormalEquations):
    """The normal equations with ``Q p`` taken as ``A^T (A p)``: ``Q`` is never built.

    The same interface and results as :class:`NormalEquations` (``q``, ``c``, ``scale``,
    :meth:`product`, :meth:`jacobi`, :meth:`coarsened`, :meth:`lipschitz`), so the solvers that
    only apply ``Q`` run on either. The Jacobi scaling multiplies A's columns (``A S``), and tying
    columns into blocks sums them (``A P``): each level is again a pair of sparse factors.

    Where a smoothness penalty is solved (:meth:`TransportOperator.with_smoothness`), ``Q p`` is
    ``A^T (A p) + R p`` with ``R = lam D^T D`` applied as it is (a cell and its neighbours), not as
    two more factors: ties and scalings act on it as on ``Q``.

    Attributes:
        A, At: CSR :math:`(N_{rows}, N_{cols})` and its transpose.
        penalty: CSR :math:`(N_{cols}, N_{cols})` ``R``, or None.
    """

    def __init__(self, A: torch.Tensor, At: torch.Tensor, q: torch.Tensor, c: torch.Tensor,
                 scale: torch.Tensor | None = None, penalty: torch.Tensor | None = None):
        super().__init__(None, q, c, scale)
        self.A, self.At, self.penalty = A, At, penalty
        self._rows_buffer = None

    @classmethod
    def from_operator(cls, op: TransportOperator) -> "ProductNormalEquations":
        with torch.no_grad():
            A, At, penalty = op._product_factors()
            return cls(A, At, op.targets_adjoint(), op.rhs.double().pow(2).sum(0) + op.constant.double(),
                       penalty=penalty)

    def _with(self, q: torch.Tensor, c: torch.Tensor, scale: torch.Tensor | None = None) -> "ProductNormalEquations":
        """The same ``A`` with other ``q``, ``c`` and scale, nothing cached (:meth:`NormalEquations.with_targets`)."""
        return ProductNormalEquations(self.A, self.At, q, c, scale, self.penalty)

    def product(self, p: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
        """``A^T (A p)`` (plus ``R p``) for :math:`(N_{cols}, C)` p, into ``out`` when given."""
        rows = self._rows_buffer
        if rows is None or rows.shape[1] != p.shape[1] or rows.dtype != p.dtype or rows.device != p.device:
            rows = self._rows_buffer = torch.empty(self.A.shape[0], p.shape[1], dtype=p.dtype, device=p.device)
        rows = spmm(self.A, p, rows)
        if self.penalty is None:
            return spmm(self.At, rows, out)
        return spmm(self.At, rows, spmm(self.penalty, p, out), add=True)

    def coarsened(self, block: torch.Tensor) -> "ProductNormalEquations":
        """``A P`` (columns summed per ``block``), ``P^T q`` and ``c``; cached for that tensor."""
        if (self._coarse is None or self._coarse[0] is not block) and self._origin is not None:
            coarse = self._origin.coarsened(block)
            self._coarse = (block, self._sharing(coarse, _sum_blocks(self.q, block, coarse.q.shape[0])))
        if self._coarse is None or self._coarse[0] is not block:
            n = int(block.max()) + 1
            tied = _tie_columns(self.A, block, n)
            penalty = None if self.penalty is None else _from_scipy(
                _tied(_to_scipy(self.penalty, torch.float64), block), self.penalty.dtype).to(self.penalty.device)
            self._coarse = (block, ProductNormalEquations(tied, _transpose(tied), _sum_blocks(self.q, block, n),
                                                          self.c, penalty=penalty))
        return self._coarse[1]

    def jacobi(self) -> "ProductNormalEquations":
        """The system in ``z = p / scale`` with ``scale = diag(A^T A)^-1/2``: A's columns scaled to unit
        norm (cached)."""
        if self._jacobi is None and self._origin is not None:
            j = self._origin.jacobi()
            self._jacobi = self._sharing(j, self.q * j.scale)
        if self._jacobi is None:
            # Indexed by A's own (int32) column indices, and A^T's rows (A's columns) by repeating each
            # scale along its row: on the default scene's 8.8 M entries 90 ms against 165 ms through
            # int64 indices (the same values).
            crow, col, val = self.A.crow_indices(), self.A.col_indices(), self.A.values()
            norm = torch.zeros(self.A.shape[1], dtype=val.dtype, device=val.device).index_add_(0, col, val * val)
            penalty = self.penalty
            if penalty is not None:  # its diagonal joins the column norms, and it is scaled as Q is
                rows = entry_rows(penalty, penalty.col_indices().dtype)
                norm += _diagonal(penalty, rows)
            s = norm.clamp_min(1e-30).rsqrt()
            A = csr_tensor(crow, col, s.index_select(0, col).mul_(val), self.A.shape)
            t_crow, t_col, t_val = self.At.crow_indices(), self.At.col_indices(), self.At.values()
            At = csr_tensor(t_crow, t_col, torch.repeat_interleave(s, t_crow.diff()).mul_(t_val), self.At.shape)
            if penalty is not None:
                penalty = _scaled_both(penalty, s, rows)
            self._jacobi = ProductNormalEquations(A, At, self.q * s[:, None], self.c, s[:, None], penalty)
        return self._jacobi

    def _nonnegative(self) -> bool:
        """Whether ``Q`` has no negative entry: where A has none and there is no penalty, whose ``-lam``
        between neighbours is negative (:meth:`NormalEquations.lipschitz`)."""
        values = self.A.values()
        return self.penalty is None and (values.numel() == 0 or float(values.min()) >= 0)

    def _absolute_product(self):
        """``x -> |A|^T |A| x + |R| x``: entry by entry no smaller than ``|Q|``, so its largest eigenvalue
        bounds Q's (:meth:`NormalEquations.lipschitz`)."""
        A, At = (_absolute(m) for m in (self.A, self.At))
        if self.penalty is None:
            return lambda x: spmm(At, spmm(A, x))
        R = _absolute(self.penalty)
        return lambda x: spmm(At, spmm(A, x), spmm(R, x), add=True)


def _absolute(matrix: torch.Tensor) -> torch.Tensor:
    """A CSR matrix's entries taken by their size."""
    return csr_tensor(matrix.crow_indices(), matrix.col_indices(), matrix.values().abs(), matrix.shape)


def _diagonal(Q: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """The diagonal of a square CSR ``Q`` whose entries' rows are ``rows`` (:func:`entry_rows`); a CSR
    row holds its diagonal once, so it is written, not summed."""
    col, val = Q.col_indices(), Q.values()
    on = rows == col
    diag = torch.zeros(Q.shape[0], dtype=val.dtype, device=val.device)
    diag[col[on].long()] = val[on]
    return diag


def _scaled_both(Q: torch.Tensor, s: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """``S Q S`` for ``S = diag(s)``, ``rows`` as :func:`_diagonal`'s. Both scales are gathered by
    index_select, which on the default scene's 16 M entries takes 30 ms a gather against 55 ms for
    indexing and 53 ms for repeating each row's scale along its row."""
    col, val = Q.col_indices(), Q.values()
    return csr_tensor(Q.crow_indices(), col, s.index_select(0, rows).mul_(val).mul_(s.index_select(0, col)), Q.shape)


def entry_rows(matrix: torch.Tensor, dtype: torch.dtype = torch.int64) -> torch.Tensor:
    """The row of every stored entry of a CSR matrix, :math:`(nnz,)` of ``dtype`` (with ``col_indices``:
    its COO form; int32 halves the bytes where an index only compares or gathers)."""
    crow = matrix.crow_indices()
    return torch.repeat_interleave(torch.arange(matrix.shape[0], dtype=dtype, device=crow.device), crow.diff())


def _tie_columns(matrix: torch.Tensor, block: torch.Tensor, n: int) -> torch.Tensor:
    """CSR ``matrix P``: the columns of each block summed (``block`` :math:`(N_{cols},)` of ``n``)."""
    return csr_from_coo(entry_rows(matrix), block[matrix.col_indices().long()], matrix.values(), (matrix.shape[0], n))


def _transpose(matrix: torch.Tensor) -> torch.Tensor:
    """The CSR transpose of a CSR matrix: its CSC arrays read as CSR.

    On the CPU scipy converts it with one counting pass over the entries: 0.035 s against torch's
    0.49 s on the default scene's 8.8 M, and 0.43 against 1.26 s on the 25 M of its rows moved, the
    same arrays (each column's rows in order). Elsewhere (another device, a dtype numpy lacks) torch
    converts it (which itself took 0.08 s against 0.53 s for 2 M through coordinates).
    """
    shape = tuple(matrix.shape)
    if matrix.device.type == "cpu" and matrix.dtype in (torch.float32, torch.float64):  # what numpy holds
        return _from_scipy(_to_scipy(matrix).tocsc(), shape=shape[::-1])
    csc = matrix.to_sparse_csc()
    return csr_tensor(csc.ccol_indices(), csc.row_indices(), csc.values(), shape[::-1])


def _to_scipy(matrix: torch.Tensor, dtype: torch.dtype | None = None):
    """scipy's CSR matrix of a torch CSR ``matrix``, on the host, its values in ``dtype`` (default their
    own); index arrays already on the CPU are shared, not copied."""
    from scipy.sparse import csr_matrix

    values = matrix.values().detach().cpu()
    return csr_matrix(((values if dtype is None else values.to(dtype)).numpy(), matrix.col_indices().cpu().numpy(),
                       matrix.crow_indices().cpu().numpy()), shape=tuple(matrix.shape))


def _from_scipy(matrix, dtype: torch.dtype | None = None, shape: tuple[int, int] | None = None) -> torch.Tensor:
    """A torch CSR tensor of a scipy matrix's compressed arrays (``indptr``, ``indices``, ``data``), its
    values in ``dtype`` (default their own). ``shape``: what the arrays describe read as CSR, where that
    is not the matrix's own (a CSC matrix's arrays are its transpose's CSR)."""
    values = torch.from_numpy(matrix.data)
    return csr_tensor(torch.from_numpy(matrix.indptr), torch.from_numpy(matrix.indices),
                      values if dtype is None else values.to(dtype), tuple(matrix.shape) if shape is None else shape)
