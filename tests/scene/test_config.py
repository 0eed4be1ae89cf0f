import copy

import numpy as np
import pytest
import torch
import yaml
from kornia.geometry.camera import project_points

from torchproj.core import ConfigError
from torchproj.scene import BUILTIN_SCENES, load_scene, parse_scene, rotation_from_euler_deg, rotation_from_rotvec

from ..helpers import small_config


@pytest.mark.parametrize("name", BUILTIN_SCENES)
def test_builtin_scenes_load(name):
    scene = load_scene(name)
    assert scene.name == name
    assert len(scene.projectors) >= 2 and scene.states
    for state in scene.states:
        assert all(s in scene.surfaces for s in state.surfaces)


@pytest.mark.parametrize("name", BUILTIN_SCENES)
def test_configs_read_through_libyaml_are_what_pythons_safe_loader_reads(name, monkeypatch):
    """load_scene reads YAML through PyYAML's libyaml bindings where they exist (12x faster): the data,
    and the scene made from it, are those of PyYAML's own safe loader, which it falls back to."""
    from torchproj.pipeline.cache import _canonical  # every field as plain data, arrays as lists
    from torchproj.scene import builtin_config, config

    text = builtin_config(name).read_text()
    assert yaml.load(text, Loader=config._LOADER) == yaml.load(text, Loader=yaml.SafeLoader)
    fast = _canonical(load_scene(name))
    monkeypatch.setattr(config, "_LOADER", yaml.SafeLoader)
    assert _canonical(load_scene(name)) == fast


def test_paper_rig_matches_the_paper():
    scene = load_scene()
    assert [(p.width, p.height) for p in scene.projectors] == [(1024, 768), (1024, 768)]
    assert (scene.camera.width, scene.camera.height) == (1600, 1200)
    # Vertically stacked: the projectors differ only in y.
    a, b = (p.centre for p in scene.projectors)
    assert abs(a[0] - b[0]) < 1e-9 and abs(a[2] - b[2]) < 1e-9 and abs(a[1] - b[1]) > 0.05
    depths = sorted(s.world_from_local[2, 3] for s in scene.surfaces.values())
    assert depths == pytest.approx([0.8, 1.0])


def test_look_at_centres_the_target():
    scene = load_scene()
    target = torch.tensor([0.0, 0.0, 0.9], dtype=torch.float64)
    for dev in scene.projectors:
        pose = torch.as_tensor(dev.world_from_prj)
        local = (target - pose[:3, 3]) @ pose[:3, :3]
        uv = project_points(local[None], torch.as_tensor(dev.K))[0]
        assert uv.tolist() == pytest.approx([dev.cx, dev.cy], abs=1e-6)
        # The image's up (-y) points to world up (-y): the rig is not upside down.
        assert pose[1, 1] > 0.9


def test_rotations_are_orthonormal():
    for r in [rotation_from_rotvec(np.array([0.3, -0.2, 1.1])), rotation_from_euler_deg(np.array([10, 20, 30]))]:
        assert np.allclose(r @ r.T, np.eye(3)) and np.isclose(np.linalg.det(r), 1)


def _bad(mutate):
    data = small_config()
    mutate(data)
    with pytest.raises(ConfigError) as info:
        parse_scene(data)
    return str(info.value)


def test_unknown_key_suggests_the_right_one():
    msg = _bad(lambda d: d["camera"].update(focl=1000))
    assert msg.startswith("camera.focl: unknown key") and "did you mean 'focal'" in msg


def test_wrong_type_names_the_field():
    msg = _bad(lambda d: d["projectors"][1].update(focal="long"))
    assert msg.startswith("projectors[1].focal: must be a number")


def test_negative_focal_length():
    msg = _bad(lambda d: d["projectors"][0].update(focal=-5))
    assert msg.startswith("projectors[0].focal: must be greater than 0")


def test_pose_that_is_not_a_rotation():
    def mutate(d):
        d["surfaces"]["near_plane"]["pose"] = {"position": [0, 0, 0.8], "rotation": [[1, 0, 0], [0, 2, 0], [0, 0, 1]]}

    msg = _bad(mutate)
    assert msg.startswith("surfaces.near_plane.pose.rotation: is not a rotation")
    assert "orthonormal" in msg


def test_reflection_is_not_a_rotation():
    def mutate(d):
        d["surfaces"]["near_plane"]["pose"] = {"position": [0, 0, 0.8], "rotation": [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]}

    assert "is not a rotation" in _bad(mutate)


