"""Light pdfs against an independent float64 numpy computation, away from the parallel case.

Every light technique's solid-angle density at a direction ω is a sum over the emitter
triangles k that the ray (x, ω) crosses (at distance t_k, light normal n_k):

    p(ω) = Σ_k P(pick k) · t_k² / (A_k · |n_k·ω|)

with P(pick k) = A_k/A (``light-area``), L_k A_k / Σ L A (``light-power``), and for
``light-solid-angle`` P(pick k) = Ω_k L_k / Σ_j Ω_j L_j over the triangles whose front
faces x, then a direction uniform in the spherical triangle: density P(pick k)/Ω_k,
counted only where the ray meets k's front face.  Ω_k is computed here by Van Oosterom–
Strackee, crossings by float64 Möller–Trumbore: nothing is taken from warpis but the
scene's arrays.

The scene is built so that the shortcuts that agree in the usual flat setup do not here:
receivers whose normals are tilted away from every light's normal (so |n_receiver·ω| is
not |n_k·ω|), lights tilted in different directions at different distances (so t² ≠ 1
and varies), four lights of different radiance and area, one of them behind another (two
crossings on one ray), one seen from behind by one receiver, and a non-emitting occluder
that a pdf must ignore.  Directions: those each technique samples (the pdf it reports,
and ``direction_pdf`` at the sampled direction), directions to uniform random points on
the emitters, and uniform random directions (most of which miss: pdf exactly 0).

Tolerance: 1e-4 relative.  The kernels work in float32 (directions, t, cosines), whose
rounding moves these pdfs by ~1e-6 relative here; a pdf with the receiver's cosine
instead of the light's, or without t², is off by 10–200 %.  Directions within 1e-6
(barycentric) of an emitter edge, where float32 and float64 may disagree on which
triangles the ray crosses, are left out (a handful; their number is bounded).  Fixed
seeds, no statistical threshold: the tests are deterministic.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from warpis import Scene
from warpis.kernels.techniques import TECHNIQUES, direction_pdf, sample_directions

LIGHTS = tuple(t for t, e in TECHNIQUES.items() if e.light)
RTOL = 1e-4
EDGE = 1e-6  # barycentric margin under which a crossing is ambiguous in float32


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _rect(center, half_u: float, half_v: float, normal, spin: float = 0.0):
    """A rectangle about ``center`` whose front face points along ``normal``:
    (vertices (4, 3), faces (2, 3))."""
    n = _unit(normal)
    a = _unit(np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0]))
    b = np.cross(n, a)
    u = math.cos(spin) * a + math.sin(spin) * b
    v = np.cross(n, u)
    c = np.asarray(center, dtype=float)
    verts = np.array([c - half_u * u - half_v * v, c + half_u * u - half_v * v, c + half_u * u + half_v * v,
                      c - half_u * u + half_v * v])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    assert np.dot(np.cross(verts[1] - verts[0], verts[2] - verts[0]), n) > 0.0
    return verts, faces


def _tilted_scene() -> Scene:
    meshes = [
        # (vertices, faces, radiance)
        (*_rect((0.2, 0.1, 2.0), 0.6, 0.35, (0.3, -0.5, -1.0), spin=0.4), 4.0),  # A: tilted 32°
        (*_rect((-0.9, 0.3, 1.3), 0.06, 0.04, (0.8, -0.2, -0.6)), 300.0),  # B: small, tilted 53°
        (np.array([[1.4, -0.8, 0.2], [1.4, -0.2, 1.2], [1.4, 0.4, 0.3]]), np.array([[0, 1, 2]]), 20.0),  # C: a wall
        (*_rect((0.1, -0.1, 3.2), 1.5, 1.2, (0.35, 0.25, -1.0), spin=-0.3), 1.0),  # D: large, behind A
        (*_rect((0.0, 0.2, 1.0), 0.3, 0.3, (0.0, 0.0, 1.0)), 0.0),  # a non-emitting occluder
    ]
    verts, faces, emission, owner = [], [], [], []
    offset = 0
    for i, (v, f, radiance) in enumerate(meshes):
        verts.append(v)
        faces.append(f + offset)
        emission += [radiance] * len(f)
        owner += [i] * len(f)
        offset += len(v)
    positions = [[0.0, 0.0, 0.0], [0.5, -0.4, 0.1], [-0.4, 0.6, 0.3], [1.0, -0.3, 0.5], [-0.3, 0.2, 2.6]]
    normals = _unit([[0.3, -0.2, 0.93], [-0.5, 0.2, 0.84], [0.1, -0.6, 0.8], [0.2, 0.6, 0.77], [0.2, 0.1, 0.97]])
    return Scene.from_arrays(np.vstack(verts), np.vstack(faces), np.array(emission), np.array(positions), normals,
                             triangle_mesh=np.array(owner), mesh_names=["A", "B", "C", "D", "occluder"],
                             name="tilted-lights")


@pytest.fixture(scope="module")
def scene() -> Scene:
    return _tilted_scene()


# --------------------------------------------------------------------------- numpy


def triangle_solid_angles(p: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Solid angle of each triangle (E, 3, 3) seen from p (Van Oosterom–Strackee), float64."""
    a, b, c = (tris[:, i] - p for i in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    num = np.abs(np.einsum("ij,ij->i", a, np.cross(b, c)))
    den = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", a, c) * lb
           + np.einsum("ij,ij->i", b, c) * la)
    return 2.0 * np.arctan2(num, den)


