"""Bad values through the Python face, as a script or a notebook passes them: every argument of the
functions a user calls, given values of the wrong kind. The contract, as for the commands
(tests/test_bad_inputs.py): the call works, or it raises a :class:`~torchproj.core.TorchprojError`
(an ``InputError``, ``ConfigError`` or ``CaptureError``, all ``ValueError``) that names what it was
given; never an AttributeError, TypeError or KeyError from deep inside.

Each value goes to one argument at a time, the others as a working call has them. Arguments whose
truth is all that is read (``progress``, ``merge``, ``noise``) and callbacks a user writes are left out.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

import torchproj as tp
from torchproj.core import TorchprojError

from torchproj.pipeline import capture_sequence

from .helpers import SIZES, RigDisplay, calibrate_once, small_scene, synthetic_calibration, targets

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


@pytest.fixture(scope="module")
def gray_capture():
    """A 16 x 8 projector's Gray code seen by a camera of two pixels per cell (every bit readable): its
    size, the capture and its decoding."""
    size = (16, 8)
    images = tp.graycode_patterns(*size).repeat_interleave(2, -1).repeat_interleave(2, -2)
    capture = dict(patterns=images[:-2], white=images[-2], black=images[-1])
    return size, capture, tp.decode_gray(**capture, projector_size=size)


def test_the_scene_and_bench_helpers_name_values_of_the_wrong_kind(tmp_path, monkeypatch, gray_capture):
    """The functions of the subpackages a bench script or a scene generator calls, below the top-level face."""
    import numpy as np
    import yaml

    from torchproj import calib, metrics, scene as sc

    monkeypatch.chdir(tmp_path)  # a value such as "x" is a path too: what it writes lands here
    size, capture, decoding = gray_capture
    prj_xy = decoding.prj_xy.float()
    points = torch.randn(200, 3) * torch.tensor([1.0, 1.0, 0.01]) + torch.tensor([0.0, 0.0, 1.0])
    config = yaml.safe_load(sc.builtin_config().read_text())
    image = torch.rand(1, 1, 20, 20)
    calls = {
        "look_at": (lambda **k: sc.look_at(**{"position": (0, 0, -1), "target": (0, 0, 1), **k}), ["position", "target", "up"]),
        "rotation_from_rotvec": (lambda **k: sc.rotation_from_rotvec(**{"rotvec": (0, 0.1, 0), **k}), ["rotvec"]),
        "rotation_from_euler_deg": (lambda **k: sc.rotation_from_euler_deg(**{"angles": (0, 1, 2), **k}), ["angles"]),
        "scale_config": (lambda **k: sc.scale_config(**{"data": config, "scale": 0.5, **k}), ["data", "scale", "camera", "projector"]),
        "parse_scene": (lambda **k: sc.parse_scene(**{"data": sc.procedural_config(1, 0), **k}), ["data", "base_dir", "size_limit"]),
        "shown_scene": (lambda **k: sc.shown_scene(**k), ["scene"]),
        "suite_names": (lambda **k: sc.suite_names(**{"count": 2, **k}), ["seed", "count", "size", "start"]),
        "ssim_map": (lambda **k: metrics.ssim_map(**{"estimate": image, "reference": image, **k}), ["estimate", "reference", "data_range"]),
        "write_sequence": (lambda **k: calib.write_sequence(**{"folder": tmp_path / "seq", "width": 16, "height": 8, "ramp_steps": 4, **k}),
                           ["folder", "width", "height", "ramp_steps", "bits"]),
        "primary_patterns": (lambda **k: calib.primary_patterns(**{"width": 16, "height": 8, **k}), ["width", "height"]),
        "ramp_pattern": (lambda **k: calib.ramp_pattern(**{"width": 16, "height": 8, "steps": 4, **k}), ["width", "height", "steps"]),
        "fit_homography": (lambda **k: calib.fit_homography(**{"prj_xy": prj_xy, **k}),
                           ["prj_xy", "block", "max_points", "soft_threshold", "iterations"]),
        "homography_map": (lambda **k: calib.homography_map(**{"matrix": torch.eye(3), "mask": decoding.valid, "projector_size": size, **k}),
                           ["matrix", "mask", "projector_size"]),
        "inverse_map": (lambda **k: calib.inverse_map(**{"prj_xy": prj_xy, "projector_size": size, **k}), ["prj_xy", "projector_size"]),
        "fill_holes": (lambda **k: calib.fill_holes(**{"values": prj_xy, **k}), ["values", "max_area"]),
        "refine_subpixel": (lambda **k: calib.refine_subpixel(**{"prj_xy": prj_xy, "valid": decoding.valid, **k}),
                            ["prj_xy", "valid", "window", "min_fill", "max_shift", "spread"]),
        "band_pixels": (lambda **k: calib.band_pixels(**{"prj_xy": prj_xy, **k}), ["prj_xy", "reach"]),
        "cell_shares": (lambda **k: calib.cell_shares(**{**capture, "decoding": decoding, "projector_size": size, **k}),
                        ["patterns", "white", "black", "decoding", "projector_size"]),
        "capture_noise": (lambda **k: calib.capture_noise(**{**capture, **k}), ["patterns", "white", "black", "pixels"]),
        "measure_ramp": (lambda **k: calib.measure_ramp(**{"ramp": capture["white"], "white": capture["white"], "black": capture["black"],
                                                           "prj_x": prj_xy[..., 0], "projector_width": 16, "steps": 4, **k}),
                         ["ramp", "prj_x", "projector_width", "steps", "margin", "min_contrast"]),
        "fit_colour_mixing": (lambda **k: calib.fit_colour_mixing(**{"primaries": torch.rand(3, 3, 16, 32), "white": torch.rand(3, 16, 32) + 0.5,
                                                                     "black": torch.zeros(3, 16, 32), **k}), ["primaries", "white", "black", "lit"]),
        "largest_plane": (lambda **k: calib.largest_plane(**{"points": points, "threshold": 0.05, "trials": 20, **k}),
                          ["points", "threshold", "trials", "seed", "sample"]),
        "write_ply": (lambda **k: calib.write_ply(**{"path": tmp_path / "cloud.ply", "points": points.numpy(), **k}),
                      ["path", "points", "colors"]),
    }
    wrong = WRONG + [1.5, float("inf"), 0, (), np.float32(0.5)]
    failures = [f"{name}({line}" for name, (call, names) in calls.items() for line in _mishandled(call, names, wrong)]
    assert not failures, f"{len(failures)} value(s) mishandled:\n" + "\n".join(failures)


def test_what_the_helpers_took_without_a_word(tmp_path, capfd):
    from torchproj import calib, scene as sc

    # Names past the suite's first scene read back; suite-1--1 read as nothing.
    with pytest.raises(TorchprojError, match="start"):
        sc.suite_names(1, 2, start=-1)
    assert sc.suite_names(1, 2, start=3) == ["suite-1-3", "suite-1-4"]
    # A pose of NaN, or looking at itself, was a rotation of NaN.
    for call in (lambda: sc.look_at((0, 0, 1), (0, 0, 1)), lambda: sc.look_at((0, 0, float("nan")), (0, 1, 0)),
                 lambda: sc.rotation_from_euler_deg((float("nan"), 0, 0)), lambda: sc.rotation_from_rotvec((1, 0, 0, 0))):
        with pytest.raises(TorchprojError):
            call()
    # A camera of 1.5 pixels reached the config, to be refused there under another name.
    with pytest.raises(TorchprojError, match="camera"):
        sc.scale_config({"camera": {"resolution": [64, 48], "focal": 50.0}}, camera=(1.5, 5))
    # An int path is a file descriptor to open(): True wrote the cloud to standard output.
    with pytest.raises(TorchprojError, match="path"):
        calib.write_ply(True, torch.zeros(4, 3).numpy())
    assert capfd.readouterr().out == ""
    # Bits of the wrong kind were refused after the sequence's folder was made.
    with pytest.raises(TorchprojError, match="bits"):
        calib.write_sequence(tmp_path / "seq", 16, 8, ramp_steps=4, bits=1.5)
    assert not (tmp_path / "seq").exists()
    # A refinement window of 1.5 pixels, and a fill of a window over 1, were taken.
    prj_xy, valid = torch.zeros(12, 12, 2), torch.ones(12, 12, dtype=torch.bool)
    for options in ({"window": 7.0 + 0.5}, {"min_fill": 1.5}, {"max_shift": 0}):
        with pytest.raises(TorchprojError, match=next(iter(options))):
            calib.refine_subpixel(prj_xy, valid, **options)


def test_the_solving_and_positioning_helpers_name_values_of_the_wrong_kind(problem, tmp_path):
    """The subpackages' functions beside the solvers: the captured loss, the projectable patterns, the
    epipolar geometry, the footprint's choice, the scores and the positioning's poses."""
    import numpy as np

    from torchproj import experiments as ex, pipeline as pl, solve as so, transport as tr
    from torchproj.core import sparse

    cals, tgts, op, curves = problem
    p = torch.rand(op.shape[1], 1)
    image, covered = torch.rand(1, 8, 8), torch.ones(8, 8, dtype=torch.bool)
    rng = np.random.default_rng(0)
    calls = {
        "captured_loss": (lambda **k: so.captured_loss(**{"op": op, "measured": op.A(p), **k}), ["op", "measured"]),
        "projectable_patterns": (lambda **k: so.projectable_patterns(**{"op": op, "p": p, "bounds": (0, 1), "responses": curves, **k}),
                                 ["op", "p", "bounds", "responses"]),
        "compensate": (lambda **k: so.compensate(**{"images": [torch.rand(1, 4, 4)] * 2, "responses": curves, **k}), ["images"]),
        "psnr_hinge": (lambda **k: so.psnr_hinge(**{"ratio": torch.rand(3), "psnr_drop": 1.0, **k}), ["ratio", "psnr_drop", "weight"]),
        "image_objective": (lambda **k: so.image_objective(**{"name": "ssim", **k}), ["iterations"]),
        "component_chains": (lambda **k: so.component_chains(**k), ["op"]),
        "fundamental_between_projectors": (lambda **k: so.fundamental_between_projectors(**{"calibrations": cals, **k}),
                                           ["calibrations", "first", "second", "max_points"]),
        "solve_gain_offset": (lambda **k: so.solve_gain_offset(**{"op": op, "flat": torch.rand(op.shape[0], 1), "max_iter": 3,
                                                                  "outer": 1, **k}), ["op", "outer", "max_iter"]),
        "csr_from_coo": (lambda **k: sparse.csr_from_coo(**{"rows": torch.tensor([0, 1]), "cols": torch.tensor([1, 0]),
                                                            "vals": torch.ones(2), "shape": (2, 2), **k}), ["rows", "cols", "vals", "shape"]),
        "group_rows": (lambda **k: tr.group_rows(**k), ["columns"]),
        "normal_form": (lambda **k: tr.normal_form(**k), ["op"]),
        "map_slope": (lambda **k: tr.map_slope(**{"prj_xy": cals["near"].prj_xy[0], **k}), ["prj_xy", "like"]),
        "retarget_rhs": (lambda **k: tr.retarget_rhs(**{"op": op, "calibrations": cals, "targets": tgts, **k}),
                         ["op", "calibrations", "targets"]),
        "target_on_camera": (lambda **k: tr.target_on_camera(**{"target": tgts[0], "mask": torch.ones(15, 20, dtype=torch.bool), **k}),
                             ["target", "mask"]),
        "choose_footprint": (lambda **k: pl.choose_footprint(**{"states": cals, "targets": tgts, **k}), ["states", "tolerance_db"]),
        "default_images": (lambda **k: pl.default_images(**{"count": 2, "channels": 1, **k}), ["count", "channels"]),
        "affine_psnr": (lambda **k: pl.affine_psnr(**{"estimate": image, "values": image, "covered": covered, **k}),
                        ["estimate", "values", "covered"]),
        "score_image": (lambda **k: pl.score_image(**{"estimate": image, "values": image, "covered": covered, **k}),
                        ["estimate", "values", "covered"]),
        "decoding_accuracy": (lambda **k: pl.decoding_accuracy(**{"decoded": torch.rand(8, 8, 2), "truth": torch.rand(8, 8, 2), **k}),
                              ["decoded", "truth"]),
        "pose_error": (lambda **k: ex.pose_error(**{"pose": np.eye(4), "goal": np.eye(4), **k}), ["pose", "goal"]),
        "scan_distance": (lambda **k: ex.scan_distance(**{"points": rng.random((10, 3)), "reference": rng.random((12, 3)), **k}),
                          ["points", "reference"]),
        "box_surface_distance": (lambda **k: ex.box_surface_distance(**{"points": rng.random((10, 3)), "world_from_local": np.eye(4),
                                                                        "size": (1, 1, 1), **k}), ["points", "world_from_local", "size"]),
        "random_pose_near": (lambda **k: ex.random_pose_near(**{"goal": np.eye(4), "spread_m": 0.01, "spread_deg": 1.0, "rng": rng, **k}),
                             ["goal", "spread_m", "spread_deg", "rng"]),
        "placement_error": (lambda **k: ex.placement_error(**{"placed": tmp_path, "reference": tmp_path, "distance": 0.5, **k}),
                            ["placed", "reference", "distance"]),
    }
    failures = [f"{name}({line}" for name, (call, names) in calls.items() for line in _mishandled(call, names)]
    assert not failures, f"{len(failures)} value(s) mishandled:\n" + "\n".join(failures)
    # A column past the last landed in the next row; the same projector twice made an epipolar geometry of nothing.
    with pytest.raises(TorchprojError, match="cols"):
        sparse.csr_from_coo(torch.tensor([0, 0]), torch.tensor([0, 2]), torch.ones(2), (2, 2))
    with pytest.raises(TorchprojError, match="two projectors"):
        so.fundamental_between_projectors(cals, 0, 0)


def test_the_virtual_rig_helpers_name_values_of_the_wrong_kind(tmp_path, monkeypatch):
    """The rig's own helpers: a capture sequence, the light levels, the camera model, a caster, the
    exact procam calibration and the placement's search."""
    import numpy as np

    monkeypatch.chdir(tmp_path)  # "x" is a folder name: the simulation it asks for is written here

    from torchproj import experiments as ex, pipeline as pl, sim

    scene = small_scene(camera=(160, 120), projector=(64, 48))
    rig = calibrate_once(scene).rig
    calls = {
        "simulate_calibration": (lambda **k: pl.simulate_calibration(**{"rig": rig, "state": "near", "projector": 0, **k}),
                                 ["rig", "projector"]),
        "calibrate_rig": (lambda **k: pl.calibrate_rig(**{"rig": rig, **k}), ["rig"]),
        "white_levels": (lambda **k: pl.white_levels(**k), ["scene"]),
        "describe_light": (lambda **k: pl.describe_light(**{"scene": scene, **k}), ["scene", "threshold"]),
        "true_responses": (lambda **k: pl.true_responses(**k), ["scene"]),
        "scene_images": (lambda **k: pl.scene_images(**k), ["scene"]),
        "simulate_scene": (lambda **k: pl.simulate_scene(**{"scene": scene, **k}), ["folder"]),
        "rig_procam": (lambda **k: ex.rig_procam(**{"scene": scene, "j": 0, **k}), ["scene", "j"]),
        "make_caster": (lambda **k: sim.make_caster(**{"surface": next(iter(scene.surfaces.values())), **k}), ["surface", "device"]),
        "apply_camera": (lambda **k: sim.apply_camera(**{"radiance": torch.rand(1, 1, 8, 8), "camera": scene.camera,
                                                         "generator": torch.Generator(), **k}), ["radiance", "camera", "generator", "out"]),
        "place_by_feedback": (lambda **k: ex.place_by_feedback(**{"feedback": lambda pose: 1.0, "start": np.eye(4), "step_m": 0.001,
                                                                  "step_deg": 0.1, "max_evaluations": 5, **k}),
                              ["feedback", "start", "step_m", "step_deg", "max_evaluations", "tolerance_m", "coarse"]),
        "feedback_profile": (lambda **k: ex.feedback_profile(**{"feedback": lambda pose: 1.0, "goal": np.eye(4),
                                                                "offsets_m": np.array([0.0, 0.01]), **k}), ["feedback", "goal", "offsets_m"]),
    }
    failures = [f"{name}({line}" for name, (call, names) in calls.items() for line in _mishandled(call, names)]
    assert not failures, f"{len(failures)} value(s) mishandled:\n" + "\n".join(failures)
    # A projector past the last, given to the rig's own calibration sequence, was an IndexError.
    with pytest.raises(TorchprojError, match="no projector 5"):
        pl.simulate_calibration(rig, "near", 5)


