"""The list of primitive kinds, and what follows from it: each compiled traversal's coverage, the result tags
and fields, and the kind of a geometry.

Adding a kind: write its module (a :class:`~jaxrt._src.kinds.kind.Kind` with its leaf layout table, bounds,
tests, tags, coverage, its ``rt.IntersectionType`` member and tags, the build's geometry protocol, its analytic
row for the compiled loops, and the hooks the leaf tests, fields, point queries and checks call) and add it to
:data:`KINDS` (docs/design.md, "Kinds and layers"). The public enum ``rt.IntersectionType`` and the kinds' tags
in ``rt.tags`` are built from this list.

The coverage rule (:func:`declines`) is the one place that decides which traversal runs a scene: the portable
traversal traces every kind; a compiled traversal (:data:`BACKENDS`) traces a scene when every kind present
is covered there (:class:`~jaxrt._src.kinds.kind.Coverage`) and every decision that needs JAX (user
intersection functions, filters) can be handed over in candidate waves.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from jaxrt import tags as tag_module
from jaxrt._src.kinds.bounding_box import BOUNDING_BOX
from jaxrt._src.kinds.curve import CURVE
from jaxrt._src.kinds.kind import Coverage, Kind
from jaxrt._src.kinds.sphere import SPHERE
from jaxrt._src.kinds.triangle import TRIANGLE

__all__ = [
    "BACKENDS",
    "BOUNDING_BOX",
    "CURVE",
    "FIELD_TAGS",
    "KINDS",
    "RESULT_TAGS",
    "SCENE_FIELDS",
    "SPHERE",
    "TRIANGLE",
    "Backend",
    "declines",
    "kind",
    "needs_jax",
    "present",
    "waves_cover",
]

#: Every primitive kind, in the order of ``rt.IntersectionType``.
KINDS: tuple[Kind, ...] = (TRIANGLE, BOUNDING_BOX, CURVE, SPHERE)

_BY_NAME = {k.name: k for k in KINDS}

# The kinds' own tags join the scene's in ``rt.tags`` (the tag vocabulary, the bottom layer, imports no kind).
for _kind in KINDS:
    for _name, _doc in _kind.tag_docs.items():
        tag_module.define(_name, _doc)


@dataclasses.dataclass(frozen=True)
class Backend:
    """What a compiled traversal covers beyond its kinds.

    Attributes:
      name: how messages name it.
      motion: keyframe motion at each ray's time (primitive motion in a primitive structure at least).
      waves: candidate waves: JAX takes the decisions of user code between the traversal's turns.
      instanced_motion: keyframe motion in instance structures too (moving instances, or moving primitives
        below instances).
    """

    name: str
    motion: bool
    waves: bool
    instanced_motion: bool = True


#: The compiled traversals: the GPU kernel (:mod:`jaxrt._src.traversal.gpu`) and the CPU traversal
#: (:mod:`jaxrt._src.traversal.cpu`).
BACKENDS = {
    "gpu": Backend("GPU kernel", motion=True, waves=True),
    "cpu": Backend("CPU traversal", motion=True, waves=False, instanced_motion=False),
}

#: Result fields no kind owns, with the tag that asks for each (the kinds' own follow from :data:`KINDS`).
SCENE_FIELDS = {
    "instance_id": "instancing",
    "instance_count": "instancing",
    "user_instance_id": "instancing",
    "object_to_world_transform": "world_space_data",
    "world_to_object_transform": "world_space_data",
    "time": "primitive_motion",
    "primitive_data": "primitive_data",
    "nodes_visited": "stats",
    "primitives_tested": "stats",
    "stack_overflow": "stats",
    "normal": "normal",
}
#: Tags that ask for no field of their own (they allow a kind of scene or set a static count).
_SCENE_TAGS = ("max_levels", "user_instance_id", "instance_motion")

#: The tag that adds each optional result field.
FIELD_TAGS = {**{f: t for k in KINDS for f, t in k.fields.items()}, **SCENE_FIELDS}
#: Every intersector tag. Each backend covers them all: a traversal returns the leaf and the instance chain, and
#: the result fields of every tag are computed from them in JAX (:mod:`jaxrt._src.fields`).
RESULT_TAGS = frozenset({t for k in KINDS for t in k.tags} | set(FIELD_TAGS.values()) | set(_SCENE_TAGS))


def kind(name: str) -> Kind:
    """The kind called ``name`` (``GeometryInfo.kind``); ``ValueError`` for an unknown name."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise ValueError(f"unknown geometry kind {name!r}; kinds: {sorted(_BY_NAME)}") from None


