"""Output folders that appear whole or not at all, and never take a person's files with them.

The contract every command that writes ``--out`` keeps (docs/commands.md, "Commands"):

- ``--out`` is replaced only where torchproj wrote it: a missing or empty folder, or one whose every
  file and folder, at any depth, is listed in the manifest (:data:`MANIFEST`) an earlier torchproj
  command left there. A folder holding anything else (a person's captures, notes, a file they added
  inside ``captures/``, an older tool's output) is refused before any work begins, naming what is
  there; nothing in it is touched. So is the folder the command runs in (``--out .``) or one above it,
  and (:func:`check_inputs_outside`) one that is, or holds, what the command reads.
- The new result is written beside it and swapped in whole by two renames (the old folder aside,
  the new one in), then the old one is removed: an interruption at any moment (Ctrl-C, SIGTERM, a
  full disk, a file that cannot be removed) leaves the complete old result or the complete new one
  at ``--out``, never a mixture.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import os
import shutil
import signal
import tempfile
import warnings
from pathlib import Path

from .errors import InputError, TorchprojError

__all__ = ["MANIFEST", "atomic_output", "check_inputs_outside", "check_output_folder", "write_json"]

MANIFEST = ".torchproj-output.json"  # what torchproj wrote into an output folder, so that it may replace it


def check_output_folder(out_dir: str | os.PathLike, replace: bool = True) -> Path:
    """Raise :class:`InputError` unless ``out_dir`` is, or can become, a folder this process may write.

    Nothing is created: the nearest existing folder on the path is what is checked, so a refused
    output leaves no empty folders behind. Commands call it before their work, not after.
    ``replace``: the command replaces the folder whole (:func:`atomic_output`), so a folder holding
    anything torchproj did not write is refused (module docstring); False for a working folder a
    command adds to (``torchproj refine``).
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"output folder {out_dir}: is a file; choose a folder (or remove the file)")
    here, full = Path.cwd().resolve(), out_dir.resolve()
    if replace and (full == here or full in here.parents):
        # ``--out .``: the new result was staged beside ``.``, which is inside it, and then refused as
        # something torchproj did not write; and a folder being replaced whole is no place to stand.
        where = "the folder this command runs in" + ("" if full == here else ", or one above it")
        raise InputError(f"output folder {out_dir}: is {where}; torchproj replaces --out whole: give a folder of its "
                         "own (e.g. --out out)")
    if replace and out_dir.is_dir():
        theirs = _not_written(out_dir)
        if theirs:
            shown = ", ".join(theirs[:5]) + (" and more" if len(theirs) > 5 else "")
            raise InputError(f"output folder {out_dir}: holds {shown}, which torchproj did not write there; torchproj "
                             "replaces only an output folder it wrote itself: give a new or empty --out folder (nothing "
                             "was touched)")
    existing = out_dir
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise InputError(f"output folder {out_dir}: {existing} is a file, so no folder can be made under it")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise InputError(f"output folder {out_dir}: {existing} is not writable; choose another folder")
    return out_dir


def check_inputs_outside(out_dir: str | os.PathLike, inputs: dict[str, str | os.PathLike]) -> None:
    """Raise :class:`InputError` where ``out_dir`` is, or holds, a file or folder the command reads.

    ``inputs``: what names each input (an option, ``bundle``) -> its path. A folder torchproj wrote may
    be replaced (:func:`check_output_folder`), and so ``torchproj solve calib --out calib`` replaced the
    calibration it had just read with its patterns: a bench's 184 captures' work gone without a word.
    """
    out = Path(out_dir).resolve()
    for what, path in inputs.items():
        full = Path(path).resolve()
        if full == out or out in full.parents:
            where = f"is this command's {what}" if full == out else f"holds {path}, this command's {what}"
            raise InputError(f"output folder {out_dir}: {where}; torchproj replaces --out whole, so give an --out "
                             "apart from what it reads (nothing was touched)")


