"""Instances and instance acceleration structures (Metal's instance descriptors and instance structures).

An instance places a child structure (primitive or instance structure) in the parent's space by an affine
object-to-world transform. :func:`build_instance_structure` builds a BVH (a full-sweep SAH tree by default, or
the LBVH) over the world-space boxes of the instances: the transformed corners of the boxes of the child's
first tree levels (not a bounding sphere, nor only the root box).

Representation: an :class:`InstanceAccelerationStructure` is a small scene graph stored flat. It holds every
*distinct* structure below it once: the primitive structures, and one :class:`InstanceTable` per instance
structure (its own BVH and instance arrays). A static map says, for each table, which component each index
of its ``structures`` argument refers to. So a tree shared by a thousand forest instances and by several
forests is stored once, as in Metal, where instances reference their structures by pointer; and the graph
survives ``jit``/``vmap`` round trips of the pytree unchanged.

Node layout of an :class:`InstanceTable` (that of :mod:`jaxrt._src.structures`, over instances; ``C`` is
the leaf capacity, a power of two at least 2, ``N`` the number of instance slots):

==================== ================ =========================================================================
array                shape, dtype     contents
==================== ================ =========================================================================
``node_lower``       (C-1, 2, 3) f    lower corners of both children of each internal node (world space)
``node_upper``       (C-1, 2, 3) f    upper corners; an empty child is (+inf, -inf)
``node_children``    (C-1, 2) i32     internal child ``c >= 0``, or leaf ``k`` as ``-1 - k``
``node_range``       (C-1, 2) i32     first and last leaf under the node
``leaf_instance``    (C,) i32         instance index of leaf ``k``; -1 for padding
``structure_index``  (N,) i32         index into the ``structures`` the table was built with
``transform``        (N, 3, 4) f      object-to-world, row-major, last column the translation
``world_to_object``  (N, 3, 4) f      its inverse (computed in the build, differentiable)
``mask``             (N,) u32         instance mask (visible to a ray when ``mask & ray.mask != 0``)
``user_id``          (N,) u32         user instance id
``options``          (N,) u32         :class:`InstanceOptions` bits
``count``            () i32           instances ``>= count`` do not exist (empty boxes)
==================== ================ =========================================================================
"""

from __future__ import annotations

import dataclasses
import enum
import functools
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxrt._src.bvh.boxes import child_boxes, range_boxes
from jaxrt._src.bvh.morton import morton_codes
from jaxrt._src.bvh.radix_tree import build_radix_tree, tree_depth_bound
from jaxrt._src.bvh.sweep_sah import sweep_sah_tree
from jaxrt._src.checks import check_instances
from jaxrt._src.geometry import float_dtype
from jaxrt._src.motion import MotionSpec
from jaxrt._src.numerics import full_precision
from jaxrt._src.structures import PrimitiveAccelerationStructure, capacity_bucket
from jaxrt._src.transforms import SINGULAR_TOLERANCE, InstanceMotion, invert_transform, transform_boxes

__all__ = [
    "InstanceOptions",
    "Instances",
    "InstanceTable",
    "InstanceAccelerationStructure",
    "build_instance_structure",
    "refit_instances",
    "SceneArrays",
    "scene_arrays",
]


class InstanceOptions(enum.IntFlag):
    """Per-instance options (Metal's ``MTLAccelerationStructureInstanceOptions``, same bits)."""

    NONE = 0
    """No option."""
    DISABLE_TRIANGLE_CULLING = 1
    """The intersector's ``triangle_cull_mode`` does not apply to this instance's triangles."""
    TRIANGLE_FRONT_FACING_WINDING_COUNTERCLOCKWISE = 2
    """Flip the intersector's ``front_facing_winding`` for this instance (culling and ``triangle_front_facing``)."""
    OPAQUE = 4
    """Treat the instance's geometry as opaque, whatever its geometries say (for filters)."""
    NON_OPAQUE = 8
    """Treat the instance's geometry as non-opaque (alpha-tested), whatever its geometries say."""


_ALL_OPTIONS = int(sum(InstanceOptions))


def _is_concrete(x: Any) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _uint32(value: Any, name: str, n: int, owner: str) -> jax.Array:
    """An integer argument broadcast to ``(n,)`` uint32, range-checked on the host when concrete."""
    dtype = np.dtype(getattr(value, "dtype", None) or np.asarray(value).dtype)
    if not np.issubdtype(dtype, np.integer):
        raise TypeError(f"{owner}: {name} must be an integer (array), got dtype {dtype}")
    if _is_concrete(value):
        host = np.asarray(value)
        if host.ndim > 1 or (host.ndim == 1 and host.shape[0] != n):
            raise ValueError(f"{owner}: {name} must be a scalar or have shape ({n},), got {host.shape}")
        if host.size and ((host < 0).any() or (host > 0xFFFFFFFF).any()):
            bad = host.reshape(-1)[np.argmax(((host < 0) | (host > 0xFFFFFFFF)).reshape(-1))]
            raise ValueError(f"{owner}: {name} values must be in [0, 2**32), got {int(bad)}")
        return jnp.asarray(np.broadcast_to(host.astype(np.uint32), (n,)))
    return jnp.broadcast_to(jnp.asarray(value).astype(jnp.uint32), (n,))


