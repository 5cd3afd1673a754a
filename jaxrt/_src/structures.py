"""Acceleration structure pytrees and the functions that build and refit them.

Node layout of :class:`PrimitiveAccelerationStructure` (a binary LBVH, Karras 2012, with both child boxes
stored in the parent as in Aila & Laine, "Understanding the Efficiency of Ray Traversal on GPUs", HPG 2009,
so one node fetch gives the two boxes a traversal step tests). ``C`` is the capacity, a power of two:

==================  ==============  ================================================================
array               shape, dtype    contents
==================  ==============  ================================================================
``node_lower``      (C-1, 2, 3) f   lower corner of child 0 and child 1 of each internal node
``node_upper``      (C-1, 2, 3) f   upper corner of each child; an empty child is (+inf, -inf)
``node_children``   (C-1, 2) i32    child index: internal node ``c >= 0``, or leaf ``k`` as ``-1 - k``
``node_range``      (C-1, 2) i32    first and last leaf (sorted position) under the node (for refit)
``leaf_geometry``   (C,) i32        geometry index of the primitive in leaf ``k``; -1 for padding
``leaf_primitive``  (C,) i32        primitive index within its geometry; -1 for padding
``leaf_triangle``   (C, 3, 3) f     the three vertices of leaf ``k``'s triangle, in leaf order (padding 0)
``geometry_primitive_count`` (G,) i32  primitives of each geometry (an array, so that structures of one
                                    capacity and kinds share the compiled traversal whatever their counts)
``leaf_curve``      (C, 6, 4) f     with curves only (else ``None``): leaf ``k``'s curve segment packed by
                                    :func:`jaxrt._src.curves.pack_segments` (cubic Bezier points relative to
                                    the segment's first control point, that point, and the predecessor's
                                    joint derivative); 0 for triangles and padding
``leaf_curve_flags`` (C,) i32       with curves only: links, end caps, type, and a bit marking curve leaves
``leaf_box``        (C, 2, 3) f     with bounding-box geometry only (else ``None``): lower and upper corner of
                                    leaf ``k``'s box primitive; empty for other leaves and padding
``leaf_primitive_data`` pytree      with primitive data only (else ``None``): every geometry's
                                    ``primitive_data`` in leaf order, leaves of shape ``(C, ...)``; rows of
                                    geometries without data and of padding are zeros
``motion_triangle`` (K, C, 3, 3) f  with keyframe motion only (else ``None``, like the two below):
                                    ``leaf_triangle`` at each of the ``K`` keyframes (``leaf_triangle`` is
                                    keyframe 0); static geometries repeat their rows
``motion_curve``    (K, C, 6, 4) f  with motion and curves: ``leaf_curve`` per keyframe (the packing is
                                    linear in the control points, so blending packed keyframes packs the
                                    blended curve)
``motion_box``      (K, C, 2, 3) f  with motion and bounding boxes: ``leaf_box`` per keyframe
``motion_node_lower`` (K, C-1, 2, 3) with motion: the child boxes of every node at each keyframe (and
``motion_node_upper``               its upper corners); blended at a ray's time they bound the subtree then
==================  ==============  ================================================================

``kernel_layout`` (a :class:`~jaxrt._src.traversal.packed.KernelLayout`, or ``None``) holds the rows the GPU
kernel reads, ``(C-1, 16)`` node rows and ``(C, 12)`` triangle rows in float32 (112 bytes per leaf slot, about
as much again as the arrays above for a triangle structure): packed once where the structure is made, so that
a trace does not repack them. Builds add it where the GPU kernel can run (default backend a GPU, Triton and
jax-triton installed, float32 triangles without motion) or where ``kernel_layout=True`` asks; refit, compaction
and loading keep it consistent with the arrays. Without it (CPU installs) the kernel packs the rows per call.
This module imports nothing of the kernel: the field is an opaque pytree here, and the GPU side
(:mod:`jaxrt._src.prepacked`) passes its packer to :func:`build_structure` and :func:`refit_primitives`.

With keyframe motion (static ``motion``, a :class:`~jaxrt.MotionSpec`) ``node_lower``/``node_upper`` bound
each primitive over every keyframe (the union of its keyframe boxes; instance boxes and the SAH cost read
them), ``motion_node_lower``/``motion_node_upper`` hold the node boxes of each keyframe, which the traversal
blends at each ray's time ("linear bounds", as Embree's motion-blur BVHs interpolate node bounds), and the
leaf tests blend the keyframe rows (:mod:`jaxrt._src.motion`).

The kind of a leaf (triangle, curve, bounding box) and whether it is opaque follow from its geometry index
and the static :class:`GeometryInfo` of that geometry. Internal node 0 is the root. Every leaf holds one
primitive. Leaves past the primitive count are padding: their boxes are empty, so no ray enters them and they
never show in results. The LBVH (``quality="fast"``) links only the real leaves (at least two), in internal
nodes ``0 .. n - 2``; the rows past them are unused (empty boxes, children pointing at a padding leaf). The
clustering tree (``"high"``) and the SAH tree (``"sah"``) hang the padding leaves under the root in a subtree of
their own.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxrt._src.bvh.boxes import child_boxes, range_boxes
from jaxrt._src.bvh.morton import morton_codes
from jaxrt._src.bvh.ploc import restructure
from jaxrt._src.bvh.radix_tree import build_radix_tree, tree_depth_bound
from jaxrt._src.checks import check_geometries
from jaxrt._src.curves import CurveInfo, curve_leaves
from jaxrt._src.geometry import TriangleGeometry
from jaxrt._src.kinds import registry
from jaxrt._src.kinds.kind import Kind
from jaxrt._src.kinds.registry import BOUNDING_BOX, CURVE, TRIANGLE
from jaxrt._src.motion import MotionSpec, motion_bounds
from jaxrt._src.numerics import full_precision
from jaxrt._src.primitive_data import gather_leaf_data, primitive_data_layout
from jaxrt._src.primitives import triangle

__all__ = [
    "PrimitiveAccelerationStructure",
    "build_structure",
    "refit_primitives",
    "capacity_bucket",
    "geometry_info",
    "geometries_dtype",
    "as_geometry_tuple",
    "QUALITIES",
]


@dataclasses.dataclass(frozen=True)
class GeometryInfo:
    """Static description of one geometry in a structure."""

    kind: str
    opaque: bool
    curve: CurveInfo | None = None  # basis, control point count, type and end caps of a curve geometry
    motion: bool = False  # a keyframed (Motion*) geometry


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PrimitiveAccelerationStructure:
    """An LBVH over the primitives of one or more geometries (see the module docstring for the layout).

    Build it with :func:`build_primitive_structure`; it is an immutable pytree of padded arrays whose static
    part (capacity, geometry kinds and counts) decides the compiled traversal.
    """

    node_lower: jax.Array
    node_upper: jax.Array
    node_children: jax.Array
    node_range: jax.Array
    leaf_geometry: jax.Array
    leaf_primitive: jax.Array
    leaf_triangle: jax.Array
    geometry_primitive_count: jax.Array
    geometry_info: tuple[GeometryInfo, ...] = dataclasses.field(metadata=dict(static=True))
    leaf_curve: jax.Array | None = None
    leaf_curve_flags: jax.Array | None = None
    leaf_box: jax.Array | None = None
    leaf_primitive_data: Any = None
    motion_triangle: jax.Array | None = None
    motion_curve: jax.Array | None = None
    motion_box: jax.Array | None = None
    motion_node_lower: jax.Array | None = None
    motion_node_upper: jax.Array | None = None
    motion: MotionSpec | None = dataclasses.field(default=None, metadata=dict(static=True))
    kernel_layout: Any = None  # the GPU kernel's rows (a KernelLayout), or None

    @property
    def keyframe_count(self) -> int:
        """Keyframes of the structure's primitive motion (1 for a static structure)."""
        return 1 if self.motion_triangle is None else int(self.motion_triangle.shape[0])

    @property
    def capacity(self) -> int:
        """Number of leaf slots (a power of two, at least 2)."""
        return int(self.leaf_geometry.shape[-1])

    @property
    def primitive_count(self) -> int:
        """Number of real primitives over all geometries (on the host: not inside ``jax.jit``)."""
        return int(np.sum(np.asarray(self.geometry_primitive_count)))

    @property
    def levels(self) -> int:
        """Instance levels below this structure (a primitive structure has none)."""
        return 0

    @property
    def max_depth(self) -> int:
        """An upper bound on the depth of any leaf (:func:`~jaxrt._src.bvh.radix_tree.tree_depth_bound`)."""
        return tree_depth_bound(self.capacity)


