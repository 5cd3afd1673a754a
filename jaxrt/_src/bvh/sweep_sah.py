"""Top-down full-sweep SAH build, one tree level per pass, for small primitive counts (instances).

Reference: Wald, "On fast Construction of SAH-based Bounding Volume Hierarchies", IEEE Symposium on
Interactive Ray Tracing 2007, section 3 (the sweep evaluation of every split position along each axis);
MacDonald & Booth 1990 for the cost.

Every node covers a contiguous range of leaf positions. The leaves are sorted by centroid along each axis
once; each of the three orders keeps every node's leaves contiguous and sorted. One pass splits every node of
a tree level at once: segmented prefix and suffix scans over each order give the box and the count of valid
leaves on each side of every split position, each node takes its cheapest split
``area(left) * count(left) + area(right) * count(right)`` over all positions and axes (ties: the split
nearest the middle, so coincident centroids and padding split evenly), and the two other orders are
partitioned stably by the side each leaf went to (a prefix count and a scatter, no sort: the presorted sweep
of Wald 2007, section 3.2). Invalid leaves (padding, instances that do not exist) sort to the end of every
node and count for nothing. The passes go on until every node is a single leaf, one primitive per leaf, so
the work is ``O(C)`` scans per tree level, the number of passes the tree's depth.

Depth bound: a split is allowed only if a median split of its larger side could still end within
``max_depth`` (``depth + 1 + ceil(log2(larger side)) <= max_depth``); the median split always is, so the
tree never exceeds the traversal's stack bound however skewed the primitives are.

Node numbering (the structure layout of :mod:`jaxrt._src.structures`, root at 0, depth first): an internal
node covering positions from ``first`` whose root path turns left ``k`` times has pre-order index
``first + k`` (the nodes before it in pre-order are its ancestors and every internal node of the subtrees
hanging to its left, which hold ``first`` leaves in as many subtrees as the path turns right).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

__all__ = ["sweep_sah_tree"]


def _area(lower: jax.Array, upper: jax.Array) -> jax.Array:
    d = jnp.maximum(upper - lower, 0.0)
    return 2.0 * (d[..., 0] * d[..., 1] + d[..., 1] * d[..., 2] + d[..., 2] * d[..., 0])


def _ceil_log2(x: jax.Array) -> jax.Array:
    """``ceil(log2(x))`` of int32 ``x >= 1``."""
    return 32 - lax.clz((x - 1).astype(jnp.uint32)).astype(jnp.int32)


def _segmented_boxes(start: jax.Array, lower: jax.Array, upper: jax.Array, reverse: bool):
    """Running union of boxes, restarting where ``start`` is set (scanning backwards with ``reverse``)."""

    def combine(a, b):
        fa, la, ua = a
        fb, lb, ub = b
        return (
            fa | fb,
            jnp.where(fb[..., None], lb, jnp.minimum(la, lb)),
            jnp.where(fb[..., None], ub, jnp.maximum(ua, ub)),
        )

    _, lo, hi = lax.associative_scan(combine, (start, lower, upper), reverse=reverse)
    return lo, hi


def _split_costs(first, last, lower, upper, valid, order):
    """One axis: the SAH cost of the split after each position of ``order`` (leaves sorted by centroid)."""
    size = order.shape[0]
    position = jnp.arange(size, dtype=jnp.int32)
    lo, hi, ok = lower[order], upper[order], valid[order]
    prefix_lo, prefix_hi = _segmented_boxes(position == first, lo, hi, reverse=False)
    suffix_lo, suffix_hi = _segmented_boxes(position == last, lo, hi, reverse=True)
    counted = jnp.cumsum(ok.astype(jnp.int32))
    before = counted[first] - ok[first].astype(jnp.int32)
    left = (counted - before).astype(lower.dtype)
    right = (counted[last] - before).astype(lower.dtype) - left
    after_lo, after_hi = jnp.roll(suffix_lo, -1, axis=0), jnp.roll(suffix_hi, -1, axis=0)
    cost = _area(prefix_lo, prefix_hi) * left + _area(after_lo, after_hi) * right
    return jnp.where(jnp.isnan(cost), jnp.inf, cost)


def _partition(order, goes_left, first, split, active):
    """``order`` with every active node's leaves stably partitioned: those going left first (from ``first``),
    the others from ``split + 1``. ``goes_left`` is indexed by slot."""
    size = order.shape[0]
    position = jnp.arange(size, dtype=jnp.int32)
    left = goes_left[order].astype(jnp.int32)
    left_before = jnp.cumsum(left) - left  # left leaves before each position, from the start of the array
    rank_left = left_before - left_before[first]
    rank_right = (position - first) - rank_left
    target = jnp.where(left == 1, first + rank_left, split + 1 + rank_right)
    target = jnp.where(active, target, position)
    return jnp.zeros_like(order).at[target].set(order)


def sweep_sah_tree(
    lower: jax.Array, upper: jax.Array, valid: jax.Array, max_depth: int
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The full-sweep SAH tree over ``C >= 2`` leaf slots (module docstring), in the structure's node layout.

    Args:
      lower, upper: ``(C, 3)`` leaf boxes.
      valid: ``(C,)`` bool; invalid slots (empty or non-finite boxes, padding) go to the ends of the nodes
        and are not counted by the cost, but are still leaves of the tree.
      max_depth: the deepest leaf allowed (the root's depth is 1); at least ``1 + log2(C)``.

    Returns:
      ``(children, node_range, order)``: ``children`` ``(C-1, 2)`` int32 (internal child ``c >= 0``, leaf
      position ``k`` as ``-1 - k``), ``node_range`` ``(C-1, 2)`` the first and last leaf position under each
      node, and ``order[k]`` the slot at leaf position ``k``.
    """
    size = lower.shape[0]
    lower, upper = lax.stop_gradient(lower), lax.stop_gradient(upper)
    centroid = 0.5 * (lower + upper)
    valid = valid & jnp.all(jnp.isfinite(centroid), axis=-1) & jnp.all(lower <= upper, axis=-1)
    centroid = jnp.where(valid[:, None], centroid, 0.0)
    position = jnp.arange(size, dtype=jnp.int32)
    big = jnp.int32(2**31 - 1)
    invalid = (~valid).astype(jnp.int32)
    orders = jnp.stack([lax.sort((invalid, centroid[:, a], position), num_keys=2, is_stable=True)[2] for a in range(3)])

    def level(state):
        orders, first, last, turns, depth, children, node_range = state
        active = first < last
        costs = jnp.stack([_split_costs(first, last, lower, upper, valid, orders[a]) for a in range(3)])
        median = (first + last) // 2
        larger = jnp.maximum(position - first + 1, last - position)
        allowed = active & (position < last) & ((depth + 1 + _ceil_log2(larger) <= max_depth) | (position == median))
        costs = jnp.where(allowed[None], costs, jnp.inf)
        # The cheapest split of each node (scattered to its first position), then the one nearest the middle.
        segment = jnp.broadcast_to(first, (3, size))
        best = jnp.full((size,), jnp.inf, costs.dtype).at[segment].min(costs)[first]
        near = jnp.isfinite(costs) & (costs <= best * (1 + 1e-6))
        offset = jnp.abs(2 * position + 1 - first - last)
        tie = jnp.full((size,), big).at[segment].min(jnp.where(near, offset, big))[first]
        axes = jnp.arange(3, dtype=jnp.int32)[:, None]
        code = jnp.where(near & (offset == tie), axes * size + position, big)
        code = jnp.full((size,), big).at[segment].min(code)[first]
        code = jnp.where(code == big, median, code)  # nothing finite (overflowing areas): split at the middle
        axis, split = code // size, code % size
        # The side of every leaf, from the chosen axis's order; then every order partitioned by it.
        chosen = jnp.take_along_axis(orders, axis[None], axis=0)[0]
        goes_left = jnp.zeros((size,), bool).at[chosen].set(position <= split)
        orders = jnp.stack([_partition(orders[a], goes_left, first, split, active) for a in range(3)])
        # Write each split node once, from its first position.
        node = jnp.where(active & (position == first), first + turns, size)
        left = jnp.where(split == first, -1 - first, first + turns + 1)
        right = jnp.where(split + 1 == last, -1 - last, split + 1 + turns)
        children = children.at[node].set(jnp.stack([left, right], axis=-1), mode="drop")
        node_range = node_range.at[node].set(jnp.stack([first, last], axis=-1), mode="drop")
        to_left = active & (position <= split)
        to_right = active & (position > split)
        return (
            orders,
            jnp.where(to_right, split + 1, first),
            jnp.where(to_left, split, last),
            turns + to_left.astype(jnp.int32),
            depth + 1,
            children,
            node_range,
        )

    state = (
        orders,
        jnp.zeros((size,), jnp.int32),
        jnp.full((size,), size - 1, jnp.int32),
        jnp.zeros((size,), jnp.int32),
        jnp.int32(1),
        jnp.zeros((size - 1, 2), jnp.int32),
        jnp.zeros((size - 1, 2), jnp.int32),
    )
    state = lax.while_loop(lambda s: jnp.any(s[1] < s[2]), level, state)
    return state[5], state[6], state[0][0]
