"""Positioning: placing a box by its projected image, scanning it, and the numbers reported."""

import json

import numpy as np
import pytest
import torch
import yaml

from torchproj.cli import main
from torchproj.core import ConfigError, InputError
from torchproj.experiments import box_surface_distance, evaluate_positioning, place_by_feedback, pose_error, random_pose_near, scan_distance, scan_surface
from torchproj.experiments.positioning import (COARSE_PIXELS, FINE_PIXELS, PlacementTrial, _box_window, _posed,
                                               coarse_looks, feedback_stride_for, position_markdown)
from torchproj.scene import parse_scene, rotation_from_euler_deg
from torchproj.sim import VirtualRig

from ..helpers import CHESSBOARD, small_config, small_scene

SMALL = dict(camera=(320, 240), projector=(256, 192))


@pytest.fixture(scope="module")
def box_scene():
    return parse_scene(dict(small_config("box_positions", **SMALL), name="small_box"), name="small_box")


@pytest.fixture(scope="module")
def position_run(tmp_path_factory):
    path = tmp_path_factory.mktemp("cfg") / "small_box.yaml"
    path.write_text(yaml.safe_dump(dict(small_config("box_positions", **SMALL), name="small_box")))
    out = tmp_path_factory.mktemp("position") / "out"
    assert main(["position", str(path), "--out", str(out), "--trials", "2", "--max-evaluations", "60"]) == 0
    return out, json.loads((out / "report.json").read_text())


def test_capture_of_posed_surfaces_equals_the_transport_capture():
    scene = small_scene("box_cylinders", camera=(160, 120), projector=(128, 96))
    rig = VirtualRig(scene)
    gen = torch.Generator().manual_seed(3)
    patterns = {j: torch.rand(1, 1, p.height, p.width, generator=gen) for j, p in enumerate(scene.projectors)}
    state = scene.states[0]
    reference = rig.capture(state.name, patterns, noise=False)[0].reshape(scene.channels, -1)
    pixels = torch.randperm(reference.shape[1], generator=gen)[:3000]
    direct = rig.capture_surfaces([scene.surfaces[n] for n in state.surfaces], patterns, pixels, noise=False)
    # Same physics, shadows included (the cylinders shadow the box), without a transport matrix.
    assert (direct - reference[:, pixels]).abs().max() <= 1 / 255 + 1e-6
    assert (direct > 0.05).float().mean() > 0.2  # most sampled pixels see a lit surface


def test_repeated_looks_follow_patterns_and_pixels_changed_in_place():
    # capture_surfaces reuses the last look's rays and emitted light for the same tensors; a pattern or
    # pixel list modified in place must still be seen as it is now, as a fresh rig sees it.
    scene = small_scene("box_cylinders", camera=(160, 120), projector=(128, 96))
    surfaces = [scene.surfaces[n] for n in scene.states[0].surfaces]
    gen = torch.Generator().manual_seed(4)
    patterns = {j: torch.rand(1, 1, p.height, p.width, generator=gen) for j, p in enumerate(scene.projectors)}
    pixels = torch.randperm(160 * 120, generator=gen)[:2000]
    rig = VirtualRig(scene)
    first = rig.capture_surfaces(surfaces, patterns, pixels, noise=False)
    assert torch.equal(rig.capture_surfaces(surfaces, patterns, pixels, noise=False), first)
    patterns[0].mul_(0.3)
    pixels[:1000] = torch.randperm(160 * 120, generator=gen)[:1000]
    again = rig.capture_surfaces(surfaces, patterns, pixels, noise=False)
    fresh = VirtualRig(scene).capture_surfaces(surfaces, {j: p.clone() for j, p in patterns.items()}, pixels.clone(),
                                               noise=False)
    assert torch.equal(again, fresh) and not torch.equal(again, first)