def capacity_bucket(count: int, capacity: int | None = None) -> int:
    """The power-of-two capacity for ``count`` primitives (at least 2 and at least ``capacity``)."""
    if capacity is not None:
        if int(capacity) < count:
            raise ValueError(f"build_primitive_structure: capacity={capacity} is below the primitive count {count}")
        count = int(capacity)
    return max(2, 1 << (max(count, 1) - 1).bit_length())


def _is_geometry(g: Any) -> bool:
    """Whether ``g`` is a geometry: an object whose class names a kind of the registry (the geometry protocol of
    :class:`~jaxrt._src.kinds.kind.Kind`)."""
    name = getattr(type(g), "kind", None)
    return isinstance(name, str) and any(k.name == name for k in registry.KINDS)


def _moves(g: Any) -> bool:
    """Whether ``g`` is a keyframed geometry (``Motion*Geometry``)."""
    return bool(getattr(g, "motion", False))


def _class_names(motion: bool = False) -> str:
    """The geometry classes of every kind, for messages."""
    return ", ".join(("Motion" if motion else "") + k.geometry for k in registry.KINDS)


def geometry_info(g: Any) -> GeometryInfo:
    """The static :class:`GeometryInfo` of a geometry."""
    curve = g.info if CURVE.holds(g) else None
    return GeometryInfo(g.kind, g.opaque, curve, _moves(g))


