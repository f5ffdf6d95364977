"""The Mitsuba 3 scene source: an XML scene and its receivers file → :class:`Scene`.

Mitsuba's own parser reads the XML (includes, ``<default>``, ``<ref>``, ``<path>``,
transforms, spectra), in its ``scalar_rgb`` variant; this module turns what it built into
warpis's arrays and hands them to the same gate as every other source (``_assemble``):

* shapes: every triangle mesh (obj, ply, serialized, cube, ...) as Mitsuba holds it,
  already in world space; ``rectangle`` as its two triangles; ``sphere``, ``disk`` and
  ``cylinder`` tessellated (``SPHERE_SUBDIVISIONS``, ``DISK_SEGMENTS``,
  ``CYLINDER_SEGMENTS``) with their vertices pushed out so that each tessellation keeps
  the analytic area.  Each triangle winds counter-clockwise around the side Mitsuba calls
  the front (its shading normal, after ``flip_normals``): the side an area light emits
  on and a one-sided BSDF reflects on;
* emitters: ``area`` emitters with a uniform radiance, one-sided;
* colour: warpis is monochrome, so radiance and diffuse reflectance become one channel
  (``CHANNELS``: r, g, b, or the luminance y of linear sRGB); a conductor keeps its three
  channels of ``eta`` and ``k``, and ``specular`` holds each channel's weight (see
  :mod:`warpis.kernels.shading`);
* BSDFs: ``diffuse`` → lambert, ``roughconductor`` → roughconductor, ``roughplastic`` →
  roughplastic, each alone or inside ``twosided``; a receiver takes the BSDF of the
  shape it lies on.  A shape with any other BSDF is an occluder only: it blocks shadow
  rays, as every shape does in Mitsuba's ``direct`` integrator (its ``ray_test`` reads no
  BSDF: glass, a ``null`` BSDF and a ``mask`` of any opacity block alike), and a receiver
  on it is an error, raised only then; a camera pixel that sees it is masked.  A texture
  on a receiver's reflectance (or a roughconductor's alpha) is evaluated by Mitsuba at
  the receiver's own surface point (``_texture_values``), a constant per receiver;
* receivers: a TOML file beside the XML (``<stem>.receivers.toml``; README.md,
  "Mitsuba scenes") lists points on the scene's surfaces, or grids over planar shapes,
  and where the viewer is (default: the XML's first sensor).

Anything warpis cannot represent exactly as Mitsuba means it is refused with a one-line
:class:`~warpis.errors.WarpisError` naming the file, the element and what is supported.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from ..analysis.closed_form import triangle_irradiance
from ..errors import WarpisError, fail
from ..kernels.integrand import MATERIALS
from ..kernels.shading import DISTRIBUTIONS
from .camera import SURFACE_FIELDS, Camera, camera_receiver_fields, cast_camera, image_side
from .delta import DeltaLights
from .environment import Environment
from .normals import interpolate_normals
from .description import (MICROFACET_DEFAULTS, MIN_ALPHA, Receivers, Scene, _assemble, _coordinates, _receiver_count,
                          _unit)
from .toml_source import _check_keys, _require, _vector, _vectors, read_toml

__all__ = ["CHANNELS", "check_channel", "load_mitsuba", "receivers_path"]

# Weights of linear sRGB's channels in warpis's one channel.  y is the luminance with the
# weights Mitsuba itself uses (mi.luminance).
CHANNELS: dict[str, tuple[float, float, float]] = {
    "r": (1.0, 0.0, 0.0),
    "g": (0.0, 1.0, 0.0),
    "b": (0.0, 0.0, 1.0),
    "y": (0.212671, 0.715160, 0.072169),
}
_CHANNEL_WORDS = {
    "r": "the red channel of linear sRGB",
    "g": "the green channel of linear sRGB",
    "b": "the blue channel of linear sRGB",
    "y": "luminance of linear sRGB, 0.212671 R + 0.715160 G + 0.072169 B",
}
DEFAULT_CHANNEL = "y"

# Tessellation of Mitsuba's analytic shapes, the coarsest for which an emitter's area and
# the irradiance it casts at a unit distance stay within TESSELLATION_ERROR of the
# analytic shape's (each load reports its own figures in Scene.notes):
# an icosphere of 20·4^3 = 1280 triangles, a fan of 64 triangles, a tube of 2 × 128.
SPHERE_SUBDIVISIONS = 3
DISK_SEGMENTS = 64
CYLINDER_SEGMENTS = 128
TESSELLATION_ERROR = 1e-3

# A receiver lies on a triangle when it is within this fraction of the scene's bounding
# box diagonal (float32 vertices, numbers written with a few digits), plus how far an
# analytic shape's tessellation strays from it.
ON_SURFACE = 1e-5

# Eta below which a conductor's Fresnel term is 1 to float32's precision: Mitsuba's
# material "none" (eta = 0, k = 1, a perfect mirror) becomes eta = NONE_ETA, whose
# Fresnel term is within 2e-6 of 1 at every angle.
NONE_ETA = 1e-6

SUPPORTED_SHAPES = "triangle meshes (obj, ply, serialized, cube, ...), rectangle, sphere, disk and cylinder"
SUPPORTED_BSDFS = ("diffuse, roughconductor and roughplastic (uniform or textured reflectances, and a uniform or "
                   "textured roughconductor alpha), alone or inside twosided (the same BSDF on both sides), on a "
                   "shape that holds receivers (a shape without receivers may have any BSDF: it only blocks light, "
                   "as in Mitsuba's direct integrator)")
SUPPORTED_EMITTERS = ("area emitters (an <emitter type=\"area\"> inside a <shape>) with uniform radiance, an envmap "
                      "(a rotation as its to_world), a constant emitter of uniform radiance, and point, spot and "
                      "directional lights")
_ENVIRONMENTS = {"EnvironmentMapEmitter", "ConstantBackgroundEmitter"}
_DELTA = {"PointLight": "point", "SpotLight": "spot", "DirectionalEmitter": "directional"}

_SHAPE_PLUGINS = {"OBJMesh": "obj", "PLYMesh": "ply", "SerializedMesh": "serialized", "Cube": "cube",
                  "Rectangle": "rectangle", "Sphere": "sphere", "Disk": "disk", "Cylinder": "cylinder",
                  "Instance": "instance", "ShapeGroup": "shapegroup", "BSplineCurve": "bsplinecurve",
                  "LinearCurve": "linearcurve", "SDFGrid": "sdfgrid", "Ellipsoids": "ellipsoids",
                  "EllipsoidsMesh": "ellipsoidsmesh", "Mesh": "mesh"}
_BSDF_PLUGINS = {"SmoothDiffuse": "diffuse", "RoughConductor": "roughconductor", "RoughPlastic": "roughplastic",
                 "TwoSided": "twosided", "TwoSidedBRDF": "twosided", "SmoothDielectric": "dielectric",
                 "ThinDielectric": "thindielectric", "RoughDielectric": "roughdielectric",
                 "SmoothConductor": "conductor", "SmoothPlastic": "plastic", "BlendBSDF": "blendbsdf",
                 "MaskBSDF": "mask", "Mask": "mask", "BumpMap": "bumpmap", "NormalMap": "normalmap", "Principled": "principled",
                 "PrincipledThin": "principledthin", "Null": "null", "Hair": "hair", "PolarizedPlastic": "pplastic",
                 "LinearPolarizer": "polarizer", "LinearRetarder": "retarder", "Measured": "measured",
                 "MeasuredPolarized": "measured_polarized"}
_EMITTER_PLUGINS = {"PointLight": "point", "SpotLight": "spot", "ConstantBackgroundEmitter": "constant",
                    "EnvironmentMapEmitter": "envmap", "DirectionalEmitter": "directional", "Projector": "projector",
                    "DirectionalArea": "directionalarea", "SunskyEmitter": "sunsky", "AreaLight": "area"}
_TEXTURE_PLUGINS = {"BitmapTexture": "bitmap", "Checkerboard": "checkerboard", "MeshAttribute": "mesh_attribute",
                    "VolumeTexture": "volume"}
# Mitsuba's spectra that are one value over the whole surface (in scalar_rgb).
_UNIFORM = {"UniformSpectrum", "SRGBReflectanceSpectrum", "SRGBEmitterSpectrum", "SRGBSpectrum"}
# Sensors whose rays start at their position, and the one whose rays are parallel.
_POINT_SENSORS = {"PerspectiveCamera", "ThinLensCamera", "RadianceMeter", "BatchSensor"}
_PARALLEL_SENSORS = {"OrthographicCamera"}


def receivers_path(file: Path) -> Path:
    """The default receivers file of the Mitsuba scene ``file``: ``<stem>.receivers.toml`` beside it."""
    return file.with_name(file.stem + ".receivers.toml")


def check_channel(channel: Any, where: object) -> str:
    """``channel`` if it names one of ``CHANNELS``, else a one-line error."""
    if not isinstance(channel, str) or channel not in CHANNELS:
        raise fail(where, f"channel {channel!r}: expected one of {', '.join(CHANNELS)} (r, g, b of linear sRGB, "
                          f"or y, its luminance)")
    return channel


def load_mitsuba(file: Path, device: str = "cpu", channel: str | None = None, receivers: Path | None = None,
                 camera: bool = False, width: int | None = None, height: int | None = None) -> Scene:
    """The scene of the Mitsuba 3 XML file ``file`` (README.md, "Mitsuba scenes").

    Parameters
    ----------
    file
        A Mitsuba 3 scene (``<scene version="3...">``).
    device
        Warp device of the scene's kernels.
    channel
        ``"r"``, ``"g"``, ``"b"`` or ``"y"`` (luminance): the colour channel warpis
        computes; None takes the receivers file's ``channel``, else ``"y"``.
    receivers
        The receivers file; None: ``<stem>.receivers.toml`` beside ``file``.
    camera, width, height
        With ``camera``, the receivers are the pixels of the file's first sensor (a
        ``perspective`` one; ``width``/``height`` override its film size, keeping its
        horizontal field of view) and the receivers file is optional (its name,
        description and channel are still read; its receivers are not).

    Raises
    ------
    WarpisError
        One line naming the file (and the element) for anything that cannot be loaded
        as Mitsuba means it: a missing package or file, an unsupported shape, emitter or
        BSDF, a receiver on no surface, ...
    """
    file = Path(file)
    if channel is not None:
        check_channel(channel, file)
    if not file.is_file():
        raise fail(file, "no such Mitsuba scene file")
    sidecar = receivers_path(file) if receivers is None else Path(receivers)
    if camera and (width is not None or height is not None):
        for what, side_px in (("width", width), ("height", height)):
            if side_px is not None:
                image_side(side_px, what, file)
    elif width is not None or height is not None:
        raise fail(file, "width and height resize the camera of an image; this load has no camera")
    side = _read_sidecar(sidecar, file, receivers_needed=not camera)
    channel = channel if channel is not None else side["channel"] or DEFAULT_CHANNEL
    weights = np.array(CHANNELS[channel])
    with _Mitsuba(file) as session:
        scene = session.load()
        environment = _environment(session.mi, scene, file, weights)
        delta_emitters = [e for e in scene.emitters() if e.class_name() in _DELTA]
        shapes = _shapes(session, scene, file, weights, lit=environment is not None or bool(delta_emitters))
        sensor = _sensor(session.mi, scene)
        lens = _camera(session.mi, scene, file, width, height) if camera else None
        notes = [f"colour channel {channel}: {_CHANNEL_WORDS[channel]}"]
        notes += session.warnings()
    label = {i: s.label for i, s in enumerate(shapes)}
    vertices, triangles, emission, owner = _concatenate(shapes)
    if lens is not None:
        rx, receiver_notes, under = _camera_receivers(lens, shapes, vertices, triangles, emission, owner, file,
                                                      str(device), scene)
    else:
        rx, receiver_notes, under = _receivers(side, shapes, vertices, triangles, owner, sensor, file, sidecar, scene)
    delta = None
    if delta_emitters:
        with session:
            delta = _delta_lights(session.mi, delta_emitters, rx.positions, file, weights)
    coloured_light = (any(s.radiance is not None and not _grey(s.radiance) for s in shapes)
                      or (environment is not None and not environment.grey) or (delta is not None and not delta.grey))
    if channel == "y" and coloured_light and any(not shapes[k].material.grey for k in under):
        notes.append("channel y multiplies the luminance of the emission by the luminance of the BSDF: with "
                     "coloured light on coloured receivers this differs from the luminance of Mitsuba's RGB result, "
                     "which is the same luminance of warpis's channels r, g and b (each matches Mitsuba's)")
    for s in shapes:
        notes += s.notes
    if environment is not None:
        notes += environment.notes
    if delta is not None:
        notes += _delta_notes(delta)
    notes += receiver_notes
    name = side["name"] or (file.parent.name if file.name == "scene.xml" else file.stem)
    hint = (f"give some <shape> an <emitter type=\"area\">, or the scene an envmap or constant emitter, with a "
            f"radiance > 0 in channel {channel}")
    return _assemble(file, lambda m: f"{file}: shape {label[m]!r}", hint, name=name, vertices=vertices,
                     triangles=triangles, emission=emission, receivers=rx, triangle_mesh=owner,
                     mesh_names=[s.label for s in shapes], description=side["description"], device=str(device),
                     path=file, notes=tuple(notes), environment=environment, delta_lights=delta)


# ----------------------------------------------------------------------------- Mitsuba


_SOURCE_PREFIX = re.compile(r"\[[\w.]+\.(?:cpp|h|py):\d+\]\s*")
_LOG_PREFIX = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\s+[A-Z]+\s+")


def _first_line(message: str) -> str:
    """The line of a Mitsuba message that says what went wrong: source locations
    stripped, a list under a header joined to it, context lines skipped."""
    lines: list[str] = []
    for raw in str(message).splitlines():
        line = _SOURCE_PREFIX.sub("", raw).strip()
        if not line:
            continue
        if line.startswith("- ") and lines:
            head = lines[-1]
            lines[-1] = head + (" " if head.endswith(":") else ", ") + line[2:]
        else:
            lines.append(line)
    for line in lines:
        if not line.endswith(":"):
            return line
    return lines[-1] if lines else "unknown error"


class _Mitsuba:
    """Mitsuba in its scalar_rgb variant with its log captured while warpis reads a
    scene; the caller's variant, log level and log appenders come back afterwards."""

    def __init__(self, file: Path):
        self.file = file
        try:
            import mitsuba
        except ImportError:
            raise fail(file, 'Mitsuba scenes need the optional mitsuba package: pip install "warpis[mitsuba]"') from None
        except OSError as exc:  # installed, but its libraries cannot load
            raise fail(file, f"Mitsuba cannot start: {exc}") from None
        self.mi = mitsuba
        self.log: list[tuple[Any, str]] = []

    def __enter__(self) -> _Mitsuba:
        mi = self.mi
        self.variant = mi.variant()
        try:
            mi.set_variant("scalar_rgb")
        except Exception as exc:  # a build without the variant
            raise fail(self.file, f"Mitsuba cannot run its scalar_rgb variant: {_first_line(str(exc))}") from None
        logger = mi.logger()
        self.level = logger.log_level()
        self.appenders = [logger.appender(i) for i in range(logger.appender_count())]
        log = self.log

        class Capture(mi.Appender):
            def append(self, level: Any, text: str) -> None:
                log.append((level, text))

            def log_progress(self, *args: Any) -> None:
                pass

        self.capture = Capture()
        logger.clear_appenders()
        logger.add_appender(self.capture)
        logger.set_log_level(mi.LogLevel.Warn)
        return self

    def __exit__(self, *exc: Any) -> None:
        mi = self.mi
        logger = mi.logger()
        logger.clear_appenders()
        for appender in self.appenders:
            logger.add_appender(appender)
        logger.set_log_level(self.level)
        if self.variant is not None and self.variant != "scalar_rgb":
            mi.set_variant(self.variant)

    def load(self) -> Any:
        """The scene, its shapes in the file's order and each one separate: Mitsuba's
        optimisations would merge meshes that share a BSDF and load them in any order."""
        mi = self.mi
        try:
            scene = mi.load_file(str(self.file), parallel=False, optimize=False)
        except Exception as exc:
            raise fail(self.file, f"Mitsuba cannot load it: {_first_line(str(exc))}") from None
        if not isinstance(scene, mi.Scene):
            raise fail(self.file, f"Mitsuba loads a {type(scene).__name__}, not a <scene>")
        return scene

    def warnings(self) -> list[str]:
        """Mitsuba's warnings while loading, as notes."""
        out = []
        for _, text in self.log:
            line = _first_line(_LOG_PREFIX.sub("", text))
            out.append(f"Mitsuba: {line}")
        return out


