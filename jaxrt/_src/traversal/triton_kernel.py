"""The Triton traversal kernel: the portable stack traversal's algorithm, one warp of 32 rays per program.

Imported only where Triton is installed (see :mod:`jaxrt._src.traversal.gpu`). It reads the packed arrays of
:mod:`jaxrt._src.traversal.packed` and makes, step for step, the same decisions as the portable step in
:mod:`jaxrt._src.traversal.stack`: both child boxes tested with the conservative slab test (Ize 2013, with
the same handling of zero direction components), leaf children tested on sight with the watertight triangle
test (Woop et al. 2013, edges evaluated in a canonical endpoint order), the nearer inner child entered and the
farther one pushed (in any-hit mode a box holding the ray's start after one entered ahead), ties resolved the
same way. The traversal order, and hence the chosen leaf among equally
distant hits and the first accepted hit in any-hit mode, are those of the portable path wherever both compute
the same values.

Exactness: the slab test, the shear and the watertight test are the shared formulas of
:mod:`jaxrt._src.formulas` (which the portable primitives also call) instantiated for Triton. The kernel is
compiled without floating-point contraction (no fused multiply-add), and the hit distance is a correctly
rounded division (``div_rn``), so every value is the IEEE result of the formulas of
:mod:`jaxrt._src.primitives.triangle` and :mod:`jaxrt._src.primitives.box`. Rounding is monotonic, so each
edge function ``round(a b) - round(c d)`` has the sign of the exact ``a b - c d`` or is zero (zero counts as
inside): no ray passes between triangles that share an edge or a vertex. A contracted
``fma(a, b, -round(c d))`` can take the wrong sign when ``a b`` and ``c d`` nearly cancel, which is why
contraction is off.

Work layout: one program traces ``LANES`` rays. A loop step costs one warp vote (``redux``), which also skips
a leaf test that no ray of the warp needs (``BRANCH``). Each lane keeps its traversal stack in a global scratch
buffer laid out ``[program, stack entry, lane]``, so that a warp's accesses to one stack level fall in one
128-byte line. At most ``n_programs`` programs walk the ray blocks with a stride, so the scratch buffer is
bounded whatever the batch size. The stack has ``STACK`` entries, the structure's depth bound, so it cannot
overflow; a push that would is flagged anyway (and dropped).

Deferred curve tests (compile-time constant ``CURVE_BATCH``; 0 tests curve leaves on sight and generates the
code without it): the segment test is hundreds of instructions, and a warp runs it whenever one lane needs it.
With ``CURVE_BATCH = B`` a step is split into a box phase and a leaf-and-advance phase: a lane whose step
needs a curve test becomes *pending*, keeps that step's children, box hits and near distances, and takes no
further step; the other lanes keep taking complete steps (triangle leaves tested on sight). When ``B`` lanes
are pending, or no other lane can step, every pending lane's step is completed in the same iteration: one
warp-wide curve test for the lanes' first curve leaves, a second only for the lanes with two, then the
step's usual ending (nearer leaf kept, near child entered, far one pushed). A pending lane only waits: its
distance bound, stack and state do not change meanwhile, so each ray makes the same decisions in the same
order, and its result and counters are bit for bit those of the on-sight kernel.

Instances (``LEVELS > 0``, a compile-time constant: with 0 the instance code is not generated): the kernel
makes the decisions of the portable ``step.visit`` and ``step.transition``. An instance leaf is ordered and
pushed like an inner node when its mask meets the ray's; a stack entry keeps its level in its low ``SHIFT``
bits (the portable path derives it from the depth at which each level was entered: the same level). When the
next entry is an instance, or belongs to a shallower level than the loaded ray, a warp-uniform branch loads
that level's ray (origin, unnormalised direction and facing, kept per lane in a ``[program, level, field,
lane]`` scratch buffer), moves it by the instance's world-to-object rows in the portable path's order of
operations, and recomputes the reciprocal direction and shear with correctly rounded divisions, so every
level sees the values the portable path computes. Each new nearest hit copies the current instance chain
into the output.

Keyframe motion (compile-time constants ``NODE_KEYS``, ``LEAF_KEYS`` and ``IWIDTH``; all 0 for a static
scene, whose kernel is then the code generated without them): the ray block carries the ray's keyframe
segment and weight for the scene's primitive motion (computed by the portable path's own JAX function) and
its time. A primitive structure's node rows hold every keyframe's child boxes, node-major, and a step blends
the two around the ray's time as the portable ``step._node_boxes_at`` does (equal corners kept as they are);
leaf triangles are blended as ``motion.LeafKeys`` blends them, ``(1 - w) a + w b``, and a moving leaf is not
hit outside the range on a "vanish" border. Below instances the node boxes are the union boxes (as in the
portable path) and the leaves are blended the same way. A moving instance is visible only inside its table's
range on a "vanish" border, and entering it moves the ray by the inverse of its keyframe transforms blended at
the ray's time: the segment and weight computed as ``motion.keyframe_position`` computes them (correctly
rounded division), the blend, and the adjugate over the determinant of ``instances.invert_transform``,
operation for operation. Without contraction these are the portable path's floats wherever XLA evaluates the
same operations in the same order.

Hit lists (compile-time constants ``MAX_HITS`` and ``COUNT``; 0 and ``False`` generate none of this code): the
portable ``step.HitList``. ``MAX_HITS = K`` keeps each ray's ``K`` nearest hits sorted in the output buffers
themselves, laid out ``(K, n_rays)`` so that a warp's accesses to one entry fall in one 128-byte line, like the
stack; an insertion reads the ``K`` distances to find its place (after equal ones) and moves the entries behind
it back by one, only in lanes that hit, behind the same warp-uniform branch as the leaf test. Registers would
need ``K`` separately named values per field and unrolled selects for every shift (Triton has no per-lane
arrays), and the list must reach memory anyway; an insertion is rare next to a step, so the lines stay in L1.
Both leaves of a step are tested against the bound before it and inserted leaf child 0 first; once more than
``K`` hits are known the bound is the ``K``-th distance, which culls boxes and leaves as in the portable path.
``COUNT`` counts every accepted hit and never lowers the bound.

Analytic leaves (compile-time constant ``ANALYTIC``; 0 generates the triangle-only code): bounding-box leaves
whose geometry uses a built-in intersection function, and the leaves of kinds with an analytic row (built-in
spheres), carry their parameters in their triangle row, with the shape code in column 3 (0 for triangles;
:func:`jaxrt._src.traversal.packed.pack_analytic`). :func:`_leaf` reads the code and runs
:func:`jaxrt._src.traversal.triton_analytic.analytic_hit` (the shapes of bits 0-2 of ``ANALYTIC``, and
from bit 5 on the kinds') and, where bit 3 says the scene also holds triangles, the watertight test on the lanes with a
triangle, each behind a warp-uniform branch. The shapes see the ray of the current level (origin and
unnormalised direction; the extended ray block carries the direction also without instances).
"""

from __future__ import annotations

import triton
import triton.language as tl

from jaxrt._src import formulas
from jaxrt._src.traversal.triton_analytic import analytic_hit
from jaxrt._src.traversal.triton_curves import curve_leaf, curve_ray, is_curve_leaf

_box = formulas.instance("box", "triton")
_slab_axis = _box.slab_axis
_slab_distances = _box.slab_distances
_box_hit = _box.box_hit
_tri = formulas.instance("triangle", "triton")
_shear_axes = _tri.shear_axes
_shear_of = _tri.shear
_sheared_vertex = _tri.sheared_vertex
_edge_functions = _tri.edge_functions
_edges_inside = _tri.edges_inside
_facing_accepts = _tri.facing_accepts
_plane_distance = _tri.plane_distance
_in_interval = _tri.in_interval


@triton.jit
def _bit_or(a, b):
    return a | b


@triton.jit
def _select(k, x, y, z):
    """``(x, y, z)[k]`` per lane."""
    return tl.where(k == 0, x, tl.where(k == 1, y, z))


@triton.jit
def _quad(ptr, row, width: tl.constexpr, offset: tl.constexpr, mask, LANES: tl.constexpr, VECTOR: tl.constexpr):
    """Four consecutive float32 columns ``offset..offset+3`` of rows ``row`` (one 16-byte load per lane)."""
    base = ptr + row * width + offset
    if VECTOR:
        q = tl.load(base[:, None] + tl.arange(0, 4)[None, :], mask=mask[:, None], other=0.0)
        even, odd = tl.split(tl.reshape(q, (LANES, 2, 2)))
        a, c = tl.split(even)
        b, d = tl.split(odd)
    else:
        a = tl.load(base, mask=mask, other=0.0)
        b = tl.load(base + 1, mask=mask, other=0.0)
        c = tl.load(base + 2, mask=mask, other=0.0)
        d = tl.load(base + 3, mask=mask, other=0.0)
    return a, b, c, d


@triton.jit
def _blend(a, b, rest, weight):
    """``(1 - w) a + w b`` with ``rest = 1 - w``: the portable ``motion.blend``, operation for operation."""
    return rest * a + weight * b


@triton.jit
def _box_blend(a, b, rest, weight):
    """A node box corner blended as the portable ``_node_boxes_at`` does: equal corners kept as they are."""
    return tl.where(a == b, a, _blend(a, b, rest, weight))


@triton.jit
def _box_quads(ptr, row, mask, rest, weight, LANES: tl.constexpr, VECTOR: tl.constexpr):
    """The 12 box columns of node rows ``row`` and ``row + 1`` (two keyframes), blended."""
    a0, a1, a2, a3 = _quad(ptr, row, 16, 0, mask, LANES, VECTOR)
    a4, a5, a6, a7 = _quad(ptr, row, 16, 4, mask, LANES, VECTOR)
    a8, a9, a10, a11 = _quad(ptr, row, 16, 8, mask, LANES, VECTOR)
    b0, b1, b2, b3 = _quad(ptr, row + 1, 16, 0, mask, LANES, VECTOR)
    b4, b5, b6, b7 = _quad(ptr, row + 1, 16, 4, mask, LANES, VECTOR)
    b8, b9, b10, b11 = _quad(ptr, row + 1, 16, 8, mask, LANES, VECTOR)
    return (
        _box_blend(a0, b0, rest, weight),
        _box_blend(a1, b1, rest, weight),
        _box_blend(a2, b2, rest, weight),
        _box_blend(a3, b3, rest, weight),
        _box_blend(a4, b4, rest, weight),
        _box_blend(a5, b5, rest, weight),
        _box_blend(a6, b6, rest, weight),
        _box_blend(a7, b7, rest, weight),
        _box_blend(a8, b8, rest, weight),
        _box_blend(a9, b9, rest, weight),
        _box_blend(a10, b10, rest, weight),
        _box_blend(a11, b11, rest, weight),
    )


