"""Scenes as plain data: geometry, emission and receivers in numpy, named by their content.

A :class:`Scene` comes from one of two sources, and both pass the same checks
(:func:`_assemble`) before anything reaches a device:

* a scene file (TOML, :func:`load_scene`) listing meshes in any format trimesh reads,
  each with an optional transform and an optional one-sided ``emission``, receivers
  (explicit points or grids, in one or several groups) and the material at the
  receivers (README.md, "Scene files");
* arrays (:meth:`Scene.from_arrays`).

Bad input raises :class:`~warpis.errors.WarpisError` with one line naming the file (or
the scene) and the problem.  A Scene holds read-only numpy arrays and the name of its
Warp device, nothing else: it pickles, and :attr:`Scene.digest` names its content.
Its Warp side (mesh, BVH, structs, self-hit slabs, light table) is built by
:func:`warpis.device.upload` once per (digest, device); ``scene.data``,
``scene.receiver_data`` and ``scene.slab`` fetch it.
"""

from __future__ import annotations

import hashlib
import io
import math
import tomllib
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields, replace
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from . import limits
from .device import SELF_HIT_SLAB, DeviceScene, ReceiverData, SceneData, check_device, upload
from .errors import WarpisError, fail
from .vocabulary import MATERIALS, Material

__all__ = ["DIGEST_FIELDS", "SELF_HIT_SLAB", "DeviceScene", "ReceiverData", "Receivers", "Scene", "SceneData",
           "bundled_scenes", "check_device", "load_scene", "read_toml", "resolve_scene_path", "upload"]

# Emitter triangles whose area is below this fraction of their longest edge squared are
# needles: no float32 ray can hit them reliably nor can they be sampled with a finite pdf.
DEGENERATE_AREA = 1e-12

# The arrays the digest hashes, in this order: every array a result depends on.  Names,
# the description, the path, mesh names, the triangle → mesh index and receiver groups
# only label things (warpis info, figures), so renaming or moving a file keeps the digest.
DIGEST_FIELDS = ("vertices", "triangles", "emission", "receivers.positions", "receivers.normals",
                 "receivers.material", "receivers.albedo", "receivers.exponent", "receivers.view")
_DIGEST_FORMAT = b"warpis scene digest 1\0"  # a new encoding below gets a new number


def _freeze(obj: Any, names: Sequence[str]) -> None:
    """Replace the arrays ``names`` of a frozen dataclass by read-only views: the digest
    is computed once, so nothing may change the arrays under it."""
    for name in names:
        view = np.asarray(getattr(obj, name)).view()
        view.flags.writeable = False
        object.__setattr__(obj, name, view)


_RECEIVER_ARRAYS = ("positions", "normals", "material", "albedo", "exponent", "view", "group")


@dataclass(frozen=True, eq=False)
class Receivers:
    """Receiver points with their normals and materials (numpy, read-only)."""

    positions: np.ndarray  # (R, 3) float64
    normals: np.ndarray  # (R, 3) float64, unit
    material: np.ndarray  # (R,) int32, vocabulary.MATERIALS code
    albedo: np.ndarray  # (R,) float64
    exponent: np.ndarray  # (R,) float64
    view: np.ndarray  # (R, 3) float64, unit
    group: np.ndarray  # (R,) int32, index into group_names
    group_names: list[str] = field(default_factory=list)
    grid_shape: tuple[int, int] | None = None  # (rows, cols) when the only group is a grid

    def __post_init__(self) -> None:
        _freeze(self, _RECEIVER_ARRAYS)

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)  # unpickled arrays are writable: freeze them again
        _freeze(self, _RECEIVER_ARRAYS)

    def __len__(self) -> int:
        return len(self.positions)

    def material_of(self, index: int) -> Material:
        """The material of receiver ``index`` (its entry in ``vocabulary.MATERIALS``)."""
        return MATERIALS.by_code(self.material[index])

    def material_name(self, index: int) -> str:
        """The material type of receiver ``index`` as spelled in scene files."""
        return self.material_of(index).name


_SCENE_ARRAYS = ("vertices", "triangles", "emission", "triangle_mesh")


