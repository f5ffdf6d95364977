"""A scene as plain data: geometry, emission and receivers in numpy, named by their content.

Every scene source (a TOML scene file, :meth:`Scene.from_arrays`, any future importer)
ends in :func:`assemble_scene`, the one gate that checks each array against the kernels'
limits before anything reaches a device.  A :class:`Scene` holds read-only numpy arrays
and the name of its Warp device, nothing else: it pickles, and :attr:`Scene.digest`
names its content.  Its Warp side (mesh, BVH, structs, self-hit slabs, light table) is
built by :func:`warpis.kernels.device.upload` once per (digest, device), a floor above:
the scenes never import the kernels.

Bad input raises :class:`~warpis.errors.WarpisError` with one line naming the file (or
the scene) and the problem.
"""

from __future__ import annotations

import hashlib
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from .. import limits
from ..errors import WarpisError, fail
from ..limits import check_device
from ..vocabulary import DISTRIBUTIONS, MATERIALS, Material
from .camera import ImageLayout
from .delta import DeltaLights, check_delta_lights
from .environment import Environment, check_environment
from .spheres import Spheres, check_spheres

# Emitter triangles whose area is below this fraction of their longest edge squared are
# needles: no float32 ray can hit them reliably nor can they be sampled with a finite pdf.
DEGENERATE_AREA = 1e-12

# The arrays the digest hashes, in this order: every array a result depends on.  Names,
# the description, the path, mesh names, the triangle → mesh index and receiver groups
# only label things (warpis info, figures), so renaming or moving a file keeps the digest.

DIGEST_FIELDS = ("vertices", "triangles", "emission", "receivers.positions", "receivers.normals",
                 "receivers.material", "receivers.albedo", "receivers.exponent", "receivers.view",
                 "receivers.alpha", "receivers.distribution", "receivers.sample_visible", "receivers.eta",
                 "receivers.k", "receivers.specular", "receivers.specular_weight")

_DIGEST_FORMAT = b"warpis scene digest 2\0"  # a new encoding below gets a new number

def _freeze(obj: Any, names: Sequence[str]) -> None:
    """Replace the arrays ``names`` of a frozen dataclass by read-only views: the digest
    is computed once, so nothing may change the arrays under it."""
    for name in names:
        view = np.asarray(getattr(obj, name)).view()
        view.flags.writeable = False
        object.__setattr__(obj, name, view)

_RECEIVER_ARRAYS = ("positions", "normals", "material", "albedo", "exponent", "view", "group", "alpha",
                    "distribution", "sample_visible", "eta", "k", "specular", "specular_weight", "geometric_normals")
# Per-channel microfacet parameters (see kernels/shading.py): (R, 3) arrays.
_CHANNEL_ARRAYS = ("eta", "k", "specular")
# Microfacet parameters of receivers whose material has none (any valid value would do).
MICROFACET_DEFAULTS = {"alpha": 0.1, "distribution": DISTRIBUTIONS["ggx"], "sample_visible": 1, "eta": 1.5, "k": 0.0,
                       "specular": 1.0, "specular_weight": 0.5}

