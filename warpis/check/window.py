"""The windowed sphere: a magnification about a lobe's axis, and a quadrature over it.

A narrow lobe (a GGX α = 0.01 conductor, a small light) falls into a cell or two of the
chi-square grid (40 × 80 cells uniform in cos θ and φ), where neither the histogram nor
the quadrature of the expected counts resolves it.  :class:`Window` stretches the sphere
about an axis, θ' = π log(1 + θ/θc) / log(1 + π/θc), keeping φ: a bijection of the
sphere that magnifies angles near the axis by π/(θc log(1 + π/θc)) and shrinks the far
side mildly, so that the lobe and what lies around it both cover many cells.  A density
p on the sphere becomes p/J on the window, J = dω'/dω = (sin θ'/sin θ)·dθ'/dθ; every
integral is unchanged, so the chi-square test, ∫pdf and ∫eval are computed on the window
exactly as on the sphere.  θc is chosen from the samples themselves (their median angle
from their mean direction), so no subject has to say where its lobe is.

:class:`SphereQuadrature` integrates functions over the windowed sphere by jittered
quadrature, one point per stratum of a fine (cos θ', φ') grid, with an estimate of its
variance that errs high (collapsed strata: neighbouring strata paired, the larger of two
pairings kept).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from ..testing import orthonormal_frame

# A lobe whose median angle from its axis is at least this is binned on the plain sphere:
# the grid resolves it (a cosine lobe's median is π/4).
PLAIN_MEDIAN = 0.4
# θc is never below this: float32 directions resolve ~1e-7 rad, a lobe of α = 1e-4 ~1e-4.
MIN_THETA_C = 1e-5
# A cap's window reaches θ' = 0.9π: 95 % of the grid's rows in cos θ'.
CAP_REACH = 0.9 * math.pi


class Window:
    """The sphere magnified about ``axis`` on the angular scale ``theta_c`` (None: plain).

    With ``span`` < π it is a cap's window: the cap of that angular radius about the axis
    fills the windowed sphere up to θ' = CAP_REACH (not π, where the Jacobian of a cap's
    edge would vanish), for a region that lies in the cap; directions outside it map
    past CAP_REACH, and the cells beyond expect nothing.
    """

    def __init__(self, axis: NDArray, theta_c: float | None, span: float = math.pi) -> None:
        self.frame = np.stack(orthonormal_frame(axis))  # rows b1, b2, axis
        self.axis = self.frame[2]
        self.theta_c = None if theta_c is None else max(float(theta_c), MIN_THETA_C)
        self.span = float(span)
        self.reach = math.pi if self.span >= math.pi else CAP_REACH
        self.log_span = 0.0 if self.theta_c is None else math.log1p(self.span / self.theta_c)

    @classmethod
    def for_samples(cls, dirs: NDArray, normal: NDArray) -> Window:
        """A window suited to unit ``dirs`` (valid samples): about their mean direction
        on the scale of their median angle from it; the plain sphere about ``normal`` for
        a broad lobe (or no samples)."""
        if len(dirs) == 0:
            return cls(normal, None)
        mean = dirs.mean(axis=0)
        length = float(np.linalg.norm(mean))
        if length < 0.5:
            return cls(normal, None)
        axis = mean / length
        median = float(np.median(_angle(dirs, axis)))
        if median >= PLAIN_MEDIAN:
            return cls(axis if np.dot(axis, normal) < 0.9 else normal, None)
        return cls(axis, median)

    @property
    def plain(self) -> bool:
        return self.theta_c is None

    def describe(self) -> str:
        a = np.array2string(self.axis, precision=3, suppress_small=True)
        if self.plain:
            return f"sphere about {a}"
        scope = "sphere" if self.span >= math.pi else f"cap of {math.degrees(self.span):.3g}°"
        return f"{scope} magnified about {a}, θc = {self.theta_c:.3g} rad"

    # -- the map ---------------------------------------------------------------------

    def _polar(self, d: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        local = d @ self.frame.T
        rho = np.hypot(local[:, 0], local[:, 1])
        theta = np.arctan2(rho, local[:, 2])
        return local, rho, theta

    def _rebuild(self, local: NDArray, rho: NDArray, theta: NDArray) -> NDArray:
        """World directions with the azimuth of ``local`` and polar angle ``theta``."""
        safe = np.where(rho > 0.0, rho, 1.0)
        cx = np.where(rho > 0.0, local[:, 0] / safe, 1.0)
        cy = np.where(rho > 0.0, local[:, 1] / safe, 0.0)
        s = np.sin(theta)
        out = np.stack([s * cx, s * cy, np.cos(theta)], axis=1)
        return out @ self.frame

    def _jacobian(self, theta: NDArray, theta_w: NDArray) -> NDArray:
        """dω'/dω at polar angle θ (θ' its image)."""
        assert self.theta_c is not None
        dtheta = self.reach / (self.log_span * (self.theta_c + theta))
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(theta > 1e-12, np.sin(theta_w) / np.sin(theta), dtheta)
        # At the antipode both sines vanish: the limit of the ratio is dθ'/dθ there too.
        ratio = np.where(np.minimum(math.pi - theta, math.pi - theta_w) > 1e-9, ratio, dtheta)
        return ratio * dtheta

    def forward(self, d: NDArray) -> tuple[NDArray, NDArray]:
        """Windowed directions of unit ``d`` and the Jacobian dω'/dω at each."""
        if self.plain:
            return d, np.ones(len(d))
        local, rho, theta = self._polar(d)
        theta_w = np.minimum(self.reach * np.log1p(theta / self.theta_c) / self.log_span, math.pi)
        return self._rebuild(local, rho, theta_w), self._jacobian(theta, theta_w)

    def inverse(self, d_w: NDArray) -> tuple[NDArray, NDArray]:
        """Sphere directions of windowed unit ``d_w`` and the Jacobian dω'/dω there."""
        if self.plain:
            return d_w, np.ones(len(d_w))
        local, rho, theta_w = self._polar(d_w)
        theta = self.theta_c * np.expm1(np.minimum(theta_w, self.reach) * self.log_span / self.reach)
        theta = np.minimum(theta, self.span)
        jac = self._jacobian(theta, theta_w)
        # Past a cap window's reach lies no direction: an infinite Jacobian, density 0.
        return self._rebuild(local, rho, theta), np.where(theta_w <= self.reach, jac, np.inf)

    def grid_directions(self, cos_t: NDArray, phi: NDArray) -> NDArray:
        """Windowed unit directions for (cos θ', φ') about the axis."""
        s = np.sqrt(np.maximum(0.0, 1.0 - cos_t * cos_t))
        local = np.stack([s * np.cos(phi), s * np.sin(phi), cos_t], axis=1)
        return local @ self.frame

    def wrap_pdf(self, pdf: Callable[[NDArray], NDArray]) -> Callable[[NDArray], NDArray]:
        """The windowed density of ``pdf``: p(inverse(d'))/J."""
        def windowed(d_w: NDArray) -> NDArray:
            d, jac = self.inverse(d_w)
            return np.asarray(pdf(d), dtype=np.float64) / jac
        return windowed


