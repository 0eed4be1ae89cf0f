import re
from pathlib import Path

import numpy as np
import pytest
import torch

from torchproj.core import (CaptureError, InputError, atomic_output, check_finite, check_image, check_shape,
                            pixel_grid, read_image, round_to_pixel, write_image)
from torchproj.core.checks import all_finite


class TestCheckShape:
    def test_binds_named_dimensions(self):
        assert check_shape(torch.zeros(5, 7, 2), "prj_xy", ["H", "W", 2]) == {"H": 5, "W": 7}

    def test_leading_star(self):
        assert check_shape(torch.zeros(4, 3, 5, 6), "img", ["*", "C", "H", "W"]) == {"C": 3, "H": 5, "W": 6}

    @pytest.mark.parametrize("shape", [(5, 7), (5, 7, 3), (5, 7, 2, 1)])
    def test_wrong_shape_names_argument(self, shape):
        with pytest.raises(InputError, match=r"prj_xy must have shape \(H, W, 2\)"):
            check_shape(torch.zeros(shape), "prj_xy", ["H", "W", 2])

    def test_repeated_letter_must_agree(self):
        with pytest.raises(InputError, match="equal sizes for 'N'"):
            check_shape(torch.zeros(3, 4), "a", ["N", "N"])

    def test_not_a_tensor(self):
        with pytest.raises(InputError, match="must be a torch.Tensor"):
            check_shape(np.zeros(3), "a", ["N"])

    def test_input_error_is_value_error(self):
        assert issubclass(InputError, ValueError)


def test_check_finite_counts_bad_values():
    x = torch.ones(4)
    x[1] = float("nan")
    x[2] = float("inf")
    with pytest.raises(InputError, match="2 non-finite"):
        check_finite(x, "x")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16])
@pytest.mark.parametrize("shape", [(1,), (7,), (3, 97, 131), (2, 1000, 33)])
def test_all_finite_agrees_with_isfinite_wherever_the_bad_value_lies(dtype, shape):
    # aminmax works in vector lanes and a remainder: a NaN or an infinity in any lane, in the
    # remainder, in a strided view, or several of them, must each be found
    gen = torch.Generator().manual_seed(sum(shape))
    x = torch.rand(shape, generator=gen).to(dtype) * 2 - 1
    assert all_finite(x) and all_finite(x.transpose(0, -1)) and all_finite(x[..., ::3])
    flat = x.reshape(-1)
    spots = {0, flat.numel() - 1, *torch.randint(flat.numel(), (6,), generator=gen).tolist()}
    for spot in spots:
        for bad in (float("nan"), float("inf"), -float("inf")):
            y = flat.clone()
            y[spot] = bad
            y = y.reshape(shape)
            assert not all_finite(y), (spot, bad)
            assert all_finite(y) == bool(torch.isfinite(y).all())
            assert not all_finite(y.transpose(0, -1))
    assert all_finite(torch.zeros(0))


def test_counts_and_numbers_are_checked_by_kind_not_only_by_size():
    from torchproj.core import check_count, check_number

    assert check_count(np.int64(3), "n") == 3 and type(check_count(np.int64(3), "n")) is int
    for bad in (2.5, True, "3", None, 0):
        with pytest.raises(InputError, match=f"n must be a whole number >= 1, got {bad!r}"):
            check_count(bad, "n")
    assert check_number(np.float32(0.5), "w") == 0.5 and check_number(0, "w") == 0.0
    for bad in (float("nan"), float("inf"), -1e-9, True, "1"):
        with pytest.raises(InputError, match="w must be a finite number >= 0"):
            check_number(bad, "w")
    with pytest.raises(InputError, match="lr must be a finite number > 0, got 0"):
        check_number(0, "lr", strict=True)