@triton.jit
def _key_position(time, start, end, count):
    """The portable ``motion.keyframe_position`` of one instance table: ``(index, weight)``."""
    segments = count - 1
    span = segments.to(tl.float32)
    position = tl.math.div_rn(time - start, end - start) * span
    position = tl.where(position != position, 0.0, position)
    clamped = tl.minimum(tl.maximum(position, 0.0), span)
    index = tl.minimum(tl.maximum(tl.floor(clamped).to(tl.int32), 0), segments - 1)
    return index, clamped - index.to(tl.float32)


@triton.jit
def _instance_visible(time, start, end, flags):
    """Whether an instance exists at ``time``: a moving one (flag 1) is absent before ``start`` with flag 2
    and after ``end`` with flag 4 (the portable ``_instance_visible``)."""
    gone = ((time < start) & ((flags & 2) != 0)) | ((time > end) & ((flags & 4) != 0))
    return (gone == 0) | ((flags & 1) == 0)


@triton.jit
def _triangle(
    tris_ptr,
    leaf,
    mask,
    kx,
    ky,
    kz,
    okx,
    oky,
    okz,
    sx,
    sy,
    sz,
    t_min,
    t_max,
    facing,
    key_index,
    key_weight,
    key_visible,
    CULL: tl.constexpr,
    LANES: tl.constexpr,
    VECTOR: tl.constexpr,
    LEVELS: tl.constexpr,
    LEAF_KEYS: tl.constexpr,
):
    """Watertight test of leaf triangles: ``(hit, distance)``, the distance ``inf`` where not hit.

    Below instances (``LEVELS > 0``) the cull sense is ``facing * CULL`` per lane: the product of the
    instance chain's winding flips (or 0 where an instance disables culling) times the intersector's.
    With keyframe motion (``LEAF_KEYS > 0``: ``tris_ptr`` holds the rows per keyframe) the triangle is the
    blend of keyframes ``key_index`` and ``key_index + 1`` by ``key_weight`` (the portable ``LeafKeys``), and
    a moving leaf is not hit where ``key_visible`` is false (a "vanish" border).
    """
    if LEAF_KEYS > 0:
        row = leaf * LEAF_KEYS + key_index
        ax, bx, cx, moving = _quad(tris_ptr, row, 12, 0, mask, LANES, VECTOR)
        ay, by, cy, _ = _quad(tris_ptr, row, 12, 4, mask, LANES, VECTOR)
        az, bz, cz, _ = _quad(tris_ptr, row, 12, 8, mask, LANES, VECTOR)
        ax1, bx1, cx1, _ = _quad(tris_ptr, row + 1, 12, 0, mask, LANES, VECTOR)
        ay1, by1, cy1, _ = _quad(tris_ptr, row + 1, 12, 4, mask, LANES, VECTOR)
        az1, bz1, cz1, _ = _quad(tris_ptr, row + 1, 12, 8, mask, LANES, VECTOR)
        rest = 1.0 - key_weight
        ax = _blend(ax, ax1, rest, key_weight)
        bx = _blend(bx, bx1, rest, key_weight)
        cx = _blend(cx, cx1, rest, key_weight)
        ay = _blend(ay, ay1, rest, key_weight)
        by = _blend(by, by1, rest, key_weight)
        cy = _blend(cy, cy1, rest, key_weight)
        az = _blend(az, az1, rest, key_weight)
        bz = _blend(bz, bz1, rest, key_weight)
        cz = _blend(cz, cz1, rest, key_weight)
    else:
        ax, bx, cx, _ = _quad(tris_ptr, leaf, 12, 0, mask, LANES, VECTOR)
        ay, by, cy, _ = _quad(tris_ptr, leaf, 12, 4, mask, LANES, VECTOR)
        az, bz, cz, _ = _quad(tris_ptr, leaf, 12, 8, mask, LANES, VECTOR)
    # Vertices relative to the origin in the ray's (kx, ky, kz) frame, sheared (the formulas of
    # jaxrt._src.formulas.triangle).
    a_x, a_y, a_z = _sheared_vertex(_select(kx, ax, ay, az) - okx, _select(ky, ax, ay, az) - oky, _select(kz, ax, ay, az) - okz, sx, sy, sz)  # fmt: skip
    b_x, b_y, b_z = _sheared_vertex(_select(kx, bx, by, bz) - okx, _select(ky, bx, by, bz) - oky, _select(kz, bx, by, bz) - okz, sx, sy, sz)  # fmt: skip
    c_x, c_y, c_z = _sheared_vertex(_select(kx, cx, cy, cz) - okx, _select(ky, cx, cy, cz) - oky, _select(kz, cx, cy, cz) - okz, sx, sy, sz)  # fmt: skip
    e0, e1, e2 = _edge_functions(a_x, a_y, b_x, b_y, c_x, c_y)
    inside, det = _edges_inside(e0, e1, e2)
    if LEVELS > 0:
        if CULL != 0:
            inside = inside & _facing_accepts(det, facing * CULL)
    elif CULL == 1:
        inside = inside & (det >= 0)
    elif CULL == -1:
        inside = inside & (det < 0)
    if LEAF_KEYS > 0:
        inside = inside & ((moving == 0) | key_visible)
    distance = _plane_distance(e0, e1, e2, a_z, b_z, c_z, det)
    hit = mask & inside & _in_interval(distance, t_min, t_max)
    return hit, tl.where(hit, distance, float("inf"))


@triton.jit
def _leaf(
    tris_ptr, leaf, mask, kx, ky, kz, okx, oky, okz, sx, sy, sz, t_min, t_max, facing, key_index, key_weight,
    key_visible, ox, oy, oz, dx, dy, dz, CULL: tl.constexpr, LANES: tl.constexpr, VECTOR: tl.constexpr,
    LEVELS: tl.constexpr, LEAF_KEYS: tl.constexpr, ANALYTIC: tl.constexpr,
):  # fmt: skip
    """The leaf test: :func:`_triangle`, or with ``ANALYTIC`` (analytic shapes in the scene) each leaf by the
    shape code of its row, ``(hit, distance)``."""
    if ANALYTIC == 0:
        hit, distance = _triangle(
            tris_ptr, leaf, mask, kx, ky, kz, okx, oky, okz, sx, sy, sz, t_min, t_max, facing, key_index,
            key_weight, key_visible, CULL, LANES, VECTOR, LEVELS, LEAF_KEYS,
        )  # fmt: skip
    else:
        px, py, pz, code = _quad(tris_ptr, leaf, 12, 0, mask, LANES, VECTOR)
        qx, qy, qz, radius = _quad(tris_ptr, leaf, 12, 4, mask, LANES, VECTOR)
        shaped = mask & (code != 0)
        hit, distance = analytic_hit(
            code, shaped, px, py, pz, qx, qy, qz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max, ANALYTIC
        )
        if (ANALYTIC & 8) != 0:
            plain = mask & (code == 0)
            if tl.max(plain.to(tl.int32), axis=0) > 0:
                flat_hit, flat_t = _triangle(
                    tris_ptr, leaf, plain, kx, ky, kz, okx, oky, okz, sx, sy, sz, t_min, t_max, facing, key_index,
                    key_weight, key_visible, CULL, LANES, VECTOR, LEVELS, LEAF_KEYS,
                )  # fmt: skip
                hit = hit | flat_hit
                distance = tl.where(flat_hit, flat_t, distance)
    return hit, distance


@triton.jit
def _axis(lo, hi, o, inv, PARALLEL: tl.constexpr, PLAIN: tl.constexpr):
    """Entry and exit distance of one slab (:mod:`jaxrt._src.formulas.box`); ``PLAIN``: no ray of the warp has a
    zero direction component, so the clamped-reciprocal case is not generated (the same values)."""
    if PLAIN:
        near, far = _slab_distances(lo, hi, o, inv)
    else:
        near, far = _slab_axis(lo, hi, o, inv, PARALLEL)
    return near, far


@triton.jit
def _slab(
    lo_x,
    hi_x,
    lo_y,
    hi_y,
    lo_z,
    hi_z,
    ox,
    oy,
    oz,
    ix,
    iy,
    iz,
    t_min,
    t_max,
    FAR_SCALE: tl.constexpr,
    PARALLEL: tl.constexpr,
    PLAIN: tl.constexpr = False,
):
    """Conservative slab test of one child box: ``(hit, t_near, t_far)`` (``PLAIN``: see :func:`_axis`)."""
    near_x, far_x = _axis(lo_x, hi_x, ox, ix, PARALLEL, PLAIN)
    near_y, far_y = _axis(lo_y, hi_y, oy, iy, PARALLEL, PLAIN)
    near_z, far_z = _axis(lo_z, hi_z, oz, iz, PARALLEL, PLAIN)
    return _box_hit(near_x, far_x, near_y, far_y, near_z, far_z, lo_x, hi_x, t_min, t_max, FAR_SCALE)


@triton.jit
def _load_ray(rays_ptr, n_rays, ray):
    """One ray per lane from the packed ray block: origin, reciprocal direction, shear, ``t_min``, sheared axes,
    the origin in those axes, the initial distance bound (``-inf`` for a disabled ray) and ``done``."""
    ox = tl.load(rays_ptr + ray)
    oy = tl.load(rays_ptr + n_rays + ray)
    oz = tl.load(rays_ptr + 2 * n_rays + ray)
    ix = tl.load(rays_ptr + 3 * n_rays + ray)
    iy = tl.load(rays_ptr + 4 * n_rays + ray)
    iz = tl.load(rays_ptr + 5 * n_rays + ray)
    sx = tl.load(rays_ptr + 6 * n_rays + ray)
    sy = tl.load(rays_ptr + 7 * n_rays + ray)
    sz = tl.load(rays_ptr + 8 * n_rays + ray)
    t_min = tl.load(rays_ptr + 9 * n_rays + ray)
    bound = tl.load(rays_ptr + 10 * n_rays + ray)
    kx = tl.load(rays_ptr + 11 * n_rays + ray).to(tl.int32)
    ky = tl.load(rays_ptr + 12 * n_rays + ray).to(tl.int32)
    kz = tl.load(rays_ptr + 13 * n_rays + ray).to(tl.int32)
    enabled = tl.load(rays_ptr + 14 * n_rays + ray) != 0
    okx, oky, okz, distance, done = _ray_start(ox, oy, oz, kx, ky, kz, enabled, bound)
    return ox, oy, oz, ix, iy, iz, sx, sy, sz, t_min, kx, ky, kz, okx, oky, okz, distance, done


@triton.jit
def _ray_start(ox, oy, oz, kx, ky, kz, enabled, t_max):
    """A loaded ray's origin in its sheared axes, its initial distance bound (``-inf`` for a disabled ray, so
    that it never hits) and ``done``."""
    okx = _select(kx, ox, oy, oz)
    oky = _select(ky, ox, oy, oz)
    okz = _select(kz, ox, oy, oz)
    distance = tl.where(enabled, t_max, float("-inf"))
    done = tl.where(enabled, 0, 1)
    return okx, oky, okz, distance, done


