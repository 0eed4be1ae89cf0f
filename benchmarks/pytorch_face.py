"""The model under torch's own tools: ``torch.compile``, ``torch.func.vmap``, a batch, 16-bit storage.

    python benchmarks/pytorch_face.py --out benchmarks/results/pytorch_face
    python benchmarks/pytorch_face.py --scales 0.25 --out /tmp/face     # quick

On the paper's rig (``paper_two_planes``, the virtual calibration, its default targets, the area
model ``run`` solves), per scale, the median seconds of one forward and backward of a squared-error
loss through ``ProjectionModel``:

- eager, and ``torch.compile(model, fullgraph=True)`` (inductor; its first call, which compiles,
  timed apart);
- a batch of B patterns: ``model(P)`` with ``P`` ``(B, N, C)`` (one sparse product), against B
  calls one by one, and against ``torch.func.vmap(model)``;
- the model stored in bfloat16 (products accumulate in float32), with its largest error against
  float32.

Writes ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path

import torch
from common import machine, median_time, write_results

from torchproj.pipeline import calibrate_virtual, scene_targets
from torchproj.scene import load_scene
from torchproj.solve import ProjectionModel

BATCH = 8


def _step(model, patterns=None):
    model.zero_grad(set_to_none=True)
    if patterns is not None and patterns.grad is not None:
        patterns.grad = None
    image = model(patterns)
    (image - model.targets).pow(2).sum().backward()


def measure(scale: float, log=print) -> dict:
    scene = load_scene("paper_two_planes", scale=scale)
    cal = calibrate_virtual(scene, progress=False)
    model = ProjectionModel.from_calibration(cal, scene_targets(scene, rig=cal.rig))
    row = {"scale": scale, "columns": model.operator.shape[1], "rows": model.operator.shape[0],
           "nnz": model.operator.nnz, "eager_s": median_time(_step, model)}
    compiled = torch.compile(model, fullgraph=True)
    t0 = time.perf_counter()
    _step(compiled)
    row["compile_first_call_s"] = time.perf_counter() - t0
    row["compiled_s"] = median_time(_step, compiled)

    batch = torch.rand(BATCH, *model.patterns.shape, generator=torch.Generator().manual_seed(0)).requires_grad_(True)
    row["batch"] = BATCH
    row["batched_s"] = median_time(_step, model, batch)
    row["one_by_one_s"] = median_time(lambda: [_step(model, p.detach().requires_grad_(True)) for p in batch])
    row["vmap_s"] = median_time(lambda: (torch.func.vmap(model)(batch) - model.targets).pow(2).sum().backward())

    half = copy.deepcopy(model).to(torch.bfloat16)
    row["bfloat16_s"] = median_time(_step, half)
    with torch.no_grad():
        row["bfloat16_max_error"] = float((half().float() - model()).abs().max())
    log(f"scale {scale}: eager {row['eager_s']:.3f} s, compiled {row['compiled_s']:.3f} s (first call "
        f"{row['compile_first_call_s']:.1f} s); batch of {BATCH} {row['batched_s']:.3f} s against "
        f"{row['one_by_one_s']:.3f} s one by one and {row['vmap_s']:.3f} s through vmap; bfloat16 "
        f"{row['bfloat16_s']:.3f} s, error {row['bfloat16_max_error']:.2g}")
    return row


def markdown(rows: list[dict]) -> str:
    lines = [f"Machine: {machine()}. Median seconds of one forward + backward of a squared-error loss through "
             "ProjectionModel (paper_two_planes, area model).", "",
             "| scale | columns / nnz | eager | compiled (first call) | batch of 8: model(P) / one by one / vmap "
             "| bfloat16 (max error) |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scale']} | {r['columns']} / {r['nnz']} | {r['eager_s']:.3f} | {r['compiled_s']:.3f} "
                     f"({r['compile_first_call_s']:.1f}) | {r['batched_s']:.3f} / {r['one_by_one_s']:.3f} / "
                     f"{r['vmap_s']:.3f} | {r['bfloat16_s']:.3f} ({r['bfloat16_max_error']:.2g}) |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scales", type=float, nargs="+", default=[0.25, 1.0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/pytorch_face"))
    args = parser.parse_args(argv)
    rows = [measure(s) for s in args.scales]
    write_results(args.out, {"machine": machine(), "rows": rows}, markdown(rows))
    print(markdown(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