def _check_transforms(transform: jax.Array, owner: str) -> None:
    """Reject non-finite and (numerically) singular transforms, naming the instance and the value."""
    host = np.asarray(transform, np.float64)
    bad = ~np.isfinite(host)
    if bad.any():
        index = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"{owner}: transform has a non-finite value {host[index]} at index {index}")
    linear = host[:, :, :3]
    det = np.linalg.det(linear)
    scale = np.prod(np.linalg.norm(linear, axis=1), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        relative = np.where(scale > 0, np.abs(det) / np.where(scale > 0, scale, 1.0), 0.0)
    singular = relative < SINGULAR_TOLERANCE
    if singular.any():
        i = int(np.argmax(singular))
        raise ValueError(
            f"{owner}: transform[{i}] is singular (determinant {det[i]:.3g}, relative determinant "
            f"{relative[i]:.3g} < {SINGULAR_TOLERANCE}); an instance transform must be invertible"
        )


@jax.tree_util.register_pytree_node_class
class Instances:
    """A batch of instances: which structure each one places, where, and how (Metal's instance descriptors).

    Args:
      structure_index: ``(N,)`` integers, each an index into the ``structures`` given to
        :func:`build_instance_structure`.
      transform: ``(N, 3, 4)`` float object-to-world transforms, row-major with the translation in the last
        column (a point ``p`` in the child's space is at ``transform[:, :3] @ p + transform[:, 3]``). They must
        be finite and invertible; mirroring (negative determinant) and non-uniform scale are fine. Instance
        motion: ``(N, K, 3, 4)``, ``K >= 2`` keyframes per instance, evenly spaced over the time range of the
        ``motion`` given to :func:`build_instance_structure`; a ray at time ``t`` sees each instance under the
        component-wise blend of its two neighbouring keyframe transforms (Metal's default), whose inverse
        moves the ray. Mirroring is read from keyframe 0.
      mask: instance masks, a scalar or ``(N,)``; an instance is visible to a ray when
        ``mask & ray.mask != 0`` (Metal's default instance mask is ``0xFF``).
      user_id: ``(N,)`` (or scalar) 32-bit user ids reported as ``user_instance_id``; ``None`` gives 0, as a
        zero-initialised Metal descriptor does.
      options: :class:`InstanceOptions` per instance (scalar or ``(N,)``); ``None`` is ``NONE``.

    Raises:
      TypeError: non-float transforms or non-integer indices, masks, ids or options.
      ValueError: wrong shapes, a negative structure index, a non-finite or singular transform, masks or ids
        outside 32 bits, unknown option bits, or ``OPAQUE`` together with ``NON_OPAQUE``. Each message names
        the argument and the offending instance; ``(N, K, 3, 4)`` transforms with ``K < 2``.

    Inside ``jax.jit`` (traced arrays) only shapes and dtypes are checked.

    Examples:
      >>> import numpy as np, jaxrt as rt
      >>> rt.Instances([0, 0], np.tile(np.eye(3, 4, dtype=np.float32), (2, 1, 1))).count
      2
    """

    def __init__(
        self, structure_index: Any, transform: Any, *, mask: Any = 0xFF, user_id: Any = None, options: Any = None
    ):
        owner = "Instances"
        dtype = np.dtype(getattr(transform, "dtype", None) or np.asarray(transform).dtype)
        if dtype not in (np.float32, np.float64):
            raise TypeError(f"{owner}: transform must be float32 or float64, got dtype {dtype}")
        transform = jnp.asarray(transform, float_dtype())
        if transform.ndim not in (3, 4) or transform.shape[-2:] != (3, 4):
            raise ValueError(
                f"{owner}: transform must have shape (N, 3, 4), or (N, K, 3, 4) for instance motion, got "
                f"{tuple(transform.shape)}"
            )
        if transform.ndim == 4 and transform.shape[1] < 2:
            raise ValueError(
                f"{owner}: keyframed transforms (N, K, 3, 4) need K >= 2 keyframes, got {tuple(transform.shape)}"
            )
        n = int(transform.shape[0])
        if n == 0:
            raise ValueError(f"{owner}: transform is empty; an instance structure needs at least one instance slot")
        if _is_concrete(transform):
            if transform.ndim == 4:
                for k in range(transform.shape[1]):
                    _check_transforms(transform[:, k], f"{owner} (keyframe {k})")
            else:
                _check_transforms(transform, owner)
        index_dtype = np.dtype(getattr(structure_index, "dtype", None) or np.asarray(structure_index).dtype)
        if not np.issubdtype(index_dtype, np.integer):
            raise TypeError(f"{owner}: structure_index must have an integer dtype, got {index_dtype}")
        if _is_concrete(structure_index):
            host = np.asarray(structure_index)
            if host.shape != (n,):
                raise ValueError(f"{owner}: structure_index must have shape ({n},) like transform, got {host.shape}")
            if (host < 0).any():
                i = int(np.argmax(host < 0))
                raise ValueError(f"{owner}: structure_index[{i}] = {int(host[i])} is negative")
            if (host > np.iinfo(np.int32).max).any():
                raise ValueError(f"{owner}: structure_index exceeds the int32 range")
        elif tuple(structure_index.shape) != (n,):
            raise ValueError(f"{owner}: structure_index must have shape ({n},), got {tuple(structure_index.shape)}")
        self.structure_index = jnp.asarray(structure_index, jnp.int32)
        self.transform = transform
        self.keyframed = transform.ndim == 4
        self.mask = _uint32(mask, "mask", n, owner)
        self.user_id = _uint32(0 if user_id is None else user_id, "user_id", n, owner)
        options = _uint32(0 if options is None else options, "options", n, owner)
        if _is_concrete(options):
            host = np.asarray(options)
            unknown = (host & ~np.uint32(_ALL_OPTIONS)) != 0
            if unknown.any():
                i = int(np.argmax(unknown))
                raise ValueError(f"{owner}: options[{i}] = {int(host[i])} has bits outside InstanceOptions")
            both = (host & (InstanceOptions.OPAQUE | InstanceOptions.NON_OPAQUE)) == (
                InstanceOptions.OPAQUE | InstanceOptions.NON_OPAQUE
            )
            if both.any():
                raise ValueError(f"{owner}: options[{int(np.argmax(both))}] sets both OPAQUE and NON_OPAQUE")
        self.options = options

    @property
    def count(self) -> int:
        """Number of instance slots ``N`` (static)."""
        return int(self.transform.shape[-4 if self.keyframed else -3])

    @property
    def keyframe_count(self) -> int:
        """Keyframes ``K`` of keyframed transforms (instance motion); 1 for ``(N, 3, 4)`` transforms."""
        return int(self.transform.shape[-3]) if self.keyframed else 1

    def keyframe(self, k: int) -> Instances:
        """The instances under keyframe ``k``'s transforms (no validation)."""
        children, _ = self.tree_flatten()
        transform = self.transform[..., k, :, :] if self.keyframed else self.transform
        return Instances.tree_unflatten((False,), (children[0], transform, *children[2:]))

    def tree_flatten(self):
        return (self.structure_index, self.transform, self.mask, self.user_id, self.options), (self.keyframed,)

    @classmethod
    def tree_unflatten(cls, aux, children):
        obj = object.__new__(cls)
        obj.structure_index, obj.transform, obj.mask, obj.user_id, obj.options = children
        (obj.keyframed,) = aux
        return obj

    def __repr__(self) -> str:
        return f"Instances(count={self.count})"


# --- structures -------------------------------------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True, eq=False)
class InstanceTable:
    """One instance structure's own BVH and instance arrays (layout in the module docstring).

    Compared by identity: the same table reached through two parents is stored once in a scene.
    """

    node_lower: jax.Array
    node_upper: jax.Array
    node_children: jax.Array
    node_range: jax.Array
    leaf_instance: jax.Array
    structure_index: jax.Array
    transform: jax.Array
    world_to_object: jax.Array
    mask: jax.Array
    user_id: jax.Array
    options: jax.Array
    count: jax.Array
    motion_transform: jax.Array | None = None  # (N, K, 3, 4) object-to-world keyframes (instance motion only)
    motion: MotionSpec | None = dataclasses.field(default=None, metadata=dict(static=True))

    @property
    def capacity(self) -> int:
        """Leaf slots of the BVH (a power of two, at least 2)."""
        return int(self.leaf_instance.shape[-1])

    @property
    def instance_slots(self) -> int:
        """Number of instance slots ``N`` (static); the instances that exist are the first ``count``."""
        return int(self.transform.shape[-3])

    @property
    def max_depth(self) -> int:
        """Bound on the depth of any leaf (as for a primitive structure)."""
        return tree_depth_bound(self.capacity)


def _check_graph(primitive_count: int, tables: int, children: tuple[tuple[int, ...], ...]) -> None:
    """The component graph must reference existing components and be acyclic, naming the offending table."""
    owner = "InstanceAccelerationStructure"
    if len(children) != tables:
        raise ValueError(f"{owner}: children has {len(children)} entries for {tables} instance tables")
    total = primitive_count + tables
    for t, refs in enumerate(children):
        for c in refs:
            if not (isinstance(c, int) and 0 <= c < total):
                raise ValueError(f"{owner}: instance table {t} references component {c!r}, outside [0, {total})")
    state = [0] * tables  # 0 unvisited, 1 on the current path, 2 done

    def visit(t: int, path: list[int]) -> None:
        if state[t] == 2:
            return
        if state[t] == 1:
            cycle = " -> ".join(str(i) for i in path[path.index(t) :] + [t])
            raise ValueError(f"{owner}: the instance structures form a cycle (tables {cycle})")
        state[t] = 1
        for c in children[t]:
            if c >= primitive_count:
                visit(c - primitive_count, path + [t])
        state[t] = 2

    for t in range(tables):
        visit(t, [])


def _levels_of(primitive_count: int, children: tuple[tuple[int, ...], ...]) -> tuple[int, ...]:
    """Instance levels below each component (0 for primitive structures)."""
    memo: dict[int, int] = {}

    def levels(c: int) -> int:
        if c < primitive_count:
            return 0
        if c not in memo:
            refs = children[c - primitive_count]
            memo[c] = 1 + max((levels(r) for r in refs), default=0)
        return memo[c]

    return tuple(levels(c) for c in range(primitive_count + len(children)))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True, eq=False)
