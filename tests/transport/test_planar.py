"""One homography per plane: the fit against OpenCV's, the map, the planarity test, the virtual rig."""

import cv2
import numpy as np
import pytest
import torch

from torchproj.core import InputError
from torchproj.core.conventions import pixel_grid
from torchproj.pipeline import run_virtual
from torchproj.transport import StateCalibration, fit_homography, homography_map, planar_calibration

from ..helpers import calibrate_once, small_scene

TRUE_H = torch.tensor([[0.62, 0.05, 12.0], [-0.03, 0.58, 9.0], [1e-4, -6e-5, 1.0]], dtype=torch.float64)


def apply(h: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    p = torch.cat([xy, torch.ones_like(xy[..., :1])], -1) @ h.T
    return p[..., :2] / p[..., 2:]


def decoded_like(h=TRUE_H, shape=(120, 160), bit_errors=0.01, seed=0) -> torch.Tensor:
    """A decoded map of a plane: integer cells (quantised as Gray code decodes), some bit errors, a hole."""
    g = torch.Generator().manual_seed(seed)
    xy = torch.floor(apply(h, pixel_grid(*shape, dtype=torch.float64)) + 0.5)
    wrong = torch.rand(shape, generator=g) < bit_errors
    xy[wrong] += torch.tensor([64.0, -32.0], dtype=torch.float64)  # a flipped high bit: far off
    xy[50:60, 70:80] = float("nan")
    return xy.float()


def test_fit_matches_opencv_and_the_truth_despite_bit_errors():
    xy = decoded_like()
    fit = fit_homography(xy)
    ok = torch.isfinite(xy).all(-1)
    cam = pixel_grid(*xy.shape[:2], dtype=torch.float64)[ok].numpy()
    ref, _ = cv2.findHomography(cam, xy[ok].double().numpy(), cv2.LMEDS)  # robust to the 1% bit errors
    grid = pixel_grid(*xy.shape[:2], dtype=torch.float64).reshape(-1, 2)
    ours, theirs, truth = apply(fit.matrix, grid), apply(torch.from_numpy(ref), grid), apply(TRUE_H, grid)
    # Quantisation to whole cells averages out over many pixels: both fits land far inside a cell.
    assert (ours - truth).norm(dim=-1).max() < 0.1
    assert (ours - theirs).norm(dim=-1).max() < 0.1
    # 99% of pixels sit within half a cell diagonal of the fit; the 1% bit errors do not move the p95.
    assert fit.p95 < 0.75 and fit.median < 0.5
    assert fit.points == int(ok.sum()) and fit.fitted_on <= 20000


def test_map_covers_exactly_the_mask_and_clamps_to_the_image():
    mask = torch.zeros(120, 160, dtype=torch.bool)
    mask[10:100, 0:150] = True
    shift = torch.tensor([[1.0, 0, -3.2], [0, 1.0, 0], [0, 0, 1.0]], dtype=torch.float64)  # column 0 -> x = -3.2
    out = homography_map(shift, mask, (100, 200))
    assert torch.equal(torch.isfinite(out).all(-1), mask)
    expected = apply(shift, pixel_grid(120, 160, dtype=torch.float64))[mask]
    inside = (expected[:, 0] >= -0.5) & (expected[:, 0] < 99.5)
    assert torch.allclose(out[mask][inside].double(), expected[inside], atol=1e-4)
    # Clamped onto the first and last cells, not dropped.
    assert float(out[mask][:, 0].min()) == -0.5
    assert 99.49 < float(out[mask][:, 0].max()) < 99.5


def test_a_folded_surface_is_refused_with_the_state_and_projector_named():
    left = decoded_like(bit_errors=0)
    right = decoded_like(TRUE_H @ torch.tensor([[1.0, 0, 8.0], [0, 1.1, 0], [0, 0, 1]], dtype=torch.float64),
                         bit_errors=0)
    folded = torch.cat([left[:, :80], right[:, 80:]], 1)
    weight = torch.ones(120, 160)
    states = {"flat": StateCalibration([left, left], [weight, weight], [(256, 192)] * 2),
              "box": StateCalibration([left, folded], [weight, weight], [(256, 192)] * 2)}
    with pytest.raises(InputError, match=r"state 'box', projector 1: the decoded map is not one plane"):
        planar_calibration(states)
    with pytest.raises(InputError, match=r"state 'box', projector 'lower': the decoded map is not one plane.*"
                                         r"raise the tolerance \(--plane-tolerance; plane_tolerance= in Python\)"):
        planar_calibration(states, names=["upper", "lower"])
    planar, fits = planar_calibration({"flat": states["flat"]})
    assert fits["flat"][0].p95 < 0.75
    assert torch.equal(planar["flat"].lit(), states["flat"].lit())
    assert planar["flat"].weight[0] is weight  # the measured weights stay


@pytest.fixture(scope="module")
def planes():
    scene = small_scene("paper_two_planes", camera=(400, 300), projector=(256, 192))
    return scene, calibrate_once(scene)


def test_on_the_virtual_rig_the_planar_map_is_closer_to_the_exact_geometry(planes):
    scene, cal = planes
    planar, fits = planar_calibration(cal.states)
    for state, decoded in cal.states.items():
        for j, (xy, hom) in enumerate(zip(decoded.prj_xy, planar[state].prj_xy)):
            truth = cal.rig.geometry(state).prj_xy[j]
            ok = torch.isfinite(xy).all(-1) & torch.isfinite(truth).all(-1)
            err_decoded = (xy[ok] - truth[ok]).norm(dim=-1)
            err_planar = (hom[ok] - truth[ok]).norm(dim=-1)
            assert float(err_planar.median()) < 0.5 * float(err_decoded.median())
            assert float(err_planar.quantile(0.95)) < float(err_decoded.quantile(0.95))
            assert fits[state][j].p95 < 1.0


def test_run_with_homography_maps_reports_the_fits_and_keeps_quality(planes):
    scene, cal = planes
    decoded = run_virtual(scene, calibration=cal, progress=False).report
    planar = run_virtual(scene, calibration=cal, maps="homography", progress=False).report
    assert planar["maps"] == "homography" and set(planar["homographies"]) == {"near", "far"}
    assert all(len(v) == 2 and v[0]["p95_px"] < 1 for v in planar["homographies"].values())
    for a, b in zip(planar["targets"], decoded["targets"]):
        assert a["pixels"] == b["pixels"]  # the same camera pixels are modelled and scored
        assert a["psnr_db"] > b["psnr_db"] - 0.1


def test_a_box_is_not_a_plane():
    scene = small_scene("box_positions", camera=(400, 300), projector=(256, 192), supersampling=2)
    with pytest.raises(InputError, match=r"state '\w+', projector '(upper|lower)': the decoded map is not one plane"):
        run_virtual(scene, maps="homography", progress=False)


def test_maps_must_be_known():
    with pytest.raises(InputError, match=r"maps must be one of \['decoded', 'homography'\], got 'mesh'"):
        run_virtual(small_scene(), maps="mesh", progress=False)


def test_too_few_points_are_refused():
    xy = torch.full((10, 10, 2), float("nan"))
    xy[0, :3] = torch.tensor(np.array([[0, 0], [1, 0], [2, 0]], dtype=np.float32))
    with pytest.raises(InputError, match="at least 4 decoded pixels"):
        fit_homography(xy)


@pytest.fixture(scope="module")
def board():
    from torchproj.calib import decode_gray, read_graycode_folder, refine_subpixel

    from ..helpers import CHESSBOARD

    if not (CHESSBOARD / "capture_0" / "graycode_41.png").is_file():
        pytest.skip(f"real captures not found at {CHESSBOARD} (they live in ../shared/data beside the checkout)")
    cap = read_graycode_folder(CHESSBOARD / "capture_0", (1024, 768))
    dec = decode_gray(cap.patterns, cap.white, cap.black, (1024, 768))
    white = np.round(cap.white[0].numpy() * 255).astype(np.uint8)
    ok, corners = cv2.findChessboardCorners(white, (9, 7))
    assert ok
    hull = np.zeros(white.shape, np.uint8)
    cv2.fillConvexPoly(hull, cv2.convexHull(corners.reshape(-1, 2)).astype(np.int32), 1)
    return refine_subpixel(dec.prj_xy, dec.valid), torch.from_numpy(hull.astype(bool))


def test_the_real_chessboard_is_one_plane_and_the_whole_frame_is_not(board):
    xy, hull = board
    on_board = torch.where(hull[..., None], xy, float("nan"))
    fit = fit_homography(on_board)
    # A real plane through real lenses: within the default tolerance of one homography.
    assert fit.p95 < 1.0 and fit.points > 100_000
    ok = torch.isfinite(on_board).all(-1)
    cam = pixel_grid(*xy.shape[:2], dtype=torch.float64)[ok]
    ref, _ = cv2.findHomography(cam.numpy(), on_board[ok].double().numpy(), cv2.LMEDS)
    gap = (apply(fit.matrix, cam) - apply(torch.from_numpy(ref), cam)).norm(dim=-1)
    assert float(gap.quantile(0.95)) < 0.2  # the same plane as OpenCV's robust fit, to a fifth of a cell
    # The board together with the room around it is not one plane, and is refused.
    weight = torch.ones(xy.shape[:2])
    with pytest.raises(InputError, match="not one plane"):
        planar_calibration({"room": StateCalibration([xy], [weight], [(1024, 768)])})
    planar, _ = planar_calibration({"board": StateCalibration([on_board], [weight], [(1024, 768)])})
    assert torch.equal(planar["board"].lit(), ok)
