"""The README a newcomer reads and the pages it links: short, linked, and its examples run as written."""

import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = sorted((ROOT / "docs").glob("*.md"))


def test_the_readme_is_read_in_five_minutes_and_its_links_resolve():
    text = README.read_text()
    assert len(text.splitlines()) <= 250
    for page in [README, *PAGES]:
        for target in re.findall(r"\]\(([^)#\s]+)\)", page.read_text()):
            if not target.startswith(("http://", "https://")):
                assert (page.parent / target).exists(), f"{page.name} links {target}, which is not there"
    linked = set(re.findall(r"\(docs/([\w-]+\.md)\)", text))
    assert linked == {p.name for p in PAGES}, "every documentation page is linked from the README, and only those"


def test_the_readmes_scene_is_valid_and_bright_enough():
    from torchproj.pipeline import white_levels
    from torchproj.scene import parse_scene

    block = re.search(r"```yaml\n(.*?)```", README.read_text(), re.S).group(1)
    scene = parse_scene(yaml.safe_load(block))
    assert all(level > 40 / 255 for level in white_levels(scene).values())


@pytest.mark.slow
def test_the_readmes_python_example_runs_as_written(tmp_path):
    code = re.search(r"```python\n(.*?)```", README.read_text(), re.S).group(1)
    code += "\nassert all(t.ssim > 0.6 and t.psnr_db > 15 for t in scores.targets), scores.targets\n"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