def test_seeds_are_whole_numbers_the_generators_take():
    from torchproj.core import check_seed

    assert check_seed(np.int64(7)) == 7 and type(check_seed(np.int64(7))) is int
    assert check_seed(2 ** 63 - 1) == 2 ** 63 - 1
    torch.Generator().manual_seed(check_seed(2 ** 63 - 1))  # the largest one torch takes
    for bad in (-1, 2 ** 63, 1.0, True, "1", None):
        with pytest.raises(InputError, match=rf"seed must be a whole number from 0 to 2\*\*63 - 1, got {re.escape(repr(bad))}"):
            check_seed(bad)
    with pytest.raises(InputError, match=r"trial seed must be a whole number from 0 to 1000 - 1 \(or none\), got 1000"):
        check_seed(1000, "trial seed", limit=1000, hint=" (or none)")


def test_check_image_range():
    with pytest.raises(InputError, match=r"must lie in \[0, 1\]"):
        check_image(torch.full((1, 2, 2), 1.5), "target")
    with pytest.raises(InputError, match=r"must lie in \[0, 1\], got values in \[-0.5, 0\]"):
        check_image(torch.tensor([[[0.0, -0.5]]]), "target")
    for bad in (float("nan"), float("inf")):
        image = torch.full((3, 4, 5), 0.5)
        image[2, 3, 4] = bad
        with pytest.raises(InputError, match="target holds 1 non-finite"):
            check_image(image, "target")
    with pytest.raises(InputError, match="target is empty"):
        check_image(torch.zeros(1, 0, 4), "target")
    with pytest.raises(InputError, match="1 or 3 channels"):
        check_image(torch.zeros(2, 2, 2), "target")
    assert check_image(torch.zeros(3, 4, 5), "target") == {"C": 3, "H": 4, "W": 5}


def test_pixel_centres_are_integers():
    grid = pixel_grid(2, 3)
    assert grid.shape == (2, 3, 2)
    assert grid[1, 2].tolist() == [2.0, 1.0]  # (x, y) of row 1, column 2
    u = torch.tensor([-0.5, -0.49, 0.49, 0.5, 2.51])
    assert round_to_pixel(u).tolist() == [0, 0, 0, 1, 3]


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("channels", [1, 3])
def test_image_round_trip(tmp_path, bits, channels):
    peak = (1 << bits) - 1
    img = torch.randint(0, peak + 1, (channels, 9, 11)).float() / peak
    path = tmp_path / f"img{bits}.png"
    write_image(path, img, bits)
    back = read_image(path)
    assert back.shape == img.shape
    assert torch.equal(back, img)


def test_read_image_errors_name_the_file(tmp_path):
    with pytest.raises(CaptureError, match="missing.png: file not found"):
        read_image(tmp_path / "missing.png")
    bad = tmp_path / "truncated.png"
    write_image(bad, torch.rand(1, 20, 20))
    bad.write_bytes(bad.read_bytes()[:30])
    with pytest.raises(CaptureError, match="truncated.png: cannot be read"):
        read_image(bad)


@pytest.mark.parametrize("suffix", [".jpg", ".png"])
@pytest.mark.parametrize("channels", [1, 3])
def test_images_are_read_upright_by_their_exif_orientation(tmp_path, suffix, channels):
    """A phone's photo keeps the sensor's rows and says its turn in EXIF: read as Pillow turns it.

    A smooth picture with one bright corner, its chroma kept whole (``subsampling=0``): JPEG decoders
    then differ by a level or two, far less than any wrong turn or mirror moves the picture."""
    from PIL import Image, ImageOps

    ys, xs = np.mgrid[0:12, 0:20]
    stored = (8 * xs + 4 * ys).astype(np.uint8)
    stored[:4, :5] = 250  # the top-left corner, which every turn and mirror moves
    stored = np.stack([stored, stored[::-1], 255 - stored], -1) if channels == 3 else stored
    for orientation in range(1, 9):
        image = Image.fromarray(stored)
        exif = image.getexif()
        exif[274] = orientation
        path = tmp_path / f"turned{orientation}{suffix}"
        image.save(path, exif=exif, **({"quality": 95, "subsampling": 0} if suffix == ".jpg" else {}))
        upright = np.asarray(ImageOps.exif_transpose(Image.open(path)), dtype=np.float32) / 255
        got = read_image(path).permute(1, 2, 0).numpy()
        got = got[..., 0] if channels == 1 else got
        assert got.shape == upright.shape, orientation
        assert np.abs(got - upright).mean() <= 2 / 255, orientation
        if orientation in (2, 3, 4):  # the same shape as stored: the content tells the turn
            assert np.abs(got - stored.astype(np.float32) / 255).mean() > 10 / 255, orientation


