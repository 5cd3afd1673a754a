"""The formula operations in Numba: scalar functions compiled into the CPU traversal, in the geometry's dtype.

``sub_product`` and ``sum_of_products`` call ``llvm.fma`` where XLA's CPU backend contracts the same
expression (Numba itself never contracts: ``fastmath=False``), and ``rounded_product`` reproduces XLA's
``reduce_precision``, so the CPU traversal computes the portable path's floats to the bit.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic, overload

INF = math.inf


@intrinsic
def fma(typingctx, a, b, c):
    """``a * b + c`` rounded once (``llvm.fma``)."""
    sig = a(a, a, a)

    def codegen(context, builder, signature, args):
        ty = args[0].type
        name = "llvm.fma.f32" if ty == ir.FloatType() else "llvm.fma.f64"
        fn = builder.module.declare_intrinsic(name, [ty], ir.FunctionType(ty, [ty, ty, ty]))
        return builder.call(fn, args)

    return sig, codegen


@intrinsic
def rounded_product(typingctx, a, b):
    """``a * b`` rounded to one mantissa bit less, to nearest even (XLA's ``reduce_precision``); NaN kept."""
    sig = a(a, a)

    def codegen(context, builder, signature, args):
        ty = args[0].type
        bits = 32 if ty == ir.FloatType() else 64
        it = ir.IntType(bits)
        product = builder.fmul(args[0], args[1])
        x = builder.bitcast(product, it)
        last = builder.lshr(builder.and_(x, ir.Constant(it, 2)), ir.Constant(it, 1))
        rounded = builder.and_(builder.add(x, last), ir.Constant(it, ~1 & ((1 << bits) - 1)))
        out = builder.bitcast(rounded, ty)
        is_nan = builder.fcmp_unordered("uno", product, product)
        return builder.select(is_nan, product, out)

    return sig, codegen


def like(x, value):
    """``value`` in the float type of ``x`` (typed by the overload below)."""
    return value


@overload(like, inline="always")
def _like(x, value):
    if x == types.float32:
        return lambda x, value: np.float32(value)
    return lambda x, value: np.float64(value)


def epsilon_of(x):
    """The machine epsilon of ``x``'s float type (typed by the overload below)."""
    return np.finfo(np.float64).eps


@overload(epsilon_of, inline="always")
def _epsilon_of(x):
    if x == types.float32:
        eps32 = np.float32(np.finfo(np.float32).eps)
        return lambda x: eps32
    eps64 = np.float64(np.finfo(np.float64).eps)
    return lambda x: eps64


def tiny_of(x):
    """The smallest positive normal number of ``x``'s float type (typed by the overload below)."""
    return np.finfo(np.float64).tiny


@overload(tiny_of, inline="always")
def _tiny_of(x):
    if x == types.float32:
        tiny32 = np.float32(np.finfo(np.float32).tiny)
        return lambda x: tiny32
    tiny64 = np.float64(np.finfo(np.float64).tiny)
    return lambda x: tiny64


@numba.njit(inline="always")
def sample_weights(x, index, pieces):
    """``curve._bernstein``'s weights at sample ``index`` in float64, rounded once to ``x``'s type. The powers
    are products (NumPy calls ``pow``): equal in float64 where ``index / pieces`` is a dyadic fraction (every
    power of two of pieces), else within an ulp of float64, which rounds to the same float32 weight except
    within an ulp of float64 of a rounding boundary."""
    u = 1.0 if index == pieces else index * (1.0 / pieces)
    v = 1.0 - u
    return like(x, v * v * v), like(x, 3.0 * u * (v * v)), like(x, 3.0 * (u * u) * v), like(x, u * u * u)


@numba.njit(inline="always")
def any_lane(condition):
    return condition


@numba.njit(inline="always")
def false_like(condition):
    return False


@numba.njit(inline="always")
def select(condition, a, b):
    return a if condition else b


@numba.njit(inline="always")
def minimum(a, b):
    return min(a, b)


@numba.njit(inline="always")
def maximum(a, b):
    return max(a, b)


@numba.njit(inline="always")
def absolute(x):
    return abs(x)


@numba.njit(inline="always")
def sqrt(x):
    return np.sqrt(x)


@numba.njit(inline="always")
def atan2(y, x):
    return math.atan2(y, x)


@numba.njit(inline="always")
def div_rn(a, b):
    return a / b


@numba.njit(inline="always")
def div(a, b):
    return a / b


@numba.njit(inline="always")
def sub_product(c, a, b):
    return fma(-a, b, c)


@numba.njit(inline="always")
def sum_of_products(a0, b0, a1, b1, a2, b2):
    return fma(a2, b2, fma(a0, b0, a1 * b1))


@numba.njit(inline="always")
def dot3(ax, ay, az, bx, by, bz):
    return (ax * bx + ay * by) + az * bz


def key_caches_on_formulas(namespace: dict, *extra: str) -> None:
    """Key the on-disk cache of every cached Numba function in ``namespace`` (a module's globals) also on the
    formulas' source (:func:`jaxrt._src.formulas.source_digest`) and on ``extra`` (digests of other source the
    functions embed, such as generated code).

    Numba keys a cached function by its own file's time stamp and bytecode; the formulas compiled into it live
    in other files, so without this an edited formula would load the stale machine code.
    """
    from numba.core.caching import FunctionCache

    from jaxrt._src.formulas import source_digest

    digest = source_digest() + "".join(extra)

    class _Cache(FunctionCache):
        def _index_key(self, sig, codegen):
            return (*super()._index_key(sig, codegen), digest)

    for value in list(namespace.values()):
        if isinstance(value, numba.core.dispatcher.Dispatcher) and value._cache.__class__ is FunctionCache:
            value._cache = _Cache(value.py_func)
