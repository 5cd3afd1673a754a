"""Result assembly: the fields the intersector's tags ask for, from the leaf and instance chain a traversal found.

The traversal only picks the hit (detached). The chosen primitive is then intersected again in JAX, with the
ray moved into the hit's object space level by level as the traversal did: exact values come from the test
the traversal ran, gradients from a smooth formula (triangles: a world-space re-intersection with the vertices
moved by the chain's composed object-to-world transform), the curve's smooth hit, the user's intersection
function called again, or the test of a kind with ``formula_leaves`` (spheres) run again. So distances,
barycentrics, curve parameters, box distances, normals and world-space transforms differentiate with respect to
vertices, control points, sphere centres, radii, instance transforms and rays, holding the hit fixed. A scene
without instances compiles none of the transform code.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
from jax import lax

from jaxrt._src import curves as curve_support
from jaxrt._src import leaves as leaf_tests
from jaxrt._src import normals as hit_normals
from jaxrt._src.kinds.registry import BOUNDING_BOX, CURVE, KINDS
from jaxrt._src.primitive_data import data_at
from jaxrt._src.primitives import curve as primitive
from jaxrt._src.primitives import triangle
from jaxrt._src.result import IntersectionType
from jaxrt._src.scene_view import SceneView
from jaxrt._src.transforms import apply_transform, compose_transforms, instance_motion_at, invert_transform

__all__ = ["NO_USER_ID", "hit_fields"]

#: Filler of ``user_instance_id`` past ``instance_count`` (and on misses).
NO_USER_ID = 0xFFFFFFFF


class _Chain:
    """The composed transforms of each hit's instance chain, and the ray in the hit's object space."""

    def __init__(
        self,
        view: SceneView,
        chain: jax.Array,
        found: jax.Array,
        origin: jax.Array,
        direction: jax.Array,
        time: jax.Array | None = None,
    ):
        detached = lax.stop_gradient
        instances = view.instances
        dtype = origin.dtype
        chain = jnp.where(found[:, None], chain, -1)  # (n, L)
        self.valid = chain >= 0
        self.g = jnp.maximum(chain, 0)
        identity = jnp.eye(3, 4, dtype=dtype)
        # The stored inverses (the values the traversal used), differentiated as the inverse of the transforms.
        inverse = invert_transform(instances.transform)
        world_to_object_rows = detached(instances.world_to_object) + (inverse - detached(inverse))
        to_world, to_object = instances.transform[self.g], world_to_object_rows[self.g]
        if instances.motion is not None and time is not None:  # moving instances: blended at the ray's time
            moved, inverse, _, moving = instance_motion_at(instances.motion, self.g, time[:, None])
            to_world = jnp.where(moving[..., None, None], moved, to_world)
            to_object = jnp.where(moving[..., None, None], inverse, to_object)
        to_world = jnp.where(self.valid[..., None, None], to_world, identity)  # (n, L, 3, 4)
        to_object = jnp.where(self.valid[..., None, None], to_object, identity)
        object_to_world = jnp.broadcast_to(identity, (chain.shape[0], 3, 4))
        world_to_object = object_to_world
        for level in range(chain.shape[1]):
            object_to_world = compose_transforms(object_to_world, to_world[:, level])
            world_to_object = compose_transforms(to_object[:, level], world_to_object)
        self.object_to_world = object_to_world
        self.world_to_object = world_to_object
        # The ray as the traversal moved it, level by level (the same arithmetic, so a re-test sees its ray).
        for level in range(chain.shape[1]):
            m = to_object[:, level]
            origin = jnp.sum(m[..., :3] * origin[:, None, :], axis=-1) + m[..., 3]
            direction = jnp.sum(m[..., :3] * direction[:, None, :], axis=-1)
        self.origin, self.direction = origin, direction


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _with_smooth_tangent(which: int, exact, origin, direction, vertices):
    """``exact`` (the traversal's value), differentiated as output ``which`` (distance, u, v) of the smooth
    re-intersection :func:`~jaxrt._src.primitives.triangle.smooth_hit` of the rays with the triangles.

    The smooth formula runs only where a derivative is taken: a plain call reads no vertices for it.
    """
    return exact


@_with_smooth_tangent.defjvp
def _with_smooth_tangent_jvp(which, primals, tangents):
    exact, origin, direction, vertices = primals
    _, d_origin, d_direction, d_vertices = tangents
    smooth = jax.vmap(triangle.smooth_hit)
    _, tangent = jax.jvp(smooth, (origin, direction, vertices), (d_origin, d_direction, d_vertices))
    return exact, tangent[which]


def _pad_levels(values: jax.Array, n: int, fill) -> jax.Array:
    """``(rays, L)`` to ``(rays, n)`` with ``fill`` past ``L``."""
    extra = n - values.shape[1]
    if extra <= 0:
        return values
    return jnp.concatenate([values, jnp.full((values.shape[0], extra), fill, values.dtype)], axis=1)


def _instance_fields(intersector: Any, view: SceneView, chain: _Chain | None, found: jax.Array, dtype) -> dict:
    """``instance_id``, ``instance_count``, ``user_instance_id`` and the world-space transforms."""
    n, levels = found.shape[0], intersector.max_levels
    if chain is None:
        fields = {
            "instance_id": jnp.full((n, levels), -1, jnp.int32),
            "instance_count": jnp.zeros((n,), jnp.int32),
            "user_instance_id": jnp.full((n, levels), NO_USER_ID, jnp.uint32),
        }
        identity = jnp.where(found[:, None, None], jnp.eye(3, 4, dtype=dtype), 0.0)
        to_world = to_object = identity
    else:
        instances = view.instances
        fields = {
            "instance_id": _pad_levels(jnp.where(chain.valid, instances.local_index[chain.g], -1), levels, -1),
            "instance_count": jnp.sum(chain.valid, axis=1).astype(jnp.int32),
            "user_instance_id": _pad_levels(
                jnp.where(chain.valid, instances.user_id[chain.g], jnp.uint32(NO_USER_ID)).astype(jnp.uint32),
                levels,
                NO_USER_ID,
            ),
        }
        to_world = jnp.where(found[:, None, None], chain.object_to_world, 0.0)
        to_object = jnp.where(found[:, None, None], chain.world_to_object, 0.0)
    if intersector.has("world_space_data"):
        fields["object_to_world_transform"] = to_world
        fields["world_to_object_transform"] = to_object
    return fields


def _box_distance(intersector, view, leaf, is_box, origin, direction, t_min, t_max, distance):
    """Box hit distances: the traversal's value, with the gradient of the function called again on the box.

    The call again sees the ray's own interval (the nearest accepted root of this box is the one found): with
    the found distance as ``max_distance``, a recomputation an ulp larger (other FMA contractions in another
    program) would be rejected and lose the gradient.
    """
    detached = lax.stop_gradient
    # Lanes without a box hit call the function with a harmless ray (no NaN in their zero gradients).
    ray_origin = jnp.where(is_box[:, None], origin, 0.0)
    ray_direction = jnp.where(is_box[:, None], direction, jnp.array([0.0, 0.0, 1.0], direction.dtype))
    t_max = jnp.where(is_box, detached(t_max), 1.0)

    boxes = view.leaves.box[leaf]  # gathered per ray: a moving box is blended at each ray's time

    def one(o, d, lo, hi, k, box):
        ray = leaf_tests.function_ray(o, d, lo, hi)
        candidate = leaf_tests.box_candidate(view, k, box=box)
        return leaf_tests.call_function(intersector.intersection_functions, ray, candidate)

    accept, smooth = jax.vmap(one)(ray_origin, ray_direction, jnp.where(is_box, t_min, 0.0), t_max, leaf, boxes)
    attached = detached(distance) + jnp.where(accept, smooth - detached(smooth), 0.0)
    return jnp.where(is_box, attached, jnp.inf)


def _formula_hits(kind, rows, mine, origin, direction, t_min, t_max, distance):
    """Hits of a ``formula_leaves`` kind (spheres): ``(distance, front, normal)``, the traversal's distance with
    the gradient of the kind's test run again (in object space, on the ray's own interval, so it takes the same
    root); ``normal`` the kind's object-space normal at that distance (unnormalised). Other lanes test the
    kind's dummy row and ray (no NaN in their zero gradients)."""
    detached = lax.stop_gradient
    dummy_row, dummy_origin, dummy_direction = kind.dummy(rows.dtype)
    rows = jnp.where(mine.reshape(mine.shape + (1,) * (rows.ndim - 1)), rows, dummy_row)
    origin = jnp.where(mine[:, None], origin, dummy_origin)
    direction = jnp.where(mine[:, None], direction, dummy_direction)
    lo = jnp.where(mine, t_min, 0.0)
    hi = jnp.where(mine, detached(t_max), jnp.inf)
    accept, smooth, front = kind.reintersect(origin, direction, lo, hi, rows)
    smooth = jnp.where(accept, smooth, 1.0)
    attached = detached(distance) + jnp.where(accept, smooth - detached(smooth), 0.0)
    normal = kind.normal(origin, direction, jnp.where(mine, attached, 1.0), rows)
    return jnp.where(mine, attached, jnp.inf), mine & detached(front), normal


