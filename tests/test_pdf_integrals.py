"""Every technique's direction pdf integrates to its valid fraction, by deterministic quadrature.

``direction_pdf`` of every technique in ``TECHNIQUES`` (the loop is over the registry) is
integrated over the whole sphere at receivers with tilted normals and tilted views
(Phong exponents 0, 10 and 2000), in a scene of tilted lights of different sizes and
radiances, one of them behind another.  The integral must equal the fraction of primary
samples for which the technique produces a direction (pdf > 0): every technique here
produces one for every u, so the fraction is 1 — except light-solid-angle at a receiver
that no emitter faces, which produces none (fraction 0, and its pdf is 0 everywhere).
A light technique's pdf is, by its definition in ``techniques.py``, the density of the
directions it produces, summed over every emitter crossing of the ray; the directions
always go to a point of an emitter (light-area, light-power) or into the spherical
triangle of a front-facing one (light-solid-angle), so the pdf carries all of the mass.

*Quadrature, where the pdf lives.*

- Hemisphere and lobe techniques: about the technique's axis (the normal for uniform and
  cosine, the lobe axis for phong; ``SPHERE_AXES`` must name one for each such technique),
  composite Gauss–Legendre in h = 1 − cos θ on panels [0, 1e-6, 1e-5, …, 0.1, 0.5, 1, 1.5,
  2] (48 nodes each) times the periodic trapezoid rule in φ (96 points).  The panels crowd
  towards the axis, where cos^2000 α lives (its mass sits at h ~ 5e-4), and a panel edge
  sits on the horizon h = 1 where these pdfs jump or kink; on each panel the pdf is
  smooth, so the rule is exact to rounding.
- Light techniques: over the emitters' area instead of over directions.  Each emitter
  triangle is cut into convex pieces by the central projection (from the receiver) of
  the other emitter triangles onto its plane, so that on each piece the number c of
  emitter triangles a ray crosses is constant and the pdf is smooth; then
  ∫ p dω = Σ_pieces ∫ p(ω(y)) / c · |n·ω| / t² dA (a direction through two lights is met
  on two pieces, each counting half), ω(y) the direction from the receiver to y, by
  Gauss–Legendre 24 × 24 on the square, Duffy-mapped to the triangles of each piece.
  The pdf must be 0 away from the emitters (checked on the sphere rule's directions).

``test_quadrature_rules_are_exact_for_numpy_pdfs`` runs the same rules on float64 numpy
pdfs: they come out 1 to 1e-10 (measured 1e-15), so what the kernels' integrals lose is
float32 rounding: measured ≤ 1.3e-7 for every technique and receiver, except Phong at
e = 2000 (≤ 1.5e-4, see ``LOBE_AXIS_ULPS``).  Tolerance 1e-4 (Phong: 1e-4 + e·1.2e-7):
a pdf scaled by 1.01 is off by 1e-2; Phong normalised by (e+2) instead of (e+1) by 1.0
at e = 0, 9e-2 at e = 10 and 5e-4 at e = 2000.  Deterministic: no statistical threshold.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import concat_meshes, sky_environment
from test_light_pdf import numpy_light_pdfs

from warpis import Scene
from warpis.kernels.integrand import MATERIALS
from warpis.kernels.techniques import TECHNIQUES, direction_pdf, sample_directions
from warpis.testing import orthonormal_frame

TOL = 1e-4
# The kernel normalises the lobe axis in float32: its length is 1 ± δ, δ ≤ 2 ulps of 1
# (1.2e-7), and cos^e α then carries (1 ± δ)^e ≈ 1 ± e·δ into the whole lobe (measured:
# 1.5e-4 at e = 2000 for one of the receivers below).  So Phong's integral is held to
# TOL + e·LOBE_AXIS_ULPS: 3.4e-4 at e = 2000, still below the 5e-4 of (e+2)/(e+1).
LOBE_AXIS_ULPS = 1.2e-7
H_EDGES = (0.0, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 0.1, 0.5, 1.0, 1.5, 2.0)
SPHERE_AXES = {"uniform": "normal", "cosine": "normal", "phong": "lobe"}
EXPONENTS = (0.0, 10.0, 2000.0, 2000.0, 10.0)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _rect(center, half_u: float, half_v: float, normal):
    """A rectangle about ``center`` whose front face points along ``normal``."""
    n = _unit(normal)
    u = _unit(np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0]))
    v = np.cross(n, u)
    c = np.asarray(center, dtype=float)
    verts = np.array([c - half_u * u - half_v * v, c + half_u * u - half_v * v, c + half_u * u + half_v * v,
                      c - half_u * u + half_v * v])
    return verts, np.array([[0, 1, 2], [0, 2, 3]])


def _scene() -> Scene:
    meshes = [
        (*_rect((0.4, -0.2, 1.8), 0.5, 0.3, (-0.3, 0.4, -1.0)), 5.0),  # tilted quad
        (*_rect((-0.7, 0.5, 1.1), 0.05, 0.03, (0.6, -0.3, -0.7)), 800.0),  # small and bright, tilted 45°
        (*_rect((0.0, 0.0, 3.0), 1.2, 1.0, (0.2, -0.3, -1.0)), 1.0),  # large, behind the first
        (np.array([[-0.6, -1.5, 0.2], [0.8, -1.5, 0.4], [0.1, -1.5, 1.3]]), np.array([[0, 2, 1]]), 30.0),  # a wall
        (*_rect((0.1, 0.1, 0.9), 0.25, 0.25, (0.0, 0.0, 1.0)), 0.0),  # an occluder: not an emitter
    ]
    vertices, triangles, emission = concat_meshes(meshes)
    positions = np.array([[0.0, 0.0, 0.0], [0.5, -0.4, 0.1], [-0.4, 0.6, 0.3], [0.2, 0.3, 0.05], [0.0, -2.5, 5.0]])
    normals = _unit([[-0.4, -0.3, 0.87], [0.3, 0.5, 0.81], [0.1, -0.6, 0.8], [0.6, 0.3, 0.74], [0.1, 0.2, 0.97]])
    views = _unit([[-0.5, 0.3, 0.8], [0.2, 0.6, 0.77], [0.7, -0.1, 0.7], [-0.2, -0.7, 0.68], [0.1, 0.2, 0.97]])
    return Scene.from_arrays(vertices, triangles, emission, positions, normals,
                             material=MATERIALS["phong"].code, exponent=np.array(EXPONENTS), view=views,
                             name="pdf-integrals", environment=sky_environment())


@pytest.fixture(scope="module")
def scene() -> Scene:
    return _scene()


# --------------------------------------------------------------------------- rules


def sphere_rule(axis, n_gl: int = 48, n_phi: int = 96) -> tuple[np.ndarray, np.ndarray]:
    """Directions and weights for ∫ over the whole sphere, crowded about ``axis``."""
    b1, b2, a = orthonormal_frame(axis)
    x, wx = np.polynomial.legendre.leggauss(n_gl)
    h, wh = [], []
    for lo, hi in zip(H_EDGES[:-1], H_EDGES[1:]):
        h.append(lo + 0.5 * (hi - lo) * (x + 1.0))
        wh.append(0.5 * (hi - lo) * wx)
    h, wh = np.concatenate(h), np.concatenate(wh)
    phi = (np.arange(n_phi) + 0.5) * (2.0 * math.pi / n_phi)
    hh, pp = np.meshgrid(h, phi, indexing="ij")
    cos_t = 1.0 - hh
    sin_t = np.sqrt(hh * (2.0 - hh))
    d = (sin_t * np.cos(pp))[..., None] * b1 + (sin_t * np.sin(pp))[..., None] * b2 + cos_t[..., None] * a
    w = np.repeat(wh[:, None], n_phi, axis=1) * (2.0 * math.pi / n_phi)
    return d.reshape(-1, 3), w.ravel()


def _crossing_count(p: np.ndarray, w: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """How many of the triangles (E, 3, 3) each ray (p, w[i]) crosses (float64)."""
    a = tris[None, :, 0]
    e1 = tris[None, :, 1] - a
    e2 = tris[None, :, 2] - a
    wk = w[:, None, :]
    pv = np.cross(wk, e2)
    inv = 1.0 / np.sum(e1 * pv, axis=-1)
    tv = p - a
    bu = np.sum(tv * pv, axis=-1) * inv
    qv = np.cross(tv, e1)
    bv = np.sum(wk * qv, axis=-1) * inv
    t = np.sum(e2 * qv, axis=-1) * inv
    return np.sum((bu > 0.0) & (bv > 0.0) & (bu + bv < 1.0) & (t > 0.0), axis=1)


def _clip(poly: np.ndarray, a: np.ndarray, b: np.ndarray, keep_left: bool) -> np.ndarray:
    """The part of convex polygon ``poly`` (m, 2) left (or right) of the line a → b."""
    if len(poly) == 0:
        return poly
    side = (b[0] - a[0]) * (poly[:, 1] - a[1]) - (b[1] - a[1]) * (poly[:, 0] - a[0])
    return _keep_nonnegative(poly, side if keep_left else -side)


def _keep_nonnegative(poly: np.ndarray, side: np.ndarray) -> np.ndarray:
    """The part of convex polygon ``poly`` (m, d) where the affine function with vertex
    values ``side`` is ≥ 0 (Sutherland–Hodgman against one edge)."""
    out = []
    for i in range(len(poly)):
        j = (i + 1) % len(poly)
        if side[i] >= 0.0:
            out.append(poly[i])
        if (side[i] >= 0.0) != (side[j] >= 0.0):
            out.append(poly[i] + side[i] / (side[i] - side[j]) * (poly[j] - poly[i]))
    return np.array(out).reshape(-1, poly.shape[1])


def _signed_area2(poly: np.ndarray) -> float:
    """Signed area of a 2D polygon (positive when counter-clockwise)."""
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _area2(poly: np.ndarray) -> float:
    return abs(_signed_area2(poly))


def _clip_3d(poly: np.ndarray, p: np.ndarray, n: np.ndarray, margin: float) -> np.ndarray:
    """The part of convex polygon ``poly`` (m, 3) where (y − p)·n ≥ margin."""
    return _keep_nonnegative(poly, (poly - p) @ n - margin)


def emitter_pieces(scene: Scene, r: int) -> list[tuple[np.ndarray, int]]:
    """The emitter triangles cut into convex pieces (3D polygons) on each of which the
    number c of emitter triangles that the rays from receiver r cross is constant: each
    triangle j is clipped by the central projection (from the receiver) of every other
    emitter triangle onto j's plane.  Returns (polygon (m, 3), c) pairs."""
    p = scene.receivers.positions[r]
    tris = scene.triangle_vertices(scene.emitters).astype(np.float64)
    pieces = []
    for j, (a, b, c) in enumerate(tris):
        n = _unit(np.cross(b - a, c - a))
        e1 = _unit(b - a)
        e2 = np.cross(n, e1)

        def flat(y, a=a, e1=e1, e2=e2):
            return np.stack([(y - a) @ e1, (y - a) @ e2], axis=-1)

        size = _area2(flat(np.array([a, b, c])))
        polys = [(flat(np.array([a, b, c])), 1)]
        for k, other in enumerate(tris):
            if k == j:
                continue
            # The part of the other triangle on the same side of the receiver as j's plane
            # (rays from the receiver meet nothing else of it), centrally projected onto it.
            height = (a - p) @ n
            part = _clip_3d(other, p, n * np.sign(height), 1e-9 * abs(height))
            if len(part) < 3:
                continue
            q = flat(p + (height / ((part - p) @ n))[:, None] * (part - p))
            if _signed_area2(q) < 0.0:
                q = q[::-1]  # counter-clockwise: inside is left of every edge
            cut = []
            for poly, count in polys:
                rest = poly
                for i in range(len(q)):
                    outside = _clip(rest, q[i], q[(i + 1) % len(q)], keep_left=False)
                    if _area2(outside) > 1e-12 * size:
                        cut.append((outside, count))
                    rest = _clip(rest, q[i], q[(i + 1) % len(q)], keep_left=True)
                if _area2(rest) > 1e-12 * size:
                    cut.append((rest, count + 1))
            polys = cut
        pieces += [(a + poly[:, :1] * e1 + poly[:, 1:] * e2, count) for poly, count in polys]
    return pieces


