"""Textured BSDF parameters on Mitsuba receivers (warpis/scenes/mitsuba/materials.py, receivers.py).

A texture on a receiver's diffuse ``reflectance``, roughplastic ``diffuse_reflectance``
or ``specular_reflectance``, or roughconductor ``specular_reflectance`` or ``alpha`` is
one value at the receiver's own point: warpis asks Mitsuba for it (the surface
interaction of a short ray at the point against the receiver's own shape, then the
texture's ``eval``/``eval_1`` there), so the receiver's BSDF is Mitsuba's there exactly.

Checked here, against Mitsuba (``scalar_rgb``) itself:

* per receiver, warpis's albedo (and specular, alpha) is Mitsuba's texture value at the
  point — ``bsdf.eval_diffuse_reflectance`` at Mitsuba's own hit from above, weighted by
  the channel — to float32 precision (1e-6), on a checkerboard floor (both colours), a
  bitmap roughplastic and a bitmap roughconductor (specular and alpha), for points,
  grids and camera pixels;
* f at the receivers of the bitmap materials: ``evaluate_integrand`` against Mitsuba's
  Le × ``bsdf.eval`` in directions its emitter sampling draws, and the ``bsdf``
  technique's density against ``bsdf.pdf`` there: relative error ≤ 1e-4;
* F against Mitsuba's ``direct`` integrator (``mi.render`` of a radiancemeter looking at
  each point from the receiver's viewer; ``SEEDS`` renders of ``SPP`` samples, mean and
  the standard error of their spread, 31 degrees of freedom) within Z = 4.5 combined
  standard errors (warpis's reference at ``REL_ERROR``, 32 replicas).  A two-sided t
  tail at 4.5 with 31 degrees of freedom is 8.6e-5; over the 8 comparisons (2 on the
  checkerboard, 3 on each bitmap material) the false-failure probability is ≤ 6.9e-4
  (Bonferroni), over the fixed seeds;
* a texture warpis cannot take (on an emitter's radiance, on a conductor's eta, an
  anisotropic alpha at the point, a value out of range) is one line, exit 2.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from conftest import one_error_line  # noqa: E402
from warpis.analysis.reference import reference  # noqa: E402
from warpis.errors import WarpisError  # noqa: E402
from warpis.kernels.integrand import evaluate_integrand  # noqa: E402
from warpis.kernels.techniques import direction_pdf  # noqa: E402
from warpis.scenes.mitsuba import CHANNELS, load_mitsuba  # noqa: E402

REL_ERROR = 2e-4
Z = 4.5
SEEDS, SPP = 32, 4096
F_RTOL = 1e-4
EXACT = 1e-6  # float32 texture values against float64 weights

SENSOR = """<sensor type="perspective" id="cam"><float name="fov" value="60"/>
  <transform name="to_world"><lookat origin="0, -3, 4" target="0, 0, 0" up="0, 0, 1"/></transform>
  <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="18"/></film>
</sensor>"""
METER = """<integrator type="direct"/>
<sensor type="radiancemeter">
  <point name="origin" x="{o[0]}" y="{o[1]}" z="{o[2]}"/><vector name="direction" x="{d[0]}" y="{d[1]}" z="{d[2]}"/>
  <film type="hdrfilm"><integer name="width" value="1"/><integer name="height" value="1"/><rfilter type="box"/>
    <string name="pixel_format" value="rgb"/></film>
  <sampler type="independent"><integer name="sample_count" value="{spp}"/></sampler>
