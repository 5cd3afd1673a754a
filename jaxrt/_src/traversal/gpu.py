"""GPU traversal: a Triton kernel called through jax-triton, behind the same contract as the portable traversal.

:func:`trace_scene` traces a :class:`~jaxrt._src.traversal.scene.TraversalScene` (any number of instance
levels; a primitive structure is a scene of zero levels) and returns the
:class:`~jaxrt._src.traversal.scene.TraversalResult` of the portable traversal: the same leaf, distance and
instance chain (:func:`jaxrt._src.pipeline.gpu_trace` is the same for a primitive structure).

The intersector picks this path (``backend="auto"`` or ``"gpu"``) when :func:`unavailable_reason` returns
``None``: the default JAX backend is a GPU, Triton and jax-triton import (``pip install jaxrt[gpu]``), geometry
is float32, and the intersector asks only for what the kernel covers (triangles, bounding boxes whose
intersection functions are the built-in sphere, disk and capped cylinder (:func:`analytic_leaves`; not with
keyframe motion), round and flat curves of a static primitive structure (:mod:`jaxrt._src.traversal.triton_curves`;
:func:`curve_leaves`; not in one structure with boxes), nearest and any hit, cull modes and windings, ray
intervals, masks and disabled rays, several geometries per structure, instances over any number of levels,
keyframe motion of triangles and instances at each ray's time, the ``K`` nearest hits of ``max_hits`` with each
hit's instance chain, counting every hit, and the tags of :data:`COVERED_TAGS`). Triton is imported only here
and only when a trace is compiled, so CPU-only installs never import it.

The kernel traces the scene's binary nodes by default; ``KernelOptions(node_width=4)`` traces a 4-wide tree
with leaf clusters collapsed from them on every call (slower on an H200: docs/performance.md). The 4-wide
layout covers one primitive structure only: instanced scenes, scenes with keyframe motion and batches of
scenes take the binary layout. With keyframe motion the kernel also reads the keyframe rows of
:mod:`jaxrt._src.traversal.packed` (nodes, triangles, instance transforms) and each ray's time: pass ``time``
and :func:`leaf_motion` to :func:`trace_scene`.

What the kernel computes, and why it equals the portable path, is in
:mod:`jaxrt._src.traversal.triton_kernel`; the arrays it reads are in :mod:`jaxrt._src.traversal.packed`.

Composition:
  - ``jax.jit``: the kernel is one XLA custom call.
  - ``jax.vmap`` over ray batches: a batching rule folds the batch axis into the ray axis (one launch).
  - ``jax.vmap`` over (rays, scene) pairs: the rule concatenates the scenes' arrays with per-scene index
    offsets (one elementwise pass), gives each ray its scene's root node, launches once, and maps leaf and
    instance ids back to each scene's numbering.
  - ``jax.grad``: the kernel only picks the leaf; its inputs are detached and the intersector re-computes the
    hit differentiably, so no derivative of the kernel is needed.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxrt._src import numerics
from jaxrt._src.kinds import registry
from jaxrt._src.kinds.registry import BOUNDING_BOX, TRIANGLE
from jaxrt._src.motion import KeyframePosition, spec_position
from jaxrt._src.primitives import analytic, box, curve
from jaxrt._src.traversal import analytic_rows, kernel_cache, packed
from jaxrt._src.traversal.scene import TraversalLayout, TraversalResult, TraversalScene
from jaxrt._src.traversal.step import HitList

__all__ = [
    "AnalyticLeaves",
    "KernelOptions",
    "DEFAULT_OPTIONS",
    "COVERED_TAGS",
    "MAX_PROGRAMS",
    "unavailable_reason",
    "trace_scene",
    "analytic_leaves",
]

#: Intersector tags whose fields the GPU path can produce: every tag (:data:`jaxrt._src.kinds.registry.RESULT_TAGS`),
#: since the intersector re-computes the fields from the leaf and the instance chain.
COVERED_TAGS = registry.RESULT_TAGS
#: Most programs per launch; larger batches are walked with a stride, which bounds the scratch buffers (stack,
#: and per-level rays below instances) to ``MAX_PROGRAMS * rays_per_program`` times the entries per ray.
MAX_PROGRAMS = 1 << 15
#: Programs per launch with :attr:`KernelOptions.work_stealing` (at most): about what an H200 keeps resident
#: (132 multiprocessors, 28 one-warp programs each at the kernel's 64-69 registers), twice over.
STEALING_PROGRAMS = 1 << 13
#: Leading arguments of the kernel call that come from the scene (the rest are per ray).
SCENE_ARGS = 16
#: Per-ray arguments after them (origin, direction, t_min, t_max, enabled, mask, time, cursor distance, cursor
#: leaf, root); a prepacked call appends the structure's node and triangle rows
#: (:class:`~jaxrt._src.traversal.packed.KernelLayout`).
RAY_ARGS = 10
#: The position of the cursor leaf among them.
CURSOR_LEAF = 8


#: Default :attr:`KernelOptions.curve_batch`; the environment variable ``JAXRT_CURVE_BATCH`` (read at import)
#: overrides it, so that benches can compare thresholds without editing code.
CURVE_BATCH = int(os.environ.get("JAXRT_CURVE_BATCH", "16"))


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
        among equally distant triangles and the first hit of an any-hit query may differ. One primitive
        structure only: instanced scenes and batches of scenes are traced with the binary nodes.
      leaf_size: most leaves in one leaf cluster of the 4-wide tree (1-4).
      curve_batch: with curve leaves (binary nodes, ``leaf_branch``), a ray whose step needs a curve test waits
        until this many rays of the warp wait (or none other can step), so that one warp-wide curve test serves
        them all; the other rays keep taking steps meanwhile. Each ray makes the same decisions either way.
        0 tests curves on sight (each step that needs one runs the whole test for the warp).
      fused_rays: where the rays need only the basic ray block (a primitive structure without motion, analytic
        leaves or curves; binary nodes; float32 rays), the kernel reads the caller's ray arrays and computes
        each ray's reciprocal direction and shear itself, as the packing does, instead of a ray block packed
        by a separate XLA program per call. The same results either way; on an H200 ``intersect`` gained
        1.10-1.13x on primary rays into small meshes, 1.02-1.05x on primary rays into 1M-triangle scenes and
        0.97-1.02x on diffuse and shadow rays (docs/performance.md, "Fused rays").
      work_stealing: binary nodes without a hit list: at most :data:`STEALING_PROGRAMS` programs, each taking the
        next untraced block of rays from a counter in device memory (an atomic add) until none is left, instead
        of one program per block (or a fixed stride). The same results; on an H200 1.02-1.09x on the sphere,
        0.99-1.01x elsewhere (docs/performance.md, "Where the kernel's time goes").

    The defaults were the fastest on an H200 (``python -m jaxrt.bench.gpu --variants``).
    """

    rays_per_program: int = 32
    vector_loads: bool = True
    leaf_branch: bool = True
    fp_fusion: bool = False
    node_width: int = 2
    leaf_size: int = 4
    curve_batch: int = CURVE_BATCH
    fused_rays: bool = True
    work_stealing: bool = True

    def __post_init__(self):
        if self.node_width not in (2, 4):
            raise ValueError(f"KernelOptions: node_width must be 2 or 4, got {self.node_width}")
        if not 1 <= self.leaf_size <= packed.MAX_LEAF_SIZE:
            raise ValueError(f"KernelOptions: leaf_size must be in 1..{packed.MAX_LEAF_SIZE}, got {self.leaf_size}")
        if not 0 <= self.curve_batch <= 255:
            raise ValueError(f"KernelOptions: curve_batch must be in 0..255, got {self.curve_batch}")


