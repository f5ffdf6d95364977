"""Gallery: MIS weights that do not sum to 1: the power heuristic over (Σ g)² instead of Σ g².

w_k = g_k² / (Σ_j g_j)² sums to less than 1 wherever two techniques overlap, so the
estimator loses energy there.  Caught by weights-sum.
"""

import numpy as np

import warpis


def power_wrong(pdfs):
    total = np.sum(pdfs, axis=1, keepdims=True) ** 2
    return np.where(total > 0.0, pdfs**2 / np.where(total > 0.0, total, 1.0), 0.0)


def power(pdfs):
    total = np.sum(pdfs**2, axis=1, keepdims=True)
    return np.where(total > 0.0, pdfs**2 / np.where(total > 0.0, total, 1.0), 0.0)


warpis.register_numpy_combiner("power-over-sum-squared", power_wrong, description="g_k²/(Σg)²")
warpis.register_numpy_combiner("power-heuristic", power, description="g_k²/Σg²")
