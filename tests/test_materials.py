"""Every material of the ``MATERIALS`` registry, checked *through an estimator* against a
value computed without warpis's integrand.

The reference is a float64 numpy Gauss–Legendre quadrature over the light's area of

    F(x) = ∫_light L · ρ(ω) · (n·ω) · cos θ_y / r² dA,

with ρ written here from its definition (docs/scene-files.md; docs/theory.md, "The
integrand at a receiver"), not taken from warpis:

* ``irradiance``: ρ = 1;
* ``lambert``:    ρ = albedo/π;
* ``phong``:      ρ = albedo·(e+2)/(2π)·max(0, cos α)^e, α the angle between ω and the
  mirror direction r = 2(n·v)n − v of the (unit) view v;
* ``roughconductor``, ``roughplastic``: Mitsuba 3's own ``bsdf.eval`` / cos θo (the
  mitsuba package of the test extra).

The scenes are a square light and free-standing receivers (no floor, nothing in between),
every receiver sees the whole light above its horizon and, for Phong, inside the lobe's
hemisphere (cos α > 0 on the whole light, asserted), so the integrand is smooth and the
quadrature converges to float64 precision (64 against 128 nodes per axis agree to 1e-10,
asserted).  warpis.analysis.reference is *not* used: it runs the same integrand, so it
could not tell a wrong ρ.

Each material's estimate is the mean of ``TRIALS`` trials of two unbiased estimators:
light-solid-angle sampling (jittered), which does not depend on ρ's normalisation at all,
and balance MIS of light-area with the material's own BSDF technique (whose pdf, for Phong,
is the *sampling* density (e+1)/(2π) cos^e α, distinct from the BRDF's (e+2)/(2π)).

Statistical threshold.  z = (mean − F)/se with se the standard error from the spread of
the trials (F is exact to ~1e-14, so it carries no error of its own).  The estimates of an
unoccluded light are bounded (light-solid-angle: f/g ≤ L·ρ_max·Ω; balance: f/ḡ ≤ 2·f/g_light),
so the mean of 2000 trials is normal to an excellent approximation.  All K comparisons of
the module are held at the two-sided Bonferroni threshold z* = Φ⁻¹(1 − α/(2K)) with
α = 1e-4: a correct implementation fails this module by chance with probability ≤ 1e-4.
The seeds are fixed, so every run draws the same numbers.

Power.  A Phong lobe normalised by (e+1)/(2π) instead of (e+2)/(2π) scales F by
(e+1)/(e+2), a relative shift δ = 1/(e+2) (3.1% at e = 30, the narrowest lobe here).  Every
Phong comparison asserts se ≤ δ·F/(z* + 3), so that shift lies ≥ z* + 3 standard errors
away and would be rejected with probability ≥ Φ(3) = 0.9987 whatever the seed (the test
also asserts that this alternative is rejected with the fixed seed); the other materials
assert se ≤ 0.4% of F.  The narrow lobe gets 8000 trials to reach that precision.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from scipy.stats import norm

import warpis
from warpis.kernels.engine import run_trials
from warpis.kernels.integrand import MATERIALS

LE = 3.0  # radiance of the light's front (downward) face
HEIGHT, HALF = 1.0, 0.5  # the light: the square |x|, |y| ≤ HALF at z = HEIGHT, facing −z
N, SEED = 64, 17
ALPHA = 1e-4  # false-failure probability of the whole module (Bonferroni)
MAX_REL_SE = 4e-3  # power, non-Phong materials: every estimate's se is at most this fraction of F


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


# Three receivers in free space below the light: centred and upright, off-centre, and
# raised and tilted.  View directions differ per receiver so that the Phong lobe axis is
# tilted by different amounts (but stays within 90° of every point of the light).
POSITIONS = np.array([[0.0, 0.0, 0.0], [0.7, -0.3, 0.0], [-0.4, 0.5, 0.2]])
NORMALS = np.array([_unit([0, 0, 1]), _unit([0, 0, 1]), _unit([0.3, -0.2, 1.0])])
VIEWS = np.array([_unit([0, 0, 1]), _unit([0.6, 0.1, 1.0]), _unit([-0.5, -0.3, 1.0])])


def _light():
    vertices = np.array([[-HALF, -HALF, HEIGHT], [-HALF, HALF, HEIGHT], [HALF, HALF, HEIGHT], [HALF, -HALF, HEIGHT]])
    return vertices, [[0, 1, 2], [0, 2, 3]]  # clockwise from above: the front faces down


# --------------------------------------------------------------------------- ρ, written here


def _rho_irradiance(params: dict, n: np.ndarray, w: np.ndarray) -> np.ndarray:
    return np.ones(w.shape[:-1])


def _rho_lambert(params: dict, n: np.ndarray, w: np.ndarray) -> np.ndarray:
    return np.full(w.shape[:-1], params["albedo"] / math.pi)


def _rho_phong(params: dict, n: np.ndarray, w: np.ndarray) -> np.ndarray:
    v = _unit(params["view"])
    axis = _unit(2.0 * np.dot(n, v) * n - v)  # mirror direction of the view about n
    cos_a = w @ axis
    assert np.all(cos_a > 0), "the light must lie inside the lobe's hemisphere (smooth integrand)"
    e = params["exponent"]
    return params["albedo"] * (e + 2.0) / (2.0 * math.pi) * cos_a**e


def _local_frame(n: np.ndarray) -> np.ndarray:
    """Rows t, b, n of an orthonormal frame about n (the microfacet materials are isotropic)."""
    t = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    t /= np.linalg.norm(t)
    return np.stack([t, np.cross(n, t), n])


def _rho_mitsuba(params: dict, n: np.ndarray, w: np.ndarray) -> np.ndarray:
    """ρ of a microfacet material from Mitsuba 3 itself: its ``bsdf.eval`` (which includes
    cos θo) over cos θo, one scalar call per direction (mitsuba is in the test extra)."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    spec = {k: v for k, v in params.items() if k not in ("view", "specular")}
    if params["type"] == "roughplastic":
        spec.pop("eta")
        spec["int_ior"], spec["ext_ior"] = params["eta"], 1.0
        spec["diffuse_reflectance"] = spec.pop("albedo")
    bsdf = mi.load_dict(spec)
    frame = _local_frame(n)
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(*(frame @ _unit(params["view"])))
    ctx = mi.BSDFContext()
    local = w.reshape(-1, 3) @ frame.T
    values = np.array([bsdf.eval(ctx, si, mi.Vector3f(*d))[0] / d[2] for d in local])
    return values.reshape(w.shape[:-1])


