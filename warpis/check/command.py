"""``warpis check``: its options, their validation, and the run behind the command.

Every option is checked before anything is sampled or written; bad input is one line,
``warpis: error: <option>: <problem>``, exit 2.  The run exits 0 when every check
passes and 1 when one fails, after printing the table (and writing ``--out``).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import Any

from .. import limits
from ..errors import WarpisError

DEFAULT_SCENE = "occluded-quad"
DEFAULT_COMBINER_TECHNIQUES = "light-area+cosine"
MIN_SAMPLES = 1000  # a chi-square of fewer samples has almost no cell to test
MAX_SAMPLES = 20_000_000  # per frame: ~1.5 GB of directions, pdfs and weights in float64
MAX_FRAMES = 64


def add_arguments(c: argparse.ArgumentParser) -> None:
    """The options of ``warpis check`` (the subject: one of --technique, --bsdfs, --combiner)."""
    g = c.add_mutually_exclusive_group(required=True)
    g.add_argument("--technique", metavar="NAME",
                   help="a technique: built in, a Warp pair (warpis.register_technique) or numpy functions "
                        "(warpis.register_numpy_technique), e.g. from --plugin")
    g.add_argument("--bsdfs", metavar="FILE", help="every BSDF of this Mitsuba 3 XML file, through Mitsuba's own "
                                                   "sample, eval and pdf (needs warpis[mitsuba] and libLLVM 19)")
    g.add_argument("--combiner", metavar="NAME",
                   help="a combiner's weights (warpis.register_numpy_combiner, or a built-in MIS heuristic)")
    c.add_argument("--techniques", metavar="A+B",
                   help=f"with --combiner: the techniques whose pdfs it weighs (default {DEFAULT_COMBINER_TECHNIQUES})")
    c.add_argument("--scene", help=f"Warp techniques and combiners: the scene whose receivers are the frames "
                                   f"(default {DEFAULT_SCENE}); numpy techniques: its receivers instead of a spread "
                                   "of views")
    c.add_argument("--receivers", metavar="0,3", help="comma-separated receiver indices of --scene (default: "
                                                      "--frames of them, spread through the list)")
    c.add_argument("--receivers-file", metavar="FILE",
                   help="with --bsdfs: the receivers file (default: <scene>.receivers.toml beside the XML)")
    c.add_argument("--frames", metavar="K", help="frames per subject: receivers, or views in a spread (default 4)")
    c.add_argument("--samples", metavar="N", help="samples per frame (default 1000000)")
    c.add_argument("--seed", metavar="S", default="0", help="random seed in [0, 2^32) (default 0)")
    c.add_argument("--significance", metavar="A",
                   help="family-wise false-failure rate of the run, Šidák over its statistical tests (default 1e-3)")
    c.add_argument("--checks", metavar="A,B", help="only these checks (default: every one that applies)")
    c.add_argument("--out", metavar="DIR", help="write index.html, check.json and a figure per check here")
    c.add_argument("--device", default="cpu", help="Warp device of Warp techniques: cpu (default) or cuda[:N]")
    c.add_argument("--json", action="store_true", help="print JSON instead of the table")


def _receiver_list(text: str | None) -> list[int] | None:
    return None if text is None else limits.receiver_list_text(text)


def _options(args: argparse.Namespace) -> dict[str, Any]:
    """Every option checked, before anything runs."""
    from .run import DEFAULT_FRAMES, DEFAULT_SAMPLES, Budget, check_significance, parse_checks

    if args.techniques is not None and args.combiner is None:
        raise WarpisError("--techniques: only with --combiner (a technique is checked with --technique)")
    if args.bsdfs is not None:
        for option, value in (("--scene", args.scene), ("--receivers", args.receivers)):
            if value is not None:
                raise WarpisError(f"{option}: not with --bsdfs (the BSDFs are seen at the file's own receivers)")
    elif args.receivers_file is not None:
        raise WarpisError("--receivers-file: only with --bsdfs (a scene's receivers are chosen with --receivers)")
    samples = DEFAULT_SAMPLES if args.samples is None else limits.count_text(args.samples, "--samples",
                                                                            minimum=MIN_SAMPLES, maximum=MAX_SAMPLES)
    frames = DEFAULT_FRAMES if args.frames is None else limits.count_text(args.frames, "--frames", maximum=MAX_FRAMES)
    seed = limits.seed(limits.count_text(args.seed, "--seed", minimum=0, maximum=2**63), "--seed")
    significance = 1e-3 if args.significance is None else check_significance(args.significance)
    budget = Budget(samples=samples, seed=seed, significance=significance, checks=parse_checks(args.checks))
    from ..runs.outdir import out_option

    return {"budget": budget, "frames": frames, "receivers": _receiver_list(args.receivers),
            "out": out_option(args.out)}


def _scene(args: argparse.Namespace, default: str | None) -> Any:
    from ..scenes import load_scene

    name = args.scene if args.scene is not None else default
    return None if name is None else load_scene(name, device=args.device)


def _technique(name: str, args: argparse.Namespace, opts: dict[str, Any]) -> tuple[str, list[Any]]:
    from ..kernels.techniques import TECHNIQUES
    from .entries import NUMPY_TECHNIQUES
    from .subjects import numpy_technique, numpy_technique_at, warp_technique

    if name in NUMPY_TECHNIQUES:
        entry = NUMPY_TECHNIQUES[name]
        scene = _scene(args, None)
        if scene is None:
            return f"numpy technique {name} at a spread of views", [numpy_technique(entry, opts["frames"])]
        subject = numpy_technique_at(entry, scene, opts["receivers"], opts["frames"])
        return f"numpy technique {name} at receivers of {scene.name}", [subject]
    if name not in TECHNIQUES:
        valid = ", ".join(list(TECHNIQUES) + list(NUMPY_TECHNIQUES))
        raise WarpisError(f"--technique: unknown technique {name!r} (valid: {valid})")
    scene = _scene(args, DEFAULT_SCENE)
    from ..kernels.techniques import check_lights

    check_lights(scene, [name], estimates_f=False)
    subject = warp_technique(scene, name, opts["receivers"], opts["frames"])
    return f"{subject.kind} {name} at receivers of {scene.name}", [subject]


def _combiner(name: str, args: argparse.Namespace, opts: dict[str, Any]) -> tuple[str, Any]:
    from ..kernels.estimators import COMBINERS
    from ..kernels.techniques import TECHNIQUES, check_lights
    from .entries import NUMPY_COMBINERS, NUMPY_TECHNIQUES
    from .run import CombinerSubject
    from .subjects import builtin_weights, numpy_technique_at, warp_technique

    if name in NUMPY_COMBINERS:
        weights = NUMPY_COMBINERS[name].weights
    elif name in COMBINERS:
        weights = builtin_weights(COMBINERS[name])
    else:
        valid = ", ".join(list(COMBINERS) + list(NUMPY_COMBINERS))
        raise WarpisError(f"--combiner: unknown combiner {name!r} (valid: {valid})")
    names = [t.strip() for t in (args.techniques or DEFAULT_COMBINER_TECHNIQUES).split("+")]
    if len(names) < 2 or len(set(names)) != len(names) or not all(names):
        raise WarpisError(f"--techniques: a combiner weighs two or more different techniques, got {args.techniques!r}")
    for t in names:
        if t not in TECHNIQUES and t not in NUMPY_TECHNIQUES:
            valid = ", ".join(list(TECHNIQUES) + list(NUMPY_TECHNIQUES))
            raise WarpisError(f"--techniques: unknown technique {t!r} (valid: {valid})")
    scene = _scene(args, DEFAULT_SCENE)
    check_lights(scene, [t for t in names if t in TECHNIQUES], estimates_f=False)
    subjects = [numpy_technique_at(NUMPY_TECHNIQUES[t], scene, opts["receivers"], opts["frames"])
                if t in NUMPY_TECHNIQUES else warp_technique(scene, t, opts["receivers"], opts["frames"])
                for t in names]
    title = f"combiner {name} over {'+'.join(names)} at receivers of {scene.name}"
    return title, CombinerSubject(name, weights, subjects)


def run_command(args: argparse.Namespace, emit: Callable[[Any, bool, str], None]) -> int:
    """``warpis check``: 0 when every check passes, 1 when one fails."""
    from . import report

    opts = _options(args)
    out = opts["out"]
    if out is None:
        run = _run(args, opts)
    else:
        from ..runs.outdir import locked

        # Locked before the run: a folder in use, or one that cannot be written, fails at
        # once; a folder created here is removed again if the run then refuses its input.
        with locked(out):
            run = _run(args, opts)
            command = "warpis " + " ".join(sys.argv[1:]) if sys.argv[1:] else "warpis check"
            report.write_report(run, out, command)
    lines = report.table_lines(run)
    if out is not None:
        lines.append(f"wrote {out / 'index.html'}, {out / 'check.json'} and "
                     f"{sum(v.figure is not None for v in run.verdicts)} figure(s) in {out / 'figures'}")
    emit(report.json_safe(run.as_dict()), args.json, "\n".join(lines))
    return 0 if run.passed else 1


def _run(args: argparse.Namespace, opts: dict[str, Any]) -> Any:
    from .run import run_combiner, run_subjects

    budget = opts["budget"]
    if args.combiner is not None:
        title, combiner = _combiner(args.combiner, args, opts)
        return run_combiner(title, combiner, budget)
    if args.technique is not None:
        title, subjects = _technique(args.technique, args, opts)
    else:
        from .mitsuba_bsdfs import bsdf_subjects

        subjects = bsdf_subjects(args.bsdfs, opts["frames"], args.receivers_file)
        title = f"every BSDF of {args.bsdfs}: {len(subjects)}"
    return run_subjects(title, subjects, budget)
