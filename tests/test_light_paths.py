"""The two ways warpis finds f and a light sample's pdf, and that they agree.

On a planar emitter set (every emitter triangle in one plane, facing one way:
``SceneData.planar_emitters``) a light-area or light-power sample knows the one point
where its ray crosses the emitters, the point it sampled: its pdf is that point's
density and its f needs only the shadow ray to that point
(``techniques.sample_light_point`` and ``integrand.integrand_via``).  Everywhere else f
looks up the nearest emitter crossing (or casts a closest-hit ray) and the pdf sums
over every crossing (``light_pdf``).  Here both are run on the same directions: same
pdf to float32 rounding, same f.  The convention at the emitter end (geometry within the
emitter's own self-hit slab is not seen) is pinned from both sides.  Deterministic: no
test can fail by chance.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from test_integrand import CEILING, CEILING_L, FLOOR, _quad, _write_scene

import warpis
from warpis.kernels.device import SELF_HIT_SLAB, ReceiverData, SceneData, planar_emitters, upload
from warpis.kernels.integrand import integrand, integrand_via, shading_point
from warpis.kernels.techniques import TECHNIQUES, LightTable, light_table, sample_light_point, technique_pdf
from warpis.scenes import load_scene

PLANAR = ("occluded-quad", "heavy-occluder", "mitsuba-cornell-box")
NOT_PLANAR = ("two-lights", "veach-plates", "mitsuba-veach-plates")


@wp.kernel(enable_backward=False)
def _both_paths(scene: SceneData, recv: ReceiverData, table: LightTable, tech: wp.int32, r: wp.int32,
                u: wp.array(dtype=wp.vec2), dirs: wp.array(dtype=wp.vec3), own_pdf: wp.array(dtype=wp.float32),
                summed_pdf: wp.array(dtype=wp.float32), f_known: wp.array(dtype=wp.float32),
                f_looked_up: wp.array(dtype=wp.float32)):
    i = wp.tid()
    sp = shading_point(scene, recv, r)
    smp = sample_light_point(tech, scene, sp, u[i])
    dirs[i] = smp.w
    own_pdf[i] = smp.pdf
    summed_pdf[i] = technique_pdf(tech, scene, table, sp, smp.w)
    f_known[i] = integrand_via(scene, sp, smp.w, smp.emitter, smp.t)
    f_looked_up[i] = integrand(scene, sp, smp.w)


def both_paths(scene: warpis.Scene, technique: str, receiver: int, count: int, seed: int) -> tuple[np.ndarray, ...]:
    up = upload(scene)
    u = np.random.default_rng(seed).random((count, 2)).astype(np.float32)
    out = [wp.zeros(count, dtype=wp.vec3)] + [wp.zeros(count, dtype=wp.float32) for _ in range(4)]
    wp.launch(_both_paths, dim=count, inputs=[up.data, up.receiver_data, light_table(scene),
                                              TECHNIQUES[technique].code, receiver, wp.array(u, dtype=wp.vec2), *out])
    return tuple(a.numpy() for a in out)


@pytest.mark.parametrize("name", PLANAR + NOT_PLANAR)
def test_planar_emitters_are_recognised(name):
    scene = warpis.load_scene(name)
    assert bool(upload(scene).data.planar_emitters) == (name in PLANAR)


def test_planar_needs_one_plane_and_one_facing():
    v, f = _quad([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]])
    quad = v[f]
    beside = quad + np.array([2.0, 0.0, 0.0])
    assert planar_emitters(np.concatenate([quad, beside]))
    assert not planar_emitters(np.concatenate([quad, beside[:, ::-1]]))  # the second one faces up
    assert not planar_emitters(np.concatenate([quad, beside + np.array([0.0, 0.0, 1e-3])]))  # a step
    folded = quad.copy()
    folded[1, :, 2] += 1e-3 * folded[1, :, 0]  # the second triangle tilts about the y axis
    assert not planar_emitters(folded)
    assert planar_emitters(quad + 1e-3 * quad[:, :, :1])  # a tilted plane is still one plane
    assert not planar_emitters(np.zeros((0, 3, 3)))


@pytest.mark.parametrize("name", PLANAR)
@pytest.mark.parametrize("technique", ["light-area", "light-power"])
def test_a_light_sample_on_a_planar_set_knows_its_pdf_and_its_value(name, technique):
    scene = warpis.load_scene(name)
    lit = 0
    for r in range(min(len(scene.receivers), 8)):
        dirs, own, summed, f_known, f_looked_up = both_paths(scene, technique, r, 20000, seed=r)
        np.testing.assert_allclose(own, summed, rtol=2e-4, err_msg=f"{name} receiver {r}")
        # f: the same value, except where the two emitter tests differ at a triangle's
        # edge (float32 rounding of the sampled point against the float64 crossing test).
        differ = ~np.isclose(f_known, f_looked_up, rtol=1e-5, atol=0)
        assert differ.mean() <= 1e-3, f"{name} receiver {r}: {differ.sum()} values differ"
        lit += int((f_known > 0).sum())
    assert lit > 0  # the receivers see some light


def _blocked_light(tmp_path, gap: float):
    """The ceiling light (facing down at z = 2) with an opaque quad of its size right
    below it at z = 2 − gap, and a receiver under both."""
    blocker, faces = CEILING
    blocker = blocker * np.array([1.2, 1.2, 1.0]) - np.array([0.0, 0.0, gap])
    return load_scene(_write_scene(tmp_path, [(*CEILING, CEILING_L), (blocker, faces, 0.0), (*FLOOR, 0.0)],
                                   {"points": [[0.1, 0.05, 0.0]], "normal": [0.0, 0.0, 1.0]}))


@pytest.mark.parametrize("inside", [True, False])
def test_geometry_within_the_emitters_slab_is_not_seen_on_either_path(tmp_path, inside):
    """The shadow ray stops where it enters the emitter's self-hit slab (integrand.py):
    SELF_HIT_SLAB × the magnitude of the light point y (the light has no bent
    neighbours).  A blocker inside that slab (a quarter of its least height below the
    light) is not seen, one four greatest heights below blocks all light, on the
    light-sample path and on the lookup path alike."""
    corners = CEILING[0]
    least, most = SELF_HIT_SLAB * np.abs(corners[:, 2]).min(), SELF_HIT_SLAB * np.abs(corners).max()
    scene = _blocked_light(tmp_path / "scene", gap=least / 4 if inside else 4 * most)
    assert upload(scene).data.planar_emitters  # the blocker does not emit: the set stays planar
    _, own, _, f_known, f_looked_up = both_paths(scene, "light-area", 0, 4000, seed=3)
    if inside:
        assert np.all(f_known > 0) and np.all(f_looked_up > 0)
    else:
        assert np.all(f_known == 0) and np.all(f_looked_up == 0)


def test_a_light_sample_from_behind_a_planar_light_sees_nothing(tmp_path):
    """One-sided emission on both paths: a receiver above the ceiling light (which faces
    down), facing it, gets f = 0 for every light sample, whether the sample's crossing
    is known or looked up; one below it gets its light on both."""
    scene = load_scene(_write_scene(tmp_path, [(*CEILING, CEILING_L)],
                                    [{"points": [[0.1, 0.0, 3.0]], "normal": [0.0, 0.0, -1.0]},
                                     {"points": [[0.1, 0.0, 0.0]], "normal": [0.0, 0.0, 1.0]}],
                                    material={"type": "irradiance"}))
    assert upload(scene).data.planar_emitters
    _, own, summed, f_known, f_looked_up = both_paths(scene, "light-area", 0, 4000, seed=4)
    assert np.all(own > 0) and np.all(f_known == 0) and np.all(f_looked_up == 0)
    _, _, _, f_known, f_looked_up = both_paths(scene, "light-area", 1, 4000, seed=4)
    assert np.all(f_known > 0) and np.allclose(f_known, f_looked_up, rtol=1e-6)
