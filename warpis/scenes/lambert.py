"""Lambert's contour formula: the exact, occlusion-free irradiance from uniform polygons.

``E(x) = (1/2π) Σ_edges θ_ij · n·(r_i × r_j)/|r_i × r_j|`` over the part of each polygon
above the horizon of ``x`` (clipped to ``n·(y − x) > 0``); triangles emit from their front
face only.  Pure numpy in float64, so scene sources (a tessellation's irradiance error)
and the analysis (closed-form references, ``analysis/closed_form.py``) share one
implementation.  Derivation: docs/theory.md, "Irradiance from a uniform polygonal emitter".

Array conventions: receivers ``x`` and normals ``n`` are ``(R, 3)``, triangles are
``(T, 3, 3)`` (triangle, vertex, coordinate), per-triangle radiance is ``(T,)``.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

# Upper bound on the number of (receiver, triangle) pairs held in memory at once by
# triangle_irradiance (a few tens of MB per temporary).
PAIR_CHUNK = 1 << 16

# --------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------


def as_points(a: np.ndarray, name: str) -> np.ndarray:
    """``a`` as a float64 array of shape ``(R, 3)`` (a single point becomes ``(1, 3)``)."""
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim == 1:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (3,) or (R, 3), got {np.shape(a)}")
    return arr


def unit_rows(v: np.ndarray, name: str) -> np.ndarray:
    """Rows of ``v`` scaled to unit length; a zero row is an error."""
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    if np.any(norm == 0.0) or not np.all(np.isfinite(norm)):
        raise ValueError(f"{name} must be finite and non-zero")
    return v / norm


def as_triangles(tris: np.ndarray) -> np.ndarray:
    """``tris`` as a float64 array of shape ``(T, 3, 3)``."""
    arr = np.asarray(tris, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (3, 3):
        raise ValueError(f"triangles must have shape (T, 3, 3), got {np.shape(tris)}")
    return arr


def normalize_or_zero(v: np.ndarray, scale: np.ndarray | float = 1.0,
                       rel: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors along the last axis and a validity mask.

    A vector is valid when its length exceeds ``rel * scale`` (``scale`` broadcast
    against the vector's leading shape); invalid vectors come back as zeros.
    """
    norm = np.linalg.norm(v, axis=-1)
    valid = norm > rel * np.asarray(scale, dtype=np.float64)
    safe = np.where(valid, norm, 1.0)
    return np.where(valid[..., None], v / safe[..., None], 0.0), valid


