"""The virtual rig as a calibrated rig: its calibration captures, decoded, and their check against the truth.

:func:`calibrate_virtual` is what ``torchproj run`` and every benchmark calibrate with: the solver
then knows only what the captures recovered (the virtual rig's physics, docs/scenes.md), or, in oracle
mode, the simulator's exact geometry.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..calib import (DIM_THRESHOLD, SATURATED, SATURATED_SHARE, GraycodeCapture, ResponseCurve, calibrate_projector,
                     checker_patterns, graycode_bits, graycode_patterns, primary_patterns, ramp_pattern, sequence_bits,
                     warn_if_few_decoded, warn_if_noisy, warn_if_saturated)
from ..calib.pipeline import check_calibration_options
from ..calib.response import RAMP_STEPS
from ..core.checks import check, check_number, check_path, check_shape
from ..core.choices import BLACK_THRESHOLD
from ..core.conventions import to_numpy
from ..core.errors import InputError
from ..scene.config import Scene, check_scene
from ..sim.rig import VirtualRig, check_rig
from ..transport import StateCalibration

__all__ = ["DECODE_THRESHOLD", "DecodingAccuracy", "VirtualCalibration", "calibrate_rig", "calibrate_virtual",
           "check_calibration", "check_light", "decoding_accuracy", "describe_light", "simulate_calibration",
           "simulate_markdown", "simulate_scene", "true_responses", "white_levels"]


def simulate_calibration(rig: VirtualRig, state: str, projector: int | str, ramp_steps: int = RAMP_STEPS,
                         noise: bool = True, bits: int | tuple[int, int] | None = None) -> GraycodeCapture:
    """Capture the calibration sequence of one projector in one state on the virtual rig.

    The projector shows its Gray code (the first ``bits`` pairs per axis of it, if given), white,
    black, the ramp and mirrored ramp and, after a full Gray code, the checkerboard pair
    (:func:`~torchproj.calib.checker_patterns`) and, for a colour camera, the three primaries
    (:func:`~torchproj.calib.primary_patterns`): what ``torchproj sequence`` writes. The other
    projectors stay on showing black, as on a real bench.
    """
    check_rig(rig)
    index = rig.scene.projector_index(projector)
    proj = rig.scene.projectors[index]
    extra = [ramp_pattern(proj.width, proj.height, ramp_steps), ramp_pattern(proj.width, proj.height, ramp_steps, mirrored=True)]
    full = sequence_bits(proj.width, proj.height, bits) == graycode_bits(proj.width, proj.height)
    if full:
        extra.append(checker_patterns(proj.width, proj.height))
    gray = graycode_patterns(proj.width, proj.height, bits)
    images = rig.capture(state, {index: torch.cat([gray, *extra])}, noise=noise)
    n = gray.shape[0]
    # A colour camera also sees the three primaries alone (its colour mixing); a 3-channel pattern
    # is a separate capture, so that the grey sequence is not held three times over.
    primaries = rig.capture(state, {index: primary_patterns(proj.width, proj.height)}, noise=noise) \
        if rig.scene.camera.channels == 3 else None
    return GraycodeCapture(patterns=images[:n - 2], white=images[n - 2], black=images[n - 1], ramp=images[n:n + 2],
                           checker=images[n + 2:n + 4] if full else None, primaries=primaries)


@dataclass
class DecodingAccuracy:
    """How decoded coordinates compare with the simulator's truth for one projector and state.

    Fractions are over the camera pixels the projector truly lights (``lit``).
    """

    lit: int  # pixels truly lit
    decoded: float  # fraction of lit pixels decoded
    exact: float  # fraction of decoded pixels whose cell equals the true cell
    within_one: float  # ... within one cell in x and y
    false_valid: float  # fraction of unlit pixels (shadow, background) reported valid
    rms_px: float  # RMS distance to the continuous true coordinate, over decoded lit pixels

    def as_dict(self) -> dict:
        return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


def decoding_accuracy(decoded: torch.Tensor, truth: torch.Tensor) -> DecodingAccuracy:
    """Compare decoded :math:`(H, W, 2)` projector coordinates with the true ones (NaN = unlit)."""
    sizes = check_shape(truth, "truth", ["H", "W", 2])
    check_shape(decoded, "decoded", [sizes["H"], sizes["W"], 2])
    lit = torch.isfinite(truth).all(-1)
    valid = torch.isfinite(decoded).all(-1)
    both = lit & valid
    cell_true = torch.floor(truth[both] + 0.5)
    cell_dec = torch.floor(decoded[both] + 0.5)
    diff = (cell_dec - cell_true).abs().max(-1).values
    n_lit, n_both = int(lit.sum()), int(both.sum())
    err = (decoded[both] - truth[both]).norm(dim=-1)
    return DecodingAccuracy(
        lit=n_lit,
        decoded=n_both / max(n_lit, 1),
        exact=float((diff == 0).float().mean()) if n_both else 0.0,
        within_one=float((diff <= 1).float().mean()) if n_both else 0.0,
        false_valid=float((valid & ~lit).sum()) / max(int((~lit).sum()), 1),
        rms_px=float(err.pow(2).mean().sqrt()) if n_both else float("nan"),
    )


@dataclass
class VirtualCalibration:
    """A scene calibrated on the virtual rig: what the solver may know, plus the rig to evaluate on."""

    rig: VirtualRig
    states: dict[str, StateCalibration]
    black: dict[str, torch.Tensor]  # per state, (C, H, W) capture with every projector showing black
    responses: list  # per projector, its fitted ResponseCurve
    seconds: float
    oracle: bool = False
    bits: list | None = None  # per projector, (kx, ky) of a shortened Gray-code sequence; None: the full one
    homographies: dict | None = None  # per state, per projector, the HomographyFit a shortened sequence gave
    decoded: dict | None = None  # per state, per projector name, the share of its lit pixels decoded fully or partly
    # per state, per projector name, the shares of its lit pixels decoded fully, partly and not at all
    decode: dict | None = None
    # per state, per projector name, the camera noise of a lit pixel's white minus black, as a share of it
    # (torchproj.calib.capture_noise)
    capture_noise: dict | None = None
    # per state, per projector name, the share of its lit pixels whose white capture the camera clipped
    # (ProjectorCalibration.saturated)
    white_clipped: dict | None = None


def check_virtual_calibration(value, name: str = "calibration") -> None:
    """``value`` a :class:`VirtualCalibration`: what the virtual rig's runs, scores and loops read."""
    check(isinstance(value, VirtualCalibration), f"{name} must be a VirtualCalibration (calibrate_virtual's or "
                                                 f"shown_world's), got {type(value).__name__}")