def test_the_estimators_and_geometry_helpers_name_values_of_the_wrong_kind(gray_capture, tmp_path):
    """What the calibration reads beyond the decoder (stripes, edges, blur), the warnings it gives, the
    triangulation and the planar maps, the exact light's rows."""
    from torchproj import calib, experiments as ex, pipeline as pl, transport as tr

    size, capture, decoding = gray_capture
    prj_xy = decoding.prj_xy.float()
    cells = torch.where(decoding.valid[..., None], prj_xy.round(), -1).to(torch.int32)
    scene = small_scene(camera=(160, 120), projector=(64, 48))
    cal = calibrate_once(scene)
    tgts = tp.scene_targets(scene, rig=cal.rig)
    procam = ex.rig_procam(scene, 0)
    rows = tp.build_transport(cal.states, tgts, merge=False)
    fundamental = tp.solve.fundamental_between_projectors(cal.states)
    pixels = torch.tensor([0, 5])
    ray = torch.tensor([[0.0, 0, 1]])
    calls = {
        "stripe_contrast": (lambda **k: calib.stripe_contrast(**{**capture, "cells": cells, "projector_size": size, **k}),
                            ["patterns", "cells", "projector_size", "margin"]),
        "stripe_shares": (lambda **k: calib.stripe_shares(**{"patterns": capture["patterns"], "span": torch.ones(16, 32),
                                                             "pixels": pixels, "bits": (4, 3), **k}), ["patterns", "span", "pixels", "bits"]),
        "checker_shares": (lambda **k: calib.checker_shares(**{"pair": torch.rand(2, 1, 16, 32), "white": capture["white"],
                                                               "black": capture["black"], "cells": cells, **k}), ["pair", "white", "black", "cells"]),
        "find_edge_pixels": (lambda **k: calib.find_edge_pixels(**{**capture, "prj_xy": prj_xy, "projector_size": size, **k}),
                             ["prj_xy", "projector_size", "slope", "depth"]),
        "measure_blur": (lambda **k: calib.measure_blur(**{**capture, "prj_xy": prj_xy, "projector_size": size, **k}),
                         ["prj_xy", "projector_size", "finest", "step", "min_contrast", "slope"]),
        "triangulate": (lambda **k: calib.triangulate(**{"cam_xy": torch.rand(5, 2), "prj_xy": torch.rand(5, 2), "calib": procam, **k}),
                        ["cam_xy", "prj_xy", "calib"]),
        "triangulate_map": (lambda **k: calib.triangulate_map(**{"prj_xy": prj_xy, "calib": procam, **k}), ["prj_xy", "calib"]),
        "read_opencv_calibration": (lambda **k: calib.read_opencv_calibration(**k), ["path"]),
        "warn_if_few_decoded": (lambda **k: calib.warn_if_few_decoded(**{"decoding": decoding, "where": "here", **k}), ["decoding"]),
        "warn_if_noisy": (lambda **k: calib.warn_if_noisy(**{"noise": 0.01, "saturated": 0.0, "where": "here", "frames": "1", **k}),
                          ["noise", "saturated"]),
        "warn_if_saturated": (lambda **k: calib.warn_if_saturated(**{"saturated": 0.0, "where": "here", **k}), ["saturated"]),
        "planar_calibration": (lambda **k: tr.planar_calibration(**{"states": cal.states, **k}), ["states", "tolerance", "names"]),
        "cell_blocks": (lambda **k: tr.cell_blocks(**{"column_projector": torch.tensor([0, 0, 1]), "column_cell": torch.tensor([0, 1, 0]),
                                                      "projector_sizes": [(2, 1), (2, 1)], **k}),
                        ["column_projector", "column_cell", "projector_sizes"]),
        "triangulate_rays": (lambda **k: tr.triangulate_rays(**{"o1": torch.zeros(1, 3), "d1": ray, "o2": ray, "d2": ray, **k}),
                             ["o1", "d1", "o2", "d2"]),
        "light_transport": (lambda **k: pl.light_transport(**{"rig": cal.rig, "targets": tgts,
                                                              "rows": tp.build_transport(cal.states, tgts, merge=False), **k}),
                            ["rig", "targets", "rows"]),
        "scan_surface": (lambda **k: ex.scan_surface(**{"scene": scene, "surface": next(iter(scene.surfaces.values())), "pose": torch.eye(4), **k}),
                         ["scene", "surface", "pose", "seed"]),
        "epipolar_bands": (lambda **k: tp.solve.epipolar_bands(**{"op": rows, "F": fundamental, **k}), ["op", "F", "band"]),
        "make_patterns": (lambda **k: tp.make_patterns(**{"op": rows, "solver": "fista", "bounds": (0, 1),
                                                          "responses": pl.true_responses(scene), "max_iter": 2, **k}), ["op"]),
        "point_map": (lambda **k: tr.point_map(**{"prj_xy": cal.states["near"].prj_xy, "camera": scene.camera,
                                                  "projectors": scene.projectors, **k}), ["prj_xy", "camera", "projectors"]),
        "geometric_weights": (lambda **k: tr.geometric_weights(**{"prj_xy": cal.states["near"].prj_xy, "camera": scene.camera,
                                                                  "projectors": scene.projectors, **k}), ["window"]),
        "normal_map": (lambda **k: tr.normal_map(**{"points": torch.rand(20, 20, 3), "camera_centre": (0, 0, 0), **k}),
                       ["points", "camera_centre", "window"]),
    }
    with warnings.catch_warnings():  # the warnings' own values (an infinite noise) are warned of, as they should be
        warnings.simplefilter("ignore")
        failures = [f"{name}({line}" for name, (call, names) in calls.items() for line in _mishandled(call, names)]
    assert not failures, f"{len(failures)} value(s) mishandled:\n" + "\n".join(failures)


