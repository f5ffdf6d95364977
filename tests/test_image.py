"""Tests of ``warpis image`` (warpis/runs/image.py and cli.cmd_image): the files it writes,
the statistics of its images against the reference and the exact prediction, results that
do not depend on threads or tiles, resuming from finished tiles, and bad input.

Most runs use a small written camera scene (a lambert floor, a phong plate, a quad
light the camera sees from above) at 24×18 pixels; the pictures are not drawn there
(tests/test_image_report.py covers them), except in the command-line run on the bundled
veach-plates-camera.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

import warpis
from conftest import one_error_line, write_scene
from warpis.stats import sidak_threshold
from warpis.errors import WarpisError
from warpis.kernels.engine import run_trials
from warpis.kernels.estimators import parse_estimator
from warpis.runs import image as image_run
from warpis.runs import image_report
from warpis.runs.image import ImageRun, _winner, run_image

SINGLE = "jittered:single:light-area"
BALANCE = "jittered:balance:light-solid-angle+bsdf"
SPECS = (SINGLE, BALANCE)
PER_ESTIMATOR = ("mean", "mean_stderr", "single", "variance", "variance_lo", "variance_hi", "predicted",
                 "predicted_stderr", "ratio", "rel_error", "cost", "efficiency", "relative_efficiency")
TIMED = ("cost", "efficiency", "relative_efficiency")  # from measured seconds: never compared bit for bit


# --------------------------------------------------------------------------- scenes and runs


def rect(origin, eu, ev) -> tuple[np.ndarray, np.ndarray]:
    """A parallelogram origin + s·eu + t·ev as two triangles; its front normal is eu × ev."""
    o, eu, ev = (np.asarray(x, float) for x in (origin, eu, ev))
    return np.array([o, o + eu, o + eu + ev, o + ev]), np.array([[0, 1, 2], [0, 2, 3]])


def entry(path: str, shape, **keys) -> dict:
    return {"path": path, "vertices": shape[0], "faces": shape[1], **keys}


def image_scene(directory: Path, light_facing: str = "down", width: int = 24, height: int = 18) -> Path:
    """A lambert floor, a phong (exponent 20) plate leaning back, and a 1×1 light at z = 2
    (facing down, or up: then no pixel gets any light), seen from above and in front."""
    eu, ev = ([1, 0, 0], [0, -1, 0]) if light_facing == "down" else ([1, 0, 0], [0, 1, 0])
    meshes = [entry("floor.obj", rect([-2, -2, 0], [4, 0, 0], [0, 4, 0]), material={"type": "lambert", "albedo": 0.7}),
              entry("plate.obj", rect([-1.5, 1.0, 0.2], [3, 0, 0], [0, 0.4, 1.2]),
                    material={"type": "phong", "exponent": 20.0}),
              entry("light.obj", rect([-0.5, 0.5 if light_facing == "down" else -0.5, 2.0], eu, ev), emission=10.0)]
    camera = {"position": [0.0, -4.0, 3.5], "target": [0.0, 0.0, 0.5], "fov": 45.0, "width": width, "height": height}
    return write_scene(directory, meshes=meshes, receivers={"camera": camera}, material=None)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> warpis.Scene:
    return warpis.load_scene(image_scene(tmp_path_factory.mktemp("image-scene")), camera=True)


@pytest.fixture
def no_pictures(monkeypatch):
    """Skip the PNGs, EXR and page (seconds of matplotlib); the numbers are still written."""
    for name in ("write_pictures", "write_exr", "write_index"):
        monkeypatch.setattr(image_report, name, lambda *args, **kwargs: [])


def image(scene: warpis.Scene, out: Path, specs=SPECS, n: int = 4, trials: int = 16, seed: int = 0,
          points: int = 256, threads: int | None = 2, baseline: int = 0) -> image_run.ImageResult:
    run = ImageRun(scene, tuple(parse_estimator(s) for s in specs), n, trials, seed=seed, baseline=baseline, points=points,
                   threads=threads)
    return run_image(run, out)


def untimed(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The arrays that depend on nothing but the run's inputs (no measured times)."""
    return {k: v for k, v in arrays.items() if k != "winner" and not k.startswith(TIMED)}


def assert_same(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k], equal_nan=True), k


