"""The seed's equations as printed and exactly: one ``Form`` each in ``FORMS``, and ``predictions``.

A form reads a cell (one receiver × estimator × N): the reference moments and exact
variances of :mod:`warpis.analysis.quadrature`, each computed on first use.
docs/theory.md derives each form and states how an ambiguous print is read.  An entry
registered without its theory leaves its forms out with a reason, never an error.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..limits import default_threads
from ..kernels.estimators import Estimator, parse_estimator
from ..kernels.techniques import TECHNIQUES
from ..scenes import Scene
from ..vocabulary import Blocks
from .quadrature import (REL_TOL, REPLICAS, SEED, Estimate, Evaluator, Moments, exact_form_problem, exact_variance,
                         extended_terms, jittered_points, moments, stratum_integrals)

# --------------------------------------------------------------------------- the equations


@dataclass(frozen=True)
class Scope:
    """The estimators a form describes: a pattern and a combiner (None: any), optionally a
    technique count, optionally every pattern but one."""

    pattern: str | None = None
    combiner: str | None = None
    techniques: int | None = None
    not_pattern: str | None = None

    def covers(self, est: Estimator) -> bool:
        return (self.pattern in (None, est.pattern) and self.combiner in (None, est.combiner)
                and self.techniques in (None, est.technique_count) and est.pattern != self.not_pattern)

    def __str__(self) -> str:
        """As a spec pattern, e.g. ``independent:balance:*`` (+ what else it requires)."""
        text = f"{self.pattern or '*'}:{self.combiner or '*'}:*"
        if self.techniques:
            text += f" with {self.techniques} techniques"
        return text + (f" not under {self.not_pattern}" if self.not_pattern else "")


class _Cell:
    """One receiver × estimator × N: what the forms read, each part computed on first use."""

    def __init__(self, scene: Scene, receiver: int, est: Estimator, n: int, mom: Moments, rel_tol: float):
        self.scene, self.receiver, self.est, self.n, self.mom, self.rel_tol = scene, receiver, est, n, mom, rel_tol
        self._exact: Estimate | str | None = None

    @property
    def exact(self) -> Estimate | str:
        """The estimator's exact variance, or why it has none."""
        if self._exact is None:
            self._exact = exact_form_problem(self.est) or exact_variance(self.scene, self.receiver, self.est, self.n,
                                                                           rel_tol=self.rel_tol)
        return self._exact

    @property
    def i_k(self) -> np.ndarray:
        return np.array([e.value for e in self.mom.I_k])


def _eq1(c: _Cell) -> Estimate:
    mom, n = c.mom, c.n
    return _form((mom.E_is2[0].value - mom.I_k[0].value ** 2) / n, mom.E_is2[0], 1 / n)


def _eq17(c: _Cell) -> Estimate | str:
    mom, n = c.mom, c.n
    inv = mom.int_inv_g[0]  # infinite unless g is uniform: then the bound says nothing (known: _inverse_pdf_known)
    if mom.int_f2.value == 0:  # no light in view: f ≡ 0 and the bound is 0
        return Estimate(0.0, 0.0)
    return Estimate(mom.int_f2.value * inv / n, 0.0 if math.isinf(inv) else mom.int_f2.stderr * inv / n)


def _eq8(c: _Cell) -> Estimate:
    mom, n = c.mom, c.n
    return _form((mom.E_hbar2.value - mom.I.value**2) / n, mom.E_hbar2, 1 / n)


def _eq7_printed(c: _Cell) -> Estimate:
    return _eq7(c, printed=True)


def _eq7_exact(c: _Cell) -> Estimate:
    return _eq7(c, printed=False)


def _eq7(c: _Cell, printed: bool) -> Estimate:
    mom, n, n_g, big_i, i_k = c.mom, c.n, c.est.technique_count, c.mom.I.value, c.i_k
    v_avg = (mom.E_hbar2.value - big_i**2) / n
    if printed:  # κ with the full double sum
        kappa = (i_k.sum() ** 2) - n_g * (n_g - 1) * big_i**2
    else:  # κ over i ≠ j
        kappa = n_g * big_i**2 - (i_k**2).sum()
    return _form(v_avg + kappa / (n * n_g), mom.E_hbar2, 1 / n)


def _eq6(c: _Cell) -> Estimate:
    mom, n, big_i, i_k = c.mom, c.n, c.mom.I.value, c.i_k
    return _form((2 * mom.E_hbar2.value - 4 * big_i**2 + 2 * i_k[0] * i_k[1]) / (2 * n), mom.E_hbar2, 1 / n)


def _eq19(c: _Cell) -> Estimate:
    mom, n = c.mom, c.n
    return _form((mom.int_f2g[0].value - mom.int_fg[0].value ** 2) / n, mom.int_f2g[0], 1 / n)


def _eq20(c: _Cell) -> Estimate:
    return Estimate(c.mom.int_f2.value / c.n, c.mom.int_f2.stderr / c.n)