@dataclass(frozen=True, eq=False)
class Scene:
    """A scene as plain data: geometry, emission and receivers in numpy (read-only), and
    the Warp device its kernels run on.

    Build one with :func:`load_scene` or :meth:`from_arrays`, which validate; the
    dataclass constructor (and :func:`dataclasses.replace`) checks nothing.
    """

    name: str
    vertices: np.ndarray  # (V, 3) float64, transformed
    triangles: np.ndarray  # (T, 3) int32
    emission: np.ndarray  # (T,) float64: radiance of each triangle's front face, 0 for no emitter
    receivers: Receivers
    triangle_mesh: np.ndarray  # (T,) int32: index into mesh_names of the mesh each triangle comes from
    mesh_names: list[str]  # a scene file's [[mesh]] paths as written; labels for arrays
    description: str = ""
    path: Path | None = None  # the scene file, for a scene loaded from one
    device: str = "cpu"  # Warp device of scene.data and of every kernel run on this scene

    def __post_init__(self) -> None:
        _freeze(self, _SCENE_ARRAYS)

    def __getstate__(self) -> dict[str, Any]:
        # The fields only: cached values (digest, emitters) are recomputed after loading.
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        _freeze(self, _SCENE_ARRAYS)

    @classmethod
    def from_arrays(cls, vertices: Any, triangles: Any, emission: Any, positions: Any, normals: Any, *,
                    material: str | Any = "irradiance", albedo: Any = 1.0, exponent: Any = 1.0,
                    view: Any = (0.0, 0.0, 1.0), group: Any = None, group_names: Sequence[str] | None = None,
                    grid_shape: tuple[int, int] | None = None, triangle_mesh: Any = None,
                    mesh_names: Sequence[str] | None = None, name: str = "arrays", description: str = "",
                    device: str = "cpu") -> Scene:
        """A validated scene from arrays, with the same checks as a scene file.

        Parameters
        ----------
        vertices, triangles
            (V, 3) coordinates and (T, 3) integer vertex indices; a triangle's front face
            is the one its vertices wind counter-clockwise around.
        emission
            (T,) radiance of each triangle's front face (0: not an emitter).
        positions, normals
            (R, 3) receiver points and their normals (one (3,) normal for all, or (R, 3));
            normals are normalised.
        material
            A material name (``"irradiance"``, ``"lambert"``, ``"phong"``) for every
            receiver, or the ``vocabulary.MATERIALS`` code of each (one or (R,)).
        albedo, exponent, view
            Material parameters, one for all or one per receiver; ``view`` (the direction
            towards the viewer, normalised) is (3,) or (R, 3).
        group, group_names, grid_shape
            Receiver group index of each receiver (default 0) and the groups' names
            (default ``["receivers"]``); (rows, cols) when the receivers form a grid.
        triangle_mesh, mesh_names
            Index of the mesh each triangle belongs to (default 0) and mesh names
            (default ``[name]``): labels for ``warpis info`` and messages.
        name, description, device
            Labels, and the Warp device (``"cpu"``, ``"cuda"``, ``"cuda:N"``).

        Raises
        ------
        WarpisError
            One line, ``scene '<name>': <array>: <problem>``, for any invalid array.
        """
        if not isinstance(name, str) or not isinstance(description, str):
            raise WarpisError(f"Scene.from_arrays: name and description must be strings, got {name!r}, "
                              f"{description!r}")
        where = f"scene {name!r}"
        check_device(device)
        rx = _receivers_from_arrays(where, positions, normals, material, albedo, exponent, view, group,
                                    group_names, grid_shape)
        names = [name] if mesh_names is None else mesh_names
        return _assemble(where, lambda m: f"{where}: mesh {names[m]!r}", "give some triangle an emission > 0",
                         name=name, vertices=vertices, triangles=triangles, emission=emission, receivers=rx,
                         triangle_mesh=triangle_mesh, mesh_names=names, description=description,
                         device=str(device))

    def on(self, device: str) -> Scene:
        """The same scene with its kernels on ``device``."""
        return replace(self, device=check_device(device))

    @cached_property
    def digest(self) -> str:
        """sha256 (hex) of the arrays in ``DIGEST_FIELDS``: each one's name, dtype, shape
        and little-endian bytes.  Equal digests mean equal results."""
        h = hashlib.sha256(_DIGEST_FORMAT)
        for name in DIGEST_FIELDS:
            a = self
            for part in name.split("."):
                a = getattr(a, part)
            a = np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("<"))
            h.update(f"{name} {a.dtype.str} {a.shape}\0".encode())
            h.update(a.tobytes())
        return h.hexdigest()

    # ----------------------------------------------------------------- on the device

    @property
    def data(self) -> SceneData:
        """The SceneData struct on ``device`` (see :func:`warpis.device.upload`)."""
        return upload(self).data

    @property
    def receiver_data(self) -> ReceiverData:
        """The ReceiverData struct on ``device``."""
        return upload(self).receiver_data

    @property
    def slab(self) -> np.ndarray:
        """(R,) self-hit slab height of each receiver, as computed on ``device``."""
        return upload(self).slab

    # ----------------------------------------------------------------- derived numbers

    @cached_property
    def emitters(self) -> np.ndarray:
        """(E,) int32 index of each emitter triangle (emission > 0)."""
        out = np.flatnonzero(self.emission > 0).astype(np.int32)
        out.flags.writeable = False
        return out

    @cached_property
    def emitter_areas(self) -> np.ndarray:
        """(E,) area of each emitter triangle."""
        out = _triangle_areas(self.vertices, self.triangles)[self.emitters]
        out.flags.writeable = False
        return out

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

    def summary(self) -> dict[str, Any]:
        """Counts and emitter totals, as printed by ``warpis scenes`` and ``warpis info``."""
        return {
            "scene": self.name,
            "path": None if self.path is None else str(self.path),
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


def resolve_scene_path(name_or_path: str | Path, base: Path | None = Path()) -> Path:
    """A path to a scene file (or to a folder holding ``scene.toml``), else a bundled
    scene's name → the scene file's path.

    Relative paths are taken from ``base`` (the working directory by default; a study's
    folder for its scenes); ``base=None`` accepts bundled names only.
    """
    text = str(name_or_path)
    if base is not None:
        candidate = base / text
        if candidate.is_file():
            return candidate
        if candidate.is_dir() and (candidate / "scene.toml").is_file():
            return candidate / "scene.toml"
    bundled = _bundled_root() / text / "scene.toml"
    if "/" not in text and "\\" not in text and bundled.is_file():
        return Path(str(bundled))
    names = ", ".join(bundled_scenes())
    where = text if base is None or base == Path() else base / text
    raise fail(where, f"no such scene file or bundled scene (bundled: {names})")


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


def _coordinates(points: np.ndarray, what: str, where: object) -> np.ndarray:
    """Points whose coordinates float32 kernels can hold and square (limits.coordinates)."""
    _within(where, limits.coordinates, points, what)
    return points


def _unit(v: np.ndarray, what: str, where: object) -> np.ndarray:
    norms = np.linalg.norm(v, axis=-1, keepdims=True)
    if not np.all(norms > 0):
        raise fail(where, f"{what} has zero length")
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


def _receiver_count(count: int, what: str, where: object) -> None:
    """Refuse up front a receiver count the kernels cannot index or memory cannot hold."""
    if count > limits.MAX_COUNT:
        raise fail(where, f"{what}: {count:,} receivers, more than the {limits.MAX_COUNT:,} the kernels can index")
    _within(where, limits.memory, count * RECEIVER_BYTES, f"{what} ({count:,} receivers)")


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


# --------------------------------------------------------------------------- reading files


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


# --------------------------------------------------------------------------- arrays


def _within(where: object, check: Callable[..., Any], *args: Any) -> None:
    """Run a :mod:`warpis.limits` check; its one-line error is prefixed with ``where``."""
    try:
        check(*args)
    except WarpisError as exc:
        raise fail(where, str(exc)) from None


def _numbers(value: Any, what: str, where: object, integer: bool = False) -> np.ndarray:
    """``value`` as a new float64 (or int64) array, never the caller's memory; non-numbers,
    and non-integers where integers are due, are refused (nothing is truncated)."""
    try:
        a = np.asarray(value)  # astype below copies
    except (TypeError, ValueError):  # ragged rows, or objects numpy cannot hold
        raise fail(where, f"{what}: not a rectangular array of numbers") from None
    if a.size and a.dtype.kind not in ("iu" if integer else "iuf"):
        raise fail(where, f"{what}: expected {'integers' if integer else 'real numbers'}, got dtype {a.dtype}")
    return a.astype(np.int64 if integer else np.float64)


def _array(value: Any, what: str, where: object, shape: tuple[int | None, ...], spelled: str,
           integer: bool = False) -> np.ndarray:
    """An array of exactly ``shape`` (None: any length >= 1), written ``spelled`` in errors."""
    a = _numbers(value, what, where, integer)
    if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)) or a.size == 0:
        raise fail(where, f"{what}: expected shape {spelled}, got {a.shape}")
    return a


