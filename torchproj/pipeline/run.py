"""The main job on the virtual rig: calibrate, build, solve, compensate, project, capture, evaluate.

The evaluation captures are rendered by the simulator from the physics, never computed as ``A p``:
the solver only knows what calibration recovered, so calibration errors show in the numbers.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..calib import SATURATED_SHARE, sequence_bits
from ..core.checks import check, is_whole
from ..core.errors import InputError
from ..scene.config import Scene, check_scene
from ..scene.show import describe_show
from ..solve import (SolveResult, check_solve_options, image_objective, make_patterns, projectable_patterns,
                     solve_gain_offset)
from ..solve.compensate import ILL_POSED_MESSAGE, check_solver_options, iteration_limit, resolve_smoothness, unexplained
from ..solve.gain_offset import check_gain_offset
from ..solve.refine import check_relax, refine_patterns
from ..transport import COLOUR_WEIGHTS, DEFAULT_FOOTPRINT, MAPS, Target, build_transport, select_maps
from ..transport.build import build_operators, used_colour_weights
from .ceiling import check_linear_camera, light_transport, solve_on_light_transport
from .footprint import AUTO, check_footprint, choose_footprint
from .register import Reregister
from .shown import rig_measure, shown_world
from .scoring import EVALUATION, TargetScore, evaluate_patterns, score_image
from .targets import checked_images, scene_targets
from .cache import (NOT_KEPT, cached_calibration, cached_transport, calibration_key, keep_geometry, keep_normal_matrices,
                    read_geometry, read_normal_matrices, scene_as_calibrated, smoothed_key, transport_key,
                    writing_behind)
from .virtual import VirtualCalibration, calibrate_virtual, check_shown_light, check_virtual_calibration, true_responses

__all__ = ["CEILING_ITERATIONS", "ORACLES", "RunResult", "image_objective_report", "run_markdown", "run_virtual"]

from ..core.choices import ORACLES  # noqa: E402  what an oracle run takes from the simulator (run_virtual's ``oracle``)
MAX_REFINE = 100  # camera-loop updates a run may ask for: each is a capture of every state
CEILING_ITERATIONS = 3000  # FISTA's limit for the ceiling: it stops on its gap long before on the shipped scenes


@dataclass
class RunResult:
    """Everything a run produced. ``report`` is what ``report.json`` holds."""

    report: dict
    patterns: list[torch.Tensor]  # per projector, (C, H_j, W_j) uint8
    captures: dict[str, torch.Tensor]  # per state, (C, H, W) float in [0, 1]
    targets: list[TargetScore] = field(default_factory=list)  # per target, its score, capture and image on the camera
    solution: SolveResult | None = None  # the solver's own result (values in its bounds, history)
    scene: Scene | None = None
    calibration: VirtualCalibration | None = None  # what the run solved on (given, read from the cache or simulated)

    def write(self, folder) -> str:
        """``report.json``, ``report.md``, ``overview.png``, ``patterns/`` and ``captures/`` into ``folder``.

        Returns the markdown report.
        """
        from ..core.imageio import write_image
        from ..core.output import write_json
        from ..figures import run_overview

        folder = Path(folder)
        names = [p.name for p in self.scene.projectors]
        (folder / "patterns").mkdir(parents=True, exist_ok=True)
        for name, pattern in zip(names, self.patterns):
            write_image(folder / "patterns" / f"{name}.png", pattern.float() / 255)
        (folder / "captures").mkdir(exist_ok=True)
        for state, shot in self.captures.items():
            write_image(folder / "captures" / f"{state}.png", shot, bits=self.scene.camera.stored_bits)
        run_overview(folder / "overview.png", self.patterns, names, self.targets,
                     title=f"Fig. 1: torchproj run: scene {self.report['scene']}, solver {self.report['solver']}, footprint "
                           f"{self.report.get('footprint', 'nearest')}")
        text = run_markdown(self.report)
        write_json(folder / "report.json", self.report)
        (folder / "report.md").write_text(text)
        return text


def _check_calibration_of(calibration, scene: Scene) -> None:
    """A calibration given to a run must be of the run's scene as calibrated: one of another scene (another
    size, another rig) was solved and scored in its own world, and the report named the scene given."""
    check_virtual_calibration(calibration)
    if scene_as_calibrated(calibration.rig.scene) != scene_as_calibrated(scene):
        theirs, ours = calibration.rig.scene, scene
        raise InputError(f"the calibration is of scene {theirs.name!r} (camera {theirs.camera.width}x"
                         f"{theirs.camera.height}), which differs from scene {ours.name!r} (camera {ours.camera.width}x"
                         f"{ours.camera.height}) in more than its name, targets and show: section; calibrate this "
                         "scene, or pass its own scene")


def run_virtual(scene: Scene, *, solver: str = "fista", bounds_8bit=(0, 255), images: list[torch.Tensor] | None = None,
                device="cpu", max_iter: int | None = None, progress=None, calibration: VirtualCalibration | None = None,
                oracle: bool | str = False, gain_offset: tuple[tuple[float, float], tuple[float, float]] | None = None,
                maps: str = "decoded", plane_tolerance: float = 1.0, bits: int | None = None,
                objective="l2", footprint: str = DEFAULT_FOOTPRINT, ceiling: bool = False, outside: str = "clip",
                chains: str = "epipolar", solver_options: dict | None = None,
                colour_weights: str = "channel", refine: int = 0, refine_frames: int = 1,
                refine_relax: float = 1.0, cache: bool = False, smoothness: float | None = None) -> RunResult:
    """Run the whole workflow on the virtual rig for the scene's targets (:meth:`Scene.target_specs`).

    Args:
        scene: the scene; its ``targets`` (or one per state) say which image goes where.
        solver: ``fista`` (default, the best measured), ``pgd``, ``adam``, ``lf`` or ``eo``.
        bounds_8bit: solver bounds in 8-bit units as in the paper (``(-100, 255)`` with ``eo`` is
            ``EO_-100^255``); bounds outside [0, 255] are brought into range afterwards.
        images: one :math:`(C, h, w)` image per target; default: the config's, else scikit-image's.
        device: torch device for the rig and the solver.
        max_iter: iteration limit of the pattern solver (None: 300 for the gradient solvers, LF and EO
            their own convergence rules; :data:`~torchproj.solve.compensate.PIPELINE_ITERATIONS`).
        progress: progress bars (None: on a terminal, for steps longer than a second).
        calibration: reuse an earlier :func:`calibrate_virtual` of the same scene.
        oracle: ``"geometry"`` (or True): build the operator from the simulator's exact geometry
            instead of calibration, with calibration's footprint model (what the maps cost);
            ``"transport"``: solve on the simulator's own light transport (:mod:`.ceiling`: what the
            whole model costs, the best any calibration can reach). With ``calibration`` given,
            ``"geometry"`` is ignored (that calibration's own mode counts) and ``"transport"``
            solves on the exact light at that calibration's rows.
        gain_offset: ``((gain_lo, gain_hi), (offset_lo, offset_hi))`` to optimise one gain and offset
            per target with FISTA (:func:`~torchproj.solve.solve_gain_offset`); None asks for the
            images as they are. Metrics then compare with the adjusted image ``g t + o``, and the
            report also scores against the original.
            A scene with a ``show`` section (:mod:`torchproj.scene.show`) is calibrated as written and
            its patterns are shown, captured and scored in the changed world
            (:func:`~torchproj.pipeline.shown_world`); the oracles and the ceiling are that world's.
        maps: ``"decoded"`` (default: the per-pixel Gray-code maps) or ``"homography"`` (one fitted
            homography per state and projector, :func:`~torchproj.transport.planar_calibration`;
            for scenes where each state is one plane; refused otherwise).
        plane_tolerance: with ``maps="homography"`` or ``bits``, the largest 95th-percentile
            residual (projector pixels) between decoded and fitted coordinates that counts as a plane.
        bits: calibrate with the first ``bits`` Gray-code pattern pairs per axis only, read through
            one homography per state and projector (:func:`calibrate_virtual`); planar scenes.
            Ignored when ``calibration`` is given.
        objective: ``l2`` (least squares, the solver's own), ``ssim`` or ``mixed`` (SSIM of the
            predicted images with a small or a larger weight on their squared error, each target
            within 1 dB of least squares), or an :class:`~torchproj.solve.ImageObjective`; the
            image objectives start from the solver's patterns (:func:`~torchproj.solve.solve_ssim`).
        footprint: the projector cells each camera pixel's light is modelled on: ``"nearest"``
            (one per projector, as the paper), ``"bilinear"`` (the four around its sub-pixel
            coordinate) or ``"area"`` (the cells its area covers, the default:
            :data:`~torchproj.transport.DEFAULT_FOOTPRINT`; :func:`~torchproj.transport.build_transport`),
            or ``"auto"``: the least costly of nearest and area whose expected loss, from the
            calibration's measured cell shares, is within 0.2 dB (:func:`~torchproj.pipeline.choose_footprint`;
            ``report.json``'s ``footprint_choice`` says which and why).
        ceiling: also solve the same targets, rows and bounds on the simulator's own light transport
            (FISTA, least squares, to convergence; then the run's image ``objective`` with its options,
            where one is asked) and score it the same way: each report row gets ``ceiling = {psnr_db,
            ssim}``, the best any calibration could give that target under that objective.
        outside: how values solved outside [0, 255] are shown: ``clip`` (below black shows black) or
            ``map`` (the bounds map linearly onto 0..255); :func:`~torchproj.solve.to_projectable`.
        chains: ``eo``'s independent problems: ``epipolar`` (the paper's; two projectors) or
            ``components`` (connected components of the transport; any number of projectors).
        solver_options: further keywords for the solver (e.g. ``{"normalise": "projector"}`` for
            ``lf``, :func:`~torchproj.solve.solve_lf`); the report keeps them.
        colour_weights: with a colour camera and colour targets, ``"channel"`` (default) models
            each channel with its own white minus black and solves the channels apart
            (:func:`~torchproj.transport.build_channel_transports`); ``"grey"`` gives every
            channel their mean. Gain/offset couples the channels and uses grey; an image objective
            refines the channels' solution together, each channel with its own weights;
            report.json ``colour_weights`` says which was used.
        refine: camera-in-the-loop updates after the solve (:func:`~torchproj.solve.refine_patterns`):
            show, capture every state, correct, ``refine`` times; the best captured iterate is kept
            and scored. ``report.json``'s ``refine`` holds each capture's loss and PSNRs and the
            start's scores. 0: none.
        refine_frames: captures averaged per state and update (camera noise).
        refine_relax: the share of each capture's defect the loop takes (1: all).
        smoothness: weight of the penalty on neighbouring cells' differences in the model's
            least-squares solve (:meth:`~torchproj.transport.TransportOperator.with_smoothness`);
            None: :data:`~torchproj.core.choices.DEFAULT_SMOOTHNESS` for fista, pgd and adam, 0 for
            lf and eo; report.json's ``smoothness`` says which was used.
        cache: read the simulated calibration from the cache where the same scene was calibrated
            before, else keep it there (:mod:`.cache`; ``torchproj run`` does unless ``--no-cache``);
            report.json ``calibration_cache`` says ``read``, ``stored``, ``recomputed``, ``not kept`` or ``off``; the
            transport built from a cached calibration is kept beside it, and ``transport_cache``
            says the same of it.
    """
    check_scene(scene)
    oracle, bounds, image = _check_run(scene, solver, oracle, gain_offset, objective, bounds_8bit, maps, ceiling,
                                       outside, chains, (refine, refine_frames, refine_relax))
    smoothness = _check_smoothness(solver, smoothness, oracle, gain_offset)
    check(colour_weights in COLOUR_WEIGHTS, f"colour_weights must be one of {list(COLOUR_WEIGHTS)}, got {colour_weights!r}")
    check_footprint(footprint)
    check_solver_options(solver_options)
    iteration_limit(max_iter, solver)  # max_iter checked before the calibration, not at the solve
    images = checked_images(scene, images)  # a missing image file, or one image too few, is refused before the work
    check_shown_light(scene, device)
    t_total = time.perf_counter()
    # Cache entries are written on a background thread while the run goes on (1.2 GB on the default
    # scene); the block waits for them before the report says what was kept.
    with writing_behind() as behind:
        cached = None
        calibrated_with = dict(oracle=oracle is not None, bits=bits, plane_tolerance=plane_tolerance)
        if calibration is not None:
            _check_calibration_of(calibration, scene)
            cal = calibration
        elif cache:
            cal, cached = cached_calibration(scene, device=device, progress=progress, **calibrated_with)
        else:
            cal = calibrate_virtual(scene, device, progress, **calibrated_with)
        timings = {"calibrate": cal.seconds if calibration is None else 0.0}
        cast = {}  # how the cache served the rays cast through the world the patterns are shown in

        def read_cast(rig):
            if not rig.cast_geometry():  # a calibration simulated in this run has cast them already
                cast["how"] = read_geometry(rig)

        world = shown_world(cal, scene, prepare=None if cached is None else read_cast)
        if cached is not None and world is cal:
            read_cast(cal.rig)
        if cached is not None and cast.get("how") is None and _cast_all(world.rig):
            cast["how"] = keep_geometry(world.rig)  # now, so that writing it overlaps the run; nothing casts more
        t0 = time.perf_counter()
        states, maps, fits = select_maps(cal.states, maps, plane_tolerance, cal.homographies,
                                         [p.name for p in scene.projectors])
        if fits is not None and cal.homographies is None:
            timings["homography"] = time.perf_counter() - t0
        targets = scene_targets(scene, images, cal.rig)
        choice = None
        if footprint == AUTO:
            choice = choose_footprint(states, targets, bounds, device=device)
            footprint, timings["footprint"] = choice.footprint, choice.seconds

        exact = oracle == "transport"
        if gain_offset is not None or exact:
            colour_weights = "grey"  # these couple the channels (the transport oracle has its own per-channel light)
        # The transport of a cached calibration is kept beside it: the same scene and targets again (another
        # solver, objective or bounds) read it instead of building it.
        keyed = None if cached is None else calibration_key(scene, **calibrated_with) + f"/maps={maps}"
        solved = _build_and_solve(world if exact else cal, states, targets, bounds, solver=solver, image=image, exact=exact,
                                  gain_offset=gain_offset, footprint=footprint, max_iter=max_iter, progress=progress,
                                  device=device, timings=timings, outside=outside, chains=chains,
                                  solver_options=solver_options, colour_weights=colour_weights, start=choice,
                                  rows_on_camera=refine > 0, cache_key=keyed, smoothness=smoothness)
        refined = None
        if refine:
            t0 = time.perf_counter()
            measure = rig_measure(world, solved.ops, targets, refine_frames)
            remodel = None if exact else Reregister(states, targets, footprint=footprint, colour_weights=colour_weights,
                                                    device=device)
            refined = refine_patterns(solved.ops, solved.result.patterns, measure, bounds, cal.responses,
                                      iterations=refine, objective=image or "l2", relax=refine_relax, outside=outside,
                                      progress=progress, remodel=remodel)
            timings["refine"] = time.perf_counter() - t0
            start_scores = evaluate_patterns(world, solved.patterns, targets, scale=solved.scale, states=states,
                                             paper=False).targets
            solved.patterns = refined.images
        solved.release_operators()
        t0 = time.perf_counter()
        evaluation = evaluate_patterns(world, solved.patterns, targets, scale=solved.scale, states=states)
        scores, rows = _target_rows(scene, evaluation.targets, solved.result.info if gain_offset is not None else None)
        timings["evaluate"] = time.perf_counter() - t0
        if ceiling:
            t0 = time.perf_counter()
            # With a gain and offset, the run is scored against the images it fitted (g t + o): the ceiling
            # is asked for the same images, so that the two columns compare like with like.
            asked = targets if gain_offset is None else _fitted_targets(targets, solved.result.info)
            for row, score in zip(rows, _ceiling(world, states, asked, bounds, footprint, progress, device, outside,
                                                 image)):
                row["ceiling"] = {"psnr_db": score.psnr_db, "ssim": score.ssim}
            timings["ceiling"] = time.perf_counter() - t0
        if cached is not None and cast.get("how") is None:
            t0 = time.perf_counter()
            cast["how"] = keep_geometry(world.rig)
            timings["keep"] = timings.get("keep", 0.0) + time.perf_counter() - t0
        t0 = time.perf_counter()
    if behind.handed:  # what the run waited for the cache's writes after its own work
        timings["keep"] = timings.get("keep", 0.0) + time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_total
    report = _report(scene, cal, solver, image, bounds_8bit, device, maps, solved, timings, rows, gain_offset, oracle)
    report["footprint"] = footprint
    if choice is not None:
        report["footprint_choice"] = choice.as_dict()
    report["colour_weights"] = "channel" if solved.channels > 1 and not exact else "grey"
    report["calibration_cache"] = NOT_KEPT if "calibration" in behind.refused else cached or "off"
    report["transport_cache"] = NOT_KEPT if "transport" in behind.refused else solved.transport_cache or "off"
    report["cast_cache"] = NOT_KEPT if "cast geometry" in behind.refused else cast.get("how", "off")
    report["outside"] = outside
    report["smoothness"] = smoothness
    if solver == "eo":
        report["chains"] = chains
    if solver_options:
        report["solver_options"] = dict(solver_options)
    if scene.show is not None:
        report["show"] = scene.show.as_dict()
    if refined is not None:
        report["refine"] = {**refined.as_dict(), "captures_per_state": measure.captures, "frames": refine_frames,
                            "relax": refine_relax, "registration": [] if remodel is None else remodel.fits,
                            "start": [{"name": sc.name, "psnr_db": sc.psnr_db, "ssim": sc.ssim} for sc in start_scores]}
    if fits is not None:
        report["homographies"] = fits
    solution = solved.result if refined is None else dataclasses.replace(solved.result, patterns=refined.patterns)
    return RunResult(report=report, patterns=solved.patterns, captures=evaluation.captures, targets=scores,
                     solution=solution, scene=scene, calibration=cal)


def _cast_all(rig) -> bool:
    """Whether ``rig`` has cast every state of its scene (so that nothing later casts more)."""
    return set(rig.cast_geometry()) == {st.name for st in rig.scene.states}


def _check_smoothness(solver, smoothness, oracle, gain_offset) -> float:
    """The model solve's smoothness weight (:func:`~torchproj.solve.compensate.resolve_smoothness`): 0 where
    the exact light or a gain and offset are solved, which take none."""
    if oracle == "transport" or gain_offset is not None:
        check(not smoothness, "the exact light and --gain/--offset are solved without a smoothness penalty: "
                              "leave --smoothness out")
        return 0.0
    return resolve_smoothness(solver, smoothness)


def _check_run(scene, solver, oracle, gain_offset, objective, bounds_8bit, maps, ceiling, outside, chains,
               loop=(0, 1, 1.0)):
    """:func:`run_virtual`'s options checked together, before any work; returns the oracle's name (or
    None), the bounds in linear light and the image objective (None for least squares). ``loop``:
    ``(refine, refine_frames, refine_relax)``."""
    refine, frames, relax = loop
    check(is_whole(refine) and 0 <= refine <= MAX_REFINE,
          f"refine must be a whole number of updates in 0..{MAX_REFINE}, got {refine!r}")
    check(not refine or gain_offset is None, "the loop refines the images as they are: drop --gain/--offset or --refine")
    check(is_whole(frames) and 1 <= frames <= MAX_REFINE,
          f"refine_frames must be a whole number of captures in 1..{MAX_REFINE}, got {frames!r}")
    check_relax(relax, "refine_relax")
    bounds = check_solve_options(solver, bounds_8bit, len(scene.projectors), outside, chains)
    oracle = {True: "geometry", False: None}.get(oracle, oracle) if isinstance(oracle, (bool, str)) else oracle
    check(oracle in (None, *ORACLES), f"oracle must be one of {list(ORACLES)}, got {oracle!r}")
    exact = oracle == "transport"
    check(not exact or gain_offset is None, "the transport oracle solves the targets as they are: drop --gain/--offset")
    check(not exact or solver != "eo", "the exact light transport has no epipolar chains for eo to walk: use a "
                                       "solver other than eo with --oracle transport")
    if exact or ceiling:  # before calibrating, not after
        check_linear_camera(scene)
    image = image_objective(objective)
    check(gain_offset is None or (solver == "fista" and image is None),
          "gain_offset works with the fista solver and the l2 objective; drop --solver, --objective or the "
          "gain/offset option")
    if gain_offset is not None:
        try:
            gain, offset = gain_offset
        except (TypeError, ValueError):
            raise InputError(f"gain_offset must be ((gain_lo, gain_hi), (offset_lo, offset_hi)), got {gain_offset!r}") \
                from None
        check_gain_offset(gain, offset)
    check(maps in MAPS, f"maps must be one of {list(MAPS)}, got {maps!r}")
    return oracle, bounds, image


@dataclass
class _Solved:
    """What :func:`_build_and_solve` gives the rest of a run."""

    result: SolveResult
    ops: list  # the operator(s) the patterns were solved on: one, or one per colour channel
    patterns: list[torch.Tensor]  # per projector, 8-bit
    model: dict  # the size report of the operator solved (before gain/offset's extra variables)
    transport_cache: str | None = None  # how the cache served the transport (None: not asked)
    scale: float = field(init=False)  # the operators' target scale
    channels: int = field(init=False)  # how many operators: one per colour channel, or one
    unexplained_fraction: float | None = field(default=None, init=False)  # set as the operators go

    def __post_init__(self):
        self.scale, self.channels = self.ops[0].scale, len(self.ops)

    def release_operators(self) -> None:
        """Drop the operators, keeping what the report reads from them. Scoring simulates the world, not
        the model: without them (A, its transpose, Q and the smoothed stack; 0.5-1 GB on the default
        scene) the captures' simulation starts from a smaller heap, and the run's peak is the larger of
        the two stages, not their sum."""
        self.unexplained_fraction = round(unexplained(self.ops, self.result.patterns), 5)
        self.ops = []


def _build_and_solve(cal, states, targets, bounds, *, solver, image, exact, gain_offset, footprint, max_iter,
                     progress, device, timings, outside, chains, solver_options=None,
                     colour_weights: str = "grey", start=None, rows_on_camera: bool = False,
                     cache_key: str | None = None, smoothness: float = 0.0) -> _Solved:
    """Build the transport from the calibrated states and solve it; ``timings`` gets transport and solve.
    ``start``: a :class:`~torchproj.pipeline.FootprintChoice` whose patterns start a FISTA solve on one
    operator (``footprint="auto"``). ``rows_on_camera``: keep rows camera pixels (a camera loop compares them).
    ``cache_key``: the calibration's cache key, to read or keep the transport in the cache (None: build it)."""
    t0 = time.perf_counter()
    # Rows stay camera pixels where the objective is an image (and for gain/offset, so that any
    # per-target g t + o is an exact right-hand side of the same A), and with the bilinear or area footprint,
    # whose rows almost never repeat (default scene: 2,067,273 -> 2,066,931 rows, for 17 s of merging);
    # merged otherwise (exact, smaller).
    # As the build uses them, so that "channel" and "grey" ask the cache for the same operator where they build it.
    colour_weights = used_colour_weights(states, targets, colour_weights)
    options = dict(merge=gain_offset is None and image is None and not exact and footprint == "nearest"
                   and not rows_on_camera, footprint=footprint, colour_weights=colour_weights, device=device)
    normal_read = None  # per operator the coarse levels read with its Q, where a Q was read
    if cache_key is None:
        ops, how = build_operators(states, targets, **options), None
    else:
        cache_key = transport_key(cache_key, targets, **options)
        ops, how = cached_transport(cache_key, lambda: build_operators(states, targets, **options), device)
    # The operators the solve runs on, whose Q = A^T A (built from the matrix), coarse levels and solver
    # setup the first solve keeps beside the transport: with the smoothness penalty, its stacked operator
    # (make_patterns takes the same one from with_smoothness); a colour run keeps none (make_patterns
    # forgets each channel's); a solve on the exact light uses another matrix.
    solving, normal_key = list(ops), cache_key
    if smoothness and len(ops) == 1 and cache_key is not None:
        solving, normal_key = [ops[0].with_smoothness(smoothness)], smoothed_key(cache_key, smoothness)
    if cache_key is not None and how == "read" and not exact:
        normal_read = read_normal_matrices(normal_key, solving)
    op = ops[0]
    if exact:
        ops = light_transport(cal.rig, targets, op)
    model = ops[0].size_report()
    timings["transport"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    if exact:
        result, _, patterns = solve_on_light_transport(ops, bounds, true_responses(cal.rig.scene), solver=solver,
                                                       max_iter=max_iter, progress=progress, objective=image,
                                                       outside=outside, world=cal, targets=targets)
    elif gain_offset is not None:
        result, op, patterns = _solve_gain_offset(op, states, targets, bounds, gain_offset, cal.responses,
                                                  max_iter, progress, device, footprint, outside)
        ops = [op]
    else:
        options = solver_options if start is None else start.solver_options(ops, solver, solver_options)
        result, _, patterns = make_patterns(ops, solver, bounds, cal.responses, calibrations=states,
                                            max_iter=max_iter, progress=progress, objective=image, outside=outside,
                                            chains=chains, solver_options=options, smoothness=smoothness)
    timings["solve"] = time.perf_counter() - t0
    if cache_key is not None and how != NOT_KEPT and (normal_read is None or any(
            len(o.coarse_matrices()) > n for o, n in zip(solving, normal_read))):
        t0 = time.perf_counter()
        if keep_normal_matrices(normal_key, solving):  # nothing to keep where the solve iterated on products
            timings["keep"] = timings.get("keep", 0.0) + time.perf_counter() - t0
    return _Solved(result, ops, patterns, model, how)


def _target_rows(scene, scores: list[TargetScore], gain_offset: dict | None):
    """Per target, its report row; with a gain and offset (``SolveResult.info``) its scores are against
    the adjusted image ``g t + o``, and against ``t`` as ``psnr_db_original`` / ``ssim_original``."""
    scores, rows = list(scores), []
    for k, (spec, score) in enumerate(zip(scene.target_specs(), scores)):
        row = {**score.as_dict(), "surfaces": spec.surfaces}
        if gain_offset is not None:
            g, o = gain_offset["gain"][k], gain_offset["offset"][k]
            adjusted = (g * score.values + o).clamp(0, 1)
            row.update(gain=round(g, 4), offset=round(o, 4), psnr_db_original=score.psnr_db,
                       ssim_original=score.ssim, **score_image(score.estimate, adjusted, score.covered))
            scores[k] = dataclasses.replace(score, values=adjusted, psnr_db=row["psnr_db"], ssim=row["ssim"])
        rows.append(row)
    return scores, rows


def _fitted_targets(targets: list[Target], info: dict) -> list[Target]:
    """Each target as its fitted gain and offset ask for it: ``g t + o`` in [0, 1]."""
    return [dataclasses.replace(t, image=(g * t.image + o).clamp(0, 1))
            for t, g, o in zip(targets, info["gain"], info["offset"])]


def _solve_gain_offset(op, states, targets, bounds, gain_offset, responses, max_iter, progress, device, footprint,
                       outside):
    """FISTA with one gain and offset per target: the result, the operator it solved, the 8-bit patterns."""
    flat = build_transport(states, [dataclasses.replace(t, image=torch.ones_like(t.image)) for t in targets],
                           merge=False, scale=op.scale, footprint=footprint, device=device)
    result = solve_gain_offset(op, flat.rhs, bounds, gain=gain_offset[0], offset=gain_offset[1],
                               progress=progress, **iteration_limit(max_iter))
    op = result.info.pop("operator")
    return result, op, projectable_patterns(op, result.patterns, bounds, responses, outside)[1]


def _ceiling(cal, states, targets, bounds, footprint, progress, device, outside, image) -> list[TargetScore]:
    """The targets' scores when solved on the simulator's own light transport, on the same rows, with the
    run's ``image`` objective (None: least squares). A run that maximises SSIM is measured against what
    maximising SSIM on the exact light gives: against the least-squares optimum, its SSIM stood above
    the ceiling (the default scene's 0.764 against 0.661, with ``--ssim-iter 200 --psnr-drop -1``)."""
    rows = build_transport(states, targets, merge=False, footprint=footprint, device=device)
    # The exact light, shown through the projectors' exact responses: a response fit the world biases
    # (light bouncing between surfaces lifts the ramp's captures) is calibration's error, not the ceiling's.
    # Whether the targets can be shown apart, the run's own solve has said: the ceiling's would say it
    # again in the same words (an ill-posed scene is ill-posed on the exact light too).
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=ILL_POSED_MESSAGE)
        _, _, patterns = solve_on_light_transport(light_transport(cal.rig, targets, rows), bounds,
                                                  true_responses(cal.rig.scene), max_iter=CEILING_ITERATIONS,
                                                  progress=progress, outside=outside, world=cal, targets=targets,
                                                  objective=image)
    return evaluate_patterns(cal, patterns, targets, scale=rows.scale, states=states, paper=False).targets


