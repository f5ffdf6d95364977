"""Maps from the unit square to directions and surface points, each beside its density.

In the style of pbrt-v4's ``sampling.h``: every map ``square_to_X`` has its density
``X_pdf`` next to it.  All maps are inverse-CDF style and continuous on each cell of the
square, so stratification of u survives them.  Directions are in a local frame whose z
axis is the frame normal unless stated otherwise.
"""

from __future__ import annotations

import warp as wp

PI = wp.constant(3.14159265358979323846)
INV_PI = wp.constant(0.31830988618379067154)
INV_2PI = wp.constant(0.15915494309189533577)
PI64 = wp.constant(wp.float64(3.14159265358979323846))


@wp.func
def frame(n: wp.vec3):
    """Two tangents completing an orthonormal frame about unit ``n`` (Duff et al. 2017)."""
    sign = wp.where(n[2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + n[2])
    b = n[0] * n[1] * a
    return wp.vec3(1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]), wp.vec3(b, sign + n[1] * n[1] * a, -n[1])


@wp.func
def to_world(local: wp.vec3, n: wp.vec3) -> wp.vec3:
    """A local direction (z along ``n``) expressed in world coordinates."""
    t, b = frame(n)
    return local[0] * t + local[1] * b + local[2] * n


# --------------------------------------------------------------------------- hemisphere


@wp.func
def square_to_uniform_hemisphere(u: wp.vec2) -> wp.vec3:
    """Uniform direction on the hemisphere z ≥ 0: cos θ = u.x, φ = 2π u.y."""
    z = u[0]
    r = wp.sqrt(wp.max(0.0, 1.0 - z * z))
    phi = 2.0 * PI * u[1]
    return wp.vec3(r * wp.cos(phi), r * wp.sin(phi), z)


@wp.func
def uniform_hemisphere_pdf(cos_theta: float) -> float:
    """Solid-angle density of :func:`square_to_uniform_hemisphere`."""
    return wp.where(cos_theta > 0.0, INV_2PI, 0.0)


@wp.func
def square_to_concentric_disk(u: wp.vec2) -> wp.vec2:
    """Shirley–Chiu concentric map of the square to the unit disk (area preserving)."""
    a = 2.0 * u[0] - 1.0
    b = 2.0 * u[1] - 1.0
    if a == 0.0 and b == 0.0:
        return wp.vec2(0.0, 0.0)
    r = float(0.0)
    theta = float(0.0)
    if wp.abs(a) > wp.abs(b):
        r = a
        theta = (PI / 4.0) * (b / a)
    else:
        r = b
        theta = PI / 2.0 - (PI / 4.0) * (a / b)
    return wp.vec2(r * wp.cos(theta), r * wp.sin(theta))


@wp.func
def square_to_cosine_hemisphere(u: wp.vec2) -> wp.vec3:
    """Cosine-weighted direction (Malley: lift the concentric disk to the hemisphere)."""
    d = square_to_concentric_disk(u)
    z = wp.sqrt(wp.max(0.0, 1.0 - d[0] * d[0] - d[1] * d[1]))
    return wp.vec3(d[0], d[1], z)


@wp.func
def cosine_hemisphere_pdf(cos_theta: float) -> float:
    """Solid-angle density of :func:`square_to_cosine_hemisphere`: cos θ / π."""
    return wp.max(cos_theta, 0.0) * INV_PI


# --------------------------------------------------------------------------- Phong lobe


@wp.func
def square_to_phong_lobe(u: wp.vec2, exponent: float) -> wp.vec3:
    """Direction about local z with density (n+1)/(2π) cos^n α on the whole sphere."""
    cos_a = wp.pow(wp.max(u[0], 1.0e-30), 1.0 / (exponent + 1.0))
    sin_a = wp.sqrt(wp.max(0.0, 1.0 - cos_a * cos_a))
    phi = 2.0 * PI * u[1]
    return wp.vec3(sin_a * wp.cos(phi), sin_a * wp.sin(phi), cos_a)


@wp.func
def phong_lobe_pdf(cos_alpha: float, exponent: float) -> float:
    """Solid-angle density of :func:`square_to_phong_lobe` at angle α from the lobe axis."""
    if cos_alpha <= 0.0:
        return 0.0
    return (exponent + 1.0) * INV_2PI * wp.pow(cos_alpha, exponent)


