"""Shortened Gray-code sequences read through one homography: the fit to blocks, its refusals, and
the calibration of coarse captures against the simulator's truth and the real chessboard."""

from dataclasses import replace

import cv2
import numpy as np
import pytest
import torch

from torchproj.calib import calibrate_projector, decode_gray, fit_homography, graycode_patterns, read_graycode_folder, sequence_bits
from torchproj.pipeline import simulate_calibration
from torchproj.core import InputError
from torchproj.core.conventions import pixel_grid
from torchproj.pipeline import calibrate_virtual
from torchproj.sim import VirtualRig

from ..helpers import CHESSBOARD, small_scene

TRUE_H = torch.tensor([[0.95, 0.08, 12.0], [-0.05, 1.02, 7.0], [1e-4, -6e-5, 1.0]], dtype=torch.float64)


def apply(h, pts):
    q = torch.cat([pts, torch.ones(len(pts), 1, dtype=pts.dtype)], 1) @ h.T
    return q[:, :2] / q[:, 2:]


def block_map(h, shape, size, block, flip=0.0, seed=0):
    """The block centres a plane seen through ``h`` decodes to, computed from the block arithmetic
    alone (no Gray code): cells floor(x / b) * b ..., cut at the image edge."""
    cam = pixel_grid(*shape, dtype=torch.float64).reshape(-1, 2)
    xy = apply(h, cam)
    cell = torch.floor(xy + 0.5)
    out = torch.full_like(xy, float("nan"))
    for axis, (b, n) in enumerate(zip(block, size)):
        first = torch.div(cell[:, axis], b, rounding_mode="floor") * b
        if flip:  # bit errors: a fraction of the pixels decode to a neighbouring block
            g = torch.Generator().manual_seed(seed + axis)
            wrong = torch.rand(len(first), generator=g) < flip
            first[wrong] += b * torch.where(torch.rand(int(wrong.sum()), generator=g) < 0.5, -1.0, 1.0)
        out[:, axis] = (first + torch.clamp(first + b, max=n) - 1) / 2
    inside = ((cell >= 0) & (cell < torch.tensor(size, dtype=cell.dtype))).all(-1)
    out[~inside] = float("nan")
    return out.reshape(*shape, 2).float()


def gap(h, cam):
    return float((apply(h, cam) - apply(TRUE_H, cam)).norm(dim=-1).max())


@pytest.mark.parametrize("block", [(8, 8), (32, 32), (64, 32)])
def test_a_homography_is_recovered_from_blocks_to_a_fraction_of_a_cell(block):
    blocks = block_map(TRUE_H, (240, 320), (256, 192), block)
    fit = fit_homography(blocks, block=block)
    cam = pixel_grid(240, 320, dtype=torch.float64).reshape(-1, 2)
    # The block centres are off by up to half a block; the fit to the block edges is not.
    centre_error = float((blocks.reshape(-1, 2).double() - apply(TRUE_H, cam)).norm(dim=-1).nanmean())
    assert centre_error > block[0] / 5
    assert gap(fit.matrix, cam) < 0.1
    assert fit.p95 < 0.5 and fit.block == block


def test_bit_errors_do_not_pull_the_block_fit():
    blocks = block_map(TRUE_H, (240, 320), (256, 192), (32, 32), flip=0.01)
    fit = fit_homography(blocks, block=(32, 32))
    cam = pixel_grid(240, 320, dtype=torch.float64).reshape(-1, 2)
    # 1% of pixels a block off, anywhere in the image; without the filter of isolated pixels the
    # fit is 1.8 px off.
    assert gap(fit.matrix, cam) < 0.3
    assert fit.p95 < 1.0  # the flipped pixels do not make the plane look folded


def test_a_fold_is_refused_even_where_blocks_hide_it():
    # Two planes meeting along a line: within a block nothing shows it, at the block edges it does.
    other = TRUE_H @ torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [8e-4, 0.0, 1.0]], dtype=torch.float64)
    a = block_map(TRUE_H, (240, 320), (256, 192), (32, 32))
    b = block_map(other, (240, 320), (256, 192), (32, 32))
    folded = torch.cat([a[:, :160], b[:, 160:]], 1)
    fit = fit_homography(folded, block=(32, 32))
    assert fit.p95 > 1.0


def test_too_few_block_edges_are_refused():
    blocks = block_map(TRUE_H, (240, 320), (256, 192), (128, 96))  # one bit per axis: one edge each
    with pytest.raises(InputError, match="1 column and 1 row edges, a homography needs at least 2"):
        fit_homography(blocks, block=(128, 96))
    # A surface inside one block shows no edge at all: the start's fit on its one centre is degenerate,
    # and the count, not the degenerate fit, says what to do.
    one = torch.where(torch.isfinite(blocks), torch.tensor([64.0, 48.0]), blocks)
    with pytest.raises(InputError, match="0 column and 0 row edges.*--bits"):
        fit_homography(one, block=(128, 96))


