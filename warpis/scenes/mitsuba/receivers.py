"""Receivers: the receivers file beside the XML (``<stem>.receivers.toml``;
docs/mitsuba-scenes.md), whose points lie on the scene's surfaces, or grids over planar
shapes, seen from a viewer (default: the XML's first sensor); or the pixels of a camera.
Each receiver takes the BSDF of the shape it lies on, Mitsuba's shading normal there, and
a textured parameter evaluated by Mitsuba at its own surface point (``_texture_values``),
a constant per receiver."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import WarpisError, fail
from ...vocabulary import MATERIALS
from ..camera import SURFACE_FIELDS, Camera, camera_receiver_fields, cast_camera
from ..description import MIN_ALPHA, Receivers, check_receiver_count, checked_coordinates, checked_unit
from ..normals import interpolate_normals
from ..toml_source import check_keys, read_toml, required_key, toml_vector, toml_vectors
from .channels import check_channel
from .materials import first_texture, texture_name
from .parse import MitsubaSession, is_grey, to_rgb, vector_text
from .sensors import Viewer
from ..spheres import Spheres, sphere_points
from .shapes import Shape
from .surfaces import locate, nearest_distance, planar_grid

# A receiver lies on a triangle when it is within this fraction of the scene's bounding
# box diagonal (float32 vertices, numbers written with a few digits), plus how far an
# analytic shape's tessellation strays from it.
ON_SURFACE = 1e-5


# ----------------------------------------------------------------------------- receivers file


def receivers_path(file: Path) -> Path:
    """The default receivers file of the Mitsuba scene ``file``: ``<stem>.receivers.toml`` beside it."""
    return file.with_name(file.stem + ".receivers.toml")


_SIDECAR_KEYS = {"name", "description", "channel", "view", "receivers", "tessellate"}
_GROUP_KEYS = {"name", "points", "normal", "normals", "view", "grid"}
_GRID_KEYS = {"shape", "resolution"}


def read_receivers_file(sidecar: Path, file: Path, receivers_needed: bool = True) -> dict[str, Any]:
    """The receivers file, checked for its keys and their types (a camera's receivers are
    its pixels: then the file may be missing and its receivers are not read)."""
    if not receivers_needed and not sidecar.is_file():
        return {"name": None, "description": "", "channel": None, "view": None, "groups": [], "tessellate": False}
    if not sidecar.is_file():
        raise fail(file, f"its receivers file {sidecar} does not exist: write one with [[receivers]] tables of "
                         f"points = [[x, y, z], ...] on the scene's surfaces, or grid = {{ shape = \"<id>\", "
                         f"resolution = [nu, nv] }} (docs/mitsuba-scenes.md)")
    doc = read_toml(sidecar)
    check_keys(doc, _SIDECAR_KEYS, "the top level", sidecar)
    for key in ("name", "description", "channel"):
        if key in doc and not isinstance(doc[key], str):
            raise fail(sidecar, f"{key} must be a string, got {doc[key]!r}")
    if "channel" in doc:
        check_channel(doc["channel"], sidecar)
    view = toml_vector(doc["view"], "view", sidecar) if "view" in doc else None
    tessellate = doc.get("tessellate", False)
    if not isinstance(tessellate, bool):
        raise fail(sidecar, f"tessellate must be true or false, got {tessellate!r}")
    if not receivers_needed:
        return {"name": doc.get("name"), "description": doc.get("description", ""), "channel": doc.get("channel"),
                "view": view, "groups": [], "tessellate": tessellate}
    spec = required_key(doc, "receivers", "the top level", sidecar)
    specs = spec if isinstance(spec, list) else [spec]
    if not specs:
        raise fail(sidecar, "[[receivers]] is empty")
    groups = [_group(g, "[receivers]" if len(specs) == 1 else f"[[receivers]] #{i + 1}", sidecar)
              for i, g in enumerate(specs)]
    return {"name": doc.get("name"), "description": doc.get("description", ""), "channel": doc.get("channel"),
            "view": view, "groups": groups, "tessellate": tessellate}


def _group(spec: Any, where: str, sidecar: Path) -> dict[str, Any]:
    if not isinstance(spec, dict):
        raise fail(sidecar, f"{where} must be a table")
    check_keys(spec, _GROUP_KEYS, where, sidecar)
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
        group["points"] = toml_vectors(spec["points"], f"{where}.points", sidecar)
        checked_coordinates(group["points"], f"{where}.points", sidecar)
        check_receiver_count(len(group["points"]), f"{where}.points", sidecar)
    else:
        grid = spec["grid"]
        if not isinstance(grid, dict):
            raise fail(sidecar, f"{where}.grid must be a table {{ shape = \"<id>\", resolution = [nu, nv] }}")
        check_keys(grid, _GRID_KEYS, f"{where}.grid", sidecar)
        shape = required_key(grid, "shape", f"{where}.grid", sidecar)
        if not isinstance(shape, str):
            raise fail(sidecar, f"{where}.grid.shape must be a shape's id (a string), got {shape!r}")
        res = required_key(grid, "resolution", f"{where}.grid", sidecar)
        if (not isinstance(res, list) or len(res) != 2
                or not all(isinstance(r, int) and not isinstance(r, bool) for r in res)):
            raise fail(sidecar, f"{where}.grid.resolution must be two integers [nu, nv], got {res!r}")
        if res[0] < 1 or res[1] < 1:
            raise fail(sidecar, f"{where}.grid.resolution must be at least [1, 1], got {res!r}")
        check_receiver_count(res[0] * res[1], f"{where}.grid.resolution {res!r}", sidecar)
        group["grid"] = (shape, int(res[0]), int(res[1]))
    if "normals" in spec:
        if "grid" in spec:
            raise fail(sidecar, f"{where}: a grid takes one 'normal', not 'normals'")
        normals = toml_vectors(spec["normals"], f"{where}.normals", sidecar)
        if len(normals) != len(group["points"]):
            raise fail(sidecar, f"{where}.normals has {len(normals)} entries for {len(group['points'])} points")
        group["normals"] = checked_unit(normals, f"{where}.normals", sidecar)
    elif "normal" in spec:
        group["normal"] = checked_unit(toml_vector(spec["normal"], f"{where}.normal", sidecar), f"{where}.normal", sidecar)
    if "view" in spec:
        group["view"] = toml_vector(spec["view"], f"{where}.view", sidecar)
    return group


# ----------------------------------------------------------------------------- receivers on surfaces


def file_receivers(side: dict[str, Any], shapes: list[Shape], vertices: np.ndarray, triangles: np.ndarray,
                   owner: np.ndarray, sensor: Viewer | str | None, file: Path, sidecar: Path,
                   mitsuba_scene: Any = None, spheres: Spheres | None = None
                   ) -> tuple[Receivers, list[str], np.ndarray]:
    """The receivers of the receivers file on the scene's surfaces (triangles, and the
    analytic ``spheres``, on which a point is moved radially onto the exact surface),
    notes about them, and the shapes they lie on (``mitsuba_scene``: Mitsuba's, which
    evaluates textures)."""
    tris = vertices[triangles]
    cross = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        front = cross / np.linalg.norm(cross, axis=1, keepdims=True)
    base = ON_SURFACE * _diagonal(vertices, spheres)
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

            index, closest = locate(points, tris, tol, base, rank)
            ball, closest = _on_spheres(spheres, points, index, closest, base)
            missing = np.flatnonzero((index < 0) & (ball < 0))
            if len(missing):
                i = int(missing[0])
                d = float(nearest_distance(points[i:i + 1], tris)[0])
                if spheres is not None:
                    d = min(d, float(spheres.surface_distance(points[i:i + 1]).min()))
                raise fail(sidecar, f"{where} point {i} {vector_text(points[i])} lies on no surface of {file.name}: "
                                    f"the nearest is {d:.3g} away (tolerance {base:.3g})"
                                    + (f"; {len(missing) - 1} more point(s) too" if len(missing) > 1 else ""))
            on_ball = ball >= 0
            index[on_ball] = -1
            shape_of = np.where(on_ball, -1 if spheres is None else spheres.owner[np.maximum(ball, 0)], owner[index])
            normals_front = front[index]
            if on_ball.any():
                normals_front[on_ball] = spheres.normals_at(ball[on_ball], closest[on_ball])
            moved = np.linalg.norm(closest - points, axis=1)
            analytic = np.array([shapes[k].deviation > 0 for k in shape_of])
            if analytic.any() and moved[analytic].max() > base:
                notes.append(f"{where}: {int((moved[analytic] > base).sum())} point(s) moved onto the "
                             f"tessellation of an analytic shape, by at most {moved[analytic].max():.3g}")
            points = closest
        else:
            points, k, n, shape_rc = planar_grid(group, shapes, base, sidecar, file)
            mine = np.flatnonzero(owner == k)
            index, closest = locate(points, tris[mine], tol[mine], base,
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
            raise fail(sidecar, f"{where} point {i} {vector_text(points[i])} lies on shape "
                                f"{shapes[shape_of[i]].label!r}, an emitter: receivers must lie on surfaces that do not "
                                f"emit")
        _check_shaded(shapes, shape_of, points, f"{where} in {sidecar.name}")
        one_sided = ~np.array([s.material.twosided for s in shapes])[shape_of]
        if (one_sided & ~facing).any():
            i = int(np.argmax(one_sided & ~facing))
            s = shapes[shape_of[i]]
            raise fail(sidecar, f"{where} point {i} {vector_text(points[i])}: the viewer ({viewer.what}) is behind "
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
            raise fail(sidecar, f"{where} point {i} {vector_text(points[i])}: the viewer ({viewer.what}) is behind its "
                                f"normal {vector_text(normals[i])}")
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
    check_receiver_count(len(shape_of), "[[receivers]]", sidecar)
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


def _diagonal(vertices: np.ndarray, spheres: Spheres | None) -> float:
    """The diagonal of the box around the scene's vertices and analytic spheres."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    if spheres is not None:
        lo = np.minimum(lo, (spheres.centers - spheres.radii[:, None]).min(axis=0))
        hi = np.maximum(hi, (spheres.centers + spheres.radii[:, None]).max(axis=0))
    return float(np.linalg.norm(hi - lo))


