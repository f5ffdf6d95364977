"""The ``warpis`` command: scenes, info, reference, estimate, verify, study, demo.

Bad input (files, scenes, estimator specs, options) ends with one line on stderr,
``warpis: error: <file or option>: <problem>``, and exit status 2; nothing is written.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from collections.abc import Sequence
from typing import Any, NoReturn

from .errors import WarpisError


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (no usage dump) and exit status 2."""

    def error(self, message: str) -> NoReturn:
        print(f"warpis: error: {message} (see 'warpis --help')", file=sys.stderr)
        raise SystemExit(2)


def _receiver_list(text: str) -> list[int]:
    try:
        out = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--receivers takes comma-separated indices, got {text!r}") from None
    if not out:
        raise argparse.ArgumentTypeError("--receivers is empty")
    return out


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def _emit(data: Any, as_json: bool, text: str) -> None:
    print(json.dumps(data, indent=2) if as_json else text)


def _load(args: argparse.Namespace):
    from .scene import load_scene

    return load_scene(args.scene, device=args.device)


# --------------------------------------------------------------------------- commands


def _summary_line(s: dict) -> str:
    return (f"{s['scene']:<16} {s['triangles']:>9} {s['emitter_triangles']:>9} {s['receivers']:>9}"
            f" {s['emitter_area']:>12.5g} {s['total_power']:>12.5g}")


_SUMMARY_HEAD = f"{'scene':<16} {'triangles':>9} {'emitters':>9} {'receivers':>9} {'emitter area':>12} {'power':>12}"


def cmd_scenes(args: argparse.Namespace) -> int:
    from .scene import bundled_scenes, load_scene

    rows = [load_scene(name, device=args.device).summary() for name in bundled_scenes()]
    _emit({"scenes": rows}, args.json, "\n".join([_SUMMARY_HEAD] + [_summary_line(r) for r in rows]))
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
            "mesh": scene.mesh_paths[m], "triangles": int(mine.sum()),
            "radiance": float(scene.emitter_radiance[mine][0]),
            "area": float(scene.emitter_areas[mine].sum()),
            "power": float((scene.emitter_areas[mine] * scene.emitter_radiance[mine]).sum()),
        })
    groups = [{"name": name, "receivers": int((rx.group == g).sum()),
               "material": rx.material_name(int(np.flatnonzero(rx.group == g)[0]))}
              for g, name in enumerate(rx.group_names)]
    s.update({"description": scene.description, "emitters": emitters, "receiver_groups": groups})
    lines = [_SUMMARY_HEAD, _summary_line(s)]
    if scene.description:
        lines.insert(0, scene.description)
    lines.append("")
    lines.append(f"{'emitter mesh':<28} {'triangles':>9} {'radiance':>10} {'area':>10} {'power':>10}")
    for e in emitters:
        lines.append(f"{e['mesh']:<28} {e['triangles']:>9} {e['radiance']:>10.4g} {e['area']:>10.4g} {e['power']:>10.4g}")
    lines.append("")
    lines.append("receiver groups: " + ", ".join(f"{g['name']} ({g['receivers']}, {g['material']})" for g in groups))
    _emit(s, args.json, "\n".join(lines))
    return 0


def cmd_reference(args: argparse.Namespace) -> int:
    from .reference import reference

    scene = _load(args)
    refs = reference(scene, args.receivers, samples=args.samples)
    data = {"scene": scene.name, "receivers": [r.as_dict() for r in refs]}
    lines = [f"{'receiver':>8} {'value':>14} {'stderr':>11}  method"]
    for r in refs:
        how = r.method if r.method == "closed-form" else f"{r.method} ({r.samples} samples)"
        lines.append(f"{r.index:>8} {r.value:>14.8g} {r.stderr:>11.3g}  {how}")
    _emit(data, args.json, "\n".join(lines))
    return 0


def cmd_estimate(args: argparse.Namespace) -> int:
    from .engine import run_trials
    from .estimators import parse_estimator
    from .reference import reference
    from .stats import variance_interval

    est = parse_estimator(args.estimator)
    est.check_n(args.n)
    if args.trials < 2:
        raise WarpisError(f"--trials must be at least 2 to measure a variance (got {args.trials})")
    scene = _load(args)
    with _progress(args.trials, "trials") as bar:
        values = run_trials(scene, est, args.n, args.trials, seed=args.seed, receivers=args.receivers,
                            threads=args.threads, progress=bar)
    stats = variance_interval(values)
    refs = reference(scene, args.receivers)
    rows = []
    for i, ref in enumerate(refs):
        rows.append({
            "index": ref.index, "mean": float(stats.mean[i]), "stderr": float(stats.mean_stderr[i]),
            "variance": float(stats.variance[i]), "variance_ci": [float(stats.lo[i]), float(stats.hi[i])],
            "reference": ref.value, "reference_stderr": ref.stderr, "reference_method": ref.method,
        })
    data = {"scene": scene.name, "estimator": est.spec, "n": args.n, "trials": args.trials, "seed": args.seed,
            "receivers": rows}
    lines = [f"{scene.name}  {est.spec}  N={args.n}  trials={args.trials}  seed={args.seed}",
             f"{'receiver':>8} {'mean':>13} {'stderr':>10} {'variance':>11} {'95% interval':>25} "
             f"{'reference':>13} {'ref stderr':>10} {'z':>6}"]
    for r in rows:
        se = (r["stderr"] ** 2 + r["reference_stderr"] ** 2) ** 0.5
        z = (r["mean"] - r["reference"]) / se if se > 0 else 0.0
        lo, hi = r["variance_ci"]
        lines.append(f"{r['index']:>8} {r['mean']:>13.7g} {r['stderr']:>10.3g} {r['variance']:>11.4g} "
                     f"{f'[{lo:.4g}, {hi:.4g}]':>25} {r['reference']:>13.7g} {r['reference_stderr']:>10.3g} {z:>6.2f}")
    _emit(data, args.json, "\n".join(lines))
    return 0


