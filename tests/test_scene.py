"""Tests of warpis.scenes: the scene-file loader, its validation, and the Warp mesh it builds.

Four parts:

* the loader on the bundled scenes and on small scenes written here (counts, emitter
  areas and CDFs, receivers and materials, transforms, receiver groups and grids, every
  mesh format trimesh reads);
* bad input: each gives a :class:`WarpisError` with a one-line message naming the file
  and the problem, and through the command line exit status 2 with one
  ``warpis: error:`` line on stderr and nothing on stdout;
* ray casting through ``upload(scene).data.mesh`` (``wp.mesh_query_ray``) against a brute-force
  float64 Möller–Trumbore first hit over every triangle, on rays from each receiver's
  shading point to the emitters;
* scenes as plain data: ``Scene.from_arrays`` against the same scene file, its one-line
  errors, the content digest, pickling, and the upload cache per (digest, device).
"""

from __future__ import annotations

import io
import math
import pickle
import tomllib
from dataclasses import fields, replace
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
import trimesh
import warp as wp
from conftest import (BUNDLED, CAMERA_BUNDLED, MITSUBA_BUNDLED, floor_entry, light_entry, quad, run_warpis,
                      tessellated_veach_plates, write_mesh, write_scene)

import warpis
from warpis.errors import WarpisError
from warpis.kernels.device import SELF_HIT_SLAB, SceneData, clear_device_cache, device_cache_keys, upload
from warpis.kernels.integrand import MATERIALS, incident_radiance
from warpis.scenes import load_scene

MESHES = Path(str(resources.files("warpis.meshes")))

# Hand-counted from meshes/*/: (triangles, emitter triangles, receivers, emitter area, Σ L·A).
# veach-plates' lights are four analytic spheres of radii 0.03, 0.1, 0.3, 0.9 and
# radiance 0.81/r²: each has area 4πr² and power 4π · 0.81.
VEACH_AREA = 4 * math.pi * (0.03**2 + 0.1**2 + 0.3**2 + 0.9**2)
EXPECTED = {
    "occluded-quad": (16, 2, 8, 0.5, 5.0),
    "two-lights": (18, 4, 8, 0.01 + 9.0, 2000 * 0.01 + 2 * 9.0),
    "heavy-occluder": (81924, 2, 8, 0.36, 3.6),
    "veach-plates": (8, 0, 16, VEACH_AREA, 4 * 4 * math.pi * 0.81),
}


def _toml(scene: warpis.Scene) -> dict:
    with open(scene.path, "rb") as fh:
        return tomllib.load(fh)


def _trimesh(path: Path) -> trimesh.Trimesh:
    return trimesh.load(str(path), force="mesh", process=False)


# =========================================================================== bundled scenes


def test_bundled_scene_names():
    """bundled_scenes() lists exactly the scenes shipped in meshes/: TOML (points and a camera) and Mitsuba XML."""
    assert warpis.bundled_scenes() == sorted(BUNDLED + MITSUBA_BUNDLED + CAMERA_BUNDLED)


def test_bundled_counts_and_totals(bundled_scene):
    """Triangle, emitter-triangle and receiver counts and the emitter area and power
    totals are the hand-counted ones, and agree mesh by mesh with trimesh's own reading
    of each file (face count, and area × scale² for every emitter mesh)."""
    s = bundled_scene
    triangles, emitter_triangles, receivers, area, power = EXPECTED[s.name]
    assert (s.triangle_count, s.emitter_count, len(s.receivers)) == (triangles, emitter_triangles, receivers)

    doc = _toml(s)
    expect_area = expect_power = 0.0
    for i, entry in enumerate(doc["mesh"]):
        m = _trimesh(s.path.parent / entry["path"])
        mine = s.triangle_mesh == i
        assert mine.sum() == len(m.faces)
        emission = entry.get("emission", 0.0)
        assert np.all(s.emission[mine] == emission)
        if emission > 0:
            scale = entry.get("transform", {}).get("scale", 1.0)
            assert np.isscalar(scale), "bundled emitters are scaled uniformly"
            expect_area += m.area * scale**2
            expect_power += emission * m.area * scale**2
            in_mesh = s.triangle_mesh[s.emitters] == i
            assert in_mesh.sum() == len(m.faces)
            np.testing.assert_allclose(s.emitter_areas[in_mesh].sum(), m.area * scale**2, rtol=1e-9)
    for ball in doc.get("sphere", []):
        expect_area += 4 * math.pi * ball["radius"] ** 2
        expect_power += ball.get("emission", 0.0) * 4 * math.pi * ball["radius"] ** 2
    # the OBJ files store 6-7 significant digits
    np.testing.assert_allclose(expect_area, area, rtol=1e-6)
    np.testing.assert_allclose(expect_power, power, rtol=1e-6)
    np.testing.assert_allclose(s.total_emitter_area, expect_area, rtol=1e-9)
    np.testing.assert_allclose(s.total_power, expect_power, rtol=1e-9)
    summary = s.summary()
    assert summary["triangles"] == triangles and summary["emitter_triangles"] == emitter_triangles
    assert summary["receivers"] == receivers


def test_emitter_cdfs(bundled_scene):
    """The area and power CDFs have E + L + 1 entries, start at 0, end at exactly 1, never
    decrease, and their steps are each light's share (emitter triangles, then sphere
    lights) of area and of power."""
    s = bundled_scene
    areas = s.light_areas
    power = areas * s.light_radiance
    for name, weights in (("area_cdf", areas), ("power_cdf", power)):
        cdf = getattr(upload(s).data, name).numpy().astype(np.float64)
        assert cdf.shape == (s.light_count + 1,), name
        assert cdf[0] == 0.0 and cdf[-1] == 1.0, name
        assert np.all(np.diff(cdf) >= 0.0), name
        np.testing.assert_allclose(np.diff(cdf), weights / weights.sum(), atol=1e-6, err_msg=name)
    assert np.all(areas > 0)


def test_warp_data_mirrors_numpy(bundled_scene):
    """upload(scene).data holds the same geometry, emission and emitter tables as the numpy
    scene (to float32), and scene.receiver_data the same receivers."""
    s = bundled_scene
    d = upload(s).data
    np.testing.assert_array_equal(d.points.numpy(), s.vertices.astype(np.float32))
    np.testing.assert_array_equal(d.indices.numpy(), s.triangles.reshape(-1))
    np.testing.assert_array_equal(d.tri_emission.numpy(), s.emission.astype(np.float32))
    np.testing.assert_array_equal(d.emitter_tri.numpy(), s.emitters)
    np.testing.assert_array_equal(d.emitter_area.numpy(), s.emitter_areas.astype(np.float32))
    assert np.all(s.emission[s.emitters] > 0) and np.count_nonzero(s.emission) == s.emitter_count
    assert d.emitter_count == s.emitter_count
    np.testing.assert_allclose(d.total_area, s.total_emitter_area, rtol=1e-6)
    np.testing.assert_allclose(d.total_power, s.total_power, rtol=1e-6)
    r = upload(s).receiver_data
    np.testing.assert_allclose(r.position.numpy(), s.receivers.positions, atol=1e-6)
    np.testing.assert_allclose(r.normal.numpy(), s.receivers.normals, atol=1e-6)
    np.testing.assert_array_equal(r.material.numpy(), s.receivers.material)


def test_self_hit_slab_follows_the_coordinates_around_each_receiver(bundled_scene):
    """Each receiver's slab is SELF_HIT_SLAB × the largest coordinate magnitude of the
    receiver and of the triangles that touch it (to SELF_HIT_SLAB × their magnitude)
    outside its own plane (numpy and trimesh's closest points over all triangles, against
    the Warp kernel's BVH query): local magnitudes only, no scene size."""
    import trimesh

    s = bundled_scene
    tris = s.triangle_vertices().astype(np.float32).astype(np.float64)
    normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    mag = np.abs(tris).max(axis=(1, 2))
    for r, (x, n) in enumerate(zip(s.receivers.positions.astype(np.float32).astype(np.float64),
                                   s.receivers.normals.astype(np.float32).astype(np.float64))):
        m = np.maximum(mag, np.abs(x).max())
        height = np.abs(np.einsum("ij,ij->i", x - tris[:, 0], normal))
        own_plane = (np.abs(normal @ n) >= 1 - 1e-6) & (height <= SELF_HIT_SLAB * m)
        distance = np.linalg.norm(trimesh.triangles.closest_point(tris, np.tile(x, (len(tris), 1))) - x, axis=1)
        touching = ~own_plane & (distance <= SELF_HIT_SLAB * m)
        scale = max(np.abs(x).max(), m[touching].max() if touching.any() else 0.0)
        np.testing.assert_allclose(upload(s).slab[r], SELF_HIT_SLAB * scale, rtol=1e-6, err_msg=f"{s.name} receiver {r}")
    np.testing.assert_array_equal(upload(s).receiver_data.slab.numpy(), upload(s).slab.astype(np.float32))