_CALIBRATION = {None: "Gray code on the virtual rig", "geometry": "oracle (the simulator's exact geometry)",
                "transport": "oracle (the simulator's own light transport)"}


def _report(scene, cal, solver, image, bounds_8bit, device, maps, solved: _Solved, timings, rows,
            gain_offset, oracle) -> dict:
    """What ``report.json`` holds (``objective`` is always the least-squares value of the patterns)."""
    result, model = solved.result, solved.model
    least_squares = result.info["l2_objective"] if image is not None else result.objective
    report = {
        "scene": scene.name, "solver": solver if gain_offset is None else "fista+gain/offset",
        "bounds_8bit": list(bounds_8bit), "device": str(device),
        "calibration": _CALIBRATION["geometry" if oracle is None and cal.oracle else oracle],
        "maps": maps, "graycode": _graycode_report(scene, cal), "decoded_fraction": cal.decoded,
        "decode": cal.decode, "capture_noise": cal.capture_noise, "white_clipped": cal.white_clipped,
        "model": model, "objective": least_squares,
        "unexplained_fraction": solved.unexplained_fraction,
        "iterations": result.iterations, "scale": solved.scale,
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "evaluation": EVALUATION + ("; with gain/offset, psnr_db and ssim compare with the adjusted image g t + o, "
                                    "psnr_db_original and ssim_original with t" if gain_offset is not None else ""),
        "targets": rows,
    }
    if image is not None:
        report["image_objective"] = image_objective_report(result)
        report["iterations"] = result.info["start"].iterations
    if gain_offset is not None:
        report["gain_offset_limits"] = {"gain": list(gain_offset[0]), "offset": list(gain_offset[1])}
    return report


