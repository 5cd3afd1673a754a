"""The ray/curve-segment test (round tubes and flat ribbons of cubic Bezier segments), one formula for every
backend: the method of :func:`jaxrt._src.primitives.curve.intersect`, per ray and segment.

:func:`segment` is the whole leaf test of one packed segment (:func:`jaxrt._src.curves.pack_segments`): its
control points moved into the ray's frame (:func:`ray_space`), a conservative cull by the control points'
hull (:func:`hull_cull`), and the round (:func:`round_test`) or flat (:func:`flat_test`) test in the order of
operations of ``curve._round`` and ``curve._flat``: the chord pieces as exact round cones and inner spheres,
the safeguarded Newton steps towards the closest approach, the Newton refinement of two starts, the chord
fallback and the end spheres and disks with the joint rules; for ribbons, the chord crossings, Newton on
``p . p' = 0`` from every candidate near the polyline, and the ray-facing end disks and spheres. Candidates
are walked in the portable order, each kind keeping the first of its smallest keys (the portable
``argmin``), so one piece's values are live at a time.

The static options (``pieces``, ``iterations``, ``approach``, ``tolerance``, whether disk and sphere caps are
compiled) are Python values in JAX, constant expressions in Triton and plain arguments in Numba; loops run
over them only (never over values). ``hull_cull`` is a pure cull: every hit either test accepts lies within
the hull grown by the largest radius, so a culled lane is a miss of the test too.

Exactness: divisions are ``div_rn`` and square roots correctly rounded; the Bernstein weights of the samples
are computed in float64 and rounded once (:func:`~jaxrt._src.formulas.vocabulary.sample_weights`), as
``curve._bernstein`` rounds them. Numba and Triton leave every multiply-add unfused; XLA contracts some of
``curve.intersect``'s, so distances agree with the portable path to a few ulps (the decisions, hit or miss
and which segment, agree on the tested scenes).

References: see :mod:`jaxrt._src.primitives.curve` (Reshetov and Luebke 2018; Woop et al. 2014; van Wijk 1985).
"""

from __future__ import annotations

from jaxrt._src.formulas.vocabulary import (
    INF,
    absolute,
    any_lane,
    div_rn,
    epsilon_of,
    false_like,
    like,
    maximum,
    minimum,
    sample_weights,
    select,
    sqrt,
    tiny_of,
)

#: The Numba instance's functions are compiled as calls that LLVM inlines, not inlined at Numba's IR level
#: (which compiles the round test several times slower).
NUMBA_INLINE = False

#: Which part of the segment was hit (``curve.PART_*``).
PART_TUBE = 0
PART_SPHERE = 1
PART_DISK = 2
PART_RIBBON = 3
PART_FACING_DISK = 4

__all__ = [
    "ray_space",
    "hull_cull",
    "round_test",
    "flat_test",
    "segment",
    "cone",
    "sphere_entry",
    "enter_slope",
    "end_disk",
]


def diff_of_squares(a, b):
    """``a^2 - b^2`` as ``(a - b)(a + b)`` (no cancellation when ``a`` and ``b`` are close)."""
    return (a - b) * (a + b)


def clip(x, lo, hi):
    return minimum(maximum(x, lo), hi)


def evaluate(c0, c1, c2, c3, u):
    """Value, first and second derivative at ``u`` of one power-basis channel (``curve._evaluate``)."""
    value = c0 + u * (c1 + u * (c2 + u * c3))
    first = c1 + u * (like(u, 2.0) * c2 + like(u, 3.0) * u * c3)
    second = like(u, 2.0) * c2 + like(u, 6.0) * u * c3
    return value, first, second


def value_at(c0, c1, c2, c3, u):
    return c0 + u * (c1 + u * (c2 + u * c3))


def power(q0, q1, q2, q3):
    """Power-basis coefficients of one channel (``curve._combine(_TO_POWER, q)``, row by row)."""
    return (
        q0,
        like(q0, -3.0) * q0 + like(q0, 3.0) * q1,
        like(q0, 3.0) * q0 + like(q0, -6.0) * q1 + like(q0, 3.0) * q2,
        like(q0, -1.0) * q0 + like(q0, 3.0) * q1 + like(q0, -3.0) * q2 + q3,
    )


def sample(index, pieces, x0, x1, x2, x3, y0, y1, y2, y3, z0, z1, z2, z3, r0, r1, r2, r3):
    """Ray-space sample ``(x, y, z, |r|)`` number ``index`` (``0..pieces``) of the segment (``curve._samples``):
    the weights of the zero Bernstein terms are left out, as ``curve._combine`` leaves them out."""
    w0, w1, w2, w3 = sample_weights(x0, index, pieces)
    x = combine(index, pieces, w0, w1, w2, w3, x0, x1, x2, x3)
    y = combine(index, pieces, w0, w1, w2, w3, y0, y1, y2, y3)
    z = combine(index, pieces, w0, w1, w2, w3, z0, z1, z2, z3)
    r = combine(index, pieces, w0, w1, w2, w3, r0, r1, r2, r3)
    return x, y, z, absolute(r)


