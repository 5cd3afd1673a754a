"""Candidate waves: user intersection functions and filters behind the GPU kernel.

A Triton kernel cannot call JAX code, and a user's intersection function or filter is JAX code. So the kernel
and JAX take turns, inside one ``lax.while_loop`` (no host round trip):

1. **List.** The kernel traces every ray that still needs candidates and keeps its ``K`` first *candidates
   past its cursor*, in ``(distance, leaf)`` order: triangle hits (opaque or not, culled as the intersector
   says), built-in analytic hits, and the box leaves of user functions at the box's entry distance (the slab
   test's, clamped to ``t_min``). It is the kernel's ``max_hits = K`` list with the cursor test and a leaf
   tie order (``gpu.trace_scene(cursor=...)``).
2. **Decide.** JAX runs the portable leaf tests (the caller's tester, :func:`jaxrt._src.leaves.leaf_tester`: the watertight test
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
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from jaxrt._src.kinds import registry
from jaxrt._src.kinds.bounding_box import builtin
from jaxrt._src.traversal import step
from jaxrt._src.traversal.scene import TraversalResult
from jaxrt._src.traversal.step import HitList

__all__ = [
    "CANDIDATES",
    "LATER_CANDIDATES",
    "WaveLoop",
    "WaveState",
    "covers",
    "needs_waves",
    "trace_waves",
    "user_functions",
]


def _candidate_counts(setting: str) -> tuple[int, int]:
    """``"K"`` or ``"K,LATER"`` as ``(K, LATER)`` (``LATER = K`` when it is not given)."""
    counts = [int(part) for part in setting.split(",")]
    return counts[0], counts[-1]


#: Candidates listed per ray in the first wave (the kernel's ``max_hits``), and in each later one: few rays
#: need those, and more candidates per wave end the tail in fewer waves. ``JAXRT_WAVE_CANDIDATES`` (``K`` or
#: ``K,LATER``, read at import) overrides them for benches.
CANDIDATES, LATER_CANDIDATES = _candidate_counts(os.environ.get("JAXRT_WAVE_CANDIDATES", "4,16"))


def covers(geometry_info: tuple, *, motion: bool = False, levels: int = 0) -> bool:
    """Whether the GPU kernel lists candidates for a scene of these geometries: a static (no keyframe motion,
    ``motion`` nor any geometry's) primitive structure (``levels == 0``) whose kinds waves list
    (:func:`jaxrt._src.kinds.registry.waves_cover`)."""
    return registry.waves_cover(geometry_info, "gpu", motion=motion, levels=levels)


def user_functions(intersector: Any) -> bool:
    """Whether some intersection function of ``intersector`` is user code (not a built-in shape)."""
    return any(not builtin(fn) for _, fn in intersector.intersection_functions or ())


def needs_waves(intersector: Any, view: Any, *, filter_decided: bool = False) -> bool:
    """Whether tracing ``view`` with ``intersector`` calls user code per candidate
    (:func:`jaxrt._src.kinds.registry.needs_jax`): a filter on non-opaque triangles (unless ``filter_decided``:
    decided per primitive, :mod:`jaxrt._src.filter_states`), or a bounding-box function that is not one of the
    built-in ``rt.intersection_functions``."""
    return registry.needs_jax(intersector, view.geometry_info, filter_decided=filter_decided)


class WaveState(NamedTuple):
    """The loop state of every ray between waves."""

    hit_t: jax.Array  # (n, kept) accepted distances so far, sorted (inf past the last)
    hit_leaf: jax.Array  # (n, kept) their leaves (-1 past the last)
    total: jax.Array  # (n,) accepted hits so far
    cursor_t: jax.Array  # (n,) the last candidate listed: distance
    cursor_leaf: jax.Array  # (n,) and leaf
    active: jax.Array  # (n,) the ray needs another wave
    visited: jax.Array  # (n,) nodes visited over all waves
    tested: jax.Array  # (n,) primitives tested over all waves


class WaveLoop:
    """One batch of rays in candidate waves: :meth:`initial`, :meth:`wave` (any number of times, each with
    its own ``K``) and :meth:`result`; :func:`trace_waves` composes them. ``tester``: the portable leaf tests
    of the scene (:func:`jaxrt._src.leaves.leaf_tester`), which take the decisions."""

    def __init__(self, intersector: Any, tester: Any, rays: Any, list_candidates: Callable):
        self.tester = tester
        self.origin, self.direction, self.t_min = (
            lax.stop_gradient(a) for a in (rays.origin, rays.direction, rays.t_min)
        )
        self.enabled = rays.enabled
        self.list_candidates = list_candidates
        self.count_all = bool(intersector.counts_all)
        self.listing = intersector.max_hits is not None and not self.count_all
        self.kept = int(intersector.max_hits) if self.listing else 1
        self.any_hit = bool(intersector.accept_any_intersection)
        self.dtype = rays.t_max.dtype
        self.start = jnp.where(rays.enabled, lax.stop_gradient(rays.t_max), -jnp.inf).astype(self.dtype)

    def initial(self) -> WaveState:
        n, dtype = self.origin.shape[0], self.dtype
        zeros = jnp.zeros((n,), jnp.int32)
        return WaveState(
            jnp.full((n, self.kept), jnp.inf, dtype),
            jnp.full((n, self.kept), -1, jnp.int32),
            zeros,
            jnp.full((n,), -jnp.inf, dtype),
            jnp.full((n,), -1, jnp.int32),
            self.enabled,
            zeros,
            zeros,
        )

    def bound(self, hit_t: jax.Array, total: jax.Array) -> jax.Array:
        """Each ray's distance bound: its nearest accepted hit (the ``kept``-th once more are known, as the
        portable hit list culls; never lowered when counting)."""
        if self.count_all:
            return self.start
        if self.listing:
            return jnp.where(total > self.kept, hit_t[:, self.kept - 1], self.start)
        return jnp.where(total > 0, hit_t[:, 0], self.start)

    def _decide(self, leaves: jax.Array, valid: jax.Array, bound: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The portable leaf tests (filter, intersection functions) on each ray's listed candidates."""
        tester = self.tester

        def one(origin, direction, t_min, t_max, leaf):
            return tester(step.prepare(tester, origin, direction, None, None), leaf, t_min, t_max)

        ok, t = jax.vmap(one)(self.origin, self.direction, self.t_min, bound, jnp.where(valid, leaves, -1))
        ok = ok & valid
        return ok, jnp.where(ok, t, jnp.inf).astype(self.dtype)

    def wave(self, state: WaveState, k: int) -> WaveState:
        """List ``k`` candidates per active ray, decide them, merge, and move the cursors."""
        bound = self.bound(state.hit_t, state.total)
        found = self.list_candidates(k, bound, state.active, state.cursor_t, state.cursor_leaf)
        listed = found.hits
        valid = state.active[:, None] & (jnp.arange(k)[None, :] < jnp.minimum(listed.total, k)[:, None])
        ok, t = self._decide(listed.leaf, valid, bound)
        total = state.total + jnp.sum(ok, axis=1, dtype=jnp.int32)
        hit_t, hit_leaf = state.hit_t, state.hit_leaf
        if not self.count_all:  # merge: earlier hits first, then this wave's in candidate order (a stable sort)
            all_t = jnp.concatenate([hit_t, t], axis=1)
            all_leaf = jnp.concatenate([hit_leaf, jnp.where(ok, listed.leaf, -1)], axis=1)
            order = jnp.argsort(all_t, axis=1, stable=True)[:, : self.kept]
            hit_t = jnp.take_along_axis(all_t, order, axis=1)
            hit_leaf = jnp.take_along_axis(all_leaf, order, axis=1)
        last_t, last_leaf = listed.distance[:, k - 1], listed.leaf[:, k - 1]
        more = state.active & (listed.total > k) & (last_t <= self.bound(hit_t, total))
        if self.any_hit:
            more = more & (total == 0)
        return WaveState(
            hit_t,
            hit_leaf,
            total,
            jnp.where(more, last_t, state.cursor_t),
            jnp.where(more, last_leaf, state.cursor_leaf),
            more,
            state.visited + jnp.where(state.active, found.nodes_visited, 0),
            state.tested + jnp.where(state.active, found.primitives_tested, 0),
        )

    def result(self, state: WaveState) -> TraversalResult:
        """The portable traversal's :class:`TraversalResult` of the accepted hits."""
        n = state.total.shape[0]
        overflow = jnp.zeros((n,), bool)
        levels = jnp.zeros((n, 0), jnp.int32)
        if self.count_all:
            hits = HitList(jnp.zeros((n, 0), self.dtype), jnp.zeros((n, 0), jnp.int32), state.total)
            no_leaf = jnp.full((n,), -1, jnp.int32)
            return TraversalResult(self.start, no_leaf, levels, state.visited, state.tested, overflow, hits)
        if self.listing:  # the result's distance is the list's bound, as in the portable traversal
            distance, hits = self.bound(state.hit_t, state.total), HitList(state.hit_t, state.hit_leaf, state.total)
        else:
            distance, hits = jnp.where(state.total > 0, state.hit_t[:, 0], self.start), None
        return TraversalResult(distance, state.hit_leaf[:, 0], levels, state.visited, state.tested, overflow, hits)


