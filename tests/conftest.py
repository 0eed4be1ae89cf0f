"""Shared fixtures."""

from __future__ import annotations

import os

# Under pytest-xdist (`-n 2`) two workers share this machine's 2 cores. numpy's and scipy's OpenBLAS read
# their thread count once, when loaded (torch loads numpy), so it is set before that: two workers with 2
# BLAS threads each spin against each other (a scipy reference solve took 4.6x as long).
if os.environ.get("PYTEST_XDIST_WORKER"):
    for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_name, "1")

import pytest  # noqa: E402
import torch  # noqa: E402

from .helpers import CHESSBOARD, calibrate_once


@pytest.fixture(autouse=True)
def _threads():
    # This machine has 2 cores. Under pytest-xdist two workers share them, and a worker that also asked
    # torch for 2 threads would oversubscribe them: its OpenMP threads spin while waiting.
    torch.set_num_threads(1 if os.environ.get("PYTEST_XDIST_WORKER") else 2)


@pytest.fixture(autouse=True, scope="session")
def _calibration_cache(tmp_path_factory):
    """Commands the tests run keep their calibrations in a folder of the session's, not the user's cache.

    pytest-xdist's workers share it (the folder beside their own temporary roots), as runs side by side
    share a user's: a scene one worker calibrated, the other reads (:func:`tests.helpers.calibrate_once`).
    """
    from torchproj.pipeline.cache import CACHE_DIR_ENV

    before = os.environ.get(CACHE_DIR_ENV)
    if os.environ.get("PYTEST_XDIST_WORKER"):
        folder = tmp_path_factory.getbasetemp().parent / "calibration_cache"
        folder.mkdir(exist_ok=True)
    else:
        folder = tmp_path_factory.mktemp("calibration_cache")
    os.environ[CACHE_DIR_ENV] = str(folder)
    yield
    if before is None:
        os.environ.pop(CACHE_DIR_ENV, None)
    else:
        os.environ[CACHE_DIR_ENV] = before


@pytest.fixture
def chessboard():
    if not (CHESSBOARD / "capture_0" / "graycode_41.png").is_file():
        pytest.skip(f"real captures not found at {CHESSBOARD} (they live in ../shared/data beside the checkout)")
    return CHESSBOARD


@pytest.fixture(scope="session")
def quarter_rig():
    """The paper's rig at a quarter of its resolution (``load_scene(scale=0.25)``), calibrated once per session."""
    from torchproj.scene import load_scene

    scene = load_scene("paper_two_planes", scale=0.25)
    return scene, calibrate_once(scene)
