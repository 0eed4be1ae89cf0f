"""Does the area footprint's sample grid flatter the judge? The default run against the ceiling on
``box_positions``' geometry, its camera's point samples varied, and the area model sampled n x n.

    python benchmarks/area_grid.py --out benchmarks/results/area_grid

The virtual camera integrates a pixel as ``supersampling`` x ``supersampling`` point samples, each
lit by the cell it falls in, and the ceiling (``--oracle transport``) is that point-sampled light.
The ``area`` footprint samples a camera pixel's square at ``_AREA_SAMPLES`` x ``_AREA_SAMPLES``
points (4 by default) carried through the calibrated map. Where both grids are the same and the
map is right, the model's samples fall on the camera's own and its row is the exact one, to the
judge's quantisation; ``box_positions`` ships with a 4 x 4 camera. Its boxes' faces are steep to
the projectors (a camera pixel spans 1.5-1.8 cells), so a tilted cell edge splits a few point
samples between cells in a way that no area can, and the captures' Gray code, constant along one
projector axis at a time, measures only each axis' split, not that joint one: the checkerboard
pair the sequence shows after it (:func:`~torchproj.calib.checker_patterns`) measures how the two
combine (:attr:`CellShares.checker <torchproj.calib.CellShares>`, the share of a pixel's light on
cells of the other parity ``(x + y) mod 2``).

1. ``box_positions`` with its camera's supersampling set to each of ``--cameras`` (one calibration
   each): the default run (the checkerboard share measured from its noisy captures) with the area
   model sampled at each of ``--samples`` (and, as by default, at ``_STEEP_SAMPLES`` squared points
   where a pixel spans more than ``_STEEP_EXTENT`` cells), and the ceiling.
2. With ``--checker``: the same runs with no finer grid on steep rows (``everywhere``), without the
   checkerboard share (the Gray code alone, as a capture folder without the pair, whose rows keep
   one grid), and with it taken from the exact light (what a noise-free capture of the pair would
   measure): what the finer grid and the pair are worth, and what the pair's noise costs.
3. The cost on a full-size scene: ``paper_two_planes`` (3 x 3 camera) built at each sample count,
   its transport seconds and scores.

Writes ``results.json``, ``results.md`` and ``area_grid.png`` (each target's PSNR below the
ceiling against the camera's grid, one line per model grid).
"""

from __future__ import annotations

import argparse
import dataclasses
import warnings
from pathlib import Path

import torch
from common import machine, without_checker, write_results
from matplotlib.figure import Figure

from torchproj.pipeline import calibrate_virtual, run_virtual
from torchproj.pipeline.ceiling import _gather_rows
from torchproj.scene import load_scene
from torchproj.transport import build

_DEFAULT, _STEEP = build._AREA_SAMPLES, build._STEEP_SAMPLES


def _scores(run) -> list[dict]:
    return [{"name": t.name, "psnr_db": round(t.psnr_db, 3), "ssim": round(t.ssim, 4)} for t in run.targets]


def _with_checker(cal, exact: bool):
    """``cal`` with each pixel's checkerboard share from the exact light, or with none (module text,
    point 2)."""
    if not exact:
        return dataclasses.replace(cal, states=without_checker(cal.states))
    states = {}
    for name, state in cal.states.items():
        transport, shares = cal.rig.geometry(name).transport, []
        for j, part in enumerate(state.shares):
            height, width = part.cell.shape[:2]
            row, col, val = _gather_rows(transport[j][0].cpu(), torch.arange(height * width))
            val = val.double()
            cols = cal.rig.scene.projectors[j].width
            cell = part.cell.reshape(-1, 2).long()
            other = (col % cols + col // cols) % 2 != (cell[row, 0] + cell[row, 1]) % 2
            total = torch.zeros(height * width, dtype=torch.float64).index_add_(0, row, val)
            far = torch.zeros_like(total).index_add_(0, row, torch.where(other, val, 0.0))
            checker = torch.where((cell >= 0).all(1) & (total > 0), far / total.clamp_min(1e-12), float("nan"))
            shares.append(dataclasses.replace(part, checker=checker.float().reshape(height, width)))
        states[name] = dataclasses.replace(state, shares=shares)
    return dataclasses.replace(cal, states=states)


def _runs(scene, samples: list[int], checker: bool = False) -> dict:
    """One calibration of ``scene``; the default run at each area sample count (and, ``checker``,
    without the checkerboard's share and with the exact one), and the ceiling."""
    cal = calibrate_virtual(scene, progress=False)
    out = {"ceiling": _scores(run_virtual(scene, calibration=cal, progress=False, oracle="transport"))}
    # (key, the grid, the steep rows' grid, the calibration)
    variants = [(str(n), n, max(n, _STEEP), cal) for n in samples]
    if checker:
        variants += [(f"{n}+flat", n, n, cal) for n in samples if n < _STEEP]
        for how, exact in (("gray", False), ("exact", True)):
            changed = _with_checker(cal, exact)
            variants += [(f"{n}+{how}", n, max(n, _STEEP), changed) for n in samples]
    for key, n, steep, c in variants:
        build._AREA_SAMPLES, build._STEEP_SAMPLES = n, steep
        try:
            run = run_virtual(scene, calibration=c, progress=False)
        finally:
            build._AREA_SAMPLES, build._STEEP_SAMPLES = _DEFAULT, _STEEP
        out[key] = {"targets": _scores(run), "transport_s": round(run.report["timings_s"]["transport"], 2)}
    return out


def _with_camera(scene, supersampling: int):
    return dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, supersampling=supersampling))


