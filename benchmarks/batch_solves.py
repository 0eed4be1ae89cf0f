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
from torchproj.solve.solvers import _Sweep  # one iteration's element-wise pass, timed alone
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


def iteration_parts(op) -> dict:
    """One FISTA iteration's two parts on ``op``'s normal equations, scaled as the solver scales them
    (ms): the product of ``Q`` and the element-wise pass (objective, extrapolation, step, clamp),
    and the megabytes that pass reads and writes (six blocks of the patterns' size)."""
    ne = op.normal_equations("auto").jacobi()
    sweep = _Sweep(ne, 1.0 / ne.lipschitz(), 0.0, 1.0)
    gen = torch.Generator(device=ne.q.device).manual_seed(0)
    z, previous = (sweep.block(torch.rand(ne.q.shape, generator=gen, device=ne.q.device)) for _ in range(2))
    qz, q_previous, out = sweep.block(ne.product(z[0])), sweep.block(ne.product(previous[0])), sweep.block()
    product = timed(lambda: ne.product(z[0], qz[0]), repeats=15)
    step = timed(lambda: sweep(z, qz, previous, q_previous, 1.3, out), repeats=15)
    return {"product": round(product * 1e3, 2), "pass": round(step * 1e3, 2),
            "megabytes": 6 * ne.q.numel() * ne.q.element_size() / 1e6}


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
    parts = {"one set": iteration_parts(op.with_rhs(rhs[0])), "all sets": iteration_parts(op.with_rhs(torch.cat(rhs, 1)))}
    result = {"machine": machine(), "device": args.device, "scale": args.scale or 1.0, "sets": args.sets, "variables": op.shape[1],
              "rows": op.shape[0], "one_set_s": round(one, 3), "all_sets_s": round(many, 3),
              "ratio": round(many / one, 2), "one_set_iterations": single.iterations,
              "all_sets_iterations": joint.iterations, "iteration_ms": parts}
    md = (f"# Target sets solved side by side ({result['machine']}, {args.device})\n\n"
          f"Command: `python benchmarks/batch_solves.py --device {args.device}`. "
          f"The paper's rig at scale {result['scale']:g}: {op.shape[1]:,} variables, {op.shape[0]:,} rows; FISTA, "
          "300 iterations at most, median of 3.\n\n| sets | seconds | iterations |\n|---|---|---|\n"
          f"| 1 | {one:.2f} | {single.iterations} |\n| {args.sets} side by side | {many:.2f} | {joint.iterations} |\n\n"
          f"{args.sets} sets take {many / one:.2f}x the time of one.\n\n"
          "One iteration's parts (ms, median of 15): " + "; ".join(
              f"{k}: the product of `Q` {v['product']:.1f}, the element-wise pass {v['pass']:.1f} over "
              f"{v['megabytes']:.0f} MB" for k, v in parts.items()) + "\n")
    write_results(args.out, result, md)
    print(md)


if __name__ == "__main__":
    main()
