"""The refining fit beside creases and on curves: the map's error against the simulator's truth, per choice.

    python benchmarks/refine.py --out benchmarks/results/refine
    python benchmarks/refine.py --vary curve --out benchmarks/results/refine_curve

Each projector's calibration capture of each state is simulated once and calibrated with each
``crease_ratio`` (:func:`torchproj.calib.refine_subpixel`): ``inf`` fits the window centred on each
pixel only (the refining fit before creases were handled), a finite ratio lets a window beside the
pixel win where it fits that many times better. The refined map (``prj_xy``) is compared with the
simulator's exact projector coordinates at the pixel centres, in bands the truth defines. With
``--vary curve`` the ratio varied is ``curve_ratio`` instead (``inf``: planes only; a finite ratio
lets the centred window's quadratic win where it fits that many times better than its plane, on the
default scenes small curved objects before coarse cameras, and planes and boxes that must not lose):

- ``crease``: within 4 pixels of a crease (the true map bends by over 0.05 cells per pixel between
  neighbours, without a jump), and more than 8 from a depth edge;
- ``edge``: within 4 pixels of a depth edge or of the map's outline;
- ``rest``: everything else.

The seconds are ``refine_subpixel``'s alone, within each calibration, mean over the maps.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from matplotlib.figure import Figure

from common import machine, write_results
import torchproj.calib.pipeline as pipeline
from torchproj.calib import calibrate_projector
from torchproj.calib.maps import depth_edges
from torchproj.pipeline import simulate_calibration
from torchproj.scene import load_scene
from torchproj.sim import VirtualRig

RATIOS = (math.inf, 1.0, 1.5, 2.0, 3.0)


def _near(mask: torch.Tensor, reach: int) -> torch.Tensor:
    return F.max_pool2d(mask[None, None].float(), 2 * reach + 1, 1, reach)[0, 0] > 0


def bands(truth: torch.Tensor) -> dict[str, torch.Tensor]:
    """The crease, edge and rest bands of the camera image (see the module's text)."""
    unmapped = ~torch.isfinite(truth).all(-1)
    edge = depth_edges(truth) | (_near(unmapped, 1) & ~unmapped)
    bend = torch.zeros_like(unmapped)
    for dim in (0, 1):
        second = (torch.roll(truth, 1, dim) + torch.roll(truth, -1, dim) - 2 * truth).abs().amax(-1)
        bend |= (second > 0.05) & (second < 3)
    crease = _near(bend, 4) & ~_near(edge, 8)
    near_edge = _near(edge, 4)
    return {"crease": crease & ~near_edge, "edge": near_edge, "rest": ~crease & ~near_edge}


class _TimedRefine:
    """Seconds of each ``refine_subpixel`` call calibration makes, while in a ``with`` block."""

    def __enter__(self):
        self.seconds, self.real = [], pipeline.refine_subpixel

        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            out = self.real(*args, **kwargs)
            self.seconds.append(time.perf_counter() - t0)
            return out

        pipeline.refine_subpixel = timed
        return self

    def __exit__(self, *exc):
        pipeline.refine_subpixel = self.real


def chart(rows: list[dict], path: Path, key: str = "crease_ratio") -> None:
    """Per scene, each band's rms error against the varied ratio; the infinite ratio dashed."""
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    fig = Figure(figsize=(4 * len(scenes), 3.4))
    for k, scene in enumerate(scenes):
        ax = fig.add_subplot(1, len(scenes), k + 1)
        mine = [r for r in rows if r["scene"] == scene]
        finite = [r for r in mine if r[key] is not None]
        for band, colour in (("crease", "tab:red"), ("edge", "tab:orange"), ("rest", "tab:blue")):
            ax.plot([r[key] for r in finite], [r[f"{band}_rms"] for r in finite], "o-", color=colour,
                    label=band)
            for r in mine:
                if r[key] is None and r[f"{band}_rms"] is not None:
                    ax.axhline(r[f"{band}_rms"], color=colour, ls="--", lw=1)
        ax.set_yscale("log")
        ax.set_title(scene)
        ax.set_xlabel(f"{key} (dashed: inf, " + ("the centred window only)" if key == "crease_ratio" else "planes only)"))
        ax.set_ylabel("map error vs truth (cells rms)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vary", choices=["crease", "curve"], default="crease",
                        help="the ratio varied: crease_ratio (windows beside a crease) or curve_ratio (the window's quadratic)")
    parser.add_argument("--scenes", nargs="+",
                        help="default: box_positions box_cylinders head_two_positions (crease); small curved objects "
                             "before coarse cameras, planes and boxes (curve)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/refine"))
    parser.add_argument("--chart-only", action="store_true", help="redraw refine.png from --out's results.json")
    args = parser.parse_args(argv)
    key = f"{args.vary}_ratio"
    if args.chart_only:
        chart(json.loads((args.out / "results.json").read_text())["rows"], args.out / "refine.png", key)
        return 0
    if args.scenes is None:
        args.scenes = ["box_positions", "box_cylinders", "head_two_positions"] if args.vary == "crease" else \
            ["suite-1206-6", "suite-1-14", "suite-97-7", "suite-1206-5", "box_positions", "box_cylinders"]
    rows = []
    for name in args.scenes:
        scene = load_scene(name)
        rig = VirtualRig(scene)
        errors = {ratio: {band: [] for band in ("crease", "edge", "rest")} for ratio in RATIOS}
        seconds = {ratio: [] for ratio in RATIOS}
        for state in scene.states:
            for j, projector in enumerate(scene.projectors):
                size = (projector.width, projector.height)
                capture = simulate_calibration(rig, state.name, j)
                truth = rig.geometry(state.name).prj_xy[j].cpu()
                where = bands(truth)
                for ratio in RATIOS:
                    with _TimedRefine() as timer:
                        fitted = calibrate_projector(capture, size, require_response=False, **{key: ratio}).prj_xy
                    miss = (fitted - truth).norm(dim=-1)
                    for band, mask in where.items():
                        errors[ratio][band].append(miss[mask & torch.isfinite(miss)])
                    seconds[ratio].extend(timer.seconds)
                del capture
        for ratio in RATIOS:
            row = {"scene": name, key: None if math.isinf(ratio) else ratio,
                   "refine_s_per_map": round(sum(seconds[ratio]) / len(seconds[ratio]), 3)}
            for band, parts in errors[ratio].items():
                miss = torch.cat(parts)
                row[f"{band}_pixels"] = int(miss.numel())
                row[f"{band}_rms"] = round(float(miss.pow(2).mean().sqrt()), 4) if miss.numel() else None
                row[f"{band}_p99"] = round(float(miss.quantile(0.99)), 4) if miss.numel() else None
            rows.append(row)
            print(row, flush=True)
    write_results(args.out, {"machine": machine(), "rows": rows})
    chart(rows, args.out / "refine.png", key)
    lines = ["# The refining fit " + ("beside creases" if args.vary == "crease" else "on curves"), "",
             f"Command: `{' '.join(['python benchmarks/refine.py', *(argv if argv is not None else sys.argv[1:])])}` ({machine()})", "",
             "Refined map against the simulator's exact coordinates, cells: rms (99th percentile) per band; "
             f"{key} inf = " + ("the centred window only" if args.vary == "crease" else "planes only")
             + ". Bands in the module's text.", "",
             f"| scene | {key} | crease | edge | rest | refine (s per map) |", "|---|---|---|---|---|---|"]
    for r in rows:
        cells = [f"{r[f'{b}_rms']:.3f} ({r[f'{b}_p99']:.3f})" if r[f"{b}_rms"] is not None else "-"
                 for b in ("crease", "edge", "rest")]
        ratio = "inf" if r[key] is None else f"{r[key]:g}"
        lines.append(f"| {r['scene']} | {ratio} | {' | '.join(cells)} | {r['refine_s_per_map']:.2f} |")
    if rows:
        first = rows[0]
        lines += ["", "Pixels per band (" + first["scene"] + "): " + ", ".join(
            f"{b} {first[f'{b}_pixels']}" for b in ("crease", "edge", "rest"))]
    (args.out / "results.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