def test_surface_behind_the_camera():
    msg = _bad(lambda d: d["surfaces"]["far_plane"]["pose"].update(position=[0, 0, -1.0]))
    assert msg.startswith("surfaces.far_plane.pose.position: lies behind the camera")


def test_missing_mesh_file(tmp_path):
    def mutate(d):
        d["surfaces"]["near_plane"] = {"type": "mesh", "file": "head.obj", "pose": {"position": [0, 0, 0.8]}}

    data = small_config()
    mutate(data)
    with pytest.raises(ConfigError, match=r"surfaces.near_plane.file: mesh file .*head.obj' not found"):
        parse_scene(data, base_dir=tmp_path)


def test_a_mesh_in_millimetres_is_warned_of_naming_the_scale(tmp_path):
    """A 20 cm ball saved in millimetres was read as 200 m across, the camera inside it: the run was
    refused as a state no light reaches. Warned of at load, naming the scale that reads millimetres."""
    import warnings

    import trimesh

    trimesh.creation.icosphere(2, radius=100.0).export(tmp_path / "ball.ply")  # 200 mm across, in mm
    data = small_config()
    data["surfaces"]["near_plane"] = {"type": "mesh", "file": "ball.ply", "pose": {"position": [0, 0, 0.8]}}
    with pytest.warns(UserWarning, match=r"surfaces.near_plane.file: the mesh spans 200 m at scale 1, .* give the "
                                         r"surface scale: 0.001"):
        parse_scene(data, base_dir=tmp_path)
    data["surfaces"]["near_plane"]["scale"] = 0.001
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = parse_scene(data, base_dir=tmp_path)
    assert scene.surfaces["near_plane"].scale == 0.001


def test_state_naming_an_unknown_surface():
    msg = _bad(lambda d: d["states"][0].update(surfaces=["nope"]))
    assert msg.startswith("states[0].surfaces: names unknown surface 'nope'")


def test_a_surface_listed_twice_is_refused():
    """A state casting its surface twice (the copy hidden behind the first, at twice the cost) or a
    target naming it twice was taken without a word."""
    msg = _bad(lambda d: d["states"][0].update(surfaces=["near_plane", "near_plane"]))
    assert msg == "states[0].surfaces: names 'near_plane' twice (list each surface once)"
    msg = _bad(lambda d: d.update(targets=[{"name": "t", "state": "near", "surfaces": ["near_plane", "near_plane"]}]))
    assert msg == "targets[0].surfaces: names 'near_plane' twice (list each surface once)"


def test_transmittance_only_on_screens():
    def mutate(d):
        d["surfaces"]["box"] = {"type": "box", "size": [0.1, 0.1, 0.1], "transmittance": 0.5,
                                "pose": {"position": [0, 0, 0.9]}}

    assert _bad(mutate).startswith("surfaces.box.transmittance: is only supported on screens")


def test_two_orientations_conflict():
    msg = _bad(lambda d: d["camera"]["pose"].update(rotvec=[0, 0, 0]))
    assert msg.startswith("camera.pose.rotvec: conflicts with 'look_at'")


def test_missing_config_file_is_clear():
    with pytest.raises(ConfigError, match="not found"):
        load_scene("no_such_scene")


@pytest.mark.parametrize("source", [3, b"paper_two_planes", ["paper_two_planes"]])
def test_a_scene_that_is_no_name_or_path_is_named(source):
    """Path()'s TypeError before."""
    with pytest.raises(ConfigError, match=f"config: must be a YAML file's path or a scene's name, got {type(source).__name__}"):
        load_scene(source)


@pytest.mark.parametrize("limit", ["1e9", None, True])
def test_a_size_limit_that_is_no_number_is_named(limit):
    """A string or None ended in a TypeError on '<'; True was a limit of one ray."""
    with pytest.raises(ConfigError, match="size_limit: must be a finite number above 0"):
        load_scene("paper_two_planes", size_limit=limit)


def test_valid_config_is_not_mutated():
    data = small_config()
    before = copy.deepcopy(data)
    parse_scene(data)
    assert data == before


def _with_targets(targets):
    data = small_config("box_cylinders")
    data["targets"] = targets
    return data


def test_targets_name_surfaces_of_their_state():
    scene = parse_scene(_with_targets([
        {"name": "cyl", "state": "together", "surfaces": ["cylinder_left", "cylinder_right"], "image": "astronaut"},
        {"name": "box", "state": "together", "surfaces": ["box"]}]))
    assert [(t.name, t.surfaces, t.image) for t in scene.target_specs()] == [
        ("cyl", ["cylinder_left", "cylinder_right"], "astronaut"), ("box", ["box"], None)]


