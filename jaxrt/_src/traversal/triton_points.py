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

Variants (:class:`Variant`, :data:`VARIANTS`; ``JAXRT_POINT_VARIANT`` picks the one the queries use, and
``python -m jaxrt.bench.points --variants`` times them side by side). All make the decisions above, so they pick
the same leaf and add the same fast winding terms in the same order (the same floats):

- ``stack`` (:func:`nearest_kernel`, :func:`winding_kernel`): every node is pushed and popped, as above.
- ``near`` (:func:`nearest_near_kernel`, :func:`winding_near_kernel`; the default, the fastest of them on an
  H100, ``docs/point_queries.md``): the node to visit next stays in a
  register. The nearer inner child within the radius is entered at once, the farther pushed only when both are
  entered (the stack walk pushes both and pops the nearer at once: the same order and the same radius); the
  stack is popped only when no child is entered, with ``skip`` in a loop of its own until an entry lies within
  the radius. A stack entry holds the node and its box distance in one 8-byte word pair. The winding walk
  enters child 1 where it is opened (pushing child 0 if also opened), the stack walk's order.
- ``refill`` (:func:`nearest_refill_kernel`, :func:`winding_refill_kernel`): the ``near`` walk, with a program
  owning a run of consecutive points and a lane taking the next one as soon as its walk ends (Aila and Laine's
  persistent threads, 2009), instead of the warp waiting for the slowest of each block of 32 points.
- ``stackless`` (:func:`nearest_stackless_kernel`, :func:`winding_stackless_kernel`): no stack (Hapala et al.,
  "Efficient Stack-less BVH Traversal for Ray Tracing", SCCG 2011): a lane keeps its node, that node's
  parent and a direction. Going up from a child, the parent's two boxes are measured again (the same floats),
  so the walk knows whether it leaves the nearer child, and then enters the farther one if it is an inner node
  within the radius of that moment (when the stack walk would pop it), else goes up again. Parents come from
  the node children (:func:`jaxrt._src.bvh.ploc.parent_nodes`) per call. No scratch memory, so every block of
  points gets its own program.
- ``vector_loads``: node rows, triangle rows and stack entries with 16- and 8-byte loads; ``leaf_batch``: one
  leaf test for each lane's first leaf child (child 0, else child 1), a second only for lanes that test both
  (child 1 against the radius child 0 left), instead of one branch per child; ``programs``, ``lanes``: the launch
  (one warp per program always). The winding variants read each node's two dipoles from one 64-byte row
  (:func:`_dipole_rows`, packed per call).
"""

from __future__ import annotations

import dataclasses
import functools
import os

import jax
import jax.numpy as jnp
import triton
import triton.language as tl

from jaxrt._src import formulas
from jaxrt._src.bvh.ploc import parent_nodes
from jaxrt._src.bvh.radix_tree import tree_depth_bound
from jaxrt._src.traversal import kernel_cache, packed
from jaxrt._src.traversal.triton_kernel import _quad

_f = formulas.instance("point_triangle", "triton")
_closest_on_triangle = _f.closest_on_triangle
_triangle_point = _f.triangle_point
_squared_box_distance = _f.squared_box_distance
_solid_angle = _f.solid_angle

__all__ = ["VARIANT", "VARIANTS", "Variant", "exact_winding", "fast_winding", "nearest", "variant"]

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
    return _vertices_distance(ax, ay, az, bx, by, bz, cx, cy, cz, box_ptr, flag_ptr, k, mask, px, py, pz, BOXES)


@triton.jit
def _vertices_distance(ax, ay, az, bx, by, bz, cx, cy, cz, box_ptr, flag_ptr, k, mask, px, py, pz,
                       BOXES: tl.constexpr):  # fmt: skip
    """Squared distance from ``p`` to leaf ``k`` given its vertices (its solid box where flagged)."""
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


# --- the variants' kernels (module docstring, "Variants") -------------------------------------------------------


@triton.jit
def _node_row(nodes_ptr, node, mask, px, py, pz, LANES: tl.constexpr, VECTOR: tl.constexpr):
    """Squared distances from ``p`` to both child boxes of ``node`` (NaN for an empty box) and its children."""
    lo0x, hi0x, lo1x, hi1x = _quad(nodes_ptr, node, 16, 0, mask, LANES, VECTOR)
    lo0y, hi0y, lo1y, hi1y = _quad(nodes_ptr, node, 16, 4, mask, LANES, VECTOR)
    lo0z, hi0z, lo1z, hi1z = _quad(nodes_ptr, node, 16, 8, mask, LANES, VECTOR)
    c0f, c1f, _, _ = _quad(nodes_ptr, node, 16, 12, mask, LANES, VECTOR)
    d0 = _squared_box_distance(px, py, pz, lo0x, lo0y, lo0z, hi0x, hi0y, hi0z)
    d1 = _squared_box_distance(px, py, pz, lo1x, lo1y, lo1z, hi1x, hi1y, hi1z)
    d0 = tl.where(d0 < float("inf"), d0, float("nan"))
    d1 = tl.where(d1 < float("inf"), d1, float("nan"))
    return d0, d1, c0f.to(tl.int32, bitcast=True), c1f.to(tl.int32, bitcast=True)


@triton.jit
def _children(nodes_ptr, node, mask, LANES: tl.constexpr, VECTOR: tl.constexpr):
    """The two children of ``node`` (int32)."""
    c0f, c1f, _, _ = _quad(nodes_ptr, node, 16, 12, mask, LANES, VECTOR)
    return c0f.to(tl.int32, bitcast=True), c1f.to(tl.int32, bitcast=True)


@triton.jit
def _triangle_rows(tri_ptr, k, mask, LANES: tl.constexpr, VECTOR: tl.constexpr):
    """Leaf ``k``'s vertices from its packed row with three 16-byte loads (``VECTOR``) or twelve."""
    ax, bx, cx, _ = _quad(tri_ptr, k, 12, 0, mask, LANES, VECTOR)
    ay, by, cy, _ = _quad(tri_ptr, k, 12, 4, mask, LANES, VECTOR)
    az, bz, cz, _ = _quad(tri_ptr, k, 12, 8, mask, LANES, VECTOR)
    return ax, ay, az, bx, by, bz, cx, cy, cz


