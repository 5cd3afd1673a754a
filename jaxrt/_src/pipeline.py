"""The intersection pipeline: rays -> scene view -> traversal (GPU kernel, CPU traversal or portable) ->
result fields.

One path for every structure: a primitive structure is a scene with zero instance levels. Where
:func:`kernel_declines` finds nothing the compiled traversals lack, the traversal is the GPU kernel
(:mod:`jaxrt._src.traversal.gpu`) when the default backend is a GPU, or the Numba-compiled CPU traversal
(:mod:`jaxrt._src.traversal.cpu`) when it is the CPU; else the portable stack traversal
(:mod:`jaxrt._src.traversal.drivers`) with the leaf tests of :mod:`jaxrt._src.leaves`. All return the same
:class:`~jaxrt._src.traversal.scene.TraversalResult`.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
from jax import lax

from jaxrt._src import fields as result_fields
from jaxrt._src import filter_states
from jaxrt._src import leaves as leaf_tests
from jaxrt._src.kinds import registry
from jaxrt._src.kinds.registry import BOUNDING_BOX, CURVE, TRIANGLE
from jaxrt._src.numerics import full_precision
from jaxrt._src.ray import Ray
from jaxrt._src.result import IntersectionResult
from jaxrt._src.scene_view import SceneView, scene_view
from jaxrt._src.traversal import cpu, drivers, gpu, waves
from jaxrt._src.traversal.scene import TraversalRays, TraversalResult

__all__ = [
    "CPU_CHUNK",
    "GPU_CHUNK",
    "GPU_REFILL_LANES",
    "cpu_kernel_arguments",
    "gpu_trace",
    "INTERSECT_CHUNK",
    "REFILL_LANES",
    "sanitized_rays",
    "enabled_rays",
    "intersect",
    "kernel_declines",
    "power_of_two_bucket",
    "resolve_backend",
    "trace",
]

#: Rays per traversal batch. Batches run one after another; on the CPU a batch that stays in cache is faster.
CPU_CHUNK = 1 << 16
GPU_CHUNK = 1 << 22
#: Rays in flight in the refill driver (chosen by measurement on a 2-core CPU: 512, 2048, 8192 lanes).
REFILL_LANES = 2048
#: On a GPU a step over few lanes is all launch overhead: keep many rays in flight.
GPU_REFILL_LANES = 1 << 18
#: Rays per compiled intersection call. Larger batches are traced in sequential chunks of this many rays
#: (``lax.map``), so that the temporaries of packing, traversal and result assembly stay per chunk (by a count
#: of the arrays, at most about 200 bytes per ray: 3.4 GB at 2**24); the rays, one padded copy of them and the
#: result are per batch. Measured on an H200: 100M rays in one call peaked at 14.3 GB (docs/performance.md).
INTERSECT_CHUNK = 1 << 24


def power_of_two_bucket(n: int) -> int:
    """The smallest power of two ``>= max(n, 1)``: sizes in one bucket share compiled code."""
    return 1 << max(0, (max(n, 1) - 1).bit_length())


def enabled_rays(rays: Ray) -> jax.Array:
    """Rays that can hit: finite, non-zero direction, ``min_distance <= max_distance``, mask not 0."""
    finite = jnp.all(jnp.isfinite(rays.origin), axis=-1) & jnp.all(jnp.isfinite(rays.direction), axis=-1)
    nonzero = jnp.any(rays.direction != 0, axis=-1)
    interval = (rays.min_distance <= rays.max_distance) & ~jnp.isnan(rays.min_distance) & ~jnp.isnan(rays.max_distance)
    return finite & nonzero & interval & (rays.mask != 0)


def sanitized_rays(rays: Ray) -> TraversalRays:
    """The :class:`~jaxrt._src.traversal.scene.TraversalRays` of a flat ray batch: disabled rays replaced by a
    harmless one (origin 0, direction +z, interval [0, 0])."""
    on = enabled_rays(rays)
    unit_z = jnp.array([0.0, 0.0, 1.0], rays.direction.dtype)
    return TraversalRays(
        origin=jnp.where(on[..., None], rays.origin, 0.0),
        direction=jnp.where(on[..., None], rays.direction, unit_z),
        t_min=jnp.where(on, rays.min_distance, 0.0),
        t_max=jnp.where(on, rays.max_distance, 0.0),
        enabled=on,
        mask=rays.mask,
        time=jnp.where(on, rays.time, 0.0),  # read only by scenes with keyframe motion
    )


def kernel_declines(
    intersector: Any, geometry_info: tuple, backend: str = "gpu", motion: bool = False, levels: int = 0
) -> str | None:
    """Why the compiled traversal of ``backend`` (``"gpu"``: the GPU kernel, ``"cpu"``: the CPU traversal)
    does not cover a scene of these geometries with this intersector (``None``: it does); ``motion`` says
    that the scene has keyframe motion (primitive motion is also read from the geometries), ``levels`` how
    many instance levels it has.

    Derived from the kind registry (:func:`jaxrt._src.kinds.registry.declines`): each kind's coverage on the
    backend, and its decisions that need JAX (user intersection functions and filters, which the GPU kernel
    hands over in candidate waves, :mod:`jaxrt._src.traversal.waves`). With
    :func:`jaxrt._src.traversal.gpu.unavailable_reason` and :func:`jaxrt._src.traversal.cpu.unavailable_reason`
    (the machine) it decides which traversal runs.
    """
    return registry.declines(intersector, geometry_info, backend, motion, levels)


def resolve_backend(intersector: Any) -> str:
    """``"portable"``, ``"gpu"`` or ``"cpu"``: which traversal runs for this intersector on the default JAX
    backend (a forced ``"gpu"`` or ``"cpu"`` that cannot run raises ``ValueError``)."""
    if intersector.backend == "portable":
        return "portable"

    if intersector.backend == "cpu":
        reason = cpu.unavailable_reason(intersector)
        if reason is not None:
            raise ValueError(f"Intersector: backend='cpu' cannot run: {reason}")
        return "cpu"
    reason = gpu.unavailable_reason(intersector)
    if reason is None:
        return "gpu"
    if intersector.backend == "gpu":
        raise ValueError(f"Intersector: backend='gpu' cannot run: {reason}")
    return "cpu" if cpu.unavailable_reason(intersector) is None else "portable"


def _chunked(fn, args, chunk: int):
    """``fn`` over the rays in sequential chunks of ``chunk`` (the ray count is a power of two)."""
    n = args[0].shape[0]
    if n <= chunk:
        return fn(*args)
    split = [a.reshape(n // chunk, chunk, *a.shape[1:]) for a in args]
    out = lax.map(lambda xs: fn(*xs), split)
    return jax.tree_util.tree_map(lambda a: a.reshape(n, *a.shape[2:]), out)


def _trace_portable(intersector: Any, view: SceneView, rays: TraversalRays) -> TraversalResult:
    """The portable stack traversal over chunks of rays, with the refill driver."""
    detached = lax.stop_gradient
    scene = jax.tree_util.tree_map(detached, view.traversal)
    tester = leaf_tests.leaf_tester(intersector, view)
    on_gpu = jax.default_backend() == "gpu"
    chunk, lanes = (GPU_CHUNK, GPU_REFILL_LANES) if on_gpu else (CPU_CHUNK, REFILL_LANES)
    fn = functools.partial(
        drivers.traverse_refill,
        scene,
        view.layout,
        tester,
        any_hit=intersector.accept_any_intersection,
        max_hits=0 if intersector.counts_all else intersector.max_hits,
        count_all=intersector.counts_all,
        lanes=lanes,
        split=jax.default_backend() == "cpu",
    )
    args = tuple(detached(a) for a in (rays.origin, rays.direction, rays.t_min, rays.t_max)) + (
        rays.enabled,
        rays.mask,
    )
    if view.layout.motion:  # keyframe motion: the traversal reads each ray's time
        args += (detached(rays.time),)
    return _chunked(fn, args, chunk)


def wave_lister(intersector: Any, view: SceneView, rays: TraversalRays) -> Any:
    """The GPU kernel's wave for :mod:`jaxrt._src.traversal.waves`: ``(K, t_max, enabled, cursor_t,
    cursor_leaf) -> TraversalResult`` listing each ray's ``K`` first candidates past its cursor."""
    detached = lax.stop_gradient
    scene = jax.tree_util.tree_map(detached, view.traversal)
    analytic = None
    if BOUNDING_BOX.name in view.kinds:
        analytic = gpu.analytic_leaves(intersector.intersection_functions, view, jnp.float32, candidates=True)
    origin, direction, t_min = (detached(a) for a in (rays.origin, rays.direction, rays.t_min))

    def list_candidates(k, t_max, enabled, cursor_t, cursor_leaf):
        return gpu.trace_scene(
            scene,
            view.layout,
            origin,
            direction,
            t_min,
            t_max,
            enabled,
            rays.mask,
            any_hit=False,
            cull=intersector.cull,
            max_hits=k,
            analytic=analytic,
            cursor=(cursor_t, cursor_leaf),
        )

    return list_candidates


