"""Affine and keyframed transform math: inverse, composition, application, the world box of transformed
boxes, and instance transforms at a ray's time.

Transforms are ``(..., 3, 4)`` row-major object-to-world matrices whose last column is the translation. The
instance build (:mod:`jaxrt._src.instances`), the traversals (entering an instance with motion) and the result
fields (the chain's transforms) all read them here.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxrt._src.motion import blend, keyframe_position
from jaxrt._src.numerics import full_precision, gamma

__all__ = [
    "SINGULAR_TOLERANCE",
    "InstanceMotion",
    "apply_transform",
    "compose_transforms",
    "instance_motion_at",
    "invert_transform",
    "transform_boxes",
]

#: Smallest relative determinant ``|det A| / (|a0| |a1| |a2|)`` (columns ``a_i`` of the linear part) of an
#: accepted transform. Below it the float32 inverse loses most of its digits and object-space rays go wrong.
SINGULAR_TOLERANCE = 1e-6


@full_precision
def invert_transform(transform: jax.Array) -> jax.Array:
    """Inverse of ``(..., 3, 4)`` affine transforms (adjugate over determinant; differentiable)."""
    a = transform[..., :3]
    t = transform[..., 3]
    c0 = jnp.cross(a[..., 1, :], a[..., 2, :])
    c1 = jnp.cross(a[..., 2, :], a[..., 0, :])
    c2 = jnp.cross(a[..., 0, :], a[..., 1, :])
    det = jnp.sum(a[..., 0, :] * c0, axis=-1)
    det = jnp.where(det == 0, 1.0, det)
    inverse = jnp.stack([c0, c1, c2], axis=-1) / det[..., None, None]
    return jnp.concatenate([inverse, -jnp.einsum("...ij,...j->...i", inverse, t)[..., None]], axis=-1)


@full_precision
def compose_transforms(outer: jax.Array, inner: jax.Array) -> jax.Array:
    """``outer o inner`` for ``(..., 3, 4)`` affine transforms (apply ``inner`` first)."""
    linear = jnp.einsum("...ij,...jk->...ik", outer[..., :3], inner[..., :3])
    translation = jnp.einsum("...ij,...j->...i", outer[..., :3], inner[..., 3]) + outer[..., 3]
    return jnp.concatenate([linear, translation[..., None]], axis=-1)


@full_precision
def apply_transform(transform: jax.Array, point: jax.Array, *, vector: bool = False) -> jax.Array:
    """``transform`` ``(3, 4)`` applied to ``(..., 3)`` points (or, with ``vector``, directions)."""
    out = jnp.einsum("ij,...j->...i", transform[:, :3], point)
    return out if vector else out + transform[:, 3]


@full_precision
def transform_boxes(transform: jax.Array, lower: jax.Array, upper: jax.Array) -> tuple[jax.Array, jax.Array]:
    """World boxes ``(N, 3)`` around the transformed corners of object boxes ``(N, B, 3)``, padded outwards.

    Each instance's box bounds the eight transformed corners of each of its ``B`` object boxes (empty ones
    skipped). The pad (a few float32 roundings of the largest coordinate magnitude) keeps the box conservative
    for the rounding of the corner transform here and of the ray transform in the traversal. An instance
    whose boxes are all empty stays empty.
    """
    bits = jnp.array([[(k >> i) & 1 for i in range(3)] for k in range(8)], bool)  # (8, 3)
    corners = jnp.where(bits[None, None], upper[:, :, None, :], lower[:, :, None, :])  # (N, B, 8, 3)
    world = jnp.einsum("nij,nbkj->nbki", transform[:, :, :3], corners) + transform[:, None, None, :, 3]
    empty = jnp.any(lower > upper, axis=-1)[:, :, None, None]  # (N, B, 1, 1)
    lo = jnp.min(jnp.where(empty, jnp.inf, world), axis=(1, 2))
    hi = jnp.max(jnp.where(empty, -jnp.inf, world), axis=(1, 2))
    finite = jnp.where(empty, 0.0, jnp.abs(world))
    magnitude = jnp.maximum(jnp.max(finite, axis=(1, 2)), jnp.sum(jnp.abs(transform[:, :, 3:]), axis=-1))
    pad = magnitude * gamma(8)
    none = jnp.all(empty, axis=(1, 2, 3))[:, None]
    return jnp.where(none, jnp.inf, lo - pad), jnp.where(none, -jnp.inf, hi + pad)


class InstanceMotion(NamedTuple):
    """Keyframed object-to-world transforms of every global instance (static instances repeat theirs)."""

    keys: jax.Array  # (G, K, 3, 4), K the largest keyframe count; shorter tables repeat their last keyframe
    count: jax.Array  # (G,) int32 keyframes of the instance's table (2 for static tables)
    start: jax.Array  # (G,) float
    end: jax.Array  # (G,) float
    vanish_start: jax.Array  # (G,) bool
    vanish_end: jax.Array  # (G,) bool
    moving: jax.Array  # (G,) bool: the instance's table has motion


def instance_motion_at(motion: InstanceMotion, g: jax.Array, time: jax.Array):
    """``(to_world, to_object, visible, moving)`` of global instances ``g`` at ``time`` (broadcast together):
    the component-wise blend of the two neighbouring keyframe transforms, its inverse, whether the instance
    exists at that time (a ``"vanish"`` border), and whether it moves at all."""
    position = keyframe_position(
        time, motion.count[g], motion.start[g], motion.end[g], motion.vanish_start[g], motion.vanish_end[g]
    )
    a = motion.keys[g, position.index]
    b = motion.keys[g, position.index + 1]
    w = position.weight[..., None, None]
    to_world = blend(a, b, w)
    return to_world, invert_transform(to_world), position.visible | ~motion.moving[g], motion.moving[g]
