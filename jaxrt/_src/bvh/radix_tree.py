"""Binary radix tree over sorted keys (Karras 2012), built for all internal nodes in parallel.

Reference: Karras, "Maximizing Parallelism in the Construction of BVHs, Octrees, and k-d Trees", HPG 2012,
algorithm 4 (``determineRange`` and ``findSplit``), with equal codes made distinct by appending the sorted
position to the key ("index tie-break", section 4).

For ``n`` leaves the tree has ``n - 1`` internal nodes; internal node 0 is the root. Node ``i`` covers the
contiguous range of sorted leaves ``[first[i], last[i]]``. Its two children are each either a leaf (when the
child's range holds a single key) or the internal node with the same index as the split position.

The binary searches run in ``lax.fori_loop`` with a static trip count (``log2(n)`` steps). On the CPU the loop
is kept (XLA recomputes unrolled passes there and builds an order of magnitude slower); on accelerators it is
unrolled (:func:`jaxrt._src.bvh.boxes.loop_unroll`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

from jaxrt._src.bvh.boxes import loop_unroll


def _common_prefix(codes: jax.Array, i: jax.Array, j: jax.Array) -> jax.Array:
    """Karras' delta: length of the common prefix of keys ``i`` and ``j``, or -1 if ``j`` is out of range.

    The key is the 32-bit code followed by the 32-bit sorted position, so equal codes still differ.
    """
    n = codes.shape[0]
    inside = (j >= 0) & (j < n)
    jc = jnp.clip(j, 0, n - 1)
    ci, cj = codes[i], codes[jc]
    diff = ci ^ cj
    by_code = lax.clz(diff).astype(jnp.int32)
    by_index = 32 + lax.clz((i ^ jc).astype(jnp.uint32)).astype(jnp.int32)
    delta = jnp.where(diff != 0, by_code, by_index)
    return jnp.where(inside, delta, -1)


def build_radix_tree(sorted_codes: jax.Array, unroll: bool | None = None) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Children and leaf ranges of every internal node.

    Args:
      sorted_codes: ``(n,)`` uint32 codes in ascending order, ``n >= 2`` (static).
      unroll: unroll the binary searches (see :func:`jaxrt._src.bvh.boxes.loop_unroll`).

    Returns:
      ``children`` ``(n-1, 2)`` int32: an internal child as its index ``>= 0``, a leaf ``k`` as ``-1 - k``;
      ``first`` and ``last`` ``(n-1,)`` int32: the leaf range of each internal node.
    """
    n = sorted_codes.shape[0]
    steps = max(1, (n - 1).bit_length())
    i = jnp.arange(n - 1, dtype=jnp.int32)
    delta = lambda a, b: _common_prefix(sorted_codes, a, b)  # noqa: E731

    d = jnp.where(delta(i, i + 1) - delta(i, i - 1) >= 0, 1, -1).astype(jnp.int32)
    delta_min = delta(i, i - d)

    # The other end j = i + l d: the largest l whose prefix with i is longer than delta_min. The predicate
    # holds for l = 1 .. L and fails beyond, so one binary search from the power of two above n finds L
    # (Karras first doubles an upper bound, then halves: twice the passes for the same L).
    def find_end(k, carry):
        length, t = carry
        t = t // 2
        take = delta(i, i + (length + t) * d) > delta_min
        return jnp.where(take, length + t, length), t

    top = jnp.full_like(i, 1 << (steps + 1))
    length, _ = lax.fori_loop(0, steps + 1, find_end, (jnp.zeros_like(i), top), unroll=loop_unroll(unroll))
    j = i + length * d
    delta_node = delta(i, j)

    # Binary search for the split: the last position whose prefix with i is longer than the node's.
    def find_split(k, carry):
        split, t, active = carry
        t = (t + 1) // 2
        take = active & (delta(i, i + (split + t) * d) > delta_node)
        return jnp.where(take, split + t, split), t, active & (t > 1)

    split, _, _ = lax.fori_loop(
        0, steps + 2, find_split, (jnp.zeros_like(i), length, jnp.ones_like(i, bool)), unroll=loop_unroll(unroll)
    )
    gamma = i + split * d + jnp.minimum(d, 0)
    first = jnp.minimum(i, j)
    last = jnp.maximum(i, j)
    left = jnp.where(first == gamma, -1 - gamma, gamma)
    right = jnp.where(last == gamma + 1, -1 - (gamma + 1), gamma + 1)
    return jnp.stack([left, right], axis=-1), first, last


def tree_depth_bound(capacity: int) -> int:
    """The deepest leaf of a radix tree over ``capacity`` leaf slots: 30 Morton bits, then the index
    tie-break bits, plus one (each level of Karras' tree consumes at least one bit of the key). A traversal
    stack of this many entries cannot overflow."""
    return 31 + max(1, (capacity - 1).bit_length())
