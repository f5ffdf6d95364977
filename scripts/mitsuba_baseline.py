"""Mitsuba 3 (Dr.Jit, ``llvm_ad_rgb``) implementation of ``independent:single:light-area``, for benchmarks.

A script module, not part of the installed package: ``scripts/bench.py`` imports it from
this folder, ``tests/test_bench_mitsuba.py`` by putting this folder on ``sys.path``.  It
needs the optional ``mitsuba`` (``pip install -e ".[bench]"``) and a libLLVM that Dr.Jit's
LLVM backend can use: ``DRJIT_LIBLLVM_PATH``, or else the first
``/usr/lib/x86_64-linux-gnu/libLLVM.so.19*`` (:func:`llvm_library`).  An older system LLVM
is no substitute: with LLVM 15 the process aborts while compiling the kernels ("Cannot
select: fmaximum"), LLVM 14 is not loaded at all; :func:`mitsuba_unavailable` finds out
in a child process.

The estimator is warpis's, computed over the very same data:

* geometry: one ``mi.Mesh`` holding ``scene.vertices`` and ``scene.triangles`` as float32
  (the arrays warpis uploads), in a scene of its own (``mi.load_dict``); Mitsuba's CPU
  variants trace rays with Embree 3 (its bundled ``libembree3.so``), on a BVH Embree builds;
* receivers: ``scene.receivers`` positions and normals (float32), ρ = 1 for irradiance,
  albedo/π for lambert (other materials are refused), and each receiver's self-hit slab
  δ = ``upload(scene).slab`` (as computed by warpis);
* sampling: the emitter triangle is picked by its share of the total emitter area through
  the same float32 CDF as warpis (a binary search for cdf[k] ≤ u.x < cdf[k+1]), u.x is
  rescaled within [cdf[k], cdf[k+1]) and a point y = (1 − √u₀)a + √u₀(1 − u₁)b + √u₀u₁c
  placed on it (:func:`warpis.kernels.warps.square_to_triangle`); ω = normalize(y − x);
* pdf = (1/A_total)·t²/|cos θ_y| with t = |y − x| and θ_y the angle between ω and the
  sampled triangle's normal.  warpis's :func:`~warpis.kernels.techniques.light_pdf` sums
  that density over *every* emitter crossing of the ray (x, ω); the two agree when a ray
  from a receiver crosses the emitter at most once, which holds when every emitter
  triangle lies in one plane and faces one way.  :meth:`MitsubaScene.build` checks exactly
  that and refuses other scenes (the bundled ``occluded-quad`` and ``heavy-occluder``
  pass: each has one rectangular light);
* f = Le · ρ · max(0, n·ω), Le the emission of the first triangle hit by the ray from
  x + (δ / n·ω)·ω along ω when its front face is hit (dot((v1 − v0) × (v2 − v0), ω) < 0),
  else 0 (:mod:`warpis.kernels.integrand`); the estimate of a trial is (1/N) Σ f/pdf,
  each f/pdf in float32, the sum in float64.

Two ways to find Le (``mode``):

``closest``  ``scene.ray_intersect_preliminary``: the first hit's face index selects its
             emission and face normal (what warpis does; the mode the bench compares).
``anyhit``   ``scene.ray_test`` with maxt just short of y (the distance to y times
             1 − ``mi.math.ShadowEpsilon``, as Mitsuba's own shadow rays): Le is the
             sampled triangle's emission when nothing occludes it and its front faces ω.
             That is the same f when no emitter triangle hides behind another one, as in
             the planar emitters accepted here, so the two modes estimate the same F.

Random numbers: Mitsuba's ``independent`` sampler (PCG32 streams scrambled with TEA),
seeded once per chunk of about :data:`CHUNK_SAMPLES` samples from (seed, chunk index);
chunks are whole trials and do not depend on the thread count, so neither do the
results.  Everything is vectorised over all (receiver, trial, sample) of a chunk at once
in Dr.Jit arrays; Dr.Jit's thread pool (``dr.set_thread_count``) runs the kernels and
Embree's packet queries.
"""

