"""Shading normals: a mesh's vertex normals interpolated at points of its triangles.

Mitsuba shades a mesh that has vertex normals (an OBJ or PLY that carries them, or one
without them, for which its loader computes them unless ``face_normals`` is set) with
the normal interpolated from them: n = normalize(b0·n0 + b1·n1 + b2·n2) at the point's
barycentric coordinates.  warpis's receivers take that normal for their BSDF and its
cosine, and keep the triangle's own normal for what rays see (kernels/integrand.py).
"""

from __future__ import annotations

import numpy as np


def barycentric(tris: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(K, 3) barycentric coordinates of ``points`` (K, 3) in triangles ``tris`` (K, 3, 3),
    of the point's projection onto each triangle's plane (float64 normal equations)."""
    e1, e2, d = tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0], points - tris[:, 0]
    d11, d12, d22 = (np.einsum("ij,ij->i", a, b) for a, b in ((e1, e1), (e1, e2), (e2, e2)))
    d1, d2 = np.einsum("ij,ij->i", d, e1), np.einsum("ij,ij->i", d, e2)
    with np.errstate(divide="ignore", invalid="ignore"):
        det = d11 * d22 - d12 * d12
        b1, b2 = (d22 * d1 - d12 * d2) / det, (d11 * d2 - d12 * d1) / det
    return np.stack([1.0 - b1 - b2, b1, b2], axis=1)


def interpolate_normals(corner_normals: np.ndarray, tris: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(K, 3) unit shading normals at ``points`` (K, 3) of triangles ``tris`` (K, 3, 3)
    whose corners carry ``corner_normals`` (K, 3, 3); NaN where they cancel."""
    b = barycentric(tris, points)
    n = np.einsum("kc,kcj->kj", b, corner_normals)
    with np.errstate(divide="ignore", invalid="ignore"):
        return n / np.linalg.norm(n, axis=1, keepdims=True)
