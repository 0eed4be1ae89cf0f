"""Virtual-rig calibration says how much of each projector's light decoded, and warns when little did."""

import warnings

import pytest

from torchproj.calib import FEW_DECODED
from torchproj.pipeline import calibrate_virtual, decoding_accuracy
from torchproj.scene import parse_scene

from ..helpers import small_config


def test_decoded_share_is_reported_and_warned_where_stripes_are_finer_than_the_camera():
    # A camera as fine as the projectors decodes nearly everything it sees lit.
    fine = parse_scene(small_config(camera=(400, 300), projector=(256, 192)), name="fine")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning at all
        cal = calibrate_virtual(fine, progress=False)
    shares = [v for per in cal.decoded.values() for v in per.values()]
    assert len(shares) == 4 and min(shares) > 0.95
    # One camera pixel over ~2.4 projector cells, averaged over 4x4 samples: the finest stripes blur to grey and fail the
    # reliability test, so few lit pixels decode fully; their sharp bits still name two or four cells, so nearly all are
    # partly decoded, placed from their neighbours, and nothing needs a warning.
    coarse = parse_scene(small_config(camera=(100, 75), projector=(256, 192), supersampling=4), name="coarse")
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*decoded")
        cal = calibrate_virtual(coarse, progress=False)
    for state, per in cal.decode.items():
        for name, v in per.items():
            assert v["full"] < FEW_DECODED and v["partial"] > 0.5 and v["none"] < 0.05
            assert v["full"] + v["partial"] + v["none"] == pytest.approx(1, abs=1e-3)
            # The decoded share a run reports, and the warning compares, counts both: what calibration places.
            assert cal.decoded[state][name] == pytest.approx(v["full"] + v["partial"], abs=2e-4)
    # The share agrees with the simulator's truth within what the shadow mask leaves out.
    geo = cal.rig.geometry("near")
    truth = decoding_accuracy(cal.states["near"].prj_xy[0], geo.prj_xy[0].cpu())
    placed = cal.decode["near"]["upper"]
    assert abs(truth.decoded - (placed["full"] + placed["partial"])) < 0.15