def _graycode_report(scene: Scene, cal: VirtualCalibration) -> dict | None:
    """Per projector, the Gray-code bits shown and the captures that took per state (None for the oracle)."""
    if cal.oracle:
        return None
    sizes = [(p.width, p.height) for p in scene.projectors]
    shown = cal.bits or [sequence_bits(*size) for size in sizes]
    # Pattern/inverse pairs, white and black, and the two ramps.
    return {p.name: {"bits": list(b), "captures_per_state": 2 * sum(b) + 4} for p, b in zip(scene.projectors, shown)}


def image_objective_report(result: SolveResult) -> dict:
    """The ``image_objective`` entry of a report, from :func:`~torchproj.solve.make_patterns`' result."""
    image, start = result.info["objective"], result.info["start"]
    return {"name": image.name, "l2_weight": image.l2_weight, "psnr_drop_db": image.psnr_drop,
            "value": result.objective, "iterations": result.iterations, "model_ssim": result.info["model_ssim"],
            "model_psnr_change_db": result.info["model_psnr_change_db"],
            "start": {"solver": start.method, "iterations": start.iterations, "objective": start.objective}}


def _decoded_lines(decoded: dict | None, decode: dict | None = None) -> list[str]:
    from ..calib import FEW_DECODED

    if not decoded:
        return []
    if decode:  # fully, partly (placed from their neighbours) and not at all
        low = any(1 - v["none"] < FEW_DECODED for per in decode.values() for v in per.values())
        text = "; ".join(f"{state} " + ", ".join(f"{name} {v['full']:.1%} fully, {v['partial']:.1%} partly, "
                                                  f"{v['none']:.1%} not" for name, v in per.items())
                         for state, per in decode.items())
        return [f"Decoded (shares of each projector's lit pixels; a partly decoded pixel is placed from its neighbours): "
                f"{text}" + (f". Under {FEW_DECODED:.0%} decoded somewhere: the others take no part in the solve (see "
                             "the warning)." if low else "."), ""]
    low = any(v < FEW_DECODED for per in decoded.values() for v in per.values())
    return ["Decoded (share of each projector's lit pixels): " + "; ".join(
        f"{state} " + ", ".join(f"{name} {v:.1%}" for name, v in per.items()) for state, per in decoded.items())
        + (f". Under {FEW_DECODED:.0%} somewhere: those pixels take no part in the solve (see the warning)."
           if low else "."), ""]


