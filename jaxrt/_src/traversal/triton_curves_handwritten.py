"""The former hand-written Triton port of the curve leaf test, kept only to time it against the shared formula
(:mod:`jaxrt._src.formulas.curve`, called by :func:`jaxrt._src.traversal.triton_curves.curve_leaf`): the kernel
compiles it with ``JAXRT_CURVE_LEAF=handwritten`` (:data:`jaxrt._src.traversal.triton_kernel.CURVE_LEAF`).
To be deleted with that switch once the measurement is done.

Imported only where Triton is installed (by :mod:`jaxrt._src.traversal.triton_kernel`). :func:`curve_leaf`
tests one leaf per lane against the segment in its kernel row (:func:`jaxrt._src.traversal.packed.pack_curves`)
with the formulas of ``curve.intersect`` for a round segment, written in the same order of operations: the
ray-space control points, the chord pieces as exact round cones and inner spheres, the safeguarded Newton
steps towards the closest approach, the Newton refinement of the two starts, the chord fallback, and the end
spheres and disks with the joint rules; for a flat segment (:func:`_flat_segment`, ``curve._flat``), the chord
crossings, Newton on ``p . p' = 0`` from every candidate near the polyline, and the ray-facing end disks and
spheres. Each lane walks its segment's pieces in order in a loop, keeping the
first of the smallest keys of each candidate kind (the portable ``argmin`` over the pieces), so only one piece's
values are live at a time (a ``(lanes, pieces)`` block kept every piece in registers and spilled).

Exactness: the kernel is compiled without contraction, every division is ``div_rn`` and every square root
``sqrt_rn`` (Triton's ``/`` and ``sqrt`` on float32 are approximate on CUDA), and the sample weights of the
Bernstein basis are computed in float64 and rounded once, as ``curve._bernstein`` and ``curve._combine`` round
them. Candidates are chosen as ``jnp.argmin`` chooses (the first of equal keys, in the portable order).
Where XLA evaluates the same operations in the same order the floats are the portable path's.
"""

from __future__ import annotations

import triton
import triton.language as tl

from jaxrt._src.traversal.triton_curves import CURVE_WIDTH


@triton.jit
def _div(a, b):
    return tl.math.div_rn(a, b)


@triton.jit
def _sqrt(x):
    return tl.math.sqrt_rn(x)


@triton.jit
def _diff_of_squares(a, b):
    return (a - b) * (a + b)


@triton.jit
def _evaluate(c0, c1, c2, c3, u):
    """Value, first and second derivative of one power-basis channel (``curve._evaluate``)."""
    value = c0 + u * (c1 + u * (c2 + u * c3))
    first = c1 + u * (2.0 * c2 + 3.0 * u * c3)
    second = 2.0 * c2 + 6.0 * u * c3
    return value, first, second


@triton.jit
def _value(c0, c1, c2, c3, u):
    return c0 + u * (c1 + u * (c2 + u * c3))


@triton.jit
def _power(q0, q1, q2, q3):
    """Power-basis coefficients of one channel (``curve._combine(_TO_POWER, q)``, row by row)."""
    return q0, -3.0 * q0 + 3.0 * q1, 3.0 * q0 + -6.0 * q1 + 3.0 * q2, -1.0 * q0 + 3.0 * q1 + -3.0 * q2 + q3


@triton.jit
def _weights(index, PIECES: tl.constexpr):
    """Bernstein weights of sample ``index`` (float64 ``index``, ``0..PIECES``) rounded to float32 once, as
    ``curve._bernstein`` over ``np.linspace(0, 1, PIECES + 1)``."""
    u = index * (1.0 / tl.full(index.shape, PIECES, tl.float64))
    u = tl.where(index == PIECES, 1.0, u)
    v = 1.0 - u
    w0 = (v * v * v).to(tl.float32)
    w1 = (3.0 * u * (v * v)).to(tl.float32)
    w2 = (3.0 * (u * u) * v).to(tl.float32)
    w3 = (u * u * u).to(tl.float32)
    return w0, w1, w2, w3


@triton.jit
def _combine(w0, w1, w2, w3, q0, q1, q2, q3):
    return w0 * q0 + w1 * q1 + w2 * q2 + w3 * q3


@triton.jit
def _sample(index, x0, x1, x2, x3, y0, y1, y2, y3, z0, z1, z2, z3, r0, r1, r2, r3, PIECES: tl.constexpr):
    """Ray-space sample ``(x, y, z, |r|)`` number ``index`` (``0..PIECES``) of every lane's segment."""
    w0, w1, w2, w3 = _weights(tl.zeros((1,), tl.float64) + index, PIECES)
    x = _combine(w0, w1, w2, w3, x0, x1, x2, x3)
    y = _combine(w0, w1, w2, w3, y0, y1, y2, y3)
    z = _combine(w0, w1, w2, w3, z0, z1, z2, z3)
    r = _combine(w0, w1, w2, w3, r0, r1, r2, r3)
    return x, y, z, tl.abs(r)


@triton.jit
def _enter_slope(x, y, z, r, dx, dy, dz, dr):
    """``curve._enter_slope``: sign-carrying slope of ``t_enter`` at a sphere along a derivative."""
    depth = _diff_of_squares(tl.abs(r), _sqrt(x * x + y * y))
    root = _sqrt(tl.maximum(depth, 0.0))
    return dz * root - (r * dr - x * dx - y * dy)


@triton.jit
def _sphere_entry(x, y, z, r):
    depth = _diff_of_squares(tl.abs(r), _sqrt(x * x + y * y))
    return depth >= 0, z - _sqrt(tl.maximum(depth, 0.0))