def _params(mi: Any, obj: Any) -> dict[str, Any]:
    """The parameters Mitsuba exposes for ``obj`` (mi.traverse), by key."""
    traversed = mi.traverse(obj)
    return {key: traversed[key] for key in traversed.keys()}


def _matrix(transform: Any) -> np.ndarray:
    return np.array(transform.matrix, dtype=np.float64).reshape(4, 4)


def _fields(text: str) -> tuple[str, dict[str, str]]:
    """Mitsuba's description of an object, ``Class[ key = value, ... ]`` → its class
    and the text of each top-level value."""
    name = re.match(r"\s*(\w*)", text).group(1)
    start = text.find("[")
    if start < 0:
        return name, {}
    depth, end = 0, len(text)
    for i in range(start, len(text)):
        if text[i] == "[":
            depth += 1
        elif text[i] == "]":
            depth -= 1
            if depth == 0:
                end = i
                break
    parts, depth, current = [], 0, []
    for ch in text[start + 1:end]:
        if ch == "[":
            depth += 1
        elif ch == "]":
            depth -= 1
        if ch == "," and depth == 0:
            parts.append("".join(current))
            current = []
        else:
            current.append(ch)
    parts.append("".join(current))
    out = {}
    for part in parts:
        key, eq, value = part.partition("=")
        if eq:
            out[key.strip()] = value.strip()
    return name, out


def _rgb(value: Any) -> np.ndarray:
    """A Mitsuba colour or float → (3,) float64."""
    a = np.array(value, dtype=np.float64).reshape(-1)
    return np.repeat(a, 3) if a.size == 1 else a[:3].copy()


# ----------------------------------------------------------------------------- materials


@dataclass
class _Material:
    """A receiver's material in warpis's terms, as read from one Mitsuba BSDF."""

    kind: str  # MATERIALS name
    text: str  # how it reads in notes
    albedo: float = 0.0
    alpha: float = MICROFACET_DEFAULTS["alpha"]
    distribution: int = MICROFACET_DEFAULTS["distribution"]
    sample_visible: int = MICROFACET_DEFAULTS["sample_visible"]
    eta: np.ndarray = field(default_factory=lambda: np.full(3, MICROFACET_DEFAULTS["eta"]))
    k: np.ndarray = field(default_factory=lambda: np.full(3, MICROFACET_DEFAULTS["k"]))
    specular: np.ndarray = field(default_factory=lambda: np.full(3, MICROFACET_DEFAULTS["specular"] / 3))
    specular_weight: float = MICROFACET_DEFAULTS["specular_weight"]
    twosided: bool = False
    grey: bool = True  # the same in every colour channel
    # A BSDF warpis cannot shade: the one-line error a receiver on it raises, and the
    # BSDF's name; "" for one it shades.  Such a shape is an occluder only.
    problem: str = ""
    unshaded: str = ""
    # Parameters given by a texture, evaluated at each receiver: "albedo", "specular" or
    # "alpha" → the Mitsuba Texture objects it comes from (alpha: alpha_u and alpha_v, or
    # alpha), and how each reads in notes.  The field itself holds NaN until then.
    textures: dict[str, tuple[Any, ...]] = field(default_factory=dict)
    texture_text: dict[str, str] = field(default_factory=dict)
    weights: Any = None  # the channel's weights, for textured colours

    def same(self, other: _Material) -> bool:
        """The same material (a textured parameter: the same texture)."""
        def equal(a: Any, b: Any) -> bool:
            return bool(np.array_equal(a, b, equal_nan=True))
        return (self.kind == other.kind and equal(self.albedo, other.albedo) and equal(self.alpha, other.alpha)
                and self.distribution == other.distribution and self.sample_visible == other.sample_visible
                and equal(self.eta, other.eta) and equal(self.k, other.k) and equal(self.specular, other.specular)
                and self.specular_weight == other.specular_weight and self.texture_text == other.texture_text)

    def check(self, where: str) -> None:
        """The kernels' domain for this material's parameters (textured ones: see _texture_values)."""
        if (self.kind in ("roughconductor", "roughplastic") and "alpha" not in self.textures
                and not MIN_ALPHA <= self.alpha <= 1e3):
            raise fail(where, f"{self.kind} alpha={self.alpha:g}: warpis supports roughness in [{MIN_ALPHA:g}, 1000]")
        if not (np.all(self.eta > 0) and np.all(self.eta <= 1e3) and np.all(self.k >= 0) and np.all(self.k <= 1e3)):
            raise fail(where, f"{self.kind} eta={_triple(self.eta)} k={_triple(self.k)}: warpis supports eta in "
                              f"(0, 1000] and k in [0, 1000]")
        specular_ok = "specular" in self.textures or (np.all(self.specular >= 0) and np.all(self.specular <= 1e3))
        if not (specular_ok and ("albedo" in self.textures or 0 <= self.albedo <= 1e3)):
            raise fail(where, f"{self.kind}: reflectances must lie in [0, 1000] in every channel")


def _grey(rgb: np.ndarray) -> bool:
    return bool(np.all(rgb == rgb[0]))


def _triple(a: np.ndarray) -> str:
    return "(" + ", ".join(f"{x:.6g}" for x in a) + ")" if not np.all(a == a[0]) else f"{a[0]:.6g}"


def _texture_name(text: str) -> str:
    cls = text.split("[")[0].strip()
    return _TEXTURE_PLUGINS.get(cls, cls)


def _uniform(fields: dict[str, str], name: str, where: str, plugin: str) -> bool:
    """Whether the parameter ``name`` is given (a uniform value); a texture is an error."""
    text = fields.get(name)
    if text is None:
        return False
    if text.split("[")[0].strip() not in _UNIFORM:
        raise fail(where, f"{plugin}: its {name} is a {_texture_name(text)!r} texture; warpis supports only uniform "
                          f"values")
    return True


def _colour(fields: dict[str, str], params: dict[str, Any], name: str, where: str, plugin: str,
            default: float | None = None) -> np.ndarray:
    """A uniform spectrum parameter of a BSDF or emitter as linear sRGB (3,)."""
    if not _uniform(fields, name, where, plugin):
        if default is not None:
            return np.full(3, default)
        raise fail(where, f"{plugin}: cannot read its {name}")
    value = params.get(f"{name}.value", params.get(name))
    if value is None:
        raise fail(where, f"{plugin}: cannot read its {name}")
    rgb = _rgb(value)
    if not np.all(np.isfinite(rgb)):
        raise fail(where, f"{plugin}: its {name} {rgb.tolist()} is not finite")
    return rgb


def _scalar(params: dict[str, Any], name: str, where: str, plugin: str) -> float:
    if name not in params:
        raise fail(where, f"{plugin}: cannot read its {name}")
    return float(params[name])


def _microfacet_options(fields: dict[str, str], where: str, plugin: str) -> tuple[int, int]:
    distribution = fields.get("distribution", "")
    if distribution not in DISTRIBUTIONS:
        raise fail(where, f"{plugin}: distribution {distribution!r}; warpis supports {', '.join(DISTRIBUTIONS)}")
    visible = fields.get("sample_visible", "")
    if visible not in ("0", "1"):
        raise fail(where, f"{plugin}: cannot read sample_visible ({visible!r})")
    return DISTRIBUTIONS[distribution], int(visible)


def _options_text(m: _Material) -> str:
    name = next(d for d, code in DISTRIBUTIONS.items() if code == m.distribution)
    alpha = "" if "alpha" in m.textures else f" alpha={m.alpha:.6g}"
    return f"{name}{alpha} ({'visible normals' if m.sample_visible else 'all normals'})"


def _children(mi: Any, obj: Any) -> dict[str, Any]:
    """The Mitsuba objects ``obj`` holds (its textures, nested BSDFs), by parameter name."""
    found: dict[str, Any] = {}

    class Children(mi.TraversalCallback):
        def put(self, name: str, value: Any, flags: Any, *rest: Any) -> None:
            if isinstance(value, mi.Object):
                found[name] = value

    obj.traverse(Children())
    return found


def _textured(fields: dict[str, str], name: str) -> bool:
    """Whether the parameter ``name`` is given by a texture (not a uniform value)."""
    text = fields.get(name)
    return text is not None and text.split("[")[0].strip() not in _UNIFORM


