"""The vectorised decoder against OpenCV and against the simulator's ground truth."""

import math

import cv2
import numpy as np
import pytest
import torch

from torchproj.calib import warn_if_few_decoded
from torchproj.calib.maps import depth_edges
from torchproj.calib.graycode import CREASE_RATIO, CURVE_RATIO, _refine_again, _window_planes, _window_quadratics
from torchproj.calib import (GraycodeCapture, band_pixels, calibrate_projector, capture_noise, cell_means, cell_shares, checker_patterns,
                             checker_shares, decode_gray, graycode_bits, graycode_patterns, read_graycode_folder, refine_subpixel, stripe_shares,
                             write_graycode_folder)
from torchproj.pipeline import decoding_accuracy, simulate_calibration
from torchproj.core import InputError
from torchproj.sim import VirtualRig

from ..helpers import area_captures, curved_map as _curved, small_scene


@pytest.mark.parametrize("size", [(64, 48), (100, 37), (1024, 768)])
def test_decoding_the_patterns_themselves_gives_the_pixel_grid(size):
    w, h = size
    seq = graycode_patterns(w, h)
    nx, ny = graycode_bits(w, h)
    assert seq.shape == (2 * (nx + ny) + 2, 1, h, w)
    dec = decode_gray(seq[:-2], seq[-2], seq[-1], size)
    assert dec.valid.all()
    ys, xs = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    assert torch.equal(dec.prj_xy[..., 0], xs.float()) and torch.equal(dec.prj_xy[..., 1], ys.float())


def test_matches_opencv_getprojpixel_on_a_simulated_capture():
    scene = small_scene("box_cylinders", camera=(240, 180), projector=(128, 96))
    cap = simulate_calibration(VirtualRig(scene), "together", 0)
    dec = decode_gray(cap.patterns, cap.white, cap.black, (128, 96))
    imgs = [np.round(i[0].numpy() * 255).astype(np.uint8) for i in cap.patterns]
    white = np.round(cap.white[0].numpy() * 255).astype(int)
    black = np.round(cap.black[0].numpy() * 255).astype(int)
    gc = cv2.structured_light.GrayCodePattern.create(128, 96)
    agree = disagree = 0
    for y in range(0, 180, 3):
        for x in range(0, 240, 3):
            lit = abs(white[y, x] - black[y, x]) > 40
            err, pix = gc.getProjPixel(imgs, x, y)
            ref_valid = lit and not err
            assert ref_valid == bool(dec.valid[y, x]), (x, y)
            if ref_valid:
                same = tuple(int(v) for v in pix) == tuple(int(v) for v in dec.prj_xy[y, x])
                agree, disagree = agree + same, disagree + (not same)
    assert agree > 500 and disagree == 0


def test_thresholds_follow_opencv():
    pats = graycode_patterns(8, 4)
    white, black = pats[-2], pats[-1]
    dim = pats[:-2] * (4 / 255) + 0.5  # every pair differs by 4/255 < the white threshold of 5
    assert not decode_gray(dim, white, black, (8, 4)).valid.any()
    assert decode_gray(dim, white, black, (8, 4), white_threshold=4).valid.all()
    dark_white = black + 40 / 255  # |white - black| must exceed the black threshold
    assert not decode_gray(pats[:-2], dark_white, black, (8, 4)).valid.any()


def test_wrong_number_of_images():
    pats = graycode_patterns(64, 48)
    with pytest.raises(InputError, match="must hold 24 images for a 64x48 projector"):
        decode_gray(pats[:-4], pats[-2], pats[-1], (64, 48))


@pytest.mark.parametrize("change, says", [
    (lambda p, w, b: ((p * 255).to(torch.uint8), w, b), "patterns must be float captures in \\[0, 1\\].*uint8"),
    (lambda p, w, b: (p * 255, w * 255, b), "white must lie in \\[0, 1\\].*up to 255"),
    (lambda p, w, b: (p.numpy(), w, b), "patterns must be float captures.*ndarray"),
])
def test_captures_in_8_bit_units_are_refused_not_read_against_thresholds_over_255(change, says):
    """The thresholds are 8-bit units over 255: 0-255 captures passed every pixel as lit and reliable."""
    pats = graycode_patterns(64, 48)
    with pytest.raises(InputError, match=says):
        decode_gray(*change(pats[:-2], pats[-2], pats[-1]), (64, 48))


def test_bad_thresholds_and_sizes_are_named():
    pats = graycode_patterns(64, 48)
    for options, says in [({"white_threshold": -1}, "white_threshold must be a finite number >= 0"),
                          ({"black_threshold": float("nan")}, "black_threshold must be a finite number >= 0"),
                          ({"white_threshold": 255}, "white_threshold is in 8-bit units and must be under 255"),
                          ({"black_threshold": 300}, "black_threshold is in 8-bit units and must be under 255")]:
        with pytest.raises(InputError, match=says):
            decode_gray(pats[:-2], pats[-2], pats[-1], (64, 48), **options)
    # A threshold no difference of captures reaches kept no pixel, reported as a projector that lit nothing.
    decoded = decode_gray(pats[:-2], pats[-2], pats[-1], (64, 48), black_threshold=254)
    assert bool(decoded.lit.all())
    with pytest.raises(InputError, match=r"black_threshold is in 8-bit units and must be under 255 \(.*\), got 300"):
        decoded.above(300)
    with pytest.raises(InputError, match="projector_size must be \\(width, height\\), got \\(64,\\)"):
        decode_gray(pats[:-2], pats[-2], pats[-1], (64,))
    # A float or a pair of the wrong length ended in "'float' object is not iterable" or an unpacking error.
    for bits in (2.5, (4,), (4, 4, 4), (4, 2.5), "4", True):
        with pytest.raises(InputError, match=r"bits must be a whole number, or a pair \(kx, ky\) of them, one per axis"):
            decode_gray(pats[:-2], pats[-2], pats[-1], (64, 48), bits=bits)
        with pytest.raises(InputError, match=r"bits must be a whole number, or a pair"):
            graycode_patterns(64, 48, bits=bits)
    assert graycode_patterns(64, 48, bits=(np.int64(3), 2)).shape == graycode_patterns(64, 48, bits=(3, 2)).shape


def test_a_pixel_whose_captures_are_nan_is_not_decoded():
    """NaN compares false with the threshold: its bits were taken as reliable and decoded to a cell."""
    pats = graycode_patterns(64, 48)
    stack = pats[:-2].clone()
    stack[3, 0, 5:9, 10:20] = float("nan")  # one capture of one pair, a block of pixels
    decoded = decode_gray(stack, pats[-2], pats[-1], (64, 48))
    assert not decoded.valid[5:9, 10:20].any()
    assert decoded.valid[:5].all() and decoded.valid[9:].all()


