"""GPU traversal: a Triton kernel called through jax-triton, behind the same contract as the portable traversal.

The intersector picks this path (``backend="auto"`` or ``"gpu"``) when :func:`unavailable_reason` returns
``None``: the default JAX backend is a GPU, Triton and jax-triton import (``pip install jaxrt[gpu]``), geometry
is float32, and the intersector asks only for what the kernel covers (triangles, nearest and any hit, cull
modes and windings, ray intervals and disabled rays, several geometries per structure, the ``triangle_data``
and ``stats`` tags). Triton is imported only here and only when a trace is compiled, so CPU-only installs
never import it.

The kernel traces the structure's binary nodes by default; ``KernelOptions(node_width=4)`` traces a 4-wide tree
with leaf clusters collapsed from them on every call (slower on an H200: docs/performance.md).

What the kernel computes, and why it equals the portable path, is in
:mod:`jaxrt._src.traversal.triton_kernel`; the arrays it reads are in :mod:`jaxrt._src.traversal.packed`.

Composition:
  - ``jax.jit``: the kernel is one XLA custom call.
  - ``jax.vmap`` over ray batches: a batching rule folds the batch axis into the ray axis (one launch).
  - ``jax.vmap`` over (rays, structure) pairs: the rule falls back to the portable stack traversal, vmapped
    over the structures (the kernel traces one structure per launch).
  - ``jax.grad``: the kernel only picks the leaf; its inputs are detached and the intersector re-computes the
    hit differentiably, so no derivative of the kernel is needed.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxrt._src.primitives import box
from jaxrt._src.traversal import packed
from jaxrt._src.traversal.stack import TraversalResult, traverse

__all__ = ["KernelOptions", "unavailable_reason", "trace", "COVERED_TAGS", "MAX_PROGRAMS"]

#: Intersector tags whose fields the GPU path can produce (the intersector re-computes them from the leaf).
COVERED_TAGS = frozenset({"triangle_data", "stats", "primitive_data"})
#: Most programs per launch; larger batches are walked with a stride, which bounds the stack scratch buffer
#: to ``MAX_PROGRAMS * rays_per_program * stack depth`` int32 (about 230 MB for a 2**24-leaf structure).
MAX_PROGRAMS = 1 << 15
#: Leading arguments of the kernel call that come from the structure (the rest are rays).
STRUCTURE_ARGS = 5


@dataclasses.dataclass(frozen=True)
class KernelOptions:
    """Static code-generation choices of the kernel (all give the same results except ``fp_fusion``).

    Attributes:
      rays_per_program: rays traced by one program of one warp (32: one ray per thread; 64: two, which gives
        each thread two independent traversals to interleave but runs until the slower of 64 rays ends).
      vector_loads: read node and triangle rows with 16-byte loads instead of one load per float.
      leaf_branch: skip a leaf test that no ray of the warp needs, with a warp-uniform branch.
      fp_fusion: let the compiler contract multiply-adds into FMAs. Off by default: with contraction an edge
        function can take the wrong sign where its two products nearly cancel (see the kernel module).
      node_width: 2 traces the structure's binary nodes (step for step the portable traversal's decisions);
        4 traces a 4-wide tree with leaf clusters, collapsed from them on every call
        (:func:`~jaxrt._src.traversal.packed.pack_wide_nodes`): the same nearest distances, but the choice
        among equally distant triangles and the first hit of an any-hit query may differ.
      leaf_size: most leaves in one leaf cluster of the 4-wide tree (1-4).

    The defaults were the fastest on an H200 (``python -m jaxrt.bench.gpu --variants``).
    """

    rays_per_program: int = 32
    vector_loads: bool = True
    leaf_branch: bool = True
    fp_fusion: bool = False
    node_width: int = 2
    leaf_size: int = 4

    def __post_init__(self):
        if self.node_width not in (2, 4):
            raise ValueError(f"KernelOptions: node_width must be 2 or 4, got {self.node_width}")
        if not 1 <= self.leaf_size <= packed.MAX_LEAF_SIZE:
            raise ValueError(f"KernelOptions: leaf_size must be in 1..{packed.MAX_LEAF_SIZE}, got {self.leaf_size}")


DEFAULT_OPTIONS = KernelOptions()


@functools.lru_cache(maxsize=1)
def _import_error() -> str | None:
    try:
        import jax_triton  # noqa: F401
        import triton  # noqa: F401
    except ImportError as error:  # pragma: no cover - depends on the install
        return f"Triton or jax-triton cannot be imported ({error}); install jaxrt[gpu] on a CUDA machine"
    return None


def unavailable_reason(intersector: Any) -> str | None:
    """Why the GPU kernel cannot run ``intersector`` here, or ``None`` when it can."""
    backend = jax.default_backend()
    if backend != "gpu":
        return f"the default JAX backend is {backend!r}; the kernel needs a CUDA GPU"
    if jax.config.jax_enable_x64:
        return "jax_enable_x64 stores geometry in float64; the kernel traces float32 structures"
    uncovered = sorted({tag.name for tag in intersector.tags} - COVERED_TAGS)
    if uncovered:
        return f"tags {uncovered} are not covered by the GPU kernel"
    if "curve" in (getattr(intersector, "geometry_types", None) or ()) or getattr(intersector, "curve_type", None):
        return "curves are not covered by the GPU kernel (structures with curves take the portable traversal)"
    return _import_error()


def _launch(
    nodes: jax.Array,
    triangles: jax.Array,
    rays: jax.Array,
    *,
    any_hit: bool,
    cull: int,
    stack: int,
    options: KernelOptions,
) -> tuple[jax.Array, ...]:
    """One kernel launch over a packed ray block ``(16, size)``: ``(distance, leaf, visited, tested, overflow)``."""
    import jax_triton as jt

    from jaxrt._src.traversal import triton_kernel

    size = rays.shape[1]
    lanes = options.rays_per_program
    programs = max(1, min(size // lanes, MAX_PROGRAMS))
    if options.node_width == 4:
        stack = packed.wide_stack_size(stack)
        kernel, extra = triton_kernel.trace_wide_kernel, {}
    else:
        kernel, extra = triton_kernel.trace_kernel, dict(BRANCH=options.leaf_branch)
    out_shape = [
        jax.ShapeDtypeStruct((size,), jnp.float32),
        jax.ShapeDtypeStruct((size,), jnp.int32),
        jax.ShapeDtypeStruct((size,), jnp.int32),
        jax.ShapeDtypeStruct((size,), jnp.int32),
        jax.ShapeDtypeStruct((size,), jnp.int32),
        jax.ShapeDtypeStruct((programs * stack * lanes,), jnp.int32),  # stack scratch, never read back
    ]
    out = jt.triton_call(
        nodes,
        triangles,
        rays,
        size,
        programs,
        kernel=kernel,
        out_shape=out_shape,
        grid=(programs,),
        num_warps=1,
        num_stages=1,
        enable_fp_fusion=options.fp_fusion,
        STACK=stack,
        ANY_HIT=any_hit,
        CULL=cull,
        FAR_SCALE=float(np.float32(box.FAR_SCALE)),
        PARALLEL=float(np.float32(box.PARALLEL_RECIPROCAL)),
        LANES=lanes,
        VECTOR=options.vector_loads,
        **extra,
    )
    return tuple(out[:5])


def pack_nodes(options: KernelOptions, node_lower, node_upper, node_children, node_range) -> jax.Array:
    """The node rows the kernel of ``options`` reads (binary or 4-wide)."""
    if options.node_width == 4:
        return packed.pack_wide_nodes(node_lower, node_upper, node_children, node_range, options.leaf_size)
    return packed.pack_nodes(node_lower, node_upper, node_children)


def _kernel(
    node_lower,
    node_upper,
    node_children,
    node_range,
    leaf_triangle,
    origin,
    direction,
    t_min,
    t_max,
    enabled,
    *,
    options,
    **config,
):
    """Pack the structure and the rays, launch the kernel, and drop the padding rays."""
    n = origin.shape[0]
    lanes = options.rays_per_program
    size = max(lanes, -(-n // lanes) * lanes)
    nodes = pack_nodes(options, node_lower, node_upper, node_children, node_range)
    triangles = packed.pack_triangles(leaf_triangle)
    rays = packed.pack_rays(origin, direction, t_min, t_max, enabled, size)
    out = _launch(nodes, triangles, rays, options=options, **config)
    return tuple(a[:n] for a in out)


def _portable(
    node_lower,
    node_upper,
    node_children,
    node_range,
    leaf_triangle,
    origin,
    direction,
    t_min,
    t_max,
    enabled,
    *,
    any_hit,
    cull,
    stack,
):
    """The portable stack traversal over one structure (the fallback for batched structures)."""
    from jaxrt._src.intersector import _TriangleLeaves

    leaves = _TriangleLeaves(leaf_triangle, cull)
    fn = functools.partial(traverse, node_lower, node_upper, node_children, leaves, any_hit=any_hit, stack_size=stack)
    result = jax.vmap(fn)(origin, direction, t_min, t_max, enabled)
    return (
        result.distance,
        result.leaf,
        result.nodes_visited,
        result.primitives_tested,
        result.stack_overflow.astype(jnp.int32),
    )


@functools.cache
def _traversal(any_hit: bool, cull: int, stack: int, options: KernelOptions):
    """The kernel call for one static configuration, with its batching rule."""
    config = dict(any_hit=any_hit, cull=cull, stack=stack)

    @jax.custom_batching.custom_vmap
    def call(*args):
        return _kernel(*args, options=options, **config)

    @call.def_vmap
    def rule(axis_size, in_batched, *args):
        if any(in_batched[:STRUCTURE_ARGS]):
            in_axes = [0 if b else None for b in in_batched]
            fn = functools.partial(_portable, **config)
            return jax.vmap(fn, in_axes=in_axes, axis_size=axis_size)(*args), (True,) * 5
        structure_args, ray_args = args[:STRUCTURE_ARGS], args[STRUCTURE_ARGS:]
        rays = [
            a if b else jnp.broadcast_to(a, (axis_size, *a.shape))
            for a, b in zip(ray_args, in_batched[STRUCTURE_ARGS:], strict=True)
        ]
        n = rays[0].shape[1]
        out = call(*structure_args, *(a.reshape(axis_size * n, *a.shape[2:]) for a in rays))
        return tuple(a.reshape(axis_size, n) for a in out), (True,) * 5

    return call


def trace(
    structure: Any,
    origin: jax.Array,
    direction: jax.Array,
    t_min: jax.Array,
    t_max: jax.Array,
    enabled: jax.Array,
    *,
    any_hit: bool,
    cull: int,
    options: KernelOptions | None = None,
) -> TraversalResult:
    """Trace rays with the GPU kernel.

    Args:
      structure: a :class:`~jaxrt.PrimitiveAccelerationStructure` (float32).
      origin, direction: ``(N, 3)``; a disabled ray must still have a non-zero direction.
      t_min, t_max: ``(N,)`` accepted distance interval.
      enabled: ``(N,)`` bool; disabled rays miss and take no step.
      any_hit: stop at the first accepted hit.
      cull: 0 culls nothing, +1 clockwise triangles, -1 counterclockwise ones.
      options: code-generation choices (static); ``None`` takes :data:`DEFAULT_OPTIONS` at call time.

    Returns:
      A :class:`~jaxrt._src.traversal.stack.TraversalResult` equal to the portable traversal's: the leaf
      (-1 on a miss) and its distance (the initial bound on a miss), nodes visited, primitives tested, and
      the stack overflow flag (never set: the stack has the structure's depth bound).
    """
    kinds = sorted({g.kind for g in structure.geometry_info} - {"triangle"})
    if kinds:
        raise NotImplementedError(f"traversal.gpu.trace: geometry kinds {kinds} are not covered by the GPU kernel")
    call = _traversal(bool(any_hit), int(cull), int(structure.max_depth), options or DEFAULT_OPTIONS)
    args = (
        structure.node_lower,
        structure.node_upper,
        structure.node_children,
        structure.node_range,
        structure.leaf_triangle,
        origin,
        direction,
        t_min,
        t_max,
        enabled,
    )
    distance, leaf, visited, tested, overflow = call(*(lax.stop_gradient(a) for a in args))
    return TraversalResult(distance, leaf, visited, tested, overflow.astype(bool))
