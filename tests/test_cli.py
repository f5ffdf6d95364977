"""Tests of the ``warpis`` command: scenes, info, reference, estimate, help and errors.

Most runs call ``warpis.cli.main`` in this process (the ``cli`` fixture of conftest.py);
the help text and usage errors are also checked in a fresh process, as a user sees them.
Every usage error must end with exit status 2, exactly one ``warpis: error:`` line on
stderr, no traceback and nothing on stdout.
"""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
import warpis
from conftest import BUNDLED, CAMERA_BUNDLED, MITSUBA_BUNDLED
from conftest import one_error_line as _one_error_line
from conftest import run_warpis, write_scene

SUMMARY_KEYS = {"scene", "triangles", "emitter_triangles", "receivers", "emitter_area", "total_power"}
ESTIMATE = ["estimate", "occluded-quad", "--estimator", "independent:single:light-area", "--n", "8",
            "--trials", "50", "--json"]


def test_scenes_lists_the_bundled_scenes(cli, loaded_scenes):
    """`warpis scenes` prints a header and one row per bundled scene, with its triangle
    count; `--json` gives the same scenes with each scene's summary."""
    result = cli("scenes")
    assert result.status == 0 and "Traceback" not in result.err
    lines = result.out.strip().splitlines()
    assert lines[0].split()[0] == "scene"
    rows = {line.split()[0]: line.split() for line in lines[1:]}
    assert sorted(rows) == sorted(BUNDLED + MITSUBA_BUNDLED + CAMERA_BUNDLED)
    scenes = loaded_scenes | {name: warpis.load_scene(name) for name in MITSUBA_BUNDLED + CAMERA_BUNDLED}
    for name, row in rows.items():
        assert int(row[1]) == scenes[name].triangle_count

    result = cli("scenes", "--json")
    data = json.loads(result.out)
    assert [row["scene"] for row in data["scenes"]] == sorted(BUNDLED + MITSUBA_BUNDLED + CAMERA_BUNDLED)
    for row in data["scenes"]:
        assert SUMMARY_KEYS <= set(row)
        assert row["emitter_triangles"] == scenes[row["scene"]].emitter_count


def test_info_table(cli):
    """`warpis info SCENE` prints the description, the counts, the emitter meshes
    (light.obj with radiance 10) and the receiver groups."""
    result = cli("info", "occluded-quad")
    assert result.status == 0 and result.err == ""
    assert "occluded-quad" in result.out and "light.obj" in result.out
    row = next(line for line in result.out.splitlines() if line.startswith("occluded-quad"))
    assert row.split()[1:4] == ["16", "2", "8"]
    assert "receiver groups:" in result.out and "irradiance" in result.out


@pytest.mark.parametrize("name", BUNDLED)
def test_info_json(name, cli, loaded_scenes):
    """`warpis info SCENE --json` is JSON with the keys scene, triangles,
    emitter_triangles, receivers, emitter_area and total_power, equal to the loaded
    scene's; its emitters add up to the totals."""
    result = cli("info", name, "--json")
    assert result.status == 0
    data = json.loads(result.out)
    assert SUMMARY_KEYS <= set(data)
    s = loaded_scenes[name]
    assert data["scene"] == name
    assert (data["triangles"], data["emitter_triangles"], data["receivers"]) == (
        s.triangle_count, s.emitter_count, len(s.receivers))
    assert data["emitter_area"] == pytest.approx(s.total_emitter_area, rel=1e-12)
    assert data["total_power"] == pytest.approx(s.total_power, rel=1e-12)
    assert sum(e["area"] for e in data["emitters"]) == pytest.approx(data["emitter_area"], rel=1e-9)
    assert sum(e["power"] for e in data["emitters"]) == pytest.approx(data["total_power"], rel=1e-9)
    assert sum(g["receivers"] for g in data["receiver_groups"]) == data["receivers"]


def test_info_on_a_path(cli, tmp_path):
    """`warpis info` takes a scene file's path or its folder as well as a bundled name."""
    path = write_scene(tmp_path, name="my-scene")
    for arg in (path, tmp_path):
        result = cli("info", arg, "--json")
        assert result.status == 0, result.err
        data = json.loads(result.out)
        assert data["scene"] == "my-scene"
        assert (data["triangles"], data["emitter_triangles"], data["receivers"]) == (4, 2, 1)
        assert data["emitter_area"] == pytest.approx(1.0) and data["total_power"] == pytest.approx(10.0)


def test_help():
    """`warpis --help` exits 0 and names every subcommand; each subcommand has help."""
    result = run_warpis("--help")
    assert result.status == 0 and result.err == ""
    assert result.out.startswith("usage: warpis")
    for command in ("scenes", "info", "reference", "estimate"):
        assert command in result.out