def measure_tiles(out: Path) -> list[Path]:
    """The tile files under OUT/tiles that hold measured moments (not the reference or predictions)."""
    tiles = []
    for path in sorted((out / "tiles").glob("*.npz")):
        with np.load(path) as data:
            if "count" in data.files:
                tiles.append(path)
    return tiles


# --------------------------------------------------------------------------- the command line

CLI_ARGS = ["image", "veach-plates-camera", "--estimator", "jittered:single:light-solid-angle", "--estimator",
            BALANCE, "--n", "4", "--trials", "8", "--width", "16", "--height", "12", "--baseline", BALANCE,
            "--prediction-points", "512", "--json"]


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory) -> dict:
    """`warpis image` on veach-plates-camera at 16×12, run once: status, output, the folder."""
    from warpis.cli import main

    out = tmp_path_factory.mktemp("cli") / "out"
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        status = main([*CLI_ARGS, "--out", str(out)])
    with np.load(out / "image.npz") as data:
        arrays = {k: data[k] for k in data.files}
    return {"status": status, "out": out, "stdout": stdout.getvalue(), "stderr": stderr.getvalue(),
            "arrays": arrays}


def test_cli_writes_the_page_and_the_numbers(cli_run):
    """Exit 0; index.html, image.npz, image.json and the pictures are written; --json is
    the run's meta (the same as image.json), describing the run asked for."""
    assert cli_run["status"] == 0, cli_run["stderr"]
    out = cli_run["out"]
    for name in ("index.html", "image.npz", "image.json", "mean.png", "variance.png"):
        assert (out / name).is_file(), name
    meta = json.loads(cli_run["stdout"])
    assert meta == json.loads((out / "image.json").read_text())
    assert meta["estimators"] == ["jittered:single:light-solid-angle", BALANCE]
    assert (meta["baseline"], meta["n"], meta["trials"], meta["width"], meta["height"]) == (1, 4, 8, 16, 12)
    mask = cli_run["arrays"]["mask"]
    assert meta["receivers"] == int((mask == 0).sum()) > 0
    assert meta["masked"] == {"nothing": int((mask == 1).sum()), "emitter": int((mask == 2).sum()),
                              "back": int((mask == 3).sum()), "unshaded": int((mask == 4).sum())}
    assert [row["estimator"] for row in meta["summary"]] == meta["estimators"]
    assert all(row["predicted_pixels"] == meta["receivers"] for row in meta["summary"])
    # The baseline beats itself nowhere and is at 1 across its pixels; the page shows the same columns.
    base = meta["summary"][1]
    assert base["beats_baseline_share"] == 0 and base["relative_efficiency_p05"] == base["relative_efficiency_p95"] == 1
    page = (out / "index.html").read_text()
    assert "pixels where it beats the baseline" in page and "5th – 95th percentile" in page
    assert "Traceback" not in cli_run["stderr"]


def test_cli_arrays_are_images_masked_with_nan(cli_run):
    """image.npz holds mask, reference, reference_stderr, the 13 images of each estimator
    and winner, all 12×16; every float image is NaN exactly at the masked pixels; the
    mask is the scene's; winner is −1 at masked pixels and an estimator's index elsewhere."""
    arrays = cli_run["arrays"]
    want = {"mask", "reference", "reference_stderr", "winner"} | {f"{k}_{i}" for k in PER_ESTIMATOR for i in (0, 1)}
    assert set(arrays) == want
    mask = arrays["mask"]
    assert mask.dtype == np.int8 and mask.shape == (12, 16)
    scene = warpis.load_scene("veach-plates-camera", camera=True, width=16, height=12)
    np.testing.assert_array_equal(mask, scene.receivers.image.seen)
    masked = mask != 0
    for name, a in arrays.items():
        assert a.shape == (12, 16), name
        if a.dtype.kind == "f":
            assert np.isnan(a[masked]).all(), name
            if name.startswith(("ratio", "rel_error", "relative_efficiency")):
                continue  # 0/0 where a pixel gets no light
            assert not np.isnan(a[~masked]).any(), name
    winner = arrays["winner"]
    assert winner.dtype == np.int16 and (winner[masked] == -1).all() and set(np.unique(winner[~masked])) <= {-1, 0, 1}


