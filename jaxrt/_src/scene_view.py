"""One view of any structure for the traversals: a primitive structure is a scene with zero instance levels.

:func:`traversal_scene` gives the :class:`~jaxrt._src.traversal.scene.TraversalScene` (global node arrays) and
the static :class:`~jaxrt._src.traversal.scene.TraversalLayout` of a primitive or instance structure; the
portable traversal and the GPU kernel both read these and nothing else of the structure's BVH.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxrt._src.instances import InstanceAccelerationStructure, primitive_leaf_count, scene_arrays, scene_root
from jaxrt._src.structures import PrimitiveAccelerationStructure
from jaxrt._src.traversal.scene import TraversalLayout, TraversalScene

__all__ = ["traversal_scene"]


def traversal_scene(
    structure: PrimitiveAccelerationStructure | InstanceAccelerationStructure,
) -> tuple[TraversalScene, TraversalLayout]:
    """The global node arrays of ``structure`` and their static layout (inside or outside ``jit``)."""
    if isinstance(structure, InstanceAccelerationStructure):
        scene = scene_arrays(structure)
        view = TraversalScene(
            node_lower=scene.node_lower,
            node_upper=scene.node_upper,
            node_children=scene.node_children,
            leaf_triangle=scene.leaf_triangle,
            instance_world_to_object=scene.world_to_object,
            instance_child_root=scene.child_root,
            instance_facing=(scene.flip * scene.cull).astype(jnp.int32),
            instance_mask=scene.mask,
        )
        layout = TraversalLayout(
            root=scene_root(structure),
            primitive_leaves=primitive_leaf_count(structure),
            levels=structure.levels,
            stack_size=structure.max_depth,
        )
        return view, layout
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
    )
    layout = TraversalLayout(root=0, primitive_leaves=structure.capacity, levels=0, stack_size=structure.max_depth)
    return view, layout