@triton.jit
def _load_fused_ray(
    origin_ptr, direction_ptr, t_min_ptr, t_max_ptr, enabled_ptr, n_real, ray,
    CLAMP: tl.constexpr, HUGE: tl.constexpr, CLAMPED: tl.constexpr,
):  # fmt: skip
    """:func:`_load_ray` from the caller's ray arrays (``(N, 3)`` origins and directions, ``(N,)`` intervals and
    enabled flags, float32): the reciprocal direction and the shear computed here as
    :func:`jaxrt._src.traversal.packed.pack_rays` computes them (so bit for bit the same constants); a lane
    past the ``n_real`` rays is a disabled ray."""
    real = ray < n_real
    ox = tl.load(origin_ptr + 3 * ray, mask=real, other=0.0)
    oy = tl.load(origin_ptr + 3 * ray + 1, mask=real, other=0.0)
    oz = tl.load(origin_ptr + 3 * ray + 2, mask=real, other=0.0)
    dx = tl.load(direction_ptr + 3 * ray, mask=real, other=1.0)
    dy = tl.load(direction_ptr + 3 * ray + 1, mask=real, other=1.0)
    dz = tl.load(direction_ptr + 3 * ray + 2, mask=real, other=1.0)
    t_min = tl.load(t_min_ptr + ray, mask=real, other=0.0)
    t_max = tl.load(t_max_ptr + ray, mask=real, other=0.0)
    enabled = real & (tl.load(enabled_ptr + ray, mask=real, other=0).to(tl.int32) != 0)
    ix = _safe_reciprocal(dx, CLAMP, HUGE, CLAMPED)
    iy = _safe_reciprocal(dy, CLAMP, HUGE, CLAMPED)
    iz = _safe_reciprocal(dz, CLAMP, HUGE, CLAMPED)
    kx, ky, kz, sx, sy, sz = _shear(dx, dy, dz)
    okx, oky, okz, distance, done = _ray_start(ox, oy, oz, kx, ky, kz, enabled, t_max)
    return ox, oy, oz, ix, iy, iz, sx, sy, sz, t_min, kx, ky, kz, okx, oky, okz, distance, done


@triton.jit
def _store_result(
    distance_ptr, leaf_ptr, visited_ptr, tested_ptr, overflow_ptr, ray, distance, leaf, visited, tested, overflow
):
    """Write one ray per lane of the traversal result."""
    tl.store(distance_ptr + ray, distance)
    tl.store(leaf_ptr + ray, leaf)
    tl.store(visited_ptr + ray, visited)
    tl.store(tested_ptr + ray, tested)
    tl.store(overflow_ptr + ray, overflow)


@triton.jit
def _keep_nearer(hit, t, index, distance, leaf):
    """Keep leaf ``index`` at distance ``t`` where it is hit and strictly nearer than the current hit; the first
    hit may lie exactly at ``t_max`` (closed interval)."""
    found = hit & ((t < distance) | ((leaf < 0) & (t <= distance)))
    return tl.where(found, t, distance), tl.where(found, index, leaf)


@triton.jit
def _candidate_box(tris_ptr, leaf, test, near, hit, t, LANES: tl.constexpr):
    """Bounding-box leaves whose intersection function is user code (shape code 4): the box itself is the
    candidate, at its entry distance ``near`` (the slab test's, clamped to ``t_min``), for JAX to decide."""
    code = tl.load(tris_ptr + leaf * 12 + 3, mask=test, other=0.0)
    box = test & (code == 4.0)
    return hit | box, tl.where(box, near, t)


@triton.jit
def _past_cursor(hit, t, leaf, cursor_t, cursor_leaf):
    """Keep only candidates past the cursor in ``(distance, leaf)`` order: the previous waves listed the rest."""
    past = hit & ((t > cursor_t) | ((t == cursor_t) & (leaf > cursor_leaf)))
    return past, tl.where(past, t, float("inf"))


@triton.jit
def _start_hits(hd_ptr, hl_ptr, hc_ptr, n_rays, ray, MAX_HITS: tl.constexpr, LEVELS: tl.constexpr, LANES: tl.constexpr):
    """An empty hit list for one ray per lane: every entry at distance ``inf``, leaf -1, chain -1."""
    for j in tl.static_range(MAX_HITS):
        tl.store(hd_ptr + j * n_rays + ray, tl.full((LANES,), float("inf"), tl.float32))
        tl.store(hl_ptr + j * n_rays + ray, tl.full((LANES,), -1, tl.int32))
        for index in tl.static_range(LEVELS):
            tl.store(hc_ptr + (j * LEVELS + index) * n_rays + ray, tl.full((LANES,), -1, tl.int32))


@triton.jit
def _insert_hit(
    hd_ptr,
    hl_ptr,
    hc_ptr,
    n_rays,
    ray,
    ok,
    t,
    leaf,
    level_base,
    level,
    MAX_HITS: tl.constexpr,
    LEVELS: tl.constexpr,
    LANES: tl.constexpr,
    ORDER: tl.constexpr = False,
):
    """Insert a hit at distance ``t`` into the sorted list where ``ok`` (the portable ``step._insert``): after
    every entry at a distance ``<= t``, the entries behind it moved back by one, the last one dropped. Below
    instances (``LEVELS > 0``) the entry's chain is the current path (``level`` instances entered). With
    ``ORDER`` (candidate waves) equal distances are ordered by leaf instead of by arrival."""
    position = tl.zeros((LANES,), tl.int32)
    for j in tl.static_range(MAX_HITS):
        listed = tl.load(hd_ptr + j * n_rays + ray, mask=ok, other=float("inf"))
        if ORDER:
            listed_leaf = tl.load(hl_ptr + j * n_rays + ray, mask=ok, other=0)
            before = (listed < t) | ((listed == t) & (listed_leaf < leaf) & (listed_leaf >= 0))
            position = position + before.to(tl.int32)
        else:
            position = position + (listed <= t).to(tl.int32)
    for j in tl.static_range(MAX_HITS - 1, 0, -1):
        move = ok & (position < j)
        d = tl.load(hd_ptr + (j - 1) * n_rays + ray, mask=move, other=0.0)
        k = tl.load(hl_ptr + (j - 1) * n_rays + ray, mask=move, other=0)
        tl.store(hd_ptr + j * n_rays + ray, d, mask=move)
        tl.store(hl_ptr + j * n_rays + ray, k, mask=move)
        for index in tl.static_range(LEVELS):
            g = tl.load(hc_ptr + ((j - 1) * LEVELS + index) * n_rays + ray, mask=move, other=0)
            tl.store(hc_ptr + (j * LEVELS + index) * n_rays + ray, g, mask=move)
    put = ok & (position < MAX_HITS)
    tl.store(hd_ptr + position * n_rays + ray, t, mask=put)
    tl.store(hl_ptr + position * n_rays + ray, leaf, mask=put)
    for index in tl.static_range(LEVELS):
        on_path = put & (level > index)
        g = tl.load(level_base + (index * 8 + 7) * LANES, mask=on_path, other=0.0).to(tl.int32, bitcast=True)
        tl.store(hc_ptr + (position * LEVELS + index) * n_rays + ray, tl.where(on_path, g, -1), mask=put)


@triton.jit
def _hit_lists(
    hd_ptr, hl_ptr, hc_ptr, n_rays, ray, votes, active, h0, t0, c0, h1, t1, c1, distance, total, level_base, level,
    MAX_HITS: tl.constexpr, LEVELS: tl.constexpr, LANES: tl.constexpr, BRANCH: tl.constexpr,
    ORDER: tl.constexpr = False,
):  # fmt: skip
    """One step of the ``K`` nearest hits: both leaves into the list (leaf child 0 first), then the bound, the
    ``K``-th distance once more than ``K`` hits are known. Returns ``(distance, total)``."""
    if BRANCH:
        if (votes & 1) != 0:
            _insert_hit(hd_ptr, hl_ptr, hc_ptr, n_rays, ray, h0, t0, -1 - c0, level_base, level, MAX_HITS, LEVELS, LANES, ORDER)  # fmt: skip
        if (votes & 2) != 0:
            _insert_hit(hd_ptr, hl_ptr, hc_ptr, n_rays, ray, h1, t1, -1 - c1, level_base, level, MAX_HITS, LEVELS, LANES, ORDER)  # fmt: skip
    else:
        _insert_hit(hd_ptr, hl_ptr, hc_ptr, n_rays, ray, h0, t0, -1 - c0, level_base, level, MAX_HITS, LEVELS, LANES, ORDER)  # fmt: skip
        _insert_hit(hd_ptr, hl_ptr, hc_ptr, n_rays, ray, h1, t1, -1 - c1, level_base, level, MAX_HITS, LEVELS, LANES, ORDER)  # fmt: skip
    total = total + h0.to(tl.int32) + h1.to(tl.int32)
    full = active & (total > MAX_HITS)
    kth = tl.load(hd_ptr + (MAX_HITS - 1) * n_rays + ray, mask=full, other=0.0)
    return tl.where(full, kth, distance), total


@triton.jit
def _push(stack_base, depth, overflow, entry, STACK: tl.constexpr, LANES: tl.constexpr):
    """Push ``entry`` where it is a node (``>= 0``); a push past ``STACK`` entries is flagged and dropped."""
    want = entry >= 0
    push = want & (depth < STACK)
    tl.store(stack_base + depth * LANES, entry, mask=push)
    return depth + push.to(tl.int32), overflow | (want & (depth >= STACK)).to(tl.int32)


@triton.jit
def _advance(stack_base, active, enter, node, depth, leaf, done, ANY_HIT: tl.constexpr, LANES: tl.constexpr):
    """Enter node ``enter`` where it is one (``>= 0``), else pop the stack; a lane whose stack is empty (or, in
    any-hit mode, that has a hit) is done. Returns ``(node, depth, done)``."""
    pop = active & (enter < 0)
    nonempty = depth > 0
    top = tl.load(stack_base + (depth - 1) * LANES, mask=pop & nonempty, other=0)
    node = tl.where(active, tl.where(pop, top, enter), node)
    depth = tl.where(pop & nonempty, depth - 1, depth)
    finished = pop & (nonempty == 0)
    if ANY_HIT:
        finished = finished | (active & (leaf >= 0))
    return node, depth, tl.where(finished, 1, done)


