"""What ``warpis check`` checks: a subject seen in frames, each frame a sampler and its densities.

A :class:`Frame` is one shading frame (a receiver of a scene, or a view in a fixed local
frame) in which a subject draws directions and evaluates its pdf (and, for a BSDF, its
``eval``).  A :class:`Subject` is a named set of frames plus what applies to it as a
whole.  Warp techniques are seen at receivers of a scene (``sample_directions`` /
``direction_pdf``), numpy techniques at a spread of views about a tilted normal, Mitsuba
BSDFs at their scene's receivers (:mod:`.mitsuba_bsdfs`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import WarpisError
from ..kernels.techniques import TECHNIQUES, direction_pdf, sample_directions
from ..testing import orthonormal_frame
from .entries import NumpyTechnique

# Rows per call of a user's numpy function: bounds its temporaries, not its results.
NUMPY_BATCH = 1 << 20
# Views of a spread: θo from 0 to this, about a tilted normal (not an axis of the world,
# so that a technique that assumes n = z is caught).
SPREAD_MAX_DEGREES = 80.0
SPREAD_NORMAL = np.array([0.3, -0.2, 0.93]) / np.linalg.norm([0.3, -0.2, 0.93])
SPREAD_AZIMUTH = 0.7
# The measure check moves the receiver so that its distance to the emitters doubles.
MOVE_FACTOR = 2.0


@dataclass
class Draw:
    """Directions a frame's sampler drew."""

    dirs: NDArray  # (N, 3) float64, unit where valid, 0 elsewhere
    valid: NDArray  # (N,) bool: the sampler produced a direction
    reported: NDArray | None = None  # (N,) the density the sampler reports at each, if it reports one
    weight: NDArray | None = None  # (N, C) the sampler's own eval/pdf (a BSDF's sample weight), if any


@dataclass
class Frame:
    """One frame of a subject: its sampler, its pdf and, for a BSDF, its eval."""

    label: str
    normal: NDArray  # (3,) the frame's normal: the chi-square grid's pole for broad lobes
    draw: Callable[[int, int], Draw]  # (count, seed)
    pdf: Callable[[NDArray], NDArray]  # (K, 3) → (K,) solid-angle density
    eval: Callable[[NDArray], NDArray] | None = None  # (K, 3) → (K, C): BSDF × |cos θ|
    # (count, seed) → f(a → b), f(b → a), each (K, C), for pairs where the BSDF claims reciprocity
    reciprocity: Callable[[int, int], tuple[NDArray, NDArray]] | None = None
    # The same frame with the light moved away (MOVE_FACTOR × the distance), for the measure check
    moved: Callable[[], Frame] | None = None
    receiver: int | None = None  # the scene receiver it is, for the unbiasedness check


@dataclass
class Unbiasedness:
    """Estimates of F by a technique at scene receivers, against Lambert's closed form."""

    run: Callable[[int, int], list[tuple[str, float, float, float]]]  # (trials, seed) → (label, mean, se, ref)
    receivers: int  # how many receivers it holds (the family counts each)


@dataclass
class Subject:
    """A technique, a BSDF or a combiner, as the checks see it."""

    kind: str  # "Warp technique", "numpy technique", "Mitsuba BSDF", "combiner"
    name: str
    frames: list[Frame]
    unbiased: Unbiasedness | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def label(self) -> str:
        return f"{self.kind} {self.name}"


# --------------------------------------------------------------------------- Warp techniques


def _receivers(scene: Any, receivers: Sequence[int] | None, frames: int) -> list[int]:
    """The receivers asked for, or ``frames`` spread evenly through the scene's list."""
    count = len(scene.receivers)
    if receivers is not None:
        bad = [r for r in receivers if not 0 <= r < count]
        if bad:
            raise WarpisError(f"--receivers: receiver {bad[0]} does not exist (scene {scene.name!r} has {count})")
        return list(dict.fromkeys(int(r) for r in receivers))
    return sorted({int(round(x)) for x in np.linspace(0, count - 1, min(frames, count))})


