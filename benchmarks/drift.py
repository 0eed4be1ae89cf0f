"""A world that drifted from its calibration: the stale model, a full recalibration, the camera loop, the ceiling.

    python benchmarks/drift.py --out benchmarks/results/drift [--scenes paper_two_planes@0.25 suite-1-7 ...]
           [--captures 10] [--frames 1]
    python benchmarks/drift.py --noise --captures 6 --out benchmarks/results/drift   # camera noise: frames, relax
    python benchmarks/drift.py --moved-models --scenes box_cylinders@0.25 suite-1-7 \
           --kinds translation_mm rotation_deg camera_mm --out benchmarks/results/drift   # exact moves
    python benchmarks/drift.py --unchanged --out benchmarks/results/drift   # no change: the loop's own limit

Each scene is calibrated once as written. Then, per kind of change and two magnitudes (module
:mod:`torchproj.scene.show`; the first projector changes, or the camera), the scene is shown in the
changed world and scored on the rig's captures:

- ``stale``: the patterns solved on the calibration (what a run without the loop shows);
- ``loop@n``: ``torchproj run --refine`` after n captures of patterns per state (the first is of
  the stale patterns; the best captured iterate so far, by the loop's captured loss; PSNR on the
  model's rows as the loop's camera saw them, one frame each);
- ``kept``: the loop's kept patterns after all captures, captured again and scored as ``run`` scores;
- ``recalibrated``: the changed world calibrated anew (184 captures per state on the paper's rig)
  and solved;
- ``ceiling``: the changed world's exact light (``--ceiling``), the best any model could reach.

``moved_cells``: the simulator's truth of how far the change moved each camera pixel's projector
coordinates (median over lit pixels, the most moved projector and state): the model's columns are
that far from where the light now lands. A black frame per state is captured at show time for every
method (room light that changed is not scored as error).

Writes ``results.json``, ``results.md`` and ``drift.png`` (per scene, mean PSNR over targets against
captures per state, stale to ceiling, and the SSIM gained; ``--chart`` redraws it from results.json).
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import statistics
import time
from pathlib import Path

import torch
import yaml
from common import machine, write_results
from matplotlib.figure import Figure

from torchproj.pipeline import calibrate_virtual, run_virtual
from torchproj.scene import builtin_config, parse_scene, scale_config, shown_scene
from torchproj.scene.procedural import parse_suite_name, procedural_config
from torchproj.sim import VirtualRig

SCENES = ("paper_two_planes@0.25", "box_cylinders@0.25", "suite-1-7")
CHANGES = {  # kind -> (small, large)
    "gain": (1.1, 1.3),
    "exponent": (1.05, 1.15),
    "ambient": (0.03, 0.1),  # W/m^2 added to the scene's room light
    "translation_mm": (0.5, 2.0),
    "rotation_deg": (0.05, 0.2),
    "camera_mm": (0.5, 2.0),
}


def scene_data(spec: str) -> dict:
    """A scene's YAML data: ``name@scale`` for a built-in one, or a procedural suite name."""
    suite = parse_suite_name(spec)
    if suite is not None:
        return procedural_config(*suite)
    name, _, scale = spec.partition("@")
    data = yaml.safe_load(builtin_config(name).read_text())
    data["name"] = spec
    return scale_config(data, float(scale)) if scale else data


def show_section(data: dict, kind: str, value: float) -> dict | None:
    first = data["projectors"][0].get("name", "projector0")
    if kind == "none":
        return None
    if kind in ("gain", "exponent"):
        return {"projectors": {first: {kind: value}}}
    if kind == "ambient":
        return {"ambient": data.get("ambient", 0.0) + value}
    if kind == "translation_mm":
        return {"projectors": {first: {"translation_mm": [value, 0, 0]}}}
    if kind == "rotation_deg":
        return {"projectors": {first: {"rotation_deg": [0, value, 0]}}}
    return {"camera": {"translation_mm": [value, 0, 0]}}


