"""Positioning accuracy (paper section 5.2): place a box guided only by the projected image, then scan it.

The patterns show an image on a box at a goal pose and fade elsewhere. A placement trial starts the
box at a random pose near the goal and moves it the way a person or a robot with a camera would:
it looks at what the camera sees on the box and keeps the moves that make it look more like the
intended image. The feedback is the PSNR of the camera image (black capture taken off, divided by
the target scale, as in ``run_virtual``) against the target image, over the camera pixels where the
target image should appear. The true pose is never read during placement; the optimiser only knows
the moves it made from wherever the box started (Nelder-Mead over a 6-DoF displacement).

The placed box is then scanned with Gray code on the virtual rig (its camera noise included) and
triangulated with the rig's known geometry (camera and each projector, all points pooled). The
error is the RMS distance of the scanned points from the box surface at the goal pose, in
millimetres and as a percentage of the distance from the goal box centre to the projectors (the
midpoint of their centres), the paper's measure: 1.47 % near (about 710 mm), 1.26 % far (880 mm).

Poses are 4x4 ``world_from_local`` matrices (world frame: :mod:`torchproj.core.conventions`).
"""

from __future__ import annotations

import dataclasses
import math
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..calib import scan_map
from ..pipeline import simulate_calibration
from ..calib.triangulate import ProCamCalibration, triangulate
from ..core.checks import check, check_array, check_count, check_number, check_path, check_seed, is_number, is_whole
from ..core.progress import progress_bar
from ..core.conventions import pixel_grid, to_numpy
from ..core.errors import CaptureError, ConfigError, InputError
from ..scene.config import Scene, State, Surface, check_scene
from ..scene.show import describe_show
from ..scene.pose import rotation_from_rotvec
from ..sim.rig import VirtualRig
from ..metrics import psnr
from ..solve import check_solve_options
from ..solve.compensate import iteration_limit
from ..pipeline import VirtualCalibration, calibrate_virtual, run_virtual, shown_world

__all__ = ["PAPER_RMSE_PERCENT", "PlacementTrial", "PositioningResult", "box_surface_distance", "evaluate_positioning",
           "feedback_profile", "place_by_feedback", "placement_error", "position_markdown", "pose_error", "random_pose_near", "rig_procam", "scan_distance",
           "scan_surface"]

# Paper section 5.2: average RMSE as a percentage of the box-projector distance, and that distance.
PAPER_RMSE_PERCENT = {"near": {"percent": 1.47, "distance_mm": 710}, "far": {"percent": 1.26, "distance_mm": 880}}


# ------------------------------------------------------------------------------------------ poses
def _moved(pose: np.ndarray, displacement: np.ndarray) -> np.ndarray:
    """``pose`` translated by ``displacement[:3]`` (metres, world axes) and turned about its own
    centre by the rotation vector ``displacement[3:]`` (radians, world axes): how one moves a box."""
    out = pose.copy()
    out[:3, :3] = rotation_from_rotvec(displacement[3:]) @ pose[:3, :3]
    out[:3, 3] = pose[:3, 3] + displacement[:3]
    return out


def random_pose_near(goal: np.ndarray, spread_m: float, spread_deg: float, rng: np.random.Generator) -> np.ndarray:
    """A start pose: each coordinate of the centre within ``spread_m`` of the goal's, and turned by
    up to ``spread_deg`` about a random axis through the centre."""
    goal = _pose(goal, "goal")
    check_number(spread_m, "spread_m (metres)")
    check_number(spread_deg, "spread_deg (degrees)")
    check(isinstance(rng, np.random.Generator), f"rng must be a numpy Generator (np.random.default_rng(seed)), got "
                                                f"{type(rng).__name__}")
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = math.radians(spread_deg) * rng.uniform(-1, 1)
    return _moved(goal, np.r_[rng.uniform(-spread_m, spread_m, 3), axis * angle])


def _pose(pose, name: str) -> np.ndarray:
    """A :math:`(4, 4)` ``world_from_local`` of finite numbers."""
    return check_array(pose, f"{name} (a 4x4 world_from_local pose)", (4, 4), finite=True)


def pose_error(pose: np.ndarray, goal: np.ndarray) -> dict:
    """Translation of the centre (mm, world axes, and its length) and rotation angle (degrees)."""
    pose, goal = _pose(pose, "pose"), _pose(goal, "goal")
    t = (pose[:3, 3] - goal[:3, 3]) * 1000
    cos = (np.trace(goal[:3, :3].T @ pose[:3, :3]) - 1) / 2
    return {"translation_mm": [round(float(v), 3) for v in t], "distance_mm": round(float(np.linalg.norm(t)), 3),
            "rotation_deg": round(math.degrees(math.acos(float(np.clip(cos, -1, 1)))), 4)}