@triton.jit
def _leaf_distance_rows(tri_ptr, box_ptr, flag_ptr, k, mask, px, py, pz, BOXES: tl.constexpr, LANES: tl.constexpr,
                        VECTOR: tl.constexpr):  # fmt: skip
    """:func:`_leaf_distance` with the triangle read by :func:`_triangle_rows`."""
    ax, ay, az, bx, by, bz, cx, cy, cz = _triangle_rows(tri_ptr, k, mask, LANES, VECTOR)
    return _vertices_distance(ax, ay, az, bx, by, bz, cx, cy, cz, box_ptr, flag_ptr, k, mask, px, py, pz, BOXES)


@triton.jit
def _keep(test, d, k, best, leaf):
    """The walk's rule: leaf ``k`` at squared distance ``d`` replaces the best only when strictly nearer (or
    when none is known yet and it is within the radius)."""
    better = test & ((d < best) | ((leaf < 0) & (d <= best)))
    return tl.where(better, d, best), tl.where(better, k, leaf)


@triton.jit
def _bit_or(a, b):
    return a | b


@triton.jit
def _leaves(tri_ptr, box_ptr, flag_ptr, c0, c1, d0, d1, visit, best, leaf, active, px, py, pz, BOXES: tl.constexpr,
            LANES: tl.constexpr, VECTOR: tl.constexpr, BATCH: tl.constexpr):  # fmt: skip
    """Test a visited node's leaf children in the walk's order (child 0, then child 1 against the radius child
    0 left) behind warp-uniform branches. ``BATCH``: one test serves each lane's first leaf child (child 0, or
    child 1 where child 0 is not tested), a second only the lanes that test both. Also returns the warp's
    vote: bit 2 set where some lane is ``active``."""
    test0 = visit & (c0 < 0) & (d0 <= best)
    test1 = visit & (c1 < 0) & (d1 <= best)  # child 1 only gets fewer once child 0 lowered the radius
    if BATCH:
        first = test0 | test1
        both = test0 & test1
        votes = tl.reduce(first.to(tl.int32) | (both.to(tl.int32) << 1) | (active.to(tl.int32) << 2), 0, _bit_or)
        if (votes & 1) != 0:
            k = tl.where(test0, -1 - c0, -1 - c1)
            d = _leaf_distance_rows(tri_ptr, box_ptr, flag_ptr, k, first, px, py, pz, BOXES, LANES, VECTOR)
            best, leaf = _keep(first, d, k, best, leaf)
        if (votes & 2) != 0:
            second = both & (d1 <= best)
            d = _leaf_distance_rows(tri_ptr, box_ptr, flag_ptr, -1 - c1, second, px, py, pz, BOXES, LANES, VECTOR)
            best, leaf = _keep(second, d, -1 - c1, best, leaf)
    else:
        votes = tl.reduce(test0.to(tl.int32) | (test1.to(tl.int32) << 1) | (active.to(tl.int32) << 2), 0, _bit_or)
        if (votes & 1) != 0:
            d = _leaf_distance_rows(tri_ptr, box_ptr, flag_ptr, -1 - c0, test0, px, py, pz, BOXES, LANES, VECTOR)
            best, leaf = _keep(test0, d, -1 - c0, best, leaf)
        if (votes & 2) != 0:
            test1 = test1 & (d1 <= best)
            d = _leaf_distance_rows(tri_ptr, box_ptr, flag_ptr, -1 - c1, test1, px, py, pz, BOXES, LANES, VECTOR)
            best, leaf = _keep(test1, d, -1 - c1, best, leaf)
    return best, leaf, votes


@triton.jit
def _stack_entry(base, depth, mask, LANES: tl.constexpr, VECTOR: tl.constexpr):
    """Stack entry ``depth`` (a node and its squared box distance, adjacent int32 words) of each lane."""
    at = base + depth * (2 * LANES)
    if VECTOR:
        pair = tl.load(at[:, None] + tl.arange(0, 2)[None, :], mask=mask[:, None], other=0)
        node, bits = tl.split(pair)
    else:
        node = tl.load(at, mask=mask, other=0)
        bits = tl.load(at + 1, mask=mask, other=0)
    return node, bits.to(tl.float32, bitcast=True)


@triton.jit
def _push_entry(base, depth, mask, node, bound, LANES: tl.constexpr, VECTOR: tl.constexpr):
    at = base + depth * (2 * LANES)
    bits = bound.to(tl.int32, bitcast=True)
    if VECTOR:
        tl.store(at[:, None] + tl.arange(0, 2)[None, :], tl.join(node, bits), mask=mask[:, None])
    else:
        tl.store(at, node, mask=mask)
        tl.store(at + 1, bits, mask=mask)


