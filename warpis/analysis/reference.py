"""Ground truth F(x) per receiver: Lambert's closed form where exact, dense quadrature otherwise.

The closed form (``closed_form.triangle_irradiance``, and ``scenes.lambert.sphere_irradiance``
for sphere lights) is exact for irradiance and lambert receivers when no scene triangle
meets any receiver–emitter pyramid (a sphere light's: the pyramids to the faces of a
cube around it) and no sphere enters any light's cone (``closed_form.sphere_occlusion``).  Elsewhere
(occluders, Phong receivers) F is integrated by dense stratified sampling with the same
Warp integrand, as ``replicas`` independent jittered estimates whose spread gives the
standard error (the mean of the replicas over their standard error follows Student's t
with replicas − 1 degrees of freedom, so 32 replicas give a nearly normal z).

Two modes:

* **fixed** (``rel_error=None``, the library default used by ``estimate``, ``verify``
  and ``study``): one round of ``QUADRATURE_SAMPLES`` samples per replica with
  :func:`quadrature_estimator`; cheap, about 1e-4–1e-3 relative on the bundled scenes.
* **to a target** (``rel_error=r``, what ``warpis reference`` does with
  ``DEFAULT_REL_ERROR``): the candidate estimators of the receiver's material
  (:func:`candidates`) race at 1024, 4096, … samples per replica until the cheapest is
  predicted to reach the target within 16× its last count; that one is then run afresh
  (new seed, so the choice does not bias the stated error) at the predicted count, and
  again with more samples while it misses, up to a budget of samples per replica.  The
  prediction uses jittered sampling's rate, error ∝ N^-α with α between 1/2 (no gain)
  and 1 (a smooth 2D integrand), measured from the receiver's own runs; an edge
  (occluder, horizon, light outline) gives α ≈ 3/4, so tightening the target 10× costs
  about 20× the samples.

A receiver meets the target when ``stderr <= r * max(|F|, FLOOR * scale)``, ``scale``
being its Lambert value with every occluder removed (× albedo/π for lambert and phong):
the floor keeps receivers with F ≈ 0 (deep penumbra, a lobe facing away) from
demanding unbounded samples.  Receivers whose replicas are all exactly 0 (umbra) have
stderr 0 and meet any target.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace

import numpy as np

from ..errors import WarpisError
from ..kernels.engine import as_scene, run_trials, select_receivers
from ..kernels.estimators import parse_estimator
from ..kernels.integrand import delta_terms
from ..vocabulary import MATERIALS
from ..kernels.techniques import TECHNIQUES
from ..limits import count as check_count
from ..limits import seed as check_seed
from ..scenes import Scene
from ..scenes.lambert import sphere_irradiance
from .closed_form import DEFAULT_REL_TOL, pyramid_blockers, sphere_light_boxes, sphere_occlusion, triangle_irradiance

QUADRATURE_SAMPLES = 4096
QUADRATURE_REPLICAS = 32
# A seed no estimator run uses by default, so reference and estimates are independent.
REFERENCE_SEED = 0x5EED
# `warpis reference`'s target: the tightest that 2 cores reach in seconds per receiver
# on every bundled scene.  1e-5 costs ~20× more (error ∝ N^-3/4): ~30 s per veach-plates
# receiver, and heavy-occluder's deep penumbra misses it within the default budget.
DEFAULT_REL_ERROR = 1e-4
# Default budget with a target, in samples per replica (× 32 replicas = 33.5M per receiver).
MAX_QUADRATURE_SAMPLES = 1 << 20
PILOT_SAMPLES = 1024  # the race's first count, and the least a reported run uses
PRUNE = 8.0  # candidates this many times costlier than the leader stop racing
FINAL_SEEDS = 1 << 16  # seed offset of the reported rounds, past any race round's
FLOOR = 1e-3  # near F = 0 the tolerance is relative to 1e-3 × the unoccluded value (see above)
# Aim at 0.8 × the tolerance: with 32 replicas the estimated stderr scatters by ~13%, so
# a run sized for the tolerance itself would miss it (and need another round) half the time.
SAFETY = 0.8
ALPHA_RANGE = (0.5, 1.0)  # jittered error ∝ N^-α: 1/2 (no gain) to 1 (smooth 2D integrand)
DEFAULT_ALPHA = 0.75  # an edge (occluder, horizon, light outline) in a 2D integrand
# A round uses at most GROWTH × the samples of the last: a rate measured over 4× extrapolated
# much further over- or undershoots by large factors.
GROWTH = 16

DIFFUSE_CANDIDATES = ("jittered:single:light-solid-angle", "jittered:single:light-area")

Progress = Callable[[int, int], None]  # (done, planned so far) in the unit of the current stage
Stage = Callable[[str, str], None]  # (what starts now, the unit progress then counts in)
# Receivers per call of the closed form's occlusion test (milliseconds each against
# tessellated lights): progress moves between calls, also on a grid of a million.
CLOSED_FORM_CHUNK = 256


@dataclass(frozen=True)
class Reference:
    """The reference value of one receiver."""

    index: int
    value: float
    stderr: float
    method: str  # "closed-form" or "quadrature"
    samples: int  # samples per receiver of the run reported (all replicas); 0 for the closed form
    estimator: str = ""  # the quadrature's estimator; "" for the closed form
    rel_error: float | None = None  # the target asked for; None in fixed mode
    target_met: bool | None = None  # stderr within the target; None in fixed mode
    delta: float = 0.0  # the delta lights' exact term, included in value (0 without delta lights)

    def as_dict(self) -> dict:
        return asdict(self)


def quadrature_estimator(scene: Scene, receiver: int) -> str:
    """The estimator of fixed mode: light sampling; for glossy receivers MIS with the lobe.

    The power heuristic has 1.5–2× less variance than the balance heuristic on
    veach-plates' glossy receivers at the same cost (at N = 1024 to 65536).
    """
    material = scene.receivers.material_of(receiver)
    lights = _lights(scene)
    if material.diffuse and len(lights) == 1:
        return f"jittered:single:{lights[0]}"
    return f"jittered:power:{'+'.join(lights)}+{material.bsdf_technique}"


def _lights(scene: Scene) -> tuple[str, ...]:
    """The light techniques that together cover every emitter of ``scene``: light-solid-angle
    for its emitter triangles, envmap for its environment."""
    return (("light-solid-angle",) if scene.light_count else ()) + \
        (("envmap",) if scene.environment is not None else ())


def candidates(scene: Scene, receiver: int) -> tuple[str, ...]:
    """Estimators a targeted quadrature chooses from for one receiver.

    Measured with run_trials at N = 1024–65536 on the bundled scenes, no single one is
    best: light-solid-angle wins under broad lobes and several lights, light-area under
    one quad light, the lobe alone for sharp lobes under big lights (10–1000× less
    variance × cost).  MIS (balance or power of light-solid-angle + phong) is never
    clearly better than the better of its two techniques alone (within ~15% in variance ×
    cost) and is left out: its weight f/Σg turns any direction where a light pdf
    wrongly reads 0 into a rare huge sample (seen at the silhouettes of veach-plates'
    sphere lights: replica kurtosis ~50 instead of 3), and a replica spread then
    understates the error most of the time.  Single-technique estimators of
    these bounded integrands have light tails, so the t-based stderr holds.
    """
    material = scene.receivers.material_of(receiver)
    bsdf = f"jittered:single:{material.bsdf_technique}"
    if scene.environment is not None:
        # One light technique covers only its own emitters: with an environment and
        # emitter triangles both, light sampling is their MIS.
        lights = _lights(scene)
        light = f"jittered:single:{lights[0]}" if len(lights) == 1 else f"jittered:balance:{'+'.join(lights)}"
        return light, bsdf
    if material.diffuse:
        return DIFFUSE_CANDIDATES
    return ("jittered:single:light-solid-angle", bsdf)


def check_rel_error(value: object, what: str = "rel_error") -> float:
    """A relative error target: a finite number in (0, 1), else a one-line error naming ``what``."""
    try:
        r = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise WarpisError(f"{what}: expected a number in (0, 1), got {value!r}") from None
    if isinstance(value, bool) or not math.isfinite(r) or not 0.0 < r < 1.0:
        raise WarpisError(f"{what}: must be a finite number in (0, 1), got {value!r}")
    return r


def reference(
    scene: Scene,
    receivers: Sequence[int] | None = None,
    samples: int | None = None,
    replicas: int = QUADRATURE_REPLICAS,
    seed: int = REFERENCE_SEED,
    rel_error: float | None = None,
    progress: Progress | None = None,
    closed_form: bool = True,
    stage: Stage | None = None,
) -> list[Reference]:
    """Reference values for the chosen receivers (default: all), with standard errors.

    Parameters
    ----------
    scene
        A loaded scene, or a bundled scene's name or a scene file's path (loaded on the
        CPU as :func:`~warpis.scenes.load_scene` does).
    receivers
        Receiver indices; default all (one integer is one receiver).
    samples
        Jittered samples per replica: the count of fixed mode (default
        ``QUADRATURE_SAMPLES``), or the most a targeted quadrature may use (default
        ``MAX_QUADRATURE_SAMPLES``).
    replicas
        Independent replicas (≥ 2; the stderr is their spread).
    seed
        Seed of the quadrature's random numbers.
    rel_error
        None for fixed mode; else the relative standard error to reach (see the module
        docstring for the rule near F = 0).  Receivers that miss it within ``samples``
        report the error reached, ``target_met=False``, and one warning names them.
    progress
        Called as ``progress(done, planned)`` as the work goes: in receivers through the
        closed form's occlusion test (after every ``CLOSED_FORM_CHUNK``), then in samples
        through the quadrature (after each launch).
    closed_form
        False integrates every receiver by quadrature (to test the quadrature where the
        closed form is known, or to skip the closed form's occlusion test, which costs
        milliseconds per receiver against tessellated lights: camera images).  The test
        runs only for diffuse receivers, the only ones whose closed form is F.
    stage
        Called as ``stage(what, unit)`` when each of those two stages starts
        (``("closed-form test", "receivers")``, ``("quadrature", "samples")``), so that a
        display can say what the counts of ``progress`` are.
    """
    scene = as_scene(scene)
    target = None if rel_error is None else check_rel_error(rel_error)
    budget = check_count(samples if samples is not None else
                         (QUADRATURE_SAMPLES if target is None else MAX_QUADRATURE_SAMPLES), "samples")
    replicas = check_count(replicas, "replicas", minimum=2)
    seed = check_seed(seed)
    idx = select_receivers(scene, receivers)
    values, diffuse = _lambert(scene, idx)
    exact = _unblocked(scene, idx, diffuse, progress, stage) if closed_form else np.zeros(len(idx), bool)
    out: dict[int, Reference] = {}
    delta = delta_terms(scene)
    for i, r in enumerate(idx):
        if exact[i]:  # the closed form is the area lights' part; the quadrature's estimates carry delta already
            out[int(r)] = Reference(int(r), float(values[i] + delta[r]), 0.0, "closed-form", 0, "", target,
                                    None if target is None else True)
    todo = [int(r) for r in idx if int(r) not in out]
    floor = {int(r): FLOOR * abs(float(values[i])) for i, r in enumerate(idx)}
    if todo and stage is not None:
        stage("quadrature", "samples")
    tick = _Ticker(progress)
    if target is None:
        out.update(fixed_quadrature(scene, todo, budget, replicas, seed, tick))
    elif todo:
        out.update(targeted_quadrature(scene, todo, target, budget, replicas, seed, floor, tick))
        _warn_missed([out[r] for r in todo], budget, replicas)
    return [replace(out[int(r)], delta=float(delta[r])) for r in idx]


def _lambert(scene: Scene, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each receiver's Lambert value with every occluder removed (× albedo/π for lambert
    and phong; the irradiance for irradiance receivers), and whether its material is
    diffuse (where that value is F itself when nothing occludes)."""
    rx = scene.receivers
    # The integrand shades at the receiver position x itself (no offset along n).
    values = triangle_irradiance(rx.positions[idx], rx.normals[idx], scene.triangle_vertices(), scene.emission)
    if scene.spheres is not None:
        s = scene.spheres
        values = values + sphere_irradiance(rx.positions[idx], rx.normals[idx], s.centers, s.radii, s.emission,
                                            s.inward)
    if scene.environment is not None:  # a scale only: F itself is never this (see _unblocked)
        values = values + scene.environment.irradiance(rx.normals[idx])
    diffuse = np.zeros(len(idx), bool)
    albedo = np.empty(len(idx))
    for material in MATERIALS.values():
        mine = rx.material[idx] == material.code
        diffuse[mine] = material.diffuse
        albedo[mine] = material.lambert_scale(rx, idx[mine])
    return values * albedo, diffuse