class InstanceAccelerationStructure:
    """A BVH over instances of other structures, possibly instance structures (multi-level instancing).

    Build it with :func:`build_instance_structure`. The pytree holds every distinct structure below it once
    (see the module docstring): ``primitive_structures``, and ``instance_tables`` whose last entry is this
    structure's own table. ``children[t]`` (static) gives, for table ``t``, the component each of its
    ``structure_index`` values refers to: ``c < P`` is ``primitive_structures[c]``, ``c >= P`` is
    ``instance_tables[c - P]``.

    Raises:
      ValueError: (direct construction) a component reference out of range, or a cycle, naming the tables.
    """

    primitive_structures: tuple[PrimitiveAccelerationStructure, ...]
    instance_tables: tuple[InstanceTable, ...]
    children: tuple[tuple[int, ...], ...] = dataclasses.field(metadata=dict(static=True))

    def __post_init__(self):
        _check_graph(len(self.primitive_structures), len(self.instance_tables), self.children)

    @property
    def root(self) -> InstanceTable:
        """This structure's own table (BVH and instances)."""
        return self.instance_tables[-1]

    @property
    def levels(self) -> int:
        """Instance levels from this structure down to the primitives (1 for instances of primitive structures)."""
        return _levels_of(len(self.primitive_structures), self.children)[-1]

    @property
    def has_instance_motion(self) -> bool:
        """Whether some instance table below (or at) this structure has keyframed transforms."""
        return any(t.motion is not None for t in self.instance_tables)

    @property
    def instance_count(self) -> jax.Array:
        """The number of instances that exist (the ``count`` of the build; may be traced)."""
        return self.root.count

    @property
    def capacity(self) -> int:
        """Leaf slots of this structure's own BVH."""
        return self.root.capacity

    @property
    def primitive_count(self) -> int:
        """Distinct primitives stored (not the instanced total)."""
        return sum(s.primitive_count for s in self.primitive_structures)

    @property
    def max_depth(self) -> int:
        """A traversal stack bound: the sum over levels of the deepest tree that can appear at that level."""
        p = len(self.primitive_structures)
        depth_of = [s.max_depth for s in self.primitive_structures] + [t.max_depth for t in self.instance_tables]
        frontier = {p + len(self.instance_tables) - 1}
        total = 0
        while frontier:
            total += max(depth_of[c] for c in frontier)
            frontier = {r for c in frontier if c >= p for r in self.children[c - p]}
        return total


