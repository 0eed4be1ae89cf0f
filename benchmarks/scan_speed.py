"""A placed box's Gray-code scan decoded two ways: the whole calibration, or the forward map a scan uses.

    python benchmarks/scan_speed.py --out benchmarks/results/scan_speed

``torchproj position`` scans every placed box (``scan_surface``): each projector's Gray code is
simulated on the box alone and decoded, and the decoded map is triangulated. Only the forward map is
triangulated; ``calibrate_projector`` also computes the inverse map, edge pixels, defocus, response
and stripe contrast. This times ``calibrate_projector(...).prj_xy`` against ``scan_map`` on the same
captures (box_positions' near box at its goal pose, both projectors), interleaved, and checks that
the two maps are equal.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import torch
from common import machine, write_results

from torchproj.calib import calibrate_projector, scan_map
from torchproj.pipeline import simulate_calibration
from torchproj.scene import load_scene
from torchproj.scene.config import State
from torchproj.sim import VirtualRig


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/scan_speed"))
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    scene = load_scene("box_positions")
    box = scene.states[0].surfaces[0]
    scanned = dataclasses.replace(scene, states=[State("scan", [box])], targets=[], seed=0)
    rig = VirtualRig(scanned)
    t0 = time.perf_counter()
    captures = [simulate_calibration(rig, "scan", j) for j in range(len(scene.projectors))]
    simulate_s = time.perf_counter() - t0
    sizes = [(p.width, p.height) for p in scene.projectors]
    ways = {"calibrate_projector": lambda c, size: calibrate_projector(c, size).prj_xy, "scan_map": scan_map}
    seconds = {name: [] for name in ways}
    maps = {}
    for _ in range(args.repeats):
        for name, decode in ways.items():
            t0 = time.perf_counter()
            maps[name] = [decode(c, size) for c, size in zip(captures, sizes)]
            seconds[name].append(round(time.perf_counter() - t0, 3))
    equal = all(torch.equal(torch.nan_to_num(a, nan=-1.0), torch.nan_to_num(b, nan=-1.0))
                for a, b in zip(maps["calibrate_projector"], maps["scan_map"]))
    result = {"machine": machine(), "surface": box, "projectors": len(sizes), "simulate_s": round(simulate_s, 3),
              "seconds": seconds, "maps_equal": equal}
    lines = [f"# Decoding a placed box's scan ({result['machine']})", "",
             "Command: `python benchmarks/scan_speed.py`. box_positions' box "
             f"`{box}` at its goal pose, {len(sizes)} projectors' Gray code simulated once "
             f"({simulate_s:.2f} s, casting included), then decoded {args.repeats} times each way, interleaved.", "",
             "| decoding | seconds (each repeat) |", "|---|---|"]
    lines += [f"| `{name}` | {' / '.join(f'{v:.2f}' for v in values)} |" for name, values in seconds.items()]
    lines += ["", f"The two maps are {'equal' if equal else 'NOT equal'} (NaN where not decoded)."]
    write_results(args.out, result, "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0 if equal else 1


if __name__ == "__main__":
    sys.exit(main())
