"""The counter-based generator (``warpis.kernels.rng``): its numpy twin and independent trials.

*Bit for bit.*  ``uniform(stream(seed, receiver, trial, technique), sample, dim)`` run in a
Warp kernel on the CPU equals ``uniform_np(seed, receiver, trial, technique, sample, dim)``
as float32 bit patterns over a grid of coordinates that includes their extremes (seed 0
and 2³² − 1, trial and sample 2³¹ − 1, the mixture's pick stream).  Deterministic: no
threshold, no false failures.

*Independent trials.*  One ``run_trials`` run at a receiver in occluded-quad's penumbra,
where the estimates are continuous: (i) no two consecutive trials give the same estimate,
(ii) at most 8 of the M = 4096 estimates repeat an earlier value, and (iii) the lag-1
autocorrelation r1 of the estimates in trial order satisfies |r1| < 4.5/√M.

- (i), (ii): an estimate is a float64 sum of float32 terms, so two independent trials tie
  exactly with a small probability: measured over 300 runs of 4096 trials at this
  receiver, λ = 0.08 (light-area) and 0.25 (balance) repeated values per run, none
  between consecutive trials.  "All M distinct" would therefore fail for ~20% of seeds;
  instead, a tie between consecutive trials has probability ≈ λ·(M − 1)/(M²/2) ≈ 1.2e-4
  per run, and more than 8 repeats (Poisson(λ ≤ 0.25)) ≈ 1e-11.
- (iii): for independent trials r1 is asymptotically N(0, 1/M), so one comparison fails
  by chance with probability 2·(1 − Φ(4.5)) ≈ 6.8e-6.

Two estimators: the module's false-failure probability is ≈ 2·(1.2e-4 + 6.8e-6) ≈ 2.6e-4
(union bound; the seeds are fixed, so every run draws the same numbers).  Trials that
shared a stream in pairs (trial → trial // 2) give M/2 distinct values, M/2 consecutive
ties and r1 ≈ 0.5 = 32/√M: all three checks fail.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

from warpis.analysis.closed_form import irradiance_closed_form
from warpis.kernels.engine import run_trials
from warpis.kernels.estimators import PICK_STREAM
from warpis.kernels.rng import stream, uniform, uniform_np

INT32_MAX = 2**31 - 1

SEEDS = (0, 1, 0x9E3779B9, 2**31, 2**32 - 1)
RECEIVERS = (0, 1, 7, 65_535, INT32_MAX)
TRIALS = (0, 1, 2, 3, 16_383, 16_384, 2**24 + 1, INT32_MAX - 1, INT32_MAX)
TECHNIQUES = (0, 1, 2, 5, PICK_STREAM)
SAMPLES = (0, 1, 2, 255, 4_096, INT32_MAX)
DIMS = (0, 1, 2)


@wp.kernel(enable_backward=False)
def _uniform_kernel(seed: wp.array(dtype=wp.uint32), receiver: wp.array(dtype=wp.int32),
                    trial: wp.array(dtype=wp.int32), technique: wp.array(dtype=wp.int32),
                    sample: wp.array(dtype=wp.int32), dim: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.float32)):
    i = wp.tid()
    out[i] = uniform(stream(seed[i], receiver[i], trial[i], technique[i]), sample[i], dim[i])


def _warp_uniform(seed, receiver, trial, technique, sample, dim) -> np.ndarray:
    """Warp's uniform(stream(...), sample, dim) at each row of the coordinate arrays (CPU)."""
    arrays = [wp.array(np.ascontiguousarray(a, dtype=dt), dtype=wdt, device="cpu") for a, dt, wdt in (
        (seed, np.uint32, wp.uint32), (receiver, np.int32, wp.int32), (trial, np.int32, wp.int32),
        (technique, np.int32, wp.int32), (sample, np.int32, wp.int32), (dim, np.int32, wp.int32))]
    out = wp.zeros(len(seed), dtype=wp.float32, device="cpu")
    wp.launch(_uniform_kernel, dim=len(seed), inputs=[*arrays, out], device="cpu")
    return out.numpy()


