"""A driver for per-point tree walks: a fixed window of lanes refilled with new points as old ones end.

A vmapped ``lax.while_loop`` runs every lane until the slowest point of the batch ends; point queries vary
more than rays (a point deep inside a closed mesh opens most of the tree), so, as the ray traversal's refill
driver (:mod:`jaxrt._src.traversal.drivers`, after Aila and Laine's persistent threads, 2009), lanes whose
walk ended take the next point of a queue every few steps. Points are queued along a Morton curve so that
neighbouring lanes walk similar paths.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from jax import lax

__all__ = ["in_morton_order", "lanes_for_backend", "morton_order", "walk_points"]



def lanes_for_backend(cpu_lanes: int, gpu_lanes: int = 1 << 18) -> int:
    """Lanes in flight for the default JAX backend: a small window that stays in cache on the CPU, a wide one on
    accelerators, where a step over few lanes is all launch overhead."""
    return cpu_lanes if jax.default_backend() == "cpu" else gpu_lanes

def _spread(x: jax.Array) -> jax.Array:
    """The low 10 bits of ``x`` spread to every third bit."""
    x = (x | (x << 16)) & 0x030000FF
    x = (x | (x << 8)) & 0x0300F00F
    x = (x | (x << 4)) & 0x030C30C3
    return (x | (x << 2)) & 0x09249249


def morton_order(points: jax.Array) -> jax.Array:
    """The permutation that sorts ``points (n, 3)`` along a 30-bit Morton curve over their bounding box."""
    lo, hi = jnp.min(points, axis=0), jnp.max(points, axis=0)
    extent = hi - lo
    scale = jnp.where(extent > 0, 1023.0 / jnp.where(extent > 0, extent, 1), 0)
    cell = jnp.clip((points - lo) * scale, 0, 1023).astype(jnp.uint32)
    codes = (_spread(cell[:, 0]) << 2) | (_spread(cell[:, 1]) << 1) | _spread(cell[:, 2])
    return jnp.argsort(codes)


def in_morton_order(walk: Callable[[jax.Array], jax.Array], points: jax.Array) -> jax.Array:
    """``walk(points)`` (one result row per point) on the points sorted along a Morton curve, its results put back
    in the given order; points with a NaN or infinite coordinate sort anywhere."""
    finite = jnp.all(jnp.isfinite(points), axis=-1, keepdims=True)
    order = morton_order(jnp.where(finite, points, 0))
    out = walk(points[order])
    return jnp.zeros_like(out).at[order].set(out)


def _select(mask: jax.Array, new: Any, old: Any) -> Any:
    return jax.tree_util.tree_map(lambda a, b: jnp.where(mask.reshape(-1, *([1] * (b.ndim - 1))), a, b), new, old)


def walk_points(
    points: jax.Array,
    start: Callable[[jax.Array], Any],
    step: Callable[[jax.Array, Any], Any],
    done: Callable[[Any], jax.Array],
    output: Callable[[Any], Any],
    *,
    lanes: int = 1024,
    steps_per_refill: int = 4,
) -> Any:
    """Walk every point of ``points (n, 3)`` to the end; returns ``output`` of each final state, in order.

    Args:
      start: ``point -> state`` (one lane). step: ``(point, state) -> state``; a state for which ``done``
        holds must step to itself. output: ``state -> pytree`` of per-point results.
      lanes: points in flight at a time. steps_per_refill: steps between refills.
    """
    n = points.shape[0]
    order = morton_order(points)
    queue = points[order]
    width = min(lanes, n)
    vstart, vstep = jax.vmap(start), jax.vmap(step)
    vdone, voutput = jax.vmap(done), jax.vmap(output)
    lane_point = jnp.arange(width, dtype=jnp.int32)
    state = vstart(queue[:width])
    out = jax.tree_util.tree_map(lambda a: jnp.zeros((n, *a.shape[1:]), a.dtype), voutput(state))

    def body(carry):
        lane_point, state, next_point, out = carry
        p = queue[jnp.maximum(lane_point, 0)]
        state = lax.fori_loop(0, steps_per_refill, lambda _, s: vstep(p, s), state)
        retire = vdone(state) & (lane_point >= 0)
        target = jnp.where(retire, lane_point, n)
        out = jax.tree_util.tree_map(lambda o, v: o.at[target].set(v, mode="drop"), out, voutput(state))
        new_point = next_point + jnp.cumsum(retire, dtype=jnp.int32) - 1
        fresh = retire & (new_point < n)
        lane_point = jnp.where(retire, jnp.where(fresh, new_point, -1), lane_point)
        state = _select(fresh, vstart(queue[jnp.clip(new_point, 0, n - 1)]), state)
        next_point = jnp.minimum(next_point + jnp.sum(retire, dtype=jnp.int32), n)
        return lane_point, state, next_point, out

    carry = (lane_point, state, jnp.int32(width), out)
    *_, out = lax.while_loop(lambda c: jnp.any(c[0] >= 0), body, carry)
    inverse = jnp.zeros((n,), jnp.int32).at[order].set(jnp.arange(n, dtype=jnp.int32))
    return jax.tree_util.tree_map(lambda a: a[inverse], out)
