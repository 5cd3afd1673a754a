"""Curve leaves in the CPU traversal: the shared curve formula (:mod:`jaxrt._src.formulas.curve`) instantiated
for Numba, read from the scene's packed segments.

Imported only by :mod:`jaxrt._src.traversal.cpu_kernel`. :func:`curve_leaf` tests one ray against one leaf's
segment (``(6, 4)`` rows of :func:`jaxrt._src.curves.pack_segments`, in the geometry's dtype) with the ray's
frame from :func:`jaxrt._src.primitives.curve.curve_ray` (computed by JAX, as the portable path computes it):
the control points in ray space, the hull cull, and the round or flat test the segment's flags and the static
``flat`` choice call for. A culled ray returns before the test (the GPU kernel skips it where no lane of a warp
is live; JAX masks).

The static curve options travel in the kernel's integer parameters (:func:`jaxrt._src.traversal.cpu.curve_params`),
the tolerance as the bits of its float64 value, so that it rounds to the geometry's dtype as a Python float
does in JAX.
"""

from __future__ import annotations

import numba
import numpy as np

from jaxrt._src import formulas
from jaxrt._src.formulas.ops_numba import key_caches_on_formulas

_curve = formulas.instance("curve", "numba")
_ray_space = _curve.ray_space
_hull_cull = _curve.hull_cull
_round_test = _curve.round_test
_flat_test = _curve.flat_test

__all__ = ["curve_hit", "curve_leaf", "nearest_parts", "pairs"]


@numba.njit(cache=True)
def curve_hit(segments, flags, leaf, ox, oy, oz, frame, ray, t_min, t_max, params, at, inf):
    """``(accepted, distance, u, part)`` of leaf ``leaf``'s segment (``segments[leaf]``, flags ``flags[leaf]``)
    for ray ``ray`` (origin ``o``, frame row ``frame[ray]``: ``e1, e2, n, 1 / |d|``) in ``[t_min, t_max]``:
    ``u`` the curve parameter and ``part`` the ``PART_*`` code of the part hit (as ``curve.intersect``
    reports them); the curve options are ``params[at : at + 8]`` (:func:`jaxrt._src.traversal.cpu.curve_params`)."""
    pieces, iterations, approach = params[at + 1], params[at + 2], params[at + 3]
    disk, sphere, flat = params[at + 4] != 0, params[at + 5] != 0, params[at + 6]
    tolerance = params[at + 7 : at + 8].view(np.float64)[0]
    s = segments[leaf]
    bits = flags[leaf]
    f = frame[ray]
    scale_t = f[9]
    x0, y0, z0, x1, y1, z1, x2, y2, z2, x3, y3, z3, pvx, pvy, pvz = _ray_space(
        s[0, 0], s[0, 1], s[0, 2], s[1, 0], s[1, 1], s[1, 2], s[2, 0], s[2, 1], s[2, 2], s[3, 0], s[3, 1], s[3, 2],
        s[4, 0], s[4, 1], s[4, 2], s[5, 0], s[5, 1], s[5, 2], ox, oy, oz, f[0], f[1], f[2], f[3], f[4], f[5], f[6],
        f[7], f[8],
    )  # fmt: skip
    r0, r1, r2, r3 = s[0, 3], s[1, 3], s[2, 3], s[3, 3]
    lo = t_min / scale_t
    hi = t_max / scale_t
    zero = scale_t - scale_t
    live, noise = _hull_cull(x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, lo, hi, tolerance)
    if not live:
        return False, inf, zero, 0
    if flat == 1 or (flat == 2 and (bits & 16) != 0):
        hit, t, u, part = _flat_test(
            x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, pvx, pvy, bits, lo, hi, noise,
            pieces, iterations, tolerance, disk, sphere,
        )  # fmt: skip
    else:
        hit, t, u, part = _round_test(
            x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, pvx, pvy, pvz, s[5, 3], bits, lo, hi,
            noise, pieces, iterations, approach, tolerance, disk, sphere,
        )  # fmt: skip
    if hit:
        return True, t * scale_t, u, part
    return False, inf, zero, 0


@numba.njit(cache=True)
def curve_leaf(segments, flags, leaf, ox, oy, oz, frame, ray, t_min, t_max, params, at, inf):
    """``(accepted, distance)`` of :func:`curve_hit`: the traversal's leaf test."""
    ok, t, _, _ = curve_hit(segments, flags, leaf, ox, oy, oz, frame, ray, t_min, t_max, params, at, inf)
    return ok, t


@numba.njit(nogil=True, cache=True)
def nearest_parts(segments, flags, leaf, origin, frame, t_min, t_max, enabled, params, at, inf, out_u, out_part):
    """The curve parameter and part (:func:`curve_hit`) of each enabled ray's nearest hit ``leaf[i]`` where
    that leaf is a curve, tested again in the ray's interval as the result fields re-test it
    (``jaxrt._src.curves.curve_hit_fields``); 0 elsewhere."""
    for i in range(leaf.shape[0]):
        out_u[i] = 0
        out_part[i] = 0
        k = leaf[i]
        if enabled[i] and k >= 0 and (flags[k] & 32) != 0:
            _, _, u, part = curve_hit(
                segments, flags, k, origin[i, 0], origin[i, 1], origin[i, 2], frame, i, t_min[i], t_max[i], params,
                at, inf,
            )  # fmt: skip
            out_u[i] = u
            out_part[i] = part


@numba.njit(cache=True)
def pairs(segments, flags, origin, frame, t_min, t_max, params, inf, out_hit, out_distance, out_u, out_part):
    """:func:`curve_hit` of segment ``i`` and ray ``i`` for every ``i`` (the formula tests' loop)."""
    for i in range(origin.shape[0]):
        out_hit[i], out_distance[i], out_u[i], out_part[i] = curve_hit(
            segments, flags, i, origin[i, 0], origin[i, 1], origin[i, 2], frame, i, t_min[i], t_max[i], params, 0, inf
        )


#: Cached functions here embed the formulas: their disk cache is keyed on the formulas' source too.
key_caches_on_formulas(globals())