def _noise_lines(noise: dict | None) -> list[str]:
    said = [f"{state} " + ", ".join(f"{name} {v:.2%}" for name, v in per.items() if v is not None)
            for state, per in (noise or {}).items() if any(v is not None for v in per.values())]
    if not said:
        return []
    return ["Camera noise of a lit pixel's white - black in the calibration captures (median share of it; "
            "every row's weight, map and shares carry it, and averaging N frames a capture, `camera.frames`, "
            "divides it by the square root of N): " + "; ".join(said) + ".", ""]


def _clipped_lines(clipped: dict | None) -> list[str]:
    """Said where the camera clipped any lit pixel's white: a bright enough camera to be worth a look."""
    said = [f"{state} " + ", ".join(f"{name} {v:.1%}" for name, v in per.items())
            for state, per in (clipped or {}).items() if any(v > 0 for v in per.values())]
    if not said:
        return []
    return [f"White capture clipped by the camera (share of each projector's lit pixels; past {SATURATED_SHARE:.0%} "
            "every row's weight and the ramp read low there, and calibration warned): " + "; ".join(said) + ".", ""]


def _image_objective_lines(image: dict | None) -> list[str]:
    if image is None:
        return []
    budget = "" if image["psnr_drop_db"] is None else f", each target within {image['psnr_drop_db']:g} dB of it"
    return [f"Image objective: {image['name']}, 1 - SSIM plus {image['l2_weight']:g} x the relative squared error"
            f"{budget}; {image['iterations']} iterations from {image['start']['solver']}'s least-squares patterns. "
            "The model predicts SSIM " + " / ".join(f"{v:.3f}" for v in image["model_ssim"]) + " and PSNR changes of "
            + " / ".join(f"{v:+.2f}" for v in image["model_psnr_change_db"]) + " dB (the captures below are what "
            "counts).", ""]