@triton.jit
def _load_points(points_ptr, p, live):
    px = tl.load(points_ptr + p * 3, mask=live, other=float("nan"))
    py = tl.load(points_ptr + p * 3 + 1, mask=live, other=float("nan"))
    pz = tl.load(points_ptr + p * 3 + 2, mask=live, other=float("nan"))
    return px, py, pz


@triton.jit
def _near_step(nodes_ptr, tri_ptr, box_ptr, flag_ptr, base, node, bound, size, best, leaf, active, px, py, pz,
               STACK: tl.constexpr, LANES: tl.constexpr, BOXES: tl.constexpr, VECTOR: tl.constexpr,
               BATCH: tl.constexpr, SKIP: tl.constexpr):  # fmt: skip
    """One step of the ``near`` walk for every ``active`` lane: visit ``node`` (dropped where its box distance
    ``bound`` is beyond the radius), then enter a child or pop. Returns the new state and the warp's vote (bit 2:
    some lane was active)."""
    visit = active & (bound <= best)
    d0, d1, c0, c1 = _node_row(nodes_ptr, node, visit, px, py, pz, LANES, VECTOR)
    best, leaf, votes = _leaves(
        tri_ptr, box_ptr, flag_ptr, c0, c1, d0, d1, visit, best, leaf, active, px, py, pz, BOXES, LANES, VECTOR,
        BATCH,
    )  # fmt: skip
    swap = d1 < d0
    far_c = tl.where(swap, c0, c1)
    far_d = tl.where(swap, d0, d1)
    near_c = tl.where(swap, c1, c0)
    near_d = tl.where(swap, d1, d0)
    enter_near = visit & (near_c >= 0) & (near_d <= best)
    enter_far = visit & (far_c >= 0) & (far_d <= best)
    push = enter_near & enter_far & (size < STACK)
    _push_entry(base, size, push, far_c, far_d, LANES, VECTOR)
    size = size + push.to(tl.int32)
    node = tl.where(enter_near, near_c, tl.where(enter_far, far_c, node))
    bound = tl.where(enter_near, near_d, tl.where(enter_far, far_d, bound))
    pending = active & (enter_near == 0) & (enter_far == 0)
    if SKIP:
        active = active & (pending == 0)
        while tl.max(pending.to(tl.int32), axis=0) > 0:
            has = pending & (size > 0)
            top, b = _stack_entry(base, size - 1, has, LANES, VECTOR)
            size = tl.where(has, size - 1, size)
            node = tl.where(has, top, node)
            bound = tl.where(has, b, bound)
            ok = has & (b <= best)
            active = active | ok
            pending = has & (ok == 0)
    else:
        has = pending & (size > 0)
        top, b = _stack_entry(base, size - 1, has, LANES, VECTOR)
        size = tl.where(has, size - 1, size)
        node = tl.where(has, top, node)
        bound = tl.where(has, b, bound)
        active = active & ((pending == 0) | has)
    return node, bound, size, best, leaf, active, votes


@triton.jit
def nearest_near_kernel(
    points_ptr, nodes_ptr, tri_ptr, box_ptr, flag_ptr, limit_ptr, n_points, n_programs,
    out_ptr, stack_ptr, STACK: tl.constexpr, LANES: tl.constexpr, BOXES: tl.constexpr, VECTOR: tl.constexpr,
    BATCH: tl.constexpr, SKIP: tl.constexpr,
):  # fmt: skip
    """:func:`nearest_kernel`'s decisions, entering the nearer inner child directly: only the farther one is
    pushed (node and box distance in one 8-byte entry) and the stack is popped only when no child is entered.
    ``SKIP``: a pop takes entries until one is within the radius, in a loop of its own."""
    pid = tl.program_id(0)
    lane = tl.arange(0, LANES)
    base = stack_ptr + pid * (STACK * 2 * LANES) + lane * 2
    limit2 = tl.load(limit_ptr)
    block = pid
    while block * LANES < n_points:
        p = block * LANES + lane
        live = p < n_points
        px, py, pz = _load_points(points_ptr, p, live)
        best = tl.zeros((LANES,), tl.float32) + limit2
        leaf = tl.full((LANES,), -1, tl.int32)
        active = live & _finite(px, py, pz)
        node = tl.zeros((LANES,), tl.int32)
        bound = tl.full((LANES,), float("-inf"), tl.float32)  # the current node's box distance
        size = tl.zeros((LANES,), tl.int32)
        go = tl.max(active.to(tl.int32), axis=0)
        while go > 0:
            node, bound, size, best, leaf, active, votes = _near_step(
                nodes_ptr, tri_ptr, box_ptr, flag_ptr, base, node, bound, size, best, leaf, active, px, py, pz,
                STACK, LANES, BOXES, VECTOR, BATCH, SKIP,
            )  # fmt: skip
            go = votes & 4  # one (masked) step more after the last lane ends
        tl.store(out_ptr + p, leaf, mask=live)
        block += n_programs


