"""The watertight ray/triangle test (Woop, Benthin, Wald 2013), one formula for every backend.

Reference: Woop, Benthin, Wald, "Watertight Ray/Triangle Intersection", JCGT 2(1), 2013. The ray is sheared so
that it runs along +z through the origin (:func:`shear_axes`, :func:`shear`); the vertices relative to the
origin, read in the ray's axis order ``(kx, ky, kz)``, are sheared (:func:`sheared_vertex`); the three 2D edge
functions are computed from the sheared vertices alone (:func:`edge_functions`), so an edge shared by two
triangles gives the same value with opposite sign in both and no ray passes between them. Zero edge functions
count as inside (:func:`edges_inside`).

Each edge function ``a b - c d`` is the difference of two products rounded separately, and a bit more
(:func:`~jaxrt._src.formulas.vocabulary.rounded_product`): rounding is monotonic, so it has the exact sign of
the real value or is zero, whatever a compiler contracts; XLA would otherwise fuse it into
``fma(a, b, -c d)``, whose sign can be wrong when the products nearly cancel.

Winding: seen from the ray origin looking along the ray, a triangle ``(v0, v1, v2)`` is clockwise when
``det < 0``.
"""

from __future__ import annotations

from jaxrt._src.formulas.vocabulary import (
    absolute,
    div,
    div_rn,
    like,
    rounded_product,
    select,
    sub_product,
    sum_of_products,
)

__all__ = [
    "shear_axes",
    "shear",
    "sheared_vertex",
    "edge_functions",
    "edges_inside",
    "facing_accepts",
    "plane_distance",
    "in_interval",
]


def shear_axes(dx, dy, dz):
    """The ray's axis order ``(kx, ky, kz)``: ``kz`` the dominant axis of the direction, ``kx, ky`` the next two
    cyclically, swapped when the dominant component is negative (to keep the winding)."""
    ax = absolute(dx)
    ay = absolute(dy)
    az = absolute(dz)
    kz = select(ax >= ay, select(ax >= az, 0, 2), select(ay >= az, 1, 2))
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    d_z = select(kz == 0, dx, select(kz == 1, dy, dz))
    swap = d_z < 0
    return select(swap, ky, kx), select(swap, kx, ky), kz


def shear(d_x, d_y, d_z):
    """The shear ``(Sx, Sy, Sz) = (d_x / d_z, d_y / d_z, 1 / d_z)`` of the direction's components in the ray's
    axis order, divided as XLA divides on the device (:func:`~jaxrt._src.formulas.vocabulary.div`); a zero
    ``d_z`` (a zero direction) divides by 1."""
    safe = select(d_z == 0, like(d_z, 1.0), d_z)
    return div(d_x, safe), div(d_y, safe), div(like(d_z, 1.0), safe)


def sheared_vertex(r_x, r_y, r_z, sx, sy, sz):
    """A vertex relative to the ray origin, its components in the ray's axis order, sheared: ``(x, y, z)``."""
    return sub_product(r_x, sx, r_z), sub_product(r_y, sy, r_z), sz * r_z


def edge_functions(ax, ay, bx, by, cx, cy):
    """The sheared 2D edge functions ``(e0, e1, e2)`` (the weights of ``v0, v1, v2``) of sheared vertices."""
    e0 = rounded_product(cx, by) - rounded_product(cy, bx)
    e1 = rounded_product(ax, cy) - rounded_product(ay, cx)
    e2 = rounded_product(bx, ay) - rounded_product(by, ax)
    return e0, e1, e2


def edges_inside(e0, e1, e2):
    """``(inside, det)``: no two edge functions of opposite sign (zero counts as inside) and a non-zero
    determinant ``det = e0 + e1 + e2`` (a degenerate triangle, zero-area after projection, never hits)."""
    negative = (e0 < 0) | (e1 < 0) | (e2 < 0)
    positive = (e0 > 0) | (e1 > 0) | (e2 > 0)
    det = e0 + e1 + e2
    return ((negative & positive) == 0) & (det != 0), det


def facing_accepts(det, sense):
    """Whether the cull sense ``sense`` accepts a triangle of determinant ``det``: ``+1`` culls clockwise
    (``det < 0``) triangles, ``-1`` counterclockwise ones, ``0`` none."""
    return ((sense <= 0) | (det >= 0)) & ((sense >= 0) | (det < 0))


def plane_distance(e0, e1, e2, z0, z1, z2, det):
    """The distance to the triangle's plane, ``(e0 z0 + e1 z1 + e2 z2) / det`` correctly rounded (``z`` the
    sheared vertex depths); a zero ``det`` divides by 1."""
    return div_rn(sum_of_products(e0, z0, e1, z1, e2, z2), select(det == 0, like(det, 1.0), det))


def in_interval(t, t_min, t_max):
    """Whether ``t`` lies in the closed interval ``[t_min, t_max]``."""
    return (t >= t_min) & (t <= t_max)
