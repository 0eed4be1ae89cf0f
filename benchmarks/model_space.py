"""Pattern solvers in model space on the paper's two-plane rig, calibrated on the virtual rig.

    python benchmarks/model_space.py --out benchmarks/results/model_space

Calibrates both states of ``configs/paper_two_planes.yaml`` (1600x1200 camera, two 1024x768
projectors) from simulated Gray-code captures, builds the operator for two RGB targets (scikit-image's
astronaut on the near plane, chelsea on the far one), and runs every solver. Quality is measured in
model space: ``A p / scale`` against the targets on the target pixels (PSNR, data range 1); the
objective gap is relative to the best optimum found (FISTA run to a 1e-12 relative change). The
virtual rig's own captures of the patterns are the business of ``torchproj run``, not of this file.

Writes ``results.json``, ``results.md`` and ``psnr_vs_time.png``.
"""

from __future__ import annotations

import argparse
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

from common import machine, median_time, write_results  # noqa: E402
from torchproj.pipeline import calibrate_virtual, target_image  # noqa: E402
from torchproj.metrics import model_space_psnr  # noqa: E402
from torchproj.scene import load_scene  # noqa: E402
from torchproj.solve import (epipolar_chains, fundamental_between_projectors, solve_adam, solve_eo,  # noqa: E402
                             solve_fista, solve_lf, solve_pgd, to_projectable)
from torchproj.transport import Target, build_transport  # noqa: E402

NEG = -100 / 255


def calibrate(scene_name: str):
    scene = load_scene(scene_name)
    return scene, calibrate_virtual(scene).states


def image(name: str) -> torch.Tensor:
    """A scikit-image test image in RGB, as the benchmarks' targets."""
    return target_image(name, 3)


def product_floor(op) -> dict:
    """One product of each kind on 3 channels: ``A p``, ``A^T r``, ``Q p``, and ``Q p`` at each coarse level."""
    x = torch.rand(op.shape[1], 3)
    return {"A_p_s": median_time(op.A, x), "At_r_s": median_time(op.A_adjoint, torch.rand(op.shape[0], 3)),
            "Q_nnz": int(op.normal_equations().Q._nnz()), **q_products(op)}


def q_products(op) -> dict:
    """The time of one ``Q p`` (3 channels, Jacobi-scaled as the solvers use it) at full size and at each
    coarse level FISTA starts on."""
    ne = op.normal_equations()
    return {"Q_p_s": median_time(ne.jacobi().product, torch.rand(op.shape[1], 3)),
            "Q_p_coarse_s": [median_time(level.jacobi().product, torch.rand(level.Q.shape[0], 3))
                             for level, _ in op.coarse_levels(3)]}


