"""The procedural scene suite: every model against the exact-light ceiling on scenes nobody tuned for.

    python benchmarks/suite.py --seed 1 --count 20 --out benchmarks/results/suite [--size small|full]
           [--models nearest bilinear area auto] [--scenes suite-1-3 ...]

Each scene of the suite (:mod:`torchproj.scene.procedural`: seeded, 1-4 projectors, cameras whose
pixels cover 1/4 to 4 cells, solids, tilted and overlapping planes, grey and colour, defocus, one
or several states) is calibrated once from simulated captures, as ``torchproj run`` calibrates.
Each model of a camera pixel's light (``nearest``, the paper's; ``bilinear``; ``area``, the default
of ``run``; ``auto``, the least costly model whose expected loss is within a tolerance of the
richest, :func:`torchproj.pipeline.choose_footprint`) is built and solved as ``run`` builds and
solves it (FISTA, least squares, bounds 0..255; colour scenes one operator per channel), and the
patterns are scored on the rig's captures. ``ceiling`` is the same rows solved on the simulator's
own light transport (``torchproj run --ceiling``), the best any calibration could reach. Every
model's captures and the ceiling's meet the same camera noise (drawn from the scene's seed:
``evaluate_patterns(..., seed=)``), so a gap is the models' difference, not two noise draws': one
draw moves a target of a few hundred pixels by up to a decibel, and before, what else a run
measured first changed which draw each model met.

Writes ``results.json``, ``results.md`` (per scene and model: each target's PSNR / SSIM, its gap to
the ceiling, build and solve time; a summary per model), ``suite.png`` (each target's gap to the
ceiling against the model's build + solve time over nearest's) and ``scenes/NAME.yaml`` (each
scene as a config: ``torchproj run benchmarks/results/suite/scenes/suite-1-3.yaml --ceiling``
reruns one). Times are this machine's, on its CPU threads.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import yaml
from common import machine, write_results
from matplotlib.figure import Figure

from torchproj.pipeline import (CEILING_ITERATIONS, calibrate_virtual, choose_footprint, evaluate_patterns,
                                light_transport, scene_targets, solve_on_light_transport, true_responses)
from torchproj.cli_options import positive_int
from torchproj.core import InputError, check_seed
from torchproj.pipeline.run import build_operators
from torchproj.scene import load_scene
from torchproj.scene.procedural import KINDS, parse_suite_name, procedural_config, suite_names
from torchproj.solve import make_patterns

BOUNDS = (0.0, 1.0)
MODELS = ("nearest", "bilinear", "area", "auto")


def describe(scene) -> dict:
    """What kind of scene it is, in the suite's terms."""
    cam = scene.camera
    finest = max(p.fx for p in scene.projectors)
    seed, index, _ = parse_suite_name(scene.name) or (None, 0, None)
    return {"kind": KINDS[index % len(KINDS)] if seed is not None else "config",
            "projectors": len(scene.projectors), "camera": [cam.width, cam.height],
            "samples": cam.supersampling, "channels": cam.channels,
            "defocus": any(p.focus_distance is not None for p in scene.projectors),
            "states": len(scene.states), "targets": len(scene.target_specs()),
            # camera pixel width in the finest projector's cells, on a surface as far from both
            "pixel_cells": round(finest / cam.fx, 3),
            "surfaces": sorted({s.type if s.type != "sphere" or len(set(s.radii)) == 1 else "ellipsoid"
                                for s in scene.surfaces.values()})}


