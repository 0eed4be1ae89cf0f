"""How much of the suite's gap to the ceiling is the calibration captures' camera noise.

    python benchmarks/suite_noise.py --seed 2412 --out benchmarks/results/suite_noise/seed_2412
           [--scenes suite-2412-10 ...]

The ceiling solves on the simulator's exact light; the default model (``area``) is calibrated from
captures that carry the camera's noise (shot noise, read noise, 8-bit quantisation). Each noisy
capture puts its error into the map, the weights and the shares the rows are fitted to, and no
model of a pixel's footprint can take it out again. This calibrates every scene of a suite twice,
as written and with every calibration capture the mean of ``FRAMES`` frames (``camera.frames``,
as ``torchproj capture --frames`` takes them on a bench; the world and its geometry the same; the
noise of a capture falls by the square root of ``FRAMES``), builds and solves ``area`` on each as
``benchmarks/suite.py`` does, and scores both and the ceiling on the scene as written, with its
noise and seed, so that all three meet the same captures' noise, on the pixels all three
calibrations light. What the averaged frames close of a target's gap is the calibration noise's;
what they leave is the model's.

Writes ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import warnings
from pathlib import Path

from common import machine, write_results
from suite import solve_model

from torchproj.cli_options import positive_int
from torchproj.pipeline import calibrate_virtual, evaluate_patterns, scene_targets
from torchproj.scene import load_scene
from torchproj.scene.procedural import suite_names

FRAMES = 16
AVERAGED = f"area, calibrated from {FRAMES} frames a capture"


def measure(name: str, log=print) -> dict:
    scene = load_scene(name)
    averaged = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, frames=FRAMES))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal, cal_averaged = calibrate_virtual(scene, progress=False), calibrate_virtual(averaged, progress=False)
        targets = scene_targets(scene, None, cal.rig)
        scores = {}
        for label, calibrated, model in (("area", cal, "area"), (AVERAGED, cal_averaged, "area"),
                                         ("ceiling", cal, "ceiling")):
            ops, _, _, _, patterns, _ = solve_model(calibrated, targets, model)
            # Scored on the scene as written: its captures' noise, drawn from its seed, for all three.
            scores[label] = evaluate_patterns(cal, patterns, targets, scale=ops[0].scale, paper=False, seed=scene.seed,
                                              states=calibrated.states).targets
    # Each on the pixels all three score: a pixel about the shadow threshold's white minus black may
    # count as lit in one calibration and not the other, and such a pixel, hardly lit, is a large
    # error in a small target's score.
    psnr = {label: {} for label in scores}
    for k, target in enumerate(targets):
        common = scores["area"][k].covered & scores[AVERAGED][k].covered & scores["ceiling"][k].covered
        for label, each in scores.items():
            error = ((each[k].estimate - each[k].values) ** 2).mean(0)[common]
            psnr[label][target.name] = round(-10 * math.log10(float(error.mean())), 3)
    top = psnr["ceiling"]
    gaps = {label: {t: round(top[t] - v, 3) for t, v in values.items()} for label, values in psnr.items() if label != "ceiling"}
    log(f"{name}: " + "; ".join(f"{t} {gaps['area'][t]:+.2f} -> {gaps[AVERAGED][t]:+.2f}" for t in top))
    return {"scene": name, "psnr": psnr, "gap": gaps}


def summary(results: list[dict]) -> dict:
    out = {}
    for label in ("area", AVERAGED):
        gaps = [g for r in results for g in r["gap"][label].values()]
        out[label] = {"targets": len(gaps), "median_gap_db": round(statistics.median(gaps), 3),
                      "worst_gap_db": round(max(gaps), 3), "within_0.5_db": round(sum(g <= 0.5 for g in gaps) / len(gaps), 3),
                      "mean_gap_db": round(statistics.fmean(gaps), 3)}
    return out


def markdown(results: list[dict], total: dict, title: str) -> str:
    lines = [f"# {title}: the gap to the ceiling with averaged calibration captures ({machine()})", "",
             "Gap: the ceiling's PSNR minus the default model's (dB), every model scored on the scene as written "
             f"(its camera noise, its seed), on the pixels all three calibrations light. `{FRAMES} frames a capture`: "
             f"the same world calibrated from captures each the mean of {FRAMES} frames; what it closes is the "
             "calibration noise's.", "",
             "| calibration | targets | median gap (dB) | worst gap (dB) | within 0.5 dB | mean gap (dB) |", "|---|---|---|---|---|---|"]
    for label, s in total.items():
        lines.append(f"| {label} | {s['targets']} | {s['median_gap_db']:.2f} | {s['worst_gap_db']:.2f} | "
                     f"{s['within_0.5_db']:.0%} | {s['mean_gap_db']:.2f} |")
    lines += ["", f"| scene | target | ceiling (dB) | gap as calibrated (dB) | gap, {FRAMES} frames a capture (dB) |",
              "|---|---|---|---|---|"]
    for r in results:
        for t, top in r["psnr"]["ceiling"].items():
            lines.append(f"| {r['scene']} | {t} | {top:.2f} | {r['gap']['area'][t]:.2f} | "
                         f"{r['gap'][AVERAGED][t]:.2f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=2412)
    ap.add_argument("--count", type=positive_int, default=20)
    ap.add_argument("--scenes", nargs="+", help="these scenes instead of the seed's")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/suite_noise"))
    args = ap.parse_args()
    names = args.scenes or suite_names(args.seed, args.count)
    results = []
    for name in names:
        results.append(measure(name))
        total = summary(results)
        title = f"Suite seed {args.seed}" if not args.scenes else "Suite scenes"
        write_results(args.out, {"machine": machine(), "seed": args.seed, "names": names, "summary": total,
                                 "results": results}, markdown(results, total, title))
    print(f"wrote {args.out}/results.json, results.md")


if __name__ == "__main__":
    main()
