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

from jaxrt._src.numerics import gamma

FAR_SCALE = 1.0 + 2.0 * gamma(3)


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
    t_near = jnp.maximum(jnp.max(jnp.minimum(t0, t1), axis=-1), t_min)
    t_far = jnp.minimum(jnp.min(jnp.maximum(t0, t1), axis=-1) * FAR_SCALE, t_max)
    # An empty box (lower > upper) would pass the slab test: its slabs swap to (-inf, inf).
    return (t_near <= t_far) & (lower[..., 0] <= upper[..., 0]), t_near
