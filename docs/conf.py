"""Sphinx configuration of torchproj's documentation site.

Build it with one command from the repository root (after ``pip install -e ".[docs]"``):

    python -m sphinx -W --keep-going docs docs/_build/html

The pages are the Markdown under ``docs/`` (read through ``_ext/markdown_source.py``), plus what
``_ext/generated_pages.py`` writes before each build: the README as the first page, the API reference
from the docstrings, the gallery (its scripts run at a small size) and the benchmarks' results.
"""

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "_ext"))

import torchproj  # noqa: E402

project = "torchproj"
release = version = torchproj.__version__
extensions = ["sphinx.ext.autodoc", "sphinx.ext.napoleon", "markdown_source", "generated_pages"]
root_doc = "index"
exclude_patterns = ["_build", "_ext", "generated/gallery/*/**"]
repository_root = ".."
html_theme = "alabaster"
html_title = f"torchproj {release}"
html_theme_options = {"page_width": "1200px", "sidebar_width": "260px"}
numfig = True  # every figure numbered, its caption beside the number
autodoc_member_order = "bysource"
autodoc_typehints = "description"
napoleon_google_docstring = True
napoleon_numpy_docstring = False

# The gallery: each script as a user runs it, at a size that keeps the build short. ``before``: a
# command whose output the script reads; {out} is the script's folder, {input} the command's.
gallery_scripts = [
    {"script": "examples/train_patterns.py", "args": ["--scale", "0.25", "--steps", "12", "--out", "{out}"]},
    {"script": "examples/video_frames.py", "args": ["--frames", "3", "--steps", "10", "--out", "{out}"]},
    {"script": "viz/rig.py", "args": ["configs/box_cylinders.yaml", "--out", "{out}/rig.png"]},
    {"script": "viz/correspondences.py", "before": ["-m", "torchproj.cli", "simulate", "--out", "{input}"],
     "args": ["{input}", "--out", "{out}/correspondences.png"]},
]
