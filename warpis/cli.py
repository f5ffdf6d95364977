"""The ``warpis`` command: scenes, info, reference, estimate, verify, image, study, demo, check.

Bad input (files, scenes, estimator specs, options) ends with one line on stderr,
``warpis: error: <file or option>: <problem>``, and exit status 2; nothing is written.

``--plugin FILE`` (any command, repeatable) runs a Python file before the command, so
that the techniques and patterns it registers (``warpis.register_technique``,
``warpis.register_pattern``) can be named in estimator specs and study files.

The commands that can run for minutes (reference, estimate, verify, image, study, demo)
show what they are doing, how far they are and the time left as a tqdm bar on stderr:
when stderr is a terminal and the output is not ``--json``, or always with
``--progress``; never with ``--quiet``, which wins over ``--progress``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import runpy
import sys
import warnings
from collections.abc import Callable, Iterator, Sequence
from typing import Any, NoReturn

from . import limits
from .errors import WarpisError
from .kernels.device import quiet_warp
from .kernels.estimators import estimator_help
from .kernels.techniques import TECHNIQUES


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (no usage dump) and exit status 2."""

    def error(self, message: str) -> NoReturn:
        print(f"warpis: error: {message} (see 'warpis --help')", file=sys.stderr)
        raise SystemExit(2)


def _option_type(check: Callable[[str], Any]) -> Callable[[str], Any]:
    """An argparse type from a limits check: its WarpisError becomes argparse's one line."""
    def convert(text: str) -> Any:
        try:
            return check(text)
        except WarpisError as exc:
            raise argparse.ArgumentTypeError(str(exc).split(": ", 1)[-1]) from None
    return convert


_receiver_list = _option_type(limits.receiver_list_text)
_positive = _option_type(lambda text: limits.count_text(text, "count"))
_seed = _option_type(lambda text: limits.seed(limits.count_text(text, "--seed", minimum=0, maximum=2**63)))


def _check_finite(data: Any, where: str = "output") -> None:
    """Refuse to report a NaN or infinite number: it would be a wrong figure with exit 0."""
    if isinstance(data, float) and not math.isfinite(data):
        raise WarpisError(f"{where}: the computation gave {data} (a float32 overflow or a degenerate "
                          "scene); nothing is reported")
    if isinstance(data, dict):
        for key, value in data.items():
            _check_finite(value, f"{where}.{key}")
    elif isinstance(data, (list, tuple)):
        for i, value in enumerate(data):
            _check_finite(value, f"{where}[{i}]")


def _emit(data: Any, as_json: bool, text: str) -> None:
    _check_finite(data)
    _print(json.dumps(data, indent=2, allow_nan=False) if as_json else text)


def _print(text: str) -> None:
    """Print and flush the results; a full or unwritable stdout is a one-line error."""
    _to_stdout(lambda: print(text, flush=True))


def _load(args: argparse.Namespace):
    from .scenes import load_scene

    return load_scene(args.scene, device=args.device, channel=args.channel, receivers=args.receivers_file)


# --------------------------------------------------------------------------- commands


def _summary_line(s: dict) -> str:
    return (f"{s['scene']:<22} {s['triangles']:>9} {s['emitter_triangles'] + s['sphere_lights']:>9} {s['receivers']:>9}"
            f" {s['emitter_area']:>12.5g} {s['total_power']:>12.5g}")


_SUMMARY_HEAD = f"{'scene':<22} {'triangles':>9} {'emitters':>9} {'receivers':>9} {'emitter area':>12} {'power':>12}"