def test_box_surface_distance_against_a_dense_sampling():
    pose = np.eye(4)
    pose[:3, :3] = rotation_from_euler_deg([10, 30, -5])
    pose[:3, 3] = [0.1, -0.05, 0.8]
    size = (0.2, 0.15, 0.12)
    # Dense samples of the six faces, in the world.
    g = np.linspace(-0.5, 0.5, 61)
    u, v = np.meshgrid(g, g)
    faces = []
    for axis in range(3):
        for sign in (-0.5, 0.5):
            local = np.zeros((u.size, 3))
            others = [a for a in range(3) if a != axis]
            local[:, axis] = sign * size[axis]
            local[:, others[0]] = u.ravel() * size[others[0]]
            local[:, others[1]] = v.ravel() * size[others[1]]
            faces.append(local)
    surface = np.concatenate(faces) @ pose[:3, :3].T + pose[:3, 3]
    rng = np.random.default_rng(0)
    points = pose[:3, 3] + rng.normal(scale=0.08, size=(300, 3))
    brute = np.linalg.norm(points[:, None] - surface[None], axis=-1).min(1)
    exact = box_surface_distance(points, pose, size)
    spacing = max(size) / 60
    assert np.all(exact <= brute + 1e-12) and np.all(brute - exact < spacing)
    assert box_surface_distance(surface, pose, size).max() < 1e-12


def test_random_starts_stay_within_the_spread_and_pose_error_measures_a_move():
    goal = np.eye(4)
    goal[:3, 3] = [0, 0, 0.7]
    rng = np.random.default_rng(1)
    for _ in range(50):
        start = random_pose_near(goal, 0.02, 5.0, rng)
        err = pose_error(start, goal)
        assert max(abs(v) for v in err["translation_mm"]) <= 20 + 1e-9 and err["rotation_deg"] <= 5 + 1e-6
    moved = goal.copy()
    moved[:3, :3] = rotation_from_euler_deg([0, 3, 0])
    moved[:3, 3] += [0.003, 0, -0.004]
    err = pose_error(moved, goal)
    assert err["distance_mm"] == pytest.approx(5.0) and err["rotation_deg"] == pytest.approx(3.0, abs=1e-4)


def test_placement_climbs_a_peak_it_can_only_sample():
    goal = np.eye(4)
    goal[:3, :3] = rotation_from_euler_deg([0, 25, 0])
    goal[:3, 3] = [0.0, 0.0, 0.71]
    looks = []

    def feedback(pose):  # a smooth peak at the goal; the placer sees only these values
        looks.append(pose)
        err = pose_error(pose, goal)
        return 20 - err["distance_mm"] ** 2 / 50 - err["rotation_deg"] ** 2 / 5

    start = random_pose_near(goal, 0.02, 5.0, np.random.default_rng(2))
    placed, history = place_by_feedback(feedback, start, step_m=0.02, step_deg=5.0, max_evaluations=600)
    err = pose_error(placed, goal)
    assert err["distance_mm"] < 1.0 and err["rotation_deg"] < 0.5
    assert len(history) == len(looks) <= 600 and max(history) == pytest.approx(feedback(placed), abs=1e-9)


def test_coarse_to_fine_placement_looks_coarse_first_then_fine():
    goal = np.eye(4)
    goal[:3, 3] = [0.0, 0.0, 0.71]
    calls = []

    def peak(pose, width):
        err = pose_error(pose, goal)
        return 20 - err["distance_mm"] ** 2 / width - err["rotation_deg"] ** 2 / width * 10

    def fine(pose):  # sharp: a narrow peak
        calls.append("fine")
        return peak(pose, 5.0)

    def coarse(pose):  # blunt: a wide one, on a scale of its own
        calls.append("coarse")
        return 100 + peak(pose, 200.0)

    start = random_pose_near(goal, 0.02, 5.0, np.random.default_rng(4))
    placed, history = place_by_feedback(fine, start, step_m=0.02, step_deg=5.0, max_evaluations=200, coarse=coarse)
    n = coarse_looks(200)
    assert n == 99 and len(history) == len(calls) <= 200
    # One fine look at the start, the coarse looks, then only fine ones.
    assert calls[0] == "fine" and calls[1:1 + n].count("coarse") == len(calls[1:1 + n]) and "coarse" not in calls[1 + n:]
    assert history[0] == pytest.approx(fine(start), abs=1e-9)
    err = pose_error(placed, goal)
    assert err["distance_mm"] < 0.5 and err["rotation_deg"] < 0.2
    trial = PlacementTrial("near", 0, start, placed, history, {}, 0.0, 0.0, 0.0, coarse_looks=n)
    own = trial.fine_history()
    assert len(own) == len(history) - n and max(own) < 100 <= min(history[1:1 + n])  # no coarse value among them
    assert max(own) == pytest.approx(fine(placed), abs=1e-9)
    # A coarse stage whose simplex closes early (on a flat coarse feedback) leaves its looks to the fine stage.
    calls.clear()

    def flat(pose):
        calls.append("coarse")
        return 100.0

    # (a first simplex of 1 mm is already within the coarse stage's tolerance)
    placed, history = place_by_feedback(fine, start, step_m=0.001, step_deg=0.2, max_evaluations=200, coarse=flat)
    early = calls.count("coarse")
    assert 0 < early < n and calls[1:1 + early] == ["coarse"] * early and "coarse" not in calls[1 + early:]
    assert len(history) == len(calls) <= 200 and history[1:1 + early] == [100.0] * early