@triton.jit
def _cone(ax, ay, az, ar, bx, by, bz, br):
    """``curve._round_cone_tube``: ``(valid, t, s)`` of the round cones from ``a`` to ``b``."""
    p1x = bx - ax
    p1y = by - ay
    z1 = bz - az
    dr = br - ar
    big_a = dr * dr - (p1x * p1x + p1y * p1y)
    big_b = ar * dr - (ax * p1x + ay * p1y)
    k = z1 * z1 - big_a
    mx = dr * ax - ar * p1x
    my = dr * ay - ar * p1y
    mixed = _sqrt(mx * mx + my * my)
    cross = tl.abs(ax * p1y - ay * p1x)
    disc = _diff_of_squares(mixed, cross)
    exists = (k > 0) & (disc >= 0)
    root = z1 * _sqrt(tl.where(exists, _div(disc, tl.where(k > 0, k, 1.0)), 0.0))
    first = -big_b + root
    numerator_2 = z1 * z1 * (ar * ar - (ax * ax + ay * ay)) - big_b * big_b
    denominator_2 = k * (-big_b - root)
    same = (-big_b) * root >= 0
    num = tl.where(same, first, numerator_2)
    den = tl.where(same, big_a, denominator_2)
    ok = exists & (den != 0)
    s = tl.where(ok, _div(num, tl.where(den != 0, den, 1.0)), -1.0)
    px = ax + s * p1x
    py = ay + s * p1y
    r = tl.abs(ar + s * dr)
    depth = _diff_of_squares(r, _sqrt(px * px + py * py))
    valid = ok & (s >= 0) & (s <= 1) & (depth >= 0)
    t = az + s * z1 - _sqrt(tl.maximum(depth, 0.0))
    return valid, t, s


@triton.jit
def _entry_at(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u):
    """``t_enter(u) = z - sqrt(max(r^2 - |p|^2, 0))`` on the true cubic."""
    x = _value(cx0, cx1, cx2, cx3, u)
    y = _value(cy0, cy1, cy2, cy3, u)
    z = _value(cz0, cz1, cz2, cz3, u)
    r = _value(cr0, cr1, cr2, cr3, u)
    return z - _sqrt(tl.maximum(_diff_of_squares(tl.abs(r), _sqrt(x * x + y * y)), 0.0))


@triton.jit
def _newton(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u, t, ITERATIONS: tl.constexpr, H: tl.constexpr):  # fmt: skip
    """``ITERATIONS`` Newton steps on the tube's two equations in ``(u, t)``, kept within ``H`` of the start."""
    window_lo = tl.maximum(u - H, 0.0)
    window_hi = tl.minimum(u + H, 1.0)
    for _ in range(ITERATIONS):
        x, dx, ddx = _evaluate(cx0, cx1, cx2, cx3, u)
        y, dy, ddy = _evaluate(cy0, cy1, cy2, cy3, u)
        z, dz, ddz = _evaluate(cz0, cz1, cz2, cz3, u)
        r, dr, ddr = _evaluate(cr0, cr1, cr2, cr3, u)
        w = t - z
        f = x * x + y * y + w * w - r * r
        g = -x * dx - y * dy + w * dz + r * dr
        f_u = -2.0 * g
        f_t = 2.0 * w
        g_u = -(dx * dx + dy * dy + dz * dz) - x * ddx - y * ddy + w * ddz + dr * dr + r * ddr
        det = f_u * dz - f_t * g_u
        safe = tl.where(det == 0, 1.0, det)
        du = tl.where(det == 0, 0.0, _div(-f * dz + f_t * g, safe))
        dt = tl.where(det == 0, 0.0, _div(-f_u * g + f * g_u, safe))
        u = tl.minimum(tl.maximum(u + du, window_lo), window_hi)
        t = t + dt
    return u, t


@triton.jit
def _accept(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u, t, found, noise, lo, hi, TOLERANCE: tl.constexpr):  # fmt: skip
    """Whether a Newton result ``(u, t)`` is a converged tube entry: ``(converged, valid)``."""
    x, dx, ddx = _evaluate(cx0, cx1, cx2, cx3, u)
    y, dy, ddy = _evaluate(cy0, cy1, cy2, cy3, u)
    z, dz, ddz = _evaluate(cz0, cz1, cz2, cz3, u)
    r, dr, ddr = _evaluate(cr0, cr1, cr2, cr3, u)
    w = t - z
    speed = _sqrt(dx * dx + dy * dy + dz * dz)
    radius = tl.abs(r)
    tol = TOLERANCE * radius + noise
    off_sphere = tl.abs(_sqrt(x * x + y * y + w * w) - radius)
    off_envelope = tl.abs(-x * dx - y * dy + w * dz + r * dr)
    g_u = -(dx * dx + dy * dy + dz * dz) - x * ddx - y * ddy + w * ddz + dr * dr + r * ddr
    f = x * x + y * y + w * w - r * r
    g = -x * dx - y * dy + w * dz + r * dr
    det = -2.0 * g * dz - 2.0 * w * g_u
    remaining = _div(tl.abs(2.0 * g * g + f * g_u), tl.maximum(tl.abs(det), 1.1754943508222875e-38))
    converged = found & (off_sphere <= tol) & (off_envelope <= tol * (speed + tl.abs(dr))) & (remaining <= tol)
    slack = 1e-6
    valid = converged & (w <= 0) & (g_u <= 0) & (u >= -slack) & (u <= 1 + slack) & (t >= lo) & (t <= hi)
    return converged, valid


