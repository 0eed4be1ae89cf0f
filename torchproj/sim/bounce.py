"""One bounce of projector light between surfaces: the light a direct-light model never holds.

Physics (the virtual rig's contract, ``interreflection: true`` in a scene). Projector j's cell c sends
intensity ``L_c`` (W/sr, the direct model's ``E = L cos / d^2``) into its solid angle
``Omega_c = cos^3(alpha) / (f_x f_y)`` (alpha: the ray's angle to the axis), so a block of cells whose
rays land at surface point Y carries flux ``Phi = Omega sum_block L_c``. Y reflects it diffusely with
its albedo rho_Y, as a small Lambertian patch of intensity ``rho_Y Phi cos(theta_out) / pi``. A surface
point X then receives

    ``E_X = sum_sources rho_Y Phi max(0, n_Y . w) max(0, -n_X . w) / (pi (r^2 + A / pi)) V(X, Y)``

with w the unit direction from Y to X, r the distance, V whether the segment is clear of every surface,
and A the patch's area (a disc's exact on-axis irradiance, ``A / (r^2 + A / pi)``, instead of the point
source's ``A / r^2``, which diverges where two surfaces meet). The camera sees ``rho_X E_X / pi`` more.
Convex surfaces do not light themselves (every point of one lies behind another's tangent plane).

Sampling, our choice (the paper has one bounce nowhere): a source per block of about 1/32 of each
projector's width (``SOURCES`` blocks across, as many down as the cells are square), where the block's
centre ray lands; receivers every k-th camera pixel's centre (about ``RECEIVERS`` of them), their
irradiance interpolated between them (bilinear over the receivers on the pixel's own surface, so that a
silhouette does not darken its neighbours nor a corner's faces blend). The light bounced is then a matrix product per capture: receivers x sources,
times the block sums of each projector's light.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..core.sparse import csr_from_coo, spmm
from ..scene.config import Projector

__all__ = ["Bounce", "RECEIVERS", "SOURCES", "cast_bounce"]

SOURCES = 32  # source blocks across each projector's image
RECEIVERS = 12_000  # about this many camera pixels receive; the rest interpolate
_PAIRS = 1 << 21  # receiver-source pairs per visibility chunk: bounds memory


@dataclass
class Bounce:
    """One state's bounce: receivers x sources geometry, and how to make the sources' light.

    Attributes:
        transfer: :math:`(R, S)` irradiance at each receiver per unit of each source's light
            (``Omega`` and the geometry of the module docstring, without albedos).
        source_albedo: :math:`(A, S)` albedo of the surface each source landed on (0: missed).
        blocks: per projector, its block size in cells (sources are numbered projector by projector,
            blocks row-major).
        grid: ``(h, w, k)``: receivers are the pixel centres ``(k i, k j)`` of an h x w grid.
        interpolation: CSR :math:`(H W, h w)` from receivers to pixels (:func:`_interpolation`).
        receiver_albedo: :math:`(A, H, W)` albedo over pi of the surface each camera pixel centre sees.
    """

    transfer: torch.Tensor
    source_albedo: torch.Tensor
    blocks: list[int]
    grid: tuple[int, int, int]
    interpolation: torch.Tensor
    receiver_albedo: torch.Tensor

    def flux(self, j: int, light: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        """Projector j's light summed over each of its source blocks.

        Args:
            light: :math:`(N, C_p, H_j W_j)` light as the camera's channels see it
                (:meth:`~torchproj.sim.VirtualRig.radiance`).
            size: the projector's ``(width, height)``.

        Returns:
            :math:`(N, C_p, S_j)`.
        """
        (width, height), block = size, self.blocks[j]
        rows, cols = -(-height // block), -(-width // block)
        image = light.reshape(light.shape[0], light.shape[1], height, width)
        image = F.pad(image, (0, cols * block - width, 0, rows * block - height))
        return image.reshape(*image.shape[:2], rows, block, cols, block).sum((3, 5)).flatten(2)

    def source_of(self, sizes: list[tuple[int, int]], projector: torch.Tensor,
                  cell: torch.Tensor) -> tuple[torch.Tensor, int]:
        """Each cell's source, numbered as :meth:`flux` and ``transfer`` number them (projector by
        projector, blocks row-major), and the number of sources.

        Args:
            sizes: per projector ``(width, height)``.
            projector, cell: :math:`(M,)` a cell's projector and row-major index.
        """
        counts = [-(-h // b) * -(-w // b) for (w, h), b in zip(sizes, self.blocks)]
        device = cell.device
        starts = torch.tensor([0, *counts], device=device).cumsum(0)[projector]
        widths = torch.tensor([w for w, _ in sizes], device=device)[projector]
        blocks = torch.tensor(self.blocks, device=device)[projector]
        return starts + (cell // widths // blocks) * -(-widths // blocks) + (cell % widths) // blocks, sum(counts)

    def add_to(self, radiance: torch.Tensor, fluxes: list[torch.Tensor]) -> torch.Tensor:
        """Add the bounced light to :math:`(N, C, H W)` radiance, in place, image by image.

        Args:
            fluxes: per projector, :meth:`flux` of its light, for N images or one shown in all.
        """
        channels = radiance.shape[1]
        albedo = self.receiver_albedo[[min(ch, self.receiver_albedo.shape[0] - 1) for ch in range(channels)]]
        for i in range(radiance.shape[0]):
            received = []
            for ch in range(channels):
                flux = torch.cat([f[min(i, f.shape[0] - 1), min(ch, f.shape[1] - 1)] for f in fluxes])  # (S,)
                flux = flux * self.source_albedo[min(ch, self.source_albedo.shape[0] - 1)]
                received.append(self.transfer @ flux)  # (R,)
            full = spmm(self.interpolation, torch.stack(received).T).T  # (C, H W)
            radiance[i] += full * albedo.flatten(1)
        return radiance


def _interpolation(surface_id: torch.Tensor, k: int) -> torch.Tensor:
    """CSR :math:`(H W, h w)`: each pixel's bilinear weights over its four neighbouring receivers that
    see the pixel's own surface, normalised (the bounce differs from one surface to the next, and a
    corner's two faces must not be blended); a pixel with none of them gets no bounced light."""
    height, width = surface_id.shape
    grid = surface_id[::k, ::k]
    h, w = grid.shape
    y = torch.arange(height, device=surface_id.device, dtype=torch.float32) / k
    x = torch.arange(width, device=surface_id.device, dtype=torch.float32) / k
    y0 = y.floor().long().clamp(max=h - 1)[:, None].expand(height, width)
    x0 = x.floor().long().clamp(max=w - 1)[None, :].expand(height, width)
    fy = (y[:, None] - y0).expand(height, width)
    fx = (x[None, :] - x0).expand(height, width)
    rows, cols, vals = [], [], []
    pixel = torch.arange(height * width, device=surface_id.device).reshape(height, width)
    for dy, dx in ((0, 0), (0, 1), (1, 0), (1, 1)):
        yy, xx = (y0 + dy).clamp(max=h - 1), (x0 + dx).clamp(max=w - 1)
        weight = (fy if dy else 1 - fy) * (fx if dx else 1 - fx)
        same = (grid[yy, xx] == surface_id) & (surface_id >= 0) & (weight > 0)
        rows.append(pixel[same])
        cols.append((yy * w + xx)[same])
        vals.append(weight[same])
    rows, cols, vals = torch.cat(rows), torch.cat(cols), torch.cat(vals)
    total = torch.zeros(height * width, device=surface_id.device).index_add_(0, rows, vals)
    return csr_from_coo(rows, cols, vals / total[rows], (height * width, h * w))


