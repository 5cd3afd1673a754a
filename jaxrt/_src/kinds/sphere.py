"""Spheres (``rt.SphereGeometry``, ``rt.MotionSphereGeometry``): particles, molecules, point clouds.

Leaf layout (``C`` leaf slots; ``K`` keyframes with keyframe motion). A sphere needs four floats, its centre and
radius (16 bytes in float32); it keeps them in the row every leaf has, so a sphere adds no leaf array:

====================  ================  =========  ==================================================================
array                 per leaf          fill       contents
====================  ================  =========  ==================================================================
``leaf_triangle``     (3, 3) float      zeros      row 0: the centre ``(x, y, z)``; row 1: ``(radius, 0, 0)``;
                                                   row 2: zeros (the shared row of :mod:`.triangle`)
``motion_triangle``   (K, 3, 3) float   zeros      that row at each keyframe: blended linearly at a ray's time,
                                                   centre and radius move linearly between keyframes
====================  ================  =========  ==================================================================

Bounds: the centre plus and minus the radius (an empty box for a negative, NaN or infinite radius or a
non-finite centre, so that no ray enters a bad sphere). Intersection and re-intersection: the robust test of
Haines et al. (Ray Tracing Gems ch. 7), :func:`jaxrt._src.formulas.sphere.ray_sphere`, whose JAX instance is
differentiable in the centre, the radius and the ray. A ray that starts inside a sphere (or enters it before
``t_min``) hits it where it leaves it, with ``sphere_front_facing`` false (OptiX's convention for its built-in
spheres); ``normal`` is the outward normal either way. Point queries:
:func:`~jaxrt._src.formulas.sphere.closest_on_sphere` (the surface). Decisions that need JAX: a user filter on
non-opaque spheres (it sees a ``TriangleCandidate`` with zero barycentrics and ``front_facing`` as above).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from jaxrt._src import formulas
from jaxrt._src.kinds.kind import AnalyticRow, Coverage, Kind, LeafArray

__all__ = [
    "SPHERE",
    "analytic_parameters",
    "bounds",
    "checks",
    "closest_point",
    "code_bounds",
    "dummy",
    "inside",
    "intersect",
    "normal",
    "rows",
    "unpack",
]

_formula = formulas.instance("sphere", "jax")


def rows(centers: jax.Array, radii: jax.Array) -> jax.Array:
    """The ``(N, 3, 3)`` leaf rows of spheres ``centers (N, 3)``, ``radii (N,)`` (the layout table)."""
    radius_row = jnp.zeros_like(centers).at[:, 0].set(radii)
    return jnp.stack([centers, radius_row, jnp.zeros_like(centers)], axis=1)


def unpack(row: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(centre (..., 3), radius (...))`` of leaf rows ``(..., 3, 3)``."""
    return row[..., 0, :], row[..., 1, 0]


def valid(row: jax.Array) -> jax.Array:
    """Whether rows ``(..., 3, 3)`` hold a sphere that can be hit (finite centre, finite radius ``>= 0``)."""
    centre, radius = unpack(row)
    return jnp.all(jnp.isfinite(centre), axis=-1) & jnp.isfinite(radius) & (radius >= 0)