def ray_crossings(p: np.ndarray, w: np.ndarray, tris: np.ndarray):
    """Rays (p, w[i]) against triangles (E, 3, 3), float64 Möller–Trumbore: (K, E) arrays
    of the distance t, whether the ray crosses, and the smallest barycentric margin."""
    a = tris[None, :, 0]
    e1 = tris[None, :, 1] - a
    e2 = tris[None, :, 2] - a
    wk = w[:, None, :]
    pv = np.cross(wk, e2)
    det = np.sum(e1 * pv, axis=-1)
    inv = 1.0 / np.where(det == 0.0, np.inf, det)
    tv = p - a
    bu = np.sum(tv * pv, axis=-1) * inv
    qv = np.cross(tv, e1)
    bv = np.sum(wk * qv, axis=-1) * inv
    t = np.sum(e2 * qv, axis=-1) * inv
    margin = np.minimum(np.minimum(bu, bv), 1.0 - bu - bv)
    return t, (margin >= 0.0) & (t > 0.0), margin


def numpy_light_pdfs(scene: Scene, r: int, w: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Each light technique's pdf at unit directions w (K, 3) from receiver r, float64,
    and a mask of the directions that pass within EDGE of an emitter edge."""
    p = np.asarray(scene.receivers.positions[r], dtype=np.float64)
    w = _unit(np.asarray(w, dtype=np.float64))
    tris = scene.triangle_vertices(scene.emitters).astype(np.float64)
    normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    area = 0.5 * np.linalg.norm(normal, axis=1)
    n_hat = normal / (2.0 * area[:, None])
    radiance = scene.emission[scene.emitters].astype(np.float64)
    t, hit, margin = ray_crossings(p, w, tris)
    edge = np.any((np.abs(margin) < EDGE) & (t > 0.0), axis=1)
    cos_light = np.abs(w @ n_hat.T)  # |n_k·ω|: the LIGHT's cosine
    # Area density on triangle k is 1/A_k; in solid angle t²/(A_k |n_k·ω|).
    per_area = np.where(hit, t * t / (area[None, :] * np.where(hit, cos_light, 1.0)), 0.0)
    facing = np.einsum("ij,ij->i", normal, p - tris[:, 0]) > 0.0
    front = (w @ normal.T) < 0.0
    omega = triangle_solid_angles(p, tris)
    pick_sa = np.where(facing, omega * radiance, 0.0)
    pdfs = {
        "light-area": per_area @ (area / area.sum()),
        "light-power": per_area @ (radiance * area / np.sum(radiance * area)),
        "light-solid-angle": (np.where(hit & front, 1.0, 0.0) @ (pick_sa / omega / pick_sa.sum())
                              if pick_sa.sum() > 0.0 else np.zeros(len(w))),
    }
    return pdfs, edge


def _compare(scene, r, technique, w, got, where) -> None:
    pdfs, edge = numpy_light_pdfs(scene, r, w)
    assert technique in pdfs, f"no numpy pdf for light technique {technique!r} in numpy_light_pdfs"
    want = pdfs[technique]
    assert np.count_nonzero(edge) <= max(2, len(w) // 1000), f"{np.count_nonzero(edge)} directions on edges"
    ok = ~edge
    err = np.abs(got[ok] - want[ok])
    bad = err > RTOL * np.maximum(np.abs(want[ok]), np.abs(got[ok]))
    if np.any(bad):
        i = int(np.flatnonzero(bad)[np.argmax(err[bad] / np.maximum(want[ok][bad], 1e-300))])
        raise AssertionError(f"{where}: {np.count_nonzero(bad)} of {np.count_nonzero(ok)} pdfs differ from numpy by "
                             f"more than {RTOL:g}; worst at ω = {w[ok][i]}: warpis {got[ok][i]!r}, "
                             f"numpy {want[ok][i]!r}")


# --------------------------------------------------------------------------- the geometry


def test_scene_is_tilted(scene):
    """No receiver normal is parallel to any light normal (|n_r·n_k| < 0.97), the lights'
    normals differ, receiver 4 sees lights A and B from behind, light D lies behind light
    A along some rays, and every receiver sees some light's front face."""
    tris = scene.triangle_vertices(scene.emitters)
    normal = _unit(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]))
    assert np.max(np.abs(scene.receivers.normals @ normal.T)) < 0.97
    assert len(np.unique(normal.round(6), axis=0)) == 4
    facing = np.einsum("kj,rkj->rk", normal, scene.receivers.positions[:, None, :] - tris[None, :, 0]) > 0.0
    assert facing.any(axis=1).all()
    owner = scene.triangle_mesh[scene.emitters]
    assert not facing[4, owner == 0].any() and not facing[4, owner == 1].any()
    # A ray from receiver 0 through light A's centre goes on to cross light D.
    centre_a = tris[owner == 0].reshape(-1, 3).mean(axis=0)
    _, hit, _ = ray_crossings(scene.receivers.positions[0], _unit(centre_a - scene.receivers.positions[0])[None], tris)
    assert set(owner[hit[0]]) == {0, 3}


