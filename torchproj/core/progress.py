"""Progress bars on long work: one helper, so that every loop shows and hides them alike."""

from __future__ import annotations

import sys

__all__ = ["progress_bar"]


def progress_bar(iterable=None, desc: str = "", enabled: bool | None = None, total: int | None = None):
    """A tqdm bar on stderr that clears itself when done.

    Args:
        iterable: what to iterate (or None for a bar updated by hand, with ``total``).
        enabled: True shows it, False hides it, None shows it on a terminal once the work has run
            for a second (short steps stay quiet, and logs of pipes stay clean).
    """
    from tqdm import tqdm

    return tqdm(iterable, desc=desc, total=total, leave=False, file=sys.stderr, delay=1.0,
                disable=True if enabled is False else (None if enabled is None else False))
