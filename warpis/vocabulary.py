"""The vocabulary of warpis: one registry per axis (patterns, combiners, techniques, materials).

Each entry is a frozen descriptor that holds everything the rest of warpis needs to know
about it: its name and a one-line description (for ``--help``), its integer code for the
kernels, its constraints on N, the numpy twins the theory uses (how a pattern splits its
samples into independent blocks, a combiner's weights), whether it has an exact-variance
form, and the convergence rate to expect.  Every other module reads these registries:
estimator parsing, the kernel launch arguments, the theory's forms, verify's default
estimators, study slopes, the scene loader's material table and the error messages that
list valid names.

Codes are dispatch tags.  The kernel modules define their ``wp.constant`` from them
(``JITTERED = wp.constant(PATTERNS["jittered"].code)``), named ``entry.constant``, so a
kernel branch and its registry entry cannot disagree (tests/test_vocabulary.py checks
every entry).  A code never enters a random stream or a result; append new entries with
the next free code anyway, so that existing codes never move.

Adding an entry is one descriptor here, plus its constant and the branch that implements
it in the kernel module of its axis (patterns.py, estimators.py, techniques.py,
integrand.py); its tests come from looping over the registry.  An entry may leave out its
theory (``blocks=None``, ``weights=None``, ``inverse_pdf_integral=None``, ``slope=None``):
the predictions then say why a form is missing instead of failing.

A technique can also come from outside warpis: ``warpis.register_technique`` appends an
entry (next free code, no theory) for a user's Warp ``sample``/``pdf`` pair, and the kernels
that dispatch on technique codes are rebuilt for the registered set (techniques.py).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator, MutableMapping
from dataclasses import dataclass
from typing import Generic, TypeVar

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
        """The one-line problem of a name that is not registered, listing the valid ones."""
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


@dataclass(frozen=True, kw_only=True)
class Pattern(Entry):
    """Where the m primary samples u ∈ [0,1)² of one technique in one trial fall."""

    paired: bool = False  # places samples in pairs (u and a reflection): m must be even
    grid: bool = False  # one point per cell of the grid_shape(m) grid: float32 limits the cells per side
    blocks: Callable[[int], Blocks] | None = None  # m samples → independent blocks; None: no exact form
    slope: Slope | None = None  # expected convergence (for a stratifying combiner); None: none stated

    def problem(self, m: int) -> str | None:
        """Why this pattern cannot place ``m`` samples per technique, or None when it can."""
        if m < 1:
            return "needs at least one sample per technique"
        if self.paired and m % 2:
            return f"pairs samples, so it needs an even number of samples per technique (got {m})"
        if self.grid and max(grid_shape(m)) > MAX_CELLS_PER_SIDE:
            rows, cols = grid_shape(m)
            return (f"lays {m} samples per technique on a {rows} × {cols} grid, and float32 cannot place points "
                    f"inside more than {MAX_CELLS_PER_SIDE} cells per side")
        return None


def _whole_square(m: int) -> Blocks:
    return Blocks(1, m, (1, 1), False)


def _pairs_on_square(m: int) -> Blocks:
    return Blocks(1, m // 2, (1, 1), True)


def _cells(m: int) -> Blocks:
    return Blocks(m, 1, grid_shape(m), False)


def _pairs_of_cells(m: int) -> Blocks:
    """Cell i < m/2 and its mirror m−1−i form one block (see patterns.pattern_point)."""
    return Blocks(m // 2, 1, grid_shape(m), True)


PATTERNS: Registry[Pattern] = Registry("pattern", [
    Pattern(name="independent", code=0, description="uniform independent points", blocks=_whole_square,
            slope=IID_SLOPE),
    Pattern(name="jittered", code=1, description="one uniform point per cell of a rows × cols = m grid, as square "
                                                 "as m allows",
            grid=True, blocks=_cells, slope=STRATIFIED_SLOPE),
    Pattern(name="antithetic", code=2, description="pairs u and (1,1) − u", paired=True, blocks=_pairs_on_square,
            slope=IID_SLOPE),
    Pattern(name="jittered-antithetic", code=3, description="jittered points in half the cells, reflected through "
                                                            "the centre into the mirrored cells",
            paired=True, grid=True, blocks=_pairs_of_cells, slope=STRATIFIED_SLOPE),
])


# --------------------------------------------------------------------------- combiners

# ψ_k: the value a sample of technique k adds to the combiner's sum, from f (P,) and the
# pdfs of every technique of the set (P, N_g) at the sample's direction (theory.py masks
# samples with f = 0 or g_k = 0).  Each mirrors its branch in estimators.stratified_trial.
Weights = Callable[[int, np.ndarray, np.ndarray], np.ndarray]


def _importance_weights(k: int, f: np.ndarray, pdf: np.ndarray) -> np.ndarray:
    return f / pdf[:, k]


def _unweighted(k: int, f: np.ndarray, pdf: np.ndarray) -> np.ndarray:
    return f.copy()


def _balance_weights(k: int, f: np.ndarray, pdf: np.ndarray) -> np.ndarray:
    return f * pdf.shape[1] / pdf.sum(axis=1)  # f/ḡ


def _power_weights(k: int, f: np.ndarray, pdf: np.ndarray) -> np.ndarray:
    return f * pdf[:, k] / (pdf**2).sum(axis=1)  # w_k f/g_k, w_k = g_k²/Σ_j g_j²


@dataclass(frozen=True, kw_only=True)
class Combiner(Entry):
    """How the samples of the estimator's techniques combine into one estimate."""

    several: bool  # combines two or more techniques (False: takes exactly one)
    splits_n: bool = False  # m = N/N_g samples per technique (N must divide); else each pattern places N
    random_pick: bool = False  # one stream; each sample picks its technique at random (not stratified)
    divides_by_n: bool = False  # estimate = Σ_k Σ_i ψ_k / (m·N_g) (balance); else / m, as the kernel does
    unbiased: bool = True  # converges to F (biased converges to ∫ f g)
    weights: Weights | None = None  # numpy twin of ψ_k for the theory; None: no exact form
    verify_under: tuple[str, ...] | None = None  # patterns `warpis verify` runs it under by default (None: all)

    def per_technique(self, n: int, techniques: int) -> int:
        """m: the samples each technique's pattern places."""
        return n // techniques if self.splits_n else n

    def scale(self, m: int, techniques: int) -> float:
        """c in estimate = c · Σ_k Σ_i ψ_k."""
        return 1.0 / (m * techniques) if self.divides_by_n else 1.0 / m


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
])


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
    inverse_pdf_integral: float | None = None  # ∫ 1/g dω over the hemisphere (eq17); None: not known
    cost: float = 1.0  # relative CPU cost of one sample: ranks quadrature candidates (reference.py)


