"""The operations a formula may use, with their meaning; each backend's namespace implements them.

A formula module imports its operations from here, so it reads (and lints) as plain Python, and these
definitions double as a scalar reference in float64. :func:`jaxrt._src.formulas.instance` executes the
module's source again with the names replaced by one backend's (:mod:`.ops_jax`, :mod:`.ops_numba`,
:mod:`.ops_triton`).

Rules for a formula body (so that one source compiles under JAX, Numba and Triton):

- straight-line code over scalars (a lane): no ``if``, ``and``, ``or``, ``not`` or ``~`` on values (use
  :func:`select`, ``&``, ``|`` and comparisons), no loops over values;
- a lane-uniform early-out, ``if any_lane(c):``, only around code whose every result is masked by ``c`` (so
  that skipping it where ``c`` is false changes nothing): JAX always runs it, Numba skips it for its one lane,
  Triton for a block where no lane needs it;
- no ``/`` (Triton's is approximate): :func:`div_rn` or :func:`div`;
- no bare float literal in arithmetic or a select (Numba would widen float32 to float64): :func:`like`;
- ``+``, ``-``, ``*`` and comparisons are IEEE operations everywhere; a multiply feeding an add is left
  unfused by Numba and by the Triton kernel (compiled without contraction) and is contracted by XLA as XLA
  decides; where the CPU traversal must reproduce XLA's contraction exactly, the formula says so with
  :func:`sub_product` or :func:`sum_of_products`.
"""

from __future__ import annotations

import math

__all__ = [
    "INF",
    "absolute",
    "atan2",
    "any_lane",
    "div",
    "div_rn",
    "dot3",
    "epsilon_of",
    "false_like",
    "like",
    "maximum",
    "minimum",
    "rounded_product",
    "sample_weights",
    "select",
    "sqrt",
    "sub_product",
    "sum_of_products",
    "tiny_of",
]

#: Positive infinity (a compile-time constant; use ``like(x, INF)`` for a value of ``x``'s type).
INF = math.inf


def select(condition, a, b):
    """``a`` where ``condition`` else ``b`` (both evaluated)."""
    return a if condition else b


def minimum(a, b):
    """The smaller of ``a`` and ``b`` (with a NaN operand, the backend's rule: no formula relies on it)."""
    return b if b < a else a


def maximum(a, b):
    """The larger of ``a`` and ``b`` (with a NaN operand, the backend's rule: no formula relies on it)."""
    return b if b > a else a


def absolute(x):
    """``|x|``."""
    return abs(x)


def sqrt(x):
    """The correctly rounded square root (NaN below zero)."""
    return math.sqrt(x) if x >= 0 else math.nan


def atan2(y, x):
    """The angle of ``(x, y)`` in ``[-pi, pi]``: the backend's library function (XLA's and Numba's), a
    polynomial in Triton; none is correctly rounded, so the backends may differ by a few ulps."""
    return math.atan2(y, x)


def div_rn(a, b):
    """The correctly rounded quotient ``a / b`` on every backend (IEEE: a zero divisor gives an infinity or NaN)."""
    import numpy as np

    with np.errstate(divide="ignore", invalid="ignore"):
        return float(np.float64(a) / np.float64(b))


def div(a, b):
    """``a / b`` as XLA divides on the device: correctly rounded on the CPU; on the GPU PTX's ``div.full.f32``
    (within 2 ulp), which is what XLA's GPU backend emits and what the kernel must reproduce."""
    return div_rn(a, b)


def like(x, value):
    """The constant ``value`` in the float type of ``x``."""
    return float(value)


def false_like(condition):
    """``False`` in the shape of ``condition``."""
    return False


def rounded_product(a, b):
    """``a * b`` rounded once more, to one mantissa bit less than the float has (nearest, ties to even; NaN
    kept): the watertight test's FMA-proof product (see :mod:`jaxrt._src.formulas.triangle`)."""
    import numpy as np

    product = np.float64(a) * np.float64(b)
    if product != product:
        return float(product)
    bits = int(np.array(product).view(np.int64))
    bits = (bits + ((bits >> 1) & 1)) & ~1
    return float(np.array(bits, np.int64).view(np.float64))


def sub_product(c, a, b):
    """``c - a * b`` as XLA's CPU backend evaluates it: contracted into one fused multiply-add (Numba calls
    ``llvm.fma``); unfused in the Triton kernel (compiled without contraction); JAX leaves it to XLA."""
    return c - a * b


def sum_of_products(a0, b0, a1, b1, a2, b2):
    """``(a0 b0 + a1 b1) + a2 b2`` as XLA's CPU backend contracts that expression,
    ``fma(a2, b2, fma(a0, b0, a1 b1))`` (Numba); unfused in the Triton kernel; JAX leaves it to XLA."""
    return (a0 * b0 + a1 * b1) + a2 * b2


def dot3(ax, ay, az, bx, by, bz):
    """The dot product of two 3-vectors: ``jnp.dot`` in JAX; ``(ax bx + ay by) + az bz`` unfused in Numba and
    Triton."""
    return (ax * bx + ay * by) + az * bz


def epsilon_of(x):
    """The machine epsilon of the float type of ``x`` (``2^-23`` for float32)."""
    return 2.0**-52


def tiny_of(x):
    """The smallest positive normal number of the float type of ``x``."""
    return 2.0**-1022


def sample_weights(x, index, pieces):
    """The four cubic Bernstein weights at ``u = index / pieces`` (``index`` in ``0..pieces``; ``u`` as
    ``np.linspace(0, 1, pieces + 1)`` computes it), computed in float64 as
    :func:`jaxrt._src.primitives.curve._bernstein` computes them and rounded once to the float type of ``x``."""
    u = 1.0 if index == pieces else index * (1.0 / pieces)
    return (1.0 - u) ** 3, 3.0 * u * (1.0 - u) ** 2, 3.0 * u**2 * (1.0 - u), u**3


def any_lane(condition):
    """Whether any lane needs the branch that ``if any_lane(condition):`` guards (see the rules above)."""
    return bool(condition)