def test_noise_free_round_trip_is_exact():
    """Each camera pixel centre sees one LCD cell: decoding must give exactly that cell."""
    scene = small_scene(supersampling=1)
    scene.camera.full_well = scene.camera.read_noise = 0.0
    rig = VirtualRig(scene)
    for state in ("near", "far"):
        for j in range(2):
            cap = simulate_calibration(rig, state, j, noise=False)
            dec = decode_gray(cap.patterns, cap.white, cap.black, (256, 192))
            err = decoding_accuracy(dec.prj_xy, rig.geometry(state).prj_xy[j])
            assert err.lit > 20000
            assert err.decoded == 1.0 and err.exact == 1.0


def test_shadowed_pixels_are_masked_not_guessed():
    scene = small_scene("box_cylinders")
    rig = VirtualRig(scene)
    truth = rig.geometry("together").prj_xy
    for j in range(2):
        cap = simulate_calibration(rig, "together", j)
        dec = decode_gray(cap.patterns, cap.white, cap.black, (256, 192))
        unlit = ~torch.isfinite(truth[j]).all(-1)
        # Interior of unlit regions (shadows, background): a pixel whose whole neighbourhood is unlit.
        interior = torch.nn.functional.max_pool2d((~unlit).float()[None, None], 5, 1, 2)[0, 0] == 0
        assert int((interior & unlit).sum()) > 1000
        assert not dec.valid[interior].any()
        # Faces at grazing angles are too dim for OpenCV's black threshold (40/255) and stay
        # undecoded, as on a real bench; every clearly lit pixel must decode, and correctly.
        bright = (cap.white - cap.black)[0] > 50 / 255
        err = decoding_accuracy(torch.where(bright[..., None], dec.prj_xy, float("nan")),
                             torch.where(bright[..., None], truth[j], float("nan")))
        assert err.lit > 15000 and err.decoded > 0.98 and err.exact > 0.995
        assert not dec.valid[(cap.white - cap.black)[0] <= 40 / 255].any()


def test_a_higher_shadow_threshold_on_a_decoding_is_decoding_with_it():
    """Calibration decodes once, down to the dim threshold, and takes the lit pixels' decoding from it
    (GrayDecoding.above): the same as decoding at OpenCV's threshold, on box_cylinders' grazing faces,
    which hold pixels between the two."""
    rig = VirtualRig(small_scene("box_cylinders"))
    cap = simulate_calibration(rig, "together", 0)
    low = decode_gray(cap.patterns, cap.white, cap.black, (256, 192), black_threshold=10)
    want = decode_gray(cap.patterns, cap.white, cap.black, (256, 192), black_threshold=40)
    got = low.above(40)
    assert int((low.valid & ~want.valid).sum()) > 100 and int((low.partial & ~want.partial).sum()) > 0
    for field in ("prj_xy", "valid", "lit", "coarse_xy", "spread"):
        torch.testing.assert_close(getattr(got, field), getattr(want, field), equal_nan=True)
    assert got.counts() == want.counts()


def test_noisy_round_trip_and_subpixel_refinement():
    """Stated tolerance with camera noise and 3x3 supersampling: >= 99.5% of lit pixels decoded,
    >= 99.9% of those in the true cell; the sub-pixel fit is at least 3x closer to the truth."""
    scene = small_scene(camera=(480, 360))
    rig = VirtualRig(scene)
    cap = simulate_calibration(rig, "near", 1)
    dec = decode_gray(cap.patterns, cap.white, cap.black, (256, 192))
    truth = rig.geometry("near").prj_xy[1]
    integer = decoding_accuracy(dec.prj_xy, truth)
    refined = decoding_accuracy(refine_subpixel(dec.prj_xy, dec.valid), truth)
    assert integer.decoded > 0.995 and integer.exact > 0.999
    assert integer.rms_px == pytest.approx(np.sqrt(2 / 12), rel=0.05)  # uniform quantisation in x and y
    assert refined.rms_px < integer.rms_px / 3


def test_refine_recovers_an_affine_map_exactly():
    ys, xs = torch.meshgrid(torch.arange(40.0), torch.arange(50.0), indexing="ij")
    true = torch.stack([0.37 * xs + 0.05 * ys + 3.2, -0.02 * xs + 0.41 * ys + 7.7], -1)
    decoded = torch.floor(true + 0.5)
    valid = torch.ones(40, 50, dtype=torch.bool)
    refined = refine_subpixel(decoded, valid, window=9)
    inner = refined[6:-6, 6:-6] - true[6:-6, 6:-6]
    assert float(inner.abs().max()) < 0.06
    assert float((decoded - true).abs().max()) > 0.4


def _creased(noise: float, jump: float = 0.0):
    """A map over a 60 x 80 camera with a crease along x = 40 + 0.2 y: two faces of a box, their
    slopes 1.6 and 0.9 cells per pixel along x, meeting without a gap (or, with ``jump``, a depth
    edge instead), 900 cells from the origin; ``noise`` cells uniform noise on the values, as on the
    cells' means. Returns the values, the truth and the pixels' distance from the crease along x."""
    ys, xs = torch.meshgrid(torch.arange(60.0, dtype=torch.float64), torch.arange(80.0, dtype=torch.float64),
                            indexing="ij")
    across = xs - (40 + 0.2 * ys)
    u = 900 + 1.6 * xs + 0.1 * ys + torch.where(across > 0, (0.9 - 1.6) * across + jump, 0.0)
    v = 300 - 0.05 * xs + 1.3 * ys + torch.where(across > 0, 0.2 * across, 0.0)
    truth = torch.stack([u, v], -1).float()
    g = torch.Generator().manual_seed(0)
    values = truth + (torch.rand(truth.shape, generator=g) - 0.5) * 2 * noise
    return values, truth, across.abs().float()


def test_refine_fits_each_face_beside_a_crease():
    """Beside a crease the centred 7 x 7 plane straddles both faces; a window beside the pixel, on its
    own face, recovers the map there (against the exact faces, 900 cells from the origin, where the
    float64 residuals matter), and elsewhere the centred window still rules."""
    values, truth, distance = _creased(noise=0.15)
    valid = torch.ones(values.shape[:2], dtype=torch.bool)
    inner = torch.zeros_like(valid)
    inner[4:-4, 4:-4] = True
    beside_crease = inner & (distance >= 1) & (distance <= 3)
    away = inner & (distance > 7)
    rms = {}
    for name, ratio in (("centred", math.inf), ("beside", 2.0)):
        err = (refine_subpixel(values, valid, crease_ratio=ratio, curve_ratio=ratio) - truth).norm(dim=-1)
        rms[name] = {k: float(err[m].pow(2).mean().sqrt()) for k, m in (("crease", beside_crease), ("away", away))}
    assert rms["centred"]["crease"] > 0.1, rms  # the straddling plane: the bias this fixes
    assert rms["beside"]["crease"] < rms["centred"]["crease"] / 3, rms
    assert rms["beside"]["away"] < rms["centred"]["away"] * 1.2, rms
    # without noise a face's own window fits it exactly
    exact = refine_subpixel(truth, valid)
    assert float((exact - truth)[beside_crease].abs().max()) < 1e-3


