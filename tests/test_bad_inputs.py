"""Bad inputs, as a new user makes them: every config field, CLI option, capture file and bundle file
mutated by a seeded fuzzer. The contract for each: the command either works, or it prints one
``torchproj CMD: error:`` line and exits 2; never a traceback, never a file left in ``--out`` or beside
it, and never a refusal after calibration for what could have been checked before it.

The default run draws a fixed sample of every mutation family; ``TORCHPROJ_FUZZ=all`` runs them all
(marked slow, as CI's full pass does).
"""

from __future__ import annotations

import copy
import json
import os
import random
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from torchproj.cli import main
from torchproj.scene import parse_scene

from .helpers import calibrate_bench, small_config

# What a hand-edited YAML or a typo gives: wrong types, signs, NaN, inf, huge sizes, empties.
BAD_VALUES = [None, "", "abc", -1, 0, 0.5, 1e30, -1e30, float("nan"), float("inf"), 10 ** 12, True, [], {}, [1],
              [1, 2, 3], {"x": 1}]
SAMPLE = None if os.environ.get("TORCHPROJ_FUZZ") == "all" else 40


def tiny_config() -> dict:
    data = small_config(camera=(160, 120), projector=(128, 96))
    data["camera"]["supersampling"] = 2
    data["targets"] = [{"name": "a", "state": "near", "image": "astronaut"},
                       {"name": "b", "state": "far", "image": "camera"}]
    return data


def _leaves(data, path=()):
    """Every field of a YAML tree as a path of keys and indices (mappings, lists and their items)."""
    if isinstance(data, dict):
        for k, v in data.items():
            yield path + (k,)
            yield from _leaves(v, path + (k,))
    elif isinstance(data, list):
        # The first and last items stand for the rest (a ramp holds 32 numbers of one kind).
        for i in sorted({0, len(data) - 1} if data else ()):
            yield path + (i,)
            yield from _leaves(data[i], path + (i,))


def _mutated(data: dict, path: tuple, value) -> dict:
    data = copy.deepcopy(data)
    node = data
    for key in path[:-1]:
        node = node[key]
    if value is _DELETE:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return data


_DELETE = object()


def _sample(cases: list, seed: int) -> list:
    return cases if SAMPLE is None or len(cases) <= SAMPLE else random.Random(seed).sample(cases, SAMPLE)


class WorkCounter:
    """Counts the virtual-rig runs that got past calibration (``run_virtual`` takes the world as shown
    next). A bad input is refused before the work begins, or by calibration's own measurements (a
    ramp that shows no levels, a state that decodes nothing: what the captures say), never after a
    finished calibration for something that could have been checked first (on the full-size rig
    that is half a minute lost)."""

    def __init__(self):
        from torchproj.pipeline import run

        self.module, self.count = run, 0
        self.originals = {"shown_world": run.shown_world}

    def __enter__(self):
        for name, original in self.originals.items():
            setattr(self.module, name, self._counted(original))
        return self

    def __exit__(self, *exc):
        for name, original in self.originals.items():
            setattr(self.module, name, original)

    def _counted(self, original):
        def counted(*args, **kwargs):
            self.count += 1
            return original(*args, **kwargs)

        return counted


def run_cli(argv: list[str], capsys, out: Path | None = None) -> tuple[int, str, int]:
    """``main(argv)`` in this process: exit code (argparse's SystemExit included), stderr, and how many
    virtual-rig runs got past calibration (:class:`WorkCounter`)."""
    with WorkCounter() as work:
        try:
            code = main(argv)
        except SystemExit as exc:
            code = exc.code
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    assert code in (0, 2), f"exit code {code} for {argv}: {err}"
    if code == 2:
        assert f"torchproj {argv[0]}: error:" in err or "error: argument" in err or "error: the following" in err, err
        assert work.count == 0, f"{argv} was refused after its calibration was done: {err}"
        if out is not None:
            assert not out.exists(), f"{out} written by a refused {argv}"
    if out is not None:
        assert not [p for p in out.parent.iterdir() if ".partial-" in p.name], f"staging left beside {out}"
    return code, err, work.count