def bounds(row: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The box ``(lower, upper)`` of leaf rows ``(..., 3, 3)``; empty (``+inf``, ``-inf``) for a bad sphere."""
    centre, radius = unpack(row)
    ok = valid(row)[..., None]
    r = radius[..., None]
    return jnp.where(ok, centre - r, jnp.inf), jnp.where(ok, centre + r, -jnp.inf)


def code_bounds(row: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The point box of the centres of leaf rows ``(..., 3, 3)``, whose centre gives a sphere's Morton code (also
    for a bad sphere, whose box is empty)."""
    centre, _ = unpack(row)
    return centre, centre


def analytic_parameters(row: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(p, q, radius)`` of the compiled loops' analytic rows (code 5) from leaf rows ``(C, 3, 3)``: the centre,
    zeros and the radius."""
    centre, radius = unpack(row)
    return centre, jnp.zeros_like(centre), radius


def intersect(
    origin: jax.Array, direction: jax.Array, t_min: jax.Array, t_max: jax.Array, row: jax.Array
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(hit, distance, front)`` of rays ``(..., 3)`` with leaf rows ``(..., 3, 3)`` (broadcast), the JAX
    instance of :func:`jaxrt._src.formulas.sphere.ray_sphere` (differentiable: gradients reach the rows)."""
    centre, radius = unpack(row)
    o, d, c = (jnp.moveaxis(x, -1, 0) for x in jnp.broadcast_arrays(origin, direction, centre))
    return _formula.ray_sphere(*c, radius, *o, *d, t_min, t_max)


def normal(origin: jax.Array, direction: jax.Array, distance: jax.Array, row: jax.Array) -> jax.Array:
    """The outward normal (not normalised) at ``origin + distance * direction``, from the centre-to-origin
    vector, which keeps its precision for a small sphere far from the origin."""
    centre, _ = unpack(row)
    return (origin - centre) + distance[..., None] * direction


def closest_point(point: jax.Array, row: jax.Array) -> jax.Array:
    """The point of the sphere surface of leaf row ``row (..., 3, 3)`` closest to ``point (..., 3)``."""
    centre, radius = unpack(row)
    p, c = (jnp.moveaxis(x, -1, 0) for x in jnp.broadcast_arrays(point, centre))
    qx, qy, qz, _ = _formula.closest_on_sphere(*p, *c, radius)
    return jnp.stack([qx, qy, qz], axis=-1)


def inside(point: jax.Array, row: jax.Array) -> jax.Array:
    """Whether ``point (..., 3)`` lies in the closed ball of leaf row ``row (..., 3, 3)``."""
    centre, radius = unpack(row)
    return jnp.sum((point - centre) ** 2, axis=-1) <= radius * radius


def dummy(dtype: Any) -> tuple[jax.Array, jax.Array, jax.Array]:
    """A unit sphere at the origin and a ray along ``+z`` from ``(0, 0, -2)`` that hits it."""
    row = rows(jnp.zeros((1, 3), dtype), jnp.ones((1,), dtype))[0]
    return row, jnp.array([0.0, 0.0, -2.0], dtype), jnp.array([0.0, 0.0, 1.0], dtype)


def checks(geometry: Any) -> tuple[tuple[str, jax.Array, jax.Array], ...]:
    """The rules of ``checks=True`` for a sphere geometry: finite centres, finite radii ``>= 0``."""
    centers, radii = geometry.centers, geometry.radii
    not_finite = ~jnp.all(jnp.isfinite(centers), axis=1)
    bad_radius = ~jnp.isfinite(radii) | ~(radii >= 0)
    return (
        ("centers[{index}] = {value} is not finite", not_finite, centers),
        ("radii[{index}] = {value} is negative or not finite", bad_radius, radii),
    )


def _filter_code(intersector: Any, infos: tuple, traversal: str, where: str) -> str | None:
    if intersector.filter is None or all(g.opaque for g in infos):
        return None
    return f"filters on non-opaque spheres{where} are not covered by the {traversal}"


SPHERE = Kind(
    name="sphere",
    plural="spheres",
    be="are",
    intersection_type=4,
    leaf_arrays=(
        LeafArray("leaf_triangle", (3, 3), "float", "zeros", "motion_triangle", "centre; radius, 0, 0; zeros", True),
    ),
    bounds=bounds,
    intersect=intersect,
    reintersect=intersect,
    closest_point=closest_point,
    tags=("sphere_data", "normal"),
    fields={"sphere_front_facing": "sphere_data"},
    # the compiled traversals test sphere leaves as analytic rows (code 5, ``analytic``), from the static leaf rows
    coverage={"gpu": Coverage(motion=False, waves=False), "cpu": Coverage(motion=False)},
    filter_code=_filter_code,
    formula_leaves=True,
    normal=normal,
    front_field="sphere_front_facing",
    dummy=dummy,
    inside=inside,
    checks=checks,
    doc="A built-in sphere (``rt.SphereGeometry``).",
    tag_docs={
        "sphere_data": (
            "Adds ``sphere_front_facing`` (sphere geometry): true where the ray enters the sphere at the hit, "
            "false where it leaves it (a ray that starts inside the sphere, or enters it before its "
            "``min_distance``); false off spheres."
        ),
    },
    geometry="SphereGeometry",
    code_bounds=code_bounds,
    analytic=AnalyticRow(5, "sphere", "ray_sphere", ("px", "py", "pz", "radius"), 3, analytic_parameters),
    float_array="centers",
)