def test_refine_keeps_the_centred_window_beside_a_depth_edge():
    """Pixels beside a depth edge may see both surfaces: they keep the centred fit (or their own value)."""
    values, truth, distance = _creased(noise=0.15, jump=30.0)
    valid = torch.ones(values.shape[:2], dtype=torch.bool)
    edge = depth_edges(values)
    assert int(edge.sum()) >= 2 * 60 - 4
    beside, centred = refine_subpixel(values, valid), refine_subpixel(values, valid, crease_ratio=math.inf)
    torch.testing.assert_close(beside[edge], centred[edge])
    assert not torch.equal(beside[~edge], centred[~edge])


def test_refine_leaves_a_map_smaller_than_its_window_as_decoded():
    values = torch.rand(2, 3, 2, generator=torch.Generator().manual_seed(0)) * 100
    for ratio in (2.0, math.inf):
        assert torch.equal(refine_subpixel(values, torch.ones(2, 3, dtype=torch.bool), crease_ratio=ratio), values)


def _sphere_like(noise: float):
    """A map over a 50 x 60 camera that curves within a window, as a small sphere's seen through pixels
    wider than a cell does (its slope along x goes from 0.1 to 4.6 cells per pixel across the image),
    800 cells from the origin; ``noise`` cells uniform noise on the values, as on the cells' means."""
    ys, xs = torch.meshgrid(torch.arange(50.0, dtype=torch.float64), torch.arange(60.0, dtype=torch.float64),
                            indexing="ij")
    u = 800 + 2.0 * xs + 0.035 * (xs - 30) ** 2 + 0.01 * xs * ys
    v = 500 + 1.8 * ys + 0.035 * (ys - 25) ** 2 - 0.006 * xs * xs
    truth = torch.stack([u, v], -1).float()
    g = torch.Generator().manual_seed(1)
    return truth + (torch.rand(truth.shape, generator=g) - 0.5) * 2 * noise, truth


def test_refine_follows_a_surface_curved_within_its_window():
    """Where the map curves within a window, the centred plane misses the centre by the curvature
    times the window's spread (0.18 cells rms here); the window's quadratic recovers it. On planar
    faces the windows beside a pixel show no bend worth fitting one, or it must fit 1.5 times as well
    as the plane to be taken, so it seldom is and moves little."""
    values, truth = _sphere_like(noise=0.15)
    valid = torch.ones(values.shape[:2], dtype=torch.bool)
    inner = torch.zeros_like(valid)
    inner[4:-4, 4:-4] = True
    err = {name: float((refine_subpixel(values, valid, curve_ratio=ratio) - truth)[inner].norm(dim=-1).pow(2).mean().sqrt())
           for name, ratio in (("planes", math.inf), ("quadratics", CURVE_RATIO))}
    assert err["planes"] > 0.15, err
    assert err["quadratics"] < err["planes"] / 2, err
    planar, flat_truth, distance = _creased(noise=0.15)
    away = torch.zeros_like(distance, dtype=torch.bool)
    away[4:-4, 4:-4] = True
    away &= distance > 7
    flat = {ratio: float((refine_subpixel(planar, torch.ones_like(away), curve_ratio=ratio) - flat_truth)[away]
                         .norm(dim=-1).pow(2).mean().sqrt()) for ratio in (math.inf, CURVE_RATIO)}
    assert flat[CURVE_RATIO] < flat[math.inf] * 1.1, flat


def test_an_outline_pixel_beside_a_curved_surface_keeps_its_own_value():
    """A pixel whose own window the mask cuts takes a window beside it; where that window's surface
    curves, its plane read half a window away misses by the curvature, and the pixel keeps its own
    value (its cells' mean). Beside a planar face it still takes the plane, as it did."""
    values, truth = _sphere_like(noise=0.05)
    valid = torch.ones(values.shape[:2], dtype=torch.bool)
    valid[:, 45:] = False  # an outline along x = 44
    outline = torch.zeros_like(valid)
    outline[5:-5, 42:45] = True  # under 70% of their 7 x 7 windows is mapped
    err = {ratio: float((refine_subpixel(values, valid, curve_ratio=ratio) - truth)[outline].norm(dim=-1)
                        .pow(2).mean().sqrt()) for ratio in (math.inf, CURVE_RATIO)}
    own = float((values - truth)[outline].norm(dim=-1).pow(2).mean().sqrt())
    assert err[math.inf] > 3 * own, (err, own)  # the shifted planes' curvature bias
    assert err[CURVE_RATIO] < 1.5 * own, (err, own)
    planar, _, _ = _creased(noise=0.15)
    planar_valid = torch.ones(planar.shape[:2], dtype=torch.bool)
    planar_valid[:, 30:] = False  # left of the crease: one planar face
    cut = torch.zeros_like(planar_valid)
    cut[5:-5, 27:30] = True
    torch.testing.assert_close(refine_subpixel(planar, planar_valid)[cut],
                               refine_subpixel(planar, planar_valid, curve_ratio=math.inf)[cut])
    assert not torch.equal(refine_subpixel(planar, planar_valid)[cut], planar[cut])


def test_calibration_places_a_small_sphere_closer_with_the_window_quadratic():
    """A procedural scene's small ellipsoid before camera pixels 1.7 cells wide, three projectors
    (suite-1206-6, the scene the quadratic was found on): the calibrated map against the simulator's
    exact coordinates, with and without the quadratic (0.35 -> 0.22 cells rms when measured)."""
    from torchproj.scene import load_scene

    scene = load_scene("suite-1206-6")
    rig = VirtualRig(scene)
    projector = scene.projectors[0]
    capture = simulate_calibration(rig, "at0", 0)
    truth = rig.geometry("at0").prj_xy[0]
    rms = {}
    for ratio in (math.inf, CURVE_RATIO):
        xy = calibrate_projector(capture, (projector.width, projector.height), curve_ratio=ratio,
                                 require_response=False).prj_xy
        both = torch.isfinite(xy).all(-1) & torch.isfinite(truth).all(-1)
        rms[ratio] = float((xy - truth)[both].norm(dim=-1).pow(2).mean().sqrt())
    assert rms[CURVE_RATIO] < 0.75 * rms[math.inf], rms