@triton.jit
def _disk(px, py, pz, pr, dx, dy, dz, dr, fx, fy, fz, sign):
    """``curve._disk``: entry through the flat disk spanning the tube's end circle; ``(f*)`` the fallback axis."""
    tiny = 1.1754943508222875e-38
    speed = _sqrt(dx * dx + dy * dy + dz * dz)
    moving = speed > 0
    ax = tl.where(moving, dx, fx)
    ay = tl.where(moving, dy, fy)
    az = tl.where(moving, dz, fz)
    length = tl.maximum(_sqrt(ax * ax + ay * ay + az * az), tiny)
    ax = _div(ax, length)
    ay = _div(ay, length)
    az = _div(az, length)
    radius = tl.abs(pr)
    offset = tl.minimum(tl.maximum(_div(-pr * dr, tl.maximum(speed, tiny)), -radius), radius)
    cx = px + offset * ax
    cy = py + offset * ay
    cz = pz + offset * az
    facing = sign * az > 0
    t = _div(cx * ax + cy * ay + cz * az, tl.where(az == 0, 1.0, az))
    hx = 0.0 * t - cx
    hy = 0.0 * t - cy
    hz = t - cz
    inside = hx * hx + hy * hy + hz * hz <= _diff_of_squares(radius, tl.abs(offset))
    return facing & inside, t


@triton.jit
def _nearer(ok, t, u, best_ok, best_t, best_u, lo, hi):
    """``curve._pick`` one candidate at a time: a later candidate wins only with a strictly smaller key."""
    good = ok & (t >= lo) & (t <= hi)
    key = tl.where(good, t, float("inf"))
    take = key < best_t
    return best_ok | good, tl.where(take, key, best_t), tl.where(take, u, best_u)


@triton.jit
def curve_leaf(
    curves_ptr,
    leaf,
    test,
    hit,
    distance,
    ray,
    t_min,
    t_max,
    LANES: tl.constexpr,
    PIECES: tl.constexpr,
    ITERATIONS: tl.constexpr,
    APPROACH: tl.constexpr,
    TOLERANCE: tl.constexpr,
    DISK: tl.constexpr,
    SPHERE: tl.constexpr,
    FLAT: tl.constexpr,
):
    """The leaf test's ``(hit, distance)`` with curve leaves: where ``test`` and leaf ``leaf`` is a curve (its
    row's flags have ``IS_CURVE``), the nearest entry of the lane's ray into its segment within
    ``[t_min, t_max]`` (``curve.intersect``; distance ``inf`` where not hit) replaces ``(hit, distance)``, the
    triangle test's answer (a curve leaf's triangle is degenerate: never hit).

    ``ray`` is :func:`~jaxrt._src.traversal.triton_curves.curve_ray`'s tuple; the options are ``curve.CurveOptions`` (``PIECES``, ``ITERATIONS``,
    ``APPROACH`` = ``approach_iterations``, ``TOLERANCE``),
    ``DISK``/``SPHERE`` say whether any segment has disk or sphere end caps, and ``FLAT`` which segment test is
    compiled: 0 round only, 1 flat (ray-facing ribbons) only, 2 both, chosen per row by ``FLAT_BIT``."""
    ox, oy, oz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz, scale_t = ray
    row = curves_ptr + leaf * CURVE_WIDTH
    bits = tl.load(row + 19, mask=test, other=0.0).to(tl.int32, bitcast=True)
    is_curve = test & ((bits & 32) != 0)
    if tl.max(is_curve.to(tl.int32), axis=0) > 0:
        if FLAT == 0:
            curve_hit, curve_distance = _round_segment(
                row, is_curve, bits, ox, oy, oz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz, scale_t, t_min, t_max,
                LANES, PIECES, ITERATIONS, APPROACH, TOLERANCE, DISK, SPHERE,
            )  # fmt: skip
        elif FLAT == 1:
            curve_hit, curve_distance = _flat_segment(
                row, is_curve, bits, ox, oy, oz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz, scale_t, t_min, t_max,
                LANES, PIECES, ITERATIONS, TOLERANCE, DISK, SPHERE,
            )  # fmt: skip
        else:
            flat = (bits & 16) != 0
            curve_hit, curve_distance = _round_segment(
                row, is_curve & (flat == 0), bits, ox, oy, oz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz, scale_t,
                t_min, t_max, LANES, PIECES, ITERATIONS, APPROACH, TOLERANCE, DISK, SPHERE,
            )  # fmt: skip
            flat_hit, flat_distance = _flat_segment(
                row, is_curve & flat, bits, ox, oy, oz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz, scale_t, t_min,
                t_max, LANES, PIECES, ITERATIONS, TOLERANCE, DISK, SPHERE,
            )  # fmt: skip
            curve_hit = tl.where(flat, flat_hit, curve_hit)
            curve_distance = tl.where(flat, flat_distance, curve_distance)
        hit = tl.where(is_curve, curve_hit, hit)
        distance = tl.where(is_curve, curve_distance, distance)
    return hit, distance


@triton.jit
def _to_ray(row, k: tl.constexpr, mask, bx, by, bz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz):
    """Control point ``k`` in ray space: ``_rotate((base - origin) + local, frame)`` and its radius."""
    lx = tl.load(row + 4 * k, mask=mask, other=0.0)
    ly = tl.load(row + 4 * k + 1, mask=mask, other=0.0)
    lz = tl.load(row + 4 * k + 2, mask=mask, other=0.0)
    r = tl.load(row + 4 * k + 3, mask=mask, other=0.0)
    vx = bx + lx
    vy = by + ly
    vz = bz + lz
    return vx * e1x + vy * e1y + vz * e1z, vx * e2x + vy * e2y + vz * e2z, vx * nx + vy * ny + vz * nz, r


