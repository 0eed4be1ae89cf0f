"""Many target sets at once: one FISTA over their right-hand sides side by side, against one set.

    python benchmarks/batch_solves.py --out benchmarks/results/batch_solves [--scale 1] [--sets 16] [--device cuda]

On the default scene (the paper's rig, full size unless ``--scale``): the calibrated area transport
(rows on camera pixels), ``--sets`` sets of two target images (scikit-image's test images in turn,
as frames of a video would differ), each set's right-hand side from ``retarget_rhs`` (no second
build), and FISTA with the pipeline's limit (300 iterations, its default tolerance) on one set and
on all of them side by side (``solve_target_sets``). Median of 3 runs each, in turn after a first, the normal equations
built beforehand (shared by every set). One iteration's two parts are timed alone: the product of ``Q``
and the element-wise pass (eager, as the solver runs it; on the CPU also the same pass written as one
expression that ``torch.compile`` fuses into one loop, and the floor of that loop: the seven blocks it
reads and writes at the rate a copy of one block moves them), each part timed in turn with the others. With ``--device cuda`` the calibration, the operator and the
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
from torchproj.transport.operator import SUM_RUN


def _pass_as_one_loop(z, qz, z_prev, qz_prev, two_q, hi, weight: float, step: float, half_step: float, out, runs):
    """``_Sweep``'s pass (the objective by runs, the extrapolation, the step, the clamp to ``[0, hi]``)
    as one expression, for ``torch.compile`` to fuse into one loop: what a fused kernel would take.
    Writes ``out`` and ``runs``; returns the partial run's sum."""
    w = (qz - two_q) * z
    flat = w.reshape(-1)
    n = runs.numel() * SUM_RUN
    runs.copy_(flat[:n].view(-1, SUM_RUN).sum(1))
    y = z_prev + weight * (z - z_prev)
    q_y = qz_prev + weight * (qz - qz_prev)
    stepped = (y - step * q_y + half_step * two_q).clamp_min(0.0)
    out.copy_(torch.minimum(stepped, hi) if torch.is_tensor(hi) else stepped.clamp_max(hi))
    return flat[n:].double().sum()


def _interleaved(runs: dict, repeats: int) -> dict[str, float]:
    """Median seconds of each of ``runs`` (after one warm-up call each), called in turn, so that a
    machine whose speed drifts (a shared host's memory bandwidth moved 14-31 GB/s within an hour
    here) weighs on each alike."""
    times = {k: [] for k in runs}
    for fn in runs.values():
        fn()
    for _ in range(repeats):
        for k, fn in runs.items():
            t0 = time.perf_counter()
            fn()
            if torch.cuda.is_available():
                torch.cuda.synchronize()  # a GPU's kernels run after the call returns
            times[k].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in times.items()}