def _keyframe_count(geometries: tuple, motion: Any, owner: str) -> int:
    """The common keyframe count of the motion geometries (1 without any), checked against ``motion``."""
    counts = {i: g.keyframe_count for i, g in enumerate(geometries) if _moves(g)}
    if motion is not None and not isinstance(motion, MotionSpec):
        raise TypeError(f"{owner}: motion must be an rt.MotionSpec or None, got {motion!r}")
    if not counts:
        if motion is not None:
            raise ValueError(
                f"{owner}: motion={motion} needs at least one Motion*Geometry ({_class_names(motion=True)}) among "
                "the geometries"
            )
        return 1
    if motion is None:
        first = next(iter(counts))
        raise ValueError(
            f"{owner}: geometries[{first}] is a {type(geometries[first]).__name__}; keyframe motion needs "
            "motion=rt.MotionSpec(start_time, end_time, ...)"
        )
    if len(set(counts.values())) > 1:
        raise ValueError(
            f"{owner}: the motion geometries have different keyframe counts {counts} (geometry index: count); "
            "every motion geometry of a structure needs the same count"
        )
    return next(iter(counts.values()))


def _keyframes(geometries: tuple, count: int) -> list[tuple]:
    """The static geometries of every keyframe (static geometries repeat)."""
    return [tuple(g.keyframe(k) if _moves(g) else g for g in geometries) for k in range(count)]


def as_geometry_tuple(geometries: Any) -> tuple[TriangleGeometry, ...]:
    """``geometries`` (one or a sequence) as a tuple, checked (named ``TypeError`` and ``ValueError``)."""
    if _is_geometry(geometries):
        geometries = (geometries,)
    if not isinstance(geometries, Sequence) or isinstance(geometries, str):
        raise TypeError(
            f"build_primitive_structure: geometries must be a geometry or a sequence of them, got {type(geometries).__name__}"
        )
    geometries = tuple(geometries)
    if not geometries:
        raise ValueError("build_primitive_structure: geometries is empty; a structure needs at least one geometry")
    for index, geometry in enumerate(geometries):
        if not _is_geometry(geometry):
            raise TypeError(
                f"build_primitive_structure: geometries[{index}] is a {type(geometry).__name__}; "
                f"supported geometry types: {_class_names()} and their Motion* variants"
            )
    primitive_data_layout(geometries)  # one layout for all primitive data (a named error otherwise)
    return geometries


