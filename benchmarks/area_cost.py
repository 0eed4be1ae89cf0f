"""What the area model's cost over nearest's is made of, and whether its nonzeros earn it.

    python benchmarks/area_cost.py --seed 1 --count 20 --out benchmarks/results/area_cost [--chart-only]

Issue 42 asks that the area model build and solve in no more than twice nearest's time on every
suite scene. Per scene of the procedural suite (small size, calibrated once), this writes, for
``nearest`` and ``area`` as ``run`` builds and solves them: build and solve seconds (median of
``--repeats``), FISTA's iterations, seconds per iteration, nonzeros; and for area with each row's
smallest cells dropped (``pruned τ``: the cells carrying under τ of the row's light; the row's
total kept), the same with the PSNR each target loses against area itself. If the cells could go
for little loss, the model would hold more than the scene needs; if they cannot, area's nonzeros
are what its accuracy costs, and the cost ratio is bounded by them and by the iterations its wider
rows need. Writes ``results.json``, ``results.md`` and ``area_cost.png`` (each target's loss to
area against the nonzeros kept, per τ).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch
from common import machine, nonzero_rows, row_sums, with_matrix, write_results
from matplotlib.figure import Figure

from torchproj.cli_options import positive_int
from torchproj.pipeline import calibrate_virtual, evaluate_patterns, scene_targets
from torchproj.pipeline.run import build_operators
from torchproj.scene import load_scene
from torchproj.scene.procedural import suite_names
from torchproj.solve import make_patterns
from torchproj.transport import TransportOperator

BOUNDS = (0.0, 1.0)
TAUS = (0.02, 0.05)


def pruned(op: TransportOperator, tau: float) -> TransportOperator:
    """``op`` without each row's cells under ``tau`` of the row's light, the rest scaled to keep the row's total."""
    rows, total = nonzero_rows(op), row_sums(op)
    keep = op.val >= tau * total[rows]
    kept = torch.zeros_like(total).index_add_(0, rows, torch.where(keep, op.val, 0.0))
    val = (op.val * (total / kept.clamp_min(1e-30))[rows])[keep]
    crow = torch.zeros(op.shape[0] + 1, dtype=op.crow.dtype)
    crow[1:] = torch.cumsum(torch.bincount(rows[keep], minlength=op.shape[0]), 0)
    return with_matrix(op, crow, op.col[keep], val)


def timed(repeats: int, fn, *args, **kwargs):
    """``fn(*args, **kwargs)``'s last result and its median seconds over ``repeats`` calls."""
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn(*args, **kwargs)
        times.append(time.perf_counter() - t0)
    return out, statistics.median(times)


def measure(name: str, repeats: int, log=print) -> dict:
    scene = load_scene(name)
    cal = calibrate_virtual(scene, progress=False)
    targets = scene_targets(scene, None, cal.rig)
    row = {"scene": name}
    for model in ("nearest", "area"):
        ops, built = timed(repeats, build_operators, cal.states, targets, footprint=model, merge=model == "nearest",
                           colour_weights="channel", device="cpu")
        variants = [(model, ops)] + ([(f"pruned {t:g}", [pruned(o, t) for o in ops]) for t in TAUS]
                                     if model == "area" else [])
        for label, these in variants:
            (result, _, patterns), solved = timed(repeats, make_patterns, these, "fista", BOUNDS, cal.responses,
                                                  progress=False)
            scores = evaluate_patterns(cal, patterns, targets, scale=these[0].scale, paper=False).targets
            row[label] = {"build_s": round(built, 4), "solve_s": round(solved, 4), "iterations": result.iterations,
                          "per_iteration_ms": round(1000 * solved / max(result.iterations, 1), 3),
                          "nnz": sum(o.nnz for o in these), "psnr_db": [round(s.psnr_db, 3) for s in scores]}
            log(f"{name} {label}: build {built:.3f} s, solve {solved:.3f} s ({result.iterations} it), "
                f"nnz {row[label]['nnz']}, " + " / ".join(f"{p:.2f}" for p in row[label]["psnr_db"]))
    return row