@contextlib.contextmanager
def atomic_output(out_dir: str | os.PathLike):
    """Yield a staging folder; on success its files move into ``out_dir``, on failure it vanishes.

    A run that fails half-way therefore leaves no half-written report: ``out_dir`` holds either
    the previous run's files or this run's complete set.
    """
    out_dir = check_output_folder(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    try:
        stage = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-", dir=out_dir.parent))
    except OSError as exc:
        raise OSError(exc.errno, f"{exc.strerror or exc}: cannot make a folder beside {out_dir} for the new result; "
                                 f"{out_dir} is as it was") from None
    old = None
    try:
        yield stage
        write_json(stage / MANIFEST, {"written by": "torchproj", "written": sorted(_entries(stage))})
        check_output_folder(out_dir)  # again: the person may have put something there while the work ran
        with _signals_held():  # the two renames: no interruption between them
            if out_dir.exists():
                old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.old-", dir=out_dir.parent))
                os.replace(out_dir, old / out_dir.name)
            os.replace(stage, out_dir)
        os.chmod(out_dir, 0o777 & ~_umask())  # a staging folder is private; an output folder is as mkdir makes it
    except OSError as exc:
        inside = _inside(exc.filename, stage)
        if exc.filename is not None and inside is None:
            raise  # about another file (an input), which names itself
        # Named as the person will look for it: the staging folder is gone by the time they read this. A
        # write the disk refuses part-way through a file names no file.
        what = "" if inside is None else f" while writing {inside} of the new result"
        message = f"{exc.strerror or exc}{what}; {out_dir} is as it was and nothing of the new result was kept"
        raise (OSError(message) if exc.errno is None else OSError(exc.errno, message)) from None
    except TorchprojError as exc:
        # A file of the staging folder the work read back (``simulate --write-captures``' captures) is
        # named as part of the new result: the folder is gone by the time the message is read.
        text = str(exc)
        if str(stage) in text:
            exc.args = (text.replace(f"{stage}{os.sep}", "the new result's ").replace(str(stage), "the new result")
                        + f" ({out_dir} is as it was)",)
        raise
    finally:
        if old is not None and not out_dir.exists() and (old / out_dir.name).exists():
            os.replace(old / out_dir.name, out_dir)  # the new one did not go in: the old one goes back, whole
        shutil.rmtree(stage, ignore_errors=True)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
            if old.exists():
                warnings.warn(f"{old}: the previous result (replaced whole) could not all be removed; remove it by hand",
                              stacklevel=3)


def _inside(filename, folder: Path) -> str | None:
    """``filename`` relative to ``folder`` where it lies inside it, else None."""
    try:
        return Path(os.fsdecode(filename)).resolve().relative_to(folder.resolve()).as_posix()
    except (TypeError, ValueError):
        return None


@contextlib.contextmanager
def _signals_held():
    """Hold Ctrl-C and SIGTERM (where the platform can) until the block is done."""
    held = {signal.SIGINT, signal.SIGTERM}
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    before = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _entries(folder: Path, descend=None):
    """Every file and folder under ``folder`` as a relative POSIX path (links not followed), at any
    depth; ``descend(entry)`` False keeps the walk out of that folder (it is still named)."""
    for root, dirs, files in os.walk(folder):
        base = Path(root).relative_to(folder)
        for name in sorted(dirs + files):
            yield (base / name).as_posix()
        if descend is not None:
            dirs[:] = [name for name in dirs if descend((base / name).as_posix())]


def _not_written(out_dir: Path, limit: int = 6) -> list[str]:
    """Up to ``limit`` entries of ``out_dir`` that its manifest does not list (all of them without one).

    An entry counts at any depth: a person's file put inside a folder torchproj wrote is theirs; a
    folder of theirs is named, not walked.
    """
    try:
        listed = json.loads((out_dir / MANIFEST).read_text()).get("written", [])
        written = {name for name in listed if isinstance(name, str)}
    except (OSError, ValueError, AttributeError, TypeError):  # no manifest, or one that is not ours: nothing listed
        written = set()
    theirs = (entry for entry in _entries(out_dir, descend=written.__contains__)
              if entry != MANIFEST and entry not in written)
    return sorted(itertools.islice(theirs, limit))


def write_json(path: str | os.PathLike, data) -> None:
    """Write JSON with stable key order and NaN and infinities spelled as null (JSON has neither: a
    target shown perfectly has an infinite PSNR, which Python's json would write as ``Infinity``)."""

    def clean(v):
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        return v

    from .checks import check_path  # here: checks imports torch, and the command imports this module before it

    check_path(path, "path", "the JSON file")
    try:
        text = json.dumps(clean(data), indent=2) + "\n"
    except (TypeError, ValueError) as exc:  # a tensor, a set, a key that is not a string or number
        raise InputError(f"{path}: data must be JSON (dicts, lists, strings, numbers, None): {exc}") from None
    Path(path).write_text(text)