def _show_lines(report: dict) -> list[str]:
    lines = []
    if "show" in report:
        lines += [f"Shown in a world changed after calibration: {describe_show(report['show'])}. Captures, black frames, scores and "
                  "any ceiling are that world's; the solver knows only the calibration.", ""]
    refine = report.get("refine")
    if refine:
        start = " / ".join(f"{s['psnr_db']:.2f}" for s in refine["start"])
        trail = "; ".join(f"{h['capture']}: " + " / ".join(f"{v:.2f}" for v in h["psnr_db"]) for h in refine["history"])
        lines += [f"Camera in the loop: {refine['captures_per_state']} captures per state ({refine['frames']} per step), "
                  f"best at capture {refine['best_capture']}. PSNR (dB) of the solver's patterns as captured: {start}; "
                  f"per capture, on the model's rows: {trail}. The table scores the kept patterns.", ""]
        lines += _promise_lines(refine["history"])
        lines += _registration_lines(refine["registration"])
    return lines


def _registration_lines(fits: list[dict]) -> list[str]:
    """Where the loop found the light moved, and the model it took for it (:class:`~torchproj.pipeline.register.Reregister`)."""
    if not fits:
        return []
    parts = []
    for k, fit in enumerate(fits, start=1):
        shifts = ", ".join(f"({dx:.2f}, {dy:.2f})" for dx, dy in fit["camera_shift_px"])
        parts.append(f"{k}: {fit['model']} (the projectors' fit moves the light {fit['median_move_cells']:.2f} cells, "
                     f"the camera's {fit['camera_move_cells']:.2f}, shifting each target's image by {shifts} px)")
    return ["Where the light moved, fitted after each capture, and the model the loop took (the one that "
            f"predicted that capture best): {'; '.join(parts)}.", ""]