def moved_cells(scene, shown) -> float:
    """The largest, over states and projectors, median distance (cells) between a lit pixel's projector
    coordinates in the calibrated world and in the shown one (the simulator's truth)."""
    before, after = VirtualRig(scene), VirtualRig(shown)
    worst = 0.0
    for state in scene.states:
        a, b = before.geometry(state.name), after.geometry(state.name)
        for j in range(len(scene.projectors)):
            d = (a.prj_xy[j] - b.prj_xy[j]).norm(dim=-1)
            d = d[torch.isfinite(d)]
            if len(d):
                worst = max(worst, float(d.median()))
    return worst


def loop_curve(history: list[dict], counts, score: str = "psnr_db") -> dict:
    """Mean row PSNR (or SSIM) of the best captured iterate (by loss) among the first n captures, per n."""
    out = {}
    for n in counts:
        best = min(history[:n], key=lambda h: h["loss"])
        out[n] = statistics.fmean(best[score])
    return out


def run_case(data, cal, kind, value, captures: int, frames: int) -> dict:
    d = copy.deepcopy(data)
    show = show_section(data, kind, value)
    d.pop("show", None)  # a scene's own show section (sphere_three_projectors has one) is not "none"
    if show is not None:
        d["show"] = show
    scene = parse_scene(d, name=d["name"])
    t0 = time.perf_counter()
    result = run_virtual(scene, calibration=cal, refine=captures - 1, refine_frames=frames, ceiling=True,
                         progress=False)
    seconds = time.perf_counter() - t0
    refine = result.report["refine"]
    counts = [n for n in (1, 2, 3, 5, 10, captures) if n <= captures]
    plain = shown_scene(scene)
    recal = run_virtual(plain, calibration=calibrate_virtual(plain), progress=False)
    targets = result.report["targets"]
    steps = [h["solve_s"] for h in refine["history"] if "solve_s" in h]
    return {
        "kind": kind, "value": value, "show": show,
        "moved_cells": round(moved_cells(cal.rig.scene, plain), 3) if show is not None else 0.0,
        "stale": [s["psnr_db"] for s in refine["start"]],
        "kept": [t["psnr_db"] for t in targets],
        "kept_ssim": [t["ssim"] for t in targets],
        "stale_ssim": [s["ssim"] for s in refine["start"]],
        "recalibrated": [t["psnr_db"] for t in recal.report["targets"]],
        "ceiling": [t["ceiling"]["psnr_db"] for t in targets],
        "ceiling_ssim": [t["ceiling"]["ssim"] for t in targets],
        "loop": {str(n): v for n, v in loop_curve(refine["history"], counts).items()},
        "loop_ssim": {str(n): v for n, v in loop_curve(refine["history"], counts, "ssim").items()},
        "best_capture": refine["best_capture"],
        "update_s": round(statistics.fmean(steps), 4) if steps else 0.0,
        "run_s": round(seconds, 2),
    }


