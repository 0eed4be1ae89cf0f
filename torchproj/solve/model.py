"""The image-space model: patterns as parameters, and the camera image each target will show.

Solvers see the transport operator's rows; people and losses see images. :class:`ProjectionModel`
holds the patterns as an ``nn.Parameter`` and predicts, differentiably, what the camera captures of
each target, so that any torch loss (SSIM, gradients, a perceptual metric, a crosstalk penalty) can
drive them in a training-style loop. :func:`solve_ssim` is such a loop.

Units (the evaluation's): a predicted image is in *target units*, the camera value minus the
state's black capture, over the operator's ``scale``, so 1 asks for a target's white and 0 for the
state's black; compare it with the target image directly.
"""

from __future__ import annotations

import torch
from torch import nn

from ..core.checks import check, check_finite
from ..transport.build import DEFAULT_FOOTPRINT, StateCalibration, Target, build_operators
from ..transport.operator import TransportOperator, check_operators
from .compensate import projectable_patterns
from .solvers import check_bounds, check_patterns_shape, solve_fista

__all__ = ["ProjectionModel", "calibration_parts"]


def calibration_parts(calibration) -> tuple[dict[str, StateCalibration], list | None]:
    """Per-state calibrations and per-projector response curves, from any calibration torchproj makes.

    Args:
        calibration: a :class:`~torchproj.calib.CalibrationBundle` (``torchproj calibrate``,
            :func:`~torchproj.calib.load_bundle`), a virtual-rig calibration
            (:func:`~torchproj.calibrate_virtual`), or a dict of state name ->
            :class:`~torchproj.transport.StateCalibration` (then no responses).

    Returns:
        ``(states, responses)``; ``responses`` None where the calibration holds none.
    """
    from ..calib.bundle import CalibrationBundle

    if isinstance(calibration, CalibrationBundle):
        return StateCalibration.from_bundle(calibration), calibration.response_curves()
    states = getattr(calibration, "states", calibration)
    check(isinstance(states, dict) and len(states) > 0
          and all(isinstance(s, StateCalibration) for s in states.values()),
          f"calibration must be a CalibrationBundle (torchproj calibrate), a virtual calibration "
          f"(calibrate_virtual) or a dict of StateCalibration, got {type(calibration).__name__}")
    return states, getattr(calibration, "responses", None)


class _Channels(nn.Module):
    """One operator per colour channel (:func:`~torchproj.transport.build_channel_transports`) as
    one with ``C`` channels: column ``c`` of the patterns goes through operator ``c``. An image loss
    needs the predicted rows, the targets and the rows' camera pixels, which the channels share.

    A tinted surface is why: one grey weight mispredicts every channel of it, and on ``suite-777-3``
    (albedo 0.54 / 0.82 / 0.50) an SSIM solve on the grey model lost 7.8 and 11.7 dB of PSNR on two
    targets against the channels' least squares, the SSIM of one of them falling too."""

    def __init__(self, ops: list[TransportOperator]):
        super().__init__()
        check(all(isinstance(o, TransportOperator) for o in ops), "give TransportOperators, one per colour channel")
        check(len({(o.shape, o.target_count) for o in ops}) == 1 and all(o.channels == 1 for o in ops),
              "give one single-channel operator per colour channel with the same rows and columns "
              "(build_channel_transports)")
        self.ops = nn.ModuleList(ops)
        first = ops[0]
        self.shape, self.scale, self.target_count = first.shape, first.scale, first.target_count
        self.projector_sizes = first.projector_sizes

    # Tensors read from the operators when asked, so that they follow the operators to a device.
    @property
    def rhs(self) -> torch.Tensor:
        return torch.cat([o.rhs for o in self.ops], 1)

    @property
    def row_pixel(self) -> torch.Tensor | None:
        return self.ops[0].row_pixel

    @property
    def row_target(self) -> torch.Tensor:
        return self.ops[0].row_target

    @property
    def val(self) -> torch.Tensor:
        return self.ops[0].val

    @property
    def channels(self) -> int:
        return len(self.ops)

    def A(self, p: torch.Tensor) -> torch.Tensor:
        """``A p`` :math:`(N_{rows}, C)`; with :math:`C B` columns, ``B`` members side by side per
        channel (column ``c B + b``: member ``b``'s channel ``c``, as :meth:`ProjectionModel.forward`
        lays a batch out)."""
        width = p.shape[1] // len(self.ops)
        check(width * len(self.ops) == p.shape[1], f"p must have a multiple of {len(self.ops)} columns (the channels), "
                                                   f"got {p.shape[1]}")
        return torch.cat([o.A(p[:, c * width:(c + 1) * width]) for c, o in enumerate(self.ops)], 1)

    def to_images(self, p: torch.Tensor) -> list[torch.Tensor]:
        return self.ops[0].to_images(p)

    def objective(self, p: torch.Tensor) -> torch.Tensor:
        return sum(o.objective(p[:, c:c + 1]) for c, o in enumerate(self.ops))

    def to_camera(self, values: torch.Tensor) -> torch.Tensor:
        return self.ops[0].to_camera(values)

    def camera_masks(self) -> torch.Tensor:
        return self.ops[0].camera_masks()


