"""Gallery: a two-lobe sampler whose pdf weighs each lobe's density by the other's probability.

With probability 0.25 a direction from a Phong lobe (exponent 30) about the mirror
direction, else a cosine-weighted one; the pdf must be 0.25 p_lobe + 0.75 p_cos.  The
bug swaps the weights, which still integrates to 1 and is what the sampler reports: only
the histogram shows it.  Caught by the chi-square test.
"""

import numpy as np

import warpis

E, P_LOBE = 30.0, 0.25


def frame(a):
    h = np.where(np.abs(a[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    t = np.cross(h, a)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return t, np.cross(a, t)


def around(axis, cos_t, phi):
    t, b = frame(axis)
    s = np.sqrt(np.maximum(0.0, 1.0 - cos_t * cos_t))
    return (s * np.cos(phi))[:, None] * t + (s * np.sin(phi))[:, None] * b + cos_t[:, None] * axis


def mirror(n, wo):
    return 2.0 * np.sum(n * wo, axis=1)[:, None] * n - wo


def sample(n, wo, u):
    lobe = u[:, 0] < P_LOBE
    v = np.where(lobe, u[:, 0] / P_LOBE, (u[:, 0] - P_LOBE) / (1.0 - P_LOBE))  # u.x reused within its part
    phi = 2.0 * np.pi * u[:, 1]
    glossy = around(mirror(n, wo), (1.0 - v) ** (1.0 / (E + 1.0)), phi)
    diffuse = around(n, np.sqrt(1.0 - v), phi)
    return np.where(lobe[:, None], glossy, diffuse)


def densities(n, wo, w):
    c = np.sum(mirror(n, wo) * w, axis=1)
    p_lobe = np.where(c > 0.0, (E + 1.0) / (2.0 * np.pi) * np.maximum(c, 0.0) ** E, 0.0)
    p_cos = np.maximum(np.sum(n * w, axis=1), 0.0) / np.pi
    return p_lobe, p_cos


def pdf_swapped(n, wo, w):
    p_lobe, p_cos = densities(n, wo, w)
    return (1.0 - P_LOBE) * p_lobe + P_LOBE * p_cos


def pdf(n, wo, w):
    p_lobe, p_cos = densities(n, wo, w)
    return P_LOBE * p_lobe + (1.0 - P_LOBE) * p_cos


warpis.register_numpy_technique("two-lobes-swapped", sample, pdf_swapped, description="lobe weights swapped in pdf")
warpis.register_numpy_technique("two-lobes", sample, pdf, description="a Phong lobe (0.25) and a cosine lobe")
