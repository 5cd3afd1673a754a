"""One view of any structure for the traversal and the result: a primitive structure is a scene with zero
instance levels.

:func:`scene_view` gives, for a primitive or an instance structure, the
:class:`~jaxrt._src.traversal.scene.TraversalScene` (global node arrays) and its static
:class:`~jaxrt._src.traversal.scene.TraversalLayout`, which the portable traversal and the GPU kernel read,
and the global leaf and instance arrays, which the leaf tests and the result assembly read. Global geometry
*slots* number the geometries of every primitive structure below the root one after another, so that static
per-geometry facts (kind, opacity) are one table lookup per leaf; hits still report the geometry's index
within its own structure.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt._src.bvh.boxes import empty_box
from jaxrt._src.instances import InstanceAccelerationStructure, primitive_leaf_count, scene_arrays, scene_root
from jaxrt._src.motion import KeyframePosition, LeafKeys, MotionSpec, spec_position
from jaxrt._src.structures import GeometryInfo, PrimitiveAccelerationStructure
from jaxrt._src.traversal.scene import TraversalLayout, TraversalScene

__all__ = [
    "InstanceArrays",
    "LeafArrays",
    "LeafMotion",
    "SceneView",
    "primitive_structures",
    "scene_view",
    "traversal_scene",
]


@dataclasses.dataclass(frozen=True)
class LeafArrays:
    """Per primitive leaf of the scene (global leaf index), as laid out in :mod:`jaxrt._src.structures`."""

    triangle: jax.Array  # (P, 3, 3) object space
    geometry: jax.Array  # (P,) geometry index within its structure; -1 for padding
    primitive: jax.Array  # (P,) primitive index within its geometry; -1 for padding
    slot: jax.Array  # (P,) global geometry slot; -1 for padding
    curve: jax.Array | None = None  # (P, 6, 4) packed segments, with curves only
    curve_flags: jax.Array | None = None  # (P,) int32
    box: jax.Array | None = None  # (P, 2, 3), with bounding-box geometry only
    primitive_data: Any = None  # pytree of (P, ...) leaves, with primitive data only
    motion: LeafMotion | None = None  # keyframes of moving primitives, with primitive motion only


@dataclasses.dataclass(frozen=True)
class LeafMotion:
    """The leaf arrays per keyframe ``(K, P, ...)`` of a scene with primitive motion (one spec for the scene;
    leaves of static structures repeat their rows)."""

    spec: MotionSpec
    triangle: jax.Array  # (K, P, 3, 3)
    curve: jax.Array | None = None  # (K, P, 6, 4)
    box: jax.Array | None = None  # (K, P, 2, 3)

    @property
    def keyframe_count(self) -> int:
        return int(self.triangle.shape[0])


@dataclasses.dataclass(frozen=True)
class InstanceArrays:
    """Per global instance of the scene: what the result fields read."""

    transform: jax.Array  # (G, 3, 4) object-to-world
    world_to_object: jax.Array  # (G, 3, 4)
    flip: jax.Array  # (G,) int32: -1 flips the winding, else +1
    local_index: jax.Array  # (G,) index of the instance within its structure
    user_id: jax.Array  # (G,) uint32
    options: jax.Array  # (G,) uint32 InstanceOptions bits
    motion: Any = None  # keyframed transforms (:class:`~jaxrt._src.instances.InstanceMotion`), or None


@dataclasses.dataclass(frozen=True)
class SceneView:
    """A structure seen by the engine (built inside ``jit``; not a pytree)."""

    traversal: TraversalScene
    layout: TraversalLayout
    leaves: LeafArrays
    geometry_info: tuple[GeometryInfo, ...]  # per global geometry slot (static)
    instances: InstanceArrays | None = None  # None for a primitive structure

    @property
    def kinds(self) -> frozenset[str]:
        """The geometry kinds present in the scene."""
        return frozenset(g.kind for g in self.geometry_info)

    @property
    def levels(self) -> int:
        """Instance levels of the scene (0 for a primitive structure)."""
        return self.layout.levels

    def slots_where(self, predicate) -> tuple[int, ...]:
        """Global geometry slots whose :class:`GeometryInfo` satisfies ``predicate``."""
        return tuple(i for i, g in enumerate(self.geometry_info) if predicate(g))

    def slot_table(self, slots: tuple[int, ...]) -> jax.Array:
        """A bool lookup table over global geometry slots, True at ``slots``; a last row stands for padding."""
        table = np.zeros(len(self.geometry_info) + 1, bool)
        table[list(slots)] = True
        return jnp.asarray(table)

    def leaf_flag(self, table: jax.Array, leaves: jax.Array) -> jax.Array:
        """``table``'s entry for the geometry slot of each leaf (padding leaves read the padding row)."""
        slot = self.leaves.slot[jnp.maximum(leaves, 0)]
        return table[jnp.where(slot < 0, table.shape[0] - 1, slot)]

    def keyframe_position(self, time: jax.Array) -> KeyframePosition:
        """Where ``time`` falls among the keyframes of the scene's primitive motion."""
        motion = self.leaves.motion
        return spec_position(motion.spec, motion.keyframe_count, time)

    def at(self, position: KeyframePosition) -> SceneView:
        """The view whose leaf triangles, curves and boxes are the keyframes blended at ``position``
        (:class:`~jaxrt._src.motion.LeafKeys`, indexed like the static arrays); ``self`` without motion."""
        motion = self.leaves.motion
        if motion is None:
            return self
        keys = lambda a: None if a is None else LeafKeys(a, position)  # noqa: E731
        leaves = dataclasses.replace(
            self.leaves, triangle=keys(motion.triangle), curve=keys(motion.curve), box=keys(motion.box)
        )
        return dataclasses.replace(self, leaves=leaves)