@triton.jit
def _control_points(row, mask, ox, oy, oz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz):
    """The segment's four control points and radii in ray space, about the row's base point (row entries
    16-18): ``x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3``."""
    bx = tl.load(row + 16, mask=mask, other=0.0) - ox
    by = tl.load(row + 17, mask=mask, other=0.0) - oy
    bz = tl.load(row + 18, mask=mask, other=0.0) - oz
    x0, y0, z0, r0 = _to_ray(row, 0, mask, bx, by, bz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz)
    x1, y1, z1, r1 = _to_ray(row, 1, mask, bx, by, bz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz)
    x2, y2, z2, r2 = _to_ray(row, 2, mask, bx, by, bz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz)
    x3, y3, z3, r3 = _to_ray(row, 3, mask, bx, by, bz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz)
    return x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3


@triton.jit
def _hull_cull(x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, mask, lo, hi, TOLERANCE: tl.constexpr):
    """``(live, noise)``: the lanes of ``mask`` whose segment the round and the flat test can hit, and the
    rounding noise of the ray-space coordinates (16 eps of their scale).

    A lane is culled when its ray passes outside the control points' hull in ray space grown by the largest
    radius (with the Newton tolerance and the rounding of the evaluations), or when the hull lies beyond the
    interval. Every hit either test can accept (chord, Newton, fallback, cap, joint; a ribbon's cross-section
    has half-width ``|r(u)|``) lies within that reach of the hull, so culled lanes are misses of the test too.
    """
    position_scale = tl.maximum(
        tl.maximum(tl.maximum(tl.maximum(tl.abs(x0), tl.abs(y0)), tl.maximum(tl.abs(z0), tl.abs(x1))),
                   tl.maximum(tl.maximum(tl.abs(y1), tl.abs(z1)), tl.maximum(tl.abs(x2), tl.abs(y2)))),
        tl.maximum(tl.maximum(tl.abs(z2), tl.abs(x3)), tl.maximum(tl.abs(y3), tl.abs(z3))),
    )  # fmt: skip
    radius_scale = tl.maximum(tl.maximum(tl.abs(r0), tl.abs(r1)), tl.maximum(tl.abs(r2), tl.abs(r3)))
    noise = 1.9073486328125e-06 * (position_scale + radius_scale)
    reach = radius_scale * (1.0 + 2.0 * TOLERANCE) + 8.0 * noise
    min_x = tl.minimum(tl.minimum(x0, x1), tl.minimum(x2, x3))
    max_x = tl.maximum(tl.maximum(x0, x1), tl.maximum(x2, x3))
    min_y = tl.minimum(tl.minimum(y0, y1), tl.minimum(y2, y3))
    max_y = tl.maximum(tl.maximum(y0, y1), tl.maximum(y2, y3))
    min_z = tl.minimum(tl.minimum(z0, z1), tl.minimum(z2, z3))
    max_z = tl.maximum(tl.maximum(z0, z1), tl.maximum(z2, z3))
    outside = (min_x > reach) | (max_x < -reach) | (min_y > reach) | (max_y < -reach)
    outside = outside | (min_z - reach > hi) | (max_z + reach < lo)
    live = mask & (outside == 0)
    return live, noise


@triton.jit
def _chord_bound(
    x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, LANES: tl.constexpr, PIECES: tl.constexpr
):
    """``curve._chord_bound``: how far the curve (radius included) strays from its chords, ``0.75 h^2`` times
    the largest second difference of the control points (``h = 1 / PIECES``)."""
    sx = x0 - 2.0 * x1 + x2
    sy = y0 - 2.0 * y1 + y2
    sz = z0 - 2.0 * z1 + z2
    tx = x1 - 2.0 * x2 + x3
    ty = y1 - 2.0 * y2 + y3
    tz = z1 - 2.0 * z2 + z3
    position = tl.maximum(_sqrt(sx * sx + sy * sy + sz * sz), _sqrt(tx * tx + ty * ty + tz * tz))
    radius = tl.maximum(tl.abs(r0 - 2.0 * r1 + r2), tl.abs(r1 - 2.0 * r2 + r3))
    return _div(0.75 * (position + radius), tl.full((LANES,), PIECES * PIECES, tl.float32))