def _trace_waves(intersector: Any, view: SceneView, rays: TraversalRays) -> TraversalResult:
    """The GPU kernel in candidate waves (:mod:`jaxrt._src.traversal.waves`): user functions and filters."""
    lister = wave_lister(intersector, view, rays)
    tester = leaf_tests.leaf_tester(intersector, view)
    return waves.trace_waves(
        intersector, tester, rays, lister, candidates=waves.CANDIDATES, later=waves.LATER_CANDIDATES
    )


def _curve_leaves(intersector: Any, view: SceneView, backend: str) -> Any:
    """The curve leaves as the compiled traversal of ``backend`` reads them (rows and static options)."""
    leaves = gpu.curve_leaves(view, leaf_tests.curve_configuration(intersector, view))
    if backend == "cpu":
        return cpu.CurveLeaves(view.leaves.curve, view.leaves.curve_flags, leaves.options)
    return leaves


def trace(intersector: Any, view: SceneView, rays: TraversalRays, host: Any = None) -> TraversalResult:
    """Run the traversal the intersector and scene call for (a compiled one where it covers them). ``host``:
    the addresses the CPU traversal may read the scene from (:func:`jaxrt._src.traversal.cpu.host_scene`)."""
    backend = resolve_backend(intersector)
    covered = backend != "portable" and (
        kernel_declines(intersector, view.geometry_info, backend, view.layout.motion, view.layout.levels) is None
    )
    if backend == "cpu":  # the CPU loop is compiled per float type: geometry and rays must share one
        covered = covered and view.traversal.node_lower.dtype == rays.origin.dtype
    if backend != "portable" and covered:
        detached = lax.stop_gradient
        moving = {}  # keyframe motion (GPU kernel only): each ray's time and the triangle keyframes
        if view.layout.motion:
            moving = dict(time=detached(rays.time), leaf_motion=gpu.leaf_motion(view))
        if CURVE.name in view.kinds:  # curves: their rows and the static test options
            moving.update(curves=_curve_leaves(intersector, view, backend))
        if intersector.max_hits is not None or intersector.counts_all:
            moving.update(max_hits=0 if intersector.counts_all else intersector.max_hits)
            moving.update(count_all=intersector.counts_all)
        scene = jax.tree_util.tree_map(detached, view.traversal)
        if backend == "gpu":
            # A filter that reads only the primitive is decided once per primitive: accepted ones are traced as
            # opaque, rejected ones not at all (filter_states); other user code per candidate in waves.
            rejected = filter_states.rejected_leaves(intersector, view)
            if waves.needs_waves(intersector, view, filter_decided=rejected is not None):
                return _trace_waves(intersector, view, rays)
            if rejected is not None:
                no_triangle = jnp.zeros((), scene.leaf_triangle.dtype)
                triangles = jnp.where(rejected[:, None, None], no_triangle, scene.leaf_triangle)
                scene = scene._replace(leaf_triangle=triangles, kernel_layout=None)
        # the analytic rows (built-in functions, spheres): None where the scene's kinds need none
        dtype = view.traversal.node_lower.dtype if backend == "cpu" else jnp.float32
        moving.update(analytic=gpu.analytic_leaves(intersector.intersection_functions, view, dtype))
        return (cpu if backend == "cpu" else gpu).trace_scene(
            scene,
            view.layout,
            *(detached(a) for a in (rays.origin, rays.direction, rays.t_min, rays.t_max)),
            rays.enabled,
            rays.mask,
            any_hit=intersector.accept_any_intersection,
            cull=intersector.cull,
            **moving,
            **({"host": host} if backend == "cpu" else {}),
        )
    return _trace_portable(intersector, view, rays)


