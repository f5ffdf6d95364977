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

from collections.abc import Iterator

import numpy as np

__all__ = [
    "clip_polygon_to_halfspace",
    "polygon_irradiance",
    "triangle_irradiance",
    "pyramid_blockers",
    "irradiance_closed_form",
]

# Upper bound on the number of (receiver, triangle) pairs held in memory at once by
# triangle_irradiance (a few tens of MB per temporary).
_PAIR_CHUNK = 1 << 16
# (pyramid, triangle) pairs per separating-axis batch; small enough that the search
# stops soon after the first blocker.
_SAT_CHUNK = 1 << 13
# Pyramids per bounding-cone cluster in pyramid_blockers.
_CLUSTER = 32
# Angular slack (radians) added to bounding cones, above arccos round-off.
_ANGLE_SLACK = 1e-6
# Relative tolerance of pyramid_blockers when ``tol`` is not given: a fraction of the
# diagonal of the bounding box of the scene and the receivers.
_DEFAULT_REL_TOL = 1e-6


# --------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------


def _as_points(a: np.ndarray, name: str) -> np.ndarray:
    """``a`` as a float64 array of shape ``(R, 3)`` (a single point becomes ``(1, 3)``)."""
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim == 1:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (3,) or (R, 3), got {np.shape(a)}")
    return arr


def _unit_rows(v: np.ndarray, name: str) -> np.ndarray:
    """Rows of ``v`` scaled to unit length; a zero row is an error."""
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    if np.any(norm == 0.0) or not np.all(np.isfinite(norm)):
        raise ValueError(f"{name} must be finite and non-zero")
    return v / norm