def _cases_for_config(data: dict) -> list:
    cases = [(path, _DELETE) for path in _leaves(data)]
    cases += [(path, value) for path in _leaves(data) for value in BAD_VALUES]
    return cases


def _each(cases: list, seed: int, tmp_path: Path, attempt) -> None:
    """``attempt(case, folder)`` for the sample of ``cases``; one failure list for all of them."""
    failures = []
    for i, case in enumerate(_sample(cases, seed)):
        folder = tmp_path / f"case{i}"
        folder.mkdir()
        try:
            attempt(case, folder)
        except Exception as exc:  # noqa: BLE001 - a traceback is exactly what this test looks for
            failures.append(f"{case!r}: {type(exc).__name__}: {str(exc)[:300]}")
    assert not failures, f"{len(failures)} bad input(s) mishandled:\n" + "\n".join(failures)


def test_mutated_configs_are_refused_cleanly_or_run(tmp_path, capsys):
    data = tiny_config()

    def attempt(case, folder):
        path, value = case
        config = folder / "scene.yaml"
        config.write_text(yaml.safe_dump(_mutated(data, path, value)))
        run_cli(["run", str(config), "--out", str(folder / "out"), "--max-iter", "20"], capsys, folder / "out")

    _each(_cases_for_config(data), 0, tmp_path, attempt)


# Every option of a command with values of the wrong kind; argparse or the library must refuse them.
BAD_ARGS = ["-1", "0", "nan", "inf", "1e30", "abc", "", "1,1", "2,1", "-1e30,1e30", "nan,1"]


def _options(command: str) -> list[str]:
    """Every option of a subcommand that takes a value, read from the parser itself."""
    from torchproj.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command").choices[command]
    return [a.option_strings[-1] for a in sub._actions
            if a.option_strings and a.nargs != 0 and a.dest not in ("help", "out")]


@pytest.mark.slow
def test_bad_run_options_are_refused_cleanly_or_run(tmp_path, capsys):
    config = tmp_path / "scene.yaml"
    config.write_text(yaml.safe_dump(tiny_config()))

    def attempt(case, folder):
        option, value = case
        run_cli(["run", str(config), "--out", str(folder / "out"), "--max-iter", "20", f"{option}={value}"], capsys,
                folder / "out")

    _each([(o, v) for o in _options("run") for v in BAD_ARGS], 1, tmp_path, attempt)


@pytest.fixture(scope="module")
def capture_root(tmp_path_factory):
    return capture_root_for(tmp_path_factory.mktemp("fuzz"))


def capture_root_for(root: Path) -> Path:
    """A tiny rig's calibration captures as a bench stores them (``root/captures``), and its calibration
    bundle (``root/bundle``), made with ``torchproj calibrate``."""
    data = tiny_config()
    data["states"] = sorted(data["states"], key=lambda s: s["name"])
    calibrate_bench(root, parse_scene(data, name="tiny"), out="bundle")
    return root


def _corrupt(path: Path, how: str, seed: int) -> None:
    if how == "delete":
        path.unlink()
    elif how == "truncate":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif how == "empty":
        path.write_bytes(b"")
    elif how == "garbage":
        path.write_bytes(np.random.default_rng(seed).bytes(200))


FILE_DAMAGE = ["delete", "truncate", "empty", "garbage"]


def _files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.is_file())


