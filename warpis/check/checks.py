"""The checks of ``warpis check``, each a verdict on one frame of a subject.

Every check states how often it fails a correct subject by chance:

* **statistical** checks (chi-square, pdf-integral, measure, unbiased, eval-quadrature,
  energy) compare a statistic with a threshold at the per-test level of the run's
  family (:class:`Family`): Šidák's correction over every statistical test of the run,
  so the whole run fails a correct subject by chance with probability at most the
  family-wise level (default 1e-3);
* **deterministic** checks (pdf-at-sample, zero-pdf, weight, reciprocity, weights-sum,
  weights-zero) compare numbers that agree exactly in exact arithmetic, with a tolerance
  above float32 rounding (stated beside each constant) and a fraction of samples that
  may exceed it (those on a discontinuity, where rounding picks a side).

The statistical checks that hold a quadrature against a sample mean carry, besides the
two standard errors, a floor for the float32 rounding of the densities (``*_FLOOR``):
a systematic error no sample count removes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtri

from ..stats import sidak_threshold
from ..testing import ChiSquareTest
from .subjects import MOVE_FACTOR, Draw, Frame
from .window import Region, SphereQuadrature, sample_regions

CHECKS = {
    "chi-square": "the histogram of the samples against the pdf, on a windowed sphere grid (Pearson)",
    "pdf-integral": "∫pdf dω ≤ 1 and equal to the fraction of samples the sampler produced",
    "pdf-at-sample": "the pdf the sampler reports against the pdf recomputed at the sampled direction",
    "zero-pdf": "no sample lands where the pdf is 0",
    "measure": "∫pdf/valid fraction does not change when the light moves away (a solid-angle, not an area density)",
    "unbiased": "the mean of independent:single estimates against Lambert's closed form",
    "weight": "the sampler's weight equals eval/pdf at the sampled direction",
    "eval-quadrature": "the mean sample weight (eval/pdf) against a quadrature of eval (which includes cos θ)",
    "reciprocity": "f(a→b) = f(b→a), where the BSDF claims it",
    "energy": "the albedo ∫eval dω ≤ 1 in every channel (a white furnace)",
    "weights-sum": "a combiner's weights sum to 1 wherever any technique has density",
    "weights-zero": "a technique's weight is 0 where its pdf is 0",
}
STATISTICAL = ("chi-square", "pdf-integral", "measure", "unbiased", "eval-quadrature", "energy")

# pdf-at-sample and weight: float32 densities and weights agree to ~1e-6 relative; 1e-3
# leaves room for a pdf recomputed from a float32-rounded direction on a steep lobe.  At
# most PDF_MISMATCH_FRACTION of the samples may exceed it (samples on a discontinuity).
PDF_RTOL = 1e-3
PDF_MISMATCH_FRACTION = 1e-4
# zero-pdf: a float32 direction on the edge of the support may round to where the pdf is
# 0; at most this fraction of the samples may (none did on warpis's techniques and
# Mitsuba's BSDFs at 10⁶ samples).
ZERO_PDF_FRACTION = 1e-5
# reciprocity: float32 evaluation, and Mitsuba's roughplastic reads its transmittance
# from a table interpolated in cos θ, which differs by ~1e-5 between the two orders.
RECIPROCITY_RTOL = 1e-3
RECIPROCITY_FRACTION = 1e-4
RECIPROCITY_PAIRS = 100_000
# Quadrature floors (relative): float32 pdfs and evals integrate to their float64 values
# within 2e-6 on warpis's techniques, within 1.5e-4 for a lobe about a float32 axis at
# exponent 2000 (tests/test_pdf_integrals.py); 2e-4 covers both.
INTEGRAL_FLOOR = 2e-4
# weights-sum: numpy float64 weights sum to 1 within ~1e-15; a float32 combiner would
# need 1e-6.
WEIGHTS_TOL = 1e-6


@dataclass
class Family:
    """The statistical tests of one run, at family-wise level ``alpha`` (Šidák)."""

    alpha: float
    tests: int

    @property
    def per_test(self) -> float:
        return sidak_threshold(self.alpha, max(1, self.tests))

    @property
    def z_two_sided(self) -> float:
        return float(ndtri(1.0 - 0.5 * self.per_test))

    @property
    def z_one_sided(self) -> float:
        return float(ndtri(1.0 - self.per_test))


@dataclass
class Verdict:
    """One check of one frame: passed (True/False), or not applicable (None)."""

    check: str
    subject: str
    frame: str
    passed: bool | None
    summary: str
    numbers: dict[str, Any] = field(default_factory=dict)
    figure: dict[str, Any] | None = None  # what the report draws

    def as_dict(self) -> dict[str, Any]:
        return {"check": self.check, "subject": self.subject, "frame": self.frame, "passed": self.passed,
                "summary": self.summary, "numbers": self.numbers}


def grid_sizes(samples: int) -> tuple[tuple[int, int], tuple[int, int]]:
    """(chi-square grid, quadrature strata) for a sample count: ~50 or more samples per
    chi-square cell where the density is even, and strata ≥ 8× the cells per side."""
    if samples >= 500_000:
        return (40, 80), (256, 512)
    if samples >= 50_000:
        return (20, 40), (128, 256)
    return (10, 20), (64, 128)


# --------------------------------------------------------------------------- one frame


@dataclass
class FrameData:
    """What the checks of one frame share: its samples, their pdfs, the window, the
    quadrature of pdf (and eval) over it."""

    frame: Frame
    draw: Draw
    recomputed: NDArray  # pdf at every valid sample
    regions: list[Region]  # the windows of the chi-square tests and the integrals
    integral: float
    integral_se: float
    eval_integral: NDArray | None = None  # (C,)
    eval_se: NDArray | None = None
    # Where eval is 0 in every channel (below a BSDF's horizon): ∫pdf there, and the
    # fraction of the samples that landed there; reported when ∫pdf disagrees.
    dark_integral: float | None = None
    dark_fraction: float | None = None
    chi: list[ChiSquareTest] | None = None

    @property
    def count(self) -> int:
        return len(self.draw.valid)

    @property
    def valid_count(self) -> int:
        return int(np.count_nonzero(self.draw.valid))

    @property
    def valid_fraction(self) -> float:
        return self.valid_count / self.count

    @property
    def valid_se(self) -> float:
        v = self.valid_fraction
        return math.sqrt(v * (1.0 - v) / self.count)


def frame_regions(frame: Frame, seed: int) -> list[Region]:
    """The regions of a frame, from the first samples of its draw at ``seed`` (the same
    as :func:`measure_frame` finds at any budget)."""
    from .window import REGION_SAMPLES

    draw = frame.draw(REGION_SAMPLES, seed)
    return sample_regions(draw.dirs[draw.valid], frame.normal)


def measure_frame(frame: Frame, samples: int, seed: int, with_eval: bool = True) -> FrameData:
    """Draw ``samples`` directions, evaluate the pdf at them and integrate pdf (and eval)
    over the frame's regions."""
    draw = frame.draw(samples, seed)
    dirs = draw.dirs[draw.valid]
    recomputed = frame.pdf(dirs) if len(dirs) else np.zeros(0)
    regions = sample_regions(dirs, frame.normal)
    _, strata = grid_sizes(samples)
    quads = [SphereQuadrature(r.window, *strata, np.random.default_rng([seed, 0x9AD, k]))
             for k, r in enumerate(regions)]

    def integrate(f):
        parts = [q.integrate(r.restrict(f)) for q, r in zip(quads, regions)]
        return sum(p[0] for p in parts), np.sqrt(sum(np.square(p[1]) for p in parts))

    integral, integral_se = integrate(frame.pdf)
    data = FrameData(frame, draw, recomputed, regions, float(integral), float(integral_se))
    if with_eval and frame.eval is not None:
        q, se = integrate(frame.eval)
        data.eval_integral, data.eval_se = np.atleast_1d(q), np.atleast_1d(se)
        evaluate = frame.eval
        dark, _ = integrate(lambda d: frame.pdf(d) * np.all(evaluate(d) == 0.0, axis=1))
        data.dark_integral = float(dark)
        if len(dirs):
            data.dark_fraction = float(np.count_nonzero(np.all(evaluate(dirs) == 0.0, axis=1))) / len(draw.valid)
    return data