def test_window_quadratics_are_each_windows_least_squares_quadratic():
    """Every window's quadratic (value at the centre, misfit) against numpy's least squares on that
    window alone: whole windows (the orthogonal terms beside the plane, in float32 where the values
    are 900 cells from the origin) and windows the mask cuts (each solved on its own)."""
    gen = torch.Generator().manual_seed(5)
    height, width, window = 60, 70, 7
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                            indexing="ij")
    smooth = torch.stack([900 + 1.3 * xs + 0.02 * xs * ys, 400 + 0.8 * ys - 0.01 * xs * xs], -1)
    values = (smooth + torch.rand(height, width, 2, generator=gen, dtype=torch.float64) * 0.3).float()
    mask = torch.zeros(height, width, dtype=torch.bool)
    mask[5:55, 8:64] = torch.rand(50, 56, generator=gen) > 0.03
    mask[20:30, 20:30] = True  # a block of whole windows
    planes, misfit, count = _window_planes(values, mask, window)
    probes = [(25, 25), (40, 40), (5, 8), (8, 11), (54, 63), (30, 10), (12, 60)]
    # Asked for a few windows, each is gathered; asked for every masked pixel's, the whole ones come
    # from the correlations.
    few = torch.tensor([y * width + x for y, x in probes])
    every = torch.nonzero(mask.reshape(-1))[:, 0]
    at = torch.searchsorted(every, few)
    assert torch.equal(every[at], few)
    gathered = _window_quadratics(values, mask, window, few, planes, misfit, count)
    value, quad_misfit = (t[at] for t in _window_quadratics(values, mask, window, every, planes, misfit, count))
    torch.testing.assert_close(value, gathered[0], rtol=0, atol=2e-4)
    torch.testing.assert_close(quad_misfit, gathered[1], rtol=2e-3, atol=0)
    r = window // 2
    assert int(count[25, 25]) == window * window and int(count[5, 8]) < window * window
    for i, (y, x) in enumerate(probes):
        wy, wx = np.mgrid[y - r:y + r + 1, x - r:x + r + 1]
        inside = (wy >= 0) & (wy < height) & (wx >= 0) & (wx < width)
        wy, wx = wy[inside], wx[inside]
        on = mask.numpy()[wy, wx]
        dx, dy = (wx[on] - x).astype(np.float64), (wy[on] - y).astype(np.float64)
        design = np.stack([np.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy], 1)
        target = values.double().numpy()[wy[on], wx[on]]
        coef, *_ = np.linalg.lstsq(design, target, rcond=None)
        rss = ((design @ coef - target) ** 2).sum()
        np.testing.assert_allclose(value[i].double().numpy(), coef[0], rtol=0, atol=2e-4)
        np.testing.assert_allclose(float(quad_misfit[i]), rss / (2 * (on.sum() - 6)), rtol=2e-3)


def test_refine_refuses_a_curve_ratio_below_one():
    values, _, _ = _creased(noise=0.0)
    with pytest.raises(InputError, match="curve_ratio must be >= 1"):
        refine_subpixel(values, torch.ones(values.shape[:2], dtype=torch.bool), curve_ratio=0.5)


def test_refine_refuses_a_crease_ratio_below_one():
    values, _, _ = _creased(noise=0.0)
    with pytest.raises(InputError, match="crease_ratio must be >= 1"):
        refine_subpixel(values, torch.ones(values.shape[:2], dtype=torch.bool), crease_ratio=0.5)


def test_cell_means_are_the_mean_cell_of_each_pixel_light():
    """Against the mean cell of each pixel's 64 lit points, and, refined, three times as close to the
    true map as the fit over integer cells (0.024 against 0.094 cells rms)."""
    camera, projector = (60, 70), (80, 64)
    patterns, white, black, points = area_captures(_curved, camera, projector)
    mean_cell = points.double().mean(-2)
    dec = decode_gray(patterns, white, black, projector)
    assert dec.valid.float().mean() > 0.85  # a pixel split evenly across a cell edge is partly decoded
    means = cell_means(patterns, white, black, dec, projector)
    assert torch.isnan(means[~dec.valid]).all()
    torch.testing.assert_close(means[dec.valid].double(), mean_cell[dec.valid], atol=1e-4, rtol=0)
    ys, xs = torch.meshgrid(torch.arange(60.0), torch.arange(70.0), indexing="ij")
    truth = _curved(xs, ys)
    inner = torch.zeros(camera, dtype=torch.bool)
    inner[4:-4, 4:-4] = True
    inner &= dec.valid
    rms = {name: float((refine_subpixel(m, dec.valid) - truth)[inner].norm(dim=-1).pow(2).mean().sqrt())
           for name, m in (("integer", dec.prj_xy), ("means", means))}
    assert rms["means"] < rms["integer"] / 3, rms


def test_calibration_places_partly_decoded_pixels_by_their_own_shares():
    """A partly decoded pixel (its light straddles a finest stripe evenly) first takes the centre of
    the cells its bits leave open; calibration then measures its shares about the nearest cell of that
    fit, and a second fit over their means lands closer to the true map, on those pixels (0.033 ->
    0.022 cells rms) and on the fully decoded ones whose windows hold them (0.027 -> 0.023)."""
    camera, projector = (60, 70), (80, 64)
    patterns, white, black, _ = area_captures(_curved, camera, projector)
    dec = decode_gray(patterns, white, black, projector)
    first = refine_subpixel(torch.where(dec.valid[..., None], cell_means(patterns, white, black, dec, projector),
                                        dec.coarse_xy), dec.valid | dec.partial, spread=dec.spread)
    cal = calibrate_projector(GraycodeCapture(patterns, white, black, ramp=None), projector)
    partly = dec.partial & ~dec.valid
    assert int(partly.sum()) > 100
    nearest = first.round().long()
    assert torch.equal(cal.shares.cell[partly].long(), nearest[partly])
    torch.testing.assert_close(cal.shares.across[partly], cell_shares(patterns, white, black, dec, projector,
                                                                      cells=nearest).across[partly], equal_nan=True)
    ys, xs = torch.meshgrid(torch.arange(60.0), torch.arange(70.0), indexing="ij")
    truth = _curved(xs, ys)
    inner = torch.zeros(camera, dtype=torch.bool)
    inner[4:-4, 4:-4] = True
    for pixels, gain in ((partly, 0.8), (dec.valid, 0.95)):
        rms = [float((m - truth)[pixels & inner].norm(dim=-1).pow(2).mean().sqrt()) for m in (first, cal.prj_xy)]
        assert rms[1] < gain * rms[0], rms


def test_cell_shares_refuse_cells_off_the_projector_or_not_integer():
    patterns, white, black, _ = area_captures(_curved, (12, 14), (80, 64))
    dec = decode_gray(patterns, white, black, (80, 64))
    cells = torch.full((12, 14, 2), -1, dtype=torch.long)
    cells[3, 4] = torch.tensor([80, 5])
    with pytest.raises(InputError, match="outside the 80x64 projector"):
        cell_shares(patterns, white, black, dec, (80, 64), cells=cells)
    with pytest.raises(InputError, match="cells must be integer"):
        cell_shares(patterns, white, black, dec, (80, 64), cells=cells.float())
    with pytest.raises(InputError, match="cells"):
        cell_shares(patterns, white, black, dec, (80, 64), cells=cells[:5])