def _eq10_printed(c: _Cell) -> Estimate:
    """Seed eq. 10 as printed: (1/N²) Σ_i (∫_{D_i} f²/g − I_i²), strata without the m-fold
    renormalisation of the stratum pdf; I_i = J_i (the same integral in u)."""
    mom, n = c.mom, c.n
    j = stratum_integrals(c.scene, c.receiver, c.est.techniques, n)
    return _form((mom.E_is2[0].value - (j[0] ** 2).sum()) / n**2, mom.E_is2[0], 1 / n**2)


def _eq14_printed(c: _Cell) -> Estimate:
    mom, n, n_g, big_i, i_k = c.mom, c.n, c.est.technique_count, c.mom.I.value, c.i_k
    m = n // n_g
    j = stratum_integrals(c.scene, c.receiver, c.est.techniques, m) / n_g  # ∫_{D_i^k} f̌ g_k with f̌ = f/(N_g ḡ)
    eta = sum(i_k[a] * i_k[b] for a in range(n_g) for b in range(a + 1, n_g)) / n_g**2
    psi_k = ((j.sum(axis=1) ** 2) - (j**2).sum(axis=1)).sum()
    psi = eta + psi_k - (n_g - 1) / n_g * big_i**2
    v_avg = (mom.E_hbar2.value - big_i**2) / n
    return _form(n_g / n * v_avg + n_g**2 / n**2 * psi, mom.E_hbar2, n_g / n**2)


def _exact(c: _Cell) -> Estimate | str:
    return c.exact


def _inverse_pdf_known(est: Estimator) -> str | None:
    """eq17 needs ∫ 1/g dω of the technique (its registry entry may not give it)."""
    if TECHNIQUES[est.techniques[0]].inverse_pdf_integral is None:
        return f"∫ 1/g dω is not known for technique {est.techniques[0]!r}"
    return None


def _power_exact_known(est: Estimator) -> str | None:
    """Veach's bound needs the exact variance of the power heuristic under the same pattern."""
    power = Estimator(est.pattern, "power", est.techniques)
    problem = exact_form_problem(power)
    return f"needs the exact variance of {power.spec}: {problem}" if problem else None


def _veach_bound(c: _Cell) -> Estimate | str:
    """Veach's bound with the power heuristic under the same pattern as the other weighting."""
    power = Estimator(c.est.pattern, "power", c.est.techniques)
    v = exact_variance(c.scene, c.receiver, power, c.n, rel_tol=c.rel_tol)
    m = c.est.per_technique(c.n)
    return Estimate(v.value + (1 / m - 1 / c.n) * c.mom.I.value**2, v.stderr)


def _optimal_ab(c: _Cell) -> Estimate:
    """Kondapaneni et al.'s variance of optimal MIS under independent samples, from A and b:
    (1/m)(∫ f²/Σ_l g_l − bᵀA⁻¹b) at α = A⁻¹b (docs/theory.md, "Optimal MIS"), with A, b and
    ∫ f²/Σ_l g_l from their own dense points (not the kernel's α): the best any α gives."""
    m = c.est.per_technique(c.n)
    a, b, f2 = _optimal_integrals(c.scene, c.receiver, c.est.techniques)

    def variance(keep: np.ndarray) -> float:
        am, bm = a[keep].mean(axis=0), b[keep].mean(axis=0)
        return float((f2[keep].mean() - bm @ np.linalg.lstsq(am, bm, rcond=None)[0]) / m)

    r = len(f2)
    full = variance(np.ones(r, bool))
    leave = np.array([variance(np.arange(r) != i) for i in range(r)])
    points = r * OPTIMAL_SUB * OPTIMAL_SUB * c.est.technique_count
    return Estimate(full, float(math.sqrt((r - 1) / r * ((leave - leave.mean()) ** 2).sum())), points)


# sub × sub jittered points per replica and technique behind optimal-ab's A, b and ∫ f²/Σ g.
OPTIMAL_SUB = 128


