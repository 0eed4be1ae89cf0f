"""Look at a real scan: the point cloud from ``torchproj decode --calibration``, the largest plane in it
found by RANSAC (a flat target such as the chessboard, not the wall behind it or clutter near the
floor), and each point on that plane coloured by its signed distance to it: the scan's noise and
any calibration bias. Points off the plane are grey.

    python viz/point_cloud.py DECODE_DIR [--threshold 2] [--units mm] [--out FILE.png] [--show]

Distances are in the calibration's units (millimetres for the shipped chessboard). Writes the PNG and,
beside it, ``.vtm`` with the cloud and its distances (``pyvista.read`` or ParaView opens it) and
``.gltf``, the view in its colours for any glTF viewer. Off-screen by default.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pyvista as pv
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import finish, read_points, side_bar, written  # noqa: E402

from torchproj.calib import largest_plane  # noqa: E402
from torchproj.cli_options import positive_float  # noqa: E402

# A few times a structured-light scan's noise in millimetres (0.3-0.6 mm on the shipped chessboard): a
# tolerance derived from the scan itself (1% of its extent, then robust deviations) took in a strip of
# the wall behind the board on the real capture, which lies near the board's plane (RMS 3.3 mm for 0.9).
DEFAULT_THRESHOLD = 2.0


def draw_plane_fit(points: np.ndarray, out: Path | None, show: bool = False, limit: float | None = None,
                   threshold: float | None = None, units: str = "mm",
                   window_size=(1000, 750)) -> tuple[pv.Plotter, np.ndarray, np.ndarray]:
    """Render points :math:`(N, 3)` by signed distance to their largest plane (:func:`largest_plane`).

    Args:
        limit: the colour scale's half-range (default: the 99th percentile of the plane's points).
        threshold: the largest distance of a point on the plane, in the points' units
            (:data:`DEFAULT_THRESHOLD`).

    Returns:
        the plotter, the signed distances :math:`(N,)` and the points on the plane :math:`(N,)`.
    """
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 3:
        raise SystemExit("fewer than 3 points: nothing to fit a plane to")
    threshold = DEFAULT_THRESHOLD if threshold is None else threshold
    centroid, normal, residual, on_plane = (t.numpy() for t in largest_plane(torch.as_tensor(points), threshold))
    near = np.abs(residual[on_plane])
    top = limit if limit is not None else max(float(np.percentile(near, 99)), 1e-9)
    rms = float(np.sqrt(np.mean(residual[on_plane] ** 2)))
    plotter = pv.Plotter(off_screen=not show, window_size=window_size)
    plotter.set_background("white")
    cloud = pv.PolyData(points)
    cloud[f"signed distance ({units})"] = residual
    cloud["on plane"] = on_plane.astype(np.uint8)
    board = cloud.extract_points(on_plane, adjacent_cells=False)
    if (~on_plane).any():
        plotter.add_mesh(cloud.extract_points(~on_plane, adjacent_cells=False), color="lightgrey", point_size=1)
    plotter.add_mesh(board, scalars=f"signed distance ({units})", cmap="RdBu_r", clim=(-top, top), point_size=2,
                     scalar_bar_args=side_bar(f"signed distance to the plane ({units})"))
    plotter.add_text(f"Largest plane (RANSAC, within {threshold:.3g} {units}): {int(on_plane.sum())} of {len(points)} "
                     f"points, RMS {rms:.3g} {units}; grey: off the plane", font_size=10, color="black")
    plotter.camera_position = [centroid - normal * 3 * np.ptp(points, axis=0).max(), centroid, (0, -1, 0)]
    return finish(plotter, out, show, geometry={"cloud": cloud}), residual, on_plane


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("decode_dir", type=Path, help="output folder of torchproj decode --calibration")
    parser.add_argument("--out", type=Path, help="PNG to write (default DECODE_DIR/points.png)")
    parser.add_argument("--threshold", type=positive_float, help="largest distance of a point on the plane, in the calibration's "
                                                            f"units (default {DEFAULT_THRESHOLD:g}, for mm)")
    parser.add_argument("--units", default="mm", help="the calibration's length unit, for the labels (default mm)")
    parser.add_argument("--show", action="store_true", help="open a window (needs a display)")
    args = parser.parse_args(argv)
    ply = args.decode_dir / "points.ply"
    if not ply.is_file():
        parser.error(f"{ply} not found: run torchproj decode with --calibration to triangulate")
    out = args.out or args.decode_dir / "points.png"
    points = read_points(parser, ply, "run torchproj decode with --calibration to triangulate again")
    plotter, residual, on_plane = draw_plane_fit(points, out, args.show,
                                                 threshold=args.threshold, units=args.units)
    plotter.close()
    print(f"{int(on_plane.sum())} of {len(on_plane)} points on the largest plane, RMS "
          f"{np.sqrt(np.mean(residual[on_plane] ** 2)):.3g} {args.units}; wrote {written(out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