def _promise_lines(history: list[dict]) -> list[str]:
    """What the model promised each capture's patterns against what the camera gave, and where the
    loop shortened its step: where the two part, the world answers otherwise than the model."""
    promised = [h for h in history if "predicted" in h]
    if not promised:
        return []
    pairs = "; ".join(f"{h['capture']}: {h['loss']:.4g} ({h['predicted']:.4g})" for h in promised)
    halved = [a["capture"] for a, b in zip(history, history[1:]) if b["step"] < a["step"]]
    why = (f" The step was halved after capture {', '.join(map(str, halved))}: a capture worse than the best, or "
           "better by less than a quarter of what the model promised." if halved else "")
    return [f"The loop's loss as captured (and as the model promised it) per capture: {pairs}.{why}", ""]


# The paper's prototype (EO_0^255 on two planes, its table of PSNR and SSIM per plane, scored against
# its own baseline): what a reader can hold a run's scores against.
PAPER_PROTOTYPE = {"psnr_db": (18.3, 20.9), "ssim": (0.58, 0.77)}


def _verdict_lines(targets: list[dict], ceiling: bool, lifted: float = 0.0) -> list[str]:
    """report.md's opening: one line that says how the run came out, and a legend of the scores.

    ``lifted``: the share of white that ``--outside map`` shows for a solved zero (0: none). The
    verdict then says so: every cell's light is lifted by it, which the PSNR against the target
    counts as error (4.7 dB on the default scene's near target), while the affine PSNR, which takes
    each target's brightness out, keeps the structure.
    """
    if not targets:
        return []
    scored = [t for t in targets if t.get("psnr_db") is not None]
    if not scored:
        return ["**Verdict:** no target could be scored (see each row's notes).", ""]
    worst = min(scored, key=lambda t: t["psnr_db"])
    lo, hi = PAPER_PROTOTYPE["psnr_db"]
    place = "above" if worst["psnr_db"] > hi else "within" if worst["psnr_db"] >= lo else "below"
    verdict = (f"**Verdict:** the weakest target, {worst['name']}, captures at {worst['psnr_db']:.1f} dB PSNR and SSIM "
               f"{worst['ssim']:.2f}: {place} the paper's prototype range ({lo}-{hi} dB, SSIM "
               f"{PAPER_PROTOTYPE['ssim'][0]}-{PAPER_PROTOTYPE['ssim'][1]} per plane)")
    if ceiling:
        gap = max(t["ceiling"]["psnr_db"] - t["psnr_db"] for t in scored if t["ceiling"]["psnr_db"] is not None)
        verdict += f", and at most {gap:.2f} dB below what the exact light allows (the ceiling)"
    verdict += "."
    if lifted > 0:
        affine = worst.get("affine_psnr_db")
        verdict += (f" Values below black were shown by map (--outside map), which lifts a solved zero to "
                    f"{100 * lifted:.0f}% of white on every cell: PSNR counts that light as error"
                    + (f" (its affine PSNR, brightness taken out, is {affine:.1f} dB)" if affine is not None else "")
                    + "; --outside clip shows them black.")
    return [verdict, "",
            "Legend: PSNR in dB, higher is better (each 6 dB halves the RMS error; past about 30 dB a difference is "
            "hard to see); SSIM 1 is the target's structure exactly, 0 none of it; crosstalk 0 means no trace of "
            "another target's image, 1 its full image; ghost is the share of the error the other states' images "
            "explain. Depth-dependent projection shares every projector between all targets, so two full "
            "images rarely both reach 30 dB.", ""]