def _unblocked(scene: Scene, idx: np.ndarray, among: np.ndarray, progress: Progress | None = None,
               stage: Stage | None = None) -> np.ndarray:
    """Where no scene triangle meets any receiver–emitter pyramid (the closed form is
    exact), tested only for the receivers ``among`` (the test costs milliseconds per
    receiver against tessellated lights); False elsewhere.

    The test runs ``CLOSED_FORM_CHUNK`` receivers at a time, with ``progress`` told after
    each; its tolerance is the one a single call over all of them would take (it depends
    on the bounding box of the triangles and these receivers), so the result is the same.
    """
    out = np.zeros(len(idx), bool)
    if not among.any() or scene.environment is not None:  # the closed form knows no environment
        return out
    rx, sel = scene.receivers, idx[among]
    tris, emits = scene.triangle_vertices(), scene.emission != 0.0
    spheres = scene.spheres
    if spheres is not None:
        # Sphere lights get pyramids to the faces of a cube around each; a sphere in any
        # light's cone, or a triangle inside a light's cube, sends the receiver to the
        # quadrature (closed_form.sphere_occlusion).
        lights = scene.sphere_lights
        cubes = sphere_light_boxes(spheres.centers[lights], spheres.radii[lights])
        near = sphere_occlusion(rx.positions[sel], tris, scene.emission, spheres.centers, spheres.radii, lights)
        tris = np.concatenate([tris, cubes])
        emits = np.concatenate([emits, np.ones(len(cubes), bool)])
    pts = np.concatenate([tris.reshape(-1, 3), rx.positions[sel]], axis=0)
    tol = DEFAULT_REL_TOL * float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    if stage is not None:
        stage("closed-form test", "receivers")
    clear = np.empty(len(sel), bool)
    for start in range(0, len(sel), CLOSED_FORM_CHUNK):
        part = sel[start:start + CLOSED_FORM_CHUNK]
        clear[start:start + len(part)] = ~pyramid_blockers(rx.positions[part], rx.normals[part], tris, emits, tol)
        if spheres is not None:
            clear[start:start + len(part)] &= ~near[start:start + len(part)]
        if progress is not None:
            progress(start + len(part), len(sel))
    out[among] = clear
    return out


