"""Estimators as data: pattern × combiner × techniques, and the trial kernel that runs them.

An estimator is spelled ``PATTERN:COMBINER:TECH[+TECH...]``, e.g.
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
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from .. import limits
from ..errors import WarpisError
from ..vocabulary import Combiner, Pattern, Registry, grid_shape
from .device import ReceiverData, SceneData
from .integrand import ShadingPoint, integrand, shading_point
from .patterns import PATTERNS, pattern_point, point_dispatch, user_patterns
from .rng import stream, uniform
from .techniques import TECHNIQUES, LightTable, dispatch, sample_direction, technique_pdf, user_techniques


def _importance_weights(k: int, f: np.ndarray, pdf: np.ndarray) -> np.ndarray:
    return f / pdf[:, k]


def _unweighted(k: int, f: np.ndarray, pdf: np.ndarray) -> np.ndarray:
    return f.copy()


def _balance_weights(k: int, f: np.ndarray, pdf: np.ndarray) -> np.ndarray:
    return f * pdf.shape[1] / pdf.sum(axis=1)  # f/ḡ


def _power_weights(k: int, f: np.ndarray, pdf: np.ndarray) -> np.ndarray:
    return f * pdf[:, k] / (pdf**2).sum(axis=1)  # w_k f/g_k, w_k = g_k²/Σ_j g_j²


def _maximum_weights(k: int, f: np.ndarray, pdf: np.ndarray) -> np.ndarray:
    """w_k = 1 where g_k is the largest pdf (ties to the first technique), else 0."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.argmax(pdf, axis=1) == k, f / pdf[:, k], 0.0)


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
# Random-number stream of the mixture's technique choices: past any technique's stream.
PICK_STREAM = 1 << 16


@dataclass(frozen=True)
class Estimator:
    """An estimator: where samples go (pattern), how they combine, and from what techniques."""

    pattern: str
    combiner: str
    techniques: tuple[str, ...]

    def __post_init__(self) -> None:
        problem = self._problem()
        if problem:
            raise WarpisError(f"estimator {self.spec!r}: {problem}")

    @property
    def spec(self) -> str:
        """The estimator's spelling, ``PATTERN:COMBINER:TECH[+TECH...]``."""
        return f"{self.pattern}:{self.combiner}:{'+'.join(self.techniques)}"

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
        m = self.per_technique(n)
        problem = self.pattern_entry.problem(m)
        if problem:
            step = 2 * (k if splits else 1)
            hint = f"; valid N: multiples of {step}" if m % 2 and self.pattern_entry.paired else ""
            raise WarpisError(f"estimator {self.spec!r}: pattern {self.pattern!r} {problem}{hint}")


def _either(names: list[str]) -> str:
    """Names joined as "a, b or c"."""
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} or {names[-1]}"


def parse_estimator(spec: str | Estimator) -> Estimator:
    """``"PATTERN:COMBINER:TECH[+TECH...]"`` → :class:`Estimator` (one-line error if invalid)."""
    if isinstance(spec, Estimator):
        return spec
    parts = str(spec).strip().split(":")
    if len(parts) != 3 or not all(parts):
        raise WarpisError(
            f"estimator {spec!r}: expected PATTERN:COMBINER:TECH[+TECH...] with PATTERN in "
            f"{'|'.join(PATTERNS)}, COMBINER in {'|'.join(COMBINERS)}, TECH in {'|'.join(TECHNIQUES)}")
    return Estimator(parts[0], parts[1], tuple(parts[2].split("+")))


@dataclass(frozen=True)
class KernelArgs:
    """The integers the trial kernel needs for one estimator at one N."""

    pattern: int
    combiner: int
    techniques: tuple[int, ...]
    m: int
    rows: int
    cols: int

    @classmethod
    def of(cls, est: Estimator, n: int) -> "KernelArgs":
        est.check_n(n)  # before anything is computed from n: no truncation, no int32 wrap
        m = est.per_technique(n)
        rows, cols = grid_shape(m)
        return cls(PATTERNS[est.pattern].code, COMBINERS[est.combiner].code,
                   tuple(TECHNIQUES[t].code for t in est.techniques), m, rows, cols)


# --------------------------------------------------------------------------- kernel


@wp.func
def contribution(scene: SceneData, sp: ShadingPoint, w: wp.vec3) -> float:
    """f(ω) for a sampled direction; 0 for a failed sample (zero vector).

    The trial kernels evaluate pdfs only where f > 0: a zero-valued sample adds nothing
    whatever its pdf, and for light techniques the pdf is a BVH traversal.
    """
    if wp.length_sq(w) == 0.0:
        return 0.0
    return integrand(scene, sp, w)