def _angle(dirs: NDArray, axis: NDArray) -> NDArray:
    """Angles of unit ``dirs`` from unit ``axis``, accurate near 0 and π."""
    return np.arctan2(np.linalg.norm(np.cross(dirs, axis), axis=1), dirs @ axis)


class SphereQuadrature:
    """Jittered quadrature over the windowed sphere: one point per stratum of a
    ``rows`` × ``cols`` grid uniform in (cos θ', φ'), all strata of equal solid angle,
    refined where the integrand is rough.

    :meth:`integrate` evaluates a function at a pilot set of points (sphere directions;
    each point's weight is its stratum's solid angle over J) and estimates the variance of
    each 2 × 2 block of strata by collapsed strata (pairs along φ or along cos θ, the
    larger: an estimate that errs high), to find the roughest blocks: those an edge of the
    integrand crosses (a light's silhouette, a horizon), and their neighbours.  It then
    integrates afresh, independently of the pilot: the rough blocks with REFINE × REFINE
    points per stratum (their variance falls by about REFINE³; estimated by collapsed
    strata again), the others with one (their variance estimated by each block's
    interaction term, exact for a linear integrand).  (Keeping the pilot's values of the
    blocks it found smooth would be biased: an edge block whose four points all fell on
    one side looks smooth.)
    """

    REFINE = 8
    # Blocks refined: those holding REFINED_SHARE of the estimated variance and their
    # neighbours, at most REFINED_FRACTION of the blocks (4 × 64 points each: 8× the
    # pilot's points at most).
    REFINED_SHARE = 0.99
    REFINED_FRACTION = 1.0 / 8.0

    def __init__(self, window: Window, rows: int, cols: int, rng: np.random.Generator) -> None:
        self.window, self.rng = window, rng
        self.rows, self.cols = int(rows) - int(rows) % 2, int(cols) - int(cols) % 2
        self.dc, self.dphi = 2.0 / self.rows, 2.0 * math.pi / self.cols
        self.max_refined = max(1, int(self.REFINED_FRACTION * (self.rows // 2) * (self.cols // 2)))
        self._i = np.repeat(np.arange(self.rows), self.cols)
        self._j = np.tile(np.arange(self.cols), self.rows)
        self.directions, self.weights = self._jittered()

    def _jittered(self) -> tuple[NDArray, NDArray]:
        """One jittered point per stratum: directions and weights."""
        return self._points(self._i + self.rng.random(self._i.size), self._j + self.rng.random(self._j.size), 1)

    def _points(self, ci: NDArray, cj: NDArray, per: int) -> tuple[NDArray, NDArray]:
        """Sphere directions and solid-angle weights of grid coordinates (in strata units)."""
        d_w = self.window.grid_directions(-1.0 + ci * self.dc, cj * self.dphi)
        d, jac = self.window.inverse(d_w)
        return d, (self.dc * self.dphi / (per * per)) / jac

    @staticmethod
    def _block_variance(y: NDArray) -> NDArray:
        """(B,) collapsed-strata variance of blocks y (B, 2m, 2m, C): the larger of the
        pairings along either axis, summed over channels."""
        by_phi = np.sum((y[:, :, 0::2] - y[:, :, 1::2]) ** 2, axis=(1, 2))
        by_cos = np.sum((y[:, 0::2] - y[:, 1::2]) ** 2, axis=(1, 2))
        return np.maximum(by_phi, by_cos)  # (B, C)

    def integrate(self, func: Callable[[NDArray], NDArray]) -> tuple[NDArray, NDArray]:
        """(∫ g dω, its standard error) for g = ``func`` (directions (P, 3) → (P,) or
        (P, C)); arrays of shape (C,), or scalars for a (P,) g."""
        pilot, scalar = self._blocks(func, self.directions, self.weights)
        rough = self._rough(self._block_variance(pilot))
        blocks, _ = self._blocks(func, *self._jittered())
        channels = blocks.shape[-1]
        sums = blocks.sum(axis=(1, 2))
        # A block the pilot found smooth: the square of its interaction term
        # y00 − y01 − y10 + y11, which a linear integrand leaves with exactly the variance
        # of the block's sum (the jitter's), where pair differences would add the gradient.
        var = (blocks[:, 0, 0] - blocks[:, 0, 1] - blocks[:, 1, 0] + blocks[:, 1, 1]) ** 2
        if rough.size:
            fine, fine_var = self._refine(func, rough, channels)
            sums[rough], var[rough] = fine, fine_var
        total, stderr = sums.sum(axis=0), np.sqrt(var.sum(axis=0))
        return (total[0], stderr[0]) if scalar else (total, stderr)

    def _blocks(self, func: Callable[[NDArray], NDArray], d: NDArray, w: NDArray) -> tuple[NDArray, bool]:
        """The weighted values g·w at one point per stratum as 2 × 2 blocks (B, 2, 2, C),
        and whether g is scalar."""
        raw = np.asarray(func(d), dtype=np.float64)
        y = (raw.reshape(len(raw), -1).T * w).T
        br, bc = self.rows // 2, self.cols // 2
        channels = y.shape[1]
        return y.reshape(br, 2, bc, 2, channels).transpose(0, 2, 1, 3, 4).reshape(br * bc, 2, 2, channels), \
            raw.ndim == 1

    def _rough(self, var: NDArray) -> NDArray:
        """The blocks to refine: the fewest holding REFINED_SHARE of the variance."""
        score = var.sum(axis=1)
        total = float(score.sum())
        if not total > 0.0:
            return np.zeros(0, dtype=np.int64)
        order = np.argsort(-score, kind="stable")
        need = int(np.searchsorted(np.cumsum(score[order]), self.REFINED_SHARE * total)) + 1
        core = order[:min(need, self.max_refined, len(order))]
        # With their neighbours: an edge runs on from the blocks where the pilot saw it
        # into those whose four points it happened to miss.
        br, bc = self.rows // 2, self.cols // 2
        mask = np.zeros((br, bc), dtype=bool)
        mask.flat[core] = True
        grown = mask.copy()
        for di in (-1, 0, 1):
            shifted = np.zeros_like(mask)
            lo, hi = max(di, 0), br + min(di, 0)
            shifted[lo:hi] = mask[lo - di:hi - di]
            for dj in (-1, 0, 1):
                grown |= np.roll(shifted, dj, axis=1)  # φ is periodic
        extra = np.flatnonzero(grown & ~mask)
        extra = extra[np.argsort(-score[extra], kind="stable")][:max(0, self.max_refined - core.size)]
        return np.concatenate([core, extra])

    def _refine(self, func: Callable[[NDArray], NDArray], blocks: NDArray, channels: int) -> tuple[NDArray, NDArray]:
        """The sums and variances of ``blocks`` (flat indices) with REFINE² points per stratum."""
        k = self.REFINE
        side = 2 * k  # sub-strata per block side
        bc = self.cols // 2
        bi, bj = (blocks // bc)[:, None], (blocks % bc)[:, None]
        sub = np.arange(side * side)
        si, sj = (sub // side)[None, :], (sub % side)[None, :]
        ci = 2 * bi + (si + self.rng.random((len(blocks), sub.size))) / k
        cj = 2 * bj + (sj + self.rng.random((len(blocks), sub.size))) / k
        d, w = self._points(ci.ravel(), cj.ravel(), k)
        raw = np.asarray(func(d), dtype=np.float64).reshape(len(d), -1)
        y = (raw.T * w).T.reshape(len(blocks), side, side, channels)
        return y.sum(axis=(1, 2)), self._block_variance(y)


# --------------------------------------------------------------------------- regions

# Where a frame's samples fall apart into separate clusters (several lights), each cluster
# gets a window of its own: a cap about it, magnified on its own scale.  Clusters are
# found on the first REGION_SAMPLES samples (the same whatever the budget, so that a run
# can count its tests before it draws them all): occupied cells of a REGION_GRID grid
# about the normal, grown by one cell (so that a sparse lobe stays one cluster) and
# joined where they touch.
REGION_SAMPLES = 20_000
REGION_GRID = (48, 96)
MIN_REGION_SHARE = 0.01  # a smaller cluster is left to the rest of the sphere
MAX_WINDOWS = 4
MAX_CAP = 1.0  # rad: a cluster wider than this is broad, binned on the plain sphere with the rest
CAP_MARGIN = 1.2  # a cap holds its cluster with this factor on its largest angle, plus 0.01 rad


class Region:
    """A part of the sphere and the window its chi-square test and integrals use: inside
    ``cap`` and outside the caps ``before`` it, or (``cap`` None) outside all of them.
    With no caps at all it is the whole sphere."""

    def __init__(self, window: Window, cap: tuple[NDArray, float] | None,
                 before: list[tuple[NDArray, float]]) -> None:
        self.window, self.cap, self.before = window, cap, before

    @property
    def whole(self) -> bool:
        return self.cap is None and not self.before

    def contains(self, d: NDArray) -> NDArray:
        inside = np.ones(len(d), dtype=bool)
        if self.cap is not None:
            inside &= d @ self.cap[0] >= self.cap[1]
        for axis, cos_max in self.before:
            inside &= d @ axis < cos_max
        return inside

    def restrict(self, f: Callable[[NDArray], NDArray]) -> Callable[[NDArray], NDArray]:
        """``f`` where the region is, 0 elsewhere (rows of any trailing shape)."""
        if self.whole:
            return f

        def restricted(d: NDArray) -> NDArray:
            value = np.asarray(f(d), dtype=np.float64)
            inside = self.contains(d)
            return np.where(inside.reshape((-1,) + (1,) * (value.ndim - 1)), value, 0.0)
        return restricted

    def describe(self) -> str:
        if self.whole:
            return self.window.describe()
        if self.cap is None:
            return f"the rest of the sphere (outside {len(self.before)} cap(s)), {self.window.describe()}"
        return self.window.describe() + (f", without {len(self.before)} narrower cap(s)" if self.before else "")


def sample_regions(dirs: NDArray, normal: NDArray) -> list[Region]:
    """The regions of a frame from its first REGION_SAMPLES valid unit directions: the
    whole sphere (one window, :meth:`Window.for_samples`) unless they fall into two or
    more clusters, or a narrow cluster beside a broad spread; then a cap per narrow
    cluster (the narrowest first, each without the caps before it; at most MAX_WINDOWS)
    and the rest of the sphere."""
    sub = dirs[:REGION_SAMPLES]
    if len(sub) == 0:
        return [Region(Window(normal, None), None, [])]
    clusters = _split(sub, np.arange(len(sub)), Window(normal, None), 0)
    if len(clusters) == 1:
        return [Region(Window.for_samples(dirs, normal), None, [])]
    caps: list[tuple[NDArray, float, float]] = []
    for idx in sorted(clusters, key=len, reverse=True):
        if len(idx) < MIN_REGION_SHARE * len(sub) or len(caps) == MAX_WINDOWS:
            break
        cap = _cap(sub[idx])
        if cap is not None:
            caps.append(cap)
    if not caps:
        return [Region(Window.for_samples(dirs, normal), None, [])]
    caps.sort(key=lambda c: -c[1])  # the narrowest first: a small light inside a wide cap keeps its own
    regions = [Region(Window(axis, theta_c, math.acos(cos_max)), (axis, cos_max), [(a, c) for a, c, _ in caps[:k]])
               for k, (axis, cos_max, theta_c) in enumerate(caps)]
    regions.append(Region(Window(normal, None), None, [(a, c) for a, c, _ in caps]))
    return regions


def _cap(cluster: NDArray) -> tuple[NDArray, float, float] | None:
    """(axis, cos of the cap's radius, θc) of a narrow cluster; None for a broad one."""
    mean = cluster.mean(axis=0)
    if np.linalg.norm(mean) < 0.5:
        return None
    axis = mean / np.linalg.norm(mean)
    angles = _angle(cluster, axis)
    radius = min(math.pi, CAP_MARGIN * float(angles.max()) + 0.01)
    if radius > MAX_CAP:
        return None
    return axis, math.cos(radius), max(float(np.median(angles)), MIN_THETA_C)


def _split(sub: NDArray, idx: NDArray, window: Window, depth: int) -> list[NDArray]:
    """The clusters of the directions ``sub[idx]`` as index arrays: the connected parts of
    their cells on a grid of ``window``, each split again on a window magnified about it
    (lights far apart at one scale may be close at another), at most 3 levels deep."""
    parts = _components(sub[idx], window)
    if len(parts) == 1 and depth > 0:
        return [idx]
    out = []
    for part in parts:
        members = idx[part]
        mean = sub[members].mean(axis=0)
        narrow = np.linalg.norm(mean) >= 0.5 and len(members) > 1
        if depth < 3 and narrow:
            axis = mean / np.linalg.norm(mean)
            theta_c = float(np.median(_angle(sub[members], axis)))
            out += _split(sub, members, Window(axis, theta_c), depth + 1)
        else:
            out.append(members)
    return out


def _components(dirs: NDArray, window: Window) -> list[NDArray]:
    """Index arrays of the connected parts of ``dirs``'s occupied cells on a REGION_GRID
    grid of ``window`` (grown by one cell; φ periodic)."""
    from scipy import ndimage

    local = window.forward(dirs)[0] @ window.frame.T
    rows, cols = REGION_GRID
    i = np.clip(((local[:, 2] + 1.0) * 0.5 * rows).astype(int), 0, rows - 1)
    j = (np.mod(np.arctan2(local[:, 1], local[:, 0]), 2 * math.pi) * cols / (2 * math.pi)).astype(int) % cols
    occupied = np.zeros((rows, cols), dtype=bool)
    occupied[i, j] = True
    grown = ndimage.binary_dilation(np.pad(occupied, ((0, 0), (1, 1)), mode="wrap"), structure=np.ones((3, 3)))
    labels, _ = ndimage.label(grown[:, 1:-1], structure=np.ones((3, 3)))
    for r in range(rows):  # φ is periodic: join the labels that meet across the seam
        a, b = labels[r, 0], labels[r, -1]
        if a and b and a != b:
            labels[labels == b] = a
    member = labels[i, j]
    return [np.flatnonzero(member == v) for v in np.unique(member)]
