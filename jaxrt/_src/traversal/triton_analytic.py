"""The built-in analytic intersection functions in Triton: sphere, disk and capped cylinder leaves of the kernel.

:func:`analytic_hit` is the leaf test of :mod:`jaxrt._src.traversal.triton_kernel` for bounding-box leaves whose
geometry uses one of :mod:`jaxrt._src.primitives.analytic`'s functions. Each shape repeats that module's
formulas operation for operation, in the same order (a dot product is ``(x0 y0 + x1 y1) + x2 y2``), with
correctly rounded divisions and square roots (``div_rn``, ``sqrt_rn``) and no contraction, so every value is
the IEEE result of the portable function's expression; ``_nearest`` keeps the first smallest root in
``[t_min, t_max]`` in the function's order of candidates. ``t_max`` is the ray's current nearest distance,
as the portable traversal passes it to the function.

Parameters come from the leaf's row (:func:`jaxrt._src.traversal.packed.pack_analytic`): ``p`` (the sphere's
or disk's centre, the cylinder's ``p0``), ``q`` (the disk's normal, the cylinder's ``p1``), ``radius`` and the
shape code (1 sphere, 2 disk, 3 capped cylinder).
"""

from __future__ import annotations

import triton
import triton.language as tl


@triton.jit
def _dot(ax, ay, az, bx, by, bz):
    """``jnp.dot`` of two 3-vectors: ``(ax bx + ay by) + az bz``."""
    return (ax * bx + ay * by) + az * bz


@triton.jit
def _take(best_ok, best_t, ok, t, t_min, t_max):
    """One candidate of the portable ``_nearest``: kept where valid, inside the interval and strictly nearer."""
    ok = ok & (t >= t_min) & (t <= t_max)
    take = ok & (t < best_t)
    return best_ok | ok, tl.where(take, t, best_t)


@triton.jit
def _sphere(px, py, pz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max):
    """The portable ``sphere``: the stable root pair from the closest-approach discriminant (RTG ch. 7)."""
    fx = ox - px
    fy = oy - py
    fz = oz - pz
    a = _dot(dx, dy, dz, dx, dy, dz)
    b = -_dot(fx, fy, fz, dx, dy, dz)
    s = tl.math.div_rn(b, a)
    gx = fx + s * dx
    gy = fy + s * dy
    gz = fz + s * dz
    rr = radius * radius
    disc = a * (rr - _dot(gx, gy, gz, gx, gy, gz))
    ok = disc >= 0
    q = b + tl.where(b >= 0, 1.0, -1.0) * tl.math.sqrt_rn(tl.where(ok, disc, 1.0))
    c = _dot(fx, fy, fz, fx, fy, fz) - rr
    q_ok = ok & (q != 0)
    t0 = tl.math.div_rn(c, tl.where(q_ok, q, 1.0))
    t1 = tl.math.div_rn(q, a)
    best_ok = tl.zeros(ok.shape, tl.int1)
    best_t = tl.full(ok.shape, float("inf"), tl.float32)
    best_ok, best_t = _take(best_ok, best_t, q_ok, t0, t_min, t_max)
    best_ok, best_t = _take(best_ok, best_t, ok, t1, t_min, t_max)
    return best_ok, best_t


@triton.jit
def _disk(px, py, pz, nx, ny, nz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max):
    """The portable ``disk`` (both faces)."""
    denom = _dot(dx, dy, dz, nx, ny, nz)
    ok = denom != 0
    t = tl.math.div_rn(_dot(px - ox, py - oy, pz - oz, nx, ny, nz), tl.where(ok, denom, 1.0))
    ux = (ox + t * dx) - px
    uy = (oy + t * dy) - py
    uz = (oz + t * dz) - pz
    inside = _dot(ux, uy, uz, ux, uy, uz) <= radius * radius
    best_ok = tl.zeros(ok.shape, tl.int1)
    best_t = tl.full(ok.shape, float("inf"), tl.float32)
    return _take(best_ok, best_t, ok & inside, t, t_min, t_max)


@triton.jit
def _wall(best_ok, best_t, wall_ok, b, root, a_safe, oc_along, d_along, length2, t_min, t_max):
    """One root of the cylinder's side wall, kept between the cap planes."""
    t = tl.math.div_rn(-b + root, a_safe)
    along = oc_along + t * d_along
    return _take(best_ok, best_t, wall_ok & (along >= 0) & (along <= length2), t, t_min, t_max)


@triton.jit
def _cap(best_ok, best_t, cap_ok, start, d_safe, ux, uy, uz, vx, vy, vz, limit, t_min, t_max):
    """One cap disk of the cylinder: the plane crossing ``start / d_along``, inside the radius."""
    t = tl.math.div_rn(start, d_safe)
    rx = ux + t * vx
    ry = uy + t * vy
    rz = uz + t * vz
    return _take(best_ok, best_t, cap_ok & (_dot(rx, ry, rz, rx, ry, rz) <= limit), t, t_min, t_max)


