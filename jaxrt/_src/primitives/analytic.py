"""Analytic intersection functions for bounding-box geometry: sphere, disk, capped cylinder.

Each has the intersection-function signature ``fn(ray, candidate) -> (accept, distance)``: ``ray`` is one
:class:`~jaxrt.Ray` (its ``max_distance`` is the distance of the nearest hit so far) and ``candidate`` a
:class:`~jaxrt._src.candidate.BoundingBoxCandidate`. Shape parameters come from the candidate's
``primitive_data`` (a mapping with the keys each function names) or, where a function says so, from the box.
All are differentiable in the ray and the parameters; an invalid configuration (a ray parallel to a disk,
a miss) returns ``accept = False`` with no NaN in the distance or its gradient.

References:
  Haines, Günther, Akenine-Möller, "Precision Improvements for Ray/Sphere Intersection", Ray Tracing Gems,
  ch. 7, 2019 (the sphere's discriminant from the closest-approach vector and the stable root pair).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

__all__ = [
    "sphere",
    "disk",
    "capped_cylinder",
    "sphere_bounds",
    "disk_bounds",
    "capped_cylinder_bounds",
    "SHAPE_CODES",
    "shape_code",
]


def _param(candidate: Any, name: str) -> jax.Array:
    data = candidate.primitive_data
    if data is None or name not in data:
        raise ValueError(f"intersection function needs primitive_data[{name!r}] (per-primitive parameters)")
    return data[name]


def _nearest(ray: Any, *candidates: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, jax.Array]:
    """The smallest valid distance in ``[ray.min_distance, ray.max_distance]`` among (valid, t) pairs."""
    best_ok, best_t = jnp.zeros((), bool), jnp.full((), jnp.inf, ray.origin.dtype)
    for ok, t in candidates:
        ok = ok & (t >= ray.min_distance) & (t <= ray.max_distance)
        take = ok & (t < best_t)
        best_ok, best_t = best_ok | ok, jnp.where(take, t, best_t)
    return best_ok, jnp.where(best_ok, best_t, jnp.inf)


def _safe(x: jax.Array, ok: jax.Array) -> jax.Array:
    """``x`` where ``ok``, else 1 (keeps divisions and square roots finite on rejected branches)."""
    return jnp.where(ok, x, 1.0)


def sphere(ray: Any, candidate: Any) -> tuple[jax.Array, jax.Array]:
    """Ray/sphere intersection; ``primitive_data`` keys ``center`` (3,) and ``radius`` (), or, without
    primitive data, the sphere inscribed in the box (centre of the box, half its smallest extent).

    Returns the nearer root inside the ray interval (the far root when the origin is inside the sphere).
    """
    if candidate.primitive_data is None:
        center = 0.5 * (candidate.lower + candidate.upper)
        radius = 0.5 * jnp.min(candidate.upper - candidate.lower)
    else:
        center, radius = _param(candidate, "center"), _param(candidate, "radius")
    d = ray.direction
    f = ray.origin - center
    a = jnp.dot(d, d)
    b = -jnp.dot(f, d)
    closest = f + (b / a) * d  # the centre-to-ray vector at closest approach (RTG ch. 7)
    disc = a * (radius * radius - jnp.dot(closest, closest))
    ok = disc >= 0
    q = b + jnp.where(b >= 0, 1.0, -1.0) * jnp.sqrt(_safe(disc, ok))
    c = jnp.dot(f, f) - radius * radius
    q_ok = ok & (q != 0)
    t0 = c / _safe(q, q_ok)
    t1 = q / a
    return _nearest(ray, (q_ok, t0), (ok, t1))


def disk(ray: Any, candidate: Any) -> tuple[jax.Array, jax.Array]:
    """Ray/disk intersection (both faces); ``primitive_data`` keys ``center`` (3,), ``normal`` (3,), ``radius`` ()."""
    center, normal, radius = (_param(candidate, k) for k in ("center", "normal", "radius"))
    denom = jnp.dot(ray.direction, normal)
    ok = denom != 0
    t = jnp.dot(center - ray.origin, normal) / _safe(denom, ok)
    offset = ray.origin + t * ray.direction - center
    inside = jnp.dot(offset, offset) <= radius * radius
    return _nearest(ray, (ok & inside, t))


def capped_cylinder(ray: Any, candidate: Any) -> tuple[jax.Array, jax.Array]:
    """Ray/capped-cylinder intersection; ``primitive_data`` keys ``p0``, ``p1`` (3,) (the axis ends) and ``radius``.

    The surface is the side wall between the two cap planes plus the two cap disks.
    """
    p0, p1, radius = (_param(candidate, k) for k in ("p0", "p1", "radius"))
    axis = p1 - p0
    length2 = jnp.dot(axis, axis)
    oc = ray.origin - p0
    d = ray.direction
    # Project out the axis component (scaled by length2 to avoid a division): |oc_perp + t d_perp|^2 = r^2.
    d_along, oc_along = jnp.dot(d, axis), jnp.dot(oc, axis)
    d_perp = d * length2 - axis * d_along
    oc_perp = oc * length2 - axis * oc_along
    a = jnp.dot(d_perp, d_perp)
    b = jnp.dot(oc_perp, d_perp)
    c = jnp.dot(oc_perp, oc_perp) - radius * radius * length2 * length2
    disc = b * b - a * c
    wall_ok = (a > 0) & (disc >= 0)
    root = jnp.sqrt(_safe(disc, wall_ok))
    a_safe = _safe(a, wall_ok)
    walls = []
    for sign in (-1.0, 1.0):
        t = (-b + sign * root) / a_safe
        along = oc_along + t * d_along
        walls.append((wall_ok & (along >= 0) & (along <= length2), t))
    caps = []
    cap_ok = d_along != 0
    for target in (0.0, 1.0):
        t = (target * length2 - oc_along) / _safe(d_along, cap_ok)
        radial = oc_perp + t * d_perp
        caps.append((cap_ok & (jnp.dot(radial, radial) <= radius * radius * length2 * length2), t))
    return _nearest(ray, *walls, *caps)


#: The GPU kernel's code of each built-in function (:mod:`jaxrt._src.traversal.triton_analytic` repeats
#: their formulas); a box geometry with any other function is traced by the portable traversal.
SHAPE_CODES = {sphere: 1, disk: 2, capped_cylinder: 3}


def shape_code(fn: Any) -> int:
    """The kernel code of ``fn`` when it is one of the built-in functions (by identity), else 0."""
    for builtin, code in SHAPE_CODES.items():
        if fn is builtin:
            return code
    return 0


def sphere_bounds(center: Any, radius: Any) -> tuple[jax.Array, jax.Array]:
    """``(N, 3)`` box corners of spheres ``center (N, 3)``, ``radius (N,)``."""
    center, radius = jnp.asarray(center), jnp.asarray(radius)[..., None]
    return center - radius, center + radius


def disk_bounds(center: Any, normal: Any, radius: Any) -> tuple[jax.Array, jax.Array]:
    """Tight ``(N, 3)`` box corners of disks: the extent along axis ``i`` is ``r * sqrt(1 - n_i^2)``."""
    center, normal, radius = jnp.asarray(center), jnp.asarray(normal), jnp.asarray(radius)[..., None]
    n = normal / jnp.linalg.norm(normal, axis=-1, keepdims=True)
    extent = radius * jnp.sqrt(jnp.clip(1.0 - n * n, 0.0, 1.0))
    return center - extent, center + extent


def capped_cylinder_bounds(p0: Any, p1: Any, radius: Any) -> tuple[jax.Array, jax.Array]:
    """Tight ``(N, 3)`` box corners of capped cylinders (the union of the two cap disks' boxes)."""
    p0, p1 = jnp.asarray(p0), jnp.asarray(p1)
    lo0, hi0 = disk_bounds(p0, p1 - p0, radius)
    lo1, hi1 = disk_bounds(p1, p1 - p0, radius)
    return jnp.minimum(lo0, lo1), jnp.maximum(hi0, hi1)
