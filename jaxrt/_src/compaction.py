"""Compaction: trim the padding of a built structure to the rows its tree uses (Metal's compaction).

A structure is padded to a power-of-two capacity ``C`` so that scenes of similar size share compiled code
(:func:`jaxrt._src.structures.capacity_bucket`). Once a structure is final, the padding is memory it never
reads. :func:`compact` returns the same tree in the smallest layout that holds it:

- the LBVH (``quality="fast"``) links only the real leaves ``0 .. n - 1`` (at least two), in internal nodes
  ``0 .. n - 2``; the rows past them are dropped, so the capacity becomes ``max(n, 2)``;
- the clustering tree (``quality="high"``) and the SAH tree (``"sah"``) hang the padding leaves under the root
  in a subtree of their own:
  node 0 joins the real tree (nodes ``1 .. n - 1``) and the padding subtree. The padding subtree is replaced by
  one padding leaf ``n`` (an empty box, as before), so the capacity becomes ``n + 1``.

Node boxes, leaf order and every kept row are copied unchanged, so a compacted structure traces bit for bit
as the original does (same distances, ids and barycentrics). The trade-off: its capacity is no longer a
power of two, so the first trace of a compacted structure compiles a traversal for its exact size rather
than reusing the one of its bucket.

Instance structures: their primitive structures are compacted; their own instance tables are kept as they
are (an instance tree links its padding leaves into the tree, and an instance table is small next to the
geometry below it). The root boxes the tables were built from do not change, since node 0 is kept as is.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt._src.instances import InstanceAccelerationStructure
from jaxrt._src.prepacked import with_kernel_layout
from jaxrt._src.structures import PrimitiveAccelerationStructure

__all__ = ["compact", "compact_capacity"]

_OWNER = "compact"


def _host(x: Any, name: str) -> np.ndarray:
    if isinstance(x, jax.core.Tracer):
        raise ValueError(
            f"{_OWNER}: {name} is traced; compaction reads the primitive count on the host, so call it outside "
            "jax.jit (the compacted sizes are static)"
        )
    return np.asarray(x)


def _references_within(children: np.ndarray, nodes: int, leaves: int) -> bool:
    """Every child of ``children`` is an internal node below ``nodes`` or a leaf below ``leaves``."""
    inner = children >= 0
    return bool(np.all(np.where(inner, children < nodes, -1 - children < leaves)))


def compact_capacity(structure: PrimitiveAccelerationStructure) -> tuple[int, bool]:
    """The capacity of the compacted structure, and whether the root's padding subtree becomes one leaf.

    Args:
      structure: a (concrete, unbatched) :class:`~jaxrt.PrimitiveAccelerationStructure`.

    Returns:
      ``(capacity, clustered)``: ``clustered`` is true for a clustering tree whose root holds the padding
      subtree (its second child then becomes padding leaf ``capacity - 1``).

    Raises:
      ValueError: a traced or batched structure, or a tree whose rows past the real leaves are referenced in
        a way neither build produces (naming the capacity and the primitive count).
    """
    leaf_geometry = _host(structure.leaf_geometry, "structure.leaf_geometry")
    if leaf_geometry.ndim != 1:
        raise ValueError(
            f"{_OWNER}: structure is batched (leaf_geometry has shape {leaf_geometry.shape}); compact one "
            "structure at a time"
        )
    capacity = structure.capacity
    n = int(np.sum(leaf_geometry >= 0))
    children = _host(structure.node_children, "structure.node_children")
    real = max(n, 2)
    if _references_within(children[: real - 1], real - 1, real):
        return real, False  # the LBVH (or a clustering tree without padding)
    if n + 1 <= capacity and n >= 1:
        root = children[0]
        real_root_ok = (root[0] == 1 and n >= 2) or (root[0] == -1 and n == 1)
        padding_root_ok = root[1] == n or root[1] == -1 - n
        lower = _host(structure.node_lower, "structure.node_lower")[0, 1]
        upper = _host(structure.node_upper, "structure.node_upper")[0, 1]
        padding_empty = bool(np.any(lower > upper))
        if real_root_ok and padding_root_ok and padding_empty and _references_within(children[1:n], n, n):
            return n + 1, True
    raise ValueError(
        f"{_OWNER}: the tree of this structure (capacity {capacity}, {n} primitives) references rows past its "
        "real leaves in a layout neither build produces; it cannot be compacted"
    )


def _trim(x: Any, rows: int) -> Any:
    return None if x is None else jax.tree_util.tree_map(lambda a: a[:rows], x)


def _trim_keys(x: jax.Array | None, rows: int) -> jax.Array | None:
    """Keyframe leaf arrays ``(K, C, ...)`` trimmed to ``rows`` leaves."""
    return None if x is None else x[:, :rows]


def _compact_primitive(structure: PrimitiveAccelerationStructure) -> PrimitiveAccelerationStructure:
    capacity, clustered = compact_capacity(structure)
    if capacity == structure.capacity:
        return structure
    nodes = capacity - 1
    node_children = structure.node_children[:nodes]
    node_range = structure.node_range[:nodes]
    if clustered:  # the root's padding subtree becomes the one padding leaf kept
        pad = capacity - 1
        node_children = node_children.at[0, 1].set(-1 - pad)
        node_range = node_range.at[0].set(jnp.asarray([0, pad], node_range.dtype))
    compacted = dataclasses.replace(
        structure,
        node_lower=structure.node_lower[:nodes],
        node_upper=structure.node_upper[:nodes],
        node_children=node_children,
        node_range=node_range,
        leaf_geometry=structure.leaf_geometry[:capacity],
        leaf_primitive=structure.leaf_primitive[:capacity],
        leaf_triangle=structure.leaf_triangle[:capacity],
        leaf_curve=_trim(structure.leaf_curve, capacity),
        leaf_curve_flags=_trim(structure.leaf_curve_flags, capacity),
        leaf_box=_trim(structure.leaf_box, capacity),
        leaf_primitive_data=_trim(structure.leaf_primitive_data, capacity),
        motion_triangle=_trim_keys(structure.motion_triangle, capacity),
        motion_curve=_trim_keys(structure.motion_curve, capacity),
        motion_box=_trim_keys(structure.motion_box, capacity),
        motion_node_lower=_trim_keys(structure.motion_node_lower, nodes),
        motion_node_upper=_trim_keys(structure.motion_node_upper, nodes),
    )
    # The kernel's packed rows, where the structure has them, packed again (the root's row may have changed).
    return with_kernel_layout(compacted, structure.kernel_layout is not None)


def compact(
    structure: PrimitiveAccelerationStructure | InstanceAccelerationStructure,
) -> PrimitiveAccelerationStructure | InstanceAccelerationStructure:
    """Trim a structure's padding to the rows its tree uses (Metal's acceleration-structure compaction).

    The compacted structure traces bit for bit as the original does (same distances, ids, barycentrics and
    primitive data) and refits the same way. Its capacity is the primitive count (at least 2) for the LBVH,
    and the primitive count plus one padding leaf for the clustering tree (``quality="high"``). Instance
    structures keep their instance tables and compact their primitive structures (see the module docstring).

    Trade-off: padding exists so that structures of similar size share compiled code; a compacted
    structure's capacity is exact, so its first trace may compile a new traversal. Compact structures that
    are kept (static scenery, saved files), not ones rebuilt every frame. Call it on the host, not in ``jit``.

    Args:
      structure: a :class:`~jaxrt.PrimitiveAccelerationStructure` or
        :class:`~jaxrt.InstanceAccelerationStructure`.

    Returns:
      A structure of the same type; :func:`~jaxrt.structure_sizes` gives its bytes.

    Raises:
      TypeError: ``structure`` is not an acceleration structure.
      ValueError: a traced or batched structure, or a tree layout neither build produces.

    Examples:
      >>> import numpy as np, jaxrt as rt
      >>> triangles = np.random.default_rng(0).normal(size=(5, 3, 3)).astype(np.float32)
      >>> structure = rt.build_primitive_structure(rt.TriangleGeometry(triangles.reshape(-1, 3)))
      >>> structure.capacity, rt.compact(structure).capacity
      (8, 5)
    """
    if isinstance(structure, PrimitiveAccelerationStructure):
        return _compact_primitive(structure)
    if isinstance(structure, InstanceAccelerationStructure):
        return dataclasses.replace(
            structure, primitive_structures=tuple(_compact_primitive(s) for s in structure.primitive_structures)
        )
    raise TypeError(
        f"{_OWNER}: structure must be a PrimitiveAccelerationStructure or an InstanceAccelerationStructure, "
        f"got {type(structure).__name__}"
    )
