"""Delta lights (Mitsuba's point, spot, directional): an exact term in every estimate of F.

The scene: a floor, a box on it and a small rectangle area light, lit also by a point
light, a spot light (cutoff 25°, beam width 15°) and a directional light.  Receivers: a
point lit by every light; one in the spot's full beam, one in its falloff band and one
outside its cone; one where the box hides the point light; one where it hides the sun.

* **The term is Mitsuba's**, receiver by receiver: Σ over the delta lights of Mitsuba's
  own ``sample_direction`` weight × ``bsdf.eval`` × Mitsuba's ``ray_test`` along the
  segment (to infinity for the sun), against ``Reference.delta``: deterministic, to
  float32 rounding (1e-5 relative).  The receivers where a light is hidden, outside the
  cone or in its falloff band are asserted to be so, from Mitsuba's figures.
* **Every estimate carries it**: trials on the scene minus trials, same seed, on the scene
  without its delta lights equal the term to 1e-12 (deterministic); the reference is the
  area light's quadrature plus the term, and estimates agree with it within 4 of their
  stderr (false failure ≤ 6 × 6.3e-5).
* ``warpis info`` and the JSON show the term apart; a biased combiner is refused (its mean
  is ∫ f g of the sampled light); a malformed table is refused in one line.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

import warpis  # noqa: E402
from conftest import one_error_line  # noqa: E402
from warpis.analysis.reference import reference  # noqa: E402
from warpis.kernels.engine import run_trials  # noqa: E402
from warpis.scenes.delta import DeltaLights  # noqa: E402
from warpis.scenes.mitsuba import load_mitsuba  # noqa: E402

LIGHTS = """  <emitter type="point" id="bulb"><point name="position" x="-0.5" y="0.9" z="0.5"/>
    <rgb name="intensity" value="4, 3, 2"/></emitter>
  <emitter type="spot" id="spot">
    <transform name="to_world"><lookat origin="-1, 2, 0" target="-1, 0, 0" up="0, 0, 1"/></transform>
    <rgb name="intensity" value="20, 20, 20"/><float name="cutoff_angle" value="25"/>
    <float name="beam_width" value="15"/></emitter>
  <emitter type="directional" id="sun"><vector name="direction" x="1" y="-0.5" z="-0.2"/>
    <rgb name="irradiance" value="2, 2, 2"/></emitter>
"""
SCENE = """<scene version="3.0.0">
{lights}  <shape type="rectangle" id="floor"><transform name="to_world"><rotate x="1" angle="-90"/><scale value="3"/>
    </transform><bsdf type="diffuse"><rgb name="reflectance" value="0.6, 0.5, 0.4"/></bsdf></shape>
  <shape type="cube" id="box"><transform name="to_world"><scale value="0.2"/><translate x="0.8" y="0.2" z="0.8"/>
    </transform><bsdf type="diffuse"/></shape>
  <shape type="rectangle" id="lamp"><transform name="to_world"><rotate x="1" angle="90"/><scale value="0.3"/>
    <translate x="1" y="1.2" z="-1"/></transform><emitter type="area"><rgb name="radiance" value="5, 5, 5"/></emitter>
  </shape>
  <sensor type="perspective"><transform name="to_world"><lookat origin="0, 3, 5" target="0, 0, 0" up="0, 1, 0"/>
    </transform></sensor>
