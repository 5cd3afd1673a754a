"""The surface area heuristic (SAH) cost of a built tree: a measure of its quality for random rays.

MacDonald & Booth, "Heuristics for ray tracing using space subdivision", The Visual Computer 6(3), 1990: a
random ray that hits a node's parent box enters the node with a probability equal to the ratio of their
surface areas. The cost of a tree is then

    (sum of the areas of the internal nodes + sum of the areas of the leaves * primitives per leaf) / root area

with traversal and intersection costing 1 each, over the real primitives (padding boxes are empty: area 0).
It is the definition the GPU bench reports (``jaxrt.bench.gpu``). It is normalised by the root's area, so
trees over a deforming mesh compare frame to frame: a refit keeps the topology and lets its boxes grow and
overlap, so its cost drifts up from that of a rebuild.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["tree_cost"]


def _area(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    extent = np.where(lower <= upper, upper - lower, 0.0)
    return 2.0 * (extent[..., 0] * extent[..., 1] + extent[..., 1] * extent[..., 2] + extent[..., 2] * extent[..., 0])


def tree_cost(node_lower: Any, node_upper: Any, node_children: Any) -> float:
    """The SAH cost (see the module docstring) of a tree's node arrays, on the host in float64
    (:func:`jaxrt.sah_cost` for a structure).

    Raises:
      ValueError: batched arrays, or a root box that is empty or has no area.
    """
    lower = np.asarray(node_lower, np.float64)
    upper = np.asarray(node_upper, np.float64)
    children = np.asarray(node_children)
    if lower.ndim != 3:
        raise ValueError(f"sah_cost: structure is batched (node_lower has shape {lower.shape}); pass one structure")
    child_area = _area(lower, upper)  # (C-1, 2)
    root = float(_area(lower[0].min(axis=0), upper[0].max(axis=0)))
    if not root > 0.0:
        raise ValueError(f"sah_cost: the root box has area {root}; the cost is relative to it")
    # Every internal node but the root is the child of one node; leaves are children too.
    internal = child_area[children >= 0].sum() + root
    leaves = child_area[children < 0].sum()
    return float((internal + leaves) / root)
