"""A scene's Warp side: the mesh, BVH, structs, self-hit slabs and everything derived on a device.

A :class:`~warpis.scenes.Scene` is plain numpy data named by its content digest; the
kernels need Warp objects built from it on one device.  :func:`upload` builds them once
per (digest, device) into a :class:`DeviceScene` and keeps it in one process-wide cache,
so two Scene objects with the same content (a scene loaded twice, one unpickled in
another process, the same file under another path) share one upload, and nothing is ever
attached to a Scene.  What is derived from the Warp side (the light table of
:mod:`warpis.kernels.techniques`, theory's block variances) lives in the same entry
(:meth:`DeviceScene.cached`).

The cache keeps the :data:`DEVICE_CACHE_SIZE` most recently used entries.  A Warp struct
refers to its mesh and BVH by id only, so code that launches kernels holds the
DeviceScene (not just ``.data``) until its launches are done.
"""

from __future__ import annotations

import os
import sys
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
import warp as wp

from ..errors import WarpisError
from ..limits import check_device
from ..vocabulary import MATERIALS
from .bvh import PARALLEL, PLANE_TOL, SELF_HIT, WideBvh, cached_wide_bvh, coplanar, magnitude, upload_wide_bvh, vec64
from .environment import EnvironmentData
from .precompiled import compile_portably, seed_kernel_cache

compile_portably(__name__)  # shipped compiled: precompiled.py says why portably

if TYPE_CHECKING:
    from ..scenes import Scene

T = TypeVar("T")

# Self-hit slab, relative to the float32 magnitude of the coordinates around a receiver:
# rays ignore surfaces within this height above the receiver's tangent plane (see
# integrand.py), and hits on triangles in a plane through the receiver (bvh.py).  2^-16
# is 128 float32 ulps: far above the rounding of Warp's watertight ray-triangle test,
# and second order in F (docs/theory.md, "The integrand at a receiver").
SELF_HIT_SLAB = float(SELF_HIT)
# Uploads kept: more than the scenes of any study (a study's cells run scene by scene, so
# a larger study only rebuilds on revisits), few enough that a process looping over many
# generated scenes does not keep every mesh alive.
DEVICE_CACHE_SIZE = 16


@wp.struct
class SceneData:
    """Everything a kernel needs to cast rays and sample the emitters of a scene."""

    mesh: wp.uint64  # every triangle: emitters occlude too
    bvh: WideBvh  # the same triangles in a 4-wide BVH: the CPU's ray query (bvh.py)
    emitter_bvh: wp.uint64  # bounds of the emitter triangles, for light-sampling pdfs
    points: wp.array(dtype=wp.vec3)
    indices: wp.array(dtype=wp.int32)  # 3 per triangle, into points
    tri_emission: wp.array(dtype=wp.float32)  # radiance of each triangle's front face
    emitter_tri: wp.array(dtype=wp.int32)  # emitter k → triangle index in `mesh`
    emitter_area: wp.array(dtype=wp.float32)
    emitter_normal: wp.array(dtype=wp.vec3)  # unit normal of each emitter triangle's front face
    emitter_slab: wp.array(dtype=wp.float32)  # self-hit slab height anywhere on it (integrand.py)
    emitter_lower: wp.vec3  # bounds of all emitter triangles, widened as the emitter BVH's boxes
    emitter_upper: wp.vec3
    # The lights the light techniques pick from: the E emitter triangles, then the L
    # emitting spheres (light k ≥ E is sphere sphere_light[k − E]).
    area_cdf: wp.array(dtype=wp.float32)  # E + L + 1 entries, 0 … 1
    power_cdf: wp.array(dtype=wp.float32)  # E + L + 1 entries, 0 … 1 (radiance × area)
    total_area: wp.float32  # of every light
    total_power: wp.float32  # Σ radiance × area over every light
    emitter_count: wp.int32  # E
    light_count: wp.int32  # E + L
    # 1 when every emitter triangle lies in one plane facing one way and no sphere emits:
    # a ray then crosses the emitters at most once, so a light sample's own point is its
    # only crossing.
    planar_emitters: wp.int32
    # Analytic spheres (spheres.py): float64, so that a sphere far from the origin or
    # seen from just above it keeps its cone exact.  One unused row when there is none.
    sphere_center: wp.array(dtype=wp.vec3d)
    sphere_radius: wp.array(dtype=wp.float64)
    sphere_emission: wp.array(dtype=wp.float32)  # radiance of its front, 0: no light
    sphere_inward: wp.array(dtype=wp.int32)  # 1: its front is the inside
    sphere_count: wp.int32
    sphere_bvh: wp.uint64  # bounds of the spheres, read beyond spheres.FEW_SPHERES
    sphere_light: wp.array(dtype=wp.int32)  # L entries: the sphere of light E + j
    # roughplastic's precomputed transmittance (and internal reflectance) per distinct
    # (distribution, alpha, eta) of the receivers: microfacet.plastic_table rows.
    plastic_table: wp.array2d(dtype=wp.float32)
    # The radiance of rays that leave the scene, and its sampling (environment.py);
    # environment.present = 0 for a scene without an environment light.
    environment: EnvironmentData


