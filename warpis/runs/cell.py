"""One measure-against-predict pipeline: a *cell* measured, every prediction attached, verdicts.

A cell is scene × estimator × N over some receivers.  :func:`measure_cell` runs its M
trials, takes the fourth-moment interval of the variance at every receiver, looks up the
receiver's reference and moments in the run's :class:`RunCache`, attaches every form of
``theory.predictions`` that applies (a form that does not apply, or has no exact form, is
absent with its reason in ``Row.reasons``, never an error) and scores each against the
measurement.  ``warpis verify`` (one scene, default estimators) and ``warpis study`` both
call it and write its :class:`Row` in their own file formats.

Every rule of the comparison lives here, once:

* the interval: ``stats.variance_interval`` at ``LEVEL``, whose quantile is ``Z95``;
* the z-score of a form: (s² − V)/√(se(s²)² + se(V)²), None where that is not a number;
* *inside*: an equation when |z| ≤ ``Z95`` (|s² − V| ≤ 1.96·√(se(s²)² + se(V)²)), or,
  with no spread on either side, when s² = V; a bound when it is not below the interval;
* *holds*: an equation when ≥ ``INSIDE_SHARE`` of its cells are inside and the median
  measured/predicted ratio is within ``RATIO_TOLERANCE`` of 1; a bound on every cell;
* ``MIN_TRIALS``, the fewest trials that give a variance interval.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeVar

import numpy as np
from scipy.special import ndtri

from ..analysis.reference import Reference, reference
from ..stats import VarianceEstimate
from ..analysis.quadrature import Estimate, Moments, moments_together
from ..analysis.theory import BOUNDS, predictions
from ..errors import WarpisError
from ..kernels.engine import run_moments, warm
from ..kernels.estimators import Estimator
from ..kernels.techniques import check_lights
from ..limits import default_threads
from ..scenes import Scene

A = TypeVar("A")
T = TypeVar("T")

LEVEL = 0.95  # two-sided level of every interval and every "inside"
Z95 = float(ndtri(0.5 * (1.0 + LEVEL)))  # 1.959963984540054, the quantile stats.variance_interval uses
# The fourth-moment se(s²) = √((m4 − s⁴(M − 3)/(M − 1))/M) subtracts its σ⁴ term from
# M = 4 on; at M = 3 that term vanishes and at M = 2 it adds, so the "interval" says
# nothing.  One floor for verify, study and estimate (verify and study had 4; estimate 2).
MIN_TRIALS = 4
# An equation holds when this share of its cells is inside (95% intervals of heavy-tailed
# estimates under-cover somewhat: 80% leaves room for that, not for a wrong formula) ...
INSIDE_SHARE = 0.8
# ... and its median measured/predicted ratio lies within this factor of 1.
RATIO_TOLERANCE = 1.1


# --------------------------------------------------------------------------- the rules


def check_trials(trials: int, what: str = "--trials") -> None:
    """A one-line WarpisError unless ``trials`` ≥ ``MIN_TRIALS``."""
    if trials < MIN_TRIALS:
        raise WarpisError(f"{what} must be at least {MIN_TRIALS} to give a variance interval (got {trials})")


def is_bound(form: str) -> bool:
    """Whether ``form`` is an upper bound (theory.FORMS says so) rather than an equation."""
    return form in BOUNDS


def z_score(measured: float, measured_se: float, predicted: float, predicted_se: float) -> float | None:
    """(measured − predicted)/√(se² + se_p²); None with no spread on either side or when not finite."""
    scale = math.hypot(measured_se, predicted_se)
    if not scale > 0:
        return None
    z = (measured - predicted) / scale
    return z if math.isfinite(z) else None


def inside(form: str, variance: float, lo: float, value: float, z: float | None) -> bool:
    """Whether prediction ``value`` of ``form`` agrees with a measured variance.

    Written in terms of z so that a row read back from results.csv (which keeps z, not
    se(V)) is judged exactly as when it was measured.  A bound is inside when it is not
    below the interval (lo ≤ V); it is never scored by z.
    """
    if is_bound(form):
        return bool(lo <= value)
    if z is None:  # no spread at all (an umbra): only an exact match agrees
        return bool(value == variance)
    return bool(abs(z) <= Z95)


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


# --------------------------------------------------------------------------- per-run cache


@dataclass
class RunCache:
    """What the cells of one run share: references per (scene, receivers), moments per
    (scene, receiver, technique set).  Plain dicts keyed by plain values; scenes are told
    apart by name (a run never holds two scenes of one name).  ``technique_sets`` names,
    per (scene digest, receiver), the sets whose moments the run will ask for there (the
    runner knows its cells: :func:`moment_sets`); a receiver's first moments are then found
    for all of them together, each technique evaluated once (``moments_together``)."""

    references: dict[tuple[str, tuple[int, ...]], dict[int, Reference]] = field(default_factory=dict)
    moments: dict[tuple[str, int, tuple[str, ...]], Moments] = field(default_factory=dict)
    technique_sets: dict[tuple[str, int], list[tuple[str, ...]]] = field(default_factory=dict)

    def reference(self, scene: Scene, receivers: Sequence[int]) -> dict[int, Reference]:
        """Receiver → reference, for all ``receivers`` at once (computed on first use)."""
        key = (scene.name, tuple(int(r) for r in receivers))
        if key not in self.references:
            self.references[key] = {r.index: r for r in reference(scene, list(key[1]))}
        return self.references[key]

    def moments_of(self, scene: Scene, receiver: int, techniques: tuple[str, ...]) -> Moments:
        key = (scene.name, int(receiver), tuple(techniques))
        if key not in self.moments:
            wanted = [key[2], *(s for s in self.technique_sets.get((scene.digest, key[1]), ())
                                if s != key[2] and (scene.name, key[1], s) not in self.moments)]
            for s, mom in zip(wanted, moments_together(scene, key[1], wanted)):
                self.moments[(scene.name, key[1], s)] = mom
        return self.moments[key]

    def expect(self, jobs: Sequence[CellJob]) -> None:
        """Note the technique sets whose moments ``jobs`` will ask for (:func:`moment_sets`)."""
        for where, sets in moment_sets(jobs).items():
            known = self.technique_sets.setdefault(where, [])
            known += [s for s in sets if s not in known]


def moment_sets(jobs: Sequence[CellJob]) -> dict[tuple[str, int], list[tuple[str, ...]]]:
    """(scene digest, receiver) → the technique sets whose moments the cells of ``jobs``
    that predict ask for there, in the order first asked: what one ``moments_together``
    finds.  A set the scene has no lights for is left out: it is its own cell's one-line
    error, not every cell's at that receiver."""
    out: dict[tuple[str, int], list[tuple[str, ...]]] = {}
    for job in jobs:
        if not job.predict:
            continue
        techniques = job.estimator.techniques
        try:
            check_lights(job.scene, techniques)
        except WarpisError:
            continue
        for r in job.receivers:
            sets = out.setdefault((job.scene.digest, int(r)), [])
            if techniques not in sets:
                sets.append(techniques)
    return out


