"""Points on the scene's triangles: the triangle each point lies on (a uniform grid of
cells finds the candidates), and the cell centres of a grid over a planar shape."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ...errors import fail
from .shapes import Shape


def _closest_points(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The closest point to each p on triangle (a, b, c), row by row (Ericson, Real-Time
    Collision Detection, 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        out = a + ab * (vb / denom)[:, None] + ac * (vc / denom)[:, None]
        e_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        out = np.where(((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0))[:, None], b + (c - b) * e_bc[:, None], out)
        e_ac = d2 / (d2 - d6)
        out = np.where(((vb <= 0) & (d2 >= 0) & (d6 <= 0))[:, None], a + ac * e_ac[:, None], out)
        out = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, out)
        e_ab = d1 / (d1 - d3)
        out = np.where(((vc <= 0) & (d1 >= 0) & (d3 <= 0))[:, None], a + ab * e_ab[:, None], out)
        out = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, out)
        out = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, out)
    return out


_PAIRS = 1 << 21  # (point, triangle) pairs held at once


def nearest_distance(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Distance from each point to the nearest of ``tris`` (brute force, for messages)."""
    best = np.full(len(points), np.inf)
    step = max(1, _PAIRS // max(1, len(tris)))
    for s in range(0, len(points), step):
        p = points[s:s + step]
        pi = np.repeat(np.arange(len(p)), len(tris))
        ti = np.tile(np.arange(len(tris)), len(p))
        q = _closest_points(p[pi], tris[ti, 0], tris[ti, 1], tris[ti, 2])
        d = np.linalg.norm(p[pi] - q, axis=1)
        d[~np.isfinite(d)] = np.inf
        np.minimum.at(best[s:s + step], pi, d)
    return best


# Above this many (point, triangle) box tests, candidates come from a uniform grid of
# cells, whose (cell, triangle) entries are kept below _GRID_ENTRIES.
_BRUTE_FORCE = 1 << 23
_GRID_ENTRIES = 1 << 26


def _box_pairs(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every (point, triangle) pair whose box [lo, hi] holds the point."""
    if len(points) * len(lo) <= _BRUTE_FORCE:
        step = max(1, _PAIRS // max(1, len(lo)))
        found = [np.nonzero(((points[s:s + step, None, :] >= lo[None]) & (points[s:s + step, None, :] <= hi[None]))
                            .all(axis=2)) for s in range(0, len(points), step)]
        return (np.concatenate([pi + k * step for k, (pi, _) in enumerate(found)]),
                np.concatenate([ti for _, ti in found]))
    # A uniform grid: each box is listed in every cell it overlaps, each point looks up its cell.
    origin = lo.min(axis=0)
    extent = float((hi.max(axis=0) - origin).max())
    cell = max(float(np.median((hi - lo).max(axis=1))), extent / 256, extent * 1e-9, 1e-300)
    while True:
        shape = np.floor((hi.max(axis=0) - origin) / cell).astype(np.int64) + 1
        c_lo = np.floor((lo - origin) / cell).astype(np.int64)
        c_hi = np.floor((hi - origin) / cell).astype(np.int64)
        dims = c_hi - c_lo + 1
        counts = dims.prod(axis=1)
        if counts.sum() <= _GRID_ENTRIES:
            break
        cell *= 2.0
    total = int(counts.sum())
    tri = np.repeat(np.arange(len(lo)), counts)
    local = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    ix = c_lo[tri, 0] + local % dims[tri, 0]
    iy = c_lo[tri, 1] + (local // dims[tri, 0]) % dims[tri, 1]
    iz = c_lo[tri, 2] + local // (dims[tri, 0] * dims[tri, 1])
    keys = (ix * shape[1] + iy) * shape[2] + iz
    order = np.argsort(keys, kind="stable")
    keys, tri = keys[order], tri[order]
    c = np.floor((points - origin) / cell).astype(np.int64)
    outside = ((c < 0) | (c >= shape)).any(axis=1)
    c = np.clip(c, 0, shape - 1)
    point_keys = (c[:, 0] * shape[1] + c[:, 1]) * shape[2] + c[:, 2]
    left = np.searchsorted(keys, point_keys, side="left")
    right = np.searchsorted(keys, point_keys, side="right")
    length = np.where(outside, 0, right - left)
    pi = np.repeat(np.arange(len(points)), length)
    ti = tri[np.repeat(left, length) + np.arange(int(length.sum())) - np.repeat(np.cumsum(length) - length, length)]
    keep = ((points[pi] >= lo[ti]) & (points[pi] <= hi[ti])).all(axis=1)
    return pi[keep], ti[keep]


def locate(points: np.ndarray, tris: np.ndarray, tol: np.ndarray, slack: float, rank: Any
            ) -> tuple[np.ndarray, np.ndarray]:
    """The triangle each point lies on (within its ``tol``) and the closest point on it;
    -1 where none.  Among triangles within ``slack`` of the nearest, the lowest ``rank``
    (point index array, triangle index array → sort keys, most important last) wins."""
    index = np.full(len(points), -1, np.int64)
    closest = points.copy()
    candidates_p, candidates_t = _box_pairs(points, tris.min(axis=1) - tol[:, None], tris.max(axis=1) + tol[:, None])
    found_p, found_t, found_d, found_q = [], [], [], []
    for u in range(0, len(candidates_p), _PAIRS):
        a, t = candidates_p[u:u + _PAIRS], candidates_t[u:u + _PAIRS]
        q = _closest_points(points[a], tris[t, 0], tris[t, 1], tris[t, 2])
        d = np.linalg.norm(points[a] - q, axis=1)
        ok = np.isfinite(d) & (d <= tol[t])
        found_p.append(a[ok])
        found_t.append(t[ok])
        found_d.append(d[ok])
        found_q.append(q[ok])
    if not found_p:
        return index, closest
    pi, ti, d, q = (np.concatenate(x) for x in (found_p, found_t, found_d, found_q))
    if not len(pi):
        return index, closest
    best = np.full(len(points), np.inf)
    np.minimum.at(best, pi, d)
    near = d <= best[pi] + slack
    pi, ti, q = pi[near], ti[near], q[near]
    order = np.lexsort((ti, *rank(pi, ti), pi))
    pi, ti, q = pi[order], ti[order], q[order]
    first = np.flatnonzero(np.r_[True, pi[1:] != pi[:-1]])
    index[pi[first]] = ti[first]
    closest[pi[first]] = q[first]
    return index, closest


# ----------------------------------------------------------------------------- grids over planar shapes


def _turn(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """z of (a − o) × (b − o): > 0 when o → a → b turns counter-clockwise."""
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def _hull(points: np.ndarray) -> np.ndarray:
    """Convex hull of 2D points, counter-clockwise (Andrew's monotone chain)."""
    pts = np.unique(points, axis=0)
    if len(pts) < 3:
        return pts

    def half(seq: np.ndarray) -> list[np.ndarray]:
        out: list[np.ndarray] = []
        for p in seq:
            while len(out) >= 2 and _turn(out[-2], out[-1], p) <= 0:
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1])


def planar_grid(group: dict[str, Any], shapes: list[Shape], base: float, sidecar: Path, file: Path
          ) -> tuple[np.ndarray, int, np.ndarray, tuple[int, int]]:
    """Cell centres of a grid over a planar shape's minimum-area bounding rectangle: the
    points, the shape's index, its front normal and the grid's (rows, cols)."""
    where = group["where"]
    sid, nu, nv = group["grid"]
    matches = [i for i, s in enumerate(shapes) if s.id == sid]
    if not matches:
        ids = ", ".join(repr(s.id) for s in shapes if s.id) or "none"
        raise fail(sidecar, f"{where}: grid shape {sid!r}: no shape with that id in {file.name} (ids: {ids})")
    index = matches[0]
    s = shapes[index]
    if s.sphere is not None:
        raise fail(sidecar, f"{where}: grid: shape {sid!r} is not planar (an analytic sphere); a grid needs a planar "
                            f"shape: list points instead")
    tris = s.vertices[s.faces]
    cross = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    areas = np.linalg.norm(cross, axis=1)
    total = cross.sum(axis=0)
    if not np.linalg.norm(total) > 0:
        raise fail(sidecar, f"{where}: grid: shape {sid!r} has no area facing one side (a grid needs a planar shape)")
    n = total / np.linalg.norm(total)
    used = s.vertices[np.unique(s.faces)]
    centre = used.mean(axis=0)
    off_plane = float(np.abs((used - centre) @ n).max())
    good = areas > 0
    folded = bool(np.any(np.einsum("fj,j->f", cross[good] / areas[good, None], n) < 1 - 1e-6))
    if off_plane > base + s.deviation or folded:
        raise fail(sidecar, f"{where}: grid: shape {sid!r} is not planar (its vertices stray up to {off_plane:.3g} "
                            f"from its mean plane{', and its faces face different ways' if folded else ''}); a grid "
                            f"needs a planar shape: list points instead")
    e1 = np.cross(n, [1.0, 0.0, 0.0])
    if np.linalg.norm(e1) < 0.5:
        e1 = np.cross(n, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    flat = np.stack([(used - centre) @ e1, (used - centre) @ e2], axis=1)
    hull = _hull(flat)
    best = None
    for i in range(len(hull)):
        edge = hull[(i + 1) % len(hull)] - hull[i]
        if not np.linalg.norm(edge) > 0:
            continue
        a = edge / np.linalg.norm(edge)
        b = np.array([-a[1], a[0]])
        pa, pb = hull @ a, hull @ b
        area = (pa.max() - pa.min()) * (pb.max() - pb.min())
        if best is None or area < best[0] * (1 - 1e-12):
            best = (area, a, b, (pa.min(), pa.max()), (pb.min(), pb.max()))
    if best is None:
        raise fail(sidecar, f"{where}: grid: shape {sid!r} has no area")
    _, a, b, (a0, a1), (b0, b1) = best
    sides = [(a1 - a0, a[0] * e1 + a[1] * e2), (b1 - b0, b[0] * e1 + b[1] * e2)]
    longest = max(length for length, _ in sides)
    candidates = [d / np.linalg.norm(d) for length, d in sides if length >= longest * (1 - 1e-9)]
    # u along the longer side, pointing where its largest component is positive; for a
    # square, the side closest to the x axis (then y).
    candidates = [d if d[np.argmax(np.abs(d))] > 0 else -d for d in candidates]
    u = max(candidates, key=lambda d: tuple(np.round(np.abs(d), 9)))
    v = np.cross(n, u)
    rel = flat @ np.array([u @ e1, u @ e2]), flat @ np.array([v @ e1, v @ e2])
    lu, lv = rel[0].max() - rel[0].min(), rel[1].max() - rel[1].min()
    origin = centre + rel[0].min() * u + rel[1].min() * v
    su = (np.arange(nu) + 0.5) / nu
    sv = (np.arange(nv) + 0.5) / nv
    points = origin + sv[:, None, None] * lv * v + su[None, :, None] * lu * u
    return points.reshape(-1, 3), index, n, (nv, nu)