#: Tree levels read below a child structure's root for the world box of its instances: the union of the
#: transformed boxes of up to ``2 ** TOP_LEVELS`` nodes of its first levels (a leaf met earlier counts as its
#: own box) bounds a rotated instance more tightly than its transformed root box.
TOP_LEVELS = 4


def _top_boxes(component: PrimitiveAccelerationStructure | InstanceTable, levels: int = TOP_LEVELS):
    """Up to ``2 ** levels`` boxes ``(2 ** levels, 3)`` covering a structure: the children of the nodes of its
    first ``levels - 1`` levels below the root, where a child that is a leaf (or empty) stands for itself,
    beside empty boxes. Their union is the root's box."""
    lower, upper, child = component.node_lower[0], component.node_upper[0], component.node_children[0]
    for _ in range(levels - 1):
        opens = (child >= 0) & jnp.all(lower <= upper, axis=-1)
        node = jnp.maximum(child, 0)
        empty = jnp.full(lower.shape, jnp.inf, lower.dtype)
        own_lower = jnp.stack([lower, empty], axis=1)
        own_upper = jnp.stack([upper, -empty], axis=1)
        lower = jnp.where(opens[:, None, None], component.node_lower[node], own_lower).reshape(-1, 3)
        upper = jnp.where(opens[:, None, None], component.node_upper[node], own_upper).reshape(-1, 3)
        child = jnp.where(opens[:, None], component.node_children[node], -1).reshape(-1)
    return lower, upper


def _child_boxes(roots: list) -> tuple[jax.Array, jax.Array]:
    """Covering boxes ``(S', B, 3)`` of the child structures (:func:`_top_boxes`), padded with empty ones to a
    power of two ``S'`` (so that builds over similar numbers of structures share compiled code; no index refers
    to the padding)."""
    boxes = [_top_boxes(r) for r in roots]
    pad = (1 << (len(boxes) - 1).bit_length()) - len(boxes)
    shape = boxes[0][0].shape
    lower = jnp.stack([b[0] for b in boxes] + [jnp.full(shape, jnp.inf, boxes[0][0].dtype)] * pad)
    upper = jnp.stack([b[1] for b in boxes] + [jnp.full(shape, -jnp.inf, boxes[0][1].dtype)] * pad)
    return lax.stop_gradient(lower), lax.stop_gradient(upper)


