"""Studies: a TOML file of scenes × estimators × N, run cell by cell into files that survive a kill.

A study file holds one ``[study]`` table (docs/studies.md gives the format), read by
:mod:`warpis.runs.study_file`; the summaries, figures and report are
:mod:`warpis.runs.study_report`'s.  A
*cell* is scene × estimator × N over the study's receivers of that scene; each cell adds
one row per receiver to ``OUT/results.csv`` and refreshes ``OUT/summary.json``.  Both are
rewritten after every cell through a uniquely named temporary file and :func:`os.replace`,
so a run killed at any moment leaves valid files holding every finished cell.  A run holds
an exclusive lock on ``OUT`` (``OUT/.lock``, :mod:`warpis.runs.outdir`) from start to end, so a
second run on the same folder stops at once instead of racing the first.

Each cell has a *key*: a hash of the scene's content digest (``Scene.digest``: its
arrays, not its files or their paths) and name, the estimator, N, the trials, the seed,
the receivers, whether predictions are attached and the warpis version.  Rows carry
their key (column ``cell``).  A rerun reads the rows back, keeps every row whose key is
still in the study *verbatim* (its ``seconds`` included), drops the rows of cells no
longer in the study, computes only the missing cells and writes the files in the
canonical cell order (scenes, then estimators, then N, as listed; receivers in order
within a cell).  Every number is deterministic, so a resumed run ends
with the same files as an uninterrupted one, except the ``seconds`` of the cells the
second run computed.  ``summary.json`` holds no timings and is byte-identical.

After the last cell the figures (``OUT/figures/``) and then ``OUT/report.md`` are written
from the rows, each atomically: convergence plots with fitted slopes, variance maps over a
receiver grid and a calibration plot of the predictions.  A damaged ``results.csv`` costs
only its unreadable rows, whose cells are recomputed.
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..version import __version__
from . import outdir
from .cell import CellJob, LocalRunner, MeasuredCell, Row, Runner, inside
from .study_file import FORMS, HEADER, Z_FORMS, Cell, Study, StudyRun
from .study_report import figures, remove_stale_figures, report, summary


# --------------------------------------------------------------------------- rows


def _num(x: float | None) -> str:
    """A float as the shortest text that reads back to the same float ('' for None)."""
    if x is None:
        return ""
    return repr(float(x))


def _parse(text: str) -> float | None:
    return float(text) if text != "" else None


# Columns every row written by csv_rows fills (predictions and z may be empty).
REQUIRED = ("scene", "receiver", "estimator", "n", "trials", "seed", "mean", "mean_stderr", "reference",
            "reference_stderr", "variance", "variance_stderr", "variance_lo", "variance_hi", "seconds",
            "warpis_version", "cell")


def typed_row(raw: list[str]) -> dict[str, Any]:
    """A CSV row (strings) → a dict of numbers, with ``predictions``/``z``/``inside`` as in verify.json.

    ValueError for a row csv_rows cannot have written (damaged on disk): wrong column
    count, an empty required field, a field that is not a number, a malformed cell key.
    """
    if len(raw) != len(HEADER):
        raise ValueError(f"{len(raw)} fields, expected {len(HEADER)}")
    d = dict(zip(HEADER, raw))
    empty = [k for k in REQUIRED if d[k] == ""]
    if empty:
        raise ValueError(f"empty {empty[0]}")
    if not re.fullmatch(r"[0-9a-f]{16}", d["cell"]):
        raise ValueError(f"malformed cell key {d['cell']!r}")
    row: dict[str, Any] = {"scene": d["scene"], "receiver": int(d["receiver"]), "estimator": d["estimator"],
                           "n": int(d["n"]), "trials": int(d["trials"]), "seed": int(d["seed"]),
                           "warpis_version": d["warpis_version"], "cell": d["cell"]}
    for k in ("mean", "mean_stderr", "reference", "reference_stderr", "variance", "variance_stderr",
              "variance_lo", "variance_hi", "seconds", "seconds_per_estimate", "efficiency"):
        row[k] = _parse(d[k])
    row["variance_ci"] = [row["variance_lo"], row["variance_hi"]]
    preds = {f: _parse(d[f"pred_{f}"]) for f in FORMS if d[f"pred_{f}"] != ""}
    row["predictions"] = {f: (v if v is not None and math.isfinite(v) else None) for f, v in preds.items()}
    row["z"] = {f: _parse(d[f"z_{f}"]) for f in Z_FORMS if f in preds}
    # Judged by the pipeline's one rule, from z (results.csv keeps z, not se(V)).
    row["inside"] = {f: inside(f, row["variance"], row["variance_lo"], v, row["z"].get(f))
                     for f, v in preds.items()}
    return row


def cell_job(study: Study, cell: Cell) -> CellJob:
    """What a runner needs to measure ``cell`` (:func:`warpis.runs.cell.measure_cell`)."""
    s = cell.scene
    return CellJob(s.scene, tuple(int(r) for r in s.receivers), cell.estimator, cell.n, study.trials, study.seed,
                   study.predictions)


def csv_rows(cell: Cell, measured: MeasuredCell) -> list[list[str]]:
    """A measured cell → its CSV rows (strings)."""
    seconds = f"{measured.seconds:.3f}"
    return [csv_row(row) + [seconds, __version__, cell.key] for row in measured.rows]


def csv_row(row: Row) -> list[str]:
    """A measured row as the columns of results.csv before ``seconds``: numbers as the
    shortest text that reads back to the same float, '' for a form that is absent."""
    return ([row.scene, str(row.receiver), row.estimator, str(row.n), str(row.trials), str(row.seed)]
            + [_num(x) for x in (row.mean, row.mean_stderr, row.reference, row.reference_stderr, row.variance,
                                 row.variance_stderr, row.variance_lo, row.variance_hi)]
            + [_num(row.predictions[f].value) if f in row.predictions else "" for f in FORMS]
            + [_num(row.z.get(f)) for f in Z_FORMS]
            + [_num(row.seconds_per_estimate), _num(row.efficiency)])


# --------------------------------------------------------------------------- files


def read_rows(path: Path) -> tuple[dict[str, list[list[str]]], str | None]:
    """Rows of an earlier ``results.csv`` grouped by cell key, and a note on what could not be read.

    Damage (a torn or edited file, bad bytes, a garbage header) costs only the rows it
    touches: every row that parses is kept verbatim; the others are counted in the note
    and their cells, no longer complete, are recomputed.  Rows of another warpis version
    carry other cell keys and are dropped as cells no longer in the study.
    """
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return {}, None
    except OSError as exc:
        return {}, f"cannot read {path} ({exc.strerror or exc}); recomputing every cell"
    # Bytes that are not UTF-8 become lone surrogates, which no row warpis wrote holds: they
    # make their row unreadable, not the file.
    reader = csv.reader(io.StringIO(data.decode("utf-8", "surrogateescape"), newline=""))
    out: dict[str, list[list[str]]] = {}
    bad, header = 0, None
    while True:
        try:
            row = next(reader)
        except StopIteration:
            break
        except csv.Error:  # e.g. a field over the csv module's size limit; the reader goes on
            bad += 1
            continue
        if header is None:
            header = row
            continue
        if not row:
            continue
        try:
            "".join(row).encode("utf-8")
            typed_row(row)
        except (ValueError, TypeError):  # UnicodeEncodeError is a ValueError
            bad += 1
            continue
        out.setdefault(row[-1], []).append(row)
    return out, _damage_note(path, header, bad)


def _damage_note(path: Path, header: list[str] | None, bad: int) -> str | None:
    notes = []
    if header is not None and header != HEADER:
        notes.append("its header is not warpis's (damaged, or another version); rows are read by position")
    if bad:
        notes.append(f"{bad} unreadable row(s) will be recomputed")
    return f"{path}: {'; '.join(notes)}" if notes else None


def _finished(rows: list[list[str]] | None, cell: Cell, study: Study) -> bool:
    """Whether ``rows`` are exactly the cell's: its receivers in order, and its scene, estimator, N,
    trials and seed in every row (the key says so too, but a damaged field would not change the key)."""
    if rows is None or [r[1] for r in rows] != [str(i) for i in cell.scene.receivers]:
        return False
    same = [cell.scene.name, cell.estimator.spec, str(cell.n), str(study.trials), str(study.seed)]
    return all([r[0], r[2], r[3], r[4], r[5]] == same for r in rows)


def csv_text(cells: list[Cell], done: dict[str, list[list[str]]]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(HEADER)
    for c in cells:
        if c.key in done:
            w.writerows(done[c.key])
    return buf.getvalue()


def write_results(out: Path, study: Study, cells: list[Cell], done: dict[str, list[list[str]]],
                  typed: dict[str, list[dict]] | None = None) -> None:
    """results.csv, then summary.json, each replaced atomically.

    ``typed`` caches :func:`typed_row` of each finished cell's rows (filled as needed).
    """
    typed = {} if typed is None else typed
    outdir.write_text(out / "results.csv", csv_text(cells, done))
    for c in cells:
        if c.key in done and c.key not in typed:
            typed[c.key] = [typed_row(r) for r in done[c.key]]
    rows = [r for c in cells if c.key in done for r in typed[c.key]]
    outdir.write_text(out / "summary.json", json.dumps(summary(study, cells, done, rows), indent=1) + "\n")


# --------------------------------------------------------------------------- running


def run_study(study: Study, out: Path, progress: Callable[[int, int], None] | None = None,
              log: Callable[[str], None] | None = None, runner: Runner | None = None,
              figure_processes: int = 1) -> StudyRun:
    """Run every unfinished cell of ``study`` into ``out``; then figures and report.md.

    ``progress(done, total)`` counts the cells this run computes; ``log`` receives one-line
    notes (cells skipped, rows dropped, damaged rows) as they happen.  The folder is locked
    for the whole run (:func:`warpis.runs.outdir.locked`): a second run on it fails at once,
    so no run ever rewrites results.csv without rows the other one finished.  A file that
    cannot be written is a one-line WarpisError; the files already there stay intact.
    ``runner`` measures the cells (default: :class:`~warpis.runs.cell.LocalRunner`; a
    Dask cluster: :func:`warpis.runs.cluster.connect`); the files do not depend on it.
    ``figure_processes`` ≥ 2 lets a second process draw figures beside this one
    (:func:`warpis.plots.draw_all`; the command line passes the study's threads).  It is
    spawned, so it imports the caller's ``__main__`` again: a script that passes it
    needs the ``if __name__ == "__main__":`` guard, as any use of multiprocessing does.
    """
    with outdir.locked(Path(out)) as out:
        return _run_locked(study, out, progress, log or (lambda line: None), runner, figure_processes)


def _run_locked(study: Study, out: Path, progress: Callable[[int, int], None] | None,
                log: Callable[[str], None], runner: Runner | None, figure_processes: int) -> StudyRun:
    cells = study.cells()
    done, dropped = _resume(study, cells, out / "results.csv", log)
    todo = [c for c in cells if c.key not in done]
    typed: dict[str, list[dict]] = {}
    write_results(out, study, cells, done, typed)
    if progress is not None:
        progress(0, len(todo))
    runner = runner or LocalRunner(study.threads)
    for finished, (i, measured) in enumerate(runner.measure([cell_job(study, c) for c in todo]), start=1):
        done[todo[i].key] = csv_rows(todo[i], measured)
        write_results(out, study, cells, done, typed)  # canonical order, whatever order cells finish in
        if progress is not None:
            progress(finished, len(todo))
    rows = [r for c in cells for r in typed[c.key]]
    run = StudyRun(out, len(cells), len(cells) - len(todo), len(todo), dropped, rows)
    # Figures first, then the report that links them, then stale figures: a kill at any
    # point leaves a report whose every link resolves.
    run.figures, run.notes = figures(study, rows, out / "figures", figure_processes)
    outdir.write_text(out / "report.md", report(study, rows, run))
    remove_stale_figures(out / "figures", run.figures)
    return run


def _resume(study: Study, cells: list[Cell], results: Path,
            log: Callable[[str], None]) -> tuple[dict[str, list[list[str]]], int]:
    """The finished cells of an earlier ``results.csv`` (key → rows, verbatim) and how many cells were dropped."""
    previous, note = read_rows(results)
    if note:
        log(note)
    done = {c.key: previous[c.key] for c in cells if _finished(previous.get(c.key), c, study)}
    dropped = len(set(previous) - {c.key for c in cells})
    incomplete = sum(c.key in previous and c.key not in done for c in cells)
    if done:
        log(f"skipping {len(done)} of {len(cells)} cells already finished in {results}")
    if dropped:
        log(f"dropping the rows of {dropped} cell(s) no longer in the study (or changed)")
    if incomplete:
        log(f"recomputing {incomplete} cell(s) whose rows in {results} are incomplete or damaged")
    return done, dropped