def test_a_trials_coarse_looks_are_counted_as_they_were_made(box_scene):
    from torchproj.experiments import positioning

    made = []
    original = positioning.place_by_feedback

    def counting(feedback, start, **kwargs):
        before = kwargs["coarse"].count
        out = original(feedback, start, **kwargs)
        made.append(kwargs["coarse"].count - before)
        return out

    positioning.place_by_feedback = counting
    try:
        result = evaluate_positioning(box_scene, trials=1, max_evaluations=12, profile_steps=1)
    finally:
        positioning.place_by_feedback = original
    assert [t.coarse_looks for t in result.trials] == made and all(0 < m <= coarse_looks(12) for m in made)
    for t, row in zip(result.trials, result.report["trials"]):
        assert row["coarse_looks"] == t.coarse_looks and row["feedback_final_db"] == round(max(t.fine_history()), 3)


def test_the_feedbacks_keep_enough_pixels():
    region = torch.zeros(600, 800, dtype=torch.bool)
    region[100:500, 100:600] = True  # 200,000 pixels: every 4th keeps 12,500
    assert feedback_stride_for(region) == 4 == feedback_stride_for(region, COARSE_PIXELS)
    region[:] = False
    region[:250, :250] = True  # 62,500: every 2nd keeps 15,625, every 3rd 7,056, every 4th 3,969
    assert feedback_stride_for(region) == 2 and int(region[::2, ::2].sum()) >= FINE_PIXELS > int(region[::3, ::3].sum())
    assert feedback_stride_for(region, COARSE_PIXELS) == 4
    region[:] = False
    region[:80, :80] = True  # 6,400: too few for any fine stride but 1; every 2nd keeps 1,600 < 2,500
    assert feedback_stride_for(region) == 1 == feedback_stride_for(region, COARSE_PIXELS)


def test_a_scan_window_is_the_same_camera_where_the_box_can_be(box_scene):
    import dataclasses

    box = box_scene.surfaces["box_near"]
    pose = random_pose_near(box.world_from_local, 0.02, 5.0, np.random.default_rng(1))
    cam = box_scene.camera
    x0, y0, window = _box_window(cam, _posed(box, pose))
    assert 0 < window.width < cam.width and 0 < window.height < cam.height
    # The window's pixels look along the full camera's rays for the same pixels.
    full = VirtualRig(box_scene)
    part = VirtualRig(dataclasses.replace(box_scene, camera=window))
    _, d_part = part.camera_rays(1)
    _, d_full = full.camera_rays(1)
    rows = torch.arange(y0, y0 + window.height)[:, None] * cam.width + torch.arange(x0, x0 + window.width)
    assert torch.allclose(d_part, d_full[rows.reshape(-1)], atol=1e-6)
    # Every sample ray of the full camera that meets the box (the simulator's own caster) is in a
    # pixel of the window, and the window is no more than the margin wider than those pixels.
    casters = full._materials([_posed(box, pose)])[0]
    o, d = full.camera_rays(cam.supersampling)
    t, _ = casters[0].hit(o, d)
    pixel = torch.nonzero(torch.isfinite(t))[:, 0] // cam.supersampling**2
    x, y = pixel % cam.width, pixel // cam.width
    assert int(x.min()) >= x0 and int(x.max()) < x0 + window.width and int(y.min()) >= y0 and int(y.max()) < y0 + window.height
    assert int(x.min()) - x0 <= 3 and int(y.min()) - y0 <= 3
    assert x0 + window.width - 1 - int(x.max()) <= 3 and y0 + window.height - 1 - int(y.max()) <= 3
    # A distorting lens keeps the whole image.
    assert _box_window(dataclasses.replace(cam, distortion=(0.1, 0, 0, 0, 0)), _posed(box, pose))[2].width == cam.width