def box_surface_distance(points: np.ndarray, world_from_local: np.ndarray, size, signed: bool = False) -> np.ndarray:
    """Distance of world points :math:`(N, 3)` from the surface of a box (same units).

    Outside the box it is the distance to the nearest point of the box; inside, to the nearest face.
    ``signed``: negative inside (a scanned face pushed past the goal's), positive outside (short of it).
    """
    points = check_array(points, "points", (None, 3))
    world_from_local = _pose(world_from_local, "world_from_local")
    size = check_array(size, "size (the box's sides)", (3,), finite=True)
    check(bool((size > 0).all()), f"size must be the box's three sides, each > 0, got {size.tolist()}")
    local = (points - world_from_local[:3, 3]) @ world_from_local[:3, :3]
    q = np.abs(local) - np.asarray(size, dtype=np.float64) / 2
    outside = np.linalg.norm(np.maximum(q, 0), axis=1)
    inside = np.minimum(q.max(axis=1), 0)
    return outside + inside if signed else np.abs(outside + inside)


def _posed(surface: Surface, pose: np.ndarray, name: str | None = None) -> Surface:
    return dataclasses.replace(surface, name=name or surface.name, world_from_local=pose)


# --------------------------------------------------------------------------------------- feedback
class _Feedback:
    """What the camera tells about a pose: PSNR against the intended image over the target's pixels."""

    def __init__(self, rig: VirtualRig, surface: Surface, shown: dict, region: torch.Tensor, values: torch.Tensor,
                 black: torch.Tensor, scale: float, seed: int, stride: int = 1):
        self.rig, self.surface, self.shown, self.scale = rig, surface, shown, scale
        # The match is scored on every stride-th pixel in each direction: the score hardly changes
        # and each look simulates stride^2 times fewer pixels.
        region = region.clone()
        keep = torch.zeros_like(region)
        keep[::stride, ::stride] = True
        region &= keep
        self.pixels = torch.nonzero(region.reshape(-1))[:, 0]
        self.values = values[:, region]
        self.black = black[:, region]
        self.seed = seed
        self.count = 0

    def __call__(self, pose: np.ndarray) -> float:
        self.count += 1
        shot = self.rig.capture_surfaces([_posed(self.surface, pose)], self.shown, self.pixels,
                                         seed=self.seed + self.count).cpu()
        return psnr(((shot - self.black) / self.scale).clamp(0, 1), self.values)


def _nelder_mead(feedback, start: np.ndarray, origin: np.ndarray, scale: np.ndarray, looks: int, tolerance: float,
                 history: list[float]) -> np.ndarray:
    """Nelder-Mead on ``feedback`` over the displacement ``origin + x * scale`` from ``start``, at
    most ``looks`` looks (appended to ``history``); returns the best displacement it found."""
    from scipy.optimize import minimize

    first = len(history)

    def cost(x):
        history.append(feedback(_moved(start, origin + x * scale)))
        return -history[-1]

    # A simplex that has collapsed may sit on a ridge rather than the peak: start again from the
    # best pose with a simplex half as large, as a person nudges the box once more, until a restart
    # no longer helps or the looks are used up.
    x, best, size = np.zeros(6), -math.inf, 1.0
    while len(history) - first < looks:
        simplex = x + np.vstack([np.zeros(6), size * np.eye(6)])
        res = minimize(cost, x, method="Nelder-Mead",
                       options={"initial_simplex": simplex, "maxfev": looks - (len(history) - first),
                                "xatol": tolerance, "fatol": 0.01, "adaptive": True})
        if -res.fun < best + 0.05:
            x = res.x if -res.fun > best else x
            break
        x, best, size = res.x, -res.fun, size / 2
    return origin + x * scale


def _check_feedback(feedback, name: str = "feedback") -> None:
    check(callable(feedback), f"{name} must be a function of a pose (higher is better), got {type(feedback).__name__}")


