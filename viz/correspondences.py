"""Look at calibration correspondences in 3D: each state's decoded camera-projector pairs triangulated
with the virtual rig's geometry, coloured by projector or by decoding contrast, with the camera and
projector rays of a few sampled pairs and the devices' frusta.

    python viz/correspondences.py SIMULATE_DIR [--colour projector|contrast] [--rays 6] [--points 40000]
                                  [--out FILE.png] [--show]

SIMULATE_DIR is what ``torchproj simulate --out`` wrote (its report names the scene config). Beside
the PNG: ``.vtm`` with each state's and projector's cloud and its contrast, and ``.gltf`` of the
view (any glTF viewer opens it). Off-screen by default; ``--show`` opens a window where a display exists.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pyvista as pv
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import finish, frame_rig, frustum, read_json, read_npz, read_or_refuse, side_bar, written  # noqa: E402

from torchproj.calib import triangulate  # noqa: E402
from torchproj.cli_options import positive_int  # noqa: E402
from torchproj.core.conventions import pixel_grid  # noqa: E402
from torchproj.experiments import rig_procam  # noqa: E402
from torchproj.scene import Scene, load_scene  # noqa: E402

PROJECTOR_COLOURS = ["#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e", "#17becf", "#8c564b", "#e377c2"]


def cloud_colour(projector: int, state: int, states: int) -> str:
    """A (state, projector) cloud's colour: its projector's (as its frustum and rays are drawn), darker in
    the first state and lighter in each later one, so that states and overlapping clouds differ. A
    palette of its own per cloud gave a third projector's rays the colour of another's far cloud."""
    base = np.array([int(PROJECTOR_COLOURS[projector % len(PROJECTOR_COLOURS)][i:i + 2], 16) for i in (1, 3, 5)])
    t = state / max(states - 1, 1)
    dark, light = 0.75 * base, base + 0.55 * (255 - base)  # the same hue, shaded and tinted
    rgb = (1 - t) * dark + t * light
    return "#" + "".join(f"{int(round(min(v, 255))):02x}" for v in rgb)
POINTS_PER_CLOUD = 40_000  # drawn per (state, projector); only these are triangulated


def correspondence_clouds(scene: Scene, run_dir: Path, points: int = POINTS_PER_CLOUD, seed: int = 0,
                          read=np.load) -> list[dict]:
    """Triangulate ``points`` sampled pairs of every ``calibration/STATE/PROJECTOR/correspondence.npz``
    of a simulate run (every decoded pixel was triangulated and three in four then dropped: 29
    minutes on a busy 2-core machine for a view of the full-size rig).

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
            data = read(path)
            prj_xy = torch.as_tensor(data["prj_xy"]).double()
            valid = torch.isfinite(prj_xy).all(-1)
            if not bool(valid.any()):
                continue
            keep = torch.nonzero(valid.reshape(-1))[:, 0]
            keep = keep[torch.randperm(len(keep), generator=torch.Generator().manual_seed(seed))[:points]].sort().values
            valid = torch.zeros(valid.numel(), dtype=torch.bool).index_fill_(0, keep, True).reshape(valid.shape)
            in_cam = triangulate(grid[valid], prj_xy[valid], rig_procam(scene, j)).numpy()
            world = in_cam @ cam.world_from_cam[:3, :3].T + cam.world_from_cam[:3, 3]
            out.append({"state": st.name, "projector": j, "points": world,
                        "contrast": data["contrast"][valid.numpy()].astype(np.float64),
                        "cam_centre": cam.world_from_cam[:3, 3], "prj_centre": proj.centre})
    return out


