"""The vocabulary of warpis: what an entry of each axis (pattern, combiner, technique, material) is.

Each axis is a :class:`Registry` of frozen descriptors, declared in the kernel module of
its axis beside the Warp branch that implements it: ``PATTERNS`` in
``kernels/patterns.py``, ``COMBINERS`` in ``kernels/estimators.py``, ``TECHNIQUES`` in
``kernels/techniques.py``, ``MATERIALS`` in ``kernels/integrand.py``.  Adding an entry is
one file: its descriptor, its ``wp.constant`` and its branch.  A descriptor holds
everything the rest of warpis needs to know: its name and a one-line description (for
``--help``), its integer code for the kernels, its constraints on N, the numpy twins the
theory uses (how a pattern splits its samples into independent blocks, a combiner's
weights), whether it has an exact-variance form, and the convergence rate to expect.
Every other module reads the registries: estimator parsing, the kernel launch arguments,
the theory's forms, verify's default estimators, study slopes, the scene loader's
material table and the error messages that list valid names.

Codes are dispatch tags.  The kernel modules define their ``wp.constant`` from them
(``JITTERED = wp.constant(PATTERNS["jittered"].code)``), named ``entry.constant``, so a
kernel branch and its registry entry cannot disagree (tests/test_vocabulary.py checks
every entry).  A code never enters a random stream or a result; append new entries with
the next free code anyway, so that existing codes never move.  An entry may leave out its
theory (``blocks=None``, ``weights=None``, ``inverse_pdf_integral=None``, ``slope=None``):
the predictions then say why a form is missing instead of failing.

Techniques and patterns can also come from outside warpis (:class:`UserEntries`):
``warpis.register_technique`` and ``warpis.register_pattern`` append an entry (next free
code, no theory) for a user's Warp functions, and the kernels that dispatch on those
codes are rebuilt for the registered set.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator, MutableMapping
from dataclasses import dataclass
from typing import Any, Generic, NamedTuple, TypeVar

import numpy as np

from .errors import WarpisError

# float32 holds every integer up to 2^24 exactly: a jittered cell index beyond it (and a
# cell narrower than the generator's 2^-24 lattice) would no longer be placed exactly.
MAX_CELLS_PER_SIDE = 1 << 24


def grid_shape(m: int) -> tuple[int, int]:
    """(rows, cols) with rows × cols = m and rows the largest divisor of m ≤ √m.

    Searches down from ⌊√m⌋ and stops at the first divisor: at most √m steps, i.e.
    46,341 for the largest N the kernels take (limits.MAX_COUNT).
    """
    rows = next(d for d in range(math.isqrt(m), 0, -1) if m % d == 0)
    return rows, m // rows


# --------------------------------------------------------------------------- registries


@dataclass(frozen=True, kw_only=True)
class Entry:
    """What every entry of every axis has."""

    name: str  # as spelled in estimator specs and scene files
    code: int  # the kernels' integer for it
    description: str  # one line, for --help

    @property
    def constant(self) -> str:
        """The name of its ``wp.constant`` in the kernel module of its axis."""
        return self.name.upper().replace("-", "_")


E = TypeVar("E", bound=Entry)


class Registry(MutableMapping[str, E], Generic[E]):
    """Name → descriptor of one axis, in declaration order; names and codes are unique.

    Mutable so that a test can register an entry for its duration (pytest's
    ``monkeypatch.setitem``); warpis itself only reads it.
    """

    def __init__(self, axis: str, entries: Iterable[E]):
        self.axis = axis
        self._entries: dict[str, E] = {}
        # Names registered outside this registry (a numpy technique for `warpis check`),
        # each with the line that says why it cannot be used here.
        self.elsewhere: dict[str, str] = {}
        for entry in entries:
            self[entry.name] = entry

    def __getitem__(self, name: str) -> E:
        return self._entries[name]

    def __setitem__(self, name: str, entry: E) -> None:
        if name != entry.name:
            raise ValueError(f"{self.axis} {entry.name!r} registered under the name {name!r}")
        clash = [e.name for e in self._entries.values() if e.code == entry.code and e.name != name]
        if clash:
            raise ValueError(f"{self.axis} {name!r} has code {entry.code}, already that of {clash[0]!r}")
        self._entries[name] = entry

    def __delitem__(self, name: str) -> None:
        del self._entries[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)

    def __repr__(self) -> str:
        return f"Registry({self.axis!r}, {list(self._entries)})"

    def unknown(self, name: str) -> str:
        """The one-line problem of a name that is not registered, listing the valid ones
        (or, for a name known elsewhere, why it cannot be used here)."""
        if name in self.elsewhere:
            return self.elsewhere[name]
        return f"unknown {self.axis} {name!r} (valid: {', '.join(self)})"

    def lookup(self, name: str) -> E:
        """The entry called ``name``, or a one-line WarpisError listing the valid names."""
        if name not in self._entries:
            raise WarpisError(self.unknown(name))
        return self._entries[name]

    def by_code(self, code: int) -> E:
        """The entry whose kernel code is ``code``."""
        return next(e for e in self._entries.values() if e.code == int(code))

    def help(self) -> str:
        """One line per entry: its name and description."""
        return "\n".join(f"  {e.name:<20} {e.description}" for e in self._entries.values())


class UserEntry(NamedTuple):
    """An entry registered from Python: its name, its code and the user's Warp functions."""

    name: str
    code: int
    functions: tuple[Any, ...]  # @wp.func each, in the order the axis's dispatch takes them


