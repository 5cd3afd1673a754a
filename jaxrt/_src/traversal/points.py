"""Which walk answers a point query, and the calls into the compiled ones.

Point queries (:func:`~jaxrt.closest_point`, :func:`~jaxrt.winding_number`, :func:`~jaxrt.contains`,
:func:`~jaxrt.signed_distance`) take ``backend="auto" | "portable" | "cpu" | "gpu"``, as
:class:`~jaxrt.Intersector` does for rays:

- ``"portable"``: the JAX walks of :mod:`jaxrt._src.point_query` and :mod:`jaxrt._src.winding`;
- ``"cpu"``: the Numba walks of :mod:`jaxrt._src.traversal.cpu_points`, called through a host callback and run in
  parallel over the machine's cores (the default JAX backend must be the CPU and Numba must import);
- ``"gpu"``: the Triton kernels of :mod:`jaxrt._src.traversal.triton_points` (a CUDA GPU, Triton and jax-triton,
  float32 geometry);
- ``"auto"``: the compiled walk of the default JAX backend where it covers the structure, else the portable one.

The compiled walks cover primitive structures of triangles and bounding boxes (every kind the portable walks
answer today; a kind added later is left to the portable walks until a compiled walk tests it). They only pick
a leaf (or sum a winding number, which is not differentiated): JAX computes the result fields from the picked
leaf again, so gradients reach the points and the vertices as on the portable path.

Composition: ``jax.jit`` (one callback), ``jax.vmap`` (the callback receives the batch axes: points batched over
one structure are walked in one parallel call, batches of structures one after another), ``jax.grad`` (the
callback's inputs are detached).
"""

from __future__ import annotations

import functools
import math
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxrt._src.kinds import registry
from jaxrt._src.kinds.registry import BOUNDING_BOX, TRIANGLE
from jaxrt._src.traversal import cpu

try:  # the callback that hands XLA's buffers over in place
    from jax.experimental.buffer_callback import buffer_callback as _buffer_callback
except ImportError:  # pragma: no cover - depends on the jax version
    _buffer_callback = None

__all__ = [
    "BACKENDS",
    "box_leaves",
    "cpu_exact_winding",
    "cpu_nearest",
    "cpu_winding",
    "gpu_exact_winding",
    "gpu_nearest",
    "gpu_winding",
    "resolve",
]

#: The values of a point query's ``backend`` argument.
BACKENDS = ("auto", "portable", "cpu", "gpu")
#: The kinds the compiled walks test.
COMPILED_KINDS = (TRIANGLE, BOUNDING_BOX)
#: Points a thread claims at a time.
CHUNK = 64
#: Fewest points per thread worth starting one.
MIN_TASK = 512


def _declines(structure: Any) -> str | None:
    """Why the compiled walks do not cover ``structure`` (``None``: they do)."""
    for kind in registry.present(structure.geometry_info):
        if kind not in COMPILED_KINDS:
            return f"{kind.plural} {kind.be} not covered by the compiled point walks"
    return None


def _cpu_unavailable() -> str | None:
    return cpu.unavailable_reason()


def _gpu_unavailable(dtype: Any) -> str | None:
    backend = jax.default_backend()
    if backend != "gpu":
        return f"the default JAX backend is {backend!r}; the GPU point kernel needs a CUDA GPU"
    if jnp.dtype(dtype) != jnp.float32:
        return f"the GPU point kernel walks float32 structures, not {jnp.dtype(dtype).name}"
    try:
        import jax_triton  # noqa: F401
        import triton  # noqa: F401
    except ImportError as error:  # pragma: no cover - depends on the install
        return f"Triton or jax-triton cannot be imported ({error}); install jaxrt[gpu]"
    return None


