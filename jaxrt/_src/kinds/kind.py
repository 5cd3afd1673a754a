"""The record that defines a primitive kind (:class:`Kind`), and what one compiled traversal covers of it
(:class:`Coverage`).

A kind is one definition: its leaf arrays, its bounds, the traversal's exact test and the differentiable
re-intersection behind the result fields, the tags it adds, the decisions that need JAX, and each compiled
traversal's coverage. The modules of this package declare one kind each; :mod:`jaxrt._src.kinds.registry`
lists them, and coverage, leaf packing, file formats and result assembly iterate over that list.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["AnalyticRow", "Coverage", "Kind", "LeafArray"]


@dataclasses.dataclass(frozen=True)
class LeafArray:
    """One per-leaf array of a kind in a primitive structure (a row of the kind's layout table).

    Attributes:
      name: the field of :class:`~jaxrt._src.structures.PrimitiveAccelerationStructure` (and, without the
        ``leaf_`` prefix, of :class:`~jaxrt._src.scene_view.LeafArrays`).
      shape: the shape of one leaf's row.
      dtype: ``"float"`` (the geometry's float type) or a NumPy type name.
      fill: what rows of other kinds and of padding hold: ``"zeros"`` or ``"empty box"`` (``+inf`` lower,
        ``-inf`` upper corner, so that no ray enters it).
      keyframes: the field of the keyframed rows ``(K, C, *shape)`` with keyframe motion, or ``None`` when the
        array does not move (flags).
      doc: what a row holds.
      shared: every primitive structure has the array, whatever its kinds (rows of other kinds hold the fill);
        else only structures with geometry of the kind have it (``None`` otherwise).
    """

    name: str
    shape: tuple[int, ...]
    dtype: str
    fill: str
    keyframes: str | None
    doc: str
    shared: bool = False


@dataclasses.dataclass(frozen=True)
class Coverage:
    """What one compiled traversal (the GPU kernel, the CPU traversal) traces of a kind; the portable traversal
    traces everything.

    Attributes:
      traced: the traversal tests the kind's leaves at all.
      instanced: also below instances.
      motion: also in a scene with keyframe motion (primitive or instance).
      alone: not in one structure with another kind that is not a triangle.
      waves: candidate waves (:mod:`jaxrt._src.traversal.waves`) list this kind's leaves, so that JAX can take
        the decisions of user code on a scene that holds them.
    """

    traced: bool = True
    instanced: bool = True
    motion: bool = True
    alone: bool = False
    waves: bool = True


#: The columns of an analytic row (:func:`jaxrt._src.traversal.packed.pack_analytic`) an :class:`AnalyticRow`'s
#: test may read, by name: ``p`` (columns 0-2), ``q`` (4-6) and ``radius`` (7); column 3 holds the shape code.
ROW_COLUMNS = ("px", "py", "pz", "qx", "qy", "qz", "radius")


@dataclasses.dataclass(frozen=True)
class AnalyticRow:
    """How the compiled loops test the leaves of a kind whose formula alone decides them (``formula_leaves``):
    as analytic rows, the parameter rows the GPU kernel and the CPU traversal also read for the built-in
    intersection functions of bounding boxes. The loops' leaf dispatch is generated from these records
    (:mod:`jaxrt._src.traversal.analytic_rows`), so a new kind needs no branch of its own there.

    Attributes:
      code: the shape code in column 3 of the kind's rows (``>= 5``: codes 1-3 are the built-in intersection
        functions, 4 the candidate boxes of user functions); bit ``code`` of the traversals' ``shapes`` says a
        scene holds such leaves.
      formula: the formula module (:mod:`jaxrt._src.formulas`) that holds the test.
      test: the test's name in that module: ``(*columns, ox, oy, oz, dx, dy, dz, t_min, t_max) -> (hit,
        distance, ...)`` (further results are ignored).
      columns: the row columns the test takes first, by name (:data:`ROW_COLUMNS`).
      results: how many values the test returns (at least ``hit`` and ``distance``).
      pack: ``leaf rows (C, *shape) -> (p (C, 3), q (C, 3), radius (C,))``: the analytic row's parameters from
        the rows of the kind's first leaf array (detached; unused values are zeros).
    """

    code: int
    formula: str
    test: str
    columns: tuple[str, ...]
    results: int
    pack: Callable[[Any], tuple[Any, Any, Any]]


@dataclasses.dataclass(frozen=True, eq=False)
class Kind:
    """One primitive kind (identity is equality: each kind is defined once, in its module).

    Attributes:
      name: the kind's name in :class:`~jaxrt._src.structures.GeometryInfo` and in saved files.
      plural: how messages name its geometry ("curves"), and ``be`` the verb that agrees with it.
      intersection_type: the value of ``rt.IntersectionType`` its hits report.
      leaf_arrays: its per-leaf arrays (the layout table of its module's docstring).
      bounds: ``row -> (lower, upper)``: the box of one leaf row (the first of ``leaf_arrays``).
      intersect: the exact test the traversals make (JAX, batched over leaves).
      reintersect: the differentiable test the result fields are computed from (``None``: the geometry's
        intersection function, called again by the result fields).
      closest_point: the point-to-primitive formula of point queries (``rt.closest_point``, winding numbers),
        ``(point, row) -> closest point``; ``None``: point queries refuse the kind.
      tags: the intersector tags whose fields the kind fills.
      fields: the result fields the kind fills, each with the tag that asks for it.
      coverage: by backend name (``"gpu"``, ``"cpu"``): what that compiled traversal traces of the kind.
      function_code: ``(intersector, geometry_info, traversal, where) -> str | None``: why the compiled
        ``traversal`` (its name, for the message; ``where`` qualifies it) hands the hits of the kind's
        geometries among ``geometry_info`` to user intersection functions (``None``: it does not). Such a
        decision needs JAX: the traversal hands it over in candidate waves, or leaves the scene to the portable
        one.
      filter_code: the same for user filters (decided per primitive instead where the filter reads only the
        primitive, :mod:`jaxrt._src.filter_states`).
      declines: ``(intersector, geometry_info, traversal) -> str | None``: what else of the kind no compiled
        traversal takes, even in candidate waves (``None``: nothing).
      formula_leaves: the portable traversal and the result fields need no code of their own for the kind
        (:mod:`jaxrt._src.leaves`, :mod:`jaxrt._src.fields` iterate over such kinds): the leaves are tested by
        ``intersect`` on the rows of the first of ``leaf_arrays``, ``(origin, direction, t_min, t_max, row) ->
        (hit, distance, front)``; a user filter on the kind's non-opaque geometries sees a
        :class:`~jaxrt.TriangleCandidate` with zero barycentrics and ``front``; the fields run ``reintersect``
        again on each hit's interval (the distance's gradient), report ``front`` as ``front_field`` and take the
        surface normal from ``normal``.
      normal: ``(origin, direction, distance, row) -> normal`` (not normalised, object space) of a
        ``formula_leaves`` kind.
      front_field: the result field that reports a ``formula_leaves`` kind's ``front`` (false off the kind).
      dummy: ``dtype -> (row, origin, direction)``: a leaf row and a ray that hit each other, tested in the
        lanes of other kinds so that their zero gradients hold no NaN (``formula_leaves`` kinds).
      inside: ``(point, row) -> bool``: whether the point lies inside the closed primitive of a row, for a
        kind that winding numbers count as a solid (1 inside, 0 outside: no surface orientation to integrate);
        ``None``: the kind is counted by its triangles' solid angles.
      checks: ``geometry -> ((message, bad, value), ...)``: the rules of ``checks=True`` for a geometry of the
        kind: ``bad (N,)`` flags the bad rows of ``value (N, ...)``; ``message`` names the array with
        ``{index}`` and ``{value}`` (``None``: the kind has no rules, or :mod:`jaxrt._src.checks` writes them).
      doc: what a hit of the kind is: the docstring of its ``rt.IntersectionType`` member.
      tag_docs: the tags the kind defines, each with its docstring (``rt.tags.<name>``, added to
        :mod:`jaxrt.tags` by the registry); ``tags`` lists them with the shared ones it also fills.
      geometry: the name of the kind's static geometry class, for messages (its keyframed variant is
        ``"Motion" + geometry``).
      float_array: the attribute of the kind's geometries whose dtype is the geometry's float type.
      code_bounds: ``row -> (lower, upper)``: the box whose centre gives a leaf's Morton code (``None``:
        ``bounds``), for a kind whose bounds may be empty where the leaf still has a place (a bad sphere).
      analytic: how the compiled loops test the kind's leaves (``None``: a branch of their own, or not traced).

    The build reads a kind's leaves through this record and the geometry protocol: a geometry names its kind
    (``kind``), has ``primitive_count`` and ``opaque``, ``motion = True`` and ``keyframe(k)`` when keyframed, and,
    for a kind other than triangles whose first leaf array is the shared ``leaf_triangle`` row, ``leaf_rows()``
    (``(N, 3, 3)``, differentiable): the build bounds those rows with ``bounds`` and codes them with
    ``code_bounds``.
    """

    name: str
    plural: str
    be: str
    intersection_type: int
    leaf_arrays: tuple[LeafArray, ...]
    bounds: Callable[..., Any]
    intersect: Callable[..., Any]
    reintersect: Callable[..., Any] | None
    closest_point: Callable[..., Any] | None
    tags: tuple[str, ...]
    fields: Mapping[str, str]
    coverage: Mapping[str, Coverage]
    function_code: Callable[[Any, tuple, str, str], str | None] | None = None
    filter_code: Callable[[Any, tuple, str, str], str | None] | None = None
    declines: Callable[[Any, tuple, str], str | None] | None = None
    formula_leaves: bool = False
    normal: Callable[..., Any] | None = None
    front_field: str | None = None
    dummy: Callable[[Any], tuple[Any, Any, Any]] | None = None
    inside: Callable[..., Any] | None = None
    checks: Callable[[Any], tuple[tuple[str, Any, Any], ...]] | None = None
    doc: str = ""
    tag_docs: Mapping[str, str] = dataclasses.field(default_factory=dict)
    geometry: str = ""
    float_array: str = ""
    code_bounds: Callable[..., Any] | None = None
    analytic: AnalyticRow | None = None

    def holds(self, info: Any) -> bool:
        """Whether the geometry described by ``info`` (a ``GeometryInfo`` or a geometry) is of this kind."""
        return info.kind == self.name

    def __repr__(self) -> str:
        return f"Kind({self.name!r})"
