"""Calibration speed: torchproj's decoder against OpenCV's per-pixel loop, and the virtual rig.

    python benchmarks/calibration_speed.py --out benchmarks/results/calibration_speed

Writes ``results.json``, ``results.md`` and ``speed.png`` into ``--out``. Decoding is timed on one
real 42-image 1280x1024 capture (``../shared/data/procam_chessboard/capture_0``): torchproj's
vectorised decoder (median of several runs after one warm-up) against OpenCV's
``GrayCodePattern.getProjPixel`` called for every pixel of the shadow mask, the way OpenCV's own
``decode`` works. The virtual rig is timed on the paper's rig (two 1024x768 projectors, a 1600x1200
camera with 3x3 supersampling): casting a state, then capturing one projector's 42-image Gray-code
sequence.

The everyday loop is timed as a user meets it, each command in a fresh process on the default
scene: ``torchproj run`` and ``torchproj position`` (wall time, peak resident memory from the
kernel's accounting of the child, and the stage timings of ``report.json``); ``--suite`` also times
the default test suite (``python -m pytest -q``) and the slow tests (``-m slow``).
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from common import median_time, write_results  # noqa: E402
from torchproj.calib import (cell_shares, decode_gray, fill_holes, graycode_patterns, inverse_map,  # noqa: E402
                             read_graycode_folder, refine_subpixel)
from torchproj.scene import load_scene  # noqa: E402
from torchproj.sim import VirtualRig  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "procam_chessboard" / "capture_0"


def bench_decode(results: dict, opencv_pixels: int | None) -> None:
    results["read_42_pngs_s"] = median_time(read_graycode_folder, DATA, (1024, 768), repeats=3)
    cap = read_graycode_folder(DATA, (1024, 768))
    dec = decode_gray(cap.patterns, cap.white, cap.black, (1024, 768))
    results["torchproj_decode_s"] = median_time(decode_gray, cap.patterns, cap.white, cap.black, (1024, 768))
    results["torchproj_cell_shares_s"] = median_time(cell_shares, cap.patterns, cap.white, cap.black, dec, (1024, 768))
    results["torchproj_refine_s"] = median_time(refine_subpixel, dec.prj_xy, dec.valid)
    results["torchproj_fill_and_inverse_s"] = median_time(lambda: inverse_map(fill_holes(dec.prj_xy), (1024, 768)))
    results["valid_fraction"] = dec.valid_fraction

    raw = [cv2.imread(str(DATA / f"graycode_{i:02d}.png"), cv2.IMREAD_GRAYSCALE) for i in range(42)]
    gc = cv2.structured_light.GrayCodePattern.create(1024, 768)
    ys, xs = np.nonzero(np.abs(raw[40].astype(int) - raw[41].astype(int)) > 40)
    total = len(xs)
    if opencv_pixels is not None and opencv_pixels < total:
        pick = np.random.default_rng(0).choice(total, opencv_pixels, replace=False)
        ys, xs = ys[pick], xs[pick]
    patterns = raw[:40]
    t0 = time.perf_counter()
    for x, y in zip(xs.tolist(), ys.tolist()):
        gc.getProjPixel(patterns, x, y)
    elapsed = time.perf_counter() - t0
    results["opencv_pixels_timed"] = len(xs)
    results["opencv_shadow_mask_pixels"] = total
    results["opencv_getprojpixel_s"] = elapsed * total / len(xs)  # extrapolated when sampled
    results["speedup"] = results["opencv_getprojpixel_s"] / results["torchproj_decode_s"]


def bench_virtual_rig(results: dict) -> None:
    scene = load_scene()
    rig = VirtualRig(scene)
    t0 = time.perf_counter()
    rig.geometry("near")
    results["cast_state_s"] = time.perf_counter() - t0
    seq = graycode_patterns(1024, 768)
    t0 = time.perf_counter()
    images = rig.capture("near", {0: seq})
    results["capture_42_images_s"] = time.perf_counter() - t0
    results["capture_shape"] = list(images.shape)
    results["transport_nnz"] = [int(m[0]._nnz()) for m in rig.geometry("near").transport]


# The child reports its own peak (VmHWM: the high-water mark of its address space since exec). The
# kernel's rusage would not do: a child's ru_maxrss starts from the parent's size at fork, and this
# benchmark process is over a gigabyte by then.
_CLI = """import atexit, sys
peak_file = sys.argv.pop(1)
def peak():
    with open("/proc/self/status") as f:
        kib = next(line.split()[1] for line in f if line.startswith("VmHWM"))
    with open(peak_file, "w") as f:
        f.write(kib)
