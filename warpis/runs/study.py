"""Studies: a TOML file of scenes × estimators × N, run cell by cell into files that survive a kill.

A study file holds one ``[study]`` table (README.md, "Studies", gives the format).  A
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
import hashlib
import io
import json
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import limits
from ..analysis.stats import fit_slope
from ..analysis.theory import BOUNDS, missing_forms
from ..errors import WarpisError
from ..kernels.estimators import Estimator, parse_estimator
from ..kernels.integrand import MATERIALS
from ..scenes import Scene, load_scene, read_toml, resolve_scene_path
from ..vocabulary import expected_slope as registry_slope
from . import outdir
from .cell import MIN_TRIALS, CellJob, LocalRunner, MeasuredCell, Row, Runner, inside, summarize

STUDY_KEYS = ("name", "description", "seed", "trials", "n", "scenes", "estimators", "receivers", "predictions",
              "outputs", "threads")
OUTPUTS = ("convergence", "maps", "calibration")
# Every prediction form of theory.FORMS, in the order of the CSV's columns (a file format:
# a new form gets its column here; tests/test_vocabulary.py checks that none is missing).
FORMS = ("exact", "eq1", "eq6", "eq7-printed", "eq7-exact", "eq8", "eq10-printed", "eq10-exact", "eq14-printed",
         "eq14-exact", "eq17", "eq19", "eq20", "power-exact", "mixture-exact", "antithetic-exact",
         "jittered-antithetic-exact", "veach-bound", "optimal-ab")
BOUND_FORMS = BOUNDS
Z_FORMS = tuple(f for f in FORMS if f not in BOUND_FORMS)
HEADER = (["scene", "receiver", "estimator", "n", "trials", "seed", "mean", "mean_stderr", "reference",
           "reference_stderr", "variance", "variance_stderr", "variance_lo", "variance_hi"]
          + [f"pred_{f}" for f in FORMS] + [f"z_{f}" for f in Z_FORMS]
          + ["seconds_per_estimate", "efficiency", "seconds", "warpis_version", "cell"])
# Bytes per trial estimate while a cell runs: the float64 result and about three
# float64 temporaries of the same size in stats.variance_interval.
TRIAL_BYTES = 32
# Convergence figures per scene: the first receivers of the study's list for that scene.
MAX_CONVERGENCE_RECEIVERS = 8
# Rows beyond which report.md lists no cells (results.csv holds them).
MAX_REPORT_ROWS = 2000
# Most camera pixels a study predicts at (each receiver's forms cost seconds).
MAX_PREDICTED_PIXELS = 64

# The built-in study of ``warpis demo`` (scripts/studies/demo.toml is the same study as a file).
DEMO_ESTIMATORS = {
    "random": "independent:single:uniform",
    "jittered": "jittered:single:uniform",
    "light IS": "independent:single:light-area",
    "cosine IS": "independent:single:cosine",
    "jittered IS": "jittered:single:light-area",
    "MIS": "independent:balance:light-area+cosine",
    "jittered MIS": "jittered:balance:light-area+cosine",
    "antithetic": "antithetic:single:light-area",
    "jittered antithetic": "jittered-antithetic:single:light-area",
    "biased IS": "independent:biased:cosine",
}
DEMO = {
    "name": "demo",
    "description": "Ten estimators of direct illumination on occluded-quad: lit, penumbra and umbra receivers.",
    "seed": 1,
    "trials": 20000,
    "n": [4, 16, 64, 256],
    "scenes": ["occluded-quad"],
    "estimators": dict(DEMO_ESTIMATORS),
}


def _version() -> str:
    from .. import __version__

    return __version__


# --------------------------------------------------------------------------- the study


@dataclass
class StudyScene:
    """One scene of a study: as written, loaded, its receivers and its content digest."""

    source: str
    scene: Scene
    receivers: list[int]
    digest: str

    @property
    def name(self) -> str:
        return self.scene.name


@dataclass(frozen=True)
class Cell:
    """scene × estimator × N, over the study's receivers of that scene."""

    scene: StudyScene
    estimator: Estimator
    n: int
    key: str


@dataclass
class Study:
    """A validated study: everything checked and every scene loaded."""

    name: str
    seed: int
    trials: int
    n: list[int]
    scenes: list[StudyScene]
    estimators: list[Estimator]
    predictions: bool = True
    outputs: tuple[str, ...] = OUTPUTS
    threads: int | None = None
    description: str = ""
    source: str = ""  # the study file, or a word for a built-in study
    labels: dict[str, str] = field(default_factory=dict)  # spec → the name the study gives it (figures, report)

    def label(self, est: Estimator) -> str:
        """``name (spec)`` for a named estimator, else its spec."""
        name = self.labels.get(est.spec, est.spec)
        return est.spec if name == est.spec else f"{name} ({est.spec})"

    def cells(self) -> list[Cell]:
        """Every cell, in the canonical order: scenes, then estimators, then N, as listed."""
        return [Cell(s, e, n, cell_key(self, s, e, n)) for s in self.scenes for e in self.estimators for n in self.n]


