"""The numpy + Embree baseline (scripts/baseline.py) against warpis's trial kernels.

Both implement the same estimators with different random numbers, so they must agree in
distribution: per receiver of occluded-quad, the two sample means must agree within 4
combined standard errors, |x̄_w − x̄_b| ≤ 4·sqrt(se_w² + se_b²).  For normal means (M is
large) that fails by chance with probability 2·(1 − Φ(4)) ≈ 6.3e-5 per comparison.  The
two sample variances must agree within 4 combined fourth-moment standard errors of s²
(``warpis.stats.variance_interval``); that interval is asymptotic, so its false-failure
probability is only approximately the same 6.3e-5.  Two estimators × 6 lit receivers ×
(mean, variance) make 24 comparisons, so by the union bound a false failure has
probability below about 1.5e-3 (and, the seeds being fixed, every run draws the same
samples).  Receivers in the umbra must give exactly 0 on both sides.

Where no triangle occludes the light, the baseline's mean is also held against the
closed-form irradiance (warpis.analysis.closed_form) within 4 standard errors: 2 estimators × 2
unoccluded receivers add 4 comparisons, ≈ 2.5e-4 more.

On occluded-quad the light is parallel to the receivers' plane, where the light's cosine
|n_light·ω| and the receiver's |n·ω| coincide: a light pdf that used the wrong one would
pass.  So the same comparison runs on a tilted scene (``_tilted_scene``): a light tilted
45° over a floor tilted 15° the other way, an occluder casting a penumbra, receivers on
the floor.  Its 6 receivers that see the light (one more sees it only below its horizon:
exactly 0 on both sides) × 2 estimators × (mean, variance) add 24 comparisons, and the
baseline's and warpis's means against the closed form at its 3 unoccluded receivers
12 more: 36 × 6.3e-5 ≈ 2.3e-3.  The module's false-failure probability is therefore below
about 4e-3 (union bound).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
from conftest import concat_meshes
import pytest

import warpis
from warpis.analysis.closed_form import irradiance_closed_form
from warpis.stats import variance_interval
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


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _rect(center, half_u: float, half_v: float, normal) -> tuple[np.ndarray, np.ndarray]:
    """A rectangle about ``center`` whose front face points along ``normal``."""
    n = _unit(normal)
    u = _unit(np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0]))
    v = np.cross(n, u)
    c = np.asarray(center, dtype=float)
    return (np.array([c - half_u * u - half_v * v, c + half_u * u - half_v * v, c + half_u * u + half_v * v,
                      c - half_u * u + half_v * v]), np.array([[0, 1, 2], [0, 2, 3]]))


FLOOR_TILT = math.radians(15.0)
FLOOR_NORMAL = np.array([0.0, -math.sin(FLOOR_TILT), math.cos(FLOOR_TILT)])
LIGHT_NORMAL = _unit([-0.7, 0.2, -0.7])


def _tilted_scene() -> warpis.Scene:
    """A 1 × 0.6 light of radiance 6 tilted 45°, over a floor tilted 15° about x; a
    non-emitting 0.5 × 0.4 occluder between them; 7 receivers on the floor."""
    meshes = [(*_rect((0.0, 0.0, 0.0), 3.0, 3.0, FLOOR_NORMAL), 0.0),
              (*_rect((0.3, 0.2, 1.8), 0.5, 0.3, LIGHT_NORMAL), 6.0),
              (*_rect((0.5, 0.0, 0.9), 0.25, 0.2, (0.1, 0.0, 1.0)), 0.0)]
    vertices, triangles, emission = concat_meshes(meshes)
    xy = np.array([[-1.3, -0.4], [-0.5, 0.3], [0.0, -0.2], [0.6, 0.1], [0.9, -0.3], [1.4, 0.4], [2.2, 0.0]])
    points = np.stack([xy[:, 0], xy[:, 1], xy[:, 1] * math.tan(FLOOR_TILT)], axis=1)  # on the floor
    return warpis.Scene.from_arrays(vertices, triangles, emission, points, FLOOR_NORMAL,
                                    name="tilted-baseline")


@pytest.fixture(scope="module")
def tilted_scene():
    return _tilted_scene()


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


def test_tilted_scene_is_tilted(tilted_scene):
    """The light is 45° from the receivers' plane (|n·n_light| ≈ 0.6); some receivers are
    unoccluded, some in penumbra, one sees the light only below its horizon."""
    rx = tilted_scene.receivers
    assert abs(float(np.dot(rx.normals[0], LIGHT_NORMAL))) < 0.75
    exact_value, exact = irradiance_closed_form(rx.positions, rx.normals, tilted_scene.triangle_vertices(),
                                                tilted_scene.emission)
    assert exact.sum() >= 3 and (~exact).sum() >= 3
    assert exact_value[-1] == 0.0 and exact[-1]


@pytest.mark.parametrize("estimator", BASELINE_ESTIMATORS)
def test_baseline_matches_warpis_on_a_tilted_scene(tilted_scene, estimator):
    """Light tilted against the receivers: the two implementations agree in mean and
    variance within 4 combined standard errors at every lit receiver, both are exactly 0
    where the light is below the horizon, and both means match the closed form within 4
    standard errors where nothing occludes the light (false-failure rates in the module
    docstring).  A light pdf with the receiver's cosine for the light's, or without t²,
    moves warpis's means by many standard errors."""
    w = variance_interval(run_trials(tilted_scene, estimator, N, TRIALS, seed=21))
    b = variance_interval(baseline_trials(tilted_scene, estimator, N, TRIALS, seed=22))
    dark = (w.variance == 0.0) & (b.variance == 0.0)
    assert np.all(w.mean[dark] == 0.0) and np.all(b.mean[dark] == 0.0)
    lit = ~dark
    assert lit.sum() == 6
    mean_z = (w.mean - b.mean)[lit] / np.hypot(w.mean_stderr, b.mean_stderr)[lit]
    var_z = (w.variance - b.variance)[lit] / np.hypot(w.variance_stderr, b.variance_stderr)[lit]
    assert np.all(np.abs(mean_z) <= Z), f"means differ: z = {np.round(mean_z, 2)}"
    assert np.all(np.abs(var_z) <= Z), f"variances differ: z = {np.round(var_z, 2)}"
    rx = tilted_scene.receivers
    exact_value, exact = irradiance_closed_form(rx.positions, rx.normals, tilted_scene.triangle_vertices(),
                                                tilted_scene.emission)
    check = exact & lit
    for name, v in (("warpis", w), ("baseline", b)):
        z = (v.mean - exact_value)[check] / v.mean_stderr[check]
        assert np.all(np.abs(z) <= Z), f"{name} differs from the closed form: z = {np.round(z, 2)}"


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
