"""What every benchmark shares: one timer and one way to write its results."""

from __future__ import annotations

import dataclasses
import platform
import statistics
import time
import warnings
from pathlib import Path

import torch
from torch.utils.benchmark import Timer

from torchproj.core import write_json
from torchproj.core.sparse import csr_tensor
from torchproj.transport import TransportOperator

__all__ = ["bandwidth_gb_s", "interleaved", "machine", "median_time", "nonzero_rows", "row_sums", "run_operators", "with_matrix", "write_results"]


def median_time(fn, *args, repeats: int = 5) -> float:
    """Median seconds of ``fn(*args)`` over ``repeats`` runs after one warm-up (first calls pay for
    allocation and thread start-up). torch's Timer, on this process's threads, synchronises CUDA."""
    fn(*args)
    timer = Timer(stmt="fn(*args)", globals={"fn": fn, "args": args}, num_threads=torch.get_num_threads())
    return timer.timeit(1).median if repeats == 1 else _median(timer, repeats)


def _median(timer: Timer, repeats: int) -> float:
    times = sorted(timer.timeit(1).median for _ in range(repeats))
    return times[len(times) // 2] if repeats % 2 else 0.5 * (times[repeats // 2 - 1] + times[repeats // 2])


def interleaved(runs: dict, repeats: int, warm_up: bool = False) -> dict:
    """Median seconds of each of ``runs`` (name -> function), called in turn ``repeats`` times, so that
    a machine whose speed drifts (a shared host's memory bandwidth moved 14-31 GB/s within an hour
    here) weighs on each alike; ``warm_up`` calls each once first. A GPU's kernels are waited for."""
    times = {k: [] for k in runs}
    if warm_up:
        for fn in runs.values():
            fn()
    for _ in range(repeats):
        for k, fn in runs.items():
            t0 = time.perf_counter()
            fn()
            if torch.cuda.is_available():
                torch.cuda.synchronize()  # a GPU's kernels run after the call returns
            times[k].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in times.items()}


def bandwidth_gb_s() -> float:
    """Bytes read plus written per second by a copy of a 512 MB tensor: the yardstick of a pass's
    floor (what its bytes cost at this machine's memory bandwidth)."""
    source = torch.rand(128 * 1024 * 1024)
    target = torch.empty_like(source)
    seconds = median_time(target.copy_, source)
    return 2 * source.numel() * 4 / seconds / 1e9


def machine() -> str:
    """What ran a benchmark: the processor's architecture and the threads torch uses."""
    return f"{platform.machine()}, {torch.get_num_threads()} threads"


def write_results(folder: Path, result, markdown: str | None = None) -> None:
    """``results.json`` (NaN written as null, so the file stays valid JSON) and, given, ``results.md``."""
    folder.mkdir(parents=True, exist_ok=True)
    write_json(folder / "results.json", result)
    if markdown is not None:
        (folder / "results.md").write_text(markdown)


def without_checker(states: dict) -> dict:
    """Each state's calibration without the checkerboard pair's shares: what a capture folder of the
    Gray code alone gives (state name -> :class:`~torchproj.transport.StateCalibration`)."""
    return {name: dataclasses.replace(state, shares=state.shares and [
        part and dataclasses.replace(part, checker=None) for part in state.shares]) for name, state in states.items()}


def nonzero_rows(op: TransportOperator) -> torch.Tensor:
    """The row of each of ``op``'s nonzeros, in CSR order."""
    return torch.repeat_interleave(torch.arange(op.shape[0]), op.crow.diff())


def row_sums(op: TransportOperator) -> torch.Tensor:
    """Each row's total light (the sum of its entries)."""
    return torch.zeros(op.shape[0], dtype=op.val.dtype).index_add_(0, nonzero_rows(op), op.val)


def with_matrix(op: TransportOperator, crow: torch.Tensor, col: torch.Tensor, val: torch.Tensor) -> TransportOperator:
    """``op`` with another matrix on the same rows and columns (CSR arrays), everything else kept."""
    return TransportOperator(csr_tensor(crow, col, val, op.shape), op.rhs, op.column_projector, op.column_cell,
                             op.projector_sizes, constant=op.constant, row_target=op.row_target, scale=op.scale,
                             row_pixel=op.row_pixel, camera_size=op.camera_size, target_count=op.target_count)


def run_operators(name: str, scale: float | None = None):
    """A shipped or suite scene, calibrated on the virtual rig (its warnings quiet), and its transport
    under the ``nearest`` and the ``area`` footprint as ``torchproj run`` builds them (nearest merged,
    area on camera pixels): ``(footprint, operator)`` pairs, one operator at a time."""
    from torchproj.pipeline import calibrate_virtual, scene_targets
    from torchproj.scene import load_scene
    from torchproj.transport import build_transport

    scene = load_scene(name, scale=scale)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = calibrate_virtual(scene, progress=False)
    targets = scene_targets(scene, None, cal.rig)
    for footprint in ("nearest", "area"):
        yield footprint, build_transport(cal.states, targets, footprint=footprint, merge=footprint == "nearest")