# --------------------------------------------------------------------------- the checks


def chi_square(data: FrameData, family: Family, subject: str, seed: int) -> Verdict:
    """Pearson's test of the histogram against the pdf, one per region of the frame on
    its windowed grid; samples outside the region, and those the sampler did not produce,
    are one more bin, expected N (1 − ∫pdf over the region)."""
    if data.valid_count == 0:
        return Verdict("chi-square", subject, data.frame.label, None, "no sample produced: nothing to bin")
    tests, panels, problems = [], [], []
    for k, region in enumerate(data.regions):
        chi = _region_test(data, region, seed + k)
        if chi is None:
            continue
        tests.append(chi)
        # A cell whose quadrature finds no mass but holds a sample is zero-pdf's to judge:
        # it evaluates the pdf at the sample itself, where a sliver of a light is not missed.
        problems += [line.strip()[len("problem: "):] for line in chi.messages.splitlines()
                     if line.strip().startswith("problem: ") and "impossible" not in line]
        assert chi.histogram is not None and chi.expected is not None
        panels.append({"observed": chi.histogram, "expected": chi.expected, "window": region.describe()})
    data.chi = tests
    level = family.per_test
    p_values = [t.p_value for t in tests]
    passed = not problems and all(p >= level for p in p_values)
    if len(tests) == 1:
        t = tests[0]
        summary = (f"p = {t.p_value:.3g} ({'≥' if t.p_value >= level else '<'} {level:.2g}), "
                   f"statistic {t.statistic:.0f}, dof {t.dof}")
    else:
        summary = (f"{len(tests)} regions: p = {', '.join(f'{p:.3g}' for p in p_values)} "
                   f"({'all ≥' if all(p >= level for p in p_values) else 'not all ≥'} {level:.2g})")
    if problems:
        summary += "; " + problems[0]
    numbers = {"p_value": _finite(min(p_values)), "p_values": [_finite(p) for p in p_values],
               "statistic": [_finite(t.statistic) for t in tests], "dof": [t.dof for t in tests],
               "threshold": level, "regions": [r["window"] for r in panels], "problems": problems}
    return Verdict("chi-square", subject, data.frame.label, passed, summary, numbers,
                   {"kind": "histograms", "panels": panels})