atexit.register(peak)
from torchproj.cli import main
sys.exit(main())
"""


def _timed(command: list[str]) -> float:
    """Wall seconds of ``command`` run as a child process (fails loudly)."""
    t0 = time.perf_counter()
    with tempfile.TemporaryFile() as err:
        code = subprocess.run(command, stdout=subprocess.DEVNULL, stderr=err).returncode
        wall = time.perf_counter() - t0
        if code != 0:
            err.seek(0)
            raise SystemExit(f"{' '.join(command)} failed:\n{err.read().decode()[-2000:]}")
    return wall


def bench_everyday(results: dict, suite: bool) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        for name in ("run", "position"):
            out, peak = Path(tmp) / name, Path(tmp) / f"{name}.peak"
            # Cold: a calibration kept by an earlier run would make these a cache read.
            results[f"{name}_wall_s"] = _timed([sys.executable, "-c", _CLI, str(peak), name, "--no-cache", "--out",
                                                str(out)])
            results[f"{name}_peak_rss_gb"] = int(peak.read_text()) / 1024**2
            results[f"{name}_timings_s"] = json.loads((out / "report.json").read_text())["timings_s"]
    if suite:
        root = Path(__file__).resolve().parents[1]
        for name, extra in (("suite", []), ("suite_slow", ["-m", "slow"])):
            results[f"{name}_wall_s"] = _timed([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                                                "--rootdir", str(root), str(root / "tests"), *extra])


def _everyday_rows(r: dict) -> list[str]:
    if "run_wall_s" not in r:
        return []
    stages = lambda t: ", ".join(f"{k} {v:.1f}" for k, v in t.items())  # noqa: E731
    rows = ["", "| everyday command (fresh process, default scene) | wall seconds | peak memory (GB) | "
            "stages (report.json, s) |", "|---|---|---|---|",
            f"| `torchproj run` | {r['run_wall_s']:.1f} | {r['run_peak_rss_gb']:.2f} | {stages(r['run_timings_s'])} |",
            f"| `torchproj position` | {r['position_wall_s']:.1f} | {r['position_peak_rss_gb']:.2f} | "
            f"{stages(r['position_timings_s'])} |"]
    if "suite_wall_s" in r:
        rows += [f"| `python -m pytest` (default suite) | {r['suite_wall_s']:.0f} | | |",
                 f"| `python -m pytest -m slow` | {r['suite_slow_wall_s']:.0f} | | |"]
    return rows


def markdown(r: dict) -> str:
    return "\n".join([
        "# Calibration speed",
        "",
        f"Machine: {r['machine']}, torch {r['torch']} ({r['threads']} threads). Command: `{r['command']}`.",
        "",
        "| step | seconds |",
        "|---|---|",
        f"| read 42 PNGs (1280x1024, 8-bit) | {r['read_42_pngs_s']:.3f} |",
        f"| **torchproj decode** (vectorised, OpenCV semantics) | **{r['torchproj_decode_s']:.3f}** |",
        f"| OpenCV getProjPixel over the shadow mask ({r['opencv_shadow_mask_pixels']} px"
        f"{'' if r['opencv_pixels_timed'] == r['opencv_shadow_mask_pixels'] else ', extrapolated from ' + str(r['opencv_pixels_timed'])}) "
        f"| {r['opencv_getprojpixel_s']:.2f} |",
        f"| speed-up of the decode | {r['speedup']:.0f}x |",
        f"| each pixel's shares across its cell's edges, from its Gray-code differences (cell_shares; "
        f"cell_means is their mean) | {r['torchproj_cell_shares_s']:.3f} |",
        f"| sub-pixel refinement (7x7 affine fit) | {r['torchproj_refine_s']:.3f} |",
        f"| hole filling + inverse map | {r['torchproj_fill_and_inverse_s']:.3f} |",
        f"| virtual rig: cast one state (1600x1200, 3x3 samples, 2 projectors) | {r['cast_state_s']:.2f} |",
        f"| virtual rig: capture one projector's 42-image Gray-code sequence | {r['capture_42_images_s']:.2f} |",
        *_everyday_rows(r),
        "",
        f"Decoded fraction of the camera frame: {r['valid_fraction']:.1%}.",
        "",
    ])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/calibration_speed"))
    parser.add_argument("--opencv-pixels", type=int, default=None,
                        help="time OpenCV on this many sampled pixels and extrapolate (default: all)")
    parser.add_argument("--skip-everyday", action="store_true", help="do not time torchproj run and position")
    parser.add_argument("--suite", action="store_true", help="also time the test suite (minutes)")
    args = parser.parse_args(argv)
    if not DATA.is_dir():
        print(f"real captures not found at {DATA}", file=sys.stderr)
        return 1
    results = {"machine": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} threads",
               "torch": torch.__version__, "threads": torch.get_num_threads(),
               "command": "python benchmarks/calibration_speed.py " + " ".join(argv if argv is not None else sys.argv[1:])}
    if not args.skip_everyday:
        bench_everyday(results, args.suite)
    bench_decode(results, args.opencv_pixels)
    bench_virtual_rig(results)
    args.out.mkdir(parents=True, exist_ok=True)
    write_results(args.out, results, markdown(results))
    fig, ax = plt.subplots(figsize=(7, 3))
    labels = ["OpenCV getProjPixel loop", "torchproj decode", "read 42 PNGs"]
    values = [results["opencv_getprojpixel_s"], results["torchproj_decode_s"], results["read_42_pngs_s"]]
    ax.barh(labels, values, color=["#999999", "#d62728", "#1f77b4"])
    ax.set_xscale("log")
    ax.set_xlabel("seconds (log scale), one 42-image 1280x1024 capture")
    for i, v in enumerate(values):
        ax.text(v, i, f" {v:.3g} s", va="center")
    fig.tight_layout()
    fig.savefig(args.out / "speed.png", dpi=100)
    print(markdown(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