@triton.jit
def nearest_refill_kernel(
    points_ptr, nodes_ptr, tri_ptr, box_ptr, flag_ptr, limit_ptr, n_points, per_program,
    out_ptr, stack_ptr, STACK: tl.constexpr, LANES: tl.constexpr, BOXES: tl.constexpr, VECTOR: tl.constexpr,
    BATCH: tl.constexpr, SKIP: tl.constexpr,
):  # fmt: skip
    """:func:`nearest_near_kernel`'s walk, with lanes refilled: a program owns ``per_program`` consecutive
    points, and a lane whose walk has ended takes the program's next point at the start of the following step
    (persistent threads, Aila and Laine 2009), so the warp steps with all its lanes busy until its points run
    out instead of waiting for the slowest of each block of 32. Each point's walk is unchanged."""
    pid = tl.program_id(0)
    lane = tl.arange(0, LANES)
    base = stack_ptr + pid * (STACK * 2 * LANES) + lane * 2
    limit2 = tl.load(limit_ptr)
    begin = pid * per_program
    end = tl.minimum(begin + per_program, n_points)
    following = begin
    p = tl.zeros((LANES,), tl.int32)
    px = tl.zeros((LANES,), tl.float32)
    py = tl.zeros((LANES,), tl.float32)
    pz = tl.zeros((LANES,), tl.float32)
    best = tl.zeros((LANES,), tl.float32)
    leaf = tl.full((LANES,), -1, tl.int32)
    node = tl.zeros((LANES,), tl.int32)
    bound = tl.zeros((LANES,), tl.float32)
    size = tl.zeros((LANES,), tl.int32)
    active = tl.zeros((LANES,), tl.int1)
    go = (following < end).to(tl.int32)
    while go > 0:
        idle = (active == 0).to(tl.int32)
        free = tl.sum(idle, axis=0)
        if (free > 0) & (following < end):
            q = following + tl.cumsum(idle, 0) - 1
            take = (idle != 0) & (q < end)
            qx, qy, qz = _load_points(points_ptr, q, take)
            walk = take & _finite(qx, qy, qz)
            tl.store(out_ptr + q, tl.full((LANES,), -1, tl.int32), mask=take & (walk == 0))  # no step
            p = tl.where(take, q, p)
            px = tl.where(take, qx, px)
            py = tl.where(take, qy, py)
            pz = tl.where(take, qz, pz)
            best = tl.where(take, limit2, best)
            leaf = tl.where(take, -1, leaf)
            node = tl.where(take, 0, node)
            bound = tl.where(take, float("-inf"), bound)
            size = tl.where(take, 0, size)
            active = active | walk
            following += free
        walking = active
        node, bound, size, best, leaf, active, votes = _near_step(
            nodes_ptr, tri_ptr, box_ptr, flag_ptr, base, node, bound, size, best, leaf, active, px, py, pz,
            STACK, LANES, BOXES, VECTOR, BATCH, SKIP,
        )  # fmt: skip
        tl.store(out_ptr + p, leaf, mask=walking & (active == 0))
        go = (votes & 4) | (following < end).to(tl.int32)


@triton.jit
def nearest_stackless_kernel(
    points_ptr, nodes_ptr, tri_ptr, box_ptr, flag_ptr, limit_ptr, parent_ptr, n_points, n_programs,
    out_ptr, LANES: tl.constexpr, BOXES: tl.constexpr, VECTOR: tl.constexpr, BATCH: tl.constexpr,
):  # fmt: skip
    """:func:`nearest_kernel`'s decisions without a stack (Hapala et al. 2011, "Efficient stack-less BVH
    traversal for ray tracing"): each lane keeps a node, its parent and a direction in registers. Going down, a
    node is visited (leaf children tested) and its nearer entered child taken, else its farther one, else the
    walk turns up. Going up from child ``c`` to its parent, the parent's two boxes are measured again (the
    same floats, so the same near and far child): from the nearer child the walk enters the farther one where
    it is an inner node within the radius, else it goes up again; above the root it ends. The order of visits
    is that of the stack walk (the farther child is entered after the nearer subtree, when the stack walk would
    pop it, and against the radius of that moment), hence the same leaf."""
    pid = tl.program_id(0)
    lane = tl.arange(0, LANES)
    limit2 = tl.load(limit_ptr)
    block = pid
    while block * LANES < n_points:
        p = block * LANES + lane
        live = p < n_points
        px, py, pz = _load_points(points_ptr, p, live)
        best = tl.zeros((LANES,), tl.float32) + limit2
        leaf = tl.full((LANES,), -1, tl.int32)
        active = live & _finite(px, py, pz)
        node = tl.zeros((LANES,), tl.int32)
        parent = tl.full((LANES,), -1, tl.int32)
        up = tl.zeros((LANES,), tl.int1)
        go = tl.max(active.to(tl.int32), axis=0)
        while go > 0:
            down = active & (up == 0)
            rising = active & up  # each such lane has a parent (a lane above the root has ended)
            # Going down the row is the node's; going up, its parent's (whose parent is read alongside).
            row = tl.where(up, parent, node)
            d0, d1, c0, c1 = _node_row(nodes_ptr, row, active, px, py, pz, LANES, VECTOR)
            grand = tl.load(parent_ptr + row, mask=rising, other=-1)
            best, leaf, votes = _leaves(
                tri_ptr, box_ptr, flag_ptr, c0, c1, d0, d1, down, best, leaf, active, px, py, pz, BOXES, LANES,
                VECTOR, BATCH,
            )  # fmt: skip
            go = votes & 4
            swap = d1 < d0
            far_c = tl.where(swap, c0, c1)
            far_d = tl.where(swap, d0, d1)
            near_c = tl.where(swap, c1, c0)
            near_d = tl.where(swap, d1, d0)
            far_ok = (far_c >= 0) & (far_d <= best)
            enter_near = down & (near_c >= 0) & (near_d <= best)
            enter_far = down & (enter_near == 0) & far_ok
            sibling = rising & (node == near_c) & far_ok
            enter = enter_near | enter_far | sibling
            target = tl.where(enter_near, near_c, far_c)
            # Entering: the row's node becomes the parent. Rising past a finished child: one level up.
            parent = tl.where(enter, row, tl.where(rising, grand, parent))
            node = tl.where(enter, target, tl.where(rising, row, node))
            up = (up | down) & (enter == 0)
            active = active & ((up & (parent < 0)) == 0)
        tl.store(out_ptr + p, leaf, mask=live)
        block += n_programs


