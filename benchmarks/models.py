"""Transport models against the exact-light ceiling: captured quality, model size and time.

    python benchmarks/models.py --out benchmarks/results/models [--scenes paper_two_planes box_cylinders ...] [--update]

Each scene is calibrated once from simulated captures. For each model of a camera pixel's light
(the nearest cell, as the paper; the four cells around its sub-pixel coordinate, ``bilinear``; the
cells the pixel's own area covers through the map's local slope, ``area-map``; those cells with
their weights fitted to the shares the Gray-code captures measured, ``area-gray`` (a capture folder
without the checkerboard pair); fitted to those and the checkerboard pair's share, ``area``, the
default of ``run``; on scenes where every state is one plane, those rows on one fitted homography
per state and projector (``area, homography maps``, ``--maps homography``) and on the shortened
Gray-code sequence read through homographies (``area, 3-bit Gray code``, ``--bits 3``);
with ``--share-limits``, ``area`` with other limits on the light measured past a row's cells, above
which a row is not fitted; with ``--share-sweeps``, ``area`` fitted in more sweeps; with
``--share-reach``, ``area`` with other shares measured across an edge over which a row short of it
gains the cells there (``inf``: rows stay as the parallelogram gives them); and, with ``--blur``,
``area+blur``: the area footprint spread over each
projector's defocus disc as measured from the Gray-code captures by :func:`torchproj.calib.measure_blur`)
the operator is built on that calibration; on a scene with a colour camera, ``area+channel`` too
(each channel with its own white minus black, solved apart: what ``run`` does there by default).
Each is solved with FISTA (least squares, bounds 0..255) and the patterns scored on the virtual
rig's captures as ``torchproj run`` scores them. The top line is the ceiling: the same rows solved
on the simulator's own light transport
(:func:`torchproj.pipeline.light_transport`), the best any calibration could give. Times are this
machine's, on its CPU threads; ``build`` includes merging rows where the run merges them.

Writes ``results.json``, ``results.md`` and ``models.png`` (captured PSNR and SSIM per target
against build + solve time, one panel per scene).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

from common import machine, without_checker, write_results
from matplotlib.figure import Figure

from torchproj.calib import graycode_patterns, measure_blur
from torchproj.core import InputError
from torchproj.pipeline import (CEILING_ITERATIONS, calibrate_virtual, evaluate_patterns, light_transport,
                                scene_targets, simulate_calibration, solve_on_light_transport, true_responses)
from torchproj.scene import BUILTIN_SCENES, load_scene
from torchproj.solve import make_patterns
from torchproj.transport import build, build_channel_transports, build_transport, has_colour_weights, planar_calibration
from torchproj.transport.build import _CHECKER_SWEEPS, _SHARE_OUTSIDE, _SHARE_REACH, _SHARE_SWEEPS

BOUNDS = (0.0, 1.0)
SHORT_BITS = 3  # the shortened sequence's pattern pairs per axis (docs/real-bench.md "Shortened sequences")
HOMOGRAPHY, SHORT = "area, homography maps", f"area, {SHORT_BITS}-bit Gray code"  # planar scenes' models
# Models that read no checkerboard pair: their calibrations need the Gray code, white, black and ramps only.
WITHOUT_CHECKER = ("nearest", "bilinear", "area-map", "area-gray")


def calibration_images(scene, model: str) -> int | None:
    """Captures the model's calibration needs, over every state and projector (None for the ceiling)."""
    if model == "ceiling":
        return None
    per = []
    for p in scene.projectors:
        gray = graycode_patterns(p.width, p.height, SHORT_BITS if model == SHORT else None).shape[0]
        per.append(gray + 2 + (0 if model in (*WITHOUT_CHECKER, SHORT) else 2))  # ramps, checkerboard pair
    return sum(per) * len(scene.states)


def measured_blur(cal) -> tuple[dict, float, dict]:
    """Each state's calibration with the defocus measured from its Gray-code captures (captured again:
    calibrate_virtual does not keep them), the seconds measuring took, and the median per state and
    projector."""
    states, seconds, medians = {}, 0.0, {}
    for name, state in cal.states.items():
        blur = []
        for j, p in enumerate(cal.rig.scene.projectors):
            capture = simulate_calibration(cal.rig, name, j)
            t0 = time.perf_counter()
            blur.append(measure_blur(capture.patterns, capture.white, capture.black, state.prj_xy[j], (p.width, p.height)))
            seconds += time.perf_counter() - t0
            medians.setdefault(name, {})[p.name] = round(float(blur[-1].nanmedian()), 2)
        states[name] = dataclasses.replace(state, blur=blur)
    return states, seconds, medians


