"""Camera-projector triangulation from an OpenCV stereo calibration.

The calibration file is OpenCV FileStorage as written by the usual procam-calibration scripts:
``cam_int``, ``cam_dist``, ``proj_int``, ``proj_dist``, ``rotation`` (also read under the
misspelling ``roration``) and ``translation``, with ``x_proj = R x_cam + T`` as returned by
``cv2.stereoCalibrate``. Points come out in the camera frame, in the calibration's units
(usually millimetres).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from kornia.geometry.calibration import undistort_points
from kornia.geometry.epipolar import triangulate_points

from ..core.checks import check, check_array, check_count, check_number, check_path, check_seed, check_shape
from ..core.errors import CaptureError

__all__ = ["ProCamCalibration", "read_opencv_calibration", "triangulate", "triangulate_map", "fit_plane", "largest_plane",
           "write_ply"]


@dataclass
class ProCamCalibration:
    """Intrinsics, distortion and the camera-to-projector pose of one camera and one projector."""

    cam_K: torch.Tensor  # 3x3
    cam_dist: torch.Tensor  # (k,)
    prj_K: torch.Tensor  # 3x3
    prj_dist: torch.Tensor  # (k,)
    prj_from_cam: torch.Tensor  # 3x4 [R | T]


def read_opencv_calibration(path: str | os.PathLike) -> ProCamCalibration:
    """Read a camera-projector calibration written by OpenCV's FileStorage (XML or YAML)."""
    check_path(path, "path", "the calibration file")
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: calibration file not found")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        opened = fs.isOpened()
    except (cv2.error, SystemError):  # OpenCV's parser raises on malformed XML/YAML
        raise CaptureError(f"{path}: not a readable OpenCV FileStorage file (malformed XML or YAML)") from None
    if not opened:
        raise CaptureError(f"{path}: not an OpenCV FileStorage file (XML or YAML)")

    def mat(shapes, *names):
        for name in names:
            node = fs.getNode(name)
            if node.empty():
                continue
            value = node.mat()
            if value is None or tuple(value.shape) not in shapes:
                raise CaptureError(f"{path}: '{name}' must be a matrix of shape "
                                   f"{' or '.join(map(str, shapes))}, got "
                                   f"{'no matrix' if value is None else tuple(value.shape)}")
            value = torch.as_tensor(value, dtype=torch.float64)
            if not torch.isfinite(value).all():
                raise CaptureError(f"{path}: '{name}' holds NaN or infinite values")
            return value
        raise CaptureError(f"{path}: missing '{names[0]}' (expected cam_int, cam_dist, proj_int, proj_dist, "
                           "rotation, translation as written by cv2.stereoCalibrate scripts)")

    square, vector3 = [(3, 3)], [(3, 1), (1, 3)]  # intrinsics and rotation; translation
    distortion = [(1, n) for n in (4, 5, 8, 12, 14)] + [(n, 1) for n in (4, 5, 8, 12, 14)]
    rotation = mat(square, "rotation", "roration", "R")
    translation = mat(vector3, "translation", "T").reshape(3, 1)
    calib = ProCamCalibration(
        cam_K=mat(square, "cam_int"), cam_dist=mat(distortion, "cam_dist").reshape(-1),
        prj_K=mat(square, "proj_int"), prj_dist=mat(distortion, "proj_dist").reshape(-1),
        prj_from_cam=torch.cat([rotation, translation], 1))
    fs.release()
    return calib