RHO: dict[str, Callable[[dict, np.ndarray, np.ndarray], np.ndarray]] = {
    "irradiance": _rho_irradiance, "lambert": _rho_lambert, "phong": _rho_phong,
    "roughconductor": _rho_mitsuba, "roughplastic": _rho_mitsuba}

# Material configurations: (material, its parameters, trials); Phong at a broad, a medium
# and a narrow lobe.  Phong's and the microfacet materials' view is per receiver (VIEWS).
CONFIGS = [("irradiance", {}, 2000), ("lambert", {"albedo": 0.6}, 2000),
           ("phong", {"albedo": 0.8, "exponent": 1.0}, 2000), ("phong", {"albedo": 0.8, "exponent": 6.0}, 2000),
           ("phong", {"albedo": 0.8, "exponent": 30.0}, 8000),
           ("roughconductor", {"alpha": 0.3, "eta": 1.5, "k": 2.0, "distribution": "ggx"}, 2000),
           ("roughconductor", {"alpha": 0.2, "eta": 0.2, "k": 3.0, "distribution": "beckmann",
                               "sample_visible": False}, 8000),
           ("roughplastic", {"alpha": 0.3, "eta": 1.5, "albedo": 0.5, "distribution": "ggx"}, 2000)]
MICROFACET = ("roughconductor", "roughplastic")


def _quadrature(p: np.ndarray, n: np.ndarray, rho, nodes: int) -> float:
    """F at p by nodes × nodes Gauss–Legendre over the light, float64."""
    x, w = np.polynomial.legendre.leggauss(nodes)
    s, ws = HALF * x, HALF * w
    gx, gy = np.meshgrid(s, s, indexing="ij")
    weights = np.outer(ws, ws)
    d = np.stack([gx, gy, np.full_like(gx, HEIGHT)], axis=-1) - p
    r2 = (d * d).sum(axis=-1)
    w_dir = d / np.sqrt(r2)[..., None]
    cos_x = w_dir @ n
    cos_y = w_dir[..., 2]  # the light's front normal is −z, and −ω · (−z) = ω_z
    assert np.all(cos_x > 0) and np.all(cos_y > 0), "the whole light must face the receiver above its horizon"
    return float((LE * rho(w_dir) * cos_x * cos_y / r2 * weights).sum())


