"""``warpis check`` (warpis/check/): the gallery of planted bugs, warpis's own techniques,
Mitsuba's BSDFs, the family-wise level, the window, and what bad input gets.

*The gallery* (docs/check-gallery/, shown in docs/check.md): each plugin registers a buggy
subject and its correct version.  Each runs through the command line at a reduced budget
(``GALLERY_ARGS``: 10⁵ samples, 2 frames) that still catches its bug; the test asserts
that the buggy one exits 1 with its named check failed at every frame, and that the
correct one passes every check (exit 0).  The bugs are large (7 % and more, or a
density off by a factor 4), deterministic checks catch them exactly, and the statistical
ones by hundreds of standard errors; the correct versions pass at family-wise level 1e-3
per run (Šidák over the run's tests), so with 7 of them the file fails a correct
implementation by chance with probability ≤ 7e-3 — and never at these fixed seeds.

*Built-in techniques* (cosine, light-area and light-solid-angle on occluded-quad; phong
and light-solid-angle among veach-plates' four sphere lights, which split into a
chi-square region each) *and Mitsuba BSDFs* run at the same reduced budget, family-wise
level 1e-3 each run: with about a dozen runs passing here, the file fails a correct
implementation by chance with probability ≤ 2e-2 under other seeds, and at these fixed
seeds it does not.  Mitsuba's part skips, with the reason, where the llvm_ad_rgb variant cannot run
(no libLLVM 19), as tests/test_bench_mitsuba.py does.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from conftest import one_error_line

import warpis
from warpis.check.entries import NUMPY_COMBINERS, NUMPY_TECHNIQUES
from warpis.check.run import Budget, count_tests, run_subjects
from warpis.check.subjects import numpy_technique
from warpis.check.window import SphereQuadrature, Window
from warpis.errors import WarpisError
from warpis.kernels.techniques import TECHNIQUES, user_techniques
from warpis.stats import sidak_threshold

ROOT = Path(__file__).resolve().parents[1]
GALLERY = ROOT / "docs" / "check-gallery"
GALLERY_ARGS = ("--samples", "100000", "--frames", "2", "--json")

# plugin → (subject option, buggy name, correct name, the check that must catch the bug)
CASES = {
    "pdf_mismatch": ("--technique", "cosine-pdf-7pct", "cosine-pdf-fixed", "pdf-at-sample"),
    "area_measure": ("--technique", "quad-light-area-pdf", "quad-light", "measure"),
    "missing_cos": ("--technique", "cosine-no-cos", "cosine-with-cos", "pdf-integral"),
    "half_vector": ("--technique", "half-vector-no-jacobian", "half-vector", "chi-square"),
    "wrong_lobe": ("--technique", "two-lobes-swapped", "two-lobes", "chi-square"),
    "weights_sum": ("--combiner", "power-over-sum-squared", "power-heuristic", "weights-sum"),
    "zero_pdf": ("--technique", "lambert-capped", "lambert-cosine", "eval-quadrature"),
}


def _registered() -> tuple[set[str], set[str], set[str]]:
    return set(NUMPY_TECHNIQUES), set(NUMPY_COMBINERS), {u.name for u in user_techniques()}


def _unregister_since(before: tuple[set[str], set[str], set[str]]) -> None:
    """Undo what plugins registered since ``before``, so that the next run may load them again."""
    now = _registered()
    for name in now[0] - before[0]:
        warpis.unregister_numpy_technique(name)
    for name in now[1] - before[1]:
        warpis.unregister_numpy_combiner(name)
    for name in now[2] - before[2]:
        warpis.unregister_technique(name)


@pytest.fixture
def clean_registries():
    before = _registered()
    yield
    _unregister_since(before)


def _check(cli, *args: str) -> tuple[int, dict]:
    """Run ``warpis check ARGS`` (with ``--json``) in this process, unregistering what its plugins add."""
    before = _registered()
    try:
        result = cli("check", *args)
    finally:
        _unregister_since(before)
    assert result.status in (0, 1), result.err
    return result.status, json.loads(result.out)


@pytest.mark.parametrize("plugin", list(CASES))
def test_every_gallery_bug_is_caught_by_its_check(cli, plugin):
    option, bad, good, named = CASES[plugin]
    path = str(GALLERY / f"{plugin}.py")
    status, data = _check(cli, "--plugin", path, option, bad, *GALLERY_ARGS)
    assert status == 1 and not data["passed"]
    caught = [v for v in data["verdicts"] if v["check"] == named]
    assert caught and all(v["passed"] is False for v in caught), [(v["check"], v["summary"]) for v in caught]
    status, data = _check(cli, "--plugin", path, option, good, *GALLERY_ARGS)
    failed = [(v["check"], v["frame"], v["summary"]) for v in data["verdicts"] if v["passed"] is False]
    assert status == 0 and data["passed"] and not failed, failed


def test_the_gallery_page_shows_every_case():
    page = (ROOT / "docs" / "check.md").read_text()
    for plugin, (option, bad, good, named) in CASES.items():
        assert f"docs/check-gallery/{plugin}.py" in page and f"{option} {bad}" in page, plugin
        assert named in page


# --------------------------------------------------------------------------- warpis's own


@pytest.mark.parametrize("technique, scene", [("cosine", "occluded-quad"), ("light-area", "occluded-quad"),
                                               ("light-solid-angle", "occluded-quad"),
                                               ("light-solid-angle", "veach-plates"), ("phong", "veach-plates")])
def test_warpis_techniques_pass(cli, technique, scene):
    """Built-in techniques at two receivers of a scene; on veach-plates the four sphere
    lights fall apart into regions, each a chi-square test of its own."""
    frames = "1" if scene == "veach-plates" else "2"  # its lights: five regions per frame, each integrated
    status, data = _check(cli, "--technique", technique, "--scene", scene, "--samples", "100000", "--frames", frames,
                          "--json")
    failed = [(v["check"], v["frame"], v["summary"]) for v in data["verdicts"] if v["passed"] is False]
    assert status == 0 and not failed, failed
    checks = {v["check"] for v in data["verdicts"]}
    assert {"chi-square", "pdf-integral", "pdf-at-sample", "zero-pdf"} <= checks
    if TECHNIQUES[technique].light:
        assert "measure" in checks
    if TECHNIQUES[technique].light and scene == "occluded-quad":  # veach-plates has no closed form
        assert "unbiased" in checks


@pytest.mark.parametrize("combiner", ["balance", "power", "maximum", "cutoff"])
def test_builtin_combiner_weights_sum_to_one(cli, combiner):
    status, data = _check(cli, "--combiner", combiner, "--samples", "20000", "--frames", "2", "--json")
    assert status == 0, [v["summary"] for v in data["verdicts"] if v["passed"] is False]
    assert {v["check"] for v in data["verdicts"]} == {"weights-sum", "weights-zero"}


def test_a_numpy_technique_is_refused_by_estimators_with_the_reason(cli, clean_registries):
    cli("check", "--plugin", str(GALLERY / "missing_cos.py"), "--technique", "cosine-with-cos", "--checks",
        "zero-pdf", "--samples", "1000", "--frames", "1")
    line = one_error_line(cli("estimate", "occluded-quad", "--estimator", "independent:single:cosine-with-cos",
                              "--n", "4"))
    assert "numpy technique" in line and "no per-sample Python" in line, line


# --------------------------------------------------------------------------- the family and the tolerances


def _cosine_entry(reported_factor: float = 1.0):
    def tangents(n):
        a = np.where(np.abs(n[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
        t = np.cross(a, n)
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        return t, np.cross(n, t)

    def sample(n, wo, u):
        t, b = tangents(n)
        r, phi, z = np.sqrt(u[:, 0]), 2 * math.pi * u[:, 1], np.sqrt(1 - u[:, 0])
        w = (r * np.cos(phi))[:, None] * t + (r * np.sin(phi))[:, None] * b + z[:, None] * n
        return w, reported_factor * z / math.pi

    def pdf(n, wo, w):
        return np.maximum(np.sum(n * w, axis=1), 0.0) / math.pi

    return warpis.check.NumpyTechnique("test-cosine", sample, pdf)


def test_the_family_is_every_statistical_test_of_the_run():
    """Per frame: chi-square and pdf-integral (no eval, no light): 2 × frames tests, each at
    Šidák's level; the chi-square p-values of a correct sampler over 40 frames reach below
    the family-wise level, and the run still passes: only the corrected level decides."""
    subject = numpy_technique(_cosine_entry(), 40)
    budget = Budget(samples=2000, seed=11, significance=0.05)
    assert count_tests([subject], budget) == 80
    run = run_subjects("family", [subject], budget)
    assert run.family.per_test == pytest.approx(sidak_threshold(0.05, 80))
    p = [v.numbers["p_value"] for v in run.verdicts if v.check == "chi-square"]
    assert min(p) < 0.05, min(p)  # would fail at the uncorrected level
    assert run.passed, [v.summary for v in run.failed]


@pytest.mark.parametrize("factor, passes", [(1.0, True), (1.0 + 1e-5, True), (1.005, False), (0.99, False)])
def test_pdf_at_sample_tolerance(factor, passes):
    """The reported pdf may differ from the recomputed one by float32 rounding (1e-5 passes),
    not by 0.5 % (deterministic)."""
    run = run_subjects("tolerance", [numpy_technique(_cosine_entry(factor), 1)],
                       Budget(samples=5000, checks=("pdf-at-sample",)))
    (verdict,) = run.verdicts
    assert verdict.passed is passes, verdict.summary


def test_the_window_keeps_every_integral():
    """The magnified sphere is a bijection with the right Jacobian: forward then inverse is
    the identity, and a lobe of width 0.02 rad integrates to 1 on it within 4 of the
    quadrature's (upward-biased) standard errors (deterministic at this seed)."""
    axis = np.array([0.2, -0.4, 0.89]) / np.linalg.norm([0.2, -0.4, 0.89])
    win = Window(axis, 0.02)
    d = np.random.default_rng(1).normal(size=(1000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    back, _ = win.inverse(win.forward(d)[0])
    np.testing.assert_allclose(back, d, atol=1e-9)
    k = 2.0 / 0.02**2  # a von Mises–Fisher lobe, concentration k: ∫ = 1

    def lobe(x):
        return k / (2 * math.pi * -math.expm1(-2 * k)) * np.exp(k * (x @ axis - 1.0))

    total, se = SphereQuadrature(win, 128, 256, np.random.default_rng(2)).integrate(lobe)
    assert abs(total - 1.0) <= 4 * se + 1e-9 and se < 2e-3, (total, se)


def test_out_writes_the_report(cli, tmp_path):
    out = tmp_path / "report"
    status, data = _check(cli, "--technique", "cosine", "--samples", "20000", "--frames", "1", "--out", str(out),
                          "--json")
    assert status == 0
    stored = json.loads((out / "check.json").read_text())
    assert stored["verdicts"] == data["verdicts"]
    html = (out / "index.html").read_text()
    figures = sorted((out / "figures").glob("*.png"))
    assert len(figures) == sum(v["passed"] is not None for v in data["verdicts"]) >= 4
    assert all(f.read_bytes().startswith(b"\x89PNG") for f in figures)
    assert all(f"figures/{f.name}" in html for f in figures)


# --------------------------------------------------------------------------- Mitsuba


@pytest.fixture(scope="module")
def mitsuba_ok():
    from warpis.check.mitsuba_bsdfs import mitsuba_unusable

    why = mitsuba_unusable()
    if why is not None:
        pytest.skip(why)


def test_mitsuba_bsdfs_of_the_bundled_scenes(cli, mitsuba_ok):
    """Every BSDF type of the bundled Mitsuba scenes: diffuse and GGX roughconductor pass every
    check; Mitsuba 3.9's roughplastic fails chi-square and pdf-integral only — its pdf does
    not vanish below the horizon, where its sampler's reflections have weight 0 — and
    passes weight, eval-quadrature, energy and reciprocity."""
    status, data = _check(cli, "--bsdfs", str(ROOT / "meshes" / "mitsuba-material-preview" / "scene.xml"),
                          *GALLERY_ARGS)
    by = {}
    for v in data["verdicts"]:
        by.setdefault(v["subject"].split(" (")[0].split()[-1], []).append(v)
    assert set(by) == {"floor", "gold", "plastic"}
    for name in ("floor", "gold"):
        failed = [(v["check"], v["summary"]) for v in by[name] if v["passed"] is False]
        assert not failed, (name, failed)
    failed = {v["check"] for v in by["plastic"] if v["passed"] is False}
    assert failed == {"chi-square", "pdf-integral"}, failed
    assert all("where eval = 0" in v["summary"] for v in by["plastic"] if v["check"] == "pdf-integral")
    assert status == 1
    assert {"weight", "eval-quadrature", "energy", "reciprocity"} <= {v["check"] for v in by["gold"]}


def test_mitsuba_beckmann_pdf_is_reported_with_its_numbers(cli, mitsuba_ok, tmp_path):
    """Mitsuba's Beckmann visible-normal pdf carries the rational G1 where its sampler draws
    the exact one: ∫pdf/valid fraction departs from 1 by up to 0.3 % per view (at θi = 53°
    for α = 0.55: +0.28 %, 7σ at 10⁶ samples), and the check fails there with the ratio."""
    xml = (GALLERY / "beckmann.xml").read_text()
    xml = xml[:xml.index('    <shape type="rectangle" id="ggx">')] + "</scene>\n"
    (tmp_path / "beckmann.xml").write_text(xml)
    status, data = _check(cli, "--bsdfs", str(tmp_path / "beckmann.xml"), "--samples", "1000000", "--frames", "4",
                          "--checks", "pdf-integral", "--json")
    ratios = {v["frame"]: v["numbers"]["ratio"] for v in data["verdicts"]}
    assert status == 1 and [v["frame"] for v in data["verdicts"] if not v["passed"]] == ["view θi = 53°"]
    assert 1.0015 < ratios["view θi = 53°"] < 1.004, ratios
    assert all(abs(r - 1.0) < 4e-3 for r in ratios.values()), ratios


# --------------------------------------------------------------------------- bad input

PLUGIN = str(GALLERY / "pdf_mismatch.py")
BAD = {
    "no subject": ([], "one of the arguments --technique --bsdfs --combiner is required"),
    "two subjects": (["--technique", "cosine", "--combiner", "balance"], "not allowed with"),
    "unknown technique": (["--technique", "nope"], "--technique: unknown technique 'nope'"),
    "unknown combiner": (["--combiner", "nope"], "--combiner: unknown combiner 'nope'"),
    "a combiner that weighs one technique": (["--combiner", "single"], "--combiner single: not a set of MIS"),
    "--techniques without --combiner": (["--technique", "cosine", "--techniques", "a+b"], "--techniques: only with"),
    "--techniques of one": (["--combiner", "balance", "--techniques", "cosine"], "--techniques: a combiner weighs"),
    "--techniques unknown": (["--combiner", "balance", "--techniques", "cosine+nope"], "unknown technique 'nope'"),
    "--samples too few": (["--technique", "cosine", "--samples", "10"], "--samples"),
    "--samples not an integer": (["--technique", "cosine", "--samples", "1e6"], "--samples"),
    "--samples past the limit": (["--technique", "cosine", "--samples", "100000000"], "--samples"),
    "--frames 0": (["--technique", "cosine", "--frames", "0"], "--frames"),
    "--frames too many": (["--technique", "cosine", "--frames", "65"], "--frames"),
    "--seed negative": (["--technique", "cosine", "--seed", "-1"], "--seed"),
    "--seed past 2^32": (["--technique", "cosine", "--seed", "4294967296"], "--seed"),
    "--significance 0": (["--technique", "cosine", "--significance", "0"], "--significance"),
    "--significance 1": (["--technique", "cosine", "--significance", "1"], "--significance"),
    "--significance not a number": (["--technique", "cosine", "--significance", "often"], "--significance"),
    "--checks unknown": (["--technique", "cosine", "--checks", "chi-square,nope"], "--checks: unknown check 'nope'"),
    "--checks empty": (["--technique", "cosine", "--checks", ","], "--checks"),
    "--receivers out of range": (["--technique", "cosine", "--receivers", "0,99"], "--receivers: receiver 99"),
    "--receivers negative": (["--technique", "cosine", "--receivers", "-1"], "--receivers"),
    "--scene unknown": (["--technique", "cosine", "--scene", "no-such-scene"], "no-such-scene"),
    "--scene with --bsdfs": (["--bsdfs", "x.xml", "--scene", "occluded-quad"], "--scene: not with --bsdfs"),
    "--receivers with --bsdfs": (["--bsdfs", "x.xml", "--receivers", "0"], "--receivers: not with --bsdfs"),
    "--receivers-file without --bsdfs": (["--technique", "cosine", "--receivers-file", "r.toml"],
                                         "--receivers-file: only with --bsdfs"),
    "--bsdfs missing": (["--bsdfs", "no/such.xml"], "--bsdfs no/such.xml: no such file"),
    "--bsdfs a directory": (["--bsdfs", "docs"], "is a directory"),
    "--bsdfs not XML": (["--bsdfs", "README.md"], "not a Mitsuba scene"),
    "--out empty": (["--technique", "cosine", "--out", ""], "--out: must name a directory"),
    "envmap on a scene without an environment": (["--technique", "envmap"], "has no environment light"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input_is_one_line(cli, case, monkeypatch):
    monkeypatch.chdir(ROOT)
    args, expected = BAD[case]
    budget = [] if "--samples" in args else ["--samples", "1000"]  # small, should one slip through
    line = one_error_line(cli("check", *args, *budget))
    assert expected in line, line


def test_out_that_is_a_file_is_one_line_and_writes_nothing(cli, tmp_path):
    blocker = tmp_path / "afile"
    blocker.write_text("x")
    line = one_error_line(cli("check", "--technique", "cosine", "--samples", "1000", "--out", str(blocker / "sub")))
    assert "cannot write" in line or "is a file" in line or "directory" in line, line
    assert blocker.read_text() == "x" and not (tmp_path / "afile" / "sub").exists()


def test_refused_input_leaves_no_out_folder(cli, tmp_path):
    out = tmp_path / "never"
    one_error_line(cli("check", "--technique", "nope", "--samples", "1000", "--out", str(out)))
    assert not out.exists()


def _write(tmp_path: Path, body: str) -> str:
    path = tmp_path / "plugin.py"
    path.write_text("import numpy as np\nimport warpis\n" + body)
    return str(path)


USER_BUGS = {
    "sample raises": ("def s(n, wo, u):\n    raise ValueError('boom')\n"
                      "warpis.register_numpy_technique('t-raise', s, lambda n, wo, w: np.ones(len(w)))\n",
                      "t-raise", "technique 't-raise': sample raised ValueError: boom"),
    "sample returns the wrong shape": ("warpis.register_numpy_technique('t-shape', lambda n, wo, u: u, "
                                       "lambda n, wo, w: np.ones(len(w)))\n",
                                       "t-shape", "sample returned shape"),
    "pdf returns the wrong shape": ("warpis.register_numpy_technique('t-pdf', lambda n, wo, u: n, "
                                    "lambda n, wo, w: np.ones((len(w), 2)))\n", "t-pdf", "pdf returned shape"),
    "sample returns three things": ("warpis.register_numpy_technique('t-three', lambda n, wo, u: (n, n, n), "
                                    "lambda n, wo, w: np.ones(len(w)))\n", "t-three", "a tuple of 3"),
    "eval returns the wrong shape": ("warpis.register_numpy_technique('t-eval', lambda n, wo, u: n, "
                                     "lambda n, wo, w: np.ones(len(w)), eval=lambda n, wo, w: np.ones((2, 2)))\n",
                                     "t-eval", "eval returned shape"),
    "not a function": ("warpis.register_numpy_technique('t-nf', 3, lambda n, wo, w: w)\n", "t-nf",
                       "sample must be a function"),
    "a taken name": ("warpis.register_numpy_technique('cosine', lambda n, wo, u: n, lambda n, wo, w: w)\n", "cosine",
                     "'cosine' is already registered"),
    "a name with a plus": ("warpis.register_numpy_technique('a+b', lambda n, wo, u: n, lambda n, wo, w: w)\n", "a+b",
                           "a name must be"),
}


@pytest.mark.parametrize("case", list(USER_BUGS))
def test_a_broken_numpy_technique_is_one_line(cli, tmp_path, case):
    body, name, expected = USER_BUGS[case]
    before = _registered()
    try:
        line = one_error_line(cli("check", "--plugin", _write(tmp_path, body), "--technique", name, "--samples",
                                  "1000", "--frames", "1"))
    finally:
        _unregister_since(before)
    assert expected in line, line


COMBINER_BUGS = {
    "weights raise": ("def w(p):\n    raise KeyError('k')\nwarpis.register_numpy_combiner('c-raise', w)\n", "c-raise",
                      "combiner 'c-raise': weights raised KeyError"),
    "weights of the wrong shape": ("warpis.register_numpy_combiner('c-shape', lambda p: p[:, 0])\n", "c-shape",
                                   "weights returned shape"),
}


@pytest.mark.parametrize("case", list(COMBINER_BUGS))
def test_a_broken_numpy_combiner_is_one_line(cli, tmp_path, case):
    body, name, expected = COMBINER_BUGS[case]
    before = _registered()
    try:
        line = one_error_line(cli("check", "--plugin", _write(tmp_path, body), "--combiner", name, "--samples",
                                  "1000", "--frames", "1"))
    finally:
        _unregister_since(before)
    assert expected in line, line


def test_the_api_refuses_the_same_registrations():
    with pytest.raises(WarpisError, match="already registered"):
        warpis.register_numpy_technique("light-area", lambda n, wo, u: n, lambda n, wo, w: w)
    with pytest.raises(WarpisError, match="weights must be a function"):
        warpis.register_numpy_combiner("c", None)
    with pytest.raises(WarpisError, match="was not added"):
        warpis.unregister_numpy_technique("cosine")
