"""Helpers shared by the viz scripts: device frusta, surface meshes, saving a view."""

from __future__ import annotations

import contextlib
import json
import logging
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pyvista as pv

__all__ = ["frustum", "surface_mesh", "finish", "box_wireframe", "side_bar", "written", "frame_rig", "read_or_refuse",
           "read_json", "read_npz", "read_points"]

# What a file cut short, edited, or written by another program raises as it is read: numpy's, json's,
# a zip's and VTK's errors, and the package's own for a scene it names (a ValueError).
UNREADABLE = (OSError, ValueError, KeyError, IndexError, TypeError, EOFError, zipfile.BadZipFile)


def read_or_refuse(parser, path: Path, read, fix: str):
    """``read(path)``, or the script's usage error (exit status 2) naming the file, what was wrong with
    it and ``fix``: such a file ended in a traceback from inside numpy, json or VTK."""
    try:
        return read(path)
    except UNREADABLE as exc:
        reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        parser.error(f"{path}: cannot be read ({reason}); {fix}")


def read_json(parser, path: Path, keys: tuple[str, ...], fix: str) -> dict:
    """A JSON object holding ``keys``, or the parser's error naming the file and the first key it lacks."""
    data = read_or_refuse(parser, path, lambda p: json.loads(p.read_text()), fix)
    _require(parser, path, data if isinstance(data, dict) else {}, keys, "", fix)
    return data


def read_npz(parser, path: Path, keys: tuple[str, ...], fix: str) -> dict:
    """An ``.npz``'s arrays (no pickled objects) holding ``keys``, or the parser's error naming the file."""
    def read(p):
        with np.load(p) as data:
            return {k: data[k] for k in data.files}

    arrays = read_or_refuse(parser, path, read, fix)
    _require(parser, path, arrays, keys, "array ", fix)
    return arrays


def _require(parser, path: Path, have: dict, keys: tuple[str, ...], what: str, fix: str) -> None:
    """The parser's error naming the file and the first of ``keys`` it lacks (``what``: "array ")."""
    missing = [k for k in keys if k not in have]
    if missing:
        parser.error(f"{path}: has no {what}{missing[0]!r}; {fix}")


def read_points(parser, path: Path, fix: str) -> np.ndarray:
    """A point cloud file's finite points :math:`(N, 3)`. pyvista's readers warn and give an empty mesh
    where VTK cannot read a file, after VTK's own reports on standard error and the log: the warning
    becomes the parser's error, the reports are held back."""
    quiet = pv.vtk_verbosity("off") if hasattr(pv, "vtk_verbosity") else contextlib.nullcontext()  # pyvista >= 0.45

    def read(p):
        with warnings.catch_warnings(), quiet:
            warnings.simplefilter("error")
            logging.disable(logging.ERROR)
            try:
                return np.asarray(pv.read(p).points, dtype=np.float64).reshape(-1, 3)
            except UserWarning as exc:
                raise ValueError(str(exc)) from None
            finally:
                logging.disable(logging.NOTSET)

    points = read_or_refuse(parser, path, read, fix)
    finite = np.isfinite(points).all(1)
    if not finite.all():
        parser.error(f"{path}: {int((~finite).sum())} of its {len(points)} points are not finite; {fix}")
    return points


def frustum(K: np.ndarray, width: int, height: int, world_from_dev: np.ndarray, depth: float) -> pv.PolyData:
    """Lines from the optical centre through the image corners (pixel-centre convention) to ``depth``."""
    corners = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5], [-0.5, height - 0.5]])
    rays = np.c_[(corners - K[:2, 2]) / np.diag(K)[:2], np.ones(4)] * depth
    pts = np.vstack([np.zeros(3), rays]) @ world_from_dev[:3, :3].T + world_from_dev[:3, 3]
    lines = [2, 0, 1, 2, 0, 2, 2, 0, 3, 2, 0, 4, 2, 1, 2, 2, 2, 3, 2, 3, 4, 2, 4, 1]
    return pv.PolyData(pts, lines=np.array(lines))


