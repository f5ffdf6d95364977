"""Tests of the Mitsuba 3 scene source (warpis/scenes/mitsuba/).

Small XML scenes are written into tmp_path (two meshes live in tests/data/mitsuba/) and
loaded both by warpis and by Mitsuba itself, which is the reference for what each
element means:

* geometry: every shape type, transforms and flip_normals; the front side of each
  warpis triangle (counter-clockwise winding) is checked against Mitsuba's own hit
  normal and area-light emission by casting rays at it from both sides;
* emission and colour: rgb and spectral radiance and reflectance in each channel,
  against Mitsuba's emitter.eval and bsdf.eval;
* analytic emitters: tessellated area and irradiance within TESSELLATION_ERROR of the
  closed forms, and the figures in Scene.notes;
* BSDFs: roughconductor and roughplastic parameters read back exactly, twosided;
* receivers: points, normals, grids, viewers and the material under each point;
* every bad input gives one line naming the file and the element.
"""

from __future__ import annotations

import math
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

mi = pytest.importorskip("mitsuba")

import warpis  # noqa: E402
from warpis.analysis.closed_form import triangle_irradiance  # noqa: E402
from warpis.errors import WarpisError  # noqa: E402
from warpis.kernels.integrand import MATERIALS  # noqa: E402
from warpis.kernels.shading import DISTRIBUTIONS  # noqa: E402
from warpis.scenes import resolve_scene_path  # noqa: E402
from warpis.scenes.mitsuba import CHANNELS, TESSELLATION_ERROR, load_mitsuba  # noqa: E402

DATA = Path(__file__).parent / "data" / "mitsuba"
Y = np.array(CHANNELS["y"])

SENSOR = """<sensor type="perspective" id="cam">
  <transform name="to_world"><lookat origin="0, 0, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
</sensor>"""
FLOOR = """<shape type="rectangle" id="floor">
  <transform name="to_world"><scale value="2"/></transform>
  <bsdf type="diffuse"><rgb name="reflectance" value="0.2, 0.5, 0.8"/></bsdf>
</shape>"""
# A 1 x 1 light at z = 2 facing down (a rectangle's normal is +z; rotated about x).
LIGHT = """<shape type="rectangle" id="light">
  <transform name="to_world"><scale value="0.5"/><rotate x="1" angle="180"/><translate z="2"/></transform>
  <emitter type="area"><rgb name="radiance" value="{radiance}"/></emitter>
</shape>"""
ONE_POINT = """[[receivers]]
name = "centre"
points = [[0, 0, 0]]
"""


def write(directory: Path, body: str, receivers: str | None = ONE_POINT, name: str = "scene",
          sensor: bool = True) -> Path:
    """Write ``<name>.xml`` (a scene holding ``body``) and its receivers file."""
    path = directory / f"{name}.xml"
    path.write_text(f'<scene version="3.0.0">\n{SENSOR if sensor else ""}\n{body}\n</scene>\n')
    if receivers is not None:
        (directory / f"{name}.receivers.toml").write_text(receivers)
    return path


def light(radiance: str = "10") -> str:
    return LIGHT.format(radiance=radiance)


def mitsuba_scene(path: Path):
    mi.set_variant("scalar_rgb")
    return mi.load_file(str(path), parallel=False, optimize=False)


def mesh_triangles(scene: warpis.Scene, label: str) -> np.ndarray:
    return np.flatnonzero(scene.triangle_mesh == scene.mesh_names.index(label))


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def check_fronts(path: Path, scene: warpis.Scene, label: str, count: int = 12) -> None:
    """Rays at triangles of shape ``label`` from both sides: Mitsuba's shading normal is
    on warpis's front side, and an emitter emits on the front side only."""
    ms = mitsuba_scene(path)
    ids = mesh_triangles(scene, label)
    pick = ids[np.unique(np.linspace(0, len(ids) - 1, count).astype(int))]
    tris = scene.triangle_vertices(pick)
    centres = tris.mean(axis=1)
    normals = unit(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]))
    size = np.linalg.norm(np.ptp(scene.triangle_vertices(ids).reshape(-1, 3), axis=0))
    emitter = bool(scene.emission[ids[0]] > 0)
    for c, n in zip(centres, normals):
        for side in (1.0, -1.0):
            origin = c + side * 0.02 * size * n
            si = ms.ray_intersect(mi.Ray3f(mi.Point3f(*origin), mi.Vector3f(*(-side * n))))
            assert si.is_valid() and si.shape.id() == label, (label, c, side)
            # Mitsuba's shading normal (smooth on a mesh with shared vertices) on warpis's front side.
            assert np.dot(np.array(si.sh_frame.n), n) > 0.5, (label, c, np.array(si.sh_frame.n), n)
            if emitter:
                radiance = np.array(si.emitter(ms).eval(si))
                assert (radiance.max() > 0) == (side > 0), (label, c, side, radiance)


def one_line(excinfo: pytest.ExceptionInfo, path: Path, *parts: str) -> str:
    message = str(excinfo.value)
    assert "\n" not in message, message
    assert message.startswith(str(path)), message
    for part in parts:
        assert part in message, (part, message)
    return message


def note(scene: warpis.Scene, pattern: str) -> re.Match:
    for line in scene.notes:
        found = re.search(pattern, line)
        if found:
            return found
    raise AssertionError(f"no note matches {pattern!r}: {scene.notes}")


# ----------------------------------------------------------------------------- scenes and geometry


def test_quad_light_over_diffuse_floor(tmp_path):
    path = write(tmp_path, FLOOR + light("1, 2, 3"))
    scene = load_mitsuba(path)
    assert scene.mesh_names == ["floor", "light"]
    assert scene.name == tmp_path.name and scene.path == path  # scene.xml: named after its folder
    assert scene.triangle_count == 4 and scene.emitter_count == 2
    np.testing.assert_allclose(scene.emitter_radiance, Y @ [1, 2, 3])
    assert scene.total_emitter_area == pytest.approx(1.0)
    floor = scene.triangle_vertices(mesh_triangles(scene, "floor")).reshape(-1, 3)
    np.testing.assert_allclose(np.abs(floor[:, :2]), 2.0)
    # The light faces down: the floor's centre sees the closed form of a 1 x 1 square at height 2.
    expected = np.array([[[-0.5, -0.5, 2], [0.5, 0.5, 2], [0.5, -0.5, 2]],
                         [[-0.5, -0.5, 2], [-0.5, 0.5, 2], [0.5, 0.5, 2]]])
    got = triangle_irradiance(np.zeros((1, 3)), np.array([[0, 0, 1.0]]), scene.triangle_vertices(scene.emitters),
                              scene.emitter_radiance)
    want = triangle_irradiance(np.zeros((1, 3)), np.array([[0, 0, 1.0]]), expected, np.full(2, Y @ [1, 2, 3]))
    assert got[0] == pytest.approx(want[0], rel=1e-12) and got[0] > 0
    rx = scene.receivers
    assert rx.material_name(0) == "lambert"
    assert rx.albedo[0] == pytest.approx(Y @ np.float32([0.2, 0.5, 0.8]), rel=1e-7)
    np.testing.assert_allclose(rx.normals[0], [0, 0, 1])
    np.testing.assert_allclose(rx.view[0], [0, 0, 1])
    assert rx.group_names == ["centre"]
    for label in ("floor", "light"):
        check_fronts(path, scene, label)
    assert any("colour channel y" in line for line in scene.notes)
    note(scene, r"^floor: diffuse albedo=0\.45")


