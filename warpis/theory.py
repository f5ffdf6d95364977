"""Predicted variances: reference moments from dense u-space evaluation, and the seed's equations.

Everything is built from the same Warp integrand and techniques the estimators use: at
dense jittered points u of each technique's primary-sample square, a kernel returns
f(T_k(u)) and the pdf of every technique of the set at T_k(u).  From those:

* **Exact variance of any estimator** (``exact_variance``).  Every pattern splits one
  technique's m samples into independent *blocks*: ``independent`` has m blocks, each one
  point over the whole square; ``jittered`` m blocks, one per cell; ``antithetic`` m/2
  blocks, each the pair (u, 1−u) over the whole square; ``jittered-antithetic`` m/2 blocks,
  the pair (u, reflect(u)) with u in cell i < m/2.  An estimate is c·Σ_k Σ_blocks (block
  sum of ψ_k), ψ_k the combiner's weighted value of a sample of technique k, so
  Var = c² Σ_k Σ_b Var(block sum) — a sum of within-block variances, never a difference of
  two large numbers.  The mixture's random technique choice enters through the moments
  given u: E[ψ|u] = mean_k ψ_k(u), E[ψ²|u] = mean_k ψ_k(u)².
* **Reference moments** (``moments``): I, I_k, E_ḡ[h²], E_{g_k}[(f/g_k)²], ∫ f g_k,
  ∫ f² g_k, ∫ f², ∫ 1/g_k, and the stratum integrals J_ik.
* **The seed's equations** as printed and exactly (``predictions``); docs/theory.md derives
  each and states how an ambiguous print is read.

Accuracy: each quantity is computed from R independent replicas of the jittered points.
Block variances use E[Q] − E[P]² with E[P]² estimated from *pairs of different replicas*,
which is unbiased; the standard error comes from a jackknife over replicas.  The density
is raised (×4 points per block) until the relative error is below ``REL_TOL`` or the point
budget is spent, which the result then says.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

from .engine import default_threads
from .estimators import Estimator, parse_estimator
from .integrand import integrand, shading_point
from .patterns import grid_shape
from .scene import ReceiverData, Scene, SceneData
from .techniques import TECHNIQUES, LightTable, light_table, sample_technique, technique_pdf

REL_TOL = 0.01
REPLICAS = 8
MIN_POINTS = 1 << 17  # per technique and block layout, over all replicas
MAX_POINTS = 1 << 20  # per technique and block layout, over all replicas
SEED = 0x7E0


# --------------------------------------------------------------------------- kernel


@wp.kernel
def _evaluate_kernel(scene: SceneData, recv: ReceiverData, table: LightTable, r: wp.int32,
                     techs: wp.array(dtype=wp.int32), k: wp.int32, u: wp.array(dtype=wp.vec2),
                     f_out: wp.array(dtype=wp.float64), pdf_out: wp.array2d(dtype=wp.float64)):
    """f and every technique's pdf at the direction technique k maps u[i] to."""
    i = wp.tid()
    sp = shading_point(scene, recv, r)
    w, pdf = sample_technique(techs[k], scene, table, sp, u[i])
    f = float(0.0)
    if pdf > 0.0:
        f = integrand(scene, sp, w)
    for j in range(techs.shape[0]):
        g = pdf
        if j != k:
            g = float(0.0)
            if pdf > 0.0:
                g = technique_pdf(techs[j], scene, table, sp, w)
        pdf_out[i, j] = wp.float64(g)
    f_out[i] = wp.float64(f)