def _texture(fields: dict[str, str], objects: dict[str, Any], name: str) -> Any:
    """The Texture object of the parameter ``name`` if it is not uniform (a texture warpis
    evaluates at each receiver), else None."""
    return objects.get(name) if _textured(fields, name) else None


def _one_bsdf(cls: str, fields: dict[str, str], params: dict[str, Any], where: str, weights: np.ndarray,
              notes: list[str], objects: dict[str, Any] | None = None) -> _Material:
    """One (not twosided) Mitsuba BSDF → a warpis material.  A texture on a reflectance,
    or on a roughconductor's alpha, is kept (``textures``) to be evaluated at each receiver."""
    plugin = _BSDF_PLUGINS.get(cls, cls)
    objects = objects or {}
    if cls == "SmoothDiffuse":
        tex = _texture(fields, objects, "reflectance")
        if tex is not None:
            name = _texture_name(fields["reflectance"])
            return _Material("lambert", f"diffuse reflectance from a {name!r} texture", albedo=math.nan,
                             textures={"albedo": (tex,)}, texture_text={"albedo": fields["reflectance"]},
                             grey=False)  # not known to be grey: channel y's note then applies
        rgb = _colour(fields, params, "reflectance", where, plugin)
        albedo = float(weights @ rgb)
        return _Material("lambert", f"diffuse albedo={albedo:.6g}", albedo=albedo, grey=_grey(rgb))
    if cls == "RoughConductor":
        distribution, visible = _microfacet_options(fields, where, plugin)
        textures: dict[str, tuple[Any, ...]] = {}
        texture_text: dict[str, str] = {}
        if _textured(fields, "alpha_u") or _textured(fields, "alpha_v"):
            keys = ("alpha",) if "alpha" in objects else ("alpha_u", "alpha_v")
            if not all(key in objects for key in keys):
                raise fail(where, f"{plugin}: cannot read its alpha texture")
            textures["alpha"] = tuple(objects[key] for key in keys)
            texture_text["alpha"] = " / ".join(fields.get(n, "") for n in ("alpha_u", "alpha_v"))
            alpha_u = alpha_v = math.nan
        else:
            for name in ("alpha_u", "alpha_v"):
                if not _uniform(fields, name, where, plugin):
                    raise fail(where, f"{plugin}: cannot read its {name}")
            try:
                alpha_u, alpha_v = ((float(params["alpha.value"]),) * 2 if "alpha.value" in params else
                                    (float(params["alpha_u.value"]), float(params["alpha_v.value"])))
            except KeyError:
                raise fail(where, f"{plugin}: cannot read its alpha") from None
        if alpha_u != alpha_v and "alpha" not in textures:
            raise fail(where, f"{plugin}: anisotropic roughness alpha_u={alpha_u:.6g}, alpha_v={alpha_v:.6g}; "
                              f"warpis supports an isotropic alpha only")
        eta = _colour(fields, params, "eta", where, plugin)
        k = _colour(fields, params, "k", where, plugin)
        tex = _texture(fields, objects, "specular_reflectance")
        if tex is not None:
            textures["specular"] = (tex,)
            texture_text["specular"] = fields["specular_reflectance"]
            specular = np.full(3, math.nan)
        else:
            specular = _colour(fields, params, "specular_reflectance", where, plugin, default=1.0)
        if np.any(eta == 0):
            notes.append(f"roughconductor eta=0 (Mitsuba's material \"none\" is eta=0, k=1, a perfect mirror) "
                         f"taken as eta={NONE_ETA:g}: its Fresnel term stays within 2e-6 of Mitsuba's")
            eta = np.where(eta == 0, NONE_ETA, eta)
        m = _Material("roughconductor", "", alpha=alpha_u, distribution=distribution,
                      sample_visible=visible, eta=eta, k=k, specular=weights * specular,
                      grey=_grey(eta) and _grey(k) and _grey(specular) and not textures, textures=textures, texture_text=texture_text)
        m.text = (f"roughconductor {_options_text(m)} eta={_triple(eta)} k={_triple(k)}"
                  + ("" if "specular" in textures or np.all(specular == 1) else
                     f" specular_reflectance={_triple(specular)}")
                  + _textures_text(texture_text, {"alpha": "alpha", "specular": "specular_reflectance"}))
        return m
    if cls == "RoughPlastic":
        distribution, visible = _microfacet_options(fields, where, plugin)
        if fields.get("nonlinear", "0") != "0":
            raise fail(where, f"{plugin}: nonlinear=true; warpis supports the linear roughplastic only")
        alpha = _scalar(params, "alpha", where, plugin)
        eta = _scalar(params, "eta", where, plugin)
        textures, texture_text, means = {}, {}, []
        for field_name, name in (("albedo", "diffuse_reflectance"), ("specular", "specular_reflectance")):
            tex = _texture(fields, objects, name)
            if tex is not None:
                textures[field_name] = (tex,)
                texture_text[field_name] = fields[name]
                means.append(float(tex.mean()))  # Mitsuba's specular_sampling_weight takes the texture's mean
        diffuse = (np.full(3, math.nan) if "albedo" in textures else
                   _colour(fields, params, "diffuse_reflectance", where, plugin))
        specular = (np.full(3, math.nan) if "specular" in textures else
                    _colour(fields, params, "specular_reflectance", where, plugin, default=1.0))
        d_mean = means.pop(0) if "albedo" in textures else float(diffuse.mean())
        s_mean = means.pop(0) if "specular" in textures else float(specular.mean())
        # Mitsuba's specular_sampling_weight: the lobe choice, from the RGB means.
        weight = s_mean / (d_mean + s_mean) if d_mean + s_mean > 0 else 0.5
        m = _Material("roughplastic", "", albedo=float(weights @ diffuse), alpha=alpha, distribution=distribution,
                      sample_visible=visible, eta=np.full(3, eta), k=np.zeros(3), specular=weights * specular,
                      specular_weight=weight, grey=_grey(diffuse) and _grey(specular) and not textures, textures=textures,
                      texture_text=texture_text)
        m.text = (f"roughplastic {_options_text(m)} eta={eta:.6g}"
                  + ("" if "albedo" in textures else f" albedo={m.albedo:.6g}")
                  + ("" if "specular" in textures else f" specular={float(m.specular.sum()):.6g}")
                  + f" specular_weight={weight:.6g}"
                  + _textures_text(texture_text, {"albedo": "diffuse_reflectance", "specular": "specular_reflectance"}))
        return m
    raise fail(where, f"BSDF {plugin!r} is not supported; warpis supports {SUPPORTED_BSDFS}")


def _textures_text(texture_text: dict[str, str], names: dict[str, str]) -> str:
    """How a material's textured parameters read in notes."""
    return "".join(f" {names[f]} from a {_texture_name(_first_texture(t))!r} texture" for f, t in texture_text.items())


def _first_texture(text: str) -> str:
    """The first non-uniform of the ' / '-joined texture descriptions (alpha_u / alpha_v)."""
    for part in text.split(" / "):
        if part.split("[")[0].strip() not in _UNIFORM:
            return part
    return text


def _material(mi: Any, bsdf: Any, where: str, weights: np.ndarray, notes: list[str]) -> _Material:
    """A shape's Mitsuba BSDF → its warpis material; one warpis cannot shade → an
    occluder's placeholder holding the error (``problem``), which a receiver on the
    shape raises (a shape only blocks light in Mitsuba's ``direct``, whatever its BSDF)."""
    kept: list[str] = []
    try:
        material = _shaded_material(mi, bsdf, where, weights, kept)
    except WarpisError as exc:
        cls = bsdf.class_name()
        name = _BSDF_PLUGINS.get(cls, cls)
        return _Material("lambert", f"BSDF {name!r}, which warpis cannot shade: an occluder only (it blocks light, "
                                    f"as any shape does in Mitsuba's direct integrator)", problem=str(exc),
                         unshaded=name)
    notes += kept
    return material


def _shaded_material(mi: Any, bsdf: Any, where: str, weights: np.ndarray, notes: list[str]) -> _Material:
    """A shape's Mitsuba BSDF → its warpis material, or a one-line error."""
    params = _params(mi, bsdf)
    _, fields = _fields(str(bsdf))
    cls = bsdf.class_name()
    objects = _children(mi, bsdf)
    if _BSDF_PLUGINS.get(cls) != "twosided":
        return replace(_one_bsdf(cls, fields, params, where, weights, notes, objects), weights=weights)
    sides = []
    for i in (0, 1):
        side_cls, side_fields = _fields(fields.get(f"brdf[{i}]", ""))
        prefix = f"brdf_{i}." if any(key.startswith(f"brdf_{i}.") for key in params) else "brdf_0."
        side_params = {key[len(prefix):]: value for key, value in params.items() if key.startswith(prefix)}
        side = objects.get(f"brdf_{i}", objects.get("brdf_0"))
        sides.append(_one_bsdf(side_cls, side_fields, side_params, where, weights, notes,
                               _children(mi, side) if side is not None else {}))
        sides[-1].weights = weights
    if not sides[0].same(sides[1]):
        raise fail(where, f"twosided with a different BSDF on each side ({sides[0].text}; {sides[1].text}); warpis "
                          f"supports twosided around one BSDF")
    sides[0].twosided = True
    sides[0].text = "twosided " + sides[0].text
    return sides[0]


# ----------------------------------------------------------------------------- shapes


@dataclass
class _Shape:
    """One Mitsuba shape as triangles: the front of each (counter-clockwise) is Mitsuba's."""

    label: str  # its id, or "<plugin> #<position>" for a shape without one
    plugin: str
    vertices: np.ndarray  # (V, 3) float64, world space
    faces: np.ndarray  # (F, 3) int64
    radiance: np.ndarray | None  # linear sRGB of its area emitter
    emission: float  # radiance in warpis's channel (0: none)
    material: _Material
    deviation: float = 0.0  # how far the triangles stray from Mitsuba's analytic surface
    id: str = ""
    shading: np.ndarray | None = None  # (V, 3) Mitsuba's vertex normals on the front side, for a mesh
    # (P, 3) → (P, 3) Mitsuba's front normal of a curved analytic shape (sphere, cylinder)
    # at points of its tessellation, unnormalised: what Mitsuba shades with there
    analytic_normal: Any = None
    notes: list[str] = field(default_factory=list)


def _shapes(session: _Mitsuba, scene: Any, file: Path, weights: np.ndarray, lit: bool = False) -> list[_Shape]:
    """The scene's shapes; ``lit``: an environment lights the scene, so it needs no area emitter."""
    mi = session.mi
    for emitter in scene.emitters():
        cls = emitter.class_name()
        if cls != "AreaLight" and cls not in _ENVIRONMENTS and cls not in _DELTA:
            name = f"{emitter.id()!r} ({_EMITTER_PLUGINS.get(cls, cls)})" if emitter.id() else \
                repr(_EMITTER_PLUGINS.get(cls, cls))
            raise fail(file, f"emitter {name}: warpis supports {SUPPORTED_EMITTERS}")
    out = []
    for i, shape in enumerate(scene.shapes()):
        cls = shape.class_name()
        plugin = _SHAPE_PLUGINS.get(cls, cls.lower())
        label = shape.id() or f"{plugin} #{i + 1}"
        where = f"{file}: shape {label!r}"
        notes: list[str] = []
        vertices, faces, deviation, shading, analytic_normal = _geometry(mi, shape, cls, where, notes)
        radiance, emission = None, 0.0
        if shape.is_emitter():
            radiance, emission = _radiance(mi, shape.emitter(), where, weights)
        material = _material(mi, shape.bsdf(), where, weights, notes)
        s = _Shape(label=label, plugin=plugin, vertices=vertices, faces=faces, radiance=radiance, emission=emission,
                   material=material, deviation=deviation, id=shape.id(), shading=shading,
                   analytic_normal=analytic_normal)
        if radiance is not None:
            s.notes.append(f"{label}: area emitter, radiance {emission:.6g} (linear sRGB {_triple(radiance)})"
                           + ("; 0 in this channel: it emits nothing here" if emission == 0 else ""))
            if plugin in ("sphere", "disk", "cylinder"):
                s.notes.append(f"{label}: {_tessellation_note(mi, shape, plugin, vertices, faces)}")
        else:
            s.notes.append(f"{label}: {material.text}")
            if plugin in ("sphere", "disk", "cylinder"):
                s.notes.append(f"{label}: {plugin} tessellated into {len(faces)} triangles (pushed out to keep its "
                               f"area)")
        s.notes += [f"{label}: {note}" for note in dict.fromkeys(notes)]
        out.append(s)
    if not lit and not any(s.radiance is not None for s in out):
        raise fail(file, f"the scene has no emitter: warpis needs at least one <shape> with an "
                         f"<emitter type=\"area\">, or an envmap or constant emitter ({SUPPORTED_EMITTERS})")
    return out


