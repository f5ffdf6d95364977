"""``warpis verify``: measured variance beside every applicable prediction, cell by cell.

Verify is a study of one scene with default estimators: each receiver × estimator × N
*cell* is measured by :func:`warpis.runs.cell.measure_cell`, the pipeline ``warpis study``
shares, which also holds the rules (a form is *inside* when
|s² − V| ≤ 1.96·√(se(s²)² + se(V)²), a bound (eq17, eq20, veach-bound) when it is not
below the interval; when a form *holds*).  What is verify's own is the choice of
estimators and the output: ``verify.json`` (rewritten atomically after every
estimator × N, so an interrupted run keeps what it finished), ``verify.md`` and figures.
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import limits
from ..analysis.theory import missing_forms
from ..kernels.engine import as_scene, select_receivers
from ..kernels.estimators import COMBINERS, Estimator, parse_estimator
from ..vocabulary import MATERIALS
from ..kernels.patterns import PATTERNS
from ..scenes import Scene
from . import outdir
from .cell import CellJob, LocalRunner, Row, Runner, check_trials, summarize

DEFAULT_N = (4, 16, 64, 256, 1024)
DEFAULT_TRIALS = 400


def default_techniques(scene: Scene) -> tuple[str, str]:
    """Light sampling plus the receivers' BSDF sampling: light-area + cosine where every
    receiver is diffuse, else light-solid-angle + the lobe of the glossy materials (``bsdf``,
    each receiver's own sampling, when they have different lobes)."""
    materials = [MATERIALS.by_code(c) for c in np.unique(scene.receivers.material)]
    lobes = {m.bsdf_technique for m in materials if not m.diffuse}
    if not lobes:
        return ("light-area", "cosine")
    return ("light-solid-angle", lobes.pop() if len(lobes) == 1 else "bsdf")


DEFAULT_RECEIVERS = 8


def default_receivers(scene: Scene) -> list[int]:
    """All receivers, or ``DEFAULT_RECEIVERS`` of them evenly spread through the list."""
    count = len(scene.receivers)
    if count <= DEFAULT_RECEIVERS:
        return list(range(count))
    return sorted({int(round(i)) for i in np.linspace(0, count - 1, DEFAULT_RECEIVERS)})


def default_estimators(techniques: Sequence[str]) -> list[Estimator]:
    """Every estimator the technique set allows: each one-technique combiner per technique,
    then each combiner of several techniques over the set, each under the patterns its
    registry entry names for verify (``Combiner.verify_under``; by default every pattern
    with an exact form)."""
    techs = tuple(techniques)
    out: list[Estimator] = []
    for t in techs:
        out += [Estimator(p, c.name, (t,)) for c in COMBINERS.values() if not c.several for p in _patterns(c.name)]
    if len(techs) > 1:
        out += [Estimator(p, c.name, techs) for c in COMBINERS.values() if c.several for p in _patterns(c.name)]
    return out


def _patterns(combiner: str) -> tuple[str, ...]:
    """The patterns verify runs ``combiner`` under by default."""
    under = COMBINERS[combiner].verify_under
    if under is not None:
        return under
    # Verify holds measurements against the theory: patterns without it (neither blocks nor
    # a pair form, so no exact form) have nothing to be held against, and are left to studies.
    return tuple(name for name, entry in PATTERNS.items() if entry.blocks is not None or entry.sum_variance is not None)


@dataclass
class VerifyResult:
    scene: str
    trials: int
    seed: int
    techniques: tuple[str, ...]
    rows: list[dict] = field(default_factory=list)
    seconds: float = 0.0

    def as_json(self) -> dict:
        return {"scene": self.scene, "trials": self.trials, "seed": self.seed, "techniques": list(self.techniques),
                "seconds": round(self.seconds, 2), "rows": self.rows}


def verify(
    scene: Scene,
    techniques: Sequence[str] | None = None,
    estimators: Sequence[str | Estimator] | None = None,
    n_values: Sequence[int] = DEFAULT_N,
    trials: int = DEFAULT_TRIALS,
    seed: int = 0,
    receivers: Sequence[int] | None = None,
    threads: int | None = None,
    out: Path | None = None,
    progress: Callable[[int, int], None] | None = None,
    runner: Runner | None = None,
) -> VerifyResult:
    """Measure and predict every cell; write ``out/verify.json`` as cells finish (if ``out``).

    ``out`` is locked (:func:`warpis.runs.outdir.locked`) once the arguments have been checked,
    so bad input creates no folder and two runs never write one folder together.
    ``runner`` measures the cells (default: here, with ``threads``; a Dask cluster:
    :func:`warpis.runs.cluster.connect`); the result does not depend on it.
    """
    scene = as_scene(scene)
    techs = tuple(techniques) if techniques else default_techniques(scene)
    ests = [parse_estimator(e) for e in estimators] if estimators else default_estimators(techs)
    for est in ests:
        for n in n_values:
            est.check_n(n)
    trials = limits.count(trials, "trials")
    check_trials(trials)
    seed = limits.seed(seed)  # up front, as every other bad value: before a folder or a cell
    rx = select_receivers(scene, receivers if receivers is not None else default_receivers(scene))
    with outdir.locked(out) if out is not None else contextlib.nullcontext():
        return _measure(scene, techs, ests, n_values, trials, seed, rx, threads, out, progress, runner)


def _measure(scene: Scene, techs: tuple[str, ...], ests: list[Estimator], n_values: Sequence[int], trials: int,
             seed: int, rx: np.ndarray, threads: int | None, out: Path | None,
             progress: Callable[[int, int], None] | None, runner: Runner | None) -> VerifyResult:
    start = time.perf_counter()
    result = VerifyResult(scene.name, trials, seed, techs)
    receivers = tuple(int(r) for r in rx)
    jobs = [CellJob(scene, receivers, est, n, trials, seed) for est in ests for n in n_values]
    finished: dict[int, list[dict]] = {}
    for done, (i, cell) in enumerate((runner or LocalRunner(threads)).measure(jobs), start=1):
        finished[i] = [json_row(row) for row in cell.rows]
        result.rows = [row for j in sorted(finished) for row in finished[j]]  # estimator × N order
        result.seconds = time.perf_counter() - start
        if out is not None:
            write_json(out, result)
        if progress is not None:
            progress(done, len(jobs))
    return result


def json_row(row: Row) -> dict:
    """A row of verify.json (docs/python-api.md, "JSON that other tools read"): the shared row's
    numbers, each prediction's relative error, and eq. 18 with the bias for biased IS."""
    plain = row.as_dict()
    out = {k: plain[k] for k in ("receiver", "estimator", "n", "mean", "mean_stderr", "reference",
                                 "reference_stderr", "variance", "variance_stderr", "variance_ci", "predictions")}
    out["prediction_rel_error"] = {k: _finite(e.rel_error) for k, e in row.predictions.items()}
    out["inside"], out["z"] = plain["inside"], plain["z"]
    out["absent"] = missing_forms(row.estimator)  # forms in scope with no value, and why
    if row.mean_predictions:
        out["mean_predictions"] = {k: e.value for k, e in row.mean_predictions.items()}
        out["mean_inside"] = dict(row.mean_inside)
        out["bias"] = row.bias
    return out


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def write_json(out: Path, result: VerifyResult) -> None:
    """Write ``verify.json`` atomically (a unique temporary file, then a rename)."""
    outdir.make_dir(out)
    outdir.write_text(out / "verify.json", json.dumps(result.as_json(), indent=1))


def write_outputs(out: Path, result: VerifyResult, command: str) -> None:
    """``verify.md`` and the figures beside ``verify.json``, each replaced atomically."""
    from .. import plots

    outdir.make_dir(out)
    outdir.write_text(out / "verify.md", markdown(result, command))
    plots.calibration_plot(result.rows, out)
    for r in sorted({row["receiver"] for row in result.rows}):
        plots.convergence_plot(result.rows, r, out)


# --------------------------------------------------------------------------- summary


def summary_lines(result_or_rows) -> list[str]:
    rows = result_or_rows.rows if isinstance(result_or_rows, VerifyResult) else result_or_rows
    lines = []
    for s in summarize(rows):
        verdict = "holds" if s.holds else "FAILS"
        kind = "bound" if s.bound else "equation"
        lines.append(f"{s.form:<26} {verdict:<6} {kind:<8} inside on {s.inside:>4}/{s.cells:<4} cells, "
                     f"median measured/predicted {s.median_ratio:.3g}")
    return lines


def markdown(result: VerifyResult, command: str) -> str:
    """verify.md: the command, the summary per form, and the full table."""
    lines = [f"# warpis verify: {result.scene}", "", f"`{command}`", "",
             f"{result.trials} trials per cell, seed {result.seed}, techniques {'+'.join(result.techniques)}, "
             f"{len(result.rows)} cells, {result.seconds:.0f} s.", "", "## Summary", "",
             "| form | verdict | kind | inside / cells | median measured/predicted |", "| --- | --- | --- | --- | --- |"]
    for s in summarize(result.rows):
        lines.append(f"| {s.form} | {'holds' if s.holds else '**fails**'} | {'bound' if s.bound else 'equation'} "
                     f"| {s.inside}/{s.cells} | {s.median_ratio:.3g} |")
    lines += ["", "## Cells", "", "| receiver | estimator | N | variance | 95% interval | form | predicted | "
              "measured/predicted | inside |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for row in result.rows:
        lo, hi = row["variance_ci"]
        for form, value in row["predictions"].items():
            if form == "exact":
                continue
            ratio = row["variance"] / value if value else float("nan")  # None: an infinite bound
            shown = "∞" if value is None else f"{value:.4g}"
            lines.append(f"| {row['receiver']} | `{row['estimator']}` | {row['n']} | {row['variance']:.4g} | "
                         f"[{lo:.4g}, {hi:.4g}] | {form} | {shown} | {ratio:.3g} | "
                         f"{'yes' if row['inside'][form] else 'no'} |")
    return "\n".join(lines) + "\n"
