"""The intersector: static tags and options, and their validation against a structure (Metal's ``intersector``).

Tracing itself is :mod:`jaxrt._src.pipeline`; this module holds configuration only."""

from __future__ import annotations

import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt import tags as tag_module
from jaxrt._src import curves as curve_support
from jaxrt._src import pipeline
from jaxrt._src.candidate import BoundingBoxCandidate, TriangleCandidate
from jaxrt._src.instances import InstanceAccelerationStructure, InstanceOptions
from jaxrt._src.kinds import registry
from jaxrt._src.kinds.registry import BOUNDING_BOX, TRIANGLE
from jaxrt._src.primitives.curve import CurveOptions
from jaxrt._src.ray import Ray
from jaxrt._src.result import IntersectionResult, IntersectionType
from jaxrt._src.scene_view import primitive_structures
from jaxrt._src.structures import PrimitiveAccelerationStructure

__all__ = ["Intersector", "count_intersections"]

_SUPPORTED_TAGS = registry.RESULT_TAGS
#: Geometry kinds ``geometry_types`` may name (strings or ``rt.IntersectionType`` members).
_GEOMETRY_TYPES = {IntersectionType(k.intersection_type): k.name for k in registry.KINDS}
_CULL_MODES = ("none", "front", "back")
_WINDINGS = ("clockwise", "counterclockwise")
_BACKENDS = ("auto", "portable", "gpu", "cpu")