def test_a_float32_point_map_has_the_normals_of_its_float64_copy():
    from torchproj.transport import normal_map

    ys, xs = torch.meshgrid(torch.arange(12.0), torch.arange(16.0), indexing="ij")
    points = torch.stack([xs, ys, 0.3 * xs + 0.1 * ys + 5], -1).double()  # a tilted plane
    wide = normal_map(points, (0.0, 0.0, -10.0))
    assert torch.allclose(normal_map(points.float(), (0.0, 0.0, -10.0)), wide, atol=1e-6, equal_nan=True)
    assert bool(torch.isfinite(wide).any())


class _FlatCamera:
    def grab(self):
        return np.zeros((6, 10), np.uint8)


def test_the_bench_depth_and_mixing_helpers_name_values_of_the_wrong_kind(tmp_path, monkeypatch):
    """The helpers the fuzzes above left: the capture loop a bench script runs (its display and camera
    are the script's own objects), the depth sweep, and the solve through a colour camera's mixing."""
    from torchproj.calib import write_sequence
    from torchproj.experiments import depth_sweep
    from torchproj.pipeline.acquire import LiveBench
    from torchproj.solve.mixing import solve_through_mixing

    import time

    monkeypatch.chdir(tmp_path)  # a path of "x" is written nowhere else
    sleep = time.sleep  # a wait of 2 s an image is a wait, not a bad value: waited as 0 s of its own type
    monkeypatch.setattr(time, "sleep", lambda seconds: sleep(seconds * 0))
    write_sequence(tmp_path / "seq", 16, 8, ramp_steps=4)
    scene = small_scene(camera=(160, 120), projector=(64, 48))
    run = tp.run_virtual(scene, calibration=calibrate_once(scene), max_iter=5)
    cals, tgts = synthetic_calibration(), targets(channels=3)
    op = tp.build_transport(cals, tgts, merge=False)
    solved = tp.solve_patterns(op, max_iter=3)
    mixings = [torch.eye(3) * 0.8 + 0.2 / 3] * len(SIZES)
    capture = {"sequence_dir": tmp_path / "seq", "out_dir": tmp_path / "out", "display": RigDisplay(),
               "camera": _FlatCamera(), "settle_s": 0}
    sweep = {"scene": scene, "surface": "near_plane", "depths": [0.8], "patterns": run.patterns, "targets": run.targets,
             "scale": run.report["scale"]}
    calls = {
        # None for the display or camera opens OpenCV's, which a machine without a screen or camera refuses.
        "capture_sequence": (lambda **k: capture_sequence(**{**capture, **k}),
                             ["sequence_dir", "out_dir", "display", "camera", "settle_s", "frames", "screen",
                              "camera_index"]),
        "LiveBench": (lambda **k: LiveBench(**{"displays": {"upper": RigDisplay()}, "camera": _FlatCamera(), **k}),
                      ["displays", "camera", "settle_s", "frames"]),
        "depth_sweep": (lambda **k: depth_sweep(**{**sweep, **k}),
                        ["scene", "surface", "depths", "patterns", "targets", "scale", "device", "min_pixels"]),
        "solve_through_mixing": (lambda **k: solve_through_mixing(**{"ops": op, "result": solved, "mixings": mixings,
                                                                     "bounds": (0, 1), "max_iter": 2, **k}),
                                 ["ops", "result", "mixings", "bounds", "max_iter", "extra"]),
    }
    wrong = [*WRONG, 1.5, float("inf"), 0, (), np.float32(2)]
    failures = [f"{name}({line}" for name, (call, names) in calls.items() for line in _mishandled(call, names, wrong)]
    assert not failures, f"{len(failures)} value(s) mishandled:\n" + "\n".join(failures)


