"""The 4-wide BVH (warpis/kernels/bvh.py): its build, and its ray queries against Warp's.

* Build: every triangle in exactly one leaf slot, every box holding what lies below it,
  the emitters kept in their own subtree.
* Queries: on a million rays per bundled scene, ``closest_hit`` finds the face
  ``wp.mesh_query_ray`` finds and ``any_hit`` answers as ``wp.mesh_query_ray_anyhit``,
  on at least 99.999% of rays, and every ray where they differ is explained (float64
  brute force): a tie (the other face is hit within 1e-5 relative of the same distance,
  as on an edge two triangles share) or a hit within 1e-5 relative of the segment's end.
  Deterministic (fixed seeds): no false-failure rate to state.
* The stack guard: a tree deeper than the fixed traversal stack is answered by Warp's
  query, not by reading past the stack.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import warpis
from warpis.kernels.bvh import (CACHE_MIN_TRIANGLES, LEAF_SIZE, STACK_SIZE, WideBvh, WideBvhArrays, any_hit,
                                build_wide_bvh, cached_wide_bvh, closest_hit, upload_wide_bvh)
from warpis.kernels.device import upload

SCENES = ("occluded-quad", "two-lights", "heavy-occluder", "veach-plates", "mitsuba-cornell-box",
          "mitsuba-veach-plates")
RAYS = 1 << 20
AGREEMENT = 0.99999  # the rate the issue asks for; measured: 1.0 on every scene
TIE_RTOL = 1e-5


@wp.kernel(enable_backward=False)
def _closest_kernel(bvh: WideBvh, mesh: wp.uint64, o: wp.array(dtype=wp.vec3), d: wp.array(dtype=wp.vec3),
                    wide: wp.array(dtype=wp.int32), wide_sign: wp.array(dtype=wp.float32),
                    warp_face: wp.array(dtype=wp.int32), warp_sign: wp.array(dtype=wp.float32)):
    i = wp.tid()
    hit = closest_hit(bvh, mesh, o[i], d[i], 1.0e30)
    wide[i] = hit.face
    wide_sign[i] = hit.sign
    q = wp.mesh_query_ray(mesh, o[i], d[i], 1.0e30)
    warp_face[i] = wp.where(q.result, q.face, -1)
    warp_sign[i] = wp.where(q.result, q.sign, 0.0)


@wp.kernel(enable_backward=False)
def _any_kernel(bvh: WideBvh, mesh: wp.uint64, o: wp.array(dtype=wp.vec3), d: wp.array(dtype=wp.vec3),
                t_max: wp.array(dtype=wp.float32), wide: wp.array(dtype=wp.int32), warp_any: wp.array(dtype=wp.int32)):
    i = wp.tid()
    wide[i] = wp.where(any_hit(bvh, mesh, o[i], d[i], t_max[i]), 1, 0)
    warp_any[i] = wp.where(wp.mesh_query_ray_anyhit(mesh, o[i], d[i], t_max[i]), 1, 0)


def random_rays(scene: warpis.Scene, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Half the rays from random points of the scene's box in random directions, half from
    such points at random points of random triangles (area-weighted: through the dense
    parts of the mesh)."""
    rng = np.random.default_rng(seed)
    v = np.asarray(scene.vertices, dtype=np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    pad = 0.1 * (hi - lo) + 1e-3
    origins = rng.uniform(lo - pad, hi + pad, size=(count, 3))
    dirs = rng.normal(size=(count, 3))
    tris = scene.triangle_vertices().astype(np.float64)
    area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    half = count // 2
    pick = rng.choice(len(tris), size=half, p=area / area.sum())
    u = rng.random((half, 2))
    flip = u.sum(axis=1) > 1
    u[flip] = 1 - u[flip]
    t = tris[pick]
    target = t[:, 0] + u[:, :1] * (t[:, 1] - t[:, 0]) + u[:, 1:] * (t[:, 2] - t[:, 0])
    dirs[:half] = target - origins[:half]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return origins.astype(np.float32), dirs.astype(np.float32)


def crossing_distance(tris: np.ndarray, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """float64 Möller–Trumbore distance of each ray i to triangle tris[i] (inf if missed),
    with edges widened by 1e-5 of the triangle (barycentric): a ray through an edge meets
    both triangles that share it."""
    e1, e2 = tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    pv = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, pv)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        tv = o - tris[:, 0]
        bu = np.einsum("ij,ij->i", tv, pv) * inv
        qv = np.cross(tv, e1)
        bv = np.einsum("ij,ij->i", d, qv) * inv
        t = np.einsum("ij,ij->i", e2, qv) * inv
    eps = 1e-5
    ok = (det != 0) & (bu >= -eps) & (bv >= -eps) & (bu + bv <= 1 + eps) & (t >= -eps * np.abs(t).max(initial=1))
    return np.where(ok, t, np.inf)


def _scene_query(name: str):
    scene = warpis.load_scene(name)
    up = upload(scene)
    return scene, up


@pytest.mark.parametrize("name", SCENES)
def test_closest_hit_agrees_with_warp(name):
    scene, up = _scene_query(name)
    o, d = random_rays(scene, RAYS, seed=1)
    out = [wp.zeros(RAYS, dtype=t) for t in (wp.int32, wp.float32, wp.int32, wp.float32)]
    wp.launch(_closest_kernel, dim=RAYS, inputs=[up.data.bvh, up.mesh.id, wp.array(o, dtype=wp.vec3),
                                                 wp.array(d, dtype=wp.vec3), *out])
    wide, wide_sign, warp_face, warp_sign = (a.numpy() for a in out)
    assert (warp_face >= 0).mean() > 0.4  # the test covers hits, not only misses
    differ = np.flatnonzero(wide != warp_face)
    assert 1.0 - len(differ) / RAYS >= AGREEMENT, f"{name}: {len(differ)} of {RAYS} rays differ"
    if len(differ):
        tris = scene.triangle_vertices().astype(np.float64)
        oo, dd = o[differ].astype(np.float64), d[differ].astype(np.float64)
        both = (wide[differ] >= 0) & (warp_face[differ] >= 0)
        assert both.all(), f"{name}: one query hits and the other misses on rays {differ[~both][:5]}"
        t_wide = crossing_distance(tris[wide[differ]], oo, dd)
        t_warp = crossing_distance(tris[warp_face[differ]], oo, dd)
        tie = np.isfinite(t_wide) & np.isclose(t_wide, t_warp, rtol=TIE_RTOL, atol=0)
        assert tie.all(), f"{name}: unexplained differences on rays {differ[~tie][:5]}"
    same = (wide == warp_face) & (wide >= 0)
    np.testing.assert_array_equal(wide_sign[same] > 0, warp_sign[same] > 0)


@pytest.mark.parametrize("name", SCENES)
def test_any_hit_agrees_with_warp(name):
    scene, up = _scene_query(name)
    o, d = random_rays(scene, RAYS, seed=2)
    extent = float(np.ptp(scene.vertices, axis=0).max())
    t_max = np.random.default_rng(3).uniform(0.0, 1.5 * extent, RAYS).astype(np.float32)
    wide, warp_any = wp.zeros(RAYS, dtype=wp.int32), wp.zeros(RAYS, dtype=wp.int32)
    wp.launch(_any_kernel, dim=RAYS, inputs=[up.data.bvh, up.mesh.id, wp.array(o, dtype=wp.vec3),
                                             wp.array(d, dtype=wp.vec3), wp.array(t_max), wide, warp_any])
    wide, warp_any = wide.numpy(), warp_any.numpy()
    assert 0.2 < warp_any.mean() < 0.9  # both answers are common
    differ = np.flatnonzero(wide != warp_any)
    assert 1.0 - len(differ) / RAYS >= AGREEMENT, f"{name}: {len(differ)} of {RAYS} rays differ"
    if len(differ):
        # Explained when the first hit lies at the segment's end (to 1e-5 relative).
        closest = [wp.zeros(len(differ), dtype=t) for t in (wp.int32, wp.float32, wp.int32, wp.float32)]
        wp.launch(_closest_kernel, dim=len(differ), inputs=[up.data.bvh, up.mesh.id, wp.array(o[differ], dtype=wp.vec3),
                                                            wp.array(d[differ], dtype=wp.vec3), *closest])
        face = closest[2].numpy()
        tris = scene.triangle_vertices().astype(np.float64)
        t_first = crossing_distance(tris[np.maximum(face, 0)], o[differ].astype(np.float64),
                                    d[differ].astype(np.float64))
        at_end = (face >= 0) & np.isclose(t_first, t_max[differ], rtol=TIE_RTOL, atol=0)
        assert at_end.all(), f"{name}: unexplained differences on rays {differ[~at_end][:5]}"


def test_every_triangle_sits_in_one_leaf_and_every_box_holds_its_content():
    scene = warpis.load_scene("veach-plates")
    built = build_wide_bvh(scene.vertices, scene.triangles, scene.emitters)
    faces = built.faces[built.faces >= 0]
    np.testing.assert_array_equal(np.sort(faces), np.arange(scene.triangle_count))
    corners = built.corners.reshape(-1, 3, 3, LEAF_SIZE)  # leaf, vertex, coordinate, slot
    tris = scene.triangle_vertices().astype(np.float32)
    for leaf, slot in zip(*np.nonzero(built.faces >= 0)):
        np.testing.assert_array_equal(corners[leaf, :, :, slot], tris[built.faces[leaf, slot]])
    bounds = built.bounds.reshape(-1, 3, 2, 4)  # node, axis, lower/upper, child
    lower, upper = _subtree_bounds(built, tris)
    for node in range(len(built.children)):
        for slot, child in enumerate(built.children[node]):
            box_lo, box_hi = bounds[node, :, 0, slot], bounds[node, :, 1, slot]
            if np.isinf(box_lo).all():
                continue  # an empty slot
            if child >= 0:
                lo, hi = lower[child], upper[child]
            else:
                leaf_tris = tris[built.faces[-child - 1][built.faces[-child - 1] >= 0]]
                lo, hi = leaf_tris.min(axis=(0, 1)), leaf_tris.max(axis=(0, 1))
            assert np.all(box_lo <= lo) and np.all(box_hi >= hi), (node, slot)


def _subtree_bounds(built: WideBvhArrays, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of the triangles below each node, from the leaves up."""
    n = len(built.children)
    lower, upper = np.full((n, 3), np.inf), np.full((n, 3), -np.inf)
    for node in reversed(range(n)):  # children are numbered after their parents
        for child in built.children[node]:
            if child >= 0:
                lo, hi = lower[child], upper[child]
            else:
                slots = built.faces[-child - 1]
                leaf_tris = tris[slots[slots >= 0]]
                if len(leaf_tris) == 0:
                    continue
                lo, hi = leaf_tris.min(axis=(0, 1)), leaf_tris.max(axis=(0, 1))
            lower[node], upper[node] = np.minimum(lower[node], lo), np.maximum(upper[node], hi)
    return lower, upper


def test_emitters_have_their_own_subtree():
    """The root's emitter child holds the emitter triangles and nothing else, so a ray to
    the light need not search the occluder (heavy-occluder: 2 emitters, 81,922 others)."""
    scene = warpis.load_scene("heavy-occluder")
    built = build_wide_bvh(scene.vertices, scene.triangles, scene.emitters)
    emitters = set(scene.emitters.tolist())
    below = [_faces_below(built, child) for child in built.children[0]]
    assert any(found == emitters for found in below)
    assert sum(bool(found & emitters) for found in below) == 1


def _faces_below(built: WideBvhArrays, child: int) -> set[int]:
    if child < 0:
        slots = built.faces[-child - 1]
        return set(slots[slots >= 0].tolist())
    return set().union(*(_faces_below(built, c) for c in built.children[child] if not _empty(built, child, c)))


def _empty(built: WideBvhArrays, node: int, child: int) -> bool:
    slot = list(built.children[node]).index(child)
    return bool(np.isinf(built.bounds.reshape(-1, 3, 2, 4)[node, 0, 0, slot]))


def _chain(levels: int) -> tuple[WideBvhArrays, np.ndarray, np.ndarray]:
    """A tree ``levels`` nodes deep along one ray: each node holds three leaves the ray
    meets (one triangle each, across the ray at increasing distance) and the next node."""
    tris, faces, corners = [], [], []
    children = np.zeros((levels, 4), np.int32)
    bounds = np.zeros((levels, 6, 4), np.float32)
    for level in range(levels):
        for slot in range(3):
            z = 1.0 + level * 3 + slot
            tri = np.array([[-1, -1, z], [3, -1, z], [-1, 3, z]], np.float32)
            leaf = len(faces)
            tris.append(tri)
            faces.append([leaf, -1, -1, -1])
            c = np.zeros((3, 3, 4), np.float32)
            c[:, :, 0] = tri
            corners.append(c)
            children[level, slot] = -(leaf + 1)
            bounds[level, 0::2, slot] = tri.min(axis=0)
            bounds[level, 1::2, slot] = tri.max(axis=0)
        children[level, 3] = level + 1 if level + 1 < levels else children[level, 0]
        bounds[level, 0::2, 3] = [-1, -1, 1 + 3 * (level + 1)]
        bounds[level, 1::2, 3] = [3, 3, 3 * levels + 1]
    built = WideBvhArrays(bounds=bounds.reshape(-1, 4), children=children,
                          corners=np.concatenate(corners).reshape(-1, 4), faces=np.array(faces, np.int32),
                          depth=levels)
    vertices = np.concatenate(tris)
    return built, vertices, np.arange(len(vertices)).reshape(-1, 3)


def test_a_tree_deeper_than_the_stack_is_answered_by_warps_query():
    """Each level of the chain leaves three entries on the stack: a chain of STACK_SIZE / 2
    levels runs past the stack, and the query must still answer right (Warp does not
    bounds-check local vectors in release builds: an unguarded push would overwrite
    memory silently).  Rays along +z from below hit the first triangle; rays from inside
    the chain hit the next one."""
    levels = STACK_SIZE // 2
    built, vertices, triangles = _chain(levels)
    bvh = upload_wide_bvh(built)
    mesh = wp.Mesh(points=wp.array(vertices, dtype=wp.vec3), indices=wp.array(triangles.reshape(-1), dtype=wp.int32))
    # Reversed along -z from above the chain the nearest triangle is the last: the
    # traversal must descend every level (pushing three leaves at each) to find it.
    o = np.array([[0.2, 0.3, 0.0], [0.2, 0.3, 3 * levels + 5.0], [0.1, 0.1, 4.5]], np.float32)
    d = np.array([[0, 0, 1], [0, 0, -1], [0, 0, 1]], np.float32)
    out = [wp.zeros(3, dtype=t) for t in (wp.int32, wp.float32, wp.int32, wp.float32)]
    wp.launch(_closest_kernel, dim=3, inputs=[bvh, mesh.id, wp.array(o, dtype=wp.vec3), wp.array(d, dtype=wp.vec3),
                                              *out])
    wide, warp_face = out[0].numpy(), out[2].numpy()
    np.testing.assert_array_equal(wide, warp_face)
    np.testing.assert_array_equal(warp_face, [0, 3 * levels - 1, 4])


def test_disabled_bvh_is_warps_query():
    """upload_wide_bvh(None) (the CUDA path) answers with wp.mesh_query_ray itself."""
    scene = warpis.load_scene("occluded-quad")
    up = upload(scene)
    o, d = random_rays(scene, 4096, seed=5)
    out = [wp.zeros(len(o), dtype=t) for t in (wp.int32, wp.float32, wp.int32, wp.float32)]
    wp.launch(_closest_kernel, dim=len(o), inputs=[upload_wide_bvh(None), up.mesh.id, wp.array(o, dtype=wp.vec3),
                                                   wp.array(d, dtype=wp.vec3), *out])
    np.testing.assert_array_equal(out[0].numpy(), out[2].numpy())
    np.testing.assert_array_equal(out[1].numpy(), out[3].numpy())


def _soup(count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` random small triangles in the unit cube."""
    rng = np.random.default_rng(seed)
    centres = rng.random((count, 1, 3))
    vertices = (centres + 0.02 * rng.normal(size=(count, 3, 3))).reshape(-1, 3).astype(np.float32)
    return vertices, np.arange(3 * count, dtype=np.int32).reshape(-1, 3)


def _same(a: WideBvhArrays, b: WideBvhArrays) -> bool:
    return a.depth == b.depth and all(np.array_equal(getattr(a, f), getattr(b, f))
                                      for f in ("bounds", "children", "corners", "faces"))


def test_the_disk_cache_returns_the_built_tree_and_replaces_a_bad_file(tmp_path, monkeypatch):
    monkeypatch.setenv("WARPIS_CACHE_DIR", str(tmp_path))
    vertices, triangles = _soup(CACHE_MIN_TRIANGLES, seed=1)
    apart = np.arange(10)
    built = build_wide_bvh(vertices, triangles, apart)
    assert _same(cached_wide_bvh(vertices, triangles, apart), built)
    (path,) = tmp_path.iterdir()
    written = path.stat().st_mtime_ns
    assert _same(cached_wide_bvh(vertices, triangles, apart), built)  # now read from the file,
    assert path.stat().st_mtime_ns == written  # which is accepted, not rebuilt and replaced
    # Another mesh gets another file.
    moved = vertices + np.float32(1.0)
    cached_wide_bvh(moved, triangles, apart)
    assert len(list(tmp_path.iterdir())) == 2
    # A damaged file, or a valid one that does not hold every triangle once, is rebuilt.
    path.write_bytes(b"not a bvh")
    assert _same(cached_wide_bvh(vertices, triangles, apart), built)
    assert path.read_bytes() != b"not a bvh"
    wrong = {f: getattr(built, f) for f in ("bounds", "children", "corners", "faces")}
    wrong["faces"] = np.where(wrong["faces"] == 7, 8, wrong["faces"])  # triangle 7 lost, 8 twice
    np.savez(path, depth=built.depth, **wrong)
    assert _same(cached_wide_bvh(vertices, triangles, apart), built)
    # So is one whose triangles are all there, but moved (another mesh's geometry).
    moved_corners = {f: getattr(built, f) for f in ("bounds", "children", "corners", "faces")}
    moved_corners["corners"] = built.corners + np.float32(0.5)
    np.savez(path, depth=built.depth, **moved_corners)
    assert _same(cached_wide_bvh(vertices, triangles, apart), built)


def test_an_unwritable_cache_only_costs_a_build(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache folder would go")
    monkeypatch.setenv("WARPIS_CACHE_DIR", str(blocker / "cache"))
    vertices, triangles = _soup(CACHE_MIN_TRIANGLES, seed=2)
    assert _same(cached_wide_bvh(vertices, triangles, np.arange(3)), build_wide_bvh(vertices, triangles, np.arange(3)))