@triton.jit
def _classify(inst_ptr, imotion_ptr, child, hit, n_primitives, ray_mask, time, IWIDTH: tl.constexpr):
    """Sort a hit child of an instanced scene: ``(test, inner, entry)``.

    ``test``: a primitive leaf to test now; ``inner``: an inner node or an instance visible to the ray (mask
    AND; with instance motion, ``IWIDTH > 0``, also present at the ray's time), to enter or push; ``entry``:
    the node, or ``-1 - g`` for instance ``g``.
    """
    is_leaf = child < 0
    k = -1 - child
    primitive = is_leaf & (k < n_primitives)
    instance = is_leaf & (k >= n_primitives)
    g = k - n_primitives
    bits = tl.load(inst_ptr + g * 16 + 14, mask=hit & instance, other=0.0).to(tl.int32, bitcast=True)
    if IWIDTH > 0:
        read = hit & instance
        start = tl.load(imotion_ptr + g * IWIDTH, mask=read, other=0.0)
        end = tl.load(imotion_ptr + g * IWIDTH + 1, mask=read, other=0.0)
        flags = tl.load(imotion_ptr + g * IWIDTH + 3, mask=read, other=0.0).to(tl.int32, bitcast=True)
        visible = ((bits & ray_mask) != 0) & _instance_visible(time, start, end, flags)
        inner = hit & ((child >= 0) | (instance & visible))
    else:
        inner = hit & ((child >= 0) | (instance & ((bits & ray_mask) != 0)))
    return hit & primitive, inner, tl.where(instance, -1 - g, child)


@triton.jit
def _record_chain(chain_ptr, level_base, n_rays, ray, found, level, LEVELS: tl.constexpr, LANES: tl.constexpr):
    """Write the instance chain of the current path as the hit's chain where ``found`` (-1 past its length)."""
    for index in tl.static_range(LEVELS):
        on_path = found & (level > index)
        g = tl.load(level_base + (index * 8 + 7) * LANES, mask=on_path, other=0.0).to(tl.int32, bitcast=True)
        tl.store(chain_ptr + index * n_rays + ray, tl.where(on_path, g, -1), mask=found)


@triton.jit
def _advance_levels(
    stack_base,
    active,
    inner0,
    inner1,
    entry0,
    entry1,
    near,
    far,
    node,
    level,
    depth,
    overflow,
    leaf,
    done,
    STACK: tl.constexpr,
    ANY_HIT: tl.constexpr,
    LANES: tl.constexpr,
    SHIFT: tl.constexpr,
):
    """Push the farther entry where both are entered, then enter the next entry or pop one; instance entries
    (negative) are entries too, so the stack holds ``entry << SHIFT | level``. Returns
    ``(node, level, depth, overflow, done)``."""
    both = inner0 & inner1
    push = both & (depth < STACK)
    tl.store(stack_base + depth * LANES, (far << SHIFT) | level, mask=push)
    overflow = overflow | (both & (depth >= STACK)).to(tl.int32)
    depth = depth + push.to(tl.int32)
    pop = active & (inner0 == 0) & (inner1 == 0)
    nonempty = depth > 0
    top = tl.load(stack_base + (depth - 1) * LANES, mask=pop & nonempty, other=0)
    next_entry = tl.where(both, near, tl.where(pop, top >> SHIFT, tl.where(inner0, entry0, entry1)))
    next_level = tl.where(pop, top & ((1 << SHIFT) - 1), level)
    depth = tl.where(pop & nonempty, depth - 1, depth)
    finished = pop & (nonempty == 0)
    if ANY_HIT:
        finished = finished | (active & (leaf >= 0))
    go = active & (finished == 0)
    node = tl.where(go, next_entry, node)
    level = tl.where(go, next_level, level)
    return node, level, depth, overflow, tl.where(finished, 1, done)


# A ray's constants (reciprocal direction, shear) divide with Triton's ``/``, PTX's approximate
# ``div.full.f32``, not ``div_rn``: XLA's GPU backend lowers float32 division to the same instruction (not
# correctly rounded: 25% of 4M random quotients and 14% of reciprocals differ from the IEEE result; PTX bounds
# the error at 2 ulp), and Triton's ``/`` equals it bit for bit (the same 4M quotients and reciprocals, zeros,
# infinities and NaN included; H200, jax 0.11.2).
# So the kernel starts from the portable path's constants, whether it reads a ray block that XLA packed or
# computes them itself. (Triton's interpreter and XLA on the CPU both divide correctly rounded.)


@triton.jit
def _safe_reciprocal(x, CLAMP: tl.constexpr, HUGE: tl.constexpr, CLAMPED: tl.constexpr):
    """``jaxrt._src.numerics.safe_reciprocal`` in float32: ``|x|`` clamped to ``[CLAMP, HUGE]``, sign kept
    (divided as XLA divides on the GPU, see above)."""
    negative = x.to(tl.int32, bitcast=True) < 0
    magnitude = tl.abs(x)
    x = tl.where(magnitude < CLAMP, tl.where(negative, -CLAMP, CLAMP), x)
    x = tl.where(magnitude > HUGE, tl.where(negative, -CLAMPED, CLAMPED), x)
    return 1.0 / x


@triton.jit
def _shear(dx, dy, dz):
    """``jaxrt._src.primitives.triangle.shear_ray``: sheared axes ``(kx, ky, kz)`` and shear ``(Sx, Sy, Sz)``
    (divided as XLA divides on the GPU)."""
    kx, ky, kz = _shear_axes(dx, dy, dz)
    sx, sy, sz = _shear_of(_select(kx, dx, dy, dz), _select(ky, dx, dy, dz), _select(kz, dx, dy, dz))
    return kx, ky, kz, sx, sy, sz


@triton.jit
def _cross(u0, u1, u2, v0, v1, v2):
    """``jnp.cross(u, v)`` component for component."""
    return u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0


@triton.jit
def _moved_to_object(keys, mask, weight):
    """World-to-object rows of an instance's keyframes ``keys`` (a pointer per lane) blended by ``weight``
    (the portable ``instance_motion_at``: the component-wise blend, then ``invert_transform``, the adjugate
    over the determinant, operation for operation)."""
    rest = 1.0 - weight
    a00 = _blend(tl.load(keys, mask=mask, other=0.0), tl.load(keys + 12, mask=mask, other=0.0), rest, weight)
    a01 = _blend(tl.load(keys + 1, mask=mask, other=0.0), tl.load(keys + 13, mask=mask, other=0.0), rest, weight)
    a02 = _blend(tl.load(keys + 2, mask=mask, other=0.0), tl.load(keys + 14, mask=mask, other=0.0), rest, weight)
    t0 = _blend(tl.load(keys + 3, mask=mask, other=0.0), tl.load(keys + 15, mask=mask, other=0.0), rest, weight)
    a10 = _blend(tl.load(keys + 4, mask=mask, other=0.0), tl.load(keys + 16, mask=mask, other=0.0), rest, weight)
    a11 = _blend(tl.load(keys + 5, mask=mask, other=0.0), tl.load(keys + 17, mask=mask, other=0.0), rest, weight)
    a12 = _blend(tl.load(keys + 6, mask=mask, other=0.0), tl.load(keys + 18, mask=mask, other=0.0), rest, weight)
    t1 = _blend(tl.load(keys + 7, mask=mask, other=0.0), tl.load(keys + 19, mask=mask, other=0.0), rest, weight)
    a20 = _blend(tl.load(keys + 8, mask=mask, other=0.0), tl.load(keys + 20, mask=mask, other=0.0), rest, weight)
    a21 = _blend(tl.load(keys + 9, mask=mask, other=0.0), tl.load(keys + 21, mask=mask, other=0.0), rest, weight)
    a22 = _blend(tl.load(keys + 10, mask=mask, other=0.0), tl.load(keys + 22, mask=mask, other=0.0), rest, weight)
    t2 = _blend(tl.load(keys + 11, mask=mask, other=0.0), tl.load(keys + 23, mask=mask, other=0.0), rest, weight)
    c00, c01, c02 = _cross(a10, a11, a12, a20, a21, a22)
    c10, c11, c12 = _cross(a20, a21, a22, a00, a01, a02)
    c20, c21, c22 = _cross(a00, a01, a02, a10, a11, a12)
    det = (a00 * c00 + a01 * c01) + a02 * c02
    det = tl.where(det == 0, 1.0, det)
    # Row i of the inverse is (c0[i], c1[i], c2[i]) / det.
    m00 = tl.math.div_rn(c00, det)
    m01 = tl.math.div_rn(c10, det)
    m02 = tl.math.div_rn(c20, det)
    m10 = tl.math.div_rn(c01, det)
    m11 = tl.math.div_rn(c11, det)
    m12 = tl.math.div_rn(c21, det)
    m20 = tl.math.div_rn(c02, det)
    m21 = tl.math.div_rn(c12, det)
    m22 = tl.math.div_rn(c22, det)
    m03 = -((m00 * t0 + m01 * t1) + m02 * t2)
    m13 = -((m10 * t0 + m11 * t1) + m12 * t2)
    m23 = -((m20 * t0 + m21 * t1) + m22 * t2)
    return m00, m01, m02, m03, m10, m11, m12, m13, m20, m21, m22, m23


