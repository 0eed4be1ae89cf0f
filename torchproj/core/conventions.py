"""Coordinate and image conventions used everywhere in torchproj.

This module is the one place where conventions are stated; every other docstring refers here.

**Units.** Metres and radians in scene descriptions and the simulator. Real calibration files keep
their own units (OpenCV calibrations are usually in millimetres); functions that read them say so.

**Frames.** A pose is named ``dst_from_src``: a 4x4 matrix mapping homogeneous points of frame
``src`` into frame ``dst`` (``world_from_cam`` maps camera-frame points into the world). Camera and
projector frames follow OpenCV: x right, y down, z forward along the optical axis.

**Pixels.** Image coordinates ``(x, y)``: x is the column, y the row, origin at the top-left of
the image, and *pixel centres at integer coordinates*, as in OpenCV and kornia. Pixel ``(i, j)``
(row i, column j) therefore covers ``[j - 0.5, j + 0.5) x [i - 0.5, i + 0.5)``. A projector pixel
index decoded from Gray code is the integer centre of the LCD cell that lit the camera pixel, so
a continuous projector coordinate ``u`` decodes to ``floor(u + 0.5)``.

**Sizes.** Resolutions are written ``(width, height)`` on the command line and in YAML
(``1024x768``), but tensors are ``(..., H, W)``. Maps from camera pixels to projector coordinates
are ``(H, W, 2)`` with the last axis ``(x, y)``; invalid entries are NaN.

**Images.** Inside the library images are float tensors ``(C, H, W)`` with values in ``[0, 1]``
(C = 1 or 3). 8-bit or 16-bit integers appear only at file edges (reading captures, writing
patterns).

**Colour.** Channels are ``(R, G, B)``. A projector's colour mixing (how a colour camera sees its
primaries) is a 3 x 3 matrix whose row c is camera channel c and column p projector primary p:
channel c sees ``sum_p mixing[c, p] light_p``. No mixing is the identity.

**Devices.** Tensors may live on any torch device (``--device cuda``); what leaves torch for numpy,
scipy, files or figures goes through :func:`to_numpy`, which brings it to the host first.
"""

from __future__ import annotations

import torch

__all__ = ["DEFAULT_COLOUR_MIXING", "MAX_MIXING_CONDITION", "pixel_grid", "round_to_pixel", "to_numpy"]

# The virtual rig's colour mixing where a scene gives none: a projector's primaries against a Bayer
# camera's filters, green leaking most (its band sits between the others), each row summing to 1 so
# that white looks as without mixing. A typical magnitude we chose, not a measured device.
DEFAULT_COLOUR_MIXING = ((0.88, 0.10, 0.02),
                         (0.07, 0.86, 0.07),
                         (0.02, 0.12, 0.86))
# A mixing whose condition number passes this cannot be undone: the camera cannot tell the primaries apart.
MAX_MIXING_CONDITION = 50.0


def pixel_grid(height: int, width: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """Return the pixel-centre coordinates of an image.

    Args:
        height: image height H.
        width: image width W.

    Returns:
        :math:`(H, W, 2)` tensor of ``(x, y)`` pixel centres (integers, see the module docstring).
    """
    from .checks import check, check_count

    check_count(height, "height", 0)
    check_count(width, "width", 0)
    check(isinstance(dtype, torch.dtype), f"dtype must be a torch.dtype, got {type(dtype).__name__}")
    try:
        ys, xs = torch.meshgrid(
            torch.arange(height, device=device, dtype=dtype),
            torch.arange(width, device=device, dtype=dtype),
            indexing="ij",
        )
    except (RuntimeError, TypeError):
        check(False, f"device must be a torch device this machine has, got {device!r}")
    return torch.stack([xs, ys], dim=-1)


def round_to_pixel(coords: torch.Tensor) -> torch.Tensor:
    """Index of the pixel cell containing continuous coordinates (``floor(u + 0.5)``).

    Args:
        coords: any shape, continuous pixel coordinates.

    Returns:
        int64 tensor of the same shape.
    """
    if not (isinstance(coords, torch.Tensor) and coords.is_floating_point()):
        from .errors import InputError

        raise InputError(f"coords must be a float tensor of pixel coordinates, got "
                         f"{coords.dtype if isinstance(coords, torch.Tensor) else type(coords).__name__}")
    return torch.floor(coords + 0.5).to(torch.int64)


def to_numpy(tensor: torch.Tensor):
    """A tensor's values as a numpy array on the host, from any device and detached from autograd
    (numpy cannot read a GPU's memory; ``Tensor.numpy()`` refuses a CUDA tensor)."""
    return tensor.detach().cpu().numpy()
