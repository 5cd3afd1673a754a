"""Closest-point queries: the nearest primitive of a structure to each of a batch of points.

A depth-first walk of the structure's BVH per point, run by
:func:`~jaxrt._src.point_traversal.walk_points` (a window of vmapped lanes refilled as points end). A step pops
a node and measures the point's distance to both child boxes (stored in the parent); child leaves are tested
exactly (:mod:`jaxrt._src.primitives.point_triangle`), child nodes nearer than the best distance so far are
pushed farther first, so the nearer is visited next, and an entry popped after the best distance has shrunk
below its box distance is dropped. The traversal picks the primitive under ``stop_gradient``; its closest
point is then computed again differentiably, so distances and points differentiate with respect to the
points and the vertices (holding the chosen primitive fixed), as hits do in the intersector.

This is the portable walk (``backend="portable"``); the compiled walks of
:mod:`jaxrt._src.traversal.points` (Numba on the CPU, Triton on the GPU) make the same decisions and run by
default where they cover the structure. Every walk only picks the leaf: :func:`_fields_flat` computes the result.

Supported: primitive structures of the kinds with a closest-point formula (``Kind.closest_point``): triangles,
bounding boxes (a box's distance is that of the solid box: 0 inside) and spheres (the surface). Instance
structures and curve geometry raise ``NotImplementedError``.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxrt._src.instances import InstanceAccelerationStructure
from jaxrt._src.kinds import registry
from jaxrt._src.kinds.registry import BOUNDING_BOX
from jaxrt._src.point_traversal import in_morton_order, lanes_for_backend, walk_points
from jaxrt._src.primitives import point_triangle as geo
from jaxrt._src.structures import PrimitiveAccelerationStructure
from jaxrt._src.traversal import points as points_backend

__all__ = ["ClosestPointResult", "closest_point", "check_not_empty", "check_points", "check_structure", "run_flat"]

#: Stack entries a step may drop before it visits one.
_POPS = 4
#: Points traversed together by one vmapped loop.
LANES = 512


class ClosestPointResult(NamedTuple):
    """The nearest primitive to each point (every field has the batch shape of the points).

    Points with no primitive within ``max_distance`` are misses: ``primitive_id`` and ``geometry_id`` -1,
    ``distance`` ``inf``, ``point`` ``inf`` and barycentrics 0 (no NaN).
    """

    distance: jax.Array
    """Euclidean distance to the nearest primitive (0 inside a box primitive)."""
    point: jax.Array
    """``(..., 3)`` the closest point on that primitive."""
    primitive_id: jax.Array
    """Index of the primitive within its geometry; -1 on a miss."""
    geometry_id: jax.Array
    """Index of the geometry in the structure; -1 on a miss."""
    triangle_barycentric_coord: jax.Array
    """``(..., 2)`` ``(u, v)`` with ``point = (1 - u - v) v0 + u v1 + v v2``; 0 for boxes and misses."""


def check_structure(structure, name: str) -> PrimitiveAccelerationStructure:
    """``structure`` if a point query supports it, else a clear error naming ``name``."""
    if isinstance(structure, InstanceAccelerationStructure):
        raise NotImplementedError(
            f"{name}: instance structures are not supported yet; query the primitive structures directly"
        )
    if not isinstance(structure, PrimitiveAccelerationStructure):
        raise TypeError(f"{name}: structure must be a PrimitiveAccelerationStructure, got {type(structure).__name__}")
    for kind in registry.present(structure.geometry_info):
        if kind.closest_point is None:
            supported = ", ".join(k.name for k in registry.KINDS if k.closest_point is not None)
            raise NotImplementedError(f"{name}: {kind.name} geometry is not supported; supported kinds: {supported}")
    return structure


def check_not_empty(structure: PrimitiveAccelerationStructure, name: str) -> None:
    """``ValueError`` naming ``name`` where a concrete structure holds no primitive a point query can find (every
    triangle without area: the builder leaves such triangles out of the tree). Nothing is checked under a trace."""
    lower, upper = structure.node_lower, structure.node_upper
    if isinstance(lower, jax.core.Tracer) or isinstance(upper, jax.core.Tracer):
        return
    if lower.ndim != 3:  # a batch of structures: checked per query inside the walk (every point a miss)
        return
    with jax.ensure_compile_time_eval():  # the root's boxes only, also where the query is being traced
        empty = not bool(jnp.any(lower[0] <= upper[0]))
    if empty:
        raise ValueError(
            f"{name}: the structure is empty: none of its {structure.capacity} leaves holds a primitive with a "
            "non-empty box (triangles of zero area are left out of the tree), so no point has a nearest primitive"
        )


def check_points(points, name: str, dtype) -> jax.Array:
    """``points`` as an array ``(..., 3)`` of ``dtype``; ``ValueError``/``TypeError`` for bad input (the
    finiteness check only where the values are concrete, outside ``jit``)."""
    if isinstance(points, jax.core.Tracer):
        array = points
    else:
        array = jnp.asarray(points)
    if not (jnp.issubdtype(array.dtype, jnp.floating) or jnp.issubdtype(array.dtype, jnp.integer)):
        raise TypeError(f"{name}: points must be real numbers, got dtype {array.dtype}")
    if array.ndim < 1 or array.shape[-1] != 3:
        raise ValueError(f"{name}: points must have shape (..., 3), got {tuple(array.shape)}")
    if not isinstance(array, jax.core.Tracer):
        bad = ~np.isfinite(np.asarray(array, np.float64))
        if bad.any():
            index = tuple(int(i) for i in np.argwhere(bad.any(axis=-1))[0]) if array.ndim > 1 else ()
            raise ValueError(f"{name}: points must be finite; points{list(index)} = {np.asarray(array)[index]}")
    return array.astype(dtype)


class _State(NamedTuple):
    stack: jax.Array  # (S,) node indices
    bound: jax.Array  # (S,) squared box distance of each stacked node when pushed
    size: jax.Array
    best: jax.Array  # squared distance of the best primitive so far (starts at max_distance^2)
    leaf: jax.Array  # its leaf, -1 while none


def _leaf_distance(structure: PrimitiveAccelerationStructure, tables, p: jax.Array, leaf: jax.Array):
    """Squared distance from ``p`` to leaf ``leaf``'s primitive (a triangle, or a kind of ``tables``)."""
    tri = structure.leaf_triangle[leaf]
    u, v = geo.closest_on_triangle(p, tri)
    q = _other_kinds(structure, tables, p, leaf, geo.triangle_point(tri, u, v))
    d = p - q
    return jnp.sum(d * d)


