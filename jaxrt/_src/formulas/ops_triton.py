"""The formula operations in Triton: ``triton.jit`` device functions and builtins for the GPU kernels.

The kernels are compiled without floating-point contraction, so ``+``, ``-`` and ``*`` are single IEEE
operations; ``div_rn`` and ``sqrt`` are correctly rounded; ``div`` is Triton's ``/`` (PTX ``div.full.f32``,
the instruction XLA's GPU backend emits for a float32 division). Imported only where Triton is installed.
"""

from __future__ import annotations

import triton
import triton.language as tl

INF = tl.constexpr(float("inf"))
#: Extra globals of a formula module instantiated for Triton: the interpreter (``TRITON_INTERPRET=1``) swaps
#: ``triton.language``'s functions for its own through the jit function's globals, so every operation below
#: reaches ``tl`` through a jit function (inlined by the compiler) rather than an alias bound at import.
GLOBALS = {"tl": tl}


def constant(value):
    """A formula module's number constant (such as ``curve.PART_TUBE``) as Triton's compiler reads a global: a
    ``tl.constexpr`` (it rejects plain Python numbers)."""
    return tl.constexpr(value)


@triton.jit
def select(condition, a, b):
    return tl.where(condition, a, b)


@triton.jit
def minimum(a, b):
    return tl.minimum(a, b)


@triton.jit
def maximum(a, b):
    return tl.maximum(a, b)


@triton.jit
def absolute(x):
    return tl.abs(x)


@triton.jit
def sqrt(x):
    return tl.math.sqrt_rn(x)


@triton.jit
def atan2(y, x):
    """Cephes' ``atanf`` of ``y / x`` (range reduction at tan(pi/8) and tan(3pi/8), a degree-9 odd polynomial;
    within a few float32 ulps), moved to the quadrant of ``(x, y)``. Written with ``tl`` operations so that
    Triton's interpreter runs it (it has no libdevice)."""
    r = tl.math.div_rn(y, x)
    a = tl.abs(r)
    big = a > 2.414213562373095
    mid = (a > 0.4142135623730950) & (big == 0)
    t = tl.where(big, tl.math.div_rn(-tl.full(a.shape, 1.0, a.dtype), a), a)
    t = tl.where(mid, tl.math.div_rn(a - 1.0, a + 1.0), t)
    base = tl.where(big, 1.5707963267948966, tl.where(mid, 0.7853981633974483, 0.0))
    z = t * t
    poly = (((8.05374449538e-2 * z - 1.38776856032e-1) * z + 1.99777106478e-1) * z - 3.33329491539e-1) * z * t + t
    angle = base + poly
    angle = tl.where(r < 0, -angle, angle)
    return tl.where(x < 0, tl.where(y < 0, angle - 3.141592653589793, angle + 3.141592653589793), angle)


@triton.jit
def div_rn(a, b):
    return tl.math.div_rn(a, b)


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


@triton.jit
def epsilon_of(x):
    return tl.full(x.shape, 1.1920928955078125e-07, x.dtype)


@triton.jit
def tiny_of(x):
    return tl.full(x.shape, 1.1754943508222875e-38, x.dtype)


@triton.jit
def sample_weights(x, index, pieces: tl.constexpr):
    """The Bernstein weights at sample ``index`` in float64, rounded once to ``x``'s type."""
    i = tl.zeros((1,), tl.float64) + index
    u = i * (1.0 / tl.full(i.shape, pieces, tl.float64))
    u = tl.where(i == pieces, 1.0, u)
    v = 1.0 - u
    w0 = (v * v * v).to(x.dtype)
    w1 = (3.0 * u * (v * v)).to(x.dtype)
    w2 = (3.0 * (u * u) * v).to(x.dtype)
    w3 = (u * u * u).to(x.dtype)
    return w0, w1, w2, w3


@triton.jit
def any_lane(condition):
    return tl.max(condition.to(tl.int32), axis=0) > 0
