"""Leaf tests for the traversal: one tester per primitive kind, and the one per-leaf switch between kinds.

Every tester follows :class:`~jaxrt._src.traversal.step.LeafTester`: ``prepare(origin, direction, facing)``
gives per-ray constants in the space of the level being walked (``facing`` is ``None`` in a scene without
instances, else the level's winding flip or culling switch), and ``tester(context, leaves, t_min, t_max)``
tests a pair of global leaves (``-1``: none). :func:`leaf_tester` composes the tests a scene and an intersector
need: only the kinds present are compiled; several kinds go through :class:`KindSwitch`, which selects each
leaf's answer by its geometry slot.

User code: non-opaque triangles go through the intersector's ``filter`` (:class:`FilteredTriangleLeaves`) and
box primitives through its intersection functions (:class:`BoxLeaves`) (Metal's alpha-test triangle functions
and bounding-box intersection functions). Under ``vmap`` every lane evaluates the functions of every box
geometry and selects its own, as a ``lax.switch`` over the geometry would. Intersection functions are keyed
by the geometry's index within its own structure (the ``geometry_id`` hits report), at every instance level.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from jax import lax

from jaxrt._src import curves as curve_support
from jaxrt._src.candidate import BoundingBoxCandidate, TriangleCandidate
from jaxrt._src.kinds.kind import Kind
from jaxrt._src.kinds.registry import BOUNDING_BOX, CURVE, KINDS, TRIANGLE
from jaxrt._src.primitive_data import data_at
from jaxrt._src.primitives import triangle
from jaxrt._src.ray import Ray
from jaxrt._src.scene_view import SceneView

__all__ = [
    "BoxLeaves",
    "FilteredTriangleLeaves",
    "FormulaLeaves",
    "KindSwitch",
    "MotionLeaves",
    "TriangleLeaves",
    "box_candidate",
    "box_slots",
    "curve_configuration",
    "call_function",
    "filtered_slots",
    "formula_rows",
    "function_ray",
    "leaf_tester",
]


def _accept_facing(hit: triangle.TriangleHit, cull: jax.Array) -> jax.Array:
    """``hit.hit`` with a traced cull sense: +1 culls clockwise triangles, -1 counterclockwise ones, 0 none."""
    return hit.hit & ~((cull > 0) & hit.clockwise) & ~((cull < 0) & ~hit.clockwise)


class TriangleLeaves:
    """Watertight triangle tests (Woop et al. 2013). Outside instances the cull sense is static; below them
    it is the intersector's times the level's ``facing``."""

    def __init__(self, leaf_triangle: jax.Array, cull: int):
        self.leaf_triangle = leaf_triangle
        self.cull = cull

    def prepare(self, origin, direction, facing):
        sheared = triangle.shear_ray(origin, direction)
        return sheared if facing is None else (sheared, facing)

    def test(self, context, leaves, t_min, t_max) -> tuple[triangle.TriangleHit, jax.Array]:
        """The watertight hits of ``leaves`` and whether each is accepted by the cull mode."""
        vertices = self.leaf_triangle[jnp.maximum(leaves, 0)]
        if isinstance(context, triangle.ShearedRay):
            hit = triangle.watertight(context, t_min, t_max, vertices, self.cull)
            return hit, hit.hit & (leaves >= 0)
        sheared, facing = context
        hit = triangle.watertight(sheared, t_min, t_max, vertices, 0)
        accept = _accept_facing(hit, facing * self.cull) if self.cull else hit.hit
        return hit, accept & (leaves >= 0)

    def __call__(self, context, leaves, t_min, t_max):
        hit, accept = self.test(context, leaves, t_min, t_max)
        return accept, hit.distance  # the traversal reads the distance only where accepted


def filtered_slots(intersector: Any, view: SceneView) -> tuple[int, ...]:
    """Geometry slots of non-opaque triangle geometry whose candidates go to the intersector's filter."""
    if intersector.filter is None:
        return ()
    return view.slots_where(lambda g: TRIANGLE.holds(g) and not g.opaque)


def box_slots(view: SceneView) -> tuple[int, ...]:
    """Geometry slots of bounding-box geometry."""
    return view.slots_where(BOUNDING_BOX.holds)


