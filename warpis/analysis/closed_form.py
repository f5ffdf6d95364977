"""Closed-form irradiance from uniform, one-sided polygonal emitters.

Ground truth for the irradiance integrand (ρ = 1)::

    F(x) = ∫ Le(ω) · V(x, ω) · max(0, n·ω) dω

at a receiver point ``x`` with unit normal ``n``.  Emission is one-sided: a triangle
``(v0, v1, v2)`` emits only from its front face, the side its normal
``(v1 − v0) × (v2 − v0)`` points to.  Without occlusion the integral is the sum, over
the emitter triangles whose front faces ``x``, of the radiance times the cosine-weighted
solid angle of the part of the triangle above ``x``'s horizon; that part is obtained by
clipping the triangle to the half-space ``n·(y − x) > 0`` and integrated exactly with
Lambert's contour formula (see ``docs/theory.md``).

:func:`pyramid_blockers` tells, per receiver, whether the occlusion-free sum is the
true value: it looks for scene triangles inside the pyramid spanned by ``x`` and each
front-facing, horizon-clipped emitter triangle.

Everything is pure numpy in float64.  Array conventions: receivers ``x`` and normals
``n`` are ``(R, 3)``, triangles are ``(T, 3, 3)`` (triangle, vertex, coordinate),
per-triangle radiance is ``(T,)``.
"""

from __future__ import annotations

import numpy as np

from ..scenes.lambert import (as_points, as_triangles, chunks, clip_batch, clip_polygon_to_halfspace, dot,
                              front_facing, normalize_or_zero, polygon_irradiance, triangle_irradiance, unit_rows)

__all__ = [
    "clip_polygon_to_halfspace",
    "polygon_irradiance",
    "triangle_irradiance",
    "pyramid_blockers",
    "irradiance_closed_form",
]

# (pyramid, triangle) pairs per separating-axis batch; small enough that the search
# stops soon after the first blocker.
_SAT_CHUNK = 1 << 13
# Pyramids per bounding-cone cluster in pyramid_blockers.
_CLUSTER = 32
# Angular slack (radians) added to bounding cones, above arccos round-off.
_ANGLE_SLACK = 1e-6
# Relative tolerance of pyramid_blockers when ``tol`` is not given: a fraction of the
# diagonal of the bounding box of the scene and the receivers.
DEFAULT_REL_TOL = 1e-6


# --------------------------------------------------------------------------------------
# exactness: separating-axis test of scene triangles against emitter pyramids
# --------------------------------------------------------------------------------------


