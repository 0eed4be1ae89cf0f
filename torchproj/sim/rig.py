"""The virtual projector-camera rig: the physics every torchproj number is measured against.

Physics (docs/scenes.md, "The virtual rig"): a camera sample ray hits surface point X (through any
semi-transparent screens in front, each passing ``transmittance`` of the light on). Projector j lights
X with irradiance ``E_j = L_j(u_j) * max(0, n.l_j) / d_j^2`` where u_j is X projected into projector j,
``L_j`` the light of the LCD cell containing u_j, d_j the distance to the projector centre, and zero
where X is shadowed from j. A colour camera's channel c sees ``sum_p M_j[c, p] L_{j,p}`` of projector
j's primaries p (its ``colour_mixing`` M_j; conventions module, "Colour"). With ``interreflection``
the light also bounces once between surfaces (:mod:`torchproj.sim.bounce`). A projector with a lens focused elsewhere (``focus`` in its config) blurs:
``L_j`` is then the mean light over the circle of confusion around u_j at X's depth (thin lens;
shadows stay those of the lens centre). The radiance towards the camera is ``albedo / pi * (sum_j E_j + ambient)``;
the camera model (:mod:`torchproj.sim.camera`) turns it into pixel values.

Geometry is cast once per state. Because the LCD cells are squares of constant light, a camera pixel's
radiance is a fixed linear combination of emitted cell values, so each state is held as one sparse
matrix per projector ("light transport", camera pixels x projector cells) and capturing any pattern
is a sparse product. This matrix is the simulator's private ground truth: the solvers never see it
(they work from what calibration recovers), except in an explicitly named oracle mode.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass

import torch
from kornia.geometry.calibration import undistort_points

from ..core.checks import check, check_device, check_seed, check_shape
from ..core.conventions import pixel_grid, round_to_pixel
from ..core.lens import DISC_POINTS, GOLDEN_ANGLE, disc_points
from ..core.sparse import csr_tensor
from ..scene.config import SAMPLE_SPACING, Projector, Scene, Surface, check_scene, supersampling_for
from .bounce import Bounce, cast_bounce
from .camera import apply_camera
from .primitives import make_caster

__all__ = ["VirtualRig", "StateGeometry", "sample_spacing", "supersampling_needed"]

_CHUNK = 1 << 20  # rays per chunk: bounds memory whatever the camera resolution
_SPACING_PIXELS = 1 << 18  # camera pixels sample_spacing reads at most (every k-th of each axis beyond)


@dataclass
class StateGeometry:
    """What ray casting found for one scene state.

    Attributes:
        transport: per projector, a list of CSR matrices :math:`(H W, H_j W_j)` (one per albedo
            channel, or a single one for grey albedos) mapping emitted cell light to camera radiance.
        ambient: :math:`(C_a, H, W)` radiance from ambient light.
        prj_xy: :math:`(J, H, W, 2)` continuous projector coordinates (conventions module) of the
            surface point seen at each camera pixel centre, NaN where projector j does not light it
            (outside its image, facing away, or shadowed).
        points: :math:`(H, W, 3)` world point seen at each pixel centre, NaN where no surface.
        normals: :math:`(H, W, 3)` unit normals there, turned towards the camera.
        surface_id: :math:`(H, W)` index into the state's surface list, -1 where no surface.
        bounce: with ``interreflection``, the light bounced once between surfaces
            (:mod:`torchproj.sim.bounce`); None without.
    """

    state: str
    transport: list[list[torch.Tensor]]
    ambient: torch.Tensor
    prj_xy: torch.Tensor
    points: torch.Tensor
    normals: torch.Tensor
    surface_id: torch.Tensor
    bounce: Bounce | None = None


@dataclass
class _Layer:
    sid: torch.Tensor  # (M,) surface index within the state
    x: torch.Tensor  # (M, 3) world points
    n: torch.Tensor  # (M, 3) unit normals towards the camera
    weight: torch.Tensor  # (M,) light fraction passed on by screens in front
    ray: torch.Tensor  # (M,) index of the ray within its chunk


def _vignette(p: Projector, device) -> torch.Tensor:
    """Relative light of each LCD cell, :math:`(H_j W_j,)`: ``1 - v (r / r_corner)^2``."""
    grid = pixel_grid(p.height, p.width, device=device)
    centre = torch.tensor([p.cx, p.cy], device=device)
    r2 = ((grid - centre) ** 2).sum(-1)
    corners = torch.tensor([[0, 0], [p.width - 1, 0], [0, p.height - 1], [p.width - 1, p.height - 1]],
                           device=device, dtype=torch.float32)
    r2max = ((corners - centre) ** 2).sum(-1).max()
    return (1 - p.vignetting * r2 / r2max).reshape(-1)


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Row-wise dot products of :math:`(N, 3)` arrays, as a product with a ones vector: torch's sum
    over a last axis of three is more than twice as slow, and casting runs several per ray."""
    return (a * b) @ torch.ones(3, dtype=a.dtype, device=a.device)