def cmd_scenes(args: argparse.Namespace) -> int:
    from .scenes import bundled_scenes, load_scene

    rows, missing = [], []
    for name in bundled_scenes():
        try:
            rows.append(load_scene(name, device=args.device).summary())
        except WarpisError as exc:
            if "pip install" not in str(exc):  # a broken bundled scene is a bug: say so
                raise
            missing.append(name)  # a Mitsuba scene without the mitsuba extra
    lines = [_SUMMARY_HEAD] + [_summary_line(r) for r in rows]
    if missing:
        lines.append(f"also bundled, with the mitsuba extra (pip install \"warpis[mitsuba]\"): {', '.join(missing)}")
    _emit({"scenes": rows, "need_mitsuba": missing}, args.json, "\n".join(lines))
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    import numpy as np

    scene = _load(args)
    s = scene.summary()
    rx = scene.receivers
    emitters = []
    for m in np.unique(scene.triangle_mesh[scene.emitters]):
        mine = scene.triangle_mesh[scene.emitters] == m
        emitters.append({
            "mesh": scene.mesh_names[m], "triangles": int(mine.sum()),
            "radiance": float(scene.emitter_radiance[mine][0]),
            "area": float(scene.emitter_areas[mine].sum()),
            "power": float((scene.emitter_areas[mine] * scene.emitter_radiance[mine]).sum()),
        })
    spheres = scene.spheres
    for k in scene.sphere_lights:
        area = float(spheres.areas[k])
        emitters.append({"mesh": scene.mesh_names[spheres.owner[k]], "triangles": 0,
                         "sphere": {"center": spheres.centers[k].tolist(), "radius": float(spheres.radii[k]),
                                    "inward": bool(spheres.inward[k])},
                         "radiance": float(spheres.emission[k]), "area": area,
                         "power": area * float(spheres.emission[k])})
    groups = [{"name": name, "receivers": int((rx.group == g).sum()),
               "material": rx.material_name(int(np.flatnonzero(rx.group == g)[0]))}
              for g, name in enumerate(rx.group_names)]
    env = scene.environment
    environment = None if env is None else {
        "kind": env.kind, "resolution": list(env.resolution), "power": env.power,
        "brightest_1_percent_share": env.brightest_share()}
    delta = scene.delta_lights
    delta_lights = [] if delta is None else [
        {"label": label, "kind": kind, "irradiance_min": float(delta.irradiance[:, k].min()),
         "irradiance_max": float(delta.irradiance[:, k].max())}
        for k, (label, kind) in enumerate(zip(delta.labels, delta.kinds))]
    s.update({"description": scene.description, "emitters": emitters, "receiver_groups": groups,
              "environment": environment, "delta_lights": delta_lights})
    lines = [_SUMMARY_HEAD, _summary_line(s)]
    if scene.description:
        lines.insert(0, scene.description)
    lines.append("")
    lines.append(f"{'emitter mesh':<28} {'triangles':>9} {'radiance':>10} {'area':>10} {'power':>10}")
    for e in emitters:
        shape = "sphere" if "sphere" in e else e["triangles"]
        lines.append(f"{e['mesh']:<28} {shape:>9} {e['radiance']:>10.4g} {e['area']:>10.4g} {e['power']:>10.4g}")
    if spheres is not None:
        lines.append(f"{len(spheres)} analytic sphere(s), {len(scene.sphere_lights)} of them emitting: intersected and "
                     f"sampled exactly (light-solid-angle samples the cone each subtends)")
    if env is not None:
        width, height = env.resolution
        lines.append(f"environment ({env.kind}): {width} × {height} texels, ∫ L dω = {env.power:.6g} over the sphere, "
                     f"{100 * env.brightest_share():.3g}% of it in its brightest 1% of texels")
    for d in delta_lights:
        lines.append(f"delta light {d['label']} ({d['kind']}): irradiance {d['irradiance_min']:.6g} to "
                     f"{d['irradiance_max']:.6g} at the receivers, an exact term in every estimate (reference: "
                     f"its 'delta')")
    lines.append("")
    lines.append("receiver groups: " + ", ".join(f"{g['name']} ({g['receivers']}, {g['material']})" for g in groups))
    s["notes"] = list(scene.notes)
    lines.extend(scene.notes)
    _emit(s, args.json, "\n".join(lines))
    return 0


def cmd_reference(args: argparse.Namespace) -> int:
    from .analysis.reference import DEFAULT_REL_ERROR, MAX_QUADRATURE_SAMPLES, check_rel_error, reference

    rel_error = check_rel_error(args.rel_error, "--rel-error") if args.rel_error is not None else DEFAULT_REL_ERROR
    samples = limits.count_text(args.samples, "--samples") if args.samples is not None else MAX_QUADRATURE_SAMPLES
    scene = _load(args)
    count = len(args.receivers) if args.receivers is not None else len(scene.receivers)
    with _Progress(args, "reference", "receivers", total=count, scale=True) as bar:
        refs = reference(scene, args.receivers, samples=samples, rel_error=rel_error, progress=bar,
                         stage=bar.stage)
    data = {"scene": scene.name, "rel_error": rel_error, "samples": samples, "receivers": [r.as_dict() for r in refs]}
    lines = [f"{scene.name}: target stderr <= {rel_error:g} × |value| within {samples} samples per replica",
             f"{'receiver':>8} {'value':>14} {'stderr':>11} {'relative':>9}  method"]
    for r in refs:
        rel = r.stderr / abs(r.value) if r.value else 0.0
        how = r.method if r.method == "closed-form" else f"{r.method} {r.estimator} ({r.samples} samples)"
        miss = "" if r.target_met is not False else "  MISSED TARGET"
        exact = f", delta lights {r.delta:.9g} of it" if scene.delta_lights is not None else ""
        lines.append(f"{r.index:>8} {r.value:>14.9g} {r.stderr:>11.3g} {rel:>9.2g}  {how}{exact}{miss}")
    _emit(data, args.json, "\n".join(lines))
    return 0