def test_without_targets_each_state_is_one_target():
    scene = parse_scene(small_config())
    assert [(t.name, t.state, t.surfaces) for t in scene.target_specs()] == [("near", "near", None), ("far", "far", None)]


@pytest.mark.parametrize("target, message", [
    ({"name": "a", "state": "elsewhere"}, r"targets\[0\]\.state: must be one of"),
    ({"name": "a", "state": "together", "surfaces": ["near_plane"]}, "not present in state"),
    ({"name": "a", "state": "together", "surfaces": []}, "non-empty list"),
    ({"name": "a", "state": "together", "image": "missing.png"}, "not found"),
    ({"name": "a", "state": "together", "colour": 1}, "unknown key"),
])
def test_bad_targets_name_the_field(target, message):
    with pytest.raises(ConfigError, match=message):
        parse_scene(_with_targets([target]))


def test_target_names_are_unique():
    with pytest.raises(ConfigError, match="unique"):
        parse_scene(_with_targets([{"name": "a", "state": "together"}, {"name": "a", "state": "together"}]))


@pytest.mark.parametrize("second, where", [
    ({"name": "b", "state": "together", "surfaces": ["box", "cylinder_left"]}, r"targets\[1\]\.surfaces: puts target 'b' "
                                                                              r"on surface 'cylinder_left'"),
    ({"name": "b", "state": "together"}, r"targets\[1\]: puts target 'b' on surface 'cylinder_left'")])
def test_two_targets_of_a_state_on_one_surface_are_refused(second, where):
    """Two images asked of one surface at once ran, both at 14 dB and crosstalk 0.74; refused, naming
    the surface and the target already there."""
    first = {"name": "a", "state": "together", "surfaces": ["cylinder_left"]}
    with pytest.raises(ConfigError, match=where + r" in state 'together', where targets\[0\] \('a'\) already is"):
        parse_scene(_with_targets([first, second]))
    other = parse_scene(_with_targets([first, {"name": "b", "state": "together", "surfaces": ["box"]}]))
    assert [t.surfaces for t in other.target_specs()] == [["cylinder_left"], ["box"]]


def test_target_image_paths_are_relative_to_the_config(tmp_path):
    import yaml

    from torchproj.core import write_image

    write_image(tmp_path / "logo.png", torch.rand(1, 8, 8))
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(_with_targets([{"name": "a", "state": "together", "image": "logo.png"}])))
    assert load_scene(path).targets[0].image == str(tmp_path / "logo.png")


def test_a_scaled_scene_is_the_same_rig_with_fewer_pixels():
    full, quarter = load_scene("paper_two_planes"), load_scene("paper_two_planes", scale=0.25)
    assert (quarter.camera.width, quarter.camera.height) == (400, 300)
    assert [(p.width, p.height) for p in quarter.projectors] == [(256, 192), (256, 192)]
    # A world point lands on the same place of each image, in fractions of its size (pixel centres at integers).
    point = np.array([0.05, -0.02, 0.8, 1.0])

    def fraction(device, world_from_device):
        local = np.linalg.inv(world_from_device) @ point
        u = device.K @ (local[:3] / local[2])
        return (u[0] + 0.5) / device.width, (u[1] + 0.5) / device.height

    assert np.allclose(fraction(full.camera, full.camera.world_from_cam),
                       fraction(quarter.camera, quarter.camera.world_from_cam), atol=1e-12)
    for a, b in zip(full.projectors, quarter.projectors):
        assert np.allclose(fraction(a, a.world_from_prj), fraction(b, b.world_from_prj), atol=1e-12)
    assert quarter.surfaces.keys() == full.surfaces.keys()


@pytest.mark.parametrize("scale", [0, -1, 10, "half", True])
def test_a_scale_out_of_range_is_refused(scale):
    with pytest.raises(ConfigError, match="scale: must be a number in"):
        load_scene("paper_two_planes", scale=scale)


def test_a_built_in_name_is_found_whatever_the_working_folder_holds(tmp_path, monkeypatch):
    (tmp_path / "paper_two_planes").mkdir()  # a folder of the same name where the user stands
    monkeypatch.chdir(tmp_path)
    assert load_scene("paper_two_planes").name == "paper_two_planes"
    with pytest.raises(ConfigError) as err:
        load_scene("paper_two_plane")
    assert "'paper_two_plane' not found" in str(err.value) and "'paper_two_plane'," not in str(err.value)


