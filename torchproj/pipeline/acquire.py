"""A small capture helper for benches: show a sequence full-screen on a projector, grab a frame each.

The loop only needs two things, so anything can stand in for them: a *display* with
``show(image)`` (an :math:`(H, W)` or :math:`(H, W, 3)` uint8 array) and a *camera* with ``grab()``
returning a uint8 or uint16 :math:`(H, W)` / :math:`(H, W, 3)` array (BGR from OpenCV, converted).
:class:`OpenCVDisplay` and :class:`OpenCVCamera` are the OpenCV ones. Showing a window needs an
OpenCV build with a GUI (``opencv-contrib-python`` in place of the headless wheel torchproj
installs); grabbing from a camera works with either.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from ..core.checks import check, check_count, check_path, is_number, is_whole
from ..core.errors import CaptureError, InputError
from ..core.imageio import read_image, write_image
from ..calib.bundle import SEQUENCE_FILE

__all__ = ["LiveBench", "OpenCVCamera", "OpenCVDisplay", "capture_sequence", "check_capture_options"]


class OpenCVDisplay:
    """A borderless full-screen window on the screen whose top-left corner is at ``(x, y)``."""

    def __init__(self, x: int = 0, y: int = 0, name: str = "torchproj"):
        self.name = name
        try:
            cv2.namedWindow(name, cv2.WINDOW_NORMAL)
        except cv2.error as exc:
            raise CaptureError("this OpenCV build cannot open windows (the headless wheel): install "
                               "opencv-contrib-python in place of opencv-contrib-python-headless to show patterns "
                               f"({str(exc).strip()})") from None
        cv2.moveWindow(name, x, y)
        cv2.setWindowProperty(name, cv2.WND_PROP_FULLSCREEN, cv2.WINDOW_FULLSCREEN)

    def show(self, image: np.ndarray) -> None:
        cv2.imshow(self.name, image[..., ::-1] if image.ndim == 3 else image)
        cv2.waitKey(1)

    def close(self) -> None:
        cv2.destroyWindow(self.name)


class OpenCVCamera:
    """``cv2.VideoCapture`` by device index; drops ``flush`` frames so that a grab is fresh."""

    def __init__(self, index: int = 0, flush: int = 2):
        self.cap = cv2.VideoCapture(index)
        if not self.cap.isOpened():
            raise CaptureError(f"camera {index}: cannot be opened (is it connected and free?)")
        self.flush = flush

    def grab(self) -> np.ndarray:
        for _ in range(self.flush):
            self.cap.grab()
        ok, frame = self.cap.read()
        if not ok:
            raise CaptureError("the camera returned no frame; check its connection")
        return frame[..., ::-1] if frame.ndim == 3 else frame

    def close(self) -> None:
        self.cap.release()


def capture_sequence(sequence_dir: str | os.PathLike, out_dir: str | os.PathLike, display=None, camera=None, *,
                     settle_s: float = 0.2, screen: tuple[int, int] = (0, 0), camera_index: int = 0,
                     frames: int = 1) -> Path:
    """Show every image of a sequence (``torchproj sequence``) in order and save each capture under the
    same file name, plus ``sequence.json``, in ``out_dir`` (a ``CAPTURE_ROOT/STATE/PROJECTOR`` folder).

    Args:
        display, camera: see the module; None opens (and afterwards closes) an :class:`OpenCVDisplay`
            at ``screen`` and an :class:`OpenCVCamera` with ``camera_index``.
        settle_s: seconds to wait after showing an image before grabbing (projector and camera lag).
        frames: grabs averaged per image: the camera's noise in the map, weights and cell shares
            falls as their square root (docs/accuracy.md, "What the calibration's noise costs").
            A mean of several is written as a 16-bit PNG, which keeps the levels between one grab's.
    """
    settle_s = check_capture_options(settle_s, frames)
    check_path(sequence_dir, "sequence_dir", "the sequence folder (torchproj sequence)")
    check_path(out_dir, "out_dir", "the capture folder")
    _check_devices({} if display is None else {"display": display}, camera, opens=True)
    if display is None:
        check(isinstance(screen, (tuple, list)) and len(screen) == 2 and all(is_whole(v) for v in screen),
              f"screen must be the screen's top-left corner (x, y), two whole numbers of pixels, got {screen!r}")
    if camera is None:
        check_count(camera_index, "camera_index", 0)
    sequence_dir, out_dir = Path(sequence_dir), Path(out_dir)
    manifest_path = sequence_dir / SEQUENCE_FILE
    if not manifest_path.is_file():
        raise CaptureError(f"{sequence_dir}: no {SEQUENCE_FILE}; write the sequence with torchproj sequence")
    if display is None or camera is None:
        opened = []  # close what this call opened, and only that
        try:
            if display is None:
                display = OpenCVDisplay(*screen)
                opened.append(display)
            if camera is None:
                camera = OpenCVCamera(camera_index)
                opened.append(camera)
            return capture_sequence(sequence_dir, out_dir, display, camera, settle_s=settle_s, frames=frames)
        finally:
            for device in opened:
                device.close()
    manifest = json.loads(manifest_path.read_text())
    out_dir.mkdir(parents=True, exist_ok=True)
    for entry in manifest["images"]:
        pattern = read_image(sequence_dir / entry["file"])
        display.show(_to_screen(pattern))
        time.sleep(settle_s)
        image, bits = _grab(camera, frames)
        write_image(out_dir / entry["file"], image, bits=bits if frames == 1 else 16)
    shutil.copyfile(manifest_path, out_dir / SEQUENCE_FILE)
    return out_dir


def _to_screen(image: torch.Tensor) -> np.ndarray:
    """A :math:`(C, H, W)` image in [0, 1] as the uint8 :math:`(H, W)` or :math:`(H, W, 3)` array a display shows."""
    return (image.permute(1, 2, 0).squeeze(-1).cpu().numpy() * 255).round().astype(np.uint8)


def check_capture_options(settle_s, frames) -> float:
    """Before any window opens, the wait and the grabs a photo takes (``--settle``, ``--frames``): the
    wait as a float, as ``time.sleep`` refuses a negative or NaN one with a traceback, takes no numpy
    float, and never grabs after an infinite one."""
    if not (is_whole(frames) and frames >= 1):
        raise InputError(f"frames must be a whole number of camera frames, at least 1, got {frames!r}")
    if not (is_number(settle_s) and 0 <= settle_s <= 60):
        raise InputError(f"settle must be seconds in [0, 60] (--settle), got {settle_s!r}")
    return float(settle_s)


def _check_devices(displays: dict, camera, *, opens: bool = False) -> None:
    """Before anything is shown: each display has ``show`` and the camera ``grab``, the module's two
    things. ``opens``: a camera of None is allowed, as the caller then opens OpenCV's."""
    for name, display in displays.items():
        check(callable(getattr(display, "show", None)),
              f"{name} must be a display with show(image) (an OpenCVDisplay, or your own), got {type(display).__name__}")
    check((opens and camera is None) or callable(getattr(camera, "grab", None)),
          f"camera must have grab() returning a uint8 or uint16 frame (an OpenCVCamera, or your own), got "
          f"{type(camera).__name__}")


