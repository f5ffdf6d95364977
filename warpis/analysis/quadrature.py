"""Reference quantities from dense u-space evaluation: exact variances, moments, the optimal α.

Everything is built from the same Warp integrand and techniques the estimators use: at
dense jittered points u of each technique's primary-sample square, a kernel returns
f(T_k(u)) and the pdf of every technique of the set at T_k(u).  From those:

* **Exact variance of any estimator** (``exact_variance``).  Every pattern splits one
  technique's m samples into independent *blocks* (its ``blocks`` in vocabulary.PATTERNS):
  ``independent`` has m blocks, each one point over the whole square; ``jittered`` m
  blocks, one per cell; ``antithetic`` m/2 blocks, each the pair (u, 1−u) over the whole
  square; ``jittered-antithetic`` m/2 blocks, the pair (u, reflect(u)) with u in cell
  i < m/2.  An estimate is c·Σ_k Σ_blocks (block
  sum of ψ_k), ψ_k the combiner's weighted value of a sample of technique k (its
  ``weights`` in vocabulary.COMBINERS), so
  Var = c² Σ_k Σ_b Var(block sum) — a sum of within-block variances, never a difference of
  two large numbers.  The mixture's random technique choice enters through the moments
  given u: E[ψ|u] = mean_k ψ_k(u), E[ψ²|u] = mean_k ψ_k(u)².
* **Point sets that are not independent blocks** (lhs, lattice, sobol, halton): their
  pattern's pair form (``Pattern.sum_variance``, point_sets) gives Var(Σ ψ) of
  each technique stream from ψ at the points it asks for (``pair_variance``).
* **Optimal MIS**: the oracle's α = A⁻¹b per receiver (``optimal_alpha``, which the
  engine passes to the kernel), and Kondapaneni et al.'s optimum (1/m)(∫ f²/Σg − bᵀA⁻¹b)
  (the form ``optimal-ab``).
* **Exact variances of many receivers** (``exact_variances``, a variance image): the
  same at a fixed density, every receiver of a launch at the same points.
* **Reference moments** (``moments``): I, I_k, E_ḡ[h²], E_{g_k}[(f/g_k)²], ∫ f g_k,
  ∫ f² g_k, ∫ f², ∫ 1/g_k, and the stratum integrals J_ik.

The seed's equations built from these are :mod:`warpis.analysis.theory`'s.

Accuracy: each quantity is computed from R independent replicas of the jittered points.
Block variances use E[Q] − E[P]² with E[P]² estimated from *pairs of different replicas*,
which is unbiased; the standard error comes from a jackknife over replicas.  For one
receiver (``exact_variance``) the density is raised (×4 points per block) until the
relative error is below ``REL_TOL`` or the point budget is spent, which the result then
says; for many (``exact_variances``) it is the caller's, and the stderr says what it gave.
"""

from __future__ import annotations

import hashlib
import math
import threading
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from .. import limits
from ..errors import WarpisError
from ..kernels.device import DeviceScene, upload
from ..kernels.engine import register_oracle
from ..limits import default_threads
from ..kernels.estimators import COMBINERS, Estimator, parse_estimator
from ..kernels.patterns import PATTERNS
from ..kernels.registered import registered_kernels
from ..kernels.techniques import TECHNIQUES, check_lights, light_table
from ..scenes import Scene
from ..vocabulary import Blocks, WeightContext
from ..point_sets import MAX_POINTS_PER_CALL
from . import memo

REL_TOL = 0.01
REPLICAS = 8
MIN_POINTS = 1 << 17  # per technique and block layout, over all replicas
MAX_POINTS = 1 << 20  # per technique and block layout, over all replicas
SEED = 0x7E0


# --------------------------------------------------------------------------- kernel


@dataclass(frozen=True)
class Evaluator:
    """The evaluate kernel (:mod:`warpis.kernels.evaluate`, the registry's: it knows the
    user techniques) bound to one scene's upload and one technique set."""

    up: DeviceScene  # held until the launches are done: the structs know their mesh by id only
    table: Any  # LightTable
    codes: Any  # wp.array of the techniques' codes
    kernel: Any
    techniques: int
    names: tuple[str, ...]  # the technique set

    @classmethod
    def of(cls, scene: Scene, techniques: tuple[str, ...]) -> Evaluator:
        check_lights(scene, techniques)
        up = upload(scene)
        codes = wp.array(np.array([TECHNIQUES[t].code for t in techniques], np.int32), dtype=wp.int32,
                         device=up.device)
        return cls(up, light_table(scene), codes, registered_kernels().evaluate, len(techniques),
                   tuple(techniques))

    @property
    def cpu(self) -> bool:
        return wp.get_device(self.up.device).is_cpu

    def load(self) -> None:
        """Compile the kernel once, before threads race to."""
        wp.load_module(self.kernel.module, device=self.up.device)

    def __call__(self, rows: np.ndarray, k: int, u: np.ndarray, pieces: int = 1, every: bool = False
                 ) -> tuple[np.ndarray, np.ndarray]:
        """f (R, P) and the pdfs (R, P, N_g; 0 where f is, unless ``every``; 0 at a failed
        sample) at T_k(u) seen from receivers ``rows`` (R,), for points u (P, 2).  The
        points split into ``pieces`` launches on as many threads (a CPU launch runs on one
        core and releases the GIL)."""
        dev = self.up.device
        receivers = wp.array(np.asarray(rows, np.int32), dtype=wp.int32, device=dev)
        f_all = np.empty((len(rows), len(u)))
        pdf_all = np.empty((len(rows), len(u), self.techniques))

        def run(lo: int, hi: int) -> None:
            uu = wp.array(np.ascontiguousarray(u[lo:hi], np.float32), dtype=wp.vec2, device=dev)
            f = wp.empty((len(rows), hi - lo), dtype=wp.float64, device=dev)
            pdf = wp.empty((len(rows), hi - lo, self.techniques), dtype=wp.float64, device=dev)
            wp.launch(self.kernel, dim=(len(rows), hi - lo), device=dev,
                      inputs=[self.up.data, self.up.receiver_data, self.table, receivers, self.codes, k, uu,
                              int(every), f, pdf])
            f_all[:, lo:hi] = f.numpy()
            pdf_all[:, lo:hi] = pdf.numpy()

        if pieces <= 1:
            run(0, len(u))
            return f_all, pdf_all
        bounds = [int(b) for b in np.linspace(0, len(u), pieces + 1)]
        with ThreadPoolExecutor(max_workers=pieces) as pool:
            for fut in [pool.submit(run, lo, hi) for lo, hi in zip(bounds[:-1], bounds[1:])]:
                fut.result()
        return f_all, pdf_all


