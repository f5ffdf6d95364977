"""A pattern written by a user as a Warp point function, registered from Python or by ``--plugin``.

The user's pattern is a randomly shifted rank-1 lattice: point i of m is
frac((i/m, i/φ) + Δ) with one uniform shift Δ per technique and trial.  Each point is
uniform on [0,1)², so every unbiased combiner stays unbiased; the points are spread far
more evenly than independent ones, so on a smooth integrand the variance drops.

*Unbiasedness.*  The mean of 4000 trials at N = 16 on the lit, unoccluded receiver 0 of
occluded-quad against its closed-form reference, z = (mean − F)/se, at the two-sided
Bonferroni threshold Φ⁻¹(1 − 1e-3/4) ≈ 3.48 over the two estimators: false-failure
probability ≤ 1e-3 under the normal approximation of the mean.

*It is the user's points that run.*  At N = 64 with light-area sampling (a smooth
integrand at that receiver) the lattice's variance is about 16× below independent
sampling's (1.8e-5 against 3.0e-4 at 2000 trials).  The test asks only that the upper
end of the lattice's 99.9% interval lies below the lower end of independent's: with a
true ratio of 16 a chance failure needs both fourth-moment intervals to miss by a factor
of 4, far beyond their 1e-3 miss rate.  A dispatch that fell back to the built-in
``independent`` branch would fail it.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import warp as wp
from conftest import one_error_line, run_warpis
from scipy.stats import norm

import warpis
from warpis.analysis.reference import reference
from warpis.analysis.theory import predictions
from warpis.kernels import estimators, patterns, registered
from warpis.kernels.estimators import parse_estimator
from warpis.kernels.patterns import PATTERNS

NAME = "test-lattice"
BUILT_IN = set(PATTERNS)  # before any test registers one
GOLDEN = 0.6180339887498949


@wp.func
def lattice_point(s: wp.uint32, i: wp.int32, m: wp.int32) -> wp.vec2:
    x = float(i) / float(m) + warpis.uniform(s, 0, 0)
    y = float(i) * 0.6180339887 + warpis.uniform(s, 0, 1)
    return wp.vec2(wp.min(x - wp.floor(x), 0.99999994), wp.min(y - wp.floor(y), 0.99999994))


@wp.func
def outside_point(s: wp.uint32, i: wp.int32, m: wp.int32) -> wp.vec2:
    """Wrong: the last point of every trial lands on the square's edge u = 1."""
    if i == m - 1:
        return wp.vec2(1.0, 0.5)
    return wp.vec2(warpis.uniform(s, i, 0), warpis.uniform(s, i, 1))


@pytest.fixture
def lattice():
    entry = warpis.register_pattern(NAME, lattice_point, description="randomly shifted rank-1 lattice")
    try:
        yield entry
    finally:
        warpis.unregister_pattern(NAME)


@pytest.fixture(scope="module")
def quad():
    return warpis.load_scene("occluded-quad")


def test_registration_adds_an_entry_without_theory(lattice):
    assert PATTERNS[NAME] is lattice
    assert lattice.code == max(e.code for e in PATTERNS.values())
    assert lattice.blocks is None and lattice.slope is None and not lattice.paired
    assert parse_estimator(f"{NAME}:balance:light-area+cosine").pattern_entry is lattice


@pytest.mark.parametrize("spec", [f"{NAME}:single:light-area", f"{NAME}:balance:light-area+cosine"])
def test_user_pattern_is_unbiased(lattice, quad, spec):
    ref = reference(quad, receivers=[0])[0]
    values = warpis.run_trials(quad, spec, 16, 4000, seed=5, receivers=[0])[0]
    z = (values.mean() - ref.value) / math.hypot(values.std(ddof=1) / math.sqrt(len(values)), ref.stderr)
    assert values.std() > 0.0
    assert abs(z) < norm.ppf(1 - 1e-3 / 4), f"{spec}: mean {values.mean():.6g} reference {ref.value:.6g} z = {z:.2f}"


def test_the_users_points_are_the_ones_that_run(lattice, quad):
    z999 = float(norm.ppf(1 - 1e-3 / 2))
    lat = warpis.variance_interval(warpis.run_trials(quad, f"{NAME}:single:light-area", 64, 2000, seed=1,
                                                     receivers=[0])[0], level=0.999)
    iid = warpis.variance_interval(warpis.run_trials(quad, "independent:single:light-area", 64, 2000, seed=1,
                                                     receivers=[0])[0], level=0.999)
    assert lat.variance + z999 * lat.variance_stderr < iid.variance - z999 * iid.variance_stderr, (lat, iid)