def _leaf_primitives(geometries: tuple[TriangleGeometry, ...], capacity: int):
    """Concatenated triangles, ids and boxes of all geometries, padded to ``capacity`` (unsorted)."""
    curves = curve_leaves(geometries, capacity)  # None without curve geometries
    dtype = geometries_dtype(geometries)
    triangles = jnp.concatenate([_shared_rows(g, dtype) for g in geometries], axis=0)
    count = triangles.shape[0]
    geometry_id = jnp.concatenate([jnp.full((g.primitive_count,), i, jnp.int32) for i, g in enumerate(geometries)])
    primitive_id = jnp.concatenate([jnp.arange(g.primitive_count, dtype=jnp.int32) for g in geometries])
    pad = capacity - count
    triangles = jnp.pad(triangles, ((0, pad), (0, 0), (0, 0)))
    geometry_id = jnp.pad(geometry_id, (0, pad), constant_values=-1)
    primitive_id = jnp.pad(primitive_id, (0, pad), constant_values=-1)
    valid = geometry_id >= 0
    # A triangle whose edge vectors have an exactly zero cross product has no area: it gets an empty box, so
    # no ray tests it. (Its sheared projection could round it into a sub-ulp sliver that a ray would hit.)
    enterable = valid & triangle.has_area(triangles)
    triangle_lower, triangle_upper = TRIANGLE.bounds(triangles)
    lower = jnp.where(enterable[:, None], triangle_lower, jnp.inf)
    upper = jnp.where(enterable[:, None], triangle_upper, -jnp.inf)
    rows = _row_slots(geometries, capacity)
    for kind, slots in rows:  # kinds in the shared row (spheres): their own bounds (empty for a bad leaf)
        kind_lower, kind_upper = kind.bounds(triangles)
        lower = jnp.where(slots[:, None], kind_lower, lower)
        upper = jnp.where(slots[:, None], kind_upper, upper)
    if curves is not None:  # curve segments: their Bezier hull grown by the radius
        lower = jnp.where(curves.is_curve[:, None], curves.lower, lower)
        upper = jnp.where(curves.is_curve[:, None], curves.upper, upper)
    boxes = _leaf_boxes(geometries, capacity, dtype)
    if boxes is not None:  # box primitives: their own box
        is_box = boxes[:, 0, 0] <= boxes[:, 1, 0]
        box_lower, box_upper = BOUNDING_BOX.bounds(boxes)
        lower = jnp.where(is_box[:, None], box_lower, lower)
        upper = jnp.where(is_box[:, None], box_upper, upper)
    return triangles, geometry_id, primitive_id, lower, upper, valid, curves, boxes, rows


def _in_shared_row(kind: Kind) -> bool:
    """Whether ``kind`` keeps its leaves in the shared ``leaf_triangle`` row without owning it (spheres): its
    geometries provide ``leaf_rows()``."""
    return kind is not TRIANGLE and kind.leaf_arrays[0].name == "leaf_triangle"


def _shared_rows(g: Any, dtype) -> jax.Array:
    """The ``(N, 3, 3)`` rows of ``leaf_triangle`` of one geometry: triangles' vertices, the ``leaf_rows()`` of a
    kind that keeps its leaves there (:func:`_in_shared_row`), zeros for the other kinds."""
    if TRIANGLE.holds(g):
        return g.triangle_vertices()
    if _in_shared_row(registry.kind(g.kind)):
        return g.leaf_rows().astype(dtype)
    return jnp.zeros((g.primitive_count, 3, 3), dtype)


def _row_slots(geometries, capacity: int) -> tuple[tuple[Kind, jax.Array], ...]:
    """For each kind present that keeps its leaves in the shared row (:func:`_in_shared_row`), ``(kind, (C,)
    whether each unsorted slot holds one of its leaves)``."""
    out = []
    for kind in registry.present(geometries):
        if not _in_shared_row(kind):
            continue
        flags = np.zeros(capacity, bool)
        start = 0
        for g in geometries:
            flags[start : start + g.primitive_count] = kind.holds(g)
            start += g.primitive_count
        out.append((kind, jnp.asarray(flags)))
    return tuple(out)


def geometries_dtype(geometries) -> jnp.dtype:
    """The float type of a sequence of geometries (the first one's)."""
    first = geometries[0]
    return getattr(first, registry.kind(first.kind).float_array).dtype


def _leaf_boxes(geometries, capacity: int, dtype) -> jax.Array | None:
    """``(C, 2, 3)`` corners of the box primitives in unsorted slot order (empty for other rows), or ``None``."""
    if not any(BOUNDING_BOX.holds(g) for g in geometries):
        return None
    empty = lambda n: jnp.stack([jnp.full((n, 3), jnp.inf, dtype), jnp.full((n, 3), -jnp.inf, dtype)], 1)  # noqa: E731
    rows = [
        jnp.stack([g.lower, g.upper], axis=1).astype(dtype) if BOUNDING_BOX.holds(g) else empty(g.primitive_count)
        for g in geometries
    ]
    count = sum(g.primitive_count for g in geometries)
    return jnp.concatenate([*rows, empty(capacity - count)], axis=0)