def hit_fields(
    intersector: Any,
    view: SceneView,
    origin: jax.Array,
    direction: jax.Array,
    t_min: jax.Array,
    t_max: jax.Array,
    leaf: jax.Array,
    distance: jax.Array,
    chain: jax.Array,
    *,
    time: jax.Array | None = None,
    curve: Any = None,
) -> dict[str, Any]:
    """The hit fields of rays ``(n,)`` whose traversal found ``leaf`` (``-1``: a miss) at ``distance`` through
    the instance ``chain`` ``(n, levels)``; ``time`` ``(n,)`` with keyframe motion: moving primitives are
    re-intersected as blended at each ray's time (differentiable in the keyframes and the time); ``curve``:
    the traversal's exact ``(u, part)`` of curve hits (:class:`~jaxrt._src.traversal.scene.TraversalResult`),
    or ``None`` to test them again here."""
    if time is not None and view.leaves.motion is not None:
        view = view.at(view.keyframe_position(time))

    detached = lax.stop_gradient
    dtype = origin.dtype
    unit_z = jnp.array([0.0, 0.0, 1.0], dtype)
    found = leaf >= 0
    leaf = jnp.maximum(leaf, 0)
    leaves = view.leaves
    transforms = _Chain(view, chain, found, origin, direction, time) if view.levels else None
    object_origin, object_direction = (transforms.origin, transforms.direction) if transforms else (origin, direction)
    kinds = view.kinds
    hit = found  # triangle hits, once the other kinds are taken out
    kind = jnp.full(found.shape, int(IntersectionType.NONE), jnp.int32)
    exact_distance = jnp.full(found.shape, jnp.inf, dtype)
    if CURVE.name in kinds:  # curve hits: re-tested (in object space) differentiably
        config = leaf_tests.curve_configuration(intersector, view)
        is_curve, curve_t, curve_u, curve_part = curve_support.curve_hit_fields(
            leaves.curve, leaves.curve_flags, leaf, hit, object_origin, object_direction, t_min, t_max, distance, config,
            exact=curve,
        )  # fmt: skip
        hit = hit & ~is_curve
        kind = jnp.where(is_curve, int(IntersectionType.CURVE), kind)
        exact_distance = jnp.where(is_curve, curve_t, exact_distance)
    if BOUNDING_BOX.name in kinds:
        is_box = found & view.leaf_flag(view.slot_table(leaf_tests.box_slots(view)), leaf)
        box_t = _box_distance(intersector, view, leaf, is_box, object_origin, object_direction, t_min, t_max, distance)
        hit = hit & ~is_box
        kind = jnp.where(is_box, int(IntersectionType.BOUNDING_BOX), kind)
        exact_distance = jnp.where(is_box, box_t, exact_distance)
    formula_hits = {}  # the formula kinds' hits (spheres): re-tested (in object space) differentiably
    for formula_kind in KINDS:
        if formula_kind.formula_leaves and formula_kind.name in kinds:
            mine = found & view.leaf_flag(view.slot_table(view.slots_where(formula_kind.holds)), leaf)
            rows = leaf_tests.formula_rows(formula_kind, view)[leaf]
            kind_t, front, kind_normal = _formula_hits(
                formula_kind, rows, mine, object_origin, object_direction, t_min, t_max, distance
            )
            formula_hits[formula_kind] = (mine, front, kind_normal)
            hit = hit & ~mine
            kind = jnp.where(mine, formula_kind.intersection_type, kind)
            exact_distance = jnp.where(mine, kind_t, exact_distance)
    kind = jnp.where(hit, int(IntersectionType.TRIANGLE), kind)

    # Re-intersect the chosen triangle: exact values from the watertight test (in object space), gradients from
    # a smooth world-space one with the vertices moved by the chain's composed transform.
    vertices = leaves.triangle[leaf]
    world_vertices = jax.vmap(apply_transform)(transforms.object_to_world, vertices) if transforms else vertices
    dummy = jnp.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]], dtype)
    world_vertices = jnp.where(hit[:, None, None], world_vertices, dummy)
    # Misses also get a dummy ray: with their own (finite but possibly huge) origin the smooth formula can
    # overflow, and its zero cotangent times inf would be a NaN gradient.
    smooth_origin = jnp.where(hit[:, None], origin, 0.0)
    smooth_direction = jnp.where(hit[:, None], direction, unit_z)

    def attach(exact, which):
        value = _with_smooth_tangent(which, detached(exact), smooth_origin, smooth_direction, world_vertices)
        return jnp.where(hit, value, 0.0)

    # A primitive structure of one geometry: every real leaf is geometry 0 (no gather per ray).
    one_geometry = view.levels == 0 and len(view.geometry_info) == 1
    fields: dict[str, Any] = {
        "type": kind,
        "distance": jnp.where(hit, attach(distance, 0), exact_distance),
        "primitive_id": jnp.where(found, leaves.primitive[leaf], -1),
        "geometry_id": jnp.where(found, jnp.int32(0) if one_geometry else leaves.geometry[leaf], jnp.int32(-1)),
    }
    if intersector.has("triangle_data"):
        triangle_direction = jnp.where(hit[:, None], detached(object_direction), unit_z)
        sheared = jax.vmap(triangle.shear_ray)(detached(object_origin), triangle_direction)
        u, v, clockwise = jax.vmap(triangle.barycentrics)(sheared, detached(vertices))
        fields["triangle_barycentric_coord"] = jnp.stack([attach(u, 1), attach(v, 2)], axis=-1)
        if transforms is not None:
            flips = jnp.prod(jnp.where(transforms.valid, view.instances.flip[transforms.g], 1), axis=1)
            clockwise = clockwise ^ (flips < 0)
        front = clockwise if intersector.front_facing_winding == "clockwise" else ~clockwise
        fields["triangle_front_facing"] = hit & front
    if intersector.has("curve_data"):
        fields["curve_parameter"] = (
            jnp.where(is_curve, curve_u, 0.0) if CURVE.name in kinds else jnp.zeros_like(distance)
        )
    for formula_kind in KINDS:
        if formula_kind.front_field is not None and intersector.has(formula_kind.fields[formula_kind.front_field]):
            kind_hits = formula_hits.get(formula_kind)
            fields[formula_kind.front_field] = kind_hits[1] if kind_hits else jnp.zeros(found.shape, bool)
    if intersector.has("primitive_data"):
        fields["primitive_data"] = data_at(leaves.primitive_data, leaf, found)
    if intersector.has("instancing"):
        fields.update(_instance_fields(intersector, view, transforms, found, dtype))
    if intersector.has("normal"):
        # Triangles: the object-space face normal of the (differentiable) vertices; dummy ones elsewhere.
        object_vertices = jnp.where(hit[:, None, None], vertices, dummy)
        normal = jnp.where(hit[:, None], hit_normals.triangle_normal(object_vertices), 0.0)
        if CURVE.name in kinds:
            curve_normal = _curve_normals(
                view, leaf, is_curve, curve_part, curve_u, curve_t, object_origin, object_direction
            )
            normal = jnp.where(is_curve[:, None], curve_normal, normal)
        for mine, _, kind_normal in formula_hits.values():
            normal = jnp.where(mine[:, None], kind_normal, normal)
        if transforms is not None:
            normal = hit_normals.to_world(normal, transforms.world_to_object)
        fields["normal"] = hit_normals.unit(normal)
    return fields


def _curve_normals(view, leaf, is_curve, part, u, t, origin, direction):
    """Object-space normals of curve hits (zeros elsewhere): evaluated on the hit segment at the hit's
    differentiable ``(distance, u)``, with dummy values in the other lanes (no NaN in their gradients)."""
    segment = view.leaves.curve[leaf]
    dummy = jnp.zeros((6, 4), segment.dtype).at[:4, 0].set(jnp.array([0.0, 1 / 3, 2 / 3, 1.0])).at[:4, 3].set(0.5)
    segment = jnp.where(is_curve[:, None, None], segment, dummy)
    origin = jnp.where(is_curve[:, None], origin, jnp.array([0.5, 0.0, -1.0], origin.dtype))
    direction = jnp.where(is_curve[:, None], direction, jnp.array([0.0, 0.0, 1.0], direction.dtype))
    part = jnp.where(is_curve, part, primitive.PART_TUBE)
    u = jnp.where(is_curve, u, 0.5)
    t = jnp.where(is_curve, t, 0.5)
    normal = jax.vmap(hit_normals.curve_normal)(origin, direction, segment, part, u, t)
    return jnp.where(is_curve[:, None], normal, 0.0)