def combine(index, pieces, w0, w1, w2, w3, q0, q1, q2, q3):
    """``w0 q0 + w1 q1 + w2 q2 + w3 q3``; at the ends (one weight 1, the others 0) the end point itself."""
    inner = ((w0 * q0 + w1 * q1) + w2 * q2) + w3 * q3
    return select(index == 0, q0, select(index == pieces, q3, inner))


def enter_slope(x, y, z, r, dx, dy, dz, dr):
    """Sign-carrying slope of ``t_enter`` at a sphere along a derivative (``curve._enter_slope``)."""
    depth = diff_of_squares(absolute(r), sqrt(x * x + y * y))
    root = sqrt(maximum(depth, like(depth, 0.0)))
    return dz * root - (r * dr - x * dx - y * dy)


def sphere_entry(x, y, z, r):
    """Entry ``(valid, t)`` of the ray (``+z`` from the origin) into the sphere ``(x, y, z)``, radius ``|r|``."""
    depth = diff_of_squares(absolute(r), sqrt(x * x + y * y))
    return depth >= 0, z - sqrt(maximum(depth, like(depth, 0.0)))


def cone(ax, ay, az, ar, bx, by, bz, br):
    """``(valid, t, s)``: the entry into the round cone from ``a`` to ``b`` (``curve._round_cone_tube``)."""
    p1x = bx - ax
    p1y = by - ay
    z1 = bz - az
    dr = br - ar
    big_a = dr * dr - (p1x * p1x + p1y * p1y)
    big_b = ar * dr - (ax * p1x + ay * p1y)
    k = z1 * z1 - big_a
    mx = dr * ax - ar * p1x
    my = dr * ay - ar * p1y
    mixed = sqrt(mx * mx + my * my)
    cross = absolute(ax * p1y - ay * p1x)
    disc = diff_of_squares(mixed, cross)
    exists = (k > 0) & (disc >= 0)
    one = like(k, 1.0)
    root = z1 * sqrt(select(exists, div_rn(disc, select(k > 0, k, one)), like(k, 0.0)))
    first = -big_b + root
    numerator_2 = z1 * z1 * (ar * ar - (ax * ax + ay * ay)) - big_b * big_b
    denominator_2 = k * (-big_b - root)
    same = (-big_b) * root >= 0
    num = select(same, first, numerator_2)
    den = select(same, big_a, denominator_2)
    ok = exists & (den != 0)
    s = select(ok, div_rn(num, select(den != 0, den, one)), like(k, -1.0))
    px = ax + s * p1x
    py = ay + s * p1y
    r = absolute(ar + s * dr)
    depth = diff_of_squares(r, sqrt(px * px + py * py))
    valid = ok & (s >= 0) & (s <= 1) & (depth >= 0)
    t = az + s * z1 - sqrt(maximum(depth, like(depth, 0.0)))
    return valid, t, s


def entry_at(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u):
    """``t_enter(u) = z - sqrt(max(r^2 - |p|^2, 0))`` on the true cubic."""
    x = value_at(cx0, cx1, cx2, cx3, u)
    y = value_at(cy0, cy1, cy2, cy3, u)
    z = value_at(cz0, cz1, cz2, cz3, u)
    r = value_at(cr0, cr1, cr2, cr3, u)
    return z - sqrt(maximum(diff_of_squares(absolute(r), sqrt(x * x + y * y)), like(z, 0.0)))


def tube_newton(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u, t, iterations, h):  # fmt: skip
    """``iterations`` Newton steps on the tube's two equations in ``(u, t)``, kept within ``h`` of the start."""
    window_lo = maximum(u - h, like(u, 0.0))
    window_hi = minimum(u + h, like(u, 1.0))
    two = like(u, 2.0)
    for _ in range(iterations):
        x, dx, ddx = evaluate(cx0, cx1, cx2, cx3, u)
        y, dy, ddy = evaluate(cy0, cy1, cy2, cy3, u)
        z, dz, ddz = evaluate(cz0, cz1, cz2, cz3, u)
        r, dr, ddr = evaluate(cr0, cr1, cr2, cr3, u)
        w = t - z
        f = x * x + y * y + w * w - r * r
        g = -x * dx - y * dy + w * dz + r * dr
        f_u = -two * g
        f_t = two * w
        g_u = -(dx * dx + dy * dy + dz * dz) - x * ddx - y * ddy + w * ddz + dr * dr + r * ddr
        det = f_u * dz - f_t * g_u
        safe = select(det == 0, like(det, 1.0), det)
        du = select(det == 0, like(det, 0.0), div_rn(-f * dz + f_t * g, safe))
        dt = select(det == 0, like(det, 0.0), div_rn(-f_u * g + f * g_u, safe))
        u = clip(u + du, window_lo, window_hi)
        t = t + dt
    return u, t