@triton.jit
def _leaf_winding_rows(tri_ptr, box_ptr, flag_ptr, geometry_ptr, k, mask, px, py, pz, BOXES: tl.constexpr,
                       LANES: tl.constexpr, VECTOR: tl.constexpr):  # fmt: skip
    """:func:`_leaf_winding` with the triangle read by :func:`_triangle_rows`."""
    ax, ay, az, bx, by, bz, cx, cy, cz = _triangle_rows(tri_ptr, k, mask, LANES, VECTOR)
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
def _dipole(dip_ptr, node, CENTER: tl.constexpr, NORMAL: tl.constexpr, inner, add, px, py, pz, LANES: tl.constexpr,
            VECTOR: tl.constexpr):  # fmt: skip
    """Whether the child subtree whose dipole row columns start at ``CENTER`` (centre, squared reach) and
    ``NORMAL`` is far from ``p`` (on ``inner``), and its dipole term where also ``add`` (else 0)."""
    cx, cy, cz, reach = _quad(dip_ptr, node, 16, CENTER, inner, LANES, VECTOR)
    ox = cx - px
    oy = cy - py
    oz = cz - pz
    dist2 = (ox * ox + oy * oy) + oz * oz
    far = inner & (dist2 > reach)
    term_on = far & add
    nx, ny, nz, _ = _quad(dip_ptr, node, 16, NORMAL, term_on, LANES, VECTOR)
    safe = tl.where(term_on, dist2, 1.0)
    den = (12.566370614359172 * safe) * tl.math.sqrt_rn(safe)
    return far, tl.where(term_on, tl.math.div_rn((nx * ox + ny * oy) + nz * oz, den), 0.0)


@triton.jit
def _node_terms(tri_ptr, box_ptr, flag_ptr, geometry_ptr, dip_ptr, row, c0, c1, down, active, px, py, pz,
                BOXES: tl.constexpr, LANES: tl.constexpr, VECTOR: tl.constexpr, BATCH: tl.constexpr):  # fmt: skip
    """The terms of node ``row``'s two children (leaf solid angles and far dipoles, 0 for an opened child) on
    ``down``, whether each inner child is opened (on ``active``), and the warp's vote (bit 2: some lane
    ``active``)."""
    leaf0 = down & (c0 < 0)
    leaf1 = down & (c1 < 0)
    far0, t0 = _dipole(dip_ptr, row, 0, 8, active & (c0 >= 0), down, px, py, pz, LANES, VECTOR)
    far1, t1 = _dipole(dip_ptr, row, 4, 12, active & (c1 >= 0), down, px, py, pz, LANES, VECTOR)
    open0 = active & (c0 >= 0) & (far0 == 0)
    open1 = active & (c1 >= 0) & (far1 == 0)
    if BATCH:
        first = leaf0 | leaf1
        both = leaf0 & leaf1
        votes = tl.reduce(first.to(tl.int32) | (both.to(tl.int32) << 1) | (active.to(tl.int32) << 2), 0, _bit_or)
        if (votes & 1) != 0:
            k = tl.where(leaf0, -1 - c0, -1 - c1)
            w = _leaf_winding_rows(tri_ptr, box_ptr, flag_ptr, geometry_ptr, k, first, px, py, pz, BOXES, LANES, VECTOR)  # fmt: skip
            t0 = tl.where(leaf0, w, t0)
            t1 = tl.where(leaf1 & (leaf0 == 0), w, t1)
        if (votes & 2) != 0:
            w = _leaf_winding_rows(tri_ptr, box_ptr, flag_ptr, geometry_ptr, -1 - c1, both, px, py, pz, BOXES, LANES, VECTOR)  # fmt: skip
            t1 = tl.where(both, w, t1)
    else:
        votes = tl.reduce(leaf0.to(tl.int32) | (leaf1.to(tl.int32) << 1) | (active.to(tl.int32) << 2), 0, _bit_or)
        if (votes & 1) != 0:
            w = _leaf_winding_rows(tri_ptr, box_ptr, flag_ptr, geometry_ptr, -1 - c0, leaf0, px, py, pz, BOXES, LANES, VECTOR)  # fmt: skip
            t0 = tl.where(leaf0, w, t0)
        if (votes & 2) != 0:
            w = _leaf_winding_rows(tri_ptr, box_ptr, flag_ptr, geometry_ptr, -1 - c1, leaf1, px, py, pz, BOXES, LANES, VECTOR)  # fmt: skip
            t1 = tl.where(leaf1, w, t1)
    return t0, t1, open0, open1, votes


@triton.jit
def _winding_near_step(nodes_ptr, tri_ptr, box_ptr, flag_ptr, geometry_ptr, dip_ptr, stack_base, node, size, total,
                       active, px, py, pz, STACK: tl.constexpr, LANES: tl.constexpr, BOXES: tl.constexpr,
                       VECTOR: tl.constexpr, BATCH: tl.constexpr):  # fmt: skip
    """One step of the ``near`` winding walk for every ``active`` lane: ``node``'s terms added, then a child
    entered or the stack popped. Returns the new state and the warp's vote (bit 2: some lane was active)."""
    c0, c1 = _children(nodes_ptr, node, active, LANES, VECTOR)
    t0, t1, open0, open1, votes = _node_terms(
        tri_ptr, box_ptr, flag_ptr, geometry_ptr, dip_ptr, node, c0, c1, active, active, px, py, pz, BOXES, LANES,
        VECTOR, BATCH,
    )  # fmt: skip
    total = total + t0
    total = total + t1
    push = open1 & open0 & (size < STACK)
    tl.store(stack_base + size * LANES, c0, mask=push)
    size = size + push.to(tl.int32)
    node = tl.where(open1, c1, tl.where(open0, c0, node))
    pop = active & (open0 == 0) & (open1 == 0)
    has = pop & (size > 0)
    top = tl.load(stack_base + (size - 1) * LANES, mask=has, other=0)
    size = tl.where(has, size - 1, size)
    node = tl.where(has, top, node)
    active = active & ((pop == 0) | has)
    return node, size, total, active, votes


