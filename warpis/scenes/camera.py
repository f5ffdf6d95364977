"""Camera receivers: a pinhole camera turns every pixel into a receiver.

Each pixel casts one primary ray through its centre (:func:`Camera.directions`); the first
surface it meets becomes a receiver there, with the triangle's geometric normal turned
towards the camera, the material of the mesh it belongs to, and the unit direction to
the camera as its view.  A pixel is *masked* (no receiver, left out of every statistic)
when it sees nothing, sees an emitter triangle (either side: warpis measures reflected
direct light, not emission seen directly), sees the back of a one-sided surface
(Mitsuba returns 0 there), or sees a surface whose BSDF warpis cannot shade (a Mitsuba
shape that warpis keeps as an occluder only: it blocks light, but its reflection is not
warpis's to compute).  :class:`ImageLayout` keeps which pixel each receiver is and
why the others are masked, so that per-receiver numbers become images.

Every scene source with a camera (a TOML scene's ``[receivers.camera]``, a Mitsuba
file's ``perspective`` sensor) builds its receivers with :func:`camera_receivers` from
one material row per mesh (:data:`SURFACE_FIELDS`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .. import limits
from ..errors import WarpisError, fail
from .normals import interpolate_normals
from .spheres import Spheres

# The primary-ray cast that finds what each pixel sees is a Warp kernel, a floor above
# the scenes: kernels/camera.py registers it here when it is imported (warpis/__init__.py
# imports it), so the scenes stay plain data that never import the kernels.
RayCaster = Callable[..., np.ndarray]
_ray_caster: list[RayCaster] = []


def register_ray_caster(cast: RayCaster) -> None:
    """Set ``cast(vertices, triangles, origin, directions, device[, spheres]) → (P,) int32``,
    the first primitive each ray meets: a triangle index, T + s for analytic sphere s of
    ``spheres`` (a :class:`~warpis.scenes.spheres.Spheres`), −1 for none; camera receivers
    are found with it."""
    _ray_caster[:] = [cast]


def first_hits(vertices: np.ndarray, triangles: np.ndarray, origin: np.ndarray, directions: np.ndarray,
               device: str, spheres: Spheres | None = None) -> np.ndarray:
    """The registered ray cast (see :func:`register_ray_caster`)."""
    if not _ray_caster:
        raise WarpisError("camera receivers need the kernels' ray cast: import warpis (it registers it)")
    if spheres is None:
        return _ray_caster[0](vertices, triangles, origin, directions, device)
    return _ray_caster[0](vertices, triangles, origin, directions, device, spheres)


# What a pixel sees (ImageLayout.seen).
PIXEL_RECEIVER, PIXEL_NOTHING, PIXEL_EMITTER, PIXEL_BACK, PIXEL_UNSHADED = 0, 1, 2, 3, 4
MASK_WORDS = {PIXEL_NOTHING: "sees nothing", PIXEL_EMITTER: "sees an emitter",
              PIXEL_BACK: "sees the back of a one-sided surface",
              PIXEL_UNSHADED: "sees a surface whose BSDF warpis cannot shade"}
# Largest image side: far beyond any variance study, small enough that W × H rays and
# their receivers fit the kernels' int32 indices.
MAX_SIDE = 1 << 14
# The receiver arrays a mesh's material gives its pixels (one row per mesh; eta, k and
# specular are (3,) per row, see description.Receivers).
SURFACE_FIELDS = ("material", "albedo", "exponent", "alpha", "distribution", "sample_visible", "eta", "k",
                  "specular", "specular_weight")


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera: position, unit forward, up and right (orthogonal; right is the image's
    +x, which a mirrored camera points the other way), vertical field of view in degrees,
    and the image size in pixels (row 0 at the top)."""

    position: np.ndarray
    forward: np.ndarray
    up: np.ndarray
    right: np.ndarray
    fov: float
    width: int
    height: int

    @classmethod
    def look_at(cls, position: Any, target: Any, up: Any, fov: float, width: int, height: int,
                where: object) -> Camera:
        """A validated camera at ``position`` looking at ``target``; ``up`` need only not be
        parallel to the view; ``fov`` is the vertical field of view in degrees."""
        position, target, up = (np.asarray(v, np.float64) for v in (position, target, up))
        for name, v in (("position", position), ("target", target), ("up", up)):
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise fail(where, f"camera {name}: expected three finite numbers, got {v.tolist()}")
        try:
            limits.coordinates(position[None], "camera position")
        except WarpisError as exc:
            raise fail(where, str(exc)) from None
        forward = target - position
        if not np.linalg.norm(forward) > 0:
            raise fail(where, "camera target: equals the camera position, so the camera looks nowhere")
        forward = forward / np.linalg.norm(forward)
        right = np.cross(forward, up)
        if not np.linalg.norm(right) > 1e-9 * np.linalg.norm(up):
            raise fail(where, f"camera up {up.tolist()}: parallel to the view direction (or zero)")
        right /= np.linalg.norm(right)
        return cls.framed(position, forward, np.cross(right, forward), right, fov, width, height, where)

    @classmethod
    def framed(cls, position: np.ndarray, forward: np.ndarray, up: np.ndarray, right: np.ndarray, fov: float,
               width: int, height: int, where: object) -> Camera:
        """A validated camera from its orthonormal frame (forward, up, right)."""
        if not (isinstance(fov, (int, float)) and not isinstance(fov, bool) and 0 < fov < 180):
            raise fail(where, f"camera fov: expected a vertical field of view in degrees in (0, 180), got {fov!r}")
        width, height = image_side(width, "width", where), image_side(height, "height", where)
        try:
            limits.memory(width * height * 64.0, f"a {width} × {height} camera")
        except WarpisError as exc:
            raise fail(where, str(exc)) from None
        return cls(position, forward, up, right, float(fov), width, height)

    def resized(self, width: int | None, height: int | None, where: object) -> Camera:
        """The camera with a new image size (either side None: kept, or scaled with the
        other to keep the aspect); the vertical field of view is kept."""
        if width is None and height is None:
            return self
        if height is None:
            height = max(1, round(image_side(width, "width", where) * self.height / self.width))
        if width is None:
            width = max(1, round(image_side(height, "height", where) * self.width / self.height))
        return Camera.framed(self.position, self.forward, self.up, self.right, self.fov, width, height, where)

    @property
    def shape(self) -> tuple[int, int]:
        return self.height, self.width

    def directions(self) -> np.ndarray:
        """(H·W, 3) unit directions through the pixel centres, row-major from the top left."""
        tan_y = math.tan(math.radians(self.fov) / 2)
        tan_x = tan_y * self.width / self.height
        right = self.right
        x = ((np.arange(self.width) + 0.5) / self.width * 2 - 1) * tan_x
        y = (1 - (np.arange(self.height) + 0.5) / self.height * 2) * tan_y
        d = self.forward + x[None, :, None] * right + y[:, None, None] * self.up
        d = d.reshape(-1, 3)
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def describe(self) -> str:
        p, f = self.position, self.position + self.forward
        return (f"camera at ({', '.join(f'{x:.6g}' for x in p)}) looking towards "
                f"({', '.join(f'{x:.6g}' for x in f)}), vertical field of view {self.fov:.6g}°, "
                f"{self.width} × {self.height} pixels")


