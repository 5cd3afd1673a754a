"""30-bit Morton codes (10 bits per axis) of box centroids.

Reference: Karras, "Maximizing Parallelism in the Construction of BVHs, Octrees, and k-d Trees", HPG 2012,
section 4 (the same quantisation and bit interleaving).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

MORTON_BITS = 30
#: Code of padding slots: above every 30-bit code, so padding sorts after all real primitives.
PADDING_CODE = 0xFFFFFFFF


def _spread_bits(x: jax.Array) -> jax.Array:
    """Insert two zero bits after each of the 10 low bits of ``x`` (uint32)."""
    x = (x * jnp.uint32(0x00010001)) & jnp.uint32(0xFF0000FF)
    x = (x * jnp.uint32(0x00000101)) & jnp.uint32(0x0F00F00F)
    x = (x * jnp.uint32(0x00000011)) & jnp.uint32(0xC30C30C3)
    x = (x * jnp.uint32(0x00000005)) & jnp.uint32(0x49249249)
    return x


def morton_codes(lower: jax.Array, upper: jax.Array, valid: jax.Array) -> jax.Array:
    """Morton code of each box centroid, quantised in the bounds of the valid centroids.

    Args:
      lower, upper: ``(N, 3)`` primitive boxes.
      valid: ``(N,)`` bool; invalid (padding) slots get :data:`PADDING_CODE`, and so do slots whose
        centroid is not finite (an empty box, or a NaN coordinate inside ``jit``), which would otherwise make
        the scene bounds, and so every code, NaN.

    Returns:
      ``(N,)`` uint32 codes.
    """
    centroid = 0.5 * (lower + upper)
    valid = valid & jnp.all(jnp.isfinite(centroid), axis=-1)
    centroid = jnp.where(valid[:, None], centroid, 0.0)
    big = jnp.finfo(centroid.dtype).max
    scene_lo = jnp.min(jnp.where(valid[:, None], centroid, big), axis=0)
    scene_hi = jnp.max(jnp.where(valid[:, None], centroid, -big), axis=0)
    extent = scene_hi - scene_lo
    scale = jnp.where(extent > 0, 1024.0 / jnp.where(extent > 0, extent, 1.0), 0.0)
    q = jnp.clip(jnp.floor((centroid - scene_lo) * scale), 0, 1023).astype(jnp.uint32)
    code = (_spread_bits(q[:, 0]) << 2) | (_spread_bits(q[:, 1]) << 1) | _spread_bits(q[:, 2])
    return jnp.where(valid, code, jnp.uint32(PADDING_CODE))