def _environment(mi: Any, scene: Any, file: Path, weights: np.ndarray) -> Environment | None:
    """The scene's envmap or constant emitter as warpis's Environment (one at most), its
    table exactly the one Mitsuba looks up (scenes/environment.py)."""
    found = [e for e in scene.emitters() if e.class_name() in _ENVIRONMENTS]
    if not found:
        return None
    emitter = found[0]
    cls = emitter.class_name()
    plugin = _EMITTER_PLUGINS[cls]
    where = f"{file}: emitter {emitter.id()!r} ({plugin})" if emitter.id() else f"{file}: emitter {plugin!r}"
    params = _params(mi, emitter)
    _, fields = _fields(str(emitter))
    if cls == "ConstantBackgroundEmitter":
        rgb = _colour(fields, params, "radiance", where, plugin)
        if np.any(rgb < 0):
            raise fail(where, f"{plugin}: radiance {rgb.tolist()} is negative in some channel")
        texels, rotation, grey = np.full((3, 2), float(weights @ rgb)), np.eye(3), _grey(rgb)
        text = f"constant environment, radiance {float(weights @ rgb):.6g} (linear sRGB {_triple(rgb)})"
    else:
        rgb_texels = _envmap_texels(params, fields, where)
        grey = bool(np.all(rgb_texels == rgb_texels[..., :1]))
        texels = rgb_texels @ weights * float(params["scale"])
        m = _matrix(params["to_world"])
        rotation = m[:3, :3]
        if not np.all(np.isfinite(m)) or not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-5):
            raise fail(where, f"{plugin}: its to_world is not a rotation (it scales or shears; Mitsuba does not "
                              f"normalise a <rotate> axis): warpis supports rotations of the map")
        if np.any(texels < 0) or not np.all(np.isfinite(texels)):
            raise fail(where, f"{plugin}: its radiance must be finite and non-negative in every texel")
        text = f"envmap {fields.get('filename', '<bitmap>').strip(chr(34))}"
    env = Environment(texels=texels, rotation=rotation, kind=plugin, label=where)
    width, height = env.resolution
    note = (f"{text}: {width} × {height} texels, ∫ L dω = {env.power:.6g} over the sphere, its brightest 1% of "
            f"texels carry {100 * env.brightest_share():.3g}% of it")
    return Environment(texels=texels, rotation=rotation, kind=plugin, label=where, notes=(note,), grey=grey)


def _delta_lights(mi: Any, emitters: list[Any], points: np.ndarray, file: Path, weights: np.ndarray) -> DeltaLights:
    """What each point, spot or directional light sends to each receiver, as Mitsuba's own
    ``sample_direction`` says from the receiver's position (intensity, falloff and cone
    included): its direction and distance, and the irradiance on a surface facing it."""
    labels, kinds = [], []
    count = len(points)
    directions = np.zeros((count, len(emitters), 3))
    distances = np.zeros((count, len(emitters)))
    irradiance = np.zeros((count, len(emitters)))
    grey = True
    for k, emitter in enumerate(emitters):
        kind = _DELTA[emitter.class_name()]
        label = emitter.id() or f"{kind} #{k + 1}"
        where = f"{file}: emitter {label!r} ({kind})"
        # A spot's texture, like its falloff, is one value towards each receiver: Mitsuba's
        # sample_direction evaluates it there, so textured spots are exact too.
        it = mi.Interaction3f()
        for r, p in enumerate(points.tolist()):
            it.p = mi.Point3f(*p)
            ds, spec = emitter.sample_direction(it, mi.Point2f(0.5, 0.5), False)
            directions[r, k] = np.array(ds.d, dtype=np.float64)
            distances[r, k] = math.inf if kind == "directional" else float(ds.dist)
            rgb = _rgb(spec)
            irradiance[r, k] = float(weights @ rgb)
            grey = grey and _grey(rgb)
        if kind != "directional" and np.any(distances[:, k] <= 0):
            r = int(np.flatnonzero(distances[:, k] <= 0)[0])
            raise fail(where, f"{kind}: it sits at receiver {r} {_triple3(points[r])}, where its irradiance is "
                              f"infinite: move the light off the surface")
        if np.any(irradiance[:, k] < 0) or not np.all(np.isfinite(irradiance[:, k])):
            raise fail(where, f"{kind}: its intensity must be finite and non-negative in every channel")
        labels.append(label)
        kinds.append(kind)
    directions /= np.maximum(np.linalg.norm(directions, axis=-1, keepdims=True), 1e-300)
    return DeltaLights(labels=tuple(labels), kinds=tuple(kinds), directions=directions, distances=distances,
                       irradiance=irradiance, grey=grey)


def _delta_notes(delta: DeltaLights) -> list[str]:
    out = []
    for k, (label, kind) in enumerate(zip(delta.labels, delta.kinds)):
        e = delta.irradiance[:, k]
        out.append(f"{label}: {kind} light, irradiance {e.min():.6g} to {e.max():.6g} at the receivers (facing it): "
                   f"an exact term, with no variance, in every estimate and reference")
    return out


def _envmap_texels(params: dict[str, Any], fields: dict[str, str], where: str) -> np.ndarray:
    """(H, W, 3) linear sRGB of an envmap's bitmap, from the table Mitsuba looks up: it
    pads the bitmap with copies of its edge columns, one before (3.9) or none, and one
    after (scenes/environment.py)."""
    data = np.asarray(params["data"], dtype=np.float64)
    match = re.search(r"\[(\d+),\s*(\d+)\]", fields.get("res", ""))
    width = int(match.group(1)) if match else data.shape[1] - 2
    if data.ndim != 3 or data.shape[2] < 3:
        raise fail(where, f"envmap: Mitsuba's table has shape {data.shape}; warpis expects (H, W, 3) in scalar_rgb")
    if data.shape[1] == width + 2 and np.array_equal(data[:, 0], data[:, width]) \
            and np.array_equal(data[:, width + 1], data[:, 1]):
        return data[:, 1:width + 1, :3]
    if data.shape[1] == width + 1 and np.array_equal(data[:, width], data[:, 0]):
        return data[:, :width, :3]
    raise fail(where, f"envmap: Mitsuba's table ({data.shape[1]} columns for a bitmap {width} wide) is not laid out "
                      f"as warpis reads it")


def _radiance(mi: Any, emitter: Any, where: str, weights: np.ndarray) -> tuple[np.ndarray, float]:
    cls = emitter.class_name()
    if cls != "AreaLight":
        raise fail(where, f"emitter {_EMITTER_PLUGINS.get(cls, cls)!r}: warpis supports {SUPPORTED_EMITTERS}")
    _, fields = _fields(str(emitter))
    rgb = _colour(fields, _params(mi, emitter), "radiance", where, "area emitter")
    if np.any(rgb < 0):
        raise fail(where, f"area emitter: radiance {rgb.tolist()} is negative in some channel")
    return rgb, float(weights @ rgb)


def _geometry(mi: Any, shape: Any, cls: str, where: str, notes: list[str]
              ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray | None, Any]:
    """Vertices and faces of a shape, each face wound counter-clockwise around Mitsuba's
    front side; how far they stray from Mitsuba's surface (0 for triangle meshes); a
    mesh's vertex normals, which Mitsuba shades with; and a curved analytic shape's front
    normal as a function of the point, which Mitsuba shades with there."""
    kind = int(shape.shape_type())
    plugin = _SHAPE_PLUGINS.get(cls, cls.lower())
    flipped = bool(shape.has_flipped_normals())
    if kind == int(mi.ShapeType.Mesh):
        vertices, faces, shading = _mesh(mi, shape, where, notes)
        return vertices, faces, 0.0, shading, None
    if kind in (int(mi.ShapeType.Rectangle), int(mi.ShapeType.Sphere), int(mi.ShapeType.Disk),
                int(mi.ShapeType.Cylinder)):
        m = _matrix(_params(mi, shape)["to_world"])
        if not np.all(np.isfinite(m)) or abs(np.linalg.det(m[:3, :3])) == 0:
            raise fail(where, f"{plugin}: its to_world is singular or not finite")
        builder = {int(mi.ShapeType.Rectangle): _rectangle, int(mi.ShapeType.Sphere): _sphere,
                   int(mi.ShapeType.Disk): _disk, int(mi.ShapeType.Cylinder): _cylinder}[kind]
        vertices, faces, normal, deviation = builder(m, where)
        sign = -1.0 if flipped else 1.0
        curved = kind in (int(mi.ShapeType.Sphere), int(mi.ShapeType.Cylinder))
        analytic = (lambda p: sign * normal(p)) if curved else None
        return vertices, _orient(vertices, faces, normal, sign), deviation, None, analytic
    if plugin in ("instance", "shapegroup"):
        raise fail(where, f"{plugin}s are not supported; warpis supports {SUPPORTED_SHAPES}")
    raise fail(where, f"shape type {plugin!r} is not supported; warpis supports {SUPPORTED_SHAPES}")