DECODE_THRESHOLD = BLACK_THRESHOLD / 255  # calibrate_projector's shadow mask, in camera values: below it, not decoded
# Camera pixels per axis at which white_levels samples each state: enough to find a surface's brightest part.
LIGHT_CHECK_GRID = 64


def white_levels(scene: Scene, device="cpu") -> dict[tuple[str, str], float]:
    """Each projector's brightest white-minus-black camera value in each state, from the rig's light model.

    White and black captures are simulated without noise at a grid of ``LIGHT_CHECK_GRID`` pixels per
    axis (direct light only: a lower bound where light also bounces); no calibration is needed. A
    value of 0 means the projector does not reach the state's surfaces, or the black capture is
    already saturated where it would (:func:`check_light` tells which).

    Returns:
        ``(state, projector) -> value`` in [0, 1] camera units.
    """
    return _light_levels(scene, device, quiet=False)[0]


def quiet_rig(scene: Scene, device) -> VirtualRig:
    """A second rig of a scene (a check before the work, the world as shown), without the warning
    about the camera's samples that the focal lengths alone decide and the rig doing the work gives:
    a run printed it once per rig made."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"scene .*: camera samples are [\d.]+ projector cells apart")
        return VirtualRig(scene, device=device)


def _light_levels(scene: Scene, device, threshold: float = DECODE_THRESHOLD, states: list[str] | None = None,
                  grid: int | None = LIGHT_CHECK_GRID, whites: bool = True, quiet: bool = True
                  ) -> tuple[dict[tuple[str, str], float], dict[str, float], dict[tuple[str, str], float]]:
    """:func:`white_levels`; per state the median of its black capture over the grid; and per state and
    projector the share of the grid's lit pixels (white minus black past ``threshold``) whose white
    capture is clipped (:data:`~torchproj.calib.SATURATED`). ``states``: those only (default all);
    ``grid`` None: every camera pixel; ``whites`` False: the black captures only (the first and
    third dicts empty); ``quiet``: without the rig's warning about the camera's samples (a check
    before the work, whose own rig gives it), else with it (the levels asked for alone)."""
    check_scene(scene)
    check_number(threshold, "threshold (white minus black, in [0, 1])")
    cam = scene.camera
    rig = quiet_rig(scene, device) if quiet else VirtualRig(scene, device=device)
    pixels = None
    if grid is not None:
        ys = torch.linspace(0, cam.height - 1, min(grid, cam.height), device=device).round().long()
        xs = torch.linspace(0, cam.width - 1, min(grid, cam.width), device=device).round().long()
        pixels = (ys[:, None] * cam.width + xs[None, :]).reshape(-1)
    levels, blacks, clipped = {}, {}, {}
    for state in scene.states if states is None else [scene.state(name) for name in states]:
        surfaces = [scene.surfaces[n] for n in state.surfaces]
        black = rig.capture_surfaces(surfaces, {}, pixels, noise=False, direct_only=True)
        blacks[state.name] = float(black.mean(0).median())
        for j, proj in enumerate(scene.projectors if whites else []):
            white = rig.capture_surfaces(surfaces, {j: torch.ones(1, 1, proj.height, proj.width, device=device)},
                                         pixels, noise=False, direct_only=True)
            levels[state.name, proj.name] = float((white - black).mean(0).max())
            lit = (white - black).mean(0) >= threshold
            clipped[state.name, proj.name] = float((lit & (white.amax(0) >= SATURATED)).sum()) / max(int(lit.sum()), 1)
    return levels, blacks, clipped


def check_light(scene: Scene, device="cpu", threshold: float = DECODE_THRESHOLD, grid: int = LIGHT_CHECK_GRID) -> None:
    """Refuse, before any calibration, a scene where a projector lights a state too dimly to decode.

    Gray-code decoding keeps pixels whose white minus black passes ``threshold`` (the shadow mask of
    :func:`~torchproj.calib.calibrate_projector`, 40/255); a projector whose brightest lit pixel in
    a state stays under it (:func:`white_levels`) decodes nothing there, and calibration fails
    minutes later at the ramp. A projector that reaches a state's surfaces at all must pass the
    threshold somewhere on them, and each projector must light something the camera sees in some
    state; a state whose black capture is saturated by room light shows no
    projector at all, and neither does a state a target asks for whose surfaces no projector's light
    reaches the camera from (out of view, hidden or black). ``grid``: pixels per axis the levels are
    read at (:data:`LIGHT_CHECK_GRID`); a state dark on the grid is read at every pixel before it is
    refused.
    """
    levels, blacks, _ = _light_levels(scene, device, threshold, grid=grid)
    for state, black in blacks.items():
        if black >= 1 - 1 / 255 and not any(levels[state, p.name] >= threshold for p in scene.projectors):
            raise InputError(
                f"state {state!r}: the black capture saturates the camera (room light alone, ambient "
                f"{scene.ambient:g} at exposure {scene.camera.exposure:g}), so no projector's light can be seen: "
                "lower camera.exposure or ambient (checked before calibrating; nothing was simulated)")
    # A state a target asks for that no projector's light reaches at any pixel: nothing there can be
    # decoded or shown. The grid may pass between the pixels of a small object, so every pixel of such
    # a state is asked before it is refused.
    dark = [name for name in dict.fromkeys(spec.state for spec in scene.target_specs())
            if all(levels[name, p.name] == 0 for p in scene.projectors)]
    if dark:
        everywhere = _light_levels(scene, device, threshold, states=dark, grid=None)[0]
        dark = [name for name in dark if all(everywhere[name, p.name] == 0 for p in scene.projectors)]
    if dark:
        others = f" (and state(s) {', '.join(map(repr, dark[1:]))})" if len(dark) > 1 else ""
        # A camera gamma under 1 takes each value to the power 1 / gamma: 0.2 puts a quarter-white at 1/1000,
        # under one 8-bit level, and the state reads dark with every pose right.
        gamma = scene.camera.gamma
        bent = f" and camera.gamma ({gamma:g}: values go as v**{1 / gamma:.3g})" if gamma < 1 else ""
        raise InputError(
            f"state {dark[0]!r}{others}: no projector's light reaches the camera there (white minus black is 0 at every "
            "pixel, for each projector), so nothing can be decoded or shown: its surfaces are out of the camera's "
            "or every projector's view, hidden behind others, black (albedo 0), or lit too faintly for the camera's "
            f"{scene.camera.bit_depth} bits to register; check their poses and albedo, the camera's pose, and the "
            f"projectors' power against camera.exposure{bent} (checked before calibrating; nothing was simulated)")
    # A projector that lights nothing the camera sees, in any state, decodes nothing: its calibration
    # failed after every state was simulated, at a ramp that showed "0 usable levels".
    unlit, faint = [j for j, p in enumerate(scene.projectors) if all(levels[state, p.name] == 0 for state in blacks)], []
    if unlit:
        everywhere = _light_levels(scene, device, threshold, grid=None)[0]
        peaks = {j: max(everywhere[state, scene.projectors[j].name] for state in blacks) for j in unlit}
        # Between the grid's pixels it may light a sliver, too faintly to decode anywhere (a projector
        # behind the screens reaching an object's limb past their edge at 0.3/255): it decodes nothing.
        faint = [(peaks[j], j) for j in unlit if 0 < peaks[j] < threshold]
        unlit = [j for j in unlit if peaks[j] == 0]
    if faint:
        peak, j = min(faint)
        raise InputError(
            f"projectors[{j}]: projector {scene.projectors[j].name!r} lights what the camera sees at most "
            f"{peak * 255:.2g}/255 above black, in any state, and Gray-code decoding needs {threshold * 255:.0f}/255, "
            "so it can be neither calibrated nor used: check its pose (it may light the surfaces from behind, or "
            "be hidden behind them) and the camera's, or leave it out of the scene (checked before calibrating; "
            "nothing was simulated)")
    if unlit:
        j = unlit[0]
        others = f" (and {', '.join(repr(scene.projectors[k].name) for k in unlit[1:])})" if len(unlit) > 1 else ""
        raise InputError(
            f"projectors[{j}]: projector {scene.projectors[j].name!r}{others} lights nothing the camera sees in any "
            "state (white minus black is 0 at every pixel), so it can be neither calibrated nor used: check its pose "
            "(it may face away from the surfaces or be hidden behind them) and the camera's, or leave it out of the "
            "scene (checked before calibrating; nothing was simulated)")
    dim = sorted((peak, state, name) for (state, name), peak in levels.items() if 0 < peak < threshold)
    if dim:
        peak, state, name = dim[0]
        others = f" (and {len(dim) - 1} more state-projector pair(s))" if len(dim) > 1 else ""
        raise InputError(
            f"state {state!r}: projector {name!r} lights it at most {peak * 255:.0f}/255 above black in its white "
            f"capture{others}, and Gray-code decoding needs {threshold * 255:.0f}/255: raise camera.exposure (to about "
            f"{scene.camera.exposure * threshold / peak * 1.1:.3g}) or the projectors' power, or bring the surfaces "
            "closer (checked before calibrating; nothing was simulated)")


def check_shown_light(scene: Scene, device="cpu", grid: int = LIGHT_CHECK_GRID) -> None:
    """Refuse, before any calibration, a ``show`` section whose room light saturates the camera's black
    capture in a state the targets ask for: no pattern could be seen in the world as shown (the
    grid's median, as :func:`check_light` reads a calibrated state's)."""
    from ..scene.show import shown_scene

    if scene.show is None:
        return
    shown = shown_scene(scene)
    asked = list(dict.fromkeys(spec.state for spec in scene.target_specs()))
    _, blacks, _ = _light_levels(shown, device, states=asked, grid=grid, whites=False)
    for state, black in blacks.items():
        if black >= 1 - 1 / 255:
            raise InputError(f"show.ambient: room light of {shown.ambient:g} while showing saturates the camera's black "
                             f"capture in state {state!r} (exposure {shown.camera.exposure:g}), so no pattern could be "
                             "seen there: lower show.ambient (checked before calibrating; nothing was simulated)")


def describe_light(scene: Scene, device="cpu", threshold: float = DECODE_THRESHOLD) -> str:
    """Lines for ``torchproj scene``: each state's brightest white level per projector against the
    decoder's threshold (:func:`white_levels`)."""
    levels, _, clipped = _light_levels(scene, device, threshold, quiet=False)
    lines = [f"white level per state and projector (brightest pixel, white minus black, of 255; decoding needs "
             f"{threshold * 255:.0f}; saturation at 255):"]
    for state in scene.states:
        cells = []
        for proj in scene.projectors:
            peak, share = levels[state.name, proj.name], clipped[state.name, proj.name]
            verdict = "does not reach it" if peak == 0 else "too dim: raise camera.exposure or move closer" \
                if peak < threshold else f"white clipped at {share:.0%} of its lit pixels: lower camera.exposure" \
                if share > SATURATED_SHARE else "ok"
            cells.append(f"{proj.name} {peak * 255:.0f} ({verdict})")
        lines.append(f"  state {state.name}: " + ", ".join(cells))
    return "\n".join(lines)


