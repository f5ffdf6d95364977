"""The TOML scene source: a scene file → :class:`~warpis.scenes.description.Scene`.

A scene file lists meshes in any format trimesh reads, each with an optional transform
and an optional one-sided ``emission``, receivers (explicit points or grids, in one or
several groups) and the material at the receivers (docs/scene-files.md).  It
produces its arrays and hands them to the same gate as :meth:`Scene.from_arrays`.
"""

from __future__ import annotations

import io
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import trimesh

from .. import limits
from ..errors import WarpisError, fail
from ..vocabulary import DISTRIBUTIONS, MATERIALS
from .camera import Camera, camera_receiver_fields, cast_camera
from .description import (MICROFACET_DEFAULTS, MIN_ALPHA, Receivers, Scene, assemble_scene, checked_coordinates, check_receiver_count,
                          checked_unit, grey_microfacet)
from .spheres import Spheres, tessellate_sphere


def check_keys(table: dict, allowed: set[str], where: str, file: Path) -> None:
    """Refuse, naming them, the keys of ``table`` outside ``allowed`` (a typo is never ignored)."""
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise fail(file, f"unknown key {unknown[0]!r} in {where} (allowed: {', '.join(sorted(allowed))})")

def required_key(table: dict, key: str, where: str, file: Path) -> Any:
    """``table[key]``, or a one-line error naming the missing key and its table."""
    if key not in table:
        raise fail(file, f"missing key {key!r} in {where}")
    return table[key]