def _make_trial_kernel(sample_direction: Any, technique_pdf: Any, pattern_point: Any, module: Any) -> Any:
    """The trial kernel over the technique dispatch ``sample_direction``/``technique_pdf``
    and the pattern dispatch ``pattern_point`` (the built-in functions, or those of
    :func:`warpis.kernels.techniques.dispatch` and :func:`warpis.kernels.patterns.point_dispatch`
    for user techniques and patterns)."""

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
            w = sample_direction(techs[k], scene, table, sp, u)
            f = contribution(scene, sp, w)
            if f > 0.0:
                pdf = technique_pdf(techs[k], scene, table, sp, w)
                if pdf > 0.0:
                    gbar = other_pdfs(techs, k, pdf, scene, table, sp, w, 1) / float(n_g)
                    total = total + wp.float64(f / gbar)
        return total / wp.float64(n)

    @wp.func(module=module)
    def stratified_trial(scene: SceneData, table: LightTable, sp: ShadingPoint, seed: wp.uint32, trial: wp.int32,
                         pattern: wp.int32, combiner: wp.int32, techs: wp.array(dtype=wp.int32), m: wp.int32,
                         rows: wp.int32, cols: wp.int32) -> wp.float64:
        """single, balance, power, maximum and biased: m samples from each technique's own pattern."""
        n_g = techs.shape[0]
        total = wp.float64(0.0)
        for k in range(n_g):
            s = stream(seed, sp.receiver, trial, k)
            for i in range(m):
                u = pattern_point(pattern, s, i, m, rows, cols)
                w = sample_direction(techs[k], scene, table, sp, u)
                f = contribution(scene, sp, w)
                if f > 0.0:
                    if combiner == BIASED:
                        total = total + wp.float64(f)
                    else:
                        pdf = technique_pdf(techs[k], scene, table, sp, w)
                        if pdf > 0.0:
                            if combiner == SINGLE:
                                total = total + wp.float64(f / pdf)
                            elif combiner == BALANCE:
                                gbar = other_pdfs(techs, k, pdf, scene, table, sp, w, 1) / float(n_g)
                                total = total + wp.float64(f / gbar)
                            elif combiner == MAXIMUM:
                                if largest_pdf(techs, k, pdf, scene, table, sp, w):
                                    total = total + wp.float64(f / pdf)
                            else:
                                total = total + wp.float64(f * pdf / other_pdfs(techs, k, pdf, scene, table, sp, w, 2))
        if combiner == BALANCE:
            return total / wp.float64(m * n_g)
        return total / wp.float64(m)

    @wp.kernel(module=module)
    def trial_kernel(scene: SceneData, recv: ReceiverData, table: LightTable, receivers: wp.array(dtype=wp.int32),
                     trial_offset: wp.int32, seed: wp.uint32, pattern: wp.int32, combiner: wp.int32,
                     techs: wp.array(dtype=wp.int32), m: wp.int32, rows: wp.int32, cols: wp.int32,
                     out: wp.array2d(dtype=wp.float64)):
        """One estimate per thread: receiver row i, trial trial_offset + j, into out[i, j]
        (``out`` holds one launch's trials; the trial number only seeds the generator)."""
        i, j = wp.tid()
        trial = trial_offset + j
        sp = shading_point(scene, recv, receivers[i])
        if combiner == MIXTURE:
            out[i, j] = mixture_trial(scene, table, sp, seed, trial, pattern, techs, m, rows, cols)
        else:
            out[i, j] = stratified_trial(scene, table, sp, seed, trial, pattern, combiner, techs, m, rows, cols)

    return trial_kernel


trial_kernel = _make_trial_kernel(sample_direction, technique_pdf, pattern_point, None)


@functools.lru_cache(maxsize=None)
def _trial_kernel_for(user: tuple, user_points: tuple = ()) -> Any:
    if not user and not user_points:
        return trial_kernel
    return _make_trial_kernel(*dispatch(user), point_dispatch(user_points), "unique")


def trial_kernel_for_registry() -> Any:
    """The trial kernel that knows every registered technique and pattern: the built-in
    ``trial_kernel`` itself unless user techniques or patterns are registered (one kernel
    per set of them, cached)."""
    return _trial_kernel_for(user_techniques(), user_patterns())
