"""The trial engine: R receivers × M trials of one estimator at N samples, on every core.

Trials are split into chunks; on the CPU each chunk is one ``wp.launch`` (which runs on
one core and releases the GIL) issued from a pool of Python threads, so all cores work.
Every random number is a pure function of (seed, receiver, trial, technique, sample,
dimension), so the result is bit-identical whatever the thread count, chunk size or
receiver order.

Two ways to collect the trials share one launch loop (:func:`_drive`):

* :func:`run_trials` keeps every estimate, an (R, M) float64 array;
* :func:`run_moments` keeps only running moments per receiver
  (:class:`~warpis.stats.SampleMoments`): trials are reduced over fixed blocks of
  ``BLOCK`` trials and the blocks merged in trial order, so memory stays flat in M and
  the result does not depend on threads or chunks.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
import warp as wp

from .. import limits
from ..limits import default_threads
from ..stats import SampleMoments
from ..errors import WarpisError
from .device import DeviceScene, upload
from .estimators import Estimator, KernelArgs, parse_estimator
from .integrand import delta_terms
from .registered import registered_kernels
from .techniques import check_lights, light_table

if TYPE_CHECKING:  # annotations only: scenes import the kernels' registries
    from ..scenes import Scene

# Target work of one launch, in integrand evaluations: large enough to amortise the
# launch, small enough that progress moves, threads balance and Ctrl-C is prompt.
CHUNK_EVALUATIONS = 1 << 19
CHUNKS_PER_THREAD = 16
# Chunks queued or running per worker thread: enough to keep every core busy, few
# enough that memory stays flat in M and that Ctrl-C has little to cancel.
IN_FLIGHT_PER_THREAD = 2
# Trials per reduction block of run_moments.  Blocks start at multiples of BLOCK
# whatever the launch chunks are, so the merged moments are bit-identical for any
# thread count or chunk size; 2^14 keeps the per-block numpy overhead small next to
# the kernels even for the cheapest estimator.
BLOCK = 1 << 14
# Largest launch buffer (R × chunk float64) a worker thread holds; also keeps its row
# stride within Warp's 32-bit strides.
MAX_BUFFER_BYTES = 1 << 27

Progress = Callable[[int, int], None]  # (trials done, trials total)
T = TypeVar("T")


def as_scene(scene: Scene | str | os.PathLike, what: str = "scene") -> Scene:
    """A loaded scene: a :class:`~warpis.scenes.Scene` as it is, a bundled scene's name or
    a scene file's path loaded on the CPU as :func:`~warpis.scenes.load_scene` loads it;
    anything else a one-line error naming ``what``."""
    from ..scenes import Scene, load_scene  # scenes import the kernels' registries

    if isinstance(scene, Scene):
        return scene
    if isinstance(scene, (str, os.PathLike)):
        return load_scene(scene)
    raise WarpisError(f"{what}: expected a Scene, a bundled scene's name or a scene file's path, "
                      f"got {type(scene).__name__} {scene!r}")


def select_receivers(scene: Scene, receivers: Sequence[int] | int | None) -> np.ndarray:
    """Receiver indices as int32, validated against the scene (default: all; one integer is one receiver)."""
    if receivers is None:
        return np.arange(len(scene.receivers), dtype=np.int32)
    return limits.receiver_indices(receivers, "receivers", len(scene.receivers))


@dataclass(frozen=True)
class _Job:
    """One validated run with its kernel inputs uploaded; launches any range of its trials."""

    device: Any
    spec: str
    rows: int
    n: int
    trials: int
    head: tuple  # kernel inputs before the trial offset
    tail: tuple  # kernel inputs between the trial offset and the output
    upload: DeviceScene  # owns the mesh and BVH that head's struct knows by id only
    kernel: Any  # the trial kernel (the built-in one unless user techniques are registered)
    first: int = 0  # the first trial to run: trials first..trials−1 (a cluster task runs a range)
    # (R, 1): the delta lights' exact term at each row's receiver, added to every trial
    # (integrand.delta_terms); None when the scene has no delta light.
    delta: np.ndarray | None = None

    def launch(self, start: int, count: int, buf: wp.array) -> None:
        """Trials start..start+count−1 of every receiver into columns 0..count−1 of ``buf``."""
        wp.launch(self.kernel, dim=(self.rows, count), device=self.device,
                  inputs=[*self.head, start, *self.tail, buf])


def _prepare(scene: Scene, estimator: str | Estimator, n: int, trials: int, seed: int,
             receivers: Sequence[int] | None, first: int = 0) -> _Job:
    """Validate the arguments (nothing truncated or wrapped) and upload the kernel inputs."""
    scene = as_scene(scene)
    est = parse_estimator(estimator)
    n = limits.count(n, "n")
    trials = limits.count(trials, "trials")
    seed = limits.seed(seed)
    args = KernelArgs.of(est, n)
    rx = select_receivers(scene, receivers)
    check_lights(scene, est.techniques)
    delta = None
    if scene.delta_lights is not None:
        if not est.combiner_entry.unbiased:
            raise WarpisError(f"estimator {est.spec}: its mean is ∫ f g of the sampled light, and scene "
                              f"{scene.name!r} has delta lights, whose term no sample sees: use an unbiased combiner")
        delta = delta_terms(scene)[rx][:, None]
    up = upload(scene)
    dev = up.device
    head = (up.data, up.receiver_data, light_table(scene), wp.array(rx, dtype=wp.int32, device=dev))
    techs = wp.array(np.array(args.techniques, dtype=np.int32), dtype=wp.int32, device=dev)
    tail = (wp.uint32(seed), args.pattern, args.combiner, techs, args.m, args.rows, args.cols, args.pilot,
            args.parameter, wp.array(_alphas(scene, est, rx), dtype=wp.vec4d, device=dev))
    return _Job(dev, est.spec, len(rx), n, trials, head, tail, up, registered_kernels().trial, first, delta)


# The optimal oracle's coefficients come from the theory, a floor above the engine: it
# registers its solver here when it is imported (warpis/__init__.py imports it).
_oracle: list[Callable[[Scene, np.ndarray, tuple[str, ...]], np.ndarray]] = []


def register_oracle(solve: Callable[[Scene, np.ndarray, tuple[str, ...]], np.ndarray]) -> None:
    """Set the function ``solve(scene, rows, techniques) → (R, K) α`` that the
    ``optimal-oracle`` combiner's runs take their coefficients from."""
    _oracle[:] = [solve]


