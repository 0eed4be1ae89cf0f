"""Whether the suite's misses are the simulator's sampling: the worst scenes again at twice the samples.

    python benchmarks/suite_sampling.py --from benchmarks/results/suite_resolved/seed_55 ... \
           --out benchmarks/results/suite_sampling [--threshold 0.8]

The virtual rig lights each of a camera pixel's s x s samples from the one LCD cell it falls in, so
a pixel's light is a sum of s^2 cells' values where a real camera integrates them. The ceiling
(``torchproj run --ceiling``) solves on exactly that light: where the samples fall far apart on a
projector's cells, it can put light where they land and nowhere else, and a calibrated model, which
sees the cells only through the captures, cannot follow. Such a gap to the ceiling would be the
simulator's, not the model's.

For every scene of the suite runs given (``benchmarks/suite.py`` outputs) with a target more than
``--threshold`` dB below its ceiling, this calibrates the scene again, as written and with twice
the camera's samples per axis (everything else the same), and measures the default model (``area``)
and the ceiling in each, as ``suite.py`` does. If a miss were the sampling, it would close at twice
the samples. Also written: each state's sample spacing (:func:`torchproj.sim.rig.sample_spacing`,
the median over the pixels of the farthest two samples fall apart on a projector's cells).

Writes ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import warnings
from pathlib import Path

from common import machine, write_results
from suite import solve_model

from torchproj.pipeline import calibrate_virtual, evaluate_patterns, scene_targets
from torchproj.scene import load_scene
from torchproj.sim.rig import sample_spacing

FACTOR = 2


def worst_scenes(folders: list[Path], threshold: float) -> list[str]:
    """The scenes of the runs in ``folders`` with an ``area`` target over ``threshold`` dB below the ceiling."""
    names = []
    for folder in folders:
        rows = json.loads((folder / "results.json").read_text())["rows"]
        names += [r["scene"] for r in rows if r["model"] == "area" and max(t["gap_db"] for t in r["targets"]) > threshold]
    return list(dict.fromkeys(names))


def measure(name: str, log=print) -> dict:
    scene = load_scene(name)
    samples = scene.camera.supersampling
    out = {"scene": name, "samples": samples, "runs": {}}
    for s in (samples, FACTOR * samples):
        world = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, supersampling=s))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cal = calibrate_virtual(world, progress=False)
            targets = scene_targets(world, None, cal.rig)
            run = {"spacing": {}}
            for state in world.states:
                geo = cal.rig.geometry(state.name)
                run["spacing"][state.name] = round(float(sample_spacing(geo.prj_xy, geo.surface_id, s).nan_to_num(0).max()), 3)
            for model in ("area", "ceiling"):
                ops, _, _, _, patterns, _ = solve_model(cal, targets, model)
                scores = evaluate_patterns(cal, patterns, targets, scale=ops[0].scale, paper=False, seed=scene.seed).targets
                run[model] = {t.name: round(t.psnr_db, 3) for t in scores}
        run["gap"] = {t: round(run["ceiling"][t] - run["area"][t], 3) for t in run["area"]}
        out["runs"][str(s)] = run
        log(f"{name} at {s} samples: " + ", ".join(f"{t} {g:+.2f}" for t, g in run["gap"].items()))
    return out


def summary(results: list[dict], threshold: float) -> dict:
    first = [g for r in results for g in r["runs"][str(r["samples"])]["gap"].values()]
    second = [g for r in results for g in r["runs"][str(FACTOR * r["samples"])]["gap"].values()]
    return {"targets": len(first), "median_gap_db": [round(statistics.median(first), 3), round(statistics.median(second), 3)],
            "over_0.5": [sum(g > 0.5 for g in first), sum(g > 0.5 for g in second)],
            f"over_{threshold}": [sum(g > threshold for g in first), sum(g > threshold for g in second)]}


def markdown(results: list[dict], total: dict, threshold: float) -> str:
    lines = [f"# The suite's worst scenes at twice the camera's samples ({machine()})", "",
             f"Scenes with a target more than {threshold} dB below the ceiling, calibrated and measured as written and "
             f"with {FACTOR}x the samples per pixel axis. Gap: the ceiling's PSNR minus the default model's (dB). "
             "Spacing: the most any state's samples fall apart on a projector's cells (median over its pixels).", "",
             f"Over {total['targets']} targets: median gap {total['median_gap_db'][0]:.2f} -> {total['median_gap_db'][1]:.2f} dB; "
             f"over 0.5 dB {total['over_0.5'][0]} -> {total['over_0.5'][1]}; over {threshold} dB "
             f"{total[f'over_{threshold}'][0]} -> {total[f'over_{threshold}'][1]}.", "",
             "| scene | samples | spacing (cells) | target | gap (dB) | ceiling (dB) | area (dB) |", "|---|---|---|---|---|---|---|"]
    for r in results:
        a, b = r["runs"][str(r["samples"])], r["runs"][str(FACTOR * r["samples"])]
        spacing = f"{max(a['spacing'].values()):.2f} -> {max(b['spacing'].values()):.2f}"
        for t in a["gap"]:
            lines.append(f"| {r['scene']} | {r['samples']} -> {FACTOR * r['samples']} | {spacing} | {t} | "
                         f"{a['gap'][t]:.2f} -> {b['gap'][t]:.2f} | {a['ceiling'][t]:.2f} -> {b['ceiling'][t]:.2f} | "
                         f"{a['area'][t]:.2f} -> {b['area'][t]:.2f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--from", dest="sources", type=Path, nargs="+", required=True, help="suite runs (benchmarks/suite.py --out)")
    ap.add_argument("--threshold", type=float, default=0.8)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/suite_sampling"))
    args = ap.parse_args()
    results = [measure(name) for name in worst_scenes(args.sources, args.threshold)]
    total = summary(results, args.threshold)
    write_results(args.out, {"machine": machine(), "factor": FACTOR, "threshold": args.threshold,
                             "sources": [str(s) for s in args.sources], "summary": total, "scenes": results},
                  markdown(results, total, args.threshold))
    print(f"wrote {args.out}/results.json, results.md")


if __name__ == "__main__":
    main()
