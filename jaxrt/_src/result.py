"""The intersection result pytree, shaped by the intersector's tags."""

from __future__ import annotations

import enum
from collections.abc import Iterator, Mapping
from typing import Any

import jax

from jaxrt._src.kinds import registry

__all__ = ["IntersectionType", "IntersectionResult", "FIELD_TAGS"]


#: What a ray that hits nothing reports.
NONE_DOC = "The ray missed (or was disabled)."


def _intersection_type() -> type[enum.IntEnum]:
    """``IntersectionType``, one member per kind of the registry (its ``intersection_type`` and ``doc``)."""
    members = {"NONE": 0, **{k.name.upper(): k.intersection_type for k in registry.KINDS}}
    cls = enum.IntEnum("IntersectionType", members, module=__name__, qualname="IntersectionType")
    docs = {"NONE": NONE_DOC, **{k.name.upper(): k.doc for k in registry.KINDS}}
    cls.__doc__ = (
        "What a ray hit (Metal's ``intersection_type``): one member per primitive kind.\n\nMembers:\n"
        + "".join(f"  {name} ({members[name]}): {doc}\n" for name, doc in docs.items())
    )
    return cls


#: What a ray hit (Metal's ``intersection_type``): ``NONE`` and one member per primitive kind of the registry
#: (``TRIANGLE`` 1, ``BOUNDING_BOX`` 2, ``CURVE`` 3, ``SPHERE`` 4, ...).
IntersectionType = _intersection_type()


#: The tag that adds each optional result field (the kinds' own and the scene's,
#: :data:`jaxrt._src.kinds.registry.FIELD_TAGS`).
FIELD_TAGS = registry.FIELD_TAGS


@jax.tree_util.register_pytree_node_class
class IntersectionResult(Mapping):
    """Per-ray hit record; its fields depend on the intersector's tags.

    Always present: ``type`` (int32 :class:`IntersectionType`), ``distance`` (``inf`` on a miss),
    ``primitive_id`` and ``geometry_id`` (int32, ``-1`` on a miss). Tags add fields (see ``rt.tags``);
    asking for a field whose tag is absent raises ``AttributeError`` naming the tag. Fields of misses are
    zeros (``False`` for booleans). The result is a pytree and a read-only mapping of field names.
    """

    __slots__ = ("_fields",)

    def __init__(self, fields: Mapping[str, Any]):
        object.__setattr__(self, "_fields", dict(fields))

    def __getattr__(self, name: str) -> Any:
        fields = object.__getattribute__(self, "_fields")
        if name in fields:
            return fields[name]
        if name in FIELD_TAGS:
            raise AttributeError(
                f"IntersectionResult has no field {name!r}: add rt.tags.{FIELD_TAGS[name]} to the Intersector, "
                f"e.g. rt.Intersector(rt.tags.{FIELD_TAGS[name]})"
            )
        raise AttributeError(f"IntersectionResult has no field {name!r}")

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("IntersectionResult is immutable")

    def __getitem__(self, name: str) -> Any:
        fields = self._fields
        if name not in fields and name in FIELD_TAGS:
            raise KeyError(f"{name!r}: add rt.tags.{FIELD_TAGS[name]} to the Intersector")
        return fields[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._fields)

    def __len__(self) -> int:
        return len(self._fields)

    def __repr__(self) -> str:
        shapes = ", ".join(f"{k}={getattr(v, 'shape', '?')}" for k, v in self._fields.items())
        return f"IntersectionResult({shapes})"

    def tree_flatten(self):
        keys = tuple(self._fields)
        return tuple(self._fields[k] for k in keys), keys

    @classmethod
    def tree_unflatten(cls, keys, values):
        return cls(dict(zip(keys, values, strict=True)))