@dataclass(frozen=True, eq=False)
class Receivers:
    """Receiver points with their normals and materials (numpy, read-only)."""

    positions: np.ndarray  # (R, 3) float64
    normals: np.ndarray  # (R, 3) float64, unit: the shading normal (the BSDF's frame and its cosine)
    material: np.ndarray  # (R,) int32, MATERIALS (kernels/integrand.py) code
    albedo: np.ndarray  # (R,) float64
    exponent: np.ndarray  # (R,) float64
    view: np.ndarray  # (R, 3) float64, unit
    group: np.ndarray  # (R,) int32, index into group_names
    group_names: list[str] = field(default_factory=list)
    grid_shape: tuple[int, int] | None = None  # (rows, cols) when the only group is a grid
    # Microfacet materials (roughconductor, roughplastic; kernels/shading.py), defaults for
    # the others: None → MICROFACET_DEFAULTS.
    alpha: np.ndarray = None  # type: ignore[assignment]  # (R,) float64, isotropic roughness
    distribution: np.ndarray = None  # type: ignore[assignment]  # (R,) int32, shading.DISTRIBUTIONS
    sample_visible: np.ndarray = None  # type: ignore[assignment]  # (R,) int32, 0 or 1
    eta: np.ndarray = None  # type: ignore[assignment]  # (R, 3) float64, per channel
    k: np.ndarray = None  # type: ignore[assignment]  # (R, 3) float64, per channel
    specular: np.ndarray = None  # type: ignore[assignment]  # (R, 3) reflectance × channel weight
    specular_weight: np.ndarray = None  # type: ignore[assignment]  # (R,) roughplastic lobe choice
    # A camera's receivers: which pixel each one is and what the others see (scenes/camera.py).
    image: ImageLayout | None = None
    # (R, 3) float64, unit: the normal of the surface each receiver lies on (its triangle's),
    # which governs what rays see, not what the BSDF reflects: the side a ray leaves from,
    # the receiver's own plane and its self-hit slab (kernels/integrand.py).  It differs
    # from ``normals`` where a mesh shades with normals interpolated from its vertex
    # normals, as Mitsuba does.  None: the same as ``normals``.
    geometric_normals: np.ndarray = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        count = len(self.positions)
        if self.geometric_normals is None:
            object.__setattr__(self, "geometric_normals", np.asarray(self.normals))
        for name, value in MICROFACET_DEFAULTS.items():
            if getattr(self, name) is None:
                shape = (count, 3) if name in _CHANNEL_ARRAYS else (count,)
                kind = np.int32 if name in ("distribution", "sample_visible") else np.float64
                fill = value / 3 if name == "specular" else value
                object.__setattr__(self, name, np.full(shape, fill, kind))
        _freeze(self, _RECEIVER_ARRAYS)

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)  # unpickled arrays are writable: freeze them again
        _freeze(self, _RECEIVER_ARRAYS)

    def __len__(self) -> int:
        return len(self.positions)

    def material_of(self, index: int) -> Material:
        """The material of receiver ``index`` (its entry in ``MATERIALS (kernels/integrand.py)``)."""
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
    notes: tuple[str, ...] = ()  # what a source wants `warpis info` to say (colour channel, tessellation error)
    # Radiance from infinitely far away, seen by every ray that leaves the scene
    # (scenes/environment.py); None: rays that leave see nothing.
    environment: Environment | None = None
    # Point, spot and directional lights as seen from each receiver (scenes/delta.py):
    # their exact term is part of every estimate of F.  None: the scene has none.
    delta_lights: DeltaLights | None = None
    # Analytic spheres (scenes/spheres.py): shapes of their own beside the triangles,
    # intersected and sampled exactly; emitters where their emission > 0.  None: none.
    spheres: Spheres | None = None

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
                    view: Any = (0.0, 0.0, 1.0), alpha: Any = None, distribution: str | Any = "ggx",
                    sample_visible: Any = True, eta: Any = None, k: Any = None, specular: Any = None,
                    specular_weight: Any = None, group: Any = None, group_names: Sequence[str] | None = None,
                    grid_shape: tuple[int, int] | None = None, triangle_mesh: Any = None,
                    mesh_names: Sequence[str] | None = None, name: str = "arrays", description: str = "",
                    device: str = "cpu", geometric_normals: Any = None,
                    environment: Environment | None = None, delta_lights: DeltaLights | None = None,
                    spheres: Spheres | None = None) -> Scene:
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
            receiver, or the ``MATERIALS (kernels/integrand.py)`` code of each (one or (R,)).
        albedo, exponent, view
            Material parameters, one for all or one per receiver; ``view`` (the direction
            towards the viewer, normalised) is (3,) or (R, 3).
        alpha, distribution, sample_visible, eta, k, specular, specular_weight
            Microfacet parameters (roughconductor, roughplastic), one for all or one per
            receiver, grey (the same in every colour channel): roughness, ``"ggx"`` or
            ``"beckmann"``, visible-normal sampling, the index of refraction (conductor:
            its real part; roughplastic: int_ior/ext_ior), the conductor's extinction, the
            specular reflectance, and roughplastic's lobe-choice weight (default
            specular/(albedo + specular), as Mitsuba computes it).
        group, group_names, grid_shape
            Receiver group index of each receiver (default 0) and the groups' names
            (default ``["receivers"]``); (rows, cols) when the receivers form a grid.
        triangle_mesh, mesh_names
            Index of the mesh each triangle belongs to (default 0) and mesh names
            (default ``[name]``): labels for ``warpis info`` and messages.
        name, description, device
            Labels, and the Warp device (``"cpu"``, ``"cuda"``, ``"cuda:N"``).
        geometric_normals
            The normal of the surface under each receiver, where it differs from the
            shading normal ``normals`` (a mesh shaded with interpolated vertex normals):
            one (3,) or (R, 3), normalised; default ``normals``.  Rays leave from its
            side and ignore its plane; the BSDF and its cosine use ``normals``.
        environment
            An :class:`~warpis.scenes.environment.Environment`: the radiance of rays that
            leave the scene (then ``emission`` may be all 0).
        delta_lights
            A :class:`~warpis.scenes.delta.DeltaLights` table at these receivers: point,
            spot and directional lights, whose exact term every estimate of F carries.
        spheres
            A :class:`~warpis.scenes.spheres.Spheres` table: analytic spheres (owners
            index ``mesh_names``), emitters where their emission > 0.

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
        microfacet = {"alpha": alpha, "distribution": distribution, "sample_visible": sample_visible, "eta": eta,
                      "k": k, "specular": specular, "specular_weight": specular_weight}
        rx = _receivers_from_arrays(where, positions, normals, material, albedo, exponent, view, group,
                                    group_names, grid_shape, microfacet, geometric_normals)
        names = [name] if mesh_names is None else mesh_names
        return assemble_scene(where, lambda m: f"{where}: mesh {names[m]!r}", "give some triangle an emission > 0",
                         name=name, vertices=vertices, triangles=triangles, emission=emission, receivers=rx,
                         triangle_mesh=triangle_mesh, mesh_names=names, description=description,
                         device=str(device), environment=environment, delta_lights=delta_lights,
                         spheres=spheres)

    def on(self, device: str) -> Scene:
        """The same scene with its kernels on ``device``."""
        return replace(self, device=check_device(device))

    @cached_property
    def digest(self) -> str:
        """sha256 (hex) of the arrays in ``DIGEST_FIELDS``: each one's name, dtype, shape
        and little-endian bytes, and the receivers' geometric normals where they are not
        their normals.  Equal digests mean equal results."""
        h = hashlib.sha256(_DIGEST_FORMAT)
        rx = self.receivers
        shaded = () if np.array_equal(rx.geometric_normals, rx.normals) else ("receivers.geometric_normals",)
        lit = () if self.environment is None else ("environment.texels", "environment.rotation")
        delta = () if self.delta_lights is None else ("delta_lights.directions", "delta_lights.distances",
                                                      "delta_lights.irradiance")
        round_ = () if self.spheres is None else ("spheres.centers", "spheres.radii", "spheres.emission",
                                                  "spheres.inward")
        for name in DIGEST_FIELDS + shaded + lit + delta + round_:
            a = self
            for part in name.split("."):
                a = getattr(a, part)
            a = np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("<"))
            h.update(f"{name} {a.dtype.str} {a.shape}\0".encode())
            h.update(a.tobytes())
        return h.hexdigest()

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
        """The emitter triangles (sphere lights are :attr:`sphere_lights`)."""
        return len(self.emitters)

    @property
    def emitter_radiance(self) -> np.ndarray:
        return self.emission[self.emitters]

    @cached_property
    def sphere_lights(self) -> np.ndarray:
        """(L,) int32 index into ``spheres`` of each emitting sphere."""
        out = np.zeros(0, np.int32) if self.spheres is None else self.spheres.lights
        out.flags.writeable = False
        return out

    @property
    def light_count(self) -> int:
        """The lights the light techniques sample: emitter triangles, then emitting spheres."""
        return self.emitter_count + len(self.sphere_lights)

    @property
    def light_areas(self) -> np.ndarray:
        """(E + L,) area of each emitter triangle, then of each sphere light."""
        spheres = np.zeros(0) if self.spheres is None else self.spheres.areas[self.sphere_lights]
        return np.concatenate([self.emitter_areas, spheres])

    @property
    def light_radiance(self) -> np.ndarray:
        """(E + L,) radiance of each emitter triangle, then of each sphere light."""
        spheres = np.zeros(0) if self.spheres is None else self.spheres.emission[self.sphere_lights]
        return np.concatenate([self.emitter_radiance, spheres])

    @property
    def total_emitter_area(self) -> float:
        """Σ area over the emitter triangles and sphere lights."""
        return float(self.light_areas.sum())

    @property
    def total_power(self) -> float:
        """Σ radiance × area over emitter triangles and sphere lights (radiant exitance
        would add a π)."""
        return float((self.light_radiance * self.light_areas).sum())

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
            "spheres": 0 if self.spheres is None else len(self.spheres),
            "sphere_lights": len(self.sphere_lights),
            "receivers": len(self.receivers),
            "emitter_area": self.total_emitter_area,
            "total_power": self.total_power,
        }