def cmd_verify(args: argparse.Namespace) -> int:
    from pathlib import Path

    from . import plots
    from .estimators import parse_estimator
    from .verify import DEFAULT_N, markdown, summary_lines, verify

    techniques = tuple(args.techniques.split("+")) if args.techniques else None
    estimators = [parse_estimator(e) for e in args.estimators.split(",")] if args.estimators else None
    n_values = _int_list(args.n, "--n") if args.n else DEFAULT_N
    out = Path(args.out) if args.out else None
    if out is not None and out.exists() and not out.is_dir():
        raise WarpisError(f"{out}: --out must be a directory")
    if techniques:
        from .techniques import technique_code

        for t in techniques:
            technique_code(t)
    scene = _load(args)
    with _progress(0, "cells") as bar:
        def progress(done: int, total: int) -> None:
            bar.bar.total = total
            bar(done, total)

        result = verify(scene, techniques, estimators, n_values, args.trials, args.seed, args.receivers,
                        args.threads, out, progress)
    command = "warpis " + " ".join(sys.argv[1:]) if sys.argv[1:] else f"warpis verify {args.scene}"
    if out is not None:
        (out / "verify.md").write_text(markdown(result, command))
        plots.calibration_plot(result.rows, out)
        for r in sorted({row["receiver"] for row in result.rows}):
            plots.convergence_plot(result.rows, r, out)
    lines = [f"{scene.name}: {len(result.rows)} cells, {result.trials} trials each, {result.seconds:.0f} s"]
    lines += summary_lines(result)
    if out is not None:
        lines.append(f"wrote {out / 'verify.json'}, {out / 'verify.md'} and figures")
    _emit(result.as_json(), args.json, "\n".join(lines))
    return 0


def cmd_study(args: argparse.Namespace) -> int:
    from pathlib import Path

    from .study import default_out, load_study

    study = load_study(Path(args.file), threads=args.threads)
    return _run_study(study, Path(args.out) if args.out else default_out(study))


def cmd_demo(args: argparse.Namespace) -> int:
    from pathlib import Path

    from .study import default_out, demo_study

    study = demo_study(threads=args.threads)
    return _run_study(study, Path(args.out) if args.out else default_out(study))


def _run_study(study, out) -> int:
    """Run a validated study into ``out`` with a bar of cells done and time left; say where it wrote."""
    from .study import run_study

    if out.exists() and not out.is_dir():
        raise WarpisError(f"{out}: --out must be a directory")
    cells = len(study.cells())
    print(f"study {study.name}: {cells} cells ({len(study.scenes)} scene(s) × {len(study.estimators)} estimator(s) "
          f"× {len(study.n)} N), {study.trials} trials each, into {out}", flush=True)
    with _progress(0, "cells") as bar:
        def progress(done: int, total: int) -> None:
            bar.bar.total = total
            bar.bar.refresh()
            bar(done, total)

        def log(line: str) -> None:
            bar.bar.write(line, file=sys.stdout)
            sys.stdout.flush()

        run = run_study(study, out, progress=progress, log=log)
    print(f"computed {run.computed} cell(s), skipped {run.skipped} already finished; "
          f"{len(run.rows)} rows in {out / 'results.csv'}")
    print(f"wrote {out / 'report.md'}, {out / 'summary.json'} and {len(run.figures)} figure file(s) in "
          f"{out / 'figures'}")
    return 0


def _int_list(text: str, option: str) -> list[int]:
    try:
        values = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise WarpisError(f"{option} takes comma-separated integers, got {text!r}") from None
    if not values or min(values) < 1:
        raise WarpisError(f"{option} takes positive integers, got {text!r}")
    return values


class _progress:
    """A tqdm bar on stderr (silent when stderr is not a terminal) fed by run_trials."""

    def __init__(self, total: int, unit: str):
        self.total, self.unit, self.bar = total, unit, None

    def __enter__(self):
        from tqdm import tqdm

        self.bar = tqdm(total=self.total, unit=self.unit, disable=None, file=sys.stderr, leave=False)
        return self

    def __call__(self, done: int, total: int) -> None:
        self.bar.update(done - self.bar.n)

    def __exit__(self, *exc) -> None:
        self.bar.close()


