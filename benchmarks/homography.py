"""When is one homography per plane enough, and what does it save? Measured on the shipped scenes.

    python benchmarks/homography.py --out benchmarks/results/homography

Each state and projector is calibrated with Gray code on the virtual rig. The benchmark then builds
the camera-to-projector map in four ways:

1. **decoded**: the per-pixel map (decoded, sub-pixel refined, holes filled), as ``torchproj run``;
2. **homography**: one homography fitted to that map (:func:`torchproj.transport.planar_calibration`);
3. **homography, k bits**: a shortened sequence, the first k Gray-code pattern pairs per axis,
   captured on the virtual rig and calibrated as ``torchproj run --bits k`` does
   (:func:`torchproj.pipeline.calibrate_virtual`): the captures decode to blocks of ``2^(n-k)``
   cells, and one homography is fitted to the block edges. That is ``2 (k_x + k_y) + 2`` images
   instead of ``2 (n_x + n_y) + 2``. Fewer captures is what the model saves. On scenes that are
   not one plane the fit is forced through (the tolerance lifted) to show what it would cost;
4. **oracle**: the simulator's exact geometry.

For each map it records:
- the distance of every map to the exact projector coordinates (median and 95th percentile, in
  projector pixels);
- the fit's own 95th-percentile residual (the test :func:`~torchproj.calib.check_plane` applies;
  for blocks, the distance outside the block over the pixels at block edges);
- the PSNR / SSIM of the virtual capture after FISTA on each model.

The plane scenes are ``paper_two_planes``, ``colour_two_planes`` and ``three_planes``. Two scenes
where a state is not one plane show the failure: ``box_positions`` (a box) and ``two_screens`` (a
semi-transparent screen in front of another).

On the real captures in ``../shared/data/procam_chessboard`` (a printed chessboard, real lenses),
it fits the decoded map inside the board's corner hull and over the whole frame (board and room),
and compares the board's homography with OpenCV's robust (LMedS) fit to the full decoding; then
the same from the first k pattern pairs per axis of those captures alone.

Writes ``results.json``, ``results.md`` and ``homography.png``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from common import machine, write_results  # noqa: E402
from torchproj.calib import fit_homography, graycode_bits, homography_map  # noqa: E402
from torchproj.core import InputError  # noqa: E402
from torchproj.pipeline import calibrate_virtual, run_virtual  # noqa: E402
from torchproj.pipeline import VirtualCalibration  # noqa: E402
from torchproj.scene import load_scene  # noqa: E402
from torchproj.transport import StateCalibration  # noqa: E402

PLANES = ("paper_two_planes", "colour_two_planes", "three_planes")
NOT_PLANES = ("box_positions", "two_screens")


def map_error(xy: torch.Tensor, truth: torch.Tensor) -> tuple[float, float, int]:
    """Median and 95th percentile of the distance to the exact coordinates, over pixels both have."""
    ok = torch.isfinite(xy).all(-1) & torch.isfinite(truth).all(-1)
    d = (xy[ok].double() - truth[ok].double()).norm(dim=-1)
    med, p95 = torch.quantile(d[torch.linspace(0, len(d) - 1, min(len(d), 1_000_000)).long()],
                              torch.tensor([0.5, 0.95], dtype=torch.float64)).tolist()
    return med, p95, int(ok.sum())


def run_scene(name: str, bits_list, log=print) -> dict:
    scene = load_scene(name)
    sizes = [(p.width, p.height) for p in scene.projectors]
    cal = calibrate_virtual(scene)
    oracle = calibrate_virtual(scene, oracle=True)
    n_bits = [graycode_bits(*s) for s in sizes]
    out = {"scene": name, "calibrate_s": round(cal.seconds, 2), "projectors": [list(s) for s in sizes],
           "captures_per_projector_and_state": {"full": [2 * (nx + ny) + 2 for nx, ny in n_bits]},
           "maps": {}, "quality": {}}
    models = {"decoded": cal.states}
    calibrations = {"decoded": cal}
    fits_full, t_fit = {}, 0.0
    states, fits = {}, {}
    for st, state in cal.states.items():
        t0 = time.perf_counter()
        fits[st] = [fit_homography(xy) for xy in state.prj_xy]
        t_fit += time.perf_counter() - t0
        states[st] = StateCalibration([homography_map(f.matrix, torch.isfinite(xy).all(-1), size)
                                       for f, xy, size in zip(fits[st], state.prj_xy, sizes)],
                                      state.weight, state.projector_sizes)
    models["homography"], calibrations["homography"], fits_full = states, cal, fits
    out["fit_p95_px"] = {"homography": {st: [round(f.p95, 3) for f in per] for st, per in fits.items()}}
    for k in bits_list:
        label = f"homography, {k} bits"
        # The tolerance lifted: non-planar scenes are refused at the default, and the forced fit
        # shows what ignoring that would cost.
        try:
            short = calibrate_virtual(scene, bits=k, plane_tolerance=1e9)
        except InputError as exc:  # too few block edges in view to pin a homography down
            out.setdefault("refused", {})[label] = str(exc)
            log(f"{name:18s} {label:22s} refused: {exc}")
            continue
        models[label], calibrations[label] = short.states, short
        out["captures_per_projector_and_state"][label] = [2 * sum(b) + 2 for b in short.bits]
        out["fit_p95_px"][label] = {st: [round(f.p95, 3) for f in per] for st, per in short.homographies.items()}
        out.setdefault("calibrate_s_bits", {})[label] = round(short.seconds, 2)
    out["fit_s_per_map"] = round(t_fit / max(1, sum(len(v) for v in fits_full.values())), 4)
    out["plane"] = all(f.p95 <= 1.0 for per in fits_full.values() for f in per)

    for label, states in models.items():
        errs = [map_error(xy, cal.rig.geometry(st).prj_xy[j].cpu())
                for st, state in states.items() for j, xy in enumerate(state.prj_xy)]
        out["maps"][label] = {"median_px": round(float(np.mean([e[0] for e in errs])), 4),
                              "p95_px": round(float(np.mean([e[1] for e in errs])), 4)}
    models["oracle"], calibrations["oracle"] = oracle.states, oracle
    for label, states in models.items():
        use = calibrations[label]
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


def real_board(root: Path, bits_list) -> list[dict]:
    """The homography test on real captures of a chessboard: the board alone, and the whole frame;
    from the full decoding, then from the first k pattern pairs per axis of the same captures."""
    import cv2

    from torchproj.calib import decode_gray, read_graycode_folder, refine_subpixel
    from torchproj.core import InputError
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
        rows.append({"capture": name, "bits": "all", "board_p95_px": round(fit.p95, 3),
                     "board_median_px": round(fit.median, 3), "board_pixels": fit.points,
                     "frame_p95_px": round(whole.p95, 2), "frame_median_px": round(whole.median, 2),
                     "frame_pixels": whole.points, "vs_opencv_lmeds_p95_px": round(float(gap.quantile(0.95)), 4)})
        nx = graycode_bits(1024, 768)[0]
        for k in bits_list:
            # The captures of the first k pairs per axis are exactly what a shortened sequence shows.
            keep = [*range(2 * k), *range(2 * nx, 2 * nx + 2 * k)]
            coarse = decode_gray(cap.patterns[keep], cap.white, cap.black, (1024, 768), bits=k)
            on_board = torch.where(torch.from_numpy(hull.astype(bool))[..., None], coarse.prj_xy, float("nan"))
            row = {"capture": name, "bits": k}
            try:
                t0 = time.perf_counter()
                fit = fit_homography(on_board, block=coarse.block)
                row["fit_s"] = round(time.perf_counter() - t0, 3)
                whole = fit_homography(coarse.prj_xy, block=coarse.block)
            except InputError as exc:
                row["refused"] = str(exc)
                rows.append(row)
                continue
            gap = (transform_points(fit.matrix[None], cam[None])[0]
                   - transform_points(torch.from_numpy(ref)[None], cam[None])[0]).norm(dim=-1)
            row.update(board_p95_px=round(fit.p95, 3), board_median_px=round(fit.median, 3), board_pixels=fit.points,
                       frame_p95_px=round(whole.p95, 2), frame_median_px=round(whole.median, 2),
                       frame_pixels=whole.points, vs_opencv_lmeds_p95_px=round(float(gap.quantile(0.95)), 4),
                       vs_opencv_lmeds_median_px=round(float(gap.median()), 4))
            rows.append(row)
    return rows


def chart(results, path):
    labels = [q for q in results[0]["quality"]]
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.6))
    x = np.arange(len(results))
    width = 0.8 / len(labels)
    for i, label in enumerate(labels):
        # A model refused outright for a scene (too few block edges) has no bar there.
        axes[0].bar(x + i * width, [np.mean(r["quality"][label]["psnr_db"]) if label in r["quality"] else np.nan
                                    for r in results], width, label=label)
        if label != "oracle":
            axes[1].bar(x + i * width, [r["maps"][label]["p95_px"] if label in r["maps"] else np.nan for r in results],
                        width, label=label)
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
             "against what it was fitted to (the planarity test, tolerance 1 px; for blocks, the distance outside "
             "the block over the pixels at block edges). Captures: "
             "images per projector and state (Gray-code pairs, white, black; the response ramp comes on top). "
             "PSNR / SSIM: the virtual capture after FISTA on that model, per target.", ""]
    for r in result["scenes"]:
        lines += [f"## {r['scene']} ({'one plane per state' if r['plane'] else 'not one plane per state: refused'})",
                  "", f"Calibration {r['calibrate_s']:.1f} s"
                  + "".join(f"; {label.split(', ')[1]}: {v:.1f} s" for label, v in r.get("calibrate_s_bits", {}).items())
                  + f"; one homography fit to a decoded map {r['fit_s_per_map']:.3f} s.", "",
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
        lines += [f"| {label} | refused: {why} | | | | |" for label, why in r.get("refused", {}).items()]
        lines.append("")
    if result.get("real_board"):
        lines += ["## Real captures: a chessboard (`../shared/data/procam_chessboard`)", "",
                  "Bits: all (the decoded sub-pixel map), or the first k pattern pairs per axis of the same "
                  "captures (blocks; 4k + 2 images instead of 42). Residual 95th percentile / median (projector "
                  "pixels, the planarity test) inside the board's corner hull and over the whole frame (board and "
                  "room; for blocks, over the pixels at block edges); last column: the board's homography against "
                  "OpenCV's LMedS fit to the full decoding (95th percentile over the board's pixels).", "",
                  "| capture | bits | board p95 / median (px) | board pixels | whole frame p95 / median (px) | "
                  "frame pixels | vs OpenCV (px) |", "|---|---|---|---|---|---|---|"]
        for r in result["real_board"]:
            if "refused" in r:
                lines.append(f"| {r['capture']} | {r['bits']} | refused: {r['refused']} | | | | |")
                continue
            lines.append(f"| {r['capture']} | {r['bits']} | {r['board_p95_px']:.3f} / {r['board_median_px']:.3f} | "
                         f"{r['board_pixels']} | {r['frame_p95_px']:.2f} / {r['frame_median_px']:.2f} | "
                         f"{r['frame_pixels']} | {r['vs_opencv_lmeds_p95_px']:.4f} |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/homography"))
    parser.add_argument("--scenes", nargs="+", default=[*PLANES, *NOT_PLANES])
    parser.add_argument("--bits", nargs="+", type=int, default=[2, 3, 5, 7],
                        help="Gray-code bits per axis of the shortened sequences")
    args = parser.parse_args(argv)
    command = " ".join(["python benchmarks/homography.py", *(argv if argv is not None else sys.argv[1:])])
    results = [run_scene(name, args.bits) for name in args.scenes]
    board_root = Path(__file__).resolve().parents[2] / "shared" / "data" / "procam_chessboard"
    result = {"command": command, "machine": machine(),
              "torch": torch.__version__, "scenes": results,
              "real_board": real_board(board_root, args.bits) if (board_root / "capture_0").is_dir() else None}
    args.out.mkdir(parents=True, exist_ok=True)
    write_results(args.out, result, markdown(result))
    chart(results, args.out / "homography.png")
    print(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
