"""Gallery: a sampler whose pdf is 0 where the BSDF is not: near the horizon.

A Lambertian BSDF (``eval`` = 0.8 cos θ/π) sampled cosine-weighted within cos θ > 0.3
only, with the pdf normalised on that cap: the histogram matches the pdf and the pdf
integrates to 1, but an estimator never sees the 9% of the albedo below the cap.  Caught
by eval-quadrature: the mean of eval/pdf falls short of ∫eval.
"""

import numpy as np

import warpis

ALBEDO, CUT = 0.8, 0.3


def tangents(n):
    a = np.where(np.abs(n[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    t = np.cross(a, n)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return t, np.cross(n, t)


def make(cut):
    mass = 1.0 - cut * cut  # ∫ cos θ/π over the cap cos θ > cut

    def sample(n, wo, u):
        t, b = tangents(n)
        z = np.sqrt(1.0 - mass * u[:, 0])  # cos θ from the cap's own cdf
        r, phi = np.sqrt(1.0 - z * z), 2.0 * np.pi * u[:, 1]
        return (r * np.cos(phi))[:, None] * t + (r * np.sin(phi))[:, None] * b + z[:, None] * n

    def pdf(n, wo, w):
        c = np.sum(n * w, axis=1)
        return np.where(c > cut, c / (np.pi * mass), 0.0)

    return sample, pdf


def lambert(n, wo, w):
    return ALBEDO * np.maximum(np.sum(n * w, axis=1), 0.0) / np.pi


warpis.register_numpy_technique("lambert-capped", *make(CUT), eval=lambert, description="pdf 0 for cos θ < 0.3")
warpis.register_numpy_technique("lambert-cosine", *make(0.0), eval=lambert, description="the whole hemisphere")
