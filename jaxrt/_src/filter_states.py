"""Filters that read only the primitive, decided once per primitive instead of once per candidate.

OptiX's opacity micromaps and DirectX's opacity states mark primitives (or parts of them) as opaque or
transparent ahead of traversal, so that any-hit code runs only where the answer depends on the hit. jaxrt does
this at primitive granularity, automatically: when the intersector's filter reads only a candidate's primitive
id, geometry id and primitive data, never its distance, barycentrics or facing (:func:`reads_only_primitive`
follows the filter's jaxpr), its decision for every non-opaque primitive is computed once per traced call
(:func:`rejected_leaves`), and the GPU kernel sees accepted primitives as opaque and rejected ones as absent.
The decisions are the filter's own, so the results are those of calling it per candidate. A filter that reads
the hit (a texture looked up at the barycentrics, say) is called per candidate in waves
(:mod:`jaxrt._src.traversal.waves`).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from jax import lax

from jaxrt._src import leaves as leaf_tests
from jaxrt._src.candidate import TriangleCandidate
from jaxrt._src.primitive_data import data_at

__all__ = ["reads_only_primitive", "rejected_leaves"]


def _candidate(view: Any, leaf: jax.Array, data: Any) -> TriangleCandidate:
    """Leaf ``leaf``'s candidate with a placeholder hit (distance 0, barycentrics 0, back facing)."""
    leaves = view.leaves
    dtype = leaves.triangle.dtype
    k = jnp.maximum(leaf, 0)
    return TriangleCandidate(
        leaves.primitive[k],
        leaves.geometry[k],
        jnp.zeros((), dtype),
        jnp.zeros((2,), dtype),
        jnp.zeros((), bool),
        data_at(data, k),
    )


def reads_only_primitive(filter_fn: Any, candidate: TriangleCandidate) -> bool:
    """Whether ``filter_fn``'s decision can depend on nothing but the candidate's primitive id, geometry id
    and primitive data: no output of its jaxpr is computed from the distance, the barycentrics or the facing.

    Conservative: an equation with any such input taints all its outputs (also calls, loops and conditionals,
    whose bodies are not followed), so "no" may be answered for a filter that ignores them.
    """
    hit_fields = (candidate.distance, candidate.barycentric_coord, candidate.front_facing)
    rest = (candidate.primitive_id, candidate.geometry_id, candidate.primitive_data)

    def decide(hit, other):
        distance, barycentric, front = hit
        primitive, geometry, data = other
        return filter_fn(TriangleCandidate(primitive, geometry, distance, barycentric, front, data))

    closed = jax.make_jaxpr(decide)(hit_fields, rest)
    jaxpr = closed.jaxpr
    tainted = {id(v) for v in jaxpr.invars[: len(jax.tree_util.tree_leaves(hit_fields))]}
    for eqn in jaxpr.eqns:
        if any(id(v) in tainted for v in eqn.invars if _is_variable(v)):
            tainted.update(id(v) for v in eqn.outvars)
    return not any(id(v) in tainted for v in jaxpr.outvars if _is_variable(v))


def _is_variable(atom: Any) -> bool:
    """A jaxpr variable (a literal carries its value)."""
    return not hasattr(atom, "val")


def rejected_leaves(intersector: Any, view: Any) -> jax.Array | None:
    """``(P,)`` bool: the primitive leaves the filter rejects (non-opaque geometry only), or ``None`` when the
    intersector has no filter on non-opaque geometry or its filter reads the hit."""
    slots = leaf_tests.filtered_slots(intersector, view)
    if not slots:
        return None
    data = jax.tree_util.tree_map(lax.stop_gradient, view.leaves.primitive_data)
    if not reads_only_primitive(intersector.filter, _candidate(view, jnp.zeros((), jnp.int32), data)):
        return None
    count = view.leaves.geometry.shape[0]
    leaves = jnp.arange(count, dtype=jnp.int32)
    filtered = view.leaf_flag(view.slot_table(slots), leaves)
    accept = jax.vmap(lambda k: jnp.asarray(intersector.filter(_candidate(view, k, data)), bool))(leaves)
    return filtered & ~accept