def markdown(rows: list[dict], title: str) -> str:
    lines = [f"# {title}", "", "Median seconds of the repeats; ratio = area's over nearest's. `pruned τ`: area "
             "without each row's cells under τ of its light, its worst target's PSNR loss to area (dB) and the "
             "nonzeros it keeps.", "",
             "| scene | nnz ratio | build (s) nearest / area | solve (s) nearest / area | iterations nearest / area "
             "| ms per iteration nearest / area | build + solve ratio | "
             + " | ".join(f"pruned {t:g}: worst loss (dB) / nnz kept" for t in TAUS) + " |",
             "|" + "---|" * (7 + len(TAUS))]
    for r in rows:
        n, a = r["nearest"], r["area"]
        ratio = (a["build_s"] + a["solve_s"]) / (n["build_s"] + n["solve_s"])
        prunes = [f"{max(x - y for x, y in zip(a['psnr_db'], r[f'pruned {t:g}']['psnr_db'])):.2f} / "
                  f"{r[f'pruned {t:g}']['nnz'] / a['nnz']:.0%}" for t in TAUS]
        lines.append(f"| {r['scene']} | {a['nnz'] / n['nnz']:.1f} | {n['build_s']:.3f} / {a['build_s']:.3f} | "
                     f"{n['solve_s']:.3f} / {a['solve_s']:.3f} | {n['iterations']} / {a['iterations']} | "
                     f"{n['per_iteration_ms']:.2f} / {a['per_iteration_ms']:.2f} | {ratio:.2f} | " + " | ".join(prunes) + " |")
    ratios = sorted((r["area"]["build_s"] + r["area"]["solve_s"]) / (r["nearest"]["build_s"] + r["nearest"]["solve_s"])
                    for r in rows)
    build = sorted(r["area"]["build_s"] / r["nearest"]["build_s"] for r in rows)
    solve = sorted(r["area"]["solve_s"] / max(r["nearest"]["solve_s"], 1e-9) for r in rows)
    its = sorted(r["area"]["iterations"] / max(r["nearest"]["iterations"], 1) for r in rows)
    lines += ["", f"Build + solve over nearest's: median {statistics.median(ratios):.2f}, worst {ratios[-1]:.2f}; "
              f"build alone median {statistics.median(build):.1f}, solve alone median {statistics.median(solve):.1f}, "
              f"iterations median {statistics.median(its):.1f}."]
    return "\n".join(lines) + "\n"


def chart(path: Path, rows: list[dict], title: str) -> None:
    fig = Figure(figsize=(7, 4.5), dpi=120)
    ax = fig.subplots()
    for marker, t in zip("os^", TAUS):
        kept = [r[f"pruned {t:g}"]["nnz"] / r["area"]["nnz"] for r in rows for _ in r["area"]["psnr_db"]]
        loss = [x - y for r in rows for x, y in zip(r["area"]["psnr_db"], r[f"pruned {t:g}"]["psnr_db"])]
        ax.scatter(kept, loss, marker=marker, label=f"cells under {t:g} of a row's light dropped", alpha=0.7)
    ax.axhline(0, color="grey", lw=0.8)
    ax.set(xlabel="nonzeros kept (share of area's)", ylabel="PSNR lost to area (dB)", title=title)
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--count", type=positive_int, default=20)
    ap.add_argument("--repeats", type=positive_int, default=3, help="builds and solves per model (median)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/area_cost"))
    ap.add_argument("--chart-only", action="store_true", help="redraw area_cost.png from --out's results.json")
    args = ap.parse_args()
    if args.chart_only:
        result = json.loads((args.out / "results.json").read_text())
        chart(args.out / "area_cost.png", result["rows"], f"The area model's cost, suite seed {result['seed']} "
                                                          f"({result['machine']})")
        return
    rows = [measure(name, args.repeats) for name in suite_names(args.seed, args.count)]
    title = f"The area model's cost, suite seed {args.seed} ({machine()})"
    write_results(args.out, {"machine": machine(), "seed": args.seed, "taus": TAUS, "rows": rows}, markdown(rows, title))
    chart(args.out / "area_cost.png", rows, title)
    print(f"wrote {args.out}/results.json, results.md, area_cost.png")


if __name__ == "__main__":
    main()
