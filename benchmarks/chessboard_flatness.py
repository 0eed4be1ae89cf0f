"""Flatness of the triangulated real chessboard: integer Gray-code cells against sub-pixel refinement
over the integer cells and over the cells' means (what calibration uses); and how much light its
pixels measured past the cells beside their own (what the ``area`` rows' fit checks).

    python benchmarks/chessboard_flatness.py --out benchmarks/results/chessboard_flatness

For both captures of ``../shared/data/procam_chessboard``: decode, triangulate with the shipped
OpenCV calibration, keep the points inside the convex hull of the detected 9x7 inner corners, fit a
plane and report the RMS residual (mm). The data's README quotes a plain OpenCV pipeline at about
0.58 mm (capture_0) and 0.37 mm (capture_1); ``tests/calib/test_real_data.py`` recomputes that
reference with OpenCV and checks torchproj against it. Over the decoded pixels of the whole frame,
the light measured past cells ``n +- 1`` (:attr:`torchproj.calib.CellShares.outside`, the larger of
the two axes): its median and the share of pixels above the limit over which the ``area`` footprint
leaves a row unfitted.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

from common import write_results
from torchproj.calib import (cell_shares, decode_gray, fill_holes, fit_plane, read_graycode_folder,
                             read_opencv_calibration, refine_subpixel, triangulate)
from torchproj.transport.build import _SHARE_OUTSIDE

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "procam_chessboard"
README_MM = {"capture_0": 0.58, "capture_1": 0.37}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/chessboard_flatness"))
    args = parser.parse_args(argv)
    if not DATA.is_dir():
        print(f"real captures not found at {DATA}", file=sys.stderr)
        return 1
    calib = read_opencv_calibration(DATA / "calibration_result.xml")
    rows = []
    for name in ("capture_0", "capture_1"):
        cap = read_graycode_folder(DATA / name, (1024, 768))
        dec = decode_gray(cap.patterns, cap.white, cap.black, (1024, 768))
        white = np.round(cap.white[0].numpy() * 255).astype(np.uint8)
        ok, corners = cv2.findChessboardCorners(white, (9, 7))
        mask = np.zeros(white.shape, np.uint8)
        cv2.fillConvexPoly(mask, cv2.convexHull(corners.reshape(-1, 2)).astype(np.int32), 1)
        row = {"capture": name, "opencv_pipeline_readme_mm": README_MM[name]}
        refined = refine_subpixel(dec.prj_xy, dec.valid)
        shares = cell_shares(cap.patterns, cap.white, cap.black, dec, (1024, 768))
        means = refine_subpixel(shares.means(), dec.valid)
        outside = shares.outside[dec.valid].amax(-1)
        row["outside_median"] = float(outside.median())
        row["outside_above_limit"] = float((outside > _SHARE_OUTSIDE).float().mean())
        for label, xy in [("integer", dec.prj_xy), ("subpixel", refined), ("means", means),
                          ("means_filled", fill_holes(means))]:
            sel = torch.isfinite(xy).all(-1) & torch.from_numpy(mask.astype(bool))
            ys, xs = torch.nonzero(sel, as_tuple=True)
            pts = triangulate(torch.stack([xs, ys], -1).double(), xy[sel].double(), calib)
            rms = float(fit_plane(pts)[2].pow(2).mean().sqrt())
            row[f"{label}_rms_mm"] = rms
            row[f"{label}_points"] = int(sel.sum())
        rows.append(row)
    args.out.mkdir(parents=True, exist_ok=True)
    write_results(args.out, rows)
    lines = ["# Chessboard flatness (plane-fit RMS, mm, inside the board's corner hull)", "",
             f"Command: `python benchmarks/chessboard_flatness.py {' '.join(argv if argv is not None else sys.argv[1:])}`", "",
             "| capture | OpenCV pipeline (data README) | torchproj integer | sub-pixel over integer cells | "
             "sub-pixel over cell means (calibration's) | the same + hole filling | light past the neighbour "
             f"cells (median) | pixels above the area fit's limit {_SHARE_OUTSIDE:g} |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['capture']} | {r['opencv_pipeline_readme_mm']:.2f} | {r['integer_rms_mm']:.3f} "
                     f"({r['integer_points']} pts) | {r['subpixel_rms_mm']:.3f} | {r['means_rms_mm']:.3f} | "
                     f"{r['means_filled_rms_mm']:.3f} ({r['means_filled_points']} pts) | {r['outside_median']:.3f} | "
                     f"{r['outside_above_limit']:.2%} |")
    (args.out / "results.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
