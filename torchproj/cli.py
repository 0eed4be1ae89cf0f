"""The ``torchproj`` command: thin wrappers that parse arguments and call the library's rooms."""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

import numpy as np
import torch

from . import __version__
from .core.errors import TorchprojError
from .core.output import atomic_output, write_json

__all__ = ["main", "build_parser"]


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w <= 0 or h <= 0:
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT in pixels such as 1024x768, got {text!r}") from None
    return w, h


def _write_report(stage: Path, report: dict, markdown) -> str:
    """``report.json`` and its ``report.md`` rendering into the staging folder; returns the markdown."""
    text = markdown(report)
    write_json(stage / "report.json", report)
    (stage / "report.md").write_text(text)
    return text


# ------------------------------------------------------------------------------------- scene
def cmd_scene(args) -> int:
    from .scene import load_scene

    scene = load_scene(args.config)
    cam = scene.camera
    print(f"scene {scene.name} ({scene.source})")
    for p in scene.projectors:
        print(f"  projector {p.name}: {p.width}x{p.height}, f={p.fx:g}px, at {np.round(p.centre, 3).tolist()} m, "
              f"response x^{'/'.join(f'{b:g}' for b in p.response_b)}, black {p.black_level:g}")
    print(f"  camera: {cam.width}x{cam.height}, f={cam.fx:g}px, {cam.channels} channel(s), "
          f"{cam.bit_depth}-bit, {cam.supersampling}x{cam.supersampling} samples per pixel")
    for s in scene.surfaces.values():
        print(f"  surface {s.name}: {s.type} at {np.round(s.world_from_local[:3, 3], 3).tolist()} m")
    for st in scene.states:
        print(f"  state {st.name}: {', '.join(st.surfaces)}")
    return 0


# ---------------------------------------------------------------------------------- simulate
def cmd_simulate(args) -> int:
    from .calib import read_graycode_folder, write_graycode_folder
    from .figures import calibration_summary
    from .pipeline import calibrate_rig, check_calibration
    from .scene import load_scene
    from .sim import VirtualRig

    t_start = time.perf_counter()
    scene = load_scene(args.config)
    rig = VirtualRig(scene, device=args.device)
    timings = {"cast": 0.0, "capture": 0.0, "calibrate": 0.0}
    results, rows = [], []
    with atomic_output(args.out) as stage:
        def through_files(state, j, capture):
            proj = scene.projectors[j]
            folder = stage / "captures" / state / proj.name
            write_graycode_folder(folder, capture, bits=scene.camera.bit_depth)
            return read_graycode_folder(folder, (proj.width, proj.height), bits=args.bits)

        for state, j, capture, cal in calibrate_rig(rig, bits=args.bits, plane_tolerance=args.plane_tolerance,
                                                    noise=not args.no_noise, timings=timings,
                                                    through=through_files if args.write_captures else None):
            result, row = check_calibration(rig, state, j, capture, cal, noise=not args.no_noise)
            out_dir = stage / "calibration" / state / scene.projectors[j].name
            out_dir.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(out_dir / "correspondence.npz", prj_xy=cal.prj_xy.numpy(),
                                prj_xy_integer=cal.decoding.prj_xy.numpy(), cam_xy=cal.cam_xy.numpy(),
                                count=cal.count.numpy(), contrast=cal.decoding.contrast.numpy())
            results.append(result)
            rows.append(row)
        calibration_summary(stage / "calibration.png", rows)
        timings["total"] = time.perf_counter() - t_start
        report = {"scene": scene.name, "config": str(scene.source), "torchproj": __version__,
                  "device": str(rig.device), "noise": not args.no_noise,
                  "timings_s": {k: round(v, 3) for k, v in timings.items()}, "calibrations": results}
        text = _write_report(stage, report, _simulate_markdown)
    print(text)
    print(f"wrote {args.out}/report.json, report.md, calibration.png")
    return 0