def calibrate_virtual(scene: Scene, device="cpu", progress=None, oracle: bool = False,
                      bits: int | None = None, plane_tolerance: float = 1.0) -> VirtualCalibration:
    """Simulate and decode every state's calibration captures (Gray code, white, black, ramps and,
    after a full Gray code, the checkerboard pair).

    Args:
        bits: show only the first ``bits`` Gray-code pattern pairs per axis, and read each capture
            through one homography (:func:`~torchproj.calib.calibrate_projector`); for scenes
            where every state is one plane. None: the full sequence.
        plane_tolerance: with ``bits``, the largest 95th-percentile residual (projector pixels)
            that counts as a plane.
        oracle: skip calibration and take the simulator's exact geometry (projector coordinates at
            pixel centres), expected white-minus-black weights (no noise, no quantisation) and true
            responses, on the pixels whose white minus black passes the decoder's shadow threshold
            (40/255, as ``calibrate_projector``). It shows how much quality calibration costs; it is
            not available on a real rig.
    """
    check_scene(scene)
    if oracle:
        check(bits is None, "oracle calibration takes the exact geometry: it shows no Gray code to shorten; drop "
                            "--bits or --oracle")
        return _oracle_calibration(scene, device)
    check_light(scene, device)
    t0 = time.perf_counter()
    rig = VirtualRig(scene, device=device)
    per_state: dict[str, list] = {}
    black = {}
    decoded: dict[str, dict[str, float]] = {}
    decode: dict[str, dict[str, dict]] = {}
    noise: dict[str, dict[str, float | None]] = {}
    clipped: dict[str, dict[str, float]] = {}
    for name, j, capture, calibration in calibrate_rig(rig, bits=bits, plane_tolerance=plane_tolerance,
                                                        progress=progress):
        per_state.setdefault(name, []).append(calibration)
        decoded.setdefault(name, {})[scene.projectors[j].name] = round(calibration.decoding.lit_located_fraction, 4)
        counts = calibration.decoding.counts()
        decode.setdefault(name, {})[scene.projectors[j].name] = {
            k: round(counts[k] / max(counts["lit"], 1), 4) for k in ("full", "partial", "none")}
        noise.setdefault(name, {})[scene.projectors[j].name] = (None if calibration.capture_noise is None
                                                                else round(calibration.capture_noise, 5))
        clipped.setdefault(name, {})[scene.projectors[j].name] = round(calibration.saturated, 4)
        # Every projector shows black: the state's black level and ambient light. A copy, not a view that
        # would keep the whole capture stack (hundreds of MB per projector) alive.
        black[name] = capture.black.to("cpu", copy=True)
        del capture  # see calibrate_rig
    states = {name: StateCalibration.from_calibrations(pcs) for name, pcs in per_state.items()}
    shown = homographies = None
    if bits is not None:
        shown = [sequence_bits(p.width, p.height, bits) for p in scene.projectors]
        homographies = {name: [pc.homography for pc in pcs] for name, pcs in per_state.items()}
    return VirtualCalibration(rig=rig, states=states, black=black, responses=_first_responses(per_state, scene),
                              seconds=time.perf_counter() - t0, bits=shown, homographies=homographies,
                              decoded=decoded, decode=decode, capture_noise=noise, white_clipped=clipped)