@triton.jit
def _transition(
    inst_ptr,
    imotion_ptr,
    time,
    level_base,
    need,
    node,
    level,
    ray_level,
    ray,
    LANES: tl.constexpr,
    VECTOR: tl.constexpr,
    CLAMP: tl.constexpr,
    HUGE: tl.constexpr,
    CLAMPED: tl.constexpr,
    IWIDTH: tl.constexpr,
):
    """Load the ray of the next entry's level and, where the entry is an instance, enter it (the portable
    ``step.transition``). ``ray`` is ``(ox, oy, oz, dx, dy, dz, facing, ix, iy, iz, kx, ky, kz, sx, sy, sz)``;
    returns ``(node, level, ray_level, ray)``. With instance motion (``IWIDTH > 0``) a moving instance moves
    the ray by the inverse of its keyframe transforms blended at the ray's ``time``."""
    ox, oy, oz, dx, dy, dz, facing, ix, iy, iz, kx, ky, kz, sx, sy, sz = ray
    # The saved ray of level ``level`` (slot ``level``: origin, direction, facing, instance entered there).
    reload = need & (level != ray_level)
    slot = level_base + level * (8 * LANES)
    bx = tl.where(reload, tl.load(slot, mask=reload, other=0.0), ox)
    by = tl.where(reload, tl.load(slot + LANES, mask=reload, other=0.0), oy)
    bz = tl.where(reload, tl.load(slot + 2 * LANES, mask=reload, other=0.0), oz)
    bdx = tl.where(reload, tl.load(slot + 3 * LANES, mask=reload, other=0.0), dx)
    bdy = tl.where(reload, tl.load(slot + 4 * LANES, mask=reload, other=0.0), dy)
    bdz = tl.where(reload, tl.load(slot + 5 * LANES, mask=reload, other=0.0), dz)
    bf = tl.where(reload, tl.load(slot + 6 * LANES, mask=reload, other=0.0).to(tl.int32, bitcast=True), facing)
    # Entering instance g: world-to-object rows, child root and facing (one 64-byte row).
    entering = need & (node < 0)
    g = -1 - node
    m00, m01, m02, m03 = _quad(inst_ptr, g, 16, 0, entering, LANES, VECTOR)
    m10, m11, m12, m13 = _quad(inst_ptr, g, 16, 4, entering, LANES, VECTOR)
    m20, m21, m22, m23 = _quad(inst_ptr, g, 16, 8, entering, LANES, VECTOR)
    root_bits, facing_bits, _, _ = _quad(inst_ptr, g, 16, 12, entering, LANES, VECTOR)
    if IWIDTH > 0:
        row = imotion_ptr + g * IWIDTH
        start = tl.load(row, mask=entering, other=0.0)
        end = tl.load(row + 1, mask=entering, other=0.0)
        count = tl.load(row + 2, mask=entering, other=0.0).to(tl.int32, bitcast=True)
        flags = tl.load(row + 3, mask=entering, other=0.0).to(tl.int32, bitcast=True)
        moving = entering & ((flags & 1) != 0)
        index, weight = _key_position(time, start, end, count)
        k00, k01, k02, k03, k10, k11, k12, k13, k20, k21, k22, k23 = _moved_to_object(
            row + 4 + index * 12, moving, weight
        )
        m00 = tl.where(moving, k00, m00)
        m01 = tl.where(moving, k01, m01)
        m02 = tl.where(moving, k02, m02)
        m03 = tl.where(moving, k03, m03)
        m10 = tl.where(moving, k10, m10)
        m11 = tl.where(moving, k11, m11)
        m12 = tl.where(moving, k12, m12)
        m13 = tl.where(moving, k13, m13)
        m20 = tl.where(moving, k20, m20)
        m21 = tl.where(moving, k21, m21)
        m22 = tl.where(moving, k22, m22)
        m23 = tl.where(moving, k23, m23)
    nx = ((m00 * bx + m01 * by) + m02 * bz) + m03
    ny = ((m10 * bx + m11 * by) + m12 * bz) + m13
    nz = ((m20 * bx + m21 * by) + m22 * bz) + m23
    ndx = (m00 * bdx + m01 * bdy) + m02 * bdz
    ndy = (m10 * bdx + m11 * bdy) + m12 * bdz
    ndz = (m20 * bdx + m21 * bdy) + m22 * bdz
    nf = bf * facing_bits.to(tl.int32, bitcast=True)
    inner_slot = slot + 8 * LANES
    tl.store(inner_slot, nx, mask=entering)
    tl.store(inner_slot + LANES, ny, mask=entering)
    tl.store(inner_slot + 2 * LANES, nz, mask=entering)
    tl.store(inner_slot + 3 * LANES, ndx, mask=entering)
    tl.store(inner_slot + 4 * LANES, ndy, mask=entering)
    tl.store(inner_slot + 5 * LANES, ndz, mask=entering)
    tl.store(inner_slot + 6 * LANES, nf.to(tl.float32, bitcast=True), mask=entering)
    tl.store(slot + 7 * LANES, g.to(tl.float32, bitcast=True), mask=entering)
    ox = tl.where(entering, nx, bx)
    oy = tl.where(entering, ny, by)
    oz = tl.where(entering, nz, bz)
    dx = tl.where(entering, ndx, bdx)
    dy = tl.where(entering, ndy, bdy)
    dz = tl.where(entering, ndz, bdz)
    facing = tl.where(entering, nf, bf)
    level = tl.where(entering, level + 1, level)
    node = tl.where(entering, root_bits.to(tl.int32, bitcast=True), node)
    ray_level = tl.where(need, level, ray_level)
    # Per-ray constants of the loaded ray, computed as the portable path's ``prepare`` does.
    new_kx, new_ky, new_kz, new_sx, new_sy, new_sz = _shear(dx, dy, dz)
    ix = tl.where(need, _safe_reciprocal(dx, CLAMP, HUGE, CLAMPED), ix)
    iy = tl.where(need, _safe_reciprocal(dy, CLAMP, HUGE, CLAMPED), iy)
    iz = tl.where(need, _safe_reciprocal(dz, CLAMP, HUGE, CLAMPED), iz)
    kx = tl.where(need, new_kx, kx)
    ky = tl.where(need, new_ky, ky)
    kz = tl.where(need, new_kz, kz)
    sx = tl.where(need, new_sx, sx)
    sy = tl.where(need, new_sy, sy)
    sz = tl.where(need, new_sz, sz)
    return node, level, ray_level, (ox, oy, oz, dx, dy, dz, facing, ix, iy, iz, kx, ky, kz, sx, sy, sz)


@triton.jit
def _save_level_ray(slot, ox, oy, oz, dx, dy, dz, facing, LANES: tl.constexpr):
    tl.store(slot, ox)
    tl.store(slot + LANES, oy)
    tl.store(slot + 2 * LANES, oz)
    tl.store(slot + 3 * LANES, dx)
    tl.store(slot + 4 * LANES, dy)
    tl.store(slot + 5 * LANES, dz)
    tl.store(slot + 6 * LANES, facing.to(tl.float32, bitcast=True))


