"""The smoothness penalty's weight on the procedural suite: each target's gap to the ceiling per weight.

    python benchmarks/smoothness.py --seeds 55 97 --weights 0 0.0001 0.0002 0.0003 --column-weights 0.001 \
        --out benchmarks/results/smoothness [--count 20] [--scenes paper_two_planes ...]

Each suite scene is calibrated once, as ``torchproj run`` calibrates; its area model is built once
and solved with FISTA at each weight of :meth:`TransportOperator.with_smoothness` (0: the plain box
least squares; ``lam`` = weight x the target scale squared) and at each ``--column-weights`` weight
(``lam`` = weight x A's mean squared column norm, the rule of ed02fe1: the same relative penalty on
every scene, whatever its pixels per cell); the ceiling is the same rows solved on the simulator's
own light transport, as ``benchmarks/suite.py`` solves it. Every solve's patterns meet the same
camera noise (the scene's seed, ``evaluate_patterns(..., seed=)``), so a gap is the weights'
difference and not two noise draws'. The column rule's weight was chosen on seeds 55 and 97 and
checked on 1, 8080, 56 and 4321; the scale rule's on those six, and checked on 2718, 314, 777, 1234
and 31337.

Writes ``results.json`` (per scene, weight and target: pixels, PSNR, gap to the ceiling; solve
seconds), ``results.md`` (per seed and weight: median, mean and worst gap, the share of targets
within 0.5 dB, the summed solve time) and ``smoothness.png`` (each target's gap at the chosen weight
against its gap without the penalty).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch
from common import machine, write_results
from matplotlib.figure import Figure
from suite import solve_model

from torchproj.core.choices import DEFAULT_SMOOTHNESS
from torchproj.pipeline import calibrate_virtual, evaluate_patterns, scene_targets
from torchproj.pipeline.run import build_operators
from torchproj.scene import load_scene
from torchproj.scene.procedural import suite_names
from torchproj.solve import make_patterns

BOUNDS = (0.0, 1.0)


def pixels_per_cell(op) -> float:
    """The model's mean squared column norm over the camera value a target of 1 asks for, squared: about
    how many camera pixels see a cell whole (under 1 where cells are finer than the pixels)."""
    norms = torch.zeros(op.shape[1], dtype=torch.float64).index_add_(0, op.col.long(), op.val.double().pow(2))
    return float(norms.mean()) / op.scale ** 2


def measure(name: str, weights: list[float], column_weights: list[float] = (), log=print) -> list[dict]:
    """Per weight, each target's gap. ``weights`` are :meth:`TransportOperator.with_smoothness`'s (``lam``
    over the target scale squared); ``column_weights`` are over A's mean squared column norm instead
    (the rule of ed02fe1, the same relative penalty on every scene), each converted for this scene by
    :func:`pixels_per_cell`."""
    scene = load_scene(name)
    cal = calibrate_virtual(scene, progress=False)
    targets = scene_targets(scene, None, cal.rig)
    ceiling = solve_model(cal, targets, "ceiling")
    top = evaluate_patterns(cal, ceiling[4], targets, scale=ceiling[0][0].scale, paper=False, seed=scene.seed).targets
    ops = build_operators(cal.states, targets, footprint="area", merge=False, colour_weights="channel", device="cpu")
    density = pixels_per_cell(ops[0])
    rows = []
    for rule, asked in [*(("scale", w) for w in weights), *(("columns", w) for w in column_weights)]:
        weight = asked if rule == "scale" else asked * density
        t0 = time.perf_counter()
        _, _, patterns = make_patterns(ops, "fista", BOUNDS, cal.responses, progress=False, smoothness=weight)
        solved = time.perf_counter() - t0
        scores = evaluate_patterns(cal, patterns, targets, scale=ops[0].scale, paper=False, seed=scene.seed).targets
        rows.append({"scene": name, "rule": rule, "asked": asked, "weight": weight, "pixels_per_cell": round(density, 4),
                     "solve_s": round(solved, 3),
                     "targets": [{"name": s.name, "pixels": s.pixels, "psnr_db": round(s.psnr_db, 3),
                                  "ceiling_db": round(c.psnr_db, 3), "gap_db": round(c.psnr_db - s.psnr_db, 3)}
                                 for s, c in zip(scores, top)]})
        log(f"{name} weight {asked:g} over the {rule} ({weight:.3g} over the scale): solve {solved:.2f} s, gaps "
            + ", ".join(f"{t['gap_db']:.2f}" for t in rows[-1]["targets"]))
    return rows


def summary(rows: list[dict], seeds: list[int], rules: list[tuple[str, float]]) -> list[dict]:
    out = []
    for seed in [*seeds, None]:
        for rule, weight in rules:
            mine = [r for r in rows if (r["rule"], r["asked"]) == (rule, weight) and (seed is None or r["seed"] == seed)]
            gaps = [t["gap_db"] for r in mine for t in r["targets"]]
            if gaps:
                out.append({"seed": "all" if seed is None else seed, "rule": rule, "weight": weight, "targets": len(gaps),
                            "median_gap_db": round(statistics.median(gaps), 3),
                            "mean_gap_db": round(statistics.mean(gaps), 3), "worst_gap_db": round(max(gaps), 2),
                            "within_half_db": round(sum(g <= 0.5 for g in gaps) / len(gaps), 3),
                            "solve_s": round(sum(r["solve_s"] for r in mine), 2)})
    return out


def markdown(totals: list[dict]) -> str:
    lines = ["# The smoothness penalty's weight (area model, FISTA)", "",
             "Gap: the ceiling's PSNR minus the weight's, per target, under one noise draw for both. Weight over: "
             "`scale`, the target scale squared (`with_smoothness`); `columns`, A's mean squared column norm.", "",
             "| seed | weight over | weight | targets | median gap (dB) | mean | worst | within 0.5 dB | solve s (summed) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for t in totals:
        lines.append(f"| {t['seed']} | {t['rule']} | {t['weight']:g} | {t['targets']} | {t['median_gap_db']:.3f} | "
                     f"{t['mean_gap_db']:.3f} | {t['worst_gap_db']:.2f} | {t['within_half_db']:.0%} | {t['solve_s']:.1f} |")
    return "\n".join(lines) + "\n"


def chart(path: Path, rows: list[dict], weight: float) -> None:
    plain = {(r["scene"], t["name"]): t["gap_db"] for r in rows if r["weight"] == 0 for t in r["targets"]}
    chosen = [(plain[(r["scene"], t["name"])], t["gap_db"]) for r in rows if (r["rule"], r["asked"]) == ("scale", weight)
              for t in r["targets"] if (r["scene"], t["name"]) in plain]
    if not chosen:
        return
    fig = Figure(figsize=(5.5, 5))
    ax = fig.subplots()
    ax.scatter([a for a, _ in chosen], [b for _, b in chosen], s=10, alpha=0.6)
    top = max(max(a, b) for a, b in chosen) + 0.3
    ax.plot([-0.2, top], [-0.2, top], color="grey", lw=0.8)
    ax.set_xlabel("gap to the ceiling without the penalty (dB)")
    ax.set_ylabel(f"gap with smoothness {weight:g} (dB)")
    ax.set_title("Each suite target: below the line, the penalty helped")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[55, 97])
    ap.add_argument("--count", type=int, default=20, help="scenes per seed (default 20)")
    ap.add_argument("--scenes", nargs="+", help="these scenes instead of the seeds' (built-in names or YAML files)")
    ap.add_argument("--weights", type=float, nargs="+", default=[0.0, 0.0001, DEFAULT_SMOOTHNESS, 0.0003])
    ap.add_argument("--column-weights", type=float, nargs="*", default=[0.001],
                    help="weights over A's mean squared column norm (the rule of ed02fe1), converted per scene")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/smoothness"))
    args = ap.parse_args()
    weights = sorted({0.0, *args.weights})
    rules = [*(("scale", w) for w in weights), *(("columns", w) for w in args.column_weights)]
    rows = []
    groups = {"chosen": args.scenes} if args.scenes else {seed: suite_names(seed, args.count, "small")
                                                           for seed in args.seeds}
    for group, names in groups.items():
        for name in names:
            rows += [{**r, "seed": group} for r in measure(name, weights, args.column_weights)]
    totals = summary(rows, list(groups), rules)
    write_results(args.out, {"machine": machine(), "seeds": list(groups), "weights": weights,
                             "column_weights": args.column_weights, "summary": totals,
                             "rows": rows}, markdown(totals))
    chart(args.out / "smoothness.png", rows, DEFAULT_SMOOTHNESS if DEFAULT_SMOOTHNESS in weights else weights[-1])
    print(markdown(totals))
    print(f"wrote {args.out}/results.json, results.md, smoothness.png")


if __name__ == "__main__":
    main()
