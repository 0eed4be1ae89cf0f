"""How much of each projector's light decodes, on every shipped scene (the basis of ``FEW_DECODED``).

    python benchmarks/decoding.py --out benchmarks/results/decoding

Each state and projector of each built-in scene is calibrated with Gray code on the virtual rig
(:func:`torchproj.pipeline.calibrate_virtual`, as ``torchproj run``), and the share of the pixels the
projector visibly lights that decoded fully, partly (a few cells named, placed from the neighbours) or not
at all is recorded; the located share (:attr:`torchproj.calib.GrayDecoding.lit_located_fraction`, fully or
partly) is what the warning compares with ``FEW_DECODED``.
Writes ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

from common import machine, write_results

from torchproj.calib import FEW_DECODED
from torchproj.pipeline import calibrate_virtual
from torchproj.scene import BUILTIN_SCENES, load_scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/decoding"))
    parser.add_argument("--scale", type=float, help="resolution factor for quick runs (default: full size)")
    args = parser.parse_args()
    rows = []
    for name in BUILTIN_SCENES:
        with warnings.catch_warnings(record=True):
            warnings.simplefilter("always")
            cal = calibrate_virtual(load_scene(name, scale=args.scale), progress=False)
        for state, per in cal.decoded.items():
            for projector, share in per.items():
                shares = cal.decode[state][projector]
                rows.append({"scene": name, "state": state, "projector": projector, "lit_located": share, **shares})
                print(f"{name:20s} {state:12s} {projector:10s} {shares['full']:.1%} fully, "
                      f"{shares['partial']:.1%} partly", flush=True)
    lines = ["# Share of each projector's lit pixels that decodes, fully or partly", "",
             f"`python benchmarks/decoding.py`{'' if args.scale is None else f' --scale {args.scale:g}'} on "
             f"{machine()}; under {FEW_DECODED:.0%} torchproj warns.", "",
             "| scene | state | projector | fully | partly | not | located |", "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['scene']} | {r['state']} | {r['projector']} | {r['full']:.1%} | {r['partial']:.1%} | "
              f"{r['none']:.1%} | {r['lit_located']:.1%}" + (" (warned)" if r["lit_located"] < FEW_DECODED else "")
              + " |" for r in rows]
    write_results(args.out, {"machine": machine(), "scale": args.scale, "threshold": FEW_DECODED, "rows": rows},
                  "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