def test_trials_are_deterministic_and_differ_from_the_built_in_patterns(lattice, quad):
    a = warpis.run_trials(quad, f"{NAME}:single:cosine", 16, 64, seed=3, receivers=[0])
    b = warpis.run_trials(quad, f"{NAME}:single:cosine", 16, 64, seed=3, receivers=[0])
    np.testing.assert_array_equal(a, b)
    for builtin in ("independent", "jittered"):
        c = warpis.run_trials(quad, f"{builtin}:single:cosine", 16, 64, seed=3, receivers=[0])
        assert not np.array_equal(a, c)


def test_theory_says_why_it_has_no_exact_form(lattice, quad):
    pred = predictions(quad, 0, f"{NAME}:balance:light-area+cosine", 16)
    assert "exact" not in pred and "no block decomposition" in pred.reasons["exact"]
    assert pred.reasons["eq7-exact"].startswith("applies only to independent")
    assert "veach-bound" in pred.reasons


def test_a_paired_user_pattern_refuses_odd_n(quad):
    warpis.register_pattern(NAME, lattice_point, paired=True)
    try:
        with pytest.raises(warpis.WarpisError, match="even number"):
            parse_estimator(f"{NAME}:single:cosine").check_n(5)
        parse_estimator(f"{NAME}:single:cosine").check_n(6)
    finally:
        warpis.unregister_pattern(NAME)


def test_a_point_outside_the_square_is_refused_at_registration():
    with pytest.raises(warpis.WarpisError, match=r"point 0 of m = 1 is \(1\.0, 0\.5\), outside"):
        warpis.register_pattern(NAME, outside_point)
    assert NAME not in PATTERNS


@pytest.mark.parametrize("name, point, problem", [
    ("jittered", lattice_point, "already registered"),
    ("a:b", lattice_point, "without ':'"),
    ("", lattice_point, "non-empty"),
    (NAME, lambda s, i, m: None, "@wp.func"),
])
def test_bad_registrations_are_one_line_errors(name, point, problem):
    with pytest.raises(warpis.WarpisError, match=problem):
        warpis.register_pattern(name, point)
    assert set(PATTERNS) == BUILT_IN


def test_unregistering_an_unknown_pattern_fails():
    with pytest.raises(warpis.WarpisError, match="was not added"):
        warpis.unregister_pattern("jittered")


def test_without_user_patterns_the_built_in_kernel_runs(lattice):
    """A user pattern rebuilds the trial and pilot kernels only: the sample, pdf and
    evaluate kernels know techniques, not patterns, and stay built in."""
    kernels = registered.registered_kernels()
    assert kernels.trial is not estimators.trial_kernel and kernels.pilot.module is kernels.trial.module
    assert (kernels.sample, kernels.pdf, kernels.evaluate) == (registered.BUILT_IN.sample, registered.BUILT_IN.pdf,
                                                               registered.BUILT_IN.evaluate)
    warpis.unregister_pattern(NAME)
    try:
        assert patterns.user_patterns() == ()
        assert registered.registered_kernels() is registered.BUILT_IN
    finally:
        warpis.register_pattern(NAME, lattice_point)


# --------------------------------------------------------------------------- --plugin

PLUGIN = '''
import warp as wp
import warpis

@wp.func
def hammersley_point(s: wp.uint32, i: wp.int32, m: wp.int32) -> wp.vec2:
    # (i/m, the base-2 radical inverse of i), shifted by one random vector per trial
    r = float(0.0)
    f = float(0.5)
    n = i
    while n > 0:
        if n % 2 == 1:
            r = r + f
        n = n / 2
        f = f * 0.5
    x = float(i) / float(m) + warpis.uniform(s, 0, 0)
    y = r + warpis.uniform(s, 0, 1)
    return wp.vec2(wp.min(x - wp.floor(x), 0.99999994), wp.min(y - wp.floor(y), 0.99999994))

warpis.register_pattern("hammersley", hammersley_point, description="a randomly shifted Hammersley set")
'''