def checked_coordinates(points: np.ndarray, what: str, where: object) -> np.ndarray:
    """Points whose coordinates float32 kernels can hold and square (limits.coordinates)."""
    _within(where, limits.coordinates, points, what)
    return points

def checked_unit(v: np.ndarray, what: str, where: object) -> np.ndarray:
    """``v``'s rows scaled to unit length, or a one-line error at ``where`` naming a zero row."""
    norms = np.linalg.norm(v, axis=-1, keepdims=True)
    if not np.all(norms > 0):
        raise fail(where, f"{what} has zero length")
    return v / norms

def _triangle_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    v = vertices[triangles]
    return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)

RECEIVER_BYTES = 256

def check_receiver_count(count: int, what: str, where: object) -> None:
    """Refuse up front a receiver count the kernels cannot index or memory cannot hold."""
    if count > limits.MAX_COUNT:
        raise fail(where, f"{what}: {count:,} receivers, more than the {limits.MAX_COUNT:,} the kernels can index")
    _within(where, limits.memory, count * RECEIVER_BYTES, f"{what} ({count:,} receivers)")

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
                           grid_shape: Any, microfacet: dict[str, Any], geometric_normals: Any = None) -> Receivers:
    """Receivers from arrays, broadcast to one row per receiver, directions normalised."""
    p = _array(positions, "positions", where, (None, 3), "(R, 3)")
    count = len(p)
    check_receiver_count(count, "positions", where)  # before anything is broadcast to R rows
    n = _directions(_per_receiver(normals, "normals", where, count, 3), "normals", where)
    ng = n if geometric_normals is None else \
        _directions(_per_receiver(geometric_normals, "geometric_normals", where, count, 3), "geometric_normals", where)
    v = _directions(_per_receiver(view, "view", where, count, 3), "view", where)
    g = np.zeros(count, np.int64) if group is None else _per_receiver(group, "group", where, count, integer=True)
    names = ["receivers"] if group_names is None else list(group_names) if isinstance(group_names, (list, tuple)) \
        else group_names
    _check_groups(g, names, where)
    return Receivers(
        positions=p, normals=checked_unit(n, "normals", where), material=_material_codes(material, count, where),
        albedo=_per_receiver(albedo, "albedo", where, count),
        exponent=_per_receiver(exponent, "exponent", where, count),
        view=checked_unit(v, "view", where), group=g.astype(np.int32), group_names=names,
        grid_shape=_grid_shape(grid_shape, count, where),
        geometric_normals=checked_unit(ng, "geometric_normals", where),
        **grey_microfacet(microfacet, _per_receiver(albedo, "albedo", where, count), count, where),
    )


