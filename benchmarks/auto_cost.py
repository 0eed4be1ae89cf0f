"""What ``--footprint auto`` costs beside the model it chooses, with and without its early screen.

    python benchmarks/auto_cost.py --seed 1 --count 20 --out benchmarks/results/auto_cost

Issue 42 asks that ``auto`` come within 0.2 dB of the best model at no more than that model's cost.
Per scene of the procedural suite (small size, calibrated once), as ``run`` builds and solves
(FISTA, least squares, bounds 0..255), interleaved and each the median of ``--repeats``:

- ``area``: the area model built and solved;
- ``auto``: :func:`~torchproj.pipeline.choose_footprint` (nearest's expected loss first on the
  targets' back-projection, before nearest is built; where that is within the tolerance, nearest
  built and solved for :data:`~torchproj.pipeline.footprint.SCREEN_ITERATIONS` iterations, to the
  end only where the early estimate is within the tolerance too), then the chosen model built and
  solved (from nearest's patterns where nearest was solved to the end);
- ``auto, iterations``: the rule before the back-projection's screen (``SCREEN_BACK_PROJECTION``
  off): nearest always built and solved for ``SCREEN_ITERATIONS`` first;
- ``auto, no screen``: nearest always solved to the end before deciding (both screens off:
  ``SCREEN_ITERATIONS`` set to the pipeline's 300), area then solved as ``auto`` solves it.

Each run starts as a fresh ``torchproj run`` does: new targets, and the states without what an
earlier run kept on them (each target's warp onto the camera, the lit pixels, the maps' slopes),
which within one run the decision and the chosen model's build share.

Writes ``results.json`` and ``results.md``: seconds, auto's choice, the decision's share, the ratio
to area's cost, the solve's objective against area's, whether auto showed area's very patterns,
each target's PSNR on the rig's captures (in results.json: camera noise moves it), and nearest's
expected loss per target on the back-projection, after 5, 10 and 20 iterations and at the end
(what the screens assume: the earlier ones no higher).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from pathlib import Path

from common import machine, write_results

import torchproj.pipeline.footprint as footprint
from torchproj.cli_options import positive_int
from torchproj.pipeline import calibrate_virtual, choose_footprint, evaluate_patterns, scene_targets
from torchproj.pipeline.run import build_operators
from torchproj.scene import load_scene
from torchproj.scene.procedural import suite_names
from torchproj.solve import make_patterns, solve_fista
from torchproj.transport import build_transport
from torchproj.solve.compensate import PIPELINE_ITERATIONS

BOUNDS = (0.0, 1.0)
SCREEN = footprint.SCREEN_ITERATIONS


def _solve(cal, targets, model: str, choice=None):
    ops = build_operators(cal.states, targets, footprint=model, merge=False, colour_weights="channel", device="cpu")
    options = None if choice is None else choice.solver_options(ops, "fista")
    return make_patterns(ops, "fista", BOUNDS, cal.responses, progress=False, solver_options=options), ops


def _auto(cal, targets, screen: int, back_projection: bool = True):
    footprint.SCREEN_ITERATIONS, footprint.SCREEN_BACK_PROJECTION = screen, back_projection
    try:
        t0 = time.perf_counter()
        choice = choose_footprint(cal.states, targets, BOUNDS)
        decided = time.perf_counter() - t0
        return _solve(cal, targets, choice.footprint, choice), choice, decided
    finally:
        footprint.SCREEN_ITERATIONS, footprint.SCREEN_BACK_PROJECTION = SCREEN, True


EARLY = (5, 10, 20)


def estimates(cal, targets) -> dict[str, list[float]]:
    """Nearest's expected loss per target (dB) on the targets' back-projection (``"0"``), after each of
    :data:`EARLY` iterations and at the end (the pipeline's limit): what the screens assume is that the
    earlier ones are no higher."""
    op = build_transport(cal.states, targets, footprint="nearest", merge=False)
    shares = footprint._share_rows(cal.states, targets, op)
    out = {"0": [round(v, 4) for v in footprint._back_projected_loss(cal.states, targets, BOUNDS).values()]}
    for n in (*EARLY, PIPELINE_ITERATIONS["fista"]):
        patterns = solve_fista(op, BOUNDS, progress=False, max_iter=n).patterns
        out[str(n)] = [round(v, 4) for v in footprint._expected_loss(op, shares, patterns, targets).values()]
    return out


def _fresh(cal, targets: list) -> list:
    """The targets and states anew (the same tensors, none of what an earlier run kept on them: each
    target's warp onto the camera, the lit pixels, the maps' slopes): each run starts as a fresh
    ``torchproj run`` does, where the decision and the chosen model's build share them."""
    cal.states = {name: dataclasses.replace(state) for name, state in cal.states.items()}
    return [dataclasses.replace(t) for t in targets]


def measure(name: str, repeats: int) -> dict:
    cal = calibrate_virtual(load_scene(name), progress=False)
    targets = scene_targets(cal.rig.scene, None, cal.rig)
    runs = {"area": lambda ts: (_solve(cal, ts, "area"), None, 0.0),
            "auto": lambda ts: _auto(cal, ts, SCREEN),
            "auto, iterations": lambda ts: _auto(cal, ts, SCREEN, back_projection=False),
            "auto, no screen": lambda ts: _auto(cal, ts, PIPELINE_ITERATIONS["fista"], back_projection=False)}
    times = {label: [] for label in runs}
    decisions = {label: [] for label in runs}
    last = {}
    for _ in range(repeats):
        for label, run in runs.items():  # interleaved: this machine's speed drifts between runs
            fresh = _fresh(cal, targets)
            t0 = time.perf_counter()
            last[label] = run(fresh)
            times[label].append(time.perf_counter() - t0)
            decisions[label].append(last[label][2])
    row = {"scene": name, "nearest_estimates_db": estimates(cal, targets)}
    area = last["area"][0][0]
    for label, ((solved, ops), choice, _) in last.items():
        result, _, patterns = solved
        scores = evaluate_patterns(cal, patterns, targets, scale=ops[0].scale, paper=False).targets
        row[label] = {"seconds": round(statistics.median(times[label]), 4),
                      "decision_s": round(statistics.median(decisions[label]), 4),
                      "chose": None if choice is None else choice.footprint,
                      "nearest_iterations": None if choice is None else choice.iterations,
                      # Noise-free: the solver's objective over area's, and whether the shown patterns are area's.
                      "objective_over_area": result.objective / area[0].objective - 1,
                      "same_patterns": all(bool((x == y).all()) for x, y in zip(patterns, area[2])),
                      "psnr_db": [round(s.psnr_db, 3) for s in scores]}
    print(name, {k: v for k, v in row.items() if k != "scene"}, flush=True)
    return row


def markdown(rows: list[dict], title: str) -> str:
    labels = ("auto", "auto, iterations", "auto, no screen")
    lines = [f"# {title}", "", "Median seconds of the repeats (build and solve; auto's include its decision). "
             "Ratio: over area's. `objective`: the solve's objective over area's (model space, no camera noise); "
             "`area's patterns`: whether auto showed exactly area's; `iterations`: nearest's before the choice (0: "
             "decided on the back-projection). Camera noise moves a small scene's captured PSNR by up to 0.3 dB "
             "between captures of the same patterns, so the captures are not compared here.", "",
             "| scene | area (s) | " + " | ".join(f"{label} (s) | decision (s) | iterations | ratio | objective"
                                                 for label in labels) + " | area's patterns | chose |",
             "|" + "---|" * (4 + 5 * len(labels))]
    for r in rows:
        a, s = r["area"], r["auto"]
        cells = [f"{r[label]['seconds']:.3f} | {r[label]['decision_s']:.3f} | {r[label]['nearest_iterations']} | "
                 f"{r[label]['seconds'] / a['seconds']:.2f} | {r[label]['objective_over_area']:+.2%}" for label in labels]
        lines.append(f"| {r['scene']} | {a['seconds']:.3f} | " + " | ".join(cells)
                     + f" | {'yes' if s['same_patterns'] else 'no'} | {s['chose']} |")
    end = str(PIPELINE_ITERATIONS["fista"])
    steps = ["0", *map(str, EARLY), end]
    pairs = [(r["nearest_estimates_db"][a][k], r["nearest_estimates_db"][b][k]) for r in rows
             for a, b in zip(steps, steps[1:]) for k in range(len(r["nearest_estimates_db"][end]))]
    lines.append(f"\nNearest's expected loss on the back-projection, after {', '.join(map(str, EARLY))} iterations and "
                 f"at the end ({end}), each at or below the next: {sum(x <= y + 1e-9 for x, y in pairs)} of {len(pairs)} "
                 f"pairs, over {sum(len(r['nearest_estimates_db'][end]) for r in rows)} targets; the back-projection's "
                 f"at or below the end's on {sum(x <= y + 1e-9 for r in rows for x, y in zip(r['nearest_estimates_db']['0'], r['nearest_estimates_db'][end]))}.")
    for label in labels:
        ratios = sorted(r[label]["seconds"] / r["area"]["seconds"] for r in rows)
        lines.append(f"\n`{label}` over area: median {statistics.median(ratios):.2f}, best {ratios[0]:.2f}, "
                     f"worst {ratios[-1]:.2f}.")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--count", type=positive_int, default=20)
    ap.add_argument("--repeats", type=positive_int, default=3, help="runs per model and scene (median)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/auto_cost"))
    args = ap.parse_args()
    rows = [measure(name, args.repeats) for name in suite_names(args.seed, args.count)]
    title = f"auto's cost beside area's, suite seed {args.seed} ({machine()})"
    write_results(args.out, {"machine": machine(), "seed": args.seed, "rows": rows}, markdown(rows, title))


if __name__ == "__main__":
    main()
