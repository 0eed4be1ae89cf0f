"""Compensation: solved linear light -> 8-bit pattern images through each projector's inverse response."""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Mapping

import torch

from ..calib.response import ResponseCurve
from ..core.checks import check, check_count, check_shape
from ..core.choices import DEFAULT_SMOOTHNESS
from ..core.errors import InputError
from ..transport.operator import check_operators, check_smoothness

__all__ = ["check_solve_options", "compensate", "make_patterns", "projectable_patterns"]


def check_responses(responses, projectors: int) -> None:
    """One :class:`~torchproj.calib.ResponseCurve` per projector, in a list."""
    check(isinstance(responses, (list, tuple)) and all(isinstance(r, ResponseCurve) for r in responses),
          f"responses must be a list of one ResponseCurve per projector, got {type(responses).__name__}"
          + (f" of {sorted({type(r).__name__ for r in responses})}" if isinstance(responses, (list, tuple)) else ""))
    check(len(responses) == projectors, f"got {projectors} projectors' images but {len(responses)} response curves")


def compensate(images: list[torch.Tensor], responses: list[ResponseCurve]) -> list[torch.Tensor]:
    """Turn linear relative light per projector into the 8-bit values to send to it.

    Args:
        images: per projector, :math:`(C, H_j, W_j)` linear relative light in [0, 1] (0 = the
            projector's black, 1 = its white), e.g. from :meth:`TransportOperator.to_images`.
        responses: per projector, its fitted :class:`~torchproj.calib.ResponseCurve`.

    Returns:
        per projector, :math:`(C, H_j, W_j)` uint8 pattern images.
    """
    check(isinstance(images, (list, tuple)), f"images must be a list of (C, H, W) light per projector, got "
                                             f"{type(images).__name__}")
    check_responses(responses, len(images))
    out = []
    for j, (img, resp) in enumerate(zip(images, responses)):
        check_shape(img, f"images[{j}]", ["C", "H", "W"])
        lo, hi = float(img.min()), float(img.max())
        check(lo >= -1e-6 and hi <= 1 + 1e-6, f"images[{j}] must lie in [0, 1] (bring wider bounds into range "
                                              f"with to_projectable first), got [{lo:.3g}, {hi:.3g}]")
        x = resp.to_pattern(img.clamp(0, 1))
        out.append(torch.round(x * 255).to(torch.uint8))
    return out


UNEXPLAINED_WARNING = 0.1


def unexplained(ops, p: torch.Tensor) -> float:
    """:meth:`~torchproj.transport.TransportOperator.unexplained` over one operator, or over one per
    colour channel (``p``'s column ``c`` on operator ``c``) as one problem."""
    if not isinstance(ops, (list, tuple)):
        return ops.unexplained(p)
    if len(ops) == 1:
        return ops[0].unexplained(p)
    energy = sum(float(op.rhs.pow(2).sum() + op.constant.sum()) for op in ops)
    return sum(float(op.objective(p[:, c:c + 1])) for c, op in enumerate(ops)) / energy if energy > 0 else 0.0


ILL_POSED_MESSAGE = "the patterns leave"  # how warn_if_ill_posed's warning starts (a filter matches it)


def warn_if_ill_posed(op, patterns: torch.Tensor, limit: float = UNEXPLAINED_WARNING, limits: list[str] = ()) -> float:
    """Warn when the patterns leave more than ``limit`` of the targets' energy unexplained.

    Shipped scenes stay under 0.07 (``benchmarks/stability.py``); past 0.1 the targets cannot be shown
    apart: no projector baseline, targets asking opposite light along the same rays, more targets
    than the projectors can carry, or a calibration drowned in noise. That reading holds for the
    bounded least-squares optimum the threshold was set on: where the solve's own options kept it
    from that optimum (``limits``, :func:`solve_limits`), the warning names them first. Returns the
    share. ``op`` may be one operator per colour channel (:func:`unexplained`).
    """
    share = unexplained(op, patterns)
    if share > limit:
        scene = ("projectors too close together, targets too close in depth or asking opposite light along the same "
                 "rays, more targets than the projectors can carry, or a noisy calibration")
        why = (f"This solve's own options keep it from the optimum: {'; '.join(limits)}. With them at their defaults, "
               f"a share this high would say the scene is ill-posed ({scene})" if limits else
               f"The scene may be ill-posed: {scene}")
        warnings.warn(f"{ILL_POSED_MESSAGE} {share:.0%} of the targets' energy unexplained (over {limit:.0%}): expect "
                      f"faint images and crosstalk. {why}", stacklevel=3)
    return share