def frame_rig(plotter: pv.Plotter, geometry: dict) -> None:
    """Look at a rig from the devices' right, above and behind (y points down), framed on ``geometry``
    (name -> dataset) with room for the axes' labels: a camera fixed for the paper's rig cut other
    rigs' axes off at the image's edges."""
    plotter.camera_position = [(1.6, -0.9, -1.6), (0.0, 0.0, 0.0), (0, -1, 0)]
    plotter.reset_camera(bounds=pv.MultiBlock(geometry).bounds)
    plotter.camera.zoom(0.95)


def surface_mesh(surface) -> pv.DataSet:
    """A pyvista mesh of a surface in its local frame (as :class:`torchproj.scene.Surface` defines it)."""
    if surface.type == "rectangle":
        mesh = pv.Plane(i_size=surface.size[0], j_size=surface.size[1])
    elif surface.type == "plane":
        mesh = pv.Plane(i_size=2.0, j_size=2.0)
    elif surface.type == "box":
        sx, sy, sz = surface.size
        mesh = pv.Box(bounds=(-sx / 2, sx / 2, -sy / 2, sy / 2, -sz / 2, sz / 2))
    elif surface.type == "cylinder":
        mesh = pv.Cylinder(radius=surface.radius, height=surface.height, direction=(0, 1, 0), resolution=64)
    elif surface.type == "sphere":
        mesh = pv.Sphere(radius=1.0, theta_resolution=48, phi_resolution=48).scale(surface.radii, inplace=False)
    else:
        mesh = pv.read(surface.mesh_file).scale(surface.scale, inplace=False)
    return mesh.transform(surface.world_from_local, inplace=False)


def box_wireframe(world_from_local: np.ndarray, size) -> pv.PolyData:
    """The edges of a box (local frame: :class:`torchproj.scene.Surface`) at a pose."""
    sx, sy, sz = size
    box = pv.Box(bounds=(-sx / 2, sx / 2, -sy / 2, sy / 2, -sz / 2, sz / 2))
    return box.transform(np.asarray(world_from_local, dtype=np.float64), inplace=False).extract_all_edges()


def side_bar(title: str, fmt: str = "%.2f") -> dict:
    """``scalar_bar_args`` of a colour bar standing at the right edge, its title above its ticks (a
    horizontal bar under the view put its title over them), far enough in that a title of 35
    characters, centred over it, ends inside the image (at 0.85 the positioning view's ran off it)."""
    return {"title": title, "color": "black", "vertical": True, "position_x": 0.8, "position_y": 0.1,
            "height": 0.7, "title_font_size": 12, "label_font_size": 11, "fmt": fmt}


def finish(plotter: pv.Plotter, out: Path | None, show: bool, geometry: dict | None = None) -> pv.Plotter:
    """Save the view as a PNG (creating its folder), its geometry with its values beside it, and open
    a window if asked.

    ``geometry``: name -> pyvista dataset; written as ``OUT.vtm`` (a multiblock file ParaView and
    ``pyvista.read`` open, every point value kept), so that the view can be explored, not only looked at.
    The view itself, in its colours, is written as ``OUT.gltf`` (one file, its buffers inline): any
    glTF viewer opens it, browser-based ones included (three.js, Babylon.js, an online glTF viewer),
    where HTML would need trame's server stack, which the project does not install.
    A window's screenshot is taken by ``show`` itself: an on-screen plotter has nothing to screenshot
    before its window has rendered (``--show`` failed with "Nothing to screenshot").
    """
    if out is not None:
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        if geometry:
            pv.MultiBlock(geometry).save(str(out.with_suffix(".vtm")))
        plotter.export_gltf(str(out.with_suffix(".gltf")))
    if show:
        plotter.show(screenshot=None if out is None else str(out))
    elif out is not None:
        plotter.screenshot(str(out))
    return plotter


def written(out: Path) -> str:
    """The files :func:`finish` writes for ``out``, as a message names them."""
    out = Path(out)
    return f"{out}, {out.with_suffix('.vtm')} and {out.with_suffix('.gltf')}"
