"""Streaming trials into running moments, prompt Ctrl-C, and the engine's argument checks.

``run_moments`` reduces trials over fixed blocks and merges the blocks with Pébay's
pairwise formulas; these tests hold it against ``variance_interval`` of the full
``run_trials`` array (the same trials), against numpy's two-pass moments on data with
a large mean and a tiny spread, and against itself across thread counts and chunk sizes
(bit-identical).  Every test is deterministic (fixed seeds): the tolerances bound
floating-point rounding, not sampling noise, so none of them has a false-failure rate
beyond that of a change in numpy's summation order.
"""

from __future__ import annotations

import select
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from warpis import limits
from warpis.stats import SampleMoments, variance_interval
from warpis.errors import WarpisError
from warpis.kernels.engine import BLOCK, _BlockReducer, default_threads, run_moments, run_trials
from warpis.scenes import load_scene

FIELDS = ("mean", "mean_stderr", "variance", "variance_stderr", "lo", "hi")
SPEC = "jittered:balance:light-area+cosine"
# Three whole blocks and a partial one; receivers 3 and 4 are in the umbra (all zeros).
TRIALS = 3 * BLOCK + 1234
RECEIVERS = [0, 1, 3, 5, 7]


@pytest.fixture(scope="module")
def quad():
    return load_scene("occluded-quad")


def _same_moments(a: SampleMoments, b: SampleMoments) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in ("count", "mean", "m2", "m3", "m4"))


def _empty() -> SampleMoments:
    """Moments of no values (count 0)."""
    return SampleMoments(np.zeros((), np.int64), np.zeros(()), np.zeros(()), np.zeros(()), np.zeros(()))


def test_streamed_moments_match_the_full_array(quad):
    """On occluded-quad, run_moments(...).interval() equals variance_interval(run_trials(...))
    on the same trials to 1e-12 relative for five receivers (two in the umbra, exactly 0
    both ways); measured differences are ~2e-16.  Deterministic."""
    full = run_trials(quad, SPEC, 4, TRIALS, seed=5, receivers=RECEIVERS)
    streamed = run_moments(quad, SPEC, 4, TRIALS, seed=5, receivers=RECEIVERS)
    assert streamed.count.tolist() == [TRIALS] * len(RECEIVERS)
    want, got = variance_interval(full), streamed.interval()
    assert got.trials == TRIALS and got.level == 0.95
    for field in FIELDS:
        np.testing.assert_allclose(getattr(got, field), getattr(want, field), rtol=1e-12, atol=0, err_msg=field)
    assert got.variance[2] == 0.0 and got.mean[2] == 0.0  # receiver 3: umbra
    assert np.all(got.variance[[0, 1, 3, 4]] > 0)


def test_streamed_moments_are_bit_identical_across_threads_and_chunks(quad):
    """The merged moments do not depend on the thread count or on how launches are
    chunked (chunks smaller than a block, straddling blocks, or the whole run at once),
    bit for bit; neither do run_trials' values.  Deterministic."""
    base = run_moments(quad, SPEC, 4, TRIALS, seed=8, receivers=RECEIVERS, threads=1)
    for threads, chunk in [(2, None), (2, 777), (1, 2 * BLOCK + 3), (2, TRIALS), (2, 5000)]:
        other = run_moments(quad, SPEC, 4, TRIALS, seed=8, receivers=RECEIVERS, threads=threads, chunk=chunk)
        assert _same_moments(base, other), (threads, chunk)
    a = run_trials(quad, SPEC, 4, 5000, seed=8, receivers=RECEIVERS, threads=1)
    b = run_trials(quad, SPEC, 4, 5000, seed=8, receivers=RECEIVERS, threads=2, chunk=333)
    assert np.array_equal(a, b)


