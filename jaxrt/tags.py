"""Metal-style intersection tags: each asks for result fields (and only then compiles their work).

Examples:
  >>> import jaxrt as rt
  >>> rt.Intersector(rt.tags.triangle_data).tags
  (Tag(name='triangle_data', value=None),)
"""

from __future__ import annotations

import dataclasses

__all__ = [
    "Tag",
    "triangle_data",
    "curve_data",
    "instancing",
    "max_levels",
    "world_space_data",
    "primitive_motion",
    "instance_motion",
    "primitive_data",
    "user_instance_id",
    "stats",
]


@dataclasses.dataclass(frozen=True, order=True)
class Tag:
    """A static, hashable intersection tag."""

    name: str
    value: int | None = None


triangle_data = Tag("triangle_data")
"""Adds ``triangle_barycentric_coord`` ``(..., 2)`` and ``triangle_front_facing`` to the result."""
curve_data = Tag("curve_data")
"""Adds ``curve_parameter`` (curve geometry)."""
instancing = Tag("instancing")
"""Allows instance structures; adds ``instance_id`` and ``user_instance_id`` ``(..., n)`` and ``instance_count``
(``n`` from :func:`max_levels`, 1 without it)."""
world_space_data = Tag("world_space_data")
"""Adds the object-to-world and world-to-object transforms ``(..., 3, 4)`` of the hit instance chain (needs
:data:`instancing`)."""
primitive_motion = Tag("primitive_motion")
"""Keyframe motion of primitives at each ray's time."""
instance_motion = Tag("instance_motion")
"""Keyframe motion of instance transforms at each ray's time."""
primitive_data = Tag("primitive_data")
"""Adds the hit primitive's user data."""
user_instance_id = Tag("user_instance_id")
"""Metal's tag for the user ids of the hit instance chain; ``instancing`` already adds ``user_instance_id``,
so this one only requires :data:`instancing`."""
stats = Tag("stats")
"""Adds traversal counters: ``nodes_visited``, ``primitives_tested`` and ``stack_overflow``."""


def max_levels(n: int) -> Tag:
    """The deepest instance nesting the intersector handles (``n`` levels of instances above primitives)."""
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise ValueError(f"tags.max_levels: n must be a positive int, got {n!r}")
    return Tag("max_levels", n)


KNOWN = frozenset(
    [
        "triangle_data",
        "curve_data",
        "instancing",
        "max_levels",
        "world_space_data",
        "primitive_motion",
        "instance_motion",
        "primitive_data",
        "user_instance_id",
        "stats",
    ]
)
