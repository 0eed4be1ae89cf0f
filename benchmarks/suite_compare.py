"""Two runs of the suite side by side: what a change to the model did to each target's gap to the ceiling.

    python benchmarks/suite_compare.py BEFORE AFTER [BEFORE AFTER ...] --out benchmarks/results/suite_strips
           [--model area] [--moved 0.1]

Each ``BEFORE AFTER`` pair is two ``benchmarks/suite.py`` output folders of the same seed and scenes,
run on two commits (e.g. the code before a change in a ``git worktree``). Per pair: the median and
worst gap of ``--model`` to the ceiling and the share of targets within 0.5 dB, before and after,
and every target whose gap moved by more than ``--moved`` dB. The ceiling is each run's own (the
exact light does not depend on the model, but a run's captures carry their own noise). Writes
``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from common import write_results


def gaps(folder: Path, model: str) -> dict[tuple[str, str], float]:
    """(scene, target) -> the model's gap to the ceiling (dB) in a suite run's ``results.json``."""
    rows = json.loads((folder / "results.json").read_text())["rows"]
    return {(r["scene"], t["name"]): t["gap_db"] for r in rows if r["model"] == model for t in r["targets"]}


def summary(values: list[float]) -> dict:
    return {"median_db": round(statistics.median(values), 3), "worst_db": round(max(values), 3),
            "within_half_db": round(sum(v <= 0.5 for v in values) / len(values), 3)}


def compare(before: Path, after: Path, model: str, moved: float) -> dict:
    a, b = gaps(before, model), gaps(after, model)
    keys = sorted(set(a) & set(b))
    if not keys:
        raise SystemExit(f"{before} and {after} share no target of model {model!r}: give two runs of one seed")
    changed = [{"scene": s, "target": t, "before_db": a[(s, t)], "after_db": b[(s, t)]}
               for s, t in keys if abs(a[(s, t)] - b[(s, t)]) > moved]
    return {"before": str(before), "after": str(after), "targets": len(keys),
            "before_summary": summary([a[k] for k in keys]), "after_summary": summary([b[k] for k in keys]),
            "moved": changed}


def markdown(results: list[dict], model: str, moved: float) -> str:
    lines = [f"# The suite before and after ({model}'s gap to the ceiling, dB)", "",
             "| runs | targets | median before / after | worst before / after | within 0.5 dB before / after |",
             "|---|---|---|---|---|"]
    for r in results:
        x, y = r["before_summary"], r["after_summary"]
        lines.append(f"| `{r['before']}` -> `{r['after']}` | {r['targets']} | {x['median_db']:.2f} / {y['median_db']:.2f} "
                     f"| {x['worst_db']:.2f} / {y['worst_db']:.2f} | {x['within_half_db']:.0%} / {y['within_half_db']:.0%} |")
    lines += ["", f"Targets whose gap moved by more than {moved} dB:", "", "| scene | target | before | after |",
              "|---|---|---|---|"]
    for r in results:
        lines += [f"| {m['scene']} | {m['target']} | {m['before_db']:.2f} | {m['after_db']:.2f} |" for m in r["moved"]]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="BEFORE AFTER folder pairs (benchmarks/suite.py outputs)")
    ap.add_argument("--model", default="area")
    ap.add_argument("--moved", type=float, default=0.1, help="list targets whose gap moved by more than this (dB)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    if len(args.runs) % 2:
        ap.error(f"give the runs in BEFORE AFTER pairs, got {len(args.runs)} folders")
    for folder in args.runs:
        if not (folder / "results.json").is_file():
            ap.error(f"{folder} holds no results.json: give benchmarks/suite.py output folders")
    results = [compare(args.runs[i], args.runs[i + 1], args.model, args.moved) for i in range(0, len(args.runs), 2)]
    text = markdown(results, args.model, args.moved)
    write_results(args.out, {"model": args.model, "moved_db": args.moved, "pairs": results}, text)
    print(text)
    print(f"wrote {args.out}/results.json, results.md")


if __name__ == "__main__":
    main()