def test_subcommand_help(cli):
    """`warpis estimate --help` documents --estimator, --n, --trials and --seed."""
    result = cli("estimate", "--help")
    assert result.status == 0
    for option in ("--estimator", "--n", "--trials", "--seed", "--receivers", "--json"):
        assert option in result.out


def test_unknown_subcommand():
    """An unknown subcommand exits 2 with one error line naming the valid commands,
    in a fresh process, with nothing on stdout."""
    line = _one_error_line(run_warpis("frobnicate", "occluded-quad"))
    assert "frobnicate" in line and "estimate" in line


def test_missing_subcommand(cli):
    """`warpis` with no subcommand exits 2 with one error line."""
    _one_error_line(cli())


def test_reference_json(cli):
    """`warpis reference occluded-quad --json` is {"scene", "receivers": [{"index",
    "value", "stderr", "method"}]} with one row per receiver in order, method closed-form
    or quadrature, finite values, closed forms exact (stderr 0), and umbra receivers 0."""
    result = cli("reference", "occluded-quad", "--json")
    assert result.status == 0, result.err
    data = json.loads(result.out)
    assert data["scene"] == "occluded-quad"
    rows = data["receivers"]
    assert [r["index"] for r in rows] == list(range(8))
    for r in rows:
        assert {"index", "value", "stderr", "method"} <= set(r)
        assert r["method"] in {"closed-form", "quadrature"}
        assert math.isfinite(r["value"]) and r["value"] >= 0.0
        assert math.isfinite(r["stderr"]) and r["stderr"] >= 0.0
        if r["method"] == "closed-form":
            assert r["stderr"] == 0.0
    assert rows[3]["value"] == 0.0 and rows[4]["value"] == 0.0  # umbra of the box
    assert rows[0]["value"] > 0.0 and rows[7]["value"] > 0.0  # fully lit


def test_reference_selected_receivers(cli):
    """--receivers picks the rows, in the order given."""
    data = json.loads(cli("reference", "occluded-quad", "--json", "--receivers", "7,0").out)
    assert [r["index"] for r in data["receivers"]] == [7, 0]


def test_estimate_json(cli):
    """`warpis estimate occluded-quad --estimator independent:single:light-area --n 8
    --trials 50 --json` has the documented schema, and its numbers are the documented
    statistics of the 50 trials (recomputed here from ``run_trials`` with the same seed,
    which draws the same estimates): the mean, stderr = √(s²/M), the unbiased s² and the
    95% interval s² ∓ 1.96·√((m4 − s⁴(M−3)/(M−1))/M), lo clipped at 0, m4 the plug-in
    fourth central moment (docs/python-api.md, "JSON that other tools read"); umbra receivers
    estimate exactly 0 with zero variance.  And each mean lies within 5 combined standard
    errors of the reference: light-area estimates are bounded (f/g ≤ L·A·cos θ·cos θ_y/r²),
    so the mean of 50 is close to normal and |z| > 5 has probability 5.7e-7 per receiver
    (6 lit or penumbra receivers: ≤ 3.4e-6 under another seed; with seed 0 the numbers
    are the same every run)."""
    result = cli(*ESTIMATE)
    assert result.status == 0, result.err
    data = json.loads(result.out)
    assert {"scene", "estimator", "n", "trials", "seed", "receivers"} <= set(data)
    assert (data["scene"], data["estimator"], data["n"], data["trials"], data["seed"]) == (
        "occluded-quad", "independent:single:light-area", 8, 50, 0)
    rows = data["receivers"]
    assert [r["index"] for r in rows] == list(range(8))

    from scipy.stats import norm

    import warpis
    from warpis.kernels.engine import run_trials

    trials = run_trials(warpis.load_scene("occluded-quad"), "independent:single:light-area", 8, 50, seed=0)
    z = float(norm.ppf(0.975))
    for r, x in zip(rows, trials):
        assert {"index", "mean", "stderr", "variance", "variance_ci", "reference", "reference_stderr"} <= set(r)
        m = len(x)
        s2 = x.var(ddof=1)
        m4 = np.mean((x - x.mean()) ** 4)
        se = math.sqrt(max((m4 - s2 * s2 * (m - 3) / (m - 1)) / m, 0.0))
        assert r["mean"] == pytest.approx(x.mean(), rel=1e-12, abs=1e-15), r["index"]
        assert r["stderr"] == pytest.approx(math.sqrt(s2 / m), rel=1e-9, abs=1e-15), r["index"]
        assert r["variance"] == pytest.approx(s2, rel=1e-9, abs=1e-15), r["index"]
        assert r["variance_ci"] == pytest.approx([max(0.0, s2 - z * se), s2 + z * se], rel=1e-9, abs=1e-15), r["index"]
        se_total = math.hypot(r["stderr"], r["reference_stderr"])
        assert abs(r["mean"] - r["reference"]) <= 5 * se_total + 1e-12
    assert all(rows[r]["variance_ci"][1] > rows[r]["variance"] > 0 for r in (0, 1, 2, 5, 6, 7))
    for umbra in (3, 4):
        assert rows[umbra]["mean"] == 0.0 and rows[umbra]["variance"] == 0.0 and rows[umbra]["variance_ci"] == [0, 0]


