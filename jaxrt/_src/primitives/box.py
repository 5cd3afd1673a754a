"""Conservative ray/box slab test (Ize 2013).

Reference: Ize, "Robust BVH Ray Traversal", JCGT 2(2), 2013: with the reciprocal direction rounded once, the
far slab distance scaled by ``1 + 2 * gamma(3)`` bounds the rounding of the subtraction, the product and the
reciprocal, so no box the exact ray passes through is missed. Direction components are clamped away from
zero before the reciprocal (:func:`jaxrt._src.numerics.safe_reciprocal`), so axis-parallel rays and rays
starting on a slab plane produce no NaN.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxrt._src.numerics import RECIPROCAL_CLAMP, gamma

FAR_SCALE = 1.0 + 2.0 * gamma(3)
#: Reciprocals at least this large come from clamped (zero) direction components (see ``safe_reciprocal``).
PARALLEL_RECIPROCAL = 0.5 / RECIPROCAL_CLAMP


def ray_box(
    origin: jax.Array, inv_direction: jax.Array, t_min: jax.Array, t_max: jax.Array, lower: jax.Array, upper: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Whether a ray overlaps boxes within ``[t_min, t_max]``, and the entry distance.

    Args:
      origin, inv_direction: ``(3,)`` ray origin and safe reciprocal direction.
      t_min, t_max: scalars, the ray's distance interval.
      lower, upper: ``(..., 3)`` boxes; an empty box (+inf, -inf) never overlaps.

    Returns:
      ``hit`` (bool) and ``t_near`` (entry distance, clamped to ``t_min``), both of shape ``(...)``.
    """
    t0 = (lower - origin) * inv_direction
    t1 = (upper - origin) * inv_direction
    # A zero direction component (its reciprocal clamped) keeps the ray at one coordinate: the slab holds all
    # of the ray when the origin is in [lower, upper], boundary included, and none of it otherwise. The
    # clamped reciprocal alone would make a ray lying in a slab plane leave the slab at t = 0 (it acts like
    # a tiny component of the zero's sign), and miss primitives on that face of the box.
    parallel = jnp.abs(inv_direction) >= PARALLEL_RECIPROCAL
    inside = (lower <= origin) & (origin <= upper)
    near = jnp.where(parallel, jnp.where(inside, -jnp.inf, jnp.inf), jnp.minimum(t0, t1))
    far = jnp.where(parallel, jnp.where(inside, jnp.inf, -jnp.inf), jnp.maximum(t0, t1))
    t_near = jnp.maximum(jnp.max(near, axis=-1), t_min)
    t_far = jnp.minimum(jnp.min(far, axis=-1) * FAR_SCALE, t_max)
    # An empty box (lower > upper) would pass the slab test: its slabs swap to (-inf, inf).
    return (t_near <= t_far) & (lower[..., 0] <= upper[..., 0]), t_near