@triton.jit
def _capped_cylinder(px, py, pz, qx, qy, qz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max):
    """The portable ``capped_cylinder``: the side wall (axis component projected out, scaled by ``|axis|^2``)
    and the two cap disks, candidates in its order (wall near root, far root, cap at ``p0``, cap at ``p1``)."""
    ax = qx - px
    ay = qy - py
    az = qz - pz
    length2 = _dot(ax, ay, az, ax, ay, az)
    cx = ox - px
    cy = oy - py
    cz = oz - pz
    d_along = _dot(dx, dy, dz, ax, ay, az)
    oc_along = _dot(cx, cy, cz, ax, ay, az)
    vx = dx * length2 - ax * d_along
    vy = dy * length2 - ay * d_along
    vz = dz * length2 - az * d_along
    ux = cx * length2 - ax * oc_along
    uy = cy * length2 - ay * oc_along
    uz = cz * length2 - az * oc_along
    a = _dot(vx, vy, vz, vx, vy, vz)
    b = _dot(ux, uy, uz, vx, vy, vz)
    limit = ((radius * radius) * length2) * length2
    c = _dot(ux, uy, uz, ux, uy, uz) - limit
    disc = b * b - a * c
    wall_ok = (a > 0) & (disc >= 0)
    root = tl.math.sqrt_rn(tl.where(wall_ok, disc, 1.0))
    a_safe = tl.where(wall_ok, a, 1.0)
    best_ok = tl.zeros(wall_ok.shape, tl.int1)
    best_t = tl.full(wall_ok.shape, float("inf"), tl.float32)
    best_ok, best_t = _wall(best_ok, best_t, wall_ok, b, -root, a_safe, oc_along, d_along, length2, t_min, t_max)
    best_ok, best_t = _wall(best_ok, best_t, wall_ok, b, root, a_safe, oc_along, d_along, length2, t_min, t_max)
    cap_ok = d_along != 0
    d_safe = tl.where(cap_ok, d_along, 1.0)
    best_ok, best_t = _cap(best_ok, best_t, cap_ok, 0.0 - oc_along, d_safe, ux, uy, uz, vx, vy, vz, limit, t_min, t_max)
    best_ok, best_t = _cap(best_ok, best_t, cap_ok, length2 - oc_along, d_safe, ux, uy, uz, vx, vy, vz, limit, t_min, t_max)  # fmt: skip
    return best_ok, best_t


@triton.jit
def _any(flags):
    """Whether some lane of the warp has ``flags`` set (a warp-uniform value)."""
    return tl.max(flags.to(tl.int32), axis=0) > 0


@triton.jit
def _merge(hit, distance, shape_hit, shape_t):
    return hit | shape_hit, tl.where(shape_hit, shape_t, distance)


@triton.jit
def analytic_hit(
    code, mask, px, py, pz, qx, qy, qz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max, SHAPES: tl.constexpr
):  # fmt: skip
    """``(hit, distance)`` of analytic leaves where ``mask`` (``inf`` where not hit): each lane's shape by its
    ``code``. ``SHAPES`` (compile-time) has bit ``code - 1`` set for each shape the scene holds: only those
    are compiled, and with several each is computed only where some lane of the warp needs it."""
    hit = tl.zeros(mask.shape, tl.int1)
    distance = tl.full(mask.shape, float("inf"), tl.float32)
    if (SHAPES & 1) != 0:
        lanes = mask & (code == 1.0)
        if (SHAPES & (SHAPES - 1)) != 0:
            if _any(lanes):
                h, t = _sphere(px, py, pz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max)
                hit, distance = _merge(hit, distance, lanes & h, t)
        else:
            h, t = _sphere(px, py, pz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max)
            hit, distance = _merge(hit, distance, lanes & h, t)
    if (SHAPES & 2) != 0:
        lanes = mask & (code == 2.0)
        if (SHAPES & (SHAPES - 1)) != 0:
            if _any(lanes):
                h, t = _disk(px, py, pz, qx, qy, qz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max)
                hit, distance = _merge(hit, distance, lanes & h, t)
        else:
            h, t = _disk(px, py, pz, qx, qy, qz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max)
            hit, distance = _merge(hit, distance, lanes & h, t)
    if (SHAPES & 4) != 0:
        lanes = mask & (code == 3.0)
        if (SHAPES & (SHAPES - 1)) != 0:
            if _any(lanes):
                h, t = _capped_cylinder(px, py, pz, qx, qy, qz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max)
                hit, distance = _merge(hit, distance, lanes & h, t)
        else:
            h, t = _capped_cylinder(px, py, pz, qx, qy, qz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max)
            hit, distance = _merge(hit, distance, lanes & h, t)
    return hit, tl.where(hit, distance, float("inf"))