@functools.partial(jax.jit, static_argnums=0)
@full_precision
def _intersect_jit(intersector: Any, rays: Ray, structure: Any, host: Any = None) -> IntersectionResult:
    """The result for a flat, padded ray batch ``(n,)`` (inside ``jit``)."""
    view = scene_view(structure)
    ray = sanitized_rays(rays)
    found = trace(intersector, view, ray, host)
    if intersector.counts_all:
        return IntersectionResult({"hit_count": found.hits.total})
    geometry = (ray.origin, ray.direction, ray.t_min, ray.t_max)
    moving = view.layout.motion
    if intersector.max_hits is None:
        fields = result_fields.hit_fields(
            intersector,
            view,
            *geometry,
            found.leaf,
            found.distance,
            found.instances,
            time=ray.time if moving else None,
            curve=found.curve,
        )
    else:  # the same fields for each of the K hits, on an axis after the ray axis
        k = intersector.max_hits
        hits = found.hits
        chains = hits.instances if hits.instances is not None else jnp.zeros((*hits.leaf.shape, 0), jnp.int32)
        flat = result_fields.hit_fields(
            intersector,
            view,
            *(jnp.repeat(a, k, axis=0) for a in geometry),
            hits.leaf.reshape(-1),
            hits.distance.reshape(-1),
            chains.reshape(hits.leaf.size, chains.shape[-1]),
            time=jnp.repeat(ray.time, k, axis=0) if moving else None,
        )
        fields = jax.tree_util.tree_map(lambda a: a.reshape(-1, k, *a.shape[1:]), flat)
        fields["hit_count"] = jnp.minimum(hits.total, k)
        fields["hit_overflow"] = hits.total > k
    if intersector.has("primitive_motion") or intersector.has("instance_motion"):
        hit = fields["type"] != 0
        fields["time"] = jnp.where(hit, rays.time[:, None] if hit.ndim > 1 else rays.time, 0.0)
    if intersector.has("stats"):
        fields["nodes_visited"] = found.nodes_visited
        fields["primitives_tested"] = found.primitives_tested
        fields["stack_overflow"] = found.stack_overflow
    return IntersectionResult(fields)