# --------------------------------------------------------------------------- parser


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="warpis", description="Variance of Monte Carlo direct-illumination estimators on mesh scenes, "
                                           "measured in Warp kernels and held against closed forms.")
    p.add_argument("--version", action="version", version=f"warpis {_version()}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    def scene_command(name: str, help: str) -> argparse.ArgumentParser:
        c = sub.add_parser(name, help=help, description=help)
        c.add_argument("scene", help="a bundled scene's name (see 'warpis scenes') or a scene TOML path")
        c.add_argument("--device", default="cpu", help="Warp device: cpu (default) or cuda[:N]")
        c.add_argument("--json", action="store_true", help="print JSON instead of a table")
        return c

    c = sub.add_parser("scenes", help="list the bundled scenes with triangle, emitter and receiver counts")
    c.add_argument("--device", default="cpu", help=argparse.SUPPRESS)
    c.add_argument("--json", action="store_true", help="print JSON instead of a table")
    c.set_defaults(func=cmd_scenes)

    c = scene_command("info", "load and validate one scene; print counts, emitter areas and total power")
    c.set_defaults(func=cmd_info)

    c = scene_command("reference", "reference value of F at each receiver: closed form or dense quadrature")
    c.add_argument("--receivers", type=_receiver_list, help="comma-separated receiver indices (default: all)")
    c.add_argument("--samples", type=_positive, default=4096, help="quadrature samples per replica (default 4096)")
    c.set_defaults(func=cmd_reference)

    c = scene_command("estimate", "run M independent trials of one estimator; mean, variance and its interval")
    c.add_argument("--estimator", required=True, help="PATTERN:COMBINER:TECH[+TECH...], "
                                                      "e.g. jittered:balance:light-area+cosine")
    c.add_argument("--n", type=_positive, required=True, help="samples per estimate (N)")
    c.add_argument("--trials", type=_positive, default=1000, help="independent trials (M, default 1000)")
    c.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    c.add_argument("--receivers", type=_receiver_list, help="comma-separated receiver indices (default: all)")
    c.add_argument("--threads", type=_positive, help="CPU threads (default: all cores; results do not depend on it)")
    c.set_defaults(func=cmd_estimate)

    c = scene_command("verify", "hold measured variances against the seed's equations, cell by cell")
    c.add_argument("--techniques", help="technique set A+B (default: light-area+cosine, or "
                                        "light-solid-angle+phong for glossy receivers)")
    c.add_argument("--estimators", help="comma-separated estimator specs (default: every estimator the set allows)")
    c.add_argument("--n", help="comma-separated sample counts (default 4,16,64,256,1024)")
    c.add_argument("--trials", type=_positive, default=400, help="trials per cell (default 400)")
    c.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    c.add_argument("--receivers", type=_receiver_list,
                   help="comma-separated receiver indices (default: all, or 8 spread through the list when more)")
    c.add_argument("--threads", type=_positive, help="CPU threads (default: all cores)")
    c.add_argument("--out", help="directory for verify.json, verify.md and figures")
    c.set_defaults(func=cmd_verify)

    c = sub.add_parser("study", help="run a study file (scenes × estimators × N) into results, figures and a report; "
                                     "resumable", description="run a study file (scenes × estimators × N) into "
                                                              "results.csv, summary.json, figures and report.md; "
                                                              "rerunning skips finished cells")
    c.add_argument("file", help="the study TOML (see README, 'Studies')")
    c.add_argument("--out", help="output directory (default ./warpis-out/<name>/)")
    c.add_argument("--threads", type=_positive, help="CPU threads (default: the study's, else all cores)")
    c.set_defaults(func=cmd_study)

    c = sub.add_parser("demo", help="the main job: ten estimators on occluded-quad, variance against N, "
                                    "slopes and predictions (1–2 minutes)",
                       description="run the built-in demo study (scripts/studies/demo.toml) on occluded-quad")
    c.add_argument("--out", help="output directory (default ./warpis-out/demo/)")
    c.add_argument("--threads", type=_positive, help="CPU threads (default: all cores)")
    c.set_defaults(func=cmd_demo)
    return p


def _quiet_warp(device: str) -> None:
    """Start Warp so that only its errors reach the terminal.

    On a machine without a GPU, Warp's native library prints a CUDA-driver notice to the
    process's stderr while it starts; for CPU work that is noise, so the start-up runs
    with file descriptor 2 pointed at /dev/null.
    """
    import os

    import warp as wp

    if hasattr(wp, "LOG_ERROR"):
        wp.config.log_level = wp.LOG_ERROR
    if not str(device).startswith("cpu"):
        wp.init()
        return
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            wp.init()
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _version() -> str:
    from . import __version__

    return __version__


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``warpis`` console script."""
    args = build_parser().parse_args(argv)
    _quiet_warp(getattr(args, "device", "cpu"))
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            status = args.func(args)
        for w in caught:
            if not issubclass(w.category, DeprecationWarning):
                print(f"warpis: warning: {w.message}", file=sys.stderr)
        return status
    except WarpisError as exc:
        print(f"warpis: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("warpis: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into head & co.: stop quietly
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