@full_precision
def _build_table(
    child_lower: jax.Array,
    child_upper: jax.Array,
    structure_index: jax.Array,
    transform: jax.Array,
    mask: jax.Array,
    user_id: jax.Array,
    options: jax.Array,
    count: jax.Array,
    motion: MotionSpec | None = None,
    quality: str = "high",
) -> InstanceTable:
    """The tree over instance boxes: the full-sweep SAH tree (``quality="high"``,
    :mod:`jaxrt._src.bvh.sweep_sah`) or the LBVH (``"fast"``: Morton codes, sort, radix tree).

    With keyframed transforms ``(N, K, 3, 4)`` an instance's box is the union of its child's box under every
    keyframe transform. A component-wise blend maps each child point to a convex combination of its images
    under two keyframes, so the union bounds the instance at every time (conservatively: it also covers the
    space between keyframes that a rotation sweeps around rather than through).
    """
    n = transform.shape[0]
    capacity = capacity_bucket(n)
    structures = child_lower.shape[0]
    in_range = (structure_index >= 0) & (structure_index < structures)
    exists = (jnp.arange(n) < count) & in_range
    index = jnp.clip(structure_index, 0, structures - 1)
    keys = transform if transform.ndim == 4 else transform[:, None]
    boxes = [
        transform_boxes(lax.stop_gradient(keys[:, k]), child_lower[index], child_upper[index])
        for k in range(keys.shape[1])
    ]
    lower = functools.reduce(jnp.minimum, [b[0] for b in boxes])
    upper = functools.reduce(jnp.maximum, [b[1] for b in boxes])
    lower = jnp.where(exists[:, None], lower, jnp.inf)
    upper = jnp.where(exists[:, None], upper, -jnp.inf)
    valid = jnp.pad(exists & jnp.all(lower <= upper, axis=-1), (0, capacity - n))
    lower = jnp.pad(lower, ((0, capacity - n), (0, 0)), constant_values=jnp.inf)
    upper = jnp.pad(upper, ((0, capacity - n), (0, 0)), constant_values=-jnp.inf)
    if quality == "high":
        children, node_range, order = sweep_sah_tree(lower, upper, valid, tree_depth_bound(capacity))
        first, last = node_range[:, 0], node_range[:, 1]
    else:
        codes = morton_codes(lower, upper, valid)
        order = jnp.arange(capacity, dtype=jnp.int32)
        codes, order = lax.sort((codes, order), num_keys=1, is_stable=True)
        children, first, last = build_radix_tree(codes)
        node_range = jnp.stack([first, last], axis=-1)
    leaf_lower, leaf_upper = lower[order], upper[order]
    range_lower, range_upper = range_boxes(leaf_lower, leaf_upper, first, last)
    node_lower, node_upper = child_boxes(children, range_lower, range_upper, leaf_lower, leaf_upper)
    return InstanceTable(
        node_lower=node_lower,
        node_upper=node_upper,
        node_children=children,
        node_range=node_range,
        leaf_instance=jnp.where(order < n, order, -1).astype(jnp.int32),
        structure_index=structure_index,
        transform=keys[:, 0],
        world_to_object=invert_transform(keys[:, 0]),
        mask=mask,
        user_id=user_id,
        options=options,
        count=count,
        motion_transform=transform if transform.ndim == 4 else None,
        motion=motion if transform.ndim == 4 else None,
    )


_build_table_jit = jax.jit(_build_table, static_argnums=(8, 9))

#: Instance tree qualities: the full-sweep SAH tree (``"high"``, the default) and the LBVH (``"fast"``).
INSTANCE_QUALITIES = ("high", "fast")


def _check_motion(instances: Instances, motion: Any, owner: str) -> None:
    """Keyframed transforms need a :class:`MotionSpec` and a spec needs keyframed transforms."""
    if motion is not None and not isinstance(motion, MotionSpec):
        raise TypeError(f"{owner}: motion must be an rt.MotionSpec or None, got {motion!r}")
    if instances.keyframe_count > 1 and motion is None:
        raise ValueError(
            f"{owner}: instances.transform {tuple(instances.transform.shape)} is keyframed (instance motion); pass "
            "motion=rt.MotionSpec(start_time, end_time, ...)"
        )
    if instances.keyframe_count == 1 and motion is not None:
        raise ValueError(
            f"{owner}: motion={motion} needs keyframed transforms (N, K, 3, 4), got {tuple(instances.transform.shape)}"
        )


def _check_quality(quality: Any, owner: str) -> None:
    if quality not in INSTANCE_QUALITIES:
        raise ValueError(f"{owner}: quality must be one of {INSTANCE_QUALITIES}, got {quality!r}")


def _count(count: Any, n: int) -> jax.Array:
    owner = "build_instance_structure"
    if count is None:
        return jnp.asarray(n, jnp.int32)
    dtype = np.dtype(getattr(count, "dtype", None) or np.asarray(count).dtype)
    if not np.issubdtype(dtype, np.integer):
        raise TypeError(f"{owner}: count must be an integer scalar, got dtype {dtype}")
    if np.ndim(count) != 0:
        raise ValueError(f"{owner}: count must be a scalar, got shape {np.shape(count)}")
    if _is_concrete(count) and not 0 <= int(count) <= n:
        raise ValueError(f"{owner}: count = {int(count)} is outside [0, {n}] (the number of instance slots)")
    return jnp.asarray(count, jnp.int32)


class _Merger:
    """Collects the distinct components of child structures (by identity) and their graph."""

    def __init__(self):
        self.primitives: list[PrimitiveAccelerationStructure] = []
        self.tables: list[InstanceTable] = []
        self.table_children: list[tuple[tuple[str, int], ...]] = []  # ("p", i) or ("t", i)
        self._ids: dict[int, tuple[str, int]] = {}

    def _primitive(self, s: PrimitiveAccelerationStructure) -> tuple[str, int]:
        if id(s) not in self._ids:
            self._ids[id(s)] = ("p", len(self.primitives))
            self.primitives.append(s)
        return self._ids[id(s)]

    def add(self, s: PrimitiveAccelerationStructure | InstanceAccelerationStructure) -> tuple[str, int]:
        """Merge ``s`` and return the reference of its root component."""
        if isinstance(s, PrimitiveAccelerationStructure):
            return self._primitive(s)
        local: list[tuple[str, int]] = [self._primitive(p) for p in s.primitive_structures]
        for table, refs in zip(s.instance_tables, s.children, strict=True):
            if id(table) not in self._ids:
                self._ids[id(table)] = ("t", len(self.tables))
                self.tables.append(table)
                self.table_children.append(tuple(local[r] for r in refs))
            local.append(self._ids[id(table)])
        return local[-1]


