"""Ground truth: importance-sampled estimates against the closed form and the quadrature.

Every technique that applies to irradiance receivers (every registered technique but
the glossy lobes: uniform, cosine, light-area, light-power, light-solid-angle) estimates
F at receivers whose reference is exact (``warpis.analysis.reference.reference`` → method
"closed-form": Lambert's formula, no occluder):
lights at several distances and tilts, one partly below the receiver's horizon, one
almost edge-on, one seen from behind (F = 0).  Each estimate is the mean of 1024 trials
of ``independent:single:T`` with N = 1024 (about 10⁶ samples); its standard error comes
from the spread of the trials.  The estimators are bounded here, so the mean is normal
to an excellent approximation, and each comparison passes when it lies within 4.5
standard errors of the reference: a false failure has probability 2·(1 − Φ(4.5)) ≈ 6.8e-6.

On the bundled occluded-quad the reference is the closed form for the lit receivers
and quadrature (dense jittered light-solid-angle sampling) for the shadowed ones; the
quadrature agrees with an independent ``jittered:balance:light-area+cosine`` estimate
within 4.5 combined standard errors (the quadrature's stderr, from 32 replicas, is small
beside the estimate's, so the combined z is normal to a good approximation).

Comparisons: (8 + 3 receivers of the two scenes) × 5 techniques = 55, of which the 5
at the receiver behind its light (F = 0) are exact: every trial must return 0.  With
the 6 lit or penumbra receivers of occluded-quad (its 2 umbra receivers are exact zeros
too) that makes 56 comparisons that can fail by chance; by the union bound the
probability that this module fails by chance is below 56 × 6.8e-6 ≈ 3.8e-4 (the seeds
are fixed, so every run draws the same numbers).  (At 4 standard errors it was 3.5e-3,
too high for a suite that runs on every change; the loss of power is 12%.)

Two one-sided checks are not tests of chance: ``se < 0.05·F`` (the estimate is precise
enough for the comparison to mean something: a requirement on the test, met by a wide
margin with 10⁶ samples), and a shadowed receiver's quadrature lies more than 10 of its
own standard errors below the unoccluded closed form (measured: 860 to 2900).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from conftest import write_scene

from warpis.analysis.closed_form import irradiance_closed_form
from warpis.analysis.reference import reference
from warpis.cli import main
from warpis.kernels.engine import run_trials
from warpis.kernels.integrand import MATERIALS, evaluate_integrand
from warpis.kernels.techniques import TECHNIQUES as REGISTERED
from warpis.scenes import load_scene

# Every technique that applies to irradiance receivers under emitter triangles: all but
# the glossy materials' lobes and the environment's (its closed form, F = albedo · L under
# a constant environment, is tests/test_environment.py's).
LOBES = {m.bsdf_technique for m in MATERIALS.values() if not m.diffuse}
TECHNIQUES = tuple(t for t, e in REGISTERED.items() if t not in LOBES and not e.environment)
N, TRIALS = 1024, 1024
Z_MAX = 4.5  # two-sided normal tail 6.8e-6 per comparison (module docstring)

# --------------------------------------------------------------------------- scene files


def _write_scene(directory: Path, meshes: list[tuple], receivers: dict, material: dict | None = None) -> Path:
    """``meshes``: (vertices (V, 3), faces (F, 3), emission) per mesh, written as OBJ files;
    ``receivers`` and ``material`` (default irradiance) as tables.  Returns the TOML's path."""
    entries = [{"path": f"mesh{i}.obj", "vertices": np.asarray(v, float), "faces": np.asarray(f, int),
                **({"emission": float(e)} if e else {})} for i, (v, f, e) in enumerate(meshes)]
    return write_scene(directory, entries, receivers, material or {"type": "irradiance"}, name=directory.name)


def _unit(v) -> list[float]:
    v = np.asarray(v, dtype=float)
    return (v / np.linalg.norm(v)).tolist()


