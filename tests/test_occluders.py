"""Shapes whose BSDF warpis cannot shade, as occluders (warpis/scenes/mitsuba/materials.py).

Mitsuba's ``direct`` integrator traces its shadow rays with ``scene.ray_test``, which
reads no BSDF: a glass, a conductor, a ``null`` BSDF and an alpha ``mask`` of any opacity
(0 included) block them alike, and its BSDF-sampled rays stop at the first surface they
meet, so they do not pass a ``mask`` or ``null`` shape either.  warpis keeps every such
shape as an occluder only — its triangles block light and nothing reads its BSDF — and
raises the BSDF's one-line error only when a receiver lies on it; a camera pixel that
sees it is masked (``PIXEL_UNSHADED``).

The scene: a 4 × 4 diffuse floor (reflectance 0.5) at z = 0, a 1 × 1 light (radiance 10)
at z = 2 facing down, and a 0.6 × 0.6 occluder at z = 1 with each BSDF of ``OCCLUDERS``.
From a floor point (x, 0, 0) the occluder hides the part x < 0.6 − x of the light (its
shadow spans the light's whole width for |y| ≤ 0.1), so the light is hidden for
x ≤ 0.1 (umbra), partly hidden for 0.1 < x < 1.1 (penumbra), and whole for x ≥ 1.1.
The exact F is then ρ/π · Le · E of the visible rectangle of the light
(``triangle_irradiance``, the closed form of a polygon).

Tolerances: warpis's reference (``REL_ERROR`` target, 32 replicas) within Z = 4.5 of its
stderr plus 1e-6 relative (float32 vertices) of the exact value; Mitsuba's ``direct``
(``mi.render`` of a radiancemeter looking at the point, ``SEEDS`` independent renders of
``SPP`` samples, mean and the standard error of their spread: Student's t, 31 degrees
of freedom) within Z of the exact value.  A two-sided t tail at 4.5 with 31 degrees of
freedom is 8.6e-5 (the normal's at 4.5 is 6.8e-6); over the 2 × 4 comparisons the
false-failure probability is ≤ 7e-4 (Bonferroni), over the fixed seeds.  Exact checks:
the umbra is 0 on both sides; warpis's scene arrays (its digest) are the same whatever
the occluder's BSDF; Mitsuba's render with one seed is bit-for-bit the same for every
occluder BSDF; and the unshadowed point equals the scene without the occluder.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

import warpis  # noqa: E402
from conftest import one_error_line  # noqa: E402
from warpis.analysis.closed_form import triangle_irradiance  # noqa: E402
from warpis.analysis.reference import reference  # noqa: E402
from warpis.errors import WarpisError  # noqa: E402
from warpis.scenes.camera import MASK_WORDS, PIXEL_UNSHADED  # noqa: E402
from warpis.scenes.mitsuba import load_mitsuba  # noqa: E402

ALBEDO, LE = 0.5, 10.0
UMBRA = [(0.0, 0.0), (0.08, 0.05)]
PENUMBRA = [(0.3, 0.0), (0.8, 0.05)]
FULL = [(1.5, 0.0), (1.2, -0.9)]
POINTS = UMBRA + PENUMBRA + FULL
REL_ERROR = 1e-4
Z = 4.5
SEEDS, SPP = 32, 8192

OCCLUDERS = {
    "dielectric": '<bsdf type="dielectric"/>',
    "thindielectric": '<bsdf type="thindielectric"/>',
    "roughdielectric": '<bsdf type="roughdielectric"/>',
    "conductor": '<bsdf type="conductor"/>',
    "plastic": '<bsdf type="plastic"/>',
    "principled": '<bsdf type="principled"/>',
    "principledthin": '<bsdf type="principledthin"/>',
    "hair": '<bsdf type="hair"/>',  # Mitsuba cannot read back its unset sigma_a: warpis must not need it
    "null": '<bsdf type="null"/>',
    "mask": '<bsdf type="mask"><float name="opacity" value="0.3"/><bsdf type="diffuse"/></bsdf>',
    "mask-0": '<bsdf type="mask"><float name="opacity" value="0"/><bsdf type="diffuse"/></bsdf>',
    "blendbsdf": '<bsdf type="blendbsdf"><float name="weight" value="0.5"/><bsdf type="diffuse"/>'
                 '<bsdf type="dielectric"/></bsdf>',
    "twosided-two": '<bsdf type="twosided"><bsdf type="diffuse"/><bsdf type="roughconductor"/></bsdf>',
    "diffuse": '<bsdf type="diffuse"/>',  # one warpis shades: the same occluder
}

SENSOR = """<sensor type="perspective" id="cam"><float name="fov" value="60"/>
  <transform name="to_world"><lookat origin="0, -3, 4" target="0, 0, 0" up="0, 0, 1"/></transform>
  <film type="hdrfilm"><integer name="width" value="48"/><integer name="height" value="36"/></film>