def place_by_feedback(feedback, start: np.ndarray, *, step_m: float, step_deg: float, max_evaluations: int = 200,
                      tolerance_m: float = 2e-4, coarse=None) -> tuple[np.ndarray, list[float]]:
    """Move a box from ``start`` to where ``feedback(pose)`` (higher is better) peaks.

    Nelder-Mead over the displacement from the start (3 translations, 3 rotations about the box's
    centre), its first simplex a step of ``step_m`` / ``step_deg`` along each. It never sees the
    goal: only the feedback of the poses it tries.

    With ``coarse`` (a second feedback, cheaper: the same score on fewer pixels), the placement goes
    coarse to fine, as a person first gets the image roughly onto the box and then brings its
    detail into line: one look with ``feedback`` at the start, half of the looks on ``coarse`` from
    the start (until its simplex is within ``COARSE_TOLERANCE_M``), then the rest on ``feedback``
    from the best coarse pose, its first simplex ``FINE_STEP`` times the steps. Far from the goal a
    sparse sample of the image says which way to move as well as a dense one; near it, more pixels
    tell finer moves apart. A choice of torchproj's (the paper's people placed boxes by eye),
    measured in ``benchmarks/placement.py``.

    Returns:
        the placed pose and the feedback of every look, in order (with ``coarse``, looks 1 to k are
        the coarse feedback's values, on its own scale: k is the number of ``coarse``'s calls, at most
        ``coarse_looks(max_evaluations)``, fewer where its simplex closes first).
    """
    _check_feedback(feedback)
    if coarse is not None:
        _check_feedback(coarse, "coarse")
    start = _pose(start, "start")
    check_number(step_m, "step_m (metres)", strict=True)
    check_number(step_deg, "step_deg (degrees)", strict=True)
    check_count(max_evaluations, "max_evaluations")
    check_number(tolerance_m, "tolerance_m (metres)")
    scale = np.r_[np.full(3, step_m), np.full(3, math.radians(step_deg))]
    history: list[float] = []
    if coarse is None:
        x = _nelder_mead(feedback, start, np.zeros(6), scale, max_evaluations, tolerance_m / step_m, history)
        return _moved(start, x), history
    history.append(feedback(start))
    rough: list[float] = []
    x = _nelder_mead(coarse, start, np.zeros(6), scale, coarse_looks(max_evaluations), COARSE_TOLERANCE_M / step_m,
                     rough)
    fine = scale * np.r_[np.full(3, FINE_STEP[0]), np.full(3, FINE_STEP[1])]
    history += rough
    x = _nelder_mead(feedback, start, x, fine, max_evaluations - len(history), tolerance_m / fine[0], history)
    return _moved(start, x), history


COARSE_TOLERANCE_M = 1e-3  # the coarse stage stops once its simplex is within a millimetre
FINE_STEP = (0.1, 0.2)  # the fine stage's first simplex: a tenth of the translation step, a fifth of the turn
# The feedbacks score every n-th pixel in each direction, the sparsest n up to 4 that keeps this many of
# the target's pixels: every 4th (coarse) and every 3rd / 2nd (fine) on the default scene's near / far box.
COARSE_PIXELS, FINE_PIXELS = 2_500, 10_000


def coarse_looks(max_evaluations: int) -> int:
    """How many of a coarse-to-fine placement's looks go to the coarse stage: half of those after the first."""
    return (max_evaluations - 1) // 2


def feedback_stride_for(region: torch.Tensor, pixels: int = FINE_PIXELS) -> int:
    """The sparsest stride (1-4) whose grid keeps at least ``pixels`` of the target's pixels
    ``region`` :math:`(H, W)` (bool), else 1: a small target is scored on every pixel, coarse or fine."""
    return max([1] + [s for s in (2, 3, 4) if int(region[::s, ::s].sum()) >= pixels])


# ------------------------------------------------------------------------------------------- scan
def rig_procam(scene: Scene, j: int) -> ProCamCalibration:
    """The exact camera-projector calibration of a virtual rig (camera and projector ``j``), for
    :func:`~torchproj.calib.triangulate`: what a perfect stereo calibration would give."""
    cam, proj = check_scene(scene).camera, scene.projectors[scene.projector_index(j)]
    prj_from_cam = np.linalg.inv(proj.world_from_prj) @ cam.world_from_cam
    dist = torch.tensor(list(cam.distortion) or [0.0] * 5, dtype=torch.float64)
    return ProCamCalibration(cam_K=torch.as_tensor(cam.K, dtype=torch.float64), cam_dist=dist,
                             prj_K=torch.as_tensor(proj.K, dtype=torch.float64),
                             prj_dist=torch.zeros(5, dtype=torch.float64),
                             prj_from_cam=torch.as_tensor(prj_from_cam[:3], dtype=torch.float64))