def _per_receiver(value: Any, what: str, where: object, count: int, width: int | None = None,
                  integer: bool = False) -> np.ndarray:
    """One value (or one (width,) vector) for every receiver, or one per receiver."""
    one = () if width is None else (width,)
    a = _numbers(value, what, where, integer)
    if a.shape == one:
        return np.tile(a, (count,) + (1,) * len(one))
    if a.shape != (count, *one):
        raise fail(where, f"{what}: expected shape {one} or {(count, *one)} (one per receiver), got {a.shape}")
    return a


def _directions(v: np.ndarray, what: str, where: object) -> np.ndarray:
    """Refuse a NaN, infinite, zero or overflowing direction (normals, views)."""
    finite = np.isfinite(v).all(axis=1)
    if not finite.all():
        raise fail(where, f"{what}: entry {int(np.argmin(finite))} is NaN or infinite")
    with np.errstate(over="ignore"):
        norms = np.linalg.norm(v, axis=1)
    if not (norms > 0).all():
        raise fail(where, f"{what}: entry {int(np.argmin(norms > 0))} has zero length")
    if not np.isfinite(norms).all():
        raise fail(where, f"{what}: entry {int(np.argmin(np.isfinite(norms)))} is too long to normalise")
    return v


def _material_codes(material: Any, count: int, where: object) -> np.ndarray:
    """A material name for every receiver, or codes (one or one per receiver) → (R,) int32."""
    if isinstance(material, str):
        if material not in MATERIALS:
            raise fail(where, f"material: {MATERIALS.unknown(material)}")
        material = MATERIALS[material].code
    codes = _per_receiver(material, "material", where, count, integer=True)
    _check_codes(codes, where)
    return codes.astype(np.int32)


