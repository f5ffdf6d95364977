"""Hostile input: nothing a user types or writes may give a wrong number with exit 0.

Two halves:

* **Scale.** F is a property of the scene's geometry, not of its units: scaling a whole
  scene by 1e-3 … 1e4, or stretching its floor ×3000 / ×30000 far beyond a small light,
  must leave every reference and every estimate where it was (to 1e-6 relative; the
  same seed gives the same random numbers, so estimates are compared sample-for-sample,
  which is deterministic, not statistical).
* **Bad input.** Every value the kernels cannot hold (counts past int32, seeds past
  2^32, floats outside float32's normal range, coordinates float32 cannot square,
  devices that do not exist, files that cannot be decoded, outputs that cannot be
  written) ends in exactly one ``warpis: error:`` line, exit status 2, no traceback and
  nothing on stdout.  The table of docs/bad-input.md lists the same classes.  The
  Python API refuses the same classes (a bool or float where a count or seed is due, a
  value that is not a scene, a non-finite array) with one-line WarpisErrors naming the
  argument (``BAD_API_CALLS``).
"""

from __future__ import annotations

import functools
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import floor_entry, light_entry, one_error_line, write_scene

import warpis
from warpis.analysis.reference import reference
from warpis.stats import variance_interval
from warpis.cli import _emit, _mean_z
from warpis.errors import WarpisError
from warpis.kernels.engine import run_moments, run_trials
from warpis.runs.verify import verify
from warpis.scenes import load_scene, resolve_scene_path

OCCLUDED_QUAD = resolve_scene_path("occluded-quad").parent
RECEIVERS = [[-1.5, 0.0, 0.0], [-0.6, 0.0, 0.0], [-0.2, 0.0, 0.0], [0.3, 0.0, 0.0], [0.7, 0.0, 0.0],
             [1.3, 0.0, 0.0], [1.7, 0.0, 0.0], [2.4, 0.0, 0.0]]
SCALE_ESTIMATORS = ("independent:single:light-solid-angle", "jittered:balance:light-area+cosine")
# Relative change of F allowed when a scene's units change (the bound).
SCALE_RTOL = 1e-6


def _scaled_occluded_quad(directory: Path, s: float) -> Path:
    """occluded-quad with every mesh and receiver scaled by ``s`` about the origin."""
    text = f"""name = "occluded-quad-x{s:g}"
[[mesh]]
path = "{OCCLUDED_QUAD / 'floor.obj'}"
transform = {{ scale = {s!r} }}
[[mesh]]
path = "{OCCLUDED_QUAD / 'light.obj'}"
emission = 10.0
transform = {{ scale = {s!r} }}
[[mesh]]
path = "{OCCLUDED_QUAD / 'box.obj'}"
transform = {{ translate = [{0.3 * s!r}, 0.0, {1.0 * s!r}], scale = [{0.8 * s!r}, {s!r}, {0.1 * s!r}], \
rotate = {{ axis = [0.0, 0.0, 1.0], degrees = 20.0 }} }}
[receivers]
points = {[[c * s for c in p] for p in RECEIVERS]!r}
normal = [0.0, 0.0, 1.0]
[material]
type = "irradiance"
"""
    path = directory / f"scaled-{s:g}.toml"
    path.write_text(text)
    return path


def _rel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(a - b) / np.maximum(np.abs(b), 1e-300)


@pytest.fixture(scope="module")
def unit_scale(tmp_path_factory) -> dict:
    scene = load_scene(_scaled_occluded_quad(tmp_path_factory.mktemp("unit"), 1.0))
    return {"refs": reference(scene),
            "means": {e: run_trials(scene, e, 16, 1000, seed=3).mean(axis=1) for e in SCALE_ESTIMATORS}}


@pytest.mark.parametrize("s", [1e-3, 1e4])
def test_scaling_a_scene_changes_no_number(s, unit_scale, tmp_path):
    """Scaled by 1e-3 or 1e4, occluded-quad keeps every reference (closed form and
    quadrature) and every estimate of the same seed within 1e-6 relative.  (The
    measured change is ~2e-7: float32 rounding of the scaled coordinates.)"""
    scene = load_scene(_scaled_occluded_quad(tmp_path, s))
    refs = reference(scene)
    assert [r.method for r in refs] == [r.method for r in unit_scale["refs"]]
    values = np.array([r.value for r in refs])
    expected = np.array([r.value for r in unit_scale["refs"]])
    assert np.all((values == 0) == (expected == 0))
    assert np.all(_rel(values, expected)[expected > 0] <= SCALE_RTOL), _rel(values, expected)
    for est in SCALE_ESTIMATORS:
        means = run_trials(scene, est, 16, 1000, seed=3).mean(axis=1)
        base = unit_scale["means"][est]
        assert np.all((means == 0) == (base == 0)), est
        assert np.all(_rel(means, base)[base > 0] <= SCALE_RTOL), (est, _rel(means, base))


