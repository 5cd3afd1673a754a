"""Packed arrays read by the GPU traversal kernel, derived from a structure and a ray batch.

The kernel reads one node with four 16-byte loads and one triangle with three, so the structure's arrays are
repacked into rows of float32 quads (children bit-cast to float32), 112 bytes per leaf slot. Structures built
where the kernel runs hold these node and triangle rows (:class:`KernelLayout`, packed at build time and
kept consistent by refit, compaction and loading); for other structures (and instanced scenes) the kernel
call packs them per call. The ray block is packed in every call, except where the kernel reads the caller's
ray arrays itself (``KernelOptions.fused_rays``: a primitive structure whose rays need only the 16 basic rows).

Node row, ``(C-1, 16)`` float32, one per internal node (both child boxes in the parent, as in Aila & Laine,
"Understanding the Efficiency of Ray Traversal on GPUs", HPG 2009):

=======  ==========================================================
columns  contents
=======  ==========================================================
0-3      ``lower0.x, upper0.x, lower1.x, upper1.x``
4-7      the same for y
8-11     the same for z
12-13    child 0 and child 1 (int32 bits: node ``c >= 0`` or leaf ``-1 - k``)
14-15    zero
=======  ==========================================================

Wide node row, ``(W, 32)`` float32, for the 4-wide kernel (:func:`pack_wide_nodes`): four child slots, each a
box and a reference, so that one 128-byte row gives the four boxes a step tests:

=======  ==========================================================
columns  contents
=======  ==========================================================
0-3      ``lower.x`` of slots 0-3
4-7      ``upper.x`` of slots 0-3
8-23     the same for y (8-15) and z (16-23)
24-27    slot references (int32 bits): wide node ``w >= 0``, or a leaf cluster ``-1 - (4 first + count - 1)``
         holding leaves ``first .. first + count - 1`` (at most 4); an unused slot has an empty box
28-31    zero
=======  ==========================================================

Triangle row, ``(C, 12)`` float32, one per leaf: ``v0.x, v1.x, v2.x, 0, v0.y, v1.y, v2.y, 0, v0.z, v1.z,
v2.z, 0``.

Analytic row, ``(C, 12)``, in place of the triangle row of a bounding-box leaf whose geometry uses a built-in
intersection function (:func:`pack_analytic`): ``p.x, p.y, p.z, code, q.x, q.y, q.z, radius, 0, 0, 0, 0``,
with ``code`` 1 for a sphere (``p`` its centre), 2 for a disk (``p`` its centre, ``q`` its normal) and 3 for a
capped cylinder (``p``, ``q`` the axis ends ``p0``, ``p1``). A triangle row has 0 in column 3.

Instance row, ``(G, 16)`` float32, one per instance of an instanced scene (read when a ray enters it):
the world-to-object transform row by row (columns 0-11), then as int32 bits the global root node of its
child (12), its facing in {-1, 0, +1} (13) and its mask (14, uint32 bits); column 15 is zero. A scene
without instances has one zero row (the kernel never reads it).

Ray block, ``(16, N)`` float32, one column per ray (rows are coalesced across the 32 rays of a program):
origin (rows 0-2), the safe reciprocal direction (3-5), the watertight shear ``Sx, Sy, Sz`` (6-8), ``t_min``
(9), the initial distance bound (10: ``t_max``, or ``-inf`` for a disabled ray, so that it never hits), the
sheared axes ``kx, ky, kz`` as small integers (11-13), and 1 for an enabled ray, else 0 (14). The extended
block, ``(20, N)``, for instanced scenes and batches of scenes, adds the ray mask (row 15, uint32 bits),
the ray's root node (16, int32 bits) and the direction (17-19), from which the kernel computes each
level's ray.

Keyframe motion adds, where the scene has it:

- node rows per keyframe, ``(M K, 16)``: row ``i K + k`` is :func:`pack_nodes`'s row of node ``i`` with
  keyframe ``k``'s child boxes (node-major, so that the two keyframes a ray blends are adjacent);
- triangle rows per keyframe, ``(P K, 12)``: row ``j K + k`` is leaf ``j``'s triangle at keyframe ``k``, with
  column 3 set to 1 where the leaf's geometry moves (it vanishes outside the range on a "vanish" border);
- instance motion rows, ``(G, 4 + 12 K)``: the instance's start and end time, its keyframe count (int32 bits)
  and flags (int32 bits: 1 moving, 2 vanishes before the start, 4 after the end), then its ``K``
  object-to-world keyframe transforms row by row;
- ray block rows 20-23 (the extended block): the keyframe segment of the scene's primitive motion at the
  ray's time (int32 bits), its blend weight, 1 where moving leaves exist at that time (else 0), and the time.

Curves add, where the structure has curve leaves:

- curve rows, ``(C, 24)`` float32, 96 bytes per leaf (:func:`pack_curves`): the packed segment of
  :func:`jaxrt._src.curves.pack_segments` as the portable test starts from it: the four cubic Bezier control
  points ``x, y, z, radius`` relative to the base point (columns 0-15), the base point (16-18), the segment's
  flags (19, int32 bits: previous / next segment, end caps, ``IS_CURVE``; 0 for a triangle leaf) and the
  predecessor's derivative at the joint (20-23);
- ray block rows 24-33 (after the extended block, motion rows zero without motion): the ray's curve frame
  ``e1, e2, n`` row by row and ``1 / |d|`` (:func:`jaxrt._src.primitives.curve.curve_ray`).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from jaxrt._src.bvh.ploc import parent_nodes, path_sums
from jaxrt._src.numerics import safe_reciprocal
from jaxrt._src.primitives import triangle

__all__ = [
    "NODE_WIDTH",
    "WIDE_NODE_WIDTH",
    "TRIANGLE_WIDTH",
    "RAY_ROWS",
    "pack_nodes",
    "unpack_nodes",
    "pack_wide_nodes",
    "wide_node_capacity",
    "wide_stack_size",
    "pack_triangles",
    "pack_instances",
    "pack_rays",
    "pack_node_keys",
    "pack_triangle_keys",
    "pack_instance_motion",
    "pack_curves",
    "CURVE_WIDTH",
    "KernelLayout",
    "kernel_layout",
    "pack_analytic",
]

NODE_WIDTH = 16
WIDE_NODE_WIDTH = 32
#: Most leaves in one leaf cluster of the wide layout (the count is stored in two bits).
MAX_LEAF_SIZE = 4
TRIANGLE_WIDTH = 12
INSTANCE_WIDTH = 16
RAY_ROWS = 16
#: Rows of the extended ray block (ray mask, root node and direction added).
EXTENDED_RAY_ROWS = 20
#: Rows of the extended ray block with keyframe motion (keyframe segment, weight, visibility and time added).
MOTION_RAY_ROWS = 24
#: Columns of a curve row (:func:`pack_curves`).
CURVE_WIDTH = 24
#: Rows of the ray block with curves (the curve frame and ``1 / |d|`` added after the motion rows).
CURVE_RAY_ROWS = 34


def pack_nodes(node_lower: jax.Array, node_upper: jax.Array, node_children: jax.Array) -> jax.Array:
    """The ``(C-1, 16)`` float32 node rows (layout in the module docstring)."""
    m = node_lower.shape[0]
    lower = node_lower.astype(jnp.float32)
    upper = node_upper.astype(jnp.float32)
    # (m, axis, [lower0, upper0, lower1, upper1])
    boxes = jnp.stack([lower[:, 0], upper[:, 0], lower[:, 1], upper[:, 1]], axis=-1)
    children = lax.bitcast_convert_type(node_children.astype(jnp.int32), jnp.float32)
    tail = jnp.concatenate([children, jnp.zeros((m, 2), jnp.float32)], axis=-1)
    return jnp.concatenate([boxes.reshape(m, 12), tail], axis=-1)


def unpack_nodes(packed: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Inverse of :func:`pack_nodes`: ``(node_lower, node_upper, node_children)``."""
    m = packed.shape[0]
    boxes = packed[:, :12].reshape(m, 3, 4)
    lower = jnp.stack([boxes[:, :, 0], boxes[:, :, 2]], axis=1)
    upper = jnp.stack([boxes[:, :, 1], boxes[:, :, 3]], axis=1)
    children = lax.bitcast_convert_type(packed[:, 12:14], jnp.int32)
    return lower, upper, children


