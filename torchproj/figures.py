"""PNG summaries a person can check at a glance (matplotlib, off-screen).

Figures are matplotlib ``Figure`` objects written straight to files, never pyplot's: importing this
module leaves the user's backend (a notebook's, a window's) as it was.
"""

from __future__ import annotations

import os

import matplotlib as mpl
import numpy as np
import torch
from matplotlib.figure import Figure

from .core.conventions import to_numpy

__all__ = ["decode_summary", "calibration_summary", "run_overview", "depth_selectivity", "positioning_feedback"]


TITLE_PT, LABEL_PT, DPI = 11, 9, 110  # readable at a glance on a laptop screen


def _save(fig: Figure, path: str | os.PathLike, dpi: int = DPI) -> None:
    """``fig`` as a PNG at ``dpi``. zlib level 3, not Pillow's 6: on the default run's overview (1452 x
    1188) 0.09 s against 0.20 s to encode, and a file no larger (1.52 against 1.55 MB)."""
    fig.savefig(path, dpi=dpi, pil_kwargs={"compress_level": 3})


def _shown(data: np.ndarray, ax, dpi: int = DPI) -> np.ndarray:
    """``data`` :math:`(H, W)` or :math:`(H, W, C)` averaged over blocks of pixels down to no fewer than
    the panel ``ax`` shows, NaN left out of each mean (NaN where a whole block is).

    A PNG holds no more detail than its panel can show, and matplotlib draws a 1500 x 1100 image into
    a 480-pixel panel several times slower than one of the panel's own size (eight such panels: 0.85
    against 0.18 s). Averaging, not picking every k-th pixel, keeps fine patterns from aliasing.
    """
    box = ax.get_position()
    width, height = ax.figure.get_size_inches()
    k = int(min(data.shape[0] / max(box.height * height * dpi, 1), data.shape[1] / max(box.width * width * dpi, 1)))
    if k < 2:
        return data
    h, w = -(-data.shape[0] // k) * k, -(-data.shape[1] // k) * k
    padded = np.full((h, w, *data.shape[2:]), np.nan)
    padded[:data.shape[0], :data.shape[1]] = data
    blocks = padded.reshape(h // k, k, w // k, k, *data.shape[2:])
    known = ~np.isnan(blocks)
    count = known.sum((1, 3))
    total = np.where(known, blocks, 0.0).sum((1, 3))
    return np.divide(total, count, out=np.full(total.shape, np.nan), where=count > 0)


def _map_panel(ax, data, title, cmap="viridis", label=None, **kw):
    im = ax.imshow(np.ma.masked_invalid(_shown(data, ax)), cmap=cmap, interpolation="nearest", **kw)
    ax.set_title(title, fontsize=TITLE_PT)
    ax.set_xticks([])
    ax.set_yticks([])
    cb = ax.figure.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
    cb.ax.tick_params(labelsize=LABEL_PT)
    if label:
        cb.set_label(label, fontsize=LABEL_PT)


def decode_summary(path: str | os.PathLike, prj_xy: torch.Tensor, contrast: torch.Tensor,
                   points: torch.Tensor | None = None, title: str = "") -> None:
    """Decoded projector x and y per camera pixel, the contrast (white - black), and depth."""
    n = 4 if points is not None else 3
    fig = Figure(figsize=(4.2 * n, 3.6))
    axes = fig.subplots(1, n)
    _map_panel(axes[0], to_numpy(prj_xy[..., 0]), "projector x (column)", label="px")
    _map_panel(axes[1], to_numpy(prj_xy[..., 1]), "projector y (row)", label="px")
    _map_panel(axes[2], to_numpy(contrast), "white - black (decoding confidence)", cmap="gray")
    if points is not None:
        _map_panel(axes[3], to_numpy(points[..., 2]), "triangulated depth z", cmap="turbo",
                   label="calibration units")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    _save(fig, path, 90)


def calibration_summary(path: str | os.PathLike, rows: list[dict], title: str = "") -> None:
    """One row per (state, projector): decoded x, decoded y, error against the truth, response fit.

    Each row dict holds ``label``, ``prj_xy`` (H, W, 2), ``error`` (H, W) pixels or None (then
    ``valid`` (H, W), the decoded mask, is shown if given), and for the response ``levels``,
    ``measured`` (L, C), ``response`` (the fitted :class:`~torchproj.calib.ResponseCurve`) and
    optionally ``true_b``.
    """
    fig = Figure(figsize=(17, 3.4 * len(rows)))
    axes = fig.subplots(len(rows), 4, squeeze=False)
    # One error scale for every row (they are compared), at the 99th percentile of the errors: a fixed
    # 0-0.5 px scale left maps of 0.05 px errors nearly black. numpy's quantile selects where torch's
    # sorts (a full-size map: 14 against 100 ms, the same value), and takes any number of them.
    errors = [to_numpy(row["error"][torch.isfinite(row["error"])]) for row in rows if row.get("error") is not None]
    top = max((float(np.quantile(e, 0.99)) for e in errors if e.size), default=0.5)
    for ax_row, row in zip(axes, rows):
        _map_panel(ax_row[0], to_numpy(row["prj_xy"][..., 0]), f"{row['label']}: projector x", label="px")
        _map_panel(ax_row[1], to_numpy(row["prj_xy"][..., 1]), f"{row['label']}: projector y", label="px")
        if row.get("error") is not None:
            _map_panel(ax_row[2], to_numpy(row["error"]), "|decoded - true| (sub-pixel)", cmap="magma",
                       label="projector px", vmin=0, vmax=max(top, 1e-3))
        elif row.get("valid") is not None:
            valid = row["valid"]
            _map_panel(ax_row[2], to_numpy(valid.float()), f"decoded ({float(valid.float().mean()):.1%} of the camera)",
                       cmap="gray", vmin=0, vmax=1)
        else:
            ax_row[2].axis("off")
        ax = ax_row[3]
        if row.get("levels") is not None:
            x = torch.linspace(0, 1, 200)
            response = row["response"]
            ax.plot(row["levels"], row["measured"][:, 0], "o", ms=3, label="measured (median)")
            ax.plot(to_numpy(x), to_numpy(response(x[None, None])[0, 0]), "-",
                    label=f"fit a x^b + c, b={float(response.b[0]):.3f}")
            if row.get("true_b") is not None:
                ax.plot(to_numpy(x), to_numpy(x) ** row["true_b"], "--", label=f"true x^{row['true_b']:.2f}")
            ax.set_xlabel("pattern value x", fontsize=LABEL_PT)
            ax.set_ylabel("relative light (white - black = 1)", fontsize=LABEL_PT)
            ax.legend(fontsize=LABEL_PT)
            ax.set_title("response (normalised by white - black)", fontsize=TITLE_PT)
        else:
            ax.axis("off")
    if title:
        fig.suptitle(title, fontsize=TITLE_PT + 1)
    fig.tight_layout()
    _save(fig, path)


def _lit_box(pattern: torch.Tensor, keep: float = 0.6) -> tuple[int, int, int, int]:
    """``(y0, y1, x0, x1)``: the part of a :math:`(C, H, W)` pattern to draw, the box of its cells
    that are not black with a margin of a tenth of its side, or the whole image where that box spans
    more than ``keep`` of both sides. A projector that reaches only a small object lights a few
    dozen cells of its image, which drawn whole are a speck in a black panel."""
    height, width = pattern.shape[-2:]
    lit = (pattern > 0).any(0)
    if not lit.any():
        return 0, height, 0, width
    ys, xs = torch.nonzero(lit, as_tuple=True)
    y0, y1, x0, x1 = int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1
    if y1 - y0 > keep * height and x1 - x0 > keep * width:
        return 0, height, 0, width
    dy, dx = max(1, (y1 - y0) // 10), max(1, (x1 - x0) // 10)
    return max(0, y0 - dy), min(height, y1 + dy), max(0, x0 - dx), min(width, x1 + dx)


def run_overview(path: str | os.PathLike, patterns: list[torch.Tensor], projector_names: list[str],
                 targets: list, title: str = "") -> None:
    """Projector patterns on top; one row per target: the target on the camera, the capture, the error.

    ``targets``: :class:`~torchproj.pipeline.TargetScore` per target; all three panels are cropped
    to the target's pixels, and every error map shares one colour scale. A pattern lit over a small
    part of its image is drawn cropped to it (:func:`_lit_box`), its title naming the cells. Where the top row has room
    beside the patterns, it lists the scores.
    """
    n_cols = max(3, len(patterns))
    fig = Figure(figsize=(4.4 * n_cols, 3.6 * (1 + len(targets))))
    axes = fig.subplots(1 + len(targets), n_cols, squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for j, (pat, name) in enumerate(zip(patterns, projector_names)):
        y0, y1, x0, x1 = _lit_box(pat)
        img = _shown(to_numpy(pat[:, y0:y1, x0:x1].permute(1, 2, 0)) / 255.0, axes[0, j])
        axes[0, j].imshow(img[..., 0] if img.shape[2] == 1 else img, cmap="gray", vmin=0, vmax=1,
                          interpolation="nearest")
        height, width = pat.shape[-2:]
        where = ("" if (y1 - y0, x1 - x0) == (height, width)
                 else f"\ncells {x0}-{x1 - 1} x {y0}-{y1 - 1} of {width} x {height}")
        axes[0, j].set_title(f"pattern for projector {name} (8-bit){where}", fontsize=TITLE_PT)
    if len(patterns) < n_cols:  # the room beside the patterns: the scores, so no panel is empty
        lines = ["scores (captured against target)", ""] + [
            f"{t.name}: {t.psnr_db:.1f} dB PSNR, SSIM {t.ssim:.2f}, crosstalk {t.crosstalk:.2f}" for t in targets]
        axes[0, n_cols - 1].text(0.0, 0.9, "\n".join(lines), fontsize=TITLE_PT, va="top", family="monospace",
                                 transform=axes[0, n_cols - 1].transAxes)
    errors = [(t.estimate - t.values).abs().mean(0, keepdim=True) for t in targets]
    # numpy's quantile selects (a partition), torch's sorts: the same value, a tenth of the time on a
    # million pixels
    top = max((float(np.quantile(to_numpy(e[0][t.covered]), 0.99)) for e, t in zip(errors, targets) if t.covered.any()),
              default=0.5)
    top = max(top, 1e-3)
    for row, (t, err) in enumerate(zip(targets, errors), start=1):
        ys, xs = torch.nonzero(t.covered, as_tuple=True)
        y0, y1, x0, x1 = int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1
        mask = t.covered[y0:y1, x0:x1]

        def crop(img):
            c = img[:, y0:y1, x0:x1].clone()
            c[:, ~mask] = float("nan")
            c = to_numpy(c.permute(1, 2, 0))
            return c[..., 0] if c.shape[2] == 1 else np.nan_to_num(c)

        for col, (img, panel_title) in enumerate([(t.values, f"target {t.name}"),
                                                  (t.estimate, f"captured: {t.psnr_db:.1f} dB, SSIM {t.ssim:.2f}")]):
            axes[row, col].imshow(_shown(crop(img), axes[row, col]), interpolation="nearest", cmap="gray", vmin=0,
                                  vmax=1)
            axes[row, col].set_title(panel_title, fontsize=TITLE_PT)
        axes[row, 2].axis("on")
        _map_panel(axes[row, 2], crop(err), f"|captured - target| (crosstalk {t.crosstalk:.2f})", cmap="magma",
                   label="error (target units, 1 = white)", vmin=0, vmax=top)
    if title:
        fig.suptitle(title, fontsize=TITLE_PT + 1)
    fig.tight_layout()
    _save(fig, path)


def depth_selectivity(path: str | os.PathLike, sweeps: dict, target_depths: dict[str, float] | None = None) -> None:
    """PSNR and SSIM of each target's image against the depth of the moved surface, one line per
    (method, target); dotted verticals at the depths where the targets belong.

    Args:
        sweeps: method label -> :class:`~torchproj.pipeline.DepthSweep`.
        target_depths: target name -> its depth in metres.
    """
    fig = Figure(figsize=(12, 4.2))
    axes = fig.subplots(1, 2)
    styles = ["-", "--", ":", "-."]
    colours = mpl.rcParams["axes.prop_cycle"].by_key()["color"]
    for m, (label, sweep) in enumerate(sweeps.items()):
        for k, name in enumerate(sweep.names):
            for ax, values in zip(axes, (sweep.psnr_db, sweep.ssim)):
                ax.plot(sweep.depths, values[:, k], styles[m % len(styles)], color=colours[k % len(colours)],
                        marker="o", markersize=3, label=f"{label}: image '{name}'")
    for ax, unit in zip(axes, ("PSNR (dB)", "SSIM")):
        for k, (name, z) in enumerate((target_depths or {}).items()):
            ax.axvline(z, color=colours[k % len(colours)], lw=0.8, alpha=0.6)
        ax.set_xlabel("depth of the moved surface (m)")
        ax.set_ylabel(unit)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle("Fig. 1: depth selectivity: each image should appear where it belongs (vertical lines) and fade elsewhere",
                 fontsize=10)
    fig.tight_layout()
    _save(fig, path, 110)


def positioning_feedback(path: str | os.PathLike, profiles: dict[str, dict], trials: list[dict]) -> None:
    """What guides a placement: the feedback (PSNR of the camera image against the target image) with
    the box moved from its goal along depth, across and vertically, and the best feedback so far in
    each trial.

    Args:
        profiles: position name -> :func:`~torchproj.pipeline.feedback_profile` output.
        trials: per trial, ``{"position", "trial", "history" (feedback per look), "rmse_mm"}``, and
            ``"coarse_looks"`` where looks 1 to that many scored the coarse feedback
            (:func:`~torchproj.experiments.place_by_feedback`): the best so far is the feedback's own,
            carried through them.
    """
    fig = Figure(figsize=(12, 8))
    axes = fig.subplots(2, 2)
    axes = axes.ravel()
    colours = mpl.rcParams["axes.prop_cycle"].by_key()["color"]
    names = list(profiles)
    keys = ("depth", "across", "vertical")
    for k, name in enumerate(names):
        prof = profiles[name]
        for ax, key in zip(axes[:3], keys):
            if key in prof:
                ax.plot(prof["offsets_mm"], prof[key], "-o", color=colours[k % len(colours)], markersize=3,
                        label=f"{name}")
    for ax, title in zip(axes[:3], ("moved along depth (world z)", "moved across (world x)",
                                    "moved vertically (world y, along the projectors' baseline)")):
        ax.set_xscale("symlog", linthresh=1.0)
        reach = max(abs(v) for prof in profiles.values() for v in prof["offsets_mm"]) if profiles else 1.0
        ticks = [t for t in (-reach, -10, -1, 0, 1, 10, reach) if abs(t) <= reach]
        ax.set_xticks(ticks, [f"{t:g}" for t in ticks])
        ax.axvline(0, color="grey", lw=0.8)
        ax.set_xlabel("displacement from the goal (mm, symmetric log scale)")
        ax.set_ylabel("feedback: PSNR against the target (dB)")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    styles = ("-", "--", ":", "-.")
    for t in trials:
        k = names.index(t["position"]) if t["position"] in names else 0
        # Colour by position, line style by trial: a position's trials had one colour and could not be told apart.
        own = np.asarray(t["history"], dtype=float)
        own[1:1 + t.get("coarse_looks", 0)] = -np.inf
        axes[3].plot(np.maximum.accumulate(own), color=colours[k % len(colours)], lw=1.4,
                     linestyle=styles[int(t["trial"]) % len(styles)],
                     label=f"{t['position']} #{t['trial']}: {t['rmse_mm']:.1f} mm")
    coarse = max((t.get("coarse_looks", 0) for t in trials), default=0)
    if coarse:
        axes[3].axvspan(1, 1 + coarse, color="grey", alpha=0.12, lw=0,
                        label="coarse looks (fewer pixels, their own scale: not drawn)")
    axes[3].set_xlabel("camera looks")
    axes[3].set_ylabel("best feedback so far (dB)")
    axes[3].set_title("placement trials (legend: scan RMSE)", fontsize=10)
    axes[3].grid(alpha=0.3)
    axes[3].legend(fontsize=7)
    fig.suptitle("Fig. 1: guidance by the projected image: how sharply the feedback peaks at the goal pose", fontsize=10)
    fig.tight_layout()
    _save(fig, path, 110)
