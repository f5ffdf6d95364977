"""A run of ``warpis check``: every applicable check on every frame of its subjects, one family.

The run first counts its statistical tests (per frame: a chi-square test per region of
its samples, pdf-integral, measure where a light can move, eval-quadrature and energy per
colour channel where there is an eval; per receiver: unbiased), so that each is held at the Šidák level that keeps the
family-wise false-failure rate of the whole run at ``Budget.significance``.  Then it
measures each frame once (its samples, their pdfs, the quadrature of pdf and eval over
the windowed sphere) and gives every check its verdict.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import WarpisError
from . import checks as ck
from .checks import CHECKS, STATISTICAL, Family, Verdict
from .subjects import Frame, Subject

DEFAULT_SAMPLES = 1_000_000
DEFAULT_FRAMES = 4
DEFAULT_SIGNIFICANCE = 1e-3
# independent:single estimates of the unbiasedness check: N samples each, samples/N trials.
UNBIASED_N = 16
# A combiner's weights are probed at this many directions per technique and frame, and as
# many spread uniformly over the sphere.
COMBINER_DIRECTIONS = 100_000


@dataclass(frozen=True)
class Budget:
    """How much a run spends, at which seed and family-wise level, on which checks."""

    samples: int = DEFAULT_SAMPLES  # per frame
    seed: int = 0
    significance: float = DEFAULT_SIGNIFICANCE  # family-wise
    checks: tuple[str, ...] | None = None  # None: every applicable check

    def wants(self, check: str) -> bool:
        return self.checks is None or check in self.checks


def parse_checks(text: str | None) -> tuple[str, ...] | None:
    """``--checks a,b``: names of CHECKS, or a one-line error listing them."""
    if text is None:
        return None
    names = tuple(t.strip() for t in text.split(",") if t.strip())
    if not names:
        raise WarpisError("--checks: names no check")
    unknown = [n for n in names if n not in CHECKS]
    if unknown:
        raise WarpisError(f"--checks: unknown check {unknown[0]!r} (valid: {', '.join(CHECKS)})")
    return names


def check_significance(value: Any, what: str = "--significance") -> float:
    """A family-wise level: a number in (0, 1)."""
    try:
        a = float(value)
    except (TypeError, ValueError):
        raise WarpisError(f"{what}: expected a number in (0, 1), got {value!r}") from None
    if isinstance(value, bool) or not math.isfinite(a) or not 0.0 < a < 1.0:
        raise WarpisError(f"{what}: must be a number in (0, 1), got {value!r}")
    return a


@dataclass
class CheckRun:
    """The verdicts of one run."""

    title: str
    verdicts: list[Verdict]
    family: Family
    budget: Budget
    seconds: float
    notes: list[str] = field(default_factory=list)

    @property
    def failed(self) -> list[Verdict]:
        return [v for v in self.verdicts if v.passed is False]

    @property
    def passed(self) -> bool:
        return not self.failed

    def as_dict(self) -> dict[str, Any]:
        return {"title": self.title, "passed": self.passed, "samples": self.budget.samples, "seed": self.budget.seed,
                "significance": self.family.alpha, "statistical_tests": self.family.tests,
                "per_test_level": self.family.per_test, "seconds": self.seconds, "notes": self.notes,
                "verdicts": [v.as_dict() for v in self.verdicts]}


def frame_seed(seed: int, *parts: int) -> int:
    """An independent seed per (run seed, subject, frame)."""
    return int(np.random.SeedSequence([seed, *parts]).generate_state(1)[0])


def _channels(frame: Frame) -> int:
    """Colour channels of a frame's eval (probed at its normal); 0 without one."""
    if frame.eval is None:
        return 0
    return int(np.atleast_2d(frame.eval(frame.normal[None, :])).shape[1])


def count_tests(subjects: Sequence[Subject], budget: Budget) -> int:
    """The statistical tests the run will make (its Šidák family): a chi-square test per
    region of each frame (found on the first samples of its draw, as the run finds them)."""
    tests = 0
    for i, s in enumerate(subjects):
        for j, f in enumerate(s.frames):
            if budget.wants("chi-square"):
                tests += len(ck.frame_regions(f, frame_seed(budget.seed, i, j)))
            tests += budget.wants("pdf-integral")
            tests += budget.wants("measure") and f.moved is not None
            c = _channels(f)
            tests += c * budget.wants("eval-quadrature") + 2 * c * budget.wants("energy")
        if s.unbiased is not None and budget.wants("unbiased"):
            tests += s.unbiased.receivers
    return tests


