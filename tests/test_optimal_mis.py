"""Optimal MIS (Kondapaneni et al. 2019), its oracle and pilot, and the cutoff heuristic.

*A closed form.*  At the centre of a dome of uniform radiance L, f = L cos θ = πL·g_cosine,
so with the techniques uniform + cosine f lies in the span of the pdfs: A α = b has the
solution α = (0, πL) — exactly, for the oracle's finite grid too, because b̂ = Â (0, πL)
sample by sample — and h = f − α·g vanishes, so every trial of the oracle equals F = πL
and the exact variance and Kondapaneni's (1/m)(∫ f²/S − bᵀA⁻¹b) are both 0.  Deterministic
checks (rounding only).

*Measured against predicted* (occluded-quad, lit, penumbra and umbra receivers 0–2, and
mitsuba-veach-plates receiver 1, where rough-conductor samples fail; independent pattern, N = 16, 20,000
trials): the oracle's sample variance within 4.5 of its standard errors (fourth-moment,
prediction error added in quadrature) of the exact variance at the oracle's α (4
two-sided normal checks at 6.8e-6: false failure ≈ 3e-5);
Kondapaneni's optimum within 4.5 combined standard errors of the exact variance at the
oracle's α (deterministic given the fixed points; measured within 1.2).  The oracle's exact
variance is at most the balance heuristic's (α = 0 is one of the α the optimum beats;
deterministic).

Unbiasedness of optimal, optimal-oracle and cutoff under every pattern is in
tests/test_estimators.py (which also replays each trial in numpy).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from conftest import dome_scene, one_error_line

import warpis
from warpis.stats import variance_interval
from warpis.analysis.quadrature import exact_variance, optimal_alpha
from warpis.analysis.theory import predictions
from warpis.kernels.engine import pilot_alphas, run_trials

L = 2.0
Z = 4.5


@pytest.fixture(scope="module")
def dome(tmp_path_factory):
    """A receiver at the centre of a closed inward-facing sphere of radiance L: f = L cos θ."""
    return dome_scene(tmp_path_factory.mktemp("dome"), L)


@pytest.fixture(scope="module")
def quad():
    return warpis.load_scene("occluded-quad")


def test_the_oracle_finds_the_span_of_the_pdfs_and_has_no_variance_there(dome):
    alpha = optimal_alpha(dome, [0], ("uniform", "cosine"))[0]
    np.testing.assert_allclose(alpha, [0.0, math.pi * L], atol=1e-9 * L)
    est = "jittered:optimal-oracle:uniform+cosine"
    values = run_trials(dome, est, 8, 500, seed=3)[0]
    np.testing.assert_allclose(values, math.pi * L, rtol=1e-6)
    assert exact_variance(dome, 0, est, 8).value == pytest.approx(0.0, abs=1e-12)
    p = predictions(dome, 0, "independent:optimal-oracle:uniform+cosine", 8)
    assert p["optimal-ab"].value == pytest.approx(0.0, abs=1e-9) and p["exact"].value == pytest.approx(0.0, abs=1e-12)


def test_the_pilot_is_unbiased_but_its_ridge_keeps_it_off_the_exact_alpha(dome):
    """The pilot's α solves (Â + λI)α = b̂, so on the dome it is close to (0, πL) but not
    on it, and the trials spread; every trial still averages to πL (mean within Z
    standard errors: two-sided normal 6.8e-6)."""
    est = "independent:optimal:uniform+cosine"
    alphas = pilot_alphas(dome, est, 16, 2000, seed=3)[0]
    assert alphas.shape == (2000, 2)
    # Two pilot samples per technique: the ridge moves α visibly (measured: α_cosine from
    # 3.6 to 6.2, median 5.98 against πL = 6.28), and never far from the span.
    assert abs(np.median(alphas[:, 1]) - math.pi * L) < 0.1 * math.pi * L
    assert np.abs(alphas[:, 1] - math.pi * L).min() > 1e-6
    values = run_trials(dome, est, 16, 2000, seed=3)[0]
    se = values.std(ddof=1) / math.sqrt(len(values))
    assert se > 0 and abs(values.mean() - math.pi * L) <= Z * se


@pytest.fixture(scope="module")
def plates():
    pytest.importorskip("mitsuba")
    return warpis.load_scene("mitsuba-veach-plates")


@pytest.mark.parametrize("name, receiver", [("quad", 0), ("quad", 1), ("quad", 2), ("plates", 1)])
def test_the_oracle_holds_its_exact_variance_and_kondapanenis_optimum(request, name, receiver):
    """At receiver 1 of mitsuba-veach-plates 9% of the rough-conductor samples fail (the
    extended domain's points): there the exact variance needs the −N_g α_k of a failed
    sample."""
    scene = request.getfixturevalue(name)
    techs = "light-area+cosine" if name == "quad" else "light-area+bsdf"
    est = f"independent:optimal-oracle:{techs}"
    measured = variance_interval(run_trials(scene, est, 16, 20000, seed=5, receivers=[receiver])[0])
    p = predictions(scene, receiver, est, 16)
    exact, optimum = p["exact"], p["optimal-ab"]
    assert abs(measured.variance - exact.value) <= Z * math.hypot(measured.variance_stderr, exact.stderr)
    assert abs(optimum.value - exact.value) <= Z * math.hypot(optimum.stderr, exact.stderr)
    balance = exact_variance(scene, receiver, f"independent:balance:{techs}", 16)
    assert exact.value <= balance.value + Z * math.hypot(exact.stderr, balance.stderr)


def test_the_theorys_psi_counts_every_sample_and_a_failed_one_as_minus_ng_alpha():
    """The numpy twin the exact variance uses (ψ_k = N_g (f − α·g)/Σ g, −N_g α_k where the
    sample failed), on hand-made samples: one with f > 0, one occluded (f = 0: still
    −N_g α·g/Σ g), one failed (every pdf 0)."""
    from warpis.analysis.quadrature import weighted_values
    from warpis.vocabulary import WeightContext

    f = np.array([0.5, 0.0, 0.0])
    pdf = np.array([[1.0, 3.0], [2.0, 0.5], [0.0, 0.0]])
    alpha = np.array([[0.2, 0.7]] * 3)
    psi = weighted_values("optimal-oracle", 1, f, pdf, WeightContext(None, alpha))
    np.testing.assert_allclose(psi, [2 * (0.5 - 2.3) / 4.0, 2 * (0.0 - 0.75) / 2.5, -2 * 0.7])


def test_cutoff_zero_is_the_balance_heuristic_and_one_keeps_only_the_largest_pdf(quad):
    """cutoff=0 keeps every technique (the balance heuristic, bit for bit); cutoff=1 keeps
    only the largest pdf, which is the maximum heuristic wherever no two pdfs tie."""
    balance = run_trials(quad, "independent:balance:light-area+cosine", 8, 300, seed=2)
    zero = run_trials(quad, "independent:cutoff=0:light-area+cosine", 8, 300, seed=2)
    np.testing.assert_array_equal(zero, balance)
    one = run_trials(quad, "independent:cutoff=1:light-area+cosine", 8, 300, seed=2)
    maximum = run_trials(quad, "independent:maximum:light-area+cosine", 8, 300, seed=2)
    np.testing.assert_allclose(one, maximum, rtol=1e-6)
    # Light-area's pdf is rarely within 50× of cosine's here: at α = 0.02 the lit receiver
    # 0 keeps both techniques in some samples, neither heuristic in all.
    between = run_trials(quad, "independent:cutoff=0.02:light-area+cosine", 8, 300, seed=2, receivers=[0])[0]
    assert not np.allclose(between, balance[0]) and not np.allclose(between, maximum[0])


def test_estimate_reports_the_coefficients(cli):
    oracle = cli("estimate", "occluded-quad", "--estimator", "jittered:optimal-oracle:light-area+cosine", "--n", "8",
                 "--trials", "200", "--receivers", "0,2", "--json")
    assert oracle.status == 0, oracle.err
    rows = json.loads(oracle.out)["receivers"]
    assert [len(r["alpha"]) for r in rows] == [2, 2]
    assert rows[0]["alpha"][0] == pytest.approx(rows[0]["reference"], rel=0.05)  # the lit receiver: α ≈ F on light-area
    pilot = cli("estimate", "occluded-quad", "--estimator", "jittered:optimal:light-area+cosine", "--n", "8",
                "--trials", "200", "--receivers", "0")
    assert pilot.status == 0, pilot.err
    assert "from each trial's pilot" in pilot.out and "±" in pilot.out.splitlines()[-1]


@pytest.mark.parametrize("spec, problem", [
    ("jittered:cutoff=abc:light-area+cosine", "α must be a number"),
    ("jittered:cutoff=1.5:light-area+cosine", "α must lie in [0, 1]"),
    ("jittered:cutoff=nan:light-area+cosine", "α must lie in [0, 1]"),
    ("jittered:balance=0.5:light-area+cosine", "takes no parameter"),
    ("jittered:optimal:light-area+cosine+uniform+light-power+light-solid-angle", "at most 4 techniques"),
    ("jittered:optimal:light-area", "combines two or more techniques"),
])
def test_bad_combiner_spellings_are_one_line(cli, spec, problem):
    line = one_error_line(cli("estimate", "occluded-quad", "--estimator", spec, "--n", "16", "--trials", "10"))
    assert problem in line, line


def test_a_pilot_that_leaves_no_sample_is_one_line(cli):
    line = one_error_line(cli("estimate", "occluded-quad", "--estimator", "jittered:optimal:light-area+cosine",
                              "--n", "2", "--trials", "10"))
    assert "needs N ≥ 4" in line, line
    line = one_error_line(cli("estimate", "occluded-quad", "--estimator", "antithetic:optimal:light-area+cosine",
                              "--n", "4", "--trials", "10"))
    assert "1 go to the pilot" in line, line
    assert cli("estimate", "occluded-quad", "--estimator", "antithetic:optimal:light-area+cosine", "--n", "8",
               "--trials", "10").status == 0  # m = 4: a pilot of 2 leaves the pairs an even count