</sensor>"""
METER = """<integrator type="direct"/>
<sensor type="radiancemeter">
  <point name="origin" x="{x}" y="{y_origin}" z="0.3"/><vector name="direction" x="0" y="1.5" z="-0.3"/>
  <film type="hdrfilm"><integer name="width" value="1"/><integer name="height" value="1"/><rfilter type="box"/>
    <string name="pixel_format" value="rgb"/></film>
  <sampler type="independent"><integer name="sample_count" value="{spp}"/></sampler>
</sensor>"""
FLOOR = f"""<shape type="rectangle" id="floor"><transform name="to_world"><scale value="2"/></transform>
  <bsdf type="diffuse"><rgb name="reflectance" value="{ALBEDO}"/></bsdf></shape>"""
LIGHT = f"""<shape type="rectangle" id="light">
  <transform name="to_world"><scale value="0.5"/><rotate x="1" angle="180"/><translate z="2"/></transform>
  <emitter type="area"><rgb name="radiance" value="{LE}"/></emitter></shape>"""
OCCLUDER = """<shape type="rectangle" id="glass">
  <transform name="to_world"><scale value="0.3"/><translate z="1"/></transform>{bsdf}</shape>"""


def receivers_text(points) -> str:
    return "[[receivers]]\nname = \"floor\"\npoints = [" + ", ".join(f"[{x}, {y}, 0]" for x, y in points) + "]\n"


def write(directory: Path, bsdf: str | None, receivers: str | None = None, name: str = "scene",
          sensor: str = SENSOR) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    body = FLOOR + LIGHT + ("" if bsdf is None else OCCLUDER.format(bsdf=bsdf))
    path = directory / f"{name}.xml"
    path.write_text(f'<scene version="3.0.0">\n{sensor}\n{body}\n</scene>\n')
    (directory / f"{name}.receivers.toml").write_text(receivers if receivers is not None else receivers_text(POINTS))
    return path


def exact(x: float, y: float) -> float:
    """F at the floor point (x, y, 0), |y| ≤ 0.1: the light's visible part x ≥ 0.6 − x."""
    lo = min(max(0.6 - x, -0.5), 0.5)
    if x <= 0.1 or lo >= 0.5:
        return 0.0
    # The visible rectangle of the light at z = 2, wound to face down (-z).
    quad = np.array([[lo, -0.5, 2.0], [lo, 0.5, 2.0], [0.5, 0.5, 2.0], [0.5, -0.5, 2.0]])
    tris = np.stack([quad[[0, 1, 2]], quad[[0, 2, 3]]])
    e = triangle_irradiance(np.array([[x, y, 0.0]]), np.array([[0.0, 0.0, 1.0]]), tris, np.full(2, LE))[0]
    return ALBEDO / math.pi * float(e)


def unoccluded(x: float, y: float) -> float:
    quad = np.array([[-0.5, -0.5, 2.0], [-0.5, 0.5, 2.0], [0.5, 0.5, 2.0], [0.5, -0.5, 2.0]])
    tris = np.stack([quad[[0, 1, 2]], quad[[0, 2, 3]]])
    e = triangle_irradiance(np.array([[x, y, 0.0]]), np.array([[0.0, 0.0, 1.0]]), tris, np.full(2, LE))[0]
    return ALBEDO / math.pi * float(e)