def test_warp_uniform_equals_numpy_twin_bit_for_bit():
    """Every point of the grid SEEDS × RECEIVERS × TRIALS × TECHNIQUES × SAMPLES × DIMS
    (20,250 coordinates): the Warp value and the numpy twin's have the same float32 bits,
    and the twin's float64 value is exactly a float32 on the 2⁻²⁴ lattice of [0, 1)."""
    grid = np.meshgrid(np.array(SEEDS, np.int64), RECEIVERS, TRIALS, TECHNIQUES, SAMPLES, DIMS, indexing="ij")
    seed, receiver, trial, technique, sample, dim = (g.ravel() for g in grid)
    got = _warp_uniform(seed, receiver, trial, technique, sample, dim)
    want = np.empty(len(seed))
    for s in SEEDS:  # the twin takes one seed and broadcasts the other coordinates
        at = seed == s
        want[at] = uniform_np(s, receiver[at], trial[at], technique[at], sample[at], dim[at])
    assert np.array_equal(want.astype(np.float32).astype(np.float64), want)  # exact in float32
    assert np.all((want >= 0.0) & (want < 1.0))
    assert np.all(want * 2.0**24 == np.floor(want * 2.0**24))
    differ = np.flatnonzero(got.view(np.uint32) != want.astype(np.float32).view(np.uint32))
    assert differ.size == 0, (
        f"{differ.size} of {len(seed)} differ; first at (seed, receiver, trial, technique, sample, dim) = "
        f"{tuple(int(g[differ[0]]) for g in (seed, receiver, trial, technique, sample, dim))}: "
        f"warp {got[differ[0]]!r}, numpy {want[differ[0]]!r}")
    # The grid is not degenerate: nearly every coordinate gives its own number.
    assert len(np.unique(got)) > 0.99 * len(got)


def test_numpy_twin_scalars_equal_broadcast_arrays():
    """The twin called with one coordinate tuple at a time (Python ints) gives what it
    gives for arrays, and what Warp gives."""
    r, t, k, s, d = (np.array(x) for x in ((3, 4), (INT32_MAX, 0), (1, PICK_STREAM), (7, INT32_MAX), (0, 1)))
    together = uniform_np(2**32 - 1, r, t, k, s, d)
    one_by_one = [float(uniform_np(2**32 - 1, *(int(x[i]) for x in (r, t, k, s, d)))) for i in range(2)]
    assert together.tolist() == one_by_one
    got = _warp_uniform(np.full(2, 2**32 - 1), r, t, k, s, d)
    assert got.astype(np.float64).tolist() == one_by_one


# --------------------------------------------------------------------------- trials

M = 4096
N = 16
Z_LAG = 4.5
MAX_REPEATS = 8
PENUMBRA = 1  # occluded-quad receiver x = −0.6: the box hides part of the light


def _lag1(x: np.ndarray) -> float:
    d = x - x.mean()
    return float(np.dot(d[:-1], d[1:]) / np.dot(d, d))


def test_penumbra_receiver_is_in_partial_shadow(loaded_scenes):
    """The receiver used below sees part of the light: its mean estimate lies between 0
    and the unoccluded closed form (1.0219), more than 20 standard errors from each."""
    scene = loaded_scenes["occluded-quad"]
    rx = scene.receivers
    light = scene.emitters
    unoccluded, _ = irradiance_closed_form(rx.positions[[PENUMBRA]], rx.normals[[PENUMBRA]],
                                           scene.triangle_vertices(light), scene.emission[light])
    x = run_trials(scene, "independent:single:light-area", N, 1024, seed=1, receivers=[PENUMBRA])[0]
    se = x.std(ddof=1) / math.sqrt(len(x))
    assert 20.0 * se < x.mean() < unoccluded[0] - 20.0 * se


@pytest.mark.parametrize("spec", ["independent:single:light-area", "jittered:balance:light-area+cosine"])
def test_trials_are_independent_streams(loaded_scenes, spec):
    """M estimates of one run, in trial order: no consecutive pair equal, at most 8
    repeated values, lag-1 autocorrelation |r1| < 4.5/√M (false-failure probability
    ≈ 1.3e-4 per estimator, see the module docstring).  Trials sharing a stream would
    repeat estimates and correlate."""
    scene = loaded_scenes["occluded-quad"]
    x = run_trials(scene, spec, N, M, seed=20240607, receivers=[PENUMBRA])[0]
    assert x.shape == (M,)
    assert np.all(x > 0.0) and x.std() > 0.05, "the receiver should be in the penumbra"
    consecutive = int(np.count_nonzero(x[1:] == x[:-1]))
    assert consecutive == 0, f"{consecutive} pairs of consecutive trials gave the same estimate"
    repeats = M - len(np.unique(x))
    assert repeats <= MAX_REPEATS, f"{repeats} of {M} estimates repeat an earlier one"
    r1 = _lag1(x)
    assert abs(r1) < Z_LAG / math.sqrt(M), f"lag-1 autocorrelation {r1:.4f} (bound {Z_LAG / math.sqrt(M):.4f})"
