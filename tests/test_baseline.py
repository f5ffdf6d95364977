"""The numpy + Embree baseline (scripts/baseline.py) against warpis's trial kernels.

Both implement the same estimators with different random numbers, so they must agree in
distribution: per receiver of occluded-quad, the two sample means must agree within 4
combined standard errors, |x̄_w − x̄_b| ≤ 4·sqrt(se_w² + se_b²).  For normal means (M is
large) that fails by chance with probability 2·(1 − Φ(4)) ≈ 6.3e-5 per comparison.  The
two sample variances must agree within 4 combined fourth-moment standard errors of s²
(``warpis.analysis.stats.variance_interval``); that interval is asymptotic, so its false-failure
probability is only approximately the same 6.3e-5.  Two estimators × 6 lit receivers ×
(mean, variance) make 24 comparisons, so by the union bound a false failure has
probability below about 1.5e-3 (and, the seeds being fixed, every run draws the same
samples).  Receivers in the umbra must give exactly 0 on both sides.

Where no triangle occludes the light, the baseline's mean is also held against the
closed-form irradiance (warpis.analysis.closed_form) within 4 standard errors: 2 estimators × 2
unoccluded receivers add 4 comparisons, ≈ 2.5e-4 more.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import warpis
from warpis.analysis.closed_form import irradiance_closed_form
from warpis.analysis.stats import variance_interval
from warpis.errors import WarpisError
from warpis.kernels.engine import run_trials

# The baseline is a benchmark script, not part of the package: import it from the
# repository's scripts/ folder, found from this file so that it works however warpis is
# installed (editable or not).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
from baseline import BASELINE_ESTIMATORS, baseline_trials  # noqa: E402

N = 16
TRIALS = 4000
Z = 4.0


@pytest.fixture(scope="module")
def scene():
    return warpis.load_scene("occluded-quad")


@pytest.mark.parametrize("estimator", BASELINE_ESTIMATORS)
def test_baseline_matches_warpis_in_distribution(scene, estimator):
    w = variance_interval(run_trials(scene, estimator, N, TRIALS, seed=11))
    b = variance_interval(baseline_trials(scene, estimator, N, TRIALS, seed=12))
    dark = (w.variance == 0.0) & (b.variance == 0.0)
    assert np.all(w.mean[dark] == 0.0) and np.all(b.mean[dark] == 0.0)
    lit = ~dark
    assert lit.sum() >= 4, "occluded-quad should have lit receivers"
    mean_z = (w.mean - b.mean)[lit] / np.hypot(w.mean_stderr, b.mean_stderr)[lit]
    var_z = (w.variance - b.variance)[lit] / np.hypot(w.variance_stderr, b.variance_stderr)[lit]
    assert np.all(np.abs(mean_z) <= Z), f"means differ: z = {np.round(mean_z, 2)}"
    assert np.all(np.abs(var_z) <= Z), f"variances differ: z = {np.round(var_z, 2)}"


@pytest.mark.parametrize("estimator", BASELINE_ESTIMATORS)
def test_baseline_matches_the_closed_form_where_nothing_occludes(scene, estimator):
    rx = scene.receivers
    exact_value, exact = irradiance_closed_form(rx.positions, rx.normals, scene.triangle_vertices(), scene.emission)
    assert exact.sum() >= 2, "occluded-quad should have unoccluded receivers"
    b = variance_interval(baseline_trials(scene, estimator, N, TRIALS, seed=13))
    z = (b.mean - exact_value)[exact] / b.mean_stderr[exact]
    assert np.all(np.abs(z) <= Z), f"baseline differs from the closed form: z = {np.round(z, 2)}"


def test_threads_and_receiver_subsets_do_not_change_results(scene):
    est = BASELINE_ESTIMATORS[1]
    one = baseline_trials(scene, est, N, 300, seed=5, threads=1, chunk_samples=N * 64)
    two = baseline_trials(scene, est, N, 300, seed=5, threads=2, chunk_samples=N * 64)
    np.testing.assert_array_equal(one, two)
    sub = baseline_trials(scene, est, N, 300, seed=5, receivers=[6, 1], chunk_samples=N * 64)
    np.testing.assert_array_equal(sub, one[[6, 1]])
    assert one.shape == (len(scene.receivers), 300)


def test_only_the_two_estimators_and_valid_n(scene):
    with pytest.raises(WarpisError, match="baseline implements only"):
        baseline_trials(scene, "jittered:power:light-area+cosine", N, 10)
    with pytest.raises(WarpisError, match="not divisible"):
        baseline_trials(scene, BASELINE_ESTIMATORS[1], 15, 10)
    with pytest.raises(WarpisError):
        baseline_trials(scene, BASELINE_ESTIMATORS[0], N, 0)