def tube_accept(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u, t, found, noise, lo, hi, tolerance):  # fmt: skip
    """Whether a Newton result ``(u, t)`` is a converged tube entry: ``(converged, valid)``."""
    x, dx, ddx = evaluate(cx0, cx1, cx2, cx3, u)
    y, dy, ddy = evaluate(cy0, cy1, cy2, cy3, u)
    z, dz, ddz = evaluate(cz0, cz1, cz2, cz3, u)
    r, dr, ddr = evaluate(cr0, cr1, cr2, cr3, u)
    w = t - z
    speed = sqrt(dx * dx + dy * dy + dz * dz)
    radius = absolute(r)
    tol = like(r, tolerance) * radius + noise
    off_sphere = absolute(sqrt(x * x + y * y + w * w) - radius)
    off_envelope = absolute(-x * dx - y * dy + w * dz + r * dr)
    g_u = -(dx * dx + dy * dy + dz * dz) - x * ddx - y * ddy + w * ddz + dr * dr + r * ddr
    f = x * x + y * y + w * w - r * r
    g = -x * dx - y * dy + w * dz + r * dr
    two = like(r, 2.0)
    det = -two * g * dz - two * w * g_u
    remaining = div_rn(absolute(two * g * g + f * g_u), maximum(absolute(det), tiny_of(det)))
    converged = found & (off_sphere <= tol) & (off_envelope <= tol * (speed + absolute(dr))) & (remaining <= tol)
    slack = like(u, 1e-6)
    valid = converged & (w <= 0) & (g_u <= 0) & (u >= -slack) & (u <= like(u, 1.0) + slack) & (t >= lo) & (t <= hi)
    return converged, valid


def end_disk(px, py, pz, pr, dx, dy, dz, dr, fx, fy, fz, sign):
    """Entry through the flat disk spanning the tube's end circle (``curve._disk``; ``f`` the fallback axis,
    ``sign`` +1 at the start, -1 at the end): ``(ok, t)``."""
    tiny = tiny_of(px)
    speed = sqrt(dx * dx + dy * dy + dz * dz)
    moving = speed > 0
    ax = select(moving, dx, fx)
    ay = select(moving, dy, fy)
    az = select(moving, dz, fz)
    length = maximum(sqrt(ax * ax + ay * ay + az * az), tiny)
    ax = div_rn(ax, length)
    ay = div_rn(ay, length)
    az = div_rn(az, length)
    radius = absolute(pr)
    offset = clip(div_rn(-pr * dr, maximum(speed, tiny)), -radius, radius)
    cx = px + offset * ax
    cy = py + offset * ay
    cz = pz + offset * az
    facing = like(az, sign) * az > 0
    t = div_rn(cx * ax + cy * ay + cz * az, select(az == 0, like(az, 1.0), az))
    hx = like(t, 0.0) * t - cx
    hy = like(t, 0.0) * t - cy
    hz = t - cz
    inside = hx * hx + hy * hy + hz * hz <= diff_of_squares(radius, absolute(offset))
    return facing & inside, t


def nearer(ok, t, u, part, best_ok, best_t, best_u, best_part, lo, hi):
    """``curve._pick`` one candidate at a time: a later candidate wins only with a strictly smaller key."""
    good = ok & (t >= lo) & (t <= hi)
    key = select(good, t, like(t, INF))
    take = key < best_t
    return best_ok | good, select(take, key, best_t), select(take, u, best_u), select(take, part, best_part)


def to_ray(lx, ly, lz, bx, by, bz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz):
    """A control point relative to the base point in ray space: ``_rotate((base - origin) + local, frame)``."""
    vx = bx + lx
    vy = by + ly
    vz = bz + lz
    return vx * e1x + vy * e1y + vz * e1z, vx * e2x + vy * e2y + vz * e2z, vx * nx + vy * ny + vz * nz


def ray_space(
    l0x, l0y, l0z, l1x, l1y, l1z, l2x, l2y, l2z, l3x, l3y, l3z, basex, basey, basez, vx, vy, vz,
    ox, oy, oz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz,
):  # fmt: skip
    """The segment's control points in ray space (x, y across the ray, z along its unit direction) about the
    base point, and the predecessor's joint derivative ``v`` rotated: ``(x0, y0, z0, ..., x3, y3, z3, pvx, pvy,
    pvz)``."""
    bx = basex - ox
    by = basey - oy
    bz = basez - oz
    x0, y0, z0 = to_ray(l0x, l0y, l0z, bx, by, bz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz)
    x1, y1, z1 = to_ray(l1x, l1y, l1z, bx, by, bz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz)
    x2, y2, z2 = to_ray(l2x, l2y, l2z, bx, by, bz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz)
    x3, y3, z3 = to_ray(l3x, l3y, l3z, bx, by, bz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz)
    pvx = vx * e1x + vy * e1y + vz * e1z
    pvy = vx * e2x + vy * e2y + vz * e2z
    pvz = vx * nx + vy * ny + vz * nz
    return x0, y0, z0, x1, y1, z1, x2, y2, z2, x3, y3, z3, pvx, pvy, pvz