def markdown(result: dict) -> str:
    lines = [f"# Drift: stale model, camera loop, recalibration, ceiling ({result['machine']})", "",
             f"Captures per state in the loop: up to {result['captures']} ({result['frames']} frame each); mean PSNR "
             "over targets (dB). `loop@n`: best captured iterate among the first n captures (row PSNR as the loop's "
             "camera saw it). `kept`: the loop's kept patterns captured again and scored as run scores. `worst gap`: "
             "the largest per-target ceiling minus kept. `moved`: the simulator's median shift of projector "
             "coordinates (cells) the change caused.", ""]
    for scene, cases in result["scenes"].items():
        lines += [f"## {scene}", "", "| change | moved (cells) | stale | loop@2 | loop@5 | loop@10 | kept | recalibrated | "
                  "ceiling | worst gap (dB) | update (s) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
        for c in cases:
            mean = statistics.fmean
            gap = max(ce - k for ce, k in zip(c["ceiling"], c["kept"]))
            lines.append(f"| {c['kind']} {c['value']:g} | {c['moved_cells']:.2f} | {mean(c['stale']):.2f} | "
                         f"{c['loop'].get('2', float('nan')):.2f} | {c['loop'].get('5', float('nan')):.2f} | "
                         f"{c['loop'].get('10', float('nan')):.2f} | {mean(c['kept']):.2f} | "
                         f"{mean(c['recalibrated']):.2f} | {mean(c['ceiling']):.2f} | {gap:+.2f} | {c['update_s']:.3f} |")
        lines.append("")
    return "\n".join(lines)


def chart(result: dict, path: Path) -> None:
    """Top: each large change's mean PSNR against captures, as far below the shown world's ceiling
    (the first capture is the stale patterns'). Bottom: SSIM gained since the first capture, as the
    loop's camera saw its rows (row SSIM counts pixels outside the rows as black, so only its changes
    compare with the scores run gives), beside what the ceiling holds above the stale patterns."""
    scenes = result["scenes"]
    fig = Figure(figsize=(5.2 * len(scenes), 8.4), dpi=120)
    for i, (scene, cases) in enumerate(scenes.items()):
        top, bottom = (fig.add_subplot(2, len(scenes), row * len(scenes) + i + 1) for row in (0, 1))
        for c in cases:
            if c["kind"] == "none" or c["value"] != CHANGES[c["kind"]][1]:
                continue
            xs = [int(n) for n in c["loop"]]
            ceiling = statistics.fmean(c["ceiling"])
            line = top.plot(xs, [v - ceiling for v in c["loop"].values()], marker="o",
                            label=f"{c['kind']} {c['value']:g}")[0]
            top.axhline(statistics.fmean(c["stale"]) - ceiling, color=line.get_color(), ls=":", lw=0.8)
            first = c["loop_ssim"]["1"]
            bottom.plot(xs, [v - first for v in c["loop_ssim"].values()], marker="o", color=line.get_color(),
                        label=f"{c['kind']} {c['value']:g}")
            bottom.axhline(statistics.fmean(c["ceiling_ssim"]) - statistics.fmean(c["stale_ssim"]),
                           color=line.get_color(), ls=":", lw=0.8)
        top.axhline(0, color="k", lw=0.8)
        top.axhline(-0.3, color="grey", ls="--", lw=0.8)
        top.set_ylabel("mean PSNR minus the shown world's ceiling (dB)")
        bottom.axhline(0, color="k", lw=0.8)
        bottom.set_ylabel("mean SSIM gained since the first capture")
        for ax in (top, bottom):
            ax.set_xscale("log")
            ax.set_xlabel("captures of patterns per state")
            ax.set_title(scene)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
    fig.suptitle("Camera in the loop after a change (large magnitude). Top: dotted, the stale patterns; dashed, "
                 "0.3 dB. Bottom: dotted, the ceiling's SSIM above the stale patterns'")
    fig.tight_layout()
    fig.savefig(path)


NOISE_SCENE = "paper_two_planes@0.25"
NOISY_CAMERA = {"full_well": 2000, "read": 0.01}  # a tenth of the shipped camera's well, five times its read noise
LOOPS = ((1, 1.0), (4, 1.0), (1, 0.5), (4, 0.5))  # (frames averaged per capture, relax)


def noise_study(captures: int) -> dict:
    """How the loop copes with camera noise: the shipped camera and a noisy one, a 30% brighter lamp,
    frames averaged per step and the share of each defect taken (relax)."""
    out = {}
    for camera in ("shipped", "noisy"):
        data = scene_data(NOISE_SCENE)
        if camera == "noisy":
            data["camera"]["noise"] = dict(NOISY_CAMERA)
        cal = calibrate_virtual(parse_scene(data, name=data["name"]))
        rows = []
        for frames, relax in LOOPS:
            d = copy.deepcopy(data)
            d["show"] = show_section(data, "gain", CHANGES["gain"][1])
            scene = parse_scene(d, name=d["name"])
            report = run_virtual(scene, calibration=cal, refine=captures - 1, refine_frames=frames,
                                 refine_relax=relax, ceiling=True, progress=False).report
            rows.append({"frames": frames, "relax": relax,
                         "stale": statistics.fmean(s["psnr_db"] for s in report["refine"]["start"]),
                         "kept": statistics.fmean(t["psnr_db"] for t in report["targets"]),
                         "ceiling": statistics.fmean(t["ceiling"]["psnr_db"] for t in report["targets"]),
                         "curve": [statistics.fmean(h["psnr_db"]) for h in report["refine"]["history"]],
                         "best_capture": report["refine"]["best_capture"]})
            print("noise", camera, rows[-1], flush=True)
        out[camera] = rows
    return out


def noise_markdown(study: dict) -> list[str]:
    lines = ["## Camera noise", "",
             f"{NOISE_SCENE}, the first projector's lamp 30% brighter; `noisy`: full well "
             f"{NOISY_CAMERA['full_well']} electrons and read noise {NOISY_CAMERA['read']} (the shipped camera: 20000 and "
             "0.002). Mean PSNR over targets (dB); `per capture`: what the loop's camera saw of each iterate (noisy "
             "itself); `kept`: the kept patterns captured again with one frame, as run scores.", "",
             "| camera | frames per step | relax | stale | per capture | kept | ceiling |", "|---|---|---|---|---|---|---|"]
    for camera, rows in study.items():
        for r in rows:
            lines.append(f"| {camera} | {r['frames']} | {r['relax']:g} | {r['stale']:.2f} | "
                         + " / ".join(f"{v:.2f}" for v in r["curve"]) + f" | {r['kept']:.2f} | {r['ceiling']:.2f} |")
    return lines + [""]


def exact_moves(cal, world, targets, op) -> torch.Tensor:
    """Each row's true move per projector (cells): the shown world's projector coordinates at its pixel
    less the calibrated world's (the simulator's truth; 0 where either is unknown)."""
    moves = torch.zeros(op.shape[0], len(op.projector_sizes), 2, dtype=torch.float64)
    for k, target in enumerate(targets):
        rows = op.row_target == k
        before, after = cal.rig.geometry(target.state), world.rig.geometry(target.state)
        for j in range(len(op.projector_sizes)):
            true = torch.nan_to_num(after.prj_xy[j] - before.prj_xy[j]).reshape(-1, 2)
            moves[rows, j] = true[op.row_pixel[rows]].double()
    return moves


MOVED_MODELS = ("calibrated", "rows moved", "rebuilt", "shares carried", "interval")


@contextlib.contextmanager
def _interval_only():
    """``carry_shares`` with no bin of its table read: the even interval alone (the model before the table)."""
    from torchproj.pipeline import register

    before = register._TABLE_MIN
    register._TABLE_MIN = 10**12
    try:
        yield
    finally:
        register._TABLE_MIN = before


def _moved_model(name: str, ops, moves, remodel):
    """One of :data:`MOVED_MODELS` given each row's move: the calibrated operator, its rows moved, or the
    transport rebuilt from the moved maps with the cell shares dropped or carried (:class:`Reregister`;
    ``interval``: carried through the even interval alone)."""
    if name == "calibrated":
        return ops
    if name == "rows moved":
        return [o.with_rows_moved(moves) for o in ops]
    if name == "interval":
        with _interval_only():
            return remodel._rebuilt(ops[0], moves, carry=True)
    return remodel._rebuilt(ops[0], moves, carry=name == "shares carried")


def _share_misses(cal, world, fresh) -> dict[str, list[float]]:
    """rms of the shares carried through the simulator's move against those a recalibration of the
    shown world measured (``fresh``), across the edges and of the checkerboard's, on the pixels whose new
    cell is the recalibration's, per projector that moved: ``{"table": [...], "interval": [...]}``."""
    from torchproj.pipeline.register import carry_shares

    out = {"table": [], "interval": []}
    for state, c in cal.states.items():
        for j in range(len(c.prj_xy)):
            move = torch.nan_to_num(world.rig.geometry(state).prj_xy[j] - cal.rig.geometry(state).prj_xy[j])
            if not bool(move.abs().gt(0).any()) or c.shares is None:
                continue
            truth = fresh.states[state].shares[j]
            for label in out:
                with _interval_only() if label == "interval" else contextlib.nullcontext():
                    carried = carry_shares(c.shares[j], c.prj_xy[j], c.prj_xy[j] + move, c._slope(j),
                                           c.projector_sizes[j])
                same = (carried.cell == truth.cell).all(-1) & (truth.cell >= 0).all(-1)
                miss = (carried.across - truth.across)[same]
                checker = (carried.checker - truth.checker)[same]
                out[label].append([round(float(miss[torch.isfinite(miss)].pow(2).mean().sqrt()), 4),
                                   round(float(checker[torch.isfinite(checker)].pow(2).mean().sqrt()), 4)])
    return out


def moved_models(specs, kinds) -> dict:
    """What the loop's moved models can reach at best: each given the simulator's exact moves, solved
    once (FISTA) and scored in the shown world, beside the calibrated model and the ceiling; first in
    the world as calibrated (no move: what dropping or carrying the shares costs there)."""
    from torchproj.pipeline import evaluate_patterns, scene_targets, shown_world
    from torchproj.pipeline.register import Reregister
    from torchproj.pipeline.run import build_operators
    from torchproj.solve import make_patterns

    out = {}
    for spec in specs:
        data = scene_data(spec)
        cal = calibrate_virtual(parse_scene(data, name=data["name"]))
        # First the world as calibrated: what each form costs where nothing moved.
        for kind in ("none", *kinds):
            value = CHANGES[kind][1] if kind in CHANGES else 0.0
            d = copy.deepcopy(data)
            show = show_section(data, kind, value)
            d.pop("show", None)
            if show is not None:
                d["show"] = show
            scene = parse_scene(d, name=d["name"])
            world = shown_world(cal, scene)
            targets = scene_targets(scene, None, cal.rig)
            ops = build_operators(cal.states, targets, footprint="area", merge=False, colour_weights="channel",
                                  device="cpu")
            moves = exact_moves(cal, world, targets, ops[0])
            remodel = Reregister(cal.states, targets, footprint="area", colour_weights="channel")
            remodel.calibrated = ops
            row = {}
            for name in MOVED_MODELS:
                model = _moved_model(name, ops, moves, remodel)
                _, _, patterns = make_patterns(model, "fista", (0.0, 1.0), cal.responses)
                row[name] = [t.psnr_db for t in evaluate_patterns(world, patterns, targets, scale=model[0].scale,
                                                                  paper=False).targets]
            ceiling = run_virtual(scene, calibration=cal, ceiling=True, progress=False).report["targets"]
            row["ceiling"] = [t["ceiling"]["psnr_db"] for t in ceiling]
            if kind in ("translation_mm", "rotation_deg"):
                row["share_rms"] = _share_misses(cal, world, calibrate_virtual(shown_scene(scene), progress=False))
            out[f"{spec} {kind} {value:g}"] = row
            print("moved models", spec, kind, {k: [round(v, 2) for v in vs] for k, vs in row.items() if k != "share_rms"},
                  row.get("share_rms", ""), flush=True)
    return out


def moved_markdown(study: dict) -> list[str]:
    lines = ["## The moved models with exact moves", "",
             "Each row's move taken from the simulator (no fit), the model solved once and scored in the shown world: "
             "PSNR per target (dB). What the loop's re-registration could reach at best with each form.", "",
             "`interval`: the shares carried through the even interval alone (no table). `share rms`: the carried "
             "shares' rms against what a recalibration of the shown world measures, across the edges / of the "
             "checkerboard, per projector that moved, table then interval.", "",
             "| case | calibrated (stale) | rows moved | rebuilt | rebuilt, shares carried | interval | ceiling | share rms |",
             "|---|---|---|---|---|---|---|---|"]
    for case, row in study.items():
        rms = row.get("share_rms")
        shares = "" if rms is None else "; ".join(
            f"{t[0]:.3f} / {t[1]:.3f} against {i[0]:.3f} / {i[1]:.3f}" for t, i in zip(rms["table"], rms["interval"]))
        lines.append(f"| {case} | " + " | ".join(" / ".join(f"{v:.2f}" for v in row[k]) if k in row else ""
                                                for k in (*MOVED_MODELS, "ceiling")) + f" | {shares} |")
    return lines + [""]


UNCHANGED_SCENES = ("sphere_three_projectors", "suite-1-7", "box_cylinders@0.25", "suite-5-6", "suite-7-3")


@contextlib.contextmanager
def noise_free_loop():
    """While inside, ``run_virtual``'s loop captures the expected light (no camera noise, no
    quantisation): where the loop's defect correction converges when nothing but the model is wrong."""
    import torchproj.pipeline.run as run_module

    real = run_module.rig_measure
    run_module.rig_measure = lambda world, ops, targets, frames=1: real(world, ops, targets, frames, noise=False)
    try:
        yield
    finally:
        run_module.rig_measure = real


def closed(start: float, end: float, ceiling: float) -> float | None:
    """The share of a target's gap to the ceiling closed, where it has one (0.05 dB or more)."""
    return (end - start) / (ceiling - start) if ceiling - start >= 0.05 else None


def summed_error(psnr_db: list[float], pixels: list[int]) -> float:
    """The loop's loss on a common scale: each target's mean squared error times its pixels, summed."""
    return sum(n * 10 ** (-p / 10) for p, n in zip(psnr_db, pixels))


def unchanged_study(specs, captures: int) -> dict:
    """The loop in the world it was calibrated in: what it wins of the gap between the calibrated
    model and the ceiling after 5 and ``captures`` captures per state, and where the same loop ends
    with noise-free captures (``captures`` of them): the fixed point of a loop whose gradient is the
    model's, which no number of captures passes."""
    out = {}
    for spec in specs:
        data = scene_data(spec)
        data.pop("show", None)
        scene = parse_scene(data, name=data["name"])
        cal = calibrate_virtual(scene)
        runs = {}
        for label, n, exact in (("loop@5", 5, False), (f"loop@{captures}", captures, False),
                                (f"noise-free@{captures}", captures, True)):
            with noise_free_loop() if exact else contextlib.nullcontext():
                runs[label] = run_virtual(scene, calibration=cal, refine=n - 1, ceiling=label == "loop@5",
                                          progress=False).report
        first = runs["loop@5"]
        pixels = [t["pixels"] for t in first["targets"]]
        row = {"targets": [t["name"] for t in first["targets"]], "pixels": pixels,
               "calibrated": [s["psnr_db"] for s in first["refine"]["start"]],
               "ceiling": [t["ceiling"]["psnr_db"] for t in first["targets"]]}
        for label, report in runs.items():
            row[label] = [t["psnr_db"] for t in report["targets"]]
        start, ceiling = summed_error(row["calibrated"], pixels), summed_error(row["ceiling"], pixels)
        row["summed_closed"] = {label: (start - summed_error(row[label], pixels)) / (start - ceiling)
                                if start > ceiling else None for label in runs}
        out[spec] = row
        print("unchanged", spec, {k: v for k, v in row.items() if k != "pixels"}, flush=True)
    return out


def unchanged_markdown(study: dict, captures: int) -> list[str]:
    labels = ["loop@5", f"loop@{captures}", f"noise-free@{captures}"]
    lines = ["## The world it was calibrated in", "",
             "PSNR per target (dB), scored as `run` scores; `calibrated`: the patterns solved on the calibration (the "
             "loop's start); `loop@n`: the loop's kept patterns after n captures per state; `noise-free@n`: the same "
             "loop with captures of the expected light (no noise, no quantisation), where a loop that follows the "
             "model's gradient converges; `closed`: the share of the gap to the ceiling won, per target below the "
             "ceiling by 0.05 dB or more, and of the summed squared error (the loop's loss).", "",
             "| scene | target | calibrated | " + " | ".join(labels) + " | ceiling | closed (" + " / ".join(labels)
             + ") |", "|---|---|---|---|---|---|---|---|"]
    for spec, row in study.items():
        for k, name in enumerate(row["targets"]):
            shares = [closed(row["calibrated"][k], row[label][k], row["ceiling"][k]) for label in labels]
            lines.append(f"| {spec} | {name} | {row['calibrated'][k]:.2f} | "
                         + " | ".join(f"{row[label][k]:.2f}" for label in labels) + f" | {row['ceiling'][k]:.2f} | "
                         + " / ".join("above" if v is None else f"{v:.0%}" for v in shares) + " |")
        summed = row["summed_closed"]
        lines.append(f"| {spec} | summed squared error | | | | | | "
                     + " / ".join("none" if summed[label] is None else f"{summed[label]:.0%}" for label in labels)
                     + " |")
    return lines + [""]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/drift"))
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--captures", type=int, default=10)
    ap.add_argument("--frames", type=int, default=1)
    ap.add_argument("--kinds", nargs="+", default=list(CHANGES), choices=list(CHANGES))
    ap.add_argument("--noise", action="store_true", help="only the camera-noise study (noise/ under --out)")
    ap.add_argument("--chart", action="store_true", help="only redraw drift.png from --out's results.json")
    ap.add_argument("--moved-models", action="store_true", help="only the moved models given the exact moves "
                    "(moved_models/ under --out; --scenes and --kinds choose)")
    ap.add_argument("--unchanged", action="store_true", help="only the loop in the world it was calibrated in "
                    "(unchanged/ under --out; --scenes defaults to the held-out kinds and unseen seeds)")
    args = ap.parse_args()
    if args.unchanged:
        specs = args.scenes if args.scenes != list(SCENES) else list(UNCHANGED_SCENES)
        study = unchanged_study(specs, args.captures)
        write_results(args.out / "unchanged", study, "\n".join(unchanged_markdown(study, args.captures)))
        return
    if args.chart:
        chart(json.loads((args.out / "results.json").read_text()), args.out / "drift.png")
        return
    if args.moved_models:
        study = moved_models(args.scenes, args.kinds)
        write_results(args.out / "moved_models", study, "\n".join(moved_markdown(study)))
        print("\n".join(moved_markdown(study)))
        return
    if args.noise:
        study = noise_study(args.captures)
        write_results(args.out / "noise", study, "\n".join(noise_markdown(study)))
        print("\n".join(noise_markdown(study)))
        return
    result = {"machine": machine(), "captures": args.captures, "frames": args.frames, "scenes": {}}
    for spec in args.scenes:
        data = scene_data(spec)
        cal = calibrate_virtual(parse_scene(data, name=data["name"]))
        cases = [run_case(data, cal, "none", 0.0, args.captures, args.frames)]
        for kind in args.kinds:
            for value in CHANGES[kind]:
                cases.append(run_case(data, cal, kind, value, args.captures, args.frames))
                print(spec, markdown({**result, "scenes": {spec: cases[-1:]}}).splitlines()[-1], flush=True)
        result["scenes"][spec] = cases
    args.out.mkdir(parents=True, exist_ok=True)
    write_results(args.out, result, markdown(result))
    chart(result, args.out / "drift.png")
    print(markdown(result))


if __name__ == "__main__":
    main()
