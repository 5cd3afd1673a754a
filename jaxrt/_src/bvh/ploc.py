"""Higher-quality BVH build: agglomerative clustering of the Morton-ordered primitives (PLOC).

Reference: Meister & Bittner, "Parallel Locally-Ordered Clustering for Bounding Volume Hierarchy
Construction", IEEE TVCG 24(3), 2018.

Every primitive starts as a cluster, in Morton order. Each iteration, every cluster finds its nearest neighbour
among the ``RADIUS`` clusters on each side of it in that order, the distance being the surface area of the box
that holds both; clusters that are each other's nearest neighbour merge into a new node, and the surviving
clusters are compacted (still in Morton order). The tree grows bottom-up, pairing whatever is spatially
closest, so its SAH cost is lower than the radix tree's, whose splits fall where Morton bits change.

Progress: ties are broken by a total order on pairs (area, then lower position, then upper position), so the
pair that is least in that order is always mutual and at least one pair merges per iteration. The loop is
staged: once an eighth of the clusters remain, the arrays are cut to that size, so the work is a small multiple
of one pass over the primitives.

The finished tree is laid out as the radix tree is (see :mod:`jaxrt._src.structures`): internal nodes in
depth-first order with the root at 0 and the leaves renumbered in the same order, so that every node covers a
contiguous range of leaves (what refit and the traversals read). Padding leaves hang under the root in a
subtree of their own (the LBVH leaves them unlinked). Positions in both orders are found with pointer jumping
(Wyllie's list ranking applied to root paths), ``O(n log depth)`` work.

The clustering tree has no depth bound by construction; where it is deeper than the structure's stack bound
(``PrimitiveAccelerationStructure.max_depth``) the radix tree is kept instead, so traversal stacks still
cannot overflow.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

from jaxrt._src.bvh.radix_tree import build_radix_tree
from jaxrt._src.bvh.sweep_sah import sweep_sah_tree

__all__ = ["RADIUS", "cluster_tree", "restructure", "path_sums", "parent_nodes"]

#: Neighbours searched on each side of a cluster (Meister & Bittner's ``r``).
RADIUS = 16
#: Clusters are compacted into arrays an eighth the size once that few remain ...
_SHRINK = 8
#: ... down to this size, where one loop finishes the tree.
_FINAL = 512


def _area(lower: jax.Array, upper: jax.Array) -> jax.Array:
    """Surface area of boxes ``(..., 3)``; NaN (from non-finite corners) counts as infinitely large."""
    d = jnp.maximum(upper - lower, 0.0)
    area = 2.0 * (d[..., 0] * d[..., 1] + d[..., 1] * d[..., 2] + d[..., 2] * d[..., 0])
    return jnp.where(jnp.isnan(area), jnp.inf, area)


def _nearest(lower: jax.Array, upper: jax.Array, live: jax.Array, radius: int) -> jax.Array:
    """Each live cluster's nearest neighbour within ``radius`` positions (-1 for dead clusters).

    Candidates are visited in increasing (lower position, upper position) order of the pair they form
    (offsets ``-radius..-1``, then ``1..radius``), and a later candidate wins only with a strictly smaller
    area, which realises the total order on pairs. Both clusters of a pair compute the same union box, so
    they see the same area.
    """
    size = lower.shape[0]
    index = jnp.arange(size, dtype=jnp.int32)
    count = jnp.sum(live, dtype=jnp.int32)

    def candidate(k, best):
        best_area, best_index = best
        offset = jnp.where(k < radius, k - radius, k - radius + 1)
        other = index + offset
        area = _area(
            jnp.minimum(lower, jnp.roll(lower, -offset, axis=0)), jnp.maximum(upper, jnp.roll(upper, -offset, axis=0))
        )
        take = live & (other >= 0) & (other < count) & ((area < best_area) | (best_index < 0))
        return jnp.where(take, area, best_area), jnp.where(take, other, best_index)

    best = (jnp.full((size,), jnp.inf, lower.dtype), jnp.full((size,), -1, jnp.int32))
    return lax.fori_loop(0, 2 * radius, candidate, best)[1]


def _merge_step(radius: int, state: tuple) -> tuple:
    """One clustering iteration: mutual nearest neighbours merge, survivors are compacted in order."""
    lower, upper, node, leaves, count, made, children, subtree = state
    size = lower.shape[0]
    index = jnp.arange(size, dtype=jnp.int32)
    live = index < count
    partner = _nearest(lower, upper, live, radius)
    p = jnp.maximum(partner, 0)
    mutual = live & (partner >= 0) & (partner[p] == index)
    first = mutual & (index < partner)
    second = mutual & (index > partner)
    rank = jnp.cumsum(first, dtype=jnp.int32) - first.astype(jnp.int32)
    new = made + rank  # build-order index of the node made by this pair
    merged_leaves = leaves + leaves[p]
    slot = jnp.where(first, new, children.shape[0])  # out of range: dropped
    children = children.at[slot].set(jnp.stack([node, node[p]], axis=-1), mode="drop")
    subtree = subtree.at[slot].set(merged_leaves, mode="drop")
    lower = jnp.where(first[:, None], jnp.minimum(lower, lower[p]), lower)
    upper = jnp.where(first[:, None], jnp.maximum(upper, upper[p]), upper)
    node = jnp.where(first, new, node)
    leaves = jnp.where(first, merged_leaves, leaves)
    keep = live & ~second
    target = jnp.where(keep, jnp.cumsum(keep, dtype=jnp.int32) - 1, size)

    def compact(a):
        return jnp.zeros_like(a).at[target].set(a, mode="drop")

    made = made + jnp.sum(first, dtype=jnp.int32)
    count = jnp.sum(keep, dtype=jnp.int32)
    return compact(lower), compact(upper), compact(node), compact(leaves), count, made, children, subtree


def _stage_sizes(n: int) -> list[int]:
    sizes = [n]
    while sizes[-1] > _FINAL:
        sizes.append(-(-sizes[-1] // _SHRINK))
    return sizes


def cluster_tree(lower: jax.Array, upper: jax.Array, radius: int = RADIUS) -> tuple[jax.Array, jax.Array]:
    """Agglomerative clustering of ``n >= 2`` boxes given in Morton order.

    Args:
      lower, upper: ``(n, 3)`` boxes.
      radius: neighbours searched on each side.

    Returns:
      ``children`` ``(n-1, 2)`` int32 in build order (the root is ``n - 2``; an internal child is its build
      index, leaf ``k`` is ``-1 - k``) and ``subtree`` ``(n-1,)``, the number of leaves under each node.
    """
    n = lower.shape[0]
    state = (
        lower,
        upper,
        -1 - jnp.arange(n, dtype=jnp.int32),
        jnp.ones((n,), jnp.int32),
        jnp.int32(n),
        jnp.int32(0),
        jnp.zeros((n - 1, 2), jnp.int32),
        jnp.zeros((n - 1,), jnp.int32),
    )
    sizes = _stage_sizes(n)
    for k, size in enumerate(sizes):
        goal = sizes[k + 1] if k + 1 < len(sizes) else 1
        state = tuple(a[:size] for a in state[:4]) + state[4:]
        state = lax.while_loop(lambda s, goal=goal: s[4] > goal, lambda s: _merge_step(radius, s), state)
    return state[6], state[7]


def parent_nodes(children: jax.Array) -> jax.Array:
    """The parent of every internal node of the tree ``children`` ``(m, 2)`` (leaves ``< 0``); -1 for the root."""
    m = children.shape[0]
    pairs = jnp.broadcast_to(jnp.arange(m, dtype=jnp.int32)[:, None], (m, 2))
    return jnp.full((m,), -1, jnp.int32).at[jnp.where(children >= 0, children, m)].set(pairs, mode="drop")


def path_sums(parent: jax.Array, *values: jax.Array) -> tuple[jax.Array, ...]:
    """For every node, the sum of each of ``values`` over the node and all its ancestors (pointer jumping)."""

    def body(state):
        up, sums = state
        has = up >= 0
        u = jnp.maximum(up, 0)
        sums = tuple(s + jnp.where(has, s[u], 0) for s in sums)
        return jnp.where(has, up[u], -1), sums

    _, sums = lax.while_loop(lambda s: jnp.any(s[0] >= 0), body, (parent, values))
    return sums


def _depth_first_layout(children: jax.Array, subtree: jax.Array, offset: int):
    """Depth-first numbering of a build-order tree over ``n`` leaves (root ``n - 2``).

    Returns ``(children, node_range, order, depth)`` for the nodes numbered from ``offset`` and the leaves from
    0: ``order[position]`` is the original leaf at that depth-first position, ``depth`` the deepest internal
    node's depth (the root's is 1).
    """
    m = children.shape[0]
    n = m + 1
    build = jnp.arange(m, dtype=jnp.int32)
    internal = children >= 0
    pairs = jnp.broadcast_to(build[:, None], (m, 2))
    sides = jnp.broadcast_to(jnp.arange(2, dtype=jnp.int32), (m, 2))
    node_slot = jnp.where(internal, children, m)
    leaf_slot = jnp.where(internal, n, -1 - children)
    parent = parent_nodes(children)
    side = jnp.zeros((m,), jnp.int32).at[node_slot].set(sides, mode="drop")
    leaf_parent = jnp.zeros((n,), jnp.int32).at[leaf_slot].set(pairs, mode="drop")
    leaf_side = jnp.zeros((n,), jnp.int32).at[leaf_slot].set(sides, mode="drop")
    # Leaves under the left child of each node: the offset of the right child in both orders.
    left = children[:, 0]
    left_leaves = jnp.where(left < 0, 1, subtree[jnp.maximum(left, 0)])
    shift = jnp.where(side == 1, left_leaves[jnp.maximum(parent, 0)], 0)
    root = parent < 0
    preorder_step = jnp.where(root, 0, jnp.where(side == 1, shift, 1))
    preorder, first, depth = path_sums(parent, preorder_step, jnp.where(root, 0, shift), jnp.ones((m,), jnp.int32))
    leaf_position = first[leaf_parent] + jnp.where(leaf_side == 1, left_leaves[leaf_parent], 0)
    renamed = jnp.where(internal, preorder[jnp.maximum(children, 0)] + offset, -1 - leaf_position[-1 - children])
    out_children = jnp.zeros((m, 2), jnp.int32).at[preorder].set(renamed)
    node_range = jnp.zeros((m, 2), jnp.int32).at[preorder].set(jnp.stack([first, first + subtree - 1], axis=-1))
    order = jnp.zeros((n,), jnp.int32).at[leaf_position].set(jnp.arange(n, dtype=jnp.int32))
    return out_children, node_range, order, jnp.max(depth)


def _padding_tree(count: int, node_offset: int, leaf_offset: int) -> tuple[jax.Array, jax.Array]:
    """A balanced tree over ``count >= 2`` padding leaves, numbered from the given offsets."""
    children, first, last = build_radix_tree(jnp.zeros((count,), jnp.uint32))
    children = jnp.where(children >= 0, children + node_offset, children - leaf_offset)
    return children, jnp.stack([first, last], axis=-1) + leaf_offset


def _sweep_layout(lower: jax.Array, upper: jax.Array, offset: int, max_depth: int):
    """The full-sweep SAH tree (:mod:`jaxrt._src.bvh.sweep_sah`) as :func:`_depth_first_layout` returns trees."""
    valid = jnp.ones(lower.shape[:1], bool)
    children, node_range, order = sweep_sah_tree(lower, upper, valid, max_depth)
    children = jnp.where(children >= 0, children + offset, children)
    return children, node_range, order, jnp.int32(0)  # its depth is within max_depth by construction


def restructure(
    lower: jax.Array,
    upper: jax.Array,
    count: int,
    radix_children: jax.Array,
    radix_range: jax.Array,
    max_depth: int,
    method: str = "cluster",
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The clustering tree (or, with ``method="sweep"``, the full-sweep SAH tree) over the first ``count``
    leaves in the structure's node layout.

    Args:
      lower, upper: ``(C, 3)`` leaf boxes in Morton order; leaves ``count..C-1`` are padding.
      count: number of real leaves (static).
      radix_children, radix_range: the radix tree over the same leaves, kept where the clustering tree is
        deeper than ``max_depth``.
      max_depth: the deepest internal node the traversal stacks allow (the root's depth is 1).
      method: ``"cluster"`` (PLOC) or ``"sweep"`` (top-down SAH, built within the depth bound).

    Returns:
      ``(children, node_range, order)``: the node arrays, and ``order[k]``, the Morton position of the leaf
      that the tree puts at position ``k``.
    """
    capacity = lower.shape[0]
    padding = capacity - count
    lower, upper = lax.stop_gradient(lower), lax.stop_gradient(upper)
    offset = 1 if padding else 0  # with padding, node 0 joins the real tree and the padding tree
    if count >= 2 and method == "sweep":
        # Leaves within max_depth (one level less below the root that also holds the padding subtree).
        children, node_range, order, depth = _sweep_layout(lower[:count], upper[:count], offset, max_depth - offset)
        real_root = jnp.int32(offset)
    elif count >= 2:
        children, node_range, order, depth = _depth_first_layout(*cluster_tree(lower[:count], upper[:count]), offset)
        real_root = jnp.int32(offset)
    else:
        children = jnp.zeros((0, 2), jnp.int32)
        node_range = jnp.zeros((0, 2), jnp.int32)
        order = jnp.zeros((1,), jnp.int32)
        depth = jnp.int32(0)
        real_root = jnp.int32(-1)
    if padding:
        if padding >= 2:
            pad_children, pad_range = _padding_tree(padding, count, count)
            pad_root = jnp.int32(count)
        else:
            pad_children, pad_range = jnp.zeros((0, 2), jnp.int32), jnp.zeros((0, 2), jnp.int32)
            pad_root = jnp.int32(-1 - count)
        top = jnp.stack([real_root, pad_root])[None]
        children = jnp.concatenate([top, children, pad_children])
        node_range = jnp.concatenate([jnp.array([[0, capacity - 1]], jnp.int32), node_range, pad_range])
        order = jnp.concatenate([order, jnp.arange(count, capacity, dtype=jnp.int32)])
        depth = depth + 1
    ok = depth <= max_depth
    children = jnp.where(ok, children, radix_children)
    node_range = jnp.where(ok, node_range, radix_range)
    order = jnp.where(ok, order, jnp.arange(capacity, dtype=jnp.int32))
    return children, node_range, order
