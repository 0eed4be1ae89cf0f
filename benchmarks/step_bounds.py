"""How tight, and whether a bound at all, the gradient solvers' step bound is, per scene, model and level.

    python benchmarks/step_bounds.py --out benchmarks/results/step_bounds
           [--scenes paper_two_planes box_positions suite-11-0 ...] [--products 5 10 15 20 30]

FISTA and PGD step ``1 / L`` on the Jacobi-scaled normal equations (and on each coarse level's),
which is safe only where ``L`` is at least the largest eigenvalue of ``Q``.
:meth:`torchproj.transport.operator.NormalEquations.lipschitz` finds it by power iteration. This
measures it against scipy's ``eigsh`` (ARPACK, float64, relative tolerance 1e-4: the nearest
model's eigenvalues cluster at its top, where 1e-6 takes minutes) for each scene as ``torchproj
run`` builds it (``nearest`` merged, ``area`` on camera pixels), on the full level and the three
coarse levels of :meth:`~torchproj.transport.TransportOperator.coarse_levels`:

- ``5% margin``: the power iteration's estimate after 30 products times 1.05, the rule the solvers
  used wherever the power vector had a zero (a projector cell no row sees): below 1 it is no bound.
- ``CW k``: the Collatz-Wielandt bound ``max_i (Q x)_i / x_i`` over the columns with an entry after
  ``k`` products, a bound whatever ``k`` (``Q`` is a Gram matrix with no negative entry: a column
  without an entry is a zero row, eigenvalue 0); larger than 1 by how much shorter each step is.

Writes ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from common import machine, run_operators, write_results

from torchproj.transport.operator import _to_scipy

DEFAULT_SCENES = ("paper_two_planes", "box_positions", "box_cylinders", "sphere_three_projectors",
                  "suite-11-0", "suite-11-1", "suite-11-2", "suite-11-3", "suite-11-4", "suite-11-5")


def largest_eigenvalue(ne) -> float:
    from scipy.sparse.linalg import eigsh

    return float(eigsh(_to_scipy(ne.Q, torch.float64), k=1, which="LA", tol=1e-4, return_eigenvectors=False)[0])


def power_bounds(ne, products: list[int]) -> dict:
    """The margin rule's estimate and the Collatz-Wielandt bound after each of ``products`` products."""
    x = torch.ones(ne.q.shape[0], 1, dtype=ne.q.dtype)
    out = {}
    seen = None
    for k in range(max(products) + 1):
        y = ne.product(x)
        if k == 0:
            seen = y[:, 0] > 0
        if k in products:
            out[f"CW {k}"] = float((y[seen] / x[seen]).max()) if bool((x[seen] > 0).all()) else float("nan")
        if k == 30:
            out["5% margin"] = 1.05 * float(y.norm() / x.norm())
        x = y / y.norm().clamp_min(1e-30)
    return out


def measure(name: str, products: list[int], log=print) -> list[dict]:
    rows = []
    for footprint, op in run_operators(name):
        levels = [("full", op.normal_equations("matrix"))]
        levels += [(f"coarse {k}", ne) for k, (ne, _) in enumerate(op.coarse_levels(3, "matrix"))]
        for level, ne in levels:
            scaled = ne.jacobi()
            lam = largest_eigenvalue(scaled)
            bounds = power_bounds(scaled, products)
            unseen = int((scaled.scale[:, 0] > 1e14).sum())
            row = {"scene": name, "footprint": footprint, "level": level, "columns": scaled.q.shape[0],
                   "unseen columns": unseen, "eigenvalue": lam, **{k: v / lam for k, v in bounds.items()}}
            rows.append(row)
            log(" ".join(f"{k}={v:.4f}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()))
    return rows


def markdown(rows: list[dict], products: list[int]) -> str:
    keys = ["5% margin"] + [f"CW {k}" for k in products]
    lines = [f"Machine: {machine()}", "",
             "Each bound over the largest eigenvalue of the Jacobi-scaled `Q` (scipy `eigsh`): below 1 is no "
             "bound (a step longer than FISTA's 1 / L allows); above 1, how much shorter each step is.", "",
             "| scene | model | level | columns | unseen | eigenvalue | " + " | ".join(keys) + " |",
             "|---" * (6 + len(keys)) + "|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['footprint']} | {r['level']} | {r['columns']} | {r['unseen columns']} | "
                     f"{r['eigenvalue']:.4f} | " + " | ".join(f"{r[k]:.4f}" for k in keys) + " |")
    lines += ["", "Worst over every row: " + ", ".join(
        f"{k} {min(r[k] for r in rows):.4f}-{max(r[k] for r in rows):.4f}" for k in keys)]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/step_bounds"))
    parser.add_argument("--scenes", nargs="+", default=list(DEFAULT_SCENES))
    parser.add_argument("--products", nargs="+", type=int, default=[5, 10, 15, 20, 30])
    args = parser.parse_args()
    rows = []
    for name in args.scenes:
        rows += measure(name, sorted(set(args.products)))
    write_results(args.out, {"machine": machine(), "rows": rows}, markdown(rows, sorted(set(args.products))))


if __name__ == "__main__":
    main()
