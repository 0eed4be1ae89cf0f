"""torchproj: multi-projector depth-dependent projection in PyTorch.

What a user reaches for is here; each sub-package holds the rest:

- :mod:`torchproj.scene`: rig and scene descriptions (``load_scene``).
- :mod:`torchproj.sim`: the virtual rig (``VirtualRig``).
- :mod:`torchproj.calib`: Gray code, decoding, response fit, capture folders and bundles (``load_bundle``).
- :mod:`torchproj.transport`: the sparse light-transport operator ``i = A p`` (``TransportOperator``).
- :mod:`torchproj.solve`: box-constrained solvers, ``ClampedAdam``, the image-space ``ProjectionModel``.
- :mod:`torchproj.metrics`: PSNR, SSIM (differentiable), crosstalk.
- :mod:`torchproj.pipeline`: the whole workflow on the virtual rig (``calibrate_virtual``, ``evaluate_patterns``).
- :mod:`torchproj.experiments`: depth sweeps and the positioning test.

Conventions (pixel centres, ``(x, y)`` order, frames) are stated once in :mod:`torchproj.core.conventions`.
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
    "solve": "OBJECTIVES SOLVERS ClampedAdam ImageLoss ProjectionModel SolveResult make_patterns refine_patterns "
             "solve_adam solve_eo solve_fista solve_lf solve_patterns solve_pgd solve_ssim",
    "transport": "StateCalibration Target TransportOperator build_transport",
}
_WHERE = {**{package: package for package in _OFFERED},
          **{name: package for package, names in _OFFERED.items() for name in names.split()}}
__getattr__, __dir__ = lazy_names(__name__, _WHERE)

__all__ = sorted(["__version__", *_WHERE])
