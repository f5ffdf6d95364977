"""``warpis image``: every camera pixel a receiver, measured and predicted variance as pictures.

For each estimator, every receiver of a camera scene (scenes/camera.py) is run for M
trials of N samples; the result is a set of (H, W) images: the mean, one trial (what a
render at N samples looks like), the variance with its 95% fourth-moment interval, the
exact predicted variance (quadrature.exact_variances, a fixed budget of dense points per
pixel, its standard error kept), measured/predicted, the relative error √variance /
reference, the time per estimate and the efficiency 1/(variance × time), relative to a
baseline estimator; across estimators, the per-pixel winner by efficiency.  Masked
pixels (nothing, an emitter, the back of a one-sided surface) are NaN everywhere and
left out of every statistic.

Work is cut into tiles of ``TILE`` consecutive receivers × one estimator.  Each finished
tile's moments and seconds are saved under ``OUT/tiles/`` in a file named by everything
its numbers depend on (scene content, pixels, estimator, N, M, seed, receiver range), so
an interrupted image resumes from its finished tiles and a changed run never reads
another run's tiles.  The reference and the predictions are kept the same way.
Results do not depend on the tile size or the thread count except for the times.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import time
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import limits
from ..analysis.reference import reference
from ..stats import SampleMoments
from ..analysis.quadrature import exact_form_problem, exact_variances
from ..errors import WarpisError, fail
from ..kernels.engine import default_threads, run_moments, run_trials, warm
from ..kernels.estimators import Estimator
from ..scenes import Scene
from . import outdir
from .cell import check_trials

TILE = 1024  # receivers per tile: a few seconds of work, so an interrupt loses little
# Dense points per pixel and technique for the exact predicted variance (quadrature.exact_variances):
# a few per cent of relative error per pixel, and a few seconds per estimator for 10^4 pixels.
PREDICTION_POINTS = 1 << 12
# Jittered quadrature samples per replica (× 32 replicas) for each pixel's reference
# (reference.fixed_quadrature): 4096 per pixel, a relative error far below a single
# estimate's at N ≤ 256; its standard error is kept per pixel (reference_stderr).
REFERENCE_SAMPLES = 1 << 7
_FORMAT = "warpis image 1"  # a new tile encoding gets a new name

Progress = Callable[[int, int], None]  # (pixel-trials done, total)
Log = Callable[[str], None]


@dataclass(frozen=True)
class ImageRun:
    """What an image measures: a camera scene, estimators, N, M, seed, the baseline
    estimator's index, and the prediction budget (0: no predictions)."""

    scene: Scene
    estimators: tuple[Estimator, ...]
    n: int
    trials: int
    seed: int = 0
    baseline: int = 0
    points: int = PREDICTION_POINTS
    reference_samples: int = REFERENCE_SAMPLES
    threads: int | None = None

    def __post_init__(self) -> None:
        if self.scene.receivers.image is None:
            raise fail(self.scene.path or self.scene.name, "has no camera: an image needs a camera scene "
                                                           "(docs/images.md)")
        if not self.estimators:
            raise WarpisError("--estimator: give at least one estimator")
        specs = [e.spec for e in self.estimators]
        if len(set(specs)) != len(specs):
            raise WarpisError(f"--estimator: {next(s for s in specs if specs.count(s) > 1)!r} is given twice")
        for est in self.estimators:
            est.check_n(self.n)
        limits.count(self.n, "--n")
        limits.count(self.trials, "--trials")
        check_trials(self.trials)
        limits.seed(self.seed, "--seed")
        if not 0 <= self.baseline < len(self.estimators):
            raise WarpisError(f"--baseline: {self.baseline} is not an estimator's index (0 to "
                              f"{len(self.estimators) - 1})")
        limits.count(self.points, "--prediction-points", minimum=0)
        limits.count(self.reference_samples, "reference samples")


@dataclass
class ImageResult:
    """The numbers of an image: (H, W) arrays by name (``arrays``) and what describes them (``meta``)."""

    arrays: dict[str, np.ndarray]
    meta: dict[str, Any]
    computed: int = 0  # tiles computed now
    reused: int = 0  # tiles read back from an earlier, interrupted run
    pictures: list[Path] = field(default_factory=list)


# --------------------------------------------------------------------------- keys and tiles


def _key(*parts: Any) -> str:
    """A name for numbers that depend on exactly ``parts`` (strings, numbers, arrays)."""
    h = hashlib.sha256(_FORMAT.encode())
    for part in parts:
        data = np.ascontiguousarray(part).tobytes() if isinstance(part, np.ndarray) else repr(part).encode()
        h.update(len(data).to_bytes(8, "little") + data)
    return h.hexdigest()[:32]