</sensor>"""
LIGHT = """<shape type="rectangle" id="light">
  <transform name="to_world"><scale value="0.5"/><rotate x="1" angle="160"/><translate x="0.3" z="1.5"/></transform>
  <emitter type="area"><rgb name="radiance" value="6, 8, 10"/></emitter></shape>"""
CHECKER = """<bsdf type="diffuse"><texture type="checkerboard" name="reflectance">
  <rgb name="color0" value="0.1, 0.2, 0.3"/><rgb name="color1" value="0.7, 0.6, 0.5"/></texture></bsdf>"""
# Points on both colours of the checker (the rectangle's uv is (x/4 + 1/2, y/4 + 1/2)).
CHECK_POINTS = [(0.3, 0.2), (-0.6, 0.1), (0.9, -0.7), (-0.3, -0.4)]


def floor_shape(bsdf: str, shape: str = "rectangle", extra: str = "") -> str:
    return (f'<shape type="{shape}" id="floor">{extra}<transform name="to_world"><scale value="2"/></transform>'
            f'{bsdf}</shape>')


def viewer(x: float, y: float) -> np.ndarray:
    return np.array([x - 0.8, y - 1.1, 1.3])


def receivers_text(points, channel: str = "y") -> str:
    """One group per point, each seen from its own viewer (where the meter sits)."""
    out = f'channel = "{channel}"\n'
    for i, (x, y) in enumerate(points):
        v = viewer(x, y)
        out += f'[[receivers]]\nname = "p{i}"\npoints = [[{x}, {y}, 0]]\nview = [{v[0]}, {v[1]}, {v[2]}]\n'
    return out


def write(directory: Path, body: str, receivers: str, name: str = "scene", sensor: str = SENSOR) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{name}.xml"
    path.write_text(f'<scene version="3.0.0">\n{sensor}\n{body}\n</scene>\n')
    (directory / f"{name}.receivers.toml").write_text(receivers)
    return path


def bitmap(directory: Path, name: str, pixels: np.ndarray) -> Path:
    """A small float EXR written by Mitsuba (H × W × channels)."""
    mi.set_variant("scalar_rgb")
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / name
    mi.Bitmap(np.ascontiguousarray(pixels, dtype=np.float32)).write(str(path))
    return path


def mitsuba_si(ms, x: float, y: float):
    """Mitsuba's own surface interaction at the floor point (x, y, 0), from above."""
    si = ms.ray_intersect(mi.Ray3f(mi.Point3f(x, y, 0.01), mi.Vector3f(0.0, 0.0, -1.0)))
    assert si.is_valid() and si.shape.id() == "floor"
    return si


def load_ms(path: Path):
    mi.set_variant("scalar_rgb")
    return mi.load_file(str(path), parallel=False, optimize=False)


def mitsuba_direct(directory: Path, body: str, x: float, y: float) -> tuple[float, float, np.ndarray]:
    """Mitsuba's direct integrator at (x, y, 0) seen from viewer(x, y): mean, stderr (RGB)."""
    o = viewer(x, y)
    d = np.array([x, y, 0.0]) - o
    path = write(directory, body, receivers_text([(x, y)]), name=f"meter-{x}-{y}",
                 sensor=METER.format(o=o.tolist(), d=d.tolist(), spp=SPP))
    ms = load_ms(path)
    values = np.array([np.array(mi.render(ms, seed=s), np.float64).reshape(-1)[:3] for s in range(SEEDS)])
    return values.mean(axis=0), values.std(axis=0, ddof=1) / math.sqrt(SEEDS), values


@pytest.fixture(scope="module")
def checker(tmp_path_factory):
    directory = tmp_path_factory.mktemp("checker")
    body = floor_shape(CHECKER) + LIGHT
    return directory, body, write(directory, body, receivers_text(CHECK_POINTS))


@pytest.mark.parametrize("channel", ["y", "r"])
def test_checkerboard_albedo_is_mitsubas_texture_at_each_point(checker, channel):
    directory, body, path = checker
    scene = load_mitsuba(path, channel=channel)
    ms = load_ms(path)
    weights = np.array(CHANNELS[channel])
    want = []
    for x, y in CHECK_POINTS:
        si = mitsuba_si(ms, x, y)
        want.append(float(weights @ np.array(ms.shapes()[0].bsdf().eval_diffuse_reflectance(si), np.float64)))
    np.testing.assert_allclose(scene.receivers.albedo, want, rtol=EXACT)
    colours = {round(v, 5) for v in want}
    assert len(colours) == 2, want  # both colours of the checker
    assert any("floor: 4 receiver(s) take its diffuse reflectance from its 'checkerboard' texture" in n
               for n in scene.notes), scene.notes
    if channel == "y":  # coloured light on a coloured texture: the luminance caveat applies
        assert any(n.startswith("channel y multiplies the luminance") for n in scene.notes)