def test_block_reducer_with_a_large_mean_and_tiny_spread():
    """Estimates 1e3 + 1e-3·noise (variance 1e-6, 3 rows, 10 blocks and a partial one)
    fed to the block reducer in 40 uneven chunks, shuffled: the interval matches
    variance_interval of all values to 5e-12 relative (measured worst over 20 seeds:
    6.5e-13 for s², 1.1e-12 for se(s²); the limit is the float64 rounding of the block
    means, ulp(1e3) = 1.1e-13, against block-mean differences of ~1e-5).  The one-pass
    Σx², (Σx)² formula is off by 3e-4 here, a hundred million times more.  Deterministic."""
    rng = np.random.default_rng(3)
    n = 10 * BLOCK + 4321
    x = 1000.0 + 1e-3 * rng.standard_normal((3, n))
    reducer = _BlockReducer(3, n)
    edges = np.unique(np.r_[0, rng.integers(0, n, 40), n])
    for i in rng.permutation(len(edges) - 1):
        start, end = int(edges[i]), int(edges[i + 1])
        reducer.add(start, end - start, reducer.split(start, x[:, start:end]))
    assert not reducer.partial and not reducer.waiting
    want, got = variance_interval(x), reducer.total.interval()
    for field in FIELDS:
        np.testing.assert_allclose(getattr(got, field), getattr(want, field), rtol=5e-12, atol=0, err_msg=field)
    one_pass = (np.sum(x * x, axis=1) - np.sum(x, axis=1) ** 2 / n) / (n - 1)
    assert np.max(np.abs(one_pass / want.variance - 1.0)) > 1e-5


def test_merging_many_uneven_blocks_matches_numpy_two_pass():
    """200 000 values 1e3 + 1e-3·noise cut into ~150 blocks of 1 to 2999 values (single
    values included), merged left to right with Pébay's formulas: the mean matches
    numpy's to 2e-15 relative and M2, M3, M4 match Σ(x − x̄)^k (two-pass on x − 1000,
    exact by Sterbenz's lemma) to 5e-12, 2e-11 and 1e-10 of n·σ^k (measured worst over
    20 seeds: 5e-16 for the mean, then 9e-13, 2.8e-12, 1.3e-11).  An empty sample merges
    as the identity.  Deterministic."""
    rng = np.random.default_rng(17)
    n = 200_000
    x = 1000.0 + 1e-3 * rng.standard_normal(n)
    cuts = np.cumsum(rng.integers(1, 3000, 400))
    edges = np.r_[0, cuts[cuts < n], n]
    total = _empty()
    for a, b in zip(edges[:-1], edges[1:]):
        total = total.merge(SampleMoments.of(x[a:b]))
    assert int(total.count) == n and len(edges) > 100
    dev = x - 1000.0
    dev = dev - dev.mean()
    dev -= dev.mean()
    assert abs(total.mean / np.mean(x) - 1.0) <= 2e-15
    for k, tol in ((2, 5e-12), (3, 2e-11), (4, 1e-10)):
        ref = np.sum(dev ** k)
        assert abs(getattr(total, f"m{k}") - ref) <= tol * n * 1e-3 ** k, (k, getattr(total, f"m{k}"), ref)
    single = SampleMoments.of(x)
    assert _same_moments(single.merge(_empty()), single) and _same_moments(_empty().merge(single), single)


@pytest.mark.parametrize("run", [run_trials, run_moments])
@pytest.mark.parametrize("kwargs, words", [
    ({"n": 4.7}, "n: expected an integer, got 4.7"),
    ({"seed": 1.9}, "seed: expected an integer"),
    ({"seed": 2**32}, "seed: must be in [0, 2^32)"),
    ({"receivers": [1.5]}, "receivers: indices must be integers, got 1.5"),
    ({"receivers": [8]}, "8 does not exist"),
    ({"trials": 2**31}, "trials: must be at most 2,147,483,647"),
    ({"trials": 0}, "trials: must be at least 1"),
    ({"threads": 0}, "threads: must be at least 1"),
    ({"chunk": 2.5}, "chunk: expected an integer"),
])
def test_the_api_refuses_what_the_kernels_cannot_take(quad, run, kwargs, words):
    """Non-integer or out-of-range n, seed, receivers, trials, threads and chunk are
    refused with one line naming the argument, never truncated or wrapped."""
    args = {"n": 4, "trials": 10, "seed": 0, "receivers": None} | kwargs
    n, trials = args.pop("n"), args.pop("trials")
    with pytest.raises(WarpisError) as info:
        run(quad, "independent:single:light-area", n, trials, **args)
    assert words in str(info.value) and "\n" not in str(info.value)