def _kind_tables(structure: PrimitiveAccelerationStructure) -> tuple:
    """``(kind, table)`` for each kind present other than triangles: the kind's closest-point formula and a
    bool table over geometry indices (a last row for padding)."""
    tables = []
    for kind in registry.present(structure.geometry_info):
        if kind is not registry.TRIANGLE:
            table = np.array([kind.holds(g) for g in structure.geometry_info] + [False])
            tables.append((kind, jnp.asarray(table)))
    return tuple(tables)


def _other_kinds(structure: PrimitiveAccelerationStructure, tables, p: jax.Array, leaf: jax.Array, q: jax.Array):
    """``q`` where leaf ``leaf`` (any batch shape) is a triangle, else its kind's closest point to ``p``, from
    the kind's first leaf array (:attr:`~jaxrt._src.kinds.kind.Kind.closest_point`)."""
    geometry = structure.leaf_geometry[leaf]
    for kind, table in tables:
        row = getattr(structure, kind.leaf_arrays[0].name)[leaf]
        mine = table[jnp.where(geometry < 0, -1, geometry)]
        q = jnp.where(mine[..., None], kind.closest_point(p, row), q)
    return q


def _search(structure: PrimitiveAccelerationStructure, tables, limit2: jax.Array):
    """``start``, ``step`` and ``done`` of the nearest-leaf walk for :func:`~jaxrt._src.point_traversal.walk_points`."""
    stack_size = structure.max_depth + 1
    children = structure.node_children

    def start(p: jax.Array) -> _State:
        return _State(
            stack=jnp.zeros((stack_size,), jnp.int32),
            bound=jnp.full((stack_size,), -jnp.inf, limit2.dtype),
            size=jnp.int32(1),
            best=limit2,
            leaf=jnp.int32(-1),
        )

    def step(p: jax.Array, s: _State) -> _State:
        # Entries whose box is farther than the best found since they were pushed are dropped: the topmost
        # live one of the top few is visited (no visit when none of them is live).
        depth = s.size - 1 - jnp.arange(_POPS, dtype=jnp.int32)
        alive = (depth >= 0) & (s.bound[jnp.maximum(depth, 0)] <= s.best)
        live = jnp.any(alive)
        top = jnp.where(live, depth[jnp.argmax(alive)], jnp.maximum(s.size - _POPS, 0))
        node = s.stack[top]
        size = top
        d_box = geo.squared_box_distance(p, structure.node_lower[node], structure.node_upper[node])  # (2,)
        # Empty boxes (padding, zero-area triangles) fail every comparison, even with an infinite best.
        d_box = jnp.where(d_box < jnp.inf, d_box, jnp.nan)
        kids = children[node]
        is_leaf = kids < 0
        best, leaf = s.best, s.leaf
        for j in range(2):
            k = -1 - kids[j]
            take = live & is_leaf[j] & (d_box[j] <= best)
            d = _leaf_distance(structure, tables, p, jnp.where(take, k, 0))
            better = take & ((d < best) | ((leaf < 0) & (d <= best)))
            best = jnp.where(better, d, best)
            leaf = jnp.where(better, k, leaf)
        near = jnp.where(d_box[1] < d_box[0], 1, 0)
        stack, bound = s.stack, s.bound
        for j in (1 - near, near):  # farther first: the nearer is popped next
            push = live & ~is_leaf[j] & (d_box[j] <= best)
            slot = jnp.where(push, size, stack_size)
            stack = stack.at[slot].set(kids[j], mode="drop")
            bound = bound.at[slot].set(d_box[j], mode="drop")
            size = size + push
        return _State(stack, bound, size, best, leaf)

    return start, step, lambda s: s.size == 0