class FilteredTriangleLeaves(TriangleLeaves):
    """Triangle tests whose hits on non-opaque geometry must pass the filter."""

    def __init__(self, view: SceneView, cull: int, clockwise_front: bool, filter_fn: Callable, slots: tuple):
        detached = lax.stop_gradient
        super().__init__(detached(view.leaves.triangle), cull)
        self.view = view
        self.leaf_data = jax.tree_util.tree_map(detached, view.leaves.primitive_data)
        self.clockwise_front = clockwise_front
        self.filter_fn = filter_fn
        self.non_opaque = view.slot_table(slots)

    def candidate(self, leaf: jax.Array, hit: triangle.TriangleHit, flip: Any = False) -> TriangleCandidate:
        """The filter's view of the watertight hit ``hit`` on leaf ``leaf`` (one leaf)."""
        k = jnp.maximum(leaf, 0)
        clockwise = hit.clockwise ^ flip
        front = clockwise if self.clockwise_front else ~clockwise
        leaves = self.view.leaves
        return TriangleCandidate(
            leaves.primitive[k],
            leaves.geometry[k],
            hit.distance,
            jnp.stack([hit.u, hit.v]),
            front,
            data_at(self.leaf_data, k),
        )

    def __call__(self, context, leaves, t_min, t_max):
        # Below instances the object-space winding is flipped where the level's facing is negative (an
        # instance that disables culling has facing 0: its candidates report the object-space winding).
        flip = False if isinstance(context, triangle.ShearedRay) else context[1] < 0

        def one(leaf):
            hit, accept = self.test(context, leaf, t_min, t_max)
            filtered = self.view.leaf_flag(self.non_opaque, leaf) & accept
            ok = accept & (~filtered | jnp.asarray(self.filter_fn(self.candidate(leaf, hit, flip)), bool))
            return ok, jnp.where(ok, hit.distance, jnp.inf)

        return jax.vmap(one)(leaves)


def function_ray(origin: jax.Array, direction: jax.Array, t_min: jax.Array, t_max: jax.Array) -> Ray:
    """The :class:`~jaxrt.Ray` an intersection function sees: the ray (in the box's object space), with
    ``max_distance`` the nearest accepted distance so far (mask and time keep their defaults)."""
    return Ray(origin, direction, t_min, t_max)


def box_candidate(view: SceneView, leaf: jax.Array, data: Any = None, box: Any = None) -> BoundingBoxCandidate:
    """The candidate of box leaf ``leaf`` (one leaf); ``data`` the per-leaf primitive data to read, ``box``
    the ``(2, 3)`` box where it is not the view's (a moving box blended at the ray's time)."""
    k = jnp.maximum(leaf, 0)
    leaves = view.leaves
    box = leaves.box[k] if box is None else box
    data = leaves.primitive_data if data is None else data
    return BoundingBoxCandidate(leaves.primitive[k], leaves.geometry[k], box[0], box[1], data_at(data, k))


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
    """Box primitives: the user's intersection function decides each entered box."""

    def __init__(self, view: SceneView, functions: tuple[tuple[int, Callable], ...]):
        self.view = view
        self.data = jax.tree_util.tree_map(lax.stop_gradient, view.leaves.primitive_data)
        self.functions = functions

    def prepare(self, origin, direction, facing):
        del facing  # culling applies to triangles only
        return origin, direction

    def __call__(self, context, leaves, t_min, t_max):
        origin, direction = context
        ray = function_ray(origin, direction, t_min, t_max)

        def one(leaf):
            accept, t = call_function(self.functions, ray, box_candidate(self.view, leaf, self.data))
            return accept & (leaf >= 0), t

        return jax.vmap(one)(leaves)


class FormulaLeaves:
    """The leaves of a kind tested by its formula alone (``Kind.formula_leaves``: built-in spheres): the kind's
    ``intersect`` on the rows of its first leaf array; hits on the kind's non-opaque geometries must pass the
    intersector's filter where it has one (a :class:`~jaxrt.TriangleCandidate` with zero barycentrics)."""

    def __init__(self, kind: Kind, view: SceneView, rows: Any, filter_fn: Callable | None = None):
        self.kind = kind
        self.view = view
        self.rows = rows
        self.filter_fn = filter_fn
        if filter_fn is not None:
            self.non_opaque = view.slot_table(view.slots_where(lambda g: kind.holds(g) and not g.opaque))
            self.leaf_data = jax.tree_util.tree_map(lax.stop_gradient, view.leaves.primitive_data)

    def prepare(self, origin, direction, facing):
        del facing  # culling applies to triangles only
        return origin, direction

    def __call__(self, context, leaves, t_min, t_max):
        origin, direction = context
        k = jnp.maximum(leaves, 0)
        hit, distance, front = self.kind.intersect(origin, direction, t_min, t_max, self.rows[k])
        hit = hit & (leaves >= 0)
        if self.filter_fn is not None:
            leaf_arrays = self.view.leaves

            def one(leaf, ok, t, front):
                k = jnp.maximum(leaf, 0)
                candidate = TriangleCandidate(
                    leaf_arrays.primitive[k],
                    leaf_arrays.geometry[k],
                    t,
                    jnp.zeros((2,), t.dtype),
                    front,
                    data_at(self.leaf_data, k),
                )
                filtered = self.view.leaf_flag(self.non_opaque, leaf) & ok
                return ok & (~filtered | jnp.asarray(self.filter_fn(candidate), bool))

            hit = jax.vmap(one)(leaves, hit, distance, front)
        return hit, jnp.where(hit, distance, jnp.inf)


