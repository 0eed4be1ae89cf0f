"""Pages the docs build writes before Sphinx reads: the README, the API, the gallery and the results.

Everything lands in ``docs/generated/`` (not committed), rewritten only where its text changed so
Sphinx's incremental builds stay incremental:

- ``start.md``: the README, the site's first page, its links resolved from the repository root.
- ``api.rst``: the face of ``import torchproj`` (``torchproj._OFFERED``), one section per
  sub-package, by autodoc from the docstrings.
- ``gallery/``: each script of ``gallery_scripts`` run as a user runs it (its own process, at the
  small size given), a page each with its docstring, the command, the figures it wrote and its code.
  As sphinx-gallery does, a script is run again only when its text or arguments changed
  (sphinx-gallery is not on the package index this project installs from offline).
- ``results/``: each benchmark's ``benchmarks/results/NAME/results.md`` as the benchmark wrote it,
  with the charts beside it: the results pages are the benchmarks' own output, not copies by hand.
"""

from __future__ import annotations

import hashlib
import importlib
import inspect
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

from sphinx.errors import ExtensionError
from sphinx.util.logging import getLogger

LOGGER = getLogger(__name__)


def write_if_changed(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not path.exists() or path.read_text() != text:
        path.write_text(text)


def heading(text: str, mark: str = "=") -> str:
    return f"{text}\n{mark * len(text)}\n"


def readme_page(root: Path, out: Path) -> None:
    write_if_changed(out / "start.md", "<!-- origin: ../../README.md -->\n" + (root / "README.md").read_text())


def api_page(out: Path) -> None:
    import torchproj

    lines = [heading("API reference"), "",
             "The names ``import torchproj`` offers, by the sub-package that holds them (each is also "
             "``torchproj.NAME``). Shapes and units are in each docstring; the conventions (pixel "
             "centres, ``(x, y)`` order) are stated once in ``torchproj.core.conventions``.", ""]
    for package, names in sorted(torchproj._OFFERED.items()):
        if not names:
            continue
        module = importlib.import_module(f"torchproj.{package}")
        lines += [heading(f"torchproj.{package}", "-"), "", f".. automodule:: torchproj.{package}",
                  "   :no-members:", ""]
        for name in sorted(names.split()):
            value = getattr(module, name)
            if inspect.isclass(value):
                lines += [f".. autoclass:: torchproj.{package}.{name}", "   :members:", ""]
            elif callable(value):
                lines += [f".. autofunction:: torchproj.{package}.{name}", ""]
            else:  # a constant: documented where it is assigned, by its ``#:`` comment
                lines += [f".. autodata:: {_assigned_in(module, name)}.{name}", ""]
    write_if_changed(out / "api.rst", "\n".join(lines))


def _assigned_in(package, name: str) -> str:
    """The module under ``package`` whose source assigns ``name`` at its top level."""
    root = Path(package.__file__).parent.parent
    for source in sorted(root.rglob("*.py")):
        if re.search(rf"^{name}\s*[:=]", source.read_text(), re.M):
            return ".".join(source.relative_to(root.parent).with_suffix("").parts).removesuffix(".__init__")
    raise ExtensionError(f"api: no module of torchproj assigns {name}")


def gallery_pages(root: Path, out: Path, scripts: list[dict]) -> None:
    pages = []
    for entry in scripts:
        script = entry["script"]
        source = root / script
        name = source.stem
        folder = out / "gallery" / name
        places = {"out": folder.relative_to(root).as_posix(), "input": f"{folder.relative_to(root).as_posix()}-input"}
        argv = [arg.format(**places) for arg in entry.get("args", [])]
        before = [arg.format(**places) for arg in entry.get("before", [])]
        stamp = out / "gallery" / f"{name}.stamp.json"  # outside the folder, which the script owns
        key = hashlib.sha256(source.read_bytes() + json.dumps([before, argv]).encode()).hexdigest()
        ran = _run_once(root, stamp, key, ([before] if before else []) + [[script, *argv]])
        figures = sorted(folder.rglob("*.png"))
        if not figures:
            raise ExtensionError(f"gallery: {script} wrote no figure under {folder}")
        doc = inspect.cleandoc(_docstring(source))
        title, _, body = doc.partition("\n\n")  # the first paragraph is the page's title
        title = " ".join(title.split())
        # A docstring's indented paragraphs are its usage lines: literal blocks, not quotes.
        body = re.sub(r"(\A\n*|\n\n)((?: {4}.*(?:\n|\Z))+)", r"\1::\n\n\2", "\n\n" + body)
        command = " ".join(["python", script, *argv])
        if before:
            command = " ".join(["python", *before]).replace("python -m torchproj.cli", "torchproj") + " && " + command
        lines = [heading(title.rstrip(".")), "", body.strip(), "", heading("Run here", "-"), "",
                 f"``{command}`` took {ran['seconds']} s when the docs were built.", ""]
        for figure in figures:
            lines += [f".. figure:: /{figure.relative_to(out.parent).as_posix()}", "   :width: 100%", "",
                      f"   ``{figure.relative_to(folder).as_posix()}``", ""]
        files = sorted(f for f in folder.iterdir() if f.suffix in (".gltf", ".json", ".ply", ".md"))
        if files:
            lines += ["Beside the figures it wrote "
                      + ", ".join(f":download:`{f.name} </{f.relative_to(out.parent).as_posix()}>`" for f in files)
                      + " (a ``.gltf`` opens in any glTF viewer, browser ones included).", ""]
        lines += [heading("The script", "-"), "", f".. literalinclude:: /../{script}", "   :language: python", ""]
        write_if_changed(out / "gallery" / f"{name}.rst", "\n".join(lines))
        pages.append(name)
    index = [heading("Gallery"), "",
             "Scripts as a user writes them, run when these pages were built, at a small size so the build "
             "stays short; each page gives the command, what it drew and the code.", "",
             ".. toctree::", "   :maxdepth: 1", "", *[f"   {page}" for page in pages], ""]
    write_if_changed(out / "gallery" / "index.rst", "\n".join(index))


def _run_once(root: Path, stamp: Path, key: str, commands: list[list[str]]) -> dict:
    """Run ``commands`` (``python`` arguments, in order, from ``root``) unless ``stamp`` records ``key``;
    the stamp: ``{"key", "seconds"}``."""
    ran = json.loads(stamp.read_text()) if stamp.exists() else {}
    if ran.get("key") == key:
        return ran
    stamp.parent.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    for command in commands:
        LOGGER.info("gallery: running python %s", " ".join(command))
        done = subprocess.run([sys.executable, *command], cwd=root, capture_output=True, text=True,
                              env={**os.environ, "MPLBACKEND": "Agg"})
        if done.returncode != 0:
            raise ExtensionError(f"gallery: python {' '.join(command)} failed:\n{done.stderr[-3000:]}")
    ran = {"key": key, "seconds": round(time.perf_counter() - start, 1)}
    stamp.write_text(json.dumps(ran))
    return ran


def _docstring(source: Path) -> str:
    import ast

    doc = ast.get_docstring(ast.parse(source.read_text()), clean=False)
    if not doc:
        raise ExtensionError(f"gallery: {source} has no docstring to open its page with")
    return doc


def results_pages(root: Path, out: Path) -> None:
    results = root / "benchmarks" / "results"
    names = []
    for table in sorted(results.glob("*/results.md")):
        folder = table.parent
        text = table.read_text().rstrip("\n") + "\n"
        if not text.startswith("# "):
            text = f"# {folder.name}\n\n{text}"  # a page's title; a few benchmarks write none
        charts = sorted(folder.glob("*.png"))
        if charts:
            text += "\n## Charts\n\n" + "\n\n".join(f"![{c.name}]({c.name})" for c in charts) + "\n"
        origin = os.path.relpath(table, out / "results")
        write_if_changed(out / "results" / f"{folder.name}.md", f"<!-- origin: {origin} -->\n{text}")
        names.append(folder.name)
    index = [heading("Results"), "",
             "What each benchmark under ``benchmarks/`` wrote when it last ran (``python benchmarks/NAME.py``; "
             "each page names its command and machine). The figures in the user guide come from these.", "",
             ".. toctree::", "   :maxdepth: 1", "", *[f"   {name}" for name in names], ""]
    write_if_changed(out / "results" / "index.rst", "\n".join(index))


def generate(app) -> None:
    srcdir = Path(app.srcdir)
    root = (srcdir / app.config.repository_root).resolve()
    out = srcdir / "generated"
    readme_page(root, out)
    api_page(out)
    results_pages(root, out)
    gallery_pages(root, out, app.config.gallery_scripts)


def setup(app):
    app.add_config_value("gallery_scripts", [], "env")
    app.connect("builder-inited", generate)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
