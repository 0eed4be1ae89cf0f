"""Target images and the targets of a scene: what to show where.

Images are :math:`(C, h, w)` float in [0, 1] (the library's convention); a target places one on the
camera pixels of its surfaces (:class:`~torchproj.transport.Target`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from ..core.checks import check, check_count, check_image, is_whole
from ..core.errors import InputError
from ..core.imageio import read_image
from ..scene.config import Scene, check_scene
from ..transport import Target

__all__ = ["DEFAULT_IMAGES", "default_images", "image_with_channels", "scene_images", "scene_targets", "target_image"]

DEFAULT_IMAGES = ("astronaut", "chelsea", "coffee", "rocket", "camera")
# Grey from RGB by the weights of scikit-image's rgb2gray (Poynton's luminance for CRT phosphors),
# applied here because importing its colour module imports scipy (0.1 s of a run from the cache);
# tests/pipeline/test_run.py compares the two to the bit.
LUMINANCE = (0.2125, 0.7154, 0.0721)


def _check_channels(channels) -> None:
    check(is_whole(channels) and channels in (1, 3),
          f"channels must be 1 (grey) or 3 (RGB), the camera's, got {channels!r}")


def target_image(name: str, channels: int) -> torch.Tensor:
    """A target image by scikit-image test-image name (``astronaut``, ``checkerboard``...) or file path.

    Returns:
        :math:`(C, h, w)` float in [0, 1] with the camera's channel count (RGB to grey by luminance,
        grey repeated to RGB, alpha dropped).
    """
    from skimage import data  # a lazy package: its loaders import on first use

    _check_channels(channels)
    check(isinstance(name, (str, os.PathLike)), f"image name must be a scikit-image test image's name or a file path, "
                                                f"got {type(name).__name__}")
    if Path(name).suffix:
        img = read_image(name, "save the target image again as PNG, TIFF or JPEG").permute(1, 2, 0).numpy()
    elif (shipped := _shipped_file(name)) is not None:
        img = read_image(shipped).permute(1, 2, 0).numpy()
    else:
        check(name in getattr(data, "__all__", dir(data)) and not name.startswith("_")
              and callable(getattr(data, name, None)),
              f"unknown image {name!r}: give an image file (with its suffix) or a scikit-image test image "
              "name such as astronaut, chelsea, coffee, rocket, camera, checkerboard, horse")
        try:
            raw = getattr(data, name)()
        except Exception as exc:  # noqa: BLE001 - a loader that must download fails in as many ways as a network
            raise InputError(f"image {name!r}: scikit-image could not load it ({type(exc).__name__}: some of its "
                             "images are downloaded on first use); give an image file instead") from None
        check(isinstance(raw, np.ndarray) and (raw.ndim == 2 or (raw.ndim == 3 and raw.shape[2] in (3, 4))),
              f"image {name!r}: scikit-image's loader gives "
              f"{f'an array of shape {raw.shape}' if isinstance(raw, np.ndarray) else type(raw).__name__}, not one "
              "grey or colour picture; choose another name or give an image file")
        raw = np.asarray(raw)
        img = raw.astype(np.float32) / (1.0 if raw.dtype == bool else float(np.iinfo(raw.dtype).max)
                                        if raw.dtype.kind in "ui" else 1.0)
    if img.ndim == 2:
        img = img[..., None]
    check(img.shape[0] >= 2 and img.shape[1] >= 2, f"image {name!r}: {img.shape[1]}x{img.shape[0]} pixels; a target "
                                                    "image is stretched over its surfaces' pixels and needs at least "
                                                    "2 x 2")
    return torch.from_numpy(_with_channels(img[..., :3], channels)).permute(2, 0, 1)


def _with_channels(img: np.ndarray, channels: int) -> np.ndarray:
    """An :math:`(h, w, C)` image (C 1 or 3) with the camera's ``channels``: grey repeated to RGB,
    RGB to grey by :data:`LUMINANCE`; float32, contiguous."""
    if img.shape[-1] == 1 and channels == 3:
        img = np.repeat(img, 3, -1)
    elif img.shape[-1] == 3 and channels == 1:
        img = (img @ np.asarray(LUMINANCE, dtype=img.dtype))[..., None]
    return np.ascontiguousarray(img, dtype=np.float32)


def _shipped_file(name: str) -> Path | None:
    """The PNG file scikit-image ships for default image ``name`` (:data:`DEFAULT_IMAGES`), where it
    is there; None otherwise (then its loader reads it).

    Its loader gives the same pixels from the same file, but the first call imports ``skimage.io``,
    imageio and scipy (0.3 s of a 4.5 s run from the cache); the project's own reader takes 0.03 s.
    Only PNGs, which every decoder reads to the same values, and only the default images, whose
    loaders read their file as it is (``tests/pipeline/test_run.py`` compares each with its loader).
    """
    if name not in DEFAULT_IMAGES:
        return None
    from skimage import data

    path = Path(data.__file__).parent / f"{name}.png"
    return path if path.is_file() else None


def default_images(count: int, channels: int) -> list[torch.Tensor]:
    """Test images that ship with scikit-image, one per target: :math:`(C, h, w)` in [0, 1]."""
    check_count(count, "count (of default images)", 0)
    check(count <= len(DEFAULT_IMAGES), f"at most {len(DEFAULT_IMAGES)} default images; give your own targets")
    return [target_image(name, channels) for name in DEFAULT_IMAGES[:count]]


def scene_images(scene: Scene) -> list[torch.Tensor]:
    """One image per target of the scene: the config's choice, else the next default image."""
    specs = check_scene(scene).target_specs()
    defaults = iter(name for name in DEFAULT_IMAGES if name not in {t.image for t in specs})
    images = []
    for spec in specs:
        name = spec.image or next(defaults, None)
        check(name is not None, f"more targets than default images; give target {spec.name!r} an image")
        images.append(target_image(name, scene.camera.channels))
    return images