def test_checkerboard_floor_matches_mitsubas_direct(checker, tmp_path):
    directory, body, path = checker
    scene = load_mitsuba(path, channel="g")
    refs = reference(scene, rel_error=REL_ERROR)
    for i, (x, y) in enumerate(CHECK_POINTS[:2]):
        mean, se, _ = mitsuba_direct(directory, body, x, y)
        z = (refs[i].value - mean[1]) / math.hypot(refs[i].stderr, se[1])
        assert abs(z) <= Z, (x, y, refs[i], mean[1], se[1], z)


@pytest.fixture(scope="module")
def bitmaps(tmp_path_factory):
    """A roughplastic floor with a bitmap diffuse_reflectance, and a roughconductor one
    with a bitmap specular_reflectance and a one-channel bitmap alpha."""
    directory = tmp_path_factory.mktemp("bitmaps")
    bitmap(directory, "colour.exr", np.array([[[0.1, 0.2, 0.3], [0.9, 0.8, 0.7]], [[0.5, 0.4, 0.6], [0.0, 1.0, 0.2]]]))
    bitmap(directory, "rough.exr", np.array([[[0.08], [0.4]], [[0.25], [0.15]]]))
    plastic = ('<bsdf type="roughplastic"><float name="alpha" value="0.3"/><string name="distribution" value="ggx"/>'
               '<texture type="bitmap" name="diffuse_reflectance"><string name="filename" value="colour.exr"/>'
               '</texture></bsdf>')
    conductor = ('<bsdf type="roughconductor"><string name="distribution" value="ggx"/><string name="material" '
                 'value="Cu"/><texture type="bitmap" name="specular_reflectance"><string name="filename" '
                 'value="colour.exr"/></texture><texture type="bitmap" name="alpha"><string name="filename" '
                 'value="rough.exr"/></texture></bsdf>')
    points = [(0.3, 0.2), (-0.6, 0.1), (0.9, -0.7)]
    out = {}
    for name, bsdf in (("plastic", plastic), ("conductor", conductor)):
        body = floor_shape(bsdf) + LIGHT
        out[name] = (directory, body, write(directory, body, receivers_text(points, "g"), name=name), points)
    return out


@pytest.mark.parametrize("material", ["plastic", "conductor"])
def test_bitmap_parameters_and_f_are_mitsubas(bitmaps, material):
    directory, body, path, points = bitmaps[material]
    scene = load_mitsuba(path)
    ms = load_ms(path)
    bsdf = ms.shapes()[0].bsdf()
    rx = scene.receivers
    ctx = mi.BSDFContext()
    worst = 0.0
    for i, (x, y) in enumerate(points):
        si = mitsuba_si(ms, x, y)
        v = viewer(x, y) - np.array([x, y, 0.0])
        si.wi = si.to_local(mi.Vector3f(*(v / np.linalg.norm(v))))
        if material == "plastic":
            assert rx.albedo[i] == pytest.approx(float(bsdf.eval_diffuse_reflectance(si)[1]), rel=EXACT)
        dirs, ref = [], []
        for a, b in np.random.default_rng(7 + i).random((256, 2)).tolist():
            ds, spec = ms.sample_emitter_direction(si, mi.Point2f(a, b), False)
            if spec[1] > 0:
                dirs.append(np.array(ds.d, np.float64))
                ref.append(spec[1] * ds.pdf * bsdf.eval(ctx, si, si.to_local(ds.d))[1])
        f = evaluate_integrand(scene, i, np.array(dirs))
        rel = np.abs(f - np.array(ref)) / np.abs(np.array(ref))
        assert rel.max() <= F_RTOL, (material, i, float(rel.max()))
        worst = max(worst, float(rel.max()))
        # The bsdf technique's density is Mitsuba's bsdf.pdf (for roughplastic, its lobe
        # choice from the texture's mean, as Mitsuba's specular_sampling_weight).
        world = np.array(dirs, np.float32)
        pdf = direction_pdf(scene, i, "bsdf", world)
        want = np.array([bsdf.pdf(ctx, si, si.to_local(mi.Vector3f(*d))) for d in world.tolist()])
        np.testing.assert_allclose(pdf, want, rtol=F_RTOL, err_msg=f"{material} {i}")
    if material == "conductor":
        assert len(set(np.round(rx.alpha, 6))) == len(points) and (rx.alpha > 0.08 - 1e-6).all()
        assert len(set(np.round(rx.specular[:, 1], 6))) == len(points)


