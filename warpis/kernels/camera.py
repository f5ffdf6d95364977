"""Primary rays: the first surface each camera pixel sees (one Warp launch over the pixels)."""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from ..scenes.camera import register_ray_caster
from .integrand import FAR
from .precompiled import compile_portably, seed_kernel_cache
from .spheres import NO_ROOT, sphere_roots

compile_portably(__name__)  # shipped compiled: precompiled.py says why portably


@wp.kernel(enable_backward=False)
def first_hit_kernel(mesh: wp.uint64, origin: wp.vec3, directions: wp.array(dtype=wp.vec3),
                     centers: wp.array(dtype=wp.vec3d), radii: wp.array(dtype=wp.float64), triangles: wp.int32,
                     face: wp.array(dtype=wp.int32)):
    """The primitive the ray from ``origin`` along ``directions[i]`` meets first: its
    triangle, ``triangles`` + s for analytic sphere s, −1 for none."""
    i = wp.tid()
    d = directions[i]
    q = wp.mesh_query_ray(mesh, origin, d, FAR)
    face[i] = -1
    best = float(FAR)
    if q.result:
        face[i] = q.face
        best = q.t
    for s in range(radii.shape[0]):
        roots = sphere_roots(origin, d, centers[s], radii[s])
        if roots[1] != wp.float64(NO_ROOT):
            t = float(wp.where(roots[0] > wp.float64(0.0), roots[0], roots[1]))
            if t > 0.0 and t < best:
                best = t
                face[i] = triangles + s


def first_hits(vertices: np.ndarray, triangles: np.ndarray, origin: np.ndarray, directions: np.ndarray,
               device: str, spheres: Any = None) -> np.ndarray:
    """(P,) int32: the primitive each ray from ``origin`` along ``directions`` (P, 3) meets
    first — a triangle, T + s for sphere s of ``spheres`` — and −1 where it meets nothing,
    cast in float32 against a BVH of the triangles (float64 against the spheres)."""
    seed_kernel_cache()  # this launch needs no upload, the other way into the shipped modules
    points = wp.array(np.ascontiguousarray(vertices, np.float32), dtype=wp.vec3, device=device)
    indices = wp.array(np.ascontiguousarray(triangles, np.int32).ravel(), dtype=wp.int32, device=device)
    mesh = wp.Mesh(points=points, indices=indices)  # held until the launch is done: the kernel knows it by id
    dirs = wp.array(np.ascontiguousarray(directions, np.float32), dtype=wp.vec3, device=device)
    centers = np.zeros((0, 3)) if spheres is None else spheres.centers
    radii = np.zeros(0) if spheres is None else spheres.radii
    face = wp.empty(len(directions), dtype=wp.int32, device=device)
    wp.launch(first_hit_kernel, dim=len(directions), device=device,
              inputs=[mesh.id, wp.vec3(*np.asarray(origin, np.float32)), dirs,
                      wp.array(np.ascontiguousarray(centers, np.float64), dtype=wp.vec3d, device=device),
                      wp.array(np.ascontiguousarray(radii, np.float64), dtype=wp.float64, device=device),
                      len(triangles), face])
    return face.numpy()


register_ray_caster(first_hits)  # camera receivers (scenes/camera.py) are found with it
