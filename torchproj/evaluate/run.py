"""The main job on the virtual rig: calibrate, build, solve, compensate, project, capture, evaluate.

The evaluation captures are rendered by the simulator from the physics, never computed as ``A p``:
the solver only knows what calibration recovered, so calibration errors show in the numbers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from ..calib import ResponseCurve, calibrate_projector, sequence_bits, simulate_calibration
from ..core.checks import check
from ..core.errors import InputError
from ..core.imageio import read_image
from ..scene.config import Scene
from ..sim.rig import VirtualRig
from ..solve import SolveResult, compensate, make_patterns, solve_gain_offset, to_projectable
from ..transport import StateCalibration, Target, build_transport, planar_calibration, target_on_camera
from .metrics import crosstalk, masked_ssim, psnr

__all__ = ["RunResult", "VirtualCalibration", "calibrate_virtual", "default_images", "run_virtual", "scene_images",
           "target_image", "SOLVER_NAMES"]

DEFAULT_IMAGES = ("astronaut", "chelsea", "coffee", "rocket", "camera")
SOLVER_NAMES = ("fista", "pgd", "adam", "lf", "eo")


def target_image(name: str, channels: int) -> torch.Tensor:
    """A target image by scikit-image test-image name (``astronaut``, ``checkerboard``...) or file path.

    Returns:
        :math:`(C, h, w)` float in [0, 1] with the camera's channel count (RGB to grey by luminance,
        grey repeated to RGB, alpha dropped).
    """
    from skimage import color, data

    if Path(name).suffix:
        img = read_image(name).permute(1, 2, 0).numpy()
    else:
        check(name in getattr(data, "__all__", dir(data)) and not name.startswith("_"),
              f"unknown image {name!r}: give an image file (with its suffix) or a scikit-image test image "
              "name such as astronaut, chelsea, coffee, rocket, camera, checkerboard, horse")
        raw = np.asarray(getattr(data, name)())
        img = raw.astype(np.float32) / (1.0 if raw.dtype == bool else float(np.iinfo(raw.dtype).max)
                                        if raw.dtype.kind in "ui" else 1.0)
    if img.ndim == 2:
        img = img[..., None]
    img = img[..., :3]
    if img.shape[-1] == 1 and channels == 3:
        img = np.repeat(img, 3, -1)
    elif img.shape[-1] == 3 and channels == 1:
        img = color.rgb2gray(img)[..., None]
    return torch.from_numpy(np.ascontiguousarray(img, dtype=np.float32)).permute(2, 0, 1)


def default_images(count: int, channels: int) -> list[torch.Tensor]:
    """Test images that ship with scikit-image, one per target: :math:`(C, h, w)` in [0, 1]."""
    check(count <= len(DEFAULT_IMAGES), f"at most {len(DEFAULT_IMAGES)} default images; give your own targets")
    return [target_image(name, channels) for name in DEFAULT_IMAGES[:count]]


def scene_images(scene: Scene) -> list[torch.Tensor]:
    """One image per target of the scene: the config's choice, else the next default image."""
    specs = scene.target_specs()
    defaults = iter(name for name in DEFAULT_IMAGES if name not in {t.image for t in specs})
    images = []
    for spec in specs:
        name = spec.image or next(defaults, None)
        check(name is not None, f"more targets than default images; give target {spec.name!r} an image")
        images.append(target_image(name, scene.camera.channels))
    return images


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