class UserEntries:
    """The entries of one registry that came from a user's Warp functions
    (``register_technique``, ``register_pattern``): their checks, codes and removal."""

    def __init__(self, registry: Registry[Any], how: str):
        self.registry, self.how = registry, how  # how: the function that adds them, for messages
        self._added: dict[str, UserEntry] = {}

    def next_code(self, name: str, functions: dict[str, Any]) -> int:
        """The code for a new entry ``name`` made of ``functions`` (role → function), or a
        one-line WarpisError: not Warp functions, a taken name, or one an estimator spec
        cannot spell."""
        axis = self.registry.axis
        import warp as wp  # only a user entry needs Warp here: the vocabulary stays under the kernels

        if not all(isinstance(f, wp.Function) for f in functions.values()):
            kind = "@wp.func functions" if len(functions) > 1 else "a @wp.func function"
            raise WarpisError(f"{axis} {name!r}: {' and '.join(functions)} must be {kind}")
        if name in self.registry:
            raise WarpisError(f"{axis} {name!r} is already registered")
        if not name or any(c in name for c in ":+ "):
            raise WarpisError(f"{axis} {name!r}: a name must be non-empty, without ':', '+' or spaces")
        return max(e.code for e in self.registry.values()) + 1

    def add(self, entry: E, functions: tuple[Any, ...]) -> E:
        self.registry[entry.name] = entry
        self._added[entry.name] = UserEntry(entry.name, entry.code, functions)
        return entry

    def remove(self, name: str) -> None:
        if name not in self._added:
            raise WarpisError(f"{self.registry.axis} {name!r} was not added by {self.how}")
        del self._added[name]
        if name in self.registry:
            del self.registry[name]

    def active(self) -> tuple[UserEntry, ...]:
        """The user entries still in the registry, in registration order (hashable: it keys
        the kernels built for them)."""
        return tuple(u for u in self._added.values()
                     if u.name in self.registry and self.registry[u.name].code == u.code)


# --------------------------------------------------------------------------- patterns


@dataclass(frozen=True)
class Blocks:
    """The independent blocks of one technique's m samples under a pattern (the theory's
    unit: an estimate's variance is the sum of its blocks' variances)."""

    count: int  # number of blocks (identical blocks are not repeated)
    multiplicity: int  # each listed block stands for this many identical ones
    cells: tuple[int, int]  # (rows, cols) of the grid the blocks live on; (1, 1) = whole square
    paired: bool  # antithetic: block value is ψ(u) + ψ(reflect(u))


@dataclass(frozen=True)
class Slope:
    """The rate theory expects for variance against N (log-log), stated beside fitted slopes."""

    smooth: float  # on smooth integrands
    discontinuous: float  # where the integrand has edges (shadows, light silhouettes)

    def as_dict(self) -> dict[str, float]:
        return {"smooth": self.smooth, "discontinuous": self.discontinuous}


# Independent-sample rates: stratification changes the constant, not the rate.
IID_SLOPE = Slope(-1.0, -1.0)
# Jittered 2D points: −2 on smooth integrands, −1.5 across edges.
STRATIFIED_SLOPE = Slope(-2.0, -1.5)
# Owen-scrambled (0,m,2)-nets: N^-3 (log N) on smooth integrands (Owen 1997), and the
# N^-3/2 of stratification across edges.
SCRAMBLED_NET_SLOPE = Slope(-3.0, -1.5)