def primitive_structures(structure: Any) -> tuple[PrimitiveAccelerationStructure, ...]:
    """The distinct primitive structures of a scene (the structure itself for a primitive structure)."""
    if isinstance(structure, InstanceAccelerationStructure):
        return tuple(structure.primitive_structures)
    return (structure,)


def _concatenate_data(prims: tuple[PrimitiveAccelerationStructure, ...]) -> Any:
    """Every structure's per-leaf primitive data, concatenated (zeros for structures without data)."""
    with_data = [s.leaf_primitive_data for s in prims if s.leaf_primitive_data is not None]
    if not with_data:
        return None
    layout = jax.tree_util.tree_map(lambda a: (a.shape[1:], a.dtype), with_data[0])
    for data in with_data[1:]:
        if jax.tree_util.tree_map(lambda a: (a.shape[1:], a.dtype), data) != layout:
            raise ValueError(
                "Intersector.intersect: the primitive structures below the instance structure carry primitive_data "
                "of different layouts; tags.primitive_data needs one layout for the whole scene"
            )
    parts = []
    for s in prims:
        if s.leaf_primitive_data is not None:
            parts.append(s.leaf_primitive_data)
        else:
            parts.append(
                jax.tree_util.tree_map(lambda a, n=s.capacity: jnp.zeros((n, *a.shape[1:]), a.dtype), with_data[0])
            )
    return jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *parts)


def _leaf_boxes(prims: tuple[PrimitiveAccelerationStructure, ...]) -> jax.Array | None:
    """Every structure's box leaves, concatenated (empty boxes for structures without boxes)."""
    with_boxes = [s.leaf_box for s in prims if s.leaf_box is not None]
    if not with_boxes:
        return None
    dtype = with_boxes[0].dtype
    parts = [s.leaf_box if s.leaf_box is not None else jnp.stack(empty_box(s.capacity, dtype), axis=1) for s in prims]
    return jnp.concatenate(parts)


def _leaf_motion(prims: tuple[PrimitiveAccelerationStructure, ...]) -> LeafMotion | None:
    """The keyframe leaf arrays of every structure, concatenated (``None`` when no structure moves)."""
    moving = [s for s in prims if s.motion is not None]
    if not moving:
        return None
    specs = {s.motion for s in moving}
    counts = {s.keyframe_count for s in moving}
    if len(specs) > 1 or len(counts) > 1:
        raise ValueError(
            "Intersector.intersect: the primitive structures with motion below the instance structure have "
            f"different motion specs {sorted(map(str, specs))} or keyframe counts {sorted(counts)}; one scene "
            "takes one spec and keyframe count for its primitive motion"
        )
    k = counts.pop()

    def stacked(name: str, keyed: str, empty) -> jax.Array | None:
        if all(getattr(s, name) is None for s in prims):
            return None
        parts = []
        for s in prims:
            if getattr(s, keyed) is not None:
                parts.append(getattr(s, keyed))
            else:
                static = getattr(s, name)
                static = empty(s) if static is None else static
                parts.append(jnp.broadcast_to(static, (k, *static.shape)))
        return jnp.concatenate(parts, axis=1)

    dtype = moving[0].leaf_triangle.dtype
    return LeafMotion(
        spec=specs.pop(),
        triangle=stacked("leaf_triangle", "motion_triangle", None),
        curve=stacked("leaf_curve", "motion_curve", lambda s: jnp.zeros((s.capacity, 6, 4), dtype)),
        box=stacked("leaf_box", "motion_box", lambda s: jnp.stack(empty_box(s.capacity, dtype), axis=1)),
    )


