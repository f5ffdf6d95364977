"""A numpy + Embree reference implementation of two warpis estimators, for benchmarks.

A script module, not part of the installed package: ``scripts/bench.py`` imports it
from this folder, ``tests/test_baseline.py`` by putting this folder on ``sys.path``.
It needs the optional ``embreex`` (``pip install -e ".[bench]"``).

``independent:single:light-area`` and ``jittered:balance:light-area+cosine`` written
the obvious way without Warp: per receiver, the (trials × samples) primary samples are
drawn with numpy's :class:`~numpy.random.Generator`, mapped to directions with the same
maps as :mod:`warpis.kernels.warps` / :mod:`warpis.kernels.techniques`, and the rays are cast with
trimesh's Embree intersector (:class:`trimesh.ray.ray_pyembree.RayMeshIntersector`,
package ``embreex``):

* the shadow ray of each sample is one first-hit query (``intersects_first``) on the
  whole scene along ω from the receiver x, starting where it leaves the receiver's
  self-hit slab (x + δ/(n·ω)·ω, as :mod:`warpis.kernels.integrand`); Le is the radiance of the
  triangle hit when the ray meets its front face (dot((v1 − v0) × (v2 − v0), ω) < 0), else 0;
* the light-area pdf at a direction is the sum over every emitter triangle the ray
  (x, ω) crosses of (1/A_total)·t²/|cos θ_y|, as in :func:`warpis.kernels.techniques.light_pdf`;
  the crossings come from a second intersector built on the emitter triangles alone,
  queried with ``intersects_location(multiple_hits=True)``.

The results agree with :func:`warpis.kernels.engine.run_trials` in distribution (same mean and
variance per receiver), not bit for bit: the random numbers come from a different
generator and everything is in float64.  Work is split into tasks of one receiver and a
chunk of trials; each task has its own generator, seeded from (seed, receiver, first
trial), so the result does not depend on the thread count.  Tasks run on a thread pool:
Embree and numpy's large-array loops release the GIL.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector

from warpis.errors import WarpisError
from warpis.kernels.device import upload
from warpis.kernels.engine import default_threads, select_receivers
from warpis.kernels.estimators import parse_estimator
from warpis.kernels.integrand import MATERIALS
from warpis.scenes import Scene
from warpis.testing import orthonormal_frame
from warpis.vocabulary import grid_shape

__all__ = ["BASELINE_ESTIMATORS", "BaselineScene", "baseline_scene", "baseline_trials"]

BASELINE_ESTIMATORS = ("independent:single:light-area", "jittered:balance:light-area+cosine")

# Target number of samples (shadow rays) of one task: large enough that numpy's and
# Embree's per-call costs vanish, small enough that the temporaries stay at a few tens
# of MB and that the thread pool has tasks to balance.
CHUNK_SAMPLES = 1 << 16

_BELOW_ONE = float(np.nextafter(1.0, 0.0))
_LAMBERT = MATERIALS["lambert"].code
_PHONG = MATERIALS["phong"].code


@dataclass
class BaselineScene:
    """A scene as the numpy baseline sees it: two Embree intersectors and float64 tables."""

    scene: Scene
    everything: RayMeshIntersector  # all triangles: emitters occlude too
    emitters: RayMeshIntersector  # emitter triangles only, for light-area pdfs
    front: np.ndarray  # (T, 3) unnormalised normals (v1 − v0) × (v2 − v0)
    emission: np.ndarray  # (T,)
    corners: np.ndarray  # (E, 3, 3) emitter triangle corners, in scene.emitters order
    emitter_normal: np.ndarray  # (E, 3) unit normals of the emitter triangles
    area_cdf: np.ndarray  # (E + 1,) 0 … 1
    total_area: float

    @classmethod
    def build(cls, scene: Scene) -> "BaselineScene":
        v = np.asarray(scene.vertices, dtype=np.float64)
        tris = np.asarray(scene.triangles, dtype=np.int64)
        corners_all = v[tris]
        front = np.cross(corners_all[:, 1] - corners_all[:, 0], corners_all[:, 2] - corners_all[:, 0])
        everything = RayMeshIntersector(trimesh.Trimesh(v, tris, process=False, validate=False))
        # The emitter mesh keeps only its own vertices (the intersector's scaling and the
        # multi-hit step size follow the extent of the mesh's vertices).
        e_tris = tris[scene.emitters]
        used, local = np.unique(e_tris, return_inverse=True)
        emitters = RayMeshIntersector(
            trimesh.Trimesh(v[used], local.reshape(-1, 3), process=False, validate=False))
        corners = v[e_tris]
        e_front = front[scene.emitters]
        areas = np.asarray(scene.emitter_areas, dtype=np.float64)
        cdf = np.concatenate([[0.0], np.cumsum(areas)])
        cdf /= cdf[-1]
        cdf[-1] = 1.0
        return cls(
            scene=scene, everything=everything, emitters=emitters, front=front,
            emission=np.asarray(scene.emission, dtype=np.float64), corners=corners,
            emitter_normal=e_front / np.linalg.norm(e_front, axis=1, keepdims=True),
            area_cdf=cdf, total_area=float(areas.sum()),
        )

    def warm_up(self) -> None:
        """Build both BVHs now (Embree builds them lazily on the first query)."""
        o = np.zeros((1, 3))
        d = np.array([[0.0, 0.0, 1.0]])
        self.everything.intersects_first(o, d)
        self.emitters.intersects_location(o, d, multiple_hits=True)

    # ----------------------------------------------------------------------- rays

    def incident_radiance(self, origins: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Le of the first surface hit by each ray (origins[i], w[i]): front-face radiance, else 0."""
        hit = self.everything.intersects_first(origins, w)
        found = hit >= 0
        le = np.zeros(len(w))
        tri = hit[found]
        front_hit = np.einsum("ij,ij->i", self.front[tri], w[found]) < 0.0
        le[np.flatnonzero(found)[front_hit]] = self.emission[tri[front_hit]]
        return le

    def light_area_pdf(self, p: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Solid-angle density of light-area sampling at each w[i]: Σ over emitter crossings."""
        if len(w) == 0:
            return np.zeros(0)
        origins = np.broadcast_to(p, w.shape)
        locations, ray, tri = self.emitters.intersects_location(origins, w, multiple_hits=True)
        t2 = np.sum((locations - p) ** 2, axis=1)
        cos_y = np.maximum(np.abs(np.einsum("ij,ij->i", self.emitter_normal[tri], w[ray])), 1e-12)
        return np.bincount(ray, weights=t2 / cos_y, minlength=len(w)) / self.total_area


def baseline_scene(scene: Scene | BaselineScene) -> BaselineScene:
    """The :class:`BaselineScene` of ``scene``, built (BVHs included) once per content,
    kept with its upload (:meth:`warpis.kernels.device.DeviceScene.cached`)."""
    if isinstance(scene, BaselineScene):
        return scene
    return upload(scene).cached("baseline", lambda: _built(scene))


def _built(scene: Scene) -> BaselineScene:
    built = BaselineScene.build(scene)
    built.warm_up()  # before any worker thread can race to build the BVHs
    return built


# --------------------------------------------------------------------------- receivers


@dataclass
class _Receiver:
    p: np.ndarray  # the receiver x
    slab: float  # self-hit slab height: rays start where they leave it (integrand.py)
    n: np.ndarray
    material: int
    albedo: float
    exponent: float
    lobe_axis: np.ndarray
    frame: np.ndarray  # (3, 3) rows: tangent x, tangent y, n

    @classmethod
    def of(cls, bs: BaselineScene, r: int) -> "_Receiver":
        rx = bs.scene.receivers
        n = np.asarray(rx.normals[r], dtype=np.float64)
        v = np.asarray(rx.view[r], dtype=np.float64)
        axis = 2.0 * np.dot(n, v) * n - v
        return cls(p=rx.positions[r], slab=float(upload(bs.scene).slab[r]), n=n, material=int(rx.material[r]),
                   albedo=float(rx.albedo[r]), exponent=float(rx.exponent[r]),
                   lobe_axis=axis / np.linalg.norm(axis), frame=np.stack(orthonormal_frame(n)))

    def integrand(self, bs: BaselineScene, w: np.ndarray) -> np.ndarray:
        """f(ω) = Le · ρ · max(0, n·ω) for each row of w; one shadow ray where f can be > 0."""
        cos_n = w @ self.n
        rho = self.brdf(w)
        live = np.flatnonzero((cos_n > 0.0) & (rho > 0.0))
        f = np.zeros(len(w))
        if len(live):
            wl, cl = w[live], cos_n[live]
            origins = self.p + wl * (self.slab / cl)[:, None]
            f[live] = bs.incident_radiance(origins, wl) * rho[live] * cl
        return f

    def brdf(self, w: np.ndarray) -> np.ndarray:
        if self.material == _LAMBERT:
            return np.full(len(w), self.albedo / math.pi)
        if self.material == _PHONG:
            c = np.maximum(w @ self.lobe_axis, 0.0)
            return self.albedo * (self.exponent + 2.0) / (2.0 * math.pi) * c ** self.exponent * (c > 0.0)
        return np.ones(len(w))


# --------------------------------------------------------------------------- sampling


def _independent(rng: np.random.Generator, trials: int, m: int) -> np.ndarray:
    """(trials, m, 2) iid uniform points."""
    return rng.random((trials, m, 2))


def _jittered(rng: np.random.Generator, trials: int, m: int) -> np.ndarray:
    """(trials, m, 2): one uniform point per cell (row-major) of the grid_shape(m) grid."""
    rows, cols = grid_shape(m)
    cell = np.arange(m)
    base = np.stack([cell % cols, cell // cols], axis=-1).astype(np.float64)
    u = (base + rng.random((trials, m, 2))) / np.array([cols, rows], dtype=np.float64)
    return np.minimum(u, _BELOW_ONE)


def _sample_light_area(bs: BaselineScene, p: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Unit directions towards uniform points on the emitters (u.x picks the triangle by area)."""
    cdf = bs.area_cdf
    k = np.clip(np.searchsorted(cdf, u[:, 0], side="right") - 1, 0, len(cdf) - 2)
    lo, hi = cdf[k], cdf[k + 1]
    ux = np.clip((u[:, 0] - lo) / np.maximum(hi - lo, 1e-300), 0.0, _BELOW_ONE)
    s = np.sqrt(ux)[:, None]
    uy = u[:, 1:2]
    c = bs.corners[k]
    y = (1.0 - s) * c[:, 0] + s * (1.0 - uy) * c[:, 1] + s * uy * c[:, 2]
    d = y - p
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _sample_cosine(rx: _Receiver, u: np.ndarray) -> np.ndarray:
    """Cosine-weighted directions: Shirley–Chiu concentric disk lifted to the hemisphere."""
    a = 2.0 * u[:, 0] - 1.0
    b = 2.0 * u[:, 1] - 1.0
    use_a = np.abs(a) > np.abs(b)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(use_a, a, b)
        theta = np.where(use_a, (math.pi / 4.0) * (b / a), math.pi / 2.0 - (math.pi / 4.0) * (a / b))
    theta = np.where((a == 0.0) & (b == 0.0), 0.0, theta)
    x = r * np.cos(theta)
    y = r * np.sin(theta)
    z = np.sqrt(np.maximum(0.0, 1.0 - x * x - y * y))
    return np.stack([x, y, z], axis=-1) @ rx.frame


# --------------------------------------------------------------------------- estimators


def _single_light_area(bs: BaselineScene, rx: _Receiver, rng: np.random.Generator, trials: int,
                       n: int) -> np.ndarray:
    """independent:single:light-area — (1/N) Σ f/g_light over N light-area samples."""
    u = _independent(rng, trials, n).reshape(-1, 2)
    w = _sample_light_area(bs, rx.p, u)
    f = rx.integrand(bs, w)
    contrib = np.zeros(len(w))
    live = np.flatnonzero(f > 0.0)
    if len(live):
        g = bs.light_area_pdf(rx.p, w[live])
        ok = g > 0.0
        contrib[live[ok]] = f[live[ok]] / g[ok]
    return contrib.reshape(trials, n).sum(axis=1) / n


def _balance_light_area_cosine(bs: BaselineScene, rx: _Receiver, rng: np.random.Generator, trials: int,
                               n: int) -> np.ndarray:
    """jittered:balance:light-area+cosine — m = N/2 jittered samples each, (1/N) Σ f/ḡ."""
    m = n // 2
    total = np.zeros(trials)
    for technique in ("light-area", "cosine"):
        u = _jittered(rng, trials, m).reshape(-1, 2)
        w = _sample_light_area(bs, rx.p, u) if technique == "light-area" else _sample_cosine(rx, u)
        f = rx.integrand(bs, w)
        live = np.flatnonzero(f > 0.0)
        contrib = np.zeros(len(w))
        if len(live):
            wl = w[live]
            g_light = bs.light_area_pdf(rx.p, wl)
            g_cos = np.maximum(wl @ rx.n, 0.0) / math.pi
            own = g_light if technique == "light-area" else g_cos
            ok = own > 0.0  # a sample its own technique gives no density to is a failed sample
            contrib[live[ok]] = f[live[ok]] / (0.5 * (g_light[ok] + g_cos[ok]))
        total += contrib.reshape(trials, m).sum(axis=1)
    return total / n


_KERNELS = {
    "independent:single:light-area": _single_light_area,
    "jittered:balance:light-area+cosine": _balance_light_area_cosine,
}


def baseline_trials(
    scene: Scene | BaselineScene,
    spec: str,
    n: int,
    trials: int,
    seed: int = 0,
    *,
    receivers: Sequence[int] | None = None,
    threads: int | None = None,
    chunk_samples: int = CHUNK_SAMPLES,
) -> np.ndarray:
    """Estimates of F from ``trials`` trials of ``n`` samples, in numpy with Embree rays.

    Parameters
    ----------
    scene
        A loaded scene, or its :class:`BaselineScene` (see :func:`baseline_scene`).
    spec
        ``"independent:single:light-area"`` or ``"jittered:balance:light-area+cosine"``.
    n
        Samples per estimate (N); even for the balance estimator.
    trials
        Independent trials (M).
    seed
        Seed of numpy's generator; task (receiver r, first trial t) uses
        ``SeedSequence(seed, spawn_key=(r, t))``.
    receivers
        Receiver indices (default: all).
    threads
        Worker threads (default: :func:`warpis.kernels.engine.default_threads`).  Does not change
        results.
    chunk_samples
        About this many samples per task.  Changes which random numbers are drawn, not
        their distribution.

    Returns
    -------
    numpy.ndarray
        (R, M) float64 estimates, row i for ``receivers[i]``, distributed as the rows of
        ``run_trials(scene, spec, n, trials, receivers=receivers)``.
    """
    bs = baseline_scene(scene)
    canonical = parse_estimator(spec).spec
    if canonical not in _KERNELS:
        raise WarpisError(f"estimator {spec!r}: the numpy baseline implements only {', '.join(BASELINE_ESTIMATORS)}")
    parse_estimator(canonical).check_n(int(n))
    if trials < 1:
        raise WarpisError(f"trials must be at least 1 (got {trials})")
    kernel = _KERNELS[canonical]
    rx_idx = select_receivers(bs.scene, receivers)
    rx = {int(r): _Receiver.of(bs, int(r)) for r in np.unique(rx_idx)}
    out = np.empty((len(rx_idx), trials))
    chunk = max(1, min(trials, int(chunk_samples) // int(n)))
    tasks = [(i, int(r), start) for i, r in enumerate(rx_idx) for start in range(0, trials, chunk)]

    def run(task: tuple[int, int, int]) -> None:
        i, r, start = task
        count = min(chunk, trials - start)
        rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(r, start)))
        out[i, start:start + count] = kernel(bs, rx[r], rng, count, int(n))

    workers = max(1, int(threads or default_threads()))
    if workers == 1 or len(tasks) == 1:
        for t in tasks:
            run(t)
    else:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            for f in [pool.submit(run, t) for t in tasks]:
                f.result()
    return out
