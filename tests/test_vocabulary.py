"""The registries (warpis.vocabulary): codes agree with the kernels, every entry is
consistent, and everything that lists names takes them from the registries.

All checks are deterministic and cheap; the statistical tests of each entry (chi-square
per technique, unbiasedness per pattern × combiner, exact variance against measurement)
live beside their subject and loop over these same registries.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import warpis
from warpis.analysis import theory
from warpis.kernels import estimators, integrand, patterns, techniques
from warpis.kernels.estimators import COMBINERS, Estimator, KernelArgs, estimator_help, parse_estimator
from warpis.kernels.integrand import MATERIALS
from warpis.kernels.patterns import PATTERNS
from warpis.kernels.techniques import TECHNIQUES
from warpis.runs import study_file, study_report
from warpis.runs.verify import default_estimators
from warpis.vocabulary import IID_SLOPE, Pattern, Registry, expected_slope, grid_shape

REGISTRIES = {"pattern": PATTERNS, "combiner": COMBINERS, "technique": TECHNIQUES, "material": MATERIALS}
# The module whose kernels branch on each axis's wp.constants.
KERNEL_MODULES = {"pattern": patterns, "combiner": estimators, "technique": techniques, "material": integrand}
# Codes of the entries that existed when the registries were introduced: they never move
# (new entries take new codes).
FIRST_CODES = {
    "pattern": {"independent": 0, "jittered": 1, "antithetic": 2, "jittered-antithetic": 3},
    "combiner": {"single": 0, "mixture": 1, "balance": 2, "power": 3, "biased": 4},
    "technique": {"uniform": 0, "cosine": 1, "phong": 2, "light-area": 3, "light-power": 4, "light-solid-angle": 5},
    "material": {"irradiance": 0, "lambert": 1, "phong": 2},
}


@pytest.mark.parametrize("axis", REGISTRIES)
def test_codes_are_unique_and_match_the_kernel_constants(axis):
    """Every entry has its wp.constant in the kernel module of its axis, equal to its code;
    codes are unique, and the first entries keep their codes."""
    registry, module = REGISTRIES[axis], KERNEL_MODULES[axis]
    codes = [e.code for e in registry.values()]
    assert len(set(codes)) == len(codes), codes
    for entry in registry.values():
        assert entry.name and entry.description and "\n" not in entry.description, entry
        assert hasattr(module, entry.constant), f"{module.__name__} has no kernel constant {entry.constant}"
        assert getattr(module, entry.constant) == entry.code, entry
        assert registry.by_code(entry.code) is entry
    for name, code in FIRST_CODES[axis].items():
        assert registry[name].code == code


def test_registry_refuses_clashes_and_explains_unknown_names():
    """A second entry with a taken code, or filed under another name, is refused; an unknown
    name gets one line that lists the valid ones."""
    fake = Pattern(name="fake", code=PATTERNS["jittered"].code, description="clashes with jittered")
    with pytest.raises(ValueError, match="already that of 'jittered'"):
        PATTERNS["fake"] = fake
    with pytest.raises(ValueError, match="under the name"):
        PATTERNS["other"] = dataclasses.replace(fake, code=1000)
    assert "fake" not in PATTERNS and "other" not in PATTERNS
    for registry in REGISTRIES.values():
        with pytest.raises(warpis.WarpisError) as err:
            registry.lookup("no-such-entry")
        message = str(err.value)
        assert "\n" not in message and f"unknown {registry.axis} 'no-such-entry'" in message
        assert message.endswith(f"(valid: {', '.join(registry)})")
    with pytest.raises(dataclasses.FrozenInstanceError):
        PATTERNS["jittered"].code = 7
    with pytest.raises(ValueError, match="already that of"):
        Registry("pattern", [fake, dataclasses.replace(fake, name="twin")])


@pytest.mark.parametrize("name", PATTERNS)
def test_pattern_blocks_cover_its_samples(name):
    """For every m a pattern takes, its blocks hold exactly m samples (count × multiplicity,
    two per paired block) on a grid of its cells; m it cannot take has a one-line reason."""
    pattern = PATTERNS[name]
    for m in range(1, 130):
        problem = pattern.problem(m)
        if problem is not None:
            assert "\n" not in problem
            assert pattern.paired and m % 2, (name, m, problem)  # the only limit below 2^24 cells
            continue
        if pattern.blocks is None:
            continue
        b = pattern.blocks(m)
        assert b.count * b.multiplicity * (2 if b.paired else 1) == m, (name, m, b)
        assert b.paired == pattern.paired
        rows, cols = b.cells
        assert b.count <= rows * cols and (rows, cols) in ((1, 1), grid_shape(m))
    assert pattern.problem(0) is not None


@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("combiner", COMBINERS)
def test_every_pattern_and_combiner_checks_n_from_its_entries(pattern, combiner):
    """check_n and KernelArgs follow the registry: N/N_g per technique where the combiner
    splits N, less its pilot where it has one (at least one sample left), an even m for
    paired patterns, the entries' codes for the kernel."""
    comb = COMBINERS[combiner]
    techs = ("light-area", "cosine") if comb.several else ("light-area",)
    est = Estimator(pattern, combiner, techs)
    for n in range(1, 41):
        m = n // len(techs) if comb.splits_n else n
        pilot = comb.pilot(m) if comb.pilot else 0
        ok = (not (comb.splits_n and n % len(techs)) and m - pilot >= 1
              and PATTERNS[pattern].problem(m - pilot) is None)
        if not ok:
            with pytest.raises(warpis.WarpisError):
                est.check_n(n)
            continue
        args = KernelArgs.of(est, n)
        assert (args.pattern, args.combiner, args.m, args.pilot) == (PATTERNS[pattern].code, comb.code, m - pilot,
                                                                      pilot)
        m -= pilot
        assert args.techniques == tuple(TECHNIQUES[t].code for t in techs)
        assert (args.rows, args.cols) == grid_shape(m)


