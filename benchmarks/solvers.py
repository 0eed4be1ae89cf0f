"""Speed against accuracy: every solver along its iterations, on the paper's rig at three sizes (RGB).

    python benchmarks/solvers.py --out benchmarks/results/solvers

For the paper's two-plane rig with an RGB camera (``colour_two_planes``: per-primary responses,
tinted planes) and projectors at quarter, half and full resolution (256x192, 512x384, 1024x768; the
camera scaled alike, fields of view kept), calibrated on the virtual rig,
with astronaut on the near plane and chelsea on the far one (RGB): the objective gap to the best
optimum found, model-space PSNR (``A p / scale`` against the targets), and PSNR / SSIM of the simulated
captures of the compensated patterns, against wall time. Methods: LF, EO at both bounds, clamped Adam
at three learning rates, projected gradient, FISTA, and scipy's ``lsq_linear`` on one channel as the
outside reference (on channel 0, against FISTA on the same channel and on all three). Also the
floor (one sparse product, 3 channels, at full size and at each of FISTA's coarse levels), each
method's time over the products it needed at those times, the time to a 1e-3 relative gap (median
of 5 runs, the floor timed before each) with and without FISTA's coarse start, the one-off setup
per rig, peak memory of that solve, the CUDA path where a GPU is present, and the
model's size with and without its reductions (variables only for lit projector cells; rows merged
where they share columns; both leave the objective unchanged).

Writes ``results.json``, ``results.md``, ``pareto.png`` (PSNR against log time, one panel per size)
and ``scaling.png`` (time and memory against problem size).

    python benchmarks/solvers.py --cuda-only --out benchmarks/results/solvers/cuda

on a machine with a GPU times the CUDA section alone at each size (the rig calibrated and the operator
built on the GPU, the best objective from FISTA to tol 1e-11 there), for a lease too short for the rest.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from scipy.optimize import lsq_linear  # noqa: E402
from scipy.sparse import csr_matrix  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine, median_time, write_results  # noqa: E402
from model_space import floor_time, image, product_floor, q_products  # noqa: E402
from stability import small  # noqa: E402

from torchproj.pipeline import calibrate_virtual, evaluate_patterns  # noqa: E402
from torchproj.metrics import model_space_psnr  # noqa: E402
from torchproj.scene import parse_scene  # noqa: E402
from torchproj.solve import (projectable_patterns, solve_adam, solve_eo, solve_fista, solve_lf,  # noqa: E402
                             solve_pgd, to_projectable)
from torchproj.transport import Target, build_transport  # noqa: E402

SIZES = {"quarter": ((256, 192), (400, 300)), "half": ((512, 384), (800, 600)), "full": ((1024, 768), (1600, 1200))}
NEG = -100 / 255


def peak_rss_reset() -> None:
    """Reset the process's peak resident memory (Linux: clear_refs 5), so the next peak is one step's."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def peak_rss_gb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024**2
    return float("nan")


def captured(cal, op, targets, p, bounds) -> tuple[list[float], list[float]]:
    """PSNR and SSIM per target of the virtual rig's capture of the compensated patterns."""
    scores = evaluate_patterns(cal, projectable_patterns(op, p, bounds, cal.responses)[1], targets,
                               scale=op.scale).targets
    return [round(t.psnr_db, 3) for t in scores], [round(t.ssim, 4) for t in scores]