def _label(key) -> str:
    n, _, how = str(key).partition("+")
    steep = f" ({_STEEP} x {_STEEP} steep)" if int(n) < _STEEP and how in ("", "exact") else ""
    return f"area {n} x {n}{steep}" + {"": "", "flat": " everywhere", "gray": ", Gray code only",
                                        "exact": ", checker from the exact light"}[how]


def markdown(grid: dict, cost: dict, keys: list, samples: list[int]) -> str:
    lines = [f"# The area model's sample grid against the camera's ({machine()})", "",
             (f"## box_positions, camera point samples varied: PSNR / SSIM per target (ceiling: the exact "
              f"point-sampled light); default model grid {_DEFAULT} x {_DEFAULT}"), "",
             "| camera | " + " | ".join(_label(n) for n in keys) + " | ceiling |",
             "|---|" + "---|" * (len(keys) + 1)]
    for cam, runs in grid.items():
        cells = ["; ".join(f"{t['name']} {t['psnr_db']:.2f} / {t['ssim']:.3f}" for t in runs[n]["targets"])
                 for n in keys]
        top = "; ".join(f"{t['name']} {t['psnr_db']:.2f} / {t['ssim']:.3f}" for t in runs["ceiling"])
        lines.append(f"| {cam} x {cam} | " + " | ".join(cells) + f" | {top} |")
    lines += ["", "Below the ceiling, PSNR (dB) / SSIM, per target:", "",
              "| camera | " + " | ".join(_label(n) for n in keys) + " |",
              "|---|" + "---|" * len(keys)]
    for cam, runs in grid.items():
        cells = ["; ".join(f"{t['name']} {c['psnr_db'] - t['psnr_db']:.2f} / {c['ssim'] - t['ssim']:.3f}"
                           for t, c in zip(runs[n]["targets"], runs["ceiling"])) for n in keys]
        lines.append(f"| {cam} x {cam} | " + " | ".join(cells) + " |")
    lines += ["", "## paper_two_planes (3 x 3 camera): the cost", "",
              "| area grid | transport (s) | per target PSNR / SSIM |", "|---|---|---|"]
    for n in map(str, samples):
        lines.append(f"| {n} x {n} | {cost[n]['transport_s']:.1f} | "
                     + "; ".join(f"{t['name']} {t['psnr_db']:.2f} / {t['ssim']:.3f}" for t in cost[n]["targets"]) + " |")
    lines.append("| ceiling | | " + "; ".join(f"{t['name']} {t['psnr_db']:.2f} / {t['ssim']:.3f}"
                                               for t in cost["ceiling"]) + " |")
    return "\n".join(lines) + "\n"


def chart(path: Path, grid: dict, keys: list) -> None:
    """Per target, PSNR below the ceiling against the camera's grid, one line per model grid."""
    cams = list(grid)
    names = [t["name"] for t in grid[cams[0]]["ceiling"]]
    fig = Figure(figsize=(5 * len(names), 4), layout="constrained")
    for k, name in enumerate(names):
        ax = fig.add_subplot(1, len(names), k + 1)
        for n in keys:
            gap = [grid[c]["ceiling"][k]["psnr_db"] - grid[c][n]["targets"][k]["psnr_db"] for c in cams]
            ax.plot(cams, gap, "o-", label=_label(n) + (" (default)" if n == str(_DEFAULT) else ""))
        ax.axhline(0.3, color="grey", ls="--", lw=1, label="issue 18's goal")
        ax.set(title=f"box_positions, {name}", xlabel="camera point samples per pixel (s x s)",
               ylabel="PSNR below the ceiling (dB)", xticks=cams)
        ax.legend(fontsize=8)
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/area_grid"))
    ap.add_argument("--cameras", type=int, nargs="+", default=[2, 3, 4, 5, 6])
    ap.add_argument("--samples", type=int, nargs="+", default=[4, 8, 12])
    ap.add_argument("--checker", action="store_true",
                    help="also run without the checkerboard's share and with it from the exact light")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    base = load_scene("box_positions")
    grid = {}
    for cam in args.cameras:
        grid[cam] = _runs(_with_camera(base, cam), args.samples, args.checker)
        print("camera", cam, {k: v if k == "ceiling" else v["targets"] for k, v in grid[cam].items()}, flush=True)
    cost = _runs(load_scene("paper_two_planes"), args.samples)
    print("paper_two_planes", cost, flush=True)
    keys = [f"{n}{how}" for how in ["", *(["+flat", "+gray", "+exact"] if args.checker else [])] for n in args.samples
            if how != "+flat" or n < _STEEP]
    write_results(args.out, {"machine": machine(), "default_samples": _DEFAULT, "box_positions": grid,
                             "paper_two_planes": cost}, markdown(grid, cost, keys, args.samples))
    chart(args.out / "area_grid.png", grid, keys)


if __name__ == "__main__":
    main()