def _optimal_integrals(scene: Scene, receiver: int, techniques: tuple[str, ...], sub: int = OPTIMAL_SUB,
                       seed: int = SEED) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per replica (``REPLICAS`` of sub² jittered points per technique): A (r, N_g, N_g),
    b (r, N_g) and ∫ f²/Σ_l g_l (r,), each Σ_t E_t[·] over the extended domain."""
    n_g = len(techniques)
    u = jittered_points(Blocks(1, 1, (1, 1), False), sub, REPLICAS, np.random.default_rng([seed, receiver, 0xAB]))
    ev = Evaluator.of(scene, techniques)
    a, b, f2 = np.zeros((REPLICAS, n_g, n_g)), np.zeros((REPLICAS, n_g)), np.zeros(REPLICAS)
    for t in range(n_g):
        f, pdf = ev(np.array([receiver], np.int32), t, u.reshape(-1, 2), default_threads(), every=True)
        r, fs = extended_terms(f.reshape(REPLICAS, -1), pdf.reshape(REPLICAS, -1, n_g), t)
        a += np.einsum("rpi,rpj->rij", r, r) / r.shape[1]
        b += np.einsum("rp,rpi->ri", fs, r) / r.shape[1]
        f2 += (fs * fs).mean(axis=1)
    return a, b, f2


@dataclass(frozen=True)
class Form:
    """A prediction: the estimators it describes, what it needs of their registry entries
    (``needs``: why an estimator in scope still has no value, or None), how it is computed
    (an Estimate, or the reason it cannot be at this cell), and whether it is an upper
    bound rather than an equation."""

    name: str
    scope: Scope
    compute: Callable[[_Cell], Estimate | str]
    bound: bool = False
    needs: Callable[[Estimator], str | None] = lambda est: None

    def problem(self, est: Estimator) -> str | None:
        """Why this form gives no value for ``est`` whatever the scene, or None."""
        if not self.scope.covers(est):
            return f"applies only to {self.scope}"
        return self.needs(est)


# Every form (docs/theory.md derives each; docs/verify.md lists them), in the order they appear in
# a prediction dict.  Registry entries reach them through their numpy twins: a new pattern
# or combiner gets ``exact`` (and the forms scoped to any pattern or combiner) from its
# descriptor, or a reason why not.
FORMS: tuple[Form, ...] = (
    Form("eq1", Scope("independent", "single"), _eq1),
    Form("eq17", Scope("independent", "single"), _eq17, bound=True, needs=_inverse_pdf_known),
    Form("eq8", Scope("independent", "mixture"), _eq8),
    Form("eq7-printed", Scope("independent", "balance"), _eq7_printed),
    Form("eq7-exact", Scope("independent", "balance"), _eq7_exact),
    Form("eq6", Scope("independent", "balance", techniques=2), _eq6),
    Form("eq19", Scope("independent", "biased"), _eq19),
    Form("eq20", Scope("independent", "biased"), _eq20, bound=True),
    Form("eq10-printed", Scope("jittered", "single"), _eq10_printed),
    Form("eq10-exact", Scope("jittered", "single"), _exact, needs=exact_form_problem),
    Form("eq14-printed", Scope("jittered", "balance"), _eq14_printed),
    Form("eq14-exact", Scope("jittered", "balance"), _exact, needs=exact_form_problem),
    Form("power-exact", Scope(combiner="power"), _exact, needs=exact_form_problem),
    Form("mixture-exact", Scope(combiner="mixture", not_pattern="independent"), _exact,  # eq8 is independent's
         needs=exact_form_problem),
    Form("antithetic-exact", Scope("antithetic"), _exact, needs=exact_form_problem),
    Form("jittered-antithetic-exact", Scope("jittered-antithetic"), _exact, needs=exact_form_problem),
    Form("veach-bound", Scope(combiner="balance"), _veach_bound, bound=True, needs=_power_exact_known),
    Form("optimal-ab", Scope("independent", "optimal-oracle"), _optimal_ab),
    Form("exact", Scope(), _exact, needs=exact_form_problem),
)
BOUNDS = tuple(f.name for f in FORMS if f.bound)


class Predictions(dict[str, Estimate]):
    """Form name → predicted variance for every form that applies and can be computed;
    ``reasons`` says, for every other form of ``FORMS``, why it is absent."""

    def __init__(self) -> None:
        super().__init__()
        self.reasons: dict[str, str] = {}


def predictions(scene: Scene, receiver: int, estimator: str | Estimator, n: int,
                mom: Moments | None = None, rel_tol: float = REL_TOL) -> Predictions:
    """Every form of ``FORMS`` that applies to ``estimator`` at N = ``n``: name → predicted
    variance, with the reason for each absent form in ``.reasons`` (a form outside its
    scope, or an estimator whose registry entries carry no exact form): never an error
    for an estimator that parses and takes N.
    """
    est = parse_estimator(estimator)
    est.check_n(n)
    cell = _Cell(scene, receiver, est, n, mom or moments(scene, receiver, est.techniques), rel_tol)
    out = Predictions()
    for form in FORMS:
        problem = form.problem(est)
        if problem:
            out.reasons[form.name] = problem
            continue
        value = form.compute(cell)
        if isinstance(value, str):
            out.reasons[form.name] = value
        else:
            out[form.name] = value
    return out


def missing_forms(estimator: str | Estimator) -> dict[str, str]:
    """The forms whose scope covers ``estimator`` but which give it no value on any scene
    (its registry entries lack what they need), each with the reason: what verify.json
    and summary.json report as ``absent``."""
    est = parse_estimator(estimator)
    return {f.name: problem for f in FORMS if f.scope.covers(est) and (problem := f.needs(est))}


def _form(value: float, source: Estimate, scale: float) -> Estimate:
    """A closed-form prediction ``value`` whose error is that of ``scale`` × one moment."""
    return Estimate(value, abs(scale) * source.stderr)