class Intersector:
    """Intersects rays with acceleration structures (Metal's ``intersector``).

    Args:
      *tags: tags from ``rt.tags``; each adds result fields and only then compiles their work.
      accept_any_intersection: stop at the first accepted hit (occlusion/shadow rays) instead of the nearest.
      triangle_cull_mode: ``"none"``, ``"front"`` or ``"back"``: skip triangles facing that way.
      front_facing_winding: ``"clockwise"`` (Metal's default) or ``"counterclockwise"``: the winding, seen
        from the ray origin, of a front-facing triangle. With right-handed coordinates a triangle is clockwise
        when ``dot(cross(v1 - v0, v2 - v0), ray.direction) > 0``.
      backend: ``"auto"`` (the GPU kernel on a GPU, the compiled CPU traversal on the CPU, where they cover the
        scene; else the portable traversal), ``"portable"`` (the vmapped stack traversal in JAX: the reference,
        and the path on TPUs), ``"gpu"`` or ``"cpu"`` (force one; ``ValueError`` where it cannot run).
      geometry_types: the geometry kinds the structures hold (Metal's ``assume_geometry_type``): one of, or a
        collection of, ``"triangle"``, ``"curve"`` (or ``rt.IntersectionType`` members). Tracing a structure
        with another kind is a ``ValueError``. ``None``: whatever the structure holds. Either way only the
        kinds present are compiled: a triangle-only structure compiles no curve code.
      curve_basis, curve_type, curve_control_point_count: what every curve geometry is (Metal's
        ``assume_curve_*``): a ``rt.CurveBasis``, a ``rt.CurveType``, an int; checked at ``intersect``. The
        compiled code already follows the structure's curve types, end caps and bases (linear-only
        structures use the exact round-cone test).
      curve_options: static accuracy knobs of the curve test (``rt.CurveOptions``; see docs/curves.md).
      intersection_functions: mapping from the index of a ``rt.BoundingBoxGeometry`` in the structure to
        ``fn(ray, candidate) -> (accept, distance)``, an ordinary JAX function of one ray (an ``rt.Ray`` whose
        ``max_distance`` is the nearest accepted distance so far) and one
        :class:`~jaxrt.BoundingBoxCandidate`. It is called on every box the ray enters, nearer subtrees
        first; the nearest accepted distance inside ``[min_distance, max_distance]`` is the hit. Hits are
        differentiable through the function (it is called again on the chosen box with gradients).
      filter: ``fn(candidate) -> accept`` for triangles of non-opaque geometry (``opaque=False``): called on
        each such candidate hit (an :class:`~jaxrt.TriangleCandidate`, with barycentrics and primitive data);
        rejected candidates do not end the search (alpha testing). Opaque geometry never uses it; non-opaque
        triangles without a filter are accepted.
      max_hits: static ``K``: return the ``K`` nearest hits per ray, sorted by distance, on an axis after the
        batch axes of every hit field (``distance`` is ``(..., K)``, ``triangle_barycentric_coord``
        ``(..., K, 2)``), plus ``hit_count`` (hits returned) and ``hit_overflow`` (more than ``K`` existed).
        Not with ``accept_any_intersection``.

    All options are static and hashable: an intersector can be closed over by ``jax.jit`` and used as a
    static argument.

    Raises:
      ValueError: an unknown tag or a bad option value. NotImplementedError: a tag or option for a feature
        this version does not provide.

    Examples:
      >>> import jaxrt as rt
      >>> s = rt.build_primitive_structure(rt.TriangleGeometry([[0., 0, 0], [1, 0, 0], [0, 1, 0]]))
      >>> hit = rt.Intersector(rt.tags.triangle_data).intersect(rt.Ray([.2, .2, -1], [0., 0, 1]), s)
      >>> float(hit.distance), [round(x, 4) for x in hit.triangle_barycentric_coord.tolist()]
      (1.0, [0.2, 0.2])
    """

    def __init__(
        self,
        *tags: tag_module.Tag,
        accept_any_intersection: bool = False,
        triangle_cull_mode: str = "none",
        front_facing_winding: str = "clockwise",
        backend: str = "auto",
        geometry_types: Any = None,
        curve_basis: Any = None,
        curve_type: Any = None,
        curve_control_point_count: Any = None,
        intersection_functions: Any = None,
        filter: Any = None,  # noqa: A002 - Metal's name
        max_hits: Any = None,
        curve_options: Any = None,
    ):
        for tag in tags:
            if not isinstance(tag, tag_module.Tag) or tag.name not in tag_module.KNOWN:
                raise ValueError(f"Intersector: unknown tag {tag!r}; tags come from jaxrt.tags")
            if tag.name not in _SUPPORTED_TAGS:
                raise NotImplementedError(f"Intersector: tags.{tag.name} is not supported in this version")
        _check_tags(tags)
        if triangle_cull_mode not in _CULL_MODES:
            raise ValueError(
                f"Intersector: triangle_cull_mode must be one of {_CULL_MODES}, got {triangle_cull_mode!r}"
            )
        if front_facing_winding not in _WINDINGS:
            raise ValueError(
                f"Intersector: front_facing_winding must be one of {_WINDINGS}, got {front_facing_winding!r}"
            )
        if backend not in _BACKENDS:
            raise ValueError(f"Intersector: backend must be one of {_BACKENDS}, got {backend!r}")
        if not isinstance(accept_any_intersection, bool):
            raise ValueError(f"Intersector: accept_any_intersection must be a bool, got {accept_any_intersection!r}")
        self.geometry_types = _geometry_types(geometry_types)
        self.curve_basis = None if curve_basis is None else curve_support.CurveBasis.coerce(curve_basis, "Intersector")
        self.curve_type = None if curve_type is None else curve_support.CurveType.coerce(curve_type, "Intersector")
        if curve_control_point_count is not None and curve_control_point_count not in (2, 3, 4):
            raise ValueError(
                f"Intersector: curve_control_point_count must be 2, 3 or 4, got {curve_control_point_count!r}"
            )
        self.curve_control_point_count = curve_control_point_count

        if curve_options is not None and not isinstance(curve_options, CurveOptions):
            raise TypeError(f"Intersector: curve_options must be an rt.CurveOptions, got {curve_options!r}")
        self.curve_options = curve_options
        self.intersection_functions = _functions(intersection_functions)
        if filter is not None and not callable(filter):
            raise TypeError(f"Intersector: filter must be a callable fn(candidate) -> accept, got {filter!r}")
        self.filter = filter
        if max_hits is not None:
            if isinstance(max_hits, bool) or not isinstance(max_hits, int) or max_hits < 1:
                raise ValueError(f"Intersector: max_hits must be a positive int, got {max_hits!r}")
            if accept_any_intersection:
                raise ValueError("Intersector: max_hits and accept_any_intersection exclude each other")
        self.max_hits = max_hits
        self.tags = tuple(sorted(set(tags)))
        self.accept_any_intersection = accept_any_intersection
        self.triangle_cull_mode = triangle_cull_mode
        self.front_facing_winding = front_facing_winding
        self.backend = backend

    #: Whether the intersector only counts hits (:func:`count_intersections`).
    counts_all = False

    def _key(self):
        return (
            type(self),
            self.tags,
            self.accept_any_intersection,
            self.triangle_cull_mode,
            self.front_facing_winding,
            self.backend,
            self.geometry_types,
            self.curve_basis,
            self.curve_type,
            self.curve_control_point_count,
            self.curve_options,
            self.intersection_functions,
            self.filter,
            self.max_hits,
            self.counts_all,
        )

    def __hash__(self) -> int:
        return hash(self._key())

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Intersector) and self._key() == other._key()

    def __repr__(self) -> str:
        tags = ", ".join(t.name if t.value is None else f"{t.name}({t.value})" for t in self.tags)
        return (
            f"Intersector({tags}, accept_any_intersection={self.accept_any_intersection}, "
            f"triangle_cull_mode={self.triangle_cull_mode!r}, front_facing_winding={self.front_facing_winding!r}, "
            f"backend={self.backend!r})"
        )

    def has(self, name: str) -> bool:
        """Whether the intersector carries the tag called ``name``."""
        return any(t.name == name for t in self.tags)

    @property
    def max_levels(self) -> int:
        """Instance levels handled: the ``max_levels(n)`` tag, 1 with ``instancing`` alone, else 0."""
        if not self.has("instancing"):
            return 0
        values = [t.value for t in self.tags if t.name == "max_levels"]
        return int(values[0]) if values else 1

    @property
    def cull(self) -> int:
        """+1 culls clockwise triangles, -1 counterclockwise ones, 0 none."""
        if self.triangle_cull_mode == "none":
            return 0
        front = 1 if self.front_facing_winding == "clockwise" else -1
        return front if self.triangle_cull_mode == "front" else -front

    def intersect(
        self, rays: Ray, structure: PrimitiveAccelerationStructure | InstanceAccelerationStructure
    ) -> IntersectionResult:
        """Intersect a batch of rays (any batch shape) with a structure.

        Works under ``jax.jit`` and ``jax.vmap``. The ray batch is padded to a power of two so that batch
        sizes in one bucket share compiled code; padding never shows in the result. Batches larger than
        ``INTERSECT_CHUNK`` rays (2**24) are padded to a multiple of it and traced chunk after chunk. To trace
        rays sharded over several devices, wrap this call in ``jax.shard_map`` over the ray axis with the
        structure replicated (see docs/performance.md).

        Returns:
          An :class:`~jaxrt.IntersectionResult` with the batch shape of ``rays``. Distances, barycentrics
          and the hit point are differentiable with respect to vertices and rays (the hit primitive is held
          fixed; visibility changes are not differentiated).
        """
        if not isinstance(rays, Ray):
            raise TypeError(f"Intersector.intersect: rays must be a jaxrt.Ray, got {type(rays).__name__}")
        if not isinstance(structure, PrimitiveAccelerationStructure | InstanceAccelerationStructure):
            raise TypeError(
                f"Intersector.intersect: structure must be an acceleration structure, got {type(structure).__name__}"
            )
        _check_levels(self, structure)
        _check_motion(self, structure)
        _check_geometry(self, structure)
        _warn_if_closed_over(rays, structure)
        pipeline.resolve_backend(self)  # raises early, outside jit, when a forced backend is unavailable
        return pipeline.intersect(self, rays, structure)