def test_bundled_receivers_and_materials(bundled_scene):
    """Receivers are where the scene file puts them, with unit normals along the written
    normal, and each group's material (type, albedo, exponent, unit view) is the one
    written, per [[receivers]] group where a group has its own."""
    s = bundled_scene
    rx = s.receivers
    np.testing.assert_allclose(np.linalg.norm(rx.normals, axis=1), 1.0, atol=1e-12)
    doc = _toml(s)
    groups = doc["receivers"] if isinstance(doc["receivers"], list) else [doc["receivers"]]
    assert len(rx.group_names) == len(groups)
    start = 0
    for g, spec in enumerate(groups):
        points = np.array(spec["points"], dtype=float)
        rows = slice(start, start + len(points))
        start += len(points)
        assert np.all(rx.group[rows] == g)
        if "name" in spec:
            assert rx.group_names[g] == spec["name"]
        np.testing.assert_array_equal(rx.positions[rows], points)
        n = np.array(spec["normal"], dtype=float)
        np.testing.assert_allclose(rx.normals[rows], np.tile(n / np.linalg.norm(n), (len(points), 1)), atol=1e-12)
        mat = spec.get("material", doc.get("material"))
        assert np.all(rx.material[rows] == MATERIALS[mat["type"]].code)
        np.testing.assert_allclose(rx.albedo[rows], mat.get("albedo", 1.0))
        if mat["type"] == "phong":
            np.testing.assert_allclose(rx.exponent[rows], mat["exponent"])
            v = np.array(mat["view"], dtype=float)
            np.testing.assert_allclose(rx.view[rows], np.tile(v / np.linalg.norm(v), (len(points), 1)), atol=1e-12)
    assert start == len(rx)
    if s.name == "veach-plates":
        assert rx.group_names == ["plate-1", "plate-2", "plate-3", "plate-4"]
        assert [rx.exponent[rx.group == g][0] for g in range(4)] == [10.0, 50.0, 300.0, 2000.0]
        assert {rx.material_name(i) for i in range(len(rx))} == {"phong"}
    else:
        assert {rx.material_name(i) for i in range(len(rx))} == {"irradiance"}


# =========================================================================== small scenes

# One triangle with corners on the axes, so every image is easy to compute by hand.
TRIANGLE = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])

TRANSFORMS = {
    # translate only
    "translate": ({"translate": [1.0, 2.0, 3.0]},
                  [[2, 2, 3], [1, 3, 3], [1, 2, 4]]),
    # uniform scale
    "scale": ({"scale": 2.0},
              [[2, 0, 0], [0, 2, 0], [0, 0, 2]]),
    # per-axis scale
    "scale-xyz": ({"scale": [2.0, 3.0, 4.0]},
                  [[2, 0, 0], [0, 3, 0], [0, 0, 4]]),
    # right-handed 90° about +z: x → y, y → −x
    "rotate-z": ({"rotate": {"axis": [0, 0, 1], "degrees": 90}},
                 [[0, 1, 0], [-1, 0, 0], [0, 0, 1]]),
    # right-handed 90° about +x: y → z, z → −y
    "rotate-x": ({"rotate": {"axis": [1, 0, 0], "degrees": 90}},
                 [[1, 0, 0], [0, 0, 1], [0, -1, 0]]),
    # right-handed 90° about +y: z → x, x → −z; the axis need not be unit length
    "rotate-y": ({"rotate": {"axis": [0, 5, 0], "degrees": 90}},
                 [[0, 0, -1], [0, 1, 0], [1, 0, 0]]),
    # 120° about (1,1,1) cycles the axes: x → y → z → x
    "rotate-diagonal": ({"rotate": {"axis": [1, 1, 1], "degrees": 120}},
                        [[0, 1, 0], [0, 0, 1], [1, 0, 0]]),
    # scale (2,3,4), then 90° about z, then translate: (1,0,0) → (2,0,0) → (0,2,0) → (1,4,3);
    # rotating first would give (0,3,0) → (1,5,3) instead
    "scale-rotate-translate": ({"translate": [1.0, 2.0, 3.0], "scale": [2.0, 3.0, 4.0],
                                "rotate": {"axis": [0, 0, 1], "degrees": 90}},
                               [[1, 4, 3], [-2, 2, 3], [1, 2, 7]]),
}


@pytest.mark.parametrize("case", list(TRANSFORMS))
def test_transform(case, tmp_path):
    """A [[mesh]] transform applies scale (scalar or per-axis), then a right-handed
    rotation about the (normalised) axis, then translation: the loaded triangle's corners
    are the hand-computed ones, in the numpy scene and in the Warp mesh."""
    transform, expected = TRANSFORMS[case]
    path = write_scene(tmp_path, meshes=[
        {"path": "tri.obj", "vertices": TRIANGLE, "faces": [[0, 1, 2]], "transform": transform},
        light_entry(height=5.0)])
    s = load_scene(path)
    corners = s.triangle_vertices(np.flatnonzero(s.triangle_mesh == 0))
    np.testing.assert_allclose(corners[0], expected, atol=1e-12)
    warp_points = upload(s).data.points.numpy()[upload(s).data.indices.numpy()[:3]]
    np.testing.assert_allclose(warp_points, expected, atol=1e-6)


def test_transform_of_an_emitter(tmp_path):
    """A transformed emitter's triangles, areas and power follow the transform: scale
    [2, 3, 1] multiplies a horizontal light's area by 6, rotation keeps it, and the
    light's centre lands on the translation."""
    light = light_entry(height=0.0, half=0.5, emission=4.0,
                        transform={"scale": [2.0, 3.0, 1.0], "rotate": {"axis": [0, 0, 1], "degrees": 30},
                                   "translate": [0.5, -0.25, 2.0]})
    s = load_scene(write_scene(tmp_path, meshes=[floor_entry(), light]))
    np.testing.assert_allclose(s.total_emitter_area, 6.0, rtol=1e-12)
    np.testing.assert_allclose(s.total_power, 24.0, rtol=1e-12)
    centre = s.vertices[np.unique(s.triangles[s.emitters])].mean(axis=0)
    np.testing.assert_allclose(centre, [0.5, -0.25, 2.0], atol=1e-12)


def test_receiver_groups_with_materials(tmp_path):
    """[[receivers]] groups keep their order, names and own materials (lambert, phong);
    a group without a material takes the scene's [material]; per-point normals are
    normalised; a view vector is normalised."""
    groups = [
        {"name": "diffuse", "points": [[0, 0, 0], [0.5, 0, 0]], "normals": [[0, 0, 2], [0, 1, 1]],
         "material": {"type": "lambert", "albedo": 0.25}},
        {"name": "glossy", "points": [[-0.5, 0, 0]], "normal": [0, 0, 1],
         "material": {"type": "phong", "albedo": 0.5, "exponent": 20.0, "view": [0, -3, 4]}},
        {"points": [[0, 0.5, 0]], "normal": [0, 0, 1]},
    ]
    s = load_scene(write_scene(tmp_path, receivers=groups, material={"type": "irradiance"}))
    rx = s.receivers
    assert len(rx) == 4
    assert list(rx.group) == [0, 0, 1, 2]
    assert rx.group_names[:2] == ["diffuse", "glossy"]
    assert [rx.material_name(i) for i in range(4)] == ["lambert", "lambert", "phong", "irradiance"]
    codes = [MATERIALS[m].code for m in ("lambert", "lambert", "phong", "irradiance")]
    np.testing.assert_array_equal(rx.material, codes)
    np.testing.assert_allclose(rx.albedo, [0.25, 0.25, 0.5, 1.0])
    assert rx.exponent[2] == 20.0
    np.testing.assert_allclose(rx.view[2], [0, -0.6, 0.8], atol=1e-12)
    np.testing.assert_allclose(rx.normals[:2], [[0, 0, 1], [0, math.sqrt(0.5), math.sqrt(0.5)]], atol=1e-12)
    np.testing.assert_allclose(rx.positions, [[0, 0, 0], [0.5, 0, 0], [-0.5, 0, 0], [0, 0.5, 0]])
    assert rx.grid_shape is None
    np.testing.assert_array_equal(upload(s).receiver_data.material.numpy(), rx.material)


