"""Environment lights: Mitsuba's envmap and constant emitters, the ``envmap`` technique, references.

The scene (written here with Mitsuba's own ``Bitmap``): a procedural 48 × 24 HDR sky with a
sun 60× the sky, rotated by a to_world about a tilted axis and scaled, over a diffuse
floor with a box on it and a roughplastic plate, and a small rectangle area light: a
scene lit by both an environment and an emitter triangle set.

* **The lookup** is Mitsuba's: ``Environment.radiance`` (numpy) and the kernel's f on an
  open floor (f = L · albedo/π · cos θ) against Mitsuba's ``emitter.eval`` at 3000
  directions, the poles and the seam of the map among them: to float32 rounding (2e-6
  relative to the map's largest value: deterministic).
* **The constant emitter**: F = albedo · L on an open floor, the closed form, from
  ``reference`` (quadrature) and from envmap IS alone, each within 4 of its stderr
  (false failure ≤ 4 × 6.3e-5).
* **References against Mitsuba's direct light**: at five receivers (lit floor, the box's
  sun shadow, the box's top, the glossy plate, a floor point under the area light)
  warpis's ``reference`` (the MIS of light-solid-angle and envmap, or the BSDF alone,
  whichever the race picks) against ``SAMPLES`` of Mitsuba's own emitter sampling
  (``sample_emitter_direction``: it picks the envmap or the rectangle and importance
  samples it) × its ``bsdf.eval`` × visibility along the segment, as
  tests/test_against_mitsuba.py does.  Tolerance: 4 combined standard errors, for each
  of the five: ≤ 5 × 6.9e-5 = 3.5e-4 false failures (Bonferroni; Mitsuba's samples are
  bounded, the mean over 2^18 normal; warpis's stderr from 32 replicas, asserted at most
  half of Mitsuba's, gives ≥ 775 degrees of freedom).  The fixed seeds make every run the
  same.
* **Theory applies unchanged**: the exact variance of ``jittered:balance:envmap+bsdf`` at
  the plate against the variance of 20,000 trials, within the fourth-moment interval at
  z = 4 of the two combined (false failure ≤ 6.3e-5).
* Bad input: a scaled to_world, a textured constant radiance (Mitsuba's own refusal), a light technique on a
  scene without emitter triangles, an envmap technique on a scene without an
  environment, a malformed table: one line, exit 2.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

import warpis  # noqa: E402
from conftest import one_error_line, sky_environment  # noqa: E402
from warpis.analysis.reference import reference  # noqa: E402
from warpis.analysis.quadrature import exact_variance  # noqa: E402
from warpis.kernels.engine import run_moments  # noqa: E402
from warpis.kernels.integrand import evaluate_integrand  # noqa: E402
from warpis.scenes.mitsuba import load_mitsuba  # noqa: E402

SAMPLES = 1 << 18  # Mitsuba's emitter samples per receiver
SEED = 1234
Z = 4.0
SE_SHARE = 0.5
REL_ERROR = 5e-4

SCENE_XML = """<scene version="3.0.0">
  <emitter type="envmap" id="sky">
    <string name="filename" value="sky.exr"/>
    <float name="scale" value="0.8"/>
    <transform name="to_world"><rotate x="0.282216" y="0.940720" z="0.188144" angle="35"/></transform>
  </emitter>
  <shape type="rectangle" id="floor">
    <transform name="to_world"><rotate x="1" angle="-90"/><scale value="3"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.6, 0.5, 0.4"/></bsdf>
  </shape>
  <shape type="cube" id="box">
    <transform name="to_world"><scale x="0.3" y="0.6" z="0.3"/><translate x="0.48" y="0.6" z="0.3"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.3, 0.4, 0.5"/></bsdf>
  </shape>
  <shape type="rectangle" id="plate">
    <transform name="to_world"><rotate x="1" angle="-60"/><scale value="0.4"/><translate x="-1" y="0.5" z="0"/>
    </transform>
    <bsdf type="roughplastic"><float name="alpha" value="0.2"/><string name="distribution" value="ggx"/>
      <rgb name="diffuse_reflectance" value="0.2, 0.3, 0.4"/></bsdf>
  </shape>
  <shape type="rectangle" id="lamp">
    <transform name="to_world"><rotate x="1" angle="90"/><scale value="0.2"/><translate x="0" y="1.5" z="-1.5"/>
    </transform>
    <emitter type="area"><rgb name="radiance" value="30, 30, 25"/></emitter>
  </shape>
  <sensor type="perspective">
    <transform name="to_world"><lookat origin="0, 3, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
  </sensor>