def build_instance_structure(
    structures: Sequence[PrimitiveAccelerationStructure | InstanceAccelerationStructure],
    instances: Instances,
    *,
    count: Any = None,
    motion: Any = None,
    checks: bool = False,
    quality: str = "high",
) -> InstanceAccelerationStructure:
    """Build an instance structure: a BVH over the world-space boxes of ``instances``.

    Each instance's box bounds the transformed corners of the boxes of its child's first tree levels (up to 16
    boxes, slightly padded for rounding), which is tighter than the transformed root box for rotated
    instances. Structures may be primitive or instance structures (multi-level instancing); distinct
    structures reached through several paths are stored once. Works under ``jax.jit`` and ``jax.vmap`` (over
    same-shape inputs: ``jax.vmap(rt.build_instance_structure)(structures, instances)``).

    Args:
      structures: the structures instances refer to by ``structure_index``.
      instances: an :class:`Instances`.
      count: how many of the instances exist (Metal's indirect instance count): instances ``>= count`` are
        skipped. A Python int or a (possibly traced) int32 scalar; changing only its value does not recompile.
        ``None`` means all.
      motion: the time range and border modes (an :class:`~jaxrt.MotionSpec`) of keyframed transforms
        ``(N, K, 3, 4)`` (required with them, refused without them). A static instance of a moving table
        repeats one transform over its keyframes. Moving and static tables mix at any level.
      checks: also check traced inputs (non-finite or singular transforms and structure indices out of range
        among the ``count`` existing instances), which are checked only when concrete otherwise: a
        :class:`~jaxrt._src.checks.BuildCheckError` (inside ``jit``, a ``jax.errors.JaxRuntimeError``
        carrying its message; :func:`~jaxrt.build_check_errors` raises it as the former). Costs a host synchronisation per build (:mod:`jaxrt._src.checks`).
      quality: ``"high"`` (default): a full-sweep SAH tree over the instances (one pass of three sorts per
        tree level, :mod:`jaxrt._src.bvh.sweep_sah`); ``"fast"``: the LBVH (Morton codes and a radix tree),
        cheaper to build for very many instances rebuilt every frame, with more overlapping nodes.

    Returns:
      An :class:`InstanceAccelerationStructure`. Transforms keep their gradient connection (boxes do not), so
      hit distances and world-space data differentiate with respect to them.

    Raises:
      TypeError: a structure that is not an acceleration structure, or ``instances`` not :class:`Instances`.
      ValueError: empty ``structures``, a ``structure_index`` out of range, ``count`` outside ``[0, N]``
        (checked when concrete; inside ``jit`` an out-of-range index makes the instance not exist), or an
        unknown ``quality``.

    Examples:
      >>> import numpy as np, jaxrt as rt
      >>> blas = rt.build_primitive_structure(rt.TriangleGeometry([[0., 0, 0], [1, 0, 0], [0, 1, 0]]))
      >>> moved = np.array([[[1, 0, 0, 5], [0, 1, 0, 0], [0, 0, 1, 0]]], np.float32)
      >>> scene = rt.build_instance_structure([blas], rt.Instances([0], moved))
      >>> hit = rt.Intersector(rt.tags.instancing).intersect(rt.Ray([5.2, .2, 1], [0., 0, -1]), scene)
      >>> float(hit.distance), hit.instance_id.tolist()
      (1.0, [0])
    """
    owner = "build_instance_structure"
    if isinstance(structures, PrimitiveAccelerationStructure | InstanceAccelerationStructure):
        structures = (structures,)
    if not isinstance(structures, Sequence) or isinstance(structures, str):
        raise TypeError(f"{owner}: structures must be a sequence of structures, got {type(structures).__name__}")
    structures = tuple(structures)
    if not structures:
        raise ValueError(f"{owner}: structures is empty; instances need a structure to refer to")
    for i, s in enumerate(structures):
        if not isinstance(s, PrimitiveAccelerationStructure | InstanceAccelerationStructure):
            raise TypeError(f"{owner}: structures[{i}] is a {type(s).__name__}, not an acceleration structure")
    if not isinstance(instances, Instances):
        raise TypeError(f"{owner}: instances must be a jaxrt.Instances, got {type(instances).__name__}")
    if _is_concrete(instances.structure_index):
        host = np.asarray(instances.structure_index)
        bad = (host < 0) | (host >= len(structures))
        if bad.any():
            i = int(np.argmax(bad))
            raise ValueError(
                f"{owner}: instances.structure_index[{i}] = {int(host[i])} is out of range for "
                f"{len(structures)} structures"
            )
    _check_motion(instances, motion, owner)
    _check_quality(quality, owner)
    n = instances.count
    count = _count(count, n)
    if checks:
        for k in range(instances.keyframe_count):
            check_instances(instances.keyframe(k), len(structures), count, SINGULAR_TOLERANCE, owner)

    merger = _Merger()
    refs = tuple(merger.add(s) for s in structures)
    p = len(merger.primitives)
    resolve = lambda ref: ref[1] if ref[0] == "p" else p + ref[1]  # noqa: E731
    roots = [merger.primitives[i] if kind == "p" else merger.tables[i] for kind, i in refs]
    child_lower, child_upper = _child_boxes(roots)
    table = _build_table_jit(
        child_lower,
        child_upper,
        instances.structure_index,
        instances.transform,
        instances.mask,
        instances.user_id,
        instances.options,
        count,
        motion,
        quality,
    )
    children = tuple(tuple(resolve(r) for r in t) for t in merger.table_children) + (tuple(resolve(r) for r in refs),)
    return InstanceAccelerationStructure(
        primitive_structures=tuple(merger.primitives),
        instance_tables=(*merger.tables, table),
        children=children,
    )