def _markdown_table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header), *("| " + " | ".join(r) + " |" for r in rows)]


def _score_tables(targets: list[dict], paper: bool, adjusted: bool, ceiling: bool) -> list[str]:
    """report.md's scores: the primary ones (and the ceiling's beside them) in a table a reader takes
    in at a glance, the others in a second one; the brightness fit's, where it ran, in a third (one
    table had been ten to sixteen columns wide)."""
    main = _markdown_table(["target", "state", "PSNR (dB)", "SSIM"] + (["ceiling PSNR (dB)", "ceiling SSIM"] if ceiling else []),
                           [[r["name"], r["state"], f"{r['psnr_db']:.2f}", f"{r['ssim']:.3f}"]
                            + ([f"{r['ceiling']['psnr_db']:.2f}", f"{r['ceiling']['ssim']:.3f}"] if ceiling else [])
                            for r in targets])
    more = _markdown_table(["target", "crosstalk", "ghost", "pixels", "affine PSNR (dB)"]
                           + (["paper PSNR (dB)", "paper SSIM"] if paper else []),
                           [[r["name"], f"{r['crosstalk']:.3f}", f"{r.get('ghost', float('nan')):.3f}", str(r["pixels"]),
                             f"{r.get('affine_psnr_db', float('nan')):.2f}"]
                            + ([f"{r['paper']['psnr_db']:.2f}", f"{r['paper']['ssim']:.3f}"] if paper else [])
                            for r in targets])
    lines = [*main, "", "More scores per target:", "", *more]
    if adjusted:
        lines += ["", "Brightness fitted to what the projectors can give (gain and offset of each target; the scores "
                      "above are against the fitted target, these against the target as given):", "",
                  *_markdown_table(["target", "gain", "offset", "PSNR vs target (dB)", "SSIM vs target"],
                                   [[r["name"], f"{r['gain']:.3f}", f"{r['offset']:.3f}", f"{r['psnr_db_original']:.2f}",
                                     f"{r['ssim_original']:.3f}"] for r in targets])]
    return lines


