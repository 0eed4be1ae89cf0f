"""Bad values through the Python face, as a script or a notebook passes them: every argument of the
functions a user calls, given values of the wrong kind. The contract, as for the commands
(tests/test_bad_inputs.py): the call works, or it raises a :class:`~torchproj.core.TorchprojError`
(an ``InputError``, ``ConfigError`` or ``CaptureError``, all ``ValueError``) that names what it was
given; never an AttributeError, TypeError or KeyError from deep inside.

Each value goes to one argument at a time, the others as a working call has them. Arguments whose
truth is all that is read (``progress``, ``merge``, ``noise``) and callbacks a user writes are left out.
"""

from __future__ import annotations

import pytest
import torch

import torchproj as tp
from torchproj.core import TorchprojError

from .helpers import SIZES, calibrate_once, small_scene, synthetic_calibration, targets

# What a slip of the keyboard or the wrong variable gives: nothing, text, containers, NaN, a bool, a
# negative number, a tensor of several values.
WRONG = [None, "x", [1, 2], {"a": 1}, float("nan"), True, -1, torch.zeros(3)]


def _mishandled(call, names, wrong=WRONG) -> list[str]:
    failures = []
    for name in names:
        for value in wrong:
            try:
                call(**{name: value})
            except TorchprojError:
                pass
            except Exception as exc:  # noqa: BLE001 - such an exception is what this test looks for
                failures.append(f"{name}={value!r}: {type(exc).__name__}: {str(exc)[:200]}")
    return failures


@pytest.fixture(scope="module")
def problem():
    cals, tgts = synthetic_calibration(), targets()
    op = tp.build_transport(cals, tgts, merge=False)
    curves = [tp.ResponseCurve(torch.ones(1), torch.ones(1), torch.zeros(1))] * len(SIZES)
    return cals, tgts, op, curves


def test_the_solving_face_names_values_of_the_wrong_kind(problem):
    cals, tgts, op, curves = problem
    image, mask = torch.rand(1, 20, 20), torch.ones(20, 20, dtype=torch.bool)
    calls = {
        "build_transport": (lambda **k: tp.build_transport(**{"calibrations": cals, "targets": tgts, **k}),
                            ["calibrations", "targets", "footprint", "scale", "device"]),
        "Target": (lambda **k: tp.build_transport(cals, [tp.Target(**{"state": "near", "image": image, **k})]),
                   ["state", "image", "mask", "corners", "name"]),
        "solve_patterns": (lambda **k: tp.solve_patterns(**{"op": op, "max_iter": 3, **k}),
                           ["op", "method", "bounds", "max_iter", "tol", "x0", "levels", "form"]),
        "solve_ssim": (lambda **k: tp.solve_ssim(**{"op": op, "max_iter": 2, **k}),
                       ["bounds", "l2_weight", "psnr_drop", "x0", "max_iter", "lr", "tol", "offset"]),
        "make_patterns": (lambda **k: tp.make_patterns(**{"op": op, "solver": "fista", "bounds": (0, 1),
                                                          "responses": curves, "max_iter": 3, **k}),
                          ["solver", "bounds", "responses", "objective", "outside", "solver_options"]),
        "ProjectionModel": (lambda **k: tp.ProjectionModel(**{"operator": op, **k})(), ["operator", "bounds", "start"]),
        "ImageLoss": (lambda **k: tp.ImageLoss(**{"op": op, "start": torch.rand(op.shape[1], 1), **k}),
                      ["start", "l2_weight", "psnr_drop", "offset"]),
        "A": (lambda **k: op.A(**k), ["p"]),
        "refine_patterns": (lambda **k: tp.refine_patterns(**{"op": op, "start": torch.rand(op.shape[1], 1),
                                                              "measure": lambda images: op.A(torch.rand(op.shape[1], 1)),
                                                              "responses": curves, "iterations": 1, **k}),
                            ["start", "measure", "bounds", "responses", "iterations", "objective", "relax",
                             "solver_iterations", "remodel"]),
        "psnr": (lambda **k: tp.psnr(**{"estimate": image, "reference": image, **k}), ["estimate", "reference", "data_range"]),
        "ssim": (lambda **k: tp.ssim(**{"estimate": image, "reference": image, "mask": mask, **k}),
                 ["estimate", "reference", "mask", "data_range"]),
        "crosstalk": (lambda **k: tp.crosstalk(**{"captured": image, "others": [image], "mask": mask, **k}),
                      ["captured", "others", "mask"]),
        "SSIMLoss": (lambda **k: tp.SSIMLoss(**{"reference": image, "mask": mask, **k})(image),
                     ["reference", "mask", "data_range"]),
    }
    failures = [f"{name}({line}" for name, (call, names) in calls.items() for line in _mishandled(call, names)]
    assert not failures, f"{len(failures)} value(s) mishandled:\n" + "\n".join(failures)