def present(geometry_info: tuple) -> tuple[Kind, ...]:
    """The kinds of these geometries (``GeometryInfo`` records or geometries), in :data:`KINDS` order."""
    names = {g.kind for g in geometry_info}
    return tuple(k for k in KINDS if k.name in names)


def _of(kind: Kind, geometry_info: tuple) -> tuple:
    return tuple(g for g in geometry_info if kind.holds(g))


def _moving(geometry_info: tuple, motion: bool) -> bool:
    return bool(motion) or any(g.motion for g in geometry_info)


def waves_cover(geometry_info: tuple, backend: str = "gpu", *, motion: bool = False, levels: int = 0) -> bool:
    """Whether ``backend`` lists candidates in waves for a scene of these geometries: a static (no keyframe
    motion, ``motion`` nor any geometry's) primitive structure (``levels == 0``) whose every kind waves list."""
    if not BACKENDS[backend].waves or levels or _moving(geometry_info, motion):
        return False
    return all(k.coverage[backend].waves for k in present(geometry_info))


def _waves_where(backend: str) -> str:
    """Where candidate waves do not reach, for messages."""
    if not BACKENDS[backend].waves:
        return ""
    listed = [k.plural for k in KINDS if not k.coverage[backend].waves]
    return " below instances, with keyframe motion" + "".join(f" or with {p}" for p in listed)


def needs_jax(intersector: Any, geometry_info: tuple, *, filter_decided: bool = False) -> bool:
    """Whether tracing these geometries with ``intersector`` calls user code per candidate: a user
    intersection function or (unless ``filter_decided``: decided per primitive) a filter."""
    for k in present(geometry_info):
        mine = _of(k, geometry_info)
        if k.function_code is not None and k.function_code(intersector, mine, "", ""):
            return True
        if not filter_decided and k.filter_code is not None and k.filter_code(intersector, mine, "", ""):
            return True
    return False


def declines(
    intersector: Any, geometry_info: tuple, backend: str = "gpu", motion: bool = False, levels: int = 0
) -> str | None:
    """Why the compiled traversal ``backend`` does not cover a scene of these geometries with this
    intersector (``None``: it does); ``motion``: the scene has keyframe motion (primitive motion is also read
    from the geometries); ``levels``: its instance levels.

    Derived from the kinds present: each one's :class:`~jaxrt._src.kinds.kind.Coverage` on ``backend``, its
    decisions that need JAX (handed over in candidate waves where :func:`waves_cover`), and the backend's own
    :class:`Backend` facts.
    """
    target = BACKENDS[backend]
    name = target.name
    kinds = present(geometry_info)
    moving = _moving(geometry_info, motion)
    for k in kinds:
        cover: Coverage = k.coverage[backend]
        if not cover.traced:
            return f"{k.plural} {k.be} not covered by the {name}"
        if levels and not cover.instanced:
            return f"{k.plural} below instances {k.be} not covered by the {name}"
        if moving and not cover.motion:
            return f"{k.plural} in a structure with keyframe motion {k.be} not covered by the {name}"
        others = [o for o in kinds if o is not k and o is not TRIANGLE]
        if cover.alone and others:
            return f"{k.plural} and {others[0].plural} in one structure are not covered by the {name}"
    in_waves = waves_cover(geometry_info, backend, motion=motion, levels=levels)
    where = _waves_where(backend)
    for k in kinds:
        if k.declines is not None and (reason := k.declines(intersector, _of(k, geometry_info), name)):
            return reason
    if not in_waves:  # intersection functions first, then filters
        for code in ("function_code", "filter_code"):
            for k in kinds:
                decide = getattr(k, code)
                if decide is not None and (reason := decide(intersector, _of(k, geometry_info), name, where)):
                    return reason
    if moving and not target.motion:
        return f"keyframe motion is not covered by the {name}"
    if moving and levels and not target.instanced_motion:
        return f"keyframe motion in instance structures is not covered by the {name}"
    return None