def test_cli_derived_images(cli_run):
    """efficiency = 1/(variance × cost); ratio = variance/predicted; rel_error =
    √variance/|reference|; relative efficiency is efficiency over the baseline's (here the
    second estimator: 1 where defined); winner is the most efficient estimator."""
    a = cli_run["arrays"]
    ok = a["mask"] == 0
    with np.errstate(divide="ignore", invalid="ignore"):
        for i in (0, 1):
            np.testing.assert_allclose(a[f"efficiency_{i}"][ok], 1 / (a[f"variance_{i}"][ok] * a[f"cost_{i}"][ok]),
                                       rtol=1e-12)
            np.testing.assert_allclose(a[f"ratio_{i}"][ok], a[f"variance_{i}"][ok] / a[f"predicted_{i}"][ok],
                                       rtol=1e-12)
            np.testing.assert_allclose(a[f"rel_error_{i}"][ok], np.sqrt(a[f"variance_{i}"][ok]) /
                                       np.abs(a["reference"][ok]), rtol=1e-12)
            assert (a[f"cost_{i}"][ok] > 0).all()
            assert (a[f"variance_lo_{i}"][ok] <= a[f"variance_{i}"][ok]).all()
            assert (a[f"variance_{i}"][ok] <= a[f"variance_hi_{i}"][ok]).all()
        base = a["efficiency_1"][ok]
        defined = np.isfinite(base) & (base > 0)
        assert defined.sum() > 0
        np.testing.assert_array_equal(a["relative_efficiency_1"][ok][defined], 1.0)
        np.testing.assert_allclose(a["relative_efficiency_0"][ok][defined],
                                   a["efficiency_0"][ok][defined] / base[defined], rtol=1e-12)
        eff = np.stack([a["efficiency_0"][ok], a["efficiency_1"][ok]])
    np.testing.assert_array_equal(a["winner"][ok], _winner(eff))


# --------------------------------------------------------------------------- statistics


def test_mean_agrees_with_the_reference_and_variance_with_the_prediction(scene, tmp_path, no_pictures):
    """At M = 1024 trials, per unmasked pixel and estimator:

    * z = (mean − reference)/√(mean_stderr² + reference_stderr²): max |z| stays below the
      Šidák threshold for a family-wise false-failure rate of 1e-3 over all pixels ×
      estimators (normal tails: at M = 1024 the t-statistic's tails and the skew of these
      bounded estimates move it by far less than the margin); mean(z) within ±0.35 and
      sd(z) within [0.8, 1.25] (over ~240 pixels, ≥ 5 and ≥ 4 standard errors away; a
      skewed estimate's t-statistic has mean about −skewness/(2√M), ≈ −0.1 here);
    * the prediction lies in the measured 95% interval, widened by two of the prediction's
      standard errors, at ≥ 85% of pixels (the expectation is ≥ 95%; 85% is 7 binomial
      standard errors below it), and the median measured/predicted ratio is within
      [0.9, 1.1] (its spread at M = 1024 with a few per cent of prediction error is ~1%).

    Guards against a biased mean, a misplaced pixel, a wrong standard error and a
    variance or prediction at the wrong scale or the wrong pixel."""
    result = image(scene, tmp_path / "out", trials=1024, points=4096, seed=3)
    a = result.arrays
    ok = a["mask"] == 0
    runs = 2 * int(ok.sum())
    z_max = stats.norm.isf(sidak_threshold(1e-3, runs) / 2)
    for i, spec in enumerate(SPECS):
        mean, se = a[f"mean_{i}"][ok], a[f"mean_stderr_{i}"][ok]
        ref, ref_se = a["reference"][ok], a["reference_stderr"][ok]
        dark = (se == 0) & (ref_se == 0)
        np.testing.assert_array_equal(mean[dark], ref[dark])  # no light: exactly 0 on both sides
        z = (mean - ref)[~dark] / np.hypot(se, ref_se)[~dark]
        assert np.abs(z).max() < z_max, (spec, np.abs(z).max(), z_max)
        assert abs(z.mean()) < 0.35, (spec, z.mean())
        assert 0.8 < z.std() < 1.25, (spec, z.std())
        pred, pred_se = a[f"predicted_{i}"][ok], a[f"predicted_stderr_{i}"][ok]
        lo, hi, var = a[f"variance_lo_{i}"][ok], a[f"variance_hi_{i}"][ok], a[f"variance_{i}"][ok]
        assert np.isfinite(pred).all()
        lit = pred > 0
        inside = (pred >= lo - 2 * pred_se) & (pred <= hi + 2 * pred_se)
        assert inside[lit].mean() >= 0.85, (spec, inside[lit].mean())
        assert 0.9 <= np.median(var[lit] / pred[lit]) <= 1.1, (spec, np.median(var[lit] / pred[lit]))
        # Seconds per estimate: M estimates at every pixel cannot have taken more CPU time than
        # the whole run had on every core.
        assert 0 < a[f"cost_{i}"][ok].sum() * 1024 <= result.meta["seconds"] * os.cpu_count()
        row = result.meta["summary"][i]
        assert row["median_ratio"] == pytest.approx(np.median(a[f"ratio_{i}"][ok][lit]), rel=1e-12)


