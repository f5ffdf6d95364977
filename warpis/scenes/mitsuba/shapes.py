"""Shapes: every triangle mesh (obj, ply, serialized, cube, ...) as Mitsuba holds it,
already in world space; ``rectangle`` as its two triangles; ``sphere`` as an analytic
sphere (scenes/spheres.py), intersected and sampled exactly as Mitsuba does, or
tessellated where the receivers file says ``tessellate = true`` (for comparisons);
``disk`` and ``cylinder`` tessellated (``DISK_SEGMENTS``, ``CYLINDER_SEGMENTS``).  A
tessellation's vertices are pushed out so that it keeps the analytic area, and its
error is reported (``TESSELLATION_ERROR``).  Each triangle winds
counter-clockwise around the side Mitsuba calls the front (its shading normal, after
``flip_normals``): the side an area light emits on and a one-sided BSDF reflects on.
Each shape carries its material (:mod:`.materials`) and area emitter (:mod:`.emitters`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import fail
from ..lambert import triangle_irradiance
from ..spheres import Spheres, tessellate_sphere
from .emitters import DELTA_KINDS, EMITTER_PLUGINS, ENVIRONMENT_CLASSES, SUPPORTED_EMITTERS, area_radiance
from .materials import Material, read_material
from .parse import MitsubaSession, object_parameters, rgb_text, transform_matrix

# Tessellation of Mitsuba's analytic shapes, the coarsest for which an emitter's area and
# the irradiance it casts at a unit distance stay within TESSELLATION_ERROR of the
# analytic shape's (each load reports its own figures in Scene.notes):
# an icosphere of 20·4^3 = 1280 triangles, a fan of 64 triangles, a tube of 2 × 128.
DISK_SEGMENTS = 64
CYLINDER_SEGMENTS = 128
TESSELLATION_ERROR = 1e-3

SUPPORTED_SHAPES = "triangle meshes (obj, ply, serialized, cube, ...), rectangle, sphere, disk and cylinder"
_SHAPE_PLUGINS = {"OBJMesh": "obj", "PLYMesh": "ply", "SerializedMesh": "serialized", "Cube": "cube",
                  "Rectangle": "rectangle", "Sphere": "sphere", "Disk": "disk", "Cylinder": "cylinder",
                  "Instance": "instance", "ShapeGroup": "shapegroup", "BSplineCurve": "bsplinecurve",
                  "LinearCurve": "linearcurve", "SDFGrid": "sdfgrid", "Ellipsoids": "ellipsoids",
                  "EllipsoidsMesh": "ellipsoidsmesh", "Mesh": "mesh"}


@dataclass
class Shape:
    """One Mitsuba shape as triangles: the front of each (counter-clockwise) is Mitsuba's."""

    label: str  # its id, or "<plugin> #<position>" for a shape without one
    plugin: str
    vertices: np.ndarray  # (V, 3) float64, world space
    faces: np.ndarray  # (F, 3) int64
    radiance: np.ndarray | None  # linear sRGB of its area emitter
    emission: float  # radiance in warpis's channel (0: none)
    material: Material
    deviation: float = 0.0  # how far the triangles stray from Mitsuba's analytic surface
    id: str = ""
    shading: np.ndarray | None = None  # (V, 3) Mitsuba's vertex normals on the front side, for a mesh
    # (P, 3) → (P, 3) Mitsuba's front normal of a curved analytic shape (sphere, cylinder)
    # at points of its tessellation, unnormalised: what Mitsuba shades with there
    analytic_normal: Any = None
    # An analytic sphere (no triangles): (centre, radius, inward: its front is the inside)
    sphere: tuple[np.ndarray, float, bool] | None = None
    notes: list[str] = field(default_factory=list)


def read_shapes(session: MitsubaSession, scene: Any, file: Path, weights: np.ndarray, lit: bool = False,
                tessellate: bool = False) -> list[Shape]:
    """The scene's shapes; ``lit``: an environment lights the scene, so it needs no area
    emitter; ``tessellate``: spheres as triangles rather than analytic spheres."""
    mi = session.mi
    for emitter in scene.emitters():
        cls = emitter.class_name()
        if cls != "AreaLight" and cls not in ENVIRONMENT_CLASSES and cls not in DELTA_KINDS:
            name = f"{emitter.id()!r} ({EMITTER_PLUGINS.get(cls, cls)})" if emitter.id() else \
                repr(EMITTER_PLUGINS.get(cls, cls))
            raise fail(file, f"emitter {name}: warpis supports {SUPPORTED_EMITTERS}")
    out = []
    for i, shape in enumerate(scene.shapes()):
        cls = shape.class_name()
        plugin = _SHAPE_PLUGINS.get(cls, cls.lower())
        label = shape.id() or f"{plugin} #{i + 1}"
        where = f"{file}: shape {label!r}"
        notes: list[str] = []
        vertices, faces, deviation, shading, analytic_normal, sphere = _geometry(mi, shape, cls, where, notes,
                                                                                tessellate)
        radiance, emission = None, 0.0
        if shape.is_emitter():
            radiance, emission = area_radiance(mi, shape.emitter(), where, weights)
        material = read_material(mi, shape.bsdf(), where, weights, notes)
        s = Shape(label=label, plugin=plugin, vertices=vertices, faces=faces, radiance=radiance, emission=emission,
                  material=material, deviation=deviation, id=shape.id(), shading=shading,
                  analytic_normal=analytic_normal, sphere=sphere)
        tessellated = plugin in ("disk", "cylinder") or (plugin == "sphere" and sphere is None)
        if radiance is not None:
            s.notes.append(f"{label}: area emitter, radiance {emission:.6g} (linear sRGB {rgb_text(radiance)})"
                           + ("; 0 in this channel: it emits nothing here" if emission == 0 else ""))
            if tessellated:
                s.notes.append(f"{label}: {_tessellation_note(mi, shape, plugin, vertices, faces)}")
        else:
            s.notes.append(f"{label}: {material.text}")
            if tessellated:
                s.notes.append(f"{label}: {plugin} tessellated into {len(faces)} triangles (pushed out to keep its "
                               f"area)")
        s.notes += [f"{label}: {note}" for note in dict.fromkeys(notes)]
        out.append(s)
    if not lit and not any(s.radiance is not None for s in out):
        raise fail(file, f"the scene has no emitter: warpis needs at least one <shape> with an "
                         f"<emitter type=\"area\">, or an envmap or constant emitter ({SUPPORTED_EMITTERS})")
    return out


