"""The 3D inspection scripts render off-screen and show what they should."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from torchproj.core import read_image
from torchproj.scene import load_scene

from .helpers import CHESSBOARD, small_config

ROOT = Path(__file__).resolve().parents[1]


def _load(name):
    spec = importlib.util.spec_from_file_location(f"viz_{name}", ROOT / "viz" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def rig_module():
    pytest.importorskip("pyvista")
    return _load("rig")


def test_rig_view_draws_devices_and_surfaces(rig_module, tmp_path):
    images = {}
    for name in ("paper_two_planes", "box_cylinders"):
        out = tmp_path / f"{name}.png"
        rig_module.draw_rig(load_scene(name), out, window_size=(400, 300)).close()
        img = read_image(out)
        assert img.shape[1:] == (300, 400)
        images[name] = img
        # Not blank: the frusta (red) and surfaces (blue-ish) are drawn on the white background.
        rgb = img.numpy()
        red = (rgb[0] > 0.6) & (rgb[1] < 0.4) & (rgb[2] < 0.4)
        blue = (rgb[2] > rgb[0] + 0.2)
        assert red.sum() > 100 and blue.sum() > 500
    assert not np.array_equal(images["paper_two_planes"].numpy(), images["box_cylinders"].numpy())
    # Beside each PNG: every frustum and surface by name, and the view for a glTF viewer.
    import pyvista as pv

    scene = load_scene("box_cylinders")
    blocks = pv.read(tmp_path / "box_cylinders.vtm")
    assert sorted(blocks.keys()) == sorted(["camera", *(f"projector_{p.name}" for p in scene.projectors),
                                            *(f"{st.name}_{s}" for st in scene.states for s in st.surfaces)])
    assert len(_gltf(tmp_path / "box_cylinders.gltf")) >= len(blocks)


def test_frustum_passes_through_the_image_corners(rig_module):
    scene = load_scene()
    p = scene.projectors[0]
    lines = rig_module.frustum(p.K, p.width, p.height, p.world_from_prj, depth=1.0)
    corner = lines.points[1]  # top-left image corner at depth 1 m along the optical axis
    local = (corner - p.centre) @ p.world_from_prj[:3, :3]
    assert local[2] == pytest.approx(1.0)
    assert p.fx * local[0] / local[2] + p.cx == pytest.approx(-0.5)
    assert p.fy * local[1] / local[2] + p.cy == pytest.approx(-0.5)


@pytest.fixture(scope="module")
def viz():
    pytest.importorskip("pyvista")
    return {name: _load(name) for name in ("positioning", "point_cloud", "correspondences")}


def _colours(path):
    """Pixels of pure red (the goal box's wireframe) and pixels painted at all (anything but white)."""
    rgb = read_image(path).numpy()
    red = (rgb[0] > 0.8) & (rgb[1] < 0.2) & (rgb[2] < 0.2)
    painted = (np.abs(rgb - 1).sum(0) > 0.1)
    return red.sum(), painted.sum()


def _box_front_points(pose, size, n=60):
    """Points on the box face whose outward normal is local -z (the face the rig sees)."""
    g = np.linspace(-0.45, 0.45, n)
    u, v = np.meshgrid(g * size[0], g * size[1])
    local = np.c_[u.ravel(), v.ravel(), np.full(u.size, -size[2] / 2)]
    return local @ pose[:3, :3].T + pose[:3, 3]


def test_positioning_view_colours_the_signed_error(viz, tmp_path):
    """Toward the rig (short of the goal) is positive, past it negative; the scan's values are written
    beside the PNG, and the title names the RMSE and the placed pose's error."""
    pv = pytest.importorskip("pyvista")
    box = load_scene("box_positions").surfaces["box_near"]
    goal, size = box.world_from_local, np.array(box.size)
    normal = goal[:3, :3] @ np.array([0.0, 0.0, -1.0])  # out of the face the rig sees
    for shift_mm in (-3, 1, 12):
        placed = goal.copy()
        placed[:3, 3] += shift_mm / 1000 * normal
        scan = {"points": _box_front_points(placed, size), "goal_pose": goal, "box_size": size,
                "placed_pose": placed, "start_pose": placed}
        out = tmp_path / f"shift{shift_mm}.png"
        viz["positioning"].draw_scan(scan, out, max_mm=15, window_size=(400, 300)).close()
        red, painted = _colours(out)
        assert red > 50 and painted > 2000  # the goal's red wireframe, and the scan
        values = pv.read(out.with_suffix(".vtm"))["scan"]["signed distance to goal (mm)"]
        assert np.allclose(values, shift_mm, atol=0.01), shift_mm


def test_positioning_views_of_a_run_share_one_colour_scale(viz, tmp_path, capsys):
    box = load_scene("box_positions").surfaces["box_near"]
    goal, size = box.world_from_local, np.array(box.size)
    (tmp_path / "scans").mkdir()
    for name, shift_mm in (("near_0", 1), ("near_1", 9)):
        placed = goal.copy()
        placed[:3, 3] += shift_mm / 1000 * (goal[:3, :3] @ np.array([0.0, 0.0, -1.0]))
        np.savez(tmp_path / "scans" / f"{name}.npz", points=_box_front_points(placed, size), goal_pose=goal,
                 box_size=size, placed_pose=placed, start_pose=goal)
    drawn = []
    real = viz["positioning"].draw_scan

    def spy(scan, out, max_mm=None, *args, **kwargs):
        drawn.append(max_mm)
        return real(scan, out, max_mm, *args, window_size=(300, 200))

    viz["positioning"].draw_scan = spy
    try:
        assert viz["positioning"].main([str(tmp_path)]) == 0
    finally:
        viz["positioning"].draw_scan = real
    assert len(drawn) == 2 and drawn[0] == drawn[1] == pytest.approx(9, abs=0.01)
    assert (tmp_path / "views" / "near_0.png").is_file() and (tmp_path / "views" / "near_1.vtm").is_file()


def test_point_cloud_view_fits_the_plane(viz, tmp_path):
    rng = np.random.default_rng(0)
    xy = rng.uniform(-100, 100, size=(5000, 2))
    bump = 3.0 * np.exp(-(xy**2).sum(1) / 400)  # a 3 mm bump in the middle of a tilted plane (mm)
    points = np.c_[xy, 800 + 0.2 * xy[:, 0] + bump]
    out = tmp_path / "plane.png"
    plotter, residual, on_plane = viz["point_cloud"].draw_plane_fit(points, out, threshold=10,
                                                                     window_size=(400, 300))
    plotter.close()
    assert on_plane.all()  # every point within 10 mm: the least-squares plane of the whole cloud
    tilt = np.array([-0.2, 0.0, 1.0]) / np.linalg.norm([-0.2, 0.0, 1.0])
    expected = (points - points.mean(0)) @ tilt
    assert np.allclose(np.abs(residual), np.abs(expected), atol=0.1)
    rgb = read_image(out).numpy()
    warm = (rgb[0] > rgb[2] + 0.3).sum()
    cool = (rgb[2] > rgb[0] + 0.3).sum()
    assert warm > 200 and cool > 200
    # The view's geometry is written beside it with its values, and reads back as written.
    pv = pytest.importorskip("pyvista")
    back = pv.read(out.with_suffix(".vtm"))["cloud"]
    assert np.allclose(back.points, points, atol=1e-3) and np.allclose(back["signed distance (mm)"], residual)
    # And the view as a glTF viewer shows it: the same points, coloured.
    clouds = [g for g in _gltf(out.with_suffix(".gltf")) if len(g.vertices) == len(points)]
    assert len(clouds) == 1 and np.allclose(clouds[0].vertices, points, atol=1e-3)


def _gltf(path):
    """The geometries of a glTF file as trimesh (the ray caster's library, a dependency) reads them."""
    import trimesh

    assert path.is_file(), path
    return list(trimesh.load(path, force="scene").geometry.values())


def test_point_cloud_view_measures_the_board_not_the_wall_behind_it(viz, tmp_path):
    """A board with 0.3 mm noise before a wall: the view fits the board (one plane through all of it
    gave an RMS of 7 without a unit on the real capture) and greys the wall."""
    rng = np.random.default_rng(1)
    board = np.c_[rng.uniform(-100, 100, (4000, 2)), 800 + rng.normal(0, 0.3, 4000)]
    wall = np.c_[rng.uniform(-300, 300, (3000, 2)), np.full(3000, 950.0)]
    out = tmp_path / "board.png"
    plotter, residual, on_plane = viz["point_cloud"].draw_plane_fit(np.vstack([board, wall]), out, threshold=1.5,
                                                                     window_size=(400, 300))
    plotter.close()
    assert on_plane[:4000].mean() > 0.98 and not on_plane[4000:].any()
    assert np.sqrt(np.mean(residual[on_plane] ** 2)) == pytest.approx(0.3, rel=0.1)


def test_show_takes_the_screenshot_after_the_window_renders(viz, tmp_path):
    """``--show`` failed: the PNG was taken before the window existed. The shared ending now asks the
    window for it; the glTF is written first, while the window is open (``show`` closes it)."""
    calls = []

    class Window:
        def show(self, screenshot=None):
            calls.append(("show", screenshot))

        def screenshot(self, path):
            calls.append(("screenshot", path))

        def export_gltf(self, path):
            calls.append(("gltf", path))

    finish = viz["point_cloud"].finish
    finish(Window(), tmp_path / "v.png", show=True)
    finish(Window(), tmp_path / "w.png", show=False)
    assert calls == [("gltf", str(tmp_path / "v.gltf")), ("show", str(tmp_path / "v.png")),
                     ("gltf", str(tmp_path / "w.gltf")), ("screenshot", str(tmp_path / "w.png"))]


@pytest.mark.slow
@pytest.mark.skipif(not CHESSBOARD.is_dir(), reason=f"real captures not found at {CHESSBOARD}")
def test_point_cloud_view_of_the_real_chessboard(viz, tmp_path):
    from torchproj.cli import main

    out = tmp_path / "dec"
    assert main(["decode", str(CHESSBOARD / "capture_1"), "--projector", "1024x768", "--out", str(out),
                 "--calibration", str(CHESSBOARD / "calibration_result.xml")]) == 0
    assert viz["point_cloud"].main([str(out)]) == 0
    assert (out / "points.png").is_file() and _colours(out / "points.png")[1] > 5000
    # The board, not the wall behind it: one plane through everything had an RMS of 7.1 mm; the board's
    # own, over the whole board to its curved edges, is under a millimetre.
    pv = pytest.importorskip("pyvista")
    cloud = pv.read(out / "points.vtm")["cloud"]
    on = cloud["on plane"].astype(bool)
    assert 0.2 < on.mean() < 0.6 and np.sqrt(np.mean(cloud["signed distance (mm)"][on] ** 2)) < 1.0


@pytest.mark.slow
def test_correspondences_view_triangulates_onto_the_planes(viz, tmp_path):
    import yaml

    from torchproj.cli import main

    path = tmp_path / "small.yaml"
    path.write_text(yaml.safe_dump(dict(small_config(camera=(240, 180), projector=(128, 96)), name="small")))
    assert main(["simulate", str(path), "--out", str(tmp_path / "sim")]) == 0
    scene = load_scene(path)
    clouds = viz["correspondences"].correspondence_clouds(scene, tmp_path / "sim")
    assert len(clouds) == 4
    for c in clouds:
        plane_z = scene.surfaces[scene.state(c["state"]).surfaces[0]].world_from_local[2, 3]
        assert len(c["points"]) > 1000
        assert np.median(np.abs(c["points"][:, 2] - plane_z)) < 2e-3  # metres
    images = []
    for colour in ("projector", "contrast"):
        out = tmp_path / f"{colour}.png"
        assert viz["correspondences"].main([str(tmp_path / "sim"), "--colour", colour, "--out", str(out)]) == 0
        images.append(read_image(out).numpy())
        assert _colours(out)[1] > 2000
    assert not np.array_equal(images[0], images[1])
    # Only the pairs drawn are triangulated, and the view's clouds are written beside it with their values.
    few = viz["correspondences"].correspondence_clouds(scene, tmp_path / "sim", points=500)
    assert [len(c["points"]) for c in few] == [500] * 4
    pv = pytest.importorskip("pyvista")
    blocks = pv.read(tmp_path / "contrast.vtm")
    assert sorted(blocks.keys()) == sorted(f"{c['state']}_{scene.projectors[c['projector']].name}" for c in clouds)


@pytest.mark.parametrize("script, argv", [("point_cloud", ["--threshold", "-1"]), ("point_cloud", ["--threshold", "nan"]),
                                          ("correspondences", ["--points", "-5"]), ("positioning", ["--max-mm", "0"])])
def test_a_views_bad_option_is_refused_by_its_parser(viz, tmp_path, capsys, script, argv):
    """A negative --points took all but that many pairs; a NaN tolerance ended in a traceback."""
    with pytest.raises(SystemExit) as refused:
        viz[script].main([str(tmp_path), *argv])
    assert refused.value.code == 2 and f"argument {argv[0]}" in capsys.readouterr().err


@pytest.mark.parametrize("name, far", [("suite-1-3", None), ("paper_two_planes", 2.5)])
def test_rig_view_frames_rigs_of_any_size_and_reaches_past_every_surface(rig_module, tmp_path, name, far):
    """The view was fixed on the paper's rig: other rigs' axes ran off the image's edges, and frusta 1.1 m
    long stopped short of surfaces beyond it. The view is framed on what the scene holds (nothing drawn
    touches the left, right or bottom edge), and the frusta reach every surface point a device faces."""
    if far is None:
        scene = load_scene(name)
    else:  # the same planes moved out to 2.5 m
        data = small_config(name)
        for surface in data["surfaces"].values():
            surface["pose"]["position"][2] *= far
        from torchproj.scene import parse_scene

        scene = parse_scene(data, name=name)
    out = tmp_path / "rig.png"
    rig_module.draw_rig(scene, out, window_size=(500, 375)).close()
    ink = (read_image(out).numpy() < 0.8).any(0)
    assert ink.sum() > 2000
    assert not ink[:, :3].any() and not ink[:, -3:].any() and not ink[-3:, :].any()
    depth = rig_module.frustum_depth(scene)
    points = np.vstack([rig_module.surface_mesh(s).points for s in scene.surfaces.values()])
    for pose in [scene.camera.world_from_cam, *(p.world_from_prj for p in scene.projectors)]:
        assert ((points - pose[:3, 3]) @ pose[:3, 2]).max() <= depth


def test_each_cloud_takes_its_projectors_colour_and_no_other_clouds(viz):
    """Rays and frusta are drawn in their projector's colour; a cloud palette of its own gave a third
    projector's rays the colour of the first projector's far cloud. Each (state, projector) cloud now
    has a colour of its own, nearer its projector's than any other projector's."""
    module = viz["correspondences"]

    import colorsys

    def hue(hex_colour):
        return colorsys.rgb_to_hsv(*(int(hex_colour[i:i + 2], 16) / 255 for i in (1, 3, 5)))[0]

    projectors = [hue(module.PROJECTOR_COLOURS[j]) for j in range(4)]
    for states in (1, 2, 3):
        clouds = {(j, s): module.cloud_colour(j, s, states) for j in range(4) for s in range(states)}
        assert len(set(clouds.values())) == len(clouds)
        for (j, _), colour in clouds.items():
            gaps = [min(abs(hue(colour) - h), 1 - abs(hue(colour) - h)) for h in projectors]
            assert int(np.argmin(gaps)) == j and gaps[j] < 0.02, (j, colour)


@pytest.mark.parametrize("script, argv, message", [
    ("rig", ["--depth=-1"], "argument --depth: must be a finite number above 0"),
    ("rig", ["--depth=nan"], "argument --depth: must be a finite number above 0"),
    ("rig", ["no_such_scene"], "config: file 'no_such_scene' not found"),
    ("correspondences", ["RUN", "--rays=-1"], "argument --rays: must be 0-100 rays per cloud, got -1"),
    ("correspondences", ["RUN", "--rays=5000"], "argument --rays: must be 0-100 rays per cloud, got 5000")])
def test_the_views_refuse_bad_options_by_name(script, argv, message, tmp_path, capsys):
    """A frustum of -1 m or NaN was drawn without a word, ``--rays -1`` ended in numpy's traceback and 5000
    rays (a mesh each) drew for minutes; a misspelt scene was a traceback."""
    pytest.importorskip("pyvista")
    with pytest.raises(SystemExit) as stopped:
        _load(script).main([str(tmp_path) if a == "RUN" else a for a in argv] + ["--out", str(tmp_path / "v.png")])
    assert stopped.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "v.png").exists()