def test_mean_and_single_are_the_measured_trials_at_each_pixel(scene, tmp_path, no_pictures):
    """mean_i at each receiver's pixel is the mean of run_trials' M trials there, and
    single_i is trial 0 of that same stream: guards against images placed at the wrong
    pixels, a different seed or stream for the single render, and lost trials."""
    result = image(scene, tmp_path / "out", trials=24, seed=5, points=0)
    pixel = scene.receivers.image.pixel
    for i, spec in enumerate(SPECS):
        trials = run_trials(scene, spec, 4, 24, seed=5)
        np.testing.assert_allclose(result.arrays[f"mean_{i}"].ravel()[pixel], trials.mean(axis=1), rtol=1e-12,
                                   atol=1e-300)
        np.testing.assert_array_equal(result.arrays[f"single_{i}"].ravel()[pixel], trials[:, 0])
        np.testing.assert_allclose(result.arrays[f"variance_{i}"].ravel()[pixel], trials.var(axis=1, ddof=1),
                                   rtol=1e-9, atol=1e-300)
    assert np.isnan(result.arrays["predicted_0"]).all()  # --prediction-points 0: no predictions
    assert result.meta["prediction"] == "no predictions (--prediction-points 0)"


# --------------------------------------------------------------------------- determinism


def test_results_do_not_depend_on_threads_or_tiles(scene, tmp_path, monkeypatch, no_pictures):
    """Every array but the timed ones is bit-identical with 1 or 2 threads and with tiles of
    1024 or 7 receivers (tiles then split the image mid-row, dozens of them)."""
    one = image(scene, tmp_path / "one", threads=1)
    two = image(scene, tmp_path / "two", threads=2)
    monkeypatch.setattr(image_run, "TILE", 7)
    tiled = image(scene, tmp_path / "tiled", threads=2)
    assert (one.computed, tiled.computed) == (2, 2 * math.ceil(len(scene.receivers) / 7))
    assert_same(untimed(one.arrays), untimed(two.arrays))
    assert_same(untimed(one.arrays), untimed(tiled.arrays))
    assert np.isfinite(one.arrays["predicted_1"][one.arrays["mask"] == 0]).all()


# --------------------------------------------------------------------------- resuming


@pytest.fixture
def small_tiles(monkeypatch):
    """Tiles of 40 receivers: several per estimator."""
    monkeypatch.setattr(image_run, "TILE", 40)
    return 40


def test_an_interrupted_image_resumes_from_its_finished_tiles(scene, tmp_path, monkeypatch, small_tiles,
                                                              no_pictures):
    """A KeyboardInterrupt after 5 tiles leaves those 5 saved; the rerun reuses them,
    computes the rest, and its numbers equal those of an uninterrupted run."""
    total = 2 * math.ceil(len(scene.receivers) / small_tiles)
    real = image_run._measure
    calls = []

    def measure_then_stop(*args, **kwargs):
        if len(calls) == 5:
            raise KeyboardInterrupt
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(image_run, "_measure", measure_then_stop)
    with pytest.raises(KeyboardInterrupt):
        image(scene, tmp_path / "out")
    assert len(measure_tiles(tmp_path / "out")) == 5
    assert not (tmp_path / "out" / "image.npz").exists()
    monkeypatch.setattr(image_run, "_measure", real)
    resumed = image(scene, tmp_path / "out")
    assert (resumed.reused, resumed.computed) == (5, total - 5)
    fresh = image(scene, tmp_path / "fresh")
    assert (fresh.reused, fresh.computed) == (0, total)
    assert_same(untimed(resumed.arrays), untimed(fresh.arrays))


