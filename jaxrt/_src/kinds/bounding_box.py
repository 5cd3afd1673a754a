"""Bounding boxes (``rt.BoundingBoxGeometry``, ``rt.MotionBoundingBoxGeometry``), with the built-in analytic
shapes (``rt.intersection_functions.sphere``, ``disk``, ``capped_cylinder``).

Leaf layout (``C`` leaf slots; ``K`` keyframes with keyframe motion):

====================  ================  =========  ==================================================================
array                 per leaf          fill       contents
====================  ================  =========  ==================================================================
``leaf_box``          (2, 3) float      empty box  lower and upper corner of the box primitive
``motion_box``        (K, 2, 3) float   empty box  ``leaf_box`` at each keyframe
====================  ================  =========  ==================================================================

Bounds: the box itself. Intersection: the conservative slab test (:func:`jaxrt._src.primitives.box.ray_box`)
decides which boxes a ray enters; the hit is the geometry's intersection function's. The built-in functions
(:mod:`jaxrt._src.primitives.analytic`) are recognised by identity and traced by the compiled traversals;
re-intersection calls the function again, differentiably. Point queries take the solid box
(:func:`jaxrt._src.primitives.point_triangle.closest_on_box`). Decisions that need JAX: user intersection
functions.
"""

from __future__ import annotations

from typing import Any

import jax

from jaxrt._src.kinds.kind import Coverage, Kind, LeafArray
from jaxrt._src.primitives import analytic, box, point_triangle

__all__ = ["BOUNDING_BOX", "bounds", "builtin"]

#: What the compiled traversals trace of intersection functions (for messages).
_BUILTIN = "rt.intersection_functions.sphere, disk and capped_cylinder"


def bounds(row: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The box ``(lower, upper)`` of box rows ``(..., 2, 3)``."""
    return row[..., 0, :], row[..., 1, :]


def builtin(fn: Any) -> bool:
    """Whether ``fn`` is one of the built-in analytic shapes (by identity), which compiled traversals trace."""
    return bool(analytic.shape_code(fn))


def _user(intersector: Any) -> list[str]:
    functions = intersector.intersection_functions or ()
    return [f"geometry {index}: {getattr(fn, '__name__', repr(fn))}" for index, fn in functions if not builtin(fn)]


def _function_code(intersector: Any, infos: tuple, traversal: str, where: str) -> str | None:
    user = _user(intersector)
    if not user:
        return None
    return (
        f"bounding-box geometry with user intersection functions ({', '.join(user)}){where} is not covered by the "
        f"{traversal} (it traces {_BUILTIN})"
    )


def _declines(intersector: Any, infos: tuple, traversal: str) -> str | None:
    if intersector.intersection_functions:
        return None
    return (
        f"bounding-box geometry without intersection functions is not covered by the {traversal} (it traces {_BUILTIN})"
    )


BOUNDING_BOX = Kind(
    name="bounding_box",
    plural="bounding-box geometry",
    be="is",
    intersection_type=2,
    leaf_arrays=(LeafArray("leaf_box", (2, 3), "float", "empty box", "motion_box", "lower and upper corner"),),
    bounds=bounds,
    intersect=box.ray_box,
    reintersect=None,  # the geometry's intersection function, called again differentiably
    closest_point=point_triangle.closest_on_box,
    tags=(),
    fields={},
    coverage={"gpu": Coverage(motion=False), "cpu": Coverage(motion=False)},
    function_code=_function_code,
    declines=_declines,
    doc="A bounding-box primitive, accepted by its intersection function.",
    geometry="BoundingBoxGeometry",
    float_array="lower",
)
