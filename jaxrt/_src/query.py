"""Intersection queries: the traversal as a state the user steps, deciding candidates in their own loop
(Metal's ``intersection_query``).

A query walks the structure with the portable stack traversal. Opaque triangles and curves are committed as
they are found; each non-opaque triangle the ray hits and each box primitive it enters becomes a *candidate*
that :meth:`IntersectionQuery.next` stops at, nearest first within a node, and only while it is nearer than
the committed hit. The user reads the candidate and commits it or not; the next call to ``next`` continues
the traversal, culling by the committed distance. After the loop the ``committed_*`` accessors describe the
nearest committed hit. A query is a pytree of one ray's state: build it inside ``jax.vmap`` over rays and
step it with ``lax.while_loop``::

    def trace(ray):
        def body(q):
            alpha = texture_alpha(q.candidate_primitive_id, q.candidate_triangle_barycentric_coord)
            return q.commit_triangle_intersection(alpha >= 0.5).next()

        q = rt.intersection_query(ray, structure, rt.Intersector(rt.tags.triangle_data))
        q = lax.while_loop(lambda q: q.has_candidate, body, q.next())
        return q.committed_distance

The intersector's ``filter`` and ``intersection_functions`` are not used: the loop decides. Results of a
query are not differentiable (trace again with ``Intersector.intersect`` for gradients).

On a GPU (where the intersector's backend is the GPU kernel), a query of a static primitive structure
without curves lists its candidates with the kernel instead, as candidate waves do
(:mod:`jaxrt._src.traversal.waves`): ``next`` serves the candidates of the last listing one by one, in
``(distance, leaf)`` order, committing opaque triangles on the way, and when they run out the kernel lists
the next :data:`KERNEL_CANDIDATES` past the last one, culled by the committed distance. Under ``jax.vmap``
each listing is one launch for every ray that needs one. Candidates then come nearest first, so none behind
the committed hit is presented; the committed result is the same.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from jaxrt._src import leaves as leaf_tests
from jaxrt._src.instances import InstanceAccelerationStructure
from jaxrt._src.intersector import Intersector, _check_levels
from jaxrt._src.kinds.registry import BOUNDING_BOX, KINDS, TRIANGLE
from jaxrt._src.pipeline import resolve_backend, sanitized_rays, wave_lister
from jaxrt._src.primitive_data import data_at
from jaxrt._src.primitives import triangle
from jaxrt._src.primitives.box import ray_box
from jaxrt._src.ray import Ray
from jaxrt._src.result import IntersectionType
from jaxrt._src.scene_view import SceneView, primitive_structures, scene_view
from jaxrt._src.structures import PrimitiveAccelerationStructure
from jaxrt._src.traversal import waves
from jaxrt._src.traversal.step import RayConstants, State, select_level, start, step

__all__ = ["IntersectionQuery", "intersection_query"]

_NONE, _TRIANGLE, _BOX = int(IntersectionType.NONE), int(IntersectionType.TRIANGLE), int(IntersectionType.BOUNDING_BOX)

#: Candidates the GPU kernel lists per ray and launch for a query (the query serves them one at a time).
KERNEL_CANDIDATES = 8


class _OpaqueLeaves:
    """The intersector's opaque tests (triangles, curves) with candidate leaves masked out (a ``LeafTester``)."""

    def __init__(self, inner: Any, is_candidate_geometry: jax.Array, view: SceneView):
        self.inner = inner
        self.table = is_candidate_geometry
        self.view = view

    def prepare(self, origin, direction, facing):
        return self.inner.prepare(origin, direction, facing)

    def __call__(self, context, leaves, t_min, t_max):
        hit, t = self.inner(context, leaves, t_min, t_max)
        candidate = self.view.leaf_flag(self.table, leaves)
        return hit & ~candidate, jnp.where(candidate, jnp.inf, t)


def _candidate_table(view: SceneView) -> jax.Array:
    """Geometries whose primitives are candidates: non-opaque triangles and boxes (padding row last)."""
    return view.slot_table(view.slots_where(lambda g: (TRIANGLE.holds(g) and not g.opaque) or BOUNDING_BOX.holds(g)))