from __future__ import annotations

import importlib.util
import math
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from warpis.check.mitsuba_bsdfs import LLVM_GLOB, llvm_library
from warpis.errors import WarpisError
from warpis.kernels.device import upload
from warpis.kernels.estimators import parse_estimator
from warpis.kernels.integrand import MATERIALS
from warpis.scenes import Scene

__all__ = ["CHUNK_SAMPLES", "MITSUBA_ESTIMATOR", "MODES", "VARIANT", "MitsubaScene", "llvm_library",
           "llvm_variant", "load_mitsuba", "mean_z", "mitsuba_scene", "mitsuba_trials", "mitsuba_unavailable"]

MITSUBA_ESTIMATOR = "independent:single:light-area"
VARIANT = "llvm_ad_rgb"
MODES = ("closest", "anyhit")
# Samples per chunk: enough to keep every Dr.Jit worker and Embree's packets busy, few
# enough that a chunk's arrays (16 MiB per 4-byte value per sample; Dr.Jit keeps a few
# dozen alive across the ray query) stay at a few hundred MB.
CHUNK_SAMPLES = 1 << 22

# Relative tolerances of the planarity check: float32 rounding of the coordinates is
# 6e-8 of their magnitude, a tilt or step that matters is far larger.
PLANE_TOLERANCE = 1e-5
FACING_TOLERANCE = 1e-6
_BELOW_ONE = 0.99999994  # warpis's rescale clamp: u.x stays below 1 in float32
_IRRADIANCE = MATERIALS["irradiance"].code
_LAMBERT = MATERIALS["lambert"].code


# --------------------------------------------------------------------------- import


def load_mitsuba() -> ModuleType:
    """``mitsuba``, its ``llvm_ad_rgb`` variant loaded (ImportError when unavailable).

    The process's current variant is left as it was: everything here runs inside
    :func:`llvm_variant`, so other code using Mitsuba in the same process (warpis's
    Mitsuba scene loader, other tests) keeps its own variant.
    """
    if llvm_library() is None:
        raise ImportError(f"no libLLVM for Dr.Jit: set DRJIT_LIBLLVM_PATH (nothing matches {LLVM_GLOB})")
    import mitsuba as mi

    if VARIANT not in mi.variants():
        raise ImportError(f"mitsuba {mi.__version__} has no {VARIANT} variant")
    with llvm_variant(mi):  # loads it, or raises Dr.Jit's ImportError
        pass
    return mi


@contextmanager
def llvm_variant(mi: ModuleType) -> Iterator[None]:
    """Mitsuba's current variant is ``llvm_ad_rgb`` inside, and what it was outside.

    ``mi.scoped_set_variant`` cannot restore "no variant" (it fails on leaving), so a
    process without one gets ``llvm_ad_rgb`` for good: no one else holds a variant to keep.
    """
    if mi.variant() is None:
        mi.set_variant(VARIANT)
        yield
        return
    with mi.scoped_set_variant(VARIANT):
        yield


_SMOKE = ("import sys; sys.path.insert(0, sys.argv[1]); import mitsuba_baseline as m; "
          "mi = m.load_mitsuba(); import drjit as dr; mi.set_variant(m.VARIANT); "
          "x = dr.maximum(mi.Float([1.0, 2.0]), dr.opaque(mi.Float, 1.5)); dr.eval(x); "
          "print('ok', mi.__version__)")