def test_expected_slopes_come_from_the_registry():
    """Stratifying patterns expect −2 (smooth) / −1.5 (edges) unless the combiner picks its
    technique at random per sample; the others −1; study_report.expected_slope reports the same."""
    for pattern in PATTERNS.values():
        for combiner in COMBINERS.values():
            est = Estimator(pattern.name, combiner.name, ("light-area", "cosine") if combiner.several
                            else ("cosine",))
            slope = expected_slope(pattern, combiner)
            assert slope == (IID_SLOPE if combiner.random_pick else pattern.slope)
            assert study_report.expected_slope(est) == (None if slope is None else slope.as_dict())
    assert study_report.expected_slope(parse_estimator("jittered:balance:light-area+cosine")) == {
        "smooth": -2.0, "discontinuous": -1.5}
    assert study_report.expected_slope(parse_estimator("jittered:mixture:light-area+cosine")) == {
        "smooth": -1.0, "discontinuous": -1.0}


def test_combiner_entries_are_consistent():
    """verify's patterns are registered; one-technique combiners place all N; every
    combiner with an exact form has default verify estimators, which parse, under every
    pattern with an exact form (blocks or a pair form); a combiner without one (the
    optimal pilot) says why; the help names every entry."""
    for combiner in COMBINERS.values():
        assert combiner.verify_under is None or set(combiner.verify_under) <= set(PATTERNS)
        assert combiner.several or not combiner.splits_n
        assert (combiner.weights is None) == (combiner.no_exact_form is not None) == (combiner.verify_under == ())
    ests = default_estimators(("light-area", "cosine"))
    assert {e.combiner for e in ests} == {name for name, c in COMBINERS.items() if c.weights is not None}
    assert {e.pattern for e in ests} == {name for name, entry in PATTERNS.items()
                                         if entry.blocks is not None or entry.sum_variance is not None}
    assert len({e.spec for e in ests}) == len(ests)
    text = estimator_help()
    for registry in (PATTERNS, COMBINERS, TECHNIQUES):
        for entry in registry.values():
            assert f"{entry.name} " in text and entry.description in text


def test_material_and_technique_entries_are_consistent():
    """A material's required keys are among its keys, which the scene loader can read; its
    BSDF technique is registered; every technique has a positive cost."""
    from warpis.scenes.toml_source import MATERIAL_PARAMETERS

    receivers = warpis.load_scene("veach-plates").receivers

    for material in MATERIALS.values():
        assert set(material.required) <= set(material.keys) <= set(MATERIAL_PARAMETERS)
        assert material.bsdf_technique in TECHNIQUES
        scale = material.lambert_scale(receivers, np.array([0, 1]))
        assert scale.shape == (2,) and np.all(scale > 0)
    for technique in TECHNIQUES.values():
        assert technique.cost > 0
        assert technique.inverse_pdf_integral is None or technique.inverse_pdf_integral > 0


def test_study_columns_cover_every_form():
    """results.csv has a pred_ column for every form of theory.FORMS (and no other), and its
    bounds are theory's."""
    assert set(study_file.FORMS) == {f.name for f in theory.FORMS}
    assert len(study_file.FORMS) == len(theory.FORMS)
    assert study_file.BOUND_FORMS == theory.BOUNDS == tuple(f.name for f in theory.FORMS if f.bound)
