"""Cells on a Dask cluster: plain functions over plain data, the same bits as a local run.

A cell's trials are reduced in fixed blocks of ``engine.BLOCK`` trials, merged in trial
order (:func:`warpis.kernels.engine.run_block_moments`); the local pipeline merges the
same blocks in the same order (``run_moments``).  So the work spreads freely:

* **trial units** — consecutive blocks of one cell, or the blocks of several small cells
  batched, each unit about ``UNIT_EVALUATIONS`` integrand evaluations; a unit returns
  each block's moments (count, mean, M2..M4 per receiver), never raw trials;
* **references** — one task per (scene, receivers), **moments** — one per (scene,
  receiver) for every technique set of the run, each technique evaluated once, as
  :class:`~warpis.runs.cell.RunCache` finds them locally (``moments_together``);
* **scoring** — one task per cell: its blocks merged in order, its interval, reference
  and predictions (:func:`warpis.runs.cell.score_cell`).

Every task is a module-level function of its arguments; a scene travels once per worker
as plain data (``client.scatter``, keyed by its content digest), and a worker process
keeps what it uploaded and compiled (``kernels.device``'s cache) between tasks.  Tasks
are pure, so Dask may rerun those of a worker that dies.  A worker started with the
environment variable ``WARPIS_DEVICE=cuda`` runs its tasks on its GPU (the numbers then
agree with the CPU's to the CPU/CUDA tolerance, not bit for bit).

Dask is an optional extra (``pip install "warpis[cluster]"``); nothing here is imported
unless ``--scheduler`` or ``--workers`` is given.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any

from ..analysis.reference import Reference, reference
from ..stats import SampleMoments
from ..analysis.quadrature import Moments, moments_together
from ..errors import WarpisError
from ..kernels.engine import BLOCK, block_count, run_block_moments, warm
from ..scenes import Scene
from .cell import LEVEL, CellJob, MeasuredCell, Row, moment_sets, score_cell

EXTRA = 'pip install "warpis[cluster]"'
# Integrand evaluations per trial unit: a few seconds of one core, so that the scheduler's
# per-task cost (milliseconds) stays small next to the work, and a study's cells still
# spread over many workers.
UNIT_EVALUATIONS = 1 << 26
CONNECT_TIMEOUT = 20  # seconds to reach a scheduler
WORKER_TIMEOUT = 60  # seconds to wait for a first worker


# --------------------------------------------------------------------------- tasks (run on workers)


def worker_version() -> str:
    """The warpis version of the process this runs in."""
    from ..version import __version__

    return __version__


def start_worker() -> str:
    """Start Warp quietly in a worker (the CUDA-driver notice of a CPU-only machine is
    noise), so every later task finds it ready."""
    from ..kernels.device import quiet_warp

    quiet_warp()
    return worker_version()


def _on_device(scene: Scene) -> Scene:
    device = os.environ.get("WARPIS_DEVICE")
    return scene.on(device) if device else scene


@dataclass(frozen=True)
class UnitItem:
    """Blocks ``first``..``stop``−1 of one cell's trials."""

    scene: str  # the scene's digest: its key in the task's ``scenes``
    spec: str
    n: int
    trials: int
    seed: int
    receivers: tuple[int, ...]
    first: int
    stop: int


def unit_task(scenes: dict[str, Scene], items: list[UnitItem],
              delay: float = 0.0) -> list[tuple[list[SampleMoments], float]]:
    """Each item's block moments (trial order) and the seconds it took.  ``delay`` adds
    that many seconds per block (benchmarks: it stands in for a remote machine's work)."""
    out = []
    for item in items:
        scene = _on_device(scenes[item.scene])
        warm(scene, item.spec, item.n)  # a first compile or light table is not the trials' cost
        start = time.process_time()  # CPU seconds, as measure_cell counts the trials' cost
        blocks = run_block_moments(scene, item.spec, item.n, item.trials, seed=item.seed,
                                   receivers=list(item.receivers), blocks=range(item.first, item.stop))
        seconds = time.process_time() - start
        if delay:
            time.sleep(delay * (item.stop - item.first))
            seconds += delay * (item.stop - item.first)
        out.append((blocks, seconds))
    return out


def reference_task(scene: Scene, receivers: tuple[int, ...]) -> dict[int, Reference]:
    """As ``RunCache.reference``: receiver → reference, for all ``receivers`` at once."""
    return {r.index: r for r in reference(_on_device(scene), list(receivers))}


def moments_task(scene: Scene, receiver: int, technique_sets: list[tuple[str, ...]]) -> list[Moments]:
    """As ``RunCache.moments_of`` for every set of ``technique_sets`` at once: their moments, in order."""
    return moments_together(_on_device(scene), receiver, technique_sets)


