"""The examples run as shipped (at a reduced size) and write what they say."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_train_patterns_example(tmp_path):
    out = tmp_path / "train"
    run = subprocess.run([sys.executable, str(ROOT / "examples" / "train_patterns.py"), "--scale", "0.25",
                          "--steps", "12", "--out", str(out)], capture_output=True, text=True, cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    report = json.loads((out / "report.json").read_text())
    assert [t["name"] for t in report["targets"]] == ["near", "far"] and len(report["loss_history"]) == 12
    assert report["loss_history"][-1] < report["loss_history"][0]
    for t in report["targets"]:
        assert {"psnr_db", "ssim", "crosstalk", "least_squares"} <= set(t)
    assert sum(t["ssim"] for t in report["targets"]) > sum(t["least_squares"]["ssim"] for t in report["targets"])
    assert (out / "overview.png").read_bytes()[:4] == b"\x89PNG"
    checkpoint = torch.load(out / "checkpoint.pt")
    assert checkpoint["step"] == 12 and "patterns" in checkpoint["model"] and "state" in checkpoint["optimizer"]