def _damaged_runs(root: Path) -> list[tuple[str, Path, str]]:
    """Folders the views read, each with one file cut short, edited or of another program: (script, folder,
    what the refusal says)."""
    import json

    from torchproj.calib import write_ply

    cases = []

    def folder(name, files):
        path = root / name
        for rel, content in files.items():
            (path / rel).parent.mkdir(parents=True, exist_ok=True)
            if callable(content):
                content(path / rel)
            else:
                (path / rel).write_bytes(content)
        return path

    report = json.dumps({"config": "paper_two_planes"}).encode()
    cases += [("correspondences", folder("cut", {"report.json": b'{"config": '}), "report.json: cannot be read"),
              ("correspondences", folder("noconfig", {"report.json": b"{}"}), "report.json: has no 'config'"),
              ("correspondences", folder("gone", {"report.json": json.dumps({"config": str(root / "moved.yaml")}).encode()}),
               "cannot be read (config: file"),
              ("correspondences", folder("npz", {"report.json": report, "calibration/near/upper/correspondence.npz": b"xx"}),
               "correspondence.npz: cannot be read"),
              ("correspondences", folder("keys", {"report.json": report, "calibration/near/upper/correspondence.npz":
                                                  lambda p: np.savez(p, prj_xy=np.zeros((2, 2, 2)))}),
               "correspondence.npz: has no array 'contrast'"),
              ("correspondences", folder("shape", {"report.json": report, "calibration/near/upper/correspondence.npz":
                                                   lambda p: np.savez(p, prj_xy=np.zeros((2, 2, 2)), contrast=np.zeros((2, 2)))}),
               "do not fit the scene's 1600x1200 camera"),
              ("point_cloud", folder("ply", {"points.ply": b"garbage"}), "points.ply: cannot be read"),
              ("point_cloud", folder("nan", {"points.ply": lambda p: write_ply(p, np.full((5, 3), np.nan))}),
               "5 of its 5 points are not finite"),
              ("positioning", folder("scan", {"scans/near_0.npz": b"xx"}), "near_0.npz: cannot be read"),
              ("positioning", folder("pickled", {"scans/near_0.npz": lambda p: np.savez(p, points=np.array([{}]))}),
               "near_0.npz: cannot be read (Object arrays cannot be loaded"),
              ("positioning", folder("pose", {"scans/near_0.npz": lambda p: np.savez(p, points=np.zeros((5, 3)))}),
               "near_0.npz: has no array 'goal_pose'")]
    return cases


def test_a_views_damaged_input_is_refused_naming_the_file(tmp_path, capsys):
    """A run folder whose files were cut short, edited or written by another program ended in json's,
    numpy's or VTK's traceback (VTK's after a page of its own log, and an empty cloud after it)."""
    pytest.importorskip("pyvista")
    failures = []
    for script, folder, says in _damaged_runs(tmp_path):
        out = tmp_path / f"{folder.name}.png"
        try:
            _load(script).main([str(folder), "--out", str(out)])
            failures.append(f"{script} {folder.name}: drew it")
        except SystemExit as stopped:
            err = capsys.readouterr().err
            if stopped.code != 2 or says not in err or out.exists():
                failures.append(f"{script} {folder.name}: exit {stopped.code}, {err.strip()[-300:]!r}")
    assert not failures, "\n".join(failures)
