"""The SSIM solve's first call against its steady state, on any device, with a profile of five iterations.

    python benchmarks/ssim_first_call.py [cpu|cuda] [OUT_TABLE]

On the default scene (its calibration from the cache, the area transport with rows on camera pixels,
FISTA's patterns as the start): ``solve_ssim`` with one iteration (the first call in the process), then
with five, then five under ``torch.profiler``, whose tables (by CPU time, and by GPU time on a GPU) go
to ``OUT_TABLE`` (default ``/tmp/prof.txt``). On a GPU the first call pays for every kernel's first
launch, which a run's one SSIM solve never wins back.
"""

import sys
import time

import torch
from torch.profiler import ProfilerActivity, profile

from torchproj.pipeline import scene_targets
from torchproj.pipeline.cache import cached_calibration
from torchproj.scene import load_scene
from torchproj.solve import solve_fista, solve_ssim
from torchproj.transport import build_transport


def main() -> None:
    dev = sys.argv[1] if len(sys.argv) > 1 else "cpu"
    out = sys.argv[2] if len(sys.argv) > 2 else "/tmp/prof.txt"
    scene = load_scene("paper_two_planes")
    cal, _ = cached_calibration(scene, device=dev)
    targets = scene_targets(scene, None, cal.rig)
    op = build_transport(cal.states, targets, merge=False, footprint="area", device=dev)
    x0 = solve_fista(op, (0, 1), progress=False).patterns
    sync = torch.cuda.synchronize if dev == "cuda" else (lambda: None)
    for n in (1, 5):
        sync()
        t0 = time.time()
        solve_ssim(op, (0, 1), x0=x0, max_iter=n, tol=0)
        sync()
        print(f"solve_ssim {n} it: {time.time() - t0:.3f} s", flush=True)
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev == "cuda" else [])
    with profile(activities=acts) as prof:
        solve_ssim(op, (0, 1), x0=x0, max_iter=5, tol=0)
        sync()
    with open(out, "w") as f:
        f.write(prof.key_averages().table(sort_by="cpu_time_total", row_limit=40))
        if dev == "cuda":
            f.write(prof.key_averages().table(sort_by="self_cuda_time_total", row_limit=25))


if __name__ == "__main__":
    main()
