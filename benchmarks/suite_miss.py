"""Where and why the default model misses the ceiling on suite scenes: the outline band, the weights, the rows.

    python benchmarks/suite_miss.py --from benchmarks/results/suite --out benchmarks/results/suite_miss
           [--scenes suite-1-12 ...] [--threshold 0.5]

For each scene of a suite run (``benchmarks/suite.py``'s ``results.json``) with a target more than
``--threshold`` dB below the ceiling (or the scenes named), calibrated once as ``run`` calibrates:

- **where**: each target's PSNR of the default model and of the ceiling over all its pixels, over
  its interior (pixels 2 or more from the edge of its region) and over the band within 2 pixels of
  its outline, where a camera pixel may see the object and what lies behind it;
- **what**: the same rows solved with each row's measured weight (white minus black) replaced by the
  simulator's exact one (``exact weights``), and with each row's shape (how its light is shared among
  cells) replaced by the exact light's, scaled to the measured weight (``exact shapes``), and built
  again with every decoded pixel's map coordinate replaced by the simulator's (``exact maps``; the
  shares, blur and edge pixels as measured). What the measured weight costs is the first's gain;
  what the model of a pixel's footprint costs, the second's; what of that is the map's error, the
  third's;
- **which rows**: the exact shapes swapped in on some rows only: those of the pixels
  :func:`~torchproj.calib.find_edge_pixels` modelled (``exact shapes, edge pixels``: one or two
  surfaces carried from the neighbours) and those of the outline band (``exact shapes, band``).

Grey scenes only (a tinted surface gives the exact light one operator per channel). Writes
``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import warnings
from pathlib import Path

import torch
import torch.nn.functional as F
from common import machine, nonzero_rows, row_sums, with_matrix, write_results

from torchproj.pipeline import (CEILING_ITERATIONS, calibrate_virtual, evaluate_patterns, light_transport,
                                scene_targets, solve_on_light_transport, true_responses)
from torchproj.scene import load_scene
from torchproj.solve import make_patterns
from torchproj.transport import TransportOperator, build_transport, csr_from_coo

BOUNDS = (0.0, 1.0)
BAND = 2  # camera pixels from a target region's outline that count as its outline band


def rescaled(op: TransportOperator, factor: torch.Tensor) -> TransportOperator:
    """``op`` with each row multiplied by ``factor``."""
    return with_matrix(op, op.crow, op.col, op.val * factor[nonzero_rows(op)])


def _entries(op: TransportOperator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``op``'s nonzeros as (row, global column, value), a global column numbering every projector's
    cells in turn."""
    offsets = torch.tensor([0] + [w * h for w, h in op.projector_sizes]).cumsum(0)
    column = offsets[op.column_projector.long()] + op.column_cell.long()
    return nonzero_rows(op), column[op.col.long()], op.val


def mixed(model: TransportOperator, other: TransportOperator, rows: torch.Tensor) -> TransportOperator:
    """``model`` with the ``rows`` (a mask over its rows) taken from ``other`` (the same rows, any
    columns), each such row scaled to ``model``'s row sum."""
    r, c, v = _entries(model)
    ro, co, vo = _entries(other)
    vo = vo * (row_sums(model) / row_sums(other).clamp_min(1e-12))[ro]
    keep, take = ~rows[r], rows[ro]
    r, c, v = torch.cat([r[keep], ro[take]]), torch.cat([c[keep], co[take]]), torch.cat([v[keep], vo[take]])
    used = torch.unique(c)
    offsets = torch.tensor([0] + [w * h for w, h in model.projector_sizes]).cumsum(0)
    projector = torch.searchsorted(offsets, used, right=True) - 1
    matrix = csr_from_coo(r, torch.searchsorted(used, c), v, (model.shape[0], len(used)))
    return TransportOperator(matrix, model.rhs, projector, used - offsets[projector], model.projector_sizes,
                             row_target=model.row_target, scale=model.scale, row_pixel=model.row_pixel,
                             camera_size=model.camera_size, target_count=model.target_count)


def edge_rows(cal, targets, model: TransportOperator) -> torch.Tensor:
    """A mask over ``model``'s rows: the pixels some projector's edge pixels (one surface or two) hold."""
    width, height = model.camera_size
    out = torch.zeros(model.shape[0], dtype=torch.bool)
    for k, target in enumerate(targets):
        edges = torch.zeros(width * height, dtype=torch.bool)
        for found in cal.states[target.state].edges or []:
            if found is not None:
                edges[found.pixel.long().cpu()] = True
        out |= (model.row_target == k) & edges[model.row_pixel.long()]
    return out


def band_rows(targets, model: TransportOperator) -> torch.Tensor:
    """A mask over ``model``'s rows: those within ``BAND`` pixels of their target's outline."""
    width, height = model.camera_size
    out = torch.zeros(model.shape[0], dtype=torch.bool)
    for k in range(len(targets)):
        mine = model.row_target == k
        region = torch.zeros(width * height, dtype=torch.bool)
        region[model.row_pixel[mine].long()] = True
        band = region & ~inside(region.reshape(height, width)).reshape(-1)
        out |= mine & band[model.row_pixel.long()]
    return out


def inside(region: torch.Tensor) -> torch.Tensor:
    """The pixels of ``region`` :math:`(H, W)` ``BAND`` or more pixels from its edge."""
    return -F.max_pool2d(-region.float()[None, None], 2 * BAND + 1, 1, BAND)[0, 0] > 0.5


