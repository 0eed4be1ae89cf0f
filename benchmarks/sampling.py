"""Does the simulated camera resolve the projector cells? Patterns solved at one supersampling, scored
at that supersampling and at a finer one, at the goal pose and a little off it.

    python benchmarks/sampling.py --out benchmarks/results/sampling

Each camera pixel is simulated by s x s point samples, each lit by the one LCD cell it falls in. If
the samples are too sparse for the cells, the solver can learn where they fall: the image looks
better than it is at the exact pose and falls apart a fraction of a millimetre away, and a finer
simulation of the same patterns scores lower. Scores are PSNR of the noise-free capture (black taken
off, divided by the target scale) against the target over its pixels, as ``torchproj run``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import torch

from common import write_results
from torchproj.pipeline import calibrate_virtual, run_virtual
from torchproj.metrics import psnr
from torchproj.scene import load_scene
from torchproj.sim import VirtualRig

CASES = [  # scene, supersampling solved at, offsets along world z (mm)
    ("box_positions", 2, (0.0, 0.5)),
    ("box_positions", 4, (0.0, 0.5)),
    ("paper_two_planes", 3, (0.0,)),
]


def _score(scene, state_surfaces, patterns, run, black, supersampling, offset_mm) -> list[float]:
    """PSNR per target with every target surface moved ``offset_mm`` along z, at this supersampling."""
    rig = VirtualRig(dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, supersampling=supersampling)))
    shown = {j: (p.float() / 255)[None] for j, p in enumerate(patterns)}
    out = []
    for k, spec in enumerate(scene.target_specs()):
        region = run.targets[k].covered
        pixels = torch.nonzero(region.reshape(-1))[:, 0]
        surfaces = []
        for name in state_surfaces[spec.state]:
            surf = scene.surfaces[name]
            pose = surf.world_from_local.copy()
            pose[2, 3] += offset_mm / 1000
            surfaces.append(dataclasses.replace(surf, world_from_local=pose))
        shot = rig.capture_surfaces(surfaces, shown, pixels, noise=False)
        estimate = ((shot - black[spec.state][:, region]) / run.report["scale"]).clamp(0, 1)
        out.append(round(psnr(estimate, run.targets[k].values[:, region]), 3))
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/sampling"))
    args = parser.parse_args(argv)
    rows = []
    for name, ss, offsets in CASES:
        t0 = time.perf_counter()
        base = load_scene(name)
        scene = dataclasses.replace(base, camera=dataclasses.replace(base.camera, supersampling=ss))
        cal = calibrate_virtual(scene)
        run = run_virtual(scene, calibration=cal)
        states = {st.name: st.surfaces for st in scene.states}
        for off in offsets:
            for eval_ss in (ss, 2 * ss):
                rows.append({"scene": name, "solved_at": ss, "scored_at": eval_ss, "offset_mm": off,
                             "targets": [s.name for s in scene.target_specs()],
                             "psnr_db": _score(scene, states, run.patterns, run, cal.black, eval_ss, off)})
                print(rows[-1], flush=True)
        rows[-1]["seconds_case"] = round(time.perf_counter() - t0, 1)
    args.out.mkdir(parents=True, exist_ok=True)
    write_results(args.out, rows)
    lines = ["# Supersampling: patterns solved at s x s samples per pixel, scored at s and 2s", "",
             f"Command: `python benchmarks/sampling.py {' '.join(argv if argv is not None else sys.argv[1:])}`", "",
             "PSNR (dB) of the noise-free capture per target; offset: every target surface moved along z.", "",
             "| scene | solved at | scored at | offset (mm) | PSNR per target |", "|---|---|---|---|---|"]
    for r in rows:
        scores = ", ".join(f"{t} {v:.2f}" for t, v in zip(r["targets"], r["psnr_db"]))
        lines.append(f"| {r['scene']} | {r['solved_at']}x{r['solved_at']} | {r['scored_at']}x{r['scored_at']} | "
                     f"{r['offset_mm']:g} | {scores} |")
    (args.out / "results.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
