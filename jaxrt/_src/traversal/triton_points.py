"""Point queries as Triton kernels: the nearest-leaf walk and the fast and exact winding numbers on the GPU.

Imported only where a GPU point query runs (Triton and jax-triton installed). The kernels make the decisions of
the Numba walks (:mod:`jaxrt._src.traversal.cpu_points`, whose docstring states them) and of the portable walks:
the nearest-leaf walk pops a node, measures both child boxes (stored in the node), tests leaf children on sight
(child 0, then child 1; a leaf replaces the best only when strictly nearer), pushes inner children no farther
than the best distance farther first, and drops a popped entry whose box is farther than the best distance; the
radius starts at ``max_distance``. The fast winding walk (Barill et al. 2018) sums exact solid angles at the
leaves it reaches and the dipoles of the far subtrees. The leaf formulas are those of
:mod:`jaxrt._src.formulas.point_triangle` instantiated for Triton; the kernels are compiled without
floating-point contraction, so they compute the Numba walk's floats (``atan2`` aside: each backend's library
function).

Work layout: a program walks blocks of ``LANES`` points (one warp), striding by the number of programs. Each
lane keeps its stack in a global scratch buffer laid out ``[program, entry, lane]`` (the ray kernel's layout),
so a warp's accesses to one stack level fall in one cache line. A leaf test runs only when some lane of the warp
needs it. Points with a NaN or infinite coordinate take no step (leaf -1, winding number NaN).

The kernels read the ray kernel's packed rows (:mod:`jaxrt._src.traversal.packed`): a node's two child boxes and
children in one 64-byte row, a triangle in one 48-byte row (the structure's ``kernel_layout`` where it was
built for the kernel, else packed per call), float32.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import triton
import triton.language as tl

from jaxrt._src import formulas
from jaxrt._src.bvh.radix_tree import tree_depth_bound
from jaxrt._src.traversal import kernel_cache, packed

_f = formulas.instance("point_triangle", "triton")
_closest_on_triangle = _f.closest_on_triangle
_triangle_point = _f.triangle_point
_squared_box_distance = _f.squared_box_distance
_solid_angle = _f.solid_angle

__all__ = ["exact_winding", "fast_winding", "nearest"]

#: Points per program block (one warp).
LANES = 32
#: Most programs of a launch (they stride over the blocks): bounds the stack scratch buffer.
MAX_PROGRAMS = 8192
_FOUR_PI = 12.566370614359172


@triton.jit
def _finite(px, py, pz):
    return (tl.abs(px) < float("inf")) & (tl.abs(py) < float("inf")) & (tl.abs(pz) < float("inf"))


@triton.jit
def _triangle(tri_ptr, k, mask):
    """Leaf ``k``'s vertices from its packed row (per axis: the three vertices' coordinates and a zero)."""
    t = tri_ptr + k * 12
    return (
        tl.load(t + 0, mask=mask, other=0.0), tl.load(t + 4, mask=mask, other=0.0), tl.load(t + 8, mask=mask, other=0.0),
        tl.load(t + 1, mask=mask, other=0.0), tl.load(t + 5, mask=mask, other=0.0), tl.load(t + 9, mask=mask, other=0.0),
        tl.load(t + 2, mask=mask, other=0.0), tl.load(t + 6, mask=mask, other=0.0), tl.load(t + 10, mask=mask, other=0.0),
    )  # fmt: skip


@triton.jit
def _leaf_distance(tri_ptr, box_ptr, flag_ptr, k, mask, px, py, pz, BOXES: tl.constexpr):
    """Squared distance from ``p`` to leaf ``k`` (its triangle, or its solid box where flagged) on ``mask``."""
    ax, ay, az, bx, by, bz, cx, cy, cz = _triangle(tri_ptr, k, mask)
    u, v = _closest_on_triangle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz)
    qx, qy, qz = _triangle_point(ax, ay, az, bx, by, bz, cx, cy, cz, u, v)
    dx = px - qx
    dy = py - qy
    dz = pz - qz
    d = (dx * dx + dy * dy) + dz * dz
    if BOXES:
        is_box = tl.load(flag_ptr + k, mask=mask, other=0) != 0
        b = box_ptr + k * 6
        box = mask & is_box
        db = _squared_box_distance(
            px, py, pz,
            tl.load(b + 0, mask=box, other=0.0), tl.load(b + 1, mask=box, other=0.0),
            tl.load(b + 2, mask=box, other=0.0), tl.load(b + 3, mask=box, other=0.0),
            tl.load(b + 4, mask=box, other=0.0), tl.load(b + 5, mask=box, other=0.0),
        )  # fmt: skip
        d = tl.where(is_box, db, d)
    return d


@triton.jit
def _child_box(nodes_ptr, node, j: tl.constexpr, mask, px, py, pz):
    """Squared distance from ``p`` to child ``j``'s box of ``node`` (its packed row: per axis lower0, upper0,
    lower1, upper1); NaN for an empty box."""
    o = nodes_ptr + node * 16 + 2 * j
    d = _squared_box_distance(
        px, py, pz,
        tl.load(o, mask=mask, other=0.0), tl.load(o + 4, mask=mask, other=0.0), tl.load(o + 8, mask=mask, other=0.0),
        tl.load(o + 1, mask=mask, other=0.0), tl.load(o + 5, mask=mask, other=0.0), tl.load(o + 9, mask=mask, other=0.0),
    )  # fmt: skip
    return tl.where(d < float("inf"), d, float("nan"))


@triton.jit
def _child(nodes_ptr, node, j: tl.constexpr, mask):
    """Child ``j`` of ``node`` (int32 bits in its packed row): a node ``c >= 0`` or leaf ``-1 - c``."""
    return tl.load(nodes_ptr + node * 16 + 12 + j, mask=mask, other=0.0).to(tl.int32, bitcast=True)


@triton.jit
def nearest_kernel(
    points_ptr, nodes_ptr, tri_ptr, box_ptr, flag_ptr, limit_ptr, n_points, n_programs,
    out_ptr, stack_ptr, bound_ptr, STACK: tl.constexpr, LANES: tl.constexpr, BOXES: tl.constexpr,
):  # fmt: skip
    """The nearest leaf of each point (``-1``: none within the squared radius ``limit_ptr[0]``)."""
    pid = tl.program_id(0)
    lane = tl.arange(0, LANES)
    stack_base = stack_ptr + pid * (STACK * LANES) + lane
    bound_base = bound_ptr + pid * (STACK * LANES) + lane
    limit2 = tl.load(limit_ptr)
    block = pid
    while block * LANES < n_points:
        p = block * LANES + lane
        live = p < n_points
        px = tl.load(points_ptr + p * 3, mask=live, other=float("nan"))
        py = tl.load(points_ptr + p * 3 + 1, mask=live, other=float("nan"))
        pz = tl.load(points_ptr + p * 3 + 2, mask=live, other=float("nan"))
        best = tl.zeros((LANES,), tl.float32) + limit2
        leaf = tl.full((LANES,), -1, tl.int32)
        start = live & _finite(px, py, pz)
        tl.store(stack_base, tl.zeros((LANES,), tl.int32), mask=start)
        tl.store(bound_base, tl.full((LANES,), float("-inf"), tl.float32), mask=start)
        size = start.to(tl.int32)
        go = tl.max(size, axis=0)
        while go > 0:
            active = size > 0
            top = tl.maximum(size - 1, 0)
            node = tl.load(stack_base + top * LANES, mask=active, other=0)
            bound = tl.load(bound_base + top * LANES, mask=active, other=float("inf"))
            size = tl.where(active, top, size)
            visit = active & (bound <= best)
            d0 = _child_box(nodes_ptr, node, 0, visit, px, py, pz)
            d1 = _child_box(nodes_ptr, node, 1, visit, px, py, pz)
            c0 = _child(nodes_ptr, node, 0, visit)
            c1 = _child(nodes_ptr, node, 1, visit)
            test0 = visit & (c0 < 0) & (d0 <= best)
            if tl.max(test0.to(tl.int32), axis=0) > 0:
                d = _leaf_distance(tri_ptr, box_ptr, flag_ptr, -1 - c0, test0, px, py, pz, BOXES)
                better = test0 & ((d < best) | ((leaf < 0) & (d <= best)))
                best = tl.where(better, d, best)
                leaf = tl.where(better, -1 - c0, leaf)
            test1 = visit & (c1 < 0) & (d1 <= best)
            if tl.max(test1.to(tl.int32), axis=0) > 0:
                d = _leaf_distance(tri_ptr, box_ptr, flag_ptr, -1 - c1, test1, px, py, pz, BOXES)
                better = test1 & ((d < best) | ((leaf < 0) & (d <= best)))
                best = tl.where(better, d, best)
                leaf = tl.where(better, -1 - c1, leaf)
            # Farther first, so that the nearer is popped next.
            swap = d1 < d0
            far_c = tl.where(swap, c0, c1)
            far_d = tl.where(swap, d0, d1)
            near_c = tl.where(swap, c1, c0)
            near_d = tl.where(swap, d1, d0)
            push = visit & (far_c >= 0) & (far_d <= best) & (size < STACK)
            tl.store(stack_base + size * LANES, far_c, mask=push)
            tl.store(bound_base + size * LANES, far_d, mask=push)
            size = size + push.to(tl.int32)
            push = visit & (near_c >= 0) & (near_d <= best) & (size < STACK)
            tl.store(stack_base + size * LANES, near_c, mask=push)
            tl.store(bound_base + size * LANES, near_d, mask=push)
            size = size + push.to(tl.int32)
            go = tl.max(size, axis=0)
        tl.store(out_ptr + p, leaf, mask=live)
        block += n_programs


@triton.jit
def _leaf_winding(tri_ptr, box_ptr, flag_ptr, geometry_ptr, k, mask, px, py, pz, BOXES: tl.constexpr):
    """Winding number of leaf ``k`` at ``p`` on ``mask`` (0 off it and for padding)."""
    ax, ay, az, bx, by, bz, cx, cy, cz = _triangle(tri_ptr, k, mask)
    w = _solid_angle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz)
    w = tl.math.div_rn(w, tl.full(w.shape, 12.566370614359172, tl.float32))
    real = mask & (tl.load(geometry_ptr + k, mask=mask, other=-1) >= 0)
    if BOXES:
        box = real & (tl.load(flag_ptr + k, mask=mask, other=0) != 0)
        b = box_ptr + k * 6
        inside = (tl.load(b + 0, mask=box, other=1.0) <= px) & (px <= tl.load(b + 3, mask=box, other=0.0))
        inside = inside & (tl.load(b + 1, mask=box, other=1.0) <= py) & (py <= tl.load(b + 4, mask=box, other=0.0))
        inside = inside & (tl.load(b + 2, mask=box, other=1.0) <= pz) & (pz <= tl.load(b + 5, mask=box, other=0.0))
        w = tl.where(box, inside.to(tl.float32), w)
    return tl.where(real, w, 0.0)


@triton.jit
def winding_kernel(
    points_ptr, nodes_ptr, tri_ptr, box_ptr, flag_ptr, geometry_ptr, normal_ptr, center_ptr, reach_ptr, n_points,
    n_programs, out_ptr, stack_ptr, STACK: tl.constexpr, LANES: tl.constexpr, BOXES: tl.constexpr,
):  # fmt: skip
    """The fast winding number of each point (NaN for a point with a NaN or infinite coordinate)."""
    pid = tl.program_id(0)
    lane = tl.arange(0, LANES)
    stack_base = stack_ptr + pid * (STACK * LANES) + lane
    block = pid
    while block * LANES < n_points:
        p = block * LANES + lane
        live = p < n_points
        px = tl.load(points_ptr + p * 3, mask=live, other=float("nan"))
        py = tl.load(points_ptr + p * 3 + 1, mask=live, other=float("nan"))
        pz = tl.load(points_ptr + p * 3 + 2, mask=live, other=float("nan"))
        start = live & _finite(px, py, pz)
        total = tl.zeros((LANES,), tl.float32)
        tl.store(stack_base, tl.zeros((LANES,), tl.int32), mask=start)
        size = start.to(tl.int32)
        go = tl.max(size, axis=0)
        while go > 0:
            active = size > 0
            top = tl.maximum(size - 1, 0)
            node = tl.load(stack_base + top * LANES, mask=active, other=0)
            size = tl.where(active, top, size)
            for j in tl.static_range(2):
                child = node * 2 + j
                c = _child(nodes_ptr, node, j, active)
                is_leaf = active & (c < 0)
                if tl.max(is_leaf.to(tl.int32), axis=0) > 0:
                    w = _leaf_winding(tri_ptr, box_ptr, flag_ptr, geometry_ptr, -1 - c, is_leaf, px, py, pz, BOXES)
                    total += tl.where(is_leaf, w, 0.0)
                inner = active & (c >= 0)
                ox = tl.load(center_ptr + child * 3, mask=inner, other=0.0) - px
                oy = tl.load(center_ptr + child * 3 + 1, mask=inner, other=0.0) - py
                oz = tl.load(center_ptr + child * 3 + 2, mask=inner, other=0.0) - pz
                dist2 = (ox * ox + oy * oy) + oz * oz
                far = inner & (dist2 > tl.load(reach_ptr + child, mask=inner, other=0.0))
                nx = tl.load(normal_ptr + child * 3, mask=far, other=0.0)
                ny = tl.load(normal_ptr + child * 3 + 1, mask=far, other=0.0)
                nz = tl.load(normal_ptr + child * 3 + 2, mask=far, other=0.0)
                safe = tl.where(far, dist2, 1.0)
                den = (12.566370614359172 * safe) * tl.math.sqrt_rn(safe)
                total += tl.where(far, tl.math.div_rn((nx * ox + ny * oy) + nz * oz, den), 0.0)
                push = inner & (far == 0) & (size < STACK)
                tl.store(stack_base + size * LANES, c, mask=push)
                size = size + push.to(tl.int32)
            go = tl.max(size, axis=0)
        tl.store(out_ptr + p, tl.where(start, total, float("nan")), mask=live)
        block += n_programs


@triton.jit
def exact_kernel(
    points_ptr, tri_ptr, box_ptr, flag_ptr, geometry_ptr, n_points, n_leaves, out_ptr, LANES: tl.constexpr,
    BOXES: tl.constexpr,
):  # fmt: skip
    """The exact winding number of each point: every leaf's solid angle summed in leaf order."""
    pid = tl.program_id(0)
    p = pid * LANES + tl.arange(0, LANES)
    live = p < n_points
    px = tl.load(points_ptr + p * 3, mask=live, other=float("nan"))
    py = tl.load(points_ptr + p * 3 + 1, mask=live, other=float("nan"))
    pz = tl.load(points_ptr + p * 3 + 2, mask=live, other=float("nan"))
    start = live & _finite(px, py, pz)
    total = tl.zeros((LANES,), tl.float32)
    for k in range(n_leaves):
        kk = tl.zeros((LANES,), tl.int32) + k
        total += _leaf_winding(tri_ptr, box_ptr, flag_ptr, geometry_ptr, kk, start, px, py, pz, BOXES)
    tl.store(out_ptr + p, tl.where(start, total, float("nan")), mask=live)