def evaluate(scene: Scene, receiver: int, techniques: tuple[str, ...], k: int, u: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """f (P,) and the pdfs (P, N_g) of all ``techniques`` at T_k(u) for points u (P, 2).

    On the CPU the points are split over the engine's worker threads (one launch each).
    """
    dev = scene.device
    codes = wp.array(np.array([TECHNIQUES[t] for t in techniques], np.int32), dtype=wp.int32, device=dev)
    table = light_table(scene)
    f_all = np.empty(len(u))
    pdf_all = np.empty((len(u), len(techniques)))

    def run(lo: int, hi: int) -> None:
        uu = wp.array(np.ascontiguousarray(u[lo:hi], np.float32), dtype=wp.vec2, device=dev)
        f = wp.zeros(hi - lo, dtype=wp.float64, device=dev)
        pdf = wp.zeros((hi - lo, len(techniques)), dtype=wp.float64, device=dev)
        wp.launch(_evaluate_kernel, dim=hi - lo, device=dev,
                  inputs=[scene.data, scene.receiver_data, table, receiver, codes, k, uu, f, pdf])
        f_all[lo:hi] = f.numpy()
        pdf_all[lo:hi] = pdf.numpy()

    workers = default_threads() if wp.get_device(dev).is_cpu and len(u) >= 1 << 14 else 1
    bounds = [int(b) for b in np.linspace(0, len(u), workers + 1)]
    if workers == 1:
        run(0, len(u))
    else:
        wp.load_module(_evaluate_kernel.module, device=dev)
        with ThreadPoolExecutor(max_workers=workers) as pool:
            for fut in [pool.submit(run, lo, hi) for lo, hi in zip(bounds[:-1], bounds[1:])]:
                fut.result()
    return f_all, pdf_all


def weighted_values(combiner: str, k: int, f: np.ndarray, pdf: np.ndarray) -> np.ndarray:
    """ψ_k: the value a sample of technique k adds to the combiner's sum (see estimators.py)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        gk = pdf[:, k]
        if combiner == "single":
            out = f / gk
        elif combiner == "biased":
            out = f.copy()
        elif combiner in ("balance", "mixture"):
            out = f * pdf.shape[1] / pdf.sum(axis=1)
        elif combiner == "power":
            out = f * gk / (pdf**2).sum(axis=1)
        else:
            raise ValueError(combiner)
    return np.where((gk > 0) & (f > 0), out, 0.0)


def combiner_scale(est: Estimator, n: int) -> float:
    """c in estimate = c · Σ_k Σ_i ψ_k."""
    m = est.per_technique(n)
    if est.combiner == "balance":
        return 1.0 / (m * est.technique_count)
    return 1.0 / m


# --------------------------------------------------------------------------- blocks


@dataclass(frozen=True)
class Blocks:
    """The independent blocks of one technique's m samples under a pattern."""

    count: int  # number of blocks (identical blocks are not repeated)
    multiplicity: int  # each listed block stands for this many identical ones
    cells: tuple[int, int]  # (rows, cols) of the grid the blocks live on; (1, 1) = whole square
    paired: bool  # antithetic: block value is ψ(u) + ψ(reflect(u))


def blocks_of(pattern: str, m: int) -> Blocks:
    if pattern == "independent":
        return Blocks(1, m, (1, 1), False)
    if pattern == "antithetic":
        return Blocks(1, m // 2, (1, 1), True)
    rows, cols = grid_shape(m)
    if pattern == "jittered":
        return Blocks(m, 1, (rows, cols), False)
    if pattern == "jittered-antithetic":
        return Blocks(m // 2, 1, (rows, cols), True)
    raise ValueError(pattern)


def _points(blocks: Blocks, sub: int, replicas: int, rng: np.random.Generator) -> np.ndarray:
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


def _unbiased_block_variance(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Σ over blocks of E[Q] − E[P]², from per-replica block means q, p of shape (R, B).

    E[P]² is estimated by the mean over ordered pairs of *different* replicas of
    p_a · p_b, which is unbiased because replicas are independent.
    """
    r = q.shape[0]
    sp = p.sum(axis=0)
    pairs = (sp * sp - (p * p).sum(axis=0)) / (r * (r - 1))
    return (q.mean(axis=0) - pairs).sum()


def _jackknife(q: np.ndarray, p: np.ndarray) -> tuple[float, float]:
    r = q.shape[0]
    full = _unbiased_block_variance(q, p)
    leave = np.array([_unbiased_block_variance(np.delete(q, a, 0), np.delete(p, a, 0)) for a in range(r)])
    se = math.sqrt(max((r - 1) / r * ((leave - leave.mean()) ** 2).sum(), 0.0))
    return float(full), se


# --------------------------------------------------------------------------- exact variance


def exact_variance(scene: Scene, receiver: int, estimator: str | Estimator, n: int, rel_tol: float = REL_TOL,
                   seed: int = SEED, max_points: int = MAX_POINTS) -> Estimate:
    """The exact variance of one estimate (N = ``n``) at one receiver, to ``rel_tol``.

    Var = c² · multiplicity · Σ_k Σ_b Var(block sum).  The block sums are computed once
    per block layout and cached on the scene: for ``independent`` and ``antithetic`` the
    layout (one block over the whole square) is the same for every N.
    """
    est = parse_estimator(estimator)
    est.check_n(n)
    blocks = blocks_of(est.pattern, est.per_technique(n))
    c = combiner_scale(est, n)
    cache = scene.__dict__.setdefault("_block_variance_cache", {})
    key = (receiver, est.pattern, est.combiner, est.techniques, blocks.count, blocks.cells, rel_tol, seed, max_points)
    if key not in cache:
        cache[key] = block_variance(scene, receiver, est, blocks, rel_tol, seed, max_points)
    v = cache[key]
    scale = c * c * blocks.multiplicity
    return Estimate(scale * v.value, scale * v.stderr, v.points)


def block_variance(scene: Scene, receiver: int, est: Estimator, blocks: Blocks, rel_tol: float = REL_TOL,
                   seed: int = SEED, max_points: int = MAX_POINTS) -> Estimate:
    """Σ over technique streams and listed blocks of Var(block sum of ψ), to ``rel_tol``.

    The density starts at ``MIN_POINTS`` per technique (rare features such as a tiny
    bright light must be seen by every replica for the jackknife error to mean anything)
    and rises ×4 until the jackknife relative error is ≤ ``rel_tol`` or the next step
    would pass ``max_points`` per technique; the Estimate carries the error reached.
    """
    sub = 2
    while blocks.count * sub * sub * REPLICAS < MIN_POINTS:
        sub *= 2
    rng = np.random.default_rng([seed, receiver, blocks.count, blocks.cells[0]])
    while True:
        total, var, points = 0.0, 0.0, 0
        for q, p, used in _block_moments(scene, receiver, est, blocks, sub, rng):
            v, se = _jackknife(q, p)
            total += v
            var += se * se
            points += used
        result = Estimate(total, math.sqrt(var), points)
        if result.rel_error <= rel_tol or points * 4 > max_points * est.technique_count:
            return result
        sub *= 2


def _block_moments(scene: Scene, receiver: int, est: Estimator, blocks: Blocks, sub: int,
                   rng: np.random.Generator):
    """Per technique stream: per-replica block means of Q = E[X²|u] and P = E[X|u], shifted.

    Values are shifted per block by the value at the block's centre (a constant, so the
    variance is unchanged) so that within-block variances are not lost to rounding.
    """
    techs = est.techniques
    u = _points(blocks, sub, REPLICAS, rng)
    shape = u.shape[:3]
    flat = u.reshape(-1, 2)
    centres = _centres(blocks)
    streams = [None] if est.combiner == "mixture" else range(len(techs))
    for k in streams:
        ks = range(len(techs)) if k is None else [k]

        def psi(points: np.ndarray) -> np.ndarray:
            """(P, len(ks)) weighted values of each sampling technique in this stream."""
            cols = []
            for kk in ks:
                f, pdf = evaluate(scene, receiver, techs, kk, points)
                cols.append(weighted_values(est.combiner, kk, f, pdf))
            return np.stack(cols, axis=-1)

        shift = psi(centres).mean(axis=-1)  # (B,)
        a = psi(flat).reshape(*shape, len(ks)) - shift[None, :, None, None]
        if blocks.paired:
            b = psi(_reflect(flat)).reshape(*shape, len(ks)) - shift[None, :, None, None]
            pa, pb = a.mean(-1), b.mean(-1)
            p = pa + pb
            q = (a * a).mean(-1) + (b * b).mean(-1) + 2 * pa * pb
        else:
            p = a.mean(-1)
            q = (a * a).mean(-1)
        yield q.mean(axis=2), p.mean(axis=2), flat.shape[0] * (2 if blocks.paired else 1) * len(ks)


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
    int_inv_g: list[float]  # ∫ 1/g_k over the hemisphere (inf where g_k vanishes or diverges)


def _mean_estimate(values: np.ndarray) -> Estimate:
    """Mean over (replicas, points) of stratified values with a between-replica stderr."""
    per = values.reshape(values.shape[0], -1).mean(axis=1)
    return Estimate(float(per.mean()), float(per.std(ddof=1) / math.sqrt(len(per))), values.size)


def inverse_pdf_integral(technique: str) -> float:
    """∫_hemisphere 1/g dω: 4π² for uniform; infinite for every other technique here.

    cosine: ∫ π/cos θ dω diverges (logarithmically) at the horizon; phong's lobe and the
    light techniques vanish on part of the hemisphere.
    """
    return 4 * math.pi**2 if technique == "uniform" else math.inf


def moments(scene: Scene, receiver: int, techniques: tuple[str, ...], sub: int = 256, seed: int = SEED) -> Moments:
    """Reference moments from ``REPLICAS`` × sub² jittered points per technique."""
    rng = np.random.default_rng([seed, receiver, 1])
    blocks = Blocks(1, 1, (1, 1), False)
    u = _points(blocks, sub, REPLICAS, rng).reshape(-1, 2)
    shape = (REPLICAS, -1)
    i_k, e_is2, fg, f2g, e_h2 = [], [], [], [], []
    for k, t in enumerate(techniques):
        f, pdf = evaluate(scene, receiver, techniques, k, u)
        h = weighted_values("balance", k, f, pdf)
        w = weighted_values("single", k, f, pdf)
        i_k.append(_mean_estimate(h.reshape(shape)))
        e_h2.append(h.reshape(shape) ** 2)
        e_is2.append(_mean_estimate((w * w).reshape(shape)))
        fg.append(_mean_estimate(f.reshape(shape)))
        f2g.append(_mean_estimate((f * f).reshape(shape)))
    e_hbar2 = _mean_estimate(np.mean(e_h2, axis=0))
    # ∫ f² = E_light[f²/g]: every light technique covers the support of f.
    f, pdf = evaluate(scene, receiver, ("light-area",), 0, u)
    w = weighted_values("single", 0, f, pdf)
    int_f2 = _mean_estimate((w * f).reshape(shape))
    n_g = len(techniques)
    big_i = Estimate(sum(e.value for e in i_k) / n_g, math.sqrt(sum(e.stderr**2 for e in i_k)) / n_g, u.size)
    return Moments(tuple(techniques), big_i, i_k, e_hbar2, e_is2, fg, f2g, int_f2,
                   [inverse_pdf_integral(t) for t in techniques])


def stratum_integrals(scene: Scene, receiver: int, techniques: tuple[str, ...], m: int, sub: int = 8,
                      seed: int = SEED) -> np.ndarray:
    """J_ik: ∫ over cell i of h(T_k(u)) du (cells of measure 1/m), shape (N_g, m)."""
    rng = np.random.default_rng([seed, receiver, m])
    blocks = blocks_of("jittered", m)
    u = _points(blocks, sub, 1, rng)
    out = []
    for k in range(len(techniques)):
        f, pdf = evaluate(scene, receiver, techniques, k, u.reshape(-1, 2))
        h = weighted_values("balance", k, f, pdf).reshape(blocks.count, -1)
        out.append(h.mean(axis=1) / m)
    return np.array(out)


# --------------------------------------------------------------------------- the equations


def predictions(scene: Scene, receiver: int, estimator: str | Estimator, n: int,
                mom: Moments | None = None, rel_tol: float = REL_TOL) -> dict[str, Estimate]:
    """Every form that applies to ``estimator`` at N = ``n``: name → predicted variance.

    Forms (docs/theory.md derives each; README lists them):
    ``eq1`` (independent single IS), ``eq6`` (independent balance, two techniques),
    ``eq7-printed`` / ``eq7-exact`` (independent balance), ``eq8`` (independent mixture:
    averaged-pdf IS), ``eq10-printed`` / ``eq10-exact`` (jittered single),
    ``eq14-printed`` / ``eq14-exact`` (jittered balance), ``eq17`` (bound, independent
    single), ``eq19`` (independent biased), ``eq20`` (bound, independent biased),
    ``power-exact``, ``mixture-exact``, ``antithetic-exact``, ``jittered-antithetic-exact``
    and ``veach-bound`` (balance ≤ power + (1/m − 1/N)·I²).
    """
    est = parse_estimator(estimator)
    est.check_n(n)
    techs = est.techniques
    mom = mom or moments(scene, receiver, techs)
    out: dict[str, Estimate] = {}
    exact = exact_variance(scene, receiver, est, n, rel_tol=rel_tol)
    pat, comb, n_g = est.pattern, est.combiner, len(techs)
    big_i = mom.I.value
    if pat == "independent":
        if comb == "single":
            out["eq1"] = _form((mom.E_is2[0].value - mom.I_k[0].value ** 2) / n, mom.E_is2[0], 1 / n)
            inv = mom.int_inv_g[0]  # infinite unless g is uniform: then the bound says nothing
            if mom.int_f2.value == 0:  # no light in view: f ≡ 0 and the bound is 0
                out["eq17"] = Estimate(0.0, 0.0)
            else:
                out["eq17"] = Estimate(mom.int_f2.value * inv / n,
                                       0.0 if math.isinf(inv) else mom.int_f2.stderr * inv / n)
        elif comb == "mixture":
            out["eq8"] = _form((mom.E_hbar2.value - big_i**2) / n, mom.E_hbar2, 1 / n)
        elif comb == "balance":
            i_k = np.array([e.value for e in mom.I_k])
            v_avg = (mom.E_hbar2.value - big_i**2) / n
            kappa_printed = (i_k.sum() ** 2) - n_g * (n_g - 1) * big_i**2
            kappa_exact = n_g * big_i**2 - (i_k**2).sum()
            out["eq7-printed"] = _form(v_avg + kappa_printed / (n * n_g), mom.E_hbar2, 1 / n)
            out["eq7-exact"] = _form(v_avg + kappa_exact / (n * n_g), mom.E_hbar2, 1 / n)
            if n_g == 2:
                out["eq6"] = _form((2 * mom.E_hbar2.value - 4 * big_i**2 + 2 * i_k[0] * i_k[1]) / (2 * n), mom.E_hbar2,
                                  1 / n)
        elif comb == "biased":
            out["eq19"] = _form((mom.int_f2g[0].value - mom.int_fg[0].value ** 2) / n, mom.int_f2g[0], 1 / n)
            out["eq20"] = Estimate(mom.int_f2.value / n, mom.int_f2.stderr / n)
    if pat == "jittered" and comb == "single":
        j = stratum_integrals(scene, receiver, techs, n)
        # Seed eq. 10 as printed: (1/N²) Σ_i (∫_{D_i} f²/g − I_i²), strata without the
        # m-fold renormalisation of the stratum pdf; I_i = J_i (the same integral in u).
        out["eq10-printed"] = _form((mom.E_is2[0].value - (j[0] ** 2).sum()) / n**2, mom.E_is2[0], 1 / n**2)
        out["eq10-exact"] = exact
    if pat == "jittered" and comb == "balance":
        m = n // n_g
        j = stratum_integrals(scene, receiver, techs, m) / n_g  # ∫_{D_i^k} f̌ g_k with f̌ = f/(N_g ḡ)
        i_k = np.array([e.value for e in mom.I_k])
        eta = sum(i_k[a] * i_k[b] for a in range(n_g) for b in range(a + 1, n_g)) / n_g**2
        psi_k = ((j.sum(axis=1) ** 2) - (j**2).sum(axis=1)).sum()
        psi = eta + psi_k - (n_g - 1) / n_g * big_i**2
        v_avg = (mom.E_hbar2.value - big_i**2) / n
        out["eq14-printed"] = _form(n_g / n * v_avg + n_g**2 / n**2 * psi, mom.E_hbar2, n_g / n**2)
        out["eq14-exact"] = exact
    if comb == "power":
        out["power-exact"] = exact
    if comb == "mixture" and pat != "independent":
        out["mixture-exact"] = exact
    if pat == "antithetic":
        out["antithetic-exact"] = exact
    if pat == "jittered-antithetic":
        out["jittered-antithetic-exact"] = exact
    if comb == "balance":
        power = exact_variance(scene, receiver, Estimator(pat, "power", techs), n, rel_tol=rel_tol)
        m = est.per_technique(n)
        out["veach-bound"] = Estimate(power.value + (1 / m - 1 / n) * big_i**2, power.stderr)
    out["exact"] = exact
    return out


def _form(value: float, source: Estimate, scale: float) -> Estimate:
    """A closed-form prediction ``value`` whose error is that of ``scale`` × one moment."""
    return Estimate(value, abs(scale) * source.stderr)


BOUNDS = ("eq17", "eq20", "veach-bound")