@pytest.mark.parametrize("width", [0, -3, 2.5, float("nan"), True, "64"])
def test_patterns_refuse_a_projector_size_that_is_not_a_whole_number_of_cells(width):
    for make in (graycode_patterns, checker_patterns):
        with pytest.raises(InputError, match="projector width must be a whole number of cells"):
            make(width, 48)

def _checker_captures(points, projector):
    """Noise-free captures of the checkerboard pair through the camera of :func:`area_captures`
    (``points``: each pixel's points' cells), at its contrast 0.8 over 0.05."""
    shown = checker_patterns(*projector)[:, 0]
    return (0.05 + 0.8 * shown[:, points[..., 1], points[..., 0]].mean(-1))[:, None].float()


def test_checker_shares_are_each_pixels_light_on_the_other_parity():
    """Against each pixel's 64 lit points: the share of them on cells whose parity (x + y) differs
    from the decoded cell's, to float precision, on a map where a pixel spans one or two cells.
    Pixels without a cell get NaN; bad shapes and float cells are refused."""
    camera, projector = (30, 36), (80, 64)
    patterns, white, black, points = area_captures(_curved, camera, projector)
    dec = decode_gray(patterns, white, black, projector)
    cells = cell_shares(patterns, white, black, dec, projector).cell
    pair = _checker_captures(points, projector)
    share = checker_shares(pair, white, black, cells)
    decoded = (cells >= 0).all(-1)
    assert decoded.float().mean() > 0.5 and share[~decoded].isnan().all()
    parity = (points.sum(-1) % 2) != ((cells[..., 0] + cells[..., 1]).long() % 2)[..., None]
    truth = parity.double().mean(-1)
    torch.testing.assert_close(share[decoded].double(), truth[decoded], atol=1e-5, rtol=0)
    assert 0.05 < float(truth[decoded].mean()) < 0.95  # the test sees light on both parities
    with pytest.raises(InputError, match="checker pair"):
        checker_shares(pair[:1], white, black, cells)
    with pytest.raises(InputError, match="cells must be integer"):
        checker_shares(pair, white, black, cells.float())
    # A bundle map keeps the share beside the others; a checker share that does not fit is refused.
    from torchproj.calib.bundle import SHARE_FIELDS, cell_shares_of
    shares = cell_shares(patterns, white, black, dec, projector)
    maps = {f"share_{k}": getattr(shares, k) for k in SHARE_FIELDS}
    assert cell_shares_of(maps).checker is None
    kept = cell_shares_of({**maps, "share_checker": share}).checker
    assert torch.equal(kept.isnan(), share.isnan()) and torch.equal(kept.nan_to_num(), share.nan_to_num())
    cell_shares_of({**maps, "share_checker": share}).check(camera, projector, "near.npz")
    with pytest.raises(InputError, match="near.npz: cell shares' checker"):
        cell_shares_of({**maps, "share_checker": share[:5]}).check(camera, projector, "near.npz")
    with pytest.raises(InputError, match="checker must lie in"):
        cell_shares_of({**maps, "share_checker": share + 2}).check(camera, projector, "near.npz")

def test_calibration_measures_the_checker_share_where_the_capture_holds_the_pair():
    """calibrate_projector reads the pair about each pixel's share cell, fully and partly decoded
    pixels alike, to the points' truth; without the pair, the shares carry none."""
    camera, projector = (30, 36), (80, 64)
    patterns, white, black, points = area_captures(_curved, camera, projector)
    capture = GraycodeCapture(patterns, white, black, checker=_checker_captures(points, projector))
    shares = calibrate_projector(capture, projector).shares
    cells = shares.cell
    known = (cells >= 0).all(-1)
    parity = (points.sum(-1) % 2) != ((cells[..., 0] + cells[..., 1]).long() % 2)[..., None]
    truth = parity.double().mean(-1)
    assert known.float().mean() > 0.5 and shares.checker[~known].isnan().all()
    torch.testing.assert_close(shares.checker[known].double(), truth[known], atol=1e-5, rtol=0)
    assert calibrate_projector(GraycodeCapture(patterns, white, black), projector).shares.checker is None


def _steep(x, y):
    """An affine map at 3.5 cells per camera pixel: a pixel's light spans three to four cells."""
    return torch.stack([3.5 * x + 0.3 * y + 1.2, 3.5 * y - 0.2 * x + 6.3], -1)


@pytest.mark.parametrize("given", [False, True], ids=["decoded", "given"])
@pytest.mark.parametrize("steep", [False, True])
def test_cell_shares_are_each_pixels_light_across_its_cell_edges(steep, given):
    """Against each pixel's 64 lit points: the share of them on the cell across each edge where they
    all lie within a cell of the decoded one (0.55-1.1 cells per pixel), and on a steep map, where they
    reach further, the share on the cells whose Gray bit of that edge differs (what the pair's stripe
    measures) and the largest such share of the axis' other bits (``outside``). Given cells (here the
    nearest to the points' mean), every pixel's shares about them, the partly decoded ones' too."""
    camera, projector = ((16, 19), (80, 64)) if steep else ((60, 70), (80, 64))
    patterns, white, black, points = area_captures(_steep if steep else _curved, camera, projector)
    dec = decode_gray(patterns, white, black, projector)
    if given:
        cells = points.double().mean(-2).round().long()
        assert bool((dec.partial & ~dec.valid).any())
        shares = cell_shares(patterns, white, black, dec, projector, cells=cells)
        valid = torch.ones(camera, dtype=torch.bool)
        assert torch.equal(shares.cell.long(), cells)
    else:
        shares = cell_shares(patterns, white, black, dec, projector)
        valid = dec.valid
    assert torch.equal((shares.cell >= 0).all(-1), valid) and int(valid.sum()) > 0.5 * valid.numel()
    assert torch.isnan(shares.across[~valid]).all() and torch.isnan(shares.outside[~valid]).all()
    cell = shares.cell.long()[..., None, :]  # (H, W, 1, 2) against the points' (H, W, P, 2)
    gray, own = points ^ (points >> 1), cell ^ (cell >> 1)
    bits = graycode_bits(*projector)
    want = torch.full(shares.across.shape, float("nan"), dtype=torch.float64)
    outside = torch.zeros(shares.outside.shape, dtype=torch.float64)
    for axis in (0, 1):
        n = cell[..., axis]
        edge_bits = []
        for side, step in enumerate((-1, 1)):
            other = (n + step).clamp(0, projector[axis] - 1)
            bit = torch.log2(((own[..., axis] ^ (other ^ (other >> 1))).clamp_min(1)).double()).round().long()
            edge_bits.append(torch.where((n + step < 0) | (n + step >= projector[axis]), -1, bit)[..., 0])
            differs = (((gray[..., axis] ^ own[..., axis]) >> bit) & 1).double().mean(-1)
            want[..., axis, side] = torch.where(edge_bits[-1] >= 0, differs, float("nan"))
            if not steep:  # every point within a cell of n: the share on the neighbour's cell itself
                beside = (points[..., axis] == n + step).double().mean(-1)
                inside = ((points[..., axis] - n).abs() <= 1).all(-1) & valid & (edge_bits[-1] >= 0)
                torch.testing.assert_close(want[..., axis, side][inside], beside[inside])
        for bit in range(bits[axis]):
            differs = (((gray[..., axis] ^ own[..., axis]) >> bit) & 1).double().mean(-1)
            other_bit = (edge_bits[0] != bit) & (edge_bits[1] != bit)
            outside[..., axis] = torch.where(other_bit, torch.maximum(outside[..., axis], differs), outside[..., axis])
    torch.testing.assert_close(shares.across[valid].double(), want[valid], atol=1e-4, rtol=0, equal_nan=True)
    torch.testing.assert_close(shares.outside[valid].double(), outside[valid], atol=1e-4, rtol=0)
    if steep:
        assert float((shares.outside[valid] > 0).float().mean()) > 0.5
    else:
        assert float(shares.outside[valid].max()) < 1e-4 and float(shares.across[valid].nanmean()) > 0.05


