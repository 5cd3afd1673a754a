"""Packed arrays read by the GPU traversal kernel, derived from a structure and a ray batch.

The kernel reads one node with four 16-byte loads and one triangle with three, so the structure's arrays are
repacked into rows of float32 quads (children bit-cast to float32). The packing is a cheap elementwise pass
(about 110 bytes per primitive), done inside every traced call: structures stay the one source of truth.

Node row, ``(C-1, 16)`` float32, one per internal node (both child boxes in the parent, as in Aila & Laine,
"Understanding the Efficiency of Ray Traversal on GPUs", HPG 2009):

=======  ==========================================================
columns  contents
=======  ==========================================================
0-3      ``lower0.x, upper0.x, lower1.x, upper1.x``
4-7      the same for y
8-11     the same for z
12-13    child 0 and child 1 (int32 bits: node ``c >= 0`` or leaf ``-1 - k``)
14-15    zero
=======  ==========================================================

Triangle row, ``(C, 12)`` float32, one per leaf: ``v0.x, v1.x, v2.x, 0, v0.y, v1.y, v2.y, 0, v0.z, v1.z,
v2.z, 0``.

Ray block, ``(16, N)`` float32, one column per ray (rows are coalesced across the 32 rays of a program):
origin (rows 0-2), the safe reciprocal direction (3-5), the watertight shear ``Sx, Sy, Sz`` (6-8), ``t_min``
(9), the initial distance bound (10: ``t_max``, or ``-inf`` for a disabled ray, so that it never hits), the
sheared axes ``kx, ky, kz`` as small integers (11-13), and 1 for an enabled ray, else 0 (14).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

from jaxrt._src.numerics import safe_reciprocal
from jaxrt._src.primitives import triangle

__all__ = ["NODE_WIDTH", "TRIANGLE_WIDTH", "RAY_ROWS", "pack_nodes", "unpack_nodes", "pack_triangles", "pack_rays"]

NODE_WIDTH = 16
TRIANGLE_WIDTH = 12
RAY_ROWS = 16


def pack_nodes(node_lower: jax.Array, node_upper: jax.Array, node_children: jax.Array) -> jax.Array:
    """The ``(C-1, 16)`` float32 node rows (layout in the module docstring)."""
    m = node_lower.shape[0]
    lower = node_lower.astype(jnp.float32)
    upper = node_upper.astype(jnp.float32)
    # (m, axis, [lower0, upper0, lower1, upper1])
    boxes = jnp.stack([lower[:, 0], upper[:, 0], lower[:, 1], upper[:, 1]], axis=-1)
    children = lax.bitcast_convert_type(node_children.astype(jnp.int32), jnp.float32)
    tail = jnp.concatenate([children, jnp.zeros((m, 2), jnp.float32)], axis=-1)
    return jnp.concatenate([boxes.reshape(m, 12), tail], axis=-1)


def unpack_nodes(packed: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Inverse of :func:`pack_nodes`: ``(node_lower, node_upper, node_children)``."""
    m = packed.shape[0]
    boxes = packed[:, :12].reshape(m, 3, 4)
    lower = jnp.stack([boxes[:, :, 0], boxes[:, :, 2]], axis=1)
    upper = jnp.stack([boxes[:, :, 1], boxes[:, :, 3]], axis=1)
    children = lax.bitcast_convert_type(packed[:, 12:14], jnp.int32)
    return lower, upper, children


def pack_triangles(leaf_triangle: jax.Array) -> jax.Array:
    """The ``(C, 12)`` float32 triangle rows: per axis, the three vertices' coordinates and a zero."""
    c = leaf_triangle.shape[0]
    per_axis = jnp.swapaxes(leaf_triangle.astype(jnp.float32), 1, 2)  # (C, axis, vertex)
    return jnp.pad(per_axis, ((0, 0), (0, 0), (0, 1))).reshape(c, TRIANGLE_WIDTH)


def pack_rays(
    origin: jax.Array, direction: jax.Array, t_min: jax.Array, t_max: jax.Array, enabled: jax.Array, size: int
) -> jax.Array:
    """The ``(16, size)`` float32 ray block; columns past the ray count are disabled rays.

    The per-ray constants are computed here with the same functions as the portable traversal, so both
    paths start from bit-identical values.
    """
    n = origin.shape[0]
    inv_direction = jax.vmap(safe_reciprocal)(direction)
    sheared = jax.vmap(triangle.shear_ray)(origin, direction)
    axes = jnp.stack([sheared.kx, sheared.ky, sheared.kz], axis=-1).astype(jnp.float32)
    bound = jnp.where(enabled, t_max, -jnp.inf)
    columns = jnp.concatenate(
        [
            origin,
            inv_direction,
            sheared.shear,
            t_min[:, None],
            bound[:, None],
            axes,
            enabled[:, None].astype(jnp.float32),
            jnp.zeros((n, 1), jnp.float32),
        ],
        axis=-1,
    ).astype(jnp.float32)
    columns = jnp.pad(columns, ((0, size - n), (0, 0)))
    return columns.T