def test_lambert_albedo_matches_mitsubas_bsdf_eval(tmp_path):
    path = write(tmp_path, FLOOR + light())
    ms = mitsuba_scene(path)
    si = ms.ray_intersect(mi.Ray3f(mi.Point3f(0.3, 0.2, 1.0), mi.Vector3f(0, 0, -1)))
    assert si.shape.id() == "floor"
    wo = unit(np.array([0.3, -0.2, 0.8]))
    value = np.array(si.bsdf().eval(mi.BSDFContext(), si, mi.Vector3f(*wo)))
    for channel, weights in CHANNELS.items():
        albedo = load_mitsuba(path, channel=channel).receivers.albedo[0]
        assert albedo / math.pi * wo[2] == pytest.approx(np.dot(weights, value), rel=1e-6)


def test_shape_order_and_digest_are_stable(tmp_path):
    body = "".join(f'<shape type="rectangle" id="r{i}"><transform name="to_world"><translate x="{3 * i}" z="-1"/>'
                   f'</transform></shape><shape type="cube" id="c{i}"><transform name="to_world">'
                   f'<scale value="0.2"/><translate x="{3 * i}" y="3"/></transform></shape>' for i in range(6))
    path = write(tmp_path, FLOOR + light() + body)
    first = load_mitsuba(path)
    assert first.mesh_names == ["floor", "light"] + [f"{k}{i}" for i in range(6) for k in "rc"]
    assert all(load_mitsuba(path).digest == first.digest for _ in range(3))


def test_meshes_obj_ply_cube_and_their_fronts(tmp_path):
    box = trimesh.creation.box(extents=(0.4, 0.4, 0.4))
    box.apply_translation([1.2, 0.0, 0.5])
    box.export(tmp_path / "box.ply")
    body = (f'<shape type="obj" id="plate"><string name="filename" value="{DATA / "plate.obj"}"/>'
            f'<transform name="to_world"><translate x="-0.3" y="0.5" z="0.5"/></transform></shape>'
            f'<shape type="ply" id="box"><string name="filename" value="box.ply"/></shape>'
            f'<shape type="cube" id="cube"><transform name="to_world"><scale value="0.2"/>'
            f'<rotate z="1" angle="30"/><translate x="-1.2" y="-1" z="0.5"/></transform></shape>')
    path = write(tmp_path, FLOOR + light() + body)
    scene = load_mitsuba(path)
    assert scene.mesh_names == ["floor", "light", "plate", "box", "cube"]
    plate = scene.triangle_vertices(mesh_triangles(scene, "plate")).reshape(-1, 3)
    np.testing.assert_allclose(plate.min(axis=0), [-1.8, 0.0, 0.5], atol=1e-6)
    np.testing.assert_allclose(plate.max(axis=0), [1.2, 1.0, 0.5], atol=1e-6)
    ply = scene.triangle_vertices(mesh_triangles(scene, "box")).reshape(-1, 3)
    np.testing.assert_allclose(np.sort(np.unique(ply.round(6), axis=0), axis=0),
                               np.sort(np.unique(box.vertices.round(6), axis=0), axis=0), atol=1e-6)
    assert len(mesh_triangles(scene, "cube")) == 12
    for label in ("plate", "box", "cube"):
        check_fronts(path, scene, label)


