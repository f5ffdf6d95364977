"""Gallery: a light sampler whose pdf is an area density, not a solid-angle density.

A Warp technique that samples a uniform point on occluded-quad's light (the rectangle
|x| ≤ 0.5, |y| ≤ 0.25 at z = 2, facing down; area 0.5) and returns its direction.  The
density of that direction is t²/(A |cos θ_y|); the bug returns 1/A, the density per unit
area.  Caught by measure: ∫pdf falls as distance⁻² when the light moves away.
"""

import warp as wp

import warpis

AREA = 0.5


@wp.func
def light_point(sp: warpis.ShadingPoint, u: wp.vec2) -> wp.vec3:
    y = wp.vec3(-0.5 + u[0], -0.25 + 0.5 * u[1], 2.0)
    return wp.normalize(y - sp.p)


@wp.func
def light_hit(sp: warpis.ShadingPoint, w: wp.vec3) -> float:
    """The distance t to the light along w, or 0 where the ray misses it."""
    if w[2] <= 0.0:
        return 0.0
    t = (2.0 - sp.p[2]) / w[2]
    y = sp.p + t * w
    if wp.abs(y[0]) > 0.5 or wp.abs(y[1]) > 0.25:
        return 0.0
    return t


@wp.func
def area_pdf(sp: warpis.ShadingPoint, w: wp.vec3) -> float:
    if light_hit(sp, w) == 0.0:
        return 0.0
    return 1.0 / AREA


@wp.func
def solid_angle_pdf(sp: warpis.ShadingPoint, w: wp.vec3) -> float:
    t = light_hit(sp, w)
    if t == 0.0:
        return 0.0
    return t * t / (AREA * w[2])  # |cos θ_y| = w·(0, 0, −1) negated: the light faces down


warpis.register_technique("quad-light-area-pdf", light_point, area_pdf, light=True,
                          description="a point on the quad light; pdf per unit area")
warpis.register_technique("quad-light", light_point, solid_angle_pdf, light=True,
                          description="a point on the quad light; pdf per unit solid angle")
