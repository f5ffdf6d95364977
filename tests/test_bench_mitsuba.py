"""The Mitsuba 3 comparator of the bench (scripts/mitsuba_baseline.py) against warpis's trial kernels.

Both compute ``independent:single:light-area`` over the same triangles, receivers and
emitters with different random numbers, so they must agree in distribution.  Per lit
receiver of occluded-quad, each Mitsuba mode's mean must lie within Z = 4 combined
standard errors of warpis's: for normal means (M = 4000) a false failure has probability
2·(1 − Φ(4)) ≈ 6.3e-5 per comparison; 2 modes × 6 lit receivers make 12 comparisons,
below 7.6e-4 in all by the union bound (and, the seeds being fixed, every run draws the
same samples).  Receivers in the umbra must give exactly 0 on every side.

The refusals (an emitter that is not one plane, or one facing two ways; a material other
than irradiance and lambert) happen before Mitsuba is loaded, so they run everywhere;
the rest needs Dr.Jit's LLVM backend and a libLLVM it can use (see the module
docstring of scripts/mitsuba_baseline.py).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import concat_meshes, needs_llvm, quad

import warpis
from warpis.errors import WarpisError
from warpis.kernels.engine import run_trials

# The comparator is a benchmark script, not part of the package: import it from the
# repository's scripts/ folder, found from this file so that it works however warpis is
# installed (editable or not).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
from mitsuba_baseline import MITSUBA_ESTIMATOR, MitsubaScene, mitsuba_trials  # noqa: E402

N = 16
TRIALS = 4000
Z = 4.0


@pytest.fixture(scope="module")
def scene():
    return warpis.load_scene("occluded-quad")


@pytest.fixture(scope="module")
def built(scene):
    return MitsubaScene.build(scene)


def _scene(lights: list[tuple[np.ndarray, np.ndarray]], material: str = "irradiance", **keys) -> warpis.Scene:
    """A floor at z = 0, the given emitting meshes (radiance 5), two receivers on the floor."""
    floor = quad((0.0, 0.0, 0.0), 3.0, "up")
    vertices, triangles, emission = concat_meshes([(*floor, 0.0)] + [(v, f, 5.0) for v, f in lights])
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.0]])
    return warpis.Scene.from_arrays(vertices, triangles, emission, points, (0.0, 0.0, 1.0), material=material,
                                    name="mitsuba-refusal", **keys)


@needs_llvm
def test_both_modes_match_warpis_in_mean(scene, built):
    w = run_trials(scene, MITSUBA_ESTIMATOR, N, TRIALS, seed=31)
    closest = mitsuba_trials(built, MITSUBA_ESTIMATOR, N, TRIALS, seed=32, mode="closest")
    anyhit = mitsuba_trials(built, MITSUBA_ESTIMATOR, N, TRIALS, seed=32, mode="anyhit")
    dark = w.var(axis=1) == 0.0
    assert dark.sum() >= 1 and (~dark).sum() >= 4, "occluded-quad should have lit and umbra receivers"
    se_w = w.std(axis=1, ddof=1) / np.sqrt(TRIALS)
    for name, m in (("closest", closest), ("anyhit", anyhit)):
        assert m.shape == w.shape
        assert np.all(m[dark] == 0.0) and np.all(w[dark] == 0.0), f"{name}: umbra receivers must give 0"
        se = np.hypot(se_w, m.std(axis=1, ddof=1) / np.sqrt(TRIALS))[~dark]
        z = (m.mean(axis=1) - w.mean(axis=1))[~dark] / se
        assert np.all(np.abs(z) <= Z), f"{name}: means differ from warpis's: z = {np.round(z, 2)}"
    # The same random numbers give the same f sample by sample: nothing lies within
    # ShadowEpsilon of the light, and no emitter hides another.
    assert np.mean(closest != anyhit) < 0.01


@needs_llvm
def test_threads_do_not_change_results(built):
    one = mitsuba_trials(built, MITSUBA_ESTIMATOR, N, 300, seed=5, threads=1, chunk_samples=N * 512)
    two = mitsuba_trials(built, MITSUBA_ESTIMATOR, N, 300, seed=5, threads=2, chunk_samples=N * 512)
    np.testing.assert_array_equal(one, two)


@needs_llvm
def test_only_the_one_estimator(built):
    with pytest.raises(WarpisError, match="implements only"):
        mitsuba_trials(built, "jittered:balance:light-area+cosine", N, 10)
    with pytest.raises(WarpisError, match="mode"):
        mitsuba_trials(built, MITSUBA_ESTIMATOR, N, 10, mode="shadow")


def test_refuses_an_emitter_that_is_not_one_plane():
    lower = quad((0.0, 0.0, 2.0), 0.5, "down")
    higher = quad((1.5, 0.0, 2.5), 0.5, "down")  # parallel, but half a unit higher
    with pytest.raises(WarpisError, match="planar emitter.*off that plane"):
        MitsubaScene.build(_scene([lower, higher]))


def test_refuses_an_emitter_facing_two_ways():
    down = quad((0.0, 0.0, 2.0), 0.5, "down")
    up = quad((1.5, 0.0, 2.0), 0.5, "up")  # coplanar, front face away from the floor
    with pytest.raises(WarpisError, match="facing one way"):
        MitsubaScene.build(_scene([down, up]))


def test_refuses_other_materials():
    light = quad((0.0, 0.0, 2.0), 0.5, "down")
    with pytest.raises(WarpisError, match="irradiance and lambert receivers only"):
        MitsubaScene.build(_scene([light], material="phong", exponent=10.0, view=(0.0, 0.0, 1.0)))