def run_size(label: str, projector, camera, log=print) -> dict:
    scene = parse_scene(small("colour_two_planes", camera=camera, projector=projector), name=f"colour_{label}")
    t0 = time.perf_counter()
    cal = calibrate_virtual(scene)
    t_cal = time.perf_counter() - t0
    targets = [Target("near", image("astronaut"), name="astronaut"), Target("far", image("chelsea"), name="chelsea")]
    t0 = time.perf_counter()
    op = build_transport(cal.states, targets, merge=True)
    t_build = time.perf_counter() - t0
    full = build_transport(cal.states, targets, merge=False, scale=op.scale)
    cells = sum(w * h for w, h in op.projector_sizes)
    # FISTA's one-off work per rig, shared by every set of targets (with_rhs): Q = A^T A, its Jacobi
    # scaling and Lipschitz bound, and the coarse levels (cells tied in 2x2, 4x4, 8x8 blocks).
    t0 = time.perf_counter()
    ne = op.normal_equations()
    ne.jacobi().lipschitz()
    t_normal = time.perf_counter() - t0
    t0 = time.perf_counter()
    levels = [level for level, _ in op.coarse_levels(3)]
    for level in levels:
        level.jacobi().lipschitz()
    setup = {"normal_equations_s": round(t_normal, 3), "coarse_levels_s": round(time.perf_counter() - t0, 3),
             "coarse_columns": [level.Q.shape[0] for level in levels]}
    x = torch.rand(op.shape[1], 3)
    floor = product_floor(op)

    best = {b: solve_fista(op, b, max_iter=3000, tol=1e-11).objective for b in ((0.0, 1.0), (NEG, 1.0))}
    rows = []

    def record(method, res, bounds, proximal=False, with_capture=True, projectable=None):
        p = res.patterns if projectable is None else projectable
        gap = (res.objective - best[bounds]) / best[bounds]
        row = {"method": method, "bounds_8bit": [round(b * 255) for b in bounds], "time_s": round(res.time_s, 4),
               "iterations": res.iterations, "relative_gap": gap, "model_psnr_db": model_space_psnr(full, p)}
        if proximal:
            products = floor_time(floor, res.iterations, res.info["coarse_iterations"])
            row["time_over_floor"] = round(res.time_s / products, 3)
            row["coarse_iterations"] = res.info["coarse_iterations"]
        if with_capture:
            row["capture_psnr_db"], row["capture_ssim"] = captured(cal, op, targets, res.patterns, bounds)
        rows.append(row)
        log(f"{label:8s} {method:30s} {res.time_s:8.3f} s gap {gap:9.2e} model PSNR "
            + " / ".join(f"{v:.2f}" for v in row["model_psnr_db"])
            + (" capture " + " / ".join(f"{v:.2f}" for v in row["capture_psnr_db"]) if with_capture else ""))

    for it in (2, 5, 10, 20, 30, 50, 100):
        record(f"FISTA {it} it", solve_fista(op, (0, 1), max_iter=it, tol=0), (0.0, 1.0), proximal=True,
               with_capture=it in (5, 20, 100))
    for it in (10, 20, 30, 50, 100):
        record(f"FISTA without coarse start {it} it", solve_fista(op, (0, 1), max_iter=it, tol=0, levels=0),
               (0.0, 1.0), proximal=True, with_capture=False)
    for it in (10, 30, 100, 300):
        record(f"PGD {it} it", solve_pgd(op, (0, 1), max_iter=it, tol=0), (0.0, 1.0), proximal=True,
               with_capture=it == 300)
    solve_adam(op, (0, 1), max_iter=2)  # autograd's first call sets itself up: keep that out of the timings
    for lr in (0.005, 0.02, 0.1):
        for it in (50, 200):
            record(f"Adam lr {lr} {it} it", solve_adam(op, (0, 1), lr=lr, max_iter=it, tol=0), (0.0, 1.0),
                   with_capture=it == 200)
    record("LF", solve_lf(op, (0, 1)), (0.0, 1.0))
    record("EO_0^255", solve_eo(op, (0, 1), calibrations=cal.states, max_iter=1000, tol=1e-6), (0.0, 1.0))
    res = solve_eo(op, (NEG, 1), calibrations=cal.states, max_iter=1000, tol=1e-6)
    # Shown through the linear map, as when this table was recorded (image_quality.py measures map and clip).
    record("EO_-100^255", res, (NEG, 1.0), projectable=to_projectable(res.patterns, (NEG, 1.0), "map"))

    # Time to a 1e-3 relative gap (FISTA's own history, through its coarse levels; the median of five
    # runs, as timings on this machine vary by 10-50%) and the peak memory of that solve; and the
    # same without the coarse start.
    def to_gap(res, target_best, run_floor):
        hist = np.array(res.history)
        reached = np.nonzero((hist[:, 1] - target_best) / target_best <= 1e-3)[0]
        if not len(reached):
            return {"time_s": None, "iterations": None}, hist
        k = int(reached[0])
        coarse = sum(res.info["coarse_iterations"])
        fine = max(k - coarse, 0)
        out = {"time_s": float(hist[k, 0]), "iterations": fine, "coarse_iterations": res.info["coarse_iterations"]}
        if k >= coarse:
            out["time_over_floor"] = out["time_s"] / floor_time(run_floor, fine, res.info["coarse_iterations"])
        return out, hist

    def repeated_to_gap(solve, target_best, the_op, repeats=5):
        # The floor is timed again just before each run: this machine's speed drifts between runs, and
        # a floor timed minutes apart from the solve mixes that drift into the ratio.
        runs = [to_gap(solve(), target_best, q_products(the_op)) for _ in range(repeats)]
        if any(r["time_s"] is None for r, _ in runs):
            return runs[0]
        out, hist = sorted(runs, key=lambda r: r[0]["time_s"])[repeats // 2]
        out = dict(out, time_s_runs=[round(r["time_s"], 4) for r, _ in runs])
        ratios = [r["time_over_floor"] for r, _ in runs if "time_over_floor" in r]  # not where coarse levels reached it
        if ratios:
            out["time_over_floor"] = round(float(np.median(ratios)), 3)
            out["time_over_floor_runs"] = [round(v, 3) for v in ratios]
        return out, hist

    peak_rss_reset()
    base_rss = peak_rss_gb()
    solve_fista(op, (0, 1), max_iter=500, tol=0)
    peak = peak_rss_gb()
    to_1e3, hist = repeated_to_gap(lambda: solve_fista(op, (0, 1), max_iter=500, tol=0), best[(0.0, 1.0)], op)
    held = (sum(t.numel() * t.element_size() for t in op.buffers())
            + sum(t.numel() * t.element_size() for m in [ne] + levels
                  for t in (m.Q.crow_indices(), m.Q.col_indices(), m.Q.values(), m.q))) / 1024**3
    to_1e3.update({"solve_adds_gb": round(peak - base_rss, 3), "operator_and_Q_gb": round(held, 3),
                   "peak_rss_gb": round(peak, 3), "rss_before_gb": round(base_rss, 3)})
    fine_only, hist_fine = repeated_to_gap(lambda: solve_fista(op, (0, 1), max_iter=500, tol=0, levels=0),
                                           best[(0.0, 1.0)], op)
    curves = {"FISTA": hist.tolist(), "FISTA without coarse start": hist_fine.tolist()}
    log(f"{label:8s} FISTA to a 1e-3 gap {to_1e3['time_s']:.3f} s, without coarse start {fine_only['time_s']:.3f} s")

    # scipy's bounded least squares on channel 0 alone (it takes one right-hand side), for as long as
    # it takes to reach the same gap (capped), against FISTA on the same channel and on all three.
    op0 = op.with_rhs(op.rhs[:, :1].contiguous(), op.constant[:1])
    best0 = solve_fista(op0, (0, 1), max_iter=3000, tol=1e-11)
    channel0_to_1e3, _ = repeated_to_gap(lambda: solve_fista(op0, (0, 1), max_iter=500, tol=0), best0.objective, op0)
    A = csr_matrix((op.val.double().numpy(), op.col.numpy(), op.crow.numpy()), shape=op.shape)
    b0 = op.rhs[:, 0].double().numpy()

    def channel0(pvec):
        return float(((A @ pvec - b0) ** 2).sum() + float(op.constant[0]))

    f0 = channel0(best0.patterns[:, 0].double().numpy())
    lsq_rows = []
    # Caps close enough together to bracket the time lsq_linear needs for a 1e-3 gap (each run starts afresh).
    for cap in (1, 3, 10, 14, 18, 20, 22, 24, 26, 28, 30):
        t0 = time.perf_counter()
        sol = lsq_linear(A, b0, bounds=(0, 1), lsmr_tol="auto", max_iter=cap, lsmr_maxiter=200)
        t_lsq = time.perf_counter() - t0
        gap0 = (channel0(sol.x) - f0) / f0
        lsq_rows.append({"max_iter": cap, "iterations": int(sol.nit), "time_s": round(t_lsq, 3), "relative_gap": gap0})
        log(f"{label:8s} lsq_linear cap {cap:3d}              {t_lsq:8.2f} s gap {gap0:9.2e}")
        if gap0 <= 1e-3 or t_lsq > 120:
            break
    lsq_reach = next((r for r in lsq_rows if r["relative_gap"] <= 1e-3), None)
    lsq_short = [r for r in lsq_rows if r["relative_gap"] > 1e-3]  # runs that stopped before the gap: a lower bound

    def speedup(fista_s):
        """lsq_linear's time over FISTA's, from its last run short of the gap and its first past it."""
        return [round(lsq_short[-1]["time_s"] / fista_s, 1) if lsq_short and fista_s else None,
                round(lsq_reach["time_s"] / fista_s, 1) if lsq_reach and fista_s else None]

    result = {"size": label, "projector": list(projector), "camera": list(camera), "calibrate_s": round(t_cal, 2),
              "build_s": round(t_build, 3),
              "model": {"variables": op.shape[1], "all_projector_cells": cells, "rows_merged": op.shape[0],
                        "rows_unmerged": full.shape[0], "nnz_merged": op.size_report()["nnz"],
                        "nnz_unmerged": full.size_report()["nnz"],
                        "objective_merged_vs_unmerged": [float(op.objective(x)), float(full.objective(x))]},
              "floor_s": floor, "best_objective": {str(k): v for k, v in best.items()}, "methods": rows,
              "setup_s": setup, "fista_to_1e-3": to_1e3, "fista_without_coarse_start_to_1e-3": fine_only,
              "fista_channel0_to_1e-3": channel0_to_1e3, "lsq_linear_channel0": lsq_rows,
              "lsq_linear_speedup_at_1e-3": {"fista_channel0": speedup(channel0_to_1e3["time_s"]),
                                             "fista_rgb": speedup(to_1e3["time_s"])},
              "curves": curves}
    if torch.cuda.is_available():
        result["cuda"] = cuda_timings(op, best[(0.0, 1.0)], log)
    return result


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work (GPU kernels run asynchronously; the CPU's do not)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def cuda_timings(op, best: float, log, device: str = "cuda") -> dict:
    """The same FISTA solve on the GPU: one Q product and the time to a 1e-3 gap (moves ``op``).

    ``device`` is for checking this function where no GPU is at hand (``"cpu"``).
    """
    device = torch.device(device)
    op.to(device)
    t0 = time.perf_counter()
    ne = op.normal_equations()
    ne.jacobi().lipschitz()
    for level, _ in op.coarse_levels(3):
        level.jacobi().lipschitz()
    synchronize(device)
    setup = time.perf_counter() - t0

    q_p = median_time(ne.jacobi().product, torch.rand(op.shape[1], 3, device=device))
    times = {}
    for name, levels in (("fista", 3), ("fista_without_coarse_start", 0)):
        runs = []
        for _ in range(5):
            hist = np.array(solve_fista(op, (0, 1), max_iter=500, tol=0, levels=levels).history)
            reached = np.nonzero((hist[:, 1] - best) / best <= 1e-3)[0]
            runs.append(float(hist[reached[0], 0]) if len(reached) else float("nan"))
        times[name] = {"time_s": float(np.median(runs)), "time_s_runs": [round(t, 4) for t in runs]}
    log(f"cuda: Q p {q_p * 1e3:.3f} ms, FISTA to a 1e-3 gap {times['fista']['time_s']:.3f} s")
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else device.type
    return {"device": name, "setup_s": round(setup, 3), "Q_p_s": q_p, **times}


def cuda_only(label: str, projector, camera, log=print, device: str = "cuda") -> dict:
    """The CUDA section at one size, without the CPU methods: calibrate on the GPU, build there, take
    the best objective from FISTA to tol 1e-11 on the GPU, then :func:`cuda_timings` (``device`` as there)."""
    scene = parse_scene(small("colour_two_planes", camera=camera, projector=projector), name=f"colour_{label}")
    t0 = time.perf_counter()
    cal = calibrate_virtual(scene, device)
    synchronize(torch.device(device))
    t_cal = time.perf_counter() - t0
    targets = [Target("near", image("astronaut"), name="astronaut"), Target("far", image("chelsea"), name="chelsea")]
    t0 = time.perf_counter()
    op = build_transport(cal.states, targets, merge=True, device=device)
    synchronize(torch.device(device))
    t_build = time.perf_counter() - t0
    best = solve_fista(op, (0, 1), max_iter=3000, tol=1e-11).objective
    log(f"{label}: calibrated in {t_cal:.1f} s, built in {t_build:.2f} s on the GPU; {op.shape[1]} variables, "
        f"best objective {best:.6g}")
    return {"size": label, "calibrate_s": round(t_cal, 2), "build_s": round(t_build, 3), "variables": op.shape[1],
            "best": best, **cuda_timings(op, best, log, device)}


def pareto(results, path):
    fig, axes = plt.subplots(1, len(results), figsize=(6 * len(results), 4.8), squeeze=False)
    for ax, r in zip(axes[0], results):
        families = {}
        for row in r["methods"]:
            family = re.sub(r" \d+ it$", "", row["method"])  # "FISTA 10 it" and "FISTA 30 it": one curve
            families.setdefault(family, []).append(row)
        for family, rows in families.items():
            rows = sorted(rows, key=lambda q: q["time_s"])
            ax.plot([q["time_s"] for q in rows], [np.mean(q["model_psnr_db"]) for q in rows],
                    "o-" if len(rows) > 1 else "s", label=family, markersize=4)
        ax.set_xscale("log")
        ax.set_xlabel("solve time (s, log), 2-core CPU")
        ax.set_ylabel("model-space PSNR, mean of both targets (dB)")
        m = r["model"]
        ax.set_title(f"{r['size']}: projectors {r['projector'][0]}x{r['projector'][1]}, {m['variables']} variables",
                     fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def scaling(results, path):
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    n = [r["model"]["variables"] for r in results]
    axes[0].loglog(n, [r["fista_to_1e-3"]["time_s"] or np.nan for r in results], "o-", label="FISTA to a 1e-3 gap")
    axes[0].loglog(n, [r["fista_without_coarse_start_to_1e-3"]["time_s"] or np.nan for r in results], "o:",
                   label="the same without the coarse start")
    axes[0].loglog(n, [r["floor_s"]["Q_p_s"] for r in results], "s--", label="one Q product (3 channels)")
    axes[0].loglog(n, [r["calibrate_s"] for r in results], "^:", label="calibration on the virtual rig")
    axes[0].set_xlabel("variables (lit projector cells)")
    axes[0].set_ylabel("seconds")
    axes[0].legend(fontsize=8)
    axes[0].grid(alpha=0.3, which="both")
    axes[1].plot(n, [r["fista_to_1e-3"]["operator_and_Q_gb"] for r in results], "o-", label="operator A and Q = A^T A")
    axes[1].plot(n, [r["fista_to_1e-3"]["solve_adds_gb"] for r in results], "s--", label="peak added by the solve")
    axes[1].set_xlabel("variables (lit projector cells)")
    axes[1].set_ylabel("GB")
    axes[1].legend(fontsize=8)
    axes[1].grid(alpha=0.3)
    fig.suptitle("How cost grows with problem size", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    fig.savefig(path, dpi=100)
    plt.close(fig)


def fmt(seconds) -> str:
    return "-" if seconds is None else f"{seconds:.3f}"


def bracket(speedup) -> str:
    low, high = speedup
    if high is None:
        return "lsq_linear did not reach the gap" + (f" (at least {low}x)" if low else "")
    return f"{low}x to {high}x faster (lsq_linear's last run short of the gap, its first past it)"


def markdown(result) -> str:
    lines = ["# Solvers: speed against accuracy on the paper's rig at three sizes (RGB)", "",
             f"Command: `{result['command']}` ({result['machine']}, torch {result['torch']}).", "",
             "Gap: relative objective above the best optimum found. Model PSNR: `A p / scale` against the targets "
             "(astronaut near / chelsea far). Capture: the virtual rig's capture of the compensated patterns. "
             "Floor: time / (the Q products it needed, each at its level's product time). FISTA starts from "
             "coarse levels (cells tied in 8x8, 4x4, 2x2 blocks) unless marked otherwise; its iterations count "
             "the full-resolution ones.", ""]
    for r in result["sizes"]:
        m, f, t = r["model"], r["floor_s"], r["fista_to_1e-3"]
        w, c = r["fista_without_coarse_start_to_1e-3"], r["fista_channel0_to_1e-3"]
        columns = " / ".join(map(str, r["setup_s"]["coarse_columns"]))
        coarse_products = " / ".join(f"{v * 1e3:.2f}" for v in f["Q_p_coarse_s"])
        coarse_its = "+".join(map(str, t.get("coarse_iterations", [])))
        ratios = ", ".join(map(str, t.get("time_over_floor_runs", [])))
        lines += [f"## {r['size']}: projectors {r['projector'][0]}x{r['projector'][1]}, camera "
                  f"{r['camera'][0]}x{r['camera'][1]}", "",
                  f"Model: {m['variables']} variables of {m['all_projector_cells']} projector cells, "
                  f"{m['rows_merged']} rows merged from {m['rows_unmerged']} ({m['nnz_merged']} / {m['nnz_unmerged']} "
                  f"nonzeros); objective at a random p merged / unmerged: {m['objective_merged_vs_unmerged'][0]:.6g} / "
                  f"{m['objective_merged_vs_unmerged'][1]:.6g}. Calibration {r['calibrate_s']:.1f} s, build "
                  f"{r['build_s']:.2f} s. Products: A p {f['A_p_s'] * 1e3:.2f} ms, A^T r {f['At_r_s'] * 1e3:.2f} ms, "
                  f"Q p {f['Q_p_s'] * 1e3:.2f} ms.", "",
                  f"One-off setup per rig (shared by every set of targets): Q = A^T A with its scaling and bound "
                  f"{r['setup_s']['normal_equations_s']:.2f} s, coarse levels ({columns} columns) "
                  f"{r['setup_s']['coarse_levels_s']:.2f} s; Q products at those levels {coarse_products} ms.", "",
                  f"FISTA to a 1e-3 gap (median of 5 runs): {fmt(t['time_s'])} s ({t['iterations']} iterations "
                  f"after {coarse_its} coarse ones, {t.get('time_over_floor', '-')} x the floor, the median over the "
                  f"runs of each one's time over the products it needed, timed just before it: {ratios}); without "
                  f"the coarse start {fmt(w['time_s'])} s ({w['iterations']} iterations, "
                  f"{w.get('time_over_floor', '-')} x the floor). The operator, Q and its coarse levels "
                  f"hold {t['operator_and_Q_gb']:.3f} GB and the solve adds {t['solve_adds_gb']:.3f} GB to the "
                  f"process's peak (which holds the whole benchmark: {t['peak_rss_gb']:.2f} GB).", "",
                  "Against scipy's `lsq_linear` (one right-hand side, so channel 0 alone): "
                  + ", ".join(f"{q['iterations']} it {q['time_s']:.1f} s gap {q['relative_gap']:.1e}"
                              for q in r["lsq_linear_channel0"])
                  + f". FISTA on the same channel reaches a 1e-3 gap in {fmt(c['time_s'])} s: "
                  f"{bracket(r['lsq_linear_speedup_at_1e-3']['fista_channel0'])}; FISTA on all three channels "
                  f"({fmt(t['time_s'])} s) against lsq_linear's one: "
                  f"{bracket(r['lsq_linear_speedup_at_1e-3']['fista_rgb'])}.", ""]
        if "cuda" in r:
            g = r["cuda"]
            lines += [f"CUDA ({g['device']}): setup {g['setup_s']:.2f} s, Q p {g['Q_p_s'] * 1e3:.3f} ms, FISTA to "
                      "a 1e-3 "
                      f"gap {fmt(g['fista']['time_s'])} s (without the coarse start "
                      f"{fmt(g['fista_without_coarse_start']['time_s'])} s).", ""]
        else:
            lines += ["CUDA: not timed (no GPU on the machine that ran this).", ""]
        lines += [
                  "| method | bounds | time (s) | iterations | gap | model PSNR (dB) | capture PSNR (dB) | capture SSIM | "
                  "x floor |", "|---|---|---|---|---|---|---|---|---|"]
        for q in r["methods"]:
            cap = " / ".join(f"{v:.2f}" for v in q.get("capture_psnr_db", []))
            ssim = " / ".join(f"{v:.3f}" for v in q.get("capture_ssim", []))
            lines.append(f"| {q['method']} | {q['bounds_8bit'][0]}..{q['bounds_8bit'][1]} | {q['time_s']:.3f} | "
                         f"{q['iterations']} | {q['relative_gap']:.1e} | "
                         + " / ".join(f"{v:.2f}" for v in q["model_psnr_db"])
                         + f" | {cap} | {ssim} | {q.get('time_over_floor', '')} |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/solvers"))
    parser.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    parser.add_argument("--cuda-only", action="store_true", help="the CUDA section alone (needs a GPU)")
    args = parser.parse_args(argv)
    command = " ".join(["python benchmarks/solvers.py", *(argv if argv is not None else sys.argv[1:])])
    if args.cuda_only:
        if not torch.cuda.is_available():
            parser.error("--cuda-only: torch sees no CUDA device here")
        sizes = [cuda_only(s, *SIZES[s]) for s in args.sizes]
        write_results(args.out, {"command": command, "machine": machine(), "torch": torch.__version__,
                                 "sizes": sizes})
        return 0
    results = [run_size(s, *SIZES[s]) for s in args.sizes]
    result = {"command": command, "machine": machine(),
              "torch": torch.__version__, "cuda": torch.cuda.is_available(), "sizes": results}
    args.out.mkdir(parents=True, exist_ok=True)
    write_results(args.out, result, markdown(result))
    pareto(results, args.out / "pareto.png")
    scaling(results, args.out / "scaling.png")
    print(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