def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot product over the last axis (length 3), broadcasting the others.

    Written out rather than as a matrix product: with an inner dimension of 3, BLAS
    gains nothing and its threads only add start-up and contention costs.
    """
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def chunks(count: int, size: int) -> Iterator[slice]:
    """Consecutive slices of at most ``size`` items covering ``range(count)``."""
    size = max(1, int(size))
    for start in range(0, count, size):
        yield slice(start, min(count, start + size))


# --------------------------------------------------------------------------------------
# clipping
# --------------------------------------------------------------------------------------


def clip_batch(polys: np.ndarray, x: np.ndarray, n: np.ndarray,
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
    clipped, count = clip_batch(p[None], xa, na, eps)
    return clipped[0, : int(count[0])].copy()


# --------------------------------------------------------------------------------------
# Lambert's formula
# --------------------------------------------------------------------------------------


def lambert_signed(x: np.ndarray, n: np.ndarray, polys: np.ndarray) -> np.ndarray:
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
    xa = as_points(x, "x")
    na = unit_rows(as_points(n, "n"), "n")
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
    signed = lambert_signed(xa, na, np.broadcast_to(p, (r,) + p.shape))
    out = np.where(front, np.maximum(-signed, 0.0), 0.0)
    return float(out[0]) if single else out


def front_facing(x: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """``(R, T)`` mask: triangle ``t``'s front face (``(v1−v0)×(v2−v0)`` side) sees ``x_r``."""
    normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    offset = np.einsum("tc,tc->t", normal, tris[:, 0])
    return dot(x[:, None, :], normal[None, :, :]) - offset[None, :] > 0.0


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
    xa = as_points(x, "x")
    na = unit_rows(as_points(n, "n"), "n")
    if xa.shape != na.shape:
        raise ValueError(f"x and n must have the same shape, got {xa.shape} and {na.shape}")
    t_all = as_triangles(tris)
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
    r_block = min(r, PAIR_CHUNK)
    t_block = max(1, PAIR_CHUNK // r_block)
    for rb in chunks(r, r_block):
        xb, nb = xa[rb], na[rb]
        for tb in chunks(emit.size, t_block):
            ri, ti = np.nonzero(front_facing(xb, t_e[tb]))
            if ri.size == 0:
                continue
            polys, count = clip_batch(t_e[tb][ti], xb[ri], nb[ri])
            polys = polys[:, :4]  # a clipped triangle has at most 4 vertices
            keep = count >= 3
            if not np.any(keep):
                continue
            ri, ti, polys = ri[keep], ti[keep], polys[keep]
            e = np.maximum(-lambert_signed(xb[ri], nb[ri], polys), 0.0)
            np.add.at(out, ri + rb.start, le[tb][ti] * e)
    return out


# --------------------------------------------------------------------------------------
# sphere lights
# --------------------------------------------------------------------------------------

# Gauss–Legendre nodes per smooth piece of the cone integral below (each piece has a
# square-root kink at one end: 256 nodes leave a relative error below 1e-8).
SPHERE_NODES = 256


def _ring_cosine(u: np.ndarray, cos_c: np.ndarray, sin_c: np.ndarray) -> np.ndarray:
    """∫₀^{2π} max(0, n·ω) dφ over the ring of directions at angle θ' (cos θ' = u) from an
    axis at angle θc from n: with a = u cos θc, b = sin θ' sin θc ≥ 0, the ring's
    cosine is a + b cos φ, positive for |φ| < φ0 = arccos(−a/b)."""
    a = u * cos_c
    b = np.sqrt(np.maximum(1.0 - u * u, 0.0)) * sin_c
    with np.errstate(invalid="ignore", divide="ignore"):
        phi0 = np.arccos(np.clip(-a / b, -1.0, 1.0))
    partial = 2.0 * (a * phi0 + b * np.sin(phi0))
    return np.where(a >= b, 2.0 * np.pi * a, np.where(a <= -b, 0.0, partial))


def sphere_irradiance(x: np.ndarray, n: np.ndarray, centers: np.ndarray, radii: np.ndarray,
                      radiance: np.ndarray, inward: np.ndarray) -> np.ndarray:
    """(R,) occlusion-free irradiance at points ``x`` of normals ``n`` from uniform sphere
    lights (``centers`` (S, 3), ``radii``, ``radiance``; ``inward`` 1 where a sphere emits
    on its inside).  From outside an outward sphere it is L ∫_cone max(0, n·ω) dω, whose
    rings have a closed form (``_ring_cosine``) and whose integral over cos θ' is
    Gauss–Legendre, split where the cone crosses the horizon (u = sin θc): π L sin²α cos θc
    when the cone is wholly above it.  From inside an inward sphere it is π L; otherwise 0."""
    x = as_points(x, "x")
    n = unit_rows(as_points(n, "n"), "n")
    nodes, weights = np.polynomial.legendre.leggauss(SPHERE_NODES)
    out = np.zeros(len(x))
    for c, r, le, flip in zip(np.asarray(centers, np.float64).reshape(-1, 3), np.ravel(radii), np.ravel(radiance),
                              np.ravel(inward)):
        d = c - x
        dist = np.linalg.norm(d, axis=1)
        inside = dist <= r
        if flip:
            out += np.where(inside, np.pi * le, 0.0)
            continue
        dist = np.where(inside, 2.0 * r, dist)  # unused rows: any point outside
        cos_c = np.clip(np.einsum("ij,ij->i", d, n) / dist, -1.0, 1.0)
        sin_c = np.sqrt(np.maximum(1.0 - cos_c**2, 0.0))
        cos_a = np.sqrt(np.maximum((dist - r) * (dist + r), 0.0)) / dist
        kink = np.clip(sin_c, cos_a, 1.0)
        total = np.zeros(len(x))
        for lo, hi in ((cos_a, kink), (kink, np.ones_like(kink))):
            u = 0.5 * (hi - lo)[:, None] * nodes[None] + 0.5 * (hi + lo)[:, None]
            total += 0.5 * (hi - lo) * (_ring_cosine(u, cos_c[:, None], sin_c[:, None]) @ weights)
        out += np.where(inside, 0.0, le * total)
    return out