def test_grid_receivers(tmp_path):
    """A grid gives one receiver per cell centre, resolution[0] × resolution[1] of them,
    laid out so that positions.reshape(rows, cols) is an image (row j along edge_v,
    column i along edge_u), with default normal = normalise(edge_u × edge_v)."""
    origin, eu, ev = np.array([-1.0, -1.0, 0.0]), np.array([2.0, 0.0, 0.0]), np.array([0.0, 1.0, 1.0])
    nu, nv = 4, 3
    grid = {"origin": origin, "edge_u": eu, "edge_v": ev, "resolution": [nu, nv]}
    s = load_scene(write_scene(tmp_path, receivers={"grid": grid}))
    rx = s.receivers
    assert len(rx) == nu * nv
    assert rx.grid_shape == (nv, nu)
    image = rx.positions.reshape(nv, nu, 3)
    for j in range(nv):
        for i in range(nu):
            np.testing.assert_allclose(image[j, i], origin + (i + 0.5) / nu * eu + (j + 0.5) / nv * ev, atol=1e-12)
    np.testing.assert_allclose(rx.normals, np.tile([0.0, -math.sqrt(0.5), math.sqrt(0.5)], (nu * nv, 1)), atol=1e-12)


def test_grid_receivers_explicit_normal(tmp_path):
    """An explicit normal overrides a grid's default one (normalised); a 1×1 grid is
    its centre."""
    grid = {"origin": [0, 0, 0], "edge_u": [1, 0, 0], "edge_v": [0, 1, 0], "resolution": [1, 1]}
    s = load_scene(write_scene(tmp_path, receivers={"grid": grid, "normal": [0, 0, -3]}))
    np.testing.assert_allclose(s.receivers.positions, [[0.5, 0.5, 0.0]])
    np.testing.assert_allclose(s.receivers.normals, [[0.0, 0.0, -1.0]])


def test_scene_by_name_path_or_directory(loaded_scenes, tmp_path):
    """A bundled scene loads the same by name, by the path of its scene.toml (str or
    Path) and by its directory; a written scene loads by file and by directory, and a
    scene file not named scene.toml takes its name from the file's stem when it has none."""
    by_name = loaded_scenes["occluded-quad"]
    folder = MESHES / "occluded-quad"
    for how in (folder / "scene.toml", str(folder / "scene.toml"), folder, str(folder)):
        s = load_scene(how)
        assert s.name == "occluded-quad"
        assert s.path.resolve() == by_name.path.resolve()
        np.testing.assert_array_equal(s.vertices, by_name.vertices)
        np.testing.assert_array_equal(s.triangles, by_name.triangles)
        np.testing.assert_array_equal(s.receivers.positions, by_name.receivers.positions)
    path = write_scene(tmp_path)
    assert load_scene(tmp_path).path == path == load_scene(path).path
    other = write_scene(tmp_path, name=None, filename="my-room.toml")
    assert load_scene(other).name == "my-room"


@pytest.mark.parametrize("suffix", ["obj", "ply", "stl", "off", "glb"])
def test_mesh_formats(suffix, tmp_path):
    """The same light quad written as OBJ, PLY, STL, OFF or GLB (by trimesh's exporters)
    loads with identical triangles: the same corner positions in the same order (STL has
    no shared vertices, so corners are compared, not indices), the same area and the same
    winding (front face down)."""
    v, f = quad((0.25, -0.5, 1.5), (0.5, 0.75), "down")
    light = {"path": f"light.{suffix}", "emission": 3.0}
    write_mesh(tmp_path / light["path"], v, f)
    s = load_scene(write_scene(tmp_path, meshes=[floor_entry(), light]))
    corners = s.triangle_vertices(s.emitters)
    np.testing.assert_allclose(corners, v[f], atol=1e-6)
    np.testing.assert_allclose(s.total_emitter_area, 1.5, rtol=1e-6)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert np.all(normals[:, 2] < 0)
    if suffix != "stl":
        tri = s.triangles[s.emitters] - s.triangles[s.emitters].min()
        np.testing.assert_array_equal(tri, f)


# =========================================================================== bad input


def _light_with_vertex(value: float):
    v, f = quad((0.0, 0.0, 1.0))
    v[2, 2] = value
    return {"path": "light.obj", "emission": 1.0, "vertices": v, "faces": f}


_GRID = {"origin": [0, 0, 0], "edge_u": [1, 0, 0], "edge_v": [0, 1, 0], "resolution": [2, 2]}
_DEGENERATE = {"path": "light.obj", "emission": 1.0,
               "vertices": [[0, 0, 1], [1, 0, 1], [2, 0, 1]], "faces": [[0, 1, 2]]}

# name → (write_scene keyword arguments, file named in the message (relative to the scene's
# folder), words of the problem).  Each builds a scene that is wrong in exactly one way.
BAD = {
    "missing-mesh": (dict(meshes=[floor_entry(), {"path": "nowhere.obj", "emission": 1.0}]),
                     "nowhere.obj", "mesh file not found"),
    "garbage-ply": (dict(meshes=[floor_entry(), {"path": "light.ply", "emission": 1.0,
                                                 "content": np.random.default_rng(7).bytes(512)}]),
                    "light.ply", "trimesh cannot read"),
    "obj-without-faces": (dict(meshes=[floor_entry(), {"path": "light.obj", "emission": 1.0,
                                                       "content": "this is not a mesh\nat all\n"}]),
                          "light.obj", "no triangles"),
    "obj-bad-face": (dict(meshes=[floor_entry(), {"path": "light.obj", "emission": 1.0,
                                                  "content": "v 0 0 1\nv 1 0 1\nv 0 1 1\nf 1 2 x\n"}]),
                     "light.obj", "trimesh cannot read"),
    "obj-face-out-of-range": (dict(meshes=[floor_entry(), {"path": "light.obj", "emission": 1.0,
                                                           "content": "v 0 0 1\nv 1 0 1\nv 0 1 1\nf 1 2 9\n"}]),
                              "light.obj", "cannot read"),
    "nan-vertex": (dict(meshes=[floor_entry(), _light_with_vertex(math.nan)]), "light.obj", "NaN or infinite"),
    "inf-vertex": (dict(meshes=[floor_entry(), _light_with_vertex(math.inf)]), "light.obj", "NaN or infinite"),
    "minus-inf-vertex": (dict(meshes=[floor_entry(), _light_with_vertex(-math.inf)]), "light.obj", "NaN or infinite"),
    "all-emitter-triangles-zero-area": (dict(meshes=[floor_entry(), _DEGENERATE]), "light.obj", "zero area"),
    "negative-emission": (dict(meshes=[floor_entry(), light_entry(emission=-1.0)]), "scene.toml", "emission"),
    "nan-emission": (dict(meshes=[floor_entry(), light_entry(emission=math.nan)]), "scene.toml", "emission"),
    "inf-emission": (dict(meshes=[floor_entry(), light_entry(emission=math.inf)]), "scene.toml", "emission"),
    "text-emission": (dict(meshes=[floor_entry(), light_entry(emission="bright")]), "scene.toml", "emission"),
    "no-emitter": (dict(meshes=[floor_entry(), light_entry(emission=0.0)]), "scene.toml", "no emitter"),
    "zero-normal": (dict(receivers={"points": [[0, 0, 0]], "normal": [0, 0, 0]}), "scene.toml", "zero length"),
    "one-zero-normal": (dict(receivers={"points": [[0, 0, 0], [1, 0, 0]], "normals": [[0, 0, 1], [0, 0, 0]]}),
                        "scene.toml", "zero length"),
    "zero-grid-resolution": (dict(receivers={"grid": _GRID | {"resolution": [0, 4]}}), "scene.toml", "resolution"),
    "unknown-top-key": (dict(extra={"colour": "red"}), "scene.toml", "unknown key 'colour'"),
    "unknown-mesh-key": (dict(meshes=[floor_entry(), light_entry(emmission=3.0)]), "scene.toml",
                         "unknown key 'emmission'"),
    "unknown-transform-key": (dict(meshes=[floor_entry(transform={"shear": 0.5}), light_entry()]), "scene.toml",
                              "unknown key 'shear'"),
    "unknown-rotate-key": (dict(meshes=[floor_entry(transform={"rotate": {"axis": [0, 0, 1], "angle": 30}}),
                                        light_entry()]),
                           "scene.toml", "unknown key 'angle'"),
    "unknown-receivers-key": (dict(receivers={"points": [[0, 0, 0]], "normal": [0, 0, 1], "offset": 0.1}),
                              "scene.toml", "unknown key 'offset'"),
    "unknown-grid-key": (dict(receivers={"grid": _GRID | {"spacing": 0.1}}), "scene.toml", "unknown key 'spacing'"),
    "unknown-material-key": (dict(material={"type": "lambert", "albedo": 0.5, "roughness": 0.1}), "scene.toml",
                             "unknown key 'roughness'"),
    "unknown-group-material-key": (dict(receivers=[{"points": [[0, 0, 0]], "normal": [0, 0, 1],
                                                    "material": {"type": "irradiance", "albedo": 0.5}}]),
                                   "scene.toml", "unknown key 'albedo'"),
    "unknown-material-type": (dict(material={"type": "mirror"}), "scene.toml", "'mirror'"),
    "phong-without-view": (dict(material={"type": "phong", "albedo": 0.5, "exponent": 10.0}), "scene.toml",
                           "missing key 'view'"),
}