def _sources(proj: Projector, device) -> tuple[int, torch.Tensor, torch.Tensor]:
    """A projector's source blocks: block size, each block's centre ray direction (world, unit)
    and solid angle per cell there."""
    block = max(1, math.ceil(proj.width / SOURCES))

    def centres(n: int) -> torch.Tensor:  # the middle cell of each block (the last may be partial)
        first = torch.arange(0, n, block, device=device, dtype=torch.float32)
        return (first + (first + block).clamp(max=n) - 1) / 2

    u = torch.stack(torch.meshgrid(centres(proj.width), centres(proj.height), indexing="xy"), -1).reshape(-1, 2)
    local = torch.stack([(u[:, 0] - proj.cx) / proj.fx, (u[:, 1] - proj.cy) / proj.fy, torch.ones(len(u), device=device)], -1)
    cos = 1 / local.norm(dim=-1)
    pose = torch.as_tensor(proj.world_from_prj, dtype=torch.float32, device=device)
    direction = (local * cos[:, None]) @ pose[:3, :3].T
    return block, direction, cos**3 / (proj.fx * proj.fy)


def _nearest(casters, origins: torch.Tensor, directions: torch.Tensor):
    """First hit among ``casters``: distance (inf: none), surface index, world normal (not oriented)."""
    hits = [c.hit(origins, directions) for c in casters]
    t, which = torch.stack([h[0] for h in hits], 1).min(1)
    normals = torch.stack([h[1] for h in hits], 1)[torch.arange(len(t), device=t.device), which]
    return t, which, normals


