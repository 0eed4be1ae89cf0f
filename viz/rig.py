"""Draw a scene's rig in 3D: projector and camera frusta, and the surfaces of every state.

    python viz/rig.py [CONFIG] [--out rig.png] [--show]

Off-screen PNG by default (pyvista), and beside it ``.vtm`` (every frustum and surface, by name)
and ``.gltf`` (the view, for any glTF viewer); ``--show`` opens a window where a display exists.
Each state's surfaces get their own colour; frusta are drawn to ``--depth`` metres.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pyvista as pv

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import finish, frame_rig, frustum, surface_mesh, written  # noqa: E402

from torchproj.cli_options import positive_float  # noqa: E402
from torchproj.core import ConfigError  # noqa: E402
from torchproj.scene import Scene, load_scene  # noqa: E402

STATE_COLOURS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b"]


def frustum_depth(scene: Scene, meshes: dict | None = None) -> float:
    """How far the frusta reach: just past the farthest surface point any device faces (its depth along
    that device's axis), so that every surface lies inside the lines that show what lights and sees it.
    ``meshes``: each surface's :func:`surface_mesh` by name, where the caller has made them already."""
    meshes = {name: surface_mesh(s) for name, s in scene.surfaces.items()} if meshes is None else meshes
    points = np.vstack([mesh.points for mesh in meshes.values()])
    poses = [scene.camera.world_from_cam, *(p.world_from_prj for p in scene.projectors)]
    far = max(float(((points - pose[:3, 3]) @ pose[:3, 2]).max()) for pose in poses)
    return round(min(max(1.05 * far, 0.1), 20.0), 2)


def draw_rig(scene: Scene, out: Path | None, depth: float | None = None, show: bool = False,
             window_size=(1000, 750)) -> pv.Plotter:
    """``depth``: the frusta's length in metres; None reaches past the farthest surface (:func:`frustum_depth`)."""
    # Each surface meshed once (a mesh surface is a file read): for the frusta's reach and every state it is in.
    meshes = {name: surface_mesh(s) for name, s in scene.surfaces.items()}
    depth = frustum_depth(scene, meshes) if depth is None else depth
    plotter = pv.Plotter(off_screen=not show, window_size=window_size)
    # Text is sized in points, not in parts of the view: scaled with the window so that the title and
    # the axes' labels fit a small one as they fit the default 1000 px.
    pt = window_size[0] / 1000
    cam = scene.camera
    geometry = {"camera": frustum(cam.K, cam.width, cam.height, cam.world_from_cam, depth)}
    plotter.add_mesh(geometry["camera"], color="black", line_width=2)
    plotter.add_point_labels([cam.world_from_cam[:3, 3]], ["camera"], font_size=round(12 * pt), point_size=8)
    for p in scene.projectors:
        lines = geometry[f"projector_{p.name}"] = frustum(p.K, p.width, p.height, p.world_from_prj, depth)
        plotter.add_mesh(lines, color="#d62728", line_width=2)
        plotter.add_point_labels([p.centre], [p.name], font_size=round(12 * pt), point_size=8, text_color="#d62728")
    for i, state in enumerate(scene.states):
        colour = STATE_COLOURS[i % len(STATE_COLOURS)]
        for name in state.surfaces:
            surf = scene.surfaces[name]
            mesh = geometry[f"{state.name}_{name}"] = meshes[name]
            plotter.add_mesh(mesh, color=colour, opacity=0.45 if surf.transmittance else 0.9, label=f"{state.name}: {name}")
    # The legend in a corner the frusta leave free (it covered their lines), axes in metres and a title.
    plotter.add_legend(bcolor="white", face="rectangle", loc="upper left",
                       size=(0.18, 0.03 + 0.03 * sum(len(s.surfaces) for s in scene.states)))
    plotter.show_bounds(grid=False, location="outer", xtitle="x (m)", ytitle="y (m)", ztitle="z (m)", color="black",
                        font_size=max(round(8 * pt), 4))
    plotter.add_text(f"{scene.name}: camera (black), projectors (red), frusta {depth:g} m", position="upper_edge",
                     font_size=round(10 * pt), color="black")
    frame_rig(plotter, geometry)
    return finish(plotter, out, show, geometry=geometry)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", nargs="?", help="YAML file or built-in name (default: paper_two_planes)")
    parser.add_argument("--out", type=Path, default=Path("out/rig.png"))
    parser.add_argument("--depth", type=positive_float,
                        help="frustum length in metres (default: just past the farthest surface)")
    parser.add_argument("--show", action="store_true", help="open a window (needs a display)")
    args = parser.parse_args(argv)
    try:
        scene = load_scene(args.config)
    except ConfigError as exc:  # a misspelt name or field, said as the command says it
        parser.error(str(exc))
    draw_rig(scene, args.out, args.depth, args.show).close()
    print(f"wrote {written(args.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