def wide_node_capacity(capacity: int) -> int:
    """Rows of :func:`pack_wide_nodes` for a structure of ``capacity`` leaves.

    A wide node other than the root hangs below an opened binary node, which has at most two wide children,
    and the two kinds are disjoint sets of internal nodes, so ``W <= 1 + 2 (C - 1 - W)``: ``W <= (2C - 1) / 3``.
    """
    return max(1, (2 * capacity - 1) // 3 + 1)


def wide_stack_size(max_depth: int) -> int:
    """Stack entries the 4-wide traversal can need: three pushes per wide level, one wide level per two
    binary levels of a tree at most ``max_depth`` deep."""
    return 3 * ((max_depth + 1) // 2)


def pack_wide_nodes(
    node_lower: jax.Array,
    node_upper: jax.Array,
    node_children: jax.Array,
    node_range: jax.Array,
    leaf_size: int = MAX_LEAF_SIZE,
) -> jax.Array:
    """The ``(W, 32)`` float32 rows of a 4-wide tree collapsed from the binary tree (layout in the docstring).

    Every binary node whose subtree holds at most ``leaf_size`` leaves (other than the root) becomes a leaf
    cluster, a contiguous leaf range (every node covers one, see :mod:`jaxrt._src.structures`). The remaining
    nodes at even depth (the root's is 0) become the wide nodes; each takes its children's slots, opening every
    child that is neither a leaf nor a cluster into that child's two children (the collapse of Wald et al.,
    "Getting Rid of Packets", RT 2008, one level at a time). Wide nodes keep the binary nodes' relative order.
    """
    if not 1 <= leaf_size <= MAX_LEAF_SIZE:
        raise ValueError(f"pack_wide_nodes: leaf_size must be in 1..{MAX_LEAF_SIZE}, got {leaf_size}")
    m = node_children.shape[0]
    rows = wide_node_capacity(m + 1)
    children = node_children.astype(jnp.int32)
    node = jnp.arange(m, dtype=jnp.int32)
    internal = children >= 0
    safe = jnp.maximum(children, 0)
    (levels,) = path_sums(parent_nodes(children), jnp.ones((m,), jnp.int32))  # depth + 1
    size = node_range[:, 1] - node_range[:, 0] + 1
    small = (size <= leaf_size) & (node > 0)
    wide = (levels % 2 == 1) & ~small
    wide_index = jnp.cumsum(wide.astype(jnp.int32)) - 1

    def reference(code: jax.Array) -> jax.Array:
        """A child code of the binary tree as a slot reference of the wide tree."""
        c = jnp.maximum(code, 0)
        cluster = -1 - (node_range[c, 0] * 4 + size[c] - 1)
        leaf = -1 - (-1 - code) * 4
        return jnp.where(code < 0, leaf, jnp.where(small[c], cluster, wide_index[c]))

    opened = internal & ~small[safe]  # (m, 2): the child's own children take its two slots
    grand = children[safe]  # (m, 2, 2)
    lower = node_lower.astype(jnp.float32)
    upper = node_upper.astype(jnp.float32)
    empty_lower = jnp.full((m, 3), jnp.inf, jnp.float32)
    empty_upper = jnp.full((m, 3), -jnp.inf, jnp.float32)
    slot_lower, slot_upper, slot_ref = [], [], []
    for k in range(2):
        o = opened[:, k]
        for j in range(2):
            own_lower = lower[:, k] if j == 0 else empty_lower
            own_upper = upper[:, k] if j == 0 else empty_upper
            own_ref = reference(children[:, k]) if j == 0 else jnp.zeros((m,), jnp.int32)
            slot_lower.append(jnp.where(o[:, None], lower[safe[:, k], j], own_lower))
            slot_upper.append(jnp.where(o[:, None], upper[safe[:, k], j], own_upper))
            slot_ref.append(jnp.where(o, reference(grand[:, k, j]), own_ref))
    slot_lower = jnp.stack(slot_lower, axis=-1)  # (m, axis, slot)
    slot_upper = jnp.stack(slot_upper, axis=-1)
    boxes = jnp.stack([slot_lower, slot_upper], axis=2).reshape(m, 24)  # per axis: lower x4, upper x4
    refs = lax.bitcast_convert_type(jnp.stack(slot_ref, axis=-1), jnp.float32)
    packed_rows = jnp.concatenate([boxes, refs, jnp.zeros((m, 4), jnp.float32)], axis=-1)
    target = jnp.where(wide, wide_index, rows)
    return jnp.zeros((rows, WIDE_NODE_WIDTH), jnp.float32).at[target].set(packed_rows, mode="drop")


def pack_triangles(leaf_triangle: jax.Array) -> jax.Array:
    """The ``(C, 12)`` float32 triangle rows: per axis, the three vertices' coordinates and a zero."""
    c = leaf_triangle.shape[0]
    per_axis = jnp.swapaxes(leaf_triangle.astype(jnp.float32), 1, 2)  # (C, axis, vertex)
    return jnp.pad(per_axis, ((0, 0), (0, 0), (0, 1))).reshape(c, TRIANGLE_WIDTH)


def pack_instances(world_to_object: jax.Array, child_root: jax.Array, facing: jax.Array, mask: jax.Array) -> jax.Array:
    """The ``(max(G, 1), 16)`` float32 instance rows (layout in the module docstring)."""
    g = child_root.shape[0]
    ints = jnp.stack(
        [
            child_root.astype(jnp.int32),
            facing.astype(jnp.int32),
            lax.bitcast_convert_type(mask.astype(jnp.uint32), jnp.int32),
        ],
        axis=-1,
    )
    rows = jnp.concatenate(
        [
            world_to_object.astype(jnp.float32).reshape(g, 12),
            lax.bitcast_convert_type(ints, jnp.float32),
            jnp.zeros((g, 1), jnp.float32),
        ],
        axis=-1,
    )
    return rows if g else jnp.zeros((1, INSTANCE_WIDTH), jnp.float32)


def pack_node_keys(lower_keys: jax.Array, upper_keys: jax.Array, node_children: jax.Array) -> jax.Array:
    """The ``(M K, 16)`` node rows per keyframe from node-major keyframe boxes ``(M, K, 2, 3)``."""
    m, k = lower_keys.shape[:2]
    rows = jax.vmap(pack_nodes, in_axes=(1, 1, None), out_axes=1)(lower_keys, upper_keys, node_children)
    return rows.reshape(m * k, NODE_WIDTH)


def pack_triangle_keys(leaf_keys: jax.Array, moving: jax.Array) -> jax.Array:
    """The ``(P K, 12)`` triangle rows per keyframe from leaf-major keyframe triangles ``(P, K, 3, 3)``, with
    column 3 the leaf's moving flag."""
    p, k = leaf_keys.shape[:2]
    rows = pack_triangles(leaf_keys.reshape(p * k, 3, 3)).reshape(p, k, TRIANGLE_WIDTH)
    rows = rows.at[:, :, 3].set(jnp.broadcast_to(moving.astype(jnp.float32)[:, None], (p, k)))
    return rows.reshape(p * k, TRIANGLE_WIDTH)


def pack_instance_motion(
    keys: jax.Array,
    count: jax.Array,
    start: jax.Array,
    end: jax.Array,
    vanish_start: jax.Array,
    vanish_end: jax.Array,
    moving: jax.Array,
) -> jax.Array:
    """The ``(G, 4 + 12 K)`` instance motion rows (layout in the module docstring)."""
    g, k = keys.shape[:2]
    flags = moving.astype(jnp.int32) | (vanish_start.astype(jnp.int32) << 1) | (vanish_end.astype(jnp.int32) << 2)
    bits = lax.bitcast_convert_type(jnp.stack([count.astype(jnp.int32), flags], axis=-1), jnp.float32)
    times = jnp.stack([start, end], axis=-1).astype(jnp.float32)
    return jnp.concatenate([times, bits, keys.astype(jnp.float32).reshape(g, 12 * k)], axis=-1)


def pack_curves(leaf_curve: jax.Array, leaf_flags: jax.Array) -> jax.Array:
    """The ``(C, 24)`` float32 curve rows of packed segments ``(C, 6, 4)`` and their flags ``(C,)`` (layout in
    the module docstring)."""
    c = leaf_curve.shape[0]
    segment = leaf_curve.astype(jnp.float32)
    flags = lax.bitcast_convert_type(leaf_flags.astype(jnp.int32), jnp.float32)[:, None]
    return jnp.concatenate([segment[:, :4].reshape(c, 16), segment[:, 4, :3], flags, segment[:, 5]], axis=-1)


def pack_rays(
    origin: jax.Array,
    direction: jax.Array,
    t_min: jax.Array,
    t_max: jax.Array,
    enabled: jax.Array,
    size: int,
    *,
    mask: jax.Array | None = None,
    root: jax.Array | None = None,
    motion: tuple[jax.Array, jax.Array, jax.Array, jax.Array] | None = None,
    curve_frame: jax.Array | None = None,
    cursor: tuple[jax.Array, jax.Array] | None = None,
) -> jax.Array:
    """The ``(16, size)`` float32 ray block, or the extended ``(20, size)`` one when ``mask`` and ``root`` are
    given, or the ``(24, size)`` one when ``motion`` (keyframe segment, weight, visibility and time per ray)
    is given too, or the ``(34, size)`` one when ``curve_frame`` (``(N, 10)``: the curve frame row by row and
    ``1 / |d|``) is given too (zeros where ``cursor`` is given without it), or the ``(36, size)`` one when
    ``cursor`` (each ray's cursor distance and leaf, for candidate waves) is given too; columns past the ray
    count are disabled rays.

    The per-ray constants are computed here with the same functions as the portable traversal, so both
    paths start from bit-identical values.
    """
    n = origin.shape[0]
    inv_direction = jax.vmap(safe_reciprocal)(direction)
    sheared = jax.vmap(triangle.shear_ray)(origin, direction)
    axes = jnp.stack([sheared.kx, sheared.ky, sheared.kz], axis=-1).astype(jnp.float32)
    bound = jnp.where(enabled, t_max, -jnp.inf)
    if mask is None or root is None:
        extra = [jnp.zeros((n, 1), jnp.float32)]
    else:
        bits = jnp.stack([lax.bitcast_convert_type(mask.astype(jnp.uint32), jnp.int32), root.astype(jnp.int32)], -1)
        extra = [lax.bitcast_convert_type(bits, jnp.float32), direction.astype(jnp.float32)]
        if motion is not None:
            index, weight, visible, time = motion
            extra += [
                lax.bitcast_convert_type(index.astype(jnp.int32), jnp.float32)[:, None],
                weight.astype(jnp.float32)[:, None],
                visible.astype(jnp.float32)[:, None],
                time.astype(jnp.float32)[:, None],
            ]
            if curve_frame is not None:
                extra.append(curve_frame.astype(jnp.float32))
            elif cursor is not None:
                extra.append(jnp.zeros((n, 10), jnp.float32))
            if cursor is not None:
                cursor_t, cursor_leaf = cursor
                extra += [
                    cursor_t.astype(jnp.float32)[:, None],
                    lax.bitcast_convert_type(cursor_leaf.astype(jnp.int32), jnp.float32)[:, None],
                ]
    columns = jnp.concatenate(
        [
            origin.astype(jnp.float32),
            inv_direction.astype(jnp.float32),
            sheared.shear.astype(jnp.float32),
            t_min[:, None].astype(jnp.float32),
            bound[:, None].astype(jnp.float32),
            axes,
            enabled[:, None].astype(jnp.float32),
            *extra,
        ],
        axis=-1,
    )
    columns = jnp.pad(columns, ((0, size - n), (0, 0)))
    return columns.T


def pack_analytic(
    code: jax.Array, first: jax.Array, second: jax.Array, radius: jax.Array, dtype: Any = jnp.float32
) -> jax.Array:
    """The ``(C, 12)`` analytic rows (layout in the module docstring; float32 for the GPU kernel, the scene's
    dtype for the CPU traversal) from each leaf's shape ``code`` ``(C,)`` (0: not analytic), ``first`` and
    ``second`` ``(C, 3)`` and ``radius`` ``(C,)``."""
    c = code.shape[0]
    return jnp.concatenate(
        [
            first.astype(dtype),
            code.astype(dtype)[:, None],
            second.astype(dtype),
            radius.astype(dtype)[:, None],
            jnp.zeros((c, 4), dtype),
        ],
        axis=-1,
    )


class KernelLayout(NamedTuple):
    """The rows the binary kernel reads of a primitive structure, packed once where the structure is made
    (``PrimitiveAccelerationStructure.kernel_layout``) instead of in every traced call."""

    nodes: jax.Array  # (C-1, 16) float32: pack_nodes
    triangles: jax.Array  # (C, 12) float32: pack_triangles


def kernel_layout(
    node_lower: jax.Array, node_upper: jax.Array, node_children: jax.Array, leaf_triangle: jax.Array
) -> KernelLayout:
    """:func:`pack_nodes` and :func:`pack_triangles` of a primitive structure's arrays (detached: the kernel
    only picks the leaf)."""
    return KernelLayout(
        lax.stop_gradient(pack_nodes(node_lower, node_upper, node_children)),
        lax.stop_gradient(pack_triangles(leaf_triangle)),
    )