def test_scan_measures_a_known_displacement(box_scene):
    box = box_scene.surfaces["box_near"]
    at_goal = scan_surface(box_scene, box, box.world_from_local)
    rms = lambda pts, pose: float(np.sqrt(np.mean(box_surface_distance(pts, pose, box.size) ** 2)) * 1000)  # noqa: E731
    assert len(at_goal["points"]) > 2000 and set(at_goal["projector"].tolist()) == {0, 1}
    assert rms(at_goal["points"], box.world_from_local) < 1.5
    # Pushed 6 mm along the normal of the face the rig sees best (local -z turned towards the rig).
    normal = box.world_from_local[:3, :3] @ np.array([0.0, 0.0, -1.0])
    shifted = box.world_from_local.copy()
    shifted[:3, 3] += 0.006 * normal
    scan = scan_surface(box_scene, box, shifted)
    assert rms(scan["points"], shifted) < 1.5
    assert 3.0 < rms(scan["points"], box.world_from_local) < 6.5


@pytest.mark.slow
def test_position_report_and_files(position_run):
    out, report = position_run
    assert {p["name"] for p in report["positions"]} == {"near", "far"}
    assert set(report["rmse_percent_mean"]) == {"near", "far"}
    assert len(report["trials"]) == 4
    for t in report["trials"]:
        assert {"rmse_mm", "rmse_percent", "pose_error"} <= set(t)
        p = next(p for p in report["positions"] if p["name"] == t["position"])
        assert t["rmse_percent"] == pytest.approx(100 * t["rmse_mm"] / p["projector_distance_mm"], rel=1e-3)
        assert t["feedback_final_db"] >= t["feedback_start_db"]
        assert t["evaluations"] <= 60
        assert (out / "scans" / f"{t['position']}_{t['trial']}.npz").is_file()
    for p in report["positions"]:
        mean = np.mean([t["rmse_percent"] for t in report["trials"] if t["position"] == p["name"]])
        assert p["rmse_percent_mean"] == pytest.approx(mean, abs=1e-3)
        assert p["paper_rmse_percent"] in (1.47, 1.26)
        # The feedback peaks at the goal (within a millimetre: camera noise on a flat top), along depth
        # across and vertically, and falls clearly towards the ends.
        prof = report["feedback_profiles"][p["name"]]
        for key in ("depth", "across", "vertical"):
            assert abs(prof["offsets_mm"][int(np.argmax(prof[key]))]) <= 1.0
            assert max(prof[key]) - max(prof[key][0], prof[key][-1]) > 2.0
    for name in ("report.md", "feedback.png", "patterns/upper.png", "patterns/lower.png"):
        assert (out / name).is_file()
    assert "| near |" in (out / "report.md").read_text()


@pytest.mark.slow
def test_placement_gets_closer_than_it_started(box_scene):
    result = evaluate_positioning(box_scene, trials=2, max_evaluations=120, seed=3, profile_steps=2)
    for t in result.report["trials"]:
        assert t["pose_error"]["distance_mm"] < t["start_pose_error"]["distance_mm"]