def _check_codes(codes: np.ndarray, where: object) -> None:
    valid = [m.code for m in MATERIALS.values()]
    bad = ~np.isin(codes, valid)
    if bad.any():
        i = int(np.argmax(bad))
        names = ", ".join(f"{m.code} {m.name}" for m in MATERIALS.values())
        raise fail(where, f"material: code {codes[i]} of receiver {i} is not a material (valid: {names})")


def _grid_shape(value: Any, count: int, where: object) -> tuple[int, int] | None:
    """None, or (rows, cols) of positive integers with rows × cols = the receiver count."""
    if value is None:
        return None
    shape = tuple(value) if isinstance(value, (tuple, list, np.ndarray)) else ()
    integers = all(isinstance(s, (int, np.integer)) and not isinstance(s, bool) and s >= 1 for s in shape)
    if len(shape) != 2 or not integers or shape[0] * shape[1] != count:
        raise fail(where, f"grid_shape: expected (rows, cols) with rows × cols = {count} receivers, got {value!r}")
    return int(shape[0]), int(shape[1])


def _check_groups(group: np.ndarray, names: Any, where: object) -> None:
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise fail(where, f"group_names: expected a non-empty list of strings, got {names!r}")
    bad = (group < 0) | (group >= len(names))
    if bad.any():
        i = int(np.argmax(bad))
        raise fail(where, f"group: receiver {i} is in group {group[i]}, but there are {len(names)} group name(s)")