@pytest.mark.parametrize("focus, message", [
    ({"distance": -0.8, "aperture": 10}, "projectors[0].focus.distance: must be greater than 0"),
    ({"aperture": 10}, "projectors[0].focus.distance: is required"),
    ({"distance": 0.8}, "projectors[0].focus.aperture: is required"),
    ({"distance": 0.8, "aperture": 0}, "projectors[0].focus.aperture: must be greater than 0"),
    ({"distance": 0.8, "aperture": 10000}, "projectors[0].focus.aperture: is 10000 mm, wider than any projector lens"),
    ({"distance": 0.8, "aperture": 10, "f_number": 2}, "projectors[0].focus.f_number: unknown key"),
    (0.8, "projectors[0].focus: must be a mapping"),
])
def test_bad_focus_names_the_field(focus, message):
    assert _bad(lambda d: d["projectors"][0].update(focus=focus)).startswith(message)


def test_a_focused_projector_reads_millimetres_and_says_so():
    data = small_config()
    data["projectors"][0]["focus"] = {"distance": 0.8, "aperture": 10}
    scene = parse_scene(data)
    upper, lower = scene.projectors
    assert (upper.focus_distance, upper.aperture, lower.focus_distance) == (0.8, 0.01, None)
    assert upper.blur_diameter(1.0)[0] == pytest.approx(upper.fx * 0.01 * 0.25)
    assert "focused at 0.8 m, aperture 10 mm" in scene.describe()


def _colour(mixing=None, channels=3):
    data = small_config("colour_two_planes", channels=channels)
    for p in data["projectors"]:  # the shipped rig switches mixing off; these are a user's scenes
        p.pop("colour_mixing")
    if mixing is not None:
        data["projectors"][0]["colour_mixing"] = mixing
    return data


def test_colour_mixing_is_on_for_colour_cameras_unless_switched_off():
    from torchproj.core.conventions import DEFAULT_COLOUR_MIXING

    upper, lower = parse_scene(_colour()).projectors
    assert upper.colour_mixing == lower.colour_mixing == DEFAULT_COLOUR_MIXING
    assert parse_scene(_colour("none")).projectors[0].colour_mixing is None
    grey = parse_scene(small_config()).projectors[0]
    assert grey.colour_mixing is None
    mine = [[0.8, 0.2, 0.0], [0.1, 0.8, 0.1], [0.0, 0.3, 0.7]]
    scene = parse_scene(_colour(mine))
    assert scene.projectors[0].colour_mixing == tuple(map(tuple, mine))
    assert "colour mixing [[0.8, 0.2, 0.0]" in scene.describe()


@pytest.mark.parametrize("mixing, channels, message", [
    ([[1, 0, 0], [0, 1, 0], [0, 0, 1]], 1, "projectors[0].colour_mixing: needs a colour camera"),
    ([[1, 0], [0, 1]], 3, "projectors[0].colour_mixing: must be 3 rows"),
    ("lots", 3, "projectors[0].colour_mixing: must be 3 rows"),
    ([[1, 0, 0], [0, 1, -0.1], [0, 0, 1]], 3, r"projectors[0].colour_mixing[1][2]: must be at least 0"),
    ([[1, 0, 0], [0, 0, 0], [0, 0, 1]], 3, "projectors[0].colour_mixing[1]: is all zero"),
    ([[0.5, 0.5, 0], [0.5, 0.5, 0], [0, 0, 1]], 3, "projectors[0].colour_mixing: mixes the primaries so much"),
])
def test_bad_colour_mixing_names_the_field(mixing, channels, message):
    with pytest.raises(ConfigError) as err:
        parse_scene(_colour(mixing, channels))
    assert str(err.value).startswith(message)


def test_a_misspelt_required_key_is_named():
    message = _bad(lambda d: d["camera"].update(focl=d["camera"].pop("focal")))
    assert message.startswith("camera.focal: is required") and "found 'focl': did you mean 'focal'?" in message


