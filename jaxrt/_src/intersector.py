"""The intersector: static tags and options, the traversal it compiles, and result assembly."""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
from jax import lax

from jaxrt import tags as tag_module
from jaxrt._src import curves as curve_support
from jaxrt._src import custom_leaves as custom
from jaxrt._src import intersect_instances as instancing
from jaxrt._src.instances import InstanceAccelerationStructure
from jaxrt._src.numerics import full_precision
from jaxrt._src.primitive_data import data_at
from jaxrt._src.primitives import triangle
from jaxrt._src.ray import Ray
from jaxrt._src.result import IntersectionResult, IntersectionType
from jaxrt._src.structures import PrimitiveAccelerationStructure
from jaxrt._src.traversal.stack import traverse, traverse_refill

__all__ = ["Intersector", "count_intersections"]

_SUPPORTED_TAGS = frozenset(
    [
        "triangle_data",
        "curve_data",
        "stats",
        "instancing",
        "max_levels",
        "world_space_data",
        "user_instance_id",
        "primitive_data",
    ]
)
#: Geometry kinds ``geometry_types`` may name (strings or ``rt.IntersectionType`` members).
_GEOMETRY_TYPES = {
    IntersectionType.TRIANGLE: "triangle",
    IntersectionType.CURVE: "curve",
    IntersectionType.BOUNDING_BOX: "bounding_box",
}
_CULL_MODES = ("none", "front", "back")
_WINDINGS = ("clockwise", "counterclockwise")
_BACKENDS = ("auto", "portable", "gpu")
#: Rays per traversal batch. Batches run one after another; on the CPU a batch that stays in cache is faster.
CPU_CHUNK = 1 << 16
GPU_CHUNK = 1 << 22
#: "refill" (a fixed window of lanes refilled from the ray queue) or "vmap" (a vmapped while_loop per ray);
#: both run the same per-ray step and give identical results.
PORTABLE_DRIVER = "refill"
#: Rays in flight in the refill driver (chosen by measurement on a 2-core CPU: 512, 2048, 8192 lanes).
REFILL_LANES = 2048
#: On a GPU a step over few lanes is all launch overhead: keep many rays in flight.
GPU_REFILL_LANES = 1 << 18
#: Rays per compiled intersection call. Larger batches are traced in sequential chunks of this many rays
#: (``lax.map``), so that the temporaries of packing, traversal and result assembly stay per chunk (by a count
#: of the arrays, at most about 200 bytes per ray: 3.4 GB at 2**24); the rays, one padded copy of them and the
#: result are per batch. Measured on an H200: 100M rays in one call peaked at 14.3 GB (docs/performance.md).
INTERSECT_CHUNK = 1 << 24


class _TriangleLeaves:
    """Watertight triangle tests of BVH leaves (a :class:`~jaxrt._src.traversal.stack.LeafTester`)."""

    def __init__(self, leaf_triangle: jax.Array, cull: int):
        self.leaf_triangle = leaf_triangle
        self.cull = cull

    def prepare(self, origin, direction):
        return triangle.shear_ray(origin, direction)

    def __call__(self, context, leaves, t_min, t_max):
        hit = triangle.watertight(context, t_min, t_max, self.leaf_triangle[jnp.maximum(leaves, 0)], self.cull)
        return hit.hit & (leaves >= 0), hit.distance


def _ray_bucket(n: int) -> int:
    return 1 << max(0, (max(n, 1) - 1).bit_length())