def pick(values: list[Any], i: int) -> Any:
    """``values[i]``: one set's moments from a receiver's moments task."""
    return values[i]


def score_task(scene: Scene, job: CellJob, units: list[list[tuple[list[SampleMoments], float]]],
               places: list[tuple[int, int]], refs: dict[int, Reference],
               mom: dict[int, Moments] | None) -> tuple[list[Row], float]:
    """A cell's rows: its blocks (``units[u][i]`` for each (u, i) of ``places``, in trial
    order) merged in order, scored as :func:`warpis.runs.cell.measure_cell` scores them.
    (``job`` travels without its scene, which comes as ``scene``.)"""
    start = time.perf_counter()
    job = replace(job, scene=scene)
    parts = [units[u][i] for u, i in places]
    blocks = [b for part, _ in parts for b in part]
    stats = SampleMoments.merged(blocks).interval(LEVEL)
    trial_seconds = sum(seconds for _, seconds in parts)
    rows = score_cell(job.scene, job.receivers, job.estimator, job.n, job.trials, job.seed, stats, refs, mom,
                      trial_seconds / (len(job.receivers) * job.trials))
    return rows, trial_seconds + time.perf_counter() - start


# --------------------------------------------------------------------------- planning (client)


def plan_units(jobs: Sequence[CellJob], budget: int = UNIT_EVALUATIONS) -> list[list[tuple[int, int, int]]]:
    """Trial units: lists of (cell, first block, stop block).  A cell's blocks are cut into
    runs of about ``budget`` evaluations (at least one block each); runs smaller than that
    are batched with the next cells' until a unit reaches it."""
    units: list[list[tuple[int, int, int]]] = []
    current: list[tuple[int, int, int]] = []
    work = 0
    for c, job in enumerate(jobs):
        per_block = len(job.receivers) * job.n * min(BLOCK, job.trials)
        step = max(1, budget // max(1, per_block))
        count = block_count(job.trials)
        for first in range(0, count, step):
            stop = min(count, first + step)
            current.append((c, first, stop))
            work += per_block * (stop - first)
            if work >= budget:
                units.append(current)
                current, work = [], 0
    if current:
        units.append(current)
    return units


# --------------------------------------------------------------------------- the runner


def _distributed() -> Any:
    try:
        import distributed
    except ImportError:
        raise WarpisError(f"--scheduler and --workers need Dask's distributed scheduler: {EXTRA}") from None
    # warpis speaks in its own one-liners: Dask's loggers (some configured with their own
    # levels) would add lines of their own to stderr.
    names = [n for n in logging.root.manager.loggerDict if n.split(".")[0] in ("distributed", "tornado")]
    for name in ("distributed", "distributed.client", "tornado", *names):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    return distributed


def connect(scheduler: str | None = None, workers: int | None = None) -> ClusterRunner:
    """A runner on the Dask scheduler at ``scheduler`` (``tcp://host:port``), or on a new
    local cluster of ``workers`` single-threaded worker processes.  Every worker must run
    this warpis version; any failure is a one-line WarpisError."""
    if (scheduler is None) == (workers is None):
        raise WarpisError("give exactly one of --scheduler and --workers")
    distributed = _distributed()
    cluster = None
    where = f"--scheduler {scheduler}" if scheduler is not None else f"--workers {workers}"
    try:
        if workers is not None:
            cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                               dashboard_address=":0", silence_logs=logging.CRITICAL,
                                               env={"WARPIS_THREADS": "1"})
            client = distributed.Client(cluster)
        else:
            client = distributed.Client(scheduler, timeout=CONNECT_TIMEOUT)
    except (OSError, TimeoutError, ValueError) as exc:  # ValueError: an address Dask cannot parse
        if cluster is not None:
            cluster.close()
        raise WarpisError(f"{where}: cannot reach the scheduler ({_first_line(exc)})") from None
    runner = ClusterRunner(client, cluster, where)
    try:
        runner.check_workers()
    except BaseException:
        runner.close()
        raise
    return runner


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