def solve_model(cal, targets, model: str) -> tuple:
    """Build and solve one model as ``run`` does: (operators, result, build s, solve s, patterns, the
    auto choice or None)."""
    t0 = time.perf_counter()
    choice = None
    if model == "ceiling":
        rows = build_operators(cal.states, targets, footprint="area", merge=False, colour_weights="grey",
                               device="cpu")[0]
        ops = light_transport(cal.rig, targets, rows)
    else:
        footprint = model
        if model == "auto":  # as run_virtual: the choice's time counts as building
            choice = choose_footprint(cal.states, targets, BOUNDS)
            footprint = choice.footprint
        ops = build_operators(cal.states, targets, footprint=footprint, merge=footprint == "nearest",
                              colour_weights="channel", device="cpu")
    built = time.perf_counter() - t0
    t0 = time.perf_counter()
    if model == "ceiling":
        # The projectors' own responses, as run's --ceiling: a fitted response's error is calibration's.
        result, _, patterns = solve_on_light_transport(ops, BOUNDS, true_responses(cal.rig.scene),
                                                       max_iter=CEILING_ITERATIONS)
    else:
        result, _, patterns = make_patterns(ops, "fista", BOUNDS, cal.responses, progress=False,
                                            solver_options=choice and choice.solver_options(ops, "fista"))
    return ops, result, built, time.perf_counter() - t0, patterns, choice


def measure(name: str, models: tuple[str, ...], log=print) -> list[dict]:
    scene = load_scene(name)
    t0 = time.perf_counter()
    cal = calibrate_virtual(scene, progress=False)
    calibrated = time.perf_counter() - t0
    targets = scene_targets(scene, None, cal.rig)
    about = describe(scene)
    rows = []
    for model in (*models, "ceiling"):
        ops, result, built, solved, patterns, choice = solve_model(cal, targets, model)
        scores = evaluate_patterns(cal, patterns, targets, scale=ops[0].scale, paper=False, seed=scene.seed).targets
        rows.append({"scene": name, **about, "model": model, "calibrate_s": round(calibrated, 2),
                     "variables": ops[0].shape[1], "rows": ops[0].shape[0], "nnz": sum(o.nnz for o in ops),
                     "build_s": round(built, 3), "solve_s": round(solved, 3), "iterations": result.iterations,
                     **({} if choice is None else {"chose": choice.footprint}),
                     "targets": [{"name": s.name, "pixels": s.pixels, "psnr_db": round(s.psnr_db, 3),
                                  "ssim": round(s.ssim, 4)} for s in scores]})
        if choice is not None and choice.expected_loss_db is not None:
            for t in rows[-1]["targets"]:  # auto's estimate of nearest's loss, to check against the captures
                t["nearest_expected_loss_db"] = round(choice.expected_loss_db[t["name"]], 3)
        log(f"{name} {model}: build {built:.2f} s, solve {solved:.2f} s, "
            + ", ".join(f"{t['name']} {t['psnr_db']:.2f} dB / {t['ssim']:.3f}" for t in rows[-1]["targets"]))
    top = rows[-1]
    for r in rows:
        for t, c in zip(r["targets"], top["targets"]):
            t["gap_db"] = round(c["psnr_db"] - t["psnr_db"], 3)
            t["gap_ssim"] = round(c["ssim"] - t["ssim"], 4)
    found = {r["model"]: r for r in rows}
    if {"auto", "nearest", "area"} <= set(found):  # what nearest lost to area in the captures, beside auto's estimate
        for t, near, area in zip(found["auto"]["targets"], found["nearest"]["targets"], found["area"]["targets"]):
            t["nearest_measured_loss_db"] = round(area["psnr_db"] - near["psnr_db"], 3)
    return rows


def summary(rows: list[dict]) -> list[dict]:
    """Per model: the gaps over every target of every scene, and its cost against nearest's."""
    out = []
    nearest = {r["scene"]: r["build_s"] + r["solve_s"] for r in rows if r["model"] == "nearest"}
    for model in dict.fromkeys(r["model"] for r in rows):
        if model == "ceiling":
            continue
        mine = [r for r in rows if r["model"] == model]
        gaps = [t["gap_db"] for r in mine for t in r["targets"]]
        ssim = [t["gap_ssim"] for r in mine for t in r["targets"]]
        cost = [(r["build_s"] + r["solve_s"]) / nearest[r["scene"]] for r in mine if nearest.get(r["scene"])]
        out.append({"model": model, "scenes": len(mine), "targets": len(gaps),
                    "median_gap_db": round(statistics.median(gaps), 3), "worst_gap_db": round(max(gaps), 3),
                    "within_0.5_db": round(sum(g <= 0.5 for g in gaps) / len(gaps), 3),
                    "median_gap_ssim": round(statistics.median(ssim), 4), "worst_gap_ssim": round(max(ssim), 4),
                    "within_0.02_ssim": round(sum(g <= 0.02 for g in ssim) / len(ssim), 3),
                    "median_cost_vs_nearest": round(statistics.median(cost), 2) if cost else None,
                    "worst_cost_vs_nearest": round(max(cost), 2) if cost else None})
    return out


