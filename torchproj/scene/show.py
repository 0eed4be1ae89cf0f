"""The world as shown: what changed between calibration and the moment the patterns are shown.

A bench drifts from its calibration: a projector is bumped, its lamp warms up, room light changes,
the camera's tripod settles. A scene's optional ``show:`` section describes such changes; the
virtual rig calibrates the scene as written and shows the patterns in :func:`shown_scene`'s world,
so a run scores what a stale calibration costs and what camera-in-the-loop refinement wins back
(:func:`torchproj.solve.refine_patterns`).

.. code-block:: yaml

    show:
      projectors:
        upper: {translation_mm: [1, 0, 0], rotation_deg: [0, 0.1, 0], gain: 1.2, exponent: 1.05}
      camera: {translation_mm: [0, 0.5, 0]}
      ambient: 0.05

- ``translation_mm``: the device moves by this in the world frame (x right, y down, z away from
  the rig: :mod:`torchproj.scene.pose`), millimetres.
- ``rotation_deg``: then turns about its own centre by these Euler angles in its own frame (x, then
  y, then z, as ``euler_deg``).
- ``gain``: the projector's light is this many times what it was (a warmer lamp, another mode).
- ``exponent``: its response exponent ``b`` is this many times what it was (``a x^b``).
- ``ambient``: room light while showing, W/m^2 (replaces the scene's ``ambient``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..core.errors import ConfigError
from .fields import Fields
from .pose import rotation_from_euler_deg

__all__ = ["DeviceDrift", "ProjectorDrift", "ShowChanges", "describe_show", "parse_show", "shown_scene"]

# A bump moves a device by millimetres and tenths of a degree; past these the rig is another rig,
# and a run should calibrate it rather than call it drift.
MAX_TRANSLATION_MM = 100.0
MAX_ROTATION_DEG = 10.0
RESPONSE_B_RANGE = (0.2, 5.0)  # as the scene's own response.b


@dataclass(frozen=True)
class DeviceDrift:
    """How far a device moved after calibration (module docs)."""

    translation_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def moved(self, world_from_device: np.ndarray) -> np.ndarray:
        """The device's 4x4 pose after the drift: turned about its own centre, then moved."""
        pose = world_from_device.copy()
        pose[:3, :3] = pose[:3, :3] @ rotation_from_euler_deg(np.array(self.rotation_deg))
        pose[:3, 3] = pose[:3, 3] + np.array(self.translation_mm) / 1000
        return pose

    def as_dict(self) -> dict:
        return {"translation_mm": list(self.translation_mm), "rotation_deg": list(self.rotation_deg)}


@dataclass(frozen=True)
class ProjectorDrift(DeviceDrift):
    """A projector's drift: its pose, and its light (``gain``) and response exponent (``exponent``)."""

    gain: float = 1.0
    exponent: float = 1.0

    def as_dict(self) -> dict:
        return {**super().as_dict(), "gain": self.gain, "exponent": self.exponent}


@dataclass(frozen=True)
class ShowChanges:
    """A scene's ``show:`` section: per projector name its drift, the camera's, and the room light."""

    projectors: dict[str, ProjectorDrift] = field(default_factory=dict)
    camera: DeviceDrift | None = None
    ambient: float | None = None

    def as_dict(self) -> dict:
        """For reports and the scene's YAML form."""
        out: dict = {}
        if self.projectors:
            out["projectors"] = {name: d.as_dict() for name, d in self.projectors.items()}
        if self.camera is not None:
            out["camera"] = self.camera.as_dict()
        if self.ambient is not None:
            out["ambient"] = self.ambient
        return out


def describe_show(changes: dict) -> str:
    """A ``show:`` section (:meth:`ShowChanges.as_dict`, as a report keeps it) in words, naming only
    what changed: ``"projector upper: moved [1.5, 0, 0] mm, turned [0, 0.1, 0] degrees, light x1.12;
    room light 0.05 W/m^2"``."""
    def device(what: str, d: dict) -> str:
        parts = [f"moved {[round(v, 3) for v in d['translation_mm']]} mm" if any(d.get("translation_mm", ())) else "",
                 f"turned {[round(v, 3) for v in d['rotation_deg']]} degrees" if any(d.get("rotation_deg", ())) else "",
                 f"light x{d['gain']:g}" if d.get("gain", 1.0) != 1.0 else "",
                 f"response exponent x{d['exponent']:g}" if d.get("exponent", 1.0) != 1.0 else ""]
        return f"{what}: {', '.join(p for p in parts if p) or 'unchanged'}"

    lines = [device(f"projector {name}", d) for name, d in changes.get("projectors", {}).items()]
    if "camera" in changes:
        lines.append(device("camera", changes["camera"]))
    if changes.get("ambient") is not None:
        lines.append(f"room light {changes['ambient']:g} W/m^2")
    return "; ".join(lines) or "nothing"


