"""Candidate waves: user intersection functions and filters behind the GPU kernel.

A Triton kernel cannot call JAX code, and a user's intersection function or filter is JAX code. So the kernel
and JAX take turns, inside one ``lax.while_loop`` (no host round trip):

1. **List.** The kernel traces every ray that still needs candidates and keeps its ``K`` first *candidates
   past its cursor*, in ``(distance, leaf)`` order: triangle hits (opaque or not, culled as the intersector
   says), built-in analytic hits, and the box leaves of user functions at the box's entry distance (the slab
   test's, clamped to ``t_min``). It is the kernel's ``max_hits = K`` list with the cursor test and a leaf
   tie order (``gpu.trace_scene(cursor=...)``).
2. **Decide.** JAX runs the portable leaf tests (:func:`jaxrt._src.leaves.leaf_tester`: the watertight test
   and the filter on non-opaque triangles, each box's intersection function) on the ``K`` candidates of
   every ray at once, with the ray's current bound as ``max_distance``, and merges the accepted ones into
   the ray's hits (stable by distance: earlier candidates win ties, as the first hit found does in the
   portable traversal).
3. **Go on.** A ray needs another wave only where its list was full (more candidates exist) and the last
   listed candidate is not past its bound: its cursor moves to that candidate. An any-hit query stops at its
   first accepted hit; counting never lowers the bound.

The order of candidates depends on the geometry alone, not on the traversal, so every candidate is tested
exactly once, and the result is the portable traversal's: the nearest accepted hit (a box's hit is at or
beyond its entry distance, so boxes entered past the bound cannot improve it), the ``K`` nearest with their
count for ``max_hits``, every accepted hit for counting. Ties between equally distant accepted hits may
resolve differently (the portable traversal keeps the first one it meets), as in the 4-wide kernel.

A wave re-traces from the root rather than resuming a saved stack: nothing per ray but the cursor is kept
between waves, and with ``K`` candidates a wave most rays need only one (see docs/custom_geometry.md).
"""

from __future__ import annotations

import os
from typing import Any

import jax
import jax.numpy as jnp
from jax import lax

from jaxrt._src import leaves as leaf_tests
from jaxrt._src.traversal import step
from jaxrt._src.traversal.scene import TraversalResult
from jaxrt._src.traversal.step import HitList

__all__ = ["CANDIDATES", "needs_waves", "trace_waves"]

#: Candidates listed per ray and wave (the kernel's ``max_hits``); ``JAXRT_WAVE_CANDIDATES`` (read at import)
#: overrides it for benches.
CANDIDATES = int(os.environ.get("JAXRT_WAVE_CANDIDATES", "4"))


def needs_waves(intersector: Any, view: Any) -> bool:
    """Whether tracing ``view`` with ``intersector`` calls user code per candidate: a filter on non-opaque
    triangles, or a bounding-box function that is not one of the built-in ``rt.intersection_functions``."""
    from jaxrt._src.primitives import analytic

    if leaf_tests.filtered_slots(intersector, view):
        return True
    if "bounding_box" not in view.kinds:
        return False
    functions = intersector.intersection_functions or ()
    return any(not analytic.shape_code(fn) for _, fn in functions)