# --------------------------------------------------------------------------- one cell


@dataclass
class Row:
    """One receiver of a measured cell: the schema both verify.json rows and results.csv rows come from."""

    scene: str
    receiver: int
    estimator: str
    n: int
    trials: int
    seed: int
    mean: float
    mean_stderr: float
    reference: float
    reference_stderr: float
    variance: float
    variance_stderr: float
    variance_lo: float
    variance_hi: float
    # Every form that applies (FORMS order); ``reasons`` says why each other form is absent.
    predictions: dict[str, Estimate] = field(default_factory=dict)
    reasons: dict[str, str] = field(default_factory=dict)
    z: dict[str, float | None] = field(default_factory=dict)  # equations only
    inside: dict[str, bool] = field(default_factory=dict)
    # CPU seconds per estimate (process time of the trials ÷ receivers × trials): the cost in
    # efficiency = 1/(variance × cost).  None where it was not measured.
    seconds_per_estimate: float | None = None
    # Biased IS only: the seed's eq. 18 (the mean is ∫ f g, not F) and the bias.
    mean_predictions: dict[str, Estimate] = field(default_factory=dict)
    mean_inside: dict[str, bool] = field(default_factory=dict)
    bias: float | None = None

    @property
    def efficiency(self) -> float | None:
        """1/(variance × seconds per estimate): inf at zero variance, None when the cost is unknown."""
        return efficiency(self.variance, self.seconds_per_estimate)

    def as_dict(self) -> dict[str, Any]:
        """The plain row that summaries and figures read (study.typed_row gives the same
        keys back from results.csv): predictions as values, None where not finite."""
        return {"scene": self.scene, "receiver": self.receiver, "estimator": self.estimator, "n": self.n,
                "trials": self.trials, "seed": self.seed, "mean": self.mean, "mean_stderr": self.mean_stderr,
                "reference": self.reference, "reference_stderr": self.reference_stderr,
                "variance": self.variance, "variance_stderr": self.variance_stderr,
                "variance_lo": self.variance_lo, "variance_hi": self.variance_hi,
                "variance_ci": [self.variance_lo, self.variance_hi],
                "seconds_per_estimate": self.seconds_per_estimate, "efficiency": self.efficiency,
                "predictions": {k: _finite(e.value) for k, e in self.predictions.items()},
                "z": dict(self.z), "inside": dict(self.inside)}