def refit_instances(
    structure: InstanceAccelerationStructure, instances: Instances, *, count: Any = None, quality: str = "high"
):
    """Rebuild the root table of ``structure`` for new instance arrays, keeping its children (Metal's refit).

    A rebuild over a few thousand instances costs little next to a trace, so this rebuilds the root's tree
    (best quality; ``quality`` as for :func:`build_instance_structure`) while the child structures are reused
    as they are. ``instances`` must have the same number of slots; ``count`` defaults to the structure's
    current count.
    """
    owner = "refit"
    if not isinstance(instances, Instances):
        raise TypeError(f"{owner}: an instance structure is refit with Instances, got {type(instances).__name__}")
    if instances.count != structure.root.instance_slots:
        raise ValueError(
            f"{owner}: instances has {instances.count} slots, the structure was built with "
            f"{structure.root.instance_slots}"
        )
    components = list(structure.primitive_structures) + list(structure.instance_tables)
    refs = structure.children[-1]
    if _is_concrete(instances.structure_index):
        host = np.asarray(instances.structure_index)
        if ((host < 0) | (host >= len(refs))).any():
            raise ValueError(f"{owner}: instances.structure_index is out of range for {len(refs)} structures")
    _check_motion(instances, structure.root.motion, owner)
    _check_quality(quality, owner)
    table = _build_table_jit(
        *_child_boxes([components[c] for c in refs]),
        instances.structure_index,
        instances.transform,
        instances.mask,
        instances.user_id,
        instances.options,
        structure.root.count if count is None else _count(count, instances.count),
        structure.root.motion,
        quality,
    )
    return dataclasses.replace(structure, instance_tables=(*structure.instance_tables[:-1], table))


# --- the flat scene the traversal reads ----------------------------------------------------------------------


class SceneArrays(NamedTuple):
    """All node arrays of a scene concatenated, with global indices (built inside ``jit`` per intersect).

    Node children: an internal node ``c >= 0``; a leaf ``-1 - k`` is primitive leaf ``k`` when
    ``k < primitive_leaves``, else instance ``k - primitive_leaves`` (a global instance index ``g``). The
    primitive leaves are those of every primitive structure, one structure after another, each padded to its
    capacity; ``leaf_curve`` and ``leaf_curve_flags`` are present when some primitive structure holds curves
    (zeros, without the curve bit, for the leaves of the others).
    """

    node_lower: jax.Array  # (M, 2, 3)
    node_upper: jax.Array  # (M, 2, 3)
    node_children: jax.Array  # (M, 2)
    leaf_triangle: jax.Array  # (LT, 3, 3) object space
    leaf_geometry: jax.Array  # (LT,)
    leaf_primitive: jax.Array  # (LT,)
    transform: jax.Array  # (G, 3, 4) object-to-world of global instance g
    world_to_object: jax.Array  # (G, 3, 4)
    child_root: jax.Array  # (G,) global root node of the instance's child structure
    mask: jax.Array  # (G,) uint32
    flip: jax.Array  # (G,) int32: -1 flips the winding (mirroring XOR the counterclockwise option), else +1
    cull: jax.Array  # (G,) int32: 0 disables triangle culling below the instance, else 1
    local_index: jax.Array  # (G,) index of the instance within its structure
    user_id: jax.Array  # (G,) uint32
    options: jax.Array  # (G,) uint32
    leaf_curve: jax.Array | None = None  # (LT, 6, 4) packed object-space segments, or None without curves
    leaf_curve_flags: jax.Array | None = None  # (LT,) int32
    motion: InstanceMotion | None = None  # keyframed transforms, with instance motion only


def _instance_motion(tables: tuple[InstanceTable, ...]) -> InstanceMotion | None:
    """The keyframed transforms of every table's instances, concatenated (``None`` without instance motion)."""
    if all(t.motion is None for t in tables):
        return None
    k = max(t.motion_transform.shape[1] for t in tables if t.motion is not None)
    keys, count, start, end, vanish_start, vanish_end, moving = [], [], [], [], [], [], []
    for t in tables:
        n = t.instance_slots
        own = t.motion_transform if t.motion is not None else jnp.stack([t.transform, t.transform], axis=1)
        last = own[:, -1:]
        keys.append(jnp.concatenate([own] + [last] * (k - own.shape[1]), axis=1))
        spec = t.motion or MotionSpec()
        count.append(jnp.full((n,), own.shape[1], jnp.int32))
        start.append(jnp.full((n,), spec.start_time, own.dtype))
        end.append(jnp.full((n,), spec.end_time, own.dtype))
        vanish_start.append(jnp.full((n,), spec.start_border == "vanish"))
        vanish_end.append(jnp.full((n,), spec.end_border == "vanish"))
        moving.append(jnp.full((n,), t.motion is not None))
    cat = jnp.concatenate
    return InstanceMotion(cat(keys), cat(count), cat(start), cat(end), cat(vanish_start), cat(vanish_end), cat(moving))


