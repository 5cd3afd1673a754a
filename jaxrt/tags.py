"""Metal-style intersection tags: each asks for result fields (and only then compiles their work).

The tags of the scene (instancing, motion, primitive data, normals, counters) are defined here; each primitive
kind defines its own (``triangle_data``, ``curve_data``, ``sphere_data``) in its record of the kind registry,
which adds them to this module when ``jaxrt`` is imported.

Examples:
  >>> import jaxrt as rt
  >>> rt.Intersector(rt.tags.triangle_data).tags
  (Tag(name='triangle_data', value=None),)
"""

from __future__ import annotations

import dataclasses

__all__ = [
    "Tag",
    "instancing",
    "max_levels",
    "world_space_data",
    "primitive_motion",
    "instance_motion",
    "primitive_data",
    "user_instance_id",
    "stats",
    "normal",
]


@dataclasses.dataclass(frozen=True, order=True)
class Tag:
    """A static, hashable intersection tag."""

    name: str
    value: int | None = None


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
normal = Tag("normal")
"""Adds ``normal`` ``(..., 3)``: the unit world-space geometric normal of the hit surface.

Triangles give ``normalize(cross(v1 - v0, v2 - v0))`` (the geometric normal ``Ng`` of Metal and Embree,
not flipped towards the ray): with the winding convention of ``docs/design.md`` it points along the ray
(``dot(normal, direction) > 0``) when the triangle is seen clockwise, against it when counterclockwise; use
``rt.shading.face_forward`` for a normal facing the viewer. Round curves give the tube's outward surface
normal (end spheres: outward; end disks: the end tangent, out of the tube); flat curves, which face the ray,
the ribbon normal towards the ray origin (ray-facing end disks: ``-direction``). Spheres give the outward
normal, also where a ray from inside leaves the sphere. Bounding-box hits give
zeros: the surface is the intersection function's, unknown to the library. Misses give zeros (with
``type == IntersectionType.NONE``). Through instances, object-space normals are transformed by the inverse
transpose of the chain's object-to-world transform, then normalised (a mirroring instance keeps outward
normals outward). Differentiable like the other fields, holding the hit fixed; zero-area triangles give
zeros, never NaN.
"""
stats = Tag("stats")
"""Adds traversal counters: ``nodes_visited``, ``primitives_tested`` and ``stack_overflow``."""


def max_levels(n: int) -> Tag:
    """The deepest instance nesting the intersector handles (``n`` levels of instances above primitives)."""
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise ValueError(f"tags.max_levels: n must be a positive int, got {n!r}")
    return Tag("max_levels", n)


#: The names of every tag: those above, ``max_levels``, and the kinds' tags (:func:`define`).
KNOWN = frozenset(
    [
        "instancing",
        "max_levels",
        "world_space_data",
        "primitive_motion",
        "instance_motion",
        "primitive_data",
        "user_instance_id",
        "stats",
        "normal",
    ]
)
#: The docstrings of the kinds' tags, by name (:func:`define`).
KIND_TAG_DOCS: dict[str, str] = {}


def define(name: str, doc: str) -> Tag:
    """Define the tag ``name`` of a primitive kind in this module (the kind registry calls it for each kind's
    ``tag_docs`` at import): ``jaxrt.tags.<name>``, listed in ``__all__`` and :data:`KNOWN`."""
    global KNOWN
    tag = globals().get(name)
    if tag is None:
        tag = Tag(name)
        globals()[name] = tag
        __all__.append(name)
        KNOWN = KNOWN | {name}
    KIND_TAG_DOCS[name] = doc
    return tag
