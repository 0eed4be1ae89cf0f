"""A video's frames at several depths: a batch of target sets solved together, then refined as one batch.

    python examples/video_frames.py                      # 8 frames, the paper's rig at quarter size, ~11 s
    python examples/video_frames.py --frames 16 --scale 0.5

Each frame asks for its own image for every target: on the paper's rig the near plane pans across
scikit-image's astronaut, the far one across its camera man (a scene of more targets: coffee, rocket,
chelsea). A script of a library user, in two steps:

1. Least squares for every frame in one FISTA (``torchproj.solve.solve_target_sets``): the frames'
   right-hand sides side by side, so each iteration is one sparse product with B times the columns.
2. All frames refined together on SSIM: the patterns as one ``(B, N, C)`` parameter,
   ``model(patterns)`` predicts ``(B, K, C, H, W)``, ``SSIMLoss`` and a ``PSNRBudget`` (each target
   within 1 dB of its least-squares PSNR) score the B x K images, and ``ClampedAdam`` keeps the box.

Then every frame's patterns are shown on the virtual rig and scored. Writes ``report.json`` (per
frame and target: PSNR and SSIM before and after step 2, and the seconds of each step) and
``frames.png`` (each frame's targets beside the rig's captures of the refined patterns) into ``--out``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

import torchproj
from torchproj.cli_options import positive_float, positive_int
from torchproj.core import TorchprojError, atomic_output, write_json
from torchproj.solve import projectable_patterns, solve_target_sets
from torchproj.transport import retarget_rhs


# One test image per target, the first two the paper's rig's near and far.
FRAME_IMAGES = ("astronaut", "camera", "coffee", "rocket", "chelsea")


def frame_images(frames: int, channels: int, targets: int = 2) -> list[list[torch.Tensor]]:
    """Per frame, one image per target: a window panning across a test image of its own."""
    if targets > len(FRAME_IMAGES):
        raise TorchprojError(f"the scene has {targets} targets, and this example pans across {len(FRAME_IMAGES)} "
                             "test images; give a scene with fewer targets")
    pictures = [torchproj.target_image(name, channels) for name in FRAME_IMAGES[:targets]]
    out = []
    for b in range(frames):
        crops = []
        for image in pictures:
            h, w = image.shape[1:]
            size = min(h, w) * 2 // 3
            x = round((w - size) * b / max(frames - 1, 1))
            crops.append(image[:, (h - size) // 2:(h - size) // 2 + size, x:x + size])
        out.append(crops)
    return out


def frames_figure(shown: list[list], path: Path) -> None:
    """Per frame (columns), each target's wanted image above the rig's capture of the refined patterns."""
    import matplotlib.pyplot as plt

    names = [score.name for score in shown[0]]
    fig, axes = plt.subplots(2 * len(names), len(shown), figsize=(2.4 * len(shown), 2.5 * 2 * len(names)),
                             squeeze=False, layout="constrained")
    for b, scores in enumerate(shown):
        for k, score in enumerate(scores):
            for row, (image, label) in enumerate(((score.values, "wanted"), (score.estimate, "captured"))):
                ax = axes[2 * k + row, b]
                ax.imshow(image.permute(1, 2, 0).squeeze(-1).clamp(0, 1).numpy(), cmap="gray", vmin=0, vmax=1)
                ax.set_xticks([]), ax.set_yticks([])
                title = f"frame {b}: {score.name}, {label}"
                if row:
                    title += f"\n{score.psnr_db:.1f} dB, SSIM {score.ssim:.3f}"
                ax.set_title(title, fontsize=9)
    fig.suptitle("Fig. 1: a video's frames at their depths, wanted and captured\n(refined patterns on the virtual rig)",
                 fontsize=11)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="paper_two_planes", help="a built-in scene or a YAML file (up to five targets)")
    parser.add_argument("--scale", type=positive_float, default=0.25,
                        help="resolution of camera and projectors (default 0.25)")
    parser.add_argument("--frames", type=positive_int, default=8, help="frames of the video (default 8)")
    parser.add_argument("--steps", type=positive_int, default=30,
                        help="Adam steps of the batched SSIM refinement (default 30)")
    parser.add_argument("--out", type=Path, default=Path("out/video_frames"))
    args = parser.parse_args(argv)
    try:
        return solve_and_score(args)
    except TorchprojError as exc:  # a scene or a value refused by name, not a traceback
        parser.error(str(exc))


def solve_and_score(args) -> int:
    scene = torchproj.load_scene(args.scene, scale=args.scale)
    calibration = torchproj.calibrate_virtual(scene)
    frames = [torchproj.scene_targets(scene, images, rig=calibration.rig)
              for images in frame_images(args.frames, scene.camera.channels, len(scene.target_specs()))]
    # One operator for every channel: the frames' batched least squares (solve_target_sets) runs on it.
    model = torchproj.ProjectionModel.from_calibration(calibration, frames[0], start=None, colour_weights="grey")
    op, states = model.operator, calibration.states

    # 1. Least squares for all frames at once: only the right-hand side differs between frames.
    t0 = time.perf_counter()
    rhs = [retarget_rhs(op, states, targets).to(op.rhs) for targets in frames]
    start, _ = solve_target_sets(op, rhs, model.bounds, progress=False)
    least_squares_s = time.perf_counter() - t0

    # 2. SSIM refinement of the batch: one (B, N, C) parameter, one sparse product per step.
    t0 = time.perf_counter()
    wanted = torch.stack([op.to_camera(r / op.scale) for r in rhs])  # (B, K, C, H, W)
    flat = wanted.flatten(0, 1)  # the B x K images the losses score
    masks = model.mask.repeat(args.frames, 1, 1)
    patterns = torch.nn.Parameter(torch.stack(start))
    with torch.no_grad():
        budget = torchproj.PSNRBudget(flat, masks, reference=model(patterns).flatten(0, 1), psnr_drop=1.0)
    ssim_loss = torchproj.SSIMLoss(flat, masks)
    optimizer = torchproj.ClampedAdam([patterns], lr=0.01, bounds=model.bounds)
    for _ in range(args.steps):
        optimizer.zero_grad()
        predicted = model(patterns).flatten(0, 1)
        (ssim_loss(predicted) + budget(predicted)).mean().backward()
        optimizer.step()
    refine_s = time.perf_counter() - t0

    rows, shown_scores = [], []
    world = torchproj.shown_world(calibration)  # the world as shown: a show: section's changes since calibration
    for b, targets in enumerate(frames):
        scores = {}
        for name, p in (("least_squares", start[b]), ("refined", patterns[b].detach())):
            shown = projectable_patterns(op, p, model.bounds, calibration.responses)[1]
            scores[name] = torchproj.evaluate_patterns(world, shown, targets, scale=op.scale, paper=False).targets
        shown_scores.append(scores["refined"])
        for k, target in enumerate(targets):
            before, after = scores["least_squares"][k], scores["refined"][k]
            rows.append({"frame": b, "target": target.name, "psnr_db": after.psnr_db, "ssim": after.ssim,
                         "least_squares": {"psnr_db": before.psnr_db, "ssim": before.ssim}})
            print(f"frame {b} {target.name}: PSNR {before.psnr_db:.2f} -> {after.psnr_db:.2f} dB, "
                  f"SSIM {before.ssim:.3f} -> {after.ssim:.3f}")
    report = {"scene": scene.name, "scale": args.scale, "frames": args.frames, "steps": args.steps,
              "least_squares_s": round(least_squares_s, 2), "refine_s": round(refine_s, 2), "targets": rows,
              "evaluation": torchproj.pipeline.EVALUATION}
    with atomic_output(args.out) as stage:
        write_json(stage / "report.json", report)
        frames_figure(shown_scores, stage / "frames.png")
    print(f"{args.frames} frames: least squares {least_squares_s:.1f} s, SSIM refinement {refine_s:.1f} s "
          f"({args.steps} steps); wrote {args.out}/report.json and frames.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