def _scene_key(scene: Scene) -> str:
    return _key(scene.digest, scene.receivers.image.pixel, scene.receivers.image.seen)


def _load(path: Path, key: str) -> dict[str, np.ndarray] | None:
    """The arrays saved at ``path`` under ``key``, or None (missing, another run's, unreadable)."""
    try:
        with np.load(path, allow_pickle=False) as data:
            if str(data["key"]) != key:
                return None
            return {name: data[name] for name in data.files}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error):
        return None  # a file cut short by a kill, or damaged, is computed again


def _save(path: Path, key: str, arrays: dict[str, np.ndarray]) -> None:
    buffer = io.BytesIO()
    np.savez(buffer, key=np.array(key), **arrays)
    outdir.make_dir(path.parent)
    with outdir.replacing(path) as fh:
        fh.write(buffer.getvalue())


def _kept(path: Path, key: str, compute: Callable[[], dict[str, np.ndarray]]) -> tuple[dict[str, np.ndarray], bool]:
    """The arrays saved under ``key`` at ``path``, else computed and saved; and whether they were computed."""
    found = _load(path, key)
    if found is not None:
        return found, False
    arrays = compute()
    _save(path, key, arrays)
    return arrays, True


# --------------------------------------------------------------------------- measuring


def _tiles(count: int) -> list[range]:
    return [range(start, min(start + TILE, count)) for start in range(0, count, TILE)]


def _measure(run: ImageRun, est: Estimator, tile: range, threads: int, progress: Callable[[int], None]
             ) -> dict[str, np.ndarray]:
    """One tile: the moments of M trials at each of its receivers and the CPU seconds per estimate."""
    cpu = time.process_time()  # every thread's CPU time, as study cells count their cost (cell.measure_cell)
    moments = run_moments(run.scene, est, run.n, run.trials, seed=run.seed, receivers=list(tile), threads=threads,
                          progress=lambda done, total: progress(done * len(tile)))
    cost = (time.process_time() - cpu) / (len(tile) * run.trials)
    return {"count": moments.count, "mean": moments.mean, "m2": moments.m2, "m3": moments.m3, "m4": moments.m4,
            "cost": np.full(len(tile), cost)}


def measure(run: ImageRun, out: Path, progress: Progress | None = None, log: Log | None = None
            ) -> tuple[list[dict[str, np.ndarray]], int, int]:
    """Every estimator's per-receiver moments and cost, tile by tile (saved as they finish)."""
    count = len(run.scene.receivers)
    tiles = _tiles(count)
    threads = run.threads or default_threads()
    total = len(run.estimators) * count * run.trials
    done = 0
    computed = reused = 0
    results = []
    scene_key = _scene_key(run.scene)
    for e, est in enumerate(run.estimators):
        warm(run.scene, est, run.n)  # the tiles' times are the trials' alone
        parts = []
        for tile in tiles:
            key = _key(scene_key, est.spec, run.n, run.trials, run.seed, tile.start, tile.stop)

            def tick(k: int, base: int = done) -> None:
                if progress is not None:
                    progress(base + k, total)

            arrays, fresh = _kept(out / "tiles" / f"{key}.npz", key,
                                  lambda est=est, tile=tile: _measure(run, est, tile, threads, tick))
            computed, reused = computed + fresh, reused + (not fresh)
            done += len(tile) * run.trials
            if progress is not None:
                progress(done, total)
            parts.append(arrays)
        results.append({name: np.concatenate([p[name] for p in parts]) for name in parts[0] if name != "key"})
        if log is not None:
            log(f"measured {est.spec}: {count} receivers × {run.trials} trials")
    return results, computed, reused


def _single(run: ImageRun, est: Estimator) -> np.ndarray:
    """Trial 0 of the measured stream at every receiver: one render at N samples."""
    return run_trials(run.scene, est, run.n, 1, seed=run.seed, threads=run.threads)[:, 0]


def _reference(run: ImageRun, out: Path) -> dict[str, np.ndarray]:
    key = _key(_scene_key(run.scene), "reference", run.reference_samples)

    def compute() -> dict[str, np.ndarray]:
        # Quadrature at every pixel: the closed form's occlusion test would cost more than it
        # saves (milliseconds per pixel against tessellated lights).
        refs = reference(run.scene, samples=run.reference_samples, closed_form=False)
        return {"value": np.array([r.value for r in refs]), "stderr": np.array([r.stderr for r in refs])}

    return _kept(out / "tiles" / f"{key}.npz", key, compute)[0]