def _receivers_from_arrays(where: str, positions: Any, normals: Any, material: Any, albedo: Any, exponent: Any,
                           view: Any, group: Any, group_names: Sequence[str] | None,
                           grid_shape: Any) -> Receivers:
    """Receivers from arrays, broadcast to one row per receiver, directions normalised."""
    p = _array(positions, "positions", where, (None, 3), "(R, 3)")
    count = len(p)
    _receiver_count(count, "positions", where)  # before anything is broadcast to R rows
    n = _directions(_per_receiver(normals, "normals", where, count, 3), "normals", where)
    v = _directions(_per_receiver(view, "view", where, count, 3), "view", where)
    g = np.zeros(count, np.int64) if group is None else _per_receiver(group, "group", where, count, integer=True)
    names = ["receivers"] if group_names is None else list(group_names) if isinstance(group_names, (list, tuple)) \
        else group_names
    _check_groups(g, names, where)
    return Receivers(
        positions=p, normals=_unit(n, "normals", where), material=_material_codes(material, count, where),
        albedo=_per_receiver(albedo, "albedo", where, count),
        exponent=_per_receiver(exponent, "exponent", where, count),
        view=_unit(v, "view", where), group=g.astype(np.int32), group_names=names,
        grid_shape=_grid_shape(grid_shape, count, where),
    )


def _check_receivers(rx: Receivers, where: object) -> None:
    """Every receiver array: shapes, the kernels' limits, directions, material codes, groups."""
    count = len(rx.positions)
    if rx.positions.ndim != 2 or rx.positions.shape[1] != 3 or count == 0:
        raise fail(where, f"receivers: positions must have shape (R, 3) with R >= 1, got {rx.positions.shape}")
    _receiver_count(count, "receivers", where)
    for name in _RECEIVER_ARRAYS:
        expected = (count, 3) if name in ("positions", "normals", "view") else (count,)
        if getattr(rx, name).shape != expected:
            raise fail(where, f"receivers: {name} has shape {getattr(rx, name).shape}, expected {expected}")
    _coordinates(rx.positions, "positions", where)
    _directions(rx.normals, "receiver normals", where)
    _directions(rx.view, "receiver view", where)
    _check_codes(rx.material, where)
    _within(where, limits.float32_values, rx.albedo, "albedo")
    _within(where, limits.float32_values, rx.exponent, "exponent")
    _check_groups(rx.group, rx.group_names, where)
    _grid_shape(rx.grid_shape, count, where)