def _slots(prims: tuple[PrimitiveAccelerationStructure, ...]) -> jax.Array:
    offsets = np.concatenate([[0], np.cumsum([len(s.geometry_info) for s in prims])])
    return jnp.concatenate(
        [jnp.where(s.leaf_geometry >= 0, s.leaf_geometry + int(o), -1) for s, o in zip(prims, offsets, strict=False)]
    ).astype(jnp.int32)


def scene_view(structure: PrimitiveAccelerationStructure | InstanceAccelerationStructure) -> SceneView:
    """The engine's view of ``structure`` (inside or outside ``jit``)."""
    if not isinstance(structure, InstanceAccelerationStructure):
        traversal, layout = _primitive_traversal(structure)
        leaves = LeafArrays(
            triangle=structure.leaf_triangle,
            geometry=structure.leaf_geometry,
            primitive=structure.leaf_primitive,
            slot=structure.leaf_geometry,
            curve=structure.leaf_curve,
            curve_flags=structure.leaf_curve_flags,
            box=structure.leaf_box,
            primitive_data=structure.leaf_primitive_data,
            motion=_leaf_motion((structure,)),
        )
        return SceneView(traversal, layout, leaves, structure.geometry_info)
    prims = primitive_structures(structure)
    scene = scene_arrays(structure)
    traversal, layout = _instanced_traversal(structure, scene)
    leaves = LeafArrays(
        triangle=scene.leaf_triangle,
        geometry=scene.leaf_geometry,
        primitive=scene.leaf_primitive,
        slot=_slots(prims),
        curve=scene.leaf_curve,
        curve_flags=scene.leaf_curve_flags,
        box=_leaf_boxes(prims),
        primitive_data=_concatenate_data(prims),
        motion=_leaf_motion(prims),
    )
    instances = InstanceArrays(
        transform=scene.transform,
        world_to_object=scene.world_to_object,
        flip=scene.flip,
        local_index=scene.local_index,
        user_id=scene.user_id,
        options=scene.options,
        motion=scene.motion,
    )
    infos = tuple(g for s in prims for g in s.geometry_info)
    return SceneView(traversal, layout, leaves, infos, instances)


def _primitive_traversal(structure: PrimitiveAccelerationStructure) -> tuple[TraversalScene, TraversalLayout]:
    dtype = structure.node_lower.dtype
    view = TraversalScene(
        node_lower=structure.node_lower,
        node_upper=structure.node_upper,
        node_children=structure.node_children,
        leaf_triangle=structure.leaf_triangle,
        instance_world_to_object=jnp.zeros((0, 3, 4), dtype),
        instance_child_root=jnp.zeros((0,), jnp.int32),
        instance_facing=jnp.zeros((0,), jnp.int32),
        instance_mask=jnp.zeros((0,), jnp.uint32),
        node_range=structure.node_range,
        node_motion=None
        if structure.motion_node_lower is None
        else (structure.motion_node_lower, structure.motion_node_upper),
        kernel_layout=structure.kernel_layout,
    )
    layout = TraversalLayout(
        root=0,
        primitive_leaves=structure.capacity,
        levels=0,
        stack_size=structure.max_depth,
        motion=structure.motion is not None,
        node_spec=structure.motion if structure.motion_node_lower is not None else None,
    )
    return view, layout


def _instanced_traversal(structure: InstanceAccelerationStructure, scene) -> tuple[TraversalScene, TraversalLayout]:
    view = TraversalScene(
        node_lower=scene.node_lower,
        node_upper=scene.node_upper,
        node_children=scene.node_children,
        leaf_triangle=scene.leaf_triangle,
        instance_world_to_object=scene.world_to_object,
        instance_child_root=scene.child_root,
        instance_facing=(scene.flip * scene.cull).astype(jnp.int32),
        instance_mask=scene.mask,
        instance_motion=scene.motion,
    )
    layout = TraversalLayout(
        root=scene_root(structure),
        primitive_leaves=primitive_leaf_count(structure),
        levels=structure.levels,
        stack_size=structure.max_depth,
        motion=any(s.motion is not None for s in structure.primitive_structures) or structure.has_instance_motion,
    )
    return view, layout


def traversal_scene(
    structure: PrimitiveAccelerationStructure | InstanceAccelerationStructure,
) -> tuple[TraversalScene, TraversalLayout]:
    """The global node arrays of ``structure`` and their static layout (inside or outside ``jit``)."""
    view = scene_view(structure)
    return view.traversal, view.layout