@pytest.mark.slow  # three whole `position` commands; run's own cache is the default suite's (tests/pipeline/test_cache.py)
def test_a_second_position_reads_its_calibration_and_transport_and_places_alike(tmp_path, monkeypatch):
    """`torchproj position` keeps its calibration and transport as `run` does: a second test of the same
    scene reads both, and (its noise state kept with the calibration) makes the same placements."""
    from torchproj.pipeline.cache import CACHE_DIR_ENV

    monkeypatch.setenv(CACHE_DIR_ENV, str(tmp_path / "cache"))
    path = tmp_path / "small_box.yaml"
    path.write_text(yaml.safe_dump(dict(small_config("box_positions", **SMALL), name="small_box")))
    reports = []
    for k, extra in enumerate(([], [], ["--no-cache"])):
        out = tmp_path / f"out{k}"
        assert main(["position", str(path), "--trials", "1", "--max-evaluations", "10", "--out", str(out), *extra]) == 0
        reports.append(json.loads((out / "report.json").read_text()))
    assert [(r["calibration_cache"], r["transport_cache"]) for r in reports] == [
        ("stored", "stored"), ("read", "read"), ("off", "off")]
    placed = [[{k: v for k, v in t.items() if k not in ("seconds", "scan_seconds")} for t in r["trials"]] for r in reports]
    assert placed[0] == placed[1] == placed[2]


def test_position_needs_each_target_on_one_box(tmp_path, capsys):
    with pytest.raises(ConfigError, match="targets.near.surfaces"):
        evaluate_positioning(small_scene(**SMALL))
    path = tmp_path / "planes.yaml"
    path.write_text(yaml.safe_dump(dict(small_config(**SMALL), name="planes")))
    out = tmp_path / "out"
    assert main(["position", str(path), "--out", str(out)]) == 2
    assert "exactly one box" in capsys.readouterr().err and not out.exists()


def test_position_refuses_bad_settings(box_scene):
    for kwargs in ({"trials": 0}, {"spread_mm": -1}, {"spread_mm": float("nan")}, {"max_evaluations": 3}, {"feedback_stride": 0},
                   {"feedback_stride": 1.5}, {"feedback_stride": True}):
        with pytest.raises(InputError, match="must"):
            evaluate_positioning(box_scene, **kwargs)
    # A start a metre off is a search of the room, not a placement: refused at once, saying how far is allowed.
    with pytest.raises(InputError, match=r"spread_mm 1e\+09: .* give at most \d+"):
        evaluate_positioning(box_scene, spread_mm=1e9)
    with pytest.raises(InputError, match="spread_deg 90: .* give at most 45"):
        evaluate_positioning(box_scene, spread_deg=90)
    # A negative seed reached numpy's generator ("expected non-negative integer", a traceback from the
    # command); one past 2**32 would derive capture seeds past the rig's 2**63.
    for seed in (-1, 2 ** 32, 1.5, True):
        with pytest.raises(InputError, match=r"seed must be a whole number from 0 to 2\*\*32 - 1, got"):
            evaluate_positioning(box_scene, seed=seed)



@pytest.mark.parametrize("option, value, says", [
    ("trials", 1.5, "trials must be a whole number >= 1, got 1.5"), ("trials", True, "trials must be a whole number"),
    ("spread_mm", "20", r"spread_mm \(mm\) must be a finite number >= 0, got '20'"),
    ("spread_deg", None, r"spread_deg \(degrees\) must be a finite number >= 0, got None"),
    ("max_evaluations", float("inf"), "max_evaluations must be a whole number >= 10, got inf"),
    ("profile_mm", 0, r"profile_mm \(the feedback chart's range, mm\) must be a finite number > 0, got 0"),
    ("profile_steps", -1, r"profile_steps .* must be a whole number >= 1, got -1"),
    ("max_iter", 1.5, "max_iter must be a whole number >= 1, got 1.5"),
])
def test_position_settings_of_the_wrong_kind_are_refused_before_calibrating(box_scene, option, value, says, monkeypatch):
    """The Python face of `torchproj position`: trials of 1.5 or inf, a max_evaluations of inf, any chart
    range or sample count and any max_iter were taken, until the work (or the chart, after it) failed on
    them; a string or None as a spread ended in a TypeError on '>='."""
    import torchproj.experiments.positioning as positioning

    monkeypatch.setattr(positioning, "calibrate_virtual", lambda *a, **k: pytest.fail("calibrated before the check"))
    with pytest.raises(InputError, match=says):
        evaluate_positioning(box_scene, **{option: value})


def _fake_decode(folder, points):
    folder.mkdir(parents=True)
    np.savez_compressed(folder / "correspondence.npz", points=points.astype(np.float32))
    return folder


