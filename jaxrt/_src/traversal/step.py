"""One traversal step over a scene of any instance depth: the per-ray state, its start, and the step.

The scene is a :class:`~jaxrt._src.traversal.scene.TraversalScene`: the node arrays of every distinct structure
below the root, concatenated, so one step walks all levels. A primitive structure is a scene with zero levels,
and then the step compiles no instance code at all (the level count is static).

Each step visits one internal node: it tests both child boxes (stored in the node) with the conservative slab
test, tests the primitives of leaf children at once, then enters the nearer inner child and pushes the farther
one (nearest child first, the "while-while" loop of Aila & Laine 2009, with leaves tested on sight). Under
``vmap`` both children's leaf tests run on every step (lanes are selected), so testing leaves on sight, rather
than pushing them, halves the number of steps for about the same work per step. Any-hit mode stops at the
first accepted hit, and enters a child box that holds the ray's start after one the ray enters ahead
(:func:`_any_hit_order`).

Instances (``levels > 0``): a leaf child that is an instance is treated like an inner child (ordered by entry
distance, pushed when it is the farther one), and skipped like a missed box when ``instance_mask & ray.mask``
is zero (Metal's rule). Entering an instance (:func:`transition`) moves the ray into the child's space with
the instance's world-to-object transform and continues at the child's root. The direction is transformed but
not normalised, so ``origin + t * direction`` is the same point in every space, distances stay in world units
and the interval ``[t_min, t_max]`` is shared by all levels. The stack holds nodes (``>= 0``) and instances
(``-1 - g``); the level of an entry is not stored with it: ``base[l]`` records the stack depth when level
``l + 1`` was entered, so the entry at position ``i`` belongs to the deepest level ``l`` with ``base <= i``.
Each level carries ``facing`` in {-1, 0, +1}, the product of the chain's winding flips, or 0 below an instance
that disables culling; the leaf tester receives it in ``prepare`` (``None`` in a scene without instances).

Stack bound: at each level the stack holds at most the depth of the tree walked there, so the layout's
``stack_size`` (the sum over levels of the deepest tree that can appear at that level) cannot overflow; an
overflow (only possible with a smaller, user-chosen stack) is flagged in the ``stats`` counters.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp

from jaxrt._src.motion import blend, keyframe_position, spec_position
from jaxrt._src.numerics import safe_reciprocal
from jaxrt._src.primitives.box import ray_box
from jaxrt._src.transforms import instance_motion_at
from jaxrt._src.traversal.scene import TraversalLayout, TraversalResult, TraversalScene

__all__ = [
    "HitList",
    "LeafTester",
    "RayConstants",
    "State",
    "SCRATCH",
    "needs_transition",
    "prepare",
    "result",
    "select_level",
    "start",
    "step",
    "transition",
    "visit",
]


class LeafTester(Protocol):
    """Tests the primitives of BVH leaves for one ray, in the space of the level being walked."""

    def prepare(self, origin: jax.Array, direction: jax.Array, facing: jax.Array | None) -> Any:
        """Per-ray constants for :meth:`__call__`; ``facing`` flips (-1) or disables (0) culling, ``None``
        outside instances."""

    def __call__(
        self, context: Any, leaves: jax.Array, t_min: jax.Array, t_max: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """``(hit, distance)`` for leaves ``(2,)`` (``-1``: none), accepting hits in ``[t_min, t_max]``."""


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
    instances: jax.Array | None = None  # (K, levels) the instance chain of each hit (with instances only)


def _insert(hits: HitList, ok: jax.Array, t: jax.Array, leaf: jax.Array, chain: jax.Array | None) -> HitList:
    """Insert one candidate hit into the sorted list (after hits at the same distance)."""
    k = hits.distance.shape[0]
    position = jnp.sum(hits.distance <= t).astype(jnp.int32)
    index = jnp.arange(k)
    previous = jnp.maximum(index - 1, 0)

    def shift(old, new):
        at = index.reshape(-1, *([1] * (old.ndim - 1)))
        moved = jnp.where(at == position, new, old[previous])
        return jnp.where(at < position, old, moved)

    instances = hits.instances
    if instances is not None:
        instances = jnp.where(ok, shift(instances, chain), instances)
    return HitList(
        distance=jnp.where(ok, shift(hits.distance, t), hits.distance),
        leaf=jnp.where(ok, shift(hits.leaf, leaf), hits.leaf),
        total=hits.total + ok.astype(jnp.int32),
        instances=instances,
    )


class RayConstants(NamedTuple):
    """What a ray keeps for its whole traversal (world space)."""

    origin: jax.Array
    direction: jax.Array | None  # with instances only
    inv_direction: jax.Array
    context: Any  # the leaf tester's constants for the world-space ray
    t_min: jax.Array
    mask: jax.Array | None  # uint32, AND-ed with instance masks (with instances only)
    time: jax.Array | None = None  # the ray's time (with keyframe motion only)


def prepare(tester: LeafTester, origin: jax.Array, direction: jax.Array, facing: Any, time: Any) -> Any:
    """The tester's per-ray constants; testers of moving primitives (``reads_time``) also take the time."""
    if getattr(tester, "reads_time", False):
        return tester.prepare(origin, direction, facing, time)
    return tester.prepare(origin, direction, facing)