def _leaf_curves(prims: tuple[PrimitiveAccelerationStructure, ...]) -> tuple[jax.Array | None, jax.Array | None]:
    """The curve leaves of all primitive structures, concatenated (zeros for structures without curves)."""
    with_curves = [s for s in prims if s.leaf_curve is not None]
    if not with_curves:
        return None, None
    dtype = with_curves[0].leaf_curve.dtype
    segments = [
        s.leaf_curve.astype(dtype) if s.leaf_curve is not None else jnp.zeros((s.capacity, 6, 4), dtype) for s in prims
    ]
    flags = [s.leaf_curve_flags if s.leaf_curve is not None else jnp.zeros((s.capacity,), jnp.int32) for s in prims]
    return jnp.concatenate(segments), jnp.concatenate(flags).astype(jnp.int32)


def scene_arrays(structure: InstanceAccelerationStructure) -> SceneArrays:
    """Concatenate the components of ``structure`` into one global array set (traced; cheap next to a trace)."""
    prims, tables = structure.primitive_structures, structure.instance_tables
    p = len(prims)
    node_counts = [s.node_children.shape[0] for s in prims] + [t.node_children.shape[0] for t in tables]
    node_offset = np.concatenate([[0], np.cumsum(node_counts)]).astype(np.int64)
    leaf_counts = [s.capacity for s in prims]
    leaf_offset = np.concatenate([[0], np.cumsum(leaf_counts)]).astype(np.int64)
    primitive_leaves = int(leaf_offset[-1])
    instance_counts = [t.instance_slots for t in tables]
    instance_offset = np.concatenate([[0], np.cumsum(instance_counts)]).astype(np.int64)
    if node_offset[-1] + 1 >= 2**31 or primitive_leaves + instance_offset[-1] >= 2**31:
        raise ValueError("intersect: the scene has more than 2**31 nodes or leaves")

    children = []
    for i, s in enumerate(prims):
        c = s.node_children
        children.append(jnp.where(c >= 0, c + int(node_offset[i]), c - int(leaf_offset[i])))
    for j, t in enumerate(tables):
        c = t.node_children
        instance = t.leaf_instance[jnp.maximum(-1 - c, 0)]
        leaf = -1 - (primitive_leaves + int(instance_offset[j]) + jnp.maximum(instance, 0))
        children.append(jnp.where(c >= 0, c + int(node_offset[p + j]), leaf))

    child_root = []
    for j, t in enumerate(tables):
        refs = jnp.asarray(np.asarray(node_offset[list(structure.children[j])], np.int32))
        child_root.append(refs[jnp.clip(t.structure_index, 0, len(structure.children[j]) - 1)])
    transform = jnp.concatenate([t.transform for t in tables])
    linear = lax.stop_gradient(transform[:, :, :3])
    det = jnp.sum(linear[:, 0] * jnp.cross(linear[:, 1], linear[:, 2]), axis=-1)
    options = jnp.concatenate([t.options for t in tables])
    ccw = (options & InstanceOptions.TRIANGLE_FRONT_FACING_WINDING_COUNTERCLOCKWISE) != 0
    flip = jnp.where((det < 0) ^ ccw, -1, 1).astype(jnp.int32)
    cull = jnp.where((options & InstanceOptions.DISABLE_TRIANGLE_CULLING) != 0, 0, 1).astype(jnp.int32)
    leaf_curve, leaf_curve_flags = _leaf_curves(prims)
    return SceneArrays(
        node_lower=jnp.concatenate([s.node_lower for s in prims] + [t.node_lower for t in tables]),
        node_upper=jnp.concatenate([s.node_upper for s in prims] + [t.node_upper for t in tables]),
        node_children=jnp.concatenate(children).astype(jnp.int32),
        leaf_triangle=jnp.concatenate([s.leaf_triangle for s in prims]),
        leaf_geometry=jnp.concatenate([s.leaf_geometry for s in prims]),
        leaf_primitive=jnp.concatenate([s.leaf_primitive for s in prims]),
        transform=transform,
        world_to_object=jnp.concatenate([t.world_to_object for t in tables]),
        child_root=jnp.concatenate(child_root).astype(jnp.int32),
        mask=jnp.concatenate([t.mask for t in tables]),
        flip=flip,
        cull=cull,
        local_index=jnp.concatenate([jnp.arange(n, dtype=jnp.int32) for n in instance_counts]),
        user_id=jnp.concatenate([t.user_id for t in tables]),
        options=options,
        leaf_curve=leaf_curve,
        leaf_curve_flags=leaf_curve_flags,
        motion=_instance_motion(tables),
    )


def scene_root(structure: InstanceAccelerationStructure) -> int:
    """Global index of the root node of ``structure`` in :func:`scene_arrays`."""
    counts = [s.node_children.shape[0] for s in structure.primitive_structures]
    counts += [t.node_children.shape[0] for t in structure.instance_tables[:-1]]
    return int(sum(counts))


def primitive_leaf_count(structure: InstanceAccelerationStructure) -> int:
    """Number of primitive leaves in :func:`scene_arrays` (the start of the instance leaf range)."""
    return int(sum(s.capacity for s in structure.primitive_structures))