def _clear(casters, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Whether each segment x -> y :math:`(P, 3)` is clear of every surface (ends excluded)."""
    span = y - x
    r = span.norm(dim=-1)
    d = span / r.clamp_min(1e-12)[:, None]
    clear = torch.ones(len(r), dtype=torch.bool, device=x.device)
    for c in casters:
        t, _ = c.hit(x, d, t_min=1e-4)
        clear &= ~(t < r - 1e-4)
    return clear


def cast_bounce(scene, casters, albedo: torch.Tensor, points: torch.Tensor, normals: torch.Tensor,
                surface_id: torch.Tensor, device) -> Bounce:
    """The bounce of one state (module docstring).

    Args:
        casters, albedo: the state's surfaces' ray casters and albedos :math:`(S, A)`.
        points, normals, surface_id: what each camera pixel centre sees (:class:`StateGeometry`).
    """
    sources, source_albedo, blocks, omegas, patch = [], [], [], [], []
    for proj in scene.projectors:
        block, direction, omega = _sources(proj, device)
        centre = torch.as_tensor(proj.world_from_prj[:3, 3], dtype=torch.float32, device=device)
        t, which, n = _nearest(casters, centre[None], direction)
        hit = torch.isfinite(t)
        y = centre + direction * torch.nan_to_num(t, posinf=0.0)[:, None]
        # The lit side faces the projector.
        n = n * torch.where((n * direction).sum(-1, keepdim=True) > 0, -1.0, 1.0)
        cos_in = -(n * direction).sum(-1)
        sources.append((y, n))
        source_albedo.append(torch.where(hit[:, None], albedo[which], 0.0))
        blocks.append(block)
        omegas.append(omega)
        # The block's footprint on the surface: its cells' solid angle at that distance, over the slant.
        patch.append(block * block * omega * torch.nan_to_num(t, posinf=0.0) ** 2 / cos_in.clamp_min(0.05))
    y = torch.cat([s[0] for s in sources])
    n_y = torch.cat([s[1] for s in sources])
    omega, area = torch.cat(omegas), torch.cat(patch)
    height, width = surface_id.shape
    k = max(1, math.ceil(math.sqrt(height * width / RECEIVERS)))
    x = points[::k, ::k]
    n_x = normals[::k, ::k]
    covered = surface_id[::k, ::k] >= 0
    h, w = covered.shape
    x, n_x = x.reshape(-1, 3), n_x.reshape(-1, 3)
    transfer = torch.zeros(h * w, len(y), device=device)
    receivers = torch.nonzero(covered.reshape(-1))[:, 0]
    per_chunk = max(1, _PAIRS // max(len(y), 1))
    for start in range(0, len(receivers), per_chunk):
        rx = receivers[start:start + per_chunk]
        span = x[rx, None, :] - y[None]  # (m, S, 3): from source to receiver
        r2 = (span * span).sum(-1)
        wdir = span / r2.sqrt().clamp_min(1e-12)[..., None]
        cos_out = (n_y[None] * wdir).sum(-1).clamp_min(0)
        cos_rx = (-(n_x[rx, None, :] * wdir).sum(-1)).clamp_min(0)
        g = omega * cos_out * cos_rx / (math.pi * (r2 + area / math.pi))
        pair = torch.nonzero(g > 0)
        if len(pair):
            ok = _clear(casters, x[rx[pair[:, 0]]], y[pair[:, 1]])
            g[pair[~ok, 0], pair[~ok, 1]] = 0.0
        transfer[rx] = g
    receiver_albedo = torch.where(surface_id[None] >= 0, albedo[surface_id.clamp_min(0)].permute(2, 0, 1), 0.0)
    return Bounce(transfer=transfer, source_albedo=torch.cat(source_albedo).T.contiguous(), blocks=blocks,
                  grid=(h, w, k), interpolation=_interpolation(surface_id, k),
                  receiver_albedo=receiver_albedo / math.pi)