def test_a_plugin_pattern_runs_in_estimate_and_is_listed_in_help(tmp_path):
    (tmp_path / "hammersley.py").write_text(PLUGIN)
    plugin = str(tmp_path / "hammersley.py")
    result = run_warpis("estimate", "occluded-quad", "--plugin", plugin, "--estimator", "hammersley:single:light-area",
                        "--n", "16", "--trials", "200", "--receivers", "0", "--json")
    assert result.status == 0, result.err
    row = json.loads(result.out)["receivers"][0]
    assert abs(row["mean"] - 0.5235598) < 5 * row["stderr"] + 1e-6
    help_text = run_warpis("--plugin", plugin, "estimate", "--help")
    assert "a randomly shifted Hammersley set" in help_text.out


@pytest.mark.parametrize("body, problem", [
    (None, "no such file"),
    ("<dir>", "is a directory, not a Python file"),
    ("raise RuntimeError('broken\\nsecond line')", "RuntimeError: broken"),
    ("import warpis\nwarpis.register_pattern('jittered', None)", "point must be a @wp.func"),
    ("def (:", "SyntaxError"),
    ("import sys\nsys.exit(3)", "SystemExit: 3"),
])
def test_a_bad_plugin_is_one_line_and_exit_2(cli, tmp_path, body, problem):
    """In this process (the command's own handling), but for the plugin that exits, which
    runs in a process of its own: there the exit would end the process, not a test."""
    path = tmp_path / "plugin.py"
    if body == "<dir>":
        path.mkdir()
    elif body is not None:
        path.write_text(body)
    args = ("estimate", "occluded-quad", "--plugin", str(path), "--estimator", "independent:single:cosine",
            "--n", "4", "--trials", "8")
    result = run_warpis(*args) if "sys.exit" in (body or "") else cli(*args)
    line = one_error_line(result)
    assert line.startswith(f"warpis: error: --plugin {path}: ") and problem in line, line


def test_files_say_which_forms_a_user_pattern_lacks_and_why(tmp_path):
    """summary.json (study) and verify.json (verify) list the forms in scope that have no
    value for the user's pattern, with the reason; the rows still carry the measurement."""
    (tmp_path / "hammersley.py").write_text(PLUGIN)
    (tmp_path / "study.toml").write_text(
        '[study]\nname = "hammersley"\ntrials = 8\nn = [4]\nscenes = ["occluded-quad"]\nreceivers = [0]\n'
        'estimators = ["hammersley:balance:light-area+cosine", "jittered:balance:light-area+cosine"]\noutputs = []\n')
    result = run_warpis("study", "--plugin", str(tmp_path / "hammersley.py"), str(tmp_path / "study.toml"),
                        "--out", str(tmp_path / "out"))
    assert result.status == 0, result.err
    absent = json.loads((tmp_path / "out" / "summary.json").read_text())["absent"]
    assert set(absent) == {"hammersley:balance:light-area+cosine"}
    assert "no block decomposition" in absent["hammersley:balance:light-area+cosine"]["exact"]
    assert "hammersley:power:light-area+cosine" in absent["hammersley:balance:light-area+cosine"]["veach-bound"]
    result = run_warpis("verify", "occluded-quad", "--plugin", str(tmp_path / "hammersley.py"), "--estimators",
                        "hammersley:single:cosine", "--n", "4", "--trials", "8", "--receivers", "0",
                        "--out", str(tmp_path / "verify"))
    assert result.status == 0, result.err
    row = json.loads((tmp_path / "verify" / "verify.json").read_text())["rows"][0]
    assert list(row["absent"]) == ["exact"] and "no block decomposition" in row["absent"]["exact"]
    assert row["predictions"] == {} and row["variance"] > 0


def test_verify_runs_only_estimators_whose_forms_are_all_there():
    from warpis.analysis.theory import missing_forms
    from warpis.runs.verify import default_estimators

    for est in default_estimators(("light-area", "cosine")):
        assert missing_forms(est) == {}, est


@pytest.mark.parametrize("m, trials, problem", [(0, 4, "m: must be at least 1"), (4, 2.5, "expected an integer"),
                                                (4, 1 << 31, "at most 2,147,483,647")])
def test_pattern_points_refuses_counts_the_kernels_cannot_take(m, trials, problem):
    with pytest.raises(warpis.WarpisError, match=problem):
        patterns.pattern_points("jittered", m, trials)
