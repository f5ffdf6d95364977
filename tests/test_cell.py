"""The one measure-against-predict pipeline (warpis/runs/cell.py) that verify and study share:
its rules on constructed numbers, its row schema in both file formats, the trial floor,
and a cell whose estimator has no exact form.

Measured cells here are tiny: one receiver under a square light (closed-form reference),
N = 4 and a few dozen trials.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math

import numpy as np
import pytest
from conftest import write_scene
from scipy.special import ndtri

import warpis
from warpis.stats import variance_interval
from warpis.errors import WarpisError
from warpis.kernels.estimators import parse_estimator
from warpis.kernels.patterns import PATTERNS
from warpis.runs import cell, study, study_file, study_report, verify
from warpis.runs.cell import (INSIDE_SHARE, MIN_TRIALS, RATIO_TOLERANCE, Z95, RunCache, inside, measure_cell, summarize,
                              z_score)

TRIALS = 40


@pytest.fixture(scope="module")
def lamp_dir(tmp_path_factory):
    """A floor, a square light above it and one receiver below its centre."""
    d = tmp_path_factory.mktemp("lamp")
    write_scene(d)
    return d


@pytest.fixture(scope="module")
def lamp(lamp_dir):
    return warpis.load_scene(lamp_dir / "scene.toml")


# --------------------------------------------------------------------------- the rules


def test_z95_is_the_quantile_of_every_interval():
    """One Z95: the 97.5% normal quantile, the one stats.variance_interval widens by."""
    assert Z95 == float(ndtri(0.975)) == 1.959963984540054
    v = variance_interval(np.random.default_rng(1).exponential(size=(1, 200)))
    assert (v.hi[0] - v.variance[0]) / v.variance_stderr[0] == pytest.approx(Z95, rel=1e-12)


def test_inside_rule_on_constructed_values():
    """An equation is inside when |s² − V| ≤ Z95·√(se(s²)² + se(V)²), i.e. |z| ≤ Z95; with
    no spread on either side only an exact match; a bound when it is not below lo."""
    se, se_v = 0.3, 0.4  # √(se² + se_V²) = 0.5
    for offset, expected in ((0.0, True), (0.5 * 1.95, True), (-0.5 * 1.95, True), (0.5 * 1.97, False),
                             (-0.5 * 1.97, False)):
        z = z_score(1.0, se, 1.0 - offset, se_v)
        assert z == pytest.approx(offset / 0.5)
        assert inside("eq1", 1.0, 0.2, 1.0 - offset, z) is expected, offset
    assert z_score(1.0, 0.0, 1.0, 0.0) is None
    assert inside("eq1", 1.0, 1.0, 1.0, None) is True
    assert inside("eq1", 1.0, 1.0, 1.0 + 1e-12, None) is False
    assert z_score(1.0, 0.1, math.inf, 0.0) is None and inside("eq8", 1.0, 0.5, math.inf, None) is False
    # bounds: never scored by z, inside when lo ≤ V (an infinite bound always is)
    for bound in ("eq17", "eq20", "veach-bound"):
        assert cell.is_bound(bound)
        assert inside(bound, 1.0, 0.6, 0.6, None) is True
        assert inside(bound, 1.0, 0.6, 0.59, None) is False
        assert inside(bound, 1.0, 0.6, math.inf, None) is True
        assert inside(bound, 1.0, 0.6, 100.0, 50.0) is True  # a z would not matter


def _rows(form: str, ratios: list[float], inside_: list[bool]) -> list[dict]:
    """Plain rows (the schema summaries read) with measured variance 1 and V = 1/ratio."""
    return [{"variance": 1.0, "predictions": {"exact": 1.0, form: 1.0 / r if r else None},
             "inside": {"exact": True, form: i}} for r, i in zip(ratios, inside_)]


def test_holds_rule_on_constructed_rows():
    """An equation holds when ≥ 80% of its cells are inside and the median ratio is within
    10% of 1; a bound on every cell.  ``exact`` and zero-variance cells are not counted."""
    assert (INSIDE_SHARE, RATIO_TOLERANCE) == (0.8, 1.1)

    def verdict(rows: list[dict]) -> cell.FormSummary:
        (s,) = [s for s in summarize(rows) if s.form != "exact"]
        return s

    assert verdict(_rows("eq1", [1.05] * 10, [True] * 8 + [False] * 2)).holds
    assert not verdict(_rows("eq1", [1.05] * 10, [True] * 7 + [False] * 3)).holds
    assert not verdict(_rows("eq1", [1.12] * 10, [True] * 10)).holds
    assert verdict(_rows("eq1", [0.92] * 10, [True] * 10)).holds
    assert not verdict(_rows("eq1", [0.9] * 10, [True] * 10)).holds
    bound = verdict(_rows("eq20", [0.3] * 5, [True] * 5))
    assert bound.bound and bound.holds and bound.median_ratio == pytest.approx(0.3)
    assert not verdict(_rows("eq20", [0.3] * 5, [True] * 4 + [False])).holds
    infinite = verdict(_rows("eq17", [0.0] * 3, [True] * 3))  # V = ∞ (null): ratio 0, holds as a bound
    assert infinite.holds and infinite.median_ratio == 0.0
    umbra = _rows("eq1", [1.0] * 4, [True] * 4) + [{"variance": 0.0, "predictions": {"eq1": 0.0},
                                                     "inside": {"eq1": False}}]
    assert verdict(umbra).cells == 4 and verdict(umbra).holds
    assert "exact" not in {s.form for s in summarize(_rows("eq1", [1.0], [True]))}
    # study's summary.json and verify's lines read the same verdicts
    rows = _rows("eq1", [1.05] * 10, [True] * 7 + [False] * 3)
    assert study_report.form_summaries(rows)[0]["holds"] is False
    assert "FAILS" in verify.summary_lines(rows)[0]


def test_one_trial_floor_everywhere(lamp, lamp_dir, cli):
    """MIN_TRIALS (4) is the floor of the pipeline, verify, study and estimate alike."""
    assert MIN_TRIALS == 4 and cell.MIN_TRIALS is MIN_TRIALS
    est = parse_estimator("independent:single:light-area")
    with pytest.raises(WarpisError, match="trials must be at least 4"):
        measure_cell(lamp, [0], est, 4, 3, 0, RunCache())
    with pytest.raises(WarpisError, match="--trials must be at least 4 to give a variance interval"):
        verify.verify(lamp, estimators=[est], n_values=[4], trials=3)
    with pytest.raises(WarpisError, match="trials must be at least 4"):
        study_file.study_from_dict({"name": "t", "trials": 3, "n": [4], "scenes": ["scene.toml"],
                               "estimators": [est.spec]}, "t.toml", lamp_dir)
    result = cli("estimate", lamp_dir / "scene.toml", "--estimator", est.spec, "--n", "4", "--trials", "3")
    assert result.status == 2 and "--trials must be at least 4" in result.err
    rows = measure_cell(lamp, [0], est, 4, MIN_TRIALS, 0, RunCache(), predict=False).rows
    assert len(rows) == 1 and rows[0].trials == MIN_TRIALS and rows[0].predictions == {}


# --------------------------------------------------------------------------- one schema


def test_a_measured_row_reads_the_same_in_verify_json_and_results_csv(lamp):
    """The row measure_cell gives becomes a verify.json row and a results.csv row; read back,
    the CSV row holds the same numbers, predictions, z and inside verdicts (inside judged
    again from z must agree with inside judged when measured)."""
    cache = RunCache()
    est = parse_estimator("independent:balance:light-area+cosine")
    (row,) = measure_cell(lamp, [0], est, 4, TRIALS, 7, cache).rows
    assert {"eq6", "eq7-exact", "veach-bound", "exact"} <= set(row.predictions)
    assert set(row.predictions) | set(row.reasons) == set(study_file.FORMS)
    assert set(row.inside) == set(row.predictions) and set(row.z) == set(row.predictions) - set(study_file.BOUND_FORMS)

    plain = row.as_dict()
    json_row = verify.json_row(row)
    assert list(json_row) == ["receiver", "estimator", "n", "mean", "mean_stderr", "reference", "reference_stderr",
                              "variance", "variance_stderr", "variance_ci", "predictions", "prediction_rel_error",
                              "inside", "z", "absent"]
    assert all(json_row[k] == plain[k] for k in json_row if k not in ("prediction_rel_error", "absent"))
    assert json_row["absent"] == {}  # a built-in estimator lacks no form in its scope
    json.dumps(json_row, allow_nan=False)

    typed = study.typed_row(study.csv_row(row) + ["0.1", warpis.__version__, "0123456789abcdef"])
    for key, value in plain.items():
        assert typed[key] == value, key

    # the cache keeps one reference per scene and one moments set per receiver × technique set
    measure_cell(lamp, [0], parse_estimator("jittered:balance:light-area+cosine"), 4, TRIALS, 7, cache)
    assert len(cache.references) == 1 and len(cache.moments) == 1


def test_each_receiver_runs_side_by_side_and_keeps_the_order():
    """Two receivers at once (each waits for the other at a barrier: one at a time would time
    out), results in the receivers' order whatever order they finish in, an error raised in
    the caller, and one thread means one receiver after another."""
    import threading
    import time

    meet = threading.Barrier(2, timeout=30)

    def work(r: int) -> int:
        if r < 2:
            meet.wait()
        time.sleep(0.05 * (3 - r))  # later receivers finish first
        return r * r

    assert cell.each_receiver(work, [0, 1, 2, 3], threads=2) == [0, 1, 4, 9]
    order = []
    assert cell.each_receiver(lambda r: order.append(r) or -r, [3, 1, 2], threads=1) == [-3, -1, -2]
    assert order == [3, 1, 2]

    def fails(r: int) -> int:
        raise WarpisError(f"receiver {r}: bad")

    with pytest.raises(WarpisError, match="receiver 0: bad"):
        cell.each_receiver(fails, [0, 1], threads=2)


def test_receivers_scored_side_by_side_get_their_own_predictions():
    """A cell's receivers, scored two at a time, each carry the predictions of their own
    moments: as theory.predictions gives them one receiver at a time, and as a one-thread
    run scores them."""
    from warpis.analysis.quadrature import moments
    from warpis.analysis.theory import predictions

    scene = warpis.load_scene("occluded-quad")
    est = parse_estimator("jittered:balance:light-area+cosine")
    rx = [5, 0, 3, 1]  # penumbra, lit, umbra, brightest: four different predictions
    both = measure_cell(scene, rx, est, 4, TRIALS, 7, RunCache(), threads=2).rows
    one = measure_cell(scene, rx, est, 4, TRIALS, 7, RunCache(), threads=1).rows
    assert [row.receiver for row in both] == rx
    for a, b in zip(both, one):
        assert dataclasses.replace(a, seconds_per_estimate=None) == dataclasses.replace(b, seconds_per_estimate=None)
        alone = predictions(scene, a.receiver, est, 4, mom=moments(scene, a.receiver, est.techniques))
        assert a.predictions == dict(alone) and a.reasons == dict(alone.reasons)
    assert len({row.predictions["exact"].value for row in both}) == len(rx)


def test_biased_rows_carry_eq18_and_the_bias(lamp):
    (row,) = measure_cell(lamp, [0], parse_estimator("independent:biased:cosine"), 4, TRIALS, 1, RunCache()).rows
    out = verify.json_row(row)
    assert set(out["mean_predictions"]) == set(out["mean_inside"]) == {"eq18"}
    assert out["bias"] == pytest.approx(row.mean - row.reference)


# --------------------------------------------------------------------------- no exact form


def test_an_estimator_without_exact_form_gives_reasons_in_verify_and_study(lamp, lamp_dir, tmp_path, monkeypatch):
    """Antithetic registered without its block decomposition (the kernel still runs it):
    the cell has no ``exact``/``antithetic-exact``, each with its reason, and verify and
    study write the cell with those predictions absent instead of failing."""
    monkeypatch.setitem(PATTERNS, "antithetic", dataclasses.replace(PATTERNS["antithetic"], blocks=None))
    spec = "antithetic:single:light-area"
    missing = {"exact", "antithetic-exact"}

    (row,) = measure_cell(lamp, [0], parse_estimator(spec), 4, TRIALS, 0, RunCache()).rows
    assert not missing & set(row.predictions) and not missing & set(row.inside)
    assert all("no block decomposition" in row.reasons[f] for f in missing)
    assert math.isfinite(row.variance)

    result = verify.verify(lamp, estimators=[spec], n_values=[4], trials=TRIALS, receivers=[0])
    (vrow,) = result.rows
    assert not missing & (set(vrow["predictions"]) | set(vrow["inside"]) | set(vrow["z"]))
    assert vrow["variance"] == row.variance

    s = study_file.study_from_dict({"name": "no-exact", "trials": TRIALS, "n": [4], "scenes": ["scene.toml"],
                               "estimators": [spec], "outputs": []}, "no-exact.toml", lamp_dir)
    run = study.run_study(s, tmp_path / "out")
    (srow,) = run.rows
    assert not missing & set(srow["predictions"]) and srow["variance"] == row.variance
    with open(tmp_path / "out" / "results.csv", newline="") as fh:
        header, line = list(csv.reader(fh))
    assert all(line[header.index(f"pred_{f}")] == "" for f in missing)
    forms = {f["form"] for f in json.loads((tmp_path / "out" / "summary.json").read_text())["forms"]}
    assert not missing & forms