@functools.partial(jax.jit, static_argnums=(0, 3))
def _intersect_chunks(intersector: Any, rays: Ray, structure: Any, chunk: int, host: Any = None) -> IntersectionResult:
    """``_intersect_jit`` over sequential chunks of ``chunk`` rays (the ray count is a multiple of it)."""
    split = jax.tree_util.tree_map(lambda a: a.reshape(-1, chunk, *a.shape[1:]), rays)
    out = lax.map(lambda r: _intersect_jit(intersector, r, structure, host), split)
    return jax.tree_util.tree_map(lambda a: a.reshape(-1, *a.shape[2:]), out)


def intersect(intersector: Any, rays: Ray, structure: Any) -> IntersectionResult:
    """Rays of any batch shape, padded to a power-of-two bucket (or chunks of :data:`INTERSECT_CHUNK`)."""
    shape = rays.shape
    flat = rays if len(shape) == 1 else rays.reshape(-1)  # a flat batch as it is (no eager reshape per field)
    n = flat.origin.shape[0]
    chunk = INTERSECT_CHUNK
    padded = power_of_two_bucket(n) if n <= chunk else -(-n // chunk) * chunk
    if padded != n:
        flat = jax.tree_util.tree_map(
            lambda a: jnp.concatenate([a, jnp.zeros((padded - n, *a.shape[1:]), a.dtype)]), flat
        )
    host = None
    if resolve_backend(intersector) == "cpu":  # the CPU traversal reads a concrete scene in place
        host = cpu.host_scene(structure, flat, with_rays=padded <= chunk)
    if padded <= chunk:
        result = _intersect_jit(intersector, flat, structure, host)
    else:
        result = _intersect_chunks(intersector, flat, structure, chunk, host)
    if padded == n and shape == (n,):  # nothing to cut or reshape (no extra dispatch per field)
        return result
    return jax.tree_util.tree_map(lambda a: a[:n].reshape(*shape, *a.shape[1:]), result)


def gpu_trace(
    structure: Any,
    origin: jax.Array,
    direction: jax.Array,
    t_min: jax.Array,
    t_max: jax.Array,
    enabled: jax.Array,
    *,
    any_hit: bool,
    cull: int,
    options: Any = None,
) -> TraversalResult:
    """:func:`jaxrt._src.traversal.gpu.trace_scene` for a :class:`~jaxrt.PrimitiveAccelerationStructure`
    (float32, triangles only), every ray mask all ones: the kernel with the packing of the scene's rows and of
    the rays (for benchmarks; ``options``: a :class:`~jaxrt._src.traversal.gpu.KernelOptions`)."""
    kinds = sorted(k.name for k in registry.present(structure.geometry_info) if k is not TRIANGLE)
    if kinds:
        raise NotImplementedError(f"pipeline.gpu_trace: geometry kinds {kinds} are not covered by the GPU kernel")
    view = scene_view(structure)
    mask = jnp.full(origin.shape[:1], 0xFFFFFFFF, jnp.uint32)
    return gpu.trace_scene(
        view.traversal,
        view.layout,
        origin,
        direction,
        t_min,
        t_max,
        enabled,
        mask,
        any_hit=any_hit,
        cull=cull,
        options=options,
    )


def cpu_kernel_arguments(structure: Any, rays: Ray, intersector: Any) -> tuple[tuple[int, ...], list]:
    """``(params, arrays)`` for calling the compiled CPU traversal directly on host arrays (outside ``jit``), as
    the intersector's callback would for ``rays`` (a :class:`jaxrt.Ray` of shape ``(N,)``): for benchmarks."""
    view = scene_view(structure)
    ray = sanitized_rays(rays)
    dtype = view.traversal.node_lower.dtype
    analytic = gpu.analytic_leaves(intersector.intersection_functions, view, dtype)
    return cpu.kernel_arguments(
        view.traversal,
        view.layout,
        ray,
        any_hit=intersector.accept_any_intersection,
        cull=intersector.cull,
        max_hits=0 if intersector.counts_all else intersector.max_hits,
        count_all=intersector.counts_all,
        analytic=analytic,
        leaf_motion=gpu.leaf_motion(view),
        curves=_curve_leaves(intersector, view, "cpu") if CURVE.name in view.kinds else None,
    )