def solve_limits(solver: str, bounds: tuple[float, float], result, iterations_given: bool) -> list[str]:
    """What in a solve's own options keeps its patterns from the bounded least-squares optimum, in
    the user's words: the paper's LF baseline, bounds narrower than a projector's black to white,
    an iteration limit the solve stopped at, a smoothness weight far past the default.
    ``torchproj run --solver lf`` on the default scene had been told its scene may be ill-posed."""
    lo, hi = bounds
    limits = []
    if solver == "lf":
        limits.append("lf scales the unbounded least squares into the bounds (the paper's baseline), far from the "
                      "bounded optimum fista finds")
    if hi - lo < 1:
        limits.append(f"the bounds {lo * 255:g}..{hi * 255:g} (8-bit) span {hi - lo:.1%} of each projector's black to "
                      "white")
    # Stopped by the limit while the objective still fell by a percent over the last tenth of its
    # iterations: more would have gone further. (An ill-posed scene's solve that stops at the limit
    # has long levelled off, and its share is the scene's.)
    history = [objective for _, objective in result.history]
    tail = history[min(int(len(history) * 0.9), len(history) - 2)] if len(history) >= 2 else None
    if iterations_given and not result.converged and tail is not None and tail - history[-1] > 0.01 * abs(history[-1]):
        limits.append(f"the solver stopped at its iteration limit ({result.iterations}) while still improving")
    # A penalty that dominates keeps the patterns flat, and then costs little itself: its weight says it.
    weight = result.info.get("smoothness", 0.0)
    if weight > 10 * DEFAULT_SMOOTHNESS:
        limits.append(f"a smoothness weight of {weight:g} ({weight / DEFAULT_SMOOTHNESS:.0f} times the default "
                      f"{DEFAULT_SMOOTHNESS:g}) flattens the patterns")
    return limits


def resolve_smoothness(solver: str, smoothness: float | None) -> float:
    """The smoothness weight a solve with ``solver`` uses, checked before any work: None gives
    :data:`~torchproj.core.choices.DEFAULT_SMOOTHNESS` for the least-squares solvers (fista, pgd,
    adam) and 0 for the paper's ``lf`` and ``eo``, which take none
    (:meth:`~torchproj.transport.TransportOperator.with_smoothness`)."""
    paper = solver in ("lf", "eo")
    if smoothness is None:
        return 0.0 if paper else DEFAULT_SMOOTHNESS
    smoothness = check_smoothness(smoothness, "smoothness")
    check(smoothness == 0 or not paper,
          f"smoothness is for the least-squares solvers (fista, pgd, adam); {solver}, the paper's method, takes none: "
          "leave smoothness out (or 0), or choose fista")
    return smoothness


def check_solve_options(solver: str, bounds_8bit, projectors: int, outside: str = "clip",
                        chains: str = "epipolar") -> tuple[float, float]:
    """What :func:`make_patterns` will be asked, checked before any work: the solver's name, that
    ``eo``'s chains suit the rig (epipolar chains need exactly two projectors), the paper's 8-bit
    bounds and how values outside [0, 255] are shown (:data:`~torchproj.solve.OUTSIDE`); returns
    the bounds in linear light.

    Bounds: HI in (0, 255] (a projector gives no more than its white), LO in [-255, HI) (below 0 as
    the paper's ``EO_-100^255``, whose values are brought into range afterwards).
    """
    from . import check_solver
    from .eo import CHAINS
    from .solvers import check_bounds, check_outside

    check_solver(solver)
    check_outside(outside)
    check(chains in CHAINS, f"chains must be one of {list(CHAINS)}, got {chains!r}")
    check(solver != "eo" or chains != "epipolar" or projectors == 2,
          f"eo walks epipolar chains between exactly two projectors, and this rig has {projectors}: use another "
          "solver (fista, the default, takes any number), or eo's connected components of the transport "
          "(--chains components)")
    try:
        lo, hi = check_bounds(bounds_8bit)  # finite, lo < hi
    except (TypeError, ValueError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"bounds must be two numbers LO,HI in 8-bit units, got {bounds_8bit!r}") from None
    check(0 < hi <= 255, f"bounds: HI {hi:g} must lie in (0, 255] (8-bit units: 255 is the projector's white, "
                         "more light than that it cannot give); use e.g. 0,255")
    check(lo >= -255, f"bounds: LO {lo:g} must be at least -255 (8-bit units; the paper's EO_-100^255 uses -100)")
    if hi <= 1:
        warnings.warn(f"bounds {lo:g},{hi:g} are 8-bit units: HI {hi:g} lets each cell give {hi:g}/255 of its white; "
                      "for the full range use 0,255", stacklevel=3)
    return lo / 255, hi / 255