def image_side(value: Any, what: str, where: object) -> int:
    """An image width or height: an integer in [1, MAX_SIDE]."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 1 <= value <= MAX_SIDE:
        raise fail(where, f"camera {what}: expected an integer number of pixels in [1, {MAX_SIDE}], got {value!r}")
    return int(value)


@dataclass(frozen=True, eq=False)
class ImageLayout:
    """Which pixel each receiver is, and what every other pixel sees."""

    camera: Camera
    seen: np.ndarray  # (H, W) int8, PIXEL_*
    pixel: np.ndarray  # (R,) int64: row-major index of receiver i's pixel

    @property
    def shape(self) -> tuple[int, int]:
        return self.camera.shape

    def to_image(self, values: np.ndarray, fill: float = math.nan) -> np.ndarray:
        """(H, W) image of per-receiver ``values`` (R,), ``fill`` at masked pixels."""
        out = np.full(self.shape[0] * self.shape[1], fill, dtype=np.result_type(values, type(fill)))
        out[self.pixel] = values
        return out.reshape(self.shape)

    def describe(self) -> str:
        """One line for ``warpis info``: receivers and masked pixels by reason."""
        masked = self.masked_counts()
        return (f"{len(self.pixel)} of {self.shape[0] * self.shape[1]} pixels are receivers; masked: "
                f"{masked['nothing']} see nothing, {masked['emitter']} an emitter, {masked['back']} the back of a "
                f"one-sided surface"
                + (f", {masked['unshaded']} a surface whose BSDF warpis cannot shade" if masked["unshaded"] else ""))

    def masked_counts(self) -> dict[str, int]:
        """How many pixels are masked, by reason."""
        return {"nothing": int((self.seen == PIXEL_NOTHING).sum()), "emitter": int((self.seen == PIXEL_EMITTER).sum()),
                "back": int((self.seen == PIXEL_BACK).sum()), "unshaded": int((self.seen == PIXEL_UNSHADED).sum())}


@dataclass(frozen=True)
class CameraHits:
    """Receivers of a camera as arrays: positions, normals, views, the mesh of each, and the layout."""

    positions: np.ndarray
    normals: np.ndarray  # shading normals, towards the camera
    view: np.ndarray
    mesh: np.ndarray
    layout: ImageLayout
    notes: tuple[str, ...]
    geometric_normals: np.ndarray | None = None  # the triangles' own, on the same side; None: ``normals``
    triangles: np.ndarray | None = None  # the triangle each receiver lies on


def cast_camera(camera: Camera, vertices: np.ndarray, triangles: np.ndarray, emission: np.ndarray,
                owner: np.ndarray, two_sided: Sequence[bool], device: str,
                corner_normals: np.ndarray | None = None, unshaded: Sequence[str | None] | None = None,
                spheres: Spheres | None = None) -> CameraHits:
    """Cast the camera's primary rays; the receivers they find and what each pixel sees.

    ``corner_normals`` (T, 3, 3), where given, are the vertex normals at each triangle's
    corners (its own normal, three times, for a flat one): the receivers then shade with
    their interpolation, and a one-sided surface's back is judged by it, as in Mitsuba.

    ``unshaded``, where given, holds per mesh None, or words naming a mesh whose BSDF
    warpis cannot shade (an occluder only): its pixels, either side, are masked as
    ``PIXEL_UNSHADED`` (an emitter's stay ``PIXEL_EMITTER``), with a note counting them
    by mesh.

    ``spheres``, where given, are analytic spheres (their ``owner`` indexes the same mesh
    rows): a pixel that sees one first lies on it exactly, with its exact normal."""
    directions = camera.directions()
    face = first_hits(vertices, triangles, camera.position, directions, device, spheres)
    seen = np.full(len(face), PIXEL_NOTHING, np.int8)
    hit = np.flatnonzero(face >= 0)
    d = directions[hit]
    tri = np.where(face[hit] < len(triangles), face[hit], -1)
    ball = np.flatnonzero(tri < 0)
    flat = np.flatnonzero(tri >= 0)
    n = np.zeros((len(hit), 3))
    t = np.zeros(len(hit))
    dn = np.ones(len(hit))
    v = vertices[triangles[tri[flat]]]
    with np.errstate(invalid="ignore", divide="ignore"):
        nf = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        nf /= np.linalg.norm(nf, axis=1, keepdims=True)
        n[flat] = nf
        dn[flat] = np.einsum("ij,ij->i", d[flat], nf)
        # The hit point on the triangle's plane in float64 (the float32 ray's t is coarser).
        t[flat] = np.einsum("ij,ij->i", v[:, 0] - camera.position, nf) / dn[flat]
    emitter = np.zeros(len(hit), bool)
    own = np.zeros(len(hit), np.int64)
    emitter[flat] = emission[tri[flat]] > 0
    own[flat] = owner[tri[flat]]
    if len(ball):
        sid = face[hit[ball]] - len(triangles)
        t[ball], n[ball] = _sphere_crossing(spheres, sid, camera.position, d[ball])
        emitter[ball] = spheres.emission[sid] > 0
        own[ball] = spheres.owner[sid]
    # A ray grazing a triangle edge-on, or one whose triangle has no area, finds no surface.
    solid = np.isfinite(t) & (t > 0) & (np.abs(dn) > 1e-6)
    notes = []
    if not solid.all():
        notes.append(f"{int((~solid).sum())} pixel(s) meet a triangle edge-on or one of zero area: masked as "
                     f"seeing nothing")
    shade = n.copy()
    if corner_normals is not None and len(flat):
        interpolated = interpolate_normals(corner_normals[tri[flat]], v, camera.position + t[flat, None] * d[flat])
        cancelled = ~np.isfinite(interpolated).all(axis=1)
        interpolated[cancelled] = nf[cancelled]  # vertex normals that cancel: the triangle's own
        shade[flat] = interpolated
    with np.errstate(invalid="ignore"):
        ds = np.einsum("ij,ij->i", d, shade)
    cannot = np.zeros(len(hit), bool)
    if unshaded is not None:
        cannot = np.array([u is not None for u in unshaded], bool)[own] & solid & ~emitter
        if cannot.any():
            meshes, counts = np.unique(own[cannot], return_counts=True)
            notes.append(f"{int(cannot.sum())} pixel(s) see a surface whose BSDF warpis cannot shade: masked ("
                         + ", ".join(f"{unshaded[m]}: {c}" for m, c in zip(meshes, counts)) + ")")
    back = (ds > 0) & ~np.asarray(two_sided, bool)[own] & ~cannot
    seen[hit[solid & emitter]] = PIXEL_EMITTER
    seen[hit[cannot]] = PIXEL_UNSHADED
    seen[hit[solid & ~emitter & back]] = PIXEL_BACK
    keep = solid & ~emitter & ~back & ~cannot
    seen[hit[keep]] = PIXEL_RECEIVER
    p = camera.position + t[keep, None] * d[keep]
    towards = (ds[keep] < 0)[:, None]
    normals = np.where(towards, shade[keep], -shade[keep])
    geometric = np.where(towards, n[keep], -n[keep])
    view = -d[keep]
    layout = ImageLayout(camera, seen.reshape(camera.shape), hit[keep].astype(np.int64))
    return CameraHits(p, normals, view, own[keep], layout, tuple(notes), geometric, tri[keep])


def _sphere_crossing(spheres: Spheres, index: np.ndarray, origin: np.ndarray, d: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(t, front normal) where rays from ``origin`` along ``d`` first meet spheres ``index``
    (float64; t = nan for a miss): the near root meets the outside, the far one the inside."""
    oc = spheres.centers[index] - origin
    tc = np.einsum("ij,ij->i", oc, d) / np.einsum("ij,ij->i", d, d)
    q = np.linalg.norm(tc[:, None] * d - oc, axis=1)
    r = spheres.radii[index]
    with np.errstate(invalid="ignore"):
        h = np.sqrt((r - q) * (r + q)) / np.linalg.norm(d, axis=1)
    t = np.where(tc - h > 0, tc - h, tc + h)
    outward = (origin + t[:, None] * d - spheres.centers[index]) / r[:, None]
    return t, np.where(spheres.inward[index, None] != 0, -outward, outward)


def camera_receiver_fields(hits: CameraHits, surfaces: Sequence[dict[str, Any] | None],
                           unmaterialled: Callable[[int, int], str], where: object) -> dict[str, Any]:
    """Every field of the Receivers of the camera's pixels (one group, "camera", and the
    layout): each takes its mesh's row of ``surfaces`` (``SURFACE_FIELDS``); a mesh seen
    by the camera with no material (None) is an error, ``unmaterialled(mesh, pixels)``
    saying which."""
    if len(hits.mesh) == 0:
        raise fail(where, f"the camera sees no surface that reflects light ({hits.layout.camera.describe()}; "
                          f"masked: {hits.layout.masked_counts()})")
    seen_meshes, counts = np.unique(hits.mesh, return_counts=True)
    for m, c in zip(seen_meshes, counts):
        if surfaces[m] is None:
            raise fail(where, unmaterialled(int(m), int(c)))
    out: dict[str, Any] = {"positions": hits.positions, "normals": hits.normals,
                           "geometric_normals": hits.geometric_normals, "view": hits.view,
                           "group": np.zeros(len(hits.positions), np.int32), "group_names": ["camera"],
                           "image": hits.layout}
    for name in SURFACE_FIELDS:
        kind = np.int32 if name in ("material", "distribution", "sample_visible") else np.float64
        table = np.array([np.zeros_like(surfaces[seen_meshes[0]][name]) if s is None else s[name] for s in surfaces],
                         kind)
        out[name] = table[hits.mesh]
    return out