def _region_test(data: FrameData, region: Region, seed: int) -> ChiSquareTest | None:
    """The chi-square test of one region (None where it holds no sample and no mass)."""
    valid = data.draw.valid.copy()
    inside = region.contains(data.draw.dirs[valid])
    valid[valid] = inside
    pdf = region.restrict(data.frame.pdf)
    if not valid.any() and region.cap is None and not region.whole:
        return None  # the rest of the sphere, empty: nothing to test there
    win = region.window
    dirs_w, jac = win.forward(data.draw.dirs[valid])
    out_dirs = np.zeros_like(data.draw.dirs)
    out_dirs[valid] = dirs_w
    # The pdf the harness sees at each sample: the recomputed one (the sampler's own is
    # the pdf-at-sample check's); a sample where it is 0 keeps a placeholder so that it
    # stays a sample.
    rec = data.recomputed[inside]
    reported = np.zeros(data.count)
    reported[valid] = np.where(rec > 0.0, rec / jac, 1.0)
    res, _ = grid_sizes(data.count)
    chi = ChiSquareTest(lambda count, s: (out_dirs, reported), win.wrap_pdf(pdf), win.axis,
                        sample_count=data.count, res=res, seed=seed, allow_invalid=True, pdf_mismatch_fraction=1.0)
    chi.run(1.0, 1)  # the verdict applies the family's level
    return chi