def test_transforms_flip_normals_and_vertex_normals_decide_the_front(tmp_path):
    em = '<emitter type="area"><rgb name="radiance" value="2"/></emitter>'
    body = (
        # A mirror: Mitsuba's rectangle normal follows the inverse transpose, not the winding.
        f'<shape type="rectangle" id="mirrored"><transform name="to_world"><scale x="-0.3" y="0.3"/>'
        f'<translate x="-1" z="1"/></transform>{em}</shape>'
        f'<shape type="rectangle" id="flipped"><boolean name="flip_normals" value="true"/>'
        f'<transform name="to_world"><scale value="0.3"/><rotate y="1" angle="30"/><translate x="1" z="1"/>'
        f'</transform>{em}</shape>'
        # Vertex normals against the winding: Mitsuba emits on the normals' side.
        f'<shape type="obj" id="reversed"><string name="filename" value="{DATA / "reversed-normals.obj"}"/>'
        f'<transform name="to_world"><translate y="1.2" z="1.5"/></transform>{em}</shape>'
        f'<shape type="obj" id="reversed-flipped"><string name="filename" value="{DATA / "reversed-normals.obj"}"/>'
        f'<boolean name="flip_normals" value="true"/>'
        f'<transform name="to_world"><translate y="-1.2" z="1.5"/></transform>{em}</shape>'
        f'<shape type="obj" id="plate-mirrored"><string name="filename" value="{DATA / "plate.obj"}"/>'
        f'<transform name="to_world"><scale x="-0.3" y="0.3"/><translate y="1" z="0.5"/></transform></shape>'
        f'<shape type="disk" id="disk-mirrored"><transform name="to_world"><scale x="-0.3" y="0.3" z="-1"/>'
        f'<translate x="1.5" y="-1.5" z="0.7"/></transform>{em}</shape>'
    )
    path = write(tmp_path, FLOOR + light() + body)
    scene = load_mitsuba(path)
    for label in ("mirrored", "flipped", "reversed", "reversed-flipped", "plate-mirrored", "disk-mirrored"):
        check_fronts(path, scene, label)
    front = {label: unit(np.cross(*np.diff(scene.triangle_vertices(mesh_triangles(scene, label))[0], axis=0)))
             for label in ("mirrored", "reversed", "reversed-flipped", "disk-mirrored")}
    np.testing.assert_allclose(front["mirrored"], [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(front["reversed"], [0, 0, -1], atol=1e-6)
    np.testing.assert_allclose(front["reversed-flipped"], [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(front["disk-mirrored"], [0, 0, -1], atol=1e-6)
    note(scene, r"^reversed: 2 of 2 faces wind against their vertex normals")


def test_default_ref_and_include(tmp_path):
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "light.xml").write_text(
        '<scene version="3.0.0"><shape type="rectangle" id="light"><transform name="to_world"><scale value="0.5"/>'
        '<rotate x="1" angle="180"/><translate z="$height"/></transform>'
        '<emitter type="area"><rgb name="radiance" value="$L"/></emitter></shape></scene>')
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "plate.obj").write_bytes((DATA / "plate.obj").read_bytes())
    body = ('<default name="L" value="7"/><default name="height" value="3"/><path value="meshes"/>'
            '<bsdf type="diffuse" id="matte"><rgb name="reflectance" value="0.25"/></bsdf>'
            '<shape type="rectangle" id="floor"><transform name="to_world"><scale value="2"/></transform>'
            '<ref id="matte"/></shape><include filename="parts/light.xml"/>'
            '<shape type="obj" id="plate"><string name="filename" value="plate.obj"/><ref id="matte"/>'
            '<transform name="to_world"><translate z="1"/></transform></shape>')
    scene = load_mitsuba(write(tmp_path, body))
    assert scene.mesh_names == ["floor", "light", "plate"]
    np.testing.assert_allclose(scene.triangle_vertices(mesh_triangles(scene, "plate"))[..., 2], 1.0)
    np.testing.assert_allclose(scene.emitter_radiance, 7.0 * Y.sum())
    np.testing.assert_allclose(scene.triangle_vertices(scene.emitters)[..., 2], 3.0)
    assert scene.receivers.albedo[0] == pytest.approx(0.25, rel=1e-6)


@pytest.mark.parametrize("channel", ["r", "g", "b", "y"])
def test_rgb_and_spectral_values_in_each_channel(tmp_path, channel):
    body = ('<shape type="rectangle" id="floor"><transform name="to_world"><scale value="2"/></transform>'
            '<bsdf type="diffuse"><spectrum name="reflectance" value="400:0.1, 500:0.4, 700:0.9"/></bsdf></shape>'
            '<shape type="rectangle" id="rgb"><transform name="to_world"><scale value="0.3"/><rotate x="1" angle="180"/>'
            '<translate x="-1" z="2"/></transform><emitter type="area"><rgb name="radiance" value="1, 2, 3"/>'
            '</emitter></shape>'
            '<shape type="rectangle" id="spectral"><transform name="to_world"><scale value="0.3"/>'
            '<rotate x="1" angle="180"/><translate x="1" z="2"/></transform><emitter type="area">'
            '<spectrum name="radiance" value="400:1, 550:2, 700:4"/></emitter></shape>'
            '<shape type="rectangle" id="flat"><transform name="to_world"><scale value="0.3"/>'
            '<rotate x="1" angle="180"/><translate y="1" z="2"/></transform><emitter type="area">'
            '<spectrum name="radiance" value="3"/></emitter></shape>')
    path = write(tmp_path, body)
    scene = load_mitsuba(path, channel=channel)
    weights = np.array(CHANNELS[channel])
    ms = mitsuba_scene(path)
    for label, x, y in (("rgb", -1, 0), ("spectral", 1, 0), ("flat", 0, 1)):
        si = ms.ray_intersect(mi.Ray3f(mi.Point3f(x, y, 0.5), mi.Vector3f(0, 0, 1)))
        assert si.shape.id() == label
        radiance = np.array(si.emitter(ms).eval(si), dtype=np.float64)
        emission = scene.emission[mesh_triangles(scene, label)]
        np.testing.assert_allclose(emission, weights @ radiance, rtol=1e-6)
    np.testing.assert_allclose(scene.emission[mesh_triangles(scene, "rgb")], weights @ [1, 2, 3], rtol=1e-7)
    si = ms.ray_intersect(mi.Ray3f(mi.Point3f(0.1, 0.1, 1.0), mi.Vector3f(0, 0, -1)))
    reflectance = np.array(si.bsdf().eval(mi.BSDFContext(), si, mi.Vector3f(0, 0, 1))) * math.pi
    assert scene.receivers.albedo[0] == pytest.approx(weights @ reflectance, rel=1e-6)
    note(scene, rf"^colour channel {channel}")


def test_channel_argument_overrides_the_receivers_file(tmp_path):
    path = write(tmp_path, FLOOR + light("1, 2, 3"), receivers='channel = "b"\n' + ONE_POINT)
    assert load_mitsuba(path).emitter_radiance[0] == pytest.approx(3.0)
    assert load_mitsuba(path, channel="r").emitter_radiance[0] == pytest.approx(1.0)
    assert warpis.load_scene(path, channel="g").emitter_radiance[0] == pytest.approx(2.0)


# ----------------------------------------------------------------------------- analytic shapes


def tessellation_figures(scene: warpis.Scene, label: str) -> tuple[float, float]:
    found = note(scene, rf"^{re.escape(label)}: \w+ tessellated into \d+ triangles .*area error ([-+\d.e]+)%, "
                        rf"irradiance error ([-+\d.e]+)%")
    return float(found.group(1)) / 100, float(found.group(2)) / 100


def test_sphere_light_area_and_irradiance(tmp_path):
    body = ('<shape type="sphere" id="ball"><point name="center" x="0.3" y="-0.2" z="2"/>'
            '<float name="radius" value="0.4"/><emitter type="area"><rgb name="radiance" value="5"/></emitter></shape>'
            '<shape type="sphere" id="shell"><boolean name="flip_normals" value="true"/>'
            '<transform name="to_world"><scale value="0.5"/><rotate z="1" angle="20"/><translate x="-1.3" z="1"/>'
            '</transform><emitter type="area"><rgb name="radiance" value="2"/></emitter></shape>')
    path = write(tmp_path, FLOOR + body, receivers="tessellate = true\n" + ONE_POINT)
    analytic = load_mitsuba(write(tmp_path, FLOOR + body, name="analytic"))
    np.testing.assert_allclose(analytic.spheres.radii, [0.4, 0.5], rtol=1e-7)  # Mitsuba's radii are float32
    np.testing.assert_array_equal(analytic.spheres.inward, [0, 1])
    assert analytic.emitter_count == 0 and not any("tessellated" in n for n in analytic.notes)
    scene = load_mitsuba(path)
    ball = mesh_triangles(scene, "ball")
    tris = scene.triangle_vertices(ball)
    area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1).sum()
    assert area == pytest.approx(4 * math.pi * 0.4**2, rel=1e-6)  # Mitsuba's radius is a float32
    centre = np.array([0.3, -0.2, 2.0])
    for direction in ([0, 0, 1.0], unit(np.array([1.0, 2, -0.5]))):
        x = centre + 0.8 * np.array(direction)
        e = triangle_irradiance(x[None], -np.array(direction)[None], tris, np.full(len(tris), 5.0))[0]
        assert e == pytest.approx(5 * math.pi / 4, rel=TESSELLATION_ERROR)
    shell = scene.triangle_vertices(mesh_triangles(scene, "shell"))
    e = triangle_irradiance(np.array([[-1.3, 0, 1]]), np.array([[0.6, 0, 0.8]]), shell, np.full(len(shell), 2.0))[0]
    assert e == pytest.approx(2 * math.pi, rel=TESSELLATION_ERROR)
    for label in ("ball", "shell"):
        area_error, irradiance_error = tessellation_figures(scene, label)
        assert abs(area_error) < TESSELLATION_ERROR and abs(irradiance_error) < TESSELLATION_ERROR
        check_fronts(path, scene, label)
    ms = mitsuba_scene(path)
    assert area == pytest.approx([s for s in ms.shapes() if s.id() == "ball"][0].surface_area(), rel=1e-6)


def test_disk_and_cylinder_lights(tmp_path):
    em = '<emitter type="area"><rgb name="radiance" value="3"/></emitter>'
    body = (f'<shape type="disk" id="disk"><transform name="to_world"><scale value="0.5"/><rotate x="1" angle="180"/>'
            f'<translate x="-1" z="2"/></transform>{em}</shape>'
            f'<shape type="disk" id="ellipse"><transform name="to_world"><scale x="0.6" y="0.3"/><rotate x="1" angle="150"/>'
            f'<translate x="1" z="2"/></transform>{em}</shape>'
            f'<shape type="cylinder" id="tube"><point name="p0" x="-1" y="1" z="1"/><point name="p1" x="1" y="1" z="1.5"/>'
            f'<float name="radius" value="0.2"/>{em}</shape>'
            f'<shape type="cylinder" id="inner"><boolean name="flip_normals" value="true"/>'
            f'<transform name="to_world"><scale x="0.3" y="0.3" z="0.8"/><translate x="1" y="-1" z="0.5"/></transform>'
            f'{em}</shape>')
    path = write(tmp_path, FLOOR + body)
    scene = load_mitsuba(path)
    ms = {s.id(): s for s in mitsuba_scene(path).shapes()}
    for label in ("disk", "ellipse", "tube", "inner"):
        tris = scene.triangle_vertices(mesh_triangles(scene, label))
        area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1).sum()
        assert area == pytest.approx(ms[label].surface_area(), rel=1e-6)
        area_error, irradiance_error = tessellation_figures(scene, label)
        assert abs(area_error) < TESSELLATION_ERROR and abs(irradiance_error) < TESSELLATION_ERROR
        check_fronts(path, scene, label)
    # The disk faces down: on its axis at height r below, E = π L / 2.
    tris = scene.triangle_vertices(mesh_triangles(scene, "disk"))
    e = triangle_irradiance(np.array([[-1, 0, 1.5]]), np.array([[0, 0, 1.0]]), tris, np.full(len(tris), 3.0))[0]
    assert e == pytest.approx(3 * math.pi / 2, rel=TESSELLATION_ERROR)


# ----------------------------------------------------------------------------- BSDFs