def cmd_estimate(args: argparse.Namespace) -> int:
    from .analysis.reference import reference
    from .kernels.engine import run_moments
    from .kernels.estimators import parse_estimator
    from .runs.cell import check_trials

    est = parse_estimator(args.estimator)
    est.check_n(args.n)
    check_trials(args.trials)  # the one floor of verify and study: it reports a variance interval too
    scene = _load(args)
    with _Progress(args, "estimate", "trials", total=args.trials, scale=True) as bar:
        # running moments: memory flat in --trials
        moments = run_moments(scene, est, args.n, args.trials, seed=args.seed, receivers=args.receivers,
                              threads=args.threads, progress=bar)
        refs = reference(scene, args.receivers, progress=bar,
                         stage=lambda what, unit: bar.stage(f"reference, {what}", unit))
    stats = moments.interval()
    alphas = _optimal_alphas(scene, est, args)
    rows = []
    for i, ref in enumerate(refs):
        z, agrees = _mean_z(float(stats.mean[i]), float(stats.mean_stderr[i]), ref.value, ref.stderr)
        rows.append({
            "index": ref.index, "mean": float(stats.mean[i]), "stderr": float(stats.mean_stderr[i]),
            "variance": float(stats.variance[i]), "variance_ci": [float(stats.lo[i]), float(stats.hi[i])],
            "reference": ref.value, "reference_stderr": ref.stderr, "reference_method": ref.method,
            "z": z if math.isfinite(z) else None, "agrees": agrees,
            **({} if alphas is None else {key: value[i].tolist() for key, value in alphas.items()}),
        })
    data = {"scene": scene.name, "estimator": est.spec, "n": args.n, "trials": args.trials, "seed": args.seed,
            "receivers": rows}
    lines = [f"{scene.name}  {est.spec}  N={args.n}  trials={args.trials}  seed={args.seed}",
             f"{'receiver':>8} {'mean':>13} {'stderr':>10} {'variance':>11} {'95% interval':>25} "
             f"{'reference':>13} {'ref stderr':>10} {'z':>6}"]
    for r in rows:
        lo, hi = r["variance_ci"]
        lines.append(f"{r['index']:>8} {r['mean']:>13.7g} {r['stderr']:>10.3g} {r['variance']:>11.4g} "
                     f"{f'[{lo:.4g}, {hi:.4g}]':>25} {r['reference']:>13.7g} {r['reference_stderr']:>10.3g} "
                     f"{_z_text(r):>6}")
    if alphas is not None:
        lines += _alpha_lines(est, rows)
    _emit(data, args.json, "\n".join(lines))
    return 0


def _mean_z(mean: float, stderr: float, ref: float, ref_stderr: float) -> tuple[float, bool]:
    """z = (mean − reference)/√(stderr² + ref_stderr²) and whether the two agree.

    With no spread on either side z is 0 where they are equal and ±inf where they are
    not (``stats.zscore``); they agree when |z| ≤ 1.96, the two-sided 95% rule by which
    verify and study call a prediction inside.
    """
    from .stats import zscore
    from .runs.cell import Z95

    z = float(zscore(mean, math.hypot(stderr, ref_stderr), ref))
    return z, bool(abs(z) <= Z95)


def _z_text(row: dict[str, Any]) -> str:
    """The z of an estimate row as printed: 2 decimals, or ±inf where the mean differs from
    a reference with no spread on either side (JSON holds null there, and "agrees": false)."""
    if row["z"] is not None:
        return f"{row['z']:.2f}"
    return "+inf" if row["mean"] > row["reference"] else "-inf"


def _optimal_alphas(scene: Any, est: Any, args: argparse.Namespace) -> dict[str, Any] | None:
    """The optimal combiners' α per receiver: the oracle's (``alpha``), or the pilot's mean
    and standard deviation over the run's trials (``alpha_mean``, ``alpha_sd``); None for
    any other combiner."""
    from .analysis.quadrature import optimal_alpha
    from .kernels.engine import pilot_alphas, select_receivers

    if est.combiner_entry.oracle:
        return {"alpha": optimal_alpha(scene, select_receivers(scene, args.receivers), est.techniques)}
    if est.combiner_entry.pilot:
        per_trial = pilot_alphas(scene, est, args.n, args.trials, seed=args.seed, receivers=args.receivers)
        return {"alpha_mean": per_trial.mean(axis=1), "alpha_sd": per_trial.std(axis=1)}
    return None