class ClosedOverConstantsWarning(UserWarning):
    """Rays or a structure reached a traced function as compile-time constants, not as its arguments."""


#: Bytes of rays and structure arrays above which a jitted call that closes over them (rather than taking
#: them as arguments) is warned about.
CLOSED_OVER_BYTES = 64 << 20


def _warn_if_closed_over(rays: Ray, structure: Any) -> None:
    """Warn when ``intersect`` is traced (inside ``jax.jit``) with large concrete rays or structure arrays.

    XLA folds such arrays into the program as constants: a jitted function that closed over 4M rays compiled
    for 92 s on a 2-core CPU, against 4 s with the same rays passed as an argument.
    """
    leaves = jax.tree_util.tree_leaves((rays, structure))
    constant = sum(x.nbytes for x in leaves if not isinstance(x, jax.core.Tracer) and hasattr(x, "nbytes"))
    if constant < CLOSED_OVER_BYTES or not isinstance(jnp.zeros(()), jax.core.Tracer):
        return  # small, or not inside a trace (an eager call compiles no constant)
    warnings.warn(
        f"Intersector.intersect is being traced with {constant / 2**20:.0f} MiB of concrete rays or structure "
        "arrays: jax.jit folds them into the program as constants, which makes compiling slow and the program "
        "large. Pass them to the jitted function as arguments instead (docs/performance.md, 'First calls').",
        ClosedOverConstantsWarning,
        stacklevel=3,
    )