def hull_cull(x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, lo, hi, tolerance):
    """``(live, noise)``: whether the ray passes within the control points' hull grown by the largest radius
    (with the Newton tolerance and the rounding of the evaluations) inside the interval, and the rounding noise
    of the ray-space coordinates (16 eps of their scale, as ``curve.intersect``'s)."""
    position_scale = maximum(
        maximum(maximum(maximum(absolute(x0), absolute(y0)), maximum(absolute(z0), absolute(x1))),
                maximum(maximum(absolute(y1), absolute(z1)), maximum(absolute(x2), absolute(y2)))),
        maximum(maximum(absolute(z2), absolute(x3)), maximum(absolute(y3), absolute(z3))),
    )  # fmt: skip
    radius_scale = maximum(maximum(absolute(r0), absolute(r1)), maximum(absolute(r2), absolute(r3)))
    noise = like(x0, 16.0) * epsilon_of(x0) * (position_scale + radius_scale)
    reach = radius_scale * like(x0, 1.0 + 2.0 * tolerance) + like(x0, 8.0) * noise
    min_x = minimum(minimum(x0, x1), minimum(x2, x3))
    max_x = maximum(maximum(x0, x1), maximum(x2, x3))
    min_y = minimum(minimum(y0, y1), minimum(y2, y3))
    max_y = maximum(maximum(y0, y1), maximum(y2, y3))
    min_z = minimum(minimum(z0, z1), minimum(z2, z3))
    max_z = maximum(maximum(z0, z1), maximum(z2, z3))
    outside = (min_x > reach) | (max_x < -reach) | (min_y > reach) | (max_y < -reach)
    outside = outside | (min_z - reach > hi) | (max_z + reach < lo)
    return outside == 0, noise


def chord_bound(x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, pieces):
    """How far the curve (radius included) strays from its chords (``curve._chord_bound``): ``0.75 h^2``
    times the largest second difference of the control points (``h = 1 / pieces``)."""
    two = like(x0, 2.0)
    sx = x0 - two * x1 + x2
    sy = y0 - two * y1 + y2
    sz = z0 - two * z1 + z2
    tx = x1 - two * x2 + x3
    ty = y1 - two * y2 + y3
    tz = z1 - two * z2 + z3
    position = maximum(sqrt(sx * sx + sy * sy + sz * sz), sqrt(tx * tx + ty * ty + tz * tz))
    radius = maximum(absolute(r0 - two * r1 + r2), absolute(r1 - two * r2 + r3))
    return div_rn(like(x0, 0.75) * (position + radius), like(x0, pieces * pieces))