def cell_key(study: Study, scene: StudyScene, est: Estimator, n: int) -> str:
    """The hash that says whether a finished cell can be reused."""
    data = {"scene": scene.digest, "scene_name": scene.name, "estimator": est.spec, "n": int(n),
            "trials": study.trials, "seed": study.seed, "receivers": scene.receivers,
            "predictions": study.predictions, "warpis": _version()}
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:16]


def scene_digest(scene: Scene) -> str:
    """The scene's content digest (:attr:`Scene.digest`: its arrays, not its files), so
    two files with the same content share cells and a moved file keeps its results."""
    return scene.digest


def load_study(path: str | Path, threads: int | None = None) -> Study:
    """Read and validate a study file; every scene is loaded.  One-line WarpisError naming the file."""
    file = Path(path)
    doc = read_toml(file)
    unknown = sorted(set(doc) - {"study"})
    if unknown:
        raise WarpisError(f"{file}: unknown key {unknown[0]!r} at the top level (a study file holds one [study] table)")
    if not isinstance(doc.get("study"), dict):
        raise WarpisError(f"{file}: missing [study] table")
    return study_from_dict(doc["study"], str(file), file.parent, threads=threads)


def study_from_dict(table: dict[str, Any], where: str, base: Path | None, threads: int | None = None) -> Study:
    """Validate a ``[study]`` table; ``where`` names it in errors, scene paths are relative to ``base``.

    Nothing is run: every check (keys, types, estimators, every estimator × N, trials,
    receivers) is made and every scene loaded, so a study that passes runs to the end.
    """
    def bad(problem: str) -> WarpisError:
        return WarpisError(f"{where}: {problem}")

    unknown = sorted(set(table) - set(STUDY_KEYS))
    if unknown:
        raise bad(f"unknown key {unknown[0]!r} in [study] (allowed: {', '.join(STUDY_KEYS)})")
    for key in ("name", "trials", "n", "scenes", "estimators"):
        if key not in table:
            raise bad(f"missing key {key!r} in [study]")

    name = table["name"]
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", name):
        raise bad(f"name must be a word of letters, digits, '.', '_' or '-' (it names the output folder), got {name!r}")
    description = table.get("description", "")
    if not isinstance(description, str):
        raise bad("description must be a string")
    seed = limits.seed(table.get("seed", 0), f"{where}: seed")
    trials = _integer(table["trials"], "trials", bad)
    if trials < MIN_TRIALS:  # said with its reason; limits.count below bounds it above
        raise bad(f"trials must be at least {MIN_TRIALS} to give a variance interval, got {trials}")
    trials = limits.count(trials, f"{where}: trials", minimum=MIN_TRIALS)
    n_values = _count_list(table["n"], "n", where, bad)

    named = table["estimators"]
    if isinstance(named, dict):  # label → spec, in the file's order
        if not named or not all(isinstance(v, str) for v in named.values()):
            raise bad(f"estimators must be a non-empty list of specs or a table label → spec, got {named!r}")
        specs, names = list(named.values()), list(named)
    else:
        specs = _string_list(named, "estimators", bad)
        names = [None] * len(specs)
    estimators = []
    for spec in specs:
        try:
            estimators.append(parse_estimator(spec))
        except WarpisError as exc:
            raise bad(f"estimators: {exc}") from None
    _no_duplicates([e.spec for e in estimators], "estimators", bad)
    labels = {e.spec: name or e.spec for e, name in zip(estimators, names)}
    for est in estimators:
        for n in n_values:
            try:
                est.check_n(n)
            except WarpisError as exc:
                raise bad(f"n: {exc}") from None

    predictions = table.get("predictions", True)
    if not isinstance(predictions, bool):
        raise bad(f"predictions must be true or false, got {predictions!r}")
    outputs = table.get("outputs", list(OUTPUTS))
    outputs = _string_list(outputs, "outputs", bad, empty=True)
    for o in outputs:
        if o not in OUTPUTS:
            raise bad(f"unknown output {o!r} (valid: {', '.join(OUTPUTS)})")
    file_threads = table.get("threads")
    if file_threads is not None:
        file_threads = limits.count(file_threads, f"{where}: threads")

    sources = _string_list(table["scenes"], "scenes", bad)
    _no_duplicates(sources, "scenes", bad)
    receivers = table.get("receivers")
    if receivers is not None and not isinstance(receivers, (list, dict)):
        raise bad("receivers must be a list of indices (for every scene) or a table scene → list")
    if isinstance(receivers, dict):
        for key in receivers:
            if key not in sources:
                raise bad(f"receivers: {key!r} is not one of the study's scenes ({', '.join(sources)})")

    scenes: list[StudyScene] = []
    for source in sources:
        scene = _load_scene(source, base, bad)
        chosen = receivers.get(source) if isinstance(receivers, dict) else receivers
        if chosen is None:
            idx = list(range(len(scene.receivers)))
        else:
            what = f"receivers of {source!r}" if isinstance(receivers, dict) else "receivers"
            if not isinstance(chosen, list):
                raise bad(f"{what} must be a non-empty list of integers, got {chosen!r}")
            idx = [int(i) for i in limits.receiver_indices(chosen, f"{where}: {what}", len(scene.receivers))]
            _no_duplicates(idx, what, bad)
        if any(s.name == scene.name for s in scenes):
            raise bad(f"two scenes are named {scene.name!r}; rows could not tell them apart")
        if predictions and scene.receivers.image is not None and len(idx) > MAX_PREDICTED_PIXELS:
            raise bad(f"scene {source!r}: predictions at {len(idx)} camera pixels would take hours (each receiver's "
                      f"forms need about 10^6 dense points); choose at most {MAX_PREDICTED_PIXELS} with receivers, "
                      f"set predictions = false, or use `warpis image`, which predicts every pixel's exact variance")
        scenes.append(StudyScene(source, scene, idx, scene_digest(scene)))
    # A cell's (receivers × trials) float64 estimates and the few same-sized temporaries of
    # variance_interval must fit, or the run would die after writing its first files.
    limits.memory(TRIAL_BYTES * trials * max(len(s.receivers) for s in scenes), f"{where}: trials")

    return Study(name=name, seed=seed, trials=trials, n=n_values, scenes=scenes, estimators=estimators,
                 predictions=predictions, outputs=tuple(o for o in OUTPUTS if o in outputs),
                 threads=threads or file_threads, description=description, source=where, labels=labels)


