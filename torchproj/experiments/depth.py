"""Depth selectivity: move a surface through depth under fixed patterns and score every target there.

Depth-dependent patterns should make each target's image appear sharply at its own depth and fade
elsewhere; for positioning, how fast it fades is the precision a person can reach by eye.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from ..core.checks import check, check_count, check_device, check_number
from ..core.progress import progress_bar
from ..scene.config import Scene, State, check_scene
from ..scene.show import shown_scene
from ..sim.rig import VirtualRig
from ..pipeline.scoring import TargetScore, as_light, score_image

__all__ = ["DepthSweep", "depth_sweep"]


@dataclass
class DepthSweep:
    """Scores of each target's image on a surface moved through depth.

    Attributes:
        depths: :math:`(D,)` world z of the surface's centre (metres).
        psnr_db: :math:`(D, K)` PSNR of the capture against target k, over target k's camera pixels
            that the moved surface covers (NaN where it covers too few).
        ssim: :math:`(D, K)` likewise.
        pixels: :math:`(D, K)` pixels scored.
        names: the K target names.
    """

    depths: np.ndarray
    psnr_db: np.ndarray
    ssim: np.ndarray
    pixels: np.ndarray
    names: list[str]

    def as_dict(self) -> dict:
        """JSON-ready: NaN (too few pixels scored) becomes None."""
        def table(a, digits):
            return [[None if np.isnan(v) else round(float(v), digits) for v in row] for row in a]

        return {"depths_m": self.depths.round(4).tolist(), "names": self.names,
                "psnr_db": table(self.psnr_db, 3), "ssim": table(self.ssim, 4), "pixels": self.pixels.tolist()}


def depth_sweep(scene: Scene, surface: str, depths, patterns: list[torch.Tensor], targets: list[TargetScore], scale: float,
                *, device="cpu", min_pixels: int = 500, progress=None) -> DepthSweep:
    """Capture fixed patterns on one surface placed at each depth, alone, and score every target.

    Args:
        scene: the scene the patterns were made for; where it has a ``show:`` section, they are shown in
            the world it describes (:func:`~torchproj.scene.shown_scene`), as ``run`` scores them.
        surface: name of the surface to move (along the world z axis, orientation kept).
        depths: world z positions of its centre.
        patterns: per projector, :math:`(C, H_j, W_j)` uint8 patterns (as from ``run_virtual``) or float
            light in [0, 1].
        targets: per target, its image on the camera (``values`` (C, H, W), ``covered`` (H, W)):
            :class:`~torchproj.pipeline.TargetScore` (``RunResult.targets``).
        scale: camera value of target value 1 (the operator's ``scale``).
        min_pixels: fewer scored pixels than this give NaN.
    """
    check_scene(scene)
    check(isinstance(surface, str) and surface in scene.surfaces,
          f"unknown surface {surface!r}; known: {sorted(scene.surfaces)}")
    device = check_device(device)
    camera = (scene.camera.height, scene.camera.width)
    check(isinstance(targets, (list, tuple)) and all(
              isinstance(t, TargetScore) and tuple(t.covered.shape) == camera and tuple(t.values.shape[-2:]) == camera
              for t in targets),
          f"targets must be a list of TargetScores on this scene's {camera[1]}x{camera[0]} camera (RunResult.targets), "
          f"got {type(targets).__name__}")
    given = depths
    try:
        depths = np.asarray(depths.cpu() if isinstance(depths, torch.Tensor) else depths, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        depths = None
    check(depths is not None and len(depths) >= 1 and np.isfinite(depths).all(),
          f"depths must be a non-empty list of finite numbers (world z in metres), got {given!r}")
    shown = as_light(patterns, len(scene.projectors), device)
    check_number(scale, "scale", strict=True)
    min_pixels = check_count(min_pixels, "min_pixels")
    # The patterns are shown in the world as it is when they are shown: a show: section's changes
    # since calibration apply, as they do to run's scores (torchproj.pipeline.shown_world).
    world = scene if scene.show is None else shown_scene(scene)
    base = world.surfaces[surface]
    moved, states = dict(world.surfaces), []
    for i, z in enumerate(depths):
        pose = base.world_from_local.copy()
        pose[2, 3] = z
        moved[f"{surface}@{i}"] = dataclasses.replace(base, name=f"{surface}@{i}", world_from_local=pose)
        states.append(State(name=f"z{i}", surfaces=[f"{surface}@{i}"]))
    swept = dataclasses.replace(world, surfaces=moved, states=states, targets=[], show=None)
    rig = VirtualRig(swept, device=device)
    K = len(targets)
    out = {key: np.full((len(depths), K), np.nan) for key in ("psnr", "ssim")}
    pixels = np.zeros((len(depths), K), dtype=np.int64)
    for i in progress_bar(range(len(depths)), "depth sweep", progress):
        state = states[i].name
        black = rig.capture(state, {})[0].cpu()
        estimate = ((rig.capture(state, shown)[0].cpu() - black) / scale).clamp(0, 1)
        seen = rig.surface_mask(state).cpu()
        for k, t in enumerate(targets):
            region = t.covered & seen
            pixels[i, k] = int(region.sum())
            if pixels[i, k] >= min_pixels:
                scores = score_image(estimate, t.values, region)
                out["psnr"][i, k], out["ssim"][i, k] = scores["psnr_db"], scores["ssim"]
        rig.release(state)  # one state at a time: each cast holds a full transport matrix
    return DepthSweep(depths=depths, psnr_db=out["psnr"], ssim=out["ssim"], pixels=pixels,
                      names=[t.name for t in targets])