@dataclass(frozen=True, kw_only=True)
class Pattern(Entry):
    """Where the m primary samples u ∈ [0,1)² of one technique in one trial fall."""

    paired: bool = False  # places samples in pairs (u and a reflection): m must be even
    # m → the strata per side its points must land in exactly (None: it stratifies nothing);
    # float32 resolves at most MAX_CELLS_PER_SIDE of them
    strata: Callable[[int], int] | None = None
    blocks: Callable[[int], Blocks] | None = None  # m samples → independent blocks; None: no block form
    # Var(Σ ψ) over its m points from pairs of points, for a set that is not independent
    # blocks (point_sets: a SumVarianceForm); None with blocks None: no exact form
    sum_variance: Callable[..., Any] | None = None
    slope: Slope | None = None  # expected convergence (for a stratifying combiner); None: none stated

    def problem(self, m: int) -> str | None:
        """Why this pattern cannot place ``m`` samples per technique, or None when it can."""
        if m < 1:
            return "needs at least one sample per technique"
        if self.paired and m % 2:
            return f"pairs samples, so it needs an even number of samples per technique (got {m})"
        if self.strata is not None and self.strata(m) > MAX_CELLS_PER_SIDE:
            return (f"stratifies {m} samples per technique into {self.strata(m)} strata per side, and float32 "
                    f"cannot place points inside more than {MAX_CELLS_PER_SIDE} per side")
        return None


def grid_side(m: int) -> int:
    """Strata per side of the grid_shape(m) grid (jittered cells)."""
    return max(grid_shape(m))


def every_sample(m: int) -> int:
    """Strata per side of a pattern that puts each of its m points in a row and column of its own."""
    return m




# --------------------------------------------------------------------------- combiners

@dataclass(frozen=True)
class WeightContext:
    """What a combiner's weights may read besides f and the pdfs."""

    parameter: float | None = None  # the spec's COMBINER=VALUE (cutoff's α), or its default
    alpha: np.ndarray | None = None  # (P, N_g) optimal-MIS coefficients at each sample's receiver


# ψ_k: the value a sample of technique k adds to the combiner's sum, from f (P,) and the
# pdfs of every technique of the set (P, N_g) at the sample's direction.  theory.py sets ψ
# to 0 where f = 0 or g_k = 0, except for a combiner with ``every_sample``, which gets the
# pdfs at every sample (all 0 at a failed one) and says itself what each adds.  Each
# mirrors its branch in estimators.py.
Weights = Callable[[int, np.ndarray, np.ndarray, WeightContext], np.ndarray]


@dataclass(frozen=True)
class Parameter:
    """A number a combiner takes from its spelling, ``COMBINER=VALUE``."""

    name: str  # what it is called in messages and docs, e.g. "α"
    default: float
    low: float  # valid values: low ≤ value ≤ high
    high: float

    def parse(self, text: str) -> float:
        """``text`` as a valid value, or a one-line problem (ValueError)."""
        try:
            value = float(text)
        except ValueError:
            raise ValueError(f"{self.name} must be a number (got {text!r})") from None
        if not (math.isfinite(value) and self.low <= value <= self.high):
            raise ValueError(f"{self.name} must lie in [{self.low:g}, {self.high:g}] (got {text})")
        return value



@dataclass(frozen=True, kw_only=True)
class Combiner(Entry):
    """How the samples of the estimator's techniques combine into one estimate."""

    several: bool  # combines two or more techniques (False: takes exactly one)
    splits_n: bool = False  # m = N/N_g samples per technique (N must divide); else each pattern places N
    random_pick: bool = False  # one stream; each sample picks its technique at random (not stratified)
    divides_by_n: bool = False  # estimate = Σ_k Σ_i ψ_k / (m·N_g) (balance); else / m, as the kernel does
    unbiased: bool = True  # converges to F (biased converges to ∫ f g)
    weights: Weights | None = None  # numpy twin of ψ_k for the theory; None: no exact form
    no_exact_form: str | None = None  # why it has no weights, where that is the mathematics, not a gap
    verify_under: tuple[str, ...] | None = None  # patterns `warpis verify` runs it under by default (None: all)
    parameter: Parameter | None = None  # a number spelled COMBINER=VALUE (None: takes none)
    every_sample: bool = False  # its ψ needs every technique's pdf at every sample, f = 0 or not
    # samples per technique (of N/N_g) spent on an independent pilot before the pattern's
    # points; None: no pilot
    pilot: Callable[[int], int] | None = None
    oracle: bool = False  # reads per-receiver coefficients computed from warpis's dense evaluation
    max_techniques: int | None = None  # most techniques it combines (the kernels' fixed-size vectors)

    def per_technique(self, n: int, techniques: int) -> int:
        """m: the samples each technique's pattern places (after its pilot, if any)."""
        m = n // techniques if self.splits_n else n
        return m - self.pilot(m) if self.pilot else m

    def pilot_samples(self, n: int, techniques: int) -> int:
        """Samples each technique spends on the pilot (0 without one)."""
        m = n // techniques if self.splits_n else n
        return self.pilot(m) if self.pilot else 0

    def scale(self, m: int, techniques: int) -> float:
        """c in estimate = c · Σ_k Σ_i ψ_k."""
        return 1.0 / (m * techniques) if self.divides_by_n else 1.0 / m