def test_the_core_and_remaining_helpers_name_values_of_the_wrong_kind(problem, tmp_path, monkeypatch):
    """The package's own helpers a script reaches for (``torchproj.core``'s image and file writers,
    the pixel grid) and the last public functions no fuzz above named: 165 values ended in
    AttributeErrors, torch's ``arange`` errors or numpy's shift errors at 2ed8d88."""
    from torchproj import calib, core, metrics, scene, solve, transport

    monkeypatch.chdir(tmp_path)
    cals, tgts, op, _ = problem
    image = torch.rand(1, 8, 8)
    core.write_image(tmp_path / "a.png", image)
    calls = {
        "fit_plane": (lambda **k: calib.fit_plane(**{"points": torch.rand(20, 3), **k}), ["points"]),
        "fit_response": (lambda **k: calib.fit_response(**{"levels": torch.linspace(0, 1, 8),
                                                           "response": torch.linspace(0, 1, 8)[:, None] ** 2, **k}),
                         ["levels", "response"]),
        "sequence_bits": (lambda **k: calib.sequence_bits(**{"width": 16, "height": 8, **k}), ["width", "height", "bits"]),
        "checker_patterns": (lambda **k: calib.checker_patterns(**{"width": 16, "height": 8, **k}), ["width", "height"]),
        "procedural_scene": (lambda **k: scene.procedural_scene(**{"seed": 1, **k}), ["seed", "index", "size"]),
        "has_colour_weights": (lambda **k: transport.has_colour_weights(**{"calibrations": cals, "targets": tgts, **k}),
                               ["calibrations", "targets"]),
        "select_maps": (lambda **k: transport.select_maps(**{"states": cals, **k}),
                        ["states", "maps", "tolerance", "fitted", "names"]),
        "to_projectable": (lambda **k: solve.to_projectable(**{"p": torch.rand(5, 1), "bounds": (-0.4, 1), **k}),
                           ["p", "bounds", "outside"]),
        "solve_target_sets": (lambda **k: solve.solve_target_sets(**{"op": op, "rhs_sets": [op.rhs], "max_iter": 2, **k}),
                              ["op", "rhs_sets", "bounds", "max_iter", "tol"]),
        "calibration_parts": (lambda **k: solve.calibration_parts(**k), ["calibration"]),
        "explained_share": (lambda **k: metrics.explained_share(**{"residual": image, "regressors": [image],
                                                                   "mask": torch.ones(8, 8, dtype=torch.bool), **k}),
                            ["residual", "regressors", "mask"]),
        "model_space_psnr": (lambda **k: metrics.model_space_psnr(**{"op": op, "p": torch.rand(op.shape[1], 1), **k}),
                             ["op", "p"]),
        "read_image": (lambda **k: core.read_image(**{"path": tmp_path / "a.png", **k}), ["path", "remedy"]),
        "write_image": (lambda **k: core.write_image(**{"path": tmp_path / "b.png", "image": image, **k}),
                        ["path", "image", "bits"]),
        "to_uint": (lambda **k: core.to_uint(**{"image": image, **k}), ["image", "bits"]),
        "pixel_grid": (lambda **k: core.pixel_grid(**{"height": 4, "width": 5, **k}), ["height", "width", "device", "dtype"]),
        "round_to_pixel": (lambda **k: core.round_to_pixel(**{"coords": torch.rand(4, 2), **k}), ["coords"]),
        "write_json": (lambda **k: core.write_json(**{"path": tmp_path / "c.json", "data": {"a": 1}, **k}), ["path", "data"]),
    }
    wrong = [*WRONG, 1.5, float("inf"), 0, (), np.float32(2)]
    failures = [f"{name}({line}" for name, (call, names) in calls.items() for line in _mishandled(call, names, wrong)]
    assert not failures, f"{len(failures)} value(s) mishandled:\n" + "\n".join(failures)


def test_a_state_calibration_a_script_makes_is_checked_where_it_is_built_on(problem):
    """A bench with its own decoder makes its :class:`StateCalibration` itself: lists of the wrong kind or
    length, a map of another camera or a size that is not two whole numbers ended in unpacking and
    indexing errors deep in the build (84 values at 695eb1f)."""
    cals, tgts, _, _ = problem
    near = cals["near"]
    fields = {"prj_xy": near.prj_xy, "weight": near.weight, "projector_sizes": near.projector_sizes}

    def build(**k):
        state = tp.StateCalibration(**{**fields, **k})
        tp.build_transport({"near": state, "far": cals["far"]}, tgts, merge=False)

    wrong = [*WRONG, 1.5, float("inf"), 0, (), np.float32(2), [torch.zeros(3)] * 2, [torch.zeros(15, 20, 2)],
             [torch.zeros(15, 20)], [None]]
    failures = _mishandled(build, ["prj_xy", "weight", "projector_sizes", "blur", "colour_weight", "edges", "shares", "dim"],
                           wrong)
    assert not failures, f"{len(failures)} value(s) mishandled:\n" + "\n".join(failures)