def test_bad_capture_options_are_refused_before_a_window_opens(tmp_path, capsys, monkeypatch):
    """``capture`` needs a screen and a camera, so the fuzzers below left it out, and ``--screen abc`` ended
    in a traceback, ``--settle -1`` in one mid-sequence. Every option against every bad value, with
    stand-ins for the window and the camera: refused before either opens, or captured."""
    import torchproj.pipeline.acquire as acquire

    opened = []

    class Display:
        def __init__(self, x=0, y=0, name="torchproj"):
            opened.append((x, y))

        def show(self, image):
            pass

        def close(self):
            pass

    class Camera(Display):
        def grab(self):
            return np.zeros((6, 8), np.uint8)

    monkeypatch.setattr(acquire, "OpenCVDisplay", Display)
    monkeypatch.setattr(acquire, "OpenCVCamera", lambda index=0: Camera())
    assert main(["sequence", "--projector", "64x32", "--out", str(tmp_path / "seq")]) == 0

    def attempt(case, folder):
        option, value = case
        before = len(opened)
        code, err, _ = run_cli(["capture", str(tmp_path / "seq"), "--out", str(folder / "out"), "--settle", "0",
                                f"{option}={value}"], capsys, folder / "out")
        assert code == 0 or len(opened) == before, f"{option}={value} refused after a window opened: {err}"

    _each([(o, v) for o in _options("capture") for v in BAD_ARGS], 0, tmp_path, attempt)


@pytest.mark.slow
def test_bad_options_of_every_file_command_are_refused_cleanly(capture_root, tmp_path, capsys):
    # `position` needs its box scene (a minute per valid run); `capture`'s options are the test above's.
    config = tmp_path / "scene.yaml"
    config.write_text(yaml.safe_dump(tiny_config()))
    base = {"simulate": ["simulate", str(config)], "sequence": ["sequence", "--projector", "128x96"],
            "calibrate": ["calibrate", str(capture_root / "captures"), "--projector", "128x96"],
            "solve": ["solve", str(capture_root / "bundle"), "--targets", "near=astronaut", "--max-iter", "20"],
            "decode": ["decode", str(capture_root / "captures" / "near" / "upper"), "--projector", "128x96"]}

    def attempt(case, folder):
        command, option, value = case
        run_cli([*base[command], "--out", str(folder / "out"), f"{option}={value}"], capsys, folder / "out")

    _each([(c, o, v) for c in base for o in _options(c) for v in BAD_ARGS], 4, tmp_path, attempt)


@pytest.mark.slow
def test_damaged_capture_files_are_refused_cleanly(capture_root, tmp_path, capsys):
    captures = capture_root / "captures"

    def attempt(case, folder):
        name, how = case
        shutil.copytree(captures, folder / "captures")
        _corrupt(folder / "captures" / name, how, len(str(name)))
        out = folder / "bundle"
        code, err, _ = run_cli(["calibrate", str(folder / "captures"), "--projector", "128x96", "--out", str(out)],
                               capsys, out)
        # A missing ramp is a warning (a linear response is assumed); anything else broken is an error.
        assert code == 2 or (how == "delete" and name.name.startswith("ramp")), f"exit {code}: {err}"

    _each([(f.relative_to(captures), how) for f in _files(captures) for how in FILE_DAMAGE], 2, tmp_path, attempt)


def test_damaged_bundles_are_refused_cleanly(capture_root, tmp_path, capsys):
    bundle = capture_root / "bundle"
    meta = json.loads((bundle / "bundle.json").read_text())

    def attempt(case, folder):
        kind, what, how = case
        shutil.copytree(bundle, folder / "bundle")
        if kind == "file":
            _corrupt(folder / "bundle" / what, how, len(str(what)))
        else:
            (folder / "bundle" / "bundle.json").write_text(json.dumps(_mutated(meta, what, how)))
        out = folder / "solved"
        run_cli(["solve", str(folder / "bundle"), "--targets", "near=astronaut", "far=camera", "--max-iter", "20",
                 "--out", str(out)], capsys, out)

    cases = [("file", f.relative_to(bundle), how) for f in _files(bundle) for how in FILE_DAMAGE]
    cases += [("field", path, value) for path in _leaves(meta) for value in [_DELETE, *BAD_VALUES]]
    _each(cases, 3, tmp_path, attempt)