def warp_technique(scene: Any, technique: str, receivers: Sequence[int] | None, frames: int) -> Subject:
    """A Warp technique (built in or registered) at receivers of ``scene``."""
    entry = TECHNIQUES.lookup(technique)
    out = [_warp_frame(scene, technique, r, moved=entry.light) for r in _receivers(scene, receivers, frames)]
    kind = "Warp technique" + (" (light)" if entry.light else "")
    unbiased = _warp_unbiasedness(scene, technique, [f.receiver for f in out]) if entry.light else None
    notes = [f"frames: receivers of {scene.name}"]
    return Subject(kind, technique, out, unbiased, notes)


def _warp_frame(scene: Any, technique: str, r: int, moved: bool) -> Frame:
    rx = scene.receivers

    def draw(count: int, seed: int) -> Draw:
        u = np.random.default_rng([seed, r]).random((count, 2), dtype=np.float32)
        d, p = sample_directions(scene, r, technique, u)
        return _draw(np.asarray(d, np.float64), np.asarray(p, np.float64), reported=True)

    def pdf(dirs: NDArray) -> NDArray:
        return np.asarray(direction_pdf(scene, r, technique, dirs), np.float64)

    frame = Frame(_receiver_label(scene, r), np.asarray(rx.normals[r], np.float64), draw, pdf, receiver=r)
    if moved and scene.light_count:
        frame.moved = lambda: _warp_frame(_moved_receiver(scene, r), technique, r, moved=False)
    return frame


def _receiver_label(scene: Any, r: int) -> str:
    """"receiver r", with its group's name where the scene has several groups."""
    rx = scene.receivers
    if len(rx.group_names) > 1:
        return f"receiver {r} ({rx.group_names[rx.group[r]]})"
    return f"receiver {r}"


def light_centroid(scene: Any) -> NDArray:
    """The area-weighted centroid of the scene's lights: emitter triangles and sphere lights."""
    centres = [scene.triangle_vertices(scene.emitters).mean(axis=1)]
    if scene.spheres is not None:
        centres.append(scene.spheres.centers[scene.sphere_lights])
    areas = np.asarray(scene.light_areas, np.float64)
    return (np.concatenate(centres) * areas[:, None]).sum(axis=0) / areas.sum()


def _moved_receiver(scene: Any, r: int) -> Any:
    """``scene`` with receiver r moved along the line from the emitters' centroid through
    it, to MOVE_FACTOR × its distance: the light, as the receiver sees it, moved away.
    (Moving the receiver, not the emitters, moves a light that a technique hard-codes too.)"""
    centroid = light_centroid(scene)
    positions = np.array(scene.receivers.positions, np.float64)
    positions[r] = centroid + MOVE_FACTOR * (positions[r] - centroid)
    rx = replace(scene.receivers, positions=positions)
    return replace(scene, receivers=rx, name=f"{scene.name} (light moved away)")


def _warp_unbiasedness(scene: Any, technique: str, receivers: list[int]) -> Unbiasedness:
    from ..analysis.reference import reference
    from ..kernels.engine import run_trials

    def run(trials: int, seed: int) -> list[tuple[str, float, float, float]]:
        # A tiny fixed quadrature for receivers without a closed form: they are dropped.
        refs = [ref for ref in reference(scene, receivers, samples=256) if ref.method == "closed-form"]
        if not refs:
            return []
        values = run_trials(scene, f"independent:single:{technique}", 16, trials, seed=seed,
                            receivers=[ref.index for ref in refs])
        out = []
        for ref, row in zip(refs, values):
            out.append((f"receiver {ref.index}", float(row.mean()), float(row.std(ddof=1) / math.sqrt(len(row))),
                        ref.value))
        return out

    return Unbiasedness(run, len(receivers))