class State(NamedTuple):
    """A ray's traversal state. Fields after ``hits`` exist only in scenes with instances (else ``None``)."""

    node: jax.Array  # the node to visit; with instances, between visit and transition the next entry
    stack: jax.Array  # (S,) scratch
    depth: jax.Array
    distance: jax.Array  # the nearest accepted distance (or the culling distance of a hit list)
    leaf: jax.Array
    done: jax.Array
    visited: jax.Array
    tested: jax.Array
    overflow: jax.Array
    hits: HitList | None = None
    level: jax.Array | None = None  # the level of ``node``
    ray_level: jax.Array | None = None  # the level whose ray is loaded in origin, inv_direction and context
    base: jax.Array | None = None  # (L,) scratch: stack depth when level l + 1 was entered
    chain: jax.Array | None = None  # (L,) scratch: instance entered at each level of the current path
    level_origin: jax.Array | None = None  # (L, 3) scratch: ray of level l + 1
    level_direction: jax.Array | None = None  # (L, 3) scratch
    level_facing: jax.Array | None = None  # (L,) scratch
    origin: jax.Array | None = None  # the loaded ray
    inv_direction: jax.Array | None = None
    context: Any = None
    hit_chain: jax.Array | None = None  # (L,) the instance chain of the nearest hit


#: Fields that keep their lane storage when a lane takes a new ray (each is written before it is read).
SCRATCH = ("stack", "base", "chain", "level_origin", "level_direction", "level_facing")


