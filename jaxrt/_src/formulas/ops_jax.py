"""The formula operations in JAX: elementwise on arrays of any broadcastable shape (``dot3`` on scalars or
on the last axis), differentiable where the operation is, and vmappable."""

from __future__ import annotations

import functools
import math
import operator

import jax.numpy as jnp
import numpy as np
from jax import lax

INF = math.inf
select = jnp.where
minimum = jnp.minimum
maximum = jnp.maximum
absolute = jnp.abs
sqrt = jnp.sqrt
atan2 = jnp.arctan2
div_rn = operator.truediv
div = operator.truediv


def like(x, value):
    """A Python float: JAX's weak typing keeps the other operand's dtype."""
    return value


def false_like(condition):
    return jnp.zeros_like(condition, bool)


def rounded_product(a, b):
    """``lax.reduce_precision`` to one mantissa bit less: a rounding XLA cannot remove, so the product cannot be
    fused into an FMA either (a 23-bit ``reduce_precision`` of float32 is a no-op XLA deletes)."""
    p = a * b
    info = jnp.finfo(p.dtype)
    return lax.reduce_precision(p, exponent_bits=info.nexp, mantissa_bits=info.nmant - 1)


def sub_product(c, a, b):
    return c - a * b


def sum_of_products(a0, b0, a1, b1, a2, b2):
    return a0 * b0 + a1 * b1 + a2 * b2


def dot3(ax, ay, az, bx, by, bz):
    a = jnp.stack(jnp.broadcast_arrays(ax, ay, az), axis=-1)
    b = jnp.stack(jnp.broadcast_arrays(bx, by, bz), axis=-1)
    if a.ndim == 1 and b.ndim == 1:
        return jnp.dot(a, b)
    return jnp.einsum("...i,...i->...", a, b)


def epsilon_of(x):
    """A Python float (weakly typed): the machine epsilon of ``x``'s dtype."""
    return float(jnp.finfo(jnp.result_type(x)).eps)


def tiny_of(x):
    return float(jnp.finfo(jnp.result_type(x)).tiny)


@functools.cache
def _weights(pieces: int) -> np.ndarray:
    """The cubic Bernstein weights at ``np.linspace(0, 1, pieces + 1)`` in float64, computed as
    ``jaxrt._src.primitives.curve._bernstein`` computes them (the same NumPy expression, so the same floats)."""
    u = np.linspace(0.0, 1.0, pieces + 1)[:, None]
    k = np.arange(4)
    return np.array([1, 3, 3, 1]) * u**k * (1 - u) ** (3 - k)


def sample_weights(x, index, pieces):
    """Python floats (static ``index`` and ``pieces``): the weights of ``curve._bernstein``, rounded to ``x``'s
    dtype where they multiply it (weak typing)."""
    return tuple(float(w) for w in _weights(pieces)[index])


def any_lane(condition):
    """Always ``True``: every lane of a JAX array runs the branch (its results are selected per lane)."""
    return True
