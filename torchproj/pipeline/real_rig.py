"""Patterns for a real rig, from a calibration bundle and target images (``torchproj solve``).

The same solve as on the virtual rig (:func:`~torchproj.solve.make_patterns`); without a rig to
capture on, each target's view is predicted by the calibration's own model, and the bench's camera
is what measures.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..calib import CalibrationBundle, load_bundle
from ..core.checks import check
from ..solve import SolveResult, check_solve_options, image_objective, make_patterns
from ..solve.compensate import resolve_smoothness
from ..transport import COLOUR_WEIGHTS, DEFAULT_FOOTPRINT, StateCalibration, Target, select_maps, target_on_camera
from .footprint import AUTO, check_footprint, choose_footprint
from ..transport.build import build_operators
from .run import image_objective_report
from .scoring import score_image
from .targets import check_target_channels, image_with_channels, target_image

__all__ = ["BundleSolution", "solve_bundle"]

PREDICTED = ("black capture plus each projector's weight times the light of the cells of the decoded coordinate's "
             "footprint (the calibration's own model; project the patterns and capture to measure)")


@dataclass
class BundleSolution:
    """What :func:`solve_bundle` made: the 8-bit patterns, each target's predicted view, the report."""

    report: dict
    patterns: dict[str, torch.Tensor]  # projector name -> (C, H_j, W_j) uint8
    predicted: dict[str, torch.Tensor] = field(default_factory=dict)  # target name -> (C, H, W) in [0, 1]
    solution: SolveResult | None = None

    def write(self, folder) -> None:
        """``patterns/PROJECTOR.png``, ``predicted/TARGET.png`` and ``report.json`` into ``folder``."""
        from ..core.imageio import write_image
        from ..core.output import write_json

        folder = Path(folder)
        (folder / "patterns").mkdir(parents=True, exist_ok=True)
        for name, pattern in self.patterns.items():
            write_image(folder / "patterns" / f"{name}.png", pattern.float() / 255)
        (folder / "predicted").mkdir(exist_ok=True)
        for name, view in self.predicted.items():
            write_image(folder / "predicted" / f"{name}.png", view.clamp(0, 1))
        write_json(folder / "report.json", self.report)


def _bundle_targets(bundle: CalibrationBundle, wanted) -> list[Target]:
    """Each of ``wanted`` as a :class:`Target` of the bundle's: a ``"STATE=IMAGE"`` string, a ``(state,
    image)`` pair (an image file, a scikit-image name or a :math:`(C, H, W)` tensor) or a Target."""
    states = set(bundle.states)
    check(isinstance(wanted, (list, tuple)) and len(wanted) > 0,
          f"targets must be a list of STATE=IMAGE strings, (state, image) pairs or Targets, got {wanted!r}")
    targets = []
    for item in wanted:
        if isinstance(item, Target):
            state, image = item.state, None
        else:
            if isinstance(item, str):
                state, sep, image = item.partition("=")
            elif isinstance(item, (tuple, list)) and len(item) == 2:
                (state, image), sep = item, "="
            else:
                state = sep = image = ""
            check(bool(sep and isinstance(state, str) and state and (isinstance(image, torch.Tensor) or image)),
                  f"target {item!r}: expected STATE=IMAGE (an image file or a scikit-image name), a (state, image) "
                  "pair or a Target")
        label = f"{state}={image}" if isinstance(image, str) else f"for state {state!r}"
        check(state in states, f"target {label}: the bundle has no state {state!r}; its states: {sorted(states)}")
        check(all(t.state != state for t in targets),
              f"target {label}: state {state!r} already has a target; give one per state")
        targets.append(item if isinstance(item, Target) else
                       Target(state, image_with_channels(image, bundle.channels), name=state)
                       if isinstance(image, torch.Tensor) else
                       Target(state, target_image(image, bundle.channels), name=state))
    check_target_channels(targets, bundle.channels)
    return targets


@dataclass
class BundleProblem:
    """What a bundle and its targets ask of a solve, checked: the one place ``solve`` and ``refine`` read
    their options (:func:`bundle_problem`)."""

    bundle: CalibrationBundle
    targets: list[Target]
    states: dict[str, StateCalibration]
    bounds: tuple[float, float]  # linear light
    image: object  # the image objective, or None for least squares
    footprint: str  # the footprint solved with (auto resolved)
    colour_weights: str
    maps: str
    fits: dict | None
    choice: object = None  # the FootprintChoice where footprint was auto