def efficiency(variance: float | None, seconds_per_estimate: float | None) -> float | None:
    """Monte Carlo efficiency 1/(variance × cost): the inverse of the time to reach unit
    variance; inf at zero variance, None when either is unknown."""
    if variance is None or seconds_per_estimate is None or not seconds_per_estimate > 0:
        return None
    return math.inf if variance == 0 else 1.0 / (variance * seconds_per_estimate)


@dataclass
class MeasuredCell:
    """A cell's rows (one per receiver, in order) and its wall time."""

    rows: list[Row]
    seconds: float


def measure_cell(scene: Scene, receivers: Sequence[int], estimator: Estimator, n: int, trials: int, seed: int,
                 cache: RunCache, predict: bool = True, threads: int | None = None) -> MeasuredCell:
    """M = ``trials`` trials of ``estimator`` at N = ``n`` at every receiver → a scored row each.

    References (and, with ``predict``, moments) come from ``cache``, so the cells of a run
    compute each once.  ``seconds`` counts everything this call did, cache fills included.
    The trials are reduced to moments in blocks (``run_moments``): a cluster that runs the
    blocks elsewhere and merges them in order (``runs.cluster``) gets the same bits.
    """
    check_trials(trials, "trials")
    start = time.perf_counter()
    rx = [int(r) for r in receivers]
    warm(scene, estimator, n)  # a first compile or light table is not the trials' cost
    cpu = time.process_time()  # every thread's CPU time: the trials' cost whatever the thread count
    stats = run_moments(scene, estimator, n, trials, seed=seed, receivers=rx, threads=threads).interval(LEVEL)
    cost = (time.process_time() - cpu) / (len(rx) * trials)
    refs = cache.reference(scene, rx)
    mom = None
    if predict:
        mom = dict(zip(rx, each_receiver(lambda r: cache.moments_of(scene, r, estimator.techniques), rx, threads)))
    rows = score_cell(scene, rx, estimator, n, trials, seed, stats, refs, mom, cost, threads)
    return MeasuredCell(rows, time.perf_counter() - start)


def each_receiver(work: Callable[[A], T], receivers: Sequence[A], threads: int | None = None) -> list[T]:
    """``[work(r) for r in receivers]`` (receivers, or their rows) on up to ``threads`` threads
    (default: one per core).

    A receiver's theory alternates Warp launches, which release the GIL, with numpy
    reductions in one thread; one receiver at a time leaves a core idle through each
    reduction, two at a time keep both busy.  Every theory result depends on its own
    receiver's inputs only, so the values are the same in any order.  Ctrl-C in the
    calling thread stops every receiver not yet started.
    """
    workers = min(len(receivers), default_threads() if threads is None else threads)
    if workers <= 1:
        return [work(r) for r in receivers]
    pool = ThreadPoolExecutor(max_workers=workers)
    try:
        return [f.result() for f in [pool.submit(work, r) for r in receivers]]
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def score_cell(scene: Scene, receivers: Sequence[int], estimator: Estimator, n: int, trials: int, seed: int,
               stats: VarianceEstimate, refs: Mapping[int, Reference],
               moments: Mapping[int, Moments] | None, seconds_per_estimate: float | None = None,
               threads: int | None = None) -> list[Row]:
    """The rows of a measured cell: its trial statistics (row i for ``receivers[i]``), each
    receiver's reference and, given its moments, every prediction with its z and verdict
    (receivers on up to ``threads`` threads: :func:`each_receiver`); ``seconds_per_estimate``
    is the cell's measured cost, the same for every row."""
    rows = []
    for i, r in enumerate(int(r) for r in receivers):
        rows.append(Row(scene.name, r, estimator.spec, n, trials, seed, float(stats.mean[i]),
                        float(stats.mean_stderr[i]), refs[r].value, refs[r].stderr, float(stats.variance[i]),
                        float(stats.variance_stderr[i]), float(stats.lo[i]), float(stats.hi[i]),
                        seconds_per_estimate=seconds_per_estimate))
    if moments is not None:
        each_receiver(lambda row: _predict(row, scene, estimator, moments[row.receiver]), rows, threads)
    return rows


