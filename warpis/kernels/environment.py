"""An environment light on the device: Mitsuba's lookup, and the ``envmap`` technique beside its pdf.

The radiance of a ray that leaves the scene is :func:`environment_radiance`, Mitsuba's
``envmap`` lookup (bilinear between the nodes of its lat-long table; the table and its
layout: :mod:`warpis.scenes.environment`).  The ``envmap`` technique samples the grid's
cells (between node rows j, j + 1 and columns i, i + 1) in proportion to their exact
energy ∫ L dω: a row from the marginal CDF, a column from that row's conditional CDF,
then a direction uniform *in solid angle* within the cell — φ uniform over its
longitudes and cos θ uniform over its latitudes — so that

    pdf(ω) = P(cell) / Ω(cell),   Ω(cell) = Δφ (cos θ_j − cos θ_{j+1}),

bounded everywhere, poles included (docs/theory.md, "Environment lights", derives it and
its sin θ Jacobian).  In the style of pbrt-v4's ``sampling.h``: each map beside its pdf.
"""

from __future__ import annotations

import warp as wp

from .warps import INV_2PI, INV_PI, PI

__all__ = ["EnvironmentData", "environment_pdf", "environment_radiance", "sample_environment"]

TWO_PI = wp.constant(6.28318530717958647692)


@wp.struct
class EnvironmentData:
    """An environment's table and its sampling distribution (``present`` = 0: none)."""

    present: wp.int32
    texels: wp.array2d(dtype=wp.float32)  # (H, W + 1): the texels, column 0 repeated after the last
    to_local: wp.mat33  # Rᵀ: world → the environment's frame
    to_world: wp.mat33  # R
    row_cdf: wp.array(dtype=wp.float64)  # (H,): over the H − 1 cell rows, 0 … 1
    col_cdf: wp.array2d(dtype=wp.float64)  # (H − 1, W + 1): within each cell row, 0 … 1
    total: wp.float64  # ∫ L dω over the sphere; 0: nothing to sample


@wp.func
def _search(cdf: wp.array(dtype=wp.float64), count: wp.int32, x: wp.float64) -> wp.int32:
    """The interval k < count with cdf[k] ≤ x < cdf[k + 1]."""
    lo = wp.int32(0)
    hi = count
    while hi - lo > 1:
        mid = (lo + hi) / 2
        if cdf[mid] <= x:
            lo = mid
        else:
            hi = mid
    return lo


@wp.func
def _search_row(cdf: wp.array2d(dtype=wp.float64), row: wp.int32, count: wp.int32, x: wp.float64) -> wp.int32:
    lo = wp.int32(0)
    hi = count
    while hi - lo > 1:
        mid = (lo + hi) / 2
        if cdf[row, mid] <= x:
            lo = mid
        else:
            hi = mid
    return lo


@wp.func
def environment_uv(env: EnvironmentData, w: wp.vec3) -> wp.vec2:
    """Mitsuba's lat-long coordinates of world direction ω, its half-texel shift applied
    and both wrapped into [0, 1): (u', v) with u' in columns, v in rows of the table."""
    v = env.to_local * w
    columns = float(env.texels.shape[1])
    u = wp.atan2(v[0], -v[2]) * INV_2PI - 0.5 / (columns - 1.0)
    t = wp.acos(wp.clamp(v[1], -1.0, 1.0)) * INV_PI
    return wp.vec2(u - wp.floor(u), t - wp.floor(t))


@wp.func
def environment_radiance(env: EnvironmentData, w: wp.vec3) -> float:
    """The radiance a ray leaving the scene along ω sees: Mitsuba's bilinear lookup."""
    if env.present == 0:
        return 0.0
    height = env.texels.shape[0]
    columns = env.texels.shape[1]
    uv = environment_uv(env, w)
    x = uv[0] * float(columns - 1)
    y = uv[1] * float(height - 1)
    i = wp.min(wp.int32(x), columns - 2)
    j = wp.min(wp.int32(y), height - 2)
    a = x - float(i)
    b = y - float(j)
    top = (1.0 - a) * env.texels[j, i] + a * env.texels[j, i + 1]
    bottom = (1.0 - a) * env.texels[j + 1, i] + a * env.texels[j + 1, i + 1]
    return (1.0 - b) * top + b * bottom


@wp.func
def _cell_solid_angle(env: EnvironmentData, j: wp.int32) -> wp.float64:
    """Ω of a cell in row j: Δφ (cos θ_j − cos θ_{j+1})."""
    rows = wp.float64(env.texels.shape[0] - 1)
    d_phi = wp.float64(TWO_PI) / wp.float64(env.texels.shape[1] - 1)
    pi = wp.float64(PI)
    return d_phi * (wp.cos(pi * wp.float64(j) / rows) - wp.cos(pi * wp.float64(j + 1) / rows))


@wp.func
def sample_environment(env: EnvironmentData, u: wp.vec2) -> wp.vec3:
    """The direction the ``envmap`` technique maps u to (zero vector: nothing to sample)."""
    if env.present == 0 or env.total <= wp.float64(0.0):
        return wp.vec3(0.0, 0.0, 0.0)
    height = env.texels.shape[0]
    columns = env.texels.shape[1]
    x = wp.float64(u[0])
    j = _search(env.row_cdf, height - 1, x)
    lo = env.row_cdf[j]
    x = wp.clamp((x - lo) / wp.max(env.row_cdf[j + 1] - lo, wp.float64(1.0e-300)), wp.float64(0.0),
                 wp.float64(0.9999999999))
    i = _search_row(env.col_cdf, j, columns - 1, x)
    lo = env.col_cdf[j, i]
    x = wp.clamp((x - lo) / wp.max(env.col_cdf[j, i + 1] - lo, wp.float64(1.0e-300)), wp.float64(0.0),
                 wp.float64(0.9999999999))
    # φ uniform over the cell's longitudes (the half-texel shift undone), cos θ uniform
    # over its latitudes: uniform in solid angle within the cell.
    step = wp.float64(1.0) / wp.float64(columns - 1)
    phi = wp.float64(TWO_PI) * ((wp.float64(i) + x + wp.float64(0.5)) * step)
    rows = wp.float64(height - 1)
    pi = wp.float64(PI)
    c0 = wp.cos(pi * wp.float64(j) / rows)
    c1 = wp.cos(pi * wp.float64(j + 1) / rows)
    cos_t = c0 - wp.float64(u[1]) * (c0 - c1)
    sin_t = wp.sqrt(wp.max(wp.float64(1.0) - cos_t * cos_t, wp.float64(0.0)))
    local = wp.vec3(float(wp.sin(phi) * sin_t), float(cos_t), float(-wp.cos(phi) * sin_t))
    return wp.normalize(env.to_world * local)


@wp.func
def environment_pdf(env: EnvironmentData, w: wp.vec3) -> float:
    """Solid-angle density of the ``envmap`` technique at ω: its cell's probability over
    the cell's solid angle."""
    if env.present == 0 or env.total <= wp.float64(0.0):
        return 0.0
    height = env.texels.shape[0]
    columns = env.texels.shape[1]
    uv = environment_uv(env, w)
    i = wp.min(wp.int32(uv[0] * float(columns - 1)), columns - 2)
    j = wp.min(wp.int32(uv[1] * float(height - 1)), height - 2)
    p = (env.row_cdf[j + 1] - env.row_cdf[j]) * (env.col_cdf[j, i + 1] - env.col_cdf[j, i])
    return float(p / _cell_solid_angle(env, j))