def unoccluded_lambert(scene: Scene, receivers: Sequence[int]) -> np.ndarray:
    """(R,) each receiver's Lambert value with every occluder removed (× albedo/π for
    lambert and phong): the scale of its value, and the light it would get unshadowed."""
    return np.abs(_lambert(scene, np.asarray(receivers, dtype=np.int64))[0])


class _Ticker:
    """Adds launches' samples to a running total for a progress callback."""

    def __init__(self, progress: Progress | None):
        self.progress, self.done, self.planned = progress, 0, 0

    def plan(self, samples: int) -> None:
        self.planned += samples

    def __call__(self, receivers: int, n: int) -> Callable[[int, int], None] | None:
        """A run_trials progress callback for one launch of ``receivers`` × trials × n."""
        if self.progress is None:
            return None
        start = self.done

        def report(trials_done: int, trials: int) -> None:
            self.done = start + trials_done * receivers * n
            self.progress(self.done, max(self.planned, self.done))
        return report


def _run(scene: Scene, spec: str, n: int, group: list[int], replicas: int, seed: int,
         tick: _Ticker) -> dict[int, tuple[float, float]]:
    """(mean, stderr) of ``replicas`` jittered estimates at n samples, per receiver."""
    est = run_trials(scene, spec, n, replicas, seed=seed, receivers=group, progress=tick(len(group), n))
    return {r: (float(row.mean()), float(row.std(ddof=1) / math.sqrt(replicas))) for r, row in zip(group, est)}


