"""Scene and rig descriptions: YAML files loaded into validated dataclasses.

Every check runs at load time, before any work, and a failure raises
:class:`~torchproj.core.errors.ConfigError` naming the field (``projectors[1].focal``) and the fix.
Units and frames: :mod:`torchproj.core.conventions` and :mod:`torchproj.scene.pose`.

A scene holds J projectors, one camera, named surfaces and K *states*. A state lists the surfaces
present at one moment (the same box near, then far, is two surfaces in two states). Optional
*targets* say which image should appear on which surfaces of which state; without them, each state
is one target covering everything the projectors light there.
"""

from __future__ import annotations

import copy
import math
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ..core.checks import SIZE_LIMIT, check, check_pair, check_path, is_number, is_whole
from ..core.conventions import DEFAULT_COLOUR_MIXING, MAX_MIXING_CONDITION
from ..core.errors import ConfigError, InputError
from .fields import Fields, vector
from .pose import parse_pose
from .show import ShowChanges, describe_show, parse_show

__all__ = [
    "Projector",
    "Camera",
    "Surface",
    "State",
    "TargetSpec",
    "Scene",
    "load_scene",
    "parse_scene",
    "builtin_config",
    "config_dir",
    "scale_config",
    "BUILTIN_SCENES",
    "SIZE_LIMIT",
]

SURFACE_TYPES = ("rectangle", "plane", "box", "cylinder", "sphere", "mesh")
# Frames a virtual capture averages at most: each is a draw of the sensor's whole chain, so 256 frames
# cost 256 times one's sensor work, and their mean already holds a sixteenth of one frame's noise.
MAX_FRAMES = 256
#: the shipped scenes (``configs/NAME.yaml``), each loaded by name: ``load_scene("box_cylinders")``.
BUILTIN_SCENES = ("paper_two_planes", "colour_two_planes", "three_planes", "box_cylinders", "head_two_positions",
                  "two_screens", "box_positions", "paper_defocus", "paper_bumped", "sphere_three_projectors",
                  "corner_screens")


def config_dir() -> Path:
    """The folder of the built-in scenes: ``configs/`` in a checkout, ``torchproj/configs`` when installed.

    Found through the package (``importlib.resources``), so a wheel or plain install finds it from
    any working directory; a source tree used without installing (``PYTHONPATH``) has it beside
    the package.
    """
    from importlib.resources import files
    from importlib.util import find_spec

    if find_spec("torchproj.configs") is None:
        return Path(__file__).resolve().parents[2] / "configs"
    return Path(str(files("torchproj.configs")))