def _simulate_markdown(report: dict) -> str:
    lines = [f"# Virtual-rig calibration: {report['scene']}", "",
             "Decoded coordinates against the simulator's truth, over the camera pixels each projector truly "
             "lights. `exact`: decoded cell equals the true cell; RMS: distance to the continuous true "
             "coordinate (projector pixels); `block`: cells per decoded value (a shortened sequence decodes "
             "blocks, and its map is the homography fitted to them: the RMS of the map). Flatness: "
             "compensated ramp plus its mirror, normalised by white - black (ideal 1, std 0).", "",
             "| state | projector | block | decoded | exact | RMS decoded | RMS map | fitted b (true) | "
             "ramp+mirror mean / std |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in report["calibrations"]:
        di, ds = r["decoding_integer"], r["decoding_subpixel"]
        b = "/".join(f"{v:.3f}" for v in r["response_fit"]["b"])
        tb = "/".join(f"{v:g}" for v in r["response_true_b"])
        f = r["compensated_ramp_sum"]
        lines.append(f"| {r['state']} | {r['projector']} | {'x'.join(map(str, r['block_cells']))} | "
                     f"{di['decoded']:.2%} | {di['exact']:.2%} | "
                     f"{di['rms_px']:.3f} | {ds['rms_px']:.3f} | {b} ({tb}) | {f['mean']:.3f} / {f['std']:.3f} |")
    t = report["timings_s"]
    lines += ["", "Timings (s): " + ", ".join(f"{k} {v:.1f}" for k, v in t.items()), ""]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------- run
def _pair(text: str, example: str, strict: bool) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LO,HI such as {example}, got {text!r}") from None
    if not (lo < hi if strict else lo <= hi):
        raise argparse.ArgumentTypeError(f"need LO {'<' if strict else '<='} HI, got {text!r}")
    return lo, hi


def _bounds(text: str) -> tuple[float, float]:
    return _pair(text, "0,255 or -100,255 (8-bit units)", strict=True)


def _limits(text: str) -> tuple[float, float]:
    return _pair(text, "0.5,1.5", strict=False)


def cmd_run(args) -> int:
    from .core.imageio import write_image
    from .pipeline import run_virtual
    from .figures import run_overview
    from .scene import load_scene

    scene = load_scene(args.config)
    gain_offset = None
    if args.gain is not None or args.offset is not None:
        gain_offset = (args.gain or (1.0, 1.0), args.offset or (0.0, 0.0))
    result = run_virtual(scene, solver=args.solver, bounds_8bit=args.bounds, device=args.device,
                         max_iter=args.max_iter, oracle=args.oracle, gain_offset=gain_offset, maps=args.maps,
                         plane_tolerance=args.plane_tolerance, bits=args.bits, objective=args.objective,
                         l2_weight=args.l2_weight, ssim_iter=args.ssim_iter)
    report = result.report
    with atomic_output(args.out) as stage:
        (stage / "patterns").mkdir()
        for proj, pat in zip(scene.projectors, result.patterns):
            write_image(stage / "patterns" / f"{proj.name}.png", pat.float() / 255)
        (stage / "captures").mkdir()
        for state, shot in result.captures.items():
            write_image(stage / "captures" / f"{state}.png", shot, bits=scene.camera.bit_depth)
        run_overview(stage / "overview.png", result.patterns, [p.name for p in scene.projectors], result.targets)
        text = _write_report(stage, report, _run_markdown)
    print(text)
    print(f"wrote {args.out}/report.json, report.md, overview.png, patterns/, captures/")
    return 0


def _add_solve_options(p) -> None:
    """The options of every command that solves patterns (``run``, ``solve``)."""
    from .solve import OBJECTIVES, SOLVERS

    p.add_argument("--solver", default="fista", choices=list(SOLVERS),
                   help="pattern solver (default: fista, the best measured)")
    p.add_argument("--bounds", type=_bounds, default=(0.0, 255.0), metavar="LO,HI",
                   help="solver bounds in 8-bit units as in the paper (default 0,255; eo with -100,255 is EO_-100^255)")
    p.add_argument("--objective", default="l2", choices=list(OBJECTIVES),
                   help="what the patterns optimise: l2 (least squares, default), ssim (SSIM of the predicted camera "
                        "images with a small weight on their squared error) or mixed (a larger weight); the image "
                        "objectives start from the solver's patterns")
    p.add_argument("--l2-weight", type=float, metavar="W",
                   help=f"with --objective ssim or mixed: the weight of the squared error, relative to the start's "
                        f"(defaults: ssim {OBJECTIVES['ssim']:g}, mixed {OBJECTIVES['mixed']:g})")
    p.add_argument("--ssim-iter", type=int, default=30, metavar="N",
                   help="with --objective ssim or mixed: its iterations (default 30)")
    p.add_argument("--device", default="cpu", help="torch device, cpu or cuda (default: cpu)")
    p.add_argument("--max-iter", type=int, default=300, help="iteration limit of iterative solvers (default 300)")


def _add_map_options(p, maps: bool = True, bits: bool = False) -> None:
    if maps:
        p.add_argument("--maps", default="decoded", choices=["decoded", "homography"],
                       help="camera-to-projector maps: decoded per pixel (default), or one homography per state and "
                            "projector fitted to them (scenes where each state is one plane)")
    if bits:
        p.add_argument("--bits", type=int, metavar="K",
                       help=_BITS_HELP + "; each capture is then read through one homography (planar scenes only)")
    p.add_argument("--plane-tolerance", type=float, default=1.0, metavar="PX",
                   help="with --maps homography or --bits: the largest 95th-percentile residual (projector pixels) "
                        "between decoded and fitted coordinates that counts as a plane (default 1)")


_BITS_HELP = ("show only the first K Gray-code pattern pairs per axis (at least 2): 4K + 4 images per projector "
              "and state with white, black and the two ramps, instead of 44 for a 1024x768 projector")


def _image_objective_lines(image: dict | None) -> list[str]:
    if image is None:
        return []
    return [f"Image objective: {image['name']}, 1 - SSIM plus {image['l2_weight']:g} x the relative squared error, "
            f"{image['iterations']} iterations from {image['start']['solver']}'s least-squares patterns; the model "
            f"predicts SSIM " + " / ".join(f"{v:.3f}" for v in image["model_ssim"]) + " (the captures below are what "
            "counts).", ""]


def _run_markdown(report: dict) -> str:
    m, t = report["model"], report["timings_s"]
    adjusted = "gain_offset_limits" in report
    lines = [f"# torchproj run: {report['scene']}, solver {report['solver']}, bounds "
             f"{report['bounds_8bit'][0]:g}..{report['bounds_8bit'][1]:g}", "",
             f"Calibration: {report['calibration']}; maps: {report['maps']}"
             + ("" if report.get("graycode") is None else "; Gray code per projector: " + ", ".join(
                 f"{name} {g['bits'][0]}x{g['bits'][1]} bits ({g['captures_per_state']} captures per state)"
                 for name, g in report["graycode"].items())) + ".", "",
             f"Model: {m['variables']} variables, {m['rows']} rows, {m['nnz']} nonzeros; objective "
             f"{report['objective']:.4g} after {report['iterations']} iterations.", "",
             *_image_objective_lines(report.get("image_objective")),
             f"Evaluation: {report['evaluation']}.", "",
             "| target | state | PSNR (dB) | SSIM | crosstalk | pixels |"
             + (" gain | offset | PSNR vs t | SSIM vs t |" if adjusted else ""),
             "|---|---|---|---|---|---|" + ("---|---|---|---|" if adjusted else "")]
    for r in report["targets"]:
        line = (f"| {r['name']} | {r['state']} | {r['psnr_db']:.2f} | {r['ssim']:.3f} | {r['crosstalk']:.3f} | "
                f"{r['pixels']} |")
        if adjusted:
            line += f" {r['gain']:.3f} | {r['offset']:.3f} | {r['psnr_db_original']:.2f} | {r['ssim_original']:.3f} |"
        lines.append(line)
    if "homographies" in report:
        lines += ["", "Homographies (residual from decoded to fitted coordinates, projector pixels; for Gray-code "
                      "blocks, the distance outside the block over the pixels at block edges):", "",
                  "| state | projector | block (cells) | median | 95th percentile | pixels |", "|---|---|---|---|---|---|"]
        for state, fits in report["homographies"].items():
            lines += [f"| {state} | {j} | {'x'.join(map(str, f['block_cells']))} | {f['median_px']:.3f} | "
                      f"{f['p95_px']:.3f} | {f['points']} |" for j, f in enumerate(fits)]
    lines += ["", "Timings (s): " + ", ".join(f"{k} {v:.2f}" for k, v in t.items()), ""]
    return "\n".join(lines)


# ------------------------------------------------------------------------------- position
def cmd_position(args) -> int:
    from .core.imageio import write_image
    from .experiments import evaluate_positioning
    from .figures import positioning_feedback
    from .scene import load_scene

    scene = load_scene(args.config or "box_positions")
    result = evaluate_positioning(scene, trials=args.trials, spread_mm=args.spread_mm, spread_deg=args.spread_deg,
                                  seed=args.seed, max_evaluations=args.max_evaluations, device=args.device,
                                  max_iter=args.max_iter)
    report = result.report
    with atomic_output(args.out) as stage:
        (stage / "patterns").mkdir()
        for proj, pat in zip(scene.projectors, result.patterns):
            write_image(stage / "patterns" / f"{proj.name}.png", pat.float() / 255)
        (stage / "scans").mkdir()
        goals = {p["name"]: scene.surfaces[p["surface"]] for p in report["positions"]}
        for t in result.trials:
            box = goals[t.position]
            np.savez_compressed(stage / "scans" / f"{t.position}_{t.trial}.npz", points=t.scan["points"],
                                projector=t.scan["projector"], goal_pose=box.world_from_local, placed_pose=t.placed,
                                start_pose=t.start, box_size=np.array(box.size))
        positioning_feedback(stage / "feedback.png", result.profiles,
                             [{"position": t.position, "trial": t.trial, "history": t.history, "rmse_mm": t.rmse_mm}
                              for t in result.trials])
        text = _write_report(stage, report, _position_markdown)
    print(text)
    print(f"wrote {args.out}/report.json, report.md, feedback.png, patterns/, scans/ "
          f"(view a scan: python viz/positioning.py {args.out})")
    return 0


def _position_markdown(report: dict) -> str:
    lines = [f"# torchproj position: {report['scene']}", "",
             f"{report['trials_per_position']} placements per position from starts within "
             f"{report['start_spread']['position_mm']:g} mm and {report['start_spread']['rotation_deg']:g} degrees "
             f"of the goal, at most {report['max_evaluations']} camera looks each.", "",
             f"Method: {report['method']}.", "",
             "| position | box-projector distance (mm) | PSNR at goal (dB) | scanner alone (mm) | RMSE (mm) | "
             "RMSE (% of distance) | paper (%) |",
             "|---|---|---|---|---|---|---|"]
    for p in report["positions"]:
        paper = p.get("paper_rmse_percent")
        lines.append(f"| {p['name']} | {p['projector_distance_mm']:.0f} | {p['psnr_db_at_goal']:.2f} | "
                     f"{p['scanner_rmse_mm']:.2f} | {p['rmse_mm_mean']:.2f} | {p['rmse_percent_mean']:.2f} | "
                     f"{'' if paper is None else f'{paper:.2f}'} |")
    lines += ["", "| position | trial | RMSE (mm) | RMSE (%) | centre off by (mm) | turned by (deg) | "
              "started off by (mm, deg) | feedback start -> end (dB) | looks |",
              "|---|---|---|---|---|---|---|---|---|"]
    for t in report["trials"]:
        e, s = t["pose_error"], t["start_pose_error"]
        lines.append(f"| {t['position']} | {t['trial']} | {t['rmse_mm']:.2f} | {t['rmse_percent']:.3f} | "
                     f"{e['distance_mm']:.1f} | {e['rotation_deg']:.2f} | {s['distance_mm']:.1f}, "
                     f"{s['rotation_deg']:.1f} | {t['feedback_start_db']:.1f} -> {t['feedback_final_db']:.1f} | "
                     f"{t['evaluations']} |")
    lines += ["", "Timings (s): " + ", ".join(f"{k} {v:.1f}" for k, v in report["timings_s"].items()), ""]
    return "\n".join(lines)


def _scan_points(folder: Path, mask: np.ndarray | None) -> np.ndarray:
    """The triangulated points of a ``torchproj decode --calibration`` folder, inside ``mask``."""
    path = folder / "correspondence.npz"
    if not path.is_file():
        raise TorchprojError(f"{path}: not found; give the --out folder of torchproj decode")
    data = np.load(path)
    if "points" not in data:
        raise TorchprojError(f"{path}: holds no points; run torchproj decode with --calibration FILE.xml")
    points = data["points"]
    keep = np.isfinite(points).all(-1)
    if mask is not None:
        if mask.shape != keep.shape:
            raise TorchprojError(f"--mask is {mask.shape[1]}x{mask.shape[0]} but the camera of {folder} is "
                                 f"{keep.shape[1]}x{keep.shape[0]}; paint the mask over a capture of that camera")
        keep &= mask
    return points[keep].astype(np.float64)


def cmd_placement_error(args) -> int:
    from .core.imageio import read_image
    from .experiments import scan_distance

    if args.distance <= 0:
        raise TorchprojError(f"--distance must be the object-projector distance (> 0), got {args.distance:g}")
    mask = None
    if args.mask is not None:
        mask = read_image(args.mask).mean(0).numpy() > 0.5
    placed = _scan_points(args.placed, mask)
    reference = _scan_points(args.reference, mask)
    if len(placed) == 0 or len(reference) == 0:
        raise TorchprojError("no scanned points" + (" inside --mask" if mask is not None else "") + " in "
                             + (str(args.placed) if len(placed) == 0 else str(args.reference)))
    dist = scan_distance(placed, reference)
    rmse = float(np.sqrt(np.mean(dist**2)))
    report = {"placed": str(args.placed), "reference": str(args.reference), "mask": str(args.mask) if args.mask else None,
              "points": int(len(placed)), "reference_points": int(len(reference)),
              "rmse": round(rmse, 4), "median": round(float(np.median(dist)), 4),
              "p95": round(float(np.percentile(dist, 95)), 4), "distance": args.distance,
              "rmse_percent": round(100 * rmse / args.distance, 4),
              "units": "the calibration's (usually mm)",
              "method": "distance from each point of the placed scan to the nearest point of the reference scan "
                        "(the object scanned at its goal pose); percent of --distance"}
    with atomic_output(args.out) as stage:
        write_json(stage / "report.json", report)
    print(f"RMSE {rmse:.3f} ({report['rmse_percent']:.3f}% of {args.distance:g}) over {len(placed)} points; "
          f"median {report['median']:.3f}, 95th percentile {report['p95']:.3f}")
    print(f"wrote {args.out}/report.json")
    return 0


# ------------------------------------------------------------------------------- real rig
def cmd_sequence(args) -> int:
    from .calib import write_sequence

    w, h = args.projector
    with atomic_output(args.out) as stage:
        manifest = write_sequence(stage, w, h, ramp_steps=args.ramp_steps, bits=args.bits)
    print(f"wrote {len(manifest['images'])} images for a {w}x{h} projector and sequence.json to {args.out}: show them "
          "in order and save each capture under the same file name in CAPTURE_ROOT/STATE/PROJECTOR/")
    return 0


def cmd_capture(args) -> int:
    from .calib import OpenCVCamera, OpenCVDisplay, capture_sequence

    x, y = (int(v) for v in args.screen.split(","))
    display, camera = OpenCVDisplay(x, y), OpenCVCamera(args.camera)
    try:
        with atomic_output(args.out) as stage:
            capture_sequence(args.sequence_dir, stage, display, camera, settle_s=args.settle)
    finally:
        display.close()
        camera.close()
    print(f"captured the sequence of {args.sequence_dir} into {args.out}")
    return 0


def _projector_sizes(values: list[str] | None) -> dict[str, tuple[int, int]] | None:
    sizes = {}
    for v in values or []:
        name, _, size = v.rpartition("=")
        sizes[name or "*"] = _size(size)
    return sizes or None


def cmd_calibrate(args) -> int:
    from .calib import calibrate_folders, write_bundle
    from .figures import calibration_summary

    t0 = time.perf_counter()
    if args.calibration is not None and not args.calibration.is_file():
        raise TorchprojError(f"{args.calibration}: calibration file not found")
    bundle = calibrate_folders(args.capture_root, _projector_sizes(args.projector), states=args.states,
                               white_threshold=args.white_threshold, black_threshold=args.black_threshold,
                               max_hole=args.fill_holes, bits=args.bits, plane_tolerance=args.plane_tolerance)
    rows = []
    for state, maps in bundle.states.items():
        for (name, _, _), m, resp, ramp in zip(bundle.projectors, maps, bundle.responses, bundle.ramps):
            row = {"label": f"{state}/{name}", "prj_xy": m["prj_xy"], "error": None, "valid": m["valid"]}
            if ramp is not None:
                row.update(levels=ramp[0].numpy(), measured=ramp[1].numpy(), response=resp)
            rows.append(row)
    with atomic_output(args.out) as stage:
        write_bundle(stage, bundle, args.calibration)
        calibration_summary(stage / "calibration.png", rows)
    missing = [n for (n, _, _), r in zip(bundle.projectors, bundle.responses) if r is None]
    print(f"calibrated {len(bundle.states)} state(s) x {len(bundle.projectors)} projector(s) from {args.capture_root} "
          f"in {time.perf_counter() - t0:.1f} s; decoded: " + ", ".join(
              f"{s}/{p} {f:.1%}" for s, d in bundle.decoded.items() for p, f in d.items()))
    if missing:
        print(f"no ramp captures for {missing}: solve will assume a linear response there", file=sys.stderr)
    print(f"wrote {args.out}/bundle.json, STATE/PROJECTOR.npz, STATE/black.npz, calibration.png")
    return 0


def _targets(values: list[str]) -> list[tuple[str, str]]:
    out = []
    for v in values:
        state, sep, image = v.partition("=")
        if not sep or not state or not image:
            raise TorchprojError(f"--targets {v!r}: expected STATE=IMAGE (an image file or a scikit-image name)")
        out.append((state, image))
    return out


def cmd_solve(args) -> int:
    from .calib import load_bundle
    from .core.imageio import write_image
    from .pipeline import score_image, target_image
    from .solve import image_objective, make_patterns
    from .transport import StateCalibration, Target, build_transport, select_maps, target_on_camera

    t0 = time.perf_counter()
    weight = image_objective(args.objective, args.l2_weight)
    bundle = load_bundle(args.bundle)
    states = StateCalibration.from_bundle(bundle)
    targets = []
    for state, image in _targets(args.targets):
        if state not in states:
            raise TorchprojError(f"--targets {state}={image}: the bundle has no state {state!r}; its states: "
                                 f"{sorted(states)}")
        if any(t.state == state for t in targets):
            raise TorchprojError(f"--targets {state}={image}: state {state!r} already has a target; give one per state")
        targets.append(Target(state, target_image(image, bundle.channels), name=f"{state}"))
    responses = bundle.response_curves()
    lo, hi = (b / 255 for b in args.bounds)
    fitted = ({state: [bundle.homographies[state][name] for name, _, _ in bundle.projectors] for state in bundle.states}
              if bundle.homographies else None)
    states, maps, fits = select_maps(states, args.maps, args.plane_tolerance, fitted)
    op = build_transport(states, targets, merge=weight is None, device=args.device)
    result, light, patterns = make_patterns(op, args.solver, (lo, hi), responses, calibrations=states,
                                            max_iter=args.max_iter, objective=args.objective, l2_weight=weight,
                                            ssim_iter=args.ssim_iter)
    rows = []
    with atomic_output(args.out) as stage:
        (stage / "patterns").mkdir()
        for (name, _, _), pat in zip(bundle.projectors, patterns):
            write_image(stage / "patterns" / f"{name}.png", pat.float() / 255)
        (stage / "predicted").mkdir()
        for t in targets:
            view = states[t.state].predict(light, bundle.black[t.state])
            write_image(stage / "predicted" / f"{t.name}.png", view.clamp(0, 1))
            values, covered = target_on_camera(t, states[t.state].lit())
            scores = score_image(((view - bundle.black[t.state]) / op.scale).clamp(0, 1), values, covered)
            rows.append({"name": t.name, "state": t.state, "pixels": int(covered.sum()),
                         "predicted_psnr_db": scores["psnr_db"], "predicted_ssim": scores["ssim"]})
        report = {"bundle": str(args.bundle), "solver": args.solver, "objective_name": args.objective,
                  "bounds_8bit": list(args.bounds), "model": op.size_report(),
                  "objective": result.info.get("l2_objective", result.objective), "iterations": result.iterations,
                  "scale": op.scale, "timings_s": {"total": round(time.perf_counter() - t0, 3),
                                                   "solve": round(result.time_s, 3)},
                  "predicted": "black capture plus each projector's weight times the light of the decoded cell "
                               "(the calibration's own model; project the patterns and capture to measure)",
                  "targets": rows, "maps": maps,
                  "graycode_bits": {name: list(b) for (name, _, _), b in zip(bundle.projectors, bundle.bits)}}
        if weight is not None:
            report["image_objective"] = {"name": args.objective, "l2_weight": weight, "value": result.objective,
                                         "model_ssim": result.info["model_ssim"]}
        if fits is not None:
            report["homographies"] = fits
        write_json(stage / "report.json", report)
    print(f"solved {len(targets)} target(s) with {args.solver} ({args.objective}): {op.shape[1]} variables, "
          f"least-squares objective {report['objective']:.4g}; wrote {args.out}/patterns/, predicted/, report.json")
    return 0


# ------------------------------------------------------------------------------------ decode
def cmd_decode(args) -> int:
    from .calib import calibrate_projector, read_graycode_folder, read_opencv_calibration, triangulate, write_ply
    from .figures import decode_summary

    calib = read_opencv_calibration(args.calibration) if args.calibration else None
    t_read = time.perf_counter()
    capture = read_graycode_folder(args.capture_dir, args.projector, names=args.names, bits=args.bits)
    t_read = time.perf_counter() - t_read
    cal = calibrate_projector(capture, args.projector, white_threshold=args.white_threshold,
                              black_threshold=args.black_threshold, subpixel=not args.no_subpixel,
                              max_hole=args.fill_holes, bits=args.bits, plane_tolerance=args.plane_tolerance)
    dec = cal.decoding
    report = {"capture_dir": str(args.capture_dir), "projector": list(args.projector),
              "camera": [int(dec.valid.shape[1]), int(dec.valid.shape[0])],
              "valid_fraction": dec.valid_fraction, "read_s": round(t_read, 4),
              "decode_s": round(cal.timings_s["decode"], 4), "maps_s": round(cal.timings_s["maps"], 4),
              "white_threshold": args.white_threshold, "black_threshold": args.black_threshold,
              "subpixel": not args.no_subpixel, "block_cells": list(dec.block)}
    if cal.homography is not None:
        report["homography"] = cal.homography.as_dict()
    arrays = {"prj_xy": dec.prj_xy.numpy().astype(np.float32), "prj_xy_refined": cal.prj_xy.numpy(),
              "valid": dec.valid.numpy(), "contrast": dec.contrast.numpy().astype(np.float32),
              "cam_xy": cal.cam_xy.numpy(), "count": cal.count.numpy().astype(np.int32)}
    points = None
    with atomic_output(args.out) as stage:
        if calib is not None:
            src = cal.prj_xy
            ok = torch.isfinite(src).all(-1)
            ys, xs = torch.nonzero(ok, as_tuple=True)
            cam_xy = torch.stack([xs, ys], -1).double()
            t0 = time.perf_counter()
            pts = triangulate(cam_xy, src[ok].double(), calib).float()
            report["triangulate_s"] = round(time.perf_counter() - t0, 4)
            points = torch.full(ok.shape + (3,), float("nan"))
            points[ok] = pts
            arrays["points"] = points.numpy()
            report["points"] = int(ok.sum())
            grey = (capture.white.mean(0)[ok] * 255).clamp(0, 255).to(torch.uint8).numpy()
            write_ply(stage / "points.ply", pts.numpy(), np.repeat(grey[:, None], 3, 1))
        np.savez_compressed(stage / "correspondence.npz", **arrays)
        write_json(stage / "report.json", report)
        decode_summary(stage / "decoded.png", dec.prj_xy, dec.contrast, points,
                       title=f"{args.capture_dir}: {dec.valid_fraction:.1%} of the camera decoded")
    print(f"decoded {dec.valid_fraction:.1%} of {report['camera'][0]}x{report['camera'][1]} camera pixels in "
          f"{report['decode_s']:.3f} s (reading {t_read:.2f} s)" + (f"; {report['points']} points" if calib else ""))
    print(f"wrote {args.out}/correspondence.npz, report.json, decoded.png" + (", points.ply" if calib else ""))
    return 0


# -------------------------------------------------------------------------------------- main
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="torchproj", description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--version", action="version", version=f"torchproj {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("scene", help="check a scene config and print what it describes")
    p.add_argument("config", nargs="?", help="YAML file or built-in name (default: paper_two_planes)")
    p.set_defaults(func=cmd_scene)

    p = sub.add_parser("run", help="the main job on the virtual rig: calibrate, solve, project, capture, evaluate")
    p.add_argument("config", nargs="?", help="YAML file or built-in name (default: paper_two_planes)")
    p.add_argument("--out", default="out/run", help="output folder (default: out/run)")
    _add_solve_options(p)
    p.add_argument("--oracle", action="store_true",
                   help="build the operator from the simulator's exact geometry instead of calibration "
                        "(shows what calibration costs)")
    p.add_argument("--gain", type=_limits, metavar="LO,HI",
                   help="also optimise one gain per target within these limits (fista; e.g. 0.5,1.5)")
    p.add_argument("--offset", type=_limits, metavar="LO,HI",
                   help="also optimise one offset per target within these limits (fista; e.g. -0.2,0.2)")
    _add_map_options(p, bits=True)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("position", help="the paper's positioning test on the virtual rig: place a box guided only "
                                        "by the projected image, scan it, report the error")
    p.add_argument("config", nargs="?", help="YAML file or built-in name (default: box_positions)")
    p.add_argument("--out", default="out/position", help="output folder (default: out/position)")
    p.add_argument("--trials", type=int, default=3, help="placements per position (default 3, as the paper's subjects)")
    p.add_argument("--spread-mm", type=float, default=20.0,
                   help="a trial starts with each coordinate of the box centre within this of the goal (default 20)")
    p.add_argument("--spread-deg", type=float, default=5.0,
                   help="... and turned by up to this about a random axis (default 5)")
    p.add_argument("--seed", type=int, default=0, help="seeds the start poses and the camera noise (default 0)")
    p.add_argument("--max-evaluations", type=int, default=200, help="camera looks per placement (default 200)")
    p.add_argument("--device", default="cpu", help="torch device, cpu or cuda (default: cpu)")
    p.add_argument("--max-iter", type=int, default=300, help="iteration limit of the pattern solver (default 300)")
    p.set_defaults(func=cmd_position)

    p = sub.add_parser("placement-error", help="score a real placement: a scan of the placed object against a "
                                               "scan of it at the goal (both from torchproj decode --calibration)")
    p.add_argument("placed", type=Path, help="torchproj decode --calibration output of the placed object")
    p.add_argument("--reference", type=Path, required=True,
                   help="torchproj decode --calibration output of the object at its goal pose")
    p.add_argument("--distance", type=float, required=True,
                   help="object-projector distance, in the calibration's units, for the percentage")
    p.add_argument("--mask", type=Path, help="camera-sized image, white on the object: score only those pixels")
    p.add_argument("--out", type=Path, default=Path("out/placement_error"), help="output folder")
    p.set_defaults(func=cmd_placement_error)

    p = sub.add_parser("simulate", help="calibrate every state and projector of a scene on the virtual rig, "
                                        "and check the result against the simulator's truth")
    p.add_argument("config", nargs="?", help="YAML file or built-in name (default: paper_two_planes)")
    p.add_argument("--out", default="out/simulate", help="output folder (default: out/simulate)")
    p.add_argument("--device", default="cpu", help="torch device, cpu or cuda (default: cpu)")
    p.add_argument("--no-noise", action="store_true", help="capture without camera noise")
    p.add_argument("--write-captures", action="store_true",
                   help="also write each capture as a folder of PNGs (the layout of a real capture) and "
                        "calibrate from those files")
    _add_map_options(p, maps=False, bits=True)
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("sequence", help="write the images to show on a projector, in order, with sequence.json")
    p.add_argument("--projector", type=_size, required=True, help="projector resolution WIDTHxHEIGHT, e.g. 1024x768")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--ramp-steps", type=int, default=32, help="bars in the photometric ramp (default 32)")
    p.add_argument("--bits", type=int, metavar="K", help=_BITS_HELP + "; for scenes where each state is one plane, "
                                                         "read through a homography")
    p.set_defaults(func=cmd_sequence)

    p = sub.add_parser("capture", help="show a sequence full-screen on a projector and grab a camera frame for each "
                                       "image (needs an OpenCV build with a GUI)")
    p.add_argument("sequence_dir", type=Path, help="folder from torchproj sequence")
    p.add_argument("--out", type=Path, required=True, help="CAPTURE_ROOT/STATE/PROJECTOR folder to write")
    p.add_argument("--camera", type=int, default=0, help="OpenCV camera index (default 0)")
    p.add_argument("--screen", default="0,0", metavar="X,Y", help="top-left corner of the projector's screen in the "
                                                                 "desktop (default 0,0; e.g. 1920,0 for a second screen)")
    p.add_argument("--settle", type=float, default=0.2, help="seconds between showing and grabbing (default 0.2)")
    p.set_defaults(func=cmd_capture)

    p = sub.add_parser("calibrate", help="decode every state and projector of a capture root into a calibration bundle")
    p.add_argument("capture_root", type=Path, help="CAPTURE_ROOT/STATE/PROJECTOR/ folders of captures")
    p.add_argument("--out", type=Path, required=True, help="bundle folder")
    p.add_argument("--projector", action="append", metavar="[NAME=]WxH",
                   help="projector size where a folder holds no sequence.json (repeat per projector)")
    p.add_argument("--states", nargs="+", metavar="STATE", help="state folders to calibrate (default: all)")
    p.add_argument("--calibration", type=Path, help="OpenCV camera-projector calibration to keep in the bundle")
    p.add_argument("--white-threshold", type=float, default=5, help="8-bit units (OpenCV default 5)")
    p.add_argument("--black-threshold", type=float, default=40, help="8-bit units (OpenCV default 40)")
    p.add_argument("--fill-holes", type=int, default=16, metavar="N", help="fill holes up to N pixels (0: off)")
    p.add_argument("--bits", type=int, metavar="K", help="Gray-code pattern pairs per axis of a shortened sequence, "
                                                         "where folders hold no sequence.json (which says its own)")
    _add_map_options(p, maps=False)
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("solve", help="patterns for real projectors from a calibration bundle and target images")
    p.add_argument("bundle", type=Path, help="bundle folder from torchproj calibrate")
    p.add_argument("--targets", nargs="+", required=True, metavar="STATE=IMAGE",
                   help="the image to show in each state (a file, or a scikit-image name such as astronaut)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    _add_solve_options(p)
    _add_map_options(p)
    p.set_defaults(func=cmd_solve)

    p = sub.add_parser("decode", help="decode a folder of real Gray-code captures (and triangulate)")
    p.add_argument("capture_dir", type=Path, help="folder of captures: Gray code in order, then white, then black")
    p.add_argument("--projector", type=_size, required=True, help="projector resolution WIDTHxHEIGHT, e.g. 1024x768")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--calibration", type=Path, help="OpenCV camera-projector calibration (XML/YAML) to triangulate")
    p.add_argument("--names", default="graycode_{:02d}.png", help="file name template (default: graycode_{:02d}.png)")
    p.add_argument("--white-threshold", type=float, default=5, help="8-bit units (OpenCV default 5)")
    p.add_argument("--black-threshold", type=float, default=40, help="8-bit units (OpenCV default 40)")
    p.add_argument("--no-subpixel", action="store_true", help="triangulate integer cells, no sub-pixel fit")
    p.add_argument("--fill-holes", type=int, default=16, metavar="N", help="fill holes up to N pixels (0: off)")
    p.add_argument("--bits", type=int, metavar="K", help="the folder holds a shortened sequence, the first K pattern "
                                                         "pairs per axis: read it through one homography (a plane)")
    _add_map_options(p, maps=False)
    p.set_defaults(func=cmd_decode)
    return parser


_PAIR_OPTIONS = ("--bounds", "--gain", "--offset")


def _join_negative_pairs(argv: list[str]) -> list[str]:
    """``--bounds -100,255`` -> ``--bounds=-100,255``: argparse takes a value starting with '-' (and
    not a plain number) for an option, so the paper's own notation would otherwise be refused."""
    out, i = [], 0
    while i < len(argv):
        if argv[i] in _PAIR_OPTIONS and i + 1 < len(argv) and re.fullmatch(r"-[\d.]+,-?[\d.]+", argv[i + 1]):
            out.append(f"{argv[i]}={argv[i + 1]}")
            i += 2
        else:
            out.append(argv[i])
            i += 1
    return out


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``torchproj`` console command."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(_join_negative_pairs(argv))
    try:
        return args.func(args)
    except TorchprojError as exc:
        print(f"torchproj {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