def _alpha_lines(est: Any, rows: list[dict[str, Any]]) -> list[str]:
    names = ", ".join(f"α_{t}" for t in est.techniques)
    if est.combiner_entry.oracle:
        head = f"optimal-MIS coefficients ({names}) from warpis's dense evaluation, α = A⁻¹b:"
        return [head] + [f"{r['index']:>8}  " + "  ".join(f"{a:.6g}" for a in r["alpha"]) for r in rows]
    head = f"optimal-MIS coefficients ({names}) from each trial's pilot: mean ± sd over the trials:"
    return [head] + [f"{r['index']:>8}  " + "  ".join(f"{a:.6g} ± {d:.3g}" for a, d in zip(r["alpha_mean"], r["alpha_sd"]))
                     for r in rows]


def cmd_verify(args: argparse.Namespace) -> int:
    from .kernels.estimators import parse_estimator
    from .runs import outdir
    from .runs.verify import DEFAULT_N, summary_lines, verify, write_outputs

    techniques = tuple(args.techniques.split("+")) if args.techniques else None
    estimators = [parse_estimator(e) for e in args.estimators.split(",")] if args.estimators else None
    n_values = _int_list(args.n, "--n") if args.n else DEFAULT_N
    out = outdir.out_option(args.out)  # a file in the way is refused when the folder is locked
    for t in techniques or ():
        TECHNIQUES.lookup(t)
    scene = _load(args)
    with _Progress(args, "verify", "cells") as bar:
        # One lock over verify.json, verify.md and the figures (verify() re-enters it); a folder
        # it creates is removed again if verify() then refuses its arguments.
        with outdir.locked(out) if out is not None else contextlib.nullcontext(), _runner(args) as runner:
            result = verify(scene, techniques, estimators, n_values, args.trials, args.seed, args.receivers,
                            args.threads, out, bar, runner)
            if out is not None:
                command = "warpis " + " ".join(sys.argv[1:]) if sys.argv[1:] else f"warpis verify {args.scene}"
                write_outputs(out, result, command)
    lines = [f"{scene.name}: {len(result.rows)} cells, {result.trials} trials each, {result.seconds:.0f} s"]
    lines += summary_lines(result)
    if out is not None:
        lines.append(f"wrote {out / 'verify.json'}, {out / 'verify.md'} and figures")
    _emit(result.as_json(), args.json, "\n".join(lines))
    return 0


def cmd_study(args: argparse.Namespace) -> int:
    from pathlib import Path

    from .runs.outdir import out_option
    from .runs.study_file import default_out, load_study

    out = out_option(args.out)  # before the study is read: an empty --out is not "."
    study = load_study(Path(args.file), threads=args.threads)
    return _run_study(study, out if out is not None else default_out(study), args)


def cmd_image(args: argparse.Namespace) -> int:
    from pathlib import Path

    from .kernels.estimators import parse_estimator
    from .runs import outdir
    from .runs.image import PREDICTION_POINTS, ImageRun, json_safe, run_image, summary_lines
    from .scenes import load_scene

    estimators = tuple(parse_estimator(spec) for spec in args.estimator)
    for est in estimators:
        est.check_n(args.n)  # before the scene loads (ImageRun checks again, for the API)
    out = outdir.out_option(args.out)
    scene = load_scene(args.scene, device=args.device, channel=args.channel, receivers=args.receivers_file,
                       camera=True, width=args.width, height=args.height)
    baseline = _baseline(args.baseline, estimators)
    run = ImageRun(scene, estimators, args.n, args.trials, args.seed, baseline,
                   PREDICTION_POINTS if args.prediction_points is None else args.prediction_points,
                   threads=args.threads)
    out = out if out is not None else Path("warpis-out") / f"image-{scene.name}"
    command = "warpis " + " ".join(sys.argv[1:]) if sys.argv[1:] else f"warpis image {args.scene}"
    with _Progress(args, "image", "pixel-trials", scale=True) as bar:
        # Its stage lines ("reference image …") are progress too: above the bar, or not at all.
        result = run_image(run, out, bar, (lambda line: bar.write(line, sys.stderr)) if bar.shown else None, command)
    lines = [f"{scene.name}: {len(scene.receivers)} pixels measured of {scene.receivers.image.camera.width} × "
             f"{scene.receivers.image.camera.height}, N={args.n}, {args.trials} trials, {result.meta['seconds']:.0f} s "
             f"({result.computed} tile(s) computed, {result.reused} reused)"]
    lines += summary_lines(result)
    lines.append(f"predictions: {result.meta['prediction']}")
    lines.append(f"wrote {out / 'index.html'}, {out / 'image.npz'} and {len(result.pictures)} picture(s)")
    # An infinitely efficient estimator (zero variance) is JSON's null, as in image.json.
    _emit(json_safe(result.meta), args.json, "\n".join(lines))
    return 0


