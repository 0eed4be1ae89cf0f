"""The cost of the image-space loss on the full-size rig: SSIM forward and backward, closed form against autograd.

    python benchmarks/ssim_speed.py --out benchmarks/results/ssim_speed

On the paper's full-size rig (grey, ``paper_two_planes``) and its RGB twin (``colour_two_planes``),
calibrated on the virtual rig with their default targets, each with an operator whose rows are
camera pixels: the median time of one forward and backward of

- ``SSIMLoss`` on the predicted images (the closed-form gradient ``solve_ssim`` uses);
- the same SSIM through autograd (``ssim`` with a reference that requires a gradient: plain torch
  ops, differentiable to any order);
- one whole ``ImageLoss`` step (prediction ``A p`` placed on the camera, SSIM, squared error, the
  PSNR hinge, and back through the sparse operator): what one ``solve_ssim`` iteration costs.

Writes ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from common import machine, median_time, write_results

from torchproj.metrics import SSIMLoss, ssim
from torchproj.pipeline import calibrate_virtual, scene_targets
from torchproj.scene import load_scene
from torchproj.solve import ImageLoss, ProjectionModel, solve_fista
from torchproj.transport import build_transport


def _backward(loss_fn, x):
    x = x.detach().requires_grad_(True)
    loss_fn(x).sum().backward()
    return x.grad


def measure(name: str, log=print) -> dict:
    scene = load_scene(name)
    cal = calibrate_virtual(scene, progress=False)
    op = build_transport(cal.states, scene_targets(scene, rig=cal.rig), merge=False)
    start = solve_fista(op, (0, 1), progress=False).patterns
    model = ProjectionModel(op, start=start)
    with torch.no_grad():
        prediction = model()
    closed_form = SSIMLoss(model.targets, model.mask)
    reference = model.targets.clone().requires_grad_(True)  # autograd through both images: the plain-torch path
    loss = ImageLoss(op, start)
    row = {"scene": name, "targets": int(model.targets.shape[0]), "channels": int(model.targets.shape[1]),
           "pixels_per_target": [int(m.sum()) for m in model.mask],
           "ssim_closed_form_s": median_time(_backward, closed_form, prediction),
           "ssim_autograd_s": median_time(_backward, lambda x: 1 - ssim(x, reference, model.mask), prediction),
           "image_loss_step_s": median_time(_backward, loss, start)}
    log(f"{name}: SSIM forward + backward {row['ssim_closed_form_s']:.3f} s closed form, "
        f"{row['ssim_autograd_s']:.3f} s autograd; one ImageLoss step {row['image_loss_step_s']:.3f} s")
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/ssim_speed"))
    args = parser.parse_args(argv)
    rows = [measure(name) for name in ("paper_two_planes", "colour_two_planes")]
    lines = ["# SSIM forward and backward on the full-size rig", "",
             f"`python benchmarks/ssim_speed.py` on {machine()}, torch {torch.__version__}; median of 5 after a warm-up.", "",
             "| scene | targets x channels | SSIM closed form (s) | SSIM autograd (s) | one ImageLoss step (s) |",
             "|---|---|---|---|---|"]
    lines += [f"| {r['scene']} | {r['targets']} x {r['channels']} | {r['ssim_closed_form_s']:.3f} | "
              f"{r['ssim_autograd_s']:.3f} | {r['image_loss_step_s']:.3f} |" for r in rows]
    text = "\n".join(lines) + "\n"
    write_results(args.out, {"command": "python benchmarks/ssim_speed.py", "machine": machine(),
                             "torch": torch.__version__, "rows": rows}, text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