_CACHED = {"read": "read from the cache", "stored": "kept in the cache",
           "recomputed": "computed again: its cache entry was unreadable",
           NOT_KEPT: "computed: the cache folder refused to keep it"}


def _cached(report: dict, what: str) -> str:
    """`` (read from the cache)`` and the like after the calibration or the model, where the cache served it."""
    how = report.get(f"{what}_cache", "off")
    return f" ({_CACHED[how]})" if how in _CACHED else ""


def _lifted(report: dict) -> float:
    """The share of white a solved zero is shown at: ``-lo / (hi - lo)`` under ``--outside map``
    (:func:`~torchproj.solve.to_projectable`), 0 where values below black are clipped."""
    lo, hi = report["bounds_8bit"]
    return -lo / (hi - lo) if report.get("outside", "clip") == "map" and lo < 0 else 0.0


def run_markdown(report: dict) -> str:
    """``report.md`` of a run: what ``report.json`` holds, as tables."""
    m, t = report["model"], report["timings_s"]
    adjusted = "gain_offset_limits" in report
    footprint = report.get("footprint", "nearest")
    if "footprint_choice" in report:
        footprint = f"{footprint}, chosen by auto ({report['footprint_choice']['reason']})"
    ceiling = all("ceiling" in r for r in report["targets"]) and bool(report["targets"])
    paper = all("paper" in r for r in report["targets"]) and bool(report["targets"])
    below = report["bounds_8bit"][0] < 0  # only then is there anything to clip or map
    lines = [f"# torchproj run: {report['scene']}, solver {report['solver']}, bounds "
             f"{report['bounds_8bit'][0]:g}..{report['bounds_8bit'][1]:g}"
             + (f" (values below 0 shown by {report.get('outside', 'clip')})" if below else ""), "",
             *_verdict_lines(report["targets"], ceiling, _lifted(report)),
             "Fig. 1 (`overview.png`): each projector's pattern, and per target the image asked for, the "
             "capture and the error between them, on one scale.", "",
             f"Calibration: {report['calibration']}{_cached(report, 'calibration')}; maps: {report['maps']}; "
             f"footprint: {footprint}"
             + ("" if report.get("graycode") is None else "; Gray code per projector: " + ", ".join(
                 f"{name} {g['bits'][0]}x{g['bits'][1]} bits ({g['captures_per_state']} captures per state)"
                 for name, g in report["graycode"].items())) + ".", "",
             f"Model: {m['variables']} variables, {m['rows']} rows, {m['nnz']} nonzeros"
             + (" per colour channel, each channel with its own weights and solved apart"
                if report.get("colour_weights") == "channel" else "") + _cached(report, "transport") + "; objective "
             f"{report['objective']:.4g} after {report['iterations']} iterations.", "",
             *_decoded_lines(report.get("decoded_fraction"), report.get("decode")),
             *_noise_lines(report.get("capture_noise")),
             *_clipped_lines(report.get("white_clipped")),
             *_image_objective_lines(report.get("image_objective")),
             *_show_lines(report),
             *_score_tables(report["targets"], paper, adjusted, ceiling)]
    lines += ["", "Scores: PSNR and SSIM against the target image are ours and the primary ones; affine PSNR takes "
                  "each capture's best gain and offset first (structure without brightness)"
              + ("; the paper's PSNR and SSIM compare the capture with a capture of the target image projected alone "
                 "by one projector, the paper's baseline" if paper else "") + "."]
    if ceiling:
        image = report.get("image_objective")
        lines += ["", "Ceiling: the same targets, rows and bounds solved on the simulator's own light transport "
                      "(FISTA, least squares" + (f", then the {image['name']} objective as this run" if image else "")
                  + ") and scored the same way: the best any calibration could give"
                  + (" (with a gain and offset, for the images this run fitted, g t + o)" if adjusted else "") + "."]
    lines += ["", f"How each score is computed: {report['evaluation']}."]
    if report.get("cast_cache", "off") != "off":
        lines += ["", "The captures were rendered from the rays the simulator cast through the scene"
                      + _cached(report, "cast") + "."]
    if "homographies" in report:
        lines += ["", "Homographies (residual from decoded to fitted coordinates, projector pixels; for Gray-code "
                      "blocks, the distance outside the block over the pixels at block edges):", "",
                  "| state | projector | block (cells) | median | 95th percentile | pixels |", "|---|---|---|---|---|---|"]
        for state, fits in report["homographies"].items():
            lines += [f"| {state} | {j} | {'x'.join(map(str, f['block_cells']))} | {f['median_px']:.3f} | "
                      f"{f['p95_px']:.3f} | {f['points']} |" for j, f in enumerate(fits)]
    lines += ["", "Timings (s): " + ", ".join(f"{k} {v:.2f}" for k, v in t.items()), ""]
    return "\n".join(lines)
