"""Property-based tests of the loaders (hypothesis): whatever a file holds, a loader returns what it
describes or raises torchproj's own error naming the file or field, never another exception.

The seeded fuzzer (test_bad_inputs.py) mutates one field of a valid input to values from a list;
here hypothesis draws the values (any YAML/JSON tree: huge and tiny numbers, NaN, unicode, nesting)
and the place, and shrinks a failure to its smallest case. Derandomized, so CI runs the same
examples each time; ``TORCHPROJ_FUZZ=all`` draws many more.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchproj.calib import load_bundle
from torchproj.core import CaptureError, TorchprojError, read_image
from torchproj.scene import Scene, load_scene, parse_scene

from .helpers import small_config

EXAMPLES = 2000 if os.environ.get("TORCHPROJ_FUZZ") == "all" else 150
PROPERTIES = settings(max_examples=EXAMPLES, derandomize=True, deadline=None,
                      suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

# Any tree a YAML or JSON file can hold.
SCALARS = (st.none() | st.booleans() | st.integers() | st.integers(min_value=-10 ** 40, max_value=10 ** 40)
           | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=20))
TREES = st.recursive(SCALARS, lambda inner: st.lists(inner, max_size=4)
                     | st.dictionaries(st.text(max_size=8), inner, max_size=4), max_leaves=12)


def _paths(tree, path=()):
    """Every place in a tree (its root included) a value can be put."""
    yield path
    if isinstance(tree, dict):
        for k, v in tree.items():
            yield from _paths(v, path + (k,))
    elif isinstance(tree, list):
        for i, v in enumerate(tree):
            yield from _paths(v, path + (i,))


def _put(tree, path, value):
    if not path:
        return value
    tree = json.loads(json.dumps(tree))  # a copy
    node = tree
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return tree


CONFIG = small_config(camera=(160, 120), projector=(128, 96))
CONFIG_PATHS = list(_paths(CONFIG))


@PROPERTIES
@given(place=st.sampled_from(CONFIG_PATHS), value=TREES)
def test_a_scene_config_with_any_value_anywhere_parses_or_names_the_field(place, value):
    try:
        scene = parse_scene(_put(CONFIG, place, value))
    except TorchprojError as exc:
        assert str(exc), "an error without a message"
    else:
        assert isinstance(scene, Scene)


@PROPERTIES
@given(text=st.text(max_size=200) | st.binary(max_size=200).map(lambda b: b.decode("latin-1")))
def test_a_config_file_of_any_text_loads_or_is_refused_naming_it(text):
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "scene.yaml"
        path.write_bytes(text.encode("latin-1", errors="replace") if text.isascii() else text.encode("utf-8"))
        try:
            load_scene(path)
        except TorchprojError as exc:
            assert str(exc)


@PROPERTIES
@given(data=st.binary(max_size=300), suffix=st.sampled_from([".png", ".jpg", ".tif", ".bmp"]))
def test_an_image_file_of_any_bytes_reads_or_is_refused_naming_it(data, suffix):
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / f"capture{suffix}"
        path.write_bytes(data)
        with pytest.raises(CaptureError, match="capture"):
            read_image(path)


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    """A tiny rig's calibration bundle, made with the command a person uses."""
    from .test_bad_inputs import capture_root_for

    return capture_root_for(tmp_path_factory.mktemp("bundle")) / "bundle"


@PROPERTIES
@given(data=st.data())
def test_a_bundle_json_with_any_value_anywhere_loads_or_is_refused_naming_it(bundle, data):
    meta = json.loads((bundle / "bundle.json").read_text())
    place = data.draw(st.sampled_from(list(_paths(meta))), label="place")
    value = data.draw(TREES, label="value")
    with tempfile.TemporaryDirectory() as folder:
        copy = Path(folder) / "bundle"
        shutil.copytree(bundle, copy)
        (copy / "bundle.json").write_text(json.dumps(_put(meta, place, value)))
        try:
            load_bundle(copy)
        except CaptureError as exc:
            assert "bundle" in str(exc), exc


def test_yaml_round_trip_of_the_config_used_here_is_a_valid_scene():
    """The strategies above mutate a valid config: check that it is one, so that every refusal is the
    mutation's."""
    assert isinstance(parse_scene(yaml.safe_load(yaml.safe_dump(CONFIG))), Scene)