@triton.jit
def _round_segment(
    row, mask, bits, ox, oy, oz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz, scale_t, t_min, t_max,
    LANES: tl.constexpr, PIECES: tl.constexpr, ITERATIONS: tl.constexpr,
    APPROACH: tl.constexpr, TOLERANCE: tl.constexpr, DISK: tl.constexpr, SPHERE: tl.constexpr,
):  # fmt: skip
    H = 1.0 / PIECES
    x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3 = _control_points(
        row, mask, ox, oy, oz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz
    )
    vx = tl.load(row + 20, mask=mask, other=0.0)
    vy = tl.load(row + 21, mask=mask, other=0.0)
    vz = tl.load(row + 22, mask=mask, other=0.0)
    pvr = tl.load(row + 23, mask=mask, other=0.0)
    pvx = vx * e1x + vy * e1y + vz * e1z
    pvy = vx * e2x + vy * e2y + vz * e2z
    pvz = vx * nx + vy * ny + vz * nz
    lo = _div(t_min, scale_t)
    hi = _div(t_max, scale_t)
    has_previous = (bits & 1) != 0
    has_next = (bits & 2) != 0
    caps = (bits >> 2) & 3
    live, noise = _hull_cull(x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, mask, lo, hi, TOLERANCE)
    hit = tl.zeros((LANES,), tl.int1)
    distance = tl.full((LANES,), float("inf"), tl.float32)
    if tl.max(live.to(tl.int32), axis=0) > 0:
        cx0, cx1, cx2, cx3 = _power(x0, x1, x2, x3)
        cy0, cy1, cy2, cy3 = _power(y0, y1, y2, y3)
        cz0, cz1, cz2, cz3 = _power(z0, z1, z2, z3)
        cr0, cr1, cr2, cr3 = _power(r0, r1, r2, r3)

        if ITERATIONS > 0:
            grow = _chord_bound(x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, LANES, PIECES)
            # The margin: twice the largest sample radius plus the chord bound.
            largest = tl.full((LANES,), float("-inf"), tl.float32)
            for i in range(PIECES + 1):
                w0, w1, w2, w3 = _weights(tl.zeros((1,), tl.float64) + i, PIECES)
                largest = tl.maximum(largest, tl.abs(_combine(w0, w1, w2, w3, r0, r1, r2, r3)))
            margin = 2.0 * (largest + grow)
        else:
            grow = tl.zeros((LANES,), tl.float32)
            margin = tl.zeros((LANES,), tl.float32)
        low = lo - margin

        # The pieces in order, each candidate kept where it is the first of the smallest key (``jnp.argmin``; the
        # values of piece 0 where none is valid, as the portable gather reads them).
        cone_best = tl.full((LANES,), float("inf"), tl.float32)
        cone_t = cone_best
        cone_u = tl.zeros((LANES,), tl.float32)
        sphere_best = cone_best
        sphere_t = cone_best
        sphere_u = cone_u
        touch_best = cone_best
        t_entry = cone_best
        u_entry = cone_u
        touches = tl.zeros((LANES,), tl.int1)
        px, py, pz, pr = _sample(0, x0, x1, x2, x3, y0, y1, y2, y3, z0, z1, z2, z3, r0, r1, r2, r3, PIECES)
        ax, ay, az, ar = px, py, pz, pr
        for i in range(PIECES):
            fi = i * 1.0
            bx, by, bz, br = _sample(i + 1, x0, x1, x2, x3, y0, y1, y2, y3, z0, z1, z2, z3, r0, r1, r2, r3, PIECES)
            # The chord: the exact entry of the round cone from sample i to i + 1.
            valid, t, s = _cone(ax, ay, az, ar, bx, by, bz, br)
            key = tl.where(valid & (t >= low) & (t <= hi), t, float("inf"))
            take = (key < cone_best) | (i == 0)
            cone_best = tl.where(take, key, cone_best)
            cone_t = tl.where(take, t, cone_t)
            cone_u = tl.where(take, (fi + s) * H, cone_u)
            if i > 0:
                # The inner sphere at sample i, on the chords' surface only where it fills a kink.
                ok, t = _sphere_entry(ax, ay, az, ar)
                before = _enter_slope(ax, ay, az, ar, ax - px, ay - py, az - pz, ar - pr)
                after = _enter_slope(ax, ay, az, ar, bx - ax, by - ay, bz - az, br - ar)
                ok = ok & (before <= 0) & (after >= 0)
                key = tl.where(ok & (t >= low) & (t <= hi), t, float("inf"))
                take = (key < sphere_best) | (i == 1)
                sphere_best = tl.where(take, key, sphere_best)
                sphere_t = tl.where(take, t, sphere_t)
                sphere_u = tl.where(take, fi * H, sphere_u)
            if ITERATIONS > 0:
                # Newton towards the ray's closest approach to the true curve near this piece, where its chord passes
                # within the chord bound of the ray: whether the curve is touched, and an entry estimate.
                p1x = bx - ax
                p1y = by - ay
                length2 = p1x * p1x + p1y * p1y
                s = tl.minimum(tl.maximum(_div(-(ax * p1x + ay * p1y), tl.where(length2 > 0, length2, 1.0)), 0.0), 1.0)
                reach = ar + s * (br - ar) + grow
                qx = ax + s * p1x
                qy = ay + s * p1y
                near = qx * qx + qy * qy <= reach * reach
                u = (fi + s) * H
                a = tl.minimum(tl.maximum(u - H, 0.0), 1.0)
                b = tl.minimum(tl.maximum(u + H, 0.0), 1.0)
                for _ in range(APPROACH):
                    # Safeguarded Newton on h(u) = p . p' - r r' in the bracket [a, b] (bisection where it leaves it).
                    x, dx, ddx = _evaluate(cx0, cx1, cx2, cx3, u)
                    y, dy, ddy = _evaluate(cy0, cy1, cy2, cy3, u)
                    r, dr, ddr = _evaluate(cr0, cr1, cr2, cr3, u)
                    value = x * dx + y * dy - r * dr
                    slope = dx * dx + dy * dy + x * ddx + y * ddy - dr * dr - r * ddr
                    a = tl.where(value < 0, u, a)
                    b = tl.where(value > 0, u, b)
                    step = u - _div(value, tl.where(slope > 0, slope, 1.0))
                    good = (slope > 0) & (step >= a) & (step <= b)
                    u = tl.where(good, step, 0.5 * (a + b))
                # The closest of the iterate and the bracket's ends (the first on ties).
                x = _value(cx0, cx1, cx2, cx3, u)
                y = _value(cy0, cy1, cy2, cy3, u)
                r = _value(cr0, cr1, cr2, cr3, u)
                best = x * x + y * y - r * r
                u_close = u
                x = _value(cx0, cx1, cx2, cx3, a)
                y = _value(cy0, cy1, cy2, cy3, a)
                r = _value(cr0, cr1, cr2, cr3, a)
                gap = x * x + y * y - r * r
                u_close = tl.where(gap < best, a, u_close)
                best = tl.minimum(gap, best)
                x = _value(cx0, cx1, cx2, cx3, b)
                y = _value(cy0, cy1, cy2, cy3, b)
                r = _value(cr0, cr1, cr2, cr3, b)
                gap = x * x + y * y - r * r
                u_close = tl.where(gap < best, b, u_close)
                x, dx, _ = _evaluate(cx0, cx1, cx2, cx3, u_close)
                y, dy, _ = _evaluate(cy0, cy1, cy2, cy3, u_close)
                z, dz, _ = _evaluate(cz0, cz1, cz2, cz3, u_close)
                r = _value(cr0, cr1, cr2, cr3, u_close)
                depth = _diff_of_squares(tl.abs(r), _sqrt(x * x + y * y))
                touching = near & (depth >= -2.0 * noise * (tl.abs(r) + noise))
                across2 = dx * dx + dy * dy
                shift = _div(
                    -dz * _sqrt(tl.maximum(depth, 0.0)), _sqrt(tl.maximum(across2 * (across2 + dz * dz), 1e-30))
                )
                u_try = tl.minimum(tl.maximum(u_close + tl.minimum(tl.maximum(shift, -H), H), 0.0), 1.0)
                t_try = _entry_at(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u_try)
                key = tl.where(touching & (t_try >= low) & (t_try <= hi), t_try, float("inf"))
                take = (key < touch_best) | (i == 0)
                touch_best = tl.where(take, key, touch_best)
                t_entry = tl.where(take, t_try, t_entry)
                u_entry = tl.where(take, u_try, u_entry)
                touches = touches | touching
            px, py, pz, pr = ax, ay, az, ar
            ax, ay, az, ar = bx, by, bz, br
        cone_wins = cone_best <= sphere_best  # the cones come first in the portable candidate order
        chord_ok = tl.minimum(cone_best, sphere_best) < float("inf")
        chord_t = tl.where(cone_wins, cone_t, sphere_t)
        chord_u = tl.where(cone_wins, cone_u, sphere_u)

        if ITERATIONS > 0:
            touch_ok = touch_best < float("inf")
            found = chord_ok | touch_ok
            t_chord = _entry_at(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, chord_u)
            # Two starts refined side by side: the chord's hit and the entry through the closest approach.
            u_a = tl.where(chord_ok, chord_u, u_entry)
            t_a = tl.where(chord_ok, t_chord, t_entry)
            u_a, t_a = _newton(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u_a, t_a, ITERATIONS, H)  # fmt: skip
            u_b, t_b = _newton(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u_entry, t_entry, ITERATIONS, H)  # fmt: skip
            conv_a, valid_a = _accept(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u_a, t_a, found, noise, lo, hi, TOLERANCE)  # fmt: skip
            conv_b, valid_b = _accept(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u_b, t_b, found, noise, lo, hi, TOLERANCE)  # fmt: skip
            key_a = tl.where(valid_a, t_a, float("inf"))
            key_b = tl.where(valid_b, t_b, float("inf"))
            second = key_b < key_a
            tube = tl.where(second, valid_b, valid_a)
            t = tl.where(second, t_b, t_a)
            u = tl.where(second, u_b, u_a)
            # Newton failed but the curve is touched: the chord's hit (not where Newton is leaving the segment).
            leaving = (u <= 0) | (u >= 1)
            fallback = (
                chord_ok & touches & ((conv_a | conv_b) == 0) & (leaving == 0) & (chord_t >= lo) & (chord_t <= hi)
            )
            tube_ok = tube | fallback
            tube_t = tl.where(tube, t, chord_t)
            tube_u = tl.minimum(tl.maximum(tl.where(tube, u, chord_u), 0.0), 1.0)
        else:
            tube_ok = chord_ok & (chord_t >= lo)
            tube_t = chord_t
            tube_u = chord_u

        # The end spheres: a cap, or the fill of a kink at a joint (drawn by the segment that starts there).
        dsx = 3.0 * (x1 - x0)
        dsy = 3.0 * (y1 - y0)
        dsz = 3.0 * (z1 - z0)
        dsr = 3.0 * (r1 - r0)
        dex = 3.0 * (x3 - x2)
        dey = 3.0 * (y3 - y2)
        dez = 3.0 * (z3 - z2)
        der = 3.0 * (r3 - r2)
        start_ok, start_t = _sphere_entry(x0, y0, z0, r0)
        end_ok, end_t = _sphere_entry(x3, y3, z3, r3)
        start_surface = _enter_slope(x0, y0, z0, r0, dsx, dsy, dsz, dsr) >= 0
        end_surface = _enter_slope(x3, y3, z3, r3, dex, dey, dez, der) <= 0
        joint_open = _enter_slope(x0, y0, z0, r0, pvx, pvy, pvz, pvr) <= 0
        start_accept = has_previous & joint_open
        end_accept = tl.zeros((LANES,), tl.int1)
        if SPHERE:
            start_accept = start_accept | ((has_previous == 0) & (caps == 2))
            end_accept = end_accept | ((has_next == 0) & (caps == 2))
        start_ok = start_ok & start_accept & start_surface
        end_ok = end_ok & end_accept & end_surface
        best_ok = tl.zeros((LANES,), tl.int1)
        best_t = tl.full((LANES,), float("inf"), tl.float32)
        best_u = tl.zeros((LANES,), tl.float32)
        best_ok, best_t, best_u = _nearer(tube_ok, tube_t, tube_u, best_ok, best_t, best_u, lo, hi)
        best_ok, best_t, best_u = _nearer(start_ok, start_t, 0.0, best_ok, best_t, best_u, lo, hi)
        best_ok, best_t, best_u = _nearer(end_ok, end_t, 1.0, best_ok, best_t, best_u, lo, hi)
        if DISK:
            fx = x3 - x0
            fy = y3 - y0
            fz = z3 - z0
            disk_ok, disk_t = _disk(x0, y0, z0, r0, dsx, dsy, dsz, dsr, fx, fy, fz, 1.0)
            disk_ok = disk_ok & (has_previous == 0) & (caps == 1)
            best_ok, best_t, best_u = _nearer(disk_ok, disk_t, 0.0, best_ok, best_t, best_u, lo, hi)
            disk_ok, disk_t = _disk(x3, y3, z3, r3, dex, dey, dez, der, fx, fy, fz, -1.0)
            disk_ok = disk_ok & (has_next == 0) & (caps == 1)
            best_ok, best_t, best_u = _nearer(disk_ok, disk_t, 1.0, best_ok, best_t, best_u, lo, hi)
        hit = live & best_ok
        distance = tl.where(hit, best_t * scale_t, float("inf"))
    return hit, distance


