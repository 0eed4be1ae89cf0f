"""Output folders that appear whole or not at all."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path

from .errors import InputError

__all__ = ["atomic_output", "check_output_folder", "write_json"]


def check_output_folder(out_dir: str | os.PathLike) -> Path:
    """Raise :class:`InputError` unless ``out_dir`` is, or can become, a folder this process may write.

    Nothing is created: the nearest existing folder on the path is what is checked, so a refused
    output leaves no empty folders behind. Commands call it before their work, not after.
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"output folder {out_dir}: is a file; choose a folder (or remove the file)")
    existing = out_dir
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise InputError(f"output folder {out_dir}: {existing} is a file, so no folder can be made under it")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise InputError(f"output folder {out_dir}: {existing} is not writable; choose another folder")
    return out_dir


@contextlib.contextmanager
def atomic_output(out_dir: str | os.PathLike):
    """Yield a staging folder; on success its files move into ``out_dir``, on failure it vanishes.

    A run that fails half-way therefore leaves no half-written report: ``out_dir`` holds either
    the previous run's files or this run's complete set.
    """
    out_dir = check_output_folder(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-", dir=out_dir.parent))
    try:
        yield stage
        out_dir.mkdir(parents=True, exist_ok=True)
        for item in stage.iterdir():
            target = out_dir / item.name
            if target.is_dir() and not target.is_symlink():
                shutil.rmtree(target)
            elif target.exists():
                target.unlink()
            os.replace(item, target)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def write_json(path: str | os.PathLike, data) -> None:
    """Write JSON with stable key order and NaN spelled as null."""

    def clean(v):
        if isinstance(v, float) and v != v:
            return None
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        return v

    Path(path).write_text(json.dumps(clean(data), indent=2) + "\n")