@triton.jit
def trace_kernel(
    nodes_ptr,
    tris_ptr,
    inst_ptr,
    rays_ptr,
    n_rays,
    n_programs,
    n_primitives,
    imotion_ptr,
    curves_ptr,
    ray_direction_ptr,
    ray_t_min_ptr,
    ray_t_max_ptr,
    ray_enabled_ptr,
    n_real,
    distance_ptr,
    leaf_ptr,
    visited_ptr,
    tested_ptr,
    overflow_ptr,
    chain_ptr,
    hit_distance_ptr,
    hit_leaf_ptr,
    hit_total_ptr,
    hit_chain_ptr,
    stack_ptr,
    level_ptr,
    blocks_taken_ptr,
    STACK: tl.constexpr,
    ANY_HIT: tl.constexpr,
    CULL: tl.constexpr,
    FAR_SCALE: tl.constexpr,
    PARALLEL: tl.constexpr,
    LANES: tl.constexpr,
    VECTOR: tl.constexpr,
    BRANCH: tl.constexpr,
    LEVELS: tl.constexpr,
    ROOTS: tl.constexpr,
    SHIFT: tl.constexpr,
    CLAMP: tl.constexpr,
    HUGE: tl.constexpr,
    CLAMPED: tl.constexpr,
    NODE_KEYS: tl.constexpr,
    LEAF_KEYS: tl.constexpr,
    IWIDTH: tl.constexpr,
    MAX_HITS: tl.constexpr = 0,
    COUNT: tl.constexpr = False,
    ANALYTIC: tl.constexpr = 0,
    CURVES: tl.constexpr = False,
    PIECES: tl.constexpr = 1,
    ITERATIONS: tl.constexpr = 0,
    APPROACH: tl.constexpr = 0,
    TOLERANCE: tl.constexpr = 0.0,
    DISK: tl.constexpr = False,
    SPHERE: tl.constexpr = False,
    FLAT: tl.constexpr = 0,
    CURVE_BATCH: tl.constexpr = 0,
    CURSOR: tl.constexpr = False,
    FUSED_RAYS: tl.constexpr = False,
    STEAL: tl.constexpr = False,
):
    """Trace ``n_rays`` rays (a multiple of ``LANES``); outputs as :class:`~jaxrt._src.traversal.scene.TraversalResult`.

    ``LEVELS = 0`` traces a primitive structure (the instance arguments are not read and compile to nothing).
    With ``LEVELS > 0`` a leaf ``k >= n_primitives`` is instance ``k - n_primitives``: it is ordered and pushed
    like an inner node when its mask meets the ray's, and entering it moves the ray into the child's space
    (the portable ``step.visit`` and ``step.transition``). Per lane, ``level_ptr`` keeps each level's ray and
    the instance entered there (``[program, level, field, lane]``), and ``chain_ptr`` (``(LEVELS, n_rays)``)
    receives the hit's instance chain. ``ROOTS``: each ray starts at its own root node (ray block row 16).

    Keyframe motion (every constant 0 compiles no motion code): ``NODE_KEYS > 0``, ``nodes_ptr`` holds the
    node rows of that many keyframes, blended at the ray's keyframe segment and weight (ray block rows 20-21);
    ``LEAF_KEYS > 0``, ``tris_ptr`` holds the triangle rows of that many keyframes (see :func:`_triangle`);
    ``IWIDTH > 0``, ``imotion_ptr`` holds instance motion rows of that width, read at the ray's time (row 23).

    Hit lists (``MAX_HITS = 0`` and ``COUNT = False`` compile none of this): ``MAX_HITS = K > 0`` keeps the
    ``K`` nearest hits of each ray, sorted, in ``hit_distance_ptr`` and ``hit_leaf_ptr`` (``(K, n_rays)``) and
    the number of hits accepted in ``hit_total_ptr``, as the portable ``step.HitList``: both leaves of a step
    are tested against the distance bound before it, then inserted (leaf child 0 first, each after the hits
    at the same distance), and once more than ``K`` hits are known the bound is the ``K``-th distance; the
    result's leaf is the first hit and its distance the bound. Below instances ``hit_chain_ptr``
    (``(K, LEVELS, n_rays)``) receives each hit's instance chain. ``COUNT`` counts every accepted hit in ``hit_total_ptr`` and never lowers the bound (the leaf stays -1).

    Analytic leaves (``ANALYTIC = 0`` compiles none of this): bits 0-2 name the shapes of the scene (sphere,
    disk, capped cylinder), bit 3 that it also holds triangles, bits 5 on the kinds' analytic rows (built-in
    spheres); see :func:`_leaf`. Without instances the
    direction comes from the extended ray block (rows 17-19).

    Curves (``CURVES = False`` compiles none of this): ``curves_ptr`` holds a curve row per primitive leaf
    (:func:`jaxrt._src.traversal.packed.pack_curves`) and ray block rows 24-33 each ray's curve frame; a leaf
    whose row is a curve takes the round or flat segment test of :mod:`jaxrt._src.formulas.curve` after
    the triangle test, whose answer it replaces (a primitive structure only, ``LEVELS = 0``; the options
    ``PIECES`` to ``FLAT`` are :func:`~jaxrt._src.traversal.triton_curves.curve_leaf`'s). ``CURVE_BATCH > 0``
    defers curve tests until that many lanes wait for one (or no other lane can step; see the module
    docstring): the same results, fewer warp-wide curve tests. 0 tests them on sight (binary nodes, ``BRANCH``).

    Work stealing (``STEAL``): the launch has fewer programs than blocks of ``LANES`` rays; after its first block
    (its program id) a program takes the next block no program has taken, counted in ``blocks_taken_ptr``
    (zeroed before the launch; the first ``n_programs`` blocks are taken by the program ids), so that
    programs whose rays end early take more blocks. Otherwise programs stride by ``n_programs``.

    Fused rays (``FUSED_RAYS``, a primitive structure whose ray block would have the 16 basic rows): the kernel
    reads the caller's arrays instead of a packed ray block, ``rays_ptr`` the ``(N, 3)`` origins,
    ``ray_direction_ptr`` the directions, ``ray_t_min_ptr``, ``ray_t_max_ptr`` and ``ray_enabled_ptr`` the
    intervals and enabled flags of the first ``n_real`` rays (:func:`_load_fused_ray`); otherwise those four
    arguments are not read.
    """
    pid = tl.program_id(0)
    lane = tl.arange(0, LANES)
    stack_base = stack_ptr + pid * (STACK * LANES) + lane
    if LEVELS > 0:
        level_base = level_ptr + pid * ((LEVELS + 1) * 8 * LANES) + lane
    block = pid
    while block < n_rays // LANES:
        ray = block * LANES + lane
        if FUSED_RAYS:
            ox, oy, oz, ix, iy, iz, sx, sy, sz, t_min, kx, ky, kz, okx, oky, okz, distance, done = _load_fused_ray(
                rays_ptr, ray_direction_ptr, ray_t_min_ptr, ray_t_max_ptr, ray_enabled_ptr, n_real, ray, CLAMP, HUGE,
                CLAMPED,
            )  # fmt: skip
        else:
            ox, oy, oz, ix, iy, iz, sx, sy, sz, t_min, kx, ky, kz, okx, oky, okz, distance, done = _load_ray(
                rays_ptr, n_rays, ray
            )
        if ROOTS:
            node = tl.load(rays_ptr + 16 * n_rays + ray).to(tl.int32, bitcast=True)
        else:
            node = tl.zeros((LANES,), tl.int32)
        depth = tl.zeros((LANES,), tl.int32)
        leaf = tl.full((LANES,), -1, tl.int32)
        visited = tl.zeros((LANES,), tl.int32)
        tested = tl.zeros((LANES,), tl.int32)
        overflow = tl.zeros((LANES,), tl.int32)
        if MAX_HITS > 0:
            _start_hits(hit_distance_ptr, hit_leaf_ptr, hit_chain_ptr, n_rays, ray, MAX_HITS, LEVELS, LANES)
        if MAX_HITS > 0 or COUNT:
            total = tl.zeros((LANES,), tl.int32)
        if LEAF_KEYS > 0:
            key_index = tl.load(rays_ptr + 20 * n_rays + ray).to(tl.int32, bitcast=True)
            key_weight = tl.load(rays_ptr + 21 * n_rays + ray)
            key_visible = tl.load(rays_ptr + 22 * n_rays + ray) != 0
            key_rest = 1.0 - key_weight
        else:
            key_index = 0
            key_weight = 0.0
            key_visible = 1
            key_rest = 1.0
        if IWIDTH > 0:
            time = tl.load(rays_ptr + 23 * n_rays + ray)
        else:
            time = 0.0
        if LEVELS > 0:
            ray_mask = tl.load(rays_ptr + 15 * n_rays + ray).to(tl.int32, bitcast=True)
            dx = tl.load(rays_ptr + 17 * n_rays + ray)
            dy = tl.load(rays_ptr + 18 * n_rays + ray)
            dz = tl.load(rays_ptr + 19 * n_rays + ray)
            facing = tl.full((LANES,), 1, tl.int32)
            level = tl.zeros((LANES,), tl.int32)
            ray_level = tl.zeros((LANES,), tl.int32)
            _save_level_ray(level_base, ox, oy, oz, dx, dy, dz, facing, LANES)
            for index in tl.static_range(LEVELS):
                tl.store(chain_ptr + index * n_rays + ray, tl.full((LANES,), -1, tl.int32))
        else:
            facing = 1
            if ANALYTIC != 0:  # analytic shapes read the direction (extended ray block)
                dx = tl.load(rays_ptr + 17 * n_rays + ray)
                dy = tl.load(rays_ptr + 18 * n_rays + ray)
                dz = tl.load(rays_ptr + 19 * n_rays + ray)
            else:
                dx = 0.0
                dy = 0.0
                dz = 0.0
        if CURVES:
            cray = curve_ray(rays_ptr, n_rays, ray, ox, oy, oz)
        if CURSOR:
            cursor_t = tl.load(rays_ptr + 34 * n_rays + ray)
            cursor_leaf = tl.load(rays_ptr + 35 * n_rays + ray).to(tl.int32, bitcast=True)
        if CURVE_BATCH > 0:
            # Deferred curve tests: a pending lane keeps its step's children, box results and curve flags.
            pending = tl.zeros((LANES,), tl.int1)
            kept_c0 = tl.zeros((LANES,), tl.int32)
            kept_c1 = tl.zeros((LANES,), tl.int32)
            kept_hit0 = tl.zeros((LANES,), tl.int1)
            kept_hit1 = tl.zeros((LANES,), tl.int1)
            kept_near0 = tl.zeros((LANES,), tl.float32)
            kept_near1 = tl.zeros((LANES,), tl.float32)
            kept_curve0 = tl.zeros((LANES,), tl.int1)
            kept_curve1 = tl.zeros((LANES,), tl.int1)
        if LEVELS == 0:
            # Warp-uniform: no live ray of the warp has a zero direction component, so every slab takes the plain
            # min / max of its two distances (rays below instances change direction: they keep the full test).
            parallel = (tl.abs(ix) >= PARALLEL) | (tl.abs(iy) >= PARALLEL) | (tl.abs(iz) >= PARALLEL)
            plain = tl.max((parallel & (done == 0)).to(tl.int32), axis=0) == 0
        else:
            plain = False
        # One warp reduction per step: bit 0 / 1, some lane tests leaf child 0 / 1; bit 2, some lane was
        # active when the step began. The loop therefore ends one (fully masked, no-op) step after the last ray.
        go = tl.max(1 - done, axis=0)
        while go > 0:
            active = done == 0
            if CURVE_BATCH > 0:
                fresh = active & (pending == 0)  # pending lanes take no box step
            else:
                fresh = active
            if NODE_KEYS > 0:
                # The node's child boxes blended at the ray's time (the portable ``_node_boxes_at``).
                row = node * NODE_KEYS + key_index
                lo0x, hi0x, lo1x, hi1x, lo0y, hi0y, lo1y, hi1y, lo0z, hi0z, lo1z, hi1z = _box_quads(
                    nodes_ptr, row, fresh, key_rest, key_weight, LANES, VECTOR
                )
                c0f, c1f, _, _ = _quad(nodes_ptr, row, 16, 12, fresh, LANES, VECTOR)
            else:
                lo0x, hi0x, lo1x, hi1x = _quad(nodes_ptr, node, 16, 0, fresh, LANES, VECTOR)
                lo0y, hi0y, lo1y, hi1y = _quad(nodes_ptr, node, 16, 4, fresh, LANES, VECTOR)
                lo0z, hi0z, lo1z, hi1z = _quad(nodes_ptr, node, 16, 8, fresh, LANES, VECTOR)
                c0f, c1f, _, _ = _quad(nodes_ptr, node, 16, 12, fresh, LANES, VECTOR)
            c0 = c0f.to(tl.int32, bitcast=True)
            c1 = c1f.to(tl.int32, bitcast=True)
            if plain:
                hit0, near0, far0 = _slab(
                    lo0x, hi0x, lo0y, hi0y, lo0z, hi0z, ox, oy, oz, ix, iy, iz, t_min, distance, FAR_SCALE, PARALLEL, True
                )  # fmt: skip
                hit1, near1, far1 = _slab(
                    lo1x, hi1x, lo1y, hi1y, lo1z, hi1z, ox, oy, oz, ix, iy, iz, t_min, distance, FAR_SCALE, PARALLEL, True
                )  # fmt: skip
            else:
                hit0, near0, far0 = _slab(
                    lo0x, hi0x, lo0y, hi0y, lo0z, hi0z, ox, oy, oz, ix, iy, iz, t_min, distance, FAR_SCALE, PARALLEL
                )
                hit1, near1, far1 = _slab(
                    lo1x, hi1x, lo1y, hi1y, lo1z, hi1z, ox, oy, oz, ix, iy, iz, t_min, distance, FAR_SCALE, PARALLEL
                )
            hit0 = hit0 & fresh
            hit1 = hit1 & fresh
            if CURSOR:
                # A box that ends before the cursor holds no candidate past it (a triangle's distance and a box
                # leaf's entry lie in its slab interval): culled. Entry distances stay those of t_min.
                hit0 = hit0 & (far0 >= cursor_t)
                hit1 = hit1 & (far1 >= cursor_t)
            if CURVE_BATCH > 0:
                c0 = tl.where(pending, kept_c0, c0)
                c1 = tl.where(pending, kept_c1, c1)
                hit0 = tl.where(pending, kept_hit0, hit0)
                hit1 = tl.where(pending, kept_hit1, hit1)
                near0 = tl.where(pending, kept_near0, near0)
                near1 = tl.where(pending, kept_near1, near1)
            if LEVELS > 0:
                test0, inner0, entry0 = _classify(inst_ptr, imotion_ptr, c0, hit0, n_primitives, ray_mask, time, IWIDTH)
                test1, inner1, entry1 = _classify(inst_ptr, imotion_ptr, c1, hit1, n_primitives, ray_mask, time, IWIDTH)
            else:
                test0 = hit0 & (c0 < 0)
                test1 = hit1 & (c1 < 0)
            if CURVE_BATCH > 0:
                # A lane whose step tests a curve leaf waits (pending, its state kept) until CURVE_BATCH lanes
                # wait or no other lane can take a step; then every lane's step is completed, curves tested
                # together. A lane only waits, so its decisions are unchanged. One warp reduction counts the
                # pending lanes, the lanes free to step and the pending lanes with two curve leaves.
                curve0 = tl.where(pending, kept_curve0, test0 & is_curve_leaf(curves_ptr, -1 - c0, test0 & fresh))
                curve1 = tl.where(pending, kept_curve1, test1 & is_curve_leaf(curves_ptr, -1 - c1, test1 & fresh))
                pending = curve0 | curve1
                free = active & (pending == 0)
                counts = tl.sum(
                    pending.to(tl.int32) + (free.to(tl.int32) << 8) + ((curve0 & curve1).to(tl.int32) << 16), axis=0
                )
                waiting = counts & 255
                flush = (waiting > 0) & ((waiting >= CURVE_BATCH) | ((counts & 0xFF00) == 0))
                stepping = tl.where(flush, active, free)
                kept_c0 = c0
                kept_c1 = c1
                kept_hit0 = hit0
                kept_hit1 = hit1
                kept_near0 = near0
                kept_near1 = near1
                kept_curve0 = curve0
                kept_curve1 = curve1
                hit0 = hit0 & stepping
                hit1 = hit1 & stepping
                test0 = test0 & stepping
                test1 = test1 & stepping
                curve0 = curve0 & stepping
                curve1 = curve1 & stepping
                pending = pending & (stepping == 0)
            else:
                stepping = active
            # Both leaves are tested against the distance bound before this step, as in the portable path.
            h0 = tl.zeros((LANES,), tl.int1)
            h1 = tl.zeros((LANES,), tl.int1)
            t0 = tl.full((LANES,), float("inf"), tl.float32)
            t1 = tl.full((LANES,), float("inf"), tl.float32)
            if CURVE_BATCH > 0:
                # Bits 3 / 4: some lane tests a triangle (not curve) leaf child 0 / 1.
                tri0 = test0 & (curve0 == 0)
                tri1 = test1 & (curve1 == 0)
                votes = tl.reduce(
                    test0.to(tl.int32) | (test1.to(tl.int32) << 1) | (active.to(tl.int32) << 2)
                    | (tri0.to(tl.int32) << 3) | (tri1.to(tl.int32) << 4), 0, _bit_or,
                )  # fmt: skip
            else:
                votes = tl.reduce(
                    test0.to(tl.int32) | (test1.to(tl.int32) << 1) | (active.to(tl.int32) << 2), 0, _bit_or
                )
            go = votes & 4
            if CURVE_BATCH > 0:
                # A curve leaf's triangle test is replaced by its curve test: triangle leaves only here.
                if (votes & 8) != 0:
                    h0, t0 = _leaf(tris_ptr, -1 - c0, tri0, kx, ky, kz, okx, oky, okz, sx, sy, sz, t_min, distance, facing, key_index, key_weight, key_visible, ox, oy, oz, dx, dy, dz, CULL, LANES, VECTOR, LEVELS, LEAF_KEYS, ANALYTIC)  # fmt: skip
                if (votes & 16) != 0:
                    h1, t1 = _leaf(tris_ptr, -1 - c1, tri1, kx, ky, kz, okx, oky, okz, sx, sy, sz, t_min, distance, facing, key_index, key_weight, key_visible, ox, oy, oz, dx, dy, dz, CULL, LANES, VECTOR, LEVELS, LEAF_KEYS, ANALYTIC)  # fmt: skip
                if flush:
                    # Round 0 tests each lane's first curve leaf (child 0, else child 1), round 1 child 1 of the
                    # lanes with two (a loop: the test's code once). Each test depends on the leaf, the ray and
                    # the bound only, so the order is free.
                    first_c = tl.where(curve0, c0, c1)
                    no_hit = tl.zeros((LANES,), tl.int1)
                    no_t = tl.full((LANES,), float("inf"), tl.float32)
                    rounds = 1 + ((counts >> 16) > 0).to(tl.int32)
                    r = rounds * 0
                    while r < rounds:
                        again = r > 0
                        r += 1
                        child = tl.where(again, c1, first_c)
                        mask = tl.where(again, curve0 & curve1, curve0 | curve1)
                        hr, tr = curve_leaf(curves_ptr, -1 - child, mask, no_hit, no_t, cray, t_min, distance, LANES, PIECES, ITERATIONS, APPROACH, TOLERANCE, DISK, SPHERE, FLAT)  # fmt: skip
                        on0 = curve0 & (again == 0)
                        on1 = curve1 & (curve0 == again)
                        h0 = tl.where(on0, hr, h0)
                        t0 = tl.where(on0, tr, t0)
                        h1 = tl.where(on1, hr, h1)
                        t1 = tl.where(on1, tr, t1)
            elif BRANCH:
                # Skip a leaf test that no lane of the warp needs (a warp-uniform branch).
                if (votes & 1) != 0:
                    h0, t0 = _leaf(tris_ptr, -1 - c0, test0, kx, ky, kz, okx, oky, okz, sx, sy, sz, t_min, distance, facing, key_index, key_weight, key_visible, ox, oy, oz, dx, dy, dz, CULL, LANES, VECTOR, LEVELS, LEAF_KEYS, ANALYTIC)  # fmt: skip
                    if CURVES:
                        h0, t0 = curve_leaf(curves_ptr, -1 - c0, test0, h0, t0, cray, t_min, distance, LANES, PIECES, ITERATIONS, APPROACH, TOLERANCE, DISK, SPHERE, FLAT)  # fmt: skip
                if (votes & 2) != 0:
                    h1, t1 = _leaf(tris_ptr, -1 - c1, test1, kx, ky, kz, okx, oky, okz, sx, sy, sz, t_min, distance, facing, key_index, key_weight, key_visible, ox, oy, oz, dx, dy, dz, CULL, LANES, VECTOR, LEVELS, LEAF_KEYS, ANALYTIC)  # fmt: skip
                    if CURVES:
                        h1, t1 = curve_leaf(curves_ptr, -1 - c1, test1, h1, t1, cray, t_min, distance, LANES, PIECES, ITERATIONS, APPROACH, TOLERANCE, DISK, SPHERE, FLAT)  # fmt: skip
            else:
                h0, t0 = _leaf(tris_ptr, -1 - c0, test0, kx, ky, kz, okx, oky, okz, sx, sy, sz, t_min, distance, facing, key_index, key_weight, key_visible, ox, oy, oz, dx, dy, dz, CULL, LANES, VECTOR, LEVELS, LEAF_KEYS, ANALYTIC)  # fmt: skip
                if CURVES:
                    h0, t0 = curve_leaf(curves_ptr, -1 - c0, test0, h0, t0, cray, t_min, distance, LANES, PIECES, ITERATIONS, APPROACH, TOLERANCE, DISK, SPHERE, FLAT)  # fmt: skip
                h1, t1 = _leaf(tris_ptr, -1 - c1, test1, kx, ky, kz, okx, oky, okz, sx, sy, sz, t_min, distance, facing, key_index, key_weight, key_visible, ox, oy, oz, dx, dy, dz, CULL, LANES, VECTOR, LEVELS, LEAF_KEYS, ANALYTIC)  # fmt: skip
                if CURVES:
                    h1, t1 = curve_leaf(curves_ptr, -1 - c1, test1, h1, t1, cray, t_min, distance, LANES, PIECES, ITERATIONS, APPROACH, TOLERANCE, DISK, SPHERE, FLAT)  # fmt: skip
            if (ANALYTIC & 16) != 0:
                h0, t0 = _candidate_box(tris_ptr, -1 - c0, test0, near0, h0, t0, LANES)
                h1, t1 = _candidate_box(tris_ptr, -1 - c1, test1, near1, h1, t1, LANES)
            if CURSOR:
                h0, t0 = _past_cursor(h0, t0, -1 - c0, cursor_t, cursor_leaf)
                h1, t1 = _past_cursor(h1, t1, -1 - c1, cursor_t, cursor_leaf)
            second = t1 < t0
            best_t = tl.where(second, t1, t0)
            best_leaf = tl.where(second, -1 - c1, -1 - c0)
            near_first = near0 <= near1
            if ANY_HIT:  # a box holding the ray's start after one entered ahead (the portable _any_hit_order)
                start0 = near0 <= t_min
                start1 = near1 <= t_min
                near_first = tl.where(start0 != start1, start1, near_first)
            if LEVELS > 0:
                found = (h0 | h1) & ((best_t < distance) | ((leaf < 0) & (best_t <= distance)))
                if MAX_HITS > 0:
                    distance, total = _hit_lists(
                        hit_distance_ptr, hit_leaf_ptr, hit_chain_ptr, n_rays, ray, votes, stepping, h0, t0, c0, h1,
                        t1, c1, distance, total, level_base, level, MAX_HITS, LEVELS, LANES, BRANCH, CURSOR,
                    )  # fmt: skip
                    # The first hit (the portable state's leaf, read by the next step's ``found``).
                    leaf = tl.where(stepping, tl.load(hit_leaf_ptr + ray, mask=stepping, other=-1), leaf)
                elif COUNT:
                    total = total + h0.to(tl.int32) + h1.to(tl.int32)
                else:
                    distance = tl.where(found, best_t, distance)
                    leaf = tl.where(found, best_leaf, leaf)
                _record_chain(chain_ptr, level_base, n_rays, ray, found, level, LEVELS, LANES)
                near = tl.where(near_first, entry0, entry1)
                far = tl.where(near_first, entry1, entry0)
                node, level, depth, overflow, done = _advance_levels(
                    stack_base, stepping, inner0, inner1, entry0, entry1, near, far, node, level, depth, overflow,
                    leaf, done, STACK, ANY_HIT, LANES, SHIFT,
                )  # fmt: skip
            else:
                if MAX_HITS > 0:
                    distance, total = _hit_lists(
                        hit_distance_ptr, hit_leaf_ptr, hit_chain_ptr, n_rays, ray, votes, stepping, h0, t0, c0, h1,
                        t1, c1, distance, total, stack_base, 0, MAX_HITS, LEVELS, LANES, BRANCH, CURSOR,
                    )  # fmt: skip
                elif COUNT:
                    total = total + h0.to(tl.int32) + h1.to(tl.int32)
                else:
                    distance, leaf = _keep_nearer(h0 | h1, best_t, best_leaf, distance, leaf)
                inner0 = hit0 & (c0 >= 0)
                inner1 = hit1 & (c1 >= 0)
                near = tl.where(near_first, c0, c1)
                far = tl.where(near_first, c1, c0)
                both = inner0 & inner1
                depth, overflow = _push(stack_base, depth, overflow, tl.where(both, far, -1), STACK, LANES)
                enter = tl.where(both, near, tl.where(inner0, c0, tl.where(inner1, c1, -1)))
                node, depth, done = _advance(stack_base, stepping, enter, node, depth, leaf, done, ANY_HIT, LANES)
            visited = visited + stepping.to(tl.int32)
            tested = tested + test0.to(tl.int32) + test1.to(tl.int32)
            if LEVELS > 0:
                # Entering an instance, or returning to a shallower level: a warp-uniform branch.
                need = (done == 0) & ((node < 0) | (level != ray_level))
                if tl.max(need.to(tl.int32), axis=0) > 0:
                    node, level, ray_level, moved = _transition(
                        inst_ptr, imotion_ptr, time, level_base, need, node, level, ray_level,
                        (ox, oy, oz, dx, dy, dz, facing, ix, iy, iz, kx, ky, kz, sx, sy, sz),
                        LANES, VECTOR, CLAMP, HUGE, CLAMPED, IWIDTH,
                    )  # fmt: skip
                    ox, oy, oz, dx, dy, dz, facing, ix, iy, iz, kx, ky, kz, sx, sy, sz = moved
                    okx = _select(kx, ox, oy, oz)
                    oky = _select(ky, ox, oy, oz)
                    okz = _select(kz, ox, oy, oz)

        if MAX_HITS > 0:
            leaf = tl.load(hit_leaf_ptr + ray)
        if MAX_HITS > 0 or COUNT:
            tl.store(hit_total_ptr + ray, total)
        _store_result(distance_ptr, leaf_ptr, visited_ptr, tested_ptr, overflow_ptr, ray, distance, leaf, visited, tested, overflow)  # fmt: skip
        if STEAL:  # the next block no program has taken (the count starts at zero)
            block = n_programs + tl.atomic_add(blocks_taken_ptr, 1)
        else:
            block += n_programs