def round_test(
    x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, pvx, pvy, pvz, pvr, bits, lo, hi, noise,
    pieces, iterations, approach, tolerance, disk, sphere,
):  # fmt: skip
    """``curve._round``: ``(hit, t, u, part)`` of the nearest entry into the round segment in ray space within
    ``[lo, hi]`` (``t`` in world length along the unit direction; ``inf`` on a miss). ``bits``: the segment's
    flags; ``disk``, ``sphere``: whether disk and sphere caps are compiled; ``part`` the ``PART_*`` code of the
    part hit (as ``curve.intersect`` reports it)."""
    h = like(x0, 1.0 / pieces)
    zero = like(x0, 0.0)
    one = like(x0, 1.0)
    inf = like(x0, INF)
    has_previous = (bits & 1) != 0
    has_next = (bits & 2) != 0
    caps = (bits >> 2) & 3
    cx0, cx1, cx2, cx3 = power(x0, x1, x2, x3)
    cy0, cy1, cy2, cy3 = power(y0, y1, y2, y3)
    cz0, cz1, cz2, cz3 = power(z0, z1, z2, z3)
    cr0, cr1, cr2, cr3 = power(r0, r1, r2, r3)
    grow = zero
    margin = zero
    if iterations > 0:
        grow = chord_bound(x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, pieces)
        # The margin: twice the largest sample radius plus the chord bound.
        largest = -inf
        for i in range(pieces + 1):
            _, _, _, ri = sample(i, pieces, x0, x1, x2, x3, y0, y1, y2, y3, z0, z1, z2, z3, r0, r1, r2, r3)
            largest = maximum(largest, ri)
        margin = like(x0, 2.0) * (largest + grow)
    low = lo - margin

    # The pieces in order, each candidate kept where it is the first of the smallest keys (``jnp.argmin``; the
    # values of the first piece where none is valid, as the portable gather reads them).
    cone_best = inf
    cone_t = inf
    cone_u = zero
    sphere_best = inf
    sphere_t = inf
    sphere_u = zero
    touch_best = inf
    t_entry = inf
    u_entry = zero
    touches = false_like(has_previous)
    px, py, pz, pr = sample(0, pieces, x0, x1, x2, x3, y0, y1, y2, y3, z0, z1, z2, z3, r0, r1, r2, r3)
    ax, ay, az, ar = px, py, pz, pr
    for i in range(pieces):
        fi = like(x0, i)
        bx, by, bz, br = sample(i + 1, pieces, x0, x1, x2, x3, y0, y1, y2, y3, z0, z1, z2, z3, r0, r1, r2, r3)
        # The chord: the exact entry of the round cone from sample i to i + 1.
        valid, t, s = cone(ax, ay, az, ar, bx, by, bz, br)
        key = select(valid & (t >= low) & (t <= hi), t, inf)
        take = (key < cone_best) | (i == 0)
        cone_best = select(take, key, cone_best)
        cone_t = select(take, t, cone_t)
        cone_u = select(take, (fi + s) * h, cone_u)
        if i > 0:
            # The inner sphere at sample i, on the chords' surface only where it fills a kink.
            ok, t = sphere_entry(ax, ay, az, ar)
            before = enter_slope(ax, ay, az, ar, ax - px, ay - py, az - pz, ar - pr)
            after = enter_slope(ax, ay, az, ar, bx - ax, by - ay, bz - az, br - ar)
            ok = ok & (before <= 0) & (after >= 0)
            key = select(ok & (t >= low) & (t <= hi), t, inf)
            take = (key < sphere_best) | (i == 1)
            sphere_best = select(take, key, sphere_best)
            sphere_t = select(take, t, sphere_t)
            sphere_u = select(take, fi * h, sphere_u)
        if iterations > 0:
            # Newton towards the ray's closest approach to the true curve near this piece, where its chord passes
            # within the chord bound of the ray: whether the curve is touched, and an entry estimate.
            p1x = bx - ax
            p1y = by - ay
            length2 = p1x * p1x + p1y * p1y
            s = clip(div_rn(-(ax * p1x + ay * p1y), select(length2 > 0, length2, one)), zero, one)
            reach = ar + s * (br - ar) + grow
            qx = ax + s * p1x
            qy = ay + s * p1y
            near = qx * qx + qy * qy <= reach * reach
            # The piece's values count where it is near, and the first piece's always (the portable gather's
            # values where no piece touches).
            if any_lane(near | (i == 0)):
                u = (fi + s) * h
                a = clip(u - h, zero, one)
                b = clip(u + h, zero, one)
                for _ in range(approach):
                    # Safeguarded Newton on h(u) = p . p' - r r' in the bracket [a, b] (bisection where it leaves it).
                    x, dx, ddx = evaluate(cx0, cx1, cx2, cx3, u)
                    y, dy, ddy = evaluate(cy0, cy1, cy2, cy3, u)
                    r, dr, ddr = evaluate(cr0, cr1, cr2, cr3, u)
                    value = x * dx + y * dy - r * dr
                    slope = dx * dx + dy * dy + x * ddx + y * ddy - dr * dr - r * ddr
                    a = select(value < 0, u, a)
                    b = select(value > 0, u, b)
                    step = u - div_rn(value, select(slope > 0, slope, one))
                    good = (slope > 0) & (step >= a) & (step <= b)
                    u = select(good, step, like(u, 0.5) * (a + b))
                # The closest of the iterate and the bracket's ends (the first on ties).
                x = value_at(cx0, cx1, cx2, cx3, u)
                y = value_at(cy0, cy1, cy2, cy3, u)
                r = value_at(cr0, cr1, cr2, cr3, u)
                best = x * x + y * y - r * r
                u_close = u
                x = value_at(cx0, cx1, cx2, cx3, a)
                y = value_at(cy0, cy1, cy2, cy3, a)
                r = value_at(cr0, cr1, cr2, cr3, a)
                gap = x * x + y * y - r * r
                u_close = select(gap < best, a, u_close)
                best = minimum(gap, best)
                x = value_at(cx0, cx1, cx2, cx3, b)
                y = value_at(cy0, cy1, cy2, cy3, b)
                r = value_at(cr0, cr1, cr2, cr3, b)
                gap = x * x + y * y - r * r
                u_close = select(gap < best, b, u_close)
                x, dx, _ = evaluate(cx0, cx1, cx2, cx3, u_close)
                y, dy, _ = evaluate(cy0, cy1, cy2, cy3, u_close)
                z, dz, _ = evaluate(cz0, cz1, cz2, cz3, u_close)
                r = value_at(cr0, cr1, cr2, cr3, u_close)
                depth = diff_of_squares(absolute(r), sqrt(x * x + y * y))
                touching = near & (depth >= like(x, -2.0) * noise * (absolute(r) + noise))
                across2 = dx * dx + dy * dy
                shift = div_rn(
                    -dz * sqrt(maximum(depth, zero)), sqrt(maximum(across2 * (across2 + dz * dz), like(x, 1e-30)))
                )
                u_try = clip(u_close + clip(shift, -h, h), zero, one)
                t_try = entry_at(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u_try)
                key = select(touching & (t_try >= low) & (t_try <= hi), t_try, inf)
                take = (key < touch_best) | (i == 0)
                touch_best = select(take, key, touch_best)
                t_entry = select(take, t_try, t_entry)
                u_entry = select(take, u_try, u_entry)
                touches = touches | touching
        px, py, pz, pr = ax, ay, az, ar
        ax, ay, az, ar = bx, by, bz, br
    cone_wins = cone_best <= sphere_best  # the cones come first in the portable candidate order
    chord_ok = minimum(cone_best, sphere_best) < inf
    chord_t = select(cone_wins, cone_t, sphere_t)
    chord_u = select(cone_wins, cone_u, sphere_u)

    tube_ok = chord_ok & (chord_t >= lo)
    tube_t = chord_t
    tube_u = chord_u
    if iterations > 0:
        touch_ok = touch_best < inf
        found = chord_ok | touch_ok
        # Where nothing is found no Newton result is accepted and there is no fallback: the chord's values.
        tube_ok = false_like(found)
        tube_u = clip(chord_u, zero, one)
        if any_lane(found):
            t_chord = entry_at(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, chord_u)
            # Two starts refined side by side: the chord's hit and the entry through the closest approach.
            u_a = select(chord_ok, chord_u, u_entry)
            t_a = select(chord_ok, t_chord, t_entry)
            u_a, t_a = tube_newton(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u_a, t_a, iterations, h)  # fmt: skip
            u_b, t_b = tube_newton(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u_entry, t_entry, iterations, h)  # fmt: skip
            conv_a, valid_a = tube_accept(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u_a, t_a, found, noise, lo, hi, tolerance)  # fmt: skip
            conv_b, valid_b = tube_accept(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u_b, t_b, found, noise, lo, hi, tolerance)  # fmt: skip
            key_a = select(valid_a, t_a, inf)
            key_b = select(valid_b, t_b, inf)
            second = key_b < key_a
            tube = select(second, valid_b, valid_a)
            t = select(second, t_b, t_a)
            u = select(second, u_b, u_a)
            # Newton failed but the curve is touched: the chord's hit (not where Newton is leaving the segment).
            leaving = (u <= 0) | (u >= 1)
            fallback = (
                chord_ok & touches & ((conv_a | conv_b) == 0) & (leaving == 0) & (chord_t >= lo) & (chord_t <= hi)
            )
            tube_ok = tube | fallback
            tube_t = select(tube, t, chord_t)
            tube_u = clip(select(tube, u, chord_u), zero, one)

    # The end spheres: a cap, or the fill of a kink at a joint (drawn by the segment that starts there).
    three = like(x0, 3.0)
    dsx = three * (x1 - x0)
    dsy = three * (y1 - y0)
    dsz = three * (z1 - z0)
    dsr = three * (r1 - r0)
    dex = three * (x3 - x2)
    dey = three * (y3 - y2)
    dez = three * (z3 - z2)
    der = three * (r3 - r2)
    start_ok, start_t = sphere_entry(x0, y0, z0, r0)
    end_ok, end_t = sphere_entry(x3, y3, z3, r3)
    start_surface = enter_slope(x0, y0, z0, r0, dsx, dsy, dsz, dsr) >= 0
    end_surface = enter_slope(x3, y3, z3, r3, dex, dey, dez, der) <= 0
    joint_open = enter_slope(x0, y0, z0, r0, pvx, pvy, pvz, pvr) <= 0
    start_accept = has_previous & joint_open
    end_accept = false_like(has_previous)
    if sphere:
        start_accept = start_accept | ((has_previous == 0) & (caps == 2))
        end_accept = end_accept | ((has_next == 0) & (caps == 2))
    start_ok = start_ok & start_accept & start_surface
    end_ok = end_ok & end_accept & end_surface
    best = nearer(tube_ok, tube_t, tube_u, PART_TUBE, false_like(has_previous), inf, zero, PART_TUBE, lo, hi)
    best = nearer(start_ok, start_t, zero, PART_SPHERE, *best, lo, hi)
    best = nearer(end_ok, end_t, one, PART_SPHERE, *best, lo, hi)
    if disk:
        fx = x3 - x0
        fy = y3 - y0
        fz = z3 - z0
        disk_ok, disk_t = end_disk(x0, y0, z0, r0, dsx, dsy, dsz, dsr, fx, fy, fz, 1.0)
        disk_ok = disk_ok & (has_previous == 0) & (caps == 1)
        best = nearer(disk_ok, disk_t, zero, PART_DISK, *best, lo, hi)
        disk_ok, disk_t = end_disk(x3, y3, z3, r3, dex, dey, dez, der, fx, fy, fz, -1.0)
        disk_ok = disk_ok & (has_next == 0) & (caps == 1)
        best = nearer(disk_ok, disk_t, one, PART_DISK, *best, lo, hi)
    return best