def _lit_cells(proj: Projector, u: torch.Tensor, g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Row-major index of the LCD cell each point's projector coordinate :math:`(M, 2)` falls in
    (conventions module), and whether the projector lights it: inside its image and ``g > 0``."""
    cell = round_to_pixel(u)
    inside = ((cell[:, 0] >= 0) & (cell[:, 0] < proj.width) & (cell[:, 1] >= 0) & (cell[:, 1] < proj.height)
              & (g > 0))
    return cell[:, 1] * proj.width + cell[:, 0], inside


def _footprint_cells(proj: Projector, u: torch.Tensor, g: torch.Tensor, depth: torch.Tensor,
                     ray: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Which LCD cells light each point, and what share of the point's light each gives.

    A pinhole projector lights a point from the one cell its coordinate falls in. Through a thin
    lens focused elsewhere (:class:`~torchproj.scene.Projector`) the point sees a disc of the LCD,
    the circle of confusion at its depth, every part of it equally: the disc is sampled at the points
    ``DISC_POINTS`` gives its size (:mod:`torchproj.core.lens`), turned by the golden angle per ray.

    Args:
        u: :math:`(M, 2)` projector coordinates; g: :math:`(M,)` geometric factors (0: unlit);
        depth: :math:`(M,)` depths along the projector's axis; ray: :math:`(M,)` global ray numbers.

    Returns:
        entries ``point, cell, share`` :math:`(E,)`: the point, a row-major cell that lights it and
        the share of the point's light from that cell (a point's shares sum to at most 1: less where
        part of its disc falls outside the image); unlit points have none.
    """
    if proj.focus_distance is None:
        cell, lit = _lit_cells(proj, u, g)
        point = torch.nonzero(lit)[:, 0]
        return point, cell[point], torch.ones(point.shape, dtype=u.dtype, device=u.device)
    across, down = proj.blur_diameter(depth)
    size = torch.maximum(across, down)
    entries, low = [], 0.0
    for high, count in DISC_POINTS:
        point = torch.nonzero((size >= low) & (size < high) & (g > 0))[:, 0]
        low = high
        if point.numel() == 0:
            continue
        # The spiral turned by the golden angle from one ray to the next: a camera pixel's samples see
        # different points of their circles of confusion.
        turn = (ray[point].double() * GOLDEN_ANGLE).remainder(2 * math.pi).float()
        cos, sin = turn.cos()[:, None], turn.sin()[:, None]
        disc = disc_points(count, u.device)
        dx, dy = disc[:, 0], disc[:, 1]
        spots = torch.stack([u[point, 0, None] + (cos * dx - sin * dy) * across[point, None],
                             u[point, 1, None] + (sin * dx + cos * dy) * down[point, None]], -1)  # (m, K, 2)
        cell, lit = _lit_cells(proj, spots.reshape(-1, 2), g[point].repeat_interleave(count))
        slot = torch.nonzero(lit)[:, 0]
        entries.append((point[slot // count], cell[slot], torch.full(slot.shape, 1 / count, device=u.device)))
    if not entries:
        none = torch.zeros(0, dtype=torch.int64, device=u.device)
        return none, none, torch.zeros(0, dtype=u.dtype, device=u.device)
    point, cell, share = (torch.cat(parts) for parts in zip(*entries))
    return point, cell, share


def _focal_spacing(scene: Scene) -> float:
    """Cells between a camera pixel's samples by the focal lengths alone (the finest projector, on a
    surface facing both devices at the same distance): ``f_projector / (f_camera s)``."""
    return max(p.fx for p in scene.projectors) / (scene.camera.fx * scene.camera.supersampling)


def _warn_if_undersampled(scene: Scene) -> None:
    """Warn when camera samples fall too far apart to resolve the projectors' LCD cells.

    Each camera pixel is simulated by s x s point samples, each lighting from the one cell it falls
    in. Where samples are spaced more than ``SAMPLE_SPACING`` (0.4) cells apart (on a surface about as far from the
    camera as from the projectors: spacing / cell = f_projector / (f_camera s)), a solver can learn
    where the samples fall and put light only there: quality looks higher at the exact pose than a
    finer simulation of the same light gives, and collapses a fraction of a millimetre away
    (``benchmarks/sampling.py``: 3-5 dB on ``box_positions`` with 2 x 2 samples; with 4 x 4 within
    0.35 dB of 8 x 8).
    """
    spacing = _focal_spacing(scene)
    if spacing > SAMPLE_SPACING:
        need = supersampling_for(max(p.fx for p in scene.projectors), scene.camera.fx)
        warnings.warn(f"scene {scene.name!r}: camera samples are {spacing:.2f} projector cells apart, too coarse to "
                      f"resolve the cells (solvers may fit where the samples fall); set camera.supersampling to "
                      f"{need} or more", stacklevel=3)


def sample_spacing(prj_xy: torch.Tensor, surface_id: torch.Tensor, supersampling: int) -> torch.Tensor:
    """How far apart a camera pixel's samples fall on each projector's LCD, as cast.

    The focal lengths alone (:func:`_warn_if_undersampled`) tell it for a surface facing both
    devices at the same distance; a surface the camera sees obliquely, or nearer to it than to the
    projector, spreads the samples further along one axis. Here it is read off the cast geometry:
    per camera pixel, the larger of the steps of the projector coordinate to its right and lower
    neighbours on the same surface (both lit by the projector), over the ``supersampling``.

    Args:
        prj_xy: :math:`(J, H, W, 2)` the projectors' coordinates at the pixel centres
            (:attr:`StateGeometry.prj_xy`), NaN where unlit.
        surface_id: :math:`(H, W)` (:attr:`StateGeometry.surface_id`).
        supersampling: samples per camera pixel axis.

    Returns:
        :math:`(J,)` the median over each projector's pixels of that spacing in cells, NaN where it
        lights no two neighbours on one surface.
    """
    check_shape(surface_id, "surface_id", list(prj_xy.shape[1:3]))
    height, width = surface_id.shape
    # Every step-th pixel of each axis (with its own neighbours) where the camera has more than
    # _SPACING_PIXELS: a median over a quarter of a million pixels is the whole image's to the
    # hundredth, at a ninth of the work on a 1600 x 1200 camera.
    step = max(1, math.ceil(math.sqrt(height * width / _SPACING_PIXELS)))
    sid = surface_id[::step, ::step]
    out = torch.full((prj_xy.shape[0],), float("nan"))
    for j, xy in enumerate(prj_xy):
        here = xy[::step, ::step]
        spacing = torch.full(sid.shape, float("nan"), dtype=xy.dtype, device=xy.device)
        for dy, dx in ((0, 1), (1, 0)):  # the right and lower neighbours
            there, sid_there = xy[dy::step, dx::step], surface_id[dy::step, dx::step]
            h, w = min(sid.shape[0], sid_there.shape[0]), min(sid.shape[1], sid_there.shape[1])
            a, b, sa, sb = here[:h, :w], there[:h, :w], sid[:h, :w], sid_there[:h, :w]
            same = torch.isfinite(a).all(-1) & torch.isfinite(b).all(-1) & (sa == sb) & (sa >= 0)
            spacing[:h, :w] = torch.fmax(spacing[:h, :w], torch.where(same, (a - b).norm(dim=-1), float("nan")))
        found = spacing[torch.isfinite(spacing)]
        if found.numel():
            out[j] = float(found.median()) / supersampling
    return out


def supersampling_needed(spacing: torch.Tensor, supersampling: int) -> int:
    """The fewest samples per camera pixel axis that bring a :func:`sample_spacing` measured with
    ``supersampling`` samples within ``SAMPLE_SPACING`` cells (the spacing goes as one over the
    samples; the pixel centres' geometry does not change with them)."""
    worst = float(torch.nan_to_num(spacing, nan=0.0).max()) if spacing.numel() else 0.0
    return max(1, math.ceil(supersampling * worst / SAMPLE_SPACING - 1e-9))


def _warn_if_cast_undersampled(scene: Scene, state: str, geometry: StateGeometry) -> None:
    """Warn when a state's cast geometry spreads the camera samples over more than
    ``SAMPLE_SPACING`` cells of a projector (:func:`sample_spacing`), where the focal lengths alone
    did not (:func:`_warn_if_undersampled` warned at the rig's start)."""
    cam = scene.camera
    if _focal_spacing(scene) > SAMPLE_SPACING:
        return
    spacing = sample_spacing(geometry.prj_xy.cpu(), geometry.surface_id.cpu(), cam.supersampling)
    need = supersampling_needed(spacing, cam.supersampling)
    if need <= cam.supersampling:
        return
    worst = int(torch.nan_to_num(spacing, nan=0.0).argmax())
    warnings.warn(f"scene {scene.name!r}, state {state!r}: camera samples fall {float(spacing[worst]):.2f} cells of "
                  f"projector {scene.projectors[worst].name!r} apart on its surfaces (median; an oblique surface or one "
                  f"nearer the camera spreads them), too coarse to resolve the cells (solvers may fit where the "
                  f"samples fall); set camera.supersampling to {need} or more", stacklevel=4)


def check_rig(rig, name: str = "rig") -> None:
    """``rig`` a :class:`VirtualRig` (``VirtualRig(scene)``, or a virtual calibration's ``.rig``)."""
    check(isinstance(rig, VirtualRig), f"{name} must be a VirtualRig (VirtualRig(scene), or a calibration's .rig), "
                                       f"got {type(rig).__name__}")


class VirtualRig:
    """A simulated rig for a :class:`~torchproj.scene.Scene`.

    Example:
        >>> rig = VirtualRig(load_scene())                       # doctest: +SKIP
        >>> white = torch.ones(1, 1, 768, 1024)
        >>> img = rig.capture("near", {"upper": white})          # (1, C, 1200, 1600)
    """

    def __init__(self, scene: Scene, device="cpu"):
        self.scene = check_scene(scene)
        self.device = check_device(device)
        self.generator = torch.Generator(device=self.device).manual_seed(scene.seed)
        self._geometry: dict[str, StateGeometry] = {}
        self._vignette = [_vignette(p, self.device) for p in scene.projectors]
        self._kept: dict = {}  # see _reuse
        self._spacing_checked: set[str] = set()  # states whose cast spacing was checked (geometry())
        _warn_if_undersampled(scene)

    # ---------------------------------------------------------------------------------- rays
    def camera_rays(self, supersampling: int, start: int = 0, stop: int | None = None):
        """World origins and unit directions of camera sample rays ``start:stop``.

        Rays are numbered pixel-major: ray ``i`` is sample ``i % s^2`` of pixel ``i // s^2`` (row-major
        pixels), and the s x s samples of a pixel sit at the centres of an s x s grid over its
        footprint.

        Returns:
            origins :math:`(N, 3)` and directions :math:`(N, 3)`, N = stop - start.
        """
        cam = self.scene.camera
        stop = cam.width * cam.height * supersampling**2 if stop is None else stop
        origin, dirs = self._rays(torch.arange(start, stop, device=self.device), supersampling)
        return origin.expand_as(dirs), dirs

    def _rays(self, idx: torch.Tensor, s: int):
        """The camera centre :math:`(1, 3)`, shared by every ray, and the unit directions :math:`(N, 3)`
        of the camera rays numbered ``idx`` (numbering: :meth:`camera_rays`)."""
        cam = self.scene.camera
        pixel = idx // (s * s)
        sample = idx - pixel * (s * s)
        row = pixel // cam.width
        offsets = (torch.arange(s, device=self.device, dtype=torch.float32) + 0.5) / s - 0.5
        pix = torch.stack([(pixel - row * cam.width).float().add_(offsets[sample % s]),
                           row.float().add_(offsets[sample // s])], -1)
        K = torch.as_tensor(cam.K, dtype=torch.float32, device=self.device)
        if cam.distortion:
            # A distorted lens bends the ray of pixel p: find the ideal pinhole pixel it came from.
            dist = torch.tensor(cam.distortion, dtype=torch.float32, device=self.device)
            pix = undistort_points(pix[None], K[None], dist[None], num_iters=10)[0]
        pose = torch.as_tensor(cam.world_from_cam, dtype=torch.float32, device=self.device)
        # A pinhole pixel (u, v) looks along R K^-1 (u, v, 1): one 3 x 3 product for every ray.
        world_from_pixel = pose[:3, :3] @ torch.linalg.inv(K)
        dirs = torch.addcmul(world_from_pixel[:, 2], pix[:, :1], world_from_pixel[:, 0]).addcmul_(pix[:, 1:],
                                                                                                  world_from_pixel[:, 1])
        return pose[None, :3, 3], dirs.div_(dirs.norm(dim=-1, keepdim=True))

    # ------------------------------------------------------------------------------- casting
    def geometry(self, state: str) -> StateGeometry:
        """Cast the state's geometry (once; later calls return the cached result)."""
        if not isinstance(state, str):
            self.scene.state(state)  # refused there, naming the states (a list is no key to look up)
        if state not in self._geometry:
            self._geometry[state] = self._cast(state)
        if state not in self._spacing_checked:
            self._spacing_checked.add(state)
            _warn_if_cast_undersampled(self.scene, state, self._geometry[state])
        return self._geometry[state]

    def centre_geometry(self, state: str) -> dict[str, torch.Tensor]:
        """The state's ground truth at the camera's pixel centres alone: ``prj_xy``, ``points``,
        ``normals`` and ``surface_id`` as :class:`StateGeometry` holds them. A state already cast
        gives its own; otherwise one ray a pixel is cast (no transport, a fraction of the cost), and
        nothing is kept."""
        if state in self._geometry:
            g = self._geometry[state]
            return {"prj_xy": g.prj_xy, "points": g.points, "normals": g.normals, "surface_id": g.surface_id}
        casters, _, transmit, _ = self._materials([self.scene.surfaces[n] for n in self.scene.state(state).surfaces])
        return self._centre_truth(casters, transmit)

    def cast_geometry(self) -> dict[str, StateGeometry]:
        """The states cast so far, by name (what a cache can keep for a rig of the same scene)."""
        return dict(self._geometry)

    def adopt_geometry(self, geometry: dict[str, StateGeometry]) -> None:
        """Take states cast earlier by a rig of the same scene (a cache's), instead of casting them.

        Casting is a pure function of the scene, so a rig of the same scene would cast exactly these;
        the caller vouches for the scene (:func:`torchproj.pipeline.cache.geometry_key`), this checks
        that each state fits this rig's camera and projectors, and refuses the lot otherwise.
        """
        cam, projectors = self.scene.camera, self.scene.projectors
        names = {st.name for st in self.scene.states}
        for name, geo in geometry.items():
            check(name in names and geo.state == name, f"cast geometry of state {name!r} is not this scene's")
            check(len(geo.transport) == len(projectors), f"cast geometry of state {name!r} has "
                                                         f"{len(geo.transport)} projectors, the scene {len(projectors)}")
            for mats, p in zip(geo.transport, projectors):
                check(all(tuple(m.shape) == (cam.width * cam.height, p.width * p.height) for m in mats),
                      f"cast geometry of state {name!r} does not fit projector {p.name!r} and the camera")
            check(tuple(geo.ambient.shape[1:]) == (cam.height, cam.width),
                  f"cast geometry of state {name!r} does not fit the camera")
            check(geo.ambient.device.type == torch.device(self.device).type,
                  f"cast geometry of state {name!r} is on {geo.ambient.device}, the rig on {self.device}")
        self._geometry.update(geometry)

    def _cast(self, state_name: str) -> StateGeometry:
        scene, cam = self.scene, self.scene.camera
        state = scene.state(state_name)
        casters, albedo, transmit, max_layers = self._materials([scene.surfaces[n] for n in state.surfaces])
        n_alb = albedo.shape[1]
        n_pix = cam.width * cam.height
        ss = cam.supersampling**2
        chunk = max(1, _CHUNK // ss) * ss  # whole pixels per chunk

        keys = [[] for _ in scene.projectors]
        vals = [[] for _ in scene.projectors]
        ambient = torch.zeros(n_alb, n_pix, device=self.device)
        for start in range(0, n_pix * ss, chunk):
            stop = min(start + chunk, n_pix * ss)
            o, d = self.camera_rays(cam.supersampling, start, stop)
            pixel = torch.arange(start, stop, device=self.device) // ss
            entries = [([], []) for _ in scene.projectors]
            for layer in self._layers(casters, transmit, o, d, max_layers):
                w = layer.weight[:, None] * albedo[layer.sid] / math.pi / ss  # (M, n_alb)
                layer_pixel = pixel[layer.ray]
                ambient.index_add_(1, layer_pixel, (w * scene.ambient).T)
                for j, proj in enumerate(scene.projectors):
                    u, g, depth = self._illumination(proj, casters, transmit, layer)
                    point, cell, share = _footprint_cells(proj, u, g, depth, start + layer.ray)
                    entries[j][0].append(layer_pixel[point] * (proj.width * proj.height) + cell)
                    entries[j][1].append((g[point] * share)[:, None] * w[point])
            # Merge the samples of a pixel that land in the same LCD cell. Unique keys come out
            # sorted, and chunks cover increasing pixel ranges, so rows stay in CSR order.
            for j in range(len(scene.projectors)):
                if not entries[j][0]:
                    continue
                key, inverse = torch.unique(torch.cat(entries[j][0]), return_inverse=True)
                val = torch.zeros(key.shape[0], n_alb, device=self.device)
                keys[j].append(key)
                vals[j].append(val.index_add_(0, inverse, torch.cat(entries[j][1])))
        transport = []
        for j, proj in enumerate(scene.projectors):
            n_cells = proj.width * proj.height
            key = torch.cat(keys[j]) if keys[j] else torch.zeros(0, dtype=torch.int64, device=self.device)
            val = torch.cat(vals[j]) if vals[j] else torch.zeros(0, n_alb, device=self.device)
            rows, cols = key // n_cells, key % n_cells
            crow = torch.zeros(n_pix + 1, dtype=torch.int64, device=self.device)
            crow[1:] = torch.cumsum(torch.bincount(rows, minlength=n_pix), 0)
            transport.append([csr_tensor(crow, cols, val[:, ch].contiguous(), (n_pix, n_cells))
                              for ch in range(n_alb)])

        truth = self._centre_truth(casters, transmit)
        bounce = cast_bounce(scene, casters, albedo, truth["points"], truth["normals"], truth["surface_id"],
                             self.device) if scene.interreflection else None
        return StateGeometry(state=state_name, transport=transport,
                             ambient=ambient.reshape(n_alb, cam.height, cam.width), bounce=bounce, **truth)

    def _materials(self, surfaces: list[Surface]):
        """Ray casters, albedos :math:`(S, A)` (A = 1 for grey, else 3), transmittances :math:`(S,)`
        and the most layers a camera ray can cross (1 + the number of semi-transparent screens)."""
        casters = [make_caster(s, self.device) for s in surfaces]
        grey = self.scene.camera.channels == 1 or all(len(s.albedo) == 1 for s in surfaces)
        albedo = torch.tensor(
            [[sum(s.albedo) / len(s.albedo)] if grey else list(s.albedo) * (3 // len(s.albedo)) for s in surfaces],
            dtype=torch.float32, device=self.device)
        transmit = torch.tensor([s.transmittance for s in surfaces], dtype=torch.float32, device=self.device)
        return casters, albedo, transmit, 1 + int((transmit > 0).sum())

    def _layers(self, casters, transmit, o, d, max_layers):
        """Hits along camera rays, front to back, until an opaque surface.

        Args:
            o: :math:`(N, 3)` ray origins, or :math:`(1, 3)` when all rays start at one point.
            d: :math:`(N, 3)` unit directions.

        Yields a :class:`_Layer` for the rays that hit: surface index, point, normal turned towards
        the camera, weight (the fraction of light the screens in front pass on) and ray index.
        """
        hits = [c.hit(o, d) for c in casters]
        t_all = torch.stack([h[0] for h in hits], 1)  # (N, S)
        if len(hits) == 1:
            order, normals = torch.zeros_like(t_all, dtype=torch.int64), hits[0][1]
        else:
            order, normals = torch.argsort(t_all, dim=1), torch.stack([h[1] for h in hits], 1)  # (N, S, 3)
        weight = torch.ones(d.shape[0], device=d.device)
        for layer in range(min(max_layers, len(casters))):
            sid = order[:, layer]
            t = t_all.gather(1, sid[:, None])[:, 0]
            ok = torch.isfinite(t) & (weight > 0)
            if not bool(ok.any()):
                break
            ray = torch.nonzero(ok)[:, 0]
            d_ray, sid_ray = d[ray], sid[ray]
            x = torch.addcmul(o if o.shape[0] == 1 else o[ray], d_ray, t[ray, None])
            n = normals[ray] if len(hits) == 1 else normals[ray, sid_ray]
            n = n * torch.where(_dot(n, d_ray) > 0, -1.0, 1.0)[:, None]
            yield _Layer(sid_ray, x, n, weight[ray], ray)
            weight = weight * transmit[sid]

    def _illumination(self, proj: Projector, casters, transmit, layer: "_Layer"):
        """Where a projector's light falls on a layer's points and how strongly.

        Returns:
            continuous projector coordinates :math:`(M, 2)`, the geometric factor
            ``max(0, n.l) / d^2 * visibility`` :math:`(M,)` (0 where unlit) and the points' depths
            along the projector's axis :math:`(M,)` (1 behind it, where the factor is 0).
        """
        x, n = layer.x, layer.n
        pose = torch.as_tensor(proj.world_from_prj, dtype=torch.float32, device=self.device)
        to_prj = pose[:3, 3] - x
        dist2 = _dot(to_prj, to_prj)
        x_prj = to_prj @ -pose[:3, :3]  # the point in the projector's frame
        in_front = x_prj[:, 2] > 1e-6
        # Pinhole projection u = f xy / z + c; points behind the projector get any finite value (g = 0).
        depth = torch.where(in_front, x_prj[:, 2], 1.0)[:, None]
        focal = torch.tensor([proj.fx, proj.fy], device=self.device)
        centre = torch.tensor([proj.cx, proj.cy], device=self.device)
        u = torch.addcmul(centre, x_prj[:, :2] / depth, focal)
        # max(0, n.l) / d^2 with l = to_prj / d: the clamped dot product over d^3.
        g = _dot(n, to_prj).clamp_min_(0).div_(dist2 * dist2.sqrt()).mul_(in_front)
        for index, (c, tr) in enumerate(zip(casters, transmit.tolist())):
            # Shadow rays. A point on a convex primitive that faces the projector cannot be shadowed
            # by that same primitive, so only other surfaces (and meshes, which may be concave) count.
            test = g > 0
            if c.surface.type != "mesh":
                test &= layer.sid != index
            if not bool(test.any()):
                continue
            ray = torch.nonzero(test)[:, 0]
            dist = dist2[ray].sqrt()
            t, _ = c.hit(x[ray], to_prj[ray] / dist[:, None])
            blocked = ray[t < dist - 1e-5]
            g[blocked] = g[blocked] * tr
        return u, g, depth[:, 0]

    def _centre_truth(self, casters, transmit) -> dict:
        """Ground truth at pixel centres: first surface hit, its normal, each projector's coordinate."""
        cam = self.scene.camera
        h, w = cam.height, cam.width
        points = torch.full((h * w, 3), float("nan"), device=self.device)
        normals = torch.full((h * w, 3), float("nan"), device=self.device)
        sid_map = torch.full((h * w,), -1, dtype=torch.int64, device=self.device)
        prj_xy = torch.full((len(self.scene.projectors), h * w, 2), float("nan"), device=self.device)
        for start in range(0, h * w, _CHUNK):
            o, d = self.camera_rays(1, start, min(start + _CHUNK, h * w))
            layer = next(iter(self._layers(casters, transmit, o, d, 1)), None)
            if layer is None:
                continue
            idx = start + layer.ray
            points[idx], normals[idx], sid_map[idx] = layer.x, layer.n, layer.sid
            for j, proj in enumerate(self.scene.projectors):
                u, g, _ = self._illumination(proj, casters, transmit, layer)
                inside = ((u[:, 0] >= -0.5) & (u[:, 0] < proj.width - 0.5) & (u[:, 1] >= -0.5)
                          & (u[:, 1] < proj.height - 0.5) & (g > 0))
                prj_xy[j, idx[inside]] = u[inside]
        return dict(prj_xy=prj_xy.reshape(-1, h, w, 2), points=points.reshape(h, w, 3),
                    normals=normals.reshape(h, w, 3), surface_id=sid_map.reshape(h, w))

    def release(self, state: str | None = None) -> None:
        """Drop the cached geometry of one state (None: all) to free its transport matrices."""
        if state is None:
            self._geometry.clear()
        else:
            self._geometry.pop(state, None)

    def surface_mask(self, state: str, surfaces: list[str] | None = None) -> torch.Tensor:
        """:math:`(H, W)` camera pixels whose centre sees one of ``surfaces`` first (None: any surface).

        On the virtual rig this stands in for the mask a user paints over a real capture to say
        where a target's image belongs.
        """
        geo = self.geometry(state)
        members = self.scene.state(state).surfaces
        if surfaces is None:
            return geo.surface_id >= 0
        for name in surfaces:
            check(name in members, f"surface {name!r} is not present in state {state!r}; present: {members}")
        index = torch.tensor([members.index(n) for n in surfaces], device=geo.surface_id.device)
        return torch.isin(geo.surface_id, index)

    # ------------------------------------------------------------------------------ capture
    def emitted(self, j: int, patterns: torch.Tensor) -> torch.Tensor:
        """Light of each LCD cell of projector j for pattern values in [0, 1], per primary (before
        the camera's colour mixing, which :meth:`radiance` applies).

        Args:
            patterns: :math:`(N, C, H_j, W_j)` pattern values.

        Returns:
            :math:`(N, C, H_j W_j)` emitted light (W/m^2 at 1 m): ``power (a x^b + black) vignette``.
        """
        p = self.scene.projectors[j]
        b = torch.tensor(p.response_b, dtype=patterns.dtype, device=patterns.device)
        if patterns.shape[1] == 1 and b.numel() == 3:
            patterns = patterns.expand(-1, 3, -1, -1)
        # In place on one fresh tensor: a calibration sequence is tens of full-size images.
        light = patterns.clamp(0, 1)
        light = light.pow_(p.response_b[0]) if b.numel() == 1 else light.pow_(b.view(1, -1, 1, 1))
        light.mul_(p.power * p.response_a).add_(p.power * p.black_level)
        return light.flatten(2).mul_(self._vignette[j])

    def radiance(self, state: str, patterns: dict[str | int, torch.Tensor]) -> torch.Tensor:
        """Noise-free linear radiance seen by the camera.

        Args:
            state: the scene state's name.
            patterns: projector name (or index) -> :math:`(N, C_p, H_j, W_j)` values in [0, 1]
                (C_p = 1 or 3). Projectors not named show black (they stay on, emitting their black
                level), as on a real rig during calibration.

        Returns:
            :math:`(N, C, H, W)` radiance, C the camera's channel count.
        """
        cam = self.scene.camera
        geo = self.geometry(state)
        by_index, n = self._check_patterns(patterns)
        out_c = cam.channels
        # What does not change from image to image (ambient light, projectors showing one image or
        # black) is summed once; each image then adds one sparse product per projector and channel,
        # in place. That measured faster on 2 cores than one sparse-times-dense product over the whole
        # sequence, whose dense operands need a transposed copy each way.
        base = geo.ambient.reshape(-1, cam.height * cam.width).expand(out_c, -1).clone()
        varying = []
        fluxes = [None] * len(self.scene.projectors)  # per projector, its light summed per bounce source
        for j, proj in enumerate(self.scene.projectors):
            if j in by_index and n > 1:
                varying.append(j)
                continue
            light = self._light(j, by_index.get(j))  # (1, Cp, M)
            for ch in range(out_c):
                base[ch].addmv_(geo.transport[j][min(ch, len(geo.transport[j]) - 1)], light[0, min(ch, light.shape[1] - 1)])
            if geo.bounce is not None:
                fluxes[j] = geo.bounce.flux(j, light, (proj.width, proj.height))
        total = base.expand(n, -1, -1).clone()
        for j in varying:
            mats, proj = geo.transport[j], self.scene.projectors[j]
            flux = []
            for i in range(n):
                light = self._light(j, by_index[j][i:i + 1])  # image by image: a sequence's light at once is large
                for ch in range(out_c):
                    total[i, ch].addmv_(mats[min(ch, len(mats) - 1)], light[0, min(ch, light.shape[1] - 1)])
                if geo.bounce is not None:
                    flux.append(geo.bounce.flux(j, light, (proj.width, proj.height)))
            if flux:
                fluxes[j] = torch.cat(flux)
        if geo.bounce is not None:
            geo.bounce.add_to(total, fluxes)
        return total.reshape(n, out_c, cam.height, cam.width)

    def _check_patterns(self, patterns: dict) -> tuple[dict[int, torch.Tensor], int]:
        """Patterns by projector index, checked, and how many images each projector shows."""
        scene = self.scene
        check(isinstance(patterns, Mapping), "patterns must be a dict of projector name (or index) -> (N, C, H, W) "
                                             f"light, got {type(patterns).__name__}")
        by_index = {}
        for key, pat in patterns.items():
            j = scene.projector_index(key)
            proj = scene.projectors[j]
            check_shape(pat, f"patterns[{key!r}]", ["N", "C", proj.height, proj.width])
            check(pat.shape[1] in (1, 3), f"patterns[{key!r}] must have 1 or 3 channels, got {pat.shape[1]}")
            check(pat.is_floating_point(), f"patterns[{key!r}] must be float light in [0, 1], got {pat.dtype} (8-bit "
                                           "images: divide by 255)")
            # A projector shows from its black to its white: a value past them (or NaN) is light no
            # projector gives, which the simulator would have shown all the same.
            lo, hi = (float(v) for v in torch.aminmax(pat.detach())) if pat.numel() else (0.0, 0.0)
            check(lo >= 0 and hi <= 1, f"patterns[{key!r}] must be light in [0, 1] (the projector's black to its white), "
                                       f"got values in [{lo:.3g}, {hi:.3g}]")
            check(j not in by_index, f"patterns give projector {scene.projectors[j].name!r} twice (by name and by index)")
            by_index[j] = pat.to(self.device, torch.float32)
        sizes = {p.shape[0] for p in by_index.values()}
        check(len(sizes) <= 1, f"every projector must show the same number of images, got {sorted(sizes)}")
        check(0 not in sizes, "patterns hold no image (N = 0): give at least one per projector")
        return by_index, (sizes.pop() if sizes else 1)

    def channel_gain(self, j: int) -> torch.Tensor:
        """:math:`(C,)` how much of projector j's white each camera channel sees, relative to no
        colour mixing: the mixing's row sums (ones without mixing, or for a grey camera)."""
        mixing = self.scene.projectors[j].colour_mixing
        if mixing is None:
            return torch.ones(self.scene.camera.channels, device=self.device)
        return torch.tensor(mixing, device=self.device).sum(1)

    def _light(self, j: int, patterns: torch.Tensor | None) -> torch.Tensor:
        """Emitted light of projector j for :math:`(N, C_p, H_j, W_j)` patterns as the camera's
        channels see it, :math:`(N, C_p, H_j W_j)` (3 channels where the projector's primaries mix);
        None: one black image."""
        proj = self.scene.projectors[j]
        if patterns is None:
            patterns = torch.zeros(1, 1, proj.height, proj.width, device=self.device)
        light = self.emitted(j, patterns)
        if self.scene.camera.channels == 1 and light.shape[1] == 3:
            light = light.mean(1, keepdim=True)  # a grey sensor integrates the three primaries
        mixing = self.scene.projectors[j].colour_mixing
        if mixing is not None:
            # What each camera channel sees of the primaries (conventions module, "Colour").
            mixing = torch.tensor(mixing, dtype=light.dtype, device=light.device)
            light = (light * mixing.sum(1).view(1, 3, 1) if light.shape[1] == 1
                     else torch.einsum("cp,npm->ncm", mixing, light))
        return light

    def _generator(self, seed: int | None) -> torch.Generator:
        """The generator of one capture's noise: the rig's own (None), or a fresh one from ``seed``."""
        if seed is None:
            return self.generator
        seed = check_seed(seed, hint=" (or None: the rig's own draws)")
        return torch.Generator(device=self.device).manual_seed(seed)

    def capture(self, state: str, patterns: dict[str | int, torch.Tensor], seed: int | None = None,
                noise: bool = True, quantise: bool = True) -> torch.Tensor:
        """Capture what the camera sees while the projectors show ``patterns``.

        Args:
            state: the scene state's name.
            patterns: as in :meth:`radiance`.
            seed: seed for this capture's noise (default: the rig's generator, seeded by the scene).
            noise: False gives the noise-free (still quantised) image.
            quantise: False skips quantisation (with ``noise=False``: the expected image).

        Returns:
            :math:`(N, C, H, W)` float images in [0, 1], quantised to the camera's bit depth.
        """
        gen = self._generator(seed)
        radiance = self.radiance(state, patterns)
        return apply_camera(radiance, self.scene.camera, gen if noise else None, quantise, out=radiance)

    def _pixel_rays(self, pixels: torch.Tensor, chunk: int):
        """Lazily, per chunk of ``chunk`` pixels: origin, directions, each ray's position in ``pixels``
        and its number (:meth:`camera_rays`)."""
        ss = self.scene.camera.supersampling**2
        for start in range(0, pixels.numel(), chunk):
            local = torch.arange(start, min(start + chunk, pixels.numel()), device=self.device)
            ray_id = (pixels[local, None] * ss + torch.arange(ss, device=self.device)).reshape(-1)
            yield (*self._rays(ray_id, self.scene.camera.supersampling), local.repeat_interleave(ss), ray_id)

    def _reuse(self, name: tuple, inputs: list, make):
        """``make()``, or what it gave last time for the same ``inputs`` (the same tensor objects, not
        modified since). An object placed by watching it is captured look after look through the same
        camera pixels under the same patterns: their rays and emitted light are made once."""
        stamp = [(t, t._version) for t in inputs]
        kept = self._kept.get(name)
        if kept is not None and len(kept[0]) == len(stamp) and all(
                a is b and u == v for (a, u), (b, v) in zip(kept[0], stamp)):
            return kept[1]
        value = make()
        self._kept[name] = (stamp, value)
        return value

    def capture_surfaces(self, surfaces: list[Surface], patterns: dict[str | int, torch.Tensor],
                         pixels: torch.Tensor | None = None, seed: int | None = None,
                         noise: bool = True, direct_only: bool = False) -> torch.Tensor:
        """Capture one set of patterns on surfaces placed anywhere, at some camera pixels only.

        For objects that move between captures (placing a box by watching it): the rays are cast
        for this capture alone and each sample looks up the LCD cell it falls in, so no transport
        matrix is built and nothing is cached. The physics and the camera are those of
        :meth:`capture`; only the requested pixels are simulated.

        Args:
            surfaces: the surfaces present (any poses; they need not be in the scene).
            patterns: projector name (or index) -> :math:`(1, C_p, H_j, W_j)` values in [0, 1].
            pixels: :math:`(P,)` flat row-major camera pixel indices; None: every pixel.
            seed: seed of this capture's noise (default: the rig's generator).
            noise: False gives the noise-free (still quantised) values.
            direct_only: True accepts a scene with ``interreflection`` and captures its direct light
                alone (less than the camera sees: a lower bound).

        Returns:
            :math:`(C, P)` values in [0, 1], C the camera's channel count.
        """
        cam = self.scene.camera
        check(direct_only or not self.scene.interreflection, f"scene {self.scene.name!r}: surfaces placed anywhere are "
                                                             "captured with direct light only; drop interreflection "
                                                             "from the scene")
        by_index, n = self._check_patterns(patterns)
        check(n == 1, f"capture_surfaces shows one image per projector, got {n}")
        shown = sorted(by_index)
        lights = self._reuse(("lights", *shown), [by_index[j] for j in shown],
                             lambda: [self._light(j, by_index.get(j))[0] for j in range(len(self.scene.projectors))])
        asked = pixels
        if pixels is None:
            pixels = torch.arange(cam.width * cam.height, device=self.device)
        pixels = pixels.to(self.device).reshape(-1)
        casters, albedo, transmit, max_layers = self._materials(surfaces)
        ss = cam.supersampling**2
        out_c = cam.channels
        total = torch.zeros(out_c, pixels.numel(), device=self.device)
        chunk = max(1, _CHUNK // ss)
        rays = self._reuse(("rays",), [asked], lambda: list(self._pixel_rays(pixels, chunk))) \
            if asked is not None and pixels.numel() <= chunk else self._pixel_rays(pixels, chunk)
        for o, d, owner, ray_id in rays:
            for layer in self._layers(casters, transmit, o, d, max_layers):
                w = layer.weight[:, None] * albedo[layer.sid] / math.pi / ss  # (M, A)
                received = torch.full((layer.x.shape[0],), self.scene.ambient, device=self.device)
                received = received[None].expand(out_c, -1).clone()
                for j, proj in enumerate(self.scene.projectors):
                    u, g, depth = self._illumination(proj, casters, transmit, layer)
                    point, cell, share = _footprint_cells(proj, u, g, depth, ray_id[layer.ray])
                    for ch in range(out_c):
                        light = lights[j][min(ch, lights[j].shape[0] - 1), cell] * share * g[point]
                        received[ch].index_add_(0, point, light)
                value = received * w.T[[min(ch, w.shape[1] - 1) for ch in range(out_c)]]
                total.index_add_(1, owner[layer.ray], value)
        gen = self._generator(seed)
        return apply_camera(total[None, :, :, None], cam, gen if noise else None)[0, :, :, 0]