# --------------------------------------------------------------------------- the tests


@pytest.mark.parametrize("technique", LIGHTS)
def test_light_pdf_of_sampled_directions_matches_numpy(scene, technique):
    """At every receiver, 4000 directions from the technique itself: the pdf it reports
    and ``direction_pdf`` at the direction both equal the numpy pdf to 1e-4."""
    for r in range(len(scene.receivers)):
        u = np.random.default_rng([r, 17]).random((4000, 2), dtype=np.float32)
        d, reported = sample_directions(scene, r, technique, u)
        valid = reported > 0.0
        w = d[valid].astype(np.float64)
        if technique != "light-solid-angle":
            assert np.all(valid), "light-area and light-power always produce a direction"
        elif not valid.any():
            continue
        _compare(scene, r, technique, w, reported[valid], f"receiver {r}, reported pdf")
        _compare(scene, r, technique, w, direction_pdf(scene, r, technique, w), f"receiver {r}, direction_pdf")


@pytest.mark.parametrize("technique", LIGHTS)
def test_light_pdf_towards_random_points_on_lights_matches_numpy(scene, technique):
    """Directions to 3000 uniform random points on the emitters (any light, any facing,
    some through two lights): ``direction_pdf`` equals the numpy pdf to 1e-4, and it is
    positive wherever the numpy pdf is."""
    tris = scene.triangle_vertices(scene.emitters)
    for r in range(len(scene.receivers)):
        rng = np.random.default_rng([r, 29])
        k = rng.integers(0, len(tris), 3000)
        s, v = rng.random((2, 3000))
        s = np.sqrt(s)
        y = ((1.0 - s)[:, None] * tris[k, 0] + (s * (1.0 - v))[:, None] * tris[k, 1]
             + (s * v)[:, None] * tris[k, 2])
        w = _unit(y - scene.receivers.positions[r]).astype(np.float32).astype(np.float64)
        w = _unit(w)
        got = direction_pdf(scene, r, technique, w)
        _compare(scene, r, technique, w, got, f"receiver {r}, towards the lights")


@pytest.mark.parametrize("technique", LIGHTS)
def test_light_pdf_is_zero_where_no_light_is(scene, technique):
    """20,000 uniform directions per receiver: where the numpy ray misses every emitter
    (by more than the edge margin) the pdf is exactly 0, and where it hits, it matches."""
    for r in range(len(scene.receivers)):
        w = _unit(np.random.default_rng([r, 31]).normal(size=(20_000, 3))).astype(np.float32).astype(np.float64)
        w = _unit(w)
        got = direction_pdf(scene, r, technique, w)
        pdfs, edge = numpy_light_pdfs(scene, r, w)
        miss = (pdfs["light-area"] == 0.0) & ~edge
        assert np.all(got[miss] == 0.0)
        assert np.count_nonzero(~miss) > 50  # some of them do hit a light
        _compare(scene, r, technique, w[~miss], got[~miss], f"receiver {r}, uniform directions")