def trace_waves(
    intersector: Any,
    view: Any,
    rays: Any,
    list_candidates: Any,
    *,
    candidates: int,
) -> TraversalResult:
    """The portable traversal's result for ``rays`` (a ``SanitizedRays``, detached) through the primitive
    structure of ``view``, in candidate waves.

    Args:
      intersector: its filter, intersection functions, cull mode and query (nearest, any, ``max_hits``,
        counting) decide.
      view: the scene view (a primitive structure without keyframe motion).
      rays: the flat ray batch.
      list_candidates: ``(t_max, enabled, cursor_t, cursor_leaf) -> TraversalResult`` whose ``hits`` are each
        ray's ``candidates`` first candidates past its cursor (the kernel's wave).
      candidates: static ``K``.
    """
    tester = leaf_tests.leaf_tester(intersector, view)
    origin, direction, t_min = (lax.stop_gradient(a) for a in (rays.origin, rays.direction, rays.t_min))
    n = origin.shape[0]
    k = candidates
    count_all = bool(intersector.counts_all)
    kept = 1 if intersector.max_hits is None or count_all else int(intersector.max_hits)
    listing = intersector.max_hits is not None and not count_all
    any_hit = bool(intersector.accept_any_intersection)
    dtype = rays.t_max.dtype
    start = jnp.where(rays.enabled, lax.stop_gradient(rays.t_max), -jnp.inf).astype(dtype)

    def bound_of(hit_t, total):
        if count_all:
            return start
        if listing:  # the portable list culls by the K-th distance once more than K hits are known
            return jnp.where(total > kept, hit_t[:, kept - 1], start)
        return jnp.where(total > 0, hit_t[:, 0], start)

    def decide(leaves, valid, bound):
        def one(origin, direction, t_min, t_max, leaf):
            context = step.prepare(tester, origin, direction, None, None)
            return tester(context, leaf, t_min, t_max)

        ok, t = jax.vmap(one)(origin, direction, t_min, bound, jnp.where(valid, leaves, -1))
        ok = ok & valid
        return ok, jnp.where(ok, t, jnp.inf).astype(dtype)

    def body(state):
        hit_t, hit_leaf, total, cursor_t, cursor_leaf, active, visited, tested, waves = state
        bound = bound_of(hit_t, total)
        found = list_candidates(bound, active, cursor_t, cursor_leaf)
        listed = found.hits
        index = jnp.arange(k)
        valid = active[:, None] & (index[None, :] < jnp.minimum(listed.total, k)[:, None])
        ok, t = decide(listed.leaf, valid, bound)
        total = total + jnp.sum(ok, axis=1, dtype=jnp.int32)
        if not count_all:  # merge: earlier hits first, then this wave's in candidate order (a stable sort)
            all_t = jnp.concatenate([hit_t, t], axis=1)
            all_leaf = jnp.concatenate([hit_leaf, jnp.where(ok, listed.leaf, -1)], axis=1)
            order = jnp.argsort(all_t, axis=1, stable=True)[:, :kept]
            hit_t = jnp.take_along_axis(all_t, order, axis=1)
            hit_leaf = jnp.take_along_axis(all_leaf, order, axis=1)
        last_t, last_leaf = listed.distance[:, k - 1], listed.leaf[:, k - 1]
        more = active & (listed.total > k) & (last_t <= bound_of(hit_t, total))
        if any_hit:
            more = more & (total == 0)
        cursor_t = jnp.where(more, last_t, cursor_t)
        cursor_leaf = jnp.where(more, last_leaf, cursor_leaf)
        visited = visited + jnp.where(active, found.nodes_visited, 0)
        tested = tested + jnp.where(active, found.primitives_tested, 0)
        return hit_t, hit_leaf, total, cursor_t, cursor_leaf, more, visited, tested, waves + 1

    zeros = jnp.zeros((n,), jnp.int32)
    state = (
        jnp.full((n, kept), jnp.inf, dtype),
        jnp.full((n, kept), -1, jnp.int32),
        zeros,
        jnp.full((n,), -jnp.inf, dtype),
        jnp.full((n,), -1, jnp.int32),
        rays.enabled,
        zeros,
        zeros,
        jnp.zeros((), jnp.int32),
    )
    hit_t, hit_leaf, total, *_, visited, tested, _ = lax.while_loop(lambda s: jnp.any(s[5]), body, state)
    overflow = jnp.zeros((n,), bool)
    levels = jnp.zeros((n, 0), jnp.int32)
    if count_all:
        hits = HitList(jnp.zeros((n, 0), dtype), jnp.zeros((n, 0), jnp.int32), total)
        return TraversalResult(start, jnp.full((n,), -1, jnp.int32), levels, visited, tested, overflow, hits)
    distance = jnp.where(total > 0, hit_t[:, 0], start) if not listing else bound_of(hit_t, total)
    hits = HitList(hit_t, hit_leaf, total) if listing else None
    return TraversalResult(distance, hit_leaf[:, 0], levels, visited, tested, overflow, hits)