def test_a_tiff_turned_a_quarter_is_read_upright_or_refused_saying_why(tmp_path):
    """OpenCV 5.1 reads no TIFF whose EXIF turn swaps its sides; where another OpenCV does, it is upright."""
    import cv2
    from PIL import Image

    image = Image.fromarray(np.zeros((12, 20), np.uint8))
    exif = image.getexif()
    exif[274] = 6
    image.save(tmp_path / "phone.tif", exif=exif)
    if cv2.imread(str(tmp_path / "phone.tif"), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR) is not None:
        assert read_image(tmp_path / "phone.tif").shape == (1, 20, 12)
        return
    with pytest.raises(CaptureError, match=r"phone.tif: cannot be read.*EXIF orientation.*upright or as PNG"):
        read_image(tmp_path / "phone.tif")


def test_atomic_output_leaves_nothing_on_failure(tmp_path):
    out = tmp_path / "run"
    with pytest.raises(RuntimeError):
        with atomic_output(out) as stage:
            (stage / "report.json").write_text("{}")
            raise RuntimeError("boom")
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []
    with atomic_output(out) as stage:
        (stage / "report.json").write_text("{}")
    assert (out / "report.json").is_file()
    assert [p.name for p in tmp_path.iterdir()] == ["run"]


@pytest.mark.parametrize("out", [".", "./", "..", "here/.."])
def test_the_folder_a_command_runs_in_is_no_output_folder(tmp_path, monkeypatch, out):
    """``--out .`` in an empty folder staged the new result inside ``.`` (its own parent), then refused it
    as something torchproj had not written, after all the work; the folder one stands in, or one above
    it, is refused before any, and a workspace (added to, not replaced) may be it."""
    from torchproj.core.output import check_output_folder

    here = tmp_path / "empty"
    (here / "here").mkdir(parents=True)
    monkeypatch.chdir(here)
    with pytest.raises(InputError, match=r"is the folder this command runs in.*give a folder of its own"):
        with atomic_output(out):
            raise AssertionError("no work before the refusal")
    assert [p.name for p in here.iterdir()] == ["here"] and [p.name for p in tmp_path.iterdir()] == ["empty"]
    assert check_output_folder(".", replace=False) == Path(".")
    with atomic_output("result") as stage:
        (stage / "report.json").write_text("{}")
    assert (here / "result" / "report.json").is_file()


def test_an_error_about_a_file_of_the_new_result_names_it_as_such(tmp_path):
    """``simulate --write-captures`` reads back the captures it wrote: a dark one was named by its path
    in the staging folder, which is gone by the time the message is read."""
    from torchproj.core import ConfigError

    out = tmp_path / "sim"
    with pytest.raises(CaptureError) as caught:
        with atomic_output(out) as stage:
            raise CaptureError(f"{stage / 'captures' / 'n' / 'a' / 'white.png'}: dark everywhere")
    assert str(caught.value) == f"the new result's captures/n/a/white.png: dark everywhere ({out} is as it was)"
    with pytest.raises(ConfigError, match=r"^camera.focal: bad$") as caught:  # other errors pass as they were
        with atomic_output(out):
            raise ConfigError("camera.focal", "bad")
    assert caught.value.field == "camera.focal" and list(tmp_path.iterdir()) == []


