"""Look at a positioning scan: the scanned box coloured by its signed distance to the goal box (mm),
with the goal box as a red wireframe, where the trial started in grey and where it was placed in black.

    python viz/positioning.py OUT_DIR [--trial near_0] [--out FILE.png] [--max-mm 10] [--show]

OUT_DIR is what ``torchproj position --out`` wrote. Without ``--trial`` every scan gets a PNG,
``OUT_DIR/views/TRIAL.png``, all on one colour scale so that they can be compared, and beside each a
``.vtm`` with the scan and its distances and a ``.gltf`` of the view (any glTF viewer opens it).
Off-screen by default; ``--show`` opens a window where a
display exists.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pyvista as pv

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import box_wireframe, finish, read_npz, side_bar, written  # noqa: E402

from torchproj.cli_options import positive_float  # noqa: E402
from torchproj.experiments import box_surface_distance, pose_error  # noqa: E402


def signed_distances_mm(scan: dict) -> np.ndarray:
    """Each scanned point's signed distance to the goal box's surface, mm (negative: inside it)."""
    return box_surface_distance(np.asarray(scan["points"], dtype=np.float64), scan["goal_pose"], scan["box_size"],
                                signed=True) * 1000


def draw_scan(scan: dict, out: Path | None, max_mm: float | None = None, show: bool = False, title: str = "",
              window_size=(1000, 750)) -> pv.Plotter:
    """Render one scan (``points`` (N, 3) metres, ``goal_pose`` 4x4, ``box_size`` (3,) metres, and where
    they are there, ``start_pose`` and ``placed_pose``).

    Colours run from ``-max_mm`` to ``max_mm`` (default: the 99th percentile of the absolute distances,
    at least 1 mm); give the same ``max_mm`` to views that are compared.
    """
    points = np.asarray(scan["points"], dtype=np.float64)
    if len(points) == 0:
        raise SystemExit("this scan has no points (nothing decoded): nothing to draw")
    dist_mm = signed_distances_mm(scan)
    top = max_mm if max_mm is not None else max(1.0, float(np.percentile(np.abs(dist_mm), 99)))
    plotter = pv.Plotter(off_screen=not show, window_size=window_size)
    plotter.set_background("white")
    cloud = pv.PolyData(points)
    cloud["signed distance to goal (mm)"] = dist_mm
    plotter.add_mesh(cloud, scalars="signed distance to goal (mm)", cmap="RdBu_r", clim=(-top, top), point_size=3,
                     render_points_as_spheres=False,
                     scalar_bar_args=side_bar("signed distance to goal box (mm)", "%.1f"))
    geometry = {"scan": cloud}
    legend = [["goal", "red"]]
    for key, colour, label in (("start_pose", "grey", "start"), ("placed_pose", "black", "placed")):
        if key in scan:
            plotter.add_mesh(box_wireframe(scan[key], scan["box_size"]), color=colour, line_width=2)
            legend.append([label, colour])
    plotter.add_mesh(box_wireframe(scan["goal_pose"], scan["box_size"]), color="red", line_width=3)
    plotter.add_legend(legend, bcolor="white", loc="lower left", size=(0.1, 0.09))
    rmse = float(np.sqrt(np.mean(dist_mm ** 2)))
    heading = f"{title}: " if title else ""
    heading += f"scan RMSE {rmse:.2f} mm from the goal box"
    if "placed_pose" in scan:
        error = pose_error(np.asarray(scan["placed_pose"]), np.asarray(scan["goal_pose"]))
        heading += f"; placed {error['distance_mm']:.2f} mm, {error['rotation_deg']:.2f} deg from the goal"
    plotter.add_text(heading, font_size=10, color="black")
    # Seen from the rig's side, a little above and to the right, as the camera sees the box.
    centre = np.asarray(scan["goal_pose"])[:3, 3]
    plotter.camera_position = [centre + np.array([0.35, -0.25, -0.6]), centre, (0, -1, 0)]
    return finish(plotter, out, show, geometry=geometry)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="output folder of torchproj position")
    parser.add_argument("--trial", help="scan name, e.g. near_0 (default: every scan)")
    parser.add_argument("--out", type=Path, help="PNG to write (with --trial; default OUT_DIR/views/TRIAL.png)")
    parser.add_argument("--max-mm", type=positive_float, help="half-range of the colour scale in mm (default: the 99th "
                        "percentile of the absolute distances over every scan drawn)")
    parser.add_argument("--show", action="store_true", help="open a window (needs a display)")
    args = parser.parse_args(argv)
    scans = sorted((args.run_dir / "scans").glob("*.npz"))
    if not scans:
        parser.error(f"{args.run_dir}/scans holds no .npz scans: give the --out folder of torchproj position")
    if args.trial:
        scans = [p for p in scans if p.stem == args.trial]
        if not scans:
            parser.error(f"no scan named {args.trial!r} in {args.run_dir}/scans")
    fix = "give the --out folder of torchproj position, or run it again"
    loaded = {path.stem: read_npz(parser, path, ("points", "goal_pose", "box_size"), fix) for path in scans}
    top = args.max_mm
    if top is None:  # one scale for every view, so that they can be compared
        top = max(1.0, float(np.percentile(np.abs(np.concatenate([signed_distances_mm(s) for s in loaded.values()
                                                                   if len(s["points"])])), 99)))
    for name, scan in loaded.items():
        out = args.out if (args.out and args.trial) else args.run_dir / "views" / f"{name}.png"
        draw_scan(scan, out, top, args.show, title=f"scan {name}").close()
        print(f"wrote {written(out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
