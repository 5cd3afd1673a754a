"""Intersection with instance structures: the instancing tags, the instanced traversal, and the result fields.

The traversal picks the leaf and the instance chain of the nearest accepted hit (detached). The hit is then
recomputed in JAX with the chain's transforms. Triangles: the exact values (distance from the traversal,
barycentrics from the object-space ray) carry the gradients of a smooth world-space re-intersection of the
triangle with its vertices moved by the composed object-to-world transform. Curves are traced in object space
(as Metal, OptiX and Embree do): the segment is tested again with the object-space ray, computed level by
level as the traversal did, and its differentiable re-computation takes that ray as a function of the world
ray and the instance transforms. So distances, barycentrics, curve parameters and world-space transforms
differentiate with respect to instance transforms, vertices, control points, radii and rays, holding the hit
fixed.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
from jax import lax

from jaxrt._src import curves as curve_support
from jaxrt._src.instances import (
    InstanceAccelerationStructure,
    apply_transform,
    compose_transforms,
    invert_transform,
    primitive_leaf_count,
    scene_arrays,
    scene_root,
)
from jaxrt._src.primitives import triangle
from jaxrt._src.result import IntersectionResult, IntersectionType
from jaxrt._src.traversal import instanced

__all__ = ["max_levels", "check_levels", "check_tags", "intersect_instances", "primitive_instance_fields"]

#: Filler of ``user_instance_id`` past ``instance_count`` (and on misses).
NO_USER_ID = 0xFFFFFFFF


def max_levels(intersector: Any) -> int:
    """Instance levels the intersector handles: its ``max_levels(n)`` tag, 1 with ``instancing`` alone, else 0."""
    if not intersector.has("instancing"):
        return 0
    values = [t.value for t in intersector.tags if t.name == "max_levels"]
    return int(values[0]) if values else 1


def check_tags(tags: tuple) -> None:
    """Tags that only make sense with ``instancing`` raise without it."""
    names = {t.name for t in tags}
    levels = [t for t in tags if t.name == "max_levels"]
    if len(levels) > 1:
        raise ValueError(f"Intersector: give tags.max_levels once, got {[t.value for t in levels]}")
    if "instancing" not in names:
        for name in ("max_levels", "world_space_data", "user_instance_id"):
            if name in names:
                raise ValueError(f"Intersector: tags.{name} needs tags.instancing")


def check_levels(intersector: Any, structure: Any) -> None:
    """Raise when ``structure`` nests instances deeper than the intersector handles, naming both depths."""
    depth = structure.levels
    handled = max_levels(intersector)
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


class InstancedTriangleLeaves:
    """Watertight triangle tests in object space with a per-level facing (an ``InstancedLeafTester``)."""

    def __init__(self, leaf_triangle: jax.Array, cull: int):
        self.leaf_triangle = leaf_triangle
        self.cull = cull

    def prepare(self, origin, direction, facing):
        return triangle.shear_ray(origin, direction), facing * self.cull

    def __call__(self, context, leaves, t_min, t_max):
        sheared, cull = context
        hit = triangle.watertight(sheared, t_min, t_max, self.leaf_triangle[jnp.maximum(leaves, 0)], 0)
        accept = hit.hit & (leaves >= 0)
        if self.cull != 0:
            # +1 culls (object-space) clockwise triangles, -1 counterclockwise ones, 0 none.
            accept &= ~((cull > 0) & hit.clockwise) & ~((cull < 0) & ~hit.clockwise)
        return accept, hit.distance


def curve_config(intersector: Any, structure: InstanceAccelerationStructure) -> dict:
    """The static curve code choices for every curve geometry below ``structure`` (all levels share them)."""
    infos = tuple(g.curve for s in structure.primitive_structures for g in s.geometry_info if g.curve is not None)
    return curve_support.curve_configuration(infos, intersector.curve_type, intersector.curve_options)


def _leaf_tester(intersector: Any, structure: InstanceAccelerationStructure, scene: Any):
    """The triangle test, the curve test, or both selected per leaf: only the kinds below ``structure``."""
    detached = lax.stop_gradient
    triangles = InstancedTriangleLeaves(detached(scene.leaf_triangle), intersector._cull)
    if scene.leaf_curve is None:
        return triangles
    config = curve_config(intersector, structure)
    curves = curve_support.CurveLeaves(detached(scene.leaf_curve), scene.leaf_curve_flags, **config)
    kinds = {g.kind for s in structure.primitive_structures for g in s.geometry_info}
    return curve_support.MixedLeaves(triangles, curves) if "triangle" in kinds else curves


def _object_ray(origin: jax.Array, direction: jax.Array, to_object: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The ray ``(n, 3)`` in the space of the chain's last instance, moved level by level by ``to_object``
    ``(n, L, 3, 4)`` (identity past the chain) with the traversal's arithmetic, so that a re-test sees the
    ray the traversal tested."""
    for level in range(to_object.shape[1]):
        m = to_object[:, level]
        origin = jnp.sum(m[..., :3] * origin[:, None, :], axis=-1) + m[..., 3]
        direction = jnp.sum(m[..., :3] * direction[:, None, :], axis=-1)
    return origin, direction


