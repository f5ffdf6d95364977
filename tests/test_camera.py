"""Tests of camera receivers (warpis/scenes/camera.py, kernels/camera.py and the two scene
sources' cameras): pixel rays, what each pixel sees, the receiver it becomes, and every
bad camera as a one-line error.

What each pixel sees is held against a brute-force float64 ray cast (Möller–Trumbore over
every triangle), and a Mitsuba camera's rays against Mitsuba's own ``sample_ray``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import warpis
from conftest import one_error_line, write_scene
from warpis.errors import WarpisError
from warpis.kernels.camera import first_hits
from warpis.kernels.integrand import MATERIALS
from warpis.kernels.shading import DISTRIBUTIONS
from warpis.scenes.camera import (PIXEL_BACK, PIXEL_EMITTER, PIXEL_NOTHING, PIXEL_RECEIVER, Camera, ImageLayout,
                                  cast_camera)

ESTIMATOR = "jittered:single:light-solid-angle"
EDGE = 1e-5  # barycentric distance from an edge below which float32 and float64 may disagree


# --------------------------------------------------------------------------- scenes


def rect(origin, eu, ev) -> tuple[np.ndarray, np.ndarray]:
    """A parallelogram origin + s·eu + t·ev as two triangles; its front normal is eu × ev."""
    o, eu, ev = (np.asarray(x, float) for x in (origin, eu, ev))
    return np.array([o, o + eu, o + eu + ev, o + ev]), np.array([[0, 1, 2], [0, 2, 3]])


def entry(path: str, shape: tuple[np.ndarray, np.ndarray], **keys) -> dict:
    v, f = shape
    return {"path": path, "vertices": v, "faces": f, **keys}


PHONG_10 = {"type": "phong", "exponent": 10.0}
CONDUCTOR = {"type": "roughconductor", "alpha": 0.3, "eta": 1.5, "k": 2.0, "distribution": "beckmann"}
PHONG_300 = {"type": "phong", "exponent": 300.0}
FALLBACK = {"type": "lambert", "albedo": 0.5}
CAMERA = {"position": [0.0, -6.0, 1.5], "target": [0.0, 0.0, 1.0], "fov": 40.0, "width": 24, "height": 18}


def meshes(floor: dict | None = None) -> list[dict]:
    """Seen from CAMERA (y is depth): a floor (no material of its own unless ``floor``), a
    near plate facing the camera, a plate further back facing away (seen from behind), a
    back wall, a lamp facing the camera, a lamp facing away, an unmaterialled quad behind
    the camera, and a small card a quarter unit in front of the camera (top left).  The
    sky above the wall and the sides see nothing."""
    return [
        entry("floor.obj", rect([-4, -5, 0], [8, 0, 0], [0, 8, 0]), **({} if floor is None else {"material": floor})),
        entry("near.obj", rect([-1.5, 0, 0.3], [1.3, 0, 0], [0, 0, 1.2]), material=PHONG_10),
        entry("back.obj", rect([1.2, 1.5, 0.5], [-1.7, 0, 0], [0, 0, 1.5]), material=CONDUCTOR),
        entry("wall.obj", rect([-3, 3, 0], [6, 0, 0], [0, 0, 2.5]), material=PHONG_300),
        entry("lamp.obj", rect([0.3, 0.8, 1.2], [0.6, 0, 0], [0, 0, 0.4]), emission=5.0),
        entry("lamp-back.obj", rect([2.0, 2.5, 1.0], [-0.7, 0, 0], [0, 0, 0.8]), emission=5.0),
        entry("behind.obj", rect([-1, -8, 0], [2, 0, 0], [0, 0, 2])),
        entry("close.obj", rect([-0.2, -5.75, 1.55], [0.15, 0, 0], [0, 0, 0.1]), material=PHONG_10),
    ]


def camera_scene(directory: Path, camera: dict | None = None, mesh_list: list[dict] | None = None,
                 material: dict | None = FALLBACK, receivers: dict | None = None) -> Path:
    """The scene of :func:`meshes` with ``[receivers.camera]`` = ``camera`` (default CAMERA)."""
    rx = receivers if receivers is not None else {"camera": CAMERA if camera is None else camera}
    return write_scene(directory, meshes=meshes() if mesh_list is None else mesh_list, receivers=rx,
                       material=material)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> warpis.Scene:
    return warpis.load_scene(camera_scene(tmp_path_factory.mktemp("camera")), camera=True)


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def brute_force(origin: np.ndarray, directions: np.ndarray, tris: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Möller–Trumbore in float64 of every ray against every triangle (T, 3, 3): the first
    triangle each ray meets (−1: none), its distance, and whether the pixel is ambiguous
    (its ray passes within EDGE, in barycentric terms, of some triangle's edge)."""
    e1, e2 = tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    p = np.cross(directions[:, None], e2[None])
    det = np.einsum("tk,ptk->pt", e1, p)
    s = origin - tris[:, 0]
    q = np.cross(s, e1)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.einsum("tk,ptk->pt", s, p) / det
        v = np.einsum("pk,tk->pt", directions, q) / det
        t = np.einsum("tk,tk->t", e2, q)[None] / det
    margin = np.minimum(np.minimum(u, v), 1 - u - v)
    ahead = np.isfinite(t) & (t > 0)
    hit = ahead & (margin >= 0)
    depth = np.where(hit, t, np.inf)
    first = np.where(hit.any(axis=1), np.argmin(depth, axis=1), -1)
    ambiguous = (ahead & (np.abs(margin) < EDGE)).any(axis=1)
    return first, depth.min(axis=1), ambiguous