def expected_slope(pattern: Pattern, combiner: Combiner) -> Slope | None:
    """The rate to expect for variance against N, or None where no rate is stated.

    The pattern's rate, except that a combiner that picks its technique at random per
    sample (the mixture) is not stratified whatever the pattern: −1.
    """
    return IID_SLOPE if combiner.random_pick else pattern.slope


# --------------------------------------------------------------------------- techniques


@dataclass(frozen=True, kw_only=True)
class Technique(Entry):
    """A sampling technique: a map u → ω with its solid-angle pdf (techniques.py)."""

    light: bool = False  # samples the emitters; its pdf sums over every emitter crossing
    environment: bool = False  # samples the environment light (a scene needs one to run it)
    inverse_pdf_integral: float | None = None  # ∫ 1/g dω over the hemisphere (eq17); None: not known
    cost: float = 1.0  # relative CPU cost of one sample: ranks quadrature candidates (reference.py)




# --------------------------------------------------------------------------- materials


@dataclass(frozen=True, kw_only=True)
class Material(Entry):
    """The BRDF ρ at a receiver (integrand.brdf) and how a scene file spells it."""

    keys: tuple[str, ...] = ()  # TOML keys of its table besides "type" (scenes/toml_source.py parses each)
    required: tuple[str, ...] = ()  # those of ``keys`` that have no default
    diffuse: bool  # ρ is constant: Lambert's closed form × lambert_scale is exact where unoccluded
    lambert_scale: Callable[[Any, np.ndarray], np.ndarray]  # (Receivers, rows) → the factor on Lambert's irradiance
    bsdf_technique: str  # the technique that samples its BRDF


# --------------------------------------------------------------------------- the materials
# The BRDFs the integrand evaluates (kernels/integrand.py reads their codes), here beside
# the other registries so that scene sources validate against them without the kernels.


def _unit_rho(rx: Any, rows: np.ndarray) -> np.ndarray:
    return np.ones(len(rows))


def _albedo_over_pi(rx: Any, rows: np.ndarray) -> np.ndarray:
    return rx.albedo[rows] / np.pi


def _specular_over_pi(rx: Any, rows: np.ndarray) -> np.ndarray:
    return rx.specular[rows].sum(axis=1) / np.pi


def _diffuse_and_specular_over_pi(rx: Any, rows: np.ndarray) -> np.ndarray:
    return (rx.albedo[rows] + rx.specular[rows].sum(axis=1)) / np.pi


MICROFACET_KEYS = ("alpha", "distribution", "sample_visible", "eta", "specular", "view")

MATERIALS: Registry[Material] = Registry("material", [
    Material(name="irradiance", code=0, description="ρ = 1: F is the irradiance", diffuse=True,
             lambert_scale=_unit_rho, bsdf_technique="cosine"),
    Material(name="lambert", code=1, description="diffuse, ρ = albedo/π", keys=("albedo",), diffuse=True,
             lambert_scale=_albedo_over_pi, bsdf_technique="cosine"),
    # A Phong lobe is normalised so that ∫ ρ cos θ dω ≈ albedo: albedo/π × Lambert's value
    # gives F's scale (reference.py's floor), though not F.  Likewise the microfacet
    # materials' reflectances over π.
    Material(name="phong", code=2, description="energy-normalised Phong lobe albedo·(e+2)/(2π)·cos^e α about the "
                                               "view's mirror direction",
             keys=("albedo", "exponent", "view"), required=("exponent", "view"), diffuse=False,
             lambert_scale=_albedo_over_pi, bsdf_technique="phong"),
    Material(name="roughconductor", code=3, description="Mitsuba 3's roughconductor: a GGX or Beckmann microfacet "
                                                        "lobe with the conductor's Fresnel term",
             keys=(*MICROFACET_KEYS, "k"), required=("alpha", "eta", "k", "view"), diffuse=False,
             lambert_scale=_specular_over_pi, bsdf_technique="bsdf"),
    Material(name="roughplastic", code=4, description="Mitsuba 3's roughplastic: a dielectric microfacet coating over "
                                                      "a diffuse base, with its internal scattering",
             keys=(*MICROFACET_KEYS, "albedo"), required=("alpha", "view"), diffuse=False,
             lambert_scale=_diffuse_and_specular_over_pi, bsdf_technique="bsdf"),
])


# Microfacet distributions, numbered as Mitsuba 3 numbers them (MicrofacetType);
# kernels/shading.py names the same codes for the kernels.
DISTRIBUTIONS = {"beckmann": 0, "ggx": 1}