def area_rule(scene: Scene, r: int, n_gl: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """Directions from receiver r and weights for ∫ p dω over the directions of the
    emitters: Σ over the convex pieces of the emitter triangles (``emitter_pieces``) of
    ∫ · / c · |n·ω| / t² dA, by Gauss–Legendre on the square, Duffy-mapped to each
    triangle of the piece's fan."""
    p = scene.receivers.positions[r]
    x, wx = np.polynomial.legendre.leggauss(n_gl)
    s = 0.5 * (x + 1.0)
    ws = 0.5 * wx
    ss, vv = (g.ravel() for g in np.meshgrid(s, s, indexing="ij"))
    wsv = np.outer(ws, ws).ravel()
    dirs, weights = [], []
    for poly, count in emitter_pieces(scene, r):
        for i in range(1, len(poly) - 1):
            a, b, c = poly[0], poly[i], poly[i + 1]
            normal = np.cross(b - a, c - a)
            double_area = np.linalg.norm(normal)
            if double_area <= 1e-14 * np.linalg.norm(b - a) * np.linalg.norm(c - a):
                continue  # a sliver that clipping leaves at a vertex: no area
            y = (1.0 - ss)[:, None] * a + (ss * (1.0 - vv))[:, None] * b + (ss * vv)[:, None] * c
            d = y - p
            t = np.linalg.norm(d, axis=1)
            w = d / t[:, None]
            cos_y = np.abs(w @ normal) / double_area
            dirs.append(w)
            # dA = 2A·s ds dv on the triangle, dω = |cos θ_y| dA / t².
            weights.append(wsv * ss * double_area * cos_y / (t * t) / count)
    return np.vstack(dirs), np.concatenate(weights)


def _lobe_axis(scene: Scene, r: int) -> np.ndarray:
    n, v = scene.receivers.normals[r], scene.receivers.view[r]
    return _unit(2.0 * np.dot(n, v) * n - v)


def _own(scene: Scene, r: int, technique: str) -> str:
    """``bsdf`` is the receiver material's own sampling (these receivers have no microfacet
    material): the technique it is at receiver r."""
    return scene.receivers.material_of(r).bsdf_technique if technique == "bsdf" else technique


def _axis(scene: Scene, r: int, technique: str) -> np.ndarray:
    technique = _own(scene, r, technique)
    which = SPHERE_AXES.get(technique)
    assert which is not None, (f"technique {technique!r}: add the axis its pdf is concentrated about to "
                               f"SPHERE_AXES in tests/test_pdf_integrals.py")
    return _lobe_axis(scene, r) if which == "lobe" else scene.receivers.normals[r]


def _valid_fraction(scene: Scene, r: int, technique: str) -> float:
    """Fraction of 64 × 64 grid points u for which the technique produces a direction;
    here always 0 or 1 (anything else would need a quadrature of the invalid set)."""
    g = (np.arange(64) + 0.5) / 64.0
    u = np.stack([a.ravel() for a in np.meshgrid(g, g, indexing="ij")], axis=1)
    _, pdf = sample_directions(scene, r, technique, u)
    fraction = float(np.mean(pdf > 0.0))
    assert fraction in (0.0, 1.0), f"{technique} at receiver {r}: valid fraction {fraction}"
    return fraction


def environment_rule(scene: Scene, n_gl: int = 4, n_phi: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Directions and weights for ∫ over the whole sphere, cell by cell of the scene's
    environment (Gauss–Legendre in cos θ × midpoints in φ, in its frame): the envmap pdf
    is constant on each cell, so the rule is exact to rounding."""
    env = scene.environment
    height, width = env.texels.shape
    x, wx = np.polynomial.legendre.leggauss(n_gl)
    dirs, weights = [], []
    for j in range(height - 1):
        c0, c1 = math.cos(math.pi * j / (height - 1)), math.cos(math.pi * (j + 1) / (height - 1))
        cos_t = 0.5 * (c0 + c1) + 0.5 * (c0 - c1) * x
        for i in range(width):
            phi = 2 * math.pi * ((i + (np.arange(n_phi) + 0.5) / n_phi) / width + 0.5 / width)
            ct, ph = np.meshgrid(cos_t, phi, indexing="ij")
            st = np.sqrt(1 - ct * ct)
            local = np.stack([np.sin(ph) * st, ct, -np.cos(ph) * st], axis=-1).reshape(-1, 3)
            dirs.append(local @ env.rotation.T)
            weights.append(np.repeat(0.5 * (c0 - c1) * wx, n_phi) * (2 * math.pi / width / n_phi))
    return np.vstack(dirs), np.concatenate(weights)


def integrate(scene: Scene, r: int, technique: str) -> float:
    """∫ direction_pdf over the sphere by the rule that suits the technique."""
    if TECHNIQUES[technique].environment:
        dirs, weights = environment_rule(scene)
    elif TECHNIQUES[technique].light:
        dirs, weights = area_rule(scene, r)
    else:
        dirs, weights = sphere_rule(_axis(scene, r, technique))
    return float(np.sum(weights * direction_pdf(scene, r, technique, dirs)))


# --------------------------------------------------------------------------- tests


def test_scene_has_tilted_receivers_and_the_exponents(scene):
    """Receivers with exponents 0, 10, 2000; no receiver normal parallel to a light's
    (|n_r·n_k| < 0.97), lobe axes away from the normals, and light-solid-angle has
    nothing to pick at receiver 4 while it sees the backs of all lights."""
    assert {0.0, 10.0, 2000.0} <= set(scene.receivers.exponent.tolist())
    tris = scene.triangle_vertices(scene.emitters)
    normal = _unit(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]))
    assert np.max(np.abs(scene.receivers.normals @ normal.T)) < 0.97
    for r in range(len(scene.receivers)):
        if r != 4:
            assert np.dot(_lobe_axis(scene, r), scene.receivers.normals[r]) < 0.99
    facing = np.einsum("kj,rkj->rk", normal, scene.receivers.positions[:, None, :] - tris[None, :, 0]) > 0.0
    assert not facing[4].any() and facing[:4].any(axis=1).all()
    # Some directions cross two lights (the quadrature must not count them twice).
    dirs, _ = area_rule(scene, 0)
    assert np.any(_crossing_count(scene.receivers.positions[0], dirs, tris.astype(np.float64)) == 2)


def test_quadrature_rules_are_exact_for_numpy_pdfs(scene):
    """The rules integrate float64 numpy pdfs to 1 within 1e-10: uniform, cosine and
    Phong (e = 0, 10, 2000) about tilted axes, and every light pdf at every receiver
    (numpy twins from test_light_pdf).  So the kernels' integrals below err only by
    float32 rounding, and a pdf scaled by 1.01 is off by 1e-2 ≫ TOL."""
    for r in range(len(scene.receivers)):
        n = scene.receivers.normals[r]
        d, w = sphere_rule(n)
        assert abs(np.sum(w * np.where(d @ n > 0.0, 1.0 / (2.0 * math.pi), 0.0)) - 1.0) < 1e-10
        assert abs(np.sum(w * np.maximum(d @ n, 0.0) / math.pi) - 1.0) < 1e-10
        for e in (0.0, 10.0, 2000.0):
            axis = _lobe_axis(scene, r)
            d, w = sphere_rule(axis)
            c = np.maximum(d @ axis, 0.0)
            lobe = np.where(c > 0.0, (e + 1.0) / (2.0 * math.pi) * c**e, 0.0)
            assert abs(np.sum(w * lobe) - 1.0) < 1e-10, e
            assert abs(np.sum(w * lobe * (e + 2.0) / (e + 1.0)) - 1.0) > 4.9e-4  # (e+2) instead of (e+1)
        d, w = area_rule(scene, r)
        pdfs, _ = numpy_light_pdfs(scene, r, d)
        for technique, pdf in pdfs.items():
            expected = 0.0 if (r == 4 and technique == "light-solid-angle") else 1.0
            assert abs(np.sum(w * pdf) - expected) < 1e-10, (r, technique)
            if expected:
                assert abs(np.sum(w * 1.01 * pdf) - expected) > 9.9e-3


@pytest.mark.parametrize("r", range(len(EXPONENTS)))
@pytest.mark.parametrize("technique", list(TECHNIQUES))
def test_direction_pdf_integrates_to_valid_fraction(scene, technique, r):
    """At each of the five receivers (Phong exponents 0, 10, 2000, 2000, 10), ∫
    direction_pdf dω over the sphere equals the technique's valid fraction (1, or 0 for
    light-solid-angle at receiver 4) to 1e-4 (plus e·1.2e-7 for a lobe about the float32
    lobe axis, see LOBE_AXIS_ULPS)."""
    fraction = _valid_fraction(scene, r, technique)
    integral = integrate(scene, r, technique)
    tol = TOL
    if SPHERE_AXES.get(_own(scene, r, technique)) == "lobe":
        tol += float(scene.receivers.exponent[r]) * LOBE_AXIS_ULPS
    assert abs(integral - fraction) < tol, (
        f"{technique} at receiver {r} (exponent {scene.receivers.exponent[r]:g}): ∫ pdf dω = {integral:.8f}, "
        f"valid fraction {fraction}")


@pytest.mark.parametrize("technique", [t for t, e in TECHNIQUES.items() if e.light])
def test_light_pdf_vanishes_away_from_the_emitters(scene, technique):
    """The area rule sees only the emitters' directions: on the sphere rule's directions
    (about the normal) whose rays cross no emitter, the light pdf is exactly 0."""
    tris = scene.triangle_vertices(scene.emitters).astype(np.float64)
    for r in range(len(scene.receivers)):
        d, _ = sphere_rule(scene.receivers.normals[r], n_gl=16, n_phi=64)
        d = _unit(d.astype(np.float32).astype(np.float64))
        pdf = direction_pdf(scene, r, technique, d)
        _, edge = numpy_light_pdfs(scene, r, d)
        away = (_crossing_count(scene.receivers.positions[r], d, tris) == 0) & ~edge
        assert away.sum() > 0.3 * len(d)
        assert np.all(pdf[away] == 0.0), f"receiver {r}: pdf > 0 in {np.count_nonzero(pdf[away])} empty directions"
