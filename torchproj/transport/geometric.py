"""Geometric weighting (the paper's model): fall-off and angle from triangulated points and normals.

The paper weights projector j's light at a target pixel by its geometry alone. Its equation writes
``d^2 / (L.N)``; the physics (docs/scenes.md) is the inverse, ``max(0, N.L) / d^2``, which is what a
camera measures, so that is used here. Albedo, vignetting and projector brightness are not in this
model (the radiometric weighting measures them); the overall scale is absorbed by the target scale.

Points come from camera-projector triangulation of the decoded correspondences with the rig's
device calibration (intrinsics and poses), normals from the triangulated point map.
"""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from kornia.geometry.camera import unproject_points

from ..core.checks import check, check_array, check_shape, check_window
from ..core.conventions import pixel_grid
from ..scene.config import Camera, Projector

__all__ = ["triangulate_rays", "point_map", "normal_map", "geometric_weights"]


def _rays(pixels: torch.Tensor, K, world_from_dev) -> tuple[torch.Tensor, torch.Tensor]:
    """World origin and unit directions of pinhole rays through pixels :math:`(N, 2)`."""
    K = torch.as_tensor(K, dtype=torch.float64)
    pose = torch.as_tensor(world_from_dev, dtype=torch.float64)
    d = unproject_points(pixels.double(), torch.ones_like(pixels[:, :1], dtype=torch.float64), K, normalize=True)
    return pose[:3, 3].expand(pixels.shape[0], 3), d @ pose[:3, :3].T


def triangulate_rays(o1, d1, o2, d2) -> torch.Tensor:
    """Midpoint of the shortest segment between rays ``o1 + s d1`` and ``o2 + t d2`` (N, 3 each)."""
    sizes = check_shape(o1, "o1", ["N", 3])
    for name, value in (("d1", d1), ("o2", o2), ("d2", d2)):
        check_shape(value, name, [sizes["N"], 3])
    w = o1 - o2
    a, b, c = (d1 * d1).sum(-1), (d1 * d2).sum(-1), (d2 * d2).sum(-1)
    d, e = (d1 * w).sum(-1), (d2 * w).sum(-1)
    den = (a * c - b * b).clamp_min(1e-18)
    s = (b * e - c * d) / den
    t = (a * e - b * d) / den
    return 0.5 * ((o1 + s[:, None] * d1) + (o2 + t[:, None] * d2))


def point_map(prj_xy: Sequence[torch.Tensor], camera, projectors) -> torch.Tensor:
    """World point seen at each camera pixel, triangulated with the first projector that decoded it.

    Args:
        prj_xy: per projector, :math:`(H, W, 2)` decoded coordinates (NaN where unknown).
        camera: has ``K`` and ``world_from_cam`` (e.g. :class:`torchproj.scene.Camera`).
        projectors: each has ``K`` and ``world_from_prj``.

    Returns:
        :math:`(H, W, 3)` float64 points, NaN where no projector decoded the pixel.
    """
    check(isinstance(camera, Camera), f"camera must be a scene's Camera (scene.camera), got {type(camera).__name__}")
    check(isinstance(projectors, (list, tuple)) and len(projectors) > 0 and all(isinstance(p, Projector) for p in projectors),
          f"projectors must be a scene's projectors (scene.projectors), got {type(projectors).__name__}")
    check(isinstance(prj_xy, (list, tuple)) and len(prj_xy) == len(projectors),
          f"prj_xy must be one map per projector ({len(projectors)}), got {type(prj_xy).__name__}")
    sizes = check_shape(prj_xy[0], "prj_xy[0]", ["H", "W", 2])
    for j, m in enumerate(prj_xy[1:], 1):
        check_shape(m, f"prj_xy[{j}]", [sizes["H"], sizes["W"], 2])
    h, w = prj_xy[0].shape[:2]
    points = torch.full((h * w, 3), float("nan"), dtype=torch.float64)
    done = torch.zeros(h * w, dtype=torch.bool)
    cam_pix = pixel_grid(h, w, dtype=torch.float64).reshape(-1, 2)
    for m, proj in zip(prj_xy, projectors):
        check_shape(m, "prj_xy", [h, w, 2])
        sel = torch.isfinite(m.reshape(-1, 2)).all(-1) & ~done
        if not bool(sel.any()):
            continue
        o1, d1 = _rays(cam_pix[sel], camera.K, camera.world_from_cam)
        o2, d2 = _rays(m.reshape(-1, 2)[sel], proj.K, proj.world_from_prj)
        points[sel] = triangulate_rays(o1, d1, o2, d2)
        done |= sel
    return points.reshape(h, w, 3)


def normal_map(points: torch.Tensor, camera_centre, window: int = 5) -> torch.Tensor:
    """Unit normals of a point map, turned towards the camera.

    Central differences of the box-filtered point map (``window`` pixels) along x and y; their
    cross product is the normal. NaN where the neighbourhood is incomplete (edges, holes).
    """
    check_shape(points, "points", ["H", "W", 3])
    check_window(window)
    camera_centre = check_array(camera_centre, "camera_centre", (3,), finite=True)
    points = points.double()  # the filter's weights are float64: a float32 map met them as a type error
    valid = torch.isfinite(points).all(-1)
    p = torch.nan_to_num(points).permute(2, 0, 1)[None]  # 1x3xHxW
    m = valid.double()[None, None]
    k = torch.ones(1, 1, window, window, dtype=torch.float64) / window**2
    full = F.conv2d(m, k, padding=window // 2)[0, 0] > 1 - 1e-9
    smooth = F.conv2d(p.reshape(3, 1, *p.shape[2:]), k, padding=window // 2).reshape(3, *p.shape[2:])
    dx = torch.zeros_like(smooth)
    dy = torch.zeros_like(smooth)
    dx[:, :, 1:-1] = smooth[:, :, 2:] - smooth[:, :, :-2]
    dy[:, 1:-1, :] = smooth[:, 2:, :] - smooth[:, :-2, :]
    n = torch.linalg.cross(dx.permute(1, 2, 0), dy.permute(1, 2, 0))
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    to_cam = torch.as_tensor(camera_centre, dtype=torch.float64) - points
    n = torch.where(((n * to_cam).sum(-1) < 0)[..., None], -n, n)
    ok = full & valid
    ok[0, :] = ok[-1, :] = False
    ok[:, 0] = ok[:, -1] = False
    return torch.where(ok[..., None], n, torch.full_like(n, float("nan")))


def geometric_weights(prj_xy: Sequence[torch.Tensor], camera, projectors, window: int = 5) -> list[torch.Tensor]:
    """Per projector, :math:`(H, W)` weight ``max(0, n.l) / d^2`` (0 where unknown).

    Args:
        prj_xy: per projector, decoded coordinates :math:`(H, W, 2)`.
        camera, projectors: the rig's device calibration (``K`` and poses).
        window: smoothing window of the normal estimate.
    """
    points = point_map(prj_xy, camera, projectors)
    normals = normal_map(points, torch.as_tensor(camera.world_from_cam)[:3, 3], window)
    weights = []
    for m, proj in zip(prj_xy, projectors):
        to_prj = torch.as_tensor(proj.world_from_prj, dtype=torch.float64)[:3, 3] - points
        dist = to_prj.norm(dim=-1)
        cos = (normals * to_prj).sum(-1) / dist
        w = torch.nan_to_num(cos.clamp_min(0) / dist**2, nan=0.0)
        w[~torch.isfinite(m).all(-1)] = 0.0
        weights.append(w.float())
    return weights
