"""Simulated calibrations kept between runs: the same scene calibrated again is read, not simulated.

Simulating a scene's calibration (every state and projector's Gray code, ramps, checkerboard) is
most of a ``torchproj run``; a second run of the same scene with another solver or objective repeated
all of it. :func:`cached_calibration` keys a calibration by everything it depends on:

- the scene as calibrated: every device, surface and state, canonically serialised, with the
  contents of any mesh file (its name, targets and ``show:`` changes do not enter: calibration
  happens before them);
- the calibration's options (``oracle``, ``bits``, ``plane_tolerance``);
- the code: a digest of the package's own source files, so that any change to how the rig
  simulates or how calibration decodes makes a new key (a version number would not, between
  releases).

The transport operator built from a cached calibration is kept beside it (:func:`cached_transport`),
keyed by the calibration's key, the targets (their images, masks, corners and states) and the
build's options: a second run with another solver or objective reads it instead of building it,
and the ``Q = A^T A`` the first solve built from it (:func:`keep_normal_matrices`).
So are the rays the simulator cast through the scene's world (:func:`keep_geometry`, keyed by the
scene and the code alone): a second run's evaluation captures render from them instead of casting
every camera ray again (two casts of 17 M rays, about 5 s, on the default scene).

Entries live in the platform's user cache folder (``platformdirs``; ``TORCHPROJ_CACHE_DIR``
overrides it), are written whole (a temporary file renamed into place), and the least recently used
are removed past ``TORCHPROJ_CACHE_MAX_GB`` (default 2). An entry that does not load, or whose key
does not match, is removed and recomputed, never trusted. The rig's noise generator is stored with
the calibration, so that a run from the cache captures exactly what a run without it does.

Within :func:`writing_behind` (a run does this), entries are written on one background thread while
the run builds, solves and scores: the default scene's four entries are 1.2 GB, a second or more of
writing, several where the disk is still flushing earlier runs' entries. Leaving the block waits for
every entry to be whole.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import hashlib
import json
import os
import tempfile
import threading
import time
import warnings
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch

from ..core.checks import check, env_number
from ..core.sparse import csr_tensor
from ..scene.config import Scene
from ..sim.rig import VirtualRig
from ..transport import Target, TransportOperator
from .virtual import VirtualCalibration, calibrate_virtual

__all__ = ["CACHE_DIR_ENV", "CACHE_MAX_ENV", "cache_dir", "cached_calibration", "cached_transport", "calibration_key",
           "geometry_key", "keep_geometry", "keep_normal_matrices", "read_geometry", "read_normal_matrices",
           "transport_key", "writing_behind"]

CACHE_DIR_ENV = "TORCHPROJ_CACHE_DIR"
CACHE_MAX_ENV = "TORCHPROJ_CACHE_MAX_GB"
_DEFAULT_MAX_GB = 2.0
_CODE_DIGEST: str | None = None
NOT_KEPT = "not kept"  # how an entry computed but refused by the cache folder is reported


def cache_dir() -> Path:
    """Where calibrations are kept: ``$TORCHPROJ_CACHE_DIR``, else the platform's user cache folder."""
    if os.environ.get(CACHE_DIR_ENV):
        return Path(os.environ[CACHE_DIR_ENV])
    import platformdirs

    return Path(platformdirs.user_cache_dir("torchproj")) / "calibrations"


def _code_digest() -> str:
    """A digest of the package's source files (once per process)."""
    global _CODE_DIGEST
    if _CODE_DIGEST is None:
        root = Path(__file__).resolve().parents[1]
        h = hashlib.sha256()
        for path in sorted(root.rglob("*.py")):
            h.update(str(path.relative_to(root)).encode())
            h.update(path.read_bytes())
        _CODE_DIGEST = h.hexdigest()
    return _CODE_DIGEST