def pdf_integral(data: FrameData, family: Family, subject: str) -> Verdict:
    """∫pdf ≤ 1 and = the valid fraction, within the quadrature's and the fraction's
    standard errors (z at the family's level) plus INTEGRAL_FLOOR."""
    integral, v = data.integral, data.valid_fraction
    spread = math.hypot(data.integral_se, data.valid_se)
    floor = INTEGRAL_FLOOR * max(abs(integral), v, 1e-300)
    allowed = family.z_two_sided * spread + floor
    diff = integral - v
    above_one = integral - 1.0 - (family.z_one_sided * data.integral_se + floor)
    passed = abs(diff) <= allowed and above_one <= 0.0
    summary = (f"∫pdf = {integral:.6g} ± {data.integral_se:.2g}, valid fraction {v:.6g}: "
               f"ratio {integral / v if v else math.inf:.5g}, |Δ| {abs(diff):.2g} {'≤' if abs(diff) <= allowed else '>'} "
               f"{allowed:.2g}")
    if above_one > 0.0:
        summary += "; ∫pdf > 1"
    if not passed and data.dark_integral is not None and data.dark_fraction is not None \
            and data.dark_integral > floor:
        summary += (f"; where eval = 0 (e.g. below the horizon) ∫pdf = {data.dark_integral:.4g}, "
                    f"samples {data.dark_fraction:.4g}")
    numbers = {"integral": integral, "integral_stderr": data.integral_se, "valid_fraction": v,
               "valid_stderr": data.valid_se, "ratio": _finite(integral / v) if v else None, "allowed": allowed,
               "integral_where_eval_is_0": data.dark_integral, "samples_where_eval_is_0": data.dark_fraction}
    figure = {"kind": "bars", "labels": ["∫pdf", "valid fraction"], "values": [integral, v],
              "errors": [data.integral_se, data.valid_se], "reference": 1.0}
    return Verdict("pdf-integral", subject, data.frame.label, passed, summary, numbers, figure)


def pdf_at_sample(data: FrameData, subject: str) -> Verdict:
    """The sampler's own pdf against the pdf recomputed at its direction (deterministic)."""
    if data.draw.reported is None:
        return Verdict("pdf-at-sample", subject, data.frame.label, None, "the sampler reports no pdf")
    rep = data.draw.reported[data.draw.valid]
    rec = data.recomputed
    if rep.size == 0:
        return Verdict("pdf-at-sample", subject, data.frame.label, None, "no sample produced")
    scale = np.maximum(np.abs(rep), np.abs(rec))
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(scale > 0.0, np.abs(rep - rec) / scale, 0.0)
        ratio = np.where(rec > 0.0, rep / rec, np.nan)
    rel = np.where(np.isfinite(rel), rel, np.inf)
    bad = int(np.count_nonzero(rel > PDF_RTOL))
    frac = bad / rep.size
    passed = frac <= PDF_MISMATCH_FRACTION
    finite = ratio[np.isfinite(ratio)]
    median = float(np.median(finite)) if finite.size else math.nan
    summary = (f"{bad} of {rep.size} samples ({frac:.3g}) differ by > {PDF_RTOL:g} relative "
               f"(at most {PDF_MISMATCH_FRACTION:g} may); median reported/recomputed {median:.5g}")
    numbers = {"mismatched": bad, "fraction": frac, "median_ratio": _finite(median),
               "worst_relative": _finite(float(rel.max()))}
    figure = {"kind": "ratios", "values": finite, "xlabel": "reported pdf / recomputed pdf"}
    return Verdict("pdf-at-sample", subject, data.frame.label, passed, summary, numbers, figure)


def zero_pdf(data: FrameData, subject: str) -> Verdict:
    """No produced sample where the pdf is 0 (deterministic)."""
    if data.valid_count == 0:
        return Verdict("zero-pdf", subject, data.frame.label, None, "no sample produced")
    zero = ~(data.recomputed > 0.0)  # 0, negative or NaN: not a density a sample can have
    count = int(np.count_nonzero(zero))
    frac = count / data.valid_count
    passed = frac <= ZERO_PDF_FRACTION
    summary = f"{count} of {data.valid_count} samples ({frac:.3g}) where the pdf is 0 (at most {ZERO_PDF_FRACTION:g})"
    dirs = data.draw.dirs[data.draw.valid][zero]
    numbers = {"count": count, "fraction": frac}
    figure = {"kind": "points", "dirs": dirs[:20000], "all": data.draw.dirs[data.draw.valid][:20000],
              "normal": data.frame.normal}
    return Verdict("zero-pdf", subject, data.frame.label, passed, summary, numbers, figure)


