"""Scene files (TOML) → one Warp mesh, emitter tables, receivers and their materials.

A scene file lists meshes in any format trimesh reads, each with an optional transform
and an optional one-sided ``emission``; receivers (explicit points or grids, in one or
several groups) and the material at the receivers.  See README.md ("Scene files") for
the format.  Everything is validated before any Warp array is made: bad input raises
:class:`~warpis.errors.WarpisError` with one line naming the file and the problem.
"""

from __future__ import annotations

import io
import math
import re
import tomllib
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
import warp as wp

from . import limits
from .errors import WarpisError, fail
from .vocabulary import MATERIALS, Material

# Emitter triangles whose area is below this fraction of their longest edge squared are
# needles: no float32 ray can hit them reliably nor can they be sampled with a finite pdf.
DEGENERATE_AREA = 1e-12
# Self-hit slab, relative to the float32 magnitude of the coordinates around a receiver:
# rays ignore surfaces within this height above the receiver's tangent plane (see
# integrand.py).  2^-16 is 128 float32 ulps: far above the rounding of Warp's watertight
# ray-triangle test, and second order in F (docs/theory.md, "The integrand at a receiver").
SELF_HIT_SLAB = 2.0**-16


@wp.struct
class SceneData:
    """Everything a kernel needs to cast rays and sample the emitters of a scene."""

    mesh: wp.uint64  # every triangle: emitters occlude too
    emitter_bvh: wp.uint64  # bounds of the emitter triangles, for light-sampling pdfs
    points: wp.array(dtype=wp.vec3)
    indices: wp.array(dtype=wp.int32)  # 3 per triangle, into points
    tri_emission: wp.array(dtype=wp.float32)  # radiance of each triangle's front face
    emitter_tri: wp.array(dtype=wp.int32)  # emitter k → triangle index in `mesh`
    emitter_area: wp.array(dtype=wp.float32)
    area_cdf: wp.array(dtype=wp.float32)  # E + 1 entries, 0 … 1
    power_cdf: wp.array(dtype=wp.float32)  # E + 1 entries, 0 … 1 (radiance × area)
    total_area: wp.float32
    total_power: wp.float32  # Σ radiance × area
    emitter_count: wp.int32


@wp.struct
class ReceiverData:
    """Receiver points, normals and the material of each."""

    position: wp.array(dtype=wp.vec3)
    normal: wp.array(dtype=wp.vec3)
    material: wp.array(dtype=wp.int32)  # vocabulary.MATERIALS code
    albedo: wp.array(dtype=wp.float32)
    exponent: wp.array(dtype=wp.float32)
    view: wp.array(dtype=wp.vec3)  # unit direction towards the viewer
    slab: wp.array(dtype=wp.float32)  # self-hit slab height above the tangent plane


@dataclass
class Receivers:
    """Receiver points with their normals and materials (numpy, float64)."""

    positions: np.ndarray  # (R, 3)
    normals: np.ndarray  # (R, 3), unit
    material: np.ndarray  # (R,) int, vocabulary.MATERIALS code
    albedo: np.ndarray  # (R,)
    exponent: np.ndarray  # (R,)
    view: np.ndarray  # (R, 3), unit
    group: np.ndarray  # (R,) int, index into group_names
    group_names: list[str] = field(default_factory=list)
    grid_shape: tuple[int, int] | None = None  # (rows, cols) when the only group is a grid

    def __len__(self) -> int:
        return len(self.positions)

    def material_of(self, index: int) -> Material:
        """The material of receiver ``index`` (its entry in ``vocabulary.MATERIALS``)."""
        return MATERIALS.by_code(self.material[index])

    def material_name(self, index: int) -> str:
        """The material type of receiver ``index`` as spelled in scene files."""
        return self.material_of(index).name