</scene>
"""
# (group, point): on the floor in the open, in the box's shadow of the sun, on the box's
# top, on the plate, on the floor under the lamp.
RECEIVERS = [("floor", (-0.3, 0.0, 1.2)), ("floor", None), ("box", (0.48, 1.2, 0.3)), ("plate", (-1.0, 0.5, 0.0)),
             ("floor", (0.1, 0.0, -1.3))]


def sky_rgb(height: int = 24, width: int = 48) -> np.ndarray:
    """(H, W, 3) linear sRGB: a bluish gradient, a warm ground, a sun of 60× over 2 × 2 texels."""
    theta = np.pi * (np.arange(height) + 0.5) / height
    phi = 2 * np.pi * (np.arange(width) + 0.5) / width
    up = np.cos(theta)[:, None]
    base = np.where(up > 0, 0.4 + 0.8 * up, 0.15 + 0.05 * np.sin(3 * phi)[None, :])
    rgb = np.stack([0.7 * base, 0.85 * base, 1.0 * base], axis=-1) * np.ones((height, width, 1))
    rgb[5:7, 10:12] *= 60.0
    return rgb.astype(np.float32)


def sun_direction(scene: warpis.Scene) -> np.ndarray:
    """The world direction of the brightest texel's centre."""
    env = scene.environment
    j, i = np.unravel_index(np.argmax(env.texels), env.texels.shape)
    height, width = env.texels.shape
    theta, phi = math.pi * j / (height - 1), 2 * math.pi * (i + 0.5) / width
    local = np.array([math.sin(phi) * math.sin(theta), math.cos(theta), -math.cos(phi) * math.sin(theta)])
    return env.rotation @ local


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    path = tmp_path_factory.mktemp("environment")
    mi.set_variant("scalar_rgb")
    mi.Bitmap(sky_rgb()).write(str(path / "sky.exr"))
    (path / "scene.xml").write_text(SCENE_XML)
    return path


def _write_receivers(folder, points) -> None:
    lines = []
    for group, p in points:
        lines += ["[[receivers]]", f'name = "{group}"', f"points = [[{p[0]!r}, {p[1]!r}, {p[2]!r}]]", ""]
    (folder / "scene.receivers.toml").write_text("channel = \"g\"\n" + "\n".join(lines))


@pytest.fixture(scope="module")
def scenes(folder):
    """warpis's scene and Mitsuba's, the receivers placed (the shadowed one along the sun)."""
    _write_receivers(folder, [(g, p if p is not None else (0.0, 0.0, 0.0)) for g, p in RECEIVERS])
    probe = load_mitsuba(folder / "scene.xml")
    sun = sun_direction(probe)
    inside = np.array([0.48, 1.0, 0.3])  # in the box, 0.2 under its top
    shadow = inside - sun * (inside[1] / sun[1])  # the floor point whose ray to the sun crosses the box there
    assert sun[1] > 0.3 and np.abs(shadow - inside)[[0, 2]].max() > 0.3, (sun, shadow)  # beside the box
    points = [(g, p if p is not None else (float(shadow[0]), 0.0, float(shadow[2]))) for g, p in RECEIVERS]
    _write_receivers(folder, points)
    scene = load_mitsuba(folder / "scene.xml")
    mi.set_variant("scalar_rgb")
    ms = mi.load_file(str(folder / "scene.xml"), parallel=False, optimize=False)
    return scene, ms, sun


