"""Box-constrained pattern solvers on the transport operator, and compensation to 8-bit patterns."""

from .compensate import check_solve_options, compensate, make_patterns, projectable_patterns
from .eo import CHAINS, component_chains, epipolar_bands, epipolar_chains, fundamental_between_projectors, solve_eo
from .gain_offset import solve_gain_offset
from .model import ProjectionModel, calibration_parts
from .objectives import (OBJECTIVES, PSNR_DROP_DB, ImageLoss, ImageObjective, PSNRBudget, image_objective, psnr_hinge,
                         solve_ssim)
from .refine import REFINE_SOLVER_ITERATIONS, RefineResult, captured_loss, refine_patterns
from .solvers import (LF_NORMALISE, OUTSIDE, ClampedAdam, SolveResult, check_bounds, solve_adam, solve_fista, solve_lf, solve_pgd, solve_target_sets,
                      to_projectable)

#: solver name -> its function: ``solve_patterns(op, name, ...)`` calls ``SOLVERS[name](op, bounds, ...)``.
SOLVERS = {"lf": solve_lf, "eo": solve_eo, "pgd": solve_pgd, "fista": solve_fista, "adam": solve_adam}


def check_solver(method) -> None:
    """``method`` one of :data:`SOLVERS`' names (a list or a dict in its place is named, not unhashable)."""
    from ..core.checks import check

    check(isinstance(method, str) and method in SOLVERS, f"unknown solver {method!r}; choose from {sorted(SOLVERS)}")


def solve_patterns(op, method: str = "fista", bounds=(0.0, 1.0), **kwargs) -> SolveResult:
    """Solve with a named method (``lf``, ``eo``, ``pgd``, ``fista``, ``adam``); see each ``solve_*``."""
    from ..core.checks import check

    check_solver(method)
    import inspect

    # Named here, not as Python's "got an unexpected keyword argument" from inside the solver (a
    # run's solver_options reach this point from a dict).
    options = [name for name, p in inspect.signature(SOLVERS[method]).parameters.items()
               if p.kind is p.KEYWORD_ONLY]
    unknown = sorted(set(kwargs) - set(options))
    check(not unknown, f"solver {method!r} takes no option {', '.join(map(repr, unknown))}; its options: {options}")
    return SOLVERS[method](op, bounds, **kwargs)


__all__ = ["CHAINS", "ClampedAdam", "ImageLoss", "ImageObjective", "LF_NORMALISE", "OBJECTIVES", "OUTSIDE", "PSNRBudget", "PSNR_DROP_DB", "ProjectionModel", "REFINE_SOLVER_ITERATIONS", "RefineResult", "SOLVERS", "SolveResult", "calibration_parts", "captured_loss", "check_bounds",
           "check_solve_options",
           "compensate", "component_chains", "epipolar_bands", "epipolar_chains", "fundamental_between_projectors", "image_objective",
           "make_patterns", "projectable_patterns", "psnr_hinge", "refine_patterns", "solve_adam", "solve_eo", "solve_fista", "solve_gain_offset",
           "solve_lf", "solve_patterns", "solve_pgd", "solve_ssim", "solve_target_sets", "to_projectable"]