def draw_correspondences(scene: Scene, clouds: list[dict], out: Path | None, colour: str = "projector",
                         rays: int = 6, show: bool = False, seed: int = 0, window_size=(1000, 750)) -> pv.Plotter:
    """Each (state, projector) cloud in a colour of its own (``colour="projector"``) or all by decoding
    contrast, the devices' frusta with their names, sampled rays, and axes in metres."""
    if not clouds:
        raise SystemExit("no correspondences found: run torchproj simulate on the scene first")
    rng = np.random.default_rng(seed)
    plotter = pv.Plotter(off_screen=not show, window_size=window_size)
    plotter.set_background("white")
    cam = scene.camera
    devices = {"camera": frustum(cam.K, cam.width, cam.height, cam.world_from_cam, 0.3)}
    plotter.add_mesh(devices["camera"], color="black", line_width=2)
    plotter.add_point_labels([cam.world_from_cam[:3, 3]], ["camera"], font_size=11, point_size=6, text_color="black",
                             shape_opacity=0.6)
    for j, p in enumerate(scene.projectors):
        prj_colour = PROJECTOR_COLOURS[j % len(PROJECTOR_COLOURS)]
        devices[p.name] = frustum(p.K, p.width, p.height, p.world_from_prj, 0.3)
        plotter.add_mesh(devices[p.name], color=prj_colour, line_width=2)
        plotter.add_point_labels([p.centre], [f"projector {p.name}"], font_size=11, point_size=6,
                                 text_color=prj_colour, shape_opacity=0.6)
    geometry = {}
    for c in clouds:
        name = f"{c['state']} / {scene.projectors[c['projector']].name}"
        cloud = pv.PolyData(c["points"])
        cloud["decoding contrast"] = c["contrast"]
        geometry[name.replace(" / ", "_")] = cloud
        if colour == "contrast":
            plotter.add_mesh(cloud, scalars="decoding contrast", cmap="viridis", point_size=2,
                             scalar_bar_args=side_bar("decoding contrast (white - black)"))
        else:
            state = [st.name for st in scene.states].index(c["state"])
            plotter.add_mesh(cloud, color=cloud_colour(c["projector"], state, len(scene.states)), point_size=2,
                             label=name)
        # The rays show which pair made a point: the camera's in black, the projector's in its colour.
        for i in rng.choice(len(c["points"]), size=min(rays, len(c["points"])), replace=False):
            x = c["points"][i]
            plotter.add_mesh(pv.Line(c["cam_centre"], x), color="black", line_width=1)
            plotter.add_mesh(pv.Line(c["prj_centre"], x), color=PROJECTOR_COLOURS[c["projector"] % len(PROJECTOR_COLOURS)],
                             line_width=1)
    if colour != "contrast":
        plotter.add_legend(bcolor="white", face="circle", size=(0.16, 0.03 + 0.03 * len(clouds)), loc="upper left")
    plotter.show_bounds(grid=False, location="outer", xtitle="x (m)", ytitle="y (m)", ztitle="z (m)", color="black",
                        font_size=8)
    plotter.add_text(f"Triangulated correspondences of {scene.name}, world frame (m)", position="upper_edge",
                     font_size=10, color="black")
    frame_rig(plotter, {**geometry, **{f"frustum {name}": lines for name, lines in devices.items()}})
    return finish(plotter, out, show, geometry=geometry)


MAX_RAYS = 100  # each ray is a mesh of its own: thousands took minutes to draw and hid the clouds


def _rays(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if not 0 <= value <= MAX_RAYS:
        raise argparse.ArgumentTypeError(f"must be 0-{MAX_RAYS} rays per cloud, got {value}")
    return value


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="output folder of torchproj simulate")
    parser.add_argument("--colour", choices=["projector", "contrast"], default="projector")
    parser.add_argument("--rays", type=_rays, default=6,
                        help=f"sampled correspondences drawn as rays, per cloud (0-{MAX_RAYS}; default 6)")
    parser.add_argument("--points", type=positive_int, default=POINTS_PER_CLOUD,
                        help=f"pairs triangulated and drawn per state and projector (default {POINTS_PER_CLOUD})")
    parser.add_argument("--out", type=Path, help="PNG to write (default RUN_DIR/correspondences.png)")
    parser.add_argument("--show", action="store_true", help="open a window (needs a display)")
    args = parser.parse_args(argv)
    report = args.run_dir / "report.json"
    if not report.is_file():
        parser.error(f"{report} not found: give the --out folder of torchproj simulate")
    fix = "give the --out folder of torchproj simulate, or run it again"
    config = read_json(parser, report, ("config",), fix)["config"]
    scene = read_or_refuse(parser, report, lambda _: load_scene(config), f"the scene it names, {config!r}: {fix}")
    out = args.out or args.run_dir / "correspondences.png"

    def read(path):  # a correspondence per camera pixel
        data, (w, h) = read_npz(parser, path, ("prj_xy", "contrast"), fix), (scene.camera.width, scene.camera.height)
        if data["prj_xy"].shape != (h, w, 2) or data["contrast"].shape != (h, w):
            parser.error(f"{path}: prj_xy of shape {data['prj_xy'].shape} and contrast of shape {data['contrast'].shape} "
                         f"do not fit the scene's {w}x{h} camera: was its config changed after simulate? {fix}")
        return data

    clouds = correspondence_clouds(scene, args.run_dir, args.points, read=read)
    draw_correspondences(scene, clouds, out, args.colour, args.rays, args.show).close()
    print(f"wrote {written(out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
