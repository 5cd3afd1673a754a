"""Triangles (``rt.TriangleGeometry``, ``rt.MotionTriangleGeometry``).

Leaf layout (``C`` leaf slots; ``K`` keyframes with keyframe motion):

====================  ================  =========  ==================================================================
array                 per leaf          fill       contents
====================  ================  =========  ==================================================================
``leaf_triangle``     (3, 3) float      zeros      the three vertices in object space; every kind's leaves have this
                                                   row (the traversal contract reads it), zeros for other kinds
``motion_triangle``   (K, 3, 3) float   zeros      ``leaf_triangle`` at each keyframe (keyframe 0 is the static row)
====================  ================  =========  ==================================================================

Bounds: the vertices' box; a triangle without area gets an empty box (no ray enters it). Intersection: the
watertight test of Woop, Benthin and Wald (2013), :func:`jaxrt._src.primitives.triangle.watertight`;
re-intersection: the same test for the values, :func:`~jaxrt._src.primitives.triangle.smooth_hit`
(Möller-Trumbore) for the gradients; point queries:
:func:`~jaxrt._src.primitives.point_triangle.closest_on_triangle`. Decisions that need JAX: a user filter on
non-opaque geometry.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from jaxrt._src.kinds.kind import Coverage, Kind, LeafArray
from jaxrt._src.primitives import point_triangle
from jaxrt._src.primitives import triangle as formulas

__all__ = ["TRIANGLE", "bounds"]


def bounds(vertices: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The box ``(lower, upper)`` of triangles ``(..., 3, 3)``."""
    return jnp.min(vertices, axis=-2), jnp.max(vertices, axis=-2)


def _filter_code(intersector: Any, infos: tuple, traversal: str, where: str) -> str | None:
    if intersector.filter is None or all(g.opaque for g in infos):
        return None
    return f"filters on non-opaque geometry{where} are not covered by the {traversal}"


TRIANGLE = Kind(
    name="triangle",
    plural="triangles",
    be="are",
    intersection_type=1,
    leaf_arrays=(
        LeafArray("leaf_triangle", (3, 3), "float", "zeros", "motion_triangle", "the three vertices", shared=True),
    ),
    bounds=bounds,
    intersect=formulas.watertight,
    reintersect=formulas.smooth_hit,
    closest_point=point_triangle.closest_on_triangle,
    tags=("triangle_data", "normal"),
    fields={"triangle_barycentric_coord": "triangle_data", "triangle_front_facing": "triangle_data"},
    coverage={"gpu": Coverage(), "cpu": Coverage()},
    filter_code=_filter_code,
    doc="A triangle.",
    tag_docs={
        "triangle_data": "Adds ``triangle_barycentric_coord`` ``(..., 2)`` and ``triangle_front_facing`` to the result.",
    },
    geometry="TriangleGeometry",
    float_array="vertices",
)
