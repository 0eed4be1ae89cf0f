"""The default model against the exact-light ceiling on procedural scenes nobody tuned for.

The suite's seed here (11) is not one the model was developed on (0, 1, 3 and 2026 were studied).
``python benchmarks/suite.py --seed S`` measures any other; docs/accuracy.md "Scenes nobody tuned for" gives
seed 1's table. The issue's goal (every target within 0.5 dB and 0.02 SSIM of the ceiling) is not met
on every scene: the bounds below are the regression line, and docs/accuracy.md says where and why.
"""

import dataclasses
import statistics

import pytest

from torchproj.pipeline import (CEILING_ITERATIONS, calibrate_virtual, evaluate_patterns, light_transport,
                                scene_targets, solve_on_light_transport, true_responses)
from torchproj.pipeline.run import build_operators
from torchproj.scene import load_scene
from torchproj.solve import make_patterns

BOUNDS = (0.0, 1.0)
# suite-11-3 (one projector, two states) leaves 19% of its targets unexplained, and run says so: the
# suite holds ill-posed scenes as users bring them.
pytestmark = pytest.mark.filterwarnings("ignore:the patterns leave:UserWarning")


def _scores(cal, targets, footprint=None, states=None):
    """Each target's captured (PSNR, SSIM): a model solved as ``run`` solves it, or the ceiling."""
    states = cal.states if states is None else states
    if footprint is None:
        rows = build_operators(states, targets, footprint="area", merge=False, colour_weights="grey", device="cpu")[0]
        ops = light_transport(cal.rig, targets, rows)
        # The exact light shown through the projectors' own responses, as run's --ceiling: a fitted
        # response's error is calibration's, not the ceiling's.
        _, _, patterns = solve_on_light_transport(ops, BOUNDS, true_responses(cal.rig.scene), max_iter=CEILING_ITERATIONS)
    else:
        ops = build_operators(states, targets, footprint=footprint, merge=footprint == "nearest",
                              colour_weights="channel", device="cpu")
        _, _, patterns = make_patterns(ops, "fista", BOUNDS, cal.responses, progress=False)
    return [(s.psnr_db, s.ssim) for s in evaluate_patterns(cal, patterns, targets, scale=ops[0].scale, paper=False).targets]


@pytest.fixture(scope="module")
def suite():
    out = {}
    for index in range(4):  # one scene of each kind
        scene = load_scene(f"suite-11-{index}")
        cal = calibrate_virtual(scene, progress=False)
        targets = scene_targets(scene, None, cal.rig)
        out[scene.name] = {model: _scores(cal, targets, model) for model in ("nearest", "area", None)}
    return out


def test_the_default_model_is_near_the_ceiling_on_unseen_scenes(suite):
    gaps, ssim = [], []
    for name, runs in suite.items():
        for (near, _), (area, area_ssim), (top, top_ssim) in zip(runs["nearest"], runs["area"], runs[None]):
            assert area > near - 0.1, f"{name}: area {area:.2f} dB below the paper's nearest cell {near:.2f} dB"
            gaps.append(top - area)
            ssim.append(top_ssim - area_ssim)
    assert statistics.median(gaps) <= 0.5, gaps
    assert max(ssim) <= 0.02, ssim
    assert max(gaps) <= 3.0, gaps  # the goal is 0.5 dB: docs/accuracy.md "Scenes nobody tuned for" says what is missed


def test_the_measured_defocus_brings_a_blurred_state_to_its_ceiling():
    """suite-3-3: every projector focused on the near state; the far one, 14 cm behind, gets each cell's
    light over discs 1.5-2.5 cells wide. Without the measured blur its solid lost 4 dB."""
    scene = load_scene("suite-3-3")
    cal = calibrate_virtual(scene, progress=False)
    targets = scene_targets(scene, None, cal.rig)
    assert all(b is not None for st in cal.states.values() for b in st.blur)
    sharp = {name: dataclasses.replace(st, blur=None) for name, st in cal.states.items()}
    far = [k for k, t in enumerate(targets) if t.state == "far"]
    with_blur, without, top = (_scores(cal, targets, "area"), _scores(cal, targets, "area", sharp), _scores(cal, targets))
    for k in far:
        assert with_blur[k][0] > without[k][0] + 1.0
        assert top[k][0] - with_blur[k][0] < 1.0


@pytest.mark.slow
@pytest.mark.parametrize("name, target", [("suite-2718-17", "plane1"), ("suite-8080-8", "sphere0")])
def test_outlines_beside_a_surface_seen_as_a_one_pixel_strip(name, target):
    """suite-2718-17: the wall behind plane1 shows through one row of pixels between its outline and
    a shadow; with no slope across that row it was no candidate for the outline's pixels, 3.8 dB
    below the ceiling (fill_slope lends it). suite-8080-8: a row of mixed pixels along the sphere's
    outline decodes to a strip too; taken as a surface it cost 0.34 dB (a lent pixel that sees two
    surfaces is no candidate). Seeds 2718 and 8080 were drawn after the model's development."""
    scene = load_scene(name)
    cal = calibrate_virtual(scene, progress=False)
    targets = scene_targets(scene, None, cal.rig)
    k = [t.name for t in targets].index(target)
    area, top = _scores(cal, targets, "area")[k][0], _scores(cal, targets)[k][0]
    assert top - area <= 0.5, f"{name} {target}: {area:.2f} dB against a ceiling of {top:.2f}"


@pytest.mark.parametrize("option, message", [("--seed=-1", "argument --seed: a suite seed or index must be a whole number"),
                                             ("--count=0", "argument --count: must be at least 1"),
                                             ("--models=bogus", "argument --models: invalid choice: 'bogus'")])
def test_the_suite_benchmark_refuses_bad_options_before_its_first_scene(option, message, tmp_path, capsys, monkeypatch):
    """``--seed -1`` and ``--models bogus`` were refused at the first scene, a calibration in; ``--count 0``
    wrote an empty table."""
    import importlib.util
    from pathlib import Path

    folder = Path(__file__).resolve().parents[2] / "benchmarks"
    monkeypatch.syspath_prepend(str(folder))
    spec = importlib.util.spec_from_file_location("suite_benchmark", folder / "suite.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    monkeypatch.setattr(module, "measure", lambda *a, **k: pytest.fail("measured before the options were checked"))
    with pytest.raises(SystemExit) as stopped:
        module.main([option, "--out", str(tmp_path / "suite")])
    assert stopped.value.code == 2 and message in capsys.readouterr().err and not (tmp_path / "suite").exists()