def test_a_bundle_is_read_from_its_own_file_and_a_folder_that_is_no_path_is_named(capture_root):
    """load_bundle(".../bundle.json") said "not a calibration bundle (no bundle.json)"; a number or bytes
    ended in Path()'s TypeError."""
    from torchproj.calib import load_bundle
    from torchproj.core import InputError

    folder = capture_root / "bundle"
    assert list(load_bundle(folder / "bundle.json").states) == list(load_bundle(folder).states)
    for bad in (3, bytes(folder)):
        with pytest.raises(InputError, match=f"folder must be a bundle folder's path, got {type(bad).__name__}"):
            load_bundle(bad)


def test_output_that_is_a_file_or_under_one_is_refused_before_work(tmp_path, capsys):
    config = tmp_path / "scene.yaml"
    config.write_text(yaml.safe_dump(tiny_config()))
    afile = tmp_path / "afile"
    afile.write_text("keep me")
    for out in (afile, afile / "sub"):
        code, err, _ = run_cli(["run", str(config), "--out", str(out)], capsys)
        assert code == 2 and "is a file" in err and afile.read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "scene.yaml"]


def test_read_only_output_is_refused_before_work(tmp_path, capsys, monkeypatch):
    # Root may write anywhere, so the permission the check reads is what is faked.
    config = tmp_path / "scene.yaml"
    config.write_text(yaml.safe_dump(tiny_config()))
    (tmp_path / "ro").mkdir()
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if Path(p).name == "ro" else real_access(p, mode))
    code, err, _ = run_cli(["run", str(config), "--out", str(tmp_path / "ro" / "x")], capsys)
    assert code == 2 and "is not writable" in err and not any((tmp_path / "ro").iterdir())


def _config_with(tmp_path: Path, edit) -> str:
    data = tiny_config()
    edit(data)
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def _one_projector(d):
    d["projectors"] = d["projectors"][:1]


def _surface_from(tmp_path: Path, content: bytes, suffix: str):
    mesh = tmp_path / f"thing{suffix}"
    mesh.write_bytes(content)

    def edit(d):
        d["surfaces"]["near_plane"] = {"type": "mesh", "file": str(mesh), "pose": {"position": [0, 0, 0.8]}}
    return edit


# The inputs the issue found mishandled, each with the words its refusal must hold.
NAMED = {
    "eo with one projector": (lambda t: ["run", _config_with(t, _one_projector), "--solver", "eo"],
                              "eo walks epipolar chains between exactly two projectors, and this rig has 1"),
    "bits beyond the sequence": (lambda t: ["run", _config_with(t, lambda d: None), "--bits", "100"],
                                 "shows the whole Gray-code sequence"),
    "unknown device": (lambda t: ["run", _config_with(t, lambda d: None), "--device", "foo"],
                       "device 'foo' is not a torch device; this machine has"),
    "supersampling 200": (lambda t: ["run", _config_with(t, lambda d: d["camera"].update(supersampling=2000))],
                          "rays per state, above the limit"),
    "a 60000 x 40000 camera": (lambda t: ["run", _config_with(t, lambda d: d["camera"].update(resolution=[60000,
                                                                                                          40000]))],
                               "camera: 60000x40000 pixels"),
    "a 100000 x 100000 projector": (lambda t: ["run", _config_with(t, lambda d: d["projectors"][0].update(
        resolution=[100000, 100000]))], "projectors[0].resolution: 100000x100000"),
    "a NaN size limit": (lambda t: ["run", _config_with(t, lambda d: None), "--size-limit", "nan"],
                         "size_limit: must be a finite number above 0, got nan"),
    "an empty target image": (lambda t: ["run", _config_with(t, lambda d: d["targets"][0].update(image=""))],
                              "targets[0].image: is empty"),
    "bounds to 1e30": (lambda t: ["run", _config_with(t, lambda d: None), "--bounds", "0,1e30"],
                       "HI 1e+30 must lie in (0, 255]"),
    "a text file as mesh": (lambda t: ["run", _config_with(t, _surface_from(t, b"hello\n", ".obj"))],
                            "holds no triangles"),
    "a broken PLY as mesh": (lambda t: ["run", _config_with(t, _surface_from(t, b"\x00garbage", ".ply"))],
                             "is not a mesh file trimesh can read"),
    "a projector size without its width": (lambda t: ["calibrate", str(t), "--projector", "a=256"],
                                           "expected [NAME=]WIDTHxHEIGHT"),
}