def _bad_scene(case: str, tmp_path: Path) -> tuple[Path, str, str]:
    """Write case ``case`` of BAD (or of the file-level cases) → (scene argument, file, problem)."""
    if case == "invalid-toml":
        path = tmp_path / "scene.toml"
        path.write_text('name = "broken"\n[[mesh]\npath = "floor.obj"\n')
        return path, str(path), "not valid TOML"
    if case == "scene-not-utf8":
        path = tmp_path / "scene.toml"
        path.write_bytes(b'name = "caf\xe9"\n')
        return path, str(path), "not UTF-8"
    if case == "scene-file-not-found":
        path = tmp_path / "absent" / "scene.toml"
        return path, str(path), "no such scene file"
    if case == "unknown-bundled-name":
        return Path("occluded-quadd"), "occluded-quadd", "bundled: " + ", ".join(sorted(BUNDLED + MITSUBA_BUNDLED + CAMERA_BUNDLED))
    kwargs, file, problem = BAD[case]
    path = write_scene(tmp_path, **kwargs)
    return path, str(tmp_path / file), problem


BAD_CASES = list(BAD) + ["invalid-toml", "scene-not-utf8", "scene-file-not-found", "unknown-bundled-name"]


@pytest.mark.parametrize("case", BAD_CASES)
def test_bad_scene_raises_one_line_error(case, tmp_path):
    """Each bad scene raises WarpisError whose message is one line starting with the
    offending file's path and naming the problem."""
    scene, file, problem = _bad_scene(case, tmp_path)
    with pytest.raises(WarpisError) as info:
        load_scene(scene)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"{file}: "), message
    assert problem in message, message


@pytest.mark.parametrize("case", BAD_CASES)
def test_bad_scene_cli(case, tmp_path, cli):
    """`warpis info` on each bad scene exits with status 2, prints exactly one line on
    stderr, `warpis: error: <file>: <problem>`, no traceback and nothing on stdout."""
    scene, file, problem = _bad_scene(case, tmp_path)
    result = cli("info", scene)
    assert result.status == 2
    assert result.out == ""
    assert len(result.err_lines) == 1, result.err
    line = result.err_lines[0]
    assert line.startswith(f"warpis: error: {file}: "), line
    assert problem in line and "Traceback" not in result.err


@pytest.mark.parametrize("case", ["garbage-ply", "nan-emission", "invalid-toml"])
def test_bad_scene_cli_process(case, tmp_path):
    """In a fresh process too (Warp's start-up notices included), a bad scene gives exit
    status 2, one `warpis: error:` line on stderr and nothing on stdout."""
    scene, file, problem = _bad_scene(case, tmp_path)
    result = run_warpis("info", scene)
    assert result.status == 2
    assert result.out == ""
    assert len(result.err_lines) == 1, result.err
    assert result.err_lines[0].startswith(f"warpis: error: {file}: ")
    assert problem in result.err and "Traceback" not in result.err


def test_zero_area_emitter_triangles_dropped_with_warning(tmp_path, cli):
    """Zero-area triangles of an emitter that keeps some area are dropped from the
    emitters with a warning naming the mesh file (not an error); the CLI prints the
    warning as `warpis: warning: ...` on stderr and still reports the scene."""
    v, f = quad((0.0, 0.0, 1.0), 0.5, "down")
    v = np.vstack([v, [[0.0, 0.0, 1.0], [0.1, 0.0, 1.0], [0.3, 0.0, 1.0]]])  # collinear: zero area
    f = np.vstack([f, [[4, 5, 6]]])
    path = write_scene(tmp_path, meshes=[floor_entry(), {"path": "light.obj", "emission": 2.0, "vertices": v,
                                                         "faces": f}])
    light = str(tmp_path / "light.obj")
    with pytest.warns(UserWarning) as record:
        s = load_scene(path)
    messages = [str(w.message) for w in record]
    assert any(m.startswith(f"{light}: ") and "zero-area" in m and "1 " in m for m in messages), messages
    assert s.triangle_count == 5 and s.emitter_count == 2
    assert s.emission[4] == 0.0 and 4 not in s.emitters
    np.testing.assert_allclose(s.total_emitter_area, 1.0)

    result = cli("info", path)
    assert result.status == 0
    warning_lines = [line for line in result.err_lines if line.startswith("warpis: warning:")]
    assert len(warning_lines) == 1 and light in warning_lines[0] and "zero-area" in warning_lines[0]
    assert "test-scene" in result.out and "Traceback" not in result.err


# =========================================================================== ray casting

FAR = 1.0e30
EDGE_TOLERANCE = 1e-5  # barycentric, i.e. relative to the triangle's size
DISTANCE_RTOL = 1e-4
RANDOM_TARGETS = 200


@wp.kernel(enable_backward=False)
def _cast_kernel(scene: SceneData, origins: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3),
                 face: wp.array(dtype=wp.int32), dist: wp.array(dtype=wp.float32),
                 sign: wp.array(dtype=wp.float32), radiance: wp.array(dtype=wp.float32)):
    i = wp.tid()
    q = wp.mesh_query_ray(scene.mesh, origins[i], dirs[i], FAR)
    face[i] = -1
    if q.result:
        face[i] = q.face
        dist[i] = q.t
        sign[i] = q.sign
    radiance[i] = incident_radiance(scene, origins[i], dirs[i])


def warp_cast(scene: warpis.Scene, origins: np.ndarray, dirs: np.ndarray):
    """First hit of each ray through the scene's Warp mesh: face (−1: miss), t, sign, and
    the radiance warpis.kernels.integrand.incident_radiance returns."""
    k = len(origins)
    args = [wp.array(origins.astype(np.float32), dtype=wp.vec3), wp.array(dirs.astype(np.float32), dtype=wp.vec3)]
    out = [wp.zeros(k, dtype=wp.int32), wp.zeros(k, dtype=wp.float32), wp.zeros(k, dtype=wp.float32),
           wp.zeros(k, dtype=wp.float32)]
    wp.launch(_cast_kernel, dim=k, inputs=[upload(scene).data, *args, *out], device=scene.device)
    return tuple(a.numpy() for a in out)