def _interval(axes: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Projection interval of point sets on axes.

    Parameters
    ----------
    axes : ndarray, shape (M, A, 3)
    pts : ndarray, shape (M, K, 3)

    Returns
    -------
    lo, hi : ndarray, shape (M, A)
        ``min_k axes·pts[k]`` and ``max_k axes·pts[k]``.
    """
    lo = hi = None
    for k in range(pts.shape[1]):
        p = (axes[..., 0] * pts[:, None, k, 0] + axes[..., 1] * pts[:, None, k, 1]
             + axes[..., 2] * pts[:, None, k, 2])
        if lo is None:
            lo, hi = p, p
        else:
            lo, hi = np.minimum(lo, p), np.maximum(hi, p)
    return lo, hi


def _depth(tmin: np.ndarray, tmax: np.ndarray, pmin: np.ndarray,
           pmax: np.ndarray) -> np.ndarray:
    """Penetration depth of two intervals: how far one must move to stop overlapping.

    ``min(tmax − pmin, pmax − tmin)``; ``<= 0`` when they are disjoint or touch.
    """
    return np.minimum(tmax - pmin, pmax - tmin)


def _pyramids_for_receiver(x: np.ndarray, n: np.ndarray, emitters: np.ndarray,
                           emitter_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pyramids of one receiver, in coordinates relative to ``x``.

    Apex ``x`` (the origin after the shift), base = the part of a front-facing emitter
    triangle above the horizon of ``(x, n)``.

    Returns
    -------
    verts : ndarray, shape (P, 5, 3)
        Apex (zeros) followed by the base polygon padded to 4 vertices, minus ``x``.
    owner : ndarray of int, shape (P,)
        Scene index of the emitter triangle of each pyramid.
    """
    front = front_facing(x[None], emitters)[0]
    idx = np.nonzero(front)[0]
    if idx.size == 0:
        return np.zeros((0, 5, 3)), np.zeros(0, dtype=np.int64)
    local = emitters[idx] - x
    zero = np.zeros((idx.size, 3))
    base, count = clip_batch(local, zero, np.broadcast_to(n, (idx.size, 3)))
    keep = count >= 3
    base = base[keep, :4]
    verts = np.concatenate([np.zeros((base.shape[0], 1, 3)), base], axis=1)
    return verts, emitter_index[idx[keep]]


def _pyramid_axes(verts: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Separating-axis candidates that depend on the pyramid alone.

    Receiver normal, base normal, the 4 side-face normals and the 4 in-plane normals of
    the base edges (the latter matter only for flat, degenerate pyramids).

    Returns
    -------
    axes : ndarray, shape (P, 10, 3)
        Unit axes (zero where degenerate).
    valid : ndarray of bool, shape (P, 10)
    """
    apex = verts[:, 0]
    base = verts[:, 1:]
    base_next = np.roll(base, -1, axis=1)
    side_edge = base - apex[:, None, :]
    base_edge = base_next - base
    base_n = 0.5 * np.sum(np.cross(base, base_next), axis=1)
    side_n = np.cross(side_edge, np.roll(side_edge, -1, axis=1))
    edge_n = np.cross(base_n[:, None, :], base_edge)
    p = verts.shape[0]
    raw = np.concatenate([np.broadcast_to(n, (p, 1, 3)), base_n[:, None, :], side_n, edge_n],
                         axis=1)
    scale = np.max(np.linalg.norm(side_edge, axis=-1), axis=1) + np.max(
        np.linalg.norm(base_edge, axis=-1), axis=1)
    scale_pow = np.concatenate([np.ones((p, 1)), np.repeat(scale[:, None] ** 2, 5, axis=1),
                                np.repeat(scale[:, None] ** 3, 4, axis=1)], axis=1)
    return normalize_or_zero(raw, scale_pow)


def _triangle_axes(tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Separating-axis candidates of triangles alone: normal and 3 in-plane edge normals.

    Returns
    -------
    axes : ndarray, shape (T, 4, 3)
    valid : ndarray of bool, shape (T, 4)
    """
    edge = np.roll(tris, -1, axis=1) - tris
    normal = np.cross(edge[:, 0], edge[:, 1])
    edge_n = np.cross(normal[:, None, :], edge)
    scale = np.max(np.linalg.norm(edge, axis=-1), axis=1)
    raw = np.concatenate([normal[:, None, :], edge_n], axis=1)
    scale_pow = np.stack([scale**2, scale**3, scale**3, scale**3], axis=1)
    return normalize_or_zero(raw, scale_pow)


def _sat_blocked(pv: np.ndarray, p_axes: np.ndarray, p_valid: np.ndarray,
                 p_lo: np.ndarray, p_hi: np.ndarray,
                 tv: np.ndarray, t_axes: np.ndarray, t_valid: np.ndarray,
                 tol: float) -> np.ndarray:
    """Exact separating-axis test of (pyramid, triangle) pairs, with tolerance.

    A pair is *blocked* when the penetration depth (:func:`_depth`) of their
    projections exceeds ``tol`` on every candidate axis: the 3 coordinate axes, the 10
    pyramid axes, the 4 triangle axes and the 24 cross products of a triangle edge with
    a pyramid edge (4 lateral, 4 base).  Cheap axes go first and each stage only keeps
    the pairs still unseparated.

    Parameters
    ----------
    pv : ndarray, shape (M, 5, 3)
        Pyramid vertices (apex, base).
    p_axes, p_valid : ndarray, shapes (M, 10, 3), (M, 10)
        Pyramid-only axes.
    p_lo, p_hi : ndarray, shape (M, 10)
        Projection interval of each pyramid on its own axes.
    tv : ndarray, shape (M, 3, 3)
        Triangles, in the same coordinates as ``pv``.
    t_axes, t_valid : ndarray, shapes (M, 4, 3), (M, 4)
        Triangle-only axes.
    tol : float

    Returns
    -------
    ndarray of bool, shape (M,)
    """
    out = np.zeros(pv.shape[0], dtype=bool)
    idx = np.arange(pv.shape[0])

    # Coordinate axes (bounding boxes).
    alive = np.all(_depth(tv.min(axis=1), tv.max(axis=1), pv.min(axis=1), pv.max(axis=1))
                   > tol, axis=1)
    idx = idx[alive]
    if idx.size == 0:
        return out
    pv, tv = pv[alive], tv[alive]
    p_axes, p_valid, p_lo, p_hi = p_axes[alive], p_valid[alive], p_lo[alive], p_hi[alive]
    t_axes, t_valid = t_axes[alive], t_valid[alive]

    # Pyramid faces (and the receiver's horizon).
    tmin, tmax = _interval(p_axes, tv)
    alive = ~np.any((_depth(tmin, tmax, p_lo, p_hi) <= tol) & p_valid, axis=1)
    idx = idx[alive]
    if idx.size == 0:
        return out
    pv, tv, t_axes, t_valid = pv[alive], tv[alive], t_axes[alive], t_valid[alive]

    # Triangle normal and its in-plane edge normals.
    tmin, tmax = _interval(t_axes, tv)
    pmin, pmax = _interval(t_axes, pv)
    alive = ~np.any((_depth(tmin, tmax, pmin, pmax) <= tol) & t_valid, axis=1)
    idx = idx[alive]
    if idx.size == 0:
        return out
    pv, tv = pv[alive], tv[alive]

    # Edge × edge.
    t_edge = np.roll(tv, -1, axis=1) - tv  # (M, 3, 3)
    base = pv[:, 1:]
    p_edge = np.concatenate([base - pv[:, :1], np.roll(base, -1, axis=1) - base], axis=1)
    raw = np.cross(t_edge[:, :, None, :], p_edge[:, None, :, :]).reshape(-1, 24, 3)
    scale = (np.linalg.norm(t_edge, axis=-1)[:, :, None]
             * np.linalg.norm(p_edge, axis=-1)[:, None, :]).reshape(-1, 24)
    axes, valid = normalize_or_zero(raw, scale)
    tmin, tmax = _interval(axes, tv)
    pmin, pmax = _interval(axes, pv)
    alive = ~np.any((_depth(tmin, tmax, pmin, pmax) <= tol) & valid, axis=1)
    out[idx[alive]] = True
    return out


def _bounding_cones(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Circular cones with apex at the origin containing the cones over point sets.

    Parameters
    ----------
    pts : ndarray, shape (P, K, 3)
        Points (pyramid bases, relative to the apex).

    Returns
    -------
    axis : ndarray, shape (P, 3)
        Unit axis (normalised mean of the unit directions).
    half_angle : ndarray, shape (P,)
        Half-angle, padded by a small slack; ``π`` (accept everything) when no convex
        cone with that axis is found (a point at the apex, or directions too spread).
    radius : ndarray, shape (P,)
        Largest distance of a point from the apex.
    """
    dist = np.linalg.norm(pts, axis=-1)
    ok = np.all(dist > 0.0, axis=1)
    unit = pts / np.where(dist > 0.0, dist, 1.0)[..., None]
    axis, valid = normalize_or_zero(unit.sum(axis=1))
    cos_min = np.einsum("pkc,pc->pk", unit, axis).min(axis=1)
    wide = ~(ok & valid) | (cos_min <= 0.0)
    half = np.where(wide, np.pi, np.arccos(np.clip(cos_min, -1.0, 1.0)) + _ANGLE_SLACK)
    return axis, half, dist.max(axis=1)


def _cone_hits(axis: np.ndarray, half: np.ndarray, radius: np.ndarray,
               c_dir: np.ndarray, c_half: np.ndarray, c_near: np.ndarray,
               tol: float) -> np.ndarray:
    """``(P, C)`` mask: cone ``p`` (truncated at ``radius``) may meet bounding sphere ``c``.

    The sphere is seen from the apex within ``c_half`` of ``c_dir`` and lies no nearer
    than ``c_near``; a pair is rejected only when these bounds prove it disjoint.
    """
    cos = np.clip(dot(axis[:, None, :], c_dir[None, :, :]), -1.0, 1.0)
    return (c_near[None, :] < radius[:, None] + tol) & (
        np.arccos(cos) <= half[:, None] + c_half[None, :])


def _morton_order(v: np.ndarray) -> np.ndarray:
    """Order of unit vectors along a Z-order curve of the cube ``[-1, 1]³``."""

    def spread(q: np.ndarray) -> np.ndarray:
        q = (q | (q << 16)) & 0x030000FF
        q = (q | (q << 8)) & 0x0300F00F
        q = (q | (q << 4)) & 0x030C30C3
        return (q | (q << 2)) & 0x09249249

    q = np.clip(((v + 1.0) * 511.5).astype(np.int64), 0, 1023)
    code = spread(q[:, 0]) | (spread(q[:, 1]) << 1) | (spread(q[:, 2]) << 2)
    return np.argsort(code, kind="stable")


def pyramid_blockers(x: np.ndarray, n: np.ndarray, tris: np.ndarray,
                     emitter_mask: np.ndarray, tol: float | None = None) -> np.ndarray:
    """Whether any scene triangle lies inside a receiver's emitter pyramids.

    For receiver ``r`` (point ``x_r``, unit normal ``n_r``) and each emitter triangle
    ``e`` (``emitter_mask[e]``) whose front faces ``x_r`` (``N_e·(x_r − v0_e) > 0``)
    and whose part ``e⁺`` above the horizon (clip to ``n_r·(y − x_r) > 0``) is
    non-empty, the *pyramid* is the convex hull ``P = conv({x_r} ∪ e⁺)``.  A scene
    triangle ``t ≠ e`` *blocks* ``P`` when, on every axis ``a`` of the candidate set
    below, the projections of ``t`` and ``P`` penetrate by more than ``tol``::

        min(max a·t − min a·P,  max a·P − min a·t) > tol.

    Candidate unit axes: the three coordinate axes, ``n_r``, the normals of the faces
    of ``P`` (base and lateral faces), the in-plane normals of the base edges, the
    normal of ``t`` and the in-plane normals of its edges, and every cross product of
    an edge of ``t`` with an edge of ``P``.  This set contains the face normals and
    edge-pair cross products that the separating-axis theorem needs, so with
    ``tol = 0`` a triangle blocks ``P`` exactly when it meets the *open* pyramid
    ``int P``.  With ``tol > 0`` a triangle is clear when some candidate plane puts it
    on the far side of ``P`` up to an overlap of ``tol``, i.e. it meets ``P`` at most
    in a slab of thickness ``tol`` along ``P``'s boundary.  In particular:

    * surfaces through the apex (the floor on which ``x_r`` sits, even when ``x_r``
      lies within ``tol`` below it) are clear, also when a face of a horizon-clipped
      pyramid lies in their plane;
    * triangles sharing an edge or a vertex with the base from outside ``P``
      (neighbours of the emitter, coplanar or bent away from ``x_r``; the other
      front-facing triangles of a convex light) are clear;
    * a triangle that reaches deeper than ``tol`` into ``P`` on every candidate axis
      blocks it, however small it is.

    A receiver is *clear* (``False`` here) when no triangle blocks any of its
    pyramids.  Then every ray from ``x_r`` towards the interior of a front-facing
    emitter's part above the horizon reaches that emitter first (up to the ``tol``
    slab), so the occlusion-free sum of :func:`triangle_irradiance` is the exact
    irradiance; directions outside these pyramids carry no front-face emission either
    way, so their occlusion does not matter.  Overlapping emitters are caught too: a
    nearer emitter triangle inside a farther one's pyramid blocks it.  The test is
    sufficient, not necessary: a triangle meeting the open pyramid edge-on (in a plane
    through ``x_r``) hides only a null set of directions but is still reported.

    Parameters
    ----------
    x : array_like, shape (R, 3)
        Receiver points (pyramid apices).
    n : array_like, shape (R, 3)
        Receiver normals; normalised internally.
    tris : array_like, shape (T, 3, 3)
        All scene triangles, emitters included.
    emitter_mask : array_like of bool, shape (T,)
        Which triangles emit (get pyramids).
    tol : float, optional
        Absolute tolerance in scene units.  Default: ``1e-6`` times the diagonal of the
        bounding box of the triangles and receivers.

    Returns
    -------
    ndarray of bool, shape (R,)
        ``True`` where some triangle blocks some pyramid of the receiver.

    Notes
    -----
    Work per receiver, in coordinates relative to ``x_r``: one pass over all
    triangles against the horizon plane and the bounding box of the union of the
    pyramids; the pyramids, sorted by direction, are grouped in clusters of bounding
    cones, and the surviving triangles' bounding spheres are tested against the
    cluster cones and then the pyramid cones; the remaining pairs go through the
    vectorised separating-axis test, stopping at the first blocker.  All these
    prefilters only discard pairs that are provably disjoint or within ``tol``
    along a candidate axis, so the result is that of the definition above.
    """
    xa = as_points(x, "x")
    na = unit_rows(as_points(n, "n"), "n")
    if xa.shape != na.shape:
        raise ValueError(f"x and n must have the same shape, got {xa.shape} and {na.shape}")
    t_all = as_triangles(tris)
    mask = np.asarray(emitter_mask, dtype=bool).reshape(-1)
    if mask.shape[0] != t_all.shape[0]:
        raise ValueError("emitter_mask must have one entry per triangle")
    r = xa.shape[0]
    blocked = np.zeros(r, dtype=bool)
    emit_idx = np.nonzero(mask)[0]
    if r == 0 or emit_idx.size == 0 or t_all.shape[0] == 0:
        return blocked
    if tol is None:
        pts = np.concatenate([t_all.reshape(-1, 3), xa], axis=0)
        tol = DEFAULT_REL_TOL * float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    tol = float(tol)
    if not np.isfinite(tol) or tol < 0.0:
        raise ValueError("tol must be finite and non-negative")

    emitters = t_all[emit_idx]
    t_lo = t_all.min(axis=1)
    t_hi = t_all.max(axis=1)
    t_axes_all, t_valid_all = _triangle_axes(t_all)
    t_center = t_all.mean(axis=1)
    t_rad = np.linalg.norm(t_all - t_center[:, None, :], axis=-1).max(axis=1)

    for ri in range(r):
        xr, nr = xa[ri], na[ri]
        pv, owner = _pyramids_for_receiver(xr, nr, emitters, emit_idx)
        if pv.shape[0] == 0:
            continue
        # Triangles that can meet the union of the pyramids deeper than tol along n_r and
        # the coordinate axes (the depth against the union bounds that against each).
        u_lo, u_hi = pv.min(axis=(0, 1)), pv.max(axis=(0, 1))
        h_t = np.max(dot(t_all - xr, nr), axis=1)
        h_p = float(np.min(dot(pv, nr)))
        cand = (h_t - h_p > tol) & np.all(
            _depth(t_lo - xr, t_hi - xr, u_lo[None, :], u_hi[None, :]) > tol, axis=1)
        cand_idx = np.nonzero(cand)[0]
        if cand_idx.size == 0:
            continue

        # Bounding spheres of the candidates, seen from the apex.
        c_vec = t_center[cand_idx] - xr
        c_dist = np.linalg.norm(c_vec, axis=1)
        c_r = t_rad[cand_idx]
        inside = c_r >= c_dist
        c_dir = c_vec / np.where(c_dist > 0.0, c_dist, 1.0)[:, None]
        c_half = np.where(inside, np.pi,
                          np.arcsin(np.clip(c_r / np.where(inside, 1.0, c_dist), 0.0, 1.0))
                          + _ANGLE_SLACK)
        c_near = c_dist - c_r

        # Pyramid cones, sorted by direction and grouped into clusters.
        axis, half, radius = _bounding_cones(pv[:, 1:])
        order = _morton_order(axis)
        pv, owner, axis, half, radius = pv[order], owner[order], axis[order], half[order], \
            radius[order]
        p_axes, p_valid = _pyramid_axes(pv, nr)
        p_min, p_max = _interval(p_axes, pv)

        for cl in chunks(pv.shape[0], _CLUSTER):
            g_axis, g_ok = normalize_or_zero(axis[cl].sum(axis=0)[None])
            spread = np.arccos(np.clip(dot(axis[cl], g_axis[0]), -1.0, 1.0)) + half[cl]
            g_half = np.pi if not g_ok[0] else min(np.pi, float(spread.max()) + _ANGLE_SLACK)
            near = _cone_hits(g_axis, np.array([g_half]), radius[cl].max(keepdims=True),
                              c_dir, c_half, c_near, tol)[0]
            sub = np.nonzero(near)[0]
            if sub.size == 0:
                continue
            pair = _cone_hits(axis[cl], half[cl], radius[cl], c_dir[sub], c_half[sub],
                              c_near[sub], tol)
            pair &= cand_idx[sub][None, :] != owner[cl, None]
            pi, ci = np.nonzero(pair)
            pi += cl.start
            ti = cand_idx[sub[ci]]
            hit = False
            for part in chunks(pi.size, _SAT_CHUNK):
                pp, tt = pi[part], ti[part]
                if np.any(_sat_blocked(pv[pp], p_axes[pp], p_valid[pp], p_min[pp], p_max[pp],
                                       t_all[tt] - xr, t_axes_all[tt], t_valid_all[tt], tol)):
                    hit = True
                    break
            if hit:
                blocked[ri] = True
                break
    return blocked


def irradiance_closed_form(x: np.ndarray, n: np.ndarray, all_tris: np.ndarray,
                           emission: np.ndarray,
                           tol: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form irradiance and where it is exact.

    Parameters
    ----------
    x : array_like, shape (R, 3)
        Receiver points (for warpis's integrand, the shading points ``x + ε·n``).
    n : array_like, shape (R, 3)
        Receiver normals; normalised internally.
    all_tris : array_like, shape (T, 3, 3)
        All scene triangles.
    emission : array_like, shape (T,)
        Front-face radiance per triangle, 0 for non-emitters.
    tol : float, optional
        Tolerance of :func:`pyramid_blockers`.

    Returns
    -------
    values : ndarray, shape (R,)
        Occlusion-free one-sided irradiance (:func:`triangle_irradiance`).
    exact : ndarray of bool, shape (R,)
        ``True`` where no scene triangle blocks any emitter pyramid of the receiver
        (:func:`pyramid_blockers`), so that ``values`` is the true irradiance.
    """
    t_all = as_triangles(all_tris)
    le = np.asarray(emission, dtype=np.float64).reshape(-1)
    values = triangle_irradiance(x, n, t_all, le)
    blocked = pyramid_blockers(x, n, t_all, le != 0.0, tol)
    return values, ~blocked


# --------------------------------------------------------------------------- analytic spheres


def sphere_light_boxes(centers: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """(12 L, 3, 3) the faces of the cube around each sphere (half-side its radius), wound
    outwards: a ray from outside a cube that meets its sphere enters the cube first,
    through a face that faces the ray's origin, so the pyramids to those faces
    (:func:`pyramid_blockers`) hold every ray that can reach the sphere up to the cube."""
    box = unit_cube()
    c = np.asarray(centers, np.float64).reshape(-1, 3)
    r = np.asarray(radii, np.float64).reshape(-1)
    return (c[:, None, None, :] + r[:, None, None, None] * box[None]).reshape(-1, 3, 3)


def unit_cube() -> np.ndarray:
    """(12, 3, 3) the unit cube [−1, 1]³ as triangles wound outwards."""
    out = []
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3
        for sign in (-1.0, 1.0):
            corners = []
            for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.zeros(3)
                p[axis], p[u], p[v] = sign, a, b
                corners.append(p)
            quad = [corners[0], corners[1], corners[2], corners[3]] if sign > 0 else \
                [corners[0], corners[3], corners[2], corners[1]]
            out += [[quad[0], quad[1], quad[2]], [quad[0], quad[2], quad[3]]]
    return np.array(out)


def _cones(x: np.ndarray, centers: np.ndarray, radii: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R, S, 3) unit axes, (R, S) half-angles and (R, S) inside flags of the cones the
    spheres subtend from each point (a point inside a sphere: half-angle π)."""
    d = centers[None] - x[:, None]
    dist = np.linalg.norm(d, axis=2)
    inside = dist <= radii[None]
    with np.errstate(invalid="ignore", divide="ignore"):
        half = np.where(inside, np.pi, np.arcsin(np.clip(radii[None] / dist, 0.0, 1.0)))
        axes = d / dist[..., None]
    return np.nan_to_num(axes), half, inside


def sphere_occlusion(x: np.ndarray, tris: np.ndarray, emission: np.ndarray, centers: np.ndarray, radii: np.ndarray,
                     lights: np.ndarray) -> np.ndarray:
    """(R,) whether a sphere may block some light of each receiver, or the receiver may
    not see a sphere light whole (conservative: True can be a false alarm, False is
    sure).  A light's directions from x lie in a cone: a sphere light's own, an emitter
    triangle's bounding cone (about the direction to its centroid, to its farthest
    corner).  A sphere that is not that light blocks none of them when its own cone is
    apart (angular distance ≥ the sum of the half-angles); a point inside a sphere, or a
    scene triangle whose box meets a sphere light's cube (it could stand between the
    cube and the sphere, where the pyramids end), counts as blocked."""
    x = np.asarray(x, np.float64)
    axes, half, inside = _cones(x, centers, radii)
    blocked = inside.any(axis=1)
    cubes = np.concatenate([centers[lights] - radii[lights, None], centers[lights] + radii[lights, None]], axis=1) \
        if len(lights) else np.zeros((0, 6))
    if len(tris) and len(cubes):
        lo, hi = tris.min(axis=1), tris.max(axis=1)
        meets = ((lo[:, None] <= cubes[None, :, 3:]) & (hi[:, None] >= cubes[None, :, :3])).all(axis=2)
        if meets.any():
            return np.ones(len(x), bool)
    light_axes, light_half = [axes[:, lights]], [half[:, lights]]
    light_index = [lights]
    emitters = np.flatnonzero(np.asarray(emission) > 0)
    if len(emitters):
        t = tris[emitters]
        centroid = t.mean(axis=1)
        to_c = centroid[None] - x[:, None]
        to_c /= np.linalg.norm(to_c, axis=2, keepdims=True)
        to_v = t[None] - x[:, None, None]
        to_v /= np.linalg.norm(to_v, axis=3, keepdims=True)
        spread = np.arccos(np.clip(np.einsum("resj,rej->res", to_v, to_c), -1.0, 1.0)).max(axis=2)
        light_axes.append(to_c)
        light_half.append(spread)
        light_index.append(np.full(len(emitters), -1))
    la, lh = np.concatenate(light_axes, axis=1), np.concatenate(light_half, axis=1)
    li = np.concatenate(light_index)
    apart = np.arccos(np.clip(np.einsum("rlj,rsj->rls", la, axes), -1.0, 1.0))
    overlap = apart < lh[:, :, None] + half[:, None, :]
    overlap &= li[None, :, None] != np.arange(len(radii))[None, None, :]  # a light does not block itself
    return blocked | overlap.any(axis=(1, 2))
