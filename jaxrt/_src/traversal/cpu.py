"""CPU traversal: a Numba-compiled stack traversal called through a buffer callback (``jax.pure_callback`` where
the jax version has none), behind the same contract as the portable traversal.

:func:`trace_scene` traces a :class:`~jaxrt._src.traversal.scene.TraversalScene` (any number of instance
levels) and returns the :class:`~jaxrt._src.traversal.scene.TraversalResult` of the portable traversal: the same
leaf, distance, instance chain and stats counters, decided with the same float operations
(:mod:`jaxrt._src.traversal.cpu_kernel` says how). Rays are traced in parallel over the machine's cores
(:func:`threads`): the compiled loop releases the GIL, and a thread pool runs ranges of rays. A large batch in
an incoherent order is traced sorted along a Morton curve of origin and direction
(:mod:`jaxrt._src.traversal.cpu_order`), its results put back in the given order.

The intersector picks this path (``backend="auto"`` or ``"cpu"``) when :func:`unavailable_reason` returns
``None`` (the default JAX backend is the CPU and Numba imports) and
:func:`jaxrt._src.pipeline.kernel_declines` finds the scene and intersector covered: triangles, flat or
instanced at any depth, built-in spheres, bounding boxes with the built-in sphere, disk and capped cylinder functions (their
distances equal the portable path's to rounding: XLA contracts some of their multiply-adds, the loop none),
primitive keyframe motion of triangles in a primitive structure (node boxes and triangles blended at each
ray's time as the portable step blends them), round and flat curves in a primitive structure (the shared curve
formula, :mod:`jaxrt._src.traversal.cpu_curves`; distances equal the portable path's to a few ulps, and the
traversal also reports each curve hit's parameter and part, so the result fields need not test it again in
XLA), nearest and any hit, the ``K`` nearest hits (``max_hits``) and
counting, cull modes and windings, ray intervals, ray and instance masks, disabled rays and the stats
counters, in float32 or float64.

Composition:
  - ``jax.jit``: the traversal is one host callback; Numba compiles once per dtype (not per shape), and
    ``cache=True`` keeps the machine code on disk for later processes.
  - ``jax.vmap``: the callback's ``vmap_method="expand_dims"`` hands it the batch axes; rays batched over one
    scene are traced in one parallel call, batches of scenes one scene after another.
  - ``jax.grad``: the inputs are detached; the intersector re-computes the hit differentiably in JAX.
"""

from __future__ import annotations

import ctypes
import functools
import os
import weakref
from concurrent.futures import ThreadPoolExecutor
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxrt._src import numerics

try:  # the callback that hands XLA's buffers over in place (no argument or result copies)
    from jax.experimental.buffer_callback import buffer_callback as _buffer_callback
except ImportError:  # pragma: no cover - depends on the jax version
    _buffer_callback = None
from jaxrt._src.primitives import box, curve
from jaxrt._src.traversal import analytic_rows, packed
from jaxrt._src.traversal.scene import TraversalLayout, TraversalRays, TraversalResult, TraversalScene
from jaxrt._src.traversal.step import HitList

__all__ = [
    "CurveLeaves",
    "constants",
    "curve_frames",
    "host_scene",
    "kernel_arguments",
    "trace_scene",
    "unavailable_reason",
]

#: Base ranks of the callback's arguments (scene arrays, then rays); leading axes beyond them are vmap axes.
_SCENE_RANKS = (3, 3, 2, 3, 3, 1, 1, 1, 2, 4, 4, 4, 1, 1, 1, 3, 1)
_RAY_RANKS = (2, 2, 1, 1, 1, 1, 1, 2)
#: Position of the first ray argument.
_RAYS = len(_SCENE_RANKS)
#: Positions of the float arguments (scene geometry, analytic rows, keyframes, curve segments and rays).
_FLOAT_ARGS = (0, 1, 3, 4, 8, 9, 10, 11, 13, 15, _RAYS, _RAYS + 1, _RAYS + 2, _RAYS + 3, _RAYS + 6, _RAYS + 7)
#: ``params[9]`` where the analytic leaves are those of kinds with an analytic row alone (built-in spheres;
#: :func:`_analytic_mode`).
_FORMULA_ROWS = 2
#: Bits of ``AnalyticLeaves.shapes`` (:func:`jaxrt._src.traversal.gpu.analytic_leaves`) the lean loop covers:
#: triangles (bit 3) and the kinds' analytic rows (:data:`jaxrt._src.traversal.analytic_rows.FORMULA_SHAPES`).
_LEAN_SHAPES = (1 << 3) | analytic_rows.FORMULA_SHAPES
#: Rays a thread claims at a time (rays cost unevenly: small claims keep every thread busy to the end).
CHUNK = 32
#: Fewest rays per thread worth starting one.
MIN_TASK = 256
#: Fewest rays worth sorting into a coherent order (:func:`_order`).
SORT_MIN = 1024