def test_deleted_tiles_are_computed_again_and_the_rest_reused(scene, tmp_path, small_tiles, no_pictures):
    """After a finished run, deleting 3 tile files and rerunning computes exactly those 3;
    a rerun with nothing deleted computes nothing; the numbers never change, and the
    reused tiles keep their measured cost."""
    first = image(scene, tmp_path / "out")
    again = image(scene, tmp_path / "out")
    assert (again.computed, again.reused) == (0, first.computed)
    assert_same(first.arrays, again.arrays)  # everything read back, times included
    tiles = measure_tiles(tmp_path / "out")
    assert len(tiles) == first.computed
    for path in tiles[:3]:
        path.unlink()
    third = image(scene, tmp_path / "out")
    assert (third.computed, third.reused) == (3, first.computed - 3)
    assert_same(untimed(first.arrays), untimed(third.arrays))


def test_another_runs_tiles_are_never_read(scene, tmp_path, small_tiles, no_pictures):
    """In the same --out, a different seed or N computes every tile anew (and its numbers,
    predictions included, are those of a fresh run); a tile file holding another run's
    numbers under this run's file name is not read either."""
    out = tmp_path / "out"
    base = image(scene, out, seed=0)
    before = set(measure_tiles(out))
    other = image(scene, out, seed=1)
    assert (other.reused, other.computed) == (0, base.computed)
    assert_same(untimed(other.arrays), untimed(image(scene, tmp_path / "fresh", seed=1).arrays))
    other_tiles = sorted(set(measure_tiles(out)) - before)
    assert len(other_tiles) == base.computed
    eight = image(scene, out, n=8)
    assert eight.reused == 0
    assert_same(untimed(eight.arrays), untimed(image(scene, tmp_path / "fresh-8", n=8).arrays))  # predictions too
    # Seed 1's numbers copied over seed 0's files: the key inside differs, so they are recomputed.
    for mine, theirs in zip(sorted(before), other_tiles):
        shutil.copyfile(theirs, mine)
    again = image(scene, out, seed=0)
    assert (again.reused, again.computed) == (0, base.computed)
    assert_same(untimed(again.arrays), untimed(base.arrays))