def mitsuba_unavailable(timeout: float = 120.0) -> str | None:
    """None when Mitsuba's LLVM variant imports and runs a kernel, else one line saying why.

    The check runs in a child process: a libLLVM that Dr.Jit cannot use aborts the
    process that compiles the kernel rather than raising.
    """
    if importlib.util.find_spec("mitsuba") is None:
        return "mitsuba is not installed (pip install -e \".[bench]\")"
    lib = llvm_library()
    if lib is None:
        return f"no libLLVM for Dr.Jit's LLVM backend: set DRJIT_LIBLLVM_PATH (nothing matches {LLVM_GLOB})"
    try:
        res = subprocess.run([sys.executable, "-c", _SMOKE, str(Path(__file__).resolve().parent)],
                             capture_output=True, text=True, timeout=timeout, check=False)
    except subprocess.TimeoutExpired:
        return f"mitsuba {VARIANT} check timed out after {timeout:.0f} s"
    if res.returncode == 0 and res.stdout.startswith("ok"):
        return None
    lines = [ln.strip() for ln in (res.stderr + res.stdout).splitlines() if ln.strip()]
    why = _reason(lines)
    status = f"killed by signal {-res.returncode}" if res.returncode < 0 else f"exit status {res.returncode}"
    return f"mitsuba {VARIANT} is not usable with DRJIT_LIBLLVM_PATH={lib} ({status}): {why}"


def _reason(lines: list[str]) -> str:
    """The telling line of a failed child's output: LLVM's abort message (the lines after
    it dump its selection DAG), else the exception's last line."""
    llvm = [ln for ln in lines if ln.startswith("LLVM ERROR")]
    picked = llvm[0] if llvm else (lines[-1] if lines else "no output")
    return picked[:200]


# --------------------------------------------------------------------------- scene


def _planar_emitter(scene: Scene) -> None:
    """Refuse a scene whose emitter triangles are not one plane facing one way: a ray from
    a receiver could then cross the emitter twice, where warpis's pdf sums both crossings
    and this comparator's counts only the sampled one."""
    corners = scene.triangle_vertices(scene.emitters)  # (E, 3, 3) float64
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    n0 = normals[0]
    scale = max(float(np.abs(corners).max()), float(np.ptp(corners.reshape(-1, 3), axis=0).max()))
    off_plane = np.abs((corners - corners[0, 0]) @ n0).max(axis=1)
    bad = np.flatnonzero(off_plane > PLANE_TOLERANCE * scale)
    if len(bad):
        k = int(bad[0])
        raise WarpisError(
            f"scene {scene.name!r}: the Mitsuba comparator needs a planar emitter (every emitter triangle in the "
            f"plane of the first, so that no ray crosses it twice), but emitter triangle {int(scene.emitters[k])} "
            f"lies {off_plane[k]:.3g} off that plane")
    turned = np.flatnonzero(normals @ n0 < 1.0 - FACING_TOLERANCE)
    if len(turned):
        k = int(turned[0])
        raise WarpisError(
            f"scene {scene.name!r}: the Mitsuba comparator needs a planar emitter facing one way, but emitter "
            f"triangle {int(scene.emitters[k])} faces the other way from the first")


def _rho(scene: Scene) -> np.ndarray:
    """ρ of each receiver: 1 (irradiance) or albedo/π (lambert); other materials refused."""
    rx = scene.receivers
    ok = (rx.material == _IRRADIANCE) | (rx.material == _LAMBERT)
    if not ok.all():
        r = int(np.flatnonzero(~ok)[0])
        raise WarpisError(f"scene {scene.name!r}: the Mitsuba comparator handles irradiance and lambert receivers "
                          f"only; receiver {r} is {rx.material_name(r)}")
    return np.where(rx.material == _LAMBERT, rx.albedo / math.pi, 1.0)


def _area_cdf(areas: np.ndarray) -> np.ndarray:
    """The emitters' area CDF as warpis builds it: float64 sums, normalised, cast to float32."""
    c = np.concatenate([[0.0], np.cumsum(areas, dtype=np.float64)])
    c /= c[-1]
    c[-1] = 1.0
    return c.astype(np.float32)


