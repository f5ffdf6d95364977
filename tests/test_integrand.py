"""Edge cases of the integrand f(ω) = Le(ω) · ρ(ω) · max(0, n·ω) (``warpis.kernels.integrand``).

Geometry: rays through the shared edge of two emitter triangles, grazing and
below-horizon directions, lights seen from behind (one-sided emission) and receivers
that sit exactly on a surface (the shading point p = x + ε·n must not hit it).
Materials: lambert is albedo/π times irradiance, and the energy-normalised Phong lobe
reflects ∫ ρ(ω) cos θ dω = albedo · (n·r) of the energy when the lobe (axis r) lies above
the horizon; both checked by dense deterministic quadrature inside an emitting dome of
radiance 1.  Everything here is deterministic: no test can fail by chance.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
from conftest import toml_value

from warpis.kernels.integrand import evaluate_integrand
from warpis.kernels.techniques import sample_directions
from warpis.scenes import load_scene

# --------------------------------------------------------------------------- scene files


_toml = toml_value  # the shared TOML writer of conftest.py


def _write_scene(directory: Path, meshes: list[tuple], receivers, material: dict | None = None) -> Path:
    """Write OBJ files and a scene TOML; return the TOML's path.

    ``meshes``: (vertices (V, 3), faces (F, 3), emission) per mesh; ``receivers``: one
    ``[receivers]`` table or a list of ``[[receivers]]`` tables (dicts); the material
    defaults to irradiance.
    """
    directory.mkdir(parents=True, exist_ok=True)
    lines = ['name = "test"', ""]
    for i, (v, f, emission) in enumerate(meshes):
        obj = [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(v, float).tolist()]
        obj += ["f " + " ".join(str(j + 1) for j in face) for face in np.asarray(f, int).tolist()]
        (directory / f"mesh{i}.obj").write_text("\n".join(obj) + "\n")
        lines += ["[[mesh]]", f'path = "mesh{i}.obj"']
        if emission:
            lines.append(f"emission = {float(emission)!r}")
        lines.append("")
    groups = [receivers] if isinstance(receivers, dict) else receivers
    header = "[receivers]" if isinstance(receivers, dict) else "[[receivers]]"
    for g in groups:
        lines += [header] + [f"{k} = {_toml(v)}" for k, v in g.items()] + [""]
    if material is None and isinstance(receivers, dict) and "material" not in receivers:
        material = {"type": "irradiance"}
    if material is not None:
        lines += ["[material]"] + [f"{k} = {_toml(v)}" for k, v in material.items()] + [""]
    path = directory / "scene.toml"
    path.write_text("\n".join(lines))
    return path


def _quad(corners) -> tuple[np.ndarray, np.ndarray]:
    """A quad (4 corners in order) as two triangles (0, 1, 2), (0, 2, 3): diagonal 0–2.

    The front face is the side (c1 − c0) × (c2 − c0) points to.
    """
    return np.asarray(corners, dtype=float), np.array([[0, 1, 2], [0, 2, 3]])


# A 1 × 0.5 ceiling light at z = 2 facing down, radiance 5; its diagonal runs from
# (−0.5, −0.25) to (0.5, 0.25).
CEILING = _quad([[-0.5, -0.25, 2.0], [-0.5, 0.25, 2.0], [0.5, 0.25, 2.0], [0.5, -0.25, 2.0]])
CEILING_L = 5.0
# A 4 × 4 floor at z = 0 facing up, split along the diagonal through the origin.
FLOOR = _quad([[-2.0, -2.0, 0.0], [2.0, -2.0, 0.0], [2.0, 2.0, 0.0], [-2.0, 2.0, 0.0]])


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _shading_point(scene, r: int) -> np.ndarray:
    rx = scene.receivers
    return rx.positions[r]  # directions are from the receiver itself (integrand.py)


# --------------------------------------------------------------------------- geometry


def test_ray_through_shared_edge_counts_once(tmp_path):
    """A ray through the shared diagonal (or the shared corner) of the two triangles of a
    quad light sees one radiance: f = L cos θ, neither 0 (a crack) nor 2 L cos θ."""
    scene = load_scene(_write_scene(tmp_path, [(*CEILING, CEILING_L)],
                                    {"points": [[0.0, 0.0, 0.0], [0.7, -0.4, 0.0]], "normal": [0.0, 0.0, 1.0]}))
    t = np.linspace(-0.95, 0.95, 39)
    on_diagonal = np.stack([0.5 * t, 0.25 * t, np.full_like(t, 2.0)], axis=1)
    corners = CEILING[0][[0, 2]] * np.array([0.999999, 0.999999, 1.0])  # the diagonal's ends, just inside
    targets = np.vstack([on_diagonal, corners])
    for r in range(2):
        dirs = _unit(targets - _shading_point(scene, r))
        f = evaluate_integrand(scene, r, dirs)
        np.testing.assert_allclose(f, CEILING_L * dirs[:, 2], rtol=1e-5)


def test_grazing_and_below_horizon_directions(tmp_path):
    """A vertical light straddling the receiver's horizon: f stays finite and ≥ 0 as
    n·ω → 0+, equals L n·ω above the horizon, and is exactly 0 for n·ω ≤ 0 although the
    light is there."""
    wall = _quad([[2.0, -1.0, -1.0], [2.0, -1.0, 1.0], [2.0, 1.0, 1.0], [2.0, 1.0, -1.0]])  # faces −x
    assert np.cross(wall[0][1] - wall[0][0], wall[0][2] - wall[0][0])[0] < 0
    scene = load_scene(_write_scene(tmp_path, [(*wall, 3.0)], {"points": [[0.0, 0.0, 0.0]], "normal": [0.0, 0.0, 1.0]}))
    c = np.array([0.3, 1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-12, 0.0, -1e-12, -1e-8, -1e-6, -1e-3, -0.3])
    dirs = np.stack([np.sqrt(1.0 - c * c), 0.1 * np.ones_like(c), c], axis=1)
    dirs[:, 0] = np.sqrt(1.0 - c * c - 0.01)
    f = evaluate_integrand(scene, 0, dirs)
    n_dot = dirs.astype(np.float32).astype(np.float64)[:, 2]
    assert np.all(np.isfinite(f)) and np.all(f >= 0.0)
    above = n_dot > 0.0
    np.testing.assert_allclose(f[above], 3.0 * n_dot[above], rtol=1e-4)
    assert np.all(f[~above] == 0.0)
    assert np.count_nonzero(above) >= 10


def test_light_seen_from_behind_gives_zero(tmp_path):
    """Emission is one-sided: above the ceiling light (facing up at its back) f = 0 in
    every direction that hits it, while below it f > 0."""
    scene = load_scene(_write_scene(
        tmp_path, [(*CEILING, CEILING_L)],
        {"points": [[0.0, 0.0, 3.0], [0.3, 0.1, 2.5], [0.0, 0.0, 1.0]],
         "normals": [[0.0, 0.0, -1.0], _unit([0.3, 0.0, -1.0]).tolist(), [0.0, 0.0, 1.0]]}))
    u = np.random.default_rng(7).random((20_000, 2), dtype=np.float32)
    for r in (0, 1):
        dirs, pdf = sample_directions(scene, r, "light-area", u)
        assert np.all(pdf > 0.0)
        assert np.all(evaluate_integrand(scene, r, dirs) == 0.0)
        dirs, _ = sample_directions(scene, r, "cosine", u)
        assert np.all(evaluate_integrand(scene, r, dirs) == 0.0)
    dirs, _ = sample_directions(scene, 2, "light-area", u)
    assert np.all(evaluate_integrand(scene, 2, dirs) > 0.0)


@pytest.mark.parametrize("tilt", [0.0, 25.0])
def test_receiver_on_surface_does_not_self_intersect(tmp_path, tilt):
    """Receivers exactly on a floor (on a triangle, on its shared diagonal, on a vertex)
    see the light: f > 0 for every direction that reaches it, so no ray hits the floor
    it starts on.  Also for a tilted floor, whose float32 vertices leave the receivers a
    rounding error above or below the plane."""
    rot = trimesh.transformations.rotation_matrix(math.radians(tilt), [0.0, 1.0, 0.0])[:3, :3]
    floor_v = FLOOR[0] @ rot.T
    light_v = np.array([[-1.0, -1.0, 3.0], [-1.0, 1.0, 3.0], [1.0, 1.0, 3.0], [1.0, -1.0, 3.0]])
    pts = np.array([[0.0, 0.0, 0.0], [0.3, 0.3, 0.0], [0.37, -0.21, 0.0], [-1.3, 0.45, 0.0], [2.0, 2.0, 0.0],
                    [1e-7, 1e-7, 0.0]]) @ rot.T
    normal = rot @ np.array([0.0, 0.0, 1.0])
    scene = load_scene(_write_scene(tmp_path, [(floor_v, FLOOR[1], 0.0), (light_v, CEILING[1], 4.0)],
                                    {"points": pts.tolist(), "normal": normal.tolist()}))
    u = np.random.default_rng(3).random((50_000, 2), dtype=np.float32)
    for r in range(len(pts)):
        dirs, pdf = sample_directions(scene, r, "light-area", u)
        ok = (pdf > 0.0) & (dirs @ normal > 1e-3)  # towards the light, above the horizon
        assert np.count_nonzero(ok) > 40_000
        f = evaluate_integrand(scene, r, dirs[ok])
        assert np.all(f > 0.0), f"receiver {r}: {np.count_nonzero(f <= 0)} rays blocked by the floor"
        np.testing.assert_allclose(f, 4.0 * (dirs[ok] @ normal), rtol=1e-4)


# --------------------------------------------------------------------------- materials


def _dome(radius: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
    """An icosphere about the origin whose front faces point inwards."""
    ico = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    return np.asarray(ico.vertices), np.asarray(ico.faces)[:, ::-1]


def _hemisphere_quadrature(normal, n_cos: int = 256, n_phi: int = 512):
    """Directions and weights of a product rule for ∫ over the hemisphere about ``normal``:
    Gauss–Legendre in cos θ ∈ (0, 1), the periodic trapezoid rule in φ."""
    x, w = np.polynomial.legendre.leggauss(n_cos)
    c = 0.5 * (x + 1.0)
    wc = 0.5 * w
    phi = (np.arange(n_phi) + 0.5) * (2.0 * math.pi / n_phi)
    n = _unit(normal)
    b1 = _unit(np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0]))
    b2 = np.cross(n, b1)
    cc, pp = np.meshgrid(c, phi, indexing="ij")
    s = np.sqrt(1.0 - cc * cc)
    dirs = (s * np.cos(pp))[..., None] * b1 + (s * np.sin(pp))[..., None] * b2 + cc[..., None] * n
    weights = np.repeat(wc[:, None], n_phi, axis=1) * (2.0 * math.pi / n_phi)
    return dirs.reshape(-1, 3), weights.reshape(-1)


def test_lambert_is_albedo_over_pi_times_irradiance(tmp_path):
    """Same point, same directions: f_lambert = albedo/π · f_irradiance, sample by sample."""
    point = {"points": [[0.2, -0.1, 0.0]], "normal": [0.0, 0.0, 1.0]}
    scene = load_scene(_write_scene(
        tmp_path, [(*FLOOR, 0.0), (*CEILING, CEILING_L)],
        [dict(point, name="irr", material={"type": "irradiance"}),
         dict(point, name="lam", material={"type": "lambert", "albedo": 0.6})]))
    u = np.random.default_rng(5).random((100_000, 2), dtype=np.float32)
    for tech in ("uniform", "light-area"):
        dirs, _ = sample_directions(scene, 0, tech, u)
        f_irr = evaluate_integrand(scene, 0, dirs)
        f_lam = evaluate_integrand(scene, 1, dirs)
        assert np.count_nonzero(f_irr) > 1000
        np.testing.assert_allclose(f_lam, 0.6 / math.pi * f_irr, rtol=1e-6)


def test_dome_quadrature_irradiance_and_lambert(tmp_path):
    """Inside a closed emitting dome of radiance 1: irradiance ∫ cos θ dω = π and the
    lambert receiver reflects its albedo."""
    scene = load_scene(_write_scene(
        tmp_path, [(*_dome(), 1.0)],
        [{"name": "irr", "points": [[0.0, 0.0, 0.0]], "normal": _unit([0.2, -0.3, 1.0]).tolist(),
          "material": {"type": "irradiance"}},
         {"name": "lam", "points": [[1.0, 2.0, -3.0]], "normal": _unit([1.0, 0.0, 0.0]).tolist(),
          "material": {"type": "lambert", "albedo": 0.35}}]))
    for r, expected in ((0, math.pi), (1, 0.35)):
        dirs, w = _hemisphere_quadrature(scene.receivers.normals[r], 64, 128)
        f = evaluate_integrand(scene, r, dirs)
        assert np.all(f > 0.0)  # the dome is closed: every ray above the horizon hits it
        assert abs(float(np.sum(w * f)) - expected) < 1e-5 * expected


@pytest.mark.parametrize(("exponent", "view_tilt", "normal_tilt"), [
    (0.0, 0.0, 0.0), (1.0, 0.0, 20.0), (10.0, 0.0, 0.0), (50.0, 30.0, 0.0), (300.0, 50.0, 10.0),
    (2000.0, 70.0, 35.0)])
def test_phong_lobe_is_energy_normalised(tmp_path, exponent, view_tilt, normal_tilt):
    """Modified Phong ρ = albedo (e+2)/(2π) cos^e α: ∫ ρ cos θ dω over the hemisphere is
    albedo · (n·r) for a lobe (axis r, the mirror of the view) above the horizon — albedo
    exactly when the view is the normal, albedo·cos(tilt) for a view tilted away from it
    (the lobe's weight beyond the horizon, cos^e of more than 90° − tilt, is < 1e-8 in the
    tilted cases).  Dense quadrature about the lobe axis inside an emitting dome."""
    rot_n = trimesh.transformations.rotation_matrix(math.radians(normal_tilt), [1.0, 0.0, 0.0])[:3, :3]
    rot_v = trimesh.transformations.rotation_matrix(math.radians(view_tilt), [0.0, 1.0, 0.0])[:3, :3]
    normal = rot_n @ np.array([0.0, 0.0, 1.0])
    view = rot_n @ rot_v @ np.array([0.0, 0.0, 1.0])
    albedo = 0.8
    scene = load_scene(_write_scene(
        tmp_path, [(*_dome(), 1.0)],
        {"points": [[0.5, -0.25, 0.1]], "normal": normal.tolist(),
         "material": {"type": "phong", "exponent": exponent, "albedo": albedo, "view": view.tolist()}}))
    axis = 2.0 * np.dot(normal, view) * normal - view
    if view_tilt:
        assert math.cos(math.radians(90.0 - view_tilt)) ** exponent < 1e-8
    # Gauss–Legendre in cos α is exact for the polynomial lobe; nodes crowd near α = 0 for
    # the narrow lobes because the rule is in cos α ∈ (0, 1), so use enough of them.
    n_cos = 512 if exponent < 1000 else 2048
    dirs, w = _hemisphere_quadrature(axis, n_cos, 256)
    f = evaluate_integrand(scene, 0, dirs)
    assert np.all(np.isfinite(f)) and np.all(f >= 0.0)
    expected = albedo * float(np.dot(normal, axis))
    assert abs(float(np.sum(w * f)) - expected) < 2e-4 * expected
    # Below the horizon f vanishes although ρ does not (for the tilted lobes).
    below = dirs @ normal <= 0.0
    assert np.all(f[below] == 0.0)