@triton.jit
def winding_near_kernel(
    points_ptr, nodes_ptr, tri_ptr, box_ptr, flag_ptr, geometry_ptr, dip_ptr, n_points, n_programs, out_ptr,
    stack_ptr, STACK: tl.constexpr, LANES: tl.constexpr, BOXES: tl.constexpr, VECTOR: tl.constexpr,
    BATCH: tl.constexpr,
):  # fmt: skip
    """:func:`winding_kernel`'s sum in its order, entering child 1 where it is opened (child 0 pushed if also
    opened), else child 0, else popping: the stack walk's order of nodes, so the same floats. ``dip_ptr``: the
    dipole rows (:func:`_dipole_rows`)."""
    pid = tl.program_id(0)
    lane = tl.arange(0, LANES)
    stack_base = stack_ptr + pid * (STACK * LANES) + lane
    block = pid
    while block * LANES < n_points:
        p = block * LANES + lane
        live = p < n_points
        px, py, pz = _load_points(points_ptr, p, live)
        start = live & _finite(px, py, pz)
        active = start
        total = tl.zeros((LANES,), tl.float32)
        node = tl.zeros((LANES,), tl.int32)
        size = tl.zeros((LANES,), tl.int32)
        go = tl.max(active.to(tl.int32), axis=0)
        while go > 0:
            node, size, total, active, votes = _winding_near_step(
                nodes_ptr, tri_ptr, box_ptr, flag_ptr, geometry_ptr, dip_ptr, stack_base, node, size, total, active,
                px, py, pz, STACK, LANES, BOXES, VECTOR, BATCH,
            )  # fmt: skip
            go = votes & 4
        tl.store(out_ptr + p, tl.where(start, total, float("nan")), mask=live)
        block += n_programs


@triton.jit
def winding_refill_kernel(
    points_ptr, nodes_ptr, tri_ptr, box_ptr, flag_ptr, geometry_ptr, dip_ptr, n_points, per_program, out_ptr,
    stack_ptr, STACK: tl.constexpr, LANES: tl.constexpr, BOXES: tl.constexpr, VECTOR: tl.constexpr,
    BATCH: tl.constexpr,
):  # fmt: skip
    """:func:`winding_near_kernel`'s walk with lanes refilled as in :func:`nearest_refill_kernel`."""
    pid = tl.program_id(0)
    lane = tl.arange(0, LANES)
    stack_base = stack_ptr + pid * (STACK * LANES) + lane
    begin = pid * per_program
    end = tl.minimum(begin + per_program, n_points)
    following = begin
    p = tl.zeros((LANES,), tl.int32)
    px = tl.zeros((LANES,), tl.float32)
    py = tl.zeros((LANES,), tl.float32)
    pz = tl.zeros((LANES,), tl.float32)
    total = tl.zeros((LANES,), tl.float32)
    node = tl.zeros((LANES,), tl.int32)
    size = tl.zeros((LANES,), tl.int32)
    active = tl.zeros((LANES,), tl.int1)
    go = (following < end).to(tl.int32)
    while go > 0:
        idle = (active == 0).to(tl.int32)
        free = tl.sum(idle, axis=0)
        if (free > 0) & (following < end):
            q = following + tl.cumsum(idle, 0) - 1
            take = (idle != 0) & (q < end)
            qx, qy, qz = _load_points(points_ptr, q, take)
            walk = take & _finite(qx, qy, qz)
            tl.store(out_ptr + q, tl.full((LANES,), float("nan"), tl.float32), mask=take & (walk == 0))
            p = tl.where(take, q, p)
            px = tl.where(take, qx, px)
            py = tl.where(take, qy, py)
            pz = tl.where(take, qz, pz)
            total = tl.where(take, 0.0, total)
            node = tl.where(take, 0, node)
            size = tl.where(take, 0, size)
            active = active | walk
            following += free
        walking = active
        node, size, total, active, votes = _winding_near_step(
            nodes_ptr, tri_ptr, box_ptr, flag_ptr, geometry_ptr, dip_ptr, stack_base, node, size, total, active,
            px, py, pz, STACK, LANES, BOXES, VECTOR, BATCH,
        )  # fmt: skip
        tl.store(out_ptr + p, total, mask=walking & (active == 0))
        go = (votes & 4) | (following < end).to(tl.int32)