@wp.struct
class ReceiverData:
    """Receiver points, normals and the material of each."""

    position: wp.array(dtype=wp.vec3)
    normal: wp.array(dtype=wp.vec3)  # the shading normal: the BSDF's frame and cosine
    geometric: wp.array(dtype=wp.vec3)  # the surface's own normal: rays, planes and slab
    material: wp.array(dtype=wp.int32)  # vocabulary.MATERIALS code
    albedo: wp.array(dtype=wp.float32)
    exponent: wp.array(dtype=wp.float32)
    view: wp.array(dtype=wp.vec3)  # unit direction towards the viewer
    slab: wp.array(dtype=wp.float32)  # self-hit slab height above the tangent plane
    alpha: wp.array(dtype=wp.float32)  # microfacet parameters (kernels/shading.py)
    distribution: wp.array(dtype=wp.int32)
    sample_visible: wp.array(dtype=wp.int32)
    eta: wp.array(dtype=wp.vec3)
    k: wp.array(dtype=wp.vec3)
    specular: wp.array(dtype=wp.vec3)
    specular_weight: wp.array(dtype=wp.float32)
    plastic_row: wp.array(dtype=wp.int32)  # row of SceneData.plastic_table, -1 for other materials


@dataclass(eq=False)
class DeviceScene:
    """The Warp side of one scene content on one device (see :func:`upload`)."""

    device: str  # Warp's name for the device ("cpu", "cuda:0")
    data: Any  # SceneData
    receiver_data: Any  # ReceiverData
    slab: np.ndarray  # (R,) float64, read-only: self-hit slab height of each receiver
    mesh: wp.Mesh  # data.mesh is its id: the struct does not keep it alive
    emitter_bvh: wp.Bvh  # likewise data.emitter_bvh
    sphere_bvh: wp.Bvh  # and data.sphere_bvh
    _derived: dict[str, Any] = field(default_factory=dict, repr=False)
    _lock: Any = field(default_factory=threading.RLock, repr=False)

    def cached(self, key: str, build: Callable[[], T]) -> T:
        """``build()``, computed once for this content and device and kept with it (the
        light table, theory's block variances): nothing is attached to a Scene."""
        with self._lock:
            if key not in self._derived:
                self._derived[key] = build()
            return self._derived[key]


def quiet_warp() -> None:
    """Start Warp so that only warpis's own lines reach the terminal.

    On a machine without a GPU, Warp's native library prints a CUDA-driver notice to the
    process's stderr while it starts; that is noise (an unusable ``--device`` gets its own
    one-line error), so the start-up runs with file descriptor 2 pointed at /dev/null.
    """
    if hasattr(wp, "LOG_ERROR"):
        wp.config.log_level = wp.LOG_ERROR
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            wp.init()
    finally:
        os.dup2(saved, 2)
        os.close(saved)


