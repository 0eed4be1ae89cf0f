"""Light a direct-light model does not hold: what it costs, what calibration and the camera loop win back.

    python benchmarks/world_effects.py --effects colour_mixing --out benchmarks/results/world_effects/colour_mixing
    python benchmarks/world_effects.py --effects interreflection --out benchmarks/results/world_effects/interreflection
           [--scenes corner_screens@0.5 ...] [--captures 5]

Effects: ``colour_mixing`` (each camera channel sees some of every primary, the virtual rig's default
for a colour camera; module :mod:`torchproj.core.conventions`), at the default magnitude and at
twice its leak, on colour scenes; ``interreflection`` (one bounce between surfaces,
:mod:`torchproj.sim.bounce`) on scenes with concave arrangements. Per scene and effect, each method
is shown in the world with the effect (in calibration and show alike) and scored on the rig's
captures as ``torchproj run`` scores:

- ``without``: the world without the effect, calibrated and solved (what the scene gives when the
  effect is absent);
- ``ignored``: the effect is present, the model does not know it (mixing taken out of the fitted
  responses; for the bounce, which no model holds, the same as ``modelled``);
- ``modelled``: the model as calibration fits it (``fit_colour_mixing``, undone in compensation and
  solved through, :mod:`torchproj.solve.mixing`; the bounce: the direct-light model calibrated in
  its presence);
- ``loop``: ``torchproj run --refine`` from ``modelled``, ``--captures`` captures per state;
- ``loop, exact maps``: the same loop on a model built from the simulator's exact projector
  coordinates (``--oracle geometry``; weights still the captures'): what the loop reaches when the
  model's geometry is not in question, a bound on what its direct-light gradient allows;
- ``loop, exact direct light`` (interreflection): the loop on the simulator's exact direct light and
  responses against noise-free captures, the ceiling's first stage: the bound of a direct-light
  gradient;
- ``ceiling``: the world's exact light (``--ceiling``; with the bounce, the direct transport's answer
  corrected against the noise-free captures, :func:`torchproj.pipeline.solve_on_light_transport`).

Writes ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time
from pathlib import Path

from common import machine, write_results
from drift import scene_data

from torchproj.core.conventions import DEFAULT_COLOUR_MIXING
from torchproj.pipeline import calibrate_virtual, run_virtual
from torchproj.scene import parse_scene

SCENES = {"colour_mixing": ("colour_two_planes@0.5", "suite-1-3", "suite-1-11"),
          "interreflection": ("corner_screens@0.5", "box_positions@0.5", "sphere_three_projectors@0.5")}


def doubled_leak(mixing=DEFAULT_COLOUR_MIXING) -> list[list[float]]:
    """The default mixing with every off-diagonal share doubled (rows still summing to 1)."""
    out = []
    for c, row in enumerate(mixing):
        off = [2 * v if p != c else 0.0 for p, v in enumerate(row)]
        off[c] = 1 - sum(off)
        out.append([round(v, 4) for v in off])
    return out


EFFECTS = {"colour_mixing": {"default": None, "doubled leak": doubled_leak()}, "interreflection": {"one bounce": True}}


def with_effect(data: dict, effect: str, value) -> dict:
    d = copy.deepcopy(data)
    d.pop("show", None)  # the world as calibrated: only the effect differs (sphere_three_projectors ships a bump)
    if effect == "interreflection":
        d["interreflection"] = value != "none"
    for p in d["projectors"] if effect == "colour_mixing" else []:
        # None: the colour camera's default (which a scene, colour_two_planes among them, may switch off).
        p["colour_mixing"] = [list(row) for row in DEFAULT_COLOUR_MIXING] if value is None else value
    return d


def scores(report: dict, key: str | None = None) -> dict:
    targets = report["targets"]
    pick = (lambda t: t[key]) if key else (lambda t: t)
    return {"psnr_db": [round(pick(t)["psnr_db"], 3) for t in targets], "ssim": [round(pick(t)["ssim"], 4) for t in targets]}


def run_case(data: dict, effect: str, magnitude: str, value, captures: int) -> dict:
    shown = parse_scene(with_effect(data, effect, value), name=data["name"])
    plain = parse_scene(with_effect(data, effect, "none"), name=data["name"])
    row = {"effect": effect, "magnitude": magnitude, "value": value}
    t0 = time.perf_counter()
    row["without"] = scores(run_virtual(plain, progress=False).report)
    cal = calibrate_virtual(shown)
    result = run_virtual(shown, calibration=cal, refine=captures - 1, ceiling=True, progress=False)
    row["modelled"] = {"psnr_db": [round(s["psnr_db"], 3) for s in result.report["refine"]["start"]],
                       "ssim": [round(s["ssim"], 4) for s in result.report["refine"]["start"]]}
    row["loop"] = scores(result.report)
    row["ceiling"] = scores(result.report, "ceiling")
    row["loop, exact maps"] = scores(run_virtual(shown, oracle="geometry", refine=captures - 1, progress=False).report)
    if effect == "interreflection":
        row["loop, exact direct light"] = exact_direct_loop(shown, cal)
    row["fitted_mixing"] = [r.mixing.tolist() if r.mixing is not None else None for r in cal.responses]
    if effect == "colour_mixing":
        for r in cal.responses:
            r.mixing = None
        row["ignored"] = scores(run_virtual(shown, calibration=cal, progress=False).report)
    else:
        row["ignored"] = row["modelled"]
    row["seconds"] = round(time.perf_counter() - t0, 1)
    return row


def exact_direct_loop(scene, cal) -> dict:
    """The loop with nothing of the model in question but its form: the simulator's exact direct light
    and responses on the calibrated model's rows, corrected against noise-free captures (the ceiling's
    first stage, :data:`torchproj.pipeline.ceiling.BOUNCE_UPDATES` corrections), scored as the ceiling
    is. What it misses against the ceiling is what a direct-light gradient cannot find; what the
    calibrated loop misses beyond it is the calibrated model's."""
    from torchproj.pipeline import (CEILING_ITERATIONS, evaluate_patterns, light_transport, rig_measure, scene_targets,
                                    true_responses)
    from torchproj.pipeline.ceiling import BOUNCE_SOLVER_ITERATIONS, BOUNCE_UPDATES
    from torchproj.solve import make_patterns, refine_patterns
    from torchproj.transport import DEFAULT_FOOTPRINT, build_transport

    targets = scene_targets(scene, None, cal.rig)
    rows = build_transport(cal.states, targets, merge=False, footprint=DEFAULT_FOOTPRINT)
    ops = light_transport(cal.rig, targets, rows)
    responses = true_responses(scene)
    start, _, _ = make_patterns(ops, "fista", (0.0, 1.0), responses, max_iter=CEILING_ITERATIONS)
    refined = refine_patterns(ops, start.patterns, rig_measure(cal, ops, targets, noise=False), (0.0, 1.0), responses,
                              iterations=BOUNCE_UPDATES, solver_iterations=BOUNCE_SOLVER_ITERATIONS)
    scored = evaluate_patterns(cal, refined.images, targets, scale=rows.scale, states=cal.states, paper=False).targets
    return {"psnr_db": [round(t.psnr_db, 3) for t in scored], "ssim": [round(t.ssim, 4) for t in scored]}