@dataclass
class Scene:
    """A loaded scene: geometry, emitters and receivers, in numpy and on a Warp device."""

    name: str
    path: Path
    device: str
    vertices: np.ndarray  # (V, 3) float64, transformed
    triangles: np.ndarray  # (T, 3) int32
    triangle_mesh: np.ndarray  # (T,) index of the [[mesh]] entry each triangle comes from
    mesh_paths: list[str]
    emission: np.ndarray  # (T,) radiance of each triangle's front face
    emitters: np.ndarray  # (E,) triangle index of each emitter triangle
    emitter_areas: np.ndarray  # (E,)
    receivers: Receivers
    description: str = ""
    slab: np.ndarray | None = None  # (R,) self-hit slab height of each receiver (see upload)
    data: Any = None  # SceneData on `device`
    receiver_data: Any = None  # ReceiverData on `device`
    _keep: list = field(default_factory=list, repr=False)  # Warp objects the structs point into

    @property
    def triangle_count(self) -> int:
        return len(self.triangles)

    @property
    def emitter_count(self) -> int:
        return len(self.emitters)

    @property
    def emitter_radiance(self) -> np.ndarray:
        return self.emission[self.emitters]

    @property
    def total_emitter_area(self) -> float:
        return float(self.emitter_areas.sum())

    @property
    def total_power(self) -> float:
        """Σ radiance × area over emitter triangles (radiant exitance would add a π)."""
        return float((self.emitter_radiance * self.emitter_areas).sum())

    def triangle_vertices(self, which: np.ndarray | None = None) -> np.ndarray:
        """Corner positions, (T, 3, 3), of all triangles or of the triangles ``which``."""
        tris = self.triangles if which is None else self.triangles[which]
        return self.vertices[tris]

    @property
    def diagonal(self) -> float:
        pts = np.vstack([self.vertices, self.receivers.positions])
        return float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))

    def summary(self) -> dict[str, Any]:
        """Counts and emitter totals, as printed by ``warpis scenes`` and ``warpis info``."""
        return {
            "scene": self.name,
            "path": str(self.path),
            "triangles": self.triangle_count,
            "emitter_triangles": self.emitter_count,
            "receivers": len(self.receivers),
            "emitter_area": self.total_emitter_area,
            "total_power": self.total_power,
        }


# --------------------------------------------------------------------------- bundled


def _bundled_root():
    """The installed ``warpis.meshes`` package, or ``meshes/`` beside a source checkout."""
    try:
        return resources.files("warpis.meshes")
    except ModuleNotFoundError:  # running from a checkout that was never pip-installed
        return Path(__file__).resolve().parent.parent / "meshes"


def bundled_scenes() -> list[str]:
    """Names of the scenes shipped in ``meshes/``."""
    root = _bundled_root()
    return sorted(p.name for p in root.iterdir() if p.is_dir() and (p / "scene.toml").is_file())


def resolve_scene_path(name_or_path: str | Path) -> Path:
    """A bundled scene's name or a path to a scene file → the scene file's path."""
    text = str(name_or_path)
    candidate = Path(text)
    if candidate.is_file():
        return candidate
    if candidate.is_dir() and (candidate / "scene.toml").is_file():
        return candidate / "scene.toml"
    bundled = _bundled_root() / text / "scene.toml"
    if "/" not in text and bundled.is_file():
        return Path(str(bundled))
    names = ", ".join(bundled_scenes())
    raise fail(text, f"no such scene file or bundled scene (bundled: {names})")


# --------------------------------------------------------------------------- TOML checks


def _check_keys(table: dict, allowed: set[str], where: str, file: Path) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise fail(file, f"unknown key {unknown[0]!r} in {where} (allowed: {', '.join(sorted(allowed))})")


def _require(table: dict, key: str, where: str, file: Path) -> Any:
    if key not in table:
        raise fail(file, f"missing key {key!r} in {where}")
    return table[key]


