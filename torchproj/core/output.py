"""Output folders that appear whole or not at all."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path

__all__ = ["atomic_output", "write_json"]


@contextlib.contextmanager
def atomic_output(out_dir: str | os.PathLike):
    """Yield a staging folder; on success its files move into ``out_dir``, on failure it vanishes.

    A run that fails half-way therefore leaves no half-written report: ``out_dir`` holds either
    the previous run's files or this run's complete set.
    """
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-", dir=out_dir.parent))
    try:
        yield stage
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    out_dir.mkdir(parents=True, exist_ok=True)
    for item in stage.iterdir():
        target = out_dir / item.name
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        elif target.exists():
            target.unlink()
        os.replace(item, target)
    stage.rmdir()


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