@triton.jit
def _ribbon_newton(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u, near, noise, lo, hi, ITERATIONS: tl.constexpr, H: tl.constexpr, TOLERANCE: tl.constexpr):  # fmt: skip
    """``ITERATIONS`` Newton steps on ``g(u) = p . p' = 0`` from one candidate ``u`` (kept within ``H`` of it), and
    the ribbon's key there: its depth where converged onto the ribbon within ``[lo, hi]``, else ``inf``."""
    window_lo = tl.maximum(u - H, 0.0)
    window_hi = tl.minimum(u + H, 1.0)
    for _ in range(ITERATIONS):
        x, dx, ddx = _evaluate(cx0, cx1, cx2, cx3, u)
        y, dy, ddy = _evaluate(cy0, cy1, cy2, cy3, u)
        g = x * dx + y * dy
        g_u = dx * dx + dy * dy + x * ddx + y * ddy
        step = tl.where(g_u == 0, 0.0, _div(-g, tl.where(g_u == 0, 1.0, g_u)))
        u = tl.minimum(tl.maximum(u + step, window_lo), window_hi)
    x, dx, _ = _evaluate(cx0, cx1, cx2, cx3, u)
    y, dy, _ = _evaluate(cy0, cy1, cy2, cy3, u)
    z = _value(cz0, cz1, cz2, cz3, u)
    r = _value(cr0, cr1, cr2, cr3, u)
    speed = _sqrt(dx * dx + dy * dy)
    converged = near & (tl.abs(x * dx + y * dy) <= (TOLERANCE * tl.abs(r) + noise) * speed)
    slack = 1e-6
    inside = (x * x + y * y <= r * r) & (u >= -slack) & (u <= 1 + slack) & (z >= lo) & (z <= hi)
    key = tl.where(converged & inside, z, float("inf"))
    return key, z, u


