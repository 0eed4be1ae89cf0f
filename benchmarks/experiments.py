"""The paper's experiments (section 5) on the virtual rig, and what calibration costs.

    python benchmarks/experiments.py --out benchmarks/results/experiments

For each built-in scene (two planes in grey and in colour, three planes with three simple patterns,
the head-like object wearing a different mask at two positions, the box behind two cylinders with
one image on each, two screens at once), the scene is calibrated from simulated captures and solved
with FISTA (torchproj's default), with the paper's LF and EO_0^255 (its non-planar experiments compare
those two), and with FISTA on the oracle operator (the simulator's exact geometry: the gap is what
calibration costs). Every number is scored on
simulated captures. Then the depth-selectivity sweep: with the two-plane patterns fixed, the near
plane moves from 0.65 m to 1.15 m and each target image is scored on it at every depth.

Writes ``results.json``, ``results.md``, ``depth_selectivity.png`` and one ``<scene>.png`` overview
per scene and method (``<scene>.png`` for FISTA, ``<scene>_lf.png``, ``<scene>_eo.png``: targets, patterns,
captures side by side).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from common import write_results
from torchproj.pipeline import calibrate_virtual, run_virtual
from torchproj.experiments import depth_sweep
from torchproj.figures import depth_selectivity, run_overview
from torchproj.scene import load_scene

SCENES = ["paper_two_planes", "colour_two_planes", "three_planes", "head_two_positions", "box_cylinders",
          "two_screens"]
METHODS = [("FISTA", dict(solver="fista")), ("LF", dict(solver="lf")), ("EO_0^255", dict(solver="eo")),
           ("FISTA oracle", dict(solver="fista", oracle=True))]
OVERVIEW = {"FISTA": "", "LF": "_lf", "EO_0^255": "_eo"}  # the overview image of each method, by file suffix


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/experiments"))
    parser.add_argument("--scenes", nargs="+", default=SCENES, help="scene names or YAML paths")
    parser.add_argument("--depths", type=int, default=21, help="depths in the selectivity sweep (0: skip it)")
    parser.add_argument("--sweep-scene", default="paper_two_planes", help="scene whose near_plane the sweep moves")
    args = parser.parse_args(argv)
    command = "python benchmarks/experiments.py " + " ".join(argv if argv is not None else sys.argv[1:])
    args.out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    rows, sweeps = [], {}
    for name in args.scenes:
        scene = load_scene(name)
        cal = calibrate_virtual(scene)
        oracle = calibrate_virtual(scene, oracle=True)
        for label, kw in METHODS:
            kw = dict(kw)
            res = run_virtual(scene, calibration=oracle if kw.pop("oracle", False) else cal, **kw)
            rep = res.report
            rows.append({"scene": scene.name, "method": label, "calibrate_s": round(cal.seconds, 2),
                         "solve_s": rep["timings_s"]["solve"], "model": rep["model"], "targets": rep["targets"]})
            print(f"{scene.name:20s} {label:13s} " + "  ".join(
                f"{t['name']}: {t['psnr_db']:.2f} dB SSIM {t['ssim']:.3f} xt {t['crosstalk']:.2f}"
                for t in rep["targets"]) + f"  solve {rep['timings_s']['solve']:.1f} s", flush=True)
            if label in OVERVIEW:
                run_overview(args.out / f"{scene.name}{OVERVIEW[label]}.png", res.patterns,
                             [p.name for p in scene.projectors], res.targets)
            if scene.name == args.sweep_scene and args.depths and label != "FISTA oracle":
                depths = np.linspace(0.65, 1.15, args.depths)
                sweeps[label] = depth_sweep(scene, "near_plane", depths, res.patterns, res.targets, res.report["scale"])
    result = {"command": command, "total_s": round(time.perf_counter() - t_start, 1), "rows": rows,
              "depth_sweep": {k: v.as_dict() for k, v in sweeps.items()}}
    if sweeps:
        depth_selectivity(args.out / "depth_selectivity.png", sweeps, {"near": 0.8, "far": 1.0})
    write_results(args.out, result, markdown(result))
    print(markdown(result))
    return 0


def markdown(r: dict) -> str:
    lines = ["# The paper's experiments on the virtual rig", "",
             f"Command: `{r['command']}` ({r['total_s']:.0f} s in all).", "",
             "Scored on simulated captures: PSNR (dB, data range 1) and SSIM of the captured image against the "
             "target on the camera pixels of the target's surfaces that calibration found lit; crosstalk is the "
             "largest |correlation| there with another target's image. `FISTA oracle` solves on the simulator's "
             "exact geometry instead of calibration. Affine PSNR: after the capture's best gain and offset; paper: "
             "PSNR / SSIM against a capture of the target image projected alone by one projector (the paper's "
             "protocol).", "",
             "| scene | method | target | PSNR (dB) | SSIM | crosstalk | affine PSNR (dB) | paper PSNR / SSIM | variables | "
             "solve (s) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for row in r["rows"]:
        for t in row["targets"]:
            lines.append(f"| {row['scene']} | {row['method']} | {t['name']} | {t['psnr_db']:.2f} | {t['ssim']:.3f} | "
                         f"{t['crosstalk']:.3f} | {t['affine_psnr_db']:.2f} | {t['paper']['psnr_db']:.2f} / "
                         f"{t['paper']['ssim']:.3f} | {row['model']['variables']} | {row['solve_s']:.2f} |")
    if r["depth_sweep"]:
        lines += ["", "## Depth selectivity (two-plane patterns, near plane moved through depth)", "",
                  "PSNR (dB) of each target image on the moved plane; the near image belongs at 0.80 m, the far "
                  "one at 1.00 m. Chart: `depth_selectivity.png`.", ""]
        for label, sw in r["depth_sweep"].items():
            lines += [f"### {label}", "", "| depth (m) | " + " | ".join(f"{n} PSNR | {n} SSIM" for n in sw["names"]) + " |",
                      "|---" * (1 + 2 * len(sw["names"])) + "|"]
            for i, z in enumerate(sw["depths_m"]):
                cells = ["- | -" if sw["psnr_db"][i][k] is None else f"{sw['psnr_db'][i][k]:.2f} | {sw['ssim'][i][k]:.3f}"
                         for k in range(len(sw["names"]))]
                lines.append(f"| {z:.3f} | " + " | ".join(cells) + " |")
            lines.append("")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