def floor_time(floor: dict, iterations: int, coarse_iterations: list[int]) -> float:
    """The Q products a proximal solve needed, each at its level's product time (coarsest level first, as
    the solvers report ``coarse_iterations``)."""
    per_level = floor["Q_p_coarse_s"][:len(coarse_iterations)][::-1]
    return iterations * floor["Q_p_s"] + sum(k * t for k, t in zip(coarse_iterations, per_level))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/model_space"))
    parser.add_argument("--scene", default="paper_two_planes")
    parser.add_argument("--lsq-linear-iterations", type=int, default=10,
                        help="iteration cap of scipy's lsq_linear on one channel (0 skips it)")
    parser.add_argument("--lsmr-iterations", type=int, default=200,
                        help="cap of lsq_linear's inner LSMR iterations (uncapped it ran for over 15 minutes)")
    args = parser.parse_args(argv)
    command = "python benchmarks/model_space.py " + " ".join(argv if argv is not None else sys.argv[1:])

    t0 = time.perf_counter()
    scene, cals = calibrate(args.scene)
    t_cal = time.perf_counter() - t0
    targets = [Target(scene.states[0].name, image("astronaut"), name="astronaut"),
               Target(scene.states[1].name, image("chelsea"), name="chelsea")]
    t0 = time.perf_counter()
    op = build_transport(cals, targets, merge=True)
    t_build = time.perf_counter() - t0
    full = build_transport(cals, targets, merge=False, scale=op.scale)
    assert torch.equal(full.column_cell, op.column_cell) and torch.equal(full.column_projector, op.column_projector)
    floor = product_floor(op)

    best = {}
    for bounds in [(0.0, 1.0), (NEG, 1.0)]:
        best[bounds] = solve_fista(op, bounds, max_iter=5000, tol=1e-12).objective

    rows = []

    def record(label, res, bounds, proximal=False, projectable=None):
        p = res.patterns if projectable is None else projectable
        psnrs = model_space_psnr(full, p)
        gap = (res.objective - best[bounds]) / best[bounds]
        row = {"method": label, "bounds_8bit": [round(b * 255) for b in bounds], "time_s": res.time_s,
               "iterations": res.iterations, "objective": res.objective, "relative_gap": gap,
               "psnr_db": psnrs, "info": res.info}
        if proximal:
            row["time_over_floor"] = res.time_s / floor_time(floor, res.iterations, res.info["coarse_iterations"])
        rows.append(row)
        print(f"{label:28s} {res.time_s:7.2f} s  it {res.iterations:5d}  gap {gap:9.2e}  PSNR "
              + " / ".join(f"{v:.2f}" for v in psnrs), flush=True)

    for iters in (5, 10, 20, 30, 50, 100):
        res = solve_fista(op, (0, 1), max_iter=iters, tol=0)
        record(f"FISTA {iters} it", res, (0.0, 1.0), proximal=True)
    res = solve_fista(op, (0, 1), max_iter=50, tol=0, precondition=False)
    record("FISTA 50 it, no Jacobi scaling", res, (0.0, 1.0), proximal=True)
    record("FISTA to 1e-4 change", solve_fista(op, (0, 1), max_iter=2000, tol=1e-4), (0.0, 1.0))
    record("PGD 100 it", solve_pgd(op, (0, 1), max_iter=100, tol=0), (0.0, 1.0), proximal=True)
    record("Adam lr 0.02, 200 it", solve_adam(op, (0, 1), lr=0.02, max_iter=200, tol=0), (0.0, 1.0))
    for normalise in ("joint", "projector", "clip"):
        record(f"LF ({normalise})", solve_lf(op, (0, 1), normalise=normalise), (0.0, 1.0))
    res = solve_eo(op, (0, 1), calibrations=cals)
    record("EO_0^255 (epipolar chains)", res, (0.0, 1.0))
    res = solve_eo(op, (NEG, 1), calibrations=cals)
    record("EO_-100^255 (epipolar, clipped)", res, (NEG, 1.0), projectable=to_projectable(res.patterns, (NEG, 1.0)))
    # Our choices inside EO, each against its alternative (the paper says nothing of these).
    chains = epipolar_chains(op, fundamental_between_projectors(cals))
    sizes = torch.bincount(chains).float()
    print(f"the paper's chains: {sizes.numel()}, median {float(sizes.median()):.0f} cells, largest {int(sizes.max())}")
    record("EO_0^255, each of the paper's chains a block", solve_eo(op, (0, 1), chains=chains), (0.0, 1.0))
    record("EO_0^255, 10 steps per sweep", solve_eo(op, (0, 1), calibrations=cals, inner_iter=10), (0.0, 1.0))
    record("EO_0^255, started mid-box", solve_eo(op, (0, 1), calibrations=cals, levels=0), (0.0, 1.0))
    record("EO_0^255, to a 1e-5 change", solve_eo(op, (0, 1), calibrations=cals, tol=1e-5), (0.0, 1.0))
    res = solve_eo(op, (0, 1), chains="components")
    record("EO_0^255 (components)", res, (0.0, 1.0))

    lsq = None
    if args.lsq_linear_iterations:
        A = csr_matrix((op.val.double().numpy(), op.col.numpy(), op.crow.numpy()), shape=op.shape)
        t0 = time.perf_counter()
        sol = lsq_linear(A, op.rhs[:, 0].double().numpy(), bounds=(0, 1), lsmr_tol="auto",
                         max_iter=args.lsq_linear_iterations, lsmr_maxiter=args.lsmr_iterations)
        t_lsq = time.perf_counter() - t0
        def channel0(p):
            return float((op.A(p)[:, 0] - op.rhs[:, 0]).pow(2).sum() + op.constant[0])

        f_lsq = channel0(torch.from_numpy(sol.x).float()[:, None].expand(-1, 3).contiguous())
        f_best0 = channel0(solve_fista(op, (0, 1), max_iter=5000, tol=1e-12).patterns)
        lsq = {"time_s": t_lsq, "iterations": int(sol.nit), "status": int(sol.status),
               "objective_channel0": f_lsq, "relative_gap_channel0": (f_lsq - f_best0) / f_best0}
        print(f"lsq_linear (channel 0)       {t_lsq:7.2f} s  it {sol.nit}  gap {lsq['relative_gap_channel0']:.2e}")

    result = {"command": command, "machine": machine(),
              "torch": torch.__version__, "scene": args.scene, "calibrate_s": t_cal, "build_s": t_build,
              "model": op.size_report(), "model_unmerged": full.size_report(), "scale": op.scale,
              "product_floor_s": floor, "best_objective": {str(k): v for k, v in best.items()},
              "methods": rows, "lsq_linear": lsq}
    args.out.mkdir(parents=True, exist_ok=True)
    write_results(args.out, result, markdown(result))
    chart(rows, args.out / "psnr_vs_time.png")
    print(markdown(result))
    return 0