def _first_responses(per_state: dict[str, list], scene: Scene) -> list:
    """Each projector's response from the first state whose ramp showed enough of its bars
    (``per_state``: each state's :class:`~torchproj.calib.ProjectorCalibration` per projector); a
    projector none of whose states did is refused, with the first state's reason."""
    responses = []
    for j, proj in enumerate(scene.projectors):
        fitted = [pcs[j].response for pcs in per_state.values() if pcs[j].response is not None]
        if not fitted:
            state, pcs = next(iter(per_state.items()))
            raise InputError(f"projector {proj.name!r}: no state's ramp fits its response; in state {state!r}: "
                             f"{pcs[j].response_note or 'no ramp was captured'}")
        responses.append(fitted[0])
    return responses


def calibrate_rig(rig: VirtualRig, *, bits: int | None = None, plane_tolerance: float = 1.0, noise: bool = True,
                  progress=None, through=None, timings: dict | None = None):
    """Simulate and decode the calibration captures of every state and projector, one at a time.

    The one loop behind :func:`calibrate_virtual` and ``torchproj simulate``.

    Args:
        bits, plane_tolerance: as :func:`calibrate_virtual`.
        noise: camera noise in the captures.
        progress: a progress bar (None: on a terminal, for loops longer than a second).
        through: optional ``(state, projector_index, capture) -> capture``, applied before decoding
            (``torchproj simulate --write-captures`` writes the capture as files and reads it back).
        timings: if given, seconds spent casting rays (``cast``), capturing (``capture``) and
            decoding (``calibrate``) are added to it.

    Yields:
        ``(state, projector_index, capture, calibration)``: the
        :class:`~torchproj.calib.GraycodeCapture` and its
        :class:`~torchproj.calib.ProjectorCalibration`, states in the scene's order, projectors
        within each.
    """
    from ..core.progress import progress_bar

    check_rig(rig)
    scene = rig.scene
    check_calibration_options(dict(plane_tolerance=plane_tolerance))  # read only where bits shorten the sequence
    for j, proj in enumerate(scene.projectors):
        # The ramp gives each bar a cell at least; a narrower projector would fail at its ramp after
        # the whole calibration was simulated.
        check(proj.width >= RAMP_STEPS and proj.height >= 2,
              f"projectors[{j}].resolution: projector {proj.name!r} is {proj.width}x{proj.height} cells, and "
              f"calibration shows it a response ramp of {RAMP_STEPS} bars (a cell each at least) and a Gray code "
              f"down its rows (2 at least): give it at least {RAMP_STEPS}x2 (checked before calibrating; nothing "
              "was simulated)")
    timings = {} if timings is None else timings
    jobs = [(st.name, j) for st in scene.states for j in range(len(scene.projectors))]
    for name, j in progress_bar(jobs, "calibrating states x projectors", progress):
        proj = scene.projectors[j]
        t0 = time.perf_counter()
        rig.geometry(name)
        t1 = time.perf_counter()
        capture = simulate_calibration(rig, name, j, noise=noise, bits=bits)
        if through is not None:
            capture = through(name, j, capture)
        t2 = time.perf_counter()
        try:
            # A projector's response is the same in every state: a state whose ramp shows too few
            # bars (a small object) leaves it to another (calibrate_virtual).
            calibration = calibrate_projector(capture, (proj.width, proj.height), bits=bits,
                                              plane_tolerance=plane_tolerance, require_response=False)
        except InputError as exc:  # a block map off the plane, or nothing decoded: say which state and projector
            raise InputError(f"state {name!r}, projector {proj.name!r}: {exc}") from None
        warn_if_few_decoded(calibration.decoding, f"state {name!r}, projector {proj.name!r}")
        warn_if_saturated(calibration.saturated, f"state {name!r}, projector {proj.name!r}",
                          "Lower camera.exposure or the projector's power")
        warn_if_noisy(calibration.capture_noise, calibration.saturated, f"state {name!r}, projector {proj.name!r}",
                      "camera.frames")
        for key, seconds in (("cast", t1 - t0), ("capture", t2 - t1), ("calibrate", time.perf_counter() - t2)):
            timings[key] = timings.get(key, 0.0) + seconds
        yield name, j, capture, calibration
        del capture  # a capture stack is hundreds of MB: never hold two while simulating the next


