"""Scoring patterns on the virtual rig: project them, capture, compare with each target.

This is the evaluation every number of ``torchproj run`` and the benchmarks comes from, callable on
any patterns (a solver's, a training loop's, a file's): the captures are rendered by the simulator
from the physics, never computed as ``A p``, so calibration errors show in the scores.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass

import torch

from ..core.checks import check, check_image, check_mask, check_number, check_seed, check_shape
from ..core.conventions import round_to_pixel
from ..metrics import crosstalk, explained_share, psnr, ssim
from ..transport import Target, target_on_camera
from ..transport.build import check_targets, kept_target_on_camera  # the targets' warps, kept by the model's build
from .targets import check_target_channels
from .virtual import check_virtual_calibration

__all__ = ["EVALUATION", "PatternEvaluation", "TargetScore", "affine_psnr", "evaluate_patterns", "ghost_images",
           "score_image"]

EVALUATION = ("captured image minus the state's black capture, divided by the target scale, against the target image "
              "warped onto the camera pixels of its surfaces that calibration found lit; data range 1; SSIM "
              "(scikit-image's definition, 7x7 uniform window, torchproj.metrics.ssim) averaged over those pixels; "
              "crosstalk is the largest |Pearson correlation| there with another target's image placed on the same "
              "pixels; ghost is the share of the error (capture minus target) that the other states' target images "
              "explain (least squares), each carried through each projector's correspondence onto the pixels that "
              "see the same projector cells, where parallax puts its ghost; affine PSNR is the PSNR after the best gain "
              "and offset per target (least squares), what is left when brightness is taken out; the paper's score "
              "compares the capture with a capture of the target image projected alone by one projector "
              "(response-compensated) onto the same surface, as the paper used a capture of the original image as "
              "its baseline")


def one_value(values: torch.Tensor, covered: torch.Tensor) -> bool:
    """Whether target values :math:`(C, H, W)` are one value over the ``covered`` pixels (or none)."""
    values = values[:, covered]
    return values.numel() == 0 or bool(values.max() - values.min() <= 1e-6)


def _check_scored(estimate: torch.Tensor, values: torch.Tensor, covered: torch.Tensor) -> None:
    """What :func:`affine_psnr` and :func:`score_image` read: two :math:`(C, H, W)` images, a bool mask."""
    sizes = check_shape(values, "values", ["C", "H", "W"])
    check_shape(estimate, "estimate", [sizes["C"], sizes["H"], sizes["W"]])
    check_mask(covered, "covered", [sizes["H"], sizes["W"]])


def affine_psnr(estimate: torch.Tensor, values: torch.Tensor, covered: torch.Tensor) -> float:
    """PSNR after the gain and offset that best bring the estimate onto the values (least squares, one
    pair per target over all channels): the structure of a capture, its brightness taken out.

    Args:
        estimate, values: :math:`(C, H, W)` in target units.
        covered: :math:`(H, W)` bool.
    """
    _check_scored(estimate, values, covered)
    if one_value(values, covered):
        return math.inf  # any capture's gain 0 and offset the value: exact, where lstsq rounds to ~260 dB
    x, y = estimate[:, covered].reshape(-1).double(), values[:, covered].reshape(-1).double()
    design = torch.stack([x, torch.ones_like(x)], 1)
    gain_offset = torch.linalg.lstsq(design, y[:, None]).solution
    return psnr((design @ gain_offset)[:, 0], y)


def score_image(estimate: torch.Tensor, values: torch.Tensor, covered: torch.Tensor) -> dict:
    """PSNR and SSIM of an estimate against target values over the covered pixels (float64).

    Args:
        estimate, values: :math:`(C, H, W)` in target units.
        covered: :math:`(H, W)` bool.
    """
    _check_scored(estimate, values, covered)
    # SSIM lies in [-1, 1]; an image equal to its target can come out a rounding error past 1.
    return {"psnr_db": psnr(estimate[:, covered], values[:, covered]),
            "ssim": min(1.0, max(-1.0, float(ssim(estimate.double(), values.double(), covered))))}


@dataclass
class TargetScore:
    """How one target came out in the virtual rig's capture.

    Attributes:
        name, state: the target's.
        psnr_db, ssim, crosstalk, ghost, affine_psnr_db: see :data:`EVALUATION`.
        paper: ``{psnr_db, ssim}`` against the paper's baseline, a capture of the target image projected
            alone (see :func:`evaluate_patterns`); None where it was not asked for.
        pixels: camera pixels scored.
        estimate: :math:`(C, H, W)` the capture in target units, clamped to [0, 1].
        values: :math:`(C, H, W)` the target image on the camera.
        covered: :math:`(H, W)` bool, the pixels scored.
    """

    name: str
    state: str
    psnr_db: float
    ssim: float
    crosstalk: float
    pixels: int
    estimate: torch.Tensor
    values: torch.Tensor
    covered: torch.Tensor
    ghost: float = 0.0
    affine_psnr_db: float = float("nan")
    paper: dict | None = None

    @property
    def constant_target(self) -> bool:
        """Whether the target is one value over its scored pixels: a score of brightness alone."""
        return one_value(self.values, self.covered)

    def notes(self) -> dict:
        """Why a score of this row is degenerate: field -> reason (empty for an ordinary target).

        JSON has no infinity or NaN, so ``report.json`` writes such a score as null; the reason
        stands beside it here.
        """
        notes = {}
        if self.constant_target:
            notes["target"] = ("the target image is one value over its pixels: PSNR measures brightness alone, SSIM "
                               "compares no structure, and a gain and offset reproduce it exactly (affine PSNR "
                               "infinite)")
        for field in ("psnr_db",) if self.constant_target else ("psnr_db", "affine_psnr_db"):
            value = getattr(self, field)
            if math.isinf(value):
                notes[field] = ("infinite: the capture equals the target exactly over its pixels" if field == "psnr_db"
                                else "infinite: a gain and offset bring the capture exactly onto the target")
            elif math.isnan(value):
                notes[field] = "undefined: no pixel was scored"
        return notes

    def as_dict(self) -> dict:
        """The row of ``report.json``."""
        row = {"name": self.name, "state": self.state, "psnr_db": self.psnr_db, "ssim": self.ssim,
               "crosstalk": self.crosstalk, "ghost": self.ghost, "pixels": self.pixels,
               "affine_psnr_db": self.affine_psnr_db}
        notes = self.notes()
        row = row if not notes else {**row, "notes": notes}
        return row if self.paper is None else {**row, "paper": self.paper}


@dataclass
class PatternEvaluation:
    """What :func:`evaluate_patterns` found: a score per target and the capture of each state."""

    targets: list[TargetScore]
    captures: dict[str, torch.Tensor]  # state -> (C, H, W) capture in [0, 1], on the CPU


def as_light(patterns: list[torch.Tensor], projectors: int, device) -> dict[int, torch.Tensor]:
    """Patterns as the light the rig shows: projector index -> :math:`(1, C, H_j, W_j)` float in [0, 1].

    Args:
        patterns: per projector (``projectors`` of them), :math:`(C, H_j, W_j)` uint8 levels (what
            :func:`~torchproj.solve.make_patterns` gives) or float light in [0, 1].
    """
    check(isinstance(patterns, (list, tuple)), f"patterns must be a list of one image per projector ({projectors}), "
                                               f"got {type(patterns).__name__}")
    check(len(patterns) == projectors, f"give one pattern per projector ({projectors}), got {len(patterns)}")
    shown = {}
    for j, pattern in enumerate(patterns):
        check(isinstance(pattern, torch.Tensor), f"patterns[{j}] must be a torch.Tensor, got {type(pattern).__name__}")
        if pattern.dtype == torch.uint8:
            light = pattern.float() / 255
        else:
            # Levels 0-255 in another integer type read as light 0-255 (every cell white), and float light
            # divided by 255 as if it were levels (every cell black): either is refused, not shown.
            check(pattern.is_floating_point(), f"patterns[{j}] must be uint8 (0-255, as make_patterns gives) or "
                                               f"float light in [0, 1], got {pattern.dtype}")
            check_image(pattern, f"patterns[{j}]")
            light = pattern.float()
        shown[j] = light[None].to(device)
    return shown


def evaluate_patterns(calibration, patterns: list[torch.Tensor], targets: list[Target], *, scale: float,
                      states=None, noise: bool = True, paper: bool = True, seed: int | None = None) -> PatternEvaluation:
    """Project patterns on the virtual rig, capture each target's state and score every target.

    Args:
        calibration: the :class:`~torchproj.pipeline.VirtualCalibration` the patterns were made
            for (its rig renders the captures; its black captures are subtracted), or
            :func:`~torchproj.pipeline.shown_world` of it, the world a scene's ``show:`` section
            describes (given the calibration itself, such a scene is warned about).
        patterns: per projector, :math:`(C, H_j, W_j)` uint8 images (what
            :func:`~torchproj.solve.make_patterns` and :meth:`ProjectionModel.to_patterns` give)
            or float in [0, 1].
        targets: the targets, as given to the solver.
        scale: camera value of a target value of 1 (the operator's ``scale``).
        states: per state the :class:`~torchproj.transport.StateCalibration` whose lit pixels are
            scored (default: the calibration's own; a run on homography maps passes those).
        noise: camera noise in the captures, as on a bench.
        seed: the captures' noise drawn from this seed (state ``k`` of the targets' states from
            ``seed + k``), so that every set of patterns scored with it meets the same noise and two
            sets compare by their light alone. None: the rig's own generator, whose draws go on
            from the calibration's (what ``torchproj run`` scores with). One capture's noise moves a
            target of a few hundred pixels by up to a decibel (suite-55-8, docs/accuracy.md).
        paper: also score against the paper's baseline: for each target, the target image carried onto
            the cells of the one projector that lights most of its pixels (each cell the mean of the
            target over the camera pixels decoded to it), response-compensated, projected alone onto
            its state, captured and brought to target units like the estimate. One more capture per
            target. Which projector and how the image reaches its cells are our choices: the paper
            says only that it "projected the original image on the plane".
    """
    check_virtual_calibration(calibration)
    states = calibration.states if states is None else states
    scene = calibration.rig.scene
    if scene.show is not None:
        # A script that scores in the calibrated world a scene whose show: section changed: run scores
        # in the world as shown, and these scores would not be its.
        warnings.warn(f"scene {scene.name!r} has a show: section, and these patterns are scored in the world as it "
                      "was calibrated; torchproj.shown_world(calibration) scores them in the world as shown, as "
                      "torchproj run does", stacklevel=2)
    shown = as_light(patterns, len(scene.projectors), calibration.rig.device)
    check_number(scale, "scale", strict=True)
    # State k's noise is drawn from seed + k, within the rig's 2**63.
    seed = None if seed is None else check_seed(seed, limit=2 ** 62, hint=" (or None: the rig's own noise draws)")
    check_targets(targets)
    check_target_channels(targets, scene.camera.channels)
    check(isinstance(states, Mapping), f"states must be a dict of state name -> StateCalibration, got {type(states).__name__}")
    missing = sorted({t.state for t in targets} - set(states))
    check(not missing, f"no calibration of the targets' states {missing}; calibrated: {sorted(states)}")
    for target in (t for t in targets if t.mask is not None):  # as build_transport checks them
        check_shape(target.mask, f"target {target.name!r} mask", [scene.camera.height, scene.camera.width])
    captures = {state: calibration.rig.capture(state, shown, noise=noise, seed=None if seed is None else seed + k)[0].cpu()
                for k, state in enumerate(dict.fromkeys(t.state for t in targets))}
    regions = []  # scored on the host, beside the captures
    for target in targets:
        lit = states[target.state].lit().cpu()
        regions.append(lit if target.mask is None else lit & target.mask.cpu())
    on_camera = [kept_target_on_camera(target, region) for target, region in zip(targets, regions)]
    cells = _cell_maps(states, targets)
    ghosts = ghost_images(states, targets, on_camera, cells)
    references = _paper_references(calibration, states, targets, on_camera, cells, scale, noise) if paper else None
    scores = []
    for k, target in enumerate(targets):
        values, covered = on_camera[k]
        estimate = ((captures[target.state] - calibration.black[target.state]) / scale).clamp(0, 1)
        others = [target_on_camera(Target(target.state, t.image, name=t.name), regions[k])[0]
                  for m, t in enumerate(targets) if m != k]
        scores.append(TargetScore(name=target.name, state=target.state, **score_image(estimate, values, covered),
                                  crosstalk=crosstalk(estimate, others, covered), pixels=int(covered.sum()),
                                  estimate=estimate, values=values, covered=covered,
                                  ghost=explained_share(estimate - values, ghosts[k], covered),
                                  affine_psnr_db=affine_psnr(estimate, values, covered),
                                  paper=None if references is None else score_image(estimate, references[k], covered)))
        if scores[-1].constant_target:
            warnings.warn(f"target {target.name!r}: its image is one value over its {scores[-1].pixels} pixels, so its "
                          "PSNR measures brightness alone and its SSIM compares no structure; give an image with "
                          "detail to score the patterns", stacklevel=2)
    return PatternEvaluation(scores, captures)


def _cell_maps(states, targets: list[Target]) -> dict:
    """(state, projector) -> :math:`(H W,)` each camera pixel's cell (:func:`_cells`), for the targets' states."""
    return {(state, j): _cells(states[state].prj_xy[j], size)
            for state in dict.fromkeys(t.state for t in targets)
            for j, size in enumerate(states[state].projector_sizes)}


def _on_cells(values: torch.Tensor, covered: torch.Tensor, mine: torch.Tensor, size: tuple[int, int]):
    """:math:`(C, H_j W_j)` float64: values averaged onto the cells their covered pixels decoded to, NaN
    on cells that none did."""
    w, h = size
    use = covered.reshape(-1) & (mine >= 0)
    flat = values.reshape(values.shape[0], -1)[:, use].double()
    sums = torch.zeros(values.shape[0], w * h, dtype=torch.float64).index_add_(1, mine[use], flat)
    count = torch.bincount(mine[use], minlength=w * h).double()
    return torch.where(count > 0, sums / count.clamp_min(1), float("nan"))


def _paper_references(calibration, states, targets, on_camera, cells, scale: float, noise: bool):
    """Per target, :math:`(C, H, W)` the capture of its image projected alone by one projector (see
    :func:`evaluate_patterns`), in target units."""
    from ..solve import compensate

    references = []
    for target, (values, covered) in zip(targets, on_camera):
        sizes = states[target.state].projector_sizes
        lit = [int((covered.reshape(-1) & (cells[target.state, j] >= 0)).sum()) for j in range(len(sizes))]
        j = max(range(len(sizes)), key=lambda i: (lit[i], -i))
        w, h = sizes[j]
        light = _on_cells(values, covered, cells[target.state, j], (w, h)).nan_to_num(0.0).clamp(0, 1)
        pattern = compensate([light.reshape(-1, h, w).float()], [calibration.responses[j]])[0]
        shown = {j: (pattern.float() / 255)[None].to(calibration.rig.device)}  # the others show black
        capture = calibration.rig.capture(target.state, shown, noise=noise)[0].cpu()
        references.append(((capture - calibration.black[target.state]) / scale).clamp(0, 1))
    return references


def ghost_images(states, targets: list[Target], on_camera: list, cells: dict | None = None) -> list[list[torch.Tensor]]:
    """Per target, where the other states' targets would show as ghosts on its camera pixels.

    Light meant for target ``l`` (state ``s_l``) leaves projector ``j`` from the cells that light
    ``l``'s pixels in ``s_l``; in another state the same cells light other pixels, shifted by parallax
    and differently for each projector. Per target ``l`` and projector, ``l``'s image is averaged onto
    those cells (the correspondence of ``s_l``), then read back through each other state's
    correspondence. Targets of a target's own state are left out: an opaque surface point takes a
    cell's whole light, so they share no cells with it (through a semi-transparent screen they do,
    and this leaves that leak to ``crosstalk``).

    Args:
        states: state name -> :class:`~torchproj.transport.StateCalibration`.
        on_camera: per target, ``(values (C, H, W), covered (H, W))`` on its state's camera pixels.

    Returns:
        per target, :math:`(C, H, W)` images (one per other-state target and projector), NaN where a
        pixel's cell carries nothing of that target.
    """
    cells = _cell_maps(states, targets) if cells is None else cells  # each state's map, read once
    # Per target, per projector: its image averaged onto the cells that light it.
    on_cells = [[_on_cells(values, covered, cells[target.state, j], size)
                 for j, size in enumerate(states[target.state].projector_sizes)]
                for target, (values, covered) in zip(targets, on_camera)]
    ghosts = []
    for target, (values, _) in zip(targets, on_camera):
        mine = []
        for other, per in zip(targets, on_cells):
            if other.state == target.state:
                continue
            for j, light in enumerate(per):
                seen = cells[target.state, j]
                ghost = torch.full((values.shape[0], seen.numel()), float("nan"), dtype=torch.float64)
                ghost[:, seen >= 0] = light[:, seen[seen >= 0]]
                mine.append(ghost.reshape(values.shape))
        ghosts.append(mine)
    return ghosts


def _cells(prj_xy: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """:math:`(H W,)` the projector cell each camera pixel decoded to (row-major index), -1 where none."""
    w, h = size
    xy = prj_xy.reshape(-1, 2).cpu()
    ok = torch.isfinite(xy).all(-1)
    cell = torch.full((xy.shape[0], 2), -1, dtype=torch.int64)
    cell[ok] = round_to_pixel(xy[ok])
    inside = ok & (cell[:, 0] >= 0) & (cell[:, 0] < w) & (cell[:, 1] >= 0) & (cell[:, 1] < h)
    return torch.where(inside, cell[:, 1] * w + cell[:, 0], -1)
