"""Many target sets at once: one FISTA over their right-hand sides side by side, against one set.

    python benchmarks/batch_solves.py --out benchmarks/results/batch_solves [--scale 1] [--sets 16] [--device cuda]

On the default scene (the paper's rig, full size unless ``--scale``): the calibrated area transport
(rows on camera pixels), ``--sets`` sets of two target images (scikit-image's test images in turn,
as frames of a video would differ), each set's right-hand side from ``retarget_rhs`` (no second
build), and FISTA with the pipeline's limit (300 iterations, its default tolerance) on one set and
on all of them side by side (``solve_target_sets``). Median of 3 runs each, the normal equations
built beforehand (shared by every set). With ``--device cuda`` the calibration, the operator and the
solves run on the GPU (that is the throughput a GPU multiplies). Writes ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from pathlib import Path

import torch
from common import machine, write_results

from torchproj.pipeline import default_images, scene_targets
from torchproj.pipeline.cache import cached_calibration
from torchproj.scene import load_scene
from torchproj.solve import solve_fista, solve_target_sets
from torchproj.transport import build_transport, retarget_rhs


def timed(fn, repeats: int = 3) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        if torch.cuda.is_available():
            torch.cuda.synchronize()  # a GPU's kernels run after the call returns
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/batch_solves"))
    ap.add_argument("--scale", type=float, default=None)
    ap.add_argument("--sets", type=int, default=16)
    ap.add_argument("--device", default="cpu", help="torch device (default cpu)")
    args = ap.parse_args()
    if args.sets < 1:
        ap.error(f"--sets must be at least 1, got {args.sets}")
    scene = load_scene("paper_two_planes", scale=args.scale)
    cal, _ = cached_calibration(scene, device=args.device)
    targets = scene_targets(scene, None, cal.rig)
    op = build_transport(cal.states, targets, merge=False, footprint="area", device=args.device)
    images = default_images(5, scene.camera.channels)
    sets = [[dataclasses.replace(t, image=images[(2 * k + i) % len(images)]) for i, t in enumerate(targets)]
            for k in range(args.sets)]
    rhs = [retarget_rhs(op, cal.states, s) for s in sets]
    op.normal_equations("auto")  # built once, shared by every set
    one = timed(lambda: solve_fista(op.with_rhs(rhs[0]), progress=False))
    many = timed(lambda: solve_target_sets(op, rhs, progress=False))
    _, joint = solve_target_sets(op, rhs, progress=False)
    single = solve_fista(op.with_rhs(rhs[0]), progress=False)
    result = {"machine": machine(), "device": args.device, "scale": args.scale or 1.0, "sets": args.sets, "variables": op.shape[1],
              "rows": op.shape[0], "one_set_s": round(one, 3), "all_sets_s": round(many, 3),
              "ratio": round(many / one, 2), "one_set_iterations": single.iterations,
              "all_sets_iterations": joint.iterations}
    md = (f"# Target sets solved side by side ({result['machine']}, {args.device})\n\n"
          f"Command: `python benchmarks/batch_solves.py --device {args.device}`. "
          f"The paper's rig at scale {result['scale']:g}: {op.shape[1]:,} variables, {op.shape[0]:,} rows; FISTA, "
          "300 iterations at most, median of 3.\n\n| sets | seconds | iterations |\n|---|---|---|\n"
          f"| 1 | {one:.2f} | {single.iterations} |\n| {args.sets} side by side | {many:.2f} | {joint.iterations} |\n\n"
          f"{args.sets} sets take {many / one:.2f}x the time of one.\n")
    write_results(args.out, result, md)
    print(md)


if __name__ == "__main__":
    main()
