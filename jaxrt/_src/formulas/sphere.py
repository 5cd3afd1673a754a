"""The built-in sphere primitive (``rt.SphereGeometry``): the ray/sphere test and the closest point, one formula
for every backend.

The test takes the sphere (centre ``c``, radius ``r``) and one ray (origin ``o``, unnormalised direction ``d``,
interval ``[t_min, t_max]``) and returns ``(hit, distance, front)``: the entry root where it lies in the
interval (``front`` true), else the exit root (``front`` false: the ray started inside the sphere, or entered
it before ``t_min``), else no hit (``distance`` ``inf``). A sphere with a negative, NaN or infinite radius, or
a non-finite centre, never hits. Divisions and square roots are correctly rounded; a rejected branch divides
by 1 and takes the root of 1, so no NaN reaches a value or a gradient.

Reference: Haines, Günther, Akenine-Möller, "Precision Improvements for Ray/Sphere Intersection", Ray Tracing
Gems, ch. 7, 2019: the discriminant from the centre-to-ray vector at closest approach (no cancellation of
``b^2`` against ``a c`` for small or distant spheres), and the stable root pair ``c / q`` and ``q / a`` with
``q = b + sign(b) sqrt(disc)`` (no cancellation of ``b`` against the root).
"""

from __future__ import annotations

from jaxrt._src.formulas.vocabulary import INF, div_rn, dot3, like, maximum, minimum, select, sqrt

__all__ = ["ray_sphere", "closest_on_sphere"]


def ray_sphere(cx, cy, cz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max):
    """``(hit, distance, front)`` of the ray and the sphere of centre ``c`` and ``radius`` (module docstring)."""
    fx = ox - cx
    fy = oy - cy
    fz = oz - cz
    a = dot3(dx, dy, dz, dx, dy, dz)
    b = -dot3(fx, fy, fz, dx, dy, dz)
    valid = (a > 0) & (radius >= 0) & (radius < like(radius, INF))
    a_safe = select(valid, a, like(a, 1.0))
    s = div_rn(b, a_safe)
    gx = fx + s * dx  # the centre-to-ray vector at closest approach (RTG ch. 7, eq. 7.5)
    gy = fy + s * dy
    gz = fz + s * dz
    rr = radius * radius
    disc = a * (rr - dot3(gx, gy, gz, gx, gy, gz))
    ok = valid & (disc >= 0)
    q = b + select(b >= 0, like(b, 1.0), like(b, -1.0)) * sqrt(select(ok, disc, like(disc, 1.0)))
    c = dot3(fx, fy, fz, fx, fy, fz) - rr
    q_ok = ok & (q != 0)
    t0 = div_rn(c, select(q_ok, q, like(q, 1.0)))
    t1 = div_rn(q, a_safe)
    # q == 0 only for a ray tangent at its own origin: both roots are 0.
    t0 = select(q_ok, t0, like(t0, 0.0))
    near = minimum(t0, t1)
    far = maximum(t0, t1)
    near_ok = ok & (near >= t_min) & (near <= t_max)
    far_ok = ok & (far >= t_min) & (far <= t_max)
    hit = near_ok | far_ok
    distance = select(near_ok, near, select(far_ok, far, like(near, INF)))
    return hit, distance, near_ok


def closest_on_sphere(px, py, pz, cx, cy, cz, radius):
    """The point of the sphere's surface closest to ``p``, and the signed distance to it (negative inside); a
    point at the centre takes the surface point along ``+x``."""
    ux = px - cx
    uy = py - cy
    uz = pz - cz
    length = sqrt(dot3(ux, uy, uz, ux, uy, uz))
    away = length > 0
    scale = div_rn(radius, select(away, length, like(length, 1.0)))
    qx = select(away, cx + ux * scale, cx + radius)
    qy = select(away, cy + uy * scale, cy)
    qz = select(away, cz + uz * scale, cz)
    return qx, qy, qz, length - radius