def _baseline(text: str | None, estimators) -> int:
    """``--baseline``: an estimator spec among ``--estimator`` (default: the first)."""
    if text is None:
        return 0
    from .kernels.estimators import parse_estimator

    spec = parse_estimator(text).spec
    specs = [e.spec for e in estimators]
    if spec not in specs:
        raise WarpisError(f"--baseline: {text!r} is not one of the --estimator specs ({', '.join(specs)})")
    return specs.index(spec)


def cmd_check(args: argparse.Namespace) -> int:
    """``warpis check``: every applicable check on one subject (warpis/check/); 1 when one fails."""
    from .check.command import run_command

    return run_command(args, _emit)


def cmd_demo(args: argparse.Namespace) -> int:
    from .runs.outdir import out_option
    from .runs.study_file import default_out, demo_study

    out = out_option(args.out)  # an empty --out is an error, not the default folder
    study = demo_study(threads=args.threads)
    return _run_study(study, out if out is not None else default_out(study), args)


# A local cluster is for trying a cluster on one machine: each worker is a process.
MAX_LOCAL_WORKERS = 64


@contextlib.contextmanager
def _runner(args: argparse.Namespace) -> Iterator[Any]:
    """The cluster runner that ``--scheduler``/``--workers`` ask for (closed afterwards),
    or None: cells then run here.  Dask is imported only when one is given."""
    if args.scheduler is None and args.workers is None:
        yield None
        return
    if args.scheduler is not None and not args.scheduler.strip():
        raise WarpisError("--scheduler: must name a scheduler address, e.g. tcp://host:8786")
    if args.workers is not None and args.workers > MAX_LOCAL_WORKERS:
        raise WarpisError(f"--workers: at most {MAX_LOCAL_WORKERS} local worker processes (got {args.workers})")
    from .runs.cluster import connect

    with connect(args.scheduler, args.workers) as runner:
        yield runner


def _run_study(study, out, args: argparse.Namespace) -> int:
    """Run a validated study into ``out`` with a bar of cells done and time left; say where it wrote."""
    from .runs.outdir import locked
    from .runs.study import run_study

    # Locked (run_study re-enters the lock) before anything is said: a folder in use or
    # one that cannot be written fails at once, with only its one-line error.
    with locked(out), _runner(args) as runner:
        cells = len(study.cells())
        print(f"study {study.name}: {cells} cells ({len(study.scenes)} scene(s) × {len(study.estimators)} "
              f"estimator(s) × {len(study.n)} N), {study.trials} trials each, into {out}", flush=True)
        with _Progress(args, study.name, "cells") as bar:
            def log(line: str) -> None:
                bar.write(line, sys.stdout)
                sys.stdout.flush()

            # Figures on as many processes as the study has threads: this __main__ is warpis's own.
            run = run_study(study, out, progress=bar, log=log, runner=runner,
                            figure_processes=study.threads or limits.default_threads())
    print(f"computed {run.computed} cell(s), skipped {run.skipped} already finished; "
          f"{len(run.rows)} rows in {out / 'results.csv'}")
    print(f"wrote {out / 'report.md'}, {out / 'summary.json'} and {len(run.figures)} figure file(s) in "
          f"{out / 'figures'}")
    return 0


def _int_list(text: str, option: str) -> list[int]:
    """Comma-separated counts, each checked by limits (no float, nothing past int32)."""
    values = [limits.count_text(t, option) for t in text.split(",") if t.strip()]
    if not values:
        raise WarpisError(f"{option}: takes comma-separated positive integers, got {text!r}")
    return values


def _stderr_is_terminal() -> bool:
    """Whether stderr is a terminal (where a bar redraws in place and a person watches)."""
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # replaced by an object without one, or closed
        return False


def progress_shown(args: argparse.Namespace) -> bool:
    """Whether a command shows progress: never with ``--quiet`` (it wins over
    ``--progress``), always with ``--progress``, else when stderr is a terminal and the
    output is not ``--json``."""
    if getattr(args, "quiet", False):
        return False
    if getattr(args, "progress", False):
        return True
    return not getattr(args, "json", False) and _stderr_is_terminal()


