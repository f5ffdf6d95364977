"""Gallery: a half-vector sampler without the Jacobian of the reflection.

Blinn-Phong sampling: a half vector h with density (e+1)/(2π) cos^e θh about the normal,
then wo reflected about it.  The density of wo is that of h times |dωh/dωo| = 1/(4 wo·h);
the bug returns the density of h itself.  Caught by the chi-square test (the histogram of
wo is not the pdf; its integral is off too).
"""

import numpy as np

import warpis

E = 20.0


def tangents(n):
    a = np.where(np.abs(n[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    t = np.cross(a, n)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return t, np.cross(n, t)


def sample(n, wo, u):
    t, b = tangents(n)
    c = (1.0 - u[:, 0]) ** (1.0 / (E + 1.0))
    s = np.sqrt(np.maximum(0.0, 1.0 - c * c))
    phi = 2.0 * np.pi * u[:, 1]
    h = (s * np.cos(phi))[:, None] * t + (s * np.sin(phi))[:, None] * b + c[:, None] * n
    return 2.0 * np.sum(wo * h, axis=1)[:, None] * h - wo  # wo reflected about h (wo: towards the viewer)


def half_vector_density(n, wo, w):
    h = wo + w
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-300)
    c = np.abs(np.sum(n * h, axis=1))  # h and −h reflect wo to the same w: the lobe's is the one above
    return (E + 1.0) / (2.0 * np.pi) * c**E, h


def pdf_without_jacobian(n, wo, w):
    return half_vector_density(n, wo, w)[0]


def pdf(n, wo, w):
    p, h = half_vector_density(n, wo, w)
    return p / (4.0 * np.maximum(np.abs(np.sum(w * h, axis=1)), 1e-300))


warpis.register_numpy_technique("half-vector-no-jacobian", sample, pdf_without_jacobian,
                                description="Blinn-Phong half vectors; pdf of h, not of wo")
warpis.register_numpy_technique("half-vector", sample, pdf, description="Blinn-Phong half vectors; pdf of wo")
