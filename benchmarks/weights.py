"""Three transport weights on the default scene: measured, physical geometry, and the paper's formula.

    python benchmarks/weights.py --out benchmarks/results/weights

The paper writes each entry of A as ``A(n, m) = d^2 / (L.N)`` (section "A simple linear
algebra-based pattern generation method", its equations for ``i_{k,n}`` and ``A_{k,j}``): the squared distance from the projector to the surface point over the
cosine between the surface normal and the incoming light. That is the factor by which a projector
value must be raised to give the same irradiance as at unit distance and normal incidence, the
inverse of what light does: irradiance falls as ``cos / d^2`` (Lambert and the inverse-square law;
the virtual rig's physics in docs/scenes.md). Used as the forward weight, it makes far and grazing points
brighter, not dimmer. Three weightings are compared on one calibration of ``paper_two_planes``:

- ``radiometric`` (torchproj's default): each projector's white minus black capture per camera pixel,
  which holds fall-off, angle, albedo, vignetting and brightness in one measured number;
- ``geometric``: ``max(0, N.L) / d^2`` from triangulated points and normals (``weighting="geometric"``);
- ``paper``: the paper's ``d^2 / (L.N)`` as written.

The two geometric models know nothing of brightness: each is scaled, per projector, by the median
ratio of the measured weight to it (one number, what a bench would take from one white capture), so
that all three predict camera values and share the target scale. Each is solved with FISTA, shown on
the virtual rig and scored like ``torchproj run``.

Writes ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import torch

from common import write_results
from torchproj.pipeline import calibrate_virtual, evaluate_patterns, scene_targets
from torchproj.scene import load_scene
from torchproj.solve import make_patterns
from torchproj.transport import build_transport, geometric_weights


def weightings(cal, scene) -> dict:
    """Weighting name -> per state, a StateCalibration with that weighting (brightness from the measured one)."""
    out = {"radiometric": cal.states, "geometric": {}, "paper": {}}
    for name, state in cal.states.items():
        geometric = geometric_weights(state.prj_xy, scene.camera, scene.projectors)
        paper = [torch.where(g > 0, 1.0 / g.clamp_min(1e-30), torch.zeros_like(g)) for g in geometric]
        for label, model in (("geometric", geometric), ("paper", paper)):
            scaled = []
            for measured, w in zip(state.weight, model):
                both = (w > 0) & (measured > 0)
                scaled.append(w * (measured[both] / w[both]).median())
            out[label][name] = dataclasses.replace(state, weight=scaled)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/weights"))
    parser.add_argument("--scene", default="paper_two_planes")
    args = parser.parse_args(argv)
    command = "python benchmarks/weights.py " + " ".join(argv if argv is not None else sys.argv[1:])
    scene = load_scene(args.scene)
    cal = calibrate_virtual(scene)
    targets = scene_targets(scene, rig=cal.rig)
    scale = build_transport(cal.states, targets).scale  # one target scale for all three
    rows = []
    for label, states in weightings(cal, scene).items():
        t0 = time.perf_counter()
        op = build_transport(states, targets, scale=scale)
        result, _, patterns = make_patterns(op, "fista", (0.0, 1.0), cal.responses)
        solve_s = time.perf_counter() - t0
        scores = evaluate_patterns(cal, patterns, targets, scale=scale).targets
        rows.append({"weighting": label, "build_and_solve_s": solve_s, "variables": op.shape[1],
                     "unexplained": op.unexplained(result.patterns),
                     "targets": [s.as_dict() for s in scores]})
        print(f"{label:12s} " + "  ".join(f"{s.name}: {s.psnr_db:.2f} dB SSIM {s.ssim:.3f}" for s in scores), flush=True)
    result = {"command": command, "scene": args.scene, "scale": scale, "rows": rows}
    write_results(args.out, result, markdown(result))
    print(markdown(result))
    return 0


def markdown(r: dict) -> str:
    lines = ["# Transport weights: measured, physical geometry, the paper's formula", "",
             f"Command: `{r['command']}` (scene `{r['scene']}`, FISTA 0..255, one calibration).", "",
             "`radiometric`: white minus black per pixel (default); `geometric`: max(0, N.L) / d^2; `paper`: "
             "d^2 / (L.N) as the paper writes it. The geometric two are scaled per projector by the median ratio "
             "of the measured weight to them. Scores on the virtual rig's captures, as `torchproj run`; "
             "unexplained: the share of the targets' energy the model's own optimum leaves (what the model "
             "believes, not what the capture shows).", "",
             "| weighting | target | PSNR (dB) | SSIM | affine PSNR (dB) | crosstalk | unexplained (model) |",
             "|---|---|---|---|---|---|---|"]
    for row in r["rows"]:
        for t in row["targets"]:
            lines.append(f"| {row['weighting']} | {t['name']} | {t['psnr_db']:.2f} | {t['ssim']:.3f} | "
                         f"{t['affine_psnr_db']:.2f} | {t['crosstalk']:.3f} | {row['unexplained']:.3f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