METHODS = ("without", "ignored", "modelled", "loop", "loop, exact maps", "ceiling")


def markdown(result: dict) -> str:
    mean = statistics.fmean
    methods = [m for m in (*METHODS[:-1], "loop, exact direct light", METHODS[-1])
               if all(m in r for rows in result["scenes"].values() for r in rows)]
    lines = [f"# Light a direct-light model does not hold ({result['machine']})", "",
             f"PSNR (dB) / SSIM, mean over targets, captured as `torchproj run` scores; `loop`: {result['captures']} "
             "captures per state from `modelled`; `worst gap`: the largest per-target ceiling minus loop (dB). "
             "Command in the module docstring.", "",
             "| scene | effect | " + " | ".join(methods) + " | worst gap |",
             "|---|---|" + "---|" * len(methods) + "---|"]
    for scene, rows in result["scenes"].items():
        for r in rows:
            cells = [f"{mean(r[m]['psnr_db']):.2f} / {mean(r[m]['ssim']):.3f}" for m in methods]
            gap = max(c - k for c, k in zip(r["ceiling"]["psnr_db"], r["loop"]["psnr_db"]))
            lines.append(f"| {scene} | {r['effect']} {r['magnitude']} | " + " | ".join(cells) + f" | {gap:+.2f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/world_effects"))
    ap.add_argument("--scenes", nargs="+", help="scenes for every effect given (default: each effect's own)")
    ap.add_argument("--effects", nargs="+", default=list(EFFECTS), choices=list(EFFECTS))
    ap.add_argument("--captures", type=int, default=5)
    args = ap.parse_args()
    result = {"machine": machine(), "captures": args.captures, "scenes": {}}
    for effect in args.effects:
        for spec in args.scenes or SCENES[effect]:
            data = scene_data(spec)
            for magnitude, value in EFFECTS[effect].items():
                row = run_case(data, effect, magnitude, value, args.captures)
                result["scenes"].setdefault(spec, []).append(row)
                print(spec, effect, magnitude, {m: round(statistics.fmean(row[m]["psnr_db"]), 2) for m in METHODS},
                      flush=True)
                write_results(args.out, result, markdown(result))


if __name__ == "__main__":
    main()