def exact_maps(cal) -> dict:
    """The calibrated states with each decoded pixel's projector coordinate the simulator's (NaN where
    the simulator's pixel centre is unlit), everything else as measured."""
    states = {}
    for name, state in cal.states.items():
        truth = cal.rig.geometry(name).prj_xy.cpu()
        states[name] = dataclasses.replace(state, prj_xy=[
            torch.where(torch.isfinite(m).all(-1, keepdim=True), t.to(m.dtype), m) for m, t in zip(state.prj_xy, truth)])
    return states


def psnr(score, region: torch.Tensor) -> float:
    error = ((score.estimate - score.values) ** 2).mean(0)[region]
    return -10 * math.log10(float(error.mean())) if region.any() else float("nan")


def measure(name: str, log=print) -> dict | None:
    scene = load_scene(name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = calibrate_virtual(scene, progress=False)
        targets = scene_targets(scene, None, cal.rig)
        model = build_transport(cal.states, targets, footprint="area", merge=False)
        exact = light_transport(cal.rig, targets, model)
        if len(exact) != 1 or exact[0].shape[0] != model.shape[0]:
            log(f"{name}: skipped (tinted surfaces, or rows the exact light does not reach)")
            return None
        exact = exact[0]
        measured, true = row_sums(model), row_sums(exact)
        runs = {"area": model, "area, exact weights": rescaled(model, true / measured.clamp_min(1e-12)),
                "area, exact shapes": rescaled(exact, measured / true.clamp_min(1e-12)),
                "area, exact maps": build_transport(exact_maps(cal), targets, footprint="area", merge=False,
                                                    scale=model.scale),
                "area, exact shapes, edge pixels": mixed(model, exact, edge_rows(cal, targets, model)),
                "area, exact shapes, band": mixed(model, exact, band_rows(targets, model)),
                "ceiling": exact}
        scores = {}
        for label, op in runs.items():
            iterations = CEILING_ITERATIONS if label == "ceiling" else None
            if label == "ceiling":
                _, _, patterns = solve_on_light_transport([op], BOUNDS, true_responses(cal.rig.scene), max_iter=iterations)
            else:
                _, _, patterns = make_patterns([op], "fista", BOUNDS, cal.responses, progress=False)
            scores[label] = evaluate_patterns(cal, patterns, targets, scale=model.scale, paper=False, seed=scene.seed).targets
    out = {"scene": name, "weight_error_rms": round(float(((measured / true) - 1).pow(2).mean().sqrt()), 4),
           "targets": []}
    for k, target in enumerate(targets):
        covered = scores["area"][k].covered
        inner = inside(covered)
        row = {"name": target.name, "pixels": int(covered.sum()), "outline_pixels": int((covered & ~inner).sum()),
               "edge_rows": int((edge_rows(cal, targets, model) & (model.row_target == k)).sum())}
        for label in runs:
            s = scores[label][k]
            row[label] = {"all": round(s.psnr_db, 3), "interior": round(psnr(s, inner), 3),
                          "outline": round(psnr(s, covered & ~inner), 3)}
        out["targets"].append(row)
        log(f"{name} {target.name}: " + ", ".join(f"{label} {row[label]['all']:.2f} (interior {row[label]['interior']:.2f}, "
                                                   f"outline {row[label]['outline']:.2f})" for label in runs))
    return out


COLUMNS = ("area", "area, exact weights", "area, exact shapes", "area, exact maps", "area, exact shapes, edge pixels",
           "area, exact shapes, band", "ceiling")


def markdown(results: list[dict]) -> str:
    lines = [f"# Where the default model misses the ceiling ({machine()})", "",
             f"PSNR (dB) over all of a target's pixels / its interior / the band within {BAND} pixels of its outline. "
             "`exact weights`: each row's measured white minus black replaced by the exact light's; `exact shapes`: each "
             "row's split among cells replaced by the exact light's, at the measured weight; `exact maps`: built again "
             "with each decoded pixel's map coordinate the simulator's (shares, blur and edge pixels as measured); "
             "`exact shapes, edge pixels` and `, band`: the exact shapes on the rows of the pixels find_edge_pixels "
             "modelled, or of the outline band, only.", "",
             "| scene | target | pixels (outline, edge) | " + " | ".join(COLUMNS) + " |",
             "|---|---|---|" + "---|" * len(COLUMNS)]
    for r in results:
        for t in r["targets"]:
            cells = [f"{t[k]['all']:.2f} / {t[k]['interior']:.2f} / {t[k]['outline']:.2f}" if k in t else ""
                     for k in COLUMNS]
            lines.append(f"| {r['scene']} | {t['name']} | {t['pixels']} ({t['outline_pixels']}, {t.get('edge_rows', '')}) | "
                         + " | ".join(cells) + " |")
    lines += ["", "Measured weight against the exact row sum, rms relative error per scene: "
              + ", ".join(f"{r['scene']} {r['weight_error_rms']:.4f}" for r in results) + "."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--from", dest="source", type=Path, default=Path("benchmarks/results/suite"),
                    help="a suite run's folder: its scenes with a target over --threshold dB below the ceiling")
    ap.add_argument("--scenes", nargs="+", help="these scenes instead")
    ap.add_argument("--threshold", type=float, default=0.5)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/suite_miss"))
    args = ap.parse_args()
    names = args.scenes
    if not names:
        rows = json.loads((args.source / "results.json").read_text())["rows"]
        names = list(dict.fromkeys(r["scene"] for r in rows if r["model"] == "area"
                                   and any(t["gap_db"] > args.threshold for t in r["targets"])))
    results = [r for r in (measure(n) for n in names) if r is not None]
    write_results(args.out, {"machine": machine(), "band_px": BAND, "results": results}, markdown(results))
    print(markdown(results))
    print(f"wrote {args.out}/results.json, results.md")


if __name__ == "__main__":
    main()