def test_lookup_is_mitsubas(scenes):
    """Environment.radiance and the kernel's f see what Mitsuba's envmap eval returns."""
    scene, ms, _ = scenes
    (emitter,) = [e for e in ms.emitters() if e.class_name() == "EnvironmentMapEmitter"]
    rng = np.random.default_rng(7)
    d = rng.normal(size=(3000, 3))
    d[:4] = [[0, 1, 0], [0, -1, 0], [1e-4, 1, 0], [0, 0.3, -1]]  # poles, near a pole, the map's seam
    d[4:] = d[4:] @ scene.environment.rotation.T  # and some about the rotated poles
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    theirs = np.empty(len(d))
    for k, w in enumerate(d.tolist()):
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(-w[0], -w[1], -w[2])
        theirs[k] = emitter.eval(si)[1]  # channel g
    mine = scene.environment.radiance(d)
    scale = theirs.max()
    assert np.abs(mine - theirs).max() <= 2e-6 * scale, np.abs(mine - theirs).max() / scale
    # The kernel: f at a floor point along upward directions that leave the scene (by
    # Mitsuba's own ray test; the box, the plate and the lamp hide the others).
    r = 0
    up = d[(d[:, 1] > 0.05)]
    p = scene.receivers.positions[r]
    free = np.array([not ms.ray_test(mi.Ray3f(mi.Point3f(*(p + 1e-4 * w)), mi.Vector3f(*w))) for w in up])
    assert free.mean() > 0.5
    f = evaluate_integrand(scene, r, up[free])
    seen = f / (scene.receivers.albedo[r] / math.pi * up[free, 1])
    np.testing.assert_allclose(seen, scene.environment.radiance(up[free]), rtol=2e-5, atol=2e-6 * scale)


def test_info_describes_the_map(cli, folder, scenes):
    """warpis info: the map's resolution, ∫ L dω and its brightest 1%'s share."""
    result = cli("info", str(folder / "scene.xml"))
    assert result.status == 0, result.err
    (line,) = [ln for ln in result.out.splitlines() if "envmap sky.exr" in ln]
    env = scenes[0].environment
    assert "48 × 24 texels" in line and f"{env.power:.6g}" in line, line
    share = env.brightest_share()
    assert 0.1 < share < 0.9 and f"{100 * share:.3g}%" in line, line
    assert "environment (envmap): 48 × 24 texels" in result.out
    data = json.loads(cli("info", str(folder / "scene.xml"), "--json").out)["environment"]
    assert data["resolution"] == [48, 24] and data["power"] == pytest.approx(env.power)
    assert data["brightest_1_percent_share"] == pytest.approx(share)


def test_constant_environment_is_albedo_times_radiance(tmp_path):
    """Under a constant environment an open lambert floor reflects F = albedo · L."""
    (tmp_path / "scene.xml").write_text(
        '<scene version="3.0.0"><emitter type="constant"><rgb name="radiance" value="2, 3, 4"/></emitter>'
        '<shape type="rectangle" id="floor"><transform name="to_world"><rotate x="1" angle="-90"/></transform>'
        '<bsdf type="diffuse"><rgb name="reflectance" value="0.5, 0.25, 0.125"/></bsdf></shape></scene>')
    (tmp_path / "scene.receivers.toml").write_text(
        'channel = "r"\n[[receivers]]\nname = "floor"\npoints = [[0.0, 0.0, 0.0], [0.3, 0.0, -0.2]]\n'
        'view = [0.0, 1.0, 0.0]\n')
    scene = load_mitsuba(tmp_path / "scene.xml")
    for ref in reference(scene, rel_error=1e-3):
        assert ref.method == "quadrature"
        assert abs(ref.value - 1.0) <= Z * ref.stderr + 1e-6, ref
    # envmap IS alone: its estimates average to the closed form too.
    est = run_moments(scene, "independent:single:envmap", 16, 4000, seed=2).interval()
    assert np.all(np.abs(est.mean - 1.0) <= Z * est.mean_stderr), (est.mean, est.mean_stderr)