def _geometry(vertices: Any, triangles: Any, where: object) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) float64 vertices the kernels can hold and (T, 3) int32 indices into them."""
    v = _array(vertices, "vertices", where, (None, 3), "(V, 3)")
    _coordinates(v, "vertices", where)
    t = _array(triangles, "triangles", where, (None, 3), "(T, 3)", integer=True)
    if t.size > limits.MAX_COUNT:
        raise fail(where, f"triangles: {len(t):,} triangles, more than the kernels can index")
    bad = (t < 0) | (t >= len(v))
    if bad.any():
        i = int(np.argmax(bad.any(axis=1)))
        raise fail(where, f"triangles: triangle {i} refers to vertex {t[i][bad[i]][0]}, which does not exist "
                          f"(there are {len(v)})")
    return v, t.astype(np.int32)


def _owners(triangle_mesh: Any, mesh_names: Any, count: int, where: object) -> tuple[np.ndarray, list[str]]:
    """The mesh index of each triangle (default 0) and the mesh names it indexes."""
    names = list(mesh_names) if isinstance(mesh_names, (list, tuple)) else mesh_names
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise fail(where, f"mesh_names: expected a non-empty list of strings, got {mesh_names!r}")
    if triangle_mesh is None:
        return np.zeros(count, np.int32), names
    owner = _array(triangle_mesh, "triangle_mesh", where, (count,), f"(T,) = ({count},)", integer=True)
    bad = (owner < 0) | (owner >= len(names))
    if bad.any():
        i = int(np.argmax(bad))
        raise fail(where, f"triangle_mesh: triangle {i} is in mesh {owner[i]}, but there are {len(names)} mesh name(s)")
    return owner.astype(np.int32), names


def _degenerate(vertices: np.ndarray, triangles: np.ndarray, areas: np.ndarray) -> np.ndarray:
    """Needle or point triangles: area at most DEGENERATE_AREA × longest edge², or an
    area float32 cannot hold (below its smallest normal number)."""
    v = vertices[triangles]
    edges = np.stack([v[:, 1] - v[:, 0], v[:, 2] - v[:, 1], v[:, 0] - v[:, 2]], axis=1)
    longest = (edges**2).sum(axis=2).max(axis=1)
    return (areas <= DEGENERATE_AREA * longest) | (areas < limits.FLOAT32_TINY)


def _drop_needles(vertices: np.ndarray, triangles: np.ndarray, emission: np.ndarray, owner: np.ndarray,
                  mesh_where: Callable[[int], object]) -> np.ndarray:
    """``emission`` with degenerate emitter triangles set to 0 (a warning per mesh); a mesh
    whose every emitter triangle is degenerate is an error naming it."""
    areas = _triangle_areas(vertices, triangles)
    needles = _degenerate(vertices, triangles, areas)
    emission = emission.copy()
    for m in np.unique(owner[emission > 0]):
        mine = (owner == m) & (emission > 0)
        degenerate = mine & needles
        if degenerate[mine].all():
            tiny = 0 < areas[mine].max() < limits.FLOAT32_TINY
            raise fail(mesh_where(m), "every emitter triangle has zero area" if not tiny else
                       f"every emitter triangle's area is below float32's smallest normal number "
                       f"({limits.FLOAT32_TINY:.3g}): rescale the scene")
        if degenerate.any():
            warnings.warn(f"{mesh_where(m)}: dropped {int(degenerate.sum())} zero-area emitter triangle(s)",
                          stacklevel=4)  # the caller of load_scene or Scene.from_arrays
            emission[degenerate] = 0.0
    return emission


def _assemble(where: object, mesh_where: Callable[[int], object], hint: str, *, name: str, vertices: Any,
              triangles: Any, emission: Any, receivers: Receivers, triangle_mesh: Any, mesh_names: Any,
              description: str, device: str, path: Path | None = None) -> Scene:
    """The one gate of every source (a scene file, arrays): each array against the kernels'
    limits, degenerate emitters dropped, at least one emitter → a Scene.

    ``where`` prefixes errors; ``mesh_where(m)`` names mesh m; ``hint`` says how to add an emitter.
    """
    v, t = _geometry(vertices, triangles, where)
    e = _array(emission, "emission", where, (len(t),), f"(T,) = ({len(t)},)")
    _within(where, limits.float32_values, e, "emission")
    owner, names = _owners(triangle_mesh, mesh_names, len(t), where)
    _check_receivers(receivers, where)
    e = _drop_needles(v, t, e, owner, mesh_where)
    if not (e > 0).any():
        raise fail(where, f"the scene has no emitter ({hint})")
    return Scene(name=name, vertices=v, triangles=t, emission=e, receivers=receivers, triangle_mesh=owner,
                 mesh_names=names, description=description, path=path, device=device)


# --------------------------------------------------------------------------- scene files


def load_scene(scene: str | Path, device: str = "cpu") -> Scene:
    """Load and validate a scene file (or a bundled scene by name).

    Parameters
    ----------
    scene
        A bundled scene's name (see :func:`bundled_scenes`) or the path of a scene TOML.
    device
        Warp device the scene's kernels run on: ``"cpu"`` or ``"cuda"``/``"cuda:N"``.

    Returns
    -------
    Scene
        Plain numpy data; ``scene.data`` and ``scene.receiver_data`` upload it on first use.

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
    return _assemble(file, lambda m: file.parent / paths[m], "give some [[mesh]] an emission > 0", name=name,
                     vertices=vertices, triangles=triangles, emission=emission, receivers=receivers,
                     triangle_mesh=owner, mesh_names=paths, description=str(doc.get("description", "")),
                     device=str(device), path=file)
