"""``warpis verify``: measured variance beside every applicable prediction, cell by cell.

A *cell* is receiver × estimator × N.  Its measured variance (M trials, fourth-moment 95%
interval) is held against each form of ``theory.predictions``.  A form is *inside* when
the two agree within the 95% interval widened by the prediction's own error,
|s² − V| ≤ 1.96·√(se(s²)² + se(V)²); a bound (eq17, eq20, veach-bound) is inside when it
is not below the interval, lo ≤ V.  Results are written as ``verify.json`` (rewritten
atomically after every estimator × N, so an interrupted run keeps what it finished),
``verify.md`` and figures.
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

from . import outdir
from .engine import run_trials, select_receivers
from .errors import WarpisError
from .estimators import Estimator, parse_estimator
from .reference import reference
from .scene import Scene
from .stats import variance_interval
from .theory import BOUNDS, Moments, moments, predictions
from .vocabulary import COMBINERS, MATERIALS, PATTERNS

DEFAULT_N = (4, 16, 64, 256, 1024)
DEFAULT_TRIALS = 400
Z95 = 1.959963984540054


def default_techniques(scene: Scene) -> tuple[str, str]:
    """Light sampling plus the receivers' BSDF sampling: light-area + cosine where every
    receiver is diffuse, else light-solid-angle + the lobe of the glossy material (of the
    lowest code, should there be several)."""
    materials = [MATERIALS.by_code(c) for c in np.unique(scene.receivers.material)]
    lobes = [m.bsdf_technique for m in materials if not m.diffuse]
    return ("light-solid-angle", lobes[0]) if lobes else ("light-area", "cosine")


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
    registry entry names for verify (``Combiner.verify_under``; all by default)."""
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
    return tuple(PATTERNS) if under is None else under


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


def _inside(form: str, variance: float, se: float, lo: float, value: float, value_se: float) -> bool:
    if form in BOUNDS:
        return bool(lo <= value)
    return bool(abs(variance - value) <= Z95 * math.hypot(se, value_se))


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


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
) -> VerifyResult:
    """Measure and predict every cell; write ``out/verify.json`` as cells finish (if ``out``).

    ``out`` is locked (:func:`warpis.outdir.locked`) once the arguments have been checked,
    so bad input creates no folder and two runs never write one folder together.
    """
    techs = tuple(techniques) if techniques else default_techniques(scene)
    ests = [parse_estimator(e) for e in estimators] if estimators else default_estimators(techs)
    for est in ests:
        for n in n_values:
            est.check_n(n)
    if trials < 4:
        raise WarpisError(f"--trials must be at least 4 to give a variance interval (got {trials})")
    rx = select_receivers(scene, receivers if receivers is not None else default_receivers(scene))
    with outdir.locked(out) if out is not None else contextlib.nullcontext():
        return _measure(scene, techs, ests, n_values, trials, seed, rx, threads, out, progress)


def _measure(scene: Scene, techs: tuple[str, ...], ests: list[Estimator], n_values: Sequence[int], trials: int,
             seed: int, rx: np.ndarray, threads: int | None, out: Path | None,
             progress: Callable[[int, int], None] | None) -> VerifyResult:
    start = time.perf_counter()
    refs = {r.index: r for r in reference(scene, rx)}
    result = VerifyResult(scene.name, trials, seed, techs)
    moment_cache: dict[tuple[int, tuple[str, ...]], Moments] = {}
    total, done = len(ests) * len(n_values), 0
    for est in ests:
        for n in n_values:
            values = run_trials(scene, est, n, trials, seed=seed, receivers=rx, threads=threads)
            stats = variance_interval(values)
            for i, r in enumerate(rx):
                key = (int(r), est.techniques)
                if key not in moment_cache:
                    moment_cache[key] = moments(scene, int(r), est.techniques)
                result.rows.append(_row(scene, int(r), est, n, stats, i, moment_cache[key], refs[int(r)]))
            done += 1
            result.seconds = time.perf_counter() - start
            if out is not None:
                write_json(out, result)
            if progress is not None:
                progress(done, total)
    return result


