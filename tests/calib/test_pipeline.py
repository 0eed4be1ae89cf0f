"""A scan's map is calibration's map: the same decoding, refinement and filling, without the rest."""

import pytest
import torch

from torchproj.calib import calibrate_projector, scan_map
from torchproj.core.errors import InputError

from .test_edges import PROJECTOR, _captures


@pytest.mark.parametrize("options", [{}, {"dim_threshold": 40}, {"subpixel": False, "max_hole": 0}])
def test_the_scan_map_is_the_calibrations_forward_map(options):
    capture, truth = _captures()
    cal = calibrate_projector(capture, PROJECTOR, **options)
    scanned = scan_map(capture, PROJECTOR, **options)
    torch.testing.assert_close(scanned, cal.prj_xy, rtol=0, atol=0, equal_nan=True)
    # It is a map of the surfaces, not only equal to one: most pixels within a tenth of a cell refined,
    # within the cell (half a diagonal) as decoded.
    seen = torch.isfinite(scanned).all(-1)
    assert seen.float().mean() > 0.8
    within = 0.1 if options.get("subpixel", True) else 0.71
    assert float(((scanned - truth).norm(dim=-1)[seen] < within).float().mean()) > 0.7
    # calibrate_projector's own steps still run after the shared half.
    assert cal.blur is not None and cal.edges is not None and set(cal.timings_s) >= {"decode", "maps", "blur"}


def test_the_scan_map_checks_its_options():
    capture, _ = _captures()
    for bad in (-1, 2.5):
        with pytest.raises(InputError, match=r"max_hole \(--fill-holes, the largest hole filled, pixels\) must be a "
                                             rf"whole number >= 0, got {bad}"):
            scan_map(capture, PROJECTOR, max_hole=bad)


def test_captures_whose_pairs_do_not_add_up_are_warned_about_naming_the_fix():
    """A camera drowned in noise, or an exposure that changed while capturing, spreads the sums of each
    pattern and its inverse (capture_noise); past NOISY_CAPTURES the calibration says so, with frames to
    average. One frame of the rig's camera reads under 3%; clipped whites are said as such instead."""
    import dataclasses
    import warnings

    from torchproj.calib import NOISY_CAPTURES, capture_noise, warn_if_noisy
    from torchproj.pipeline import simulate_calibration
    from torchproj.scene import parse_scene
    from torchproj.sim import VirtualRig

    from ..helpers import small_config

    def capture(**camera):
        data = small_config(camera=(200, 150), projector=(128, 96))
        data["camera"].update(camera)
        return simulate_calibration(VirtualRig(parse_scene(data, name="noise")), "far", 0)

    plain, noisy = capture(), capture(noise={"full_well": 20, "read": 0.06})
    changed = plain.patterns.clone()
    changed[1::4] *= 0.85  # every other pair's pattern image 15% darker: the exposure changed
    shares = {"one frame": capture_noise(plain.patterns, plain.white, plain.black),
              "exposure changed": capture_noise(changed, plain.white, plain.black),
              "full well of 20": capture_noise(noisy.patterns, noisy.white, noisy.black)}
    assert shares["one frame"] < 0.03 < NOISY_CAPTURES < shares["exposure changed"] < 0.1 < 0.3 < shares["full well of 20"]
    cal = calibrate_projector(dataclasses.replace(plain, patterns=changed), (128, 96))
    with pytest.warns(UserWarning, match=r"far/p: the captures' noise is 6\.\d% .* Average frames \(camera.frames"):
        warn_if_noisy(cal.capture_noise, cal.saturated, "far/p", "camera.frames")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_if_noisy(shares["one frame"], 0.0, "far/p", "camera.frames")
        warn_if_noisy(shares["full well of 20"], 0.5, "far/p", "camera.frames")  # the clipped whites explain it