def _node_boxes(children, node_range, leaf_lower, leaf_upper):
    lower, upper = range_boxes(leaf_lower, leaf_upper, node_range[:, 0], node_range[:, 1])
    return child_boxes(children, lower, upper, leaf_lower, leaf_upper)


def _lbvh(codes: jax.Array, real: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The radix tree over the first ``real`` leaves of ``C`` slots: ``(children, node_range, order)``.

    Only the real leaves (at least 2; padding codes sort last) are sorted and linked, so the work follows the
    primitive count rather than the power-of-two capacity. The tree takes internal nodes ``0 .. real - 2``;
    the unused rows past them point at a padding leaf, and no node references them.
    """
    capacity = codes.shape[0]
    order = jnp.arange(real, dtype=jnp.int32)
    sorted_codes, order = lax.sort((codes[:real], order), num_keys=1, is_stable=True)
    children, first, last = build_radix_tree(sorted_codes)
    unused = capacity - real
    children = jnp.concatenate([children, jnp.full((unused, 2), -1 - real, jnp.int32)])
    node_range = jnp.concatenate([jnp.stack([first, last], axis=-1), jnp.full((unused, 2), real, jnp.int32)])
    return children, node_range, jnp.concatenate([order, jnp.arange(real, capacity, dtype=jnp.int32)])


def _code_bounds(triangles, curves, boxes, rows=()) -> tuple[jax.Array, jax.Array]:
    """The boxes whose centroids give the Morton codes."""
    # Codes from the triangles' own boxes: a zero-area triangle's empty box has no centroid.
    bounds = lax.stop_gradient(triangles)
    code_lower, code_upper = TRIANGLE.bounds(bounds)
    if curves is not None:  # curve segments: the centroids of their boxes
        code_lower = jnp.where(curves.is_curve[:, None], lax.stop_gradient(curves.lower), code_lower)
        code_upper = jnp.where(curves.is_curve[:, None], lax.stop_gradient(curves.upper), code_upper)
    if boxes is not None:  # box primitives: the centroids of the boxes
        is_box = boxes[:, 0, 0] <= boxes[:, 1, 0]
        box_lower, box_upper = BOUNDING_BOX.bounds(lax.stop_gradient(boxes))
        code_lower = jnp.where(is_box[:, None], box_lower, code_lower)
        code_upper = jnp.where(is_box[:, None], box_upper, code_upper)
    for kind, slots in rows:  # kinds in the shared row: their code boxes (a sphere's centre, also for a bad one)
        kind_lower, kind_upper = (kind.code_bounds or kind.bounds)(bounds)
        code_lower = jnp.where(slots[:, None], kind_lower, code_lower)
        code_upper = jnp.where(slots[:, None], kind_upper, code_upper)
    return code_lower, code_upper


@full_precision
def _build(
    geometries: tuple[TriangleGeometry, ...],
    capacity: int,
    quality: str = "fast",
    motion: MotionSpec | None = None,
    packer: Any = None,
) -> PrimitiveAccelerationStructure:
    count_keys = _keyframe_count(geometries, motion, "build_primitive_structure")
    frames = [_leaf_primitives(f, capacity) for f in _keyframes(geometries, count_keys)]
    triangles, geometry_id, primitive_id, lower, upper, valid, curves, boxes, rows = frames[0]
    code_lower, code_upper = _code_bounds(triangles, curves, boxes, rows)
    if count_keys > 1:  # every box bounds its primitive at every keyframe (and so at every time)
        lower, upper = motion_bounds(jnp.stack([f[3] for f in frames]), jnp.stack([f[4] for f in frames]))
        codes = [_code_bounds(f[0], f[6], f[7], f[8]) for f in frames]
        code_lower, code_upper = motion_bounds(jnp.stack([c[0] for c in codes]), jnp.stack([c[1] for c in codes]))
    count = sum(g.primitive_count for g in geometries)
    real = max(count, 2)  # leaves the LBVH links
    children, node_range, order = _lbvh(morton_codes(code_lower, code_upper, valid), real)
    if quality in ("high", "sah"):
        max_depth = tree_depth_bound(capacity)  # PrimitiveAccelerationStructure.max_depth
        method = "cluster" if quality == "high" else "sweep"
        children, node_range, position = restructure(
            lower[order], upper[order], count, children, node_range, max_depth, method
        )
        order = order[position]

    def boxes_of(lower, upper):
        leaf_lower, leaf_upper = lower[order], upper[order]
        if quality in ("high", "sah"):
            return _node_boxes(children, node_range, leaf_lower, leaf_upper)
        # the unused rows past the tree over the real leaves stay empty
        node_lower, node_upper = _node_boxes(
            children[: real - 1], node_range[: real - 1], leaf_lower[:real], leaf_upper[:real]
        )
        node_lower = jnp.pad(node_lower, ((0, capacity - real), (0, 0), (0, 0)), constant_values=jnp.inf)
        node_upper = jnp.pad(node_upper, ((0, capacity - real), (0, 0), (0, 0)), constant_values=-jnp.inf)
        return node_lower, node_upper

    node_lower, node_upper = boxes_of(lower, upper)
    motion_nodes = {}
    if count_keys > 1:  # the node boxes of every keyframe: blended at a ray's time they bound the blend
        keyed = [boxes_of(*_keyframe_boxes(f)) for f in frames]
        motion_nodes = dict(
            motion_node_lower=lax.stop_gradient(jnp.stack([b[0] for b in keyed])),
            motion_node_upper=lax.stop_gradient(jnp.stack([b[1] for b in keyed])),
        )
    info = tuple(geometry_info(g) for g in geometries)
    return PrimitiveAccelerationStructure(
        node_lower=lax.stop_gradient(node_lower),
        node_upper=lax.stop_gradient(node_upper),
        node_children=children,
        node_range=node_range,
        leaf_geometry=geometry_id[order],
        leaf_primitive=primitive_id[order],
        leaf_triangle=triangles[order],
        geometry_primitive_count=jnp.asarray([g.primitive_count for g in geometries], jnp.int32),
        geometry_info=info,
        leaf_curve=None if curves is None else curves.segments[order],
        leaf_curve_flags=None if curves is None else curves.flags[order],
        leaf_box=None if boxes is None else lax.stop_gradient(boxes[order]),
        leaf_primitive_data=gather_leaf_data(geometries, capacity, order),
        **_motion_leaves(frames, order, motion),
        **motion_nodes,
        kernel_layout=None if packer is None else packer(node_lower, node_upper, children, triangles[order]),
    )


def _keyframe_boxes(frame) -> tuple[jax.Array, jax.Array]:
    """Leaf boxes of one keyframe in slot order, where a triangle without area keeps its (flat) box: a
    triangle flat at one keyframe may have area between keyframes, and the blend needs finite corners."""
    triangles, _, _, lower, upper, valid, _, _, rows = frame
    flat = valid & jnp.any(lower > upper, axis=-1)
    for _, slots in rows:  # a bad leaf of a kind in the shared row stays empty (its test rejects it at every time)
        flat = flat & ~slots
    triangle_lower, triangle_upper = TRIANGLE.bounds(triangles)
    lower = jnp.where(flat[:, None], triangle_lower, lower)
    upper = jnp.where(flat[:, None], triangle_upper, upper)
    return lower, upper


def _motion_leaves(frames: list, order: jax.Array, motion: MotionSpec | None) -> dict:
    """The keyframe leaf arrays of a motion structure, in leaf order (nothing for a static one)."""
    if len(frames) == 1:
        return {}
    curves = frames[0][6] is not None
    boxes = frames[0][7] is not None
    return dict(
        motion_triangle=jnp.stack([f[0][order] for f in frames]),
        motion_curve=jnp.stack([f[6].segments[order] for f in frames]) if curves else None,
        motion_box=lax.stop_gradient(jnp.stack([f[7][order] for f in frames])) if boxes else None,
        motion=motion,
    )


_build_jit = jax.jit(_build, static_argnums=(1, 2, 3, 4))

#: Build qualities: the LBVH ("fast"), agglomerative clustering of its Morton order ("high") and the
#: top-down full-sweep SAH tree ("sah", one pass of three sorts per tree level: slower to build).
QUALITIES = ("fast", "high", "sah")


def build_structure(
    geometries: TriangleGeometry | Sequence[TriangleGeometry],
    *,
    motion: Any = None,
    capacity: int | None = None,
    quality: str = "fast",
    checks: bool = False,
    packer: Any = None,
) -> PrimitiveAccelerationStructure:
    """Build an LBVH over one or more geometries (jitted; also callable on traced arrays inside ``jax.jit``):
    ``rt.build_primitive_structure`` (:func:`jaxrt._src.prepacked.build_primitive_structure`, whose docstring
    describes the arguments) without deciding on the GPU kernel's rows.

    Args:
      packer: static; ``None``, or the function that packs the GPU kernel's rows from the node arrays and
        leaf triangles (``(node_lower, node_upper, node_children, leaf_triangle) -> KernelLayout``), run in the
        same compiled build. The other arguments are those of ``rt.build_primitive_structure``.

    Returns:
      A :class:`PrimitiveAccelerationStructure`. Leaf vertices keep their gradient connection to the
      geometry, so hit distances and barycentrics differentiate through the build.
    """
    if quality not in QUALITIES:
        raise ValueError(f"build_primitive_structure: quality must be one of {QUALITIES}, got {quality!r}")
    geometries = as_geometry_tuple(geometries)
    keys = _keyframe_count(geometries, motion, "build_primitive_structure")  # named errors outside jit
    if checks:
        for k, frame in enumerate(_keyframes(geometries, keys)):
            check_geometries(frame, "build_primitive_structure" + (f" (keyframe {k})" if keys > 1 else ""))
    total = sum(g.primitive_count for g in geometries)
    return _build_jit(geometries, capacity_bucket(total, capacity), quality, motion, packer)


@full_precision
def _refit(structure: PrimitiveAccelerationStructure, geometries: tuple[TriangleGeometry, ...], packer: Any):
    triangles, _, _, lower, upper, _, curves, boxes, _ = _leaf_primitives(geometries, structure.capacity)
    # Leaf k holds unsorted slot order[k]; recover it from the stored ids (slot = offset + primitive).
    offsets = jnp.cumsum(jnp.array([0] + [g.primitive_count for g in geometries[:-1]], jnp.int32))
    padding = structure.leaf_geometry < 0
    slot = jnp.where(padding, 0, offsets[jnp.maximum(structure.leaf_geometry, 0)] + structure.leaf_primitive)
    leaf_lower = jnp.where(padding[:, None], jnp.inf, lower[slot])
    leaf_upper = jnp.where(padding[:, None], -jnp.inf, upper[slot])
    node_lower, node_upper = _node_boxes(structure.node_children, structure.node_range, leaf_lower, leaf_upper)
    leaf_triangle = jnp.where(padding[:, None, None], 0.0, triangles[slot])
    layout = None
    if packer is not None:  # kept consistent with the refitted boxes and triangles
        layout = packer(node_lower, node_upper, structure.node_children, leaf_triangle)
    return dataclasses.replace(
        structure,
        node_lower=lax.stop_gradient(node_lower),
        node_upper=lax.stop_gradient(node_upper),
        kernel_layout=layout,
        leaf_triangle=leaf_triangle,
        leaf_curve=None if curves is None else jnp.where(padding[:, None, None], 0.0, curves.segments[slot]),
        leaf_curve_flags=None if curves is None else jnp.where(padding, 0, curves.flags[slot]),
        leaf_box=None
        if boxes is None
        else lax.stop_gradient(jnp.where(padding[:, None, None], boxes[-1], boxes[slot])),
        leaf_primitive_data=gather_leaf_data(geometries, structure.capacity, jnp.where(padding, -1, slot)),
    )


_refit_jit = jax.jit(_refit, static_argnums=2)


def refit_primitives(
    structure: PrimitiveAccelerationStructure, geometries: Any, packer: Any = None
) -> PrimitiveAccelerationStructure:
    """Recompute the boxes of a primitive structure for moved vertices, keeping its topology (Metal's refit).

    The geometries must have the same kinds and primitive counts as those the structure was built from.
    Tree quality degrades as primitives move far from where they were built; rebuild then. ``packer``: as for
    :func:`build_structure` (``None``: the result carries no kernel rows).
    """
    geometries = as_geometry_tuple(geometries)
    if structure.motion is not None:
        raise NotImplementedError("refit: structures with keyframe motion are rebuilt, not refitted")
    info = tuple(geometry_info(g) for g in geometries)
    if info != structure.geometry_info:
        raise ValueError(f"refit: geometries {info} do not match the structure's {structure.geometry_info}")
    counts = [g.primitive_count for g in geometries]
    if not isinstance(structure.geometry_primitive_count, jax.core.Tracer):
        have = np.asarray(structure.geometry_primitive_count).tolist()
        if counts != have:
            raise ValueError(f"refit: the geometries have {counts} primitives, the structure was built from {have}")
    return _refit_jit(structure, geometries, packer)
