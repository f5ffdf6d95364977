"""What a study's rows say: summaries, fitted slopes, figures and ``OUT/report.md``.

Everything here reads the typed rows of ``results.csv`` (:func:`warpis.runs.study.typed_row`)
and writes nothing but through :mod:`warpis.runs.outdir`, atomically.
"""
from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..analysis.theory import missing_forms
from ..errors import WarpisError
from ..kernels.estimators import Estimator
from ..stats import fit_slope
from ..version import __version__
from ..vocabulary import MATERIALS
from ..vocabulary import expected_slope as registry_slope
from .cell import summarize
from .study_file import MAX_CONVERGENCE_RECEIVERS, MAX_REPORT_ROWS, Cell, Study, StudyRun, StudyScene


# --------------------------------------------------------------------------- summaries


def expected_slope(est: Estimator) -> dict[str, float] | None:
    """The rate theory expects for variance against N: smooth integrand, and with
    discontinuities (``vocabulary.expected_slope``); None where no rate is stated.

    −1 for independent and antithetic patterns (IS, MIS, mixture, biased alike): they
    change the constant, not the rate.  Jittered patterns: about −2 on smooth 2D
    integrands and about −1.5 where the integrand has edges (shadow boundaries, light
    silhouettes under BSDF sampling).  The mixture picks its technique at random per
    sample, which is not stratified: −1 whatever the pattern.
    """
    slope = registry_slope(est.pattern_entry, est.combiner_entry)
    return None if slope is None else slope.as_dict()


def expected_text(est: Estimator) -> str:
    e = expected_slope(est)
    if e is None:
        return "not stated"
    if e["smooth"] == e["discontinuous"]:
        return f"{e['smooth']:g}"
    return f"{e['smooth']:g} smooth, {e['discontinuous']:g} with edges"


def slopes(rows: list[dict], study: Study) -> list[dict]:
    """Per scene × receiver × estimator: the fitted slope of log variance against log N.

    Weighted by the variance intervals (``stats.fit_slope`` with se(s²)); cells whose
    variance or its standard error is 0 (an umbra) are left out, and a slope needs two N.
    """
    out = []
    by: dict[tuple, list[dict]] = {}
    for row in rows:
        by.setdefault((row["scene"], row["receiver"], row["estimator"]), []).append(row)
    for s in study.scenes:
        for r in s.receivers:
            for est in study.estimators:
                cells = sorted(by.get((s.name, r, est.spec), []), key=lambda c: c["n"])
                use = [c for c in cells if c["variance"] > 0 and c["variance_stderr"] > 0]
                entry = {"scene": s.name, "receiver": r, "estimator": est.spec, "points": len(use),
                         "slope": None, "slope_lo": None, "slope_hi": None, "expected": expected_slope(est)}
                if len({c["n"] for c in use}) >= 2:
                    fit = fit_slope([c["n"] for c in use], [c["variance"] for c in use],
                                    [c["variance_stderr"] for c in use])
                    entry.update(slope=fit.slope, slope_lo=fit.slope_lo, slope_hi=fit.slope_hi)
                if cells:
                    out.append(entry)
    return out


def form_summaries(rows: list[dict]) -> list[dict]:
    return [{"form": s.form, "kind": "bound" if s.bound else "equation", "cells": s.cells, "inside": s.inside,
             "median_ratio": s.median_ratio if math.isfinite(s.median_ratio) else None, "holds": s.holds}
            for s in summarize(rows)]


def summary(study: Study, cells: list[Cell], done: dict, rows: list[dict]) -> dict:
    """summary.json: the study, how many cells are finished, slopes and prediction verdicts (no timings)."""
    return {
        "study": study.name, "description": study.description, "warpis_version": __version__,
        "seed": study.seed, "trials": study.trials, "n": study.n, "predictions": study.predictions,
        "scenes": [{"scene": s.name, "source": s.source, "receivers": s.receivers,
                    "grid": list(s.scene.receivers.grid_shape) if _is_grid(s) else None} for s in study.scenes],
        "estimators": [e.spec for e in study.estimators],
        "labels": {e.spec: study.labels.get(e.spec, e.spec) for e in study.estimators},
        "cells": {"total": len(cells), "finished": sum(c.key in done for c in cells)},
        "complete": all(c.key in done for c in cells),
        "slopes": slopes(rows, study),
        "forms": form_summaries(rows) if study.predictions else [],
        # Forms whose scope covers an estimator that has no value for it, and why.
        "absent": {e.spec: missing for e in study.estimators if (missing := missing_forms(e))}
        if study.predictions else {},
    }