def checked_images(scene: Scene, images: list[torch.Tensor] | None) -> list[torch.Tensor]:
    """``images`` (None: :func:`scene_images`) as a list of one checked library image per target, each
    with the camera's channels as an image file gets them (:func:`target_image`: grey repeated to a
    colour camera's three, colour to a grey camera's luminance)."""
    if images is None:
        return scene_images(scene)
    specs = scene.target_specs()
    try:
        images = list(images)
    except TypeError:
        raise InputError(f"images must be a list of one (C, h, w) image per target ({len(specs)}), got "
                         f"{type(images).__name__}") from None
    check(len(images) == len(specs), f"give one target image per target ({len(specs)}), got {len(images)}")
    return [image_with_channels(img, scene.camera.channels, f"target {spec.name!r} image")
            for spec, img in zip(specs, images)]


def image_with_channels(image: torch.Tensor, channels: int, name: str = "image") -> torch.Tensor:
    """A checked :math:`(C, h, w)` image tensor with the camera's ``channels``, as :func:`target_image`
    gives a file's: grey repeated to three, colour to luminance. A grey image on a colour camera (or the
    other way) had gone through calibration and the solve, to end in the scores' "estimate must have
    shape (3, H, W)". ``name``: what the refusal of an image that is none calls it."""
    _check_channels(channels)
    check_image(image, name)
    if image.shape[0] == channels:
        return image
    converted = _with_channels(image.detach().cpu().permute(1, 2, 0).numpy(), channels)
    return torch.from_numpy(converted).permute(2, 0, 1).to(image.device)


def check_target_channels(targets: list[Target], channels: int) -> None:
    """Every target's image has the camera's ``channels`` (each is scored against the capture's)."""
    for i, target in enumerate(targets):
        count = check_image(target.image, f"target {target.name or i!r} image")["C"]  # a list there is named, not read
        check(count == channels,
              f"target {target.name!r} has {count} channel(s) and the camera {channels}: give every "
              "target the camera's (torchproj.pipeline.image_with_channels converts an image as a file is read: "
              "grey repeated to three, colour to luminance)")


def scene_targets(scene: Scene, images: list[torch.Tensor] | None = None, rig=None) -> list[Target]:
    """The scene's targets (:meth:`~torchproj.scene.Scene.target_specs`) with their images and masks.

    Args:
        images: one :math:`(C, h, w)` image per target; None: :func:`scene_images`.
        rig: the :class:`~torchproj.sim.VirtualRig` that gives a target's surfaces their camera mask
            (the pixels that see them, standing in for the mask a user paints over a real capture);
            None only for scenes whose targets name no surfaces (each covers everything lit).

    Returns:
        one :class:`~torchproj.transport.Target` per target, masks on the CPU.
    """
    specs = check_scene(scene).target_specs()
    images = checked_images(scene, images)
    check(rig is not None or all(s.surfaces is None for s in specs),
          "targets that name surfaces need the virtual rig for their camera masks: pass rig=")
    return [Target(spec.state, img.to(torch.float32), name=spec.name,
                   mask=None if spec.surfaces is None else rig.surface_mask(spec.state, spec.surfaces).cpu())
            for spec, img in zip(specs, images)]
