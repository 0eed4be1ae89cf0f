"""Reading one YAML mapping into typed values, with errors that name the field and the fix."""

from __future__ import annotations

import difflib
from typing import Any, Sequence

import numpy as np

from ..core.errors import ConfigError

_MISSING = object()


def _kind(value: Any) -> str:
    return "a list" if isinstance(value, list) else "a mapping" if isinstance(value, dict) else repr(value)


class Fields:
    """Typed access to a mapping at ``path``; :meth:`done` rejects keys nobody asked for."""

    def __init__(self, data: Any, path: str):
        if not isinstance(data, dict):
            raise ConfigError(path, f"must be a mapping of keys to values, got {_kind(data)}")
        self.data = data
        self.path = path
        self.used: set[str] = set()

    def where(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def raw(self, key: str, default: Any = _MISSING) -> Any:
        self.used.add(key)
        if key in self.data and self.data[key] is not None:
            return self.data[key]
        if default is _MISSING:
            # A misspelt required key is missing too: name the key that is there instead.
            close = difflib.get_close_matches(key, [str(k) for k in self.data if k != key], n=1)
            raise ConfigError(self.where(key), "is required",
                              f"found '{close[0]}': did you mean '{key}'?" if close else "add it")
        return default

    def has(self, key: str) -> bool:
        return key in self.data and self.data[key] is not None

    def number(self, key: str, default: Any = _MISSING, *, lo: float | None = None,
               hi: float | None = None, strict_lo: bool = False) -> float:
        value = self.raw(key, default)
        return _number(value, self.where(key), lo, hi, strict_lo)

    def integer(self, key: str, default: Any = _MISSING, *, choices: Sequence[int] | None = None,
                lo: int | None = None, hi: int | None = None) -> int:
        value = self.raw(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(self.where(key), f"must be a whole number, got {value!r}")
        if choices is not None and value not in choices:
            raise ConfigError(self.where(key), f"must be one of {list(choices)}, got {value}")
        if lo is not None and value < lo:
            raise ConfigError(self.where(key), f"must be at least {lo}, got {value}")
        if hi is not None and value > hi:
            shown = str(value) if value < 10**30 else f"a number of {len(str(value))} digits"
            raise ConfigError(self.where(key), f"must be at most {hi}, got {shown}")
        return value

    def text(self, key: str, default: Any = _MISSING, *, choices: Sequence[str] | None = None) -> str:
        value = self.raw(key, default)
        if not isinstance(value, str):
            raise ConfigError(self.where(key), f"must be text, got {value!r}")
        if choices is not None and value not in choices:
            raise ConfigError(self.where(key), f"must be one of {list(choices)}, got {value!r}")
        return value

    def name(self, key: str, default: Any = _MISSING) -> str:
        """Text that names a file or folder of the outputs (``patterns/NAME.png``, ``captures/STATE/NAME``):
        not empty, no path separator, not ``.`` or ``..``, no control characters."""
        value = self.text(key, default)
        bad = [c for c in value if c in "/\\" or ord(c) < 32]
        if not value.strip() or value in (".", "..") or bad:
            raise ConfigError(self.where(key), f"{value!r} cannot name a file or folder of the outputs",
                              "give a name of letters, digits, '-' or '_', without '/'")
        return value

    def vector(self, key: str, n: int, default: Any = _MISSING, *, lo: float | None = None,
               strict_lo: bool = False) -> tuple[float, ...]:
        value = self.raw(key, default)
        return vector(value, self.where(key), n, lo=lo, strict_lo=strict_lo)

    def scalar_or_rgb(self, key: str, default: Any, *, lo: float, hi: float | None = None) -> tuple[float, ...]:
        """A number for all channels or a list of three (R, G, B)."""
        value = self.raw(key, default)
        if isinstance(value, list):
            return vector(value, self.where(key), 3, lo=lo, hi=hi)
        return (_number(value, self.where(key), lo, hi, False),)

    def sub(self, key: str, default: Any = _MISSING) -> "Fields":
        return Fields(self.raw(key, default), self.where(key))

    def done(self) -> None:
        unknown = [k for k in self.data if k not in self.used]
        if unknown:
            key = unknown[0]
            close = difflib.get_close_matches(str(key), sorted(self.used), n=1)
            hint = f"did you mean '{close[0]}'?" if close else f"known keys: {', '.join(sorted(self.used))}"
            raise ConfigError(self.where(str(key)), "unknown key", hint)


def _number(value: Any, where: str, lo: float | None, hi: float | None, strict_lo: bool) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(where, f"must be a number, got {value!r}")
    value = float(value)
    if not np.isfinite(value):
        raise ConfigError(where, f"must be finite, got {value}")
    if lo is not None and (value <= lo if strict_lo else value < lo):
        bound = f"greater than {lo:g}" if strict_lo else f"at least {lo:g}"
        raise ConfigError(where, f"must be {bound}, got {value:g}")
    if hi is not None and value > hi:
        raise ConfigError(where, f"must be at most {hi:g}, got {value:g}")
    return value


def vector(value: Any, where: str, n: int, *, lo: float | None = None, hi: float | None = None,
           strict_lo: bool = False) -> tuple[float, ...]:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise ConfigError(where, f"must be a list of {n} numbers, got {value!r}")
    return tuple(_number(v, f"{where}[{i}]", lo, hi, strict_lo) for i, v in enumerate(value))
