"""Analytic spheres as plain data: centres, radii, one-sided emission.

A sphere is a shape of its own, not triangles: the kernels intersect it exactly
(kernels/spheres.py), light techniques sample it exactly (``light-solid-angle`` the cone
it subtends, ``light-area`` and ``light-power`` its surface), and it blocks shadow rays
like any surface.  Its *front* is the outside, or the inside where ``inward`` (Mitsuba's
``flip_normals``): an emitting sphere emits on its front only, as Mitsuba's area light
does.  Scene sources build a :class:`Spheres` table (a TOML ``[[sphere]]``, Mitsuba's
``sphere`` shape) and :func:`check_spheres` is their one gate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .. import limits
from ..errors import WarpisError, fail

__all__ = ["SPHERE_SUBDIVISIONS", "Spheres", "check_spheres", "sphere_points", "tessellate_sphere"]


@dataclass(frozen=True, eq=False)
class Spheres:
    """Analytic spheres (numpy, read-only once checked)."""

    centers: np.ndarray  # (S, 3) float64
    radii: np.ndarray  # (S,) float64, > 0
    emission: np.ndarray  # (S,) float64: radiance of the front side, 0 for no emitter
    inward: np.ndarray  # (S,) int32: 1 when the front is the inside (flip_normals)
    owner: np.ndarray  # (S,) int32: index into the scene's mesh_names (its label)

    def __len__(self) -> int:
        return len(self.radii)

    @property
    def areas(self) -> np.ndarray:
        """(S,) surface area 4πr² of each sphere."""
        return 4.0 * math.pi * self.radii**2

    @property
    def lights(self) -> np.ndarray:
        """(L,) int32 index of each emitting sphere (emission > 0)."""
        return np.flatnonzero(self.emission > 0).astype(np.int32)

    def normals_at(self, index: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(P, 3) the unit front normal of sphere ``index[i]`` at ``points[i]`` (on its surface)."""
        out = points - self.centers[index]
        out /= np.linalg.norm(out, axis=1, keepdims=True)
        return np.where(self.inward[index, None] != 0, -out, out)

    def surface_distance(self, points: np.ndarray) -> np.ndarray:
        """(P, S) distance from each point to each sphere's surface."""
        d = np.linalg.norm(points[:, None, :] - self.centers[None], axis=2)
        return np.abs(d - self.radii[None])


def check_spheres(spheres: Spheres, owners: int, where: object) -> Spheres:
    """The spheres' arrays against the kernels' limits: shapes, finite centres a float32
    kernel can square, radii > 0 within those limits, emission ≥ 0, valid owners.  Returns
    the same table with read-only arrays."""
    count = len(spheres.radii)
    arrays = {"centers": (count, 3), "radii": (count,), "emission": (count,), "inward": (count,), "owner": (count,)}
    for name, shape in arrays.items():
        a = np.asarray(getattr(spheres, name))
        if a.shape != shape:
            raise fail(where, f"spheres: {name} has shape {a.shape}, expected {shape}")
    if count == 0:
        raise fail(where, "spheres: the table is empty (pass None for a scene without spheres)")
    _within(where, limits.coordinates, spheres.centers, "sphere centres")
    radii = np.asarray(spheres.radii, np.float64)
    bad = ~(np.isfinite(radii) & (radii > 0))
    if bad.any():
        raise fail(where, f"sphere {int(np.argmax(bad))}: radius {radii[bad][0]!r} must be a finite number > 0")
    # A radius must stay resolvable beside its centre's coordinates in float32, and its
    # square (the kernels' intersection) must not overflow.
    reach = np.abs(spheres.centers).max(axis=1) + radii
    tiny = radii < limits.SPHERE_MIN_RELATIVE_RADIUS * reach
    if tiny.any():
        i = int(np.argmax(tiny))
        raise fail(where, f"sphere {i}: radius {radii[i]:.3g} is below float32's resolution at its centre "
                          f"({reach[i]:.3g} from the origin): make it larger or tessellate it")
    _within(where, limits.coordinates, reach[:, None], "sphere centre + radius")
    _within(where, limits.float32_values, spheres.emission, "sphere emission")
    if not np.isin(spheres.inward, (0, 1)).all():
        raise fail(where, "spheres: inward must be 0 or 1")
    if ((spheres.owner < 0) | (spheres.owner >= owners)).any():
        raise fail(where, f"spheres: owner must index the scene's {owners} mesh name(s)")
    for name in arrays:
        view = np.asarray(getattr(spheres, name)).view()
        view.flags.writeable = False
        object.__setattr__(spheres, name, view)
    return spheres


def sphere_points(spheres: Spheres, index: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(P, 3) ``points`` moved radially onto the surface of sphere ``index[i]``."""
    d = points - spheres.centers[index]
    return spheres.centers[index] + spheres.radii[index, None] * d / np.linalg.norm(d, axis=1, keepdims=True)


def _within(where: object, check, *args) -> None:
    try:
        check(*args)
    except WarpisError as exc:
        raise fail(where, str(exc)) from None


# Tessellation, for comparisons (``tessellate = true``): an icosphere of 20·4^3 = 1280
# triangles whose vertices are pushed out so that it keeps the sphere's area.
SPHERE_SUBDIVISIONS = 3


def tessellate_sphere(center: np.ndarray, radius: float, inward: bool = False, rotation: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray, float]:
    """An icosphere of the sphere (center, radius), turned by ``rotation`` (a 3×3 rotation,
    e.g. a Mitsuba to_world's over its scale), pushed out to keep its area: vertices,
    faces wound around its front (outside, or inside when ``inward``), and how far it
    strays from the sphere (a vertex out by push − 1, or a face's nearest point in)."""
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=SPHERE_SUBDIVISIONS, radius=1.0)
    local = np.array(ico.vertices, dtype=np.float64)
    local /= np.linalg.norm(local, axis=1, keepdims=True)
    faces = np.array(ico.faces, dtype=np.int64)
    v = local[faces]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    area = 0.5 * np.linalg.norm(n, axis=1).sum()
    push = math.sqrt(4.0 * math.pi / area)
    plane = np.abs(np.einsum("fj,fj->f", n / np.linalg.norm(n, axis=1, keepdims=True), v[:, 0])) * push
    deviation = radius * max(push - 1.0, float(1.0 - plane.min()))
    outward = np.einsum("fj,fj->f", n, v.mean(axis=1)) > 0
    faces[~outward] = faces[~outward][:, [0, 2, 1]]
    if inward:
        faces = faces[:, [0, 2, 1]]
    turned = local if rotation is None else local @ np.asarray(rotation, np.float64).T
    return np.asarray(center, np.float64) + radius * push * turned, faces, deviation