def _grab(camera, frames: int = 1) -> tuple[torch.Tensor, int]:
    """The mean of ``frames`` grabs as a :math:`(C, H, W)` float image in [0, 1], and the camera's bit depth."""
    total, bits = None, 8
    for _ in range(frames):
        frame = np.asarray(camera.grab())
        if frame.dtype not in (np.uint8, np.uint16) or not (frame.ndim == 2 or (frame.ndim == 3 and frame.shape[2] == 3)) \
                or min(frame.shape[:2], default=0) < 1:
            raise CaptureError(f"the camera's grab() gave a {frame.dtype} frame of shape {frame.shape}: a frame must be "
                               "uint8 or uint16, (H, W) or (H, W, 3); check the camera's format")
        bits = 16 if frame.dtype == np.uint16 else 8
        image = torch.from_numpy(frame.astype(np.float32) / (65535.0 if bits == 16 else 255.0))
        image = image[None] if image.dim() == 2 else image.permute(2, 0, 1)
        if total is not None and total.shape != image.shape:
            raise CaptureError(f"the camera's frames changed shape between grabs ({tuple(total.shape)} (C, H, W), then "
                               f"{tuple(image.shape)}): keep its resolution and format fixed while it captures")
        total = image if total is None else total + image
    return total / frames, bits


class LiveBench:
    """The bench in the camera loop, live (``torchproj refine --camera``): shows a step's patterns on
    every projector at once and photographs each state, where the loop would wait for a person's photos.

    Args:
        displays: projector name -> a display (module docstring), one per projector.
        camera: the camera.
        settle_s: seconds between showing and grabbing.
        frames: grabs averaged per photo (camera noise falls as their square root).
        prompt: called with a state's name before it is photographed where there are several states
            (a person moves the object there); None: no pause.
    """

    def __init__(self, displays: dict, camera, *, settle_s: float = 0.2, frames: int = 1, prompt=None):
        settle_s = check_capture_options(settle_s, frames)
        check(isinstance(displays, dict), f"displays must be a dict of projector name -> display, got "
                                          f"{type(displays).__name__}")
        _check_devices({f"displays[{name!r}]": d for name, d in displays.items()}, camera)
        self.displays, self.camera, self.settle_s, self.frames, self.prompt = displays, camera, settle_s, frames, prompt

    def photograph(self, patterns: dict[str, torch.Tensor], states: list[str], folder: Path) -> None:
        """Show ``patterns`` (projector name -> uint8 :math:`(C, H, W)`) and save ``folder/STATE.png`` per state."""
        missing = sorted(set(patterns) - set(self.displays))
        if missing:
            raise CaptureError(f"no display for projector(s) {missing}; give each a screen (--screen NAME=X,Y)")
        for name, image in patterns.items():
            self.displays[name].show(_to_screen(image.float() / 255))
        folder.mkdir(parents=True, exist_ok=True)
        for state in states:
            if self.prompt is not None and len(states) > 1:
                self.prompt(state)
            time.sleep(self.settle_s)
            image, bits = _grab(self.camera, self.frames)
            write_image(folder / f"{state}.png", image, bits=bits)