def estimate_check(rows: list[dict]) -> str:
    """How auto's expected loss of nearest compares with what nearest lost to area in the captures."""
    pairs = [(t["nearest_expected_loss_db"], t["nearest_measured_loss_db"]) for r in rows if r["model"] == "auto"
             for t in r["targets"] if "nearest_expected_loss_db" in t and "nearest_measured_loss_db" in t]
    if not pairs:
        return ""
    lines = []
    for low, high in ((-1e9, 1.0), (1.0, 2.5), (2.5, 1e9)):
        band = [(e, m) for e, m in pairs if low <= m < high]
        if band:
            errors = [abs(e - m) for e, m in band]
            lines.append(f"measured {max(low, 0):g}-{high:g} dB: {len(band)} targets, estimate off by {statistics.median(errors):.2f} dB "
                         f"median, {max(errors):.2f} at most" if high < 1e9 else
                         f"measured over {low:g} dB: {len(band)} targets, estimate / measured {statistics.median(e / m for e, m in band):.2f} median")
    return ("auto's expected loss of nearest (from the measured shares) against the loss nearest showed to area in the "
            "captures: " + "; ".join(lines) + ".")


def markdown(rows: list[dict], totals: list[dict], title: str) -> str:
    lines = [f"# {title} ({machine()})", "",
             "Gap: the ceiling's PSNR (dB) or SSIM minus the model's, per target (negative: above the ceiling, "
             "within the captures' noise). Cost: build + solve over nearest's on the same scene.", "",
             "| model | scenes | targets | median gap (dB) | worst gap (dB) | within 0.5 dB | median SSIM gap | "
             "worst SSIM gap | within 0.02 SSIM | cost vs nearest (median / worst) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for s in totals:
        cost = "" if s["median_cost_vs_nearest"] is None else f"{s['median_cost_vs_nearest']:.2f} / {s['worst_cost_vs_nearest']:.2f}"
        lines.append(f"| {s['model']} | {s['scenes']} | {s['targets']} | {s['median_gap_db']:.2f} | {s['worst_gap_db']:.2f} "
                     f"| {s['within_0.5_db']:.0%} | {s['median_gap_ssim']:.3f} | {s['worst_gap_ssim']:.3f} "
                     f"| {s['within_0.02_ssim']:.0%} | {cost} |")
    check = estimate_check(rows)
    lines += ["", check] if check else []
    lines += ["", "| scene | kind | projectors | camera (samples) | pixel (cells) | colour | defocus | states | model "
                  "| build (s) | solve (s) | per target: PSNR (dB) / SSIM (gap dB / SSIM) |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['kind']} | {r['projectors']} | {r['camera'][0]}x{r['camera'][1]} ({r['samples']}) "
                     f"| {r['pixel_cells']:.2f} | {'yes' if r['channels'] > 1 else ''} | {'yes' if r['defocus'] else ''} "
                     f"| {r['states']} | {r['model']}{' (' + r['chose'] + ')' if 'chose' in r else ''} "
                     f"| {r['build_s']:.2f} | {r['solve_s']:.2f} | "
                     + "; ".join(f"{t['name']} {t['psnr_db']:.2f} / {t['ssim']:.3f}"
                                 + ("" if r["model"] == "ceiling" else f" ({t['gap_db']:+.2f} / {t['gap_ssim']:+.3f})")
                                 for t in r["targets"]) + " |")
    return "\n".join(lines) + "\n"


def chart(path: Path, rows: list[dict], title: str) -> None:
    """Left: each target's PSNR gap to the ceiling against the model's cost over nearest's (its build +
    solve seconds where nearest was not measured); right: the same for SSIM. One colour per model; the
    goal's 0.5 dB and 0.02 SSIM as dashed lines."""
    nearest = {r["scene"]: r["build_s"] + r["solve_s"] for r in rows if r["model"] == "nearest"}
    if not nearest:
        nearest = {r["scene"]: 1.0 for r in rows}
    fig = Figure(figsize=(12, 4.8), layout="constrained")
    fig.suptitle(f"Figure 1. {title}: gap to the exact-light ceiling against cost")
    for k, (key, unit, goal) in enumerate((("gap_db", "PSNR gap to the ceiling (dB)", 0.5),
                                           ("gap_ssim", "SSIM gap to the ceiling", 0.02))):
        ax = fig.add_subplot(1, 2, k + 1)
        for i, model in enumerate(m for m in dict.fromkeys(r["model"] for r in rows) if m != "ceiling"):
            xs, ys = [], []
            for r in rows:
                if r["model"] == model and nearest.get(r["scene"]):
                    cost = (r["build_s"] + r["solve_s"]) / nearest[r["scene"]]
                    xs += [cost] * len(r["targets"])
                    ys += [t[key] for t in r["targets"]]
            ax.scatter(xs, ys, s=14, alpha=0.7, color=f"C{i}", label=model)
        ax.axhline(goal, color="k", ls="--", lw=1, label=f"goal: {goal:g}")
        ax.axhline(0, color="0.6", lw=0.8)
        against = "/ nearest's" if any(r["model"] == "nearest" for r in rows) else "(s)"
        ax.set(xscale="log", xlabel=f"build + solve time {against} (log)", ylabel=unit)
        ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)
    fig.savefig(path, dpi=120)


