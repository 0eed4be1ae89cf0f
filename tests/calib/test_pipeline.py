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
    with pytest.raises(InputError, match="max_hole"):
        scan_map(capture, PROJECTOR, max_hole=-1)
