"""The study file: one ``[study]`` table of scenes × estimators × N, read into a ``Study``.

docs/studies.md gives the format.  Every key is checked where it is read, and a bad one
is a one-line error naming the file and the key; nothing runs before the whole file is
read.  ``demo_study`` is the study ``warpis demo`` runs.
"""
from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .. import limits
from ..analysis.theory import BOUNDS
from ..errors import WarpisError
from ..kernels.estimators import Estimator, parse_estimator
from ..scenes import Scene, load_scene, read_toml, resolve_scene_path
from ..version import __version__
from .cell import MIN_TRIALS


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
# The columns of HEADER measured with a clock: the only ones a rerun of a cell may change.
TIMING_COLUMNS = ("seconds", "seconds_per_estimate", "efficiency")
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
    "trials": 5000,
    "n": [4, 16, 64, 256],
    "scenes": ["occluded-quad"],
    "estimators": dict(DEMO_ESTIMATORS),
}


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
            "predictions": study.predictions, "warpis": __version__}
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