def start(
    tester: LeafTester,
    layout: TraversalLayout,
    origin: jax.Array,
    direction: jax.Array,
    t_min: jax.Array,
    t_max: jax.Array,
    enabled: jax.Array,
    mask: jax.Array,
    time: jax.Array | None = None,
    *,
    stack_size: int | None = None,
    max_hits: int | None = None,
) -> tuple[RayConstants, State]:
    """Per-ray constants and the initial state of one ray (a disabled ray starts done). ``time`` is read
    only by scenes with keyframe motion (``layout.motion``)."""
    levels = layout.levels
    stack_size = layout.stack_size if stack_size is None else stack_size
    int_zero = jnp.zeros((), jnp.int32)
    inv_direction = safe_reciprocal(direction)
    time = jnp.asarray(time, origin.dtype) if layout.motion and time is not None else None
    context = prepare(tester, origin, direction, jnp.ones((), jnp.int32) if levels else None, time)
    # Without instances the direction and the mask are never read again: not carried (the refill driver
    # selects every carried field of a lane that takes a new ray).
    ray = RayConstants(
        origin,
        direction if levels else None,
        inv_direction,
        context,
        t_min,
        jnp.asarray(mask, jnp.uint32) if levels else None,
        time,
    )
    hits = None
    if max_hits is not None:
        chains = jnp.full((max_hits, levels), -1, jnp.int32) if levels else None
        hits = HitList(
            jnp.full((max_hits,), jnp.inf, origin.dtype), jnp.full((max_hits,), -1, jnp.int32), int_zero, chains
        )
    state = State(
        node=jnp.full((), layout.root, jnp.int32),
        stack=jnp.zeros((stack_size,), jnp.int32),
        depth=int_zero,
        distance=jnp.where(enabled, t_max, -jnp.inf).astype(origin.dtype),
        leaf=jnp.full((), -1, jnp.int32),
        done=~enabled,
        visited=int_zero,
        tested=int_zero,
        overflow=jnp.zeros((), bool),
        hits=hits,
    )
    if levels:
        state = state._replace(
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
            hit_chain=jnp.full((levels,), -1, jnp.int32),
        )
    return ray, state


def _any_hit_order(near_first: jax.Array, t_near: jax.Array, t_min: jax.Array) -> jax.Array:
    """Any-hit order: a child box that holds the ray's start (its entry clamped to ``t_min``) is entered after
    one the ray enters ahead; otherwise the nearer first. Rays that need any hit mostly leave a surface (shadow
    and occlusion rays): the box around their start holds that surface and its neighbours, which such a ray
    seldom meets, while a box it enters ahead lies across its path. Camera rays from outside the scene start
    in no child box, and keep the nearest-first order."""
    starts = t_near <= t_min
    return jnp.where(starts[0] != starts[1], starts[1], near_first)