def _number(value: Any, what: str, file: Path) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise fail(file, f"{what} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise fail(file, f"{what} must be finite, got {value!r}")
    return float(value)


def _vector(value: Any, what: str, file: Path, length: int = 3) -> np.ndarray:
    if not isinstance(value, list) or len(value) != length:
        raise fail(file, f"{what} must be a list of {length} numbers, got {value!r}")
    return np.array([_number(v, what, file) for v in value], dtype=np.float64)


def _vectors(value: Any, what: str, file: Path) -> np.ndarray:
    if not isinstance(value, list) or not value:
        raise fail(file, f"{what} must be a non-empty list of [x, y, z] points")
    return np.array([_vector(v, what, file) for v in value], dtype=np.float64).reshape(-1, 3)


def _float32(value: float, what: str, file: Path) -> float:
    """A value >= 0 in the float32 kernels' range (see limits.float32_value)."""
    try:
        return limits.float32_value(value, what)
    except WarpisError as exc:
        raise fail(file, str(exc)) from None


def _coordinates(points: np.ndarray, what: str, file: Path) -> np.ndarray:
    """Points whose coordinates float32 kernels can hold and square (limits.coordinates)."""
    try:
        limits.coordinates(points, what)
    except WarpisError as exc:
        raise fail(file, str(exc)) from None
    return points


def _unit(v: np.ndarray, what: str, file: Path) -> np.ndarray:
    norms = np.linalg.norm(v, axis=-1, keepdims=True)
    if not np.all(norms > 0):
        raise fail(file, f"{what} has zero length")
    return v / norms


# --------------------------------------------------------------------------- meshes


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
    _check_keys(spec, {"translate", "scale", "rotate"}, f"{where}.transform", file)
    scale = spec.get("scale", 1.0)
    if isinstance(scale, list):
        s = _vector(scale, f"{where}.transform.scale", file)
    else:
        s = np.full(3, _number(scale, f"{where}.transform.scale", file))
    if np.any(s == 0):
        raise fail(file, f"{where}.transform.scale must not be zero")
    r = np.eye(3)
    if "rotate" in spec:
        rot = spec["rotate"]
        if not isinstance(rot, dict):
            raise fail(file, f"{where}.transform.rotate must be a table with axis and degrees")
        _check_keys(rot, {"axis", "degrees"}, f"{where}.transform.rotate", file)
        axis = _vector(_require(rot, "axis", f"{where}.transform.rotate", file), f"{where}.transform.rotate.axis", file)
        _unit(axis, f"{where}.transform.rotate.axis", file)
        degrees = _number(_require(rot, "degrees", f"{where}.transform.rotate", file), f"{where}.transform.rotate.degrees", file)
        r = rotation_matrix(axis, degrees)
    t = _vector(spec.get("translate", [0, 0, 0]), f"{where}.transform.translate", file)
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


def _triangle_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    v = vertices[triangles]
    return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)


# --------------------------------------------------------------------------- receivers & materials


def _float32_number(value: Any, what: str, file: Path) -> float:
    return _float32(_number(value, what, file), what, file)


def _unit_vector(value: Any, what: str, file: Path) -> np.ndarray:
    return _unit(_vector(value, what, file), what, file)


# The keys a material table may hold (each material lists its own in vocabulary.MATERIALS):
# how each is read, and its value for a material without it (or that leaves it out).
MATERIAL_PARAMETERS: dict[str, tuple[Callable[[Any, str, Path], Any], Any]] = {
    "albedo": (_float32_number, 1.0),
    "exponent": (_float32_number, 1.0),
    "view": (_unit_vector, np.array([0.0, 0.0, 1.0])),
}


