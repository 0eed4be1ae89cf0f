"""What fitting the outline rows to every Gray-code pair costs a build, and what it gains the captures.

    python benchmarks/band_cost.py --scenes suite-55-16 suite-97-12 suite-1206-16 suite-1-8 paper_two_planes \
        --repeats 5 --out benchmarks/results/band_cost

Per scene, calibrated once: the ``area`` build as ``run`` makes it, with the calibration's outline
shares (:attr:`~torchproj.calib.CellShares.band_white`, fitted by ``_fit_band``) and without them
(the same calibration, the band dropped), called in turn ``--repeats`` times (median seconds, as
the machine's speed drifts); their nonzeros; and each target's captured PSNR solved on either, under
the scene's own camera noise. Writes ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import warnings
from pathlib import Path

from common import interleaved, machine, write_results

from torchproj.cli_options import positive_int
from torchproj.pipeline import calibrate_virtual, evaluate_patterns, scene_targets
from torchproj.pipeline.run import build_operators
from torchproj.scene import load_scene
from torchproj.solve import make_patterns


def without_band(states: dict) -> dict:
    """The calibrated states with no outline shares kept: the rows ``_fit_band`` leaves as they are."""
    return {name: dataclasses.replace(st, shares=None if st.shares is None else [
        dataclasses.replace(s, band=None, band_white=None) for s in st.shares]) for name, st in states.items()}


def measure(name: str, repeats: int, log=print) -> dict:
    scene = load_scene(name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = calibrate_virtual(scene, progress=False)
        targets = scene_targets(scene, None, cal.rig)
        variants = {"outline rows fitted": cal.states, "without": without_band(cal.states)}

        def build(states):
            return build_operators(states, targets, footprint="area", merge=False, colour_weights="channel",
                                   device="cpu")

        times = interleaved({k: (lambda s=s: build(s)) for k, s in variants.items()}, repeats)
        row = {"scene": name}
        for label, states in variants.items():
            ops = build(states)
            _, _, patterns = make_patterns(ops, "fista", (0.0, 1.0), cal.responses, progress=False)
            scores = evaluate_patterns(cal, patterns, targets, scale=ops[0].scale, paper=False, seed=scene.seed).targets
            row[label] = {"build_s": round(times[label], 4), "nnz": sum(o.nnz for o in ops),
                          "psnr_db": [round(s.psnr_db, 3) for s in scores]}
    log(f"{name}: build {row['without']['build_s']:.3f} -> {row['outline rows fitted']['build_s']:.3f} s, "
        f"PSNR " + " / ".join(f"{a:.2f} -> {b:.2f}" for a, b in zip(row["without"]["psnr_db"],
                                                                     row["outline rows fitted"]["psnr_db"])))
    return row


def markdown(rows: list[dict], repeats: int) -> str:
    lines = [f"# The outline rows' fit to every pattern pair: cost and gain ({machine()})", "",
             f"Median build seconds of {repeats} calls in turn; nonzeros; each target's captured PSNR (dB).", "",
             "| scene | build (s) without / fitted | ratio | nonzeros without / fitted | PSNR without -> fitted |",
             "|---|---|---|---|---|"]
    for r in rows:
        a, b = r["without"], r["outline rows fitted"]
        lines.append(f"| {r['scene']} | {a['build_s']:.3f} / {b['build_s']:.3f} | {b['build_s'] / a['build_s']:.2f} | "
                     f"{a['nnz']} / {b['nnz']} | " + ", ".join(f"{x:.2f} -> {y:.2f}" for x, y in zip(a["psnr_db"], b["psnr_db"]))
                     + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["suite-55-16", "suite-97-12", "suite-1206-16", "suite-1-8",
                                                     "paper_two_planes"])
    ap.add_argument("--repeats", type=positive_int, default=5)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/band_cost"))
    args = ap.parse_args()
    rows = [measure(n, args.repeats) for n in args.scenes]
    write_results(args.out, {"machine": machine(), "repeats": args.repeats, "rows": rows}, markdown(rows, args.repeats))
    print(markdown(rows, args.repeats))
    print(f"wrote {args.out}/results.json, results.md")


if __name__ == "__main__":
    main()