def ribbon_newton(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u, near, noise, lo, hi, iterations, h, tolerance):  # fmt: skip
    """``iterations`` Newton steps on ``g(u) = p . p' = 0`` from one candidate ``u`` (kept within ``h`` of it),
    and the ribbon's key there: its depth where converged onto the ribbon within ``[lo, hi]``, else ``inf``:
    ``(key, z, u)``."""
    window_lo = maximum(u - h, like(u, 0.0))
    window_hi = minimum(u + h, like(u, 1.0))
    for _ in range(iterations):
        x, dx, ddx = evaluate(cx0, cx1, cx2, cx3, u)
        y, dy, ddy = evaluate(cy0, cy1, cy2, cy3, u)
        g = x * dx + y * dy
        g_u = dx * dx + dy * dy + x * ddx + y * ddy
        step = select(g_u == 0, like(g, 0.0), div_rn(-g, select(g_u == 0, like(g, 1.0), g_u)))
        u = clip(u + step, window_lo, window_hi)
    x, dx, _ = evaluate(cx0, cx1, cx2, cx3, u)
    y, dy, _ = evaluate(cy0, cy1, cy2, cy3, u)
    z = value_at(cz0, cz1, cz2, cz3, u)
    r = value_at(cr0, cr1, cr2, cr3, u)
    speed = sqrt(dx * dx + dy * dy)
    converged = near & (absolute(x * dx + y * dy) <= (like(r, tolerance) * absolute(r) + noise) * speed)
    slack = like(u, 1e-6)
    inside = (x * x + y * y <= r * r) & (u >= -slack) & (u <= like(u, 1.0) + slack) & (z >= lo) & (z <= hi)
    key = select(converged & inside, z, like(z, INF))
    return key, z, u