def _draw(dirs: NDArray, pdf: NDArray | None, reported: bool, weight: NDArray | None = None) -> Draw:
    """A Draw from raw directions: a sample wherever the direction is finite and not zero.

    A direction whose reported pdf is 0 is still a sample (an estimator would drop it and
    lose that direction's share of F): the zero-pdf check counts it.
    """
    norms = np.linalg.norm(dirs, axis=1)
    valid = np.all(np.isfinite(dirs), axis=1) & (norms > 0.0)
    unit = np.where(valid[:, None], dirs / np.where(valid, norms, 1.0)[:, None], 0.0)
    rep = None
    if reported and pdf is not None:
        rep = np.where(valid, pdf, 0.0)
    return Draw(unit, valid, rep, weight)


# --------------------------------------------------------------------------- numpy techniques


def spread_views(count: int) -> list[tuple[NDArray, NDArray, str]]:
    """(normal, view, label) of ``count`` views, θo evenly from 0° to SPREAD_MAX_DEGREES."""
    b1, b2, n = orthonormal_frame(SPREAD_NORMAL)
    out = []
    for deg in np.linspace(0.0, SPREAD_MAX_DEGREES, count) if count > 1 else [45.0]:
        t = math.radians(deg)
        wo = math.sin(t) * (math.cos(SPREAD_AZIMUTH) * b1 + math.sin(SPREAD_AZIMUTH) * b2) + math.cos(t) * n
        out.append((n, wo / np.linalg.norm(wo), f"view θo = {deg:.0f}°"))
    return out


def numpy_technique(entry: NumpyTechnique, frames: int) -> Subject:
    """A numpy technique at a spread of views."""
    out = [_numpy_frame(entry, n, wo, label) for n, wo, label in spread_views(frames)]
    notes = [f"frames: {frames} views about the normal {np.array2string(SPREAD_NORMAL, precision=3)}"]
    if entry.eval is not None:
        notes.append("eval given: the checks of a BSDF apply")
    return Subject("numpy technique", entry.name, out, None, notes)


def numpy_technique_at(entry: NumpyTechnique, scene: Any, receivers: Sequence[int] | None, frames: int) -> Subject:
    """A numpy technique in the frames (normal, view) of receivers of ``scene``."""
    rx = scene.receivers
    out = [_numpy_frame(entry, np.asarray(rx.normals[r], np.float64), np.asarray(rx.view[r], np.float64),
                        _receiver_label(scene, r)) for r in _receivers(scene, receivers, frames)]
    return Subject("numpy technique", entry.name, out, None, [f"frames: receivers of {scene.name}"])


def builtin_weights(combiner: Any) -> Callable[[NDArray], NDArray]:
    """A built-in combiner's MIS weights w_k(ω) from its numpy twin ψ_k (f = 1): w_k = ψ_k g_k,
    over N_g where ψ is that of a mean over all N samples (balance, mixture)."""
    if not combiner.several or not combiner.unbiased or combiner.weights is None or combiner.every_sample:
        raise WarpisError(f"--combiner {combiner.name}: not a set of MIS weights over several techniques "
                          f"(the check holds weights that sum to 1: mixture, balance, power, maximum, cutoff)")
    from ..vocabulary import WeightContext

    ctx = WeightContext(parameter=None if combiner.parameter is None else combiner.parameter.default)
    per_n = combiner.divides_by_n or combiner.random_pick

    def weights(pdfs: NDArray) -> NDArray:
        n_g = pdfs.shape[1]
        f = np.ones(len(pdfs))
        out = np.zeros_like(pdfs)
        for k in range(n_g):
            with np.errstate(divide="ignore", invalid="ignore"):
                psi = np.where(pdfs[:, k] > 0.0, combiner.weights(k, f, pdfs, ctx), 0.0)
            out[:, k] = psi * pdfs[:, k] / (n_g if per_n else 1)
        return out

    return weights