def _mesh(mi: Any, shape: Any, where: str, notes: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A Mitsuba triangle mesh: its world-space vertices, and its faces wound around the
    side of its vertex normals (Mitsuba's front: its area light emits there and its BSDF
    reflects there), flipped with flip_normals."""
    params = _params(mi, shape)
    vertices = np.array(params["vertex_positions"], dtype=np.float64).reshape(-1, 3)
    faces = np.array(params["faces"], dtype=np.int64).reshape(-1, 3)
    if not np.all(np.isfinite(vertices)):
        raise fail(where, f"vertex {int(np.argmax(~np.isfinite(vertices).all(axis=1)))} is NaN or infinite")
    side = np.ones(len(faces))
    normals = None
    if shape.has_vertex_normals() and "vertex_normals" in params and len(faces):
        normals = np.array(params["vertex_normals"], dtype=np.float64).reshape(-1, 3)
        v = vertices[faces]
        winding = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        dots = np.einsum("fj,fkj->fk", winding, normals[faces])
        mixed = (dots > 0).any(axis=1) & (dots < 0).any(axis=1)
        if mixed.any():
            text = (f"{int(mixed.sum())} face(s), the first face {int(np.argmax(mixed))}, have vertex normals on "
                    f"both sides, so Mitsuba's front side changes across them")
            if shape.is_emitter():
                raise fail(where, f"{text}: fix the normals or set face_normals=true")
            notes.append(f"{text}; the side of their sum is taken as the front")
        side = np.where(dots.sum(axis=1) < 0, -1.0, 1.0)
        reversed_count = int((side < 0).sum())
        if reversed_count:
            notes.append(f"{reversed_count} of {len(faces)} faces wind against their vertex normals: reversed, "
                         f"to face where Mitsuba's shading normals do")
    if shape.has_flipped_normals():
        side = -side
        normals = None if normals is None else -normals
    faces = faces.copy()
    faces[side < 0] = faces[side < 0][:, [0, 2, 1]]
    return vertices, faces, normals


def _apply(m: np.ndarray, local: np.ndarray) -> np.ndarray:
    return local @ m[:3, :3].T + m[:3, 3]


def _normal_transform(m: np.ndarray) -> np.ndarray:
    """The matrix Mitsuba transforms normals with: the inverse transpose of to_world's linear part."""
    return np.linalg.inv(m[:3, :3]).T


def _orient(vertices: np.ndarray, faces: np.ndarray, normal: Any, sign: float) -> np.ndarray:
    """Faces reversed where their winding disagrees with Mitsuba's normal there (× sign)."""
    v = vertices[faces]
    winding = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    front = sign * normal(v.mean(axis=1))
    out = faces.copy()
    back = np.einsum("fj,fj->f", winding, front) < 0
    out[back] = out[back][:, [0, 2, 1]]
    return out


def _rectangle(m: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray, Any, float]:
    """Mitsuba's rectangle: [-1, 1]² at z = 0, normal +z, through to_world."""
    local = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    n = _normal_transform(m) @ np.array([0.0, 0.0, 1.0])
    return _apply(m, local), np.array([[0, 1, 2], [0, 2, 3]]), lambda c: np.broadcast_to(n, c.shape), 0.0


def _similarity_scale(m: np.ndarray, where: str, plugin: str) -> float:
    """The scale of a rotation × uniform scale (Mitsuba's sphere takes nothing else)."""
    a = m[:3, :3]
    scale = float(np.linalg.norm(a[:, 0]))
    if not np.allclose(a.T @ a, scale**2 * np.eye(3), rtol=0, atol=1e-5 * scale**2):
        raise fail(where, f"{plugin}: its to_world scales unevenly or shears; Mitsuba's {plugin} takes rotations, "
                          f"translations and uniform scales only")
    return scale


def _sphere(m: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray, Any, float]:
    """Mitsuba's sphere (unit, centred at 0, through to_world, which holds its centre and
    radius): an icosphere pushed out to the sphere's area."""
    radius = _similarity_scale(m, where, "sphere")
    centre = m[:3, 3].copy()
    ico = trimesh.creation.icosphere(subdivisions=SPHERE_SUBDIVISIONS, radius=1.0)
    local = np.array(ico.vertices, dtype=np.float64)
    local /= np.linalg.norm(local, axis=1, keepdims=True)
    faces = np.array(ico.faces, dtype=np.int64)
    v = local[faces]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum()
    push = math.sqrt(4.0 * math.pi / area)
    # Farthest from the sphere: the vertices (out by push − 1) or a face's nearest point
    # to the centre (at most its plane's distance inside).
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    plane = np.abs(np.einsum("fj,fj->f", n / np.linalg.norm(n, axis=1, keepdims=True), v[:, 0])) * push
    deviation = radius * max(push - 1.0, float(1.0 - plane.min()))
    return _apply(m, push * local), faces, lambda c: c - centre, deviation


def _ring(segments: int, radius: float) -> np.ndarray:
    phi = 2.0 * np.pi * np.arange(segments) / segments
    return np.stack([radius * np.cos(phi), radius * np.sin(phi), np.zeros(segments)], axis=1)


def _disk(m: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray, Any, float]:
    """Mitsuba's disk (unit, at z = 0, normal +z, through to_world): a fan whose regular
    polygon is pushed out to the disk's area."""
    n_seg = DISK_SEGMENTS
    push = math.sqrt(math.pi / (0.5 * n_seg * math.sin(2.0 * math.pi / n_seg)))
    local = np.vstack([np.zeros((1, 3)), _ring(n_seg, push)])
    k = np.arange(n_seg)
    faces = np.stack([np.zeros(n_seg, np.int64), 1 + k, 1 + (k + 1) % n_seg], axis=1)
    n = _normal_transform(m) @ np.array([0.0, 0.0, 1.0])
    reach = float(np.linalg.svd(m[:3, :2], compute_uv=False).max())
    deviation = reach * max(push - 1.0, 1.0 - push * math.cos(math.pi / n_seg))
    return _apply(m, local), faces, lambda c: np.broadcast_to(n, c.shape), deviation


def _cylinder(m: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray, Any, float]:
    """Mitsuba's cylinder (radius 1 about z from z = 0 to 1, open, normals outwards,
    through to_world, which holds p0, p1 and its radius): a prism pushed out to its area."""
    a = m[:3, :3]
    r0, r1, axis = (np.linalg.norm(a[:, i]) for i in range(3))
    tol = 1e-5 * max(r0, r1, axis)
    if (abs(r0 - r1) > 1e-5 * r0 or abs(a[:, 0] @ a[:, 1]) > tol * r0 or abs(a[:, 0] @ a[:, 2]) > tol * axis
            or abs(a[:, 1] @ a[:, 2]) > tol * axis):
        raise fail(where, "cylinder: its to_world scales its cross-section unevenly or shears it; Mitsuba's "
                          "cylinder is circular (rotations, translations, uniform scales and a scale along its axis)")
    n_seg = CYLINDER_SEGMENTS
    push = (math.pi / n_seg) / math.sin(math.pi / n_seg)
    ring = _ring(n_seg, push)
    local = np.vstack([ring, ring + [0.0, 0.0, 1.0]])
    k = np.arange(n_seg)
    k1 = (k + 1) % n_seg
    faces = np.vstack([np.stack([k, k1, n_seg + k1], axis=1), np.stack([k, n_seg + k1, n_seg + k], axis=1)])
    inverse = np.linalg.inv(a)
    normals = _normal_transform(m)

    def normal(c: np.ndarray) -> np.ndarray:
        p = (c - m[:3, 3]) @ inverse.T
        p[:, 2] = 0.0
        return p @ normals.T

    deviation = float(r0) * max(push - 1.0, 1.0 - push * math.cos(math.pi / n_seg))
    return _apply(m, local), faces.astype(np.int64), normal, deviation


# ----------------------------------------------------------------------------- tessellation error


def _gauss(n: int, a: float, b: float) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (b - a) * x + 0.5 * (a + b), 0.5 * (b - a) * w


def _cylinder_irradiance(length: float, inside: bool) -> float:
    """Irradiance from a unit-radiance, radius-1 open cylinder of ``length`` (Gauss–Legendre
    over the part each receiver sees, where the integrand is smooth).  Outside (normals
    out): at distance 2 from the axis, at mid-length, facing the axis.  Inside (normals
    in): on the axis at mid-length, facing a radius."""
    phi_max = math.pi / 2 if inside else math.acos(0.5)
    phi, wp = _gauss(160, -phi_max, phi_max)
    z, wz = _gauss(160, 0.0, length)
    p, zz = np.meshgrid(phi, z, indexing="ij")
    s = np.stack([np.cos(p), np.sin(p), zz], axis=-1)
    x = np.array([0.0 if inside else 2.0, 0.0, length / 2])
    d = s - x
    r = np.linalg.norm(d, axis=-1)
    out = np.stack([np.cos(p), np.sin(p), np.zeros_like(p)], axis=-1)
    cos_e = np.einsum("...j,...j->...", d, out if inside else -out) / r
    cos_r = np.einsum("...j,j->...", d, np.array([1.0 if inside else -1.0, 0.0, 0.0])) / r
    return float((np.outer(wp, wz) * cos_e * cos_r / r**2).sum())


def _disk_irradiance(m: np.ndarray, height: float) -> float:
    """Irradiance from a unit-radiance disk (any to_world) on the line through its centre
    along its normal at ``height`` on its emitting side, facing it: ∫ h²/|d|⁴ dA (the
    same on either side) by Gauss–Legendre in polar coordinates."""
    rho, wr = _gauss(96, 0.0, 1.0)
    phi, wp = _gauss(192, 0.0, 2.0 * math.pi)
    c0, c1 = m[:3, 0], m[:3, 1]
    jacobian = float(np.linalg.norm(np.cross(c0, c1)))
    n = np.cross(c0, c1) / jacobian
    rr, pp = np.meshgrid(rho, phi, indexing="ij")
    s = rr[..., None] * (np.cos(pp)[..., None] * c0 + np.sin(pp)[..., None] * c1)
    d2 = ((s - height * n) ** 2).sum(axis=-1)
    return float((np.outer(wr, wp) * jacobian * rr * height**2 / d2**2).sum())


def _tessellation_note(mi: Any, shape: Any, plugin: str, vertices: np.ndarray, faces: np.ndarray) -> str:
    """How an analytic emitter's tessellation differs from Mitsuba's shape: its area and
    the irradiance it casts at a unit distance.

    Unit distance: at 2r from a sphere's centre facing it (r its radius; at the centre
    for normals in); on a disk's axis at height r facing it (r = √(area/π)); at 2r from a
    cylinder's axis at mid-length facing it (on the axis facing a radius for normals in).
    """
    m = _matrix(_params(mi, shape)["to_world"])
    a = m[:3, :3]
    inside = bool(shape.has_flipped_normals())
    tris = vertices[faces]
    mesh_area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1).sum()
    if plugin == "sphere":
        r = float(np.linalg.norm(a[:, 0]))
        area = 4.0 * math.pi * r**2
        up = a[:, 2] / np.linalg.norm(a[:, 2])
        x, n = (m[:3, 3], up) if inside else (m[:3, 3] + 2.0 * r * up, -up)
        exact = math.pi if inside else math.pi / 4.0
        place = "at its centre" if inside else "at 2r from its centre, facing it"
    elif plugin == "disk":
        area = math.pi * float(np.linalg.norm(np.cross(a[:, 0], a[:, 1])))
        h = math.sqrt(area / math.pi)
        front = np.cross(a[:, 0], a[:, 1])
        front /= np.linalg.norm(front)
        v = tris[0]
        if np.cross(v[1] - v[0], v[2] - v[0]) @ front < 0:
            front = -front
        x, n = m[:3, 3] + h * front, -front
        exact = _disk_irradiance(m, h)
        place = "on its axis at height r facing it"
    else:
        r, length = float(np.linalg.norm(a[:, 0])), float(np.linalg.norm(a[:, 2]))
        area = 2.0 * math.pi * r * length
        radial, axis = a[:, 0] / r, a[:, 2] / length
        mid = m[:3, 3] + 0.5 * length * axis
        x, n = (mid, radial) if inside else (mid + 2.0 * r * radial, -radial)
        exact = _cylinder_irradiance(length / r, inside)
        place = "on its axis at mid-length facing a radius" if inside else \
            "at 2r from its axis at mid-length, facing it"
    irradiance = float(triangle_irradiance(x[None], n[None], tris, np.ones(len(tris)))[0])
    area_error, irradiance_error = mesh_area / area - 1.0, irradiance / exact - 1.0
    return (f"{plugin} tessellated into {len(faces)} triangles (pushed out to keep its area): area error "
            f"{_percent(area_error)}, irradiance error {_percent(irradiance_error)} {place}")


def _percent(x: float) -> str:
    return "0%" if abs(x) < 1e-12 else f"{100 * x:+.2g}%"