def scan_surface(scene: Scene, surface: Surface, pose: np.ndarray, *, seed: int = 0, device="cpu",
                 world: Scene | None = None) -> dict:
    """Gray-code scan of one surface at ``pose`` on the virtual rig, with the rig's known geometry.

    Each projector shows its Gray code alone; every decoded camera pixel is triangulated against it.
    Only the window of the camera image the box can appear in is simulated (:func:`_box_window`).

    ``world``: the scene whose devices take the scan (default ``scene``), the world as shown where it
    changed after calibration (:func:`~torchproj.scene.shown_scene`): the scanner still triangulates
    with ``scene``'s geometry, all it knows, so a projector or camera moved since shows in the points.

    Returns:
        ``points`` :math:`(N, 3)` world points (metres) and ``projector`` :math:`(N,)` the index of
        the projector each came from.
    """
    check_scene(scene)
    check(isinstance(surface, Surface) and surface.type == "box",
          f"surface must be a box Surface (a scene's box, scene.surfaces[name]), got "
          f"{getattr(surface, 'type', type(surface).__name__)!r}")
    check_seed(seed)
    world = scene if world is None else check_scene(world, "world")
    check(len(world.projectors) == len(scene.projectors) and (world.camera.width, world.camera.height)
          == (scene.camera.width, scene.camera.height),
          "world must be the scene as shown (shown_scene(scene)): the same projectors and camera, moved at most")
    placed = _posed(surface, _pose(pose, "pose"), "scanned")
    cam = scene.camera
    x0, y0, window = _box_window(world.camera, placed)
    scan_scene = dataclasses.replace(world, camera=window, surfaces={"scanned": placed},
                                     states=[State("scan", ["scanned"])], targets=[], seed=seed, show=None)
    rig = VirtualRig(scan_scene, device=device)
    grid = pixel_grid(window.height, window.width, device=rig.device).double()
    grid += torch.tensor([x0, y0], dtype=grid.dtype, device=grid.device)  # the full camera's pixel coordinates
    points, owner = [], []
    for j, proj in enumerate(scene.projectors):
        prj_xy = scan_map(simulate_calibration(rig, "scan", j), (proj.width, proj.height))
        valid = torch.isfinite(prj_xy).all(-1)
        if not bool(valid.any()):
            continue
        in_cam = to_numpy(triangulate(grid[valid], prj_xy[valid].double(), rig_procam(scene, j)))
        points.append(in_cam @ cam.world_from_cam[:3, :3].T + cam.world_from_cam[:3, 3])
        owner.append(np.full(len(in_cam), j))
    if not points:
        return {"points": np.zeros((0, 3)), "projector": np.zeros(0, dtype=int)}
    return {"points": np.concatenate(points), "projector": np.concatenate(owner)}


def _box_window(cam, box: Surface, margin: int = 2):
    """The part of the camera's image a box can appear in, as a camera of its own.

    Outside the image of the box's corners no ray meets the box (its image is the convex hull of
    theirs through a pinhole), so the scan simulates only that window, ``margin`` pixels wider: a
    cropped pinhole is the same camera with its principal point moved, so every pixel in it sees
    what it saw (its noise is drawn afresh). Where the lens distorts or a corner is behind the
    camera, the whole image.

    Returns:
        the window's left column and top row in the full image, and the cropped camera.
    """
    local = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)]) * np.asarray(box.size)
    world = local @ box.world_from_local[:3, :3].T + box.world_from_local[:3, 3]
    cam_from_world = np.linalg.inv(cam.world_from_cam)
    points = world @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    if cam.distortion or (points[:, 2] <= 1e-6).any():
        return 0, 0, cam
    u = cam.fx * points[:, 0] / points[:, 2] + cam.cx
    v = cam.fy * points[:, 1] / points[:, 2] + cam.cy
    left = int(np.clip(math.floor(u.min()) - margin, 0, cam.width - 1))
    top = int(np.clip(math.floor(v.min()) - margin, 0, cam.height - 1))
    right = int(np.clip(math.ceil(u.max()) + margin, left, cam.width - 1))
    bottom = int(np.clip(math.ceil(v.max()) + margin, top, cam.height - 1))
    return left, top, dataclasses.replace(cam, width=right - left + 1, height=bottom - top + 1, cx=cam.cx - left,
                                          cy=cam.cy - top)


