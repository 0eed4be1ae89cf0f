"""FISTA on the richer footprints: time to a 1e-3 gap and its ratio to the sparse-product floor.

    python benchmarks/fista_footprints.py --out benchmarks/results/fista_footprints

The setting of ``solvers.py``'s headline (``colour_two_planes`` at full size, RGB, the scene's own
targets, bounds 0..1) with the operator each footprint gives: ``nearest`` with its rows merged
(as ``solvers.py``) and ``area``, the default of ``run`` (rows not merged: they do not repeat). For
each: the time to a 1e-3 relative gap (FISTA's own history, coarse start included; median of three
runs) and that time over the Q products it needed (``model_space.floor_time``). Writes
``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import statistics
import warnings
from pathlib import Path

import numpy as np
from common import machine, write_results
from model_space import floor_time, q_products

from torchproj.pipeline import calibrate_virtual, scene_targets
from torchproj.scene import load_scene
from torchproj.solve import solve_fista
from torchproj.transport import build_transport


def to_gap(op, best: float) -> dict:
    res = solve_fista(op, (0.0, 1.0), max_iter=500, tol=0)
    hist = np.array(res.history)
    k = int(np.nonzero((hist[:, 1] - best) / best <= 1e-3)[0][0])
    coarse = sum(res.info["coarse_iterations"])
    fine = max(k - coarse, 0)
    return {"time_s": float(hist[k, 0]), "iterations": fine, "coarse_iterations": res.info["coarse_iterations"],
            "over_floor": float(hist[k, 0]) / floor_time(q_products(op), fine, res.info["coarse_iterations"])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/fista_footprints"))
    ap.add_argument("--scene", default="colour_two_planes")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    scene = load_scene(args.scene)
    cal = calibrate_virtual(scene, progress=False)
    targets = scene_targets(scene, None, cal.rig)
    rows = []
    for footprint in ("nearest", "area"):
        op = build_transport(cal.states, targets, footprint=footprint, merge=footprint == "nearest")
        best = solve_fista(op, (0.0, 1.0), max_iter=3000, tol=1e-11).objective
        runs = [to_gap(op, best) for _ in range(3)]
        mid = sorted(runs, key=lambda r: r["time_s"])[1]
        row = {"footprint": footprint, "rows": op.shape[0], "variables": op.shape[1], "nnz": op.nnz,
               "channels": op.channels, "time_to_1e-3_s": round(mid["time_s"], 3),
               "time_s_runs": [round(r["time_s"], 3) for r in runs],
               "over_floor": round(statistics.median(r["over_floor"] for r in runs), 2),
               "iterations": mid["iterations"], "coarse_iterations": mid["coarse_iterations"]}
        rows.append(row)
        print(row, flush=True)
    lines = [f"# FISTA to a 1e-3 gap per footprint ({args.scene}, full size, {rows[0]['channels']} channels, "
             f"{machine()})", "", "| footprint | rows | nnz | time to 1e-3 (s) | over the product floor | "
             "iterations (coarse) |", "|---|---|---|---|---|---|"]
    lines += [f"| {r['footprint']} | {r['rows']} | {r['nnz']} | {r['time_to_1e-3_s']:.3f} | {r['over_floor']:.2f}x | "
              f"{r['iterations']} ({', '.join(map(str, r['coarse_iterations']))}) |" for r in rows]
    write_results(args.out, {"machine": machine(), "scene": args.scene, "rows": rows}, "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
