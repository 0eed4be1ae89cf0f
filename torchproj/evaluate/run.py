"""The main job on the virtual rig: calibrate, build, solve, compensate, project, capture, evaluate.

The evaluation captures are rendered by the simulator from the physics, never computed as ``A p``:
the solver only knows what calibration recovered, so calibration errors show in the numbers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from ..calib import calibrate_projector, simulate_calibration
from ..core.checks import check
from ..scene.config import Scene
from ..sim.rig import VirtualRig
from ..solve import compensate, solve_eo, solve_patterns, to_projectable
from ..transport import StateCalibration, Target, build_transport, target_on_camera
from .metrics import crosstalk, masked_ssim, psnr

__all__ = ["RunResult", "VirtualCalibration", "calibrate_virtual", "default_images", "run_virtual", "SOLVER_NAMES"]

DEFAULT_IMAGES = ("astronaut", "chelsea", "coffee", "rocket", "camera")
SOLVER_NAMES = ("fista", "pgd", "adam", "lf", "eo")


def default_images(count: int, channels: int) -> list[torch.Tensor]:
    """Test images that ship with scikit-image, one per target: :math:`(C, h, w)` in [0, 1]."""
    from skimage import color, data

    check(count <= len(DEFAULT_IMAGES), f"at most {len(DEFAULT_IMAGES)} default images; give your own targets")
    images = []
    for name in DEFAULT_IMAGES[:count]:
        img = getattr(data, name)().astype(np.float32) / 255
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, -1)
        if channels == 1:
            img = color.rgb2gray(img)[..., None]
        images.append(torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1).float())
    return images


@dataclass
class VirtualCalibration:
    """A scene calibrated on the virtual rig: what the solver may know, plus the rig to evaluate on."""

    rig: VirtualRig
    states: dict[str, StateCalibration]
    black: dict[str, torch.Tensor]  # per state, (C, H, W) capture with every projector showing black
    responses: list  # per projector, its fitted ResponseCurve
    seconds: float


def calibrate_virtual(scene: Scene, device="cpu", progress=None) -> VirtualCalibration:
    """Simulate and decode every state's calibration captures (Gray code, white, black, ramps)."""
    from tqdm import tqdm

    t0 = time.perf_counter()
    rig = VirtualRig(scene, device=device)
    sizes = [(p.width, p.height) for p in scene.projectors]
    states, black, responses = {}, {}, None
    jobs = [(st.name, j) for st in scene.states for j in range(len(sizes))]
    per_state: dict[str, list] = {}
    for name, j in tqdm(jobs, desc="calibrating states x projectors", leave=False, delay=1.0,
                        disable=None if progress is None else not progress):
        cap = simulate_calibration(rig, name, j)
        per_state.setdefault(name, []).append(calibrate_projector(cap, sizes[j]))
        black[name] = cap.black.cpu()  # every projector shows black: the state's black level and ambient light
    for name, pcs in per_state.items():
        states[name] = StateCalibration.from_calibrations(pcs)
        responses = responses or [pc.response for pc in pcs]
    return VirtualCalibration(rig=rig, states=states, black=black, responses=responses,
                              seconds=time.perf_counter() - t0)


@dataclass
class RunResult:
    """Everything a run produced. ``report`` is what ``report.json`` holds."""

    report: dict
    patterns: list[torch.Tensor]  # per projector, (C, H_j, W_j) uint8
    captures: dict[str, torch.Tensor]  # per state, (C, H, W) float in [0, 1]
    targets: list[dict] = field(default_factory=list)  # per target: name, values, covered, estimate


def run_virtual(scene: Scene, *, solver: str = "fista", bounds_8bit=(0, 255), images: list[torch.Tensor] | None = None,
                device="cpu", max_iter: int = 300, progress=None,
                calibration: VirtualCalibration | None = None) -> RunResult:
    """Run the whole workflow on the virtual rig, one target per scene state.

    Args:
        scene: the scene (its states become the targets' states, in order).
        solver: ``fista`` (default, the best measured), ``pgd``, ``adam``, ``lf`` or ``eo``.
        bounds_8bit: solver bounds in 8-bit units as in the paper (``(-100, 255)`` with ``eo`` is
            ``EO_-100^255``); bounds outside [0, 255] are brought into range afterwards.
        images: one :math:`(C, h, w)` image per state; default: scikit-image's test images.
        device: torch device for the rig and the solver.
        max_iter: iteration limit of iterative solvers.
        progress: progress bars (None: on a terminal, for steps longer than a second).
        calibration: reuse an earlier :func:`calibrate_virtual` of the same scene.
    """
    check(solver in SOLVER_NAMES, f"unknown solver {solver!r}; choose from {list(SOLVER_NAMES)}")
    lo, hi = (float(b) / 255 for b in bounds_8bit)
    check(lo < hi, f"bounds must satisfy LO < HI, got {bounds_8bit}")
    images = default_images(len(scene.states), scene.camera.channels) if images is None else images
    check(len(images) == len(scene.states), f"give one target image per state ({len(scene.states)}), got {len(images)}")
    t_total = time.perf_counter()
    cal = calibration or calibrate_virtual(scene, device, progress)
    timings = {"calibrate": cal.seconds if calibration is None else 0.0}

    t0 = time.perf_counter()
    targets = [Target(st.name, img.to(torch.float32), name=st.name) for st, img in zip(scene.states, images)]
    op = build_transport(cal.states, targets, device=device)
    timings["transport"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if solver == "eo":
        result = solve_eo(op, (lo, hi), calibrations=cal.states, max_iter=max_iter, progress=progress)
    else:
        result = solve_patterns(op, solver, (lo, hi), max_iter=max_iter, progress=progress)
    light = to_projectable(result.patterns, (lo, hi)).clamp(0, 1)
    patterns = compensate([img.cpu() for img in op.to_images(light)], cal.responses)
    timings["solve"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    shown = {j: (p.float() / 255)[None].to(device) for j, p in enumerate(patterns)}
    rows, details, captures = [], [], {}
    for k, target in enumerate(targets):
        shot = cal.rig.capture(target.state, shown)[0].cpu()
        captures[target.state] = shot
        lit = cal.states[target.state].lit()
        values, covered = target_on_camera(target, lit)
        estimate = ((shot - cal.black[target.state]) / op.scale).clamp(0, 1)
        others = [target_on_camera(Target(target.state, t.image, name=t.name), lit)[0]
                  for m, t in enumerate(targets) if m != k]
        rows.append({
            "name": target.name, "state": target.state,
            "psnr_db": psnr(estimate[:, covered], values[:, covered]),
            "ssim": masked_ssim(estimate, values, covered),
            "crosstalk": crosstalk(estimate, others, covered),
            "pixels": int(covered.sum()),
        })
        details.append({"name": target.name, "values": values, "covered": covered, "estimate": estimate})
    timings["evaluate"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_total
    report = {
        "scene": scene.name, "solver": solver, "bounds_8bit": list(bounds_8bit), "device": str(device),
        "model": op.size_report(), "objective": result.objective, "iterations": result.iterations,
        "scale": op.scale,
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "evaluation": ("captured image minus the state's black capture, divided by the target scale, against the "
                       "target image warped onto the camera pixels that calibration found lit in the target's "
                       "state; data range 1; SSIM averaged over those pixels; crosstalk is the largest |Pearson "
                       "correlation| there with another target's image placed on the same pixels"),
        "targets": rows,
    }
    return RunResult(report=report, patterns=patterns, captures=captures, targets=details)