def _normalised(points: torch.Tensor, K: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """Undistorted normalised image coordinates (z = 1 plane) of pixel points :math:`(N, 2)`."""
    eye = torch.eye(3, dtype=points.dtype, device=points.device)[None]
    return undistort_points(points[None], K[None].to(points), dist[None].to(points),
                            new_K=eye, num_iters=20)[0]


def _check_procam(calib) -> None:
    check(isinstance(calib, ProCamCalibration), f"calib must be a ProCamCalibration (read_opencv_calibration's), got "
                                                f"{type(calib).__name__}")


def triangulate(cam_xy: torch.Tensor, prj_xy: torch.Tensor, calib: ProCamCalibration) -> torch.Tensor:
    """Triangulate camera-projector correspondences (linear DLT, kornia).

    Args:
        cam_xy: :math:`(N, 2)` camera pixel coordinates (conventions module).
        prj_xy: :math:`(N, 2)` projector pixel coordinates of the same points.
        calib: the stereo calibration.

    Returns:
        :math:`(N, 3)` points in the camera frame, in the calibration's units.
    """
    check_shape(cam_xy, "cam_xy", ["N", 2])
    check_shape(prj_xy, "prj_xy", ["N", 2])
    _check_procam(calib)
    cam_n = _normalised(cam_xy.double(), calib.cam_K, calib.cam_dist)
    prj_n = _normalised(prj_xy.double(), calib.prj_K, calib.prj_dist)
    # The calibration (a file's few numbers) is on the host; the points may be on a GPU.
    P1 = torch.cat([torch.eye(3, dtype=torch.float64), torch.zeros(3, 1, dtype=torch.float64)], 1).to(cam_n.device)
    P2 = calib.prj_from_cam.to(cam_n)
    return triangulate_points(P1[None], P2[None], cam_n[None], prj_n[None])[0]


def triangulate_map(prj_xy: torch.Tensor, calib: ProCamCalibration) -> torch.Tensor:
    """Triangulate every decoded camera pixel: :math:`(H, W, 2)` projector coordinates (NaN where not
    decoded) -> :math:`(H, W, 3)` float32 points in the camera frame, NaN where not decoded."""
    check_shape(prj_xy, "prj_xy", ["H", "W", 2])
    _check_procam(calib)
    ok = torch.isfinite(prj_xy).all(-1)
    ys, xs = torch.nonzero(ok, as_tuple=True)
    points = torch.full(ok.shape + (3,), float("nan"))
    points[ok] = triangulate(torch.stack([xs, ys], -1).double(), prj_xy[ok].double(), calib).float()
    return points


def fit_plane(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Least-squares plane through points (SVD of the centred cloud).

    Args:
        points: :math:`(N, 3)`.

    Returns:
        ``centroid`` (3,), unit ``normal`` (3,) and signed ``residuals`` (N,), the distances of the
        points from the plane in the points' units.
    """
    check_shape(points, "points", ["N", 3])
    centroid = points.mean(0)
    centred = points - centroid
    normal = torch.linalg.svd(centred, full_matrices=False)[2][2]
    return centroid, normal, centred @ normal


def largest_plane(points: torch.Tensor, threshold: float, trials: int = 500, seed: int = 0,
                  sample: int = 20000) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The plane most points lie on (RANSAC), refitted by least squares to the points within
    ``threshold`` of it: a board's flatness from the board, where the scan also holds the wall
    behind it and clutter (one least-squares plane through all of them measures none).

    Hand-written (a dozen lines): scikit-image's ``ransac`` would need a plane model class of ours
    all the same, and its model interface changes between releases (``estimate`` to ``from_estimate``).

    Args:
        points: :math:`(N, 3)`.
        threshold: the largest distance from the plane of a point on it (the points' units).
        trials: planes tried, each through three points drawn with ``seed``.
        sample: points the trials are scored on (all of them where fewer).

    Returns:
        ``centroid`` (3,), unit ``normal`` (3,), signed ``residuals`` (N,) of every point, and
        ``on_plane`` (N,) bool, within ``threshold`` of it. The plane is unbounded: clutter that
        crosses it within ``threshold`` counts as on it, so give a threshold a few times the scan's
        noise (a dent deeper than it is then off the plane).
    """
    check_shape(points, "points", ["N", 3])
    check(points.shape[0] >= 3, f"a plane needs 3 points or more, got {points.shape[0]}")
    check_number(threshold, "threshold (the points' units)", 0, strict=True)
    check_count(trials, "trials")
    check_seed(seed)
    check_count(sample, "sample (points the trials are scored on)", 3)
    g = torch.Generator().manual_seed(seed)
    scored = points[torch.randperm(points.shape[0], generator=g)[:sample]]
    three = points[torch.randint(points.shape[0], (trials, 3), generator=g)]
    edge_1, edge_2 = three[:, 1] - three[:, 0], three[:, 2] - three[:, 0]
    normals = torch.linalg.cross(edge_1, edge_2)
    length = normals.norm(dim=1, keepdim=True)
    # Three points on a line (to rounding: the sine of their angle under 1e-4) span no plane.
    valid = length[:, 0] > 1e-4 * edge_1.norm(dim=1) * edge_2.norm(dim=1)
    normals, anchors = normals[valid] / length[valid], three[valid, 0]
    check(len(normals) > 0, "every trial drew three points on a line; are the points all collinear?")
    counts = torch.stack([((scored - a) @ n).abs().lt(threshold).sum() for a, n in zip(anchors, normals)])
    best = int(counts.argmax())
    on_plane = ((points - anchors[best]) @ normals[best]).abs() < threshold
    centroid, normal, _ = fit_plane(points[on_plane])
    residuals = (points - centroid) @ normal
    return centroid, normal, residuals, residuals.abs() < threshold


def write_ply(path: str | os.PathLike, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Write an ASCII-header binary PLY point cloud (``points`` (N, 3); ``colors`` (N, 3) uint8)."""
    # An int is a file descriptor to open(): write_ply(True, ...) wrote the cloud to standard output.
    check_path(path, "path", "the point cloud")
    check(not os.path.isdir(path), f"path {str(path)!r} is a folder: give the point cloud's file name (cloud.ply)")
    points = check_array(points, "points", (None, 3), np.float32)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(points)}",
              "property float x", "property float y", "property float z"]
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
        fields += [("r", "u1"), ("g", "u1"), ("b", "u1")]
    header.append("end_header")
    data = np.empty(len(points), dtype=fields)
    data["x"], data["y"], data["z"] = points.T
    if colors is not None:
        colors = check_array(colors, "colors", (len(points), 3), np.uint8)
        data["r"], data["g"], data["b"] = colors.T
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode())
        f.write(data.tobytes())