QUAD_FACES = np.array([[0, 1, 2], [0, 2, 3]])
# A 1 × 1 ceiling light at z = 1.5, facing down, radiance 3.
SQUARE = np.array([[-0.5, -0.5, 1.5], [-0.5, 0.5, 1.5], [0.5, 0.5, 1.5], [0.5, -0.5, 1.5]])
SQUARE_RECEIVERS = {
    "points": [[0.0, 0.0, 0.0], [1.5, 0.5, 0.0], [0.1, 0.0, 1.2], [0.2, 0.0, 0.0], [0.0, 0.0, 0.5],
               [0.0, 0.0, 2.5], [3.0, 0.0, 0.0], [0.3, -0.2, 1.45]],
    "normals": [[0.0, 0.0, 1.0],  # straight below, facing it
                [0.0, 0.0, 1.0],  # off to the side: oblique
                [0.0, 0.0, 1.0],  # close: 0.3 below, a large solid angle
                _unit([1.0, 0.0, 1.0]),  # tilted by 45°
                _unit([1.0, 0.0, 0.2]),  # its horizon cuts the light (x > −0.2 above it)
                [0.0, 0.0, -1.0],  # above the light: sees its back, F = 0
                _unit([-1.0, 0.0, 1.0]),  # far, tilted towards the light
                _unit([0.0, 1.0, 0.05])],  # 0.05 below the light plane: grazing, horizon cuts it
}
# A tilted triangle light (front face towards −z, roughly), radiance 2.
TRIANGLE = np.array([[-1.0, -1.0, 2.0], [0.0, 1.5, 2.5], [1.5, -0.5, 1.0]])
TRIANGLE_RECEIVERS = {
    "points": [[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.5, 0.0, 1.0]],
    "normals": [[0.0, 0.0, 1.0], _unit([-1.0, 0.0, 1.0]), _unit([1.0, 0.0, 0.3])],  # the last: horizon cuts it
}
SCENES = {
    "square": ([(SQUARE, QUAD_FACES, 3.0)], SQUARE_RECEIVERS),
    "triangle": ([(TRIANGLE, np.array([[0, 1, 2]]), 2.0)], TRIANGLE_RECEIVERS),
}


@pytest.fixture(scope="module")
def closed_form_scenes(tmp_path_factory):
    out = {}
    for name, (meshes, receivers) in SCENES.items():
        out[name] = load_scene(_write_scene(tmp_path_factory.mktemp(name), meshes, receivers))
    return out


def _horizon_cuts(scene, r: int) -> bool:
    """Whether receiver r's tangent plane separates the corners of the emitters."""
    x, n = scene.receivers.positions[r], scene.receivers.normals[r]
    h = (scene.triangle_vertices(scene.emitters).reshape(-1, 3) - x) @ n
    return bool(h.min() < 0.0 < h.max())


def test_scenes_cover_the_cases(closed_form_scenes):
    """The receivers above are what their comments say."""
    sq, tri = closed_form_scenes["square"], closed_form_scenes["triangle"]
    assert [_horizon_cuts(sq, r) for r in range(8)] == [False, False, False, False, True, False, False, True]
    assert [_horizon_cuts(tri, r) for r in range(3)] == [False, False, True]
    refs = reference(sq)
    assert refs[5].value == 0.0
    assert all(r.value > 0.0 for i, r in enumerate(refs) if i != 5)


@pytest.mark.parametrize("technique", TECHNIQUES)
@pytest.mark.parametrize("scene_name", list(SCENES))
def test_estimate_matches_closed_form(closed_form_scenes, scene_name, technique):
    """IS with one technique, ~10⁶ samples per receiver: within 4 standard errors."""
    scene = closed_form_scenes[scene_name]
    refs = reference(scene)
    assert all(r.method == "closed-form" for r in refs)
    seed = 1000 + 10 * list(SCENES).index(scene_name) + TECHNIQUES.index(technique)
    est = run_trials(scene, f"independent:single:{technique}", N, TRIALS, seed=seed)
    mean = est.mean(axis=1)
    se = est.std(axis=1, ddof=1) / math.sqrt(TRIALS)
    for r, ref in enumerate(refs):
        if ref.value == 0.0:
            assert np.all(est[r] == 0.0), f"receiver {r}: F = 0 but some trial is not 0"
            continue
        assert se[r] > 0.0 and se[r] < 0.05 * ref.value
        z = (mean[r] - ref.value) / se[r]
        assert abs(z) <= Z_MAX, (f"{scene_name} receiver {r} {technique}: {mean[r]:.6g} ± {se[r]:.3g} "
                                 f"vs closed form {ref.value:.6g} (z = {z:.2f})")


# --------------------------------------------------------------------------- occluded-quad


