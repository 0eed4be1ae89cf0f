"""Calibrate a noiseless scene on two devices and say where the calibrations and operators part."""
import dataclasses, sys
import torch
from torchproj.pipeline import calibrate_virtual, scene_targets
from torchproj.pipeline.run import build_operators
from torchproj.scene import load_scene


def walk(x, path=""):
    if isinstance(x, torch.Tensor):
        yield path, x.detach().cpu()
    elif dataclasses.is_dataclass(x) and not isinstance(x, type):
        for f in dataclasses.fields(x):
            yield from walk(getattr(x, f.name), f"{path}.{f.name}")
    elif isinstance(x, (list, tuple)):
        for i, v in enumerate(x):
            yield from walk(v, f"{path}[{i}]")
    elif isinstance(x, dict):
        for k, v in x.items():
            yield from walk(v, f"{path}[{k}]")


def grab(name, device):
    scene = load_scene(name)
    cal = calibrate_virtual(scene, progress=False, device=device)
    targets = scene_targets(scene, None, cal.rig)
    op = build_operators(cal.states, targets, footprint="area", merge=False, colour_weights="channel",
                         device=device)
    op = op[0] if isinstance(op, (list, tuple)) else op
    out = dict(walk(cal.states, "states"))
    out.update(walk(cal.black, "black"))
    out.update(walk([(r.a, r.b, r.c) for r in cal.responses], "resp"))
    out["op.rhs"] = op.rhs.detach().cpu() if hasattr(op, "rhs") else torch.zeros(1)
    out["op.dense"] = op.dense().cpu() if op.shape[0] * op.shape[1] < 4e8 else torch.zeros(1)
    return out


name, devs, save = sys.argv[1], sys.argv[2].split(","), sys.argv[3]
got = {d: grab(name, d) for d in devs}
torch.save(got, save)
a, b = (got[d] for d in devs)
for k in a:
    x, y = a[k], b.get(k)
    if y is None or x.shape != y.shape:
        print(k, "shape", tuple(x.shape), None if y is None else tuple(y.shape))
        continue
    if x.dtype == torch.bool or not x.is_floating_point():
        n = int((x != y).sum())
        if n:
            print(k, f"{n} of {x.numel()} differ")
        continue
    both = torch.isfinite(x) & torch.isfinite(y)
    nan = int((torch.isfinite(x) != torch.isfinite(y)).sum())
    d = (x - y).abs()[both]
    big = int((d > 1e-3 * (1 + x.abs()[both])).sum())
    if nan or big or (d.numel() and d.max() > 1e-5):
        print(k, f"finite differ {nan}, >1e-3 rel {big} of {x.numel()}, max {float(d.max()) if d.numel() else 0:.3g}")
