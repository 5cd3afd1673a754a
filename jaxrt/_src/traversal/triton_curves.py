"""Curve leaves in the Triton traversal kernel: the shared curve formula (:mod:`jaxrt._src.formulas.curve`)
instantiated for Triton, read from the kernel's curve rows.

Imported only where Triton is installed (by :mod:`jaxrt._src.traversal.triton_kernel`). :func:`curve_leaf` tests
one leaf per lane against the segment in its kernel row (:func:`jaxrt._src.traversal.packed.pack_curves`) with
the ray's frame from the ray block (:func:`curve_ray`): the formula's ``segment`` taken apart, so that the
warp skips what no lane needs. Per segment type compiled (``FLAT``), the lanes of that type read the row, move
its control points into the ray's frame (``ray_space``) and cull by the hull (``hull_cull``); the round
(``round_test``) or flat (``flat_test``) test runs behind a warp-uniform branch, where some lane is live. The
formula's order of operations, the first of the smallest keys per candidate kind, the float64
sample weights and the correctly rounded divisions and square roots are those of the CPU traversal
(:mod:`jaxrt._src.traversal.cpu_curves`), and the kernel is compiled without contraction, so both give the same
floats; ``tests/test_formulas.py`` checks it per formula and ``tests/test_gpu_curves.py`` through the kernel.
"""

from __future__ import annotations

import triton
import triton.language as tl

from jaxrt._src import formulas

__all__ = ["CURVE_WIDTH", "curve_leaf", "curve_ray", "is_curve_leaf"]

#: Row width of a packed curve leaf (float32 columns): see :func:`jaxrt._src.traversal.packed.pack_curves`.
CURVE_WIDTH = tl.constexpr(24)

_curve = formulas.instance("curve", "triton")
_ray_space = _curve.ray_space
_hull_cull = _curve.hull_cull
_round_test = _curve.round_test
_flat_test = _curve.flat_test


@triton.jit
def curve_ray(rays_ptr, n_rays, ray, ox, oy, oz):
    """The ray's ``curve.curve_ray`` constants from ray block rows 24-33 (the frame ``e1, e2, n`` row by row,
    then ``1 / |d|``), with the origin: the ``ray`` tuple :func:`curve_leaf` reads."""
    e1x = tl.load(rays_ptr + 24 * n_rays + ray)
    e1y = tl.load(rays_ptr + 25 * n_rays + ray)
    e1z = tl.load(rays_ptr + 26 * n_rays + ray)
    e2x = tl.load(rays_ptr + 27 * n_rays + ray)
    e2y = tl.load(rays_ptr + 28 * n_rays + ray)
    e2z = tl.load(rays_ptr + 29 * n_rays + ray)
    nx = tl.load(rays_ptr + 30 * n_rays + ray)
    ny = tl.load(rays_ptr + 31 * n_rays + ray)
    nz = tl.load(rays_ptr + 32 * n_rays + ray)
    scale_t = tl.load(rays_ptr + 33 * n_rays + ray)
    return ox, oy, oz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz, scale_t