_cache: OrderedDict[tuple[str, str], DeviceScene] = OrderedDict()
_cache_lock = threading.Lock()


def upload(scene: Scene, device: str | None = None) -> DeviceScene:
    """The Warp side of ``scene`` on ``device`` (default ``scene.device``), built on first
    use and then shared by every scene with the same digest."""
    seed_kernel_cache()  # before any launch that takes the upload (camera.first_hits is the other way in)
    name = scene.device if device is None else check_device(device)
    alias = wp.get_device(name).alias  # "cuda" and "cuda:0" share an entry
    key = (scene.digest, alias)
    with _cache_lock:  # one build per key even when threads ask at once
        entry = _cache.get(key)
        if entry is None:
            entry = _cache[key] = _build(scene, alias)
            while len(_cache) > DEVICE_CACHE_SIZE:
                _cache.popitem(last=False)
        _cache.move_to_end(key)
        return entry


def clear_device_cache() -> None:
    """Drop every cached upload (their Warp memory is freed once no caller holds them)."""
    with _cache_lock:
        _cache.clear()


def device_cache_keys() -> list[tuple[str, str]]:
    """(digest, device) of each cached upload, least recently used first."""
    with _cache_lock:
        return list(_cache)


def _cdf(weights: np.ndarray) -> np.ndarray:
    c = np.concatenate([[0.0], np.cumsum(weights, dtype=np.float64)])
    if c[-1] <= 0:  # no emitter triangle: the light techniques are refused (techniques.py)
        return np.zeros(len(c), np.float32)
    c /= c[-1]
    c[-1] = 1.0
    return c.astype(np.float32)


@wp.func
def triangle_distance(x: wp.vec3, p0: wp.vec3, p1: wp.vec3, p2: wp.vec3) -> float:
    """Distance from ``x`` to the triangle (p0, p1, p2), in float64 (Ericson 2005, 5.1.5:
    the closest point by the Voronoi region of x)."""
    p = vec64(x)
    a = vec64(p0)
    ab = vec64(p1) - a
    ac = vec64(p2) - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    closest = a
    if d1 <= wp.float64(0.0) and d2 <= wp.float64(0.0):
        return float(wp.length(p - closest))
    bp = p - vec64(p1)
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= wp.float64(0.0) and d4 <= d3:
        return float(wp.length(p - vec64(p1)))
    vc = d1 * d4 - d3 * d2
    if vc <= wp.float64(0.0) and d1 >= wp.float64(0.0) and d3 <= wp.float64(0.0):
        return float(wp.length(p - (a + (d1 / (d1 - d3)) * ab)))
    cp = p - vec64(p2)
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= wp.float64(0.0) and d5 <= d6:
        return float(wp.length(p - vec64(p2)))
    vb = d5 * d2 - d1 * d6
    if vb <= wp.float64(0.0) and d2 >= wp.float64(0.0) and d6 <= wp.float64(0.0):
        return float(wp.length(p - (a + (d2 / (d2 - d6)) * ac)))
    va = d3 * d6 - d5 * d4
    if va <= wp.float64(0.0) and (d4 - d3) >= wp.float64(0.0) and (d5 - d6) >= wp.float64(0.0):
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return float(wp.length(p - (vec64(p1) + w * (vec64(p2) - vec64(p1)))))
    denom = wp.float64(1.0) / (va + vb + vc)
    closest = a + (vb * denom) * ab + (vc * denom) * ac
    return float(wp.length(p - closest))


FLOAT32_ULPS_4 = wp.constant(4.0 * 2.0**-24)  # 4 float32 ulps, relative


@wp.func
def _corners(points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32), face: wp.int32):
    return points[indices[face * 3]], points[indices[face * 3 + 1]], points[indices[face * 3 + 2]]