class _Held:
    """The structure of a query, held by reference outside the query's array leaves: a loop over queries under
    ``jax.vmap`` batches every array of its carry, and a structure among them would be copied once per ray."""

    def __init__(self, structure: Any):
        self.structure = structure

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _Held) and other.structure is self.structure

    def __hash__(self) -> int:
        return id(self.structure)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class IntersectionQuery:
    """One ray's intersection query (Metal's ``intersection_query``): an immutable pytree; every method
    returns a new query. Build it with :func:`intersection_query`."""

    ray: RayConstants
    direction: jax.Array
    state: State
    pending_leaf: jax.Array  # (2,) candidate leaves found at the last node, nearest first; -1: none
    pending_distance: jax.Array  # (2,) their triangle distance or box entry distance
    pending_chain: jax.Array  # (levels,) the instance chain of the node the pending candidates came from
    candidate: jax.Array  # the current candidate leaf; -1: none
    candidate_distance: jax.Array  # its distance (triangles) or box entry distance (boxes)
    candidate_chain: jax.Array  # (levels,) its instance chain (global ids, -1 past it)
    committed_chain: jax.Array  # (levels,) the committed hit's instance chain
    cursor_distance: jax.Array  # kernel listing: the last candidate listed (distance)
    cursor_leaf: jax.Array  # and leaf
    more: jax.Array  # kernel listing: candidates past the cursor remain to be listed
    intersector: Any = dataclasses.field(metadata=dict(static=True))
    held: _Held = dataclasses.field(metadata=dict(static=True))
    listing: int = dataclasses.field(default=0, metadata=dict(static=True))  # 0: portable; K: kernel lists K

    @property
    def structure(self) -> Any:
        """The acceleration structure the query traverses."""
        return self.held.structure

    # --- stepping -----------------------------------------------------------------------------------------

    @property
    def has_candidate(self) -> jax.Array:
        """Whether :meth:`next` stopped at a candidate (Metal's ``next()`` return value)."""
        return self.candidate >= 0

    def next(self) -> IntersectionQuery:
        """Advance to the next candidate (committing opaque hits on the way); ``has_candidate`` is False
        when the traversal has ended."""
        q = dataclasses.replace(self, candidate=jnp.int32(-1))
        if self.listing:

            def searching(q):
                return ~q.has_candidate & ~q.state.done & ((q.pending_leaf[0] >= 0) | q.more)

            return lax.while_loop(searching, lambda q: _serve(_list(q)), q)

        def searching(q):
            return ~q.has_candidate & ((q.pending_leaf[0] >= 0) | ~q.state.done)

        # Both branches and a select rather than ``lax.cond``: under ``jax.vmap`` a cond with a batched
        # predicate becomes a select whose operands, the structure's arrays among them, are copied per ray.
        return lax.while_loop(searching, lambda q: _where(q.pending_leaf[0] >= 0, _pop(q), _advance(q)), q)

    def commit_triangle_intersection(self, accept: Any = True) -> IntersectionQuery:
        """Commit the current triangle candidate (where ``accept``)."""
        ok = jnp.asarray(accept, bool) & (self.candidate_type == _TRIANGLE)
        return self._commit(ok, self.candidate_distance)

    def commit_bounding_box_intersection(self, distance: Any, accept: Any = True) -> IntersectionQuery:
        """Commit the current box candidate at ``distance`` (where ``accept`` and the distance lies between the
        ray's ``min_distance`` and the committed distance; otherwise nothing changes)."""
        distance = jnp.asarray(distance, self.ray.origin.dtype)
        ok = jnp.asarray(accept, bool) & (self.candidate_type == _BOX)
        ok &= (distance >= self.ray.t_min) & (distance <= self.state.distance)
        return self._commit(ok, distance)

    def _commit(self, ok: jax.Array, distance: jax.Array) -> IntersectionQuery:
        stop = ok & self.intersector.accept_any_intersection
        state = self.state._replace(
            distance=jnp.where(ok, distance, self.state.distance),
            leaf=jnp.where(ok, self.candidate, self.state.leaf),
            done=self.state.done | stop,
        )
        if state.hit_chain is not None:  # opaque hits found later record their chain in the state
            state = state._replace(hit_chain=jnp.where(ok, self.candidate_chain, state.hit_chain))
        pending = jnp.where(stop, -1, self.pending_leaf)
        return dataclasses.replace(self, state=state, pending_leaf=pending)

    @functools.cached_property
    def _view(self) -> SceneView:
        """The scene view, built once per query object (every accessor and step reads it)."""
        return scene_view(self.structure)

    def _chain(self, committed: bool) -> jax.Array:
        if not committed:
            return self.candidate_chain
        return self.state.hit_chain if self.state.hit_chain is not None else self.committed_chain

    def _object_ray(self, chain: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The ray moved through ``chain`` with the traversal's arithmetic (the ray its tests saw)."""
        origin, direction = self.ray.origin, self.direction
        rows = self._view.traversal.instance_world_to_object
        for level in range(chain.shape[0]):
            m = rows[jnp.maximum(chain[level], 0)]
            moved_origin = jnp.sum(m[:, :3] * origin, axis=-1) + m[:, 3]
            moved_direction = jnp.sum(m[:, :3] * direction, axis=-1)
            origin = jnp.where(chain[level] >= 0, moved_origin, origin)
            direction = jnp.where(chain[level] >= 0, moved_direction, direction)
        return origin, direction

    def _instance_ids(self, chain: jax.Array) -> jax.Array:
        """Each level's instance index within its structure (-1 past the chain)."""
        view = self._view
        if view.instances is None:
            return chain
        return jnp.where(chain >= 0, view.instances.local_index[jnp.maximum(chain, 0)], -1)

    # --- the candidate -------------------------------------------------------------------------------------

    def _kind(self, leaf: jax.Array) -> jax.Array:
        view = self._view
        types = {k.name: k.intersection_type for k in KINDS}
        kinds = [types[g.kind] for g in view.geometry_info]
        slot = view.leaves.slot[jnp.maximum(leaf, 0)]
        return jnp.where(leaf >= 0, jnp.asarray(kinds, jnp.int32)[jnp.maximum(slot, 0)], _NONE)

    @property
    def candidate_type(self) -> jax.Array:
        """``rt.IntersectionType`` of the candidate (``NONE`` without one)."""
        return self._kind(self.candidate)

    def _id(self, ids: jax.Array, leaf: jax.Array) -> jax.Array:
        """``ids`` (a leaf-ordered id array) at ``leaf``; -1 without a leaf."""
        return jnp.where(leaf >= 0, ids[jnp.maximum(leaf, 0)], -1)

    @property
    def candidate_primitive_id(self) -> jax.Array:
        return self._id(self._view.leaves.primitive, self.candidate)

    @property
    def candidate_geometry_id(self) -> jax.Array:
        return self._id(self._view.leaves.geometry, self.candidate)

    @property
    def candidate_instance_id(self) -> jax.Array:
        """``(levels,)`` the candidate's instance at each level, within its structure (-1 past the chain)."""
        return jnp.where(self.has_candidate, self._instance_ids(self.candidate_chain), -1)

    @property
    def candidate_triangle_distance(self) -> jax.Array:
        """The candidate triangle's hit distance (Metal's ``get_candidate_triangle_distance``)."""
        return jnp.where(self.candidate_type == _TRIANGLE, self.candidate_distance, jnp.inf)

    @property
    def candidate_triangle_barycentric_coord(self) -> jax.Array:
        return self._barycentrics(self.candidate, self.candidate_type == _TRIANGLE, committed=False)[0]

    @property
    def candidate_triangle_front_facing(self) -> jax.Array:
        return self._barycentrics(self.candidate, self.candidate_type == _TRIANGLE, committed=False)[1]

    @property
    def candidate_bounding_box(self) -> tuple[jax.Array, jax.Array]:
        """``(lower, upper)`` of the candidate box."""
        box = self._view.leaves.box[jnp.maximum(self.candidate, 0)]
        return box[0], box[1]

    @property
    def candidate_primitive_data(self) -> Any:
        """The candidate primitive's data pytree (``None`` for a structure without primitive data)."""
        return data_at(self._view.leaves.primitive_data, self.candidate, self.has_candidate)

    @property
    def candidate_ray(self) -> Ray:
        """The ray in the candidate's object space, with ``max_distance`` the committed distance (for box
        tests); distances are the same in every space."""
        origin, direction = self._object_ray(self.candidate_chain)
        return leaf_tests.function_ray(origin, direction, self.ray.t_min, self.state.distance)

    # --- the committed hit ---------------------------------------------------------------------------------

    @property
    def committed_type(self) -> jax.Array:
        return self._kind(self.state.leaf)

    @property
    def committed_distance(self) -> jax.Array:
        return jnp.where(self.state.leaf >= 0, self.state.distance, jnp.inf)

    @property
    def committed_primitive_id(self) -> jax.Array:
        return self._id(self._view.leaves.primitive, self.state.leaf)

    @property
    def committed_geometry_id(self) -> jax.Array:
        return self._id(self._view.leaves.geometry, self.state.leaf)

    @property
    def committed_instance_id(self) -> jax.Array:
        """``(levels,)`` the committed hit's instance at each level, within its structure (-1 past the chain)."""
        return jnp.where(self.state.leaf >= 0, self._instance_ids(self._chain(committed=True)), -1)

    @property
    def committed_triangle_barycentric_coord(self) -> jax.Array:
        return self._barycentrics(self.state.leaf, self.committed_type == _TRIANGLE, committed=True)[0]

    @property
    def committed_triangle_front_facing(self) -> jax.Array:
        return self._barycentrics(self.state.leaf, self.committed_type == _TRIANGLE, committed=True)[1]

    @property
    def committed_primitive_data(self) -> Any:
        return data_at(self._view.leaves.primitive_data, self.state.leaf, self.state.leaf >= 0)

    def _barycentrics(self, leaf: jax.Array, valid: jax.Array, committed: bool) -> tuple[jax.Array, jax.Array]:
        view = self._view
        chain = self._chain(committed)
        vertices = view.leaves.triangle[jnp.maximum(leaf, 0)]
        u, v, clockwise = triangle.barycentrics(triangle.shear_ray(*self._object_ray(chain)), vertices)
        if view.instances is not None:
            flips = jnp.prod(jnp.where(chain >= 0, view.instances.flip[jnp.maximum(chain, 0)], 1))
            clockwise = clockwise ^ (flips < 0)
        front = clockwise if self.intersector.front_facing_winding == "clockwise" else ~clockwise
        return jnp.where(valid, jnp.stack([u, v]), 0.0), valid & front


def _tester(intersector: Any, view: SceneView) -> _OpaqueLeaves:
    inner = leaf_tests.leaf_tester(intersector, view, user_code=False)
    return _OpaqueLeaves(inner, _candidate_table(view), view)


def _pop(q: IntersectionQuery) -> IntersectionQuery:
    """Take the nearest pending candidate if it is still nearer than the committed hit."""
    leaf, t = q.pending_leaf[0], q.pending_distance[0]
    valid = t <= q.state.distance
    return dataclasses.replace(
        q,
        pending_leaf=jnp.stack([q.pending_leaf[1], jnp.int32(-1)]),
        pending_distance=jnp.stack([q.pending_distance[1], jnp.inf]).astype(t.dtype),
        candidate=jnp.where(valid, leaf, -1),
        candidate_distance=jnp.where(valid, t, jnp.inf),
        candidate_chain=q.pending_chain,
    )


def _advance(q: IntersectionQuery) -> IntersectionQuery:
    """One traversal step: opaque hits are committed, candidate leaves of the node become pending."""
    s, ray = q.state, q.ray
    view = q._view
    scene, layout = view.traversal, view.layout
    levels = layout.levels
    origin, inv_direction = (s.origin, s.inv_direction) if levels else (ray.origin, ray.inv_direction)
    path = jnp.where(jnp.arange(levels) < s.level, s.chain, -1) if levels else q.pending_chain
    children = scene.node_children[s.node]
    box_hit, t_near = ray_box(
        origin, inv_direction, ray.t_min, s.distance, scene.node_lower[s.node], scene.node_upper[s.node]
    )
    primitive = (children < 0) & (-1 - children < layout.primitive_leaves)
    leaves = jnp.where(primitive & box_hit & ~s.done, -1 - children, -1)
    is_candidate = (leaves >= 0) & view.leaf_flag(_candidate_table(view), leaves)
    kinds = q._kind(leaves)
    # The candidate triangles' own test, with the facing of the level walked (as the traversal's tester).
    sheared = triangle.shear_ray(*q._object_ray(path))
    context = (sheared, select_level(s.level, jnp.ones((), jnp.int32), s.level_facing)) if levels else sheared
    triangles = leaf_tests.TriangleLeaves(view.leaves.triangle, q.intersector.cull)
    hits, accepted = triangles.test(context, leaves, ray.t_min, s.distance)
    is_candidate &= (kinds == _BOX) | accepted
    distance = jnp.where(kinds == _BOX, jnp.maximum(t_near, ray.t_min), hits.distance)
    tester = _tester(q.intersector, view)
    any_hit = q.intersector.accept_any_intersection
    state = step(scene, layout, tester, ray, s, any_hit=any_hit)
    keep = is_candidate & (distance <= state.distance) & ~(q.intersector.accept_any_intersection & (state.leaf >= 0))
    distance = jnp.where(keep, distance, jnp.inf)
    order = jnp.argsort(distance)
    return dataclasses.replace(
        q,
        state=state,
        pending_leaf=jnp.where(keep, leaves, -1)[order],
        pending_distance=distance[order],
        pending_chain=path,
    )


def _where(condition: jax.Array, a: IntersectionQuery, b: IntersectionQuery) -> IntersectionQuery:
    """``a`` where ``condition``, else ``b`` (field by field)."""
    return jax.tree_util.tree_map(lambda x, y: jnp.where(condition, x, y), a, b)


def _decided_by_the_loop(ray: Any, candidate: Any) -> Any:
    """Stands for the boxes' function when the kernel lists them: the query's loop decides each box."""
    raise NotImplementedError("an intersection query's loop decides its box candidates")


def _lister(intersector: Any, view: SceneView, rays: Any) -> Any:
    """The kernel's listing of candidates past a cursor (:func:`jaxrt._src.pipeline.wave_lister`)."""
    return wave_lister(intersector, view, rays)


def lists_with_the_kernel(intersector: Any, structure: Any) -> bool:
    """Whether a query of ``structure`` lists its candidates with the GPU kernel: where candidate waves cover
    the structure (:func:`jaxrt._src.traversal.waves.covers`) and the intersector's backend is the kernel."""
    if not isinstance(structure, PrimitiveAccelerationStructure):
        return False
    return waves.covers(structure.geometry_info, motion=structure.motion is not None) and (
        resolve_backend(intersector) == "gpu"
    )


class _ListedRay(NamedTuple):
    """One ray as the lister reads it (a batch of one)."""

    origin: jax.Array
    direction: jax.Array
    t_min: jax.Array
    mask: jax.Array


def _list(q: IntersectionQuery) -> IntersectionQuery:
    """List the next ``K`` candidates past the cursor (opaque triangles included), culled by the committed
    distance, where none is left (elsewhere the ray is disabled in the launch, and nothing changes)."""
    view, k = q._view, q.listing
    boxes = {i: _decided_by_the_loop for i, g in enumerate(view.geometry_info) if BOUNDING_BOX.holds(g)}
    lister_of = Intersector(triangle_cull_mode=q.intersector.triangle_cull_mode,
                            front_facing_winding=q.intersector.front_facing_winding,
                            intersection_functions=boxes or None)  # fmt: skip
    ray = _ListedRay(q.ray.origin[None], q.direction[None], q.ray.t_min[None], jnp.full((1,), 0xFFFFFFFF, jnp.uint32))
    needed = q.more & ~q.state.done & (q.pending_leaf[0] < 0)  # under vmap every ray passes here
    found = _lister(lister_of, view, ray)(
        k, q.state.distance[None], needed[None], q.cursor_distance[None], q.cursor_leaf[None]
    ).hits
    listed = jnp.arange(k) < jnp.minimum(found.total[0], k)
    distance = jnp.where(listed, found.distance[0], jnp.inf).astype(q.candidate_distance.dtype)
    leaf = jnp.where(listed, found.leaf[0], -1)
    more = found.total[0] > k
    return dataclasses.replace(
        q,
        pending_leaf=jnp.where(needed, leaf, q.pending_leaf),
        pending_distance=jnp.where(needed, distance, q.pending_distance),
        cursor_distance=jnp.where(needed & more, distance[k - 1], q.cursor_distance),
        cursor_leaf=jnp.where(needed & more, leaf[k - 1], q.cursor_leaf),
        more=jnp.where(needed, more, q.more),
    )


def _serve(q: IntersectionQuery) -> IntersectionQuery:
    """Take the first listed candidate if it is not past the committed hit: an opaque triangle is committed,
    anything else becomes the candidate. One past it ends the listing (the rest are farther still)."""
    leaf, t = q.pending_leaf[0], q.pending_distance[0]
    valid = (leaf >= 0) & (t <= q.state.distance)
    beyond = (leaf >= 0) & ~valid
    is_candidate = q._view.leaf_flag(_candidate_table(q._view), jnp.maximum(leaf, 0))
    opaque = valid & ~is_candidate
    state = q.state._replace(
        distance=jnp.where(opaque, t, q.state.distance),
        leaf=jnp.where(opaque, leaf, q.state.leaf),
        done=q.state.done | (opaque & q.intersector.accept_any_intersection),
    )
    chosen = valid & is_candidate
    shifted_leaf = jnp.concatenate([q.pending_leaf[1:], jnp.full((1,), -1, jnp.int32)])
    shifted_distance = jnp.concatenate([q.pending_distance[1:], jnp.full((1,), jnp.inf, t.dtype)])
    return dataclasses.replace(
        q,
        state=state,
        pending_leaf=jnp.where(beyond, -1, shifted_leaf),
        pending_distance=jnp.where(beyond, jnp.inf, shifted_distance),
        more=q.more & ~beyond,
        candidate=jnp.where(chosen, leaf, -1),
        candidate_distance=jnp.where(chosen, t, jnp.inf),
    )


def intersection_query(rays: Ray, structure: PrimitiveAccelerationStructure, intersector: Any) -> IntersectionQuery:
    """Start an intersection query of one ray (batch with ``jax.vmap``); call ``next()`` to reach the first
    candidate. The intersector supplies cull mode, winding and ``accept_any_intersection``.

    Raises:
      ValueError: ``rays`` is not a single ray, or instances nested deeper than the intersector's
        ``max_levels``.
    """
    if not isinstance(rays, Ray):
        raise TypeError(f"intersection_query: rays must be an rt.Ray, got {type(rays).__name__}")
    if rays.shape != ():
        raise ValueError(
            f"intersection_query: a query traces one ray (shape ()), got a batch of shape {rays.shape}; "
            "build the query inside jax.vmap over the rays"
        )
    if not isinstance(intersector, Intersector):
        raise TypeError(f"intersection_query: intersector must be an rt.Intersector, got {type(intersector).__name__}")
    if not isinstance(structure, PrimitiveAccelerationStructure | InstanceAccelerationStructure):
        raise TypeError(
            f"intersection_query: structure must be an acceleration structure, got {type(structure).__name__}"
        )
    _check_levels(intersector, structure)
    moving = isinstance(structure, InstanceAccelerationStructure) and structure.has_instance_motion
    if moving or any(s.motion is not None for s in primitive_structures(structure)):
        raise NotImplementedError(
            "intersection_query: structures with keyframe motion are traced with Intersector.intersect; the "
            "query does not blend keyframes at the ray's time"
        )
    ray = sanitized_rays(rays)
    origin, direction = ray.origin, ray.direction
    view = scene_view(structure)
    constants, state = start(
        _tester(intersector, view), view.layout, origin, direction, ray.t_min, ray.t_max, ray.enabled, ray.mask
    )
    no_chain = jnp.full((view.levels,), -1, jnp.int32)
    listing = KERNEL_CANDIDATES if lists_with_the_kernel(intersector, structure) else 0
    pending = listing or 2
    return IntersectionQuery(
        ray=constants,
        direction=direction,
        state=state,
        pending_leaf=jnp.full((pending,), -1, jnp.int32),
        pending_distance=jnp.full((pending,), jnp.inf, origin.dtype),
        pending_chain=no_chain,
        candidate=jnp.int32(-1),
        candidate_distance=jnp.asarray(jnp.inf, origin.dtype),
        candidate_chain=no_chain,
        committed_chain=no_chain,
        cursor_distance=jnp.asarray(-jnp.inf, origin.dtype),
        cursor_leaf=jnp.int32(-1),
        more=~state.done,
        intersector=intersector,
        held=_Held(structure),
        listing=listing,
    )