@triton.jit
def _order(key_a, ref_a, key_b, ref_b):
    """Compare-exchange of two ``(key, reference)`` pairs: the smaller key first (``a`` on ties)."""
    swap = key_b < key_a
    return (
        tl.where(swap, key_b, key_a),
        tl.where(swap, ref_b, ref_a),
        tl.where(swap, key_a, key_b),
        tl.where(swap, ref_a, ref_b),
    )


@triton.jit
def _leaf_cluster(
    tris_ptr,
    ref,
    test,
    longest,
    distance,
    leaf,
    tested,
    kx,
    ky,
    kz,
    okx,
    oky,
    okz,
    sx,
    sy,
    sz,
    t_min,
    CULL: tl.constexpr,
    LANES: tl.constexpr,
    VECTOR: tl.constexpr,
):
    """Test the triangles of one leaf-cluster slot (``longest``: the warp's largest cluster in it), nearest kept."""
    code = -1 - ref
    first = code >> 2
    count = (code & 3) + 1
    for j in range(longest):
        mask = test & (j < count)
        hit, t = _triangle(
            tris_ptr, first + j, mask, kx, ky, kz, okx, oky, okz, sx, sy, sz, t_min, distance, 1, 0, 0.0, 1,
            CULL, LANES, VECTOR, 0, 0,
        )  # fmt: skip
        distance, leaf = _keep_nearer(hit, t, first + j, distance, leaf)
        tested = tested + mask.to(tl.int32)
    return distance, leaf, tested