def _visible_fraction(scene, r: int, grid: int = 160) -> float:
    """Fraction of a grid of points on the emitters that receiver r sees unoccluded."""
    rx = scene.receivers
    p = rx.positions[r]
    s, t = np.meshgrid((np.arange(grid) + 0.5) / grid, (np.arange(grid) + 0.5) / grid, indexing="ij")
    keep = (s + t < 1.0).ravel()
    bary = np.stack([1.0 - s - t, s, t], axis=-1).reshape(-1, 3)[keep]
    pts = np.einsum("kb,ebc->ekc", bary, scene.triangle_vertices(scene.emitters)).reshape(-1, 3)
    dirs = pts - p
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    assert np.all(dirs @ rx.normals[r] > 0.0)  # the light is above every receiver's horizon here
    return float(np.mean(evaluate_integrand(scene, r, dirs) > 0.0))


def test_occluded_quad_reference_methods_and_quadrature():
    """Closed form exactly where the receiver sees the whole light; quadrature in the
    penumbra and umbra, agreeing with an independent MIS estimate (and so does the
    closed form)."""
    scene = load_scene("occluded-quad")
    refs = reference(scene)
    visible = np.array([_visible_fraction(scene, r) for r in range(len(refs))])
    methods = [r.method for r in refs]
    assert methods == ["closed-form" if v == 1.0 else "quadrature" for v in visible]
    assert methods.count("closed-form") >= 2 and np.any((visible > 0.0) & (visible < 1.0))
    unoccluded, _ = irradiance_closed_form(
        scene.receivers.positions,
        scene.receivers.normals, scene.triangle_vertices(), scene.emission)
    est = run_trials(scene, "jittered:balance:light-area+cosine", N, TRIALS, seed=4242)
    mean = est.mean(axis=1)
    se = est.std(axis=1, ddof=1) / math.sqrt(TRIALS)
    for r, ref in enumerate(refs):
        if ref.method == "quadrature":
            assert ref.samples > 0
            if visible[r] == 0.0:  # umbra: both are exactly 0
                assert ref.value == 0.0 and ref.stderr == 0.0 and np.all(est[r] == 0.0)
                continue
            # A shadow: well below the unoccluded closed form.
            assert ref.value < unoccluded[r] - 10.0 * ref.stderr
            assert ref.stderr > 0.0
        else:
            assert ref.stderr == 0.0 and ref.value == pytest.approx(unoccluded[r], rel=1e-12)
        combined = math.hypot(se[r], ref.stderr)
        z = (mean[r] - ref.value) / combined
        assert abs(z) <= Z_MAX, f"receiver {r}: MIS {mean[r]:.6g} vs {ref.method} {ref.value:.6g} (z = {z:.2f})"


# --------------------------------------------------------------------------- command line


def test_cli_reference_scales_lambert_by_albedo_over_pi(tmp_path, capsys):
    """``warpis reference --json``: a lambert receiver's value is albedo/π times the
    irradiance, for closed-form and quadrature receivers alike (same seed, same samples)."""
    floor = np.array([[-3.0, -3.0, 0.0], [3.0, -3.0, 0.0], [3.0, 3.0, 0.0], [-3.0, 3.0, 0.0]])
    light = np.array([[-0.5, -0.5, 2.0], [-0.5, 0.5, 2.0], [0.5, 0.5, 2.0], [0.5, -0.5, 2.0]])
    blocker = np.array([[0.0, -1.0, 1.0], [0.0, 1.0, 1.0], [1.0, 1.0, 1.0], [1.0, -1.0, 1.0]])
    meshes = [(floor, QUAD_FACES, 0.0), (light, QUAD_FACES, 4.0), (blocker, QUAD_FACES, 0.0)]
    receivers = {"points": [[-2.5, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 1.5, 0.0]], "normal": [0.0, 0.0, 1.0]}
    albedo = 0.45
    out = {}
    for name, material in (("irr", {"type": "irradiance"}), ("lam", {"type": "lambert", "albedo": albedo})):
        path = _write_scene(tmp_path / name, meshes, receivers, material)
        capsys.readouterr()
        assert main(["reference", str(path), "--json", "--samples", "1024"]) == 0
        out[name] = json.loads(capsys.readouterr().out)["receivers"]
    irr, lam = out["irr"], out["lam"]
    assert [r["method"] for r in irr] == [r["method"] for r in lam]
    assert {r["method"] for r in irr} == {"closed-form", "quadrature"}
    for a, b in zip(irr, lam):
        assert a["value"] > 0.0
        assert b["value"] == pytest.approx(albedo / math.pi * a["value"], rel=1e-5)
        assert b["stderr"] == pytest.approx(albedo / math.pi * a["stderr"], rel=1e-5, abs=1e-15)