class Intersector:
    """Intersects rays with acceleration structures (Metal's ``intersector``).

    Args:
      *tags: tags from ``rt.tags``; each adds result fields and only then compiles their work.
      accept_any_intersection: stop at the first accepted hit (occlusion/shadow rays) instead of the nearest.
      triangle_cull_mode: ``"none"``, ``"front"`` or ``"back"``: skip triangles facing that way.
      front_facing_winding: ``"clockwise"`` (Metal's default) or ``"counterclockwise"``: the winding, seen
        from the ray origin, of a front-facing triangle. With right-handed coordinates a triangle is clockwise
        when ``dot(cross(v1 - v0, v2 - v0), ray.direction) > 0``.
      backend: ``"auto"``, ``"portable"`` (the vmapped stack traversal) or ``"gpu"``.
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
        instancing.check_tags(tags)
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
        from jaxrt._src.primitives.curve import CurveOptions

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
        self._count_all = False  # set by count_intersections
        self.tags = tuple(sorted(set(tags)))
        self.accept_any_intersection = accept_any_intersection
        self.triangle_cull_mode = triangle_cull_mode
        self.front_facing_winding = front_facing_winding
        self.backend = backend

    def _key(self):
        return (
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
            self._count_all,
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
    def _cull(self) -> int:
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
        instancing.check_levels(self, structure)  # instance nesting deeper than the tags handle
        _check_instanced_options(self, structure)
        _check_geometry(self, structure)
        _resolve_backend(self)  # raises early, outside jit, when the GPU backend is forced but unavailable
        shape = rays.shape
        flat = rays.reshape(-1)
        n = flat.origin.shape[0]
        chunk = INTERSECT_CHUNK
        padded = _ray_bucket(n) if n <= chunk else -(-n // chunk) * chunk
        if padded != n:
            flat = jax.tree_util.tree_map(
                lambda a: jnp.concatenate([a, jnp.zeros((padded - n, *a.shape[1:]), a.dtype)]), flat
            )
        if padded <= chunk:
            result = _intersect_jit(self, flat, structure)
        else:
            result = _intersect_chunks(self, flat, structure, chunk)
        return jax.tree_util.tree_map(lambda a: a[:n].reshape(*shape, *a.shape[1:]), result)


@functools.partial(jax.jit, static_argnums=(0, 3))
def _intersect_chunks(intersector: Intersector, rays: Ray, structure: Any, chunk: int) -> IntersectionResult:
    """``_intersect_jit`` over sequential chunks of ``chunk`` rays (the ray count is a multiple of it)."""
    split = jax.tree_util.tree_map(lambda a: a.reshape(-1, chunk, *a.shape[1:]), rays)
    out = lax.map(lambda r: _intersect_jit(intersector, r, structure), split)
    return jax.tree_util.tree_map(lambda a: a.reshape(-1, *a.shape[2:]), out)


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


def count_intersections(rays: Ray, structure: PrimitiveAccelerationStructure, intersector: Intersector | None = None):
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
    import copy

    base = Intersector() if intersector is None else intersector
    if not isinstance(base, Intersector):
        raise TypeError(f"count_intersections: intersector must be an rt.Intersector, got {type(base).__name__}")
    if base.max_hits is not None or base.accept_any_intersection:
        raise ValueError("count_intersections: the intersector must not set max_hits or accept_any_intersection")
    counting = copy.copy(base)
    counting.tags = ()
    counting._count_all = True
    return counting.intersect(rays, structure).hit_count


def _check_instanced_options(intersector: Intersector, structure: Any) -> None:
    """Options the instanced traversal does not provide yet: a ``NotImplementedError`` naming them."""
    if not isinstance(structure, InstanceAccelerationStructure):
        return
    options = dict(
        max_hits=intersector.max_hits is not None,
        count_intersections=intersector._count_all,
        filter=intersector.filter is not None,
        intersection_functions=intersector.intersection_functions is not None,
        primitive_data=intersector.has("primitive_data"),
    )
    used = [name for name, on in options.items() if on]
    if any(s.leaf_box is not None for s in structure.primitive_structures):
        used.append("bounding-box geometry")
    if used:
        raise NotImplementedError(f"Intersector.intersect: {', '.join(used)} below instances are not supported yet")


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


def _check_geometry(intersector: Intersector, structure: Any) -> None:
    """The structure's kinds and curves against the intersector's declarations (and what it can trace)."""
    if isinstance(structure, InstanceAccelerationStructure):
        for primitive_structure in structure.primitive_structures:
            _check_geometry(intersector, primitive_structure)
        return
    kinds = {g.kind for g in structure.geometry_info}
    if intersector.backend == "gpu" and _gpu_declines(intersector, structure):
        raise ValueError(f"Intersector: backend='gpu' cannot run: {_gpu_declines(intersector, structure)}")
    custom.check_user_functions(intersector, structure)
    if intersector.has("primitive_data") and structure.leaf_primitive_data is None:
        raise ValueError(
            "Intersector.intersect: tags.primitive_data needs a structure built from geometries with primitive_data"
        )
    if intersector.geometry_types is not None and not kinds <= set(intersector.geometry_types):
        raise ValueError(
            f"Intersector.intersect: the structure holds geometry kinds {sorted(kinds)}, but the intersector "
            f"declares geometry_types={list(intersector.geometry_types)}"
        )
    for index, info in enumerate(structure.geometry_info):
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


def _curve_config(intersector: Intersector, structure: PrimitiveAccelerationStructure):
    infos = tuple(g.curve for g in structure.geometry_info if g.curve is not None)
    return curve_support.curve_configuration(infos, intersector.curve_type, intersector.curve_options)


def _gpu_declines(intersector: Intersector, structure: PrimitiveAccelerationStructure) -> str | None:
    """Why the GPU kernel does not cover this structure with this intersector (``None`` when it does)."""
    if structure.leaf_curve is not None:
        return "curves are not covered by the GPU kernel"
    if structure.leaf_box is not None:
        return "bounding-box geometry (intersection functions) is not covered by the GPU kernel"
    if custom.filtered_geometries(intersector, structure):
        return "filters on non-opaque geometry are not covered by the GPU kernel"
    if intersector.max_hits is not None or intersector._count_all:
        return "multi-hit (max_hits) and counting are not covered by the GPU kernel"
    return None


def _resolve_backend(intersector: Intersector) -> str:
    """``"portable"`` or ``"gpu"``: which traversal runs for this intersector on the default JAX backend."""
    if intersector.backend == "portable":
        return "portable"
    from jaxrt._src.traversal import gpu

    reason = gpu.unavailable_reason(intersector)
    if reason is None:
        return "gpu"
    if intersector.backend == "gpu":
        raise ValueError(f"Intersector: backend='gpu' cannot run: {reason}")
    return "portable"


def _enabled(rays: Ray) -> jax.Array:
    finite = jnp.all(jnp.isfinite(rays.origin), axis=-1) & jnp.all(jnp.isfinite(rays.direction), axis=-1)
    nonzero = jnp.any(rays.direction != 0, axis=-1)
    interval = (rays.min_distance <= rays.max_distance) & ~jnp.isnan(rays.min_distance) & ~jnp.isnan(rays.max_distance)
    return finite & nonzero & interval & (rays.mask != 0)


def _chunked(fn, args, chunk: int):
    """``fn`` over the rays in sequential chunks of ``chunk`` (the ray count is a power of two)."""
    n = args[0].shape[0]
    if n <= chunk:
        return fn(*args)
    split = [a.reshape(n // chunk, chunk, *a.shape[1:]) for a in args]
    out = lax.map(lambda xs: fn(*xs), split)
    return jax.tree_util.tree_map(lambda a: a.reshape(n, *a.shape[2:]), out)


def _leaf_tester(intersector: Intersector, structure: PrimitiveAccelerationStructure, user_code: bool = True):
    """The leaf tests the structure's kinds need: triangles (filtered where non-opaque), curves, boxes.

    Without ``user_code`` neither the filter nor intersection functions are called: box leaves never hit and
    non-opaque triangles are tested as opaque ones (an intersection query decides them itself).
    """
    detached = lax.stop_gradient
    filtered = custom.filtered_geometries(intersector, structure) if user_code else ()
    if filtered:
        clockwise_front = intersector.front_facing_winding == "clockwise"
        leaves = custom.FilteredTriangleLeaves(
            structure, intersector._cull, clockwise_front, intersector.filter, filtered
        )
    else:
        leaves = _TriangleLeaves(detached(structure.leaf_triangle), intersector._cull)
    kinds = {g.kind for g in structure.geometry_info}
    if structure.leaf_curve is not None:  # curves: their own test, or both tests selected per leaf
        config = _curve_config(intersector, structure)
        curves = curve_support.CurveLeaves(detached(structure.leaf_curve), structure.leaf_curve_flags, **config)
        leaves = curve_support.MixedLeaves(leaves, curves) if "triangle" in kinds else curves
    if structure.leaf_box is not None and user_code:  # boxes: the user's functions, alone or per leaf
        boxes = custom.BoxLeaves(structure, intersector.intersection_functions)
        leaves = boxes if kinds == {"bounding_box"} else custom.KindLeaves(leaves, boxes, structure)
    return leaves


def _trace_portable(intersector, structure, origin, direction, t_min, t_max, enabled):
    """The portable stack traversal over chunks of rays, with the refill driver (see traversal/stack.py)."""
    detached = lax.stop_gradient
    leaves = _leaf_tester(intersector, structure)
    nodes = (detached(structure.node_lower), detached(structure.node_upper), structure.node_children)
    options = dict(
        any_hit=intersector.accept_any_intersection,
        stack_size=structure.max_depth,
        max_hits=0 if intersector._count_all else intersector.max_hits,
        count_all=intersector._count_all,
    )
    args = tuple(detached(a) for a in (origin, direction, t_min, t_max)) + (enabled,)
    if PORTABLE_DRIVER == "vmap":
        return _chunked(jax.vmap(functools.partial(traverse, *nodes, leaves, **options)), args, CPU_CHUNK)
    on_gpu = jax.default_backend() == "gpu"
    chunk, lanes = (GPU_CHUNK, GPU_REFILL_LANES) if on_gpu else (CPU_CHUNK, REFILL_LANES)
    return _chunked(functools.partial(traverse_refill, *nodes, leaves, **options, lanes=lanes), args, chunk)


def _hit_fields(intersector, structure, origin, direction, t_min, t_max, leaf, distance) -> dict[str, Any]:
    """The hit fields of rays whose traversal found ``leaf`` (``-1``: a miss) at ``distance``.

    The chosen primitive is intersected again: exact values from the test the traversal ran, gradients from
    a smooth formula (triangles), the curve's smooth hit, or the user's function called with gradients.
    """
    detached = lax.stop_gradient
    unit_z = jnp.array([0.0, 0.0, 1.0], direction.dtype)
    found = leaf >= 0
    leaf = jnp.maximum(leaf, 0)
    hit = found  # triangle hits, once the other kinds are taken out
    infos = structure.geometry_info
    if structure.leaf_curve is not None:  # curve hits: re-tested differentiably; triangles take the rest
        is_curve, curve_t, curve_u = curve_support.curve_hit_fields(
            structure, leaf, hit, origin, direction, t_min, t_max, distance, _curve_config(intersector, structure)
        )
        hit = hit & ~is_curve
    if structure.leaf_box is not None:
        is_box_table = custom.geometry_table(len(infos), custom.box_geometries(structure))
        is_box = found & custom.leaf_flag(is_box_table, structure.leaf_geometry, leaf)
        box_t = _box_distance(intersector, structure, leaf, is_box, origin, direction, t_min, t_max, distance)
        hit = hit & ~is_box
    kind = jnp.where(hit, int(IntersectionType.TRIANGLE), int(IntersectionType.NONE))
    fields: dict[str, Any] = {
        "type": None,
        "distance": None,
        "primitive_id": jnp.where(found, structure.leaf_primitive[leaf], -1),
        "geometry_id": jnp.where(found, structure.leaf_geometry[leaf], -1),
    }
    # Re-intersect the chosen triangle: exact values from the watertight test, gradients from a smooth one.
    vertices = structure.leaf_triangle[leaf]
    dummy = jnp.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]], vertices.dtype)
    vertices = jnp.where(hit[:, None, None], vertices, dummy)
    # Misses also get a dummy ray: with their own (finite but possibly huge) origin the smooth formula can
    # overflow, and its zero cotangent times inf would be a NaN gradient.
    smooth_origin = jnp.where(hit[:, None], origin, 0.0)
    smooth_direction = jnp.where(hit[:, None], direction, unit_z)
    smooth_t, smooth_u, smooth_v = jax.vmap(triangle.smooth_hit)(smooth_origin, smooth_direction, vertices)

    def attach(exact, smooth):
        return jnp.where(hit, detached(exact) + (smooth - detached(smooth)), 0.0)

    fields["distance"] = jnp.where(hit, attach(distance, smooth_t), jnp.inf)
    if intersector.has("triangle_data"):
        sheared = jax.vmap(triangle.shear_ray)(detached(origin), detached(direction))
        u, v, clockwise = jax.vmap(triangle.barycentrics)(sheared, detached(vertices))
        fields["triangle_barycentric_coord"] = jnp.stack([attach(u, smooth_u), attach(v, smooth_v)], axis=-1)
        front = clockwise if intersector.front_facing_winding == "clockwise" else ~clockwise
        fields["triangle_front_facing"] = hit & front
    if structure.leaf_curve is not None:
        kind = jnp.where(is_curve, int(IntersectionType.CURVE), kind)
        fields["distance"] = jnp.where(is_curve, curve_t, fields["distance"])
    if structure.leaf_box is not None:
        kind = jnp.where(is_box, int(IntersectionType.BOUNDING_BOX), kind)
        fields["distance"] = jnp.where(is_box, box_t, fields["distance"])
    fields["type"] = kind.astype(jnp.int32)
    if intersector.has("curve_data"):
        curves = structure.leaf_curve is not None
        fields["curve_parameter"] = jnp.where(is_curve, curve_u, 0.0) if curves else jnp.zeros_like(distance)
    if intersector.has("primitive_data"):
        fields["primitive_data"] = data_at(structure.leaf_primitive_data, leaf, found)
    if intersector.has("instancing"):
        fields.update(instancing.primitive_instance_fields(intersector, found, vertices.dtype))
    return fields


def _box_distance(intersector, structure, leaf, is_box, origin, direction, t_min, t_max, distance):
    """Box hit distances: the traversal's value, with the gradient of the function called again on the box.

    The call again sees the ray's own interval (the nearest accepted root of this box is the one found): with
    the found distance as ``max_distance``, a recomputation an ulp larger (other FMA contractions in another
    program) would be rejected and lose the gradient.
    """
    detached = lax.stop_gradient
    arrays = (structure.leaf_box, structure.leaf_geometry, structure.leaf_primitive, structure.leaf_primitive_data)
    # Lanes without a box hit call the function with a harmless ray (no NaN in their zero gradients).
    ray_origin = jnp.where(is_box[:, None], origin, 0.0)
    ray_direction = jnp.where(is_box[:, None], direction, jnp.array([0.0, 0.0, 1.0], direction.dtype))
    t_max = jnp.where(is_box, detached(t_max), 1.0)

    def one(o, d, lo, hi, k):
        ray = custom.function_ray(o, d, lo, hi)
        return custom.call_function(intersector.intersection_functions, ray, custom.box_candidate(arrays, k))

    accept, smooth = jax.vmap(one)(ray_origin, ray_direction, jnp.where(is_box, t_min, 0.0), t_max, leaf)
    attached = detached(distance) + jnp.where(accept, smooth - detached(smooth), 0.0)
    return jnp.where(is_box, attached, jnp.inf)


def _trace(intersector, structure, origin, direction, t_min, t_max, enabled):
    """Run the traversal the intersector and structure call for (the GPU kernel where it covers them)."""
    detached = lax.stop_gradient
    if _resolve_backend(intersector) == "gpu" and _gpu_declines(intersector, structure) is None:
        from jaxrt._src.traversal import gpu

        return gpu.trace(
            structure,
            *(detached(a) for a in (origin, direction, t_min, t_max)),
            enabled,
            any_hit=intersector.accept_any_intersection,
            cull=intersector._cull,
        )
    return _trace_portable(intersector, structure, origin, direction, t_min, t_max, enabled)


@functools.partial(jax.jit, static_argnums=0)
@full_precision
def _intersect_jit(
    intersector: Intersector, rays: Ray, structure: PrimitiveAccelerationStructure | InstanceAccelerationStructure
) -> IntersectionResult:
    if isinstance(structure, InstanceAccelerationStructure):
        return instancing.intersect_instances(intersector, rays, structure)
    enabled = _enabled(rays)
    unit_z = jnp.array([0.0, 0.0, 1.0], rays.direction.dtype)
    origin = jnp.where(enabled[:, None], rays.origin, 0.0)
    direction = jnp.where(enabled[:, None], rays.direction, unit_z)
    t_min = jnp.where(enabled, rays.min_distance, 0.0)
    t_max = jnp.where(enabled, rays.max_distance, 0.0)
    found = _trace(intersector, structure, origin, direction, t_min, t_max, enabled)
    if intersector._count_all:
        return IntersectionResult({"hit_count": found.hits.total})
    if intersector.max_hits is None:
        fields = _hit_fields(intersector, structure, origin, direction, t_min, t_max, found.leaf, found.distance)
    else:  # the same fields for each of the K hits, on an axis after the ray axis
        k = intersector.max_hits
        repeat = lambda a: jnp.repeat(a, k, axis=0)  # noqa: E731
        flat = _hit_fields(
            intersector,
            structure,
            *(repeat(a) for a in (origin, direction, t_min, t_max)),
            found.hits.leaf.reshape(-1),
            found.hits.distance.reshape(-1),
        )
        fields = jax.tree_util.tree_map(lambda a: a.reshape(-1, k, *a.shape[1:]), flat)
        fields["hit_count"] = jnp.minimum(found.hits.total, k)
        fields["hit_overflow"] = found.hits.total > k
    if intersector.has("stats"):
        fields["nodes_visited"] = found.nodes_visited
        fields["primitives_tested"] = found.primitives_tested
        fields["stack_overflow"] = found.stack_overflow
    return IntersectionResult(fields)