def _as_triangles(tris: np.ndarray) -> np.ndarray:
    """``tris`` as a float64 array of shape ``(T, 3, 3)``."""
    arr = np.asarray(tris, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (3, 3):
        raise ValueError(f"triangles must have shape (T, 3, 3), got {np.shape(tris)}")
    return arr


def _normalize_or_zero(v: np.ndarray, scale: np.ndarray | float = 1.0,
                       rel: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors along the last axis and a validity mask.

    A vector is valid when its length exceeds ``rel * scale`` (``scale`` broadcast
    against the vector's leading shape); invalid vectors come back as zeros.
    """
    norm = np.linalg.norm(v, axis=-1)
    valid = norm > rel * np.asarray(scale, dtype=np.float64)
    safe = np.where(valid, norm, 1.0)
    return np.where(valid[..., None], v / safe[..., None], 0.0), valid


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot product over the last axis (length 3), broadcasting the others.

    Written out rather than as a matrix product: with an inner dimension of 3, BLAS
    gains nothing and its threads only add start-up and contention costs.
    """
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _chunks(count: int, size: int) -> Iterator[slice]:
    """Consecutive slices of at most ``size`` items covering ``range(count)``."""
    size = max(1, int(size))
    for start in range(0, count, size):
        yield slice(start, min(count, start + size))


# --------------------------------------------------------------------------------------
# clipping
# --------------------------------------------------------------------------------------


def _clip_batch(polys: np.ndarray, x: np.ndarray, n: np.ndarray,
                eps: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Sutherland–Hodgman clip of many polygons, each against its own half-space.

    Parameters
    ----------
    polys : ndarray, shape (M, K, 3)
        Polygons with ``K`` vertices each.
    x, n : ndarray, shape (M, 3)
        Point on and normal of each clipping plane; the kept side is
        ``{y : n·(y − x) > eps}``.
    eps : float
        Offset of the plane along ``n`` (in units of ``|n|``).

    Returns
    -------
    clipped : ndarray, shape (M, 2K, 3)
        Clipped polygons, vertices in the original winding order, padded by repeating
        the last vertex (zero-length edges); an empty result repeats ``polys[m, 0]``.
    count : ndarray of int, shape (M,)
        Number of genuine vertices of each clipped polygon (0 when nothing is kept).
    """
    m, k = polys.shape[:2]
    d = np.einsum("mkc,mc->mk", polys - x[:, None, :], n) - eps
    inside = d > 0.0
    nxt = np.roll(np.arange(k), -1)
    d_next = d[:, nxt]
    in_next = inside[:, nxt]
    crossing = inside != in_next
    denom = np.where(crossing, d - d_next, 1.0)
    t = np.where(crossing, d / denom, 0.0)
    p_next = polys[:, nxt, :]
    cut = polys + t[..., None] * (p_next - polys)
    # Slot 2i: vertex i when inside; slot 2i+1: the crossing on edge (i, i+1).
    slots = np.stack([polys, cut], axis=2).reshape(m, 2 * k, 3)
    valid = np.stack([inside, crossing], axis=2).reshape(m, 2 * k)
    order = np.argsort(~valid, axis=1, kind="stable")
    count = valid.sum(axis=1)
    last = np.maximum(count - 1, 0)
    take = np.minimum(np.arange(2 * k)[None, :], last[:, None])
    gathered = np.take_along_axis(slots, order[..., None], axis=1)
    clipped = np.take_along_axis(gathered, take[..., None], axis=1)
    empty = count == 0
    if np.any(empty):
        clipped[empty] = polys[empty, :1, :]
    return clipped, count


def clip_polygon_to_halfspace(poly: np.ndarray, x: np.ndarray, n: np.ndarray,
                              eps: float = 0.0) -> np.ndarray:
    """Clip a planar polygon to the open half-space ``{y : n·(y − x) > eps}``.

    Sutherland–Hodgman with a single clipping plane: each edge ``(p_i, p_{i+1})``
    emits ``p_i`` when it is inside and the intersection with the plane when the edge
    crosses it.  The winding of the input is preserved.

    Parameters
    ----------
    poly : array_like, shape (k, 3)
        Vertices of a planar polygon, in order.
    x : array_like, shape (3,)
        A point on the clipping plane.
    n : array_like, shape (3,)
        Normal of the clipping plane, pointing to the kept side (need not be unit;
        ``eps`` is measured in units of ``|n|``).
    eps : float, default 0.0
        Offset of the plane along ``n``.

    Returns
    -------
    ndarray, shape (j, 3)
        The clipped polygon; ``j = 0`` when no vertex lies strictly inside.  Vertices
        exactly on the plane are reproduced as crossings, so the closure of the result
        is the intersection of the polygon with the closed half-space.
    """
    p = np.asarray(poly, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"poly must have shape (k, 3), got {np.shape(poly)}")
    if p.shape[0] == 0:
        return p.copy()
    xa = np.asarray(x, dtype=np.float64).reshape(1, 3)
    na = np.asarray(n, dtype=np.float64).reshape(1, 3)
    clipped, count = _clip_batch(p[None], xa, na, eps)
    return clipped[0, : int(count[0])].copy()


# --------------------------------------------------------------------------------------
# Lambert's formula
# --------------------------------------------------------------------------------------


def _lambert_signed(x: np.ndarray, n: np.ndarray, polys: np.ndarray) -> np.ndarray:
    """``(1/2) Σ_i Θ_i n·Γ_i`` for padded polygons (zero-length edges contribute 0).

    ``Γ_i = (u_i × u_{i+1}) / |u_i × u_{i+1}|`` with ``u_i = v_i − x`` and
    ``Θ_i = atan2(|u_i × u_{i+1}|, u_i·u_{i+1})``.  For a polygon wound
    counter-clockwise as seen from ``x`` (front face towards ``x``) the value is minus
    the projected solid angle ``∫ n·ω dω`` over the polygon.

    Parameters
    ----------
    x, n : ndarray, shape (M, 3)
    polys : ndarray, shape (M, K, 3)

    Returns
    -------
    ndarray, shape (M,)
    """
    u = polys - x[:, None, :]
    u_next = np.roll(u, -1, axis=1)
    c = np.cross(u, u_next)
    s = np.linalg.norm(c, axis=-1)
    dot = np.einsum("mkc,mkc->mk", u, u_next)
    theta = np.arctan2(s, dot)
    ratio = np.divide(theta, s, out=np.zeros_like(theta), where=s > 0.0)
    nc = np.einsum("mkc,mc->mk", c, n)
    return 0.5 * np.sum(ratio * nc, axis=1)


def polygon_irradiance(x: np.ndarray, n: np.ndarray, poly: np.ndarray) -> np.ndarray | float:
    """Irradiance at ``x`` from a unit-radiance, one-sided planar polygon (Lambert).

    ``E = ∫_polygon max(0, n·ω) dω = −(1/2) Σ_i Θ_i n·Γ_i`` for a polygon whose front
    faces ``x``, where edge ``i`` joins ``v_i`` to ``v_{i+1}``, ``u_i = v_i − x``,
    ``Θ_i = atan2(|u_i × u_{i+1}|, u_i·u_{i+1})`` is the angle the edge subtends at
    ``x`` and ``Γ_i = (u_i × u_{i+1}) / |u_i × u_{i+1}|`` the unit normal of the plane
    through ``x`` and the edge.

    The polygon's front is the side its Newell normal ``N = (1/2) Σ v_i × v_{i+1}``
    points to (for a triangle, ``(v1 − v0) × (v2 − v0)`` up to a factor 2).  It faces
    ``x`` when ``N·(x − v0) > 0``; otherwise the one-sided polygon sends nothing to
    ``x`` and the result is exactly 0.

    Parameters
    ----------
    x : array_like, shape (3,) or (R, 3)
        Receiver point(s).
    n : array_like, shape (3,) or (R, 3)
        Receiver normal(s); normalised internally.
    poly : array_like, shape (k, 3)
        Planar polygon, ``k >= 3``.  Precondition: it lies entirely in the closed
        upper half-space ``n·(y − x) >= 0`` of every receiver (clip it first with
        :func:`clip_polygon_to_halfspace`); otherwise the formula returns the signed
        projected solid angle ``∫ n·ω dω``, where the part below the horizon counts
        negatively, and the result is clamped at 0.

    Returns
    -------
    float or ndarray, shape (R,)
        Non-negative irradiance for unit radiance (a float for a single receiver).
    """
    single = np.ndim(x) == 1 and np.ndim(n) == 1
    xa = _as_points(x, "x")
    na = _unit_rows(_as_points(n, "n"), "n")
    xa, na = np.broadcast_arrays(xa, na)
    p = np.asarray(poly, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"poly must have shape (k, 3), got {np.shape(poly)}")
    r = xa.shape[0]
    if p.shape[0] < 3:
        out = np.zeros(r)
        return float(out[0]) if single else out
    newell = 0.5 * np.sum(np.cross(p, np.roll(p, -1, axis=0)), axis=0)
    front = (xa - p[0]) @ newell > 0.0
    signed = _lambert_signed(xa, na, np.broadcast_to(p, (r,) + p.shape))
    out = np.where(front, np.maximum(-signed, 0.0), 0.0)
    return float(out[0]) if single else out


def _front_facing(x: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """``(R, T)`` mask: triangle ``t``'s front face (``(v1−v0)×(v2−v0)`` side) sees ``x_r``."""
    normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    offset = np.einsum("tc,tc->t", normal, tris[:, 0])
    return _dot(x[:, None, :], normal[None, :, :]) - offset[None, :] > 0.0


def triangle_irradiance(x: np.ndarray, n: np.ndarray, tris: np.ndarray,
                        radiance: np.ndarray) -> np.ndarray:
    """Occlusion-free, one-sided irradiance from uniformly emitting triangles.

    ``E(x_r) = Σ_t L_t · [N_t·(x_r − v0_t) > 0] · E_Lambert(x_r, n_r, clip(t))`` where
    ``clip(t)`` is triangle ``t`` clipped to the horizon half-space
    ``n_r·(y − x_r) > 0`` and ``E_Lambert`` is :func:`polygon_irradiance`.  Nothing
    occludes anything: the emitters are summed as if alone in the scene.

    Parameters
    ----------
    x : array_like, shape (R, 3)
        Receiver points.
    n : array_like, shape (R, 3)
        Receiver normals; normalised internally.
    tris : array_like, shape (T, 3, 3)
        Triangles; front face on the side of ``(v1 − v0) × (v2 − v0)``.
    radiance : array_like, shape (T,)
        Radiance of each triangle's front face; triangles with 0 are skipped.

    Returns
    -------
    ndarray, shape (R,)
        Irradiance at each receiver.
    """
    xa = _as_points(x, "x")
    na = _unit_rows(_as_points(n, "n"), "n")
    if xa.shape != na.shape:
        raise ValueError(f"x and n must have the same shape, got {xa.shape} and {na.shape}")
    t_all = _as_triangles(tris)
    le_all = np.asarray(radiance, dtype=np.float64).reshape(-1)
    if le_all.shape[0] != t_all.shape[0]:
        raise ValueError("radiance must have one value per triangle")
    emit = np.nonzero(le_all != 0.0)[0]
    r = xa.shape[0]
    out = np.zeros(r)
    if emit.size == 0 or r == 0:
        return out
    t_e = t_all[emit]
    le = le_all[emit]
    r_block = min(r, _PAIR_CHUNK)
    t_block = max(1, _PAIR_CHUNK // r_block)
    for rb in _chunks(r, r_block):
        xb, nb = xa[rb], na[rb]
        for tb in _chunks(emit.size, t_block):
            ri, ti = np.nonzero(_front_facing(xb, t_e[tb]))
            if ri.size == 0:
                continue
            polys, count = _clip_batch(t_e[tb][ti], xb[ri], nb[ri])
            polys = polys[:, :4]  # a clipped triangle has at most 4 vertices
            keep = count >= 3
            if not np.any(keep):
                continue
            ri, ti, polys = ri[keep], ti[keep], polys[keep]
            e = np.maximum(-_lambert_signed(xb[ri], nb[ri], polys), 0.0)
            np.add.at(out, ri + rb.start, le[tb][ti] * e)
    return out


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
    front = _front_facing(x[None], emitters)[0]
    idx = np.nonzero(front)[0]
    if idx.size == 0:
        return np.zeros((0, 5, 3)), np.zeros(0, dtype=np.int64)
    local = emitters[idx] - x
    zero = np.zeros((idx.size, 3))
    base, count = _clip_batch(local, zero, np.broadcast_to(n, (idx.size, 3)))
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
    return _normalize_or_zero(raw, scale_pow)


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
    return _normalize_or_zero(raw, scale_pow)


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
    axes, valid = _normalize_or_zero(raw, scale)
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
    axis, valid = _normalize_or_zero(unit.sum(axis=1))
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
    cos = np.clip(_dot(axis[:, None, :], c_dir[None, :, :]), -1.0, 1.0)
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
    xa = _as_points(x, "x")
    na = _unit_rows(_as_points(n, "n"), "n")
    if xa.shape != na.shape:
        raise ValueError(f"x and n must have the same shape, got {xa.shape} and {na.shape}")
    t_all = _as_triangles(tris)
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
        tol = _DEFAULT_REL_TOL * float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
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
        h_t = np.max(_dot(t_all - xr, nr), axis=1)
        h_p = float(np.min(_dot(pv, nr)))
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

        for cl in _chunks(pv.shape[0], _CLUSTER):
            g_axis, g_ok = _normalize_or_zero(axis[cl].sum(axis=0)[None])
            spread = np.arccos(np.clip(_dot(axis[cl], g_axis[0]), -1.0, 1.0)) + half[cl]
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
            for part in _chunks(pi.size, _SAT_CHUNK):
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
    t_all = _as_triangles(all_tris)
    le = np.asarray(emission, dtype=np.float64).reshape(-1)
    values = triangle_irradiance(x, n, t_all, le)
    blocked = pyramid_blockers(x, n, t_all, le != 0.0, tol)
    return values, ~blocked