def flat_test(
    x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, pvx, pvy, bits, lo, hi, noise,
    pieces, iterations, tolerance, disk, sphere,
):  # fmt: skip
    """``curve._flat``: ``(hit, t, u, part)`` of the nearest entry into the ray-facing ribbon segment in ray space
    within ``[lo, hi]`` (as :func:`round_test`)."""
    h = like(x0, 1.0 / pieces)
    zero = like(x0, 0.0)
    one = like(x0, 1.0)
    inf = like(x0, INF)
    has_previous = (bits & 1) != 0
    has_next = (bits & 2) != 0
    caps = (bits >> 2) & 3
    cx0, cx1, cx2, cx3 = power(x0, x1, x2, x3)
    cy0, cy1, cy2, cy3 = power(y0, y1, y2, y3)
    cz0, cz1, cz2, cz3 = power(z0, z1, z2, z3)
    cr0, cr1, cr2, cr3 = power(r0, r1, r2, r3)
    grow = zero
    if iterations > 0:
        grow = chord_bound(x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, pieces)

    # The candidates in the portable order (every piece, then every inner sample), each kind keeping the first
    # of its smallest keys: chord crossings without Newton, Newton's ribbon hits with it.
    piece_best = inf
    piece_t = inf
    piece_u = zero
    vertex_best = inf
    vertex_t = inf
    vertex_u = zero
    s_before = zero
    ax, ay, az, ar = sample(0, pieces, x0, x1, x2, x3, y0, y1, y2, y3, z0, z1, z2, z3, r0, r1, r2, r3)
    for i in range(pieces):
        fi = like(x0, i)
        bx, by, bz, br = sample(i + 1, pieces, x0, x1, x2, x3, y0, y1, y2, y3, z0, z1, z2, z3, r0, r1, r2, r3)
        p1x = bx - ax
        p1y = by - ay
        length2 = p1x * p1x + p1y * p1y
        s = clip(div_rn(-(ax * p1x + ay * p1y), select(length2 > 0, length2, one)), zero, one)
        qx = ax + s * p1x
        qy = ay + s * p1y
        closest2 = qx * qx + qy * qy
        reach = ar + s * (br - ar)
        u_piece = (fi + s) * h
        interior = (s > 0) & (s < 1)
        vertex2 = ax * ax + ay * ay
        kink = (s_before >= 1) & (s <= 0)  # at sample i (i > 0), the end of piece i - 1
        if iterations > 0:
            near = interior
            if i == 0:
                near = near | (s <= 0)
            if i == pieces - 1:
                near = near | (s >= 1)
            grown = reach + grow
            near = near & (closest2 <= grown * grown)
            if any_lane(near):
                key, t, u = ribbon_newton(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u_piece, near, noise, lo, hi, iterations, h, tolerance)  # fmt: skip
                take = key < piece_best
                piece_best = select(take, key, piece_best)
                piece_t = select(take, t, piece_t)
                piece_u = select(take, u, piece_u)
            if i > 0:
                vertex_grown = ar + grow
                near = kink & (vertex2 <= vertex_grown * vertex_grown)
                if any_lane(near):
                    key, t, u = ribbon_newton(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, fi * h, near, noise, lo, hi, iterations, h, tolerance)  # fmt: skip
                    take = key < vertex_best
                    vertex_best = select(take, key, vertex_best)
                    vertex_t = select(take, t, vertex_t)
                    vertex_u = select(take, u, vertex_u)
        else:
            t_piece = az + s * (bz - az)
            crossing = interior & (closest2 <= reach * reach)
            key = select(crossing & (t_piece >= lo) & (t_piece <= hi), t_piece, inf)
            take = key < piece_best
            piece_best = select(take, key, piece_best)
            piece_t = select(take, t_piece, piece_t)
            piece_u = select(take, u_piece, piece_u)
            if i > 0:
                crossing = kink & (vertex2 <= ar * ar)
                key = select(crossing & (az >= lo) & (az <= hi), az, inf)
                take = key < vertex_best
                vertex_best = select(take, key, vertex_best)
                vertex_t = select(take, az, vertex_t)
                vertex_u = select(take, fi * h, vertex_u)
        s_before = s
        ax, ay, az, ar = bx, by, bz, br
    piece_wins = piece_best <= vertex_best  # the pieces come first in the portable candidate order
    ribbon_ok = minimum(piece_best, vertex_best) < inf
    ribbon_t = select(piece_wins, piece_t, vertex_t)
    ribbon_u = select(piece_wins, piece_u, vertex_u)
    if iterations > 0:
        ribbon_u = clip(ribbon_u, zero, one)
    else:
        ribbon_ok = ribbon_ok & (ribbon_t >= lo)

    # The ends: ray-facing disks (a disk cap, or the fill of a joint the neighbours leave open) and spheres.
    three = like(x0, 3.0)
    dsx = three * (x1 - x0)
    dsy = three * (y1 - y0)
    dex = three * (x3 - x2)
    dey = three * (y3 - y2)
    start_in = x0 * x0 + y0 * y0 <= r0 * r0
    end_in = x3 * x3 + y3 * y3 <= r3 * r3
    start_free = x0 * dsx + y0 * dsy >= 0  # the ribbon's closest point lies before u = 0
    end_free = x3 * dex + y3 * dey <= 0
    joint_open = x0 * pvx + y0 * pvy <= 0
    start_disk = has_previous & joint_open
    best = nearer(ribbon_ok, ribbon_t, ribbon_u, PART_RIBBON, false_like(has_previous), inf, zero, PART_RIBBON, lo, hi)
    if disk:
        start_disk = start_disk | ((has_previous == 0) & (caps == 1))
    best = nearer(start_in & start_free & start_disk, z0, zero, PART_FACING_DISK, *best, lo, hi)
    if sphere:
        _, start_sphere_t = sphere_entry(x0, y0, z0, r0)
        start_sphere = (has_previous == 0) & (caps == 2)
        best = nearer(start_in & start_free & start_sphere, start_sphere_t, zero, PART_SPHERE, *best, lo, hi)
    if disk:
        end_disk_ok = (has_next == 0) & (caps == 1)
        best = nearer(end_in & end_free & end_disk_ok, z3, one, PART_FACING_DISK, *best, lo, hi)
    if sphere:
        _, end_sphere_t = sphere_entry(x3, y3, z3, r3)
        end_sphere = (has_next == 0) & (caps == 2)
        best = nearer(end_in & end_free & end_sphere, end_sphere_t, one, PART_SPHERE, *best, lo, hi)
    return best


