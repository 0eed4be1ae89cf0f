"""Many target sets at once: one FISTA over their right-hand sides side by side, against one set.

    python benchmarks/batch_solves.py --out benchmarks/results/batch_solves [--scale 1] [--sets 16] [--device cuda]

On the default scene (the paper's rig, full size unless ``--scale``): the calibrated area transport
(rows on camera pixels), ``--sets`` sets of two target images (scikit-image's test images in turn,
as frames of a video would differ), each set's right-hand side from ``retarget_rhs`` (no second
build), and FISTA with the pipeline's limit (300 iterations, its default tolerance) on one set and
on all of them side by side (``solve_target_sets``). Median of 3 runs each, in turn after a first,
the normal equations built beforehand (shared by every set); on the CPU the same solves with
``TORCHPROJ_COMPILE=1`` in turn with them (FISTA's element-wise pass compiled into one loop), and
the first compiled calls' time. One iteration's two parts are timed alone: the product of ``Q`` and
the element-wise pass (eager; on the CPU also compiled, and the floor of that loop: the seven blocks
it reads and writes at the rate a copy of one block moves them), each part timed in turn with the
others. With ``--device cuda`` the calibration, the operator and the solves run on the GPU (that is
the throughput a GPU multiplies). Writes ``results.json``, ``results.md`` and ``chart.png`` (one
iteration's parts, one set against all).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import time
from pathlib import Path

import torch
from common import interleaved, machine, write_results
from matplotlib.figure import Figure

from torchproj.core.fused import COMPILE_ENV
from torchproj.pipeline import default_images, scene_targets
from torchproj.pipeline.cache import cached_calibration
from torchproj.scene import load_scene
from torchproj.solve import solve_fista, solve_target_sets
from torchproj.solve.solvers import (
    _Sweep,  # one iteration's element-wise pass, timed alone
)
from torchproj.transport import build_transport, retarget_rhs


@contextlib.contextmanager
def _compiling(on: bool):
    """``TORCHPROJ_COMPILE`` set to ``on`` within the block (the solver reads it at each solve)."""
    before = os.environ.get(COMPILE_ENV)
    os.environ[COMPILE_ENV] = "1" if on else "0"
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(COMPILE_ENV)
        else:
            os.environ[COMPILE_ENV] = before


def _with(on: bool, fn):
    def run():
        with _compiling(on):
            return fn()
    return run


def iteration_parts(op, fuse: bool) -> dict:
    """One FISTA iteration's two parts on ``op``'s normal equations, scaled as the solver scales them
    (ms, interleaved): the product of ``Q`` and the element-wise pass (objective, extrapolation, step,
    clamp), and the megabytes that pass reads and writes (six blocks of the patterns' size). With
    ``fuse`` (a CPU's), also the pass as ``TORCHPROJ_COMPILE=1`` runs it (one compiled loop over
    whole blocks), its largest difference from the eager pass's step, and its floor: the blocks it
    reads (five, and the upper bound where it is a block) and the one it writes, each at the time a
    copy of one block takes per block moved."""
    ne = op.normal_equations("auto").jacobi()
    sweep = _Sweep(ne, 1.0 / ne.lipschitz(), 0.0, 1.0)
    gen = torch.Generator(device=ne.q.device).manual_seed(0)
    z, previous = (sweep.block(torch.rand(ne.q.shape, generator=gen, device=ne.q.device)) for _ in range(2))
    qz, q_previous, out = sweep.block(ne.product(z[0])), sweep.block(ne.product(previous[0])), sweep.block()
    runs = {"product": lambda: ne.product(z[0], qz[0]), "pass": lambda: sweep(z, qz, previous, q_previous, 1.3, out)}
    block_mb = ne.q.numel() * ne.q.element_size() / 1e6
    parts = {"megabytes": 6 * block_mb}
    if fuse:
        with _compiling(True):
            one_loop = _Sweep(ne, sweep.step, 0.0, 1.0)
        if one_loop.one_loop:
            fused_out = one_loop.block()
            t0 = time.perf_counter()
            _with(True, lambda: one_loop(z, qz, previous, q_previous, 1.3, fused_out))()
            parts["fused_first_call_s"] = round(time.perf_counter() - t0, 1)
            copy = torch.empty_like(ne.q)
            runs.update(fused=_with(True, lambda: one_loop(z, qz, previous, q_previous, 1.3, fused_out)),
                        copy=lambda: copy.copy_(qz[0]))
    ms = {k: round(v * 1e3, 2) for k, v in interleaved(runs, 15, warm_up=True).items()}
    parts.update(product=ms["product"], **{"pass": ms["pass"]})
    if "fused" in ms:
        blocks = 6 + torch.is_tensor(ne.bound(1.0))
        parts.update(fused=ms["fused"], fused_blocks=blocks, fused_floor=round(blocks * ms["copy"] / 2, 2),
                     bandwidth_gb_s=round(2 * block_mb / ms["copy"], 1),
                     fused_max_difference=float((fused_out[0] - out[0]).abs().max()))
    return parts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/batch_solves"))
    ap.add_argument("--scale", type=float, default=None)
    ap.add_argument("--sets", type=int, default=16)
    ap.add_argument("--device", default="cpu", help="torch device (default cpu)")
    ap.add_argument("--chart-from", type=Path, default=None,
                    help="only draw chart.png beside this results.json (a run's figures, not measured again)")
    args = ap.parse_args()
    if args.chart_from is not None:
        chart(args.chart_from.parent / "chart.png", json.loads(args.chart_from.read_text()))
        return
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
    fuse = args.device == "cpu"
    first_compiled = None
    if fuse:  # the compiled pass's first calls in this process (compiling, or reading inductor's cache)
        t0 = time.perf_counter()
        _with(True, lambda: (solve_fista(op.with_rhs(rhs[0]), progress=False), solve_target_sets(op, rhs, progress=False)))()
        first_compiled = time.perf_counter() - t0
    modes = (False, True) if fuse else (False,)
    solves = interleaved({(k, on): _with(on, fn) for on in modes for k, fn in (
        ("one", lambda: solve_fista(op.with_rhs(rhs[0]), progress=False)),
        ("many", lambda: solve_target_sets(op, rhs, progress=False)))}, 3, warm_up=True)
    one, many = solves[("one", False)], solves[("many", False)]
    with _compiling(False):
        _, joint = solve_target_sets(op, rhs, progress=False)
        single = solve_fista(op.with_rhs(rhs[0]), progress=False)
    parts = {"one set": iteration_parts(op.with_rhs(rhs[0]), fuse),
             "all sets": iteration_parts(op.with_rhs(torch.cat(rhs, 1)), fuse)}
    result = {"machine": machine(), "device": args.device, "scale": args.scale or 1.0, "sets": args.sets, "variables": op.shape[1],
              "rows": op.shape[0], "one_set_s": round(one, 3), "all_sets_s": round(many, 3),
              "ratio": round(many / one, 2), "one_set_iterations": single.iterations,
              "all_sets_iterations": joint.iterations, "iteration_ms": parts}
    if fuse:
        result.update(compiled_one_set_s=round(solves[("one", True)], 3), compiled_all_sets_s=round(solves[("many", True)], 3),
                      compiled_ratio=round(solves[("many", True)] / solves[("one", True)], 2),
                      compiled_first_calls_s=round(first_compiled, 1))
    md = (f"# Target sets solved side by side ({result['machine']}, {args.device})\n\n"
          f"Command: `python benchmarks/batch_solves.py --device {args.device}`. "
          f"The paper's rig at scale {result['scale']:g}: {op.shape[1]:,} variables, {op.shape[0]:,} rows; FISTA, "
          "300 iterations at most, median of 3 in turn after a first.\n\n| sets | seconds | iterations |\n|---|---|---|\n"
          f"| 1 | {one:.2f} | {single.iterations} |\n| {args.sets} side by side | {many:.2f} | {joint.iterations} |\n\n"
          f"{args.sets} sets take {many / one:.2f}x the time of one.\n\n" + _compiled_lines(result) +
          "One iteration's parts (ms, median of 15): " + "; ".join(
              f"{k}: the product of `Q` {v['product']:.1f}, the element-wise pass {v['pass']:.1f} over "
              f"{v['megabytes']:.0f} MB" for k, v in parts.items()) + "\n" + _fused_lines(parts))
    write_results(args.out, result, md)
    chart(args.out / "chart.png", result)
    print(md)


def chart(path: Path, result: dict) -> None:
    """One iteration's time, one set against all sets side by side: the product of ``Q`` and the
    element-wise pass eager, compiled (``TORCHPROJ_COMPILE=1``) and at the compiled loop's floor."""
    parts = result["iteration_ms"]
    names = [k for k in ("one set", "all sets") if k in parts]
    passes = [("pass", "element-wise pass, eager")]
    if all("fused" in parts[k] for k in names):
        passes += [("fused", "element-wise pass, compiled"), ("fused_floor", "compiled pass's floor, bytes / bandwidth")]
    fig = Figure(figsize=(7.5, 3.8), dpi=120)
    ax = fig.subplots()
    labels, y = [], 0
    for name in names:
        for key, label in passes:
            product, rest = parts[name]["product"], parts[name][key]
            ax.barh(y, product, color="#4c72b0", label="product of Q" if y == 0 else None)
            ax.barh(y, rest, left=product, color={"pass": "#dd8452", "fused": "#55a868", "fused_floor": "#c4c4c4"}[key],
                    label=label if name == names[0] else None)
            ax.text(product + rest, y, f" {product + rest:.1f}", va="center", fontsize=8)
            short = {"pass": "eager", "fused": "compiled", "fused_floor": "floor"}[key]
            labels.append(f"{name if name == 'one set' else str(result['sets']) + ' sets'}: {short}")
            y += 1
        y += 0.5
    ax.set_yticks([i + 0.5 * (i // len(passes)) for i in range(len(labels))], labels, fontsize=8)
    ax.invert_yaxis()
    longest = max(parts[k]["product"] + parts[k][key] for k in names for key, _ in passes)
    ax.set_xlim(0, longest * 1.15)
    ax.set(xlabel="ms per FISTA iteration",
           title=f"{result['sets']} target sets side by side ({result['device']}): whole solve\n"
                 f"{result['ratio']:.2f}x one set's eager"
                 + (f", {result['compiled_ratio']:.2f}x with TORCHPROJ_COMPILE=1" if "compiled_ratio" in result else ""))
    ax.title.set_fontsize(9)
    ax.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path)


def _compiled_lines(result: dict) -> str:
    if "compiled_ratio" not in result:
        return ""
    return (f"With `TORCHPROJ_COMPILE=1` (the element-wise pass compiled into one loop; the same runs, in turn with "
            f"the above): one set {result['compiled_one_set_s']:.2f} s, {result['sets']} sets "
            f"{result['compiled_all_sets_s']:.2f} s, {result['compiled_ratio']:.2f}x; the first calls of both in this "
            f"process took {result['compiled_first_calls_s']:.1f} s (compiling, or reading inductor's cache).\n\n")


def _fused_lines(parts: dict) -> str:
    one, many = parts["one set"], parts["all sets"]
    if "fused" not in one or "fused" not in many:
        return ""
    per_iteration = {"eager": (many["product"] + many["pass"]) / (one["product"] + one["pass"]),
                     "fused": (many["product"] + many["fused"]) / (one["product"] + one["fused"]),
                     "at the fused floor": (many["product"] + many["fused_floor"]) / (one["product"] + one["pass"])}
    return ("\nThe element-wise pass as `TORCHPROJ_COMPILE=1` runs it, one compiled loop (largest difference "
            f"from the eager step {max(one['fused_max_difference'], many['fused_max_difference']):.1e}): one set "
            f"{one['fused']:.1f} ms, all sets {many['fused']:.1f} ms; that loop's floor, its {many['fused_blocks']} blocks at "
            f"what a copy of one block moves ({one['bandwidth_gb_s']:.1f} and {many['bandwidth_gb_s']:.1f} GB/s), "
            f"{one['fused_floor']:.1f} and {many['fused_floor']:.1f} ms. "
            "One iteration of all sets over one set's: "
            + ", ".join(f"{k} {v:.2f}x" for k, v in per_iteration.items())
            + " (the last with one set's eager pass).\n")


if __name__ == "__main__":
    main()
