"""Ray/triangle intersection: the watertight test for traversal, a smooth one for gradients.

Reference: Woop, Benthin, Wald, "Watertight Ray/Triangle Intersection", JCGT 2(1), 2013 (the formulas are
those of :mod:`jaxrt._src.formulas.triangle`, which the compiled traversals share). The ray is sheared so
that it runs along +z through the origin; the three 2D edge functions are then computed from the vertices
alone, so an edge shared by two triangles gives the same value (with opposite sign) in both and no ray passes
between them. Zero edge functions count as inside, so a ray through an edge or vertex hits (rather than
misses) every triangle that shares it.

Winding convention: seen from the ray origin looking along the ray, a triangle ``(v0, v1, v2)`` is clockwise
when ``dot(cross(v1 - v0, v2 - v0), direction) > 0``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxrt._src import formulas

_tri = formulas.instance("triangle", "jax")


class ShearedRay(NamedTuple):
    """Per-ray constants of the watertight test (Woop et al. 2013, section 3)."""

    origin: jax.Array
    kx: jax.Array
    ky: jax.Array
    kz: jax.Array
    shear: jax.Array  # (Sx, Sy, Sz)


def _component(v: jax.Array, k: jax.Array) -> jax.Array:
    """``v[..., k]`` for a per-ray axis ``k``, as selects (cheaper than a gather under vmap)."""
    return jnp.where(k == 0, v[..., 0], jnp.where(k == 1, v[..., 1], v[..., 2]))


def shear_ray(origin: jax.Array, direction: jax.Array) -> ShearedRay:
    """Precompute the axis permutation and shear for one ray (``direction`` must be non-zero)."""
    kx, ky, kz = (jnp.asarray(k).astype(jnp.int32) for k in _tri.shear_axes(*direction))
    shear = _tri.shear(_component(direction, kx), _component(direction, ky), _component(direction, kz))
    return ShearedRay(origin, kx, ky, kz, jnp.stack(shear))


class TriangleHit(NamedTuple):
    hit: jax.Array
    distance: jax.Array
    u: jax.Array  # weight of v1
    v: jax.Array  # weight of v2
    clockwise: jax.Array  # winding seen from the ray (see the module docstring)


def _product(a: jax.Array, b: jax.Array) -> jax.Array:
    """``a * b`` rounded to one bit less than the float's mantissa, so that no compiler can fuse it into an FMA.

    The watertight test needs every edge function ``a b - c d`` to have the exact sign of the real value, or
    to be zero: then an edge shared by two triangles gets exactly opposite values in both, and the signs around
    a vertex stay consistent, so no ray passes between triangles. Separately rounded products give that
    (rounding is monotonic), but XLA contracts ``a * b - c * d`` into ``fma(a, b, -c * d)`` on the CPU and GPU,
    whose sign can be wrong when the products nearly cancel; a float32 ``reduce_precision`` to 23 bits is a
    no-op that the compiler removes. Rounding to 22 bits (23 for float64's 52) cannot be removed, is still
    monotonic, and costs a bit of precision in the barycentrics only.
    """
    return _tri.rounded_product(a, b)


def _edge_functions(ray: ShearedRay, vertices: jax.Array):
    """Woop et al.'s sheared 2D edge functions (weights of v0, v1, v2) and the sheared z of each vertex."""
    rel = vertices - ray.origin
    px, py, pz = _tri.sheared_vertex(
        _component(rel, ray.kx), _component(rel, ray.ky), _component(rel, ray.kz), *ray.shear
    )
    e0, e1, e2 = _tri.edge_functions(px[..., 0], py[..., 0], px[..., 1], py[..., 1], px[..., 2], py[..., 2])
    return e0, e1, e2, pz


def watertight(ray: ShearedRay, t_min: jax.Array, t_max: jax.Array, vertices: jax.Array, cull: int = 0) -> TriangleHit:
    """Watertight test of one ray against triangles ``vertices`` of shape ``(..., 3, 3)``.

    The formulas of :mod:`jaxrt._src.formulas.triangle` (shared with the compiled traversals), elementwise over
    the triangles.

    Args:
      ray: from :func:`shear_ray`.
      t_min, t_max: the accepted distance interval (inclusive).
      vertices: triangle vertices.
      cull: static; 0 culls nothing, +1 culls clockwise triangles, -1 counterclockwise ones.

    Returns:
      A :class:`TriangleHit`; degenerate (zero-area after projection) triangles never hit. Distances of
      misses are ``inf``, their barycentrics 0.
    """
    e0, e1, e2, sz = _edge_functions(ray, vertices)
    inside, det = _tri.edges_inside(e0, e1, e2)
    clockwise = det < 0
    if cull != 0:
        inside &= _tri.facing_accepts(det, cull)
    distance = _tri.plane_distance(e0, e1, e2, sz[..., 0], sz[..., 1], sz[..., 2], det)
    det_safe = jnp.where(det == 0, 1.0, det)
    hit = inside & _tri.in_interval(distance, t_min, t_max)
    return TriangleHit(
        hit=hit,
        distance=jnp.where(hit, distance, jnp.inf),
        u=jnp.where(hit, e1 / det_safe, 0.0),
        v=jnp.where(hit, e2 / det_safe, 0.0),
        clockwise=clockwise,
    )


def barycentrics(ray: ShearedRay, vertices: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(u, v, clockwise)`` of the ray's plane crossing, with no inside or distance test.

    For a triangle already accepted by :func:`watertight` these are its barycentrics, recomputed without
    carrying them through the traversal loop.
    """
    e0, e1, e2, _ = _edge_functions(ray, vertices)
    det = e0 + e1 + e2
    det_safe = jnp.where(det == 0, 1.0, det)
    return e1 / det_safe, e2 / det_safe, det < 0


def smooth_hit(origin: jax.Array, direction: jax.Array, vertices: jax.Array):
    """Distance and barycentrics of the ray's plane hit, smooth in all inputs (Möller & Trumbore 1997).

    Used only for gradients: the traversal picks the triangle with :func:`watertight`, then this recomputes
    the hit differentiably. Callers must pass a non-degenerate triangle (replace misses by a dummy one).

    Returns:
      ``(distance, u, v)`` with ``hit = (1 - u - v) v0 + u v1 + v v2``.
    """
    v0, v1, v2 = vertices[0], vertices[1], vertices[2]
    e1, e2 = v1 - v0, v2 - v0
    p = jnp.cross(direction, e2)
    det = jnp.dot(e1, p)
    det = jnp.where(det == 0, 1.0, det)
    s = origin - v0
    q = jnp.cross(s, e1)
    return jnp.dot(e2, q) / det, jnp.dot(s, p) / det, jnp.dot(direction, q) / det


def has_area(vertices: jax.Array) -> jax.Array:
    """Whether triangles ``(..., 3, 3)`` have a non-zero cross product of their edge vectors.

    Evaluated with the same FMA-proof products as the edge functions, so the answer does not depend on the
    compiler. A triangle without area can never be hit; the builder gives it an empty box.
    """
    e1 = vertices[..., 1, :] - vertices[..., 0, :]
    e2 = vertices[..., 2, :] - vertices[..., 0, :]
    x = _product(e1[..., 1], e2[..., 2]) - _product(e1[..., 2], e2[..., 1])
    y = _product(e1[..., 2], e2[..., 0]) - _product(e1[..., 0], e2[..., 2])
    z = _product(e1[..., 0], e2[..., 1]) - _product(e1[..., 1], e2[..., 0])
    return (x != 0) | (y != 0) | (z != 0)
