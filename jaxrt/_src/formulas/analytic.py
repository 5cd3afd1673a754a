"""The built-in analytic shapes (sphere, disk, capped cylinder), one formula for every backend.

Each takes the shape's parameters and one ray (origin ``o``, unnormalised direction ``d``, interval
``[t_min, t_max]``) and returns ``(hit, distance)``: the first smallest valid root in the interval, in the
shape's order of candidates (:func:`take`), ``inf`` where there is none. Divisions and square roots are
correctly rounded; a rejected branch divides by 1 and takes the root of 1, so no NaN reaches a value or a
gradient.

Reference: Haines, Günther, Akenine-Möller, "Precision Improvements for Ray/Sphere Intersection", Ray Tracing
Gems, ch. 7, 2019 (the sphere's discriminant from the closest-approach vector and the stable root pair).
"""

from __future__ import annotations

from jaxrt._src.formulas.vocabulary import INF, div_rn, dot3, false_like, like, select, sqrt

__all__ = ["take", "sphere", "disk", "capped_cylinder"]


def take(best_ok, best_t, ok, t, t_min, t_max):
    """One candidate root: kept where valid, inside ``[t_min, t_max]`` and strictly nearer than the best."""
    ok = ok & (t >= t_min) & (t <= t_max)
    return best_ok | ok, select(ok & (t < best_t), t, best_t)


def sphere(px, py, pz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max):
    """The sphere of centre ``p`` and ``radius``: the nearer root inside the interval (the far root when the
    origin is inside the sphere)."""
    fx = ox - px
    fy = oy - py
    fz = oz - pz
    a = dot3(dx, dy, dz, dx, dy, dz)
    b = -dot3(fx, fy, fz, dx, dy, dz)
    s = div_rn(b, a)
    gx = fx + s * dx  # the centre-to-ray vector at closest approach (RTG ch. 7)
    gy = fy + s * dy
    gz = fz + s * dz
    rr = radius * radius
    disc = a * (rr - dot3(gx, gy, gz, gx, gy, gz))
    ok = disc >= 0
    q = b + select(b >= 0, like(b, 1.0), like(b, -1.0)) * sqrt(select(ok, disc, like(disc, 1.0)))
    c = dot3(fx, fy, fz, fx, fy, fz) - rr
    q_ok = ok & (q != 0)
    t0 = div_rn(c, select(q_ok, q, like(q, 1.0)))
    t1 = div_rn(q, a)
    best_ok, best_t = take(false_like(ok), like(t0, INF), q_ok, t0, t_min, t_max)
    return take(best_ok, best_t, ok, t1, t_min, t_max)


def disk(px, py, pz, nx, ny, nz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max):
    """The disk of centre ``p``, normal ``n`` and ``radius`` (both faces)."""
    denom = dot3(dx, dy, dz, nx, ny, nz)
    ok = denom != 0
    t = div_rn(dot3(px - ox, py - oy, pz - oz, nx, ny, nz), select(ok, denom, like(denom, 1.0)))
    ux = (ox + t * dx) - px
    uy = (oy + t * dy) - py
    uz = (oz + t * dz) - pz
    inside = dot3(ux, uy, uz, ux, uy, uz) <= radius * radius
    return take(false_like(ok), like(t, INF), ok & inside, t, t_min, t_max)


def capped_cylinder(px, py, pz, qx, qy, qz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max):
    """The capped cylinder of axis ``p`` to ``q`` and ``radius``: the side wall between the cap planes (the
    axis component projected out, scaled by ``|q - p|^2`` to avoid a division) and the two cap disks, the
    candidates in that order (wall near root, far root, cap at ``p``, cap at ``q``)."""
    ax = qx - px
    ay = qy - py
    az = qz - pz
    length2 = dot3(ax, ay, az, ax, ay, az)
    cx = ox - px
    cy = oy - py
    cz = oz - pz
    d_along = dot3(dx, dy, dz, ax, ay, az)
    oc_along = dot3(cx, cy, cz, ax, ay, az)
    vx = dx * length2 - ax * d_along
    vy = dy * length2 - ay * d_along
    vz = dz * length2 - az * d_along
    ux = cx * length2 - ax * oc_along
    uy = cy * length2 - ay * oc_along
    uz = cz * length2 - az * oc_along
    a = dot3(vx, vy, vz, vx, vy, vz)
    b = dot3(ux, uy, uz, vx, vy, vz)
    limit = ((radius * radius) * length2) * length2
    c = dot3(ux, uy, uz, ux, uy, uz) - limit
    disc = b * b - a * c
    wall_ok = (a > 0) & (disc >= 0)
    root = sqrt(select(wall_ok, disc, like(disc, 1.0)))
    a_safe = select(wall_ok, a, like(a, 1.0))
    best_ok = false_like(wall_ok)
    best_t = like(a, INF)
    t = div_rn(-b + like(b, -1.0) * root, a_safe)
    along = oc_along + t * d_along
    best_ok, best_t = take(best_ok, best_t, wall_ok & (along >= 0) & (along <= length2), t, t_min, t_max)
    t = div_rn(-b + like(b, 1.0) * root, a_safe)
    along = oc_along + t * d_along
    best_ok, best_t = take(best_ok, best_t, wall_ok & (along >= 0) & (along <= length2), t, t_min, t_max)
    cap_ok = d_along != 0
    d_safe = select(cap_ok, d_along, like(d_along, 1.0))
    t = div_rn(like(length2, 0.0) * length2 - oc_along, d_safe)
    rx = ux + t * vx
    ry = uy + t * vy
    rz = uz + t * vz
    best_ok, best_t = take(best_ok, best_t, cap_ok & (dot3(rx, ry, rz, rx, ry, rz) <= limit), t, t_min, t_max)
    t = div_rn(like(length2, 1.0) * length2 - oc_along, d_safe)
    rx = ux + t * vx
    ry = uy + t * vy
    rz = uz + t * vz
    return take(best_ok, best_t, cap_ok & (dot3(rx, ry, rz, rx, ry, rz) <= limit), t, t_min, t_max)