def markdown(r: dict) -> str:
    m, mu = r["model"], r["model_unmerged"]
    lines = [
        "# Pattern solvers in model space: the paper's two-plane rig, calibrated on the virtual rig", "",
        f"Command: `{r['command']}` ({r['machine']}, torch {r['torch']}).", "",
        f"Model (RGB, 3 right-hand sides): {m['variables']} variables, {m['rows']} rows, {m['nnz']} nonzeros after "
        f"merging ({mu['rows']} rows, {mu['nnz']} nonzeros before). Calibration {r['calibrate_s']:.0f} s, "
        f"build {r['build_s']:.1f} s. One product (3 channels): A p {r['product_floor_s']['A_p_s'] * 1e3:.1f} ms, "
        f"A^T r {r['product_floor_s']['At_r_s'] * 1e3:.1f} ms, Q p {r['product_floor_s']['Q_p_s'] * 1e3:.1f} ms "
        f"(Q = A^T A, {r['product_floor_s']['Q_nnz']} nonzeros; FISTA and PGD need one Q product per "
        "iteration); at FISTA's coarse levels (cells tied in 2x2, 4x4, 8x8 blocks) "
        + " / ".join(f"{v * 1e3:.2f}" for v in r["product_floor_s"]["Q_p_coarse_s"]) + " ms. FISTA starts on "
        "those levels; its iterations count the full-resolution ones, its time includes the levels. Time / Q "
        "products: time over the products a solve needed, each at its level's product time.", "",
        "PSNR: `A p / scale` against the target on its camera pixels (data range 1), astronaut (near) / "
        "chelsea (far). Gap: relative objective above the best optimum found for the same bounds.", "",
        "| method | bounds (8-bit) | time (s) | iterations | gap | PSNR near / far (dB) | time / Q products |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in r["methods"]:
        over = f"{row['time_over_floor']:.2f}" if "time_over_floor" in row else ""
        lines.append(f"| {row['method']} | {row['bounds_8bit'][0]}..{row['bounds_8bit'][1]} | {row['time_s']:.2f} | "
                     f"{row['iterations']} | {row['relative_gap']:.1e} | "
                     f"{row['psnr_db'][0]:.2f} / {row['psnr_db'][1]:.2f} | {over} |")
    if r["lsq_linear"]:
        q = r["lsq_linear"]
        lines += ["", f"scipy `lsq_linear` (one channel, bounds 0..1, capped at {q['iterations']} iterations): "
                      f"{q['time_s']:.1f} s, relative gap {q['relative_gap_channel0']:.1e} (status {q['status']})."]
    for row in r["methods"]:
        if "blocks" in row["info"]:
            lines.append(f"\n{row['method']}: " + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                                                           for k, v in row["info"].items()))
    return "\n".join(lines) + "\n"


def chart(rows, path):
    """FISTA's checkpoints as one curve, every other run as a labelled point."""
    fig, ax = plt.subplots(figsize=(8, 4.8))
    curve = [r for r in rows if r["method"].startswith("FISTA") and r["method"].endswith(" it")]
    ax.plot([r["time_s"] for r in curve], [np.mean(r["psnr_db"]) for r in curve], "o-", color="#d62728",
            label="FISTA (Jacobi-scaled), 5..100 iterations")
    markers = "sD^v<>phX*"
    for i, r in enumerate(x for x in rows if x not in curve):
        y = np.mean(r["psnr_db"])
        ax.scatter(r["time_s"], y, marker=markers[i % len(markers)], s=45, label=r["method"])
    ax.set_xscale("log")
    ax.set_xlabel("solve time (s, log scale), 2-core CPU")
    ax.set_ylabel("model-space PSNR, mean of both targets (dB)")
    ax.set_title("Pattern solvers on the calibrated two-plane rig (RGB, 0.93 M variables)", fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