def run_subjects(title: str, subjects: Sequence[Subject], budget: Budget,
                 progress: Callable[[str], None] | None = None, tests: int | None = None) -> CheckRun:
    """Every applicable check of ``budget`` on every frame of ``subjects``; ``tests``: the
    size of the family, where it is larger than the run's own (a part of a larger run)."""
    start = time.perf_counter()
    family = Family(budget.significance, max(count_tests(subjects, budget), tests or 0))
    verdicts: list[Verdict] = []
    notes = [n for s in subjects for n in s.notes]
    for i, s in enumerate(subjects):
        for j, f in enumerate(s.frames):
            if progress is not None:
                progress(f"{s.label}: {f.label}")
            verdicts += _frame_verdicts(s, f, frame_seed(budget.seed, i, j), budget, family)
        if s.unbiased is not None and budget.wants("unbiased"):
            trials = max(budget.samples // UNBIASED_N, 2)
            rows = s.unbiased.run(trials, frame_seed(budget.seed, i, 1 << 20))
            if not rows:
                notes.append(f"{s.label}: unbiased not applicable: no receiver of the frames has a closed form")
            verdicts += [ck.unbiased(label, mean, se, ref, family, s.label) for label, mean, se, ref in rows]
    return CheckRun(title, verdicts, family, budget, time.perf_counter() - start, notes)


def _frame_verdicts(subject: Subject, frame: Frame, seed: int, budget: Budget, family: Family) -> list[Verdict]:
    name = subject.label
    data = ck.measure_frame(frame, budget.samples, seed)
    out: list[Verdict] = []
    if budget.wants("chi-square"):
        out.append(ck.chi_square(data, family, name, seed))
    if budget.wants("pdf-integral"):
        out.append(ck.pdf_integral(data, family, name))
    if budget.wants("pdf-at-sample"):
        out.append(ck.pdf_at_sample(data, name))
    if budget.wants("zero-pdf"):
        out.append(ck.zero_pdf(data, name))
    if budget.wants("measure") and frame.moved is not None:
        moved = ck.measure_frame(frame.moved(), budget.samples, seed ^ 0x5EED, with_eval=False)
        out.append(ck.measure(data, moved, family, name))
    if frame.eval is not None:
        if budget.wants("weight") and data.draw.weight is not None:
            out.append(ck.weight(data, name))
        if budget.wants("eval-quadrature"):
            out.append(ck.eval_quadrature(data, family, name))
        if budget.wants("energy"):
            out.append(ck.energy(data, family, name))
    if budget.wants("reciprocity") and frame.reciprocity is not None:
        out.append(ck.reciprocity(frame, name, seed, min(budget.samples, ck.RECIPROCITY_PAIRS)))
    return out


# --------------------------------------------------------------------------- combiners


@dataclass
class CombinerSubject:
    """A combiner's weights over the techniques of a set, seen in the same frames."""

    name: str
    weights: Callable[[np.ndarray], np.ndarray]
    techniques: list[Subject]  # one per technique, frames aligned


def run_combiner(title: str, subject: CombinerSubject, budget: Budget) -> CheckRun:
    """weights-sum and weights-zero at every frame: the weights at samples of every
    technique of the set and at directions spread over the sphere."""
    start = time.perf_counter()
    family = Family(budget.significance, 0)  # every check of a combiner is deterministic
    verdicts: list[Verdict] = []
    frames = len(subject.techniques[0].frames)
    per = min(budget.samples, COMBINER_DIRECTIONS)
    for j in range(frames):
        seed = frame_seed(budget.seed, 0, j)
        dirs = [_uniform_sphere(per, seed)]
        for t in subject.techniques:
            draw = t.frames[j].draw(per, seed)
            dirs.append(draw.dirs[draw.valid])
        d = np.concatenate(dirs)
        pdfs = np.stack([np.asarray(t.frames[j].pdf(d), np.float64) for t in subject.techniques], axis=1)
        w = _combiner_weights(subject, pdfs)
        found = ck.weights_checks(subject.techniques[0].frames[j].label, f"combiner {subject.name}", pdfs, w, d,
                                  subject.techniques[0].frames[j].normal)
        verdicts += [v for v in found if budget.wants(v.check)]
    notes = [f"techniques: {' + '.join(t.name for t in subject.techniques)}"] + subject.techniques[0].notes
    return CheckRun(title, verdicts, family, budget, time.perf_counter() - start, notes)


def _combiner_weights(subject: CombinerSubject, pdfs: np.ndarray) -> np.ndarray:
    try:
        with np.errstate(divide="ignore", invalid="ignore"):
            value = subject.weights(pdfs.copy())
    except WarpisError:
        raise
    except Exception as exc:  # a user's code: one line, not a traceback
        first = str(exc).strip().splitlines()
        raise WarpisError(f"combiner {subject.name!r}: weights raised {type(exc).__name__}"
                          + (f": {first[0]}" if first else "")) from None
    try:
        w = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise WarpisError(f"combiner {subject.name!r}: weights returned {type(value).__name__}, not numbers") from None
    if w.shape != pdfs.shape:
        raise WarpisError(f"combiner {subject.name!r}: weights returned shape {w.shape} for pdfs of shape "
                          f"{pdfs.shape}, expected the same shape")
    return w


def _uniform_sphere(count: int, seed: int) -> np.ndarray:
    u = np.random.default_rng([seed, 0x5F]).random((count, 2))
    z = 1.0 - 2.0 * u[:, 0]
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = 2.0 * math.pi * u[:, 1]
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


__all__ = ["Budget", "CheckRun", "CombinerSubject", "DEFAULT_SAMPLES", "DEFAULT_FRAMES", "DEFAULT_SIGNIFICANCE",
           "STATISTICAL", "check_significance", "count_tests", "parse_checks", "run_combiner", "run_subjects"]
