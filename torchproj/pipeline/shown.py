"""The world the patterns are shown in, on the virtual rig, and the camera that looks at it in the loop.

A scene with a ``show:`` section (:mod:`torchproj.scene.show`) is calibrated as written and shown
changed. :func:`shown_world` is the calibration's view of that world: the solver keeps what
calibration measured (maps, weights, responses), while captures, black frames, the exact light and
the responses a ceiling compensates with are the shown world's. :func:`rig_measure` is the camera
of :func:`~torchproj.solve.refine_patterns` on the virtual rig.
"""

from __future__ import annotations

import dataclasses

import torch

from ..core.checks import check, check_count
from ..scene.config import check_scene
from ..scene.show import shown_scene
from ..transport import Target
from ..transport.build import check_targets
from ..transport.operator import check_operators
from .scoring import as_light
from .virtual import VirtualCalibration, check_virtual_calibration, quiet_rig, true_responses

__all__ = ["CapturedRows", "rig_measure", "shown_world"]


def shown_world(cal: VirtualCalibration, scene=None, prepare=None) -> VirtualCalibration:
    """``cal`` with the rig, black captures and responses of the world as shown (module docs).

    ``scene``: the scene whose ``show`` applies (default: the calibrated one). A scene without
    ``show`` is shown in the world it was calibrated in: ``cal`` itself. Otherwise
    each state's black frame is captured anew (every projector black, with noise, as a bench takes
    one before showing), so that room light that changed since calibration is not scored as error.
    ``prepare``: called with the new world's rig before it captures anything (a run gives it the
    rays an earlier run cast there, :func:`~torchproj.pipeline.cache.read_geometry`).
    """
    check_virtual_calibration(cal, "cal")
    scene = cal.rig.scene if scene is None else check_scene(scene)
    if scene.show is None:
        return cal
    rig = quiet_rig(shown_scene(scene), cal.rig.device)
    if prepare is not None:
        prepare(rig)
    black = {state: rig.capture(state, {})[0].cpu() for state in cal.black}
    return dataclasses.replace(cal, rig=rig, black=black, responses=true_responses(rig.scene))


class CapturedRows:
    """Reads an operator's rows out of camera images, one image per state (a row's state is its
    target's): what every camera loop measures, on the virtual rig (:func:`rig_measure`) or a bench.

    Args:
        op: the operator (rows on camera pixels), or one per colour channel with the same rows.
        targets: the targets it was built for.
    """

    def __init__(self, op, targets: list[Target]):
        ops = check_operators(op)
        check_targets(targets)
        self.op = ops[0]
        check(self.op.row_pixel is not None, "the loop measures camera pixels: build the operator with merge=False")
        self.channels = len(ops) if len(ops) > 1 else self.op.rhs.shape[1]
        states = [t.state for t in targets]
        self.rows_of = {state: torch.nonzero(torch.isin(self.op.row_target, torch.tensor(
            [k for k, s in enumerate(states) if s == state], device=self.op.row_target.device)))[:, 0]
            for state in dict.fromkeys(states)}

    def __call__(self, above: dict[str, torch.Tensor]) -> torch.Tensor:
        """``above``: per state, :math:`(C_{cam}, H, W)` camera values above black. Returns the rows,
        :math:`(N_{rows}, C)` (a grey operator of a colour camera takes the channels' mean)."""
        op = self.op
        rows = torch.empty(op.shape[0], self.channels, dtype=op.rhs.dtype, device=op.rhs.device)
        for state, which in self.rows_of.items():
            rows[which] = self.state_rows(above[state], state)
        return rows

    def state_rows(self, image: torch.Tensor, state: str) -> torch.Tensor:
        """``state``'s rows read out of one :math:`(C_{cam}, H, W)` image, :math:`(N_{state}, C)`:
        any image, so that a photo can be read as another state's."""
        which = self.rows_of[state]
        values = image.flatten(1)[:, self.op.row_pixel[which].cpu()].T  # (rows, C_cam)
        values = values if values.shape[1] == self.channels else values.mean(1, keepdim=True)
        return values.to(self.op.rhs.device, self.op.rhs.dtype)


def rig_measure(world: VirtualCalibration, op, targets: list[Target], frames: int = 1, noise: bool = True):
    """The captured rows of patterns on the virtual rig, for :func:`~torchproj.solve.refine_patterns`.

    Args:
        world: where the patterns are shown (:func:`shown_world`).
        op: the operator whose rows are measured (rows on camera pixels), or one per colour channel
            (they share rows; column c of the result is channel c).
        targets: the targets it was built for (a row's state is its target's).
        frames: captures averaged per state and iteration (camera noise falls as its square root).
        noise: False measures the expected captures (no noise, no quantisation) above the expected
            black frame: the exact light, for a ceiling.

    Returns:
        ``measure(images) -> (N_rows, C)``: camera values above the state's black frame at each row's
        pixel; ``measure.captures`` counts the captures taken per state.
    """
    check_virtual_calibration(world, "world")
    frames = check_count(frames, "frames")
    read = CapturedRows(op, targets)
    black = world.black if noise else {state: world.rig.capture(state, {}, noise=False, quantise=False)[0].cpu()
                                       for state in read.rows_of}

    def measure(images: list[torch.Tensor]) -> torch.Tensor:
        shown = as_light(images, len(world.rig.scene.projectors), world.rig.device)
        above = {state: world.rig.capture(state, {j: s.expand(frames, -1, -1, -1) for j, s in shown.items()},
                                          noise=noise, quantise=noise).mean(0).cpu() - black[state]
                 for state in read.rows_of}
        measure.captures += frames
        return read(above)

    measure.captures = 0
    return measure
