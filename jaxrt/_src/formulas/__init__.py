"""Leaf formulas written once, instantiated for JAX, Numba and Triton.

A formula module (:mod:`.box`, :mod:`.triangle`, :mod:`.analytic`, :mod:`.point_triangle`, :mod:`.sphere`,
:mod:`.curve`: every module here but the operations, :data:`FORMULAS`) is plain Python over scalars that imports
its operations from :mod:`.vocabulary`. :func:`instance` executes the module's source once more per backend, in a
fresh module whose operation names are then bound to that backend's namespace (:mod:`.ops_jax`,
:mod:`.ops_numba`, :mod:`.ops_triton`), and wraps every function the source defines with the backend's compiler:
none for JAX, ``numba.njit`` for the CPU traversal (inlined at Numba's IR level unless the module sets
``NUMBA_INLINE = False``), ``triton.jit`` for the GPU kernels.
Calls between formulas resolve through the module's globals, so they reach the wrapped versions; Triton and
Numba read a function's globals when they compile it, so they see the backend's operations. A backend whose
operations define ``constant`` gets the module's number constants through it (Triton's compiler reads only
``tl.constexpr`` globals).

The source is registered in :mod:`linecache` under a name such as ``<jaxrt.formulas.box:triton>``: Triton
reads a jit function's source with :mod:`inspect`, and tracebacks show the formula's lines. Numba and Triton
are imported only when their instance is first asked for, so ``import jaxrt`` needs neither.
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import importlib.util
import inspect
import linecache
import pkgutil
import sys
import types
from collections.abc import Callable

__all__ = ["BACKENDS", "FORMULAS", "instance", "source_digest"]

#: The backends a formula is instantiated for.
BACKENDS = ("jax", "numba", "triton")
#: The formula modules: every module of this package but the operations (``vocabulary``, ``ops_*``), so that a
#: new formula module is listed by being written.
FORMULAS = tuple(
    sorted(
        m.name
        for m in pkgutil.iter_modules(__path__)
        if m.name not in ("vocabulary", "conftest") and not m.name.startswith("ops_")
    )
)


def _compiler(backend: str, inline: bool = True) -> Callable[[Callable], Callable]:
    if backend == "jax":
        return lambda fn: fn
    if backend == "numba":
        import numba

        # Inlined at Numba's IR level into the traversal loop (whose machine code is cached on disk); a module
        # with ``NUMBA_INLINE = False`` (large formulas, whose IR inlining takes long to compile) is left to
        # LLVM, which inlines what is worth it.
        return (lambda fn: numba.njit(inline="always")(fn)) if inline else numba.njit
    if backend == "triton":
        import triton

        return triton.jit
    raise ValueError(f"formulas.instance: backend must be one of {BACKENDS}, got {backend!r}")


@functools.cache
def instance(module: str, backend: str) -> types.ModuleType:
    """The formula module ``module`` (a name such as ``"triangle"``) compiled for ``backend``.

    Returns a module holding every function of the formula's source, each compiled for the backend, and the
    backend's operations under the vocabulary's names. Cached: one instance per module and backend.
    """
    if module not in FORMULAS:
        raise ValueError(f"formulas.instance: module must be one of {FORMULAS}, got {module!r}")
    source_module = importlib.import_module(f"{__name__}.{module}")
    compiler = _compiler(backend, getattr(source_module, "NUMBA_INLINE", True))
    source = inspect.getsource(source_module)
    filename = f"<jaxrt.formulas.{module}:{backend}>"
    linecache.cache[filename] = (len(source), None, source.splitlines(True), filename)
    ops = importlib.import_module(f"{__name__}.ops_{backend}")
    name = f"{__name__}._{module}_{backend}"
    target = types.ModuleType(name, source_module.__doc__)
    target.__file__ = filename
    sys.modules[name] = target  # Triton and pickling look functions' modules up by name
    exec(compile(source, filename, "exec"), target.__dict__)
    vocabulary = importlib.import_module(f"{__name__}.vocabulary")
    for op in vocabulary.__all__:
        setattr(target, op, getattr(ops, op))
    target.__dict__.update(getattr(ops, "GLOBALS", {}))
    constant = getattr(ops, "constant", None)
    if constant is not None:  # the module's number constants (such as ``PART_TUBE``) as the backend needs them
        for key, value in list(target.__dict__.items()):
            if not key.startswith("__") and type(value) in (bool, int, float):
                setattr(target, key, constant(value))
    for key, value in list(target.__dict__.items()):
        if inspect.isfunction(value) and value.__code__.co_filename == filename:
            setattr(target, key, compiler(value))
    return target


@functools.cache
def source_digest() -> str:
    """A digest of the formulas' and the operations' source, for caches of compiled code that embeds them."""
    digest = hashlib.sha256()
    for module in (*FORMULAS, "vocabulary", *(f"ops_{b}" for b in BACKENDS)):
        spec = importlib.util.find_spec(f"{__name__}.{module}")
        with open(spec.origin, "rb") as f:
            digest.update(f.read())
    return digest.hexdigest()