def measure(name: str, scale: float, log=print, blur: bool = False, share_limits: tuple[float, ...] = (),
            share_sweeps: tuple[int, ...] = (), share_reach: tuple[float, ...] = ()) -> list[dict]:
    scene = load_scene(name, scale=scale)
    cal = calibrate_virtual(scene, progress=False)
    targets = scene_targets(scene, None, cal.rig)
    rows = []
    colour = ("area+channel",) if has_colour_weights(cal.states, targets) else ()
    limits = tuple(f"area, outside <= {limit:g}" for limit in share_limits)
    sweeps = tuple(f"area, {n} sweeps" for n in share_sweeps)
    reaches = tuple(f"area, reach {r:g}" for r in share_reach)
    planar = {}
    try:  # where every state is one plane: its homographies, and the shortened sequence
        planar[HOMOGRAPHY] = (cal, planar_calibration(cal.states)[0])
        short = calibrate_virtual(scene, progress=False, bits=SHORT_BITS)
        planar[SHORT] = (short, short.states)
    except InputError:
        pass
    for model in ("nearest", "bilinear", "area-map", "area-gray", "area", *limits, *sweeps, *reaches, *colour,
                  *(("area+blur",) if blur else ()), *planar, "ceiling"):
        extra, states, judge = {}, cal.states, cal
        if model in planar:
            judge, states = planar[model]
        # what run uses, but where a row below names another limit, number of sweeps or reach
        build._SHARE_OUTSIDE, build._SHARE_REACH = _SHARE_OUTSIDE, _SHARE_REACH
        build._SHARE_SWEEPS, build._CHECKER_SWEEPS = _SHARE_SWEEPS, _CHECKER_SWEEPS
        if model == "area-map":
            states = {k: dataclasses.replace(s, shares=None) for k, s in states.items()}
        if model == "area-gray":
            states = without_checker(states)
        if model in limits:
            build._SHARE_OUTSIDE = share_limits[limits.index(model)]
        if model in sweeps:
            build._SHARE_SWEEPS = build._CHECKER_SWEEPS = share_sweeps[sweeps.index(model)]
        if model in reaches:
            build._SHARE_REACH = share_reach[reaches.index(model)]
        if model == "area+blur":
            states, seconds, medians = measured_blur(cal)
            extra = {"measure_blur_s": round(seconds, 2), "blur_median_cells": medians}
            log(f"{name} measured blur (median cells): {medians} in {seconds:.1f} s")
        t0 = time.perf_counter()
        footprint = "nearest" if model in ("nearest", "ceiling") else "bilinear" if model == "bilinear" else "area"
        if model == "area+channel":
            ops = build_channel_transports(states, targets, footprint=footprint)
            op = ops[0]
        else:
            op = build_transport(states, targets, footprint=footprint,
                                 merge=model == "nearest")  # as run_virtual: bilinear and area rows do not repeat
            ops = light_transport(cal.rig, targets, op) if model == "ceiling" else [op]
        built = time.perf_counter() - t0
        t0 = time.perf_counter()
        if model == "ceiling":
            result, _, patterns = solve_on_light_transport(ops, BOUNDS, true_responses(cal.rig.scene),
                                                           max_iter=CEILING_ITERATIONS)
        else:
            result, _, patterns = make_patterns(ops, "fista", BOUNDS, cal.responses, progress=False)
        solved = time.perf_counter() - t0
        scores = evaluate_patterns(judge, patterns, targets, scale=op.scale, states=states if model in planar else None).targets
        row = {"scene": name, "model": model, **extra, "images": calibration_images(scene, model),
               "variables": ops[0].shape[1], "rows": ops[0].shape[0],
               "nnz": sum(o.nnz for o in ops), "build_s": round(built, 3), "solve_s": round(solved, 3),
               "iterations": result.iterations, "converged": result.converged,
               "targets": [{"name": s.name, "psnr_db": round(s.psnr_db, 3), "ssim": round(s.ssim, 4),
                            "crosstalk": round(s.crosstalk, 4)} for s in scores]}
        log(f"{name} {model}: build {built:.2f} s, solve {solved:.2f} s, "
            + ", ".join(f"{t['name']} {t['psnr_db']:.2f} dB / {t['ssim']:.3f}" for t in row["targets"]))
        rows.append(row)
    return rows