def test_estimate_is_reproducible(cli):
    """The same command twice gives identical JSON (counter-based random numbers)."""
    first = json.loads(cli(*ESTIMATE, "--receivers", "1,5").out)
    second = json.loads(cli(*ESTIMATE, "--receivers", "1,5").out)
    assert first == second
    assert [r["index"] for r in first["receivers"]] == [1, 5]
    assert all(r["variance"] > 0 for r in first["receivers"])


BAD_OPTIONS = {
    "estimator-not-three-parts": (["--estimator", "light-area"], "PATTERN:COMBINER[=VALUE]:TECH"),
    "unknown-pattern": (["--estimator", "sobolish:single:light-area"], "unknown pattern"),
    "unknown-combiner": (["--estimator", "independent:average:light-area"], "unknown combiner"),
    "unknown-technique": (["--estimator", "independent:single:torch"], "unknown technique"),
    "single-with-two-techniques": (["--estimator", "independent:single:light-area+cosine"], "exactly one"),
    "balance-with-one-technique": (["--estimator", "independent:balance:cosine"], "two or more"),
    "n-not-divisible": (["--estimator", "independent:balance:light-area+cosine", "--n", "7"], "divisible"),
    "odd-n-antithetic": (["--estimator", "antithetic:single:cosine", "--n", "7"], "even number"),
    "odd-m-jittered-antithetic": (["--estimator", "jittered-antithetic:balance:light-area+cosine", "--n", "6"],
                                  "even number of samples per technique"),
    "n-zero": (["--n", "0"], "argument --n"),
    "n-not-a-number": (["--n", "eight"], "argument --n"),
    "trials-one": (["--trials", "1"], "--trials"),
    "receivers-not-numbers": (["--receivers", "a,b"], "--receivers"),
    "receivers-empty": (["--receivers", ","], "--receivers is empty"),
    "receiver-out-of-range": (["--receivers", "0,8"], "receiver 8"),
    "negative-receiver": (["--receivers", "-1"], "receiver -1"),
    "unknown-option": (["--samples-per-pixel", "4"], "--samples-per-pixel"),
}


@pytest.mark.parametrize("case", list(BAD_OPTIONS))
def test_estimate_bad_options(case, cli):
    """Each bad estimator spec or option of `warpis estimate` (malformed or unknown
    pattern, combiner or technique, wrong technique count, N not divisible by the
    techniques, odd N for antithetic, bad N/trials, bad --receivers) exits 2 with one
    `warpis: error:` line that names the problem, and prints nothing on stdout."""
    extra, words = BAD_OPTIONS[case]
    base = {"--estimator": "independent:single:light-area", "--n": "8", "--trials": "20"}
    args = ["estimate", "occluded-quad"]
    for key, value in base.items():
        if key not in extra:
            args += [key, value]
    line = _one_error_line(cli(*args, *extra))
    assert words in line, line


def test_estimate_bad_option_in_a_process():
    """A bad estimator spec in a fresh process: exit 2, one error line, no traceback."""
    line = _one_error_line(run_warpis("estimate", "occluded-quad", "--estimator", "antithetic:single:cosine",
                                      "--n", "3", "--trials", "10"))
    assert "even" in line


@pytest.mark.parametrize("args", [["reference", "occluded-quad", "--receivers", "99"],
                                  ["reference", "no-such-scene"],
                                  ["info", "occluded-quad", "--bogus"],
                                  ["reference", "occluded-quad", "--samples", "0"]])
def test_other_bad_arguments(args, cli):
    """Bad arguments to the other commands (receiver out of range, unknown scene,
    unknown option, zero samples) exit 2 with one error line."""
    _one_error_line(cli(*args))


def test_estimator_help_lists_the_registered_vocabulary(cli):
    """`warpis estimate --help` and `warpis verify --help` name every registered pattern,
    combiner and technique with its one-line description."""
    from warpis.kernels.estimators import COMBINERS
    from warpis.kernels.patterns import PATTERNS
    from warpis.kernels.techniques import TECHNIQUES

    for command in ("estimate", "verify"):
        result = cli(command, "--help")
        assert result.status == 0
        for registry in (PATTERNS, COMBINERS, TECHNIQUES):
            for entry in registry.values():
                assert f"  {entry.name} " in result.out and entry.description in result.out, (command, entry.name)


