"""torchproj: multi-projector depth-dependent projection in PyTorch.

What a user reaches for is here; each room (sub-package) holds the rest:

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

from . import calib, core, experiments, metrics, pipeline, scene, sim, solve, transport  # noqa: E402
from .calib import CalibrationBundle, ResponseCurve, calibrate_folders, decode_gray, graycode_patterns, load_bundle  # noqa: E402
from .core import InputError, TorchprojError  # noqa: E402
from .metrics import SSIMLoss, crosstalk, psnr, ssim  # noqa: E402
from .pipeline import (VirtualCalibration, calibrate_virtual, evaluate_patterns, rig_measure, run_virtual,  # noqa: E402
                       scene_targets, shown_world, target_image)
from .scene import BUILTIN_SCENES, Scene, load_scene  # noqa: E402
from .sim import VirtualRig  # noqa: E402
from .solve import (OBJECTIVES, SOLVERS, ClampedAdam, ImageLoss, ProjectionModel, SolveResult, make_patterns,  # noqa: E402
                    refine_patterns, solve_adam, solve_eo, solve_fista, solve_lf, solve_patterns, solve_pgd, solve_ssim)
from .transport import StateCalibration, Target, TransportOperator, build_transport  # noqa: E402

__all__ = [
    "BUILTIN_SCENES", "CalibrationBundle", "ClampedAdam", "ImageLoss", "InputError", "OBJECTIVES", "ProjectionModel", "ResponseCurve",
    "SOLVERS", "SSIMLoss", "Scene", "SolveResult", "StateCalibration", "Target", "TorchprojError", "TransportOperator",
    "VirtualCalibration", "VirtualRig", "__version__", "build_transport", "calib", "calibrate_folders",
    "calibrate_virtual", "core", "crosstalk", "decode_gray", "evaluate_patterns", "experiments", "graycode_patterns",
    "load_bundle", "load_scene", "make_patterns", "metrics", "pipeline", "psnr", "refine_patterns", "rig_measure",
    "run_virtual", "scene", "scene_targets", "shown_world", "sim", "solve", "solve_adam", "solve_eo", "solve_fista", "solve_lf", "solve_patterns",
    "solve_pgd", "solve_ssim", "ssim", "target_image", "transport",
]
