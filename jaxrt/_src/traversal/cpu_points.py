"""Point queries compiled with Numba: the nearest-leaf walk and the fast winding number, one point at a time per
thread, the portable walks' decisions in compiled loops.

Imported only when a CPU point query runs (Numba compiles on first use; ``cache=True`` keeps the machine code
on disk for later processes). The leaf and box distances and the solid angle are the shared formulas of
:mod:`jaxrt._src.formulas.point_triangle` instantiated for Numba.

:func:`nearest_leaves` walks the BVH depth first as :mod:`jaxrt._src.point_query` does: a popped node's two
child boxes (stored in the node) are measured, leaf children tested on sight (child 0, then child 1; a leaf
replaces the best one only when strictly nearer, so the first found of equal distances stays), inner children
no farther than the best distance pushed farther first, and an entry whose box is farther than the best
distance when it is popped is dropped. The radius starts at ``max_distance`` and shrinks as leaves are found.

:func:`fast_winding` is the walk of :mod:`jaxrt._src.winding` (Barill et al. 2018): a child subtree far from
the point is replaced by its dipole, leaves add their exact solid angle, the rest are opened; children are
summed and pushed in the same order as the portable walk.

Points with a NaN or infinite coordinate take no step: no leaf (-1), winding number NaN (as the portable walk
gives).

Threads claim chunks of points from a shared counter (one atomic add per chunk), so uneven points balance.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from jaxrt._src import formulas
from jaxrt._src.formulas.ops_numba import key_caches_on_formulas
from jaxrt._src.traversal.cpu_kernel import _fetch_add

_f = formulas.instance("point_triangle", "numba")
_closest_on_triangle = _f.closest_on_triangle
_triangle_point = _f.triangle_point
_squared_box_distance = _f.squared_box_distance
_solid_angle = _f.solid_angle

__all__ = ["constants", "exact_winding", "fast_winding", "nearest_leaves"]

_U1 = np.uint64(1)
_U2 = np.uint64(2)
_U3 = np.uint64(3)
_U4 = np.uint64(4)
_U5 = np.uint64(5)
_U6 = np.uint64(6)
_U7 = np.uint64(7)
_U8 = np.uint64(8)
_U9 = np.uint64(9)


def constants(dtype) -> np.ndarray:
    """The walks' float constants in ``dtype``: 0, 1, ``inf``, ``4 pi`` (rounded to ``dtype`` as the portable
    walk rounds it), NaN."""
    return np.array([0.0, 1.0, np.inf, 4 * math.pi, np.nan], dtype)


@numba.njit(cache=True, inline="always")
def _leaf_distance(tf, bf, box_leaf, k, px, py, pz):
    """Squared distance from ``p`` to leaf ``k``: its triangle, or its solid box where ``box_leaf[k]``."""
    uk = np.uint64(k)
    if box_leaf[k]:
        b = uk * _U6
        return _squared_box_distance(px, py, pz, bf[b], bf[b + _U1], bf[b + _U2], bf[b + _U3], bf[b + _U4], bf[b + _U5])  # fmt: skip
    t = uk * _U9
    ax, ay, az = tf[t], tf[t + _U1], tf[t + _U2]
    bx, by, bz = tf[t + _U3], tf[t + _U4], tf[t + _U5]
    cx, cy, cz = tf[t + _U6], tf[t + _U7], tf[t + _U8]
    u, v = _closest_on_triangle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz)
    qx, qy, qz = _triangle_point(ax, ay, az, bx, by, bz, cx, cy, cz, u, v)
    dx, dy, dz = px - qx, py - qy, pz - qz
    return (dx * dx + dy * dy) + dz * dz


@numba.njit(nogil=True, cache=True)
def nearest_leaves(points, node_lower, node_upper, node_children, leaf_triangle, leaf_box, box_leaf, limit2, consts, stack_size, counter, chunk, out_leaf):  # fmt: skip
    """The nearest leaf to each point of ``points (n, 3)`` within squared distance ``limit2`` (``-1``: none) into
    ``out_leaf``. Every thread that calls it with the same ``counter`` (``int64[1]`` from 0) claims ``chunk``
    points at a time until none is left. ``leaf_box``: ``(C, 2, 3)`` box rows, read where ``box_leaf``."""
    n = points.shape[0]
    inf, nan = consts[2], consts[4]
    stack = np.empty(max(stack_size, 1), np.int32)
    bound = np.empty(max(stack_size, 1), consts.dtype)
    lf, hf, cf = node_lower.reshape(-1), node_upper.reshape(-1), node_children.reshape(-1)
    tf, bf = leaf_triangle.reshape(-1), leaf_box.reshape(-1)
    while True:
        begin = _fetch_add(counter, chunk)
        if begin >= n:
            break
        for i in range(begin, min(begin + chunk, n)):
            px, py, pz = points[i, 0], points[i, 1], points[i, 2]
            best = limit2
            leaf = -1
            if not (abs(px) < inf and abs(py) < inf and abs(pz) < inf):
                out_leaf[i] = -1
                continue
            stack[0] = 0
            bound[0] = -inf
            size = 1
            while size > 0:
                size -= 1
                if not (bound[size] <= best):
                    continue
                node = np.uint64(stack[size])
                b = node * _U6
                d0 = _squared_box_distance(px, py, pz, lf[b], lf[b + _U1], lf[b + _U2], hf[b], hf[b + _U1], hf[b + _U2])  # fmt: skip
                d1 = _squared_box_distance(px, py, pz, lf[b + _U3], lf[b + _U4], lf[b + _U5], hf[b + _U3], hf[b + _U4], hf[b + _U5])  # fmt: skip
                # Empty boxes (padding, zero-area triangles) fail every comparison, even with an infinite best.
                if not d0 < inf:
                    d0 = nan
                if not d1 < inf:
                    d1 = nan
                c0 = cf[node * _U2]
                c1 = cf[node * _U2 + _U1]
                if c0 < 0 and d0 <= best:
                    d = _leaf_distance(tf, bf, box_leaf, -1 - c0, px, py, pz)
                    if d < best or (leaf < 0 and d <= best):
                        best = d
                        leaf = -1 - c0
                if c1 < 0 and d1 <= best:
                    d = _leaf_distance(tf, bf, box_leaf, -1 - c1, px, py, pz)
                    if d < best or (leaf < 0 and d <= best):
                        best = d
                        leaf = -1 - c1
                # Farther first, so that the nearer is popped next.
                if d1 < d0:
                    far_c, far_d, near_c, near_d = c0, d0, c1, d1
                else:
                    far_c, far_d, near_c, near_d = c1, d1, c0, d0
                if far_c >= 0 and far_d <= best and size < stack_size:
                    stack[size] = far_c
                    bound[size] = far_d
                    size += 1
                if near_c >= 0 and near_d <= best and size < stack_size:
                    stack[size] = near_c
                    bound[size] = near_d
                    size += 1
            out_leaf[i] = leaf


@numba.njit(cache=True, inline="always")
def _leaf_winding(tf, bf, box_leaf, leaf_geometry, k, px, py, pz, zero, one, four_pi):
    """Winding number of leaf ``k`` at ``p``: its solid angle over ``4 pi``, or 1 inside its box."""
    uk = np.uint64(k)
    if leaf_geometry[k] < 0:
        return zero
    if box_leaf[k]:
        b = uk * _U6
        inside = bf[b] <= px <= bf[b + _U3] and bf[b + _U1] <= py <= bf[b + _U4] and bf[b + _U2] <= pz <= bf[b + _U5]
        return one if inside else zero
    t = uk * _U9
    w = _solid_angle(px, py, pz, tf[t], tf[t + _U1], tf[t + _U2], tf[t + _U3], tf[t + _U4], tf[t + _U5], tf[t + _U6], tf[t + _U7], tf[t + _U8])  # fmt: skip
    return w / four_pi


@numba.njit(nogil=True, cache=True)
def fast_winding(points, node_children, leaf_triangle, leaf_box, box_leaf, leaf_geometry, normal, center, reach2, consts, stack_size, counter, chunk, out_total):  # fmt: skip
    """The fast winding number of each point (Barill et al. 2018) into ``out_total``: ``normal``, ``center``
    ``(M, 2, 3)`` and ``reach2 (M, 2)`` are each child subtree's dipole and the squared distance beyond which
    it stands in for the subtree (:func:`jaxrt._src.winding._dipoles`). Threads share ``counter`` as in
    :func:`nearest_leaves`."""
    n = points.shape[0]
    zero, one, inf, four_pi = consts[0], consts[1], consts[2], consts[3]
    stack = np.empty(max(stack_size, 1), np.int32)
    cf, tf, bf = node_children.reshape(-1), leaf_triangle.reshape(-1), leaf_box.reshape(-1)
    nf, mf, rf = normal.reshape(-1), center.reshape(-1), reach2.reshape(-1)
    while True:
        begin = _fetch_add(counter, chunk)
        if begin >= n:
            break
        for i in range(begin, min(begin + chunk, n)):
            px, py, pz = points[i, 0], points[i, 1], points[i, 2]
            total = zero
            if not (abs(px) < inf and abs(py) < inf and abs(pz) < inf):
                out_total[i] = consts[4]
                continue
            stack[0] = 0
            size = 1
            while size > 0:
                size -= 1
                node = np.uint64(stack[size])
                for j in range(2):
                    child = node * _U2 + np.uint64(j)
                    c = cf[child]
                    if c < 0:
                        total += _leaf_winding(tf, bf, box_leaf, leaf_geometry, -1 - c, px, py, pz, zero, one, four_pi)
                        continue
                    b = child * _U3
                    ox, oy, oz = mf[b] - px, mf[b + _U1] - py, mf[b + _U2] - pz
                    dist2 = (ox * ox + oy * oy) + oz * oz
                    if dist2 > rf[child]:
                        dot = (nf[b] * ox + nf[b + _U1] * oy) + nf[b + _U2] * oz
                        total += dot / (four_pi * dist2 * np.sqrt(dist2))
                    elif size < stack_size:
                        stack[size] = c
                        size += 1
            out_total[i] = total


@numba.njit(nogil=True, cache=True)
def exact_winding(points, leaf_triangle, leaf_box, box_leaf, leaf_geometry, consts, counter, chunk, out_total):  # fmt: skip
    """The exact winding number of each point: every leaf's solid angle (or box) summed in leaf order into
    ``out_total``. Threads share ``counter`` as in :func:`nearest_leaves`."""
    n = points.shape[0]
    zero, one, inf, four_pi = consts[0], consts[1], consts[2], consts[3]
    tf, bf = leaf_triangle.reshape(-1), leaf_box.reshape(-1)
    leaves = leaf_geometry.shape[0]
    while True:
        begin = _fetch_add(counter, chunk)
        if begin >= n:
            break
        for i in range(begin, min(begin + chunk, n)):
            px, py, pz = points[i, 0], points[i, 1], points[i, 2]
            total = consts[4]
            if abs(px) < inf and abs(py) < inf and abs(pz) < inf:
                total = zero
                for k in range(leaves):
                    total += _leaf_winding(tf, bf, box_leaf, leaf_geometry, k, px, py, pz, zero, one, four_pi)
            out_total[i] = total


#: Cached functions here embed the formulas: their disk cache is keyed on the formulas' source too.
key_caches_on_formulas(globals())