def true_responses(scene) -> list[ResponseCurve]:
    """The scene's projectors' own response curves and colour mixings (the simulator's truth, not a fit)."""
    check_scene(scene)
    return [ResponseCurve(torch.tensor([p.response_a]), torch.tensor(p.response_b), torch.tensor([p.black_level]),
                          None if p.colour_mixing is None else _shares(torch.tensor(p.colour_mixing)))
            for p in scene.projectors]


def _shares(mixing: torch.Tensor) -> torch.Tensor:
    """A colour mixing as shares of each channel's white (rows summing to 1), as calibration measures it."""
    return mixing / mixing.sum(1, keepdim=True)


def _oracle_calibration(scene: Scene, device, black_threshold: float = BLACK_THRESHOLD,
                        dim_threshold: float = DIM_THRESHOLD) -> VirtualCalibration:
    t0 = time.perf_counter()
    rig = VirtualRig(scene, device=device)
    states, black = {}, {}
    for st in scene.states:
        geo = rig.geometry(st.name)
        dark = rig.capture(st.name, {}, noise=False, quantise=False)[0]
        weight, prj_xy, colour, dim = [], [], [], []
        for j, proj in enumerate(scene.projectors):
            white = rig.capture(st.name, {j: torch.ones(1, 1, proj.height, proj.width)}, noise=False, quantise=False)[0]
            colour.append((white - dark).cpu())
            weight.append(colour[-1].mean(0))
            # Exact coordinates where a decoder could see the projector at all (the shadow mask's
            # threshold, and the dim one below it), so that oracle and calibration solve for the same pixels.
            xy = geo.prj_xy[j].cpu().clone()
            xy[weight[-1] <= dim_threshold / 255] = float("nan")
            prj_xy.append(xy)
            dim.append(torch.isfinite(xy).all(-1) & (weight[-1] <= black_threshold / 255))
        states[st.name] = StateCalibration(prj_xy, weight, [(p.width, p.height) for p in scene.projectors],
                                           colour_weight=colour if dark.shape[0] > 1 else None, dim=dim)
        black[st.name] = dark.cpu()
    return VirtualCalibration(rig=rig, states=states, black=black, responses=true_responses(scene),
                              seconds=time.perf_counter() - t0, oracle=True)