def test_an_output_folder_holding_a_persons_files_is_refused_and_left_whole(tmp_path):
    from torchproj.core.output import MANIFEST

    out = tmp_path / "run"
    (out / "captures").mkdir(parents=True)
    (out / "captures" / "mine.png").write_bytes(b"12345")
    (out / "NOTES.txt").write_text("my notes")
    with pytest.raises(InputError, match=r"holds NOTES.txt, captures, which torchproj did not write"):
        with atomic_output(out) as stage:
            (stage / "captures").mkdir()
    assert (out / "captures" / "mine.png").read_bytes() == b"12345" and (out / "NOTES.txt").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # no staging folder left behind
    # A folder torchproj wrote is replaced whole: what the new result does not hold goes with the old one.
    out = tmp_path / "mine"
    with atomic_output(out) as stage:
        (stage / "report.json").write_text("1")
        (stage / "old.png").write_text("x")
    assert sorted(p.name for p in out.iterdir()) == sorted([MANIFEST, "old.png", "report.json"])
    with atomic_output(out) as stage:
        (stage / "report.json").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "report.json"]
    assert (out / "report.json").read_text() == "2" and oct(out.stat().st_mode & 0o777) != oct(0o700)
    # ... unless the person has put something of theirs there since.
    (out / "NOTES.txt").write_text("mine")
    with pytest.raises(InputError, match="holds NOTES.txt"):
        with atomic_output(out):
            pass


def test_an_interrupted_swap_leaves_the_old_result_whole(tmp_path, monkeypatch):
    import os

    from torchproj.core import output

    out = tmp_path / "run"
    with atomic_output(out) as stage:
        (stage / "report.json").write_text("old")
    real = os.replace
    calls = []

    def failing(src, dst):  # the second rename (the new result in) fails: a full disk, a signal
        calls.append((src, dst))
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(src, dst)

    monkeypatch.setattr(output.os, "replace", failing)
    with pytest.raises(KeyboardInterrupt):
        with atomic_output(out) as stage:
            (stage / "report.json").write_text("new")
    monkeypatch.setattr(output.os, "replace", real)
    assert (out / "report.json").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_json_reports_stay_json_whatever_the_scores(tmp_path):
    import json
    import math

    from torchproj.core import write_json

    write_json(tmp_path / "r.json", {"psnr_db": math.inf, "low": -math.inf, "gap": float("nan"), "rows": [1.5, math.inf]})
    text = (tmp_path / "r.json").read_text()
    assert "Infinity" not in text and "NaN" not in text
    assert json.loads(text) == {"psnr_db": None, "low": None, "gap": None, "rows": [1.5, None]}


def test_index_arrays_are_int32_while_they_fit():
    from torchproj.core.sparse import csr_tensor, index_dtype

    assert index_dtype(5, 2**31 - 1) == torch.int32 and index_dtype(5, 2**31) == torch.int64
    m = csr_tensor(torch.tensor([0, 1, 2]), torch.tensor([1, 0]), torch.ones(2), (2, 2))
    assert m.crow_indices().dtype == m.col_indices().dtype == torch.int32


def test_environment_settings_read_as_people_write_them_and_say_what_they_cannot(monkeypatch):
    """``TORCHPROJ_COMPILE=true`` was off without a word (only ``1`` turned it on), and
    ``TORCHPROJ_CACHE_MAX_GB=500MB`` kept 2 GB without one, while ``nan`` removed every entry."""
    import warnings

    from torchproj.core.checks import _warn_setting, env_number, env_switch
    from torchproj.core.fused import COMPILE_ENV, compile_enabled

    _warn_setting.cache_clear()
    for value, on in (("1", True), ("true", True), (" Yes ", True), ("ON", True), ("0", False), ("off", False),
                      ("", False), ("False", False)):
        monkeypatch.setenv(COMPILE_ENV, value)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert env_switch(COMPILE_ENV) is on and compile_enabled() is on, value
    monkeypatch.setenv(COMPILE_ENV, "maybe")
    with pytest.warns(UserWarning, match=r"TORCHPROJ_COMPILE='maybe' is not a value torchproj reads; taking off"):
        assert env_switch(COMPILE_ENV) is False
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # said once, however often it is read
        assert compile_enabled() is False
    name = "TORCHPROJ_TEST_NUMBER"
    for value, read in (("0.5", 0.5), ("3", 3.0), ("  ", 2.0), ("0", 0.0), ("inf", float("inf"))):
        monkeypatch.setenv(name, value)
        assert env_number(name, 2.0) == read
    for value in ("500MB", "nan", "-1", "-inf"):
        monkeypatch.setenv(name, value)
        with pytest.warns(UserWarning, match=rf"{name}='{value}' is not a value torchproj reads; taking 2 \(give a number"):
            assert env_number(name, 2.0) == 2.0