def _box_table(structure: PrimitiveAccelerationStructure):
    if structure.leaf_box is None:
        return None
    table = np.array([BOUNDING_BOX.holds(g) for g in structure.geometry_info] + [False])
    return jnp.asarray(table)


@functools.partial(jax.jit, static_argnames=("lanes", "backend"))
def _nearest_flat(
    points: jax.Array, structure: PrimitiveAccelerationStructure, max_distance, *, lanes: int, backend: str
):
    """The nearest leaf to each point ``(n, 3)`` within ``max_distance`` (-1 if none); not differentiated.
    ``backend``: the walk (:func:`jaxrt._src.traversal.points.resolve`)."""
    limit = jnp.asarray(max_distance, points.dtype)
    limit2 = jnp.where(jnp.isinf(limit), jnp.inf, limit * limit)
    if backend == "cpu":
        return points_backend.cpu_nearest(points, structure, _box_table(structure), limit2)
    if backend == "gpu":
        table = _box_table(structure)
        return in_morton_order(lambda p: points_backend.gpu_nearest(p, structure, table, limit2), points)
    start, step, done = _search(structure, _kind_tables(structure), limit2)
    return walk_points(points, start, step, done, lambda s: s.leaf, lanes=lanes)


def _closest_point_flat(
    points: jax.Array, structure: PrimitiveAccelerationStructure, max_distance, *, lanes: int, backend: str
):
    # The walk is compiled apart from the differentiable fields, so that gradients do not compile it again.
    detached = lax.stop_gradient
    leaf = _nearest_flat(detached(points), detached(structure), max_distance, lanes=lanes, backend=backend)
    return _fields_flat(points, structure, leaf)


@jax.jit
def _fields_flat(points: jax.Array, structure: PrimitiveAccelerationStructure, leaf: jax.Array) -> ClosestPointResult:
    """The result fields of the points' chosen leaves, differentiable in the points and the vertices."""
    dtype = points.dtype
    tables = _kind_tables(structure)
    found = leaf >= 0
    k = jnp.maximum(leaf, 0)
    dummy = jnp.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype)
    tri = jnp.where(found[:, None, None], structure.leaf_triangle[k], dummy)
    p = jnp.where(found[:, None], points, 0)
    u, v = jax.vmap(geo.closest_on_triangle)(p, tri)
    q = jax.vmap(geo.triangle_point)(tri, u, v)
    if tables:
        q = _other_kinds(structure, tables, p, k, q)
        geometry = structure.leaf_geometry[k]
        is_triangle = found & ~jnp.any(jnp.stack([t[jnp.where(geometry < 0, -1, geometry)] for _, t in tables]), 0)
        u = jnp.where(is_triangle, u, 0)
        v = jnp.where(is_triangle, v, 0)
    diff = p - q
    d2 = jnp.sum(diff * diff, axis=-1)
    positive = d2 > 0
    distance = jnp.where(positive, jnp.sqrt(jnp.where(positive, d2, 1)), 0)
    return ClosestPointResult(
        distance=jnp.where(found, distance, jnp.inf),
        point=jnp.where(found[:, None], q, jnp.inf),
        primitive_id=jnp.where(found, structure.leaf_primitive[k], -1),
        geometry_id=jnp.where(found, structure.leaf_geometry[k], -1),
        triangle_barycentric_coord=jnp.where(found[:, None], jnp.stack([u, v], axis=-1), 0),
    )