def _row(scene: Scene, r: int, est: Estimator, n: int, stats, i: int, mom: Moments, ref) -> dict:
    pred = predictions(scene, r, est, n, mom=mom)
    var, se, lo, hi = (float(stats.variance[i]), float(stats.variance_stderr[i]), float(stats.lo[i]),
                       float(stats.hi[i]))
    row = {
        "receiver": r, "estimator": est.spec, "n": n,
        "mean": float(stats.mean[i]), "mean_stderr": float(stats.mean_stderr[i]),
        "reference": ref.value, "reference_stderr": ref.stderr,
        "variance": var, "variance_stderr": se, "variance_ci": [lo, hi],
        "predictions": {k: _finite(e.value) for k, e in pred.items()},
        "prediction_rel_error": {k: _finite(e.rel_error) for k, e in pred.items()},
        "inside": {k: _inside(k, var, se, lo, e.value, e.stderr) for k, e in pred.items()},
        "z": {k: _finite((var - e.value) / math.hypot(se, e.stderr)) if math.hypot(se, e.stderr) > 0 else None
              for k, e in pred.items() if k not in BOUNDS},
    }
    if est.combiner == "biased":  # seed eq. 18: the mean is ∫ f g, a bias of ∫ f g − F
        fg = mom.int_fg[0]
        row["mean_predictions"] = {"eq18": fg.value}
        row["mean_inside"] = {"eq18": bool(abs(row["mean"] - fg.value) <= Z95 * math.hypot(row["mean_stderr"],
                                                                                            fg.stderr))}
        row["bias"] = row["mean"] - ref.value
    return row


def write_json(out: Path, result: VerifyResult) -> None:
    """Write ``verify.json`` atomically (a unique temporary file, then a rename)."""
    outdir.make_dir(out)
    outdir.write_text(out / "verify.json", json.dumps(result.as_json(), indent=1))


def write_outputs(out: Path, result: VerifyResult, command: str) -> None:
    """``verify.md`` and the figures beside ``verify.json``, each replaced atomically."""
    from . import plots

    outdir.make_dir(out)
    outdir.write_text(out / "verify.md", markdown(result, command))
    plots.calibration_plot(result.rows, out)
    for r in sorted({row["receiver"] for row in result.rows}):
        plots.convergence_plot(result.rows, r, out)


# --------------------------------------------------------------------------- summary


@dataclass
class FormSummary:
    form: str
    cells: int
    inside: int
    median_ratio: float  # measured / predicted
    bound: bool

    @property
    def holds(self) -> bool:
        """A bound holds when it is never below the interval; an equation when ≥ 80% of
        its cells agree and the median ratio is within 10% of 1 (95% intervals of heavy-
        tailed estimates under-cover somewhat, so 80% leaves room for that, not for a
        wrong formula)."""
        if self.bound:
            return self.inside == self.cells
        if not 0 < self.median_ratio < math.inf:
            return False
        return self.inside >= 0.8 * self.cells and abs(math.log(self.median_ratio)) < math.log(1.1)


def summarize(rows: Sequence[dict]) -> list[FormSummary]:
    """Per form: cells, cells inside, median measured/predicted ratio."""
    forms: dict[str, list[tuple[bool, float]]] = {}
    for row in rows:
        for form, value in row["predictions"].items():
            if form == "exact" or row["variance"] <= 0:
                continue
            ratio = 0.0 if value is None else row["variance"] / value if value > 0 else math.inf
            forms.setdefault(form, []).append((row["inside"][form], ratio))
    out = []
    for form in sorted(forms, key=_form_order):
        cells = forms[form]
        ratios = np.array([r for _, r in cells])
        out.append(FormSummary(form, len(cells), sum(i for i, _ in cells), float(np.median(ratios)), form in BOUNDS))
    return out


def _form_order(form: str) -> tuple:
    head = form.split("-")[0]
    digits = "".join(ch for ch in head if ch.isdigit())
    return (0 if digits else 1, int(digits) if digits else 0, form)


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