def _launch(kernel: str, programs: int, args: tuple, out_shape: tuple, params: dict) -> tuple[jax.Array, ...]:
    """Run kernel ``kernel`` of this module through jax-triton (outputs after the inputs)."""
    import jax_triton as jt

    kernel_cache.install()
    out = jt.triton_call(
        *args,
        kernel=globals()[kernel],
        out_shape=list(out_shape),
        grid=(programs,),
        num_warps=1,
        num_stages=1,
        enable_fp_fusion=False,
        **params,
    )
    return tuple(out)


def _programs(n: int) -> int:
    return max(1, min(MAX_PROGRAMS, -(-n // LANES)))


def _stack(triangles) -> int:
    return tree_depth_bound(triangles.shape[0]) + 1


@jax.custom_batching.sequential_vmap
def _nearest(points, nodes, triangles, boxes, flags, limit2):
    n = points.shape[0]
    programs, stack = _programs(n), _stack(triangles)
    shapes = (
        jax.ShapeDtypeStruct((n,), jnp.int32),
        jax.ShapeDtypeStruct((programs * stack * LANES,), jnp.int32),
        jax.ShapeDtypeStruct((programs * stack * LANES,), jnp.float32),
    )
    params = dict(STACK=stack, LANES=LANES, BOXES=boxes.shape[0] == triangles.shape[0])
    args = (points, nodes, triangles, boxes, flags, limit2, n, programs)
    return _launch("nearest_kernel", programs, args, shapes, params)[0]


@jax.custom_batching.sequential_vmap
def _fast(points, nodes, triangles, boxes, flags, geometry, normal, center, reach2):
    n = points.shape[0]
    programs, stack = _programs(n), _stack(triangles)
    shapes = (jax.ShapeDtypeStruct((n,), jnp.float32), jax.ShapeDtypeStruct((programs * stack * LANES,), jnp.int32))
    params = dict(STACK=stack, LANES=LANES, BOXES=boxes.shape[0] == triangles.shape[0])
    args = (points, nodes, triangles, boxes, flags, geometry, normal, center, reach2, n, programs)
    return _launch("winding_kernel", programs, args, shapes, params)[0]


@jax.custom_batching.sequential_vmap
def _exact(points, triangles, boxes, flags, geometry):
    n = points.shape[0]
    shapes = (jax.ShapeDtypeStruct((n,), jnp.float32),)
    params = dict(LANES=LANES, BOXES=boxes.shape[0] == triangles.shape[0])
    args = (points, triangles, boxes, flags, geometry, n, triangles.shape[0])
    return _launch("exact_kernel", -(-n // LANES), args, shapes, params)[0]


def _f32(*arrays):
    return tuple(jax.lax.stop_gradient(a).astype(jnp.float32) for a in arrays)


def _i32(*arrays):
    return tuple(jax.lax.stop_gradient(a).astype(jnp.int32) for a in arrays)


def _rows(structure) -> packed.KernelLayout:
    """The structure's packed node and triangle rows (made at build time where the kernel runs, else here)."""
    layout = getattr(structure, "kernel_layout", None)
    if layout is not None:
        return packed.KernelLayout(*(jax.lax.stop_gradient(a) for a in layout))
    return packed.kernel_layout(structure.node_lower, structure.node_upper, structure.node_children, structure.leaf_triangle)  # fmt: skip


def nearest(points, structure, boxes, box_leaf, limit2) -> jax.Array:
    """The nearest leaf to each point ``(n, 3)`` within squared distance ``limit2`` (-1: none)."""
    rows = _rows(structure)
    p, b, limit = _f32(points, boxes, jnp.reshape(limit2, (1,)))
    (flags,) = _i32(box_leaf)
    return _nearest(p, rows.nodes, rows.triangles, b, flags, limit)


def fast_winding(points, structure, boxes, box_leaf, dipoles) -> jax.Array:
    """The fast winding number of each point ``(n, 3)`` (:func:`jaxrt._src.winding._dipoles`' subtrees)."""
    rows = _rows(structure)
    p, b, normal, center, reach2 = _f32(points, boxes, dipoles.normal, dipoles.center, dipoles.reach2)
    flags, geometry = _i32(box_leaf, structure.leaf_geometry)
    return _fast(p, rows.nodes, rows.triangles, b, flags, geometry, normal, center, reach2)


def exact_winding(points, structure, boxes, box_leaf) -> jax.Array:
    """The exact winding number of each point ``(n, 3)``."""
    rows = _rows(structure)
    p, b = _f32(points, boxes)
    flags, geometry = _i32(box_leaf, structure.leaf_geometry)
    return _exact(p, rows.triangles, b, flags, geometry)
