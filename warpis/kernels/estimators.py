"""Estimators as data: pattern × combiner × techniques, and the trial kernel that runs them.

An estimator is spelled ``PATTERN:COMBINER[=VALUE]:TECH[+TECH...]``, e.g.
``jittered:balance:light-area+cosine``.  One trial is one estimate of F at one receiver
from N samples; the kernel computes a whole trial per thread (sampling, casting,
weighting and the sum over N), so no per-sample Python and no R × M × N arrays.

Combiners (entries of ``COMBINERS`` (below); seed notation: g_k the pdf of technique
k, ḡ their average, N_g techniques, m = N/N_g samples per technique):

``single``   IS with one technique: (1/N) Σ f/g.
``mixture``  IS from ḡ itself (the seed's averaged-pdf IS): each sample picks a technique
             uniformly at random, weight f/ḡ; (1/N) Σ f/ḡ.  The pattern places all N points.
``balance``  multi-sample MIS, seed eq. 5: m samples per technique, (1/N) Σ_k Σ_i f/ḡ.
``power``    multi-sample MIS with the power heuristic (β = 2):
             Σ_k (1/m) Σ_i w_k f/g_k, w_k = g_k² / Σ_j g_j².
``biased``   seed eq. 19: (1/N) Σ f(X), X ~ g, unweighted (converges to ∫ f g, not F).
``maximum``  multi-sample MIS with Veach's maximum heuristic: Σ_k (1/m) Σ_i w_k f/g_k,
             w_k = 1 where g_k is the largest pdf (ties to the first technique), else 0.
``cutoff``   multi-sample MIS with Veach's cutoff heuristic, spelled ``cutoff=α`` (default
             α = 0.1): w_k = g_k / Σ_{j: g_j ≥ α g_max} g_j where g_k ≥ α g_max, else 0.
``optimal-oracle``  Kondapaneni et al. 2019's optimal MIS at fixed coefficients α
             (per receiver, from warpis's dense evaluation: ``quadrature.optimal_alpha``):
             Σ_k α_k + (1/N) Σ_k Σ_i (f − α·g)/ḡ, every sample counting (a failed sample
             of technique k adds −N_g α_k, see below).  Unbiased for any fixed α; the α
             solving A α = b minimises the variance.
``optimal``  the same with α estimated per trial from an independent pilot: ⌊m/4⌋ (at
             least 1, even when m is) of each technique's m = N/N_g samples, uniform and
             never reused, so the estimate stays unbiased; the pattern places the rest.  A
             small ridge keeps the pilot's α bounded (``pilot_alpha``).

Optimal MIS over an extended domain.  A technique whose sample fails (no direction: a
light seen from behind, a microfacet reflection below the surface) puts mass 1 − c_k on
a point of its own where f = 0 and only its pdf is non-zero.  Over the directions plus
those points every pdf integrates to 1, which the Σ_k α_k term needs; at technique k's
failure point (f − α·g)/ḡ = −N_g α_k.  docs/theory.md derives A, b and the variance.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from .. import limits
from ..errors import WarpisError
from ..vocabulary import Combiner, Parameter, Pattern, Registry, WeightContext, grid_shape
from .device import ReceiverData, SceneData
from .integrand import ShadingPoint, integrand_via, shading_point
from .patterns import PATTERNS, pattern_point
from .precompiled import compile_portably
from .rng import stream, uniform
from .techniques import (LIGHT_AREA, LIGHT_POWER, TECHNIQUES, DirectionSample, LightTable, sample_direction,
                         sample_light_point, technique_pdf, unknown_sample)

compile_portably(__name__)  # shipped compiled: precompiled.py says why portably


def _importance_weights(k: int, f: np.ndarray, pdf: np.ndarray, ctx: WeightContext) -> np.ndarray:
    return f / pdf[:, k]


def _unweighted(k: int, f: np.ndarray, pdf: np.ndarray, ctx: WeightContext) -> np.ndarray:
    return f.copy()


def _balance_weights(k: int, f: np.ndarray, pdf: np.ndarray, ctx: WeightContext) -> np.ndarray:
    return f * pdf.shape[1] / pdf.sum(axis=1)  # f/ḡ


def _power_weights(k: int, f: np.ndarray, pdf: np.ndarray, ctx: WeightContext) -> np.ndarray:
    return f * pdf[:, k] / (pdf**2).sum(axis=1)  # w_k f/g_k, w_k = g_k²/Σ_j g_j²


def _maximum_weights(k: int, f: np.ndarray, pdf: np.ndarray, ctx: WeightContext) -> np.ndarray:
    """w_k = 1 where g_k is the largest pdf (ties to the first technique), else 0."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.argmax(pdf, axis=1) == k, f / pdf[:, k], 0.0)