def expected_view(scene: warpis.Scene) -> dict[str, np.ndarray]:
    """The brute-force answer for every pixel of ``scene``'s camera."""
    cam = scene.receivers.image.camera
    dirs = cam.directions()
    tri, t, ambiguous = brute_force(cam.position, dirs, scene.vertices[scene.triangles])
    return {"dirs": dirs, "tri": tri, "t": t, "ambiguous": ambiguous}


def seen_codes(scene: warpis.Scene, tri: np.ndarray) -> np.ndarray:
    """What each pixel of a TOML scene (two-sided materials) should see, from the triangle its ray meets."""
    codes = np.full(len(tri), PIXEL_NOTHING, np.int8)
    hit = tri >= 0
    codes[hit] = np.where(scene.emission[tri[hit]] > 0, PIXEL_EMITTER, PIXEL_RECEIVER)
    return codes


# --------------------------------------------------------------------------- camera geometry


def test_directions_unit_centred_and_oriented():
    """Pixel rays are unit, the centre pixel of an odd-sized image looks straight ahead,
    row 0 is the top (+up) and column 0 the left (−right), and each pixel centre sits at
    the tangent-space offset of a vertical field of view ``fov`` and a horizontal one of
    atan(tan(fov/2)·W/H): guards against a swapped aspect, a horizontal fov read as
    vertical, flipped axes and half-pixel shifts."""
    w, h, fov = 7, 5, 50.0
    cam = Camera.look_at([1.0, 2.0, 3.0], [1.0, 7.0, 3.0], [0.0, 0.0, 4.0], fov, w, h, "here")
    np.testing.assert_allclose(cam.forward, [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(cam.up, [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(cam.right, [1, 0, 0], atol=1e-15)  # right-handed: forward × up
    d = cam.directions()
    assert d.shape == (w * h, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, rtol=1e-14)
    d = d.reshape(h, w, 3)
    np.testing.assert_allclose(d[h // 2, w // 2], cam.forward, atol=1e-15)
    along = d @ cam.forward
    horizontal = np.degrees(np.arctan2(d @ cam.right, along))
    vertical = np.degrees(np.arctan2(d @ cam.up, along))
    half_y = math.radians(fov) / 2
    half_x = math.atan(math.tan(half_y) * w / h)
    # Pixel centres: tangent offsets (1 − 1/W)·tan(half_x) from the centre at the edges.
    cols = ((np.arange(w) + 0.5) / w * 2 - 1) * math.tan(half_x)
    rows = (1 - (np.arange(h) + 0.5) / h * 2) * math.tan(half_y)
    np.testing.assert_allclose(horizontal, np.degrees(np.arctan(cols))[None, :].repeat(h, 0), atol=1e-12)
    np.testing.assert_allclose(vertical, np.degrees(np.arctan(rows))[:, None].repeat(w, 1), atol=1e-9)
    assert horizontal[0, 0] < 0 < horizontal[0, -1] and vertical[0, 0] > 0 > vertical[-1, 0]
    # The image's outer edges (half a pixel past the outer centres) are at the half-angles.
    edge_x = cols[-1] + (cols[1] - cols[0]) / 2
    edge_y = rows[0] + (rows[0] - rows[1]) / 2
    assert math.atan(edge_x) == pytest.approx(half_x, rel=1e-12)
    assert math.atan(edge_y) == pytest.approx(half_y, rel=1e-12)


def test_a_tilted_camera_keeps_an_orthonormal_frame():
    """look_at with an up that is not perpendicular to the view gives an orthonormal,
    right-handed frame whose up leans towards the given up."""
    cam = Camera.look_at([0.0, -15.0, 6.5], [0.0, -1.5, 2.1], [0.0, 0.0, 1.0], 30.0, 16, 12, "here")
    frame = np.array([cam.right, cam.up, cam.forward])
    np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(np.cross(cam.forward, cam.up), cam.right, atol=1e-14)
    assert cam.up[2] > 0.9
    np.testing.assert_allclose(cam.forward, unit(np.array([0.0, 13.5, -4.4])), atol=1e-14)


def test_resized_keeps_vertical_fov_and_aspect():
    """``resized`` with one side scales the other to keep the aspect (rounded), with both
    uses them as given, with neither is the camera itself; the vertical field of view,
    position and frame never change; a bad side is a one-line error."""
    cam = Camera.look_at([0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], 33.0, 40, 30, "here")
    assert cam.resized(None, None, "here") is cam
    for width, height, shape in [(20, None, (15, 20)), (None, 15, (15, 20)), (33, None, (25, 33)),
                                 (None, 7, (7, 9)), (17, 5, (5, 17)), (1, None, (1, 1))]:
        r = cam.resized(width, height, "here")
        assert r.shape == shape, (width, height)
        assert r.fov == cam.fov
        for name in ("position", "forward", "up", "right"):
            np.testing.assert_array_equal(getattr(r, name), getattr(cam, name))
    # The vertical angle of the top row's centre follows the new height, not the old one.
    r = cam.resized(None, 15, "here")
    top = r.directions()[0]
    assert math.degrees(math.atan2(top @ r.up, top @ r.forward)) == pytest.approx(
        math.degrees(math.atan((1 - 1 / 15) * math.tan(math.radians(16.5)))), rel=1e-12)
    for bad in (0, -3, 2.5, True, 1 << 20):
        with pytest.raises(WarpisError, match=r"^here: camera width: expected an integer number of pixels"):
            cam.resized(bad, None, "here")


# --------------------------------------------------------------------------- what each pixel sees


def test_first_hits_match_a_float64_brute_force(scene):
    """The Warp BVH cast (first_hits, float32) meets the same triangle as a float64
    Möller–Trumbore over all triangles at every pixel not within EDGE of an edge; a ray
    that meets nothing finds −1.  Guards against a wrong origin, direction or nearest hit."""
    exp = expected_view(scene)
    cam = scene.receivers.image.camera
    face = first_hits(scene.vertices, scene.triangles, cam.position, exp["dirs"], "cpu")
    clear = ~exp["ambiguous"]
    assert clear.sum() > 0.95 * len(clear)  # the comparison covers nearly every pixel
    np.testing.assert_array_equal(face[clear], exp["tri"][clear])
    # Every kind of pixel is in the picture: nothing, each mesh, both lamps.
    meshes_seen = set(scene.triangle_mesh[exp["tri"][exp["tri"] >= 0]].tolist())
    assert meshes_seen == {0, 1, 2, 3, 4, 5, 7} and (exp["tri"] < 0).any()


def test_masks_follow_what_each_pixel_sees(scene):
    """seen is 1 where the ray meets nothing, 2 on an emitter seen from either side, 0
    everywhere else (TOML materials are two-sided: the plate seen from behind is a
    receiver); the receivers are exactly the 0 pixels, row-major; masked_counts adds up."""
    exp = expected_view(scene)
    layout = scene.receivers.image
    assert layout.seen.shape == (18, 24) and layout.seen.dtype == np.int8
    codes = seen_codes(scene, exp["tri"])
    clear = ~exp["ambiguous"]
    np.testing.assert_array_equal(layout.seen.ravel()[clear], codes[clear])
    np.testing.assert_array_equal(layout.pixel, np.flatnonzero(layout.seen.ravel() == PIXEL_RECEIVER))
    assert len(scene.receivers) == len(layout.pixel)
    lamp_back = scene.mesh_names.index("lamp-back.obj")
    hit_lamp_back = np.isin(exp["tri"], np.flatnonzero(scene.triangle_mesh == lamp_back)) & clear
    assert hit_lamp_back.any() and (layout.seen.ravel()[hit_lamp_back] == PIXEL_EMITTER).all()
    counts = layout.masked_counts()
    assert counts == {"nothing": int((layout.seen == 1).sum()), "emitter": int((layout.seen == 2).sum()), "back": 0,
                      "unshaded": 0}
    assert counts["nothing"] > 0 and counts["emitter"] > 0


def test_receivers_lie_on_their_triangle_and_face_the_camera(scene):
    """Each receiver is its ray's float64 hit point on the hit triangle's plane, its normal
    is that triangle's unit normal turned towards the camera (dot(normal, view) > 0, also
    for the plate seen from behind), and its view is unit(camera − position)."""
    exp = expected_view(scene)
    rx = scene.receivers
    cam = rx.image.camera
    pix = rx.image.pixel
    clear = ~exp["ambiguous"][pix]
    tri = exp["tri"][pix][clear]
    p = rx.positions[clear]
    np.testing.assert_allclose(p, cam.position + exp["t"][pix][clear, None] * exp["dirs"][pix][clear],
                               rtol=1e-9, atol=1e-9)
    v = scene.vertices[scene.triangles[tri]]
    n = unit(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]))
    assert np.abs(np.einsum("ij,ij->i", p - v[:, 0], n)).max() < 1e-9
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", rx.normals[clear], n)), 1.0, rtol=1e-12)
    np.testing.assert_allclose(rx.view, unit(cam.position - rx.positions), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(rx.normals, axis=1), 1.0, rtol=1e-12)
    assert (np.einsum("ij,ij->i", rx.normals, rx.view) > 0).all()
    flipped = np.einsum("ij,ij->i", rx.normals[clear], n) < 0  # the geometric normal points away
    back_plate = scene.mesh_names.index("back.obj")
    assert (scene.triangle_mesh[tri[flipped]] == back_plate).all() and flipped.sum() > 0


def test_cast_camera_masks_one_sided_backs():
    """cast_camera on arrays: a one-sided triangle seen from behind is 3 (a two-sided one a
    receiver with its normal flipped), an emitter seen from behind is 2, and the meshes
    of the receivers are those they see."""
    cam = Camera.look_at([0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], 60.0, 9, 9, "here")
    # Left: a quad facing away; middle: an emitter facing away; right: a quad facing the camera.
    quads = [rect([-3, 2, -2], [0, 0, 4], [2, 0, 0]), rect([-1, 2, -2], [0, 0, 4], [2, 0, 0]),
             rect([1, 2, -2], [2, 0, 0], [0, 0, 4])]
    vertices = np.vstack([q[0] for q in quads])
    triangles = np.vstack([q[1] + 4 * i for i, q in enumerate(quads)]).astype(np.int32)
    emission = np.array([0, 0, 3.0, 3.0, 0, 0])
    owner = np.array([0, 0, 1, 1, 2, 2], np.int32)
    one = cast_camera(cam, vertices, triangles, emission, owner, [False, False, False], "cpu")
    two = cast_camera(cam, vertices, triangles, emission, owner, [True, True, True], "cpu")
    exp, _, ambiguous = brute_force(cam.position, cam.directions(), vertices[triangles])
    mesh = np.where(exp >= 0, owner[np.maximum(exp, 0)], -1)
    want = np.select([mesh == 0, mesh == 1, mesh == 2], [PIXEL_BACK, PIXEL_EMITTER, PIXEL_RECEIVER], PIXEL_NOTHING)
    np.testing.assert_array_equal(one.layout.seen.ravel()[~ambiguous], want[~ambiguous])
    assert (one.layout.seen == PIXEL_BACK).sum() >= 9 and (one.layout.seen == PIXEL_EMITTER).sum() >= 9
    want_two = np.where(want == PIXEL_BACK, PIXEL_RECEIVER, want)
    np.testing.assert_array_equal(two.layout.seen.ravel()[~ambiguous], want_two[~ambiguous])
    assert (np.einsum("ij,ij->i", two.normals, two.view) > 0).all()
    np.testing.assert_allclose(two.normals[two.mesh == 0], np.tile([0.0, -1.0, 0.0], ((two.mesh == 0).sum(), 1)))
    assert set(two.mesh.tolist()) == {0, 2} and set(one.mesh.tolist()) == {2}
    assert one.layout.masked_counts()["back"] == (one.layout.seen == PIXEL_BACK).sum()


def test_cast_camera_drops_degenerate_and_backward_hits(monkeypatch):
    """A hit the float32 cast reports on a triangle of zero area, or one whose plane lies
    behind the camera, becomes "sees nothing" with a note, never a receiver at a NaN or
    backward position."""
    cam = Camera.look_at([0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], 30.0, 4, 3, "here")
    vertices = np.array([[0, 2, 0], [1, 2, 0], [2, 2, 0],  # zero area: three points on a line
                         [-5, 2, -5], [5, 2, -5], [0, 2, 5],  # in front, facing the camera
                         [-5, -2, -5], [5, -2, -5], [0, -2, 5]], float)  # behind the camera
    triangles = np.array([[0, 1, 2], [3, 5, 4], [6, 8, 7]], np.int32)
    faces = np.array([0, 1, 2, 1, 0, 1, 2, 1, 0, 1, 2, 1], np.int32)
    monkeypatch.setattr("warpis.scenes.camera.first_hits", lambda *args: faces)
    hits = cast_camera(cam, vertices, triangles, np.zeros(3), np.arange(3, dtype=np.int32), [True] * 3, "cpu")
    seen = hits.layout.seen.ravel()
    np.testing.assert_array_equal(seen, np.where(faces == 1, PIXEL_RECEIVER, PIXEL_NOTHING))
    assert np.isfinite(hits.positions).all() and (hits.positions[:, 1] > 0).all()
    assert (hits.mesh == 1).all()
    assert len(hits.notes) == 1 and hits.notes[0].startswith("6 pixel(s) meet a triangle edge-on or one of zero area")


def test_to_image_places_each_receiver_at_its_pixel():
    """ImageLayout.to_image puts value i at pixel[i] (row-major) and fills the rest."""
    cam = Camera.look_at([0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], 40.0, 4, 3, "here")
    seen = np.array([[1, 0, 0, 2], [0, 3, 0, 0], [1, 1, 0, 1]], np.int8)
    layout = ImageLayout(cam, seen, np.flatnonzero(seen.ravel() == 0))
    img = layout.to_image(np.arange(6.0))
    assert img.shape == (3, 4)
    np.testing.assert_array_equal(img[seen == 0], np.arange(6.0))
    assert np.isnan(img[seen != 0]).all()
    winners = layout.to_image(np.array([0, 1, 1, 0, 1, 0], np.int16), fill=-1)
    assert (winners[seen != 0] == -1).all() and winners[0, 1] == 0 and winners[0, 2] == 1
    assert layout.masked_counts() == {"nothing": 4, "emitter": 1, "back": 1, "unshaded": 0}


# --------------------------------------------------------------------------- materials


def test_each_pixel_takes_its_meshs_material(scene):
    """Each receiver carries the material of the mesh it sees: phong exponents per mesh,
    the roughconductor's parameters, and the scene's [material] for the floor that has
    none of its own.  Guards against one material for all pixels or a mesh index mix-up."""
    exp = expected_view(scene)
    rx = scene.receivers
    mesh = scene.triangle_mesh[exp["tri"][rx.image.pixel]]
    names = np.array(scene.mesh_names)[mesh]
    code = {name: MATERIALS[name].code for name in ("lambert", "phong", "roughconductor")}
    for path, kind, exponent in [("floor.obj", "lambert", None), ("near.obj", "phong", 10.0),
                                 ("back.obj", "roughconductor", None), ("wall.obj", "phong", 300.0)]:
        at = names == path
        assert at.sum() > 3, path
        assert (rx.material[at] == code[kind]).all(), path
        if exponent is not None:
            assert (rx.exponent[at] == exponent).all(), path
    floor = names == "floor.obj"
    assert (rx.albedo[floor] == 0.5).all()
    metal = names == "back.obj"
    assert (rx.alpha[metal] == 0.3).all() and (rx.distribution[metal] == DISTRIBUTIONS["beckmann"]).all()
    np.testing.assert_array_equal(rx.eta[metal], np.full((metal.sum(), 3), 1.5))
    np.testing.assert_array_equal(rx.k[metal], np.full((metal.sum(), 3), 2.0))
    assert (rx.alpha[~metal] != 0.3).all()


def test_a_mesh_material_overrides_the_scene_material(tmp_path):
    """A [[mesh]] material wins over [material]: giving the floor phong 42 changes the
    floor's pixels only."""
    path = write_scene(tmp_path, meshes=meshes(floor={"type": "phong", "exponent": 42.0}),
                       receivers={"camera": CAMERA}, material=FALLBACK)
    rx = warpis.load_scene(path, camera=True).receivers
    assert (rx.exponent == 42.0).sum() > 10
    assert set(np.unique(rx.exponent).tolist()) == {1.0, 10.0, 42.0, 300.0}  # 1: the conductor's unused default
    assert MATERIALS["lambert"].code not in rx.material


def test_unmaterialled_meshes_are_an_error_only_when_a_pixel_sees_them(tmp_path):
    """Without [material], a mesh with no material that no pixel sees (behind the camera)
    or that only emits (the lamps) is fine; one that pixels see (the floor) is a one-line
    error naming it and the fix."""
    ok = write_scene(tmp_path / "ok", meshes=meshes(floor=FALLBACK), receivers={"camera": CAMERA}, material=None)
    assert len(warpis.load_scene(ok, camera=True).receivers) > 0
    bad = write_scene(tmp_path / "bad", meshes=meshes(), receivers={"camera": CAMERA}, material=None)
    with pytest.raises(WarpisError) as excinfo:
        warpis.load_scene(bad, camera=True)
    message = str(excinfo.value)
    assert "\n" not in message and message.startswith(f"{bad}: ")
    assert "[[mesh]] #1 (floor.obj) is seen by" in message and "has no material" in message


# --------------------------------------------------------------------------- bad TOML cameras


def with_camera(**change) -> dict:
    cam = dict(CAMERA)
    for key, value in change.items():
        if value is None:
            cam.pop(key)
        else:
            cam[key] = value
    return cam


FOV_RANGE = "camera fov: expected a vertical field of view in degrees in (0, 180)"
PIXELS = "expected an integer number of pixels in [1, 16384]"
BAD_CAMERAS = {
    "no-position": (with_camera(position=None), "missing key 'position' in [receivers.camera]"),
    "no-target": (with_camera(target=None), "missing key 'target' in [receivers.camera]"),
    "no-fov": (with_camera(fov=None), "missing key 'fov' in [receivers.camera]"),
    "no-width": (with_camera(width=None), "missing key 'width' in [receivers.camera]"),
    "no-height": (with_camera(height=None), "missing key 'height' in [receivers.camera]"),
    "fov-0": (with_camera(fov=0.0), FOV_RANGE),
    "fov-180": (with_camera(fov=180), FOV_RANGE),
    "fov-negative": (with_camera(fov=-30.0), FOV_RANGE),
    "fov-string": (with_camera(fov="wide"), "[receivers.camera].fov must be a number"),
    "fov-nan": (with_camera(fov=math.nan), "[receivers.camera].fov must be finite"),
    "width-0": (with_camera(width=0), f"camera width: {PIXELS}, got 0"),
    "width-huge": (with_camera(width=1 << 20), f"camera width: {PIXELS}, got 1048576"),
    "width-float": (with_camera(width=24.0), f"camera width: {PIXELS}, got 24.0"),
    "width-bool": (with_camera(width=True), f"camera width: {PIXELS}, got True"),
    "height-negative": (with_camera(height=-2), f"camera height: {PIXELS}, got -2"),
    "height-string": (with_camera(height="18"), f"camera height: {PIXELS}, got '18'"),
    "target-is-position": (with_camera(target=[0.0, -6.0, 1.5]), "camera target: equals the camera position"),
    "up-parallel": (with_camera(target=[0.0, 0.0, 1.5], up=[0.0, 2.0, 0.0]), "parallel to the view direction"),
    "up-zero": (with_camera(up=[0.0, 0.0, 0.0]), "parallel to the view direction (or zero)"),
    "position-short": (with_camera(position=[0.0, 1.0]), "[receivers.camera].position must be a list of 3 numbers"),
    "position-inf": (with_camera(position=[0.0, math.inf, 1.0]), "[receivers.camera].position must be finite"),
    "position-huge": (with_camera(position=[1e30, -6.0, 1.5]),
                      "camera position: point 0 has a coordinate of magnitude"),
    "unknown-key": (with_camera(aspect=1.5), "unknown key 'aspect' in [receivers.camera]"),
}


def bad_scene(directory: Path, case: str) -> tuple[Path, str]:
    """A scene file with one thing wrong (named ``case``) and the words its error must hold."""
    if case in BAD_CAMERAS:
        cam, words = BAD_CAMERAS[case]
        return camera_scene(directory, cam), words
    if case == "view-in-mesh-material":
        mesh_list = meshes()
        mesh_list[1]["material"] = PHONG_10 | {"view": [0.0, 0.0, 1.0]}
        return camera_scene(directory, mesh_list=mesh_list), "[[mesh]] #2.material.view: a camera gives each pixel"
    if case == "view-in-scene-material":
        return (camera_scene(directory, material={"type": "phong", "exponent": 5.0, "view": [0.0, 0.0, 1.0]}),
                "[material].view: a camera gives each pixel")
    if case == "camera-and-points":
        return (camera_scene(directory, receivers={"camera": CAMERA, "points": [[0.0, 0.0, 0.0]]}),
                "unknown key 'points' in [receivers] (a camera's receivers are its pixels)")
    if case == "camera-not-a-table":
        return camera_scene(directory, receivers={"camera": [1, 2, 3]}), "[receivers.camera] must be a table"
    if case == "unmaterialled-seen":
        return camera_scene(directory, material=None), "[[mesh]] #1 (floor.obj) is seen by"
    if case == "sees-no-receiver":
        return (camera_scene(directory, with_camera(target=[0.0, -6.0, 9.0], up=[0.0, 1.0, 0.0])),
                "the camera sees no surface that reflects light")
    raise ValueError(case)


BAD_CASES = [*BAD_CAMERAS, "view-in-mesh-material", "view-in-scene-material", "camera-and-points",
             "camera-not-a-table", "unmaterialled-seen", "sees-no-receiver"]


@pytest.mark.parametrize("case", BAD_CASES)
def test_bad_toml_camera_is_one_line_naming_the_file(tmp_path, case):
    """Each bad camera scene fails to load with one line starting with the file's path."""
    path, words = bad_scene(tmp_path, case)
    with pytest.raises(WarpisError) as excinfo:
        warpis.load_scene(path, camera=True)
    message = str(excinfo.value)
    assert "\n" not in message and message.startswith(f"{path}: "), message
    assert words in message, message


@pytest.mark.parametrize("case", ["no-position", "fov-0", "fov-negative", "fov-string", "width-huge", "width-bool",
                                  "target-is-position", "up-parallel", "unknown-key", "view-in-mesh-material",
                                  "camera-and-points", "unmaterialled-seen"])
def test_bad_toml_camera_through_warpis_image(tmp_path, cli, case):
    """`warpis image` on a bad camera scene: exit 2, one line naming the file, no --out."""
    path, words = bad_scene(tmp_path / "scene", case)
    out = tmp_path / "out"
    line = one_error_line(cli("image", path, "--estimator", ESTIMATOR, "--n", "4", "--trials", "8", "--out", out))
    assert str(path) in line and words in line, line
    assert not out.exists()


def test_image_needs_a_camera(tmp_path, cli, write_scene):
    """`warpis image` on a TOML scene without [receivers.camera] (a bundled one or a
    written one), with or without --width/--height, is one line; so is load_scene with
    width on such a scene.  Nothing is written."""
    out = tmp_path / "out"
    for args in (["occluded-quad"], ["occluded-quad", "--width", "16"], ["occluded-quad", "--height", "12"]):
        line = one_error_line(cli("image", *args, "--estimator", ESTIMATOR, "--n", "4", "--trials", "8",
                                  "--out", out))
        assert "occluded-quad" in line and "camera" in line, line
    plain = write_scene(tmp_path / "plain")
    line = one_error_line(cli("image", plain, "--estimator", ESTIMATOR, "--n", "4", "--out", out))
    assert str(plain) in line and "has no camera" in line
    assert not out.exists()
    with pytest.raises(WarpisError, match="has no camera to resize"):
        warpis.load_scene(plain, width=16)
    with pytest.raises(WarpisError, match="has no camera"):
        warpis.load_scene(plain, camera=True)
    assert warpis.load_scene(plain).receivers.image is None  # without camera=True, a plain scene loads


def test_width_and_height_resize_a_toml_camera(tmp_path, cli):
    """load_scene's width/height (and `warpis image --width/--height`) resize the camera,
    the other side following the aspect; a bad --width is one line."""
    path = camera_scene(tmp_path)
    assert warpis.load_scene(path, camera=True, width=12).receivers.image.shape == (9, 12)
    assert warpis.load_scene(path, camera=True, height=6).receivers.image.shape == (6, 8)
    scene = warpis.load_scene(path, camera=True, width=10, height=4)
    assert scene.receivers.image.shape == (4, 10) and scene.receivers.image.camera.fov == 40.0
    for bad in ("0", "-1", "2.5"):
        line = one_error_line(cli("image", path, "--estimator", ESTIMATOR, "--n", "4", "--width", bad,
                                  "--out", tmp_path / "out"))
        assert "--width" in line
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- Mitsuba cameras

FOV = 40.0
FLOOR_XML = ('<shape type="rectangle" id="floor"><transform name="to_world"><scale value="2"/></transform>'
             '<bsdf type="diffuse"/></shape>')
# A one-sided plate standing at y = 0.5: its front (the rectangle's +z, rotated to +y) faces away from the camera.
PLATE_XML = ('<shape type="rectangle" id="plate"><transform name="to_world"><scale x="0.6" y="0.4"/>'
             '<rotate x="1" angle="-90"/><translate x="-0.8" y="0.5" z="0.6"/></transform>{bsdf}</shape>')
LIGHT_XML = ('<shape type="rectangle" id="light"><transform name="to_world"><scale value="0.3"/>'
             '<rotate x="1" angle="180"/><translate x="0.8" z="1.5"/></transform>'
             '<emitter type="area"><rgb name="radiance" value="10"/></emitter></shape>')


def sensor_xml(kind: str = "perspective", pre: str = "", extra: str = "", width: int = 16, height: int = 12,
               film_extra: str = "") -> str:
    return (f'<sensor type="{kind}" id="cam">{extra}<transform name="to_world">{pre}'
            f'<lookat origin="0.5, -4, 3" target="0, 0, 0.3" up="0, 0, 1"/></transform>'
            f'<film type="hdrfilm"><integer name="width" value="{width}"/><integer name="height" value="{height}"/>'
            f'{film_extra}</film></sensor>')


def write_xml(directory: Path, sensor: str, name: str = "scene", bsdf: str = '<bsdf type="diffuse"/>') -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{name}.xml"
    plate = PLATE_XML.format(bsdf=bsdf)
    path.write_text(f'<scene version="3.0.0">{sensor}{FLOOR_XML}{plate}{LIGHT_XML}</scene>\n')
    return path


@pytest.fixture(scope="module")
def mi():
    mitsuba = pytest.importorskip("mitsuba")
    mitsuba.set_variant("scalar_rgb")
    return mitsuba


def mitsuba_directions(mi, path: Path) -> np.ndarray:
    """(H, W, 3) directions of Mitsuba's own rays through the pixel centres of the first sensor."""
    sensor = mi.load_file(str(path), parallel=False).sensors()[0]
    w, h = (int(x) for x in sensor.film().size())
    out = np.empty((h, w, 3))
    for i in range(h):
        for j in range(w):
            ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f((j + 0.5) / w, (i + 0.5) / h), mi.Point2f(0.5, 0.5))
            out[i, j] = np.array(ray.d)
    return out


def fov_xml(value: float = FOV) -> str:
    return f'<float name="fov" value="{value}"/><string name="fov_axis" value="x"/>'


@pytest.mark.parametrize("mirror", [False, True])
def test_mitsuba_camera_rays_are_mitsubas(tmp_path, mi, mirror):
    """A perspective sensor's pixel rays are Mitsuba's own rays through the pixel centres
    (its x_fov, its +x towards the image's left), mirrored or not; the origin is the sensor's."""
    path = write_xml(tmp_path, sensor_xml(extra=fov_xml(), pre='<scale x="-1"/>' if mirror else ""))
    cam = warpis.load_scene(path, camera=True).receivers.image.camera
    assert (cam.width, cam.height) == (16, 12)
    np.testing.assert_allclose(cam.directions().reshape(12, 16, 3), mitsuba_directions(mi, path), atol=2e-6)
    np.testing.assert_allclose(cam.position, [0.5, -4, 3], atol=1e-6)
    assert cam.fov == pytest.approx(2 * math.degrees(math.atan(math.tan(math.radians(FOV / 2)) * 12 / 16)), rel=1e-6)


def test_mitsuba_resize_keeps_the_horizontal_fov(tmp_path, mi):
    """width/height override the film and keep x_fov: a 16×12 film resized to 20×10 gives
    Mitsuba's rays for a 20×10 film; one side alone keeps the film's aspect."""
    small = write_xml(tmp_path / "a", sensor_xml(extra=fov_xml()))
    wide = write_xml(tmp_path / "b", sensor_xml(extra=fov_xml(), width=20, height=10))
    cam = warpis.load_scene(small, camera=True, width=20, height=10).receivers.image.camera
    assert (cam.width, cam.height) == (20, 10)
    np.testing.assert_allclose(cam.directions().reshape(10, 20, 3), mitsuba_directions(mi, wide), atol=2e-6)
    assert warpis.load_scene(small, camera=True, width=8).receivers.image.shape == (6, 8)
    assert warpis.load_scene(small, camera=True, height=3).receivers.image.shape == (3, 4)


def test_mirrored_camera_flips_the_image_left_right(tmp_path, mi):
    """<scale x="-1"/> before the lookat mirrors the picture: its seen array is the
    unmirrored one flipped left–right (the scene is not symmetric, so a no-op would fail)."""
    plain = warpis.load_scene(write_xml(tmp_path / "a", sensor_xml(extra=fov_xml())), camera=True)
    mirrored = warpis.load_scene(write_xml(tmp_path / "b", sensor_xml(extra=fov_xml(), pre='<scale x="-1"/>')),
                                 camera=True)
    seen = plain.receivers.image.seen
    assert not np.array_equal(seen, seen[:, ::-1])
    np.testing.assert_array_equal(mirrored.receivers.image.seen, seen[:, ::-1])
    assert len(mirrored.receivers) == len(plain.receivers)


def test_mitsuba_back_of_one_sided_bsdf_is_masked(tmp_path, mi):
    """Pixels that see the back of a one-sided BSDF are 3 with a note; the same plate with a
    twosided BSDF gives receivers there, normals towards the camera; Mitsuba's own rays
    meet the plate at exactly those pixels."""
    one = write_xml(tmp_path / "one", sensor_xml(extra=fov_xml()))
    two = write_xml(tmp_path / "two", sensor_xml(extra=fov_xml()),
                    bsdf='<bsdf type="twosided"><bsdf type="diffuse"/></bsdf>')
    s1 = warpis.load_scene(one, camera=True)
    s2 = warpis.load_scene(two, camera=True)
    ms = mi.load_file(str(one), parallel=False, optimize=False)  # shapes keep their ids
    cam = s1.receivers.image.camera
    on_plate = np.zeros(cam.width * cam.height, bool)
    for k, d in enumerate(cam.directions()):
        si = ms.ray_intersect(mi.Ray3f(mi.Point3f(*cam.position), mi.Vector3f(*d)))
        on_plate[k] = si.is_valid() and si.shape.id() == "plate"
    assert on_plate.sum() >= 4
    seen1, seen2 = s1.receivers.image.seen.ravel(), s2.receivers.image.seen.ravel()
    np.testing.assert_array_equal(seen1 == PIXEL_BACK, on_plate)
    assert not (seen2 == PIXEL_BACK).any()
    assert (seen2[on_plate] == PIXEL_RECEIVER).all()
    assert s1.receivers.image.masked_counts()["back"] == on_plate.sum()
    assert any("see the back of a one-sided BSDF" in n for n in s1.notes)
    rx = s2.receivers
    assert (np.einsum("ij,ij->i", rx.normals, rx.view) > 0).all()
    light = seen1 == PIXEL_EMITTER  # the light seen from above: its back, still an emitter
    assert light.any()
    np.testing.assert_array_equal(light, seen2 == PIXEL_EMITTER)


@pytest.mark.parametrize("sensor, words", [
    (sensor_xml("orthographic"), "sensor 'cam' is a 'orthographic' sensor: an image needs a 'perspective' one"),
    (sensor_xml("thinlens", extra='<float name="aperture_radius" value="0.1"/>'
                                  '<float name="focus_distance" value="3"/>'), "is a 'thinlens' sensor"),
    ("", "has no <sensor>"),
    (sensor_xml(pre='<scale value="2"/>'), "Scale factors"),
    (sensor_xml(pre='<scale x="1" y="1.5" z="1"/>'), "Scale factors"),
    (sensor_xml(extra='<float name="principal_point_offset_x" value="0.1"/>'), "a principal point offset"),
    (sensor_xml(extra='<float name="principal_point_offset_y" value="-0.2"/>'), "a principal point offset"),
    (sensor_xml(film_extra='<integer name="crop_width" value="8"/>'), "a crop window is not supported"),
    (sensor_xml(film_extra='<integer name="crop_offset_x" value="2"/><integer name="crop_width" value="14"/>'),
     "a crop window is not supported"),
])
def test_bad_mitsuba_camera_is_one_line(tmp_path, mi, cli, sensor, words):
    """Each sensor an image cannot use is one line naming the file, from load_scene and
    from `warpis image` (exit 2, nothing written)."""
    path = write_xml(tmp_path, sensor)
    with pytest.raises(WarpisError) as excinfo:
        warpis.load_scene(path, camera=True)
    message = str(excinfo.value)
    assert "\n" not in message and message.startswith(f"{path}: ") and words in message, message
    out = tmp_path / "out"
    line = one_error_line(cli("image", path, "--estimator", ESTIMATOR, "--n", "4", "--out", out))
    assert str(path) in line and words in line
    assert not out.exists()


def test_mitsuba_size_options_need_a_camera(tmp_path, mi):
    """A Mitsuba load without camera=True refuses width/height; with it, a bad width is one line."""
    path = write_xml(tmp_path, sensor_xml(extra=fov_xml()))
    with pytest.raises(WarpisError, match="this load has no camera"):
        warpis.load_scene(path, width=8)
    for bad in (0, 2.5, True, 1 << 20):
        with pytest.raises(WarpisError, match=r"camera width: expected an integer number of pixels") as excinfo:
            warpis.load_scene(path, camera=True, width=bad)
        assert str(excinfo.value).startswith(f"{path}: ")


def test_info_describes_the_camera_and_its_masks(cli):
    """`warpis info` on a camera scene names the camera and counts receivers and masked
    pixels by reason, the same counts as the scene's layout."""
    import json

    import warpis

    result = cli("info", "veach-plates-camera", "--json")
    assert result.status == 0, result.err
    notes = json.loads(result.out)["notes"]
    layout = warpis.load_scene("veach-plates-camera").receivers.image
    masked = layout.masked_counts()
    assert any(n.startswith("camera at (0, -15, 6.5)") and "128 × 96 pixels" in n for n in notes)
    assert (f"{len(layout.pixel)} of 12288 pixels are receivers; masked: {masked['nothing']} see nothing, "
            f"{masked['emitter']} an emitter, 0 the back of a one-sided surface") in notes
    assert len(layout.pixel) + sum(masked.values()) == 128 * 96