DEFAULT_OPTIONS = KernelOptions()


@dataclasses.dataclass(frozen=True)
class _Config:
    """Everything static about one kernel call (hashable: compiled traces are cached by it)."""

    any_hit: bool
    cull: int
    stack: int  # stack entries (the layout's bound)
    levels: int  # instance levels (0: a primitive structure)
    primitive_leaves: int  # leaves below this are primitives, the rest instances
    options: KernelOptions
    roots: bool  # each ray starts at its own root node (instanced scenes, batches of scenes)
    node_keys: int = 0  # keyframes of the node boxes (0: static boxes)
    leaf_keys: int = 0  # keyframes of the leaf triangles (0: static triangles)
    instance_keys: int = 0  # keyframes of the instance transforms (0: no instance motion)
    leaf_spec: Any = None  # the MotionSpec of the node and leaf keyframes
    prepacked: bool = False  # the node and triangle rows come with the arguments (packed at build time)
    max_hits: int = 0  # keep this many nearest hits per ray (0: the nearest hit only)
    count: bool = False  # count every accepted hit (no hit list)
    analytic: int = 0  # analytic leaves: bits 0-2 and 5 their shapes, bit 3 triangles too (0: triangles only)
    curves: tuple = ()  # with curve leaves: CurveLeaves.options (pieces, ..., disk, sphere, flat)
    cursor: bool = False  # candidate waves: list only candidates past each ray's cursor, in (distance, leaf) order

    @property
    def hit_list(self) -> bool:
        return bool(self.max_hits or self.count)

    @property
    def motion(self) -> bool:
        return bool(self.node_keys or self.leaf_keys or self.instance_keys)


class FusedRays(NamedTuple):
    """The caller's rays, read by the kernel itself (``KernelOptions.fused_rays``): float32 ``(N, 3)`` origins
    and directions, ``(N,)`` intervals and enabled flags, traced in ``size`` lanes (a multiple of the rays per
    program; the lanes past ``N`` are disabled rays)."""

    origin: jax.Array
    direction: jax.Array
    t_min: jax.Array
    t_max: jax.Array
    enabled: jax.Array
    size: int


class KernelCall(NamedTuple):
    """One launch, independent of how it is run (jax-triton on a GPU, or Triton's interpreter in tests)."""

    kernel: str  # name of the kernel in :mod:`jaxrt._src.traversal.triton_kernel`
    programs: int
    args: tuple  # the kernel's inputs, arrays and ints, in parameter order
    out_shape: tuple  # outputs (the results first, then scratch buffers that are never read back)
    params: dict  # compile-time constants
    results: int = 0  # leading outputs read back (0: the traversal result, 6 or 5)
    zeroed: tuple = ()  # outputs set to zero before the launch (the work-stealing counter)


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
    return _import_error()


def _level_shift(levels: int) -> int:
    """Bits of a stack entry that hold its level below instances (the entry is ``entry << shift | level``)."""
    return max(1, levels.bit_length())


def _check_indices(nodes: int, instances: int, levels: int) -> None:
    """Stack entries of an instanced scene keep their level in the low bits: the indices must leave room."""
    limit = 1 << (31 - _level_shift(levels))
    if levels and (nodes >= limit or instances >= limit):
        raise ValueError(
            f"traversal.gpu: {nodes} nodes and {instances} instances over {levels} levels exceed the kernel's "
            f"index range ({limit}); trace this scene with the portable traversal"
        )