class _CountingIntersector(Intersector):
    """An intersector that counts every accepted hit (:func:`count_intersections`)."""

    counts_all = True


def _functions(value: Any) -> tuple[tuple[int, Any], ...] | None:
    """``intersection_functions`` as a sorted tuple of ``(geometry index, fn)`` pairs (hashable)."""
    if value is None:
        return None
    if not isinstance(value, dict):
        raise TypeError(
            f"Intersector: intersection_functions must be a dict {{geometry index: fn}}, got {type(value).__name__}"
        )
    for index, fn in value.items():
        if isinstance(index, bool) or not isinstance(index, int) or index < 0:
            raise ValueError(f"Intersector: intersection_functions keys must be geometry indices, got {index!r}")
        if not callable(fn):
            raise TypeError(f"Intersector: the intersection function of geometry {index} is not callable: {fn!r}")
    return tuple(sorted(value.items(), key=lambda item: item[0]))


def count_intersections(
    rays: Ray, structure: PrimitiveAccelerationStructure | InstanceAccelerationStructure, intersector: Any = None
) -> jax.Array:
    """The number of accepted hits along each ray (no culling: every primitive the ray crosses in its interval).

    Useful for inside/outside parity tests and depth complexity. ``intersector`` supplies cull mode,
    intersection functions and the filter (default: ``rt.Intersector()``). A ray through an edge or vertex
    shared by several triangles of a mesh counts each triangle the watertight test accepts there.

    Returns:
      int32 counts with the batch shape of ``rays``.

    Examples:
      >>> import jaxrt as rt
      >>> quad = rt.TriangleGeometry([[0., 0, 0], [1, 0, 0], [0, 1, 0], [1., 0, 1], [1, 1, 1], [0, 1, 1]])
      >>> s = rt.build_primitive_structure(quad)
      >>> int(rt.count_intersections(rt.Ray([.2, .2, -1], [0., 0, 1]), s))
      1
    """
    base = Intersector() if intersector is None else intersector
    if not isinstance(base, Intersector):
        raise TypeError(f"count_intersections: intersector must be an rt.Intersector, got {type(base).__name__}")
    if base.max_hits is not None or base.accept_any_intersection:
        raise ValueError("count_intersections: the intersector must not set max_hits or accept_any_intersection")
    counting = _CountingIntersector(
        *(t for t in base.tags if t.name in ("instancing", "max_levels", "primitive_motion", "instance_motion")),
        accept_any_intersection=False,
        triangle_cull_mode=base.triangle_cull_mode,
        front_facing_winding=base.front_facing_winding,
        backend=base.backend,
        geometry_types=base.geometry_types,
        curve_basis=base.curve_basis,
        curve_type=base.curve_type,
        curve_control_point_count=base.curve_control_point_count,
        intersection_functions=dict(base.intersection_functions or {}) or None,
        filter=base.filter,
        curve_options=base.curve_options,
    )
    return counting.intersect(rays, structure).hit_count


def _geometry_types(value: Any) -> tuple[str, ...] | None:
    """``geometry_types`` as a sorted tuple of kind names."""
    if value is None:
        return None
    items = [value] if isinstance(value, str | IntersectionType) else list(value)
    kinds = set()
    for item in items:
        if isinstance(item, IntersectionType) and item in _GEOMETRY_TYPES:
            kinds.add(_GEOMETRY_TYPES[item])
        elif isinstance(item, str) and item in _GEOMETRY_TYPES.values():
            kinds.add(item)
        else:
            names = sorted(_GEOMETRY_TYPES.values())
            raise ValueError(f"Intersector: geometry_types must name kinds from {names}, got {item!r}")
    return tuple(sorted(kinds))


