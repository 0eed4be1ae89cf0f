"""How busy each stage of a cold run keeps this machine's cores: wall and CPU seconds side by side.

    python benchmarks/cpu_use.py --out benchmarks/results/cpu_use [--scene paper_two_planes] [--repeats 3]

A stage whose CPU seconds are the wall seconds times the cores is bound by the work it does: more
threads (running stages beside each other, or pieces of one) cannot make it faster, only less work
can. Issue 44 asks where the cold run's time goes and what bounds it; this says which stages are at
that bound. Per stage, the repeats one after another in one process (the first pays for allocation
as a cold run does):

- ``simulate``: one state's calibration captures for one projector (the virtual rig's rays cast
  first, outside the timing);
- ``decode``: :func:`~torchproj.calib.calibrate_projector` on that capture;
- ``build``: the transport of the scene's targets (``area``, rows on camera pixels, as ``run``);
- ``Q``: ``A^T A`` (scipy's product, one block of rows per core);
- ``fista``: FISTA from there (coarse start, scaling, step bound, iterations), as ``run``;
- ``eo``: EO_-100^255 from ``Q``, as ``run --solver eo --bounds=-100,255``.

CPU seconds are the process's (``resource.getrusage``: user + system, every thread). Writes
``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import copy
import resource
import time
from pathlib import Path

import torch
from common import machine, write_results

from torchproj.calib import calibrate_projector
from torchproj.pipeline import scene_images, simulate_calibration
from torchproj.pipeline.cache import cached_calibration
from torchproj.pipeline.run import build_operators
from torchproj.pipeline.targets import scene_targets
from torchproj.scene import load_scene
from torchproj.sim import VirtualRig
from torchproj.solve import solve_eo, solve_fista
from torchproj.solve.compensate import PIPELINE_ITERATIONS


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def timed(fn, *args, **kwargs):
    """``fn``'s result, wall seconds and CPU seconds."""
    wall, cpu = time.perf_counter(), cpu_seconds()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - wall, cpu_seconds() - cpu


def stages(scene_name: str) -> dict[str, tuple[float, float]]:
    """(wall, CPU) seconds of each stage, once."""
    scene = load_scene(scene_name)
    rig = VirtualRig(scene)
    state, projector = scene.states[0].name, scene.projectors[0]
    rig.geometry(state)
    out = {}
    capture, *out["simulate"] = timed(simulate_calibration, rig, state, 0)
    _, *out["decode"] = timed(calibrate_projector, capture, (projector.width, projector.height), require_response=False)
    del capture
    # The rest from the whole scene's calibration, as a second run reads it (the cache, under
    # TORCHPROJ_CACHE_DIR where set): the stages after it are what is timed.
    cal, _ = cached_calibration(scene, device="cpu", progress=False, oracle=False, bits=None, plane_tolerance=1.0)
    targets = scene_targets(scene, scene_images(scene), cal.rig)
    ops, *out["build"] = timed(build_operators, cal.states, targets, footprint="area", merge=False,
                               colour_weights="grey", device="cpu")
    fresh = copy.deepcopy(ops[0])  # no Q built on it
    _, *out["Q"] = timed(fresh.normal_equations)
    _, *out["eo"] = timed(solve_eo, fresh, (-100 / 255, 1.0), calibrations=cal.states, progress=False)
    fresh = copy.deepcopy(ops[0])
    fresh.normal_equations()
    _, *out["fista"] = timed(solve_fista, fresh, (0.0, 1.0), max_iter=PIPELINE_ITERATIONS["fista"], progress=False)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/cpu_use"))
    parser.add_argument("--scene", default="paper_two_planes")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    runs = [stages(args.scene) for _ in range(args.repeats)]
    cores = torch.get_num_threads()
    lines = [f"# How busy each stage keeps the cores: {args.scene} ({machine()})", "",
             f"Wall and CPU seconds per stage (`python benchmarks/cpu_use.py --scene {args.scene} --repeats "
             f"{args.repeats}`), the repeats one after another in one process, the first paying for allocation as a "
             f"cold run does. "
             f"Cores busy = CPU / wall, out of {cores}. FISTA's and EO's times start from a built `Q`.", "",
             "| stage | wall (s) | CPU (s) | cores busy |", "|---|---|---|---|"]
    for name in runs[0]:
        walls = [r[name][0] for r in runs]
        busy = [r[name][1] / r[name][0] for r in runs]
        cpus = [r[name][1] for r in runs]
        lines.append(f"| {name} | {min(walls):.2f}-{max(walls):.2f} | {min(cpus):.2f}-{max(cpus):.2f} | "
                     f"{min(busy):.2f}-{max(busy):.2f} |")
    write_results(args.out, {"scene": args.scene, "machine": machine(), "cores": cores,
                             "runs": [{k: {"wall_s": v[0], "cpu_s": v[1]} for k, v in r.items()} for r in runs]},
                  "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