@dataclass
class MitsubaScene:
    """A warpis scene as Dr.Jit arrays and one Mitsuba scene of its triangles."""

    scene: Scene
    mi: ModuleType
    accel: Any  # mi.Scene: one mi.Mesh of every triangle, emitters included
    face_normal: Any  # mi.Vector3f (T): (v1 − v0) × (v2 − v0), unnormalised
    emission: Any  # mi.Float (T)
    corners: tuple[Any, Any, Any]  # mi.Point3f (E) each: corners a, b, c of the emitter triangles
    emitter_normal: Any  # mi.Vector3f (E), unit
    emitter_emission: Any  # mi.Float (E)
    area_cdf: Any  # mi.Float (E + 1)
    emitter_count: int
    total_area: float
    position: Any  # mi.Point3f (R)
    normal: Any  # mi.Vector3f (R)
    slab: Any  # mi.Float (R)
    rho: Any  # mi.Float (R)
    load_seconds: float  # mi.load_dict's time (Embree's BVH build)

    @classmethod
    def build(cls, scene: Scene) -> MitsubaScene:
        """Check the scene (planar emitter, irradiance/lambert receivers), then build it."""
        _planar_emitter(scene)
        rho = _rho(scene)
        mi = load_mitsuba()
        with llvm_variant(mi):
            return cls._build(scene, mi, rho)

    @classmethod
    def _build(cls, scene: Scene, mi: ModuleType, rho: np.ndarray) -> MitsubaScene:
        v = np.ascontiguousarray(scene.vertices, dtype=np.float32)
        tris = np.ascontiguousarray(scene.triangles, dtype=np.uint32)
        mesh = mi.Mesh("warpis", len(v), len(tris))
        params = mi.traverse(mesh)
        params["vertex_positions"] = mi.Float(v.reshape(-1))
        params["faces"] = mi.UInt32(tris.reshape(-1))
        params.update()
        t0 = time.perf_counter()
        accel = mi.load_dict({"type": "scene", "mesh": mesh})
        load_seconds = time.perf_counter() - t0
        # Face normals from the same float32 corners the rays meet.
        c = v[tris].astype(np.float64)
        front = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
        ec = c[scene.emitters]
        e_front = front[scene.emitters]
        rx = scene.receivers

        def vec(a: np.ndarray, kind: Any) -> Any:
            a = np.ascontiguousarray(a, dtype=np.float32)
            return kind(a[:, 0], a[:, 1], a[:, 2])

        return cls(
            scene=scene, mi=mi, accel=accel, face_normal=vec(front, mi.Vector3f),
            emission=mi.Float(scene.emission.astype(np.float32)),
            corners=(vec(ec[:, 0], mi.Point3f), vec(ec[:, 1], mi.Point3f), vec(ec[:, 2], mi.Point3f)),
            emitter_normal=vec(e_front / np.linalg.norm(e_front, axis=1, keepdims=True), mi.Vector3f),
            emitter_emission=mi.Float(scene.emission[scene.emitters].astype(np.float32)),
            area_cdf=mi.Float(_area_cdf(scene.emitter_areas)), emitter_count=int(scene.emitter_count),
            total_area=float(np.float32(scene.total_emitter_area)),
            position=vec(rx.positions, mi.Point3f), normal=vec(rx.normals, mi.Vector3f),
            slab=mi.Float(np.asarray(upload(scene).slab, dtype=np.float32)), rho=mi.Float(rho.astype(np.float32)),
            load_seconds=load_seconds,
        )

    def warm_up(self, n: int = 2) -> float:
        """Compile (or load from Dr.Jit's kernel cache) both modes' kernels at N = ``n``;
        returns the seconds it took."""
        t0 = time.perf_counter()
        for mode in MODES:
            mitsuba_trials(self, MITSUBA_ESTIMATOR, n, 2, seed=0, mode=mode)
        return time.perf_counter() - t0

    # ----------------------------------------------------------------------- one chunk

    def chunk(self, n: int, trials: int, first_row: int, rows: int, seed: int, mode: str) -> np.ndarray:
        """Estimates of rows first_row … first_row + rows − 1 of the (receiver, trial) rows
        (row = receiver × trials + trial), each the mean of n samples, as float64."""
        mi = self.mi
        dr = _drjit()
        count = rows * n
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(dr.opaque(mi.UInt32, seed), count)
        # Per-chunk numbers are opaque: literals would compile a new kernel for each.
        row = dr.opaque(mi.UInt32, first_row) + dr.arange(mi.UInt32, count) // n
        r = row // dr.opaque(mi.UInt32, trials)
        sums = dr.block_sum(mi.Float64(self._f_over_pdf(r, sampler.next_2d(), mode)), n)
        dr.eval(sums)
        dr.sync_thread()
        return sums.numpy() / n

    def _f_over_pdf(self, r: Any, u: Any, mode: str) -> Any:
        """f/pdf of one light-area sample u at each receiver r (float32)."""
        mi, dr = self.mi, _drjit()
        y, k = self._sample_emitter(u)
        x = dr.gather(mi.Point3f, self.position, r)
        d = y - x
        t2 = dr.squared_norm(d)
        t = dr.sqrt(t2)
        w = d / t
        cos_n = dr.dot(dr.gather(mi.Vector3f, self.normal, r), w)
        cos_y = dr.maximum(dr.abs(dr.dot(dr.gather(mi.Vector3f, self.emitter_normal, k), w)), 1e-12)
        lit = cos_n > 0.0
        # Leave the receiver's self-hit slab along ω, as warpis's integrand does.
        offset = dr.gather(mi.Float, self.slab, r) / cos_n
        origin = x + w * offset
        if mode == "closest":
            le = self._closest_le(origin, w, lit)
        else:
            le = self._anyhit_le(origin, w, t - offset, k, lit)
        f = le * dr.gather(mi.Float, self.rho, r) * cos_n
        return dr.select(lit, f * (self.total_area * cos_y / t2), 0.0)  # f / ((1/A) t²/|cos θ_y|)

    def _sample_emitter(self, u: Any) -> tuple[Any, Any]:
        """A uniform point on the emitters, its triangle picked by area (warpis's map)."""
        mi, dr = self.mi, _drjit()
        cdf = self.area_cdf
        x = u.x
        # First j in 1 … E with cdf[j] > x; triangle k = j − 1 has cdf[k] ≤ x < cdf[k + 1].
        j = dr.binary_search(1, self.emitter_count, lambda i: dr.gather(mi.Float, cdf, i) <= x)
        k = mi.UInt32(j) - 1
        lo = dr.gather(mi.Float, cdf, k)
        hi = dr.gather(mi.Float, cdf, k + 1)
        ux = dr.clip((x - lo) / dr.maximum(hi - lo, 1e-30), 0.0, _BELOW_ONE)
        s = dr.sqrt(ux)
        a, b, c = (dr.gather(mi.Point3f, p, k) for p in self.corners)
        y = (1.0 - s) * a + s * (1.0 - u.y) * b + s * u.y * c
        return y, k

    def _closest_le(self, origin: Any, w: Any, active: Any) -> Any:
        """Emission of the first triangle hit, 0 for a miss or a back face."""
        mi, dr = self.mi, _drjit()
        pi = self.accel.ray_intersect_preliminary(mi.Ray3f(origin, w), coherent=False, active=active)
        hit = active & pi.is_valid()
        face = pi.prim_index
        front = dr.dot(dr.gather(mi.Vector3f, self.face_normal, face, hit), w) < 0.0
        return dr.select(hit & front, dr.gather(mi.Float, self.emission, face, hit), 0.0)

    def _anyhit_le(self, origin: Any, w: Any, dist: Any, k: Any, active: Any) -> Any:
        """Emission of the sampled triangle when nothing lies between and its front faces ω."""
        mi, dr = self.mi, _drjit()
        maxt = dr.maximum(dist * (1.0 - mi.math.ShadowEpsilon), 0.0)
        ray = mi.Ray3f(origin, w)
        ray.maxt = maxt
        blocked = self.accel.ray_test(ray, active)
        front = dr.dot(dr.gather(mi.Vector3f, self.emitter_normal, k), w) < 0.0
        return dr.select(active & ~blocked & front, dr.gather(mi.Float, self.emitter_emission, k), 0.0)