</scene>
"""
# lit by all; the spot's full beam (on its axis); its falloff band (20° off the axis);
# outside its cone (30°); the box between it and the bulb; the box between it and the sun.
POINTS = [(-0.4, 0.0, 0.1), (-1.0, 0.0, 0.0), (-1.0, 0.0, 2 * math.tan(math.radians(20))),
          (-1.0, 0.0, 2 * math.tan(math.radians(30))), "bulb", "sun"]
Z = 4.0


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    path = tmp_path_factory.mktemp("delta")
    (path / "scene.xml").write_text(SCENE.format(lights=LIGHTS))
    (path / "dark.xml").write_text(SCENE.format(lights=""))
    # A point inside the box near its top: the floor points whose rays to the sun and to the
    # bulb cross it lie in the box's shadows, beside the box (its footprint is x, z in
    # [0.6, 1.0]), where the area lamp still lights them.
    inside = np.array([0.8, 0.35, 0.8])
    sun = np.array([1.0, -0.5, -0.2]) / np.linalg.norm([1.0, -0.5, -0.2])
    bulb = inside - np.array([-0.5, 0.9, 0.5])
    behind = {"sun": inside - sun * (inside[1] / sun[1]), "bulb": inside - bulb * (inside[1] / bulb[1])}
    for p in behind.values():
        assert not (0.6 <= p[0] <= 1.0 and 0.6 <= p[2] <= 1.0), p
    points = [tuple(behind[p].tolist()) if isinstance(p, str) else p for p in POINTS]
    rows = ", ".join(f"[{x!r}, {y!r}, {z!r}]" for x, y, z in points)
    for stem in ("scene", "dark"):
        (path / f"{stem}.receivers.toml").write_text(f'channel = "g"\n[[receivers]]\nname = "floor"\npoints = [{rows}]\n')
    return path


def mitsuba_terms(xml) -> tuple[np.ndarray, np.ndarray]:
    """(R, L) each delta light's term at each receiver by Mitsuba alone, and (R, L) its
    weight (intensity × falloff / t², before the BSDF and visibility)."""
    mi.set_variant("scalar_rgb")
    ms = mi.load_file(str(xml), parallel=False, optimize=False)
    lights = [e for e in ms.emitters() if e.class_name() in ("PointLight", "SpotLight", "DirectionalEmitter")]
    scene = load_mitsuba(xml)
    camera = np.array(ms.sensors()[0].world_transform().matrix, dtype=np.float64)[:3, 3]
    ctx = mi.BSDFContext()
    terms = np.zeros((len(scene.receivers), len(lights)))
    weights = np.zeros_like(terms)
    for r, p in enumerate(scene.receivers.positions):
        view = (camera - p) / np.linalg.norm(camera - p)
        si = ms.ray_intersect(mi.Ray3f(mi.Point3f(*(p + 0.01 * view)), mi.Vector3f(*(-view))))
        for k, light in enumerate(lights):
            ds, spec = light.sample_direction(si, mi.Point2f(0.5, 0.5), False)
            weights[r, k] = spec[1]
            length = min(ds.dist, 1e4) * (1 - 1e-6) - 1e-5
            free = not ms.ray_test(mi.Ray3f(si.p + 1e-5 * ds.d, ds.d, length, 0.0, mi.Color0f()))
            terms[r, k] = spec[1] * si.bsdf().eval(ctx, si, si.to_local(ds.d))[1] * free
    return terms, weights


def test_delta_terms_are_mitsubas(folder):
    scene = load_mitsuba(folder / "scene.xml")
    terms, weights = mitsuba_terms(folder / "scene.xml")
    bulb, spot, sun = range(3)
    assert np.all(terms[0] > 0)  # lit by all three
    cone = weights[1:4, spot]
    falloff = cone[1] * (2 / math.cos(math.radians(20))) ** 2 / 20.0  # weight × t² / intensity
    assert cone[0] == pytest.approx(20.0 / 4) and 0.01 < falloff < 0.99, (cone, falloff)  # in the falloff band
    assert cone[2] == 0  # outside the cone
    assert terms[4, bulb] == 0 < weights[4, bulb] and terms[5, sun] == 0 < weights[5, sun]  # the box hides them
    assert terms[4, sun] > 0  # the bulb's shadow is in the sun
    refs = reference(scene, closed_form=False)
    mine = np.array([ref.delta for ref in refs])
    assert refs[4].value - refs[4].delta > 0 and refs[5].value - refs[5].delta > 0  # the lamp still lights them
    np.testing.assert_allclose(mine, terms.sum(axis=1), rtol=1e-5, atol=1e-7)


def test_estimates_carry_the_term(folder):
    lit, dark = load_mitsuba(folder / "scene.xml"), load_mitsuba(folder / "dark.xml")
    spec, n, trials = "jittered:balance:light-solid-angle+cosine", 8, 4000
    a = run_trials(lit, spec, n, trials, seed=5)
    b = run_trials(dark, spec, n, trials, seed=5)
    delta = np.array([ref.delta for ref in reference(lit, closed_form=False)])
    np.testing.assert_allclose(a - b, np.repeat(delta[:, None], trials, axis=1), rtol=0, atol=1e-12)
    refs = reference(lit, rel_error=1e-3)
    for r, ref in enumerate(refs):
        se = math.hypot(a[r].std(ddof=1) / math.sqrt(trials), ref.stderr)
        assert abs(a[r].mean() - ref.value) <= Z * se + 1e-12, (r, a[r].mean(), ref)


def test_info_and_json_show_the_term(cli, folder):
    result = cli("info", str(folder / "scene.xml"), "--json")
    assert result.status == 0, result.err
    data = json.loads(result.out)["delta_lights"]
    assert [d["kind"] for d in data] == ["point", "spot", "directional"]
    assert data[1]["irradiance_min"] == 0.0 and data[2]["irradiance_max"] == pytest.approx(2.0)
    text = cli("info", str(folder / "scene.xml")).out
    assert "delta light spot (spot): irradiance 0 to" in text
    refs = json.loads(cli("reference", str(folder / "scene.xml"), "--rel-error", "0.01", "--json").out)["receivers"]
    assert refs[0]["delta"] > 0 and refs[0]["value"] > refs[0]["delta"]


def test_a_biased_combiner_is_refused(cli, folder):
    line = one_error_line(cli("estimate", str(folder / "scene.xml"), "--estimator", "independent:biased:cosine",
                              "--n", "4", "--trials", "10"))
    assert "delta lights" in line and "unbiased combiner" in line, line


@pytest.mark.parametrize(("change", "problem"), [
    ({"distances": np.full((1, 1), -1.0)}, "distances must be > 0"),
    ({"irradiance": np.full((1, 1), np.nan)}, "irradiance must be finite"),
    ({"directions": np.zeros((1, 1, 3))}, "unit vectors"),
    ({"kinds": ("laser",)}, "kinds must be one of"),
    ({"irradiance": np.ones((2, 1))}, "expected directions"),
])
def test_a_malformed_table_is_refused(change, problem):
    table = dict(labels=("bulb",), kinds=("point",), directions=np.array([[[0.0, 0.0, 1.0]]]),
                 distances=np.ones((1, 1)), irradiance=np.ones((1, 1)))
    table.update(change)
    with pytest.raises(warpis.WarpisError, match=problem):
        warpis.Scene.from_arrays([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], [0.0], [[0.2, 0.2, 0.0]], [0, 0, 1],
                                 delta_lights=DeltaLights(**table))
