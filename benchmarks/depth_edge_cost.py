"""What taking a pixel that bridges a depth edge costs calibration: ``depth_edges`` with and without it.

    python benchmarks/depth_edge_cost.py --out benchmarks/results/depth_edge_cost [--scene paper_two_planes]

Calibrates the scene on the virtual rig (no cache) once; every call calibration makes to
:func:`torchproj.calib.maps.depth_edges` (the refinement's windows, the edge pixels, the outline
band) is timed as made, then again at once on the same map with the bridges left out
(``maps._bridges`` answering no pixel), so both sums see the same maps on the same machine state.
Also written: calibration's own time, and how many pixels the bridges add on the merged maps.
Writes ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import torch
from common import machine, write_results

from torchproj.calib import edges, graycode, maps, pipeline
from torchproj.pipeline import calibrate_virtual
from torchproj.scene import load_scene


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="paper_two_planes")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/depth_edge_cost"))
    args = ap.parse_args()
    original, bridges = maps.depth_edges, maps._bridges
    calls = []

    def without(dim, known):
        return torch.zeros((), dtype=torch.bool)

    def timed(prj_xy):
        t0 = time.perf_counter()
        edge = original(prj_xy)
        t1 = time.perf_counter()
        maps._bridges = without
        try:
            plain = original(prj_xy)
        finally:
            maps._bridges = bridges
        calls.append({"shape": list(prj_xy.shape[:2]), "with_s": t1 - t0, "without_s": time.perf_counter() - t1,
                      "added": int((edge & ~plain).sum())})
        return edge

    for module in (maps, graycode, pipeline, edges):  # each module's own name for it
        if hasattr(module, "depth_edges"):
            module.depth_edges = timed
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0 = time.perf_counter()
        calibrate_virtual(load_scene(args.scene), progress=False)
        total = time.perf_counter() - t0
    with_s, without_s = sum(c["with_s"] for c in calls), sum(c["without_s"] for c in calls)
    full = [c for c in calls if c["shape"][0] * c["shape"][1] >= 1e6]
    own = total - without_s  # calibration's time, less the repeats made here
    result = {"machine": machine(), "scene": args.scene, "calibrate_s": round(own, 2), "calls": len(calls),
              "depth_edges_with_s": round(with_s, 3), "depth_edges_without_s": round(without_s, 3),
              "full_size_calls": len(full), "added_pixels_full_size": [c["added"] for c in full], "every_call": calls}
    md = "\n".join([f"# depth_edges with and without the bridges, in one calibration of {args.scene} ({machine()})", "",
                    "| calibration (s) | depth_edges calls | their time with bridges (s) | without (s) | extra, share of calibration |",
                    "|---|---|---|---|---|",
                    f"| {own:.1f} | {len(calls)} ({len(full)} on maps of a megapixel or more) | {with_s:.2f} | {without_s:.2f} | "
                    f"{with_s - without_s:.2f} s, {(with_s - without_s) / max(own, 1e-9):.1%} |", "",
                    "Pixels the bridges add on the maps of a megapixel or more: "
                    + ", ".join(str(c["added"]) for c in full) + "."]) + "\n"
    write_results(args.out, result, md)
    print(md)


if __name__ == "__main__":
    main()