@triton.jit
def is_curve_leaf(curves_ptr, leaf, mask):
    """Whether leaf ``leaf`` is a curve (its row's flags have ``IS_CURVE``), read where ``mask``."""
    bits = tl.load(curves_ptr + leaf * CURVE_WIDTH + 19, mask=mask, other=0.0).to(tl.int32, bitcast=True)
    return mask & ((bits & 32) != 0)


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
    ``[t_min, t_max]`` (the formula's ``segment``, ``curve.intersect``; distance ``inf`` where not hit) replaces
    ``(hit, distance)``, the triangle test's answer (a curve leaf's triangle is degenerate: never hit).

    ``ray`` is :func:`curve_ray`'s tuple; the options are ``curve.CurveOptions`` (``PIECES``, ``ITERATIONS``,
    ``APPROACH`` = ``approach_iterations``, ``TOLERANCE``), ``DISK``/``SPHERE`` say whether any segment has disk
    or sphere end caps, and ``FLAT`` which segment test is compiled: 0 round only, 1 flat (ray-facing ribbons)
    only, 2 both, chosen per row by ``FLAT_BIT``."""
    row = curves_ptr + leaf * CURVE_WIDTH
    bits = tl.load(row + 19, mask=test, other=0.0).to(tl.int32, bitcast=True)
    is_curve = test & ((bits & 32) != 0)
    if tl.max(is_curve.to(tl.int32), axis=0) > 0:
        if FLAT == 0:
            curve_hit, curve_distance = _segment(
                row, is_curve, bits, ray, t_min, t_max, LANES, PIECES, ITERATIONS, APPROACH, TOLERANCE, DISK, SPHERE, 0
            )  # fmt: skip
        elif FLAT == 1:
            curve_hit, curve_distance = _segment(
                row, is_curve, bits, ray, t_min, t_max, LANES, PIECES, ITERATIONS, APPROACH, TOLERANCE, DISK, SPHERE, 1
            )  # fmt: skip
        else:
            # Each test reads and moves the row again: keeping the ray-space points of the first test live
            # through the second costs more registers than the loads.
            flat = (bits & 16) != 0
            curve_hit, curve_distance = _segment(
                row, is_curve & (flat == 0), bits, ray, t_min, t_max, LANES, PIECES, ITERATIONS, APPROACH, TOLERANCE,
                DISK, SPHERE, 0,
            )  # fmt: skip
            flat_hit, flat_distance = _segment(
                row, is_curve & flat, bits, ray, t_min, t_max, LANES, PIECES, ITERATIONS, APPROACH, TOLERANCE, DISK,
                SPHERE, 1,
            )  # fmt: skip
            curve_hit = tl.where(flat, flat_hit, curve_hit)
            curve_distance = tl.where(flat, flat_distance, curve_distance)
        hit = tl.where(is_curve, curve_hit, hit)
        distance = tl.where(is_curve, curve_distance, distance)
    return hit, distance


@triton.jit
def _segment(
    row, mask, bits, ray, t_min, t_max, LANES: tl.constexpr, PIECES: tl.constexpr, ITERATIONS: tl.constexpr,
    APPROACH: tl.constexpr, TOLERANCE: tl.constexpr, DISK: tl.constexpr, SPHERE: tl.constexpr, FLAT: tl.constexpr,
):  # fmt: skip
    """The formula's ``segment`` on the lanes of ``mask``: the row's control points moved into the ray's frame,
    the hull cull, then (behind a warp-uniform branch, where some lane is live) the round test (``FLAT = 0``) or
    the flat one (``FLAT = 1``): ``(hit, distance)``, the distance in units of the ray direction's length."""
    ox, oy, oz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz, scale_t = ray
    # The row (pack_curves): four control points and radii relative to the base point, the base point, the
    # flags, the predecessor's joint derivative and radius derivative.
    l0x = tl.load(row + 0, mask=mask, other=0.0)
    l0y = tl.load(row + 1, mask=mask, other=0.0)
    l0z = tl.load(row + 2, mask=mask, other=0.0)
    r0 = tl.load(row + 3, mask=mask, other=0.0)
    l1x = tl.load(row + 4, mask=mask, other=0.0)
    l1y = tl.load(row + 5, mask=mask, other=0.0)
    l1z = tl.load(row + 6, mask=mask, other=0.0)
    r1 = tl.load(row + 7, mask=mask, other=0.0)
    l2x = tl.load(row + 8, mask=mask, other=0.0)
    l2y = tl.load(row + 9, mask=mask, other=0.0)
    l2z = tl.load(row + 10, mask=mask, other=0.0)
    r2 = tl.load(row + 11, mask=mask, other=0.0)
    l3x = tl.load(row + 12, mask=mask, other=0.0)
    l3y = tl.load(row + 13, mask=mask, other=0.0)
    l3z = tl.load(row + 14, mask=mask, other=0.0)
    r3 = tl.load(row + 15, mask=mask, other=0.0)
    basex = tl.load(row + 16, mask=mask, other=0.0)
    basey = tl.load(row + 17, mask=mask, other=0.0)
    basez = tl.load(row + 18, mask=mask, other=0.0)
    vx = tl.load(row + 20, mask=mask, other=0.0)
    vy = tl.load(row + 21, mask=mask, other=0.0)
    vz = tl.load(row + 22, mask=mask, other=0.0)
    x0, y0, z0, x1, y1, z1, x2, y2, z2, x3, y3, z3, pvx, pvy, pvz = _ray_space(
        l0x, l0y, l0z, l1x, l1y, l1z, l2x, l2y, l2z, l3x, l3y, l3z, basex, basey, basez, vx, vy, vz,
        ox, oy, oz, e1x, e1y, e1z, e2x, e2y, e2z, nx, ny, nz,
    )  # fmt: skip
    lo = tl.math.div_rn(t_min, scale_t)
    hi = tl.math.div_rn(t_max, scale_t)
    live, noise = _hull_cull(x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, lo, hi, TOLERANCE)
    live = mask & live
    hit = tl.zeros((LANES,), tl.int1)
    distance = tl.full((LANES,), float("inf"), tl.float32)
    if tl.max(live.to(tl.int32), axis=0) > 0:
        if FLAT == 0:
            pvr = tl.load(row + 23, mask=mask, other=0.0)
            found, t, _, _ = _round_test(
                x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, pvx, pvy, pvz, pvr, bits, lo, hi,
                noise, PIECES, ITERATIONS, APPROACH, TOLERANCE, DISK, SPHERE,
            )  # fmt: skip
        else:
            found, t, _, _ = _flat_test(
                x0, y0, z0, r0, x1, y1, z1, r1, x2, y2, z2, r2, x3, y3, z3, r3, pvx, pvy, bits, lo, hi, noise,
                PIECES, ITERATIONS, TOLERANCE, DISK, SPHERE,
            )  # fmt: skip
        hit = live & found
        distance = tl.where(hit, t * scale_t, float("inf"))
    return hit, distance