def _seed(text: str) -> int:
    """A seed or an index: a whole number of 0 or more, refused before the first scene rather than at it."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    try:
        return check_seed(value, "a suite seed or index")
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=_seed, default=1, help="the suite's seed (default 1)")
    ap.add_argument("--count", type=positive_int, default=20, help="scenes from index --start (default 20)")
    ap.add_argument("--start", type=_seed, default=0, help="first scene index (default 0)")
    ap.add_argument("--size", choices=("small", "full"), default="small")
    ap.add_argument("--scenes", nargs="+", help="these scenes instead (suite names, built-in names or YAML files)")
    ap.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS,
                    help=f"models to measure (default {' '.join(MODELS)})")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/suite"))
    ap.add_argument("--chart-only", action="store_true", help="redraw suite.png from --out's results.json")
    args = ap.parse_args(argv)
    title = f"Suite seed {args.seed}, {args.size}" if not args.scenes else "Chosen scenes"
    if args.chart_only:
        chart(args.out / "suite.png", json.loads((args.out / "results.json").read_text())["rows"], title)
        return
    names = args.scenes or suite_names(args.seed, args.count, args.size, args.start)
    (args.out / "scenes").mkdir(parents=True, exist_ok=True)
    rows = []
    for name in names:
        if parse_suite_name(name):
            data = procedural_config(*parse_suite_name(name))
            (args.out / "scenes" / f"{name}.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
        rows += measure(name, tuple(args.models))
    totals = summary(rows)
    write_results(args.out, {"machine": machine(), "seed": args.seed, "size": args.size, "names": names,
                             "summary": totals, "rows": rows}, markdown(rows, totals, title))
    chart(args.out / "suite.png", rows, title)
    print(markdown(rows, totals, title).split("\n\n")[1])
    print(f"wrote {args.out}/results.json, results.md, suite.png, scenes/")


if __name__ == "__main__":
    main()
