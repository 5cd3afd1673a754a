"""Geometric normals of hits (the ``normal`` field of ``rt.tags.normal``), in object space and to world space.

Each normal is taken on the surface the hit lies on, from the same differentiable quantities as the other
fields (the triangle's vertices, the curve hit's smooth ``(distance, u)``), so it differentiates with respect
to vertices, control points, radii, instance transforms and rays, holding the hit fixed.

* Triangles: ``cross(v1 - v0, v2 - v0)``, the geometric normal (Metal's and Embree's ``Ng``), never flipped
  towards the ray. With the winding convention of ``docs/design.md`` it points away from a viewer that sees
  the triangle clockwise (``dot(normal, direction) > 0`` for a ray hitting a clockwise triangle).
* Round curves: the tube's outward surface normal ``P - C(u)`` at the hit; on an end or joint sphere
  ``P - centre``; on an end disk the curve's end tangent, pointing out of the tube.
* Flat curves: the ribbon faces the ray by construction, so its normal is the part of ``-direction``
  perpendicular to the curve's tangent (towards the ray origin); ray-facing end disks give ``-direction``.
* Bounding boxes: the library knows no surface inside an intersection function's box: zeros.

Object-space normals go to world space by the inverse transpose of the chain's object-to-world linear part
(the transpose of the world-to-object linear part), which keeps a closed mesh's outward normals outward
under mirroring instances; then they are normalised.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxrt._src.primitives import curve as primitive

__all__ = ["unit", "triangle_normal", "curve_normal", "to_world"]


def unit(v: jax.Array) -> jax.Array:
    """``v / |v|`` along the last axis; 0 (with a finite gradient) for a zero vector."""
    length2 = jnp.sum(v * v, axis=-1, keepdims=True)
    positive = length2 > 0
    return jnp.where(positive, v * jax.lax.rsqrt(jnp.where(positive, length2, 1.0)), 0.0)


def triangle_normal(vertices: jax.Array) -> jax.Array:
    """``cross(v1 - v0, v2 - v0)`` of triangles ``(..., 3, 3)`` (not normalised)."""
    return jnp.cross(vertices[..., 1, :] - vertices[..., 0, :], vertices[..., 2, :] - vertices[..., 0, :])


def curve_normal(
    origin: jax.Array, direction: jax.Array, segment: jax.Array, part: jax.Array, u: jax.Array, t: jax.Array
) -> jax.Array:
    """Object-space normal (not normalised) of one curve hit: ``segment`` the packed ``(6, 4)`` segment,
    ``part`` the ``PART_*`` code the test returned, ``(t, u)`` the hit's distance and curve parameter."""
    bezier = primitive.world_bezier(segment)
    power = jnp.asarray(primitive._TO_POWER, bezier.dtype) @ bezier
    point = origin + t * direction
    centre, tangent, _ = primitive._evaluate(power, u)
    tube = point - centre[:3]
    at_end = jax.lax.stop_gradient(u) > 0.5
    end = jnp.where(at_end, bezier[3], bezier[0])
    sphere = point - end[:3]
    end_tangent = jnp.where(at_end, bezier[3] - bezier[2], bezier[1] - bezier[0])[:3]
    # A zero end tangent (b1 = b0) is a valid curve: the disk then faces along the chord, as in the test.
    moving = jnp.dot(end_tangent, end_tangent) > 0
    axis = jnp.where(moving, end_tangent, bezier[3, :3] - bezier[0, :3])
    disk = jnp.where(at_end, axis, -axis)
    along = tangent[:3]
    along2 = jnp.dot(along, along)
    ribbon = -(direction - jnp.dot(direction, along) / jnp.where(along2 > 0, along2, 1.0) * along)
    return jnp.select(
        [part == primitive.PART_TUBE, part == primitive.PART_SPHERE, part == primitive.PART_DISK],
        [tube, sphere, disk],
        jnp.where(part == primitive.PART_RIBBON, ribbon, -direction),
    )


def to_world(normal: jax.Array, world_to_object: jax.Array) -> jax.Array:
    """Object-space normals ``(n, 3)`` to world space with the transposed linear part of ``(n, 3, 4)``
    world-to-object transforms (the inverse transpose of object-to-world)."""
    linear = world_to_object[..., :3]
    return jnp.sum(linear * normal[..., :, None], axis=-2)