def test_cell_means_of_a_noisy_virtual_capture_beat_the_integer_cells():
    """The virtual rig's noisy, 3 x 3-sampled captures of a plane: the refined means are at least twice
    as close to the simulator's truth as the refinement of integer cells (0.042 against 0.117 cells)."""
    scene = small_scene(camera=(480, 360))
    rig = VirtualRig(scene)
    cap = simulate_calibration(rig, "near", 1)
    dec = decode_gray(cap.patterns, cap.white, cap.black, (256, 192))
    truth = rig.geometry("near").prj_xy[1]
    integer = decoding_accuracy(refine_subpixel(dec.prj_xy, dec.valid), truth)
    means = decoding_accuracy(refine_subpixel(cell_means(cap.patterns, cap.white, cap.black, dec, (256, 192)),
                                              dec.valid), truth)
    assert means.rms_px < integer.rms_px / 2, (means.rms_px, integer.rms_px)


def test_cell_means_need_the_full_sequence():
    patterns, white, black, _ = area_captures(_curved, (20, 24), (80, 64))
    dec = decode_gray(patterns, white, black, (80, 64))
    with pytest.raises(InputError, match="full Gray-code sequence"):
        cell_means(patterns[:-2], white, black, dec, (80, 64))
    short = graycode_patterns(80, 64, bits=4)[:, 0:1, :20, :24]
    with pytest.raises(InputError, match="decoding.block"):
        cell_means(short[:-2], short[-2], short[-1], decode_gray(short[:-2], short[-2], short[-1], (80, 64), bits=4),
                   (80, 64))


def test_folder_round_trip_decodes_identically(tmp_path):
    scene = small_scene(camera=(200, 150), projector=(128, 96), bit_depth=16)
    cap = simulate_calibration(VirtualRig(scene), "far", 0)
    write_graycode_folder(tmp_path / "cap", cap, bits=16)
    names = sorted(p.name for p in (tmp_path / "cap").iterdir())
    assert names[:4] == ["checker.png", "checker_inverse.png", "graycode_00.png", "graycode_01.png"]
    assert "ramp.png" in names
    back = read_graycode_folder(tmp_path / "cap", (128, 96))
    for got, shot in ((back.patterns, cap.patterns), (back.ramp, cap.ramp), (back.checker, cap.checker)):
        assert torch.equal(got, shot)
    a = decode_gray(cap.patterns, cap.white, cap.black, (128, 96))
    b = decode_gray(back.patterns, back.white, back.black, (128, 96))
    assert torch.equal(a.valid, b.valid) and torch.equal(a.prj_xy[a.valid], b.prj_xy[b.valid])


def _box_blurred(size, footprints):
    """Captures of the full sequence for one row of camera pixels, each the mean of the cells listed
    in its footprint: ``footprints`` is a list of ``(xs, y)``, cells ``xs`` of row ``y``."""
    w, h = size
    seq = graycode_patterns(w, h)[:, 0]  # (N, h, w)
    cols = [seq[:, y, list(xs)].mean(-1) for xs, y in footprints]  # each (N,)
    images = torch.stack(cols, -1)[:, None]  # (N, 1, P): one camera row
    return images[:-2], images[-2], images[-1]


def test_a_pixel_on_a_stripe_edge_or_under_blur_is_partly_decoded():
    """Box footprints: a pixel inside one cell decodes fully; one straddling the edge between two
    cells, or blurred over an aligned block of 2 or 4 cells, keeps the bits that are still sharp and
    names the cells they leave open; one spread over cells no bits can name stays undecoded."""
    size = (64, 16)
    cases = [  # footprint cells, want (centre x, cells open along x) or None
        ([21], (21.0, 1)),
        ([23, 24], (23.5, 2)),  # an edge of a coarse bit (23 = 0b10111, 24 = 0b11000) and of the finest
        ([40, 41], (40.5, 2)),  # the finest bit's stripe blurred out
        ([8, 9, 10, 11], (9.5, 4)),  # the two finest bits blurred out
        ([14, 15, 16, 17], None),  # a blur over a coarse edge and a fine one: two unrelated bits unreliable
    ]
    patterns, white, black = _box_blurred(size, [(xs, 5) for xs, _ in cases])
    dec = decode_gray(patterns, white, black, size)
    for i, (xs, want) in enumerate(cases):
        if want is None:
            assert not dec.valid[0, i] and not dec.partial[0, i] and int(dec.spread[0, i, 0]) == 0
            continue
        assert bool(dec.valid[0, i]) == (want[1] == 1)
        assert dec.coarse_xy[0, i].tolist() == [want[0], 5.0]
        assert dec.spread[0, i].tolist() == [want[1], 1]
    assert dec.counts() == {"lit": 5, "full": 1, "partial": 3, "none": 1}
    assert dec.lit_located_fraction == pytest.approx(4 / 5)
    # OpenCV's semantics are untouched: a partly decoded pixel is invalid there, NaN in prj_xy.
    assert dec.valid.sum() == 1 and torch.isnan(dec.prj_xy[0, 1:4]).all()


