"""Point-to-primitive geometry: the closest point of a triangle or a box, and a triangle's solid angle.

Closest point on a triangle: Ericson, *Real-Time Collision Detection* (2005), section 5.1.5. The point's
Voronoi region of the triangle (three vertices, three edges, the face) is found from six dot products; every
division is guarded, so zero-length edges and collinear (zero-area) triangles give the closest point of
their segment or vertex instead of a NaN. Barycentrics follow Metal: the point is
``(1 - u - v) * v0 + u * v1 + v * v2``.

Solid angle: Van Oosterom and Strackee, "The Solid Angle of a Plane Triangle", IEEE Trans. Biomed. Eng.
30(2), 1983 (the ``atan2`` form), positive when the triangle's counterclockwise normal points away from the
point.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxrt._src import formulas

_formula = formulas.instance("point_triangle", "jax")

__all__ = ["closest_on_triangle", "closest_on_box", "solid_angle", "squared_box_distance"]


def closest_on_triangle(p: jax.Array, tri: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The barycentrics ``(u, v)`` of the point of triangle ``tri (3, 3)`` closest to ``p (3,)``.

    The formula of :mod:`jaxrt._src.formulas.point_triangle`. The point itself is
    ``(1 - u - v) * tri[0] + u * tri[1] + v * tri[2]``; both differentiate with respect to ``p`` and ``tri``
    within the point's Voronoi region.
    """
    coordinates = [p[..., i] for i in range(3)] + [tri[..., k, i] for k in range(3) for i in range(3)]
    return _formula.closest_on_triangle(*coordinates)


def triangle_point(tri: jax.Array, u: jax.Array, v: jax.Array) -> jax.Array:
    """``(1 - u - v) * tri[0] + u * tri[1] + v * tri[2]`` (Metal's barycentric convention)."""
    return tri[0] + u[..., None] * (tri[1] - tri[0]) + v[..., None] * (tri[2] - tri[0])


def closest_on_box(p: jax.Array, box: jax.Array) -> jax.Array:
    """The point of the solid box ``box (..., 2, 3)`` (lower, upper corner) closest to ``p (..., 3)`` (``p``
    inside it)."""
    return jnp.clip(p, box[..., 0, :], box[..., 1, :])


def squared_box_distance(p: jax.Array, lower: jax.Array, upper: jax.Array) -> jax.Array:
    """Squared distance from ``p (..., 3)`` to boxes ``(..., 3)``; ``inf`` for an empty box (lower > upper).

    The formula of :mod:`jaxrt._src.formulas.point_triangle` (the compiled walks' too)."""
    p, lower, upper = jnp.broadcast_arrays(p, lower, upper)
    return _formula.squared_box_distance(*(a[..., i] for a in (p, lower, upper) for i in range(3)))


def solid_angle(p: jax.Array, tri: jax.Array) -> jax.Array:
    """The signed solid angle of triangle ``tri (..., 3, 3)`` seen from ``p (..., 3)`` (Van Oosterom and
    Strackee 1983); 0 where the point is in the triangle's plane (or the triangle has no area). The formula of
    :mod:`jaxrt._src.formulas.point_triangle` (the compiled walks' too)."""
    p = jnp.broadcast_to(p, tri.shape[:-2] + (3,))
    coordinates = [p[..., i] for i in range(3)] + [tri[..., k, i] for k in range(3) for i in range(3)]
    return _formula.solid_angle(*coordinates)
