"""Scoring patterns on the virtual rig: project them, capture, compare with each target.

This is the evaluation every number of ``torchproj run`` and the benchmarks comes from, callable on
any patterns (a solver's, a training loop's, a file's): the captures are rendered by the simulator
from the physics, never computed as ``A p``, so calibration errors show in the scores.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..core.checks import check
from ..metrics import crosstalk, psnr, ssim
from ..transport import Target, target_on_camera

__all__ = ["EVALUATION", "PatternEvaluation", "TargetScore", "evaluate_patterns", "score_image"]

EVALUATION = ("captured image minus the state's black capture, divided by the target scale, against the target image "
              "warped onto the camera pixels of its surfaces that calibration found lit; data range 1; SSIM "
              "(scikit-image's definition, 7x7 uniform window, torchproj.metrics.ssim) averaged over those pixels; "
              "crosstalk is the largest |Pearson correlation| there with another target's image placed on the same "
              "pixels")


def score_image(estimate: torch.Tensor, values: torch.Tensor, covered: torch.Tensor) -> dict:
    """PSNR and SSIM of an estimate against target values over the covered pixels (float64).

    Args:
        estimate, values: :math:`(C, H, W)` in target units.
        covered: :math:`(H, W)` bool.
    """
    return {"psnr_db": psnr(estimate[:, covered], values[:, covered]),
            "ssim": float(ssim(estimate.double(), values.double(), covered))}


@dataclass
class TargetScore:
    """How one target came out in the virtual rig's capture.

    Attributes:
        name, state: the target's.
        psnr_db, ssim, crosstalk: see :data:`EVALUATION`.
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

    def as_dict(self) -> dict:
        """The row of ``report.json``."""
        return {"name": self.name, "state": self.state, "psnr_db": self.psnr_db, "ssim": self.ssim,
                "crosstalk": self.crosstalk, "pixels": self.pixels}


@dataclass
class PatternEvaluation:
    """What :func:`evaluate_patterns` found: a score per target and the capture of each state."""

    targets: list[TargetScore]
    captures: dict[str, torch.Tensor]  # state -> (C, H, W) capture in [0, 1], on the CPU


def evaluate_patterns(calibration, patterns: list[torch.Tensor], targets: list[Target], *, scale: float,
                      states=None, noise: bool = True) -> PatternEvaluation:
    """Project patterns on the virtual rig, capture each target's state and score every target.

    Args:
        calibration: the :class:`~torchproj.pipeline.VirtualCalibration` the patterns were made
            for (its rig renders the captures; its black captures are subtracted).
        patterns: per projector, :math:`(C, H_j, W_j)` uint8 images (what
            :func:`~torchproj.solve.make_patterns` and :meth:`ProjectionModel.to_patterns` give)
            or float in [0, 1].
        targets: the targets, as given to the solver.
        scale: camera value of a target value of 1 (the operator's ``scale``).
        states: per state the :class:`~torchproj.transport.StateCalibration` whose lit pixels are
            scored (default: the calibration's own; a run on homography maps passes those).
        noise: camera noise in the captures, as on a bench.
    """
    states = calibration.states if states is None else states
    check(len(patterns) == len(calibration.rig.scene.projectors),
          f"give one pattern per projector ({len(calibration.rig.scene.projectors)}), got {len(patterns)}")
    check(scale > 0, f"scale must be positive, got {scale}")
    device = calibration.rig.device
    shown = {j: (p.float() / 255 if p.dtype == torch.uint8 else p.float())[None].to(device)
             for j, p in enumerate(patterns)}
    captures = {state: calibration.rig.capture(state, shown, noise=noise)[0].cpu()
                for state in dict.fromkeys(t.state for t in targets)}
    scores = []
    for k, target in enumerate(targets):
        lit = states[target.state].lit()
        region = lit if target.mask is None else lit & target.mask
        values, covered = target_on_camera(target, region)
        estimate = ((captures[target.state] - calibration.black[target.state]) / scale).clamp(0, 1)
        others = [target_on_camera(Target(target.state, t.image, name=t.name), region)[0]
                  for m, t in enumerate(targets) if m != k]
        scores.append(TargetScore(name=target.name, state=target.state, **score_image(estimate, values, covered),
                                  crosstalk=crosstalk(estimate, others, covered), pixels=int(covered.sum()),
                                  estimate=estimate, values=values, covered=covered))
    return PatternEvaluation(scores, captures)
