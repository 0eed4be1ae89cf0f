"""How far a bench photo lies from the light the model predicts for its own state, and for another.

    python benchmarks/photo_states.py --out benchmarks/results/photo_states [--scenes paper_two_planes ...]

``torchproj refine`` holds each photo against the model's prediction for every state of the loop
(``torchproj.pipeline.bench_loop._check_photos``): it refuses a photo that matches another state's at
least twice as well as its own, where its own is missed by more than a tenth, and warns past half.
This measures the margins those rules stand on. Each scene, at the tests' small size (200x150 camera,
128x96 projectors), is calibrated from files as a bench is; the first solve's patterns are then
photographed on the virtual rig in three worlds: as calibrated, with the first projector's lamp 25%
brighter, and with it moved 3 mm. Each photo is read at every state's rows, and the squared error
against the model's prediction there, over the prediction's own, is tabulated. Writes
``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import tempfile
from pathlib import Path

import torch
import yaml
from common import machine, write_results

from torchproj.calib import write_graycode_folder
from torchproj.cli import main as torchproj
from torchproj.pipeline import simulate_calibration
from torchproj.pipeline.bench_loop import _shown_light
from torchproj.pipeline.real_rig import bundle_problem
from torchproj.pipeline.shown import CapturedRows
from torchproj.scene import builtin_config, parse_scene, scale_config, shown_scene
from torchproj.sim import VirtualRig
from torchproj.solve import make_patterns, projectable_patterns
from torchproj.solve.refine import _rows
from torchproj.transport.build import build_operators

TARGETS = ["near=camera", "far=coffee"]


def calibrate_bench(root: Path, data: dict) -> Path:
    """The scene's calibration captures written as a bench stores them, then ``torchproj calibrate``."""
    scene = parse_scene(data, name="bench")
    rig = VirtualRig(scene)
    for st in scene.states:
        for j, p in enumerate(scene.projectors):
            write_graycode_folder(root / "captures" / st.name / p.name, simulate_calibration(rig, st.name, j), bits=8)
    with contextlib.redirect_stdout(io.StringIO()):
        assert torchproj(["calibrate", str(root / "captures"), "--projector", "128x96", "--out", str(root / "calib")]) == 0
    return root / "calib"


def misses(data: dict, calib: Path, show: dict | None) -> dict[str, dict[str, float]]:
    """Per photographed state, per state read: the relative squared error against the prediction."""
    world = VirtualRig(shown_scene(parse_scene(dict(data, show=show) if show else data, name="bench")))
    problem = bundle_problem(calib, TARGETS, solver="fista", bounds_8bit=(0, 255), objective="l2", maps="decoded",
                             footprint="area", plane_tolerance=1.0, colour_weights="channel", outside="clip",
                             chains="epipolar", device="cpu")
    ops = build_operators(problem.states, problem.targets, merge=False, footprint=problem.footprint,
                          colour_weights=problem.colour_weights)
    responses = problem.bundle.response_curves()
    start, _, _ = make_patterns(ops, "fista", problem.bounds, responses, calibrations=problem.states, progress=False)
    images = projectable_patterns(ops[0], start.patterns, problem.bounds, responses)[1]
    predicted = _rows(ops, _shown_light(ops, images, responses)).double()
    read = CapturedRows(ops, problem.targets)
    shown = {name: image.float()[None] / 255 for (name, _, _), image in zip(problem.bundle.projectors, images)}
    out = {}
    for photo in read.rows_of:
        above = world.capture(photo, shown)[0] - problem.bundle.black[photo]
        out[photo] = {}
        for state, rows in read.rows_of.items():
            want = predicted[rows]
            out[photo][state] = float((read.state_rows(above, state).double() - want).pow(2).sum() / want.pow(2).sum())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/photo_states"))
    parser.add_argument("--scenes", nargs="+", default=["paper_two_planes", "colour_two_planes"])
    args = parser.parse_args()
    torch.set_num_threads(2)
    results, lines = {"machine": machine(), "scenes": {}}, []
    for name in args.scenes:
        data = scale_config(yaml.safe_load(builtin_config(name).read_text()), camera=(200, 150), projector=(128, 96))
        first = data["projectors"][0]["name"]
        worlds = {"as calibrated": None, f"{first} lamp +25%": {"projectors": {first: {"gain": 1.25}}},
                  f"{first} moved 3 mm": {"projectors": {first: {"translation_mm": [3, 0, 0]}}}}
        with tempfile.TemporaryDirectory() as tmp:
            calib = calibrate_bench(Path(tmp), data)
            results["scenes"][name] = {world: misses(data, calib, show) for world, show in worlds.items()}
        for world, photos in results["scenes"][name].items():
            for photo, by_state in photos.items():
                lines.append(f"| {name} | {world} | {photo} | "
                             + " | ".join(f"{by_state[s]:.2%}" for s in ("near", "far")) + " |")
    markdown = "\n".join([
        f"# A photo against each state's predicted light ({results['machine']})", "",
        "Squared error of the photo read at each state's rows against the model's prediction there, over the "
        "prediction's own (`python benchmarks/photo_states.py`). A photo is refused where another state's column is "
        "under half its own and its own over 10%; warned about where its own is over 50%.", "",
        "| scene | world | photo of | read as near | read as far |", "|---|---|---|---|---|", *lines, ""])
    write_results(args.out, results, markdown)
    print(markdown)


if __name__ == "__main__":
    main()
