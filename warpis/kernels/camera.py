"""Primary rays: the first surface each camera pixel sees (one Warp launch over the pixels)."""

from __future__ import annotations

import numpy as np
import warp as wp

from ..scenes.camera import register_ray_caster
from .integrand import FAR


@wp.kernel(enable_backward=False)
def first_hit_kernel(mesh: wp.uint64, origin: wp.vec3, directions: wp.array(dtype=wp.vec3),
                     face: wp.array(dtype=wp.int32)):
    """The triangle the ray from ``origin`` along ``directions[i]`` meets first, −1 for none."""
    i = wp.tid()
    q = wp.mesh_query_ray(mesh, origin, directions[i], FAR)
    face[i] = -1
    if q.result:
        face[i] = q.face


def first_hits(vertices: np.ndarray, triangles: np.ndarray, origin: np.ndarray, directions: np.ndarray,
               device: str) -> np.ndarray:
    """(P,) int32: the triangle each ray from ``origin`` along ``directions`` (P, 3) meets
    first, −1 where it meets nothing, cast in float32 against a BVH of the triangles."""
    points = wp.array(np.ascontiguousarray(vertices, np.float32), dtype=wp.vec3, device=device)
    indices = wp.array(np.ascontiguousarray(triangles, np.int32).ravel(), dtype=wp.int32, device=device)
    mesh = wp.Mesh(points=points, indices=indices)  # held until the launch is done: the kernel knows it by id
    dirs = wp.array(np.ascontiguousarray(directions, np.float32), dtype=wp.vec3, device=device)
    face = wp.empty(len(directions), dtype=wp.int32, device=device)
    wp.launch(first_hit_kernel, dim=len(directions), device=device,
              inputs=[mesh.id, wp.vec3(*np.asarray(origin, np.float32)), dirs, face])
    return face.numpy()


register_ray_caster(first_hits)  # camera receivers (scenes/camera.py) are found with it