def _passes_near(centre: np.ndarray, radius: np.ndarray, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Whether each ray (origin, unit dirs) can meet each sphere (centre, radius): (S, K) bool."""
    to_centre = centre - origin
    along = to_centre @ dirs.T
    off2 = np.einsum("ij,ij->i", to_centre, to_centre)[:, None] - along**2
    return (off2 <= radius[:, None] ** 2) & (along >= -radius[:, None])


def _candidate_pairs(triangles: np.ndarray, origin: np.ndarray, dirs: np.ndarray, cells: int = 16):
    """(ray, triangle) index pairs whose bounding spheres the ray passes through.

    A conservative cull, so that brute force stays fast on 82k triangles: triangles are
    grouped by the cell of a cells³ grid holding their centre; a ray is tested against
    each group's bounding sphere, then against the bounding sphere of each triangle of
    the groups it passes.  Spheres are enlarged by 0.1%, far more than EDGE_TOLERANCE
    enlarges a triangle, so no pair that could hit is dropped.
    """
    centre = triangles.mean(axis=1)
    radius = np.linalg.norm(triangles - centre[:, None], axis=2).max(axis=1) * (1 + 1e-3) + 1e-12
    lo, hi = centre.min(axis=0), centre.max(axis=0)
    cell = np.minimum(((centre - lo) / np.maximum(hi - lo, 1e-300) * cells).astype(np.int64), cells - 1)
    key = (cell[:, 0] * cells + cell[:, 1]) * cells + cell[:, 2]
    order = np.argsort(key, kind="stable")
    _, start, count = np.unique(key[order], return_index=True, return_counts=True)
    group_of = np.repeat(np.arange(len(start)), count)  # group of each triangle in `order`
    group_centre = np.add.reduceat(centre[order], start) / count[:, None]
    reach = np.linalg.norm(centre[order] - group_centre[group_of], axis=1) + radius[order]
    group_radius = np.maximum.reduceat(reach, start) * (1 + 1e-3)
    group, ray = np.nonzero(_passes_near(group_centre, group_radius, origin, dirs))
    n = count[group]
    offset = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
    tri = order[np.repeat(start[group], n) + offset]
    ray = np.repeat(ray, n)
    to_centre = centre[tri] - origin
    along = np.einsum("ij,ij->i", to_centre, dirs[ray])
    off2 = np.einsum("ij,ij->i", to_centre, to_centre) - along**2
    near = (off2 <= radius[tri] ** 2) & (along >= -radius[tri])
    return ray[near], tri[near]


def brute_first_hit(triangles: np.ndarray, origin: np.ndarray, dirs: np.ndarray, cull: bool = True):
    """First hit of rays sharing one origin, by testing every ray against every triangle.

    Every (ray, triangle) pair that :func:`_candidate_pairs` cannot rule out by bounding
    spheres (every pair, with ``cull=False``) gets the exact float64 Möller–Trumbore
    test; the first hit is the nearest.

    Returns per ray: the first hit's face (−1: miss) and distance, whether that hit is on
    the front face (the side the winding's normal points to), and whether the ray is
    *ambiguous*: its first-hit face changes when every triangle is shrunk or enlarged by
    EDGE_TOLERANCE in barycentric coordinates (it passes that close to an edge).
    """
    v0, e1, e2 = triangles[:, 0], triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]
    k = len(dirs)
    if cull:
        ray, tri = _candidate_pairs(triangles, origin, dirs)
    else:
        ray, tri = (x.ravel() for x in np.meshgrid(np.arange(k), np.arange(len(triangles)), indexing="ij"))

    # Möller–Trumbore on the pairs: det = e1·(d × e2), u = s·(d × e2)/det,
    # v = d·(s × e1)/det, t = e2·(s × e1)/det, with s = origin − v0.
    d, a, b = dirs[ray], e1[tri], e2[tri]
    s = origin - v0[tri]
    pvec = np.cross(d, b)
    qvec = np.cross(s, a)
    det = np.einsum("ij,ij->i", a, pvec)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        u = np.einsum("ij,ij->i", s, pvec) * inv
        v = np.einsum("ij,ij->i", d, qvec) * inv
        t = np.einsum("ij,ij->i", b, qvec) * inv
        lowest = np.minimum(np.minimum(u, v), 1.0 - u - v)
    valid = np.isfinite(inv) & (t > 0.0)

    def nearest(inside: np.ndarray):
        hit_t = np.where(valid & inside, t, np.inf)
        order = np.lexsort((hit_t, ray))
        first = order[np.flatnonzero(np.diff(ray[order], prepend=-1))]  # nearest per ray
        first = first[np.isfinite(hit_t[first])]
        face, dist, front = np.full(k, -1), np.full(k, np.inf), np.zeros(k, bool)
        face[ray[first]] = tri[first]
        dist[ray[first]] = hit_t[first]
        front[ray[first]] = det[first] > 0.0  # det = −d·(e1 × e2) > 0: the ray meets the front
        return face, dist, front

    face, dist, front = nearest(lowest >= 0.0)
    shrunk, _, _ = nearest(lowest >= EDGE_TOLERANCE)
    enlarged, _, _ = nearest(lowest >= -EDGE_TOLERANCE)
    return face, dist, front, shrunk != enlarged


def emitter_targets(scene: warpis.Scene, count: int, seed: int, mesh: int | None = None):
    """The centre of each emitter mesh (mean of its distinct vertices: a quad's centre,
    a sphere's centre), then ``count`` fixed uniformly random points on the emitter
    triangles (of mesh ``mesh`` only, if given).  Returns (centres, points, mesh of each centre)."""
    owner = scene.triangle_mesh[scene.emitters]
    meshes = np.unique(owner) if mesh is None else np.array([mesh])
    centres = np.array([scene.vertices[np.unique(scene.triangles[scene.emitters[owner == m]])].mean(axis=0)
                        for m in meshes])
    pick = np.isin(owner, meshes)
    tris = scene.triangle_vertices(scene.emitters[pick])
    areas = scene.emitter_areas[pick]
    rng = np.random.default_rng(seed)
    which = rng.choice(len(tris), size=count, p=areas / areas.sum())
    r1, r2 = np.sqrt(rng.random(count)), rng.random(count)
    t = tris[which]
    points = (1 - r1)[:, None] * t[:, 0] + (r1 * (1 - r2))[:, None] * t[:, 1] + (r1 * r2)[:, None] * t[:, 2]
    return centres, points, meshes


def shading_rays(scene: warpis.Scene, receiver: int, targets: np.ndarray):
    """Rays from just above receiver x to ``targets``, rounded to float32 as the kernel
    sees them, so both casts get the same rays.  The origin is SELF_HIT_SLAB × the
    scene's largest coordinate along n: clear of the rounding of every triangle, the
    receiver's own among them, for a query that ignores no plane (the integrand's
    ignores the receiver's own, bvh.py, and needs a smaller slab)."""
    x, n = scene.receivers.positions[receiver], scene.receivers.normals[receiver]
    height = SELF_HIT_SLAB * max(float(np.abs(x).max()), float(np.abs(scene.vertices).max()))
    origin = (x + height * n).astype(np.float32).astype(np.float64)
    d = targets - origin
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32).astype(np.float64)
    return origin, d


@pytest.fixture(scope="module")
def triangle_scenes(loaded_scenes, tmp_path_factory):
    """The bundled scenes, veach-plates with its sphere lights as 320-triangle icospheres:
    the brute-force triangle casts below compare triangles (test_sphere_lights.py holds
    the analytic spheres)."""
    out = dict(loaded_scenes)
    out["veach-plates"] = load_scene(tessellated_veach_plates(tmp_path_factory.mktemp("veach-tri")))
    return out


def test_brute_force_cull_drops_no_hit(triangle_scenes):
    """The bounding-sphere cull of the brute-force reference is conservative: with and
    without it, the same rays give the same first hits, distances, facings and
    ambiguity flags (all rays of occluded-quad and veach-plates' first plate, 16 rays
    from an umbra and a penumbra receiver of heavy-occluder)."""
    for name, receivers, count in (("occluded-quad", range(8), RANDOM_TARGETS),
                                   ("veach-plates", range(4), 60), ("heavy-occluder", (3, 4), 16)):
        s = triangle_scenes[name]
        centres, points, _ = emitter_targets(s, count, seed=99)
        tris = s.triangle_vertices()
        for r in receivers:
            origin, d = shading_rays(s, r, np.vstack([centres, points]))
            culled, full = brute_first_hit(tris, origin, d), brute_first_hit(tris, origin, d, cull=False)
            for a, b in zip(culled, full):
                np.testing.assert_array_equal(a, b, err_msg=f"{name} receiver {r}")


def test_warp_ray_cast_matches_brute_force(bundled_scene, triangle_scenes):
    """From every receiver's shading point, rays to each emitter's centre and to 200
    fixed random points on the emitters find the same first hit through the Warp mesh
    as a float64 brute-force Möller–Trumbore over all triangles: same face (or both
    miss), distance within 1e-4 relative, same facing (Warp's sign > 0 ⇔ front face),
    and incident_radiance = the emission of a front-face hit, else 0.

    Rule for ties: a ray is left out of the comparison when its brute-force first hit
    changes between shrinking and enlarging every triangle by 1e-5 in barycentric
    coordinates (relative to the triangle's size), i.e. when it passes within 1e-5 of a
    triangle edge, such as a quad light's diagonal through its centre; such rays may
    legitimately hit either neighbour.  At most 5% of the rays may be left out."""
    s = triangle_scenes[bundled_scene.name]  # veach-plates: its tessellated twin
    centres, points, _ = emitter_targets(s, RANDOM_TARGETS, seed=12345)
    targets = np.vstack([centres, points])
    tris = s.triangle_vertices()
    origins, dirs, expected = [], [], []
    for r in range(len(s.receivers)):
        origin, d = shading_rays(s, r, targets)
        origins.append(np.tile(origin, (len(d), 1)))
        dirs.append(d)
        expected.append(brute_first_hit(tris, origin, d))
    face, dist, sign, radiance = warp_cast(s, np.vstack(origins), np.vstack(dirs))
    b_face, b_dist, b_front, ambiguous = (np.concatenate(x) for x in zip(*expected))

    keep = ~ambiguous
    # Not a test of chance: the targets are fixed (seed 12345), so these fractions are
    # properties of one deterministic set of rays, asserted so that the comparison below
    # covers nearly all of them.  Measured: ≥ 99.4% kept on every bundled scene.
    assert keep.mean() >= 0.95, f"{(~keep).sum()} of {len(keep)} rays are within {EDGE_TOLERANCE} of an edge"
    mismatch = np.flatnonzero(keep & (face != b_face))
    assert len(mismatch) == 0, f"{s.name}: rays {mismatch[:10]}: warp {face[mismatch[:10]]}, " \
                               f"brute force {b_face[mismatch[:10]]}"
    hit = keep & (b_face >= 0)
    assert hit.mean() > 0.5  # deterministic as above; measured ≥ 99.4% (the rays aim at emitters)
    np.testing.assert_allclose(dist[hit], b_dist[hit], rtol=DISTANCE_RTOL)
    np.testing.assert_array_equal(sign[hit] > 0, b_front[hit])
    expected_le = np.where(b_front & (b_face >= 0), s.emission[np.maximum(b_face, 0)], 0.0).astype(np.float32)
    np.testing.assert_array_equal(radiance[keep], expected_le[keep])


# Receiver labels w.r.t. the brightest emitter mesh (its [[mesh]] index), from the
# visibility table scripts/make_scenes.py prints (warpis.scenes.builders.mesh_scenes): fully lit,
# or in the umbra of the occluder.
SHADOWS = {
    "occluded-quad": {"light": 1, "occluder": 2, "lit": [0, 7], "umbra": [3, 4]},
    "two-lights": {"light": 1, "occluder": 3, "lit": [0, 1, 2, 7], "umbra": [4, 5]},
    "heavy-occluder": {"light": 1, "occluder": 2, "lit": [0, 1, 7], "umbra": [4, 5]},
}


@pytest.mark.parametrize("name", list(SHADOWS))
def test_shadow_rays_hit_what_the_scene_says(name, loaded_scenes):
    """Through the Warp mesh, from a lit receiver the ray to the light's centre hits the
    light's front face and so do the rays to 200 random points on it; from an umbra
    receiver the ray to the centre hits the occluder and no ray reaches the light."""
    s = loaded_scenes[name]
    spec = SHADOWS[name]
    centres, points, _ = emitter_targets(s, RANDOM_TARGETS, seed=777, mesh=spec["light"])
    targets = np.vstack([centres, points])
    for r in spec["lit"] + spec["umbra"]:
        origin, d = shading_rays(s, r, targets)
        face, _, sign, radiance = warp_cast(s, np.tile(origin, (len(d), 1)), d)
        assert np.all(face >= 0)
        hit_mesh = s.triangle_mesh[face]
        if r in spec["lit"]:
            assert np.all(hit_mesh == spec["light"]) and np.all(sign > 0), f"{name}: receiver {r} should be lit"
            assert np.all(radiance == s.emission[face])
        else:
            assert hit_mesh[0] == spec["occluder"], f"{name}: receiver {r}'s centre ray should hit the occluder"
            assert not np.any(hit_mesh == spec["light"]) and np.all(radiance == 0.0)


def test_veach_plates_see_every_light(loaded_scenes):
    """In veach-plates every plate receiver's ray to each light sphere's centre meets no
    triangle and sees that sphere's front: its radiance."""
    s = loaded_scenes["veach-plates"]
    assert s.emitter_count == 0 and len(s.sphere_lights) == 4
    centres = s.spheres.centers[s.sphere_lights]
    for r in range(len(s.receivers)):
        origin, d = shading_rays(s, r, centres)
        face, _, _, radiance = warp_cast(s, np.tile(origin, (len(d), 1)), d)
        assert np.all(face < 0)
        np.testing.assert_array_equal(radiance, s.spheres.emission[s.sphere_lights].astype(np.float32))


# An example value for every key a material table may hold (scene.MATERIAL_PARAMETERS).
MATERIAL_EXAMPLES = {"albedo": 0.5, "exponent": 20.0, "view": [0.0, -3.0, 4.0], "alpha": 0.2,
                     "distribution": "beckmann", "sample_visible": False, "eta": 1.7, "k": 2.5, "specular": 0.8}


@pytest.mark.parametrize("name", MATERIALS)
def test_every_registered_material_loads_and_requires_its_keys(name, tmp_path):
    """Each material of the registry loads from a scene file with its keys (the receivers
    get its code, and its name back), refuses a key it does not have, and names each
    required key that is left out in a one-line error."""
    material = MATERIALS[name]
    assert set(material.keys) <= set(MATERIAL_EXAMPLES), "add an example value for the new key"
    table = {"type": name} | {k: MATERIAL_EXAMPLES[k] for k in material.keys}
    rx = load_scene(write_scene(tmp_path / "ok", material=table)).receivers
    assert np.all(rx.material == material.code) and rx.material_name(0) == name
    assert rx.material_of(0) is material
    if "albedo" in material.keys:
        assert rx.albedo[0] == 0.5
    if "alpha" in material.keys:  # grey microfacet parameters: every channel the same
        assert rx.alpha[0] == 0.2 and rx.distribution[0] == 0 and rx.sample_visible[0] == 0
        np.testing.assert_array_equal(rx.eta[0], [1.7] * 3)
        np.testing.assert_allclose(rx.specular[0].sum(), 0.8)
    if "k" in material.keys:
        np.testing.assert_array_equal(rx.k[0], [2.5] * 3)
    other = sorted(set(MATERIAL_EXAMPLES) - set(material.keys))
    if other:
        with pytest.raises(WarpisError, match=f"unknown key '{other[0]}'"):
            load_scene(write_scene(tmp_path / "extra", material=table | {other[0]: MATERIAL_EXAMPLES[other[0]]}))
    for key in material.required:
        with pytest.raises(WarpisError, match=f"missing key '{key}'") as err:
            load_scene(write_scene(tmp_path / f"no-{key}", material={k: v for k, v in table.items() if k != key}))
        assert "\n" not in str(err.value)


# =========================================================================== scenes as plain data

_FLOOR_V, _FLOOR_F = quad((0.0, 0.0, 0.0), 2.0, "up")
_LIGHT_V, _LIGHT_F = quad((0.0, 0.0, 1.0), 0.5, "down")
_POINTS = [[0.0, 0.0, 0.0], [1.5, 0.25, 0.0]]


def _arrays(**changes) -> dict:
    """Keyword arguments of Scene.from_arrays for the floor and light of ``_toml_twin``."""
    args = dict(vertices=np.vstack([_FLOOR_V, _LIGHT_V]), triangles=np.vstack([_FLOOR_F, _LIGHT_F + 4]),
                emission=[0.0, 0.0, 10.0, 10.0], positions=_POINTS, normals=[0.0, 0.0, 1.0],
                material="lambert", albedo=0.5, name="twin")
    return args | changes


def _toml_twin(directory: Path, filename: str = "scene.toml") -> Path:
    """The scene of ``_arrays()`` as a scene file (OBJ floats round-trip exactly)."""
    return write_scene(directory, meshes=[{"path": "floor.obj", "vertices": _FLOOR_V, "faces": _FLOOR_F},
                                          {"path": "light.obj", "vertices": _LIGHT_V, "faces": _LIGHT_F,
                                           "emission": 10.0}],
                       receivers={"points": _POINTS, "normal": [0.0, 0.0, 1.0]},
                       material={"type": "lambert", "albedo": 0.5}, filename=filename)


def test_from_arrays_is_the_scene_file_scene(tmp_path):
    """The same content from a scene file and from arrays: the same arrays, the same
    digest, one upload, bit-identical trials; only the labels differ."""
    from warpis.kernels.engine import run_trials

    clear_device_cache()
    from_file = load_scene(_toml_twin(tmp_path))
    from_arrays = warpis.Scene.from_arrays(**_arrays())
    for name in ("vertices", "triangles", "emission", "emitters", "emitter_areas"):
        np.testing.assert_array_equal(getattr(from_file, name), getattr(from_arrays, name), err_msg=name)
    for name in ("positions", "normals", "material", "albedo", "exponent", "view"):
        np.testing.assert_array_equal(getattr(from_file.receivers, name), getattr(from_arrays.receivers, name))
    assert from_file.digest == from_arrays.digest
    assert from_file.mesh_names == ["floor.obj", "light.obj"] and from_arrays.mesh_names == ["twin"]
    assert from_arrays.path is None and from_arrays.summary()["path"] is None
    a = run_trials(from_file, "independent:balance:light-area+cosine", 8, 64, seed=3)
    b = run_trials(from_arrays, "independent:balance:light-area+cosine", 8, 64, seed=3)
    np.testing.assert_array_equal(a, b)
    assert device_cache_keys() == [(from_file.digest, "cpu")]


def test_from_arrays_broadcasts_and_normalises():
    """Per-receiver values may be one for all; normals and views are normalised; groups,
    grid shape, material codes and mesh labels are kept."""
    s = warpis.Scene.from_arrays(**_arrays(
        positions=[[x, y, 0.0] for y in (-0.5, 0.5) for x in (-1.0, 0.0, 1.0)], normals=[0.0, 0.0, 2.0],
        material=[0, 1, 2, 3, 4, 0], exponent=20.0, alpha=[0.1, 0.2, 0.3, 0.4, 0.5, 0.6], specular=0.9, view=[0.0, 3.0, 4.0], group=[0, 0, 0, 1, 1, 1],
        group_names=["near", "far"], grid_shape=(2, 3), triangle_mesh=[0, 0, 1, 1], mesh_names=["floor", "lamp"]))
    rx = s.receivers
    np.testing.assert_array_equal(rx.normals, np.tile([0.0, 0.0, 1.0], (6, 1)))
    np.testing.assert_allclose(rx.view, np.tile([0.0, 0.6, 0.8], (6, 1)))
    assert rx.material.dtype == np.int32 and [rx.material_name(i) for i in range(5)] == list(MATERIALS)
    np.testing.assert_array_equal(rx.exponent, np.full(6, 20.0))
    np.testing.assert_array_equal(rx.alpha, [0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    np.testing.assert_allclose(rx.specular, np.full((6, 3), 0.3))  # grey: split evenly over the channels
    np.testing.assert_allclose(rx.specular_weight, np.full(6, 0.9 / 1.4))  # Mitsuba's s / (d + s), d = albedo
    assert rx.group_names == ["near", "far"] and rx.grid_shape == (2, 3)
    assert s.mesh_names == ["floor", "lamp"] and list(s.triangle_mesh) == [0, 0, 1, 1]
    assert not s.vertices.flags.writeable and not rx.positions.flags.writeable


def _mutations(scene: warpis.Scene) -> dict:
    """One changed copy of ``scene`` per array of DIGEST_FIELDS (and a changed dtype)."""
    rx = scene.receivers

    def nudged(a: np.ndarray) -> np.ndarray:
        out = np.array(a)
        out.flat[-1] = np.nextafter(out.flat[-1], np.inf) if out.dtype.kind == "f" else out.flat[-1] + 1
        return out

    out = {name: replace(scene, **{name: nudged(getattr(scene, name))}) for name in ("vertices", "emission")}
    out["triangles"] = replace(scene, triangles=scene.triangles[:, [1, 2, 0]])  # same triangles, other order
    out["triangles dtype"] = replace(scene, triangles=scene.triangles.astype(np.int64))
    for name in ("positions", "normals", "albedo", "exponent", "view", "alpha", "distribution", "sample_visible",
                 "eta", "k", "specular", "specular_weight"):
        out[f"receivers.{name}"] = replace(scene, receivers=replace(rx, **{name: nudged(getattr(rx, name))}))
    out["receivers.material"] = replace(scene, receivers=replace(rx, material=np.zeros_like(rx.material)))
    return out


def test_digest_changes_with_every_result_array(tmp_path):
    """Changing any array that a result depends on (by one ulp, one index, its dtype)
    changes the digest; the labels (name, description, path, mesh names, triangle → mesh,
    receiver groups) and the device do not."""
    from warpis.scenes import DIGEST_FIELDS

    scene = load_scene(_toml_twin(tmp_path))
    changed = _mutations(scene)
    assert {k.split(" ")[0] for k in changed} == set(DIGEST_FIELDS)
    digests = {name: s.digest for name, s in changed.items()}
    assert scene.digest not in digests.values() and len(set(digests.values())) == len(digests), digests
    rx = scene.receivers
    labels = [replace(scene, name="other", description="d", path=tmp_path / "x.toml", mesh_names=["a", "b"],
                      triangle_mesh=np.zeros(4, np.int32)),
              replace(scene, receivers=replace(rx, group_names=["g"], grid_shape=(1, 2))), scene.on("cpu")]
    assert all(s.digest == scene.digest for s in labels)


def test_digest_and_cell_key_survive_moving_the_file(tmp_path):
    """A scene file copied elsewhere under another name (meshes beside it) has the same
    digest, and a study of it the same cell keys (name given in the file)."""
    from warpis.runs.study_file import scene_digest, study_from_dict

    first = _toml_twin(tmp_path / "a")
    second = _toml_twin(tmp_path / "elsewhere" / "b", filename="renamed.toml")
    assert load_scene(first).digest == load_scene(second).digest == scene_digest(load_scene(second))
    table = {"name": "s", "trials": 100, "n": [4], "estimators": ["independent:single:cosine"]}
    keys = [[c.key for c in study_from_dict(table | {"scenes": [source]}, "t", base).cells()]
            for source, base in (("a/scene.toml", tmp_path), ("b/renamed.toml", tmp_path / "elsewhere"))]
    assert keys[0] == keys[1]


def test_scene_pickles_without_warp_objects(tmp_path):
    """A scene pickles to little more than its arrays (no Warp object, nothing cached),
    comes back read-only with the same digest, and an unpickled scene uploaded afresh
    gives bit-identical trials."""
    from warpis.kernels.engine import run_trials

    scene = load_scene("two-lights")
    expected = run_trials(scene, "jittered:balance:light-solid-angle+cosine", 8, 128, seed=5)
    blob = pickle.dumps(scene)
    arrays = sum(a.nbytes for a in (scene.vertices, scene.triangles, scene.emission, scene.triangle_mesh))
    arrays += sum(getattr(scene.receivers, n).nbytes for n in ("positions", "normals", "material", "albedo",
                                                                "exponent", "view", "group"))
    assert len(blob) < arrays + 4096, (len(blob), arrays)
    modules = set()

    class Recording(pickle.Unpickler):
        def find_class(self, module, name):
            modules.add(module)
            return super().find_class(module, name)

    clear_device_cache()
    back = Recording(io.BytesIO(blob)).load()
    assert not [m for m in modules if m.split(".")[0] == "warp"], modules
    assert back.digest == scene.digest and not back.vertices.flags.writeable
    assert not back.receivers.normals.flags.writeable
    np.testing.assert_array_equal(run_trials(back, "jittered:balance:light-solid-angle+cosine", 8, 128, seed=5),
                                  expected)


def test_device_cache_builds_once_per_digest_and_device(tmp_path, monkeypatch):
    """Two loads of one file, its twin from arrays and an unpickled copy share one upload
    (mesh, structs, slabs, light table, theory's memo); another content builds another;
    nothing is attached to the scenes."""
    from warpis.kernels import device
    from warpis.kernels.techniques import light_table

    builds = []
    real = device._build
    monkeypatch.setattr(device, "_build", lambda scene, dev: builds.append(dev) or real(scene, dev))
    clear_device_cache()
    path = _toml_twin(tmp_path)
    scenes = [load_scene(path), load_scene(path), warpis.Scene.from_arrays(**_arrays())]
    scenes.append(pickle.loads(pickle.dumps(scenes[0])))
    tables = {id(light_table(s)) for s in scenes}
    assert all(upload(s).data.mesh == upload(scenes[0]).data.mesh for s in scenes) and len(tables) == 1
    np.testing.assert_array_equal(upload(scenes[3]).slab, upload(scenes[0]).slab)
    assert builds == ["cpu"]
    other = warpis.Scene.from_arrays(**_arrays(emission=[0.0, 0.0, 10.0, 20.0]))
    assert upload(other).data.mesh != upload(scenes[0]).data.mesh and builds == ["cpu", "cpu"]
    allowed = {f.name for f in fields(warpis.Scene)} | {"digest", "emitters", "emitter_areas", "sphere_lights"}
    for s in scenes:
        assert set(vars(s)) <= allowed, set(vars(s)) - allowed


def _bad_arrays() -> dict:
    """name → (Scene.from_arrays changes, words of the problem): each wrong in one way."""
    nan_vertex = _arrays()["vertices"].copy()
    nan_vertex[5, 2] = math.nan
    flat = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [2.0, 0.0, 1.0]])
    return {
        "nan-vertex": (dict(vertices=nan_vertex), "vertices: point 5 is NaN or infinite"),
        "huge-vertex": (dict(vertices=_arrays()["vertices"] * 1e16), "coordinate of magnitude"),
        "vertices-2d": (dict(vertices=_arrays()["vertices"][:, :2]), "vertices: expected shape (V, 3), got (8, 2)"),
        "vertices-text": (dict(vertices=[["a", "b", "c"]] * 8), "vertices: expected real numbers"),
        "ragged-triangles": (dict(triangles=[[0, 1, 2], [0, 2]]), "triangles: not a rectangular array of numbers"),
        "float-triangles": (dict(triangles=_arrays()["triangles"] + 0.5), "triangles: expected integers"),
        "index-out-of-range": (dict(triangles=[[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 8]]),
                               "triangle 3 refers to vertex 8, which does not exist"),
        "negative-index": (dict(triangles=[[0, 1, 2], [0, 2, 3], [4, -1, 6], [4, 6, 7]]), "refers to vertex -1"),
        "emission-length": (dict(emission=[0.0, 10.0]), "emission: expected shape (T,) = (4,), got (2,)"),
        "nan-emission": (dict(emission=[0.0, 0.0, math.nan, 10.0]), "emission[2]: must be a finite number"),
        "negative-emission": (dict(emission=[0.0, -1.0, 10.0, 10.0]), "emission[1]"),
        "huge-emission": (dict(emission=[0.0, 0.0, 1e39, 10.0]), "outside the range the float32 kernels"),
        "no-emitter": (dict(emission=np.zeros(4)), "the scene has no emitter"),
        "degenerate-emitter": (dict(vertices=np.vstack([_FLOOR_V, flat]), triangles=[[0, 1, 2], [0, 2, 3], [4, 5, 6]],
                                    emission=[0.0, 0.0, 1.0]), "mesh 'bad': every emitter triangle has zero area"),
        "material-code": (dict(material=[0, 7]), "code 7 of receiver 1 is not a material (valid: 0 irradiance"),
        "material-name": (dict(material="mirror"), "unknown material 'mirror'"),
        "zero-normal": (dict(normals=[[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]), "normals: entry 1 has zero length"),
        "nan-normal": (dict(normals=[math.nan, 0.0, 1.0]), "normals: entry 0 is NaN or infinite"),
        "normals-shape": (dict(normals=np.ones((3, 3))), "normals: expected shape (3,) or (2, 3)"),
        "zero-view": (dict(view=[0.0, 0.0, 0.0]), "view: entry 0 has zero length"),
        "no-receivers": (dict(positions=np.zeros((0, 3))), "positions: expected shape (R, 3)"),
        "nan-receiver": (dict(positions=[[0.0, 0.0, 0.0], [math.inf, 0.0, 0.0]]), "point 1 is NaN or infinite"),
        "negative-albedo": (dict(albedo=[0.5, -0.5]), "albedo[1]: must be a finite number >= 0"),
        "subnormal-exponent": (dict(exponent=1e-45), "exponent[0]"),
        "group-out-of-range": (dict(group=[0, 1]), "group: receiver 1 is in group 1"),
        "grid-shape": (dict(grid_shape=(3, 3)), "grid_shape: expected (rows, cols) with rows × cols = 2"),
        "mesh-out-of-range": (dict(triangle_mesh=[0, 0, 1, 2], mesh_names=["a", "b"]), "triangle 3 is in mesh 2"),
    }


@pytest.mark.parametrize("case", list(_bad_arrays()))
def test_from_arrays_refuses_bad_arrays(case):
    """Each bad array gives one line naming the scene, the array and the problem (the
    checks of a scene file, limits.py's float32 ranges among them)."""
    changes, problem = _bad_arrays()[case]
    with pytest.raises(WarpisError) as info:
        warpis.Scene.from_arrays(**_arrays(name="bad", **changes))
    message = str(info.value)
    assert "\n" not in message and message.startswith("scene 'bad': "), message
    assert problem in message, message


def test_from_arrays_refuses_a_device_that_does_not_exist():
    with pytest.raises(WarpisError, match="unknown device"):
        warpis.Scene.from_arrays(**_arrays(device="tpu"))


def test_docs_from_arrays_example_runs():
    """The from-arrays example of docs/scene-files.md (between its markers) runs as written."""
    page = (Path(__file__).resolve().parents[1] / "docs" / "scene-files.md").read_text()
    code = page.split("<!-- from-arrays:begin -->\n```python\n", 1)[1].split("```", 1)[0]
    namespace: dict = {}
    exec(compile(code, "docs/scene-files.md", "exec"), namespace)
    scene = namespace["scene"]
    assert scene.emitter_count == 2 and len(scene.receivers) == 2 and namespace["x"].shape == (2, 1000)


def test_roughplastic_of_index_one_is_refused_in_one_line(tmp_path):
    """A roughplastic whose int_ior/ext_ior is 1 (its tables have no meaning) is refused
    when the scene loads, in one line, rather than failing later in the upload; a
    conductor with eta = 1 is a valid conductor."""
    table = {"type": "roughplastic", "alpha": 0.2, "eta": 1.0, "view": [0.0, 0.0, 1.0]}
    with pytest.raises(WarpisError) as err:
        load_scene(write_scene(tmp_path / "plastic", material=table))
    assert "must differ from 1" in str(err.value) and "\n" not in str(err.value)
    conductor = {"type": "roughconductor", "alpha": 0.2, "eta": 1.0, "k": 2.0, "view": [0.0, 0.0, 1.0]}
    assert load_scene(write_scene(tmp_path / "conductor", material=conductor)).receivers.eta[0, 0] == 1.0


@pytest.mark.parametrize("key,value,needle", [
    ("alpha", 0.0, "alpha must be in [0.0001, 1000]"),
    ("alpha", "rough", "alpha must be a number"),
    ("distribution", "phong", "distribution must be one of 'beckmann', 'ggx'"),
    ("sample_visible", 1, "sample_visible must be true or false"),
    ("eta", 0.0, "eta must be in (0, 1000]"),
    ("k", -1.0, "k must be in [0, 1000]"),
    ("specular", float("inf"), "specular must be finite"),
])
def test_microfacet_keys_refuse_bad_values_in_one_line(tmp_path, key, value, needle):
    """Each microfacet key of a scene file's material: a value outside its domain is one
    line naming the key, the file and what is allowed."""
    table = {"type": "roughconductor", "alpha": 0.2, "eta": 1.5, "k": 2.0, "view": [0.0, 0.0, 1.0], key: value}
    with pytest.raises(WarpisError) as err:
        load_scene(write_scene(tmp_path, material=table))
    assert needle in str(err.value) and "\n" not in str(err.value), str(err.value)


def test_from_arrays_refuses_microfacet_values_outside_their_domain():
    """Scene.from_arrays checks the microfacet arrays like a scene file: one line naming
    the array and the first bad receiver."""
    for changes, needle in [({"alpha": -1.0}, "alpha of receiver 0"), ({"distribution": "phong"}, "distribution"),
                            ({"sample_visible": 2}, "sample_visible of receiver 0"),
                            ({"eta": [1.5, 0.0]}, "eta of receiver 1"), ({"specular_weight": 1.5}, "specular_weight"),
                            ({"material": "roughplastic", "eta": [1.5, 1.0]}, "eta of receiver 1")]:
        with pytest.raises(WarpisError) as err:
            warpis.Scene.from_arrays(**_arrays(**({"material": "roughconductor", "view": [0.0, 0.0, 1.0]} | changes)))
        assert needle in str(err.value) and "\n" not in str(err.value), str(err.value)


@pytest.mark.parametrize("generator", ["mesh_scenes", "mitsuba_scenes"])
def test_the_committed_scenes_are_their_generators(generator, capsys):
    """``scripts/make_scenes.py --check`` and ``scripts/make_mitsuba_scenes.py --check`` in
    process: a fresh generation by warpis.scenes.builders writes the files committed under
    meshes/ byte for byte (writing needs neither Mitsuba nor a ray caster)."""
    import importlib

    module = importlib.import_module(f"warpis.scenes.builders.{generator}")
    status = module.check(Path(__file__).resolve().parents[1] / "meshes")
    assert status == 0, capsys.readouterr().out
