"""The same scene again: `torchproj run` and `torchproj position` with and without the cache, each in a fresh process.

    python benchmarks/run_again.py --out benchmarks/results/run_again [--commands run] [--repeats 5]

On the default scene (the paper's rig), with an empty cache folder of its own: ``run --no-cache``
(the cold run), ``run`` (simulates and keeps the calibration, its transport, the solve's ``Q`` and coarse
levels and the rays it cast), then ``run`` again, ``run --solver pgd``, ``run --objective ssim`` and ``run
--solver eo --bounds=-100,255`` (read them); then ``position --no-cache``, ``position`` (keeps its own
scene's) and ``position`` again (reads them). Wall time, peak resident memory and the stage timings
of ``report.json``; writes ``results.json`` and ``results.md``. ``--repeats N`` runs each command that
reads the cache N times and gives the median wall time (single runs on this machine drift by 10%).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

from calibration_speed import _CLI, _timed
from common import machine, write_results

from torchproj.pipeline.cache import CACHE_DIR_ENV

RUNS = (("run, cold, --no-cache", ["run", "--no-cache"]), ("run, first, keeps the calibration and transport", ["run"]),
        ("run again, the same command", ["run"]), ("run again, --solver pgd", ["run", "--solver", "pgd"]),
        ("run again, --objective ssim", ["run", "--objective", "ssim"]),
        ("run again, --solver eo --bounds=-100,255", ["run", "--solver", "eo", "--bounds=-100,255"]),
        ("position, cold, --no-cache", ["position", "--no-cache"]), ("position, first, keeps them", ["position"]),
        ("position again", ["position"]))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/run_again"))
    parser.add_argument("--commands", nargs="+", choices=("run", "position"), default=["run", "position"],
                        help="which commands' rows to time (default both)")
    parser.add_argument("--repeats", type=int, default=1, help="runs of each command that reads the cache (median)")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats must be at least 1, got {args.repeats}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        os.environ[CACHE_DIR_ENV] = str(Path(tmp) / "cache")  # the children inherit it
        for k, (label, extra) in enumerate(RUNS):
            if extra[0] not in args.commands:
                continue
            out, peak = Path(tmp) / f"run{k}", Path(tmp) / f"run{k}.peak"
            walls = [_timed([sys.executable, "-c", _CLI, str(peak), *extra, "--out", str(out)])
                     for _ in range(args.repeats if "again" in label else 1)]
            wall = sorted(walls)[len(walls) // 2]
            report = json.loads((out / "report.json").read_text())
            rows.append({"run": label, "wall_s": round(wall, 2), "wall_s_runs": [round(w, 2) for w in walls],
                         "peak_rss_gb": round(int(peak.read_text()) / 1024**2, 2),
                         "calibration_cache": report["calibration_cache"],
                         "transport_cache": report.get("transport_cache", "off"),
                         "cast_cache": report.get("cast_cache", "off"), "timings_s": report["timings_s"],
                         "psnr_db": [round(t["psnr_db"], 3) for t in report["targets"]] if "targets" in report else
                         [round(p["psnr_db_at_goal"], 3) for p in report["positions"]]})
            print(rows[-1], flush=True)
    # What any command pays before its work: Python importing torch, then torchproj's command line
    # (median of three fresh processes each).
    imports = {name: round(sorted(_timed([sys.executable, "-c", f"import {module}"]) for _ in range(3))[1], 2)
               for name, module in (("python", "sys"), ("torch", "torch"),
                                    ("torchproj", "torchproj.cli, torchproj.pipeline, torchproj.figures"))}
    print(imports, flush=True)
    result = {"machine": machine(), "rows": rows, "imports_s": imports}
    command = " ".join(["python benchmarks/run_again.py", *(argv if argv is not None else sys.argv[1:])])
    lines = [f"# The same scene again ({result['machine']})", "", f"Command: `{command}`; each "
             "command's default scene (`run`: paper_two_planes, `position`: box_positions), each run a fresh process, "
             f"one cache folder for all; the commands that read the cache median of {args.repeats}. PSNR: per target "
             "(`run`) or of the feedback at the goal (`position`).", "",
             "| run | wall (s) | peak (GB) | calibration | transport | cast rays | stages (report.json, s) | PSNR (dB) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        stages = ", ".join(f"{k} {v:.1f}" for k, v in r["timings_s"].items())
        lines.append(f"| {r['run']} | {r['wall_s']:.1f} | {r['peak_rss_gb']:.2f} | {r['calibration_cache']} | "
                     f"{r['transport_cache']} | {r['cast_cache']} | {stages} | "
                     + " / ".join(f"{v:.2f}" for v in r["psnr_db"]) + " |")
    lines += ["", f"A fresh process: Python alone {imports['python']:.2f} s, importing torch {imports['torch']:.2f} s, "
                  "importing what `torchproj run` imports (torch, torchproj.pipeline, torchproj.figures) "
                  f"{imports['torchproj']:.2f} s (median of three). "
              "Wall minus the run's own total minus the import is writing the report, images and figures."]
    write_results(args.out, result, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