def _one_operator(op):
    """``op``, or a list of one operator per colour channel as one (:class:`_Channels`)."""
    if isinstance(op, (list, tuple)):
        check(len(op) >= 1, "give an operator, or one per colour channel")
        return op[0] if len(op) == 1 else _Channels(list(op))
    return op


def image_operator(op):
    """``op`` as one operator (:func:`_one_operator`), checked to predict camera images: a
    :class:`~torchproj.transport.TransportOperator` (or one per colour channel) whose rows are
    camera pixels. The one check of :class:`ProjectionModel` and :class:`~torchproj.solve.ImageLoss`."""
    op = _one_operator(op)
    check(isinstance(op, (TransportOperator, _Channels)), f"operator must be a TransportOperator (or a list "
                                                          f"of one per colour channel), got {type(op).__name__}")
    check(op.row_pixel is not None, "the operator's rows are merged and mix camera pixels: build it with "
                                    "build_transport(..., merge=False) for an image-space model")
    return op


def _least_squares(op, bounds, smoothness: float | None = None) -> torch.Tensor:
    """FISTA's bounded least squares with the smoothness penalty (None: ``torchproj run``'s default),
    each colour channel's alone where ``op`` holds one per channel."""
    from .compensate import resolve_smoothness

    smoothness = resolve_smoothness("fista", smoothness)
    return torch.cat([solve_fista(o.with_smoothness(smoothness), bounds, progress=False).patterns
                      for o in check_operators(op)], 1)


