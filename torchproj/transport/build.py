"""Building ``i = A p`` from calibration results and target images.

Model (radiometric weighting): a camera pixel r of state k sees
``black_k(r) + sum_j w_j(r) * p_j(cell_j(r))``, where ``w_j(r)`` is projector j's white-minus-black
at r, measured from the same Gray-code capture set (it folds fall-off, angle, albedo and vignetting
into one number), ``cell_j(r)`` the decoded projector coordinate, and ``p_j`` the projector's linear
relative light (0 = black, 1 = white). A target asks for ``black_k(r) + scale * t(r)`` at its pixels,
so ``A[r, (j, cell)] = w_j(r)`` and ``i[r] = scale * t(r)``. With the bilinear footprint a pixel
spreads its weight over the four cells around its sub-pixel coordinate. With the ``area`` footprint
it spreads it over the cells its own area covers on the projector: the square pixel carried through
the map's local slope (a parallelogram, from the calibrated map alone), each cell weighted by the
share of the pixel it lights. That is the light a camera pixel integrates when it is as large as a
few projector cells (a camera coarser than the projectors, a steep surface). Where calibration
measured how each pixel's light is shared across the edges of its cell (:func:`~torchproj.calib.cell_shares`),
the ``area`` row is then fitted to those shares (:func:`_fit_shares`), after gaining the cells across
an edge where the captures saw light the parallelogram does not reach (:func:`_reach_shares`): the
parallelogram is only the map's guess at the pixel's footprint, the captures measure it.

Rows with the same columns merge exactly: their normal-equation blocks add, and an equivalent set
of at most ``s`` rows (s = columns per row) replaces them (``R^T R = sum a a^T``, ``R^T b = sum i a``),
so the model follows the projector pixels, not the camera pixels. The constant left over keeps the
objective equal to the unmerged one.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping

from dataclasses import dataclass

import torch
from kornia.geometry.transform import get_perspective_transform, warp_perspective

from ..core.checks import check, check_device, check_finite, check_image, check_mask, check_number, check_shape
from ..core.conventions import round_to_pixel
from ..core.errors import InputError
from ..calib.maps import check_projector_size, map_slope, pixel_square
from ..calib.bundle import cell_shares_of, edge_pixels
from ..calib.edges import EdgePixels
from ..calib.graycode import WIDE_SHARE, CellShares, graycode_bits, stripe_signs
from ..core.lens import disc_points, points_for_diameter
from ..core.sparse import csr_tensor, index_dtype
from ..metrics.ssim import WINDOW
from .operator import TransportOperator, check_operator

__all__ = ["BLUR_MIN", "COLOUR_WEIGHTS", "DEFAULT_FOOTPRINT", "FOOTPRINTS", "Target", "StateCalibration", "target_on_camera",
           "build_transport", "build_channel_transports", "group_rows", "has_colour_weights", "map_slope",
           "retarget_rhs"]

# A colour camera's weights: one white minus black per channel (build_channel_transports), or their
# mean for every channel (build_transport). Per channel is what run and solve use where calibration
# has it: on colour_two_planes it lifts the near target 0.9 dB, to the ceiling's colour balance
# (benchmarks/models.py, docs/accuracy.md "The ceiling").
# (COLOUR_WEIGHTS, FOOTPRINTS and DEFAULT_FOOTPRINT live in core.choices, which the command's parser reads.)
# What run, solve and position model by default: the footprint closest to the exact-light ceiling on
# the shipped scenes, for a few seconds more than nearest (benchmarks/models.py, docs/accuracy.md "The
# ceiling"). build_transport's own default stays the paper's nearest cell, whose rows merge.
from ..core.choices import COLOUR_WEIGHTS, DEFAULT_FOOTPRINT, FOOTPRINTS  # noqa: E402

# Points per axis at which a camera pixel's area is carried onto the projector by the ``area``
# footprint: 4 x 4 shares a pixel's light among its cells to 1/16. box_positions' camera samples its
# pixels at the same 4 x 4 points, which flatters the model there; 8 x 8 and 12 x 12 against cameras
# of 2-6 points per axis: benchmarks/area_grid.py, docs/accuracy.md "The ceiling".
_AREA_SAMPLES = 4
# Where a camera pixel spans more than _STEEP_EXTENT cells along a projector axis (steep faces, a
# cylinder's limb) and its rows are fitted to a checkerboard share, its square is sampled at
# _STEEP_SAMPLES x _STEEP_SAMPLES points instead: there 4 x 4 points leave whole cells to one or two
# samples each. Our choice (the paper models no footprint), measured by benchmarks/area_grid.py and
# benchmarks/models.py (docs/accuracy.md "The ceiling").
_STEEP_EXTENT, _STEEP_SAMPLES = 1.0, 12
_AREA_CHUNK, _BLUR_CHUNK = 1 << 18, 1 << 15  # rows per pass, sharp and blurred
# Defocus discs narrower than this (cells) are taken as sharp: measure_blur reads diameters in half
# cells, and a half-cell disc inside a pixel's own footprint changes its row by less than its share of
# the captures' noise; spreading such rows cost a focused plane 0.56 dB on a suite scene (suite-3-3's
# near state, measured 0.5 where the lens is focused).
BLUR_MIN = 1.0
# Points per axis of a blurred row's square where the pixel spans a cell or less, each spread over up
# to 16 points of its disc (wider pixels keep _AREA_SAMPLES): on paper_defocus at half scale (0.6-cell
# pixels) 2 x 2 scores as 4 x 4 (within 0.01 dB) and builds in 3.0 s against 8.7 s; on the suite's
# seed 3 (0.7-1.8-cell pixels) 2 x 2 everywhere cost 0.2-0.45 dB.
_BLUR_SAMPLES = 2
# Sweeps of _fit_shares over a row's four measured shares: the x and y conditions nearly separate,
# so on box_cylinders and paper_two_planes a second or third sweep moves no score by more than
# 0.02 dB or 0.001 SSIM (benchmarks/models.py --share-sweeps 2 3). A row with less than _SHARE_TOL
# of its light on one side of an edge has none there to scale.
_SHARE_SWEEPS, _SHARE_TOL = 1, 1e-6
# Sweeps where a checkerboard pair's share (CellShares.checker) joins the four: on box_positions with
# a 3 x 3 camera, 4 sweeps against 1 gain 0.3 dB near (benchmarks/area_grid.py --checker).
_CHECKER_SWEEPS = 4
# A row is left as it is where more light than WIDE_SHARE was measured past cells n +- 1 on an axis
# (CellShares.outside) and the row holds no cell there: its measured shares then describe a wider
# footprint (defocus) than the row can hold. 0.05 against 0.1 and no limit on paper_defocus:
# docs/accuracy.md "The ceiling".
_SHARE_OUTSIDE = WIDE_SHARE
# A row gains the cells across an edge of its decoded cell where more than this share of the pixel's
# light was measured across it and the row holds none there (_reach_shares). The same 0.05 as above,
# over the noise; 0.03 and 0.1 give the same scores on box_cylinders (docs/accuracy.md "The ceiling").
_SHARE_REACH = 0.05
# _fit_band: the share of a row's light each cell it gains around its own starts with (the fit only
# scales light, so a cell must start with some; 0.003 and 0.01 score within 0.1 dB but for
# suite-55-16's box, 0.26 dB better at 0.01; 0.03 took 1.4 dB from suite-56-1's near plane), the
# sweeps over every pattern pair's condition (20 as 8, within 0.1 dB), and the largest miss of a
# pair's share a row may have and be left as it is (the captures' noise, as _SHARE_REACH: fitting
# every row added 25-57% nonzeros on the suite scenes and lost suite-1-12's cylinder 0.75 dB, 0.05
# adds 2-10% and 0.4 dB). Our choices, on suite-56-1, suite-1206-6, suite-55-16, suite-97-8 and
# suite-1-12 (docs/accuracy.md "The ceiling").
_BAND_SEED, _BAND_SWEEPS, _BAND_MISS = 0.01, 8, 0.05


def _stamp(tensors: list[torch.Tensor]) -> list[tuple[torch.Tensor, int]]:
    """Each tensor with its version: what a result computed from them is kept against."""
    return [(t, t._version) for t in tensors]


def _unchanged(stamped: list[tuple[torch.Tensor, int]], tensors: list) -> bool:
    """Whether ``tensors`` are the very tensors :func:`_stamp` stamped, none changed in place since."""
    return len(stamped) == len(tensors) and all(a is b and v == b._version for (a, v), b in zip(stamped, tensors))


@dataclass
class StateCalibration:
    """What calibration recovered for one scene state, per projector.

    Attributes:
        prj_xy: list over projectors of :math:`(H, W, 2)` projector coordinates per camera pixel
            (NaN where unknown), e.g. :attr:`torchproj.calib.ProjectorCalibration.prj_xy`.
        weight: list over projectors of :math:`(H, W)` white minus black of that projector.
        projector_sizes: ``(width, height)`` per projector.
        blur: None, or per projector :math:`(H, W)` the diameter in cells of the disc over which a
            defocused lens spreads each cell's light where that pixel looks (0 = in focus; NaN
            where unknown, taken as 0), e.g. :func:`torchproj.calib.measure_blur`, which every
            full-sequence calibration runs (:attr:`~torchproj.calib.ProjectorCalibration.blur`).
            Only the ``area`` footprint uses it, where it is :data:`BLUR_MIN` cells or wider.
        colour_weight: None, or per projector :math:`(C, H, W)` white minus black per camera
            channel (``weight`` is their mean), e.g.
            :attr:`torchproj.calib.ProjectorCalibration.colour_contrast`. Where the surfaces are
            tinted or the projectors' white balance differs, one grey weight is wrong in every
            channel; :func:`build_channel_transports` gives each channel its own.
        edges: None, or per projector the :class:`~torchproj.calib.EdgePixels` beside depth edges
            and at the fringe of its map, e.g. :attr:`torchproj.calib.ProjectorCalibration.edges`.
            The ``area`` footprint gives such a pixel its surfaces' cells (two where it sees an
            object's outline and what lies behind), each by its share.
        shares: None, or per projector the :class:`~torchproj.calib.CellShares` its captures
            measured, e.g. :attr:`torchproj.calib.ProjectorCalibration.shares`. The ``area``
            footprint fits each row to them.
        dim: None, or per projector :math:`(H, W)` bool, the pixels of its map (``prj_xy``) that
            it lights too dimly to count as lit (:attr:`torchproj.calib.ProjectorCalibration.dim_xy`):
            its light there is part of the rows of pixels another projector lights, but such a
            pixel is no row of its own (:meth:`lit`).
    """

    prj_xy: list[torch.Tensor]
    weight: list[torch.Tensor]
    projector_sizes: list[tuple[int, int]]
    blur: list[torch.Tensor] | None = None
    colour_weight: list[torch.Tensor] | None = None
    edges: list[EdgePixels] | None = None
    shares: list[CellShares] | None = None
    dim: list[torch.Tensor] | None = None

    @classmethod
    def from_calibrations(cls, calibrations, weighting: str = "radiometric", camera=None,
                          projectors=None) -> "StateCalibration":
        """From one :class:`~torchproj.calib.ProjectorCalibration` per projector.

        Args:
            calibrations: per projector, its calibration in this state.
            weighting: ``"radiometric"`` (measured white minus black: fall-off, angle, albedo and
                vignetting in one number) or ``"geometric"`` (the paper's ``cos / d^2`` from
                triangulated points and normals; needs ``camera`` and ``projectors``, the rig's
                intrinsics and poses).
        """
        check(weighting in ("radiometric", "geometric"),
              f"weighting must be 'radiometric' or 'geometric', got {weighting!r}")
        prj_xy, dim = _with_dim([c.prj_xy for c in calibrations], [getattr(c, "dim_xy", None) for c in calibrations])
        sizes = [(c.cam_xy.shape[1], c.cam_xy.shape[0]) for c in calibrations]
        colour = None
        edges = [c.edges for c in calibrations] if all(getattr(c, "edges", None) is not None
                                                        for c in calibrations) else None
        shares = [c.shares for c in calibrations] if all(getattr(c, "shares", None) is not None
                                                          for c in calibrations) else None
        blur = [c.blur for c in calibrations] if all(getattr(c, "blur", None) is not None
                                                    for c in calibrations) else None
        if weighting == "radiometric":
            weight = [c.decoding.contrast.clamp_min(0) for c in calibrations]
            if all(getattr(c, "colour_contrast", None) is not None for c in calibrations):
                colour = [c.colour_contrast.clamp_min(0) for c in calibrations]
        else:
            check(camera is not None and projectors is not None,
                  "geometric weighting needs the camera and projectors (intrinsics and poses) to triangulate")
            from .geometric import geometric_weights

            weight = geometric_weights(prj_xy, camera, projectors)
        return cls(prj_xy, weight, sizes, blur=blur, colour_weight=colour, edges=edges, shares=shares, dim=dim)

    @classmethod
    def from_bundle(cls, bundle) -> dict[str, "StateCalibration"]:
        """State name -> calibration, from a :class:`~torchproj.calib.CalibrationBundle` (radiometric)."""
        sizes = [(w, h) for _, w, h in bundle.projectors]
        def colour(maps):  # bundles written before per-channel contrast, or from a grey camera, have none
            return [m["colour_contrast"].clamp_min(0) for m in maps] if all("colour_contrast" in m for m in maps) else None

        def every(read, maps):  # bundles from shortened sequences, or older ones, may have none
            found = [read(m) for m in maps]
            return found if all(e is not None for e in found) else None

        states = {}
        for name, maps in bundle.states.items():
            prj_xy, dim = _with_dim([m["prj_xy"] for m in maps], [m.get("dim_xy") for m in maps])
            states[name] = cls(prj_xy, [m["contrast"].clamp_min(0) for m in maps], sizes, colour_weight=colour(maps),
                               edges=every(edge_pixels, maps), shares=every(cell_shares_of, maps), dim=dim,
                               blur=every(lambda m: m.get("blur"), maps))
        return states

    def predict(self, light: list[torch.Tensor], black: torch.Tensor, footprint: str = "nearest") -> torch.Tensor:
        """What the camera should see when the projectors emit ``light``, by this calibration's model.

        Args:
            light: per projector, :math:`(C, H_j, W_j)` linear relative light (0 = black, 1 = white).
            black: :math:`(C, H, W)` the state's all-black capture.
            footprint: the cells each pixel sees, as in :func:`build_transport`.

        Returns:
            :math:`(C, H, W)`: black plus, per projector, its weight times the light of the cell(s)
            each pixel decoded to; each channel's own weight where :attr:`colour_weight` has as
            many channels as ``light``.
        """
        check(footprint in FOOTPRINTS, f"footprint must be one of {list(FOOTPRINTS)}, got {footprint!r}")
        out = black.float().clone()
        for j, (xy, weight, img) in enumerate(zip(self.prj_xy, self.weight, light)):
            w, h = self.projector_sizes[j]
            check_shape(img, f"light[{j}]", ["C", h, w])
            cells, weights = self._rows(j, torch.arange(xy.shape[0] * xy.shape[1]), footprint)
            flat = img.reshape(img.shape[0], -1)[:, cells.clamp_min(0)]  # (C, N, s); unused slots weigh 0
            seen = (flat * weights).sum(-1)
            if self.colour_weight is not None and self.colour_weight[j].shape[0] == img.shape[0] > 1:
                seen = seen * _channel_ratio(self.colour_weight[j].reshape(img.shape[0], -1), weight.reshape(-1))
            out += seen.reshape(out.shape)
        return out

    def _rows(self, j: int, pixels: torch.Tensor, footprint: str) -> tuple[torch.Tensor, torch.Tensor]:
        """Projector ``j``'s cells and weights :math:`(N, s)` for the flat camera ``pixels``
        :math:`(N,)`: the ``footprint``'s rows, edge pixels on their surfaces and fitted to the
        measured shares where this calibration has them (``area``)."""
        xy, weight = self.prj_xy[j].reshape(-1, 2)[pixels], self.weight[j].reshape(-1)[pixels]
        size = self.projector_sizes[j]
        if footprint != "area":
            return _footprint(xy, weight, size, footprint)
        slope = self._slope(j).reshape(-1, 2, 2)[pixels]
        blur = None
        if self.blur is not None:  # NaN where measure_blur could not tell: taken as in focus
            blur = torch.nan_to_num(self.blur[j].reshape(-1)[pixels].to(xy.dtype), nan=0.0).clamp_min(0)
        # Steep rows are sampled finely only where the fit has the checkerboard's condition: with the
        # per-axis shares alone, the coarse rows' missing cells are what _reach_shares adds on a limb.
        fine = self.shares is not None and self.shares[j].checker is not None
        cells, values = _footprint(xy, weight, size, footprint, slope, blur, fine)
        if self.edges is not None:
            maps = (self.prj_xy[j], self.blur[j]) if self._defocused(j) else None
            cells, values = _edge_rows(cells, values, self.edges[j], pixels, weight, size, blur, fine, maps)
        if self.shares is not None:
            cells, values = _reach_shares(cells, values, self.shares[j], pixels, size)
            values = _fit_shares(cells, values, self.shares[j], pixels, size)
            cells, values = _fit_band(cells, values, self.shares[j], pixels, size)
        return cells, values

    def _slope(self, j: int) -> torch.Tensor:
        """:func:`map_slope` of projector ``j``'s map, kept while the map is unchanged: a state's
        targets each ask for it."""
        xy = self.prj_xy[j]
        cache = self.__dict__.setdefault("_slopes", {})  # projector -> (its map, stamped; slope)
        kept = cache.get(j)
        if kept is None or not _unchanged(kept[0], [xy]):
            cache[j] = kept = (_stamp([xy]), map_slope(xy))
        return kept[1]

    def _defocused(self, j: int) -> bool:
        """Whether projector ``j`` was measured defocused, most of its pixels' discs a cell or wider
        (:data:`BLUR_MIN`), kept while its blur map is unchanged: a state's targets each ask. Only such
        a projector's edge rows read each surface's own blur: on a sharp one the blur measured beside
        outlines is noise of 1-1.5 cells."""
        if self.blur is None:
            return False
        blur = self.blur[j]
        cache = self.__dict__.setdefault("_defocus", {})  # projector -> (its blur map, stamped; defocused)
        kept = cache.get(j)
        if kept is None or not _unchanged(kept[0], [blur]):
            cache[j] = kept = (_stamp([blur]), float(torch.nanmedian(blur)) >= BLUR_MIN)
        return kept[1]

    def lit(self) -> torch.Tensor:
        """:math:`(H, W)` pixels lit (decoded, not only dimly: :attr:`dim`) by at least one projector.

        Kept while the maps and dim masks are the same tensors, unchanged: every target's rows ask
        for it (a tenth of ``footprint="auto"``'s decision on a small scene of three projectors)."""
        parts = [*self.prj_xy, *(self.dim or [])]
        if not all(isinstance(t, torch.Tensor) for t in parts):
            return self._lit()  # refused there, naming the part
        kept = self.__dict__.get("_kept_lit")  # (the parts, stamped; lit)
        if kept is None or not _unchanged(kept[0], parts):
            kept = self.__dict__["_kept_lit"] = (_stamp(parts), self._lit())
        return kept[1].clone()

    def _lit(self) -> torch.Tensor:
        mapped = [torch.isfinite(m).all(-1) for m in self.prj_xy]
        if self.dim is not None:
            check(len(self.dim) == len(mapped), f"dim holds {len(self.dim)} masks for {len(mapped)} projectors: give "
                                                "one per projector (or None)")
            for j, (m, d) in enumerate(zip(mapped, self.dim)):
                check_shape(d, f"dim[{j}]", list(m.shape))
            mapped = [m & ~d.to(device=m.device, dtype=torch.bool) for m, d in zip(mapped, self.dim)]
        return torch.stack(mapped).any(0)


def _with_dim(prj_xy: list[torch.Tensor], dim_xy: list[torch.Tensor | None]):
    """Per projector, its map of lit pixels joined with the dimly lit ones' (where every projector has
    them): the maps and :attr:`StateCalibration.dim` (None where some projector has no dim map)."""
    if any(d is None for d in dim_xy):
        return list(prj_xy), None
    dim = [torch.isfinite(d).all(-1) & ~torch.isfinite(m).all(-1) for m, d in zip(prj_xy, dim_xy)]
    return [torch.where(k[..., None], d, m) for m, d, k in zip(prj_xy, dim_xy, dim)], dim


@dataclass
class Target:
    """An image to show in one scene state, on a region of the camera view.

    Attributes:
        state: the scene state's name.
        image: :math:`(C, h, w)` float in [0, 1].
        mask: :math:`(H, W)` bool camera pixels of the surface(s) that show the image; None means
            every pixel the projectors light in that state.
        corners: :math:`(4, 2)` camera coordinates where the image's top-left, top-right,
            bottom-right and bottom-left corners go; None fits the image to the mask's bounding box.
        name: for reports.
    """

    state: str
    image: torch.Tensor
    mask: torch.Tensor | None = None
    corners: torch.Tensor | None = None
    name: str = ""

    def __post_init__(self):
        # The names key the calibrations and name the report's rows and files: a list or a tensor there
        # ended in a hash or truth-value error far from here.
        check(isinstance(self.name, str), f"target name must be a str, got {type(self.name).__name__}")
        check(isinstance(self.state, str),
              f"target {self.name!r} state must be the name of a state (a str), got {type(self.state).__name__}")
        # Every use takes the mask as bool (selection, &, indexing): one of 0/1 values becomes that here,
        # and one of other values is refused: a NaN or a painted 0.5 read as bool is True, the whole
        # camera or a blurred edge taken in.
        if self.mask is None:
            return
        mask = self.mask
        if not isinstance(mask, torch.Tensor):
            try:  # a numpy array, as an image library gives a painted mask
                mask = torch.as_tensor(mask)
            except (TypeError, ValueError, RuntimeError):
                raise InputError(f"target {self.name!r} mask must be a bool tensor, got {type(mask).__name__}") from None
        if mask.dtype != torch.bool:
            check(bool(((mask == 0) | (mask == 1)).all()),
                  f"target {self.name!r} mask must be bool, or hold only 0 and 1; got {mask.dtype} values "
                  "outside them (threshold a painted mask first: mask > 127 for 8-bit, mask > 0.5 for [0, 1])")
            mask = mask != 0
        self.mask = mask


def target_on_camera(target: Target, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Warp a target image onto camera pixels (kornia ``warp_perspective``).

    Args:
        target: the target.
        mask: :math:`(H, W)` the camera pixels the image may cover.

    Returns:
        ``values`` :math:`(C, H, W)` and ``covered`` :math:`(H, W)`: mask pixels the warped image
        reaches.
    """
    check(isinstance(target, Target), f"target must be a Target, got {type(target).__name__}")
    check_mask(mask, "mask (the camera's pixels)", ["H", "W"])
    sizes = check_image(target.image, f"target {target.name!r} image")
    h_img, w_img = sizes["H"], sizes["W"]
    check(min(h_img, w_img) >= 2, f"target {target.name!r} image is {w_img}x{h_img} pixels; a target image is "
                                  "stretched over its surfaces' pixels and needs at least 2 x 2")
    H, W = mask.shape
    if target.corners is not None:
        try:
            corners = torch.as_tensor(target.corners, dtype=torch.float32)
        except (TypeError, ValueError, RuntimeError):
            raise InputError(f"target {target.name!r} corners must be 4 (x, y) camera pixel coordinates, got "
                             f"{target.corners!r}") from None
        check_shape(corners, f"target {target.name!r} corners", [4, 2])
        _check_corners(target, corners)
    else:
        ys, xs = torch.nonzero(mask, as_tuple=True)
        check(len(xs) > 0, f"target {target.name!r}: its region holds no lit camera pixel in state {target.state!r}")
        _check_room(target, mask)  # before a warp onto a box that may have no height
        x0, x1, y0, y1 = float(xs.min()), float(xs.max()), float(ys.min()), float(ys.max())
        corners = torch.tensor([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    src = torch.tensor([[0.0, 0.0], [w_img - 1, 0.0], [w_img - 1, h_img - 1], [0.0, h_img - 1]])
    # The warp runs where the mask lives (a user's image is on the host, the maps may be on a GPU).
    dst_from_src = get_perspective_transform(src[None], corners.cpu()[None]).to(mask.device)  # 1x3x3, pixel centres
    # The image is what to show: data the solve reads, not a graph it extends (the solvers iterate in
    # place and take no gradient through their right-hand side), so one that requires grad is detached.
    image = torch.cat([target.image.detach().float().cpu(), torch.ones(1, h_img, w_img)])[None].to(mask.device)
    warped = warp_perspective(image, dst_from_src, (H, W), mode="bilinear", align_corners=True)[0]
    covered = mask & (warped[-1] > 0.999)
    check(target.corners is None or bool(covered.any()),
          f"target {target.name!r}: its corners {corners.tolist()} place the image on none of the lit camera pixels "
          f"of state {target.state!r} (camera pixel coordinates, x right and y down, within {W}x{H})")
    _check_room(target, covered)
    # At the image's outline the warp blends it with the zeros outside, by the share the last channel
    # (ones, warped alike) keeps: divided by that share, a covered pixel holds the image's own values (a
    # white image stays 1 there, not up to 0.1% darker and so no longer "one value").
    values = torch.where(covered, warped[:-1] / warped[-1].clamp_min(1e-6), warped[:-1])
    return values.clamp(0, 1), covered


def check_calibrations(calibrations, name: str = "calibrations") -> None:
    """``calibrations`` a dict of state name -> :class:`StateCalibration`; a whole calibration in its
    place (a bundle's, the virtual rig's) is pointed to its ``.states``."""
    check(isinstance(calibrations, Mapping) and all(isinstance(c, StateCalibration) for c in calibrations.values()),
          f"{name} must be a dict of state name -> StateCalibration, got {type(calibrations).__name__}"
          + (" (give its .states)" if hasattr(calibrations, "states") else ""))
    camera: dict = {}
    for state, cal in calibrations.items():
        _check_state_calibration(cal, f"{name}[{state!r}]", camera)


def _check_state_calibration(cal: StateCalibration, name: str, camera: dict) -> None:
    """A :class:`StateCalibration` a script made itself: per projector a map, a weight and a size, and
    the optional per-projector lists as long, all on one camera's pixels (``camera`` binds H and W
    across the states). Its own lists ended in unpacking and indexing errors deep in the build."""
    check(isinstance(cal.prj_xy, (list, tuple)) and len(cal.prj_xy) >= 1,
          f"{name}.prj_xy must be a list of one (H, W, 2) map per projector, got {type(cal.prj_xy).__name__}")
    count = len(cal.prj_xy)
    for field in ("weight", "projector_sizes"):
        value = getattr(cal, field)
        check(isinstance(value, (list, tuple)) and len(value) == count,
              f"{name}.{field} must be a list of one per projector ({count}, as prj_xy), got {type(value).__name__}"
              + (f" of {len(value)}" if isinstance(value, (list, tuple)) else ""))
    # The lists' lengths: shares', dim's and colour_weight's are checked where they are read, in their
    # own words; blur's and edges' here.
    for field, kind in (("blur", torch.Tensor), ("colour_weight", torch.Tensor), ("edges", EdgePixels),
                        ("shares", CellShares), ("dim", torch.Tensor)):
        value = getattr(cal, field)
        check(value is None or (isinstance(value, (list, tuple)) and all(v is None or isinstance(v, kind) for v in value)
                                and (len(value) == count or field not in ("blur", "edges"))),
              f"{name}.{field} must be None or a list of one {kind.__name__} (or None) per projector ({count}), got "
              f"{type(value).__name__}" + (f" of {len(value)}" if isinstance(value, (list, tuple)) else ""))
    for j in range(count):
        check_shape(cal.prj_xy[j], f"{name}.prj_xy[{j}]", [*camera.get("size", ("H", "W")), 2])
        camera.setdefault("size", tuple(cal.prj_xy[j].shape[:2]))
        check(cal.prj_xy[j].is_floating_point(), f"{name}.prj_xy[{j}] must be float coordinates, got {cal.prj_xy[j].dtype}")
        check_shape(cal.weight[j], f"{name}.weight[{j}]", list(camera["size"]))
        check_projector_size(cal.projector_sizes[j], f"{name}.projector_sizes[{j}]")


def check_targets(targets) -> None:
    """``targets`` a list (or tuple) of at least one :class:`Target`: one Target alone is named as such."""
    check(isinstance(targets, (list, tuple)) and all(isinstance(t, Target) for t in targets),
          f"targets must be a list of Target, got {type(targets).__name__}"
          + (f" of {sorted({type(t).__name__ for t in targets})}" if isinstance(targets, (list, tuple)) else ""))
    check(len(targets) >= 1, "targets must hold at least one Target")


def _target_channels(targets: list[Target]) -> int:
    """The channel count all ``targets``' images share, each image checked first (so that a wrong one,
    an :math:`(H, W)` image, a 4-channel one, a list, is named as itself, not as a count that differs)."""
    check_targets(targets)
    channels = {check_image(t.image, f"target {t.name or i!r} image")["C"] for i, t in enumerate(targets)}
    check(len(channels) == 1, f"all targets must have the same number of channels, got {sorted(channels)}: give each "
                              "the camera's (torchproj.pipeline.image_with_channels converts an image, grey repeated to "
                              "three, colour to luminance)")
    return channels.pop()


def _check_corners(target: Target, corners: torch.Tensor) -> None:
    """Corners :math:`(4, 2)` that go once around a quadrilateral with area: each turn from one edge to
    the next the same way (a mirrored image turns the other way throughout). A crossed order (a bow
    tie) would fold the image over itself, and a line or a point stretches it over nothing."""
    check(bool(torch.isfinite(corners).all()), f"target {target.name!r}: corners must be finite, got {corners.tolist()}")
    edges = corners.roll(-1, 0) - corners
    turns = edges[:, 0] * edges.roll(-1, 0)[:, 1] - edges[:, 1] * edges.roll(-1, 0)[:, 0]
    check(bool((turns > 0).all() or (turns < 0).all()),
          f"target {target.name!r}: corners {corners.tolist()} do not go once around a quadrilateral with area; give "
          "the image's top-left, top-right, bottom-right and bottom-left corners in that order")


def _check_room(target: Target, covered: torch.Tensor) -> None:
    """Refuse a target the camera sees on too few pixels to hold an image: its pixels (``covered``
    :math:`(H, W)` bool) must span at least SSIM's window (7 x 7) each way, or every score of it
    would fail after the solve."""
    rows, cols = torch.nonzero(covered.any(1))[:, 0], torch.nonzero(covered.any(0))[:, 0]
    wide = int(cols[-1] - cols[0]) + 1 if len(cols) else 0
    high = int(rows[-1] - rows[0]) + 1 if len(rows) else 0
    check(min(wide, high) >= WINDOW,
          f"target {target.name!r}: the camera sees it on {int(covered.sum())} lit pixels spanning {wide}x{high} "
          f"in state {target.state!r}, too few to show an image (at least {WINDOW}x{WINDOW}); bring its surfaces "
          "into the camera's view, clear of the surfaces in front of them, or leave the target out")


def kept_target_on_camera(target: Target, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`target_on_camera`, its last warp kept on the target and given again (a copy) while its
    image (the same tensor, unchanged), its corners and the mask are.

    For the targets a model is built for: ``footprint="auto"`` decides on nearest's rows, then builds
    the chosen model's rows of the same targets, and the run scores them, and each asks for the warp
    (with the lit pixels, a third to a half of the decision's time on the procedural suite's small
    scenes). It holds the warp as long as the target lives (about 11 MB for a grey target of the
    default camera), so a new image for a built model (:func:`retarget_rhs`: frames of a video)
    is warped by :func:`target_on_camera`, keeping nothing."""
    values, covered = _kept_warp(target, mask)
    if values is None:
        values, covered = target_on_camera(target, mask)
        target.__dict__["_on_camera"] = (_stamp([target.image]), _corners_key(target), mask.clone(), values, covered)
    return values.clone(), covered.clone()