def demo_study(threads: int | None = None) -> Study:
    """The built-in study of ``warpis demo``."""
    return study_from_dict(DEMO, "demo", None, threads=threads)


def _load_scene(source: str, base: Path | None, bad) -> Scene:
    """A path relative to the study file (``base``), else a bundled name (only that for a
    built-in study, ``base`` None) → the loaded scene."""
    try:
        return load_scene(resolve_scene_path(source, base))
    except WarpisError as exc:
        raise bad(f"scene {source!r}: {exc}") from None


def _integer(value: Any, what: str, bad) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise bad(f"{what} must be an integer, got {value!r}")
    return value


def _count_list(value: Any, what: str, where: str, bad) -> list[int]:
    """A non-empty list of distinct counts, each one a count the kernels can hold."""
    if not isinstance(value, list) or not value:
        raise bad(f"{what} must be a non-empty list of integers, got {value!r}")
    out = [limits.count(v, f"{where}: {what}") for v in value]
    _no_duplicates(out, what, bad)
    return out


def _string_list(value: Any, what: str, bad, empty: bool = False) -> list[str]:
    if not isinstance(value, list) or (not value and not empty) or not all(isinstance(v, str) for v in value):
        raise bad(f"{what} must be a {'' if empty else 'non-empty '}list of strings, got {value!r}")
    return list(value)


def _no_duplicates(values: list, what: str, bad) -> None:
    seen = set()
    for v in values:
        if v in seen:
            raise bad(f"{what} lists {v!r} twice")
        seen.add(v)


def default_out(study: Study) -> Path:
    """``./warpis-out/<name>/``."""
    return Path("warpis-out") / study.name


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
    return [csv_row(row) + [seconds, _version(), cell.key] for row in measured.rows]


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
        "study": study.name, "description": study.description, "warpis_version": _version(),
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


# --------------------------------------------------------------------------- running


@dataclass
class StudyRun:
    """What a run did and wrote."""

    out: Path
    cells: int
    skipped: int
    computed: int
    dropped: int
    rows: list[dict] = field(default_factory=list)
    figures: list[Path] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def run_study(study: Study, out: Path, progress: Callable[[int, int], None] | None = None,
              log: Callable[[str], None] | None = None, runner: Runner | None = None) -> StudyRun:
    """Run every unfinished cell of ``study`` into ``out``; then figures and report.md.

    ``progress(done, total)`` counts the cells this run computes; ``log`` receives one-line
    notes (cells skipped, rows dropped, damaged rows) as they happen.  The folder is locked
    for the whole run (:func:`warpis.runs.outdir.locked`): a second run on it fails at once,
    so no run ever rewrites results.csv without rows the other one finished.  A file that
    cannot be written is a one-line WarpisError; the files already there stay intact.
    ``runner`` measures the cells (default: :class:`~warpis.runs.cell.LocalRunner`; a
    Dask cluster: :func:`warpis.runs.cluster.connect`); the files do not depend on it.
    """
    with outdir.locked(Path(out)) as out:
        return _run_locked(study, out, progress, log or (lambda line: None), runner)