def _is_grid(s: StudyScene) -> bool:
    return s.scene.receivers.grid_shape is not None


def _mapper(s: StudyScene) -> Callable[[dict[int, float]], np.ndarray] | None:
    """Receiver → value dicts as 2D maps (NaN where absent): a camera's image, a receiver
    grid, or None for receivers that form no picture."""
    rx = s.scene.receivers
    if rx.image is not None:
        return lambda values: rx.image.to_image(_spread(values, len(rx)))
    if rx.grid_shape is not None:
        return lambda values: _spread(values, len(rx)).reshape(rx.grid_shape)
    return None


def _spread(values: dict[int, float], count: int) -> np.ndarray:
    out = np.full(count, np.nan)
    for r, v in values.items():
        out[r] = np.nan if v is None else v
    return out


# Penumbra: a diffuse pixel receiving between these shares of its unoccluded light.
PENUMBRA = (0.2, 0.8)


def representative_pixels(s: StudyScene, rows: list[dict]) -> list[tuple[str, int]]:
    """A camera scene's pixels whose convergence is worth a figure, from the references:
    a lit pixel (diffuse, unoccluded, the median value among those), a penumbra pixel
    (diffuse, closest to half its unoccluded value within ``PENUMBRA``) and a glossy
    highlight (the brightest non-diffuse pixel).  Kinds the picture lacks are left out;
    with none found, the brightest pixel stands in."""
    from ..analysis.reference import unoccluded_lambert

    ref = {r["receiver"]: r["reference"] for r in rows if r["scene"] == s.name}
    idx = np.array([r for r in s.receivers if ref.get(r) is not None], dtype=np.int64)
    if len(idx) == 0:
        return []
    value = np.array([ref[r] for r in idx])
    rx = s.scene.receivers
    diffuse = np.array([MATERIALS.by_code(c).diffuse for c in rx.material[idx]])
    share = np.full(len(idx), np.nan)
    if diffuse.any():  # the closed form costs milliseconds per pixel: only where it is read
        with np.errstate(divide="ignore", invalid="ignore"):
            share[diffuse] = value[diffuse] / unoccluded_lambert(s.scene, idx[diffuse])
    picked: list[tuple[str, int]] = []
    lit = np.flatnonzero(diffuse & (share > 0.999) & (value > 0))
    if len(lit):
        order = lit[np.argsort(value[lit])]
        picked.append(("lit", int(idx[order[len(order) // 2]])))
    shade = np.flatnonzero(diffuse & (share > PENUMBRA[0]) & (share < PENUMBRA[1]))
    if len(shade):
        picked.append(("penumbra", int(idx[shade[np.argmin(np.abs(share[shade] - 0.5))]])))
    glossy = np.flatnonzero(~diffuse & (value > 0))
    if len(glossy):
        picked.append(("glossy highlight", int(idx[glossy[np.argmax(value[glossy])]])))
    if not picked:
        picked.append(("brightest", int(idx[np.argmax(value)])))
    return picked


# --------------------------------------------------------------------------- figures and report

FIGURE_PREFIXES = ("convergence-", "variance-map-", "variance-ratio-", "slope-map-", "calibration.")


def _index(rows: list[dict]) -> dict[tuple, dict]:
    return {(r["scene"], r["receiver"], r["estimator"], r["n"]): r for r in rows}


@dataclass(frozen=True)
class Figure:
    """One figure to draw: a call of a :mod:`warpis.plots` function on plain data (picklable),
    and the report's note if it draws nothing."""

    draw: functools.partial
    if_none: str | None = None


def figures(study: Study, rows: list[dict], fig_dir: Path, processes: int = 1) -> tuple[list[Path], list[str]]:
    """Every figure the study's ``outputs`` ask for (PNG and PDF) → (paths, notes for the report),
    drawn by :func:`warpis.plots.draw_all` on up to ``processes`` processes."""
    from .. import plots

    plan = figure_plan(study, rows, fig_dir)
    jobs = [f for f in plan if isinstance(f, Figure)]
    drawn = iter(plots.draw_all([f.draw for f in jobs], processes))
    paths: list[Path] = []
    notes: list[str] = []
    for entry in plan:
        if isinstance(entry, str):
            notes.append(entry)
            continue
        made = next(drawn)
        paths += made
        if not made and entry.if_none:
            notes.append(entry.if_none)
    return paths, notes


def figure_plan(study: Study, rows: list[dict], fig_dir: Path) -> list[Figure | str]:
    """The figures and the report's notes on them, in the report's order."""
    from .. import plots

    plan: list[Figure | str] = []

    def job(plot: Callable[..., list[Path]], *args: Any, note: str | None = None) -> None:
        plan.append(Figure(functools.partial(plot, *args), note))

    if not study.outputs:
        return plan
    at = _index(rows)
    fits = {(f["scene"], f["receiver"], f["estimator"]): f for f in slopes(rows, study)}
    for s in study.scenes:
        slug = plots._slug(s.name)
        if "convergence" in study.outputs:
            if s.scene.receivers.image is not None:
                picked = representative_pixels(s, rows)
                shown = [r for _, r in picked]
                plan.append(f"{s.name}: convergence figures for representative pixels: "
                            + "; ".join(f"{what}: receiver {r} (pixel row {p // w}, column {p % w})"
                                        for what, r in picked
                                        for p, w in [(int(s.scene.receivers.image.pixel[r]),
                                                      s.scene.receivers.image.camera.width)]))
            else:
                shown = s.receivers[:MAX_CONVERGENCE_RECEIVERS]
                if len(s.receivers) > len(shown):
                    plan.append(f"{s.name}: convergence figures for the first {len(shown)} of its "
                                f"{len(s.receivers)} receivers")
            for r in shown:
                series = []
                for est in study.estimators:
                    cells = [at[k] for k in ((s.name, r, est.spec, n) for n in sorted(study.n)) if k in at]
                    if not cells:
                        continue
                    fit = fits.get((s.name, r, est.spec))
                    series.append({
                        "label": study.label(est), "n": [c["n"] for c in cells],
                        "variance": [c["variance"] for c in cells],
                        "lo": [c["variance_lo"] for c in cells], "hi": [c["variance_hi"] for c in cells],
                        "prediction": [c["predictions"].get("exact") for c in cells] if study.predictions else None,
                        "slope": (fit["slope"], fit["slope_lo"], fit["slope_hi"])
                        if fit and fit["slope"] is not None else None,
                    })
                job(plots.slope_convergence_plot, series,
                    f"{s.name}, receiver {r}: variance against N, {study.trials} trials per point"
                    + (" (dashed: exact prediction)" if study.predictions else ""),
                    fig_dir, f"convergence-{slug}-r{r}",
                    note=f"{s.name}, receiver {r}: zero variance under every estimator; no convergence figure"
                    if series else None)
        to_map = _mapper(s)
        if "maps" in study.outputs and to_map is not None:
            origin = "upper" if s.scene.receivers.image is not None else "lower"
            what = "the camera's pixels" if origin == "upper" else "the receiver grid"
            grids = {(est.spec, n): to_map({r: at[s.name, r, est.spec, n]["variance"] for r in s.receivers
                                            if (s.name, r, est.spec, n) in at})
                     for est in study.estimators for n in study.n}
            for n in sorted(study.n):
                job(plots.variance_map_plot, [(study.label(est), grids[est.spec, n]) for est in study.estimators],
                    f"{s.name}: variance over {what}, N = {n} (shared log scale)",
                    fig_dir, f"variance-map-{slug}-n{n}", origin)
            if len(study.estimators) >= 2:
                ea, eb = study.estimators[0], study.estimators[1]
                a, b = ea.spec, eb.spec
                with np.errstate(all="ignore"):
                    ratio = [(f"N = {n}", grids[a, n] / grids[b, n]) for n in sorted(study.n)]
                job(plots.ratio_map_plot, ratio, f"{s.name}: variance of {study.label(ea)} / variance of "
                                                 f"{study.label(eb)}", fig_dir, f"variance-ratio-{slug}", origin)
            if origin == "upper" and len(study.n) >= 2:
                slope_maps = [(study.label(est), to_map({r: f["slope"] for r in s.receivers
                                                         if (f := fits.get((s.name, r, est.spec))) is not None
                                                         and f["slope"] is not None}))
                              for est in study.estimators]
                job(plots.slope_map_plot, slope_maps, f"{s.name}: convergence slope per pixel over N = "
                                                      f"{', '.join(map(str, sorted(study.n)))}", fig_dir,
                    f"slope-map-{slug}")
    if "calibration" in study.outputs and study.predictions:
        job(plots.calibration_plot, rows, fig_dir, "calibration")
    return plan


def remove_stale_figures(fig_dir: Path, keep: list[Path]) -> None:
    """Delete figures of an earlier version of the study (they would mislead); run after report.md."""
    if not fig_dir.is_dir():
        return
    names = {p.name for p in keep}
    for old in fig_dir.iterdir():
        if old.suffix in (".png", ".pdf") and old.name.startswith(FIGURE_PREFIXES) and old.name not in names:
            try:
                old.unlink()
            except FileNotFoundError:
                pass
            except OSError as exc:
                raise WarpisError(f"{old}: cannot remove a stale figure: {exc.strerror or exc}") from None


def _est(study: Study, spec: str) -> str:
    name = study.labels.get(spec, spec)
    return f"`{spec}`" if name == spec else f"{name} (`{spec}`)"


def _g(x: float | None) -> str:
    return "" if x is None else f"{x:.4g}"


def efficiencies(rows: list[dict], study: Study) -> list[dict[str, Any]]:
    """Per N and estimator: the median over receivers of its efficiency relative to the
    study's first estimator at the same receiver and N, and the share of receivers where
    it is the most efficient (ties and unknown costs count for none)."""
    by = {(r["scene"], r["receiver"], r["n"], r["estimator"]): r.get("efficiency") for r in rows}
    base = study.estimators[0].spec
    out = []
    for n in study.n:
        places = sorted({(sc, rc) for sc, rc, nn, _ in by if nn == n})
        best: dict[tuple[str, int], str | None] = {}
        for place in places:
            effs = {e.spec: by.get((*place, n, e.spec)) for e in study.estimators}
            known = {k: v for k, v in effs.items() if v is not None}
            top = max(known.values(), default=None)
            winners = [k for k, v in known.items() if v == top]
            best[place] = winners[0] if len(winners) == 1 and len(known) == len(effs) else None
        for est in study.estimators:
            ratios = []
            for place in places:
                a, b = by.get((*place, n, est.spec)), by.get((*place, n, base))
                if a is not None and b is not None and not (math.isinf(a) and math.isinf(b)) and b > 0:
                    ratios.append(a / b)
            out.append({"n": n, "estimator": est.spec, "median_relative_efficiency":
                        float(np.median(ratios)) if ratios else None,
                        "wins_share": sum(w == est.spec for w in best.values()) / len(places) if places else None})
    return out


def _efficiency_lines(study: Study, rows: list[dict]) -> list[str]:
    table = efficiencies(rows, study)
    if not any(t["median_relative_efficiency"] is not None for t in table):
        return []
    lines = ["", "## Efficiency", "",
             f"Efficiency is 1/(variance × CPU seconds per estimate), the inverse of the time to reach unit variance "
             f"(columns `seconds_per_estimate` and `efficiency` of `results.csv`).  Relative to "
             f"{_est(study, study.estimators[0].spec)} at the same receiver and N: the median over receivers, and "
             f"the share of receivers where the estimator is the most efficient.  Times depend on the machine and "
             f"its load; ratios of estimators measured in one run are what carries over.", "",
             "| N | estimator | median relative efficiency | most efficient at |", "| --- | --- | --- | --- |"]
    for t in table:
        eff = "" if t["median_relative_efficiency"] is None else f"{t['median_relative_efficiency']:.3g}"
        share = "" if t["wins_share"] is None else f"{t['wins_share']:.0%}"
        lines.append(f"| {t['n']} | {_est(study, t['estimator'])} | {eff} | {share} |")
    return lines


def report(study: Study, rows: list[dict], run: StudyRun) -> str:
    """report.md: the study, the slopes, the prediction verdicts, the figures and a row per cell."""
    seconds = sum({r["cell"]: r["seconds"] or 0.0 for r in rows}.values())
    lines = [f"# warpis study: {study.name}", ""]
    if study.description:
        lines += [study.description, ""]
    lines += [
        f"From `{study.source}`: {len(study.scenes)} scene(s), {len(study.estimators)} estimator(s), "
        f"N = {', '.join(map(str, study.n))}, {study.trials} trials per cell, seed {study.seed}, predictions "
        f"{'on' if study.predictions else 'off'}; {run.cells} cells, {len(rows)} rows (one per receiver × cell), "
        f"{seconds:.0f} s of cell time as recorded in `results.csv`, warpis {__version__}.",
        "",
        "Files: [`results.csv`](results.csv) (one row per receiver × cell), [`summary.json`](summary.json), "
        "[`figures/`](figures/).",
        "",
        "| scene | source | receivers |", "| --- | --- | --- |",
    ]
    for s in study.scenes:
        grid = ""
        if _is_grid(s):
            grid = f" (a {s.scene.receivers.grid_shape[0]} × {s.scene.receivers.grid_shape[1]} grid)"
        shown = ", ".join(map(str, s.receivers)) if len(s.receivers) <= 16 else f"{len(s.receivers)} receivers"
        lines.append(f"| {s.name} | `{s.source}` | {shown}{grid} |")

    lines += ["", "## Convergence rates", "",
              "Slope of log variance against log N per estimator and receiver, fitted by weighted least squares "
              "(weights from the variance intervals), with its 95% interval.  *Expected* is what theory leads one "
              "to expect, not a test: −1 for independent and antithetic patterns (IS, MIS, mixture, biased); about "
              "−2 for jittered patterns on smooth 2D integrands and about −1.5 where the integrand has edges "
              "(shadow boundaries, light silhouettes under BSDF sampling).  Receivers whose variance is zero "
              "(an umbra) have no slope.", "",
              "| scene | receiver | estimator | slope | 95% interval | expected |",
              "| --- | --- | --- | --- | --- | --- |"]
    ests = {e.spec: e for e in study.estimators}
    for f in slopes(rows, study):
        if f["slope"] is None:
            continue
        lines.append(f"| {f['scene']} | {f['receiver']} | {_est(study, f['estimator'])} | {f['slope']:.2f} | "
                     f"[{f['slope_lo']:.2f}, {f['slope_hi']:.2f}] | {expected_text(ests[f['estimator']])} |")

    if study.predictions:
        lines += ["", "## Predictions", "",
                  "A form is *inside* a cell when |s² − V| ≤ 1.96·√(se(s²)² + se(V)²) (a bound: when it is "
                  "not below the interval); it *holds* when ≥ 80% of its cells are inside and the median "
                  "measured/predicted is within 10% of 1 (a bound: on every cell).", "",
                  "| form | verdict | kind | inside / cells | median measured/predicted |",
                  "| --- | --- | --- | --- | --- |"]
        for f in form_summaries(rows):
            ratio = "" if f["median_ratio"] is None else f"{f['median_ratio']:.3g}"
            lines.append(f"| {f['form']} | {'holds' if f['holds'] else '**fails**'} | {f['kind']} | "
                         f"{f['inside']}/{f['cells']} | {ratio} |")

    lines += _efficiency_lines(study, rows)
    lines += ["", "## Figures", ""]
    if not run.figures:
        lines.append("None (the study's `outputs` asked for none, or nothing had a variance to draw).")
    for note in run.notes:
        lines.append(f"- {note}")
    if run.notes:
        lines.append("")
    for path in run.figures:
        if path.suffix != ".png":
            continue
        rel = f"figures/{path.name}"
        lines += [f"### {path.stem}", "", f"![{path.stem}]({rel})", "", f"[PDF](figures/{path.stem}.pdf)", ""]

    lines += ["", "## Cells", ""]
    if len(rows) > MAX_REPORT_ROWS:  # a camera's pixels: the table would bury the report
        lines.append(f"{len(rows)} rows: see [`results.csv`](results.csv).")
        return "\n".join(lines) + "\n"
    lines += ["| scene | receiver | estimator | N | mean | reference | variance | 95% interval | exact prediction "
              "| measured/exact |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        exact = r["predictions"].get("exact")
        ratio = f"{r['variance'] / exact:.3g}" if exact else ""
        lines.append(f"| {r['scene']} | {r['receiver']} | {_est(study, r['estimator'])} | {r['n']} | {_g(r['mean'])} | "
                     f"{_g(r['reference'])} | {_g(r['variance'])} | [{_g(r['variance_lo'])}, {_g(r['variance_hi'])}] "
                     f"| {_g(exact)} | {ratio} |")
    return "\n".join(lines) + "\n"