def markdown(rows: list[dict], scale: float) -> str:
    lines = [f"# Transport models against the exact-light ceiling (scale {scale:g}, {machine()})", "",
             "| scene | model | calibration images | variables | rows | nnz | build (s) | solve (s) | per target: PSNR "
             "(dB) / SSIM / crosstalk |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        images = "" if r.get("images") is None else r["images"]
        lines.append(f"| {r['scene']} | {r['model']} | {images} | {r['variables']} | {r['rows']} | {r['nnz']} | {r['build_s']:.2f} "
                     f"| {r['solve_s']:.2f} | " + "; ".join(f"{t['name']} {t['psnr_db']:.2f} / {t['ssim']:.3f} / "
                                                           f"{t['crosstalk']:.3f}" for t in r["targets"]) + " |")
    return "\n".join(lines) + "\n"


def chart(path: Path, rows: list[dict]) -> None:
    """Per scene, each target's captured SSIM against build + solve time for each model; the ceiling
    is a dashed line per target (its time is not a user's: it needs the simulator)."""
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    cols = min(4, len(scenes))
    lines = -(-len(scenes) // cols)
    fig = Figure(figsize=(5 * cols, 4 * lines), layout="constrained")
    for i, scene in enumerate(scenes):
        ax = fig.add_subplot(lines, cols, i + 1)
        mine = [r for r in rows if r["scene"] == scene and r["model"] != "ceiling"]
        top = next(r for r in rows if r["scene"] == scene and r["model"] == "ceiling")
        for k, name in enumerate(t["name"] for t in top["targets"]):
            colour = f"C{k}"
            ax.axhline(top["targets"][k]["ssim"], color=colour, ls="--", lw=1, label=f"{name}: ceiling")
            for marker, r in zip("os^vDPX*hp<>", mine):
                ax.plot(r["build_s"] + r["solve_s"], r["targets"][k]["ssim"], marker, color=colour,
                        label=f"{name}: {r['model']}")
        ax.set(title=scene, xlabel="build + solve (s)", ylabel="captured SSIM")
        ax.legend(fontsize=7)
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/models"))
    ap.add_argument("--scenes", nargs="+", default=list(BUILTIN_SCENES))
    ap.add_argument("--scale", type=float, default=1.0, help="resolution scale of every scene (default 1)")
    ap.add_argument("--chart-only", action="store_true", help="redraw models.png from --out's results.json")
    ap.add_argument("--blur", action="store_true", help="also the area footprint with the defocus measured from captures")
    ap.add_argument("--share-limits", nargs="+", type=float, default=[],
                    help="also the area footprint with these limits on the light measured past a row's cells "
                         f"(default of run: {_SHARE_OUTSIDE})")
    ap.add_argument("--share-sweeps", nargs="+", type=int, default=[],
                    help=f"also the area footprint fitted in these numbers of sweeps (default of run: {_SHARE_SWEEPS}; "
                         f"{_CHECKER_SWEEPS} where a checkerboard share joins the fit)")
    ap.add_argument("--share-reach", nargs="+", type=float, default=[],
                    help="also the area footprint whose rows gain the cells across an edge over these measured shares "
                         f"(inf: never; default of run: {_SHARE_REACH})")
    ap.add_argument("--update", action="store_true", help="keep --out's rows of the scenes not measured now")
    args = ap.parse_args()
    if args.chart_only:
        chart(args.out / "models.png", json.loads((args.out / "results.json").read_text())["rows"])
        return
    rows = [r for name in args.scenes for r in measure(name, args.scale, blur=args.blur,
                                                       share_limits=tuple(args.share_limits),
                                                       share_sweeps=tuple(args.share_sweeps),
                                                       share_reach=tuple(args.share_reach))]
    if args.update:
        kept = [r for r in json.loads((args.out / "results.json").read_text())["rows"] if r["scene"] not in args.scenes]
        order = list(dict.fromkeys([r["scene"] for r in kept] + args.scenes))
        rows = sorted(kept + rows, key=lambda r: order.index(r["scene"]))  # stable: models stay in order
    args.out.mkdir(parents=True, exist_ok=True)
    write_results(args.out, {"machine": machine(), "scale": args.scale, "rows": rows}, markdown(rows, args.scale))
    chart(args.out / "models.png", rows)
    print(f"wrote {args.out}/results.json, results.md, models.png")


if __name__ == "__main__":
    main()