def _canonical(value):
    """Plain JSON values for a scene's dataclasses: arrays as lists, mesh files by their contents."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _canonical(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): _canonical(v) for k, v in sorted(value.items(), key=lambda kv: str(kv[0]))}
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, Path):
        return {"file": str(value), "sha256": hashlib.sha256(value.read_bytes()).hexdigest() if value.is_file() else None}
    return value


def calibration_key(scene: Scene, **options) -> str:
    """The cache key of ``scene`` calibrated with ``options`` (module docstring)."""
    return _scene_key(scene, {"options": _canonical(options)})


def geometry_key(scene: Scene) -> str:
    """The cache key of the rays cast through ``scene``'s world (:class:`~torchproj.sim.rig.StateGeometry`):
    its devices, surfaces and states and the code, as for a calibration; no options enter casting."""
    return _scene_key(scene, {"cast": "geometry"})


def scene_as_calibrated(scene: Scene) -> dict:
    """What of ``scene`` a calibration depends on (module docstring), canonically: two scenes that give
    the same are one world to calibrate, whatever their names, targets and ``show:`` changes."""
    return _canonical(dataclasses.replace(scene, name="", targets=[], show=None, source=None))


def _scene_key(scene: Scene, what: dict) -> str:
    """A digest of the scene as calibrated (module docstring), of ``what`` is made from it, and of the code."""
    text = json.dumps({"scene": scene_as_calibrated(scene), **what, "code": _code_digest()}, sort_keys=True,
                      default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def transport_key(calibration: str, targets: list[Target], **options) -> str:
    """The cache key of the operator(s) built from the calibration keyed ``calibration`` for ``targets``
    with the build's ``options`` (footprint, merging, maps, colour weights, device)."""
    h = hashlib.sha256(json.dumps({"calibration": calibration, "options": _canonical(options)}, sort_keys=True,
                                  default=str).encode())
    for t in targets:
        h.update(json.dumps([t.state, t.name]).encode())
        for part in (t.image, t.mask, t.corners):
            h.update(b"none" if part is None else
                     json.dumps([str(part.dtype), list(part.shape)]).encode() + part.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def smoothed_key(transport: str, weight: float) -> str:
    """The cache key of the normal equations of the operator kept under key ``transport`` with the
    smoothness penalty ``weight`` below it (:meth:`~torchproj.transport.TransportOperator.with_smoothness`),
    whose ``Q``, coarse levels and solver setup a smoothed solve builds and a later one reads."""
    return hashlib.sha256(json.dumps({"transport": transport, "smoothness": float(weight)}).encode()).hexdigest()


def cached_transport(key: str, build, device="cpu") -> tuple[list[TransportOperator], str]:
    """``build()`` (a list of :class:`~torchproj.transport.TransportOperator`) through the cache under ``key``.

    Returns:
        ``(operators, how)``, ``how`` as for :func:`cached_calibration`.
    """
    folder = cache_dir()
    path = folder / f"transport-{key}.pt"
    how = "stored"
    if path.is_file():
        ops = _read(path, key, "transport", lambda payload: [_operator(parts, device) for parts in payload["operators"]])
        if ops is not None:
            return ops, "read"
        how = "recomputed"
    ops = build()
    kept = _write(folder, path, {"key": key, "operators": [_operator_parts(op) for op in ops]}, "transport")
    return ops, how if kept else NOT_KEPT


def read_normal_matrices(key: str, ops: list[TransportOperator]) -> list[int] | None:
    """Give the operators read under transport key ``key`` the ``Q = A^T A``, the coarse levels'
    ``P^T Q P`` and the solver's setup on them an earlier solve built (:func:`keep_normal_matrices`).

    Returns:
        per operator the number of coarse levels read, or None where nothing was (no entry, or an
        unreadable one: removed with a warning, and the operators left as they were).
    """
    path = cache_dir() / f"normal-{key}.pt"
    if not path.is_file():
        return None

    def adopt(payload):
        coarse = payload.get("coarse", [[] for _ in payload["Q"]])
        check(len(payload["Q"]) == len(ops) == len(coarse), f"{len(payload['Q'])} matrices for {len(ops)} operators")
        setups = payload.get("setup", [[] for _ in payload["Q"]])  # entries kept before setups were: none
        check(len(setups) == len(ops), f"{len(setups)} solver setups for {len(ops)} operators")
        try:
            for op, Q, levels, setup in zip(ops, payload["Q"], coarse, setups):
                check(Q is not None or not levels, "coarse levels kept without their Q")
                if Q is not None:
                    op.adopt_normal_matrix(Q)
                    op.adopt_coarse_matrices(levels)
                    op.adopt_solver_setup(setup)
        except Exception:
            for op in ops:  # all or nothing: a solve builds what it needs again
                op.forget_normal_equations()
            raise
        return [len(levels) for levels in coarse]

    return _read(path, key, "normal matrix", adopt, device=ops[0].val.device)


def keep_normal_matrices(key: str, ops: list[TransportOperator]) -> bool:
    """Keep the ``Q = A^T A`` a solve built for the operators kept under transport key ``key`` (those it
    built in the matrix form; a colour run forgets each channel's after its solve and keeps none), the
    coarse levels it built on them and what it computed on each level (Lipschitz bounds, 30 products
    each; the Jacobi scaling, three passes over the entries)."""
    matrices = [op.normal_matrix() for op in ops]
    if all(Q is None for Q in matrices):
        return False
    folder = cache_dir()
    return _write(folder, folder / f"normal-{key}.pt",
                  {"key": key, "Q": matrices, "coarse": [op.coarse_matrices() for op in ops],
                   "setup": [op.solver_setup() for op in ops]}, "normal matrix")


def read_geometry(rig: VirtualRig) -> str | None:
    """Give ``rig`` the states its scene's world cast in an earlier run, kept by :func:`keep_geometry`.

    Returns:
        ``"read"``, or None where the cache holds none for this world (an unreadable entry is removed
        with a warning, and the rig casts as if there were none).
    """
    key = geometry_key(rig.scene)
    path = cache_dir() / f"geometry-{key}.pt"
    if not path.is_file():
        return None

    def adopt(payload):
        rig.adopt_geometry(payload["states"])
        return True

    return None if _read(path, key, "cast geometry", adopt, device=rig.device) is None else "read"


def keep_geometry(rig: VirtualRig) -> str:
    """Keep the states ``rig`` has cast, for the next run of the same world (:func:`read_geometry`).

    Returns:
        ``"stored"`` or ``"not kept"`` (the cache folder refused it, with a warning).
    """
    key = geometry_key(rig.scene)
    folder = cache_dir()
    kept = _write(folder, folder / f"geometry-{key}.pt", {"key": key, "states": rig.cast_geometry()}, "cast geometry")
    return "stored" if kept else NOT_KEPT


def _operator_parts(op: TransportOperator) -> dict:
    """What rebuilds ``op``: its matrix, its transpose and bookkeeping."""
    return {"crow": op.crow, "col": op.col, "val": op.val, "transpose": (op.t_crow, op.t_col, op.t_val),
            "shape": op.shape, "rhs": op.rhs,
            "column_projector": op.column_projector, "column_cell": op.column_cell,
            "projector_sizes": op.projector_sizes, "constant": op.constant, "row_target": op.row_target,
            "scale": op.scale, "row_pixel": op.row_pixel, "camera_size": op.camera_size,
            "target_count": op.target_count}


def _operator(parts: dict, device) -> TransportOperator:
    parts = {k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in parts.items()}
    matrix = csr_tensor(parts.pop("crow"), parts.pop("col"), parts.pop("val"), parts.pop("shape"))
    transpose = parts.pop("transpose", None)  # entries kept before it was: computed again
    transpose = None if transpose is None else tuple(t.to(device) for t in transpose)
    return TransportOperator(matrix, **parts, transpose=transpose)


def cached_calibration(scene: Scene, *, device="cpu", progress=None, oracle: bool = False, bits: int | None = None,
                       plane_tolerance: float = 1.0) -> tuple[VirtualCalibration, str]:
    """:func:`~torchproj.pipeline.calibrate_virtual` through the cache.

    Returns:
        ``(calibration, how)``: ``how`` is ``"read"`` (from the cache), ``"stored"`` (simulated
        and kept), ``"recomputed"`` (an entry that would not load was replaced) or ``"not kept"``
        (simulated; the cache folder refused to keep it, with a warning).
    """
    key = calibration_key(scene, oracle=oracle, bits=bits, plane_tolerance=plane_tolerance)
    folder = cache_dir()
    path = folder / f"{key}.pt"
    how = "stored"
    if path.is_file():
        t0 = time.perf_counter()
        cal = _load(path, key, scene, device)
        if cal is not None:
            cal.seconds = time.perf_counter() - t0  # what this run spent on calibration: reading it
            return cal, "read"
        how = "recomputed"
    cal = calibrate_virtual(scene, device, progress, oracle=oracle, bits=bits, plane_tolerance=plane_tolerance)
    return cal, how if _store(folder, path, key, cal) else NOT_KEPT


def _load(path: Path, key: str, scene: Scene, device) -> VirtualCalibration | None:
    def make(payload):
        rig = VirtualRig(scene, device=device)
        rig.generator.set_state(payload["generator"])
        return VirtualCalibration(rig=rig, **payload["calibration"])

    return _read(path, key, "calibration", make)


def _store(folder: Path, path: Path, key: str, cal: VirtualCalibration) -> bool:
    fields = {f.name: getattr(cal, f.name) for f in dataclasses.fields(cal) if f.name != "rig"}
    return _write(folder, path, {"key": key, "calibration": fields, "generator": cal.rig.generator.get_state()}, "calibration")


def _read(path: Path, key: str, what: str, make, device="cpu"):
    """``make(payload)`` of the entry at ``path`` (its tensors on ``device``; the entry marked recently
    used), or None (the entry removed) where anything is wrong with it."""
    try:
        # The cache is this user's own folder, written by torchproj; the entry is checked against its key.
        # Mapped, not read, where the system lets a mapped file be removed or replaced (POSIX): a run
        # touches only the parts it uses (a calibration holds every map, share and capture; scoring
        # reads a few), and those straight from the page cache.
        # Rebuilding the sparse matrices, torch.load (2.11 with CUDA) warned on every run that CSR support
        # is beta and that invariant checks are off unless asked for: they stay off, as for every CSR
        # torchproj builds, and neither warning is shown (core.sparse.csr_tensor silences the same two).
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
            warnings.filterwarnings("ignore", message="Sparse invariant checks are implicitly disabled")
            payload = torch.load(path, map_location=device, weights_only=False, mmap=os.name == "posix")
        if not isinstance(payload, dict) or payload.get("key") != key:
            raise ValueError("its key does not match its name")
        made = make(payload)
    except FileNotFoundError:
        # Removed since it was found: another process sharing the folder made room under the cap. Not
        # a broken entry, so nothing to say; this run computes it.
        return None
    except Exception as exc:  # whatever is wrong with it, it is not trusted
        warnings.warn(f"{what} cache entry {path} is unreadable ({type(exc).__name__}: {exc}); recomputing it",
                      stacklevel=4)
        path.unlink(missing_ok=True)
        return None
    try:
        os.utime(path)  # recently used: evicted last
    except OSError:
        pass  # removed by another process after it was read whole (a mapped file stays readable)
    return made


class _Behind:
    """The entries a :func:`writing_behind` block hands to its writer thread, written one at a time, in order."""

    def __init__(self):
        self.refused: set[str] = set()  # what each refused entry held ("calibration", ...), filled on leaving
        self._writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="torchproj-cache")
        self._writes: list[tuple[str, Path, Future]] = []

    @property
    def handed(self) -> int:
        """How many entries the block has handed to its writer."""
        return len(self._writes)

    def submit(self, folder: Path, path: Path, payload: dict, what: str) -> None:
        # The payload's containers are copied here, on the caller's thread, so that the run may go on
        # changing its own dicts and lists while pickling walks the copies; tensors are shared, never copied
        # (nothing changes a kept tensor in place after it is made).
        self._writes.append((what, folder, self._writer.submit(_write_now, folder, path, _containers_copied(payload))))

    def finish(self, abandoned: bool = False) -> None:
        """Wait for the writes; ``abandoned`` (the block raised: an interrupt, an error): the entry being
        written is finished, whole, and those not begun are dropped."""
        self._writer.shutdown(wait=True, cancel_futures=abandoned)
        for what, folder, done in self._writes:
            exc = None if done.cancelled() else done.exception()
            if exc is None:
                continue
            if not isinstance(exc, (OSError, RuntimeError)):
                raise exc
            self.refused.add(what)
            _warn_not_kept(what, folder, exc)


