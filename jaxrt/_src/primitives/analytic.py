"""Analytic intersection functions for bounding-box geometry: sphere, disk, capped cylinder.

Each has the intersection-function signature ``fn(ray, candidate) -> (accept, distance)``: ``ray`` is one
:class:`~jaxrt.Ray` (its ``max_distance`` is the distance of the nearest hit so far) and ``candidate`` a
:class:`~jaxrt._src.candidate.BoundingBoxCandidate`. Shape parameters come from the candidate's
``primitive_data`` (a mapping with the keys each function names) or, where a function says so, from the box.
All are differentiable in the ray and the parameters; an invalid configuration (a ray parallel to a disk,
a miss) returns ``accept = False`` with no NaN in the distance or its gradient. The formulas are those of
:mod:`jaxrt._src.formulas.analytic`, which the compiled traversals share.

References:
  Haines, Günther, Akenine-Möller, "Precision Improvements for Ray/Sphere Intersection", Ray Tracing Gems,
  ch. 7, 2019 (the sphere's discriminant from the closest-approach vector and the stable root pair).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from jaxrt._src import formulas

_shapes = formulas.instance("analytic", "jax")

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


def _xyz(v: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    return v[0], v[1], v[2]


def _ray(ray: Any) -> tuple[jax.Array, ...]:
    """The ray's origin, direction and interval, component by component."""
    return (*_xyz(ray.origin), *_xyz(ray.direction), ray.min_distance, ray.max_distance)


def _finish(ok: jax.Array, t: jax.Array) -> tuple[jax.Array, jax.Array]:
    return ok, jnp.where(ok, t, jnp.inf)


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
    return _finish(*_shapes.sphere(*_xyz(center), radius, *_ray(ray)))


def disk(ray: Any, candidate: Any) -> tuple[jax.Array, jax.Array]:
    """Ray/disk intersection (both faces); ``primitive_data`` keys ``center`` (3,), ``normal`` (3,), ``radius`` ()."""
    center, normal, radius = (_param(candidate, k) for k in ("center", "normal", "radius"))
    return _finish(*_shapes.disk(*_xyz(center), *_xyz(normal), radius, *_ray(ray)))


def capped_cylinder(ray: Any, candidate: Any) -> tuple[jax.Array, jax.Array]:
    """Ray/capped-cylinder intersection; ``primitive_data`` keys ``p0``, ``p1`` (3,) (the axis ends) and ``radius``.

    The surface is the side wall between the two cap planes plus the two cap disks.
    """
    p0, p1, radius = (_param(candidate, k) for k in ("p0", "p1", "radius"))
    return _finish(*_shapes.capped_cylinder(*_xyz(p0), *_xyz(p1), radius, *_ray(ray)))


#: The compiled traversals' code of each built-in function (they call the same formulas); a box geometry with any other function is traced by the portable traversal.
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