def test_reference_matches_mitsuba_direct(scenes):
    """F at the five receivers against Mitsuba's emitter sampling (see the module docstring)."""
    scene, ms, sun = scenes
    refs = reference(scene, rel_error=REL_ERROR)
    camera = np.array(ms.sensors()[0].world_transform().matrix, dtype=np.float64)[:3, 3]
    ctx = mi.BSDFContext()
    rows, bad = [], []
    for i, ref in enumerate(refs):
        p = scene.receivers.positions[i]
        view = (camera - p) / np.linalg.norm(camera - p)
        si = ms.ray_intersect(mi.Ray3f(mi.Point3f(*(p + 0.01 * view)), mi.Vector3f(*(-view))))
        assert si.is_valid() and si.shape.id() == RECEIVERS[i][0], i
        values = np.zeros(SAMPLES)
        for j, (a, b) in enumerate(np.random.default_rng(SEED + i).random((SAMPLES, 2)).tolist()):
            ds, spec = ms.sample_emitter_direction(si, mi.Point2f(a, b), False)
            weight = spec[1]
            if weight > 0.0:
                length = min(ds.dist, 1e4) * (1.0 - 1e-5) - 1e-5
                if not ms.ray_test(mi.Ray3f(si.p + 1e-5 * ds.d, ds.d, length, 0.0, mi.Color0f())):
                    values[j] = weight * si.bsdf().eval(ctx, si, si.to_local(ds.d))[1]
        mean, se = float(values.mean()), float(values.std(ddof=1) / math.sqrt(SAMPLES))
        sigma = math.hypot(ref.stderr, se)
        z = (ref.value - mean) / sigma
        rows.append(f"  {i} {RECEIVERS[i][0]:<6} warpis {ref.value:.6f} ± {ref.stderr:.1e} ({ref.estimator})  "
                    f"mitsuba {mean:.6f} ± {se:.1e}  z {z:+.2f}")
        if not (abs(z) <= Z and ref.stderr <= SE_SHARE * se and mean > 0):
            bad.append(i)
    table = "\n".join(rows)
    print("\nF (channel g) under the envmap and the lamp, warpis vs Mitsuba:\n" + table)
    assert not bad, f"receivers {bad} disagree:\n{table}"
    # The box hides the sun from receiver 1, not from receiver 0.
    f_sun = [evaluate_integrand(scene, r, sun[None, :])[0] for r in (0, 1)]
    assert f_sun[0] > 0 and f_sun[1] == 0, f_sun


def test_exact_variance_of_envmap_mis(scenes):
    """verify's exact form, over the technique pdfs, holds for envmap + bsdf at the plate."""
    scene = scenes[0]
    estimator, n, trials = "jittered:balance:envmap+bsdf", 8, 20_000
    exact = exact_variance(scene, 3, estimator, n)
    measured = run_moments(scene, estimator, n, trials, seed=11, receivers=[3]).interval()
    s2, se = float(measured.variance[0]), float(measured.variance_stderr[0])
    assert abs(s2 - exact.value) <= Z * math.hypot(se, exact.stderr), (s2, se, exact)


# --------------------------------------------------------------------------- bad input


def test_a_scaled_envmap_is_refused(cli, folder):
    xml = SCENE_XML.replace('<rotate x="0.282216" y="0.940720" z="0.188144" angle="35"/>', '<scale value="2"/>')
    (folder / "scaled.xml").write_text(xml)
    (folder / "scaled.receivers.toml").write_text((folder / "scene.receivers.toml").read_text())
    line = one_error_line(cli("info", str(folder / "scaled.xml")))
    assert "emitter 'sky' (envmap)" in line and "not a rotation" in line, line


def test_a_textured_constant_is_refused(cli, tmp_path):
    (tmp_path / "scene.xml").write_text(
        '<scene version="3.0.0"><emitter type="constant"><texture type="checkerboard" name="radiance"/></emitter>'
        '<shape type="rectangle" id="floor"><bsdf type="diffuse"/></shape></scene>')
    (tmp_path / "scene.receivers.toml").write_text('[[receivers]]\nname = "floor"\npoints = [[0.0, 0.0, 0.0]]\n')
    line = one_error_line(cli("info", str(tmp_path / "scene.xml")))  # Mitsuba itself refuses it
    assert "constant" in line and "non-spatially varying" in line, line