def calibrate_virtual(scene: Scene, device="cpu", progress=None, oracle: bool = False,
                      bits: int | None = None, plane_tolerance: float = 1.0) -> VirtualCalibration:
    """Simulate and decode every state's calibration captures (Gray code, white, black, ramps).

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
    if oracle:
        check(bits is None, "oracle calibration takes the exact geometry: it shows no Gray code to shorten; drop "
                            "--bits or --oracle")
        return _oracle_calibration(scene, device)
    from tqdm import tqdm

    t0 = time.perf_counter()
    rig = VirtualRig(scene, device=device)
    sizes = [(p.width, p.height) for p in scene.projectors]
    states, black, responses = {}, {}, None
    jobs = [(st.name, j) for st in scene.states for j in range(len(sizes))]
    per_state: dict[str, list] = {}
    for name, j in tqdm(jobs, desc="calibrating states x projectors", leave=False, delay=1.0,
                        disable=None if progress is None else not progress):
        cap = simulate_calibration(rig, name, j, bits=bits)
        try:
            per_state.setdefault(name, []).append(calibrate_projector(cap, sizes[j], bits=bits,
                                                                      plane_tolerance=plane_tolerance))
        except InputError as exc:  # a block map off the plane: say which state and projector
            raise InputError(f"state {name!r}, projector {scene.projectors[j].name!r}: {exc}") from None
        black[name] = cap.black.cpu()  # every projector shows black: the state's black level and ambient light
    for name, pcs in per_state.items():
        states[name] = StateCalibration.from_calibrations(pcs)
        responses = responses or [pc.response for pc in pcs]
    shown = homographies = None
    if bits is not None:
        shown = [sequence_bits(*size, bits) for size in sizes]
        homographies = {name: [pc.homography for pc in pcs] for name, pcs in per_state.items()}
    return VirtualCalibration(rig=rig, states=states, black=black, responses=responses,
                              seconds=time.perf_counter() - t0, bits=shown, homographies=homographies)


def _oracle_calibration(scene: Scene, device, black_threshold: float = 40) -> VirtualCalibration:
    t0 = time.perf_counter()
    rig = VirtualRig(scene, device=device)
    states, black = {}, {}
    for st in scene.states:
        geo = rig.geometry(st.name)
        dark = rig.capture(st.name, {}, noise=False, quantise=False)[0]
        weight, prj_xy = [], []
        for j, proj in enumerate(scene.projectors):
            white = rig.capture(st.name, {j: torch.ones(1, 1, proj.height, proj.width)}, noise=False, quantise=False)[0]
            weight.append((white - dark).mean(0).cpu())
            # Exact coordinates where a decoder could see the projector at all (the shadow mask's
            # threshold), so that oracle and calibration solve for the same pixels.
            xy = geo.prj_xy[j].cpu().clone()
            xy[weight[-1] <= black_threshold / 255] = float("nan")
            prj_xy.append(xy)
        states[st.name] = StateCalibration(prj_xy, weight, [(p.width, p.height) for p in scene.projectors])
        black[st.name] = dark.cpu()
    responses = [ResponseCurve(torch.tensor([p.response_a]), torch.tensor(p.response_b), torch.tensor([p.black_level]))
                 for p in scene.projectors]
    return VirtualCalibration(rig=rig, states=states, black=black, responses=responses,
                              seconds=time.perf_counter() - t0, oracle=True)


@dataclass
class RunResult:
    """Everything a run produced. ``report`` is what ``report.json`` holds."""

    report: dict
    patterns: list[torch.Tensor]  # per projector, (C, H_j, W_j) uint8
    captures: dict[str, torch.Tensor]  # per state, (C, H, W) float in [0, 1]
    targets: list[dict] = field(default_factory=list)  # per target: name, values, covered, estimate
    solution: SolveResult | None = None  # the solver's own result (values in its bounds, history)


def run_virtual(scene: Scene, *, solver: str = "fista", bounds_8bit=(0, 255), images: list[torch.Tensor] | None = None,
                device="cpu", max_iter: int = 300, progress=None, calibration: VirtualCalibration | None = None,
                oracle: bool = False, gain_offset: tuple[tuple[float, float], tuple[float, float]] | None = None,
                maps: str = "decoded", plane_tolerance: float = 1.0, bits: int | None = None) -> RunResult:
    """Run the whole workflow on the virtual rig for the scene's targets (:meth:`Scene.target_specs`).

    Args:
        scene: the scene; its ``targets`` (or one per state) say which image goes where.
        solver: ``fista`` (default, the best measured), ``pgd``, ``adam``, ``lf`` or ``eo``.
        bounds_8bit: solver bounds in 8-bit units as in the paper (``(-100, 255)`` with ``eo`` is
            ``EO_-100^255``); bounds outside [0, 255] are brought into range afterwards.
        images: one :math:`(C, h, w)` image per target; default: the config's, else scikit-image's.
        device: torch device for the rig and the solver.
        max_iter: iteration limit of iterative solvers.
        progress: progress bars (None: on a terminal, for steps longer than a second).
        calibration: reuse an earlier :func:`calibrate_virtual` of the same scene.
        oracle: build the operator from the simulator's exact geometry instead of calibration
            (ignored when ``calibration`` is given; that one's own mode counts).
        gain_offset: ``((gain_lo, gain_hi), (offset_lo, offset_hi))`` to optimise one gain and offset
            per target with FISTA (:func:`~torchproj.solve.solve_gain_offset`); None asks for the
            images as they are. Metrics then compare with the adjusted image ``g t + o``, and the
            report also scores against the original.
        maps: ``"decoded"`` (default: the per-pixel Gray-code maps) or ``"homography"`` (one fitted
            homography per state and projector, :func:`~torchproj.transport.planar_calibration`;
            for scenes where each state is one plane; refused otherwise).
        plane_tolerance: with ``maps="homography"`` or ``bits``, the largest 95th-percentile
            residual (projector pixels) between decoded and fitted coordinates that counts as a plane.
        bits: calibrate with the first ``bits`` Gray-code pattern pairs per axis only, read through
            one homography per state and projector (:func:`calibrate_virtual`); planar scenes.
            Ignored when ``calibration`` is given.
    """
    check(solver in SOLVER_NAMES, f"unknown solver {solver!r}; choose from {list(SOLVER_NAMES)}")
    check(gain_offset is None or solver == "fista", "gain_offset works with the fista solver; drop --solver or "
                                                    "the gain/offset option")
    lo, hi = (float(b) / 255 for b in bounds_8bit)
    check(lo < hi, f"bounds must satisfy LO < HI, got {bounds_8bit}")
    specs = scene.target_specs()
    images = scene_images(scene) if images is None else images
    check(len(images) == len(specs), f"give one target image per target ({len(specs)}), got {len(images)}")
    t_total = time.perf_counter()
    check(maps in ("decoded", "homography"), f"maps must be 'decoded' or 'homography', got {maps!r}")
    cal = calibration or calibrate_virtual(scene, device, progress, oracle=oracle, bits=bits,
                                           plane_tolerance=plane_tolerance)
    timings = {"calibrate": cal.seconds if calibration is None else 0.0}
    states, fits = cal.states, cal.homographies
    if cal.homographies is not None:
        maps = "homography"  # a shortened sequence is read through homographies already
    elif maps == "homography":
        t0 = time.perf_counter()
        states, fits = planar_calibration(cal.states, plane_tolerance)
        timings["homography"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    targets = [Target(spec.state, img.to(torch.float32), name=spec.name,
                      mask=None if spec.surfaces is None else cal.rig.surface_mask(spec.state, spec.surfaces).cpu())
               for spec, img in zip(specs, images)]
    if gain_offset is None:
        op = build_transport(states, targets, device=device)
    else:
        # Unmerged rows, so that any per-target g t + o is an exact right-hand side of the same A.
        op = build_transport(states, targets, merge=False, device=device)
        flat = build_transport(states, [replace(t, image=torch.ones_like(t.image)) for t in targets],
                               merge=False, scale=op.scale, device=device)
    timings["transport"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if gain_offset is not None:
        result = solve_gain_offset(op, flat.rhs, (lo, hi), gain=gain_offset[0], offset=gain_offset[1], max_iter=max_iter,
                                   progress=progress)
        model = op.size_report()
        op = result.info.pop("operator")
        light = to_projectable(result.patterns, (lo, hi)).clamp(0, 1)
        patterns = compensate([img.cpu() for img in op.to_images(light)], cal.responses)
    else:
        result, _, patterns = make_patterns(op, solver, (lo, hi), cal.responses, calibrations=states,
                                            max_iter=max_iter, progress=progress)
    timings["solve"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    shown = {j: (p.float() / 255)[None].to(device) for j, p in enumerate(patterns)}
    captures = {state: cal.rig.capture(state, shown)[0].cpu() for state in dict.fromkeys(t.state for t in targets)}
    rows, details = [], []
    for k, target in enumerate(targets):
        lit = states[target.state].lit()
        region = lit if target.mask is None else lit & target.mask
        values, covered = target_on_camera(target, region)
        estimate = ((captures[target.state] - cal.black[target.state]) / op.scale).clamp(0, 1)
        others = [target_on_camera(Target(target.state, t.image, name=t.name), region)[0]
                  for m, t in enumerate(targets) if m != k]
        row = {"name": target.name, "state": target.state, "surfaces": specs[k].surfaces}
        if gain_offset is not None:
            g, o = result.info["gain"][k], result.info["offset"][k]
            row.update(gain=round(g, 4), offset=round(o, 4),
                       psnr_db_original=psnr(estimate[:, covered], values[:, covered]),
                       ssim_original=masked_ssim(estimate, values, covered))
            values = (g * values + o).clamp(0, 1)
        row.update(psnr_db=psnr(estimate[:, covered], values[:, covered]),
                   ssim=masked_ssim(estimate, values, covered),
                   crosstalk=crosstalk(estimate, others, covered), pixels=int(covered.sum()))
        rows.append(row)
        details.append({"name": target.name, "values": values, "covered": covered, "estimate": estimate})
    timings["evaluate"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_total
    report = {
        "scene": scene.name, "solver": solver if gain_offset is None else "fista+gain/offset",
        "bounds_8bit": list(bounds_8bit), "device": str(device),
        "calibration": "oracle (the simulator's exact geometry)" if cal.oracle else "Gray code on the virtual rig",
        "maps": maps,
        "graycode": _graycode_report(scene, cal),
        "model": model if gain_offset is not None else op.size_report(), "objective": result.objective,
        "unexplained_fraction": round(op.unexplained(result.patterns), 5),
        "iterations": result.iterations, "scale": op.scale,
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "evaluation": ("captured image minus the state's black capture, divided by the target scale, against the "
                       "target image warped onto the camera pixels of its surfaces that calibration found lit; "
                       "data range 1; SSIM averaged over those pixels; crosstalk is the largest |Pearson "
                       "correlation| there with another target's image placed on the same pixels"
                       + ("; with gain/offset, psnr_db and ssim compare with the adjusted image g t + o, "
                          "psnr_db_original and ssim_original with t" if gain_offset is not None else "")),
        "targets": rows,
    }
    if fits is not None:
        report["homographies"] = {state: [f.as_dict() for f in per] for state, per in fits.items()}
    if gain_offset is not None:
        report["gain_offset_limits"] = {"gain": list(gain_offset[0]), "offset": list(gain_offset[1])}
    return RunResult(report=report, patterns=patterns, captures=captures, targets=details, solution=result)


def _graycode_report(scene: Scene, cal: VirtualCalibration) -> dict | None:
    """Per projector, the Gray-code bits shown and the captures that took per state (None for the oracle)."""
    if cal.oracle:
        return None
    sizes = [(p.width, p.height) for p in scene.projectors]
    shown = cal.bits or [sequence_bits(*size) for size in sizes]
    # Pattern/inverse pairs, white and black, and the two ramps.
    return {p.name: {"bits": list(b), "captures_per_state": 2 * sum(b) + 4} for p, b in zip(scene.projectors, shown)}
