"""Test helpers: small versions of the built-in scenes, a synthetic calibration, the real captures' location."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import yaml

from torchproj.calib import graycode_patterns
from torchproj.calib.maps import pixel_square
from torchproj.scene import builtin_config, parse_scene, scale_config
from torchproj.transport import StateCalibration, Target
from torchproj.transport.build import target_on_camera

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
CHESSBOARD = SHARED_DATA / "procam_chessboard"


def small_config(name: str = "paper_two_planes", camera=(400, 300), projector=(256, 192), **camera_overrides) -> dict:
    """A built-in scene's YAML data with smaller devices (:func:`torchproj.scene.scale_config`) and
    camera settings overridden."""
    data = scale_config(yaml.safe_load(builtin_config(name).read_text()), camera=camera, projector=projector)
    data["camera"].update(camera_overrides)
    return data


def small_scene(name: str = "paper_two_planes", camera=(400, 300), projector=(256, 192), **camera_overrides):
    return parse_scene(small_config(name, camera, projector, **camera_overrides), name=name)


SIZES = [(12, 9), (10, 8)]
LARGE = [(40, 32), (36, 28)]  # large enough for two coarse levels (tests/transport/test_operator.py)


def synthetic_calibration(seed=0, shape=(15, 20), sizes=SIZES):
    """Two projectors, two states: random sub-pixel correspondences with holes, random weights."""
    g = torch.Generator().manual_seed(seed)
    cals = {}
    for state in ("near", "far"):
        prj, wts = [], []
        for w, h in sizes:
            xy = torch.rand(*shape, 2, generator=g) * torch.tensor([w - 1.0, h - 1.0])
            xy[torch.rand(shape, generator=g) < 0.15] = float("nan")
            prj.append(xy)
            wts.append(0.2 + torch.rand(shape, generator=g))
        cals[state] = StateCalibration(prj, wts, sizes)
    return cals


def targets(channels=1, seed=1):
    g = torch.Generator().manual_seed(seed)
    return [Target("near", torch.rand(channels, 6, 8, generator=g), name="a"),
            Target("far", torch.rand(channels, 7, 5, generator=g), name="b")]


def dense_reference(cals, tgts, scale, bilinear=False):
    """Rows, columns and values by plain loops (independent of the vectorised builder)."""
    offsets = [0, SIZES[0][0] * SIZES[0][1]]
    rows, rhs = [], []
    for t in tgts:
        cal = cals[t.state]
        lit = cal.lit()
        values, covered = target_on_camera(t, lit)
        for y in range(lit.shape[0]):
            for x in range(lit.shape[1]):
                if not covered[y, x]:
                    continue
                entries = {}
                for j, (w, h) in enumerate(SIZES):
                    u = cal.prj_xy[j][y, x].double().numpy()
                    if not np.isfinite(u).all():
                        continue
                    wt = float(cal.weight[j][y, x])
                    if bilinear:
                        bx, by = int(np.floor(u[0])), int(np.floor(u[1]))
                        fx, fy = u[0] - bx, u[1] - by
                        for dx, dy, f in [(0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy),
                                          (1, 1, fx * fy)]:
                            if 0 <= bx + dx < w and 0 <= by + dy < h and f > 0:
                                entries[offsets[j] + (by + dy) * w + bx + dx] = wt * f
                    else:
                        cx, cy = int(np.floor(u[0] + 0.5)), int(np.floor(u[1] + 0.5))
                        entries[offsets[j] + cy * w + cx] = wt
                if entries:
                    rows.append(entries)
                    rhs.append(values[:, y, x].double().numpy() * scale)
    cols = sorted({c for r in rows for c in r})
    index = {c: i for i, c in enumerate(cols)}
    A = np.zeros((len(rows), len(cols)))
    for i, r in enumerate(rows):
        for c, v in r.items():
            A[i, index[c]] = v
    return A, np.array(rhs), np.array(cols)


def area_captures(true_map, camera, projector, samples=8):
    """Noise-free captures of the full Gray-code sequence: each camera pixel the mean of ``samples`` x
    ``samples`` points of its square, each lit by the cell it falls in, at contrast 0.8 over 0.05.
    Returns the captures and each pixel's points' cells :math:`(H, W, samples^2, 2)` int64."""
    h, w = camera
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    offset = pixel_square(samples, dtype=torch.float64)
    cell = torch.floor(true_map(xs[..., None] + offset[:, 0], ys[..., None] + offset[:, 1]) + 0.5).long()
    seq = graycode_patterns(*projector)[:, 0].double()
    images = (0.05 + 0.8 * seq[:, cell[..., 1], cell[..., 0]].mean(-1))[:, None].float()  # (N + 2, 1, H, W)
    return images[:-2], images[-2], images[-1], cell


def curved_map(x, y):
    """A smooth, slightly curved map at 0.55-1.1 cells per camera pixel."""
    return torch.stack([0.55 * x + 0.004 * x * x + 0.07 * y + 3.3, 0.6 * y + 0.003 * y * y - 0.05 * x + 5.1], -1)


class RigDisplay:
    """A projector that is one of the virtual rig's, standing in for a display (``show(image)``):
    remembers what it was told to show."""

    def __init__(self):
        self.image = None

    def show(self, image):
        self.image = image

    def pattern(self) -> torch.Tensor:
        """What it shows as the rig takes patterns: :math:`(1, C, H, W)` in [0, 1]."""
        image = torch.from_numpy(self.image.astype(np.float32) / 255)
        return image.permute(2, 0, 1)[None] if image.dim() == 3 else image[None, None]


def calibrate_bench(root: Path, scene, projector: str = "128x96", out: str = "calib") -> Path:
    """A bench made of files: every state's and projector's Gray-code captures on the virtual rig written
    as a bench stores them (``root/captures``), then ``torchproj calibrate`` into ``root/<out>``."""
    from torchproj.calib import write_graycode_folder
    from torchproj.cli import main
    from torchproj.pipeline import simulate_calibration
    from torchproj.sim import VirtualRig

    rig = VirtualRig(scene)
    for st in scene.states:
        for j, p in enumerate(scene.projectors):
            write_graycode_folder(root / "captures" / st.name / p.name, simulate_calibration(rig, st.name, j), bits=8)
    assert main(["calibrate", str(root / "captures"), "--projector", projector, "--out", str(root / out)]) == 0
    return root / out


def calibrate_once(scene, **options):
    """``scene``'s virtual calibration through the session's cache (``tests/conftest.py``), for tests whose
    subject is what is done with a calibration rather than calibrating: a scene another test or worker
    calibrated is read back, the same to the bit, the rig's noise going on where calibration left it
    (``tests/pipeline/test_cache.py``). ``options`` are :func:`~torchproj.pipeline.cache.cached_calibration`'s."""
    from torchproj.pipeline.cache import cached_calibration

    return cached_calibration(scene, progress=False, **options)[0]
