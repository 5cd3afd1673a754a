"""Axis-aligned boxes of primitives and of BVH nodes, computed without a sequential bottom-up pass.

An LBVH internal node covers a contiguous range of sorted leaves, so its box is a range reduction over leaf
boxes. We answer all ranges at once with a sparse table (Bentley's range-minimum technique): level ``k`` holds
the union of ``2**k`` consecutive leaves, and the box of ``[a, b]`` is the union of two overlapping level-``k``
windows with ``k = floor(log2(b - a + 1))``. Min and max are exact, so the result equals the bottom-up union.
Only one level is alive at a time (``O(n)`` memory); ``log2(n)`` parallel passes replace the atomic-counter
bottom-up pass of Karras 2012, which has no data-parallel equivalent in XLA.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax


def empty_box(n: int, dtype) -> tuple[jax.Array, jax.Array]:
    """``n`` empty boxes: lower ``+inf``, upper ``-inf`` (the identity of box union; every ray misses them)."""
    return jnp.full((n, 3), jnp.inf, dtype), jnp.full((n, 3), -jnp.inf, dtype)


def range_boxes(
    leaf_lower: jax.Array, leaf_upper: jax.Array, first: jax.Array, last: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Union of the leaf boxes ``[first[i], last[i]]`` for every range ``i``.

    Args:
      leaf_lower, leaf_upper: ``(n, 3)`` leaf boxes in sorted order.
      first, last: ``(m,)`` int32 inclusive leaf ranges.

    Returns:
      ``(m, 3)`` lower and upper corners.
    """
    n = leaf_lower.shape[0]
    length = last - first + 1
    level = 31 - lax.clz(length.astype(jnp.uint32)).astype(jnp.int32)
    inf = jnp.array(jnp.inf, leaf_lower.dtype)
    positions = jnp.arange(n, dtype=jnp.int32)

    def body(k, carry):
        table_lo, table_hi, out_lo, out_hi = carry
        width = jnp.left_shift(jnp.int32(1), k)
        b = jnp.clip(last - width + 1, 0, n - 1)
        lo = jnp.minimum(table_lo[first], table_lo[b])
        hi = jnp.maximum(table_hi[first], table_hi[b])
        here = (level == k)[:, None]
        out_lo = jnp.where(here, lo, out_lo)
        out_hi = jnp.where(here, hi, out_hi)
        inside = (positions + width < n)[:, None]
        table_lo = jnp.minimum(table_lo, jnp.where(inside, jnp.roll(table_lo, -width, axis=0), inf))
        table_hi = jnp.maximum(table_hi, jnp.where(inside, jnp.roll(table_hi, -width, axis=0), -inf))
        return table_lo, table_hi, out_lo, out_hi

    out_lo, out_hi = empty_box(first.shape[0], leaf_lower.dtype)
    levels = max(1, n.bit_length())
    _, _, out_lo, out_hi = lax.fori_loop(0, levels, body, (leaf_lower, leaf_upper, out_lo, out_hi))
    return out_lo, out_hi


def child_boxes(
    children: jax.Array,
    node_lower: jax.Array,
    node_upper: jax.Array,
    leaf_lower: jax.Array,
    leaf_upper: jax.Array,
) -> tuple[jax.Array, jax.Array]:
    """Boxes of both children of every internal node, ``(m, 2, 3)`` each (leaf ``k`` is encoded ``-1 - k``)."""
    is_leaf = (children < 0)[..., None]
    leaf = jnp.maximum(-1 - children, 0)
    node = jnp.maximum(children, 0)
    lower = jnp.where(is_leaf, leaf_lower[leaf], node_lower[node])
    upper = jnp.where(is_leaf, leaf_upper[leaf], node_upper[node])
    return lower, upper
