"""The CPU traversal compiled with Numba: one ray at a time per thread, the portable step's decisions exactly.

Imported only by :mod:`jaxrt._src.traversal.cpu`, and only when a CPU trace runs (Numba compiles on first
use; ``cache=True`` keeps the machine code on disk for later processes).

Each ray runs the loop of :mod:`jaxrt._src.traversal.step` sequentially: one internal node per iteration, both
child boxes with the conservative slab test (Ize 2013), the primitives of leaf children tested on sight with the
watertight test (Woop, Benthin, Wald 2013), the nearer inner child entered and the farther one pushed (the
any-hit order of :func:`_first`), and the instance transition (ray moved by the instance's world-to-object
rows, facing multiplied along the chain).
:func:`trace_rays` is the general loop; :func:`trace_flat` the same loop for a primitive structure of triangles
and the leaves of kinds with an analytic row (built-in spheres) with a nearest or any-hit query (no instance,
hit-list or analytic bookkeeping per visit), which tests both child boxes of a node in one vector slab test
(:func:`_box_pair`, on the node rows of :func:`box_rows`) for rays parallel to no axis.

The leaf and box tests are the shared formulas of :mod:`jaxrt._src.formulas` (slab test, shear, watertight
triangle, analytic shapes, curves through :mod:`jaxrt._src.traversal.cpu_curves`) instantiated for Numba; this
module holds the loop and the memory layout around them.

Same decisions to the bit: every value the portable path compares is computed here with the same float
operations, in the same order and precision (the geometry's dtype). Two details make that hold (both in
:mod:`jaxrt._src.formulas.ops_numba`):

- XLA's CPU backend contracts a multiply feeding an add into one fused multiply-add. Where the portable path's
  expressions are contracted (the sheared vertex coordinates ``p - s * z``, the scaled distance
  ``e0 z0 + e1 z1 + e2 z2``, and the instance transition's rows here), ``llvm.fma`` is called explicitly;
  elsewhere products stay unfused (Numba does not contract: ``fastmath=False``).
- The edge functions' products are rounded to one mantissa bit less than the float has, as
  :func:`jaxrt._src.primitives.triangle._product` does with ``lax.reduce_precision`` (round to nearest even,
  NaN kept), so that no fused multiply-add can change an edge function's sign.

The formulas are compiled into this module's functions, whose machine code Numba caches on disk keyed by this
file; :func:`jaxrt._src.formulas.ops_numba.key_caches_on_formulas` adds the formulas' source to the key, so
an edited formula recompiles the traversal.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from jaxrt._src import formulas
from jaxrt._src.formulas.ops_numba import fma as _fma
from jaxrt._src.formulas.ops_numba import key_caches_on_formulas
from jaxrt._src.traversal import analytic_rows as row_dispatch
from jaxrt._src.traversal import cpu_curves

_box_f = formulas.instance("box", "numba")
_slab_axis = _box_f.slab_axis
_box_hit = _box_f.box_hit
_tri = formulas.instance("triangle", "numba")
_shear_axes = _tri.shear_axes
_shear = _tri.shear
_sheared_vertex = _tri.sheared_vertex
_edge_functions = _tri.edge_functions
_edges_inside = _tri.edges_inside
_facing_accepts = _tri.facing_accepts
_plane_distance = _tri.plane_distance
_in_interval = _tri.in_interval
_curve_leaf = cpu_curves.curve_leaf

__all__ = ["trace_flat", "trace_rays"]

#: The flag bit of curve leaves (:data:`jaxrt._src.primitives.curve.IS_CURVE`).
_IS_CURVE = 32

#: Unsigned offsets: rows are read from flat views at unsigned indices (no negative-index wraparound code).
_U1 = np.uint64(1)
_U2 = np.uint64(2)
_U3 = np.uint64(3)
_U4 = np.uint64(4)
_U5 = np.uint64(5)
_U6 = np.uint64(6)
_U7 = np.uint64(7)
_U8 = np.uint64(8)
_U9 = np.uint64(9)
_U12 = np.uint64(12)

# The dispatch over analytic rows, generated from the kind registry (:mod:`jaxrt._src.traversal.analytic_rows`):
# ``_analytic`` tests any analytic row, ``_is_formula_row`` and ``_formula_row`` a kind's row in the lean loop.
_generated = row_dispatch.compile_source(
    "numba",
    row_dispatch.numba_source(),
    dict(
        np=np,
        _U1=_U1,
        _U2=_U2,
        _U3=_U3,
        _U4=_U4,
        _U5=_U5,
        _U6=_U6,
        _U7=_U7,
        tests=lambda module, name: getattr(formulas.instance(module, "numba"), name),
    ),
)
_analytic = numba.njit(_generated.analytic)
_is_formula_row = numba.njit(inline="always")(_generated.is_formula_row)
_formula_row = numba.njit(inline="always")(_generated.formula_row)


@intrinsic
def _fetch_add(typingctx, counter, amount):
    """``counter[0] += amount`` as one atomic step; returns the value before."""
    sig = types.int64(counter, types.int64)

    def codegen(context, builder, signature, args):
        array = context.make_array(signature.args[0])(context, builder, args[0])
        return builder.atomic_rmw("add", array.data, args[1], "monotonic")

    return sig, codegen


def _lane_mask(*lanes):
    """An LLVM shuffle mask."""
    i32 = ir.IntType(32)
    return ir.Constant(ir.VectorType(i32, len(lanes)), [ir.Constant(i32, x) for x in lanes])


def _splat(builder, value, n):
    """``value`` in each of ``n`` lanes."""
    vt = ir.VectorType(value.type, n)
    zero = ir.Constant(ir.IntType(32), 0)
    return builder.shuffle_vector(
        builder.insert_element(ir.Constant(vt, None), value, zero), ir.Constant(vt, None), _lane_mask(*[0] * n)
    )


def _slab_pair(context, builder, signature, x, y, z, ray):
    """The slab test of :func:`_box` for both boxes of a node whose axes are the vectors ``x, y, z`` (each
    ``[lower of box 0, lower of box 1, upper of box 0, upper of box 1]``), for the ray ``(o0, o1, o2, i0, i1,
    i2, t_min, t_max, far_scale)``: the tuple ``(hit0, near0, hit1, near1)``. Every lane computes the scalar
    test's slab distances (the same subtraction, product and ``select``-based ``min``/``max``), and the same
    decisions for an interval without NaN."""
    o0, o1, o2, i0, i1, i2, t_min, t_max, far_scale = ray

    def select_min(a, c):  # Numba's ``min(a, c)``: ``c if c < a else a``
        return builder.select(builder.fcmp_ordered("<", c, a), c, a)

    def select_max(a, c):
        return builder.select(builder.fcmp_ordered(">", c, a), c, a)

    nears, fars = [], []
    for vector, o, inv in ((x, o0, i0), (y, o1, i1), (z, o2, i2)):
        t = builder.fmul(builder.fsub(vector, _splat(builder, o, 4)), _splat(builder, inv, 4))
        t0 = builder.shuffle_vector(t, t, _lane_mask(0, 1))  # the lower planes' distances
        t1 = builder.shuffle_vector(t, t, _lane_mask(2, 3))
        nears.append(select_min(t0, t1))
        fars.append(select_max(t0, t1))
    # The scalar test's near = max(max(max(nx, ny), nz), t_min) and hit = near <= min(far, t_max), in fewer
    # dependent steps: max(max(nx, ny), max(t_min, nz)) and (near <= far) & (near <= t_max). The same
    # decisions where t_min and t_max are not NaN (an enabled ray's interval): ``select`` keeps its first
    # operand where the second is NaN, so t_min goes first; near is only compared (a zero's sign is moot).
    # An empty box has NaN x bounds in its row (box_rows), so a NaN near: no hit.
    near = select_max(select_max(nears[0], nears[1]), select_max(_splat(builder, t_min, 2), nears[2]))
    far = builder.fmul(select_min(select_min(fars[0], fars[1]), fars[2]), _splat(builder, far_scale, 2))
    hit = builder.and_(
        builder.fcmp_ordered("<=", near, far), builder.fcmp_ordered("<=", near, _splat(builder, t_max, 2))
    )
    i32 = ir.IntType(32)
    lane = lambda v, k: builder.extract_element(v, ir.Constant(i32, k))  # noqa: E731
    values = [lane(hit, 0), lane(near, 0), lane(hit, 1), lane(near, 1)]
    return context.make_tuple(builder, signature.return_type, values)


@intrinsic
def _box_pair(typingctx, rows, b, o0, o1, o2, i0, i1, i2, t_min, t_max, far_scale):
    """Both child boxes of a node (its twelve values at flat offset ``b`` of ``rows``, laid out by
    :func:`box_rows`) with the slab test of :func:`_box` for a ray parallel to no axis:
    ``(hit0, near0, hit1, near1)`` (:func:`_slab_pair`). Each axis is one vector load, ``[lower of box 0,
    lower of box 1, upper of box 0, upper of box 1]``."""
    sig = types.Tuple((types.boolean, o0, types.boolean, o0))(rows, b, o0, o1, o2, i0, i1, i2, t_min, t_max, far_scale)  # fmt: skip

    def codegen(context, builder, signature, args):
        ty = args[2].type
        size = 4 if ty == ir.FloatType() else 8
        v4 = ir.VectorType(ty, 4)
        data = context.make_array(signature.args[0])(context, builder, args[0]).data

        def axis(k):  # the four values at offset ``b + 4 k``
            at = builder.gep(data, [builder.add(args[1], ir.Constant(args[1].type, 4 * k))])
            return builder.load(builder.bitcast(at, v4.as_pointer()), align=size)

        return _slab_pair(context, builder, signature, axis(0), axis(1), axis(2), args[2:])

    return sig, codegen


@intrinsic
def _blended_box_pair(typingctx, lower, upper, b0, b1, w, one, o0, o1, o2, i0, i1, i2, t_min, t_max, far_scale):
    """:func:`_node_keys` then :func:`_box_pair` for a ray parallel to no axis, without the row in memory: the
    node's six lower and six upper corner values of one keyframe at flat offset ``b0`` of the keyframe boxes
    ``lower``, ``upper`` ``(K, M, 2, 3)`` and of the next at ``b1`` (each a four- and a two-lane load) are
    blended lane by lane as :func:`_blend` blends them (equal values kept), rearranged into the rows of
    :func:`box_rows` (an empty box's x bounds NaN) and tested by :func:`_slab_pair`."""
    sig = types.Tuple((types.boolean, o0, types.boolean, o0))(
        lower, upper, b0, b1, w, one, o0, o1, o2, i0, i1, i2, t_min, t_max, far_scale
    )

    def codegen(context, builder, signature, args):
        ty = args[4].type
        size = 4 if ty == ir.FloatType() else 8
        v4, v2 = ir.VectorType(ty, 4), ir.VectorType(ty, 2)
        arrays = [context.make_array(signature.args[k])(context, builder, args[k]).data for k in (0, 1)]
        name = "llvm.fma.v4f32" if ty == ir.FloatType() else "llvm.fma.v4f64"
        fma = cgutils.get_or_insert_function(builder.module, ir.FunctionType(v4, [v4, v4, v4]), name)
        w = args[4]
        keep, weight = _splat(builder, builder.fsub(args[5], w), 4), _splat(builder, w, 4)

        def corners(data, b):  # the six values at offset ``b``: a vector of the first four, one of the last two twice
            head = builder.load(builder.bitcast(builder.gep(data, [b]), v4.as_pointer()), align=size)
            at = builder.gep(data, [builder.add(b, ir.Constant(b.type, 4))])
            tail = builder.load(builder.bitcast(at, v2.as_pointer()), align=size)
            tail = builder.shuffle_vector(tail, tail, _lane_mask(0, 1, 0, 1))
            return head, tail

        def blended(data):  # _blend(a, c, w, one) = fma(1 - w, a, w c), a kept where a == c
            out = []
            for a, c in zip(corners(data, args[2]), corners(data, args[3]), strict=True):
                mixed = builder.call(fma, [keep, a, builder.fmul(weight, c)])
                out.append(builder.select(builder.fcmp_ordered("==", a, c), a, mixed))
            return out

        # lower: [l0x l0y l0z l1x] [l1y l1z . .]; upper likewise
        (lh, lt), (uh, ut) = blended(arrays[0]), blended(arrays[1])
        lower_xyz = builder.shuffle_vector(lh, lt, _lane_mask(0, 1, 2, 3, 4, 5, 4, 5))  # l0x l0y l0z l1x l1y l1z
        upper_xyz = builder.shuffle_vector(uh, ut, _lane_mask(0, 1, 2, 3, 4, 5, 4, 5))
        x = builder.shuffle_vector(lower_xyz, upper_xyz, _lane_mask(0, 3, 8, 11))
        y = builder.shuffle_vector(lower_xyz, upper_xyz, _lane_mask(1, 4, 9, 12))
        z = builder.shuffle_vector(lower_xyz, upper_xyz, _lane_mask(2, 5, 10, 13))
        # An empty box (not lower <= upper in x) gets NaN x bounds, as box_rows marks it.
        lo, up = (builder.shuffle_vector(x, x, _lane_mask(*lanes)) for lanes in ((0, 1), (2, 3)))
        full = builder.fcmp_ordered("<=", lo, up)
        full = builder.shuffle_vector(full, full, _lane_mask(0, 1, 0, 1))
        nan = ir.Constant(v4, [float("nan")] * 4)
        x = builder.select(full, x, nan)
        return _slab_pair(context, builder, signature, x, y, z, args[6:])

    return sig, codegen


@numba.njit(nogil=True, cache=True)
def box_rows(node_lower, node_upper, rows):
    """The child boxes of every node as :func:`_box_pair` reads them: ``rows[n, 4 a : 4 a + 4]`` holds axis
    ``a``'s lower plane of box 0 and of box 1, then its upper plane of box 0 and of box 1 (one row of twelve
    values per node: both boxes of a visit in one or two cache lines, each axis one vector load). A box that
    the slab test rejects by its x bounds alone (not ``lower <= upper``: an empty box) gets NaN x bounds,
    which make its near distance NaN and so reject it in :func:`_box_pair` without a separate test."""
    nan = node_lower.dtype.type(np.nan)
    for n in range(node_lower.shape[0]):
        for a in range(3):
            rows[n, 4 * a] = node_lower[n, 0, a]
            rows[n, 4 * a + 1] = node_lower[n, 1, a]
            rows[n, 4 * a + 2] = node_upper[n, 0, a]
            rows[n, 4 * a + 3] = node_upper[n, 1, a]
        for k in range(2):
            if not node_lower[n, k, 0] <= node_upper[n, k, 0]:
                rows[n, k] = nan
                rows[n, 2 + k] = nan


@numba.njit(cache=True)
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


@numba.njit(cache=True)
def _pick(k, a0, a1, a2):
    return a0 if k == 0 else (a1 if k == 1 else a2)


@numba.njit(cache=True, inline="always")  # inlined where it is called: once per ray (and per instance level)
def _load(o0, o1, o2, d0, d1, d2, one, clamp, huge, clamped_huge):
    """The loaded ray's constants: reciprocal direction, axes and shear (Woop et al. section 3)."""
    i0 = _reciprocal(d0, clamp, huge, clamped_huge, one)
    i1 = _reciprocal(d1, clamp, huge, clamped_huge, one)
    i2 = _reciprocal(d2, clamp, huge, clamped_huge, one)
    kx, ky, kz = _shear_axes(d0, d1, d2)
    sx, sy, sz = _shear(_pick(kx, d0, d1, d2), _pick(ky, d0, d1, d2), _pick(kz, d0, d1, d2))
    return i0, i1, i2, kx, ky, kz, sx, sy, sz


@numba.njit(cache=True)
def _box(lx, ly, lz, hx, hy, hz, o0, o1, o2, i0, i1, i2, t_min, t_max, far_scale, parallel, inf):
    """The conservative slab test of a box (the formulas of :mod:`jaxrt._src.formulas.box`): ``(hit, t_near)``."""
    n0, f0 = _slab_axis(lx, hx, o0, i0, parallel)
    n1, f1 = _slab_axis(ly, hy, o1, i1, parallel)
    n2, f2 = _slab_axis(lz, hz, o2, i2, parallel)
    hit, t_near, _ = _box_hit(n0, f0, n1, f1, n2, f2, lx, hx, t_min, t_max, far_scale)
    return hit, t_near


@numba.njit(cache=True)
def _sheared(x, y, z, o0, o1, o2, kx, ky, kz, sx, sy, sz):
    """A vertex relative to the origin, sheared: ``(px, py, z)``."""
    r0, r1, r2 = x - o0, y - o1, z - o2
    return _sheared_vertex(_pick(kx, r0, r1, r2), _pick(ky, r0, r1, r2), _pick(kz, r0, r1, r2), sx, sy, sz)


@numba.njit(cache=True, inline="always")
def _watertight(ax, ay, z0, bx, by, z1, cx, cy, z2, t_min, t_max, cull, inf):
    """The watertight test's edge functions, culling and distance on the sheared vertices ``(x, y, z)`` of a
    triangle (cull sense ``cull``: +1 culls clockwise, -1 counterclockwise): ``(accepted, distance)``; the
    distance is computed only for a triangle the ray passes through."""
    e0, e1, e2 = _edge_functions(ax, ay, bx, by, cx, cy)
    inside, det = _edges_inside(e0, e1, e2)
    if not inside or (cull != 0 and not _facing_accepts(det, cull)):  # cull 0 accepts every facing
        return False, inf
    t = _plane_distance(e0, e1, e2, z0, z1, z2, det)
    if _in_interval(t, t_min, t_max):
        return True, t
    return False, inf


@numba.njit(cache=True)
def _triangle(v, o0, o1, o2, kx, ky, kz, sx, sy, sz, t_min, t_max, cull, inf):
    """The watertight test (:func:`jaxrt._src.primitives.triangle.watertight`) of a triangle ``v`` (nine
    coordinates) with a cull sense ``cull`` (+1 culls clockwise, -1 counterclockwise): ``(accepted, distance)``."""
    ax, ay, z0 = _sheared(v[0], v[1], v[2], o0, o1, o2, kx, ky, kz, sx, sy, sz)
    bx, by, z1 = _sheared(v[3], v[4], v[5], o0, o1, o2, kx, ky, kz, sx, sy, sz)
    cx, cy, z2 = _sheared(v[6], v[7], v[8], o0, o1, o2, kx, ky, kz, sx, sy, sz)
    return _watertight(ax, ay, z0, bx, by, z1, cx, cy, z2, t_min, t_max, cull, inf)


@numba.njit(cache=True, inline="always")
def _first(near0, near1, t_min, any_hit):
    """Whether child 0 is entered first when both are: the nearer entry first; with ``any_hit``, a box that
    holds the ray's start (entry ``t_min``) after one entered ahead (the portable ``step._any_hit_order``)."""
    if any_hit:
        start0 = near0 <= t_min
        start1 = near1 <= t_min
        if start0 != start1:
            return start1
    return near0 <= near1


@numba.njit(cache=True)
def _row(m0, m1, m2, x0, x1, x2):
    """``m0 x0 + m1 x1 + m2 x2`` as XLA's CPU backend sums a row of the transform in the portable transition:
    a reduction whose multiply-adds are contracted, ``fma(m2, x2, fma(m1, x1, m0 x0))``."""
    return _fma(m2, x2, _fma(m1, x1, m0 * x0))


@numba.njit(cache=True)
def _insert(hit_distance, hit_leaf, hit_chains, k, t, leaf, chain, level, levels):
    """Insert a hit at distance ``t`` into the sorted list of ``k`` hits after those at the same distance (the
    portable ``_insert``), with the path ``chain[:level]``; returns 1 (the hit is counted even when it falls
    past the list's end)."""
    position = 0
    for h in range(k):
        if hit_distance[h] <= t:
            position += 1
    if position < k:
        for h in range(k - 1, position, -1):
            hit_distance[h] = hit_distance[h - 1]
            hit_leaf[h] = hit_leaf[h - 1]
            for j in range(levels):
                hit_chains[h, j] = hit_chains[h - 1, j]
        hit_distance[position] = t
        hit_leaf[position] = leaf
        for j in range(levels):
            hit_chains[position, j] = chain[j] if j < level else -1
    return 1


@numba.njit(cache=True, inline="always")
def _keyframe_position(time, start, end, span, segments, vanish_start, vanish_end, one):
    """:func:`jaxrt._src.motion.keyframe_position` for one ray: ``(index, weight, visible)`` (``span`` is
    ``end - start`` rounded from the spec's floats, ``segments`` is ``K - 1``, both in the time's dtype)."""
    position = (time - start) / span * segments
    if np.isnan(position):  # NaN times take keyframe 0
        position = one - one
    clamped = min(max(position, one - one), segments)
    # The clipped floor as a float (a whole number, exact), so that the weight stays in the time's dtype.
    key = min(max(np.floor(clamped), one - one), segments - one)
    visible = not (time < start and vanish_start) and not (time > end and vanish_end)
    return np.int64(key), clamped - key, visible


@numba.njit(cache=True, inline="always")
def _blend(a, b, w, one):
    """:func:`jaxrt._src.motion.blend`, ``(1 - w) a + w b``, as XLA's CPU backend contracts it:
    ``fma(1 - w, a, w b)``."""
    return _fma(one - w, a, w * b)


@numba.njit(cache=True, inline="always")
def _node_keys(lower, upper, key, node, w, one, out):
    """Node ``node``'s two child boxes blended between keyframes ``key`` and ``key + 1`` (the portable
    ``_node_boxes_at``: equal corners kept as they are) into ``out``: both lowers, then both uppers."""
    for c in range(2):
        for a in range(3):
            x, y = lower[key, node, c, a], lower[key + 1, node, c, a]
            out[3 * c + a] = x if x == y else _blend(x, y, w, one)
            x, y = upper[key, node, c, a], upper[key + 1, node, c, a]
            out[6 + 3 * c + a] = x if x == y else _blend(x, y, w, one)


@numba.njit(cache=True, inline="always")
def _leaf_keys(keys, key, leaf, w, one, out):
    """Leaf ``leaf``'s triangle blended between keyframes ``key`` and ``key + 1`` into ``out`` (nine values)."""
    for v in range(3):
        for a in range(3):
            out[3 * v + a] = _blend(keys[key, leaf, v, a], keys[key + 1, leaf, v, a], w, one)


@numba.njit(nogil=True, cache=True)
def trace_rays(
    node_lower, node_upper, node_children, leaf_triangle, world_to_object, child_root, instance_facing,
    instance_mask, analytic_rows, node_keys_lower, node_keys_upper, leaf_keys, leaf_moving, motion_f, motion_i,
    curve_segments, curve_flags, origin, direction, t_min_all, t_max_all, enabled, mask_all, time_all, curve_frame,
    consts, params, counter, chunk, end, out_distance,
    out_leaf, out_chain, out_visited, out_tested, out_overflow, out_hit_distance, out_hit_leaf, out_hit_total,
    out_hit_chain,
):  # fmt: skip
    """Trace rays ``0`` to ``end``; results go to the ``out_*`` arrays. Runs without the GIL: every thread that
    calls it with the same ``counter`` (``int64[1]``, starting at 0) claims the next ``chunk`` rays until all are
    claimed.

    ``params`` holds ``root, primitive_leaves, levels, stack_size, any_hit, cull, hit_list, max_hits,
    count_all, analytic`` (``analytic``: leaves whose row in ``analytic_rows`` has a shape code are tested as
    that shape, the others as triangles); ``consts`` the float constants in the geometry's dtype
    (:func:`jaxrt._src.traversal.cpu.constants`). With ``hit_list`` the ``K = max_hits`` nearest hits go to
    ``out_hit_*`` (``(end, K)``, ``(end, K)``, ``(end,)``, ``(end, K, levels)``) as the portable
    :class:`~jaxrt._src.traversal.step.HitList` keeps them; ``out_distance`` is then the culling distance and
    ``out_leaf`` the first hit.

    With ``params[10]`` (primitive keyframe motion, no instances) each ray's node boxes and triangles are the
    keyframes blended at its time ``time_all[i]`` (:func:`_keyframe_position`, :func:`_blend`): the node boxes
    ``node_keys_*`` ``(K, M, 2, 3)`` where ``motion_i[0]``, the triangles ``leaf_keys`` ``(L, P, 3, 3)``, and
    moving leaves (``leaf_moving``) vanish outside the range on a ``"vanish"`` border. ``motion_f`` holds
    the node then the leaf keyframes' ``start, end, end - start, K - 1`` in the geometry's dtype, ``motion_i``
    whether nodes move, vanish at start, vanish at end.

    With ``params[11]`` (curves, in a primitive structure) leaves whose flags ``curve_flags`` have ``IS_CURVE``
    are tested as their segment in ``curve_segments`` (``(P, 6, 4)``) with the ray's frame ``curve_frame[i]``
    (:func:`jaxrt._src.traversal.cpu_curves.curve_leaf`, options ``params[11:19]``).
    """
    root, primitive_leaves, levels, stack_size, any_hit, cull = params[0], params[1], params[2], params[3], params[4] != 0, params[5]  # fmt: skip
    hit_list, k, count_all, analytic = params[6] != 0, params[7], params[8] != 0, params[9] != 0
    moving, nodes_move = params[10] != 0, motion_i[0] != 0
    curves = params[11] != 0
    vanish_start, vanish_end = motion_i[1] != 0, motion_i[2] != 0
    key_v = np.empty(9, consts.dtype)
    key_b = np.empty(12, consts.dtype)
    hit_distance = np.empty(max(k, 1), consts.dtype)
    hit_leaf = np.empty(max(k, 1), np.int32)
    hit_chains = np.empty((max(k, 1), max(levels, 1)), np.int32)
    stack = np.empty(max(stack_size, 1), np.int32)
    base = np.zeros(max(levels, 1), np.int32)
    chain = np.full(max(levels, 1), -1, np.int32)
    level_ray = np.zeros((max(levels, 1), 6), consts.dtype)
    level_facing = np.ones(max(levels, 1), np.int32)
    hit_chain = np.full(max(levels, 1), -1, np.int32)
    one, inf, clamp, huge, clamped_huge = consts[0], consts[2], consts[3], consts[4], consts[5]
    far_scale, parallel = consts[6], consts[7]
    instances = child_root.shape[0]
    # Flat views: node ``k`` has its two child boxes at ``6k`` (lower and upper), its children at ``2k``.
    lf, hf, cf, tf = node_lower.reshape(-1), node_upper.reshape(-1), node_children.reshape(-1), leaf_triangle.reshape(-1)  # fmt: skip
    while True:  # claim ranges of ``chunk`` rays until none is left (threads finish together)
        begin = _fetch_add(counter, chunk)
        if begin >= end:
            break
        for i in range(begin, min(begin + chunk, end)):
            if not enabled[i]:
                out_distance[i] = -inf
                out_leaf[i] = -1
                for j in range(levels):
                    out_chain[i, j] = -1
                out_visited[i] = 0
                out_tested[i] = 0
                out_overflow[i] = False
                if hit_list:
                    for h in range(k):
                        out_hit_distance[i, h] = inf
                        out_hit_leaf[i, h] = -1
                        for j in range(levels):
                            out_hit_chain[i, h, j] = -1
                    out_hit_total[i] = 0
                continue
            t_min = t_min_all[i]
            distance = t_max_all[i]
            ray_mask = mask_all[i]
            leaf = -1
            o0, o1, o2 = origin[i, 0], origin[i, 1], origin[i, 2]
            w0, w1, w2 = direction[i, 0], direction[i, 1], direction[i, 2]  # the loaded direction
            i0, i1, i2, kx, ky, kz, sx, sy, sz = _load(o0, o1, o2, w0, w1, w2, one, clamp, huge, clamped_huge)
            node_key, node_w, leaf_key, leaf_w, visible = 0, one, 0, one, True
            if moving:
                time = time_all[i]
                node_key, node_w, _ = _keyframe_position(time, motion_f[0], motion_f[1], motion_f[2], motion_f[3], False, False, one)  # fmt: skip
                leaf_key, leaf_w, visible = _keyframe_position(time, motion_f[4], motion_f[5], motion_f[6], motion_f[7], vanish_start, vanish_end, one)  # fmt: skip
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
            total = 0
            if hit_list:
                for h in range(k):
                    hit_distance[h] = inf
                    hit_leaf[h] = -1
                    for j in range(levels):
                        hit_chains[h, j] = -1
            while True:
                visited += 1
                un = np.uint64(node)
                c0 = cf[un * _U2]
                c1 = cf[un * _U2 + _U1]
                b = un * _U6
                if moving and nodes_move:  # the node's keyframe boxes blended at the ray's time
                    _node_keys(node_keys_lower, node_keys_upper, node_key, node, node_w, one, key_b)
                    hit0, near0 = _box(key_b[0], key_b[1], key_b[2], key_b[6], key_b[7], key_b[8], o0, o1, o2, i0, i1, i2, t_min, distance, far_scale, parallel, inf)  # fmt: skip
                    hit1, near1 = _box(key_b[3], key_b[4], key_b[5], key_b[9], key_b[10], key_b[11], o0, o1, o2, i0, i1, i2, t_min, distance, far_scale, parallel, inf)  # fmt: skip
                else:
                    hit0, near0 = _box(lf[b], lf[b + _U1], lf[b + _U2], hf[b], hf[b + _U1], hf[b + _U2], o0, o1, o2, i0, i1, i2, t_min, distance, far_scale, parallel, inf)  # fmt: skip
                    hit1, near1 = _box(lf[b + _U3], lf[b + _U4], lf[b + _U5], hf[b + _U3], hf[b + _U4], hf[b + _U5], o0, o1, o2, i0, i1, i2, t_min, distance, far_scale, parallel, inf)  # fmt: skip
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
                            if analytic and analytic_rows[k0, 3] != 0:
                                ok0, t0 = _analytic(analytic_rows[k0], o0, o1, o2, w0, w1, w2, t_min, distance, one, inf)  # fmt: skip
                            elif curves and (curve_flags[k0] & _IS_CURVE) != 0:
                                ok0, t0 = _curve_leaf(curve_segments, curve_flags, k0, o0, o1, o2, curve_frame, i, t_min, distance, params, 11, inf)  # fmt: skip
                            elif moving:  # the triangle blended at the ray's time; a moving one may vanish
                                _leaf_keys(leaf_keys, leaf_key, k0, leaf_w, one, key_v)
                                v = (key_v[0], key_v[1], key_v[2], key_v[3], key_v[4], key_v[5], key_v[6], key_v[7], key_v[8])  # fmt: skip
                                ok0, t0 = _triangle(v, o0, o1, o2, kx, ky, kz, sx, sy, sz, t_min, distance, sense, inf)  # fmt: skip
                                if not visible and leaf_moving[k0]:
                                    ok0, t0 = False, inf
                            else:
                                q = np.uint64(k0) * _U9
                                v = (tf[q], tf[q + _U1], tf[q + _U2], tf[q + _U3], tf[q + _U4], tf[q + _U5], tf[q + _U6], tf[q + _U7], tf[q + _U8])  # fmt: skip
                                ok0, t0 = _triangle(v, o0, o1, o2, kx, ky, kz, sx, sy, sz, t_min, distance, sense, inf)  # fmt: skip
                    else:
                        g = min(max(k0 - primitive_leaves, 0), instances - 1)
                        e0 = -1 - g
                        inner0 = hit0 and (instance_mask[g] & ray_mask) != 0
                if c1 < 0:
                    if k1 < primitive_leaves:
                        if hit1:
                            tested += 1
                            if analytic and analytic_rows[k1, 3] != 0:
                                ok1, t1 = _analytic(analytic_rows[k1], o0, o1, o2, w0, w1, w2, t_min, distance, one, inf)  # fmt: skip
                            elif curves and (curve_flags[k1] & _IS_CURVE) != 0:
                                ok1, t1 = _curve_leaf(curve_segments, curve_flags, k1, o0, o1, o2, curve_frame, i, t_min, distance, params, 11, inf)  # fmt: skip
                            elif moving:  # the triangle blended at the ray's time; a moving one may vanish
                                _leaf_keys(leaf_keys, leaf_key, k1, leaf_w, one, key_v)
                                v = (key_v[0], key_v[1], key_v[2], key_v[3], key_v[4], key_v[5], key_v[6], key_v[7], key_v[8])  # fmt: skip
                                ok1, t1 = _triangle(v, o0, o1, o2, kx, ky, kz, sx, sy, sz, t_min, distance, sense, inf)  # fmt: skip
                                if not visible and leaf_moving[k1]:
                                    ok1, t1 = False, inf
                            else:
                                q = np.uint64(k1) * _U9
                                v = (tf[q], tf[q + _U1], tf[q + _U2], tf[q + _U3], tf[q + _U4], tf[q + _U5], tf[q + _U6], tf[q + _U7], tf[q + _U8])  # fmt: skip
                                ok1, t1 = _triangle(v, o0, o1, o2, kx, ky, kz, sx, sy, sz, t_min, distance, sense, inf)  # fmt: skip
                    else:
                        g = min(max(k1 - primitive_leaves, 0), instances - 1)
                        e1 = -1 - g
                        inner1 = hit1 and (instance_mask[g] & ray_mask) != 0
                culling = distance
                first = leaf
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
                if hit_list:
                    # Both leaves' hits into the sorted list (each after the hits at its distance); the culling
                    # distance becomes the K-th hit's once more than K are known (never when counting).
                    distance = culling
                    if ok0:
                        total += _insert(hit_distance, hit_leaf, hit_chains, k, t0, k0, chain, level, levels)
                    if ok1:
                        total += _insert(hit_distance, hit_leaf, hit_chains, k, t1, k1, chain, level, levels)
                    if not count_all and k > 0 and total > k:
                        distance = hit_distance[k - 1]
                    leaf = hit_leaf[0] if k > 0 else first
                finished = False
                if inner0 and inner1:
                    if _first(near0, near1, t_min, any_hit):
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
                        m = world_to_object
                        # Row by row, as the portable transition sums them.
                        n0 = _row(m[g, 0, 0], m[g, 0, 1], m[g, 0, 2], b0, b1, b2) + m[g, 0, 3]
                        n1 = _row(m[g, 1, 0], m[g, 1, 1], m[g, 1, 2], b0, b1, b2) + m[g, 1, 3]
                        n2 = _row(m[g, 2, 0], m[g, 2, 1], m[g, 2, 2], b0, b1, b2) + m[g, 2, 3]
                        v0 = _row(m[g, 0, 0], m[g, 0, 1], m[g, 0, 2], d0, d1, d2)
                        v1 = _row(m[g, 1, 0], m[g, 1, 1], m[g, 1, 2], d0, d1, d2)
                        v2 = _row(m[g, 2, 0], m[g, 2, 1], m[g, 2, 2], d0, d1, d2)
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
                    o0, o1, o2 = b0, b1, b2
                    w0, w1, w2 = d0, d1, d2
                    i0, i1, i2, kx, ky, kz, sx, sy, sz = _load(b0, b1, b2, d0, d1, d2, one, clamp, huge, clamped_huge)
            out_distance[i] = distance
            out_leaf[i] = leaf
            for j in range(levels):
                out_chain[i, j] = hit_chain[j]
            if hit_list:
                for h in range(k):
                    out_hit_distance[i, h] = hit_distance[h]
                    out_hit_leaf[i, h] = hit_leaf[h]
                    for j in range(levels):
                        out_hit_chain[i, h, j] = hit_chains[h, j]
                out_hit_total[i] = total
            out_visited[i] = visited
            out_tested[i] = tested
            out_overflow[i] = overflow


@numba.njit(nogil=True, cache=True)
def trace_flat(
    node_lower, node_upper, node_children, leaf_triangle, rows, origin, direction, t_min_all, t_max_all, enabled,
    consts, root, stack_size, any_hit, cull, counter, chunk, end, out_distance, out_leaf, out_visited, out_tested,
    out_overflow, moving, node_keys_lower, node_keys_upper, leaf_keys, leaf_moving, motion_f, motion_i, time_all,
    formula_rows, analytic_rows,
):  # fmt: skip
    """:func:`trace_rays` for a primitive structure of triangles and the leaves of kinds with an analytic row
    (built-in spheres; no instance levels, no hit list, no built-in intersection functions): the same loop
    without the instance, hit-list and analytic bookkeeping, and the same results. The instance chain (zero columns) is not written. ``rows`` holds the node boxes as
    :func:`box_rows` lays them out, for the vector test; the scalar test reads ``node_lower`` and
    ``node_upper``. With ``moving`` (triangles only), the primitive keyframe motion of :func:`trace_rays` (its
    ``node_keys_*`` to ``time_all`` arguments): each visited node's boxes and each tested triangle are blended
    at the ray's time first. With ``formula_rows``, a leaf whose row of ``analytic_rows`` (as :func:`trace_rays`
    reads them) has a kind's code (:mod:`jaxrt._src.traversal.analytic_rows`) is tested by that kind's formula,
    as :func:`_analytic` tests it."""
    stack = np.empty(max(stack_size, 1), np.int32)
    nodes_move, vanish_start, vanish_end = motion_i[0] != 0, motion_i[1] != 0, motion_i[2] != 0
    key_b = np.empty(12, consts.dtype)  # a node's boxes blended: lowers, then uppers (as _node_keys writes them)
    key_v = np.empty(9, consts.dtype)
    one, inf, clamp, huge, clamped_huge = consts[0], consts[2], consts[3], consts[4], consts[5]
    far_scale, parallel = consts[6], consts[7]
    lf, hf, cf, tf = node_lower.reshape(-1), node_upper.reshape(-1), node_children.reshape(-1), leaf_triangle.reshape(-1)  # fmt: skip
    rf = rows.reshape(-1)
    lkf, ukf = node_keys_lower.reshape(-1), node_keys_upper.reshape(-1)
    node_count = np.uint64(node_keys_lower.shape[1])
    af = analytic_rows.reshape(-1)
    width = np.uint64(analytic_rows.shape[1])
    while True:
        begin = _fetch_add(counter, chunk)
        if begin >= end:
            break
        for i in range(begin, min(begin + chunk, end)):
            if not enabled[i]:
                out_distance[i] = -inf
                out_leaf[i] = -1
                out_visited[i] = 0
                out_tested[i] = 0
                out_overflow[i] = False
                continue
            t_min = t_min_all[i]
            distance = t_max_all[i]
            leaf = -1
            o0, o1, o2 = origin[i, 0], origin[i, 1], origin[i, 2]
            w0, w1, w2 = direction[i, 0], direction[i, 1], direction[i, 2]
            i0, i1, i2, kx, ky, kz, sx, sy, sz = _load(o0, o1, o2, w0, w1, w2, one, clamp, huge, clamped_huge)
            # The sheared triangle test reads the vertex components ``kx, ky, kz`` and the origin's.
            ox, oy, oz = _pick(kx, o0, o1, o2), _pick(ky, o0, o1, o2), _pick(kz, o0, o1, o2)
            ux, uy, uz = np.uint64(kx), np.uint64(ky), np.uint64(kz)
            straight = abs(i0) < parallel and abs(i1) < parallel and abs(i2) < parallel
            node_key, node_w, leaf_key, leaf_w, visible = 0, one, 0, one, True
            if moving:
                time = time_all[i]
                node_key, node_w, _ = _keyframe_position(time, motion_f[0], motion_f[1], motion_f[2], motion_f[3], False, False, one)  # fmt: skip
                leaf_key, leaf_w, visible = _keyframe_position(time, motion_f[4], motion_f[5], motion_f[6], motion_f[7], vanish_start, vanish_end, one)  # fmt: skip
            node = root
            depth = 0
            visited = 0
            tested = 0
            overflow = False
            while True:
                visited += 1
                un = np.uint64(node)
                c0 = cf[un * _U2]
                c1 = cf[un * _U2 + _U1]
                b = un * _U6
                if moving and nodes_move:  # the node's keyframe boxes blended at the ray's time
                    if straight:  # both keyframes' corners blended in vector registers
                        at = (np.uint64(node_key) * node_count + un) * _U6
                        hit0, near0, hit1, near1 = _blended_box_pair(lkf, ukf, at, at + node_count * _U6, node_w, one, o0, o1, o2, i0, i1, i2, t_min, distance, far_scale)  # fmt: skip
                    else:
                        _node_keys(node_keys_lower, node_keys_upper, node_key, node, node_w, one, key_b)
                        hit0, near0 = _box(key_b[0], key_b[1], key_b[2], key_b[6], key_b[7], key_b[8], o0, o1, o2, i0, i1, i2, t_min, distance, far_scale, parallel, inf)  # fmt: skip
                        hit1, near1 = _box(key_b[3], key_b[4], key_b[5], key_b[9], key_b[10], key_b[11], o0, o1, o2, i0, i1, i2, t_min, distance, far_scale, parallel, inf)  # fmt: skip
                elif straight:
                    hit0, near0, hit1, near1 = _box_pair(rf, un * _U12, o0, o1, o2, i0, i1, i2, t_min, distance, far_scale)  # fmt: skip
                else:
                    hit0, near0 = _box(lf[b], lf[b + _U1], lf[b + _U2], hf[b], hf[b + _U1], hf[b + _U2], o0, o1, o2, i0, i1, i2, t_min, distance, far_scale, parallel, inf)  # fmt: skip
                    hit1, near1 = _box(lf[b + _U3], lf[b + _U4], lf[b + _U5], hf[b + _U3], hf[b + _U4], hf[b + _U5], o0, o1, o2, i0, i1, i2, t_min, distance, far_scale, parallel, inf)  # fmt: skip
                ok0 = False
                ok1 = False
                t0 = inf
                t1 = inf
                if c0 < 0 and hit0:
                    tested += 1
                    a = np.uint64(-1 - c0) * width
                    if formula_rows and _is_formula_row(af[a + _U3]):  # a kind's analytic row (built-in sphere)
                        ok0, t0 = _formula_row(af, a, o0, o1, o2, w0, w1, w2, t_min, distance, inf)
                        if not ok0:
                            t0 = inf
                    elif moving:  # the triangle blended at the ray's time; a moving one may vanish
                        _leaf_keys(leaf_keys, leaf_key, -1 - c0, leaf_w, one, key_v)
                        ok0, t0 = _triangle_at(key_v, _U1 - _U1, ux, uy, uz, ox, oy, oz, sx, sy, sz, t_min, distance, cull, inf)  # fmt: skip
                        if not visible and leaf_moving[-1 - c0]:
                            ok0, t0 = False, inf
                    else:
                        ok0, t0 = _triangle_at(tf, np.uint64(-1 - c0) * _U9, ux, uy, uz, ox, oy, oz, sx, sy, sz, t_min, distance, cull, inf)  # fmt: skip
                if c1 < 0 and hit1:
                    tested += 1
                    a = np.uint64(-1 - c1) * width
                    if formula_rows and _is_formula_row(af[a + _U3]):  # a kind's analytic row (built-in sphere)
                        ok1, t1 = _formula_row(af, a, o0, o1, o2, w0, w1, w2, t_min, distance, inf)
                        if not ok1:
                            t1 = inf
                    elif moving:
                        _leaf_keys(leaf_keys, leaf_key, -1 - c1, leaf_w, one, key_v)
                        ok1, t1 = _triangle_at(key_v, _U1 - _U1, ux, uy, uz, ox, oy, oz, sx, sy, sz, t_min, distance, cull, inf)  # fmt: skip
                        if not visible and leaf_moving[-1 - c1]:
                            ok1, t1 = False, inf
                    else:
                        ok1, t1 = _triangle_at(tf, np.uint64(-1 - c1) * _U9, ux, uy, uz, ox, oy, oz, sx, sy, sz, t_min, distance, cull, inf)  # fmt: skip
                if ok0 or ok1:
                    if t1 < t0:
                        best_t, best_leaf = t1, -1 - c1
                    else:
                        best_t, best_leaf = t0, -1 - c0
                    # Strictly nearer than the current hit; the first hit may lie exactly at t_max (closed interval).
                    if best_t < distance or (leaf < 0 and best_t <= distance):
                        distance = best_t
                        leaf = best_leaf
                inner0 = hit0 and c0 >= 0
                inner1 = hit1 and c1 >= 0
                if inner0 and inner1:
                    if _first(near0, near1, t_min, any_hit):
                        near, far = c0, c1
                    else:
                        near, far = c1, c0
                    if depth < stack_size:
                        stack[np.uint64(depth)] = far
                        depth += 1
                    else:
                        overflow = True
                    node = near
                elif inner0:
                    node = c0
                elif inner1:
                    node = c1
                elif depth == 0:
                    break
                else:
                    depth -= 1
                    node = stack[np.uint64(depth)]
                if any_hit and leaf >= 0:
                    break
            out_distance[i] = distance
            out_leaf[i] = leaf
            out_visited[i] = visited
            out_tested[i] = tested
            out_overflow[i] = overflow


@numba.njit(cache=True, inline="always")
def _triangle_at(tf, q, ux, uy, uz, ox, oy, oz, sx, sy, sz, t_min, t_max, cull, inf):
    """:func:`_triangle` of the triangle at flat offset ``q``, its vertices' components read at the ray's
    axes ``ux, uy, uz`` (``kx, ky, kz``; ``ox, oy, oz`` the origin's): the same operations on the same values."""
    ax, ay, z0 = _sheared_vertex(tf[q + ux] - ox, tf[q + uy] - oy, tf[q + uz] - oz, sx, sy, sz)
    bx, by, z1 = _sheared_vertex(tf[q + _U3 + ux] - ox, tf[q + _U3 + uy] - oy, tf[q + _U3 + uz] - oz, sx, sy, sz)
    cx, cy, z2 = _sheared_vertex(tf[q + _U6 + ux] - ox, tf[q + _U6 + uy] - oy, tf[q + _U6 + uz] - oz, sx, sy, sz)
    return _watertight(ax, ay, z0, bx, by, z1, cx, cy, z2, t_min, t_max, cull, inf)


#: Cached functions here embed the formulas: their disk cache is keyed on the formulas' source too.
key_caches_on_formulas(globals(), row_dispatch.SOURCE_DIGEST)