class _Progress:
    """One tqdm bar on stderr fed by the engine's and the reference's ``Progress``
    callbacks: what the command is doing (``what``, then each ``stage``), how far it is
    and the time left.  Disabled (every call a no-op) unless :func:`progress_shown`."""

    def __init__(self, args: argparse.Namespace, what: str, unit: str, total: int = 0, scale: bool = False):
        self.what, self.unit, self.total, self.scale = what, unit, total, scale
        self.shown = progress_shown(args)
        self.bar: Any = None

    def __enter__(self) -> _Progress:
        from tqdm import tqdm

        # To a terminal the bar redraws in place; to a file or pipe (--progress) each
        # redraw is a new record, so fewer of them.
        interval = 0.1 if _stderr_is_terminal() else 1.0
        self.bar = tqdm(total=self.total or None, desc=self.what, unit=self.unit, unit_scale=self.scale,
                        disable=not self.shown, file=sys.stderr, leave=False, dynamic_ncols=True,
                        mininterval=interval)
        return self

    def __call__(self, done: int, total: int) -> None:
        """``Progress``: ``done`` of ``total`` (the total may grow as work is planned)."""
        if not self.shown:
            return
        if total != self.bar.total:
            self.bar.total = total
            self.bar.refresh()
        self.bar.update(done - self.bar.n)

    def stage(self, what: str, unit: str) -> None:
        """A new stage of the command: the count restarts at 0, in ``unit``."""
        if not self.shown:
            return
        self.bar.set_description_str(f"{self.what}: {what}", refresh=False)
        self.bar.unit = unit
        self.bar.reset(total=0)

    def write(self, line: str, file: Any) -> None:
        """A line of output that the bar, when shown, redraws below."""
        self.bar.write(line, file=file)

    def __exit__(self, *exc: Any) -> None:
        self.bar.close()


# --------------------------------------------------------------------------- plugins


