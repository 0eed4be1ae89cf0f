"""Poses from YAML: a position plus one way of giving the orientation.

World frame of the shipped configs: x right, y down, z away from the rig (the OpenCV camera
convention, :mod:`torchproj.core.conventions`), so a device that looks straight ahead has the
identity rotation.
"""

from __future__ import annotations

import numpy as np

from ..core.checks import check, check_array
from ..core.errors import ConfigError
from .fields import Fields

__all__ = ["parse_pose", "look_at", "rotation_from_rotvec", "rotation_from_euler_deg"]

_ORIENTATIONS = ("look_at", "rotation", "rotvec", "euler_deg")


def rotation_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: axis-angle (radians) to a 3x3 rotation."""
    rotvec = check_array(rotvec, "rotvec (axis times angle, radians)", (3,), finite=True)
    theta = float(np.linalg.norm(rotvec))
    if theta < 1e-12:
        return np.eye(3)
    k = rotvec / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * kx @ kx


def rotation_from_euler_deg(angles: np.ndarray) -> np.ndarray:
    """Rotations about x, then y, then z (degrees), composed as ``Rz @ Ry @ Rx``."""
    rx, ry, rz = np.deg2rad(check_array(angles, "angles (degrees about x, y, z)", (3,), finite=True))
    return (
        rotation_from_rotvec(np.array([0, 0, rz]))
        @ rotation_from_rotvec(np.array([0, ry, 0]))
        @ rotation_from_rotvec(np.array([rx, 0, 0]))
    )


def look_at(position, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """Rotation ``world_from_local`` of a device at ``position`` whose +z looks at ``target``.

    ``up`` is the world direction that should appear up in the device's image (its -y axis).
    Returns None when the viewing direction is parallel to ``up`` (no unique answer).
    """
    z = check_array(target, "target", (3,), finite=True) - check_array(position, "position", (3,), finite=True)
    check(np.linalg.norm(z) >= 1e-9, f"target {target!r} is the position itself: look at another point")
    z /= np.linalg.norm(z)
    x = np.cross(z, check_array(up, "up", (3,), finite=True))
    if np.linalg.norm(x) < 1e-9:
        return None
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def parse_pose(fields: Fields) -> np.ndarray:
    """Read ``position`` and at most one orientation key into a 4x4 ``world_from_local`` pose.

    Orientation keys: ``look_at`` (a point; optional ``up``), ``rotation`` (3x3, rows),
    ``rotvec`` (axis-angle, radians) or ``euler_deg`` (x, y, z in degrees). None means identity.
    """
    position = np.array(fields.vector("position", 3))
    given = [k for k in _ORIENTATIONS if fields.has(k)]
    if len(given) > 1:
        raise ConfigError(fields.where(given[1]), f"conflicts with '{given[0]}'", "give one orientation")
    rotation = np.eye(3)
    if given == ["look_at"]:
        target = np.array(fields.vector("look_at", 3))
        up = fields.vector("up", 3, (0.0, -1.0, 0.0))
        if np.linalg.norm(target - position) < 1e-9:
            raise ConfigError(fields.where("look_at"), "equals the position", "look at another point")
        rotation = look_at(position, target, up)
        if rotation is None:
            raise ConfigError(fields.where("up"), "is parallel to the viewing direction", "choose another up")
    elif given == ["rotation"]:
        rows = fields.raw("rotation")
        if not isinstance(rows, list) or len(rows) != 3:
            raise ConfigError(fields.where("rotation"), "must be 3 rows of 3 numbers")
        from .fields import vector

        rotation = np.array([vector(r, fields.where(f"rotation[{i}]"), 3) for i, r in enumerate(rows)])
        err = np.abs(rotation @ rotation.T - np.eye(3)).max()
        if err > 1e-4 or np.linalg.det(rotation) < 0:
            raise ConfigError(
                fields.where("rotation"),
                f"is not a rotation (R R^T deviates from identity by {err:.2g}, det {np.linalg.det(rotation):.3g})",
                "give an orthonormal matrix with determinant +1, or use rotvec / euler_deg / look_at",
            )
    elif given == ["rotvec"]:
        rotation = rotation_from_rotvec(np.array(fields.vector("rotvec", 3)))
    elif given == ["euler_deg"]:
        rotation = rotation_from_euler_deg(np.array(fields.vector("euler_deg", 3)))
    if "look_at" not in given:
        fields.used.add("up")
        if fields.has("up"):
            raise ConfigError(fields.where("up"), "only goes with look_at", "remove it or use look_at")
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = position
    fields.done()
    return pose