def bundle_problem(bundle, targets: list, *, solver: str, bounds_8bit, objective, maps: str, footprint: str,
                   plane_tolerance: float, colour_weights: str, outside: str, chains: str, device) -> BundleProblem:
    """Load and check a bundle, its targets and the solve's options (:func:`solve_bundle`'s arguments)."""
    image = image_objective(objective)
    check(colour_weights in COLOUR_WEIGHTS, f"colour_weights must be one of {list(COLOUR_WEIGHTS)}, got {colour_weights!r}")
    bundle = bundle if isinstance(bundle, CalibrationBundle) else load_bundle(bundle)
    lo, hi = check_solve_options(solver, bounds_8bit, len(bundle.projectors), outside, chains)
    check_footprint(footprint)
    wanted = _bundle_targets(bundle, targets)
    fitted = ({state: [bundle.homographies[state][name] for name, _, _ in bundle.projectors] for state in bundle.states}
              if bundle.homographies else None)
    states, maps, fits = select_maps(StateCalibration.from_bundle(bundle), maps, plane_tolerance, fitted,
                                     [name for name, _, _ in bundle.projectors])
    choice = None
    if footprint == AUTO:
        choice = choose_footprint(states, wanted, (lo, hi), device=device)
        footprint = choice.footprint
    return BundleProblem(bundle, wanted, states, (lo, hi), image, footprint, colour_weights, maps, fits, choice)


def solve_bundle(bundle, targets: list, *, solver: str = "fista", bounds_8bit=(0, 255),
                 objective="l2", maps: str = "decoded", footprint: str = DEFAULT_FOOTPRINT,
                 plane_tolerance: float = 1.0, max_iter: int | None = None, device="cpu", progress=None,
                 outside: str = "clip", chains: str = "epipolar", colour_weights: str = "channel",
                 smoothness: float | None = None) -> BundleSolution:
    """Solve the patterns that show each image in its state, from a bench's calibration.

    Args:
        bundle: a :class:`~torchproj.calib.CalibrationBundle` or its folder (``torchproj calibrate``).
        targets: ``"STATE=IMAGE"`` strings, ``(state, image)`` pairs (an image file, a scikit-image
            test-image name or a :math:`(C, H, W)` tensor) or :class:`~torchproj.transport.Target` objects,
            one per state.
        solver, bounds_8bit, objective, maps, footprint, plane_tolerance, max_iter,
        device, outside, chains, colour_weights, smoothness: as :func:`~torchproj.pipeline.run_virtual`; the
        predicted views use the weights the solve used.
    """
    t0 = time.perf_counter()
    smoothness = resolve_smoothness(solver, smoothness)
    problem = bundle_problem(bundle, targets, solver=solver, bounds_8bit=bounds_8bit, objective=objective, maps=maps,
                             footprint=footprint, plane_tolerance=plane_tolerance, colour_weights=colour_weights,
                             outside=outside, chains=chains, device=device)
    bundle, wanted, states, maps, fits = problem.bundle, problem.targets, problem.states, problem.maps, problem.fits
    lo, hi = problem.bounds
    image, choice, footprint, colour_weights = problem.image, problem.choice, problem.footprint, problem.colour_weights
    # Bilinear rows almost never repeat: merging them costs time and saves nothing (run_virtual).
    ops = build_operators(states, wanted, merge=image is None and footprint == "nearest", footprint=footprint,
                          colour_weights=colour_weights, device=device)
    if len(ops) == 1:  # the predicted views follow the weights solved with
        states = {name: dataclasses.replace(s, colour_weight=None) for name, s in states.items()}
    op = ops[0]
    result, light, patterns = make_patterns(ops, solver, (lo, hi), bundle.response_curves(), calibrations=states,
                                            max_iter=max_iter, progress=progress, objective=image, outside=outside,
                                            chains=chains, solver_options=choice and choice.solver_options(ops, solver),
                                            smoothness=smoothness)
    rows, predicted = [], {}
    for t in wanted:
        view = states[t.state].predict(light, bundle.black[t.state], footprint)
        predicted[t.name] = view
        values, covered = target_on_camera(t, states[t.state].lit())
        scores = score_image(((view - bundle.black[t.state]) / op.scale).clamp(0, 1), values, covered)
        rows.append({"name": t.name, "state": t.state, "pixels": int(covered.sum()),
                     "predicted_psnr_db": scores["psnr_db"], "predicted_ssim": scores["ssim"]})
    report = {"solver": solver, "bounds_8bit": list(bounds_8bit), "outside": outside, "smoothness": smoothness,
              **({"chains": chains} if solver == "eo" else {}),
              "model": op.size_report(), "objective": result.info.get("l2_objective", result.objective),
              "iterations": result.iterations, "scale": op.scale,
              "timings_s": {"total": round(time.perf_counter() - t0, 3), "solve": round(result.time_s, 3)},
              "predicted": PREDICTED, "targets": rows, "maps": maps, "footprint": footprint,
              "colour_weights": "channel" if len(ops) > 1 else "grey",
              "graycode_bits": {name: list(b) for (name, _, _), b in zip(bundle.projectors, bundle.bits)}}
    if image is not None:
        report["image_objective"] = image_objective_report(result)
    if fits is not None:
        report["homographies"] = fits
    if choice is not None:
        report["footprint_choice"] = choice.as_dict()
    return BundleSolution(report=report, patterns={name: p for (name, _, _), p in zip(bundle.projectors, patterns)},
                          predicted=predicted, solution=result)
