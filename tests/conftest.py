"""Shared fixtures."""

from __future__ import annotations

import pytest
import torch

from .helpers import CHESSBOARD


@pytest.fixture(autouse=True)
def _threads():
    torch.set_num_threads(2)


@pytest.fixture
def chessboard():
    if not (CHESSBOARD / "capture_0" / "graycode_41.png").is_file():
        pytest.skip(f"real captures not found at {CHESSBOARD} (they live in ../shared/data beside the checkout)")
    return CHESSBOARD