def trace_waves(
    intersector: Any,
    tester: Any,
    rays: Any,
    list_candidates: Callable,
    *,
    candidates: int,
    later: int,
) -> TraversalResult:
    """The portable traversal's result for ``rays`` (:class:`~jaxrt._src.traversal.scene.TraversalRays`) through a primitive structure, in
    candidate waves: the first with ``candidates`` per ray, the rest (few rays) with ``later``.

    Args:
      intersector: its filter, intersection functions, cull mode and query (nearest, any, ``max_hits``,
        counting) decide.
      tester: the portable leaf tests of the scene (a primitive structure without keyframe motion), which
        take the decisions (:func:`jaxrt._src.leaves.leaf_tester`).
      rays: the flat ray batch.
      list_candidates: ``(K, t_max, enabled, cursor_t, cursor_leaf) -> TraversalResult`` whose ``hits`` are
        each ray's ``K`` first candidates past its cursor (the kernel's wave; ``K`` static).
      candidates, later: static ``K`` of the first wave and of the others.
    """
    loop = WaveLoop(intersector, tester, rays, list_candidates)
    state = loop.wave(loop.initial(), candidates)
    state = lax.while_loop(lambda s: jnp.any(s.active), lambda s: loop.wave(s, later), state)
    return loop.result(state)