def test_roughconductor_parameters_read_back_exactly(tmp_path):
    body = ('<shape type="rectangle" id="plate1"><transform name="to_world"><scale value="2"/></transform>'
            '<bsdf type="roughconductor"><string name="distribution" value="ggx"/><float name="alpha" value="0.05"/>'
            '<rgb name="eta" value="0.2, 0.9, 1.1"/><rgb name="k" value="3, 2.5, 2"/>'
            '<rgb name="specular_reflectance" value="0.9, 0.8, 0.7"/></bsdf></shape>'
            '<shape type="rectangle" id="gold"><transform name="to_world"><translate x="3"/></transform>'
            '<bsdf type="roughconductor"><string name="material" value="Au"/><float name="alpha_u" value="0.2"/>'
            '<float name="alpha_v" value="0.2"/><boolean name="sample_visible" value="false"/></bsdf></shape>'
            '<shape type="rectangle" id="mirror"><transform name="to_world"><translate x="-3"/></transform>'
            '<bsdf type="roughconductor"/></shape>')
    receivers = ('[[receivers]]\npoints = [[0, 0, 0]]\n[[receivers]]\npoints = [[3, 0, 0]]\nview = [3, 1, 4]\n'
                 '[[receivers]]\npoints = [[-3, 0, 0]]\n')
    path = write(tmp_path, body + light(), receivers=receivers)
    for channel, weights in CHANNELS.items():
        rx = load_mitsuba(path, channel=channel).receivers
        assert [rx.material_name(i) for i in range(3)] == ["roughconductor"] * 3
        assert rx.alpha[0] == np.float32(0.05) and rx.alpha[1] == np.float32(0.2) and rx.alpha[2] == np.float32(0.1)
        assert list(rx.distribution) == [DISTRIBUTIONS["ggx"], DISTRIBUTIONS["beckmann"], DISTRIBUTIONS["beckmann"]]
        assert list(rx.sample_visible) == [1, 0, 1]
        np.testing.assert_array_equal(rx.eta[0], np.float32([0.2, 0.9, 1.1]))
        np.testing.assert_array_equal(rx.k[0], np.float32([3, 2.5, 2]))
        np.testing.assert_allclose(rx.specular[0], np.array(weights) * np.float32([0.9, 0.8, 0.7]), rtol=1e-15)
        np.testing.assert_allclose(rx.specular[1], weights, rtol=1e-15)
    scene = load_mitsuba(path)
    gold = [s for s in mitsuba_scene(path).shapes() if s.id() == "gold"][0].bsdf()
    text = str(gold)
    for name, row in (("eta", scene.receivers.eta[1]), ("k", scene.receivers.k[1])):
        printed = re.search(rf"{name} = SRGBReflectanceSpectrum\[\s*value = \[([^\]]*)\]", text).group(1)
        np.testing.assert_allclose(row, [float(x) for x in printed.split(",")], rtol=1e-5)
    # Mitsuba's default material "none" (eta 0, k 1): a mirror, eta kept just above 0.
    assert np.all(scene.receivers.eta[2] > 0) and np.all(scene.receivers.eta[2] <= 1e-6)
    np.testing.assert_array_equal(scene.receivers.k[2], 1.0)
    note(scene, r"^plate1: roughconductor ggx alpha=0\.05 \(visible normals\) eta=\(0\.2, 0\.9, 1\.1\)")
    note(scene, r"^gold: roughconductor beckmann alpha=0\.2 \(all normals\)")
    note(scene, r"^mirror: roughconductor eta=0 .* taken as eta=1e-06")


def test_roughplastic_parameters_read_back_exactly(tmp_path):
    body = ('<shape type="rectangle" id="plastic"><transform name="to_world"><scale value="2"/></transform>'
            '<bsdf type="roughplastic"><string name="distribution" value="ggx"/><float name="alpha" value="0.3"/>'
            '<float name="int_ior" value="1.6"/><float name="ext_ior" value="1.1"/>'
            '<rgb name="diffuse_reflectance" value="0.1, 0.2, 0.3"/><rgb name="specular_reflectance" value="0.5, 0.6, 0.7"/>'
            '<boolean name="sample_visible" value="false"/></bsdf></shape>'
            '<shape type="rectangle" id="default"><transform name="to_world"><translate x="3"/></transform>'
            '<bsdf type="roughplastic"/></shape>')
    receivers = '[[receivers]]\npoints = [[0, 0, 0], [3, 0, 0]]\n'
    path = write(tmp_path, body + light(), receivers=receivers)
    ms = {s.id(): str(s.bsdf()) for s in mitsuba_scene(path).shapes()}
    for channel, weights in CHANNELS.items():
        rx = load_mitsuba(path, channel=channel).receivers
        assert [rx.material_name(i) for i in range(2)] == ["roughplastic"] * 2
        assert rx.alpha[0] == np.float32(0.3) and rx.alpha[1] == np.float32(0.1)
        assert list(rx.distribution) == [DISTRIBUTIONS["ggx"], DISTRIBUTIONS["beckmann"]]
        assert list(rx.sample_visible) == [0, 1]
        np.testing.assert_array_equal(rx.eta[0], np.float32(np.float32(1.6) / np.float32(1.1)))
        np.testing.assert_array_equal(rx.k, 0.0)
        assert rx.albedo[0] == pytest.approx(np.dot(weights, np.float32([0.1, 0.2, 0.3])), rel=1e-15)
        np.testing.assert_allclose(rx.specular[0], np.array(weights) * np.float32([0.5, 0.6, 0.7]), rtol=1e-15)
        for i, label in enumerate(("plastic", "default")):
            printed = float(re.search(r"specular_sampling_weight = ([\d.]+)", ms[label]).group(1))
            assert rx.specular_weight[i] == pytest.approx(printed, abs=1e-6)
            eta = float(re.search(r"\beta = ([\d.]+)", ms[label]).group(1))
            assert rx.eta[i, 0] == pytest.approx(eta, abs=1e-5)
    assert load_mitsuba(path).receivers.specular_weight[0] == pytest.approx(0.6 / (0.6 + 0.2), rel=1e-6)


def test_twosided_flips_the_normal_to_the_viewer(tmp_path):
    body = ('<shape type="rectangle" id="sheet"><transform name="to_world"><scale value="2"/></transform>'
            '<bsdf type="twosided"><bsdf type="diffuse"><rgb name="reflectance" value="0.4"/></bsdf></bsdf></shape>'
            '<shape type="rectangle" id="under"><transform name="to_world"><scale value="0.5"/><translate z="-2"/>'
            '</transform><emitter type="area"><rgb name="radiance" value="3"/></emitter></shape>')
    receivers = ('[[receivers]]\nname = "below"\npoints = [[0.5, 0.5, 0]]\nview = [0, 0, -5]\n'
                 '[[receivers]]\nname = "above"\npoints = [[0.5, 0.5, 0]]\n'
                 '[[receivers]]\nname = "given"\npoints = [[0.2, 0.5, 0]]\nnormal = [0, 0.6, -0.8]\nview = [0, 0, -5]\n')
    scene = load_mitsuba(write(tmp_path, body, receivers=receivers))
    rx = scene.receivers
    np.testing.assert_allclose(rx.normals, [[0, 0, -1], [0, 0, 1], [0, 0.6, -0.8]], atol=1e-12)
    assert rx.view[0, 2] < 0 < rx.view[1, 2]
    assert rx.group_names == ["below", "above", "given"]
    assert np.all(rx.albedo == pytest.approx(0.4, rel=1e-6))
    note(scene, r"^sheet: twosided diffuse albedo=0\.4")


# ----------------------------------------------------------------------------- receivers