def test_techniques_need_their_lights(cli, tmp_path):
    """light-area on a scene lit by its environment alone, envmap on one without."""
    (tmp_path / "scene.xml").write_text(
        '<scene version="3.0.0"><emitter type="constant"/>'
        '<shape type="rectangle" id="floor"><bsdf type="diffuse"/></shape></scene>')
    (tmp_path / "scene.receivers.toml").write_text(
        '[[receivers]]\nname = "floor"\npoints = [[0.0, 0.0, 0.0]]\nview = [0.0, 0.0, 1.0]\n')
    line = one_error_line(cli("estimate", str(tmp_path / "scene.xml"), "--estimator", "independent:single:light-area",
                              "--n", "4", "--trials", "10"))
    assert "technique light-area" in line and "no emitter triangle" in line, line
    line = one_error_line(cli("estimate", "occluded-quad", "--estimator", "independent:single:envmap", "--n", "4",
                              "--trials", "10"))
    assert "technique envmap" in line and "no environment" in line, line


@pytest.mark.parametrize(("texels", "problem"), [
    (np.ones((2, 4)), "at least 3 rows"),
    (np.full((4, 4), -1.0), "non-negative"),
    (np.full((4, 4), np.nan), "finite"),
])
def test_a_malformed_table_is_refused(texels, problem):
    env = warpis.Environment(texels=texels, rotation=np.eye(3))
    with pytest.raises(warpis.WarpisError, match=problem):
        warpis.Scene.from_arrays([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], [0.0], [[0.2, 0.2, 0.0]], [0, 0, 1],
                                 environment=env)


def test_a_scene_lit_only_by_an_environment_runs(tmp_path):
    """No emitter triangle, the sky of conftest: envmap, cosine and their MIS agree."""
    scene = warpis.Scene.from_arrays([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]],
                                     [0.0, 0.0], [[0.0, 0.0, 0.0]], [0, 0, 1], environment=sky_environment())
    means = []
    for spec in ("jittered:single:envmap", "jittered:single:cosine", "jittered:power:envmap+cosine"):
        est = run_moments(scene, spec, 16, 4000, seed=3).interval()
        means.append((float(est.mean[0]), float(est.mean_stderr[0])))
    (a, sa), (b, sb), (c, sc) = means
    assert abs(a - b) <= Z * math.hypot(sa, sb) and abs(a - c) <= Z * math.hypot(sa, sc), means


def test_the_moments_of_an_environment_scene(tmp_path):
    """The reference moments (analysis/quadrature.moments) of a scene lit by its sky
    alone: ∫ f² from the set itself (envmap + cosine, whatever lights the scene has)
    agrees with cosine sampling's own E[f²/g] within 4 combined standard errors (the
    quadrature's jackknife over 32 replicas: t tails at 31 dof, ≤ 1.5e-4).  It used to
    be light-area's E[f²/g], which a scene without emitter triangles refused, and which
    misses the sky's part of f in a scene with both."""
    from warpis.analysis.quadrature import moments

    scene = warpis.Scene.from_arrays([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]],
                                     [0.0, 0.0], [[0.0, 0.0, 0.0]], [0, 0, 1], environment=sky_environment())
    both = moments(scene, 0, ("envmap", "cosine"), sub=64)
    alone = moments(scene, 0, ("cosine",), sub=64)
    a, b = both.int_f2, alone.int_f2
    assert a.value > 0 and abs(a.value - b.value) <= Z * math.hypot(a.stderr, b.stderr), (a, b)


def test_light_techniques_alone_miss_the_environment(cli, folder, scenes):
    """On a scene lit by an envmap and a lamp, light sampling alone estimates only the
    lamp's part of F, and envmap alone misses the lamp where the map is dark: refused."""
    xml = str(folder / "scene.xml")
    line = one_error_line(cli("estimate", xml, "--estimator", "independent:single:light-solid-angle", "--n", "4",
                              "--trials", "10"))
    assert "miss the environment light" in line, line
    line = one_error_line(cli("estimate", xml, "--estimator", "independent:single:envmap", "--n", "4", "--trials",
                              "10"))
    assert "misses the emitter triangles" in line, line
    result = cli("estimate", xml, "--estimator", "independent:balance:light-solid-angle+envmap", "--n", "4",
                 "--trials", "10")
    assert result.status == 0, result.err