# The gradient solvers' iteration limit where the pipeline is given none. They rarely converge to their
# tolerance on a scene whose calibration is off (box_cylinders' grazing faces, the dim screen), and
# there the last iterations fit the calibration's errors: box_cylinders' captures measured 26.07 / 28.99
# dB at 300 iterations and 25.16 / 27.15 dB at 500. LF and EO stop on their own convergence rules.
PIPELINE_ITERATIONS = {"fista": 300, "pgd": 300, "adam": 300}


def iteration_limit(max_iter: int | None, solver: str = "fista") -> dict:
    """``max_iter`` as a solver keyword; None gives the pipeline's limit for ``solver``
    (:data:`PIPELINE_ITERATIONS`), or leaves LF and EO their own."""
    if max_iter is None:
        return {"max_iter": PIPELINE_ITERATIONS[solver]} if solver in PIPELINE_ITERATIONS else {}
    return {"max_iter": check_count(max_iter, "max_iter")}


def check_solver_options(solver_options) -> None:
    """Further keywords for the solver: a dict (or None)."""
    check(solver_options is None or isinstance(solver_options, Mapping),
          f"solver_options must be a dict of the solver's keywords, got {type(solver_options).__name__}")


def make_patterns(op, solver: str, bounds: tuple[float, float], responses: list[ResponseCurve], *, calibrations=None,
                  max_iter: int | None = None, progress: bool | None = None, objective="l2", outside: str = "clip",
                  chains: str = "epipolar", solver_options: dict | None = None, smoothness: float | None = None):
    """Solve, bring the solution into what projectors can show, and compensate their responses.

    Args:
        op: the transport operator (rows on camera pixels, ``merge=False``, for an image-space
            objective), or a list of one per colour channel with the same columns
            (:func:`~torchproj.transport.build_channel_transports`): least squares in a box
            separates over channels, so each is solved alone and the solutions joined (an image
            objective then refines them together, each channel predicted with its own weights).
        solver: a name of :data:`~torchproj.solve.SOLVERS`; ``eo`` needs ``calibrations``.
        bounds: the solver's box, linear light (the paper's 8-bit bounds over 255).
        responses: per projector, its response curve.
        objective: ``l2`` (the solver's least squares), or an image-space objective (``ssim``,
            ``mixed`` or an :class:`~torchproj.solve.ImageObjective`) started from the solver's
            patterns (:func:`~torchproj.solve.solve_ssim`).
        max_iter: the solver's iteration limit (None: 300 for fista, pgd and adam, see
            :data:`PIPELINE_ITERATIONS`; LF and EO their own convergence rules).
        outside: how values solved outside [0, 1] are shown (:func:`~torchproj.solve.to_projectable`).
        chains: ``eo``'s independent problems (:func:`~torchproj.solve.solve_eo`): ``epipolar`` (the
            paper's, two projectors) or ``components`` (connected components of the transport).
        solver_options: further keywords for the solver (e.g. ``{"normalise": "clip"}`` for ``lf``).
        smoothness: weight of a penalty on neighbouring cells' differences in the least-squares solve
            (:meth:`~torchproj.transport.TransportOperator.with_smoothness`; 0: none; None: the
            default, :func:`resolve_smoothness`). It steers the least-squares solution, which an image
            objective then starts from; ``lf`` and ``eo``, the paper's methods, take none.

    Where ``responses`` hold a colour camera's mixing of the primaries, an ``l2`` solve with bounds
    within [0, 1] is refined with the channels coupled through it (:mod:`torchproj.solve.mixing`).

    Returns:
        ``(result, light, patterns)``: the :class:`SolveResult` (for an image-space objective, its
        ``info["start"]`` is the solver's own result), per projector the linear light
        :math:`(C, H_j, W_j)` in [0, 1] it should emit, and the uint8 patterns to send it.
    """
    from . import check_solver, solve_patterns
    from .eo import solve_eo
    from .mixing import solve_through_mixing
    from .objectives import image_objective, solve_ssim

    check_solver(solver)
    ops = check_operators(op)
    check_responses(responses, len(ops[0].projector_sizes))  # before the solve, not after it
    image = image_objective(objective)
    check_solver_options(solver_options)
    limit = {**iteration_limit(max_iter, solver), **(solver_options or {})}

    def solve(one):
        if solver == "eo":
            return solve_eo(one, bounds, chains=chains, calibrations=calibrations, progress=progress, **limit)
        return solve_patterns(one, solver, bounds, progress=progress, **limit)

    smoothness = resolve_smoothness(solver, smoothness)
    if len(ops) > 1:
        check(len({o.shape[1] for o in ops}) == 1 and all(o.channels == 1 for o in ops),
              "give one operator, or one single-channel operator per colour channel with the same columns "
              "(build_channel_transports)")
        results, solved = [], []
        for one in ops:
            solved.append(one.with_smoothness(smoothness))
            results.append(solve(solved[-1]))
            for o in (one, solved[-1]):
                o.forget_normal_equations()  # one channel's Q and stacked matrix at a time
        result = _join_channels(results)
    else:
        solved = [ops[0].with_smoothness(smoothness)]
        result = solve(solved[0])
    if smoothness:  # the objective a result reports is the light's error alone, as without the penalty
        with torch.no_grad():
            plain = (float(ops[0].objective(result.patterns)) if len(ops) == 1 else
                     sum(float(o.objective(result.patterns[:, c:c + 1])) for c, o in enumerate(ops)))
        result = dataclasses.replace(result, objective=plain,
                                     info={**result.info, "smoothness": smoothness, "penalised_objective": result.objective})
    # Whether the targets can be shown apart at all is a property of the least-squares optimum (the
    # threshold is calibrated on it); an image objective departs from it on purpose.
    warn_if_ill_posed(ops, result.patterns, limits=solve_limits(solver, bounds, result,
                                                             max_iter is not None or "max_iter" in (solver_options or {})))
    mixings = [r.mixing for r in responses]
    # A mixing that is the identity couples nothing: the channels' answer is already the optimum (a
    # colour camera calibrated on a rig without mixing measures exactly that, and the 200 coupled
    # iterations were half of a small colour scene's solve).
    mixed = any(m is not None and not torch.equal(m, torch.eye(m.shape[0], dtype=m.dtype, device=m.device))
                for m in mixings)
    if image is None and result.patterns.shape[1] == 3 and mixed and 0 <= bounds[0] and bounds[1] <= 1:
        # A colour camera sees the primaries mixed: the channels' answer, brought into what the
        # primaries can give, is refined with the channels coupled (torchproj.solve.mixing).
        result = solve_through_mixing(solved, result, mixings, bounds)
    if image is not None:
        start = result
        result = solve_ssim(ops, bounds, l2_weight=image.l2_weight, psnr_drop=image.psnr_drop, x0=start.patterns,
                            max_iter=image.iterations, progress=progress)
        result.info["start"] = start
        result.info["objective"] = image
        result.time_s += start.time_s
    return (result, *projectable_patterns(ops[0], result.patterns, bounds, responses, outside))