def _corners_key(target: Target) -> tuple | None:
    """The corners' values (a list the user may change in place); where they are no numbers, a key
    equal to none kept, so that :func:`target_on_camera` warps anew and refuses them."""
    if target.corners is None:
        return None
    try:
        return tuple(torch.as_tensor(target.corners).reshape(-1).tolist())
    except (TypeError, ValueError, RuntimeError):
        return (object(),)  # equal to no kept key: warped anew, and refused there


def _kept_warp(target: Target, mask: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """The target's kept warp where its image, corners and ``mask`` are those it was made for."""
    kept = target.__dict__.get("_on_camera")  # (the image, stamped; corners, mask, values, covered)
    if (kept is None or not _unchanged(kept[0], [target.image]) or not isinstance(mask, torch.Tensor)
            or (kept[2].device, kept[2].dtype, kept[2].shape) != (mask.device, mask.dtype, mask.shape)
            or kept[1] != _corners_key(target) or not torch.equal(kept[2], mask)):
        return None, None
    return kept[3], kept[4]


def group_rows(columns: torch.Tensor) -> tuple[torch.Tensor, int]:
    """Group identical rows of an integer matrix :math:`(N, s)` (exact lexicographic sort).

    Returns:
        ``group`` :math:`(N,)` group index of each row, and the number of groups.
    """
    check_shape(columns, "columns", ["N", "S"])
    order = torch.arange(columns.shape[0], device=columns.device)
    for k in range(columns.shape[1] - 1, -1, -1):  # stable sorts from the last key to the first
        order = order[torch.sort(columns[order, k], stable=True).indices]
    ordered = columns[order]
    new = torch.ones(columns.shape[0], dtype=torch.bool, device=columns.device)
    new[1:] = (ordered[1:] != ordered[:-1]).any(1)
    group_sorted = torch.cumsum(new.long(), 0) - 1
    group = torch.empty_like(group_sorted)
    group[order] = group_sorted
    return group, int(new.sum())


def _area_cells(u: torch.Tensor, slope: torch.Tensor, ok: torch.Tensor, size: tuple[int, int],
                blur: torch.Tensor | None = None, fine: bool = False):
    """The cells a camera pixel's square covers, carried through the local ``slope``, and the share
    of the pixel each lights (sampled at ``_AREA_SAMPLES`` squared points; with ``fine``,
    ``_STEEP_SAMPLES`` squared where the square spans more than ``_STEEP_EXTENT`` cells along a
    projector axis): :math:`(N, s)` each.

    With ``blur`` :math:`(N,)` (disc diameters in cells), each sample of a row whose disc is
    ``BLUR_MIN`` cells or wider also spreads over its disc: the light a pixel sees through a
    defocused lens is the mean of the cells within that circle. Narrower discs are taken as sharp
    (:attr:`StateCalibration.blur`). Blurred rows of pixels that span a cell or less take
    ``_BLUR_SAMPLES`` squared points, each already spread over up to 16 disc points."""
    blurred = torch.zeros_like(ok) if blur is None or not blur.numel() else blur >= BLUR_MIN
    extent = slope.abs().sum(-1).amax(-1)  # cells per camera pixel along the wider projector axis
    steep = torch.zeros_like(ok) if not fine or _STEEP_SAMPLES == _AREA_SAMPLES else (extent > _STEEP_EXTENT) & ~blurred
    plain = ~blurred & ~steep
    if bool(plain.all()):
        return _sampled_cells(u, slope, ok, size, None, _AREA_SAMPLES)
    # Steep and blurred rows in smaller passes: their samples' temporaries as large as the others'.
    # (rows, blur or None, samples, rows per pass)
    groups = [(torch.nonzero(plain)[:, 0], None, _AREA_SAMPLES, _AREA_CHUNK),
              (torch.nonzero(steep)[:, 0], None, _STEEP_SAMPLES, max(1, _AREA_CHUNK * _AREA_SAMPLES ** 2 // _STEEP_SAMPLES ** 2)),
              (torch.nonzero(blurred & (extent <= 1))[:, 0], blur, _BLUR_SAMPLES, _BLUR_CHUNK),
              (torch.nonzero(blurred & ~(extent <= 1))[:, 0], blur, _AREA_SAMPLES, _BLUR_CHUNK)]
    parts, order = [], []
    for rows, disc, samples, step in groups:
        for i in rows.split(step):
            parts.append(_sampled_cells(u[i], slope[i], ok[i], size, None if disc is None else disc[i], samples))
            order.append(i)
    cells, values = _stack_rows([c for c, _ in parts], [v for _, v in parts])
    back = torch.argsort(torch.cat(order))  # back to the rows' own order
    return cells[back], values[back]


def _sampled_cells(u: torch.Tensor, slope: torch.Tensor, ok: torch.Tensor, size: tuple[int, int],
                   blur: torch.Tensor | None, samples: int):
    """:func:`_area_cells` with the square sampled at ``samples`` squared points."""
    w, h = size
    offset = pixel_square(samples, u.dtype, u.device)  # (S, 2) camera-pixel offsets from the centre
    # Cell centres at integers (conventions module): a point's cell is floor(u + 0.5), kept in float
    # (exact for any projector size) and turned to int32 once, for a fast sort.
    points = torch.einsum("nij,sj->nsi", torch.nan_to_num(slope), offset).add_(u[:, None, :] + 0.5)
    if blur is not None and blur.numel():
        count = points_for_diameter(float(blur.max()))  # as the virtual rig samples a circle of confusion
        if count > 1:
            disc = disc_points(count, u.device).to(u.dtype)  # (K, 2)
            spread = blur[:, None, None, None] * disc  # (N, 1, K, 2)
            points = (points[:, :, None, :] + spread).reshape(u.shape[0], -1, 2)
            offset = offset.repeat_interleave(count, 0)
    points = points.floor_()
    x, y = points.unbind(-1)
    inside = ok[:, None] & (x >= 0) & (x < w) & (y >= 0) & (y < h)
    # Each row's light is shared among its samples on the projector. A sample past the projector's
    # edge sees no light of it, and the pixel's measured white minus black (the row's weight) is
    # the light of the others alone: where the surface runs on past the projector's field, the
    # samples on it take the whole weight, not their count over all the square's.
    share = (1.0 / inside.sum(1, keepdim=True).clamp_min(1)).to(u.dtype)

    def by_sorting(xs, ys, lit, each):
        flat = torch.where(lit, ys * w + xs, -1.0).to(torch.int32)
        return _combine(flat, torch.where(flat >= 0, each, 0.0).to(u.dtype))

    # Most rows' samples fall in a few cells' window: binned there, no sort is needed (below). Rows
    # whose window is wider (a grazing face, a wide disc) are combined by sorting their samples.
    if x.numel() < _BINNED_MIN:
        return by_sorting(x, y, inside, share)
    near, x0, y0, span = _windows(x, y, inside)
    if bool(near.all()):
        return _binned(x, y, inside, x0, y0, span, share, w)
    close, wide = torch.nonzero(near)[:, 0], torch.nonzero(~near)[:, 0]
    parts = [_binned(x[close], y[close], inside[close], x0[close], y0[close], span, share[close], w),
             by_sorting(x[wide], y[wide], inside[wide], share[wide])]
    cells, values = _stack_rows([c for c, _ in parts], [v for _, v in parts])
    back = torch.argsort(torch.cat([close, wide]))  # back to the rows' own order
    return cells[back], values[back]


# A row's samples are binned on a window of cells at most this many per axis (else sorted), where a
# pass holds _BINNED_MIN samples or more: binning takes more steps than a sort, which small passes
# (a small scene's) pay for in overhead rather than arithmetic.
_WINDOW, _BINNED_MIN = 8, 1 << 16


def _windows(x: torch.Tensor, y: torch.Tensor, inside: torch.Tensor):
    """Which rows' samples :math:`(N, S)` (cells ``x``, ``y``, as whole floats; ``inside`` the
    projector) lie within ``_WINDOW`` cells per axis, each row's first cell ``x0``, ``y0``, and the
    window :math:`(k_x, k_y)` that holds all of those rows."""
    far = torch.tensor(float("inf"), dtype=x.dtype, device=x.device)
    x0, y0 = torch.where(inside, x, far).amin(1), torch.where(inside, y, far).amin(1)
    x0, y0 = torch.where(torch.isfinite(x0), x0, 0.0), torch.where(torch.isfinite(y0), y0, 0.0)
    kx = torch.where(inside, x - x0[:, None], 0.0).amax(1) + 1
    ky = torch.where(inside, y - y0[:, None], 0.0).amax(1) + 1
    near = (kx <= _WINDOW) & (ky <= _WINDOW)
    span = (int(kx[near].max()), int(ky[near].max())) if bool(near.any()) else (1, 1)
    return near, x0, y0, span


def _binned(x, y, inside, x0, y0, span: tuple[int, int], share: torch.Tensor, w: int):
    """:func:`_combine` for samples :math:`(N, S)` that lie within a ``span`` window of cells from
    each row's ``x0``, ``y0``: each sample's ``share`` (its row's, :math:`(N, 1)`) added to its
    cell's bin, the lit bins kept.
    Bins go row by row of the window, so each row's cells come out ascending, as sorting gives them."""
    kx, ky = span
    bins = kx * ky
    local = torch.where(inside, (y - y0[:, None]) * kx + (x - x0[:, None]), float(bins)).long()
    light = torch.zeros(x.shape[0], bins + 1, dtype=x.dtype, device=x.device)
    light.scatter_add_(1, local, share.expand_as(x).contiguous())
    light = light[:, :bins]
    offsets = torch.arange(bins, device=x.device)
    cells = ((y0.long()[:, None] + offsets // kx) * w + x0.long()[:, None] + offsets % kx)
    return _compact(torch.where(light > 0, cells, -1), light)


def _compact(cells: torch.Tensor, values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows :math:`(N, k)` with their used slots (cell >= 0) moved first, in order, and as many slots
    as the fullest row uses (at least one): the layout :func:`_combine` gives."""
    used = cells >= 0
    slot = used.cumsum(1) - 1
    slots = max(int(slot[:, -1].max()) + 1 if slot.numel() else 1, 1)
    slot = torch.where(used, slot, slots)
    out = torch.full((cells.shape[0], slots + 1), -1, dtype=torch.int64, device=cells.device).scatter_(1, slot, cells.long())
    total = torch.zeros(cells.shape[0], slots + 1, dtype=values.dtype, device=values.device).scatter_(
        1, slot, torch.where(used, values, 0))
    return out[:, :slots], total[:, :slots]


def _combine(cells: torch.Tensor, values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each row's distinct cells (int64, ascending and first, -1 = none after them) and their values
    summed: :math:`(N, s)` each, from rows of cells that may repeat :math:`(N, k)` (int32 sorts
    faster, where the cells fit)."""
    last = torch.iinfo(cells.dtype).max  # unused slots sort after every cell
    cells, order = torch.sort(torch.where(cells >= 0, cells, last), dim=1)
    values = values.gather(1, order)
    run = torch.zeros_like(cells)
    run[:, 1:] = (cells[:, 1:] != cells[:, :-1]).cumsum(1)
    slots = int(run.max()) + 1 if run.numel() else 1
    cells = torch.where(cells == last, -1, cells)
    out = torch.full((cells.shape[0], slots), -1, dtype=torch.int64, device=cells.device).scatter_(1, run, cells.long())
    total = torch.zeros(cells.shape[0], slots, dtype=values.dtype, device=values.device).scatter_add_(
        1, run, torch.where(cells >= 0, values, 0))
    return out, total


def _surface_blur(prj_xy: torch.Tensor, blur: torch.Tensor, edge: torch.Tensor, pixels: torch.Tensor,
                  xy: torch.Tensor) -> torch.Tensor:
    """:math:`(n, 2)` each surface's defocus disc (cells) at the edge ``pixels`` :math:`(n,)`: the
    ``blur`` :math:`(H, W)` of the pixel within two whose map coordinate (``prj_xy`` :math:`(H, W, 2)`)
    is nearest the surface's ``xy`` :math:`(n, 2, 2)`, among those that are no ``edge`` pixel
    :math:`(H, W)` (whose blur mixes both surfaces): a pixel that sees that surface alone. NaN where
    no such pixel is mapped nearer that surface than the other (the surface was seen only dimly).

    An outline pixel sees an object and what lies behind it, at two depths, so through two discs: a
    lens focused on the object blurs the surface behind. The pixel's own measured blur is one of the
    two (or neither), so each surface takes its own from a pixel that sees it alone. Our choice (the
    paper has no defocus), taken on projectors measured defocused only (``StateCalibration._rows``):
    suite-2718-12's and suite-2718-4's spheres 0.24 and 0.25 dB nearer their ceiling
    (docs/accuracy.md)."""
    height, width = blur.shape
    step = torch.arange(-2, 3, device=pixels.device)
    dy, dx = (t.reshape(-1) for t in torch.meshgrid(step, step, indexing="ij"))
    y, x = pixels // width, pixels % width
    cy, cx = (y[:, None] + dy).clamp(0, height - 1), (x[:, None] + dx).clamp(0, width - 1)
    there = prj_xy[cy, cx].to(xy.dtype)  # (n, 25, 2)
    far = (there[:, None] - xy[:, :, None]).abs().amax(-1)  # (n, 2, 25)
    far = torch.nan_to_num(far, nan=float("inf")).masked_fill(edge[cy, cx][:, None], float("inf"))
    best, near = far.min(-1)  # (n, 2)
    other = far.flip(1).gather(2, near[..., None])[..., 0]  # the chosen pixel's distance to the other surface
    seen = torch.nan_to_num(blur[cy, cx].to(xy.dtype), nan=0.0).clamp_min(0)  # (n, 25); NaN: in focus
    return torch.where(torch.isfinite(best) & (best <= other), seen.gather(1, near), float("nan"))


def _edge_rows(cells: torch.Tensor, values: torch.Tensor, edges: EdgePixels, pixels: torch.Tensor,
               weight: torch.Tensor, size: tuple[int, int], blur: torch.Tensor | None = None, fine: bool = False,
               maps: tuple[torch.Tensor, torch.Tensor] | None = None):
    """The ``area`` rows of those camera ``pixels`` :math:`(N,)` that are ``edges``: each surface's
    cells, the pixel's square carried through that surface's slope and spread by its blur, by its
    share of the pixel's ``weight``. Other rows stay as they are. ``maps``: the projector's map and
    blur map :math:`(H, W, 2)`, :math:`(H, W)`, from which each surface's blur is read
    (:func:`_surface_blur`); None: the pixels' ``blur`` for both."""
    if not len(edges) or not pixels.numel():
        return cells, values
    order = torch.argsort(edges.pixel)
    known = edges.pixel[order]
    at = torch.searchsorted(known, pixels).clamp(max=known.numel() - 1)
    hit = torch.nonzero(known[at] == pixels)[:, 0]
    if not hit.numel():
        return cells, values
    entry = order[at[hit]]
    lit = weight[hit] > 0
    own = None
    if blur is not None:
        own = blur[hit][:, None].expand(-1, 2)
        if maps is not None:
            edge = torch.zeros(maps[1].numel(), dtype=torch.bool, device=pixels.device)
            edge[edges.pixel] = True
            found = _surface_blur(maps[0], maps[1], edge.reshape(maps[1].shape), pixels[hit],
                                  edges.xy[entry].to(values.dtype))
            own = torch.where(torch.isnan(found), own, found)
    parts = [_area_cells(edges.xy[entry, k].to(values.dtype), edges.slope[entry, k].to(values.dtype), lit, size,
                         None if own is None else own[:, k].contiguous(), fine) for k in (0, 1)]
    share = edges.share[entry].to(values.dtype) * torch.where(lit, weight[hit], 0.0)[:, None]
    two_cells, two_values = _combine(torch.cat([parts[0][0], parts[1][0]], 1),
                                     torch.cat([parts[0][1] * share[:, :1], parts[1][1] * share[:, 1:]], 1))
    width = max(cells.shape[1], two_cells.shape[1])
    cells, values = _widen(cells, values, width)
    cells[hit], values[hit] = _widen(two_cells, two_values, width)
    return cells, values


def _reach_shares(cells: torch.Tensor, values: torch.Tensor, shares: CellShares, pixels: torch.Tensor,
                  size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """The rows :math:`(N, s)` of those camera ``pixels`` :math:`(N,)` whose captures measured light
    across an edge of the decoded cell where the row holds none, given the cells across that edge.

    The parallelogram comes from the map's slope, a mean over two pixels either side. Where a
    curved surface turns away from the camera (a cylinder's limb) the slope grows within those
    pixels, and on the outline only the pixels on one side count: the slope is underestimated and
    the parallelogram falls short of cells the pixel sees. On ``box_cylinders`` up to a third of such a
    pixel's light comes from a cell its row does not hold, and :func:`_fit_shares`, which only
    rescales the cells a row has, cannot put it there. So where the measured share across an edge
    (:attr:`~torchproj.calib.CellShares.across`) exceeds ``_SHARE_REACH`` and the row holds no cell
    past it, each of the row's cells on the decoded cell's column (row, for ``y``) gains its
    neighbour across the edge, seeded in proportion so that the new cells keep the column's
    profile along the other axis (axis by axis, so a row short of an ``x`` and a ``y`` edge also
    gains the cell across both); :func:`_fit_shares` then sets their share. The row's total (its
    white minus black) is kept.

    Light two cells away reads otherwise. Gray code flips bit 0 at every odd step, so of ``n - 2``
    and ``n + 2`` the one of ``n``'s parity class (``n - 2`` for an even ``n``, ``n + 2`` for an odd
    one) differs from ``n`` in exactly the bits of ``n``'s two edges: its light reads as light
    across both edges, as light on ``n - 1`` and ``n + 1`` would. The checkerboard tells them apart
    (:attr:`~torchproj.calib.CellShares.checker`: cells ``n +- 1`` are of the other parity,
    ``n +- 2`` of the same): where its share is below what either edge measured by more than
    ``_SHARE_REACH``, the row's cells on the decoded cell's column gain that cell too. On
    ``box_cylinders`` these are the pixels on the cylinders' outline as the camera sees it, where the
    surface turns away within the pixel and the slope, taken from the inner side only, falls far
    short: their rows held a third of their light on the wrong cells.

    Defocus is left alone: a pixel whose light reached past cells ``n +- 1`` on that axis
    (:attr:`~torchproj.calib.CellShares.outside`), or was measured across all four edges (a disc
    wider than the pixel every way; a limb or a steep face stretches a pixel's footprint one way),
    gains nothing. Blurred light comes from past the four neighbours too, and the neighbours alone
    would take all of it: on ``paper_defocus`` widening such rows costs the near target 0.034 SSIM.
    Our choice (the paper models one cell per pixel): docs/accuracy.md "The ceiling" measures it against rows
    left short.
    """
    if not cells.numel():
        return cells, values
    if cells.shape[0] > _AREA_CHUNK:  # (N, s) masks per edge: chunks keep them small
        parts = [_reach_shares(cells[i:i + _AREA_CHUNK], values[i:i + _AREA_CHUNK], shares, pixels[i:i + _AREA_CHUNK],
                               size) for i in range(0, cells.shape[0], _AREA_CHUNK)]
        return _stack_rows([c for c, _ in parts], [v for _, v in parts])
    w = size[0]
    cell = shares.cell.reshape(-1, 2)[pixels].long()
    across = shares.across.reshape(-1, 2, 2)[pixels].to(values.dtype)
    outside = shares.outside.reshape(-1, 2)[pixels] > _SHARE_OUTSIDE
    checker = None if shares.checker is None else shares.checker.reshape(-1)[pixels].to(values.dtype)
    used, total = cells >= 0, values.sum(1)
    row = torch.div(cells, w, rounding_mode="floor")
    short = []  # per axis, per side: the rows short of that edge of the decoded cell
    for axis, coord in enumerate((cells - row * w, row)):
        for side, step in enumerate((-1, 1)):
            share = across[:, axis, side]
            held = torch.where(used & ((coord - cell[:, axis, None]) * step >= 1), values, 0.0).sum(1)
            short.append(torch.isfinite(share) & (share > _SHARE_REACH) & (held <= _SHARE_TOL * total) & (total > 0)
                         & ~outside[:, axis] & (cell[:, axis] >= 0))
    disc = (across > _SHARE_REACH).reshape(-1, 4).all(1)
    # The cell two away whose light reads as light across both edges (docstring): its direction per
    # axis, -1 for an even cell, +1 for an odd one, and the rows where the checkerboard puts it there.
    towards = [2 * (cell[:, axis] % 2 == 1).long() - 1 for axis in (0, 1)]
    twice = []
    for axis, far in enumerate(towards):
        lo, hi = across[:, axis, 0], across[:, axis, 1]
        inside = (cell[:, axis] + 2 * far >= 0) & (cell[:, axis] + 2 * far < size[axis])
        coord = cells - row * w if axis == 0 else row
        held = torch.where(used & ((coord - cell[:, axis, None]) * far[:, None] >= 2), values, 0.0).sum(1)
        twice.append(torch.zeros_like(inside) if checker is None else
                     torch.isfinite(lo) & torch.isfinite(hi) & (torch.minimum(lo, hi) > checker + _SHARE_REACH)
                     & inside & (held <= _SHARE_TOL * total) & (total > 0) & (cell[:, axis] >= 0))
    rows = torch.nonzero((torch.stack(short).any(0) & ~disc) | torch.stack(twice).any(0))[:, 0]
    if not rows.numel():
        return cells, values
    # Axis by axis, so that a row short of an x and a y edge also gains the cell across both: light
    # measured across both comes partly from that corner, and without it the conditions conflict.
    grown, seeded = cells[rows], values[rows]
    for axis in (0, 1):
        coord = grown % w if axis == 0 else torch.div(grown, w, rounding_mode="floor")
        column = (grown >= 0) & (coord == cell[rows, axis, None])
        new_cells, new_values = [grown], [seeded]
        unit = 1 if axis == 0 else w
        for side, step in enumerate((-1, 1)):
            # The edge is not the projector's border (the share is finite), so the neighbour is a cell.
            gain = short[2 * axis + side][rows, None] & column & ~disc[rows, None]
            share = across[rows, axis, side, None].clamp(max=0.5)  # a seed: _fit_shares sets the split
            new_cells.append(torch.where(gain, grown + step * unit, -1))
            new_values.append(torch.where(gain, seeded * share / (1 - share), 0.0))
        far = towards[axis][rows, None]
        gain = twice[axis][rows, None] & column
        share = torch.minimum(across[rows, axis, 0], across[rows, axis, 1])[:, None].clamp(max=0.5)
        new_cells.append(torch.where(gain, grown + 2 * far * unit, -1))
        new_values.append(torch.where(gain, seeded * share / (1 - share), 0.0))
        grown, seeded = _combine(torch.cat(new_cells, 1), torch.cat(new_values, 1))
    seeded = seeded * (total[rows] / seeded.sum(1))[:, None]
    width = max(cells.shape[1], grown.shape[1])
    cells, values = _widen(cells, values, width)
    cells[rows], values[rows] = _widen(grown, seeded, width)
    return cells, values


def _fit_shares(cells: torch.Tensor, values: torch.Tensor, shares: CellShares, pixels: torch.Tensor,
                size: tuple[int, int]) -> torch.Tensor:
    """The rows' values :math:`(N, s)`, rescaled so that each row puts the measured share of its light
    across each edge of the pixel's decoded cell (:class:`~torchproj.calib.CellShares`).

    The share across an edge is exactly the share of the pixel's light on the cells where that
    edge's pattern pair shows the other stripe than on the decoded cell; so each measured share is
    one linear condition on the row, whatever its footprint. Iterative proportional fitting meets
    them: per condition, the row's cells on either side are scaled to the measured split, keeping
    the row's total (its white minus black); one sweep over the four conditions settles them
    (``_SHARE_SWEEPS``). Cells the row does not have are not added here: the parallelogram says where
    the light may fall, the captures how it is split (where it falls short of an edge the captures
    saw light across, :func:`_reach_shares` has already added the cells). A condition the row cannot meet (all its light
    on one side), or that was not measured (an undecoded pixel, the projector's border), is left out;
    so is a row whose
    pixel saw light past cells ``n +- 1`` (:attr:`~torchproj.calib.CellShares.outside`) where the
    row has no cell: defocus spread that light, and its shares would pull the row's light onto the
    wrong cells. Where the shares carry a checkerboard's (:attr:`~torchproj.calib.CellShares.checker`),
    it is a fifth condition: the share on the cells of the other parity than the decoded cell's,
    which says how the two axes' splits combine.

    Our choice, not the paper's (it models one cell per pixel): the virtual rig's camera samples a
    pixel at 3 x 3 points, a real one integrates it with its own sensitivity and lens blur; the
    shares measure either, the parallelogram neither (docs/accuracy.md "The ceiling").
    """
    if not cells.numel():
        return values
    if cells.shape[0] > _AREA_CHUNK:  # the conditions are (N, s) masks: chunks keep them small
        return torch.cat([_fit_shares(cells[i:i + _AREA_CHUNK], values[i:i + _AREA_CHUNK], shares,
                                      pixels[i:i + _AREA_CHUNK], size) for i in range(0, cells.shape[0], _AREA_CHUNK)])
    cell = shares.cell.reshape(-1, 2)[pixels]  # -1 where the pixel has no cell: no share was measured there
    cells = cells.to(torch.int32)
    across = shares.across.reshape(-1, 2, 2)[pixels].to(values.dtype)
    outside = shares.outside.reshape(-1, 2)[pixels] > _SHARE_OUTSIDE
    used, w = cells >= 0, size[0]
    row = torch.div(cells, w, rounding_mode="floor")
    conditions, wider = [], torch.zeros(cells.shape[0], dtype=torch.bool, device=cells.device)
    column = cells - row * w
    for axis, coord in enumerate((column, row)):
        own = cell[:, axis]
        gray = own ^ (own >> 1)
        stripe = coord ^ (coord >> 1)
        reach = (used & ((coord - own[:, None]).abs() >= 2)).any(1)  # the row holds cells past n +- 1
        wider |= outside[:, axis] & ~reach
        for side, step in enumerate((-1, 1)):
            other = own + step
            bit = (gray ^ (other ^ (other >> 1))).clamp_min(1).to(torch.float64).log2().round().to(torch.int32)
            far = used & ((((stripe ^ gray[:, None]) >> bit[:, None]) & 1) == 1)
            conditions.append((far, across[:, axis, side]))
    sweeps = _SHARE_SWEEPS
    if shares.checker is not None:
        # The checkerboard's condition couples the axes: cells of one parity lie on both sides of
        # every edge, so the conditions no longer nearly separate and the fit needs more sweeps.
        parity = (cell[:, 0] + cell[:, 1]) % 2
        conditions.append((used & ((column + row) % 2 != parity[:, None]),
                           shares.checker.reshape(-1)[pixels].to(values.dtype)))
        sweeps = _CHECKER_SWEEPS
    # Once for every sweep: each condition's cells as 1 / 0 and the rest as 1 / 0 (products select
    # faster than torch.where with a broadcast operand, and exactly: x 1 + y 0 is x), and its share
    # NaN where it does not apply.
    conditions = [(ones := far.to(values.dtype), 1 - ones, torch.where(~wider, share, float("nan")))
                  for far, share in conditions]
    values, tiny = values.clone(), torch.finfo(values.dtype).tiny  # scaled in place below
    for _ in range(sweeps):
        for far, near, share in conditions:
            # Each side's part of the row as it now is, both summed: taken of the total the row began
            # with, or as 1 minus the far part (float32 keeps 1 - 0.999999 to a few per cent), a
            # step's rounding compounded until a row of 0.19 held 150 (suite-55-9).
            part, rest = torch.mul(values, far).sum(1), torch.mul(values, near).sum(1)
            whole = (part + rest).clamp_min_(tiny)
            part, rest = part.div_(whole), rest.div_(whole)
            on = (part > _SHARE_TOL) & (rest > _SHARE_TOL) & torch.isfinite(share)
            up = torch.where(on, share / part.clamp_min(_SHARE_TOL), 1.0)
            down = torch.where(on, (1 - share) / rest.clamp_min(_SHARE_TOL), 1.0)
            values.mul_(torch.mul(near, down[:, None]).addcmul_(far, up[:, None]))  # up on the far cells, down elsewhere
    return values


def _fit_band(cells: torch.Tensor, values: torch.Tensor, shares: CellShares, pixels: torch.Tensor,
              size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """The rows :math:`(N, s)` of those camera ``pixels`` :math:`(N,)` that lie beside an outline
    (:attr:`~torchproj.calib.CellShares.band`), widened by the cells around their own and fitted to
    the share of the pixel's light that every Gray-code pattern pair measured there
    (:attr:`~torchproj.calib.CellShares.band_white`). Other rows stay as they are.

    Beside an outline a camera pixel may see part of an object and part of what lies behind it (a
    jump of a cell or two, which :func:`~torchproj.calib.find_edge_pixels` does not take for two
    surfaces), or part of an object and nothing: its light falls on cells of two slopes, or on part
    of the parallelogram only, and the cells near the row's edge are wrong by up to a cell. Each
    pattern pair is one linear condition on the row, as in :func:`_fit_shares`: the share of its
    light on the cells the pair shows white. Neighbouring cells differ in one pair, so the pairs
    say how the light splits across the cell edges the row spans, along each axis, where the four
    shares about the decoded cell say it for that cell's edges alone (not wholly: the finest pair
    flips at every other edge, so two edges two cells apart share one condition). The row first gains
    the cells around its own (each seeded with ``_BAND_SEED`` of the row's light, so that the fit,
    which only scales light, can move light there; a cell no pair tells apart from its neighbours
    keeps about its seed), then ``_BAND_SWEEPS`` sweeps of iterative proportional fitting meet the
    conditions, the row's total kept, and the row keeps its cells of most light, as many as the
    other rows have slots. A row that already gives every pair's share within ``_BAND_MISS`` is
    left as it is. Our choice, not the paper's (it models one cell per pixel); measured in
    docs/accuracy.md ("The ceiling").
    """
    if shares.band is None or not shares.band.numel() or not pixels.numel():
        return cells, values
    band = shares.band.to(pixels.device)
    at = torch.searchsorted(band, pixels).clamp(max=band.numel() - 1)  # band is sorted
    hit = torch.nonzero(band[at] == pixels)[:, 0]
    hit = hit[(cells[hit] >= 0).any(1)]
    w, h = size
    bits = graycode_bits(w, h)
    if not hit.numel() or shares.band_white.shape[1] != sum(bits):
        return cells, values
    white = shares.band_white.to(pixels.device)[at[hit]]
    # Rows whose cells already give every pair's share (within _BAND_MISS) are left as they are.
    missed = _pair_miss(cells[hit], values[hit], white, size, bits) > _BAND_MISS
    hit, white = hit[missed], white[missed].double()
    if not hit.numel():
        return cells, values
    own, light = cells[hit], values[hit].double()
    total = light.sum(1, keepdim=True)
    # The row's cells and their eight neighbours on the projector; the new ones seeded.
    x, y = own % w, torch.div(own, w, rounding_mode="floor")
    around = [own]
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dx or dy:
                inside = (own >= 0) & (x + dx >= 0) & (x + dx < w) & (y + dy >= 0) & (y + dy < h)
                around.append(torch.where(inside, own + dy * w + dx, -1))
    around = torch.cat(around, 1)
    first = torch.zeros_like(around, dtype=light.dtype)
    first[:, :own.shape[1]] = (own >= 0).to(light.dtype)
    spread = torch.zeros_like(first)
    spread[:, :own.shape[1]] = light
    grown, kept = _combine(around, spread)
    had = _combine(around, first)[1] > 0  # the same sort: the same cells in the same slots
    light = torch.where(had, kept, torch.where(grown >= 0, _BAND_SEED * total, 0.0))
    light = light * (total / light.sum(1, keepdim=True).clamp_min(1e-300))
    # Per pair, the rows whose cells it splits (most pairs show one stripe on a whole row's cells)
    # and which of their cells it lights.
    used, lit_by = grown >= 0, _pairs_lit(grown, size, bits)
    conditions = []
    for k in range(sum(bits)):
        lit = lit_by[..., k]
        rows = torch.nonzero(lit.any(1) & (used & ~lit).any(1))[:, 0]
        if rows.numel():
            conditions.append((rows, lit[rows].to(light.dtype), white[rows, k]))
    for _ in range(_BAND_SWEEPS):
        for rows, lit, share in conditions:
            part_of = light[rows]
            whole = part_of.sum(1)
            part = (part_of * lit).sum(1)
            rest = whole - part  # float64: no rounding to speak of
            on = (part > _SHARE_TOL * whole) & (rest > _SHARE_TOL * whole)
            up = torch.where(on, share * whole / part.clamp_min(1e-300), 1.0)
            down = torch.where(on, (1 - share) * whole / rest.clamp_min(1e-300), 1.0)
            light[rows] = part_of * (down[:, None] + lit * (up - down)[:, None])
    if grown.shape[1] > cells.shape[1]:
        # Each row keeps its cells of most light, as many as the other rows have slots (98-100% of
        # its light on the default scene, a median 99% on suite-55-16): a few wider rows would widen
        # every row of the build. The row's light stays whole.
        light, slot = light.topk(cells.shape[1], dim=1)
        grown = grown.gather(1, slot)
        light = light * (total / light.sum(1, keepdim=True).clamp_min(1e-300))
        grown, light = _combine(torch.where(light > 0, grown, -1), light)  # ascending again, as assembly reads rows
    cells, values = cells.clone(), values.clone()
    cells[hit], values[hit] = _widen(grown, light.to(values.dtype), cells.shape[1])
    return cells, values


def _pairs_lit(cells: torch.Tensor, size: tuple[int, int], bits: tuple[int, int]) -> torch.Tensor:
    """:math:`(N, s, B)` bool: which of the rows' flat ``cells`` :math:`(N, s)` (-1 unused) on a
    ``size`` projector each of its ``bits = (x, y)`` pattern pairs lights in its first image, ``x``
    pairs first (:func:`~torchproj.calib.graycode.stripe_signs`, :attr:`~torchproj.calib.CellShares.band_white`'s order)."""
    width, height = size
    column, row = (cells % width).float(), torch.div(cells, width, rounding_mode="floor").float()
    lit = torch.cat([stripe_signs(column, bits[0], width), stripe_signs(row, bits[1], height)], -1) > 0
    return lit & (cells >= 0)[..., None]


def _pair_miss(cells: torch.Tensor, values: torch.Tensor, white: torch.Tensor, size: tuple[int, int],
               bits: tuple[int, int]) -> torch.Tensor:
    """:math:`(N,)` the largest difference between each row's share of its light on the cells each
    pattern pair's first image lights (rows of flat ``cells`` on a ``size`` projector, -1 unused,
    and their ``values``) and the measured one, ``white`` :math:`(N, B)`."""
    light = torch.where(cells >= 0, values, 0.0).double()
    share = torch.einsum("ns,nsb->nb", light, _pairs_lit(cells, size, bits).double())
    return (share / light.sum(1, keepdim=True).clamp_min(1e-300) - white.double()).abs().amax(1)


def _widen(cells: torch.Tensor, values: torch.Tensor, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows padded to ``width`` slots with empty ones (cell -1, value 0)."""
    pad = (0, width - cells.shape[1])
    return torch.nn.functional.pad(cells, pad, value=-1), torch.nn.functional.pad(values, pad)


def _stack_rows(cells: list[torch.Tensor], values: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Blocks of rows with different numbers of slots, one below the other, each widened to the widest
    (written into one array: padding each block and joining them copied every slot twice).

    Takes the blocks out of the two lists as it writes them (the lists are left empty), so that each
    block is freed once copied, where the caller holds no other reference: the stacked rows and the
    blocks are never all held at once.
    """
    width = max(c.shape[1] for c in cells)
    if len(cells) == 1:
        return _widen(cells.pop(), values.pop(), width)
    promote = functools.partial(functools.reduce, torch.promote_types)
    dtype = promote(v.dtype for v in values)
    out_cells = torch.full((sum(c.shape[0] for c in cells), width), -1, dtype=promote(c.dtype for c in cells),
                           device=cells[0].device)
    out_values = torch.zeros(out_cells.shape, dtype=dtype, device=values[0].device)
    start = 0
    cells.reverse()
    values.reverse()
    while cells:
        c, v = cells.pop(), values.pop()
        out_cells[start:start + c.shape[0], :c.shape[1]] = c
        out_values[start:start + c.shape[0], :c.shape[1]] = v
        start += c.shape[0]
        del c, v
    return out_cells, out_values


def _footprint(prj_xy: torch.Tensor, weight: torch.Tensor, size: tuple[int, int], model: str,
               slope: torch.Tensor | None = None, blur: torch.Tensor | None = None, fine: bool = False):
    """Cells and weights of one projector for rows: :math:`(N, s)` flat cells (-1 = none), weights.

    ``slope`` :math:`(N, 2, 2)` (:func:`map_slope` at the rows) is needed by the ``area`` model; a
    row whose slope is unknown keeps its nearest cell. ``blur`` :math:`(N,)`, the ``area`` model's
    defocus disc per row (:attr:`StateCalibration.blur`, NaN already taken as 0). ``fine``: steep
    rows sampled finely (:func:`_area_cells`)."""
    w, h = size
    ok = torch.isfinite(prj_xy).all(-1) & (weight > 0)
    if model == "area":
        u = torch.nan_to_num(prj_xy, nan=-10.0)
        known = torch.isfinite(slope).all(-1).all(-1)
        slope = torch.where(known[:, None, None], slope, 0.0)
        # Rows go in chunks, so the samples' temporaries (16 per row; blurred and steep rows in smaller
        # passes, _area_cells) stay small.
        step = _AREA_CHUNK
        parts = [_area_cells(u[i:i + step], slope[i:i + step], ok[i:i + step], size,
                             None if blur is None else blur[i:i + step], fine) for i in range(0, max(u.shape[0], 1), step)]
        cells, share = _stack_rows([c for c, _ in parts], [v for _, v in parts])
        return cells, share * torch.where(ok, weight, 0.0)[:, None]
    if model == "nearest":
        cell = round_to_pixel(torch.nan_to_num(prj_xy, nan=-10.0))
        ok &= (cell[:, 0] >= 0) & (cell[:, 0] < w) & (cell[:, 1] >= 0) & (cell[:, 1] < h)
        flat = torch.where(ok, cell[:, 1] * w + cell[:, 0], -1)
        return flat[:, None], torch.where(ok, weight, 0.0)[:, None]
    u = torch.nan_to_num(prj_xy, nan=-10.0)
    base = torch.floor(u).long()
    frac = u - base
    cells, weights = [], []
    for dy in (0, 1):
        for dx in (0, 1):
            cx, cy = base[:, 0] + dx, base[:, 1] + dy
            f = (frac[:, 0] if dx else 1 - frac[:, 0]) * (frac[:, 1] if dy else 1 - frac[:, 1])
            inside = ok & (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h) & (f > 0)
            cells.append(torch.where(inside, cy * w + cx, -1))
            weights.append(torch.where(inside, weight * f, 0.0))
    return torch.stack(cells, 1), torch.stack(weights, 1)


def _merge(columns: torch.Tensor, values: torch.Tensor, rhs: torch.Tensor, target: torch.Tensor):
    """Replace rows sharing the same columns by an equivalent smaller set (float64 algebra).

    Args:
        columns: :math:`(N, s)` global column per slot (-1 for unused slots).
        values: :math:`(N, s)` matrix entries.
        rhs: :math:`(N, C)`.
        target: :math:`(N,)` target index per row.

    Returns:
        merged ``columns, values, rhs, target`` and the constant :math:`(C,)`.
    """
    group, n_groups = group_rows(columns)
    # A row alone in its group is its own exact replacement: only the groups of two or more rows go
    # through the eigen-decomposition (on the default scene 55% of the rows are alone).
    alone = torch.bincount(group, minlength=n_groups)[group] == 1
    shared = torch.nonzero(~alone)[:, 0]
    ids, compact = torch.unique(group[shared], return_inverse=True)
    *merged, merged_group, constant = _merge_groups(columns[shared], values[shared], rhs[shared], target[shared],
                                                    compact, ids.numel())
    # Rows in group order (the columns' lexicographic order), whatever order the targets came in:
    # the same model gives the same products to the last bit.
    order = torch.sort(torch.cat([group[alone], ids[merged_group]]), stable=True).indices
    return (*(torch.cat([x[alone], m])[order] for x, m in zip((columns, values, rhs, target), merged)), constant)


EIGH_CHUNK = 16384  # groups per batched eigen-decomposition in _merge_groups


def _merge_groups(columns, values, rhs, target, group, n_groups):
    """:func:`_merge` for rows already grouped (``group`` :math:`(N,)` of ``n_groups``); also returns
    the group of each new row, before the constant."""
    s = columns.shape[1]
    a = values.double()
    gram = torch.zeros(n_groups, s, s, dtype=torch.float64, device=a.device)
    gram.index_add_(0, group, a[:, :, None] * a[:, None, :])
    cross = torch.zeros(n_groups, s, rhs.shape[1], dtype=torch.float64, device=a.device)
    cross.index_add_(0, group, a[:, :, None] * rhs.double()[:, None, :])
    total = rhs.double().pow(2).sum(0)
    # Ascending eigenvalues, (G, s) and (G, s, s). In chunks: cuSOLVER's batched solver sizes its
    # workspace in 32-bit integers and failed (CUSOLVER_STATUS_INTERNAL_ERROR) on the half-size
    # rig's few hundred thousand groups on an H100; on the CPU the chunks cost nothing.
    parts = [torch.linalg.eigh(chunk) for chunk in gram.split(EIGH_CHUNK)]
    lam, vec = torch.cat([q[0] for q in parts]), torch.cat([q[1] for q in parts])
    keep = lam > lam[:, -1:].clamp_min(1e-300) * 1e-9
    root = lam.clamp_min(0).sqrt()
    rows_val = (root[:, :, None] * vec.transpose(1, 2))  # (G, k, s): row k = sqrt(l_k) v_k^T
    rows_rhs = (vec.transpose(1, 2) @ cross) / torch.where(keep, root, 1.0)[:, :, None]  # (G, k, C)
    first = torch.full((n_groups,), columns.shape[0], dtype=torch.int64, device=a.device)
    first.scatter_reduce_(0, group, torch.arange(columns.shape[0], device=a.device), reduce="amin")
    g_idx, k_idx = torch.nonzero(keep, as_tuple=True)
    new_cols = columns[first][g_idx]
    new_vals = rows_val[g_idx, k_idx].to(values.dtype)
    new_rhs = rows_rhs[g_idx, k_idx]
    constant = (total - new_rhs.pow(2).sum(0)).clamp_min(0)
    return new_cols, new_vals, new_rhs.to(rhs.dtype), target[first][g_idx], g_idx, constant.to(rhs.dtype)


def _channel_ratio(colour: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """:math:`(C, N)` each channel's white minus black over the grey one (their mean), 0 where the grey
    one is not positive (no light modelled there)."""
    return torch.where(weight > 0, colour / torch.where(weight > 0, weight, 1.0), 0.0)


@dataclass
class _Rows:
    """The rows of an unmerged operator, before assembly: one per covered, lit camera pixel."""

    cols: torch.Tensor  # (N, s) global cell per slot (projectors' cells offset apart), -1 for none
    vals: torch.Tensor  # (N, s) float32, the grey weight's entries
    values: torch.Tensor  # (N, C) the targets' values
    target: torch.Tensor  # (N,) target index
    pixel: torch.Tensor  # (N,) flat camera pixel
    camera: tuple[int, int]  # (H, W)
    sizes: list[tuple[int, int]]  # per projector (width, height)
    ratio: torch.Tensor | None  # (N, P, C) per projector, each channel's weight over the grey one


def _target_rows(calibrations: dict[str, StateCalibration], targets: list[Target], footprint: str,
                 colour: bool) -> _Rows:
    """Every target's rows (:func:`build_transport`'s checks, in the user's terms); with ``colour`` also
    each row's per-channel ratios (every state needs :attr:`StateCalibration.colour_weight`)."""
    check(footprint in FOOTPRINTS, f"footprint must be one of {list(FOOTPRINTS)}, got {footprint!r}")
    check_calibrations(calibrations)
    n_ch = _target_channels(targets)
    sizes = camera = None
    checked = set()
    shown = {}  # state -> [(target, its pixels)]: a camera pixel shows one image at a time
    row_cols, row_vals, row_values, row_tgt, row_pix, row_ratio = [], [], [], [], [], []
    for ti, target in enumerate(targets):
        check(target.state in calibrations, f"target {target.name or ti!r} names state {target.state!r}, which was "
                                            f"not calibrated; calibrated states: {sorted(calibrations)}")
        cal = calibrations[target.state]
        sizes = sizes or cal.projector_sizes
        check(cal.projector_sizes == sizes, "every state must be calibrated with the same projectors")
        lit = cal.lit()
        camera = camera or lit.shape
        check(lit.shape == camera, f"state {target.state!r} is calibrated with a {lit.shape[1]}x{lit.shape[0]} camera, "
                                   f"another state with {camera[1]}x{camera[0]}: calibrate every state with one camera")
        if colour:
            check(cal.colour_weight is not None and len(cal.colour_weight) == len(cal.prj_xy),
                  f"state {target.state!r} has no white minus black per colour channel for every projector: "
                  f"calibrate it with a colour camera, or use build_transport's one grey weight")
            for j, c in enumerate(cal.colour_weight):
                check_shape(c, f"colour_weight[{j}] of state {target.state!r}", [n_ch, *lit.shape])
        mask = lit if target.mask is None else target.mask.to(device=lit.device, dtype=torch.bool)
        check_shape(mask, f"target {target.name!r} mask", list(lit.shape))
        check(bool((mask & lit).any()), f"target {target.name!r} lies outside the lit region of state "
                                        f"{target.state!r}: no pixel of its mask is lit by any projector")
        values, covered = kept_target_on_camera(target, mask & lit)
        for other, pixels in shown.get(target.state, ()):
            # Two images asked of one pixel: the least squares would show their mean on it, each
            # target scored against its own image there.
            shared = int((pixels & covered).sum())
            check(shared == 0, f"targets {other!r} and {target.name or ti!r} of state {target.state!r} share {shared} "
                               "camera pixels, and a pixel shows one image at a time: give each target of a state its "
                               "own mask (Target(mask=...)), or put them in different states")
        shown.setdefault(target.state, []).append((target.name or ti, covered))
        rows = torch.nonzero(covered.reshape(-1))[:, 0]
        cols, vals, ratio = [], [], []
        offset = 0
        # Global cells fit int32 on any rig (a few million cells): half the bytes of the rows' largest
        # arrays, which set the cold run's peak memory where the last target's rows are stacked.
        cell_type = index_dtype(sum(w * h for w, h in cal.projector_sizes))
        for name, per in (("blur maps", cal.blur), ("edge-pixel sets", cal.edges), ("cell-share sets", cal.shares)):
            check(per is None or len(per) == len(cal.prj_xy),
                  f"state {target.state!r} has {len(per or [])} {name} for {len(cal.prj_xy)} projectors: "
                  "give one per projector")
        for j, weight in enumerate(cal.weight):
            if (target.state, j) not in checked:  # a state's parts once, whatever its number of targets
                checked.add((target.state, j))
                check_finite(weight, f"weight[{j}] of state {target.state!r}")
                if cal.edges is not None:
                    cal.edges[j].check(tuple(lit.shape), f"edges[{j}] of state {target.state!r}")
                if cal.shares is not None:
                    cal.shares[j].check(tuple(lit.shape), sizes[j], f"shares[{j}] of state {target.state!r}")
                if cal.blur is not None:
                    check_shape(cal.blur[j], f"blur[{j}] of state {target.state!r}", list(lit.shape))
                    check(not torch.isinf(cal.blur[j]).any(), f"blur[{j}] of state {target.state!r} holds "
                                                              "infinite diameters: give them in cells, NaN where unknown")
            c, v = cal._rows(j, rows, footprint)
            cols.append(torch.where(c >= 0, c + offset, -1).to(cell_type))
            vals.append(v)
            if colour:
                ratio.append(_channel_ratio(cal.colour_weight[j].reshape(n_ch, -1)[:, rows].float(),
                                            weight.reshape(-1)[rows].float()).T)
            offset += sizes[j][0] * sizes[j][1]
        cols, vals = torch.cat(cols, 1), torch.cat(vals, 1)
        lit_rows = (vals > 0).any(1)
        every = bool(lit_rows.all())  # then the rows as they are, not a copy of them
        row_cols.append(cols if every else cols[lit_rows])
        row_vals.append(vals if every else vals[lit_rows])
        del cols, vals
        row_values.append(values.reshape(n_ch, -1)[:, rows[lit_rows]].T)
        row_tgt.append(torch.full((int(lit_rows.sum()),), ti, dtype=torch.int64, device=rows.device))
        row_pix.append(rows[lit_rows])
        if colour:
            row_ratio.append(torch.stack(ratio, 1)[lit_rows])
    # The area footprint gives each target as many slots as its widest row needs.
    cols, vals = _stack_rows(row_cols, row_vals)
    return _Rows(cols, vals.float(), torch.cat(row_values).float(), torch.cat(row_tgt), torch.cat(row_pix),
                 tuple(camera), sizes, torch.cat(row_ratio) if colour else None)


def _scale(vals: torch.Tensor, scale: float | None) -> float:
    """The camera value asked for a target value of 1 (:func:`build_transport`'s ``scale``)."""
    if scale is None:
        scale = 0.5 * float(vals.sum(1).median())
    return check_number(scale, "scale", 0.0, strict=True)


def _assemble(cols: torch.Tensor, vals: torch.Tensor, sizes: list[tuple[int, int]]):
    """CSR pieces of rows' slots: ``crow``, each nonzero's variable and value, and each variable's cell
    and projector."""
    # Variables only for the cells that light at least one row, numbered in cell order through a
    # table over all cells (a few million), not a sort of every nonzero. Each row names a cell at most
    # once (projectors' cells are offset apart), so each row's used slots in ascending order give CSR
    # directly. The footprints' rows come ascending already (each projector's cells first, in order,
    # and projectors' blocks side by side): the rows are sorted only where they are not.
    starts = torch.tensor([0] + [w * h for w, h in sizes], device=cols.device).cumsum(0)
    used = cols >= 0
    counts = used.sum(1)
    crow = torch.zeros(cols.shape[0] + 1, dtype=torch.int64, device=cols.device)
    crow[1:] = torch.cumsum(counts, 0)
    flat = cols[used]
    step = flat[1:] - flat[:-1]
    first = torch.zeros(flat.numel(), dtype=torch.bool, device=cols.device)
    first[crow[:-1][counts > 0]] = True  # a row's first nonzero follows another row's last
    if not bool(((step > 0) | first[1:]).all()):
        cols, order = torch.sort(cols, dim=1)
        vals = vals.gather(1, order)
        used = cols >= 0
        check(not bool((used[:, 1:] & (cols[:, 1:] == cols[:, :-1])).any()), "a row names one cell twice")
        flat = cols[used]
    lights = torch.zeros(int(starts[-1]), dtype=torch.bool, device=cols.device)
    lights[flat] = True
    global_cols = torch.nonzero(lights)[:, 0]
    number = torch.cumsum(lights, 0) - 1
    projector = torch.searchsorted(starts, global_cols, right=True) - 1
    return crow, number[flat], vals[used], global_cols - starts[projector], projector


def build_transport(calibrations: dict[str, StateCalibration], targets: list[Target], *,
                    footprint: str = "nearest", merge: bool = True, scale: float | None = None,
                    device="cpu") -> TransportOperator:
    """Build the sparse light-transport operator and its right-hand side.

    Args:
        calibrations: state name -> :class:`StateCalibration` (from Gray-code calibration).
        targets: at least one :class:`Target`; each names a calibrated state.
        footprint: ``"nearest"`` (one cell per projector and row, as the paper), ``"bilinear"`` (the four
            around the sub-pixel coordinate) or ``"area"`` (the cells the pixel's area covers).
        merge: merge rows with the same columns (exact; smaller model). Unmerged rows are camera
            pixels, and the operator keeps their map (:meth:`TransportOperator.to_camera`), which
            an image-space model needs (:class:`~torchproj.solve.ProjectionModel`).
        scale: camera value asked for a target value of 1; None picks half the median, over the
            target pixels, of the light all projectors together can put there.
        device: where the operator lives.

    Returns:
        a :class:`TransportOperator` with ``rhs`` = scale * targets.
    """
    device = check_device(device)
    rows = _target_rows(calibrations, targets, footprint, colour=False)
    scale = _scale(rows.vals, scale)
    cols, vals, rhs, tgt = rows.cols, rows.vals, rows.values * scale, rows.target
    constant, pixels = None, {"row_pixel": rows.pixel, "camera_size": (rows.camera[1], rows.camera[0])}
    if merge:
        cols, vals, rhs, tgt, constant = _merge(cols, vals, rhs, tgt)
        pixels = {}  # merged rows mix pixels
    crow, variable, value, cell, projector = _assemble(cols, vals, rows.sizes)
    matrix = csr_tensor(crow, variable, value, (cols.shape[0], cell.numel()))
    return TransportOperator(matrix, rhs, projector, cell, rows.sizes, constant, tgt, scale,
                             target_count=len(targets), **pixels).to(device)


def has_colour_weights(calibrations: dict[str, StateCalibration], targets: list[Target]) -> bool:
    """Whether :func:`build_channel_transports` applies: colour targets, and every target's state
    calibrated with a white minus black per channel of each projector."""
    if isinstance(targets, (list, tuple)) and not targets:
        return False  # no target asks for colour; anything but a list is named by _target_channels
    n_ch = _target_channels(targets)
    return n_ch > 1 and all(
        t.state in calibrations and calibrations[t.state].colour_weight is not None
        and all(c.shape[0] == n_ch for c in calibrations[t.state].colour_weight) for t in targets)


def used_colour_weights(calibrations: dict[str, StateCalibration], targets: list[Target], asked: str) -> str:
    """The weights a build uses: ``"channel"`` only for colour targets calibrated per channel
    (:func:`has_colour_weights`); elsewhere "channel" builds what "grey" does."""
    return "channel" if asked == "channel" and has_colour_weights(calibrations, targets) else "grey"


def build_operators(calibrations: dict[str, StateCalibration], targets: list[Target], *, footprint: str, merge: bool,
                    colour_weights: str, scale: float | None = None, device="cpu") -> list[TransportOperator]:
    """The operator(s) a solve runs on: one per colour channel (:func:`build_channel_transports`) where
    ``colour_weights`` is ``"channel"`` and calibration measured each channel's weight, else one with
    the grey weight (:func:`build_transport`)."""
    if used_colour_weights(calibrations, targets, colour_weights) == "channel":
        return build_channel_transports(calibrations, targets, footprint=footprint, scale=scale, device=device)
    return [build_transport(calibrations, targets, merge=merge, footprint=footprint, scale=scale, device=device)]


def build_channel_transports(calibrations: dict[str, StateCalibration], targets: list[Target], *,
                             footprint: str = "nearest", scale: float | None = None,
                             device="cpu") -> list[TransportOperator]:
    """One operator per colour channel, each with that channel's own white minus black.

    A camera channel sees each projector's primary of that channel through the surface's albedo in
    that channel (as the virtual rig renders it, :mod:`torchproj.sim.rig`; a camera whose channels
    also see the other primaries breaks this model, as it breaks the grey one), so channel ``c``'s
    entries are :func:`build_transport`'s with :attr:`StateCalibration.colour_weight`'s
    channel ``c`` in place of the grey weight. The cells, rows and ``scale`` are the grey model's,
    shared by every channel; least squares in a box then separates over channels, and each channel
    is solved alone (:func:`~torchproj.solve.make_patterns` with a list of operators). Rows stay
    camera pixels (no merging: the channels' rows would merge differently).

    Args:
        calibrations: as :func:`build_transport`; every state needs ``colour_weight`` with as many
            channels as the targets.
        targets, footprint, scale, device: as :func:`build_transport`.

    Returns:
        one :class:`TransportOperator` per target channel, each with that channel's right-hand side
        :math:`(N, 1)`.
    """
    device = check_device(device)
    rows = _target_rows(calibrations, targets, footprint, colour=True)
    scale = _scale(rows.vals, scale)
    crow, variable, value, cell, projector = _assemble(rows.cols, rows.vals, rows.sizes)
    n_rows = rows.cols.shape[0]
    # Each nonzero's row and projector, to pick its ratio.
    nonzero_row = torch.repeat_interleave(torch.arange(n_rows, device=crow.device), crow.diff())
    nonzero_projector = projector[variable]
    ops = []
    for c in range(rows.values.shape[1]):
        matrix = csr_tensor(crow, variable, value * rows.ratio[nonzero_row, nonzero_projector, c], (n_rows, cell.numel()))
        ops.append(TransportOperator(matrix, rows.values[:, c:c + 1] * scale, projector, cell, rows.sizes, None,
                                     rows.target, scale, target_count=len(targets), row_pixel=rows.pixel,
                                     camera_size=(rows.camera[1], rows.camera[0])).to(device))
    return ops


def retarget_rhs(op, calibrations: dict[str, StateCalibration], targets: list[Target]) -> torch.Tensor:
    """The right-hand side other images give on an operator's rows, without building ``A`` again.

    An operator whose rows are camera pixels (``merge=False``) keeps its rows for any images on the
    same regions: a target's rows are the lit pixels its region covers, whatever the image shows.
    So a frame of a video or a point of a parameter sweep needs only ``scale * values`` at the rows'
    pixels (:meth:`TransportOperator.with_rhs`).

    Args:
        op: the operator, built for ``len(targets)`` targets with ``merge=False``.
        calibrations: the states it was built from.
        targets: the new images, one per target of ``op``, on the same states, masks and corners.

    Returns:
        :math:`(N_{rows}, C)`, C the images' channels.
    """
    check_operator(op)
    check_calibrations(calibrations)
    check_targets(targets)
    check(op.row_pixel is not None, "new images on an operator's rows need rows that are camera pixels: build it "
                                    "with merge=False")
    check(len(targets) == op.target_count, f"give one image per target of the operator ({op.target_count}), got "
                                           f"{len(targets)}")
    rhs = torch.empty(op.shape[0], _target_channels(targets), dtype=op.rhs.dtype)
    for k, target in enumerate(targets):
        check(target.state in calibrations, f"target {target.name or k!r} names state {target.state!r}, which was not "
                                            f"calibrated; calibrated states: {sorted(calibrations)}")
        lit = calibrations[target.state].lit()
        mask = lit if target.mask is None else target.mask.to(device=lit.device, dtype=torch.bool) & lit
        values, covered = target_on_camera(target, mask)
        rows = torch.nonzero(op.row_target.cpu() == k)[:, 0]
        pixels = op.row_pixel.cpu()[rows]
        check(bool(covered.reshape(-1)[pixels].all()), f"target {target.name or k!r}: the new image covers other pixels "
                                                       "than the operator's rows (another state, mask or corners): "
                                                       "build the transport for it")
        rhs[rows] = (op.scale * values.reshape(values.shape[0], -1)[:, pixels].T).to(rhs)
    return rhs.to(op.rhs.device)
