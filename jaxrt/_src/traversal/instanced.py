"""Stack traversal of multi-level instance scenes: one per-ray step over the scene's concatenated node arrays.

The node arrays of every distinct structure of a scene are concatenated (:func:`jaxrt._src.instances.scene_arrays`),
so one step function walks all levels: a leaf child of a node is either a primitive (tested on sight, as in
:mod:`jaxrt._src.traversal.stack`) or an instance, which the step treats like an inner child (ordered by entry
distance, pushed when it is the farther one). Entering an instance transforms the ray into the child's space
with the instance's world-to-object transform and continues at the child's root node in the same arrays.

The direction is transformed but not normalised, so ``origin + t * direction`` is the same point in every
space and distances stay in world units: no distance conversion between levels, and the hit interval
``[t_min, t_max]`` is shared by all levels.

State per ray: the current node and level, the ray of each level (to restore it when the traversal returns
to a shallower level), the instance chain of the current path, and one stack whose entries are nodes
(``>= 0``) or instances (``-1 - g``). The level an entry belongs to is not stored with it: ``base[l]`` records
the stack depth when level ``l`` was entered, so an entry at stack position ``i`` belongs to the deepest level
``l <= level`` with ``base[l] <= i`` (entries of deeper levels are always above those of shallower ones).

Stack bound: at each level the stack holds at most the depth of the tree being walked there, so the sum over
levels of the deepest tree that can appear at that level
(:attr:`jaxrt._src.instances.InstanceAccelerationStructure.max_depth`) cannot overflow.

Masks: an instance child whose ``mask & ray.mask`` is zero is skipped like a missed box (Metal semantics).
Facing: each level carries ``facing`` in {-1, 0, +1}: the product of the chain's winding flips (mirroring
transforms and the counterclockwise option), or 0 below an instance that disables triangle culling. The
leaf tester receives it in ``prepare`` and culls in object space with the flipped sense.

Primitive kinds: the traversal knows none. The leaf tester prepares its per-ray constants from the ray of the
level being walked (object space: triangles shear it, curves build their ray frame from the unnormalised
direction, so their distances are world-space parameters too) and tests leaves by global index.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp
from jax import lax

from jaxrt._src.numerics import safe_reciprocal
from jaxrt._src.primitives.box import ray_box

__all__ = ["InstancedLeafTester", "InstancedScene", "InstancedTraversalResult", "traverse", "traverse_refill"]


class InstancedLeafTester(Protocol):
    """Tests primitive leaves for one ray in the space of the level being walked."""

    def prepare(self, origin: jax.Array, direction: jax.Array, facing: jax.Array) -> Any:
        """Per-ray constants for :meth:`__call__`; ``facing`` flips (-1) or disables (0) culling."""

    def __call__(
        self, context: Any, leaves: jax.Array, t_min: jax.Array, t_max: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """``(hit, distance)`` for leaves ``(2,)`` (``-1``: none), accepting hits in ``[t_min, t_max]``."""


class InstancedScene(NamedTuple):
    """What the traversal reads of a scene (global indices; see ``scene_arrays``)."""

    node_lower: jax.Array
    node_upper: jax.Array
    node_children: jax.Array
    instance_rows: jax.Array  # (G, 16) float: world-to-object (12), child root and facing (int32 bits), unused
    mask: jax.Array  # (G,) uint32


def pack_instances(world_to_object: jax.Array, child_root: jax.Array, facing: jax.Array) -> jax.Array:
    """``(G, 16)`` rows read by one gather when a ray enters an instance.

    Args:
      world_to_object: ``(G, 3, 4)`` transforms.
      child_root: ``(G,)`` int32 global root node of each instance's child.
      facing: ``(G,)`` int32 in {-1, 0, 1}: winding flip times culling switch.
    """
    ints = jnp.stack([child_root, facing, jnp.zeros_like(facing), jnp.zeros_like(facing)], axis=-1).astype(jnp.int32)
    if world_to_object.dtype == jnp.float32:
        bits = lax.bitcast_convert_type(ints, jnp.float32)
    else:  # float64 under x64: the int32 values are exact
        bits = ints.astype(world_to_object.dtype)
    return jnp.concatenate([world_to_object.reshape(-1, 12), bits], axis=-1)


def _unpack(row: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    m = row[:12].reshape(3, 4)
    tail = row[12:14]
    ints = lax.bitcast_convert_type(tail, jnp.int32) if row.dtype == jnp.float32 else tail.astype(jnp.int32)
    return m, ints[0], ints[1]


class InstancedTraversalResult(NamedTuple):
    distance: jax.Array  # inf on a miss
    leaf: jax.Array  # global primitive leaf, -1 on a miss
    instances: jax.Array  # (levels,) global instance ids of the hit's chain, outermost first, -1 past it
    nodes_visited: jax.Array
    primitives_tested: jax.Array
    stack_overflow: jax.Array


class _Ray(NamedTuple):
    origin: jax.Array
    direction: jax.Array
    inv_direction: jax.Array
    context: Any
    t_min: jax.Array
    mask: jax.Array


class _State(NamedTuple):
    node: jax.Array  # the node to visit; between visit and transition, the next entry (-1 - g: instance g)
    stack: jax.Array  # (S,) scratch
    depth: jax.Array
    level: jax.Array  # the level of ``node``
    ray_level: jax.Array  # the level whose ray is loaded in origin, inv_direction and context
    base: jax.Array  # (L,) scratch: stack depth when level l + 1 was entered
    chain: jax.Array  # (L,) scratch: instance entered at each level of the current path
    level_origin: jax.Array  # (L, 3) scratch: ray of level l + 1
    level_direction: jax.Array  # (L, 3) scratch
    level_facing: jax.Array  # (L,) scratch
    origin: jax.Array
    inv_direction: jax.Array
    context: Any
    distance: jax.Array
    leaf: jax.Array
    hit_chain: jax.Array  # (L,)
    done: jax.Array
    visited: jax.Array
    tested: jax.Array
    overflow: jax.Array


#: Fields that keep their lane storage when a lane takes a new ray (each is written before it is read).
_SCRATCH = ("stack", "base", "chain", "level_origin", "level_direction", "level_facing")


def _select_level(level: jax.Array, top: jax.Array, per_level: jax.Array) -> jax.Array:
    """``top`` at level 0, else ``per_level[level - 1]`` (selects: the level count is small and static)."""
    out = top
    for index in range(per_level.shape[0]):
        out = jnp.where(level == index + 1, per_level[index], out)
    return out


def _start(leaf_tester, root, levels, origin, direction, t_min, t_max, enabled, mask, stack_size):
    int_zero = jnp.zeros((), jnp.int32)
    one = jnp.ones((), jnp.int32)
    inv_direction = safe_reciprocal(direction)
    context = leaf_tester.prepare(origin, direction, one)
    ray = _Ray(origin, direction, inv_direction, context, t_min, mask)
    state = _State(
        node=jnp.full((), root, jnp.int32),
        stack=jnp.zeros((stack_size,), jnp.int32),
        depth=int_zero,
        level=int_zero,
        ray_level=int_zero,
        base=jnp.zeros((levels,), jnp.int32),
        chain=jnp.full((levels,), -1, jnp.int32),
        level_origin=jnp.zeros((levels, 3), origin.dtype),
        level_direction=jnp.zeros((levels, 3), origin.dtype),
        level_facing=jnp.ones((levels,), jnp.int32),
        origin=origin,
        inv_direction=inv_direction,
        context=context,
        distance=jnp.where(enabled, t_max, -jnp.inf).astype(origin.dtype),
        leaf=jnp.full((), -1, jnp.int32),
        hit_chain=jnp.full((levels,), -1, jnp.int32),
        done=~enabled,
        visited=int_zero,
        tested=int_zero,
        overflow=jnp.zeros((), bool),
    )
    return ray, state


def _visit(scene: InstancedScene, leaf_tester, primitive_leaves: int, ray: _Ray, s: _State, any_hit: bool) -> _State:
    """Visit one internal node with the loaded ray and choose the next entry (a node or an instance).

    The next entry and the level it belongs to are left in ``node`` and ``level``; :func:`_transition` then
    loads that level's ray and enters the instance, if it is one.
    """
    levels = s.chain.shape[0]
    stack_size = s.stack.shape[0]
    instances = scene.instance_rows.shape[0]
    active = ~s.done
    children = scene.node_children[s.node]
    box_hit, t_near = ray_box(
        s.origin, s.inv_direction, ray.t_min, s.distance, scene.node_lower[s.node], scene.node_upper[s.node]
    )
    box_hit &= active
    leaf_index = -1 - children
    is_leaf = children < 0
    is_primitive = is_leaf & (leaf_index < primitive_leaves)
    is_instance = is_leaf & ~is_primitive
    instance = jnp.clip(leaf_index - primitive_leaves, 0, instances - 1)
    visible = (scene.mask[instance] & ray.mask) != 0

    test = is_primitive & box_hit
    leaf_hit, leaf_t = leaf_tester(s.context, jnp.where(test, leaf_index, -1), ray.t_min, s.distance)
    leaf_hit &= test
    leaf_t = jnp.where(leaf_hit, leaf_t, jnp.inf)
    second = leaf_t[1] < leaf_t[0]
    best_t = jnp.where(second, leaf_t[1], leaf_t[0])
    best_leaf = jnp.where(second, leaf_index[1], leaf_index[0])
    # Strictly nearer than the current hit; the first hit may lie exactly at t_max (the interval is closed).
    found = (leaf_hit[0] | leaf_hit[1]) & ((best_t < s.distance) | ((s.leaf < 0) & (best_t <= s.distance)))
    distance = jnp.where(found, best_t, s.distance)
    leaf = jnp.where(found, best_leaf, s.leaf)
    on_path = jnp.arange(levels) < s.level
    hit_chain = jnp.where(found, jnp.where(on_path, s.chain, -1), s.hit_chain)

    entry = jnp.where(is_instance, -1 - instance, children)
    inner = box_hit & (~is_leaf | (is_instance & visible))
    near_first = t_near[0] <= t_near[1]
    near = jnp.where(near_first, entry[0], entry[1])
    far = jnp.where(near_first, entry[1], entry[0])
    both = inner[0] & inner[1]
    one = jnp.where(inner[0], entry[0], entry[1])
    push = both & (s.depth < stack_size)
    stack = s.stack.at[jnp.where(push, s.depth, stack_size)].set(far, mode="drop")
    depth = s.depth + push.astype(jnp.int32)
    overflow = s.overflow | (both & (s.depth >= stack_size))
    pop = ~inner[0] & ~inner[1]
    empty = depth == 0
    top_index = jnp.maximum(depth - 1, 0)
    top = stack[top_index]
    top_level = jnp.sum((s.base <= top_index) & (jnp.arange(1, levels + 1) <= s.level)).astype(jnp.int32)
    next_entry = jnp.where(both, near, jnp.where(pop, top, one))
    next_level = jnp.where(pop, top_level, s.level)
    depth = jnp.where(pop & ~empty, depth - 1, depth)
    finished = (pop & empty) | (any_hit & (leaf >= 0))
    go = active & ~finished
    return s._replace(
        node=jnp.where(go, next_entry, s.node),
        level=jnp.where(go, next_level, s.level),
        stack=stack,
        depth=jnp.where(active, depth, s.depth),
        distance=distance,
        leaf=leaf,
        hit_chain=hit_chain,
        done=s.done | finished,
        visited=s.visited + active.astype(jnp.int32),
        tested=s.tested + jnp.sum(test).astype(jnp.int32),
        overflow=overflow,
    )


def _needs_transition(s: _State) -> jax.Array:
    """The next entry is an instance, or belongs to a shallower level than the loaded ray."""
    return ~s.done & ((s.node < 0) | (s.level != s.ray_level))


def _transition(scene: InstancedScene, leaf_tester, ray: _Ray, s: _State) -> _State:
    """Load the ray of the next entry's level and, if the entry is an instance, enter it."""
    levels = s.chain.shape[0]
    instances = scene.instance_rows.shape[0]
    need = _needs_transition(s)
    base_origin = _select_level(s.level, ray.origin, s.level_origin)
    base_direction = _select_level(s.level, ray.direction, s.level_direction)
    base_facing = _select_level(s.level, jnp.ones((), jnp.int32), s.level_facing)
    entering = need & (s.node < 0)
    g = jnp.clip(-1 - s.node, 0, instances - 1)
    m, child_root, instance_facing = _unpack(scene.instance_rows[g])
    # Elementwise products, not matmuls: a batched 3x3 dot is a slow library call on the CPU.
    new_origin = jnp.sum(m[:, :3] * base_origin, axis=-1) + m[:, 3]
    new_direction = jnp.sum(m[:, :3] * base_direction, axis=-1)
    new_facing = base_facing * instance_facing
    # Level ``level + 1`` is stored at index ``level`` (selects, not scatters: the arrays are tiny).
    at_slot = entering & (jnp.arange(levels) == s.level)
    origin = jnp.where(entering, new_origin, base_origin)
    direction = jnp.where(entering, new_direction, base_direction)
    facing = jnp.where(entering, new_facing, base_facing)
    level = jnp.where(entering, s.level + 1, s.level)
    context = leaf_tester.prepare(origin, direction, facing)
    keep = lambda new, old: jax.tree_util.tree_map(lambda a, b: jnp.where(need, a, b), new, old)  # noqa: E731
    return s._replace(
        node=jnp.where(entering, child_root, s.node),
        level=level,
        ray_level=jnp.where(need, level, s.ray_level),
        base=jnp.where(at_slot, s.depth, s.base),
        chain=jnp.where(at_slot, g, s.chain),
        level_origin=jnp.where(at_slot[:, None], new_origin, s.level_origin),
        level_direction=jnp.where(at_slot[:, None], new_direction, s.level_direction),
        level_facing=jnp.where(at_slot, new_facing, s.level_facing),
        origin=keep(origin, s.origin),
        inv_direction=keep(safe_reciprocal(direction), s.inv_direction),
        context=keep(context, s.context),
    )


