"""Look at a real scan: the point cloud from ``torchproj decode --calibration`` coloured by its
distance to the best-fitting plane (for a flat target such as the chessboard, this is the scan's
noise and any calibration bias).

    python viz/point_cloud.py DECODE_DIR [--out FILE.png] [--show]

Distances are in the calibration's units (usually millimetres). Off-screen by default.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pyvista as pv
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import finish  # noqa: E402

from torchproj.calib import fit_plane  # noqa: E402


def draw_plane_fit(points: np.ndarray, out: Path | None, show: bool = False, limit: float | None = None,
                   window_size=(1000, 750)) -> tuple[pv.Plotter, np.ndarray]:
    """Render points :math:`(N, 3)` coloured by signed distance to their least-squares plane.

    Returns:
        the plotter and the signed distances :math:`(N,)`.
    """
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 3:
        raise SystemExit("fewer than 3 points: nothing to fit a plane to")
    centroid, normal, residual = (t.numpy() for t in fit_plane(torch.as_tensor(points)))
    top = limit if limit is not None else max(float(np.percentile(np.abs(residual), 99)), 1e-9)
    plotter = pv.Plotter(off_screen=not show, window_size=window_size)
    plotter.set_background("white")
    cloud = pv.PolyData(points)
    cloud["distance to plane"] = np.clip(residual, -top, top)
    plotter.add_mesh(cloud, scalars="distance to plane", cmap="coolwarm", clim=(-top, top), point_size=2,
                     scalar_bar_args={"title": "distance to fitted plane", "color": "black"})
    plotter.add_text(f"{len(points)} points, RMS {np.sqrt(np.mean(residual**2)):.3g} from the plane",
                     font_size=10, color="black")
    plotter.camera_position = [centroid - normal * 3 * np.ptp(points, axis=0).max(), centroid, (0, -1, 0)]
    return finish(plotter, out, show), residual


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("decode_dir", type=Path, help="output folder of torchproj decode --calibration")
    parser.add_argument("--out", type=Path, help="PNG to write (default DECODE_DIR/points.png)")
    parser.add_argument("--show", action="store_true", help="open a window (needs a display)")
    args = parser.parse_args(argv)
    ply = args.decode_dir / "points.ply"
    if not ply.is_file():
        parser.error(f"{ply} not found: run torchproj decode with --calibration to triangulate")
    out = args.out or args.decode_dir / "points.png"
    plotter, _ = draw_plane_fit(np.asarray(pv.read(ply).points), out, args.show)
    plotter.close()
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
