"""Candidate hits handed to user intersection functions and filters (Metal's candidate accessors)."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax


class BoundingBoxCandidate(NamedTuple):
    """A bounding-box primitive the ray entered, as seen by an intersection function.

    Attributes:
      primitive_id: index of the box within its geometry (int32 scalar).
      geometry_id: index of the geometry in the structure (int32 scalar).
      lower, upper: ``(3,)`` the primitive's box.
      primitive_data: the primitive's slice of the geometry's ``primitive_data`` pytree (or ``None``).
    """

    primitive_id: jax.Array
    geometry_id: jax.Array
    lower: jax.Array
    upper: jax.Array
    primitive_data: Any


class TriangleCandidate(NamedTuple):
    """A triangle the ray hit in non-opaque geometry, as seen by a filter (alpha test).

    Attributes:
      primitive_id, geometry_id: int32 scalars.
      distance: the hit distance.
      barycentric_coord: ``(2,)`` ``(u, v)`` with ``hit = (1 - u - v) v0 + u v1 + v v2``.
      front_facing: bool scalar.
      primitive_data: the primitive's slice of the geometry's ``primitive_data`` pytree (or ``None``).
    """

    primitive_id: jax.Array
    geometry_id: jax.Array
    distance: jax.Array
    barycentric_coord: jax.Array
    front_facing: jax.Array
    primitive_data: Any