def quadrature(scene: Scene, receivers: Sequence[int], spec: str, n: int,
               replicas: int = QUADRATURE_REPLICAS, seed: int = REFERENCE_SEED) -> dict[int, tuple[float, float]]:
    """One quadrature round: (mean, stderr) per receiver of ``replicas`` estimates at n samples."""
    return _run(scene, spec, n, list(receivers), replicas, seed, _Ticker(None))


def fixed_quadrature(scene: Scene, receivers: list[int], n: int, replicas: int, seed: int,
                     tick: _Ticker) -> dict[int, Reference]:
    """Fixed mode: one round of :func:`quadrature_estimator` at n samples per replica."""
    tick.plan(len(receivers) * n * replicas)
    out: dict[int, Reference] = {}
    for spec in sorted({quadrature_estimator(scene, r) for r in receivers}):
        group = [r for r in receivers if quadrature_estimator(scene, r) == spec]
        k = len(parse_estimator(spec).techniques)  # MIS of k techniques: n a multiple of k
        m = n if _runs_at(spec, n) else max(k, n // k * k)
        for r, (mean, se) in _run(scene, spec, m, group, replicas, seed, tick).items():
            out[r] = Reference(r, mean, se, "quadrature", m * replicas, spec)
    return out


# --------------------------------------------------------------------------- to a target


def _round_up(n: float) -> int:
    """The smallest 2^k or 3·2^k ≥ n (few distinct counts batch receivers; ≤ 1.5× waste)."""
    p = 1 << max(0, math.ceil(math.log2(max(n, 1.0))))
    return 3 * p // 4 if p >= 4 and 3 * p // 4 >= n else p


def _runs_at(spec: str, n: int) -> bool:
    """Whether ``spec`` can place n samples (MIS needs n divisible by its techniques)."""
    try:
        parse_estimator(spec).check_n(n)
    except WarpisError:
        return False
    return True


def _cost(spec: str) -> float:
    """Relative cost of one sample (MIS, should a candidate use it, samples its techniques in turn)."""
    techs = parse_estimator(spec).techniques
    return sum(TECHNIQUES[t].cost for t in techs) / len(techs)


def _needed(n: int, se: float, tol: float, alpha: float) -> float:
    """Samples per replica predicted to bring ``se`` (measured at n) to SAFETY × tol."""
    if se <= 0.0:
        return 1.0
    if tol <= 0.0:
        return math.inf
    return float(n) * (se / (SAFETY * tol)) ** (1.0 / alpha)


def _size(need: float, least: int, budget: int, spec: str) -> int:
    """A sample count for ``spec``: ``need`` rounded up, at least ``least``, at most the budget."""
    n = min(_round_up(min(max(need, least), budget)), budget)
    est = parse_estimator(spec)
    k = est.technique_count if est.combiner in ("balance", "power") else 1
    return max(k, n - n % k)  # MIS places n / k samples per technique


def _alpha(se_a: float, se_b: float, ratio: float) -> float:
    """Convergence rate from stderrs at n and ratio × n, clamped to ALPHA_RANGE."""
    if se_a <= 0 or se_b <= 0:
        return ALPHA_RANGE[0]
    return min(max(math.log(se_a / se_b) / math.log(ratio), ALPHA_RANGE[0]), ALPHA_RANGE[1])


@dataclass
class _Plan:
    """One receiver's chosen estimator, its convergence rate, its last run and its next count."""

    spec: str
    alpha: float
    last_n: int
    last_se: float
    n: int = 0

    def advance(self, n: int, se: float, tol: float, budget: int) -> bool:
        """Record a run at n that missed tol; size the next (2× to GROWTH×); False if the budget allows none."""
        if n >= 4 * self.last_n:  # spans under 4× give a rate too noisy to use
            self.alpha = _alpha(self.last_se, se, n / self.last_n)
        self.last_n, self.last_se = n, se
        self.n = _size(_needed(n, se, tol, self.alpha), 2 * n, min(budget, GROWTH * n), self.spec)
        return self.n > n


def _race_round(scene: Scene, alive: dict[int, list[str]], n: int, replicas: int, seed: int,
                tick: _Ticker) -> dict[tuple[int, str], tuple[float, float]]:
    """Every receiver's live candidates at n samples: (receiver, spec) → (mean, stderr)."""
    specs = sorted({s for live in alive.values() for s in live if _runs_at(s, n)})
    groups = {spec: [r for r, live in alive.items() if spec in live] for spec in specs}
    tick.plan(sum(len(g) for g in groups.values()) * n * replicas)
    return {(r, spec): m_se for spec, group in groups.items()
            for r, m_se in _run(scene, spec, n, group, replicas, seed, tick).items()}


def _race(scene: Scene, receivers: list[int], budget: int, replicas: int, seed: int,
          tol: Callable[[int, float], float], tick: _Ticker) -> dict[int, _Plan]:
    """Pick each receiver's estimator by racing its candidates at 1024, 4096, … samples.

    Candidates are ranked at equal n by cost × the samples each would need at a common
    rate (a rate measured over 4× is too noisy to rank on when extrapolated far: it
    picked the lobe alone for a broad-lobe receiver that then missed 1e-5 by 20×).  A
    receiver stops racing once its leader is predicted to need at most GROWTH × n;
    candidates over PRUNE × the leader's cost drop out.
    """
    alive = {r: list(candidates(scene, r)) for r in receivers}
    last: dict[tuple[int, str], tuple[int, float]] = {}
    plans: dict[int, _Plan] = {}
    n, step = min(PILOT_SAMPLES, budget), 0
    while alive:
        runs = _race_round(scene, alive, n, replicas, (seed + 1 + step) % 2**32, tick)
        for r in list(alive):
            mine = {spec: runs[(r, spec)] for spec in alive[r] if (r, spec) in runs}
            t = tol(r, min(mine.values(), key=lambda m_se: m_se[1])[0])
            score = {spec: _cost(spec) * _needed(n, se, t, DEFAULT_ALPHA) for spec, (_, se) in mine.items()}
            spec = min(score, key=score.get)
            se = mine[spec][1]
            alpha = _alpha(last[(r, spec)][1], se, n / last[(r, spec)][0]) if (r, spec) in last else DEFAULT_ALPHA
            need = _needed(n, se, t, alpha)
            if need <= GROWTH * n or 4 * n > budget:
                plans[r] = _Plan(spec, alpha, n, se, _size(need, PILOT_SAMPLES, budget, spec))
                del alive[r]
            else:
                alive[r] = [s for s in mine if score[s] <= PRUNE * score[spec]]
            last.update({(r, s): (n, mine[s][1]) for s in mine})
        n, step = 4 * n, step + 1
    return plans


def targeted_quadrature(scene: Scene, receivers: list[int], rel_error: float, budget: int, replicas: int,
                        seed: int, floor: dict[int, float], tick: _Ticker) -> dict[int, Reference]:
    """Quadrature to stderr ≤ rel_error · max(|F|, floor) per receiver, within ``budget`` samples per replica."""
    def tol(r: int, mean: float) -> float:
        return rel_error * max(abs(mean), floor[r])

    plans = _race(scene, receivers, budget, replicas, seed, tol, tick)
    out: dict[int, Reference] = {}
    for round_ in range(1, 64):  # each round at least doubles n ≤ 2^31: at most 31 rounds
        if not plans:
            break
        # Fresh seeds per round, apart from the race's: the run reported is independent of
        # the choice of estimator and of the earlier rounds.
        round_seed = (seed + FINAL_SEEDS + round_) % 2**32
        batches: dict[tuple[str, int], list[int]] = {}
        for r, p in plans.items():
            batches.setdefault((p.spec, p.n), []).append(r)
        for (spec, n), group in batches.items():
            tick.plan(len(group) * n * replicas)
        for (spec, n), group in sorted(batches.items()):
            for r, (mean, se) in _run(scene, spec, n, group, replicas, round_seed, tick).items():
                met = se <= tol(r, mean)
                if met or not plans[r].advance(n, se, tol(r, mean), budget):
                    out[r] = Reference(r, mean, se, "quadrature", n * replicas, spec, rel_error, met)
                    del plans[r]
    return out


def _warn_missed(refs: list[Reference], budget: int, replicas: int) -> None:
    """One warning naming every receiver that missed its target, with the error it reached."""
    missed = [r for r in refs if r.target_met is False]
    if not missed:
        return
    reached = ", ".join(f"{r.index} ({r.stderr / abs(r.value) if r.value else r.stderr:.2g})" for r in missed)
    warnings.warn(f"reference: {len(missed)} receiver(s) missed the relative error {missed[0].rel_error:g} within "
                  f"{budget} samples per replica × {replicas} replicas; reached: {reached}", stacklevel=3)