def _pad_levels(values: jax.Array, n: int, fill) -> jax.Array:
    """``(rays, L)`` to ``(rays, n)`` with ``fill`` past ``L``."""
    extra = n - values.shape[1]
    if extra <= 0:
        return values
    return jnp.concatenate([values, jnp.full((values.shape[0], extra), fill, values.dtype)], axis=1)


def primitive_instance_fields(intersector: Any, hit: jax.Array, dtype) -> dict[str, jax.Array]:
    """Instancing fields for a primitive structure traced with ``instancing``: no instance on any hit."""
    n, levels = hit.shape[0], max_levels(intersector)
    fields = {
        "instance_id": jnp.full((n, levels), -1, jnp.int32),
        "instance_count": jnp.zeros((n,), jnp.int32),
        "user_instance_id": jnp.full((n, levels), NO_USER_ID, jnp.uint32),
    }
    if intersector.has("world_space_data"):
        identity = jnp.where(hit[:, None, None], jnp.eye(3, 4, dtype=dtype), 0.0)
        fields["object_to_world_transform"] = identity
        fields["world_to_object_transform"] = identity
    return fields


def _trace(intersector, structure, scene, origin, direction, t_min, t_max, enabled, mask):
    from jaxrt._src import intersector as core

    detached = lax.stop_gradient
    traversal_scene = instanced.InstancedScene(
        node_lower=detached(scene.node_lower),
        node_upper=detached(scene.node_upper),
        node_children=scene.node_children,
        instance_rows=instanced.pack_instances(
            detached(scene.world_to_object), scene.child_root, scene.flip * scene.cull
        ),
        mask=scene.mask,
    )
    leaves = _leaf_tester(intersector, structure, scene)
    options = dict(
        root=scene_root(structure),
        primitive_leaves=primitive_leaf_count(structure),
        levels=structure.levels,
        any_hit=intersector.accept_any_intersection,
        stack_size=structure.max_depth,
    )
    args = tuple(detached(a) for a in (origin, direction, t_min, t_max)) + (enabled, mask)
    if core.PORTABLE_DRIVER == "vmap":
        fn = jax.vmap(functools.partial(instanced.traverse, traversal_scene, leaves, **options))
        return core._chunked(fn, args, core.CPU_CHUNK)
    on_gpu = jax.default_backend() == "gpu"
    chunk, lanes = (core.GPU_CHUNK, core.GPU_REFILL_LANES) if on_gpu else (core.CPU_CHUNK, core.REFILL_LANES)
    split = jax.default_backend() == "cpu"
    fn = functools.partial(instanced.traverse_refill, traversal_scene, leaves, **options, lanes=lanes, split=split)
    return core._chunked(fn, args, chunk)