def _material(spec: Any, where: str, file: Path) -> dict[str, Any]:
    if not isinstance(spec, dict):
        raise fail(file, f"{where} must be a table")
    kind = _require(spec, "type", where, file)
    if kind not in MATERIALS:
        raise fail(file, f"{where}.type {kind!r} is not one of {', '.join(MATERIALS)}")
    material = MATERIALS[kind]
    _check_keys(spec, {"type", *material.keys}, where, file)
    out: dict[str, Any] = {"code": material.code}
    for key, (parse, default) in MATERIAL_PARAMETERS.items():
        if key in material.required:
            out[key] = parse(_require(spec, key, where, file), f"{where}.{key}", file)
        elif key in spec:
            out[key] = parse(spec[key], f"{where}.{key}", file)
        else:
            out[key] = default
    return out


def _grid_points(spec: Any, where: str, file: Path) -> tuple[np.ndarray, tuple[int, int], np.ndarray]:
    if not isinstance(spec, dict):
        raise fail(file, f"{where}.grid must be a table")
    _check_keys(spec, {"origin", "edge_u", "edge_v", "resolution"}, f"{where}.grid", file)
    origin = _vector(_require(spec, "origin", f"{where}.grid", file), f"{where}.grid.origin", file)
    eu = _vector(_require(spec, "edge_u", f"{where}.grid", file), f"{where}.grid.edge_u", file)
    ev = _vector(_require(spec, "edge_v", f"{where}.grid", file), f"{where}.grid.edge_v", file)
    res = _require(spec, "resolution", f"{where}.grid", file)
    if (not isinstance(res, list) or len(res) != 2
            or not all(isinstance(r, int) and not isinstance(r, bool) for r in res)):
        raise fail(file, f"{where}.grid.resolution must be two integers, got {res!r}")
    nu, nv = res
    if nu < 1 or nv < 1:
        raise fail(file, f"{where}.grid.resolution must be at least [1, 1], got {res!r}")
    _receiver_count(nu * nv, f"{where}.grid.resolution {res!r}", file)
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
RECEIVER_BYTES = 256


def _receiver_count(count: int, what: str, file: Path) -> None:
    """Refuse up front a receiver count the kernels cannot index or memory cannot hold."""
    if count > limits.MAX_COUNT:
        raise fail(file, f"{what}: {count:,} receivers, more than the {limits.MAX_COUNT:,} the kernels can index")
    try:
        limits.memory(count * RECEIVER_BYTES, f"{what} ({count:,} receivers)")
    except WarpisError as exc:
        raise fail(file, str(exc)) from None


def _receiver_group(spec: Any, where: str, file: Path, default_material: dict | None) -> dict[str, Any]:
    if not isinstance(spec, dict):
        raise fail(file, f"{where} must be a table")
    _check_keys(spec, {"points", "grid", "normal", "normals", "name", "material"}, where, file)
    if ("points" in spec) == ("grid" in spec):
        raise fail(file, f"{where} needs exactly one of 'points' or 'grid'")
    grid_shape = None
    if "points" in spec:
        points = _vectors(spec["points"], f"{where}.points", file)
        default_normal = None
    else:
        points, grid_shape, default_normal = _grid_points(spec["grid"], where, file)
    if "normal" in spec and "normals" in spec:
        raise fail(file, f"{where} has both 'normal' and 'normals'")
    if "normals" in spec:
        normals = _vectors(spec["normals"], f"{where}.normals", file)
        if len(normals) != len(points):
            raise fail(file, f"{where}.normals has {len(normals)} entries for {len(points)} points")
    elif "normal" in spec:
        normals = np.tile(_vector(spec["normal"], f"{where}.normal", file), (len(points), 1))
    elif default_normal is not None:
        normals = np.tile(default_normal, (len(points), 1))
    else:
        raise fail(file, f"{where} needs 'normal' or 'normals'")
    normals = _unit(normals, f"{where} normal", file)
    if "material" in spec:
        material = _material(spec["material"], f"{where}.material", file)
    elif default_material is not None:
        material = default_material
    else:
        raise fail(file, f"{where} has no material and the scene has no [material] table")
    name = spec.get("name", where)
    if not isinstance(name, str):
        raise fail(file, f"{where}.name must be a string")
    _coordinates(points, f"{where} receivers", file)
    return {"points": points, "normals": normals, "material": material, "name": name, "grid": grid_shape}