def evaluate(scene: Scene, receiver: int, techniques: tuple[str, ...], k: int, u: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """f (P,) and the pdfs (P, N_g) of all ``techniques`` at T_k(u) for points u (P, 2).

    The pdfs are found only where f > 0 and are 0 elsewhere (every weighted value is 0
    there).  On the CPU the points are split over the engine's worker threads (one launch
    each).
    """
    ev = Evaluator.of(scene, techniques)
    pieces = default_threads() if ev.cpu and len(u) >= 1 << 14 else 1
    if pieces > 1:
        ev.load()
    f, pdf = ev(np.array([receiver], np.int32), k, u, pieces)
    return f[0], pdf[0]


def weighted_values(combiner: str, k: int, f: np.ndarray, pdf: np.ndarray, ctx: WeightContext = WeightContext()
                    ) -> np.ndarray:
    """ψ_k: the value a sample of technique k adds to the combiner's sum (its registry
    entry's numpy weights; see estimators.py), 0 where f or g_k is 0 unless the combiner
    counts every sample (its weights then say what a failed sample adds)."""
    entry = COMBINERS[combiner]
    if entry.weights is None:  # exact_form_problem tells the callers first
        raise WarpisError(f"combiner {combiner!r} has no numpy weights")
    if ctx.parameter is None and entry.parameter is not None:
        ctx = WeightContext(entry.parameter.default, ctx.alpha)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = entry.weights(k, f, pdf, ctx)
    if entry.every_sample:
        return out
    return np.where((pdf[:, k] > 0) & (f > 0), out, 0.0)


# Dense points per technique and receiver behind the optimal-oracle's α (a 64 × 64 jittered grid).
ORACLE_POINTS = 1 << 12


def optimal_alpha(scene: Scene, receivers: Sequence[int], techniques: tuple[str, ...], points: int = ORACLE_POINTS,
                  seed: int = SEED) -> np.ndarray:
    """α = A⁻¹b of Kondapaneni et al.'s optimal MIS at each receiver ((R, N_g)), the
    coefficients the optimal-oracle uses (docs/theory.md, "Optimal MIS").

    A_ij = ∫ g_i g_j / Σ_l g_l and b_i = ∫ f g_i / Σ_l g_l over the extended domain (a
    failed sample of technique k is a point of its own where only g_k is non-zero), each
    estimated as Σ_t E_t[r_i r_j] and Σ_t E_t[(f/Σ_l g_l) r_i] with r = g/Σ_l g_l (r = e_t
    at technique t's failures), over sub × sub jittered points of every technique.  The
    points depend only on ``seed`` and ``points``, and each receiver's α only on its own
    values, so a receiver's α is the same whatever else is asked for: it is kept with the
    scene's upload.  α = 0 (the balance heuristic) where A is singular to working
    precision, as in the kernel's pilot.
    """
    rows = limits.receiver_indices(receivers, "optimal_alpha: receivers", len(scene.receivers))
    cache = upload(scene).cached("optimal_alpha", dict)

    def key(r: int) -> tuple:
        return r, tuple(techniques), points, seed

    missing = np.array([r for r in dict.fromkeys(rows.tolist()) if key(r) not in cache], np.int32)
    if len(missing):
        for r, alpha in zip(missing.tolist(), _solve_alpha(scene, missing, tuple(techniques), points, seed)):
            cache[key(r)] = alpha
    return np.array([cache[key(r)] for r in rows.tolist()]).reshape(len(rows), len(techniques))


def extended_terms(f: np.ndarray, pdf: np.ndarray, t: int) -> tuple[np.ndarray, np.ndarray]:
    """r = g/Σ_l g_l (e_t at a failed sample of technique t, where every pdf is 0) and
    f/Σ_l g_l (0 there), from f (...,) and the pdfs (..., N_g) of technique t's samples:
    the terms of A and b over the extended domain (estimators.optimal_terms in the kernel)."""
    total = pdf.sum(axis=-1, keepdims=True)
    valid = pdf[..., t:t + 1] > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        return (np.where(valid, pdf / total, np.eye(pdf.shape[-1])[t]),
                np.where(valid[..., 0], f / total[..., 0], 0.0))


def _solve_alpha(scene: Scene, rows: np.ndarray, techniques: tuple[str, ...], points: int, seed: int) -> np.ndarray:
    n_g = len(techniques)
    sub = max(1, math.isqrt(points))
    u = jittered_points(Blocks(1, 1, (1, 1), False), sub, 1, np.random.default_rng([seed, sub, 0xA1FA])).reshape(-1, 2)
    ev = Evaluator.of(scene, techniques)
    a = np.zeros((len(rows), n_g, n_g))
    b = np.zeros((len(rows), n_g))

    def chunk(lo: int, hi: int, pieces: int) -> None:
        for t in range(n_g):
            r, fs = extended_terms(*ev(rows[lo:hi], t, u, pieces, every=True), t)
            a[lo:hi] += np.einsum("rpi,rpj->rij", r, r) / len(u)
            b[lo:hi] += np.einsum("rp,rpi->ri", fs, r) / len(u)

    most = max(1, CHUNK_BYTES // (8 * len(u) * (3 * n_g + 4)))
    _run_chunks(ev, len(rows), most, default_threads(), chunk, None)
    largest = np.max(np.diagonal(a, axis1=1, axis2=2), axis=1)
    singular = ~(np.abs(np.linalg.det(a)) > 1e-10 * largest ** n_g)
    a[singular] = np.eye(n_g)
    alpha = np.linalg.solve(a, b[..., None])[..., 0]
    alpha[singular] = 0.0
    return alpha


# --------------------------------------------------------------------------- blocks


def jittered_points(blocks: Blocks, sub: int, replicas: int, rng: np.random.Generator) -> np.ndarray:
    """Jittered points: (replicas, blocks, sub², 2), sub × sub strata inside each block's cell."""
    rows, cols = blocks.cells
    b = np.arange(blocks.count)
    r0, c0 = (b // cols)[:, None], (b % cols)[:, None]
    s = np.arange(sub * sub)
    sy, sx = (s // sub)[None, :], (s % sub)[None, :]
    jitter = rng.random((replicas, blocks.count, sub * sub, 2))
    x = (c0 + (sx + jitter[..., 0]) / sub) / cols
    y = (r0 + (sy + jitter[..., 1]) / sub) / rows
    return np.minimum(np.stack([x, y], axis=-1), np.float32(0.99999994))


def _centres(blocks: Blocks) -> np.ndarray:
    rows, cols = blocks.cells
    b = np.arange(blocks.count)
    return np.stack([((b % cols) + 0.5) / cols, ((b // cols) + 0.5) / rows], axis=-1)


def _reflect(u: np.ndarray) -> np.ndarray:
    return np.minimum(1.0 - u, np.float32(0.99999994))


@dataclass
class Estimate:
    """A predicted quantity with its standard error (relative error = stderr/|value|)."""

    value: float
    stderr: float
    points: int = 0

    @property
    def rel_error(self) -> float:
        if self.value == 0:
            return 0.0 if self.stderr == 0 else math.inf
        return abs(self.stderr / self.value)


def _estimate_json(e: Estimate) -> list:
    return [e.value, e.stderr, e.points]


def _estimate_of(d: list) -> Estimate:
    value, stderr, points = d
    return Estimate(float(value), float(stderr), int(points))


def _unbiased_block_variance(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Σ over blocks of E[Q] − E[P]², from per-replica block means q, p of shape (..., B, r).

    E[P]² is estimated by the mean over ordered pairs of *different* replicas of
    p_a · p_b, which is unbiased because replicas are independent.  Every sum runs over
    the last axis, so a receiver's value does not depend on the others in the array.
    """
    r = q.shape[-1]
    sp = p.sum(axis=-1)
    pairs = (sp * sp - (p * p).sum(axis=-1)) / (r * (r - 1))
    return (q.mean(axis=-1) - pairs).sum(axis=-1)


def _jackknife(q: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The unbiased block variance and its jackknife stderr over replicas, for per-replica
    block means q, p of shape (R, B, r): each (R,)."""
    r = q.shape[-1]
    full = _unbiased_block_variance(q, p)
    leave = np.stack([_unbiased_block_variance(np.delete(q, a, -1), np.delete(p, a, -1)) for a in range(r)], -1)
    spread = ((leave - leave.mean(axis=-1, keepdims=True)) ** 2).sum(axis=-1)
    return full, np.sqrt(np.maximum((r - 1) / r * spread, 0.0))


# --------------------------------------------------------------------------- exact variance


# Float64 working memory of one chunk of receivers (kernel outputs and the numpy
# reductions): receivers are chunked so that a chunk stays about this size (one receiver
# at least, whatever its points need).
CHUNK_BYTES = 128 << 20


@dataclass(frozen=True, eq=False)
class Variances:
    """Exact variances of one estimate at many receivers, at a fixed density."""

    value: np.ndarray  # (R,) exact variance of one estimate at each receiver
    stderr: np.ndarray  # (R,) jackknife standard error over replicas
    points: int  # dense points evaluated per receiver (all techniques, all replicas)

    @property
    def rel_error(self) -> np.ndarray:
        """stderr/|value| (0 where both are 0, inf where only the value is)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.value == 0, np.where(self.stderr == 0, 0.0, math.inf),
                            np.abs(self.stderr / self.value))


def exact_form_problem(est: Estimator) -> str | None:
    """Why ``est`` has no exact variance (an entry registered without its theory, or a
    combiner whose variance has no closed form), or None."""
    pattern = est.pattern_entry
    if pattern.blocks is None and pattern.sum_variance is None:
        return f"pattern {est.pattern!r} has no block decomposition nor pair form, so no exact variance"
    if est.combiner_entry.weights is None:
        reason = est.combiner_entry.no_exact_form or "it has no numpy weights"
        return f"combiner {est.combiner!r} has no exact variance: {reason}"
    return None


def _exact_estimator(estimator: str | Estimator, n: int) -> tuple[Estimator, int, Blocks | None, float]:
    """The estimator, m, the blocks of each technique's m samples (None for a pattern with
    a pair form) and the factor of Var = factor · Σ_k Σ_b Var(block sum) (c² · multiplicity;
    c² for a pair form, whose Var(Σ ψ) covers all m points); a one-line WarpisError for an
    N it cannot take or where it has no exact form."""
    est = parse_estimator(estimator)
    est.check_n(n)
    problem = exact_form_problem(est)
    if problem:
        raise WarpisError(f"estimator {est.spec!r}: {problem}")
    m = est.per_technique(n)
    c = est.combiner_entry.scale(m, est.technique_count)
    if est.pattern_entry.blocks is None:
        return est, m, None, c * c
    blocks = est.pattern_entry.blocks(m)
    return est, m, blocks, c * c * blocks.multiplicity


def exact_variances(scene: Scene, receivers: Sequence[int], estimator: str | Estimator, n: int,
                    points: int = 1 << 12, seed: int = SEED, threads: int | None = None,
                    progress: Callable[[int, int], None] | None = None) -> Variances:
    """The exact variance of one estimate (N = ``n``) at each of ``receivers``, at a fixed density.

    The mathematics of :func:`exact_variance` for many receivers at once (a variance
    image), with no refinement: ``points`` is the budget of dense points per technique
    and receiver over all ``REPLICAS`` replicas.  Each block's cell gets sub × sub jittered
    strata, sub the largest with blocks · sub² · REPLICAS ≤ ``points`` (at least 1), so
    fewer points than asked are used where the budget is not of that form, and more
    (blocks · REPLICAS) where it is below one point per block and replica; paired
    patterns also evaluate the reflected points.  The stderr says how good the result
    is: it falls as 1/√points on smooth integrands (faster still where stratification
    helps), so ×4 points roughly halves it.

    Every receiver sees the same points (drawn from ``seed`` and the block layout), so a
    receiver's value does not depend on which others are asked for, nor on ``threads``.
    Receivers are taken in equal chunks of at most about ``CHUNK_BYTES`` of float64
    working memory each; on the CPU the chunks run on ``threads`` worker threads (default
    the engine's), one launch per chunk and technique.
    ``progress(receivers_done, receivers_total)`` is called after each chunk, in the
    calling thread.

    Raises a one-line WarpisError where the estimator has no exact form
    (``exact_form_problem``), cannot take N = ``n``, or ``points``, ``receivers``,
    ``seed`` or ``threads`` are not valid.
    """
    est, m, blocks, scale = _exact_estimator(estimator, n)
    budget = limits.count(points, "exact_variances: points")
    rows = limits.receiver_indices(receivers, "exact_variances: receivers", len(scene.receivers))
    seed = limits.seed(seed, "exact_variances: seed")
    workers = default_threads() if threads is None else limits.count(threads, "exact_variances: threads")
    if blocks is None:
        value, stderr, used = _pair_variances(scene, rows, est, m, budget, seed, workers, progress)
    else:
        sub = max(1, math.isqrt(budget // (blocks.count * REPLICAS)))
        value, stderr, used = _block_variances(scene, rows, est, blocks, sub, seed, workers, progress)
    return Variances(_frozen(scale * value), _frozen(scale * stderr), used)


def _frozen(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


def exact_variance(scene: Scene, receiver: int, estimator: str | Estimator, n: int, rel_tol: float = REL_TOL,
                   seed: int = SEED, max_points: int = MAX_POINTS) -> Estimate:
    """The exact variance of one estimate (N = ``n``) at one receiver, to ``rel_tol``.

    Var = c² · multiplicity · Σ_k Σ_b Var(block sum).  The block sums are computed once
    per block layout and kept with the scene's upload (per content and device): for
    ``independent`` and ``antithetic`` the layout (one block over the whole square) is the
    same for every N.  A one-line
    WarpisError where the estimator has no exact form (``exact_form_problem``).
    """
    est, m, blocks, scale = _exact_estimator(estimator, n)
    up = upload(scene)
    cache = up.cached("block_variance", dict)  # kept per content and device, and on disk (memo)
    layout = (m,) if blocks is None else (blocks.count, blocks.cells)
    key = (int(receiver), est.pattern, est.combiner, est.parameter_value, est.techniques, layout, rel_tol, seed,
           max_points)
    if key not in cache:
        def compute() -> Estimate:
            if blocks is None:
                return pair_variance(scene, receiver, est, m, rel_tol, seed, max_points)
            return block_variance(scene, receiver, est, blocks, rel_tol, seed, max_points)

        if memo.keepable(est.techniques, est.pattern):
            path = memo.kept_path("variance", scene.digest, up.device, key)
            cache[key] = memo.kept(path, compute, _estimate_json, _estimate_of)
        else:
            cache[key] = compute()
    v = cache[key]
    return Estimate(scale * v.value, scale * v.stderr, v.points)


def pair_variance(scene: Scene, receiver: int, est: Estimator, m: int, rel_tol: float = REL_TOL,
                  seed: int = SEED, max_points: int = MAX_POINTS) -> Estimate:
    """Σ over technique streams of Var(Σ_{i<m} ψ(u_i)) under a pattern with a pair form
    (``Pattern.sum_variance``, point_sets), to ``rel_tol``: the budget starts at
    ``MIN_POINTS`` per technique and rises ×4 until the relative error is ≤ ``rel_tol``
    or the next step would pass ``max_points``, as :func:`block_variance` does."""
    rows = np.array([receiver], np.int32)
    budget = MIN_POINTS
    while True:
        value, stderr, points = _pair_variances(scene, rows, est, m, budget, seed, default_threads(), None)
        result = Estimate(float(value[0]), float(stderr[0]), points)
        if result.rel_error <= rel_tol or budget * 4 > max_points:
            return result
        budget *= 4


def _alpha_for(scene: Scene, rows: np.ndarray, est: Estimator) -> np.ndarray | None:
    """The optimal-oracle's α at each receiver of ``rows`` (those the kernel uses), or None."""
    return optimal_alpha(scene, rows, est.techniques) if est.combiner_entry.oracle else None


def _pair_variances(scene: Scene, rows: np.ndarray, est: Estimator, m: int, budget: int, seed: int, workers: int,
                    progress: Callable[[int, int], None] | None) -> tuple[np.ndarray, np.ndarray, int]:
    """Σ over technique streams of Var(Σ_{i<m} ψ(u_i)) at each receiver of ``rows`` and its
    stderr (each (R,)) from the pattern's pair form at ``budget`` points per technique,
    and the dense points evaluated per receiver.  Every chunk of receivers gives the form
    the same generator state, so every receiver sees the same points."""
    form = est.pattern_entry.sum_variance
    assert form is not None
    n_g = est.technique_count
    ev = Evaluator.of(scene, est.techniques)
    alpha = _alpha_for(scene, rows, est)
    streams = [tuple(range(n_g))] if est.combiner_entry.random_pick else [(k,) for k in range(n_g)]
    value, var = np.zeros(len(rows)), np.zeros(len(rows))
    used = [0] * len(streams)

    def chunk(lo: int, hi: int, pieces: int) -> None:
        part = None if alpha is None else alpha[lo:hi]
        for index, ks in enumerate(streams):
            def values(u: np.ndarray, ks: tuple[int, ...] = ks) -> tuple[np.ndarray, np.ndarray]:
                psi = [_psi(ev, rows[lo:hi], est, k, u, pieces, part) for k in ks]
                return sum(psi) / len(ks), sum(x * x for x in psi) / len(ks)

            result = form(values, m, budget, np.random.default_rng([seed, m, index, 0x9A1]))
            value[lo:hi] += result.value
            var[lo:hi] += result.stderr ** 2
            used[index] = result.points * len(ks)

    per_row = 8 * MAX_POINTS_PER_CALL * (2 * (n_g + 1) + 2 * len(streams[0]) + 6)
    _run_chunks(ev, len(rows), max(1, CHUNK_BYTES // per_row), workers, chunk, progress)
    return value, np.sqrt(var), sum(used)


def block_variance(scene: Scene, receiver: int, est: Estimator, blocks: Blocks, rel_tol: float = REL_TOL,
                   seed: int = SEED, max_points: int = MAX_POINTS) -> Estimate:
    """Σ over technique streams and listed blocks of Var(block sum of ψ), to ``rel_tol``.

    The density starts at ``MIN_POINTS`` per technique (rare features such as a tiny
    bright light must be seen by every replica for the jackknife error to mean anything)
    and rises ×4 until the jackknife relative error is ≤ ``rel_tol`` or the next step
    would pass ``max_points`` per technique; the Estimate carries the error reached.
    Each density is the fixed-density computation of :func:`exact_variances` at one
    receiver, with its own points.
    """
    sub = 2
    while blocks.count * sub * sub * REPLICAS < MIN_POINTS:
        sub *= 2
    rows = np.array([receiver], np.int32)
    while True:
        value, stderr, points = _block_variances(scene, rows, est, blocks, sub, seed, default_threads(), None)
        result = Estimate(float(value[0]), float(stderr[0]), points)
        if result.rel_error <= rel_tol or points * 4 > max_points * est.technique_count:
            return result
        sub *= 2


def _block_variances(scene: Scene, rows: np.ndarray, est: Estimator, blocks: Blocks, sub: int, seed: int,
                     workers: int, progress: Callable[[int, int], None] | None
                     ) -> tuple[np.ndarray, np.ndarray, int]:
    """Σ over technique streams and listed blocks of Var(block sum of ψ) at each receiver
    of ``rows`` and its jackknife stderr (each (R,)), from ``REPLICAS`` replicas of sub ×
    sub jittered strata per block; and the dense points evaluated per receiver.

    The points depend on the seed and the block layout only (every receiver of every
    chunk sees the same ones) and every reduction runs along one receiver's own values,
    so a receiver's values are the same whatever else is asked for, however the
    receivers are chunked and whatever ``workers``.
    """
    u = jittered_points(blocks, sub, REPLICAS, np.random.default_rng([seed, blocks.count, *blocks.cells, sub]))
    ev = Evaluator.of(scene, est.techniques)
    alpha = _alpha_for(scene, rows, est)
    value, var = np.zeros(len(rows)), np.zeros(len(rows))

    def chunk(lo: int, hi: int, pieces: int) -> None:
        part = None if alpha is None else alpha[lo:hi]
        for q, p in _block_moments(ev, rows[lo:hi], est, blocks, u, pieces, part):
            v, se = _jackknife(q, p)
            value[lo:hi] += v
            var[lo:hi] += se * se

    _run_chunks(ev, len(rows), _chunk_rows(est, blocks, u), workers, chunk, progress)
    points = u.shape[0] * u.shape[1] * u.shape[2] * (2 if blocks.paired else 1) * est.technique_count
    return value, np.sqrt(var), points


def _chunk_rows(est: Estimator, blocks: Blocks, u: np.ndarray) -> int:
    """The most receivers per chunk: the float64 arrays of a chunk (kernel outputs and their copies,
    ψ of each technique of a stream, the shifted values, their moments and numpy's
    temporaries) stay within ``CHUNK_BYTES``."""
    dense = u.shape[0] * u.shape[1] * u.shape[2] * (2 if blocks.paired else 1)
    stream = est.technique_count if est.combiner_entry.random_pick else 1
    per_row = 8 * (blocks.count + dense) * (2 * (est.technique_count + 1) + 2 * stream + 6)
    return max(1, CHUNK_BYTES // per_row)


def _run_chunks(ev: Evaluator, count: int, most: int, workers: int, chunk: Callable[[int, int, int], None],
                progress: Callable[[int, int], None] | None) -> None:
    """``chunk(lo, hi, pieces)`` for equal chunks of at most ``most`` of ``count`` receivers.

    On the CPU the chunks run on a pool of up to ``workers`` threads, as many chunks as
    whole rounds of the pool need (so no thread waits on a long last chunk), and a chunk
    splits its launches into ``pieces`` so that fewer receivers than workers (one, say)
    still use every core; the calling thread waits in the pool, where Ctrl-C raises at
    once, and after an exception no further chunk starts.  ``progress`` runs in the
    calling thread, in completion order.
    """
    chunks = -(-count // most)
    if ev.cpu:
        chunks = min(count, -(-chunks // workers) * workers)
    size = -(-count // chunks)
    bounds = [(lo, min(lo + size, count)) for lo in range(0, count, size)]
    done = 0

    def record(lo: int, hi: int) -> None:
        nonlocal done
        done += hi - lo
        if progress is not None:
            progress(done, count)

    if not ev.cpu:  # GPU launches are asynchronous: one thread feeds them
        for lo, hi in bounds:
            chunk(lo, hi, 1)
            record(lo, hi)
        return
    ev.load()
    pieces = max(1, workers // len(bounds))
    pool = ThreadPoolExecutor(max_workers=min(workers, len(bounds)))
    try:
        running = {pool.submit(chunk, lo, hi, pieces): (lo, hi) for lo, hi in bounds}
        for fut in as_completed(running):
            fut.result()
            record(*running[fut])
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _block_moments(ev: Evaluator, rows: np.ndarray, est: Estimator, blocks: Blocks, u: np.ndarray,
                   pieces: int, alpha: np.ndarray | None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Per technique stream: per-replica block means of Q = E[X²|u] and P = E[X|u],
    shifted, at each receiver of ``rows``: each (R, B, replicas).

    Values are shifted per receiver and block by the value at the block's centre (a
    constant, so the variance is unchanged) so that within-block variances are not lost
    to rounding.
    """
    n_g, count = est.technique_count, blocks.count
    flat = u.reshape(-1, 2)
    halves = [flat, _reflect(flat)] if blocks.paired else [flat]
    at = np.concatenate([_centres(blocks), *halves])  # one launch per technique for everything
    dense_shape = (len(rows), len(halves), *u.shape[:3])  # (R, halves, replicas, B, sub²)
    # A combiner that picks the technique per sample has one stream; its moments given u
    # average over the techniques.  Otherwise each technique is its own stream.
    streams = [tuple(range(n_g))] if est.combiner_entry.random_pick else [(k,) for k in range(n_g)]
    for ks in streams:
        psi = [_psi(ev, rows, est, k, at, pieces, alpha) for k in ks]
        shift = (sum(x[:, :count] for x in psi) / len(ks))[:, None, None, :, None]
        shifted = [x[:, count:].reshape(dense_shape) - shift for x in psi]
        del psi
        mean = sum(shifted) / len(ks)  # E[ψ|u] and E[ψ²|u] over the stream's techniques
        square = sum(x * x for x in shifted) / len(ks)
        del shifted
        if blocks.paired:
            p = mean[:, 0] + mean[:, 1]
            q = square[:, 0] + square[:, 1] + 2 * mean[:, 0] * mean[:, 1]
        else:
            p, q = mean[:, 0], square[:, 0]
        yield _per_block(q), _per_block(p)


def _psi(ev: Evaluator, rows: np.ndarray, est: Estimator, k: int, at: np.ndarray, pieces: int,
         alpha: np.ndarray | None) -> np.ndarray:
    """(R, P) weighted values ψ_k at T_k(at) seen from each receiver of ``rows`` (``alpha``:
    the optimal-oracle's (R, N_g) coefficients, or None)."""
    f, pdf = _recent_values(ev, rows, k, at, pieces, est.combiner_entry.every_sample)
    per_point = None if alpha is None else np.repeat(alpha, f.shape[1], axis=0)
    ctx = WeightContext(est.parameter_value, per_point)
    return weighted_values(est.combiner, k, f.reshape(-1), pdf.reshape(-1, ev.techniques), ctx).reshape(f.shape)


# The dense values of the last few single-receiver evaluations.  Two combiners over one
# technique set at one block layout evaluate the very same points at the same receiver
# (a cell's balance heuristic and the power heuristic behind its Veach bound), so the
# second reads them here: the same arrays (read-only), a few MB each.
RECENT_EVALUATIONS = 4
_recent: OrderedDict[tuple, tuple[DeviceScene, np.ndarray, np.ndarray]] = OrderedDict()
_recent_lock = threading.Lock()


def _recent_values(ev: Evaluator, rows: np.ndarray, k: int, at: np.ndarray, pieces: int, every: bool
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``ev(rows, k, at, pieces, every=every)``, read from the last few evaluations of one receiver."""
    if len(rows) != 1:
        return ev(rows, k, at, pieces, every=every)
    # The entry holds its upload, so no other upload can take its id while it is kept.
    key = (id(ev.up), ev.kernel, ev.names, int(rows[0]), k, every, at.shape, at.dtype.str,
           hashlib.sha256(np.ascontiguousarray(at).tobytes()).digest())
    with _recent_lock:
        if key in _recent:
            _recent.move_to_end(key)
            return _recent[key][1:]
    f, pdf = ev(rows, k, at, pieces, every=every)
    f.flags.writeable = pdf.flags.writeable = False
    with _recent_lock:
        _recent[key] = (ev.up, f, pdf)
        while len(_recent) > RECENT_EVALUATIONS:
            _recent.popitem(last=False)
    return f, pdf


def _per_block(x: np.ndarray) -> np.ndarray:
    """(R, replicas, B, sub²) values → (R, B, replicas) block means, replicas last for the jackknife."""
    return np.ascontiguousarray(x.mean(axis=-1).transpose(0, 2, 1))


# --------------------------------------------------------------------------- moments


@dataclass
class Moments:
    """Reference moments of one receiver for one technique set (seed notation)."""

    techniques: tuple[str, ...]
    I: Estimate  # F(x)
    I_k: list[Estimate]  # E_{g_k}[f/ḡ]
    E_hbar2: Estimate  # E_ḡ[h²] = ∫ f²/ḡ
    E_is2: list[Estimate]  # E_{g_k}[(f/g_k)²] = ∫ f²/g_k
    int_fg: list[Estimate]  # ∫ f g_k
    int_f2g: list[Estimate]  # ∫ f² g_k
    int_f2: Estimate  # ∫ f² over the hemisphere
    int_inv_g: list[float | None]  # ∫ 1/g_k over the hemisphere (inf where g_k vanishes or diverges; None: unknown)


def _mean_estimate(values: np.ndarray) -> Estimate:
    """Mean over (replicas, points) of stratified values with a between-replica stderr."""
    per = values.reshape(values.shape[0], -1).mean(axis=1)
    return Estimate(float(per.mean()), float(per.std(ddof=1) / math.sqrt(len(per))), values.size)


def _moments_json(mom: Moments) -> dict:
    return {"techniques": list(mom.techniques), "I": _estimate_json(mom.I), "E_hbar2": _estimate_json(mom.E_hbar2),
            "int_f2": _estimate_json(mom.int_f2), "int_inv_g": list(mom.int_inv_g),
            **{name: [_estimate_json(e) for e in getattr(mom, name)] for name in _MOMENT_LISTS}}


def _moments_of(d: dict) -> Moments:
    return Moments(tuple(str(t) for t in d["techniques"]), _estimate_of(d["I"]),
                   [_estimate_of(e) for e in d["I_k"]], _estimate_of(d["E_hbar2"]),
                   *([_estimate_of(e) for e in d[name]] for name in _MOMENT_LISTS[1:]),
                   _estimate_of(d["int_f2"]), [None if g is None else float(g) for g in d["int_inv_g"]])


_MOMENT_LISTS = ("I_k", "E_is2", "int_fg", "int_f2g")


def moments(scene: Scene, receiver: int, techniques: tuple[str, ...], sub: int = 256, seed: int = SEED) -> Moments:
    """Reference moments from ``REPLICAS`` × sub² jittered points per technique (kept on
    disk by content: :mod:`warpis.analysis.memo`)."""
    return moments_together(scene, receiver, [tuple(techniques)], sub, seed)[0]


def moments_together(scene: Scene, receiver: int, technique_sets: Sequence[tuple[str, ...]], sub: int = 256,
                     seed: int = SEED) -> list[Moments]:
    """``[moments(scene, receiver, s) for s in technique_sets]``, bit for bit, each technique
    of their union evaluated once.

    Every set's moments at a receiver sit at the same points (they depend on the seed,
    the receiver and sub alone), and f and a technique's pdf at T_k(u) do not depend on
    which set asked for them: so each technique of the union is evaluated once, with the
    pdf of every technique of the union, and each set reads its own columns (a study of
    light IS, BSDF IS and their MIS evaluates two techniques, not five).  Results kept on
    disk are read, and the others kept, one file per set as by :func:`moments`.
    """
    sets = list(dict.fromkeys(tuple(s) for s in technique_sets))
    for s in sets:
        check_lights(scene, s)
    device = upload(scene).device
    paths = {s: memo.kept_path("moments", scene.digest, device, (int(receiver), s, sub, seed))
             for s in sets if memo.keepable(s)}
    found = {s: m for s in paths if (m := memo.read(paths[s], _moments_of)) is not None}
    todo = [s for s in sets if s not in found]
    if todo:
        union = tuple(dict.fromkeys(t for s in todo for t in s))
        values = _UnionValues(scene, receiver, union, _moment_points(receiver, sub, seed))
        for s in todo:
            found[s] = _moments(scene, receiver, s, sub, seed, values)
            if s in paths:
                memo.keep(paths[s], found[s], _moments_json)
    return [found[tuple(s)] for s in technique_sets]


def _moment_points(receiver: int, sub: int, seed: int) -> np.ndarray:
    """The (REPLICAS · sub², 2) jittered points of one receiver's moments, whatever the technique set."""
    return jittered_points(Blocks(1, 1, (1, 1), False), sub, REPLICAS,
                           np.random.default_rng([seed, receiver, 1])).reshape(-1, 2)


class _UnionValues:
    """f and the pdfs at T_k(u) for any technique set drawn from ``union``, at the points ``u``
    of one receiver: each technique of the union evaluated once, on first use.

    The kernel finds technique t's column at a sample the same way whatever else is in
    the set (its pdf where the sampling technique's own pdf and f are > 0, that own pdf
    where not), so a set's columns read from the union's evaluation are those of the
    set's own, bit for bit.
    """

    def __init__(self, scene: Scene, receiver: int, union: tuple[str, ...], u: np.ndarray):
        self.scene, self.receiver, self.union, self.u = scene, receiver, union, u
        self.done: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def for_set(self, techniques: tuple[str, ...], k: int) -> tuple[np.ndarray, np.ndarray]:
        """``evaluate(scene, receiver, techniques, k, u)``."""
        if not set(techniques) <= set(self.union):
            return evaluate(self.scene, self.receiver, techniques, k, self.u)
        t = techniques[k]
        if t not in self.done:
            self.done[t] = evaluate(self.scene, self.receiver, self.union, self.union.index(t), self.u)
        f, pdf = self.done[t]
        if techniques == self.union:
            return f, pdf
        return f, pdf[:, [self.union.index(name) for name in techniques]]


def _moments(scene: Scene, receiver: int, techniques: tuple[str, ...], sub: int, seed: int,
             values: _UnionValues | None = None) -> Moments:
    values = values or _UnionValues(scene, receiver, techniques, _moment_points(receiver, sub, seed))
    u = values.u
    shape = (REPLICAS, -1)
    i_k, e_is2, fg, f2g, e_h2 = [], [], [], [], []
    f2_mixture = np.zeros(len(u))
    for k, t in enumerate(techniques):
        f, pdf = values.for_set(techniques, k)
        with np.errstate(divide="ignore", invalid="ignore"):
            f2_mixture += np.where(f > 0, f * f / pdf.sum(axis=1), 0.0)
        h = weighted_values("balance", k, f, pdf)
        w = weighted_values("single", k, f, pdf)
        i_k.append(_mean_estimate(h.reshape(shape)))
        e_h2.append(h.reshape(shape) ** 2)
        e_is2.append(_mean_estimate((w * w).reshape(shape)))
        fg.append(_mean_estimate(f.reshape(shape)))
        f2g.append(_mean_estimate((f * f).reshape(shape)))
    e_hbar2 = _mean_estimate(np.mean(e_h2, axis=0))
    if scene.environment is None and scene.light_count:
        # ∫ f² = E_light[f²/g]: light-area covers the support of f when all light comes
        # from emitter triangles and spheres.  The points depend on (seed, receiver, sub)
        # alone, so every technique set of a receiver shares this one evaluation.
        shared = upload(scene).cached("int_f2", dict)  # per content and device
        key = (int(receiver), sub, seed)
        if key not in shared:
            f, pdf = values.for_set(("light-area",), 0)
            w = weighted_values("single", 0, f, pdf)
            shared[key] = _mean_estimate((w * f).reshape(shape))
        int_f2 = shared[key]
    else:
        # An environment: ∫ f² = Σ_k E_{g_k}[f² / Σ_j g_j] over the set itself, which covers
        # the support of f (every set that estimates F does: techniques.check_lights).
        int_f2 = _mean_estimate(f2_mixture.reshape(shape))
    n_g = len(techniques)
    big_i = Estimate(sum(e.value for e in i_k) / n_g, math.sqrt(sum(e.stderr**2 for e in i_k)) / n_g, u.size)
    return Moments(tuple(techniques), big_i, i_k, e_hbar2, e_is2, fg, f2g, int_f2,
                   [TECHNIQUES[t].inverse_pdf_integral for t in techniques])


def stratum_integrals(scene: Scene, receiver: int, techniques: tuple[str, ...], m: int, sub: int = 8,
                      seed: int = SEED) -> np.ndarray:
    """J_ik: ∫ over cell i of h(T_k(u)) du (cells of measure 1/m), shape (N_g, m)."""
    rng = np.random.default_rng([seed, receiver, m])
    blocks = PATTERNS["jittered"].blocks(m)  # the cells of the m-cell grid
    u = jittered_points(blocks, sub, 1, rng)
    out = []
    for k in range(len(techniques)):
        f, pdf = evaluate(scene, receiver, techniques, k, u.reshape(-1, 2))
        h = weighted_values("balance", k, f, pdf).reshape(blocks.count, -1)
        out.append(h.mean(axis=1) / m)
    return np.array(out)


register_oracle(optimal_alpha)  # the engine's optimal-oracle runs take their α from here
