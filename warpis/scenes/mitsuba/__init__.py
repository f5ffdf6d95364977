"""The Mitsuba 3 scene source: an XML scene and its receivers file → :class:`Scene`.

Mitsuba's own parser reads the XML (includes, ``<default>``, ``<ref>``, ``<path>``,
transforms, spectra), in its ``scalar_rgb`` variant; this package turns what it built into
warpis's arrays and hands them to the same gate as every other source (``assemble_scene``).
:func:`load_mitsuba` runs the steps top-down, one module each:

* :mod:`.channels` — colour: warpis is monochrome, so radiance and diffuse reflectance
  become one channel (``CHANNELS``: r, g, b, or the luminance y of linear sRGB);
* :mod:`.parse` — Mitsuba's loader: its variant and log handled while it reads the file
  (``MitsubaSession``), and what it built read into numpy;
* :mod:`.emitters` — ``area`` emitters with a uniform radiance, one-sided; an envmap or
  constant emitter as the scene's environment; point, spot and directional lights;
* :mod:`.shapes` — every shape as triangles wound around Mitsuba's front side: triangle
  meshes as Mitsuba holds them; ``rectangle`` as two; ``sphere`` as an analytic sphere
  (or, with the receivers file's ``tessellate = true``, tessellated); ``disk`` and
  ``cylinder`` tessellated to keep their area (``TESSELLATION_ERROR``);
* :mod:`.materials` — each shape's BSDF: ``diffuse`` → lambert, ``roughconductor`` →
  roughconductor, ``roughplastic`` → roughplastic, alone or inside ``twosided``.  A
  shape with any other BSDF is an occluder only: it blocks shadow rays, as every shape
  does in Mitsuba's ``direct`` integrator (its ``ray_test`` reads no BSDF: glass, a
  ``null`` BSDF and a ``mask`` of any opacity block alike), and a receiver on it is an
  error, raised only then; a camera pixel that sees it is masked;
* :mod:`.sensors` — the first sensor: the default viewer of the receivers, or the
  camera of an image;
* :mod:`.receivers` (with :mod:`.surfaces`, points on triangles) — a TOML file beside
  the XML (``<stem>.receivers.toml``; docs/mitsuba-scenes.md) lists points on the
  scene's surfaces, or grids over planar shapes, and where the viewer is; or a camera's
  pixels are the receivers.  A receiver takes the BSDF of the shape it lies on; a
  texture on its reflectance (or a roughconductor's alpha) is evaluated by Mitsuba at
  the receiver's own surface point, a constant per receiver.

Anything warpis cannot represent exactly as Mitsuba means it is refused with a one-line
:class:`~warpis.errors.WarpisError` naming the file, the element and what is supported.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import fail
from ..camera import image_side
from ..description import Scene, assemble_scene
from .channels import CHANNEL_WORDS, CHANNELS, DEFAULT_CHANNEL, check_channel
from .emitters import DELTA_KINDS, SUPPORTED_EMITTERS, delta_notes, read_delta_lights, read_environment
from .materials import NONE_ETA, SUPPORTED_BSDFS
from .parse import MitsubaSession, is_grey
from .receivers import ON_SURFACE, camera_receivers, file_receivers, read_receivers_file, receivers_path
from .sensors import first_camera, first_viewer
from ..spheres import SPHERE_SUBDIVISIONS
from .shapes import (CYLINDER_SEGMENTS, DISK_SEGMENTS, SUPPORTED_SHAPES, TESSELLATION_ERROR, concatenate_shapes,
                     read_shapes, shape_spheres)

__all__ = ["CHANNELS", "CYLINDER_SEGMENTS", "DEFAULT_CHANNEL", "DISK_SEGMENTS", "NONE_ETA", "ON_SURFACE",
           "SPHERE_SUBDIVISIONS", "SUPPORTED_BSDFS", "SUPPORTED_EMITTERS", "SUPPORTED_SHAPES", "TESSELLATION_ERROR",
           "check_channel", "load_mitsuba", "receivers_path"]


def load_mitsuba(file: Path, device: str = "cpu", channel: str | None = None, receivers: Path | None = None,
                 camera: bool = False, width: int | None = None, height: int | None = None) -> Scene:
    """The scene of the Mitsuba 3 XML file ``file`` (docs/mitsuba-scenes.md).

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
    side = read_receivers_file(sidecar, file, receivers_needed=not camera)
    channel = channel if channel is not None else side["channel"] or DEFAULT_CHANNEL
    weights = np.array(CHANNELS[channel])
    with MitsubaSession(file) as session:
        scene = session.load()
        environment = read_environment(session.mi, scene, file, weights)
        delta_emitters = [e for e in scene.emitters() if e.class_name() in DELTA_KINDS]
        shapes = read_shapes(session, scene, file, weights, lit=environment is not None or bool(delta_emitters),
                             tessellate=side["tessellate"])
        sensor = first_viewer(session.mi, scene)
        lens = first_camera(session.mi, scene, file, width, height) if camera else None
        notes = [f"colour channel {channel}: {CHANNEL_WORDS[channel]}"]
        notes += session.warnings()
    label = {i: s.label for i, s in enumerate(shapes)}
    vertices, triangles, emission, owner = concatenate_shapes(shapes)
    spheres = shape_spheres(shapes)
    if not len(triangles):
        raise fail(file, "the scene has no triangle shape: warpis needs at least one mesh, rectangle, disk or "
                         "cylinder beside its spheres (or tessellate = true in the receivers file)")
    if lens is not None:
        rx, receiver_notes, under = camera_receivers(lens, shapes, vertices, triangles, emission, owner, file,
                                                     str(device), scene, spheres)
    else:
        rx, receiver_notes, under = file_receivers(side, shapes, vertices, triangles, owner, sensor, file, sidecar,
                                                   scene, spheres)
    delta = None
    if delta_emitters:
        with session:
            delta = read_delta_lights(session.mi, delta_emitters, rx.positions, file, weights)
    coloured_light = (any(s.radiance is not None and not is_grey(s.radiance) for s in shapes)
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
        notes += delta_notes(delta)
    notes += receiver_notes
    name = side["name"] or (file.parent.name if file.name == "scene.xml" else file.stem)
    hint = (f"give some <shape> an <emitter type=\"area\">, or the scene an envmap or constant emitter, with a "
            f"radiance > 0 in channel {channel}")
    return assemble_scene(file, lambda m: f"{file}: shape {label[m]!r}", hint, name=name, vertices=vertices,
                     triangles=triangles, emission=emission, receivers=rx, triangle_mesh=owner,
                     mesh_names=[s.label for s in shapes], description=side["description"], device=str(device),
                     path=file, notes=tuple(notes), environment=environment, delta_lights=delta, spheres=spheres)