def _receivers(doc: dict, file: Path) -> Receivers:
    default = _material(doc["material"], "[material]", file) if "material" in doc else None
    spec = _require(doc, "receivers", "the scene", file)
    groups_spec = spec if isinstance(spec, list) else [spec]
    if not groups_spec:
        raise fail(file, "[[receivers]] is empty")
    groups = [
        _receiver_group(g, "[receivers]" if len(groups_spec) == 1 else f"[[receivers]] #{i + 1}", file, default)
        for i, g in enumerate(groups_spec)
    ]
    count = [len(g["points"]) for g in groups]
    _receiver_count(sum(count), "[[receivers]]", file)
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
    )


# --------------------------------------------------------------------------- loading


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


def _meshes(doc: dict, file: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[str]]:
    entries = _require(doc, "mesh", "the scene", file)
    if not isinstance(entries, list) or not entries:
        raise fail(file, "the scene needs at least one [[mesh]]")
    vertices, triangles, emission, owner, paths = [], [], [], [], []
    offset = 0
    for i, entry in enumerate(entries):
        where = f"[[mesh]] #{i + 1}"
        if not isinstance(entry, dict):
            raise fail(file, f"{where} must be a table")
        _check_keys(entry, {"path", "emission", "transform", "name"}, where, file)
        rel = _require(entry, "path", where, file)
        if not isinstance(rel, str):
            raise fail(file, f"{where}.path must be a string")
        radiance = entry.get("emission", 0.0)
        if isinstance(radiance, bool) or not isinstance(radiance, (int, float)):
            raise fail(file, f"{where} ({rel}): emission must be a finite number >= 0, got {radiance!r}")
        radiance = _float32(float(radiance), f"{where} ({rel}): emission", file)
        if not isinstance(entry.get("name", ""), str):
            raise fail(file, f"{where}.name must be a string, got {entry['name']!r}")
        v, f = _read_mesh((file.parent / rel), file)
        if "transform" in entry:
            m = _transform(entry["transform"], where, file)
            with np.errstate(over="ignore", invalid="ignore"):  # overflow is reported just below
                v = v @ m[:3, :3].T + m[:3, 3]
        _coordinates(v, f"{where} ({rel}) after its transform", file)
        vertices.append(v)
        triangles.append(f + offset)
        emission.append(np.full(len(f), float(radiance)))
        owner.append(np.full(len(f), i, np.int32))
        paths.append(rel)
        offset += len(v)
    return np.vstack(vertices), np.vstack(triangles).astype(np.int32), np.concatenate(emission), np.concatenate(owner), paths


def _degenerate(vertices: np.ndarray, triangles: np.ndarray, areas: np.ndarray) -> np.ndarray:
    """Needle or point triangles: area at most DEGENERATE_AREA × longest edge², or an
    area float32 cannot hold (below its smallest normal number)."""
    v = vertices[triangles]
    edges = np.stack([v[:, 1] - v[:, 0], v[:, 2] - v[:, 1], v[:, 0] - v[:, 2]], axis=1)
    longest = (edges**2).sum(axis=2).max(axis=1)
    return (areas <= DEGENERATE_AREA * longest) | (areas < limits.FLOAT32_TINY)


