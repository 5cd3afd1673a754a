"""The formula operations in Triton: ``triton.jit`` device functions and builtins for the GPU kernels.

The kernels are compiled without floating-point contraction, so ``+``, ``-`` and ``*`` are single IEEE
operations; ``div_rn`` and ``sqrt`` are correctly rounded; ``div`` is Triton's ``/`` (PTX ``div.full.f32``,
the instruction XLA's GPU backend emits for a float32 division). Imported only where Triton is installed.
"""

from __future__ import annotations

import triton
import triton.language as tl

INF = tl.constexpr(float("inf"))
select = tl.where
minimum = tl.minimum
maximum = tl.maximum
absolute = tl.abs
sqrt = tl.math.sqrt_rn
div_rn = tl.math.div_rn


@triton.jit
def like(x, value: tl.constexpr):
    return tl.full(x.shape, value, x.dtype)


@triton.jit
def false_like(condition):
    return tl.zeros(condition.shape, tl.int1)


@triton.jit
def div(a, b):
    return a / b


@triton.jit
def rounded_product(a, b):
    """``a * b`` rounded to 22 mantissa bits (nearest, ties to even), as XLA's ``reduce_precision``."""
    bits = (a * b).to(tl.int32, bitcast=True)
    # One dropped bit: a set bit is exactly half an ulp of the kept mantissa; round up only to an even result.
    bits = (bits + (bits & (bits >> 1) & 1)) & ~1
    return bits.to(tl.float32, bitcast=True)


@triton.jit
def sub_product(c, a, b):
    return c - a * b


@triton.jit
def sum_of_products(a0, b0, a1, b1, a2, b2):
    return a0 * b0 + a1 * b1 + a2 * b2


@triton.jit
def dot3(ax, ay, az, bx, by, bz):
    return (ax * bx + ay * by) + az * bz