@pytest.mark.parametrize("name", sorted(NAMED))
def test_named_bad_inputs_get_their_error(name, tmp_path, capsys):
    argv, words = NAMED[name]
    out = tmp_path / "out"
    code, err, _ = run_cli([*argv(tmp_path), "--out", str(out)], capsys, out)
    assert code == 2 and words in err, err


def test_bad_calibration_file_name_template_and_sequence_json(capture_root, tmp_path, capsys):
    folder = capture_root / "captures" / "near" / "upper"
    xml = tmp_path / "calibration.xml"
    for content in ("<x>", "<?xml version='1.0'?><opencv_storage><cam_int>3</cam_int></opencv_storage>"):
        xml.write_text(content)
        code, err, _ = run_cli(["decode", str(folder), "--projector", "128x96", "--calibration", str(xml),
                                "--out", str(tmp_path / "d")], capsys, tmp_path / "d")
        assert code == 2 and "calibration.xml: " in err and ("not a readable OpenCV" in err or "missing" in err)
    code, err, _ = run_cli(["decode", str(folder), "--projector", "128x96", "--names", "{", "--out",
                            str(tmp_path / "d")], capsys, tmp_path / "d")
    assert code == 2 and "not a file name template" in err
    root = tmp_path / "captures"
    shutil.copytree(capture_root / "captures", root)
    (root / "near" / "upper" / "sequence.json").write_text("{not json")
    code, err, _ = run_cli(["calibrate", str(root), "--projector", "128x96", "--out", str(tmp_path / "b")], capsys,
                           tmp_path / "b")
    assert code == 2 and "sequence.json: not valid JSON" in err


def test_hand_edited_bundle_response_is_refused(capture_root, tmp_path, capsys):
    bundle = tmp_path / "bundle"
    shutil.copytree(capture_root / "bundle", bundle)
    meta = json.loads((bundle / "bundle.json").read_text())
    meta["responses"][0]["b"] = [-3.0]
    (bundle / "bundle.json").write_text(json.dumps(meta))
    out = tmp_path / "solved"
    code, err, _ = run_cli(["solve", str(bundle), "--targets", "near=astronaut", "--out", str(out)], capsys, out)
    assert code == 2 and "responses[0]: y = a x^b + c needs a > 0 and b > 0" in err
    (bundle / "near" / "upper.npz").write_bytes(b"")
    code, err, _ = run_cli(["solve", str(bundle), "--targets", "near=astronaut", "--out", str(out)], capsys, out)
    assert code == 2 and "upper.npz" in err


def test_decoding_with_the_wrong_projector_size_warns(capture_root, tmp_path, capsys):
    # The capture came from a 128x96 projector; 100x70 has as many Gray-code bits (7 x 7), so the image
    # count fits and only the codes beyond 100x70 tell. The right size decodes without the warning.
    out = tmp_path / "d"
    code, err, _ = run_cli(["decode", str(capture_root / "captures" / "near" / "upper"), "--projector", "100x70",
                            "--out", str(out)], capsys, out)
    assert "read codes beyond a 100x70 projector (up to 1" in err  # (the ramp then fails to read, an error too)
    code, err, _ = run_cli(["decode", str(capture_root / "captures" / "near" / "upper"), "--projector", "128x96",
                            "--out", str(tmp_path / "e")], capsys, tmp_path / "e")
    assert code == 0 and "beyond" not in err


def test_bounds_in_linear_units_by_mistake_warn(tmp_path, capsys):
    from torchproj.solve import check_solve_options

    with pytest.warns(UserWarning, match="8-bit units: HI 1 lets each cell give 1/255 of its white"):
        assert check_solve_options("fista", (0, 1), 2) == (0.0, 1 / 255)
    assert check_solve_options("eo", (-100, 255), 2) == (-100 / 255, 1.0)