def _number(value: Any, what: str, file: Path) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise fail(file, f"{what} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise fail(file, f"{what} must be finite, got {value!r}")
    return float(value)

def toml_vector(value: Any, what: str, file: Path, length: int = 3) -> np.ndarray:
    """A list of ``length`` finite numbers as a float64 array, or a one-line error."""
    if not isinstance(value, list) or len(value) != length:
        raise fail(file, f"{what} must be a list of {length} numbers, got {value!r}")
    return np.array([_number(v, what, file) for v in value], dtype=np.float64)

def toml_vectors(value: Any, what: str, file: Path) -> np.ndarray:
    """A non-empty list of [x, y, z] points as an (N, 3) float64 array, or a one-line error."""
    if not isinstance(value, list) or not value:
        raise fail(file, f"{what} must be a non-empty list of [x, y, z] points")
    return np.array([toml_vector(v, what, file) for v in value], dtype=np.float64).reshape(-1, 3)

def _float32(value: float, what: str, file: Path) -> float:
    """A value >= 0 in the float32 kernels' range (see limits.float32_value)."""
    try:
        return limits.float32_value(value, what)
    except WarpisError as exc:
        raise fail(file, str(exc)) from None

def rotation_matrix(axis: np.ndarray, degrees: float) -> np.ndarray:
    """Right-handed rotation by ``degrees`` about ``axis`` (Rodrigues' formula)."""
    k = axis / np.linalg.norm(axis)
    a = math.radians(degrees)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(a) * kx + (1 - math.cos(a)) * kx @ kx

def _transform(spec: Any, where: str, file: Path) -> np.ndarray:
    """A [[mesh]] transform table → 4×4 matrix: scale, then rotate, then translate."""
    if not isinstance(spec, dict):
        raise fail(file, f"{where}.transform must be a table")
    check_keys(spec, {"translate", "scale", "rotate"}, f"{where}.transform", file)
    scale = spec.get("scale", 1.0)
    if isinstance(scale, list):
        s = toml_vector(scale, f"{where}.transform.scale", file)
    else:
        s = np.full(3, _number(scale, f"{where}.transform.scale", file))
    if np.any(s == 0):
        raise fail(file, f"{where}.transform.scale must not be zero")
    r = np.eye(3)
    if "rotate" in spec:
        rot = spec["rotate"]
        if not isinstance(rot, dict):
            raise fail(file, f"{where}.transform.rotate must be a table with axis and degrees")
        check_keys(rot, {"axis", "degrees"}, f"{where}.transform.rotate", file)
        axis = toml_vector(required_key(rot, "axis", f"{where}.transform.rotate", file), f"{where}.transform.rotate.axis", file)
        checked_unit(axis, f"{where}.transform.rotate.axis", file)
        degrees = _number(required_key(rot, "degrees", f"{where}.transform.rotate", file), f"{where}.transform.rotate.degrees", file)
        r = rotation_matrix(axis, degrees)
    t = toml_vector(spec.get("translate", [0, 0, 0]), f"{where}.transform.translate", file)
    m = np.eye(4)
    m[:3, :3] = r @ np.diag(s)
    m[:3, 3] = t
    return m


# Text formats whose loaders decode the file: trimesh guesses a non-UTF-8 encoding with
# the optional charset_normalizer, so warpis decodes them itself (UTF-8, else Latin-1,
# which accepts any byte; only comments and names can hold such bytes).

_TEXT_FORMATS = {".obj", ".off"}

def _trimesh_load(path: Path) -> Any:
    if path.suffix.lower() not in _TEXT_FORMATS:
        return trimesh.load(str(path), force="mesh", process=False)
    raw = path.read_bytes()
    try:
        raw.decode("utf-8")
    except UnicodeDecodeError:
        raw = raw.decode("latin-1").encode("utf-8")
    return trimesh.load(io.BytesIO(raw), file_type=path.suffix[1:].lower(), force="mesh", process=False)

def _read_mesh(path: Path, scene_file: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of a mesh file, exactly as written (no vertex merging)."""
    if not path.is_file():
        raise fail(path, f"mesh file not found (named in {scene_file})")
    try:
        loaded = _trimesh_load(path)
    except OSError as exc:
        raise fail(path, f"cannot read: {exc.strerror or exc}") from None
    except Exception as exc:  # trimesh raises many types for unparsable files
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise fail(path, f"trimesh cannot read this mesh: {reason}") from None
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64)
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64)
    if faces.ndim != 2 or len(faces) == 0:
        raise fail(path, "mesh has no triangles (or trimesh cannot read it as a triangle mesh)")
    if not np.all(np.isfinite(vertices)):
        bad = int(np.argmax(~np.all(np.isfinite(vertices), axis=1)))
        raise fail(path, f"vertex {bad} is NaN or infinite")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise fail(path, "a face refers to a vertex that does not exist")
    return vertices, faces

def _file_normals(path: Path, vertices: np.ndarray) -> np.ndarray | None:
    """The vertex normals an OBJ (``vn``) or PLY (nx, ny, nz) file carries, one per vertex
    of ``vertices`` as trimesh read them, else None (trimesh's mesh loader drops them, so
    its format readers are asked; a file whose normals do not line up with its vertices
    is an error rather than a mesh shaded flat)."""
    suffix = path.suffix.lower()
    if suffix not in (".obj", ".ply"):
        return None
    try:
        with open(path, "rb") as fh:
            if suffix == ".ply":
                parts = [trimesh.exchange.ply.load_ply(fh)]
            else:
                raw = fh.read()
                try:
                    raw.decode("utf-8")
                except UnicodeDecodeError:
                    raw = raw.decode("latin-1").encode("utf-8")
                parts = list(trimesh.exchange.obj.load_obj(io.BytesIO(raw)).get("geometry", {}).values())
    except Exception:  # the mesh itself was read: a reader that fails here found no normals to give
        return None
    if not parts or any(part.get("vertex_normals") is None for part in parts):
        return None
    their_vertices = np.vstack([np.asarray(part["vertices"], np.float64) for part in parts])
    normals = np.vstack([np.asarray(part["vertex_normals"], np.float64) for part in parts])
    if their_vertices.shape != vertices.shape or not np.array_equal(their_vertices, vertices) \
            or normals.shape != vertices.shape:
        raise fail(path, "its vertex normals do not line up with its vertices as read: set vertex_normals = false "
                         "in its [[mesh]] to shade with the triangles' own normals")
    return normals


def _float32_number(value: Any, what: str, file: Path) -> float:
    return _float32(_number(value, what, file), what, file)

def _unit_vector(value: Any, what: str, file: Path) -> np.ndarray:
    return checked_unit(toml_vector(value, what, file), what, file)


# The keys a material table may hold (each material lists its own in MATERIALS (kernels/integrand.py)):
# how each is read, and its value for a material without it (or that leaves it out).

def _distribution(value: Any, what: str, file: Path) -> int:
    if value not in DISTRIBUTIONS:
        raise fail(file, f"{what} must be one of {', '.join(repr(d) for d in DISTRIBUTIONS)}, got {value!r}")
    return DISTRIBUTIONS[value]

def _boolean(value: Any, what: str, file: Path) -> int:
    if not isinstance(value, bool):
        raise fail(file, f"{what} must be true or false, got {value!r}")
    return int(value)

def _in_range(low: float, high: float, open_low: bool = False) -> Callable[[Any, str, Path], float]:
    def parse(value: Any, what: str, file: Path) -> float:
        x = _number(value, what, file)
        if not (low < x if open_low else low <= x) or x > high:
            raise fail(file, f"{what} must be in {'(' if open_low else '['}{low:g}, {high:g}], got {value!r}")
        return x
    return parse

MATERIAL_PARAMETERS: dict[str, tuple[Callable[[Any, str, Path], Any], Any]] = {
    "albedo": (_float32_number, 1.0),
    "exponent": (_float32_number, 1.0),
    "view": (_unit_vector, np.array([0.0, 0.0, 1.0])),
    # Microfacet materials (grey: the same in every colour channel; see kernels/shading.py).
    "alpha": (_in_range(MIN_ALPHA, 1e3), MICROFACET_DEFAULTS["alpha"]),
    "distribution": (_distribution, MICROFACET_DEFAULTS["distribution"]),
    "sample_visible": (_boolean, MICROFACET_DEFAULTS["sample_visible"]),
    "eta": (_in_range(0.0, 1e3, open_low=True), MICROFACET_DEFAULTS["eta"]),
    "k": (_in_range(0.0, 1e3), MICROFACET_DEFAULTS["k"]),
    "specular": (_in_range(0.0, 1e3), MICROFACET_DEFAULTS["specular"]),
}

def _material(spec: Any, where: str, file: Path, camera: bool = False) -> dict[str, Any]:
    """A material table; under a camera (``camera``) each pixel's view is its direction to
    the camera, so ``view`` is neither required nor allowed."""
    if not isinstance(spec, dict):
        raise fail(file, f"{where} must be a table")
    kind = required_key(spec, "type", where, file)
    if kind not in MATERIALS:
        raise fail(file, f"{where}.type {kind!r} is not one of {', '.join(MATERIALS)}")
    material = MATERIALS[kind]
    if camera and "view" in spec:
        raise fail(file, f"{where}.view: a camera gives each pixel its own view (towards the camera); remove it")
    check_keys(spec, {"type", *material.keys} - ({"view"} if camera else set()), where, file)
    out: dict[str, Any] = {"code": material.code}
    for key, (parse, default) in MATERIAL_PARAMETERS.items():
        if key in material.required and not (camera and key == "view"):
            out[key] = parse(required_key(spec, key, where, file), f"{where}.{key}", file)
        elif key in spec:
            out[key] = parse(spec[key], f"{where}.{key}", file)
        else:
            out[key] = default
    return out

def _grid_points(spec: Any, where: str, file: Path) -> tuple[np.ndarray, tuple[int, int], np.ndarray]:
    if not isinstance(spec, dict):
        raise fail(file, f"{where}.grid must be a table")
    check_keys(spec, {"origin", "edge_u", "edge_v", "resolution"}, f"{where}.grid", file)
    origin = toml_vector(required_key(spec, "origin", f"{where}.grid", file), f"{where}.grid.origin", file)
    eu = toml_vector(required_key(spec, "edge_u", f"{where}.grid", file), f"{where}.grid.edge_u", file)
    ev = toml_vector(required_key(spec, "edge_v", f"{where}.grid", file), f"{where}.grid.edge_v", file)
    res = required_key(spec, "resolution", f"{where}.grid", file)
    if (not isinstance(res, list) or len(res) != 2
            or not all(isinstance(r, int) and not isinstance(r, bool) for r in res)):
        raise fail(file, f"{where}.grid.resolution must be two integers, got {res!r}")
    nu, nv = res
    if nu < 1 or nv < 1:
        raise fail(file, f"{where}.grid.resolution must be at least [1, 1], got {res!r}")
    check_receiver_count(nu * nv, f"{where}.grid.resolution {res!r}", file)
    cross = np.cross(eu, ev)
    # Relative to the edges' own lengths: a grid's size is the user's choice of units.
    if not np.linalg.norm(cross) > 1e-12 * np.linalg.norm(eu) * np.linalg.norm(ev):
        raise fail(file, f"{where}.grid edges are parallel or zero")
    # Cell centres, row-major over (v, u) so that reshape(nv, nu) is an image.
    su = (np.arange(nu) + 0.5) / nu
    sv = (np.arange(nv) + 0.5) / nv
    pts = origin + sv[:, None, None] * ev + su[None, :, None] * eu
    return pts.reshape(-1, 3), (nv, nu), cross / np.linalg.norm(cross)


# Bytes a receiver costs while a scene loads (float64 numpy arrays, their float32 Warp
# copies, the slab and the light table's row headers), for the memory check up front.

def _receiver_group(spec: Any, where: str, file: Path, default_material: dict | None) -> dict[str, Any]:
    if not isinstance(spec, dict):
        raise fail(file, f"{where} must be a table")
    check_keys(spec, {"points", "grid", "normal", "normals", "name", "material"}, where, file)
    if ("points" in spec) == ("grid" in spec):
        raise fail(file, f"{where} needs exactly one of 'points' or 'grid'")
    grid_shape = None
    if "points" in spec:
        points = toml_vectors(spec["points"], f"{where}.points", file)
        default_normal = None
    else:
        points, grid_shape, default_normal = _grid_points(spec["grid"], where, file)
    if "normal" in spec and "normals" in spec:
        raise fail(file, f"{where} has both 'normal' and 'normals'")
    if "normals" in spec:
        normals = toml_vectors(spec["normals"], f"{where}.normals", file)
        if len(normals) != len(points):
            raise fail(file, f"{where}.normals has {len(normals)} entries for {len(points)} points")
    elif "normal" in spec:
        normals = np.tile(toml_vector(spec["normal"], f"{where}.normal", file), (len(points), 1))
    elif default_normal is not None:
        normals = np.tile(default_normal, (len(points), 1))
    else:
        raise fail(file, f"{where} needs 'normal' or 'normals'")
    normals = checked_unit(normals, f"{where} normal", file)
    if "material" in spec:
        material = _material(spec["material"], f"{where}.material", file)
    elif default_material is not None:
        material = default_material
    else:
        raise fail(file, f"{where} has no material and the scene has no [material] table")
    name = spec.get("name", where)
    if not isinstance(name, str):
        raise fail(file, f"{where}.name must be a string")
    checked_coordinates(points, f"{where} receivers", file)
    return {"points": points, "normals": normals, "material": material, "name": name, "grid": grid_shape}

def _receivers(doc: dict, file: Path) -> Receivers:
    default = _material(doc["material"], "[material]", file) if "material" in doc else None
    spec = required_key(doc, "receivers", "the scene", file)
    groups_spec = spec if isinstance(spec, list) else [spec]
    if not groups_spec:
        raise fail(file, "[[receivers]] is empty")
    groups = [
        _receiver_group(g, "[receivers]" if len(groups_spec) == 1 else f"[[receivers]] #{i + 1}", file, default)
        for i, g in enumerate(groups_spec)
    ]
    count = [len(g["points"]) for g in groups]
    check_receiver_count(sum(count), "[[receivers]]", file)
    microfacet = [grey_microfacet(g["material"], np.full(c, g["material"]["albedo"]), c, file)
                  for g, c in zip(groups, count)]
    return Receivers(
        positions=np.vstack([g["points"] for g in groups]),
        normals=np.vstack([g["normals"] for g in groups]),
        material=np.concatenate([np.full(c, g["material"]["code"], np.int32) for g, c in zip(groups, count)]),
        albedo=np.concatenate([np.full(c, g["material"]["albedo"]) for g, c in zip(groups, count)]),
        exponent=np.concatenate([np.full(c, g["material"]["exponent"]) for g, c in zip(groups, count)]),
        view=np.vstack([np.tile(g["material"]["view"], (c, 1)) for g, c in zip(groups, count)]),
        group=np.concatenate([np.full(c, i, np.int32) for i, c in enumerate(count)]),
        group_names=[g["name"] for g in groups],
        grid_shape=groups[0]["grid"] if len(groups) == 1 else None,
        **{name: np.concatenate([m[name] for m in microfacet]) for name in microfacet[0]},
    )

def read_toml(file: Path) -> dict:
    """Parse a TOML file (scene or study); any unreadable file is a one-line WarpisError."""
    try:
        with open(file, "rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise fail(file, f"not valid TOML: {exc}") from None
    except UnicodeDecodeError as exc:
        raise fail(file, f"not valid TOML: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except RecursionError:
        raise fail(file, "not valid TOML: nested too deeply") from None
    except IsADirectoryError:
        raise fail(file, "is a directory, not a TOML file") from None
    except OSError as exc:
        raise fail(file, f"cannot read: {exc.strerror}") from None

@dataclass(frozen=True)
class _Meshes:
    """The scene's [[mesh]] tables, concatenated; ``surfaces``: each mesh's material row for a camera (or None)."""

    vertices: np.ndarray
    triangles: np.ndarray
    emission: np.ndarray
    owner: np.ndarray
    paths: list[str]
    surfaces: list[dict[str, Any] | None]
    # (T, 3, 3) the normal a camera pixel shades with at each triangle's corner: a mesh's
    # file vertex normals, else the triangle's own; None when no mesh has any.
    corner_normals: np.ndarray | None = None


def _surface(spec: Any, where: str, file: Path) -> dict[str, Any]:
    """A [[mesh]] material as the receiver arrays its camera pixels take (camera.SURFACE_FIELDS)."""
    return _surface_row(_material(spec, where, file, camera=True), file)


def _surface_row(material: dict[str, Any], file: Path) -> dict[str, Any]:
    microfacet = grey_microfacet(material, np.array([material["albedo"]]), 1, file)
    return {"material": material["code"], "albedo": material["albedo"], "exponent": material["exponent"],
            **{name: value[0] for name, value in microfacet.items()}}


def _meshes(doc: dict, file: Path, shading: bool = False) -> _Meshes:
    """The [[mesh]] tables; with ``shading`` (a camera's receivers shade), also the vertex
    normals their files carry."""
    entries = required_key(doc, "mesh", "the scene", file)
    if not isinstance(entries, list) or not entries:
        raise fail(file, "the scene needs at least one [[mesh]]")
    vertices, triangles, emission, owner, paths, surfaces, normals = [], [], [], [], [], [], []
    offset = 0
    for i, entry in enumerate(entries):
        where = f"[[mesh]] #{i + 1}"
        if not isinstance(entry, dict):
            raise fail(file, f"{where} must be a table")
        check_keys(entry, {"path", "emission", "transform", "name", "material", "vertex_normals"}, where, file)
        rel = required_key(entry, "path", where, file)
        if not isinstance(rel, str):
            raise fail(file, f"{where}.path must be a string")
        radiance = entry.get("emission", 0.0)
        if isinstance(radiance, bool) or not isinstance(radiance, (int, float)):
            raise fail(file, f"{where} ({rel}): emission must be a finite number >= 0, got {radiance!r}")
        radiance = _float32(float(radiance), f"{where} ({rel}): emission", file)
        if not isinstance(entry.get("name", ""), str):
            raise fail(file, f"{where}.name must be a string, got {entry['name']!r}")
        smooth = entry.get("vertex_normals", True)
        if not isinstance(smooth, bool):
            raise fail(file, f"{where} ({rel}): vertex_normals must be true or false, got {smooth!r}")
        v, f = _read_mesh((file.parent / rel), file)
        n = _file_normals(file.parent / rel, v) if smooth and shading else None
        if "transform" in entry:
            m = _transform(entry["transform"], where, file)
            with np.errstate(over="ignore", invalid="ignore"):  # overflow is reported just below
                v = v @ m[:3, :3].T + m[:3, 3]
                n = None if n is None else n @ np.linalg.inv(m[:3, :3])  # normals: the inverse transpose
        if n is not None:
            length = np.linalg.norm(n, axis=1)
            bad = ~(np.isfinite(length) & (length > 0))
            if bad.any():
                raise fail(file.parent / rel, f"vertex normal {int(np.argmax(bad))} is zero or not finite: fix it, "
                                              f"or set vertex_normals = false in its [[mesh]]")
            n = n / length[:, None]
        normals.append(n)
        checked_coordinates(v, f"{where} ({rel}) after its transform", file)
        vertices.append(v)
        triangles.append(f + offset)
        emission.append(np.full(len(f), float(radiance)))
        owner.append(np.full(len(f), i, np.int32))
        paths.append(rel)
        surfaces.append(_surface(entry["material"], f"{where}.material", file) if "material" in entry else None)
        offset += len(v)
    return _Meshes(np.vstack(vertices), np.vstack(triangles).astype(np.int32), np.concatenate(emission),
                   np.concatenate(owner), paths, surfaces, _corner_normals(vertices, triangles, normals))


_SPHERE_KEYS = {"center", "radius", "emission", "material", "name", "inward", "tessellate"}


def _spheres(doc: dict, file: Path, meshes: _Meshes) -> tuple[_Meshes, Spheres | None]:
    """The scene's [[sphere]] tables: analytic spheres (owners after the meshes), and the
    meshes with the triangles of those that ask to be tessellated (``tessellate = true``,
    for comparisons: the icosphere keeps the sphere's area, scenes/spheres.py)."""
    entries = doc.get("sphere", [])
    if not isinstance(entries, list):
        raise fail(file, "[[sphere]] must be an array of tables (write [[sphere]], not [sphere])")
    vertices, triangles = [meshes.vertices], [meshes.triangles]
    emission, owner = [meshes.emission], [meshes.owner]
    paths, surfaces = list(meshes.paths), list(meshes.surfaces)
    corners = [] if meshes.corner_normals is None else [meshes.corner_normals]
    rows: list[tuple[np.ndarray, float, float, int, int]] = []
    offset = len(meshes.vertices)
    flat_corners = meshes.corner_normals is None
    for i, entry in enumerate(entries):
        where = f"[[sphere]] #{i + 1}"
        if not isinstance(entry, dict):
            raise fail(file, f"{where} must be a table")
        check_keys(entry, _SPHERE_KEYS, where, file)
        center = toml_vector(required_key(entry, "center", where, file), f"{where}.center", file)
        radius = _number(required_key(entry, "radius", where, file), f"{where}.radius", file)
        if radius <= 0:
            raise fail(file, f"{where}.radius must be > 0, got {entry['radius']!r}")
        radiance = entry.get("emission", 0.0)
        if isinstance(radiance, bool) or not isinstance(radiance, (int, float)):
            raise fail(file, f"{where}: emission must be a finite number >= 0, got {radiance!r}")
        radiance = _float32(float(radiance), f"{where}: emission", file)
        name = entry.get("name", where)
        if not isinstance(name, str):
            raise fail(file, f"{where}.name must be a string, got {name!r}")
        inward = _boolean(entry.get("inward", False), f"{where}.inward", file)
        tessellate = _boolean(entry.get("tessellate", False), f"{where}.tessellate", file)
        checked_coordinates(np.array([np.abs(center) + radius]), f"{where} (centre + radius)", file)
        mesh = len(paths)
        paths.append(name)
        surfaces.append(_surface(entry["material"], f"{where}.material", file) if "material" in entry else None)
        if not tessellate:
            rows.append((center, radius, float(radiance), inward, mesh))
            continue
        v, f, _ = tessellate_sphere(center, radius, bool(inward))
        vertices.append(v)
        triangles.append(f + offset)
        emission.append(np.full(len(f), float(radiance)))
        owner.append(np.full(len(f), mesh, np.int32))
        radial = (v - center) / radius * (-1.0 if inward else 1.0)
        corners.append(radial[f])
        offset += len(v)
    if flat_corners and len(corners):  # the meshes' own normals beside the tessellations' radial ones
        t = meshes.vertices[meshes.triangles]
        own = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        with np.errstate(invalid="ignore", divide="ignore"):
            own /= np.linalg.norm(own, axis=1, keepdims=True)
        corners.insert(0, np.repeat(own[:, None, :], 3, axis=1))
    spheres = None
    if rows:
        spheres = Spheres(centers=np.array([r[0] for r in rows]), radii=np.array([r[1] for r in rows]),
                          emission=np.array([r[2] for r in rows]), inward=np.array([r[3] for r in rows], np.int32),
                          owner=np.array([r[4] for r in rows], np.int32))
    merged = _Meshes(np.vstack(vertices), np.vstack(triangles).astype(np.int32), np.concatenate(emission),
                     np.concatenate(owner), paths, surfaces, np.concatenate(corners) if corners else None)
    return merged, spheres


def _corner_normals(vertices: list[np.ndarray], triangles: list[np.ndarray], normals: list[np.ndarray | None]
                    ) -> np.ndarray | None:
    """(T, 3, 3) each triangle's corner normals: its mesh's vertex normals, else its own."""
    if all(n is None for n in normals):
        return None
    out, offset = [], 0
    for v, f, n in zip(vertices, triangles, normals):
        local = f - offset
        if n is None:
            t = v[local]
            own = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
            with np.errstate(invalid="ignore", divide="ignore"):
                own /= np.linalg.norm(own, axis=1, keepdims=True)
            out.append(np.repeat(own[:, None, :], 3, axis=1))
        else:
            out.append(n[local])
        offset += len(v)
    return np.concatenate(out)

def load_toml(file: Path, device: str = "cpu", width: int | None = None, height: int | None = None) -> Scene:
    """The scene of the TOML scene file ``file`` on Warp device ``device`` (docs/scene-files.md);
    ``width``/``height`` resize its camera (a scene with [receivers.camera])."""
    doc = read_toml(file)
    check_keys(doc, {"name", "description", "mesh", "sphere", "receivers", "material"}, "the top level", file)
    name = doc.get("name", file.parent.name if file.name == "scene.toml" else file.stem)
    if not isinstance(name, str):
        raise fail(file, "name must be a string")
    if not isinstance(doc.get("description", ""), str):
        raise fail(file, "description must be a string")
    camera = _camera_spec(doc, file)
    meshes, spheres = _spheres(doc, file, _meshes(doc, file, shading=camera is not None))
    notes: tuple[str, ...] = ()
    if camera is not None:
        receivers, notes = _camera_receivers(camera.resized(width, height, file), meshes, doc, file, str(device),
                                             spheres)
    elif width is not None or height is not None:
        raise fail(file, "has no camera to resize: a camera scene has [receivers.camera] (docs/images.md)")
    else:
        receivers = _receivers(doc, file)
    count = len(doc["mesh"])
    return assemble_scene(file, lambda m: file.parent / meshes.paths[m] if m < count else f"{file}: {meshes.paths[m]}",
                          "give some [[mesh]] or [[sphere]] an emission > 0", name=name,
                     vertices=meshes.vertices, triangles=meshes.triangles, emission=meshes.emission,
                     receivers=receivers, triangle_mesh=meshes.owner, mesh_names=meshes.paths,
                     description=str(doc.get("description", "")), device=str(device), path=file, notes=notes,
                     spheres=spheres)


_CAMERA_KEYS = {"position", "target", "up", "fov", "width", "height"}


def _camera_spec(doc: dict, file: Path) -> Camera | None:
    """The scene's [receivers.camera] (the only key of [receivers] then), or None."""
    spec = doc.get("receivers")
    if not isinstance(spec, dict) or "camera" not in spec:
        return None
    check_keys(spec, {"camera"}, "[receivers] (a camera's receivers are its pixels)", file)
    cam = spec["camera"]
    if not isinstance(cam, dict):
        raise fail(file, "[receivers.camera] must be a table")
    check_keys(cam, _CAMERA_KEYS, "[receivers.camera]", file)
    where = "[receivers.camera]"
    position = toml_vector(required_key(cam, "position", where, file), f"{where}.position", file)
    target = toml_vector(required_key(cam, "target", where, file), f"{where}.target", file)
    up = toml_vector(cam.get("up", [0.0, 0.0, 1.0]), f"{where}.up", file)
    fov = _number(required_key(cam, "fov", where, file), f"{where}.fov", file)
    width, height = required_key(cam, "width", where, file), required_key(cam, "height", where, file)
    return Camera.look_at(position, target, up, fov, width, height, file)


def _camera_receivers(camera: Camera, meshes: _Meshes, doc: dict, file: Path, device: str,
                      spheres: Spheres | None = None) -> tuple[Receivers, tuple[str, ...]]:
    """The camera's pixels as receivers: each takes its mesh's material, else the scene's [material]."""
    default = None
    if "material" in doc:
        default = _surface(doc["material"], "[material]", file)
    surfaces = [s if s is not None else default for s in meshes.surfaces]
    # TOML materials reflect on both sides: the normal is turned towards the camera.
    hits = cast_camera(camera, meshes.vertices, meshes.triangles, meshes.emission, meshes.owner,
                       [True] * len(meshes.paths), device, meshes.corner_normals, spheres=spheres)
    check_receiver_count(len(hits.positions), f"[receivers.camera] ({camera.width} × {camera.height})", file)

    def unmaterialled(m: int, pixels: int) -> str:
        what = f"[[mesh]] #{m + 1} ({meshes.paths[m]})" if m < len(doc["mesh"]) else meshes.paths[m]
        return (f"{what} is seen by {pixels} camera pixel(s) but has no material: "
                f"give it material = {{ type = ... }}, or give the scene a [material] table")

    rx = Receivers(**camera_receiver_fields(hits, surfaces, unmaterialled, file))
    return rx, (camera.describe(), hits.layout.describe()) + hits.notes