def check_calibration(rig: VirtualRig, state: str, projector: int, capture: GraycodeCapture, calibration,
                      noise: bool = True) -> tuple[dict, dict]:
    """One projector's calibration in one state against the simulator's truth (``torchproj simulate``).

    Compares the decoded coordinates, integer and sub-pixel, with the true ones
    (:func:`decoding_accuracy`), and projects the response-compensated ramp and its mirror: their
    sum, normalised by white minus black, should be flat at 1 (the paper's check of the
    compensation, its fig. 4c).

    Returns:
        ``(report, figure_row)``: the ``report.json`` entry, and the row of
        :func:`torchproj.figures.calibration_summary`.
    """
    check_rig(rig)
    projector = rig.scene.projector_index(projector)
    proj = rig.scene.projectors[projector]
    truth = rig.geometry(state).prj_xy[projector]
    counts = calibration.decoding.counts()
    report = {"state": state, "projector": proj.name, "block_cells": list(calibration.decoding.block),
              "decode": {k: counts[k] for k in ("lit", "full", "partial", "none")},
              "decoding_integer": decoding_accuracy(calibration.decoding.prj_xy, truth).as_dict(),
              "decoding_subpixel": decoding_accuracy(calibration.prj_xy, truth).as_dict(),
              "response_fit": None, "response_true_b": list(proj.response_b), "compensated_ramp_sum": None,
              "response_note": calibration.response_note, "capture_noise": calibration.capture_noise}
    row = {"label": f"{state}/{proj.name}", "prj_xy": calibration.prj_xy,
           "error": (calibration.prj_xy - truth).norm(dim=-1), "levels": None}
    if calibration.response is not None:  # else this state's ramp showed too few bars (response_note)
        ramps = torch.cat([ramp_pattern(proj.width, proj.height), ramp_pattern(proj.width, proj.height, mirrored=True)])
        shot = rig.capture(state, {projector: calibration.response.to_pattern(ramps)}, noise=noise)
        span = capture.white - capture.black
        lit = calibration.decoding.valid & (span.mean(0) > 0.1)
        flat = (((shot - capture.black) / span.clamp_min(1e-3)).mean(1).sum(0))[lit]
        report["response_fit"] = calibration.response.as_dict()
        report["compensated_ramp_sum"] = {"mean": float(flat.mean()), "std": float(flat.std())}
        levels, measured = calibration.ramp
        row.update(levels=to_numpy(levels), measured=to_numpy(measured), response=calibration.response,
                   true_b=proj.response_b[0])
    return report, row