def segment(
    l0x, l0y, l0z, r0, l1x, l1y, l1z, r1, l2x, l2y, l2z, r2, l3x, l3y, l3z, r3, basex, basey, basez, bits,
    vx, vy, vz, vr, ox, oy, oz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz, scale_t, t_min, t_max,
    pieces, iterations, approach, tolerance, disk, sphere, flat,
):  # fmt: skip
    """The leaf test of one packed segment (``curve.intersect``): ``(hit, distance, u, part)``, the distance in
    units of the ray direction's length (``inf`` on a miss), ``u`` the segment parameter (0 on a miss), ``part``
    the ``PART_*`` code of the part hit.

    The segment is its row of :func:`jaxrt._src.traversal.packed.pack_curves` (control points ``l`` and radii
    relative to the base point, the flags ``bits``, the predecessor's joint derivative ``v``); the ray its
    origin, frame ``e1, e2, n`` and ``scale_t = 1 / |d|`` (``curve.curve_ray``). ``flat``: 0 compiles the
    round test only, 1 the flat test only, 2 both (chosen by the segment's flat bit)."""
    x0, y0, z0, x1, y1, z1, x2, y2, z2, x3, y3, z3, pvx, pvy, pvz = ray_space(
        l0x, l0y, l0z, l1x, l1y, l1z, l2x, l2y, l2z, l3x, l3y, l3z, basex, basey, basez, vx, vy, vz,
        ox, oy, oz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz,
    )  # fmt: skip
    lo = div_rn(t_min, scale_t)
    hi = div_rn(t_max, scale_t)
    live, noise = hull_cull(x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, lo, hi, tolerance)
    if flat != 1:
        hit, t, u, part = round_test(
            x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, pvx, pvy, pvz, vr, bits, lo, hi, noise,
            pieces, iterations, approach, tolerance, disk, sphere,
        )  # fmt: skip
    if flat != 0:
        flat_hit, flat_t, flat_u, flat_part = flat_test(
            x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, pvx, pvy, bits, lo, hi, noise,
            pieces, iterations, tolerance, disk, sphere,
        )  # fmt: skip
        if flat == 1:
            hit, t, u, part = flat_hit, flat_t, flat_u, flat_part
        else:
            is_flat = (bits & 16) != 0
            hit = select(is_flat, flat_hit, hit)
            t = select(is_flat, flat_t, t)
            u = select(is_flat, flat_u, u)
            part = select(is_flat, flat_part, part)
    hit = live & hit
    return hit, select(hit, t * scale_t, like(t, INF)), select(hit, u, like(u, 0.0)), part
