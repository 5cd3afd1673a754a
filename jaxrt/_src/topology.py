"""Whether a triangle surface is closed: a host-side count of its boundary edges.

The inside tests (:func:`~jaxrt.contains`, the sign of :func:`~jaxrt.signed_distance`) read the generalized
winding number, which is an integer (1 inside, 0 outside) only for a closed, consistently oriented surface.
Across an open surface (a quad, a mesh with a hole) it varies smoothly, so a point is "inside" only where the
surface wraps around it by at least half: both sides of an open quad are outside. :func:`boundary_edge_count`
counts the directed edges that no edge of opposite direction matches (the boundary of an open surface, and
the edges between triangles of opposite orientation); :func:`is_closed` says whether there is none. The
point queries that read the inside warn once per structure when they find an open one.
"""

from __future__ import annotations

import warnings
import weakref
from typing import Any

import jax
import numpy as np

from jaxrt._src.kinds.registry import BOUNDING_BOX, TRIANGLE
from jaxrt._src.structures import PrimitiveAccelerationStructure

__all__ = ["boundary_edge_count", "is_closed", "warn_if_open"]


def _triangles_as_indices(surface: Any) -> np.ndarray | None:
    """``(T, 3)`` vertex indices of the surface's triangles (``None``: no triangles; boxes are closed)."""
    if isinstance(surface, PrimitiveAccelerationStructure):
        triangle_slots = [g for g, info in enumerate(surface.geometry_info) if TRIANGLE.holds(info)]
        if not triangle_slots:
            return None
        geometry = np.asarray(surface.leaf_geometry)
        rows = np.asarray(surface.leaf_triangle)[np.isin(geometry, triangle_slots)].reshape(-1, 3)
        # one vertex per position: triangles of a structure share vertices by their exact coordinates
        _, index = np.unique(rows, axis=0, return_inverse=True)
        return index.reshape(-1, 3)
    if hasattr(surface, "kind") and TRIANGLE.holds(surface):
        return np.asarray(surface.indices).reshape(-1, 3)
    if hasattr(surface, "kind") and BOUNDING_BOX.holds(surface):
        return None
    raise TypeError(
        "is_closed: expected a TriangleGeometry, MotionTriangleGeometry, BoundingBoxGeometry or "
        f"PrimitiveAccelerationStructure, got {type(surface).__name__}"
    )


def boundary_edge_count(surface: Any) -> int:
    """The number of directed edges of ``surface``'s triangles that no edge of opposite direction matches.

    0 for a closed, consistently oriented surface; an open quad has 4. Counted on the host (``O(T log T)``):
    geometries by their indices, structures by their vertices' exact positions.

    Args:
      surface: a triangle or bounding-box geometry, or a primitive structure (box primitives are closed).

    Returns:
      The count, an ``int``.
    """
    triangles = _triangles_as_indices(surface)
    if triangles is None or len(triangles) == 0:
        return 0
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    edges = edges[edges[:, 0] != edges[:, 1]]  # repeated vertices of a zero-area triangle
    forward = edges[:, 0] < edges[:, 1]
    key = np.sort(edges, axis=1)
    pairs, inverse = np.unique(key, axis=0, return_inverse=True)
    balance = np.zeros(len(pairs), np.int64)
    np.add.at(balance, inverse.reshape(-1), np.where(forward, 1, -1))
    return int(np.abs(balance).sum())


def is_closed(surface: Any) -> bool:
    """Whether ``surface`` is closed and consistently oriented: every triangle edge is matched by an edge of
    opposite direction (:func:`boundary_edge_count` is 0).

    Only then is the generalized winding number 1 inside and 0 outside, and :func:`~jaxrt.contains` and the
    sign of :func:`~jaxrt.signed_distance` mean inside and outside; on an open surface both sides read as
    outside away from where it wraps around.

    Args:
      surface: a triangle or bounding-box geometry, or a primitive structure (host-side: not inside ``jit``).

    Examples:
      >>> import jaxrt as rt
      >>> quad = rt.TriangleGeometry([[0., 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]])
      >>> rt.is_closed(quad), rt.boundary_edge_count(quad)
      (False, 4)
      >>> vertices = [[0., 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
      >>> rt.is_closed(rt.TriangleGeometry(vertices, [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))
      True
    """
    return boundary_edge_count(surface) == 0


_warned: dict[tuple[str, int], Any] = {}  # (function, id of a structure's leaf array) -> a weak reference to it


def warn_if_open(structure: Any, name: str) -> None:
    """Warn once per structure and function (outside ``jit``) that an open surface has no inside for ``name``."""
    leaves = structure.leaf_triangle
    if isinstance(leaves, jax.core.Tracer):
        return
    key = (name, id(leaves))
    seen = _warned.get(key)
    if seen is not None and seen() is leaves:
        return
    try:
        _warned[key] = weakref.ref(leaves)
    except TypeError:  # an array type without weak references: check every call
        pass
    count = boundary_edge_count(structure)
    if count:
        warnings.warn(
            f"{name}: the structure's triangles form an open surface ({count} boundary edges, rt.is_closed is "
            "False); its winding number is not 1 inside and 0 outside, so inside/outside (and the distance's "
            "sign) are meaningful only where the surface wraps around a point (docs/point_queries.md)",
            UserWarning,
            stacklevel=3,
        )