def grey_microfacet(values: dict[str, Any], albedo: np.ndarray, count: int, where: object) -> dict[str, np.ndarray]:
    """Receivers' microfacet arrays from grey values (one for all, or one per receiver;
    None: the default): every channel the same, the specular reflectance split evenly
    over the three so that their sum is the grey value."""
    out: dict[str, np.ndarray] = {}
    for name, default in MICROFACET_DEFAULTS.items():
        value = values.get(name)
        if name == "specular_weight":
            continue
        if name == "distribution" and isinstance(value, str):
            if value not in DISTRIBUTIONS:
                raise fail(where, f"distribution {value!r}: expected one of {', '.join(DISTRIBUTIONS)}")
            value = DISTRIBUTIONS[value]
        if name == "sample_visible" and value is not None and np.asarray(value).dtype == bool:
            value = np.asarray(value).astype(np.int64)
        integer = name in ("distribution", "sample_visible")
        a = _per_receiver(default if value is None else value, name, where, count, integer=integer)
        if name in _CHANNEL_ARRAYS:
            a = np.repeat(a[:, None] / (3.0 if name == "specular" else 1.0), 3, axis=1)
        out[name] = a.astype(np.int32) if integer else a
    weight = values.get("specular_weight")
    if weight is None:  # Mitsuba's specular_sampling_weight: s_mean / (d_mean + s_mean)
        s = out["specular"].sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            weight = np.where(s + albedo > 0, s / (s + albedo), 0.5)
    out["specular_weight"] = _per_receiver(weight, "specular_weight", where, count)
    return out

