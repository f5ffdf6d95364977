"""Shading normals: receivers that shade with a normal other than their surface's.

A receiver's ``normals`` (its BSDF's frame and cosine) may differ from its
``geometric_normals`` (the triangle it lies on): on a mesh shaded with interpolated
vertex normals, as Mitsuba shades (its own agreement is tests/test_shading_normals.py).
Rays then follow the surface: they leave x through either side of it, ignoring x's own
plane, as Mitsuba's spawn_ray does, and f counts the shading hemisphere.

The 4σ checks run at fixed seeds; each has a false-failure rate of 6e-5.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from conftest import one_error_line

import warpis
from warpis.analysis.closed_form import triangle_irradiance
from warpis.analysis.reference import reference
from warpis.kernels.engine import run_trials
from warpis.scenes.normals import interpolate_normals

Z_LIMIT = 4.0


def _tilted_receiver_scene() -> warpis.Scene:
    """A floor at z = 0 (its own normal +z) and a receiver on it whose shading normal leans
    40° towards +x, facing a light that hangs off to +x and reaches below the floor's
    plane: part of the light is seen only by rays that leave through the floor."""
    floor = np.array([[-2.0, -2.0, 0.0], [2.0, -2.0, 0.0], [2.0, 2.0, 0.0], [-2.0, 2.0, 0.0]])
    # a vertical light at x = 1.5 spanning z in [-0.6, 0.6], facing -x (towards the receiver)
    light = np.array([[1.5, -0.5, -0.6], [1.5, -0.5, 0.6], [1.5, 0.5, 0.6], [1.5, 0.5, -0.6]])
    vertices = np.vstack([floor, light])
    triangles = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    a = np.radians(40.0)
    shading = np.array([np.sin(a), 0.0, np.cos(a)])
    return warpis.Scene.from_arrays(vertices, triangles, np.array([0.0, 0.0, 7.0, 7.0]),
                                    np.array([[0.0, 0.0, 0.0], [0.3, 0.2, 0.0]]), shading,
                                    geometric_normals=[0.0, 0.0, 1.0], name="tilted-shading")


def test_a_shading_normal_sees_light_below_its_surfaces_plane():
    """F over the shading hemisphere, the light's part below the floor's plane included:
    the closed form (Lambert's, with the shading normal) and light and cosine sampling
    agree within 4σ; without that part (the floor blocking rays that leave through it)
    F would be about a third lower."""
    scene = _tilted_receiver_scene()
    rx = scene.receivers
    # Nothing occludes but the floor, which rays from x cross only at x: Lambert's sum.
    values = triangle_irradiance(rx.positions, rx.normals, scene.triangle_vertices(), scene.emission)
    assert np.all(values > 0)
    refs = reference(scene, rel_error=1e-3)  # quadrature: the floor slices the closed form's pyramids
    np.testing.assert_allclose([r.value for r in refs], values, rtol=4e-3)
    for estimator in ("independent:single:light-area", "independent:single:cosine",
                      "jittered:balance:light-area+cosine"):
        x = run_trials(scene, estimator, 16, 3000, seed=21)
        mean, se = x.mean(axis=1), x.std(axis=1, ddof=1) / np.sqrt(x.shape[1])
        z = (mean - values) / se
        assert np.all(np.abs(z) < Z_LIMIT), (estimator, mean, values, z)
    half = scene.vertices.copy()
    half[4:, 2] = np.maximum(half[4:, 2], 0.0)  # the light cut at the floor's plane: what rays that
    # could not cross the floor would see
    above = warpis.Scene.from_arrays(half, scene.triangles, scene.emission, scene.receivers.positions,
                                     scene.receivers.normals, geometric_normals=[0.0, 0.0, 1.0])
    below_cut = triangle_irradiance(rx.positions, rx.normals, above.triangle_vertices(), above.emission)
    assert np.all(below_cut < 0.8 * values)


def test_geometric_normals_default_to_the_normals_and_enter_the_digest():
    """Without geometric normals a scene is what it was (same digest); with them it is
    another scene; bad ones are one-line errors."""
    scene = _tilted_receiver_scene()
    same = warpis.Scene.from_arrays(scene.vertices, scene.triangles, scene.emission, scene.receivers.positions,
                                    scene.receivers.normals)
    np.testing.assert_array_equal(same.receivers.geometric_normals, same.receivers.normals)
    assert same.digest != scene.digest
    flat = warpis.Scene.from_arrays(scene.vertices, scene.triangles, scene.emission, scene.receivers.positions,
                                    scene.receivers.normals, geometric_normals=scene.receivers.normals)
    assert flat.digest == same.digest
    for bad, word in (([0.0, 0.0, 0.0], "zero length"), ([[0.0, 0.0, 1.0]] * 3, "shape"),
                      ([np.nan, 0.0, 1.0], "NaN")):
        with pytest.raises(warpis.WarpisError, match=f"geometric_normals.*{word}"):
            warpis.Scene.from_arrays(scene.vertices, scene.triangles, scene.emission, scene.receivers.positions,
                                     scene.receivers.normals, geometric_normals=bad)


def _ball_scene(tmp_path, **mesh_keys) -> tuple:
    """A TOML camera scene: an icosphere OBJ carrying vertex normals, under a light."""
    ball = trimesh.creation.icosphere(2, radius=0.5)
    (tmp_path / "ball.obj").write_text(trimesh.exchange.obj.export_obj(ball, include_normals=True))
    light = np.array([[-0.5, -0.5, 2.0], [-0.5, 0.5, 2.0], [0.5, 0.5, 2.0], [0.5, -0.5, 2.0]])
    keys = "".join(f"{k} = {v}\n" for k, v in mesh_keys.items())
    text = f"""[[mesh]]
path = "ball.obj"
{keys}material = {{ type = "lambert", albedo = 0.5 }}
[[mesh]]
path = "light.obj"
emission = 5.0
[receivers.camera]
position = [0, -3, 1]
target = [0, 0, 0]
fov = 30
width = 24
height = 24
"""
    trimesh.Trimesh(light, [[0, 1, 2], [0, 2, 3]], process=False).export(tmp_path / "light.obj")
    (tmp_path / "scene.toml").write_text(text)
    return tmp_path / "scene.toml", ball


def test_camera_pixels_on_a_mesh_with_vertex_normals_shade_with_their_interpolation(tmp_path):
    """Each pixel on the ball takes the file's vertex normals interpolated at its point
    (trimesh's barycentric coordinates, independently of warpis's), turned towards the
    camera, and keeps its triangle's normal for rays; `vertex_normals = false` shades
    flat.  The ball's facets are 8.7° apart: the two differ by up to 9.4°."""
    path, ball = _ball_scene(tmp_path)
    rx = warpis.load_scene(path).receivers
    tris = ball.triangles
    distance = np.stack([np.linalg.norm(trimesh.triangles.closest_point(tris, np.tile(p, (len(tris), 1))) - p, axis=1)
                         for p in rx.positions])
    face = np.argmin(distance, axis=1)  # the triangle each pixel's point lies on
    bary = trimesh.triangles.points_to_barycentric(tris[face], rx.positions)
    expected = np.einsum("kc,kcj->kj", bary, ball.vertex_normals[ball.faces[face]])
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    np.testing.assert_allclose(rx.normals, expected, atol=1e-6)
    np.testing.assert_allclose(rx.geometric_normals, ball.face_normals[face], atol=1e-6)
    np.testing.assert_allclose(interpolate_normals(ball.vertex_normals[ball.faces[face]], tris[face], rx.positions),
                               expected, atol=1e-9)
    angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", rx.normals, rx.geometric_normals), -1, 1)))
    assert 2.0 < angle.max() < 12.0
    (tmp_path / "flat").mkdir()
    flat, _ = _ball_scene(tmp_path / "flat", vertex_normals="false")
    rx = warpis.load_scene(flat).receivers
    np.testing.assert_array_equal(rx.normals, rx.geometric_normals)


@pytest.mark.parametrize("value, word", [('"yes"', "vertex_normals must be true or false"),
                                         ("1", "vertex_normals must be true or false")])
def test_a_bad_vertex_normals_key_is_one_line(cli, tmp_path, value, word):
    path, _ = _ball_scene(tmp_path, vertex_normals=value)
    line = one_error_line(cli("info", path))
    assert word in line and "ball.obj" in line, line


def test_a_zero_vertex_normal_is_one_line(cli, tmp_path):
    path, _ = _ball_scene(tmp_path)
    text = (tmp_path / "ball.obj").read_text().splitlines()
    first = next(i for i, line in enumerate(text) if line.startswith("vn "))
    text[first] = "vn 0 0 0"
    (tmp_path / "ball.obj").write_text("\n".join(text) + "\n")
    line = one_error_line(cli("info", path))
    assert "vertex normal" in line and "vertex_normals = false" in line, line