@pytest.mark.parametrize("damage", ["truncated", "garbage", "empty"])
def test_a_damaged_tile_is_computed_again(scene, tmp_path, small_tiles, no_pictures, damage):
    """A tile file cut short by a kill, overwritten with junk, or empty is computed again
    (never an error), and the numbers are unchanged."""
    first = image(scene, tmp_path / "out")
    path = measure_tiles(tmp_path / "out")[2]
    data = path.read_bytes()
    path.write_bytes({"truncated": data[: len(data) // 2], "garbage": b"\x00not a zip" * 50, "empty": b""}[damage])
    again = image(scene, tmp_path / "out")
    assert (again.computed, again.reused) == (1, first.computed - 1)
    assert_same(untimed(first.arrays), untimed(again.arrays))


# --------------------------------------------------------------------------- units


def test_winner_picks_the_single_most_efficient_estimator():
    """_winner: the index of the largest efficiency; NaN counts as nothing; one infinite
    efficiency (zero variance) wins; −1 where all are NaN, where several tie at the top
    (several infinite included)."""
    nan, inf = math.nan, math.inf
    eff = np.array([[1.0, 3.0, nan, inf, inf, 2.0, nan, 5.0, 0.0],
                    [2.0, 1.0, nan, 7.0, inf, 2.0, 4.0, nan, 0.0],
                    [0.5, 2.0, nan, 1.0, 1.0, 1.0, 3.0, 1.0, 0.0]])
    got = _winner(eff)
    assert got.dtype == np.int16
    np.testing.assert_array_equal(got, [1, 0, -1, 0, -1, -1, 1, 0, -1])
    np.testing.assert_array_equal(_winner(np.array([[nan, 2.0]])), [-1, 0])  # one estimator
    np.testing.assert_array_equal(_winner(np.full((2, 3), nan)), [-1, -1, -1])


def test_relative_efficiency_of_the_baseline_is_one(scene, tmp_path, no_pictures):
    """With --baseline the second estimator, its relative efficiency is 1 wherever its
    efficiency is finite and positive, the other's is their quotient, and the summary's
    median relative efficiency is the baseline's 1."""
    result = image(scene, tmp_path / "out", baseline=1, points=0)
    a = result.arrays
    ok = a["mask"] == 0
    base = a["efficiency_1"][ok]
    defined = np.isfinite(base) & (base > 0)
    assert defined.sum() > 0.9 * ok.sum()
    np.testing.assert_array_equal(a["relative_efficiency_1"][ok][defined], 1.0)
    np.testing.assert_allclose(a["relative_efficiency_0"][ok][defined],
                               a["efficiency_0"][ok][defined] / base[defined], rtol=1e-12)
    assert result.meta["summary"][1]["median_relative_efficiency"] == 1.0
    assert result.meta["baseline"] == 1


# --------------------------------------------------------------------------- bad input


def image_args(scene_path: Path, out: Path, *extra: str, estimators=SPECS, n: str = "4") -> list[str]:
    args = ["image", str(scene_path)]
    for spec in estimators:
        args += ["--estimator", spec]
    return [*args, "--n", n, "--trials", "8", "--out", str(out), *extra]


@pytest.mark.parametrize("change, words", [
    ({"estimators": (SINGLE, SINGLE)}, f"--estimator: {SINGLE!r} is given twice"),
    ({"extra": ("--baseline", "independent:single:bsdf")}, "--baseline: 'independent:single:bsdf' is not one of"),
    ({"extra": ("--baseline", "nonsense")}, "nonsense"),
    ({"extra": ("--trials", "3")}, "--trials must be at least"),
    ({"estimators": ("jittered:single:light-area", "jittered:balance:light-area+bsdf"), "n": "5"},
     "N = 5 is not divisible by its 2 techniques"),
    ({"extra": ("--prediction-points", "-1")}, "--prediction-points"),
    ({"extra": ("--prediction-points", "many")}, "--prediction-points"),
    ({"estimators": ("jittered:single:no-such-technique",)}, "no-such-technique"),
    ({"extra": ("--n", "0")}, "--n"),
    ({"extra": ("--width", "0")}, "--width"),
    ({"extra": ("--threads", "0")}, "--threads"),
    ({"extra": ("--seed", "-1")}, "--seed"),
])
def test_bad_image_options_are_one_line_and_write_nothing(tmp_path, cli, change, words):
    """Each bad option: exit 2, one `warpis: error:` line saying what is wrong, and no
    --out folder at all."""
    path = image_scene(tmp_path / "scene")
    out = tmp_path / "out"
    args = image_args(path, out, *change.get("extra", ()), estimators=change.get("estimators", SPECS),
                      n=change.get("n", "4"))
    line = one_error_line(cli(*args))
    assert words in line, line
    assert not out.exists()


@pytest.mark.parametrize("spec, n", [("jittered:balance:light-area+bsdf", "3"), ("antithetic:single:light-area", "5")])
def test_check_n_decides_which_n_an_image_takes(tmp_path, cli, spec, n):
    """`warpis image` refuses an N that Estimator.check_n refuses (a combiner that splits N
    over 2 techniques, a pattern that pairs samples), with check_n's own message."""
    path = image_scene(tmp_path / "scene")
    with pytest.raises(WarpisError) as excinfo:
        parse_estimator(spec).check_n(int(n))
    line = one_error_line(cli(*image_args(path, tmp_path / "out", estimators=(spec,), n=n)))
    assert line == f"warpis: error: {excinfo.value}"
    assert not (tmp_path / "out").exists()


def test_an_image_with_no_light_on_any_pixel_finishes(tmp_path, cli, monkeypatch, no_pictures):
    """A camera scene whose only light faces away from everything the camera sees is a
    valid (all-black) image: `warpis image` finishes with exit 0 and a zero reference."""
    path = image_scene(tmp_path / "scene", light_facing="up")
    out = tmp_path / "out"
    result = cli(*image_args(path, out, estimators=(SINGLE,)))
    assert result.status == 0, result.err
    with np.load(out / "image.npz") as data:
        ok = data["mask"] == 0
        assert (data["reference"][ok] == 0).all()