def _result(state: _State) -> InstancedTraversalResult:
    return InstancedTraversalResult(
        state.distance, state.leaf, state.hit_chain, state.visited, state.tested, state.overflow
    )


def traverse(
    scene: InstancedScene,
    leaf_tester: InstancedLeafTester,
    origin: jax.Array,
    direction: jax.Array,
    t_min: jax.Array,
    t_max: jax.Array,
    enabled: jax.Array,
    mask: jax.Array,
    *,
    root: int,
    primitive_leaves: int,
    levels: int,
    any_hit: bool,
    stack_size: int,
) -> InstancedTraversalResult:
    """Trace one ray through a multi-level scene (batch it with ``vmap``).

    Args:
      scene: the scene's global arrays.
      leaf_tester: primitive tests (static).
      origin, direction: ``(3,)`` world-space ray; direction non-zero when ``enabled``.
      t_min, t_max: accepted distance interval (world units, shared by every level).
      enabled: scalar bool; a disabled ray takes no step.
      mask: uint32 ray mask, AND-ed with instance masks.
      root: static global index of the root node.
      primitive_leaves: static number of primitive leaves (instance leaves follow them).
      levels: static instance levels of the scene.
      any_hit: static; stop at the first accepted hit.
      stack_size: static stack depth (the scene's ``max_depth``).
    """
    ray, state = _start(leaf_tester, root, levels, origin, direction, t_min, t_max, enabled, mask, stack_size)
    body = lambda s: _transition(scene, leaf_tester, ray, _visit(scene, leaf_tester, primitive_leaves, ray, s, any_hit))  # noqa: E731
    return _result(lax.while_loop(lambda s: ~s.done, body, state))