def _check_receivers(rx: Receivers, where: object) -> None:
    """Every receiver array: shapes, the kernels' limits, directions, material codes, groups."""
    count = len(rx.positions)
    if rx.positions.ndim != 2 or rx.positions.shape[1] != 3 or count == 0:
        raise fail(where, f"receivers: positions must have shape (R, 3) with R >= 1, got {rx.positions.shape}")
    check_receiver_count(count, "receivers", where)
    for name in _RECEIVER_ARRAYS:
        expected = (count, 3) if name in ("positions", "normals", "view", "geometric_normals", *_CHANNEL_ARRAYS) \
            else (count,)
        if getattr(rx, name).shape != expected:
            raise fail(where, f"receivers: {name} has shape {getattr(rx, name).shape}, expected {expected}")
    checked_coordinates(rx.positions, "positions", where)
    _directions(rx.normals, "receiver normals", where)
    _directions(rx.geometric_normals, "receiver geometric normals", where)
    _directions(rx.view, "receiver view", where)
    _check_codes(rx.material, where)
    _within(where, limits.float32_values, rx.albedo, "albedo")
    _within(where, limits.float32_values, rx.exponent, "exponent")
    _check_microfacet(rx, where)
    _check_groups(rx.group, rx.group_names, where)
    _grid_shape(rx.grid_shape, count, where)
    if rx.image is not None and rx.image.pixel.shape != (count,):
        raise fail(where, f"receivers: image.pixel has shape {rx.image.pixel.shape}, expected ({count},)")

# Roughness below this makes D's peak (1/(π α²)) overflow the float32 products f is made
# of at grazing half-vectors; Mitsuba's own smallest useful alpha is far above it.
MIN_ALPHA = 1e-4


def _first_bad(ok: np.ndarray, values: np.ndarray, what: str, rule: str, where: object) -> None:
    if not ok.all():
        i = int(np.argmin(ok.reshape(len(ok), -1).all(axis=1)))
        raise fail(where, f"{what} of receiver {i} is {np.asarray(values[i]).tolist()}: {rule}")