def reference_values(material: str, params: dict) -> np.ndarray:
    """F at every receiver, converged: 64 and 128 nodes per axis agree to 1e-10 (1e-6 for
    Mitsuba's float32 microfacet ρ)."""
    out = []
    for r in range(len(POSITIONS)):
        p = dict(params, view=VIEWS[r], type=material)
        rho = lambda w, n=NORMALS[r], p=p: RHO[material](p, n, w)  # noqa: E731
        coarse, fine = (_quadrature(POSITIONS[r], NORMALS[r], rho, k) for k in (64, 128))
        # Mitsuba evaluates in float32: its ρ is smooth to ~1e-7, not to float64.
        assert abs(coarse - fine) <= (1e-6 if material in MICROFACET else 1e-10) * abs(fine), (material, r, coarse, fine)
        out.append(fine)
    return np.array(out)


def _scene(material: str, params: dict) -> warpis.Scene:
    vertices, triangles = _light()
    keys = dict(params)
    return warpis.Scene.from_arrays(vertices=vertices, triangles=triangles, emission=[LE, LE], positions=POSITIONS,
                                    normals=NORMALS, material=material, view=VIEWS, name=f"{material}-lamp", **keys)


def _estimators(material: str) -> list[str]:
    return ["jittered:single:light-solid-angle",
            f"independent:balance:light-area+{MATERIALS[material].bsdf_technique}"]


def test_every_registered_material_has_an_independent_rho_here():
    """The loop below covers the whole registry: a new material needs its ρ written in RHO
    (and a configuration in CONFIGS) before this module can vouch for it."""
    assert set(RHO) == set(MATERIALS), f"write ρ for {sorted(set(MATERIALS) - set(RHO))} in tests/test_materials.py"
    assert {m for m, _, _ in CONFIGS} == set(MATERIALS)


def test_quadrature_reference_reproduces_lamberts_formula():
    """The reference machinery itself, on irradiance at the centred receiver: a centred
    square of half-side a at height h gives E = L·4·s·atan(s), s = a/√(a²+h²)
    (docs/theory.md, Lambert's formula).  Deterministic."""
    s = HALF / math.hypot(HALF, HEIGHT)
    assert reference_values("irradiance", {})[0] == pytest.approx(LE * 4 * s * math.atan(s), rel=1e-12)


def test_every_material_through_an_estimator_matches_an_independent_quadrature():
    """For each material of the registry (Phong at e = 1, 6 and 30): the mean of two
    unbiased estimators at three receivers lies within z* of the numpy quadrature of
    L·ρ·cos over the light, with ρ written here from its definition; and, for Phong, it
    excludes the (e+1)/(2π)-normalised lobe.  False failure ≤ 1e-4 (module docstring)."""
    checks = []  # (material, params, estimator, receiver, mean, se, F)
    for material, params, trials in CONFIGS:
        ref = reference_values(material, params)
        scene = _scene(material, params)
        for spec in _estimators(material):
            x = run_trials(scene, spec, N, trials, seed=SEED)
            mean, se = x.mean(axis=1), x.std(axis=1, ddof=1) / math.sqrt(trials)
            checks += [(material, params, spec, r, mean[r], se[r], ref[r]) for r in range(len(ref))]
    k = len(checks)
    z_star = float(norm.ppf(1 - ALPHA / (2 * k)))
    assert k == sum(len(_estimators(m)) for m, _, _ in CONFIGS) * len(POSITIONS)
    failures, weak = [], []
    for material, params, spec, r, mean, se, ref in checks:
        label = f"{material} {params} {spec} receiver {r}: mean {mean:.7g} ± {se:.2g}, quadrature {ref:.7g}"
        shift = 1 / (params["exponent"] + 2) if material == "phong" else None
        if not 0 < se <= (shift / (z_star + 3) if shift else MAX_REL_SE) * ref:
            weak.append(label)
        if abs(mean - ref) > z_star * se:
            failures.append(f"{label} (z = {(mean - ref) / se:.2f}, z* = {z_star:.2f})")
        if material == "phong":  # the alternative normalisation must be rejected as well
            wrong = ref * (1 - shift)  # = F·(e+1)/(e+2)
            if abs(mean - wrong) <= z_star * se:
                failures.append(f"{label}: also consistent with the (e+1)/(2π) lobe {wrong:.7g}")
    assert not weak, "too noisy to tell a 3% normalisation error:\n" + "\n".join(weak)
    assert not failures, "\n".join(failures)