@wp.func
def _off_plane(points64: wp.array(dtype=wp.vec3d), indices: wp.array(dtype=wp.int32), face: wp.int32,
               x: wp.vec3d, mag: float) -> bool:
    """Whether x lies more than 4 float32 ulps of ``mag`` off the plane of triangle
    ``face`` in the scene's own float64 coordinates (float32 rounding alone puts it 2 off)."""
    a = points64[indices[face * 3]]
    n = wp.cross(points64[indices[face * 3 + 1]] - a, points64[indices[face * 3 + 2]] - a)
    h = wp.dot(n, x - a)
    tol = wp.float64(mag) * wp.float64(FLOAT32_ULPS_4)
    return h * h > tol * tol * wp.dot(n, n)


@wp.kernel(enable_backward=False)
def _slab_kernel(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32),
                 points64: wp.array(dtype=wp.vec3d), reach: float, position: wp.array(dtype=wp.vec3),
                 position64: wp.array(dtype=wp.vec3d), normal: wp.array(dtype=wp.vec3),
                 slab: wp.array(dtype=wp.float32), hidden: wp.array(dtype=wp.int32)):
    """Slab height of each receiver x: SELF_HIT × the largest coordinate magnitude of x and
    of every triangle at x (within PLANE_TOL × its magnitude: float32's resolution
    there), leaving out the triangles of x's own plane (through x, normal parallel to
    x's), whose hits the rays ignore (bvh.py): so a huge floor under x costs no slab,
    only a huge surface that bends away from x does.

    ``hidden``: −1, or 3 × a triangle + why it leaves no safe slab: (0) one at x to float32's
    resolution but not through x (farther than x's own slab), so rays cannot tell which
    side of it they leave; (1) one of x's own plane for the rays although, in the scene's
    float64 coordinates, x lies off it (a parallel surface nearer than float32
    resolves); or (2) one nearer to x than the slab and not at x (the slab would hide it).

    Warp's watertight ray test works on vertex − origin differences, so its rounding
    scales with those magnitudes; the slab follows them and nothing else (no scene size).
    ``reach`` (PLANE_TOL × the largest magnitude in the scene) bounds every triangle's
    resolution, so the box query finds each triangle that can be at x.
    """
    r = wp.tid()
    x = position[r]
    nx = normal[r]
    own = magnitude(x)
    scale = own
    hidden[r] = -1
    query = wp.mesh_query_aabb(mesh, x - wp.vec3(reach), x + wp.vec3(reach))
    face = wp.int32(0)
    while wp.mesh_query_aabb_next(query, face):
        p0, p1, p2 = _corners(points, indices, face)
        mag = wp.max(wp.max(magnitude(p0), magnitude(p1)), wp.max(magnitude(p2), own))
        dist = triangle_distance(x, p0, p1, p2)
        if dist <= mag * PLANE_TOL:  # a surface at x, to float32's resolution there
            if not coplanar(p0, p1, p2, x, nx):
                scale = wp.max(scale, mag)
                if dist > own * SELF_HIT:  # near x but not through it: its side is lost
                    hidden[r] = 3 * face
            elif _off_plane(points64, indices, face, position64[r], mag):
                hidden[r] = 3 * face + 1  # a parallel surface the rays would take for x's own plane
    delta = scale * SELF_HIT
    if scale > own and hidden[r] < 0:  # a surface coarser than x's own coordinates sets the slab
        near = wp.mesh_query_aabb(mesh, x - wp.vec3(delta), x + wp.vec3(delta))
        while wp.mesh_query_aabb_next(near, face):
            p0, p1, p2 = _corners(points, indices, face)
            mag = wp.max(wp.max(magnitude(p0), magnitude(p1)), wp.max(magnitude(p2), own))
            dist = triangle_distance(x, p0, p1, p2)
            if dist > mag * PLANE_TOL and dist < delta and not coplanar(p0, p1, p2, x, nx):
                hidden[r] = 3 * face + 2  # what the slab would hide
    slab[r] = delta