def visit(
    scene: TraversalScene,
    layout: TraversalLayout,
    tester: LeafTester,
    ray: RayConstants,
    s: State,
    *,
    any_hit: bool,
    count_all: bool = False,
) -> State:
    """Visit one internal node with the loaded ray and choose the next entry; a no-op for a ray that is done.

    With a hit list (``max_hits``) both leaves' hits are inserted into it, and ``distance`` is the culling
    distance (see :class:`HitList`); ``count_all`` never culls. With instances the next entry and its level
    are left in ``node`` and ``level``: :func:`transition` then loads that level's ray and enters the
    instance, if it is one.
    """
    levels = layout.levels
    stack_size = s.stack.shape[0]
    active = ~s.done
    if levels:
        origin, inv_direction, context = s.origin, s.inv_direction, s.context
    else:
        origin, inv_direction, context = ray.origin, ray.inv_direction, ray.context
    children = scene.node_children[s.node]
    lower, upper = scene.node_lower[s.node], scene.node_upper[s.node]
    if scene.node_motion is not None:  # the node's keyframe boxes blended at the ray's time
        lower, upper = _node_boxes_at(scene.node_motion, layout.node_spec, s.node, ray.time)
    box_hit, t_near = ray_box(origin, inv_direction, ray.t_min, s.distance, lower, upper)
    box_hit &= active
    is_leaf = children < 0
    leaf_index = -1 - children
    if levels:
        is_primitive = is_leaf & (leaf_index < layout.primitive_leaves)
        is_instance = is_leaf & ~is_primitive
        instance = jnp.clip(leaf_index - layout.primitive_leaves, 0, scene.instance_mask.shape[0] - 1)
        visible = (scene.instance_mask[instance] & ray.mask) != 0
        if scene.instance_motion is not None:  # a moving instance on a "vanish" border is not there
            visible &= _instance_visible(scene.instance_motion, instance, ray.time)
    else:
        is_primitive = is_leaf
    test = is_primitive & box_hit
    leaf_hit, leaf_t = tester(context, jnp.where(test, leaf_index, -1), ray.t_min, s.distance)
    leaf_hit &= test
    leaf_t = jnp.where(leaf_hit, leaf_t, jnp.inf)
    second = leaf_t[1] < leaf_t[0]
    best_t = jnp.where(second, leaf_t[1], leaf_t[0])
    best_leaf = jnp.where(second, leaf_index[1], leaf_index[0])
    # Strictly nearer than the current hit; the first hit may lie exactly at t_max (the interval is closed).
    found = (leaf_hit[0] | leaf_hit[1]) & ((best_t < s.distance) | ((s.leaf < 0) & (best_t <= s.distance)))
    distance = jnp.where(found, best_t, s.distance)
    leaf = jnp.where(found, best_leaf, s.leaf)
    path = jnp.where(jnp.arange(levels) < s.level, s.chain, -1) if levels else None
    hit_chain = jnp.where(found, path, s.hit_chain) if levels else None
    hits = s.hits
    if hits is not None:
        for i in range(2):
            hits = _insert(hits, leaf_hit[i], leaf_t[i], leaf_index[i], path)
        k = hits.distance.shape[0]
        full = hits.total > k
        distance = s.distance if count_all or k == 0 else jnp.where(full, hits.distance[k - 1], s.distance)
        leaf = hits.leaf[0] if k else s.leaf

    entry = jnp.where(is_instance, -1 - instance, children) if levels else children
    inner = box_hit & (~is_leaf | (is_instance & visible)) if levels else box_hit & ~is_leaf
    near_first = t_near[0] <= t_near[1]
    if any_hit:
        near_first = _any_hit_order(near_first, t_near, ray.t_min)
    near = jnp.where(near_first, entry[0], entry[1])
    far = jnp.where(near_first, entry[1], entry[0])
    both = inner[0] & inner[1]
    one = jnp.where(inner[0], entry[0], entry[1])
    # Push the far entry when both are entered (a scatter that drops out-of-range writes, not a select).
    push = both & (s.depth < stack_size)
    stack = s.stack.at[jnp.where(push, s.depth, stack_size)].set(far, mode="drop")
    depth = s.depth + push.astype(jnp.int32)
    overflow = s.overflow | (both & (s.depth >= stack_size))
    # Next entry: the near child, the only child entered, or the top of the stack.
    pop = ~inner[0] & ~inner[1]
    empty = depth == 0
    top_index = jnp.maximum(depth - 1, 0)
    top = stack[top_index]
    node = jnp.where(both, near, jnp.where(pop, top, one))
    depth = jnp.where(pop & ~empty, depth - 1, depth)
    finished = (pop & empty) | (any_hit & (leaf >= 0))
    out = s._replace(
        node=jnp.where(active, node, s.node),
        stack=stack,
        depth=jnp.where(active, depth, s.depth),
        distance=distance,
        leaf=leaf,
        done=s.done | finished,
        visited=s.visited + active.astype(jnp.int32),
        tested=s.tested + jnp.sum(test).astype(jnp.int32),
        overflow=overflow,
        hits=hits,
    )
    if not levels:
        return out
    top_level = jnp.sum((s.base <= top_index) & (jnp.arange(1, levels + 1) <= s.level)).astype(jnp.int32)
    go = active & ~finished
    return out._replace(
        node=jnp.where(go, node, s.node),
        level=jnp.where(go, jnp.where(pop, top_level, s.level), s.level),
        hit_chain=hit_chain,
    )


