"""Gallery: the pdf a sampler reports at sample time is 7% off the pdf it evaluates later.

Cosine-weighted hemisphere sampling (Malley) whose ``sample`` returns (w, pdf) with the
density × 1.07, while ``pdf`` returns cos θ/π: the histogram agrees with ``pdf``, but an
estimator dividing by the sample-time pdf is biased by 1/1.07.  Caught by pdf-at-sample.
"""

import numpy as np

import warpis


def tangents(n):
    a = np.where(np.abs(n[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    t = np.cross(a, n)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return t, np.cross(n, t)


def make_sample(factor):
    def sample(n, wo, u):
        t, b = tangents(n)
        r, phi = np.sqrt(u[:, 0]), 2.0 * np.pi * u[:, 1]
        z = np.sqrt(1.0 - u[:, 0])
        w = (r * np.cos(phi))[:, None] * t + (r * np.sin(phi))[:, None] * b + z[:, None] * n
        return w, factor * z / np.pi  # the density as the sampler knows it
    return sample


def pdf(n, wo, w):
    return np.maximum(np.sum(n * w, axis=1), 0.0) / np.pi


warpis.register_numpy_technique("cosine-pdf-7pct", make_sample(1.07), pdf, description="reports 1.07 × its pdf")
warpis.register_numpy_technique("cosine-pdf-fixed", make_sample(1.0), pdf, description="reports its pdf")
