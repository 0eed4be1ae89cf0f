"""The built-in scenes: the YAML files beside this one (installed as ``torchproj.configs``).

This folder is where people read and edit them; ``pyproject.toml`` ships it inside the package,
so a plain or wheel install finds the scenes with ``importlib.resources`` wherever it runs.
"""