def _check_tags(tags: tuple) -> None:
    """Tags that only make sense with ``instancing`` raise without it."""
    names = {t.name for t in tags}
    levels = [t for t in tags if t.name == "max_levels"]
    if len(levels) > 1:
        raise ValueError(f"Intersector: give tags.max_levels once, got {[t.value for t in levels]}")
    if "instancing" not in names:
        for name in ("max_levels", "world_space_data", "user_instance_id"):
            if name in names:
                raise ValueError(f"Intersector: tags.{name} needs tags.instancing")


def _check_levels(intersector: Intersector, structure: Any) -> None:
    """Raise when ``structure`` nests instances deeper than the intersector handles, naming both depths."""
    depth = structure.levels
    handled = intersector.max_levels
    if depth <= handled:
        return
    if handled == 0:
        raise ValueError(
            f"Intersector.intersect: the structure has {depth} instance level(s) but the intersector has no "
            f"tags.instancing and handles 0; add tags.instancing and tags.max_levels({depth})"
        )
    raise ValueError(
        f"Intersector.intersect: the structure is nested {depth} instance levels deep, deeper than the "
        f"intersector's tags.max_levels({handled}); use tags.max_levels({depth})"
    )


def _check_motion(intersector: Intersector, structure: Any) -> None:
    """A structure with keyframe motion needs the motion tag of its kind (Metal's intersector tags)."""
    if any(s.motion is not None for s in primitive_structures(structure)) and not intersector.has("primitive_motion"):
        raise ValueError(
            "Intersector.intersect: the structure has primitive keyframe motion (a structure built with motion=); "
            "add tags.primitive_motion to the Intersector"
        )
    if getattr(structure, "has_instance_motion", False) and not intersector.has("instance_motion"):
        raise ValueError(
            "Intersector.intersect: the structure has instance keyframe motion ((N, K, 3, 4) transforms); add "
            "tags.instance_motion to the Intersector"
        )


def _check_geometry(intersector: Intersector, structure: Any) -> None:
    """The structure's kinds, curves and user functions against the intersector's declarations."""
    prims = primitive_structures(structure)
    if intersector.backend in ("gpu", "cpu"):
        infos = tuple(g for s in prims for g in s.geometry_info)
        motion = bool(getattr(structure, "has_instance_motion", False))
        levels = 0 if len(prims) == 1 and prims[0] is structure else 1
        reason = pipeline.kernel_declines(intersector, infos, intersector.backend, motion, levels)
        if reason:
            raise ValueError(f"Intersector: backend={intersector.backend!r} cannot run: {reason}")
    _check_user_functions(intersector, prims)
    _check_opacity_options(intersector, structure)
    if intersector.has("primitive_data") and all(s.leaf_primitive_data is None for s in prims):
        raise ValueError(
            "Intersector.intersect: tags.primitive_data needs a structure built from geometries with primitive_data"
        )
    for s in prims:
        kinds = {g.kind for g in s.geometry_info}
        if intersector.geometry_types is not None and not kinds <= set(intersector.geometry_types):
            raise ValueError(
                f"Intersector.intersect: the structure holds geometry kinds {sorted(kinds)}, but the intersector "
                f"declares geometry_types={list(intersector.geometry_types)}"
            )
        for index, info in enumerate(s.geometry_info):
            if info.curve is None:
                continue
            declared = dict(
                curve_basis=(intersector.curve_basis, info.curve.basis),
                curve_type=(intersector.curve_type, info.curve.curve_type),
                curve_control_point_count=(intersector.curve_control_point_count, info.curve.control_point_count),
            )
            for name, (want, have) in declared.items():
                if want is not None and want != have:
                    raise ValueError(
                        f"Intersector.intersect: geometry {index} has {name}={getattr(have, 'value', have)!r}, but "
                        f"the intersector declares {name}={getattr(want, 'value', want)!r}"
                    )


