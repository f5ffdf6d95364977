"""Emitters: an area emitter's uniform radiance (one-sided, read with its shape in
:mod:`.shapes`), an envmap or constant emitter as warpis's :class:`Environment`, and
point, spot and directional lights as :class:`DeltaLights` at the receivers."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import fail
from ..delta import DeltaLights
from ..environment import Environment
from .materials import uniform_colour
from .parse import is_grey, object_fields, object_parameters, rgb_text, to_rgb, transform_matrix, vector_text

SUPPORTED_EMITTERS = ("area emitters (an <emitter type=\"area\"> inside a <shape>) with uniform radiance, an envmap "
                      "(a rotation as its to_world), a constant emitter of uniform radiance, and point, spot and "
                      "directional lights")
ENVIRONMENT_CLASSES = {"EnvironmentMapEmitter", "ConstantBackgroundEmitter"}
DELTA_KINDS = {"PointLight": "point", "SpotLight": "spot", "DirectionalEmitter": "directional"}
EMITTER_PLUGINS = {"PointLight": "point", "SpotLight": "spot", "ConstantBackgroundEmitter": "constant",
                   "EnvironmentMapEmitter": "envmap", "DirectionalEmitter": "directional", "Projector": "projector",
                   "DirectionalArea": "directionalarea", "SunskyEmitter": "sunsky", "AreaLight": "area"}


def read_environment(mi: Any, scene: Any, file: Path, weights: np.ndarray) -> Environment | None:
    """The scene's envmap or constant emitter as warpis's Environment (one at most), its
    table exactly the one Mitsuba looks up (scenes/environment.py)."""
    found = [e for e in scene.emitters() if e.class_name() in ENVIRONMENT_CLASSES]
    if not found:
        return None
    emitter = found[0]
    cls = emitter.class_name()
    plugin = EMITTER_PLUGINS[cls]
    where = f"{file}: emitter {emitter.id()!r} ({plugin})" if emitter.id() else f"{file}: emitter {plugin!r}"
    params = object_parameters(mi, emitter)
    _, fields = object_fields(str(emitter))
    if cls == "ConstantBackgroundEmitter":
        rgb = uniform_colour(fields, params, "radiance", where, plugin)
        if np.any(rgb < 0):
            raise fail(where, f"{plugin}: radiance {rgb.tolist()} is negative in some channel")
        texels, rotation, grey = np.full((3, 2), float(weights @ rgb)), np.eye(3), is_grey(rgb)
        text = f"constant environment, radiance {float(weights @ rgb):.6g} (linear sRGB {rgb_text(rgb)})"
    else:
        rgb_texels = _envmap_texels(params, fields, where)
        grey = bool(np.all(rgb_texels == rgb_texels[..., :1]))
        texels = rgb_texels @ weights * float(params["scale"])
        m = transform_matrix(params["to_world"])
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


def read_delta_lights(mi: Any, emitters: list[Any], points: np.ndarray, file: Path, weights: np.ndarray) -> DeltaLights:
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
        kind = DELTA_KINDS[emitter.class_name()]
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
            rgb = to_rgb(spec)
            irradiance[r, k] = float(weights @ rgb)
            grey = grey and is_grey(rgb)
        if kind != "directional" and np.any(distances[:, k] <= 0):
            r = int(np.flatnonzero(distances[:, k] <= 0)[0])
            raise fail(where, f"{kind}: it sits at receiver {r} {vector_text(points[r])}, where its irradiance is "
                              f"infinite: move the light off the surface")
        if np.any(irradiance[:, k] < 0) or not np.all(np.isfinite(irradiance[:, k])):
            raise fail(where, f"{kind}: its intensity must be finite and non-negative in every channel")
        labels.append(label)
        kinds.append(kind)
    directions /= np.maximum(np.linalg.norm(directions, axis=-1, keepdims=True), 1e-300)
    return DeltaLights(labels=tuple(labels), kinds=tuple(kinds), directions=directions, distances=distances,
                       irradiance=irradiance, grey=grey)


def delta_notes(delta: DeltaLights) -> list[str]:
    """One note per point, spot or directional light: its irradiance at the receivers."""
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


def area_radiance(mi: Any, emitter: Any, where: str, weights: np.ndarray) -> tuple[np.ndarray, float]:
    """A shape's area emitter: its uniform radiance, linear sRGB and in warpis's channel."""
    cls = emitter.class_name()
    if cls != "AreaLight":
        raise fail(where, f"emitter {EMITTER_PLUGINS.get(cls, cls)!r}: warpis supports {SUPPORTED_EMITTERS}")
    _, fields = object_fields(str(emitter))
    rgb = uniform_colour(fields, object_parameters(mi, emitter), "radiance", where, "area emitter")
    if np.any(rgb < 0):
        raise fail(where, f"area emitter: radiance {rgb.tolist()} is negative in some channel")
    return rgb, float(weights @ rgb)