@triton.jit
def _longest(votes, slot: tl.constexpr):
    """The largest leaf-cluster size any lane tests in ``slot`` (its vote nibble has bit ``size - 1`` set)."""
    nibble = (votes >> (4 * slot)) & 15
    return (nibble > 0).to(tl.int32) + (nibble > 1).to(tl.int32) + (nibble > 3).to(tl.int32) + (nibble > 7).to(tl.int32)


@triton.jit
def trace_wide_kernel(
    nodes_ptr,
    tris_ptr,
    rays_ptr,
    n_rays,
    n_programs,
    distance_ptr,
    leaf_ptr,
    visited_ptr,
    tested_ptr,
    overflow_ptr,
    stack_ptr,
    STACK: tl.constexpr,
    ANY_HIT: tl.constexpr,
    CULL: tl.constexpr,
    FAR_SCALE: tl.constexpr,
    PARALLEL: tl.constexpr,
    LANES: tl.constexpr,
    VECTOR: tl.constexpr,
):
    """:func:`trace_kernel` over the 4-wide rows of :func:`~jaxrt._src.traversal.packed.pack_wide_nodes`.

    A step tests the four slot boxes of one wide node, the triangles of every leaf cluster hit (in slot order,
    each kept if strictly nearer), and enters the nearest inner slot hit, pushing the others farthest first.
    The tests are those of :func:`trace_kernel`, so the nearest distance is the same; among triangles at
    exactly that distance, and for the first hit in any-hit mode, the visiting order (and so the choice) may
    differ from the binary traversal's.
    """
    pid = tl.program_id(0)
    lane = tl.arange(0, LANES)
    stack_base = stack_ptr + pid * (STACK * LANES) + lane
    block = pid
    while block < n_rays // LANES:
        ray = block * LANES + lane
        ox, oy, oz, ix, iy, iz, sx, sy, sz, t_min, kx, ky, kz, okx, oky, okz, distance, done = _load_ray(
            rays_ptr, n_rays, ray
        )
        node = tl.zeros((LANES,), tl.int32)
        depth = tl.zeros((LANES,), tl.int32)
        leaf = tl.full((LANES,), -1, tl.int32)
        visited = tl.zeros((LANES,), tl.int32)
        tested = tl.zeros((LANES,), tl.int32)
        overflow = tl.zeros((LANES,), tl.int32)
        go = tl.max(1 - done, axis=0)
        while go > 0:
            active = done == 0
            lo_x0, lo_x1, lo_x2, lo_x3 = _quad(nodes_ptr, node, 32, 0, active, LANES, VECTOR)
            hi_x0, hi_x1, hi_x2, hi_x3 = _quad(nodes_ptr, node, 32, 4, active, LANES, VECTOR)
            lo_y0, lo_y1, lo_y2, lo_y3 = _quad(nodes_ptr, node, 32, 8, active, LANES, VECTOR)
            hi_y0, hi_y1, hi_y2, hi_y3 = _quad(nodes_ptr, node, 32, 12, active, LANES, VECTOR)
            lo_z0, lo_z1, lo_z2, lo_z3 = _quad(nodes_ptr, node, 32, 16, active, LANES, VECTOR)
            hi_z0, hi_z1, hi_z2, hi_z3 = _quad(nodes_ptr, node, 32, 20, active, LANES, VECTOR)
            r0f, r1f, r2f, r3f = _quad(nodes_ptr, node, 32, 24, active, LANES, VECTOR)
            r0 = r0f.to(tl.int32, bitcast=True)
            r1 = r1f.to(tl.int32, bitcast=True)
            r2 = r2f.to(tl.int32, bitcast=True)
            r3 = r3f.to(tl.int32, bitcast=True)
            h0, n0, _ = _slab(lo_x0, hi_x0, lo_y0, hi_y0, lo_z0, hi_z0, ox, oy, oz, ix, iy, iz, t_min, distance, FAR_SCALE, PARALLEL)  # fmt: skip
            h1, n1, _ = _slab(lo_x1, hi_x1, lo_y1, hi_y1, lo_z1, hi_z1, ox, oy, oz, ix, iy, iz, t_min, distance, FAR_SCALE, PARALLEL)  # fmt: skip
            h2, n2, _ = _slab(lo_x2, hi_x2, lo_y2, hi_y2, lo_z2, hi_z2, ox, oy, oz, ix, iy, iz, t_min, distance, FAR_SCALE, PARALLEL)  # fmt: skip
            h3, n3, _ = _slab(lo_x3, hi_x3, lo_y3, hi_y3, lo_z3, hi_z3, ox, oy, oz, ix, iy, iz, t_min, distance, FAR_SCALE, PARALLEL)  # fmt: skip
            h0 = h0 & active
            h1 = h1 & active
            h2 = h2 & active
            h3 = h3 & active
            test0 = h0 & (r0 < 0)
            test1 = h1 & (r1 < 0)
            test2 = h2 & (r2 < 0)
            test3 = h3 & (r3 < 0)
            # One warp reduction per step: bit 4 s + size - 1, some lane tests a cluster of that size in slot s;
            # bit 16, some lane was active when the step began.
            bit0 = ((-1 - r0) & 3) + 0
            bit1 = ((-1 - r1) & 3) + 4
            bit2 = ((-1 - r2) & 3) + 8
            bit3 = ((-1 - r3) & 3) + 12
            lane_votes = (
                (test0.to(tl.int32) << bit0)
                | (test1.to(tl.int32) << bit1)
                | (test2.to(tl.int32) << bit2)
                | (test3.to(tl.int32) << bit3)
                | (active.to(tl.int32) << 16)
            )
            votes = tl.reduce(lane_votes, 0, _bit_or)
            go = votes & (1 << 16)
            # Leaves are tested on sight, against the distance found so far.
            distance, leaf, tested = _leaf_cluster(tris_ptr, r0, test0, _longest(votes, 0), distance, leaf, tested, kx, ky, kz, okx, oky, okz, sx, sy, sz, t_min, CULL, LANES, VECTOR)  # fmt: skip
            distance, leaf, tested = _leaf_cluster(tris_ptr, r1, test1, _longest(votes, 1), distance, leaf, tested, kx, ky, kz, okx, oky, okz, sx, sy, sz, t_min, CULL, LANES, VECTOR)  # fmt: skip
            distance, leaf, tested = _leaf_cluster(tris_ptr, r2, test2, _longest(votes, 2), distance, leaf, tested, kx, ky, kz, okx, oky, okz, sx, sy, sz, t_min, CULL, LANES, VECTOR)  # fmt: skip
            distance, leaf, tested = _leaf_cluster(tris_ptr, r3, test3, _longest(votes, 3), distance, leaf, tested, kx, ky, kz, okx, oky, okz, sx, sy, sz, t_min, CULL, LANES, VECTOR)  # fmt: skip

            # Inner slots hit, nearest first (a 4-input sorting network; misses sort last with key inf).
            inner0 = h0 & (r0 >= 0)
            inner1 = h1 & (r1 >= 0)
            inner2 = h2 & (r2 >= 0)
            inner3 = h3 & (r3 >= 0)
            big = 3.4028234663852886e38
            k0 = tl.where(inner0, tl.minimum(n0, big), float("inf"))
            k1 = tl.where(inner1, tl.minimum(n1, big), float("inf"))
            k2 = tl.where(inner2, tl.minimum(n2, big), float("inf"))
            k3 = tl.where(inner3, tl.minimum(n3, big), float("inf"))
            a0 = tl.where(inner0, r0, -1)
            a1 = tl.where(inner1, r1, -1)
            a2 = tl.where(inner2, r2, -1)
            a3 = tl.where(inner3, r3, -1)
            k0, a0, k1, a1 = _order(k0, a0, k1, a1)
            k2, a2, k3, a3 = _order(k2, a2, k3, a3)
            k0, a0, k2, a2 = _order(k0, a0, k2, a2)
            k1, a1, k3, a3 = _order(k1, a1, k3, a3)
            k1, a1, k2, a2 = _order(k1, a1, k2, a2)
            # Push the others farthest first, so that the nearest of them is popped first.
            depth, overflow = _push(stack_base, depth, overflow, a3, STACK, LANES)
            depth, overflow = _push(stack_base, depth, overflow, a2, STACK, LANES)
            depth, overflow = _push(stack_base, depth, overflow, a1, STACK, LANES)
            node, depth, done = _advance(stack_base, active, a0, node, depth, leaf, done, ANY_HIT, LANES)
            visited = visited + active.to(tl.int32)

        _store_result(distance_ptr, leaf_ptr, visited_ptr, tested_ptr, overflow_ptr, ray, distance, leaf, visited, tested, overflow)  # fmt: skip
        block += n_programs
