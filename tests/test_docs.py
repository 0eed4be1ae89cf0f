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


def _build_site(tmp_path, pages: dict[str, str], builder: str = "xml") -> tuple[int, str, Path]:
    """A Sphinx site of ``pages`` (name -> Markdown) read through docs/_ext/markdown_source.py."""
    pytest.importorskip("sphinx", reason="the docs extra is not installed (pip install -e '.[docs]')")
    from sphinx.cmd.build import build_main

    src, out = tmp_path / "src", tmp_path / "out"
    src.mkdir(exist_ok=True)
    (src / "conf.py").write_text(f"import sys\nsys.path.insert(0, {str(ROOT / 'docs' / '_ext')!r})\n"
                                 f"extensions = ['markdown_source']\nsmartquotes = False\nrepository_root = {str(tmp_path)!r}\n")
    toctree = "\n".join(f"   {name}" for name in pages)
    (src / "index.rst").write_text(f"Site\n====\n\n.. toctree::\n\n{toctree}\n")
    for name, text in pages.items():
        (src / f"{name}.md").write_text(text)
    warnings = tmp_path / "warnings.txt"
    code = build_main(["-W", "-q", "-b", builder, "-w", str(warnings), str(src), str(out)])
    return code, warnings.read_text(), out


PAGE = """# Top

A paragraph with **bold**, *emphasis* and `code`, a link to [the other page](other.md), one to
[a scene](../scene.yaml), one to [a folder](results/) and one [down the page](#sub).

## Sub

1. first
2. second

- a
- b

```python
x = 1
```

| name | value |
|---|---|
| a | `1` |
| b | 2 |

### Deeper

Text.

![a chart of x](chart.png)
"""


def test_markdown_pages_become_sections_tables_lists_links_and_code(tmp_path):
    import xml.etree.ElementTree as ET

    (tmp_path / "scene.yaml").write_text("name: x\n")
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "chart.png").write_bytes(_png())
    code, warnings, out = _build_site(tmp_path, {"page": PAGE, "other": "# Other\n\nHello.\n"})
    assert code == 0, warnings
    doc = ET.parse(out / "page.xml").getroot()
    top = doc.find("section")
    assert top.find("title").text == "Top"
    sub = top.find("section")
    assert sub.find("title").text == "Sub" and sub.find("section/title").text == "Deeper"
    paragraph = top.find("paragraph")
    assert paragraph.find("strong").text == "bold" and paragraph.find("emphasis").text == "emphasis"
    assert paragraph.find("literal").text == "code"
    assert [r.get("refuri") for r in paragraph.findall("reference")] == ["other.html", "#sub"]
    assert paragraph.find("download_reference").get("reftarget") == "../scene.yaml"
    assert "results" in "".join(paragraph.itertext())  # a folder that is no page: its path, not a dead link
    assert [len(sub.findall(f"{kind}/list_item")) for kind in ("enumerated_list", "bullet_list")] == [2, 2]
    block = sub.find("literal_block")
    assert block.get("language") == "python" and block.text == "x = 1"
    rows = sub.findall("table/tgroup/*/row")
    assert [["".join(e.itertext()).strip() for e in row.findall("entry")] for row in rows] == [
        ["name", "value"], ["a", "1"], ["b", "2"]]
    figure = sub.find("section/figure")  # an image alone in its paragraph: a numbered figure, its alt the caption
    assert figure.find("image").get("uri") == "chart.png" and figure.find("caption").text == "a chart of x"


def _png() -> bytes:
    import io

    from PIL import Image

    buffer = io.BytesIO()
    Image.new("RGB", (4, 4)).save(buffer, format="PNG")
    return buffer.getvalue()


def test_the_guide_pages_keep_every_word_markdown_it_renders(tmp_path):
    """Nothing the pages say vanishes on the site: their words, built, equal markdown-it's HTML's."""
    import xml.etree.ElementTree as ET
    from collections import Counter
    from html.parser import HTMLParser

    from markdown_it import MarkdownIt

    class Text(HTMLParser):
        def __init__(self):
            super().__init__()
            self.parts = []

        def handle_data(self, data):
            self.parts.append(data)

    pages = {p.stem: p.read_text() for p in PAGES}
    code, warnings, out = _build_site(tmp_path, pages)
    assert code == 0, warnings
    for name, text in pages.items():
        html = Text()
        html.feed(MarkdownIt("commonmark").enable("table").render(text))
        built = " ".join(ET.parse(out / f"{name}.xml").getroot().itertext())
        assert Counter(" ".join(html.parts).split()) == Counter(built.split()), name


def test_markdown_the_site_cannot_carry_stops_the_build_naming_the_line(tmp_path):
    code, warnings, _ = _build_site(tmp_path, {"page": "# Page\n\nFine.\n\n<div>raw html</div>\n"})
    assert code != 0 and "line 5" in warnings and "html_block" in warnings, warnings