def measure(data: FrameData, moved: FrameData, family: Family, subject: str) -> Verdict:
    """∫pdf/valid fraction at the receiver and with the light MOVE_FACTOR× as far: equal
    for a solid-angle density; an area density's falls as distance⁻²."""
    r1, se1 = _ratio(data)
    r2, se2 = _ratio(moved)
    if not (r1 > 0.0 and r2 > 0.0):
        return Verdict("measure", subject, data.frame.label, None, "no sample produced at one of the distances")
    allowed = family.z_two_sided * math.hypot(se1, se2) + 2.0 * INTEGRAL_FLOOR * max(r1, r2)
    passed = abs(r2 - r1) <= allowed
    k = math.log(r2 / r1) / math.log(MOVE_FACTOR)
    summary = (f"∫pdf/valid fraction {r1:.5g} here, {r2:.5g} with the light {MOVE_FACTOR:g}× as far: "
               f"∝ distance^{k:+.2f}")
    if not passed:
        summary += (" — an area density (per unit area of the light): a solid-angle pdf is p_A·t²/|cos θ_y|"
                    if abs(k + 2.0) < 0.5 else " — the normalisation depends on the distance")
    numbers = {"ratio_here": r1, "ratio_moved": r2, "stderr_here": se1, "stderr_moved": se2, "exponent": k,
               "distance_factor": MOVE_FACTOR, "allowed": allowed}
    figure = {"kind": "measure", "distances": [1.0, MOVE_FACTOR], "values": [r1, r2], "errors": [se1, se2]}
    return Verdict("measure", subject, data.frame.label, passed, summary, numbers, figure)


def _ratio(data: FrameData) -> tuple[float, float]:
    v = data.valid_fraction
    if v == 0.0:
        return 0.0, 0.0
    r = data.integral / v
    return r, r * math.hypot(data.integral_se / max(data.integral, 1e-300), data.valid_se / v)


def unbiased(label: str, mean: float, se: float, ref: float, family: Family, subject: str) -> Verdict:
    """z = (mean − closed form)/stderr at the family's two-sided level."""
    if se == 0.0:
        passed = mean == ref
        z = 0.0 if passed else math.copysign(math.inf, mean - ref)
    else:
        z = (mean - ref) / se
        passed = abs(z) <= family.z_two_sided
    summary = f"mean {mean:.6g} ± {se:.2g}, closed form {ref:.6g}: z = {z:+.2f} (|z| ≤ {family.z_two_sided:.2f})"
    numbers = {"mean": mean, "stderr": se, "reference": ref, "z": _finite(z)}
    figure = {"kind": "bars", "labels": ["mean", "closed form"], "values": [mean, ref], "errors": [se, 0.0]}
    return Verdict("unbiased", subject, label, passed, summary, numbers, figure)


def sample_weights(data: FrameData) -> NDArray:
    """(N, C) weight of every sample (0 where none was produced): the sampler's own, or
    eval/pdf with the recomputed pdf."""
    frame, draw = data.frame, data.draw
    if draw.weight is not None:
        w = np.where(draw.valid[:, None], draw.weight, 0.0)
        return np.where(np.isfinite(w), w, 0.0)
    assert frame.eval is not None
    out = np.zeros((data.count, len(data.eval_integral)))
    dirs = draw.dirs[draw.valid]
    if len(dirs):
        f = frame.eval(dirs)
        with np.errstate(divide="ignore", invalid="ignore"):
            out[draw.valid] = np.where(data.recomputed[:, None] > 0.0, f / data.recomputed[:, None], 0.0)
    return out


