"""What every traversal reads of a scene: one set of global node arrays for any structure.

A primitive structure is a scene with zero instance levels; an instance structure is the concatenation of
the node arrays of every distinct structure below it (built by :mod:`jaxrt._src.scene_view`). The portable
traversal (:mod:`jaxrt._src.traversal.step`) and the GPU kernel (:mod:`jaxrt._src.traversal.gpu`) both take a
:class:`TraversalScene` and a static :class:`TraversalLayout`, and both return a :class:`TraversalResult`, so
they are interchangeable behind the intersector.

Node encoding (global indices): ``node_children[i, j] >= 0`` is an internal node; ``-1 - k`` is leaf ``k``,
a primitive leaf when ``k < primitive_leaves`` (its triangle is ``leaf_triangle[k]``), else instance
``k - primitive_leaves``. Entering instance ``g`` moves the ray by ``instance_world_to_object[g]`` (the
direction is not normalised, so distances stay in world units at every level) and continues at node
``instance_child_root[g]``. An instance is visible to a ray when ``instance_mask[g] & ray_mask != 0``;
``instance_facing[g]`` in {-1, 0, +1} flips (mirroring transforms, the counterclockwise option) or disables
(the no-culling option) triangle culling below it; the facing of a level is the product along the chain.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax

__all__ = ["TraversalScene", "TraversalLayout", "TraversalRays", "TraversalResult"]


class TraversalScene(NamedTuple):
    """The arrays a traversal reads (see the module docstring for the encoding)."""

    node_lower: jax.Array  # (M, 2, 3) float: lower corners of both children of each internal node
    node_upper: jax.Array  # (M, 2, 3) float: upper corners; an empty child is (+inf, -inf)
    node_children: jax.Array  # (M, 2) int32
    leaf_triangle: jax.Array  # (P, 3, 3) float: triangle of each primitive leaf (zeros for other kinds)
    instance_world_to_object: jax.Array  # (G, 3, 4) float; G = 0 without instances
    instance_child_root: jax.Array  # (G,) int32
    instance_facing: jax.Array  # (G,) int32 in {-1, 0, 1}
    instance_mask: jax.Array  # (G,) uint32
    node_range: jax.Array | None = None  # (M, 2) int32 leaf range per node (zero levels only; wide layouts)
    instance_motion: Any = None  # keyframed transforms (:class:`~jaxrt._src.instances.InstanceMotion`), or None
    node_motion: Any = None  # zero levels with primitive motion: (lower, upper) node boxes per keyframe (K, M, 2, 3)
    kernel_layout: Any = None  # zero levels: the GPU kernel's rows packed at build time (KernelLayout), or None


class TraversalLayout(NamedTuple):
    """Static facts about a scene that shape the compiled traversal (hashable)."""

    root: int  # global index of the root node
    primitive_leaves: int  # P: leaves below it are primitives, the rest instances
    levels: int  # instance levels (0: a primitive structure)
    stack_size: int  # entries of the traversal stack that can never overflow (see :func:`~jaxrt._src.bvh.radix_tree.tree_depth_bound`)
    motion: bool = False  # keyframe motion (primitives or instances): the traversal reads each ray's time
    node_spec: Any = None  # with ``node_motion``: the MotionSpec whose keyframes the node boxes follow


class TraversalRays(NamedTuple):
    """A flat batch of rays as the traversals read it (batch axis first), built once below the public
    ``rt.Ray`` (:func:`jaxrt._src.pipeline.sanitized_rays`): a disabled ray holds harmless values (origin 0,
    direction +z, interval [0, 0]) and is skipped."""

    origin: jax.Array  # (N, 3) world space
    direction: jax.Array  # (N, 3), never zero
    t_min: jax.Array  # (N,) accepted distance interval
    t_max: jax.Array  # (N,)
    enabled: jax.Array  # (N,) bool: finite, non-zero direction, t_min <= t_max, mask not 0
    mask: jax.Array  # (N,) uint32 ray mask
    time: jax.Array  # (N,) read only by scenes with keyframe motion


class TraversalResult(NamedTuple):
    """What a traversal found for each ray (batch axis first)."""

    distance: jax.Array  # hit distance; the initial bound (t_max, or -inf for a disabled ray) on a miss
    leaf: jax.Array  # global primitive leaf, -1 on a miss
    instances: jax.Array  # (levels,) global instance ids of the hit's chain, outermost first, -1 past it
    nodes_visited: jax.Array
    primitives_tested: jax.Array
    stack_overflow: jax.Array
    hits: Any = None  # with ``max_hits``: a :class:`~jaxrt._src.traversal.step.HitList`
    # ``(u, part)``: the curve parameter and ``PART_*`` code of each ray's ``leaf`` where it is a curve, from
    # the exact curve test in the ray's interval, where the traversal computed them (the CPU traversal), else
    # ``None`` (the result fields then test the leaf again)
    curve: Any = None