def mitsuba_direct(directory: Path, bsdf: str, x: float, y: float, seeds: int, spp: int) -> np.ndarray:
    """Mitsuba's ``direct`` integrator at the floor point (x, y, 0): one value per seed."""
    mi.set_variant("scalar_rgb")
    sensor = METER.format(x=x, y_origin=y - 1.5, spp=spp)
    path = write(directory, bsdf, name="meter", sensor=sensor)
    ms = mi.load_file(str(path), parallel=False, optimize=False)
    return np.array([float(np.array(mi.render(ms, seed=s)).reshape(-1)[0]) for s in range(seeds)])


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """warpis's reference of the scene with a diffuse occluder, and its digest."""
    path = write(tmp_path_factory.mktemp("base"), OCCLUDERS["diffuse"])
    scene = load_mitsuba(path)
    return scene, reference(scene, rel_error=REL_ERROR)


def test_exact_figures_are_consistent():
    """The visible-rectangle formula: the whole light beyond the penumbra, nothing in the umbra."""
    for x, y in FULL:
        if abs(y) <= 0.1:
            assert exact(x, y) == pytest.approx(unoccluded(x, y), rel=1e-12)
    for x, y in UMBRA:
        assert exact(x, y) == 0.0
    for x, y in PENUMBRA:
        assert 0.0 < exact(x, y) < unoccluded(x, y)


def test_warpis_reference_is_the_exact_shadow(base):
    scene, refs = base
    assert len(refs) == len(POINTS)
    for (x, y), ref in zip(POINTS, refs):
        if (x, y) in UMBRA:
            assert ref.value == 0.0, (x, y, ref)
        elif (x, y) in FULL:
            assert ref.value == pytest.approx(unoccluded(x, y), rel=1e-6), (x, y, ref)
        else:
            want = exact(x, y)
            assert abs(ref.value - want) <= Z * ref.stderr + 1e-6 * want, (x, y, ref, want)


@pytest.mark.parametrize("name", [n for n in OCCLUDERS if n != "diffuse"])
def test_any_bsdf_occludes_as_in_mitsubas_direct(name, base, tmp_path):
    """Each occluder BSDF: warpis's scene is the diffuse occluder's (so its reference is
    the one checked above), a note says it only occludes, and Mitsuba's direct render is
    bit-for-bit the diffuse occluder's at each point (0 in the umbra)."""
    scene = load_mitsuba(write(tmp_path, OCCLUDERS[name]))
    assert scene.digest == base[0].digest
    plugin = name.split("-")[0]
    assert any(n.startswith(f"glass: BSDF '{plugin}', which warpis cannot shade: an occluder only")
               for n in scene.notes), scene.notes
    for x, y in UMBRA + PENUMBRA[:1]:
        got = mitsuba_direct(tmp_path / "mine", OCCLUDERS[name], x, y, 1, 1024)
        want = mitsuba_direct(tmp_path / "diffuse", OCCLUDERS["diffuse"], x, y, 1, 1024)
        assert got[0] == want[0], (name, x, y, got, want)
        if (x, y) in UMBRA:
            assert got[0] == 0.0


@pytest.mark.parametrize("x, y", PENUMBRA + FULL[:1] + UMBRA[:1])
def test_mitsubas_direct_is_the_exact_shadow(x, y, tmp_path):
    """Mitsuba's direct render (a mask of opacity 0.3 as the occluder) against the exact F."""
    values = mitsuba_direct(tmp_path, OCCLUDERS["mask"], x, y, SEEDS, SPP)
    want = exact(x, y)
    if want == 0.0:
        assert (values == 0.0).all()
        return
    mean, se = values.mean(), values.std(ddof=1) / math.sqrt(SEEDS)
    assert abs(mean - want) <= Z * se, (x, y, mean, se, want, (mean - want) / se)