@triton.jit
def winding_stackless_kernel(
    points_ptr, nodes_ptr, tri_ptr, box_ptr, flag_ptr, geometry_ptr, dip_ptr, parent_ptr, n_points, n_programs,
    out_ptr, LANES: tl.constexpr, BOXES: tl.constexpr, VECTOR: tl.constexpr, BATCH: tl.constexpr,
):  # fmt: skip
    """:func:`winding_near_kernel`'s order without a stack (as :func:`nearest_stackless_kernel`): down, a node's
    terms are added and child 1 entered where opened, else child 0, else the walk turns up; up from child 1,
    child 0 is entered where opened (the same test again), else the walk goes up again."""
    pid = tl.program_id(0)
    lane = tl.arange(0, LANES)
    block = pid
    while block * LANES < n_points:
        p = block * LANES + lane
        live = p < n_points
        px, py, pz = _load_points(points_ptr, p, live)
        start = live & _finite(px, py, pz)
        active = start
        total = tl.zeros((LANES,), tl.float32)
        node = tl.zeros((LANES,), tl.int32)
        parent = tl.full((LANES,), -1, tl.int32)
        up = tl.zeros((LANES,), tl.int1)
        go = tl.max(active.to(tl.int32), axis=0)
        while go > 0:
            down = active & (up == 0)
            rising = active & up
            row = tl.where(up, parent, node)
            c0, c1 = _children(nodes_ptr, row, active, LANES, VECTOR)
            grand = tl.load(parent_ptr + row, mask=rising, other=-1)
            t0, t1, open0, open1, votes = _node_terms(
                tri_ptr, box_ptr, flag_ptr, geometry_ptr, dip_ptr, row, c0, c1, down, active, px, py, pz, BOXES,
                LANES, VECTOR, BATCH,
            )  # fmt: skip
            go = votes & 4
            total = total + t0
            total = total + t1
            enter1 = down & open1
            enter0 = (down & (open1 == 0) & open0) | (rising & (node == c1) & open0)
            enter = enter0 | enter1
            parent = tl.where(enter, row, tl.where(rising, grand, parent))
            node = tl.where(enter1, c1, tl.where(enter0, c0, tl.where(rising, row, node)))
            up = (up | down) & (enter == 0)
            active = active & ((up & (parent < 0)) == 0)
        tl.store(out_ptr + p, tl.where(start, total, float("nan")), mask=live)
        block += n_programs


@dataclasses.dataclass(frozen=True)
class Variant:
    """Static choices of the point kernels (module docstring, "Variants"). Every variant picks the same leaf
    and sums the fast winding number in the same order.

    Attributes:
      walk: ``"stack"`` (pop every node), ``"near"`` (enter the nearer child, push only the farther one),
        ``"refill"`` (``near`` with lanes refilled from the program's points as their walks end) or
        ``"stackless"`` (parent pointers, no scratch memory).
      vector_loads: read node and triangle rows, and stack entries, with 16- and 8-byte loads (``near`` and
        ``stackless``).
      leaf_batch: one leaf test for each lane's first leaf child, a second only for lanes with two.
      skip: ``near``: a pop takes entries until one within the radius, in a loop of its own.
      programs: most programs of a launch (their blocks strided); ``None``: :data:`MAX_PROGRAMS`; 0: one per
        block of lanes.
      lanes: points per program (one warp: 64 gives each thread two points).
    """

    walk: str = "stack"
    vector_loads: bool = False
    leaf_batch: bool = False
    skip: bool = False
    programs: int | None = None
    lanes: int = LANES


#: The named variants (``JAXRT_POINT_VARIANT`` picks the default; ``python -m jaxrt.bench.points --variants``).
VARIANTS = {
    "stack": Variant(),
    "near": Variant("near", vector_loads=True, leaf_batch=True, skip=True),
    "near-scalar": Variant("near", leaf_batch=True, skip=True),
    "near-plain": Variant("near"),
    "near-noskip": Variant("near", vector_loads=True, leaf_batch=True),
    "near-32k": Variant("near", vector_loads=True, leaf_batch=True, skip=True, programs=1 << 15),
    "near-64": Variant("near", vector_loads=True, leaf_batch=True, skip=True, lanes=64),
    "refill": Variant("refill", vector_loads=True, leaf_batch=True, skip=True),
    "refill-scalar": Variant("refill", leaf_batch=True, skip=True),
    "refill-4k": Variant("refill", vector_loads=True, leaf_batch=True, skip=True, programs=1 << 12),
    "stackless": Variant("stackless", vector_loads=True, leaf_batch=True, programs=0),
    "stackless-scalar": Variant("stackless", leaf_batch=True, programs=0),
    "stackless-8k": Variant("stackless", vector_loads=True, leaf_batch=True),
}
#: The variant the point queries use (read at import from ``JAXRT_POINT_VARIANT``; set it, then clear JAX's
#: caches, to change it in a running process).
VARIANT = os.environ.get("JAXRT_POINT_VARIANT", "near")


def variant(name: str | None = None) -> Variant:
    """The variant called ``name`` (default: :data:`VARIANT`); ``ValueError`` for an unknown name."""
    name = VARIANT if name is None else name
    if name not in VARIANTS:
        raise ValueError(f"unknown point kernel variant {name!r}; known: {', '.join(VARIANTS)}")
    return VARIANTS[name]


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