def _user_call(entry: NumpyTechnique, role: str, f: Callable[..., Any], *args: NDArray) -> Any:
    """A user's function on one batch; whatever it raises is one line naming it."""
    try:
        return f(*args)
    except WarpisError:
        raise
    except Exception as exc:  # a user's code: reported, not a traceback
        first = str(exc).strip().splitlines()
        raise WarpisError(f"technique {entry.name!r}: {role} raised {type(exc).__name__}"
                          + (f": {first[0]}" if first else "")) from None


def _as_array(entry: NumpyTechnique, role: str, value: Any, shape: tuple[int, ...]) -> NDArray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise WarpisError(f"technique {entry.name!r}: {role} returned {type(value).__name__}, not numbers") from None
    if a.shape != shape:
        raise WarpisError(f"technique {entry.name!r}: {role} returned shape {a.shape} for {shape[0]} rows, "
                          f"expected {shape}")
    return a


def _in_batches(count: int, call: Callable[[slice], Any]) -> list[Any]:
    return [call(slice(start, min(start + NUMPY_BATCH, count))) for start in range(0, count, NUMPY_BATCH)]


def _numpy_frame(entry: NumpyTechnique, n: NDArray, wo: NDArray, label: str) -> Frame:
    def frame_arrays(k: int) -> tuple[NDArray, NDArray]:
        return np.tile(n, (k, 1)), np.tile(wo, (k, 1))

    def draw(count: int, seed: int) -> Draw:
        u = np.random.default_rng(seed).random((count, 2))
        parts = _in_batches(count, lambda s: _sample_batch(u[s]))
        dirs = np.concatenate([p[0] for p in parts])
        reported = None if parts[0][1] is None else np.concatenate([p[1] for p in parts])
        return _draw(dirs, reported, reported=reported is not None)

    def _sample_batch(u: NDArray) -> tuple[NDArray, NDArray | None]:
        k = len(u)
        out = _user_call(entry, "sample", entry.sample, *frame_arrays(k), u.copy())
        if isinstance(out, tuple):
            if len(out) != 2:
                raise WarpisError(f"technique {entry.name!r}: sample returned a tuple of {len(out)}, expected w "
                                  f"or (w, pdf)")
            return _as_array(entry, "sample's w", out[0], (k, 3)), _as_array(entry, "sample's pdf", out[1], (k,))
        return _as_array(entry, "sample", out, (k, 3)), None

    def pdf(dirs: NDArray) -> NDArray:
        def one(s: slice) -> NDArray:
            k = len(dirs[s])
            return _as_array(entry, "pdf", _user_call(entry, "pdf", entry.pdf, *frame_arrays(k), dirs[s].copy()),
                             (k,))
        return np.concatenate(_in_batches(len(dirs), one)) if len(dirs) else np.zeros(0)

    frame = Frame(label, n, draw, pdf)
    if entry.eval is not None:
        frame.eval = lambda dirs: _numpy_eval(entry, frame_arrays, dirs)
    return frame


def _numpy_eval(entry: NumpyTechnique, frame_arrays: Callable[[int], tuple[NDArray, NDArray]],
                dirs: NDArray) -> NDArray:
    assert entry.eval is not None

    def one(s: slice) -> NDArray:
        k = len(dirs[s])
        value = _user_call(entry, "eval", entry.eval, *frame_arrays(k), dirs[s].copy())
        a = np.asarray(value, dtype=np.float64) if not isinstance(value, (str, bytes)) else None
        if a is None or a.ndim not in (1, 2) or a.shape[0] != k:
            shape = getattr(a, "shape", type(value).__name__)
            raise WarpisError(f"technique {entry.name!r}: eval returned shape {shape} for {k} rows, expected ({k},) "
                              f"or ({k}, C)")
        return a.reshape(k, -1)

    return np.concatenate(_in_batches(len(dirs), one)) if len(dirs) else np.zeros((0, 1))