@pytest.mark.parametrize("material", ["plastic", "conductor"])
def test_bitmap_materials_match_mitsubas_direct(bitmaps, material):
    directory, body, path, points = bitmaps[material]
    scene = load_mitsuba(path)
    refs = reference(scene, rel_error=REL_ERROR)
    for i, (x, y) in enumerate(points):
        mean, se, _ = mitsuba_direct(directory, body, x, y)
        z = (refs[i].value - mean[1]) / math.hypot(refs[i].stderr, se[1])
        assert abs(z) <= Z, (x, y, refs[i], mean[1], se[1], z)


def test_grid_and_camera_pixels_take_the_texture_at_their_own_point(checker, tmp_path):
    directory, body, path = checker
    ms = load_ms(path)
    bsdf = ms.shapes()[0].bsdf()
    weights = np.array(CHANNELS["y"])
    grid = write(tmp_path, body, "[[receivers]]\ngrid = { shape = 'floor', resolution = [5, 4] }\n", name="grid")
    for scene in (load_mitsuba(grid), load_mitsuba(path, camera=True)):
        rx = scene.receivers
        want = [float(weights @ np.array(bsdf.eval_diffuse_reflectance(mitsuba_si(ms, p[0], p[1])), np.float64))
                for p in rx.positions.tolist()]
        np.testing.assert_allclose(rx.albedo, want, rtol=EXACT)
        assert len({round(v, 5) for v in want}) == 2
    # A textured sphere: the ray meets Mitsuba's sphere, not the tessellation.
    sphere = ('<shape type="sphere" id="ball"><point name="center" x="0" y="0" z="0.6"/><float name="radius" '
              'value="0.5"/>' + CHECKER + '</shape>')
    ball = write(tmp_path, floor_shape('<bsdf type="diffuse"/>') + LIGHT + sphere,
                 "[[receivers]]\npoints = [[0, -0.3, 1.0], [0.3, -0.24, 0.92], [-0.14, -0.48, 0.6]]\n",
                 name="ball")
    scene = load_mitsuba(ball)
    mb = load_ms(ball)
    (shape,) = [s for s in mb.shapes() if s.id() == "ball"]
    for i, p in enumerate(scene.receivers.positions.tolist()):
        n = np.array(p) - np.array([0, 0, 0.6])
        n /= np.linalg.norm(n)
        si = shape.ray_intersect(mi.Ray3f(mi.Point3f(*(np.array(p) + 0.1 * n)), mi.Vector3f(*(-n))))
        want = float(weights @ np.array(shape.bsdf().eval_diffuse_reflectance(si), np.float64))
        assert scene.receivers.albedo[i] == pytest.approx(want, rel=EXACT)