@dataclass
class Pinhole:
    """Resolution and intrinsics shared by cameras and projectors (pixels, conventions module)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])


@dataclass
class Projector(Pinhole):
    """A pinhole projector with an LCD pixel grid.

    Emitted light of a pixel with pattern value x in [0, 1] (per colour channel):
    ``power * (a * x**b + black_level) * vignette(u)``, where
    ``vignette(u) = 1 - vignetting * (r / r_corner)**2`` and r is the distance of pixel u from the
    principal point. ``power`` is the irradiance in W/m^2 on a surface facing the projector at 1 m.

    Lens (optional, a thin lens): focused at ``focus_distance`` metres (depth along the projector's
    axis) with an aperture of diameter ``aperture`` metres. A cell's light then reaches a surface
    point at depth z spread over a disc (the circle of confusion) of diameter
    :meth:`blur_diameter` cells; None (the default) is a pinhole, sharp at every depth.

    ``colour_mixing``: with a colour camera, how much of each primary each camera channel sees
    (conventions module, "Colour"); None: each channel sees its own primary alone.
    """

    name: str = ""
    world_from_prj: np.ndarray = field(default_factory=lambda: np.eye(4))
    response_a: float = 1.0
    response_b: tuple[float, ...] = (2.2,)
    black_level: float = 0.01
    vignetting: float = 0.0
    power: float = 1.0
    focus_distance: float | None = None
    aperture: float = 0.0
    colour_mixing: tuple[tuple[float, ...], ...] | None = None

    @property
    def centre(self) -> np.ndarray:
        return self.world_from_prj[:3, 3]

    def blur_diameter(self, depth):
        """Diameters ``(along x, along y)`` in LCD cells of the circle of confusion at ``depth``
        metres (a number or an array). The aperture's cone converges on the focus plane, so at depth z
        it is ``aperture |z - z_f| / z_f`` wide; seen from the projector at depth z that is
        ``f aperture |1/z_f - 1/z|`` cells (f the focal length in cells, per axis)."""
        if self.focus_distance is None:
            return 0.0 * depth, 0.0 * depth
        spread = self.aperture * abs(1 / self.focus_distance - 1 / depth)
        return self.fx * spread, self.fy * spread


@dataclass
class Camera(Pinhole):
    """A pinhole camera with optional distortion (OpenCV's k1, k2, p1, p2, k3).

    Pixel value before noise: ``exposure * radiance`` (linear; ``gamma`` != 1 bends it as
    ``v**(1/gamma)``). Noise: shot noise with ``full_well`` electrons at value 1 and Gaussian read
    noise of standard deviation ``read_noise`` (in [0, 1] units), then quantisation to ``bit_depth``.
    Each capture is the mean of ``frames`` such frames (their noise falls as the square root of
    their number), as a bench averages grabs (``torchproj capture --frames``). Each pixel integrates
    ``supersampling**2`` rays over its footprint.
    """

    world_from_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    distortion: tuple[float, ...] = ()
    channels: int = 1
    exposure: float = 1.0
    gamma: float = 1.0
    full_well: float = 0.0
    read_noise: float = 0.0
    bit_depth: int = 8
    supersampling: int = 2
    frames: int = 1

    @property
    def stored_bits(self) -> int:
        """Bits a capture file keeps: ``bit_depth``, or 16 for a mean of several frames, which holds
        levels between one frame's."""
        return self.bit_depth if self.frames == 1 else 16


# Camera samples must fall at most this many projector cells apart, or a solver learns where they land
# (the virtual rig warns: torchproj.sim.rig; benchmarks/sampling.py measures it).
SAMPLE_SPACING = 0.4


def supersampling_for(projector_focal: float, camera_focal: float, wanted: int = 1) -> int:
    """The fewest samples per camera pixel axis (at least ``wanted``) that keep them within
    :data:`SAMPLE_SPACING` projector cells of each other on a surface as far from the camera as from
    the projector (focal lengths in pixels)."""
    return max(int(wanted), math.ceil(projector_focal / (camera_focal * SAMPLE_SPACING) - 1e-9))


@dataclass
class Surface:
    """A matte (Lambertian) surface. Local frames (before ``world_from_local``):

    - ``rectangle``: the plane z = 0, ``size`` = (width along x, height along y); ``plane`` is
      the same without bounds.
    - ``box``: axis-aligned, centred, ``size`` = (x, y, z) edge lengths.
    - ``cylinder``: axis along y, centred, ``radius``, ``height``, closed by caps.
    - ``sphere``: centred, ``radii`` = (rx, ry, rz) (equal for a sphere, else an ellipsoid).
    - ``mesh``: a triangle mesh file (anything trimesh reads) scaled by ``scale``.

    ``transmittance`` (screens only): the fraction of light a semi-transparent screen passes on.
    """

    name: str
    type: str
    world_from_local: np.ndarray
    albedo: tuple[float, ...] = (0.8,)
    transmittance: float = 0.0
    size: tuple[float, ...] = ()
    radius: float = 0.0
    height: float = 0.0
    radii: tuple[float, ...] = ()
    mesh_file: Path | None = None
    scale: float = 1.0


@dataclass
class State:
    """One arrangement of the scene: which surfaces are present."""

    name: str
    surfaces: list[str]


@dataclass
class TargetSpec:
    """An image to show on some surfaces of one state.

    Attributes:
        name: for reports.
        state: the state in which the image should appear.
        surfaces: the surfaces that carry it (their camera pixels are the target's mask); None means
            everything lit in the state.
        image: a scikit-image test image name (``astronaut``, ``checkerboard``...) or an image file
            (relative to the config's folder); None leaves the choice to the caller.
    """

    name: str
    state: str
    surfaces: list[str] | None = None
    image: str | None = None


@dataclass
class Scene:
    name: str
    projectors: list[Projector]
    camera: Camera
    surfaces: dict[str, Surface]
    states: list[State]
    ambient: float = 0.0
    seed: int = 0
    targets: list[TargetSpec] = field(default_factory=list)
    source: Path | None = field(default=None, compare=False)
    show: ShowChanges | None = None  # what changed after calibration (torchproj.scene.show)
    interreflection: bool = False  # one bounce of projector light between surfaces (torchproj.sim.bounce)

    def describe(self) -> str:
        """What the scene holds, one line per device, surface and state (``torchproj scene``)."""
        cam = self.camera
        lines = [f"scene {self.name} ({self.source if self.source is not None else 'generated, not read from a file'})"]
        for p in self.projectors:
            lines.append(f"  projector {p.name}: {p.width}x{p.height}, f={p.fx:g}px, at "
                         f"{np.round(p.centre, 3).tolist()} m, response x^{'/'.join(f'{b:g}' for b in p.response_b)}, "
                         f"black {p.black_level:g}"
                         + (f", focused at {p.focus_distance:g} m, aperture {p.aperture * 1000:g} mm"
                            if p.focus_distance is not None else "")
                         + (f", colour mixing {[list(row) for row in p.colour_mixing]}"
                            if p.colour_mixing is not None else ""))
        lines.append(f"  camera: {cam.width}x{cam.height}, f={cam.fx:g}px, at "
                     f"{np.round(cam.world_from_cam[:3, 3], 3).tolist()} m, {cam.channels} channel(s), "
                     f"{cam.bit_depth}-bit, exposure {cam.exposure:g}, {cam.supersampling}x{cam.supersampling} "
                     "samples per pixel"
                     + (f", gamma {cam.gamma:g}" if cam.gamma != 1 else "")
                     + (f", distortion {list(cam.distortion)}" if any(cam.distortion) else "")
                     + (f", each capture the mean of {cam.frames} frames" if cam.frames > 1 else ""))
        lines += [f"  surface {s.name}: {s.type} at {np.round(s.world_from_local[:3, 3], 3).tolist()} m, albedo "
                  f"{'/'.join(f'{a:g}' for a in s.albedo)}"
                  + (f", passes {s.transmittance:g} of the light on" if s.transmittance > 0 else "")
                  for s in self.surfaces.values()]
        if self.ambient > 0:
            lines.append(f"  room light: {self.ambient:g} W/m^2 on every surface")
        lines += [f"  state {st.name}: {', '.join(st.surfaces)}" for st in self.states]
        if self.interreflection:
            lines.append("  interreflection: one bounce of projector light between surfaces")
        if self.show is not None:
            lines.append(f"  shown after calibration with changes: {describe_show(self.show.as_dict())}")
        return "\n".join(lines)

    def projector_index(self, key) -> int:
        """The index of projector ``key``, given by name or by index."""
        names = [p.name for p in self.projectors]
        check(key in names or (is_whole(key) and 0 <= key < len(names)),
              f"no projector {key!r}: give one of {names} or an index from 0 to {len(names) - 1}")
        return names.index(key) if key in names else int(key)

    def target_specs(self) -> list[TargetSpec]:
        """The scene's targets, or one per state (all its surfaces) when the config names none."""
        return self.targets or [TargetSpec(name=st.name, state=st.name) for st in self.states]

    def state(self, name: str) -> State:
        for s in self.states:
            if s.name == name:
                return s
        raise ConfigError("states", f"no state named {name!r}", f"known: {[s.name for s in self.states]}")

    @property
    def channels(self) -> int:
        return self.camera.channels


def _resolution(f: Fields, key: str = "resolution") -> tuple[int, int]:
    value = f.raw(key)
    if isinstance(value, str) and "x" in value:
        value = value.split("x")
        try:
            value = [int(v) for v in value]
        except ValueError:
            pass
    if (not isinstance(value, list) or len(value) != 2
            or not all(is_whole(v) and v > 0 for v in value)):
        raise ConfigError(f.where(key), f"must be [width, height] in whole pixels, got {f.data[key]!r}")
    return value[0], value[1]


def _intrinsics(f: Fields, width: int, height: int) -> tuple[float, float, float, float]:
    """Focal length (one or two numbers, pixels) and principal point (or lens shift)."""
    focal = f.raw("focal")
    if isinstance(focal, list):
        fx, fy = f.vector("focal", 2, lo=0, strict_lo=True)
    else:
        fx = fy = f.number("focal", lo=0, strict_lo=True)
    if f.has("principal_point") and f.has("lens_shift"):
        raise ConfigError(f.where("lens_shift"), "conflicts with 'principal_point'", "give one of them")
    centre = ((width - 1) / 2, (height - 1) / 2)
    if f.has("principal_point"):
        cx, cy = f.vector("principal_point", 2)
    else:
        # Lens shift as projector makers quote it: a fraction of the image size.
        sx, sy = f.vector("lens_shift", 2, (0.0, 0.0))
        cx, cy = centre[0] + sx * width, centre[1] + sy * height
    return fx, fy, cx, cy


# A projector lens wider than this is no lens a projector has: most likely metres written as millimetres.
_MAX_APERTURE_MM = 200.0


def _colour_mixing(f: Fields, channels: int) -> tuple[tuple[float, ...], ...] | None:
    """A projector's ``colour_mixing``: three rows (camera channels R, G, B) of three shares
    (primaries), ``none`` for none; absent: :data:`~torchproj.core.conventions.DEFAULT_COLOUR_MIXING`
    with a colour camera, none with a grey one."""
    value = f.raw("colour_mixing", "default")
    if value == "default":
        return DEFAULT_COLOUR_MIXING if channels == 3 else None
    if value == "none":
        return None
    where = f.where("colour_mixing")
    if channels != 3:
        raise ConfigError(where, "needs a colour camera (camera.channels: 3): a grey camera sums the primaries",
                          "drop it, or set camera.channels to 3")
    if not isinstance(value, list) or len(value) != 3:
        raise ConfigError(where, f"must be 3 rows (camera channels R, G, B) of 3 shares (primaries), or 'none', got "
                                 f"{value!r}", "e.g. [[0.9, 0.1, 0.0], [0.05, 0.9, 0.05], [0.0, 0.1, 0.9]]")
    rows = tuple(vector(row, f"{where}[{i}]", 3, lo=0, hi=1) for i, row in enumerate(value))
    for i, row in enumerate(rows):
        if sum(row) <= 0:
            raise ConfigError(f"{where}[{i}]", "is all zero: that camera channel would see no projector light",
                              "give it the share of each primary it sees")
    cond = float(np.linalg.cond(np.array(rows)))
    if not cond <= MAX_MIXING_CONDITION:
        raise ConfigError(where, f"mixes the primaries so much that the camera cannot tell them apart (condition "
                                 f"number {cond:.3g}, over {MAX_MIXING_CONDITION:g})",
                          "each row's largest share should be its own primary's (the diagonal)")
    return rows


def _parse_projector(f: Fields, index: int, channels: int = 1) -> Projector:
    name = f.name("name", f"projector{index}")
    width, height = _resolution(f)
    fx, fy, cx, cy = _intrinsics(f, width, height)
    pose = parse_pose(f.sub("pose"))
    response = f.sub("response", {})
    a = response.number("a", 1.0, lo=0, strict_lo=True)
    b = response.scalar_or_rgb("b", 2.2, lo=0.2, hi=5.0)
    response.done()
    proj = Projector(
        name=name, width=width, height=height, fx=fx, fy=fy, cx=cx, cy=cy, world_from_prj=pose,
        response_a=a, response_b=b,
        black_level=f.number("black_level", 0.01, lo=0, hi=1),
        vignetting=f.number("vignetting", 0.0, lo=0, hi=0.99),
        power=f.number("power", 1.0, lo=0, strict_lo=True),
        colour_mixing=_colour_mixing(f, channels),
    )
    if f.has("focus"):
        lens = f.sub("focus")
        proj.focus_distance = lens.number("distance", lo=0, strict_lo=True)
        # Millimetres in the file, as lens makers quote apertures; metres inside, as every length.
        aperture = lens.number("aperture", lo=0, strict_lo=True)
        if aperture > _MAX_APERTURE_MM:
            raise ConfigError(lens.where("aperture"), f"is {aperture:g} mm, wider than any projector lens",
                              "give the lens aperture's diameter in millimetres (a projector's is about 5-30)")
        proj.aperture = aperture / 1000
        lens.done()
    else:
        f.raw("focus", None)
    f.done()
    return proj


def _parse_camera(f: Fields) -> Camera:
    width, height = _resolution(f)
    fx, fy, cx, cy = _intrinsics(f, width, height)
    distortion = ()
    if f.has("distortion"):
        raw = f.raw("distortion")
        n = len(raw) if isinstance(raw, list) else 0
        if n not in (4, 5):
            raise ConfigError(f.where("distortion"), f"must be 4 or 5 numbers (k1, k2, p1, p2[, k3]), got {raw!r}")
        distortion = f.vector("distortion", n)
    noise = f.sub("noise", {})
    cam = Camera(
        width=width, height=height, fx=fx, fy=fy, cx=cx, cy=cy, world_from_cam=parse_pose(f.sub("pose")),
        distortion=distortion,
        channels=f.integer("channels", 1, choices=(1, 3)),
        exposure=f.number("exposure", 1.0, lo=0, strict_lo=True),
        gamma=f.number("gamma", 1.0, lo=0.2, hi=5.0),
        full_well=noise.number("full_well", 0.0, lo=0),
        read_noise=noise.number("read", 0.0, lo=0, hi=0.5),
        bit_depth=f.integer("bit_depth", 8, choices=(8, 16)),
        supersampling=f.integer("supersampling", 2, lo=1),
        frames=f.integer("frames", 1, lo=1, hi=MAX_FRAMES),
    )
    noise.done()
    f.done()
    return cam


# A mesh wider than this (metres, after its scale) is more likely a file in millimetres than an object
# before projectors: warned of, naming the scale that reads millimetres.
MESH_SPAN_WARN = 10.0


def _check_mesh(path: Path, where: str) -> float:
    """A mesh file must hold triangles trimesh can read (the ray caster's loader), checked at load time.
    Returns the mesh's largest extent in the file's units."""
    import trimesh

    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as exc:  # noqa: BLE001 - trimesh's loaders raise many kinds for a file that is not a mesh
        raise ConfigError(where, f"{str(path)!r} is not a mesh file trimesh can read ({type(exc).__name__}: {exc})",
                          "give an OBJ, PLY, STL, OFF or GLB file of triangles") from None
    faces = getattr(mesh, "faces", None)
    if faces is None or len(faces) == 0 or not np.isfinite(np.asarray(mesh.vertices)).all():
        raise ConfigError(where, f"{str(path)!r} holds no triangles (or non-finite vertices)",
                          "give an OBJ, PLY, STL, OFF or GLB file of triangles")
    return float(np.max(mesh.extents))


def _parse_surface(f: Fields, name: str, base_dir: Path) -> Surface:
    kind = f.text("type", choices=SURFACE_TYPES)
    surf = Surface(name=name, type=kind, world_from_local=parse_pose(f.sub("pose")),
                   albedo=f.scalar_or_rgb("albedo", 0.8, lo=0, hi=1),
                   transmittance=f.number("transmittance", 0.0, lo=0, hi=0.99))
    if surf.transmittance > 0 and kind not in ("rectangle", "plane"):
        raise ConfigError(f.where("transmittance"), f"is only supported on screens, not on a {kind}",
                          "make the semi-transparent surface a rectangle")
    if kind == "rectangle":
        surf.size = f.vector("size", 2, lo=0, strict_lo=True)
    elif kind == "box":
        surf.size = f.vector("size", 3, lo=0, strict_lo=True)
    elif kind == "cylinder":
        surf.radius = f.number("radius", lo=0, strict_lo=True)
        surf.height = f.number("height", lo=0, strict_lo=True)
    elif kind == "sphere":
        radius = f.raw("radius")
        if isinstance(radius, list):
            surf.radii = f.vector("radius", 3, lo=0, strict_lo=True)
        else:
            surf.radii = (f.number("radius", lo=0, strict_lo=True),) * 3
    elif kind == "mesh":
        path = Path(f.text("file"))
        if not path.is_absolute():
            path = base_dir / path
        if not path.is_file():
            raise ConfigError(f.where("file"), f"mesh file {str(path)!r} not found",
                              "paths are relative to the config file's folder")
        extent = _check_mesh(path, f.where("file"))
        surf.mesh_file = path
        surf.scale = f.number("scale", 1.0, lo=0, strict_lo=True)
        if extent * surf.scale > MESH_SPAN_WARN:
            warnings.warn(f"{f.where('file')}: the mesh spans {extent * surf.scale:.4g} m at scale {surf.scale:g}, and "
                          "scenes are in metres: if the file is in millimetres, give the surface scale: 0.001",
                          stacklevel=2)
    f.done()
    return surf


def _check_in_front(scene: Scene) -> None:
    """Every surface must lie in front of the camera, or it can never be calibrated or seen."""
    cam_from_world = np.linalg.inv(scene.camera.world_from_cam)
    for surf in scene.surfaces.values():
        if surf.type == "plane":
            continue
        z = (cam_from_world @ surf.world_from_local[:, 3])[2]
        if z <= 0:
            raise ConfigError(f"surfaces.{surf.name}.pose.position",
                              f"lies behind the camera (z = {z:.3g} m in the camera frame)",
                              "move the surface in front of the camera or turn the camera towards it")


def _surface_names(f: Fields, known, unknown) -> list[str]:
    """``f``'s ``surfaces``: a non-empty list of names from ``known``, each once (a surface listed twice
    was cast twice, its second copy hidden behind the first). ``unknown(name)`` gives the message and
    the fix for a name not in ``known``."""
    members = f.raw("surfaces")
    if not isinstance(members, list) or not members:
        raise ConfigError(f.where("surfaces"), "must be a non-empty list of surface names")
    for i, m in enumerate(members):
        if not isinstance(m, str) or m not in known:
            raise ConfigError(f.where("surfaces"), *unknown(m))
        if m in members[:i]:
            raise ConfigError(f.where("surfaces"), f"names {m!r} twice", "list each surface once")
    return list(members)


def _parse_targets(top: Fields, states: dict[str, State], base_dir: Path) -> list[TargetSpec]:
    raw = top.raw("targets")
    if not isinstance(raw, list) or not raw:
        raise ConfigError("targets", "must be a non-empty list of {name, state, surfaces, image}",
                          "or leave it out: each state is then one target")
    targets = []
    for i, t in enumerate(raw):
        tf = Fields(t, f"targets[{i}]")
        state = tf.text("state", choices=tuple(states))
        surfaces = None
        if tf.has("surfaces"):
            surfaces = _surface_names(tf, states[state].surfaces,
                                      lambda m, state=state: (f"names {m!r}, which is not present in state {state!r}",
                                                              f"choose from {states[state].surfaces}"))
        image = tf.text("image") if tf.has("image") else None
        if image is not None and not image.strip():
            raise ConfigError(tf.where("image"), "is empty", "give an image file or a scikit-image name such as "
                                                             "astronaut, or leave image out for the default")
        if image is not None and Path(image).suffix:
            path = Path(image) if Path(image).is_absolute() else base_dir / image
            if not path.is_file():
                raise ConfigError(tf.where("image"), f"image file {str(path)!r} not found",
                                  "paths are relative to the config file's folder; a name without a suffix "
                                  "is a scikit-image test image")
            image = str(path)
        targets.append(TargetSpec(name=tf.name("name", f"target{i}"), state=state,
                                  surfaces=None if surfaces is None else list(surfaces), image=image))
        tf.done()
    _unique_names("targets", [t.name for t in targets])
    # One surface shows one image at a time: two targets on it in one state ask its pixels for two
    # images, and the solve could only split the difference (a run gave both 14 dB, crosstalk 0.74).
    shown: dict[tuple[str, str], int] = {}
    for i, t in enumerate(targets):
        for m in dict.fromkeys(states[t.state].surfaces if t.surfaces is None else t.surfaces):
            k = shown.setdefault((t.state, m), i)
            if k != i:
                where = f"targets[{i}]" + (".surfaces" if t.surfaces is not None else "")
                raise ConfigError(where, f"puts target {t.name!r} on surface {m!r} in state {t.state!r}, where "
                                         f"targets[{k}] ({targets[k].name!r}) already is: a surface shows one image "
                                         "at a time", "give each target of a state its own surfaces, or put them in "
                                                      "different states")
    return targets


def _unique_names(where: str, names: list[str]) -> None:
    if len(set(names)) != len(names):
        raise ConfigError(where, f"names must be unique, got {names}")


def _unique_file_names(where: str, names: list[str]) -> None:
    """Projectors and states name files of the outputs (``patterns/PROJECTOR.png``, ``captures/STATE.png``):
    unique, and unique ignoring case, which macOS's and Windows' file systems ignore (``a.png`` and
    ``A.png`` are one file there: one pattern would be written over the other without a word)."""
    _unique_names(where, names)
    folded = [n.casefold() for n in names]
    same = sorted({n for n, f in zip(names, folded) if folded.count(f) > 1})
    if same:
        raise ConfigError(where, f"names {same} differ only in case, and name one file of the outputs on macOS and "
                                 "Windows", "give each a name of its own beyond case")


def _interreflection(top: Fields, surfaces: dict[str, Surface]) -> bool:
    """``interreflection``: true simulates one bounce of projector light between the (opaque) surfaces."""
    value = top.raw("interreflection", False)
    if not isinstance(value, bool):
        raise ConfigError(top.where("interreflection"), f"must be true or false, got {value!r}")
    screens = sorted(name for name, s in surfaces.items() if s.transmittance > 0)
    if value and screens:
        raise ConfigError(top.where("interreflection"), f"is simulated between opaque surfaces, and {screens} pass "
                                                        "light on (transmittance)", "drop one or the other")
    return value


def parse_scene(data: Any, base_dir: str | os.PathLike = ".", name: str = "scene",
                size_limit: float = SIZE_LIMIT) -> Scene:
    """Validate a scene mapping (as loaded from YAML) into a :class:`Scene`.

    ``size_limit``: the most camera rays per state (pixels x supersampling^2) and cells per projector
    accepted (:data:`SIZE_LIMIT`).
    """
    check_path(base_dir, "base_dir", "the folder a config's relative file names are read from")
    base_dir = Path(base_dir)
    top = Fields(data, "")
    projectors_raw = top.raw("projectors")
    if not isinstance(projectors_raw, list) or not projectors_raw:
        raise ConfigError("projectors", "must be a non-empty list of projectors")
    camera = _parse_camera(top.sub("camera"))
    projectors = [_parse_projector(Fields(p, f"projectors[{i}]"), i, camera.channels)
                  for i, p in enumerate(projectors_raw)]
    _unique_file_names("projectors", [p.name for p in projectors])
    surfaces_f = top.sub("surfaces")
    surfaces = {}
    for key in surfaces_f.data:
        surfaces[str(key)] = _parse_surface(surfaces_f.sub(key), str(key), base_dir)
    if not surfaces:
        raise ConfigError("surfaces", "is empty", "describe at least one surface")
    states_raw = top.raw("states")
    if not isinstance(states_raw, list) or not states_raw:
        raise ConfigError("states", "must be a non-empty list of {name, surfaces}")
    states = []
    for i, s in enumerate(states_raw):
        sf = Fields(s, f"states[{i}]")
        members = _surface_names(sf, surfaces, lambda m: (f"names unknown surface {m!r}", f"known: {sorted(surfaces)}"))
        states.append(State(name=sf.name("name", f"state{i}"), surfaces=members))
        sf.done()
    _unique_file_names("states", [s.name for s in states])
    targets = _parse_targets(top, {s.name: s for s in states}, base_dir) if top.has("targets") else []
    show = parse_show(top.sub("show"), projectors) if top.has("show") else top.raw("show", None)
    scene = Scene(
        name=top.text("name", name), projectors=projectors, camera=camera, surfaces=surfaces, states=states,
        ambient=top.number("ambient", 0.0, lo=0), seed=top.integer("seed", 0, lo=0, hi=2**63 - 1), targets=targets,
        show=show,
        interreflection=_interreflection(top, surfaces),
    )
    top.done()
    _check_in_front(scene)
    _check_size(scene, size_limit)
    return scene


def _check_size(scene: Scene, limit: float) -> None:
    """Refuse, before any work, a rig whose ray casting or patterns would not fit in time or memory."""
    fix = "or raise the limit: --size-limit N, or load_scene(size_limit=N)"
    # A NaN limit would compare false everywhere and silently switch the check off.
    if not (is_number(limit) and 0 < limit < float("inf")):
        raise ConfigError("size_limit", f"must be a finite number above 0, got {limit!r}", "e.g. --size-limit 1e9")
    cam = scene.camera
    rays = cam.width * cam.height * cam.supersampling ** 2
    if rays > limit:
        raise ConfigError("camera", f"{cam.width}x{cam.height} pixels x {cam.supersampling}x{cam.supersampling} "
                                    f"samples = {rays:.3g} rays per state, above the limit of {limit:.3g} (the "
                                    "default scene casts 1.7e7; time and memory grow with it)",
                          f"lower camera.resolution or camera.supersampling, {fix}")
    for i, proj in enumerate(scene.projectors):
        if proj.width * proj.height > limit:
            raise ConfigError(f"projectors[{i}].resolution", f"{proj.width}x{proj.height} = "
                              f"{proj.width * proj.height:.3g} cells, above the limit of {limit:.3g}",
                              f"lower the resolution, {fix}")


def builtin_config(name: str = "paper_two_planes") -> Path:
    """Path of a config shipped with torchproj (by file stem; :data:`BUILTIN_SCENES`)."""
    path = config_dir() / f"{name}.yaml"
    if not path.is_file():
        raise ConfigError("scene", f"no built-in scene named {name!r}", f"choose from {list(BUILTIN_SCENES)}")
    return path


def scale_config(data: dict, scale: float | None = None, *, camera: tuple[int, int] | None = None,
                 projector: tuple[int, int] | None = None) -> dict:
    """A scene's YAML data with its camera and projectors at another resolution, the rig unchanged.

    Focal lengths and principal points scale with the width and height, so fields of view, lens
    shifts, poses and surfaces stay those of the original: the same rig seen with fewer pixels
    (for quick runs, tests and benchmarks at several sizes).

    Args:
        data: the YAML data (not modified).
        scale: factor for every device's resolution (rounded to whole pixels, at least 8).
        camera, projector: ``(width, height)`` to give the camera or every projector instead.
    """
    if scale is not None and not (is_number(scale) and 0 < scale <= 4):
        raise ConfigError("scale", f"must be a number in (0, 4], got {scale!r}")
    check(isinstance(data, dict), f"data must be a scene's YAML data (a dict, as yaml.safe_load reads a config), "
                                  f"got {type(data).__name__}")
    camera, projector = (None if size is None else check_pair(size, name, "(width, height) in pixels", 1)
                         for name, size in (("camera", camera), ("projector", projector)))
    data = copy.deepcopy(data)
    projectors = data.get("projectors") if isinstance(data.get("projectors"), list) else []
    devices = [("camera", data.get("camera"), camera)] + [(f"projectors[{i}]", p, projector)
                                                          for i, p in enumerate(projectors)]
    for where, device, size in devices:
        if not isinstance(device, dict) or "resolution" not in device:
            continue  # parse_scene reports what is missing
        w0, h0 = _resolution(Fields(device, where))
        w, h = size if size is not None else (w0, h0) if scale is None else (max(8, round(w0 * scale)),
                                                                               max(8, round(h0 * scale)))
        sx, sy = w / w0, h / h0
        focal = device.get("focal")
        device["focal"] = [focal[0] * sx, focal[1] * sy] if isinstance(focal, list) else focal * sx
        if "principal_point" in device:  # pixel centres at integers: the centre of a pixel scales about -0.5
            cx, cy = device["principal_point"]
            device["principal_point"] = [(cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5]
        device["resolution"] = [w, h]
    return data


# A scene config is a few kilobytes and names each value once; past these it is not one (or it is an
# alias bomb, whose expansion takes minutes and gigabytes before any field is read).
MAX_CONFIG_BYTES = 10_000_000
MAX_YAML_ALIASES = 100


# Collections open and close in the token stream; a config nested deeper than any scene needs is
# refused before PyYAML's composer, which recurses per level, overflows Python's stack.
_OPENING = (yaml.BlockMappingStartToken, yaml.BlockSequenceStartToken, yaml.FlowMappingStartToken,
            yaml.FlowSequenceStartToken)
_CLOSING = (yaml.BlockEndToken, yaml.FlowMappingEndToken, yaml.FlowSequenceEndToken)
MAX_YAML_DEPTH = 64
# PyYAML's bindings to libyaml where it was built with them (its wheels are): the same safe loader's
# data, read 12x faster than in Python (9 ms of every load_scene of the default scene before).
_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _read_yaml(path: Path):
    """A config file's YAML data, or a :class:`ConfigError` naming the file and what is wrong with it."""
    if path.stat().st_size > MAX_CONFIG_BYTES:
        raise ConfigError(str(path), f"is {path.stat().st_size / 1e6:.0f} MB, larger than any scene config",
                          "check that this is the scene's YAML file")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(str(path), f"is not UTF-8 text (byte {exc.start}: {exc.object[exc.start:exc.start + 1]!r})",
                          "save it as UTF-8") from None
    try:
        aliases = depth = deepest = 0
        for token in yaml.scan(text, Loader=_LOADER):  # the scanner is a loop; the composer after it recurses per level
            aliases += isinstance(token, yaml.AliasToken)
            if isinstance(token, _OPENING):
                depth += 1
                deepest = max(deepest, depth)
            elif isinstance(token, _CLOSING):
                depth -= 1
        if aliases > MAX_YAML_ALIASES:
            raise ConfigError(str(path), f"uses {aliases} YAML aliases (*name), over {MAX_YAML_ALIASES}",
                              "write the values out: a scene names each once")
        if deepest > MAX_YAML_DEPTH:
            raise ConfigError(str(path), f"nests lists and mappings {deepest} deep, over {MAX_YAML_DEPTH}",
                              "a scene config is a few levels deep: check the brackets")
        return yaml.load(text, Loader=_LOADER)
    except yaml.YAMLError as exc:
        raise ConfigError(str(path), f"is not valid YAML: {exc}") from None
    except ConfigError:
        raise  # the limits above, already worded
    except ValueError as exc:  # an integer past Python's digit limit
        raise ConfigError(str(path), f"holds a value YAML cannot read: {str(exc).splitlines()[0]}") from None


def check_scene(scene, name: str = "scene") -> Scene:
    """``scene`` a :class:`Scene`: a name or a path in its place is pointed to :func:`load_scene`."""
    if not isinstance(scene, Scene):
        how = (f"load it with torchproj.load_scene({str(scene)!r})" if isinstance(scene, (str, os.PathLike))
               else "load one with torchproj.load_scene")
        raise InputError(f"{name} must be a Scene, got {type(scene).__name__}: {how}")
    return scene


def load_scene(path: str | os.PathLike | None = None, scale: float | None = None,
               size_limit: float = SIZE_LIMIT) -> Scene:
    """Load a scene YAML file, or a built-in scene by name (None: the paper's two-plane rig).

    Args:
        path: a YAML file, a name of :data:`BUILTIN_SCENES`, or a procedural scene's name
            (``suite-SEED-INDEX``, ``suite-SEED-INDEX-full``: :mod:`torchproj.scene.procedural`).
        scale: give every camera and projector ``scale`` times the resolution (:func:`scale_config`):
            ``load_scene("paper_two_planes", scale=0.25)`` is the paper's rig with 256x192
            projectors and a 400x300 camera, a quick stand-in for the full one.
        size_limit: see :func:`parse_scene`.
    """
    if path is None:
        path = builtin_config()
    if not isinstance(path, (str, os.PathLike)):
        raise ConfigError("config", f"must be a YAML file's path or a scene's name, got {type(path).__name__}",
                          f"give a path, a built-in name ({list(BUILTIN_SCENES)}) or suite-SEED-INDEX")
    from .procedural import parse_suite_name, procedural_config  # here: the generator builds on this module

    suite = parse_suite_name(path) if isinstance(path, str) else None
    if suite is not None and not Path(path).is_file():
        data = procedural_config(*suite)
        if scale is not None:
            data = scale_config(data, scale)
        return parse_scene(data, name=data["name"], size_limit=size_limit)
    path = Path(path)
    if not path.is_file() and path.suffix == "" and path.name in BUILTIN_SCENES:
        path = builtin_config(path.name)
    if path.is_dir():
        raise ConfigError("config", f"{str(path)!r} is a folder", "give the scene's YAML file")
    if path.exists() and not path.is_file():
        raise ConfigError("config", f"{str(path)!r} is not a regular file (a device or a pipe)", "give a YAML file")
    if not path.is_file():
        raise ConfigError("config", f"file {str(path)!r} not found",
                          f"give a YAML path, a built-in name ({list(BUILTIN_SCENES)}) or a procedural scene's "
                          "name (suite-SEED-INDEX)")
    data = _read_yaml(path)
    if scale is not None and isinstance(data, dict):
        data = scale_config(data, scale)
    scene = parse_scene(data, base_dir=path.parent, name=path.stem, size_limit=size_limit)
    scene.source = path
    return scene
