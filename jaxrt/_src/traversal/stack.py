"""Portable stack traversal of a binary BVH for one ray (batched with ``jax.vmap``).

Each loop step visits one internal node: it tests both child boxes (stored in the node), tests the
primitives of leaf children at once, descends into the nearer internal child and pushes the farther one
(nearest-child first, as in Aila & Laine 2009's "while-while" loop with leaves tested on sight). Any-hit mode
stops at the first accepted hit.

The traversal knows nothing of primitive kinds: a :class:`LeafTester` prepares per-ray constants and tests a
pair of leaves. Under ``vmap`` both children's leaf tests run on every step (lanes are selected), so testing
leaves on sight, rather than pushing them, halves the number of steps for about the same work per step.

Stack depth: the radix tree over 30-bit Morton codes with the index tie-break has depth at most
``31 + ceil(log2(capacity))``, and the stack never holds more entries than the current depth, so a stack of
:attr:`PrimitiveAccelerationStructure.max_depth` entries cannot overflow. An overflow (only possible with a
smaller, user-chosen stack) is flagged in the ``stats`` counters instead of being silent.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp
from jax import lax

from jaxrt._src.numerics import safe_reciprocal
from jaxrt._src.primitives.box import ray_box


class LeafTester(Protocol):
    """Tests the primitives in BVH leaves for one ray."""

    def prepare(self, origin: jax.Array, direction: jax.Array) -> Any:
        """Per-ray constants for :meth:`__call__`."""

    def __call__(
        self, context: Any, leaves: jax.Array, t_min: jax.Array, t_max: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """``(hit, distance)`` for leaves ``(2,)``, accepting hits in ``[t_min, t_max]``."""


class TraversalResult(NamedTuple):
    distance: jax.Array  # inf on a miss
    leaf: jax.Array  # -1 on a miss
    nodes_visited: jax.Array
    primitives_tested: jax.Array
    stack_overflow: jax.Array


class _State(NamedTuple):
    node: jax.Array
    stack: jax.Array
    depth: jax.Array
    distance: jax.Array
    leaf: jax.Array
    done: jax.Array
    visited: jax.Array
    tested: jax.Array
    overflow: jax.Array


def traverse(
    node_lower: jax.Array,
    node_upper: jax.Array,
    node_children: jax.Array,
    leaf_tester: LeafTester,
    origin: jax.Array,
    direction: jax.Array,
    t_min: jax.Array,
    t_max: jax.Array,
    enabled: jax.Array,
    *,
    any_hit: bool,
    stack_size: int,
) -> TraversalResult:
    """Trace one ray through a binary BVH (layout in :mod:`jaxrt._src.structures`).

    Args:
      node_lower, node_upper, node_children: the node arrays.
      leaf_tester: primitive tests (static).
      origin, direction: ``(3,)``; direction non-zero when ``enabled``.
      t_min, t_max: accepted distance interval.
      enabled: scalar bool; a disabled ray takes no step.
      any_hit: static; stop at the first accepted hit.
      stack_size: static stack depth.
    """
    inv_direction = safe_reciprocal(direction)
    context = leaf_tester.prepare(origin, direction)
    int_zero = jnp.zeros((), jnp.int32)

    def step(s: _State) -> _State:
        children = node_children[s.node]
        box_hit, t_near = ray_box(origin, inv_direction, t_min, s.distance, node_lower[s.node], node_upper[s.node])
        is_leaf = children < 0
        leaf_hit, leaf_t = leaf_tester(context, jnp.where(is_leaf & box_hit, -1 - children, -1), t_min, s.distance)
        leaf_hit &= is_leaf & box_hit
        leaf_t = jnp.where(leaf_hit, leaf_t, jnp.inf)
        second = leaf_t[1] < leaf_t[0]
        best_t = jnp.where(second, leaf_t[1], leaf_t[0])
        best_leaf = jnp.where(second, -1 - children[1], -1 - children[0])
        found = best_t < s.distance
        distance = jnp.where(found, best_t, s.distance)
        leaf = jnp.where(found, best_leaf, s.leaf)

        inner = box_hit & ~is_leaf
        near_first = t_near[0] <= t_near[1]
        near = jnp.where(near_first, children[0], children[1])
        far = jnp.where(near_first, children[1], children[0])
        both = inner[0] & inner[1]
        one = jnp.where(inner[0], children[0], children[1])
        # Push the far child when both are entered.
        push = both & (s.depth < stack_size)
        stack = jnp.where(push, s.stack.at[jnp.minimum(s.depth, stack_size - 1)].set(far), s.stack)
        depth = s.depth + push.astype(jnp.int32)
        overflow = s.overflow | (both & (s.depth >= stack_size))
        # Next node: the near child, the only child entered, or the top of the stack.
        pop = ~inner[0] & ~inner[1]
        empty = depth == 0
        top = stack[jnp.maximum(depth - 1, 0)]
        node = jnp.where(both, near, jnp.where(pop, top, one))
        depth = jnp.where(pop & ~empty, depth - 1, depth)
        done = (pop & empty) | (any_hit & (leaf >= 0))
        return _State(
            node=node,
            stack=stack,
            depth=depth,
            distance=distance,
            leaf=leaf,
            done=done,
            visited=s.visited + 1,
            tested=s.tested + jnp.sum((is_leaf & box_hit).astype(jnp.int32)),
            overflow=overflow,
        )

    init = _State(
        node=int_zero,
        stack=jnp.zeros((stack_size,), jnp.int32),
        depth=int_zero,
        distance=jnp.where(enabled, t_max, -jnp.inf).astype(origin.dtype),
        leaf=jnp.full((), -1, jnp.int32),
        done=~enabled,
        visited=int_zero,
        tested=int_zero,
        overflow=jnp.zeros((), bool),
    )
    final = lax.while_loop(lambda s: ~s.done, step, init)
    return TraversalResult(final.distance, final.leaf, final.visited, final.tested, final.overflow)