def _emitters(vertices: np.ndarray, triangles: np.ndarray, emission: np.ndarray, owner: np.ndarray,
              paths: list[str], file: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Emitter triangle indices and areas; degenerate emitter triangles are dropped."""
    areas = _triangle_areas(vertices, triangles)
    needles = _degenerate(vertices, triangles, areas)
    emission = emission.copy()
    for m in np.unique(owner[emission > 0]):
        mine = (owner == m) & (emission > 0)
        degenerate = mine & needles
        if degenerate[mine].all():
            tiny = 0 < areas[mine].max() < limits.FLOAT32_TINY
            raise fail(file.parent / paths[m], "every emitter triangle has zero area" if not tiny else
                       f"every emitter triangle's area is below float32's smallest normal number "
                       f"({limits.FLOAT32_TINY:.3g}): rescale the scene")
        if degenerate.any():
            warnings.warn(f"{file.parent / paths[m]}: dropped {int(degenerate.sum())} zero-area emitter triangle(s)",
                          stacklevel=3)
            emission[degenerate] = 0.0
    emitters = np.flatnonzero(emission > 0).astype(np.int32)
    if len(emitters) == 0:
        raise fail(file, "the scene has no emitter (give some [[mesh]] an emission > 0)")
    return emitters, areas[emitters], emission


def check_device(device: str, what: str = "device") -> str:
    """``device`` if it names a Warp device of this machine (cpu, cuda, cuda:N), else a
    one-line error saying which devices exist."""
    name = str(device)
    if name == "cpu":
        return name
    match = re.fullmatch(r"cuda(?::(\d+))?", name)
    if match is None:
        raise WarpisError(f"{what} {name!r}: unknown device (valid: cpu, cuda, cuda:N)")
    count = wp.get_cuda_device_count()
    if count == 0:
        raise WarpisError(f"{what} {name!r}: this machine has no CUDA device (use cpu)")
    ordinal = int(match.group(1) or 0)
    if ordinal >= count:
        raise WarpisError(f"{what} {name!r}: this machine has {count} CUDA device(s), cuda:0 to cuda:{count - 1}")
    return name


def load_scene(scene: str | Path, device: str = "cpu") -> Scene:
    """Load and validate a scene file (or a bundled scene by name) onto a Warp device.

    Parameters
    ----------
    scene
        A bundled scene's name (see :func:`bundled_scenes`) or the path of a scene TOML.
    device
        Warp device for the scene's arrays: ``"cpu"`` or ``"cuda"``/``"cuda:N"``.

    Returns
    -------
    Scene
        Geometry in numpy and as Warp structs (``scene.data``, ``scene.receiver_data``).

    Raises
    ------
    WarpisError
        One line naming the file and the problem, for any invalid input.
    """
    check_device(device)
    file = resolve_scene_path(scene)
    doc = read_toml(file)
    _check_keys(doc, {"name", "description", "mesh", "receivers", "material"}, "the top level", file)
    name = doc.get("name", file.parent.name if file.name == "scene.toml" else file.stem)
    if not isinstance(name, str):
        raise fail(file, "name must be a string")
    if not isinstance(doc.get("description", ""), str):
        raise fail(file, "description must be a string")
    vertices, triangles, emission, owner, paths = _meshes(doc, file)
    receivers = _receivers(doc, file)
    emitters, areas, emission = _emitters(vertices, triangles, emission, owner, paths, file)
    result = Scene(
        name=name, path=file, device=str(device), vertices=vertices, triangles=triangles,
        triangle_mesh=owner, mesh_paths=paths, emission=emission, emitters=emitters,
        emitter_areas=areas, receivers=receivers, description=str(doc.get("description", "")),
    )
    upload(result, device)
    return result


def _cdf(weights: np.ndarray) -> np.ndarray:
    c = np.concatenate([[0.0], np.cumsum(weights, dtype=np.float64)])
    c /= c[-1]
    c[-1] = 1.0
    return c.astype(np.float32)


@wp.kernel
def _slab_kernel(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32),
                 position: wp.array(dtype=wp.vec3), slab: wp.array(dtype=wp.float32)):
    """Slab height of each receiver: SELF_HIT_SLAB × the largest coordinate magnitude of
    the receiver and of every triangle whose bounds hold it (its own surface among them).

    Warp's watertight ray test works on vertex − origin differences, so its rounding
    scales with those magnitudes; the slab follows them and nothing else (no scene size).
    """
    r = wp.tid()
    x = position[r]
    scale = wp.max(wp.max(wp.abs(x[0]), wp.abs(x[1])), wp.abs(x[2]))
    reach = scale * 1.0e-6 + 1.0e-30
    query = wp.mesh_query_aabb(mesh, x - wp.vec3(reach), x + wp.vec3(reach))
    face = wp.int32(0)
    while wp.mesh_query_aabb_next(query, face):
        for j in range(3):
            v = points[indices[face * 3 + j]]
            scale = wp.max(scale, wp.max(wp.max(wp.abs(v[0]), wp.abs(v[1])), wp.abs(v[2])))
    slab[r] = scale * SELF_HIT_SLAB


def _emitter_boxes(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float32 bounds of emitter triangles, widened by a little of each triangle's own
    size and magnitude: flat (axis-aligned) triangles get boxes of non-zero width, and a
    ray the widened triangle test (EDGE_SLACK) accepts is never culled by float32 box
    rounding.  A wider box costs a few more triangle tests, never a wrong pdf."""
    lo, hi = corners.min(axis=1), corners.max(axis=1)
    pad = 1e-4 * (hi - lo).max(axis=1) + 2.0**-14 * np.abs(corners).max(axis=(1, 2))
    return (lo - pad[:, None]).astype(np.float32), (hi + pad[:, None]).astype(np.float32)


def upload(scene: Scene, device: str) -> None:
    """Build the Warp meshes and structs of ``scene`` on ``device`` (in place)."""
    with wp.ScopedDevice(device):
        points = wp.array(scene.vertices.astype(np.float32), dtype=wp.vec3)
        indices = wp.array(scene.triangles.reshape(-1).astype(np.int32), dtype=wp.int32)
        mesh = wp.Mesh(points=points, indices=indices)
        lower, upper = _emitter_boxes(scene.triangle_vertices(scene.emitters))
        emitter_bvh = wp.Bvh(wp.array(lower, dtype=wp.vec3), wp.array(upper, dtype=wp.vec3))
        d = SceneData()
        d.mesh = mesh.id
        d.emitter_bvh = emitter_bvh.id
        d.points = points
        d.indices = indices
        d.tri_emission = wp.array(scene.emission.astype(np.float32), dtype=wp.float32)
        d.emitter_tri = wp.array(scene.emitters, dtype=wp.int32)
        d.emitter_area = wp.array(scene.emitter_areas.astype(np.float32), dtype=wp.float32)
        d.area_cdf = wp.array(_cdf(scene.emitter_areas), dtype=wp.float32)
        d.power_cdf = wp.array(_cdf(scene.emitter_areas * scene.emitter_radiance), dtype=wp.float32)
        d.total_area = float(scene.total_emitter_area)
        d.total_power = float(scene.total_power)
        d.emitter_count = int(scene.emitter_count)
        r = scene.receivers
        rd = ReceiverData()
        rd.position = wp.array(r.positions.astype(np.float32), dtype=wp.vec3)
        rd.normal = wp.array(r.normals.astype(np.float32), dtype=wp.vec3)
        rd.material = wp.array(r.material.astype(np.int32), dtype=wp.int32)
        rd.albedo = wp.array(r.albedo.astype(np.float32), dtype=wp.float32)
        rd.exponent = wp.array(r.exponent.astype(np.float32), dtype=wp.float32)
        rd.view = wp.array(r.view.astype(np.float32), dtype=wp.vec3)
        rd.slab = wp.zeros(len(r), dtype=wp.float32)
        wp.launch(_slab_kernel, dim=len(r), inputs=[mesh.id, points, indices, rd.position, rd.slab])
    scene.device = str(device)
    scene.slab = rd.slab.numpy().astype(np.float64)
    scene.data = d
    scene.receiver_data = rd
    scene._keep = [points, indices, mesh, emitter_bvh]