def _join_channels(results):
    """One :class:`SolveResult` from each colour channel's: values side by side, objectives and times
    summed, iterations the most any channel took, converged where every channel did."""
    return dataclasses.replace(
        results[0], patterns=torch.cat([r.patterns for r in results], 1), history=[],
        iterations=max(r.iterations for r in results), objective=sum(r.objective for r in results),
        time_s=sum(r.time_s for r in results), converged=all(r.converged for r in results),
        info={**results[0].info, "channels_solved_apart": len(results)})


def projectable_patterns(op, p: torch.Tensor, bounds: tuple[float, float], responses: list[ResponseCurve],
                         outside: str = "clip"):
    """Solved values -> what each projector should emit, and the 8-bit images that make it emit that.

    Args:
        op: the operator whose columns ``p`` holds, or one per colour channel (they share columns).
        p: :math:`(N_{cols}, C)` values solved within ``bounds``.
        outside: how values outside [0, 1] are shown (:func:`~torchproj.solve.to_projectable`).

    Returns:
        ``(light, patterns)``: per projector :math:`(C, H_j, W_j)` linear light in [0, 1] (on the
        CPU; cells that are not variables stay black), and the uint8 images (:func:`compensate`).
    """
    from .solvers import to_projectable

    # Columns per channel: a colour rig's per-channel operators share the grey one's columns.
    op = check_operators(op)[0]
    check_shape(p, "p", [op.shape[1], "C"])
    light = [img.cpu() for img in op.to_images(to_projectable(p.detach(), bounds, outside).clamp(0, 1))]
    return light, compensate(light, responses)