def _check_microfacet(rx: Receivers, where: object) -> None:
    """The microfacet parameters: their kernels' domains (every receiver, whatever its material)."""
    with np.errstate(invalid="ignore"):
        _first_bad((rx.alpha >= MIN_ALPHA) & (rx.alpha <= 1e3), rx.alpha, "alpha",
                   f"expected a roughness in [{MIN_ALPHA:g}, 1000]", where)
        _first_bad(np.isin(rx.distribution, list(DISTRIBUTIONS.values())), rx.distribution, "distribution",
                   f"expected a code of {DISTRIBUTIONS}", where)
        _first_bad(np.isin(rx.sample_visible, (0, 1)), rx.sample_visible, "sample_visible", "expected 0 or 1", where)
        _first_bad((rx.eta > 0) & (rx.eta <= 1e3), rx.eta, "eta", "expected an index of refraction in (0, 1000]",
                   where)
        _first_bad((rx.k >= 0) & (rx.k <= 1e3), rx.k, "k", "expected an extinction coefficient in [0, 1000]", where)
        _first_bad((rx.specular >= 0) & (rx.specular <= 1e3), rx.specular, "specular",
                   "expected a reflectance in [0, 1000]", where)
        _first_bad((rx.specular_weight >= 0) & (rx.specular_weight <= 1), rx.specular_weight, "specular_weight",
                   "expected a probability in [0, 1]", where)
    # A roughplastic interface of relative index 1 (in float32, as the kernels hold it)
    # reflects nothing and transmits everything: its tables have no meaning.
    plastic = rx.material == MATERIALS["roughplastic"].code
    _first_bad(~plastic | (rx.eta[:, 0].astype(np.float32) != np.float32(1.0)), rx.eta, "eta",
               "a roughplastic's int_ior/ext_ior must differ from 1", where)


def _geometry(vertices: Any, triangles: Any, where: object) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) float64 vertices the kernels can hold and (T, 3) int32 indices into them."""
    v = _array(vertices, "vertices", where, (None, 3), "(V, 3)")
    checked_coordinates(v, "vertices", where)
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

def assemble_scene(where: object, mesh_where: Callable[[int], object], hint: str, *, name: str, vertices: Any,
              triangles: Any, emission: Any, receivers: Receivers, triangle_mesh: Any, mesh_names: Any,
              description: str, device: str, path: Path | None = None, notes: tuple[str, ...] = (),
              environment: Environment | None = None, delta_lights: DeltaLights | None = None,
              spheres: Spheres | None = None) -> Scene:
    """The one gate of every source (a scene file, arrays): each array against the kernels'
    limits, degenerate emitters dropped, at least one emitter (a triangle, a sphere, an
    environment or a delta light) → a Scene.

    ``where`` prefixes errors; ``mesh_where(m)`` names mesh m; ``hint`` says how to add an emitter.
    """
    v, t = _geometry(vertices, triangles, where)
    e = _array(emission, "emission", where, (len(t),), f"(T,) = ({len(t)},)")
    _within(where, limits.float32_values, e, "emission")
    owner, names = _owners(triangle_mesh, mesh_names, len(t), where)
    _check_receivers(receivers, where)
    e = _drop_needles(v, t, e, owner, mesh_where)
    if environment is not None:
        if not isinstance(environment, Environment):
            raise fail(where, f"environment: expected an Environment, got {type(environment).__name__}")
        check_environment(environment, where)
    if delta_lights is not None:
        if not isinstance(delta_lights, DeltaLights):
            raise fail(where, f"delta_lights: expected DeltaLights, got {type(delta_lights).__name__}")
        check_delta_lights(delta_lights, len(receivers), where)
    if spheres is not None:
        if not isinstance(spheres, Spheres):
            raise fail(where, f"spheres: expected Spheres, got {type(spheres).__name__}")
        check_spheres(spheres, len(names), where)
    if not (e > 0).any() and (environment is None or environment.power <= 0) and \
            (delta_lights is None or not (delta_lights.irradiance > 0).any()) and \
            (spheres is None or not (spheres.emission > 0).any()):
        raise fail(where, f"the scene has no emitter ({hint})")
    return Scene(name=name, vertices=v, triangles=t, emission=e, receivers=receivers, triangle_mesh=owner,
                 mesh_names=names, description=description, path=path, device=device, notes=tuple(notes),
                 environment=environment, delta_lights=delta_lights, spheres=spheres)