def test_sequence_bits_and_the_shortened_patterns():
    assert sequence_bits(1024, 768) == (10, 10)
    assert sequence_bits(1024, 768, 3) == (3, 3) and sequence_bits(100, 60, 6) == (6, 6)
    assert sequence_bits(100, 60, (4, 2)) == (4, 2) and sequence_bits(100, 60, (7, 6)) == (7, 6)
    # One number that covers the whole sequence is no shortening: refused, not read through a homography.
    for bits in (7, 10, 40):
        with pytest.raises(InputError, match=r"whole Gray-code sequence .* \(7 x 6 pattern pairs\).* fewer than 7"):
            sequence_bits(100, 60, bits)
    with pytest.raises(InputError, match="at least 2 Gray-code bits"):
        sequence_bits(1024, 768, 1)
    with pytest.raises(InputError, match=r"at most \(7, 6\)"):
        sequence_bits(100, 60, (3, 7))
    # The shortened sequence is the full one's first pairs per axis, then white and black.
    full, short = graycode_patterns(100, 60), graycode_patterns(100, 60, (3, 2))
    nx = 7
    assert torch.equal(short[:6], full[:6]) and torch.equal(short[6:10], full[2 * nx:2 * nx + 4])
    assert torch.equal(short[-2:], full[-2:]) and len(short) == 2 * (3 + 2) + 2


def test_shortened_decoding_gives_the_block_centres():
    # A camera that sees the projector one cell per pixel: each pixel decodes to its own cell, so
    # the first k bits name the block of 2^(n-k) cells it lies in (cut at the edge: 100 = 96 + 4).
    width, height = 100, 60
    for bits in [(3, 2), (7, 6), (2, 2)]:
        seq = graycode_patterns(width, height, bits)
        dec = decode_gray(seq[:-2, 0], seq[-2, 0], seq[-1, 0], (width, height), bits=bits)
        block = (2 ** (7 - bits[0]), 2 ** (6 - bits[1]))
        assert dec.block == block and bool(dec.valid.all())
        cells = pixel_grid(height, width)
        expected = block_map(torch.eye(3, dtype=torch.float64), (height, width), (width, height), block)
        assert torch.equal(dec.prj_xy, expected), bits
        if block == (1, 1):
            assert torch.equal(dec.prj_xy, cells)


@pytest.fixture(scope="module")
def planes():
    return small_scene()


def test_a_shortened_capture_maps_the_plane_better_than_the_full_decoding(planes):
    rig = VirtualRig(planes)
    state = planes.states[0].name
    truth = rig.geometry(state).prj_xy[0]
    size = (planes.projectors[0].width, planes.projectors[0].height)

    def error(xy):
        ok = torch.isfinite(xy).all(-1) & torch.isfinite(truth).all(-1)
        return float((xy[ok] - truth[ok]).norm(dim=-1).median())

    full = calibrate_projector(simulate_calibration(rig, state, 0), size)
    coarse = calibrate_projector(simulate_calibration(rig, state, 0, bits=3), size, bits=3)
    assert coarse.decoding.block == (32, 32) and coarse.homography is not None
    assert error(coarse.decoding.prj_xy) > 5  # the blocks themselves are coarse
    # 0.003 against 0.027 cells (median): eight parameters from the whole plane beat any local fit
    assert error(coarse.prj_xy) < min(0.005, error(full.prj_xy) / 5)
    # The fitted map covers the decoded pixels, and the response is fitted from 16 images, not 40.
    assert int(torch.isfinite(coarse.prj_xy).all(-1).sum()) >= int(coarse.decoding.valid.sum())
    assert coarse.response.b[0] == pytest.approx(float(full.response.b[0]), abs=0.02)


def test_a_box_is_refused_with_its_state_and_projector_named():
    scene = small_scene("box_positions")
    with pytest.raises(InputError, match=r"state '\w+', projector '\w+': a 32x32-cell Gray-code block map: the decoded "
                                         r"map is not one plane.*no --bits"):
        calibrate_virtual(scene, bits=3)


def test_the_real_chessboard_from_its_first_three_bits():
    folder = CHESSBOARD / "capture_0"
    if not (folder / "graycode_41.png").is_file():
        pytest.skip(f"real captures not found at {CHESSBOARD} (they live in ../shared/data beside the checkout)")
    cap = read_graycode_folder(folder, (1024, 768))
    full = decode_gray(cap.patterns, cap.white, cap.black, (1024, 768))
    white = np.round(cap.white[0].numpy() * 255).astype(np.uint8)
    ok, corners = cv2.findChessboardCorners(white, (9, 7))
    assert ok
    hull = np.zeros(white.shape, np.uint8)
    cv2.fillConvexPoly(hull, cv2.convexHull(corners.reshape(-1, 2)).astype(np.int32), 1)
    hull = torch.from_numpy(hull.astype(bool))
    # The first 3 of 10 pattern pairs per axis: 12 of the 40 Gray-code images.
    keep = [*range(6), *range(20, 26)]
    coarse = decode_gray(cap.patterns[keep], cap.white, cap.black, (1024, 768), bits=3)
    on_board = torch.where(hull[..., None], coarse.prj_xy, float("nan"))
    fit = fit_homography(on_board, block=coarse.block)
    assert fit.p95 < 1.0
    # Against OpenCV's robust fit to the full decoding of the same pixels.
    valid = hull & full.valid
    cam = pixel_grid(*hull.shape, dtype=torch.float64)[valid]
    ref, _ = cv2.findHomography(cam.numpy(), full.prj_xy[valid].double().numpy(), cv2.LMEDS)
    distance = (apply(fit.matrix, cam) - apply(torch.from_numpy(ref), cam)).norm(dim=-1)
    assert float(distance.quantile(0.95)) < 0.5
    # The board with the room around it is no plane: its block edges say so.
    with pytest.raises(InputError, match="not one plane"):
        calibrate_projector(replace(cap, patterns=cap.patterns[keep], ramp=None), (1024, 768), bits=3)