def _on_spheres(spheres: Spheres | None, points: np.ndarray, index: np.ndarray, closest: np.ndarray, base: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """The analytic sphere each point lies on (within ``base`` of its surface and no
    farther than the triangle ``locate`` found), −1 elsewhere, and the points with those
    moved radially onto their sphere."""
    ball = np.full(len(points), -1, np.int64)
    if spheres is None:
        return ball, closest
    dist = spheres.surface_distance(points)
    nearest = np.argmin(dist, axis=1)
    d = dist[np.arange(len(points)), nearest]
    to_triangle = np.where(index >= 0, np.linalg.norm(closest - points, axis=1), np.inf)
    take = (d <= base) & (d <= to_triangle)
    ball[take] = nearest[take]
    closest = closest.copy()
    closest[take] = sphere_points(spheres, nearest[take], points[take])
    return ball, closest


def _group_viewer(group: dict[str, Any], side: dict[str, Any], sensor: Viewer | str | None, where: str,
                  file: Path, sidecar: Path) -> Viewer:
    if group["view"] is not None:
        return Viewer(f"{where}.view {vector_text(group['view'])}", position=group["view"])
    if side["view"] is not None:
        return Viewer(f"view {vector_text(side['view'])}", position=side["view"])
    if isinstance(sensor, Viewer):
        return sensor
    why = f"{file.name} has no <sensor>" if sensor is None else f"in {file.name}, {sensor}"
    raise fail(sidecar, f"{where}: no viewer: {why}; give view = [x, y, z] (the viewer's position) at the top "
                        f"level or in the group")


def _check_shaded(shapes: list[Shape], shape_of: np.ndarray, points: np.ndarray, where: str) -> None:
    """A receiver on a shape whose BSDF warpis cannot shade raises that shape's error."""
    for k in np.unique(shape_of):
        if shapes[k].material.problem:
            i = int(np.argmax(shape_of == k))
            raise WarpisError(f"{shapes[k].material.problem}; point {i} {vector_text(points[i])} of {where} lies on it")


def _shading_normals(where: str, shapes: list[Shape], shape_of: np.ndarray, index: np.ndarray, points: np.ndarray,
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
            raise fail(where, f"point {i} {vector_text(points[i])}: the vertex normals of shape {shapes[k].label!r} "
                              f"cancel there, so Mitsuba has no shading normal")
        shading_normals[rows] = interpolated
        cosine = np.clip(np.einsum("ij,ij->i", interpolated, fronts[rows]), -1.0, 1.0)
        angle = np.degrees(np.arccos(cosine))
        if angle.max() > 0.01:
            notes.append(f"{where}: on shape {shapes[k].label!r}, receivers shade with Mitsuba's normals interpolated "
                         f"from its vertex normals, up to {angle.max():.3g}° from the triangles' own normals "
                         f"({int((angle > 0.01).sum())} of {len(rows)} receivers)")
    return shading_normals, notes


# ----------------------------------------------------------------------------- camera pixels


def _corner_normals(shapes: list[Shape], vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray | None:
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


def _analytic_pixels(hits: Any, shapes: list[Shape]) -> Any:
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


def camera_receivers(camera: Camera, shapes: list[Shape], vertices: np.ndarray, triangles: np.ndarray,
                     emission: np.ndarray, owner: np.ndarray, file: Path, device: str, mitsuba_scene: Any = None,
                     spheres: Spheres | None = None) -> tuple[Receivers, list[str], np.ndarray]:
    """The camera's pixels as receivers, each with the material of the shape it sees (a
    textured parameter evaluated by Mitsuba at the pixel's own point) and Mitsuba's
    shading normal there."""
    unshaded = [f"shape {s.label!r} ({s.material.unshaded})" if s.material.problem else None for s in shapes]
    hits = cast_camera(camera, vertices, triangles, emission, owner, [s.material.twosided for s in shapes], device,
                       _corner_normals(shapes, vertices, triangles), unshaded, spheres)
    hits = _analytic_pixels(hits, shapes)
    check_receiver_count(len(hits.positions), f"the camera ({camera.width} × {camera.height})", file)
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
    diagonal = _diagonal(vertices, spheres)
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


# ----------------------------------------------------------------------------- textures at receivers


def _texture_values(mitsuba_scene: Any, file: Path, shapes: list[Shape], shape_of: np.ndarray, faces: np.ndarray,
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
    with MitsubaSession(file) as session:
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
                    raise fail(where(r), f"Mitsuba finds no surface of shape {s.label!r} at {vector_text(p)} to "
                                         f"evaluate its BSDF's textures at")
                for name, textures in m.textures.items():
                    if name == "alpha":
                        alpha = [float(t.eval_1(si)) for t in textures]
                        if len(alpha) == 2 and alpha[0] != alpha[1]:
                            raise fail(where(r), f"shape {s.label!r}: roughconductor alpha_u={alpha[0]:.6g}, "
                                                 f"alpha_v={alpha[1]:.6g} at {vector_text(p)} (anisotropic); warpis "
                                                 f"supports an isotropic alpha only")
                        values[name].append(alpha[0])
                    else:
                        values[name].append(to_rgb(textures[0].eval(si)))
            for name, got in values.items():
                label = {"albedo": "diffuse reflectance", "specular": "specular reflectance", "alpha": "alpha"}[name]
                if name == "alpha":
                    v = np.array(got, np.float64)
                    bad = ~((v >= MIN_ALPHA) & (v <= 1e3))
                    domain = f"roughness in [{MIN_ALPHA:g}, 1000]"
                else:
                    rgb = np.array(got, np.float64)
                    if not all(is_grey(c) for c in rgb):
                        m.grey = False
                    v = rgb @ m.weights if name == "albedo" else rgb * m.weights
                    bad = ~np.all((rgb >= 0) & (rgb <= 1e3), axis=1)
                    domain = "reflectances in [0, 1000] in every channel"
                if bad.any():
                    i = int(rows[np.argmax(bad)])
                    value = got[int(np.argmax(bad))]
                    shown = f"{value:.6g}" if name == "alpha" else vector_text(value)
                    raise fail(where(i), f"shape {s.label!r}: its {label} texture is {shown} at "
                                         f"{vector_text(points[i])}; warpis supports {domain}")
                out.setdefault(name, ([], []))
                out[name][0].extend(rows.tolist())
                out[name][1].extend(list(v))
                shown = v if v.ndim == 1 else v.sum(axis=1)
                notes.append(f"{s.label}: {len(rows)} receiver(s) take its {label} from its "
                             f"{texture_name(first_texture(m.texture_text[name]))!r} texture at their own point "
                             f"(Mitsuba's eval there): {float(shown.min()):.6g} to {float(shown.max()):.6g}"
                             + (" in this channel" if name != "alpha" else ""))
    return {name: (np.array(r, np.int64), np.array(v, np.float64)) for name, (r, v) in out.items()}, notes