class ClusterRunner:
    """Measures cells on a Dask cluster (see the module's docstring); use as a context
    manager, or call :meth:`close`."""

    def __init__(self, client: Any, cluster: Any = None, where: str = "the cluster"):
        self.client, self.cluster, self.where = client, cluster, where
        self.unit_evaluations = UNIT_EVALUATIONS  # the size of a trial unit (plan_units)
        self.delay = 0.0  # benchmarks only: seconds each block sleeps, standing in for remote work

    def __enter__(self) -> ClusterRunner:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        try:
            self.client.close()
        finally:
            if self.cluster is not None:
                self.cluster.close()

    def check_workers(self) -> None:
        """At least one worker, every one on this warpis version (Warp started quietly)."""
        try:
            self.client.wait_for_workers(1, timeout=WORKER_TIMEOUT)
            versions = self.client.run(start_worker)
        except (OSError, TimeoutError) as exc:
            raise WarpisError(f"{self.where}: no worker answered ({_first_line(exc)})") from None
        mine = worker_version()
        for address, version in sorted(versions.items()):
            if version != mine:
                raise WarpisError(f"{self.where}: worker {address} runs warpis {version}, this is warpis {mine}: "
                                  f"install the same version everywhere")

    def measure(self, jobs: Sequence[CellJob]) -> Iterator[tuple[int, MeasuredCell]]:
        """Submit every cell at once; yield ``(index, MeasuredCell)`` as cells finish."""
        distributed = _distributed()
        futures: list[Any] = []
        try:
            scored = self._submit(jobs, futures)
            for future in distributed.as_completed(scored):
                rows, seconds = future.result()
                yield scored[future], MeasuredCell(rows, seconds)
        except WarpisError:
            raise
        except (OSError, TimeoutError, distributed.CancelledError) as exc:
            raise WarpisError(f"{self.where}: lost the cluster ({_first_line(exc)}); finished cells are kept") from None
        finally:
            self.client.cancel(futures)

    def _submit_unit(self, jobs: Sequence[CellJob], unit: list[tuple[int, int, int]], scenes: dict[str, Any]) -> Any:
        items = [UnitItem(jobs[c].scene.digest, jobs[c].estimator.spec, jobs[c].n, jobs[c].trials, jobs[c].seed,
                          jobs[c].receivers, first, stop) for c, first, stop in unit]
        needed = {item.scene: scenes[item.scene] for item in items}
        return self.client.submit(unit_task, needed, items, self.delay, pure=False)

    def _submit(self, jobs: Sequence[CellJob], futures: list[Any]) -> dict[Any, int]:
        client = self.client
        scenes = {}
        for job in jobs:  # each scene once, by content
            if job.scene.digest not in scenes:
                scenes[job.scene.digest] = client.scatter(job.scene, hash=False, broadcast=True)
        refs = {}
        for job in jobs:
            key = (job.scene.digest, job.receivers)
            if key not in refs:
                refs[key] = client.submit(reference_task, scenes[job.scene.digest], job.receivers, pure=False)
        # One moments task per (scene, receiver) for all its technique sets; a set the scene
        # has no lights for (left out of moment_sets) gets a task of its own, whose error is
        # its own cell's alone.
        moms, groups = {}, []

        def submit_moments(digest: str, r: int, listed: list[tuple[str, ...]]) -> None:
            group = client.submit(moments_task, scenes[digest], r, listed, pure=False)
            groups.append(group)
            for i, techniques in enumerate(listed):
                moms[(digest, r, techniques)] = client.submit(pick, group, i, pure=False)

        for (digest, r), listed in moment_sets(jobs).items():
            submit_moments(digest, r, listed)
        for job in jobs:
            for r in job.receivers if job.predict else ():
                if (job.scene.digest, r, job.estimator.techniques) not in moms:
                    submit_moments(job.scene.digest, r, [job.estimator.techniques])
        units = plan_units(jobs, self.unit_evaluations)
        places: dict[int, list[tuple[int, int]]] = {c: [] for c in range(len(jobs))}
        for u, unit in enumerate(units):
            for i, (c, _, _) in enumerate(unit):
                places[c].append((u, i))
        unit_futures: dict[int, Any] = {}
        scored = {}
        # Cell by cell, its units then its scoring: Dask runs earlier submissions first, so
        # cells finish (and results.csv grows) in order, and scoring is spread over the run
        # instead of waiting for every unit.
        for c, job in enumerate(jobs):
            needed = sorted({u for u, _ in places[c]})
            for u in needed:
                if u not in unit_futures:
                    unit_futures[u] = self._submit_unit(jobs, units[u], scenes)
            local = {u: k for k, u in enumerate(needed)}
            mom = ({r: moms[(job.scene.digest, r, job.estimator.techniques)] for r in job.receivers}
                   if job.predict else None)
            future = client.submit(score_task, scenes[job.scene.digest], replace(job, scene=None),
                                   [unit_futures[u] for u in needed],
                                   [(local[u], i) for u, i in places[c]], refs[(job.scene.digest, job.receivers)],
                                   mom, pure=False)
            scored[future] = c
        futures += [*scenes.values(), *refs.values(), *groups, *moms.values(), *unit_futures.values(), *scored]
        return scored