def _predicted(run: ImageRun, est: Estimator, out: Path) -> dict[str, np.ndarray] | None:
    """Exact variance at every receiver at the run's point budget, or None (no exact form, or points = 0)."""
    if run.points == 0 or exact_form_problem(est) is not None:
        return None
    key = _key(_scene_key(run.scene), "predicted", est.spec, run.n, run.points)

    def compute() -> dict[str, np.ndarray]:
        v = exact_variances(run.scene, np.arange(len(run.scene.receivers)), est, run.n, points=run.points,
                            threads=run.threads)
        return {"value": v.value, "stderr": v.stderr}

    return _kept(out / "tiles" / f"{key}.npz", key, compute)[0]


# --------------------------------------------------------------------------- assembling


def _winner(efficiency: np.ndarray) -> np.ndarray:
    """(R,) index of the most efficient estimator, −1 where none is (all undefined, or
    several infinitely efficient: zero variance everywhere)."""
    eff = np.where(np.isnan(efficiency), -np.inf, efficiency)
    best = np.argmax(eff, axis=0)
    top = eff.max(axis=0)
    ties = (eff == top[None]).sum(axis=0)
    return np.where((top > -np.inf) & (ties == 1), best, -1).astype(np.int16)


def _median(values: np.ndarray) -> float | None:
    finite = values[np.isfinite(values)]
    return float(np.median(finite)) if finite.size else None


def _percentile(values: np.ndarray, q: float) -> float | None:
    """The q-th percentile of ``values``, one of them (infinities included: a zero-variance
    pixel is infinitely efficient, and interpolating towards one would give NaN)."""
    return float(np.percentile(values, q, method="nearest")) if values.size else None


def assemble(run: ImageRun, measured: list[dict[str, np.ndarray]], singles: list[np.ndarray],
             ref: dict[str, np.ndarray], predicted: list[dict[str, np.ndarray] | None]
             ) -> tuple[dict[str, np.ndarray], list[dict[str, Any]]]:
    """Per-receiver numbers → (H, W) images by name (runs/image_report.py's contract), and
    the summary line of each estimator."""
    layout = run.scene.receivers.image
    image = layout.to_image
    arrays: dict[str, np.ndarray] = {"mask": layout.seen.copy(), "reference": image(ref["value"]),
                                     "reference_stderr": image(ref["stderr"])}
    variances, efficiencies = [], []
    with np.errstate(divide="ignore", invalid="ignore"):
        for i, (m, single, pred) in enumerate(zip(measured, singles, predicted)):
            stats = SampleMoments(m["count"], m["mean"], m["m2"], m["m3"], m["m4"]).interval()
            var = stats.variance
            cost = np.where(m["cost"] > 0, m["cost"], np.nan)  # a clock that saw no time gives no efficiency
            eff = 1.0 / (var * cost)
            variances.append(var)
            efficiencies.append(eff)
            p = np.full(len(var), np.nan) if pred is None else pred["value"]
            pse = np.full(len(var), np.nan) if pred is None else pred["stderr"]
            arrays.update({f"mean_{i}": image(stats.mean), f"mean_stderr_{i}": image(stats.mean_stderr),
                           f"single_{i}": image(single), f"variance_{i}": image(var),
                           f"variance_lo_{i}": image(stats.lo), f"variance_hi_{i}": image(stats.hi),
                           f"predicted_{i}": image(p), f"predicted_stderr_{i}": image(pse),
                           f"ratio_{i}": image(var / p), f"rel_error_{i}": image(np.sqrt(var) / np.abs(ref["value"])),
                           f"cost_{i}": image(m["cost"]), f"efficiency_{i}": image(eff)})
        eff = np.array(efficiencies)
        winner = _winner(eff)
        base = eff[run.baseline]
        summary = []
        for i, est in enumerate(run.estimators):
            relative = eff[i] / base
            arrays[f"relative_efficiency_{i}"] = image(relative)
            ratio = arrays[f"ratio_{i}"][np.isfinite(arrays[f"ratio_{i}"])]
            defined = relative[~np.isnan(relative)]
            summary.append({"estimator": est.spec, "median_relative_efficiency": _median(relative),
                            "relative_efficiency_p05": _percentile(defined, 5),
                            "relative_efficiency_p95": _percentile(defined, 95),
                            "beats_baseline_share": float((defined > 1).mean()) if defined.size else None,
                            "wins_share": float((winner == i).mean()), "median_variance": _median(variances[i]),
                            "median_ratio": float(np.median(ratio)) if ratio.size else None,
                            "predicted_pixels": int(np.isfinite(arrays[f"predicted_{i}"]).sum()),
                            "seconds_per_estimate": _median(measured[i]["cost"])})
    arrays["winner"] = image(winner, fill=-1).astype(np.int16)
    return arrays, summary


