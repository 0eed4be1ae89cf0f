"""FISTA against itself at another git revision: time to a 1e-3 gap, the two taking turns.

    python benchmarks/solver_ab.py --against 7fc3bc7

This machine's speed drifts by 10-50% from one minute to the next, more than most changes to the
solver make, so two benchmark runs an hour apart cannot tell them apart. Here both versions run in
one process, on the same operator, one run each in turn, so that both see the same drift; each
pair of runs gives a ratio, and the table reports their median. The other revision's
``torchproj/solve/solvers.py`` is read with ``git show`` and loaded as a module of the current
package: it runs on the current operator, and a revision whose solver needs something the current
operator lacks fails to load.

Rig: as ``benchmarks/solvers.py`` (``colour_two_planes`` at quarter, half and full projector
resolution, astronaut near and chelsea far, RGB). Writes ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import subprocess
import sys
import types
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import write_results  # noqa: E402
from model_space import image  # noqa: E402
from solvers import SIZES  # noqa: E402
from stability import small  # noqa: E402

from torchproj.pipeline import calibrate_virtual  # noqa: E402
from torchproj.scene import parse_scene  # noqa: E402
from torchproj.solve import solvers as current  # noqa: E402
from torchproj.transport import Target, build_transport  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
GAP = 1e-3


def load_revision(rev: str) -> types.ModuleType:
    """``torchproj/solve/solvers.py`` as it was at ``rev``, as a module beside the current one."""
    source = subprocess.run(["git", "show", f"{rev}:torchproj/solve/solvers.py"], cwd=ROOT, capture_output=True,
                            text=True)
    if source.returncode != 0:
        raise SystemExit(f"--against {rev}: git could not show its solvers.py ({source.stderr.strip()})")
    name = f"torchproj.solve._solvers_at_{rev.replace('-', '_')}"
    module = types.ModuleType(name)
    module.__package__, module.__file__ = "torchproj.solve", f"{rev}:torchproj/solve/solvers.py"
    sys.modules[name] = module  # dataclasses look their module up while the class is made
    exec(compile(source.stdout, module.__file__, "exec"), module.__dict__)
    return module


def time_to_gap(solve, op, best: float, levels: int) -> float:
    res = solve(op, (0, 1), max_iter=500, tol=0, levels=levels, progress=False)
    return next((t for t, f in res.history if (f - best) / best <= GAP), float("nan"))


def compare(label: str, other, runs: int, log=print) -> dict:
    projector, camera = SIZES[label]
    scene = parse_scene(small("colour_two_planes", camera=camera, projector=projector), name=f"colour_{label}")
    cal = calibrate_virtual(scene)
    targets = [Target("near", image("astronaut"), name="astronaut"), Target("far", image("chelsea"), name="chelsea")]
    op = build_transport(cal.states, targets, merge=True)
    best = current.solve_fista(op, max_iter=3000, tol=1e-10, progress=False).objective
    versions = {"current": current.solve_fista, "other": other.solve_fista}
    rows = []
    for levels in (3, 0):
        for solve in versions.values():
            time_to_gap(solve, op, best, levels)  # the first solve per rig pays one-off setup
        times = {name: [] for name in versions}
        for _ in range(runs):
            for name, solve in versions.items():
                times[name].append(time_to_gap(solve, op, best, levels))
        ratios = [o / c for c, o in zip(times["current"], times["other"])]
        rows.append({"levels": levels, "current_s": statistics.median(times["current"]),
                     "other_s": statistics.median(times["other"]), "other_over_current": statistics.median(ratios),
                     "ratio_range": [min(ratios), max(ratios)],
                     "runs": {k: [round(t, 5) for t in v] for k, v in times.items()}})
        log(f"{label} levels={levels}: current {rows[-1]['current_s'] * 1e3:.1f} ms, other "
            f"{rows[-1]['other_s'] * 1e3:.1f} ms, other / current {rows[-1]['other_over_current']:.2f}")
    return {"variables": op.shape[1], "rows": rows}


def markdown(rev: str, head: str, results: dict, runs: int) -> str:
    lines = [f"# FISTA at {head} (current) against {rev}: time to a {GAP:g} relative gap", "",
             f"Command: `python benchmarks/solver_ab.py --against {rev}` ({platform.machine()}, "
             f"{torch.get_num_threads()} threads, torch {torch.__version__}). {runs} runs of each version, taking "
             "turns on one operator; the ratio is the median over the pairs of runs.", "",
             "| size (variables) | coarse start | current (ms) | other (ms) | other / current (range) |",
             "|---|---|---|---|---|"]
    for label, r in results.items():
        for row in r["rows"]:
            lo, hi = row["ratio_range"]
            lines.append(f"| {label} ({r['variables']}) | {'yes' if row['levels'] else 'no'} | "
                         f"{row['current_s'] * 1e3:.1f} | {row['other_s'] * 1e3:.1f} | "
                         f"{row['other_over_current']:.2f} ({lo:.2f}-{hi:.2f}) |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--against", required=True, help="a git revision (commit, tag, branch) to compare with")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/solver_ab"))
    parser.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    parser.add_argument("--runs", type=int, default=7, help="runs of each version per size (default 7)")
    args = parser.parse_args(argv)
    if args.runs < 1:
        parser.error(f"--runs must be at least 1, got {args.runs}")
    other = load_revision(args.against)
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                          text=True).stdout.strip() or "HEAD"
    results = {label: compare(label, other, args.runs) for label in args.sizes}
    write_results(args.out, {"against": args.against, "head": head, "runs": args.runs, "sizes": results}, markdown(args.against, head, results, args.runs))
    print(f"wrote {args.out / 'results.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