def _geometry(mi: Any, shape: Any, cls: str, where: str, notes: list[str], tessellate: bool = False
              ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray | None, Any, Any]:
    """Vertices and faces of a shape, each face wound counter-clockwise around Mitsuba's
    front side; how far they stray from Mitsuba's surface (0 for triangle meshes); a
    mesh's vertex normals, which Mitsuba shades with; a curved analytic shape's front
    normal as a function of the point, which Mitsuba shades with there; and for an
    analytic sphere (no faces) its (centre, radius, inward)."""
    kind = int(shape.shape_type())
    plugin = _SHAPE_PLUGINS.get(cls, cls.lower())
    flipped = bool(shape.has_flipped_normals())
    if kind == int(mi.ShapeType.Mesh):
        vertices, faces, shading = _mesh(mi, shape, where, notes)
        return vertices, faces, 0.0, shading, None, None
    if kind in (int(mi.ShapeType.Rectangle), int(mi.ShapeType.Sphere), int(mi.ShapeType.Disk),
                int(mi.ShapeType.Cylinder)):
        m = transform_matrix(object_parameters(mi, shape)["to_world"])
        if not np.all(np.isfinite(m)) or abs(np.linalg.det(m[:3, :3])) == 0:
            raise fail(where, f"{plugin}: its to_world is singular or not finite")
        sign = -1.0 if flipped else 1.0
        if kind == int(mi.ShapeType.Sphere) and not tessellate:
            radius = _similarity_scale(m, where, "sphere")
            centre = m[:3, 3].copy()
            return (np.zeros((0, 3)), np.zeros((0, 3), np.int64), 0.0, None, lambda p: sign * (p - centre),
                    (centre, radius, flipped))
        builder = {int(mi.ShapeType.Rectangle): _rectangle, int(mi.ShapeType.Sphere): _sphere,
                   int(mi.ShapeType.Disk): _disk, int(mi.ShapeType.Cylinder): _cylinder}[kind]
        vertices, faces, normal, deviation = builder(m, where)
        curved = kind in (int(mi.ShapeType.Sphere), int(mi.ShapeType.Cylinder))
        analytic = (lambda p: sign * normal(p)) if curved else None
        return vertices, _orient(vertices, faces, normal, sign), deviation, None, analytic, None
    if plugin in ("instance", "shapegroup"):
        raise fail(where, f"{plugin}s are not supported; warpis supports {SUPPORTED_SHAPES}")
    raise fail(where, f"shape type {plugin!r} is not supported; warpis supports {SUPPORTED_SHAPES}")


def _mesh(mi: Any, shape: Any, where: str, notes: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A Mitsuba triangle mesh: its world-space vertices, and its faces wound around the
    side of its vertex normals (Mitsuba's front: its area light emits there and its BSDF
    reflects there), flipped with flip_normals."""
    params = object_parameters(mi, shape)
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
    radius) tessellated: an icosphere pushed out to the sphere's area (scenes/spheres.py)."""
    radius = _similarity_scale(m, where, "sphere")
    centre = m[:3, 3].copy()
    vertices, faces, deviation = tessellate_sphere(centre, radius, rotation=m[:3, :3] / radius)
    return vertices, faces, lambda c: c - centre, deviation


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
    m = transform_matrix(object_parameters(mi, shape)["to_world"])
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
    penumbra = ("; larger in a penumbra, where a sliver of it shows (0.77% measured where under 1% of a sphere "
                "shows: docs/mitsuba-scenes.md); without tessellate = true it is an exact analytic sphere"
                if plugin == "sphere" else "")
    return (f"{plugin} tessellated into {len(faces)} triangles (pushed out to keep its area): area error "
            f"{_percent(area_error)}, irradiance error {_percent(irradiance_error)} {place}{penumbra}")


def _percent(x: float) -> str:
    return "0%" if abs(x) < 1e-12 else f"{100 * x:+.2g}%"


def shape_spheres(shapes: list[Shape]) -> Spheres | None:
    """The analytic spheres among ``shapes`` (their owner: the shape's index), or None."""
    rows = [(k, s) for k, s in enumerate(shapes) if s.sphere is not None]
    if not rows:
        return None
    return Spheres(centers=np.array([s.sphere[0] for _, s in rows], np.float64),
                   radii=np.array([s.sphere[1] for _, s in rows], np.float64),
                   emission=np.array([s.emission for _, s in rows], np.float64),
                   inward=np.array([int(s.sphere[2]) for _, s in rows], np.int32),
                   owner=np.array([k for k, _ in rows], np.int32))


def concatenate_shapes(shapes: list[Shape]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """All shapes' vertices, triangles, per-triangle emission and owning shape, in order."""
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