def _floor_and_light(directory: Path, floor_scale: float) -> Path:
    text = f"""[[mesh]]
path = "{OCCLUDED_QUAD / 'floor.obj'}"
transform = {{ scale = [{floor_scale!r}, {floor_scale!r}, 1.0] }}
[[mesh]]
path = "{OCCLUDED_QUAD / 'light.obj'}"
emission = 10.0
[receivers]
points = [[-1.5, 0.0, 0.0], [0.0, 0.0, 0.0]]
normal = [0.0, 0.0, 1.0]
[material]
type = "irradiance"
"""
    path = directory / f"floor-x{floor_scale:g}.toml"
    path.write_text(text)
    return path


def test_a_huge_floor_does_not_move_the_receivers(tmp_path):
    """The floor of occluded-quad stretched ×3000 and ×30000 (a room in millimetres
    beside a small lamp) changes neither the closed form at the two receivers
    (0.5235598 and 1.1885848, as with the original floor; a whole-scene offset gave
    0.564 and 1.537, and 0 at ×30000) nor the estimates of the same seed."""
    base = load_scene(_floor_and_light(tmp_path, 1.0))
    expected = np.array([r.value for r in reference(base)])
    np.testing.assert_allclose(expected, [0.5235598396, 1.1885848], rtol=1e-6)
    base_means = run_trials(base, "jittered:balance:light-area+cosine", 16, 1000, seed=5).mean(axis=1)
    for stretch in (3000.0, 30000.0):
        scene = load_scene(_floor_and_light(tmp_path, stretch))
        refs = reference(scene)
        assert [r.method for r in refs] == ["closed-form", "closed-form"]
        np.testing.assert_allclose([r.value for r in refs], expected, rtol=1e-12)
        means = run_trials(scene, "jittered:balance:light-area+cosine", 16, 1000, seed=5).mean(axis=1)
        assert np.all(_rel(means, base_means) <= SCALE_RTOL), (stretch, means, base_means)


# --------------------------------------------------------------------------- bad input: options

EST = ["estimate", "occluded-quad", "--estimator", "independent:single:light-area", "--n", "4", "--trials", "8"]


def _with(args: list[str], option: str, value: str) -> list[str]:
    out = list(args)
    out[out.index(option) + 1] = value
    return out


BAD_OPTIONS = {
    "N wraps int32 to 1": (_with(EST, "--n", "4294967297"), "--n"),
    "N wraps int32 to a negative": (_with(EST, "--n", "3000000000"), "--n"),
    "N written as a float": (_with(EST, "--n", "1e18"), "--n"),
    "trials past int32": (_with(EST, "--trials", "4000000000"), "--trials"),
    "receiver past int64": (EST + ["--receivers", "99999999999999999999"], "--receivers"),
    "receiver that does not exist": (EST + ["--receivers", "0,8"], "receiver"),
    "negative receiver": (EST + ["--receivers", "-1"], "--receivers"),
    "fractional seed": (EST + ["--seed", "1.9"], "--seed"),
    "seed past 2^32": (EST + ["--seed", "4294967296"], "--seed"),
    "seed far past 2^63": (EST + ["--seed", "99999999999999999999999"], "--seed"),
    "reference samples past int32": (["reference", "occluded-quad", "--samples", "3000000000"], "--samples"),
    "cuda without a GPU": (["info", "occluded-quad", "--device", "cuda"], "--device"),
    "cuda device that does not exist": (["info", "occluded-quad", "--device", "cuda:7"], "--device"),
    "unknown device": (["info", "occluded-quad", "--device", "tpu"], "--device"),
    "jittered grid finer than float32": (_with(_with(EST, "--n", "2147483647"), "--estimator",
                                               "jittered:single:cosine"), "float32"),
    "--progress given a value": (EST + ["--progress=yes"], "--progress"),
    "--quiet given a value": (["reference", "occluded-quad", "--quiet=1"], "--quiet"),
    "--progress on a command that has none": (["info", "occluded-quad", "--progress"], "--progress"),
}