def _cutoff_weights(k: int, f: np.ndarray, pdf: np.ndarray, ctx: WeightContext) -> np.ndarray:
    """w_k f/g_k = f / Σ_{j: g_j ≥ α g_max} g_j where g_k ≥ α g_max, else 0 (the kernel
    compares in float32, as here)."""
    g = pdf.astype(np.float32)
    floor = np.float32(ctx.parameter) * g.max(axis=1)
    kept = g >= floor[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(kept[:, k], f / np.where(kept, pdf, 0.0).sum(axis=1), 0.0)


def _optimal_weights(k: int, f: np.ndarray, pdf: np.ndarray, ctx: WeightContext) -> np.ndarray:
    """ψ_k = N_g (f − α·g)/Σ_j g_j at a sample, −N_g α_k at a failed one (every pdf 0)."""
    assert ctx.alpha is not None
    n_g = pdf.shape[1]
    total = pdf.sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        value = n_g * (f - (ctx.alpha * pdf).sum(axis=1)) / total
    return np.where(pdf[:, k] > 0, value, -n_g * ctx.alpha[:, k])


def _quarter(m: int) -> int:
    """The optimal combiner's pilot: ⌊m/4⌋ of each technique's m samples, at least 1, and
    made even when m is even (while one sample is left), so that a paired pattern keeps an
    even count: m = 4 → 2, 6 → 2, 8 → 2, 12 → 4."""
    pilot = max(1, m // 4)
    if m % 2 == 0 and pilot % 2 and pilot + 1 < m:
        pilot += 1
    return pilot


# Kondapaneni et al.'s linear system is solved in the kernel with Warp's 4 × 4 matrices.
MAX_OPTIMAL_TECHNIQUES = 4

COMBINERS: Registry[Combiner] = Registry("combiner", [
    Combiner(name="single", code=0, description="IS with one technique: (1/N) Σ f/g", several=False,
             weights=_importance_weights),
    Combiner(name="mixture", code=1, description="IS from the averaged pdf ḡ: a technique picked at random per "
                                                 "sample, weight f/ḡ",
             several=True, random_pick=True, weights=_balance_weights, verify_under=("independent", "jittered")),
    Combiner(name="balance", code=2, description="multi-sample MIS, balance heuristic: N/N_g samples per "
                                                 "technique, weight f/ḡ",
             several=True, splits_n=True, divides_by_n=True, weights=_balance_weights),
    Combiner(name="power", code=3, description="multi-sample MIS, power heuristic (β = 2): N/N_g samples per "
                                               "technique",
             several=True, splits_n=True, weights=_power_weights, verify_under=("independent", "jittered")),
    Combiner(name="biased", code=4, description="the unweighted mean of f over samples of one technique: "
                                                "converges to ∫ f g, not F",
             several=False, unbiased=False, weights=_unweighted, verify_under=("independent",)),
    Combiner(name="maximum", code=5, description="multi-sample MIS, maximum heuristic (Veach): a sample counts, "
                                                 "weight f/g_k, only where its technique's pdf is the largest",
             several=True, splits_n=True, weights=_maximum_weights, verify_under=("independent", "jittered")),
    Combiner(name="cutoff", code=6, description="multi-sample MIS, cutoff heuristic (Veach), spelled cutoff=α "
                                                "(default 0.1): the balance heuristic over the techniques whose "
                                                "pdf is ≥ α × the largest",
             several=True, splits_n=True, weights=_cutoff_weights, verify_under=("independent", "jittered"),
             parameter=Parameter("α", 0.1, 0.0, 1.0)),
    Combiner(name="optimal-oracle", code=7, description="optimal MIS (Kondapaneni et al. 2019) with α = A⁻¹b "
                                                        "per receiver from warpis's dense evaluation: the best "
                                                        "achievable",
             several=True, splits_n=True, divides_by_n=True, weights=_optimal_weights, every_sample=True,
             oracle=True, max_techniques=MAX_OPTIMAL_TECHNIQUES, verify_under=("independent", "jittered")),
    Combiner(name="optimal", code=8, description="optimal MIS (Kondapaneni et al. 2019) with α from an "
                                                 "independent uniform pilot of about a quarter of each "
                                                 "technique's m samples, not reused",
             several=True, splits_n=True, divides_by_n=True, every_sample=True, pilot=_quarter,
             max_techniques=MAX_OPTIMAL_TECHNIQUES, verify_under=(),  # no exact form to be held against
             no_exact_form="its α is a ratio estimate from a random pilot, so its variance (the mean over the "
                           "pilot of a quadratic in α) has no closed form; optimal-oracle has the variance at "
                           "a fixed α"),
])

def estimator_help() -> str:
    """The axes of an estimator spec, PATTERN:COMBINER:TECH[+TECH...], a line per entry
    (for ``--help``)."""
    return "\n".join(f"{axis} ({part}):\n{registry.help()}" for axis, part, registry in (
        ("patterns", "PATTERN", PATTERNS), ("combiners", "COMBINER", COMBINERS), ("techniques", "TECH", TECHNIQUES)))


# The kernels' combiner codes, from the registry (COMBINERS above).
SINGLE = wp.constant(COMBINERS["single"].code)
MIXTURE = wp.constant(COMBINERS["mixture"].code)
BALANCE = wp.constant(COMBINERS["balance"].code)
POWER = wp.constant(COMBINERS["power"].code)
BIASED = wp.constant(COMBINERS["biased"].code)
MAXIMUM = wp.constant(COMBINERS["maximum"].code)
CUTOFF = wp.constant(COMBINERS["cutoff"].code)
OPTIMAL_ORACLE = wp.constant(COMBINERS["optimal-oracle"].code)
OPTIMAL = wp.constant(COMBINERS["optimal"].code)
# Random-number stream of the mixture's technique choices: past any technique's stream.
PICK_STREAM = 1 << 16
# Random-number streams of the optimal combiner's pilot, one per technique: past those too.
PILOT_STREAM = wp.constant(1 << 17)
vec5d = wp.types.vector(length=5, dtype=wp.float64)
# The pilot's ridge, relative to the mean diagonal of Â (see pilot_alpha).
PILOT_RIDGE = wp.constant(wp.float64(0.01))


@dataclass(frozen=True)
class Estimator:
    """An estimator: where samples go (pattern), how they combine, and from what techniques."""

    pattern: str
    combiner: str
    techniques: tuple[str, ...]
    parameter: float | None = None  # the combiner's number, as spelled COMBINER=VALUE (None: its default)

    def __post_init__(self) -> None:
        problem = self._problem()
        if problem:
            raise WarpisError(f"estimator {self.spec!r}: {problem}")

    @property
    def spec(self) -> str:
        """The estimator's spelling, ``PATTERN:COMBINER[=VALUE]:TECH[+TECH...]``."""
        combiner = self.combiner if self.parameter is None else f"{self.combiner}={self.parameter!r}"
        return f"{self.pattern}:{combiner}:{'+'.join(self.techniques)}"

    @property
    def parameter_value(self) -> float:
        """The combiner's number: as spelled, or its default (0.0 for a combiner that takes none)."""
        entry = self.combiner_entry.parameter
        if self.parameter is not None:
            return self.parameter
        return entry.default if entry else 0.0

    def __str__(self) -> str:
        return self.spec

    @property
    def pattern_entry(self) -> Pattern:
        """The pattern's descriptor in ``PATTERNS`` (kernels/patterns.py)."""
        return PATTERNS[self.pattern]

    @property
    def combiner_entry(self) -> Combiner:
        """The combiner's descriptor in ``COMBINERS`` (below)."""
        return COMBINERS[self.combiner]

    def _problem(self) -> str | None:
        for registry, names in ((PATTERNS, (self.pattern,)), (COMBINERS, (self.combiner,)),
                                (TECHNIQUES, self.techniques)):
            unknown = [name for name in names if name not in registry]
            if unknown:
                return registry.unknown(unknown[0])
        if len(set(self.techniques)) != len(self.techniques):
            return "a technique is listed twice"
        count = len(self.techniques)
        several = [c.name for c in COMBINERS.values() if c.several]
        if not self.combiner_entry.several and count != 1:
            return f"combiner {self.combiner!r} takes exactly one technique (got {count}); " \
                   f"use {_either(several)} to combine several"
        if self.combiner_entry.several and count < 2:
            one = next(c.name for c in COMBINERS.values() if not c.several and c.unbiased)
            return f"combiner {self.combiner!r} combines two or more techniques; use {one} for one"
        most = self.combiner_entry.max_techniques
        if most is not None and count > most:
            return f"combiner {self.combiner!r} combines at most {most} techniques (got {count})"
        entry = self.combiner_entry.parameter
        if self.parameter is not None:
            if entry is None:
                return f"combiner {self.combiner!r} takes no parameter (spell it {self.combiner!r}, without '=')"
            try:
                entry.parse(repr(self.parameter))
            except ValueError as exc:
                return f"combiner {self.combiner!r}: {exc}"
        return None

    @property
    def technique_count(self) -> int:
        return len(self.techniques)

    def per_technique(self, n: int) -> int:
        """m: samples each technique places (N/N_g where the combiner splits N, else all N)."""
        return self.combiner_entry.per_technique(n, self.technique_count)

    def check_n(self, n: int) -> None:
        """Raise a one-line error if this estimator cannot use N = ``n`` samples."""
        limits.count(n, f"estimator {self.spec!r}: N")
        k = self.technique_count
        splits = self.combiner_entry.splits_n
        if splits and n % k:
            valid = ", ".join(str(k * i) for i in range(1, 5))
            raise WarpisError(f"estimator {self.spec!r}: N = {n} is not divisible by its {k} techniques "
                              f"(valid: multiples of {k}, e.g. {valid}, …)")
        if self.combiner_entry.pilot and n // k < 2:
            raise WarpisError(f"estimator {self.spec!r}: combiner {self.combiner!r} spends "
                              f"{self.combiner_entry.pilot(2)} of each technique's N/{k} samples on its pilot, so it "
                              f"needs N ≥ {2 * k} (got {n})")
        m = self.per_technique(n)
        problem = self.pattern_entry.problem(m)
        if problem:
            step = 2 * (k if splits else 1)
            hint = f"; valid N: multiples of {step}" if m % 2 and self.pattern_entry.paired else ""
            if self.combiner_entry.pilot:
                hint = f" (of N/{k} = {n // k}, {self.pilot_samples(n)} go to the pilot)"
            raise WarpisError(f"estimator {self.spec!r}: pattern {self.pattern!r} {problem}{hint}")

    def pilot_samples(self, n: int) -> int:
        """Samples each technique spends on the combiner's pilot (0 without one)."""
        return self.combiner_entry.pilot_samples(n, self.technique_count)


def _either(names: list[str]) -> str:
    """Names joined as "a, b or c"."""
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} or {names[-1]}"


def parse_estimator(spec: str | Estimator) -> Estimator:
    """``"PATTERN:COMBINER[=VALUE]:TECH[+TECH...]"`` → :class:`Estimator` (one-line error if invalid)."""
    if isinstance(spec, Estimator):
        return spec
    parts = str(spec).strip().split(":")
    if len(parts) != 3 or not all(parts):
        raise WarpisError(
            f"estimator {spec!r}: expected PATTERN:COMBINER[=VALUE]:TECH[+TECH...] with PATTERN in "
            f"{'|'.join(PATTERNS)}, COMBINER in {'|'.join(COMBINERS)}, TECH in {'|'.join(TECHNIQUES)}")
    combiner, eq, text = parts[1].partition("=")
    parameter = None
    if eq:
        entry = COMBINERS.get(combiner)
        if entry is not None and entry.parameter is not None:
            try:
                parameter = entry.parameter.parse(text)
            except ValueError as exc:
                raise WarpisError(f"estimator {spec!r}: combiner {combiner!r}: {exc}") from None
        elif entry is not None:
            raise WarpisError(f"estimator {spec!r}: combiner {combiner!r} takes no parameter "
                              f"(spell it {combiner!r}, without '=')")
    return Estimator(parts[0], combiner, tuple(parts[2].split("+")), parameter)


@dataclass(frozen=True)
class KernelArgs:
    """The integers the trial kernel needs for one estimator at one N."""

    pattern: int
    combiner: int
    techniques: tuple[int, ...]
    m: int  # samples each technique's pattern places
    rows: int
    cols: int
    pilot: int  # samples each technique spends on the combiner's pilot
    parameter: float  # the combiner's number (0 where it takes none)

    @classmethod
    def of(cls, est: Estimator, n: int) -> "KernelArgs":
        est.check_n(n)  # before anything is computed from n: no truncation, no int32 wrap
        m = est.per_technique(n)
        rows, cols = grid_shape(m)
        return cls(PATTERNS[est.pattern].code, COMBINERS[est.combiner].code,
                   tuple(TECHNIQUES[t].code for t in est.techniques), m, rows, cols, est.pilot_samples(n),
                   est.parameter_value)


# --------------------------------------------------------------------------- kernel


def make_trial_kernel(sample_direction: Any, technique_pdf: Any, pattern_point: Any, module: Any) -> tuple[Any, Any]:
    """The trial kernel and the pilot kernel over the technique dispatch
    ``sample_direction``/``technique_pdf`` and the pattern dispatch ``pattern_point`` (the
    built-in functions, or those of :func:`warpis.kernels.techniques.dispatch` and
    :func:`warpis.kernels.patterns.point_dispatch` for user techniques and patterns), in
    the Warp module ``module`` (None: this one)."""

    @wp.func(module=module)
    def draw(tech: wp.int32, scene: SceneData, table: LightTable, sp: ShadingPoint, u: wp.vec2) -> DirectionSample:
        """Technique ``tech``'s sample for u, with its pdf and its emitter crossing where
        the technique knows them (a light point on a planar emitter set)."""
        if scene.planar_emitters != 0 and (tech == LIGHT_AREA or tech == LIGHT_POWER):
            return sample_light_point(tech, scene, sp, u)
        return unknown_sample(sample_direction(tech, scene, table, sp, u))

    @wp.func(module=module)
    def value(scene: SceneData, sp: ShadingPoint, smp: DirectionSample) -> float:
        """f at the sample; 0 for a failed sample (zero vector)."""
        if wp.length_sq(smp.w) == 0.0:
            return 0.0
        return integrand_via(scene, sp, smp.w, smp.emitter, smp.t)

    @wp.func(module=module)
    def own_pdf(tech: wp.int32, scene: SceneData, table: LightTable, sp: ShadingPoint, smp: DirectionSample) -> float:
        """The sampling technique's density at the sample."""
        if smp.pdf >= 0.0:
            return smp.pdf
        return technique_pdf(tech, scene, table, sp, smp.w)

    @wp.func(module=module)
    def other_pdfs(techs: wp.array(dtype=wp.int32), k: wp.int32, pdf_k: float, scene: SceneData, table: LightTable,
                   sp: ShadingPoint, w: wp.vec3, power: wp.int32) -> float:
        """Σ_j g_j(ω)^power over all techniques, reusing g_k(ω) = pdf_k."""
        acc = float(0.0)
        for j in range(techs.shape[0]):
            g = pdf_k
            if j != k:
                g = technique_pdf(techs[j], scene, table, sp, w)
            if power == 2:
                g = g * g
            acc = acc + g
        return acc

    @wp.func(module=module)
    def largest_pdf(techs: wp.array(dtype=wp.int32), k: wp.int32, pdf_k: float, scene: SceneData, table: LightTable,
                    sp: ShadingPoint, w: wp.vec3) -> bool:
        """Whether g_k(ω) = pdf_k is the largest pdf of the set, ties going to the first technique."""
        for j in range(techs.shape[0]):
            if j != k:
                g = technique_pdf(techs[j], scene, table, sp, w)
                if g > pdf_k or (j < k and g == pdf_k):
                    return False
        return True

    @wp.func(module=module)
    def cutoff_sum(techs: wp.array(dtype=wp.int32), k: wp.int32, pdf_k: float, scene: SceneData, table: LightTable,
                   sp: ShadingPoint, w: wp.vec3, alpha: float) -> float:
        """Σ_j g_j over the techniques with g_j ≥ α·g_max, or 0 where g_k = pdf_k itself is below."""
        largest = pdf_k
        for j in range(techs.shape[0]):
            if j != k:
                largest = wp.max(largest, technique_pdf(techs[j], scene, table, sp, w))
        floor = alpha * largest
        if pdf_k < floor:
            return 0.0
        acc = float(0.0)
        for j in range(techs.shape[0]):
            g = pdf_k
            if j != k:
                g = technique_pdf(techs[j], scene, table, sp, w)
            if g >= floor:
                acc = acc + g
        return acc

    @wp.func(module=module)
    def pdf_vector(techs: wp.array(dtype=wp.int32), k: wp.int32, pdf_k: float, scene: SceneData, table: LightTable,
                   sp: ShadingPoint, w: wp.vec3) -> wp.vec4d:
        """Every technique's pdf at ω (at most four), reusing g_k(ω) = pdf_k; zero-padded."""
        g = wp.vec4d()
        for j in range(techs.shape[0]):
            if j == k:
                g[j] = wp.float64(pdf_k)
            else:
                g[j] = wp.float64(technique_pdf(techs[j], scene, table, sp, w))
        return g

    @wp.func(module=module)
    def optimal_terms(scene: SceneData, table: LightTable, sp: ShadingPoint, techs: wp.array(dtype=wp.int32),
                      k: wp.int32, u: wp.vec2) -> vec5d:
        """(r_0..r_3, f/Σ_j g_j) at technique k's sample from u, r = g/Σ_j g_j; where the
        sample fails, r = e_k (technique k's own point of the extended domain) and f = 0."""
        t = vec5d()
        t[k] = wp.float64(1.0)
        smp = draw(techs[k], scene, table, sp, u)
        if wp.length_sq(smp.w) > 0.0:
            pdf = own_pdf(techs[k], scene, table, sp, smp)
            if pdf > 0.0:
                g = pdf_vector(techs, k, pdf, scene, table, sp, smp.w)
                total = g[0] + g[1] + g[2] + g[3]
                for j in range(4):
                    t[j] = g[j] / total
                t[4] = wp.float64(value(scene, sp, smp)) / total
        return t

    @wp.func(module=module)
    def pilot_alpha(scene: SceneData, table: LightTable, sp: ShadingPoint, seed: wp.uint32, trial: wp.int32,
                    techs: wp.array(dtype=wp.int32), pilot: wp.int32) -> wp.vec4d:
        """α solving (Â + λI) α = b̂ from ``pilot`` independent uniform samples of each
        technique: Â = Σ r rᵀ, b̂ = Σ (f/Σ_j g_j) r over the pilot samples (``optimal_terms``).

        The ridge λ = ``PILOT_RIDGE`` · trace(Â)/N_g keeps α bounded: a pilot of a few
        samples can make Â nearly singular, and an unbounded α, though it leaves the
        estimate unbiased, gives it heavy tails (on heavy-occluder with one pilot sample
        per technique, |α| reached 81 and the stderr of the mean grew 14×).  α = 0 (the
        balance heuristic) where the system is still singular to working precision."""
        n_g = techs.shape[0]
        a = wp.mat44d()
        b = wp.vec4d()
        for k in range(n_g):
            s = stream(seed, sp.receiver, trial, PILOT_STREAM + k)
            for i in range(pilot):
                t = optimal_terms(scene, table, sp, techs, k, wp.vec2(uniform(s, i, 0), uniform(s, i, 1)))
                r = wp.vec4d(t[0], t[1], t[2], t[3])
                a = a + wp.outer(r, r)
                b = b + t[4] * r
        largest = wp.float64(0.0)
        trace = wp.float64(0.0)
        for j in range(n_g):
            largest = wp.max(largest, a[j, j])
            trace = trace + a[j, j]
        ridge = PILOT_RIDGE * trace / wp.float64(n_g)
        for j in range(n_g):
            a[j, j] = a[j, j] + ridge
        for j in range(n_g, 4):
            a[j, j] = largest  # unused techniques: α_j = 0, without moving the determinant's scale
        if not (wp.abs(wp.determinant(a)) > wp.float64(1e-10) * largest * largest * largest * largest):
            return wp.vec4d()
        return wp.inverse(a) * b

    @wp.func(module=module)
    def optimal_trial(scene: SceneData, table: LightTable, sp: ShadingPoint, seed: wp.uint32, trial: wp.int32,
                      pattern: wp.int32, techs: wp.array(dtype=wp.int32), m: wp.int32, rows: wp.int32,
                      cols: wp.int32, alpha: wp.vec4d) -> wp.float64:
        """Σ_k α_k + (1/(m N_g)) Σ_k Σ_i N_g (f − α·g)/Σ_j g_j, a failed sample adding −N_g α_k."""
        n_g = techs.shape[0]
        total = wp.float64(0.0)
        for k in range(n_g):
            s = stream(seed, sp.receiver, trial, k)
            for i in range(m):
                t = optimal_terms(scene, table, sp, techs, k, pattern_point(pattern, s, i, m, rows, cols))
                total = total + t[4] - (alpha[0] * t[0] + alpha[1] * t[1] + alpha[2] * t[2] + alpha[3] * t[3])
        return alpha[0] + alpha[1] + alpha[2] + alpha[3] + total / wp.float64(m)

    @wp.func(module=module)
    def mixture_trial(scene: SceneData, table: LightTable, sp: ShadingPoint, seed: wp.uint32, trial: wp.int32,
                      pattern: wp.int32, techs: wp.array(dtype=wp.int32), n: wp.int32, rows: wp.int32,
                      cols: wp.int32) -> wp.float64:
        n_g = techs.shape[0]
        s = stream(seed, sp.receiver, trial, 0)
        s_pick = stream(seed, sp.receiver, trial, PICK_STREAM)
        total = wp.float64(0.0)
        for i in range(n):
            u = pattern_point(pattern, s, i, n, rows, cols)
            k = wp.min(wp.int32(uniform(s_pick, i, 0) * float(n_g)), n_g - 1)
            smp = draw(techs[k], scene, table, sp, u)
            w = smp.w
            f = value(scene, sp, smp)
            if f > 0.0:
                pdf = own_pdf(techs[k], scene, table, sp, smp)
                if pdf > 0.0:
                    gbar = other_pdfs(techs, k, pdf, scene, table, sp, w, 1) / float(n_g)
                    total = total + wp.float64(f / gbar)
        return total / wp.float64(n)

    @wp.func(module=module)
    def stratified_trial(scene: SceneData, table: LightTable, sp: ShadingPoint, seed: wp.uint32, trial: wp.int32,
                         pattern: wp.int32, combiner: wp.int32, techs: wp.array(dtype=wp.int32), m: wp.int32,
                         rows: wp.int32, cols: wp.int32, parameter: float) -> wp.float64:
        """single, balance, power, maximum, cutoff and biased: m samples from each technique's own pattern."""
        n_g = techs.shape[0]
        total = wp.float64(0.0)
        for k in range(n_g):
            s = stream(seed, sp.receiver, trial, k)
            for i in range(m):
                u = pattern_point(pattern, s, i, m, rows, cols)
                smp = draw(techs[k], scene, table, sp, u)
                w = smp.w
                f = value(scene, sp, smp)
                if f > 0.0:
                    if combiner == BIASED:
                        total = total + wp.float64(f)
                    else:
                        pdf = own_pdf(techs[k], scene, table, sp, smp)
                        if pdf > 0.0:
                            if combiner == SINGLE:
                                total = total + wp.float64(f / pdf)
                            elif combiner == BALANCE:
                                gbar = other_pdfs(techs, k, pdf, scene, table, sp, w, 1) / float(n_g)
                                total = total + wp.float64(f / gbar)
                            elif combiner == MAXIMUM:
                                if largest_pdf(techs, k, pdf, scene, table, sp, w):
                                    total = total + wp.float64(f / pdf)
                            elif combiner == CUTOFF:
                                kept = cutoff_sum(techs, k, pdf, scene, table, sp, w, parameter)
                                if kept > 0.0:
                                    total = total + wp.float64(f / kept)
                            else:
                                total = total + wp.float64(f * pdf / other_pdfs(techs, k, pdf, scene, table, sp, w, 2))
        if combiner == BALANCE:
            return total / wp.float64(m * n_g)
        return total / wp.float64(m)

    # No kernel of warpis is differentiated, and without a backward pass a kernel compiles
    # about 3× faster (cold run_trials on occluded-quad: 32 s → 11 s).  The built-in trial
    # kernel keeps Warp's default all the same: it is compiled once per cache and runs every
    # estimate, and LLVM builds a faster forward pass beside its backward one (measured:
    # 140 against 165 ns per evaluation of independent:single:light-area on occluded-quad).
    @wp.kernel(module=module, enable_backward=None if module is None else False)
    def trial_kernel(scene: SceneData, recv: ReceiverData, table: LightTable, receivers: wp.array(dtype=wp.int32),
                     trial_offset: wp.int32, seed: wp.uint32, pattern: wp.int32, combiner: wp.int32,
                     techs: wp.array(dtype=wp.int32), m: wp.int32, rows: wp.int32, cols: wp.int32,
                     pilot: wp.int32, parameter: float, alphas: wp.array(dtype=wp.vec4d),
                     out: wp.array2d(dtype=wp.float64)):
        """One estimate per thread: receiver row i, trial trial_offset + j, into out[i, j]
        (``out`` holds one launch's trials; the trial number only seeds the generator).
        ``alphas[i]``: the optimal-oracle's coefficients at row i (unread otherwise)."""
        i, j = wp.tid()
        trial = trial_offset + j
        sp = shading_point(scene, recv, receivers[i])
        if combiner == MIXTURE:
            out[i, j] = mixture_trial(scene, table, sp, seed, trial, pattern, techs, m, rows, cols)
        elif combiner == OPTIMAL:
            alpha = pilot_alpha(scene, table, sp, seed, trial, techs, pilot)
            out[i, j] = optimal_trial(scene, table, sp, seed, trial, pattern, techs, m, rows, cols, alpha)
        elif combiner == OPTIMAL_ORACLE:
            out[i, j] = optimal_trial(scene, table, sp, seed, trial, pattern, techs, m, rows, cols, alphas[i])
        else:
            out[i, j] = stratified_trial(scene, table, sp, seed, trial, pattern, combiner, techs, m, rows, cols,
                                         parameter)

    @wp.kernel(module=module, enable_backward=False)
    def pilot_kernel(scene: SceneData, recv: ReceiverData, table: LightTable, receivers: wp.array(dtype=wp.int32),
                     seed: wp.uint32, techs: wp.array(dtype=wp.int32), pilot: wp.int32,
                     out: wp.array2d(dtype=wp.vec4d)):
        """The optimal combiner's α of receiver row i in trial j, as the trial kernel finds it."""
        i, j = wp.tid()
        sp = shading_point(scene, recv, receivers[i])
        out[i, j] = pilot_alpha(scene, table, sp, seed, j, techs, pilot)

    return trial_kernel, pilot_kernel


trial_kernel, pilot_kernel = make_trial_kernel(sample_direction, technique_pdf, pattern_point, None)