def kernel_call(
    nodes: jax.Array,
    triangles: jax.Array,
    instances: jax.Array,
    rays: jax.Array | FusedRays,
    config: _Config,
    instance_motion: jax.Array | None = None,
    curves: jax.Array | None = None,
):
    """The :class:`KernelCall` tracing the packed ``rays`` block (or the caller's arrays, :class:`FusedRays`)
    through the packed scene (with keyframe motion, ``nodes`` and ``triangles`` are the rows per keyframe and
    ``instance_motion`` the instance motion rows; with curves, ``curves`` the curve rows:
    :mod:`jaxrt._src.traversal.packed`)."""
    fused = isinstance(rays, FusedRays)
    size = rays.size if fused else rays.shape[1]
    options = config.options
    lanes = options.rays_per_program
    steal = options.work_stealing and options.node_width == 2 and not config.hit_list
    cap = min(MAX_PROGRAMS, STEALING_PROGRAMS) if steal else MAX_PROGRAMS
    programs = max(1, min(size // lanes, cap))
    params = dict(
        ANY_HIT=config.any_hit,
        CULL=config.cull,
        FAR_SCALE=float(np.float32(box.FAR_SCALE)),
        PARALLEL=float(np.float32(box.PARALLEL_RECIPROCAL)),
        LANES=lanes,
        VECTOR=options.vector_loads,
    )
    results = (
        jax.ShapeDtypeStruct((size,), jnp.float32),  # distance
        jax.ShapeDtypeStruct((size,), jnp.int32),  # leaf
        jax.ShapeDtypeStruct((size,), jnp.int32),  # nodes visited
        jax.ShapeDtypeStruct((size,), jnp.int32),  # primitives tested
        jax.ShapeDtypeStruct((size,), jnp.int32),  # stack overflow
    )
    if options.node_width == 4:
        stack = packed.wide_stack_size(config.stack)
        scratch = (jax.ShapeDtypeStruct((programs * stack * lanes,), jnp.int32),)
        params.update(STACK=stack)
        return KernelCall("trace_wide_kernel", programs, (nodes, triangles, rays, size, programs), results + scratch, params)  # fmt: skip
    levels = config.levels
    clamp = np.float32(numerics.RECIPROCAL_CLAMP)
    params.update(
        STACK=config.stack,
        BRANCH=options.leaf_branch,
        LEVELS=levels,
        ROOTS=config.roots,
        SHIFT=_level_shift(levels),
        CLAMP=float(clamp),
        HUGE=float(np.float32(1.0 / numerics.RECIPROCAL_CLAMP)),
        CLAMPED=float(np.float32(1.0) / clamp),
        NODE_KEYS=config.node_keys,
        LEAF_KEYS=config.leaf_keys,
        IWIDTH=4 + 12 * config.instance_keys if config.instance_keys else 0,
    )
    params.update(MAX_HITS=config.max_hits, COUNT=config.count, ANALYTIC=config.analytic)
    pieces, iterations, approach, tolerance, disk, sphere, flat = config.curves or (1, 0, 0, 0.0, False, False, 0)
    params.update(
        CURVES=bool(config.curves),
        PIECES=pieces,
        ITERATIONS=iterations,
        APPROACH=approach,
        TOLERANCE=float(np.float32(tolerance)),
        DISK=disk,
        SPHERE=sphere,
        FLAT=flat,
    )
    batched = config.curves and levels == 0 and options.leaf_branch
    params.update(CURVE_BATCH=min(options.curve_batch, lanes) if batched else 0)
    params.update(CURSOR=config.cursor, FUSED_RAYS=fused, STEAL=steal)
    k = config.max_hits
    extra = (
        jax.ShapeDtypeStruct((max(1, levels * size),), jnp.int32),  # instance chain, (levels, size)
        jax.ShapeDtypeStruct((max(1, k * size),), jnp.float32),  # hit list distances, (K, size)
        jax.ShapeDtypeStruct((max(1, k * size),), jnp.int32),  # hit list leaves, (K, size)
        jax.ShapeDtypeStruct((size if config.hit_list else 1,), jnp.int32),  # hits accepted
        jax.ShapeDtypeStruct((max(1, k * levels * size),), jnp.int32),  # hit list chains, (K, levels, size)
        jax.ShapeDtypeStruct((programs * config.stack * lanes,), jnp.int32),  # stack scratch
        jax.ShapeDtypeStruct((max(1, programs * (levels + 1) * 8 * lanes),), jnp.float32),  # per-level rays
        jax.ShapeDtypeStruct((1,), jnp.int32),  # blocks taken (work stealing)
    )
    if instance_motion is None:
        instance_motion = jnp.zeros((1,), jnp.float32)
    if curves is None:
        curves = jnp.zeros((1,), jnp.float32)
    if fused:
        ray_args = (rays.origin, size, programs, config.primitive_leaves, instance_motion, curves, *rays[1:5])
        ray_args += (rays.origin.shape[0],)
    else:
        unread = jnp.zeros((1,), jnp.float32)
        ray_args = (rays, size, programs, config.primitive_leaves, instance_motion, curves, unread, unread, unread)
        ray_args += (jnp.zeros((1,), bool), size)
    args = (nodes, triangles, instances, *ray_args)
    zeroed = (len(results) + len(extra) - 1,) if steal else ()
    return KernelCall("trace_kernel", programs, args, results + extra, params, 10 if config.hit_list else 6, zeroed)


def _launch(call: KernelCall) -> tuple[jax.Array, ...]:
    """Run one :class:`KernelCall` through jax-triton: ``(distance, leaf, visited, tested, overflow[, chain])``."""
    import jax_triton as jt

    from jaxrt._src.traversal import triton_kernel

    kernel_cache.install()
    out = jt.triton_call(
        *call.args,
        kernel=getattr(triton_kernel, call.kernel),
        out_shape=list(call.out_shape),
        grid=(call.programs,),
        num_warps=1,
        num_stages=1,
        enable_fp_fusion=False,
        zeroed_outputs=call.zeroed,
        **call.params,
    )
    return tuple(out[: returned(call)])


def returned(call: KernelCall) -> int:
    """How many leading outputs of ``call`` are read back (the rest are scratch)."""
    return call.results or (6 if call.kernel == "trace_kernel" else 5)


def pack_nodes(options: KernelOptions, node_lower, node_upper, node_children, node_range) -> jax.Array:
    """The node rows the kernel of ``options`` reads (binary or 4-wide)."""
    if options.node_width == 4:
        return packed.pack_wide_nodes(node_lower, node_upper, node_children, node_range, options.leaf_size)
    return packed.pack_nodes(node_lower, node_upper, node_children)


def _kernel(*args, config: _Config) -> tuple[jax.Array, ...]:
    """Pack the scene (unless ``config.prepacked``) and the rays, launch the kernel, and drop the padding rays.

    Returns ``(distance, leaf, instances (n, levels), visited, tested, overflow)``, and with a hit list
    ``(hit distances (n, K), hit leaves (n, K), hits accepted (n,), hit chains (n, K, levels))`` after them.
    """
    (node_lower, node_upper, node_children, node_range, leaf_triangle, world_to_object, child_root, facing,
     instance_mask, node_keys_lower, node_keys_upper, leaf_keys, leaf_moving, instance_motion, leaf_analytic,
     curve_rows, origin, direction, t_min, t_max, enabled, mask, time, cursor_t, cursor_leaf,
     root) = args[: SCENE_ARGS + RAY_ARGS]  # fmt: skip
    n = origin.shape[0]
    lanes = config.options.rays_per_program
    size = max(lanes, -(-n // lanes) * lanes)
    if config.prepacked:
        nodes, triangles = args[SCENE_ARGS + RAY_ARGS :]
    else:
        if config.node_keys:
            nodes = packed.pack_node_keys(node_keys_lower, node_keys_upper, node_children)
        else:
            nodes = pack_nodes(config.options, node_lower, node_upper, node_children, node_range)
        if config.leaf_keys:
            triangles = packed.pack_triangle_keys(leaf_keys, leaf_moving)
        elif config.analytic and not config.analytic & 8:  # no triangles: the analytic rows are the leaf rows
            triangles = leaf_analytic
        else:
            triangles = packed.pack_triangles(leaf_triangle)
    if config.analytic and triangles is not leaf_analytic:  # analytic leaves take their rows (code in column 3)
        triangles = jnp.where(leaf_analytic[:, 3:4] != 0, leaf_analytic, triangles)
    instances = packed.pack_instances(world_to_object, child_root, facing, instance_mask)
    extended = config.levels > 0 or config.roots or config.motion or bool(config.analytic) or bool(config.curves)
    extended = extended or config.cursor
    motion = None
    if config.motion or config.curves or config.cursor:
        if config.leaf_keys:  # the scene's keyframe segment at each ray's time, as the portable path finds it
            position = spec_position(config.leaf_spec, config.leaf_keys, time)
        else:  # (also the placeholder rows before the curve rows)
            zero = jnp.zeros(time.shape, jnp.int32)
            position = KeyframePosition(zero, zero.astype(jnp.float32), jnp.ones(time.shape, bool))
        motion = (position.index, position.weight, position.visible, time)
    fused = (
        config.options.fused_rays
        and config.options.node_width == 2
        and not extended
        and all(a.dtype == jnp.float32 for a in (origin, direction, t_min, t_max))
    )
    if fused:
        rays = FusedRays(origin, direction, t_min, t_max, enabled, size)
    else:
        rays = packed.pack_rays(
            origin,
            direction,
            t_min,
            t_max,
            enabled,
            size,
            mask=mask if extended else None,
            root=root if extended else None,
            motion=motion,
            curve_frame=_curve_frames(origin, direction) if config.curves else None,
            cursor=(cursor_t, cursor_leaf) if config.cursor else None,
        )
    moving_instances = instance_motion if config.instance_keys else None
    curves = curve_rows if config.curves else None
    out = _launch(kernel_call(nodes, triangles, instances, rays, config, moving_instances, curves))
    distance, leaf, visited, tested, overflow = (a[:n] for a in out[:5])
    if config.levels and len(out) > 5:
        chain = out[5][: config.levels * size].reshape(config.levels, size)[:, :n].T
    else:
        chain = jnp.zeros((n, config.levels), jnp.int32)
    if not config.hit_list:
        return distance, leaf, chain, visited, tested, overflow
    k, levels = config.max_hits, config.levels
    hit_list = (out[6][: k * size].reshape(k, size)[:, :n].T, out[7][: k * size].reshape(k, size)[:, :n].T)
    chains = out[9][: k * levels * size].reshape(k, levels, size)[:, :, :n].transpose(2, 0, 1)
    return distance, leaf, chain, visited, tested, overflow, *hit_list, out[8][:n], chains


def _curve_frames(origin: jax.Array, direction: jax.Array) -> jax.Array:
    """``(N, 10)``: each ray's :func:`~jaxrt._src.primitives.curve.curve_ray` frame row by row and ``1 / |d|``,
    computed by the portable test's own function."""
    ray = jax.vmap(curve.curve_ray)(origin, direction)
    return jnp.concatenate([ray.frame.reshape(-1, 9), ray.inv_length[:, None]], axis=-1)


def _concatenate_scenes(scene: list[jax.Array], root: jax.Array) -> tuple[list[jax.Array], jax.Array, int, int]:
    """``B`` scenes (leading axis) as one: node, leaf and instance indices moved by each scene's offsets.

    Primitive leaves of scene ``b`` become ``b P + k``, its instances ``B P + b G + g`` (all primitive leaves
    first, as the kernel expects), its nodes ``b M + i``. Returns the flat scene arrays, the flat roots
    (``(B, n)`` to ``(B n,)``), ``P`` and ``G``.
    """
    (node_lower, node_upper, node_children, node_range, leaf_triangle, world_to_object, child_root, facing,
     instance_mask, *motion) = scene  # fmt: skip
    b, m = node_children.shape[:2]
    p, g = leaf_triangle.shape[1], child_root.shape[1]
    if b * max(m, 1) >= 2**31 or b * (p + g) >= 2**31:
        raise ValueError(f"traversal.gpu: {b} scenes of {m} nodes and {p + g} leaves exceed int32 indices")
    index = jnp.arange(b, dtype=jnp.int32)
    k = -1 - node_children
    shifted = jnp.where(k < p, k + index[:, None, None] * p, b * p + index[:, None, None] * g + (k - p))
    children = jnp.where(node_children >= 0, node_children + index[:, None, None] * m, -1 - shifted)
    flat = lambda a: a.reshape(-1, *a.shape[2:])  # noqa: E731
    arrays = [node_lower, node_upper, children, node_range, leaf_triangle, world_to_object]
    arrays += [child_root + index[:, None] * m, facing, instance_mask]
    arrays += motion  # keyframe, analytic and curve rows: node-, leaf- and instance-major, no indices to move
    return [flat(a) for a in arrays], flat(root + index[:, None] * m), p, g


def _batched_scenes(config: _Config, call_for, axis_size: int, in_batched, args):
    """One launch over ``axis_size`` (rays, scene) pairs (the batching rule's case of batched scenes)."""
    args = [a if b else jnp.broadcast_to(a, (axis_size, *a.shape)) for a, b in zip(args, in_batched, strict=True)]
    scene, rays = args[:SCENE_ARGS], args[SCENE_ARGS:]
    n = rays[0].shape[1]
    flat_scene, flat_root, p, g = _concatenate_scenes(scene, rays[-1])
    index = jnp.arange(axis_size, dtype=jnp.int32)[:, None]
    cursor_leaf = rays[CURSOR_LEAF]  # a leaf of its own scene: moved with the scene's leaves
    rays = [
        *rays[:CURSOR_LEAF],
        jnp.where(cursor_leaf >= 0, cursor_leaf + index * p, cursor_leaf),
        *rays[CURSOR_LEAF + 1 :],
    ]
    flat_rays = [a.reshape(axis_size * n, *a.shape[2:]) for a in rays[:-1]]
    _check_indices(flat_scene[2].shape[0], axis_size * g, config.levels)
    options = dataclasses.replace(config.options, node_width=2)
    batched = dataclasses.replace(config, primitive_leaves=axis_size * p, options=options, roots=True)
    distance, leaf, chain, visited, tested, overflow, *hit_list = call_for(batched)(*flat_scene, *flat_rays, flat_root)
    leaf = leaf.reshape(axis_size, n)
    leaf = jnp.where(leaf >= 0, leaf - index * p, leaf)
    chain = chain.reshape(axis_size, n, config.levels)
    chain = jnp.where(chain >= 0, chain - index[..., None] * g, chain)
    per_scene = lambda a: a.reshape(axis_size, n, *a.shape[1:])  # noqa: E731
    out = per_scene(distance), leaf, chain, per_scene(visited), per_scene(tested), per_scene(overflow)
    if hit_list:
        hit_distance, hit_leaf, total, chains = (per_scene(a) for a in hit_list)
        hit_leaf = jnp.where(hit_leaf >= 0, hit_leaf - index[..., None] * p, hit_leaf)
        chains = jnp.where(chains >= 0, chains - index[..., None, None] * g, chains)
        out += (hit_distance, hit_leaf, total, chains)
    return out


@functools.cache
def _traversal(config: _Config):
    """The kernel call for one static configuration, with its batching rule."""

    @jax.custom_batching.custom_vmap
    def call(*args):
        return _kernel(*args, config=config)

    @call.def_vmap
    def rule(axis_size, in_batched, *args):
        outputs = 10 if config.hit_list else 6
        plain = SCENE_ARGS + RAY_ARGS  # past them: the prepacked rows, if any
        if any(in_batched[:SCENE_ARGS]) or any(in_batched[plain:]):  # a batch of scenes: packed per call
            unpacked = dataclasses.replace(config, prepacked=False)
            out = _batched_scenes(unpacked, _traversal, axis_size, in_batched[:plain], args[:plain])
            return out, (True,) * outputs
        scene, ray_args, rows = args[:SCENE_ARGS], args[SCENE_ARGS:plain], args[plain:]
        rays = [
            a if b else jnp.broadcast_to(a, (axis_size, *a.shape))
            for a, b in zip(ray_args, in_batched[SCENE_ARGS:plain], strict=True)
        ]
        n = rays[0].shape[1]
        out = call(*scene, *(a.reshape(axis_size * n, *a.shape[2:]) for a in rays), *rows)
        return tuple(a.reshape(axis_size, n, *a.shape[1:]) for a in out), (True,) * outputs

    return call


class CurveLeaves(NamedTuple):
    """The curve leaves of a primitive structure as the kernel reads them (:func:`curve_leaves`)."""

    rows: jax.Array  # (P, 24) float32: packed.pack_curves of every primitive leaf
    # static: (pieces, iterations, approach_iterations, tolerance, any disk caps, any sphere caps, flat), flat 0 for
    # round segments only, 1 for flat ones only, 2 for both (chosen per segment by its flags)
    options: tuple


def curve_leaves(view: Any, config: dict) -> CurveLeaves | None:
    """The :class:`CurveLeaves` of a :class:`~jaxrt._src.scene_view.SceneView` with the static curve code choices
    ``config`` (:func:`jaxrt._src.leaves.curve_configuration`), or ``None`` without curves: round and flat
    (ray-facing ribbon) curves, each with the portable ``curve.intersect`` test."""
    if view.leaves.curve is None:
        return None
    types = config["curve_types"]
    options = config["options"]
    caps = config["end_caps"]
    static = (
        int(options.pieces),
        int(options.iterations),
        int(options.approach_iterations),
        float(options.tolerance),
        curve.CAP_DISK in caps,
        curve.CAP_SPHERE in caps,
        0 if curve.FLAT not in types else 2 if curve.ROUND in types else 1,
    )
    rows = packed.pack_curves(lax.stop_gradient(view.leaves.curve), view.leaves.curve_flags)
    return CurveLeaves(rows, static)


class LeafMotion(NamedTuple):
    """The triangle keyframes of a scene with primitive motion, as the kernel reads them."""

    spec: Any  # the MotionSpec (static)
    triangle: jax.Array  # (K, P, 3, 3) every primitive leaf's triangle at each keyframe
    moving: jax.Array  # (P,) bool: the leaf's geometry moves (it vanishes outside the range on a "vanish" border)


def leaf_motion(view: Any) -> LeafMotion | None:
    """The :class:`LeafMotion` of a :class:`~jaxrt._src.scene_view.SceneView` (``None`` without primitive
    motion): the keyframes the portable ``MotionLeaves`` blends, and its moving-leaf flags."""
    motion = view.leaves.motion
    if motion is None:
        return None
    table = view.slot_table(view.slots_where(lambda g: g.motion))
    moving = view.leaf_flag(table, jnp.arange(motion.triangle.shape[1]))
    return LeafMotion(motion.spec, lax.stop_gradient(motion.triangle), moving)


#: The shape code of a box leaf whose intersection function is user code (candidate waves): the kernel lists the
#: box at its entry distance and JAX calls the function.
CANDIDATE_BOX = 4


class AnalyticLeaves(NamedTuple):
    """The parameter rows of a scene's analytic leaves, as the kernel reads them (:func:`analytic_leaves`)."""

    rows: jax.Array  # (P, 12) float32: :func:`~jaxrt._src.traversal.packed.pack_analytic`, code 0 elsewhere
    shapes: int  # static: bit ``code - 1`` for each shape of the intersector's functions, bit 3 with triangles,
    # bit 4 with boxes of user functions (code CANDIDATE_BOX, listed as candidates in waves), bit ``code`` with the
    # leaves of a kind with an analytic row (its ``Kind.analytic.code``, >= 5: built-in spheres)


def analytic_leaves(
    functions: Any, view: Any, dtype: Any = jnp.float32, *, candidates: bool = False
) -> AnalyticLeaves | None:
    """The :class:`AnalyticLeaves` of a :class:`~jaxrt._src.scene_view.SceneView` whose bounding-box
    geometries use built-in functions (``functions``: the intersector's ``(geometry index, fn)`` pairs;
    ``None`` without box geometry), in ``dtype`` (float32 for this kernel; the CPU traversal takes the
    scene's dtype).

    Each box leaf's shape is the code of its geometry's function (keyed by the geometry's index within its
    structure, as the portable ``call_function``); its parameters are read as the function reads them: from
    the scene's primitive data, or, for a sphere in a scene without primitive data, from the leaf's box.

    With ``candidates`` (candidate waves, :mod:`jaxrt._src.traversal.waves`), the leaves of a user function
    take code 4: the kernel lists the box itself as a candidate (bit 4 of ``shapes``).

    Raises:
      ValueError: a function that is not built-in (without ``candidates``), or primitive data without the
        fields a function reads.
    """
    if not any(k.name in view.kinds for k in (BOUNDING_BOX, *analytic_rows.ROW_KINDS)):
        return None
    codes = np.zeros(len(view.geometry_info) + 1, np.int32)  # by geometry index; the last entry: padding
    shapes = 8 if TRIANGLE.name in view.kinds else 0
    for index, fn in functions or ():
        code = analytic.shape_code(fn)
        if not code and not candidates:
            raise ValueError(f"traversal.gpu: the intersection function of geometry {index} ({fn!r}) is not built-in")
        code = code or CANDIDATE_BOX
        if index < codes.shape[0] - 1:
            codes[index] = code
        shapes |= 1 << (code - 1) if code != CANDIDATE_BOX else 16
    leaves = view.leaves
    count = leaves.geometry.shape[0]
    is_box = view.leaf_flag(view.slot_table(view.slots_where(BOUNDING_BOX.holds)), jnp.arange(count))
    geometry = jnp.where(leaves.geometry < 0, codes.shape[0] - 1, leaves.geometry)
    code = jnp.where(is_box, jnp.asarray(codes)[geometry], 0)
    data = jax.tree_util.tree_map(lax.stop_gradient, leaves.primitive_data)

    def field(name: str, shape: tuple) -> jax.Array:
        if data is None or not isinstance(data, dict) or name not in data:
            raise ValueError(f"intersection function needs primitive_data[{name!r}] (per-primitive parameters)")
        value = data[name]
        if tuple(value.shape[1:]) != shape:
            raise ValueError(
                f"traversal.gpu: primitive_data[{name!r}] has rows of shape {tuple(value.shape[1:])}; the built-in "
                f"intersection functions read {shape}"
            )
        return value.astype(dtype)

    zero3, zero = jnp.zeros((count, 3), dtype), jnp.zeros((count,), dtype)
    first, second, radius = zero3, zero3, zero
    for shape in (1, 2, 3):
        if not shapes & (1 << (shape - 1)):
            continue
        if shape == 1 and data is None:  # the sphere inscribed in the box, as ``analytic.sphere`` takes it
            box = lax.stop_gradient(leaves.box).astype(dtype)
            p, q, r = 0.5 * (box[:, 0] + box[:, 1]), zero3, 0.5 * jnp.min(box[:, 1] - box[:, 0], axis=-1)
        elif shape == 1:
            p, q, r = field("center", (3,)), zero3, field("radius", ())
        elif shape == 2:
            p, q, r = field("center", (3,)), field("normal", (3,)), field("radius", ())
        else:
            p, q, r = field("p0", (3,)), field("p1", (3,)), field("radius", ())
        mine = code == shape
        first = jnp.where(mine[:, None], p, first)
        second = jnp.where(mine[:, None], q, second)
        radius = jnp.where(mine, r, radius)
    for kind in analytic_rows.ROW_KINDS:  # kinds tested by their formula (spheres): parameters from the leaf rows
        if kind.name not in view.kinds:
            continue
        mine = view.leaf_flag(view.slot_table(view.slots_where(kind.holds)), jnp.arange(count))
        rows = getattr(leaves, kind.leaf_arrays[0].name.removeprefix("leaf_"))
        p, q, r = kind.analytic.pack(lax.stop_gradient(rows).astype(dtype))
        code = jnp.where(mine, kind.analytic.code, code)
        first = jnp.where(mine[:, None], p, first)
        second = jnp.where(mine[:, None], q, second)
        radius = jnp.where(mine, r, radius)
        shapes |= 1 << analytic_rows.shape_bit(kind.analytic.code)
    return AnalyticLeaves(packed.pack_analytic(code, first, second, radius, dtype), shapes)


def _motion_arguments(scene: TraversalScene, layout: TraversalLayout, leaves: LeafMotion | None, config: _Config):
    """The kernel's keyframe arrays (node-, leaf- and instance-major; small placeholders where the scene has
    none) and the configuration with their keyframe counts."""
    dtype = jnp.float32
    node_lower = node_upper = jnp.zeros((1, 1, 2, 3), dtype)
    leaf_keys = jnp.zeros((1, 1, 3, 3), dtype)
    leaf_moving = jnp.zeros((1,), bool)
    instance_motion = jnp.zeros((1, 4), dtype)
    changes = {}
    if leaves is not None:
        leaf_keys = jnp.swapaxes(leaves.triangle, 0, 1)
        leaf_moving = leaves.moving
        changes.update(leaf_keys=int(leaves.triangle.shape[0]), leaf_spec=leaves.spec)
    if scene.node_motion is not None:
        lower, upper = scene.node_motion
        if leaves is None or layout.node_spec != leaves.spec or lower.shape[0] != leaves.triangle.shape[0]:
            raise ValueError(
                "traversal.gpu.trace_scene: node keyframes need the triangle keyframes of the same motion spec"
            )
        node_lower, node_upper = jnp.swapaxes(lower, 0, 1), jnp.swapaxes(upper, 0, 1)
        changes.update(node_keys=int(lower.shape[0]))
    motion = scene.instance_motion
    if motion is not None and motion.keys.shape[0]:
        instance_motion = packed.pack_instance_motion(
            motion.keys, motion.count, motion.start, motion.end, motion.vanish_start, motion.vanish_end, motion.moving
        )
        changes.update(instance_keys=int(motion.keys.shape[1]))
    return (node_lower, node_upper, leaf_keys, leaf_moving, instance_motion), dataclasses.replace(config, **changes)


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
    options: KernelOptions | None = None,
    time: jax.Array | None = None,
    leaf_motion: LeafMotion | None = None,
    max_hits: int | None = None,
    count_all: bool = False,
    analytic: AnalyticLeaves | None = None,
    curves: CurveLeaves | None = None,
    cursor: tuple[jax.Array, jax.Array] | None = None,
) -> TraversalResult:
    """Trace rays through a scene of any instance depth with the GPU kernel.

    Args:
      scene: the global node arrays (:func:`jaxrt._src.scene_view.traversal_scene`), float32.
      layout: its static layout (root, primitive leaves, levels, stack size).
      origin, direction: ``(N, 3)`` world-space rays; a disabled ray must still have a non-zero direction.
      t_min, t_max: ``(N,)`` accepted distance interval (world units at every level).
      enabled: ``(N,)`` bool; disabled rays miss and take no step.
      mask: ``(N,)`` uint32 ray masks; an instance is entered only where ``instance_mask & mask != 0``.
      any_hit: stop at the first accepted hit.
      cull: 0 culls nothing, +1 clockwise triangles, -1 counterclockwise ones; below instances the sense is
        multiplied by the chain's ``instance_facing``.
      options: code-generation choices (static); ``None`` takes :data:`DEFAULT_OPTIONS` at call time. Scenes
        with instances or keyframe motion are traced with the binary layout whatever ``node_width`` says.
      time: ``(N,)`` each ray's time; required where the layout has keyframe motion (``layout.motion``).
      leaf_motion: the triangle keyframes of a scene with primitive motion (:func:`leaf_motion`); the node
        keyframes (``scene.node_motion``) and instance keyframes (``scene.instance_motion``) come with the
        scene.
      max_hits: static ``K``: also keep the ``K`` nearest hits of each ray in ``hits`` (a
        :class:`~jaxrt._src.traversal.step.HitList`, as the portable traversal's ``max_hits``, with each hit's
        instance chain below instances; not with ``any_hit``). ``0`` with ``count_all``.
      count_all: static; count every accepted hit in ``hits.total`` (no culling), at any instance depth.
      analytic: the parameter rows of the scene's analytic leaves (:func:`analytic_leaves`): bounding-box
        leaves tested as the built-in intersection functions test them (not with keyframe motion).
      curves: the round curve leaves of a primitive structure (:func:`curve_leaves`): leaves whose row is a
        curve take the portable ``curve.intersect`` test (in the kernel) instead of the triangle test.
      cursor: ``((N,) distances, (N,) leaves)``: one wave of candidates (:mod:`jaxrt._src.traversal.waves`;
        with ``max_hits``, a primitive structure): the hit list keeps the ``K`` first hits past each ray's
        cursor in ``(distance, leaf)`` order (ties by leaf, not by arrival), and the box leaves of user
        functions (code 4 in ``analytic``) are listed at their entry distance.

    Returns:
      The portable traversal's :class:`~jaxrt._src.traversal.scene.TraversalResult`: the leaf (-1 on a miss),
      its distance (the initial bound on a miss), the instance chain ``(N, levels)`` (global ids, outermost
      first, -1 past it), nodes visited, primitives tested, and the stack overflow flag (never set: the stack
      has the layout's bound). With ``max_hits`` or ``count_all``, ``hits`` as in the portable traversal
      (then ``leaf`` is the first hit and ``distance`` the culling bound).
    """
    options = options or DEFAULT_OPTIONS
    levels = int(layout.levels)
    k = int(max_hits or 0)
    hit_list = max_hits is not None or count_all
    if hit_list and (any_hit or (count_all and k) or (not count_all and k < 1)):
        raise ValueError(
            "traversal.gpu.trace_scene: hit lists need max_hits >= 1 (0 with count_all) and no any_hit "
            f"(got max_hits={max_hits}, count_all={count_all}, any_hit={any_hit})"
        )
    if hit_list or analytic is not None or curves is not None:  # the 4-wide layout: no hit lists, triangles only
        options = dataclasses.replace(options, node_width=2)
    if layout.motion and time is None:
        raise ValueError("traversal.gpu.trace_scene: the scene has keyframe motion; pass each ray's time")
    if layout.motion and analytic is not None:
        raise ValueError("traversal.gpu.trace_scene: analytic leaves are not covered with keyframe motion")
    moving = layout.motion and (
        scene.node_motion is not None or scene.instance_motion is not None or leaf_motion is not None
    )
    if options.node_width == 4 and (levels or scene.node_range is None or layout.root != 0 or moving):
        options = dataclasses.replace(options, node_width=2)
    node_range = scene.node_range if options.node_width == 4 else jnp.zeros((1, 2), jnp.int32)
    _check_indices(scene.node_children.shape[0], scene.instance_child_root.shape[0], levels)
    if curves is not None and (levels or moving):
        raise ValueError("traversal.gpu.trace_scene: curves are covered in static primitive structures only")
    if cursor is not None and (k < 1 or count_all or levels or layout.root != 0 or moving):
        raise ValueError("traversal.gpu.trace_scene: a cursor needs max_hits >= 1 in a static primitive structure")
    rows = getattr(scene, "kernel_layout", None)
    prepacked = rows is not None and options.node_width == 2 and levels == 0 and layout.root == 0 and not moving
    config = _Config(
        any_hit=bool(any_hit),
        cull=int(cull),
        stack=int(layout.stack_size),
        levels=levels,
        primitive_leaves=int(layout.primitive_leaves),
        options=options,
        roots=levels > 0 or layout.root != 0,
        prepacked=prepacked,
        max_hits=k,
        count=bool(count_all),
        analytic=0 if analytic is None else int(analytic.shapes),
        curves=curves.options if curves is not None else (),
        cursor=cursor is not None,
    )
    detached = lax.stop_gradient
    motion_args, config = _motion_arguments(scene, layout, leaf_motion, config)
    if time is None:
        time = jnp.zeros(origin.shape[:1], jnp.float32)
    args = (
        detached(scene.node_lower),
        detached(scene.node_upper),
        scene.node_children,
        node_range,
        detached(scene.leaf_triangle),
        detached(scene.instance_world_to_object),
        scene.instance_child_root,
        scene.instance_facing,
        scene.instance_mask,
        *(detached(a) for a in motion_args),
        jnp.zeros((1, packed.TRIANGLE_WIDTH), jnp.float32) if analytic is None else detached(analytic.rows),
        detached(curves.rows) if curves is not None else jnp.zeros((1, packed.CURVE_WIDTH), jnp.float32),
        *(detached(a) for a in (origin, direction, t_min, t_max)),
        enabled,
        mask.astype(jnp.uint32),
        detached(time).astype(jnp.float32),
        *(_no_cursor(origin.shape[0]) if cursor is None else (detached(cursor[0]), cursor[1].astype(jnp.int32))),
        jnp.full(origin.shape[:1], layout.root, jnp.int32),
        *((detached(rows.nodes), detached(rows.triangles)) if prepacked else ()),
    )
    distance, leaf, instances, visited, tested, overflow, *found = _traversal(config)(*args)
    hits = None
    if hit_list:
        distances, leaves, total, chains = found
        hits = HitList(distances, leaves, total, chains if levels else None)
    return TraversalResult(distance, leaf, instances, visited, tested, overflow.astype(bool), hits)


def _no_cursor(n: int) -> tuple[jax.Array, jax.Array]:
    """The cursor arguments of a call without one (every candidate is past it; not read by the kernel)."""
    return jnp.full((n,), -jnp.inf, jnp.float32), jnp.full((n,), -1, jnp.int32)
