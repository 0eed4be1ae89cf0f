"""What bad capture folders get: an error naming the file and what to do."""

import pytest
import torch

from torchproj.calib import GraycodeCapture, checker_patterns, graycode_patterns, read_graycode_folder, write_graycode_folder
from torchproj.core import CaptureError, write_image


def written():
    pats = graycode_patterns(64, 48)
    return GraycodeCapture(patterns=pats[:-2] * 0.8 + 0.1, white=pats[-2] * 0.9, black=pats[-1] + 0.05)


@pytest.fixture
def folder(tmp_path):
    write_graycode_folder(tmp_path / "cap", written())
    return tmp_path / "cap"


def test_reads_a_complete_folder(folder):
    cap, want = read_graycode_folder(folder, (64, 48)), written()
    assert cap.patterns.shape == (24, 1, 48, 64) and cap.ramp is None
    # Each image comes back as written, to the 8-bit step of the files, in the sequence's order.
    for got, expected in ((cap.patterns, want.patterns), (cap.white, want.white), (cap.black, want.black)):
        assert float((got - expected).abs().max()) <= 0.5 / 255 + 1e-6
    assert not torch.equal(cap.patterns[0], cap.patterns[2])  # not one image repeated


def test_reads_the_checkerboard_pair_beside_the_sequence(folder):
    pair = checker_patterns(64, 48) * 0.7 + 0.1
    write_graycode_folder(folder, GraycodeCapture(**{**written().__dict__, "checker": pair}))
    cap = read_graycode_folder(folder, (64, 48))
    assert float((cap.checker - pair).abs().max()) <= 0.5 / 255 + 1e-6
    # Half a pair is refused naming the missing file; a pair of another size too.
    (folder / "checker_inverse.png").unlink()
    with pytest.raises(CaptureError, match="checker_inverse.png: missing, while checker.png is there"):
        read_graycode_folder(folder, (64, 48))
    write_image(folder / "checker_inverse.png", torch.zeros(1, 40, 64))
    with pytest.raises(CaptureError, match="checker_inverse.png: size .* differs from graycode_00.png"):
        read_graycode_folder(folder, (64, 48))
    (folder / "checker.png").unlink()
    (folder / "checker_inverse.png").unlink()
    assert read_graycode_folder(folder, (64, 48)).checker is None


def test_missing_image(folder):
    (folder / "graycode_07.png").unlink()
    with pytest.raises(CaptureError, match=r"expected 26 images .* missing 1: graycode_07.png"):
        read_graycode_folder(folder, (64, 48))


def test_wrong_projector_size(folder):
    with pytest.raises(CaptureError, match="expected 32 images for a 200x100 projector"):
        read_graycode_folder(folder, (200, 100))


@pytest.mark.parametrize("name", ["graycode_26.png", "graycode_99.png", "graycode_100.png"])
def test_extra_image(folder, name):
    write_image(folder / name, torch.zeros(1, 48, 64))
    with pytest.raises(CaptureError, match=f"{name}: 1 image.* beyond a 64x48 projector's 26"):
        read_graycode_folder(folder, (64, 48))


@pytest.mark.parametrize("names", ["graycode.png", "{", "{}/{}.png", "img_{x}.png", "{:q}.png"])
def test_bad_name_template(folder, names):
    with pytest.raises(CaptureError, match="not a file name template with one number field"):
        read_graycode_folder(folder, (64, 48), names=names)


def test_inconsistent_sizes(folder):
    write_image(folder / "graycode_03.png", torch.zeros(1, 40, 64))
    with pytest.raises(CaptureError, match="graycode_03.png: size .* differs from graycode_00.png"):
        read_graycode_folder(folder, (64, 48))


def test_projector_off(folder):
    write_image(folder / "graycode_24.png", torch.full((1, 48, 64), 2 / 255))
    with pytest.raises(CaptureError, match="graycode_24.png: the white capture is dark everywhere"):
        read_graycode_folder(folder, (64, 48))


def test_corrupt_file(folder):
    (folder / "graycode_10.png").write_bytes(b"not a png")
    with pytest.raises(CaptureError, match="graycode_10.png: cannot be read"):
        read_graycode_folder(folder, (64, 48))


@pytest.mark.parametrize("names", ["graycode.png", "{", "img_{x}.png"])
def test_a_template_without_the_index_writes_nothing(tmp_path, names):
    """write_graycode_folder(names="graycode.png") wrote every image of the sequence to one file, the last
    one left: a folder no read could take back."""
    with pytest.raises(CaptureError, match="not a file name template with one number field"):
        write_graycode_folder(tmp_path / "cap", written(), names=names)
    assert not (tmp_path / "cap").exists()


def test_folders_captures_and_sizes_of_the_wrong_kind_are_named(folder, tmp_path):
    """Path()'s TypeError, an AttributeError on .patterns and an unpacking error before."""
    from torchproj.calib import calibrate_projector, scan_map
    from torchproj.core import InputError

    with pytest.raises(InputError, match="folder must be a capture folder's path, got int"):
        read_graycode_folder(3, (64, 48))
    with pytest.raises(InputError, match="folder must be a capture folder's path, got NoneType"):
        write_graycode_folder(None, written())
    with pytest.raises(InputError, match="capture must be a GraycodeCapture, got list"):
        write_graycode_folder(tmp_path / "w", [written()])
    with pytest.raises(InputError, match="bits must be 8 or 16, got tensor"):
        write_graycode_folder(tmp_path / "w", written(), bits=torch.tensor([8, 16]))
    with pytest.raises(InputError, match=r"projector_size must be \(width, height\), got 64"):
        read_graycode_folder(folder, 64)
    for call in (calibrate_projector, scan_map):
        with pytest.raises(InputError, match="capture must be a GraycodeCapture .*, got str"):
            call(str(folder), (64, 48))
        with pytest.raises(InputError, match=r"projector_size must be \(width, height\), got None"):
            call(read_graycode_folder(folder, (64, 48)), None)


def test_missing_folder(tmp_path):
    with pytest.raises(CaptureError, match="capture folder not found"):
        read_graycode_folder(tmp_path / "nope", (64, 48))


def test_captures_that_decode_nothing_are_an_error_naming_the_folder(tmp_path):
    """Identical captures (a frozen camera, every image the white one) decoded 0% and exited 0."""
    from torchproj.calib import decode_folder

    frozen = tmp_path / "frozen"
    pats = graycode_patterns(64, 48)
    same = pats[-2] * 0.8 + 0.1  # the white capture, every time
    write_graycode_folder(frozen, GraycodeCapture(patterns=same.expand(len(pats) - 2, -1, -1, -1), white=same,
                                                  black=same))
    with pytest.raises(CaptureError, match=r"frozen: only 0.000% of the camera decoded; .* \(identical or saturated"):
        decode_folder(frozen, (64, 48))