def simulate_scene(scene: Scene, folder, *, device="cpu", noise: bool = True, bits: int | None = None,
                   plane_tolerance: float = 1.0, write_captures: bool = False, progress=None) -> str:
    """Calibrate every state and projector on the virtual rig and check it against the truth (``torchproj simulate``).

    Writes into ``folder``: ``report.json`` (per state and projector, :func:`check_calibration`),
    ``report.md``, ``calibration.png``, ``calibration/STATE/PROJECTOR/correspondence.npz`` and, with
    ``write_captures``, the captures as a folder of images (``captures/STATE/PROJECTOR/``), which are
    then what is decoded. Returns the markdown.
    """
    from .. import __version__
    from ..calib import read_graycode_folder, write_graycode_folder
    from ..calib.bundle import SEQUENCE_FILE, sequence_manifest
    from ..core.output import write_json
    from ..figures import calibration_summary

    check_path(folder, "folder", "the simulation's output folder")
    t_start = time.perf_counter()
    folder = Path(folder)
    rig = VirtualRig(scene, device=device)
    timings = {"cast": 0.0, "capture": 0.0, "calibrate": 0.0}

    def through_files(state, j, capture):
        proj = scene.projectors[j]
        path = folder / "captures" / state / proj.name
        write_graycode_folder(path, capture, bits=scene.camera.stored_bits)
        # sequence.json beside them, as torchproj capture leaves it: torchproj calibrate reads the
        # projector's size and bits there. It names the images the virtual rig took.
        manifest = sequence_manifest(proj.width, proj.height, bits=bits)
        manifest["images"] = [entry for entry in manifest["images"] if (path / entry["file"]).is_file()]
        write_json(path / SEQUENCE_FILE, manifest)
        return read_graycode_folder(path, (proj.width, proj.height), bits=bits)

    results, rows = [], []
    for state, j, capture, cal in calibrate_rig(rig, bits=bits, plane_tolerance=plane_tolerance, noise=noise,
                                                progress=progress, timings=timings,
                                                through=through_files if write_captures else None):
        result, row = check_calibration(rig, state, j, capture, cal, noise=noise)
        out = folder / "calibration" / state / scene.projectors[j].name
        out.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(out / "correspondence.npz", prj_xy=to_numpy(cal.prj_xy),
                            prj_xy_integer=to_numpy(cal.decoding.prj_xy), cam_xy=to_numpy(cal.cam_xy),
                            count=to_numpy(cal.count), contrast=to_numpy(cal.decoding.contrast))
        results.append(result)
        rows.append(row)
        del capture  # see calibrate_rig
    calibration_summary(folder / "calibration.png", rows,
                        title=f"Fig. 1: calibration of {scene.name} on the virtual rig, per state and projector")
    timings["total"] = time.perf_counter() - t_start
    # A procedural scene has no file: its name (suite-SEED-INDEX) is what loads it again.
    config = str(scene.source) if scene.source is not None else scene.name
    report = {"scene": scene.name, "config": config, "torchproj": __version__, "device": str(rig.device),
              "noise": noise, "timings_s": {k: round(v, 3) for k, v in timings.items()}, "calibrations": results}
    text = simulate_markdown(report)
    write_json(folder / "report.json", report)
    (folder / "report.md").write_text(text)
    return text