def test_without_the_occluder_unshadowed_points_are_the_same(base, tmp_path):
    scene, refs = base
    bare = load_mitsuba(write(tmp_path, None))
    bare_refs = reference(bare, rel_error=REL_ERROR)
    for i, (x, y) in enumerate(POINTS):
        if (x, y) in FULL:
            assert refs[i].value == pytest.approx(bare_refs[i].value, rel=1e-9), (x, y)
            assert refs[i].value == pytest.approx(unoccluded(x, y), rel=1e-6)
        else:
            assert bare_refs[i].value > refs[i].value


@pytest.mark.parametrize("group", [
    "[[receivers]]\nname = 'on-glass'\npoints = [[1.5, 0, 0], [0.1, 0.1, 1]]\n",
    "[[receivers]]\ngrid = { shape = 'glass', resolution = [2, 2] }\n",
], ids=["point", "grid"])
def test_a_receiver_on_the_glass_is_one_line(group, tmp_path, cli):
    path = write(tmp_path, OCCLUDERS["dielectric"], receivers=group)
    result = cli("reference", path)
    line = one_error_line(result)
    assert line.startswith(f"warpis: error: {path}: shape 'glass': BSDF 'dielectric' is not supported"), line
    assert "lies on it" in line and "scene.receivers.toml" in line, line
    # The same through the library, and for a BSDF inside twosided.
    path = write(tmp_path, OCCLUDERS["twosided-two"], receivers=group)
    with pytest.raises(WarpisError) as excinfo:
        load_mitsuba(path)
    assert str(excinfo.value).startswith(f"{path}: shape 'glass': twosided with a different BSDF on each side")


def test_camera_pixels_on_the_glass_are_masked(tmp_path, cli, monkeypatch):
    """The camera sees the glass from above: those pixels, and only those (Mitsuba's own
    first hit along each pixel's ray), are masked with the new reason, counted in the
    notes by shape and BSDF; the rest are receivers as without the glass."""
    path = write(tmp_path / "glass", OCCLUDERS["dielectric"])
    scene = load_mitsuba(path, camera=True)
    layout = scene.receivers.image
    mi.set_variant("scalar_rgb")
    ms = mi.load_file(str(path), parallel=False, optimize=False)
    cam = layout.camera
    first = np.array([ms.ray_intersect(mi.Ray3f(mi.Point3f(*cam.position), mi.Vector3f(*d))) for d in
                      cam.directions().tolist()], dtype=object)
    ids = np.array([si.shape.id() if si.is_valid() else "" for si in first]).reshape(cam.shape)
    unshaded = layout.seen == PIXEL_UNSHADED
    np.testing.assert_array_equal(unshaded, ids == "glass")
    count = int(unshaded.sum())
    assert count > 20 and layout.masked_counts()["unshaded"] == count
    assert f"{count} pixel(s) see a surface whose BSDF warpis cannot shade: masked (shape 'glass' (dielectric): " \
           f"{count})" in scene.notes, scene.notes
    assert any(n.endswith(f", {count} a surface whose BSDF warpis cannot shade") for n in scene.notes)
    assert MASK_WORDS[PIXEL_UNSHADED] == "sees a surface whose BSDF warpis cannot shade"
    # Without the glass the same pixels are receivers, the others unchanged.
    bare = load_mitsuba(write(tmp_path / "bare", None), camera=True).receivers.image
    np.testing.assert_array_equal(bare.seen[~unshaded], layout.seen[~unshaded])
    assert (bare.seen[unshaded] == 0).all()
    # `warpis image` runs over the masked pixels and reports them.
    out = tmp_path / "out"
    result = cli("image", path, "--estimator", "jittered:single:light-area", "--n", "4", "--trials", "4",
                 "--width", "24", "--height", "18", "--out", out, "--json")
    assert result.status == 0, result.err
    with np.load(out / "image.npz") as data:
        mask = data["mask"]
        assert np.isnan(data["reference"][mask != 0]).all() and np.isfinite(data["reference"][mask == 0]).all()
    import json
    meta = json.loads((out / "image.json").read_text())
    assert meta["masked"]["unshaded"] == int((mask == PIXEL_UNSHADED).sum()) > 0
    assert "sees a surface whose BSDF warpis cannot shade" in (out / "index.html").read_text()