@pytest.mark.parametrize("body, words", [
    (floor_shape('<bsdf type="diffuse"/>') + '<shape type="rectangle" id="tex-light"><transform name="to_world">'
     '<rotate x="1" angle="180"/><translate z="1.5"/></transform><emitter type="area"><texture type="checkerboard" '
     'name="radiance"/></emitter></shape>', "shape 'tex-light': area emitter: its radiance is a 'checkerboard' texture"),
    (floor_shape('<bsdf type="roughconductor"><texture type="checkerboard" name="eta"/></bsdf>') + LIGHT,
     "shape 'floor': roughconductor: its eta is a 'checkerboard' texture"),
    (floor_shape('<bsdf type="roughconductor"><texture type="checkerboard" name="alpha_u"/>'
                 '<float name="alpha_v" value="0.3"/></bsdf>') + LIGHT,
     "roughconductor alpha_u=0.2, alpha_v=0.3 at (0.3, 0.2, 0) (anisotropic)"),
    (floor_shape('<bsdf type="diffuse"><texture type="bitmap" name="reflectance"><string name="filename" '
                 'value="negative.exr"/><string name="filter_type" value="nearest"/></texture></bsdf>') + LIGHT,
     "its diffuse reflectance texture is (-0.5, 0.25, 0.5) at (0.3, 0.2, 0); warpis supports reflectances in"),
    (floor_shape('<bsdf type="roughconductor"><texture type="checkerboard" name="alpha"><float name="color1" '
                 'value="0"/></texture></bsdf>') + LIGHT, "its alpha texture is 0 at (0.3, 0.2, 0); warpis supports roughness in"),
], ids=["textured-emitter", "textured-eta", "anisotropic", "negative", "zero-alpha"])
def test_textures_warpis_cannot_take_are_one_line(body, words, tmp_path, cli):
    bitmap(tmp_path, "negative.exr", np.full((2, 2, 3), [-0.5, 0.25, 0.5]))
    path = write(tmp_path, body, receivers_text([(0.3, 0.2)]))
    line = one_error_line(cli("reference", path))
    assert words in line, line
    with pytest.raises(WarpisError) as excinfo:
        load_mitsuba(path)
    assert "\n" not in str(excinfo.value)


def test_a_textured_occluder_needs_no_evaluation(tmp_path):
    """A textured shape without receivers is an occluder whatever its texture."""
    body = (floor_shape('<bsdf type="diffuse"/>') + LIGHT + '<shape type="rectangle" id="board"><transform '
            'name="to_world"><scale value="0.2"/><translate z="0.7"/></transform><bsdf type="roughconductor">'
            '<texture type="checkerboard" name="eta"/></bsdf></shape>')
    scene = load_mitsuba(write(tmp_path, body, receivers_text([(0.3, 0.2)])))
    assert len(scene.receivers) == 1


def test_a_textured_mesh_and_a_twosided_texture(tmp_path):
    """An OBJ with texture coordinates (each receiver's own triangle gives Mitsuba's uv) and
    a checkerboard inside twosided, seen from below: Mitsuba's value at each point."""
    (tmp_path / "quad.obj").write_text(
        "v -2 -2 0\nv 2 -2 0\nv 2 2 0\nv -2 2 0\nvt 0 0\nvt 3 0\nvt 3 1.5\nvt 0 1.5\n"
        "f 1/1 2/2 3/3\nf 1/1 3/3 4/4\n")
    points = [(0.3, 0.2), (-0.6, 0.1), (0.9, -0.7), (-1.3, 1.1), (1.7, 0.4)]
    body = floor_shape(CHECKER, shape="obj", extra='<string name="filename" value="quad.obj"/>') + LIGHT
    path = write(tmp_path, body.replace('<scale value="2"/>', '<scale value="1"/>'), receivers_text(points))
    scene = load_mitsuba(path)
    ms = load_ms(path)
    weights = np.array(CHANNELS["y"])
    want = [float(weights @ np.array(ms.shapes()[0].bsdf().eval_diffuse_reflectance(mitsuba_si(ms, x, y)),
                                     np.float64)) for x, y in points]
    np.testing.assert_allclose(scene.receivers.albedo, want, rtol=EXACT)
    assert len({round(v, 5) for v in want}) == 2
    # twosided, the viewer below the floor: the same texture values.
    two = body.replace(CHECKER, f'<bsdf type="twosided">{CHECKER}</bsdf>').replace('<scale value="2"/>',
                                                                                  '<scale value="1"/>')
    below = "".join(f"[[receivers]]\npoints = [[{x}, {y}, 0]]\nview = [{x}, {y}, -1]\n" for x, y in points)
    flipped = load_mitsuba(write(tmp_path, two, below, name="two"))
    np.testing.assert_allclose(flipped.receivers.albedo, want, rtol=EXACT)
    assert (flipped.receivers.normals[:, 2] < 0).all()
