"""FISTA on the formed normal equations ``Q = A^T A`` against ``A^T (A p)`` products, per scene and model.

    python benchmarks/normal_forms.py --out benchmarks/results/normal_forms
           [--scenes paper_two_planes box_positions suite-1-0-full ...] [--scale 1] [--repeats 3]

The gradient solvers apply ``Q`` once per iteration. Formed (``matrix``), ``Q`` costs a scipy
product to build, and its coarse levels two more each; its nonzeros are every pair of cells that
share a row. As products (``products``), each iteration applies ``A`` and ``A^T``. Which is faster
depends on the model's shape: :func:`torchproj.transport.normal_form` picks, and this measures
both on each scene with the ``nearest`` and the ``area`` footprint as ``torchproj run`` builds them
(FISTA, bounds 0..255, 300 iterations at most, the same patterns to round-off), with the choice
marked. Times are the median of ``--repeats`` solves from a cold operator (nothing cached), on this
machine's CPU threads.

Writes ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from common import machine, run_operators, write_results

from torchproj.solve import solve_fista
from torchproj.transport import operator

DEFAULT_SCENES = ("paper_two_planes", "box_positions", "box_cylinders", "suite-1-0-full", "suite-1-1-full",
                  "suite-1-3-full")


def solve_cold(op, form: str) -> tuple[float, object]:
    """FISTA from an operator with no normal equations cached, on ``form``."""
    op.forget_normal_equations()
    op._blocks_device = None  # coarse levels rebuilt, as on a fresh operator
    t0 = time.perf_counter()
    result = solve_fista(op, (0.0, 1.0), max_iter=300, progress=False, form=form)
    return time.perf_counter() - t0, result


def measure(name: str, scale: float | None, repeats: int, log=print) -> list[dict]:
    rows = []
    for footprint, op in run_operators(name, scale):
        q_nnz = op.normal_equations("matrix").Q.values().numel()
        row = {"scene": name, "footprint": footprint, "rows": op.shape[0], "columns": op.shape[1], "nnz_A": op.nnz,
               "nnz_Q": q_nnz, "chosen": operator.normal_form(op)}
        for form in ("matrix", "products"):
            runs = [solve_cold(op, form) for _ in range(repeats)]
            row[f"{form}_s"] = round(statistics.median(t for t, _ in runs), 3)
            row[f"{form}_iterations"] = runs[0][1].iterations
            row[f"{form}_objective"] = runs[0][1].objective
        log(f"{name} {footprint}: rows {op.shape[0]}, columns {op.shape[1]}, nnz A {op.nnz}, Q {q_nnz}; matrix "
            f"{row['matrix_s']:.2f} s, products {row['products_s']:.2f} s; chosen {row['chosen']}")
        rows.append(row)
    return rows


def markdown(rows: list[dict]) -> str:
    lines = [f"# FISTA on Q against A^T A products ({machine()})", "",
             "Seconds from a cold operator (building Q and the coarse levels included), median of the repeats; "
             "**bold**: the form `normal_form` chooses.", "",
             "| scene | footprint | rows | columns | nnz A | nnz Q | matrix (s) | products (s) | iterations (matrix / "
             "products) | objective (matrix / products) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        m, p = f"{r['matrix_s']:.2f}", f"{r['products_s']:.2f}"
        m, p = (f"**{m}**", p) if r["chosen"] == "matrix" else (m, f"**{p}**")
        lines.append(f"| {r['scene']} | {r['footprint']} | {r['rows']} | {r['columns']} | {r['nnz_A']} | {r['nnz_Q']} "
                     f"| {m} | {p} | {r['matrix_iterations']} / {r['products_iterations']} | "
                     f"{r['matrix_objective']:.6g} / {r['products_objective']:.6g} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/normal_forms"))
    ap.add_argument("--scenes", nargs="+", default=list(DEFAULT_SCENES))
    ap.add_argument("--scale", type=float, default=None, help="resolution scale of every scene (default: as shipped)")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    rows = [r for name in args.scenes for r in measure(name, args.scale, args.repeats)]
    write_results(args.out, {"machine": machine(), "rows": rows}, markdown(rows))
    print(markdown(rows))
    print(f"wrote {args.out}/results.json, results.md")


if __name__ == "__main__":
    main()