def _check_opacity_options(intersector: Intersector, structure: Any) -> None:
    """The ``OPAQUE``/``NON_OPAQUE`` instance options would change which triangles the filter sees, which the
    traversal does not model: refuse them (where the options are concrete) rather than ignore them."""
    if intersector.filter is None or not isinstance(structure, InstanceAccelerationStructure):
        return

    override = int(InstanceOptions.OPAQUE | InstanceOptions.NON_OPAQUE)
    for table in structure.instance_tables:
        if isinstance(table.options, jax.core.Tracer):
            continue
        if (np.asarray(table.options) & override).any():
            raise NotImplementedError(
                "Intersector.intersect: instances with the OPAQUE or NON_OPAQUE option and an intersector filter "
                "are not supported; set the geometries' opaque flag instead"
            )


def _abstract_call(fn: Any, dtype, candidate: Any) -> Any:
    """The output shapes of ``fn(ray, candidate)`` for one abstract ray (traced, not run)."""
    scalar = jax.ShapeDtypeStruct((), dtype)
    vector = jax.ShapeDtypeStruct((3,), dtype)
    return jax.eval_shape(lambda o, d, a, b, c: fn(Ray(o, d, a, b), c), vector, vector, scalar, scalar, candidate)


def _is_scalar(x: Any) -> bool:
    return hasattr(x, "shape") and tuple(x.shape) == ()


def _check_user_functions(intersector: Intersector, prims: tuple[PrimitiveAccelerationStructure, ...]) -> None:
    """Host-side checks of intersection functions and the filter (named errors).

    Every box geometry needs a function; a function must name a box geometry (by its index within its own
    structure) of some structure of the scene, and return a pair ``(accept, distance)`` of scalars; the filter
    returns one scalar (checked by tracing them abstractly).
    """
    functions = dict(intersector.intersection_functions or ())
    boxes = sorted({i for s in prims for i, g in enumerate(s.geometry_info) if BOUNDING_BOX.holds(g)})
    for index in boxes:
        if index not in functions:
            raise ValueError(
                f"Intersector.intersect: geometry {index} is a BoundingBoxGeometry but the intersector has no "
                f"intersection function for it (pass intersection_functions={{{index}: fn}})"
            )
    for index in functions:
        if index not in boxes:
            kinds = sorted({s.geometry_info[index].kind for s in prims if index < len(s.geometry_info)})
            kind = "absent" if not kinds else f"a {' or '.join(kinds)} geometry"
            raise ValueError(
                f"Intersector.intersect: intersection_functions names geometry {index}, which is {kind}; "
                "intersection functions apply to BoundingBoxGeometry only"
            )
    dtype = prims[0].leaf_triangle.dtype
    with_data = [s.leaf_primitive_data for s in prims if s.leaf_primitive_data is not None]
    data = (
        jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(a.shape[1:], a.dtype), with_data[0])
        if with_data
        else None
    )
    int_scalar = jax.ShapeDtypeStruct((), jnp.int32)
    vector = jax.ShapeDtypeStruct((3,), dtype)
    for index in boxes:
        candidate = BoundingBoxCandidate(int_scalar, int_scalar, vector, vector, data)
        out = _abstract_call(functions[index], dtype, candidate)
        if not (isinstance(out, tuple | list) and len(out) == 2 and all(_is_scalar(x) for x in out)):
            raise TypeError(
                f"Intersector: the intersection function of geometry {index} must return a pair (accept, "
                f"distance) of scalars for one ray and one candidate, got {out!r}"
            )
    non_opaque = any(TRIANGLE.holds(g) and not g.opaque for s in prims for g in s.geometry_info)
    if intersector.filter is not None and non_opaque:
        scalar = jax.ShapeDtypeStruct((), dtype)
        candidate = TriangleCandidate(
            int_scalar, int_scalar, scalar, jax.ShapeDtypeStruct((2,), dtype), jax.ShapeDtypeStruct((), bool), data
        )
        out = jax.eval_shape(intersector.filter, candidate)
        if not _is_scalar(out):
            raise TypeError(f"Intersector: the filter must return one scalar accept flag per candidate, got {out!r}")
