"""When is one homography per plane enough, and what does it save? Measured on the shipped scenes.

    python benchmarks/homography.py --out benchmarks/results/homography

Each state and projector is calibrated with Gray code on the virtual rig. The benchmark then builds
the camera-to-projector map in four ways:

1. **decoded**: the per-pixel map (decoded, sub-pixel refined, holes filled), as ``torchproj run``;
2. **homography**: one homography fitted to that map (:func:`torchproj.transport.planar_calibration`);
3. **homography, k bits**: one homography fitted to what only the k most significant Gray-code
   bits per axis decode to, the centres of blocks of ``2^(n-k)`` cells. Those bits are exactly the
   first k pattern pairs of the sequence, so this is what a capture of ``2 (k_x + k_y) + 2``
   images gives, instead of ``2 (n_x + n_y) + 2``. Fewer captures is what the model saves;
4. **oracle**: the simulator's exact geometry.

For each map it records:
- the distance of every map to the exact projector coordinates (median and 95th percentile, in
  projector pixels);
- the fit's own 95th-percentile residual (the test :func:`~torchproj.transport.planar_calibration`
  applies);
- the PSNR / SSIM of the virtual capture after FISTA on each model.

The plane scenes are ``paper_two_planes``, ``colour_two_planes`` and ``three_planes``. Two scenes
where a state is not one plane show the failure: ``box_positions`` (a box) and ``two_screens`` (a
semi-transparent screen in front of another).

On the real captures in ``../shared/data/procam_chessboard`` (a printed chessboard, real lenses),
it fits the decoded map inside the board's corner hull and over the whole frame (board and room),
and compares the board's homography with OpenCV's robust (LMedS) fit.

Writes ``results.json``, ``results.md`` and ``homography.png``.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from torchproj.calib import calibrate_projector, graycode_bits, simulate_calibration  # noqa: E402
from torchproj.evaluate import calibrate_virtual, run_virtual  # noqa: E402
from torchproj.evaluate.run import VirtualCalibration  # noqa: E402
from torchproj.scene import load_scene  # noqa: E402
from torchproj.sim import VirtualRig  # noqa: E402
from torchproj.transport import StateCalibration, fit_homography, homography_map  # noqa: E402

PLANES = ("paper_two_planes", "colour_two_planes", "three_planes")
NOT_PLANES = ("box_positions", "two_screens")


def coarse_map(decoded_xy: torch.Tensor, bits: tuple[int, int], size: tuple[int, int]) -> torch.Tensor:
    """What the first k pattern pairs per axis decode to: the centre of the block of cells they name."""
    nx, ny = graycode_bits(*size)
    out = torch.empty_like(decoded_xy)
    for axis, (n, k) in enumerate(zip((nx, ny), bits)):
        block = 2 ** (n - k)
        out[..., axis] = torch.floor(decoded_xy[..., axis] / block) * block + (block - 1) / 2
    return out


def map_error(xy: torch.Tensor, truth: torch.Tensor) -> tuple[float, float, int]:
    """Median and 95th percentile of the distance to the exact coordinates, over pixels both have."""
    ok = torch.isfinite(xy).all(-1) & torch.isfinite(truth).all(-1)
    d = (xy[ok].double() - truth[ok].double()).norm(dim=-1)
    med, p95 = torch.quantile(d[torch.linspace(0, len(d) - 1, min(len(d), 1_000_000)).long()],
                              torch.tensor([0.5, 0.95], dtype=torch.float64)).tolist()
    return med, p95, int(ok.sum())


def calibrate(scene):
    """Gray-code calibration of every state and projector, keeping the raw decodings."""
    t0 = time.perf_counter()
    rig = VirtualRig(scene)
    sizes = [(p.width, p.height) for p in scene.projectors]
    per_state, black = {}, {}
    for st in scene.states:
        for j in range(len(sizes)):
            cap = simulate_calibration(rig, st.name, j)
            per_state.setdefault(st.name, []).append(calibrate_projector(cap, sizes[j]))
            black[st.name] = cap.black.cpu()
    states = {name: StateCalibration.from_calibrations(pcs) for name, pcs in per_state.items()}
    responses = [pc.response for pc in next(iter(per_state.values()))]
    cal = VirtualCalibration(rig=rig, states=states, black=black, responses=responses,
                             seconds=time.perf_counter() - t0)
    return cal, per_state


def run_scene(name: str, bits_list, log=print) -> dict:
    scene = load_scene(name)
    sizes = [(p.width, p.height) for p in scene.projectors]
    cal, per_state = calibrate(scene)
    oracle = calibrate_virtual(scene, oracle=True)
    n_bits = [graycode_bits(*s) for s in sizes]
    out = {"scene": name, "calibrate_s": round(cal.seconds, 2), "projectors": [list(s) for s in sizes],
           "captures_per_projector_and_state": {"full": [2 * (nx + ny) + 2 for nx, ny in n_bits]},
           "maps": {}, "quality": {}}
    models = {"decoded": cal.states}
    fits_full, t_fit = {}, 0.0
    variants = {"homography": None, **{f"homography, {k} bits": k for k in bits_list}}
    for label, k in variants.items():
        states, fits = {}, {}
        for st, state in cal.states.items():
            maps, fits[st] = [], []
            for j, (xy, pc) in enumerate(zip(state.prj_xy, per_state[st])):
                source = xy if k is None else coarse_map(pc.decoding.prj_xy, (k, k), sizes[j])
                t0 = time.perf_counter()
                fit = fit_homography(source)
                t_fit += time.perf_counter() - t0 if k is None else 0.0
                fits[st].append(fit)
                maps.append(homography_map(fit.matrix, torch.isfinite(xy).all(-1), sizes[j]))
            states[st] = StateCalibration(maps, state.weight, state.projector_sizes)
        models[label] = states
        if k is None:
            fits_full = fits
        else:
            out["captures_per_projector_and_state"][label] = [2 * (k + k) + 2 for _ in sizes]
        out.setdefault("fit_p95_px", {})[label] = {st: [round(f.p95, 3) for f in per] for st, per in fits.items()}
    out["fit_s_per_map"] = round(t_fit / max(1, sum(len(v) for v in fits_full.values())), 4)
    out["plane"] = all(f.p95 <= 1.0 for per in fits_full.values() for f in per)

    for label, states in models.items():
        errs = [map_error(xy, cal.rig.geometry(st).prj_xy[j].cpu())
                for st, state in states.items() for j, xy in enumerate(state.prj_xy)]
        out["maps"][label] = {"median_px": round(float(np.mean([e[0] for e in errs])), 4),
                              "p95_px": round(float(np.mean([e[1] for e in errs])), 4)}
    models["oracle"] = oracle.states
    for label, states in models.items():
        use = cal if label != "oracle" else oracle
        t0 = time.perf_counter()
        run = run_virtual(scene, calibration=VirtualCalibration(rig=use.rig, states=states, black=use.black,
                                                                responses=use.responses, seconds=0.0,
                                                                oracle=label == "oracle"), progress=False)
        out["quality"][label] = {"psnr_db": [round(r["psnr_db"], 2) for r in run.report["targets"]],
                                 "ssim": [round(r["ssim"], 3) for r in run.report["targets"]],
                                 "run_s": round(time.perf_counter() - t0, 2)}
        log(f"{name:18s} {label:22s} map error median {out['maps'].get(label, {}).get('median_px', math.nan):7.3f} px"
            f"  PSNR {' / '.join(f'{v:.2f}' for v in out['quality'][label]['psnr_db'])}")
    return out


def real_board(root: Path) -> list[dict]:
    """The homography test on real captures of a chessboard: the board alone, and the whole frame."""
    import cv2

    from torchproj.calib import decode_gray, read_graycode_folder, refine_subpixel
    from torchproj.core.conventions import pixel_grid
    from kornia.geometry.linalg import transform_points

    rows = []
    for name in ("capture_0", "capture_1"):
        cap = read_graycode_folder(root / name, (1024, 768))
        dec = decode_gray(cap.patterns, cap.white, cap.black, (1024, 768))
        white = np.round(cap.white[0].numpy() * 255).astype(np.uint8)
        _, corners = cv2.findChessboardCorners(white, (9, 7))
        hull = np.zeros(white.shape, np.uint8)
        cv2.fillConvexPoly(hull, cv2.convexHull(corners.reshape(-1, 2)).astype(np.int32), 1)
        xy = refine_subpixel(dec.prj_xy, dec.valid)
        board = torch.where(torch.from_numpy(hull.astype(bool))[..., None], xy, float("nan"))
        fit, whole = fit_homography(board), fit_homography(xy)
        ok = torch.isfinite(board).all(-1)
        cam = pixel_grid(*xy.shape[:2], dtype=torch.float64)[ok]
        ref, _ = cv2.findHomography(cam.numpy(), board[ok].double().numpy(), cv2.LMEDS)
        gap = (transform_points(fit.matrix[None], cam[None])[0]
               - transform_points(torch.from_numpy(ref)[None], cam[None])[0]).norm(dim=-1)
        rows.append({"capture": name, "board_p95_px": round(fit.p95, 3), "board_median_px": round(fit.median, 3),
                     "board_pixels": fit.points, "frame_p95_px": round(whole.p95, 2),
                     "frame_median_px": round(whole.median, 2), "frame_pixels": whole.points,
                     "vs_opencv_lmeds_p95_px": round(float(gap.quantile(0.95)), 4)})
    return rows


def chart(results, path):
    labels = [q for q in results[0]["quality"]]
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.6))
    x = np.arange(len(results))
    width = 0.8 / len(labels)
    for i, label in enumerate(labels):
        axes[0].bar(x + i * width, [np.mean(r["quality"][label]["psnr_db"]) for r in results], width, label=label)
        if label != "oracle":
            axes[1].bar(x + i * width, [r["maps"][label]["p95_px"] for r in results], width, label=label)
    for ax, ylabel in zip(axes, ("capture PSNR, mean over targets (dB)", "map error to the exact geometry, p95 (px)")):
        ax.set_xticks(x + 0.4 - width / 2, [r["scene"] for r in results], rotation=15, fontsize=8)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3, axis="y")
    axes[1].set_yscale("log")
    handles, names = axes[0].get_legend_handles_labels()
    fig.legend(handles, names, loc="upper center", ncol=len(labels), fontsize=8, bbox_to_anchor=(0.5, 0.93))
    fig.suptitle("Decoded maps against one homography per plane (fewer bits = fewer captures)", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.86))
    fig.savefig(path, dpi=100)
    plt.close(fig)


def markdown(result) -> str:
    lines = ["# One homography per plane against decoded maps", "",
             f"Command: `{result['command']}` ({result['machine']}, torch {result['torch']}).", "",
             "Map error: distance of the map to the simulator's exact projector coordinates, median / 95th "
             "percentile in projector pixels, mean over states and projectors. Fit p95: the fit's residual "
             "against what it was fitted to (the planarity test; tolerance 1 px on full decodings). Captures: "
             "images per projector and state (Gray-code pairs, white, black; the response ramp comes on top). "
             "PSNR / SSIM: the virtual capture after FISTA on that model, per target.", ""]
    for r in result["scenes"]:
        lines += [f"## {r['scene']} ({'one plane per state' if r['plane'] else 'not one plane per state: refused'})",
                  "", f"Calibration {r['calibrate_s']:.1f} s; one homography fit {r['fit_s_per_map']:.3f} s.", "",
                  "| map | captures | map error median / p95 (px) | fit p95 (px) | PSNR (dB) | SSIM |",
                  "|---|---|---|---|---|---|"]
        for label, q in r["quality"].items():
            m = r["maps"].get(label)
            err = f"{m['median_px']:.3f} / {m['p95_px']:.3f}" if m else "0 (exact)"
            caps = r["captures_per_projector_and_state"].get(label, r["captures_per_projector_and_state"]["full"])
            fit = r["fit_p95_px"].get(label)
            fit_s = "; ".join(f"{st}: " + ", ".join(f"{v:.2f}" for v in vals) for st, vals in fit.items()) if fit else ""
            lines.append(f"| {label} | {caps[0] if label != 'oracle' else '-'} | {err} | {fit_s} | "
                         + " / ".join(f"{v:.2f}" for v in q["psnr_db"]) + " | "
                         + " / ".join(f"{v:.3f}" for v in q["ssim"]) + " |")
        lines.append("")
    if result.get("real_board"):
        lines += ["## Real captures: a chessboard (`../shared/data/procam_chessboard`)", "",
                  "Decoded sub-pixel maps; 95th-percentile / median distance (projector pixels) from decoded to "
                  "fitted coordinates inside the board's corner hull and over the whole frame (board and room); "
                  "last column: the board's homography against OpenCV's LMedS fit (95th percentile over the "
                  "board's pixels).", "",
                  "| capture | board p95 / median (px) | board pixels | whole frame p95 / median (px) | "
                  "frame pixels | vs OpenCV (px) |", "|---|---|---|---|---|---|"]
        lines += [f"| {r['capture']} | {r['board_p95_px']:.3f} / {r['board_median_px']:.3f} | {r['board_pixels']} | "
                  f"{r['frame_p95_px']:.2f} / {r['frame_median_px']:.2f} | {r['frame_pixels']} | "
                  f"{r['vs_opencv_lmeds_p95_px']:.4f} |" for r in result["real_board"]]
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/homography"))
    parser.add_argument("--scenes", nargs="+", default=[*PLANES, *NOT_PLANES])
    parser.add_argument("--bits", nargs="+", type=int, default=[3, 5, 7],
                        help="Gray-code bits per axis kept for the coarse fits")
    args = parser.parse_args(argv)
    command = " ".join(["python benchmarks/homography.py", *(argv if argv is not None else sys.argv[1:])])
    results = [run_scene(name, args.bits) for name in args.scenes]
    board_root = Path(__file__).resolve().parents[2] / "shared" / "data" / "procam_chessboard"
    result = {"command": command, "machine": f"{platform.machine()}, {torch.get_num_threads()} threads",
              "torch": torch.__version__, "scenes": results,
              "real_board": real_board(board_root) if (board_root / "capture_0").is_dir() else None}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(result, indent=1) + "\n")
    (args.out / "results.md").write_text(markdown(result))
    chart(results, args.out / "homography.png")
    print(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