def _run_locked(study: Study, out: Path, progress: Callable[[int, int], None] | None,
                log: Callable[[str], None], runner: Runner | None) -> StudyRun:
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
    run.figures, run.notes = figures(study, rows, out / "figures")
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


# --------------------------------------------------------------------------- figures and report

FIGURE_PREFIXES = ("convergence-", "variance-map-", "variance-ratio-", "slope-map-", "calibration.")


def _index(rows: list[dict]) -> dict[tuple, dict]:
    return {(r["scene"], r["receiver"], r["estimator"], r["n"]): r for r in rows}


def figures(study: Study, rows: list[dict], fig_dir: Path) -> tuple[list[Path], list[str]]:
    """Every figure the study's ``outputs`` ask for (PNG and PDF) → (paths, notes for the report)."""
    from .. import plots

    paths: list[Path] = []
    notes: list[str] = []
    if not study.outputs:
        return paths, notes
    at = _index(rows)
    fits = {(f["scene"], f["receiver"], f["estimator"]): f for f in slopes(rows, study)}
    for s in study.scenes:
        slug = plots._slug(s.name)
        if "convergence" in study.outputs:
            if s.scene.receivers.image is not None:
                picked = representative_pixels(s, rows)
                shown = [r for _, r in picked]
                notes.append(f"{s.name}: convergence figures for representative pixels: "
                             + "; ".join(f"{what}: receiver {r} (pixel row {p // w}, column {p % w})"
                                         for what, r in picked
                                         for p, w in [(int(s.scene.receivers.image.pixel[r]),
                                                       s.scene.receivers.image.camera.width)]))
            else:
                shown = s.receivers[:MAX_CONVERGENCE_RECEIVERS]
                if len(s.receivers) > len(shown):
                    notes.append(f"{s.name}: convergence figures for the first {len(shown)} of its "
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
                made = plots.slope_convergence_plot(
                    series, f"{s.name}, receiver {r}: variance against N, {study.trials} trials per point"
                    + (" (dashed: exact prediction)" if study.predictions else ""),
                    fig_dir, f"convergence-{slug}-r{r}")
                if not made and series:
                    notes.append(f"{s.name}, receiver {r}: zero variance under every estimator; no convergence figure")
                paths += made
        to_map = _mapper(s)
        if "maps" in study.outputs and to_map is not None:
            origin = "upper" if s.scene.receivers.image is not None else "lower"
            what = "the camera's pixels" if origin == "upper" else "the receiver grid"
            grids = {(est.spec, n): to_map({r: at[s.name, r, est.spec, n]["variance"] for r in s.receivers
                                            if (s.name, r, est.spec, n) in at})
                     for est in study.estimators for n in study.n}
            for n in sorted(study.n):
                paths += plots.variance_map_plot(
                    [(study.label(est), grids[est.spec, n]) for est in study.estimators],
                    f"{s.name}: variance over {what}, N = {n} (shared log scale)",
                    fig_dir, f"variance-map-{slug}-n{n}", origin)
            if len(study.estimators) >= 2:
                ea, eb = study.estimators[0], study.estimators[1]
                a, b = ea.spec, eb.spec
                with np.errstate(all="ignore"):
                    ratio = [(f"N = {n}", grids[a, n] / grids[b, n]) for n in sorted(study.n)]
                paths += plots.ratio_map_plot(ratio, f"{s.name}: variance of {study.label(ea)} / variance of "
                                                     f"{study.label(eb)}", fig_dir, f"variance-ratio-{slug}", origin)
            if origin == "upper" and len(study.n) >= 2:
                slope_maps = [(study.label(est), to_map({r: f["slope"] for r in s.receivers
                                                         if (f := fits.get((s.name, r, est.spec))) is not None
                                                         and f["slope"] is not None}))
                              for est in study.estimators]
                paths += plots.slope_map_plot(slope_maps, f"{s.name}: convergence slope per pixel over N = "
                                                          f"{', '.join(map(str, sorted(study.n)))}", fig_dir,
                                              f"slope-map-{slug}")
    if "calibration" in study.outputs and study.predictions:
        paths += plots.calibration_plot(rows, fig_dir, stem="calibration")
    return paths, notes


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
        f"{seconds:.0f} s of cell time as recorded in `results.csv`, warpis {_version()}.",
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
