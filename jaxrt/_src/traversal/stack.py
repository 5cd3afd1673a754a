"""Portable stack traversal of a binary BVH: one per-ray step, and two drivers that batch it.

:func:`traverse` runs one ray to completion (batch it with ``jax.vmap``). :func:`traverse_refill` runs the
same step over a batch in a fixed window of lanes that take new rays as old ones end; a vmapped
``while_loop`` instead runs every lane until the slowest ray of the batch ends, which measured 2-3x slower on
the CPU (the per-lane select of the whole carry, stack included, is paid on every step by every lane).

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
    hits: Any = None  # with ``max_hits``: a :class:`HitList`


class HitList(NamedTuple):
    """The ``K`` nearest accepted hits of a ray, sorted by distance, and how many were accepted in all.

    While no more than ``K`` hits are known the traversal culls only by the ray's ``max_distance``, so that
    ``total`` counts every hit up to ``K + 1``; after that it culls by the ``K``-th distance (``total > K``
    then only says that more than ``K`` hits exist). In counting mode (``count_all``) it never culls, and
    ``total`` is the number of hits.
    """

    distance: jax.Array  # (K,) inf past the last hit
    leaf: jax.Array  # (K,) -1 past the last hit
    total: jax.Array  # int32


def _insert(hits: HitList, ok: jax.Array, t: jax.Array, leaf: jax.Array) -> HitList:
    """Insert one candidate hit into the sorted list (after hits at the same distance)."""
    k = hits.distance.shape[0]
    position = jnp.sum(hits.distance <= t).astype(jnp.int32)
    index = jnp.arange(k)
    previous = jnp.maximum(index - 1, 0)
    shift = lambda old, new: jnp.where(index < position, old, jnp.where(index == position, new, old[previous]))  # noqa: E731
    return HitList(
        distance=jnp.where(ok, shift(hits.distance, t), hits.distance),
        leaf=jnp.where(ok, shift(hits.leaf, leaf), hits.leaf),
        total=hits.total + ok.astype(jnp.int32),
    )


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
    hits: HitList | None = None


class _RayConstants(NamedTuple):
    origin: jax.Array
    inv_direction: jax.Array
    context: Any
    t_min: jax.Array


def _start(leaf_tester, origin, direction, t_min, t_max, enabled, stack_size, max_hits=None):
    """Per-ray constants and the initial state (a disabled ray starts done)."""
    int_zero = jnp.zeros((), jnp.int32)
    constants = _RayConstants(origin, safe_reciprocal(direction), leaf_tester.prepare(origin, direction), t_min)
    state = _State(
        node=int_zero,
        stack=jnp.zeros((stack_size,), jnp.int32),
        depth=int_zero,
        distance=jnp.where(enabled, t_max, -jnp.inf).astype(origin.dtype),
        leaf=jnp.full((), -1, jnp.int32),
        done=~enabled,
        visited=int_zero,
        tested=int_zero,
        overflow=jnp.zeros((), bool),
        hits=None
        if max_hits is None
        else HitList(
            jnp.full((max_hits,), jnp.inf, origin.dtype), jnp.full((max_hits,), -1, jnp.int32), jnp.zeros((), jnp.int32)
        ),
    )
    return constants, state


def _step(
    nodes, leaf_tester, ray: _RayConstants, s: _State, any_hit: bool, stack_size: int, count_all: bool = False
) -> _State:
    """Visit one internal node; a no-op for a ray that is done.

    With a hit list (``max_hits``) both leaves' hits are inserted into it, and ``distance`` is the culling
    distance (see :class:`HitList`); ``count_all`` never culls.
    """
    node_lower, node_upper, node_children = nodes
    active = ~s.done
    children = node_children[s.node]
    box_hit, t_near = ray_box(
        ray.origin, ray.inv_direction, ray.t_min, s.distance, node_lower[s.node], node_upper[s.node]
    )
    box_hit &= active
    is_leaf = children < 0
    leaf_hit, leaf_t = leaf_tester(ray.context, jnp.where(is_leaf & box_hit, -1 - children, -1), ray.t_min, s.distance)
    leaf_hit &= is_leaf & box_hit
    leaf_t = jnp.where(leaf_hit, leaf_t, jnp.inf)
    second = leaf_t[1] < leaf_t[0]
    best_t = jnp.where(second, leaf_t[1], leaf_t[0])
    best_leaf = jnp.where(second, -1 - children[1], -1 - children[0])
    # Strictly nearer than the current hit; the first hit may lie exactly at t_max (the interval is closed).
    found = (leaf_hit[0] | leaf_hit[1]) & ((best_t < s.distance) | ((s.leaf < 0) & (best_t <= s.distance)))
    distance = jnp.where(found, best_t, s.distance)
    leaf = jnp.where(found, best_leaf, s.leaf)
    hits = s.hits
    if hits is not None:
        for i in range(2):
            hits = _insert(hits, leaf_hit[i], leaf_t[i], -1 - children[i])
        k = hits.distance.shape[0]
        full = hits.total > k
        distance = s.distance if count_all or k == 0 else jnp.where(full, hits.distance[k - 1], s.distance)
        leaf = hits.leaf[0] if k else s.leaf

    inner = box_hit & ~is_leaf
    near_first = t_near[0] <= t_near[1]
    near = jnp.where(near_first, children[0], children[1])
    far = jnp.where(near_first, children[1], children[0])
    both = inner[0] & inner[1]
    one = jnp.where(inner[0], children[0], children[1])
    # Push the far child when both are entered (a scatter that drops out-of-range writes, not a select).
    push = both & (s.depth < stack_size)
    stack = s.stack.at[jnp.where(push, s.depth, stack_size)].set(far, mode="drop")
    depth = s.depth + push.astype(jnp.int32)
    overflow = s.overflow | (both & (s.depth >= stack_size))
    # Next node: the near child, the only child entered, or the top of the stack.
    pop = ~inner[0] & ~inner[1]
    empty = depth == 0
    top = stack[jnp.maximum(depth - 1, 0)]
    node = jnp.where(both, near, jnp.where(pop, top, one))
    depth = jnp.where(pop & ~empty, depth - 1, depth)
    finished = (pop & empty) | (any_hit & (leaf >= 0))
    return _State(
        node=jnp.where(active, node, s.node),
        stack=stack,
        depth=jnp.where(active, depth, s.depth),
        distance=distance,
        leaf=leaf,
        done=s.done | finished,
        visited=s.visited + active.astype(jnp.int32),
        tested=s.tested + jnp.sum(box_hit & is_leaf).astype(jnp.int32),
        overflow=overflow,
        hits=hits,
    )


def _result(state: _State) -> TraversalResult:
    return TraversalResult(state.distance, state.leaf, state.visited, state.tested, state.overflow, state.hits)


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
    max_hits: int | None = None,
    count_all: bool = False,
) -> TraversalResult:
    """Trace one ray through a binary BVH (layout in :mod:`jaxrt._src.structures`); batch it with ``vmap``.

    Args:
      node_lower, node_upper, node_children: the node arrays.
      leaf_tester: primitive tests (static).
      origin, direction: ``(3,)``; direction non-zero when ``enabled``.
      t_min, t_max: accepted distance interval.
      enabled: scalar bool; a disabled ray takes no step.
      any_hit: static; stop at the first accepted hit.
      stack_size: static stack depth.
      max_hits: static; keep the ``max_hits`` nearest hits in a :class:`HitList` (``0`` with ``count_all``:
        only count them).
      count_all: static; with ``max_hits``, never cull (count every hit).
    """
    nodes = (node_lower, node_upper, node_children)
    ray, state = _start(leaf_tester, origin, direction, t_min, t_max, enabled, stack_size, max_hits)
    body = lambda s: _step(nodes, leaf_tester, ray, s, any_hit, stack_size, count_all)  # noqa: E731
    final = lax.while_loop(lambda s: ~s.done, body, state)
    return _result(final)


def traverse_refill(
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
    lanes: int = 2048,
    steps_per_refill: int = 2,
    max_hits: int | None = None,
    count_all: bool = False,
) -> TraversalResult:
    """Trace a batch of rays ``(N, ...)`` in a fixed window of lanes that are refilled as rays end.

    A vmapped ``while_loop`` runs every lane until the slowest ray of the batch ends. Here ``lanes`` rays
    are in flight at a time: every ``steps_per_refill`` steps, lanes whose ray is done write its result and
    take the next ray of the queue (the "persistent threads" scheme of Aila & Laine 2009). One loop with a
    fixed shape, so it compiles once; results equal :func:`traverse` exactly (same step, same order per ray).
    """
    nodes = (node_lower, node_upper, node_children)
    n = origin.shape[0]
    width = min(lanes, n)
    start = lambda *a: _start(leaf_tester, *a, 1, max_hits)  # noqa: E731
    rays, initial = jax.vmap(start)(origin, direction, t_min, t_max, enabled)
    step = jax.vmap(lambda r, s: _step(nodes, leaf_tester, r, s, any_hit, stack_size, count_all))
    take = lambda tree, index: jax.tree_util.tree_map(lambda a: a[index], tree)  # noqa: E731

    def load(state: _State, ray_index: jax.Array, fresh: jax.Array) -> _State:
        """Reset the lanes where ``fresh`` to the initial state of ray ``ray_index`` (the stack is reused)."""
        start = take(initial, ray_index)._replace(stack=state.stack)
        pick = lambda new, old: jnp.where(fresh.reshape(-1, *([1] * (old.ndim - 1))), new, old)  # noqa: E731
        return jax.tree_util.tree_map(pick, start, state)

    lane_ray = jnp.arange(width, dtype=jnp.int32)
    state = take(initial, lane_ray)._replace(stack=jnp.zeros((width, stack_size), jnp.int32))
    lane_constants = take(rays, lane_ray)
    out = _result(take(initial, jnp.arange(n)))

    def body(carry):
        lane_ray, lane_constants, state, next_ray, out = carry
        for _ in range(steps_per_refill):
            state = step(lane_constants, state)
        retire = state.done & (lane_ray >= 0)
        target = jnp.where(retire, lane_ray, n)
        out = jax.tree_util.tree_map(lambda o, v: o.at[target].set(v, mode="drop"), out, _result(state))
        new_ray = next_ray + jnp.cumsum(retire, dtype=jnp.int32) - 1
        fresh = retire & (new_ray < n)
        lane_ray = jnp.where(retire, jnp.where(fresh, new_ray, -1), lane_ray)
        source = jnp.clip(new_ray, 0, n - 1)
        incoming = take(rays, source)
        lane_constants = jax.tree_util.tree_map(
            lambda new, old: jnp.where(fresh.reshape(-1, *([1] * (old.ndim - 1))), new, old), incoming, lane_constants
        )
        state = load(state, source, fresh)
        next_ray = jnp.minimum(next_ray + jnp.sum(retire, dtype=jnp.int32), n)
        return lane_ray, lane_constants, state, next_ray, out

    carry = (lane_ray, lane_constants, state, jnp.int32(width), out)
    *_, out = lax.while_loop(lambda c: jnp.any(c[0] >= 0), body, carry)
    return out
