"""Where the area model misses the exact light: silhouettes, and the simulator's own pixel sampling.

    python benchmarks/model_miss.py --out benchmarks/results/model_miss

Two measurements behind README's "The ceiling":

1. Silhouettes. ``box_cylinders`` is run with the simulator's exact maps (``--oracle geometry``, area
   footprint) and on the exact light (``--oracle transport``); for each target, the share of its
   squared error that lies within 2 pixels of the target's edge, where a camera pixel may see an
   object and what is behind it at once.
2. Sampling. The virtual camera integrates a pixel as ``supersampling`` x ``supersampling`` point
   samples. On the paper's planes, with the exact maps, the area model predicts a noise-free capture
   of random 2x2-cell blocks, its pixel sampled 4 x 4 (the default) or on the camera's own grid;
   and ``box_cylinders`` is run both ways.

Writes ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import torch
from common import machine, write_results
from scipy import ndimage

import torchproj.transport.build as build
from torchproj.pipeline import calibrate_virtual, run_virtual
from torchproj.scene import load_scene


def edge_share(targets) -> list[dict]:
    """Per target, its PSNR and the share of its squared error within 2 pixels of its edge."""
    rows = []
    for t in targets:
        covered = t.covered.numpy()
        error = ((t.estimate - t.values).pow(2).sum(0) * t.covered).numpy()
        edge = covered & (ndimage.distance_transform_edt(covered) <= 2)
        rows.append({"name": t.name, "psnr_db": round(t.psnr_db, 2), "ssim": round(t.ssim, 3),
                     "edge_pixels": round(float(edge.sum() / covered.sum()), 3),
                     "edge_error_share": round(float(error[edge].sum() / error[covered].sum()), 3)})
    return rows


def prediction_miss(scene_name: str, samples: int) -> dict:
    """RMS of (area model's prediction - noise-free capture) over the lit pixels, per state."""
    scene = load_scene(scene_name)
    cal = calibrate_virtual(scene, progress=False, oracle=True)
    rig, g, out = cal.rig, torch.Generator().manual_seed(0), {}
    build._AREA_SAMPLES = samples
    try:
        for name, state in cal.states.items():
            shown = [torch.rand(1, 1, p.height // 2, p.width // 2, generator=g).repeat_interleave(2, 2)
                     .repeat_interleave(2, 3) for p in scene.projectors]
            shot = rig.capture(name, dict(enumerate(shown)), noise=False, quantise=False)[0]
            dark = rig.capture(name, {}, noise=False, quantise=False)[0]
            light = []
            for j, p in enumerate(shown):
                black, white = (rig.emitted(j, torch.full_like(p, v))[0] for v in (0.0, 1.0))
                light.append(((rig.emitted(j, p)[0] - black) / (white - black)).reshape(1, *p.shape[-2:]))
            lit = state.lit()
            miss = (state.predict(light, dark, "area") - shot)[:, lit]
            out[name] = {"miss_rms": round(float(miss.pow(2).mean().sqrt()), 4),
                         "signal_std": round(float((shot - dark)[:, lit].std()), 4)}
    finally:
        build._AREA_SAMPLES = 4
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/model_miss"))
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    scene = load_scene("box_cylinders")
    grid = scene.camera.supersampling
    silhouettes = {oracle: edge_share(run_virtual(scene, progress=False, oracle=oracle).targets)
                   for oracle in ("geometry", "transport")}
    sampling = {"paper_two_planes": {n: prediction_miss("paper_two_planes", n) for n in (4, 3)}}
    runs = {}
    for n in (4, grid):
        build._AREA_SAMPLES = n
        try:
            runs[n] = {oracle: edge_share(run_virtual(scene, progress=False, oracle=oracle).targets)
                       for oracle in (False, "geometry")}
        finally:
            build._AREA_SAMPLES = 4
    lines = [f"# Where the area model misses the exact light ({machine()})", "",
             "## box_cylinders: squared error within 2 pixels of each target's edge", "",
             "| run | target | PSNR / SSIM | edge pixels | share of squared error |", "|---|---|---|---|---|"]
    for oracle, rows in silhouettes.items():
        lines += [f"| --oracle {oracle} | {r['name']} | {r['psnr_db']:.2f} / {r['ssim']:.3f} | {r['edge_pixels']:.1%} | "
                  f"{r['edge_error_share']:.1%} |" for r in rows]
    lines += ["", "## paper_two_planes, exact maps: area prediction of random light, pixel sampled n x n", "",
              "| n | state | miss (RMS) | signal (std) |", "|---|---|---|---|"]
    for n, per in sampling["paper_two_planes"].items():
        lines += [f"| {n} | {s} | {v['miss_rms']:.4f} | {v['signal_std']:.4f} |" for s, v in per.items()]
    lines += ["", f"## box_cylinders runs, area pixel sampled 4 x 4 or {grid} x {grid} (the camera's grid)", "",
              "| n | maps | per target PSNR / SSIM |", "|---|---|---|"]
    for n, per in runs.items():
        lines += [f"| {n} | {'decoded' if not oracle else 'exact'} | "
                  + "; ".join(f"{r['name']} {r['psnr_db']:.2f} / {r['ssim']:.3f}" for r in rows) + " |"
                  for oracle, rows in per.items()]
    write_results(args.out, {"machine": machine(), "silhouettes": silhouettes, "sampling": sampling,
                             "runs": {str(n): {str(k): v for k, v in per.items()} for n, per in runs.items()}},
                  "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
