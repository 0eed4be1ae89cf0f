"""The package as it ships: its package list, its scenes, its dependency metadata, its import side effects."""

import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

import torchproj
from torchproj.scene import BUILTIN_SCENES, config_dir

ROOT = Path(__file__).resolve().parents[1]


def test_every_room_is_listed_for_the_wheel():
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    on_disk = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "torchproj").rglob("__init__.py")}
    assert listed == on_disk | {"torchproj.configs"}


def test_built_in_scenes_are_the_files_shipped():
    assert sorted(BUILTIN_SCENES) == sorted(p.stem for p in config_dir().glob("*.yaml"))
    assert (config_dir() / "__init__.py").is_file()  # importable as torchproj.configs once installed


def test_torch_is_a_tested_range_and_pinned_only_in_the_constraints():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    spec = next(d for d in project["dependencies"] if d.startswith("torch"))
    assert ">=" in spec and "<" in spec and "==" not in spec
    pins = [line for line in (ROOT / "constraints.txt").read_text().splitlines() if line.startswith("torch==")]
    assert len(pins) == 1


@pytest.mark.slow
def test_figures_leave_the_users_matplotlib_backend_alone(tmp_path):
    code = ("import matplotlib, numpy, torch; import torchproj.figures as f; "
            "assert matplotlib.get_backend() == 'svg', matplotlib.get_backend(); "
            "f.decode_summary(r'%s', torch.rand(20, 30, 2) * 10, torch.rand(20, 30), None, title='t'); "
            "assert matplotlib.get_backend() == 'svg'" % (tmp_path / "decoded.png"))
    env = {**os.environ, "MPLBACKEND": "svg"}
    subprocess.run([sys.executable, "-c", code], check=True, env=env, cwd=tmp_path)
    assert (tmp_path / "decoded.png").read_bytes()[:4] == b"\x89PNG"


def test_the_version_is_the_packages():
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert torchproj.__version__ == version