@pytest.mark.parametrize("case", list(BAD_OPTIONS))
def test_bad_option_is_one_line(case, cli):
    args, names = BAD_OPTIONS[case]
    line = one_error_line(cli(*args))
    assert names in line, line


def test_stdout_that_cannot_be_written_is_one_line():
    """`warpis info … > /dev/full`: one line, exit 2, no traceback (stdout is full)."""
    with open("/dev/full", "w") as full:
        proc = subprocess.run([sys.executable, "-m", "warpis.cli", "info", "occluded-quad", "--json"],
                              stdout=full, stderr=subprocess.PIPE, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == ["warpis: error: standard output: cannot write: No space left on device"]


def test_a_mean_off_a_reference_without_spread_is_not_z_zero(cli, tmp_path):
    """Cosine sampling never meets a light of 4e-6 sr in 8 × 4 samples: mean 0 and stderr 0
    against a closed form of 4e-5 with stderr 0.  The table's z is -inf (it was 0.00), the
    JSON's z null and agrees false.  An umbra (0 against 0) keeps z = 0 and agrees, and
    every other z is (mean − reference)/√(stderr² + ref stderr²)."""
    path = write_scene(tmp_path, meshes=[floor_entry(), light_entry(height=10.0, half=0.01)])
    args = ["estimate", path, "--estimator", "independent:single:cosine", "--n", "4", "--trials", "8"]
    result = cli(*args)
    assert result.status == 0, result.err
    row = result.out.splitlines()[2].split()
    assert row[1] == "0" and row[-1] == "-inf", row
    data = json.loads(cli(*args, "--json").out)["receivers"][0]
    assert (data["mean"], data["stderr"], data["reference_stderr"]) == (0.0, 0.0, 0.0) and data["reference"] > 0
    assert data["z"] is None and data["agrees"] is False
    quad = json.loads(cli(*EST, "--json", "--receivers", "3,4,0").out)["receivers"]
    assert [(r["mean"], r["reference"], r["z"], r["agrees"]) for r in quad[:2]] == [(0.0, 0.0, 0.0, True)] * 2
    r = quad[2]
    z = (r["mean"] - r["reference"]) / math.hypot(r["stderr"], r["reference_stderr"])
    assert r["z"] == pytest.approx(z, rel=1e-12) and r["agrees"] == (abs(z) <= 1.959963984540054)
    assert _mean_z(1.0, 0.0, 0.5, 0.0) == (math.inf, False) and _mean_z(0.5, 0.0, 1.0, 0.0) == (-math.inf, False)


def test_no_nan_or_infinity_is_ever_printed():
    """A non-finite number reaching the output is an error naming its field, never a bare
    NaN token in JSON or 'nan' in a table."""
    for bad in (float("nan"), float("inf")):
        with pytest.raises(WarpisError, match=r"output\.receivers\[1\]\.mean"):
            _emit({"receivers": [{"mean": 1.0}, {"mean": bad}]}, True, "")


# --------------------------------------------------------------------------- bad input: scene files


def _mesh(**keys) -> list[dict]:
    return [floor_entry(), light_entry(**keys)]


BAD_SCENES = {
    # float32 range: radiance, albedo and exponent are float32 in the kernels.
    "emission overflows float32": ({"meshes": _mesh(emission=1e39)}, "emission"),
    "emission is subnormal in float32": ({"meshes": _mesh(emission=1e-45)}, "emission"),
    "albedo overflows float32": ({"material": {"type": "lambert", "albedo": 1e39}}, "albedo"),
    "phong exponent overflows float32": ({"material": {"type": "phong", "albedo": 0.5, "exponent": 1e39,
                                                       "view": [0, 0, 1]}}, "exponent"),
    # coordinates float32 cannot square
    "translate of 1e30": ({"meshes": _mesh(transform={"translate": [1e30, 0.0, 0.0]})}, "coordinate"),
    "scale of 1e30": ({"meshes": _mesh(transform={"scale": 1e30})}, "coordinate"),
    "vertex at 1e30": ({"meshes": [floor_entry(), {**light_entry(), "vertices": np.array(
        [[-0.5, -0.5, 1.0], [-0.5, 0.5, 1.0], [1e30, 0.5, 1.0], [0.5, -0.5, 1.0]])}]}, "coordinate"),
    "light too small for float32 areas": ({"meshes": _mesh(transform={"scale": 1e-20})}, "rescale"),
    "receiver at 1e30": ({"receivers": {"points": [[1e30, 0.0, 0.0]], "normal": [0, 0, 1]}}, "coordinate"),
    # receiver counts the kernels cannot index or memory cannot hold
    "grid of 1e10 receivers": ({"receivers": {"grid": {"origin": [0, 0, 0], "edge_u": [1, 0, 0],
                                                        "edge_v": [0, 1, 0], "resolution": [100000, 100000]}}},
                               "receivers"),
    "grid larger than memory": ({"receivers": {"grid": {"origin": [0, 0, 0], "edge_u": [1, 0, 0],
                                                         "edge_v": [0, 1, 0], "resolution": [40000, 40000]}}},
                                "GiB"),
    # keys that must be strings
    "mesh name not a string": ({"meshes": [floor_entry(name=5), light_entry()]}, "name"),
    "description not a string": ({"extra": {"description": 5}}, "description"),
}


@pytest.mark.parametrize("case", list(BAD_SCENES))
def test_bad_scene_is_one_line(case, cli, tmp_path):
    keys, word = BAD_SCENES[case]
    path = write_scene(tmp_path, **keys)
    line = one_error_line(cli("info", path))
    assert str(path.parent) in line and word in line, line  # the scene file or the mesh it names


def test_deeply_nested_toml_is_one_line(cli, tmp_path):
    """TOML nested 50,000 deep (Python's parser recurses) in a scene file."""
    path = tmp_path / "deep.toml"
    path.write_text("a = " + "[" * 50_000 + "]" * 50_000 + "\n")
    line = one_error_line(cli("info", path))
    assert "nested too deeply" in line, line


def test_latin1_comment_in_an_obj_loads(tmp_path):
    """A valid OBJ with a Latin-1 comment loads (trimesh alone would need the optional
    charset_normalizer) with the same geometry as without the comment."""
    plain = load_scene(write_scene(tmp_path / "plain"))
    light = (tmp_path / "plain" / "light.obj").read_bytes()
    entry = {k: v for k, v in light_entry().items() if k not in ("vertices", "faces")}
    path = write_scene(tmp_path / "latin1", meshes=[floor_entry(), {**entry, "content": b"# caf\xe9 \xa9\n" + light}])
    scene = load_scene(path)
    np.testing.assert_array_equal(scene.vertices, plain.vertices)
    np.testing.assert_array_equal(scene.triangles, plain.triangles)


def test_api_rejects_a_device_that_does_not_exist():
    """load_scene refuses an unknown device by name (the counts, seeds and receivers of
    run_trials/run_moments are held in tests/test_streaming.py)."""
    for device in ("tpu", "cuda:7", "CPU"):
        with pytest.raises(WarpisError, match="device"):
            warpis.load_scene("occluded-quad", device=device)


# --------------------------------------------------------------------------- bad input: the Python API

LIGHT_AREA = "independent:single:light-area"


@functools.cache
def _quad() -> warpis.Scene:
    return load_scene("occluded-quad")


SEED_TRUE = r"^seed: expected an integer in \[0, 2\^32\), got True$"
BAD_API_CALLS = {
    "receivers a bool": (lambda: run_trials(_quad(), LIGHT_AREA, 4, 8, receivers=True), r"^receivers: expected"),
    "receivers a string": (lambda: run_moments(_quad(), LIGHT_AREA, 4, 8, receivers="0,1"), r"^receivers: expected"),
    "receivers a float": (lambda: reference(_quad(), receivers=2.0), r"^receivers: expected receiver indices"),
    "one receiver that does not exist": (lambda: run_moments(_quad(), LIGHT_AREA, 4, 8, receivers=8),
                                         r"^receivers: receiver 8 does not exist"),
    "scene of the wrong type": (lambda: run_trials(5, LIGHT_AREA, 4, 8), r"^scene: expected a Scene, a bundled"),
    "reference of no scene": (lambda: reference(None), r"^scene: expected a Scene"),
    "scene name that does not exist": (lambda: run_moments("no-such-scene", LIGHT_AREA, 4, 8),
                                       r"^no-such-scene: no such scene file or bundled scene"),
    "run_trials seed=True": (lambda: run_trials(_quad(), LIGHT_AREA, 4, 8, seed=True), SEED_TRUE),
    "run_moments seed=True": (lambda: run_moments(_quad(), LIGHT_AREA, 4, 8, seed=True), SEED_TRUE),
    "reference seed=True": (lambda: reference(_quad(), seed=True), SEED_TRUE),
    "verify seed=True": (lambda: verify(_quad(), estimators=[LIGHT_AREA], n_values=[4], trials=8, seed=True),
                         SEED_TRUE),
    "verify trials a float": (lambda: verify(_quad(), estimators=[LIGHT_AREA], n_values=[4], trials=8.0),
                              r"^trials: expected an integer, got 8.0$"),
    "n a bool": (lambda: run_trials(_quad(), LIGHT_AREA, True, 8), r"^n: expected an integer, got True$"),
    "trials a float": (lambda: run_moments(_quad(), LIGHT_AREA, 4, 8.0), r"^trials: expected an integer, got 8.0$"),
    "threads a bool": (lambda: run_trials(_quad(), LIGHT_AREA, 4, 8, threads=True), r"^threads: expected an integer"),
    "progress not callable": (lambda: run_trials(_quad(), LIGHT_AREA, 4, 8, progress=5), r"^progress: expected a"),
    "variance_interval of one trial": (lambda: variance_interval([1.0]),
                                       r"^estimates: a variance interval needs at least 2 trials"),
    "variance_interval with a NaN": (lambda: warpis.variance_interval([1.0, math.nan, 2.0]),
                                     r"^estimates\[1\]: nan is not a finite number"),
    "variance_interval with an infinity": (lambda: variance_interval([[1.0, 2.0], [3.0, -math.inf]]),
                                           r"^estimates\[1, 1\]: -inf is not a finite number"),
    "variance_interval of strings": (lambda: variance_interval(["a", "b"]), r"^estimates: expected an array of real"),
    "variance_interval of a ragged list": (lambda: variance_interval([[1.0, 2.0], [3.0]]),
                                           r"^estimates: expected an array of real"),
    "variance_interval of one number": (lambda: variance_interval(3.0), r"^estimates: expected an array of trials"),
    "variance_interval at level 2": (lambda: variance_interval([1.0, 2.0, 3.0], level=2), r"^level: .* got 2$"),
    "variance_interval at level True": (lambda: variance_interval([1.0, 2.0, 3.0], level=True), r"^level: .* True$"),
    "variance_interval on an axis it lacks": (lambda: variance_interval([1.0, 2.0, 3.0], axis=1), r"^axis: .* axis 1"),
}


@pytest.mark.parametrize("case", list(BAD_API_CALLS))
def test_bad_api_call_is_one_line(case):
    """Each bad argument of the Python API is a WarpisError of one line naming the
    argument (never a TypeError, AttributeError, ValueError or a silent NaN)."""
    call, match = BAD_API_CALLS[case]
    with pytest.raises(WarpisError, match=match) as info:
        call()
    assert "\n" not in str(info.value)


def test_api_takes_one_receiver_and_a_scene_by_name():
    """One integer is one receiver, and a bundled scene's name or a scene file's path is
    loaded as load_scene loads it: the same numbers as a list and a loaded scene."""
    expected = run_trials(_quad(), LIGHT_AREA, 4, 16, seed=2, receivers=[1])
    np.testing.assert_array_equal(run_trials("occluded-quad", LIGHT_AREA, 4, 16, seed=2, receivers=1), expected)
    moments = run_moments(resolve_scene_path("occluded-quad"), LIGHT_AREA, 4, 16, seed=2, receivers=np.int64(1))
    np.testing.assert_allclose(moments.mean, expected.mean(axis=1), rtol=1e-12)
    assert reference("occluded-quad", receivers=0) == reference(_quad(), receivers=[0])


def test_a_non_finite_estimate_stops_the_run():
    """Radiance past float32 slipped in through the Python API (the loaders refuse it):
    the first infinite or NaN estimate stops run_trials and run_moments with one line,
    instead of feeding NaN into every figure."""
    from dataclasses import replace

    from warpis.kernels.engine import run_moments

    scene = warpis.load_scene("occluded-quad")
    scene = replace(scene, emission=np.where(scene.emission > 0, 3e38, 0.0))  # unchecked, unlike from_arrays
    for run in (run_trials, run_moments):
        with pytest.raises(WarpisError, match=r"gave (inf|nan).*nothing is reported"):
            run(scene, "independent:single:uniform", 16, 256, receivers=[0])  # f/pdf = 3e38·2π·cos: inf