def weight(data: FrameData, subject: str) -> Verdict:
    """The sampler's weight against eval/pdf at its direction (deterministic)."""
    frame, draw = data.frame, data.draw
    if draw.weight is None or frame.eval is None:
        return Verdict("weight", subject, frame.label, None, "the sampler reports no weight")
    ok = draw.valid.copy()
    ok[draw.valid] = data.recomputed > 0.0
    if not ok.any():
        return Verdict("weight", subject, frame.label, None, "no sample with a density")
    w = draw.weight[ok]
    f = frame.eval(draw.dirs[ok])
    p = data.recomputed[data.recomputed > 0.0]
    expected = f / p[:, None]
    scale = np.maximum(np.abs(w), np.abs(expected))
    tiny = 1e-7 * max(float(scale.max()), 1e-300)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(scale > tiny, np.abs(w - expected) / scale, 0.0)
    rel = np.where(np.isfinite(rel), rel, np.inf).max(axis=1)
    bad = int(np.count_nonzero(rel > PDF_RTOL))
    frac = bad / len(rel)
    passed = frac <= PDF_MISMATCH_FRACTION
    summary = f"{bad} of {len(rel)} samples ({frac:.3g}) with weight ≠ eval/pdf beyond {PDF_RTOL:g} relative"
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = (w / expected).ravel()
    figure = {"kind": "ratios", "values": ratio[np.isfinite(ratio)], "xlabel": "weight / (eval/pdf)"}
    return Verdict("weight", subject, frame.label, passed, summary, {"mismatched": bad, "fraction": frac}, figure)


def eval_quadrature(data: FrameData, family: Family, subject: str) -> Verdict:
    """Per channel, the mean sample weight against ∫eval dω by quadrature."""
    assert data.eval_integral is not None and data.eval_se is not None
    w = sample_weights(data)
    if not np.any(w) and not np.any(data.eval_integral):
        return Verdict("eval-quadrature", subject, data.frame.label, None, "eval is 0 everywhere (a black BSDF)")
    mean = w.mean(axis=0)
    se = w.std(axis=0, ddof=1) / math.sqrt(len(w))
    spread = np.hypot(se, data.eval_se)
    allowed = family.z_two_sided * spread + INTEGRAL_FLOOR * np.abs(data.eval_integral)
    diff = mean - data.eval_integral
    passed = bool(np.all(np.abs(diff) <= allowed))
    worst = int(np.argmax(np.abs(diff) - allowed))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = mean / data.eval_integral
    summary = (f"mean weight {_vec(mean)} ± {_vec(se)}, ∫eval {_vec(data.eval_integral)} ± {_vec(data.eval_se)}: "
               f"ratio {_vec(ratio)}; |Δ| {abs(diff[worst]):.2g} {'≤' if passed else '>'} {allowed[worst]:.2g}")
    numbers = {"mean_weight": mean.tolist(), "mean_stderr": se.tolist(), "integral": data.eval_integral.tolist(),
               "integral_stderr": data.eval_se.tolist(), "allowed": allowed.tolist()}
    figure = {"kind": "channels", "series": {"mean weight": (mean, se), "∫eval": (data.eval_integral, data.eval_se)}}
    return Verdict("eval-quadrature", subject, data.frame.label, passed, summary, numbers, figure)


def energy(data: FrameData, family: Family, subject: str) -> Verdict:
    """The albedo, ∫eval dω and the mean weight, ≤ 1 in every channel (one-sided)."""
    assert data.eval_integral is not None and data.eval_se is not None
    w = sample_weights(data)
    mean = w.mean(axis=0)
    se = w.std(axis=0, ddof=1) / math.sqrt(len(w))
    z = family.z_one_sided
    excess_q = data.eval_integral - 1.0 - (z * data.eval_se + INTEGRAL_FLOOR)
    excess_w = mean - 1.0 - (z * se + INTEGRAL_FLOOR)
    passed = bool(np.all(excess_q <= 0.0) and np.all(excess_w <= 0.0))
    summary = f"albedo ∫eval {_vec(data.eval_integral)}, mean weight {_vec(mean)} (≤ 1 allowed)"
    numbers = {"albedo": data.eval_integral.tolist(), "mean_weight": mean.tolist()}
    figure = {"kind": "channels", "series": {"∫eval": (data.eval_integral, data.eval_se), "mean weight": (mean, se)},
              "reference": 1.0}
    return Verdict("energy", subject, data.frame.label, passed, summary, numbers, figure)


