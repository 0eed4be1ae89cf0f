"""torchproj: multi-projector depth-dependent projection in PyTorch.

The face, one line each (each sub-package holds the rest; conventions, pixel centres and ``(x, y)``
order, are stated once in :mod:`torchproj.core.conventions`):

Scenes and the virtual rig
- ``load_scene``: a scene from a YAML file, a built-in name or ``suite-SEED-INDEX``.
- ``Scene``: a validated rig and scene description; ``BUILTIN_SCENES``: the shipped scenes' names.
- ``VirtualRig``: the simulated rig, which captures any pattern sequence.

Calibration
- ``calibrate_virtual``: simulate and decode a scene's calibration; ``VirtualCalibration``: its result.
- ``calibrate_folders``: calibrate a bench's capture folders; ``load_bundle``: read a saved calibration.
- ``CalibrationBundle``: what calibration recovered; ``ResponseCurve``: a projector's ``a x^b + c``.
- ``graycode_patterns``: the Gray-code sequence to show; ``decode_gray``: decode its captures.

Light transport
- ``Target``: an image to show in one state; ``scene_targets``: a scene's targets; ``target_image``: an image by name.
- ``StateCalibration``: one state's maps; ``build_transport``: the sparse operator ``i = A p`` of targets.
- ``TransportOperator``: ``A``, ``A_adjoint`` and the maps back to cells and camera pixels (an ``nn.Module``).

Solving
- ``solve_patterns``: solve by name (``SOLVERS``); ``solve_fista``, ``solve_pgd``, ``solve_adam``, ``solve_lf``,
  ``solve_eo``: each solver; ``SolveResult``: what they return.
- ``make_patterns``: solve and compensate to 8-bit projector images.
- ``solve_ssim``: least squares refined on SSIM within a PSNR budget (``OBJECTIVES``); ``ImageLoss``: its loss.
- ``refine_patterns``: camera in the loop, patterns corrected from captures; ``rig_measure``: the rig's captures for it.

Training like a network
- ``ProjectionModel``: patterns as an ``nn.Parameter``; ``forward()`` predicts each target's camera image.
- ``ClampedAdam``: Adam that keeps parameters in the box.
- ``SSIMLoss``: the reported SSIM as a loss; ``PSNRBudget``: each target within a PSNR budget.

Scores and workflow
- ``evaluate_patterns``: show patterns on the virtual rig and score every target.
- ``psnr``, ``ssim``, ``crosstalk``: the scores.
- ``run_virtual``: the whole ``torchproj run`` workflow; ``shown_world``: a calibration's world as shown.
- ``InputError``, ``TorchprojError``: the errors torchproj raises (``ValueError`` subclasses).

Sub-packages: ``scene``, ``sim``, ``calib``, ``transport``, ``solve``, ``metrics``, ``pipeline``,
``experiments``, ``core``.
"""

__version__ = "0.1.0"

from ._lazy import lazy_names  # noqa: E402

# Each sub-package's names on the face, imported on first use (torchproj._lazy): `import torchproj`
# and the `torchproj` command start without torch.
_OFFERED = {
    "calib": "CalibrationBundle ResponseCurve calibrate_folders decode_gray graycode_patterns load_bundle",
    "core": "InputError TorchprojError",
    "experiments": "",
    "metrics": "SSIMLoss crosstalk psnr ssim",
    "pipeline": "VirtualCalibration calibrate_virtual evaluate_patterns rig_measure run_virtual scene_targets "
                "shown_world target_image",
    "scene": "BUILTIN_SCENES Scene load_scene",
    "sim": "VirtualRig",
    "solve": "OBJECTIVES SOLVERS ClampedAdam ImageLoss PSNRBudget ProjectionModel SolveResult make_patterns refine_patterns "
             "solve_adam solve_eo solve_fista solve_lf solve_patterns solve_pgd solve_ssim",
    "transport": "StateCalibration Target TransportOperator build_transport",
}
_WHERE = {**{package: package for package in _OFFERED},
          **{name: package for package, names in _OFFERED.items() for name in names.split()}}
__getattr__, __dir__ = lazy_names(__name__, _WHERE)

__all__ = sorted(["__version__", *_WHERE])