def test_the_calibration_and_scene_face_names_values_of_the_wrong_kind(tmp_path):
    patterns = tp.graycode_patterns(16, 8)
    capture = dict(patterns=patterns[:-2], white=patterns[-2], black=patterns[-1], projector_size=(16, 8))
    scene = small_scene(camera=(160, 120), projector=(64, 48))
    calls = {
        "graycode_patterns": (lambda **k: tp.graycode_patterns(**{"width": 16, "height": 8, **k}), ["width", "height", "bits"]),
        "decode_gray": (lambda **k: tp.decode_gray(**{**capture, **k}),
                        ["patterns", "white", "black", "projector_size", "white_threshold", "black_threshold", "bits"]),
        "load_scene": (lambda **k: tp.load_scene(**{"path": "paper_two_planes", **k}), ["path", "scale", "size_limit"]),
        "load_bundle": (lambda **k: tp.load_bundle(**k), ["folder"]),
        "calibrate_folders": (lambda **k: tp.calibrate_folders(**{"root": tmp_path, **k}),
                              ["root", "sizes", "states", "bits", "black_threshold", "ramp_steps", "plane_tolerance",
                               "crease_ratio", "max_hole"]),
        "target_image": (lambda **k: tp.target_image(**{"name": "camera", "channels": 1, **k}), ["name", "channels"]),
        "scene_targets": (lambda **k: tp.scene_targets(**{"scene": scene, **k}), ["scene", "images"]),
        # Values run_virtual takes would calibrate: the calibration is refused first, so that they cost nothing.
        "run_virtual": (lambda **k: tp.run_virtual(**{"scene": scene, "calibration": "none", **k}),
                        ["scene", "solver", "bounds_8bit", "images", "device", "max_iter", "oracle", "gain_offset",
                         "maps", "objective", "footprint", "outside", "chains", "solver_options", "colour_weights",
                         "refine", "refine_frames", "refine_relax", "smoothness"]),
        "VirtualRig.capture": (lambda **k: tp.VirtualRig(scene).capture(**{"state": "near", "patterns": {}, **k}),
                               ["state", "patterns", "seed"]),
    }
    failures = [f"{name}({line}" for name, (call, names) in calls.items() for line in _mishandled(call, names)]
    assert not failures, f"{len(failures)} value(s) mishandled:\n" + "\n".join(failures)


def test_the_virtual_rig_face_names_values_of_the_wrong_kind():
    from torchproj.experiments import evaluate_positioning

    scene = small_scene(camera=(160, 120), projector=(64, 48))
    cal = calibrate_once(scene)
    tgts = tp.scene_targets(scene, rig=cal.rig)
    model = tp.ProjectionModel.from_calibration(cal, tgts, start=None)
    patterns, op = model.to_patterns(), model.operator
    calls = {
        "evaluate_patterns": (lambda **k: tp.evaluate_patterns(**{"calibration": cal, "patterns": patterns, "targets": tgts,
                                                                  "scale": model.scale, "paper": False, **k}),
                              ["calibration", "patterns", "targets", "scale", "states", "seed"]),
        "from_calibration": (lambda **k: tp.ProjectionModel.from_calibration(**{"calibration": cal, "targets": tgts,
                                                                               "start": None, **k}),
                             # scale and a start tensor are read with the operator (0.4 s a call): build_transport's
                             # and ProjectionModel's fuzz above has them.
                             ["calibration", "targets", "bounds", "footprint", "colour_weights", "smoothness"]),
        "shown_world": (lambda **k: tp.shown_world(**{"cal": cal, **k}), ["cal", "scene"]),
        "rig_measure": (lambda **k: tp.rig_measure(**{"world": cal, "op": op, "targets": tgts, **k}),
                        ["world", "op", "targets", "frames"]),
        # Values it takes would place boxes for a minute: a scene of planes is refused after them, at once.
        "evaluate_positioning": (lambda **k: evaluate_positioning(**{"scene": scene, **k}),
                                 ["scene", "trials", "spread_mm", "spread_deg", "seed", "max_evaluations", "profile_mm",
                                  "profile_steps", "max_iter", "solver"]),
    }
    failures = [f"{name}({line}" for name, (call, names) in calls.items() for line in _mishandled(call, names)]
    assert not failures, f"{len(failures)} value(s) mishandled:\n" + "\n".join(failures)
