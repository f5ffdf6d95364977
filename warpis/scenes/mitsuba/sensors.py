"""The scene's first sensor: where receivers are seen from (a :class:`Viewer`), or the
pinhole camera whose pixels are the receivers of an image."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import fail
from ..camera import Camera
from .parse import object_parameters, transform_matrix, vector_text

# Sensors whose rays start at their position, and the one whose rays are parallel.
_POINT_SENSORS = {"PerspectiveCamera", "ThinLensCamera", "RadianceMeter", "BatchSensor"}
_PARALLEL_SENSORS = {"OrthographicCamera"}
_SENSOR_PLUGINS = {"PerspectiveCamera": "perspective", "ThinLensCamera": "thinlens", "OrthographicCamera":
                   "orthographic", "RadianceMeter": "radiancemeter", "IrradianceMeter": "irradiancemeter",
                   "BatchSensor": "batch", "DistantSensor": "distant"}


@dataclass
class Viewer:
    """Where receivers are seen from: a position, or a direction (parallel rays)."""

    what: str
    position: np.ndarray | None = None
    direction: np.ndarray | None = None  # towards the viewer

    def towards(self, points: np.ndarray) -> np.ndarray:
        if self.direction is not None:
            return np.tile(self.direction, (len(points), 1))
        return self.position - points


def first_viewer(mi: Any, scene: Any) -> Viewer | str | None:
    """The first sensor as a viewer; a string says why it cannot be one; None: no sensor."""
    sensors = scene.sensors()
    if not sensors:
        return None
    sensor = sensors[0]
    cls = sensor.class_name()
    m = transform_matrix(sensor.world_transform())
    name = f"sensor {sensor.id()!r}" if sensor.id() else f"the first sensor ({cls})"
    if cls in _POINT_SENSORS:
        return Viewer(f"{name} at {vector_text(m[:3, 3])}", position=m[:3, 3].copy())
    if cls in _PARALLEL_SENSORS:
        forward = m[:3, 2] / np.linalg.norm(m[:3, 2])
        return Viewer(f"{name}, orthographic, looking along {vector_text(forward)}", direction=-forward)
    return f"{name} has no viewpoint"


def first_camera(mi: Any, scene: Any, file: Path, width: int | None, height: int | None) -> Camera:
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
    params = object_parameters(mi, sensor)
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
    m = transform_matrix(sensor.world_transform())
    frame = m[:3, :3]
    lengths = np.linalg.norm(frame, axis=0)
    if not (np.allclose(lengths, 1, atol=1e-5) and np.allclose(frame.T @ frame, np.eye(3), atol=1e-5)):
        raise fail(file, f"{name}: its to_world scales or shears ({vector_text(lengths)} column lengths); a camera's "
                         f"to_world must be a rotation (a mirror allowed) and a translation")
    # Mitsuba's camera space: +z forward, +y up, +x towards the image's left edge.
    fov = 2 * math.degrees(math.atan(math.tan(math.radians(float(params["x_fov"])) / 2) * h / w))
    return Camera.framed(m[:3, 3].copy(), frame[:, 2].copy(), frame[:, 1].copy(), -frame[:, 0], fov, w, h, file)