def test_refinement_places_partly_decoded_pixels_between_their_cells():
    """On a smooth map whose finest stripes the camera cannot resolve at every second pixel, those
    pixels, refined from their neighbours, land near the truth, not on their block's centre."""
    ys, xs = torch.meshgrid(torch.arange(40.0), torch.arange(50.0), indexing="ij")
    true = torch.stack([0.37 * xs + 0.05 * ys + 3.2, -0.02 * xs + 0.41 * ys + 7.7], -1)
    decoded = torch.floor(true + 0.5)
    blurred = (xs.long() + ys.long()) % 2 == 1
    coarse = decoded.clone()
    coarse[blurred] = torch.floor(decoded[blurred] / 2) * 2 + 0.5  # a 2 x 2 block's centre
    spread = torch.where(blurred[..., None], 2, 1).expand(-1, -1, 2).to(torch.int16)
    refined = refine_subpixel(coarse, torch.ones(40, 50, dtype=torch.bool), window=9, spread=spread)
    inner = (refined - true)[6:-6, 6:-6][blurred[6:-6, 6:-6]]
    assert float(inner.abs().max()) < 0.25
    assert float((coarse - true)[blurred].abs().max()) > 0.9


def test_few_placed_pixels_are_warned_about_naming_the_causes():
    """Pixels whose unreliable bits name no cells (here a blur across a coarse and a fine edge) cannot be
    placed; when they are most of the lit ones, calibration says so and why."""
    size = (64, 16)
    patterns, white, black = _box_blurred(size, [([14, 15, 16, 17], 5)] * 3 + [([21], 5)])
    dec = decode_gray(patterns, white, black, size)
    assert dec.counts() == {"lit": 4, "full": 1, "partial": 0, "none": 3}
    with pytest.warns(UserWarning, match=r"only 25% of the pixels the projector lights decoded, fully or partly.*stripes"):
        assert warn_if_few_decoded(dec, "state 'near', projector 'upper'") == pytest.approx(0.25)


def test_stripe_contrast_has_a_fraction_of_white_minus_black_noise():
    """Against the simulator's noise-free white minus black: the mean over the captures that show a
    pixel white and black has at most half the error of the one white and one black frame, and no
    bias; pixels without a cell keep white minus black."""
    from torchproj.calib import stripe_contrast

    scene = small_scene("box_positions", camera=(200, 150), projector=(256, 192))
    rig = VirtualRig(scene)
    cap = simulate_calibration(rig, "near", 0)
    cal = calibrate_projector(cap, (256, 192))
    truth = (rig.capture("near", {0: torch.ones(1, 1, 192, 256)}, noise=False, quantise=False)[0]
             - rig.capture("near", {}, noise=False, quantise=False)[0]).mean(0)
    cells = cal.shares.cell
    span = stripe_contrast(cap.patterns, cap.white, cap.black, cells, (256, 192))
    assert span.shape == (1, 150, 200)
    raw = cap.white[0] - cap.black[0]
    inner = (cells >= 0).all(-1) & (truth > 0.2)
    before = ((raw - truth) / truth)[inner]
    after = ((span[0] - truth) / truth)[inner]
    assert inner.sum() > 3000
    assert after.pow(2).mean().sqrt() < 0.5 * before.pow(2).mean().sqrt()
    assert abs(float(after.mean())) < 0.002
    none = ~(cells >= 0).all(-1)
    assert torch.equal(span[0][none], raw[none])
    # calibrate_projector weighs by it: the decoding's contrast is its mean over channels.
    assert torch.equal(cal.decoding.contrast, span.mean(0))


def test_stripe_contrast_keeps_white_minus_black_where_stripes_do_not_read_as_white():
    """A projector whose stripes read dimmer than its white (blur, scatter on a real bench): no pair
    qualifies, and white minus black is returned as it is."""
    from torchproj.calib import stripe_contrast

    scene = small_scene("box_positions", camera=(200, 150), projector=(256, 192))
    cap = simulate_calibration(VirtualRig(scene), "near", 0)
    cal = calibrate_projector(cap, (256, 192))
    dimmer = cap.black + 0.95 * (cap.patterns - cap.black)
    span = stripe_contrast(dimmer, cap.white, cap.black, cal.shares.cell, (256, 192))
    assert torch.equal(span, (cap.white - cap.black).float())


def test_fitting_again_near_changed_pixels_is_the_whole_fit():
    """Calibration's second fit runs only on the tiles within a window's width of the pixels whose
    values changed: the same map as a fit over the whole image (to float32 round-off), on a map with a
    crease, holes and partly decoded pixels of wider spread."""
    g = torch.Generator().manual_seed(5)
    h, w = 150, 200
    y, x = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    crease = torch.where(x > 90, (x - 90) * 0.8, 0.0)  # a box's two faces meeting
    truth = torch.stack([40 + 1.3 * x + 0.2 * y + crease, 20 + 0.1 * x + 1.1 * y], -1)
    before = truth + 0.3 * torch.randn(h, w, 2, generator=g)
    valid = torch.rand(h, w, generator=g) > 0.1
    spread = torch.where(torch.rand(h, w, 1, generator=g) > 0.9, 4, 1).expand(h, w, 2)
    changed = torch.zeros(h, w, dtype=torch.bool)
    changed[torch.randint(0, h, (40,), generator=g), torch.randint(0, w, (40,), generator=g)] = True
    after = torch.where(changed[..., None], truth + 0.05 * torch.randn(h, w, 2, generator=g), before)
    first = refine_subpixel(before, valid, spread=spread)
    spread_after = torch.where(changed[..., None], 1, spread)
    whole = refine_subpixel(after, valid, spread=spread_after)
    again = _refine_again(after, valid, first, changed, spread_after, CREASE_RATIO)
    assert torch.equal(torch.isnan(whole), torch.isnan(again))
    assert float((torch.nan_to_num(whole) - torch.nan_to_num(again)).abs().max()) < 1e-3
    assert float((torch.nan_to_num(whole) - torch.nan_to_num(first)).abs().max()) > 0.01  # the change moved the map


