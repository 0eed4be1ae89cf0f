"""The camera loop on a bench, over files (``torchproj refine``).

On the virtual rig the loop captures by itself (:func:`~torchproj.pipeline.run_virtual`'s
``refine``); on a bench a person (or ``torchproj capture``) shows the patterns and takes the photos.
``refine_bundle`` therefore runs in turns over a working folder:

    FOLDER/loop.json                        the loop's options (a later turn must give the same)
    FOLDER/step_K/patterns/PROJECTOR.png    what to show in step K, every projector at once
    FOLDER/step_K/captures/STATE.png        the camera's photo of each target's state, taken by you
    FOLDER/best/patterns/PROJECTOR.png      after the last step: the best captured patterns
    FOLDER/report.json, report.md           each step's captured PSNR per target, so far

Each turn replays the loop (:func:`~torchproj.solve.refine_patterns`) from the start over the
captures already in the folder: the solve and every update are deterministic, so the same patterns
come back, and a step whose photos are missing is where the turn stops, after writing that step's
patterns. Nothing the person put there is ever removed or overwritten. A photo of the wrong size or
colour, or named after no state of the calibration, is refused naming the file, and so is one that
shows another state's light (:func:`_check_photos`). With a live bench
(``torchproj refine --camera``, :class:`~torchproj.pipeline.acquire.LiveBench`) torchproj shows the
patterns and takes the photos itself, into the same folder, and the loop runs to its end in one turn.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import torch

from ..core.checks import check, check_path, is_whole
from ..core.errors import CaptureError, InputError
from ..core.imageio import read_image, write_image
from ..core.output import write_json
from ..solve import make_patterns
from ..solve.compensate import resolve_smoothness
from ..solve.refine import _rows, captured_loss, refine_patterns
from ..transport import DEFAULT_FOOTPRINT
from .real_rig import bundle_problem
from .register import Reregister
from .shown import CapturedRows
from ..transport.build import build_operators

__all__ = ["refine_bundle"]

LOOP_FILE = "loop.json"


class _Waiting(Exception):
    """Raised inside the loop's ``measure`` where a step's photos are not there yet."""

    def __init__(self, step: int, missing: list[str]):
        super().__init__(step)
        self.step, self.missing = step, missing


def refine_bundle(bundle, targets: list, folder, *, iterations: int = 4, solver: str = "fista", bounds_8bit=(0, 255),
                  objective="l2", maps: str = "decoded", footprint: str = DEFAULT_FOOTPRINT, plane_tolerance: float = 1.0,
                  colour_weights: str = "channel", outside: str = "clip", chains: str = "epipolar",
                  max_iter: int | None = None, register: bool = True, device="cpu", live=None,
                  smoothness: float | None = None) -> dict:
    """One turn of the camera loop over files (module docstring).

    Args:
        bundle: a calibration bundle's folder (``torchproj calibrate``).
        targets: ``"STATE=IMAGE"`` strings, as :func:`~torchproj.pipeline.solve_bundle`.
        folder: the loop's working folder (created on the first turn).
        iterations: updates after the first photos: ``iterations + 1`` photos per state in all.
        register: fit the light's moves from each capture (:class:`~torchproj.pipeline.register.Reregister`),
            for a projector or camera that moved since calibration.
        live: None, or a :class:`~torchproj.pipeline.acquire.LiveBench` that shows each step's
            patterns and takes its photos itself: the whole loop then runs in one turn.
        solver, bounds_8bit, objective, maps, footprint, plane_tolerance, colour_weights, outside,
            chains, max_iter, device, smoothness: as :func:`~torchproj.pipeline.solve_bundle` (the start's solve).

    Returns:
        the report: ``waiting`` (the step whose photos are wanted, and which) or ``done``, and per
        captured step its loss and PSNR per target.
    """
    # The loop's options are kept in its folder by name, so that a later turn can tell it is the same
    # loop: the bundle by its folder, each target by its STATE=IMAGE text.
    check_path(bundle, "bundle", "a calibration bundle folder (torchproj calibrate's --out)")
    check_path(folder, "folder", "the loop's working folder")
    check(isinstance(targets, (list, tuple)) and all(isinstance(t, str) or (isinstance(t, (list, tuple)) and len(t) == 2
                                                                             and all(isinstance(v, str) for v in t))
                                                     for t in targets),
          f"targets must be STATE=IMAGE strings or (state, image name) pairs, the loop keeps them by name; got {targets!r}")
    folder = Path(folder)
    check(is_whole(iterations) and 0 <= iterations <= 100, f"iterations must be a whole number in [0, 100], "
                                                           f"got {iterations!r}")
    options = {"bundle": str(Path(bundle).resolve()), "targets": [str(t) for t in targets], "iterations": iterations,
               "solver": solver, "bounds_8bit": list(bounds_8bit), "objective": str(objective), "maps": maps,
               "footprint": footprint, "plane_tolerance": plane_tolerance, "colour_weights": colour_weights,
               "outside": outside, "chains": chains, "max_iter": max_iter, "register": register,
               "smoothness": resolve_smoothness(solver, smoothness)}
    _check_options(folder, options)
    problem = bundle_problem(bundle, targets, solver=solver, bounds_8bit=bounds_8bit, objective=objective, maps=maps,
                             footprint=footprint, plane_tolerance=plane_tolerance, colour_weights=colour_weights,
                             outside=outside, chains=chains, device=device)
    bundle, wanted, states, (lo, hi), image = problem.bundle, problem.targets, problem.states, problem.bounds, problem.image
    footprint, colour_weights = problem.footprint, problem.colour_weights
    ops = build_operators(states, wanted, merge=False, footprint=footprint, colour_weights=colour_weights,
                          device=device)
    responses = bundle.response_curves()
    start, _, _ = make_patterns(ops, solver, (lo, hi), responses, calibrations=states, objective=image,
                                outside=outside, chains=chains, max_iter=max_iter, progress=False,
                                smoothness=options["smoothness"])
    names = [name for name, _, _ in bundle.projectors]
    shape = (bundle.channels, bundle.camera_size[1], bundle.camera_size[0])
    steps = []
    measure = _folder_measure(folder, names, wanted, bundle.black, ops, shape, steps, live, responses)
    remodel = Reregister(states, wanted, footprint=footprint, colour_weights=colour_weights, device=device) \
        if register else None
    report = {"options": options, "camera": list(shape), "steps": steps}
    folder.mkdir(parents=True, exist_ok=True)
    write_json(folder / LOOP_FILE, options)
    try:
        refined = refine_patterns(ops, start.patterns, measure, (lo, hi), responses, iterations=iterations,
                                  objective=image or "l2", outside=outside, remodel=remodel, progress=False)
    except _Waiting as wait:
        report["waiting"] = {"step": wait.step, "photos": wait.missing,
                             "show": str(folder / f"step_{wait.step:02d}" / "patterns")}
    else:
        best = folder / "best" / "patterns"
        best.mkdir(parents=True, exist_ok=True)
        for name, img in zip(names, refined.images):
            write_image(best / f"{name}.png", img.float() / 255)
        report["done"] = {"best_step": refined.best, "patterns": str(best)}
    write_json(folder / "report.json", report)
    (folder / "report.md").write_text(refine_markdown(report))
    return report


def _check_options(folder: Path, options: dict) -> None:
    """A later turn must ask for the same loop: its photos were taken of that loop's patterns."""
    path = folder / LOOP_FILE
    if not path.is_file():
        check(not folder.exists() or not any(folder.iterdir()), f"{folder}: exists and holds files but no {LOOP_FILE}: "
                                                                "give the loop a folder of its own (a new --out)")
        return
    try:
        before = json.loads(path.read_text())
    except (OSError, ValueError):
        raise CaptureError(f"{path}: unreadable; give the loop a new --out folder") from None
    changed = sorted(k for k in options if before.get(k) != options[k])
    check(not changed, f"{folder}: its loop was started with other {', '.join(changed)} ({', '.join(f'{k}={before.get(k)!r}' for k in changed)}): "
                       "its photos are of that loop's patterns; give the same options or a new --out folder")


def _folder_measure(folder: Path, names: list[str], targets, black: dict, ops, shape, steps: list, live=None,
                    responses=None):
    """The loop's ``measure`` over the working folder: step K's photos (taken by ``live`` where they are
    missing), or the patterns to show and a stop. With the ``responses``, each photo is held against
    the light the model predicts for its state (:func:`_check_photos`)."""
    read = CapturedRows(ops, targets)
    states = list(read.rows_of)

    def measure(images: list[torch.Tensor]) -> torch.Tensor:
        k = len(steps)
        step = folder / f"step_{k:02d}"
        _write_or_compare(step / "patterns", names, images)
        captures = step / "captures"
        present = {p.stem: p for p in captures.iterdir() if p.is_file()} if captures.is_dir() else {}
        for stem, path in present.items():
            if stem not in states:
                raise CaptureError(f"{path}: names no state of this loop's targets ({', '.join(states)}); rename it "
                                   "STATE.png or move it out of the folder")
        if live is not None and any(s not in present for s in states):
            live.photograph(dict(zip(names, images)), [s for s in states if s not in present], captures)
            present = {p.stem: p for p in captures.iterdir() if p.is_file()}
        missing = [f"{captures / s}.png" for s in states if s not in present]
        if missing:
            raise _Waiting(k, missing)
        above = {}
        for state in states:
            photo = read_image(present[state])
            if tuple(photo.shape) != shape:
                raise CaptureError(f"{present[state]}: size {tuple(photo.shape)} (C, H, W), but the calibration's camera "
                                   f"gives {shape}; take the photo with the camera and settings of the calibration")
            above[state] = photo - black[state].to(photo)
        if responses is not None:
            _check_photos(read, above, _rows(ops, _shown_light(ops, images, responses)), present)
        rows = read(above)
        loss, psnr = captured_loss(ops, rows)
        steps.append({"step": k, "loss": loss, "psnr_db": psnr})
        return rows

    return measure


# How far a photo may lie from the light the model predicts for its state (squared error over the
# state's rows, over the prediction's own): past WRONG_STATE_MISS it is refused where another state's
# prediction explains it at least twice as well, past PHOTO_MISMATCH warned about. On the tests' small
# two-plane benches a photo misses its own state's by 0.04-0.07% unchanged and 1.5-3.1% with a projector
# moved 3 mm or its lamp 25% brighter, and the other state's by 31-106% (benchmarks/photo_states.py).
WRONG_STATE_MISS, PHOTO_MISMATCH = 0.1, 0.5


def _shown_light(ops, images: list[torch.Tensor], responses) -> torch.Tensor:
    """The columns the 8-bit ``images`` make the projectors emit, :math:`(N_{cols}, C)`: each cell's
    relative light, :func:`~torchproj.solve.compensate` undone (:meth:`ResponseCurve.from_pattern`)."""
    op = ops[0] if isinstance(ops, (list, tuple)) else ops
    channels = len(ops) if isinstance(ops, (list, tuple)) and len(ops) > 1 else op.rhs.shape[1]
    p = torch.zeros(op.shape[1], channels, dtype=torch.float64, device=op.rhs.device)
    for j, (image, response) in enumerate(zip(images, responses)):
        y = response.from_pattern(image.to(p.device, torch.float64) / 255)
        cells = y.reshape(y.shape[0], -1).T  # (cells, C)
        cells = cells if cells.shape[1] == channels else cells.mean(1, keepdim=True).expand(-1, channels)
        mine = op.column_projector == j
        p[mine] = cells[op.column_cell[mine]]
    return p.to(op.rhs.dtype)


def _check_photos(read: CapturedRows, above: dict, predicted: torch.Tensor, files: dict) -> None:
    """Refuse a photo whose light is another state's: it matches that state's predicted rows at least
    twice as well as its own state's, which it misses by more than :data:`WRONG_STATE_MISS` (photos
    saved under each other's names, or the scene set up as another state). Warn where a photo misses
    its own state's prediction by more than :data:`PHOTO_MISMATCH`."""
    def miss(state: str, image: torch.Tensor) -> float:
        want = predicted[read.rows_of[state]].double()
        return float((read.state_rows(image, state).double() - want).pow(2).sum() / want.pow(2).sum().clamp_min(1e-12))

    for state, image in above.items():
        own = miss(state, image)
        others = {other: miss(other, image) for other in above if other != state}
        better = min(others, key=others.get, default=None)
        if better is not None and own > WRONG_STATE_MISS and others[better] < own / 2:
            raise CaptureError(f"{files[state]}: shows the light of state {better!r}, not {state!r} (it misses the "
                               f"model's prediction for {better!r} by {others[better]:.1%} and for {state!r} by "
                               f"{own:.1%}, squared and relative): were the photos saved under each other's names, or "
                               f"the scene set up as {better!r}? Take it again with {state!r} set up, or rename the files")
        if own > PHOTO_MISMATCH:
            warnings.warn(f"{files[state]}: differs from the light the model predicts for state {state!r} by "
                          f"{own:.0%} (squared, relative): check that this step's patterns were shown with every "
                          "projector on, and that the room's light, the camera and the projectors are as at "
                          "calibration (the loop follows small moves, not large ones)", stacklevel=2)


def _write_or_compare(folder: Path, names: list[str], images: list[torch.Tensor]) -> None:
    """Write a step's patterns; where they are there already (an earlier turn), check that the replay
    gave the same (a changed bundle or target file would not)."""
    for name, img in zip(names, images):
        path = folder / f"{name}.png"
        if not path.is_file():
            folder.mkdir(parents=True, exist_ok=True)
            write_image(path, img.float() / 255)
            continue
        shown = (read_image(path) * 255).round()
        differ = float(((shown - img.float().cpu()).abs() > 1).float().mean()) if shown.shape == img.shape else 1.0
        if differ > 1e-3:
            raise InputError(f"{path}: the loop now gives other patterns for this step ({differ:.1%} of the cells) than "
                             "it wrote before: the bundle or a target image changed since; give a new --out folder")


def refine_markdown(report: dict) -> str:
    """``report.md`` of ``torchproj refine``."""
    lines = ["# Camera loop on a bench", "",
             "Each step's photos against the targets: the loss the loop minimises and the PSNR per target "
             "(camera values above the calibration's black, on the targets' pixels).", "",
             "| step | loss | PSNR per target (dB) |", "|---|---|---|"]
    for s in report["steps"]:
        lines.append(f"| {s['step']} | {s['loss']:.4g} | {' / '.join(f'{v:.2f}' for v in s['psnr_db'])} |")
    if "waiting" in report:
        w = report["waiting"]
        lines += ["", f"Waiting for step {w['step']}: show `{w['show']}` (every projector at once), photograph each "
                  "state and save the photos as " + ", ".join(f"`{p}`" for p in w["photos"]) + "; then run the same "
                  "command again."]
    else:
        d = report["done"]
        lines += ["", f"Done: the best photos were step {d['best_step']}'s; its patterns are in `{d['patterns']}`."]
    return "\n".join(lines) + "\n"
