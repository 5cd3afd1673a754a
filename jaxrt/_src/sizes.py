"""Structure sizes: the bytes of every array of a structure, before building it (Metal's size queries), and
the SAH cost of a built one (:func:`sah_cost`).

Metal asks ``accelerationStructureSizesWithDescriptor:`` for the bytes a build will need. Here the build is a
pure JAX function, so :func:`structure_sizes` runs it under :func:`jax.eval_shape`: the shapes and dtypes come
from the very function that builds, without computing or allocating anything, so they are exactly what the
build then allocates.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import numpy as np

from jaxrt._src.bvh.sah import tree_cost
from jaxrt._src.instances import InstanceAccelerationStructure, Instances, build_instance_structure
from jaxrt._src.prepacked import build_primitive_structure
from jaxrt._src.structures import PrimitiveAccelerationStructure

__all__ = ["StructureSizes", "structure_sizes", "array_bytes", "sah_cost"]

_OWNER = "structure_sizes"


@dataclasses.dataclass(frozen=True)
class StructureSizes:
    """The bytes of each array of a structure, by its pytree path (``jax.tree_util.keystr``).

    Attributes:
      arrays: ``{path: bytes}``, e.g. ``{".node_lower": 2232, ...}``; for an instance structure the paths
        start with ``.primitive_structures[i]`` or ``.instance_tables[j]``.
    """

    arrays: Mapping[str, int]

    @property
    def total(self) -> int:
        """Bytes of all arrays together."""
        return int(sum(self.arrays.values()))

    def __repr__(self) -> str:
        return f"StructureSizes(total={self.total:,} bytes in {len(self.arrays)} arrays)"


def array_bytes(tree: Any) -> StructureSizes:
    """The bytes of each array leaf of a pytree of arrays or :class:`jax.ShapeDtypeStruct`.

    Args:
      tree: a structure (built or abstract) or any pytree of arrays.

    Returns:
      A :class:`StructureSizes`.
    """
    leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
    return StructureSizes(
        {
            jax.tree_util.keystr(path): int(np.prod(leaf.shape, dtype=np.int64)) * np.dtype(leaf.dtype).itemsize
            for path, leaf in leaves
        }
    )


def structure_sizes(
    geometries_or_instances: Any,
    structures: Sequence[PrimitiveAccelerationStructure | InstanceAccelerationStructure] | None = None,
    *,
    capacity: int | None = None,
    quality: str = "fast",
    count: Any = None,
    motion: Any = None,
) -> StructureSizes:
    """Bytes of every array of the structure that a build would allocate, without building it.

    Args:
      geometries_or_instances: what :func:`~jaxrt.build_primitive_structure` takes (a geometry or a sequence
        of them), or an :class:`~jaxrt.Instances` (then ``structures`` is required), or an already built
        structure (its own arrays, e.g. after :func:`~jaxrt.compact`).
      structures: the structures the instances refer to (instance structures only). They may themselves be
        abstract (the result of ``jax.eval_shape`` of a build).
      capacity, quality: as for :func:`~jaxrt.build_primitive_structure`.
      count: as for :func:`~jaxrt.build_instance_structure`.
      motion: the :class:`~jaxrt.MotionSpec` of keyframed geometries or instances (as for the builds).

    Returns:
      A :class:`StructureSizes`; ``.total`` is the sum. For an instance structure it includes the structures
      below it, each distinct one once, as the built structure holds them.

    Raises:
      ValueError, TypeError: what the build would raise for the same arguments, or ``structures`` missing
        for instances (or given for geometries).

    Examples:
      >>> import jaxrt as rt
      >>> geometry = rt.TriangleGeometry([[0., 0, 0], [1, 0, 0], [0, 1, 0]])
      >>> rt.structure_sizes(geometry).total == rt.structure_sizes(rt.build_primitive_structure(geometry)).total
      True
      >>> rt.structure_sizes(geometry).arrays[".node_lower"]  # (C - 1, 2, 3) float32 with C = 2
      24
    """
    x = geometries_or_instances
    if isinstance(x, PrimitiveAccelerationStructure | InstanceAccelerationStructure):
        if structures is not None:
            raise ValueError(f"{_OWNER}: structures is only for Instances, got it with a built structure")
        return array_bytes(x)
    if isinstance(x, Instances):
        if structures is None:
            raise ValueError(f"{_OWNER}: Instances need the structures they refer to (structures=...)")
        structures = tuple(structures)
        if any(isinstance(a, jax.ShapeDtypeStruct) for a in jax.tree_util.tree_leaves(structures)):
            # Abstract structures are traced as arguments (each reference then counts as a distinct one).
            abstract = jax.eval_shape(
                lambda i, s: build_instance_structure(s, i, count=count, motion=motion), x, structures
            )
        else:  # closed over, so that structures shared by identity are stored (and counted) once
            abstract = jax.eval_shape(lambda i: build_instance_structure(structures, i, count=count, motion=motion), x)
        return array_bytes(abstract)
    if structures is not None:
        raise ValueError(f"{_OWNER}: structures is only for Instances, got geometries {type(x).__name__}")
    abstract = jax.eval_shape(
        lambda g: build_primitive_structure(g, capacity=capacity, quality=quality, motion=motion), x
    )
    return array_bytes(abstract)


def sah_cost(structure: Any) -> float:
    """The SAH cost of a structure's own tree (:mod:`jaxrt._src.bvh.sah`), on the host in float64.

    Args:
      structure: a :class:`~jaxrt.PrimitiveAccelerationStructure`, or an
        :class:`~jaxrt.InstanceAccelerationStructure` (the cost of its own tree over instance boxes).

    Returns:
      The cost, at least 1 for a non-empty tree (the root itself); padding and compaction do not change it.

    Raises:
      TypeError: ``structure`` is not an acceleration structure. ValueError: a batched structure, or one
        whose root box is empty or has no area (every primitive a point or a segment along one axis).

    Examples:
      >>> import jaxrt as rt
      >>> two = rt.TriangleGeometry([[0., 0, 0], [1, 0, 0], [0, 1, 0], [0., 0, 1], [1, 0, 1], [0, 1, 1]])
      >>> round(rt.sah_cost(rt.build_primitive_structure(two)), 3)  # (root 6 + two flat leaves of 2) / 6
      1.667
    """
    if isinstance(structure, InstanceAccelerationStructure):
        structure = structure.root
    elif not isinstance(structure, PrimitiveAccelerationStructure):
        raise TypeError(
            f"sah_cost: structure must be a PrimitiveAccelerationStructure or an InstanceAccelerationStructure, "
            f"got {type(structure).__name__}"
        )
    return tree_cost(structure.node_lower, structure.node_upper, structure.node_children)
