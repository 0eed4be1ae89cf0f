"""Look at calibration correspondences in 3D: each state's decoded camera-projector pairs triangulated
with the virtual rig's geometry, coloured by projector or by decoding contrast, with the camera and
projector rays of a few sampled pairs and the devices' frusta.

    python viz/correspondences.py SIMULATE_DIR [--colour projector|contrast] [--rays 6] [--out FILE.png] [--show]

SIMULATE_DIR is what ``torchproj simulate --out`` wrote (its report names the scene config).
Off-screen by default; ``--show`` opens a window where a display exists.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pyvista as pv
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import finish, frustum  # noqa: E402

from torchproj.calib import triangulate  # noqa: E402
from torchproj.core.conventions import pixel_grid  # noqa: E402
from torchproj.experiments import rig_procam  # noqa: E402
from torchproj.scene import Scene, load_scene  # noqa: E402

PROJECTOR_COLOURS = ["#d62728", "#1f77b4", "#2ca02c", "#9467bd"]


def correspondence_clouds(scene: Scene, run_dir: Path) -> list[dict]:
    """Triangulate every ``calibration/STATE/PROJECTOR/correspondence.npz`` of a simulate run.

    Returns:
        per (state, projector): ``state``, ``projector`` (index), ``points`` (N, 3) world metres,
        ``contrast`` (N,), ``cam_centre`` and ``prj_centre`` (3,).
    """
    cam = scene.camera
    grid = pixel_grid(cam.height, cam.width).double()
    out = []
    for st in scene.states:
        for j, proj in enumerate(scene.projectors):
            path = run_dir / "calibration" / st.name / proj.name / "correspondence.npz"
            if not path.is_file():
                continue
            data = np.load(path)
            prj_xy = torch.as_tensor(data["prj_xy"]).double()
            valid = torch.isfinite(prj_xy).all(-1)
            if not bool(valid.any()):
                continue
            in_cam = triangulate(grid[valid], prj_xy[valid], rig_procam(scene, j)).numpy()
            world = in_cam @ cam.world_from_cam[:3, :3].T + cam.world_from_cam[:3, 3]
            out.append({"state": st.name, "projector": j, "points": world,
                        "contrast": data["contrast"][valid.numpy()].astype(np.float64),
                        "cam_centre": cam.world_from_cam[:3, 3], "prj_centre": proj.centre})
    return out


def draw_correspondences(scene: Scene, clouds: list[dict], out: Path | None, colour: str = "projector",
                         rays: int = 6, show: bool = False, seed: int = 0, window_size=(1000, 750)) -> pv.Plotter:
    if not clouds:
        raise SystemExit("no correspondences found: run torchproj simulate on the scene first")
    rng = np.random.default_rng(seed)
    plotter = pv.Plotter(off_screen=not show, window_size=window_size)
    plotter.set_background("white")
    cam = scene.camera
    plotter.add_mesh(frustum(cam.K, cam.width, cam.height, cam.world_from_cam, 0.3), color="black", line_width=2)
    for j, p in enumerate(scene.projectors):
        plotter.add_mesh(frustum(p.K, p.width, p.height, p.world_from_prj, 0.3),
                         color=PROJECTOR_COLOURS[j % len(PROJECTOR_COLOURS)], line_width=2)
    for c in clouds:
        # Every 4th point keeps the view light; the rays show which pair made a point.
        cloud = pv.PolyData(c["points"][::4])
        if colour == "contrast":
            cloud["decoding contrast"] = c["contrast"][::4]
            plotter.add_mesh(cloud, scalars="decoding contrast", cmap="viridis", point_size=2,
                             scalar_bar_args={"title": "decoding contrast", "color": "black"})
        else:
            plotter.add_mesh(cloud, color=PROJECTOR_COLOURS[c["projector"] % len(PROJECTOR_COLOURS)], point_size=2,
                             opacity=0.6, label=f"{c['state']} / {scene.projectors[c['projector']].name}")
        for i in rng.choice(len(c["points"]), size=min(rays, len(c["points"])), replace=False):
            x = c["points"][i]
            plotter.add_mesh(pv.Line(c["cam_centre"], x), color="black", line_width=1)
            plotter.add_mesh(pv.Line(c["prj_centre"], x), color=PROJECTOR_COLOURS[c["projector"] % 4], line_width=1)
    if colour != "contrast":
        plotter.add_legend(bcolor="white", size=(0.25, 0.18), loc="lower right")
    plotter.camera_position = [(1.6, -0.9, -0.9), (0.0, 0.0, 0.7), (0, -1, 0)]
    return finish(plotter, out, show)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="output folder of torchproj simulate")
    parser.add_argument("--colour", choices=["projector", "contrast"], default="projector")
    parser.add_argument("--rays", type=int, default=6, help="sampled correspondences drawn as rays, per cloud")
    parser.add_argument("--out", type=Path, help="PNG to write (default RUN_DIR/correspondences.png)")
    parser.add_argument("--show", action="store_true", help="open a window (needs a display)")
    args = parser.parse_args(argv)
    report = args.run_dir / "report.json"
    if not report.is_file():
        parser.error(f"{report} not found: give the --out folder of torchproj simulate")
    scene = load_scene(json.loads(report.read_text())["config"])
    out = args.out or args.run_dir / "correspondences.png"
    draw_correspondences(scene, correspondence_clouds(scene, args.run_dir), out, args.colour, args.rays,
                         args.show).close()
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
