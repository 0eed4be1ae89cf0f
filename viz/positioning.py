"""Look at a positioning scan: the scanned box coloured by its distance to the goal box (mm), with
the goal box as a red wireframe.

    python viz/positioning.py OUT_DIR [--trial near_0] [--out FILE.png] [--max-mm 10] [--show]

OUT_DIR is what ``torchproj position --out`` wrote. Without ``--trial`` every scan gets a PNG,
``OUT_DIR/views/TRIAL.png``. Off-screen by default; ``--show`` opens a window where a display exists.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pyvista as pv

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import box_wireframe, finish  # noqa: E402

from torchproj.experiments import box_surface_distance  # noqa: E402


def draw_scan(scan: dict, out: Path | None, max_mm: float | None = None, show: bool = False, title: str = "",
              window_size=(1000, 750)) -> pv.Plotter:
    """Render one scan (``points`` (N, 3) metres, ``goal_pose`` 4x4, ``box_size`` (3,) metres).

    Colours run from 0 to ``max_mm`` (default: the 99th percentile of the distances, at least 1 mm).
    """
    points = np.asarray(scan["points"], dtype=np.float64)
    if len(points) == 0:
        raise SystemExit("this scan has no points (nothing decoded): nothing to draw")
    dist_mm = box_surface_distance(points, scan["goal_pose"], scan["box_size"]) * 1000
    top = max_mm if max_mm is not None else max(1.0, float(np.percentile(dist_mm, 99)))
    plotter = pv.Plotter(off_screen=not show, window_size=window_size)
    plotter.set_background("white")
    cloud = pv.PolyData(points)
    cloud["distance to goal (mm)"] = np.minimum(dist_mm, top)
    plotter.add_mesh(cloud, scalars="distance to goal (mm)", cmap="plasma", clim=(0, top), point_size=3,
                     render_points_as_spheres=False,
                     scalar_bar_args={"title": "distance to goal box (mm)", "color": "black"})
    plotter.add_mesh(box_wireframe(scan["goal_pose"], scan["box_size"]), color="red", line_width=3)
    if title:
        plotter.add_text(title, font_size=10, color="black")
    # Seen from the rig's side, a little above and to the right, as the camera sees the box.
    centre = np.asarray(scan["goal_pose"])[:3, 3]
    plotter.camera_position = [centre + np.array([0.35, -0.25, -0.6]), centre, (0, -1, 0)]
    return finish(plotter, out, show)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="output folder of torchproj position")
    parser.add_argument("--trial", help="scan name, e.g. near_0 (default: every scan)")
    parser.add_argument("--out", type=Path, help="PNG to write (with --trial; default OUT_DIR/views/TRIAL.png)")
    parser.add_argument("--max-mm", type=float, help="top of the colour scale in mm (default: 99th percentile)")
    parser.add_argument("--show", action="store_true", help="open a window (needs a display)")
    args = parser.parse_args(argv)
    scans = sorted((args.run_dir / "scans").glob("*.npz"))
    if not scans:
        parser.error(f"{args.run_dir}/scans holds no .npz scans: give the --out folder of torchproj position")
    if args.trial:
        scans = [p for p in scans if p.stem == args.trial]
        if not scans:
            parser.error(f"no scan named {args.trial!r} in {args.run_dir}/scans")
    for path in scans:
        scan = dict(np.load(path))
        out = args.out if (args.out and args.trial) else args.run_dir / "views" / f"{path.stem}.png"
        draw_scan(scan, out, args.max_mm, args.show, title=f"scan {path.stem}").close()
        print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