def intersect_instances(intersector: Any, rays: Any, structure: InstanceAccelerationStructure) -> IntersectionResult:
    """The result fields for a flat, padded ray batch ``(n,)`` and an instance structure (inside ``jit``)."""
    from jaxrt._src.intersector import _enabled

    enabled = _enabled(rays)
    unit_z = jnp.array([0.0, 0.0, 1.0], rays.direction.dtype)
    origin = jnp.where(enabled[:, None], rays.origin, 0.0)
    direction = jnp.where(enabled[:, None], rays.direction, unit_z)
    t_min = jnp.where(enabled, rays.min_distance, 0.0)
    t_max = jnp.where(enabled, rays.max_distance, 0.0)
    scene = scene_arrays(structure)
    found = _trace(intersector, structure, scene, origin, direction, t_min, t_max, enabled, rays.mask)

    detached = lax.stop_gradient
    dtype = origin.dtype
    any_hit = found.leaf >= 0
    leaf = jnp.maximum(found.leaf, 0)
    chain = jnp.where(any_hit[:, None], found.instances, -1)  # (n, L)
    valid = chain >= 0
    g = jnp.maximum(chain, 0)
    levels = chain.shape[1]

    identity = jnp.eye(3, 4, dtype=dtype)
    # The stored inverses (the values the traversal used), differentiated as the inverse of the transforms.
    inverse = invert_transform(scene.transform)
    world_to_object_rows = detached(scene.world_to_object) + (inverse - detached(inverse))
    to_world = jnp.where(valid[..., None, None], scene.transform[g], identity)  # (n, L, 3, 4)
    to_object = jnp.where(valid[..., None, None], world_to_object_rows[g], identity)
    object_to_world = jnp.broadcast_to(identity, (chain.shape[0], 3, 4))
    world_to_object = object_to_world
    for level in range(levels):
        object_to_world = compose_transforms(object_to_world, to_world[:, level])
        world_to_object = compose_transforms(to_object[:, level], world_to_object)
    curves = scene.leaf_curve is not None
    if curves or intersector.has("triangle_data"):
        object_origin, object_direction = _object_ray(origin, direction, to_object)

    hit = any_hit  # triangle hits
    if curves:  # curve hits: re-tested in object space; triangles take the rest
        is_curve, curve_t, curve_u = curve_support.curve_hit_fields(
            scene,
            leaf,
            any_hit,
            object_origin,
            object_direction,
            t_min,
            t_max,
            found.distance,
            curve_config(intersector, structure),
        )
        hit = any_hit & ~is_curve
    fields: dict[str, Any] = {
        "type": jnp.where(hit, int(IntersectionType.TRIANGLE), int(IntersectionType.NONE)).astype(jnp.int32),
        "distance": None,
        "primitive_id": jnp.where(any_hit, scene.leaf_primitive[leaf], -1),
        "geometry_id": jnp.where(any_hit, scene.leaf_geometry[leaf], -1),
    }

    # Re-intersect the chosen triangle: exact values from the traversal's object-space test, gradients from a
    # smooth test in world space with the vertices moved by the chain's composed transform.
    vertices = scene.leaf_triangle[leaf]
    world_vertices = jax.vmap(apply_transform)(object_to_world, vertices)
    dummy = jnp.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]], dtype)
    world_vertices = jnp.where(hit[:, None, None], world_vertices, dummy)
    smooth_origin = jnp.where(hit[:, None], origin, 0.0)
    smooth_direction = jnp.where(hit[:, None], direction, unit_z)
    smooth_t, smooth_u, smooth_v = jax.vmap(triangle.smooth_hit)(smooth_origin, smooth_direction, world_vertices)

    def attach(exact, smooth):
        return jnp.where(hit, detached(exact) + (smooth - detached(smooth)), 0.0)

    fields["distance"] = jnp.where(hit, attach(found.distance, smooth_t), jnp.inf)
    if intersector.has("triangle_data"):
        # The object-space ray as the traversal computed it, level by level.
        triangle_direction = jnp.where(hit[:, None], detached(object_direction), unit_z)
        sheared = jax.vmap(triangle.shear_ray)(detached(object_origin), triangle_direction)
        u, v, clockwise = jax.vmap(triangle.barycentrics)(sheared, detached(vertices))
        fields["triangle_barycentric_coord"] = jnp.stack([attach(u, smooth_u), attach(v, smooth_v)], axis=-1)
        flips = jnp.prod(jnp.where(valid, scene.flip[g], 1), axis=1)
        clockwise = clockwise ^ (flips < 0)
        front = clockwise if intersector.front_facing_winding == "clockwise" else ~clockwise
        fields["triangle_front_facing"] = hit & front
    if curves:
        fields["type"] = jnp.where(is_curve, int(IntersectionType.CURVE), fields["type"]).astype(jnp.int32)
        fields["distance"] = jnp.where(is_curve, curve_t, fields["distance"])
    if intersector.has("curve_data"):
        fields["curve_parameter"] = jnp.where(is_curve, curve_u, 0.0) if curves else jnp.zeros_like(found.distance)

    n_levels = max_levels(intersector)
    fields["instance_id"] = _pad_levels(jnp.where(valid, scene.local_index[g], -1), n_levels, -1)
    fields["instance_count"] = jnp.sum(valid, axis=1).astype(jnp.int32)
    user = jnp.where(valid, scene.user_id[g], jnp.uint32(NO_USER_ID)).astype(jnp.uint32)
    fields["user_instance_id"] = _pad_levels(user, n_levels, NO_USER_ID)
    if intersector.has("world_space_data"):
        fields["object_to_world_transform"] = jnp.where(any_hit[:, None, None], object_to_world, 0.0)
        fields["world_to_object_transform"] = jnp.where(any_hit[:, None, None], world_to_object, 0.0)
    if intersector.has("stats"):
        fields["nodes_visited"] = found.nodes_visited
        fields["primitives_tested"] = found.primitives_tested
        fields["stack_overflow"] = found.stack_overflow
    return IntersectionResult(fields)