def test_run_trials_refuses_an_array_beyond_half_the_memory(quad, monkeypatch):
    """With 1 MB available, run_trials refuses 2 × 40 000 float64 (640 kB > 0.5 MB) up
    front; run_moments, which keeps no such array, runs the same job."""
    monkeypatch.setattr(limits, "available_memory", lambda: 1_000_000)
    with pytest.raises(WarpisError, match=r"^trials: would need about"):
        run_trials(quad, "independent:single:light-area", 1, 40_000, receivers=[0, 1])
    assert run_moments(quad, "independent:single:light-area", 1, 40_000, receivers=[0, 1]).count.tolist() == [
        40_000, 40_000]


@pytest.mark.parametrize("value, words", [("abc", "expected an integer, got 'abc'"), ("0", "must be at least 1"),
                                          ("1.5", "expected an integer")])
def test_warpis_threads_must_be_a_positive_integer(monkeypatch, value, words):
    """WARPIS_THREADS=abc, 0 or 1.5 is a one-line error naming the variable; 3 is 3."""
    monkeypatch.setenv("WARPIS_THREADS", value)
    with pytest.raises(WarpisError) as info:
        default_threads()
    assert str(info.value).startswith("WARPIS_THREADS: ") and words in str(info.value)
    monkeypatch.setenv("WARPIS_THREADS", "3")
    assert default_threads() == 3


# The real command line, with run_moments wrapped to print "started" on stdout once the
# first chunk is done: Ctrl-C then arrives while launches are running and queued.
_DRIVER = """
import sys
import warpis.kernels.engine as engine
from warpis.cli import main

real = engine.run_moments


def run_moments(*args, progress=None, **kwargs):
    def tell(done, total):
        progress(done, total)
        if not tell.said:
            tell.said = True
            print("started", flush=True)
    tell.said = False
    return real(*args, progress=tell, **kwargs)


engine.run_moments = run_moments
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.parametrize("threads", ["1", "2"])
def test_ctrl_c_stops_an_estimate_within_seconds(threads):
    """SIGINT during `warpis estimate` (a job of minutes) ends the process with status 130,
    exactly `warpis: interrupted` on stderr, within 3 s (measured 0.2 s on two loaded
    cores): queued chunks are cancelled and only the running ones (each ~0.1 s here)
    finish.  Before, it waited for the whole job.  With one thread the launches still
    run off the main thread, so the interrupt is not lost in a finalizer."""
    cmd = [sys.executable, "-c", _DRIVER, "estimate", "occluded-quad", "--estimator", SPEC, "--n", "256",
           "--trials", "2000000", "--threads", threads]
    # The child gets Ctrl-C's default disposition whatever the suite was started with: a
    # shell starts a background job with SIGINT ignored, which a child inherits (and
    # Python then installs no KeyboardInterrupt handler).
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 120)  # start-up, kernel cache load, first chunk
        assert ready and proc.stdout.readline() == "started\n", proc.stderr.read() if proc.poll() else "no start"
        time.sleep(0.5)  # let more chunks start and queue up
        sent = time.monotonic()
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
        elapsed = time.monotonic() - sent
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, (proc.returncode, err)
    assert err == "warpis: interrupted\n" and out == ""
    assert elapsed < 3.0, elapsed
