"""Where the default model misses the exact light: which ingredient, and where on the image.

    python benchmarks/model_miss.py --out benchmarks/results/model_miss

Five measurements behind docs/accuracy.md "The ceiling", on the scenes whose targets stay short of it:

1. Ingredients. One calibration per scene; the default ``run`` (area footprint, shares' fit) on it,
   then with the simulator's exact projector coordinates swapped in where calibration mapped a
   pixel (``maps``), with the exact white minus black of each pixel and projector (``weights``: the
   oracle calibration's, from noise-free captures), with both, and on the exact light itself (the ceiling,
   ``--oracle transport``). What is left between "both" and the ceiling is the footprint: how the
   area model shares a pixel's light among its cells.
2. Bands. For the default run, the run with both ingredients exact, and the ceiling: each target's
   mean squared error by distance (camera pixels) to the nearest depth edge or outline, from the
   exact maps: a step over 4 cells to a neighbour in any projector's map, the border of a
   projector's lit region, or a change of surface under the camera. The share of the target's
   squared error in each band says where the dB are lost.
3. Sampling. The virtual camera integrates a pixel as ``supersampling`` x ``supersampling`` point
   samples. On the paper's planes, with the exact maps, the area model predicts a noise-free capture
   of random 2x2-cell blocks, its pixel sampled 4 x 4 (the default) or on the camera's own grid;
   and ``box_cylinders`` is run both ways.
4. Stripes as more white minus black. Inside a Gray-code stripe, more than 2.5 cells from its
   edges, ``|pattern - inverse|`` is the pixel's white minus black again, whatever the camera's
   response, so averaging the pairs where that holds would take the camera noise out of the
   weights (``stripes``: on the same captures as the calibration, regenerated from the scene's
   seed). On the real captures (``../shared/data/procam_chessboard``, skipped where absent) the
   median ratio of the two per pair says whether a bench's stripes really are that bright.
5. The faces' maps on ``box_positions``. The refined map's error on the faces (``refine.py``'s
   ``rest`` band) from the calibration captures with and without the camera's noise: what is left
   without it is the aliasing of the camera's point-sampled pixel against the cells, not noise.
   Then runs on the exact maps plus either part of the decoded map's error: its smooth part (the
   mean over :data:`SMOOTHING` x :data:`SMOOTHING` pixels) or the rest (the fine part), to say
   which part the images pay for.

Writes ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import warnings
from pathlib import Path

import torch
import torch.nn.functional as F
from common import machine, write_results
from refine import bands as map_bands
from scipy import ndimage

from torchproj.calib import calibrate_projector, read_graycode_folder
from torchproj.calib.graycode import graycode_bits
from torchproj.calib.maps import depth_edges
from torchproj.pipeline import calibrate_virtual, run_virtual
from torchproj.pipeline.virtual import simulate_calibration
from torchproj.scene import load_scene
from torchproj.sim.rig import VirtualRig
from torchproj.transport import build

BANDS = ((0, 1), (2, 3), (4, 8), (9, None))  # camera pixels from the nearest edge, both ends included
STRIPE_CLEARANCE = 2.5  # cells from the pixel's coordinate to the nearest edge of a stripe it counts in
SMOOTHING = 15  # camera pixels: the box whose mean splits a map's error into its smooth and fine parts
REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "procam_chessboard"


def inside_stripes(capture, size: tuple[int, int], xy: torch.Tensor):
    """Per Gray-code pair: its axis, bit, :math:`(H, W)` ``|pattern - inverse|`` (grey) and where the
    pixel's coordinate lies more than :data:`STRIPE_CLEARANCE` cells inside one stripe.

    Bit ``k`` of the Gray code changes between cells ``2^k - 1 + m 2^(k+1)`` and the next, i.e. at
    ``2^k - 0.5 + m 2^(k+1)`` with cells centred on integers (``torchproj.core.conventions``).
    """
    images = capture.patterns.mean(1).double()
    u = torch.nan_to_num(xy.double(), nan=-1e9)
    mapped = torch.isfinite(xy).all(-1)
    nx, ny = graycode_bits(*size)
    for pair in range(nx + ny):
        axis, k = (0, nx - 1 - pair) if pair < nx else (1, nx + ny - 1 - pair)
        period = 2 ** (k + 1)
        t = torch.remainder(u[..., axis] + 0.5 - 2 ** k, period)
        clear = mapped & (torch.minimum(t, period - t) > STRIPE_CLEARANCE)
        yield axis, k, (images[2 * pair] - images[2 * pair + 1]).abs(), clear


def stripe_weights(scene, cal) -> dict[str, list[torch.Tensor]]:
    """Per state and projector, each pixel's white minus black averaged with its clear stripes' differences."""
    rig, out = VirtualRig(scene), {}
    for st in scene.states:
        out[st.name] = []
        rig.geometry(st.name)
        for j, proj in enumerate(scene.projectors):
            capture = simulate_calibration(rig, st.name, j)  # the rig's seed: the calibration's own captures
            state = cal.states[st.name]
            contrast = (capture.white - capture.black).mean(0).double()
            if not torch.equal(contrast.clamp_min(0).to(state.weight[j].dtype), state.weight[j]):
                raise RuntimeError("the regenerated captures are not the calibration's")
            total, count = contrast.clone(), torch.ones_like(contrast)
            for _, _, diff, clear in inside_stripes(capture, (proj.width, proj.height), state.prj_xy[j]):
                total += torch.where(clear, diff, 0.0)
                count += clear
            out[st.name].append((total / count).clamp_min(0).to(state.weight[j].dtype))
    return out


def real_stripes() -> dict:
    """Per real capture and pair, the median ratio of ``|pattern - inverse|`` to white minus black where clear."""
    out = {}
    for folder in sorted(REAL.glob("capture_*")):
        capture = read_graycode_folder(folder, (1024, 768))
        cal = calibrate_projector(capture, (1024, 768))
        contrast = cal.decoding.contrast.double()
        out[folder.name] = [{"axis": "xy"[axis], "bit": k, "pixels": int(clear.sum()),
                             "median_ratio": round(float((diff[clear] / contrast[clear]).median()), 3)}
                            for axis, k, diff, clear in inside_stripes(capture, (1024, 768), cal.prj_xy)
                            if clear.sum() >= 1000]
    return out


def swapped(cal, maps: bool = False, weights: dict | None = None, map_error=None):
    """``cal`` with the simulator's exact coordinates where calibration mapped a pixel (``maps``),
    plus, if given, ``map_error(decoded - exact, known)`` of them (:math:`(H, W, 2)` and the
    :math:`(H, W)` pixels both map); and/or other weights, per state a list over projectors (``weights``)."""
    states = {}
    for name, state in cal.states.items():
        xy = list(state.prj_xy)
        if maps:
            for j, (decoded, truth) in enumerate(zip(state.prj_xy, cal.rig.geometry(name).prj_xy)):
                truth = truth.cpu().to(decoded.dtype)
                both = torch.isfinite(decoded).all(-1) & torch.isfinite(truth).all(-1)
                if map_error is not None:
                    truth = truth + map_error(torch.where(both[..., None], decoded - truth, 0.0), both)
                xy[j] = torch.where(both[..., None], truth, decoded)
        weight = state.weight if weights is None else [w.to(v.dtype) for w, v in zip(weights[name], state.weight)]
        states[name] = dataclasses.replace(state, prj_xy=xy, weight=weight)
    return dataclasses.replace(cal, states=states)


def edge_distance(rig, state: str) -> torch.Tensor:
    """:math:`(H, W)` camera pixels to the nearest depth edge or outline (module text, point 2)."""
    geo = rig.geometry(state)
    edge = torch.zeros(geo.surface_id.shape, dtype=torch.bool)
    for truth in geo.prj_xy:
        truth = truth.cpu()
        unmapped = ~torch.isfinite(truth).all(-1)
        border = torch.from_numpy(ndimage.binary_dilation(unmapped.numpy())) & ~unmapped
        edge |= depth_edges(truth) | border
    surface = geo.surface_id.cpu()
    for dim in (0, 1):
        change = surface.diff(dim=dim) != 0
        edge |= torch.nn.functional.pad(change, (0, 1) if dim else (0, 0, 0, 1))
        edge |= torch.nn.functional.pad(change, (1, 0) if dim else (0, 0, 1, 0))
    return torch.from_numpy(ndimage.distance_transform_edt(~edge.numpy()))


def banded(targets, distance: dict[str, torch.Tensor]) -> list[dict]:
    """Per target: PSNR, SSIM, and per band its pixels, mean squared error and share of the squared error."""
    rows = []
    for t in targets:
        error = (t.estimate - t.values).pow(2).mean(0)
        covered, far = t.covered, distance[t.state]
        total = float(error[covered].sum())
        bands = []
        for lo, hi in BANDS:
            inside = covered & (far >= lo) & ((far <= hi) if hi is not None else True)
            part = error[inside]
            bands.append({"from": lo, "to": hi, "pixels": int(inside.sum()),
                          "mse": round(float(part.mean()), 6) if part.numel() else None,
                          "share": round(float(part.sum()) / total, 3) if total else None})
        rows.append({"name": t.name, "psnr_db": round(t.psnr_db, 2), "ssim": round(t.ssim, 3),
                     "mse": round(float(error[covered].mean()), 6), "bands": bands})
    return rows


def weight_miss(cal, exact: dict, stripes: dict) -> dict:
    """RMS of measured minus exact white minus black over the mapped pixels, as decoded and stripe-averaged."""
    out = {}
    for name, state in cal.states.items():
        out[name] = {how: [round(float((w[j] - exact[name][j])[torch.isfinite(xy).all(-1)].pow(2).mean().sqrt()), 5)
                           for j, xy in enumerate(state.prj_xy)]
                     for how, w in (("decoded", state.weight), ("stripes", stripes[name]))}
    return out


def ingredients(scene_name: str) -> tuple[dict, dict]:
    """Runs of one scene with each ingredient exact, and the ceiling, each banded (points 1 and 2);
    and the weights' miss (point 4)."""
    scene = load_scene(scene_name)
    cal = calibrate_virtual(scene, progress=False)
    distance = {st.name: edge_distance(cal.rig, st.name) for st in scene.states}
    exact = {name: state.weight for name, state in calibrate_virtual(scene, progress=False, oracle=True).states.items()}
    stripes = stripe_weights(scene, cal)
    variants = {"decoded": swapped(cal), "maps": swapped(cal, maps=True), "weights": swapped(cal, weights=exact),
                "both": swapped(cal, maps=True, weights=exact), "stripes": swapped(cal, weights=stripes)}
    runs = {v: banded(run_virtual(scene, calibration=c, progress=False).targets, distance) for v, c in variants.items()}
    runs["ceiling"] = banded(run_virtual(scene, calibration=cal, progress=False, oracle="transport").targets, distance)
    return runs, weight_miss(cal, exact, stripes)


