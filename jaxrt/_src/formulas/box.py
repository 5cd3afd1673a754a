"""The conservative ray/box slab test (Ize 2013), one formula for every backend.

Reference: Ize, "Robust BVH Ray Traversal", JCGT 2(2), 2013: with the reciprocal direction rounded once, the
far slab distance scaled by ``1 + 2 * gamma(3)`` bounds the rounding of the subtraction, the product and the
reciprocal, so no box the exact ray passes through is missed.
"""

from __future__ import annotations

from jaxrt._src.formulas.vocabulary import INF, absolute, like, maximum, minimum, select

__all__ = ["slab_distances", "slab_axis", "box_hit"]


def slab_distances(lo, hi, o, inv):
    """Entry and exit distance of one slab, ``(min(t0, t1), max(t0, t1))``, for a non-zero direction
    component (``inv`` not clamped)."""
    t0 = (lo - o) * inv
    t1 = (hi - o) * inv
    return minimum(t0, t1), maximum(t0, t1)


def slab_axis(lo, hi, o, inv, parallel):
    """:func:`slab_distances` where ``|inv| < parallel``; a clamped reciprocal (a zero direction component,
    ``|inv| >= parallel``) keeps the ray at one coordinate, so the slab holds all of the ray when the origin is
    in ``[lo, hi]`` (boundary included) and none of it otherwise. The clamped reciprocal alone would make a
    ray lying in a slab plane leave the slab at ``t = 0``."""
    near, far = slab_distances(lo, hi, o, inv)
    flat = absolute(inv) >= parallel
    inside = (lo <= o) & (o <= hi)
    near = select(flat, select(inside, like(near, -INF), like(near, INF)), near)
    far = select(flat, select(inside, like(far, INF), like(far, -INF)), far)
    return near, far


def box_hit(near_x, far_x, near_y, far_y, near_z, far_z, lo_x, hi_x, t_min, t_max, far_scale):
    """``(hit, t_near, t_far)`` of a box from its three slabs: the entry clamped to ``t_min``, the exit scaled
    by ``far_scale`` (``1 + 2 gamma(3)``) and clamped to ``t_max``. An empty box (``lo_x > hi_x``) would pass
    (its slabs swap to ``(-inf, inf)``), so it is rejected by its x bounds."""
    near = maximum(maximum(maximum(near_x, near_y), near_z), t_min)
    far = minimum(minimum(minimum(far_x, far_y), far_z) * far_scale, t_max)
    return (near <= far) & (lo_x <= hi_x), near, far