def run_image(run: ImageRun, out: Path, progress: Progress | None = None, log: Log | None = None,
              command: str = "") -> ImageResult:
    """Measure, predict and write an image run into ``out`` (locked for the whole run):
    ``image.npz`` (every array), ``image.json`` (meta and summary), PNGs and ``index.html``."""
    from . import image_report

    started = time.perf_counter()
    with outdir.locked(out):
        measured, computed, reused = measure(run, out, progress, log)
        singles = [_single(run, est) for est in run.estimators]
        _say(log, "trial 0 of every estimator")
        ref = _reference(run, out)
        _say(log, f"reference image ({run.reference_samples} × 32 quadrature samples per pixel)")
        predicted = []
        for est in run.estimators:
            predicted.append(_predicted(run, est, out))
            if predicted[-1] is not None:
                _say(log, f"predicted {est.spec} ({run.points} points per pixel and technique)")
        arrays, summary = assemble(run, measured, singles, ref, predicted)
        meta = _meta(run, summary, predicted, command, time.perf_counter() - started)
        result = ImageResult(arrays, meta, computed, reused)
        _write_numbers(out, arrays, meta)
        image_report.write_exr(out, arrays, meta)
        result.pictures = image_report.write_pictures(out, arrays, meta)
        image_report.write_index(out, meta, result.pictures)
    return result


def _say(log: Log | None, line: str) -> None:
    if log is not None:
        log(line)


def _meta(run: ImageRun, summary: list[dict[str, Any]], predicted: list[Any], command: str,
          seconds: float) -> dict[str, Any]:
    layout = run.scene.receivers.image
    with np.errstate(divide="ignore", invalid="ignore"):  # a pixel of zero variance has no relative error
        rel = [p["stderr"] / np.abs(p["value"]) for p in predicted if p is not None]
    rel_all = np.concatenate(rel) if rel else np.array([])
    rel_all = rel_all[np.isfinite(rel_all)]
    if run.points == 0:
        prediction = "no predictions (--prediction-points 0)"
    elif not rel:
        prediction = "no estimator has an exact variance"
    elif not rel_all.size:
        prediction = (f"exact variance from {run.points} dense points per pixel and technique (8 replicas), at every "
                      f"unmasked pixel; every prediction is 0")
    else:
        prediction = (f"exact variance from {run.points} dense points per pixel and technique (8 replicas), at every "
                      f"unmasked pixel; median relative standard error {np.median(rel_all):.1%}, 90th percentile "
                      f"{np.percentile(rel_all, 90):.1%}")
    return {"scene": run.scene.name, "digest": run.scene.digest, "estimators": [e.spec for e in run.estimators],
            "baseline": run.baseline, "n": run.n, "trials": run.trials, "seed": run.seed,
            "width": layout.camera.width, "height": layout.camera.height, "receivers": len(run.scene.receivers),
            "command": command, "seconds": seconds, "prediction": prediction, "prediction_points": run.points,
            "reference_samples": run.reference_samples, "summary": summary, "masked": layout.masked_counts(),
            "camera": layout.camera.describe()}


def _write_numbers(out: Path, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> None:
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    with outdir.replacing(out / "image.npz") as fh:
        fh.write(buffer.getvalue())
    outdir.write_text(out / "image.json", json.dumps(json_safe(meta), indent=2) + "\n")


def json_safe(data: Any) -> Any:
    """JSON has no NaN or infinity: they become null (undefined, or infinitely efficient)."""
    if isinstance(data, float) and not math.isfinite(data):
        return None
    if isinstance(data, dict):
        return {k: json_safe(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [json_safe(v) for v in data]
    return data


def summary_lines(result: ImageResult) -> list[str]:
    """One line per estimator: median relative efficiency, share of pixels won, medians."""
    meta = result.meta
    base = meta["estimators"][meta["baseline"]]
    lines = [f"{'estimator':<48} {'rel. efficiency':>15} {'5%–95% of pixels':>19} {'beats base':>10} "
             f"{'wins':>6} {'median var':>11} {'meas/pred':>9}"]

    def g(x: float | None, spec: str = ".3g") -> str:
        return "—" if x is None else format(x, spec)

    for row in meta["summary"]:
        spread = f"{g(row['relative_efficiency_p05'])}–{g(row['relative_efficiency_p95'])}"
        lines.append(f"{row['estimator']:<48} {g(row['median_relative_efficiency']):>15} {spread:>19} "
                     f"{g(row['beats_baseline_share'], '.0%'):>10} {row['wins_share']:>6.0%} "
                     f"{g(row['median_variance'], '.4g'):>11} {g(row['median_ratio'], '.3f'):>9}")
    lines.append(f"relative efficiency: (1/(variance × time)) ÷ that of {base}, median and 5th–95th percentiles over "
                 f"unmasked pixels; beats base: share of pixels where it is above 1; wins: share where it is the best")
    return lines