class ProjectionModel(nn.Module):
    """Patterns as parameters; ``forward()`` predicts the camera image of every target.

    Args:
        operator: a :class:`~torchproj.transport.TransportOperator` whose rows are camera pixels
            (``build_transport(..., merge=False)``): the prediction is ``A p`` placed on them. Or
            a list of one per colour channel (:func:`~torchproj.transport.build_channel_transports`):
            channel ``c`` of the prediction is operator ``c`` times channel ``c`` of the patterns.
        bounds: the box ``(lo, hi)`` in linear light the patterns must stay in (the paper's 8-bit
            bounds over 255). A plain optimiser steps out of it: use
            :class:`~torchproj.solve.ClampedAdam` with ``bounds=model.bounds``, or :meth:`clamp_`
            after each step.
        responses: per projector, its :class:`~torchproj.calib.ResponseCurve` (for :meth:`to_patterns`).
        start: :math:`(N_{cols}, C)` initial patterns inside ``bounds``; None: the middle of the box.

    Attributes:
        patterns: ``nn.Parameter`` :math:`(N_{cols}, C)`: each lit projector cell's linear light
            (columns of the operator; :meth:`TransportOperator.to_images` shows them per projector).
        targets: :math:`(K, C, H, W)` buffer: each target image on the camera, target units, 0
            outside its mask.
        mask: :math:`(K, H, W)` bool buffer: the camera pixels that show target k.

    Shape:
        ``forward()``: :math:`(K, C, H, W)`, target units (see the module), 0 outside ``mask``.

    Example:
        >>> model = ProjectionModel.from_calibration(calibration, targets)
        >>> opt = ClampedAdam(model.parameters(), lr=1e-3, bounds=model.bounds)
        >>> loss = SSIMLoss(model.targets, model.mask)(model()).mean()
    """

    def __init__(self, operator: TransportOperator | list[TransportOperator], bounds=(0.0, 1.0),
                 responses: list | None = None, start: torch.Tensor | None = None):
        super().__init__()
        operator = image_operator(operator)
        self.bounds = check_bounds(bounds)
        check(responses is None or len(responses) == len(operator.projector_sizes),
              f"give one response curve per projector ({len(operator.projector_sizes)}), got "
              f"{None if responses is None else len(responses)}")
        self.operator = operator
        self.responses = responses
        lo, hi = self.bounds
        shape = (operator.shape[1], operator.channels)
        if start is None:
            start = torch.full(shape, 0.5 * (lo + hi), dtype=operator.val.dtype, device=operator.val.device)
        else:
            check_patterns_shape(operator, start)
            check_finite(start, "start")
            low, high = float(start.min()), float(start.max())
            check(low >= lo - 1e-6 and high <= hi + 1e-6, f"start must lie in the bounds [{lo:g}, {hi:g}], got values "
                                                           f"in [{low:.4g}, {high:.4g}]; clamp it or widen the bounds")
            start = start.detach().to(operator.val.device, operator.val.dtype).clamp(lo, hi)
        self.patterns = nn.Parameter(start.clone())
        self.register_buffer("targets", operator.to_camera(operator.rhs / operator.scale))
        self.register_buffer("mask", operator.camera_masks())

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # The box is the model's contract (the constructor enforces it on ``start``): patterns from a
        # checkpoint outside it are refused before anything is loaded, not clamped without a word.
        patterns = state_dict.get(prefix + "patterns")
        if isinstance(patterns, torch.Tensor) and patterns.numel():
            lo, hi = self.bounds
            low, high = float(patterns.min()), float(patterns.max())
            check(low >= lo - 1e-6 and high <= hi + 1e-6,
                  f"the state_dict's patterns lie in [{low:.4g}, {high:.4g}], outside this model's bounds "
                  f"[{lo:g}, {hi:g}]: clamp them, or build the model with the bounds they were trained in")
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @classmethod
    def from_calibration(cls, calibration, targets: list[Target], *, bounds=(0.0, 1.0), footprint: str = DEFAULT_FOOTPRINT,
                         scale: float | None = None, start: str | torch.Tensor | None = "l2",
                         colour_weights: str = "channel", device="cpu",
                         smoothness: float | None = None) -> "ProjectionModel":
        """Build the operator (rows on camera pixels) and the model from a calibration and targets.

        Args:
            calibration: see :func:`calibration_parts`.
            targets: one :class:`~torchproj.transport.Target` per image to show.
            footprint, scale: as in :func:`~torchproj.transport.build_transport` (the default footprint is
                ``torchproj run``'s, so that a script trains the model ``run`` solves).
            start: ``"l2"``: the least-squares optimum in the box (FISTA to a 1e-6 relative
                change; about a second at full size), the best start for any image loss measured
                (``benchmarks/objectives.py``); None: the middle of the box; or a tensor.
            colour_weights: colour targets on a calibration that measured each channel's white
                minus black: ``"channel"`` models each channel with its own (``torchproj run``'s
                default), ``"grey"`` gives every channel their mean.
            smoothness: the least-squares start's penalty on neighbouring cells' differences
                (:meth:`~torchproj.transport.TransportOperator.with_smoothness`; None: ``torchproj
                run``'s default, 0: none). The model's own loss has none: add one in a script.
        """
        from ..core.choices import COLOUR_WEIGHTS
        from .compensate import resolve_smoothness

        check(colour_weights in COLOUR_WEIGHTS, f"colour_weights must be one of {list(COLOUR_WEIGHTS)}, got {colour_weights!r}")
        check(not isinstance(start, str) or start == "l2", f"start must be 'l2', None or a tensor, got {start!r}")
        check_bounds(bounds)  # before the operator is built, not after
        smoothness = resolve_smoothness("fista", smoothness)
        states, responses = calibration_parts(calibration)
        op = _one_operator(build_operators(states, targets, footprint=footprint, merge=False, colour_weights=colour_weights,
                                           scale=scale, device=device))
        if isinstance(start, str):
            start = _least_squares(op, bounds, smoothness)
        return cls(op, bounds, responses, start)

    @property
    def scale(self) -> float:
        """Camera value of a target value of 1 (:attr:`TransportOperator.scale`)."""
        return self.operator.scale

    def forward(self, patterns: torch.Tensor | None = None) -> torch.Tensor:
        """The camera image of every target (target units), for the model's patterns or others.

        Args:
            patterns: None (the model's own), :math:`(N, C)` like :attr:`patterns`, or a batch
                :math:`(B, N, C)` (a sweep, a population, frames of a video): one sparse product for
                the whole batch, its members side by side in the product's columns.

        Returns:
            :math:`(K, C, H, W)`, or :math:`(B, K, C, H, W)` for a batch.
        """
        p = self.patterns if patterns is None else patterns
        n, c = self.patterns.shape
        check(isinstance(p, torch.Tensor), f"patterns must be a torch.Tensor, got {type(p).__name__}")
        check(p.dim() in (2, 3) and tuple(p.shape[-2:]) == (n, c),
              f"patterns must be ({n}, {c}) like the model's, or a batch (B, {n}, {c}); got {tuple(p.shape)}")
        op = self.operator
        if p.dim() == 2:
            return op.to_camera(op.A(p) / op.scale)
        b = p.shape[0]
        # (B, N, C) -> (N, C B): column c B + b of the product is member b's channel c.
        rows = op.A(p.permute(1, 2, 0).reshape(n, c * b)) / op.scale
        images = op.to_camera(rows)  # (K, C B, H, W)
        return images.reshape(images.shape[0], c, b, *images.shape[2:]).permute(2, 0, 1, 3, 4)

    def straight_through(self, captured: torch.Tensor) -> torch.Tensor:
        """The camera images with a capture's values and the model's gradient: camera in the loop
        from a training script (the step :func:`~torchproj.solve.refine_patterns` takes to its end).

        ``loss(model.straight_through(captured), targets).backward()`` puts any torch loss on what
        the camera saw of :meth:`to_patterns`, and gives the patterns the gradient the transport
        model says that loss has.

        Args:
            captured: :math:`(K, C, H, W)` each target's capture above black, over :attr:`scale`
                (target units: what :meth:`forward` predicts), e.g. ``operator.to_camera(rows / scale)``
                of :func:`torchproj.pipeline.rig_measure`'s rows.
        """
        check(isinstance(captured, torch.Tensor), f"captured must be a torch.Tensor, got {type(captured).__name__}")
        predicted = self()
        check(captured.shape == predicted.shape, f"captured must be {tuple(predicted.shape)} like the model's images, "
                                                 f"got {tuple(captured.shape)}")
        return predicted + (captured.to(predicted) - predicted).detach()

    @torch.no_grad()
    def clamp_(self) -> "ProjectionModel":
        """Project the patterns into the bounds (after a step of an optimiser that does not)."""
        self.patterns.clamp_(*self.bounds)
        return self

    def to_patterns(self) -> list[torch.Tensor]:
        """The 8-bit images to send to each projector, :math:`(C, H_j, W_j)` uint8, on the CPU.

        The same steps as :func:`~torchproj.solve.make_patterns`: values outside [0, 1] brought into
        range (:func:`~torchproj.solve.to_projectable`), then each projector's inverse response.
        """
        check(self.responses is not None, "this model holds no response curves: give responses=... (or build it with "
                                          "from_calibration from a calibration that has them)")
        return projectable_patterns(self.operator, self.patterns, self.bounds, self.responses)[1]