def prediction_miss(scene_name: str, samples: int) -> dict:
    """RMS of (area model's prediction - noise-free capture) over the lit pixels, per state."""
    scene = load_scene(scene_name)
    cal = calibrate_virtual(scene, progress=False, oracle=True)
    rig, g, out = cal.rig, torch.Generator().manual_seed(0), {}
    build._AREA_SAMPLES = samples
    try:
        for name, state in cal.states.items():
            shown = [torch.rand(1, 1, p.height // 2, p.width // 2, generator=g).repeat_interleave(2, 2)
                     .repeat_interleave(2, 3) for p in scene.projectors]
            shot = rig.capture(name, dict(enumerate(shown)), noise=False, quantise=False)[0]
            dark = rig.capture(name, {}, noise=False, quantise=False)[0]
            light = []
            for j, p in enumerate(shown):
                black, white = (rig.emitted(j, torch.full_like(p, v))[0] for v in (0.0, 1.0))
                light.append(((rig.emitted(j, p)[0] - black) / (white - black)).reshape(1, *p.shape[-2:]))
            lit = state.lit()
            miss = (state.predict(light, dark, "area") - shot)[:, lit]
            out[name] = {"miss_rms": round(float(miss.pow(2).mean().sqrt()), 4),
                         "signal_std": round(float((shot - dark)[:, lit].std()), 4)}
    finally:
        build._AREA_SAMPLES = 4
    return out


def _box_mean(values: torch.Tensor, known: torch.Tensor, size: int) -> torch.Tensor:
    """:math:`(H, W, D)` the mean of ``values`` over the ``known`` pixels of each ``size x size`` box."""
    def pool(t):
        return F.avg_pool2d(t, size, 1, size // 2, count_include_pad=False)

    total = pool(torch.where(known[..., None], values, 0.0).permute(2, 0, 1)[None])[0].permute(1, 2, 0)
    return total / pool(known.to(values.dtype)[None, None])[0, 0].clamp_min(1e-9)[..., None]


def face_maps(scene_name: str = "box_positions") -> dict:
    """Point 5: the faces' map error with and without camera noise, and runs on the exact maps plus
    the smooth or the fine part of the decoded map's error."""
    scene = load_scene(scene_name)
    rig = VirtualRig(scene)
    errors = {"noisy": [], "noise-free": []}
    for st in scene.states:
        for j, p in enumerate(scene.projectors):
            truth = rig.geometry(st.name).prj_xy[j].cpu()
            face = map_bands(truth)["rest"]
            for how, noise in (("noisy", True), ("noise-free", False)):
                xy = calibrate_projector(simulate_calibration(rig, st.name, j, noise=noise), (p.width, p.height)).prj_xy
                miss = (xy - truth).norm(dim=-1)
                errors[how].append(miss[face & torch.isfinite(miss)])
    out = {"map_rms": {how: round(float(torch.cat(m).pow(2).mean().sqrt()), 4) for how, m in errors.items()}}
    cal = calibrate_virtual(scene, progress=False)
    parts = {"smooth": lambda e, known: _box_mean(e, known, SMOOTHING),
             "fine": lambda e, known: e - _box_mean(e, known, SMOOTHING), "all": lambda e, known: e}
    faces = {name: [map_bands(truth.cpu())["rest"] for truth in cal.rig.geometry(name).prj_xy] for name in cal.states}
    runs, part_rms = {}, {}
    for part, split in parts.items():
        with_error = swapped(cal, maps=True, map_error=split)
        miss = torch.cat([(xy - truth.cpu()).norm(dim=-1)[face]
                          for name, state in with_error.states.items()
                          for xy, truth, face in zip(state.prj_xy, cal.rig.geometry(name).prj_xy, faces[name])])
        part_rms[part] = round(float(miss[torch.isfinite(miss)].pow(2).mean().sqrt()), 4)  # where both map
        runs[part] = [{"name": t.name, "psnr_db": round(t.psnr_db, 2), "ssim": round(t.ssim, 3)}
                      for t in run_virtual(scene, calibration=with_error, progress=False).targets]
    return {"scene": scene_name, **out, "part_rms": part_rms, "runs": runs}


def _band_name(band: dict) -> str:
    return f"{band['from']}-{band['to']}" if band["to"] is not None else f">= {band['from']}"


def markdown(scenes: dict, sampling: dict, runs: dict, grid: int, weights: dict, real: dict, faces: dict) -> str:
    lines = [f"# Where the default model misses the exact light ({machine()})", "",
             "## Ingredients: the default run with the simulator's exact maps and/or weights swapped in", "",
             "| scene | run | per target PSNR / SSIM |", "|---|---|---|"]
    for scene, per in scenes.items():
        lines += [f"| {scene} | {run} | " + "; ".join(f"{r['name']} {r['psnr_db']:.2f} / {r['ssim']:.3f}" for r in rows)
                  + " |" for run, rows in per.items()]
    names = [_band_name(b) for b in next(iter(next(iter(scenes.values())).values()))[0]["bands"]]
    lines += ["", ("## Bands: mean squared error (share of the target's squared error) by camera pixels "
                   "from the nearest depth edge or outline"), "",
              "| scene | run | target | pixels per band | " + " | ".join(names) + " |",
              "|---|---|---|---|" + "---|" * len(names)]
    for scene, per in scenes.items():
        for run in ("decoded", "both", "ceiling"):
            for r in per[run]:
                cells = [f"{b['mse']:.5f} ({b['share']:.0%})" if b["mse"] is not None else "-" for b in r["bands"]]
                lines.append(f"| {scene} | {run} | {r['name']} | {', '.join(str(b['pixels']) for b in r['bands'])} | "
                             + " | ".join(cells) + " |")
    lines += ["", "## paper_two_planes, exact maps: area prediction of random light, pixel sampled n x n", "",
              "| n | state | miss (RMS) | signal (std) |", "|---|---|---|---|"]
    for n, per in sampling.items():
        lines += [f"| {n} | {s} | {v['miss_rms']:.4f} | {v['signal_std']:.4f} |" for s, v in per.items()]
    lines += ["", f"## box_cylinders, area pixel sampled 4 x 4 or {grid} x {grid} (the camera's grid)", "",
              "| n | maps | per target PSNR / SSIM |", "|---|---|---|"]
    for n, per in runs.items():
        lines += [f"| {n} | {maps} | " + "; ".join(f"{r['name']} {r['psnr_db']:.2f} / {r['ssim']:.3f}" for r in rows)
                  + " |" for maps, rows in per.items()]
    lines += ["", f"## Stripes as more white minus black (clear: over {STRIPE_CLEARANCE} cells from a stripe's edge)", "",
              ("Weights' RMS miss of the exact white minus black, per projector (the runs are `decoded` and "
               "`stripes` above):"), "", "| scene | state | decoded | stripe-averaged |", "|---|---|---|---|"]
    for scene, per in weights.items():
        lines += [f"| {scene} | {st} | {', '.join(map(str, v['decoded']))} | {', '.join(map(str, v['stripes']))} |"
                  for st, v in per.items()]
    if real:
        bits = [r["bit"] for r in next(iter(real.values())) if r["axis"] == "x"]
        lines += ["", "Real captures: median of |pattern - inverse| / (white - black) over the clear pixels, per bit", "",
                  "| capture | axis | " + " | ".join(f"bit {k}" for k in bits) + " |", "|---|---|" + "---|" * len(bits)]
        for name, rows in real.items():
            for axis in "xy":
                ratio = {r["bit"]: r["median_ratio"] for r in rows if r["axis"] == axis}
                lines.append(f"| {name} | {axis} | " + " | ".join(f"{ratio[k]:.3f}" if k in ratio else "-" for k in bits) + " |")
    else:
        lines += ["", f"Real captures: {REAL} is absent, not measured."]
    lines += ["", f"## {faces['scene']}: the faces' maps", "",
              (f"Refined map's error on the faces (cells rms, `refine.py`'s rest band): {faces['map_rms']['noisy']} "
               f"from the noisy captures, {faces['map_rms']['noise-free']} from noise-free ones."), "",
              (f"Exact maps plus a part of the decoded map's error (smooth: its mean over {SMOOTHING} x {SMOOTHING} "
               "pixels; fine: the rest):"), "", "| error added | its rms on the faces | per target PSNR / SSIM |", "|---|---|---|"]
    lines += [f"| {part} | {faces['part_rms'][part]} | " + "; ".join(f"{r['name']} {r['psnr_db']:.2f} / {r['ssim']:.3f}"
                                                                for r in rows) + " |" for part, rows in faces["runs"].items()]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/model_miss"))
    ap.add_argument("--scenes", nargs="+", default=["box_cylinders", "box_positions"])
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    real = real_stripes() if REAL.is_dir() else {}
    scenes, weights = {}, {}
    for name in args.scenes:
        scenes[name], weights[name] = ingredients(name)
        print(name, {run: [(r["name"], r["psnr_db"]) for r in rows] for run, rows in scenes[name].items()}, flush=True)
    sampling = {n: prediction_miss("paper_two_planes", n) for n in (4, 3)}
    scene = load_scene("box_cylinders")
    grid = scene.camera.supersampling
    cal = calibrate_virtual(scene, progress=False)
    runs = {}
    for n in (4, grid):
        build._AREA_SAMPLES = n
        try:
            runs[n] = {maps: [{"name": t.name, "psnr_db": round(t.psnr_db, 2), "ssim": round(t.ssim, 3)}
                              for t in run_virtual(scene, calibration=swapped(cal, maps=exact), progress=False).targets]
                       for maps, exact in (("decoded", False), ("exact", True))}
        finally:
            build._AREA_SAMPLES = 4
    faces = face_maps()
    print(faces, flush=True)
    text = markdown(scenes, sampling, runs, grid, weights, real, faces)
    write_results(args.out, {"machine": machine(), "ingredients": scenes, "sampling": sampling,
                             "grid_runs": {str(n): per for n, per in runs.items()}, "weights": weights,
                             "real_stripes": real, "faces": faces}, text)
    print(text)


if __name__ == "__main__":
    main()