def scan_distance(points: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Distance from each scanned point :math:`(N, 3)` to the nearest point of a reference scan
    :math:`(M, 3)` (same units): how a real placement is scored when the goal is itself a scan of the
    object at its goal pose rather than a model."""
    from scipy.spatial import cKDTree

    points, reference = check_array(points, "points", (None, 3)), check_array(reference, "reference", (None, 3))
    check(len(points) > 0 and len(reference) > 0, "both scans need points (decode with --calibration)")
    return cKDTree(reference).query(points, k=1)[0]


# --------------------------------------------------------------------------------------- profiles
def feedback_profile(feedback, goal: np.ndarray, offsets_m: np.ndarray) -> dict:
    """Feedback with the box moved from the goal along depth (world z), across (world x) and
    vertically (world y)."""
    _check_feedback(feedback)
    goal = _pose(goal, "goal")
    offsets_m = check_array(offsets_m, "offsets_m (metres)", (None,), finite=True)
    out = {"offsets_mm": (np.asarray(offsets_m) * 1000).round(3).tolist()}
    for key, axis in (("depth", 2), ("across", 0), ("vertical", 1)):
        values = []
        for off in offsets_m:
            shift = np.zeros(6)
            shift[axis] = off
            values.append(round(feedback(_moved(goal, shift)), 3))
        out[key] = values
    return out


# ------------------------------------------------------------------------------------ evaluation
@dataclass
class PlacementTrial:
    """One placement from a random start, and the scan of where the box ended."""

    position: str
    trial: int
    start: np.ndarray
    placed: np.ndarray
    history: list[float]
    scan: dict
    rmse_mm: float
    rmse_percent: float
    seconds: float
    coarse_looks: int = 0  # looks 1..coarse_looks scored the coarse feedback (place_by_feedback)

    def fine_history(self) -> list[float]:
        """The feedback's own values, the coarse looks left out: what the report's start and end compare."""
        return [h for i, h in enumerate(self.history) if not 1 <= i <= self.coarse_looks]


@dataclass
class PositioningResult:
    report: dict
    trials: list[PlacementTrial]
    patterns: list[torch.Tensor]  # per projector, (C, H_j, W_j) uint8
    profiles: dict[str, dict] = field(default_factory=dict)  # per position: feedback_profile

    def write(self, folder, scene: Scene) -> str:
        """``report.json``, ``report.md``, ``feedback.png``, ``patterns/`` and ``scans/`` into ``folder``;
        returns the markdown."""
        from ..core.imageio import write_image
        from ..core.output import write_json
        from ..figures import positioning_feedback

        folder = Path(folder)
        (folder / "patterns").mkdir(parents=True, exist_ok=True)
        for proj, pat in zip(scene.projectors, self.patterns):
            write_image(folder / "patterns" / f"{proj.name}.png", pat.float() / 255)
        (folder / "scans").mkdir(exist_ok=True)
        goals = {p["name"]: scene.surfaces[p["surface"]] for p in self.report["positions"]}
        for t in self.trials:
            box = goals[t.position]
            np.savez_compressed(folder / "scans" / f"{t.position}_{t.trial}.npz", points=t.scan["points"],
                                projector=t.scan["projector"], goal_pose=box.world_from_local, placed_pose=t.placed,
                                start_pose=t.start, box_size=np.array(box.size))
        positioning_feedback(folder / "feedback.png", self.profiles,
                             [{"position": t.position, "trial": t.trial, "history": t.history, "rmse_mm": t.rmse_mm,
                               "coarse_looks": t.coarse_looks} for t in self.trials])
        text = position_markdown(self.report)
        write_json(folder / "report.json", self.report)
        (folder / "report.md").write_text(text)
        return text


def _positions(scene: Scene) -> list[tuple[str, str, Surface]]:
    """(target name, state, surface) of each target; each must sit on exactly one box."""
    out = []
    for spec in scene.target_specs():
        names = spec.surfaces if spec.surfaces is not None else scene.state(spec.state).surfaces
        if len(names) != 1 or scene.surfaces[names[0]].type != "box":
            raise ConfigError(f"targets.{spec.name}.surfaces",
                              f"positioning needs each target on exactly one box, got {names}",
                              "give each target `surfaces: [BOX]` naming a surface of type box")
        out.append((spec.name, spec.state, scene.surfaces[names[0]]))
    return out


def _rmse(points: np.ndarray, pose: np.ndarray, size) -> float:
    if len(points) == 0:
        return float("nan")
    return float(np.sqrt(np.mean(box_surface_distance(points, pose, size) ** 2)) * 1000)


def evaluate_positioning(scene: Scene, *, trials: int = 3, spread_mm: float = 20.0, spread_deg: float = 5.0,
                         seed: int = 0, max_evaluations: int = 200, profile_mm: float = 40.0, profile_steps: int = 8,
                         feedback_stride: int | None = None, coarse_to_fine: bool = True,
                         device="cpu", progress=None, calibration: VirtualCalibration | None = None,
                         max_iter: int | None = None, solver: str = "fista", bounds_8bit=(0, 255),
                         outside: str = "clip", chains: str = "epipolar", cache: bool = False) -> PositioningResult:
    """Solve patterns for the scene's targets, place each box from random starts by feedback, scan it.

    Args:
        scene: a scene whose every target sits on one box (``box_positions`` is the paper's test).
        trials: placements per position.
        spread_mm, spread_deg: how far from the goal a trial may start (each coordinate of the
            centre, and the angle about a random axis).
        seed: seeds the start poses and the captures' noise.
        max_evaluations: camera looks a placement may take.
        profile_mm, profile_steps: the feedback chart's range (+-) and its samples on each side of the goal
            (spaced geometrically from 0.25 mm).
        feedback_stride: score the camera image on every n-th pixel in each direction (None: the
            sparsest of 1-4 that keeps ``FINE_PIXELS`` of the target's pixels, :func:`feedback_stride_for`).
        coarse_to_fine: place each box coarse to fine (:func:`place_by_feedback`): the first half of
            the looks scored on the sparsest stride that keeps ``COARSE_PIXELS``. False: every look on the
            feedback alone.
        calibration: reuse an earlier :func:`calibrate_virtual` of the same scene.
        cache: where no ``calibration`` is given, read the calibration and its transport from the
            cache where the same scene ran before, else keep them there, as ``torchproj run`` does
            (:mod:`torchproj.pipeline.cache`; ``torchproj position`` does unless ``--no-cache``).
        max_iter: iteration limit of the pattern solver (None: as :func:`~torchproj.pipeline.run_virtual`).
        solver, bounds_8bit, outside, chains: the pattern solver, its bounds, how values outside them are
            shown and eo's chains, as :func:`~torchproj.pipeline.run_virtual`
            (the paper's own test used ``eo`` with ``(0, 255)``, ``EO_0^255``).
    """
    check_scene(scene)
    trials = check_count(trials, "trials")
    # Each position and trial draws its captures' and scans' noise from seeds derived from this one
    # (1000 (seed + 1) (k + 1) and on), which must stay within the rig's 2**63.
    seed = check_seed(seed, limit=2 ** 32)
    check_solve_options(solver, bounds_8bit, len(scene.projectors), outside, chains)  # before calibrating
    spread_mm, spread_deg = check_number(spread_mm, "spread_mm (mm)"), check_number(spread_deg, "spread_deg (degrees)")
    max_evaluations = check_count(max_evaluations, "max_evaluations", 10)
    profile_mm = check_number(profile_mm, "profile_mm (the feedback chart's range, mm)", strict=True)
    profile_steps = check_count(profile_steps, "profile_steps (the feedback chart's samples each side)")
    iteration_limit(max_iter)  # checked before calibrating, not at the solve
    check(feedback_stride is None or (is_whole(feedback_stride) and feedback_stride >= 1),
          f"feedback_stride must be a whole number of pixels, at least 1 (or None: chosen per target), got "
          f"{feedback_stride!r}")
    positions = _positions(scene)
    # A trial starts where the person first puts the object: near enough that the camera still sees it
    # lit. Past a quarter of its distance from the projectors (or a quarter turn) it is a search of the
    # room, which a 1e9 mm spread ran for minutes before failing on the projector's light.
    prj_mid = np.mean([p.centre for p in scene.projectors], axis=0)
    nearest_mm = min(float(np.linalg.norm(s.world_from_local[:3, 3] - prj_mid)) * 1000 for _, _, s in positions)
    check(spread_mm <= nearest_mm / 4, f"spread_mm {spread_mm:g}: a trial would start up to that far from the goal, past "
                                       f"a quarter of the object's {nearest_mm:.0f} mm from the projectors; give at most "
                                       f"{nearest_mm / 4:.0f}")
    check(spread_deg <= 45, f"spread_deg {spread_deg:g}: a trial would start turned up to that far; give at most 45")
    t_start = time.perf_counter()
    given = calibration is not None  # then no time of this call went into calibrating
    if calibration is None and not cache:
        calibration = calibrate_virtual(scene, device, progress)
    run = run_virtual(scene, calibration=calibration, device=device, progress=progress, max_iter=max_iter,
                      solver=solver, bounds_8bit=bounds_8bit, outside=outside, chains=chains, cache=cache)
    cal = run.calibration
    # A scene's show: section changes the world after calibration: the person looks at the patterns,
    # and the scanner scans, in the world as it is now (the run scored the patterns there too).
    world = shown_world(cal, scene)
    shown_as = world.rig.scene if world is not cal else None  # shown_world's rig casts shown_scene(scene)
    t_placing = time.perf_counter()
    scale = run.report["scale"]
    shown = {j: (p.float() / 255)[None].to(device) for j, p in enumerate(run.patterns)}
    rng = np.random.default_rng(seed)
    rows, trial_rows, placed_trials, profiles = [], [], [], {}
    jobs = [(k, t) for k in range(len(positions)) for t in range(trials)]
    bar = progress_bar(desc="placing and scanning", enabled=progress, total=len(jobs) + len(positions))
    for k, (name, state, surface) in enumerate(positions):
        detail = run.targets[k]
        goal = surface.world_from_local
        distance_mm = float(np.linalg.norm(goal[:3, 3] - prj_mid) * 1000)
        stride = feedback_stride or feedback_stride_for(detail.covered)
        rough = feedback_stride_for(detail.covered, COARSE_PIXELS)
        feedback = _Feedback(world.rig, surface, shown, detail.covered, detail.values, world.black[state], scale,
                             seed=1000 * (seed + 1) * (k + 1), stride=stride)
        # The coarse looks draw their noise from a stream of their own.
        coarse = _Feedback(world.rig, surface, shown, detail.covered, detail.values, world.black[state], scale,
                           seed=1000 * (seed + 1) * (k + 1) + 500_000, stride=rough) if coarse_to_fine else None
        # Finer near the goal, where the image comes together.
        side = np.geomspace(0.25, profile_mm, profile_steps)
        offsets = np.r_[-side[::-1], 0.0, side] / 1000
        profiles[name] = feedback_profile(feedback, goal, offsets)
        floor = scan_surface(scene, surface, goal, seed=seed + 7919 * (k + 1), device=device, world=shown_as)
        bar.update()
        row = {"name": name, "state": state, "surface": surface.name, "box_size_m": list(surface.size),
               "goal_pose": np.round(goal, 6).tolist(), "projector_distance_mm": round(distance_mm, 1),
               "psnr_db_at_goal": round(run.report["targets"][k]["psnr_db"], 3),
               "feedback_at_goal_db": round(feedback(goal), 3), "feedback_stride": stride,
               "coarse_stride": rough if coarse_to_fine else None,
               "scanner_rmse_mm": round(_rmse(floor["points"], goal, surface.size), 3)}
        if name in PAPER_RMSE_PERCENT:
            row["paper_rmse_percent"] = PAPER_RMSE_PERCENT[name]["percent"]
        errors, new_rows = _place_trials(scene, feedback, coarse, name, surface, distance_mm, trials, spread_mm,
                                         spread_deg, max_evaluations, rng, seed + 104729 * (k + 1), device, bar,
                                         shown_as)
        placed_trials += errors
        trial_rows += new_rows
        row["rmse_mm_mean"] = round(float(np.mean([e.rmse_mm for e in errors])), 3)
        row["rmse_percent_mean"] = round(float(np.mean([e.rmse_percent for e in errors])), 4)
        rows.append(row)
    bar.close()
    scanning = sum(r["scan_seconds"] for r in trial_rows)
    report = {
        "scene": scene.name, "seed": seed, "trials_per_position": trials,
        "start_spread": {"position_mm": spread_mm, "rotation_deg": spread_deg},
        "max_evaluations": max_evaluations, "feedback_stride": feedback_stride or "per target",
        "coarse_to_fine": {"coarse_looks": coarse_looks(max_evaluations), "coarse_pixels": COARSE_PIXELS}
        if coarse_to_fine else None,
        "solver": solver, "bounds_8bit": list(bounds_8bit), "outside": outside,
        "method": (f"patterns solved by {solver} (bounds {bounds_8bit[0]:g}..{bounds_8bit[1]:g}) on the Gray-code "
                   "calibration; placement by Nelder-Mead on the "
                   "6-DoF displacement from the start, maximising the PSNR of the camera image against the target "
                   "image over the target's camera pixels (no access to the true pose)"
                   + (f", coarse to fine (the first {coarse_looks(max_evaluations)} looks after the first scored on "
                      f"fewer pixels)" if coarse_to_fine else "") + "; scan by Gray code from "
                   "each projector, triangulated with the rig's geometry; rmse is the RMS distance of the scanned "
                   "points from the box surface at the goal pose, percent of the distance from the goal box centre "
                   "to the midpoint of the projector centres"),
        "paper_rmse_percent": {k: v["percent"] for k, v in PAPER_RMSE_PERCENT.items()},
        "positions": rows,
        **({"show": scene.show.as_dict()} if scene.show is not None else {}),
        "rmse_percent_mean": {r["name"]: r["rmse_percent_mean"] for r in rows},
        "trials": trial_rows,
        "feedback_profiles": profiles,
        "calibration_cache": run.report["calibration_cache"], "transport_cache": run.report["transport_cache"],
        "cast_cache": run.report["cast_cache"],
        # The run's own total holds the calibration where it read or simulated it itself: counted once here.
        "timings_s": {"calibrate": 0.0 if given else round(cal.seconds, 3),
                      "patterns": round(run.report["timings_s"]["total"] - run.report["timings_s"]["calibrate"], 3),
                      # looking (every trial's placement, the feedback profiles) and the trials' Gray-code scans
                      "place": round(time.perf_counter() - t_placing - scanning, 3),
                      "scan": round(scanning, 3),
                      "total": round(time.perf_counter() - t_start, 3)},
    }
    return PositioningResult(report=report, trials=placed_trials, patterns=run.patterns, profiles=profiles)


def _place_trials(scene, feedback, coarse, name, surface, distance_mm, trials, spread_mm, spread_deg, max_evaluations,
                  rng, scan_seed, device, bar, world=None) -> tuple[list[PlacementTrial], list[dict]]:
    """``trials`` placements of one box from random starts near its goal, each scanned and scored."""
    goal = surface.world_from_local
    placed_trials, rows = [], []
    for t in range(trials):
        t0 = time.perf_counter()
        start = random_pose_near(goal, spread_mm / 1000, spread_deg, rng)
        counted = coarse.count if coarse is not None else 0
        placed, history = place_by_feedback(feedback, start, step_m=max(spread_mm, 1.0) / 1000,
                                            step_deg=max(spread_deg, 1.0), max_evaluations=max_evaluations,
                                            coarse=coarse)
        t_scan = time.perf_counter()
        scan = scan_surface(scene, surface, placed, seed=scan_seed + t, device=device, world=world)
        t_scan = time.perf_counter() - t_scan
        rmse = _rmse(scan["points"], goal, surface.size)
        trial = PlacementTrial(position=name, trial=t, start=start, placed=placed, history=history, scan=scan,
                               rmse_mm=rmse, rmse_percent=100 * rmse / distance_mm, seconds=time.perf_counter() - t0,
                               coarse_looks=coarse.count - counted if coarse is not None else 0)
        placed_trials.append(trial)
        rows.append({
            "position": name, "trial": t, "rmse_mm": round(rmse, 3), "rmse_percent": round(trial.rmse_percent, 4),
            "pose_error": pose_error(placed, goal), "start_pose_error": pose_error(start, goal),
            "scan_to_placed_box_rmse_mm": round(_rmse(scan["points"], placed, surface.size), 3),
            "scan_points": int(len(scan["points"])), "evaluations": len(history),
            "coarse_looks": trial.coarse_looks,
            "feedback_start_db": round(history[0], 3), "feedback_final_db": round(max(trial.fine_history()), 3),
            "seconds": round(trial.seconds, 2), "scan_seconds": round(t_scan, 2)})
        bar.update()
    return placed_trials, rows


def _scan_points(folder: Path, mask: np.ndarray | None) -> np.ndarray:
    """The triangulated points of a ``torchproj decode --calibration`` folder, inside ``mask``."""
    path = folder / "correspondence.npz"
    if not path.is_file():
        raise InputError(f"{path}: not found; give the --out folder of torchproj decode")
    try:
        with np.load(path) as data:  # no pickles: a file that holds objects is not the decoder's
            points = data["points"] if "points" in data.files else None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise CaptureError(f"{path}: cannot be read as the decoder's .npz ({type(exc).__name__}); run torchproj "
                           "decode again") from None
    if points is None:
        raise InputError(f"{path}: holds no points; run torchproj decode with --calibration FILE.xml")
    if points.ndim != 3 or points.shape[-1] != 3 or not np.issubdtype(points.dtype, np.floating):
        raise CaptureError(f"{path}: points must be camera H x W x 3 floats, got {points.dtype} {points.shape}; run "
                           "torchproj decode --calibration again")
    keep = np.isfinite(points).all(-1)
    if mask is not None:
        if mask.shape != keep.shape:
            raise InputError(f"--mask is {mask.shape[1]}x{mask.shape[0]} but the camera of {folder} is "
                                 f"{keep.shape[1]}x{keep.shape[0]}; paint the mask over a capture of that camera")
        keep &= mask
    return points[keep].astype(np.float64)


def placement_error(placed, reference, distance: float, mask=None) -> dict:
    """Score a real placement: a scan of the placed object against a scan of it at its goal pose.

    Args:
        placed, reference: folders written by ``torchproj decode --calibration`` (``points`` in
            ``correspondence.npz``).
        distance: object-projector distance, in the calibration's units, for the percentage.
        mask: optional image file of the camera's size, white on the object: only those pixels count.

    Returns:
        the ``report.json`` of ``torchproj placement-error``: RMS, median and 95th percentile of the
        distance from each placed point to the nearest reference point, and the RMS as a
        percentage of ``distance``.
    """
    from ..core.imageio import read_image

    if not (is_number(distance) and distance > 0 and math.isfinite(distance)):
        raise InputError(f"--distance must be the object-projector distance (> 0), got {distance!r}")
    check_path(placed, "placed", "a torchproj decode folder")
    check_path(reference, "reference", "a torchproj decode folder")
    keep = None if mask is None else to_numpy(read_image(mask).mean(0)) > 0.5
    placed_points = _scan_points(Path(placed), keep)
    reference_points = _scan_points(Path(reference), keep)
    if len(placed_points) == 0 or len(reference_points) == 0:
        raise InputError("no scanned points" + (" inside --mask" if mask is not None else "") + " in "
                         + str(placed if len(placed_points) == 0 else reference))
    dist = scan_distance(placed_points, reference_points)
    rmse = float(np.sqrt(np.mean(dist**2)))
    return {"placed": str(placed), "reference": str(reference), "mask": None if mask is None else str(mask),
            "points": int(len(placed_points)), "reference_points": int(len(reference_points)),
            "rmse": round(rmse, 4), "median": round(float(np.median(dist)), 4),
            "p95": round(float(np.percentile(dist, 95)), 4), "distance": distance,
            "rmse_percent": round(100 * rmse / distance, 4), "units": "the calibration's (usually mm)",
            "method": "distance from each point of the placed scan to the nearest point of the reference scan "
                      "(the object scanned at its goal pose); percent of --distance"}


def position_markdown(report: dict) -> str:
    """``report.md`` of a positioning test."""
    lines = [f"# torchproj position: {report['scene']}", "",
             "Fig. 1 (`feedback.png`): the feedback around the goal pose along each axis, and each placement's "
             "best feedback against the camera looks it took.", "",
             f"{report['trials_per_position']} placements per position from starts within "
             f"{report['start_spread']['position_mm']:g} mm and {report['start_spread']['rotation_deg']:g} degrees "
             f"of the goal, at most {report['max_evaluations']} camera looks each.", "",
             f"Method: {report['method']}.", "",
             *([f"Shown in a world changed after calibration: {describe_show(report['show'])}. The feedback a placement follows and "
                "the scans are that world's; the scanner triangulates with the calibrated geometry.", ""]
               if "show" in report else []),
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