def _plugin_paths(argv: Sequence[str]) -> list[str]:
    """Every ``--plugin FILE`` (or ``--plugin=FILE``) of ``argv``, wherever it stands."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--plugin", action="append", default=[])
    known, _ = pre.parse_known_args(argv)
    return known.plugin


def load_plugin(path: str) -> None:
    """Run the Python file ``path`` (it registers techniques or patterns); any failure is
    one line naming the file."""
    where = f"--plugin {path}"
    if os.path.isdir(path):
        raise WarpisError(f"{where}: is a directory, not a Python file")
    if not os.path.isfile(path):
        raise WarpisError(f"{where}: no such file")
    try:
        runpy.run_path(path, run_name="warpis_plugin")
    except WarpisError as exc:
        raise WarpisError(f"{where}: {exc}") from None
    except (Exception, SystemExit) as exc:  # a user's file: whatever it raises is reported, not a traceback
        message = str(exc).strip().splitlines()
        raise WarpisError(f"{where}: {type(exc).__name__}" + (f": {message[0]}" if message else "")) from None


# --------------------------------------------------------------------------- parser


def progress_options(c: argparse.ArgumentParser) -> None:
    """``--progress`` / ``--quiet``: the progress bar on stderr, forced on or off."""
    c.add_argument("--progress", action="store_true",
                   help="show progress on stderr (what runs, how far, the time left) even when stderr is not a "
                        "terminal or with --json; by default only on a terminal and not with --json")
    c.add_argument("--quiet", action="store_true", help="show no progress (wins over --progress); results, "
                                                        "warnings and errors are printed as ever")


def cluster_options(c: argparse.ArgumentParser) -> None:
    """``--scheduler`` / ``--workers``: measure the cells on a Dask cluster (docs/clusters.md)."""
    g = c.add_mutually_exclusive_group()
    g.add_argument("--scheduler", metavar="ADDRESS",
                   help="run the cells on the Dask cluster of this scheduler (tcp://host:port); same results")
    g.add_argument("--workers", type=_positive, metavar="K",
                   help="run the cells on a local Dask cluster of K single-threaded worker processes")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="warpis", description="Variance of Monte Carlo direct-illumination estimators on mesh scenes, "
                                           "measured in Warp kernels and held against closed forms.")
    p.add_argument("--version", action="version", version=f"warpis {_version()}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    # Read before the parser is built (so that help lists what plugins register); declared
    # on every command so that it may stand anywhere.
    plugin = argparse.ArgumentParser(add_help=False)
    for parser in (p, plugin):
        parser.add_argument("--plugin", action="append", metavar="FILE",
                            help="run this Python file first (it may register techniques and patterns); repeatable")

    def scene_command(name: str, help: str, epilog: str | None = None) -> argparse.ArgumentParser:
        # Raw text keeps the epilog's one line per vocabulary entry.
        raw = {"formatter_class": argparse.RawDescriptionHelpFormatter} if epilog else {}
        c = sub.add_parser(name, help=help, description=help, epilog=epilog, parents=[plugin], **raw)
        c.add_argument("scene", help="a bundled scene's name (see 'warpis scenes') or a scene file: TOML, or "
                                     "Mitsuba 3 XML (needs warpis[mitsuba])")
        c.add_argument("--device", default="cpu", help="Warp device: cpu (default) or cuda[:N]")
        c.add_argument("--channel", choices=("r", "g", "b", "y"), default=None,
                       help="Mitsuba scenes: the colour channel warpis measures (default: the receivers file's "
                            "'channel', else y, the luminance of linear sRGB); TOML scenes are grey")
        c.add_argument("--receivers-file", metavar="FILE", default=None,
                       help="Mitsuba scenes: the receivers file (default: <scene>.receivers.toml beside the XML)")
        c.add_argument("--json", action="store_true", help="print JSON instead of a table")
        return c

    c = sub.add_parser("scenes", help="list the bundled scenes with triangle, emitter and receiver counts",
                       parents=[plugin])
    c.add_argument("--device", default="cpu", help=argparse.SUPPRESS)
    c.add_argument("--json", action="store_true", help="print JSON instead of a table")
    c.set_defaults(func=cmd_scenes)

    c = scene_command("info", "load and validate one scene; print counts, emitter areas and total power")
    c.set_defaults(func=cmd_info)

    c = scene_command("reference", "reference value of F at each receiver: closed form or dense quadrature")
    c.add_argument("--receivers", type=_receiver_list, help="comma-separated receiver indices (default: all)")
    c.add_argument("--rel-error", metavar="R",
                   help="quadrature refines until each stderr <= R × |value| (near 0: R × 1e-3 × the value with "
                        "occluders removed); a number in (0, 1); default 1e-4, seconds per receiver on 2 cores "
                        "(1e-5 costs ~20× that)")
    c.add_argument("--samples", metavar="N", help="the most quadrature samples per replica (32 replicas) before it "
                                                  "stops short of --rel-error with a warning (default 1048576)")
    progress_options(c)
    c.set_defaults(func=cmd_reference)

    c = scene_command("estimate", "run M independent trials of one estimator; mean, variance and its interval",
                      epilog=estimator_help())
    c.add_argument("--estimator", required=True, help="PATTERN:COMBINER[=VALUE]:TECH[+TECH...], "
                                                      "e.g. jittered:balance:light-area+cosine")
    c.add_argument("--n", type=_positive, required=True, help="samples per estimate (N)")
    c.add_argument("--trials", type=_positive, default=1000, help="independent trials (M, default 1000)")
    c.add_argument("--seed", type=_seed, default=0, help="random seed in [0, 2^32) (default 0)")
    c.add_argument("--receivers", type=_receiver_list, help="comma-separated receiver indices (default: all)")
    c.add_argument("--threads", type=_positive, help="CPU threads (default: all cores; results do not depend on it)")
    progress_options(c)
    c.set_defaults(func=cmd_estimate)

    c = scene_command("verify", "hold measured variances against the seed's equations, cell by cell",
                      epilog=estimator_help())
    c.add_argument("--techniques", help="technique set A+B (default: light-area+cosine, or "
                                        "light-solid-angle+phong for glossy receivers)")
    c.add_argument("--estimators", help="comma-separated estimator specs (default: every estimator the set allows)")
    c.add_argument("--n", help="comma-separated sample counts (default 4,16,64,256,1024)")
    c.add_argument("--trials", type=_positive, default=400, help="trials per cell (default 400)")
    c.add_argument("--seed", type=_seed, default=0, help="random seed in [0, 2^32) (default 0)")
    c.add_argument("--receivers", type=_receiver_list,
                   help="comma-separated receiver indices (default: all, or 8 spread through the list when more)")
    c.add_argument("--threads", type=_positive, help="CPU threads (default: all cores)")
    c.add_argument("--out", help="directory for verify.json, verify.md and figures")
    cluster_options(c)
    progress_options(c)
    c.set_defaults(func=cmd_verify)

    c = scene_command("image", "every pixel of the scene's camera a receiver: mean, variance, predicted variance and "
                               "efficiency images per estimator, with an index.html", epilog=estimator_help())
    c.add_argument("--estimator", required=True, action="append",
                   help="PATTERN:COMBINER[=VALUE]:TECH[+TECH...]; repeat for several estimators")
    c.add_argument("--n", type=_positive, required=True, help="samples per estimate (N)")
    c.add_argument("--trials", type=_positive, default=256, help="trials per pixel (M, default 256)")
    c.add_argument("--seed", type=_seed, default=0, help="random seed in [0, 2^32) (default 0)")
    c.add_argument("--baseline", help="the estimator efficiencies are relative to (default: the first --estimator)")
    c.add_argument("--width", type=_positive, help="image width in pixels (default: the camera's)")
    c.add_argument("--height", type=_positive, help="image height in pixels (default: the camera's)")
    c.add_argument("--prediction-points", type=_option_type(lambda t: limits.count_text(t, "--prediction-points",
                                                                                        minimum=0)),
                   default=None, help="dense points per pixel and technique for the exact predicted variance "
                                      "(default 4096; 0: no predictions)")
    c.add_argument("--threads", type=_positive, help="CPU threads (default: all cores; results do not depend on it)")
    c.add_argument("--out", help="output directory (default ./warpis-out/image-<scene>/); rerunning resumes")
    progress_options(c)
    c.set_defaults(func=cmd_image)

    c = sub.add_parser("study", help="run a study file (scenes × estimators × N) into results, figures and a report; "
                                     "resumable", description="run a study file (scenes × estimators × N) into "
                                                              "results.csv, summary.json, figures and report.md; "
                                                              "rerunning skips finished cells",
                       parents=[plugin])
    c.add_argument("file", help="the study TOML (see docs/studies.md)")
    c.add_argument("--out", help="output directory (default ./warpis-out/<name>/)")
    c.add_argument("--threads", type=_positive, help="CPU threads (default: the study's, else all cores)")
    cluster_options(c)
    progress_options(c)
    c.set_defaults(func=cmd_study)

    c = sub.add_parser("demo", help="the main job: ten estimators on occluded-quad, variance against N, "
                                    "slopes and predictions (about a minute on two cores, half a minute again)",
                       description="run the built-in demo study (scripts/studies/demo.toml) on occluded-quad",
                       parents=[plugin])
    c.add_argument("--out", help="output directory (default ./warpis-out/demo/)")
    c.add_argument("--threads", type=_positive, help="CPU threads (default: all cores)")
    cluster_options(c)
    progress_options(c)
    c.set_defaults(func=cmd_demo)

    from .check.command import add_arguments as check_arguments

    c = sub.add_parser("check", help="every applicable check on a technique, a Mitsuba file's BSDFs or a combiner: "
                                     "a verdict table (exit 1 when one fails) and a figure per check",
                       description="check a technique (--technique), every BSDF of a Mitsuba XML file (--bsdfs) or a "
                                   "combiner's weights (--combiner): chi-square, pdf integral, pdf at the sample, "
                                   "zero pdf, measure, unbiasedness, weight, eval quadrature, reciprocity, energy, "
                                   "weights (docs/check.md); exit 0 when all pass, 1 when one fails",
                       parents=[plugin])
    check_arguments(c)
    c.set_defaults(func=cmd_check)
    return p


def _silence_stdout() -> None:
    """Point stdout at /dev/null so the interpreter's last flush cannot fail again."""
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def _version() -> str:
    from . import __version__

    return __version__


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``warpis`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    plugins = _plugin_paths(argv)
    if plugins:
        quiet_warp()
        try:
            for path in plugins:
                load_plugin(path)
        except WarpisError as exc:
            print(f"warpis: error: {exc}", file=sys.stderr)
            return 2
    args = build_parser().parse_args(argv)
    quiet_warp()
    try:
        if hasattr(args, "device"):
            from .kernels.device import check_device

            check_device(args.device, "--device")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            status = args.func(args)
        for w in caught:
            if not issubclass(w.category, DeprecationWarning):
                print(f"warpis: warning: {w.message}", file=sys.stderr)
        _print_flush()
        return status
    except WarpisError as exc:
        print(f"warpis: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("warpis: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into head & co.: stop quietly
        _silence_stdout()
        return 0


def _print_flush() -> None:
    """Flush what commands printed, so that a full stdout fails here and not at exit."""
    _to_stdout(sys.stdout.flush)


def _to_stdout(write: Callable[[], Any]) -> None:
    """Run a write to stdout; a full or unwritable stdout is a one-line error (a closed
    pipe is not: main() stops quietly on it)."""
    try:
        write()
    except BrokenPipeError:
        raise
    except OSError as exc:
        _silence_stdout()
        raise WarpisError(f"standard output: cannot write: {exc.strerror}") from None


if __name__ == "__main__":
    sys.exit(main())