def _programs(n: int, lanes: int = LANES, cap: int | None = None) -> int:
    blocks = -(-n // lanes)
    cap = MAX_PROGRAMS if cap is None else cap
    return max(1, min(cap, blocks) if cap > 0 else blocks)


def _stack(triangles) -> int:
    return tree_depth_bound(triangles.shape[0]) + 1


def _flags(v: Variant) -> dict:
    return dict(VECTOR=v.vector_loads, BATCH=v.leaf_batch)


@functools.cache
def _nearest_call(v: Variant):
    """The nearest-leaf launch of variant ``v`` (walked one vmapped structure at a time)."""

    @jax.custom_batching.sequential_vmap
    def call(points, nodes, triangles, boxes, flags, limit2, parent):
        n = points.shape[0]
        programs, stack = _programs(n, v.lanes, v.programs), _stack(triangles)
        out = jax.ShapeDtypeStruct((n,), jnp.int32)
        params = dict(LANES=v.lanes, BOXES=boxes.shape[0] == triangles.shape[0])
        args = (points, nodes, triangles, boxes, flags, limit2)
        if v.walk == "stack":
            scratch = programs * stack * v.lanes
            shapes = (out, jax.ShapeDtypeStruct((scratch,), jnp.int32), jax.ShapeDtypeStruct((scratch,), jnp.float32))
            return _launch("nearest_kernel", programs, (*args, n, programs), shapes, dict(params, STACK=stack))[0]
        if v.walk in ("near", "refill"):
            shapes = (out, jax.ShapeDtypeStruct((programs * stack * v.lanes * 2,), jnp.int32))
            params = dict(params, STACK=stack, SKIP=v.skip, **_flags(v))
            kernel, step = ("nearest_near_kernel", programs) if v.walk == "near" else ("nearest_refill_kernel", -(-n // programs))  # fmt: skip
            return _launch(kernel, programs, (*args, n, step), shapes, params)[0]
        params = dict(params, **_flags(v))
        return _launch("nearest_stackless_kernel", programs, (*args, parent, n, programs), (out,), params)[0]

    return call


@functools.cache
def _fast_call(v: Variant):
    """The fast winding launch of variant ``v``."""

    @jax.custom_batching.sequential_vmap
    def call(points, nodes, triangles, boxes, flags, geometry, normal, center, reach2, parent):
        n = points.shape[0]
        programs, stack = _programs(n, v.lanes, v.programs), _stack(triangles)
        out = jax.ShapeDtypeStruct((n,), jnp.float32)
        params = dict(LANES=v.lanes, BOXES=boxes.shape[0] == triangles.shape[0])
        if v.walk == "stack":
            shapes = (out, jax.ShapeDtypeStruct((programs * stack * v.lanes,), jnp.int32))
            args = (points, nodes, triangles, boxes, flags, geometry, normal, center, reach2, n, programs)
            return _launch("winding_kernel", programs, args, shapes, dict(params, STACK=stack))[0]
        rows = _dipole_rows(normal, center, reach2)
        args = (points, nodes, triangles, boxes, flags, geometry, rows)
        if v.walk in ("near", "refill"):
            shapes = (out, jax.ShapeDtypeStruct((programs * stack * v.lanes,), jnp.int32))
            params = dict(params, STACK=stack, **_flags(v))
            kernel, step = ("winding_near_kernel", programs) if v.walk == "near" else ("winding_refill_kernel", -(-n // programs))  # fmt: skip
            return _launch(kernel, programs, (*args, n, step), shapes, params)[0]
        params = dict(params, **_flags(v))
        return _launch("winding_stackless_kernel", programs, (*args, parent, n, programs), (out,), params)[0]

    return call


def _dipole_rows(normal, center, reach2) -> jax.Array:
    """``(M, 16)`` float32 rows, one per node: each child's dipole centre and squared reach (columns 0-3 and
    4-7), then each child's normal sum and a zero (8-11 and 12-15)."""
    m = reach2.shape[0]
    zero = jnp.zeros((m, 1), jnp.float32)
    return jnp.concatenate(
        [center[:, 0], reach2[:, :1], center[:, 1], reach2[:, 1:], normal[:, 0], zero, normal[:, 1], zero], axis=-1
    )


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


def _parents(structure, v: Variant) -> jax.Array:
    """Each node's parent (-1 for the root) for the stackless walk; a placeholder for the others."""
    if v.walk != "stackless":
        return jnp.zeros((1,), jnp.int32)
    return parent_nodes(jax.lax.stop_gradient(structure.node_children).astype(jnp.int32))


def nearest(points, structure, boxes, box_leaf, limit2, variant_name: str | None = None) -> jax.Array:
    """The nearest leaf to each point ``(n, 3)`` within squared distance ``limit2`` (-1: none), by the kernel of
    variant ``variant_name`` (default: :data:`VARIANT`)."""
    v = variant(variant_name)
    rows = _rows(structure)
    p, b, limit = _f32(points, boxes, jnp.reshape(limit2, (1,)))
    (flags,) = _i32(box_leaf)
    return _nearest_call(v)(p, rows.nodes, rows.triangles, b, flags, limit, _parents(structure, v))


def fast_winding(points, structure, boxes, box_leaf, dipoles, variant_name: str | None = None) -> jax.Array:
    """The fast winding number of each point ``(n, 3)`` (:func:`jaxrt._src.winding._dipoles`' subtrees), by the
    kernel of variant ``variant_name`` (default: :data:`VARIANT`)."""
    v = variant(variant_name)
    rows = _rows(structure)
    p, b, normal, center, reach2 = _f32(points, boxes, dipoles.normal, dipoles.center, dipoles.reach2)
    flags, geometry = _i32(box_leaf, structure.leaf_geometry)
    parent = _parents(structure, v)
    return _fast_call(v)(p, rows.nodes, rows.triangles, b, flags, geometry, normal, center, reach2, parent)


def exact_winding(points, structure, boxes, box_leaf) -> jax.Array:
    """The exact winding number of each point ``(n, 3)``."""
    rows = _rows(structure)
    p, b = _f32(points, boxes)
    flags, geometry = _i32(box_leaf, structure.leaf_geometry)
    return _exact(p, rows.triangles, b, flags, geometry)