def test_placement_error_of_real_scans_from_files(tmp_path, capsys):
    # A plane scanned at its goal and 5 units further away (camera frame, calibration units).
    ys, xs = np.mgrid[0:120, 0:160].astype(np.float64)
    goal = np.stack([xs - 80, ys - 60, np.full_like(xs, 700.0)], -1)
    goal[:10] = np.nan  # rows the decoder missed
    placed = goal + np.array([0, 0, 5.0])
    ref = _fake_decode(tmp_path / "goal", goal)
    moved = _fake_decode(tmp_path / "placed", placed)
    out = tmp_path / "err"
    assert main(["placement-error", str(moved), "--reference", str(ref), "--distance", "700", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["rmse"] == pytest.approx(5.0, abs=1e-3) and report["points"] == 110 * 160
    assert report["rmse_percent"] == pytest.approx(100 * 5 / 700, abs=1e-3)
    # A mask keeps only the pixels it paints white.
    from torchproj.core import write_image
    mask = torch.zeros(1, 120, 160)
    mask[:, 60:, :80] = 1
    write_image(tmp_path / "mask.png", mask)
    assert main(["placement-error", str(moved), "--reference", str(ref), "--distance", "700", "--mask",
                 str(tmp_path / "mask.png"), "--out", str(tmp_path / "masked")]) == 0
    assert json.loads((tmp_path / "masked" / "report.json").read_text())["points"] == 60 * 80
    # Scans without points, and a mask of the wrong size, are refused before anything is written.
    (tmp_path / "nopoints").mkdir()
    np.savez_compressed(tmp_path / "nopoints" / "correspondence.npz", prj_xy=np.zeros((2, 2, 2)))
    bad = tmp_path / "bad"
    assert main(["placement-error", str(tmp_path / "nopoints"), "--reference", str(ref), "--distance", "700",
                 "--out", str(bad)]) == 2
    assert "--calibration" in capsys.readouterr().err
    write_image(tmp_path / "small_mask.png", torch.ones(1, 10, 10))
    assert main(["placement-error", str(moved), "--reference", str(ref), "--distance", "700", "--mask",
                 str(tmp_path / "small_mask.png"), "--out", str(bad)]) == 2
    assert "--mask is 10x10" in capsys.readouterr().err and not bad.exists()
    # A scan that is not the decoder's (2-vectors, a file of garbage) and a distance of inf are refused
    # too: they raised scipy's and numpy's errors, and inf made every error 0%.
    _fake_decode(tmp_path / "flat", goal[..., :2])
    (tmp_path / "garbage").mkdir()
    (tmp_path / "garbage" / "correspondence.npz").write_bytes(b"not an npz")
    for scan, distance, says in [("flat", "700", "points must be camera H x W x 3"),
                                 ("garbage", "700", "cannot be read as the decoder's .npz"),
                                 ("placed", "inf", "--distance must be the object-projector distance")]:
        assert main(["placement-error", str(tmp_path / scan), "--reference", str(ref), "--distance", distance,
                     "--out", str(bad)]) == 2
        assert says in capsys.readouterr().err and not bad.exists()


@pytest.mark.slow
@pytest.mark.skipif(not CHESSBOARD.is_dir(), reason=f"real captures not found at {CHESSBOARD}")
def test_placement_error_between_the_real_chessboard_captures(tmp_path):
    from scipy.spatial.distance import cdist

    calib = str(CHESSBOARD / "calibration_result.xml")
    for name in ("capture_0", "capture_1"):
        assert main(["decode", str(CHESSBOARD / name), "--projector", "1024x768", "--calibration", calib,
                     "--out", str(tmp_path / name)]) == 0
    assert main(["placement-error", str(tmp_path / "capture_0"), "--reference", str(tmp_path / "capture_0"),
                 "--distance", "700", "--out", str(tmp_path / "same")]) == 0
    assert json.loads((tmp_path / "same" / "report.json").read_text())["rmse"] == 0
    assert main(["placement-error", str(tmp_path / "capture_1"), "--reference", str(tmp_path / "capture_0"),
                 "--distance", "700", "--out", str(tmp_path / "moved")]) == 0
    report = json.loads((tmp_path / "moved" / "report.json").read_text())
    # Against brute-force nearest neighbours on a sample of the placed points.
    load = lambda name: np.load(tmp_path / name / "correspondence.npz")["points"]  # noqa: E731
    placed, ref = (p[np.isfinite(p).all(-1)].astype(np.float64) for p in (load("capture_1"), load("capture_0")))
    sample = placed[np.random.default_rng(0).choice(len(placed), 100, replace=False)]
    brute = cdist(sample, ref).min(1)
    assert np.allclose(scan_distance(sample, ref), brute)
    assert report["rmse"] > 1.0 and report["points"] == len(placed)


@pytest.mark.slow
def test_position_with_the_papers_eo(box_scene, tmp_path, capsys):
    # The paper's own test showed EO_0^255 patterns; the report says which solver made them.
    result = evaluate_positioning(box_scene, trials=1, max_evaluations=20, profile_steps=2, solver="eo")
    assert result.report["solver"] == "eo" and result.report["bounds_8bit"] == [0, 255]
    assert result.report["method"].startswith("patterns solved by eo (bounds 0..255)")
    fista = evaluate_positioning(box_scene, trials=1, max_evaluations=20, profile_steps=2)
    # EO is the weaker optimiser of the same problem: its patterns score no better at the goal.
    for e, f in zip(result.report["positions"], fista.report["positions"]):
        assert e["psnr_db_at_goal"] <= f["psnr_db_at_goal"] + 0.1
    path = tmp_path / "box.yaml"
    path.write_text(yaml.safe_dump(dict(small_config("box_positions", **SMALL), name="small_box")))
    with pytest.raises(SystemExit):  # argparse refuses an unknown solver before any work
        main(["position", str(path), "--solver", "nope", "--out", str(tmp_path / "o")])
    assert "invalid choice: 'nope'" in capsys.readouterr().err and not (tmp_path / "o").exists()


def _bumped(scene, **change):
    """``scene`` with a show: section that changes the upper projector after calibration."""
    return parse_scene(dict(small_config("box_positions", **SMALL), name="small_box",
                            show={"projectors": {"upper": change}}), name="small_box")


def test_a_scan_in_a_world_moved_since_calibration_triangulates_with_the_old_geometry(box_scene):
    """A projector bumped 4 mm after calibration: the scanner's points move off the box it scans, as
    they would on a bench whose scanner knows only its calibration; without a world, the scene's own."""
    from torchproj.scene import shown_scene

    box = box_scene.surfaces["box_near"]
    rms = lambda scan: float(np.sqrt(np.mean(box_surface_distance(scan["points"], box.world_from_local, box.size) ** 2)) * 1000)  # noqa: E731
    bumped = shown_scene(_bumped(box_scene, translation_mm=[4.0, 0.0, 0.0]))
    still = scan_surface(box_scene, box, box.world_from_local, seed=5)
    assert rms(still) < 1.5
    moved = scan_surface(box_scene, box, box.world_from_local, seed=5, world=bumped)
    upper = moved["projector"] == 0
    assert rms({"points": moved["points"][upper]}) > rms(still) + 1.0
    np.testing.assert_array_equal(scan_surface(box_scene, box, box.world_from_local, seed=5, world=box_scene)["points"],
                                  still["points"])
    with pytest.raises(InputError, match="world must be the scene as shown"):
        scan_surface(box_scene, box, box.world_from_local, world=small_scene(camera=(160, 120), projector=(256, 192)))


def test_positioning_looks_at_the_world_as_shown(box_scene):
    """A scene's show: section changed the world the run scored its patterns in, but the placements
    looked at the calibrated world: 22.2 dB of feedback at the near goal where the patterns captured
    14.2 dB. The feedback at the goal is now the shown world's, as the run's score is."""
    lamp = _bumped(box_scene, gain=1.6)
    result = evaluate_positioning(lamp, trials=1, max_evaluations=10, profile_steps=1)
    assert result.report["show"]["projectors"]["upper"]["gain"] == 1.6
    assert "Shown in a world changed after calibration" in position_markdown(result.report)
    for row in result.report["positions"]:
        assert abs(row["feedback_at_goal_db"] - row["psnr_db_at_goal"]) < 1.0, row