def formula_rows(kind: Kind, view: SceneView) -> jax.Array:
    """The leaf rows a ``formula_leaves`` kind is tested on: its first leaf array, as the scene view holds it."""
    return getattr(view.leaves, kind.leaf_arrays[0].name.removeprefix("leaf_"))


class KindSwitch:
    """Several kinds in one scene: every kind's test runs, and each leaf takes its own kind's answer."""

    def __init__(self, view: SceneView, testers: dict[str, Any]):
        self.view = view
        self.kinds = tuple(sorted(testers))
        self.testers = tuple(testers[k] for k in self.kinds)
        self.tables = tuple(view.slot_table(view.slots_where(lambda g, k=k: g.kind == k)) for k in self.kinds)

    def prepare(self, origin, direction, facing):
        return tuple(t.prepare(origin, direction, facing) for t in self.testers)

    def __call__(self, context, leaves, t_min, t_max):
        hit = jnp.zeros(leaves.shape, bool)
        distance = jnp.full(leaves.shape, jnp.inf, t_max.dtype)
        for tester, table, part in zip(self.testers, self.tables, context, strict=True):
            kind_hit, kind_t = tester(part, leaves, t_min, t_max)
            mine = self.view.leaf_flag(table, leaves)
            hit, distance = jnp.where(mine, kind_hit, hit), jnp.where(mine, kind_t, distance)
        return hit, distance


def curve_configuration(intersector: Any, view: SceneView) -> dict:
    """The static curve code choices for every curve geometry of the scene (all levels share them)."""
    infos = tuple(g.curve for g in view.geometry_info if g.curve is not None)
    return curve_support.curve_configuration(infos, intersector.curve_type, intersector.curve_options)


class MotionLeaves:
    """Leaf tests of a scene with primitive motion: the static tests run on the leaves blended at each ray's
    time (:meth:`~jaxrt._src.scene_view.SceneView.at`), and moving leaves vanish outside the motion range
    on a ``"vanish"`` border. ``prepare`` takes the ray's time (``reads_time``)."""

    reads_time = True

    def __init__(self, view: SceneView, make: Callable[[SceneView], Any]):
        self.view = view
        self.make = make
        self.static = make(view)
        self.moving = view.slot_table(view.slots_where(lambda g: g.motion))

    def prepare(self, origin, direction, facing, time=None):
        return self.static.prepare(origin, direction, facing), self.view.keyframe_position(time)

    def __call__(self, context, leaves, t_min, t_max):
        inner, position = context
        hit, distance = self.make(self.view.at(position))(inner, leaves, t_min, t_max)
        vanished = ~position.visible & self.view.leaf_flag(self.moving, leaves)
        return hit & ~vanished, distance


def leaf_tester(intersector: Any, view: SceneView, *, user_code: bool = True) -> Any:
    """The leaf tests the scene's kinds need: triangles (filtered where non-opaque), curves, boxes and each
    ``formula_leaves`` kind (spheres) through :class:`FormulaLeaves`; with
    primitive motion, on the leaves blended at each ray's time (:class:`MotionLeaves`).

    Without ``user_code`` neither the filter nor intersection functions are called: box leaves never hit and
    non-opaque triangles are tested as opaque ones (an intersection query decides them itself).
    """
    if view.leaves.motion is not None:
        return MotionLeaves(view, lambda v: _static_tester(intersector, v, user_code))
    return _static_tester(intersector, view, user_code)


def _static_tester(intersector: Any, view: SceneView, user_code: bool) -> Any:
    detached = lax.stop_gradient
    kinds = view.kinds
    testers: dict[str, Any] = {}
    if TRIANGLE.name in kinds:
        slots = filtered_slots(intersector, view) if user_code else ()
        if slots:
            clockwise_front = intersector.front_facing_winding == "clockwise"
            testers[TRIANGLE.name] = FilteredTriangleLeaves(
                view, intersector.cull, clockwise_front, intersector.filter, slots
            )
        else:
            testers[TRIANGLE.name] = TriangleLeaves(detached(view.leaves.triangle), intersector.cull)
    if CURVE.name in kinds:
        config = curve_configuration(intersector, view)
        testers[CURVE.name] = curve_support.CurveLeaves(detached(view.leaves.curve), view.leaves.curve_flags, **config)
    for kind in KINDS:
        if kind.formula_leaves and kind.name in kinds:
            non_opaque = any(kind.holds(g) and not g.opaque for g in view.geometry_info)
            filter_fn = intersector.filter if user_code and non_opaque else None
            testers[kind.name] = FormulaLeaves(kind, view, detached(formula_rows(kind, view)), filter_fn)
    if BOUNDING_BOX.name in kinds and user_code:
        testers[BOUNDING_BOX.name] = BoxLeaves(view, intersector.intersection_functions or ())
    if len(testers) == 1 and set(testers) == set(kinds):
        return next(iter(testers.values()))
    return KindSwitch(view, testers)  # also when a kind has no test: its leaves never hit