def threads() -> int:
    """Threads the CPU traversal uses: the cores this process may run on (``JAXRT_CPU_THREADS`` overrides)."""
    value = os.environ.get("JAXRT_CPU_THREADS")
    if value:
        if not value.strip().isdigit() or int(value) < 1:
            raise ValueError(f"traversal.cpu: JAXRT_CPU_THREADS must be a positive integer, got {value!r}")
        return int(value)
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


@functools.cache
def _pool_of(workers: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(workers, thread_name_prefix="jaxrt-cpu")


def _pool() -> ThreadPoolExecutor:
    return _pool_of(threads())


@functools.lru_cache(maxsize=1)
def _import_error() -> str | None:
    try:
        import numba  # noqa: F401
    except ImportError as error:  # pragma: no cover - depends on the install
        return f"Numba cannot be imported ({error}); install numba>=0.61"
    return None


def unavailable_reason(intersector: Any = None) -> str | None:
    """Why the CPU traversal cannot run here, or ``None`` when it can."""
    del intersector  # the scene-dependent rules are in :func:`jaxrt._src.pipeline.kernel_declines`
    backend = jax.default_backend()
    if backend != "cpu":
        return f"the default JAX backend is {backend!r}; the CPU traversal runs on the CPU backend"
    return _import_error()


def constants(dtype: Any) -> np.ndarray:
    """The float constants of the traversal in ``dtype``, rounded as the portable path rounds them."""
    t = np.dtype(dtype).type
    return np.array(
        [
            1.0,
            0.0,
            np.inf,
            t(numerics.RECIPROCAL_CLAMP),  # |d| below it is clamped up to it
            t(1.0 / numerics.RECIPROCAL_CLAMP),  # |d| above it is clamped down to sign / clamp
            t(numerics.RECIPROCAL_CLAMP),
            t(box.FAR_SCALE),
            t(box.PARALLEL_RECIPROCAL),
        ],
        dtype,
    )


def _order(arrays: list[np.ndarray], root: int) -> np.ndarray | None:
    """The order to trace the rays in, or ``None`` to trace them as given: batches of :data:`SORT_MIN` rays or
    more that are not in a coherent order already are sorted along a Morton curve of origin (in the root's
    bounds) and direction (:mod:`jaxrt._src.traversal.cpu_order`)."""
    from jaxrt._src.traversal import cpu_order

    origin, direction = arrays[_RAYS], arrays[_RAYS + 1]
    if origin.shape[0] < SORT_MIN or arrays[0].shape[0] == 0:
        return None
    lower, upper = arrays[0][root].min(axis=0), arrays[1][root].max(axis=0)
    if cpu_order.coherent(origin, direction, lower, upper):
        return None
    return cpu_order.ray_order(origin, direction, lower, upper)


def _run(params: tuple, arrays: list[np.ndarray], boxes: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """Trace one scene's rays (flat ``(n, ...)`` arrays) with the compiled kernel; with a hit list
    (``params[6]``) the hit distances, leaves, totals and chains follow the six outputs. Rays in an incoherent
    order are traced sorted (:func:`_order`): copied into that order, and their results copied back.
    ``boxes``: the scene's box rows (:func:`box_rows`), or ``None`` to lay them out here."""
    from jaxrt._src.traversal import cpu_order

    arrays = [np.ascontiguousarray(a) for a in arrays]
    order = _order(arrays, params[0])
    if order is None:
        return _trace(params, arrays, boxes)
    out = _trace(params, arrays[:_RAYS] + [cpu_order.permuted(a, order) for a in arrays[_RAYS:]], boxes)
    return tuple(cpu_order.unpermuted(a, order) for a in out)


def _trace(params: tuple, arrays: list[np.ndarray], boxes: np.ndarray | None) -> tuple[np.ndarray, ...]:
    """:func:`_run` on rays in the order given."""
    from jaxrt._src.traversal import cpu_kernel

    origin = arrays[_RAYS]
    n, levels = origin.shape[0], params[2]
    hit_list, k = bool(params[6]), params[7]
    dtype = origin.dtype
    out = (
        np.empty(n, dtype),
        np.empty(n, np.int32),
        np.empty((n, levels), np.int32),
        np.empty(n, np.int32),
        np.empty(n, np.int32),
        np.empty(n, np.bool_),
    )
    rows = n if hit_list else 0  # without a hit list the kernel writes none of these
    hits = (
        np.empty((rows, k), dtype),
        np.empty((rows, k), np.int32),
        np.empty(rows, np.int32),
        np.empty((rows, k, levels), np.int32),
    )
    consts, flags = constants(dtype), np.asarray(params, np.int64)
    counter = np.zeros(1, np.int64)
    formula_rows = params[9] == _FORMULA_ROWS
    if levels == 0 and not hit_list and not params[11] and (not params[9] or (formula_rows and not params[10])):
        # triangles and the kinds' analytic rows (built-in spheres), no instances or curves: the lean loop
        rays = arrays[_RAYS : _RAYS + 5]
        if boxes is None:
            boxes = _box_rows_in_place(arrays[0], arrays[1])
        run = functools.partial(
            cpu_kernel.trace_flat, *arrays[:4], boxes, *rays, consts, params[0], params[3], bool(params[4]), params[5],
            counter, CHUNK, n, out[0], out[1], *out[3:], bool(params[10]), *arrays[9:15], arrays[_RAYS + 6], formula_rows,
            arrays[8],
        )  # fmt: skip
    else:
        run = functools.partial(cpu_kernel.trace_rays, *arrays, consts, flags, counter, CHUNK, n, *out, *hits)
    workers = min(threads(), -(-n // MIN_TASK))
    # The kernel releases the GIL; each thread claims chunks of rays from the shared counter until none is
    # left, so uneven rays balance without a task per chunk. This thread is one of the workers.
    helpers = [_pool().submit(run) for _ in range(workers - 1)]
    run()
    for helper in helpers:
        helper.result()
    out = out + hits if hit_list else out
    if params[11]:  # curves: the parameter and part of each nearest curve hit, for the result fields
        curve = (np.empty(n, dtype), np.empty(n, np.int32))
        at = len(params) - CURVE_PARAMS
        rays = arrays[_RAYS : _RAYS + 5]
        cpu_kernel.cpu_curves.nearest_parts(
            arrays[15], arrays[16], out[1], rays[0], arrays[_RAYS + 7], *rays[2:], flags, at, consts[2], *curve
        )
        out = out + curve
    return out


def _host(params: tuple, wide: bool, hosted: tuple | None, *args: np.ndarray) -> tuple[np.ndarray, ...]:
    """The callback: ``args`` may carry leading vmap axes (size 1 where an argument is not batched).

    Float64 arrays travel both ways as pairs of uint32 words (``wide``): JAX converts a callback's float64
    arguments and results to float32 when the thread that runs it has ``jax_enable_x64`` off
    (``jax.enable_x64`` is a per-thread setting). With ``hosted`` (the shapes and dtypes of the node and
    triangle arrays), the first argument holds their addresses (:func:`host_scene`) in place of the arrays, and
    the third the structure's box rows.
    """
    boxes = None
    if hosted is not None:
        words = np.asarray(args[0]).reshape(-1, 2)[: len(hosted)].astype(np.uint64)
        addresses = words[:, 0] | (words[:, 1] << np.uint64(32))
        in_place = {i: _at(int(a), shape, dtype) for a, (i, shape, dtype) in zip(addresses, hosted, strict=True)}
        boxes = np.asarray(args[2]).view(hosted[0][2])  # the structure's box rows (host_scene), as words
        rest = iter(args[3:])  # args[1]: one element of each, so that the program holds their buffers
        args = tuple(in_place[i] if i in in_place else next(rest) for i in range(len(_SCENE_RANKS + _RAY_RANKS)))
    if wide:
        args = tuple(
            np.ascontiguousarray(a).view(np.float64)[..., 0]
            if i in _FLOAT_ARGS and (hosted is None or all(i != h[0] for h in hosted))
            else a
            for i, a in enumerate(args)
        )
    out = _host_arrays(params, *args, boxes=boxes)
    if wide:  # the float outputs (distances, the hit distances of a hit list, curve parameters) as pairs of words
        words = lambda a: a.view(np.uint32).reshape(*a.shape, 2)  # noqa: E731
        out = tuple(words(a) if a.dtype == np.float64 else a for a in out)
    return out


def _host_into(callback: Any, context: Any, outs: tuple, *args: Any) -> None:
    """``callback`` as a buffer callback: XLA's argument buffers are read in place and the results written
    into its output buffers."""
    del context
    for out, value in zip(outs, callback(*(np.asarray(a) for a in args)), strict=True):
        np.asarray(out)[...] = value


def _at(address: int, shape: tuple[int, ...], dtype: str) -> np.ndarray:
    """A read-only array over ``address`` (no copy)."""
    size = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
    if size == 0:
        return np.zeros(shape, dtype)
    array = np.frombuffer((ctypes.c_char * size).from_address(address), dtype).reshape(shape)
    array.flags.writeable = False
    return array


def box_rows(node_lower: np.ndarray, node_upper: np.ndarray) -> np.ndarray:
    """The node boxes as the lean loop's vector box test reads them (:func:`cpu_kernel.box_rows`): ``(nodes,
    12)`` in their dtype."""
    from jaxrt._src.traversal import cpu_kernel

    rows = np.empty((node_lower.shape[0], 12), node_lower.dtype)
    cpu_kernel.box_rows(node_lower, node_upper, rows)
    return rows


#: Box rows of the structures traced at top level: ``id(node_lower) -> (node_lower, node_upper, rows)``, the
#: first two weak references, the rows a uint32 array on the CPU device. An entry is dropped when its
#: ``node_lower`` array is freed (before its id can be reused), and used only for the very arrays it was made
#: from: a JAX array never changes its values, so the rows stay those of its boxes.
_BOX_ROWS: dict[int, tuple[Any, Any, jax.Array]] = {}


def _box_rows_of(structure: Any) -> jax.Array:
    """The box rows of a concrete primitive structure's nodes (as uint32 words on the CPU device), laid out on
    its first call and kept while its node arrays live."""
    lower, upper = structure.node_lower, structure.node_upper
    entry = _BOX_ROWS.get(id(lower))
    if entry is not None and entry[0]() is lower and entry[1]() is upper:
        return entry[2]
    rows = box_rows(np.asarray(lower), np.asarray(upper))
    words = jax.device_put(rows.view(np.uint32), next(iter(lower.devices())))
    _BOX_ROWS[id(lower)] = (weakref.ref(lower), weakref.ref(upper), words)
    weakref.finalize(lower, _BOX_ROWS.pop, id(lower), None)
    return words


#: Box rows of structures traced inside ``jit`` (whose callback receives the structure's own buffers):
#: ``(address of node_lower, address of node_upper) -> (node_lower, node_upper, rows)``, the first two weak
#: references to the live arrays that own those buffers. An entry is used only while both arrays are alive,
#: not deleted (donated) and still at those addresses: a live array's buffer holds its values and nothing else.
_TRACED_ROWS: dict[tuple[int, int], tuple[Any, Any, np.ndarray]] = {}


def _owner(view: np.ndarray, candidates: Any) -> Any:
    """The live, ready JAX array among ``candidates`` whose buffer is ``view``'s memory, or ``None``; arrays
    sharded over several devices have no single buffer and are never owners."""
    for array in candidates:
        if (
            array is not None
            and array.shape == view.shape
            and array.dtype == view.dtype
            and len(array.sharding.device_set) == 1
            and not array.is_deleted()
            and array.is_ready()  # a pending buffer's address would wait, holding the GIL
            and array.unsafe_buffer_pointer() == view.ctypes.data
        ):
            return array
    return None


def _drop_traced(key: tuple[int, int], ref: Any) -> None:
    entry = _TRACED_ROWS.get(key)
    if entry is not None and entry[0] is ref:
        del _TRACED_ROWS[key]


def _box_rows_in_place(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """The box rows of node arrays a callback received (:func:`box_rows`): laid out once per structure where
    the arrays are the buffers of live JAX arrays (a structure passed to a jitted function: its buffers reach
    the callback in place), else on every call (node arrays computed inside the program)."""
    if lower.size == 0:
        return box_rows(lower, upper)
    key = (lower.ctypes.data, upper.ctypes.data)
    entry = _TRACED_ROWS.get(key)
    if entry is not None and _owner(lower, [entry[0]()]) is not None and _owner(upper, [entry[1]()]) is not None:
        return entry[2]
    rows = box_rows(lower, upper)
    live = [a for a in jax.live_arrays() if a.shape in (lower.shape, upper.shape)]
    owners = _owner(lower, live), _owner(upper, live)
    if owners[0] is not None and owners[1] is not None:
        ref = weakref.ref(owners[0])
        _TRACED_ROWS[key] = (ref, weakref.ref(owners[1]), rows)
        weakref.finalize(owners[0], _drop_traced, key, ref)
    return rows


def host_scene(structure: Any, rays: Any, *, with_rays: bool = True) -> tuple[np.ndarray, jax.Array] | None:
    """The addresses of a primitive structure's node and triangle buffers, and of the flat rays' origin,
    direction and interval where they have the scene's dtype and ``with_rays`` (the program traces them in one
    piece, not in chunks) (``(4, 2)`` or ``(8, 2)`` uint32 words), for the
    CPU traversal to read them in place instead of receiving copies through the callback, with the structure's
    box rows (:func:`_box_rows_of`, laid out once per structure instead of on every call); ``None`` where that
    is not safe: inside a trace (under ``jit``, ``vmap`` or ``grad`` an address could outlive its buffer), for
    instance structures (their node arrays are assembled inside the program), or for arrays that are not
    single-device CPU buffers.

    The addresses are valid while the program that is passed the structure runs: an executing program keeps
    its argument buffers alive, and the traversal reads them only then. The box rows are an argument of that
    program themselves.
    """
    if structure.levels:  # an instance structure
        return None
    leaves = jax.tree_util.tree_leaves((structure, rays))
    default = jnp.zeros(())  # a tracer itself inside a trace, even where every leaf is concrete (closed over)
    if any(isinstance(x, jax.core.Tracer) for x in (default, *leaves)):
        return None
    arrays = (structure.node_lower, structure.node_upper, structure.node_children, structure.leaf_triangle)
    if structure.node_children.dtype != jnp.int32 or not all(isinstance(a, jax.Array) for a in arrays):
        return None
    # Every array on the default CPU device: the program runs there on these very buffers (no transfer).
    devices = {d for x in leaves if isinstance(x, jax.Array) for d in x.devices()}
    if devices != default.devices() or next(iter(devices)).platform != "cpu":
        return None
    if any(a.is_deleted() or a.size == 0 for a in arrays):
        return None
    # The rays too, where they are arrays of the scene's dtype: enabled rays are traced as given (the
    # sanitised copy differs only in disabled rays, which the kernel skips).
    ray_arrays = (rays.origin, rays.direction, rays.min_distance, rays.max_distance)
    dtype = structure.node_lower.dtype
    n = rays.origin.shape[0] if rays.origin.ndim == 2 else -1
    shapes = ((n, 3), (n, 3), (n,), (n,))
    if with_rays and all(
        isinstance(a, jax.Array) and a.dtype == dtype and a.shape == s for a, s in zip(ray_arrays, shapes, strict=True)
    ):
        if not any(a.is_deleted() or a.size == 0 for a in ray_arrays):
            arrays += ray_arrays
    # Wait for the buffers with the GIL released: ``unsafe_buffer_pointer`` waits for a pending buffer while
    # holding it, and a program queued before the one that computes the buffer may be running a traversal
    # callback that needs the GIL (a deadlock).
    jax.block_until_ready(arrays)
    addresses = [a.unsafe_buffer_pointer() for a in arrays]
    return np.array([[a & 0xFFFFFFFF, a >> 32] for a in addresses], np.uint32), _box_rows_of(structure)


def _host_arrays(params: tuple, *args: np.ndarray, boxes: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """The traversal's outputs for callback arguments with leading vmap axes (``boxes``: the box rows of an
    unbatched scene, or ``None``)."""
    ranks = _SCENE_RANKS + _RAY_RANKS
    args = [np.asarray(a) for a in args]
    lead = [a.shape[: a.ndim - r] for a, r in zip(args, ranks, strict=True)]
    batch = np.broadcast_shapes(*lead)
    if not batch:
        return _run(params, args, boxes)
    scenes = int(np.prod(np.broadcast_shapes(*lead[:_RAYS]), dtype=np.int64))
    if scenes == 1:  # rays batched over one scene: one parallel call over all of them
        scene = [a.reshape(a.shape[a.ndim - r :]) for a, r in zip(args[:_RAYS], _SCENE_RANKS, strict=True)]
        rays = [
            np.broadcast_to(a, batch + a.shape[a.ndim - r :]) for a, r in zip(args[_RAYS:], _RAY_RANKS, strict=True)
        ]
        n = rays[0].shape[-2]
        out = _run(params, scene + [a.reshape(-1, *a.shape[len(batch) + 1 :]) for a in rays], boxes)
        return tuple(a.reshape(*batch, n, *a.shape[1:]) for a in out)
    full = [np.broadcast_to(a, batch + a.shape[a.ndim - r :]) for a, r in zip(args, ranks, strict=True)]
    results = [_run(params, [a[index] for a in full]) for index in np.ndindex(*batch)]
    return tuple(np.stack(parts).reshape(*batch, *parts[0].shape) for parts in zip(*results, strict=True))


def _analytic_mode(analytic: Any) -> int:
    """``params[9]``: 0 without analytic leaves, :data:`_FORMULA_ROWS` where they are the rows of kinds alone
    (built-in spheres, beside triangles), else 1."""
    if analytic is None:
        return 0
    return _FORMULA_ROWS if analytic.shapes & ~_LEAN_SHAPES == 0 else 1


def _params(
    layout: TraversalLayout,
    any_hit: bool,
    cull: int,
    max_hits: int | None = None,
    count_all: bool = False,
    analytic: int = 0,
    motion: bool = False,
    curve_options: tuple | None = None,
) -> tuple[int, ...]:
    """The kernel's integer parameters (static); a hit list where ``max_hits`` is given or ``count_all``;
    ``analytic``: the scene's analytic leaves (:func:`_analytic_mode`); ``motion``: primitive keyframe motion; ``curve_options``: the
    static options of the scene's curves (:class:`CurveLeaves`), ``None`` without curves."""
    hit_list = max_hits is not None or count_all
    if hit_list and (any_hit or (count_all and max_hits) or (not count_all and (max_hits or 0) < 1)):
        raise ValueError(
            "traversal.cpu: hit lists need max_hits >= 1 (0 or None with count_all) and no any_hit "
            f"(got max_hits={max_hits}, count_all={count_all}, any_hit={any_hit})"
        )
    base = (int(layout.root), int(layout.primitive_leaves), int(layout.levels), int(layout.stack_size), int(bool(any_hit)), int(cull), int(hit_list), int(max_hits or 0), int(bool(count_all)), int(analytic), int(bool(motion)))  # fmt: skip
    return base + curve_params(curve_options)


#: Integer parameters of the curve test at the end of the kernel's parameters (:func:`curve_params`).
CURVE_PARAMS = 8


def curve_params(options: tuple | None) -> tuple[int, ...]:
    """The :data:`CURVE_PARAMS` integers of the static curve options (:class:`CurveLeaves`): whether the scene
    has curves, pieces, iterations, approach iterations, disk caps compiled, sphere caps compiled, flat (0
    round, 1 flat, 2 per segment), and the tolerance's float64 bits (so that the kernel rounds it to the
    geometry's dtype as JAX rounds the Python float); zeros without curves."""
    if options is None:
        return (0,) * CURVE_PARAMS
    pieces, iterations, approach, tolerance, disk, sphere, flat = options
    bits = int(np.array(float(tolerance), np.float64).view(np.int64))
    return (1, int(pieces), int(iterations), int(approach), int(bool(disk)), int(bool(sphere)), int(flat), bits)


def _motion_arguments(scene: TraversalScene, layout: TraversalLayout, leaf_motion: Any) -> tuple:
    """The keyframe arguments of :func:`cpu_kernel.trace_rays` (node keys, leaf keys, moving leaves, float and
    integer parameters); placeholders without primitive motion (``leaf_motion`` ``None``)."""
    dtype = scene.node_lower.dtype
    t = np.dtype(dtype).type
    floats = np.ones(8, dtype)
    flags = np.zeros(3, np.int32)
    node_keys = (jnp.zeros((2, 1, 2, 3), dtype),) * 2
    leaf_keys, moving = jnp.zeros((2, 1, 3, 3), dtype), jnp.zeros((1,), jnp.int32)
    if leaf_motion is not None:
        spec, keys = leaf_motion.spec, leaf_motion.triangle
        leaf_keys, moving = keys.astype(dtype), leaf_motion.moving.astype(jnp.int32)
        # As keyframe_position rounds them: each float on its own, the span in Python floats first.
        floats[4:] = [t(spec.start_time), t(spec.end_time), t(spec.end_time - spec.start_time), t(keys.shape[0] - 1)]
        flags[1:] = [spec.start_border == "vanish", spec.end_border == "vanish"]
        if scene.node_motion is not None:
            node_spec, lower = layout.node_spec, scene.node_motion[0]
            node_keys = tuple(k.astype(dtype) for k in scene.node_motion)
            span = node_spec.end_time - node_spec.start_time
            floats[:4] = [t(node_spec.start_time), t(node_spec.end_time), t(span), t(lower.shape[0] - 1)]
            flags[0] = 1
    return (*node_keys, leaf_keys, moving, jnp.asarray(floats), jnp.asarray(flags))


def _arguments(
    scene: TraversalScene,
    origin,
    direction,
    t_min,
    t_max,
    enabled,
    mask,
    floats,
    rows=None,
    motion=(),
    time=None,
    curves=None,
) -> tuple:
    """The callback's arguments in the kernel's order; ``floats`` converts the float ones; ``rows``: the
    analytic leaves' rows (``None``: a placeholder row); ``motion``: :func:`_motion_arguments`; ``time``: the
    rays' times (``None``: zeros, read only with motion); ``curves``: the :class:`CurveLeaves` (``None``:
    placeholders, and no ray frames)."""
    dtype = scene.node_lower.dtype
    if rows is None:
        rows = jnp.zeros((1, packed.TRIANGLE_WIDTH), dtype)
    if time is None:
        time = jnp.zeros(origin.shape[:-1], origin.dtype)
    if curves is None:
        segments, curve_flags = jnp.zeros((1, 6, 4), dtype), jnp.zeros((1,), jnp.int32)
        frame = jnp.zeros((origin.shape[0], 1), origin.dtype)  # (a column: a zero-size array has no reshape)
    else:
        segments, curve_flags = curves.segments.astype(dtype), curves.flags.astype(jnp.int32)
        frame = curve_frames(origin, direction)
    node_lower_keys, node_upper_keys, leaf_keys, moving, motion_f, motion_i = motion
    return (
        floats(scene.node_lower),
        floats(scene.node_upper),
        scene.node_children.astype(jnp.int32),
        floats(scene.leaf_triangle),
        floats(scene.instance_world_to_object),
        scene.instance_child_root.astype(jnp.int32),
        scene.instance_facing.astype(jnp.int32),
        scene.instance_mask.astype(jnp.uint32),
        floats(rows.astype(scene.node_lower.dtype)),
        floats(node_lower_keys),
        floats(node_upper_keys),
        floats(leaf_keys),
        moving,
        floats(motion_f),
        motion_i,
        floats(segments),
        curve_flags,
        *(floats(a) for a in (origin, direction, t_min, t_max)),
        enabled.astype(bool),
        mask.astype(jnp.uint32),
        floats(time.astype(origin.dtype)),
        floats(frame),
    )


class CurveLeaves(NamedTuple):
    """The curve leaves of a primitive structure as the CPU traversal reads them."""

    segments: jax.Array  # (P, 6, 4) every primitive leaf's packed segment (zeros for other kinds)
    flags: jax.Array  # (P,) int32 the segments' flags (IS_CURVE marks curve leaves)
    # static: (pieces, iterations, approach_iterations, tolerance, any disk caps, any sphere caps, flat), as
    # jaxrt._src.traversal.gpu.CurveLeaves.options
    options: tuple


def curve_frames(origin: jax.Array, direction: jax.Array) -> jax.Array:
    """``(N, 10)``: each ray's :func:`jaxrt._src.primitives.curve.curve_ray` frame row by row, then ``1 / |d|``
    (computed by XLA, as the portable curve test computes it)."""
    ray = jax.vmap(curve.curve_ray)(lax.stop_gradient(origin), lax.stop_gradient(direction))
    return jnp.concatenate([ray.frame.reshape(-1, 9), ray.inv_length[:, None]], axis=-1)


def kernel_arguments(
    scene: TraversalScene,
    layout: TraversalLayout,
    rays: TraversalRays,
    *,
    any_hit: bool,
    cull: int,
    max_hits: int | None = None,
    count_all: bool = False,
    analytic: Any = None,
    leaf_motion: Any = None,
    curves: CurveLeaves | None = None,
) -> tuple[tuple[int, ...], list[np.ndarray]]:
    """``(params, arrays)`` for calling the compiled traversal directly on host arrays (outside ``jit``), as
    :func:`trace_scene` would for ``rays`` (the other arguments as there): for benchmarks
    (:func:`jaxrt._src.pipeline.cpu_kernel_arguments`)."""
    moving = leaf_motion is not None
    options = None if curves is None else curves.options
    params = _params(layout, any_hit, cull, max_hits, count_all, _analytic_mode(analytic), moving, options)
    rows = None if analytic is None else analytic.rows
    motion = _motion_arguments(scene, layout, leaf_motion)
    args = _arguments(scene, *rays[:6], lambda a: a, rows, motion, rays.time if moving else None, curves)
    return params, [np.ascontiguousarray(a) for a in args]


def trace_scene(
    scene: TraversalScene,
    layout: TraversalLayout,
    origin: jax.Array,
    direction: jax.Array,
    t_min: jax.Array,
    t_max: jax.Array,
    enabled: jax.Array,
    mask: jax.Array,
    *,
    any_hit: bool,
    cull: int,
    max_hits: int | None = None,
    count_all: bool = False,
    analytic: Any = None,
    time: jax.Array | None = None,
    leaf_motion: Any = None,
    curves: CurveLeaves | None = None,
    host: Any = None,
) -> TraversalResult:
    """Trace rays through a scene of any instance depth with the compiled CPU traversal.

    Args:
      scene: the global node arrays (:func:`jaxrt._src.scene_view.traversal_scene`), float32 or float64; the
        rays must have the same float dtype.
      layout: its static layout (root, primitive leaves, levels, stack size).
      origin, direction: ``(N, 3)`` world-space rays; a disabled ray must still have a non-zero direction.
      t_min, t_max: ``(N,)`` accepted distance interval (world units at every level).
      enabled: ``(N,)`` bool; disabled rays miss (distance ``-inf``) and take no step.
      mask: ``(N,)`` uint32 ray masks; an instance is entered only where ``instance_mask & mask != 0``.
      any_hit: stop at the first accepted hit.
      cull: 0 culls nothing, +1 clockwise triangles, -1 counterclockwise ones; below instances the sense is
        multiplied by the chain's ``instance_facing``.
      max_hits: static ``K``: also keep the ``K`` nearest hits of each ray in ``hits`` (a
        :class:`~jaxrt._src.traversal.step.HitList`, as the portable traversal's ``max_hits``, with each hit's
        instance chain below instances; not with ``any_hit``). ``0`` with ``count_all``.
      count_all: static; count every accepted hit in ``hits.total`` (no culling), at any instance depth.
      analytic: the parameter rows of the scene's analytic leaves in the scene's dtype
        (:func:`jaxrt._src.traversal.gpu.analytic_leaves`): bounding-box leaves tested as the built-in
        intersection functions test them.
      time: ``(N,)`` each ray's time (read with ``leaf_motion`` only).
      leaf_motion: primitive keyframe motion of a primitive structure of triangles
        (:func:`jaxrt._src.traversal.gpu.leaf_motion`), or ``None``: node boxes (``scene.node_motion``) and
        triangles are blended at each ray's time as the portable step blends them.
      curves: the :class:`CurveLeaves` of a primitive structure with curves (``None``: none): its curve leaves
        are tested with the shared curve formula (:mod:`jaxrt._src.traversal.cpu_curves`).
      host: ``None``, or the addresses of ``scene``'s node and triangle arrays and maybe of the rays, with
        the structure's box rows (:func:`host_scene`): the arrays of a primitive structure and rays passed to
        the running program, read in place (a disabled ray's own values are read, and skipped).

    Returns:
      The portable traversal's :class:`~jaxrt._src.traversal.scene.TraversalResult`; with ``max_hits`` or
      ``count_all`` its ``hits`` too (then ``leaf`` is the first hit and ``distance`` the culling bound); with
      ``curves`` its ``curve``: the curve parameter and part of each ray's ``leaf`` where that is a curve,
      tested again in the ray's interval (the exact test the result fields would repeat).
    """
    dtype = scene.node_lower.dtype
    if origin.dtype != dtype:
        raise ValueError(f"traversal.cpu.trace_scene: rays are {origin.dtype} but the scene is {dtype}")
    levels = int(layout.levels)
    moving = leaf_motion is not None
    if moving and levels:
        raise ValueError("traversal.cpu.trace_scene: keyframe motion is traced in primitive structures only")
    if curves is not None and levels:
        raise ValueError("traversal.cpu.trace_scene: curves are traced in primitive structures only")
    options = None if curves is None else curves.options
    params = _params(layout, any_hit, cull, max_hits, count_all, _analytic_mode(analytic), moving, options)
    hit_list, k = bool(params[6]), params[7]
    detached = lax.stop_gradient
    wide = jnp.dtype(dtype).itemsize == 8
    words = lambda a: lax.bitcast_convert_type(detached(a).astype(dtype), jnp.uint32) if wide else detached(a)  # noqa: E731
    rows = None if analytic is None else analytic.rows
    motion = jax.tree_util.tree_map(detached, _motion_arguments(scene, layout, leaf_motion))
    args = _arguments(
        scene, origin, direction, t_min, t_max, enabled, mask, words, rows, motion, time if moving else None, curves
    )
    n = origin.shape[0]
    shapes = (
        jax.ShapeDtypeStruct((n, 2), jnp.uint32) if wide else jax.ShapeDtypeStruct((n,), dtype),
        jax.ShapeDtypeStruct((n,), jnp.int32),
        jax.ShapeDtypeStruct((n, levels), jnp.int32),
        jax.ShapeDtypeStruct((n,), jnp.int32),
        jax.ShapeDtypeStruct((n,), jnp.int32),
        jax.ShapeDtypeStruct((n,), jnp.bool_),
    )
    if hit_list:
        shapes += (
            jax.ShapeDtypeStruct((n, k, 2), jnp.uint32) if wide else jax.ShapeDtypeStruct((n, k), dtype),
            jax.ShapeDtypeStruct((n, k), jnp.int32),
            jax.ShapeDtypeStruct((n,), jnp.int32),
            jax.ShapeDtypeStruct((n, k, levels), jnp.int32),
        )
    if curves is not None:
        shapes += (
            jax.ShapeDtypeStruct((n, 2), jnp.uint32) if wide else jax.ShapeDtypeStruct((n,), dtype),
            jax.ShapeDtypeStruct((n,), jnp.int32),
        )
    hosted = None
    if host is not None:  # arrays read in place (see host_scene): the scene's, and maybe the rays'
        host, boxes = host
        in_place = (0, 1, 2, 3) if host.shape[0] == 4 else (0, 1, 2, 3, _RAYS, _RAYS + 1, _RAYS + 2, _RAYS + 3)
        sources = (scene.node_lower, scene.node_upper, scene.node_children, scene.leaf_triangle, origin, direction, t_min, t_max)  # fmt: skip
        hosted = tuple(
            (i, tuple(a.shape), jnp.dtype(a.dtype).name)
            for i, a in zip(in_place, sources[: len(in_place)], strict=True)
        )
        # One element of each array read in place goes along: the program then uses, and so holds, every such
        # buffer until it finishes (jit does not pass a program the arguments it does not use).
        anchors = jnp.concatenate(
            [lax.bitcast_convert_type(detached(a).reshape(-1)[:1], jnp.uint8).reshape(-1) for a in sources]
        )
        args = (jnp.asarray(host, jnp.uint32), anchors, boxes, *(a for i, a in enumerate(args) if i not in in_place))
    callback = functools.partial(_host, params, wide, hosted)
    if _buffer_callback is not None:
        out = _buffer_callback(functools.partial(_host_into, callback), shapes, vmap_method="expand_dims")(*args)
    else:  # pragma: no cover - depends on the jax version
        out = jax.pure_callback(callback, shapes, *args, vmap_method="expand_dims")
    floats = lambda a: lax.bitcast_convert_type(a, dtype) if wide else a  # noqa: E731
    hits = None
    if hit_list:
        distances, leaves, total, chains = out[6:10]
        hits = HitList(floats(distances), leaves, total, chains if levels else None)
    nearest = None
    if curves is not None:
        nearest = (floats(out[-2]), out[-1])
    return TraversalResult(floats(out[0]), *out[1:6], hits, nearest)