@triton.jit
def _flat_segment(
    row, mask, bits, ox, oy, oz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz, scale_t, t_min, t_max,
    LANES: tl.constexpr, PIECES: tl.constexpr, ITERATIONS: tl.constexpr,
    TOLERANCE: tl.constexpr, DISK: tl.constexpr, SPHERE: tl.constexpr,
):  # fmt: skip
    """``curve._flat``: the nearest entry into the lanes' ray-facing ribbon segments (``(hit, distance)``)."""
    H = 1.0 / PIECES
    x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3 = _control_points(
        row, mask, ox, oy, oz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz
    )
    vx = tl.load(row + 20, mask=mask, other=0.0)
    vy = tl.load(row + 21, mask=mask, other=0.0)
    vz = tl.load(row + 22, mask=mask, other=0.0)
    pvx = vx * e1x + vy * e1y + vz * e1z
    pvy = vx * e2x + vy * e2y + vz * e2z
    lo = _div(t_min, scale_t)
    hi = _div(t_max, scale_t)
    has_previous = (bits & 1) != 0
    has_next = (bits & 2) != 0
    caps = (bits >> 2) & 3
    live, noise = _hull_cull(x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, mask, lo, hi, TOLERANCE)
    hit = tl.zeros((LANES,), tl.int1)
    distance = tl.full((LANES,), float("inf"), tl.float32)
    if tl.max(live.to(tl.int32), axis=0) > 0:
        cx0, cx1, cx2, cx3 = _power(x0, x1, x2, x3)
        cy0, cy1, cy2, cy3 = _power(y0, y1, y2, y3)
        cz0, cz1, cz2, cz3 = _power(z0, z1, z2, z3)
        cr0, cr1, cr2, cr3 = _power(r0, r1, r2, r3)
        if ITERATIONS > 0:
            grow = _chord_bound(x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, LANES, PIECES)
        else:
            grow = tl.zeros((LANES,), tl.float32)

        # The candidates in the portable order (every piece, then every inner sample), each kind keeping the
        # first of its smallest keys: chord crossings without Newton, Newton's ribbon hits with it.
        piece_best = tl.full((LANES,), float("inf"), tl.float32)
        piece_t = piece_best
        piece_u = tl.zeros((LANES,), tl.float32)
        vertex_best = piece_best
        vertex_t = piece_best
        vertex_u = piece_u
        s_before = piece_u
        ax, ay, az, ar = _sample(0, x0, x1, x2, x3, y0, y1, y2, y3, z0, z1, z2, z3, r0, r1, r2, r3, PIECES)
        for i in range(PIECES):
            fi = i * 1.0
            bx, by, bz, br = _sample(i + 1, x0, x1, x2, x3, y0, y1, y2, y3, z0, z1, z2, z3, r0, r1, r2, r3, PIECES)
            p1x = bx - ax
            p1y = by - ay
            length2 = p1x * p1x + p1y * p1y
            s = tl.minimum(tl.maximum(_div(-(ax * p1x + ay * p1y), tl.where(length2 > 0, length2, 1.0)), 0.0), 1.0)
            qx = ax + s * p1x
            qy = ay + s * p1y
            closest2 = qx * qx + qy * qy
            reach = ar + s * (br - ar)
            u_piece = (fi + s) * H
            interior = (s > 0) & (s < 1)
            vertex2 = ax * ax + ay * ay
            kink = (s_before >= 1) & (s <= 0)  # at sample i (i > 0), the end of piece i - 1
            if ITERATIONS > 0:
                near = interior
                if i == 0:
                    near = near | (s <= 0)
                if i == PIECES - 1:
                    near = near | (s >= 1)
                grown = reach + grow
                near = live & near & (closest2 <= grown * grown)
                if tl.max(near.to(tl.int32), axis=0) > 0:
                    key, t, u = _ribbon_newton(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, u_piece, near, noise, lo, hi, ITERATIONS, H, TOLERANCE)  # fmt: skip
                    take = key < piece_best
                    piece_best = tl.where(take, key, piece_best)
                    piece_t = tl.where(take, t, piece_t)
                    piece_u = tl.where(take, u, piece_u)
                if i > 0:
                    vertex_grown = ar + grow
                    near = live & kink & (vertex2 <= vertex_grown * vertex_grown)
                    if tl.max(near.to(tl.int32), axis=0) > 0:
                        key, t, u = _ribbon_newton(cx0, cx1, cx2, cx3, cy0, cy1, cy2, cy3, cz0, cz1, cz2, cz3, cr0, cr1, cr2, cr3, fi * H + tl.zeros((LANES,), tl.float32), near, noise, lo, hi, ITERATIONS, H, TOLERANCE)  # fmt: skip
                        take = key < vertex_best
                        vertex_best = tl.where(take, key, vertex_best)
                        vertex_t = tl.where(take, t, vertex_t)
                        vertex_u = tl.where(take, u, vertex_u)
            else:
                t_piece = az + s * (bz - az)
                crossing = interior & (closest2 <= reach * reach)
                key = tl.where(crossing & (t_piece >= lo) & (t_piece <= hi), t_piece, float("inf"))
                take = key < piece_best
                piece_best = tl.where(take, key, piece_best)
                piece_t = tl.where(take, t_piece, piece_t)
                piece_u = tl.where(take, u_piece, piece_u)
                if i > 0:
                    crossing = kink & (vertex2 <= ar * ar)
                    key = tl.where(crossing & (az >= lo) & (az <= hi), az, float("inf"))
                    take = key < vertex_best
                    vertex_best = tl.where(take, key, vertex_best)
                    vertex_t = tl.where(take, az, vertex_t)
                    vertex_u = tl.where(take, fi * H, vertex_u)
            s_before = s
            ax, ay, az, ar = bx, by, bz, br
        piece_wins = piece_best <= vertex_best  # the pieces come first in the portable candidate order
        ribbon_ok = tl.minimum(piece_best, vertex_best) < float("inf")
        ribbon_t = tl.where(piece_wins, piece_t, vertex_t)
        ribbon_u = tl.where(piece_wins, piece_u, vertex_u)
        if ITERATIONS > 0:
            ribbon_u = tl.minimum(tl.maximum(ribbon_u, 0.0), 1.0)
        else:
            ribbon_ok = ribbon_ok & (ribbon_t >= lo)

        # The ends: ray-facing disks (a disk cap, or the fill of a joint the neighbours leave open) and spheres.
        dsx = 3.0 * (x1 - x0)
        dsy = 3.0 * (y1 - y0)
        dex = 3.0 * (x3 - x2)
        dey = 3.0 * (y3 - y2)
        start_in = x0 * x0 + y0 * y0 <= r0 * r0
        end_in = x3 * x3 + y3 * y3 <= r3 * r3
        start_free = x0 * dsx + y0 * dsy >= 0  # the ribbon's closest point lies before u = 0
        end_free = x3 * dex + y3 * dey <= 0
        joint_open = x0 * pvx + y0 * pvy <= 0
        start_disk = has_previous & joint_open
        best_ok = tl.zeros((LANES,), tl.int1)
        best_t = tl.full((LANES,), float("inf"), tl.float32)
        best_u = tl.zeros((LANES,), tl.float32)
        best_ok, best_t, best_u = _nearer(ribbon_ok, ribbon_t, ribbon_u, best_ok, best_t, best_u, lo, hi)
        if DISK:
            start_disk = start_disk | ((has_previous == 0) & (caps == 1))
        best_ok, best_t, best_u = _nearer(start_in & start_free & start_disk, z0, 0.0, best_ok, best_t, best_u, lo, hi)
        if SPHERE:
            _, start_sphere_t = _sphere_entry(x0, y0, z0, r0)
            start_sphere = (has_previous == 0) & (caps == 2)
            best_ok, best_t, best_u = _nearer(start_in & start_free & start_sphere, start_sphere_t, 0.0, best_ok, best_t, best_u, lo, hi)  # fmt: skip
        if DISK:
            end_disk = (has_next == 0) & (caps == 1)
            best_ok, best_t, best_u = _nearer(end_in & end_free & end_disk, z3, 1.0, best_ok, best_t, best_u, lo, hi)
        if SPHERE:
            _, end_sphere_t = _sphere_entry(x3, y3, z3, r3)
            end_sphere = (has_next == 0) & (caps == 2)
            best_ok, best_t, best_u = _nearer(end_in & end_free & end_sphere, end_sphere_t, 1.0, best_ok, best_t, best_u, lo, hi)  # fmt: skip
        hit = live & best_ok
        distance = tl.where(hit, best_t * scale_t, float("inf"))
    return hit, distance