def _concatenate(shapes: list[_Shape]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    vertices, triangles, emission, owner = [], [], [], []
    offset = 0
    for i, s in enumerate(shapes):
        vertices.append(s.vertices)
        triangles.append(s.faces + offset)
        emission.append(np.full(len(s.faces), s.emission))
        owner.append(np.full(len(s.faces), i, np.int32))
        offset += len(s.vertices)
    return (np.vstack(vertices), np.vstack(triangles).astype(np.int64), np.concatenate(emission),
            np.concatenate(owner))


# ----------------------------------------------------------------------------- sensor


@dataclass
class _Viewer:
    """Where receivers are seen from: a position, or a direction (parallel rays)."""

    what: str
    position: np.ndarray | None = None
    direction: np.ndarray | None = None  # towards the viewer

    def towards(self, points: np.ndarray) -> np.ndarray:
        if self.direction is not None:
            return np.tile(self.direction, (len(points), 1))
        return self.position - points


def _sensor(mi: Any, scene: Any) -> _Viewer | str | None:
    """The first sensor as a viewer; a string says why it cannot be one; None: no sensor."""
    sensors = scene.sensors()
    if not sensors:
        return None
    sensor = sensors[0]
    cls = sensor.class_name()
    m = _matrix(sensor.world_transform())
    name = f"sensor {sensor.id()!r}" if sensor.id() else f"the first sensor ({cls})"
    if cls in _POINT_SENSORS:
        return _Viewer(f"{name} at {_triple3(m[:3, 3])}", position=m[:3, 3].copy())
    if cls in _PARALLEL_SENSORS:
        forward = m[:3, 2] / np.linalg.norm(m[:3, 2])
        return _Viewer(f"{name}, orthographic, looking along {_triple3(forward)}", direction=-forward)
    return f"{name} has no viewpoint"


def _triple3(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{x:.6g}" for x in v) + ")"


def _camera(mi: Any, scene: Any, file: Path, width: int | None, height: int | None) -> Camera:
    """The first sensor as a pinhole camera: a ``perspective`` sensor without principal
    point offset or crop window, whose to_world is a rotation (a mirror allowed) and a
    translation; ``width``/``height`` replace its film size (its horizontal field of
    view, Mitsuba's x_fov, is kept, as Mitsuba keeps it when the film changes)."""
    sensors = scene.sensors()
    if not sensors:
        raise fail(file, "has no <sensor>: an image needs a perspective sensor to take its pixels from")
    sensor = sensors[0]
    cls = sensor.class_name()
    name = f"sensor {sensor.id()!r}" if sensor.id() else "the first sensor"
    if cls != "PerspectiveCamera":
        raise fail(file, f"{name} is a {_SENSOR_PLUGINS.get(cls, cls)!r} sensor: an image needs a 'perspective' "
                         f"one (a pinhole camera)")
    params = _params(mi, sensor)
    if params.get("principal_point_offset_x", 0) or params.get("principal_point_offset_y", 0):
        raise fail(file, f"{name}: a principal point offset is not supported (pixels would not be centred)")
    film = sensor.film()
    size = [int(x) for x in film.size()]
    if [int(x) for x in film.crop_size()] != size or any(int(x) for x in film.crop_offset()):
        raise fail(file, f"{name}: a crop window is not supported; give the film's full size instead")
    if width is None and height is not None:
        width = max(1, round(height * size[0] / size[1]))
    if height is None and width is not None:
        height = max(1, round(width * size[1] / size[0]))
    w, h = (width, height) if width is not None else size
    m = _matrix(sensor.world_transform())
    frame = m[:3, :3]
    lengths = np.linalg.norm(frame, axis=0)
    if not (np.allclose(lengths, 1, atol=1e-5) and np.allclose(frame.T @ frame, np.eye(3), atol=1e-5)):
        raise fail(file, f"{name}: its to_world scales or shears ({_triple3(lengths)} column lengths); a camera's "
                         f"to_world must be a rotation (a mirror allowed) and a translation")
    # Mitsuba's camera space: +z forward, +y up, +x towards the image's left edge.
    fov = 2 * math.degrees(math.atan(math.tan(math.radians(float(params["x_fov"])) / 2) * h / w))
    return Camera.framed(m[:3, 3].copy(), frame[:, 2].copy(), frame[:, 1].copy(), -frame[:, 0], fov, w, h, file)


_SENSOR_PLUGINS = {"PerspectiveCamera": "perspective", "ThinLensCamera": "thinlens", "OrthographicCamera":
                   "orthographic", "RadianceMeter": "radiancemeter", "IrradianceMeter": "irradiancemeter",
                   "BatchSensor": "batch", "DistantSensor": "distant"}


def _corner_normals(shapes: list[_Shape], vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray | None:
    """(T, 3, 3) the normal Mitsuba shades with at each triangle's corners: a mesh's vertex
    normals, else the triangle's own normal at every corner; None when no shape has any."""
    if all(s.shading is None for s in shapes):
        return None
    tris = vertices[triangles]
    own = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        own /= np.linalg.norm(own, axis=1, keepdims=True)
    out = np.repeat(own[:, None, :], 3, axis=1)
    start = 0
    for s in shapes:
        if s.shading is not None:
            out[start:start + len(s.faces)] = s.shading[s.faces]
        start += len(s.faces)
    return out


def _analytic_pixels(hits: Any, shapes: list[_Shape]) -> Any:
    """Camera pixels on a curved analytic shape shade with its exact normal at the point
    (turned towards the camera), as Mitsuba does, not with its tessellation's."""
    normals = np.array(hits.normals)
    changed = False
    for k, s in enumerate(shapes):
        rows = np.flatnonzero(hits.mesh == k)
        if s.analytic_normal is None or len(rows) == 0:
            continue
        n = s.analytic_normal(hits.positions[rows])
        n = n / np.linalg.norm(n, axis=1, keepdims=True)
        normals[rows] = np.where((np.einsum("ij,ij->i", n, hits.view[rows]) < 0)[:, None], -n, n)
        changed = True
    return replace(hits, normals=normals) if changed else hits


def _camera_receivers(camera: Camera, shapes: list[_Shape], vertices: np.ndarray, triangles: np.ndarray,
                      emission: np.ndarray, owner: np.ndarray, file: Path, device: str, mitsuba_scene: Any = None
                      ) -> tuple[Receivers, list[str], np.ndarray]:
    """The camera's pixels as receivers, each with the material of the shape it sees (a
    textured parameter evaluated by Mitsuba at the pixel's own point) and Mitsuba's
    shading normal there."""
    unshaded = [f"shape {s.label!r} ({s.material.unshaded})" if s.material.problem else None for s in shapes]
    hits = cast_camera(camera, vertices, triangles, emission, owner, [s.material.twosided for s in shapes], device,
                       _corner_normals(shapes, vertices, triangles), unshaded)
    hits = _analytic_pixels(hits, shapes)
    _receiver_count(len(hits.positions), f"the camera ({camera.width} × {camera.height})", file)
    for k in np.unique(hits.mesh):
        shapes[k].material.check(f"{file}: shape {shapes[k].label!r} (seen by the camera)")
    surfaces = [None if s.material.problem else
                {"material": MATERIALS[s.material.kind].code, "exponent": 1.0,
                 **{name: getattr(s.material, name) for name in SURFACE_FIELDS if name not in ("material", "exponent")}}
                for s in shapes]
    # Every shape has a material (an emitter's is its shell's); one warpis cannot shade
    # has its pixels masked, so it is never a receiver's.
    fields = camera_receiver_fields(hits, surfaces, lambda m, c: shapes[m].material.problem, file)
    starts = np.cumsum([0] + [len(s.faces) for s in shapes])
    curved = np.array([s.analytic_normal is not None for s in shapes])[hits.mesh][:, None]
    diagonal = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    textured, texture_notes = _texture_values(
        mitsuba_scene, file, shapes, hits.mesh, hits.triangles - starts[hits.mesh], hits.positions,
        np.where(curved, hits.normals, hits.geometric_normals), ON_SURFACE * diagonal,
        lambda i: f"{file}: camera pixel {int(hits.layout.pixel[i])} (row-major)")
    for name, (at, values) in textured.items():
        fields[name] = fields[name].copy()
        fields[name][at] = values
    rx = Receivers(**fields)
    notes = [camera.describe(), hits.layout.describe(), *hits.notes, *texture_notes]
    masked = hits.layout.masked_counts()
    if masked["back"]:
        notes.append(f"{masked['back']} pixel(s) see the back of a one-sided BSDF (Mitsuba returns 0 there): masked")
    return rx, notes, np.unique(hits.mesh)


# ----------------------------------------------------------------------------- receivers file


_SIDECAR_KEYS = {"name", "description", "channel", "view", "receivers"}
_GROUP_KEYS = {"name", "points", "normal", "normals", "view", "grid"}
_GRID_KEYS = {"shape", "resolution"}


def _read_sidecar(sidecar: Path, file: Path, receivers_needed: bool = True) -> dict[str, Any]:
    """The receivers file, checked for its keys and their types (a camera's receivers are
    its pixels: then the file may be missing and its receivers are not read)."""
    if not receivers_needed and not sidecar.is_file():
        return {"name": None, "description": "", "channel": None, "view": None, "groups": []}
    if not sidecar.is_file():
        raise fail(file, f"its receivers file {sidecar} does not exist: write one with [[receivers]] tables of "
                         f"points = [[x, y, z], ...] on the scene's surfaces, or grid = {{ shape = \"<id>\", "
                         f"resolution = [nu, nv] }} (README.md, \"Mitsuba scenes\")")
    doc = read_toml(sidecar)
    _check_keys(doc, _SIDECAR_KEYS, "the top level", sidecar)
    for key in ("name", "description", "channel"):
        if key in doc and not isinstance(doc[key], str):
            raise fail(sidecar, f"{key} must be a string, got {doc[key]!r}")
    if "channel" in doc:
        check_channel(doc["channel"], sidecar)
    view = _vector(doc["view"], "view", sidecar) if "view" in doc else None
    if not receivers_needed:
        return {"name": doc.get("name"), "description": doc.get("description", ""), "channel": doc.get("channel"),
                "view": view, "groups": []}
    spec = _require(doc, "receivers", "the top level", sidecar)
    specs = spec if isinstance(spec, list) else [spec]
    if not specs:
        raise fail(sidecar, "[[receivers]] is empty")
    groups = [_group(g, "[receivers]" if len(specs) == 1 else f"[[receivers]] #{i + 1}", sidecar)
              for i, g in enumerate(specs)]
    return {"name": doc.get("name"), "description": doc.get("description", ""), "channel": doc.get("channel"),
            "view": view, "groups": groups}


def _group(spec: Any, where: str, sidecar: Path) -> dict[str, Any]:
    if not isinstance(spec, dict):
        raise fail(sidecar, f"{where} must be a table")
    _check_keys(spec, _GROUP_KEYS, where, sidecar)
    if ("points" in spec) == ("grid" in spec):
        raise fail(sidecar, f"{where} needs exactly one of 'points' or 'grid'")
    if "normal" in spec and "normals" in spec:
        raise fail(sidecar, f"{where} has both 'normal' and 'normals'")
    name = spec.get("name", where)
    if not isinstance(name, str):
        raise fail(sidecar, f"{where}.name must be a string, got {name!r}")
    label = f"{where} {name!r}" if "name" in spec else where
    group: dict[str, Any] = {"where": label, "name": name, "points": None, "grid": None, "normals": None,
                             "normal": None, "view": None}
    if "points" in spec:
        group["points"] = _vectors(spec["points"], f"{where}.points", sidecar)
        _coordinates(group["points"], f"{where}.points", sidecar)
        _receiver_count(len(group["points"]), f"{where}.points", sidecar)
    else:
        grid = spec["grid"]
        if not isinstance(grid, dict):
            raise fail(sidecar, f"{where}.grid must be a table {{ shape = \"<id>\", resolution = [nu, nv] }}")
        _check_keys(grid, _GRID_KEYS, f"{where}.grid", sidecar)
        shape = _require(grid, "shape", f"{where}.grid", sidecar)
        if not isinstance(shape, str):
            raise fail(sidecar, f"{where}.grid.shape must be a shape's id (a string), got {shape!r}")
        res = _require(grid, "resolution", f"{where}.grid", sidecar)
        if (not isinstance(res, list) or len(res) != 2
                or not all(isinstance(r, int) and not isinstance(r, bool) for r in res)):
            raise fail(sidecar, f"{where}.grid.resolution must be two integers [nu, nv], got {res!r}")
        if res[0] < 1 or res[1] < 1:
            raise fail(sidecar, f"{where}.grid.resolution must be at least [1, 1], got {res!r}")
        _receiver_count(res[0] * res[1], f"{where}.grid.resolution {res!r}", sidecar)
        group["grid"] = (shape, int(res[0]), int(res[1]))
    if "normals" in spec:
        if "grid" in spec:
            raise fail(sidecar, f"{where}: a grid takes one 'normal', not 'normals'")
        normals = _vectors(spec["normals"], f"{where}.normals", sidecar)
        if len(normals) != len(group["points"]):
            raise fail(sidecar, f"{where}.normals has {len(normals)} entries for {len(group['points'])} points")
        group["normals"] = _unit(normals, f"{where}.normals", sidecar)
    elif "normal" in spec:
        group["normal"] = _unit(_vector(spec["normal"], f"{where}.normal", sidecar), f"{where}.normal", sidecar)
    if "view" in spec:
        group["view"] = _vector(spec["view"], f"{where}.view", sidecar)
    return group


# ----------------------------------------------------------------------------- receivers on surfaces


def _closest_points(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The closest point to each p on triangle (a, b, c), row by row (Ericson, Real-Time
    Collision Detection, 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        out = a + ab * (vb / denom)[:, None] + ac * (vc / denom)[:, None]
        e_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        out = np.where(((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0))[:, None], b + (c - b) * e_bc[:, None], out)
        e_ac = d2 / (d2 - d6)
        out = np.where(((vb <= 0) & (d2 >= 0) & (d6 <= 0))[:, None], a + ac * e_ac[:, None], out)
        out = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, out)
        e_ab = d1 / (d1 - d3)
        out = np.where(((vc <= 0) & (d1 >= 0) & (d3 <= 0))[:, None], a + ab * e_ab[:, None], out)
        out = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, out)
        out = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, out)
    return out


_PAIRS = 1 << 21  # (point, triangle) pairs held at once


def _nearest_distance(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Distance from each point to the nearest of ``tris`` (brute force, for messages)."""
    best = np.full(len(points), np.inf)
    step = max(1, _PAIRS // max(1, len(tris)))
    for s in range(0, len(points), step):
        p = points[s:s + step]
        pi = np.repeat(np.arange(len(p)), len(tris))
        ti = np.tile(np.arange(len(tris)), len(p))
        q = _closest_points(p[pi], tris[ti, 0], tris[ti, 1], tris[ti, 2])
        d = np.linalg.norm(p[pi] - q, axis=1)
        d[~np.isfinite(d)] = np.inf
        np.minimum.at(best[s:s + step], pi, d)
    return best


# Above this many (point, triangle) box tests, candidates come from a uniform grid of
# cells, whose (cell, triangle) entries are kept below _GRID_ENTRIES.
_BRUTE_FORCE = 1 << 23
_GRID_ENTRIES = 1 << 26


def _box_pairs(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every (point, triangle) pair whose box [lo, hi] holds the point."""
    if len(points) * len(lo) <= _BRUTE_FORCE:
        step = max(1, _PAIRS // max(1, len(lo)))
        found = [np.nonzero(((points[s:s + step, None, :] >= lo[None]) & (points[s:s + step, None, :] <= hi[None]))
                            .all(axis=2)) for s in range(0, len(points), step)]
        return (np.concatenate([pi + k * step for k, (pi, _) in enumerate(found)]),
                np.concatenate([ti for _, ti in found]))
    # A uniform grid: each box is listed in every cell it overlaps, each point looks up its cell.
    origin = lo.min(axis=0)
    extent = float((hi.max(axis=0) - origin).max())
    cell = max(float(np.median((hi - lo).max(axis=1))), extent / 256, extent * 1e-9, 1e-300)
    while True:
        shape = np.floor((hi.max(axis=0) - origin) / cell).astype(np.int64) + 1
        c_lo = np.floor((lo - origin) / cell).astype(np.int64)
        c_hi = np.floor((hi - origin) / cell).astype(np.int64)
        dims = c_hi - c_lo + 1
        counts = dims.prod(axis=1)
        if counts.sum() <= _GRID_ENTRIES:
            break
        cell *= 2.0
    total = int(counts.sum())
    tri = np.repeat(np.arange(len(lo)), counts)
    local = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    ix = c_lo[tri, 0] + local % dims[tri, 0]
    iy = c_lo[tri, 1] + (local // dims[tri, 0]) % dims[tri, 1]
    iz = c_lo[tri, 2] + local // (dims[tri, 0] * dims[tri, 1])
    keys = (ix * shape[1] + iy) * shape[2] + iz
    order = np.argsort(keys, kind="stable")
    keys, tri = keys[order], tri[order]
    c = np.floor((points - origin) / cell).astype(np.int64)
    outside = ((c < 0) | (c >= shape)).any(axis=1)
    c = np.clip(c, 0, shape - 1)
    point_keys = (c[:, 0] * shape[1] + c[:, 1]) * shape[2] + c[:, 2]
    left = np.searchsorted(keys, point_keys, side="left")
    right = np.searchsorted(keys, point_keys, side="right")
    length = np.where(outside, 0, right - left)
    pi = np.repeat(np.arange(len(points)), length)
    ti = tri[np.repeat(left, length) + np.arange(int(length.sum())) - np.repeat(np.cumsum(length) - length, length)]
    keep = ((points[pi] >= lo[ti]) & (points[pi] <= hi[ti])).all(axis=1)
    return pi[keep], ti[keep]


def _locate(points: np.ndarray, tris: np.ndarray, tol: np.ndarray, slack: float, rank: Any
            ) -> tuple[np.ndarray, np.ndarray]:
    """The triangle each point lies on (within its ``tol``) and the closest point on it;
    -1 where none.  Among triangles within ``slack`` of the nearest, the lowest ``rank``
    (point index array, triangle index array → sort keys, most important last) wins."""
    index = np.full(len(points), -1, np.int64)
    closest = points.copy()
    candidates_p, candidates_t = _box_pairs(points, tris.min(axis=1) - tol[:, None], tris.max(axis=1) + tol[:, None])
    found_p, found_t, found_d, found_q = [], [], [], []
    for u in range(0, len(candidates_p), _PAIRS):
        a, t = candidates_p[u:u + _PAIRS], candidates_t[u:u + _PAIRS]
        q = _closest_points(points[a], tris[t, 0], tris[t, 1], tris[t, 2])
        d = np.linalg.norm(points[a] - q, axis=1)
        ok = np.isfinite(d) & (d <= tol[t])
        found_p.append(a[ok])
        found_t.append(t[ok])
        found_d.append(d[ok])
        found_q.append(q[ok])
    if not found_p:
        return index, closest
    pi, ti, d, q = (np.concatenate(x) for x in (found_p, found_t, found_d, found_q))
    if not len(pi):
        return index, closest
    best = np.full(len(points), np.inf)
    np.minimum.at(best, pi, d)
    near = d <= best[pi] + slack
    pi, ti, q = pi[near], ti[near], q[near]
    order = np.lexsort((ti, *rank(pi, ti), pi))
    pi, ti, q = pi[order], ti[order], q[order]
    first = np.flatnonzero(np.r_[True, pi[1:] != pi[:-1]])
    index[pi[first]] = ti[first]
    closest[pi[first]] = q[first]
    return index, closest


def _turn(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """z of (a − o) × (b − o): > 0 when o → a → b turns counter-clockwise."""
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def _hull(points: np.ndarray) -> np.ndarray:
    """Convex hull of 2D points, counter-clockwise (Andrew's monotone chain)."""
    pts = np.unique(points, axis=0)
    if len(pts) < 3:
        return pts

    def half(seq: np.ndarray) -> list[np.ndarray]:
        out: list[np.ndarray] = []
        for p in seq:
            while len(out) >= 2 and _turn(out[-2], out[-1], p) <= 0:
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1])


def _grid(group: dict[str, Any], shapes: list[_Shape], base: float, sidecar: Path, file: Path
          ) -> tuple[np.ndarray, int, np.ndarray, tuple[int, int]]:
    """Cell centres of a grid over a planar shape's minimum-area bounding rectangle: the
    points, the shape's index, its front normal and the grid's (rows, cols)."""
    where = group["where"]
    sid, nu, nv = group["grid"]
    matches = [i for i, s in enumerate(shapes) if s.id == sid]
    if not matches:
        ids = ", ".join(repr(s.id) for s in shapes if s.id) or "none"
        raise fail(sidecar, f"{where}: grid shape {sid!r}: no shape with that id in {file.name} (ids: {ids})")
    index = matches[0]
    s = shapes[index]
    tris = s.vertices[s.faces]
    cross = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    areas = np.linalg.norm(cross, axis=1)
    total = cross.sum(axis=0)
    if not np.linalg.norm(total) > 0:
        raise fail(sidecar, f"{where}: grid: shape {sid!r} has no area facing one side (a grid needs a planar shape)")
    n = total / np.linalg.norm(total)
    used = s.vertices[np.unique(s.faces)]
    centre = used.mean(axis=0)
    off_plane = float(np.abs((used - centre) @ n).max())
    good = areas > 0
    folded = bool(np.any(np.einsum("fj,j->f", cross[good] / areas[good, None], n) < 1 - 1e-6))
    if off_plane > base + s.deviation or folded:
        raise fail(sidecar, f"{where}: grid: shape {sid!r} is not planar (its vertices stray up to {off_plane:.3g} "
                            f"from its mean plane{', and its faces face different ways' if folded else ''}); a grid "
                            f"needs a planar shape: list points instead")
    e1 = np.cross(n, [1.0, 0.0, 0.0])
    if np.linalg.norm(e1) < 0.5:
        e1 = np.cross(n, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    flat = np.stack([(used - centre) @ e1, (used - centre) @ e2], axis=1)
    hull = _hull(flat)
    best = None
    for i in range(len(hull)):
        edge = hull[(i + 1) % len(hull)] - hull[i]
        if not np.linalg.norm(edge) > 0:
            continue
        a = edge / np.linalg.norm(edge)
        b = np.array([-a[1], a[0]])
        pa, pb = hull @ a, hull @ b
        area = (pa.max() - pa.min()) * (pb.max() - pb.min())
        if best is None or area < best[0] * (1 - 1e-12):
            best = (area, a, b, (pa.min(), pa.max()), (pb.min(), pb.max()))
    if best is None:
        raise fail(sidecar, f"{where}: grid: shape {sid!r} has no area")
    _, a, b, (a0, a1), (b0, b1) = best
    sides = [(a1 - a0, a[0] * e1 + a[1] * e2), (b1 - b0, b[0] * e1 + b[1] * e2)]
    longest = max(length for length, _ in sides)
    candidates = [d / np.linalg.norm(d) for length, d in sides if length >= longest * (1 - 1e-9)]
    # u along the longer side, pointing where its largest component is positive; for a
    # square, the side closest to the x axis (then y).
    candidates = [d if d[np.argmax(np.abs(d))] > 0 else -d for d in candidates]
    u = max(candidates, key=lambda d: tuple(np.round(np.abs(d), 9)))
    v = np.cross(n, u)
    rel = flat @ np.array([u @ e1, u @ e2]), flat @ np.array([v @ e1, v @ e2])
    lu, lv = rel[0].max() - rel[0].min(), rel[1].max() - rel[1].min()
    origin = centre + rel[0].min() * u + rel[1].min() * v
    su = (np.arange(nu) + 0.5) / nu
    sv = (np.arange(nv) + 0.5) / nv
    points = origin + sv[:, None, None] * lv * v + su[None, :, None] * lu * u
    return points.reshape(-1, 3), index, n, (nv, nu)


def _receivers(side: dict[str, Any], shapes: list[_Shape], vertices: np.ndarray, triangles: np.ndarray,
               owner: np.ndarray, sensor: _Viewer | str | None, file: Path, sidecar: Path,
               mitsuba_scene: Any = None) -> tuple[Receivers, list[str], np.ndarray]:
    """The receivers of the receivers file on the scene's surfaces, notes about them, and
    the shapes they lie on (``mitsuba_scene``: Mitsuba's, which evaluates textures)."""
    tris = vertices[triangles]
    cross = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        front = cross / np.linalg.norm(cross, axis=1, keepdims=True)
    diagonal = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    base = ON_SURFACE * diagonal
    tol = base + np.array([s.deviation for s in shapes])[owner]
    emitter = np.array([s.radiance is not None for s in shapes])[owner]
    notes: list[str] = []
    rows: dict[str, list[Any]] = {k: [] for k in ("positions", "normals", "geometric", "view", "shape", "group",
                                                  "triangle", "off")}
    grid_shape = None
    viewers_used: set[str] = set()
    for g, group in enumerate(side["groups"]):
        where = group["where"]
        viewer = _group_viewer(group, side, sensor, where, file, sidecar)
        viewers_used.add(viewer.what)
        if group["points"] is not None:
            points = group["points"]
            towards = viewer.towards(points)

            def rank(pi: np.ndarray, ti: np.ndarray, towards: np.ndarray = towards) -> tuple[np.ndarray, ...]:
                facing = np.einsum("ij,ij->i", towards[pi], front[ti]) > 0
                return emitter[ti], ~facing

            index, closest = _locate(points, tris, tol, base, rank)
            missing = np.flatnonzero(index < 0)
            if len(missing):
                i = int(missing[0])
                d = float(_nearest_distance(points[i:i + 1], tris)[0])
                raise fail(sidecar, f"{where} point {i} {_triple3(points[i])} lies on no surface of {file.name}: the "
                                    f"nearest is {d:.3g} away (tolerance {base:.3g})"
                                    + (f"; {len(missing) - 1} more point(s) too" if len(missing) > 1 else ""))
            shape_of = owner[index]
            normals_front = front[index]
            moved = np.linalg.norm(closest - points, axis=1)
            analytic = np.array([shapes[k].deviation > 0 for k in shape_of])
            if analytic.any() and moved[analytic].max() > base:
                notes.append(f"{where}: {int((moved[analytic] > base).sum())} point(s) moved onto the "
                             f"tessellation of an analytic shape, by at most {moved[analytic].max():.3g}")
            points = closest
        else:
            points, k, n, shape_rc = _grid(group, shapes, base, sidecar, file)
            mine = np.flatnonzero(owner == k)
            index, closest = _locate(points, tris[mine], tol[mine], base,
                                     lambda pi, ti: (np.zeros(len(pi), bool),))
            off = int((index < 0).sum())
            if off:
                raise fail(sidecar, f"{where}: {off} of {len(points)} grid cell centres fall off shape "
                                    f"{group['grid'][0]!r} (the grid spans its minimum-area bounding rectangle; for a "
                                    f"shape that is not a rectangle, list points instead)")
            points = closest
            shape_of = np.full(len(points), k)
            normals_front = np.tile(n, (len(points), 1))
            if len(side["groups"]) == 1:
                grid_shape = shape_rc
        triangle = index if group["points"] is not None else mine[index]
        shading_front, shading_notes = _shading_normals(f"{sidecar}: {where}", shapes, shape_of, triangle, points,
                                                        tris, normals_front)
        notes += shading_notes
        towards = viewer.towards(points)
        length = np.linalg.norm(towards, axis=1)
        if not np.all(length > 0):
            i = int(np.argmin(length > 0))
            raise fail(sidecar, f"{where} point {i}: the viewer ({viewer.what}) is at the receiver itself")
        view = towards / length[:, None]
        # Mitsuba's BSDFs decide the side in the shading frame (cos θi > 0; twosided flips it).
        facing = np.einsum("ij,ij->i", view, shading_front) > 0
        on_emitter = np.array([shapes[k].radiance is not None for k in range(len(shapes))])[shape_of]
        if on_emitter.any():
            i = int(np.argmax(on_emitter))
            raise fail(sidecar, f"{where} point {i} {_triple3(points[i])} lies on shape {shapes[shape_of[i]].label!r}, "
                                f"an emitter: receivers must lie on surfaces that do not emit")
        _check_shaded(shapes, shape_of, points, f"{where} in {sidecar.name}")
        one_sided = ~np.array([s.material.twosided for s in shapes])[shape_of]
        if (one_sided & ~facing).any():
            i = int(np.argmax(one_sided & ~facing))
            s = shapes[shape_of[i]]
            raise fail(sidecar, f"{where} point {i} {_triple3(points[i])}: the viewer ({viewer.what}) is behind "
                                f"shape {s.label!r}, whose BSDF ({s.material.text}) is one-sided, so Mitsuba "
                                f"returns 0 there: wrap it in a twosided BSDF, or move the viewer")
        for k in np.unique(shape_of):
            i = int(np.argmax(shape_of == k))
            shapes[k].material.check(f"{sidecar}: {where} point {i} lies on shape {shapes[k].label!r}")
        if group["normals"] is not None:
            normals = group["normals"]
        elif group["normal"] is not None:
            normals = np.tile(group["normal"], (len(points), 1))
        else:
            normals = np.where(facing[:, None], shading_front, -shading_front)
        behind = np.einsum("ij,ij->i", view, normals) <= 0
        if behind.any():
            i = int(np.argmax(behind))
            raise fail(sidecar, f"{where} point {i} {_triple3(points[i])}: the viewer ({viewer.what}) is behind its "
                                f"normal {_triple3(normals[i])}")
        rows["positions"].append(points)
        rows["normals"].append(normals)
        rows["geometric"].append(np.where(facing[:, None], normals_front, -normals_front))
        rows["view"].append(view)
        rows["shape"].append(shape_of)
        rows["group"].append(np.full(len(points), g, np.int32))
        rows["triangle"].append(triangle)
        # Off the surface on the viewer's side: along the analytic normal of a curved shape, else the triangle's.
        curved = np.array([shapes[k].analytic_normal is not None for k in shape_of])[:, None]
        rows["off"].append(np.where(facing[:, None], 1.0, -1.0) * np.where(curved, shading_front, normals_front))
    for what in sorted(viewers_used):
        notes.append(f"receivers seen from {what}")
    shape_of = np.concatenate(rows["shape"])
    _receiver_count(len(shape_of), "[[receivers]]", sidecar)
    materials = [s.material for s in shapes]

    def per_receiver(name: str, kind: Any = np.float64) -> np.ndarray:
        return np.array([getattr(m, name) for m in materials], kind)[shape_of]

    positions = np.vstack(rows["positions"])
    starts = np.cumsum([0] + [len(s.faces) for s in shapes])
    group_of = np.concatenate(rows["group"])
    first = np.cumsum([0] + [len(x) for x in rows["group"]])
    textured, texture_notes = _texture_values(
        mitsuba_scene, file, shapes, shape_of, np.concatenate(rows["triangle"]) - starts[shape_of], positions,
        np.vstack(rows["off"]), base,
        lambda i: f"{sidecar}: {side['groups'][group_of[i]]['where']} point {i - first[group_of[i]]}")
    notes += texture_notes
    columns = {name: per_receiver(name) for name in ("albedo", "alpha", "specular")}
    for name, (at, values) in textured.items():
        columns[name][at] = values

    rx = Receivers(
        positions=positions,
        normals=np.vstack(rows["normals"]),
        geometric_normals=np.vstack(rows["geometric"]),
        material=np.array([MATERIALS[m.kind].code for m in materials], np.int32)[shape_of],
        albedo=columns["albedo"],
        exponent=np.ones(len(shape_of)),
        view=np.vstack(rows["view"]),
        group=np.concatenate(rows["group"]),
        group_names=[g["name"] for g in side["groups"]],
        grid_shape=grid_shape,
        alpha=columns["alpha"],
        distribution=per_receiver("distribution", np.int32),
        sample_visible=per_receiver("sample_visible", np.int32),
        eta=per_receiver("eta"),
        k=per_receiver("k"),
        specular=columns["specular"],
        specular_weight=per_receiver("specular_weight"),
    )
    return rx, notes, np.unique(shape_of)


def _texture_values(mitsuba_scene: Any, file: Path, shapes: list[_Shape], shape_of: np.ndarray, faces: np.ndarray,
                    points: np.ndarray, towards: np.ndarray, base: float, where: Any
                    ) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], list[str]]:
    """Textured BSDF parameters at each receiver on a textured shape, evaluated by Mitsuba
    itself: the surface interaction of a short ray at the point along ``towards`` (a
    unit vector off the surface on the viewer's side) against the receiver's own shape
    (its own triangle, on a mesh), then each texture's ``eval`` (``eval_1`` for alpha, as
    Mitsuba's roughconductor reads it) there.  ``faces`` holds each receiver's triangle
    within its shape; ``where(i)`` names receiver i in messages.  Returns, per field
    ("albedo", "specular", "alpha"), the receivers' rows and their values, and notes."""
    out: dict[str, tuple[list[int], list[Any]]] = {}
    notes: list[str] = []
    textured = [int(k) for k in np.unique(shape_of) if shapes[k].material.textures]
    if not textured:
        return {}, notes
    if mitsuba_scene is None:
        raise fail(file, f"shape {shapes[textured[0]].label!r} has a textured BSDF, which needs Mitsuba's scene")
    with _Mitsuba(file) as session:
        mi = session.mi
        mitsuba_shapes = list(mitsuba_scene.shapes())
        for k in textured:
            s, ms = shapes[k], mitsuba_shapes[k]
            m = s.material
            rows = np.flatnonzero(shape_of == k)
            reach = 10.0 * base + 2.0 * s.deviation
            values: dict[str, list[Any]] = {name: [] for name in m.textures}
            mesh = int(ms.shape_type()) == int(mi.ShapeType.Mesh)
            for r in rows.tolist():
                p, n = points[r], towards[r]
                ray = mi.Ray3f(mi.Point3f(*(p + reach * n)), mi.Vector3f(*(-n)))
                if mesh:  # its own triangle (warpis keeps a mesh's faces in Mitsuba's order)
                    hit = ms.ray_intersect_triangle(int(faces[r]), ray)
                    si = hit.compute_surface_interaction(ray) if hit.is_valid() else None
                else:
                    si = ms.ray_intersect(ray)
                if si is None or not si.is_valid() or not np.linalg.norm(np.array(si.p) - p) <= reach + base:
                    raise fail(where(r), f"Mitsuba finds no surface of shape {s.label!r} at {_triple3(p)} to evaluate "
                                         f"its BSDF's textures at")
                for name, textures in m.textures.items():
                    if name == "alpha":
                        alpha = [float(t.eval_1(si)) for t in textures]
                        if len(alpha) == 2 and alpha[0] != alpha[1]:
                            raise fail(where(r), f"shape {s.label!r}: roughconductor alpha_u={alpha[0]:.6g}, "
                                                 f"alpha_v={alpha[1]:.6g} at {_triple3(p)} (anisotropic); warpis "
                                                 f"supports an isotropic alpha only")
                        values[name].append(alpha[0])
                    else:
                        values[name].append(_rgb(textures[0].eval(si)))
            for name, got in values.items():
                label = {"albedo": "diffuse reflectance", "specular": "specular reflectance", "alpha": "alpha"}[name]
                if name == "alpha":
                    v = np.array(got, np.float64)
                    bad = ~((v >= MIN_ALPHA) & (v <= 1e3))
                    domain = f"roughness in [{MIN_ALPHA:g}, 1000]"
                else:
                    rgb = np.array(got, np.float64)
                    if not all(_grey(c) for c in rgb):
                        m.grey = False
                    v = rgb @ m.weights if name == "albedo" else rgb * m.weights
                    bad = ~np.all((rgb >= 0) & (rgb <= 1e3), axis=1)
                    domain = "reflectances in [0, 1000] in every channel"
                if bad.any():
                    i = int(rows[np.argmax(bad)])
                    value = got[int(np.argmax(bad))]
                    shown = f"{value:.6g}" if name == "alpha" else _triple3(value)
                    raise fail(where(i), f"shape {s.label!r}: its {label} texture is {shown} at "
                                         f"{_triple3(points[i])}; warpis supports {domain}")
                out.setdefault(name, ([], []))
                out[name][0].extend(rows.tolist())
                out[name][1].extend(list(v))
                shown = v if v.ndim == 1 else v.sum(axis=1)
                notes.append(f"{s.label}: {len(rows)} receiver(s) take its {label} from its "
                             f"{_texture_name(_first_texture(m.texture_text[name]))!r} texture at their own point "
                             f"(Mitsuba's eval there): {float(shown.min()):.6g} to {float(shown.max()):.6g}"
                             + (" in this channel" if name != "alpha" else ""))
    return {name: (np.array(r, np.int64), np.array(v, np.float64)) for name, (r, v) in out.items()}, notes


def _check_shaded(shapes: list[_Shape], shape_of: np.ndarray, points: np.ndarray, where: str) -> None:
    """A receiver on a shape whose BSDF warpis cannot shade raises that shape's error."""
    for k in np.unique(shape_of):
        if shapes[k].material.problem:
            i = int(np.argmax(shape_of == k))
            raise WarpisError(f"{shapes[k].material.problem}; point {i} {_triple3(points[i])} of {where} lies on it")


def _shading_normals(where: str, shapes: list[_Shape], shape_of: np.ndarray, index: np.ndarray, points: np.ndarray,
                     tris: np.ndarray, fronts: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Mitsuba's shading normal at each receiver (the front side): on a mesh with vertex
    normals, their interpolation at the point's barycentric coordinates in its triangle
    ``index``, normalised, as Mitsuba's mesh interaction computes it; elsewhere the
    triangle's own normal ``fronts``.  And a note per shape where the two differ."""
    shading_normals = fronts.copy()
    notes = []
    starts = np.cumsum([0] + [len(s.faces) for s in shapes])
    for k in np.unique(shape_of):
        shading = shapes[k].shading
        rows = np.flatnonzero(shape_of == k)
        if shapes[k].analytic_normal is not None:
            exact = shapes[k].analytic_normal(points[rows])
            shading_normals[rows] = exact / np.linalg.norm(exact, axis=1, keepdims=True)
            angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", shading_normals[rows], fronts[rows]), -1, 1)))
            if angle.max() > 0.01:
                notes.append(f"{where}: on shape {shapes[k].label!r} ({shapes[k].plugin}), receivers shade with "
                             f"Mitsuba's analytic normal, up to {angle.max():.3g}° from its tessellation's")
            continue
        if shading is None:
            continue
        interpolated = interpolate_normals(shading[shapes[k].faces[index[rows] - starts[k]]], tris[index[rows]],
                                           points[rows])
        bad = ~np.isfinite(interpolated).all(axis=1)
        if bad.any():
            i = int(rows[np.argmax(bad)])
            raise fail(where, f"point {i} {_triple3(points[i])}: the vertex normals of shape {shapes[k].label!r} "
                              f"cancel there, so Mitsuba has no shading normal")
        shading_normals[rows] = interpolated
        cosine = np.clip(np.einsum("ij,ij->i", interpolated, fronts[rows]), -1.0, 1.0)
        angle = np.degrees(np.arccos(cosine))
        if angle.max() > 0.01:
            notes.append(f"{where}: on shape {shapes[k].label!r}, receivers shade with Mitsuba's normals interpolated "
                         f"from its vertex normals, up to {angle.max():.3g}° from the triangles' own normals "
                         f"({int((angle > 0.01).sum())} of {len(rows)} receivers)")
    return shading_normals, notes


def _group_viewer(group: dict[str, Any], side: dict[str, Any], sensor: _Viewer | str | None, where: str,
                  file: Path, sidecar: Path) -> _Viewer:
    if group["view"] is not None:
        return _Viewer(f"{where}.view {_triple3(group['view'])}", position=group["view"])
    if side["view"] is not None:
        return _Viewer(f"view {_triple3(side['view'])}", position=side["view"])
    if isinstance(sensor, _Viewer):
        return sensor
    why = f"{file.name} has no <sensor>" if sensor is None else f"in {file.name}, {sensor}"
    raise fail(sidecar, f"{where}: no viewer: {why}; give view = [x, y, z] (the viewer's position) at the top "
                        f"level or in the group")
