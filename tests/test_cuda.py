"""The CUDA path gives the CPU's results: same random numbers, same maps, same rays.

Runs only where Warp sees a CUDA device (skipped otherwise, as in CI).  CPU and GPU
compile the same kernels but may contract floating-point operations differently, so
per-estimate agreement is to a relative 1e-3 on almost all estimates rather than bit for
bit; means over trials must agree to well within their standard errors.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import warpis
from warpis.analysis.quadrature import exact_variance
from warpis.kernels.engine import run_trials

pytestmark = pytest.mark.skipif(not wp.is_cuda_available(), reason="no CUDA device")

SPECS = ["independent:single:light-area", "jittered:balance:light-area+cosine",
         "antithetic:power:light-solid-angle+cosine", "jittered-antithetic:mixture:light-power+uniform"]


@pytest.mark.parametrize("scene_name", ["occluded-quad", "veach-plates", "heavy-occluder"])
@pytest.mark.parametrize("spec", SPECS)
def test_cuda_trials_match_cpu(scene_name, spec):
    if scene_name == "veach-plates":
        spec = spec.replace("cosine", "phong")
    cpu = warpis.load_scene(scene_name, device="cpu")
    gpu = warpis.load_scene(scene_name, device="cuda:0")
    a = run_trials(cpu, spec, 16, 200, seed=4)
    b = run_trials(gpu, spec, 16, 200, seed=4)
    close = np.isclose(a, b, rtol=1e-3, atol=1e-9 * max(1.0, float(np.abs(a).max())))
    assert close.mean() > 0.99, (close.mean(), a[~close][:5], b[~close][:5])
    se = a.std(axis=1, ddof=1) / np.sqrt(a.shape[1]) + 1e-12
    assert np.all(np.abs(a.mean(axis=1) - b.mean(axis=1)) <= 0.5 * se + 1e-9)


def test_cuda_predictions_match_cpu():
    cpu = warpis.load_scene("occluded-quad", device="cpu")
    gpu = warpis.load_scene("occluded-quad", device="cuda:0")
    for spec, n in (("independent:balance:light-area+cosine", 16), ("jittered:single:cosine", 64)):
        a = exact_variance(cpu, 2, spec, n)
        b = exact_variance(gpu, 2, spec, n)
        assert abs(a.value - b.value) <= 4 * np.hypot(a.stderr, b.stderr) + 1e-6 * abs(a.value)
