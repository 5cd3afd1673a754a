"""The point of a triangle closest to a point, one formula for every backend.

Reference: Ericson, *Real-Time Collision Detection* (2005), section 5.1.5. The point's Voronoi region of the
triangle (three vertices, three edges, the face) is found from six dot products; every division is guarded, so
zero-length edges and collinear (zero-area) triangles give the closest point of their segment or vertex
instead of a NaN. Barycentrics follow Metal: the point is ``(1 - u - v) v0 + u v1 + v v2``.

Also the squared distance to a box (the walks' pruning bound and the bounding-box kind's distance) and a
triangle's signed solid angle (Van Oosterom and Strackee, "The Solid Angle of a Plane Triangle", IEEE Trans.
Biomed. Eng. 30(2), 1983, the ``atan2`` form), the leaf term of winding numbers.
"""

from __future__ import annotations

from jaxrt._src.formulas.vocabulary import atan2, div_rn, dot3, like, maximum, minimum, select, sqrt

__all__ = ["ratio", "closest_on_triangle", "triangle_point", "box_gap", "squared_box_distance", "solid_angle"]


def ratio(num, den):
    """``num / den`` clamped to ``[0, 1]``, and 0 where ``den`` is 0 (no NaN value or gradient)."""
    ok = den != 0
    q = select(ok, div_rn(num, select(ok, den, like(den, 1.0))), like(num, 0.0))
    return minimum(maximum(q, like(q, 0.0)), like(q, 1.0))


def closest_on_triangle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """The barycentrics ``(u, v)`` of the point of triangle ``(a, b, c)`` closest to ``p``."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    d1 = dot3(abx, aby, abz, px - ax, py - ay, pz - az)
    d2 = dot3(acx, acy, acz, px - ax, py - ay, pz - az)
    d3 = dot3(abx, aby, abz, px - bx, py - by, pz - bz)
    d4 = dot3(acx, acy, acz, px - bx, py - by, pz - bz)
    d5 = dot3(abx, aby, abz, px - cx, py - cy, pz - cz)
    d6 = dot3(acx, acy, acz, px - cx, py - cy, pz - cz)
    # Signed areas (times |n|^2) of the sub-triangles opposite each vertex (Ericson 5.1.5).
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    in_a = (d1 <= 0) & (d2 <= 0)
    in_b = (d3 >= 0) & (d4 <= d3)
    in_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    in_c = (d6 >= 0) & (d5 <= d6)
    in_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    in_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    t_ab = ratio(d1, d1 - d3)
    t_ac = ratio(d2, d2 - d6)
    t_bc = ratio(d4 - d3, (d4 - d3) + (d5 - d6))
    area = va + vb + vc
    face_ok = area > 0
    safe_area = select(face_ok, area, like(area, 1.0))
    zero = like(d1, 0.0)
    one = like(d1, 1.0)
    face_u = select(face_ok, div_rn(vb, safe_area), zero)
    face_v = select(face_ok, div_rn(vc, safe_area), zero)
    # The regions in Ericson's order: the first that holds wins.
    u = select(in_bc, one - t_bc, face_u)
    u = select(in_ac, zero, u)
    u = select(in_c, zero, u)
    u = select(in_ab, t_ab, u)
    u = select(in_b, one, u)
    u = select(in_a, zero, u)
    v = select(in_bc, t_bc, face_v)
    v = select(in_ac, t_ac, v)
    v = select(in_c, one, v)
    v = select(in_a | in_b | in_ab, zero, v)
    return u, v


def triangle_point(ax, ay, az, bx, by, bz, cx, cy, cz, u, v):
    """``a + u (b - a) + v (c - a)``: the point of barycentrics ``(u, v)``."""
    return ax + u * (bx - ax) + v * (cx - ax), ay + u * (by - ay) + v * (cy - ay), az + u * (bz - az) + v * (cz - az)


def box_gap(p, lo, hi):
    """How far coordinate ``p`` lies outside ``[lo, hi]`` (0 inside; ``inf`` for an empty interval)."""
    return maximum(maximum(lo - p, p - hi), like(p, 0.0))


def squared_box_distance(px, py, pz, lx, ly, lz, hx, hy, hz):
    """Squared distance from ``p`` to the solid box ``[l, h]`` (``inf`` for an empty box, lower above upper)."""
    gx, gy, gz = box_gap(px, lx, hx), box_gap(py, ly, hy), box_gap(pz, lz, hz)
    return dot3(gx, gy, gz, gx, gy, gz)


def solid_angle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """The signed solid angle of triangle ``(a, b, c)`` seen from ``p``, positive when its counterclockwise
    normal points away from ``p``; 0 in the triangle's plane (or for a triangle without area)."""
    ax, ay, az = ax - px, ay - py, az - pz
    bx, by, bz = bx - px, by - py, bz - pz
    cx, cy, cz = cx - px, cy - py, cz - pz
    la, lb, lc = (
        sqrt(dot3(ax, ay, az, ax, ay, az)),
        sqrt(dot3(bx, by, bz, bx, by, bz)),
        sqrt(dot3(cx, cy, cz, cx, cy, cz)),
    )
    det = dot3(ax, ay, az, by * cz - bz * cy, bz * cx - bx * cz, bx * cy - by * cx)
    den = la * lb * lc + dot3(ax, ay, az, bx, by, bz) * lc + dot3(ax, ay, az, cx, cy, cz) * lb
    den = den + dot3(bx, by, bz, cx, cy, cz) * la
    return select(det == 0, like(det, 0.0), like(det, 2.0) * atan2(det, den))