def test_config_files_that_are_not_scenes_are_named(tmp_path):
    with pytest.raises(ConfigError, match="is a folder"):
        load_scene(tmp_path)
    with pytest.raises(ConfigError, match="is not a regular file"):
        load_scene("/dev/null")
    latin = tmp_path / "latin.yaml"
    latin.write_bytes("name: caf\xe9\n".encode("latin-1"))
    with pytest.raises(ConfigError, match=r"latin.yaml: is not UTF-8 text \(byte 9"):
        load_scene(latin)
    bomb = tmp_path / "bomb.yaml"
    lines = ["a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"] + [f"{chr(98 + i)}: &{chr(98 + i)} [" + ", ".join(
        [f"*{chr(97 + i)}"] * 10) + "]" for i in range(12)]
    bomb.write_text("\n".join(lines) + "\n")
    with pytest.raises(ConfigError, match=r"bomb.yaml: uses 120 YAML aliases"):
        load_scene(bomb)
    huge = tmp_path / "huge.yaml"
    huge.write_text(yaml.safe_dump(small_config()) + "seed: " + "9" * 5000 + "\n")
    with pytest.raises(ConfigError, match="huge.yaml: holds a value YAML cannot read"):
        load_scene(huge)


@pytest.mark.parametrize("frames, message", [(0, "must be at least 1, got 0"), (2.5, "must be a whole number"),
                                             (1000, "must be at most 256, got 1000")])
def test_bad_camera_frames_name_the_field(frames, message):
    assert _bad(lambda d: d["camera"].update(frames=frames)).startswith(f"camera.frames: {message}")


def test_a_seed_past_64_bits_is_refused():
    message = _bad(lambda d: d.update(seed=10**40))
    assert message.startswith("seed: must be at most 9223372036854775807, got a number of 41 digits")


@pytest.mark.parametrize("name", ["", "  ", "a/b", "..", ".", "a\\\\b", "tab\there"])
@pytest.mark.parametrize("where", ["projectors", "states"])
def test_a_name_that_cannot_name_an_output_file_is_refused(name, where):
    """Projector, state and target names become files and folders (patterns/NAME.png,
    captures/STATE/PROJECTOR): an empty one failed at the very end, writing patterns/.png."""
    data = small_config()
    data[where][0]["name"] = name
    with pytest.raises(ConfigError, match=rf"{where}\[0\]\.name: .* cannot name a file or folder of the outputs"):
        parse_scene(data)


@pytest.mark.parametrize("where", ["projectors", "states"])
def test_names_that_differ_only_in_case_are_refused(where):
    """``patterns/a.png`` and ``patterns/A.png`` are one file on macOS's and Windows' file systems: the
    second projector's pattern was written over the first's without a word."""
    data = small_config()
    data[where][1]["name"] = data[where][0]["name"].upper()
    with pytest.raises(ConfigError, match=rf"^{where}: names .* differ only in case"):
        parse_scene(data)


@pytest.mark.parametrize("text", ["name: " + "[" * 5000 + "]" * 5000, "camera: " + "{a: " * 2000 + "1" + "}" * 2000])
def test_a_config_nested_past_any_scene_is_refused_before_yaml_recurses(tmp_path, text):
    """PyYAML composes one level per Python call: 50,000 brackets ended in a RecursionError traceback."""
    path = tmp_path / "deep.yaml"
    path.write_text(text + "\n")
    with pytest.raises(ConfigError, match=r"deep.yaml: nests lists and mappings \d+ deep, over 64") as refused:
        load_scene(path)
    assert "cannot read" not in str(refused.value)  # worded once, not wrapped in another message


def test_describe_says_what_changes_the_light():
    """``torchproj scene`` is how a person checks a config they wrote: the camera's pose, exposure and
    distortion, each surface's albedo and transmittance and the room light change every capture, and
    none was said (a distorted camera and a veil read as a pinhole and an opaque wall)."""
    data = small_config()
    data["camera"]["distortion"] = [0.05, -0.01, 0, 0, 0]
    data["camera"]["exposure"] = 1.3
    data["surfaces"]["near_plane"].update(albedo=0.35, transmittance=0.6)
    data["ambient"] = 0.03
    lines = parse_scene(data).describe().splitlines()
    camera = next(line for line in lines if line.startswith("  camera:"))
    assert "exposure 1.3" in camera and "distortion [0.05, -0.01, 0.0, 0.0, 0.0]" in camera
    position = parse_scene(data).camera.world_from_cam[:3, 3]
    assert f"at {np.round(position, 3).tolist()} m" in camera
    assert "  surface near_plane: rectangle at [0.0, 0.0, 0.8] m, albedo 0.35, passes 0.6 of the light on" in lines
    assert "  room light: 0.03 W/m^2 on every surface" in lines
    plain = load_scene("paper_two_planes").describe()
    assert "distortion" not in plain and "passes" not in plain and "gamma" not in plain