def test_receivers_points_normals_views_and_materials(tmp_path):
    body = (FLOOR + light() +
            '<shape type="rectangle" id="panel"><transform name="to_world"><scale value="0.5"/>'
            '<rotate y="1" angle="90"/><translate x="1.5" z="0.5"/></transform>'
            '<bsdf type="roughplastic"><float name="alpha" value="0.2"/></bsdf></shape>')
    receivers = ('name = "named"\ndescription = "two groups"\nview = [0, 0, 6]\n'
                 '[[receivers]]\nname = "floor"\npoints = [[0.1, 0.2, 0.0000001], [-1, 1, 0]]\n'
                 'normals = [[0, 0, 1], [0, 0.6, 0.8]]\n'
                 '[[receivers]]\nname = "panel"\npoints = [[1.5, 0.1, 0.4]]\nview = [4, 0, 0.4]\n')
    scene = load_mitsuba(write(tmp_path, body, receivers=receivers))
    assert scene.name == "named" and scene.description == "two groups"
    rx = scene.receivers
    assert rx.group_names == ["floor", "panel"] and list(rx.group) == [0, 0, 1] and rx.grid_shape is None
    np.testing.assert_allclose(rx.positions, [[0.1, 0.2, 0], [-1, 1, 0], [1.5, 0.1, 0.4]], atol=1e-12)
    assert rx.positions[0, 2] == 0.0  # placed onto the floor
    np.testing.assert_allclose(rx.normals, [[0, 0, 1], [0, 0.6, 0.8], [1, 0, 0]], atol=1e-6)
    np.testing.assert_allclose(rx.view[0], unit(np.array([-0.1, -0.2, 6])))
    np.testing.assert_allclose(rx.view[2], unit(np.array([2.5, -0.1, 0])))
    assert [rx.material_name(i) for i in range(3)] == ["lambert", "lambert", "roughplastic"]
    assert rx.alpha[2] == np.float32(0.2)
    note(scene, r"^receivers seen from view \(0, 0, 6\)")


def test_default_normal_is_the_triangles_and_view_is_the_sensors(tmp_path):
    body = FLOOR + light() + (f'<shape type="obj" id="tilted"><string name="filename" value="{DATA / "plate.obj"}"/>'
                              f'<transform name="to_world"><scale value="0.3"/><rotate x="1" angle="40"/>'
                              f'<translate y="-1" z="0.5"/></transform></shape>')
    receivers = '[[receivers]]\npoints = [[0, -1, 0.5], [1, 1, 0]]\n'
    path = write(tmp_path, body, receivers=receivers)
    scene = load_mitsuba(path)
    rx = scene.receivers
    c, s = math.cos(math.radians(40)), math.sin(math.radians(40))
    np.testing.assert_allclose(rx.normals[0], [0, -s, c], atol=1e-6)
    np.testing.assert_allclose(rx.view[0], unit(np.array([0, 1, 4.5])))
    np.testing.assert_allclose(rx.view[1], unit(np.array([-1, -1, 5])))
    note(scene, r"^receivers seen from sensor 'cam' at \(0, 0, 5\)")


def test_grid_over_a_rectangle(tmp_path):
    body = ('<shape type="rectangle" id="floor"><transform name="to_world"><scale x="1" y="3"/>'
            '<rotate z="1" angle="90"/></transform></shape>' + light())
    receivers = 'name = "g"\n[[receivers]]\nname = "floor-grid"\ngrid = { shape = "floor", resolution = [6, 2] }\n'
    scene = load_mitsuba(write(tmp_path, body, receivers=receivers))
    rx = scene.receivers
    assert len(rx) == 12 and rx.grid_shape == (2, 6) and rx.group_names == ["floor-grid"]
    # The rectangle is 6 long along x (after the rotation) and 2 wide along y: u along x.
    xs = np.array([-2.5, -1.5, -0.5, 0.5, 1.5, 2.5])
    np.testing.assert_allclose(rx.positions[:, 0].reshape(2, 6), np.tile(xs, (2, 1)), atol=1e-6)
    np.testing.assert_allclose(np.abs(rx.positions[:, 1]), 0.5, atol=1e-6)
    np.testing.assert_allclose(rx.positions[:, 2], 0, atol=1e-12)
    np.testing.assert_allclose(rx.normals, np.tile([0, 0, 1.0], (12, 1)), atol=1e-6)


def test_grid_over_a_rotated_planar_obj(tmp_path):
    body = FLOOR + light() + (f'<shape type="obj" id="plate"><string name="filename" value="{DATA / "plate.obj"}"/>'
                              f'<transform name="to_world"><rotate z="1" angle="30"/><rotate x="1" angle="20"/>'
                              f'<translate x="0.2" y="0.1" z="0.6"/></transform>'
                              f'<bsdf type="roughconductor"><float name="alpha" value="0.3"/>'
                              f'<string name="material" value="Al"/></bsdf></shape>')
    receivers = '[[receivers]]\ngrid = { shape = "plate", resolution = [9, 3] }\n'
    path = write(tmp_path, body, receivers=receivers)
    scene = load_mitsuba(path)
    rx = scene.receivers
    assert rx.grid_shape == (3, 9) and len(rx) == 27
    tris = scene.triangle_vertices(mesh_triangles(scene, "plate"))
    normal = unit(np.cross(tris[0, 1] - tris[0, 0], tris[0, 2] - tris[0, 0]))
    np.testing.assert_allclose(rx.normals, np.tile(normal, (27, 1)), atol=1e-6)
    np.testing.assert_allclose((rx.positions - tris[0, 0]) @ normal, 0, atol=1e-6)
    grid = rx.positions.reshape(3, 9, 3)
    step_u, step_v = np.diff(grid, axis=1), np.diff(grid, axis=0)
    np.testing.assert_allclose(np.linalg.norm(step_u, axis=2), 3 / 9, rtol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(step_v, axis=2), 1 / 3, rtol=1e-5)
    np.testing.assert_allclose(np.cross(unit(step_u[0, 0]), unit(step_v[0, 0])), normal, atol=1e-6)
    assert set(rx.material_name(i) for i in range(27)) == {"roughconductor"}
    centre = np.array([0.2, 0.1, 0.6])
    np.testing.assert_allclose(rx.positions.mean(axis=0), centre, atol=1e-6)


