"""Real Gray-code captures (../shared/data/procam_chessboard): OpenCV is the reference."""

import json

import cv2
import numpy as np
import pytest
import torch

from torchproj.calib import (cell_means, decode_gray, fit_plane, read_graycode_folder, read_opencv_calibration,
                             refine_subpixel, triangulate)
from torchproj.cli import main


@pytest.fixture(scope="module")
def decoded(request):
    from ..helpers import CHESSBOARD

    if not (CHESSBOARD / "capture_0" / "graycode_41.png").is_file():
        pytest.skip(f"real captures not found at {CHESSBOARD} (they live in ../shared/data beside the checkout)")
    out = {}
    for name in ("capture_0", "capture_1"):
        cap = read_graycode_folder(CHESSBOARD / name, (1024, 768))
        out[name] = (cap, decode_gray(cap.patterns, cap.white, cap.black, (1024, 768)))
    return CHESSBOARD, out


@pytest.mark.parametrize("name", ["capture_0", "capture_1"])
def test_decoder_agrees_with_opencv_getprojpixel(decoded, name):
    root, caps = decoded
    cap, dec = caps[name]
    raw = [cv2.imread(str(root / name / f"graycode_{i:02d}.png"), cv2.IMREAD_GRAYSCALE) for i in range(42)]
    gc = cv2.structured_light.GrayCodePattern.create(1024, 768)
    shadow = np.abs(raw[40].astype(int) - raw[41].astype(int)) > 40
    rng = np.random.default_rng(1)
    both = agree = 0
    for _ in range(3000):
        y, x = int(rng.integers(0, 1024)), int(rng.integers(0, 1280))
        if not shadow[y, x]:
            assert not dec.valid[y, x]
            continue
        err, pix = gc.getProjPixel(raw[:40], x, y)
        if not err and dec.valid[y, x]:
            both += 1
            agree += (int(pix[0]), int(pix[1])) == (int(dec.prj_xy[y, x, 0]), int(dec.prj_xy[y, x, 1]))
    assert both > 1000
    assert agree / both >= 0.995


def _board_mask(white: np.ndarray) -> np.ndarray:
    ok, corners = cv2.findChessboardCorners(white, (9, 7))
    assert ok, "the chessboard's 9x7 inner corners should be found in the white capture"
    mask = np.zeros(white.shape, np.uint8)
    cv2.fillConvexPoly(mask, cv2.convexHull(corners.reshape(-1, 2)).astype(np.int32), 1)
    return mask.astype(bool)


def _plane_rms(points) -> float:
    residuals = fit_plane(torch.as_tensor(points, dtype=torch.float64))[2]
    return float(residuals.pow(2).mean().sqrt())


def _opencv_pipeline_rms(root, name, mask, calib_path, n=4000):
    """The plain OpenCV pipeline of the data's README: getProjPixel, undistortPoints, triangulatePoints."""
    raw = [cv2.imread(str(root / name / f"graycode_{i:02d}.png"), cv2.IMREAD_GRAYSCALE) for i in range(42)]
    gc = cv2.structured_light.GrayCodePattern.create(1024, 768)
    shadow = np.abs(raw[40].astype(int) - raw[41].astype(int)) > 40
    ys, xs = np.nonzero(mask & shadow)
    pick = np.random.default_rng(2).choice(len(xs), size=n, replace=False)
    cam, prj = [], []
    for i in pick:
        err, pix = gc.getProjPixel(raw[:40], int(xs[i]), int(ys[i]))
        if not err:
            cam.append((xs[i], ys[i]))
            prj.append(pix)
    fs = cv2.FileStorage(str(calib_path), cv2.FILE_STORAGE_READ)
    K1, d1, K2, d2 = (fs.getNode(k).mat() for k in ("cam_int", "cam_dist", "proj_int", "proj_dist"))
    R, T = fs.getNode("roration").mat(), fs.getNode("translation").mat()
    c = cv2.undistortPoints(np.array(cam, np.float64).reshape(-1, 1, 2), K1, d1)
    p = cv2.undistortPoints(np.array(prj, np.float64).reshape(-1, 1, 2), K2, d2)
    X = cv2.triangulatePoints(np.hstack([np.eye(3), np.zeros((3, 1))]), np.hstack([R, T]), c, p)
    return _plane_rms((X[:3] / X[3]).T)


@pytest.mark.parametrize("name,readme_mm", [("capture_0", 0.58), ("capture_1", 0.37)])
def test_triangulated_board_is_as_flat_as_the_opencv_pipeline(decoded, name, readme_mm):
    root, caps = decoded
    cap, dec = caps[name]
    calib_path = root / "calibration_result.xml"
    calib = read_opencv_calibration(calib_path)
    mask = _board_mask(np.round(cap.white[0].numpy() * 255).astype(np.uint8))
    reference = _opencv_pipeline_rms(root, name, mask, calib_path)
    assert reference == pytest.approx(readme_mm, abs=0.03)
    sel = dec.valid & torch.from_numpy(mask)
    ys, xs = torch.nonzero(sel, as_tuple=True)
    cam = torch.stack([xs, ys], -1).double()
    integer = _plane_rms(triangulate(cam, dec.prj_xy[sel].double(), calib).numpy())
    refined_xy = refine_subpixel(dec.prj_xy, dec.valid)
    refined = _plane_rms(triangulate(cam, refined_xy[sel].double(), calib).numpy())
    means_xy = refine_subpixel(cell_means(cap.patterns, cap.white, cap.black, dec, (1024, 768)), dec.valid)
    means = _plane_rms(triangulate(cam, means_xy[sel].double(), calib).numpy())
    assert integer == pytest.approx(reference, rel=0.05)  # same decoding, same geometry
    assert refined < reference  # sub-pixel refinement helps on real data
    assert means < refined  # and more over the cells' mean than over the integer cells


@pytest.mark.slow
def test_decode_command_on_real_captures(decoded, tmp_path):
    root, _ = decoded
    out = tmp_path / "dec"
    assert main(["decode", str(root / "capture_1"), "--projector", "1024x768", "--out", str(out),
                 "--calibration", str(root / "calibration_result.xml")]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["valid_fraction"] == pytest.approx(0.45, abs=0.02)  # the data's README: 45%
    assert report["decode_s"] > 0
    data = np.load(out / "correspondence.npz")
    assert data["prj_xy"].shape == (1024, 1280, 2) and data["prj_xy"].dtype == np.float32
    assert data["points"].shape == (1024, 1280, 3) and data["points"].dtype == np.float32
    valid = np.isfinite(data["prj_xy"]).all(-1)
    assert valid.mean() == pytest.approx(report["valid_fraction"])
    z = data["points"][..., 2][np.isfinite(data["points"][..., 2])]
    assert 2000 < np.median(z) < 2600  # millimetres: the board is at about 2.3 m
    assert (out / "points.ply").read_bytes().startswith(b"ply\n")
    assert (out / "decoded.png").stat().st_size > 10_000
