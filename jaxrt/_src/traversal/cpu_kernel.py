"""The CPU traversal compiled with Numba: one ray at a time per thread, the portable step's decisions exactly.

Imported only by :mod:`jaxrt._src.traversal.cpu`, and only when a CPU trace runs (Numba compiles on first
use; ``cache=True`` keeps the machine code on disk for later processes).

Each ray runs the loop of :mod:`jaxrt._src.traversal.step` sequentially: one internal node per iteration, both
child boxes with the conservative slab test (Ize 2013), the primitives of leaf children tested on sight with the
watertight test (Woop, Benthin, Wald 2013), the nearer inner child entered and the farther one pushed, and the
instance transition (ray moved by the instance's world-to-object rows, facing multiplied along the chain).

Same decisions to the bit: every value the portable path compares is computed here with the same float
operations, in the same order and precision (the geometry's dtype). Two details make that hold:

- XLA's CPU backend contracts a multiply feeding an add into one fused multiply-add. Where the portable path's
  expressions are contracted (the sheared vertex coordinates ``p - s * z``, and the scaled distance
  ``e0 z0 + e1 z1 + e2 z2``), this module calls ``llvm.fma`` explicitly; elsewhere it leaves products
  unfused (Numba does not contract: ``fastmath=False``).
- The edge functions' products are rounded to one mantissa bit less than the float has, as
  :func:`jaxrt._src.primitives.triangle._product` does with ``lax.reduce_precision`` (round to nearest even,
  NaN kept), so that no fused multiply-add can change an edge function's sign.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba import prange
from numba.core import types
from numba.extending import intrinsic

__all__ = ["trace_rays", "RAYS_PER_TASK"]

#: Rays traced one after another by one parallel task (the task's stack and level scratch are reused).
RAYS_PER_TASK = 64


@intrinsic
def _fma(typingctx, a, b, c):
    """``a * b + c`` rounded once (``llvm.fma``)."""
    sig = a(a, a, a)

    def codegen(context, builder, signature, args):
        ty = args[0].type
        name = "llvm.fma.f32" if ty == ir.FloatType() else "llvm.fma.f64"
        fn = builder.module.declare_intrinsic(name, [ty], ir.FunctionType(ty, [ty, ty, ty]))
        return builder.call(fn, args)

    return sig, codegen


@intrinsic
def _rounded_product(typingctx, a, b):
    """``a * b`` rounded to one mantissa bit less, to nearest even (XLA's ``reduce_precision``); NaN kept."""
    sig = a(a, a)

    def codegen(context, builder, signature, args):
        ty = args[0].type
        bits = 32 if ty == ir.FloatType() else 64
        it = ir.IntType(bits)
        product = builder.fmul(args[0], args[1])
        x = builder.bitcast(product, it)
        last = builder.lshr(builder.and_(x, ir.Constant(it, 2)), ir.Constant(it, 1))
        rounded = builder.and_(builder.add(x, last), ir.Constant(it, ~1 & ((1 << bits) - 1)))
        out = builder.bitcast(rounded, ty)
        is_nan = builder.fcmp_unordered("uno", product, product)
        return builder.select(is_nan, product, out)

    return sig, codegen


@numba.njit(cache=True, inline="always")
def _reciprocal(x, clamp, huge, clamped_huge, one):
    """:func:`jaxrt._src.numerics.safe_reciprocal` in the dtype of ``x``: ``huge`` is the dtype's ``1 / clamp``
    threshold, and a component above it becomes ``sign / clamped_huge`` (``clamped_huge`` is ``clamp``)."""
    sign = -one if np.signbit(x) else one
    m = abs(x)
    y = x
    if m < clamp:
        y = sign * clamp
    if m > huge:
        y = sign / clamped_huge
    return one / y


@numba.njit(cache=True, inline="always")
def _pick(k, a0, a1, a2):
    return a0 if k == 0 else (a1 if k == 1 else a2)


@numba.njit(cache=True)
def _load(ray, o0, o1, o2, d0, d1, d2, consts):
    """Fill ``ray`` with the loaded ray's constants: origin, reciprocal direction, shear (Woop et al. section 3)."""
    one, clamp, huge, clamped_huge = consts[0], consts[3], consts[4], consts[5]
    ray[0], ray[1], ray[2] = o0, o1, o2
    ray[3] = _reciprocal(d0, clamp, huge, clamped_huge, one)
    ray[4] = _reciprocal(d1, clamp, huge, clamped_huge, one)
    ray[5] = _reciprocal(d2, clamp, huge, clamped_huge, one)
    a0, a1, a2 = abs(d0), abs(d1), abs(d2)
    if a0 >= a1:
        kz = 0 if a0 >= a2 else 2
    else:
        kz = 1 if a1 >= a2 else 2
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    dz = _pick(kz, d0, d1, d2)
    if dz < 0:
        kx, ky = ky, kx
    dz_safe = one if dz == 0 else dz
    ray[6] = _pick(kx, d0, d1, d2) / dz_safe
    ray[7] = _pick(ky, d0, d1, d2) / dz_safe
    ray[8] = one / dz_safe
    return kx, ky, kz


@numba.njit(cache=True, inline="always")
def _box(ray, t_min, t_max, lo, hi, far_scale, parallel, inf):
    """The conservative slab test (:func:`jaxrt._src.primitives.box.ray_box`): ``(hit, t_near)``."""
    near = -inf
    far = inf
    for a in range(3):
        o = ray[a]
        inv = ray[3 + a]
        if abs(inv) >= parallel:
            inside = lo[a] <= o and o <= hi[a]
            n_a = -inf if inside else inf
            f_a = inf if inside else -inf
        else:
            t0 = (lo[a] - o) * inv
            t1 = (hi[a] - o) * inv
            n_a = min(t0, t1)
            f_a = max(t0, t1)
        near = max(near, n_a)
        far = min(far, f_a)
    t_near = max(near, t_min)
    t_far = min(far * far_scale, t_max)
    return (t_near <= t_far) and (lo[0] <= hi[0]), t_near


@numba.njit(cache=True, inline="always")
def _triangle(ray, kx, ky, kz, tri, t_min, t_max, cull, one, zero, inf):
    """The watertight test (:func:`jaxrt._src.primitives.triangle.watertight`) with a cull sense ``cull``
    (+1 culls clockwise, -1 counterclockwise): ``(accepted, distance)``."""
    sx, sy, sz = ray[6], ray[7], ray[8]
    o0, o1, o2 = ray[0], ray[1], ray[2]
    # Vertex j relative to the origin, sheared: (px, py) and the sheared z (Woop et al. section 3).
    r0, r1, r2 = tri[0, 0] - o0, tri[0, 1] - o1, tri[0, 2] - o2
    az = _pick(kz, r0, r1, r2)
    ax = _fma(-sx, az, _pick(kx, r0, r1, r2))
    ay = _fma(-sy, az, _pick(ky, r0, r1, r2))
    z0 = sz * az
    r0, r1, r2 = tri[1, 0] - o0, tri[1, 1] - o1, tri[1, 2] - o2
    bz = _pick(kz, r0, r1, r2)
    bx = _fma(-sx, bz, _pick(kx, r0, r1, r2))
    by = _fma(-sy, bz, _pick(ky, r0, r1, r2))
    z1 = sz * bz
    r0, r1, r2 = tri[2, 0] - o0, tri[2, 1] - o1, tri[2, 2] - o2
    cz = _pick(kz, r0, r1, r2)
    cx = _fma(-sx, cz, _pick(kx, r0, r1, r2))
    cy = _fma(-sy, cz, _pick(ky, r0, r1, r2))
    z2 = sz * cz
    e0 = _rounded_product(cx, by) - _rounded_product(cy, bx)
    e1 = _rounded_product(ax, cy) - _rounded_product(ay, cx)
    e2 = _rounded_product(bx, ay) - _rounded_product(by, ax)
    negative = e0 < 0 or e1 < 0 or e2 < 0
    positive = e0 > 0 or e1 > 0 or e2 > 0
    det = e0 + e1 + e2
    if (negative and positive) or det == 0:
        return False, inf
    clockwise = det < 0
    if (cull > 0 and clockwise) or (cull < 0 and not clockwise):
        return False, inf
    t = _fma(e2, z2, _fma(e0, z0, e1 * z1)) / det
    if t >= t_min and t <= t_max:
        return True, t
    return False, inf


@numba.njit(cache=True)
def _trace_one(
    i, node_lower, node_upper, node_children, leaf_triangle, world_to_object, child_root, instance_facing,
    instance_mask, origin, direction, t_min_all, t_max_all, mask_all, consts, root, primitive_leaves, levels,
    any_hit, cull, stack_size, stack, base, chain, level_ray, level_facing, hit_chain, ray, out_distance, out_leaf, out_chain,
    out_visited, out_tested, out_overflow,
):  # fmt: skip
    one, zero, inf = consts[0], consts[1], consts[2]
    far_scale, parallel = consts[6], consts[7]
    instances = child_root.shape[0]
    t_min = t_min_all[i]
    distance = t_max_all[i]
    ray_mask = mask_all[i]
    leaf = -1
    kx, ky, kz = _load(ray, origin[i, 0], origin[i, 1], origin[i, 2], direction[i, 0], direction[i, 1], direction[i, 2], consts)  # fmt: skip
    facing = 1
    node = root
    depth = 0
    level = 0
    ray_level = 0
    visited = 0
    tested = 0
    overflow = False
    for j in range(levels):
        hit_chain[j] = -1
    while True:
        visited += 1
        c0 = node_children[node, 0]
        c1 = node_children[node, 1]
        hit0, near0 = _box(ray, t_min, distance, node_lower[node, 0], node_upper[node, 0], far_scale, parallel, inf)
        hit1, near1 = _box(ray, t_min, distance, node_lower[node, 1], node_upper[node, 1], far_scale, parallel, inf)
        # Leaf children: primitives are tested now, instances are entered like inner children (when visible).
        k0 = -1 - c0
        k1 = -1 - c1
        inner0 = hit0 and c0 >= 0
        inner1 = hit1 and c1 >= 0
        e0 = c0
        e1 = c1
        ok0 = False
        ok1 = False
        t0 = inf
        t1 = inf
        sense = cull * facing
        if c0 < 0:
            if k0 < primitive_leaves:
                if hit0:
                    tested += 1
                    ok0, t0 = _triangle(ray, kx, ky, kz, leaf_triangle[k0], t_min, distance, sense, one, zero, inf)
            else:
                g = min(max(k0 - primitive_leaves, 0), instances - 1)
                e0 = -1 - g
                inner0 = hit0 and (instance_mask[g] & ray_mask) != 0
        if c1 < 0:
            if k1 < primitive_leaves:
                if hit1:
                    tested += 1
                    ok1, t1 = _triangle(ray, kx, ky, kz, leaf_triangle[k1], t_min, distance, sense, one, zero, inf)
            else:
                g = min(max(k1 - primitive_leaves, 0), instances - 1)
                e1 = -1 - g
                inner1 = hit1 and (instance_mask[g] & ray_mask) != 0
        if ok0 or ok1:
            if t1 < t0:
                best_t, best_leaf = t1, k1
            else:
                best_t, best_leaf = t0, k0
            # Strictly nearer than the current hit; the first hit may lie exactly at t_max (closed interval).
            if best_t < distance or (leaf < 0 and best_t <= distance):
                distance = best_t
                leaf = best_leaf
                for j in range(levels):
                    hit_chain[j] = chain[j] if j < level else -1
        finished = False
        if inner0 and inner1:
            if near0 <= near1:
                near, far = e0, e1
            else:
                near, far = e1, e0
            if depth < stack_size:
                stack[depth] = far
                depth += 1
            else:
                overflow = True
            node = near
        elif inner0:
            node = e0
        elif inner1:
            node = e1
        elif depth == 0:
            finished = True
        else:
            depth -= 1
            node = stack[depth]
            # The level of a popped entry: the deepest entered level whose stack base is at or below it.
            top = 0
            for j in range(level):
                if base[j] <= depth:
                    top += 1
            level = top
        if finished or (any_hit and leaf >= 0):
            break
        if levels and (node < 0 or level != ray_level):
            # Load the ray of the entry's level and enter the instance, if the entry is one.
            if level == 0:
                b0, b1, b2 = origin[i, 0], origin[i, 1], origin[i, 2]
                d0, d1, d2 = direction[i, 0], direction[i, 1], direction[i, 2]
                base_facing = 1
            else:
                b0, b1, b2 = level_ray[level - 1, 0], level_ray[level - 1, 1], level_ray[level - 1, 2]
                d0, d1, d2 = level_ray[level - 1, 3], level_ray[level - 1, 4], level_ray[level - 1, 5]
                base_facing = level_facing[level - 1]
            facing = base_facing
            if node < 0:
                g = min(max(-1 - node, 0), instances - 1)
                m = world_to_object[g]
                n0 = m[0, 0] * b0 + m[0, 1] * b1 + m[0, 2] * b2 + m[0, 3]
                n1 = m[1, 0] * b0 + m[1, 1] * b1 + m[1, 2] * b2 + m[1, 3]
                n2 = m[2, 0] * b0 + m[2, 1] * b1 + m[2, 2] * b2 + m[2, 3]
                v0 = m[0, 0] * d0 + m[0, 1] * d1 + m[0, 2] * d2
                v1 = m[1, 0] * d0 + m[1, 1] * d1 + m[1, 2] * d2
                v2 = m[2, 0] * d0 + m[2, 1] * d1 + m[2, 2] * d2
                facing = base_facing * instance_facing[g]
                level_ray[level, 0], level_ray[level, 1], level_ray[level, 2] = n0, n1, n2
                level_ray[level, 3], level_ray[level, 4], level_ray[level, 5] = v0, v1, v2
                level_facing[level] = facing
                base[level] = depth
                chain[level] = g
                b0, b1, b2, d0, d1, d2 = n0, n1, n2, v0, v1, v2
                node = child_root[g]
                level += 1
            ray_level = level
            kx, ky, kz = _load(ray, b0, b1, b2, d0, d1, d2, consts)
    out_distance[i] = distance
    out_leaf[i] = leaf
    for j in range(levels):
        out_chain[i, j] = hit_chain[j]
    out_visited[i] = visited
    out_tested[i] = tested
    out_overflow[i] = overflow


@numba.njit(parallel=True, cache=True)
def trace_rays(
    node_lower, node_upper, node_children, leaf_triangle, world_to_object, child_root, instance_facing,
    instance_mask, origin, direction, t_min, t_max, enabled, mask, consts, params, out_distance, out_leaf,
    out_chain, out_visited, out_tested, out_overflow,
):  # fmt: skip
    """Trace every ray; results go to the ``out_*`` arrays (see :func:`jaxrt._src.traversal.cpu.trace_scene`).

    ``params`` holds ``root, primitive_leaves, levels, stack_size, any_hit, cull``; ``consts`` the float
    constants in the geometry's dtype (:func:`jaxrt._src.traversal.cpu.constants`).
    """
    n = origin.shape[0]
    root, primitive_leaves, levels, stack_size, any_hit, cull = params[0], params[1], params[2], params[3], params[4] != 0, params[5]  # fmt: skip
    tasks = (n + RAYS_PER_TASK - 1) // RAYS_PER_TASK
    for task in prange(tasks):
        stack = np.empty(max(stack_size, 1), np.int32)
        base = np.zeros(max(levels, 1), np.int32)
        chain = np.full(max(levels, 1), -1, np.int32)
        level_ray = np.zeros((max(levels, 1), 6), consts.dtype)
        level_facing = np.ones(max(levels, 1), np.int32)
        hit_chain = np.full(max(levels, 1), -1, np.int32)
        ray = np.empty(9, consts.dtype)
        for i in range(task * RAYS_PER_TASK, min(n, (task + 1) * RAYS_PER_TASK)):
            if not enabled[i]:
                out_distance[i] = -consts[2]
                out_leaf[i] = -1
                for j in range(levels):
                    out_chain[i, j] = -1
                out_visited[i] = 0
                out_tested[i] = 0
                out_overflow[i] = False
                continue
            _trace_one(
                i, node_lower, node_upper, node_children, leaf_triangle, world_to_object, child_root,
                instance_facing, instance_mask, origin, direction, t_min, t_max, mask, consts, root,
                primitive_leaves, levels, any_hit, cull, stack_size, stack, base, chain, level_ray, level_facing, hit_chain,
                ray, out_distance, out_leaf, out_chain, out_visited, out_tested, out_overflow,
            )  # fmt: skip
