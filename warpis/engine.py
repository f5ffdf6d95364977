"""The trial engine: R receivers × M trials of one estimator at N samples, on every core.

Trials are split into chunks; on the CPU each chunk is one ``wp.launch`` (which runs on
one core and releases the GIL) issued from a pool of Python threads, so all cores work.
Every random number is a pure function of (seed, receiver, trial, technique, sample,
dimension), so the result is bit-identical whatever the thread count, chunk size or
receiver order.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

from .errors import WarpisError
from .estimators import Estimator, KernelArgs, parse_estimator, trial_kernel
from .scene import Scene
from .techniques import light_table

# Target work of one launch, in integrand evaluations: large enough to amortise the
# launch, small enough that progress moves and threads balance.
CHUNK_EVALUATIONS = 1 << 19
CHUNKS_PER_THREAD = 16

Progress = Callable[[int, int], None]  # (trials done, trials total)


def default_threads() -> int:
    """Worker threads for CPU launches: ``WARPIS_THREADS`` or the number of usable cores."""
    env = os.environ.get("WARPIS_THREADS")
    if env:
        return max(1, int(env))
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


def select_receivers(scene: Scene, receivers: Sequence[int] | None) -> np.ndarray:
    """Receiver indices as int32, validated against the scene."""
    count = len(scene.receivers)
    if receivers is None:
        return np.arange(count, dtype=np.int32)
    idx = np.asarray(list(receivers), dtype=np.int64)
    if idx.size == 0:
        raise WarpisError(f"{scene.path}: no receivers selected")
    bad = idx[(idx < 0) | (idx >= count)]
    if bad.size:
        raise WarpisError(f"{scene.path}: receiver {int(bad[0])} does not exist (the scene has {count}: 0–{count - 1})")
    return idx.astype(np.int32)


def run_trials(
    scene: Scene,
    estimator: str | Estimator,
    n: int,
    trials: int,
    seed: int = 0,
    receivers: Sequence[int] | None = None,
    threads: int | None = None,
    chunk: int | None = None,
    progress: Progress | None = None,
) -> np.ndarray:
    """Estimates of F at each receiver from ``trials`` independent trials of ``n`` samples.

    Parameters
    ----------
    scene
        A loaded scene (its device is used).
    estimator
        An :class:`Estimator` or its spelling, e.g. ``"jittered:balance:light-area+cosine"``.
    n
        Samples per estimate (N).
    trials
        Independent trials (M).
    seed
        Seed of the counter-based generator; different seeds give independent trials.
    receivers
        Receiver indices (default: all).
    threads
        CPU worker threads (default: :func:`default_threads`).  Does not change results.
    chunk
        Trials per launch (default: about ``CHUNK_EVALUATIONS`` evaluations).  Does not
        change results.
    progress
        Called as ``progress(done, total)`` in trials after each chunk.

    Returns
    -------
    numpy.ndarray
        (R, M) float64 estimates, row i for ``receivers[i]``.
    """
    est = parse_estimator(estimator)
    args = KernelArgs.of(est, int(n))
    if trials < 1:
        raise WarpisError(f"trials must be at least 1 (got {trials})")
    if not 0 <= int(seed) < 2**32:
        raise WarpisError(f"seed must be in [0, 2^32) (got {seed})")
    rx = select_receivers(scene, receivers)
    dev = scene.device
    table = light_table(scene)
    rx_wp = wp.array(rx, dtype=wp.int32, device=dev)
    techs = wp.array(np.array(args.techniques, dtype=np.int32), dtype=wp.int32, device=dev)
    out = wp.zeros((len(rx), trials), dtype=wp.float64, device=dev)
    workers = threads or default_threads()
    if chunk is None:
        # Big enough to amortise a launch, small enough for every thread to get many
        # chunks (the last chunks then finish together).
        by_work = CHUNK_EVALUATIONS // max(1, len(rx) * int(n))
        chunk = max(1, min(by_work, -(-trials // (CHUNKS_PER_THREAD * workers))))
    chunk = max(1, min(int(chunk), trials))
    starts = list(range(0, trials, chunk))

    def launch(start: int) -> int:
        count = min(chunk, trials - start)
        wp.launch(trial_kernel, dim=(len(rx), count), device=dev,
                  inputs=[scene.data, scene.receiver_data, table, rx_wp, start, wp.uint32(int(seed)), args.pattern,
                          args.combiner, techs, args.m, args.rows, args.cols, out])
        return count

    done = 0
    lock = threading.Lock()

    def run(start: int) -> None:
        nonlocal done
        count = launch(start)
        with lock:
            done += count
            if progress is not None:
                progress(done, trials)

    if wp.get_device(dev).is_cpu and workers > 1 and len(starts) > 1:
        wp.load_module(trial_kernel.module, device=dev)  # compile once, before threads race to
        with ThreadPoolExecutor(max_workers=workers) as pool:
            for f in [pool.submit(run, s) for s in starts]:
                f.result()
    else:
        for s in starts:
            run(s)
    wp.synchronize_device(dev)
    return out.numpy()
