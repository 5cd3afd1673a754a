"""Robustness helpers: each names the failure it prevents.

References:
  Ize, "Robust BVH Ray Traversal", JCGT 2(2), 2013.
  Woop, Benthin, Wald, "Watertight Ray/Triangle Intersection", JCGT 2(1), 2013.
  Wächter, Binder, "A Fast and Robust Method for Avoiding Self-Intersection", Ray Tracing Gems, ch. 6, 2019.
  Pharr, Jakob, Humphreys, "Physically Based Rendering", 4th ed., section 6.8 (``gamma(n)`` bounds).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp

__all__ = ["gamma", "safe_reciprocal", "offset_ray_origin", "full_precision", "RECIPROCAL_CLAMP"]

#: Smallest magnitude a direction component is clamped to before taking its reciprocal. It is above the
#: float32 normal range (1.2e-38), so the reciprocal (at most 1e35) is finite and never flushed to zero.
RECIPROCAL_CLAMP = 1e-35


def gamma(n: int, dtype=jnp.float32) -> float:
    """Bound ``n * eps / (1 - n * eps)`` on the relative error of ``n`` chained float operations.

    ``eps`` is half the machine epsilon of ``dtype`` (the unit roundoff), as in PBRT's ``gamma(n)``.
    """
    eps = float(jnp.finfo(dtype).eps) * 0.5
    return n * eps / (1.0 - n * eps)


def safe_reciprocal(x: jax.Array) -> jax.Array:
    """``1 / x`` with ``|x|`` clamped to ``[RECIPROCAL_CLAMP, 1 / RECIPROCAL_CLAMP]``, keeping the sign of ``x``.

    Prevents: ``inf`` reciprocals of zero direction components, whose product with a zero slab offset
    (a ray starting on a slab plane) is NaN in the slab test; and, at the other end, reciprocals of huge
    components that are subnormal and flushed to zero. The result is always finite and non-zero.
    Gradient: that of ``1/x`` inside the clamp range, zero where the clamp is active.
    """
    sign = jnp.where(jnp.signbit(x), -1.0, 1.0).astype(x.dtype)
    magnitude = jnp.abs(x)
    x = jnp.where(magnitude < RECIPROCAL_CLAMP, sign * RECIPROCAL_CLAMP, x)
    x = jnp.where(magnitude > 1.0 / RECIPROCAL_CLAMP, sign / RECIPROCAL_CLAMP, x)
    return 1.0 / x


def offset_ray_origin(point: jax.Array, normal: jax.Array) -> jax.Array:
    """Move ``point`` off a surface along ``normal`` so a secondary ray cannot re-hit that surface.

    Wächter & Binder 2019: the offset is a fixed number of float ULPs (integer arithmetic on the bit
    pattern) away from the origin, and a small absolute offset near the origin, so it scales with the
    rounding error of the hit point wherever it is. Pass the normal on the side the new ray leaves from
    (flip it for transmission). Prevents: self-intersection ("shadow acne") of rays started on a surface.

    Args:
      point: ``(..., 3)`` float32 hit points.
      normal: ``(..., 3)`` geometric normals (any length; only direction and rough scale matter).

    Returns:
      ``(..., 3)`` offset points. The gradient with respect to ``point`` is the identity (the offset is
      treated as a constant) and zero with respect to ``normal``.
    """
    point = jnp.asarray(point, jnp.float32)
    normal = jax.lax.stop_gradient(jnp.asarray(normal, jnp.float32))
    origin, float_scale, int_scale = 1.0 / 32.0, 1.0 / 65536.0, 256.0
    p = jax.lax.stop_gradient(point)
    offset_int = (int_scale * normal).astype(jnp.int32)
    bits = jax.lax.bitcast_convert_type(p, jnp.int32)
    bits = bits + jnp.where(p < 0, -offset_int, offset_int)
    p_int = jax.lax.bitcast_convert_type(bits, jnp.float32)
    p_float = p + float_scale * normal
    offset = jnp.where(jnp.abs(p) < origin, p_float, p_int)
    return point + jax.lax.stop_gradient(offset - p)


def full_precision(fn: Callable) -> Callable:
    """``fn`` traced with float32 matrix products at full precision.

    On GPUs with tensor cores JAX's default float32 ``dot``/``einsum`` precision is TF32 (10 mantissa bits): a
    relative error of about 1e-3, which would make instance boxes non-conservative and curve segments and
    transforms visibly wrong. Every library entry point that builds or traces runs under this.
    """

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with jax.default_matmul_precision("highest"):
            return fn(*args, **kwargs)

    return wrapped