def _alphas(scene: Scene, est: Estimator, rows: np.ndarray) -> np.ndarray:
    """The optimal-oracle's coefficients at each receiver of ``rows``, zero-padded to four
    ((R, 4)); one unread row for every other combiner."""
    if not est.combiner_entry.oracle:
        return np.zeros((1, 4))
    if not _oracle:
        raise WarpisError(f"estimator {est.spec}: the optimal oracle's solver is not registered "
                          f"(import warpis.analysis.quadrature)")
    alpha = _oracle[0](scene, rows, est.techniques)
    return np.pad(alpha, ((0, 0), (0, 4 - alpha.shape[1])))


def _chunk_size(job: _Job, chunk: int | None, workers: int) -> int:
    """Trials per launch: ``chunk``, or by default about ``CHUNK_EVALUATIONS`` evaluations.

    Either way at most ``MAX_BUFFER_BYTES`` of estimates per launch (each thread holds
    one such buffer); the chunk size never changes results.
    """
    if chunk is None:
        # Big enough to amortise a launch, small enough for every thread to get many
        # chunks (the last chunks then finish together).
        by_work = CHUNK_EVALUATIONS // max(1, job.rows * job.n)
        chunk = max(1, min(by_work, -(-(job.trials - job.first) // (CHUNKS_PER_THREAD * workers))))
    cap = max(1, MAX_BUFFER_BYTES // (8 * job.rows))
    return min(limits.count(chunk, "chunk"), job.trials - job.first, cap)


def _drive(job: _Job, work: Callable[[int, np.ndarray], T], finish: Callable[[int, int, T], None],
           threads: int | None, chunk: int | None, progress: Progress | None) -> None:
    """Launch every chunk of ``job``: ``work(start, values)`` then ``finish(start, count, result)``.

    ``work`` runs in the launching thread right after the launch, on an (R, count) view
    of that thread's launch buffer, which the thread's next launch overwrites: it keeps
    only what it copies.  (One buffer per thread, reused, rather than one per chunk:
    freed chunk-sized buffers pile up in the allocator's per-thread arenas, and the
    resident memory then grows with the chunk size.)  ``finish`` and ``progress`` run
    in the calling thread, in completion order.

    On the CPU the launches run on a pool of ``threads`` threads with at most
    ``IN_FLIGHT_PER_THREAD`` chunks per thread submitted at a time, so pending results
    stay bounded.  After an exception, Ctrl-C included, no further chunk starts: queued
    ones are cancelled and only those already running (each small) are waited for.
    """
    workers = default_threads() if threads is None else limits.count(threads, "threads")
    size = _chunk_size(job, chunk, workers)
    if progress is not None and not callable(progress):
        raise WarpisError(f"progress: expected a callable progress(done, total), got {progress!r}")
    local = threading.local()
    done = 0

    def task(start: int) -> T:
        count = min(size, job.trials - start)
        if not hasattr(local, "buf"):
            local.buf = wp.empty((job.rows, size), dtype=wp.float64, device=job.device)
        job.launch(start, count, local.buf)
        values = local.buf.numpy()[:, :count]
        if job.delta is not None:  # the delta lights' exact term: every estimate of F carries it
            values = values + job.delta
        _check_finite(job, start, values)
        return work(start, values)

    def record(start: int, result: T) -> None:
        nonlocal done
        count = min(size, job.trials - start)
        finish(start, count, result)
        done += count
        if progress is not None:
            progress(done, job.trials - job.first)

    starts = range(job.first, job.trials, size)
    if not wp.get_device(job.device).is_cpu:  # GPU launches are asynchronous: one thread feeds them
        for start in starts:
            record(start, task(start))
        return
    # On the CPU even one worker is a pool thread: the calling thread then waits in
    # wait(), where Ctrl-C raises at once, rather than in Warp's calls, where it can land
    # in a finalizer (array.__del__) and be swallowed.
    wp.load_module(job.kernel.module, device=job.device)  # compile once, before threads race to
    pool = ThreadPoolExecutor(max_workers=workers)
    running: dict[Future, int] = {}
    try:
        for start in starts:
            if len(running) >= IN_FLIGHT_PER_THREAD * workers:
                _collect(running, record)
            running[pool.submit(task, start)] = start
        while running:
            _collect(running, record)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _check_finite(job: _Job, start: int, values: np.ndarray) -> None:
    """A NaN or infinite estimate (a float32 overflow in some integrand or pdf) stops the
    run: it would make every figure derived from it wrong."""
    finite = np.isfinite(values)
    if not finite.all():
        row, col = np.argwhere(~finite)[0]
        raise WarpisError(f"estimator {job.spec}: trial {start + col} at receiver row {row} gave "
                          f"{values[row, col]} (a float32 overflow in the integrand or a pdf); nothing is reported")


def _collect(running: dict[Future, int], record: Callable[[int, Any], None]) -> None:
    """Wait for at least one running chunk; record every finished one."""
    finished, _ = wait(running, return_when=FIRST_COMPLETED)
    for future in finished:
        record(running.pop(future), future.result())


# What a chunk leaves of one block: the block's moments when the chunk covers all of
# it, else (offset of the piece in the block, a copy of the piece).
_Piece = tuple[int, SampleMoments | tuple[int, np.ndarray]]


class _BlockReducer:
    """Reduces chunks, arriving in any order, to moments over fixed blocks merged in trial order.

    :meth:`split` (in the launching thread) reduces the blocks a chunk covers whole and
    copies the parts of blocks it covers in part; :meth:`add` (in the calling thread)
    assembles the parts, and merges finished blocks once every earlier block is merged.
    A block is always reduced from a fresh contiguous (R, block) array, so the same
    numbers in the same layout whatever the chunks.  Memory: the partly filled and the
    waiting blocks, bounded by the chunks in flight.
    """

    def __init__(self, rows: int, trials: int, first_block: int = 0, keep_blocks: bool = False):
        self.rows, self.trials = rows, trials
        self.partial: dict[int, tuple[np.ndarray, int]] = {}  # block → (values, trials arrived)
        self.waiting: dict[int, SampleMoments] = {}  # reduced blocks with an unmerged predecessor
        self.next = first_block  # the first block not yet merged
        # Every block's own moments, in trial order, when asked for (run_block_moments):
        # run_moments keeps only the running total, so its memory stays flat in M.
        self.blocks: list[SampleMoments] | None = [] if keep_blocks else None
        self.total: SampleMoments | None = None

    def split(self, start: int, values: np.ndarray) -> list[_Piece]:
        end = start + values.shape[1]
        pieces: list[_Piece] = []
        for block in range(start // BLOCK, -(-end // BLOCK)):
            lo, hi = block * BLOCK, min((block + 1) * BLOCK, self.trials)
            a, b = max(lo, start), min(hi, end)
            part = np.array(values[:, a - start:b - start], order="C")
            pieces.append((block, SampleMoments.of(part) if (a, b) == (lo, hi) else (a - lo, part)))
        return pieces

    def add(self, start: int, count: int, pieces: list[_Piece]) -> None:
        for block, piece in pieces:
            if isinstance(piece, SampleMoments):
                self.waiting[block] = piece
                continue
            offset, part = piece
            size = min((block + 1) * BLOCK, self.trials) - block * BLOCK
            buf, filled = self.partial.pop(block, (None, 0))
            if buf is None:
                buf = np.empty((self.rows, size))
            buf[:, offset:offset + part.shape[1]] = part
            filled += part.shape[1]
            if filled < size:
                self.partial[block] = (buf, filled)
            else:
                self.waiting[block] = SampleMoments.of(buf)
        while self.next in self.waiting:
            block_moments = self.waiting.pop(self.next)
            if self.blocks is not None:
                self.blocks.append(block_moments)
            self.total = block_moments if self.total is None else self.total.merge(block_moments)
            self.next += 1


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
        A loaded scene (its device is used), or a bundled scene's name or a scene file's
        path, loaded on the CPU as :func:`~warpis.scenes.load_scene` does.
    estimator
        An :class:`Estimator` or its spelling, e.g. ``"jittered:balance:light-area+cosine"``.
    n
        Samples per estimate (N), an integer in [1, 2^31).
    trials
        Independent trials (M), an integer in [1, 2^31).
    seed
        Seed of the counter-based generator, an integer in [0, 2^32); different seeds
        give independent trials.
    receivers
        Receiver indices, integers (default: all); one integer is one receiver.
    threads
        CPU worker threads (default: :func:`default_threads`).  Does not change results.
    chunk
        Trials per launch (default: about ``CHUNK_EVALUATIONS`` evaluations).  Does not
        change results.
    progress
        Called as ``progress(done, total)`` in trials after each chunk, in the calling thread.

    Returns
    -------
    numpy.ndarray
        (R, M) float64 estimates, row i for ``receivers[i]``.

    Raises
    ------
    WarpisError
        For any argument the kernels cannot take exactly, and for an (R, M) array larger
        than half the available memory (:func:`run_moments` needs no such array).
    """
    job = _prepare(scene, estimator, n, trials, seed, receivers)
    limits.memory(job.rows * job.trials * 8, "trials")
    out = np.empty((job.rows, job.trials))

    def work(start: int, values: np.ndarray) -> None:
        out[:, start:start + values.shape[1]] = values  # chunks write disjoint columns

    _drive(job, work, lambda start, count, result: None, threads, chunk, progress)
    return out


def run_moments(
    scene: Scene,
    estimator: str | Estimator,
    n: int,
    trials: int,
    seed: int = 0,
    receivers: Sequence[int] | None = None,
    threads: int | None = None,
    chunk: int | None = None,
    progress: Progress | None = None,
) -> SampleMoments:
    """Running moments of the same trials as :func:`run_trials`, in memory flat in M.

    Takes the arguments of :func:`run_trials`.  Trials are reduced per receiver over
    fixed blocks of ``BLOCK`` trials (two-pass, float64) and the blocks merged in trial
    order with Pébay's pairwise formulas, so ``run_moments(...).interval()`` agrees with
    ``variance_interval(run_trials(...))`` to rounding (relative ~1e-12) and is
    bit-identical for any ``threads`` and ``chunk``.

    Returns
    -------
    SampleMoments
        Per-receiver count, mean and central moment sums M2, M3, M4 (row i for
        ``receivers[i]``); ``.interval(level)`` gives the mean, its stderr, s², se(s²)
        and the fourth-moment interval.
    """
    job = _prepare(scene, estimator, n, trials, seed, receivers)
    reducer = _BlockReducer(job.rows, job.trials)
    _drive(job, reducer.split, reducer.add, threads, chunk, progress)
    assert reducer.total is not None and not reducer.partial and not reducer.waiting
    return reducer.total


def warm(scene: Scene, estimator: str | Estimator, n: int) -> None:
    """Compile and load the trial kernel and build the scene's upload and light table with
    one trial at one receiver, so that a timed run that follows measures its trials alone
    (the light table of a large camera scene takes seconds; a first compile, tens)."""
    run_trials(scene, estimator, n, 1, receivers=[0], threads=1)


def block_count(trials: int) -> int:
    """The reduction blocks of ``trials`` trials: block b holds trials b·BLOCK … min((b+1)·BLOCK, trials) − 1."""
    return -(-trials // BLOCK)


def run_block_moments(
    scene: Scene,
    estimator: str | Estimator,
    n: int,
    trials: int,
    seed: int = 0,
    receivers: Sequence[int] | None = None,
    blocks: range | None = None,
    threads: int | None = None,
    chunk: int | None = None,
    progress: Progress | None = None,
) -> list[SampleMoments]:
    """The moments of each reduction block in ``blocks`` (default: all) of a run of
    ``trials`` trials, in trial order: the pieces :func:`run_moments` merges.

    ``SampleMoments.merged`` of the blocks of every range, concatenated in order, is
    ``run_moments(...)`` bit for bit, wherever each range ran: this is the unit of work
    a cluster distributes.  Takes the other arguments of :func:`run_trials`.
    """
    count = block_count(limits.count(trials, "trials"))
    blocks = range(count) if blocks is None else blocks
    if blocks.step != 1 or not 0 <= blocks.start < blocks.stop <= count:
        raise WarpisError(f"blocks must be a non-empty range within 0..{count} (got {blocks})")
    first = blocks.start * BLOCK
    job = _prepare(scene, estimator, n, min(blocks.stop * BLOCK, trials), seed, receivers, first)
    reducer = _BlockReducer(job.rows, trials, blocks.start, keep_blocks=True)
    _drive(job, reducer.split, reducer.add, threads, chunk, progress)
    assert reducer.blocks is not None and not reducer.partial and not reducer.waiting
    assert len(reducer.blocks) == len(blocks)
    return reducer.blocks


def pilot_alphas(scene: Scene, estimator: str | Estimator, n: int, trials: int, seed: int = 0,
                 receivers: Sequence[int] | None = None) -> np.ndarray:
    """The α the optimal combiner's pilot finds at each receiver in each trial, exactly as
    the trial kernel does: (R, M, N_g).  A one-line WarpisError for an estimator without a
    pilot or for arguments the kernels cannot take."""
    scene = as_scene(scene)
    est = parse_estimator(estimator)
    if not est.combiner_entry.pilot:
        raise WarpisError(f"estimator {est.spec!r}: combiner {est.combiner!r} has no pilot")
    args = KernelArgs.of(est, limits.count(n, "n"))
    trials = limits.count(trials, "trials")
    rx = select_receivers(scene, receivers)
    limits.memory(len(rx) * trials * 32, "pilot coefficients")
    up = upload(scene)
    out = wp.empty((len(rx), trials), dtype=wp.vec4d, device=up.device)
    techs = wp.array(np.array(args.techniques, dtype=np.int32), dtype=wp.int32, device=up.device)
    wp.launch(registered_kernels().pilot, dim=(len(rx), trials), device=up.device,
              inputs=[up.data, up.receiver_data, light_table(scene), wp.array(rx, dtype=wp.int32, device=up.device),
                      wp.uint32(limits.seed(seed)), techs, args.pilot, out])
    return out.numpy()[..., :est.technique_count]