def iteration_parts(op, fuse: bool) -> dict:
    """One FISTA iteration's two parts on ``op``'s normal equations, scaled as the solver scales them
    (ms, interleaved): the product of ``Q`` and the element-wise pass (objective, extrapolation, step,
    clamp), and the megabytes that pass reads and writes (six blocks of the patterns' size). With
    ``fuse`` (a CPU's), also the pass fused into one loop by ``torch.compile``, its largest difference
    from the eager pass's step, and its floor: the blocks it reads (five, and the upper bound where it
    is a block) and the one it writes, each at the time a copy of one block takes per block moved."""
    ne = op.normal_equations("auto").jacobi()
    sweep = _Sweep(ne, 1.0 / ne.lipschitz(), 0.0, 1.0)
    gen = torch.Generator(device=ne.q.device).manual_seed(0)
    z, previous = (sweep.block(torch.rand(ne.q.shape, generator=gen, device=ne.q.device)) for _ in range(2))
    qz, q_previous, out = sweep.block(ne.product(z[0])), sweep.block(ne.product(previous[0])), sweep.block()
    runs = {"product": lambda: ne.product(z[0], qz[0]), "pass": lambda: sweep(z, qz, previous, q_previous, 1.3, out)}
    block_mb = ne.q.numel() * ne.q.element_size() / 1e6
    extra = {}
    if fuse:
        hi = ne.bound(1.0)
        fused_out, sums = torch.empty_like(ne.q), torch.empty(ne.q.numel() // SUM_RUN, dtype=ne.q.dtype)
        args = (z[0], qz[0], previous[0], q_previous[0], ne.two_q, hi, 1.3, sweep.step, sweep.half_step, fused_out, sums)
        try:
            fused = torch.compile(_pass_as_one_loop, dynamic=True, fullgraph=True)
            t0 = time.perf_counter()
            fused(*args)
            extra["fused_compile_s"] = round(time.perf_counter() - t0, 1)
            copy = torch.empty_like(ne.q)
            runs.update(fused=lambda: fused(*args), copy=lambda: copy.copy_(qz[0]))
        except Exception as exc:  # noqa: BLE001 - no compiler here: the eager figures stand alone
            extra["fused_error"] = f"{type(exc).__name__}: {str(exc)[:200]}"
    ms = {k: round(v * 1e3, 2) for k, v in _interleaved(runs, 15).items()}
    parts = {"product": ms["product"], "pass": ms["pass"], "megabytes": 6 * block_mb, **extra}
    if "fused" in ms:
        blocks = 6 + torch.is_tensor(hi)
        parts.update(fused=ms["fused"], fused_blocks=blocks, fused_floor=round(blocks * ms["copy"] / 2, 2),
                     bandwidth_gb_s=round(2 * block_mb / ms["copy"], 1),
                     fused_max_difference=float((fused_out - out[0]).abs().max()))
    return parts


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
    solves = _interleaved({"one": lambda: solve_fista(op.with_rhs(rhs[0]), progress=False),
                           "many": lambda: solve_target_sets(op, rhs, progress=False)}, 3)
    one, many = solves["one"], solves["many"]
    _, joint = solve_target_sets(op, rhs, progress=False)
    single = solve_fista(op.with_rhs(rhs[0]), progress=False)
    fuse = args.device == "cpu"
    parts = {"one set": iteration_parts(op.with_rhs(rhs[0]), fuse),
             "all sets": iteration_parts(op.with_rhs(torch.cat(rhs, 1)), fuse)}
    result = {"machine": machine(), "device": args.device, "scale": args.scale or 1.0, "sets": args.sets, "variables": op.shape[1],
              "rows": op.shape[0], "one_set_s": round(one, 3), "all_sets_s": round(many, 3),
              "ratio": round(many / one, 2), "one_set_iterations": single.iterations,
              "all_sets_iterations": joint.iterations, "iteration_ms": parts}
    md = (f"# Target sets solved side by side ({result['machine']}, {args.device})\n\n"
          f"Command: `python benchmarks/batch_solves.py --device {args.device}`. "
          f"The paper's rig at scale {result['scale']:g}: {op.shape[1]:,} variables, {op.shape[0]:,} rows; FISTA, "
          "300 iterations at most, median of 3 in turn after a first.\n\n| sets | seconds | iterations |\n|---|---|---|\n"
          f"| 1 | {one:.2f} | {single.iterations} |\n| {args.sets} side by side | {many:.2f} | {joint.iterations} |\n\n"
          f"{args.sets} sets take {many / one:.2f}x the time of one.\n\n"
          "One iteration's parts (ms, median of 15): " + "; ".join(
              f"{k}: the product of `Q` {v['product']:.1f}, the element-wise pass {v['pass']:.1f} over "
              f"{v['megabytes']:.0f} MB" for k, v in parts.items()) + "\n" + _fused_lines(parts))
    write_results(args.out, result, md)
    print(md)


def _fused_lines(parts: dict) -> str:
    one, many = parts["one set"], parts["all sets"]
    if "fused" not in one or "fused" not in many:
        return ""
    per_iteration = {"eager": (many["product"] + many["pass"]) / (one["product"] + one["pass"]),
                     "fused": (many["product"] + many["fused"]) / (one["product"] + one["fused"]),
                     "at the fused floor": (many["product"] + many["fused_floor"]) / (one["product"] + one["pass"])}
    return ("\nThe element-wise pass fused into one loop (`torch.compile`, the same arithmetic; largest difference "
            f"from the eager step {max(one['fused_max_difference'], many['fused_max_difference']):.1e}): one set "
            f"{one['fused']:.1f} ms, all sets {many['fused']:.1f} ms; that loop's floor, its {many['fused_blocks']} blocks at "
            f"what a copy of one block moves ({one['bandwidth_gb_s']:.1f} and {many['bandwidth_gb_s']:.1f} GB/s), "
            f"{one['fused_floor']:.1f} and {many['fused_floor']:.1f} ms. "
            f"Compiling took {one['fused_compile_s']:.1f} s. One iteration of all sets over one set's: "
            + ", ".join(f"{k} {v:.2f}x" for k, v in per_iteration.items())
            + " (the last with one set's eager pass).\n")


if __name__ == "__main__":
    main()