# --------------------------------------------------------------------------- triangles


@wp.func
def square_to_triangle(u: wp.vec2, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> wp.vec3:
    """Uniform point on triangle abc: barycentrics (1 − √u₀, √u₀(1 − u₁), √u₀ u₁)."""
    s = wp.sqrt(u[0])
    return (1.0 - s) * a + s * (1.0 - u[1]) * b + s * u[1] * c


@wp.func
def angle_between64(a: wp.vec3d, b: wp.vec3d) -> wp.float64:
    """Angle between unit vectors, accurate for tiny and near-π angles."""
    if wp.dot(a, b) < wp.float64(0.0):
        return PI64 - wp.float64(2.0) * wp.asin(wp.min(wp.length(a + b) * wp.float64(0.5), wp.float64(1.0)))
    return wp.float64(2.0) * wp.asin(wp.min(wp.length(b - a) * wp.float64(0.5), wp.float64(1.0)))


@wp.func
def triangle_solid_angle(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> wp.float64:
    """Solid angle of triangle abc seen from p (Van Oosterom & Strackee 1983)."""
    ra = a - p
    rb = b - p
    rc = c - p
    la = wp.length(ra)
    lb = wp.length(rb)
    lc = wp.length(rc)
    num = wp.abs(wp.dot(ra, wp.cross(rb, rc)))
    den = la * lb * lc + wp.dot(ra, rb) * lc + wp.dot(ra, rc) * lb + wp.dot(rb, rc) * la
    return wp.float64(2.0) * wp.atan2(num, den)


@wp.func
def orthonormal_part64(v: wp.vec3d, w: wp.vec3d) -> wp.vec3d:
    """The unit component of ``v`` orthogonal to unit ``w`` (Gram–Schmidt)."""
    return wp.normalize(v - wp.dot(v, w) * w)


@wp.func
def square_to_spherical_triangle(u: wp.vec2, p: wp.vec3d, v0: wp.vec3d, v1: wp.vec3d, v2: wp.vec3d) -> wp.vec3d:
    """Uniform direction within the spherical triangle that v0 v1 v2 subtend at p (Arvo 1995).

    u.x picks the sub-triangle of area fraction u.x (this fixes the new vertex C' on arc
    AC); u.y then picks the point on the arc from B to C' so that the density is uniform.
    Computed in float64: the triangles of small lights subtend 1e-6 sr and less.
    """
    a = wp.normalize(v0 - p)
    b = wp.normalize(v1 - p)
    c = wp.normalize(v2 - p)
    n_ab = wp.normalize(wp.cross(a, b))
    n_bc = wp.normalize(wp.cross(b, c))
    n_ca = wp.normalize(wp.cross(c, a))
    alpha = angle_between64(n_ab, -n_ca)
    beta = angle_between64(n_bc, -n_ab)
    gamma = angle_between64(n_ca, -n_bc)
    area_u = wp.float64(u[0]) * (alpha + beta + gamma - PI64)  # area of the sub-triangle
    s = wp.sin(area_u - alpha)
    t = wp.cos(area_u - alpha)
    cos_c = wp.dot(a, b)
    uu = t - wp.cos(alpha)
    vv = s + wp.sin(alpha) * cos_c
    # cos of the arc from A to the new vertex C' (Arvo's eq. for q).
    q = ((vv * t - uu * s) * wp.cos(alpha) - vv) / ((vv * s + uu * t) * wp.sin(alpha))
    q = wp.clamp(q, wp.float64(-1.0), wp.float64(1.0))
    c_new = q * a + wp.sqrt(wp.max(wp.float64(1.0) - q * q, wp.float64(0.0))) * orthonormal_part64(c, a)
    z = wp.float64(1.0) - wp.float64(u[1]) * (wp.float64(1.0) - wp.dot(c_new, b))
    z = wp.clamp(z, wp.float64(-1.0), wp.float64(1.0))
    return z * b + wp.sqrt(wp.max(wp.float64(1.0) - z * z, wp.float64(0.0))) * orthonormal_part64(c_new, b)