@pytest.mark.parametrize("size", [(1024, 768), (640, 480), (300, 200), (97, 51)])
def test_the_gpu_machines_stand_in_generator_is_opencvs(size):
    """benchmarks/device_shim gives machines whose OpenCV lacks the contrib modules OpenCV's Gray code:
    the same images, in the same order."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "device_shim" / "sitecustomize.py"
    spec = importlib.util.spec_from_file_location("device_shim", path)
    shim = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(shim)  # leaves this cv2 alone: it has structured_light
    ok, want = cv2.structured_light.GrayCodePattern.create(*size).generate()
    done, got = shim.GrayCodePattern.create(*size).generate()
    assert ok and done and len(got) == len(want)
    assert all(np.array_equal(a, b) for a, b in zip(got, want))


def test_window_planes_are_each_windows_least_squares_plane_near_and_far_from_the_mask():
    """Every window's plane, misfit and count against numpy's least squares on that window alone, at
    pixels inside a masked block, on its border, a window beyond it, and beside a lone masked pixel far
    off (the fit sums only the columns near masked pixels: none may lose its plane or gain one)."""
    gen = torch.Generator().manual_seed(4)
    height, width, window = 300, 260, 7
    values = torch.rand(height, width, 2, generator=gen, dtype=torch.float64).float() * 4 + 100
    mask = torch.zeros(height, width, dtype=torch.bool)
    mask[40:270, 60:150] = torch.rand(230, 90, generator=gen) > 0.25
    mask[150, 250] = True  # alone, far to the right
    planes, misfit, count = _window_planes(values, mask, window)
    r = window // 2
    probes = [(100, 100), (40, 60), (37, 57), (36, 56), (269, 149), (272, 152), (273, 153), (150, 250), (152, 247),
              (150, 246), (10, 10), (299, 259)]
    for y, x in probes:
        ys, xs = np.mgrid[y - r:y + r + 1, x - r:x + r + 1]
        inside = (ys >= 0) & (ys < height) & (xs >= 0) & (xs < width)
        ys, xs = ys[inside], xs[inside]
        on = mask.numpy()[ys, xs]
        assert count[y, x] == on.sum()
        if on.sum() < 3:
            assert torch.isnan(planes[y, x]).all() and torch.isnan(misfit[y, x])
            continue
        design = np.stack([np.ones(on.sum()), xs[on] - x, ys[on] - y], 1).astype(np.float64)
        target = values.double().numpy()[ys[on], xs[on]]  # (n, 2)
        coef, *_ = np.linalg.lstsq(design, target, rcond=None)
        rss = ((design @ coef - target) ** 2).sum()
        np.testing.assert_allclose(planes[y, x].double().numpy(), coef.T, rtol=1e-5, atol=1e-4)
        np.testing.assert_allclose(float(misfit[y, x]), rss / max(2 * (on.sum() - 3), 1), rtol=1e-3, atol=1e-6)


def _mixed_pixels(size=(64, 32), pixels=60, seed=3):
    """Camera pixels (a 6 x 10 image) each lit by 1-6 cells of a ``size`` projector with random
    weights, and their captures of the Gray-code sequence: each image is the weighted sum of what
    it shows on those cells. Returns the captures (patterns, white, black), the cells (P, 6, 2) and
    weights (P, 6; zero where unused)."""
    width, height = size
    gen = torch.Generator().manual_seed(seed)
    images = graycode_patterns(width, height)[:, 0]  # (2 (kx + ky) + 2, H, W)
    cells = torch.stack([torch.randint(0, width, (pixels, 6), generator=gen),
                         torch.randint(0, height, (pixels, 6), generator=gen)], -1)
    weights = torch.rand(pixels, 6, generator=gen) * (torch.rand(pixels, 6, generator=gen) < 0.7)
    weights[:, 0] += 0.1
    shown = images[:, cells[..., 1], cells[..., 0]]  # (N, P, 6)
    captured = (shown * weights).sum(-1).reshape(-1, 6, 10)
    return captured[:-2], captured[-2], captured[-1], cells, weights


def test_stripe_shares_are_each_pairs_light_on_the_cells_its_first_image_lights():
    """Against the pattern images themselves: a pixel's share for pair k is the weight of its cells
    that the pair's first image shows white, over all its weight, whatever cells light it."""
    patterns, white, black, cells, weights = _mixed_pixels()
    images = graycode_patterns(64, 32)[:, 0]
    pixels = torch.tensor([0, 7, 13, 31, 59])
    shares = stripe_shares(patterns, white - black, pixels, graycode_bits(64, 32))
    assert shares.shape == (5, sum(graycode_bits(64, 32)))
    for row, p in enumerate(pixels.tolist()):
        for k in range(shares.shape[1]):
            lit = images[2 * k, cells[p, :, 1], cells[p, :, 0]]  # 1 where the first image lights the cell
            expected = float((weights[p] * lit).sum() / weights[p].sum())
            assert float(shares[row, k]) == pytest.approx(expected, abs=1e-5), (p, k)


def test_band_pixels_are_the_known_ones_within_two_of_an_unknown_pixel_or_a_depth_edge():
    """Against a brute-force search: a plane's map with a hole, and a step of 8 cells along a column
    (an object in front), its band the mapped pixels two or fewer pixels (either axis) from a hole
    pixel or from a pixel beside the step."""
    ys, xs = torch.meshgrid(torch.arange(30.0), torch.arange(40.0), indexing="ij")
    prj_xy = torch.stack([0.7 * xs + 0.1 * ys + 3, 0.05 * xs + 0.8 * ys + 2], -1)
    prj_xy[xs >= 25] += torch.tensor([8.0, 0.0])  # a step between columns 24 and 25
    prj_xy[10:13, 5:9] = float("nan")
    band = band_pixels(prj_xy)
    known = torch.isfinite(prj_xy).all(-1).numpy()
    beside = ~known
    beside[:, 24:26] = True  # both sides of the step see it
    expected = []
    for y in range(30):
        for x in range(40):
            if known[y, x] and beside[max(0, y - 2):y + 3, max(0, x - 2):x + 3].any():
                expected.append(y * 40 + x)
    assert band.tolist() == expected


@pytest.mark.parametrize("frames", [1, 16])
def test_capture_noise_is_the_spread_of_white_minus_black_over_repeated_captures(frames):
    """capture_noise reads the noise of a pixel's white minus black from the pattern pairs alone: the
    independent reference is the spread of white minus black over twelve more captures of each."""
    scene = small_scene(camera=(200, 150), projector=(128, 96), frames=frames)
    rig = VirtualRig(scene)
    capture = simulate_calibration(rig, "near", 0)
    on, off = {0: torch.ones(1, 1, 96, 128)}, {0: torch.zeros(1, 1, 96, 128)}
    spans = torch.stack([rig.capture("near", on, seed=10 + k)[0, 0] - rig.capture("near", off, seed=100 + k)[0, 0]
                         for k in range(12)])
    lit = spans.mean(0) > 40 / 255
    spread = float((spans.std(0) / spans.mean(0))[lit].median())
    estimate = capture_noise(capture.patterns, capture.white, capture.black)
    assert estimate == pytest.approx(spread, rel=0.1)
    assert (0.008 < estimate < 0.015) if frames == 1 else (0.002 < estimate < 0.004)  # a quarter at 16 frames


def test_capture_noise_of_the_real_captures(chessboard):
    capture = read_graycode_folder(str(chessboard / "capture_0"), (1024, 768))  # a path as text
    assert 0.005 < capture_noise(capture.patterns, capture.white, capture.black) < 0.05
    with pytest.raises(InputError, match="two or more pattern/inverse pairs"):
        capture_noise(capture.patterns[:2], capture.white, capture.black)
