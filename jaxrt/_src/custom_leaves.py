"""Leaf tests that call user code: box primitives through intersection functions, non-opaque triangles
through the filter (Metal's bounding-box intersection functions and alpha-test triangle functions).

Both are :class:`~jaxrt._src.traversal.stack.LeafTester` objects, so the stack traversal calls them on the
leaves it reaches, nearest child first, and keeps the nearest accepted hit (or stops at the first with
``accept_any_intersection``). Under ``vmap`` every lane evaluates the user functions of every box geometry
and selects its own, as a ``lax.switch`` over the geometry would; opaque geometry never sees the filter's
answer, and structures without non-opaque triangles or boxes compile neither.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt._src.candidate import BoundingBoxCandidate, TriangleCandidate
from jaxrt._src.primitive_data import data_at
from jaxrt._src.primitives import triangle
from jaxrt._src.ray import Ray

__all__ = [
    "BoxLeaves",
    "FilteredTriangleLeaves",
    "KindLeaves",
    "box_geometries",
    "check_user_functions",
    "filtered_geometries",
    "function_ray",
    "geometry_table",
    "leaf_flag",
]


def box_geometries(structure: Any) -> tuple[int, ...]:
    """Indices of the structure's bounding-box geometries."""
    return tuple(i for i, g in enumerate(structure.geometry_info) if g.kind == "bounding_box")


def filtered_geometries(intersector: Any, structure: Any) -> tuple[int, ...]:
    """Indices of the non-opaque triangle geometries whose candidates go to the intersector's filter."""
    if intersector.filter is None:
        return ()
    return tuple(i for i, g in enumerate(structure.geometry_info) if g.kind == "triangle" and not g.opaque)


def geometry_table(count: int, members: tuple[int, ...]) -> jax.Array:
    """A bool lookup table over ``count`` geometry indices, True at ``members``; a last row stands for padding."""
    table = np.zeros(count + 1, bool)
    table[list(members)] = True
    return jnp.asarray(table)


def leaf_flag(table: jax.Array, leaf_geometry: jax.Array, leaves: jax.Array) -> jax.Array:
    """``table``'s entry for the geometry of each leaf (padding leaves, geometry -1, read the padding row)."""
    geometry = leaf_geometry[jnp.maximum(leaves, 0)]
    return table[jnp.where(geometry < 0, table.shape[0] - 1, geometry)]


def function_ray(origin: jax.Array, direction: jax.Array, t_min: jax.Array, t_max: jax.Array) -> Ray:
    """The :class:`~jaxrt.Ray` an intersection function sees: the ray, with ``max_distance`` the nearest
    accepted distance so far (mask and time keep their defaults)."""
    return Ray(origin, direction, t_min, t_max)


def box_candidate(structure_arrays: Any, leaf: jax.Array) -> BoundingBoxCandidate:
    """The candidate of box leaf ``leaf`` (one leaf)."""
    leaf_box, leaf_geometry, leaf_primitive, leaf_data = structure_arrays
    k = jnp.maximum(leaf, 0)
    box = leaf_box[k]
    return BoundingBoxCandidate(leaf_primitive[k], leaf_geometry[k], box[0], box[1], data_at(leaf_data, k))


def call_function(functions, ray: Ray, candidate: BoundingBoxCandidate) -> tuple[jax.Array, jax.Array]:
    """``(accept, distance)`` of the function of the candidate's geometry, checked against the ray interval."""
    accept = jnp.zeros((), bool)
    distance = jnp.full((), jnp.inf, ray.origin.dtype)
    for geometry, fn in functions:
        ok, t = fn(ray, candidate)
        ok = jnp.asarray(ok, bool) & (candidate.geometry_id == geometry)
        t = jnp.asarray(t, ray.origin.dtype)
        accept = accept | ok
        distance = jnp.where(ok, t, distance)
    accept = accept & (distance >= ray.min_distance) & (distance <= ray.max_distance)
    return accept, jnp.where(accept, distance, jnp.inf)


class BoxLeaves:
    """Box primitives: the user's intersection function decides each entered box (a ``LeafTester``)."""

    def __init__(self, structure: Any, functions: tuple[tuple[int, Callable], ...]):
        detached = jax.lax.stop_gradient
        self.arrays = (
            structure.leaf_box,
            structure.leaf_geometry,
            structure.leaf_primitive,
            jax.tree_util.tree_map(detached, structure.leaf_primitive_data),
        )
        self.functions = functions

    def prepare(self, origin, direction):
        return origin, direction

    def __call__(self, context, leaves, t_min, t_max):
        origin, direction = context
        ray = function_ray(origin, direction, t_min, t_max)

        def one(leaf):
            accept, t = call_function(self.functions, ray, box_candidate(self.arrays, leaf))
            return accept & (leaf >= 0), t

        return jax.vmap(one)(leaves)