def _drift(f: Fields) -> dict:
    t = f.vector("translation_mm", 3, (0.0, 0.0, 0.0))
    r = f.vector("rotation_deg", 3, (0.0, 0.0, 0.0))
    if max(abs(v) for v in t) > MAX_TRANSLATION_MM:
        raise ConfigError(f.where("translation_mm"), f"moves the device by up to {max(abs(v) for v in t):g} mm, more "
                          f"than a drift (at most {MAX_TRANSLATION_MM:g} mm per axis)",
                          "give millimetres, or describe the moved rig as a scene of its own and calibrate it")
    if max(abs(v) for v in r) > MAX_ROTATION_DEG:
        raise ConfigError(f.where("rotation_deg"), f"turns the device by up to {max(abs(v) for v in r):g} degrees, "
                          f"more than a drift (at most {MAX_ROTATION_DEG:g} per axis)",
                          "give degrees, or describe the turned rig as a scene of its own and calibrate it")
    return {"translation_mm": tuple(t), "rotation_deg": tuple(r)}


def parse_show(f: Fields, projectors: list) -> ShowChanges:
    """Validate a ``show:`` mapping against the scene's projectors (their names and response exponents)."""
    by_name = {p.name: p for p in projectors}
    f.used.update(("projectors", "camera", "ambient"))  # optional: a misspelling of one is offered it
    drifts = {}
    if f.has("projectors"):
        section = f.sub("projectors")
        if not isinstance(section.data, dict) or not section.data:
            raise ConfigError(f.where("projectors"), "must map projector names to their changes",
                              f"e.g. projectors: {{{projectors[0].name}: {{gain: 1.2}}}}")
        for name in section.data:
            if name not in by_name:
                raise ConfigError(section.where(str(name)), "names no projector of the scene",
                                  f"known: {list(by_name)}")
            pf = section.sub(name)
            pf.used.update(("gain", "exponent"))
            gain = pf.number("gain", 1.0, lo=0, strict_lo=True, hi=10.0)
            exponent = pf.number("exponent", 1.0, lo=0, strict_lo=True)
            lo, hi = RESPONSE_B_RANGE
            shown_b = [b * exponent for b in by_name[name].response_b]
            if not all(lo <= b <= hi for b in shown_b):
                raise ConfigError(pf.where("exponent"), f"makes the response exponent {shown_b}, outside [{lo}, {hi}]",
                                  "give the factor on the exponent b (1.05 turns 2.2 into 2.31)")
            drifts[str(name)] = ProjectorDrift(**_drift(pf), gain=gain, exponent=exponent)
            pf.done()
    camera = None
    if f.has("camera"):
        cf = f.sub("camera")
        camera = DeviceDrift(**_drift(cf))
        cf.done()
    shown_ambient = f.number("ambient", lo=0) if f.has("ambient") else None
    f.done()
    changes = ShowChanges(drifts, camera, shown_ambient)
    if not changes.as_dict():
        raise ConfigError("show", "changes nothing", "give projectors, camera or ambient, or leave show out")
    return changes


def shown_scene(scene):
    """The scene as the patterns are shown: its ``show`` changes applied, ``show`` itself dropped.

    A scene without ``show`` is returned as it is (the world it was calibrated in).
    """
    from .config import check_scene  # config reads a scene's show section with this module

    changes: ShowChanges | None = check_scene(scene).show
    if changes is None:
        return scene
    projectors = []
    for p in scene.projectors:
        d = changes.projectors.get(p.name)
        if d is None:
            projectors.append(p)
            continue
        projectors.append(dataclasses.replace(p, world_from_prj=d.moved(p.world_from_prj), power=p.power * d.gain,
                                              response_b=tuple(b * d.exponent for b in p.response_b)))
    camera = scene.camera if changes.camera is None else dataclasses.replace(
        scene.camera, world_from_cam=changes.camera.moved(scene.camera.world_from_cam))
    ambient = scene.ambient if changes.ambient is None else changes.ambient
    return dataclasses.replace(scene, projectors=projectors, camera=camera, ambient=ambient, show=None)
