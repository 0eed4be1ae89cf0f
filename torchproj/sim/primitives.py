"""Exact ray casting of surfaces.

Analytic primitives are intersected in torch in their local frame (:class:`torchproj.scene.Surface`
documents each local frame); triangle meshes go through Embree (``embreex`` via ``trimesh``). Only a
scene that has a mesh touches the mesh machinery.

Every caster answers the same question for a batch of rays: the nearest hit with ``t > t_min`` along
``origin + t * direction`` (directions unit length, so t is a distance in metres), and the surface
normal there (world frame, not oriented: callers turn it towards the viewer).
"""

from __future__ import annotations

import numpy as np
import torch

from ..core.checks import check, check_device
from ..scene.config import Surface

__all__ = ["Caster", "make_caster"]

_TINY = 1e-12


def _nearest_positive(candidates: torch.Tensor, t_min: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Smallest candidate > t_min along the last axis (inf where none), and its index."""
    c = torch.where(candidates > t_min, candidates, torch.full_like(candidates, float("inf")))
    return c.min(dim=-1)


class Caster:
    """Ray caster of one surface. Subclasses implement :meth:`_local_hit` in the local frame."""

    def __init__(self, surface: Surface, device, dtype=torch.float32):
        self.surface = surface
        pose = torch.as_tensor(surface.world_from_local, dtype=dtype, device=device)
        self.rotation = pose[:3, :3]  # world_from_local rotation, 3x3
        self.position = pose[:3, 3]
        self.transmittance = surface.transmittance

    def hit(self, origins: torch.Tensor, directions: torch.Tensor, t_min: float = 1e-5):
        """Nearest hit of rays.

        Args:
            origins: :math:`(N, 3)` world points, or :math:`(1, 3)` when every ray starts at one point.
            directions: :math:`(N, 3)` unit world directions.
            t_min: ignore hits closer than this (metres), to step off the surface a ray starts on.

        Returns:
            ``t`` :math:`(N,)` distance (inf where missed) and ``normal`` :math:`(N, 3)` world normals.
        """
        o = (origins - self.position) @ self.rotation
        d = directions @ self.rotation
        t, n = self._local_hit(o, d, t_min)
        return t, (n @ self.rotation.T).expand(t.shape[0], 3)

    def _local_hit(self, o, d, t_min):
        raise NotImplementedError


class _Rectangle(Caster):
    def _local_hit(self, o, d, t_min):
        dz = torch.where(d[:, 2].abs() < _TINY, torch.full_like(d[:, 2], _TINY), d[:, 2])
        t = -o[:, 2] / dz
        p = o + t[:, None] * d
        ok = t > t_min
        if self.surface.type == "rectangle":
            w, h = self.surface.size
            ok &= (p[:, 0].abs() <= w / 2) & (p[:, 1].abs() <= h / 2)
        t = torch.where(ok, t, torch.full_like(t, float("inf")))
        return t, torch.tensor([[0.0, 0.0, 1.0]], dtype=o.dtype, device=o.device)


class _Ellipsoid(Caster):
    def __init__(self, surface, device, dtype=torch.float32):
        super().__init__(surface, device, dtype)
        self.radii = torch.tensor(surface.radii, dtype=dtype, device=device)

    def _local_hit(self, o, d, t_min):
        # Scale space so the ellipsoid is the unit sphere; t keeps its meaning along the ray.
        os_, ds = o / self.radii, d / self.radii
        a = (ds * ds).sum(-1)
        b = 2 * (os_ * ds).sum(-1)
        c = (os_ * os_).sum(-1) - 1
        disc = b * b - 4 * a * c
        root = torch.sqrt(disc.clamp_min(0))
        cand = torch.stack([(-b - root) / (2 * a), (-b + root) / (2 * a)], -1)
        cand = torch.where((disc >= 0)[:, None], cand, torch.full_like(cand, float("inf")))
        t, _ = _nearest_positive(cand, t_min)
        p = o + torch.nan_to_num(t, posinf=0.0)[:, None] * d
        n = torch.nn.functional.normalize(p / self.radii**2, dim=-1)
        return t, n


class _Box(Caster):
    def __init__(self, surface, device, dtype=torch.float32):
        super().__init__(surface, device, dtype)
        self.half = torch.tensor(surface.size, dtype=dtype, device=device) / 2

    def _local_hit(self, o, d, t_min):
        # Slab method: the ray is inside the box between the last entry and the first exit.
        d = torch.where(d.abs() < _TINY, torch.full_like(d, _TINY), d)
        t1 = (-self.half - o) / d
        t2 = (self.half - o) / d
        t_enter, axis_enter = torch.minimum(t1, t2).max(-1)
        t_exit, axis_exit = torch.maximum(t1, t2).min(-1)
        hit = t_exit >= torch.clamp(t_enter, min=t_min)
        from_outside = t_enter > t_min
        t = torch.where(from_outside, t_enter, t_exit)
        t = torch.where(hit, t, torch.full_like(t, float("inf")))
        axis = torch.where(from_outside, axis_enter, axis_exit)
        n = torch.nn.functional.one_hot(axis, 3).to(o.dtype)
        return t, n


class _Cylinder(Caster):
    def _local_hit(self, o, d, t_min):
        r, half = self.surface.radius, self.surface.height / 2
        # Side: x^2 + z^2 = r^2 with |y| <= h/2; caps: y = +-h/2 with x^2 + z^2 <= r^2.
        a = (d[:, 0] ** 2 + d[:, 2] ** 2).clamp_min(_TINY)
        b = 2 * (o[:, 0] * d[:, 0] + o[:, 2] * d[:, 2])
        c = o[:, 0] ** 2 + o[:, 2] ** 2 - r * r
        disc = b * b - 4 * a * c
        root = torch.sqrt(disc.clamp_min(0))
        side = torch.stack([(-b - root) / (2 * a), (-b + root) / (2 * a)], -1)
        y_side = o[:, 1:2] + side * d[:, 1:2]
        side = torch.where((disc[:, None] >= 0) & (y_side.abs() <= half), side, torch.full_like(side, float("inf")))
        dy = torch.where(d[:, 1].abs() < _TINY, torch.full_like(d[:, 1], _TINY), d[:, 1])
        caps = torch.stack([(-half - o[:, 1]) / dy, (half - o[:, 1]) / dy], -1)
        cx = o[:, 0:1] + caps * d[:, 0:1]
        cz = o[:, 2:3] + caps * d[:, 2:3]
        caps = torch.where(cx * cx + cz * cz <= r * r, caps, torch.full_like(caps, float("inf")))
        t, which = _nearest_positive(torch.cat([side, caps], -1), t_min)
        p = o + torch.nan_to_num(t, posinf=0.0)[:, None] * d
        n_side = torch.stack([p[:, 0], torch.zeros_like(p[:, 0]), p[:, 2]], -1) / r
        n_cap = torch.zeros_like(o)
        n_cap[:, 1] = 1.0
        n = torch.where((which < 2)[:, None], n_side, n_cap)
        return t, n


class _Mesh(Caster):
    """Triangle mesh through Embree. Embree works in float32 on the CPU; results come back as torch."""

    def __init__(self, surface, device, dtype=torch.float32):
        super().__init__(surface, device, dtype)
        import trimesh
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        mesh = trimesh.load(surface.mesh_file, force="mesh")
        mesh.apply_scale(surface.scale)
        mesh.apply_transform(surface.world_from_local)
        self.mesh = mesh
        self.intersector = RayMeshIntersector(mesh)
        self.face_normals = torch.tensor(np.array(mesh.face_normals), dtype=dtype)

    def hit(self, origins, directions, t_min=1e-5):
        device, dtype = origins.device, origins.dtype
        # The rig casts a camera's rays from one origin, (1, 3) against (N, 3) directions, as torch
        # broadcasts for the analytic casters; Embree takes one origin per ray.
        origins, directions = torch.broadcast_tensors(origins, directions)
        # Step the origins forward by t_min so that Embree never reports the surface a ray starts on.
        o = (origins + t_min * directions).detach().cpu().numpy().astype(np.float64)
        d = directions.detach().cpu().numpy().astype(np.float64)
        tri, ray, loc = self.intersector.intersects_id(o, d, multiple_hits=False, return_locations=True)
        t = torch.full((origins.shape[0],), float("inf"), dtype=dtype)
        n = torch.zeros((origins.shape[0], 3), dtype=dtype)
        if len(ray):
            ray_t = torch.as_tensor(ray, dtype=torch.int64)
            dist = np.linalg.norm(loc - o[ray], axis=1) + t_min
            t[ray_t] = torch.as_tensor(dist, dtype=dtype)
            n[ray_t] = self.face_normals[torch.as_tensor(tri, dtype=torch.int64)]
        return t.to(device), n.to(device)


_CASTERS = {"rectangle": _Rectangle, "plane": _Rectangle, "sphere": _Ellipsoid, "box": _Box,
            "cylinder": _Cylinder, "mesh": _Mesh}


def make_caster(surface: Surface, device="cpu", dtype=torch.float32) -> Caster:
    """The ray caster for a surface (analytic in torch, or Embree for meshes)."""
    check(isinstance(surface, Surface), f"surface must be a scene's Surface (scene.surfaces), got {type(surface).__name__}")
    return _CASTERS[surface.type](surface, check_device(device), dtype)