def traverse_refill(
    scene: InstancedScene,
    leaf_tester: InstancedLeafTester,
    origin: jax.Array,
    direction: jax.Array,
    t_min: jax.Array,
    t_max: jax.Array,
    enabled: jax.Array,
    mask: jax.Array,
    *,
    root: int,
    primitive_leaves: int,
    levels: int,
    any_hit: bool,
    stack_size: int,
    lanes: int = 2048,
    steps_per_refill: int = 2,
    split: bool = False,
) -> InstancedTraversalResult:
    """Trace a batch ``(N, ...)`` in a fixed window of lanes refilled as rays end (as ``stack.traverse_refill``).

    Results equal :func:`traverse` exactly (same steps, same order per ray). ``split`` runs the transition
    behind a ``lax.cond`` (taken when any lane needs it): faster on the CPU, where it stops XLA from fusing
    the visit into every consumer of its results.
    """
    n = origin.shape[0]
    width = min(lanes, n)
    start = lambda *a: _start(leaf_tester, root, levels, *a, 1)  # noqa: E731
    rays, initial = jax.vmap(start)(origin, direction, t_min, t_max, enabled, mask)
    visit = jax.vmap(lambda r, s: _visit(scene, leaf_tester, primitive_leaves, r, s, any_hit))
    transition = jax.vmap(lambda r, s: _transition(scene, leaf_tester, r, s))

    def step(r: _Ray, s: _State) -> _State:
        if not split:
            return transition(r, visit(r, s))
        # Behind conds, the results of each phase are materialised once; fused together, XLA's CPU backend
        # recomputes the visit inside each consumer of the next entry (measured 1.6x faster per step this way).
        s = lax.cond(jnp.any(~s.done), visit, lambda r, s: s, r, s)
        stack = s.stack  # kept out of the transition's operands, so that it is not copied
        s = lax.cond(jnp.any(jax.vmap(_needs_transition)(s)), transition, lambda r, s: s, r, s._replace(stack=None))
        return s._replace(stack=stack)

    take = lambda tree, index: jax.tree_util.tree_map(lambda a: a[index], tree)  # noqa: E731

    def pick(fresh, new, old):
        return jax.tree_util.tree_map(lambda a, b: jnp.where(fresh.reshape(-1, *([1] * (b.ndim - 1))), a, b), new, old)

    def load(state: _State, ray_index: jax.Array, fresh: jax.Array) -> _State:
        """Reset the lanes where ``fresh`` to the initial state of ray ``ray_index`` (scratch is reused)."""
        start_state = take(initial, ray_index)
        fields = {
            name: getattr(state, name)
            if name in _SCRATCH
            else pick(fresh, getattr(start_state, name), getattr(state, name))
            for name in _State._fields
        }
        return _State(**fields)

    lane_ray = jnp.arange(width, dtype=jnp.int32)
    lane_state = take(initial, lane_ray)._replace(
        stack=jnp.zeros((width, stack_size), jnp.int32),
        base=jnp.zeros((width, levels), jnp.int32),
        chain=jnp.full((width, levels), -1, jnp.int32),
        level_origin=jnp.zeros((width, levels, 3), origin.dtype),
        level_direction=jnp.zeros((width, levels, 3), origin.dtype),
        level_facing=jnp.ones((width, levels), jnp.int32),
    )
    lane_constants = take(rays, lane_ray)
    out = _result(take(initial, jnp.arange(n)))

    def body(carry):
        lane_ray, lane_constants, state, next_ray, out = carry
        for _ in range(steps_per_refill):
            state = step(lane_constants, state)
        retire = state.done & (lane_ray >= 0)
        target = jnp.where(retire, lane_ray, n)
        out = jax.tree_util.tree_map(lambda o, v: o.at[target].set(v, mode="drop"), out, _result(state))
        new_ray = next_ray + jnp.cumsum(retire.astype(jnp.int32)) - 1
        fresh = retire & (new_ray < n)
        lane_ray = jnp.where(retire, jnp.where(fresh, new_ray, -1), lane_ray)
        source = jnp.clip(new_ray, 0, n - 1)
        lane_constants = pick(fresh, take(rays, source), lane_constants)
        state = load(state, source, fresh)
        next_ray = jnp.minimum(next_ray + jnp.sum(retire.astype(jnp.int32)), n)
        return lane_ray, lane_constants, state, next_ray, out

    carry = (lane_ray, lane_constants, lane_state, jnp.int32(width), out)
    *_, out = lax.while_loop(lambda c: jnp.any(c[0] >= 0), body, carry)
    return out