@pytest.mark.parametrize("args,needle", [
    (("info", "occluded-quad", "--receivers-file", "elsewhere.toml"), "Mitsuba"),
    (("info", "mitsuba-veach-plates", "--channel", "q"), "--channel"),
    (("info", "mitsuba-veach-plates", "--receivers-file", "no-such-receivers.toml"), "no-such-receivers.toml"),
])
def test_mitsuba_options_refuse_bad_values_in_one_line(cli, args, needle):
    """--channel and --receivers-file: a bad value, or a receivers file for a TOML scene,
    is one line and exit 2, nothing on stdout."""
    pytest.importorskip("mitsuba")
    line = _one_error_line(cli(*args))
    assert needle in line, line


def test_info_on_a_mitsuba_scene_says_channel_materials_and_spheres(cli):
    """`warpis info` on an XML scene prints its triangles, emitters (its sphere lights:
    analytic, with no tessellation error), the colour channel and each shape's material."""
    pytest.importorskip("mitsuba")
    result = cli("info", "mitsuba-veach-plates", "--channel", "g")
    assert result.status == 0, result.err
    assert re.search(r"mitsuba-veach-plates +12 +4 +16 ", result.out), result.out
    assert "colour channel g" in result.out and "roughconductor ggx alpha=0.01" in result.out
    assert result.out.count(" sphere ") >= 4 and "4 analytic sphere(s), 4 of them emitting" in result.out
    assert "irradiance error" not in result.out


# --------------------------------------------------------------------------- progress

QUICK = ["estimate", "occluded-quad", "--estimator", "independent:single:light-area", "--n", "4", "--trials", "8"]


def _bar(err: str, what: str, unit: str) -> bool:
    """Whether stderr holds a tqdm bar of ``what`` counting ``unit``: description, percent,
    bar, done/total, [elapsed<left, rate]."""
    return re.search(rf"{re.escape(what)}: +\d+%\|[^|\r\n]*\| [\d.]+[kMG]?/[\d.]+[kMG]? "
                     rf"\[\d\d:\d\d<[^,\]]*, [^\]]*{unit}/s\]", err) is not None


def test_progress_option_draws_a_tqdm_bar_on_stderr(cli):
    """`--progress` shows on stderr (not a terminal here) what runs, how far and the time
    left: the trials of `estimate`, then its reference's stages; the stages of `reference`;
    with --json too.  stdout is what it is without the option."""
    plain = cli(*QUICK)
    result = cli(*QUICK, "--progress")
    assert result.status == 0 and plain.err == "", (result.err, plain.err)
    assert result.out == plain.out
    assert _bar(result.err, "estimate", "trials"), result.err
    assert _bar(result.err, "estimate: reference, quadrature", "samples"), result.err

    result = cli(*QUICK, "--json", "--progress")
    assert json.loads(result.out)["trials"] == 8 and _bar(result.err, "estimate", "trials"), result.err

    result = cli("reference", "occluded-quad", "--receivers", "0,2", "--rel-error", "0.01", "--progress")
    assert result.status == 0 and "closed-form" in result.out
    assert _bar(result.err, "reference: closed-form test", "receivers"), result.err
    assert _bar(result.err, "reference: quadrature", "samples"), result.err


def test_no_progress_into_a_pipe():
    """Without --progress, stderr that is a pipe stays empty: a fresh process, as a script
    or a `2>log` sees it."""
    result = run_warpis(*QUICK, "--receivers", "0,1")
    assert result.status == 0 and result.err == "", result.err
    assert result.out.splitlines()[0].startswith("occluded-quad")


def test_progress_on_a_terminal_unless_json_or_quiet(cli, monkeypatch):
    """With stderr a terminal, the bar is shown by default and not with --json; --quiet
    turns it off, and wins over --progress in either order (README.md, "Commands")."""
    monkeypatch.setattr("warpis.cli._stderr_is_terminal", lambda: True)
    assert _bar(cli(*QUICK).err, "estimate", "trials")
    assert _bar(cli("reference", "occluded-quad", "--receivers", "2", "--rel-error", "0.01").err,
                "reference: quadrature", "samples")
    for extra in (["--json"], ["--quiet"], ["--quiet", "--progress"], ["--progress", "--quiet"],
                  ["--json", "--quiet", "--progress"]):
        result = cli(*QUICK, *extra)
        assert result.status == 0 and result.err == "", (extra, result.err)