def planar_emitters(corners: np.ndarray) -> bool:
    """Whether the emitter triangles ``corners`` (E, 3, 3) lie in one plane and face one
    way (to float32 rounding): then a ray crosses them at most once (where it crosses the
    plane), and the light pdf of a sampled point is that point's own density."""
    c = np.asarray(corners, dtype=np.float64)
    normals = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
    lengths = np.linalg.norm(normals, axis=1)
    if len(c) == 0 or not np.all(lengths > 0):
        return False
    unit = normals / lengths[:, None]
    axis = unit[np.argmax(lengths)]
    scale = float(np.abs(c).max())
    offsets = (c - c[np.argmax(lengths), 0]) @ axis
    return bool(np.all(unit @ axis > 0.0) and np.all(np.abs(offsets) <= 1e-6 * scale))


def _emitter_boxes(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float32 bounds of emitter triangles, widened by a little of each triangle's own
    size and magnitude: flat (axis-aligned) triangles get boxes of non-zero width, and a
    ray the widened triangle test (EDGE_SLACK) accepts is never culled by float32 box
    rounding.  A wider box costs a few more triangle tests, never a wrong pdf."""
    lo, hi = corners.min(axis=1), corners.max(axis=1)
    pad = 1e-4 * (hi - lo).max(axis=1) + 2.0**-14 * np.abs(corners).max(axis=(1, 2))
    return (lo - pad[:, None]).astype(np.float32), (hi + pad[:, None]).astype(np.float32)


def emitter_slabs(scene: Scene) -> np.ndarray:
    """(E,) float32: the self-hit slab at the emitter end of a shadow ray for each emitter
    triangle k, SELF_HIT × the largest coordinate magnitude of the triangles that share a
    vertex with k and bend away from its plane.  Triangles of k's plane need none: the
    shadow ray ignores hits on the plane of its end point (bvh.coplanar, whose rule this
    follows: parallel normals and every corner of k within PLANE_TOL of the triangle's
    plane), and the end point's own magnitude enters at run time (integrand.py)."""
    from scipy.sparse import csr_matrix

    corners = scene.triangle_vertices().astype(np.float32).astype(np.float64)  # (T, 3, 3)
    count, emitters = len(scene.triangles), scene.emitters
    rows = np.repeat(np.arange(count), 3)
    incidence = csr_matrix((np.ones(3 * count), (rows, scene.triangles.ravel())),
                           shape=(count, len(scene.vertices)))
    pairs = (incidence[emitters] @ incidence.T).tocoo()  # (emitter k, triangle j) sharing a vertex
    k, j = pairs.row, pairs.col
    normal = np.cross(corners[j, 1] - corners[j, 0], corners[j, 2] - corners[j, 0])
    height = np.einsum("pj,pcj->pc", normal, corners[emitters[k]] - corners[j, :1])  # k's corners over j's plane
    size = np.abs(corners).max(axis=(1, 2))
    length = np.linalg.norm(normal, axis=1)
    own = np.cross(corners[emitters[k], 1] - corners[emitters[k], 0], corners[emitters[k], 2] - corners[emitters[k], 0])
    parallel = np.abs(np.einsum("pj,pj->p", normal, own)) >= PARALLEL * length * np.linalg.norm(own, axis=1)
    tol = PLANE_TOL * np.maximum(size[j], size[emitters[k]]) * length
    bends = ~parallel | (np.abs(height) > tol[:, None]).any(axis=1)
    out = np.zeros(len(emitters))
    np.maximum.at(out, k[bends], SELF_HIT_SLAB * size[j[bends]])
    return out.astype(np.float32)


def plastic_rows(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """roughplastic's tables: one row per distinct (distribution, alpha, eta) among the
    roughplastic receivers (a zero row when there is none), and each receiver's row (-1
    for other materials), computed once per upload for both structs."""
    from .microfacet import PLASTIC_TABLE_WIDTH, plastic_table

    rx = scene.receivers
    rows = np.full(len(rx), -1, np.int32)
    plastic = np.flatnonzero(rx.material == MATERIALS["roughplastic"].code)
    if len(plastic) == 0:
        return np.zeros((1, PLASTIC_TABLE_WIDTH), np.float32), rows
    keys = np.stack([rx.distribution[plastic].astype(np.float64), rx.alpha[plastic], rx.eta[plastic, 0]], axis=1)
    unique, inverse = np.unique(keys, axis=0, return_inverse=True)
    rows[plastic] = inverse.reshape(-1)
    table = np.stack([plastic_table(int(d), float(a), float(e)) for d, a, e in unique]).astype(np.float32)
    return table, rows


def _scene_data(scene: Scene, plastic_table: np.ndarray) -> tuple[Any, wp.Mesh, wp.Bvh, wp.Bvh]:
    """The SceneData struct of ``scene`` on the current device, with its mesh and BVHs."""
    points = wp.array(scene.vertices.astype(np.float32), dtype=wp.vec3)
    indices = wp.array(scene.triangles.reshape(-1).astype(np.int32), dtype=wp.int32)
    mesh = wp.Mesh(points=points, indices=indices)
    lower, upper = _emitter_boxes(scene.triangle_vertices(scene.emitters))
    # A scene lit by its environment alone has no emitter triangle: its emitter BVH (read
    # only beyond FEW_EMITTERS emitters) holds one empty box.
    boxes = (lower, upper) if len(lower) else (np.zeros((1, 3), np.float32), np.zeros((1, 3), np.float32))
    emitter_bvh = wp.Bvh(wp.array(boxes[0], dtype=wp.vec3), wp.array(boxes[1], dtype=wp.vec3))
    lower_all, upper_all = (lower.min(axis=0), upper.max(axis=0)) if len(lower) else (np.zeros(3), np.zeros(3))
    d = SceneData()
    d.mesh = mesh.id
    # Every device's ray queries walk warpis's 4-wide BVH: its leaf test ignores the hits
    # on a ray's own planes, which Warp's queries cannot (bvh.py).
    d.bvh = upload_wide_bvh(cached_wide_bvh(scene.vertices, scene.triangles, scene.emitters))
    d.emitter_bvh = emitter_bvh.id
    d.points = points
    d.indices = indices
    d.tri_emission = wp.array(scene.emission.astype(np.float32), dtype=wp.float32)
    d.emitter_tri = wp.array(scene.emitters, dtype=wp.int32)
    d.emitter_area = wp.array(scene.emitter_areas.astype(np.float32), dtype=wp.float32)
    corners = scene.triangle_vertices(scene.emitters).astype(np.float32).astype(np.float64)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    d.emitter_normal = wp.array(normals.astype(np.float32), dtype=wp.vec3)
    d.emitter_slab = wp.array(emitter_slabs(scene), dtype=wp.float32)
    d.area_cdf = wp.array(_cdf(scene.light_areas), dtype=wp.float32)
    d.power_cdf = wp.array(_cdf(scene.light_areas * scene.light_radiance), dtype=wp.float32)
    d.total_area = float(scene.total_emitter_area)
    d.total_power = float(scene.total_power)
    d.emitter_count = int(scene.emitter_count)
    d.light_count = int(scene.light_count)
    d.emitter_lower = wp.vec3(*lower_all.astype(np.float32))
    d.emitter_upper = wp.vec3(*upper_all.astype(np.float32))
    d.planar_emitters = int(len(scene.sphere_lights) == 0 and planar_emitters(scene.triangle_vertices(scene.emitters)))
    d.plastic_table = wp.array(plastic_table, dtype=wp.float32)
    d.environment = environment_data(scene)
    sphere_bvh = _sphere_data(scene, d)
    return d, mesh, emitter_bvh, sphere_bvh


def _sphere_data(scene: Scene, d: Any) -> wp.Bvh:
    """Fill the sphere fields of ``d``; the spheres' BVH (one empty box for none)."""
    spheres = scene.spheres
    if spheres is None:
        centers, radii, emission, inward = np.zeros((1, 3)), np.ones(1), np.zeros(1), np.zeros(1, np.int32)
    else:
        centers, radii, emission, inward = spheres.centers, spheres.radii, spheres.emission, spheres.inward
    d.sphere_center = wp.array(np.ascontiguousarray(centers, np.float64), dtype=wp.vec3d)
    d.sphere_radius = wp.array(np.ascontiguousarray(radii, np.float64), dtype=wp.float64)
    d.sphere_emission = wp.array(np.asarray(emission, np.float32), dtype=wp.float32)
    d.sphere_inward = wp.array(np.asarray(inward, np.int32), dtype=wp.int32)
    d.sphere_count = 0 if spheres is None else len(spheres)
    lights = scene.sphere_lights
    d.sphere_light = wp.array(lights if len(lights) else np.zeros(1, np.int32), dtype=wp.int32)
    # float32 boxes widened past the float64 sphere by its own rounding and a little more:
    # a box may hold more than its sphere, never less.
    pad = 1e-5 * radii + 2.0**-20 * (np.abs(centers).max(axis=1) + radii)
    lower = (centers - (radii + pad)[:, None]).astype(np.float32)
    upper = (centers + (radii + pad)[:, None]).astype(np.float32)
    if spheres is None:
        lower, upper = np.zeros((1, 3), np.float32), np.zeros((1, 3), np.float32)
    bvh = wp.Bvh(wp.array(lower, dtype=wp.vec3), wp.array(upper, dtype=wp.vec3))
    d.sphere_bvh = bvh.id
    return bvh


def environment_data(scene: Scene) -> Any:
    """The EnvironmentData struct of ``scene`` on the current device: its table, rotation
    and the ``envmap`` technique's CDFs over the cells' exact energies (a small empty
    table, ``present`` = 0, for a scene without an environment)."""
    from ..scenes.environment import cell_energies  # the scenes import this module

    env = scene.environment
    e = EnvironmentData()
    texels = np.zeros((3, 3)) if env is None else env.table
    energy = cell_energies(texels)
    rows = energy.sum(axis=1)
    total = float(rows.sum())
    e.present = 0 if env is None else 1
    e.texels = wp.array(texels.astype(np.float32), dtype=wp.float32)
    rotation = np.eye(3) if env is None else env.rotation
    e.to_world = wp.mat33(*rotation.astype(np.float32).ravel())
    e.to_local = wp.mat33(*rotation.T.astype(np.float32).ravel())
    e.row_cdf = wp.array(_cdf64(rows), dtype=wp.float64)
    e.col_cdf = wp.array(np.stack([_cdf64(row) for row in energy]), dtype=wp.float64)
    e.total = total
    return e


def _cdf64(weights: np.ndarray) -> np.ndarray:
    """0, the normalised running sums of ``weights``, … 1 (all zeros when they sum to 0)."""
    c = np.concatenate([[0.0], np.cumsum(weights, dtype=np.float64)])
    if c[-1] <= 0:
        return np.zeros_like(c)
    c /= c[-1]
    c[-1] = 1.0
    return c


def _receiver_data(scene: Scene, d: Any, plastic_row: np.ndarray) -> Any:
    """The ReceiverData struct of ``scene``, its slabs computed against the mesh of ``d``."""
    r = scene.receivers
    rd = ReceiverData()
    rd.position = wp.array(r.positions.astype(np.float32), dtype=wp.vec3)
    rd.normal = wp.array(r.normals.astype(np.float32), dtype=wp.vec3)
    rd.geometric = wp.array(r.geometric_normals.astype(np.float32), dtype=wp.vec3)
    rd.material = wp.array(r.material.astype(np.int32), dtype=wp.int32)
    rd.albedo = wp.array(r.albedo.astype(np.float32), dtype=wp.float32)
    rd.exponent = wp.array(r.exponent.astype(np.float32), dtype=wp.float32)
    rd.view = wp.array(r.view.astype(np.float32), dtype=wp.vec3)
    rd.slab = wp.zeros(len(r), dtype=wp.float32)
    rd.alpha = wp.array(r.alpha.astype(np.float32), dtype=wp.float32)
    rd.distribution = wp.array(r.distribution.astype(np.int32), dtype=wp.int32)
    rd.sample_visible = wp.array(r.sample_visible.astype(np.int32), dtype=wp.int32)
    rd.eta = wp.array(r.eta.astype(np.float32), dtype=wp.vec3)
    rd.k = wp.array(r.k.astype(np.float32), dtype=wp.vec3)
    rd.specular = wp.array(r.specular.astype(np.float32), dtype=wp.vec3)
    rd.specular_weight = wp.array(r.specular_weight.astype(np.float32), dtype=wp.float32)
    rd.plastic_row = wp.array(plastic_row, dtype=wp.int32)
    hidden = wp.zeros(len(r), dtype=wp.int32)
    reach = PLANE_TOL * float(np.abs(scene.vertices.astype(np.float32)).max(initial=0.0)) + 1.0e-30
    points64 = wp.array(scene.vertices.astype(np.float64), dtype=wp.vec3d)
    position64 = wp.array(r.positions.astype(np.float64), dtype=wp.vec3d)
    wp.launch(_slab_kernel, dim=len(r), inputs=[d.mesh, d.points, d.indices, points64, reach, rd.position, position64,
                                                rd.geometric, rd.slab, hidden])
    _refuse_hidden(scene, hidden.numpy(), rd.slab.numpy())
    return rd


def _refuse_hidden(scene: Scene, hidden: np.ndarray, slab: np.ndarray) -> None:
    """A receiver that no float32 slab keeps safe (``_slab_kernel``'s ``hidden``): one line."""
    bad = np.flatnonzero(hidden >= 0)
    if len(bad) == 0:
        return
    r, (face, why) = int(bad[0]), divmod(int(hidden[bad[0]]), 3)
    x = scene.receivers.positions[r]
    tri = scene.triangle_vertices(np.array([face]))[0].astype(np.float32).astype(np.float64)  # as the rays see it
    normal = np.cross(tri[1] - tri[0], tri[2] - tri[0])
    height = abs(float((x - tri[0]) @ normal)) / float(np.linalg.norm(normal))
    which = f"triangle {face} (mesh {scene.mesh_names[scene.triangle_mesh[face]]!r})"
    problem = (f"lies {height:.3g} from the plane of {which}, nearer than float32 resolves at its coordinates (up "
               f"to {np.abs(tri).max():.3g}), so rays cannot tell which side of it they leave",
               f"lies {height:.3g} off the plane of {which}, a parallel surface nearer than float32 resolves at its "
               f"coordinates (up to {np.abs(tri).max():.3g}), which rays would take for the receiver's own",
               f"touches a surface so large that float32 rays must skip {slab[r]:.3g} above it, which would hide "
               f"{which}, {height:.3g} away")[why]
    more = f"; {len(bad) - 1} more receiver(s) too" if len(bad) > 1 else ""
    raise WarpisError(f"scene {scene.name!r}: receiver {r} at ({x[0]:.6g}, {x[1]:.6g}, {x[2]:.6g}) {problem}{more}: "
                      f"put the receiver on that surface or farther from it, or split the large triangles")


def _build(scene: Scene, device: str) -> DeviceScene:
    """Upload ``scene`` to ``device``: its mesh, emitter BVH, structs and slabs."""
    with wp.ScopedDevice(device):
        table, rows = plastic_rows(scene)
        d, mesh, emitter_bvh, sphere_bvh = _scene_data(scene, table)
        rd = _receiver_data(scene, d, rows)
    slab = rd.slab.numpy().astype(np.float64)
    slab.flags.writeable = False
    return DeviceScene(device, d, rd, slab, mesh, emitter_bvh, sphere_bvh)
