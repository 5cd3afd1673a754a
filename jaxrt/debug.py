"""Debugging views of acceleration structures: traversal heatmaps (like Xcode's acceleration-structure viewer).

Trace with ``rt.tags.stats`` and render how many nodes (or primitives) each ray visited; hot spots show where
the tree is poor (long thin triangles, overlapping boxes after a refit) or where the scene is dense.

Examples:
  >>> import numpy as np, jaxrt as rt
  >>> from jaxrt import debug
  >>> s = rt.build_primitive_structure(rt.TriangleGeometry([[0., 0, 0], [1, 0, 0], [0, 1, 0]]))
  >>> x, y = np.meshgrid(np.linspace(0, 1, 4), np.linspace(0, 1, 3))
  >>> origin = np.stack([x, y, np.ones_like(x)], -1).astype(np.float32)
  >>> rays = rt.Ray(origin, np.broadcast_to(np.float32([0, 0, -1]), origin.shape))
  >>> image, counts = debug.traversal_heatmap(s, rays)
  >>> image.shape, image.dtype.name
  ((3, 4, 3), 'uint8')
"""

from jaxrt._src.heatmap import COLORMAPS, colorbar, colormap, heatmap, traversal_heatmap, write_png

__all__ = ["COLORMAPS", "colorbar", "colormap", "heatmap", "traversal_heatmap", "write_png"]