class FilteredTriangleLeaves:
    """Watertight triangle tests whose hits on non-opaque geometry must pass the filter (a ``LeafTester``)."""

    def __init__(self, structure: Any, cull: int, clockwise_front: bool, filter_fn: Callable, filtered: tuple):
        detached = jax.lax.stop_gradient
        self.leaf_triangle = detached(structure.leaf_triangle)
        self.leaf_geometry = structure.leaf_geometry
        self.leaf_primitive = structure.leaf_primitive
        self.leaf_data = jax.tree_util.tree_map(detached, structure.leaf_primitive_data)
        self.cull = cull
        self.clockwise_front = clockwise_front
        self.filter_fn = filter_fn
        self.non_opaque = geometry_table(len(structure.geometry_info), filtered)

    def prepare(self, origin, direction):
        return triangle.shear_ray(origin, direction)

    def candidate(self, leaf: jax.Array, hit: triangle.TriangleHit) -> TriangleCandidate:
        """The filter's view of the watertight hit ``hit`` on leaf ``leaf`` (one leaf)."""
        k = jnp.maximum(leaf, 0)
        front = hit.clockwise if self.clockwise_front else ~hit.clockwise
        return TriangleCandidate(
            self.leaf_primitive[k],
            self.leaf_geometry[k],
            hit.distance,
            jnp.stack([hit.u, hit.v]),
            front,
            data_at(self.leaf_data, k),
        )

    def test(self, context, leaf, t_min, t_max) -> tuple[triangle.TriangleHit, jax.Array]:
        """The watertight hit of one leaf and whether the filter must decide it."""
        hit = triangle.watertight(context, t_min, t_max, self.leaf_triangle[jnp.maximum(leaf, 0)], self.cull)
        filtered = leaf_flag(self.non_opaque, self.leaf_geometry, leaf)
        return hit, filtered & hit.hit & (leaf >= 0)

    def __call__(self, context, leaves, t_min, t_max):
        def one(leaf):
            hit, filtered = self.test(context, leaf, t_min, t_max)
            accept = jnp.asarray(self.filter_fn(self.candidate(leaf, hit)), bool)
            ok = hit.hit & (leaf >= 0) & (~filtered | accept)
            return ok, jnp.where(ok, hit.distance, jnp.inf)

        return jax.vmap(one)(leaves)


class KindLeaves:
    """Box leaves and the other kinds in one structure: both tests, selected by each leaf's geometry kind."""

    def __init__(self, others: Any, boxes: BoxLeaves, structure: Any):
        self.others = others
        self.boxes = boxes
        self.leaf_geometry = structure.leaf_geometry
        self.is_box = geometry_table(len(structure.geometry_info), box_geometries(structure))

    def prepare(self, origin, direction):
        return self.others.prepare(origin, direction), self.boxes.prepare(origin, direction)

    def __call__(self, context, leaves, t_min, t_max):
        other_hit, other_t = self.others(context[0], leaves, t_min, t_max)
        box_hit, box_t = self.boxes(context[1], leaves, t_min, t_max)
        is_box = leaf_flag(self.is_box, self.leaf_geometry, leaves)
        return jnp.where(is_box, box_hit, other_hit), jnp.where(is_box, box_t, other_t)


def _abstract_call(fn: Callable, dtype, candidate: Any) -> Any:
    """The output shapes of ``fn(ray, candidate)`` for one abstract ray (traced, not run)."""
    scalar = jax.ShapeDtypeStruct((), dtype)
    vector = jax.ShapeDtypeStruct((3,), dtype)
    return jax.eval_shape(lambda o, d, a, b, c: fn(Ray(o, d, a, b), c), vector, vector, scalar, scalar, candidate)


def _abstract_data(structure: Any) -> Any:
    return jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(a.shape[1:], a.dtype), structure.leaf_primitive_data)


def _is_scalar(x: Any) -> bool:
    return hasattr(x, "shape") and tuple(x.shape) == ()


def check_user_functions(intersector: Any, structure: Any) -> None:
    """Host-side checks of intersection functions and the filter against a structure (named errors).

    Every box geometry needs a function; functions must name box geometries; a function must return a pair
    ``(accept, distance)`` of scalars and the filter one scalar (checked by tracing them abstractly).
    """
    functions: Mapping[int, Callable] = dict(intersector.intersection_functions or ())
    infos = structure.geometry_info
    boxes = box_geometries(structure)
    for index in boxes:
        if index not in functions:
            raise ValueError(
                f"Intersector.intersect: geometry {index} is a BoundingBoxGeometry but the intersector has no "
                f"intersection function for it (pass intersection_functions={{{index}: fn}})"
            )
    for index in functions:
        if index >= len(infos) or infos[index].kind != "bounding_box":
            kind = "absent" if index >= len(infos) else f"a {infos[index].kind} geometry"
            raise ValueError(
                f"Intersector.intersect: intersection_functions names geometry {index}, which is {kind}; "
                "intersection functions apply to BoundingBoxGeometry only"
            )
    dtype = structure.leaf_triangle.dtype
    data = _abstract_data(structure)
    int_scalar = jax.ShapeDtypeStruct((), jnp.int32)
    vector = jax.ShapeDtypeStruct((3,), dtype)
    for index in boxes:
        fn = functions[index]
        candidate = BoundingBoxCandidate(int_scalar, int_scalar, vector, vector, data)
        out = _abstract_call(fn, dtype, candidate)
        if not (isinstance(out, tuple | list) and len(out) == 2 and all(_is_scalar(x) for x in out)):
            raise TypeError(
                f"Intersector: the intersection function of geometry {index} must return a pair (accept, "
                f"distance) of scalars for one ray and one candidate, got {out!r}"
            )
    if filtered_geometries(intersector, structure):
        scalar = jax.ShapeDtypeStruct((), dtype)
        candidate = TriangleCandidate(
            int_scalar,
            int_scalar,
            scalar,
            jax.ShapeDtypeStruct((2,), dtype),
            jax.ShapeDtypeStruct((), bool),
            data,
        )
        out = jax.eval_shape(intersector.filter, candidate)
        if not _is_scalar(out):
            raise TypeError(f"Intersector: the filter must return one scalar accept flag per candidate, got {out!r}")