def _node_boxes_at(node_motion: Any, spec: Any, node: jax.Array, time: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Node ``node``'s child boxes blended at ``time``. Each primitive blended at ``time`` lies in the blend of
    its keyframe boxes, which lies in the blend of the node's keyframe boxes (rounding is monotone, so also
    in floating point); equal corners (empty children, static geometry) are kept as they are."""
    lower_keys, upper_keys = node_motion
    p = spec_position(spec, lower_keys.shape[0], time)

    def at(keys):
        a, b = keys[p.index, node], keys[p.index + 1, node]
        return jnp.where(a == b, a, blend(a, b, p.weight))

    return at(lower_keys), at(upper_keys)


def _instance_visible(motion: Any, instance: jax.Array, time: jax.Array) -> jax.Array:
    """Whether instances exist at ``time`` (only moving ones on a ``"vanish"`` border can be absent)."""
    position = keyframe_position(
        time,
        motion.count[instance],
        motion.start[instance],
        motion.end[instance],
        motion.vanish_start[instance],
        motion.vanish_end[instance],
    )
    return position.visible | ~motion.moving[instance]


def select_level(level: jax.Array, top: jax.Array, per_level: jax.Array) -> jax.Array:
    """``top`` at level 0, else ``per_level[level - 1]`` (selects: the level count is small and static)."""
    out = top
    for index in range(per_level.shape[0]):
        out = jnp.where(level == index + 1, per_level[index], out)
    return out


def needs_transition(s: State) -> jax.Array:
    """The next entry is an instance, or belongs to a shallower level than the loaded ray."""
    return ~s.done & ((s.node < 0) | (s.level != s.ray_level))


def transition(scene: TraversalScene, tester: LeafTester, ray: RayConstants, s: State) -> State:
    """Load the ray of the next entry's level and, if the entry is an instance, enter it (scenes with
    instances only)."""
    levels = s.chain.shape[0]
    instances = scene.instance_mask.shape[0]
    need = needs_transition(s)
    base_origin = select_level(s.level, ray.origin, s.level_origin)
    base_direction = select_level(s.level, ray.direction, s.level_direction)
    base_facing = select_level(s.level, jnp.ones((), jnp.int32), s.level_facing)
    entering = need & (s.node < 0)
    g = jnp.clip(-1 - s.node, 0, instances - 1)
    m = scene.instance_world_to_object[g]
    if scene.instance_motion is not None:  # the inverse of the transform blended at the ray's time
        _, moved, _, moving = instance_motion_at(scene.instance_motion, g, ray.time)
        m = jnp.where(moving, moved, m)
    # Elementwise products, not matmuls: a batched 3x3 dot is a slow library call on the CPU.
    new_origin = jnp.sum(m[:, :3] * base_origin, axis=-1) + m[:, 3]
    new_direction = jnp.sum(m[:, :3] * base_direction, axis=-1)
    new_facing = base_facing * scene.instance_facing[g]
    # Level ``level + 1`` is stored at index ``level`` (selects, not scatters: the arrays are tiny).
    at_slot = entering & (jnp.arange(levels) == s.level)
    origin = jnp.where(entering, new_origin, base_origin)
    direction = jnp.where(entering, new_direction, base_direction)
    facing = jnp.where(entering, new_facing, base_facing)
    level = jnp.where(entering, s.level + 1, s.level)
    context = prepare(tester, origin, direction, facing, ray.time)
    keep = lambda new, old: jax.tree_util.tree_map(lambda a, b: jnp.where(need, a, b), new, old)  # noqa: E731
    return s._replace(
        node=jnp.where(entering, scene.instance_child_root[g], s.node),
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


def step(
    scene: TraversalScene,
    layout: TraversalLayout,
    tester: LeafTester,
    ray: RayConstants,
    s: State,
    *,
    any_hit: bool,
    count_all: bool = False,
) -> State:
    """One visit, and with instances the transition into the next entry's level."""
    s = visit(scene, layout, tester, ray, s, any_hit=any_hit, count_all=count_all)
    return transition(scene, tester, ray, s) if layout.levels else s


def result(s: State) -> TraversalResult:
    """The traversal's answer for a finished state."""
    chain = s.hit_chain if s.hit_chain is not None else jnp.zeros((*s.leaf.shape, 0), jnp.int32)
    return TraversalResult(s.distance, s.leaf, chain, s.visited, s.tested, s.overflow, s.hits)
