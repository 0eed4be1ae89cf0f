"""How much one capture's camera noise moves a suite target's score, and its gap to the ceiling.

    python benchmarks/noise_draws.py --scenes suite-55-8 suite-56-5 --draws 8 --out benchmarks/results/noise_draws

Per scene: the default model (``area``) and the ceiling are solved once, as ``benchmarks/suite.py``
solves them; each set of patterns is then captured under ``--draws`` noise seeds (the same seeds for
both) and once without noise. Per target it reports the PSNR's range over the draws, the noise-free
PSNR, and the gap to the ceiling's range: over draws where both meet the same noise (what the suite
scores, ``evaluate_patterns(..., seed=)``), and over pairs of different draws (what it scored
before, each capture the rig's next draw). The suite's "within 0.5 dB" reads against these.
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

from common import machine, write_results
from suite import solve_model

from torchproj.pipeline import calibrate_virtual, evaluate_patterns, scene_targets
from torchproj.scene import load_scene


def measure(name: str, draws: int) -> list[dict]:
    scene = load_scene(name)
    cal = calibrate_virtual(scene, progress=False)
    targets = scene_targets(scene, None, cal.rig)
    scored = {}
    for model in ("area", "ceiling"):
        ops, *_, patterns, _ = solve_model(cal, targets, model)
        runs = [evaluate_patterns(cal, patterns, targets, scale=ops[0].scale, paper=False, seed=1000 + 10 * d).targets
                for d in range(draws)]
        clean = evaluate_patterns(cal, patterns, targets, scale=ops[0].scale, paper=False, noise=False).targets
        scored[model] = ([[s.psnr_db for s in run] for run in runs], [s.psnr_db for s in clean])
        pixels = [s.pixels for s in clean]
    rows = []
    for k, target in enumerate(targets):
        area = [run[k] for run in scored["area"][0]]
        ceiling = [run[k] for run in scored["ceiling"][0]]
        same = [c - a for a, c in zip(area, ceiling)]
        crossed = [ceiling[j] - area[i] for i, j in itertools.permutations(range(draws), 2)]
        rows.append({"scene": name, "target": target.name, "pixels": pixels[k],
                     "area_db": [round(min(area), 2), round(max(area), 2)],
                     "area_clean_db": round(scored["area"][1][k], 2),
                     "ceiling_clean_db": round(scored["ceiling"][1][k], 2),
                     "gap_same_noise_db": [round(min(same), 2), round(max(same), 2)],
                     "gap_other_noise_db": [round(min(crossed), 2), round(max(crossed), 2)]})
        print(rows[-1], flush=True)
    return rows


def markdown(rows: list[dict], draws: int) -> str:
    lines = [f"# One capture's noise against a target's score ({machine()})", "",
             f"{draws} noise draws of the same patterns; PSNR in dB; gap = the ceiling's PSNR minus area's.", "",
             "| scene | target | pixels | area over the draws | area, no noise | ceiling, no noise | gap, the same draw "
             "| gap, other draws |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['target']} | {r['pixels']} | {r['area_db'][0]:.2f}-{r['area_db'][1]:.2f} | "
                     f"{r['area_clean_db']:.2f} | {r['ceiling_clean_db']:.2f} | "
                     f"{r['gap_same_noise_db'][0]:.2f} to {r['gap_same_noise_db'][1]:.2f} | "
                     f"{r['gap_other_noise_db'][0]:.2f} to {r['gap_other_noise_db'][1]:.2f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["suite-55-8"])
    parser.add_argument("--draws", type=int, default=8)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/noise_draws"))
    args = parser.parse_args()
    if args.draws < 2:
        parser.error("--draws must be 2 or more: a range needs two draws")
    rows = [row for name in args.scenes for row in measure(name, args.draws)]
    write_results(args.out, {"machine": machine(), "draws": args.draws, "rows": rows}, markdown(rows, args.draws))


if __name__ == "__main__":
    main()
