"""Gallery: a cosine-weighted sampler whose pdf forgot the cos θ: 1/π instead of cos θ/π.

The directions are right, the density is not: it integrates to 2 over the hemisphere.
Caught by pdf-integral (and the chi-square test).
"""

import numpy as np

import warpis


def tangents(n):
    a = np.where(np.abs(n[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    t = np.cross(a, n)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return t, np.cross(n, t)


def sample(n, wo, u):
    t, b = tangents(n)
    r, phi = np.sqrt(u[:, 0]), 2.0 * np.pi * u[:, 1]
    z = np.sqrt(1.0 - u[:, 0])
    return (r * np.cos(phi))[:, None] * t + (r * np.sin(phi))[:, None] * b + z[:, None] * n


def pdf_without_cos(n, wo, w):
    return np.where(np.sum(n * w, axis=1) > 0.0, 1.0 / np.pi, 0.0)


def pdf(n, wo, w):
    return np.maximum(np.sum(n * w, axis=1), 0.0) / np.pi


warpis.register_numpy_technique("cosine-no-cos", sample, pdf_without_cos, description="pdf 1/π: no cos θ")
warpis.register_numpy_technique("cosine-with-cos", sample, pdf, description="pdf cos θ/π")
