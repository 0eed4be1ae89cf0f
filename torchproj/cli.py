"""The ``torchproj`` command: it parses arguments and calls the library, nothing more.

It imports the library only inside the command that runs (the parser reads its choices from
:mod:`torchproj.core.choices`), so ``torchproj --help`` answers in a fraction of a second.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading
import time
import warnings
from pathlib import Path

from . import __version__
from .cli_options import (BITS_HELP, cache_option, command, config_option, decoding_options, device_options, existing_file,
                          join_negative_pairs, limits, map_options, named_projector_size, named_screen_corner,
                          projector_size, screen_corner, solve_options, solver_options)
from .core.errors import TorchprojError
from .core.output import atomic_output, check_inputs_outside, check_output_folder, write_json

__all__ = ["main", "build_parser"]


def _publish(out, write, files: str) -> None:
    """Write into a staging folder that becomes ``out`` only when complete (nothing half-written on a
    failure), then print what ``write`` returned (a report, or None) and what was written."""
    with atomic_output(out) as stage:
        text = write(Path(stage))
    if text:
        print(text)
    print(f"wrote {out}/{files}")


def _objective(args):
    from .solve import image_objective

    return image_objective(args.objective, args.l2_weight, None if args.psnr_drop < 0 else args.psnr_drop,
                           args.ssim_iter)


# ----------------------------------------------------------------------------- virtual rig
def _scene(args):
    from .scene import load_scene

    return load_scene(args.config, size_limit=args.size_limit)


def cmd_scene(args) -> int:
    from .pipeline import describe_light

    scene = _scene(args)
    print(scene.describe())
    print(describe_light(scene))
    return 0


def cmd_simulate(args) -> int:
    from .pipeline import simulate_scene

    _publish(args.out, lambda stage: simulate_scene(_scene(args), stage, device=args.device, noise=not args.no_noise,
                                                    bits=args.bits, plane_tolerance=args.plane_tolerance,
                                                    write_captures=args.write_captures),
             "report.json, report.md, calibration.png")
    return 0


def _solver_args(args) -> dict:
    """The solver options every solving command shares (``cli_options.solver_options``)."""
    return dict(solver=args.solver, bounds_8bit=args.bounds, outside=args.outside, chains=args.chains)


def cmd_run(args) -> int:
    from .pipeline import run_virtual

    gain_offset = None if args.gain is None and args.offset is None else (args.gain or (1, 1), args.offset or (0, 0))
    result = run_virtual(_scene(args), **_solver_args(args), device=args.device, max_iter=args.max_iter,
                         oracle=args.oracle, gain_offset=gain_offset, maps=args.maps,
                         plane_tolerance=args.plane_tolerance, bits=args.bits, objective=_objective(args),
                         footprint=args.footprint, ceiling=args.ceiling, colour_weights=args.colour_weights,
                         refine=args.refine, refine_frames=args.refine_frames, refine_relax=args.refine_relax,
                         cache=not args.no_cache, smoothness=args.smoothness)
    _publish(args.out, result.write, "report.json, report.md, overview.png, patterns/, captures/")
    return 0


def cmd_position(args) -> int:
    from .experiments import evaluate_positioning

    scene = _scene(args)
    result = evaluate_positioning(scene, trials=args.trials, spread_mm=args.spread_mm, spread_deg=args.spread_deg,
                                  seed=args.seed, max_evaluations=args.max_evaluations, device=args.device,
                                  max_iter=args.max_iter, cache=not args.no_cache, **_solver_args(args))
    _publish(args.out, lambda stage: result.write(stage, scene), "report.json, report.md, feedback.png, patterns/, "
             f"scans/ (view a scan: python viz/positioning.py {args.out})")
    return 0


# -------------------------------------------------------------------------------- real rig
def cmd_placement_error(args) -> int:
    from .experiments import placement_error

    report = placement_error(args.placed, args.reference, args.distance, args.mask)
    print(f"RMSE {report['rmse']:.3f} ({report['rmse_percent']:.3f}% of {args.distance:g}) over {report['points']} "
          f"points; median {report['median']:.3f}, 95th percentile {report['p95']:.3f}")
    _publish(args.out, lambda stage: write_json(stage / "report.json", report), "report.json")
    return 0


def cmd_sequence(args) -> int:
    from .calib import write_sequence

    w, h = args.projector
    with atomic_output(args.out) as stage:
        manifest = write_sequence(stage, w, h, ramp_steps=args.ramp_steps, bits=args.bits)
    print(f"wrote {len(manifest['images'])} images for a {w}x{h} projector and sequence.json to {args.out}: show them "
          "in order and save each capture under the same file name in CAPTURE_ROOT/STATE/PROJECTOR/")
    return 0


def cmd_capture(args) -> int:
    from .pipeline import capture_sequence

    with atomic_output(args.out) as stage:
        capture_sequence(args.sequence_dir, stage, settle_s=args.settle, camera_index=args.camera,
                         screen=args.screen, frames=args.frames)
    print(f"captured the sequence of {args.sequence_dir} into {args.out}")
    return 0


def cmd_calibrate(args) -> int:
    from .calib import calibrate_folders, write_bundle
    from .figures import calibration_summary

    t0 = time.perf_counter()
    bundle = calibrate_folders(args.capture_root, dict(args.projector or []) or None, states=args.states,
                               white_threshold=args.white_threshold, black_threshold=args.black_threshold,
                               dim_threshold=args.dim_threshold, max_hole=args.fill_holes, bits=args.bits, plane_tolerance=args.plane_tolerance)
    with atomic_output(args.out) as stage:
        write_bundle(stage, bundle, args.calibration)
        calibration_summary(stage / "calibration.png", bundle.figure_rows(),
                            title="Fig. 1: calibration of the bench's captures, per state and projector")
    print(f"calibrated {args.capture_root} in {time.perf_counter() - t0:.1f} s: {bundle.summary()}")
    print(f"wrote {args.out}/bundle.json, STATE/PROJECTOR.npz, STATE/black.npz, calibration.png")
    return 0


def cmd_solve(args) -> int:
    from .pipeline import solve_bundle

    solution = solve_bundle(args.bundle, args.targets, **_solver_args(args), objective=_objective(args),
                            footprint=args.footprint, colour_weights=args.colour_weights, maps=args.maps,
                            plane_tolerance=args.plane_tolerance, max_iter=args.max_iter, device=args.device,
                            smoothness=args.smoothness)
    solution.report["bundle"] = str(args.bundle)
    print(f"solved {len(solution.predicted)} target(s) with {args.solver} ({args.objective}): "
          f"{solution.report['model']['variables']} variables, least-squares objective "
          f"{solution.report['objective']:.4g}")
    _publish(args.out, solution.write, "patterns/, predicted/, report.json")
    return 0


def cmd_refine(args) -> int:
    from .pipeline.bench_loop import refine_bundle

    with _live_bench(args) as live:
        report = refine_bundle(args.bundle, args.targets, args.out, iterations=args.iterations, **_solver_args(args),
                               objective=_objective(args), footprint=args.footprint, colour_weights=args.colour_weights,
                               maps=args.maps, plane_tolerance=args.plane_tolerance, max_iter=args.max_iter,
                               register=not args.no_register, device=args.device, live=live,
                               smoothness=args.smoothness)
    for s in report["steps"]:
        print(f"step {s['step']}: PSNR " + " / ".join(f"{v:.2f}" for v in s["psnr_db"]) + " dB")
    if "waiting" in report:
        w = report["waiting"]
        print(f"show {w['show']} (every projector at once), photograph each state into "
              + ", ".join(w["photos"]) + ", then run this command again")
    else:
        print(f"done: the best photos were step {report['done']['best_step']}'s; patterns in {report['done']['patterns']}")
    return 0


@contextlib.contextmanager
def _live_bench(args):
    """``refine --camera``: a full-screen window per projector at its ``--screen`` and the camera, closed
    afterwards; None without ``--camera``."""
    if args.camera is None:
        yield None
        return
    from .calib import load_bundle
    from .core import InputError
    from .pipeline.acquire import LiveBench, OpenCVCamera, OpenCVDisplay, check_capture_options

    check_capture_options(args.settle, args.frames)  # before any window opens
    names = [name for name, _, _ in load_bundle(args.bundle).projectors]
    screens = dict(args.screen or [])
    unknown = sorted(set(screens) - set(names))
    if unknown:
        raise InputError(f"--screen names projector(s) {unknown} the bundle does not have; its projectors: {names}")
    if len(names) > 1 and set(screens) != set(names):
        raise InputError(f"--camera shows every projector at once: give each its screen, --screen NAME=X,Y for "
                         f"{sorted(set(names) - set(screens))}")
    opened = []
    try:
        displays = {}
        for name in names:
            displays[name] = OpenCVDisplay(*screens.get(name, (0, 0)), name=f"torchproj {name}")
            opened.append(displays[name])
        camera = OpenCVCamera(args.camera)
        opened.append(camera)
        yield LiveBench(displays, camera, settle_s=args.settle, frames=args.frames,
                        prompt=lambda state: input(f"place the scene in state {state!r}, then press Enter "))
    finally:
        for device in opened:
            device.close()


def cmd_decode(args) -> int:
    from .calib import decode_folder

    decoded = decode_folder(args.capture_dir, args.projector, calibration=args.calibration, names=args.names,
                            white_threshold=args.white_threshold, black_threshold=args.black_threshold,
                            subpixel=not args.no_subpixel, fill_holes=args.fill_holes, bits=args.bits,
                            plane_tolerance=args.plane_tolerance)
    print(decoded.summary())
    _publish(args.out, decoded.write, "correspondence.npz, report.json, decoded.png"
             + (", points.ply" if decoded.points is not None else ""))
    return 0


# ------------------------------------------------------------------------------------ parser
def _virtual_rig_commands(sub) -> None:
    p = command(sub, "scene", cmd_scene, "check a scene config and print what it describes", out="")
    config_option(p)

    from .core.choices import ORACLES

    p = command(sub, "run", cmd_run, "the main job on the virtual rig: calibrate, solve, project, capture, "
                 "evaluate", out="out/run")
    config_option(p)
    solve_options(p)
    p.add_argument("--oracle", nargs="?", const="geometry", choices=list(ORACLES),
                   help="skip calibration: geometry (the default) takes the simulator's exact maps into calibration's "
                        "model; transport solves on the simulator's own light transport (the best any calibration "
                        "can reach)")
    p.add_argument("--ceiling", action="store_true", help="also score the transport oracle on the same targets and "
                   "rows, solved with the same objective (least squares, or --objective's), beside each target in "
                   "the report")
    p.add_argument("--refine", type=int, default=0, metavar="N", help="camera in the loop: N times show the patterns, "
                   "capture every state and correct them from what the camera saw; the best captured patterns are "
                   "kept (default 0: none). A scene's show: section changes the world after calibration")
    p.add_argument("--refine-frames", type=int, default=1, metavar="F", help="captures averaged per state in each "
                   "loop step, against camera noise (default 1)")
    p.add_argument("--refine-relax", type=float, default=1.0, metavar="R", help="the share of each capture's "
                   "defect the loop takes, in (0, 1]: below 1 it averages camera noise over captures (default 1)")
    cache_option(p)
    p.add_argument("--gain", type=limits, metavar="LO,HI", help="also optimise a gain per target (fista; e.g. 0.5,1.5)")
    p.add_argument("--offset", type=limits, metavar="LO,HI", help="... and an offset (fista; e.g. -0.2,0.2)")
    map_options(p, bits=BITS_HELP + "; each capture is then read through one homography (planar scenes only)")

    p = command(sub, "position", cmd_position, "the paper's positioning test on the virtual rig: place a box guided "
                 "only by the projected image, scan it, report the error", out="out/position")
    config_option(p, "box_positions")
    p.add_argument("--trials", type=int, default=3, help="placements per position (default 3, as the paper's subjects)")
    p.add_argument("--spread-mm", type=float, default=20.0, help="a trial starts with each coordinate of the box "
                   "centre within this of the goal (default 20)")
    p.add_argument("--spread-deg", type=float, default=5.0, help="... turned by up to this (default 5)")
    p.add_argument("--seed", type=int, default=0, help="seeds the start poses and the camera noise (default 0)")
    p.add_argument("--max-evaluations", type=int, default=200, help="camera looks per placement (default 200)")
    cache_option(p)
    solver_options(p)
    device_options(p)

    p = command(sub, "simulate", cmd_simulate, "calibrate every state and projector of a scene on the virtual rig, "
                 "and check the result against the simulator's truth", out="out/simulate")
    config_option(p)
    device_options(p, max_iter=False)
    p.add_argument("--no-noise", action="store_true", help="capture without camera noise")
    p.add_argument("--write-captures", action="store_true",
                   help="also write each capture as a folder of PNGs (the layout of a real capture) and "
                        "calibrate from those files")
    map_options(p, maps=False, bits=BITS_HELP + "; each capture is then read through one homography "
                                                  "(planar scenes only)")


def _real_rig_commands(sub) -> None:
    p = command(sub, "placement-error", cmd_placement_error, "score a real placement: a scan of the placed object "
                 "against a scan of it at the goal (both from torchproj decode --calibration)",
                 out="out/placement_error")
    p.add_argument("placed", type=Path, help="torchproj decode --calibration output of the placed object")
    p.add_argument("--reference", type=Path, required=True,
                   help="torchproj decode --calibration output of the object at its goal pose")
    p.add_argument("--distance", type=float, required=True,
                   help="object-projector distance, in the calibration's units, for the percentage")
    p.add_argument("--mask", type=Path, help="camera-sized image, white on the object: score only those pixels")

    from .core.choices import RAMP_STEPS

    p = command(sub, "sequence", cmd_sequence, "write the images to show on a projector, in order, with sequence.json: "
                "Gray code, white, black, the ramps and a checkerboard pair")
    p.add_argument("--projector", type=projector_size, required=True, help="projector resolution WIDTHxHEIGHT, e.g. 1024x768")
    p.add_argument("--ramp-steps", type=int, default=RAMP_STEPS, help=f"bars in the photometric ramp (default {RAMP_STEPS})")
    p.add_argument("--bits", type=int, metavar="K", help=BITS_HELP + "; for scenes where each state is one plane, "
                                                         "read through a homography")

    p = command(sub, "capture", cmd_capture, "show a sequence full-screen on a projector and grab a camera frame for "
                 "each image (needs an OpenCV build with a GUI)", out_help="CAPTURE_ROOT/STATE/PROJECTOR to write")
    p.add_argument("sequence_dir", type=Path, help="folder from torchproj sequence")
    p.add_argument("--camera", type=int, default=0, help="OpenCV camera index (default 0)")
    p.add_argument("--screen", type=screen_corner, default="0,0", metavar="X,Y", help="top-left corner of the "
                   "projector's screen in the desktop (default 0,0; e.g. 1920,0 for a second screen)")
    p.add_argument("--settle", type=float, default=0.2, help="seconds between showing and grabbing (default 0.2)")
    p.add_argument("--frames", type=int, default=1, help="camera frames averaged per image, written as 16-bit PNGs "
                   "where more than one (default 1; 16 quarter the noise a calibration carries)")

    from .core.choices import DIM_THRESHOLD

    p = command(sub, "calibrate", cmd_calibrate, "decode every state and projector of a capture root into a "
                 "calibration bundle", out_help="bundle folder")
    p.add_argument("capture_root", type=Path, help="CAPTURE_ROOT/STATE/PROJECTOR/ folders of captures")
    p.add_argument("--projector", action="append", type=named_projector_size, metavar="[NAME=]WxH",
                   help="projector size where a folder holds no sequence.json (repeat per projector)")
    p.add_argument("--states", nargs="+", metavar="STATE", help="state folders to calibrate (default: all)")
    p.add_argument("--calibration", type=existing_file,
                   help="OpenCV camera-projector calibration to keep in the bundle")
    decoding_options(p)
    p.add_argument("--dim-threshold", type=float, default=DIM_THRESHOLD, metavar="LEVEL",
                   help="8-bit units: read the code down to this white minus black too, so that a projector's dim "
                        "light on pixels another one lights is modelled (default %(default)g; --black-threshold's "
                        "value or more: off)")
    map_options(p, maps=False, bits="Gray-code pattern pairs per axis of a shortened sequence, where folders hold "
                                     "no sequence.json (which says its own)")

    p = command(sub, "solve", cmd_solve, "patterns for real projectors from a calibration bundle and target images")
    p.add_argument("bundle", type=Path, help="bundle folder from torchproj calibrate")
    p.add_argument("--targets", nargs="+", required=True, metavar="STATE=IMAGE",
                   help="the image to show in each state (a file, or a scikit-image name such as astronaut)")
    solve_options(p)
    map_options(p)

    p = command(sub, "refine", cmd_refine, "the camera loop on a bench, in turns over a folder: write the patterns to "
                "show, read your photos of each state, write the next patterns (run again after each photo)",
                out_help="the loop's working folder (your photos go into it; nothing you put there is removed)")
    p.set_defaults(workspace=True)  # --out is the loop's working folder, added to, never replaced
    p.add_argument("bundle", type=Path, help="bundle folder from torchproj calibrate")
    p.add_argument("--targets", nargs="+", required=True, metavar="STATE=IMAGE",
                   help="the image to show in each state (a file, or a scikit-image name such as astronaut)")
    p.add_argument("--iterations", type=int, default=4, metavar="N",
                   help="updates after the first photos: N + 1 photos per state in all (default 4)")
    p.add_argument("--no-register", action="store_true",
                   help="do not fit the light's moves from the photos (nothing moved since calibration)")
    p.add_argument("--camera", type=int, metavar="N", help="live: show the patterns full-screen and photograph each "
                   "state with OpenCV camera N (a prompt asks you to set up each state), the whole loop in one run")
    p.add_argument("--screen", type=named_screen_corner, action="append", metavar="NAME=X,Y",
                   help="live: the top-left corner of a projector's screen in the desktop (repeat per projector)")
    p.add_argument("--settle", type=float, default=0.2, help="live: seconds between showing and grabbing (default 0.2)")
    p.add_argument("--frames", type=int, default=1, help="live: camera frames averaged per photo (default 1)")
    solve_options(p)
    map_options(p)

    p = command(sub, "decode", cmd_decode, "decode a folder of real Gray-code captures (and triangulate)")
    p.add_argument("capture_dir", type=Path, help="folder of captures: Gray code in order, then white, then black")
    p.add_argument("--projector", type=projector_size, help="projector resolution WIDTHxHEIGHT, e.g. 1024x768, where the "
                   "folder holds no sequence.json (which says its own)")
    p.add_argument("--calibration", type=existing_file,
                   help="OpenCV camera-projector calibration (XML/YAML) to triangulate")
    p.add_argument("--names", default="graycode_{:02d}.png", help="file name template (default: graycode_{:02d}.png)")
    decoding_options(p)
    p.add_argument("--no-subpixel", action="store_true", help="triangulate integer cells, no sub-pixel fit")
    map_options(p, maps=False, bits="the folder holds a shortened sequence, the first K pattern pairs per axis: "
                                     "read it through one homography (a plane)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="torchproj", description="Multi-projector depth-dependent projection: patterns that show a chosen image "
        "on each of several surfaces or positions. Start with `torchproj run` (the built-in virtual rig); `torchproj "
        "COMMAND --help` for a command's options.")
    parser.add_argument("--version", action="version", version=f"torchproj {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    _virtual_rig_commands(sub)
    _real_rig_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``torchproj`` console command."""
    argv = sys.argv[1:] if argv is None else list(argv)
    # SIGTERM (a scheduler stopping the job) unwinds like Ctrl-C, so that staging folders are removed;
    # both are caught from here on, the parser's imports of the library included.
    previous = signal.signal(signal.SIGTERM, _interrupt) if threading.current_thread() is threading.main_thread() else None
    args = None
    try:
        args = build_parser().parse_args(join_negative_pairs(argv))
        if getattr(args, "out", None) is not None:
            check_output_folder(args.out, replace=not getattr(args, "workspace", False))  # before the work
            if not getattr(args, "workspace", False):
                check_inputs_outside(args.out, _inputs(args))
        with warnings.catch_warnings():
            # The library's warnings (a state that decoded little, a missing ramp) in the command's own voice.
            warnings.showwarning = lambda message, *_: print(f"torchproj {args.command}: warning: {message}",
                                                             file=sys.stderr)
            return args.func(args)
    except BrokenPipeError:  # the reader went away (torchproj scene | head): stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except (TorchprojError, OSError) as exc:  # OSError: a disk full or a folder that turned read-only mid-run
        print(f"{_who(args)}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        out = getattr(args, "out", None)
        where = f"; {out} is as it was" if out is not None and not getattr(args, "workspace", False) else \
            "; nothing was written" if args is None else ""
        print(f"{_who(args)}: interrupted{where}", file=sys.stderr)
        return 130
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


# The arguments that name what a command reads, as its messages name them.
_INPUT_ARGS = {"config": "scene file", "placed": "placed scan", "reference": "reference scan", "mask": "--mask",
               "sequence_dir": "sequence folder", "capture_root": "capture root", "calibration": "--calibration",
               "bundle": "calibration bundle", "capture_dir": "capture folder"}


def _inputs(args) -> dict[str, Path]:
    """The files and folders ``args`` reads that exist (a built-in scene's name is no path), by what
    names each; ``--targets``' image files among them."""
    named = ((what, getattr(args, dest, None)) for dest, what in _INPUT_ARGS.items())
    found = {what: Path(path) for what, path in named if path is not None and Path(path).exists()}
    for pair in getattr(args, "targets", None) or []:
        image = pair.partition("=")[2] if isinstance(pair, str) else None
        if image and Path(image).exists():
            found[f"--targets image {image}"] = Path(image)
    return found


def _who(args) -> str:
    """The command's name in its messages (``torchproj`` alone before the arguments are parsed)."""
    return "torchproj" if args is None else f"torchproj {args.command}"


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def console() -> None:
    """The ``torchproj`` program: :func:`main`, then the interpreter's exit with Ctrl-C ignored.

    By then the command has written its result or refused, and torch's finalizers run at exit: a Ctrl-C
    landing there printed a traceback ("Exception ignored in atexit callback") under the command's own
    last line, found by ``TORCHPROJ_FUZZ=all``'s signals. SIGTERM's default ends the process silently."""
    try:
        code = main()
    except KeyboardInterrupt:  # in the instant between the command's end and here
        code = 130
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    sys.exit(code)


if __name__ == "__main__":
    console()