# --------------------------------------------------------------------------- runners


@dataclass(frozen=True)
class CellJob:
    """One cell to measure, as plain data (a Scene pickles): what a runner takes."""

    scene: Scene
    receivers: tuple[int, ...]
    estimator: Estimator
    n: int
    trials: int
    seed: int
    predict: bool = True


class Runner(Protocol):
    """Measures cells: yields ``(index into jobs, MeasuredCell)`` as each finishes."""

    def measure(self, jobs: Sequence[CellJob]) -> Iterator[tuple[int, MeasuredCell]]: ...


class LocalRunner:
    """Measures cells one after another in this process (``threads`` CPU threads per
    launch), sharing references and moments between them.  A runner's ``measure(jobs)``
    yields ``(index, MeasuredCell)`` as cells finish, in any order; ``runs.cluster``
    has the other one."""

    def __init__(self, threads: int | None = None):
        self.threads = threads
        self.cache = RunCache()

    def measure(self, jobs: Sequence[CellJob]) -> Iterator[tuple[int, MeasuredCell]]:
        self.cache.expect(jobs)
        for i, job in enumerate(jobs):
            yield i, measure_cell(job.scene, job.receivers, job.estimator, job.n, job.trials, job.seed, self.cache,
                                  predict=job.predict, threads=self.threads)


def _predict(row: Row, scene: Scene, est: Estimator, mom: Moments) -> None:
    """Attach every applicable form with its z and verdict (and eq. 18 for biased IS)."""
    with np.errstate(all="ignore"):  # an infinite bound (eq17) is a value, not a warning
        pred = predictions(scene, row.receiver, est, row.n, mom=mom)
    row.predictions, row.reasons = dict(pred), dict(pred.reasons)
    for form, e in pred.items():
        if not is_bound(form):
            row.z[form] = z_score(row.variance, row.variance_stderr, e.value, e.stderr)
        row.inside[form] = inside(form, row.variance, row.variance_lo, e.value, row.z.get(form))
    if est.combiner == "biased":  # seed eq. 18: the mean is ∫ f g, a bias of ∫ f g − F
        fg = mom.int_fg[0]
        row.mean_predictions = {"eq18": fg}
        row.mean_inside = {"eq18": inside("eq18", row.mean, -math.inf, fg.value,
                                          z_score(row.mean, row.mean_stderr, fg.value, fg.stderr))}
        row.bias = row.mean - row.reference


# --------------------------------------------------------------------------- verdicts


@dataclass
class FormSummary:
    form: str
    cells: int
    inside: int
    median_ratio: float  # measured / predicted
    bound: bool

    @property
    def holds(self) -> bool:
        """A bound holds when it is never below the interval; an equation when at least
        ``INSIDE_SHARE`` of its cells agree and the median ratio is within
        ``RATIO_TOLERANCE`` of 1."""
        if self.bound:
            return self.inside == self.cells
        if not 0 < self.median_ratio < math.inf:
            return False
        close = abs(math.log(self.median_ratio)) < math.log(RATIO_TOLERANCE)
        return self.inside >= INSIDE_SHARE * self.cells and close


def summarize(rows: Sequence[Mapping[str, Any]]) -> list[FormSummary]:
    """Per form over plain rows (``Row.as_dict``, verify.json or typed results.csv rows):
    cells, cells inside, median measured/predicted.  ``exact`` is every row's own variance,
    not an equation, and a cell of zero measured variance (an umbra) says nothing."""
    forms: dict[str, list[tuple[bool, float]]] = {}
    for row in rows:
        for form, value in row["predictions"].items():
            if form == "exact" or row["variance"] <= 0:
                continue
            ratio = 0.0 if value is None else row["variance"] / value if value > 0 else math.inf
            forms.setdefault(form, []).append((row["inside"][form], ratio))
    out = []
    for form in sorted(forms, key=form_order):
        cells = forms[form]
        ratios = np.array([r for _, r in cells])
        out.append(FormSummary(form, len(cells), sum(i for i, _ in cells), float(np.median(ratios)), is_bound(form)))
    return out


def form_order(form: str) -> tuple:
    """Numbered equations first, in number order, then the named forms alphabetically."""
    head = form.split("-")[0]
    digits = "".join(ch for ch in head if ch.isdigit())
    return (0 if digits else 1, int(digits) if digits else 0, form)