def resolve(backend: str, structure: Any, name: str) -> str:
    """``"portable"``, ``"cpu"`` or ``"gpu"``: the walk that answers ``name`` on ``structure`` for the requested
    ``backend``; ``ValueError`` for an unknown one or a forced compiled walk that cannot run."""
    if backend not in BACKENDS:
        raise ValueError(f"{name}: backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "portable":
        return "portable"
    dtype = structure.leaf_triangle.dtype
    unavailable = {"cpu": _cpu_unavailable, "gpu": lambda: _gpu_unavailable(dtype)}
    if backend in unavailable:
        reason = unavailable[backend]() or _declines(structure)
        if reason is not None:
            raise ValueError(f"{name}: backend={backend!r} cannot run: {reason}")
        return backend
    if _declines(structure) is not None:
        return "portable"
    for choice in ("gpu", "cpu") if jax.default_backend() == "gpu" else ("cpu",):
        if unavailable[choice]() is None:
            return choice
    return "portable"


# --- the CPU callbacks ------------------------------------------------------------------------------------------


def threads() -> int:
    """Threads of the CPU walks (the CPU traversal's count: ``JAXRT_CPU_THREADS`` or the usable cores)."""
    return cpu.threads()


@functools.cache
def _pool(workers: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(workers, thread_name_prefix="jaxrt-points")


def _parallel(kernel, n: int, *args: Any) -> None:
    """``kernel(*args, counter, CHUNK)`` on enough threads for ``n`` points (the kernel releases the GIL)."""
    counter = np.zeros(1, np.int64)
    run = functools.partial(kernel, *args[:-1], counter, CHUNK, args[-1])
    workers = max(1, min(threads(), -(-n // MIN_TASK)))
    helpers = [_pool(workers).submit(run) for _ in range(workers - 1)] if workers > 1 else []
    run()
    for helper in helpers:
        helper.result()


def _morton_order(points: np.ndarray) -> np.ndarray:
    """The permutation that sorts ``points (n, 3)`` along a 30-bit Morton curve over their bounding box (finite
    points; others first): neighbouring points walk similar paths, so the walk stays in cache."""
    finite = np.isfinite(points).all(axis=1)
    lo = points[finite].min(axis=0) if finite.any() else np.zeros(3)
    hi = points[finite].max(axis=0) if finite.any() else np.ones(3)
    extent = np.where(hi > lo, hi - lo, 1)
    cell = np.clip((np.where(finite[:, None], points, lo) - lo) / extent * 1023, 0, 1023).astype(np.uint32)
    x = cell.T.copy()  # (3, n): each axis's 10 bits spread to every third bit
    x = (x | (x << 16)) & 0x030000FF
    x = (x | (x << 8)) & 0x0300F00F
    x = (x | (x << 4)) & 0x030C30C3
    x = (x | (x << 2)) & 0x09249249
    return np.argsort((x[0] << 2) | (x[1] << 1) | x[2])


#: Fewest points worth sorting along a Morton curve.
SORT_MIN = 4096


def _walk(kernel, points: np.ndarray, out: np.ndarray, *args: Any) -> None:
    """``kernel`` over ``points (n, 3)`` into ``out`` (in order), sorting large batches first."""
    n = points.shape[0]
    if n >= SORT_MIN:
        order = _morton_order(points)
        sorted_out = np.empty_like(out)
        _parallel(kernel, n, np.ascontiguousarray(points[order]), *args, sorted_out)
        out[order] = sorted_out
    else:
        _parallel(kernel, n, np.ascontiguousarray(points), *args, out)


def _unwrap(a: Any, wide: bool) -> np.ndarray:
    a = np.asarray(a)
    return np.ascontiguousarray(a).view(np.float64)[..., 0] if wide and a.dtype == np.uint32 else a


def _host(walk, ranks: tuple[int, ...], floats: tuple[bool, ...], wide: bool, *args: Any) -> np.ndarray:
    """The callback: arguments (the points first) with leading vmap axes, floats as pairs of words if ``wide``."""
    args = [_unwrap(a, wide and f) for a, f in zip(args, floats, strict=True)]
    lead = [a.shape[: a.ndim - r] for a, r in zip(args, ranks, strict=True)]
    batch = np.broadcast_shapes(*lead)
    if not batch:
        return walk(*args)
    points = np.broadcast_to(args[0], batch + args[0].shape[-2:])
    if all(math.prod(s) == 1 for s in lead[1:]):  # points batched over one structure: one parallel walk
        rest = [a.reshape(a.shape[a.ndim - r :]) for a, r in zip(args[1:], ranks[1:], strict=True)]
        out = walk(points.reshape(-1, 3), *rest)
        return out.reshape(*batch, -1, *out.shape[1:])
    full = [np.broadcast_to(a, batch + a.shape[a.ndim - r :]) for a, r in zip(args, ranks, strict=True)]
    parts = [walk(*(a[index] for a in full)) for index in np.ndindex(*batch)]
    return np.stack(parts).reshape(*batch, *parts[0].shape)


def _host_into(callback: Any, context: Any, out: Any, *args: Any) -> None:
    del context
    np.asarray(out[0])[...] = callback(*(np.asarray(a) for a in args))


def _call(walk, shape: jax.ShapeDtypeStruct, args: tuple, ranks: tuple[int, ...]) -> jax.Array:
    """``walk`` (host arrays to one host array) as a callback on detached ``args``; float64 arrays travel as
    pairs of uint32 words (a callback's float64 values are narrowed on threads with x64 off)."""
    args = tuple(lax.stop_gradient(a) for a in args)
    wide = any(jnp.issubdtype(a.dtype, jnp.floating) and a.dtype.itemsize == 8 for a in args)
    floats = tuple(bool(jnp.issubdtype(a.dtype, jnp.floating)) for a in args)
    if wide:
        args = tuple(lax.bitcast_convert_type(a, jnp.uint32) if f else a for a, f in zip(args, floats, strict=True))
    out_wide = wide and jnp.issubdtype(shape.dtype, jnp.floating)
    result = shape
    if out_wide:
        result = jax.ShapeDtypeStruct((*shape.shape, 2), jnp.uint32)

    def host(*host_args):
        out = _host(walk, ranks, floats, wide, *host_args)
        return out.view(np.uint32).reshape(*out.shape, 2) if out_wide else out

    if _buffer_callback is not None:
        (out,) = _buffer_callback(functools.partial(_host_into, host), (result,), vmap_method="expand_dims")(*args)
    else:  # pragma: no cover - depends on the jax version
        out = jax.pure_callback(host, result, *args, vmap_method="expand_dims")
    return lax.bitcast_convert_type(out, shape.dtype) if out_wide else out


def _nearest_host(points, lower, upper, children, triangles, boxes, box_leaf, limit2, stack_size: int):
    from jaxrt._src.traversal import cpu_points

    dtype = lower.dtype
    out = np.empty(points.shape[0], np.int32)
    points = points.astype(dtype, copy=False)
    limit = np.asarray(limit2, dtype).reshape(-1)[0]
    args = (lower, upper, children, triangles, boxes, box_leaf, limit, cpu_points.constants(dtype), stack_size)
    _walk(cpu_points.nearest_leaves, points, out, *(np.ascontiguousarray(a) for a in args[:6]), *args[6:])
    return out


def _winding_host(points, children, triangles, boxes, box_leaf, geometry, normal, center, reach2, stack_size: int):
    from jaxrt._src.traversal import cpu_points

    dtype = triangles.dtype
    out = np.empty(points.shape[0], dtype)
    arrays = (children, triangles, boxes, box_leaf, geometry, normal, center, reach2)
    args = (*(np.ascontiguousarray(a) for a in arrays), cpu_points.constants(dtype), stack_size)
    _walk(cpu_points.fast_winding, points.astype(dtype, copy=False), out, *args)
    return out


def _exact_host(points, triangles, boxes, box_leaf, geometry):
    from jaxrt._src.traversal import cpu_points

    dtype = triangles.dtype
    out = np.empty(points.shape[0], dtype)
    arrays = (triangles, boxes, box_leaf, geometry)
    args = (*(np.ascontiguousarray(a) for a in arrays), cpu_points.constants(dtype))
    _walk(cpu_points.exact_winding, points.astype(dtype, copy=False), out, *args)
    return out


def box_leaves(structure: Any, box_table: jax.Array | None) -> tuple[jax.Array, jax.Array]:
    """``(leaf boxes (C, 2, 3) or a placeholder row, whether each leaf is a box primitive (C,))``."""
    if box_table is None or structure.leaf_box is None:
        dtype = structure.leaf_triangle.dtype
        return jnp.zeros((1, 2, 3), dtype), jnp.zeros(structure.leaf_geometry.shape, jnp.bool_)
    geometry = structure.leaf_geometry
    return structure.leaf_box, box_table[jnp.where(geometry < 0, -1, geometry)]


def cpu_nearest(points: jax.Array, structure: Any, box_table: jax.Array | None, limit2: jax.Array) -> jax.Array:
    """The nearest leaf to each point ``(n, 3)`` within squared distance ``limit2`` (-1: none), by the Numba
    walk (:func:`jaxrt._src.traversal.cpu_points.nearest_leaves`)."""
    boxes, box_leaf = box_leaves(structure, box_table)
    walk = functools.partial(_nearest_host, stack_size=structure.max_depth + 1)
    args = (points, structure.node_lower, structure.node_upper, structure.node_children.astype(jnp.int32),
            structure.leaf_triangle, boxes, box_leaf, jnp.reshape(limit2, (1,)).astype(points.dtype))  # fmt: skip
    shape = jax.ShapeDtypeStruct(points.shape[:1], jnp.int32)
    return _call(walk, shape, args, (2, 3, 3, 2, 3, 3, 1, 1))


def cpu_winding(points: jax.Array, structure: Any, box_table: jax.Array | None, dipoles: Any) -> jax.Array:
    """The fast winding number of each point ``(n, 3)`` by the Numba walk
    (:func:`jaxrt._src.traversal.cpu_points.fast_winding`); ``dipoles``: :func:`jaxrt._src.winding._dipoles`."""
    boxes, box_leaf = box_leaves(structure, box_table)
    walk = functools.partial(_winding_host, stack_size=structure.max_depth + 1)
    dtype = structure.leaf_triangle.dtype
    args = (points, structure.node_children.astype(jnp.int32), structure.leaf_triangle, boxes, box_leaf,
            structure.leaf_geometry.astype(jnp.int32), dipoles.normal.astype(dtype), dipoles.center.astype(dtype),
            dipoles.reach2.astype(dtype))  # fmt: skip
    shape = jax.ShapeDtypeStruct(points.shape[:1], dtype)
    return _call(walk, shape, args, (2, 2, 3, 3, 1, 1, 3, 3, 2))


def cpu_exact_winding(points: jax.Array, structure: Any, box_table: jax.Array | None) -> jax.Array:
    """The exact winding number of each point ``(n, 3)`` (every leaf's solid angle) by the Numba loop
    (:func:`jaxrt._src.traversal.cpu_points.exact_winding`)."""
    boxes, box_leaf = box_leaves(structure, box_table)
    args = (points, structure.leaf_triangle, boxes, box_leaf, structure.leaf_geometry.astype(jnp.int32))
    shape = jax.ShapeDtypeStruct(points.shape[:1], structure.leaf_triangle.dtype)
    return _call(_exact_host, shape, args, (2, 3, 3, 1, 1))


def gpu_nearest(points: jax.Array, structure: Any, box_table: jax.Array | None, limit2: jax.Array) -> jax.Array:
    """:func:`cpu_nearest` by the Triton kernel (:mod:`jaxrt._src.traversal.triton_points`); pass the points in a
    coherent order (:func:`jaxrt._src.point_traversal.in_morton_order`): a warp walks 32 of them together."""
    from jaxrt._src.traversal import triton_points

    boxes, box_leaf = box_leaves(structure, box_table)
    return triton_points.nearest(points, structure, boxes, box_leaf, limit2)


def gpu_winding(points: jax.Array, structure: Any, box_table: jax.Array | None, dipoles: Any) -> jax.Array:
    """:func:`cpu_winding` by the Triton kernel (:mod:`jaxrt._src.traversal.triton_points`)."""
    from jaxrt._src.traversal import triton_points

    boxes, box_leaf = box_leaves(structure, box_table)
    return triton_points.fast_winding(points, structure, boxes, box_leaf, dipoles)


def gpu_exact_winding(points: jax.Array, structure: Any, box_table: jax.Array | None) -> jax.Array:
    """:func:`cpu_exact_winding` by the Triton kernel (:mod:`jaxrt._src.traversal.triton_points`)."""
    from jaxrt._src.traversal import triton_points

    boxes, box_leaf = box_leaves(structure, box_table)
    return triton_points.exact_winding(points, structure, boxes, box_leaf)