def _drjit() -> ModuleType:
    import drjit

    return drjit


def mitsuba_scene(scene: Scene | MitsubaScene) -> MitsubaScene:
    """The :class:`MitsubaScene` of ``scene``, built once per content and kept with its
    warpis upload (:meth:`warpis.kernels.device.DeviceScene.cached`)."""
    if isinstance(scene, MitsubaScene):
        return scene
    from warpis.kernels.device import upload

    return upload(scene).cached("mitsuba", lambda: MitsubaScene.build(scene))


def mean_z(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-row z of the difference of the means of two (R, M) sets of estimates, on the
    pooled standard error sqrt(se_a² + se_b²); 0 where both rows are one same constant
    (an umbra: every estimate exactly 0), ±inf where two constant rows differ."""
    se = np.hypot(a.std(axis=1, ddof=1) / math.sqrt(a.shape[1]), b.std(axis=1, ddof=1) / math.sqrt(b.shape[1]))
    diff = a.mean(axis=1) - b.mean(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(se > 0.0, diff / se, np.where(diff == 0.0, 0.0, np.copysign(np.inf, diff)))


def _chunk_seed(seed: int, chunk: int) -> int:
    """A 32-bit sampler seed for chunk ``chunk`` of a run with ``seed``."""
    return int(np.random.SeedSequence(int(seed), spawn_key=(int(chunk),)).generate_state(1)[0])


def mitsuba_trials(
    scene: Scene | MitsubaScene,
    spec: str,
    n: int,
    trials: int,
    seed: int = 0,
    *,
    mode: str = "closest",
    threads: int | None = None,
    chunk_samples: int = CHUNK_SAMPLES,
) -> np.ndarray:
    """Estimates of F from ``trials`` trials of ``n`` samples at every receiver, in Dr.Jit.

    Parameters
    ----------
    scene
        A loaded scene, or its :class:`MitsubaScene` (see :func:`mitsuba_scene`).
    spec
        ``"independent:single:light-area"`` (the only estimator implemented).
    n, trials
        Samples per estimate (N) and trials (M).
    seed
        Run seed; chunk c's sampler is seeded from (seed, c).
    mode
        ``"closest"`` (first-hit query) or ``"anyhit"`` (shadow-ray query); see the module
        docstring.
    threads
        Dr.Jit worker threads (``dr.set_thread_count``; default: leave it as it is).  Does
        not change results.
    chunk_samples
        About this many samples per chunk (whole trials).  Changes which random numbers
        are drawn, not their distribution.

    Returns
    -------
    numpy.ndarray
        (R, M) float64 estimates, distributed as the rows of ``run_trials(scene, spec, n, trials)``.
    """
    if parse_estimator(spec).spec != MITSUBA_ESTIMATOR:
        raise WarpisError(f"estimator {spec!r}: the Mitsuba comparator implements only {MITSUBA_ESTIMATOR}")
    if mode not in MODES:
        raise WarpisError(f"mode {mode!r}: expected one of {', '.join(MODES)}")
    if n < 1 or trials < 1:
        raise WarpisError(f"n and trials must be at least 1 (got {n}, {trials})")
    ms = mitsuba_scene(scene)
    dr = _drjit()
    if threads is not None:
        dr.set_thread_count(max(1, int(threads)))
    total_rows = len(ms.scene.receivers) * int(trials)
    if total_rows >= 1 << 32:
        raise WarpisError(f"R × M = {total_rows} trials: at most 2^32 - 1 in one call (32-bit row indices)")
    step = max(1, int(chunk_samples) // int(n))
    out = np.empty(total_rows)
    with llvm_variant(ms.mi):
        for c, first in enumerate(range(0, total_rows, step)):
            rows = min(step, total_rows - first)
            out[first:first + rows] = ms.chunk(int(n), int(trials), first, rows, _chunk_seed(seed, c), mode)
    return out.reshape(-1, int(trials))