def test_receivers_on_a_smooth_mesh_and_on_an_analytic_sphere(tmp_path):
    box = trimesh.creation.box(extents=(0.4, 0.4, 0.4))  # 8 shared vertices: Mitsuba smooths its normals
    box.apply_translation([1.2, 0.0, 0.5])
    box.export(tmp_path / "box.ply")
    body = FLOOR + light() + ('<shape type="ply" id="box"><string name="filename" value="box.ply"/></shape>'
                              '<shape type="sphere" id="ball"><point name="center" x="-1" y="0" z="0.5"/>'
                              '<float name="radius" value="0.3"/></shape>')
    receivers = ('[[receivers]]\nname = "box-top"\npoints = [[1.25, 0.05, 0.7]]\n'
                 '[[receivers]]\nname = "ball-top"\npoints = [[-1, 0, 0.8]]\n')
    scene = load_mitsuba(write(tmp_path, body, receivers=receivers))
    rx = scene.receivers
    # The box top's own normal governs the rays; the shading normal is Mitsuba's, tilted.
    np.testing.assert_allclose(rx.geometric_normals[0], [0, 0, 1], atol=1e-6)
    found = note(scene, r"^.*\[\[receivers\]\] #1 'box-top': on shape 'box', receivers shade with Mitsuba's normals "
                        r"interpolated from its vertex normals, up to ([\d.]+)°")
    angle = math.degrees(math.acos(float(rx.normals[0] @ rx.geometric_normals[0])))
    assert 10 < angle < 60 and abs(angle - float(found.group(1))) < 0.01 * angle
    # The analytic sphere's top lies on the sphere itself (Mitsuba's float32 radius), with its exact normal.
    np.testing.assert_allclose(rx.positions[1], [-1, 0, 0.8], atol=1e-7)
    np.testing.assert_allclose(rx.normals[1], [0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(rx.geometric_normals[1], [0, 0, 1], atol=1e-9)
    assert not any("tessellation" in n for n in scene.notes)


def test_candidate_triangles_from_the_grid_match_brute_force(monkeypatch):
    from warpis.scenes.mitsuba import surfaces
    rng = np.random.default_rng(3)
    lo = rng.uniform(-1, 1, (500, 3)) * [1, 1, 0.1]
    hi = lo + rng.uniform(0, 0.2, (500, 3)) ** 2
    hi[:3] = lo[:3] + 1.5  # a few large boxes among small ones
    points = rng.uniform(-1.2, 1.4, (300, 3)) * [1, 1, 0.1]
    brute = set(zip(*(a.tolist() for a in surfaces._box_pairs(points, lo, hi))))
    monkeypatch.setattr(surfaces, "_BRUTE_FORCE", 0)
    grid = set(zip(*(a.tolist() for a in surfaces._box_pairs(points, lo, hi))))
    assert grid == brute and len(brute) > 50


# ----------------------------------------------------------------------------- loading paths and output


def test_load_scene_by_path_and_folder(tmp_path):
    folder = tmp_path / "demo"
    folder.mkdir()
    path = write(folder, FLOOR + light())
    assert warpis.load_scene(path).emitter_count == 2
    (folder / "scene.xml").rename(folder / "other.xml")
    (folder / "scene.receivers.toml").rename(folder / "elsewhere.toml")
    scene = warpis.load_scene(folder / "other.xml", receivers=folder / "elsewhere.toml")
    assert scene.name == "other"
    (folder / "other.xml").rename(folder / "scene.xml")
    (folder / "elsewhere.toml").rename(folder / "scene.receivers.toml")
    assert resolve_scene_path(folder) == folder / "scene.xml"
    assert warpis.load_scene(folder).name == "demo"
    assert "mitsuba-cornell-box" in warpis.bundled_scenes()


def test_mitsubas_log_stays_quiet_and_its_warnings_become_notes(tmp_path, capfd):
    body = FLOOR + light() + ('<shape type="rectangle" id="meter"><transform name="to_world"><translate z="-3"/>'
                              '</transform><sensor type="irradiancemeter"/></shape>')
    path = write(tmp_path, body, receivers='view = [0, 0, 5]\n' + ONE_POINT, sensor=False)
    scene = load_mitsuba(path)
    out, err = capfd.readouterr()
    assert out == "" and err == ""
    note(scene, r"^Mitsuba: .*IrradianceMeter.*reconstruction filter")
    assert mi.variant() == "scalar_rgb"


def test_the_callers_mitsuba_variant_comes_back(tmp_path):
    path = write(tmp_path, FLOOR + light())
    other = next((v for v in ("scalar_spectral", "scalar_mono") if v in mi.variants()), None)
    if other is None:
        pytest.skip("a single Mitsuba variant")
    mi.set_variant(other)
    try:
        load_mitsuba(path)
        assert mi.variant() == other
    finally:
        mi.set_variant("scalar_rgb")


def test_a_mitsuba_scene_runs_through_the_estimators(tmp_path):
    path = write(tmp_path, FLOOR + light("4"), receivers='[[receivers]]\npoints = [[0, 0, 0], [0.7, -0.3, 0]]\n')
    scene = load_mitsuba(path)
    x = warpis.run_trials(scene, "independent:single:light-area", n=64, trials=64, seed=1)
    floor_albedo = scene.receivers.albedo[:, None]
    e = triangle_irradiance(scene.receivers.positions, scene.receivers.normals,
                            scene.triangle_vertices(scene.emitters), scene.emitter_radiance)
    np.testing.assert_allclose(x.mean(axis=1), (floor_albedo[:, 0] / math.pi) * e, rtol=0.02)


# What Mitsuba itself measures: a radiance meter looking at the receiver, direct illumination.
METER = """<integrator type="direct"/>
<sensor type="radiancemeter">
  <point name="origin" x="-1.2" y="0.5" z="1.5"/><vector name="direction" x="1.5" y="-0.3" z="-1.5"/>
  <film type="hdrfilm"><integer name="width" value="1"/><integer name="height" value="1"/><rfilter type="box"/>
    <string name="pixel_format" value="rgb"/></film>
  <sampler type="independent"><integer name="sample_count" value="{spp}"/></sampler>
</sensor>"""
SEEN = '[[receivers]]\npoints = [[0.3, 0.2, 0]]\nview = [-1.2, 0.5, 1.5]\n'  # where the meter looks
TILTED_LIGHT = ('<shape type="rectangle" id="light"><transform name="to_world"><scale value="0.5"/>'
                '<rotate x="1" angle="150"/><translate x="0.8" z="1.2"/></transform>'
                '<emitter type="area"><rgb name="radiance" value="1, 2, 3"/></emitter></shape>')


def mitsuba_measures(path: Path, seed: int = 0) -> np.ndarray:
    return np.array(mi.render(mitsuba_scene(path), seed=seed), dtype=np.float64).reshape(-1)[:3]


def test_each_channel_matches_mitsubas_render_of_a_diffuse_receiver(tmp_path):
    body = (METER.format(spp=400000) + '<shape type="rectangle" id="floor"><transform name="to_world"><scale value="2"/>'
            '</transform><bsdf type="diffuse"><rgb name="reflectance" value="0.2, 0.5, 0.8"/></bsdf></shape>'
            + TILTED_LIGHT)
    path = write(tmp_path, body, receivers=SEEN, sensor=False)
    measured = mitsuba_measures(path)
    for c, channel in enumerate("rgb"):
        scene = load_mitsuba(path, channel=channel)
        rx = scene.receivers
        e = triangle_irradiance(rx.positions, rx.normals, scene.triangle_vertices(scene.emitters),
                                scene.emitter_radiance)[0]
        assert rx.albedo[0] / math.pi * e == pytest.approx(measured[c], rel=5e-3)
    note(load_mitsuba(path), r"^channel y multiplies the luminance of the emission by the luminance of the BSDF")


@pytest.mark.parametrize("bsdf", [
    '<bsdf type="roughconductor"><float name="alpha" value="0.3"/><string name="distribution" value="ggx"/>'
    '<string name="material" value="Cu"/><rgb name="specular_reflectance" value="0.9, 0.8, 0.7"/></bsdf>',
    '<bsdf type="roughplastic"><float name="alpha" value="0.3"/><string name="distribution" value="ggx"/>'
    '<rgb name="diffuse_reflectance" value="0.2, 0.5, 0.8"/><rgb name="specular_reflectance" value="0.6, 0.5, 0.4"/>'
    '</bsdf>',
], ids=["roughconductor", "roughplastic"])
def test_each_channel_matches_mitsubas_render_of_a_microfacet_receiver(tmp_path, bsdf):
    body = (METER.format(spp=200000) + '<shape type="rectangle" id="floor"><transform name="to_world">'
            f'<scale value="2"/></transform>{bsdf}</shape>' + TILTED_LIGHT)
    path = write(tmp_path, body, receivers=SEEN, sensor=False)
    measured = mitsuba_measures(path)
    for c, channel in enumerate("rgb"):
        trials = warpis.run_trials(load_mitsuba(path, channel=channel), "independent:balance:light-area+bsdf",
                                   n=4096, trials=32, seed=c)
        assert trials.mean() == pytest.approx(measured[c], rel=0.02)


# ----------------------------------------------------------------------------- bad input


@pytest.fixture
def scene_path(tmp_path):
    """Write a scene with the floor and the light plus ``extra``; return its path."""
    def make(extra: str = "", receivers: str | None = ONE_POINT, sensor: bool = True, floor: str = FLOOR,
             emitter: str | None = None) -> Path:
        return write(tmp_path, floor + (light() if emitter is None else emitter) + extra, receivers=receivers,
                     sensor=sensor)
    return make


def test_missing_receivers_file(scene_path):
    path = scene_path(receivers=None)
    with pytest.raises(WarpisError) as excinfo:
        load_mitsuba(path)
    one_line(excinfo, path, "scene.receivers.toml does not exist", "[[receivers]]", "docs/mitsuba-scenes.md")
    with pytest.raises(WarpisError) as excinfo:
        load_mitsuba(path, receivers=path.parent / "nope.toml")
    one_line(excinfo, path, "nope.toml does not exist")


@pytest.mark.parametrize("receivers, parts", [
    ("colour = 'y'\n" + ONE_POINT, ["unknown key 'colour' in the top level"]),
    ("[[receivers]]\npoints = [[0, 0, 0]]\nnormal = [0, 0, 1]\nmaterial = 'x'\n", ["unknown key 'material'"]),
    ("[[receivers]]\ngrid = { shape = 'floor', resolution = [2, 2], origin = [0, 0, 0] }\n",
     ["unknown key 'origin' in [receivers].grid"]),
    ("channel = 'x'\n" + ONE_POINT, ["channel 'x'", "r, g, b"]),
    ("[[receivers]]\npoints = [[0, 0]]\n", ["[receivers].points must be a list of 3 numbers"]),
    ("[[receivers]]\npoints = [[0, 0, 0]]\ngrid = { shape = 'floor', resolution = [2, 2] }\n",
     ["exactly one of 'points' or 'grid'"]),
    ("[[receivers]]\ngrid = { shape = 'floor', resolution = [0, 2] }\n", ["resolution must be at least [1, 1]"]),
    ("[[receivers]]\ngrid = { shape = 'nope', resolution = [2, 2] }\n", ["grid shape 'nope': no shape with that id"]),
    ("[[receivers]]\npoints = [[0, 0, 0]]\nnormals = [[0, 0, 1], [0, 0, 1]]\n", ["2 entries for 1 points"]),
    ("[[receivers]]\npoints = [[0, 0, 0]]\nview = 'up'\n", ["view must be a list of 3 numbers"]),
    ("name = 3\n" + ONE_POINT, ["name must be a string"]),
    ("[[receivers]\n", ["not valid TOML"]),
    ("", ["missing key 'receivers'"]),
])
def test_bad_receivers_file(scene_path, receivers, parts):
    path = scene_path(receivers=receivers)
    with pytest.raises(WarpisError) as excinfo:
        load_mitsuba(path)
    message = str(excinfo.value)
    assert "\n" not in message and message.startswith(str(path.parent / "scene.receivers.toml")), message
    for part in parts:
        assert part in message, (part, message)


@pytest.mark.parametrize("extra, parts", [
    ('<emitter type="projector" id="beamer"/>', ["emitter 'beamer' (projector)", "area emitters"]),
    ('<emitter type="sunsky"/>', ["emitter 'sunsky'", "envmap"]),
    ('<emitter type="constant"/><emitter type="constant"/>',
     ["Only one environment emitter"]),  # Mitsuba's own refusal, in one line
    ('<emitter type="point" id="bulb"><point name="position" x="0" y="0" z="0"/></emitter>',
     ["emitter 'bulb' (point)", "sits at receiver 0", "infinite"]),
    ('<shape type="shapegroup" id="group"><shape type="sphere"/></shape>'
     '<shape type="instance" id="copy"><ref id="group"/></shape>', ["shape 'copy'", "instances are not supported"]),
    ('<shape type="sphere" id="egg"><transform name="to_world"><scale x="1" y="2" z="1"/></transform></shape>',
     ["shape 'egg'", "sphere: its to_world scales unevenly"]),
    ('<shape type="cylinder" id="oval"><transform name="to_world"><scale x="1" y="2" z="1"/></transform></shape>',
     ["shape 'oval'", "cylinder: its to_world scales its cross-section unevenly"]),
    ('<shape type="rectangle" id="tex-light">'
     '<emitter type="area"><texture type="checkerboard" name="radiance"/></emitter></shape>',
     ["shape 'tex-light'", "area emitter: its radiance is a 'checkerboard' texture"]),
])
def test_unsupported_elements(scene_path, extra, parts):
    path = scene_path(extra)
    with pytest.raises(WarpisError) as excinfo:
        load_mitsuba(path)
    one_line(excinfo, path, *parts)


@pytest.mark.parametrize("extra, parts", [
    ('<shape type="rectangle" id="glass"><bsdf type="dielectric"/></shape>',
     ["shape 'glass'", "BSDF 'dielectric' is not supported", "roughconductor"]),
    ('<shape type="rectangle" id="chrome"><bsdf type="conductor"/></shape>', ["shape 'chrome'", "'conductor'"]),
    ('<shape type="rectangle" id="gloss"><bsdf type="plastic"/></shape>', ["shape 'gloss'", "'plastic'"]),
    ('<shape type="rectangle" id="p"><bsdf type="principled"/></shape>', ["shape 'p'", "'principled'"]),
    ('<shape type="rectangle" id="m"><bsdf type="mask"><bsdf type="diffuse"/></bsdf></shape>', ["'mask'"]),
    ('<shape type="rectangle" id="b"><bsdf type="blendbsdf"><float name="weight" value="0.5"/>'
     '<bsdf type="diffuse"/><bsdf type="roughconductor"/></bsdf></shape>', ["shape 'b'", "'blendbsdf'"]),
    ('<shape type="rectangle" id="chk"><bsdf type="roughconductor"><texture type="checkerboard" name="k"/>'
     '</bsdf></shape>', ["shape 'chk'", "k is a 'checkerboard' texture", "only uniform values"]),
    ('<shape type="rectangle" id="aniso"><bsdf type="roughconductor"><float name="alpha_u" value="0.1"/>'
     '<float name="alpha_v" value="0.3"/></bsdf></shape>',
     ["shape 'aniso'", "anisotropic roughness alpha_u=0.1, alpha_v=0.3", "isotropic"]),
    ('<shape type="rectangle" id="nl"><bsdf type="roughplastic"><boolean name="nonlinear" value="true"/></bsdf>'
     '</shape>', ["shape 'nl'", "nonlinear=true"]),
    ('<shape type="rectangle" id="two"><bsdf type="twosided"><bsdf type="diffuse"/><bsdf type="roughconductor"/>'
     '</bsdf></shape>', ["shape 'two'", "different BSDF on each side"]),
])
def test_unsupported_bsdfs_under_a_receiver(scene_path, extra, parts):
    """A BSDF warpis cannot shade is an error once a receiver lies on its shape (at z = 1,
    above the floor); without one the shape only occludes (tests/test_occluders.py)."""
    head, sep, rest = extra.partition(">")
    lifted = head + sep + '<transform name="to_world"><scale value="0.3"/><translate z="1"/></transform>' + rest
    on_it = "[[receivers]]\nname = 'up'\npoints = [[0.1, 0.1, 1]]\n"
    path = scene_path(lifted, receivers=on_it)
    with pytest.raises(WarpisError) as excinfo:
        load_mitsuba(path)
    one_line(excinfo, path, *parts, "point 0 (0.1, 0.1, 1) of [receivers] 'up' in scene.receivers.toml lies on it")
    assert len(load_mitsuba(scene_path(lifted)).receivers) == 1


def test_meaning_changing_warnings_are_errors_and_print_nothing(scene_path, capfd):
    path = scene_path('<shape type="sphere" id="egg"><transform name="to_world"><scale x="1" y="2" z="1"/>'
                      '</transform></shape>')
    with pytest.raises(WarpisError) as excinfo:
        load_mitsuba(path)
    one_line(excinfo, path, "shape 'egg'", "scales unevenly")
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def test_bitmap_texture(scene_path, tmp_path):
    """A bitmap reflectance is evaluated at the receiver (tests/test_textured_receivers.py)."""
    mi.set_variant("scalar_rgb")
    mi.Bitmap(np.full((2, 2, 3), 0.5, np.float32)).write(str(tmp_path / "tex.exr"))
    path = scene_path('<shape type="rectangle" id="tex"><transform name="to_world"><scale value="0.3"/>'
                      '<translate z="1"/></transform><bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
                      '<string name="filename" value="tex.exr"/></texture></bsdf></shape>',
                      receivers="[[receivers]]\npoints = [[0.1, 0.1, 1]]\n")
    scene = load_mitsuba(path)
    assert scene.receivers.albedo[0] == pytest.approx(0.5, rel=1e-6)
    note(scene, r"^tex: 1 receiver\(s\) take its diffuse reflectance from its 'bitmap' texture")


@pytest.mark.parametrize("receivers, parts", [
    ("[[receivers]]\nname = 'off'\npoints = [[0, 0, 0], [0.5, 0.5, 0.25]]\n",
     ["[receivers] 'off' point 1 (0.5, 0.5, 0.25) lies on no surface of scene.xml", "the nearest is 0.25 away"]),
    ("[[receivers]]\npoints = [[0, 0, 0]]\nview = [0, 0, -3]\n",
     ["point 0 (0, 0, 0)", "is behind shape 'floor'", "one-sided", "twosided"]),
    ("[[receivers]]\npoints = [[0.2, 0.1, 2]]\nview = [0, 0, 0]\n", ["lies on shape 'light', an emitter"]),
    ("[[receivers]]\ngrid = { shape = 'light', resolution = [2, 2] }\n", ["on shape 'light', an emitter"]),
    ("[[receivers]]\npoints = [[0, 0, 0]]\nnormal = [0, 0, -1]\n", ["the viewer", "is behind its normal (0, 0, -1)"]),
    ("[[receivers]]\npoints = [[0, 0, 0]]\nview = [0, 0, 0]\n", ["is at the receiver itself"]),
])
def test_bad_receivers(scene_path, receivers, parts):
    path = scene_path(receivers=receivers)
    with pytest.raises(WarpisError) as excinfo:
        load_mitsuba(path)
    message = str(excinfo.value)
    assert "\n" not in message and message.startswith(str(path.parent / "scene.receivers.toml")), message
    for part in parts:
        assert part in message, (part, message)


def test_grids_need_a_rectangular_planar_shape(scene_path):
    extra = ('<shape type="sphere" id="ball"><point name="center" x="1" y="1" z="1"/><float name="radius" value="0.2"/>'
             '</shape><shape type="disk" id="round"><transform name="to_world"><scale value="0.3"/>'
             '<translate x="-1" z="0.5"/></transform></shape>')
    path = scene_path(extra, receivers="[[receivers]]\ngrid = { shape = 'ball', resolution = [2, 2] }\n")
    with pytest.raises(WarpisError) as excinfo:
        load_mitsuba(path)
    assert "shape 'ball' is not planar" in str(excinfo.value)
    path = scene_path(extra, receivers="[[receivers]]\ngrid = { shape = 'round', resolution = [8, 8] }\n")
    with pytest.raises(WarpisError) as excinfo:
        load_mitsuba(path)
    message = str(excinfo.value)
    assert re.search(r"\d+ of 64 grid cell centres fall off shape 'round'", message), message
    path = scene_path(extra, receivers="[[receivers]]\ngrid = { shape = 'round', resolution = [2, 2] }\n")
    assert load_mitsuba(path).receivers.grid_shape == (2, 2)


def test_no_viewer(scene_path):
    path = scene_path(sensor=False)
    with pytest.raises(WarpisError) as excinfo:
        load_mitsuba(path)
    message = str(excinfo.value)
    assert "\n" not in message and "no viewer: scene.xml has no <sensor>" in message and "view = [x, y, z]" in message


def test_no_emitter(scene_path):
    path = scene_path(emitter="")
    with pytest.raises(WarpisError) as excinfo:
        load_mitsuba(path)
    one_line(excinfo, path, "the scene has no emitter", "area")
    path = scene_path(emitter=light("1, 0, 0"))
    with pytest.raises(WarpisError) as excinfo:
        load_mitsuba(path, channel="g")
    one_line(excinfo, path, "the scene has no emitter", "radiance > 0 in channel g")


def test_bad_channel(scene_path):
    path = scene_path()
    for bad in ("x", "Y", "rgb", 1):
        with pytest.raises(WarpisError) as excinfo:
            load_mitsuba(path, channel=bad)
        one_line(excinfo, path, f"channel {bad!r}")
    with pytest.raises(WarpisError):
        warpis.load_scene(path, channel="luminance")


@pytest.mark.parametrize("xml, parts", [
    ('<scene version="3.0.0"><shape type="rectangle"', ["Mitsuba cannot load it: Parsing of XML file", "failed"]),
    ('<scene version="3.0.0"><include filename="missing.xml"/></scene>',
     ["Mitsuba cannot load it:", 'included file "missing.xml" not found']),
    ('<scene version="3.0.0"><shape type="obj"><string name="filename" value="none.obj"/></shape></scene>',
     ["Mitsuba cannot load it:", "none.obj"]),
    ('<scene version="3.0.0"><shape type="sphere"><float name="radiuss" value="1"/></shape></scene>',
     ["Mitsuba cannot load it:", "unreferenced property", "radiuss"]),
    ('<scene version="3.0.0"><shape type="sphere"><ref id="nothing"/></shape></scene>',
     ["Mitsuba cannot load it:", 'unresolved reference to "nothing"']),
    ('<scene version="3.0.0"><shape type="teapot"/></scene>', ["Mitsuba cannot load it:", '"teapot" not found']),
    ('<bsdf type="diffuse" version="3.0.0"/>', ["not a <scene>"]),
])
def test_mitsuba_cannot_load(tmp_path, xml, parts):
    path = tmp_path / "scene.xml"
    path.write_text(xml)
    (tmp_path / "scene.receivers.toml").write_text(ONE_POINT)
    with pytest.raises(WarpisError) as excinfo:
        load_mitsuba(path)
    message = one_line(excinfo, path, *parts)
    assert "[parser.cpp" not in message and "cpp:" not in message


def test_missing_scene_file(tmp_path):
    with pytest.raises(WarpisError) as excinfo:
        load_mitsuba(tmp_path / "nope.xml")
    one_line(excinfo, tmp_path / "nope.xml", "no such Mitsuba scene file")


def test_without_the_mitsuba_package(scene_path, monkeypatch):
    path = scene_path()
    monkeypatch.setitem(sys.modules, "mitsuba", None)
    with pytest.raises(WarpisError) as excinfo:
        load_mitsuba(path)
    one_line(excinfo, path, 'Mitsuba scenes need the optional mitsuba package: pip install "warpis[mitsuba]"')


def test_receivers_argument_is_refused_for_a_toml_scene(tmp_path):
    toml = resolve_scene_path("occluded-quad")
    with pytest.raises(WarpisError) as excinfo:
        warpis.load_scene(toml, receivers=tmp_path / "x.toml")
    one_line(excinfo, toml, "a receivers file goes with a Mitsuba scene")
    assert warpis.load_scene(toml, channel="r").digest == warpis.load_scene(toml).digest


def test_bundled_mitsuba_scenes_load():
    for name in ("mitsuba-cornell-box", "mitsuba-veach-plates"):
        if name not in warpis.bundled_scenes():
            continue
        scene = warpis.load_scene(name)
        assert scene.light_count > 0 and len(scene.receivers) > 0
        assert set(MATERIALS.by_code(c).name for c in np.unique(scene.receivers.material)) <= {
            "lambert", "roughconductor", "roughplastic"}
