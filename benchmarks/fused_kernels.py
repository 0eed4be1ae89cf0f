"""Fused element-wise kernels (``torch.compile``): the camera model against its eager chain and against
this machine's memory bandwidth, and ``torchproj run`` with compiling on and off.

    python benchmarks/fused_kernels.py --out benchmarks/results/fused_kernels

- The camera model (``torchproj.sim.camera``) on one capture of the default rig's sequence (44 images
  of 1600x1200, noise drawn from the rig's generator): eager, fused, and the floor its bytes set
  (each image's radiance and noise read and its values written, 12 bytes a pixel, at the bandwidth a
  large tensor copy reaches here); how many pixels differ between the two.
- ``torchproj run --no-cache`` in fresh processes on the default scene, ``TORCHPROJ_COMPILE=1`` and
  ``0`` (the default) alternating (inductor's cache warm), wall time and the stages of
  ``report.json``; and once with an empty inductor cache: the first-ever compile's cost.

Writes ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from common import bandwidth_gb_s, machine, median_time, write_results

from torchproj.scene import load_scene
from torchproj.sim.camera import _sensor, apply_camera

IMAGES = 44


def camera_model(log=print) -> dict:
    os.environ["TORCHPROJ_COMPILE"] = "1"  # apply_camera fused; the eager chain is called as _sensor.eager
    camera = load_scene("paper_two_planes").camera
    radiance = torch.rand(IMAGES, 1, camera.height, camera.width, generator=torch.Generator().manual_seed(0)) * 0.5

    def fused():
        return apply_camera(radiance.clone(), camera, torch.Generator().manual_seed(1))

    def eager():
        out = torch.empty_like(radiance)
        g = torch.Generator().manual_seed(1)
        for i in range(IMAGES):
            noise = torch.randn(radiance[i].shape, generator=g)
            out[i] = _sensor.eager(radiance[i], noise, camera.exposure, 1 / camera.full_well, camera.read_noise ** 2,
                                   1 / camera.gamma, 255.0)
        return out

    def noise_only():
        g = torch.Generator().manual_seed(1)
        for i in range(IMAGES):
            torch.randn(radiance[i].shape, generator=g)

    a, b = fused(), eager()
    one = (radiance[0], torch.randn(radiance[0].shape), camera.exposure, 1 / camera.full_well,
           camera.read_noise ** 2, 1 / camera.gamma, 255.0)
    row = {"images": IMAGES, "pixels": camera.width * camera.height, "eager_s": median_time(eager),
           "fused_s": median_time(fused), "noise_draw_s": median_time(noise_only),
           "chain_eager_s": IMAGES * median_time(_sensor.eager, *one), "chain_fused_s": IMAGES * median_time(_sensor, *one),
           "pixels_differing": int((a != b).sum()), "values": a.numel(), "bandwidth_gb_s": bandwidth_gb_s()}
    row["floor_s"] = IMAGES * camera.width * camera.height * 12 / (row["bandwidth_gb_s"] * 1e9)
    log(f"camera model, {IMAGES} images: eager {row['eager_s']:.3f} s, fused {row['fused_s']:.3f} s (of which drawing "
        f"the noise {row['noise_draw_s']:.3f} s), floor {row['floor_s']:.3f} s at {row['bandwidth_gb_s']:.1f} GB/s; "
        f"{row['pixels_differing']} of {row['values']} values differ")
    return row


def _run(compile_on: bool, inductor_cache: str | None = None) -> dict:
    env = dict(os.environ, TORCHPROJ_COMPILE="1" if compile_on else "0")
    if inductor_cache is not None:
        env["TORCHINDUCTOR_CACHE_DIR"] = inductor_cache
    with tempfile.TemporaryDirectory() as folder:
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "torchproj.cli", "run", "--no-cache", "--out", f"{folder}/run"],
                       check=True, capture_output=True, env=env)
        wall = time.perf_counter() - t0
        report = json.loads(Path(f"{folder}/run/report.json").read_text())
    return {"compile": compile_on, "wall_s": wall, "timings_s": report["timings_s"],
            "psnr_db": [t["psnr_db"] for t in report["targets"]]}


def everyday(repeats: int, log=print) -> dict:
    runs = []
    with tempfile.TemporaryDirectory() as empty:
        first = _run(True, empty)
    log(f"first-ever compile (empty inductor cache): run {first['wall_s']:.1f} s wall")
    for _ in range(repeats):
        for on in (True, False):
            runs.append(_run(on))
            log(f"compile {'on ' if on else 'off'}: {runs[-1]['wall_s']:.1f} s wall, calibrate "
                f"{runs[-1]['timings_s']['calibrate']:.1f} s, PSNR {runs[-1]['psnr_db']}")
    return {"first_ever": first, "runs": runs}


def markdown(r: dict) -> str:
    c = r["camera_model"]
    lines = [f"Machine: {machine()}.", "",
             f"Camera model, one capture of {c['images']} images of {c['pixels']} pixels: eager {c['eager_s']:.3f} s, "
             f"fused {c['fused_s']:.3f} s ({c['eager_s'] / c['fused_s']:.1f}x; drawing the noise, eager in both, "
             f"{c['noise_draw_s']:.3f} s; the chain alone {c['chain_eager_s']:.3f} s eager, {c['chain_fused_s']:.3f} s "
             f"fused); the floor its 12 bytes a pixel set at this machine's "
             f"{c['bandwidth_gb_s']:.1f} GB/s copy bandwidth: {c['floor_s']:.3f} s. Values that differ: "
             f"{c['pixels_differing']} of {c['values']}.", "",
             "| torchproj run --no-cache | wall (s) | calibrate | transport | solve | evaluate | PSNR (dB) |",
             "|---|---|---|---|---|---|---|"]
    e = r["everyday"]
    for label, run in [("compile on, first ever (empty inductor cache)", e["first_ever"])] + [
            (f"compile {'on' if x['compile'] else 'off'}", x) for x in e["runs"]]:
        t = run["timings_s"]
        lines.append(f"| {label} | {run['wall_s']:.1f} | {t['calibrate']:.1f} | {t['transport']:.1f} | "
                     f"{t['solve']:.1f} | {t['evaluate']:.1f} | {' / '.join(f'{p:.2f}' for p in run['psnr_db'])} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/fused_kernels"))
    parser.add_argument("--repeats", type=int, default=2, help="runs of torchproj run per setting (default 2)")
    args = parser.parse_args(argv)
    result = {"machine": machine(), "camera_model": camera_model(), "everyday": everyday(args.repeats)}
    write_results(args.out, result, markdown(result))
    print(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