TECHNIQUES: Registry[Technique] = Registry("technique", [
    # ∫ 1/g dω is 2π · 2π for uniform; for cosine ∫ π/cos θ dω diverges (logarithmically)
    # at the horizon; the lobe and the light techniques vanish on part of the hemisphere.
    Technique(name="uniform", code=0, description="uniform over the receiver's hemisphere, 1/(2π)",
              inverse_pdf_integral=4 * math.pi**2),
    Technique(name="cosine", code=1, description="cosine-weighted hemisphere, cos θ/π",
              inverse_pdf_integral=math.inf),
    Technique(name="phong", code=2, description="the Phong lobe (e+1)/(2π) cos^e α about the view's mirror direction",
              inverse_pdf_integral=math.inf),
    # Costs measured on the bundled scenes: a light-solid-angle sample costs 1.5–2
    # light-area or 4–7 phong samples.  A fixed table keeps references reproducible.
    Technique(name="light-area", code=3, description="a uniform point on the emitters (triangle picked by area)",
              light=True, inverse_pdf_integral=math.inf, cost=2.0),
    Technique(name="light-power", code=4, description="a uniform point on an emitter triangle picked by "
                                                      "radiance × area",
              light=True, inverse_pdf_integral=math.inf, cost=2.0),
    Technique(name="light-solid-angle", code=5, description="a uniform direction in a spherical triangle, picked by "
                                                            "solid angle × radiance (Arvo 1995)",
              light=True, inverse_pdf_integral=math.inf, cost=5.0),
])


# --------------------------------------------------------------------------- materials


def _unit_rho(albedo: np.ndarray) -> np.ndarray:
    return np.ones_like(albedo)


def _albedo_over_pi(albedo: np.ndarray) -> np.ndarray:
    return albedo / np.pi


@dataclass(frozen=True, kw_only=True)
class Material(Entry):
    """The BRDF ρ at a receiver (integrand.brdf) and how a scene file spells it."""

    keys: tuple[str, ...] = ()  # TOML keys of its table besides "type" (scene.py parses each)
    required: tuple[str, ...] = ()  # those of ``keys`` that have no default
    diffuse: bool  # ρ is constant: Lambert's closed form × lambert_scale is exact where unoccluded
    lambert_scale: Callable[[np.ndarray], np.ndarray]  # albedo → the factor on Lambert's irradiance
    bsdf_technique: str  # the technique that samples its BRDF


MATERIALS: Registry[Material] = Registry("material", [
    Material(name="irradiance", code=0, description="ρ = 1: F is the irradiance", diffuse=True,
             lambert_scale=_unit_rho, bsdf_technique="cosine"),
    Material(name="lambert", code=1, description="diffuse, ρ = albedo/π", keys=("albedo",), diffuse=True,
             lambert_scale=_albedo_over_pi, bsdf_technique="cosine"),
    # A Phong lobe is normalised so that ∫ ρ cos θ dω ≈ albedo: albedo/π × Lambert's value
    # gives F's scale (reference.py's floor), though not F.
    Material(name="phong", code=2, description="energy-normalised Phong lobe albedo·(e+2)/(2π)·cos^e α about the "
                                               "view's mirror direction",
             keys=("albedo", "exponent", "view"), required=("exponent", "view"), diffuse=False,
             lambert_scale=_albedo_over_pi, bsdf_technique="phong"),
])


def estimator_help() -> str:
    """The axes of an estimator spec, PATTERN:COMBINER:TECH[+TECH...], a line per entry
    (for ``--help``)."""
    return "\n".join(f"{axis} ({part}):\n{registry.help()}" for axis, part, registry in (
        ("patterns", "PATTERN", PATTERNS), ("combiners", "COMBINER", COMBINERS), ("techniques", "TECH", TECHNIQUES)))