# Each thread's open writing_behind block (a run in another thread has its own writer).
_LOCAL = threading.local()


@contextlib.contextmanager
def writing_behind():
    """Write the cache entries kept inside the block on a background thread while the block goes on, and
    wait for them on leaving. A block that raises (Ctrl-C, an error) waits only for the entry being
    written, which is left whole, and drops those not begun: whole entries or none, never a part.

    Yields:
        an object whose ``refused`` set names, after the block, what the cache folder refused to keep
        (``"calibration"``, ``"transport"``, ``"normal matrix"``, ``"cast geometry"``), each with a
        warning: inside the block, keeping reports an entry kept as soon as the folder takes it.
        Nested blocks share the outer one's writer; each thread has its own blocks (a run in another
        thread writes as it would alone).
    """
    outer = getattr(_LOCAL, "behind", None)
    if outer is not None:
        yield outer
        return
    _LOCAL.behind = behind = _Behind()
    try:
        yield behind
    except BaseException:
        _LOCAL.behind = None
        behind.finish(abandoned=True)
        raise
    _LOCAL.behind = None
    behind.finish()


def _containers_copied(value):
    """``value`` with its dicts, lists, tuples and dataclass instances copied, down to the tensors and
    other leaves (shared)."""
    if isinstance(value, dict):
        return {k: _containers_copied(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)) and not hasattr(value, "_fields"):
        return type(value)(_containers_copied(v) for v in value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        copied = copy.copy(value)
        for f in dataclasses.fields(value):
            object.__setattr__(copied, f.name, _containers_copied(getattr(value, f.name)))
        return copied
    return value


def _write(folder: Path, path: Path, payload: dict, what: str) -> bool:
    """``payload`` written whole to ``path`` (a temporary file renamed into place), then the cap kept;
    whether it was written. Within :func:`writing_behind`, written on its thread: True once the folder
    exists (a write the disk refuses later is reported when the block ends)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        behind = getattr(_LOCAL, "behind", None)
        if behind is not None:
            behind.submit(folder, path, payload, what)
        else:
            _write_now(folder, path, payload)
        return True
    # A full or read-only cache folder costs the next run its time, not this run (torch.save reports a
    # write the disk refused as a RuntimeError).
    except (OSError, RuntimeError) as exc:
        _warn_not_kept(what, folder, exc)
        return False


def _warn_not_kept(what: str, folder: Path, exc: BaseException) -> None:
    # stacklevel 5: the line it pointed at before this helper (4 from _write or the writer's finish), one
    # frame further out.
    warnings.warn(f"could not keep the {what} in {folder} ({exc}); the next run will compute it again", stacklevel=5)


def _write_now(folder: Path, path: Path, payload: dict) -> None:
    fd, tmp = tempfile.mkstemp(prefix=".partial-", suffix=".pt", dir=folder)
    os.close(fd)
    try:
        torch.save(payload, tmp)
        os.replace(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)
    _evict(folder, keep=path)


def _evict(folder: Path, keep: Path) -> None:
    """Remove the least recently used entries past the size cap (never the one just written)."""
    cap = env_number(CACHE_MAX_ENV, _DEFAULT_MAX_GB) * 1e9
    # Each entry's size and age read once: another process sharing the folder may remove an entry at
    # any moment (its own cap), and one gone since the listing is simply not counted.
    entries = []
    for p in folder.glob("*.pt"):
        try:
            st = p.stat()
        except FileNotFoundError:
            continue
        entries.append((st.st_mtime, st.st_size, p))
    total = sum(size for _, size, _ in entries)
    for _, size, p in sorted(e for e in entries if e[2] != keep):
        if total <= cap:
            break
        total -= size
        p.unlink(missing_ok=True)