#: The smallest padded batch: small queries share one compiled program.
MIN_BATCH = 128


def _bucket(n: int) -> int:
    return max(MIN_BATCH, 1 << (max(n, 1) - 1).bit_length())


def run_flat(fn, points: jax.Array, *args, **kwargs):
    """``fn`` on ``points (..., 3)`` flattened and padded to a power-of-two count (repeating the first point),
    with every output reshaped back to the batch shape."""
    batch = points.shape[:-1]
    n = math.prod(batch)
    flat = points.reshape(n, 3)
    size = _bucket(n)
    if n == 0:
        flat = jnp.zeros((1, 3), points.dtype)
        size = _bucket(1)
    padded = jnp.concatenate([flat, jnp.broadcast_to(flat[:1], (size - flat.shape[0], 3))]) if size > n else flat
    out = fn(padded, *args, **kwargs)
    return jax.tree_util.tree_map(lambda a: a[:n].reshape(*batch, *a.shape[1:]), out)


def closest_point(
    points: jax.Array,
    structure: PrimitiveAccelerationStructure,
    *,
    max_distance: float = math.inf,
    backend: str = "auto",
) -> ClosestPointResult:
    """The nearest primitive of ``structure`` to each point, and the closest point on it.

    A BVH-pruned depth-first search per point (nearer child first, boxes farther than the best distance so
    far skipped) with an exact point-triangle distance (Ericson 2005, 5.1.5; safe for degenerate triangles).
    Works under ``jit`` and ``vmap``; ``distance``, ``point`` and the barycentrics differentiate with
    respect to the points and the structure's vertices (holding the chosen primitive fixed).

    Args:
      points: ``(..., 3)`` query points (finite).
      structure: a :class:`~jaxrt.PrimitiveAccelerationStructure` of triangle, bounding-box and sphere
        geometry (a box's distance is that of the solid box, 0 inside; a sphere's that of its surface).
        Instance structures and curves raise ``NotImplementedError``.
      max_distance: points farther than this from every primitive are misses.
      backend: the walk that picks the primitive: ``"auto"`` (the compiled walk of the default JAX backend
        where it covers the structure), ``"portable"`` (JAX), ``"cpu"`` (Numba) or ``"gpu"`` (Triton); see
        docs/point_queries.md. Every walk picks a nearest primitive; the result fields are computed from it in
        JAX on every walk.

    Returns:
      A :class:`ClosestPointResult` with the batch shape of ``points``; ties between primitives at the same
      distance go to either (each walk keeps the first it finds).

    Examples:
      >>> import jaxrt as rt
      >>> s = rt.build_primitive_structure(rt.TriangleGeometry([[0., 0, 0], [1, 0, 0], [0, 1, 0]]))
      >>> r = rt.closest_point([[0.25, 0.25, 2.0]], s)
      >>> float(r.distance[0]), r.point[0].tolist(), int(r.primitive_id[0])
      (2.0, [0.25, 0.25, 0.0], 0)
    """
    name = "closest_point"
    structure = check_structure(structure, name)
    walk = points_backend.resolve(backend, structure, name)
    check_not_empty(structure, name)
    dtype = structure.leaf_triangle.dtype
    points = check_points(points, name, dtype)
    if not isinstance(max_distance, jax.core.Tracer):
        value = float(np.asarray(max_distance))
        if not value >= 0:
            raise ValueError(f"{name}: max_distance must be non-negative, got {max_distance}")
    lanes = lanes_for_backend(LANES)
    return run_flat(_closest_point_flat, points, structure, max_distance, lanes=lanes, backend=walk)
