"""Patterns trained like a network: an SSIM loss on the predicted camera images, Adam, a scheduler.

    python examples/train_patterns.py                  # the paper's rig at half resolution, ~1 minute on 2 cores
    python examples/train_patterns.py --scale 1        # the full-size rig
    python examples/train_patterns.py --loss kornia    # kornia's SSIM (11x11 Gaussian window) instead
    python examples/train_patterns.py --device cuda    # on a GPU (the default where torch sees one)

A training-style script as a user of the library would write it: calibrate the virtual rig (or
load a bench's bundle with ``torchproj.load_bundle``), build the image-space model, run a clamped
Adam loop with a learning-rate schedule on an SSIM loss of what the camera will see, checkpoint
with ``state_dict`` (and resume from it), then score the patterns on the virtual rig's captures.
Writes ``report.json`` (per target: psnr_db, ssim, crosstalk, for the least-squares start and the
trained patterns), ``overview.png``, ``patterns/`` and ``checkpoint.pt`` into ``--out``.

``--loss torchproj`` (default) optimises the SSIM the evaluation reports (scikit-image's definition,
:func:`torchproj.metrics.ssim`); ``--loss kornia`` optimises kornia's, a different window and
border (docs/python.md "Training patterns like a network" compares the two).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

import torchproj
from torchproj.cli_options import positive_float, positive_int
from torchproj.core import TorchprojError, atomic_output, check_number, write_image, write_json
from torchproj.figures import run_overview


def kornia_ssim_loss(targets: torch.Tensor, masks: torch.Tensor):
    """kornia's SSIM loss over each target's masked pixels (an off-the-shelf loss plugged in)."""
    import kornia

    weight = masks[:, None].to(targets.dtype)

    def loss(prediction):
        ssim_map = kornia.metrics.ssim(prediction * weight, targets * weight, window_size=11)
        return 1 - (ssim_map * weight).sum((1, 2, 3)) / (weight.sum((1, 2, 3)) * targets.shape[1])

    return loss


def train(model, loss_name: str, steps: int, lr: float, l2_weight: float, checkpoint: Path, log=print,
          psnr_drop: float = 1.0) -> list:
    """Clamped Adam with cosine learning-rate decay on (1 - SSIM) + w * relative squared error, each
    target held within ``psnr_drop`` dB of its starting PSNR (the loss of ``torchproj.solve_ssim``)."""
    ssim_loss = (torchproj.SSIMLoss(model.targets, model.mask) if loss_name == "torchproj"
                 else kornia_ssim_loss(model.targets, model.mask))
    # Each target's PSNR held within psnr_drop of the start: without it the mean loss trades one target
    # away for the other.
    with torch.no_grad():
        budget = torchproj.PSNRBudget(model.targets, model.mask, reference=model(), psnr_drop=psnr_drop)
    optimizer = torchproj.ClampedAdam(model.parameters(), lr=lr, bounds=model.bounds)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=steps)
    history = []
    for step in range(1, steps + 1):
        optimizer.zero_grad()
        prediction = model()
        ratio = budget.ratio(prediction)  # once: the squared-error term and the budget share it
        loss = (ssim_loss(prediction) + l2_weight * ratio + budget.hinge(ratio)).mean()
        loss.backward()
        optimizer.step()
        scheduler.step()
        history.append(loss.item())
        if step % 10 == 0 or step == steps:
            torch.save({"model": model.state_dict(), "optimizer": optimizer.state_dict(),
                        "scheduler": scheduler.state_dict(), "step": step}, checkpoint)
            log(f"step {step:3d}  loss {loss.item():.4f}  lr {scheduler.get_last_lr()[0]:.4f}")
    return history


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="paper_two_planes", help="a built-in scene or a YAML file")
    parser.add_argument("--scale", type=positive_float, default=0.5,
                        help="resolution of camera and projectors (default 0.5)")
    parser.add_argument("--steps", type=positive_int, default=40, help="Adam steps (default 40)")
    parser.add_argument("--lr", type=positive_float, default=0.02, help="initial learning rate (default 0.02)")
    parser.add_argument("--l2-weight", type=float, default=0.1, help="weight of the relative squared error (0.1)")
    parser.add_argument("--loss", choices=["torchproj", "kornia"], default="torchproj")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu",
                        help="torch device (default: cuda where torch sees a GPU, else cpu)")
    parser.add_argument("--out", type=Path, default=Path("out/train_patterns"))
    args = parser.parse_args(argv)
    try:
        check_number(args.l2_weight, "--l2-weight")
        return train_and_score(args)
    except TorchprojError as exc:  # a scene, a device or a value refused by name, not a traceback
        parser.error(str(exc))


def train_and_score(args) -> int:
    t0 = time.perf_counter()
    scene = torchproj.load_scene(args.scene, scale=args.scale)
    calibration = torchproj.calibrate_virtual(scene, args.device)  # on a bench: torchproj.load_bundle("calib")
    targets = torchproj.scene_targets(scene, rig=calibration.rig)
    # Starts at the least-squares optimum; the model, its loss and the optimiser live on the device.
    model = torchproj.ProjectionModel.from_calibration(calibration, targets, device=args.device)
    # Patterns are scored in the world they are shown in: where a scene's show: section changed it after
    # calibration (paper_bumped), that world's; otherwise the calibration's own.
    world = torchproj.shown_world(calibration)
    before = torchproj.evaluate_patterns(world, model.to_patterns(), targets, scale=model.scale)
    print(f"calibrated and solved least squares in {time.perf_counter() - t0:.1f} s; training {args.steps} steps")

    with atomic_output(args.out) as stage:
        history = train(model, args.loss, args.steps, args.lr, args.l2_weight, stage / "checkpoint.pt")
        # Resume as a later script would: a fresh model of the same rig, its weights from the checkpoint.
        resumed = torchproj.ProjectionModel.from_calibration(calibration, targets, start=None, device=args.device)
        resumed.load_state_dict(torch.load(stage / "checkpoint.pt", map_location=args.device)["model"])
        patterns = resumed.to_patterns()
        after = torchproj.evaluate_patterns(world, patterns, targets, scale=resumed.scale)
        (stage / "patterns").mkdir()
        for projector, pattern in zip(scene.projectors, patterns):
            write_image(stage / "patterns" / f"{projector.name}.png", pattern.float() / 255)
        run_overview(stage / "overview.png", patterns, [p.name for p in scene.projectors], after.targets,
                     title=f"Fig. 1: train_patterns: scene {scene.name} at scale {args.scale}, {args.steps} Adam steps "
                           f"on {args.loss}'s SSIM")
        report = {"scene": scene.name, "scale": args.scale, "device": args.device, "loss": args.loss,
                  "steps": args.steps, "lr": args.lr,
                  "l2_weight": args.l2_weight, "loss_history": history, "seconds": round(time.perf_counter() - t0, 1),
                  "evaluation": torchproj.pipeline.EVALUATION,
                  "targets": [{**a.as_dict(), "least_squares": {"psnr_db": b.psnr_db, "ssim": b.ssim,
                                                                 "crosstalk": b.crosstalk}}
                              for a, b in zip(after.targets, before.targets)]}
        write_json(stage / "report.json", report)
    for a, b in zip(after.targets, before.targets):
        print(f"{a.name}: PSNR {b.psnr_db:.2f} -> {a.psnr_db:.2f} dB, SSIM {b.ssim:.3f} -> {a.ssim:.3f}, "
              f"crosstalk {b.crosstalk:.3f} -> {a.crosstalk:.3f}")
    print(f"wrote {args.out}/report.json, overview.png, patterns/, checkpoint.pt ({report['seconds']} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
