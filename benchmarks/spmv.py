"""One column through the CPU's sparse matrix-vector kernel against its matrix-matrix kernel.

    python benchmarks/spmv.py --out benchmarks/results/spmv

:func:`~torchproj.core.sparse.spmm` sends a single column (a grey image, one colour channel's
operator) to ``torch.addmv`` on the CPU, and wider blocks to ``torch.addmm``. Per scene (the
default rig at full size, ``colour_two_planes``' first channel, a small suite scene; calibrations
from the cache), interleaved, medians of ``--repeats``:

- the products: ``A``, ``A^T`` and ``Q = A^T A`` of the area transport on one column by either
  kernel (and the largest difference between their results, relative to the result's largest
  value), and ``addmm`` on three columns;
- what a person waits for: FISTA to the pipeline's limit from ``Q`` (as ``torchproj run`` solves),
  and the camera loop's update on ``A`` and ``A^T`` (30 iterations from the solution,
  ``form="products"``, as after a re-registration), with :data:`~torchproj.core.sparse.VECTOR_KERNEL`
  on and off.

Writes ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import torch
from common import interleaved, machine, write_results

import torchproj.core.sparse as sparse
from torchproj.pipeline import scene_targets
from torchproj.pipeline.cache import cached_calibration
from torchproj.pipeline.run import build_operators
from torchproj.scene import load_scene
from torchproj.solve import REFINE_SOLVER_ITERATIONS, solve_fista

SCENES = ("paper_two_planes", "colour_two_planes", "suite-1-8")
BOUNDS = (0.0, 1.0)


def _kernel(on: bool, fn):
    def run():
        sparse.VECTOR_KERNEL = on
        try:
            return fn()
        finally:
            sparse.VECTOR_KERNEL = True
    return run


def _products(matrix: torch.Tensor, gen: torch.Generator, repeats: int) -> dict:
    """Milliseconds of one column's product by either kernel and of three columns', and the largest
    difference between the kernels' results over the result's largest value."""
    x = torch.rand(matrix.shape[1], 1, generator=gen)
    three = torch.rand(matrix.shape[1], 3, generator=gen)
    out, out3 = torch.empty(matrix.shape[0], 1), torch.empty(matrix.shape[0], 3)
    t = interleaved({"mv": _kernel(True, lambda: sparse.spmm(matrix, x, out)),
                      "mm": _kernel(False, lambda: sparse.spmm(matrix, x, out)),
                      "mm, 3 columns": lambda: sparse.spmm(matrix, three, out3)}, repeats)
    vector = _kernel(True, lambda: sparse.spmm(matrix, x))()
    block = _kernel(False, lambda: sparse.spmm(matrix, x))()
    return {**{k: round(v * 1e3, 3) for k, v in t.items()},
            "difference": float((vector - block).abs().max() / block.abs().max().clamp_min(1e-30))}


def measure(name: str, repeats: int) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = cached_calibration(load_scene(name), progress=False)[0]
        targets = scene_targets(cal.rig.scene, None, cal.rig)
        op = build_operators(cal.states, targets, footprint="area", merge=False, colour_weights="channel",
                             device="cpu")[0]
    Q = op.normal_equations("matrix").Q
    row = {"scene": name, "rows": op.shape[0], "columns": op.shape[1], "nonzeros": op.val.numel(),
           "q_nonzeros": int(Q.values().numel())}
    gen = torch.Generator().manual_seed(0)
    for label, matrix in (("A", op._csr(transpose=False)), ("A^T", op._csr(transpose=True)), ("Q", Q)):
        row[label] = _products(matrix, gen, repeats * 10)
    start = solve_fista(op, BOUNDS, progress=False).patterns
    moved = op.with_rhs(op.rhs * 1.05)
    moved.normal_equations("products")
    t = interleaved({"solve, mv": _kernel(True, lambda: solve_fista(op, BOUNDS, progress=False)),
                      "solve, mm": _kernel(False, lambda: solve_fista(op, BOUNDS, progress=False)),
                      "update, mv": _kernel(True, lambda: solve_fista(moved, BOUNDS, x0=start, progress=False,
                                                                      max_iter=REFINE_SOLVER_ITERATIONS, form="products")),
                      "update, mm": _kernel(False, lambda: solve_fista(moved, BOUNDS, x0=start, progress=False,
                                                                       max_iter=REFINE_SOLVER_ITERATIONS, form="products"))},
                     repeats)
    row.update({k: round(v, 4) for k, v in t.items()})
    a = _kernel(True, lambda: solve_fista(op, BOUNDS, progress=False))()
    b = _kernel(False, lambda: solve_fista(op, BOUNDS, progress=False))()
    row["solve_objective_difference"] = abs(a.objective - b.objective) / b.objective
    row["solve_iterations"] = [a.iterations, b.iterations]
    print(row, flush=True)
    return row


def markdown(rows: list[dict], title: str) -> str:
    lines = [f"# {title}", "", "Milliseconds per product (medians, interleaved); `mv`: one column through "
             "`torch.addmv`, `mm` through `torch.addmm`; difference: the largest between their results over the "
             "result's largest value. Seconds for the solves: FISTA to the pipeline's limit from `Q`, and the "
             f"camera loop's update ({REFINE_SOLVER_ITERATIONS} iterations on `A` and `A^T`).", "",
             "| scene | nonzeros (A / Q) | A: mv / mm / mm 3 columns | A^T | Q | solve: mv / mm (s) | update: mv / mm (s) | "
             "iterations (mv / mm) | objective difference |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        cells = [f"{r[k]['mv']:.2f} / {r[k]['mm']:.2f} / {r[k]['mm, 3 columns']:.2f} ({r[k]['difference']:.1e})"
                 for k in ("A", "A^T", "Q")]
        lines.append(f"| {r['scene']} | {r['nonzeros'] / 1e6:.2f} M / {r['q_nonzeros'] / 1e6:.2f} M | " + " | ".join(cells)
                     + f" | {r['solve, mv']:.3f} / {r['solve, mm']:.3f} | {r['update, mv']:.3f} / {r['update, mm']:.3f} | "
                     f"{r['solve_iterations'][0]} / {r['solve_iterations'][1]} | {r['solve_objective_difference']:.1e} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--repeats", type=int, default=3, help="solves per kernel (products: ten times as many)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/spmv"))
    args = ap.parse_args()
    torch.set_num_threads(2)
    rows = [measure(name, args.repeats) for name in args.scenes]
    write_results(args.out, {"machine": machine(), "rows": rows}, markdown(rows, f"Sparse products, one column ({machine()})"))


if __name__ == "__main__":
    main()