def reciprocity(frame: Frame, subject: str, seed: int, pairs: int) -> Verdict:
    """f(a→b) against f(b→a) at pairs of directions (deterministic)."""
    if frame.reciprocity is None:
        return Verdict("reciprocity", subject, frame.label, None, "the BSDF does not claim reciprocity")
    ab, ba = frame.reciprocity(pairs, seed)
    scale = np.maximum(np.abs(ab), np.abs(ba))
    top = float(scale.max()) if scale.size else 0.0
    if top == 0.0:
        return Verdict("reciprocity", subject, frame.label, None, "f is 0 at every pair")
    keep = scale > 1e-5 * top  # f ~1e-5 of its peak is float32 noise in both orders
    rel = np.abs(ab - ba)[keep] / scale[keep]
    bad = int(np.count_nonzero(rel > RECIPROCITY_RTOL))
    frac = bad / rel.size
    passed = frac <= RECIPROCITY_FRACTION
    summary = (f"{bad} of {rel.size} pairs ({frac:.3g}) with f(a→b) ≠ f(b→a) beyond {RECIPROCITY_RTOL:g} relative; "
               f"worst {float(rel.max()):.2g}")
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = (ab / ba)[keep]
    figure = {"kind": "ratios", "values": ratio[np.isfinite(ratio)], "xlabel": "f(a→b) / f(b→a)"}
    return Verdict("reciprocity", subject, frame.label, passed, summary,
                   {"mismatched": bad, "fraction": frac, "worst_relative": float(rel.max())}, figure)


def weights_checks(label: str, subject: str, pdfs: NDArray, w: NDArray, dirs: NDArray,
                   normal: NDArray) -> list[Verdict]:
    """weights-sum and weights-zero of a combiner's weights ``w`` (K, T) at directions
    where the techniques' pdfs are ``pdfs`` (K, T) (deterministic)."""
    some = np.any(pdfs > 0.0, axis=1)
    total = w.sum(axis=1)
    off = np.abs(total - 1.0)
    off = np.where(np.isfinite(off), off, np.inf)
    bad = some & (off > WEIGHTS_TOL)
    count = int(np.count_nonzero(bad))
    worst = float(off[some].max()) if some.any() else 0.0
    out = [Verdict("weights-sum", subject, label, count == 0,
                   f"{count} of {int(some.sum())} directions where Σ w ≠ 1 beyond {WEIGHTS_TOL:g}; "
                   f"worst |Σ w − 1| {worst:.3g}",
                   {"bad": count, "directions": int(some.sum()), "worst": _finite(worst)},
                   {"kind": "sphere", "dirs": dirs[some], "values": (total - 1.0)[some], "normal": normal,
                    "title": "Σ w − 1"})]
    none = pdfs <= 0.0
    stray = none & (w != 0.0)
    count = int(np.count_nonzero(np.any(stray, axis=1)))
    k_bad = [int(k) for k in np.flatnonzero(stray.any(axis=0))]
    out.append(Verdict("weights-zero", subject, label, count == 0,
                       f"{count} directions where a technique without density has a weight ≠ 0"
                       + (f" (technique {', '.join(map(str, k_bad))})" if k_bad else ""),
                       {"bad": count, "techniques": k_bad},
                       {"kind": "sphere", "dirs": dirs[np.any(none, axis=1)],
                        "values": np.where(stray, np.abs(w), 0.0).max(axis=1)[np.any(none, axis=1)],
                        "normal": normal, "title": "|w_k| where g_k = 0"}))
    return out


def _vec(a: NDArray) -> str:
    a = np.atleast_1d(a)
    return f"{a[0]:.5g}" if a.size == 1 else "(" + ", ".join(f"{x:.5g}" for x in a) + ")"


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None