def _decode_shares(decode: dict | None, decoded: float) -> str:
    """``full / partly / not`` shares of the lit pixels; a shortened sequence has no partial decoding."""
    if not decode or not decode["lit"]:
        return f"{decoded:.2%}"
    return " / ".join(f"{decode[k] / decode['lit']:.1%}" for k in ("full", "partial", "none"))


def _noise(share: float | None) -> str:
    return "-" if share is None else f"{share:.2%}"


def simulate_markdown(report: dict) -> str:
    """``report.md`` of ``torchproj simulate``."""
    lines = [f"# Virtual-rig calibration: {report['scene']}", "",
             "Fig. 1 (`calibration.png`): per state and projector, the decoded x and y, their error against "
             "the truth and the fitted response.", "",
             "Decoded coordinates against the simulator's truth, over the camera pixels each projector truly "
             "lights. `exact`: decoded cell equals the true cell; RMS: distance to the continuous true "
             "coordinate (projector pixels); `block`: cells per decoded value (a shortened sequence decodes "
             "blocks, and its map is the homography fitted to them: the RMS of the map). Decoded fully / partly / "
             "not: shares of the pixels the projector visibly lights (white - black over the shadow threshold); a "
             "partly decoded pixel's reliable bits name two or a few cells, and the map places it from its "
             "neighbours (`map` covers those too). Flatness: compensated ramp plus its mirror, normalised by "
             "white - black (ideal 1, std 0). Noise: the camera noise of a lit pixel's white - black, as a share of "
             "it (median), read from how the pattern pairs' sums spread; averaging N frames a capture (`camera.frames`, "
             "`torchproj capture --frames N` on a bench) divides it by the square root of N.", "",
             "| state | projector | block | decoded fully / partly / not | exact | RMS decoded | map covers | RMS map "
             "| fitted b (true) | ramp+mirror mean / std | noise |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in report["calibrations"]:
        di, ds = r["decoding_integer"], r["decoding_subpixel"]
        tb = "/".join(f"{v:g}" for v in r["response_true_b"])
        if r["response_fit"] is None:  # this state's ramp showed too few bars: another state's fits
            b, flat = f"none, too few ramp bars seen ({tb})", "-"
        else:
            b = "/".join(f"{v:.3f}" for v in r["response_fit"]["b"]) + f" ({tb})"
            flat = f"{r['compensated_ramp_sum']['mean']:.3f} / {r['compensated_ramp_sum']['std']:.3f}"
        lines.append(f"| {r['state']} | {r['projector']} | {'x'.join(map(str, r['block_cells']))} | "
                     f"{_decode_shares(r.get('decode'), di['decoded'])} | {di['exact']:.2%} | "
                     f"{di['rms_px']:.3f} | {ds['decoded']:.2%} | {ds['rms_px']:.3f} | {b} | {flat} | "
                     f"{_noise(r.get('capture_noise'))} |")
    t = report["timings_s"]
    lines += ["", "Timings (s): " + ", ".join(f"{k} {v:.1f}" for k, v in t.items()), ""]
    return "\n".join(lines)
